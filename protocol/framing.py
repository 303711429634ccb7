"""Wire framing: COBS(header + CBOR body + CRC-32) followed by one 0x00 byte.

Frame layout before COBS (all integers little-endian)::

    offset size field
    0      1    bits 7..4: frame format version (FRAME_VERSION = 1)
                bits 3..0: flags (bit 0 MUST_UNDERSTAND; bits 1..3 reserved, 0)
    1      1    channel  (Channel: CONTROL=0, IMAGE=1, SCORES=2, EVENTS=3)
    2      1    kind     (Kind: REQUEST=0, RESPONSE=1, EVENT=2, ACK=3)
    3      1    message type (protocol.messages.MessageType)
    4      2    request id (u16)
    6      4    body length in bytes (u32) = frame length - 14
    10     n    body: one CBOR data item (protocol.messages)
    10+n   4    CRC-32 of bytes [0, 10+n): zlib/IEEE 802.3 CRC-32 (poly 0x04C11DB7
                reflected, init 0xFFFFFFFF, xorout 0xFFFFFFFF; "123456789" -> 0xCBF43926)

The message type lives in the header, not the body, so a receiver can route a
frame (latest-wins scores, image chunks) and answer ``ERROR(UNKNOWN_MESSAGE)``
with the right request id without parsing CBOR; the body is then a plain map
of fields.

The receiver (:class:`FrameDecoder`) splits the byte stream at 0x00, COBS-decodes
each piece, checks the CRC, then the header. Anything wrong drops that one frame
(counted) and decoding resumes after the next 0x00, so corruption never costs
more than the frames it touches. It never buffers more than
``cobs_max_encoded_size(max_frame_bytes)`` bytes of an unterminated frame,
whatever any length field says.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from enum import IntEnum, IntFlag, unique
from typing import ClassVar

from protocol._cobs import CobsDecodeError, cobs_decode, cobs_encode, cobs_max_encoded_size
from protocol.errors import BadCobs, BadCRC, BadHeader, FrameTooLarge, FramingError

__all__ = [
    "CRC",
    "FRAME_VERSION",
    "HEADER",
    "MAX_FRAME_BYTES_LIMIT",
    "MIN_FRAME_BYTES",
    "Channel",
    "Flags",
    "Frame",
    "FrameDecoder",
    "Kind",
    "crc32",
    "decode_frame",
    "encode_frame",
    "frame_size_bytes",
    "max_body_bytes",
    "max_encoded_frame_bytes",
]

FRAME_VERSION = 1
"""Frame format version carried in the high nibble of byte 0."""

HEADER = struct.Struct("<BBBBHI")
"""Frame header: version|flags, channel, kind, message type, request id, body length."""

CRC = struct.Struct("<I")
"""CRC-32 trailer, little-endian."""

MIN_FRAME_BYTES = HEADER.size + CRC.size
"""Smallest valid frame before COBS (empty body): 14 bytes."""

MAX_FRAME_BYTES_LIMIT = 1 << 24
"""Largest ``max_frame_bytes`` any decoder accepts (16 MiB)."""

_MIN_MAX_FRAME_BYTES = 64


@unique
class Channel(IntEnum):
    """Logical channel of a frame (one byte)."""

    CONTROL = 0
    """Session setup, auth, slots, baud, errors, ping."""
    IMAGE = 1
    """Eigenspace image transfer (begin, chunks, acks, verify)."""
    SCORES = 2
    """Score packets and view requests (latest wins)."""
    EVENTS = 3
    """Unsolicited notifications."""


@unique
class Kind(IntEnum):
    """What a frame is in a conversation (one byte)."""

    REQUEST = 0
    """Expects exactly one reply carrying the same request id."""
    RESPONSE = 1
    """Answers the request with the same request id."""
    EVENT = 2
    """One-way; no reply is owed."""
    ACK = 3
    """Cumulative flow-control acknowledgement (IMAGE_ACK)."""


class Flags(IntFlag):
    """Flag bits (low nibble of byte 0)."""

    NONE = 0
    MUST_UNDERSTAND = 1
    """A receiver that does not know the message type answers ERROR(UNKNOWN_MESSAGE);
    without it the frame is ignored."""


_RESERVED_FLAGS = 0x0F & ~int(Flags.MUST_UNDERSTAND)


def crc32(data: bytes | bytearray | memoryview) -> int:
    """Return the CRC-32 (IEEE 802.3, as ``zlib.crc32``) of ``data`` as an int.

    Parameters
    ----------
    data : bytes-like

    Returns
    -------
    int
        In [0, 2**32). ``crc32(b"123456789") == 0xCBF43926``.
    """
    return zlib.crc32(data) & 0xFFFFFFFF


def frame_size_bytes(body_bytes: int) -> int:
    """Return the frame size before COBS for a body of ``body_bytes`` bytes."""
    return MIN_FRAME_BYTES + body_bytes


def max_body_bytes(max_frame_bytes: int) -> int:
    """Return the largest CBOR body that fits a frame of ``max_frame_bytes``."""
    return max_frame_bytes - MIN_FRAME_BYTES


def max_encoded_frame_bytes(max_frame_bytes: int) -> int:
    """Return the most wire bytes one frame of ``max_frame_bytes`` can take.

    COBS worst case plus the 0x00 delimiter.
    """
    return cobs_max_encoded_size(max_frame_bytes) + 1


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame.

    Attributes
    ----------
    channel : Channel
    kind : Kind
    msg_type : int
        Message type, 0..255 (see ``protocol.messages.MessageType``).
    request_id : int
        0..65535.
    body : bytes
        The CBOR body (not decoded here).
    flags : int
        Flag bits (``Flags``), 0..15 with only defined bits set.
    version : int
        Frame format version, ``FRAME_VERSION``.
    """

    channel: Channel
    kind: Kind
    msg_type: int
    request_id: int
    body: bytes
    flags: int = 0
    version: int = FRAME_VERSION

    HEADER: ClassVar[struct.Struct] = HEADER

    @property
    def must_understand(self) -> bool:
        """True when the MUST_UNDERSTAND flag is set."""
        return bool(self.flags & Flags.MUST_UNDERSTAND)

    def encode(self) -> bytes:
        """Return the wire bytes: COBS(header + body + CRC) + 0x00."""
        return encode_frame(
            channel=self.channel,
            kind=self.kind,
            msg_type=self.msg_type,
            request_id=self.request_id,
            body=self.body,
            flags=self.flags,
        )


def encode_frame(
    *,
    channel: int,
    kind: int,
    msg_type: int,
    request_id: int,
    body: bytes | bytearray | memoryview,
    flags: int = 0,
) -> bytes:
    """Build one wire frame.

    Parameters
    ----------
    channel : Channel or int
    kind : Kind or int
    msg_type : int
        0..255.
    request_id : int
        0..65535.
    body : bytes-like
        CBOR body, < 2**32 bytes.
    flags : int
        ``Flags`` bits; reserved bits must be 0.

    Returns
    -------
    bytes
        ``COBS(header + body + CRC-32 LE) + b"\\x00"``.

    Raises
    ------
    ValueError
        If a field is out of range (a bug in the caller, not bad data).
    """
    if channel not in Channel._value2member_map_:
        raise ValueError(
            f"encode frame: channel={channel} is not one of {[int(c) for c in Channel]}"
        )
    if kind not in Kind._value2member_map_:
        raise ValueError(f"encode frame: kind={kind} is not one of {[int(k) for k in Kind]}")
    if not 0 <= msg_type <= 0xFF:
        raise ValueError(f"encode frame: msg_type={msg_type} must be in [0, 255]")
    if not 0 <= request_id <= 0xFFFF:
        raise ValueError(f"encode frame: request_id={request_id} must be in [0, 65535]")
    if flags & ~int(Flags.MUST_UNDERSTAND) or flags < 0:
        raise ValueError(f"encode frame: flags=0x{flags:x} sets reserved bits (allowed: 0x1)")
    n = len(body)
    if n >= 1 << 32:
        raise ValueError(f"encode frame: body of {n} bytes exceeds 2**32 - 1")
    raw = bytearray(HEADER.size + n + CRC.size)
    HEADER.pack_into(raw, 0, (FRAME_VERSION << 4) | flags, channel, kind, msg_type, request_id, n)
    raw[HEADER.size : HEADER.size + n] = body
    CRC.pack_into(raw, HEADER.size + n, zlib.crc32(memoryview(raw)[: HEADER.size + n]))
    return cobs_encode(raw) + b"\x00"


def _parse(payload: bytes) -> Frame:
    """Check a COBS-decoded frame (CRC, then header) and return it."""
    n = len(payload)
    if n < MIN_FRAME_BYTES:
        raise BadHeader(
            f"decode frame: {n} bytes is shorter than the {MIN_FRAME_BYTES}-byte minimum"
        )
    (sent_crc,) = CRC.unpack_from(payload, n - CRC.size)
    actual_crc = zlib.crc32(memoryview(payload)[: n - CRC.size])
    if sent_crc != actual_crc:
        raise BadCRC(
            f"decode frame: CRC-32 mismatch: frame says 0x{sent_crc:08x}, "
            f"contents give 0x{actual_crc:08x} ({n} bytes)"
        )
    ver_flags, channel, kind, msg_type, request_id, body_len = HEADER.unpack_from(payload)
    version, flags = ver_flags >> 4, ver_flags & 0x0F
    if version != FRAME_VERSION:
        raise BadHeader(
            f"decode frame: version {version} is not supported (supported: {FRAME_VERSION})"
        )
    if flags & _RESERVED_FLAGS:
        raise BadHeader(f"decode frame: flags 0x{flags:x} set reserved bits (allowed: 0x1)")
    if channel not in Channel._value2member_map_:
        raise BadHeader(
            f"decode frame: channel {channel} is not one of {[int(c) for c in Channel]}"
        )
    if kind not in Kind._value2member_map_:
        raise BadHeader(f"decode frame: kind {kind} is not one of {[int(k) for k in Kind]}")
    actual_len = n - MIN_FRAME_BYTES
    if body_len != actual_len:
        raise BadHeader(
            f"decode frame: header says body length {body_len}, frame carries {actual_len}"
        )
    return Frame(
        channel=Channel(channel),
        kind=Kind(kind),
        msg_type=msg_type,
        request_id=request_id,
        body=payload[HEADER.size : n - CRC.size],
        flags=flags,
        version=version,
    )


def _check_max_frame_bytes(max_frame_bytes: int) -> None:
    if not isinstance(max_frame_bytes, int) or not (
        _MIN_MAX_FRAME_BYTES <= max_frame_bytes <= MAX_FRAME_BYTES_LIMIT
    ):
        raise ValueError(
            f"max_frame_bytes={max_frame_bytes!r} must be an int in "
            f"[{_MIN_MAX_FRAME_BYTES}, {MAX_FRAME_BYTES_LIMIT}]"
        )


def decode_frame(wire: bytes | bytearray | memoryview, *, max_frame_bytes: int) -> Frame:
    """Decode exactly one frame (strict; for tests and tools).

    Parameters
    ----------
    wire : bytes-like
        One COBS-encoded frame, with or without its trailing 0x00.
    max_frame_bytes : int
        Largest frame (before COBS) accepted.

    Returns
    -------
    Frame

    Raises
    ------
    FrameTooLarge, BadCobs, BadCRC, BadHeader
        As named; all are ``FramingError``.
    """
    _check_max_frame_bytes(max_frame_bytes)
    data = bytes(wire)
    if data.endswith(b"\x00"):
        data = data[:-1]
    if len(data) > cobs_max_encoded_size(max_frame_bytes):
        raise FrameTooLarge(
            f"decode frame: {len(data)} encoded bytes exceed the bound "
            f"{cobs_max_encoded_size(max_frame_bytes)} for max_frame_bytes={max_frame_bytes}"
        )
    try:
        payload = cobs_decode(data)
    except CobsDecodeError as exc:
        raise BadCobs(str(exc)) from None
    if len(payload) > max_frame_bytes:
        raise FrameTooLarge(
            f"decode frame: {len(payload)} bytes exceed max_frame_bytes={max_frame_bytes}"
        )
    return _parse(payload)


class FrameDecoder:
    """Incremental frame decoder for a byte stream, split at any points.

    Parameters
    ----------
    max_frame_bytes : int
        Largest frame (header + body + CRC, before COBS) accepted, in
        [64, 2**24]. Longer frames are dropped and counted in ``oversize``.

    Attributes
    ----------
    frames_ok : int
        Frames returned.
    bad_cobs, bad_crc, bad_header : int
        Frames dropped for invalid COBS, a CRC mismatch, or a bad header (too
        short, unknown version, reserved flags, unknown channel/kind, body
        length disagreeing with the frame).
    oversize : int
        Frames dropped for exceeding ``max_frame_bytes``.
    garbage_bytes : int
        Bytes of every dropped frame (delimiters not counted).
    last_error : str or None
        One line describing the most recent dropped frame.

    Notes
    -----
    ``feed`` never raises on any input and never keeps more than
    ``max_buffered_bytes`` bytes of an unterminated frame: past that bound the
    frame is counted as oversize and its bytes are discarded up to the next
    0x00. Empty frames (consecutive 0x00 bytes) are ignored silently: a sender
    may emit a lone 0x00 to flush a receiver's partial frame.
    """

    def __init__(self, max_frame_bytes: int) -> None:
        _check_max_frame_bytes(max_frame_bytes)
        self.max_frame_bytes = max_frame_bytes
        self.max_buffered_bytes = cobs_max_encoded_size(max_frame_bytes)
        self._buf = bytearray()
        self._discarding = False
        self.frames_ok = 0
        self.bad_cobs = 0
        self.bad_crc = 0
        self.bad_header = 0
        self.oversize = 0
        self.garbage_bytes = 0
        self.last_error: str | None = None

    @property
    def buffered_bytes(self) -> int:
        """Bytes of an unterminated frame held now (<= ``max_buffered_bytes``)."""
        return len(self._buf)

    @property
    def partial(self) -> bytes:
        """The bytes of the unterminated frame held now (to hand the stream to another
        decoder: feeding them to it continues where this one stopped)."""
        return b"" if self._discarding else bytes(self._buf)

    def counters(self) -> dict[str, int]:
        """Return all counters as a dict (for status output and logs)."""
        return {
            "frames_ok": self.frames_ok,
            "bad_cobs": self.bad_cobs,
            "bad_crc": self.bad_crc,
            "bad_header": self.bad_header,
            "oversize": self.oversize,
            "garbage_bytes": self.garbage_bytes,
        }

    def reset(self) -> None:
        """Drop any partial frame (e.g. after a baud change); counters are kept."""
        self._buf.clear()
        self._discarding = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Consume bytes; return the frames completed by them, in order.

        Parameters
        ----------
        data : bytes-like
            Any bytes from the stream.

        Returns
        -------
        list of Frame
        """
        data = bytes(data)
        frames: list[Frame] = []
        start = 0
        end = len(data)
        bound = self.max_buffered_bytes
        while start < end:
            zero = data.find(b"\x00", start)
            if zero < 0:
                rest = end - start
                if self._discarding:
                    self.garbage_bytes += rest
                elif len(self._buf) + rest > bound:
                    self._drop_oversize(len(self._buf) + rest)
                    self._buf.clear()
                    self._discarding = True
                else:
                    self._buf += data[start:]
                break
            if self._discarding:
                self.garbage_bytes += zero - start
                self._discarding = False
            else:
                size = len(self._buf) + zero - start
                if size > bound:
                    self._drop_oversize(size)
                    self._buf.clear()
                    start = zero + 1
                    continue
                if self._buf:
                    self._buf += data[start:zero]
                    piece = bytes(self._buf)
                    self._buf.clear()
                else:
                    piece = data[start:zero]
                if piece:
                    frame = self._decode_piece(piece)
                    if frame is not None:
                        frames.append(frame)
            start = zero + 1
        return frames

    def _drop_oversize(self, size: int) -> None:
        self.oversize += 1
        self.garbage_bytes += size
        self.last_error = (
            f"decode frame: more than {self.max_buffered_bytes} encoded bytes without a "
            f"delimiter (max_frame_bytes={self.max_frame_bytes}); dropped"
        )

    def _decode_piece(self, piece: bytes) -> Frame | None:
        try:
            payload = cobs_decode(piece)
            if len(payload) > self.max_frame_bytes:
                raise FrameTooLarge(
                    f"decode frame: {len(payload)} bytes exceed "
                    f"max_frame_bytes={self.max_frame_bytes}"
                )
            frame = _parse(payload)
        except CobsDecodeError as exc:
            self.bad_cobs += 1
            self.last_error = str(exc)
        except BadCRC as exc:
            self.bad_crc += 1
            self.last_error = str(exc)
        except FrameTooLarge as exc:
            self.oversize += 1
            self.last_error = str(exc)
        except FramingError as exc:
            self.bad_header += 1
            self.last_error = str(exc)
        else:
            self.frames_ok += 1
            return frame
        self.garbage_bytes += len(piece)
        return None
