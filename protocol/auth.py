"""Authentication maths: AUTH proofs, the session key, signed requests and event tags.

Everything a session's security rests on, as pure functions of keys, nonces and
messages (docs/protocol.md, section 5 "Session and authentication", 5.1 "Event tags"):

* :func:`auth_proof`: each side's AUTH proof, ``HMAC-SHA256(device_key, label ||
  host_nonce || device_nonce || u8(len(id)) || id)`` with a label per role;
* :func:`derive_session_key`: ``HMAC-SHA256(device_key, b"eigencast/v1 session\\0" ||
  host_nonce || device_nonce)``;
* :func:`sign` / :func:`verify`: the session tag of a mutating request,
  ``HMAC-SHA256(session_key, u64le(counter) || u8(TYPE) || canonical body without key
  23)``, and its check (tag present, tag correct, counter above the last accepted);
* :func:`tag_event` / :func:`verify_event`: the same construction truncated to 16 bytes
  for SCORES and IMAGE_CHUNK, one counter per channel.

The messages it signs are declared in :mod:`protocol.messages` (``SignedRequest``,
``TaggedEvent``), which also resolves these names (``m.sign``) for older callers.
``tests/golden/auth.jsonl`` pins the formulas.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import struct

import cbor2

from protocol.errors import AuthenticationError, NotAuthenticated, ReplayError
from protocol.messages import (
    EVENT_TAG_BYTES,
    KEY_BYTES,
    NONCE_BYTES,
    SESSION_COUNTER_KEY,
    SESSION_TAG_KEY,
    U64,
    SignedRequest,
    TaggedEvent,
)

__all__ = ["auth_proof", "derive_session_key", "sign", "tag_event", "verify", "verify_event"]

_HOST_LABEL = b"eigencast/v1 host-auth\x00"
_DEVICE_LABEL = b"eigencast/v1 device-auth\x00"
_SESSION_LABEL = b"eigencast/v1 session\x00"
_TAG_PREFIX = struct.Struct("<QB")


def _check_counter(counter: int, where: str) -> None:
    if isinstance(counter, bool) or not isinstance(counter, int) or not 1 <= counter <= U64:
        raise ValueError(f"{where}: counter={counter!r} must be an int in [1, 2**64 - 1]")


def _check_key(key: bytes, name: str) -> bytes:
    if not isinstance(key, (bytes, bytearray)) or len(key) != KEY_BYTES:
        size = len(key) if isinstance(key, (bytes, bytearray)) else type(key).__name__
        raise ValueError(f"{name} must be {KEY_BYTES} bytes, got {size}")
    return bytes(key)


def _check_nonce(nonce: bytes, name: str) -> bytes:
    if not isinstance(nonce, (bytes, bytearray)) or len(nonce) != NONCE_BYTES:
        size = len(nonce) if isinstance(nonce, (bytes, bytearray)) else type(nonce).__name__
        raise ValueError(f"{name} must be {NONCE_BYTES} bytes, got {size}")
    return bytes(nonce)


def auth_proof(
    device_key: bytes, *, role: str, host_nonce: bytes, device_nonce: bytes, device_id: str
) -> bytes:
    """Return the AUTH proof of ``role`` ("host" or "device").

    ``HMAC-SHA256(device_key, label || host_nonce || device_nonce ||
    u8(len(id)) || id)`` where ``label`` is ``b"eigencast/v1 host-auth\\0"`` or
    ``b"eigencast/v1 device-auth\\0"`` and ``id`` is the device id in UTF-8.
    Distinct labels stop one side's proof being reflected as the other's.

    Parameters
    ----------
    device_key : bytes of length 32
    role : {"host", "device"}
    host_nonce, device_nonce : bytes of length 16
    device_id : str
        At most 64 UTF-8 bytes.

    Returns
    -------
    bytes of length 32
    """
    key = _check_key(device_key, "device_key")
    labels = {"host": _HOST_LABEL, "device": _DEVICE_LABEL}
    if role not in labels:
        raise ValueError(f"role={role!r} must be one of {sorted(labels)}")
    ident = device_id.encode("utf-8")
    if not 1 <= len(ident) <= 64:
        raise ValueError(f"device_id of {len(ident)} UTF-8 bytes must be 1..64")
    data = (
        labels[role]
        + _check_nonce(host_nonce, "host_nonce")
        + _check_nonce(device_nonce, "device_nonce")
        + bytes([len(ident)])
        + ident
    )
    return hmac.new(key, data, hashlib.sha256).digest()


def derive_session_key(device_key: bytes, host_nonce: bytes, device_nonce: bytes) -> bytes:
    """Return the session key ``HMAC-SHA256(device_key, b"eigencast/v1 session\\0" ||
    host_nonce || device_nonce)``.

    Parameters
    ----------
    device_key : bytes of length 32
    host_nonce, device_nonce : bytes of length 16
        From HELLO and HELLO_REPLY of this session.

    Returns
    -------
    bytes of length 32
    """
    key = _check_key(device_key, "device_key")
    data = (
        _SESSION_LABEL
        + _check_nonce(host_nonce, "host_nonce")
        + _check_nonce(device_nonce, "device_nonce")
    )
    return hmac.new(key, data, hashlib.sha256).digest()


def _session_tag(msg: SignedRequest, session_key: bytes, counter: int) -> bytes:
    unsigned = dataclasses.replace(msg, session_counter=counter, session_tag=None)
    data = _TAG_PREFIX.pack(counter, int(msg.TYPE)) + unsigned.to_body()
    return hmac.new(session_key, data, hashlib.sha256).digest()


def sign(msg: SignedRequest, session_key: bytes, counter: int) -> SignedRequest:
    """Return ``msg`` with ``session_counter=counter`` and its session tag.

    The tag is ``HMAC-SHA256(session_key, u64le(counter) || u8(TYPE) || body)``
    where ``body`` is the canonical CBOR body with key 22 (the counter) and
    without key 23 (the tag).

    Parameters
    ----------
    msg : SignedRequest
        A mutating request (``msg.SIGNED``).
    session_key : bytes of length 32
        From :func:`derive_session_key`.
    counter : int
        1..2**64-1, larger than every counter used before in this session.

    Returns
    -------
    SignedRequest
        A new message of the same class.
    """
    if not isinstance(msg, SignedRequest):
        raise ValueError(f"sign: {type(msg).__name__} is not a signed request")
    key = _check_key(session_key, "session_key")
    _check_counter(counter, "sign")
    tag = _session_tag(msg, key, counter)
    return dataclasses.replace(msg, session_counter=counter, session_tag=tag)


def verify(msg: SignedRequest, session_key: bytes, last_counter: int) -> int:
    """Check a signed request; return its counter (store it as the new ``last_counter``).

    Parameters
    ----------
    msg : SignedRequest
        As decoded from the wire.
    session_key : bytes of length 32
    last_counter : int
        The highest counter accepted so far in this session (0 at the start).

    Returns
    -------
    int
        ``msg.session_counter``.

    Raises
    ------
    NotAuthenticated
        The message carries no counter or tag.
    AuthenticationError
        The tag does not verify (wrong key, or altered message).
    ReplayError
        The tag verifies but the counter is not above ``last_counter``.
    """
    if not isinstance(msg, SignedRequest):
        raise ValueError(f"verify: {type(msg).__name__} is not a signed request")
    key = _check_key(session_key, "session_key")
    name = msg.TYPE.name
    if msg.session_counter is None or msg.session_tag is None:
        raise NotAuthenticated(f"verify {name}: no session tag (mutating requests must be signed)")
    expected = _session_tag(msg, key, msg.session_counter)
    if not hmac.compare_digest(expected, msg.session_tag):
        raise AuthenticationError(
            f"verify {name}: session tag mismatch (wrong session key or altered message)"
        )
    if msg.session_counter <= last_counter:
        raise ReplayError(
            f"verify {name}: session counter {msg.session_counter} is not above the last "
            f"accepted {last_counter} (replayed or stale request)"
        )
    return msg.session_counter


def _event_tag(msg: TaggedEvent, session_key: bytes, counter: int) -> bytes:
    # The canonical body with key 22 = counter and without key 23, built from the checked
    # fields directly (no re-validation of the payload: this runs for every frame).
    body = msg._to_map()
    body.pop(SESSION_TAG_KEY, None)
    body[SESSION_COUNTER_KEY] = counter
    mac = hmac.new(session_key, _TAG_PREFIX.pack(counter, int(msg.TYPE)), hashlib.sha256)
    mac.update(cbor2.dumps(body, canonical=True))
    return mac.digest()[:EVENT_TAG_BYTES]


def tag_event(msg: TaggedEvent, session_key: bytes, counter: int) -> TaggedEvent:
    """Return ``msg`` with ``session_counter=counter`` and its 16-byte event tag.

    The tag is ``HMAC-SHA256(session_key, u64le(counter) || u8(TYPE) || body)[:16]``
    where ``body`` is the canonical CBOR body with key 22 (the counter) and
    without key 23 (the tag): the signed-request construction of :func:`sign`,
    truncated to 16 bytes. Each channel (SCORES, IMAGE_CHUNK) has its own counter.

    Parameters
    ----------
    msg : TaggedEvent
        A SCORES or IMAGE_CHUNK.
    session_key : bytes of length 32
    counter : int
        1..2**64-1, larger than every counter used before on this channel in this session.

    Returns
    -------
    TaggedEvent
        A new message of the same class.
    """
    if not isinstance(msg, TaggedEvent):
        raise ValueError(f"tag_event: {type(msg).__name__} is not a tagged event")
    key = _check_key(session_key, "session_key")
    _check_counter(counter, "tag_event")
    return dataclasses.replace(msg, session_counter=counter,
                               session_tag=_event_tag(msg, key, counter))


def verify_event(msg: TaggedEvent, session_key: bytes, last_counter: int) -> int:
    """Check a tagged event; return its counter (the channel's new ``last_counter``).

    Raises
    ------
    NotAuthenticated
        No counter or tag.
    AuthenticationError
        The tag does not verify.
    ReplayError
        The counter is not above ``last_counter``.
    """
    if not isinstance(msg, TaggedEvent):
        raise ValueError(f"verify_event: {type(msg).__name__} is not a tagged event")
    key = _check_key(session_key, "session_key")
    name = msg.TYPE.name
    if msg.session_counter is None or msg.session_tag is None:
        raise NotAuthenticated(f"verify {name}: no event tag (a keyed device needs one)")
    expected = _event_tag(msg, key, msg.session_counter)
    if not hmac.compare_digest(expected, msg.session_tag):
        raise AuthenticationError(f"verify {name}: event tag mismatch")
    if msg.session_counter <= last_counter:
        raise ReplayError(
            f"verify {name}: counter {msg.session_counter} is not above the last accepted "
            f"{last_counter} (replayed)"
        )
    return msg.session_counter
