"""Byte formats of the flash store: the state record and the transfer journal.

All integers are little-endian. See :mod:`device_runtime.flash` for the
layout of the folder and the crash-safety argument.

State record (``RECORD_SIZE`` = 148 bytes, one per copy file)::

    offset size  field
    0      4     magic b"ECFS"
    4      2     format version (1)
    6      2     record size in bytes (148)
    8      8     record generation (+1 on every write; the copy file is generation % 2)
    16     8     slot capacity in bytes
    24     1     active slot: 0 = A, 1 = B, -1 = none (signed)
    25     3     zero
    28     56    slot A: state u8, bad reason u8, zero u16, boot attempts u32,
                 image size u64, image generation u64, SHA-256 32 bytes
    84     56    slot B: same layout
    140    4     zero
    144    4     CRC-32 (zlib) of bytes 0..143

Journal file (header, then appended entries)::

    header (64 bytes): magic b"ECFJ", version u16 (1), zero u16, block size u32,
                       image size u64, image generation u64, image SHA-256 32 bytes,
                       CRC-32 of the preceding 60 bytes u32
    entry  (40 bytes): block index u32, SHA-256 of that block 32 bytes,
                       CRC-32 of the preceding 36 bytes, seeded with the header's CRC u32

Reading stops at the first entry whose CRC fails (a torn last append); the
seed ties every entry to its own header.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from enum import IntEnum, unique

__all__ = [
    "JOURNAL_ENTRY_SIZE",
    "JOURNAL_HEADER_SIZE",
    "RECORD_SIZE",
    "BadReason",
    "FormatInvalid",
    "JournalHeader",
    "SlotInfo",
    "SlotState",
    "StateRecord",
    "decode_journal_entry",
    "decode_journal_header",
    "decode_record",
    "encode_journal_entry",
    "encode_journal_header",
    "encode_record",
]

RECORD_MAGIC = b"ECFS"
RECORD_VERSION = 1
JOURNAL_MAGIC = b"ECFJ"
JOURNAL_VERSION = 1

_RECORD_HEAD = struct.Struct("<4sHHQQb3x")
_RECORD_SLOT = struct.Struct("<BBHIQQ32s")
_RECORD_TAIL = struct.Struct("<4xI")
RECORD_SIZE = _RECORD_HEAD.size + 2 * _RECORD_SLOT.size + _RECORD_TAIL.size

_JOURNAL_HEAD = struct.Struct("<4sHHIQQ32sI")
JOURNAL_HEADER_SIZE = _JOURNAL_HEAD.size
_JOURNAL_ENTRY = struct.Struct("<I32sI")
JOURNAL_ENTRY_SIZE = _JOURNAL_ENTRY.size

_U32_MAX = 2**32 - 1
_NO_DIGEST = bytes(32)


class FormatInvalid(ValueError):
    """A record or journal failed its checks (internal: callers treat it as absent)."""


@unique
class SlotState(IntEnum):
    """What a slot holds.

    ``EMPTY``: nothing usable (never written, or being written now).
    ``TEST``: a verified image on its test boot(s); reverts unless confirmed.
    ``CONFIRMED``: a verified image the runtime confirmed after showing a frame.
    ``BAD``: an image that must not boot (see :class:`BadReason`).
    """

    EMPTY = 0
    TEST = 1
    CONFIRMED = 2
    BAD = 3

    @property
    def label(self) -> str:
        """Lower-case name used by ``--status`` and ``--json`` (``"test"``, ...)."""
        return self.name.lower()


@unique
class BadReason(IntEnum):
    """Why a slot is :attr:`SlotState.BAD` (``NONE`` for every other state)."""

    NONE = 0
    DIGEST_MISMATCH = 1
    NOT_CONFIRMED = 2
    ABANDONED = 3
    REVERTED = 4
    NOT_LOADABLE = 5

    @property
    def description(self) -> str:
        """A few words for status output."""
        return {
            BadReason.NONE: "",
            BadReason.DIGEST_MISMATCH: "digest mismatch at boot",
            BadReason.NOT_CONFIRMED: "test image not confirmed; reverted at boot",
            BadReason.ABANDONED: "test image abandoned for another slot",
            BadReason.REVERTED: "reverted by command",
            BadReason.NOT_LOADABLE: "the device could not load it; fell back at boot",
        }[self]


@dataclass(frozen=True)
class SlotInfo:
    """One slot as the state record describes it.

    Attributes
    ----------
    name : str
        ``"A"`` or ``"B"``.
    state : SlotState
    size_bytes : int
        Image size in bytes (0 when empty).
    sha256 : bytes or None
        SHA-256 digest of the image's ``size_bytes`` bytes (None when empty).
    image_generation : int
        The image's generation number (rollback protection).
    boot_attempts : int
        Boots of a test image so far (kept after confirmation, for information).
    bad_reason : BadReason
    """

    name: str
    state: SlotState
    size_bytes: int = 0
    sha256: bytes | None = None
    image_generation: int = 0
    boot_attempts: int = 0
    bad_reason: BadReason = BadReason.NONE

    @classmethod
    def empty(cls, name: str) -> SlotInfo:
        """An :attr:`SlotState.EMPTY` slot called ``name``."""
        return cls(name=name, state=SlotState.EMPTY)

    @property
    def bootable(self) -> bool:
        """True for TEST and CONFIRMED slots (those that may become or stay active)."""
        return self.state in (SlotState.TEST, SlotState.CONFIRMED)


@dataclass(frozen=True)
class StateRecord:
    """The decoded state record: generation, capacity, active slot index, both slots."""

    generation: int
    capacity_bytes: int
    active: int | None
    slots: tuple[SlotInfo, SlotInfo]


def encode_record(record: StateRecord) -> bytes:
    """Return the ``RECORD_SIZE`` bytes of ``record`` with its CRC-32."""
    active = -1 if record.active is None else record.active
    parts = [
        _RECORD_HEAD.pack(
            RECORD_MAGIC, RECORD_VERSION, RECORD_SIZE, record.generation,
            record.capacity_bytes, active,
        )
    ]
    for slot in record.slots:
        parts.append(
            _RECORD_SLOT.pack(
                int(slot.state), int(slot.bad_reason), 0, min(slot.boot_attempts, _U32_MAX),
                slot.size_bytes, slot.image_generation, slot.sha256 or _NO_DIGEST,
            )
        )
    body = b"".join(parts)
    return body + _RECORD_TAIL.pack(zlib.crc32(body + bytes(4)))


def decode_record(data: bytes, *, copy_index: int, names: tuple[str, str]) -> StateRecord:
    """Decode the first ``RECORD_SIZE`` bytes of a state-record copy.

    Raises
    ------
    FormatInvalid
        Short, wrong magic/version/size, CRC mismatch, a generation that does not
        belong to copy ``copy_index``, or field values out of range.
    """
    if len(data) < RECORD_SIZE:
        raise FormatInvalid(f"{len(data)} bytes, a record is {RECORD_SIZE}")
    data = bytes(data[:RECORD_SIZE])
    (stored_crc,) = _RECORD_TAIL.unpack_from(data, RECORD_SIZE - _RECORD_TAIL.size)
    computed_crc = zlib.crc32(data[:-4])
    if stored_crc != computed_crc:
        raise FormatInvalid(
            f"CRC mismatch (stored 0x{stored_crc:08x}, computed 0x{computed_crc:08x})")
    magic, version, size, generation, capacity, active = _RECORD_HEAD.unpack_from(data, 0)
    if magic != RECORD_MAGIC or version != RECORD_VERSION or size != RECORD_SIZE:
        raise FormatInvalid(f"unknown magic/version/size {magic!r}/{version}/{size}")
    if generation % 2 != copy_index:
        raise FormatInvalid(f"generation {generation} does not belong to copy {copy_index}")
    if active not in (-1, 0, 1):
        raise FormatInvalid(f"active slot index {active} is not -1, 0 or 1")
    slots = []
    for index, name in enumerate(names):
        state, reason, _, attempts, img_size, img_gen, digest = _RECORD_SLOT.unpack_from(
            data, _RECORD_HEAD.size + index * _RECORD_SLOT.size
        )
        try:
            state, reason = SlotState(state), BadReason(reason)
        except ValueError as exc:
            raise FormatInvalid(f"slot {name}: {exc}") from None
        if img_size > capacity:
            raise FormatInvalid(f"slot {name}: size {img_size} exceeds capacity {capacity}")
        empty = state is SlotState.EMPTY
        slots.append(
            SlotInfo(
                name=name, state=state, size_bytes=img_size,
                sha256=None if empty else digest, image_generation=img_gen,
                boot_attempts=attempts, bad_reason=reason,
            )
        )
    return StateRecord(
        generation=generation, capacity_bytes=capacity,
        active=None if active < 0 else active, slots=(slots[0], slots[1]),
    )


@dataclass(frozen=True)
class JournalHeader:
    """The transfer session a journal belongs to."""

    block_bytes: int
    size_bytes: int
    image_generation: int
    sha256: bytes


def encode_journal_header(header: JournalHeader) -> tuple[bytes, int]:
    """Return ``(header bytes, header CRC)``; the CRC seeds every entry's CRC."""
    body = _JOURNAL_HEAD.pack(
        JOURNAL_MAGIC, JOURNAL_VERSION, 0, header.block_bytes, header.size_bytes,
        header.image_generation, header.sha256, 0,
    )[:-4]
    crc = zlib.crc32(body)
    return body + struct.pack("<I", crc), crc


def decode_journal_header(data: bytes) -> tuple[JournalHeader, int]:
    """Decode a journal header; return ``(header, header CRC)``; raise FormatInvalid."""
    if len(data) < JOURNAL_HEADER_SIZE:
        raise FormatInvalid(f"journal header is {len(data)} bytes, needs {JOURNAL_HEADER_SIZE}")
    magic, version, _, block, size, gen, digest, crc = _JOURNAL_HEAD.unpack_from(data, 0)
    if zlib.crc32(bytes(data[: JOURNAL_HEADER_SIZE - 4])) != crc:
        raise FormatInvalid("journal header CRC mismatch")
    if magic != JOURNAL_MAGIC or version != JOURNAL_VERSION or block == 0:
        raise FormatInvalid(f"unknown journal magic/version {magic!r}/{version}")
    return JournalHeader(block, size, gen, digest), crc


def encode_journal_entry(block_index: int, digest: bytes, header_crc: int) -> bytes:
    """Return one 40-byte journal entry claiming block ``block_index`` hashes to ``digest``."""
    body = _JOURNAL_ENTRY.pack(block_index, digest, 0)[:-4]
    return body + struct.pack("<I", zlib.crc32(body, header_crc))


def decode_journal_entry(data: bytes, header_crc: int) -> tuple[int, bytes] | None:
    """Return ``(block index, digest)`` or None when the entry is torn or garbled."""
    if len(data) < JOURNAL_ENTRY_SIZE:
        return None
    index, digest, crc = _JOURNAL_ENTRY.unpack_from(data, 0)
    if zlib.crc32(bytes(data[: JOURNAL_ENTRY_SIZE - 4]), header_crc) != crc:
        return None
    return index, digest
