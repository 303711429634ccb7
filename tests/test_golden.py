"""Golden vectors that pin the wire format (tests/golden/*.jsonl).

Each line of ``messages.jsonl`` holds a message class's dotted name, its kwargs
(bytes as hex, enums as ints, nested records as objects), the frame's request
id and flags, and the expected wire frame in hex. Every line is checked in both
directions: the kwargs encode to exactly those bytes and those bytes decode to
an equal message. ``cobs.jsonl`` and ``crc.jsonl`` hold published vectors
(Wikipedia's COBS examples, the CRC-32 check value); ``auth.jsonl`` pins the
HMAC constructions.

Changing a line of messages.jsonl changes the wire format: bump the version
and record it in docs/protocol.md. To regenerate after such a decision:
``.venv/bin/python tests/test_golden.py --regenerate``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import importlib
import json
import sys
import types
import typing
import zlib
from pathlib import Path

import cbor2
import pytest
from cobs_reference import reference_cobs_decode, reference_cobs_encode

from protocol import auth
from protocol import messages as m
from protocol._cobs import cobs_decode, cobs_encode
from protocol.framing import HEADER, FrameDecoder, crc32, decode_frame

GOLDEN = Path(__file__).parent / "golden"


def _load(name: str) -> list[dict]:
    path = GOLDEN / name
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


# --------------------------------------------------------------------------- kwargs <-> JSON


def _strip_optional(tp):
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return tp


def _from_json(tp, value):
    tp = _strip_optional(tp)
    if value is None:
        return None
    if tp is bytes:
        return bytes.fromhex(value)
    if typing.get_origin(tp) is tuple:
        (item,) = typing.get_args(tp)[:1]
        return tuple(_from_json(item, v) for v in value)
    if isinstance(tp, type) and issubclass(tp, m.Record):
        return _record_from_json(tp, value)
    return value


def _record_from_json(cls, kwargs: dict):
    hints = typing.get_type_hints(cls)
    return cls(**{k: _from_json(hints[k], v) for k, v in kwargs.items()})


def _to_json(value):
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, m.Record):
        return {f.name: _to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple):
        return [_to_json(v) for v in value]
    if isinstance(value, dict):
        return {k: _to_json(v) for k, v in value.items()}
    if isinstance(value, int) and not isinstance(value, bool):
        return int(value)
    return value


def _class(dotted: str):
    module, _, name = dotted.rpartition(".")
    return getattr(importlib.import_module(module), name)


# --------------------------------------------------------------------------- messages


MESSAGE_CASES = _load("messages.jsonl") if (GOLDEN / "messages.jsonl").exists() else []


@pytest.mark.parametrize("case", MESSAGE_CASES, ids=[c["name"] for c in MESSAGE_CASES])
def test_message_golden_both_directions(case):
    cls = _class(case["class"])
    msg = _record_from_json(cls, case["kwargs"])
    wire = bytes.fromhex(case["frame"])
    # kwargs -> exactly these bytes
    assert msg.encode(request_id=case["request_id"], flags=case["flags"]) == wire
    # bytes -> an equal message, through the streaming decoder
    frames = FrameDecoder(1 << 16).feed(wire)
    assert len(frames) == 1
    frame = frames[0]
    assert (frame.request_id, frame.flags, frame.msg_type) == (
        case["request_id"],
        case["flags"],
        int(cls.TYPE),
    )
    assert m.decode_message(frame) == msg


def test_every_message_type_has_a_golden_line():
    covered = {_class(c["class"]).TYPE for c in MESSAGE_CASES}
    assert covered == set(m.MESSAGE_CLASSES)


@pytest.mark.parametrize("case", MESSAGE_CASES, ids=[c["name"] for c in MESSAGE_CASES])
def test_message_golden_frames_follow_the_documented_layout(case):
    """Re-derive each golden frame with only zlib, struct and a reference COBS decoder."""
    wire = bytes.fromhex(case["frame"])
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    raw = reference_cobs_decode(wire[:-1])
    ver_flags, channel, kind, msg_type, request_id, body_len = HEADER.unpack_from(raw)
    assert HEADER.size == 10
    assert ver_flags >> 4 == 1 and ver_flags & 0x0F == case["flags"]
    assert request_id == case["request_id"]
    assert body_len == len(raw) - 14
    assert int.from_bytes(raw[-4:], "little") == zlib.crc32(raw[:-4])
    cls = _class(case["class"])
    assert (channel, kind, msg_type) == (int(cls.CHANNEL), int(cls.KIND), int(cls.TYPE))
    body = raw[10:-4]
    obj = cbor2.loads(body)
    assert isinstance(obj, dict) and all(isinstance(k, int) for k in obj)
    # Keys on the wire are exactly the declared keys of the non-None fields.
    msg = _record_from_json(cls, case["kwargs"])
    expected_keys = {
        f.metadata["key"] for f in dataclasses.fields(cls) if getattr(msg, f.name) is not None
    }
    assert set(obj) == expected_keys
    assert list(obj) == sorted(obj)  # canonical order


def test_hand_built_ping_frame_matches_the_spec():
    """One frame built byte by byte from docs/protocol.md, independent of the encoder."""
    body = bytes([0xA2, 0x00, 0x42]) + b"hi" + bytes([0x01, 0x18, 0x7B])  # {0: h'6869', 1: 123}
    header = bytes([0x11, 0x00, 0x00, 0x05, 0x34, 0x12]) + len(body).to_bytes(4, "little")
    raw = header + body
    raw += zlib.crc32(raw).to_bytes(4, "little")
    expected = reference_cobs_encode(raw) + b"\x00"
    msg = m.Ping(payload=b"hi", sent_us=123)
    assert msg.encode(request_id=0x1234) == expected
    assert m.decode_message(decode_frame(expected, max_frame_bytes=4096)) == msg


# --------------------------------------------------------------------------- COBS / CRC


COBS_CASES = _load("cobs.jsonl")


@pytest.mark.parametrize("case", COBS_CASES, ids=[c["name"] for c in COBS_CASES])
def test_cobs_golden(case):
    data = bytes.fromhex(case["data"])
    encoded = bytes.fromhex(case["encoded"])
    assert cobs_encode(data) == encoded
    assert cobs_decode(encoded) == data


CRC_CASES = _load("crc.jsonl")


@pytest.mark.parametrize("case", CRC_CASES, ids=[c["name"] for c in CRC_CASES])
def test_crc_golden(case):
    assert crc32(case["ascii"].encode("ascii")) == int(case["crc32"], 16)


# --------------------------------------------------------------------------- auth


AUTH_CASES = _load("auth.jsonl")


@pytest.mark.parametrize("case", AUTH_CASES, ids=[c["name"] for c in AUTH_CASES])
def test_auth_golden(case):
    key = bytes.fromhex(case["device_key"])
    host_nonce = bytes.fromhex(case["host_nonce"])
    device_nonce = bytes.fromhex(case["device_nonce"])
    device_id = case["device_id"]
    session_key = auth.derive_session_key(key, host_nonce, device_nonce)
    assert session_key.hex() == case["session_key"]
    for role in ("host", "device"):
        proof = auth.auth_proof(
            key, role=role, host_nonce=host_nonce, device_nonce=device_nonce, device_id=device_id
        )
        assert proof.hex() == case[f"{role}_proof"]
    # The formulas of docs/protocol.md, computed here with hmac directly.
    ident = device_id.encode()
    suffix = host_nonce + device_nonce + bytes([len(ident)]) + ident
    assert (
        hmac.new(key, b"eigencast/v1 host-auth\x00" + suffix, hashlib.sha256).hexdigest()
        == case["host_proof"]
    )
    assert (
        hmac.new(
            key, b"eigencast/v1 session\x00" + host_nonce + device_nonce, hashlib.sha256
        ).hexdigest()
        == case["session_key"]
    )


def _hand_tag(msg, session_key: bytes) -> bytes:
    """The tag formula of docs/protocol.md, recomputed by hand: HMAC-SHA256 over the session
    counter (8 bytes, little-endian), the message type and the canonical CBOR body without
    its tag."""
    body = dict(cbor2.loads(msg.to_body()))
    del body[m.SESSION_TAG_KEY]
    data = (
        msg.session_counter.to_bytes(8, "little")
        + bytes([int(msg.TYPE)])
        + cbor2.dumps(body, canonical=True)
    )
    return hmac.new(session_key, data, hashlib.sha256).digest()


def test_signed_golden_lines_verify_with_the_golden_session_key():
    (case_auth,) = AUTH_CASES
    session_key = bytes.fromhex(case_auth["session_key"])
    signed = [c for c in MESSAGE_CASES if _class(c["class"]).SIGNED]
    assert signed
    for case in signed:
        msg = _record_from_json(_class(case["class"]), case["kwargs"])
        assert auth.verify(msg, session_key, msg.session_counter - 1) == msg.session_counter
        assert _hand_tag(msg, session_key) == msg.session_tag


def test_tagged_event_golden_lines_verify_with_the_golden_session_key():
    (case_auth,) = AUTH_CASES
    session_key = bytes.fromhex(case_auth["session_key"])
    tagged = [c for c in MESSAGE_CASES if _class(c["class"]).TAGGED]
    assert {_class(c["class"]).TYPE for c in tagged} == {m.MessageType.SCORES,
                                                          m.MessageType.IMAGE_CHUNK}
    for case in tagged:
        msg = _record_from_json(_class(case["class"]), case["kwargs"])
        assert auth.verify_event(msg, session_key, msg.session_counter - 1) == msg.session_counter
        # docs/protocol.md section 5: the signed-request formula, truncated to 16 bytes.
        assert _hand_tag(msg, session_key)[:16] == msg.session_tag


# --------------------------------------------------------------------------- docs


DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def _doc_section(text: str, msg_type: int) -> str:
    """The '### ...' section of docs/protocol.md whose heading names 0xNN."""
    marker = f"0x{msg_type:02X} "
    for section in text.split("\n### ")[1:]:
        heading = section.splitlines()[0]
        if marker in heading + " ":
            return section
    raise AssertionError(f"docs/protocol.md has no section for 0x{msg_type:02X}")


@pytest.mark.parametrize("cls", list(m.MESSAGE_CLASSES.values()), ids=lambda c: c.__name__)
def test_protocol_doc_matches_the_declarations(cls):
    """docs/protocol.md is what a C implementer reads: keep it in step with the code."""
    text = DOC.read_text()
    row = f"| 0x{int(cls.TYPE):02X} | {cls.TYPE.name} | "
    (line,) = [ln for ln in text.splitlines() if ln.startswith(row)]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[3:5] == [cls.CHANNEL.name, cls.KIND.name]
    assert (cells[6] == "yes") == cls.SIGNED
    section = _doc_section(text, int(cls.TYPE))
    for spec in cls._specs():
        if spec.key in (m.SESSION_COUNTER_KEY, m.SESSION_TAG_KEY) and "| 22, 23 |" in section:
            continue
        assert f"| {spec.key} | `{spec.name}` |" in section, (cls.__name__, spec.name)


def test_protocol_doc_describes_slot_info():
    section = DOC.read_text().split("### SlotInfo", 1)[1].split("\n### ", 1)[0]
    for spec in m.SlotInfo._specs():
        assert f"| {spec.key} | `{spec.name}` |" in section


def test_protocol_doc_lists_every_error_code():
    text = DOC.read_text()
    for code in m.ErrorCode:
        cls = m.ERROR_CLASSES[code]
        assert f"| {int(code)} | {code.name} |" in text
        assert cls.__name__ in text


# --------------------------------------------------------------------------- regeneration


def _golden_messages() -> list[tuple[str, m.Message, int]]:
    """The cases written to messages.jsonl (fixed ids, counters, keys and nonces)."""
    (case_auth,) = AUTH_CASES
    sk = bytes.fromhex(case_auth["session_key"])
    digest = hashlib.sha256(b"eigencast golden image").digest()
    return [*_session_messages(case_auth, sk, _golden_slots(digest)),
            *_image_messages(sk, digest), *_stream_messages(sk)]


def _golden_slots(digest: bytes) -> tuple[m.SlotInfo, m.SlotInfo]:
    """Slot A confirmed and active with the golden image, slot B empty."""
    return (
        m.SlotInfo(
            slot=0,
            state=m.SlotState.CONFIRMED,
            active=True,
            generation=1700000000,
            size_bytes=1234567,
            digest=digest,
        ),
        m.SlotInfo(
            slot=1, state=m.SlotState.EMPTY, active=False, generation=0, size_bytes=0, digest=b""
        ),
    )


def _session_messages(case_auth: dict, sk: bytes, slots: tuple[m.SlotInfo, m.SlotInfo]
                      ) -> list[tuple[str, m.Message, int]]:
    """The session's messages: handshake, AUTH, PING, errors, BYE, signed requests, slots."""
    return [
        (
            "hello",
            m.Hello(min_version=2, max_version=2, nonce=bytes(range(16)), host_id="host-1"),
            1,
        ),
        (
            "hello_reply",
            m.HelloReply(
                min_version=2,
                max_version=2,
                device_id="dev-1",
                nonce=bytes(range(16, 32)),
                max_frame_bytes=4096,
                ram_budget_bytes=64 << 20,
                slot_size_bytes=64 << 20,
                display_width=300,
                display_height=300,
                rx_window_frames=8,
                rx_buffer_bytes=2048,
                slots=slots,
                has_key=True,
                image_format_versions=(1,),
                software="eigencast 0.1.0",
            ),
            1,
        ),
        ("auth_challenge", m.AuthChallenge(host_proof=bytes.fromhex(case_auth["host_proof"])), 2),
        (
            "auth_response",
            m.AuthResponse(device_proof=bytes.fromhex(case_auth["device_proof"]), slots=slots,
                           ram_budget_bytes=64 << 20, slot_size_bytes=64 << 20),
            2,
        ),
        ("ping", m.Ping(payload=b"hi", sent_us=123456789), 3),
        ("pong", m.Pong(payload=b"hi", ping_sent_us=123456789, sent_us=123457000), 3),
        (
            "error",
            m.Error(
                code=m.ErrorCode.TOO_LARGE_FOR_FLASH,
                where="IMAGE_BEGIN",
                message="image is 60000000 bytes, slot holds 50331648",
                detail={"size_bytes": 60000000, "limit_bytes": 50331648},
            ),
            4,
        ),
        (
            "error_busy",
            m.Error(
                code=m.ErrorCode.BUSY,
                where="HELLO",
                message="the device is serving another host; try again when that one is done",
            ),
            1,
        ),
        ("ok", m.Ok(), 5),
        ("bye", m.Bye(reason="done"), 0),
        ("set_baud", auth.sign(m.SetBaud(baud=921600, revert_timeout_ms=2000), sk, 7), 6),
        ("reset", auth.sign(m.Reset(reason="test"), sk, 8), 7),
        ("slot_set",
         auth.sign(m.SlotSet(action=m.SlotAction.ACTIVATE, slot=1, force=True), sk, 9), 8),
        ("slot_status", m.SlotStatus(slots=slots), 8),
    ]


def _image_messages(sk: bytes, digest: bytes) -> list[tuple[str, m.Message, int]]:
    """An image transfer's messages, IMAGE_BEGIN to IMAGE_ABORT."""
    return [
        (
            "image_begin",
            auth.sign(
                m.ImageBegin(
                    size_bytes=52428800,
                    digest=digest,
                    image_tag=bytes([0x33]) * 32,
                    format_version=1,
                    generation=1700000001,
                ),
                sk,
                10,
            ),
            9,
        ),
        ("image_status", m.ImageStatus(digest=digest, size_bytes=52428800), 10),
        ("image_status_reply", m.ImageStatusReply(next_offset=65536, in_progress=True), 10),
        ("image_chunk", auth.tag_event(m.ImageChunk(offset=4096, data=bytes(range(32))), sk, 1), 9),
        ("image_ack", m.ImageAck(next_offset=8192, credits=7, window_bytes=32768), 9),
        ("image_verify", m.ImageVerify(digest=digest), 11),
        (
            "image_verify_reply",
            m.ImageVerifyReply(ok=True, digest=digest, tag_ok=True, size_bytes=52428800),
            11,
        ),
        ("image_commit", auth.sign(m.ImageCommit(digest=digest), sk, 11), 12),
        ("image_abort", auth.sign(m.ImageAbort(), sk, 12), 13),
    ]


def _stream_messages(sk: bytes) -> list[tuple[str, m.Message, int]]:
    """Serving's messages: SCORES, requests, NOTICE."""
    return [
        ("scores",
         auth.tag_event(m.Scores(sequence=42, packet=bytes.fromhex("28b52ffd0400")), sk, 3), 0),
        ("scores_look",
         auth.tag_event(m.Scores(sequence=42, packet=bytes.fromhex("28b52ffd0400"), look=1),
                        sk, 4), 0),
        ("view_request", m.ViewRequest(phi_deg=123.5, theta_deg=-12.0, sequence=42), 0),
        ("view_request_look",
         m.ViewRequest(phi_deg=123.5, theta_deg=-12.0, sequence=42, look=2), 0),
        ("keyframe_request", m.KeyframeRequest(sequence=43, last_frame=41), 0),
        ("notice", m.Notice(level=1, text="reverted to slot A at boot", detail={"slot": 0}), 0),
    ]


def _regenerate() -> None:
    key = bytes(range(0xA0, 0xC0))
    host_nonce = bytes(range(16))
    device_nonce = bytes(range(16, 32))
    case_auth = {
        "name": "dev-1",
        "device_key": key.hex(),
        "host_nonce": host_nonce.hex(),
        "device_nonce": device_nonce.hex(),
        "device_id": "dev-1",
        "session_key": auth.derive_session_key(key, host_nonce, device_nonce).hex(),
        "host_proof": auth.auth_proof(
            key, role="host", host_nonce=host_nonce, device_nonce=device_nonce, device_id="dev-1"
        ).hex(),
        "device_proof": auth.auth_proof(
            key, role="device", host_nonce=host_nonce, device_nonce=device_nonce, device_id="dev-1"
        ).hex(),
    }
    (GOLDEN / "auth.jsonl").write_text(json.dumps(case_auth) + "\n")
    AUTH_CASES[:] = [case_auth]
    lines = []
    for name, msg, request_id in _golden_messages():
        flags = 1 if msg.MUST_UNDERSTAND else 0
        kwargs = {
            f.name: _to_json(getattr(msg, f.name))
            for f in dataclasses.fields(msg)
            if getattr(msg, f.name) is not None
        }
        lines.append(
            json.dumps(
                {
                    "name": name,
                    "class": f"{type(msg).__module__}.{type(msg).__name__}",
                    "request_id": request_id,
                    "flags": flags,
                    "kwargs": kwargs,
                    "frame": msg.encode(request_id=request_id, flags=flags).hex(),
                }
            )
        )
    (GOLDEN / "messages.jsonl").write_text("\n".join(lines) + "\n")
    print(f"wrote {len(lines)} message vectors and 1 auth vector to {GOLDEN}")


if __name__ == "__main__":
    if sys.argv[1:] != ["--regenerate"]:
        sys.exit("usage: python tests/test_golden.py --regenerate")
    _regenerate()
