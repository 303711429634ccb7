"""Builders shared by the flash-store tests (test_flash.py, test_image_writer.py,
test_boot_fallback.py, test_flash_edges.py)."""

from __future__ import annotations

import hashlib
import random

from device_runtime.flash import JOURNAL_BLOCK_BYTES, FlashStore

BLOCK = JOURNAL_BLOCK_BYTES
"""One journal block: the unit the writer journals and resume claims."""
CAPACITY = 1 << 20
"""Slot capacity of the test stores (1 MiB)."""


def sha(data: bytes) -> bytes:
    """SHA-256 of ``data`` (the slot digest)."""
    return hashlib.sha256(data).digest()


def make_image(seed: int, size: int) -> bytes:
    """``size`` reproducible random bytes: opaque image contents for the store."""
    return random.Random(seed).randbytes(size)


def commit_image(flash, data: bytes, *, generation: int, confirm: bool = True) -> str:
    """Write ``data`` into the inactive slot with the flash API, commit it (and confirm it);
    return the slot now active."""
    store = FlashStore.open(flash)
    writer = store.begin_image(size_bytes=len(data), sha256=sha(data),
                               image_generation=generation, force=True)
    for offset in range(0, len(data), 8192):
        writer.write_chunk(offset, data[offset:offset + 8192])
    assert writer.verify()
    store.commit_test()
    if confirm:
        store.confirm()
    slot = store.active_slot
    store.close()
    return slot
