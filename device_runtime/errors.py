"""Error tree of the device runtime (the flash store's errors: one per wire error code).

Which ERROR a device sends for each is :func:`device_runtime.wire_errors.error_for`.
"""

from __future__ import annotations

__all__ = [
    "BadChunk",
    "BudgetError",
    "DeviceError",
    "FlashError",
    "ImageTooLarge",
    "NoImage",
    "RollbackRefused",
    "SlotBusy",
    "SlotDigestMismatch",
]



class DeviceError(Exception):
    """Base class of device-side errors a user can act on."""


class FlashError(DeviceError):
    """The flash store is missing, corrupt or cannot hold what was asked."""


class BudgetError(DeviceError):
    """Something does not fit the device's declared RAM budget."""


class ImageTooLarge(FlashError):
    """The image does not fit a slot (wire code TOO_LARGE_FOR_FLASH)."""


class RollbackRefused(FlashError):
    """An older image generation was asked for without ``force`` (ROLLBACK_REFUSED)."""


class BadChunk(FlashError):
    """A chunk lies outside the image or the window, or contradicts earlier bytes (BAD_OFFSET)."""


class NoImage(FlashError):
    """There is no active image, or no image session, for the operation (NO_IMAGE)."""


class SlotBusy(FlashError):
    """A test image awaits confirmation, so the fallback slot may not be overwritten (BUSY)."""


class SlotDigestMismatch(FlashError):
    """A slot's bytes do not match the digest recorded for it (DIGEST_MISMATCH)."""
