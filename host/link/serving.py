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
* **What is sent.** ``HostModel.quantized_scores`` at the canonical view (phi wrapped to
  [0, 360), both angles rounded to float32: exactly what the packet header carries),
  quantized at the model's score step, coded as a key or delta packet, zstd-compressed
  (`protocol.scores.encode_scores`). The device's frame is therefore bit-identical to
  ``eigencast view`` at the same view. Other ``scores`` modes send other scores through the
  same encoder: a fresh ray-cast's projection (``render``, ``refine`` at rest) or the scores
  recovered from a sparse ray-cast that fits the frame budget (``motion``,
  `host.fit.MotionScores`; the budget is `_Pace`'s: the deadline, ``1/fps`` or the link's
  measured time per packet, whichever is longest).
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
  carries on with a key frame; it logs frames sent, bytes per frame, the achieved frame
  rate and the link rate every few seconds.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from device_runtime.runtime import OrbitSpec, canonical_view
from host.fit.model import HostModel
from host.link.errors import ServeError
from host.link.true_views import TrueViewScores, _Refiner, open_true_view_scores
from protocol import messages as m
from protocol.errors import (
    RemoteError,
    TransportClosed,
    TransportError,
    TransportTimeout,
)
from protocol.link import HostSession, Link
from protocol.scores import DEFAULT_LEVEL as SCORE_LEVEL
from protocol.scores import EncodedScores, encode_scores, max_packet_size
from protocol.transport import open_transport

__all__ = [
    "FrameEncoder",
    "ServeError",
    "ServeStats",
    "serve",
]

_BACKOFF_S = (0.05, 2.0)
_WAIT_S = 0.1
_LINGER_S = 0.5
"""After an orbit's last packet, key-frame requests are still answered until the device has
been quiet this long (a lost last delta would otherwise never be repaired), seconds."""


# --------------------------------------------------------------------------- stats


@dataclass
class ServeStats:
    """What :func:`serve` did (all sessions).

    Attributes
    ----------
    frames, key_frames, delta_frames : int
        Score packets sent.
    packet_bytes, key_bytes, delta_bytes : int
        Their sizes (score packets, before framing).
    wire_bytes : int
        Bytes the links wrote (all frames, framing included) and read.
    requests, coalesced, keyframe_requests : int
        VIEW_REQUESTs received, those superseded before they were answered, KEYFRAME_REQUESTs.
    rendered_frames, refined_frames : int
        Packets of ray-cast views (``scores="render"``), refinement packets (``"refine"``).
    rendered_views, render_seconds : int, float
        Views ray-cast and projected, and the time it took.
    motion_frames, motion_pixels, motion_seconds : int, int, float
        ``scores="motion"``: packets of moving views (sparse ray-casts), rays cast for them
        and their refinements, and the host time it took.
    converged_frames : int
        ``"motion"``: refinements that reached the full projection of a resting view.
    stride_frames : dict
        ``"motion"``: moving frames per stride (str keys).
    sessions, reconnects : int
    stream_seconds : float
        Time spent streaming (sessions, not connecting).
    device_id : str
    provisioned : bool
        The image was installed first (``provision_missing``).
    """

    frames: int = 0
    key_frames: int = 0
    delta_frames: int = 0
    packet_bytes: int = 0
    key_bytes: int = 0
    delta_bytes: int = 0
    wire_bytes_sent: int = 0
    wire_bytes_received: int = 0
    requests: int = 0
    coalesced: int = 0
    keyframe_requests: int = 0
    sessions: int = 0
    reconnects: int = 0
    stream_seconds: float = 0.0
    device_id: str = ""
    provisioned: bool = False
    last_view: tuple[float, float] | None = None
    rendered_frames: int = 0
    refined_frames: int = 0
    rendered_views: int = 0
    render_seconds: float = 0.0
    motion_frames: int = 0
    motion_pixels: int = 0
    motion_seconds: float = 0.0
    converged_frames: int = 0
    stride_frames: dict = field(default_factory=dict)
    views: list = field(default_factory=list, repr=False)

    @property
    def bytes_per_frame(self) -> float:
        """Mean score-packet size, bytes."""
        return self.packet_bytes / self.frames if self.frames else 0.0

    @property
    def fps(self) -> float:
        """Frames sent per second of streaming."""
        return self.frames / self.stream_seconds if self.stream_seconds > 0 else 0.0

    @property
    def link_bytes_per_s(self) -> float:
        """Wire bytes sent per second of streaming."""
        return self.wire_bytes_sent / self.stream_seconds if self.stream_seconds > 0 else 0.0

    def as_dict(self) -> dict[str, Any]:
        """JSON-able summary."""
        out = {k: v for k, v in self.__dict__.items() if k != "views"}
        out["last_view"] = list(self.last_view) if self.last_view else None
        out.update(bytes_per_frame=self.bytes_per_frame, fps=self.fps,
                   link_bytes_per_s=self.link_bytes_per_s,
                   mean_key_bytes=self.key_bytes / self.key_frames if self.key_frames else 0.0,
                   mean_delta_bytes=(self.delta_bytes / self.delta_frames
                                     if self.delta_frames else 0.0))
        return out

    def line(self) -> str:
        """One human line: frames, bytes per frame (key / delta), fps, link rate."""
        key = self.key_bytes / self.key_frames if self.key_frames else 0.0
        delta = self.delta_bytes / self.delta_frames if self.delta_frames else 0.0
        kinds = f"{self.key_frames} key, {self.delta_frames} delta"
        if self.rendered_frames:
            kinds += f", {self.rendered_frames} ray-cast"
        if self.motion_frames:
            kinds += f", {self.motion_frames} sparse"
        if self.refined_frames:
            kinds += f", {self.refined_frames} refined"
        return (f"{self.frames} frames ({kinds}), "
                f"{self.bytes_per_frame:.0f} B/frame (key {key:.0f} B, delta {delta:.0f} B), "
                f"{self.fps:.1f} fps, link {self.link_bytes_per_s / 1024:.1f} KiB/s")


# --------------------------------------------------------------------------- encoding


class FrameEncoder:
    """Score packets of one session: frame numbers, key/delta choice, the delta base.

    Parameters
    ----------
    model : HostModel
    keyframe_interval : int
        0: deltas whenever possible (key frames only at the start and when asked);
        1: key frames only; N: at least one key frame every N frames.
    level : int
        zstd level of the packet payload.
    first_frame : int, optional
        Frame number of the first packet (default: random in 1..2**31).
    """

    def __init__(self, model: HostModel, *, keyframe_interval: int = 0,
                 level: int = SCORE_LEVEL, first_frame: int | None = None) -> None:
        if keyframe_interval < 0:
            raise ValueError(f"keyframe_interval={keyframe_interval} must be >= 0")
        self.model = model
        self.keyframe_interval = keyframe_interval
        self.level = level
        self.next_frame = first_frame if first_frame is not None else (
            1 + secrets.randbelow(1 << 31))
        self.base: EncodedScores | None = None
        self.last_was_key = False
        self._since_key = 0

    def reset(self) -> None:
        """Forget the base: the next packet is a key frame."""
        self.base = None

    def encode(self, view: tuple[float, float], *, key: bool = False,
               scores: np.ndarray | None = None) -> EncodedScores:
        """The packet for ``view`` (canonical), as a delta against the last one unless
        ``key``, the interval or a wrap of the frame number asks for a key frame.

        ``scores`` (float (K,)): send these (e.g. `HostModel.project` of a fresh ray-cast)
        instead of the model's interpolated scores at ``view``; quantized the same way."""
        frame = self.next_frame
        if frame > 0xFFFFFFFF:
            frame = 1
            self.base = None
        self.next_frame = frame + 1
        interval = self.keyframe_interval
        if interval == 1 or (interval > 1 and self._since_key + 1 >= interval):
            key = True
        model = self.model
        y = model.quantized_scores(*view) if scores is None else model.quantize(scores)
        base = None if key else self.base
        encoded = encode_scores(
            y, step=model.score_step, frame=frame, view=view, image_digest=model.digest,
            base=base, level=self.level, n_components=model.image.n_components,
        )
        self.last_was_key = base is None
        self._since_key = 0 if base is None else self._since_key + 1
        self.base = encoded
        return encoded


# --------------------------------------------------------------------------- score modes

#: What ``serve`` streams: interpolated training scores, the scores of a fresh ray-cast of
#: every view, interpolated scores at once and the ray-cast's when the view rests, or the
#: scores of a sparse ray-cast that fits each frame's deadline (`host.fit.motion`).
SCORE_MODES = ("interpolate", "render", "refine", "motion")
#: ``motion``: the frame deadline when ``fps`` sets none (a frame rate of 30), seconds.
DEFAULT_DEADLINE_S = 1.0 / 30.0
#: ``refine``: how long a view must rest (no newer request) before it is ray-cast, seconds.
DEFAULT_REFINE_DELAY_S = 0.15


# --------------------------------------------------------------------------- events


class _DeviceEvents:
    """The host link's handler: newest VIEW_REQUEST, KEYFRAME_REQUESTs, NOTICEs."""

    def __init__(self, stats: ServeStats, say: Callable[[str], None]) -> None:
        self._cond = threading.Condition()
        self.view: tuple[float, float] | None = None
        self.sequence = 0
        self.fresh = False
        self.keyframe = False
        self.poked = False
        self.stats = stats
        self.say = say

    def __call__(self, msg: m.Message, frame: Any) -> None:
        with self._cond:
            if isinstance(msg, m.ViewRequest):
                self.stats.requests += 1
                if self.fresh:
                    self.stats.coalesced += 1
                self.view = canonical_view(msg.phi_deg, msg.theta_deg)
                self.sequence = msg.sequence
                self.fresh = True
            elif isinstance(msg, m.KeyframeRequest):
                self.stats.keyframe_requests += 1
                self.keyframe = True
            elif isinstance(msg, m.Notice):
                self.say(f"device: {msg.text}")
            self._cond.notify_all()
        return None

    def wait(self, timeout_s: float) -> None:
        with self._cond:
            if not (self.fresh or self.keyframe or self.poked):
                self._cond.wait(timeout_s)
            self.poked = False

    def poke(self) -> None:
        """Wake `wait` (a refined view is ready)."""
        with self._cond:
            self.poked = True
            self._cond.notify_all()

    def take(self) -> tuple[tuple[float, float] | None, int, bool, bool]:
        """(view, sequence, fresh, keyframe wanted) and clear the flags."""
        with self._cond:
            out = (self.view, self.sequence, self.fresh, self.keyframe)
            self.fresh = False
            self.keyframe = False
            return out


# --------------------------------------------------------------------------- serve


@dataclass
class _Shown:
    """The view the device was last sent: its request sequence, the ray-cast scores it was
    sent with (None: interpolated) and when it was requested (monotonic seconds)."""

    view: tuple[float, float] | None = None
    sequence: int = 0
    scores: np.ndarray | None = None
    requested_at: float = 0.0


def _active_digest(hello: m.HelloReply) -> bytes | None:
    for slot in hello.slots:
        if slot.active and slot.state in (m.SlotState.TEST, m.SlotState.CONFIRMED):
            return bytes(slot.digest)
    return None


def serve(
    model_path: str | os.PathLike,
    url: str,
    *,
    key: bytes | None = None,
    insecure: bool = False,
    baud: int = 115200,
    orbit: OrbitSpec | None = None,
    fps: float = 60.0,
    keyframe_interval: int = 0,
    provision_missing: bool = False,
    max_frames: int | None = None,
    duration_s: float | None = None,
    reconnect: bool = True,
    max_reconnects: int | None = None,
    stop: threading.Event | None = None,
    transport_factory: Callable[[int], Any] | None = None,
    log: Callable[[str], None] | None = None,
    stats_every_s: float = 5.0,
    request_timeout_s: float = 1.0,
    model: HostModel | None = None,
    on_frame: Callable[[EncodedScores, tuple[float, float]], None] | None = None,
    host_id: str = "eigencast serve",
    scores: str = "interpolate",
    true_views: TrueViewScores | None = None,
    refine_delay_s: float = DEFAULT_REFINE_DELAY_S,
    motion: Any | None = None,
    deadline_s: float = DEFAULT_DEADLINE_S,
) -> ServeStats:
    """Serve score packets for ``model_path`` to the device at ``url``.

    Parameters
    ----------
    model_path : path-like
        The ``.ecs`` (with its host annex).
    url : str
        The device's port: ``socket://HOST:PORT``, ``/dev/ttyUSB0``, ``mem://...``.
    key : bytes, optional
        Device key (needed when the device holds one; also verifies the image's tag).
    insecure : bool
        With ``key``: serve a device that says it holds no key anyway (unauthenticated; said
        once through ``log``). Without it such a device is refused (AuthenticationError).
    baud : int
        Serial line rate.
    orbit : OrbitSpec, optional
        Drive the view from the host (VIEW_REQUESTs are then only counted).
    fps : float
        Packets per second at most (0: as fast as the link carries them).
    keyframe_interval : int
        See :class:`FrameEncoder` (1: key frames only).
    provision_missing : bool
        Install the image first when the device's active image is another one.
    max_frames, duration_s : optional
        Stop after this many packets / seconds of streaming.
    reconnect : bool
        Reconnect after a lost link (with backoff); False: return.
    max_reconnects : int, optional
        Give up after this many failed connection attempts in a row (default: never).
    stop : threading.Event, optional
        Set it to end serving (the session ends with BYE).
    transport_factory : callable, optional
        ``factory(attempt) -> Transport`` instead of ``open_transport(url, baud=baud)``.
    log : callable, optional
        One line per event (default: stderr).
    stats_every_s : float
        Period of the statistics line (0: none).
    model : HostModel, optional
        Already loaded from ``model_path``.
    on_frame : callable, optional
        ``on_frame(encoded, view)`` after each packet is queued.
    scores : {"interpolate", "render", "refine", "motion"}
        What the packets carry. ``"interpolate"``: the training views' scores interpolated
        at the view (instant; the frame shows the blend of neighbouring views).
        ``"render"``: the scores of a fresh ray-cast of every view (`TrueViewScores`: the
        eigenspace's best frame of the true view; one ray-cast per packet, requests that
        arrive meanwhile are coalesced). ``"refine"``: interpolated at once, then, once the
        view has rested ``refine_delay_s`` with no newer request, the ray-cast's scores as
        one more (delta) packet. Orbits are host-driven and never rest: ``refine`` sends
        their views interpolated. ``"motion"``: the scores of a sparse ray-cast as dense as
        the frame's budget allows (`host.fit.motion.MotionScores`) for every new view, orbits
        included, then, while the view rests, denser frames until the full projection.
    true_views : TrueViewScores, optional
        The ray-caster for ``render``/``refine`` (default: `open_true_view_scores` with the
        model's recorded volume).
    refine_delay_s : float
        ``refine``: how long a view must rest before it is ray-cast.
    motion : host.fit.motion.MotionScores, optional
        The source for ``motion`` (default: built on ``true_views``' renderer).
    deadline_s : float
        ``motion``: the frame budget, seconds; ``fps`` and the link's measured time per
        packet lengthen it when they are slower.

    Returns
    -------
    ServeStats

    Raises
    ------
    ServeError
        The device holds another image (and ``provision_missing`` is off).
    RemoteError, AuthenticationError
        The device refused the session.
    TransportError
        The device cannot be reached (``reconnect`` off, or ``max_reconnects`` exceeded).
    """
    from host.link.provisioning import inspect_image, provision

    say = log or (lambda line: print(f"eigencast serve: {line}", file=sys.stderr, flush=True))
    stop = stop or threading.Event()
    if fps < 0:
        raise ValueError(f"fps={fps} must be >= 0")
    if scores not in SCORE_MODES:
        raise ValueError(f"scores={scores!r}: expected one of {', '.join(SCORE_MODES)}")
    if refine_delay_s < 0:
        raise ValueError(f"refine_delay_s={refine_delay_s} must be >= 0")
    if not deadline_s > 0:
        raise ValueError(f"deadline_s={deadline_s} must be > 0")
    # the whole file is validated once, by HostModel.load (here or by the caller)
    info = inspect_image(model_path, key=key, whole_file=False)
    model = model or HostModel.load(model_path, key=key)
    if scores != "interpolate" and true_views is None and (scores != "motion" or motion is None):
        true_views = open_true_view_scores(model)
    if scores == "motion" and motion is None:
        from host.fit.motion import MotionScores

        motion = MotionScores(model, true_views.renderer)
    pace = _Pace(deadline_s, fps)
    if motion is not None:
        motion.budget_s = pace.budget_s
    # this end sends frames as large as the model's largest score packet; the device's own
    # limit (HELLO's max_frame_bytes, eigencast-device --max-frame) is the one that binds
    k, n_cells = model.image.n_coefficients, model.image.n_cells
    frame_limit = max(16384, max_packet_size(k, max(k, n_cells), n_cells=n_cells) + 256)
    factory = transport_factory or (
        lambda attempt: open_transport(url, baud=baud, timeout_s=max(5.0, request_timeout_s),
                                       max_frame_bytes=frame_limit))
    stats = ServeStats()
    encoder = FrameEncoder(model, keyframe_interval=keyframe_interval)
    running_orbit = orbit.start() if orbit is not None else None
    started = time.monotonic()
    last_stats = [started]
    failures = 0
    attempt = 0
    current = _Shown()
    refiner: _Refiner | None = None
    warned_insecure = False

    def done() -> bool:
        if stop.is_set():
            return True
        if max_frames is not None and stats.frames >= max_frames:
            return True
        return duration_s is not None and stats.stream_seconds >= duration_s

    try:
        while not done():
            link: Link | None = None
            try:
                transport = factory(attempt)
                attempt += 1
                events = _DeviceEvents(stats, say)
                link = Link(transport, handler=events, owns_transport=True).start()
                session = HostSession(link, key=key, host_id=host_id,
                                      request_timeout_s=request_timeout_s, insecure=insecure)
                hello = session.start()
                stats.device_id = hello.device_id
                if key is not None and not session.authenticated and not warned_insecure:
                    warned_insecure = True
                    say(f"WARNING: --insecure: device '{hello.device_id}' holds no key; "
                        "serving it unauthenticated")
                if _active_digest(hello) != info.digest:
                    if not provision_missing:
                        held = _active_digest(hello)
                        raise ServeError(
                            f"device '{hello.device_id}' does not hold {model_path} (active image: "
                            f"{held.hex()[:16] + '...' if held else 'none'}); run eigencast "
                            f"provision {model_path} --port {url} first, or pass --provision"
                        )
                    session.bye("provisioning")
                    link.close(flush_timeout_s=0.5)
                    link = None
                    say(f"device '{hello.device_id}' lacks the image: provisioning it")
                    provision(model_path, url, baud=baud, key=key, insecure=insecure, log=say,
                              transport_factory=transport_factory)
                    stats.provisioned = True
                    continue
                stats.sessions += 1
                if stats.sessions > 1:
                    stats.reconnects += 1
                failures = 0
                say(f"serving {Path(model_path).name} to device '{hello.device_id}' "
                    f"({'orbit ' + orbit.spec if orbit else 'view requests'}; "
                    f"{hello.display_width}x{hello.display_height} display; {scores} scores)")
                encoder.reset()
                if scores == "refine" and refiner is None and true_views is not None:
                    refiner = _Refiner(true_views, events.poke)
                elif refiner is not None:  # one refiner for all sessions: wake this one's
                    refiner.notify = events.poke
                sent = threading.Event()
                sent.set()
                session_start = time.monotonic()
                base_sent, base_recv = 0, 0
                next_due = 0.0
                linger_until: float | None = None
                while not done():
                    now = time.monotonic()
                    stats.stream_seconds += now - session_start
                    session_start = now
                    stats.wire_bytes_sent += link.stats.bytes_sent - base_sent
                    stats.wire_bytes_received += link.stats.bytes_received - base_recv
                    base_sent, base_recv = link.stats.bytes_sent, link.stats.bytes_received
                    if link.closed:
                        raise TransportClosed(f"{url}: link lost")
                    if stats_every_s and now - last_stats[0] >= stats_every_s:
                        last_stats[0] = now
                        say(stats.line())
                    # one packet in flight at most, and at most fps per second
                    if not sent.wait(_WAIT_S):
                        continue
                    if fps > 0 and now < next_due:
                        stop.wait(min(next_due - now, _WAIT_S))
                        continue
                    view, sequence, fresh, want_key = events.take()
                    y: np.ndarray | None = None  # interpolated unless set
                    refined = False
                    if motion is not None:
                        motion.budget_s = pace.budget_s
                    if refiner is not None and refiner.error is not None:
                        say(f"ray-casting failed ({_short(refiner.error)}); sending interpolated "
                            "scores only")
                        refiner.close()
                        refiner, scores = None, "interpolate"
                    if running_orbit is not None and linger_until is None:
                        view = running_orbit.next_view(now)
                        if view is None:  # done: still answer key-frame requests a moment
                            linger_until = now + _LINGER_S
                            say("orbit done")
                            continue
                        sequence = 0
                    elif linger_until is not None:
                        if now >= linger_until:
                            break
                        if not want_key or current.view is None:
                            events.wait(_WAIT_S)
                            continue
                        view, sequence, y = current.view, current.sequence, current.scores
                        linger_until = max(linger_until, now + _LINGER_S)
                    elif not fresh:
                        unrefined = (refiner is not None and current.view is not None
                                     and current.scores is None)
                        ready = refiner.take(current.view) if unrefined else None
                        step = None
                        if motion is not None and current.view is not None and not want_key:
                            step, error = _motion_step(motion.refine, current.view)
                            if error is not None:
                                say(f"ray-casting failed ({_short(error)}); sending "
                                    "interpolated scores only")
                                motion, scores = None, "interpolate"
                        if step is not None:
                            stats.motion_pixels += step.pixels
                            stats.motion_seconds += step.seconds
                            if step.scores is None:  # more pixels, nothing new to show yet
                                continue
                        if step is not None:  # the resting view, denser
                            view, sequence, y, refined = (current.view, current.sequence,
                                                          step.scores, True)
                            stats.converged_frames += int(step.complete)
                        elif ready is not None:  # the resting view, ray-cast: send its own scores
                            view, sequence, y, refined = current.view, current.sequence, ready, True
                        elif want_key and current.view is not None:
                            view, sequence, y = current.view, current.sequence, current.scores
                        else:
                            wait = _WAIT_S
                            if unrefined and not refiner.wanted(current.view):
                                rest = current.requested_at + refine_delay_s - now
                                if rest <= 0:
                                    refiner.submit(current.view)
                                else:
                                    wait = min(wait, rest)
                            events.wait(wait)
                            continue
                    if fresh:
                        current.requested_at = now
                    if scores == "render" and y is None:
                        y = true_views(view)
                        stats.rendered_frames += 1
                    elif motion is not None and y is None:
                        step, error = _motion_step(motion.frame, view)
                        if error is not None:
                            say(f"ray-casting failed ({_short(error)}); sending interpolated "
                                "scores only")
                            motion, scores = None, "interpolate"
                        else:
                            y = step.scores
                            stats.motion_frames += 1
                            stats.motion_pixels += step.pixels
                            stats.motion_seconds += step.seconds
                            stride = str(step.stride)
                            stats.stride_frames[stride] = stats.stride_frames.get(stride, 0) + 1
                    current.view, current.sequence, current.scores = view, sequence, y
                    encoded = encoder.encode(view, key=want_key, scores=y)
                    sent.clear()
                    queued = time.monotonic()

                    def left(queued: float = queued, sent: threading.Event = sent) -> None:
                        pace.left(time.monotonic() - queued)
                        sent.set()

                    try:
                        session.send_scores(m.Scores(sequence=sequence,
                                                     packet=encoded.packet),
                                            after_sent=left)
                    except ValueError as exc:  # the packet does not fit the device's frames
                        kind = "key" if encoder.last_was_key else "delta"
                        raise ServeError(
                            f"{' '.join(str(exc).split())}: a {kind} score packet of this model "
                            f"({len(encoded.packet)} bytes) does not fit the device's frames; "
                            "start eigencast-device with a larger --max-frame (e.g. --max-frame "
                            "65536)") from None
                    next_due = now + (1.0 / fps if fps > 0 else 0.0)
                    size = len(encoded.packet)
                    stats.frames += 1
                    stats.packet_bytes += size
                    if encoder.last_was_key:
                        stats.key_frames += 1
                        stats.key_bytes += size
                    else:
                        stats.delta_frames += 1
                        stats.delta_bytes += size
                    stats.last_view = view
                    if refined:
                        stats.refined_frames += 1
                    if on_frame is not None:
                        on_frame(encoded, view)
                # finished: let the last packet leave, say goodbye
                sent.wait(2.0)
                link.wait_writer_idle(2.0)
                session.bye("done")
                link.close(flush_timeout_s=1.0)
                link = None
                break
            except (TransportClosed, TransportTimeout, TransportError) as exc:
                if isinstance(exc, RemoteError):
                    raise
                if link is not None:
                    with contextlib.suppress(Exception):
                        link.close(flush_timeout_s=0.0)
                    link = None
                failures += 1
                if not reconnect or (max_reconnects is not None and failures > max_reconnects):
                    if stats.sessions == 0:
                        raise
                    say(f"link lost ({_short(exc)}); not reconnecting")
                    break
                delay = min(_BACKOFF_S[0] * 2 ** (failures - 1), _BACKOFF_S[1])
                say(f"link lost ({_short(exc)}); reconnecting in {delay:.2f} s")
                stop.wait(delay)  # reconnect backoff (a protocol timer)
            finally:
                if link is not None:
                    with contextlib.suppress(Exception):
                        link.close(flush_timeout_s=0.5)
    finally:
        if refiner is not None:
            refiner.close()
    if true_views is not None:
        stats.rendered_views = true_views.renders
        stats.render_seconds = true_views.render_seconds
    say(f"done: {stats.line()}")
    return stats


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


def _motion_step(call: Callable[[tuple[float, float]], Any],
                 view: tuple[float, float]) -> tuple[Any, BaseException | None]:
    """``call(view)`` and the error it raised (serve then falls back to interpolation)."""
    try:
        return call(view), None
    except Exception as exc:
        return None, exc


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 120 else text[:117] + "..."
