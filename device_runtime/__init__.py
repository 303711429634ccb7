"""eigencast device runtime: flash store, reconstruction, display and runtime loop.

Pure numpy plus pyserial, cbor2, zstandard and (display only, lazily) pygame.
Never imports ``host``.
"""
