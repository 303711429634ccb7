"""Records (protocol/records.py): fields declared with wire() are checked and normalised on
construction, round-trip through their CBOR map, and a bad declaration fails at once; the
bounded CBOR scan refuses what the protocol forbids before cbor2 sees a byte. The
messages built on them are tested in test_messages.py."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import cbor2
import pytest

from protocol import messages as m
from protocol.errors import MalformedMessage
from protocol.records import U8, Record, scan_cbor, wire


class Colour(IntEnum):
    RED = 1
    BLUE = 2


@dataclass(frozen=True)
class Point(Record):
    x: int = wire(0, ge=0, le=U8)
    colour: Colour = wire(1, default=Colour.RED)  # noqa: RUF009 (wire() is a field specifier)
    tags: tuple[bytes, ...] = wire(2, default=(), max_items=2, lengths=(2,))
    name: str | None = wire(3, default=None, max_len=4)


def _body(obj) -> bytes:
    return cbor2.dumps(obj)


def test_a_record_is_checked_normalised_and_round_trips_through_its_map():
    point = Point(x=3, colour=2, tags=[bytearray(b"ab")])
    assert point.colour is Colour.BLUE and point.tags == (b"ab",)
    assert type(point.tags[0]) is bytes
    assert point._to_map() == {0: 3, 1: 2, 2: [b"ab"]}  # None fields are not encoded
    assert Point._from_map({0: 3, 1: 2, 2: [b"ab"], 9: "unknown"}, "test") == point


@pytest.mark.parametrize(
    ("kwargs", "problem"),
    [
        ({"x": 256}, r"Point\.x \(key 0\)=256 is above the maximum 255"),
        ({"x": True}, "must be an int"),
        ({"x": 1, "colour": 7}, "is not a Colour"),
        ({"x": 1, "tags": [b"a"]}, "must be 2 bytes"),
        ({"x": 1, "tags": [b"ab"] * 3}, "has 3 items, at most 2 allowed"),
        ({"x": 1, "name": "toolong"}, "at most 4 bytes"),
    ],
)
def test_bad_field_values_are_value_errors_naming_the_field(kwargs, problem):
    with pytest.raises(ValueError, match=problem):
        Point(**kwargs)


def test_a_missing_required_key_is_named():
    with pytest.raises(ValueError, match=r"where: missing required key 0 \(x\)"):
        Point._from_map({1: 1}, "where")


def test_a_field_not_declared_with_wire_or_a_key_used_twice_is_refused():
    @dataclass(frozen=True)
    class Undeclared(Record):
        x: int = 0

    @dataclass(frozen=True)
    class Twice(Record):
        a: int = wire(0, default=0)
        b: int = wire(0, default=0)

    with pytest.raises(TypeError, match=r"Undeclared\.x is not declared with wire\(\)"):
        Undeclared()
    with pytest.raises(TypeError, match="CBOR key 0 used twice"):
        Twice()


@pytest.mark.parametrize(
    ("body", "problem"),
    [
        (b"\xc1\x00", "tag 1"),
        (b"\xbf\x00\x01\xff", "indefinite"),
        (b"\xa2\x00\x01\x00\x02", "duplicate map key"),
        (b"\xa1\x00\x01\x00", "trailing"),
        (b"\xa1\x00\x5a\xff\xff\xff\xff", "runs past the end"),
        (b"\xa1\x00\x9b" + b"\xff" * 8, "cannot fit"),
        (b"\xa1\x00\xf7", "simple value"),
        (b"\xa1\x41\x00\x01", "map key"),
        (b"\xa1\x00\x1c", "reserved value"),
        (b"\xa1\x00", "cannot fit"),
        (b"\xa1\x00\x19\x01", "truncated"),
        (b"", "truncated"),
        (b"\xa1\x00" + b"\x81" * 9 + b"\x00", "nesting deeper than max_depth=8"),
        (b"\xa1\x00\x62\xff\xfe", "CBOR"),  # invalid UTF-8: cbor2 error, wrapped
        (b"\x80", "not a map"),
    ],
)
def test_cbor_scanner_rejects_what_the_protocol_forbids(body, problem):
    with pytest.raises(MalformedMessage, match=problem):
        m.Bye.from_body(body)


def test_depth_limit_is_an_argument():
    body = _body({0: [[[1]]]})
    scan_cbor(body, max_depth=4)
    with pytest.raises(MalformedMessage, match="max_depth=3"):
        scan_cbor(body, max_depth=3)


def test_hostile_lengths_never_reach_cbor2():
    # A byte string claiming 2**63 bytes in a 12-byte body is refused by the scan.
    with pytest.raises(MalformedMessage, match="runs past the end"):
        m.Scores.from_body(b"\xa2\x00\x00\x01\x5b\x7f" + b"\xff" * 7)
