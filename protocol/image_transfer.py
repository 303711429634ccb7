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
    view = memoryview(data).cast("B")
    size = len(view)
    state = _AckState(first_ack.next_offset, first_ack.credits, first_ack.window_bytes)
    stats = TransferStats(
        start_offset=first_ack.next_offset, size_bytes=size, chunk_bytes=chunk_bytes
    )
    selective = retransmit == "selective"
    max_chunk = chunk_bytes
    min_chunk = max(1, min(min_chunk_bytes, chunk_bytes))
    chunk = max_chunk if initial_chunk_bytes is None else max(
        min_chunk, min(initial_chunk_bytes, max_chunk)
    )
    sent_at: dict[int, float] = {}  # chunk start -> send time, first transmissions only
    sent_end: dict[int, int] = {}  # chunk start -> end of the last chunk sent from there
    last_resend: dict[int, float] = {}
    srtt: float | None = None
    rttvar = 0.0
    rto = initial_rto_s
    acked = next_send = state.next_offset
    started = last_progress = last_ack_seen = time.monotonic()
    acks_seen = 0
    in_recovery, recover = False, 0
    epoch_chunks = epoch_resent = 0
    recent_new: collections.deque[int] = collections.deque(maxlen=4 * IMAGE_QUEUE_FRAMES)

    def transmit(offset: int, *, front: bool = False, resend: bool = False) -> int:
        nonlocal epoch_chunks, epoch_resent
        end = min(offset + chunk, size)
        chunk_msg: m.Message = m.ImageChunk(offset=offset, data=view[offset:end])
        if tag is not None:
            chunk_msg = tag(chunk_msg)  # type: ignore[arg-type]
        wire = link._encode(chunk_msg, transfer_id)
        if resend or offset in sent_end:
            stats.retransmitted_chunks += 1
            epoch_resent += 1
            sent_at.pop(offset, None)
        else:
            sent_at[offset] = time.monotonic()
        sent_end[offset] = end
        if not resend:
            recent_new.append(end - offset)
        epoch_chunks += 1
        stats.chunks_sent += 1
        stats.data_bytes_sent += end - offset
        stats.wire_bytes_sent += len(wire)
        link.send_chunk(wire, front=front)
        return end

    def resend_hole(now: float) -> None:
        # Everything already written goes out before the resend (it jumps the queue, not
        # the wire); chunks still queued go after it, so they are not part of this round.
        nonlocal in_recovery, recover
        queued = list(recent_new)[-link.image_queue_depth():] if link.image_queue_depth() else []
        written_end = next_send - sum(queued)
        last_resend[acked] = now
        transmit(acked, front=True, resend=True)
        recover = max(recover, written_end) if in_recovery else written_end
        in_recovery = True

    def go_back(now: float) -> None:
        nonlocal next_send, in_recovery
        last_resend[acked] = now
        link.drop_queued_chunks()
        next_send = acked
        in_recovery = False

    def shrink(now: float) -> None:
        # Frames this long do not get through: send shorter ones, and send again what
        # is in flight (it went out in frames of the failing length).
        nonlocal chunk, epoch_chunks, epoch_resent
        chunk = max(min_chunk, chunk // 2)
        epoch_chunks = epoch_resent = 0
        _logger.debug("transfer %d: chunk size now %d", transfer_id, chunk)
        go_back(now)

    link.add_listener(transfer_id, state.on_message)
    try:
        while acked < size:
            with state.cond:
                if state.error is not None:
                    raise state.error
                credits, window, dup = state.credits, state.window_bytes, state.dup_acks
                events = list(state.events)
                state.events.clear()
                if state.acks != acks_seen:
                    acks_seen = state.acks
                    last_ack_seen = time.monotonic()
            now = time.monotonic()
            progressed = False
            for when, offset in events:
                # RTT sample (RFC 6298, Karn): the chunk that was at the head of the line,
                # if it was sent once; a hole before it cannot have delayed this ack.
                sample_from = sent_at.pop(acked, None) if offset > acked else None
                if sample_from is not None:
                    sample = max(when - sample_from, 1e-4)
                    if srtt is None:
                        srtt, rttvar = sample, sample / 2
                    else:
                        rttvar = 0.75 * rttvar + 0.25 * abs(srtt - sample)
                        srtt = 0.875 * srtt + 0.125 * sample
                    rto = min(max(srtt + 4 * rttvar, min_rto_s), max_rto_s)
                if offset > acked:
                    acked, last_progress, progressed = offset, when, True
            gap = (srtt if srtt is not None else min_rto_s) * 1.5 + 0.005
            if progressed:
                for start in [s for s in sent_at if s < acked]:
                    del sent_at[start]
                for start in [s for s in sent_end if s < acked]:
                    del sent_end[start]
                if on_progress is not None:
                    on_progress(acked)
                if acked >= size:
                    break
                if in_recovery:
                    if acked >= recover:
                        in_recovery = False
                    elif selective:  # partial ack: the next hole
                        resend_hole(now)
                        with state.cond:
                            state.dup_acks = 0
                        dup = 0
            if epoch_chunks >= 16:  # adapt the chunk size to the loss rate
                if epoch_resent * 4 > epoch_chunks and chunk > min_chunk:
                    shrink(now)
                elif epoch_resent * 20 < epoch_chunks and chunk < max_chunk:
                    chunk = min(max_chunk, chunk + chunk // 2 + 1)
                epoch_chunks = epoch_resent = 0
            if next_send < acked:
                next_send = acked
            if now - last_progress > inactivity_timeout_s:
                raise TransportTimeout(
                    f"{link.name}: image transfer made no progress for "
                    f"{inactivity_timeout_s:.0f} s (stuck at offset {acked} of {size}); "
                    "the device stopped acknowledging"
                )
            outstanding = next_send > acked
            # Loss recovery.
            if outstanding and now - last_ack_seen > rto:
                _logger.debug("transfer %d: RTO %.2f s at offset %d", transfer_id, rto, acked)
                stats.timeouts += 1
                rto = min(rto * 2, max_rto_s)
                last_ack_seen = now
                if selective:
                    resend_hole(now)
                else:
                    go_back(now)
            elif (
                selective
                and in_recovery
                and outstanding
                and now - last_resend.get(acked, -math.inf) > max(2 * gap, min_rto_s)
            ):
                _logger.debug("transfer %d: hole at %d still open; resending", transfer_id, acked)
                stats.timeouts += 1
                if chunk > min_chunk:  # the hole's resend was lost as well
                    shrink(now)
                else:
                    resend_hole(now)
            elif (
                outstanding
                and dup >= 2
                and not (selective and in_recovery)
                and now - last_resend.get(acked, -math.inf) > gap
            ):
                _logger.debug("transfer %d: %d duplicate acks at offset %d", transfer_id, dup,
                              acked)
                with state.cond:
                    state.dup_acks = 0
                stats.fast_retransmits += 1
                if selective:
                    resend_hole(now)
                else:
                    go_back(now)
            # Fill the window.
            if next_send == acked:
                last_ack_seen = max(last_ack_seen, now)  # the RTO runs from the first send
            limit = min(acked + window, size)
            while (
                next_send < limit
                and -(-(next_send - acked) // chunk) < credits
                and min(next_send + chunk, size) <= limit
                and link.image_queue_depth() < IMAGE_QUEUE_FRAMES
            ):
                next_send = transmit(next_send)
            if link.closed:
                raise link._error_copy()
            # Wait: for queue space if the window allows more, else for an ack or a timer.
            window_full = (
                next_send >= limit
                or -(-(next_send - acked) // chunk) >= credits
                or min(next_send + chunk, size) > limit
            )
            timer = rto - (time.monotonic() - last_ack_seen)
            if in_recovery and selective:
                timer = min(timer, max(2 * gap, min_rto_s) - (now - last_resend.get(acked, now)))
            if dup >= 2 and not (selective and in_recovery):
                timer = min(timer, gap - (now - last_resend.get(acked, -math.inf)))
            timer = max(0.001, min(timer, 0.05))
            if not window_full:
                link.wait_image_space(timer)
            else:
                with state.cond:
                    if not state.events and state.error is None and state.acks == acks_seen:
                        state.cond.wait(timer)
    finally:
        link.remove_listener(transfer_id)
    stats.acks = state.acks
    stats.seconds = time.monotonic() - started
    stats.srtt_s = srtt or 0.0
    stats.final_chunk_bytes = chunk
    return stats
