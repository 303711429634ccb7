"""Builders shared by the flash-store tests (test_flash.py, test_image_writer.py)."""

from __future__ import annotations

import hashlib
import random

from device_runtime.flash import JOURNAL_BLOCK_BYTES

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
