"""Protocol messages: one frozen dataclass per message, CBOR bodies with integer keys.

A message class is a declaration: a ``ClassVar`` ``TYPE`` (:class:`MessageType`),
``CHANNEL`` and ``KIND`` (from :mod:`protocol.framing`), the reply it elicits
(``REPLY``), and typed fields declared with :func:`~protocol.records.wire` (CBOR key and
limits). The machinery under them is :mod:`protocol.records`: :class:`Record` checks
and normalises field values on construction and encodes/decodes canonical CBOR maps
(unknown keys ignored, missing or wrong ones :class:`~protocol.errors.MalformedMessage`),
and :func:`scan_cbor` bounds a body before cbor2 sees a byte.

The message type lives in the frame header; :func:`decode_message` maps it to a
class, or returns :class:`UnknownMessage` so a receiver can answer
``ERROR(UNKNOWN_MESSAGE)`` instead of failing.

Mutating requests (``SIGNED = True``) carry a session counter (key 22) and a
session tag (key 23), SCORES and IMAGE_CHUNK (``TAGGED``) an event tag; the maths
(``sign``, ``verify``, ``tag_event``, ``derive_session_key``) is :mod:`protocol.auth`.
The full wire specification is docs/protocol.md. The module stays one file: it is the
catalogue of every message's declaration, which the golden lines and docs/protocol.md are
checked against as one list.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, unique
from typing import Any, ClassVar

import cbor2

from protocol import errors
from protocol.errors import (
    AuthenticationError,
    LimitExceeded,
    MalformedMessage,
    NotAuthenticated,
    RemoteError,
    ReplayError,
)
from protocol.framing import Channel, Flags, Frame, Kind, encode_frame
from protocol.image import MAX_LOOKS
from protocol.records import MAX_DEPTH, U8, U16, U32, U64, Detail, Record, scan_cbor, wire

__all__ = [
    "BASELINE_MAX_FRAME_BYTES",
    "DIGEST_BYTES",
    "ERROR_CLASSES",
    "EVENT_TAG_BYTES",
    "EVENT_TAG_OVERHEAD_BYTES",
    "KEY_BYTES",
    "MAX_DEPTH",
    "MESSAGE_CLASSES",
    "NONCE_BYTES",
    "PROTOCOL_VERSION",
    "SESSION_COUNTER_KEY",
    "SESSION_TAG_KEY",
    "TAG_BYTES",
    "AuthChallenge",
    "AuthResponse",
    "Bye",
    "Error",
    "ErrorCode",
    "Hello",
    "HelloReply",
    "ImageAbort",
    "ImageAck",
    "ImageBegin",
    "ImageChunk",
    "ImageCommit",
    "ImageStatus",
    "ImageStatusReply",
    "ImageVerify",
    "ImageVerifyReply",
    "KeyframeRequest",
    "Message",
    "MessageType",
    "Notice",
    "Ok",
    "Ping",
    "Pong",
    "Record",
    "Reset",
    "Scores",
    "SetBaud",
    "SignedRequest",
    "SlotAction",
    "SlotInfo",
    "SlotSet",
    "SlotState",
    "SlotStatus",
    "TaggedEvent",
    "UnknownMessage",
    "ViewRequest",
    "decode_message",
    "encode_message",
    "error_code_for",
    "scan_cbor",
    "wire",
]

PROTOCOL_VERSION = 2
"""Message-set version this code speaks (negotiated in HELLO; frame version is separate).
2: SCORES and IMAGE_CHUNK carry an event tag on a keyed device, HELLO_REPLY hides slots and
budgets before AUTH and AUTH_RESPONSE carries them (docs/protocol.md, "Versioning")."""

NONCE_BYTES = 16
"""Length of the host and device nonces."""

KEY_BYTES = 32
"""Length of a device key and a session key."""

DIGEST_BYTES = 32
"""Length of a SHA-256 digest."""

TAG_BYTES = 32
"""Length of an HMAC-SHA256 tag."""

BASELINE_MAX_FRAME_BYTES = 1024
"""Every implementation accepts frames this large; both sides stay within it until
HELLO_REPLY has declared the device's ``max_frame_bytes``."""

SESSION_COUNTER_KEY = 22
"""CBOR key of the session counter in every signed request."""

SESSION_TAG_KEY = 23
"""CBOR key of the session tag in every signed request."""

EVENT_TAG_BYTES = 16
"""Length of the truncated HMAC-SHA256 tag of a tagged event (SCORES, IMAGE_CHUNK)."""

EVENT_TAG_OVERHEAD_BYTES = 1 + 9 + 1 + 1 + EVENT_TAG_BYTES
"""Most body bytes a tag adds to an event: key 22 + a u64 counter, key 23 + bytes header + tag."""

MAX_PAYLOAD_BYTES = 1 << 24
"""Upper bound on any one byte-string field; the frame size is the real limit."""


# --------------------------------------------------------------------------- enums


@unique
class MessageType(IntEnum):
    """Message type byte (frame header offset 3). Values are part of the wire format."""

    HELLO = 0x01
    HELLO_REPLY = 0x02
    AUTH_CHALLENGE = 0x03
    AUTH_RESPONSE = 0x04
    PING = 0x05
    PONG = 0x06
    ERROR = 0x07
    OK = 0x08
    BYE = 0x09
    SET_BAUD = 0x0A
    RESET = 0x0B
    SLOT_SET = 0x0C
    SLOT_STATUS = 0x0D
    IMAGE_BEGIN = 0x10
    IMAGE_STATUS = 0x11
    IMAGE_STATUS_REPLY = 0x12
    IMAGE_CHUNK = 0x13
    IMAGE_ACK = 0x14
    IMAGE_VERIFY = 0x15
    IMAGE_VERIFY_REPLY = 0x16
    IMAGE_COMMIT = 0x17
    IMAGE_ABORT = 0x18
    SCORES = 0x20
    VIEW_REQUEST = 0x21
    KEYFRAME_REQUEST = 0x22
    NOTICE = 0x30


@unique
class ErrorCode(IntEnum):
    """Codes carried by ERROR (key 0). Each maps to one RemoteError subclass (ERROR_CLASSES)."""

    UNKNOWN_MESSAGE = 1
    """The message type is unknown and the frame had MUST_UNDERSTAND set."""
    MALFORMED = 2
    """The body failed to decode (bad CBOR, missing key, wrong type, over a field limit),
    or channel/kind disagree with the message type."""
    UNSUPPORTED_VERSION = 3
    """No protocol version in common (HELLO)."""
    NOT_AUTHENTICATED = 4
    """The request needs a completed AUTH exchange or a session tag."""
    AUTH_FAILED = 5
    """An auth proof or session tag did not verify."""
    REPLAYED = 6
    """A session counter was not above the last accepted one."""
    BAD_OFFSET = 7
    """A chunk offset outside the transfer or the receive window."""
    DIGEST_MISMATCH = 8
    """The received image does not hash to the announced SHA-256."""
    TAG_MISMATCH = 9
    """The image's HMAC tag does not verify with the device key."""
    TOO_LARGE_FOR_FLASH = 10
    """The image exceeds the slot size."""
    TOO_LARGE_FOR_RAM = 11
    """The eigenspace would not fit the device's RAM budget."""
    UNSUPPORTED_FORMAT = 12
    """The image format version is not one the device reads."""
    ROLLBACK_REFUSED = 13
    """The image generation is older than the installed one and force was not set."""
    NO_IMAGE = 14
    """No valid image in the slot, or no transfer in progress for that digest."""
    BUSY = 15
    """Another operation is in progress; retry later."""
    INTERNAL = 16
    """A bug or unexpected condition in the peer."""
    LIMIT_EXCEEDED = 17
    """A size or count over a declared limit (frame, window, decompressed size)."""
    BAD_STATE = 18
    """The request is not valid in the current state (e.g. commit before verify)."""
    FLASH_FAILED = 19
    """Reading or writing flash failed."""
    UNSUPPORTED = 20
    """A well-formed request the device does not support (a baud rate, a slot action)."""


ERROR_CLASSES: dict[ErrorCode, type[RemoteError]] = {
    ErrorCode.UNKNOWN_MESSAGE: errors.RemoteUnknownMessage,
    ErrorCode.MALFORMED: errors.RemoteMalformed,
    ErrorCode.UNSUPPORTED_VERSION: errors.RemoteUnsupportedVersion,
    ErrorCode.NOT_AUTHENTICATED: errors.RemoteNotAuthenticated,
    ErrorCode.AUTH_FAILED: errors.RemoteAuthFailed,
    ErrorCode.REPLAYED: errors.RemoteReplayed,
    ErrorCode.BAD_OFFSET: errors.RemoteBadOffset,
    ErrorCode.DIGEST_MISMATCH: errors.RemoteDigestMismatch,
    ErrorCode.TAG_MISMATCH: errors.RemoteTagMismatch,
    ErrorCode.TOO_LARGE_FOR_FLASH: errors.RemoteTooLargeForFlash,
    ErrorCode.TOO_LARGE_FOR_RAM: errors.RemoteTooLargeForRam,
    ErrorCode.UNSUPPORTED_FORMAT: errors.RemoteUnsupportedFormat,
    ErrorCode.ROLLBACK_REFUSED: errors.RemoteRollbackRefused,
    ErrorCode.NO_IMAGE: errors.RemoteNoImage,
    ErrorCode.BUSY: errors.RemoteBusy,
    ErrorCode.INTERNAL: errors.RemoteInternal,
    ErrorCode.LIMIT_EXCEEDED: errors.RemoteLimitExceeded,
    ErrorCode.BAD_STATE: errors.RemoteBadState,
    ErrorCode.FLASH_FAILED: errors.RemoteFlashFailed,
    ErrorCode.UNSUPPORTED: errors.RemoteUnsupported,
}
"""ErrorCode -> the ProtocolError subclass the host raises for it (see Error.to_exception)."""


@unique
class SlotState(IntEnum):
    """State of one flash slot (as the flash store records it)."""

    EMPTY = 0
    """No image."""
    TEST = 1
    """Committed for a test boot, not yet confirmed (reverts at the next boot)."""
    CONFIRMED = 2
    """A confirmed, verified image."""
    BAD = 3
    """Holds bytes that failed verification."""


@unique
class SlotAction(IntEnum):
    """What SLOT_SET does."""

    ACTIVATE = 0
    """Make ``slot`` active for a test boot (needs ``force`` for an older generation)."""
    CONFIRM = 1
    """Confirm the active test image."""
    REVERT = 2
    """Make the other slot active again."""


# --------------------------------------------------------------------------- base classes


class Message(Record):
    """Base of all messages (see the module docstring).

    Class attributes
    ----------------
    TYPE : MessageType
    CHANNEL : Channel
    KIND : Kind
    REPLY : type[Message] or None
        The reply this message elicits (an ERROR may come instead of any reply).
        For REQUEST kinds it carries the same request id; VIEW_REQUEST and
        KEYFRAME_REQUEST are events answered, latest-wins, by SCORES.
    SIGNED : bool
        Carries a session counter and tag (see :func:`protocol.auth.sign`).
    MUST_UNDERSTAND : bool
        Default of the frame's MUST_UNDERSTAND flag.
    """

    TYPE: ClassVar[MessageType]
    CHANNEL: ClassVar[Channel]
    KIND: ClassVar[Kind]
    REPLY: ClassVar[type[Message] | None] = None
    SIGNED: ClassVar[bool] = False
    TAGGED: ClassVar[bool] = False
    MUST_UNDERSTAND: ClassVar[bool] = True

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "TYPE" in cls.__dict__:
            previous = MESSAGE_CLASSES.get(cls.TYPE)
            if previous is not None:
                raise TypeError(
                    f"{cls.__name__}: TYPE {cls.TYPE!r} already used by {previous.__name__}"
                )
            MESSAGE_CLASSES[cls.TYPE] = cls

    def to_body(self) -> bytes:
        """Return the canonical CBOR body (sorted integer keys, shortest forms)."""
        return cbor2.dumps(self._to_map(), canonical=True)

    def to_frame(self, *, request_id: int = 0, flags: int | None = None) -> Frame:
        """Return the :class:`Frame` carrying this message."""
        if flags is None:
            flags = int(Flags.MUST_UNDERSTAND) if self.MUST_UNDERSTAND else 0
        return Frame(
            channel=self.CHANNEL,
            kind=self.KIND,
            msg_type=int(self.TYPE),
            request_id=request_id,
            body=self.to_body(),
            flags=flags,
        )

    def encode(self, *, request_id: int = 0, flags: int | None = None) -> bytes:
        """Return the complete wire frame (COBS-encoded, 0x00-terminated)."""
        if flags is None:
            flags = int(Flags.MUST_UNDERSTAND) if self.MUST_UNDERSTAND else 0
        return encode_frame(
            channel=self.CHANNEL,
            kind=self.KIND,
            msg_type=int(self.TYPE),
            request_id=request_id,
            body=self.to_body(),
            flags=flags,
        )

    @classmethod
    def from_body(cls, body: bytes, *, max_depth: int = MAX_DEPTH) -> Any:
        """Decode a CBOR body of this message type from untrusted bytes.

        Parameters
        ----------
        body : bytes
            The frame body.
        max_depth : int
            CBOR nesting limit (see :func:`scan_cbor`).

        Returns
        -------
        Message
            An instance of ``cls``.

        Raises
        ------
        MalformedMessage
            One line: ``decode NAME: ...``.
        """
        where = f"decode {cls.TYPE.name}"
        body = bytes(body)
        scan_cbor(body, max_depth=max_depth, where=where)
        try:
            obj = cbor2.loads(body)
        except (cbor2.CBORError, ValueError, TypeError, OverflowError) as exc:
            raise MalformedMessage(f"{where}: CBOR: {exc}") from None
        if not isinstance(obj, dict):
            raise MalformedMessage(f"{where}: body is a {type(obj).__name__}, not a map")
        try:
            return cls._from_map(obj, where)
        except ValueError as exc:
            text = str(exc)
            if not text.startswith(where):
                text = f"{where}: {text}"
            raise MalformedMessage(text) from None


@dataclass(frozen=True)
class UnknownMessage:
    """A frame whose message type this side does not know.

    Attributes
    ----------
    frame : Frame
        The frame as received.
    """

    frame: Frame

    @property
    def msg_type(self) -> int:
        """The unknown type byte."""
        return self.frame.msg_type

    @property
    def request_id(self) -> int:
        """The frame's request id."""
        return self.frame.request_id

    @property
    def must_understand(self) -> bool:
        """True when the sender asked for an ERROR if the type is unknown."""
        return self.frame.must_understand

    def error_reply(self) -> Error:
        """Return the ERROR(UNKNOWN_MESSAGE) to send back (with ``request_id``)."""
        return Error(
            code=ErrorCode.UNKNOWN_MESSAGE,
            where=f"type 0x{self.msg_type:02x}",
            message=f"unknown message type 0x{self.msg_type:02x}",
        )


MESSAGE_CLASSES: dict[MessageType, type[Message]] = {}
"""MessageType -> message class, filled as the classes below are defined."""


def decode_message(frame: Frame, *, max_depth: int = MAX_DEPTH) -> Message | UnknownMessage:
    """Decode a frame's body into its message.

    Parameters
    ----------
    frame : Frame
        A frame from :class:`protocol.framing.FrameDecoder`.
    max_depth : int
        CBOR nesting limit.

    Returns
    -------
    Message or UnknownMessage
        ``UnknownMessage`` when the type is not known here (answer it with
        ``error_reply()`` if ``must_understand``, else ignore it).

    Raises
    ------
    MalformedMessage
        The body does not decode, or the frame's channel/kind is not the one
        the message type is defined with.
    """
    cls = MESSAGE_CLASSES.get(frame.msg_type)  # type: ignore[call-overload]
    if cls is None:
        return UnknownMessage(frame)
    if frame.channel != cls.CHANNEL or frame.kind != cls.KIND:
        raise MalformedMessage(
            f"decode {cls.TYPE.name}: frame says channel {Channel(frame.channel).name} kind "
            f"{Kind(frame.kind).name}, {cls.TYPE.name} is channel {cls.CHANNEL.name} kind "
            f"{cls.KIND.name}"
        )
    return cls.from_body(frame.body, max_depth=max_depth)


def encode_message(msg: Message, *, request_id: int = 0, flags: int | None = None) -> bytes:
    """Return the wire frame for ``msg`` (same as ``msg.encode(...)``)."""
    return msg.encode(request_id=request_id, flags=flags)


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, kw_only=True)
class SlotInfo(Record):
    """One flash slot as reported in HELLO_REPLY and SLOT_STATUS."""

    slot: int = wire(0, ge=0, le=3)
    """Slot index (0 = A, 1 = B)."""
    state: SlotState = wire(1)  # noqa: RUF009 (wire() is a field specifier)
    active: bool = wire(2)
    """True for the slot the device boots from."""
    generation: int = wire(3, ge=0, le=U64)
    """Image generation (monotonic; rollback is refused unless forced)."""
    size_bytes: int = wire(4, ge=0, le=U64)
    digest: bytes = wire(5, lengths=(0, DIGEST_BYTES))
    """SHA-256 of the image, or empty for an empty slot."""


# --------------------------------------------------------------------------- control


@dataclass(frozen=True, kw_only=True)
class HelloReply(Message):
    """Device -> host: capabilities, limits, slots (answers HELLO)."""

    TYPE: ClassVar[MessageType] = MessageType.HELLO_REPLY
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.RESPONSE

    min_version: int = wire(0, ge=1, le=U8)
    max_version: int = wire(1, ge=1, le=U8)
    device_id: str = wire(2, min_len=1, max_len=64)
    nonce: bytes = wire(3, lengths=(NONCE_BYTES,))
    """Device nonce (fresh per HELLO)."""
    max_frame_bytes: int = wire(4, ge=BASELINE_MAX_FRAME_BYTES, le=1 << 24)
    """Largest frame (header + body + CRC, before COBS) the device accepts."""
    ram_budget_bytes: int = wire(5, ge=0, le=U64)
    slot_size_bytes: int = wire(6, ge=0, le=U64)
    """Capacity of each flash slot."""
    display_width: int = wire(7, ge=0, le=U16)
    display_height: int = wire(8, ge=0, le=U16)
    rx_window_frames: int = wire(9, ge=1, le=U16)
    """Image receive buffers: chunks the device can hold un-acknowledged."""
    rx_buffer_bytes: int = wire(10, ge=1, le=U32)
    """Size of each receive buffer: the largest IMAGE_CHUNK data accepted."""
    slots: tuple[SlotInfo, ...] = wire(11, max_items=4)
    has_key: bool = wire(12)
    """The device holds a provisioning key (AUTH possible)."""
    image_format_versions: tuple[int, ...] = wire(13, default=(), ge=1, le=U16, max_items=8)
    """.ecs format versions the device reads (empty: unknown)."""
    software: str = wire(14, default="", max_len=64)
    """Device software name/version, informational."""
    score_versions: tuple[int, ...] | None = wire(15, default=None, ge=1, le=U8, max_items=8)
    predicts: bool | None = wire(16, default=None)  # docs/protocol.md "Predicted corrections"

    def _check(self) -> None:
        if self.min_version > self.max_version:
            raise ValueError(
                f"HelloReply: min_version={self.min_version} > max_version={self.max_version}"
            )


@dataclass(frozen=True, kw_only=True)
class Hello(Message):
    """Host -> device: first message of a session (device answers HELLO_REPLY)."""

    TYPE: ClassVar[MessageType] = MessageType.HELLO
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = HelloReply

    min_version: int = wire(0, ge=1, le=U8)
    max_version: int = wire(1, ge=1, le=U8)
    nonce: bytes = wire(2, lengths=(NONCE_BYTES,))
    """Host nonce (fresh per session)."""
    host_id: str = wire(3, default="", max_len=64)
    """Informational host name."""

    def _check(self) -> None:
        if self.min_version > self.max_version:
            raise ValueError(
                f"Hello: min_version={self.min_version} > max_version={self.max_version}"
            )


@dataclass(frozen=True, kw_only=True)
class AuthResponse(Message):
    """Device -> host: the device's proof (answers AUTH_CHALLENGE once the host's proof
    verified; otherwise the answer is ERROR(AUTH_FAILED))."""

    TYPE: ClassVar[MessageType] = MessageType.AUTH_RESPONSE
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.RESPONSE

    device_proof: bytes = wire(0, lengths=(TAG_BYTES,))
    """``auth_proof(key, "device", ...)``."""
    slots: tuple[SlotInfo, ...] | None = wire(1, default=None, max_items=4)
    """Installed images (a keyed device's HELLO_REPLY leaves them out before AUTH)."""
    ram_budget_bytes: int | None = wire(2, default=None, ge=0, le=U64)
    """RAM the eigenspace may use (hidden in HELLO_REPLY before AUTH)."""
    slot_size_bytes: int | None = wire(3, default=None, ge=0, le=U64)
    """Capacity of each flash slot (hidden in HELLO_REPLY before AUTH)."""
    predicts: bool | None = wire(4, default=None)  # as in HELLO_REPLY (hidden there)


@dataclass(frozen=True, kw_only=True)
class AuthChallenge(Message):
    """Host -> device: the host's proof of the key over both nonces and the device id."""

    TYPE: ClassVar[MessageType] = MessageType.AUTH_CHALLENGE
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = AuthResponse

    host_proof: bytes = wire(0, lengths=(TAG_BYTES,))
    """``auth_proof(key, "host", ...)``."""


@dataclass(frozen=True, kw_only=True)
class Pong(Message):
    """Answer to PING: echoes the payload and the sender's timestamp."""

    TYPE: ClassVar[MessageType] = MessageType.PONG
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.RESPONSE

    payload: bytes = wire(0, default=b"", max_len=1024, repr=False)
    ping_sent_us: int = wire(1, ge=0, le=U64)
    """The PING's ``sent_us``, echoed."""
    sent_us: int = wire(2, ge=0, le=U64)
    """Responder's monotonic clock when it sent the PONG, microseconds."""


@dataclass(frozen=True, kw_only=True)
class Ping(Message):
    """Either side: liveness and round-trip time (answered by PONG)."""

    TYPE: ClassVar[MessageType] = MessageType.PING
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = Pong

    payload: bytes = wire(0, default=b"", max_len=1024, repr=False)
    sent_us: int = wire(1, ge=0, le=U64)
    """Sender's monotonic clock, microseconds."""


@dataclass(frozen=True, kw_only=True)
class Error(Message):
    """Either side: a request failed (carries the request's id) or an unsolicited error (id 0)."""

    TYPE: ClassVar[MessageType] = MessageType.ERROR
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.RESPONSE

    code: int = wire(0, ge=0, le=U16)
    """An ErrorCode value (kept an int so codes from newer peers still decode)."""
    where: str = wire(1, default="", max_len=64)
    """The operation that failed, e.g. "IMAGE_BEGIN"."""
    message: str = wire(2, default="", max_len=256)
    """One line for a human."""
    detail: Detail | None = wire(3, default=None, max_items=16, max_len=256)  # noqa: RUF009 (wire() is a field specifier)
    """Machine-readable specifics, e.g. {"size_bytes": 9, "limit_bytes": 8}."""

    @property
    def code_name(self) -> str:
        """The ErrorCode name, or ``CODE_<n>`` for a code unknown here."""
        try:
            return ErrorCode(self.code).name
        except ValueError:
            return f"CODE_{self.code}"

    def to_exception(self) -> RemoteError:
        """Return the RemoteError subclass for this code, with a one-line message."""
        try:
            cls = ERROR_CLASSES[ErrorCode(self.code)]
        except (ValueError, KeyError):
            cls = RemoteError
        text = f"{self.where}: {self.message}" if self.where else self.message
        exc = cls(self.code, text, name=self.code_name)
        exc.where = self.where  # type: ignore[attr-defined]
        exc.detail = dict(self.detail or {})  # type: ignore[attr-defined]
        return exc

    @classmethod
    def from_exception(cls, exc: BaseException, *, where: str = "") -> Error:
        """Build the ERROR answering a failure, with the code from :func:`error_code_for`."""
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return cls(
            code=error_code_for(exc),
            where=_truncate(where, 64),
            message=_truncate(message, 256),
        )


def _truncate(text: str, max_bytes: int) -> str:
    data = text.encode("utf-8", "replace")
    if len(data) <= max_bytes:
        return text
    return data[: max_bytes - 3].decode("utf-8", "ignore") + "..."


def error_code_for(exc: BaseException) -> ErrorCode:
    """Return the ErrorCode a receiver sends back for a local exception.

    RemoteError subclasses map back to their own code; ``ReplayError`` ->
    REPLAYED; ``NotAuthenticated`` -> NOT_AUTHENTICATED; other
    ``AuthenticationError`` -> AUTH_FAILED; ``MalformedMessage`` -> MALFORMED;
    ``LimitExceeded`` -> LIMIT_EXCEEDED; anything else -> INTERNAL.
    """
    if isinstance(exc, RemoteError):
        for code, cls in ERROR_CLASSES.items():
            if type(exc) is cls:
                return code
    if isinstance(exc, ReplayError):
        return ErrorCode.REPLAYED
    if isinstance(exc, NotAuthenticated):
        return ErrorCode.NOT_AUTHENTICATED
    if isinstance(exc, AuthenticationError):
        return ErrorCode.AUTH_FAILED
    if isinstance(exc, MalformedMessage):
        return ErrorCode.MALFORMED
    if isinstance(exc, LimitExceeded):
        return ErrorCode.LIMIT_EXCEEDED
    return ErrorCode.INTERNAL


@dataclass(frozen=True, kw_only=True)
class Ok(Message):
    """Generic success reply (IMAGE_ABORT, SET_BAUD, RESET)."""

    TYPE: ClassVar[MessageType] = MessageType.OK
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.RESPONSE


@dataclass(frozen=True, kw_only=True)
class Bye(Message):
    """Either side: the session ends (no reply)."""

    TYPE: ClassVar[MessageType] = MessageType.BYE
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.EVENT

    reason: str = wire(0, default="", max_len=256)


@dataclass(frozen=True, kw_only=True)
class Notice(Message):
    """Device -> host: an informational event (image confirmed, reverted at boot, ...)."""

    TYPE: ClassVar[MessageType] = MessageType.NOTICE
    CHANNEL: ClassVar[Channel] = Channel.EVENTS
    KIND: ClassVar[Kind] = Kind.EVENT
    MUST_UNDERSTAND: ClassVar[bool] = False

    level: int = wire(0, ge=0, le=2)
    """0 info, 1 warning, 2 error."""
    text: str = wire(1, max_len=256)
    detail: Detail | None = wire(2, default=None, max_items=16, max_len=256)  # noqa: RUF009 (wire() is a field specifier)


@dataclass(frozen=True, kw_only=True)
class SignedRequest(Message):
    """Base of mutating requests: carries ``session_counter`` (key 22) and ``session_tag``
    (key 23), both absent until :func:`sign` fills them."""

    SIGNED: ClassVar[bool] = True

    session_counter: int | None = wire(SESSION_COUNTER_KEY, default=None, ge=1, le=U64)
    session_tag: bytes | None = wire(SESSION_TAG_KEY, default=None, lengths=(TAG_BYTES,))


@dataclass(frozen=True, kw_only=True)
class TaggedEvent(Message):
    """Base of events that change what a keyed device shows or stores (SCORES, IMAGE_CHUNK):
    ``session_counter`` (key 22) and a 16-byte ``session_tag`` (key 23), both absent until
    :func:`tag_event` fills them (a keyless device takes them untagged)."""

    TAGGED: ClassVar[bool] = True

    session_counter: int | None = wire(SESSION_COUNTER_KEY, default=None, ge=1, le=U64)
    session_tag: bytes | None = wire(SESSION_TAG_KEY, default=None, lengths=(EVENT_TAG_BYTES,))


@dataclass(frozen=True, kw_only=True)
class SetBaud(SignedRequest):
    """Host -> device: switch both ends to ``baud`` after the OK; the device reverts to
    the old rate unless the host pings at the new rate within ``revert_timeout_ms``."""

    TYPE: ClassVar[MessageType] = MessageType.SET_BAUD
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = Ok

    baud: int = wire(0, ge=300, le=16_000_000)
    revert_timeout_ms: int = wire(1, ge=1, le=600_000)


@dataclass(frozen=True, kw_only=True)
class Reset(SignedRequest):
    """Host -> device: reboot after sending OK."""

    TYPE: ClassVar[MessageType] = MessageType.RESET
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = Ok

    reason: str = wire(0, default="", max_len=256)


@dataclass(frozen=True, kw_only=True)
class SlotStatus(Message):
    """Device -> host: every slot after a change (answers SLOT_SET and IMAGE_COMMIT)."""

    TYPE: ClassVar[MessageType] = MessageType.SLOT_STATUS
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.RESPONSE

    slots: tuple[SlotInfo, ...] = wire(0, max_items=4)


@dataclass(frozen=True, kw_only=True)
class SlotSet(SignedRequest):
    """Host -> device: activate, confirm or revert a slot."""

    TYPE: ClassVar[MessageType] = MessageType.SLOT_SET
    CHANNEL: ClassVar[Channel] = Channel.CONTROL
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = SlotStatus

    action: SlotAction = wire(0)  # noqa: RUF009 (wire() is a field specifier)
    slot: int | None = wire(1, default=None, ge=0, le=3)
    """Target slot for ACTIVATE; ignored otherwise."""
    force: bool = wire(2, default=False)
    """Allow activating an older generation."""

    def _check(self) -> None:
        if self.action == SlotAction.ACTIVATE and self.slot is None:
            raise ValueError("SlotSet: action ACTIVATE needs slot")


# --------------------------------------------------------------------------- image


@dataclass(frozen=True, kw_only=True)
class ImageAck(Message):
    """Device -> host: cumulative acknowledgement of an image transfer.

    Answers IMAGE_BEGIN (same request id) and then follows chunks with that id:
    the request id of IMAGE_BEGIN names the transfer.
    """

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_ACK
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.ACK

    next_offset: int = wire(0, ge=0, le=U64)
    """Lowest offset not yet received (everything below it is received)."""
    credits: int = wire(1, ge=0, le=U16)
    """Chunks the host may have in flight beyond ``next_offset``."""
    window_bytes: int = wire(2, ge=0, le=U32)
    """The device accepts chunk offsets in [next_offset, next_offset + window_bytes)."""


@dataclass(frozen=True, kw_only=True)
class ImageBegin(SignedRequest):
    """Host -> device: start (or resume) writing an image to the inactive slot."""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_BEGIN
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = ImageAck

    size_bytes: int = wire(0, ge=1, le=U64)
    digest: bytes = wire(1, lengths=(DIGEST_BYTES,))
    """SHA-256 of the whole image."""
    image_tag: bytes = wire(2, lengths=(TAG_BYTES,))
    """The image's HMAC-SHA256 tag (over its digest, with the device key)."""
    format_version: int = wire(3, ge=1, le=U16)
    generation: int = wire(4, ge=0, le=U64)
    force: bool = wire(5, default=False)
    """Allow an older generation (rollback)."""


@dataclass(frozen=True, kw_only=True)
class ImageStatusReply(Message):
    """Device -> host: where a transfer of that digest would resume."""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_STATUS_REPLY
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.RESPONSE

    next_offset: int = wire(0, ge=0, le=U64)
    """Verified, durable prefix length the device holds for that digest (0: none)."""
    in_progress: bool = wire(1)
    """A journalled transfer of that digest exists."""


@dataclass(frozen=True, kw_only=True)
class ImageStatus(Message):
    """Host -> device: what offset do you need for this image?"""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_STATUS
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = ImageStatusReply

    digest: bytes = wire(0, lengths=(DIGEST_BYTES,))
    size_bytes: int = wire(1, ge=1, le=U64)


@dataclass(frozen=True, kw_only=True)
class ImageChunk(TaggedEvent):
    """Host -> device: image bytes at ``offset`` (request id = the transfer's IMAGE_BEGIN id)."""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_CHUNK
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.EVENT
    REPLY: ClassVar[type[Message] | None] = ImageAck

    offset: int = wire(0, ge=0, le=U64)
    data: bytes = wire(1, min_len=1, max_len=MAX_PAYLOAD_BYTES, repr=False)
    """At most the device's ``rx_buffer_bytes``."""


@dataclass(frozen=True, kw_only=True)
class ImageVerifyReply(Message):
    """Device -> host: result of re-reading the written slot."""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_VERIFY_REPLY
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.RESPONSE

    ok: bool = wire(0)
    """Digest matches and the tag verifies."""
    digest: bytes = wire(1, lengths=(0, DIGEST_BYTES))
    """SHA-256 the device computed over the slot."""
    tag_ok: bool = wire(2)
    size_bytes: int = wire(3, ge=0, le=U64)


@dataclass(frozen=True, kw_only=True)
class ImageVerify(Message):
    """Host -> device: re-read the written slot, check SHA-256 and the HMAC tag."""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_VERIFY
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = ImageVerifyReply

    digest: bytes = wire(0, lengths=(DIGEST_BYTES,))


@dataclass(frozen=True, kw_only=True)
class ImageCommit(SignedRequest):
    """Host -> device: make the verified image active for a test boot."""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_COMMIT
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = SlotStatus

    digest: bytes = wire(0, lengths=(DIGEST_BYTES,))


@dataclass(frozen=True, kw_only=True)
class ImageAbort(SignedRequest):
    """Host -> device: drop the transfer in progress and its journal."""

    TYPE: ClassVar[MessageType] = MessageType.IMAGE_ABORT
    CHANNEL: ClassVar[Channel] = Channel.IMAGE
    KIND: ClassVar[Kind] = Kind.REQUEST
    REPLY: ClassVar[type[Message] | None] = Ok

    digest: bytes | None = wire(0, default=None, lengths=(DIGEST_BYTES,))
    """The transfer to abort; absent: whatever is in progress."""


# --------------------------------------------------------------------------- scores


@dataclass(frozen=True, kw_only=True)
class Scores(TaggedEvent):
    """Host -> device: one score packet (protocol.scores); latest wins."""

    TYPE: ClassVar[MessageType] = MessageType.SCORES
    CHANNEL: ClassVar[Channel] = Channel.SCORES
    KIND: ClassVar[Kind] = Kind.EVENT

    sequence: int = wire(0, ge=0, le=U32)
    """The VIEW_REQUEST/KEYFRAME_REQUEST sequence answered (0: unsolicited, e.g. orbit)."""
    packet: bytes = wire(1, min_len=1, max_len=MAX_PAYLOAD_BYTES, repr=False)
    """Opaque score packet, decoded by protocol.scores with the device's limits."""
    look: int | None = wire(2, default=None, ge=0, le=MAX_LOOKS - 1)
    """The look it was made for (absent: the first); a device showing another drops it."""


@dataclass(frozen=True, kw_only=True)
class ViewRequest(Message):
    """Device -> host: show this view (answered, latest wins, by SCORES)."""

    TYPE: ClassVar[MessageType] = MessageType.VIEW_REQUEST
    CHANNEL: ClassVar[Channel] = Channel.SCORES
    KIND: ClassVar[Kind] = Kind.EVENT
    REPLY: ClassVar[type[Message] | None] = Scores

    phi_deg: float = wire(0)
    """Azimuth in degrees (any finite value; wraps at 360)."""
    theta_deg: float = wire(1, ge=-90.0, le=90.0)
    """Elevation in degrees."""
    sequence: int = wire(2, ge=0, le=U32)
    """Increases with every request; SCORES echoes it."""
    look: int | None = wire(3, default=None, ge=0, le=MAX_LOOKS - 1)
    """The look on show (`protocol.image` ``looks``; absent: the first)."""


@dataclass(frozen=True, kw_only=True)
class KeyframeRequest(Message):
    """Device -> host: I lost a delta base; send a key frame (answered by SCORES)."""

    TYPE: ClassVar[MessageType] = MessageType.KEYFRAME_REQUEST
    CHANNEL: ClassVar[Channel] = Channel.SCORES
    KIND: ClassVar[Kind] = Kind.EVENT
    REPLY: ClassVar[type[Message] | None] = Scores

    sequence: int = wire(0, ge=0, le=U32)
    last_frame: int | None = wire(1, default=None, ge=0, le=U32)
    """Frame number of the last packet the device decoded (absent: none)."""


# Every class must have resolvable field specs; build them now so a bad
# declaration fails at import, not on the first frame.
for _cls in (SlotInfo, *MESSAGE_CLASSES.values()):
    _cls._specs()
del _cls


# --------------------------------------------------------------------------- auth (protocol.auth)


def __getattr__(name: str) -> Any:
    """``m.sign`` and the other names that moved to :mod:`protocol.auth` (it imports this)."""
    if name in ("auth_proof", "derive_session_key", "sign", "tag_event", "verify", "verify_event"):
        from protocol import auth

        return getattr(auth, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
