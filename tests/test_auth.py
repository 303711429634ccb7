"""Authentication maths (protocol/auth.py): AUTH proofs by the documented formula, session
keys, signed requests (tampering, wrong key, type binding, replay, unsigned). The golden
vectors are checked in test_golden.py."""

from __future__ import annotations

import dataclasses
import hashlib
import hmac

import pytest

from protocol import auth
from protocol import messages as m
from protocol.errors import AuthenticationError, NotAuthenticated, ReplayError
from protocol.framing import FrameDecoder

DIGEST = hashlib.sha256(b"x").digest()
KEY = bytes(range(32))
HOST_NONCE = bytes(range(100, 116))
DEVICE_NONCE = bytes(range(200, 216))


def test_auth_proofs_follow_the_documented_formula_and_differ_by_role():
    args = {"host_nonce": HOST_NONCE, "device_nonce": DEVICE_NONCE, "device_id": "dev-α"}
    host = auth.auth_proof(KEY, role="host", **args)
    device = auth.auth_proof(KEY, role="device", **args)
    ident = "dev-α".encode()
    expected = hmac.new(
        KEY,
        b"eigencast/v1 device-auth\x00" + HOST_NONCE + DEVICE_NONCE + bytes([len(ident)]) + ident,
        hashlib.sha256,
    ).digest()
    assert device == expected and host != device
    assert auth.auth_proof(KEY, role="host", **{**args, "device_id": "dev-b"}) != host
    assert auth.auth_proof(bytes(32), role="host", **args) != host
    with pytest.raises(ValueError, match="role"):
        auth.auth_proof(KEY, role="peer", **args)
    with pytest.raises(ValueError, match="device_key must be 32 bytes, got 31"):
        auth.auth_proof(KEY[:31], role="host", **args)
    with pytest.raises(ValueError, match="host_nonce must be 16 bytes"):
        auth.derive_session_key(KEY, b"short", DEVICE_NONCE)


def _signed(counter: int = 5) -> tuple[m.SignedRequest, bytes]:
    sk = auth.derive_session_key(KEY, HOST_NONCE, DEVICE_NONCE)
    msg = m.SlotSet(action=m.SlotAction.ACTIVATE, slot=1)
    return auth.sign(msg, sk, counter), sk


def test_sign_and_verify_over_the_wire():
    signed, sk = _signed()
    (frame,) = FrameDecoder(256).feed(signed.encode(request_id=3))
    received = m.decode_message(frame)
    assert auth.verify(received, sk, last_counter=4) == 5


def test_verify_rejects_tampering():
    signed, sk = _signed()
    for changed in (
        dataclasses.replace(signed, slot=0),
        dataclasses.replace(signed, force=True),
        dataclasses.replace(signed, session_counter=6),
        dataclasses.replace(
            signed, session_tag=bytes([signed.session_tag[0] ^ 1]) + signed.session_tag[1:]
        ),
    ):
        with pytest.raises(AuthenticationError, match="session tag mismatch") as info:
            auth.verify(changed, sk, last_counter=0)
        assert not isinstance(info.value, ReplayError)


def test_verify_rejects_a_wrong_key_and_another_sessions_tag():
    signed, _ = _signed()
    other = auth.derive_session_key(KEY, HOST_NONCE, bytes(16))
    with pytest.raises(AuthenticationError, match="session tag mismatch"):
        auth.verify(signed, other, last_counter=0)


def test_tag_binds_the_message_type():
    """IMAGE_COMMIT and IMAGE_ABORT have the same body layout; a commit's tag must not
    authorise an abort carrying the same fields."""
    sk = auth.derive_session_key(KEY, HOST_NONCE, DEVICE_NONCE)
    commit = auth.sign(m.ImageCommit(digest=DIGEST), sk, 9)
    abort = m.ImageAbort(digest=DIGEST, session_counter=9, session_tag=commit.session_tag)
    assert abort.to_body() == commit.to_body()
    assert auth.verify(commit, sk, last_counter=0) == 9
    with pytest.raises(AuthenticationError, match="session tag mismatch"):
        auth.verify(abort, sk, last_counter=0)


def test_verify_rejects_replayed_and_stale_counters():
    signed, sk = _signed(counter=5)
    for last in (5, 6, 2**64 - 1):
        with pytest.raises(ReplayError, match=f"counter 5 is not above the last accepted {last}"):
            auth.verify(signed, sk, last_counter=last)


def test_verify_rejects_unsigned_requests():
    _, sk = _signed()
    with pytest.raises(NotAuthenticated, match="no session tag"):
        auth.verify(m.Reset(), sk, last_counter=0)
    with pytest.raises(ValueError, match="not a signed request"):
        auth.verify(m.Ping(sent_us=0), sk, last_counter=0)
    with pytest.raises(ValueError, match="counter=0"):
        auth.sign(m.Reset(), sk, 0)


def test_the_old_import_paths_resolve_to_this_module():
    # protocol.messages resolves the names it held before the split (``m.sign``)
    from protocol.messages import verify_event

    assert m.sign is auth.sign and m.tag_event is auth.tag_event
    assert verify_event is auth.verify_event
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        m.no_such_name  # noqa: B018
