"""The device's protocol side: a :class:`Device` answers a host over any transport.

One :class:`Device` owns a :class:`~device_runtime.flash.FlashStore` and serves
one host at a time through a :class:`~protocol.link.Link` (``serve``), and
keeps serving after a host goes away (``run``: a TCP listener accepts the next
host; a serial port is reopened and read again). Handlers are registered per
message type (``HANDLERS``; subclasses and :meth:`Device.on` add more); the
issue-5 runtime adds its SCORES/VIEW_REQUEST handling through the hooks
:meth:`Device.on_scores`, :meth:`Device.on_keyframe_request` and
:meth:`Device.on_image_committed` without rewriting the dispatcher.

This module is the session and authentication dispatcher (HELLO, AUTH, signed requests,
tagged events, SET_BAUD, RESET, SLOT_SET, the serve/run loops). The transfer handlers
(IMAGE_*) and what the device accepts as an image are :mod:`device_runtime.image_receiver`
(:class:`Device` inherits its :class:`~device_runtime.image_receiver.ImageReceiver`); the
ERROR sent for an exception is :mod:`device_runtime.wire_errors`. Their names are still
importable from here.

Session state machine (docs/protocol.md, "State machines")::

    NO_SESSION --HELLO--> HELLO'D --AUTH_CHALLENGE ok--> AUTHENTICATED
         ^                   |  (device without a key + --insecure: HELLO'D acts as
         +--- BYE, disconnect, new HELLO ---+   authenticated for signed requests)

Signed requests (SET_BAUD, RESET, SLOT_SET, IMAGE_BEGIN, IMAGE_COMMIT,
IMAGE_ABORT) need AUTHENTICATED and a session tag whose counter is above the
last one accepted; an exact repeat of the last accepted signed frame (a host
retry after a lost reply) is answered with the cached reply and not executed
again.

Transfer state machine::

    none --IMAGE_BEGIN--> RECEIVING --all bytes + IMAGE_VERIFY ok--> VERIFIED
                              |                                         |
                              +-- refusal (RAM, format) / abort --+     +--IMAGE_COMMIT-->
                                                                  v        slot TEST
                                                                 none      -> load, confirm

Bad input never stops the device: frames that do not decode are counted and
dropped by the link; a request that fails is answered with the ERROR for its
exception (:func:`error_for`); memory is bounded by the frame size, the inbox
(``rx_window_frames`` chunks) and the RAM budget given to the image reader.
"""

from __future__ import annotations

import contextlib
import hmac
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from device_runtime.busy_door import BusyDoor
from device_runtime.device_config import (
    DEFAULT_DEVICE_ID,
    DEFAULT_RAM_BUDGET_BYTES,
    DEFAULT_RX_WINDOW_FRAMES,
    DeviceConfig,
    DeviceStats,
)
from device_runtime.errors import DeviceError, FlashError
from device_runtime.flash import (
    FlashStore,
)
from device_runtime.image_receiver import (
    ImageReceiver,
    _Transfer,
    image_problem,
    read_device_image,
    required_ram_bytes,
)
from device_runtime.lobby import Lobby
from device_runtime.wire_errors import DeviceRefusal, _one_line, error_for
from protocol import auth
from protocol import messages as m
from protocol.errors import (
    AuthenticationError,
    NotAuthenticated,
    ProtocolError,
    ReplayError,
    TransportError,
)
from protocol.framing import Frame
from protocol.image import (
    MAX_MANIFEST_BYTES,
    SUPPORTED_VERSIONS,
)
from protocol.link import CHUNK_OVERHEAD_BYTES, Link
from protocol.transport import TcpListenTransport, open_transport

__all__ = [
    "DEFAULT_DEVICE_ID",
    "DEFAULT_RAM_BUDGET_BYTES",
    "DEFAULT_RX_WINDOW_FRAMES",
    "SUPPORTED_BAUDS",
    "Device",
    "DeviceConfig",
    "DeviceRefusal",
    "DeviceStats",
    "error_for",
    "image_problem",
    "read_device_image",
    "required_ram_bytes",
]

_logger = logging.getLogger("device_runtime.device")

SUPPORTED_BAUDS = (
    9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
    1000000, 1152000, 1500000, 2000000, 2500000, 3000000, 3500000, 4000000,
)
"""Line rates SET_BAUD accepts (others: ERROR(UNSUPPORTED))."""
PROTOCOL_VERSIONS = (m.PROTOCOL_VERSION, m.PROTOCOL_VERSION)
"""(min, max) protocol versions this device speaks."""
SOFTWARE = "eigencast-device 0.1"


@dataclass
class _Session:
    host_nonce: bytes | None = None
    device_nonce: bytes | None = None
    host_id: str = ""
    version: int = 0
    session_key: bytes | None = None
    last_counter: int = 0
    last_signed: tuple[int, bytes, m.Message] | None = None
    transfer: _Transfer | None = None
    event_counters: dict[int, int] = field(default_factory=dict)  # SCORES, IMAGE_CHUNK only

    @property
    def hello_done(self) -> bool:
        return self.device_nonce is not None

    @property
    def authenticated(self) -> bool:
        return self.session_key is not None


_SESSION_EVENTS = frozenset(
    {m.MessageType.SCORES, m.MessageType.IMAGE_CHUNK, m.MessageType.KEYFRAME_REQUEST}
)
"""Events that need a session (HELLO); the tagged ones also AUTH + a tag on a keyed device."""
_DROP_LOG_INTERVAL_S = 5.0
_MAX_TOLD_NO_TRANSFER = 64


# --------------------------------------------------------------------------- device


class Device(ImageReceiver):
    """A device: flash store, session state and per-message handlers.

    Parameters
    ----------
    config : DeviceConfig
    log : callable, optional
        ``log(line)`` for one line per event (default: the module logger at INFO).

    Attributes
    ----------
    store : FlashStore
    boot_result : BootResult
        What the last boot decided.
    stats : DeviceStats
    link : Link or None
        The current host's link while one is served.
    """

    HANDLERS: ClassVar[dict[m.MessageType, str]] = {
        m.MessageType.HELLO: "handle_hello",
        m.MessageType.AUTH_CHALLENGE: "handle_auth_challenge",
        m.MessageType.PING: "handle_ping",
        m.MessageType.BYE: "handle_bye",
        m.MessageType.SET_BAUD: "handle_set_baud",
        m.MessageType.RESET: "handle_reset",
        m.MessageType.SLOT_SET: "handle_slot_set",
        m.MessageType.IMAGE_STATUS: "handle_image_status",
        m.MessageType.IMAGE_BEGIN: "handle_image_begin",
        m.MessageType.IMAGE_CHUNK: "handle_image_chunk",
        m.MessageType.IMAGE_VERIFY: "handle_image_verify",
        m.MessageType.IMAGE_COMMIT: "handle_image_commit",
        m.MessageType.IMAGE_ABORT: "handle_image_abort",
        m.MessageType.SCORES: "handle_scores",
        m.MessageType.VIEW_REQUEST: "handle_unexpected",
        m.MessageType.KEYFRAME_REQUEST: "handle_keyframe_request",
        m.MessageType.NOTICE: "handle_notice",
    }
    """Message type -> method name; :meth:`on` overrides per instance."""

    def __init__(
        self, config: DeviceConfig, *, log: Callable[[str], None] | None = None
    ) -> None:
        self.config = config
        self._log = log or (lambda line: _logger.info("%s", line))
        self.stats = DeviceStats()
        self.session = _Session()
        self.link: Link | None = None
        self.transport: Any = None
        self._extra_handlers: dict[int, Callable[[m.Message, Frame], m.Message | None]] = {}
        self._end_session = threading.Event()
        self._reboot_requested = False
        self._baud_timer: threading.Timer | None = None
        self._told_no_transfer: set[int] = set()
        self._drop_logged: dict[str, float] = {}
        self.lobby: Lobby | None = None
        self.door: BusyDoor | None = None
        self.store = FlashStore.open(config.flash_dir, capacity_bytes=config.slot_size_bytes)
        self.boot_result = self.boot()

    # ------------------------------------------------------------------ setup

    def log(self, line: str) -> None:
        """Log one event line."""
        self._log(line)

    def on(self, msg_type: m.MessageType, handler: Callable[[m.Message, Frame], Any]) -> None:
        """Register ``handler(msg, frame) -> reply or None`` for ``msg_type`` on this device."""
        self._extra_handlers[int(msg_type)] = handler

    @property
    def max_frame_bytes(self) -> int:
        """Largest frame this device accepts and sends."""
        if self.config.max_frame_bytes is not None:
            return self.config.max_frame_bytes
        if self.transport is not None:
            return max(self.transport.max_frame_bytes, m.BASELINE_MAX_FRAME_BYTES)
        return 4096

    @property
    def rx_buffer_bytes(self) -> int:
        """Largest IMAGE_CHUNK data accepted."""
        limit = self.max_frame_bytes - CHUNK_OVERHEAD_BYTES
        if self.config.rx_buffer_bytes is not None:
            return min(self.config.rx_buffer_bytes, limit)
        return limit

    @property
    def window_bytes(self) -> int:
        """Bytes beyond the acked offset a host may send."""
        return self.config.rx_window_frames * self.rx_buffer_bytes

    @property
    def provisioning_allowed(self) -> bool:
        """A key is installed, or the device runs ``--insecure``."""
        return self.config.key is not None or self.config.insecure

    # ------------------------------------------------------------------ boot
    def boot(self) -> Any:
        """Boot the flash store, then load the active image (confirming a test image).

        An active image that does not load, whatever its state, is given up for the
        other slot (:meth:`fall_back`), as MCUboot does.
        """
        result = self.store.boot()
        self.log(f"boot: {result.reason}")
        if result.ok:
            self._load_and_confirm("boot")
        return result

    def _load_and_confirm(self, why: str) -> bool:
        """Load and validate the active image; confirm a TEST one; fall back when it fails.

        Issue 4 has no display: the image is confirmed once it has been read
        and validated (digest, tag, structure, RAM bounds). The issue-5
        runtime overrides :meth:`on_image_committed` to confirm after the first frame.
        """
        for _ in range(2):  # the active slot, then at most the one it fell back to
            slot = self.store.active_slot
            if slot is None:
                return False
            info = self.store.slots[0 if slot == "A" else 1]
            try:
                self.load_active_image()
            except (ProtocolError, DeviceError, OSError, ValueError) as exc:
                if self.fall_back(why, slot, exc) is None:
                    return False
                continue
            if info.state.name != "TEST":
                self.log(f"{why}: slot {slot}: image generation {info.image_generation} loaded")
                return True
            self.store.confirm()
            self.log(f"{why}: slot {slot}: image generation {info.image_generation} loaded and "
                     "confirmed")
            self.notice(0, f"slot {slot}: image confirmed",
                        {"event": "confirmed", "slot": slot,
                         "generation": info.image_generation})
            return True
        return False

    def fall_back(self, why: str, slot: str, exc: BaseException) -> str | None:
        """The active image (``slot``) cannot be loaded: give it up for the other slot.

        The slot is marked BAD (not loadable) and the other slot, if it holds a
        confirmed image that verifies, becomes active, in one state write
        (:meth:`FlashStore.reject_active`); a log line and an error NOTICE
        (``event`` ``load-failed``) say why. Nothing from ``slot`` is shown.

        Returns
        -------
        str or None
            The slot active now, or None when no image is.
        """
        reason = _one_line(str(exc), 160)
        self.log(f"{why}: slot {slot}: the image does not load ({reason})")
        try:
            now = self.store.reject_active()
        except FlashError as err:
            self.log(f"{why}: slot {slot}: cannot give it up: {err}")
            now = None
        outcome = (f"fell back to slot {now}" if now is not None
                   else "no other slot holds a confirmed image: nothing to show")
        self.log(f"{why}: slot {slot} marked bad; {outcome}")
        self.notice(2, f"slot {slot}: the image does not load ({reason}); {outcome}",
                    {"event": "load-failed", "slot": slot, "active": now or "",
                     "reason": reason})
        return now

    def load_active_image(self) -> Any:
        """Read and validate the active image as this device loads it; return it.

        Raises
        ------
        ImageFormatError, ImageTagError, FlashError, BudgetError
        """
        with self.store.open_active() as stream:
            return read_device_image(stream, key=self.config.key,
                                     ram_budget_bytes=self.config.ram_budget_bytes)

    def _max_manifest_bytes(self) -> int:
        return min(MAX_MANIFEST_BYTES, self.config.ram_budget_bytes)

    def reboot(self) -> None:
        """What RESET does: drop the session, close and reopen the flash store, boot."""
        self.session = _Session()
        with contextlib.suppress(FlashError):
            self.store.close()
        self.store = FlashStore.open(self.config.flash_dir)
        self.boot_result = self.boot()

    def close(self) -> None:
        """Flush an open image writer (its journal allows a resume) and release the store."""
        self._cancel_baud_timer()
        with contextlib.suppress(FlashError):
            self.store.close()

    # ------------------------------------------------------------------ serving
    def run(
        self,
        url: str,
        *,
        baud: int = 115200,
        stop: threading.Event | None = None,
        on_ready: Callable[[Any], None] | None = None,
        transport: Any = None,
    ) -> None:
        """Serve hosts on ``url`` until ``stop`` is set (keeps going after disconnects).

        Parameters
        ----------
        url : str
            ``tcp-listen://HOST:PORT`` or any port URL ``open_transport`` accepts.
        baud : int
            Line rate of serial ports.
        stop : threading.Event, optional
        on_ready : callable, optional
            ``on_ready(transport)`` once the transport is open (e.g. to print the port).
        transport : Transport, optional
            Already opened from ``url`` (it is reopened from ``url`` after a cut line).

        Raises
        ------
        TransportError
            The transport cannot be opened at start.
        """
        stop = stop or threading.Event()
        if transport is None:
            transport = open_transport(
                url, baud=baud, max_frame_bytes=self.config.max_frame_bytes
            )
        listening = isinstance(transport, TcpListenTransport)
        if on_ready is not None:
            on_ready(transport)
        backoff = 0.05
        try:
            while not stop.is_set():
                self.serve(transport, stop=stop)
                if self._reboot_requested:
                    self._reboot_requested = False
                    if listening:
                        transport.disconnect()
                    self.log("reset: rebooting")
                    self.reboot()
                if stop.is_set() or listening:
                    continue
                transport.close()  # a serial line: reopen it (a fresh mem:// line after a cut)
                while not stop.is_set():
                    try:
                        transport = open_transport(
                            url, baud=baud, max_frame_bytes=self.config.max_frame_bytes
                        )
                        break
                    except TransportError as exc:
                        self.log(f"reopen {url}: {exc}; retrying in {backoff:.2f} s")
                        stop.wait(backoff)
                        backoff = min(backoff * 2, 2.0)
                backoff = 0.05
        finally:
            if self.lobby is not None:
                self.lobby.close()
                self.lobby = None
            if self.door is not None:
                self.door.close()
                self.door = None
            transport.close()
            self.close()

    def serve(self, transport: Any, *, stop: threading.Event | None = None) -> None:
        """Serve one connection on ``transport`` until the link drops, RESET, or ``stop``.

        A keyed device listening on TCP first runs its :class:`~device_runtime.lobby.Lobby`
        until a connection authenticates, and serves that one. While a host is served on
        TCP, other connections are told BUSY (:class:`~device_runtime.busy_door.BusyDoor`);
        those still in its grace when the host leaves are the next session's."""
        stop = stop or threading.Event()
        self.transport = transport
        self._end_session.clear()
        self.session = _Session()
        listening = isinstance(transport, TcpListenTransport)
        keyed = self.config.key is not None
        admitted = None
        if listening and (self.door is None or self.door.listener is not transport.listener):
            self.door = BusyDoor(transport.listener, log=self._log_limited)
        if listening and keyed:
            admitted = self._admit(transport, stop)
            if admitted is None:
                return
            self.session = admitted.session
        elif listening and not transport.connected:
            waiting = self.door.release()
            if waiting:  # the oldest is the host; the rest wait in the door again
                transport.adopt(*waiting[0])
                for sock, address in waiting[1:]:
                    self.door.hold(sock, address, time.monotonic())
        last_frame = [time.monotonic()]

        def on_frame(frame: Frame) -> None:
            last_frame[0] = time.monotonic()

        link = self._open_link(transport, admitted, on_frame)
        unauth_since: float | None = None  # keyed TCP: since when this peer is not authenticated
        try:
            while not stop.is_set() and not self._end_session.is_set():
                if link.wait_closed(0.05 if listening and keyed else 0.25):
                    break
                now = time.monotonic()
                if (
                    listening
                    and transport.connected
                    and now - last_frame[0] > self.config.idle_timeout_s
                ):
                    self._log_limited("silent", f"host silent for "
                                      f"{self.config.idle_timeout_s:.0f} s; dropped")
                    break
                if listening and not transport.connected:
                    last_frame[0] = now
                    unauth_since = None
                    continue
                if listening:
                    self.door.poll(now)
                if not (listening and keyed):
                    continue
                # The lobby let in a connection whose AUTH verifies; should its session lose
                # authentication (a new HELLO), it has auth_timeout_s to authenticate again.
                if self.session.authenticated:
                    unauth_since = None
                    continue
                if unauth_since is None:
                    unauth_since = now
                if now - unauth_since > self.config.auth_timeout_s:
                    self.stats.auth_timeouts += 1
                    self._log_limited("auth-timeout", f"peer did not authenticate within "
                                      f"{self.config.auth_timeout_s:g} s; dropped")
                    break
        finally:
            self._end_connection(link, transport, listening)

    def _admit(self, transport: Any, stop: threading.Event) -> Any:
        """A keyed TCP device: the lobby (with those the busy door held) until a connection
        authenticates; that one (None: ``stop``)."""
        if self.lobby is None or self.lobby.transport is not transport:
            self.lobby = Lobby(transport, self, auth_timeout_s=self.config.auth_timeout_s,
                               log=self._log_limited)
        for sock, address in self.door.release():
            self.lobby.hold(sock, address, time.monotonic())
        return self.lobby.admit(stop)

    def _open_link(self, transport: Any, admitted: Any, on_frame: Callable[[Frame], None]
                   ) -> Link:
        """The session's link engine (``self.link``), started after it handled what the
        lobby already read (the AUTH_CHALLENGE and what followed)."""
        link = Link(
            transport,
            name=f"device {self.config.device_id}",
            handler=self.handle,
            error_mapper=self._map_error,
            rx_max_frame_bytes=self.max_frame_bytes,
            tx_max_frame_bytes=self.max_frame_bytes,
            inbox_frames=self.config.rx_window_frames + 16,
            image_inbox_frames=self.config.rx_window_frames,
            on_frame=on_frame,
        )
        self.link = link
        if admitted is not None:
            for frame in admitted.frames:
                link.handle_frame(frame)
            for frame in link.decoder.feed(admitted.partial):
                link.handle_frame(frame)
        link.start()
        return link

    def _end_connection(self, link: Link, transport: Any, listening: bool) -> None:
        """Close the link and the connection, forget the session, flush the flash, and say
        why the host left (at most a line every few seconds for an unauthenticated peer)."""
        error = link.error
        link.close(flush_timeout_s=1.0)
        self.link = None
        self._cancel_baud_timer()
        if listening:
            transport.disconnect()
        had_session = self.session.hello_done
        authenticated = self.session.authenticated
        self.session = _Session()
        with contextlib.suppress(FlashError):
            self.store.close()  # flush: a resumed transfer keeps what was received
        if had_session or error is not None:
            why = ""
            if error is not None and "disconnected" not in str(error):
                why = f" ({_one_line(str(error), 120)})"
            if authenticated:
                self.log(f"host disconnected{why}")
            else:  # any peer can cause this one: at most one a few seconds
                self._log_limited("disconnected", f"host disconnected{why}")

    # ------------------------------------------------------------------ dispatch
    def _map_error(self, exc: BaseException, where: str) -> m.Error:
        self.stats.errors_sent += 1
        error = error_for(exc, where)
        self.stats.refused[error.code_name] = self.stats.refused.get(error.code_name, 0) + 1
        return error

    def handle(self, msg: m.Message, frame: Frame) -> m.Message | None:
        """Answer one request or event (the link's handler; runs on its dispatcher thread).

        SCORES, IMAGE_CHUNK and KEYFRAME_REQUEST go through :meth:`admit_event` first.
        """
        if msg.TYPE in _SESSION_EVENTS and not self.admit_event(msg):
            return None
        method = self._extra_handlers.get(int(msg.TYPE))
        if method is None:
            name = self.HANDLERS.get(msg.TYPE)
            if name is None:
                if frame.kind == m.Kind.REQUEST:
                    raise DeviceRefusal(
                        m.ErrorCode.UNSUPPORTED, f"{msg.TYPE.name} is not accepted by a device"
                    )
                return None
            method = getattr(self, name)
        if not isinstance(msg, m.SignedRequest):  # handlers added with on() are checked alike
            return method(msg, frame)
        cached = self._authorize(msg, frame)
        if cached is not None:
            return cached
        try:
            reply = method(msg, frame)
        except Exception as exc:
            reply = self._map_error(exc, msg.TYPE.name)
            self._remember(frame, reply)
            return reply
        self._remember(frame, reply)
        return reply

    def admit_event(self, msg: m.Message) -> bool:
        """Whether a SCORES / IMAGE_CHUNK / KEYFRAME_REQUEST may be decoded or stored.

        It needs a session (HELLO). On a keyed device SCORES and IMAGE_CHUNK also need an
        authenticated session and an event tag (:func:`protocol.auth.verify_event`)
        whose counter is above the last one accepted on that channel. Refused events are
        counted in :attr:`stats` (``dropped_*``) and logged at most once per reason every
        few seconds; nothing is answered (an answer would be an oracle).
        """
        session = self.session
        name = msg.TYPE.name
        if not session.hello_done:
            self.stats.dropped_no_session += 1
            self._log_limited("no-session", f"{name} from a peer without a session (no HELLO) "
                           "dropped")
            return False
        if self.config.key is None or not isinstance(msg, m.TaggedEvent):
            return True
        if session.session_key is None:
            self.stats.dropped_unauthenticated += 1
            self._log_limited("unauthenticated", f"{name} outside an authenticated session "
                           "dropped (this device has a key)")
            return False
        channel = int(msg.TYPE)
        try:
            counter = auth.verify_event(msg, session.session_key,
                                     session.event_counters.get(channel, 0))
        except ReplayError:
            self.stats.dropped_replayed += 1
            self._log_limited("replayed", f"replayed {name} dropped")
            return False
        except NotAuthenticated:
            self.stats.dropped_unauthenticated += 1
            self._log_limited("untagged", f"{name} without an event tag dropped")
            return False
        except AuthenticationError:
            self.stats.dropped_bad_tag += 1
            self._log_limited("bad-tag", f"{name} with a bad event tag dropped")
            return False
        session.event_counters[channel] = counter
        return True

    def _log_limited(self, reason: str, line: str) -> None:
        """Log ``line`` unless the same reason was logged in the last few seconds.

        Every line an unauthenticated peer can cause goes through here, so no peer can
        grow the device's log faster than one line per reason per interval.
        """
        now = time.monotonic()
        if now - self._drop_logged.get(reason, -_DROP_LOG_INTERVAL_S) >= _DROP_LOG_INTERVAL_S:
            self._drop_logged[reason] = now
            self.log(line)

    def _authorize(self, msg: m.SignedRequest, frame: Frame) -> m.Message | None:
        """Check a signed request; return a cached reply for an exact repeat, else None."""
        session = self.session
        last = session.last_signed
        if self.config.key is None:
            if self.config.insecure:  # no counters: an exact repeat of the last one is a retry
                if last is not None and last[0] == frame.msg_type and last[1] == frame.body:
                    return self._replay(last[2], frame)
                return None
            raise DeviceRefusal(
                m.ErrorCode.NOT_AUTHENTICATED,
                "this device has no key: pair one (eigencast-device --pair KEYFILE) or start "
                "it with --insecure",
            )
        if session.session_key is None:
            raise NotAuthenticated(
                f"{msg.TYPE.name} needs an authenticated session (HELLO, then AUTH_CHALLENGE)"
            )
        if (
            last is not None
            and msg.session_counter == session.last_counter
            and last[0] == frame.msg_type
            and last[1] == frame.body
        ):
            return self._replay(last[2], frame)
        session.last_counter = auth.verify(msg, session.session_key, session.last_counter)
        return None

    def _replay(self, reply: m.Message, frame: Frame) -> m.Message:
        """The cached reply to a repeated signed request (a host retry after a lost reply)."""
        transfer = self.session.transfer
        if isinstance(reply, m.ImageAck) and transfer is not None:
            transfer.request_id = frame.request_id  # a retried IMAGE_BEGIN: chunks use the new id
        return reply

    def _remember(self, frame: Frame, reply: m.Message | None) -> None:
        if reply is not None and (self.session.session_key is not None or self.config.insecure):
            self.session.last_signed = (frame.msg_type, frame.body, reply)

    def notice(self, level: int, text: str, detail: dict | None = None) -> None:
        """Send a NOTICE to the host if one is connected (best effort)."""
        link = self.link
        if link is None or link.closed:
            return
        with contextlib.suppress(ProtocolError, ValueError):
            link.send(m.Notice(level=level, text=_one_line(text, 256), detail=detail))

    def _send(self, msg: m.Message, request_id: int) -> None:
        link = self.link
        if link is not None and not link.closed:
            with contextlib.suppress(ProtocolError, ValueError):
                link.send(msg, request_id=request_id)

    def _slot_infos(self) -> tuple[m.SlotInfo, ...]:
        active = self.store.active_slot
        out = []
        for index, info in enumerate(self.store.slots):
            out.append(
                m.SlotInfo(
                    slot=index,
                    state=m.SlotState(int(info.state)),
                    active=info.name == active,
                    generation=info.image_generation,
                    size_bytes=info.size_bytes,
                    digest=info.sha256 or b"",
                )
            )
        return tuple(out)

    # ------------------------------------------------------------------ control handlers
    def handle_hello(self, msg: m.Hello, frame: Frame) -> m.Message:
        """Start a new session (forget the previous one); answer HELLO_REPLY."""
        low = max(msg.min_version, PROTOCOL_VERSIONS[0])
        high = min(msg.max_version, PROTOCOL_VERSIONS[1])
        if low > high:
            raise DeviceRefusal(
                m.ErrorCode.UNSUPPORTED_VERSION,
                f"the host speaks protocol versions {msg.min_version}..{msg.max_version}, this "
                f"device {PROTOCOL_VERSIONS[0]}..{PROTOCOL_VERSIONS[1]}: update the older side "
                "(protocol 2 authenticates scores and image chunks)",
                {"min_version": PROTOCOL_VERSIONS[0], "max_version": PROTOCOL_VERSIONS[1]},
            )
        with contextlib.suppress(FlashError):
            self.store.close()  # a transfer of the old session resumes from its journal
        self.session = _Session(
            host_nonce=msg.nonce,
            device_nonce=os.urandom(m.NONCE_BYTES),
            host_id=msg.host_id,
            version=high,
        )
        self._told_no_transfer.clear()
        self.stats.sessions += 1
        self._log_limited("hello", f"hello from host '{_one_line(msg.host_id or '?', 64)}' "
                                   f"(protocol {high})")
        # A keyed device tells an unauthenticated peer only what starting a session needs;
        # slots and budgets follow in AUTH_RESPONSE (mcumgr/MCUboot: state behind auth).
        hide = self.config.key is not None
        return m.HelloReply(
            min_version=PROTOCOL_VERSIONS[0],
            max_version=PROTOCOL_VERSIONS[1],
            device_id=self.config.device_id,
            nonce=self.session.device_nonce,
            max_frame_bytes=self.max_frame_bytes,
            ram_budget_bytes=0 if hide else self.config.ram_budget_bytes,
            slot_size_bytes=0 if hide else self.store.capacity_bytes,
            display_width=self.config.display_width,
            display_height=self.config.display_height,
            rx_window_frames=self.config.rx_window_frames,
            rx_buffer_bytes=self.rx_buffer_bytes,
            slots=() if hide else self._slot_infos(),
            has_key=self.config.key is not None,
            image_format_versions=tuple(SUPPORTED_VERSIONS),
            software=SOFTWARE,
        )

    def handle_auth_challenge(self, msg: m.AuthChallenge, frame: Frame) -> m.Message:
        """Check the host's proof; answer with ours and derive the session key."""
        session = self.session
        if not session.hello_done:
            raise DeviceRefusal(m.ErrorCode.BAD_STATE, "send HELLO before AUTH_CHALLENGE")
        if self.config.key is None:
            raise DeviceRefusal(
                m.ErrorCode.NOT_AUTHENTICATED,
                "this device has no key (pair one with eigencast-device --pair KEYFILE)",
            )
        if not self.proves_key(session, msg):
            self._log_limited("auth-failed",
                              "auth failed: the host's proof does not verify (wrong key?)")
            raise AuthenticationError(
                "AUTH_CHALLENGE: the host proof does not verify with this device's key"
            )
        key = auth.derive_session_key(self.config.key, session.host_nonce, session.device_nonce)
        if session.session_key != key:  # a repeated challenge keeps the counter state
            session.session_key = key
            session.last_counter = 0
            session.last_signed = None
            self.log("host authenticated")
        return m.AuthResponse(
            device_proof=auth.auth_proof(
                self.config.key,
                role="device",
                host_nonce=session.host_nonce,
                device_nonce=session.device_nonce,
                device_id=self.config.device_id,
            ),
            slots=self._slot_infos(),
            ram_budget_bytes=self.config.ram_budget_bytes,
            slot_size_bytes=self.store.capacity_bytes,
        )

    def proves_key(self, session: _Session | None, msg: m.AuthChallenge) -> bool:
        """Whether ``msg``'s host proof verifies with this device's key in ``session``
        (HELLO done)."""
        if self.config.key is None or session is None or not session.hello_done:
            return False
        assert session.host_nonce is not None and session.device_nonce is not None
        expected = auth.auth_proof(
            self.config.key,
            role="host",
            host_nonce=session.host_nonce,
            device_nonce=session.device_nonce,
            device_id=self.config.device_id,
        )
        return hmac.compare_digest(expected, msg.host_proof)

    def lobby_frame(self, session: _Session | None, msg: m.Message,
                    frame: Frame) -> tuple[m.Message | None, _Session]:
        """Answer one frame of a connection that has not authenticated, as its own session
        (the lobby's thread, while no host is served): (the reply, its session now). An
        exception becomes the ERROR a request gets (as on a link)."""
        self.session = session or _Session()
        try:
            reply = self.handle(msg, frame)
        except Exception as exc:
            reply = self._map_error(exc, msg.TYPE.name) if frame.kind == m.Kind.REQUEST else None
        finally:
            session, self.session = self.session, _Session()
        return reply, session

    def handle_ping(self, msg: m.Ping, frame: Frame) -> m.Message:
        """Echo a PING."""
        return m.Pong(
            payload=msg.payload,
            ping_sent_us=msg.sent_us,
            sent_us=int(time.monotonic() * 1e6),
        )

    def handle_bye(self, msg: m.Bye, frame: Frame) -> None:
        """End the session (state forgotten; a transfer resumes from its journal)."""
        line = f"bye from host{': ' + _one_line(msg.reason, 120) if msg.reason else ''}"
        if self.session.authenticated:
            self.log(line)
        else:
            self._log_limited("bye", line)
        with contextlib.suppress(FlashError):
            self.store.close()
        self.session = _Session()

    def handle_set_baud(self, msg: m.SetBaud, frame: Frame) -> None:
        """Answer OK at the old rate, switch, revert unless a valid frame arrives in time."""
        if msg.baud not in SUPPORTED_BAUDS:
            raise DeviceRefusal(
                m.ErrorCode.UNSUPPORTED,
                f"baud {msg.baud} is not supported (supported: "
                f"{', '.join(map(str, SUPPORTED_BAUDS))})",
            )
        link = self.link
        assert link is not None
        old = int(getattr(self.transport, "baud", 0) or 0)
        timeout_s = msg.revert_timeout_ms / 1000.0

        def switch() -> None:
            link.switch_baud(msg.baud)
            frames_then = link.stats.frames_received
            self.log(f"set-baud: {old or '?'} -> {msg.baud}; reverting in {timeout_s:.2f} s "
                     "unless the host answers")

            def check() -> None:
                if link.closed:
                    return
                if link.stats.frames_received == frames_then and old:
                    link.switch_baud(old)
                    self.log(f"set-baud: no valid frame at {msg.baud}; reverted to {old}")
                else:
                    self.log(f"set-baud: now {msg.baud}")

            self._cancel_baud_timer()
            timer = threading.Timer(timeout_s, check)
            timer.daemon = True
            self._baud_timer = timer
            timer.start()

        reply = m.Ok()
        self._remember(frame, reply)
        link.send(reply, request_id=frame.request_id, after_sent=switch)
        return None

    def _cancel_baud_timer(self) -> None:
        timer, self._baud_timer = self._baud_timer, None
        if timer is not None:
            timer.cancel()

    def handle_reset(self, msg: m.Reset, frame: Frame) -> None:
        """Answer OK, then reboot (the link drops)."""
        link = self.link
        assert link is not None
        self.log(f"reset requested{': ' + msg.reason if msg.reason else ''}")
        reply = m.Ok()
        self._remember(frame, reply)

        def reboot() -> None:
            self._reboot_requested = True
            self._end_session.set()

        link.send(reply, request_id=frame.request_id, after_sent=reboot)
        return None

    def handle_slot_set(self, msg: m.SlotSet, frame: Frame) -> m.Message:
        """ACTIVATE / CONFIRM / REVERT; answer SLOT_STATUS."""
        if msg.action == m.SlotAction.ACTIVATE:
            if msg.slot is None or msg.slot > 1:
                raise DeviceRefusal(m.ErrorCode.UNSUPPORTED, f"slot {msg.slot} does not exist "
                                    "(this device has slots 0 = A and 1 = B)")
            name = "AB"[msg.slot]
            was = self.store.active_slot
            self.store.set_active(name, force=msg.force)
            if was != name:
                self.log(f"slot {name} activated for a test boot")
                self._after_activation()
        elif msg.action == m.SlotAction.CONFIRM:
            self.store.confirm()
            self.log(f"slot {self.store.active_slot} confirmed by the host")
        else:
            self.store.revert(force=msg.force)
            self.log(f"reverted to slot {self.store.active_slot}")
        return m.SlotStatus(slots=self._slot_infos())

    def _after_activation(self) -> None:
        link = self.link
        if link is not None:
            link.defer(self.on_image_committed)
        else:
            self.on_image_committed()

    # ------------------------------------------------------------------ hooks
    def on_image_committed(self) -> None:
        """Called (on the dispatcher) after IMAGE_COMMIT or SLOT_SET ACTIVATE made a test image
        active. Issue 4: load, validate and confirm it. The issue-5 runtime overrides this to
        confirm once the first frame is shown."""
        self._load_and_confirm("commit")

    def handle_scores(self, msg: m.Scores, frame: Frame) -> None:
        """SCORES from the host: :meth:`on_scores`."""
        self.on_scores(msg)
        return None

    def on_scores(self, msg: m.Scores) -> None:
        """Hook for the runtime (issue 5): decode and show a score packet. Here: ignored."""

    def handle_keyframe_request(self, msg: m.KeyframeRequest, frame: Frame) -> None:
        """KEYFRAME_REQUEST is device -> host; :meth:`on_keyframe_request` may use it."""
        self.on_keyframe_request(msg)
        return None

    def on_keyframe_request(self, msg: m.KeyframeRequest) -> None:
        """Hook for the runtime (issue 5). Here: ignored."""

    def handle_unexpected(self, msg: m.Message, frame: Frame) -> None:
        """A host -> device message sent the wrong way: ignored (events) or refused (requests)."""
        if frame.kind == m.Kind.REQUEST:
            raise DeviceRefusal(m.ErrorCode.UNSUPPORTED, f"{msg.TYPE.name} is device -> host")
        return None

    def handle_notice(self, msg: m.Notice, frame: Frame) -> None:
        """A NOTICE from the host: logged."""
        self._log_limited("notice", f"host notice: {_one_line(msg.text, 256)}")
        return None

