"""Serving: answer a device's view requests with score packets (``eigencast serve``).

:func:`serve` connects to a device, says HELLO (and AUTH when the device holds a key),
checks that the device's active image is the model's (provisions it first with
``provision_missing``, else stops with one line telling the user to provision), then
streams one SCORES packet per view:

* **Which view.** Without an orbit, the device's VIEW_REQUESTs drive it; requests that
  arrive while a packet is still on its way are *coalesced* (only the newest is answered).
  With an orbit (:func:`device_runtime.runtime.parse_orbit`: ``turn:SECONDS[:THETA[:TURNS]]``
  or ``steps:N[:THETA[:TURNS]]``) the host drives the view itself, for unattended demos
  and benchmarks.
* **What is sent: one path.** A device that synthesizes its own frames (its image has the
  standalone table; HELLO_REPLY lists score packet version 3 and says it predicts) shows
  its own frame of every new view at once, and the host sends only the *correction* of
  that frame (`host.link.correction`): each new view is ray-cast sparsely within the
  frame's budget (`host.fit.MotionScores` with the device's own frames; the budget is
  `_Pace`'s: the deadline, ``1/fps`` or the link's measured time per packet, whichever is
  longest), and while it rests the next frames ray-cast the missing pixels until the
  correction is the full one at the model's score step. A correction with nothing worth
  sending is not sent. Any other device (an older one, one whose image has no table, one
  started with ``--no-predict``) gets the scores such a ray-cast recovers, as key and delta
  packets (one line says so), and a model whose volume cannot be ray-cast sends the
  training views' scores interpolated at the view (``HostModel.quantized_scores``, at the
  canonical view: bit-identical to ``eigencast view --blend``).
* **Which look.** An image with several looks is served in the look the device's requests
  name (`host.link.serve_looks`); each SCORES says the look it was made for.
* **A view that fails costs that view.** A view whose ray-cast (or coding) raises is sent as
  if it could not be ray-cast (the device keeps its own frame, or gets interpolated scores),
  counted (``ServeStats.failed_views``, said in one line), and the next one is corrected.
* **Deltas.** Each delta is coded against the last packet *sent* in this session (the
  writer hands a packet to the transport before the next one is encoded, so none is
  replaced unsent). A device that misses a base (a packet lost on a noisy line) sends
  KEYFRAME_REQUEST and gets a key frame; a new session (reconnect, device reboot) always
  starts with a key frame, and its frame numbers start at a random offset so a stale base
  from an earlier session can never match.
* **Pacing.** At most one packet waits in the link at a time (the next is encoded when the
  previous has left, so on a slow serial line views are coalesced instead of queued), and
  at most ``fps`` packets per second (0: as fast as the link carries them).
* **Link loss.** The host reconnects with exponential backoff (50 ms doubling to 2 s) and
  carries on with a key frame (a first connection that fails is an error instead: nothing
  to reconnect to; ``duration_s`` counts the time spent reconnecting); it logs frames sent,
  bytes per frame, the achieved frame rate and the link rate every few seconds.

The steps are the methods of ``_Serving``: a session is ``_open``, ``_handshake``,
``_holds_image`` (or provision and connect again), ``_begin``, ``_stream``, ``_end``, in
that order in ``_Serving._attempt``, with ``_back_off`` between sessions; each turn of
``_stream`` is ``_tick``, ``_may_send``, ``_choose`` (``_orbit_view``, ``_linger``,
``_resting`` or the newest request), ``_score`` and ``_send``. :func:`serve` only checks
its options, loads the model, picks the score sources and runs them. The device's events,
one session's connection and the port opener are `host.link.serve_link`.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from device_runtime.orbit import Orbit, OrbitSpec
from host.fit.model import HostModel
from host.link.encoding import FrameEncoder
from host.link.errors import ServeError
from host.link.layers import EncodedLayer
from host.link.options import (
    DEFAULT_DEADLINE_S,
    SCORE_MODES,
    ProvisionOptions,
    ProvisionParts,
    ServeOptions,
    ServeParts,
)
from host.link.serve_link import Connection as _Connection
from host.link.serve_link import DeviceEvents as _DeviceEvents
from host.link.serve_link import device_opener as _device_opener
from host.link.serve_looks import ServedLooks, served_looks
from host.link.serve_stats import ServeStats
from host.link.true_views import open_true_view_scores
from protocol import messages as m
from protocol.errors import (
    ProtocolError,
    RemoteBusy,
    RemoteError,
    TransportClosed,
    TransportError,
    TransportTimeout,
)
from protocol.host_session import HostSession
from protocol.link import Link
from protocol.scores import EncodedScores

__all__ = [
    "DEFAULT_DEADLINE_S",
    "SCORE_MODES",
    "FrameEncoder",
    "ServeError",
    "ServeOptions",
    "ServeParts",
    "ServeStats",
    "serve",
]

_BACKOFF_S = (0.05, 2.0)
#: Before any session: how many times a device that accepted the connection and then hung
#: up is tried again (a keyed device's lobby admits unauthenticated connections in turn and
#: may give a slow host's place to the next one; provision retries likewise).
_DOOR_TRIES = 4
_WAIT_S = 0.1
_LINGER_S = 0.5
"""After an orbit's last packet, key-frame requests are still answered until the device has
been quiet this long (a lost last delta would otherwise never be repaired), seconds."""
#: Bytes a SCORES frame adds to its packet (CBOR body, event counter and tag, frame header
#: and CRC), with room to spare: a layer's file is cut in chunks that fit the device's frames.
_SCORES_OVERHEAD = 96
#: Seconds of a serial line one chunk of a refinement layer may take at most.
_CHUNK_S = 0.25
_FAILURE_LOG_S = 10.0
"""A failed view is said at most this often (the statistics line counts them all), s."""


# --------------------------------------------------------------------------- serve


def serve(
    model_path: str | os.PathLike,
    url: str,
    options: ServeOptions | None = None,
    parts: ServeParts | None = None,
) -> ServeStats:
    """Serve score packets for ``model_path`` to the device at ``url``.

    Parameters
    ----------
    model_path : path-like
        The ``.ecs`` (with its host annex).
    url : str
        The device's port: ``socket://HOST:PORT``, ``/dev/ttyUSB0``, ``mem://...``.
    options : ServeOptions, optional
        What the user chose (key, orbit, frame rate, deadline, what a resting view
        becomes ...; default: ``ServeOptions()``), validated when it was built.
    parts : ServeParts, optional
        What the caller hands in to work with (a loaded model, a renderer, a sparse source,
        a transport factory, a stop event, where log lines go, a callback per packet).

    Returns
    -------
    ServeStats

    Raises
    ------
    ServeError
        The device holds another image (and ``options.provision_missing`` is off).
    RemoteError, AuthenticationError
        The device refused the session.
    TransportError
        The device cannot be reached or does not answer at the first connection.
    """
    from host.link.correction import CorrectionEncoder
    from host.link.provisioning import inspect_image

    o = options if options is not None else ServeOptions()
    p = parts if parts is not None else ServeParts()
    # the whole file is validated once, by HostModel.load (here or by the caller)
    info = inspect_image(model_path, key=o.key, whole_file=False)
    model = p.model or HostModel.load(model_path, key=o.key)
    say = p.log or (lambda line: print(f"eigencast serve: {line}", file=sys.stderr, flush=True))
    renderer = p.renderer
    if renderer is None and o.scores != "interpolate":
        renderer = _open_renderer(model, o.volume, o.scores, say)
    settings = _Settings(
        model_path=model_path, url=url, key=o.key, insecure=o.insecure, baud=o.baud,
        orbit=o.orbit, fps=o.fps, provision_missing=o.provision_missing, force=o.force,
        max_frames=o.max_frames, duration_s=o.duration_s, reconnect=o.reconnect,
        max_reconnects=o.max_reconnects, transport_factory=p.transport_factory,
        stats_every_s=o.stats_every_s, request_timeout_s=o.request_timeout_s,
        host_id=o.host_id,
    )
    run = _Serving(
        settings, info.digest,
        factory=p.transport_factory or _device_opener(url, o.baud, o.request_timeout_s, model),
        say=say,
        stop=p.stop or threading.Event(),
        encoder=CorrectionEncoder(model, keyframe_interval=o.keyframe_interval),
        pace=_Pace(o.deadline_s, o.fps), on_frame=p.on_frame, scores=o.scores,
        renderer=renderer,
        orbit=o.orbit.start() if o.orbit is not None else None,
        sources={} if p.motion is None else {
            "correct" if getattr(p.motion, "corrects", False) else "motion": p.motion},
        rest=o.rest,
        looks=served_looks(model, model_path, o.key, renderer, lambda m: None if o.scores == (
            "interpolate") else _open_renderer(m, o.volume, o.scores, say)),
    )
    return run.run()


def _open_renderer(model: HostModel, volume: str | None, scores: str,
                   say: Callable[[str], None]) -> Any | None:
    """The model's ray-caster; with ``scores="auto"`` None (one line says why) when its
    volume cannot be loaded, else that error."""
    from host.errors import EigencastError

    try:
        return open_true_view_scores(model, volume).renderer
    except EigencastError as exc:
        if scores != "auto":
            raise
        say(f"the views cannot be ray-cast ({_short(exc)}): devices that synthesize their "
            "own frames show them uncorrected, others get interpolated scores")
        return None


# --------------------------------------------------------------------------- the steps


@dataclass(frozen=True)
class _Settings:
    """The options of :func:`serve` that the steps read (see its parameters)."""

    model_path: str | os.PathLike
    url: str
    key: bytes | None
    insecure: bool
    baud: int
    orbit: OrbitSpec | None
    fps: float
    provision_missing: bool
    force: bool
    max_frames: int | None
    duration_s: float | None
    reconnect: bool
    max_reconnects: int | None
    transport_factory: Callable[[int], Any] | None
    stats_every_s: float
    request_timeout_s: float
    host_id: str


@dataclass
class _Frame:
    """The next packet: its view, the request sequence it answers, its scores (None: the
    model's interpolated ones; a correction in a correcting session), whether a key frame
    was asked for, whether it refines the view on show, whether it is a resting view's
    complete correction (``fine``: the model's own step) and the SSIM cell weights of its
    quantizer."""

    view: tuple[float, float]
    sequence: int
    scores: np.ndarray | None = None
    key: bool = False
    refined: bool = False
    fine: bool = False
    weights: np.ndarray | None = None
    sent: Any = None
    """A packet made already: the resting view's complete correction (`EncodedScores`),
    or one chunk of a refinement layer (`host.link.layers.EncodedLayer`)."""


@dataclass
class _Shown:
    """The view the device was last sent: its request sequence and the scores it was sent
    with (None: interpolated)."""

    view: tuple[float, float] | None = None
    sequence: int = 0
    scores: np.ndarray | None = None
    fine: bool = False
    requested_at: float = 0.0


@dataclass
class _Serving:
    """One run of :func:`serve`: its steps in order, and what carries over a reconnect.

    :meth:`run` repeats :meth:`_attempt` (open, handshake, check or provision the image,
    begin, stream, end) until serving is done, backing off between attempts after a lost
    link (:meth:`_back_off`). Each turn of :meth:`_stream` accounts the link (:meth:`_tick`),
    waits for the pacing (:meth:`_may_send`), chooses the next frame (:meth:`_choose`: a new
    request, the orbit, the linger, or the resting view's refinement), gives it its scores
    (:meth:`_score`) and sends it (:meth:`_send`). The encoder, the running orbit, the
    frame sources, the view on show and the statistics carry over sessions. Each session
    picks what it sends from the device's HELLO_REPLY (:meth:`_begin`: ``kind`` is
    ``"correct"``, ``"motion"`` or ``"interpolate"``); a view whose ray-cast fails is skipped
    and counted (:meth:`_view_failed`), and the next one is ray-cast as usual.
    """

    settings: _Settings
    digest: bytes
    factory: Callable[[int], Any]
    say: Callable[[str], None]
    stop: threading.Event
    encoder: FrameEncoder
    pace: _Pace
    on_frame: Callable[[EncodedScores, tuple[float, float]], None] | None
    scores: str
    renderer: Any | None
    orbit: Orbit | None
    stats: ServeStats = field(default_factory=ServeStats)
    last_stats: float = field(default_factory=time.monotonic)
    current: _Shown = field(default_factory=_Shown)
    kind: str = "interpolate"
    motion: Any | None = None
    sources: dict = field(default_factory=dict)
    link: Link | None = None
    attempt: int = 0
    failures: int = 0
    reached: bool = False
    """The latest attempt's transport opened (the device accepted the connection)."""
    warned_insecure: bool = False
    deadline: float | None = None
    """``duration_s`` after the first session began (monotonic): reconnecting counts."""
    streaming: bool = False
    rest: Any = "exact"
    """What a resting view gets after its correction: ``"exact"``, an object SSIM to stop
    at, or ``"correction"`` (no layers)."""
    resting: Any | None = None
    """The resting views' correction and layers (`host.link.resting.RestSender`; None: this
    session's device reads no layers, or ``rest`` asks for none)."""
    failed_view: tuple[float, float] | None = None  # its refinement is not tried again
    failure_said: float | None = None  # when a failed view was last said (monotonic)
    score_room: int = 1 << 30  # the device's frame less the SCORES message around a packet
    looks: ServedLooks | None = None  # an image with several looks
    look: int = 0  # the look the device shows (the one served)
    hello: m.HelloReply | None = None

    def run(self) -> ServeStats:
        """Serve sessions until done; reconnect after a lost link (or give up)."""
        try:
            while not self._done():
                self.link = None
                try:
                    if self._attempt():
                        break
                except (TransportClosed, TransportTimeout, TransportError, RemoteBusy) as exc:
                    if isinstance(exc, RemoteError) and not isinstance(exc, RemoteBusy):
                        raise
                    self.streaming = False
                    if self.link is not None:
                        with contextlib.suppress(Exception):
                            self.link.close(flush_timeout_s=0.0)
                        self.link = None
                    if self._done() or not self._back_off(exc):
                        break
                finally:
                    if self.link is not None:
                        with contextlib.suppress(Exception):
                            self.link.close(flush_timeout_s=0.5)
        finally:
            self.deadline = None  # ends the watchdog
            self.sources.clear()
            if self.looks is not None:
                self.looks.close()
            if self.resting is not None:
                self.resting.close()
        return self._finish()

    def _done(self) -> bool:
        if self.stop.is_set():
            return True
        settings, stats = self.settings, self.stats
        if settings.max_frames is not None and stats.frames >= settings.max_frames:
            return True
        return self.deadline is not None and time.monotonic() >= self.deadline

    def _watch_deadline(self) -> None:
        """``duration_s`` while reconnecting: at the deadline, cut a connection attempt that
        hangs (a device that accepts and never answers); a stream ends by itself."""
        while self.deadline is not None and not self.stop.is_set():
            left = self.deadline - time.monotonic()
            if left > 0:
                self.stop.wait(min(left, 0.5))
                continue
            link = self.link
            if link is not None and not self.streaming:
                with contextlib.suppress(Exception):
                    link.close(flush_timeout_s=0.0)
            return

    def _attempt(self) -> bool:
        """One session, start to BYE. False: the image was provisioned first (connect again)."""
        conn = self._open()
        hello = self._handshake(conn)
        if not self._holds_image(conn, hello):
            return False
        self._begin(conn, hello)
        self._stream(conn)
        self._end(conn)
        return True

    def _open(self) -> _Connection:
        """Open the transport and start the link engine and a host session on it."""
        self.reached = False
        transport = self.factory(self.attempt)
        self.reached = True
        self.attempt += 1
        events = _DeviceEvents(self.stats, self.say)
        self.link = Link(transport, handler=events, owns_transport=True).start()
        settings = self.settings
        session = HostSession(self.link, key=settings.key, host_id=settings.host_id,
                              request_timeout_s=settings.request_timeout_s,
                              insecure=settings.insecure)
        return _Connection(self.link, session, events)

    def _handshake(self, conn: _Connection) -> m.HelloReply:
        """HELLO, and AUTH when the device holds a key (warn once when it holds none)."""
        hello = conn.session.start()
        self.stats.device_id = hello.device_id
        unauthenticated = self.settings.key is not None and not conn.session.authenticated
        if unauthenticated and not self.warned_insecure:
            self.warned_insecure = True
            self.say(f"WARNING: --insecure: device '{hello.device_id}' holds no key; "
                     "serving it unauthenticated")
        return hello

    def _holds_image(self, conn: _Connection, hello: m.HelloReply) -> bool:
        """The device's active image is the model's; else provision it (``provision_missing``:
        False, the link is closed) or stop with one line."""
        from host.link.provisioning import provision

        held = _active_digest(hello)
        if held == self.digest:
            return True
        settings = self.settings
        model_path, url = settings.model_path, settings.url
        if not settings.provision_missing:
            raise ServeError(
                f"device '{hello.device_id}' does not hold {model_path} (active image: "
                f"{held.hex()[:16] + '...' if held else 'none'}); run eigencast "
                f"provision {model_path} --port {url} first, or pass --provision"
            )
        conn.session.bye("provisioning")
        conn.link.close(flush_timeout_s=0.5)
        self.link = None
        self.say(f"device '{hello.device_id}' lacks the image: provisioning it")
        provision(model_path, url,
                  ProvisionOptions(baud=settings.baud, key=settings.key,
                                   insecure=settings.insecure, force=settings.force),
                  ProvisionParts(log=self.say, transport_factory=settings.transport_factory))
        self.stats.provisioned = True
        return False

    def _begin(self, conn: _Connection, hello: m.HelloReply) -> None:
        """Count the session, pick what it sends (:meth:`_pick`), say so, start with a key
        frame."""
        stats, orbit = self.stats, self.settings.orbit
        stats.sessions += 1
        if stats.sessions > 1:
            stats.reconnects += 1
        self.failures = 0
        if self.deadline is None and self.settings.duration_s is not None:
            self.deadline = time.monotonic() + self.settings.duration_s
            threading.Thread(target=self._watch_deadline, daemon=True,
                             name="serve-deadline").start()
        self.streaming = True
        self.hello = hello
        what = self._pick(hello)
        self.say(f"serving {Path(self.settings.model_path).name} to device '{hello.device_id}' "
                 f"({'orbit ' + orbit.spec if orbit else 'view requests'}; "
                 f"{_display(hello)}; {what})")
        self.encoder.reset()
        conn.clock = time.monotonic()

    def _pick(self, hello: m.HelloReply) -> str:
        """This session's ``kind`` and frame source from the device's HELLO_REPLY: corrections
        of its own frames when it takes them (and the model has the table), else the sparse
        ray-cast's scores, else interpolated scores; returns the phrase the log says."""
        from host.link.correction import can_correct, cannot_correct

        model = self.encoder.model
        why = cannot_correct(hello) if can_correct(model) else (
            "cannot synthesize views of this model (fitted --no-standalone)")
        correct = self.scores == "auto" and why is None
        if correct:
            self.kind = "correct"
        elif self.renderer is not None and self.scores != "interpolate":
            self.kind = "motion"
        else:
            self.kind = "interpolate"
        self.encoder.enabled = correct
        self.motion = self._source(self.kind) if self.renderer is not None else None
        self.score_room = hello.max_frame_bytes - _SCORES_OVERHEAD
        planner = self._planner(hello) if correct and self.motion is not None else None
        if self.resting is not None:
            self.resting.close()
        self.resting = None
        if planner is not None:
            from host.link.resting import RestSender

            self.resting = RestSender(model, planner)
        if self.motion is not None:
            self.motion.budget_s = self.pace.budget_s
        if correct:
            return ("corrections of the device's own frames" if self.motion is not None
                    else "the device's own frames, uncorrected")
        if self.scores == "auto" and why is not None:
            self.say(f"device '{hello.device_id}' {why}: sending "
                     f"{'ray-cast' if self.kind == 'motion' else 'interpolated'} scores "
                     "instead of corrections of its own frames")
        return f"{'ray-cast' if self.kind == 'motion' else 'interpolated'} scores"

    def _planner(self, hello: m.HelloReply) -> Any | None:
        """The layers' planner of a session whose device reads them (score packet version
        4; 5 too: lossless layers of large frames in strips) and whose ``rest`` asks for
        any; None otherwise."""
        from host.link.layers import DEFAULT_TARGETS, RestPlanner
        from protocol.layers import LAYER_VERSION, STRIP_PIXELS, STRIP_VERSION

        rest = self.rest
        versions = hello.score_versions or ()
        if rest == "correction" or LAYER_VERSION not in versions:
            return None
        if rest == "exact":
            targets, exact = DEFAULT_TARGETS, True
        else:
            targets = (*(t for t in DEFAULT_TARGETS if t < float(rest)), float(rest))
            exact = False
        # the SCORES message around a packet: its CBOR body, the event tag and the frame
        room = hello.max_frame_bytes - _SCORES_OVERHEAD
        return RestPlanner(self.encoder.model.digest, targets=targets, exact=exact,
                           max_packet_bytes=max(min(room, self._link_share()), 256),
                           strip_pixels=STRIP_PIXELS if STRIP_VERSION in versions else None)

    def _link_share(self) -> int:
        """The bytes a serial line carries in `_CHUNK_S` (a chunk never holds a new view's
        correction back longer); TCP: no bound."""
        scheme = self.settings.url.split("://", 1)[0] if "://" in self.settings.url else ""
        if scheme in ("socket", "tcp"):
            return 1 << 30
        return int(self.settings.baud / 10 * _CHUNK_S)

    def _source(self, kind: str) -> Any | None:
        """The sparse ray-cast frame source of ``kind`` (made once, kept across sessions)."""
        if kind not in ("correct", "motion"):
            return None
        source = self.sources.get(kind)
        if source is None:
            from host.fit.motion import MotionScores

            own = None
            if kind == "correct":
                from device_runtime.prediction import OwnFrames

                own = OwnFrames(self.encoder.model.image)
            source = MotionScores(self.encoder.model, self.renderer, own=own)
            source.prepare()  # its factors now, not while the first views wait
            self.sources[kind] = source
        return source

    def _stream(self, conn: _Connection) -> None:
        """One packet per turn until done (or an orbit's linger is over)."""
        while not self._done():
            now = self._tick(conn)
            if not self._may_send(conn, now):
                continue
            request = conn.events.take()
            if self.looks is not None:
                self.looks.follow(self, conn.events.taken_look)
            self._check_sources()
            if conn.linger_until is not None and now >= conn.linger_until:
                break
            frame = self._framed(conn, request, now)
            if frame is None:
                continue
            self._send(conn, frame, now)

    def _framed(self, conn: _Connection, request: tuple[Any, int, bool, bool],
                now: float) -> _Frame | None:
        """`_choose` and `_score`; any exception of a frame source (a bug, whatever view
        the device asked for) ends serving in one line (ServeError) after a BYE, never a
        traceback. Link failures go on to the reconnect."""
        try:
            frame = self._choose(conn, request, now)
            if frame is not None:
                self._score(frame)
            return frame
        except (ProtocolError, ServeError):
            raise
        except Exception as exc:
            view = self.current.view if request[0] is None else request[0]
            where = f" at view ({view[0]:g}, {view[1]:g})" if view is not None else ""
            with contextlib.suppress(Exception):
                conn.session.bye("the host's frame source failed")
                conn.link.close(flush_timeout_s=0.5)
            source = {"correct": "correction", "motion": "ray-cast"}.get(self.kind,
                                                                         "interpolation")
            raise ServeError(f"the {source} frame source failed{where}: "
                             f"{type(exc).__name__}: {_short(exc)}; serving stopped") from None

    def _tick(self, conn: _Connection) -> float:
        """Add the time and wire bytes since the last turn; the statistics line when due."""
        now, stats, link = time.monotonic(), self.stats, conn.link
        stats.stream_seconds += now - conn.clock
        conn.clock = now
        stats.wire_bytes_sent += link.stats.bytes_sent - conn.bytes_sent
        stats.wire_bytes_received += link.stats.bytes_received - conn.bytes_received
        conn.bytes_sent, conn.bytes_received = link.stats.bytes_sent, link.stats.bytes_received
        if link.closed:
            raise TransportClosed(f"{self.settings.url}: link lost")
        every = self.settings.stats_every_s
        if every and now - self.last_stats >= every:
            self.last_stats = now
            self.say(stats.line())
        return now

    def _may_send(self, conn: _Connection, now: float) -> bool:
        """One packet in flight at most, and at most ``fps`` per second (else wait a bit)."""
        if not conn.sent.wait(_WAIT_S):
            return False
        if self.settings.fps > 0 and now < conn.next_due:
            self.stop.wait(min(conn.next_due - now, _WAIT_S))
            return False
        return True

    def _check_sources(self) -> None:
        """The sparse source's budget follows the pace."""
        if self.motion is not None:
            self.motion.budget_s = self.pace.budget_s

    def _view_failed(self, view: tuple[float, float] | None, error: BaseException) -> None:
        """One view's ray-cast (or coding) raised: count it, say so (the first time, then
        at most every `_FAILURE_LOG_S`), and go on; that view is sent as if it could not
        be ray-cast and is not refined again."""
        self.stats.failed_views += 1
        self.failed_view = view
        now = time.monotonic()
        if self.failure_said is not None and now - self.failure_said < _FAILURE_LOG_S:
            return
        self.failure_said = now
        where = f" of view ({view[0]:g}, {view[1]:g})" if view is not None else ""
        shown = ("the device shows its own frame of it uncorrected" if self.kind == "correct"
                 else "it gets interpolated scores")
        n = self.stats.failed_views
        self.say(f"ray-casting failed{where} ({type(error).__name__}: {_short(error)}); "
                 f"{shown}, serving goes on ({n} failed view{'s' if n != 1 else ''} so far)")

    def _choose(self, conn: _Connection, request: tuple[Any, int, bool, bool],
                now: float) -> _Frame | None:
        """The next frame: the orbit's next view, a key frame while lingering, the resting
        view refined (or repeated as a key frame), or the newest request. None: nothing to
        send this turn."""
        view, sequence, fresh, want_key = request
        if fresh and self.resting is not None:
            self.resting.cancel()  # a new view: the resting view's plan and layers are moot
        if self.orbit is not None and conn.linger_until is None:
            frame = self._orbit_view(conn, want_key, now)
        elif conn.linger_until is not None:
            frame = self._linger(conn, want_key, now)
        elif not fresh:
            frame = self._resting(conn, want_key, now)
        else:
            frame = _Frame(view, sequence, key=want_key)
        if frame is not None and fresh:
            self.current.requested_at = now
        return frame

    def _orbit_view(self, conn: _Connection, want_key: bool, now: float) -> _Frame | None:
        """The host-driven view; at the orbit's end, start lingering."""
        assert self.orbit is not None
        view = self.orbit.next_view(now)
        if view is None:  # done: still answer key-frame requests a moment
            conn.linger_until = now + _LINGER_S
            self.say("orbit done")
            return None
        return _Frame(view, 0, key=want_key)

    def _linger(self, conn: _Connection, want_key: bool, now: float) -> _Frame | None:
        """After the orbit: the last view again as a key frame when the device asks for one."""
        shown = self.current
        if not want_key or shown.view is None:
            conn.events.wait(_WAIT_S)
            return None
        assert conn.linger_until is not None
        conn.linger_until = max(conn.linger_until, now + _LINGER_S)
        return _Frame(shown.view, shown.sequence, shown.scores, key=True)

    def _resting(self, conn: _Connection, want_key: bool, now: float) -> _Frame | None:
        """No new request: the view on show refined (a denser sparse frame, up to its full
        ray-cast), or repeated as a key frame; else wait."""
        shown = self.current
        if self.resting is not None and self.resting.pending and not want_key:
            return self._rest_packet(conn, shown)
        step = None
        if (self.motion is not None and shown.view is not None and not want_key
                and shown.view != self.failed_view):
            step = self._sparse(self.motion.refine, shown.view)
        if step is not None:
            if step.scores is None:  # more pixels, nothing new to show yet
                return None
            if self.resting is not None and not step.complete:
                return None  # layers follow: what is sent waits for the whole ray-cast
            self.stats.converged_frames += int(step.complete)
            frame = _Frame(shown.view, shown.sequence, step.scores, want_key, refined=True,
                           fine=step.complete, weights=step.weights)
            if step.complete and self.resting is not None:
                return self._plan_rest(frame)
            return frame
        if want_key and shown.view is not None:
            return _Frame(shown.view, shown.sequence, shown.scores, key=True, fine=shown.fine)
        conn.events.wait(_WAIT_S)
        return None

    def _plan_rest(self, frame: _Frame) -> _Frame | None:
        """The resting view's full ray-cast is done: code its complete correction and plan
        its layers on the planning thread (`host.link.resting`); nothing is sent until the
        plan says what. A correction that cannot be coded is sent as `_encode` made it."""
        assert self.motion is not None and self.resting is not None
        encoded = self._encode(frame)
        images = self.motion.rest_images(frame.view)
        if images is None or frame.scores is None:
            frame.sent = encoded
            return frame if encoded is not None else None
        self.current.scores, self.current.fine = frame.scores, True
        if encoded is not None and len(encoded.packet) > self.score_room:
            self._oversize(encoded)  # the layers (chunked) refine the own frame instead
            encoded = None
        self.resting.start(frame.view, *images, encoded, self.motion.own)
        return None

    def _rest_packet(self, conn: _Connection, shown: _Shown) -> _Frame | None:
        """The resting view's next packet once its plan is ready (the correction, or a
        chunk numbered by the session's counter), else a short wait."""
        assert self.resting is not None
        encoder = self.encoder
        number = encoder.next_frame if encoder.next_frame <= 0xFFFFFFFF else 1
        try:
            packet = self.resting.next(number)
        except Exception as exc:  # a plan that failed costs that view's layers only
            self._view_failed(shown.view, exc)
            self.resting.cancel()
            return None
        if packet is None:
            conn.events.wait(_WAIT_S)
            return None
        if isinstance(packet, EncodedLayer):
            encoder.next_frame = number + 1
        return _Frame(shown.view, shown.sequence, shown.scores, refined=True, fine=True,
                      sent=packet)

    def _sparse(self, call: Callable[[tuple[float, float]], Any],
                view: tuple[float, float]) -> Any | None:
        """``call(view)`` of the sparse source, its rays and time counted; None when it
        failed (that view is skipped: :meth:`_view_failed`) or had nothing to do
        (``refine`` of a view already fully ray-cast, or no longer the last frame's)."""
        try:
            step = call(view)
        except Exception as exc:
            self._view_failed(view, exc)
            return None
        if step is None:
            return None
        self.stats.motion_pixels += step.pixels
        self.stats.motion_seconds += step.seconds
        return step

    def _score(self, frame: _Frame) -> None:
        """Scores for a frame that carries none: a sparse ray-cast's (its correction in a
        correcting session); interpolated otherwise (left None)."""
        if frame.scores is not None or frame.sent is not None or self.motion is None:
            return
        stats = self.stats
        step = self._sparse(self.motion.frame, frame.view)
        if step is not None:
            self.failed_view = None
            frame.scores, frame.weights, frame.fine = step.scores, step.weights, step.complete
            stats.motion_frames += 1
            stride = str(step.stride)
            stats.stride_frames[stride] = stats.stride_frames.get(stride, 0) + 1

    def _send(self, conn: _Connection, frame: _Frame, now: float) -> None:
        """Encode the frame (key, delta or correction), hand it to the link, count it. A
        correction with nothing worth sending is not sent (the device keeps its own frame),
        except for a host-driven view, which the device must be told (an empty one)."""
        shown = self.current
        layer = isinstance(frame.sent, EncodedLayer)
        if not layer:
            shown.view, shown.sequence, shown.scores = frame.view, frame.sequence, frame.scores
            shown.fine = frame.fine
        encoded = frame.sent if frame.sent is not None else self._encode(frame)
        fps = self.settings.fps
        if encoded is None:
            self.stats.unchanged_frames += 1
            return
        if (not layer and self.encoder.last_kind == "correction"
                and len(encoded.packet) > self.score_room):
            self._oversize(encoded)  # costs this view: the device keeps its own frame
            return
        sent = conn.sent
        sent.clear()
        queued = time.monotonic()

        def left() -> None:
            self.pace.left(time.monotonic() - queued)
            sent.set()

        try:
            look = self.look if self.looks is not None else None
            conn.session.send_scores(m.Scores(sequence=frame.sequence, packet=encoded.packet,
                                              look=look), after_sent=left)
        except ValueError as exc:  # the packet does not fit the device's frames
            kind = self.encoder.last_kind
            raise ServeError(
                f"{' '.join(str(exc).split())}: a {kind} score packet of this model "
                f"({len(encoded.packet)} bytes) does not fit the device's frames; "
                "start eigencast-device with a larger --max-frame (e.g. --max-frame "
                "65536)") from None
        conn.next_due = now + (1.0 / fps if fps > 0 else 0.0)
        self._count(encoded, frame)
        if self.on_frame is not None:
            self.on_frame(encoded, frame.view)

    def _oversize(self, encoded: EncodedScores) -> None:
        """A correction larger than the device's frames is not sent: counted, and said once
        per session (the device shows its own frame of that view; at rest the layers, which
        are chunked to fit, take it to the exact frame all the same)."""
        self.stats.oversize_corrections += 1
        if self.stats.oversize_corrections == 1:
            self.say(f"a correction of {len(encoded.packet)} bytes does not fit the device's "
                     f"frames ({self.score_room} bytes of scores): such views keep the "
                     "device's own frame until their layers come (eigencast-device "
                     "--max-frame 65536 takes them)")

    def _encode(self, frame: _Frame) -> EncodedScores | None:
        """The frame's packet; scores that cannot be coded cost the view (`_view_failed`)."""
        always = self.orbit is not None
        if frame.scores is not None:
            try:
                return self.encoder.encode(frame.view, key=frame.key, scores=frame.scores,
                                           fine=frame.fine, weights=frame.weights,
                                           always=always)
            except Exception as exc:
                self._view_failed(frame.view, exc)
                frame.scores, frame.weights, frame.fine = None, None, False
                self.current.scores, self.current.fine = None, False
        return self.encoder.encode(frame.view, key=frame.key, always=always)

    def _count(self, encoded: EncodedScores | EncodedLayer, frame: _Frame) -> None:
        stats, size = self.stats, len(encoded.packet)
        stats.frames += 1
        stats.packet_bytes += size
        if isinstance(encoded, EncodedLayer):
            stats.layer_frames += 1
            stats.layer_bytes += size
            stats.exact_views += int(encoded.exact and encoded.last)
        elif self.encoder.last_kind == "correction":
            stats.correction_frames += 1
            stats.correction_bytes += size
        elif self.encoder.last_was_key:
            stats.key_frames += 1
            stats.key_bytes += size
        else:
            stats.delta_frames += 1
            stats.delta_bytes += size
        stats.last_view = frame.view
        if frame.refined:
            stats.refined_frames += 1

    def _end(self, conn: _Connection) -> None:
        """Finished: let the last packet leave, say goodbye, close the link."""
        conn.sent.wait(2.0)
        conn.link.wait_writer_idle(2.0)
        conn.session.bye("done")
        conn.link.close(flush_timeout_s=1.0)
        self.link = None
        self.streaming = False

    def _back_off(self, exc: BaseException) -> bool:
        """After a lost link: wait (exponential backoff, never past the ``duration_s``
        deadline) and reconnect (True), or stop (False).

        Raises ``exc`` again when no session ever started: reconnecting is for a link that
        was up (a device that is not there, or does not answer, is one line for the user);
        except that a device that accepted the connection and hung up before the session
        began is tried again up to `_DOOR_TRIES` times (a keyed device's lobby may have
        given the place to another connection)."""
        self.failures += 1
        settings = self.settings
        at_door = self.stats.sessions == 0 and not self.stats.provisioned
        if at_door and not (self.reached and isinstance(exc, TransportClosed)
                            and self.failures <= _DOOR_TRIES):
            raise exc
        if not at_door and (not settings.reconnect or (
                settings.max_reconnects is not None
                and self.failures > settings.max_reconnects)):
            self.say(f"link lost ({_short(exc)}); not reconnecting")
            return False
        delay = min(_BACKOFF_S[0] * 2 ** (self.failures - 1), _BACKOFF_S[1])
        if self.deadline is not None:
            delay = min(delay, max(0.0, self.deadline - time.monotonic()))
        if at_door:
            self.say(f"the device hung up before the session began ({_short(exc)}); "
                     f"trying again in {delay:.2f} s")
        else:
            self.say(f"link lost ({_short(exc)}); reconnecting in {delay:.2f} s")
        self.stop.wait(delay)  # reconnect backoff (a protocol timer)
        return True

    def _finish(self) -> ServeStats:
        """The closing line."""
        self.say(f"done: {self.stats.line()}")
        return self.stats


class _Pace:
    """The ``motion`` frame budget: the deadline, or longer when ``fps`` or the link (its
    measured seconds per packet, an exponential average) cannot carry frames that often."""

    def __init__(self, deadline_s: float, fps: float) -> None:
        self.floor = max(deadline_s, 1.0 / fps if fps > 0 else 0.0)
        self.link_s = 0.0

    def left(self, seconds: float) -> None:
        self.link_s = seconds if self.link_s == 0.0 else 0.7 * self.link_s + 0.3 * seconds

    @property
    def budget_s(self) -> float:
        return max(self.floor, self.link_s)


def _active_digest(hello: m.HelloReply) -> bytes | None:
    for slot in hello.slots:
        if slot.active and slot.state in (m.SlotState.TEST, m.SlotState.CONFIRMED):
            return bytes(slot.digest)
    return None


def _display(hello: m.HelloReply) -> str:
    """The device's display as its HELLO_REPLY says (0x0: a headless device)."""
    if not hello.display_width or not hello.display_height:
        return "headless"
    return f"{hello.display_width}x{hello.display_height} display"


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 120 else text[:117] + "..."
