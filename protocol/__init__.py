"""eigencast protocol: framing, messages, link engine, transports, image and score formats.

Shared by host and device. Imports only the standard library, numpy, pyserial,
cbor2 and zstandard; never ``host`` or ``device_runtime``.
"""
