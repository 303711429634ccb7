"""Framing: COBS, CRC, header checks, resynchronisation and bounded buffering."""

from __future__ import annotations

import random
import zlib

import numpy as np
import pytest
from cobs_reference import reference_cobs_encode
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol._cobs import CobsDecodeError, cobs_decode, cobs_encode, cobs_max_encoded_size
from protocol.errors import BadCobs, BadCRC, BadHeader, FrameTooLarge
from protocol.framing import (
    HEADER,
    MIN_FRAME_BYTES,
    Channel,
    Flags,
    Frame,
    FrameDecoder,
    Kind,
    decode_frame,
    encode_frame,
    max_encoded_frame_bytes,
)

FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _raw_frame(
    *,
    body: bytes,
    version: int = 1,
    flags: int = 0,
    channel: int = 0,
    kind: int = 0,
    msg_type: int = 5,
    request_id: int = 0,
    body_len: int | None = None,
    crc: int | None = None,
) -> bytes:
    """Build a wire frame by hand, with any field (even invalid ones) chosen."""
    raw = (
        HEADER.pack(
            (version << 4) | flags,
            channel,
            kind,
            msg_type,
            request_id,
            len(body) if body_len is None else body_len,
        )
        + body
    )
    raw += (zlib.crc32(raw) if crc is None else crc).to_bytes(4, "little")
    return reference_cobs_encode(raw) + b"\x00"


# --------------------------------------------------------------------------- COBS

zero_heavy = st.lists(st.sampled_from([0, 0, 0, 1, 255, 7]), max_size=700).map(bytes)


@FAST
@given(st.one_of(st.binary(max_size=1200), zero_heavy))
def test_cobs_matches_reference_and_round_trips(data):
    encoded = cobs_encode(data)
    assert encoded == reference_cobs_encode(data)
    assert 0 not in encoded
    assert len(data) + 1 <= len(encoded) <= cobs_max_encoded_size(len(data))
    assert cobs_decode(encoded) == data


def test_cobs_long_runs():
    for data in (
        bytes([9]) * 254 * 3,
        bytes([9]) * (254 * 3 + 1),
        bytes(5000),
        (bytes([1]) * 253 + b"\x00") * 10,
    ):
        assert cobs_encode(data) == reference_cobs_encode(data)
        assert cobs_decode(cobs_encode(data)) == data


@pytest.mark.parametrize(
    ("encoded", "problem"),
    [
        (b"", "empty"),
        (b"\x03\x11\x00\x22", "0x00 at offset 2"),
        (b"\x05\x11\x22", "past the end"),
        (b"\x02\x11\xff\x01", "past the end"),
    ],
)
def test_cobs_decode_rejects_invalid(encoded, problem):
    with pytest.raises(CobsDecodeError, match=problem):
        cobs_decode(encoded)


def test_cobs_accepts_the_non_canonical_trailing_block():
    run = bytes([9]) * 254
    assert cobs_decode(b"\xff" + run + b"\x01") == run


# --------------------------------------------------------------------------- frames


@FAST
@given(
    body=st.binary(max_size=600),
    channel=st.sampled_from(list(Channel)),
    kind=st.sampled_from(list(Kind)),
    msg_type=st.integers(0, 255),
    request_id=st.integers(0, 0xFFFF),
    flags=st.sampled_from([0, int(Flags.MUST_UNDERSTAND)]),
)
def test_frame_round_trip_every_channel_and_kind(body, channel, kind, msg_type, request_id, flags):
    wire = encode_frame(
        channel=channel, kind=kind, msg_type=msg_type, request_id=request_id, body=body, flags=flags
    )
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    assert wire == _raw_frame(
        body=body, flags=flags, channel=channel, kind=kind, msg_type=msg_type, request_id=request_id
    )
    (frame,) = FrameDecoder(1024).feed(wire)
    assert frame == Frame(
        channel=channel, kind=kind, msg_type=msg_type, request_id=request_id, body=body, flags=flags
    )
    assert frame.must_understand == bool(flags)
    assert decode_frame(wire, max_frame_bytes=1024) == frame
    assert frame.encode() == wire


@FAST
@given(bodies=st.lists(st.binary(max_size=300), min_size=1, max_size=8), data=st.data())
def test_any_split_of_a_stream_gives_the_same_frames(bodies, data):
    wires = [
        encode_frame(channel=Channel.IMAGE, kind=Kind.EVENT, msg_type=0x13, request_id=i, body=b)
        for i, b in enumerate(bodies)
    ]
    stream = b"".join(wires)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=12)))
    decoder = FrameDecoder(512)
    frames = []
    previous = 0
    for cut in [*cuts, len(stream)]:
        frames += decoder.feed(stream[previous:cut])
        previous = cut
    assert [f.body for f in frames] == bodies
    assert [f.request_id for f in frames] == list(range(len(bodies)))
    assert decoder.frames_ok == len(bodies) and decoder.garbage_bytes == 0


def _stream(n_frames: int = 6) -> tuple[bytes, list[tuple[int, int]], list[bytes]]:
    """Frames with varied bodies; returns the stream, each frame's [start, end] span
    (end = index of its 0x00 delimiter) and the bodies."""
    rng = random.Random(4)
    bodies = [
        bytes(rng.choice([0, 0, 1, 77, 255]) for _ in range(rng.randint(0, 40)))
        for _ in range(n_frames)
    ]
    spans, stream = [], b""
    for i, body in enumerate(bodies):
        wire = encode_frame(
            channel=Channel.CONTROL, kind=Kind.EVENT, msg_type=9, request_id=i, body=body
        )
        spans.append((len(stream), len(stream) + len(wire) - 1))
        stream += wire
    return stream, spans, bodies


@pytest.mark.parametrize("mutation", ["xor", "zero", "delete", "insert"])
def test_corruption_at_every_position_loses_only_the_frames_it_touches(mutation):
    stream, spans, bodies = _stream()
    for pos in range(len(stream)):
        if mutation == "xor":
            bad = stream[:pos] + bytes([stream[pos] ^ 0x5A]) + stream[pos + 1 :]
        elif mutation == "zero":
            bad = stream[:pos] + b"\x00" + stream[pos + 1 :]
        elif mutation == "delete":
            bad = stream[:pos] + stream[pos + 1 :]
        else:
            bad = stream[:pos] + b"\x42" + stream[pos:]
        decoder = FrameDecoder(256)
        got = decoder.feed(bad)
        hit = next(i for i, (s, e) in enumerate(spans) if s <= pos <= e)
        touched = {hit}
        if pos == spans[hit][1] and mutation != "zero":
            touched.add(hit + 1)  # a lost delimiter merges this frame with the next
        expected_kept = [i for i in range(len(bodies)) if i not in touched]
        ids = [f.request_id for f in got]
        assert set(expected_kept) <= set(ids), (mutation, pos)
        # Nothing corrupted gets through: every frame out is an original one.
        for frame in got:
            assert frame.body == bodies[frame.request_id]
        lost = len(bodies) - len(got)
        assert lost <= len(touched)
        dropped = decoder.bad_cobs + decoder.bad_crc + decoder.bad_header + decoder.oversize
        pending = 1 if decoder.buffered_bytes else 0  # last frame lost its delimiter
        assert dropped + pending >= (1 if lost else 0)


@FAST
@given(chunks=st.lists(st.binary(max_size=400), max_size=10))
def test_decoder_never_raises_and_stays_bounded_on_arbitrary_bytes(chunks):
    decoder = FrameDecoder(64)
    for chunk in chunks:
        decoder.feed(chunk)
        assert decoder.buffered_bytes <= decoder.max_buffered_bytes
    counted = decoder.bad_cobs + decoder.bad_crc + decoder.bad_header + decoder.oversize
    assert decoder.frames_ok + counted <= sum(c.count(0) for c in chunks) + 1


def test_endless_bytes_without_delimiter_are_dropped_not_buffered():
    decoder = FrameDecoder(1024)
    for _ in range(200):
        assert decoder.feed(b"\x55" * 4096) == []
        assert decoder.buffered_bytes <= decoder.max_buffered_bytes
    assert decoder.oversize == 1
    assert decoder.garbage_bytes == 200 * 4096
    good = encode_frame(
        channel=Channel.CONTROL, kind=Kind.EVENT, msg_type=1, request_id=1, body=b"x"
    )
    # The first delimiter ends the runaway frame; the next frame is intact.
    frames = decoder.feed(b"\x55\x00" + good)
    assert [f.body for f in frames] == [b"x"]


def test_oversize_frame_dropped_and_counted_then_next_frame_decodes():
    big = encode_frame(
        channel=Channel.IMAGE,
        kind=Kind.EVENT,
        msg_type=0x13,
        request_id=1,
        body=bytes(range(256)) * 8,
    )
    small = encode_frame(
        channel=Channel.IMAGE, kind=Kind.EVENT, msg_type=0x13, request_id=2, body=b"ok"
    )
    decoder = FrameDecoder(1024)
    frames = decoder.feed(big + small)
    assert [f.request_id for f in frames] == [2]
    assert decoder.oversize == 1
    assert decoder.garbage_bytes == len(big) - 1
    with pytest.raises(FrameTooLarge, match="1024"):
        decode_frame(big, max_frame_bytes=1024)
    assert len(big) > max_encoded_frame_bytes(1024) - 2 * 4


def test_frame_exactly_at_the_limit_is_accepted():
    body = bytes(range(1, 200)) * 5
    limit = MIN_FRAME_BYTES + len(body)
    wire = encode_frame(
        channel=Channel.IMAGE, kind=Kind.EVENT, msg_type=0x13, request_id=0, body=body
    )
    assert [f.body for f in FrameDecoder(limit).feed(wire)] == [body]
    decoder = FrameDecoder(limit - 1)
    assert decoder.feed(wire) == [] and decoder.oversize == 1


@pytest.mark.parametrize("delta", [-1, 1, 1000])
def test_body_length_disagreeing_with_the_frame_is_rejected(delta):
    wire = _raw_frame(body=b"abcdef", body_len=6 + delta)
    decoder = FrameDecoder(256)
    assert decoder.feed(wire) == []
    assert decoder.bad_header == 1
    with pytest.raises(BadHeader, match=f"header says body length {6 + delta}, frame carries 6"):
        decode_frame(wire, max_frame_bytes=256)


@pytest.mark.parametrize(
    ("fields", "problem"),
    [
        ({"version": 2}, "version 2"),
        ({"flags": 0b0100}, "reserved"),
        ({"channel": 9}, "channel 9"),
        ({"kind": 4}, "kind 4"),
    ],
)
def test_bad_header_fields_are_rejected(fields, problem):
    wire = _raw_frame(body=b"\xa0", **fields)
    decoder = FrameDecoder(256)
    assert decoder.feed(wire) == [] and decoder.bad_header == 1
    assert problem in decoder.last_error
    with pytest.raises(BadHeader, match=problem):
        decode_frame(wire, max_frame_bytes=256)


def test_bad_crc_names_both_values():
    wire = _raw_frame(body=b"\xa0", crc=0x12345678)
    decoder = FrameDecoder(256)
    assert decoder.feed(wire) == [] and decoder.bad_crc == 1
    with pytest.raises(BadCRC, match=r"frame says 0x12345678, contents give 0x[0-9a-f]{8}"):
        decode_frame(wire, max_frame_bytes=256)


def test_short_frame_and_bad_cobs_counted():
    decoder = FrameDecoder(256)
    decoder.feed(reference_cobs_encode(b"\x01\x02\x03") + b"\x00")  # 3 bytes < 14
    decoder.feed(b"\x05\x11\x22\x00")  # block runs past the end
    assert decoder.bad_header == 1 and decoder.bad_cobs == 1
    with pytest.raises(BadCobs):
        decode_frame(b"\x05\x11\x22", max_frame_bytes=256)


def test_empty_frames_are_ignored_silently():
    good = encode_frame(
        channel=Channel.EVENTS, kind=Kind.EVENT, msg_type=0x30, request_id=3, body=b""
    )
    decoder = FrameDecoder(256)
    frames = decoder.feed(b"\x00\x00" + good + b"\x00\x00\x00")
    assert len(frames) == 1 and frames[0].body == b""
    assert decoder.counters() == {
        "frames_ok": 1,
        "bad_cobs": 0,
        "bad_crc": 0,
        "bad_header": 0,
        "oversize": 0,
        "garbage_bytes": 0,
    }


def test_reset_drops_a_partial_frame():
    good = encode_frame(
        channel=Channel.CONTROL, kind=Kind.EVENT, msg_type=9, request_id=1, body=b"z"
    )
    decoder = FrameDecoder(256)
    decoder.feed(b"\x33\x44")
    decoder.reset()
    assert decoder.buffered_bytes == 0
    assert [f.body for f in decoder.feed(good)] == [b"z"]


@pytest.mark.parametrize(
    ("kwargs", "problem"),
    [
        ({"channel": 7}, "channel=7"),
        ({"kind": 9}, "kind=9"),
        ({"msg_type": 256}, "msg_type=256"),
        ({"request_id": 70000}, "request_id=70000"),
        ({"flags": 2}, "reserved"),
    ],
)
def test_encode_frame_rejects_bad_arguments(kwargs, problem):
    args = {"channel": 0, "kind": 0, "msg_type": 1, "request_id": 0, "body": b"", **kwargs}
    with pytest.raises(ValueError, match=problem):
        encode_frame(**args)


@pytest.mark.parametrize("limit", [0, 63, 1 << 25, 1.5])
def test_decoder_rejects_bad_limits(limit):
    with pytest.raises(ValueError, match="max_frame_bytes"):
        FrameDecoder(limit)


@pytest.mark.parametrize("zero_share", [0.0, 0.004, 0.02, 0.2, 0.9])
def test_cobs_fast_and_vector_paths_agree(zero_share):
    """Both implementations (chosen by zero density) give the canonical encoding."""
    from protocol import _cobs

    rng = np.random.default_rng(int(zero_share * 1000))
    for size in (1, 253, 254, 255, 508, 509, 4096, 20000):
        data = rng.integers(1, 256, size=size, dtype=np.uint8)
        data[rng.random(size) < zero_share] = 0
        raw = data.tobytes()
        fast = _cobs._encode_runs(raw)
        old_sparse = _cobs._SPARSE
        try:
            _cobs._SPARSE = 0.0  # force the vectorised paths
            vector = _cobs.cobs_encode(raw)
            assert _cobs.cobs_decode(vector) == raw
        finally:
            _cobs._SPARSE = old_sparse
        assert fast == vector
        assert _cobs._decode_runs(fast) == raw
        assert _cobs.cobs_decode(fast) == raw
