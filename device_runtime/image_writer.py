"""Image writer: stream one image into the inactive flash slot, journalling verified blocks.

:meth:`FlashStore.begin_image <device_runtime.flash.FlashStore.begin_image>` opens (or
resumes) a transfer session and hands back an :class:`ImageWriter`; the store keeps the
slots, the state record and the decisions (which slot, rollback, commit), the writer the
bytes of one transfer:

* :meth:`ImageWriter.write_chunk` stores a chunk at its offset with ``pwrite``; chunks may
  arrive in any order inside the window and repeat (bytes already received are compared,
  never rewritten), and the received ranges are kept as a sorted list of disjoint ranges
  so :attr:`ImageWriter.next_offset` is the end of the contiguous prefix;
* :meth:`ImageWriter.flush` makes completed 64 KiB blocks durable: ``fsync`` of the slot
  first, then one journal entry per block (its SHA-256, CRC-protected) and ``fsync`` of
  the journal, so no entry can vouch for bytes that are not on disk
  (:mod:`device_runtime.flash`, "Provisioning, step by step", step 3);
* :meth:`ImageWriter.verify` re-reads the slot and compares its SHA-256 (step 5).

The journal's byte format is :mod:`device_runtime._flash_format`; every mutating system
call goes through :mod:`device_runtime._flash_io` (the power-cut tests' seam).
"""

from __future__ import annotations

import bisect
import os
from typing import TYPE_CHECKING

from device_runtime._flash_format import (
    JOURNAL_ENTRY_SIZE,
    JournalHeader,
    encode_journal_entry,
    encode_journal_header,
)
from device_runtime._flash_io import _check_uint, _hash_fd, _wrap_os_errors, file_ops
from device_runtime.errors import BadChunk, NoImage

if TYPE_CHECKING:
    from device_runtime.flash import FlashStore

__all__ = ["FLUSH_EVERY_BLOCKS", "ImageWriter"]

FLUSH_EVERY_BLOCKS = 16
"""Completed blocks that trigger an automatic :meth:`ImageWriter.flush`."""
_MAX_OFFSET = 2**64 - 1


class ImageWriter:
    """Streams one image into the inactive slot; made by :meth:`FlashStore.begin_image`.

    Chunks may arrive in any order inside the window, and repeat: a byte
    range already received must be sent again identically (it is compared,
    not rewritten). Completed 64 KiB blocks are journalled by :meth:`flush`.

    Attributes
    ----------
    slot : str
        The slot being written (``"A"``/``"B"``).
    size_bytes : int
    sha256 : bytes
    image_generation : int
    force : bool
    """

    def __init__(
        self,
        *,
        store: FlashStore,
        slot: str,
        slot_index: int,
        header: JournalHeader,
        force: bool,
        slot_fd: int,
        journal_fd: int,
        journal_end: int,
        verified_blocks: bytearray,
        window_bytes: int,
    ) -> None:
        self._store = store
        self.slot_index = slot_index
        self.slot = slot
        self.path = store._slot_path(slot_index)
        self.size_bytes = header.size_bytes
        self.sha256 = header.sha256
        self.image_generation = header.image_generation
        self.force = force
        self._header_crc = encode_journal_header(header)[1]
        self._block_bytes = header.block_bytes
        self._slot_fd = slot_fd
        self._journal_fd: int | None = journal_fd
        self._journal_end = journal_end
        self._window_bytes = window_bytes
        # Per block: 0 incomplete, 1 complete and waiting for flush, 2 journalled.
        self._blocks = bytearray(2 if v else 0 for v in verified_blocks)
        self._pending: list[int] = []
        self._next = 0
        self._starts: list[int] = []  # received ranges beyond _next, sorted, disjoint
        self._ends: list[int] = []
        self._durable_blocks = 0
        self._verified = False
        self.closed = False
        for block, state in enumerate(self._blocks):
            if state == 2:
                start = block * self._block_bytes
                self._add_range(start, min(start + self._block_bytes, self.size_bytes))
        self._advance_durable()

    # ------------------------------------------------------------ properties
    @property
    def next_offset(self) -> int:
        """End of the contiguous prefix received so far (the offset to acknowledge)."""
        return self._next

    @property
    def durable_offset(self) -> int:
        """End of the contiguous prefix whose blocks are fsynced and journalled."""
        return min(self._durable_blocks * self._block_bytes, self.size_bytes)

    @property
    def verified(self) -> bool:
        """True after :meth:`verify` succeeded (and nothing was written since)."""
        return self._verified

    # ----------------------------------------------------------------- write
    @_wrap_os_errors("write_chunk")
    def write_chunk(self, offset: int, data: bytes | bytearray | memoryview) -> int:
        """Store ``data`` at byte ``offset`` of the image; return :attr:`next_offset`.

        Idempotent by offset: bytes already received are compared with
        ``data`` and not rewritten.

        Raises
        ------
        BadChunk
            The chunk runs past the image, ends more than ``window_bytes``
            beyond ``next_offset``, or differs from bytes received before.
        NoImage
            The writer is closed.
        """
        self._check_open("write_chunk")
        _check_uint("offset", offset, low=0, high=_MAX_OFFSET, error=BadChunk)
        view = memoryview(data).cast("B")
        end = offset + len(view)
        if end > self.size_bytes:
            raise BadChunk(f"flash write_chunk: offset {offset} + {len(view)} bytes runs past "
                           f"the image size {self.size_bytes}")
        if end > self._next + self._window_bytes:
            raise BadChunk(f"flash write_chunk: offset {offset} + {len(view)} bytes ends beyond "
                           f"the window (next_offset {self._next} + {self._window_bytes} bytes)")
        if not view:
            return self._next
        fresh = self._uncovered(offset, end)
        cursor = offset
        for start, stop in [*fresh, (end, end)]:  # compare the covered gaps between pieces
            if cursor < start:
                existing = os.pread(self._slot_fd, start - cursor, cursor)
                if existing != view[cursor - offset:start - offset]:
                    raise BadChunk(f"flash write_chunk: the {start - cursor} bytes at offset "
                                   f"{cursor} differ from the bytes received there before")
            cursor = stop
        for start, stop in fresh:
            file_ops().pwrite(self._slot_fd, view[start - offset:stop - offset], start)
            self._add_range(start, stop)
            self._verified = False
        first, last = offset // self._block_bytes, (end - 1) // self._block_bytes
        for block in range(first, last + 1):
            if self._blocks[block] == 0:
                start = block * self._block_bytes
                if self._covered(start, min(start + self._block_bytes, self.size_bytes)):
                    self._blocks[block] = 1
                    self._pending.append(block)
        if len(self._pending) >= FLUSH_EVERY_BLOCKS:
            self.flush()
        return self._next

    @_wrap_os_errors("flush")
    def flush(self) -> int:
        """Make completed blocks durable and journalled; return :attr:`durable_offset`.

        Order: ``fsync`` the slot, then append one journal entry per completed
        block (hash re-read from the slot), then ``fsync`` the journal. Call it
        before acknowledging progress that must survive a reboot.
        """
        if self.closed or self._journal_fd is None:
            return self.durable_offset
        if self._pending:
            ops = file_ops()
            ops.fsync(self._slot_fd)
            for block in sorted(self._pending):
                start = block * self._block_bytes
                digest, _ = _hash_fd(self._slot_fd, start,
                                     min(self._block_bytes, self.size_bytes - start))
                entry = encode_journal_entry(block, digest or bytes(32), self._header_crc)
                ops.pwrite(self._journal_fd, entry, self._journal_end)
                self._journal_end += JOURNAL_ENTRY_SIZE
            ops.fsync(self._journal_fd)
            for block in self._pending:
                self._blocks[block] = 2
            self._pending.clear()
            self._advance_durable()
        return self.durable_offset

    @_wrap_os_errors("verify")
    def verify(self) -> bool:
        """Flush, re-read the whole slot and compare its SHA-256 with the expected digest.

        Returns False while bytes are missing (the writer stays usable). A
        complete image whose digest differs returns False, removes the journal
        and closes this writer: the next ``begin_image`` starts at 0.
        """
        self._check_open("verify")
        self.flush()
        if self._next < self.size_bytes:
            return False
        digest, _ = _hash_fd(self._slot_fd, 0, self.size_bytes)
        if digest == self.sha256:
            self._verified = True
            return True
        store = self._store
        if store._writer is self:
            store.abort_image()
        else:
            self._close()
        return False

    def close(self) -> None:
        """Flush and close (the journal stays, so the session can resume)."""
        if self.closed:
            return
        try:
            self.flush()
        finally:
            self._close()
            if self._store._writer is self:
                self._store._writer = None

    def __repr__(self) -> str:
        return (f"ImageWriter(slot={self.slot}, next_offset={self._next}, "
                f"size_bytes={self.size_bytes}, durable_offset={self.durable_offset})")

    # --------------------------------------------------------------- private
    def _check_open(self, operation: str) -> None:
        if self.closed:
            raise NoImage(f"flash {operation}: this image session is closed "
                          "(superseded, committed, aborted or failed verification)")

    def _close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for fd in (self._slot_fd, self._journal_fd):
            if fd is not None:
                os.close(fd)
        self._journal_fd = None

    def _advance_durable(self) -> None:
        blocks = self._blocks
        while self._durable_blocks < len(blocks) and blocks[self._durable_blocks] == 2:
            self._durable_blocks += 1

    def _add_range(self, start: int, stop: int) -> None:
        """Record [start, stop) as received, merging ranges and advancing ``_next``."""
        if start <= self._next:
            self._next = max(self._next, stop)
        else:
            i = bisect.bisect_left(self._starts, start)
            # merge with the previous range when it touches
            if i > 0 and self._ends[i - 1] >= start:
                i -= 1
                start = self._starts[i]
                stop = max(stop, self._ends[i])
                del self._starts[i], self._ends[i]
            while i < len(self._starts) and self._starts[i] <= stop:
                stop = max(stop, self._ends[i])
                del self._starts[i], self._ends[i]
            self._starts.insert(i, start)
            self._ends.insert(i, stop)
        while self._starts and self._starts[0] <= self._next:
            self._next = max(self._next, self._ends[0])
            del self._starts[0], self._ends[0]

    def _covered(self, start: int, stop: int) -> bool:
        start = max(start, self._next)
        if start >= stop:
            return True
        i = bisect.bisect_right(self._starts, start) - 1
        return i >= 0 and self._ends[i] >= stop

    def _uncovered(self, start: int, stop: int) -> list[tuple[int, int]]:
        """Sub-ranges of [start, stop) not received yet, in order."""
        pieces = []
        cursor = max(start, self._next)
        i = max(bisect.bisect_right(self._starts, cursor) - 1, 0)
        while cursor < stop:
            while i < len(self._starts) and self._ends[i] <= cursor:
                i += 1
            if i < len(self._starts) and self._starts[i] <= cursor:
                cursor = self._ends[i]
                continue
            limit = stop if i >= len(self._starts) else min(stop, self._starts[i])
            pieces.append((cursor, limit))
            cursor = limit
        return pieces
