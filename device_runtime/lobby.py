"""The lobby: where a keyed TCP device keeps connections that have not authenticated yet.

A keyed device serves one authenticated host at a time (its :class:`~protocol.link.Link`).
Before a connection has proved the key it lives here, and nothing it does decides who
else gets in (the references: an ordinary TCP server accepts everything pending; OpenSSH's
``MaxStartups`` / ``PerSourceMaxStartups`` and MCUboot/mcumgr bound unauthenticated
clients by count and time, and keep state behind authentication):

* **Accept everything pending**, every turn (up to ``WAITING`` connections held; past that
  the oldest of the address holding the most is closed), so the kernel's listen backlog
  never fills and a key holder's connection is never left unaccepted behind others.
* **Serve up to** ``PEERS`` **at once.** An active peer's frames are answered as a host's
  would be (:meth:`Device.lobby_frame`: HELLO, PING, the refusals of everything that needs
  authentication); accepted connections wait for a place in order of arrival, address by
  address in turn (the address with the fewest active peers goes first), so peers from
  one address cannot hold the key holder's place from another.
* **Bounded by time.** An active peer that has not authenticated ``auth_timeout_s`` after
  it became active is dropped; a waiting one ``auth_timeout_s`` after it was accepted. A
  waiting connection replaces an active peer that has had its place ``GRACE_S`` (a real
  host needs one round trip after its place, its HELLO already waiting, and the time to
  compute its proof), unless that
  peer's input waits for the lobby's budget while its own lasts; peers of the address with
  the most active peers go first, then those served most, then the longest active.
* **Bounded in work.** What the lobby does for a peer is measured in CPU time (this
  thread's: reading, decoding, answering, and the turn that waited for its bytes, split
  among the peers served in it): each active peer may use ``PEER_CPU`` (a burst, then
  seconds per second), all of them together ``LOBBY_CPU``, so a flood of PINGs, requests,
  zero bytes or bytes that never complete a frame costs the device's display at most that
  share of a core. A peer over its budget is not read (TCP pushes back) until its budget
  holds a quantum again, and its frames already read wait. Peers with work are served a
  quantum (``QUANTUM_S``) at a time, the least served first (start-time fair queuing), so
  a host's two frames wait for at most one quantum of each other peer, however much those
  send. Frames are at most ``MAX_FRAME_BYTES``; replies
  the peer does not read end its connection.
* **Leaving.** An AUTH_CHALLENGE whose proof verifies (:meth:`Device.proves_key`) ends the
  lobby's turn: the connection is handed to the transport (``TcpListenTransport.adopt``),
  with its session and the frames from the AUTH_CHALLENGE on, and the device serves it as
  its host; the lobby is *paused* (its clocks stopped, its connections kept) until that
  host leaves.

One thread (the device's ``run``) drives it; nothing here is thread-safe.
"""

from __future__ import annotations

import collections
import contextlib
import errno
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from protocol import messages as m
from protocol.errors import MalformedMessage
from protocol.framing import Frame, FrameDecoder, Kind

__all__ = [
    "GRACE_S",
    "LOBBY_CPU",
    "PEERS",
    "PEER_CPU",
    "WAITING",
    "Admitted",
    "Lobby",
    "LobbyStats",
]

PEERS = 32
"""Unauthenticated connections served side by side."""
WAITING = 256
"""Accepted connections waiting for a place at most (each costs a descriptor only)."""
GRACE_S = 1.0
"""An active peer may be replaced by a waiting connection after this long, seconds (or
``auth_timeout_s`` when shorter): a host has its HELLO answered at once (it is already
waiting in the socket) and needs one more round trip and its proof's computation for
AUTH_CHALLENGE (at 0.25 s a busy host often lost its place first)."""
PEER_CPU = (0.05, 0.02)
"""CPU seconds the lobby may spend on one active peer at once, and per second after that."""
LOBBY_CPU = (0.1, 0.06)
"""CPU seconds the lobby may spend on all its peers at once, and per second after that
(0.06: 6 % of a core)."""
READ_BYTES = 2048
"""Bytes read from a peer at a time, all decoded before its budget is checked again: so the
work done past a peer's budget is at most one such read (16 KB of VIEW_REQUESTs was
measured at up to 38 ms over; a HELLO or AUTH_CHALLENGE is about 100 bytes)."""
QUANTUM_S = 0.002
"""CPU time a peer is served at a time before the next peer's turn, seconds."""
MAX_FRAME_BYTES = 1024
"""Largest frame read in the lobby (HELLO and AUTH_CHALLENGE are about 100 bytes)."""
_ACCEPT_PER_TURN = 256
_TICK_S = 0.05


@dataclass
class LobbyStats:
    """Counters of the lobby (all sessions). ``expired``: dropped at their deadline;
    ``replaced``: active peers dropped for a waiting connection; ``shed``: waiting
    connections closed because ``WAITING`` were held; ``throttled``: times a peer's frames
    were left for later because its budget or the lobby's was spent; ``frames``,
    ``bytes_read``, ``cpu_s``: what peers sent that was read, and the CPU time it took."""

    accepted: int = 0
    admitted: int = 0
    expired: int = 0
    replaced: int = 0
    shed: int = 0
    throttled: int = 0
    frames: int = 0
    bytes_read: int = 0
    cpu_s: float = 0.0


@dataclass
class Admitted:
    """A connection whose AUTH_CHALLENGE verifies: its session (HELLO done), and the frames
    from the AUTH_CHALLENGE on plus the bytes of an unfinished one, to be read by the
    host's link before anything else."""

    session: Any
    frames: list[Frame]
    partial: bytes


class _Bucket:
    """A token bucket: ``burst`` at once, ``rate`` a second."""

    def __init__(self, burst: float, rate: float, now: float) -> None:
        self.burst, self.rate, self.level, self.at = burst, rate, burst, now

    def refill(self, now: float) -> float:
        self.level = min(self.burst, self.level + (now - self.at) * self.rate)
        self.at = now
        return self.level

    def until(self, level: float) -> float:
        """Seconds until the bucket holds more than ``level`` (after a refill)."""
        return max(0.0, (level - self.level) / self.rate) + 1e-3


@dataclass(eq=False)
class _Peer:
    sock: socket.socket
    source: str
    accepted: float
    active_since: float | None = None
    session: Any = None
    decoder: FrameDecoder = field(default_factory=lambda: FrameDecoder(MAX_FRAME_BYTES))
    cpu: _Bucket | None = None
    used: float = 0.0  # CPU seconds spent on it
    pending: collections.deque = field(default_factory=collections.deque)
    out: bytearray = field(default_factory=bytearray)
    starved: bool = False  # it went over its budget: it waits for a quantum of budget

    def activate(self, now: float) -> None:
        self.active_since = now
        self.cpu = _Bucket(*PEER_CPU, now)


class Lobby:
    """The unauthenticated connections of a keyed TCP device (see the module docstring).

    Parameters
    ----------
    transport : TcpListenTransport
        Whose listener it accepts from and to which it hands an authenticated connection.
    device : Device
        ``device.lobby_frame(session, msg, frame) -> (reply, session)`` answers a frame as
        the connection's own session; ``device.proves_key(session, msg)`` checks an
        AUTH_CHALLENGE; ``device.stats`` counts ``auth_timeouts`` and ``preempted``.
    auth_timeout_s : float
    log : callable
        ``log(reason, line)``: rate-limited lines (every line here is caused by a peer
        that has not authenticated).
    """

    def __init__(self, transport: Any, device: Any, *, auth_timeout_s: float,
                 log: Callable[[str, str], None]) -> None:
        self.transport = transport
        self.device = device
        self.auth_timeout_s = auth_timeout_s
        self.grace_s = min(GRACE_S, auth_timeout_s)
        self.log = log
        self.stats = LobbyStats()
        self._active: list[_Peer] = []
        self._waiting: dict[str, collections.deque[_Peer]] = {}
        self._n_waiting = 0
        self._paused_at: float | None = None
        self._cpu = _Bucket(*LOBBY_CPU, time.monotonic())
        self._accept_after = 0.0  # accepting failed (out of descriptors...): not before this
        self._vtime = 0.0  # fair queuing: the CPU time served to the peer served last
        self._starved = False

    # ------------------------------------------------------------------ public
    @property
    def peers(self) -> tuple[int, int]:
        """(active, waiting) connections now."""
        return len(self._active), self._n_waiting

    def admit(self, stop: threading.Event) -> Admitted | None:
        """Serve the lobby until a connection authenticates (returned, its socket adopted by
        the transport) or ``stop`` is set (None)."""
        self._resume()
        try:
            while not stop.is_set():
                admitted = self._turn(time.monotonic())
                if admitted is not None:
                    return admitted
            return None
        finally:
            self._paused_at = time.monotonic()

    def close(self) -> None:
        """Close every lobby connection."""
        for peer in self._active:
            self._close(peer)
        for queue in self._waiting.values():
            for peer in queue:
                self._close(peer)
        self._active, self._waiting, self._n_waiting = [], {}, 0

    # ------------------------------------------------------------------ one turn
    def _turn(self, now: float) -> Admitted | None:
        """One turn; its whole CPU time is charged to the peers served in it (a read that
        completes no frame costs a turn, not only the read)."""
        start = time.thread_time()
        served: list[_Peer] = []
        charged = self.stats.cpu_s
        try:
            return self._turn_body(now, served)
        finally:
            if served:
                overhead = (time.thread_time() - start) - (self.stats.cpu_s - charged)
                if overhead > 0:
                    self._charge_all(served, overhead)

    def _turn_body(self, now: float, served: list[_Peer]) -> Admitted | None:
        self._accept(now)
        self._expire(now)
        self._fill(now)
        # a starved lobby waits for a quantum of budget (it does not spin on crumbs)
        lobby_ok = self._cpu.refill(now) >= (QUANTUM_S if self._starved else 0.0)
        self._starved = not lobby_ok
        readers, busy = [], False
        wake = _TICK_S if lobby_ok else self._cpu.until(QUANTUM_S)
        for peer in self._active:
            # a peer over its budget waits for a quantum of it (a wake-up per read would
            # cost as much as the read, and serve no one)
            floor = QUANTUM_S if peer.starved else 0.0
            peer.starved = peer.cpu.refill(now) <= floor
            if peer.starved:
                wake = min(wake, peer.cpu.until(QUANTUM_S))
            elif not lobby_ok:
                continue
            elif peer.pending:
                busy = True  # frames read earlier wait for it: no need to wait for input
            else:
                readers.append(peer)
        writers = [p.sock for p in self._active if p.out]
        listen = [self.transport.listener] if now >= self._accept_after else []
        try:
            ready, writable, _ = select.select(
                [*listen, *(p.sock for p in readers)], writers, [], 0.0 if busy else wake)
        except (OSError, ValueError):  # a socket closed under us: the next turn sorts it out
            time.sleep(_TICK_S)
            return None
        ready_set = set(ready)
        for sock in writable:
            peer = next((p for p in self._active if p.sock is sock), None)
            if peer is not None:
                self._flush(peer)
        if not lobby_ok:
            return None
        # start-time fair queuing: a peer with work starts no earlier than the virtual time,
        # the least served goes first (ties: the longest active), each for a quantum
        backlog = [p for p in self._active
                   if not p.starved and (p.pending or p.sock in ready_set)]
        for peer in backlog:
            peer.used = max(peer.used, self._vtime)
        backlog.sort(key=lambda p: (p.used, p.active_since))
        for peer in backlog:
            if self._cpu.level <= 0:
                break
            if peer not in self._active:
                continue
            self._vtime = max(self._vtime, peer.used)
            served.append(peer)
            admitted = self._serve_peer(peer)
            if admitted is not None:
                return admitted
        return None

    def _accept(self, now: float) -> None:
        if now < self._accept_after:
            return
        listener = self.transport.listener
        for _ in range(_ACCEPT_PER_TURN):
            try:
                sock, address = listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # a connection gone before it was accepted, or no room
                if exc.errno != errno.ECONNABORTED:
                    self._accept_after = now + _TICK_S
                    self.log("accept", f"accepting a connection failed: {exc}")
                return
            self.hold(sock, address, now)

    def hold(self, sock: socket.socket, address: Any, now: float) -> None:
        """Take ``sock`` (accepted from the listener, e.g. while a host was served) as a
        waiting connection accepted at ``now`` (monotonic)."""
        sock.setblocking(False)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        source = str(address[0])
        self._waiting.setdefault(source, collections.deque()).append(_Peer(sock, source, now))
        self._n_waiting += 1
        self.stats.accepted += 1
        if self._n_waiting > WAITING:
            crowded = max(self._waiting.values(), key=len)
            self._drop_waiting(crowded, crowded[0])
            self.stats.shed += 1

    def _expire(self, now: float) -> None:
        limit = self.auth_timeout_s
        for peer in [p for p in self._active if now - p.active_since > limit]:
            self.device.stats.auth_timeouts += 1
            self.stats.expired += 1
            self.log("auth-timeout", f"peer did not authenticate within {limit:g} s; dropped")
            self._drop_active(peer)
        for queue in list(self._waiting.values()):
            while queue and now - queue[0].accepted > limit:
                self.stats.expired += 1
                self._drop_waiting(queue, queue[0])

    def _fill(self, now: float) -> None:
        """Give free places to waiting connections (the address with the fewest active
        peers first, then the longest waiting); replace peers past their grace."""
        while self._n_waiting:
            if len(self._active) >= PEERS and not self._replace_one(now):
                return
            per_source = collections.Counter(p.source for p in self._active)
            source = min(self._waiting, key=lambda s: (per_source[s], self._waiting[s][0].accepted))
            queue = self._waiting[source]
            peer = queue.popleft()
            self._n_waiting -= 1
            if not queue:
                del self._waiting[source]
            peer.activate(now)
            self._active.append(peer)

    def _replace_one(self, now: float) -> bool:
        """Drop one active peer past its grace for a waiting connection (False: none is).

        A peer whose input waits for the lobby's budget while its own budget lasts is owed an
        answer and kept (a host's AUTH_CHALLENGE behind a busy lobby); of the others, those
        of the address with the most places go first, then those served most."""
        due = [p for p in self._active if now - p.active_since >= self.grace_s]
        if not due:
            return False
        owed = self._owed([p for p in due if p.cpu.level > 0])
        due = [p for p in due if p not in owed]
        if not due:
            return False
        per_source = collections.Counter(p.source for p in self._active)
        victim = max(due, key=lambda p: (per_source[p.source], p.used, now - p.active_since))
        self.device.stats.preempted += 1
        self.stats.replaced += 1
        self.log("replaced", "an unauthenticated connection was replaced by a waiting one")
        self._drop_active(victim)
        return True

    @staticmethod
    def _owed(peers: list[_Peer]) -> set[_Peer]:
        """Those of ``peers`` with frames or bytes the lobby has not read yet."""
        owed = {p for p in peers if p.pending}
        rest = [p.sock for p in peers if not p.pending]
        if rest:
            try:
                readable, _, _ = select.select(rest, [], [], 0.0)
            except (OSError, ValueError):
                readable = []
            owed |= {p for p in peers if p.sock in readable}
        return owed

    # ------------------------------------------------------------------ one peer
    def _serve_peer(self, peer: _Peer) -> Admitted | None:
        """Read from ``peer`` (when none of its frames wait) and answer its frames while its
        budget and the lobby's last; charge the CPU time it took to both."""
        start = time.thread_time()
        try:
            if not peer.pending:
                try:
                    data = peer.sock.recv(READ_BYTES)
                except (BlockingIOError, InterruptedError):
                    return None
                except OSError:
                    data = b""
                if not data:
                    self._drop_active(peer)
                    return None
                self.stats.bytes_read += len(data)
                peer.pending.extend(peer.decoder.feed(data))
            while peer.pending:
                spent = time.thread_time() - start
                if peer.cpu.level - spent <= 0 or self._cpu.level - spent <= 0:
                    self.stats.throttled += 1  # the rest waits for the next budget
                    break
                if spent >= QUANTUM_S:  # the others' turn; the rest waits for the next
                    break
                self.stats.frames += 1
                admitted = self._frame(peer, peer.pending.popleft())
                if admitted is not None:
                    admitted.frames.extend(peer.pending)
                    return admitted
                if peer not in self._active:
                    return None
            self._flush(peer)
            return None
        finally:
            self._charge(peer, time.thread_time() - start)

    def _charge(self, peer: _Peer, spent: float) -> None:
        """``spent`` CPU seconds on ``peer``: off its budget and the lobby's."""
        peer.cpu.level -= spent
        peer.used += spent
        self._cpu.level -= spent
        self.stats.cpu_s += spent

    def _charge_all(self, peers: list[_Peer], spent: float) -> None:
        """``spent`` CPU seconds of a turn that served ``peers``, split evenly among them
        (one that left still counts against the lobby)."""
        share = spent / len(peers)
        for peer in peers:
            if peer.cpu is not None:
                self._charge(peer, share)

    def _frame(self, peer: _Peer, frame: Frame) -> Admitted | None:
        """Answer one frame of ``peer`` (as the link would); an AUTH_CHALLENGE that
        verifies admits it instead."""
        try:
            msg = m.decode_message(frame)
        except MalformedMessage as exc:
            if frame.kind == Kind.REQUEST:
                self._reply(peer, m.Error(code=m.ErrorCode.MALFORMED, where="lobby",
                                          message=" ".join(str(exc).split())[:200]),
                            frame.request_id)
            return None
        if isinstance(msg, m.UnknownMessage):
            if msg.must_understand and frame.kind in (Kind.REQUEST, Kind.EVENT):
                self._reply(peer, msg.error_reply(), frame.request_id)
            return None
        if frame.kind not in (Kind.REQUEST, Kind.EVENT):
            return None
        if isinstance(msg, m.AuthChallenge) and self.device.proves_key(peer.session, msg):
            return self._admit(peer, frame)
        reply, peer.session = self.device.lobby_frame(peer.session, msg, frame)
        if reply is not None and frame.kind == Kind.REQUEST:
            self._reply(peer, reply, frame.request_id)
        return None

    def _admit(self, peer: _Peer, frame: Frame) -> Admitted:
        self._active.remove(peer)
        self._flush(peer)
        self.stats.admitted += 1
        partial = peer.decoder.partial  # an unfinished frame after the AUTH_CHALLENGE
        peer.sock.setblocking(True)
        self.transport.adopt(peer.sock, peer.sock.getpeername())
        return Admitted(peer.session, [frame], partial)

    def _reply(self, peer: _Peer, msg: m.Message, request_id: int) -> None:
        try:
            peer.out += msg.encode(request_id=request_id)
        except (ValueError, MalformedMessage):
            return
        if len(peer.out) >= READ_BYTES:
            self._flush(peer)
            if len(peer.out) >= READ_BYTES:  # it does not read what it asked for
                self._drop_active(peer)

    def _flush(self, peer: _Peer) -> None:
        if not peer.out:
            return
        try:
            sent = peer.sock.send(peer.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop_active(peer)
            return
        del peer.out[:sent]

    # ------------------------------------------------------------------ bookkeeping
    def _resume(self) -> None:
        """Shift every clock by the pause (a host was served meanwhile)."""
        if self._paused_at is None:
            return
        shift = time.monotonic() - self._paused_at
        self._paused_at = None
        for peer in self._active:
            peer.accepted += shift
            peer.active_since += shift
            peer.cpu.at += shift
        for queue in self._waiting.values():
            for peer in queue:
                peer.accepted += shift

    def _drop_active(self, peer: _Peer) -> None:
        if peer in self._active:
            self._active.remove(peer)
        self._close(peer)

    def _drop_waiting(self, queue: collections.deque, peer: _Peer) -> None:
        queue.remove(peer)
        self._n_waiting -= 1
        if not queue:
            del self._waiting[peer.source]
        self._close(peer)

    @staticmethod
    def _close(peer: _Peer) -> None:
        with contextlib.suppress(OSError):
            peer.sock.close()
