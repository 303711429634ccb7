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

On top of the link, each in its own module and importable from here as well:

* :func:`~protocol.image_transfer.send_image` (``image_transfer.py``) streams an image in a
  credit-based sliding window with cumulative acknowledgements and fast retransmission.
* :class:`~protocol.host_session.HostSession` (``host_session.py``): HELLO (version
  negotiation), mutual AUTH, signed mutating requests with a monotonic counter, tagged
  events, PING and SET_BAUD.

docs/protocol.md ("Link engine", "Provisioning", "State machines") is the specification.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from protocol import messages as m
from protocol.errors import (
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
    "Link",
    "LinkStats",
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


# --------------------------------------------------------------------------- on top of the link

#: Names of the modules on top of the engine, importable from here as before the split.
_ON_TOP = {
    "RETRANSMIT_STRATEGIES": "protocol.image_transfer",
    "TransferStats": "protocol.image_transfer",
    "send_image": "protocol.image_transfer",
    "HostSession": "protocol.host_session",
    "negotiate_version": "protocol.host_session",
}


def __getattr__(name: str) -> Any:
    """``from protocol.link import send_image, HostSession`` (they import this module)."""
    module = _ON_TOP.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
