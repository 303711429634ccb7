"""Link engine: one framed, prioritised, request/response conversation over a Transport.

Used by both sides. A :class:`Link` owns three threads over one
:class:`~protocol.transport.Transport`:

* **reader**: reads whatever bytes arrive, feeds one
  :class:`~protocol.framing.FrameDecoder`, decodes each frame's message and
  routes it: a RESPONSE or ACK whose request id someone waits for completes
  that request (``request``); one whose id belongs to a registered *listener*
  (an image transfer) goes to it; any other is *stale* and dropped (counted).
  REQUEST and EVENT frames go to the inbox. Malformed requests are answered
  ``ERROR(MALFORMED)``, unknown MUST_UNDERSTAND types ``ERROR(UNKNOWN_MESSAGE)``,
  with the frame's request id; nothing the peer sends can raise here.
* **dispatcher**: takes inbox frames in order and calls the handler
  (``handler(msg, frame) -> reply or None``); a REQUEST's reply (or the ERROR
  its exception maps to) is sent back with the request's id. The inbox is
  bounded: past ``inbox_frames`` (image chunks: past ``image_inbox_frames``)
  frames are dropped and counted, so a peer that ignores its credits cannot
  make the receiver allocate more.
* **writer**: sends queued frames, control first, then scores, then image
  chunks. Score-channel events are *latest wins*: a newer one of the same
  type replaces an unsent older one (counted in ``scores_replaced``). The
  image sender keeps at most ``IMAGE_QUEUE_FRAMES`` chunks queued, so a
  control or score frame waits behind at most about one chunk on the wire.

Requests (:meth:`Link.request`) carry fresh ids; each attempt waits an
inactivity timeout that grows by ``backoff`` per retry (bounded retries), and a
reply to an abandoned attempt is stale. A peer that is gone raises
:class:`~protocol.errors.TransportClosed`; one that stays silent raises
:class:`~protocol.errors.TransportTimeout`; an ERROR reply raises the
:class:`~protocol.errors.RemoteError` subclass for its code.

On top of the link:

* :func:`send_image` streams an image in a credit-based sliding window with
  cumulative acknowledgements (IMAGE_ACK names the next offset the device
  needs), fast retransmission of the missing chunk on duplicate acks
  (``"selective"``) or going back to the acked offset (``"go-back-n"``), and an
  inactivity timeout that only fires when no progress is made for that long.
* :class:`HostSession`: HELLO (version negotiation), mutual AUTH, signed
  mutating requests with a monotonic counter, PING, and :meth:`HostSession.set_baud`
  (switch, ping at the new rate, fall back when the device reverts).

docs/protocol.md ("Link engine", "Provisioning", "State machines") is the specification.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import hmac
import logging
import math
import os
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from protocol import messages as m
from protocol.errors import (
    AuthenticationError,
    MalformedMessage,
    ProtocolError,
    TransportClosed,
    TransportError,
    TransportTimeout,
)
from protocol.framing import (
    MIN_FRAME_BYTES,
    Channel,
    Frame,
    FrameDecoder,
    Kind,
)

__all__ = [
    "CHUNK_OVERHEAD_BYTES",
    "DEFAULT_REQUEST_TIMEOUT_S",
    "DEFAULT_RETRIES",
    "IMAGE_QUEUE_FRAMES",
    "RETRANSMIT_STRATEGIES",
    "HostSession",
    "Link",
    "LinkStats",
    "TransferStats",
    "negotiate_version",
    "send_image",
]

_logger = logging.getLogger("protocol.link")

DEFAULT_REQUEST_TIMEOUT_S = 1.0
"""First attempt's reply timeout of :meth:`Link.request`, seconds (later ones grow by backoff)."""
DEFAULT_RETRIES = 4
"""Retries after the first attempt of :meth:`Link.request`."""
MAX_ATTEMPT_TIMEOUT_S = 8.0
"""Longest single-attempt timeout after backoff, seconds."""
IMAGE_QUEUE_FRAMES = 2
"""Image chunks the writer holds at most: what a control frame may wait behind."""
CHUNK_OVERHEAD_BYTES = MIN_FRAME_BYTES + 16 + m.EVENT_TAG_OVERHEAD_BYTES
"""Frame bytes an IMAGE_CHUNK adds to its data (header, CRC, CBOR map/offset/length, and the
event tag a keyed device needs)."""
RETRANSMIT_STRATEGIES = ("selective", "go-back-n")
"""Loss recovery of :func:`send_image` (see its docstring)."""

_READ_BYTES = 1 << 16
_POLL_S = 0.05


# --------------------------------------------------------------------------- stats


@dataclass
class LinkStats:
    """Counters of one :class:`Link` (read them any time; they only grow).

    Attributes
    ----------
    frames_sent, frames_received : int
        Frames written / decoded (valid CRC and header).
    bytes_sent, bytes_received : int
        Wire bytes written / read.
    stale_responses : int
        Responses and acks whose request id nobody waits for (late replies to
        abandoned attempts, acks of a finished transfer), dropped.
    inbox_dropped : int
        Incoming requests/events dropped because the inbox was full (a peer
        that ignores its credits).
    malformed : int
        Frames whose body did not decode (requests among them got ERROR(MALFORMED)).
    unknown : int
        Frames of a message type unknown here.
    scores_replaced : int
        Unsent score-channel events replaced by a newer one (latest wins).
    request_retries : int
        Request attempts that timed out and were sent again.
    handler_errors : int
        Requests/events whose handler raised (answered with ERROR when a request).
    """

    frames_sent: int = 0
    frames_received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    stale_responses: int = 0
    inbox_dropped: int = 0
    malformed: int = 0
    unknown: int = 0
    scores_replaced: int = 0
    request_retries: int = 0
    handler_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        """All counters as a plain dict."""
        return dataclasses.asdict(self)


class _Pending:
    """One request attempt waiting for its reply."""

    __slots__ = ("event", "reply")

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reply: m.Message | BaseException | None = None


@dataclass
class _Out:
    data: bytes
    after_sent: Callable[[], None] | None = None


Handler = Callable[[m.Message, Frame], "m.Message | None"]
"""``handler(msg, frame)``: the reply to a REQUEST (None: no reply), ignored for events."""
ErrorMapper = Callable[[BaseException, str], m.Error]
"""``mapper(exc, where)``: the ERROR answering a request whose handler raised."""


def _default_error_mapper(exc: BaseException, where: str) -> m.Error:
    return m.Error.from_exception(exc, where=where)


# --------------------------------------------------------------------------- Link


class Link:
    """A framed conversation over one transport, with prioritised writes (see the module doc).

    Parameters
    ----------
    transport : Transport
        Not owned: :meth:`close` leaves it open unless ``owns_transport``.
    name : str, optional
        Label for messages and logs (default: the transport's URL).
    handler : callable, optional
        ``handler(msg, frame)`` for incoming REQUEST and EVENT frames, called in
        order on the dispatcher thread. Its return value answers a REQUEST;
        an exception is answered with ``error_mapper(exc, TYPE name)``.
        Without a handler, requests are answered ``ERROR(UNSUPPORTED)``.
    error_mapper : callable, optional
        Exception -> :class:`~protocol.messages.Error` (default:
        :meth:`Error.from_exception <protocol.messages.Error.from_exception>`).
    rx_max_frame_bytes : int, optional
        Largest frame accepted (default: ``transport.max_frame_bytes``, at
        least ``BASELINE_MAX_FRAME_BYTES``).
    tx_max_frame_bytes : int
        Largest frame sent (``BASELINE_MAX_FRAME_BYTES`` until the peer declared more).
    inbox_frames : int
        Incoming requests/events held for the dispatcher at most.
    image_inbox_frames : int, optional
        Image chunks among them at most (default ``inbox_frames``).
    on_close : callable, optional
        ``on_close(exc)`` once, from the thread that found the link gone.
    on_frame : callable, optional
        ``on_frame(frame)`` for every valid frame, on the reader thread (cheap work only).
    owns_transport : bool
        Close the transport in :meth:`close`.
    poll_s : float
        How often idle threads check for :meth:`close`, seconds.
    tx_low_water_bytes : int, optional
        Before writing an image chunk, wait until the port's transmit buffer
        (``port.out_waiting`` of a serial port) holds at most this many bytes, so a
        control or score frame never queues behind a driver buffer full of chunks
        (on a 115200-baud line a 4 KiB buffer is 0.36 s). None: do not wait.

    Attributes
    ----------
    stats : LinkStats
    decoder : FrameDecoder
        Its counters say how much garbage arrived.
    """

    def __init__(
        self,
        transport: Any,
        *,
        name: str | None = None,
        handler: Handler | None = None,
        error_mapper: ErrorMapper | None = None,
        rx_max_frame_bytes: int | None = None,
        tx_max_frame_bytes: int = m.BASELINE_MAX_FRAME_BYTES,
        inbox_frames: int = 64,
        image_inbox_frames: int | None = None,
        on_close: Callable[[BaseException], None] | None = None,
        on_frame: Callable[[Frame], None] | None = None,
        owns_transport: bool = False,
        poll_s: float = _POLL_S,
        tx_low_water_bytes: int | None = None,
    ) -> None:
        if inbox_frames < 1:
            raise ValueError(f"Link: inbox_frames={inbox_frames} must be >= 1")
        self.transport = transport
        self.name = name or getattr(transport, "url", "link")
        self._handler = handler
        self._error_mapper = error_mapper or _default_error_mapper
        rx = rx_max_frame_bytes or max(transport.max_frame_bytes, m.BASELINE_MAX_FRAME_BYTES)
        self.decoder = FrameDecoder(rx)
        self._reset_decoder = False
        self._tx_max_frame_bytes = tx_max_frame_bytes
        self._inbox_frames = inbox_frames
        self._image_inbox_frames = image_inbox_frames or inbox_frames
        self._control_limit = inbox_frames + 16
        self._on_close = on_close
        self._on_frame = on_frame
        self._owns_transport = owns_transport
        self._poll_s = poll_s
        self.tx_low_water_bytes = tx_low_water_bytes
        self.stats = LinkStats()

        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)  # writer queues + inbox + state
        self._control: collections.deque[_Out] = collections.deque()
        self._scores: dict[int, _Out] = {}
        self._image: collections.deque[_Out] = collections.deque()
        self._writing = False
        self._inbox: collections.deque[tuple[m.Message, Frame] | Callable[[], None]] = (
            collections.deque()
        )
        self._inbox_images = 0
        self._pending: dict[int, _Pending] = {}
        self._listeners: dict[int, Callable[[m.Message], None]] = {}
        self._next_id = secrets.randbelow(0xFFFF) + 1
        self._closing = False
        self._error: BaseException | None = None
        self._close_reported = False
        self._threads: list[threading.Thread] = []
        self._started = False

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> Link:
        """Start the reader, dispatcher and writer threads; return self."""
        if self._started:
            return self
        self._started = True
        for target, role in (
            (self._reader_loop, "reader"),
            (self._dispatch_loop, "dispatch"),
            (self._writer_loop, "writer"),
        ):
            thread = threading.Thread(target=target, name=f"link-{role}", daemon=True)
            self._threads.append(thread)
            thread.start()
        return self

    def __enter__(self) -> Link:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True once the link failed or was closed."""
        return self._closing or self._error is not None

    @property
    def error(self) -> BaseException | None:
        """Why the link is gone (None while it works or after a clean close)."""
        return self._error

    def close(self, *, flush_timeout_s: float = 1.0) -> None:
        """Send what is queued on the control channel (up to ``flush_timeout_s``), stop threads.

        Pending requests fail with ``TransportClosed``. Idempotent.
        """
        deadline = time.monotonic() + flush_timeout_s
        with self._cond:
            while (
                self._error is None
                and (self._control or self._writing)
                and time.monotonic() < deadline
            ):
                self._cond.wait(max(0.0, min(self._poll_s, deadline - time.monotonic())))
            self._closing = True
            self._cond.notify_all()
        self._fail_pending(TransportClosed(f"{self.name}: link closed"))
        current = threading.current_thread()
        for thread in self._threads:
            if thread is not current:
                thread.join(timeout=2.0)
        if self._owns_transport:
            self.transport.close()

    def wait_closed(self, timeout_s: float | None = None) -> bool:
        """Block until the link fails or is closed; True if it did within ``timeout_s``."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self.closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(self._poll_s if left is None else min(left, self._poll_s))
        return True

    # ------------------------------------------------------------------ limits
    @property
    def tx_max_frame_bytes(self) -> int:
        """Largest frame this side sends."""
        return self._tx_max_frame_bytes

    def set_tx_max_frame_bytes(self, value: int) -> None:
        """Raise or lower the send limit (after the peer declared its ``max_frame_bytes``)."""
        if not m.BASELINE_MAX_FRAME_BYTES <= value <= 1 << 24:
            raise ValueError(
                f"set_tx_max_frame_bytes: {value} must be in "
                f"[{m.BASELINE_MAX_FRAME_BYTES}, {1 << 24}]"
            )
        self._tx_max_frame_bytes = value

    # ------------------------------------------------------------------ sending
    def _check_open(self) -> None:
        if self._error is not None:
            raise self._error_copy()
        if self._closing:
            raise TransportClosed(f"{self.name}: link closed")

    def _error_copy(self) -> BaseException:
        err = self._error
        if isinstance(err, TransportTimeout):
            return TransportTimeout(str(err))
        if isinstance(err, TransportError):
            return TransportClosed(str(err))
        return TransportClosed(f"{self.name}: link failed: {err}")

    def _encode(self, msg: m.Message, request_id: int) -> bytes:
        body = msg.to_body()
        size = MIN_FRAME_BYTES + len(body)
        if size > self._tx_max_frame_bytes:
            raise ValueError(
                f"{self.name}: {msg.TYPE.name} frame of {size} bytes exceeds the peer's "
                f"max_frame_bytes={self._tx_max_frame_bytes}"
            )
        frame = Frame(
            channel=msg.CHANNEL,
            kind=msg.KIND,
            msg_type=int(msg.TYPE),
            request_id=request_id,
            body=body,
            flags=1 if msg.MUST_UNDERSTAND else 0,
        )
        return frame.encode()

    def send(
        self,
        msg: m.Message,
        *,
        request_id: int = 0,
        after_sent: Callable[[], None] | None = None,
    ) -> None:
        """Queue ``msg`` (a response, event or unsolicited frame); return at once.

        Score-channel events are latest-wins; image chunks go through
        :meth:`send_chunk`. ``after_sent()`` runs on the writer thread once the
        frame's bytes have left (used to switch the baud rate after an OK).
        """
        self._check_open()
        out = _Out(self._encode(msg, request_id), after_sent)
        with self._cond:
            if msg.CHANNEL == Channel.SCORES and msg.KIND == Kind.EVENT:
                key = int(msg.TYPE)
                if key in self._scores:
                    self.stats.scores_replaced += 1
                    del self._scores[key]
                self._scores[key] = out
            else:
                self._control.append(out)
            self._cond.notify_all()

    def send_raw(self, data: bytes) -> None:
        """Queue raw bytes on the control queue (tests; a lone 0x00 to flush a receiver)."""
        self._check_open()
        with self._cond:
            self._control.append(_Out(bytes(data)))
            self._cond.notify_all()

    def send_chunk(self, wire: bytes, *, front: bool = False) -> None:
        """Queue an encoded IMAGE_CHUNK frame (lowest priority; ``front`` for a retransmission)."""
        self._check_open()
        with self._cond:
            if front:
                self._image.appendleft(_Out(wire))
            else:
                self._image.append(_Out(wire))
            self._cond.notify_all()

    def image_queue_depth(self) -> int:
        """Image chunks queued and not yet written."""
        with self._cond:
            return len(self._image)

    def drop_queued_chunks(self) -> int:
        """Forget queued image chunks (go-back-N restarts); return how many."""
        with self._cond:
            n = len(self._image)
            self._image.clear()
            return n

    def wait_image_space(self, timeout_s: float) -> bool:
        """Wait until fewer than ``IMAGE_QUEUE_FRAMES`` chunks are queued."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self._image) >= IMAGE_QUEUE_FRAMES:
                self._check_open()
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, self._poll_s))
            return True

    def _new_request_id(self) -> int:
        with self._cond:
            for _ in range(0x10000):
                rid = self._next_id
                self._next_id = rid % 0xFFFF + 1
                if rid not in self._pending and rid not in self._listeners:
                    return rid
        raise TransportError(f"{self.name}: no free request id (65535 requests outstanding)")

    def request(
        self,
        msg: m.Message,
        *,
        timeout_s: float = DEFAULT_REQUEST_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        backoff: float = 2.0,
        max_timeout_s: float = MAX_ATTEMPT_TIMEOUT_S,
        expect: type[m.Message] | None = None,
        on_reply: Callable[[int, m.Message], None] | None = None,
    ) -> m.Message:
        """Send a request and wait for its reply, retrying with a fresh id after each timeout.

        Parameters
        ----------
        msg : Message
            A REQUEST-kind message (send a signed request already signed: every
            attempt carries the same counter; the device re-answers a repeat).
        timeout_s : float
            Reply timeout of the first attempt, seconds; each retry multiplies it
            by ``backoff`` (at most ``max_timeout_s``).
        retries : int
            Attempts after the first.
        expect : type, optional
            Reply class (default ``msg.REPLY``).
        on_reply : callable, optional
            ``on_reply(request_id, reply)`` before returning (e.g. to register a
            transfer listener under the id that was answered).

        Returns
        -------
        Message
            The reply.

        Raises
        ------
        RemoteError
            The peer answered ERROR (the subclass for its code).
        TransportTimeout
            No reply after all attempts.
        TransportClosed
            The link is gone.
        MalformedMessage
            The reply has an unexpected type.
        """
        if msg.KIND != Kind.REQUEST:
            raise ValueError(f"request: {msg.TYPE.name} is not a request")
        expect = expect or msg.REPLY
        waited = 0.0
        attempt_timeout = timeout_s
        for attempt in range(retries + 1):
            self._check_open()
            rid = self._new_request_id()
            pending = _Pending()
            with self._cond:
                self._pending[rid] = pending
            try:
                wire = self._encode(msg, rid)
                with self._cond:
                    self._control.append(_Out(wire))
                    self._cond.notify_all()
                got = pending.event.wait(attempt_timeout)
            finally:
                with self._cond:
                    self._pending.pop(rid, None)
            waited += attempt_timeout
            if got:
                reply = pending.reply
                if isinstance(reply, BaseException):
                    raise reply
                if isinstance(reply, m.Error):
                    raise reply.to_exception()
                if expect is not None and not isinstance(reply, expect):
                    name = getattr(getattr(reply, "TYPE", None), "name", type(reply).__name__)
                    raise MalformedMessage(
                        f"{self.name}: {msg.TYPE.name} answered with {name}, "
                        f"expected {expect.TYPE.name}"
                    )
                if on_reply is not None:
                    on_reply(rid, reply)  # type: ignore[arg-type]
                return reply  # type: ignore[return-value]
            if attempt < retries:
                self.stats.request_retries += 1
                attempt_timeout = min(attempt_timeout * backoff, max_timeout_s)
        raise TransportTimeout(
            f"{self.name}: no reply to {msg.TYPE.name} after {retries + 1} attempts over "
            f"{waited:.1f} s (is the device running and on this port/baud?)"
        )

    # ------------------------------------------------------------------ listeners
    def add_listener(self, request_id: int, callback: Callable[[m.Message], None]) -> None:
        """Route later RESPONSE/ACK frames with ``request_id`` (no request waiting) to
        ``callback(msg)`` on the reader thread (an image transfer's acks and errors)."""
        with self._cond:
            self._listeners[request_id] = callback

    def remove_listener(self, request_id: int) -> None:
        """Stop routing ``request_id`` (its later frames become stale)."""
        with self._cond:
            self._listeners.pop(request_id, None)

    def defer(self, task: Callable[[], None]) -> None:
        """Run ``task()`` on the dispatcher thread after the frames already in the inbox."""
        with self._cond:
            self._inbox.append(task)
            self._cond.notify_all()

    def inbox_image_frames(self) -> int:
        """Image chunks waiting for the dispatcher (the receive buffers in use)."""
        with self._cond:
            return self._inbox_images

    # ------------------------------------------------------------------ baud
    def wait_writer_idle(self, timeout_s: float = 5.0) -> bool:
        """Wait until every queued frame has been written."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._control or self._scores or self._image or self._writing:
                left = deadline - time.monotonic()
                if left <= 0 or self._error is not None:
                    return False
                self._cond.wait(min(left, self._poll_s))
        return True

    def drain_transport(self) -> None:
        """Wait until the bytes written have left the local port (mem line / UART)."""
        port = getattr(self.transport, "port", None)
        flush = getattr(port, "flush", None)
        if flush is not None:
            with contextlib.suppress(Exception):
                flush()

    def switch_baud(self, baud: int) -> None:
        """Change the local line rate now: drain, set, reset the decoder, send a lone 0x00.

        Call with the writer idle (after the OK of SET_BAUD, or from ``after_sent``).
        """
        self.drain_transport()
        self.transport.set_baud(baud)
        self._reset_decoder = True
        with contextlib.suppress(TransportError):
            self.transport.write(b"\x00")

    # ------------------------------------------------------------------ threads
    def _fail(self, exc: BaseException) -> None:
        with self._cond:
            if self._error is None and not self._closing:
                self._error = exc
            self._cond.notify_all()
        self._fail_pending(exc)
        report = False
        with self._cond:
            if not self._close_reported:
                self._close_reported = True
                report = True
        if report and self._on_close is not None:
            try:
                self._on_close(exc)
            except Exception:  # a callback bug must not kill the thread silently
                _logger.exception("%s: on_close callback failed", self.name)

    def _fail_pending(self, exc: BaseException) -> None:
        with self._cond:
            pendings = list(self._pending.values())
            self._pending.clear()
            listeners = list(self._listeners.values())
        for pending in pendings:
            pending.reply = exc if isinstance(exc, ProtocolError) else TransportClosed(str(exc))
            pending.event.set()
        for listener in listeners:
            with contextlib.suppress(Exception):
                listener(None)  # type: ignore[arg-type]

    def _reader_loop(self) -> None:
        while not self.closed:
            try:
                data = self.transport.read(_READ_BYTES, self._poll_s)
            except TransportError as exc:
                self._fail(exc if isinstance(exc, TransportClosed) else TransportClosed(str(exc)))
                return
            except Exception as exc:  # an adapter bug: report it as a closed link
                self._fail(TransportClosed(f"{self.name}: read failed: {exc}"))
                return
            if not data:
                continue
            self.stats.bytes_received += len(data)
            if self._reset_decoder:
                self._reset_decoder = False
                self.decoder.reset()
            for frame in self.decoder.feed(data):
                self.stats.frames_received += 1
                self.handle_frame(frame)

    def handle_frame(self, frame: Frame) -> None:
        """Route one decoded frame (the reader calls this; tests may too). Never raises."""
        try:
            self._route(frame)
        except Exception:  # a bug here must not stop the reader
            self.stats.handler_errors += 1
            _logger.exception("%s: routing a frame failed", self.name)

    def _route(self, frame: Frame) -> None:
        if self._on_frame is not None:
            self._on_frame(frame)
        try:
            msg = m.decode_message(frame)
        except MalformedMessage as exc:
            self.stats.malformed += 1
            if frame.kind == Kind.REQUEST:
                self._reply_quietly(
                    m.Error(
                        code=m.ErrorCode.MALFORMED,
                        where=_type_name(frame.msg_type),
                        message=_clip(str(exc), 256),
                    ),
                    frame.request_id,
                )
            elif frame.kind in (Kind.RESPONSE, Kind.ACK):
                self._deliver_response(frame.request_id, exc)
            return
        if isinstance(msg, m.UnknownMessage):
            self.stats.unknown += 1
            if msg.must_understand and frame.kind in (Kind.REQUEST, Kind.EVENT):
                self._reply_quietly(msg.error_reply(), frame.request_id)
            return
        if frame.kind in (Kind.RESPONSE, Kind.ACK):
            self._deliver_response(frame.request_id, msg)
            return
        with self._cond:
            is_image = frame.channel == Channel.IMAGE and frame.kind == Kind.EVENT
            if len(self._inbox) >= self._inbox_frames or (
                is_image and self._inbox_images >= self._image_inbox_frames
            ):
                self.stats.inbox_dropped += 1
                return
            self._inbox.append((msg, frame))
            if is_image:
                self._inbox_images += 1
            self._cond.notify_all()

    def _deliver_response(self, request_id: int, msg: m.Message | BaseException) -> None:
        with self._cond:
            pending = self._pending.pop(request_id, None)
            listener = None if pending is not None else self._listeners.get(request_id)
        if pending is not None:
            if isinstance(msg, MalformedMessage):
                pending.reply = MalformedMessage(f"{self.name}: reply did not decode: {msg}")
            else:
                pending.reply = msg
            pending.event.set()
        elif listener is not None and not isinstance(msg, BaseException):
            listener(msg)
        else:
            self.stats.stale_responses += 1

    def _reply_quietly(self, msg: m.Message, request_id: int) -> None:
        """Queue an ERROR from the reader; dropped (counted) when the peer is not reading."""
        if len(self._control) >= self._control_limit:
            self.stats.inbox_dropped += 1
            return
        with contextlib.suppress(ProtocolError, ValueError):
            self.send(msg, request_id=request_id)

    def _dispatch_loop(self) -> None:
        while True:
            with self._cond:
                # Backpressure: while the peer does not take our replies, stop consuming the
                # inbox (which then fills and drops) instead of queueing replies without bound.
                while (
                    not self._inbox or len(self._control) >= self._control_limit
                ) and not self.closed:
                    self._cond.wait(self._poll_s)
                if self.closed:
                    return
                item = self._inbox.popleft()
                if not callable(item) and item[1].channel == Channel.IMAGE and (
                    item[1].kind == Kind.EVENT
                ):
                    self._inbox_images -= 1
            if callable(item):
                try:
                    item()
                except Exception:
                    self.stats.handler_errors += 1
                    _logger.exception("%s: deferred task failed", self.name)
                continue
            msg, frame = item
            self._dispatch(msg, frame)

    def _dispatch(self, msg: m.Message, frame: Frame) -> None:
        is_request = frame.kind == Kind.REQUEST
        try:
            if self._handler is None:
                if not is_request:
                    return
                reply: m.Message | None = m.Error(
                    code=m.ErrorCode.UNSUPPORTED,
                    where=msg.TYPE.name,
                    message=f"{msg.TYPE.name} is not handled on this side",
                )
            else:
                reply = self._handler(msg, frame)
        except Exception as exc:
            self.stats.handler_errors += 1
            if not is_request:
                _logger.debug("%s: %s handler: %s", self.name, msg.TYPE.name, exc)
                return
            reply = self._error_mapper(exc, msg.TYPE.name)
        if reply is not None and is_request:
            self._reply_quietly(reply, frame.request_id)

    def _writer_loop(self) -> None:
        while True:
            with self._cond:
                while not (self._control or self._scores or self._image) and not self.closed:
                    self._cond.wait(self._poll_s)
                if self.closed:
                    return
                if not self._control and not self._scores and self.tx_low_water_bytes is not None:
                    wait_s = self._tx_backlog_wait_s()
                    if wait_s > 0:  # let the port drain first; control frames may arrive
                        self._cond.wait(wait_s)
                        continue
                if self._control:
                    out = self._control.popleft()
                elif self._scores:
                    key = next(iter(self._scores))
                    out = self._scores.pop(key)
                else:
                    out = self._image.popleft()
                self._writing = True
                self._cond.notify_all()
            try:
                self.transport.write(out.data)
                self.stats.frames_sent += 1
                self.stats.bytes_sent += len(out.data)
                if out.after_sent is not None:
                    self.drain_transport()
                    out.after_sent()
            except TransportError as exc:
                with self._cond:
                    self._writing = False
                self._fail(exc)
                return
            except Exception as exc:  # an adapter or callback bug
                _logger.exception("%s: write failed", self.name)
                with self._cond:
                    self._writing = False
                self._fail(TransportClosed(f"{self.name}: write failed: {exc}"))
                return
            with self._cond:
                self._writing = False
                self._cond.notify_all()


    def _tx_backlog_wait_s(self) -> float:
        """How long until the port's transmit backlog falls to ``tx_low_water_bytes`` (0: now)."""
        port = getattr(self.transport, "port", None)
        try:
            backlog = int(port.out_waiting) if port is not None else 0
        except Exception:  # a port without a transmit count: never wait
            return 0.0
        excess = backlog - int(self.tx_low_water_bytes or 0)
        if excess <= 0:
            return 0.0
        baud = getattr(self.transport, "baud", 0) or 115200
        return min(max(excess / (baud / 10.0), 0.0005), self._poll_s)


def _type_name(msg_type: int) -> str:
    try:
        return m.MessageType(msg_type).name
    except ValueError:
        return f"type 0x{msg_type:02x}"


def _clip(text: str, max_bytes: int) -> str:
    data = text.encode("utf-8", "replace")
    if len(data) <= max_bytes:
        return text
    return data[: max_bytes - 3].decode("utf-8", "ignore") + "..."


# --------------------------------------------------------------------------- image transfer


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


# --------------------------------------------------------------------------- host session


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
        host_proof = m.auth_proof(
            self.key,
            role="host",
            host_nonce=self._host_nonce,
            device_nonce=hello.nonce,
            device_id=hello.device_id,
        )
        reply = self.link.request(
            m.AuthChallenge(host_proof=host_proof),
            timeout_s=self.request_timeout_s,
            retries=self.retries,
        )
        assert isinstance(reply, m.AuthResponse)
        expected = m.auth_proof(
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
        self._session_key = m.derive_session_key(self.key, self._host_nonce, hello.nonce)
        self._counter = 0
        self._event_counters = {}
        self.authenticated = True
        # A keyed device tells its slots and budgets only after AUTH (protocol 2).
        full = {
            name: getattr(reply, name)
            for name in ("slots", "ram_budget_bytes", "slot_size_bytes")
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
        return m.sign(msg, self._session_key, self._counter)

    def tag_event(self, msg: m.TaggedEvent) -> m.TaggedEvent:
        """Return SCORES/IMAGE_CHUNK ``msg`` tagged with its channel's next counter
        (unchanged when not authenticated: a keyless device takes it untagged)."""
        if self._session_key is None:
            return msg
        with self._event_lock:
            counter = self._event_counters.get(int(msg.TYPE), 0) + 1
            self._event_counters[int(msg.TYPE)] = counter
        return m.tag_event(msg, self._session_key, counter)

    def send_scores(self, msg: m.Scores, *,
                    after_sent: Callable[[], None] | None = None) -> None:
        """Tag (when authenticated) and queue a SCORES event; counters leave in send order."""
        with self._event_lock:
            if self._session_key is not None:
                counter = self._event_counters.get(int(msg.TYPE), 0) + 1
                self._event_counters[int(msg.TYPE)] = counter
                msg = m.tag_event(msg, self._session_key, counter)  # type: ignore[assignment]
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
