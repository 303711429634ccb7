"""Image transfer: stream an image over a :class:`~protocol.link.Link` in a sliding window.

:func:`send_image` is the host's sender of IMAGE_CHUNK events: a credit-based sliding
window with cumulative acknowledgements (IMAGE_ACK names the next offset the device
needs), fast retransmission of the missing chunk on duplicate acks (``"selective"``) or
going back to the acked offset (``"go-back-n"``), a chunk size that adapts to the loss
rate, and an inactivity timeout that only fires when no progress is made for that long.
The acks reach it through a listener the link engine routes by the transfer's request id.

It sits on top of the engine (it only calls :class:`~protocol.link.Link`'s public
methods) and is re-exported by ``protocol.link``. docs/protocol.md ("Provisioning",
"Link engine") is the specification; the device's receiving end is
``device_runtime/device.py`` (``handle_image_chunk``).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from protocol import messages as m
from protocol.errors import TransportClosed, TransportTimeout
from protocol.link import CHUNK_OVERHEAD_BYTES, IMAGE_QUEUE_FRAMES

if TYPE_CHECKING:
    from protocol.link import Link

__all__ = ["RETRANSMIT_STRATEGIES", "TransferStats", "send_image"]

_logger = logging.getLogger("protocol.link")

RETRANSMIT_STRATEGIES = ("selective", "go-back-n")
"""Loss recovery of :func:`send_image` (see its docstring)."""


@dataclass
class TransferStats:
    """What :func:`send_image` did.

    Attributes
    ----------
    start_offset : int
        Where the transfer (re)started.
    size_bytes : int
    chunk_bytes : int
    chunks_sent : int
        Chunk frames written, retransmissions included.
    retransmitted_chunks : int
        Chunks sent more than once (fast retransmits and go-back resends).
    data_bytes_sent : int
        Image bytes in all chunk frames sent.
    wire_bytes_sent : int
        Encoded frame bytes of all chunks sent (COBS, header, CRC, CBOR included).
    timeouts : int
        Retransmission timeouts (no ack progress within the RTO).
    fast_retransmits : int
        Missing chunks resent on duplicate acks.
    acks : int
        IMAGE_ACKs received.
    seconds : float
        Wall time from the first chunk to the final ack.
    srtt_s : float
        Smoothed chunk round-trip time at the end.
    final_chunk_bytes : int
        Chunk size at the end (it adapts to the loss rate).
    """

    start_offset: int = 0
    size_bytes: int = 0
    chunk_bytes: int = 0
    chunks_sent: int = 0
    retransmitted_chunks: int = 0
    data_bytes_sent: int = 0
    wire_bytes_sent: int = 0
    timeouts: int = 0
    fast_retransmits: int = 0
    acks: int = 0
    seconds: float = 0.0
    srtt_s: float = 0.0
    final_chunk_bytes: int = 0


class _AckState:
    """Shared between the reader (acks arrive) and the sender loop."""

    def __init__(self, next_offset: int, credits: int, window_bytes: int) -> None:
        self.cond = threading.Condition()
        self.next_offset = next_offset
        self.credits = credits
        self.window_bytes = window_bytes
        self.acks = 0
        self.dup_acks = 0
        self.error: BaseException | None = None
        self.events: collections.deque[tuple[float, int]] = collections.deque()

    def on_message(self, msg: m.Message | None) -> None:
        _logger.debug("transfer ack/error: %r", msg)
        with self.cond:
            if msg is None:
                self.error = self.error or TransportClosed("link closed during the transfer")
            elif isinstance(msg, m.Error):
                self.error = self.error or msg.to_exception()  # the first error is the cause
            elif isinstance(msg, m.ImageAck):
                self.acks += 1
                if msg.next_offset > self.next_offset:
                    self.next_offset = msg.next_offset
                    self.dup_acks = 0
                    self.events.append((time.monotonic(), msg.next_offset))
                else:
                    self.dup_acks += 1
                self.credits = msg.credits
                self.window_bytes = msg.window_bytes
            self.cond.notify_all()


def send_image(
    link: Link,
    data: bytes | bytearray | memoryview,
    *,
    transfer_id: int,
    first_ack: m.ImageAck,
    chunk_bytes: int,
    min_chunk_bytes: int = 128,
    initial_chunk_bytes: int | None = None,
    inactivity_timeout_s: float = 15.0,
    initial_rto_s: float = 1.0,
    min_rto_s: float = 0.2,
    max_rto_s: float = 4.0,
    retransmit: str = "selective",
    on_progress: Callable[[int], None] | None = None,
    tag: Callable[[m.ImageChunk], m.Message] | None = None,
) -> TransferStats:
    """Stream ``data`` to the device in a credit-based sliding window until it is all acked.

    Window: at most ``credits`` chunks beyond the device's acknowledged
    ``next_offset`` are in flight, and no byte at or beyond ``next_offset +
    window_bytes`` is sent (both from the latest IMAGE_ACK). Chunks are
    idempotent by offset, so any of them may be sent again, at any size.

    Loss recovery (``retransmit``):

    * ``"selective"`` (NewReno-like): two duplicate acks (the device got later
      chunks but still needs ``next_offset``) resend just the chunk at
      ``next_offset`` and enter recovery until everything sent before that
      point is acked; an ack that advances but stays inside that range names
      the next hole, which is resent at once. New data keeps flowing.
    * ``"go-back-n"``: two duplicate acks restart sending from ``next_offset``
      (everything after it is sent again).

    Either way a hole is resent at most once per 1.5 smoothed round trips, and
    no ack at all within the retransmission timeout (RTO: RFC 6298 from the
    measured round trips, starting at ``initial_rto_s``, doubled on expiry,
    within [``min_rto_s``, ``max_rto_s``]) resends from ``next_offset`` (a lost
    tail). No progress for ``inactivity_timeout_s`` raises ``TransportTimeout``;
    there is no whole-transfer timeout.

    Chunk size adapts to the line: it starts at ``chunk_bytes``, halves (not
    below ``min_chunk_bytes``) when more than a quarter of the chunks sent in
    the last 16 had to be resent (a noisy line loses long frames) or when a
    hole's resend was lost too, and grows back by half when fewer than 1 in 20
    were resent (``initial_chunk_bytes`` starts it lower, e.g. after a reconnect).

    Parameters
    ----------
    link : Link
        Started; its ``tx_max_frame_bytes`` must hold a chunk frame.
    data : bytes-like of length size_bytes
        The image (a memoryview of an mmap is fine: chunks are sliced lazily).
    transfer_id : int
        The IMAGE_BEGIN request id that was answered (chunks carry it).
    first_ack : ImageAck
        IMAGE_BEGIN's reply: where to start, the credits and the window.
    chunk_bytes : int
        Largest data bytes per chunk (at most the device's ``rx_buffer_bytes``).
    on_progress : callable, optional
        ``on_progress(acked_offset)`` after each ack that advances, on this thread.
    tag : callable, optional
        ``tag(chunk) -> chunk`` applied to every chunk as it is sent (a resent chunk is
        tagged again with a fresh counter): :meth:`HostSession.tag_event` on a keyed device.

    Returns
    -------
    TransferStats

    Raises
    ------
    RemoteError
        The device answered ERROR for the transfer (e.g. TOO_LARGE_FOR_RAM).
    TransportTimeout, TransportClosed
        No progress for ``inactivity_timeout_s``, or the link is gone.
    """
    if retransmit not in RETRANSMIT_STRATEGIES:
        raise ValueError(f"retransmit={retransmit!r} must be one of {RETRANSMIT_STRATEGIES}")
    if chunk_bytes < 1:
        raise ValueError(f"chunk_bytes={chunk_bytes} must be >= 1")
    if chunk_bytes + CHUNK_OVERHEAD_BYTES > link.tx_max_frame_bytes:
        raise ValueError(
            f"chunk_bytes={chunk_bytes} does not fit max_frame_bytes={link.tx_max_frame_bytes} "
            f"(at most {link.tx_max_frame_bytes - CHUNK_OVERHEAD_BYTES})"
        )
    sender = _Sender(link, memoryview(data).cast("B"), transfer_id, first_ack, chunk_bytes,
                     min_chunk_bytes, initial_chunk_bytes, initial_rto_s, min_rto_s, max_rto_s,
                     retransmit == "selective", tag)
    link.add_listener(transfer_id, sender.state.on_message)
    try:
        sender.run(inactivity_timeout_s, on_progress)
    finally:
        link.remove_listener(transfer_id)
    return sender.finish()


class _Sender:
    """One run of :func:`send_image`: its state and the steps of each turn of its loop
    (:meth:`run`): take the acks (:meth:`_take_acks`), learn from them (:meth:`_absorb`,
    :meth:`_after_progress`), adapt the chunk size (:meth:`_adapt_chunk`), give up when
    stuck (:meth:`_check_stuck`), recover a loss (:meth:`_recover`), fill the window
    (:meth:`_fill`) and wait (:meth:`_wait`)."""

    def __init__(self, link: Link, view: memoryview, transfer_id: int, first_ack: m.ImageAck,
                 chunk_bytes: int, min_chunk_bytes: int, initial_chunk_bytes: int | None,
                 initial_rto_s: float, min_rto_s: float, max_rto_s: float, selective: bool,
                 tag: Callable[[m.ImageChunk], m.Message] | None) -> None:
        self.link, self.view, self.size = link, view, len(view)
        self.transfer_id, self.tag, self.selective = transfer_id, tag, selective
        self.state = _AckState(first_ack.next_offset, first_ack.credits, first_ack.window_bytes)
        self.stats = TransferStats(
            start_offset=first_ack.next_offset, size_bytes=self.size, chunk_bytes=chunk_bytes
        )
        self.max_chunk = chunk_bytes
        self.min_chunk = max(1, min(min_chunk_bytes, chunk_bytes))
        self.chunk = self.max_chunk if initial_chunk_bytes is None else max(
            self.min_chunk, min(initial_chunk_bytes, self.max_chunk)
        )
        self.sent_at: dict[int, float] = {}  # chunk start -> send time, first transmissions
        self.sent_end: dict[int, int] = {}  # chunk start -> end of the last chunk from there
        self.last_resend: dict[int, float] = {}
        self.srtt: float | None = None
        self.rttvar = 0.0
        self.rto = initial_rto_s
        self.min_rto_s, self.max_rto_s = min_rto_s, max_rto_s
        self.acked = self.next_send = self.state.next_offset
        self.started = self.last_progress = self.last_ack_seen = time.monotonic()
        self.acks_seen = 0
        self.in_recovery, self.recover = False, 0
        self.epoch_chunks = self.epoch_resent = 0
        self.recent_new: collections.deque[int] = collections.deque(
            maxlen=4 * IMAGE_QUEUE_FRAMES)

    def run(self, inactivity_timeout_s: float, on_progress: Callable[[int], None] | None
            ) -> None:
        """Send until everything is acked."""
        while self.acked < self.size:
            credits, window, dup, events = self._take_acks()
            now = time.monotonic()
            progressed = self._absorb(events)
            gap = (self.srtt if self.srtt is not None else self.min_rto_s) * 1.5 + 0.005
            if progressed:
                self._forget_acked()
                if on_progress is not None:
                    on_progress(self.acked)
                if self.acked >= self.size:
                    break
                dup = self._after_progress(now, dup)
            self._adapt_chunk(now)
            if self.next_send < self.acked:
                self.next_send = self.acked
            self._check_stuck(now, inactivity_timeout_s)
            self._recover(now, dup, gap)
            limit = self._fill(now, credits, window)
            if self.link.closed:
                raise self.link._error_copy()
            self._wait(now, credits, limit, dup, gap)

    def finish(self) -> TransferStats:
        """The statistics of the finished transfer."""
        stats = self.stats
        stats.acks = self.state.acks
        stats.seconds = time.monotonic() - self.started
        stats.srtt_s = self.srtt or 0.0
        stats.final_chunk_bytes = self.chunk
        return stats

    # ------------------------------------------------------------------ one turn's steps

    def _take_acks(self) -> tuple[int, int, int, list[tuple[float, int]]]:
        """The latest credits, window, duplicate acks and the advancing acks since the last
        turn (raises the device's error)."""
        state = self.state
        with state.cond:
            if state.error is not None:
                raise state.error
            credits, window, dup = state.credits, state.window_bytes, state.dup_acks
            events = list(state.events)
            state.events.clear()
            if state.acks != self.acks_seen:
                self.acks_seen = state.acks
                self.last_ack_seen = time.monotonic()
        return credits, window, dup, events

    def _absorb(self, events: list[tuple[float, int]]) -> bool:
        """Take the round-trip samples and the new acked offset from ``events``; whether
        the acked offset advanced."""
        progressed = False
        for when, offset in events:
            # RTT sample (RFC 6298, Karn): the chunk that was at the head of the line,
            # if it was sent once; a hole before it cannot have delayed this ack.
            sample_from = self.sent_at.pop(self.acked, None) if offset > self.acked else None
            if sample_from is not None:
                sample = max(when - sample_from, 1e-4)
                if self.srtt is None:
                    self.srtt, self.rttvar = sample, sample / 2
                else:
                    self.rttvar = 0.75 * self.rttvar + 0.25 * abs(self.srtt - sample)
                    self.srtt = 0.875 * self.srtt + 0.125 * sample
                self.rto = min(max(self.srtt + 4 * self.rttvar, self.min_rto_s), self.max_rto_s)
            if offset > self.acked:
                self.acked, self.last_progress, progressed = offset, when, True
        return progressed

    def _forget_acked(self) -> None:
        for start in [s for s in self.sent_at if s < self.acked]:
            del self.sent_at[start]
        for start in [s for s in self.sent_end if s < self.acked]:
            del self.sent_end[start]

    def _after_progress(self, now: float, dup: int) -> int:
        """Leave recovery once past it, else (selective) resend the next hole a partial ack
        names; the duplicate acks still counted."""
        if self.in_recovery:
            if self.acked >= self.recover:
                self.in_recovery = False
            elif self.selective:  # partial ack: the next hole
                self._resend_hole(now)
                with self.state.cond:
                    self.state.dup_acks = 0
                dup = 0
        return dup

    def _adapt_chunk(self, now: float) -> None:
        """Every 16 chunks: adapt the chunk size to the loss rate."""
        if self.epoch_chunks >= 16:
            if self.epoch_resent * 4 > self.epoch_chunks and self.chunk > self.min_chunk:
                self._shrink(now)
            elif self.epoch_resent * 20 < self.epoch_chunks and self.chunk < self.max_chunk:
                self.chunk = min(self.max_chunk, self.chunk + self.chunk // 2 + 1)
            self.epoch_chunks = self.epoch_resent = 0

    def _check_stuck(self, now: float, inactivity_timeout_s: float) -> None:
        if now - self.last_progress > inactivity_timeout_s:
            raise TransportTimeout(
                f"{self.link.name}: image transfer made no progress for "
                f"{inactivity_timeout_s:.0f} s (stuck at offset {self.acked} of {self.size}); "
                "the device stopped acknowledging"
            )

    def _recover(self, now: float, dup: int, gap: float) -> None:
        """Loss recovery: the RTO expired, a hole's resend is overdue, or duplicate acks."""
        acked, selective, tid = self.acked, self.selective, self.transfer_id
        outstanding = self.next_send > acked
        if outstanding and now - self.last_ack_seen > self.rto:
            _logger.debug("transfer %d: RTO %.2f s at offset %d", tid, self.rto, acked)
            self.stats.timeouts += 1
            self.rto = min(self.rto * 2, self.max_rto_s)
            self.last_ack_seen = now
            if selective:
                self._resend_hole(now)
            else:
                self._go_back(now)
        elif (
            selective
            and self.in_recovery
            and outstanding
            and now - self.last_resend.get(acked, -math.inf) > max(2 * gap, self.min_rto_s)
        ):
            _logger.debug("transfer %d: hole at %d still open; resending", tid, acked)
            self.stats.timeouts += 1
            if self.chunk > self.min_chunk:  # the hole's resend was lost as well
                self._shrink(now)
            else:
                self._resend_hole(now)
        elif (
            outstanding
            and dup >= 2
            and not (selective and self.in_recovery)
            and now - self.last_resend.get(acked, -math.inf) > gap
        ):
            _logger.debug("transfer %d: %d duplicate acks at offset %d", tid, dup, acked)
            with self.state.cond:
                self.state.dup_acks = 0
            self.stats.fast_retransmits += 1
            if selective:
                self._resend_hole(now)
            else:
                self._go_back(now)

    def _fill(self, now: float, credits: int, window: int) -> int:
        """Send new chunks while the window, the credits and the link's queue allow; the
        window's end."""
        if self.next_send == self.acked:
            self.last_ack_seen = max(self.last_ack_seen, now)  # the RTO runs from the first send
        limit = min(self.acked + window, self.size)
        while (
            self.next_send < limit
            and -(-(self.next_send - self.acked) // self.chunk) < credits
            and min(self.next_send + self.chunk, self.size) <= limit
            and self.link.image_queue_depth() < IMAGE_QUEUE_FRAMES
        ):
            self.next_send = self._transmit(self.next_send)
        return limit

    def _wait(self, now: float, credits: int, limit: int, dup: int, gap: float) -> None:
        """Wait: for queue space if the window allows more, else for an ack or a timer."""
        acked, selective, state = self.acked, self.selective, self.state
        window_full = (
            self.next_send >= limit
            or -(-(self.next_send - acked) // self.chunk) >= credits
            or min(self.next_send + self.chunk, self.size) > limit
        )
        timer = self.rto - (time.monotonic() - self.last_ack_seen)
        if self.in_recovery and selective:
            timer = min(timer, max(2 * gap, self.min_rto_s)
                        - (now - self.last_resend.get(acked, now)))
        if dup >= 2 and not (selective and self.in_recovery):
            timer = min(timer, gap - (now - self.last_resend.get(acked, -math.inf)))
        timer = max(0.001, min(timer, 0.05))
        if not window_full:
            self.link.wait_image_space(timer)
        else:
            with state.cond:
                if not state.events and state.error is None and state.acks == self.acks_seen:
                    state.cond.wait(timer)

    # ------------------------------------------------------------------ sending

    def _transmit(self, offset: int, *, front: bool = False, resend: bool = False) -> int:
        stats = self.stats
        end = min(offset + self.chunk, self.size)
        chunk_msg: m.Message = m.ImageChunk(offset=offset, data=self.view[offset:end])
        if self.tag is not None:
            chunk_msg = self.tag(chunk_msg)  # type: ignore[arg-type]
        wire = self.link._encode(chunk_msg, self.transfer_id)
        if resend or offset in self.sent_end:
            stats.retransmitted_chunks += 1
            self.epoch_resent += 1
            self.sent_at.pop(offset, None)
        else:
            self.sent_at[offset] = time.monotonic()
        self.sent_end[offset] = end
        if not resend:
            self.recent_new.append(end - offset)
        self.epoch_chunks += 1
        stats.chunks_sent += 1
        stats.data_bytes_sent += end - offset
        stats.wire_bytes_sent += len(wire)
        self.link.send_chunk(wire, front=front)
        return end

    def _resend_hole(self, now: float) -> None:
        # Everything already written goes out before the resend (it jumps the queue, not
        # the wire); chunks still queued go after it, so they are not part of this round.
        depth = self.link.image_queue_depth()
        queued = list(self.recent_new)[-depth:] if depth else []
        written_end = self.next_send - sum(queued)
        self.last_resend[self.acked] = now
        self._transmit(self.acked, front=True, resend=True)
        self.recover = max(self.recover, written_end) if self.in_recovery else written_end
        self.in_recovery = True

    def _go_back(self, now: float) -> None:
        self.last_resend[self.acked] = now
        self.link.drop_queued_chunks()
        self.next_send = self.acked
        self.in_recovery = False

    def _shrink(self, now: float) -> None:
        # Frames this long do not get through: send shorter ones, and send again what
        # is in flight (it went out in frames of the failing length).
        self.chunk = max(self.min_chunk, self.chunk // 2)
        self.epoch_chunks = self.epoch_resent = 0
        _logger.debug("transfer %d: chunk size now %d", self.transfer_id, self.chunk)
        self._go_back(now)
