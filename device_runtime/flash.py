"""Flash store: two image slots (A/B), a state record, a transfer journal, power-cut safety.

A folder stands in for the device's flash. The store keeps two slots of
``capacity_bytes`` each. A new eigenspace image is streamed into the *inactive*
slot by offset, verified (SHA-256, re-read from the slot), and committed as a
*test* image by one atomic state write; the runtime confirms it once it has
loaded it and shown a frame, and an image that is not confirmed reverts at the
next boot (MCUboot's test/confirm). At boot the active slot's digest is checked
and a bad slot falls back to the other one; an image whose digest is right but
which the device cannot load (format, tag, RAM budget: the caller's checks) is
given up the same way with :meth:`FlashStore.reject_active`. An interrupted transfer resumes,
even across a reboot, from a journal of verified blocks kept beside the
inactive slot. Image contents are opaque bytes here: format checks and the
HMAC tag are the caller's job.

Use
---
::

    store = FlashStore.open(flash_dir)              # formats a new/empty folder
    boot = store.boot()                             # at power-up: BootResult
    # provisioning (IMAGE_STATUS / BEGIN / CHUNK / ACK / VERIFY / COMMIT):
    store.image_status(sha256)                      # -> next offset to send
    writer = store.begin_image(size_bytes=n, sha256=d, image_generation=g)
    writer.write_chunk(offset, data)                # -> next_offset (in memory)
    writer.flush()                                  # -> durable_offset; before an ACK
    writer.verify(); store.commit_test()            # or store.abort_image()
    # runtime, after the first frame of the new image:
    store.confirm()
    # slot commands and status:
    store.set_active("B", force=False); store.revert(force=False)
    store.reject_active()                           # active image does not load: fall back
    format_status(store.status())                   # --status; the dict is --json

Errors are :class:`~device_runtime.errors.FlashError` subclasses, one per
wire error: :class:`ImageTooLarge`, :class:`RollbackRefused` (an older
image generation without ``force``), :class:`BadChunk`, :class:`NoImage`,
:class:`SlotBusy` (the active image is an unconfirmed test image, whose
fallback would be overwritten) and :class:`SlotDigestMismatch`.

On-disk layout
--------------
::

    DIR/state_0.rec   state record copy for even generations (148 bytes)
    DIR/state_1.rec   state record copy for odd generations
    DIR/slot_a.img    slot A: the image's bytes at offsets 0..size-1
    DIR/slot_b.img    slot B
    DIR/journal_a.jnl transfer journal of slot A (exists only while A is written)
    DIR/journal_b.jnl transfer journal of slot B

Where the pieces are: :class:`FlashStore` (this module) owns the slots, the state record
and every decision (which slot, rollback, commit, boot, fallback); the bytes of one
transfer are written and journalled by :class:`~device_runtime.image_writer.ImageWriter`
(``image_writer.py``); the byte formats of the record and the journal are
:mod:`device_runtime._flash_format`; every mutating system call goes through
:mod:`device_runtime._flash_io`; the errors are in :mod:`device_runtime.errors`. This
module stays one file because it is one argument: each method below is a step of the
power-cut reasoning that follows, and reads best next to it.

The byte formats are documented in :mod:`device_runtime._flash_format`. The
state record holds a generation counter, the slot capacity, the active slot,
and per slot: state (empty / test / confirmed / bad, with a reason when bad),
image size, SHA-256, image generation and the boot-attempt counter of a test
image; then its own CRC-32. A journal holds a header naming the session
(block size, image size, SHA-256, image generation) and one entry per
completely received 64 KiB block: the block index and the block's SHA-256,
each entry with its own CRC-32.

State record: two alternating copies
------------------------------------
Record generation ``g`` is written in place into copy ``g % 2`` (``pwrite`` +
``fsync``); the copy holding ``g - 1`` is not touched. At open both copies are
read and the valid one (magic, size, CRC-32, parity of the generation) with
the highest generation wins. A write that is torn by a power cut at any byte
(or a page cache that is lost before the ``fsync`` completes) leaves the copy
being written as the old ``g - 2`` bytes, a mix, or the new ``g`` bytes: a
mix fails its CRC, ``g - 2`` loses to the intact ``g - 1``, so the store sees
exactly the old state or exactly the new one. Since ``g - 1`` was fsynced
before ``g`` was started, both copies can never be broken by one cut. Every
state change is one record write, so every change is atomic.

Provisioning, step by step, and what a cut at each step leaves
--------------------------------------------------------------
1. ``begin_image``: state write marking the target (inactive) slot EMPTY. Cut:
   old state or new; the active slot is untouched either way.
2. Journal created as temp file + ``fsync`` + ``os.replace`` + ``fsync`` of the
   folder, so it is absent or complete. (A fresh session also truncates the slot.)
3. ``write_chunk``: ``pwrite`` into the target slot only. ``flush`` (the
   caller's job before acknowledging; also every 16 blocks) first ``fsync``s
   the slot, then appends one journal entry per completed block and
   ``fsync``s the journal. The slot data is therefore durable *before* any
   entry claiming it can reach the disk, whatever order the page cache is
   written in. A torn last entry fails its CRC and is ignored.
4. Resume (``begin_image`` for the same size and digest, after a disconnect
   or a reboot): every journalled block is re-read from the slot and
   re-hashed; only blocks that still match count, and only their contiguous
   prefix is claimed as ``next_offset``. A different image or ``abort_image``
   replaces / removes the journal.
5. ``verify``: ``flush`` (slot ``fsync``), then re-read the slot and compare its
   SHA-256 with the expected one.
6. ``commit_test``: one state write: target slot TEST with its digest, active
   = target. Cut: old image active (record not yet durable) or the new,
   verified, already durable image active as TEST.
7. ``boot``: a TEST image gets its boot counted by a state write *before*
   the runtime uses it; a TEST image found at boot with a counted boot that
   was never confirmed is marked BAD and the other (confirmed) slot becomes
   active again. Cut: either state is valid.
8. ``confirm``: one state write TEST -> CONFIRMED.
9. ``reject_active`` (the device could not load the active image, whatever its
   state): one state write marking it BAD (not loadable) and making the other
   slot active when that one is CONFIRMED and verifies (else none). Cut: the
   old state (the next boot fails to load it again and rejects it again) or
   the new one.

So at every instant the newest valid record names an active slot whose bytes
were durable before the record was written, and boot re-checks them anyway.

Power cuts versus SIGKILL
-------------------------
The tests kill a process with SIGKILL at random operations, and the crash
hook tears a write at a random byte. SIGKILL cannot lose the page cache: data
written but not yet fsynced survives a killed process, but not a real power
cut. The design does not rely on that survival: no state record or journal
entry is written before the bytes it vouches for have been fsynced (steps 3,
5, 6), new files and renames are followed by an ``fsync`` of the folder, and
a lost unsynced record write is the "old state" case above. A second test
models exactly that loss (``PageCacheModel`` in ``tests/flash_crash_driver.py``):
it cuts at every file operation and rebuilds the folder from, per file and
per folder entry, either the last fsynced or the current version; boot must
then find the old or the new image *without* needing the digest fallback (it
fails if, for example, the slot ``fsync`` before the journal or the commit is
removed). A real disk that lies about ``fsync`` is outside what any design
can cover.

One process (one :class:`FlashStore` object) owns a store at a time; every
state write first re-reads the records and refuses to go on if another
writer changed them. The objects are not thread-safe.
"""

from __future__ import annotations

import dataclasses
import io
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from device_runtime._flash_format import (
    JOURNAL_ENTRY_SIZE,
    JOURNAL_HEADER_SIZE,
    RECORD_SIZE,
    BadReason,
    FormatInvalid,
    JournalHeader,
    SlotInfo,
    SlotState,
    StateRecord,
    decode_journal_entry,
    decode_journal_header,
    decode_record,
    encode_journal_entry,
    encode_journal_header,
    encode_record,
)
from device_runtime._flash_io import (
    NotARegularFile,
    _check_uint,
    _hash_fd,
    _wrap_os_errors,
    check_regular,
    file_ops,
    open_regular,
)
from device_runtime.errors import (
    BadChunk,
    FlashError,
    ImageTooLarge,
    NoImage,
    RollbackRefused,
    SlotBusy,
    SlotDigestMismatch,
)
from device_runtime.image_writer import ImageWriter

__all__ = [
    "DEFAULT_CAPACITY_BYTES",
    "DEFAULT_WINDOW_BYTES",
    "JOURNAL_BLOCK_BYTES",
    "SLOT_NAMES",
    "BadChunk",
    "BadReason",
    "BootResult",
    "FlashStore",
    "ImageTooLarge",
    "ImageWriter",
    "NoImage",
    "RollbackRefused",
    "SlotBusy",
    "SlotDigestMismatch",
    "SlotInfo",
    "SlotState",
    "format_status",
]

DEFAULT_CAPACITY_BYTES = 64 * 1024 * 1024
"""Slot capacity of a new store when ``open`` is not given one (64 MiB)."""
MAX_CAPACITY_BYTES = 1 << 40
JOURNAL_BLOCK_BYTES = 64 * 1024
"""Journal granularity: one SHA-256 entry per completely received block."""
DEFAULT_WINDOW_BYTES = 4 * 1024 * 1024
"""How far beyond ``next_offset`` a chunk may end (bounds out-of-order bookkeeping)."""
SLOT_NAMES = ("A", "B")

_RECORD_FILES = ("state_0.rec", "state_1.rec")
_SLOT_FILES = ("slot_a.img", "slot_b.img")
_JOURNAL_FILES = ("journal_a.jnl", "journal_b.jnl")
_MAX_GENERATION = 2**64 - 1


def _short(digest: bytes | None) -> str:
    return "none" if digest is None else digest.hex()[:16] + "…"


def _slot_index(slot: str) -> int:
    if not isinstance(slot, str) or slot.upper() not in SLOT_NAMES:
        raise ValueError(f"slot={slot!r} must be one of {', '.join(SLOT_NAMES)}")
    return SLOT_NAMES.index(slot.upper())


@dataclass(frozen=True)
class BootResult:
    """What :meth:`FlashStore.boot` decided.

    Attributes
    ----------
    slot : str or None
        Active slot after boot (``"A"``/``"B"``), None when no image can boot.
    state : str
        ``"test"``, ``"confirmed"`` or ``"none"``.
    size_bytes : int
    sha256 : bytes or None
    image_generation : int
    boot_attempts : int
        For a test image: boots counted including this one.
    verified : bool
        True when the active slot's SHA-256 was checked and matched this boot.
    reverted : bool
        An unconfirmed test image was abandoned for the other slot.
    fell_back : bool
        The active slot failed its digest and the other slot took over.
    reason : str
        One or more sentences saying what happened and why.
    """

    slot: str | None
    state: str
    size_bytes: int
    sha256: bytes | None
    image_generation: int
    boot_attempts: int
    verified: bool
    reverted: bool
    fell_back: bool
    reason: str

    @property
    def ok(self) -> bool:
        """True when an image is active."""
        return self.slot is not None


def _boot_check_active(slots: list[SlotInfo], active: int,
                       check: Callable[[int], tuple[bool, str]], notes: list[str]
                       ) -> tuple[int | None, bool]:
    """`FlashStore.boot`'s step 2: an active slot that cannot boot or does not verify is
    marked BAD (in ``slots``) and the other takes over if it is CONFIRMED and verifies (else
    it is BAD too, or no image is active); (the active slot, whether it fell back)."""
    good, detail = (False, f"state {slots[active].state.label} cannot boot")
    if slots[active].bootable:
        good, detail = check(active)
    if good:
        return active, False
    bad, other = active, 1 - active
    slots[bad] = dataclasses.replace(
        slots[bad], state=SlotState.BAD, bad_reason=BadReason.DIGEST_MISMATCH)
    note = f"slot {SLOT_NAMES[bad]}: {detail}"
    if slots[other].state is not SlotState.CONFIRMED:
        notes.append(f"{note}; slot {SLOT_NAMES[other]} is "
                     f"{slots[other].state.label}; no bootable image")
        return None, False
    other_good, other_detail = check(other)
    if other_good:
        notes.append(f"{note}; fell back to slot {SLOT_NAMES[other]}")
        return other, True
    slots[other] = dataclasses.replace(
        slots[other], state=SlotState.BAD, bad_reason=BadReason.DIGEST_MISMATCH)
    notes.append(f"{note}; slot {SLOT_NAMES[other]}: {other_detail}; no bootable image")
    return None, False


class FlashStore:
    """A folder standing in for flash: two slots, a state record, a transfer journal.

    Create or open one with :meth:`open`. The module docstring describes the
    on-disk layout, the formats and why a power cut cannot leave a broken
    image active.

    Examples
    --------
    >>> store = FlashStore.open(folder, capacity_bytes=1 << 20)   # doctest: +SKIP
    >>> writer = store.begin_image(size_bytes=len(img), sha256=hashlib.sha256(img).digest(),
    ...                            image_generation=1)             # doctest: +SKIP
    >>> writer.write_chunk(0, img); writer.verify(); store.commit_test()  # doctest: +SKIP
    >>> store.boot().slot; store.confirm()                         # doctest: +SKIP
    'A'
    """

    def __init__(self, path: Path, record: StateRecord) -> None:
        self.path = path
        self._record = record
        self._writer: ImageWriter | None = None

    # ------------------------------------------------------------------ open
    @classmethod
    def open(
        cls,
        path: str | os.PathLike[str],
        *,
        capacity_bytes: int | None = None,
        create: bool = True,
    ) -> FlashStore:
        """Open the flash store in folder ``path``, formatting it when new.

        Parameters
        ----------
        path : str or path-like
            The folder. A missing folder, or an empty one, is formatted when
            ``create`` is true.
        capacity_bytes : int, optional
            Bytes per slot. Used when formatting (default
            ``DEFAULT_CAPACITY_BYTES``); for an existing store it must equal
            the stored capacity or be None.
        create : bool
            Format a missing or empty folder; when False such a folder is refused.

        Raises
        ------
        FlashError
            Missing folder (``create=False``), not a folder, not a flash store,
            both state-record copies invalid (corrupt), capacity mismatch, or an
            OS error.
        ValueError
            ``capacity_bytes`` outside ``[1, 2**40]``.
        """
        if capacity_bytes is not None:
            _check_uint("capacity_bytes", capacity_bytes, low=1, high=MAX_CAPACITY_BYTES,
                        error=ValueError)
        folder = Path(path)
        try:
            return cls._open(folder, capacity_bytes, create)
        except OSError as exc:
            where = exc.filename or folder
            raise FlashError(f"flash open: {where}: {exc.strerror or exc}") from exc

    @classmethod
    def _open(cls, folder: Path, capacity_bytes: int | None, create: bool) -> FlashStore:
        if not folder.exists():
            if not create:
                raise FlashError(f"flash open: {folder}: no such folder (create=True formats one)")
            folder.mkdir(parents=True)
            file_ops().fsync_dir(str(folder.parent))
        elif not folder.is_dir():
            raise FlashError(f"flash open: {folder}: not a folder")
        record, problems = _read_newest_record(folder)
        if record is None:
            ours = [n for n in (*_RECORD_FILES, *_SLOT_FILES, *_JOURNAL_FILES)
                    if (folder / n).exists()]
            if ours:
                raise FlashError(
                    f"flash open: {folder}: corrupt flash store, no valid state record "
                    f"({'; '.join(problems)})"
                )
            if not create:
                raise FlashError(f"flash open: {folder}: not a flash store (no state record)")
            record = _format(folder, capacity_bytes or DEFAULT_CAPACITY_BYTES)
        elif capacity_bytes is not None and capacity_bytes != record.capacity_bytes:
            raise FlashError(
                f"flash open: {folder}: formatted with {record.capacity_bytes} bytes per slot, "
                f"asked for capacity_bytes={capacity_bytes}"
            )
        return cls(folder, record)

    # ------------------------------------------------------------ properties
    @property
    def capacity_bytes(self) -> int:
        """Bytes per slot."""
        return self._record.capacity_bytes

    @property
    def record_generation(self) -> int:
        """Generation of the state record in use (grows by one per state change)."""
        return self._record.generation

    @property
    def active_slot(self) -> str | None:
        """``"A"``, ``"B"`` or None."""
        active = self._record.active
        return None if active is None else SLOT_NAMES[active]

    @property
    def slots(self) -> tuple[SlotInfo, SlotInfo]:
        """Both slots as the state record describes them (A, B)."""
        return self._record.slots

    @property
    def target_slot(self) -> str:
        """The slot a new image is written to: the inactive one (A when none is active)."""
        return SLOT_NAMES[self._target_index()]

    def _target_index(self) -> int:
        active = self._record.active
        return 0 if active is None else 1 - active

    # ------------------------------------------------------------------ boot
    @_wrap_os_errors("boot")
    def boot(self, *, verify: bool = True) -> BootResult:
        """Choose and check the image to run, as a device does at power-up.

        1. An active TEST image whose test boot was already counted and never
           confirmed is marked BAD (not confirmed) and the other slot becomes
           active, if that one is CONFIRMED (and verifies). With nothing to
           revert to, the test image boots again and the reason says so.
        2. With ``verify``, the active slot is re-hashed; on a mismatch it is
           marked BAD and the other slot takes over if it is CONFIRMED and
           verifies, else no image is active.
        3. A TEST image's boot counter is incremented.

        Any change is written as one state record before returning.

        Parameters
        ----------
        verify : bool
            Re-hash the active slot (streaming; costs one read of the image).

        Returns
        -------
        BootResult
        """
        record = self._record
        slots = list(record.slots)
        active = record.active
        notes: list[str] = []
        checked: dict[int, tuple[bool, str]] = {}
        reverted = fell_back = False

        def check(index: int) -> tuple[bool, str]:
            if not verify:
                return True, "not verified"
            if index not in checked:
                checked[index] = self._check_slot(slots[index], index)
            return checked[index]

        if active is None:
            notes.append("no image is active (" + ", ".join(
                f"slot {s.name} {s.state.label}" for s in slots) + ")")
        elif slots[active].state is SlotState.TEST and slots[active].boot_attempts >= 1:
            other = 1 - active
            name, other_name = SLOT_NAMES[active], SLOT_NAMES[other]
            if slots[other].state is SlotState.CONFIRMED and check(other)[0]:
                slots[active] = dataclasses.replace(
                    slots[active], state=SlotState.BAD, bad_reason=BadReason.NOT_CONFIRMED)
                notes.append(f"slot {name}: test image was not confirmed after its test boot; "
                             f"reverted to slot {other_name}")
                active, reverted = other, True
            else:
                notes.append(f"slot {name}: test image was not confirmed after its test boot, "
                             f"but slot {other_name} has no confirmed image to revert to; "
                             "booting it again")

        if active is not None:
            active, fell_back = _boot_check_active(slots, active, check, notes)

        if active is not None and slots[active].state is SlotState.TEST:
            slots[active] = dataclasses.replace(
                slots[active], boot_attempts=slots[active].boot_attempts + 1)
        new_record = dataclasses.replace(record, active=active, slots=(slots[0], slots[1]))
        if new_record != record:
            self._write_record(new_record)

        if active is None:
            return BootResult(None, "none", 0, None, 0, 0, False, reverted, fell_back,
                              "; ".join(notes))
        info = slots[active]
        verified = verify and check(active)[0]
        if info.state is SlotState.TEST:
            fallback = slots[1 - active]
            then = (f"the next boot reverts to slot {fallback.name}"
                    if fallback.state is SlotState.CONFIRMED
                    else f"slot {fallback.name} has no confirmed image to revert to")
            notes.append(f"slot {info.name}: test image, boot {info.boot_attempts}; confirm it "
                         f"after showing a frame ({then})")
        else:
            notes.append(f"slot {info.name}: confirmed image"
                         + (", digest verified" if verified else ", not verified"))
        return BootResult(info.name, info.state.label, info.size_bytes, info.sha256,
                          info.image_generation, info.boot_attempts, verified, reverted,
                          fell_back, "; ".join(notes))

    # ---------------------------------------------------------- image writes
    @_wrap_os_errors("begin_image")
    def begin_image(
        self,
        *,
        size_bytes: int,
        sha256: bytes,
        image_generation: int,
        force: bool = False,
        window_bytes: int = DEFAULT_WINDOW_BYTES,
    ) -> ImageWriter:
        """Start (or resume) writing an image into the inactive slot.

        The inactive slot is marked EMPTY first. When a journal for the same
        ``(size_bytes, sha256)`` lies beside it, every journalled block is
        re-hashed from the slot and the writer resumes after the verified
        contiguous prefix (``writer.next_offset``); otherwise the session
        starts at 0 with a new journal. An open writer is flushed and closed.

        Parameters
        ----------
        size_bytes : int
            Image size, 1 to ``capacity_bytes``.
        sha256 : bytes
            The image's 32-byte SHA-256 digest.
        image_generation : int
            Refused when lower than the active image's generation, unless ``force``.
        force : bool
            Allow a rollback, and overwriting the fallback slot while the
            active image is an unconfirmed test image.
        window_bytes : int
            How far beyond ``next_offset`` a chunk may end.

        Returns
        -------
        ImageWriter

        Raises
        ------
        ImageTooLarge, RollbackRefused, SlotBusy, FlashError
        """
        _check_uint("size_bytes", size_bytes, low=1, high=_MAX_GENERATION, error=FlashError)
        if size_bytes > self.capacity_bytes:
            raise ImageTooLarge(
                f"flash begin_image: the image is {size_bytes} bytes but a slot holds at most "
                f"{self.capacity_bytes} bytes ({self.path})"
            )
        if not isinstance(sha256, bytes | bytearray) or len(sha256) != 32:
            got = len(sha256) if isinstance(sha256, bytes | bytearray) else type(sha256).__name__
            raise FlashError(f"flash begin_image: sha256 must be 32 bytes, got {got}")
        _check_uint("image_generation", image_generation, low=0, high=_MAX_GENERATION,
                    error=FlashError)
        _check_uint("window_bytes", window_bytes, low=1, high=MAX_CAPACITY_BYTES,
                    error=ValueError)
        sha256 = bytes(sha256)
        self._check_may_replace(image_generation, force, "begin_image")
        self._close_writer()

        target = self._target_index()
        record = self._record
        if record.slots[target].state is not SlotState.EMPTY:
            slots = list(record.slots)
            slots[target] = SlotInfo.empty(SLOT_NAMES[target])
            self._write_record(dataclasses.replace(record, slots=(slots[0], slots[1])))
        if record.active is not None:
            self._remove_journal(record.active)  # stale: its slot is active now

        header = JournalHeader(JOURNAL_BLOCK_BYTES, size_bytes, image_generation, sha256)
        old = self._read_journal_header(target)
        same = (old is not None and old[0].block_bytes == JOURNAL_BLOCK_BYTES
                and old[0].size_bytes == size_bytes and old[0].sha256 == sha256)
        slot_path = self._slot_path(target)
        created = not slot_path.exists()
        slot_fd = file_ops().open(str(slot_path), os.O_RDWR | os.O_CREAT)
        try:
            if created:  # the new folder entry must be durable before anything vouches for it
                file_ops().fsync_dir(str(self.path))
            if not same:
                file_ops().ftruncate(slot_fd, 0)
                file_ops().fsync(slot_fd)
            verified, journal_fd, journal_end = self._new_journal(
                target, header, old if same else None, slot_fd)
        except BaseException:
            os.close(slot_fd)
            raise
        self._writer = ImageWriter(
            store=self, slot=SLOT_NAMES[target], slot_index=target, header=header, force=force,
            slot_fd=slot_fd, journal_fd=journal_fd, journal_end=journal_end,
            verified_blocks=verified, window_bytes=window_bytes,
        )
        return self._writer

    @_wrap_os_errors("image_status")
    def image_status(self, sha256: bytes) -> int:
        """Return the next offset needed to finish the image with digest ``sha256``.

        An open writer for that image answers its ``next_offset``. Otherwise
        the inactive slot's journal is consulted (read-only): its journalled
        blocks are re-hashed from the slot and the verified contiguous prefix
        is returned. 0 when there is no session for that image. Whether the
        *active* slot already holds the image is in :attr:`slots`.
        """
        writer = self._writer
        if writer is not None and not writer.closed and writer.sha256 == bytes(sha256):
            return writer.next_offset
        target = self._target_index()
        old = self._read_journal_header(target)
        if old is None:
            return 0
        header = old[0]
        if header.sha256 != bytes(sha256) or header.block_bytes != JOURNAL_BLOCK_BYTES:
            return 0
        try:
            fd = open_regular(self._slot_path(target))
        except (FileNotFoundError, NotARegularFile):
            return 0
        try:
            verified = self._scan_journal(target, header, old[1], fd, None, 0)[0]
        finally:
            os.close(fd)
        prefix = verified.find(0)
        prefix = len(verified) if prefix < 0 else prefix
        return min(prefix * header.block_bytes, header.size_bytes)

    @_wrap_os_errors("commit_test")
    def commit_test(self) -> None:
        """Make the verified, written slot active as a TEST image (one atomic state write).

        The previously active slot keeps its state (the fallback), unless it was
        itself an unconfirmed test image, which becomes BAD (abandoned).

        Raises
        ------
        NoImage
            No writer, or its image is not verified.
        RollbackRefused, SlotBusy
            The active image changed since ``begin_image`` in a way it would refuse.
        """
        writer = self._writer
        if writer is None or writer.closed:
            raise NoImage("flash commit_test: no image session (begin_image, write, verify first)")
        if not writer.verified:
            raise NoImage(
                f"flash commit_test: the image in slot {writer.slot} is not verified "
                f"(received {writer.next_offset} of {writer.size_bytes} bytes; call verify)"
            )
        self._check_may_replace(writer.image_generation, writer.force, "commit_test")
        writer.flush()
        file_ops().fsync(writer._slot_fd)
        record = self._record
        slots = list(record.slots)
        target = writer.slot_index
        slots[target] = SlotInfo(
            name=SLOT_NAMES[target], state=SlotState.TEST, size_bytes=writer.size_bytes,
            sha256=writer.sha256, image_generation=writer.image_generation,
        )
        previous = record.active
        if previous is not None and slots[previous].state is SlotState.TEST:
            slots[previous] = dataclasses.replace(
                slots[previous], state=SlotState.BAD, bad_reason=BadReason.ABANDONED)
        self._write_record(dataclasses.replace(record, active=target, slots=(slots[0], slots[1])))
        writer._close()
        self._writer = None
        self._remove_journal(target)

    @_wrap_os_errors("abort_image")
    def abort_image(self) -> None:
        """Drop the current image session: close the writer and remove the journal.

        The inactive slot stays EMPTY; the next ``begin_image`` starts at offset 0.
        Does nothing when there is no session.
        """
        writer, self._writer = self._writer, None
        if writer is not None:
            writer._close()
        self._remove_journal(self._target_index())

    # ---------------------------------------------------------- slot commands
    @_wrap_os_errors("confirm")
    def confirm(self) -> None:
        """Mark the active TEST image CONFIRMED (the runtime calls this after showing a frame).

        Does nothing when the active image is already confirmed.

        Raises
        ------
        NoImage
            No image is active.
        """
        record = self._record
        if record.active is None:
            raise NoImage(f"flash confirm: no image is active ({self.path})")
        info = record.slots[record.active]
        if info.state is SlotState.CONFIRMED:
            return
        slots = list(record.slots)
        slots[record.active] = dataclasses.replace(info, state=SlotState.CONFIRMED)
        self._write_record(dataclasses.replace(record, slots=(slots[0], slots[1])))

    @_wrap_os_errors("set_active")
    def set_active(self, slot: str, *, force: bool = False) -> None:
        """Make ``slot`` active as a TEST image (it must be confirmed after its test boot).

        The slot's digest is checked first. The slot that was active keeps
        its state if confirmed (it is the fallback); an unconfirmed test image
        becomes BAD (abandoned). Activating the active slot does nothing.

        Raises
        ------
        NoImage
            The slot is empty.
        SlotDigestMismatch
            The slot's bytes do not match its recorded digest.
        SlotBusy
            The slot is marked BAD and ``force`` is not given.
        RollbackRefused
            Its image generation is lower than the active one and ``force`` is not given.
        """
        index = _slot_index(slot)
        record = self._record
        if index == record.active:
            return
        info = record.slots[index]
        name = SLOT_NAMES[index]
        if info.state is SlotState.EMPTY:
            raise NoImage(f"flash set_active: slot {name} is empty")
        if info.state is SlotState.BAD and not force:
            raise SlotBusy(f"flash set_active: slot {name} is marked bad "
                           f"({info.bad_reason.description}); pass force to try it again")
        self._check_rollback(info.image_generation, force, f"set_active {name}")
        good, detail = self._check_slot(info, index)
        if not good:
            raise SlotDigestMismatch(f"flash set_active: slot {name}: {detail}")
        slots = list(record.slots)
        slots[index] = dataclasses.replace(info, state=SlotState.TEST, boot_attempts=0,
                                           bad_reason=BadReason.NONE)
        previous = record.active
        if previous is not None and slots[previous].state is SlotState.TEST:
            slots[previous] = dataclasses.replace(
                slots[previous], state=SlotState.BAD, bad_reason=BadReason.ABANDONED)
        self._write_record(dataclasses.replace(record, active=index, slots=(slots[0], slots[1])))
        self._remove_journal(index)

    @_wrap_os_errors("revert")
    def revert(self, *, force: bool = False) -> None:
        """Give up the active image and go back to the other, confirmed slot.

        The abandoned slot becomes BAD (reverted). Reverting from a confirmed
        image to an older generation is a rollback and needs ``force``;
        reverting an unconfirmed test image never does.

        Raises
        ------
        NoImage
            No image is active, or the other slot holds no confirmed image.
        SlotDigestMismatch
            The other slot's bytes do not match its digest.
        RollbackRefused
        """
        record = self._record
        if record.active is None:
            raise NoImage(f"flash revert: no image is active ({self.path})")
        active, other = record.active, 1 - record.active
        current, fallback = record.slots[active], record.slots[other]
        if fallback.state is not SlotState.CONFIRMED:
            raise NoImage(f"flash revert: slot {SLOT_NAMES[other]} holds no confirmed image "
                          f"(it is {fallback.state.label})")
        if current.state is SlotState.CONFIRMED:
            self._check_rollback(fallback.image_generation, force, "revert")
        good, detail = self._check_slot(fallback, other)
        if not good:
            raise SlotDigestMismatch(f"flash revert: slot {SLOT_NAMES[other]}: {detail}")
        slots = list(record.slots)
        slots[active] = dataclasses.replace(current, state=SlotState.BAD,
                                            bad_reason=BadReason.REVERTED)
        self._write_record(dataclasses.replace(record, active=other, slots=(slots[0], slots[1])))

    @_wrap_os_errors("reject_active")
    def reject_active(self) -> str | None:
        """Give up the active image because it cannot be loaded; fall back like MCUboot.

        The device calls this when the active slot's bytes match their digest but the
        image does not load (format, missing or wrong tag, RAM budget). The slot becomes
        BAD (``NOT_LOADABLE``) and the other slot becomes active if it holds a CONFIRMED
        image that verifies; otherwise no image is active. No rollback check: like the
        boot's digest fallback, a device that cannot run its newest image runs the one it
        ran before. One state write (power-cut safe).

        Returns
        -------
        str or None
            The slot active now (``"A"``/``"B"``), or None when no image is active.

        Raises
        ------
        NoImage
            No image is active.
        """
        record = self._record
        if record.active is None:
            raise NoImage(f"flash reject_active: no image is active ({self.path})")
        bad, other = record.active, 1 - record.active
        slots = list(record.slots)
        slots[bad] = dataclasses.replace(slots[bad], state=SlotState.BAD,
                                         bad_reason=BadReason.NOT_LOADABLE)
        active: int | None = None
        if slots[other].state is SlotState.CONFIRMED:
            if self._check_slot(slots[other], other)[0]:
                active = other
            else:
                slots[other] = dataclasses.replace(slots[other], state=SlotState.BAD,
                                                   bad_reason=BadReason.DIGEST_MISMATCH)
        self._write_record(dataclasses.replace(record, active=active, slots=(slots[0], slots[1])))
        return None if active is None else SLOT_NAMES[active]

    # ----------------------------------------------------------------- reads
    @_wrap_os_errors("open_slot")
    def open_slot(self, slot: str) -> io.BufferedReader:
        """Open ``slot``'s image for streaming reads (exactly ``size_bytes`` bytes, seekable).

        Raises
        ------
        NoImage
            The slot is empty.
        """
        index = _slot_index(slot)
        info = self._record.slots[index]
        if info.state is SlotState.EMPTY:
            raise NoImage(f"flash open_slot: slot {SLOT_NAMES[index]} is empty ({self.path})")
        fd = open_regular(self._slot_path(index))
        return io.BufferedReader(_SlotReader(fd, info.size_bytes), buffer_size=64 * 1024)

    @_wrap_os_errors("open_active")
    def open_active(self) -> io.BufferedReader:
        """Open the active image for streaming reads (exactly ``size_bytes`` bytes, seekable).

        Raises
        ------
        NoImage
            No image is active.
        """
        record = self._record
        if record.active is None:
            raise NoImage(f"flash open_active: no image is active ({self.path})")
        info = record.slots[record.active]
        fd = open_regular(self._slot_path(record.active))
        return io.BufferedReader(_SlotReader(fd, info.size_bytes), buffer_size=64 * 1024)

    @_wrap_os_errors("status")
    def status(
        self,
        *,
        verify: bool = True,
        check_image: Callable[[io.BufferedReader], str | None] | None = None,
    ) -> dict[str, Any]:
        """Describe the store for ``eigencast-device --status [--json]`` (changes nothing).

        Parameters
        ----------
        verify : bool
            Re-hash every non-empty slot (and the journalled blocks).
        check_image : callable, optional
            With ``verify``: ``check_image(stream) -> None`` when the slot's image (whose
            digest matched) would be loaded by the device, else a few words why not (its
            format, tag or RAM checks). Without it ``verifies`` means the digest only.

        Returns
        -------
        dict
            ``path``, ``capacity_bytes``, ``record_generation``, ``active_slot``;
            ``slots``: a list of dicts with ``slot``, ``active``, ``state``,
            ``size_bytes``, ``sha256`` (hex or None), ``image_generation``,
            ``boot_attempts``, ``bad_reason`` (text or None), ``verifies``
            (bool, or None when empty or not checked: the digest matches and, with
            ``check_image``, the device would load it) and ``problem`` (why it does not
            verify, else None); ``journal``: None or a dict
            with ``slot``, ``size_bytes``, ``sha256``, ``image_generation`` and
            ``verified_offset`` (None when not checked); ``boots``: the slot whose image
            a device would show after booting (what :meth:`boot` and the device's load
            fallback choose from these checks), or None. JSON-serialisable.
        """
        record = self._record
        slots = []
        for index, info in enumerate(record.slots):
            verifies, problem = None, None
            if verify and info.state is not SlotState.EMPTY:
                verifies, detail = self._check_slot(info, index)
                if not verifies:
                    problem = detail
                elif check_image is not None:
                    with self.open_slot(info.name) as stream:
                        problem = check_image(stream)
                    verifies = problem is None
            slots.append({
                "slot": info.name,
                "active": record.active == index,
                "state": info.state.label,
                "size_bytes": info.size_bytes,
                "sha256": None if info.sha256 is None else info.sha256.hex(),
                "image_generation": info.image_generation,
                "boot_attempts": info.boot_attempts,
                "bad_reason": info.bad_reason.description or None,
                "verifies": verifies,
                "problem": problem,
            })
        journal = None
        target = self._target_index()
        old = self._read_journal_header(target)
        if old is not None:
            header = old[0]
            journal = {
                "slot": SLOT_NAMES[target],
                "size_bytes": header.size_bytes,
                "sha256": header.sha256.hex(),
                "image_generation": header.image_generation,
                "verified_offset": self.image_status(header.sha256) if verify else None,
            }
        return {
            "path": str(self.path),
            "capacity_bytes": record.capacity_bytes,
            "record_generation": record.generation,
            "active_slot": self.active_slot,
            "boots": _would_boot(record, [slot["verifies"] is not False for slot in slots]),
            "slots": slots,
            "journal": journal,
        }

    # ------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Flush and close an open writer. The store object stays usable."""
        self._close_writer()

    def __enter__(self) -> FlashStore:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"FlashStore({str(self.path)!r}, active={self.active_slot}, "
                f"capacity_bytes={self.capacity_bytes})")

    # --------------------------------------------------------------- private
    def _slot_path(self, index: int) -> Path:
        return self.path / _SLOT_FILES[index]

    def _journal_path(self, index: int) -> Path:
        return self.path / _JOURNAL_FILES[index]

    def _close_writer(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None and not writer.closed:
            try:
                writer.flush()
            finally:
                writer._close()

    def _check_rollback(self, image_generation: int, force: bool, operation: str) -> None:
        active = self._record.active
        if force or active is None:
            return
        current = self._record.slots[active]
        if image_generation < current.image_generation:
            raise RollbackRefused(
                f"flash {operation}: image generation {image_generation} is older than the "
                f"active image's generation {current.image_generation} (slot {current.name}); "
                "rollback needs force"
            )

    def _check_may_replace(self, image_generation: int, force: bool, operation: str) -> None:
        self._check_rollback(image_generation, force, operation)
        active = self._record.active
        if force or active is None:
            return
        current = self._record.slots[active]
        if current.state is SlotState.TEST:
            raise SlotBusy(
                f"flash {operation}: slot {current.name} holds a test image that is not "
                f"confirmed yet, and slot {SLOT_NAMES[1 - active]} is its fallback; confirm "
                "it (or reboot so it reverts) first, or pass force"
            )

    def _write_record(self, record: StateRecord) -> None:
        """Write ``record`` as the next generation into its copy file and fsync it."""
        on_disk, _ = _read_newest_record(self.path)
        if on_disk is None or on_disk.generation != self._record.generation:
            found = "no valid record" if on_disk is None else f"generation {on_disk.generation}"
            raise FlashError(
                f"flash: {self.path}: the state record changed underneath this store (expected "
                f"generation {self._record.generation}, found {found}); one process at a time "
                "may own a flash folder: open it again"
            )
        generation = self._record.generation + 1
        record = dataclasses.replace(record, generation=generation)
        path = self.path / _RECORD_FILES[generation % 2]
        created = not path.exists()
        # non-blocking: a FIFO in the copy's place fails at once instead of waiting for a reader
        fd = file_ops().open(str(path), os.O_WRONLY | os.O_CREAT | os.O_NONBLOCK)
        try:
            check_regular(fd, str(path))
            file_ops().pwrite(fd, encode_record(record), 0)
            file_ops().fsync(fd)
        finally:
            os.close(fd)
        if created:
            file_ops().fsync_dir(str(self.path))
        self._record = record

    def _hash_slot(self, index: int, size_bytes: int) -> tuple[bytes | None, int]:
        """SHA-256 of the slot's first ``size_bytes`` bytes, or (None, bytes present) if short
        (NotARegularFile when the slot's name holds no file)."""
        try:
            fd = open_regular(self._slot_path(index))
        except FileNotFoundError:
            return None, 0
        try:
            return _hash_fd(fd, 0, size_bytes)
        finally:
            os.close(fd)

    def _check_slot(self, info: SlotInfo, index: int) -> tuple[bool, str]:
        """(digest matches, a few words why not) for a slot with a recorded digest."""
        if info.sha256 is None:
            return False, "no digest recorded"
        try:
            digest, have = self._hash_slot(index, info.size_bytes)
        except NotARegularFile as exc:
            return False, f"slot file {exc.filename}: {exc.strerror}"
        if digest is None:
            return False, f"slot file holds {have} of the image's {info.size_bytes} bytes"
        if digest != info.sha256:
            return False, (f"digest mismatch (recorded {_short(info.sha256)}, "
                           f"read {_short(digest)})")
        return True, "digest verified"

    def _read_journal_header(self, index: int) -> tuple[JournalHeader, int] | None:
        """The journal's header and CRC; None when absent, not a file, invalid, or claiming
        an image larger than a slot (nothing else about it can be true then)."""
        try:
            with os.fdopen(open_regular(self._journal_path(index)), "rb") as handle:
                data = handle.read(JOURNAL_HEADER_SIZE)
        except (FileNotFoundError, NotARegularFile):
            return None
        try:
            header = decode_journal_header(data)
        except FormatInvalid:
            return None
        return header if header[0].size_bytes <= self.capacity_bytes else None

    def _scan_journal(
        self,
        index: int,
        header: JournalHeader,
        header_crc: int,
        slot_fd: int,
        out_fd: int | None,
        out_crc: int,
    ) -> tuple[bytearray, int]:
        """Re-hash every journalled block; copy the verified entries to ``out_fd``.

        Returns a bytearray with 1 per verified block and the bytes written to
        ``out_fd`` after its header. Reading stops at the first torn entry.
        """
        block_bytes = header.block_bytes
        n_blocks = -(-header.size_bytes // block_bytes)
        verified = bytearray(n_blocks)
        written = 0
        batch_entries = 1024
        with os.fdopen(open_regular(self._journal_path(index)), "rb") as handle:
            handle.seek(JOURNAL_HEADER_SIZE)
            done = False
            while not done:
                batch = handle.read(batch_entries * JOURNAL_ENTRY_SIZE)
                if not batch:
                    break
                for start in range(0, len(batch), JOURNAL_ENTRY_SIZE):
                    entry = decode_journal_entry(batch[start:start + JOURNAL_ENTRY_SIZE],
                                                 header_crc)
                    if entry is None:
                        done = True
                        break
                    block, digest = entry
                    if block >= n_blocks or verified[block]:
                        continue
                    offset = block * block_bytes
                    length = min(block_bytes, header.size_bytes - offset)
                    actual, _ = _hash_fd(slot_fd, offset, length)
                    if actual != digest:
                        continue
                    verified[block] = 1
                    if out_fd is not None:
                        file_ops().pwrite(out_fd, encode_journal_entry(block, digest, out_crc),
                                          JOURNAL_HEADER_SIZE + written)
                        written += JOURNAL_ENTRY_SIZE
        return verified, written

    def _new_journal(
        self,
        index: int,
        header: JournalHeader,
        old: tuple[JournalHeader, int] | None,
        slot_fd: int,
    ) -> tuple[bytearray, int, int]:
        """Write a fresh (or compacted) journal atomically; return (verified, fd, end offset)."""
        path = self._journal_path(index)
        tmp = str(path) + ".tmp"
        header_bytes, header_crc = encode_journal_header(header)
        n_blocks = -(-header.size_bytes // header.block_bytes)
        ops = file_ops()
        fd = ops.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC)
        try:
            ops.pwrite(fd, header_bytes, 0)
            verified, written = bytearray(n_blocks), 0
            if old is not None:
                verified, written = self._scan_journal(index, old[0], old[1], slot_fd, fd,
                                                       header_crc)
            ops.fsync(fd)
            ops.replace(tmp, str(path))
            ops.fsync_dir(str(self.path))
        except BaseException:
            os.close(fd)
            raise
        return verified, fd, JOURNAL_HEADER_SIZE + written

    def _remove_journal(self, index: int) -> None:
        path = self._journal_path(index)
        if path.exists():
            file_ops().unlink(str(path))
            file_ops().fsync_dir(str(self.path))


class _SlotReader(io.RawIOBase):
    """Raw, seekable reader of the first ``size_bytes`` bytes of a slot file."""

    def __init__(self, fd: int, size_bytes: int) -> None:
        super().__init__()
        self._fd = fd
        self._size = size_bytes
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        count = max(0, min(len(view), self._size - self._pos))
        if count == 0:
            return 0
        got = os.preadv(self._fd, [view[:count]], self._pos)
        self._pos += got
        return got

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._size}[whence]
        if base + offset < 0:
            raise ValueError(f"seek to {base + offset}: negative position")
        self._pos = base + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def close(self) -> None:
        if not self.closed:
            os.close(self._fd)
        super().close()


def _read_newest_record(folder: Path) -> tuple[StateRecord | None, list[str]]:
    """The valid state-record copy with the highest generation, and why others failed."""
    best: StateRecord | None = None
    problems = []
    for index, name in enumerate(_RECORD_FILES):
        try:
            with os.fdopen(open_regular(folder / name), "rb") as handle:
                data = handle.read(RECORD_SIZE)
        except FileNotFoundError:
            problems.append(f"{name}: missing")
            continue
        except NotARegularFile as exc:
            problems.append(f"{name}: {exc.strerror}")
            continue
        try:
            record = decode_record(data, copy_index=index, names=SLOT_NAMES)
        except FormatInvalid as exc:
            problems.append(f"{name}: {exc}")
            continue
        if best is None or record.generation > best.generation:
            best = record
    return best, problems


def _would_boot(record: StateRecord, good: list[bool]) -> str | None:
    """The slot :meth:`FlashStore.boot` (then the device's load check) would end on, given
    which slots verify (``good``; unchecked ones count as good)."""
    if record.active is None:
        return None
    active, other = record.slots[record.active], record.slots[1 - record.active]
    fallback = other.state is SlotState.CONFIRMED and good[1 - record.active]
    if active.state is SlotState.TEST and active.boot_attempts >= 1 and fallback:
        return other.name
    if active.bootable and good[record.active]:
        return active.name
    return other.name if fallback else None


def _format(folder: Path, capacity_bytes: int) -> StateRecord:
    """Write generation 0 into copy 0 atomically (temp, fsync, replace, fsync folder)."""
    record = StateRecord(generation=0, capacity_bytes=capacity_bytes, active=None,
                         slots=(SlotInfo.empty("A"), SlotInfo.empty("B")))
    path = folder / _RECORD_FILES[0]
    tmp = str(path) + ".tmp"
    ops = file_ops()
    fd = ops.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        ops.pwrite(fd, encode_record(record), 0)
        ops.fsync(fd)
    finally:
        os.close(fd)
    ops.replace(tmp, str(path))
    ops.fsync_dir(str(folder))
    return record


def format_status(status: dict[str, Any]) -> str:
    """Render :meth:`FlashStore.status`'s dict as the lines ``--status`` prints."""
    lines = [f"flash {status['path']}: {status['capacity_bytes']} bytes per slot, "
             f"state record generation {status['record_generation']}, "
             f"active slot {status['active_slot'] or 'none'}"]
    for slot in status["slots"]:
        verifies = {True: "verifies", False: "DOES NOT VERIFY", None: "not checked"}
        text = (f"  slot {slot['slot']}{' *' if slot['active'] else '  '} {slot['state']:<9}")
        if slot["state"] != "empty":
            text += (f" {slot['size_bytes']} bytes, generation {slot['image_generation']}, "
                     f"sha256 {slot['sha256'][:16]}…, {verifies[slot['verifies']]}")
            if slot.get("problem"):
                text += f": {slot['problem']}"
            if slot["state"] == "test":
                text += f", boot attempts {slot['boot_attempts']}"
            if slot["bad_reason"]:
                text += f" ({slot['bad_reason']})"
        lines.append(text)
    if "boots" in status:
        boots, active = status["boots"], status["active_slot"]
        lines.append(f"  boots slot {boots}" + (f" (slot {active} does not load)"
                                                if active and boots != active else "")
                     if boots else "  boots no image (nothing to show until one is provisioned)")
    journal = status.get("journal")
    if journal:
        progress = journal["verified_offset"]
        done = "not checked" if progress is None else f"{progress} of {journal['size_bytes']} bytes"
        lines.append(f"  transfer into slot {journal['slot']}: sha256 {journal['sha256'][:16]}…, "
                     f"generation {journal['image_generation']}, verified {done}")
    return "\n".join(lines)
