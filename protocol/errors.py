"""Error tree of the protocol package (imports nothing from host or device_runtime).

Use these for bad bytes or a misbehaving peer; use ``ValueError``/``TypeError``
when our own code passes a bad argument. Messages start with the operation
("decode scores: ...") and show both sides of a mismatch.
"""

from __future__ import annotations

__all__ = [
    "AuthenticationError",
    "BadCRC",
    "BadCobs",
    "BadHeader",
    "FrameTooLarge",
    "FramingError",
    "ImageFormatError",
    "LimitExceeded",
    "MalformedMessage",
    "NotAuthenticated",
    "ProtocolError",
    "RemoteAuthFailed",
    "RemoteBadOffset",
    "RemoteBadState",
    "RemoteBusy",
    "RemoteDigestMismatch",
    "RemoteError",
    "RemoteFlashFailed",
    "RemoteInternal",
    "RemoteLimitExceeded",
    "RemoteMalformed",
    "RemoteNoImage",
    "RemoteNotAuthenticated",
    "RemoteReplayed",
    "RemoteRollbackRefused",
    "RemoteTagMismatch",
    "RemoteTooLargeForFlash",
    "RemoteTooLargeForRam",
    "RemoteUnknownMessage",
    "RemoteUnsupported",
    "RemoteUnsupportedFormat",
    "RemoteUnsupportedVersion",
    "ReplayError",
    "TransportClosed",
    "TransportError",
    "TransportTimeout",
    "WrongKey",
]


class ProtocolError(Exception):
    """Base class of every protocol-level error."""


class FramingError(ProtocolError):
    """A frame could not be decoded (bad COBS, short header, ...)."""


class BadCRC(FramingError):
    """A frame's CRC-32 does not match its contents."""


class FrameTooLarge(FramingError):
    """A frame exceeds the negotiated maximum frame size."""


class BadCobs(FramingError):
    """A frame between two 0x00 delimiters is not valid COBS."""


class BadHeader(FramingError):
    """A frame is too short, or its header has an unknown version, reserved flag bits,
    an unknown channel or kind, or a body length that disagrees with the frame."""


class MalformedMessage(ProtocolError):
    """A CBOR body does not describe a valid message."""


class LimitExceeded(ProtocolError):
    """A size or count exceeds a declared limit (frame, section, decompressed size)."""


class AuthenticationError(ProtocolError):
    """An HMAC tag or session authentication failed."""


class NotAuthenticated(AuthenticationError):
    """A request that must be authenticated (session tag, completed AUTH) was not."""


class ReplayError(AuthenticationError):
    """A session counter is not above the last one accepted (a replayed or stale frame)."""


class TransportError(ProtocolError):
    """A transport could not be opened or failed while in use."""


class TransportTimeout(TransportError):
    """A write could not complete within its timeout (the peer is not reading)."""


class TransportClosed(TransportError):
    """The connection or line is gone (peer closed, socket reset, line cut)."""


class ImageFormatError(ProtocolError):
    """An eigenspace image (.ecs) is malformed, truncated or fails its digest."""


class RemoteError(ProtocolError):
    """The peer answered with an ERROR message."""

    def __init__(self, code: int, message: str, *, name: str | None = None) -> None:
        self.code = code
        self.name = name
        label = f"{name} ({code})" if name else str(code)
        super().__init__(f"device error {label}: {message}")


# One class per protocol.messages.ErrorCode (the table is ERROR_CLASSES there).
# Each also derives from the local family it belongs to, so ``except
# AuthenticationError`` catches a local tag failure and the device's AUTH_FAILED.


class RemoteUnknownMessage(RemoteError):
    """UNKNOWN_MESSAGE: the peer does not know a message type we sent."""


class RemoteMalformed(RemoteError, MalformedMessage):
    """MALFORMED: the peer could not decode a message we sent."""


class RemoteUnsupportedVersion(RemoteError):
    """UNSUPPORTED_VERSION: no protocol version in common."""


class RemoteNotAuthenticated(RemoteError, AuthenticationError):
    """NOT_AUTHENTICATED: the request needs a completed AUTH exchange or a session tag."""


class RemoteAuthFailed(RemoteError, AuthenticationError):
    """AUTH_FAILED: our proof or session tag did not verify (wrong key?)."""


class WrongKey(RemoteAuthFailed):
    """The device refused our AUTH proof: the host's key is not the device's.

    Raised by the host's session in place of the device's AUTH_FAILED answer to
    AUTH_CHALLENGE, with a message in plain words (the device's own is kept as ``detail``).
    """

    def __init__(self, message: str, *, detail: str = "") -> None:
        ProtocolError.__init__(self, message)
        self.code, self.name, self.detail = 5, "AUTH_FAILED", detail


class RemoteReplayed(RemoteError, ReplayError):
    """REPLAYED: the session counter was not above the last one accepted."""


class RemoteBadOffset(RemoteError):
    """BAD_OFFSET: a chunk offset outside the transfer or its window."""


class RemoteDigestMismatch(RemoteError, ImageFormatError):
    """DIGEST_MISMATCH: the received image does not hash to the announced SHA-256."""


class RemoteTagMismatch(RemoteError, AuthenticationError):
    """TAG_MISMATCH: the image's HMAC tag does not verify with the device key."""


class RemoteTooLargeForFlash(RemoteError, LimitExceeded):
    """TOO_LARGE_FOR_FLASH: the image exceeds the slot size."""


class RemoteTooLargeForRam(RemoteError, LimitExceeded):
    """TOO_LARGE_FOR_RAM: the eigenspace would not fit the device's RAM budget."""


class RemoteUnsupportedFormat(RemoteError, ImageFormatError):
    """UNSUPPORTED_FORMAT: the device cannot read this image format version."""


class RemoteRollbackRefused(RemoteError):
    """ROLLBACK_REFUSED: the image generation is older than the installed one (use force)."""


class RemoteNoImage(RemoteError):
    """NO_IMAGE: no valid image in the slot or no transfer in progress."""


class RemoteBusy(RemoteError):
    """BUSY: the device is busy with another operation; retry later."""


class RemoteInternal(RemoteError):
    """INTERNAL: the peer hit a bug or an unexpected condition."""


class RemoteLimitExceeded(RemoteError, LimitExceeded):
    """LIMIT_EXCEEDED: a size or count over a limit the peer declared."""


class RemoteBadState(RemoteError):
    """BAD_STATE: the request is not valid now (e.g. commit before verify)."""


class RemoteFlashFailed(RemoteError):
    """FLASH_FAILED: the device could not read or write its flash."""


class RemoteUnsupported(RemoteError):
    """UNSUPPORTED: a valid request the device does not support (a baud, a slot action)."""
