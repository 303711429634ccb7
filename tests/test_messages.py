"""Messages: declarations, bounded CBOR decoding, unknown types and errors (the signing
maths of protocol/auth.py: test_auth.py)."""

from __future__ import annotations

import dataclasses
import hashlib
import os

import cbor2
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import errors
from protocol import messages as m
from protocol.errors import (
    AuthenticationError,
    MalformedMessage,
    NotAuthenticated,
    RemoteError,
    ReplayError,
)
from protocol.framing import Channel, Flags, Frame, FrameDecoder, Kind, encode_frame

FAST = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

DIGEST = hashlib.sha256(b"x").digest()
SLOT = m.SlotInfo(
    slot=0, state=m.SlotState.TEST, active=True, generation=3, size_bytes=9, digest=DIGEST
)

EXAMPLES: list[m.Message] = [
    m.Hello(min_version=1, max_version=2, nonce=os.urandom(16)),
    m.HelloReply(
        min_version=1,
        max_version=1,
        device_id="d",
        nonce=os.urandom(16),
        max_frame_bytes=4096,
        ram_budget_bytes=1 << 20,
        slot_size_bytes=1 << 22,
        display_width=64,
        display_height=48,
        rx_window_frames=4,
        rx_buffer_bytes=1024,
        slots=(SLOT,),
        has_key=False,
    ),
    m.AuthChallenge(host_proof=os.urandom(32)),
    m.AuthResponse(device_proof=os.urandom(32)),
    m.Ping(sent_us=5),
    m.Pong(payload=b"\x00\xff", ping_sent_us=5, sent_us=6),
    m.Error(code=m.ErrorCode.BUSY, where="SLOT_SET", message="flash busy"),
    m.Ok(),
    m.Bye(),
    m.SetBaud(baud=921600, revert_timeout_ms=1500),
    m.Reset(),
    m.SlotSet(action=m.SlotAction.REVERT),
    m.SlotStatus(slots=(SLOT, dataclasses.replace(SLOT, slot=1, active=False))),
    m.ImageBegin(
        size_bytes=100,
        digest=DIGEST,
        image_tag=bytes(32),
        format_version=1,
        generation=0,
        force=True,
    ),
    m.ImageStatus(digest=DIGEST, size_bytes=100),
    m.ImageStatusReply(next_offset=0, in_progress=False),
    m.ImageChunk(offset=96, data=b"\x00" * 4),
    m.ImageAck(next_offset=100, credits=0, window_bytes=0),
    m.ImageVerify(digest=DIGEST),
    m.ImageVerifyReply(ok=False, digest=b"", tag_ok=False, size_bytes=0),
    m.ImageCommit(digest=DIGEST),
    m.ImageAbort(digest=DIGEST),
    m.Scores(sequence=1, packet=b"\x01"),
    m.ViewRequest(phi_deg=-720.25, theta_deg=90, sequence=0),
    m.KeyframeRequest(sequence=2),
    m.Notice(level=0, text="hello", detail={"a": 1, "b": "x", "c": b"\x00", "d": 1.5, "e": True}),
]


def test_every_message_type_is_exercised_here():
    assert {type(e).TYPE for e in EXAMPLES} == set(m.MESSAGE_CLASSES)


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda e: type(e).__name__)
def test_round_trip_through_a_frame(msg):
    wire = msg.encode(request_id=77)
    (frame,) = FrameDecoder(1 << 16).feed(wire)
    assert frame.channel == msg.CHANNEL and frame.kind == msg.KIND and frame.request_id == 77
    assert frame.must_understand == msg.MUST_UNDERSTAND
    decoded = m.decode_message(frame)
    assert decoded == msg and type(decoded) is type(msg)
    assert m.encode_message(decoded, request_id=77) == wire


def test_declarations_are_consistent():
    for msg_type, cls in m.MESSAGE_CLASSES.items():
        assert cls.TYPE is msg_type and 0 <= msg_type <= 255
        if cls.KIND is Kind.REQUEST:
            assert cls.REPLY is not None, f"{cls.__name__} must name its reply"
        if cls.SIGNED:
            assert cls.KIND is Kind.REQUEST and issubclass(cls, m.SignedRequest)
    signed = {cls.TYPE for cls in m.MESSAGE_CLASSES.values() if cls.SIGNED}
    assert signed == {
        m.MessageType.IMAGE_BEGIN,
        m.MessageType.IMAGE_COMMIT,
        m.MessageType.IMAGE_ABORT,
        m.MessageType.SLOT_SET,
        m.MessageType.SET_BAUD,
        m.MessageType.RESET,
    }
    assert m.ViewRequest.REPLY is m.Scores and m.ImageBegin.REPLY is m.ImageAck


def test_construction_checks_values_with_clear_messages():
    with pytest.raises(ValueError, match=r"Hello.nonce \(key 2\) must be 16 bytes, got 3"):
        m.Hello(min_version=1, max_version=1, nonce=b"abc")
    with pytest.raises(ValueError, match=r"theta_deg \(key 1\)=91.0 is above the maximum 90"):
        m.ViewRequest(phi_deg=0, theta_deg=91, sequence=0)
    with pytest.raises(ValueError, match="must be finite"):
        m.ViewRequest(phi_deg=float("nan"), theta_deg=0, sequence=0)
    with pytest.raises(ValueError, match="min_version=2 > max_version=1"):
        m.Hello(min_version=2, max_version=1, nonce=bytes(16))
    with pytest.raises(ValueError, match="must be an int"):
        m.Ping(sent_us=True)
    with pytest.raises(ValueError, match="ACTIVATE needs slot"):
        m.SlotSet(action=m.SlotAction.ACTIVATE)
    with pytest.raises(ValueError, match="must be 0 or 32 bytes"):
        dataclasses.replace(SLOT, digest=b"\x01")
    # Normalisation: bytearray -> bytes, list -> tuple, int -> enum, dict -> record.
    msg = m.SlotStatus(slots=[{0: 1, 1: 2, 2: False, 3: 0, 4: 0, 5: bytearray()}])
    assert msg.slots == (
        m.SlotInfo(
            slot=1,
            state=m.SlotState.CONFIRMED,
            active=False,
            generation=0,
            size_bytes=0,
            digest=b"",
        ),
    )


# --------------------------------------------------------------------------- decoding


def _body(obj) -> bytes:
    return cbor2.dumps(obj)


def test_unknown_keys_are_ignored():
    msg = m.ViewRequest(phi_deg=10.0, theta_deg=5.0, sequence=3)
    body = {0: 10.0, 1: 5.0, 2: 3, 99: [1, 2, {"x": b"y"}], "future": "field"}
    assert m.ViewRequest.from_body(_body(body)) == msg


def test_missing_required_key_is_malformed_and_named():
    with pytest.raises(
        MalformedMessage, match=r"decode VIEW_REQUEST: missing required key 2 \(sequence\)"
    ):
        m.ViewRequest.from_body(_body({0: 1.0, 1: 2.0}))


@pytest.mark.parametrize(
    ("cls", "body", "problem"),
    [
        (m.Hello, {0: 1, 1: 1, 2: "not bytes"}, "must be a byte string"),
        (m.Hello, {0: 1, 1: 1, 2: b"\x00" * 17}, "must be 16 bytes, got 17"),
        (m.Hello, {0: True, 1: 1, 2: bytes(16)}, "must be an int"),
        (m.HelloReply, {0: 1}, "missing required key 1"),
        (m.SlotSet, {0: 7}, "is not a SlotAction"),
        (m.ImageChunk, {0: -1, 1: b"x"}, "below the minimum 0"),
        (
            m.ImageAck,
            {0: 0, 1: 70000, 2: 0},
            "credits \\(key 1\\)=70000 is above the maximum 65535",
        ),
        (m.ImageChunk, {0: 1 << 64, 1: b"x"}, "CBOR tag 2"),  # bignums are tags: refused
        (m.ImageChunk, {0: 0, 1: b""}, "at least 1 bytes"),
        (m.Bye, {0: "x" * 300}, "at most 256 bytes"),
        (m.Error, {0: 1, 3: {"k": [1]}}, "must be one of"),
        (m.SlotStatus, {0: [{0: 0}]}, "missing required key 1"),
        (m.SlotStatus, {0: [1, 2]}, "must be a SlotInfo map"),
        (m.ViewRequest, {0: "north", 1: 0.0, 2: 0}, "must be a number"),
        (m.KeyframeRequest, {0: 1, 1: None}, None),  # null for an optional key is fine
    ],
)
def test_wrong_types_and_limits_are_malformed(cls, body, problem):
    if problem is None:
        assert cls.from_body(_body(body)).last_frame is None
        return
    with pytest.raises(MalformedMessage, match=problem) as info:
        cls.from_body(_body(body))
    assert str(info.value).startswith(f"decode {cls.TYPE.name}: ")
    assert "\n" not in str(info.value)


@FAST
@given(body=st.binary(max_size=200), msg_type=st.sampled_from(sorted(m.MESSAGE_CLASSES)))
def test_arbitrary_bodies_give_a_message_or_malformed(body, msg_type):
    cls = m.MESSAGE_CLASSES[msg_type]
    try:
        msg = cls.from_body(body)
    except MalformedMessage as exc:
        assert "\n" not in str(exc)
    else:
        assert type(msg) is cls


@FAST
@given(
    index=st.integers(0, len(EXAMPLES) - 1),
    edits=st.lists(
        st.tuples(
            st.sampled_from(["flip", "insert", "delete"]),
            st.integers(0, 10_000),
            st.integers(0, 255),
        ),
        min_size=1,
        max_size=4,
    ),
)
def test_mutated_valid_encodings_give_a_message_or_malformed(index, edits):
    msg = EXAMPLES[index]
    body = bytearray(msg.to_body())
    for op, pos, value in edits:
        if op == "insert":
            body.insert(pos % (len(body) + 1), value)
        elif body and op == "flip":
            body[pos % len(body)] ^= value or 1
        elif body:
            del body[pos % len(body)]
    try:
        decoded = type(msg).from_body(bytes(body))
    except MalformedMessage:
        return
    assert type(decoded) is type(msg)


def test_unknown_type_gives_an_unknown_message_with_an_error_reply():
    frame = Frame(
        channel=Channel.CONTROL,
        kind=Kind.REQUEST,
        msg_type=0xEE,
        request_id=12,
        body=b"\xa0",
        flags=int(Flags.MUST_UNDERSTAND),
    )
    result = m.decode_message(frame)
    assert isinstance(result, m.UnknownMessage)
    assert (result.msg_type, result.request_id, result.must_understand) == (0xEE, 12, True)
    reply = result.error_reply()
    assert reply.code == m.ErrorCode.UNKNOWN_MESSAGE and "0xee" in reply.message
    assert isinstance(reply.to_exception(), errors.RemoteUnknownMessage)
    # Even an unknown type with a garbage body is not decoded, just reported.
    assert isinstance(
        m.decode_message(dataclasses.replace(frame, body=b"\xff\xff")), m.UnknownMessage
    )


def test_channel_or_kind_disagreeing_with_the_type_is_malformed():
    wire = encode_frame(
        channel=Channel.IMAGE,
        kind=Kind.REQUEST,
        msg_type=int(m.MessageType.PING),
        request_id=1,
        body=m.Ping(sent_us=1).to_body(),
    )
    (frame,) = FrameDecoder(256).feed(wire)
    with pytest.raises(
        MalformedMessage,
        match="frame says channel IMAGE kind REQUEST, PING is channel CONTROL kind REQUEST",
    ):
        m.decode_message(frame)


# --------------------------------------------------------------------------- errors


def test_every_error_code_maps_to_its_own_class():
    assert set(m.ERROR_CLASSES) == set(m.ErrorCode)
    assert len(set(m.ERROR_CLASSES.values())) == len(m.ErrorCode)
    for code, cls in m.ERROR_CLASSES.items():
        assert issubclass(cls, RemoteError)
        exc = m.Error(
            code=code, where="IMAGE_BEGIN", message="went wrong", detail={"n": 1}
        ).to_exception()
        assert type(exc) is cls and exc.code == code and exc.name == code.name
        assert str(exc) == f"device error {code.name} ({int(code)}): IMAGE_BEGIN: went wrong"
        assert exc.detail == {"n": 1} and exc.where == "IMAGE_BEGIN"
        assert m.error_code_for(exc) is code  # a relayed error keeps its code


def test_error_families_can_be_caught_by_the_local_base_classes():
    auth = m.Error(code=m.ErrorCode.AUTH_FAILED, message="bad proof").to_exception()
    limit = m.Error(code=m.ErrorCode.TOO_LARGE_FOR_FLASH, message="too big").to_exception()
    assert isinstance(auth, AuthenticationError)
    assert isinstance(limit, errors.LimitExceeded)


def test_unknown_error_code_still_raises_a_remote_error():
    exc = m.Error(code=999, message="from the future").to_exception()
    assert type(exc) is RemoteError and "CODE_999 (999)" in str(exc)


@pytest.mark.parametrize(
    ("exc", "code"),
    [
        (ReplayError("x"), m.ErrorCode.REPLAYED),
        (NotAuthenticated("x"), m.ErrorCode.NOT_AUTHENTICATED),
        (AuthenticationError("x"), m.ErrorCode.AUTH_FAILED),
        (MalformedMessage("x"), m.ErrorCode.MALFORMED),
        (errors.LimitExceeded("x"), m.ErrorCode.LIMIT_EXCEEDED),
        (KeyError("x"), m.ErrorCode.INTERNAL),
    ],
)
def test_error_from_exception(exc, code):
    reply = m.Error.from_exception(exc, where="IMAGE_CHUNK")
    assert reply.code == code and reply.where == "IMAGE_CHUNK"


def test_error_from_exception_truncates_to_the_field_limits():
    reply = m.Error.from_exception(ValueError("é" * 400 + "\nsecond line"), where="w" * 100)
    assert len(reply.message.encode()) <= 256 and len(reply.where.encode()) <= 64
    assert "second line" not in reply.message
