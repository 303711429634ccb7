"""The busy door: connections that reach a TCP device while it serves its host.

A TCP device serves one host at a time (docs/protocol.md 5.2). A second host used to wait in
the listen backlog, unanswered, until its HELLO timed out (half a minute: "is the device
running?"). While a host is served, :class:`BusyDoor` accepts such connections itself and
answers their HELLO with ``ERROR{code: BUSY, where: "HELLO"}`` (`BUSY_MESSAGE`) and closes
them (its side at once; the rest once the peer hangs up, or `ANSWER_S` after the grace), so
the second host says at once that the device is busy:

* **A grace first.** A connection is held `GRACE_S` before it is read: the host being served
  may be on its way out (``serve --provision`` connects again the moment ``provision``
  said BYE), and a connection still held when the session ends is handed to the next one
  (:meth:`release`: the lobby of a keyed device, the transport of a keyless one) as if it
  had waited in the backlog.
* **Bounded.** At most `ACCEPT_PER_POLL` connections are accepted a poll and `HELD` held
  (past that the oldest is closed); each is read at most `READ_BYTES` a poll, frames over
  `MAX_FRAME_BYTES` are dropped, anything but a HELLO is ignored, and a connection that
  sends no HELLO `ANSWER_S` after its grace is closed unanswered. The device's loop polls it
  every 50-250 ms.

One thread (the device's ``serve`` loop) drives it; nothing here is thread-safe.
"""

from __future__ import annotations

import collections
import contextlib
import socket
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from protocol import messages as m
from protocol.errors import MalformedMessage
from protocol.framing import FrameDecoder, Kind

__all__ = ["ANSWER_S", "BUSY_MESSAGE", "GRACE_S", "HELD", "BusyDoor"]

GRACE_S = 0.5
"""A connection is held this long before it is told BUSY, seconds (the host served may be
leaving: then it is the next session's). Under a host's first HELLO timeout (1 s), so the
answer finds the HELLO it waits for, not a retry sent after the door had read."""
ANSWER_S = 3.0
"""After its grace, a connection has this long to send HELLO, seconds."""
HELD = 16
"""Connections held at most."""
ACCEPT_PER_POLL = 4
"""Connections accepted a poll at most (a flood of connections waits in the listen backlog, as
it did before, instead of costing the device more than a few accepts a poll)."""
READ_BYTES = 1024
MAX_FRAME_BYTES = 1024
BUSY_MESSAGE = "the device is serving another host; try again when that one is done"
"""The ERROR's message (pinned by tests/golden/messages.jsonl, ``error_busy``)."""


@dataclass(eq=False)
class _Held:
    sock: socket.socket
    address: Any
    accepted: float
    decoder: FrameDecoder = field(default_factory=lambda: FrameDecoder(MAX_FRAME_BYTES))
    told: bool = False  # BUSY sent: what else it sends is drained until it hangs up


class BusyDoor:
    """Connections accepted while a host is served (see the module docstring).

    Parameters
    ----------
    listener : socket.socket
        The device's listening socket (non-blocking).
    log : callable
        ``log(reason, line)``: rate-limited lines (a stranger can cause each of them).

    Attributes
    ----------
    answered, dropped : int
        Connections told BUSY; connections closed unanswered (no HELLO, or too many held).
    """

    def __init__(self, listener: socket.socket, *, log: Callable[[str, str], None]) -> None:
        self.listener = listener
        self.log = log
        self._held: collections.deque[_Held] = collections.deque()
        self.answered = 0
        self.dropped = 0

    @property
    def held(self) -> int:
        """Connections held now."""
        return len(self._held)

    def poll(self, now: float) -> None:
        """Accept what is pending; tell BUSY those past their grace that sent HELLO."""
        self._accept(now)
        for held in list(self._held):
            waited = now - held.accepted
            if waited < GRACE_S:
                continue
            if waited > GRACE_S + ANSWER_S or self._answer(held):
                self._drop(held)

    def release(self) -> list[tuple[socket.socket, Any]]:
        """The connections held and not told BUSY, oldest first, for the next session (none
        is held after)."""
        out = [(h.sock, h.address) for h in self._held if not h.told]
        for held in [h for h in self._held if h.told]:
            self._drop(held)
        self._held.clear()
        return out

    def hold(self, sock: socket.socket, address: Any, now: float) -> None:
        """Hold ``sock`` (accepted from the listener) as if accepted at ``now``."""
        sock.setblocking(False)
        with contextlib.suppress(OSError):  # as the transport's own accept (it may be a host)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._held.append(_Held(sock, address, now))
        if len(self._held) > HELD:
            self._drop(self._held[0])

    def close(self) -> None:
        """Close every connection held."""
        for held in list(self._held):
            self._drop(held)

    # ------------------------------------------------------------------ internals
    def _accept(self, now: float) -> None:
        for _ in range(ACCEPT_PER_POLL):
            try:
                sock, address = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # gone before it was accepted, or no descriptors: next poll
                return
            self.hold(sock, address, now)

    def _answer(self, held: _Held) -> bool:
        """Read what ``held`` sent and tell it BUSY after its HELLO; True when it is done
        with (it hung up). A connection told BUSY is half-closed and drained until it
        hangs up (closing it with unread bytes, a repeated HELLO, would reset it, and the
        reset can destroy the answer before the host reads it)."""
        try:
            data = held.sock.recv(READ_BYTES)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:
            return True
        if not data:
            return True
        if held.told:
            return False
        hellos = [frame.request_id for frame in held.decoder.feed(data)
                  if frame.kind == Kind.REQUEST and _is_hello(frame)]
        if hellos:  # each HELLO read (a retry has an id of its own), then our side closes
            reply = m.Error(code=m.ErrorCode.BUSY, where="HELLO", message=BUSY_MESSAGE)
            with contextlib.suppress(OSError):
                held.sock.send(b"".join(reply.encode(request_id=rid) for rid in hellos))
                held.sock.shutdown(socket.SHUT_WR)
            held.told = True
            self.answered += 1
            self.log("busy", "a second host was told the device is busy")
        return False

    def _drop(self, held: _Held) -> None:
        """Close ``held`` (counted as dropped unless it was told BUSY)."""
        if held in self._held:
            self._held.remove(held)
            self.dropped += not held.told
        with contextlib.suppress(OSError):
            held.sock.close()


def _is_hello(frame: Any) -> bool:
    try:
        return isinstance(m.decode_message(frame), m.Hello)
    except MalformedMessage:
        return False
