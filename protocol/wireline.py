"""In-memory serial line: two ends that behave like a UART wire (one process, threads).

A *line* has two ends, ``"a"`` and ``"b"``, found by name in a process-wide
registry (:func:`open_end`). Each end owns its transmitter: the options it is
opened with (:class:`EndOptions`) describe the bytes *it sends* and the buffer
*it receives* into.

Model (what a test can rely on):

* **Pacing.** A paced end sends one byte every ``10 / baud`` seconds (8N1: start
  + 8 data + stop bits); consecutive writes queue behind each other. A byte
  becomes readable at the peer when its last bit has arrived, plus
  ``latency_s``, at the next multiple of the receiver's ``rx_tick_s`` (bytes
  show up in batches, as from a USB-serial adapter). Unpaced ends deliver at
  once (plus latency).
* **Bounded receive buffer, flow control.** Each end receives into a buffer of
  ``rx_buffer_bytes``; bytes in flight count against it. With flow control
  (default, like RTS/CTS) a writer blocks while the peer's buffer is full and
  raises :class:`LineTimeout` when its timeout expires. Without flow control
  the bytes that do not fit are lost (counted as ``overrun``).
* **write returns when the bytes are queued**, like a driver's transmit buffer;
  :meth:`LineEnd.flush` waits until they are on the wire.
* **Partial reads.** :meth:`LineEnd.read` returns what has arrived.
* **Faults** on what an end sends, drawn from a seeded ``numpy`` generator so a
  run is reproducible: independent bit flips (``ber`` per bit), dropped,
  duplicated and reordered (swapped with the next) bytes (per-byte rates), and
  bursts of ``burst_bytes`` dropped bytes (``burst`` per byte, e.g. a lost
  frame). Faults apply per write call, before queueing.
* **Baud mismatch.** When both ends are paced and the receiver's baud differs
  from the rate a byte was sent at, the receiver reads garbage instead (as a
  real UART would): this is how a failed SET_BAUD looks.
* **Disconnect.** ``disconnect_after=N`` breaks the line once this end has
  sent N bytes: both ends then raise :class:`LineBroken`; bytes already
  arrived stay readable first. A broken line is replaced by a fresh one the
  next time an end of that name is opened (a reconnect).
* **Absent peer.** Bytes sent while the other end is not open are lost (a
  rebooting device does not buffer).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "BITS_PER_BYTE",
    "ENDS",
    "EndOptions",
    "LineBroken",
    "LineEnd",
    "LineError",
    "LineTimeout",
    "WireLine",
    "open_end",
]

BITS_PER_BYTE = 10
"""8N1 framing: start bit, 8 data bits, stop bit."""

ENDS = ("a", "b")
_MAX_PIECE = 1 << 16  # bytes moved per step of a write (bounds fault arrays)


class LineError(Exception):
    """Base of wire-line errors (the pyserial handler turns them into SerialException)."""


class LineBroken(LineError):
    """The line was cut (``disconnect_after``)."""


class LineTimeout(LineError):
    """A write could not queue all its bytes within its timeout.

    Attributes
    ----------
    written : int
        Bytes queued before the timeout.
    """

    def __init__(self, message: str, written: int) -> None:
        super().__init__(message)
        self.written = written


@dataclass(frozen=True)
class EndOptions:
    """Options of one end (see the module docstring).

    Attributes
    ----------
    baud : int
        Transmit (and expected receive) rate, > 0.
    pace : bool
        Pace transmission at ``baud``.
    latency_s : float
        Added to every byte's arrival, >= 0.
    rx_buffer_bytes : int
        Receive buffer of this end, >= 1.
    flow_control : bool
        Writers to this end block when its buffer is full (else bytes are lost).
    ber : float
        Bit error rate of what this end sends, in [0, 1].
    drop_rate, dup_rate, reorder_rate, burst_rate : float
        Per-byte probabilities, in [0, 1].
    burst_bytes : int
        Bytes lost per burst, >= 1.
    disconnect_after : int or None
        Cut the line once this end has sent that many bytes.
    seed : int
        Seed of this end's fault generator.
    rx_tick_s : float
        Paced bytes become readable at this end in batches, at multiples of
        ``rx_tick_s`` (like a USB-serial adapter's latency timer), > 0.
    """

    baud: int = 115200
    pace: bool = True
    latency_s: float = 0.0
    rx_buffer_bytes: int = 4096
    flow_control: bool = True
    ber: float = 0.0
    drop_rate: float = 0.0
    dup_rate: float = 0.0
    reorder_rate: float = 0.0
    burst_rate: float = 0.0
    burst_bytes: int = 64
    disconnect_after: int | None = None
    seed: int = 0
    rx_tick_s: float = 0.001

    def __post_init__(self) -> None:
        if not isinstance(self.baud, int) or self.baud <= 0:
            raise ValueError(f"baud={self.baud!r} must be a positive int")
        if not self.latency_s >= 0:
            raise ValueError(f"latency_s={self.latency_s} must be >= 0")
        if self.rx_buffer_bytes < 1:
            raise ValueError(f"rx_buffer_bytes={self.rx_buffer_bytes} must be >= 1")
        for name in ("ber", "drop_rate", "dup_rate", "reorder_rate", "burst_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name}={value} must be in [0, 1]")
        if not self.rx_tick_s > 0:
            raise ValueError(f"rx_tick_s={self.rx_tick_s} must be > 0")
        if self.burst_bytes < 1:
            raise ValueError(f"burst_bytes={self.burst_bytes} must be >= 1")
        if self.disconnect_after is not None and self.disconnect_after < 0:
            raise ValueError(f"disconnect_after={self.disconnect_after} must be >= 0")


class _Segment:
    """Bytes queued towards a receiver by one write step."""

    __slots__ = ("arrival_start", "baud", "data", "paced", "period_s", "pos")

    def __init__(self, arrival_start: float, period_s: float, data: bytes, baud: int, paced: bool):
        self.arrival_start = arrival_start
        self.period_s = period_s
        self.data = data
        self.baud = baud
        self.paced = paced
        self.pos = 0

    def arrived(self, now: float) -> int:
        """Bytes of ``data`` whose last bit has arrived by ``now``."""
        if now < self.arrival_start:
            return 0
        if self.period_s <= 0.0:
            return len(self.data)
        # The tiny epsilon keeps float rounding from making a waiter spin.
        return min(len(self.data), int((now - self.arrival_start) / self.period_s + 1e-9))

    def next_arrival(self) -> float:
        """Arrival time of the byte at ``pos``."""
        return self.arrival_start + (self.pos + 1) * self.period_s


@dataclass
class _EndState:
    options: EndOptions
    baud: int
    rng: np.random.Generator
    rx: deque[_Segment] = field(default_factory=deque)
    rx_queued: int = 0
    tx_free_at: float = 0.0
    sent_bytes: int = 0
    stats: dict[str, int] = field(default_factory=dict)


class WireLine:
    """Both ends of one named line and the lock that serialises them."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.cond = threading.Condition()
        self.ends: dict[str, _EndState | None] = {"a": None, "b": None}
        self.broken: str | None = None

    def attach(self, end: str, options: EndOptions) -> LineEnd:
        """Open ``end`` on this line (caller holds the registry lock)."""
        state = _EndState(
            options=options,
            baud=options.baud,
            rng=np.random.default_rng(options.seed),
        )
        for key in (
            "sent",
            "delivered",
            "read",
            "bits_flipped",
            "dropped",
            "duplicated",
            "reordered",
            "burst_dropped",
            "overrun",
            "lost_no_peer",
            "garbled",
        ):
            state.stats[key] = 0
        with self.cond:
            self.ends[end] = state
            self.cond.notify_all()
        return LineEnd(self, end, state)


_registry: dict[str, WireLine] = {}
_registry_lock = threading.Lock()


def open_end(name: str, end: str, options: EndOptions | None = None) -> LineEnd:
    """Open one end of the line called ``name`` (created on first use).

    Parameters
    ----------
    name : str
        Line name, shared by both ends (process-wide).
    end : {"a", "b"}
    options : EndOptions, optional

    Returns
    -------
    LineEnd

    Raises
    ------
    LineError
        If that end is already open.
    """
    if end not in ENDS:
        raise ValueError(f"end={end!r} must be one of {ENDS}")
    options = options or EndOptions()
    with _registry_lock:
        line = _registry.get(name)
        if line is None or line.broken is not None:
            line = WireLine(name)
            _registry[name] = line
        if line.ends[end] is not None:
            raise LineError(f"mem://{name}: end {end!r} is already open")
        return line.attach(end, options)


def _apply_faults(data: bytes, opts: EndOptions, rng: np.random.Generator, stats: dict) -> bytes:
    """Return ``data`` after this end's faults (drop, burst, dup, reorder, bit flips)."""
    if not (opts.ber or opts.drop_rate or opts.dup_rate or opts.reorder_rate or opts.burst_rate):
        return data
    arr = np.frombuffer(data, dtype=np.uint8).copy()
    if opts.drop_rate and arr.size:
        keep = rng.random(arr.size) >= opts.drop_rate
        stats["dropped"] += int(arr.size - keep.sum())
        arr = arr[keep]
    if opts.burst_rate and arr.size:
        starts = np.flatnonzero(rng.random(arr.size) < opts.burst_rate)
        if starts.size:
            keep = np.ones(arr.size, dtype=bool)
            for s in starts:
                keep[s : s + opts.burst_bytes] = False
            stats["burst_dropped"] += int(arr.size - keep.sum())
            arr = arr[keep]
    if opts.dup_rate and arr.size:
        dup = rng.random(arr.size) < opts.dup_rate
        stats["duplicated"] += int(dup.sum())
        arr = np.repeat(arr, 1 + dup.astype(np.int64))
    if opts.reorder_rate and arr.size > 1:
        swap = np.flatnonzero(rng.random(arr.size - 1) < opts.reorder_rate)
        # Keep swaps disjoint (a byte moves at most one place).
        if swap.size:
            chosen = [int(swap[0])]
            for s in swap[1:]:
                if s > chosen[-1] + 1:
                    chosen.append(int(s))
            idx = np.asarray(chosen)
            arr[idx], arr[idx + 1] = arr[idx + 1].copy(), arr[idx].copy()
            stats["reordered"] += idx.size
    if opts.ber and arr.size:
        n_bits = arr.size * 8
        flips = int(rng.binomial(n_bits, opts.ber))
        if flips:
            bit = rng.choice(n_bits, size=flips, replace=False)  # distinct bits
            np.bitwise_xor.at(arr, bit // 8, (1 << (bit % 8)).astype(np.uint8))
            stats["bits_flipped"] += flips
    return arr.tobytes()


class LineEnd:
    """One open end of a :class:`WireLine` (thread-safe; one reader and one writer)."""

    def __init__(self, line: WireLine, end: str, state: _EndState) -> None:
        self.line = line
        self.end = end
        self._state = state
        self._closed = False

    # ------------------------------------------------------------------ info
    @property
    def name(self) -> str:
        """Line name."""
        return self.line.name

    @property
    def options(self) -> EndOptions:
        """Options this end was opened with."""
        return self._state.options

    @property
    def baud(self) -> int:
        """Current baud of this end."""
        return self._state.baud

    @property
    def stats(self) -> dict[str, int]:
        """Counters of this end: bytes sent/delivered/read and faults injected on its sends."""
        with self.line.cond:
            return dict(self._state.stats)

    def _peer(self) -> _EndState | None:
        return self.line.ends["b" if self.end == "a" else "a"]

    def _check_open(self) -> None:
        if self._closed:
            raise LineError(f"mem://{self.name} end {self.end}: closed")

    # ------------------------------------------------------------------ settings
    def set_baud(self, baud: int) -> None:
        """Change this end's baud (transmit pacing and expected receive rate)."""
        if not isinstance(baud, int) or baud <= 0:
            raise ValueError(f"baud={baud!r} must be a positive int")
        with self.line.cond:
            self._state.baud = baud
            self.line.cond.notify_all()

    # ------------------------------------------------------------------ write
    def write(self, data: bytes, timeout_s: float | None) -> int:
        """Queue ``data`` towards the peer.

        Parameters
        ----------
        data : bytes-like
        timeout_s : float or None
            Longest wait for buffer space; ``None`` waits forever, 0 queues
            what fits and returns.

        Returns
        -------
        int
            Bytes queued (``len(data)`` unless ``timeout_s == 0``).

        Raises
        ------
        LineTimeout
            Not all bytes could be queued in time (``written`` says how many were).
        LineBroken
            The line is cut.
        """
        data = bytes(data)
        state = self._state
        opts = state.options
        cond = self.line.cond
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        sent = 0
        with cond:
            while sent < len(data):
                self._check_open()
                if self.line.broken is not None:
                    raise LineBroken(self.line.broken)
                peer = self._peer()
                n = min(len(data) - sent, _MAX_PIECE)
                if peer is not None and peer.options.flow_control:
                    free = peer.options.rx_buffer_bytes - peer.rx_queued
                    if free <= 0:
                        now = time.monotonic()
                        if deadline is not None and now >= deadline:
                            if timeout_s == 0:
                                return sent
                            raise LineTimeout(
                                f"mem://{self.name}: write timed out after {timeout_s} s with "
                                f"{sent} of {len(data)} bytes queued (peer not reading)",
                                sent,
                            )
                        cond.wait(None if deadline is None else deadline - now)
                        continue
                    n = min(n, free)
                cut = False
                if opts.disconnect_after is not None:
                    left = opts.disconnect_after - state.sent_bytes
                    if n >= left:
                        n, cut = left, True
                self._transmit(data[sent : sent + n], peer)
                sent += n
                if cut:
                    self.line.broken = (
                        f"mem://{self.name}: line cut after end {self.end} sent "
                        f"{opts.disconnect_after} bytes (disconnect_after)"
                    )
                    for s in self.line.ends.values():
                        if s is not None:
                            # In-flight bytes are lost; arrived ones stay readable.
                            now = time.monotonic()
                            for seg in s.rx:
                                keep = seg.arrived(now)
                                if keep < len(seg.data):
                                    s.rx_queued -= len(seg.data) - keep
                                    seg.data = seg.data[:keep]
                    cond.notify_all()
                    raise LineBroken(self.line.broken)
        return sent

    def _transmit(self, piece: bytes, peer: _EndState | None) -> None:
        """Put one piece on the wire (lock held)."""
        state = self._state
        opts = state.options
        n = len(piece)
        state.sent_bytes += n
        state.stats["sent"] += n
        now = time.monotonic()
        period = BITS_PER_BYTE / state.baud if opts.pace else 0.0
        start = max(now, state.tx_free_at)
        state.tx_free_at = start + n * period
        if peer is None:
            state.stats["lost_no_peer"] += n
            return
        out = _apply_faults(piece, opts, state.rng, state.stats)
        if not peer.options.flow_control:
            free = max(0, peer.options.rx_buffer_bytes - peer.rx_queued)
            if len(out) > free:
                peer.stats["overrun"] += len(out) - free
                out = out[:free]
        if not out:
            return
        seg_period = n * period / len(out)
        peer.rx.append(_Segment(start + opts.latency_s, seg_period, out, state.baud, opts.pace))
        peer.rx_queued += len(out)
        state.stats["delivered"] += len(out)
        self.line.cond.notify_all()

    def flush(self, timeout_s: float | None = None) -> bool:
        """Wait until everything written has left this end; True if it has."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self.line.cond:
            while True:
                now = time.monotonic()
                left = self._state.tx_free_at - now
                if left <= 0:
                    return True
                if deadline is not None and now >= deadline:
                    return False
                wait = left if deadline is None else min(left, deadline - now)
                self.line.cond.wait(wait)

    @property
    def out_waiting(self) -> int:
        """Bytes queued towards the peer that have not arrived yet."""
        with self.line.cond:
            peer = self._peer()
            if peer is None:
                return 0
            now = time.monotonic()
            return sum(len(s.data) - max(s.pos, s.arrived(now)) for s in peer.rx)

    # ------------------------------------------------------------------ read
    def _take(self, max_bytes: int, now: float) -> bytes:
        """Remove up to ``max_bytes`` arrived bytes from the receive queue (lock held)."""
        state = self._state
        out = bytearray()
        tick = state.options.rx_tick_s
        visible = math.floor(now / tick + 1e-6) * tick  # paced bytes show up per tick
        while state.rx and len(out) < max_bytes:
            seg = state.rx[0]
            ready = seg.arrived(visible if seg.paced else now) - seg.pos
            if ready <= 0:
                break
            k = min(ready, max_bytes - len(out))
            chunk = seg.data[seg.pos : seg.pos + k]
            if seg.paced and state.options.pace and seg.baud != state.baud:
                chunk = state.rng.integers(0, 256, size=k, dtype=np.uint8).tobytes()
                state.stats["garbled"] += k
            out += chunk
            seg.pos += k
            state.rx_queued -= k
            if seg.pos >= len(seg.data):
                state.rx.popleft()
        if out:
            state.stats["read"] += len(out)
            self.line.cond.notify_all()
        return bytes(out)

    def _next_arrival(self) -> float | None:
        state = self._state
        while state.rx and state.rx[0].pos >= len(state.rx[0].data):
            state.rx.popleft()
        if not state.rx:
            return None
        seg = state.rx[0]
        if not seg.paced:
            return seg.next_arrival()
        tick = state.options.rx_tick_s
        return math.ceil(seg.next_arrival() / tick - 1e-6) * tick

    def read(self, size: int, timeout_s: float | None, *, first_only: bool = False) -> bytes:
        """Read up to ``size`` bytes.

        Parameters
        ----------
        size : int
        timeout_s : float or None
            ``None`` waits forever, 0 returns what has arrived.
        first_only : bool
            Return as soon as any byte is there (transport semantics) instead of
            waiting for ``size`` bytes (pyserial semantics).

        Returns
        -------
        bytes
            Possibly fewer than ``size`` bytes (b"" on timeout).

        Raises
        ------
        LineBroken
            The line is cut and nothing more is readable.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        out = bytearray()
        cond = self.line.cond
        with cond:
            while len(out) < size:
                self._check_open()
                now = time.monotonic()
                out += self._take(size - len(out), now)
                if len(out) >= size or (first_only and out):
                    break
                nxt = self._next_arrival()
                if self.line.broken is not None and nxt is None:
                    if out:
                        break
                    raise LineBroken(self.line.broken)
                if deadline is not None and now >= deadline:
                    break
                wait: float | None = None
                if nxt is not None:
                    wait = max(nxt - now, 1e-4)
                if deadline is not None:
                    wait = deadline - now if wait is None else min(wait, deadline - now)
                cond.wait(wait)
        return bytes(out)

    @property
    def in_waiting(self) -> int:
        """Bytes that have arrived and not been read."""
        with self.line.cond:
            now = time.monotonic()
            return sum(max(0, s.arrived(now) - s.pos) for s in self._state.rx)

    def reset_input(self) -> None:
        """Discard everything received or in flight towards this end."""
        with self.line.cond:
            self._state.rx.clear()
            self._state.rx_queued = 0
            self.line.cond.notify_all()

    # ------------------------------------------------------------------ close
    def close(self) -> None:
        """Close this end; the line is forgotten once both ends are closed."""
        if self._closed:
            return
        self._closed = True
        with _registry_lock:
            with self.line.cond:
                if self.line.ends[self.end] is self._state:
                    self.line.ends[self.end] = None
                self.line.cond.notify_all()
                empty = all(s is None for s in self.line.ends.values())
            if empty and _registry.get(self.name) is self.line:
                del _registry[self.name]
