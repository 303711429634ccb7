"""The host's session on a :class:`~protocol.link.Link`: HELLO, AUTH, signed requests.

:class:`HostSession` is what the host says to a device once the link engine runs: HELLO
(version negotiation, :func:`negotiate_version`), mutual AUTH (the session key of
``protocol.auth``), signed mutating requests with a monotonic counter, tagged events
(IMAGE_CHUNK, SCORES), PING, and :meth:`HostSession.set_baud` (switch, ping at the new
rate, fall back when the device reverts). The device's side of the same conversation is
``device_runtime/device.py``.

It sits on top of the engine (it only calls :class:`~protocol.link.Link`'s public
methods) and is re-exported by ``protocol.link``. docs/protocol.md ("Session and
authentication", "State machines") is the specification.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hmac
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from protocol import auth
from protocol import messages as m
from protocol.errors import (
    AuthenticationError,
    MalformedMessage,
    ProtocolError,
    RemoteAuthFailed,
    TransportError,
    TransportTimeout,
    WrongKey,
)
from protocol.keys import key_fingerprint
from protocol.link import DEFAULT_REQUEST_TIMEOUT_S, DEFAULT_RETRIES

if TYPE_CHECKING:
    from protocol.link import Link

__all__ = ["HostSession", "negotiate_version"]


def negotiate_version(
    ours: tuple[int, int], theirs: tuple[int, int]
) -> int | None:
    """Return the highest protocol version in both ranges, or None when they do not overlap."""
    low, high = max(ours[0], theirs[0]), min(ours[1], theirs[1])
    return high if low <= high else None


@dataclass
class HostSession:
    """The host's side of one session: HELLO, AUTH, signed requests, tagged events
    (SCORES, IMAGE_CHUNK: :meth:`tag_event`, :meth:`send_scores`), PING, SET_BAUD.

    Parameters
    ----------
    link : Link
        Started.
    key : bytes or None
        The device key (32 bytes); None for a device without one (``--insecure``).
    host_id : str
        Informational, sent in HELLO.
    versions : tuple of int
        (min, max) protocol versions this host speaks.
    insecure : bool
        With a ``key``: still talk to a device whose HELLO_REPLY says it holds no key
        (unauthenticated, ``--insecure``). Without it such a device is refused: it may be
        an impostor, or a man in the middle who cleared ``has_key`` (a downgrade).

    Attributes
    ----------
    hello : HelloReply or None
        The device's HELLO_REPLY; from a keyed device completed after AUTH with the slots
        and budgets its AUTH_RESPONSE carries (HELLO_REPLY hides them before AUTH).
    version : int
        Negotiated protocol version.
    authenticated : bool
        Mutual AUTH succeeded (signed requests carry session tags).
    """

    link: Link
    key: bytes | None = None
    host_id: str = "eigencast"
    versions: tuple[int, int] = (m.PROTOCOL_VERSION, m.PROTOCOL_VERSION)
    request_timeout_s: float = DEFAULT_REQUEST_TIMEOUT_S
    retries: int = DEFAULT_RETRIES
    insecure: bool = False
    hello: m.HelloReply | None = None
    version: int = 0
    authenticated: bool = False
    _session_key: bytes | None = field(default=None, repr=False)
    _counter: int = 0
    _host_nonce: bytes = b""
    _event_counters: dict[int, int] = field(default_factory=dict, repr=False)
    _event_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    # ------------------------------------------------------------------ setup
    def start(self) -> m.HelloReply:
        """HELLO (+ AUTH when the device holds a key); return the HELLO_REPLY.

        Raises
        ------
        RemoteUnsupportedVersion, ProtocolError
            No common protocol version (one line naming both ranges).
        AuthenticationError
            The device holds a key and none was given, or a proof does not verify, or a
            key was given and the device says it holds none (unless ``insecure``).
        """
        self._host_nonce = os.urandom(m.NONCE_BYTES)
        hello = self.link.request(
            m.Hello(
                min_version=self.versions[0],
                max_version=self.versions[1],
                nonce=self._host_nonce,
                host_id=self.host_id,
            ),
            timeout_s=self.request_timeout_s,
            retries=self.retries,
        )
        assert isinstance(hello, m.HelloReply)
        version = negotiate_version(self.versions, (hello.min_version, hello.max_version))
        if version is None:
            raise ProtocolError(
                f"{self.link.name}: the device speaks protocol versions "
                f"{hello.min_version}..{hello.max_version}, this host "
                f"{self.versions[0]}..{self.versions[1]}: update the older side"
            )
        self.hello, self.version = hello, version
        self.link.set_tx_max_frame_bytes(
            min(hello.max_frame_bytes, max(self.link.transport.max_frame_bytes,
                                           m.BASELINE_MAX_FRAME_BYTES))
        )
        if hello.has_key:
            self.authenticate()
        elif self.key is not None and not self.insecure:
            raise AuthenticationError(
                f"{self.link.name}: a key was given but the device '{hello.device_id}' says it "
                "holds no key: it may be an impostor or the link is tampered with; pair the "
                "device (eigencast-device --pair KEYFILE) or pass --insecure to send to a "
                "keyless device anyway"
            )
        return self.hello

    def authenticate(self) -> None:
        """Mutual AUTH: send our proof, check the device's, derive the session key."""
        hello = self.hello
        if hello is None:
            raise ValueError("authenticate: call start() first")
        if self.key is None:
            raise AuthenticationError(
                f"the device '{hello.device_id}' holds a key: pass the same key (--key KEYFILE)"
            )
        host_proof = auth.auth_proof(
            self.key,
            role="host",
            host_nonce=self._host_nonce,
            device_nonce=hello.nonce,
            device_id=hello.device_id,
        )
        try:
            reply = self.link.request(
                m.AuthChallenge(host_proof=host_proof),
                timeout_s=self.request_timeout_s,
                retries=self.retries,
            )
        except RemoteAuthFailed as exc:  # the one way our proof fails: another key
            raise WrongKey(
                f"wrong key: the device '{hello.device_id}' does not accept key "
                f"{key_fingerprint(self.key)}; pass the key it was paired with "
                "(the device logs its fingerprint at start; eigencast-device --status shows it)",
                detail=str(exc),
            ) from None
        assert isinstance(reply, m.AuthResponse)
        expected = auth.auth_proof(
            self.key,
            role="device",
            host_nonce=self._host_nonce,
            device_nonce=hello.nonce,
            device_id=hello.device_id,
        )
        if not hmac.compare_digest(expected, reply.device_proof):
            raise AuthenticationError(
                f"the device '{hello.device_id}' answered with a proof that does not verify: "
                "it is not the device this key belongs to (or a man in the middle)"
            )
        self._session_key = auth.derive_session_key(self.key, self._host_nonce, hello.nonce)
        self._counter = 0
        self._event_counters = {}
        self.authenticated = True
        # A keyed device tells its slots and budgets only after AUTH (protocol 2).
        full = {
            name: getattr(reply, name)
            for name in ("slots", "ram_budget_bytes", "slot_size_bytes", "predicts")
            if getattr(reply, name) is not None
        }
        if full:
            self.hello = dataclasses.replace(hello, **full)

    # ------------------------------------------------------------------ requests
    def sign(self, msg: m.SignedRequest) -> m.SignedRequest:
        """Return ``msg`` signed with the next counter (unsigned when not authenticated)."""
        if self._session_key is None:
            return msg
        self._counter += 1
        return auth.sign(msg, self._session_key, self._counter)

    def tag_event(self, msg: m.TaggedEvent) -> m.TaggedEvent:
        """Return SCORES/IMAGE_CHUNK ``msg`` tagged with its channel's next counter
        (unchanged when not authenticated: a keyless device takes it untagged)."""
        if self._session_key is None:
            return msg
        with self._event_lock:
            counter = self._event_counters.get(int(msg.TYPE), 0) + 1
            self._event_counters[int(msg.TYPE)] = counter
        return auth.tag_event(msg, self._session_key, counter)

    def send_scores(self, msg: m.Scores, *,
                    after_sent: Callable[[], None] | None = None) -> None:
        """Tag (when authenticated) and queue a SCORES event; counters leave in send order."""
        with self._event_lock:
            if self._session_key is not None:
                counter = self._event_counters.get(int(msg.TYPE), 0) + 1
                self._event_counters[int(msg.TYPE)] = counter
                msg = auth.tag_event(msg, self._session_key, counter)  # type: ignore[assignment]
            self.link.send(msg, after_sent=after_sent)

    def call(
        self,
        msg: m.Message,
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
        on_reply: Callable[[int, m.Message], None] | None = None,
    ) -> m.Message:
        """Send a request (signing it if it is a signed type) and return its reply."""
        if isinstance(msg, m.SignedRequest):
            msg = self.sign(msg)
        return self.link.request(
            msg,
            timeout_s=self.request_timeout_s if timeout_s is None else timeout_s,
            retries=self.retries if retries is None else retries,
            on_reply=on_reply,
        )

    def ping(self, *, payload: bytes = b"", timeout_s: float | None = None,
             retries: int | None = None) -> float:
        """PING; return the round-trip time in seconds."""
        start = time.monotonic()
        reply = self.call(
            m.Ping(payload=payload, sent_us=int(start * 1e6)),
            timeout_s=timeout_s,
            retries=retries,
        )
        assert isinstance(reply, m.Pong)
        if reply.payload != payload:
            raise MalformedMessage(f"{self.link.name}: PONG does not echo the PING payload")
        return time.monotonic() - start

    def bye(self, reason: str = "") -> None:
        """Send BYE (best effort)."""
        with contextlib.suppress(ProtocolError, ValueError):
            self.link.send(m.Bye(reason=reason[:200]))

    def set_baud(self, baud: int, *, revert_timeout_ms: int = 2000) -> bool:
        """Switch both ends to ``baud``; return True on success.

        SET_BAUD is answered OK at the old rate; then this side switches and
        PINGs at the new rate until the device answers or ``revert_timeout_ms``
        passes. On failure it waits until the device has reverted by itself,
        switches back and checks with a PING at the old rate (``False``).

        Raises
        ------
        RemoteError
            The device refused (e.g. ``UNSUPPORTED`` for that rate).
        TransportError
            Neither rate answers afterwards.
        """
        old = getattr(self.link.transport, "baud", None)
        self.call(m.SetBaud(baud=baud, revert_timeout_ms=revert_timeout_ms), retries=0)
        self.link.wait_writer_idle()
        switched_at = time.monotonic()
        self.link.switch_baud(baud)
        deadline = switched_at + revert_timeout_ms / 1000.0
        attempt_timeout = min(0.05 + revert_timeout_ms / 8000.0, 0.5)
        while time.monotonic() + attempt_timeout < deadline:
            try:
                self.ping(timeout_s=attempt_timeout, retries=0)
                return True
            except TransportTimeout:
                self.link.send_raw(b"\x00")
        if old is None:
            raise TransportError(f"{self.link.name}: SET_BAUD {baud}: no answer at the new rate")
        # Let the device revert, then go back ourselves.
        left = deadline - time.monotonic() + 0.05
        if left > 0:
            time.sleep(left)  # the device's revert deadline: a protocol timer, not a race fix
        self.link.switch_baud(int(old))
        try:
            self.ping(timeout_s=0.2, retries=4)
        except TransportTimeout:
            raise TransportError(
                f"{self.link.name}: SET_BAUD {baud}: no answer at the new rate, and none at "
                f"{old} after the revert either"
            ) from None
        return False
