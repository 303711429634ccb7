"""Error tree of the device runtime."""

from __future__ import annotations

__all__ = ["BudgetError", "DeviceError", "FlashError"]


class DeviceError(Exception):
    """Base class of device-side errors a user can act on."""


class FlashError(DeviceError):
    """The flash store is missing, corrupt or cannot hold what was asked."""


class BudgetError(DeviceError):
    """Something does not fit the device's declared RAM budget."""
