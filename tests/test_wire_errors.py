"""The ERROR a device sends for a failed request (device_runtime/wire_errors.py): a refusal
carries its own code and detail, the flash store's errors map one to one, the image's tag
and format and the RAM budget have their codes, anything else is INTERNAL; every message is
one line within the ERROR fields' limits."""

from __future__ import annotations

import pytest

from device_runtime.errors import (
    BadChunk,
    BudgetError,
    FlashError,
    ImageTooLarge,
    NoImage,
    RollbackRefused,
    SlotBusy,
    SlotDigestMismatch,
)
from device_runtime.wire_errors import DeviceRefusal, error_for
from protocol import messages as m
from protocol.errors import ImageFormatError, MalformedMessage
from protocol.image import ImageTagError


def test_a_refusal_carries_its_code_and_detail():
    refusal = DeviceRefusal(m.ErrorCode.TOO_LARGE_FOR_RAM, "too big", {"need": 9})
    error = error_for(refusal, "IMAGE_BEGIN")
    assert (error.code, error.where, error.message) == (
        m.ErrorCode.TOO_LARGE_FOR_RAM, "IMAGE_BEGIN", "too big")
    assert error.detail == {"need": 9}


@pytest.mark.parametrize(
    ("exc", "code"),
    [
        (ImageTooLarge("x"), m.ErrorCode.TOO_LARGE_FOR_FLASH),
        (RollbackRefused("x"), m.ErrorCode.ROLLBACK_REFUSED),
        (BadChunk("x"), m.ErrorCode.BAD_OFFSET),
        (NoImage("x"), m.ErrorCode.NO_IMAGE),
        (SlotBusy("x"), m.ErrorCode.BUSY),
        (SlotDigestMismatch("x"), m.ErrorCode.DIGEST_MISMATCH),
        (FlashError("x"), m.ErrorCode.FLASH_FAILED),
        (BudgetError("x"), m.ErrorCode.TOO_LARGE_FOR_RAM),
        (ImageTagError("x"), m.ErrorCode.TAG_MISMATCH),
        (ImageFormatError("x"), m.ErrorCode.UNSUPPORTED_FORMAT),
        (MalformedMessage("x"), m.ErrorCode.MALFORMED),
        (RuntimeError("x"), m.ErrorCode.INTERNAL),
    ],
)
def test_each_exception_class_gets_its_wire_code(exc, code):
    assert error_for(exc, "where").code == code


def test_messages_are_one_line_within_the_field_limits():
    error = error_for(FlashError("line one\nline two " + "x" * 400), "w" * 100)
    assert "\n" not in error.message and error.message.startswith("line one line two")
    assert len(error.message.encode()) <= 256 and error.message.endswith("...")
    assert len(error.where.encode()) <= 64
