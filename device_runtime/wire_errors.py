"""The ERROR a device sends for a failed request: :func:`error_for` and :class:`DeviceRefusal`.

A handler refuses with a specific wire code by raising :class:`DeviceRefusal`; every other
exception is mapped by its class (the flash store's errors one to one, the RAM budget, the
image's tag and format, the protocol's own errors) and anything unexpected is INTERNAL,
logged with its traceback. Messages are cut to the ERROR fields' limits on one line.
docs/protocol.md, "Error codes", is the table.
"""

from __future__ import annotations

import dataclasses
import logging

from device_runtime import errors as e
from protocol import messages as m
from protocol.errors import ImageFormatError
from protocol.image import ImageTagError

__all__ = ["DeviceRefusal", "error_for"]

_logger = logging.getLogger("device_runtime.device")  # error_for logs as the device


class DeviceRefusal(e.DeviceError):
    """A request the device refuses with a specific wire error code.

    Parameters
    ----------
    code : ErrorCode
    message : str
        One line.
    detail : dict, optional
        Machine-readable specifics (text keys, scalar values).
    """

    def __init__(self, code: m.ErrorCode, message: str, detail: dict | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.detail = detail


def _one_line(text: str, limit: int) -> str:
    text = " ".join(str(text).split())
    data = text.encode("utf-8", "replace")
    if len(data) <= limit:
        return text
    return data[: limit - 3].decode("utf-8", "ignore") + "..."


_FLASH_CODES: tuple[tuple[type[BaseException], m.ErrorCode], ...] = (
    (e.ImageTooLarge, m.ErrorCode.TOO_LARGE_FOR_FLASH),
    (e.RollbackRefused, m.ErrorCode.ROLLBACK_REFUSED),
    (e.BadChunk, m.ErrorCode.BAD_OFFSET),
    (e.NoImage, m.ErrorCode.NO_IMAGE),
    (e.SlotBusy, m.ErrorCode.BUSY),
    (e.SlotDigestMismatch, m.ErrorCode.DIGEST_MISMATCH),
    (e.BudgetError, m.ErrorCode.TOO_LARGE_FOR_RAM),
    (ImageTagError, m.ErrorCode.TAG_MISMATCH),
    (ImageFormatError, m.ErrorCode.UNSUPPORTED_FORMAT),
    (e.FlashError, m.ErrorCode.FLASH_FAILED),
)


def error_for(exc: BaseException, where: str) -> m.Error:
    """Return the ERROR a device sends for a failed request.

    :class:`DeviceRefusal` carries its code; flash errors map one to one
    (ImageTooLarge -> TOO_LARGE_FOR_FLASH, RollbackRefused -> ROLLBACK_REFUSED,
    BadChunk -> BAD_OFFSET, NoImage -> NO_IMAGE, SlotBusy -> BUSY,
    SlotDigestMismatch -> DIGEST_MISMATCH, other FlashError -> FLASH_FAILED);
    BudgetError -> TOO_LARGE_FOR_RAM; ImageTagError -> TAG_MISMATCH; other
    ImageFormatError -> UNSUPPORTED_FORMAT; protocol errors as
    :func:`protocol.messages.error_code_for`; anything else INTERNAL.
    """
    if isinstance(exc, DeviceRefusal):
        return m.Error(
            code=exc.code,
            where=_one_line(where, 64),
            message=_one_line(str(exc), 256),
            detail=exc.detail,
        )
    for cls, code in _FLASH_CODES:
        if isinstance(exc, cls):
            return m.Error(code=code, where=_one_line(where, 64), message=_one_line(str(exc), 256))
    error = m.Error.from_exception(exc, where=_one_line(where, 64))
    if error.code == m.ErrorCode.INTERNAL:
        _logger.error("%s: internal error", where, exc_info=exc)
    return dataclasses.replace(error, message=_one_line(error.message, 256))
