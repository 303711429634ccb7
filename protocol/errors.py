"""Error tree of the protocol package (imports nothing from host or device_runtime).

Use these for bad bytes or a misbehaving peer; use ``ValueError``/``TypeError``
when our own code passes a bad argument. Messages start with the operation
("decode scores: ...") and show both sides of a mismatch.
"""

from __future__ import annotations

__all__ = [
    "ProtocolError",
    "FramingError",
    "BadCRC",
    "FrameTooLarge",
    "MalformedMessage",
    "LimitExceeded",
    "AuthenticationError",
    "TransportError",
    "ImageFormatError",
    "RemoteError",
]


class ProtocolError(Exception):
    """Base class of every protocol-level error."""


class FramingError(ProtocolError):
    """A frame could not be decoded (bad COBS, short header, ...)."""


class BadCRC(FramingError):
    """A frame's CRC-32 does not match its contents."""


class FrameTooLarge(FramingError):
    """A frame exceeds the negotiated maximum frame size."""


class MalformedMessage(ProtocolError):
    """A CBOR body does not describe a valid message."""


class LimitExceeded(ProtocolError):
    """A size or count exceeds a declared limit (frame, section, decompressed size)."""


class AuthenticationError(ProtocolError):
    """An HMAC tag or session authentication failed."""


class TransportError(ProtocolError):
    """A transport could not be opened or failed while in use."""


class ImageFormatError(ProtocolError):
    """An eigenspace image (.ecs) is malformed, truncated or fails its digest."""


class RemoteError(ProtocolError):
    """The peer answered with an ERROR message."""

    def __init__(self, code: int, message: str, *, name: str | None = None) -> None:
        self.code = code
        self.name = name
        label = f"{name} ({code})" if name else str(code)
        super().__init__(f"device error {label}: {message}")
