"""The device runtime loop: boot from flash, receive scores, reconstruct, present.

:class:`RuntimeDevice` is a :class:`~device_runtime.device.Device` (it keeps answering
HELLO, provisioning and every other request) that also shows frames. Threads::

    link reader --frames--> link dispatcher --SCORES--> on_scores: decode (bounded,
                                                        keeps delta bases)
                                                              |
                                                latest-wins slot (one ScoreItem)
                                                              v
    main thread: display loop (~60 Hz)  <-- input (window) / orbit / scripted views
        take the newest scores -> Reconstructor.update (changed cells only) -> present
        view changes -> VIEW_REQUEST through a rate limiter (latest wins) -> link writer

* The display never waits for the link: the dispatcher decodes every packet (so delta
  chains stay intact) and leaves only the newest in a one-item slot; the display loop
  takes it with a short timeout and otherwise keeps polling input. Frames the display
  could not keep up with are *coalesced* (counted), never queued.
* Deltas: the host codes each delta against the last packet it *sent* in this session;
  this device keeps a few recent frames as bases (``ScoreDecoder``) and, when a delta's
  base is missing (a packet lost on a noisy line), sends KEYFRAME_REQUEST (at most one per
  ``KEYFRAME_RETRY_S``) and keeps showing the last frame until a key frame arrives. A new
  session (HELLO) forgets the bases and the device immediately asks for its current view.
* Confirm: a TEST image is confirmed in flash once a frame from it has been presented (at
  activation the runtime presents the image's first frame: the mean image, or with
  ``standalone`` the current view); until then it reverts at the next boot.
* Link loss: the last frame stays on screen; :meth:`Device.run` re-accepts (TCP) or reopens
  (serial) the port with backoff, and the new session starts with a key frame.
* Memory is flat: one frame buffer, one slot, bounded rings for statistics.

Served (``predict=True``): when the active image carries the standalone table, the device
shows its *own frame* of every new view at once (no bytes, no latency): the score blend of
its predicted scores (:mod:`device_runtime.prediction`), then, for an image fitted with
depth, the depth warp of its neighbouring training views (:mod:`device_runtime.synthesis`,
made on a thread of its own, `WarpWorker`, and shown when ready if the view is still on
show: made on the display thread it made every frame of a drag late, docs/rate-distortion.md
9.8). The view request goes out as before, and the host answers with a *correction of that
frame* (a version-3 packet, `protocol.scores`): the device shows its own frame plus the
correction's eigenimages (`Reconstructor.correct`), at once when the frame is at hand, else
as soon as the warp is made. A correction for a view the user has already left is dropped as
stale (counted); a host-driven one (``serve --orbit``) moves the view. HELLO_REPLY lists the
packet versions this device reads and says whether it predicts (``predicts``). Version-2
corrections (of the predicted scores: an older host) and full key/delta frames are still
shown as before; a full frame for a view no longer on show is dropped the same way (its
delta base is still kept).

Standalone (``standalone=True``): the image carries a quantized table of the training
views' scores and the runtime interpolates scores locally, needing no host:
:mod:`device_runtime.standalone`. Orbits and view lists (``--orbit``, ``--views``) are
:mod:`device_runtime.orbit`. Their names are still importable from here.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from device_runtime.device import Device, DeviceConfig
from device_runtime.display import (
    Action,
    HeadlessPresenter,
    Quit,
    Screenshot,
    ToggleOverlay,
    ViewDelta,
    Zoom,
)
from device_runtime.errors import DeviceError, FlashError
from device_runtime.orbit import OrbitSpec, canonical_view, parse_orbit, parse_view_list
from device_runtime.prediction import Predictor, can_predict, corrected
from device_runtime.reconstruct import Reconstructor
from device_runtime.slots import LatestSlot, RequestLimiter
from device_runtime.standalone import (
    STANDALONE_DELTA_SECTION,
    STANDALONE_SECTION,
    StandaloneScores,
    standalone_order,
    standalone_table,
)
from device_runtime.stats import RuntimeStats, peak_rss_bytes
from device_runtime.synthesis import WORKER_SCRATCH_BYTES, ViewSynthesizer, WarpWorker
from protocol import messages as m
from protocol.errors import ProtocolError
from protocol.framing import Frame
from protocol.image import EigenspaceImage
from protocol.scores import (
    VERSIONS,
    DecodedScores,
    ImageMismatch,
    MissingBase,
    ScoreDecoder,
    score_bound,
)

__all__ = [
    "DEFAULT_VIEW",
    "KEYFRAME_RETRY_S",
    "STANDALONE_DELTA_SECTION",
    "STANDALONE_SECTION",
    "LatestSlot",
    "LoadedModel",
    "OrbitSpec",
    "RequestLimiter",
    "RuntimeDevice",
    "RuntimeStats",
    "ScoreItem",
    "StandaloneScores",
    "canonical_view",
    "parse_orbit",
    "parse_view_list",
    "peak_rss_bytes",
    "standalone_order",
    "standalone_table",
]

DEFAULT_VIEW = (30.0, 15.0)
"""(phi_deg, theta_deg) shown first when nothing else says which view."""
KEYFRAME_RETRY_S = 0.1
"""Shortest time between two KEYFRAME_REQUESTs while a delta base is missing, seconds."""
_TICK_S = 1.0 / 60.0
_HEADLESS_TICK_S = 0.05
_WARP_POLL_S = 0.004
"""How often the display loop looks for a finished warp while one is due, seconds."""


# --------------------------------------------------------------------------- model


@dataclass
class LoadedModel:
    """An active eigenspace ready to show: reconstruction, score decoder, standalone data."""

    image: EigenspaceImage
    reconstructor: Reconstructor
    decoder: ScoreDecoder
    slot: str
    generation: int
    test: bool
    standalone: StandaloneScores | None = None
    confirmed: bool = False
    predictor: Predictor | None = None
    #: Depth-aware view synthesis (image fitted with ``--depth``): every standalone frame,
    #: and a predicting device's own frames while the host's are on their way.
    synthesis: ViewSynthesizer | None = None
    #: A predicting device's warps, made off the display thread (`WarpWorker`).
    warp_worker: WarpWorker | None = None

    @classmethod
    def build(cls, image: EigenspaceImage, *, slot: str, generation: int, test: bool,
              max_packet_bytes: int | None = None, want_standalone: bool = False,
              want_predictor: bool = False) -> LoadedModel:
        """Reconstructor, decoder (bounded by the image's K) and, if asked, standalone data
        and (``want_predictor``, when the image has a table) the predictor; with either and
        an image with depth, the view synthesis (sharing the predictor's table).

        The reconstructor runs on two threads when the machine has two CPUs and the
        eigenspace is large (``threads="auto"``); its frames are the same bit for bit.
        """
        standalone = StandaloneScores(image) if want_standalone else None
        decoder = ScoreDecoder(
            image.n_coefficients,
            image.digest or bytes(32),
            n_components=image.n_components,
            max_packet_bytes=max_packet_bytes,
            max_abs_score=score_bound(max(1, int(np.asarray(image.mean).shape[-1]))),
        )
        predictor = (Predictor(image) if want_predictor and not want_standalone
                     and can_predict(image) else None)
        synthesis = None
        table = standalone if standalone is not None else (
            predictor.standalone if predictor is not None else None)
        reconstructor = Reconstructor.from_image(image, threads="auto")
        if table is not None and image.synthesis is not None:
            # A standalone device shows warps only (each a new array), so the neighbours'
            # colours may use the display's reconstructor: one set of buffers. A predicting
            # device warps on its worker thread while the display shows the host's frames
            # from the display's reconstructor: the worker needs one of its own.
            synthesis = ViewSynthesizer(
                image, table, reconstructor if standalone is not None
                else Reconstructor.from_image(image, threads=1,
                                              scratch_bytes=WORKER_SCRATCH_BYTES))
        worker = WarpWorker(synthesis) if synthesis is not None and standalone is None else None
        return cls(image, reconstructor, decoder, slot, generation, test, standalone,
                   predictor=predictor, synthesis=synthesis, warp_worker=worker)

    def close(self) -> None:
        if self.warp_worker is not None:  # before the reconstructor its warps use
            self.warp_worker.close()
        self.reconstructor.close()
        if self.synthesis is not None and self.synthesis.reconstructor is not self.reconstructor:
            self.synthesis.reconstructor.close()  # a predicting device's worker's own


@dataclass(frozen=True)
class ScoreItem:
    """One decoded packet handed from the dispatcher to the display loop."""

    model: LoadedModel
    scores: DecodedScores
    sequence: int
    received_s: float


# --------------------------------------------------------------------------- runtime


class RuntimeDevice(Device):
    """A device that shows frames: the issue-5 runtime around :class:`Device`.

    Parameters
    ----------
    config : DeviceConfig
    presenter : Window or HeadlessPresenter, optional
        Default: a :class:`HeadlessPresenter` that writes nothing.
    standalone : bool
        Interpolate scores locally from the image's table (no host needed); SCORES from a
        host are then ignored.
    predict : bool
        With a host: show the device's own prediction of every new view at once when the
        image has a standalone table, and accept corrections to it (issue 14).
    view : (float, float)
        Initial ``(phi_deg, theta_deg)``.
    orbit : OrbitSpec, optional
        Drive the view by itself (standalone: locally; otherwise by VIEW_REQUESTs); the
        runtime stops when a finite orbit is done and its last frame is presented.
    views : list of (float, float), optional
        Scripted views, shown one after another (each once its frame was presented).
    request_rate_hz : float
        VIEW_REQUESTs per second at most (latest wins in between).
    max_frames : int, optional
        Stop after presenting this many frames.
    on_frame : callable, optional
        ``on_frame(frame, info)`` after each present (tests, benchmarks).
    log : callable, optional
    """

    def __init__(
        self,
        config: DeviceConfig,
        *,
        presenter: Any = None,
        standalone: bool = False,
        predict: bool = False,
        view: tuple[float, float] = DEFAULT_VIEW,
        orbit: OrbitSpec | None = None,
        views: Iterable[tuple[float, float]] | None = None,
        request_rate_hz: float = 60.0,
        max_frames: int | None = None,
        on_frame: Callable[[np.ndarray, dict], None] | None = None,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.presenter = presenter if presenter is not None else HeadlessPresenter(None)
        self.standalone = standalone
        self.predict = predict
        self.view = canonical_view(*view)
        self.orbit_spec = orbit
        self._script = collections.deque(canonical_view(*v) for v in (views or ()))
        self.limiter = RequestLimiter(request_rate_hz)
        self.max_frames = max_frames
        self.on_frame = on_frame
        self.runtime_stats = RuntimeStats()
        self._scores = LatestSlot()
        self._models = LatestSlot()
        self._decoder_model: LoadedModel | None = None  # dispatcher's
        self._model: LoadedModel | None = None  # display loop's
        self._sequence = 0
        self._request_times: collections.OrderedDict[int, float] = collections.OrderedDict()
        self._last_keyframe_request = -math.inf
        self._need_key = False
        self._wrong_image_logged = False
        self.stop_event = threading.Event()
        self._view_dirty = False
        self._redraw = False
        self._overlay_s = 0.0
        self._last_y: np.ndarray | None = None
        self._shown_frame: np.ndarray | None = None  # what the presenter shows (redraws)
        self._warp_due: tuple[float, float] | None = None  # served: the blend shown, warp next
        # served: a correction waiting for the warp of its view; the last warp made (the
        # frame a correction of its view corrects); the view whose own frame the display
        # reconstructor holds for `Reconstructor.correct`
        self._correction_due: ScoreItem | None = None
        self._own_warp: tuple[tuple[float, float], np.ndarray] | None = None
        self._synth_view: tuple[float, float] | None = None
        self._superseded = 0  # corrections replaced by newer ones while waiting for a warp
        self._blend_s = -1.0  # when a predicting device last showed a moved view's blend
        self._shown_view: tuple[Any, Any] = (None, None)
        self._link_bytes: collections.deque = collections.deque(maxlen=64)
        super().__init__(config, log=log)

    # ------------------------------------------------------------------ boot / images
    def boot(self) -> Any:
        """Boot the flash store and load the active image (confirmed after its first frame)."""
        result = self.store.boot()
        self.log(f"boot: {result.reason}")
        if result.ok:
            self._activate("boot")
        else:
            self.log("no image to show yet: provision one (eigencast provision MODEL.ecs)")
        return result

    def on_image_committed(self) -> None:
        """A new TEST image is active: load it; it is confirmed after its first frame."""
        self._activate("commit")

    def _activate(self, why: str, *, depth: int = 0) -> bool:
        slot = self.store.active_slot
        if slot is None:
            return False
        info = self.store.slots[0 if slot == "A" else 1]
        test = info.state.name == "TEST"
        try:
            image = self.load_active_image()
        except (ProtocolError, DeviceError, OSError, ValueError) as exc:
            # digest, format, tag, RAM budget: this device cannot load it, whatever its
            # state; give it up for the other slot (MCUboot) and show nothing from it
            return (self.fall_back(why, slot, exc) is not None and depth == 0
                    and self._activate(why, depth=1))
        try:
            model = LoadedModel.build(
                image,
                slot=slot,
                generation=info.image_generation,
                test=test,
                max_packet_bytes=None,
                want_standalone=self.standalone,
                want_predictor=self.predict,
            )
        except (ProtocolError, DeviceError, OSError, ValueError) as exc:
            # this run's mode cannot use it (e.g. --standalone without a table): a test
            # image goes back to the other slot; a confirmed one stays for a normal start
            text = " ".join(str(exc).split())[:200]
            self.log(f"{why}: slot {slot}: the image does not load ({text})")
            if not test:
                return False
            try:
                self.store.revert()
            except FlashError as revert_exc:
                self.log(f"{why}: cannot revert: {revert_exc}")
                self.notice(2, f"slot {slot}: image failed to load",
                            {"event": "load-failed", "slot": slot})
                return False
            self.log(f"{why}: reverted to slot {self.store.active_slot}")
            self.notice(2, f"slot {slot}: image failed to load; reverted",
                        {"event": "load-failed", "slot": slot})
            return depth == 0 and self._activate(why, depth=1)
        self.log(f"{why}: slot {slot}: image generation {model.generation} loaded "
                 f"({image.image_shape[1]}x{image.image_shape[0]}, K={image.n_coefficients}"
                 f"{', test: confirmed after the first frame' if test else ''})")
        self._decoder_model = model
        self._models.put(model)
        self._scores.wake()
        return True

    def _confirm(self, model: LoadedModel) -> None:
        """Confirm ``model``'s TEST slot (on the dispatcher when a host is connected)."""
        if not model.test or model.confirmed:
            return
        model.confirmed = True

        def confirm() -> None:
            if self.store.active_slot != model.slot:
                return
            try:
                self.store.confirm()
            except FlashError as exc:
                self.log(f"confirm: {exc}")
                return
            self.log(f"slot {model.slot}: image generation {model.generation} shown and "
                     "confirmed")
            self.notice(0, f"slot {model.slot}: image confirmed",
                        {"event": "confirmed", "slot": model.slot,
                         "generation": model.generation})

        link = self.link
        if link is not None and not link.closed:
            link.defer(confirm)
        else:
            confirm()

    # ------------------------------------------------------------------ link side
    @property
    def predicts(self) -> bool:
        """The active image has a table and this device shows corrections to its predictions."""
        model = self._decoder_model
        return model is not None and model.predictor is not None

    def handle_hello(self, msg: m.Hello, frame: Frame) -> m.Message:
        """A new session: forget delta bases, then ask the host for the current view.

        HELLO_REPLY also says which score packet versions this device reads and whether it
        predicts (a keyed device says the latter only in AUTH_RESPONSE)."""
        reply = super().handle_hello(msg, frame)
        reply = dataclasses.replace(reply, score_versions=VERSIONS, predicts=(
            None if self.config.key is not None else self.predicts))
        self.runtime_stats.sessions += 1
        model = self._decoder_model
        if model is not None:
            model.decoder.reset()
        self._need_key = False
        if not self.standalone and self.config.key is None:
            self.limiter.offer(self.view)  # sent by the display loop after the reply
        return reply

    def handle_auth_challenge(self, msg: m.AuthChallenge, frame: Frame) -> m.Message:
        """A keyed device asks for its view once the host has authenticated (not before)."""
        reply = super().handle_auth_challenge(msg, frame)
        if isinstance(reply, m.AuthResponse):
            reply = dataclasses.replace(reply, predicts=self.predicts)
        if not self.standalone:
            self.limiter.offer(self.view)
        return reply

    def on_scores(self, msg: m.Scores) -> None:
        """Decode a SCORES packet (every one: delta chains stay intact); keep the newest."""
        stats = self.runtime_stats
        stats.packets += 1
        stats.packet_bytes += len(msg.packet)
        model = self._decoder_model
        if model is None or self.standalone:
            stats.dropped_no_image += 1
            return
        t0 = time.perf_counter()
        try:
            decoded = model.decoder.decode(msg.packet)
            if (decoded.predicted or decoded.synthesized) and model.predictor is None:
                stats.corrections_without_table += 1
                self._log_limited("no-table", "a correction for a device that does not "
                                  "predict (no standalone table, or --no-predict) dropped")
                return
        except MissingBase as exc:
            stats.missing_base += 1
            self._need_key = True
            self._request_keyframe(exc.base_frame)
            return
        except ImageMismatch as exc:
            stats.wrong_image += 1
            if not self._wrong_image_logged:
                self._wrong_image_logged = True
                self.log(f"scores for another image dropped ({exc}); provision the host's "
                         "image")
            return
        except Exception as exc:  # ProtocolError, or anything else a packet provokes
            stats.decode_errors += 1
            self._log_limited("bad-scores", f"bad score packet dropped: "
                           f"{' '.join(str(exc).split())[:160]} ({stats.decode_errors} so far)")
            return
        decode_s = time.perf_counter() - t0
        stats.decode_s.add(decode_s)
        self._need_key = False
        if decoded.predicted or decoded.synthesized:
            stats.correction_packets += 1
        elif decoded.is_key:
            stats.key_frames += 1
        else:
            stats.delta_frames += 1
        stats._bytes_ring.append(decoded.packet_bytes)
        self._scores.put(ScoreItem(model, decoded, msg.sequence, time.monotonic()))

    def _session_link(self) -> Any:
        """The link when a host session is up (HELLO done; a keyed device: AUTH done), else
        None: an unauthenticated peer learns nothing from view or key-frame requests."""
        link = self.link
        if link is None or link.closed or not self.session.hello_done:
            return None
        if self.config.key is not None and not self.session.authenticated:
            return None
        return link

    def _request_keyframe(self, base_frame: int | None = None) -> None:
        now = time.monotonic()
        if now - self._last_keyframe_request < KEYFRAME_RETRY_S:
            return
        link = self._session_link()
        if link is None:
            return
        self._last_keyframe_request = now
        held = self._decoder_model.decoder.base_frames if self._decoder_model else []
        with contextlib.suppress(ProtocolError, ValueError):
            link.send(m.KeyframeRequest(sequence=self._sequence,
                                        last_frame=held[-1] if held else None))
            self.runtime_stats.keyframe_requests += 1

    def _send_view_request(self, view: tuple[float, float], now_s: float) -> None:
        link = self._session_link()
        if link is None:
            return
        self._sequence = (self._sequence % 0xFFFFFFFF) + 1
        with contextlib.suppress(ProtocolError, ValueError):
            link.send(m.ViewRequest(phi_deg=view[0], theta_deg=view[1],
                                    sequence=self._sequence))
            self.runtime_stats.view_requests += 1
            self._request_times[self._sequence] = now_s
            while len(self._request_times) > 64:
                self._request_times.popitem(last=False)

    # ------------------------------------------------------------------ display loop
    def set_view(self, phi_deg: float, theta_deg: float) -> None:
        """Change the view (display thread): standalone shows it, otherwise it is requested.
        A view a float32 step or two from the one the warp worker made ahead is that view
        (`WarpWorker.snap`: its frame is ready)."""
        view = canonical_view(phi_deg, theta_deg)
        model = self._model
        if model is not None and model.warp_worker is not None:
            view = model.warp_worker.snap(view)
        self.view = view
        self._view_dirty = True

    def apply(self, action: Action) -> None:
        """Apply one input action (display thread)."""
        if isinstance(action, ViewDelta):
            phi, theta = self.view
            self.set_view(phi + action.dphi_deg, max(-90.0, min(90.0, theta + action.dtheta_deg)))
        elif isinstance(action, Zoom):
            set_zoom = getattr(self.presenter, "set_zoom", None)
            if set_zoom is not None:
                set_zoom(self.presenter.zoom * action.factor)
        elif isinstance(action, ToggleOverlay):
            self.presenter.overlay = not self.presenter.overlay
            self._redraw = True
        elif isinstance(action, Screenshot):
            path = self.presenter.screenshot()
            if path is not None:
                self.log(f"screenshot saved to {path}")
        elif isinstance(action, Quit):
            self.stop_event.set()

    def overlay_lines(self) -> list[str]:
        """The overlay's text: fps, bytes per frame, link rate, the current view."""
        stats = self.runtime_stats
        link = self.link
        rate = 0.0
        if link is not None:
            now = time.monotonic()
            self._link_bytes.append((now, link.stats.bytes_received))
            old = next((s for s in self._link_bytes if now - s[0] <= 2.0), None)
            if old is not None and now > old[0]:
                rate = (link.stats.bytes_received - old[1]) / (now - old[0])
        mode = "standalone" if self.standalone else ("link up" if link else "no host")
        phi, theta = self.view
        fps = stats.fps()  # frames over the last second: 0 while the view rests
        return [
            (f"{fps:5.1f} fps" if fps > 0 else " idle    ") + f"   frame {stats.frames_presented}",
            f"{stats.bytes_per_frame():6.0f} B/frame  key {stats.key_frames} "
            f"delta {stats.delta_frames}"
            + (f"  warp {stats.synthesized_frames}" if stats.synthesized_frames else ""),
            f"link {rate / 1024:6.1f} KiB/s  ({mode})",
            f"view phi {phi:6.1f}  theta {theta:5.1f}",
        ]

    def _present(self, model: LoadedModel, y: np.ndarray, info: dict, *,
                 warp: bool = False, warped: np.ndarray | None = None,
                 frame: np.ndarray | None = None) -> None:
        """Show a frame: ``y`` reconstructed, or with ``warp`` (the device's own frame of
        the view ``info`` names: standalone, or a prediction) and an image with depth, the
        neighbours warped into the view (`ViewSynthesizer`). A host's frame never warps."""
        stats = self.runtime_stats
        t0 = time.perf_counter()
        if frame is not None:  # made already (a corrected frame)
            pass
        elif warped is not None or (warp and model.synthesis is not None):
            # a frame of its own, not the reconstructor's buffer: the reconstructor only
            # recomputes the cells whose scores changed, so the next host frame needs its
            # buffer to still hold the last reconstruction
            frame = warped if warped is not None else model.synthesis.frame(
                info["phi_deg"], info["theta_deg"])
            info = {**info, "synthesized": True}
            stats.synthesized_frames += 1
        else:
            frame = model.reconstructor.update(y)
        t1 = time.perf_counter()
        overlay = self.overlay_lines() if self.presenter.overlay else None
        self.presenter.present(frame, info, overlay_lines=overlay)
        t2 = time.perf_counter()
        now = time.monotonic()
        stats.reconstruct_s.add(t1 - t0)
        stats.present_s.add(t2 - t1)
        stats.stage_samples.append((info.get("decode_s", 0.0), t1 - t0, t2 - t1))
        stats.frames_presented += 1
        stats._present_times.append(now)
        seq = info.get("sequence", 0)
        if seq and seq in self._request_times:
            stats.latencies_s.append(now - self._request_times[seq])
            while self._request_times and next(iter(self._request_times)) <= seq:
                self._request_times.popitem(last=False)
        self._shown_view = (info.get("phi_deg"), info.get("theta_deg"))
        self._shown_frame = frame
        self._last_y = y
        self._confirm(model)
        if self.on_frame is not None:
            self.on_frame(frame, info)
        if self.max_frames is not None and stats.frames_presented >= self.max_frames:
            self.stop_event.set()

    def _swap_model(self, model: LoadedModel) -> None:
        old = self._model
        self._model = model
        if old is not None and old is not model:
            old.close()
        resize = getattr(self.presenter, "set_image_shape", None)
        if resize is not None:
            resize(model.image.image_shape)
        self._last_y = None
        if model.standalone is not None:
            y = model.standalone.scores(*self.view)
            self._present(model, y, {"phi_deg": self.view[0], "theta_deg": self.view[1],
                                     "key": True, "frame": 0}, warp=True)
        elif model.predictor is not None:  # its own prediction, while the host is asked
            self._predict_view(model)
        else:  # the image's own first frame (the mean), while the host is asked for the view
            y = np.zeros(model.image.n_coefficients, dtype=np.float32)
            self._present(model, y, {"frame": 0})
            self.limiter.offer(self.view)

    def run_display(self, stop: threading.Event | None = None) -> None:
        """The display loop (call on the main thread); returns when stopped or finished.

        Stops on ``stop`` / :attr:`stop_event`, Esc or a closed window, ``max_frames``, or
        when a finite orbit or view script has shown its last view.
        """
        stop_events = [self.stop_event] + ([stop] if stop is not None else [])
        headless = getattr(self.presenter, "headless", True)
        tick = _HEADLESS_TICK_S if headless else _TICK_S
        orbit = self.orbit_spec.start(phi0_deg=0.0) if self.orbit_spec else None
        waiting_for: tuple[float, float] | None = None  # steps/script: view not shown yet
        try:
            while not any(e.is_set() for e in stop_events):
                now = time.monotonic()
                for action in self.presenter.poll():
                    self.apply(action)
                model = self._models.take(0.0)
                if model is not None:
                    self._swap_model(model)
                model = self._model
                # orbit / scripted views: "steps" and scripts advance once the previous
                # view was presented, "turn" follows the clock
                if model is not None and (orbit is not None or self._script or waiting_for):
                    shown = waiting_for is None or self._shown_view == waiting_for
                    if orbit is not None and orbit.spec.kind == "turn":
                        view = orbit.next_view(now)
                        if view is None:
                            break
                        if view != self.view:
                            self.set_view(*view)
                    elif shown:
                        view = (orbit.next_view(now) if orbit is not None
                                else self._script.popleft() if self._script else None)
                        if view is None:
                            break
                        self.set_view(*view)
                        waiting_for = view
                # A predicting device shows at most one blend per display refresh (_TICK_S,
                # headless too: its benchmarks stand for a window) while its view moves: with
                # a warp due the loop turns every _WARP_POLL_S, and a blend on every turn (a
                # drag's or a clock-driven orbit's view moves on each) took the cores from the
                # warp worker and the link (at 512 headless: 70 blends a second)
                blend_in = 0.0
                if self._view_dirty and model is not None:
                    if (model.standalone is None and model.predictor is not None
                            and now - self._blend_s < _TICK_S):
                        blend_in = _TICK_S - (now - self._blend_s)
                    else:
                        self._view_dirty = False
                        if model.standalone is not None:
                            y = model.standalone.scores(*self.view)
                            self._present(model, y, {"phi_deg": self.view[0],
                                                     "theta_deg": self.view[1], "key": True},
                                          warp=True)
                        elif model.predictor is not None:
                            self._blend_s = now
                            self._predict_view(model)
                        else:
                            self.limiter.offer(self.view)
                if not self.standalone:
                    view = self.limiter.due(now)
                    if view is not None:
                        self._send_view_request(view, now)
                    if self._need_key:
                        self._request_keyframe()
                wait = tick if not self.limiter.pending else min(tick,
                                                                 self.limiter.min_interval_s)
                if self._warp_due is not None:  # look for the warp often, input comes first
                    wait = min(wait, _WARP_POLL_S)
                if blend_in > 0.0:
                    wait = min(wait, blend_in)
                item = self._scores.take(wait if model is not None else tick)
                if item is not None and item.model is self._model:
                    d = item.scores
                    try:
                        if d.synthesized:
                            self._correct(item)
                            continue
                        y = self._shown_scores(item)
                        if y is not None:
                            self._present(item.model, y, {
                                "frame": d.frame, "phi_deg": d.phi_deg,
                                "theta_deg": d.theta_deg, "key": d.is_key,
                                "packet_bytes": d.packet_bytes, "sequence": item.sequence,
                                "decode_s": 0.0, "corrected": d.predicted,
                            })
                            if (d.phi_deg, d.theta_deg) == self.view:
                                self._warp_due = None  # the host's frame is the newer one
                    except Exception as exc:
                        # A frame that cannot be shown must not stop the device: skip it.
                        self._frame_failed(d.frame, exc)
                elif self._warp_due is not None:
                    self._show_due_warp(model)
                elif self._redraw and self._model is not None and self._last_y is not None:
                    self._redraw = False
                    overlay = self.overlay_lines() if self.presenter.overlay else None
                    self.presenter.present(self._shown_frame, None, overlay_lines=overlay)
                elif (not headless and self.presenter.overlay and self._model is not None
                      and now - self._overlay_s > 0.25):
                    # keep the overlay's numbers fresh a few times a second
                    self._overlay_s = now
                    self.presenter.present(self._shown_frame if self._last_y is not None
                                           else self._model.reconstructor.frame, None,
                                           overlay_lines=self.overlay_lines())
        finally:
            self.stop_event.set()

    def _predict_view(self, model: LoadedModel) -> None:
        """A predicting device's new view: its score blend at once, the view request, and
        (an image with depth) the warp asked of the worker, shown by `_show_due_warp`; or,
        when the worker made that view's warp ahead (steady motion), the warp at once."""
        self._warp_due = None
        if self._correction_due is not None:  # its view was left before its warp was made
            self.runtime_stats.stale_dropped += 1
            self._correction_due = None
        made = None
        worker = model.warp_worker
        if worker is not None:
            worker.request(self.view)
            made = worker.take(self.view)
        if made is not None:
            self._own_warp = (self.view, made)
            self._present_prediction(model, warped=made)
        else:
            self._present_prediction(model)
            if worker is not None:
                self._warp_due = self.view
        self.limiter.offer(self.view)

    def _show_due_warp(self, model: LoadedModel | None, timeout_s: float = 0.0) -> None:
        """Replace the blend on show by the warp of its view once the worker has made it,
        unless the view moved on (or a host frame for it came) since the blend was shown."""
        due = self._warp_due
        if due is None or model is None or model.warp_worker is None:
            self._warp_due = None
            return
        if due != self.view or self._view_dirty:
            self._warp_due = None  # the user has moved on: a newer blend comes first
            return
        frame = model.warp_worker.take(due, timeout_s)
        if frame is None:
            return  # not made yet: look again on the next turn
        self._warp_due = None
        self._own_warp = (due, frame)
        item = self._correction_due
        if item is not None and (item.scores.phi_deg, item.scores.theta_deg) == due:
            self._correction_due = None
            self._show_corrected(item, frame)  # the host's correction came first
            return
        self._present_prediction(model, warped=frame)

    def _correct(self, item: ScoreItem) -> None:
        """A correction of the device's own frame of the packet's view (version 3): show
        that frame corrected, at once when the frame is at hand (a blend, or the warp made
        already), else once the warp worker has made it (`_show_due_warp`). A correction for
        a view the user has left is dropped; a host-driven one (sequence 0: ``serve
        --orbit``) moves the view."""
        d, model = item.scores, item.model
        view = (d.phi_deg, d.theta_deg)
        stats = self.runtime_stats
        if model.predictor is None:  # checked on decode; kept for safety
            stats.corrections_without_table += 1
            return
        if item.sequence and view != self.view:
            stats.stale_dropped += 1
            return
        if not item.sequence and view != self.view:
            self.view = view  # the host drives the view
        if model.warp_worker is None:  # the device's own frame is the blend
            synth = (None if self._synth_view == view
                     else model.reconstructor.update(model.predictor(*view)))
            self._show_corrected(item, synth)
        elif self._synth_view == view:
            self._show_corrected(item, None)
        elif self._own_warp is not None and self._own_warp[0] == view:
            self._show_corrected(item, self._own_warp[1])
        else:  # the warp of the view is not made yet: show it corrected once it is
            if self._correction_due is not None:  # a newer one replaces it, never shown
                self._superseded += 1
            self._correction_due = item
            if self._warp_due != view:
                model.warp_worker.request(view)
                self._warp_due = view

    def _show_corrected(self, item: ScoreItem, synth: np.ndarray | None) -> None:
        """Present ``synth`` (None: the one the display reconstructor holds) corrected by
        the packet's scores (`Reconstructor.correct`)."""
        d, model = item.scores, item.model
        view = (d.phi_deg, d.theta_deg)
        t0 = time.perf_counter()
        frame = model.reconstructor.correct(d.y, synth)
        self.runtime_stats.correct_s.add(time.perf_counter() - t0)
        self._synth_view = view
        self.runtime_stats.corrected_frames += 1
        if self._warp_due == view:
            self._warp_due = None  # the corrected frame is the newer one
        self._present(model, d.y, {
            "frame": d.frame, "phi_deg": d.phi_deg, "theta_deg": d.theta_deg, "key": False,
            "packet_bytes": d.packet_bytes, "sequence": item.sequence, "decode_s": 0.0,
            "corrected": True}, frame=frame)

    def _present_prediction(self, model: LoadedModel, *,
                            warped: np.ndarray | None = None) -> None:
        """Show the device's own prediction of the current view (no bytes, no latency).

        ``warped`` (an image with depth, once the blend is on show): the picture is this
        warp of the neighbours (`WarpWorker`), as a standalone device shows; the scores kept
        (a correction adds to them) are still the score prediction, the same on both sides
        (`device_runtime.prediction`)."""
        assert model.predictor is not None
        y = model.predictor(*self.view)
        if warped is None:
            self.runtime_stats.predicted_frames += 1
        self._present(model, y, {"phi_deg": self.view[0], "theta_deg": self.view[1],
                                 "key": False, "predicted": True}, warped=warped)

    def _shown_scores(self, item: ScoreItem) -> np.ndarray | None:
        """The scores to show for a decoded packet, or None when it is stale.

        A device that predicts shows a packet answering a view request (sequence > 0) only
        while its view is still the one on show (else the prediction already shows a newer
        view); a correction is added to the prediction of the packet's view. Host-driven
        packets (sequence 0: ``serve --orbit``) are shown whatever the current view.
        """
        d, model = item.scores, item.model
        view = (d.phi_deg, d.theta_deg)
        if model.predictor is not None and item.sequence and view != self.view:
            self.runtime_stats.stale_dropped += 1
            return None
        if not d.predicted:
            return d.y
        if model.predictor is None:  # checked on decode; kept for safety
            self.runtime_stats.corrections_without_table += 1
            return None
        self.runtime_stats.corrected_frames += 1
        return corrected(model.predictor(*view), d.y)

    def _frame_failed(self, frame: int, exc: BaseException) -> None:
        """Count a frame the display could not show; log the first one of a run of them."""
        stats = self.runtime_stats
        stats.frame_failures += 1
        if stats.frame_failures == 1 or stats.frame_failures % 1000 == 0:
            self.log(f"frame {frame} skipped ({' '.join(str(exc).split())[:160]}); "
                     f"{stats.frame_failures} skipped so far")

    def stats_dict(self) -> dict[str, Any]:
        """Runtime statistics (:meth:`RuntimeStats.as_dict`) plus the current view and image."""
        self.runtime_stats.coalesced = self._scores.replaced + self._superseded
        out = self.runtime_stats.as_dict()
        model = self._model
        out["view"] = list(self.view)
        out["standalone"] = self.standalone
        guard = self.stats
        out["link_guard"] = {  # what the device refused from its peers (issue 11)
            "dropped_no_session": guard.dropped_no_session,
            "dropped_unauthenticated": guard.dropped_unauthenticated,
            "dropped_bad_tag": guard.dropped_bad_tag,
            "dropped_replayed": guard.dropped_replayed,
            "auth_timeouts": guard.auth_timeouts,
            "preempted": guard.preempted,
            "errors_sent": guard.errors_sent,
        }
        out["image"] = None if model is None else {
            "slot": model.slot, "generation": model.generation,
            "shape": list(model.image.image_shape), "n_coefficients":
            model.image.n_coefficients,
            "eigenspace_bytes": int(model.image.eigenimages.nbytes + model.image.mean.nbytes
                                    + model.image.scales.nbytes),
        }
        return out

    def close_display(self) -> None:
        """Close the presenter and the models (on the display thread, after the loop)."""
        with contextlib.suppress(Exception):
            self.presenter.close()
        for model in {id(x): x for x in (self._model, self._decoder_model) if x}.values():
            model.close()


def make_presenter(*, headless: bool, frames_dir: Any = None, every: int = 1,
                   screenshot_dir: Any = None, image_shape: tuple[int, int] | None = None,
                   zoom: float | None = None) -> Any:
    """A :class:`~device_runtime.display.Window` or a headless presenter (window raises
    :class:`~device_runtime.display.WindowUnavailable` when none can be opened)."""
    if headless:
        return HeadlessPresenter(frames_dir, every=every, screenshot_dir=screenshot_dir)
    from device_runtime.display import Window

    return Window(image_shape or (256, 256), screenshot_dir=screenshot_dir or ".", zoom=zoom)
