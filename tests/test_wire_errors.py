"""The ERROR a device sends for a failed request (device_runtime/wire_errors.py): a refusal
carries its own code and detail, the flash store's errors map one to one, the image's tag
and format and the RAM budget have their codes, anything else is INTERNAL; every message is
one line within the ERROR fields' limits."""

from __future__ import annotations

import pytest

from device_runtime import errors as e
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


#: Wire code name -> an exception the device maps to it (docs/protocol.md, "Error codes").
EXPECTED_CODE = {
    "TOO_LARGE_FOR_FLASH": e.ImageTooLarge,
    "ROLLBACK_REFUSED": e.RollbackRefused,
    "BAD_OFFSET": e.BadChunk,
    "NO_IMAGE": e.NoImage,
    "BUSY": e.SlotBusy,
    "DIGEST_MISMATCH": e.SlotDigestMismatch,
    "FLASH_FAILED": e.FlashError,
    "TOO_LARGE_FOR_RAM": e.BudgetError,
    "TAG_MISMATCH": ImageTagError,
    "UNSUPPORTED_FORMAT": ImageFormatError,
    "MALFORMED": MalformedMessage,
    "INTERNAL": RuntimeError,
}


@pytest.mark.parametrize("name", sorted(EXPECTED_CODE))
def test_each_exception_class_gets_its_wire_code(name):
    assert error_for(EXPECTED_CODE[name]("x"), "where").code == m.ErrorCode[name]


def test_messages_are_one_line_within_the_field_limits():
    error = error_for(e.FlashError("line one\nline two " + "x" * 400), "w" * 100)
    assert "\n" not in error.message and error.message.startswith("line one line two")
    assert len(error.message.encode()) <= 256 and error.message.endswith("...")
    assert len(error.where.encode()) <= 64
