"""The device runtime loop: boot from flash, receive scores, reconstruct, present.

:class:`RuntimeDevice` is a :class:`~device_runtime.device.Device` (it keeps answering
HELLO, provisioning and every other request) that also shows frames. Threads::

    link reader --frames--> link dispatcher --SCORES--> on_scores: decode (bounded,
                                                        keeps delta bases)
                                                              |
                                                latest-wins slot (one ScoreItem)
                                                              v
    main thread: display loop, one turn per tick (--fps) or sooner when a packet or a warp
        comes  <-- input (window) / orbit / scripted views
        the frame the policy picks (device_runtime.scheduler) -> present
        view changes -> VIEW_REQUEST through a rate limiter (latest wins) -> link writer
    warp worker thread: the depth warp of the view on show, or of the next view of steady
        motion (device_runtime.warp_worker.WarpWorker)

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

Frames (`device_runtime.scheduler.FrameScheduler`, one policy for every device): when the
active image carries the standalone table, the device shows its *own frame* of every new
view at once (no bytes, no latency): the warp of the view if its worker made it ahead, else
the blend of its own scores (at most one blend per tick), then, for an image fitted with
depth, the depth warp of its neighbouring training views once the worker has made it (the
display never waits on a warp). Everything the display has made of an image lives in its
`LoadedModel` (`device_runtime.loaded`), replaced whole when another image is activated.

Served (``predict=True``): the view request goes out as well, and the host answers with a
*correction of the own frame* (a version-3 packet, `protocol.scores`): the device shows its
own frame plus the correction's eigenimages (`Reconstructor.correct`), at once when the
frame is at hand, else as soon as the warp is made. A correction for a view the user has
already left is dropped as stale (counted); a host-driven one (``serve --orbit``) moves the
view. HELLO_REPLY lists the packet versions this device reads and says whether it predicts
(``predicts``). Version-2 corrections (of the predicted scores: an older host) and full
key/delta frames are still shown as before; a full frame for a view no longer on show is
dropped the same way (its delta base is still kept).

Standalone (``standalone=True``): the image carries a quantized table of the training
views' scores and the runtime interpolates scores locally, needing no host
(:mod:`device_runtime.standalone`); at rest it shows the view's warp, bit for bit
``eigencast view``'s frame. Orbits and view lists (``--orbit``, ``--views``) are
:mod:`device_runtime.orbit`. Their names are still importable from here.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import math
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from device_runtime.device import Device, DeviceConfig
from device_runtime.display import (
    Action,
    CycleLook,
    HeadlessPresenter,
    Quit,
    Screenshot,
    ToggleOverlay,
    ViewDelta,
    Zoom,
)
from device_runtime.errors import DeviceError, FlashError
from device_runtime.loaded import LayerItem, LoadedModel, ScoreItem
from device_runtime.looks import look_index, own_scores
from device_runtime.orbit import OrbitSpec, canonical_view, parse_orbit, parse_view_list
from device_runtime.scheduler import FrameScheduler
from device_runtime.slots import LatestSlot, RequestLimiter
from device_runtime.standalone import (
    STANDALONE_DELTA_SECTION,
    STANDALONE_SECTION,
    StandaloneScores,
    standalone_order,
    standalone_table,
)
from device_runtime.stats import RuntimeStats, peak_rss_bytes
from protocol import messages as m
from protocol.errors import ProtocolError
from protocol.framing import Frame
from protocol.layers import LAYER_VERSIONS, decode_layer, is_layer, max_file_bytes
from protocol.scores import VERSIONS, ImageMismatch, MissingBase

__all__ = [
    "DEFAULT_FPS",
    "DEFAULT_VIEW",
    "HEADLESS_FPS",
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
DEFAULT_FPS = 60.0
"""Display ticks per second of a window."""
HEADLESS_FPS = 30.0
"""Display ticks per second without a screen (a board's display rate)."""
LAYER_MAX_BYTES = 1 << 16
"""A layer's packet bound when neither ``--max-frame`` nor the transport sets one."""
LAYER_QUEUE = 256
"""Chunks of refinement layers held for the display at most (and a file's worth of bytes)."""
SWITCH_INTERVAL_S = 0.001
"""The interpreter's thread switch interval while the display loop runs, seconds."""


# --------------------------------------------------------------------------- runtime


class RuntimeDevice(FrameScheduler, Device):
    """A device that shows frames: the runtime around :class:`Device`.

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
        image has a standalone table, and accept corrections to it.
    view : (float, float)
        Initial ``(phi_deg, theta_deg)``.
    orbit : OrbitSpec, optional
        Drive the view by itself (standalone: locally; otherwise by VIEW_REQUESTs); the
        runtime stops when a finite orbit is done and its last frame is presented. A
        ``turn`` orbit moves once per display tick.
    views : list of (float, float), optional
        Scripted views, shown one after another (each once its best frame is on show: the
        warp, when the image warps).
    request_rate_hz : float
        VIEW_REQUESTs per second at most (latest wins in between).
    max_frames : int, optional
        Stop after presenting this many frames.
    fps : float, optional
        Display ticks per second: at most one blend per tick while the view moves, and a
        ``turn`` orbit's step. Default `DEFAULT_FPS` with a window, `HEADLESS_FPS` without.
    look : str or int, optional
        The look to show of an image with several (a name or an index; default the
        first); `show_look` changes it, the window's ``l`` key shows the next.
    clock : callable, optional
        Monotonic seconds (tests pass a fake one).
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
        fps: float | None = None,
        look: str | int | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_frame: Callable[[np.ndarray, dict], None] | None = None,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.presenter: Any = None
        self.use_presenter(presenter if presenter is not None else HeadlessPresenter(None),
                           fps=fps)
        self.standalone = standalone
        self.predict = predict
        self.look = look
        self._decoder_lock = threading.Lock()
        self.view = canonical_view(*view)
        self.orbit_spec = orbit
        self._script = collections.deque(canonical_view(*v) for v in (views or ()))
        self.limiter = RequestLimiter(request_rate_hz)
        self.max_frames = max_frames
        self.clock = clock
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
        self._shown_frame: np.ndarray | None = None  # what the presenter shows (redraws)
        self._superseded = 0  # corrections replaced by newer ones while waiting for a warp
        self._shown_view: tuple[Any, Any] = (None, None)
        self._link_bytes: collections.deque = collections.deque(maxlen=64)
        self._orbit: Any = None  # the running orbit (display loop)
        self._tick0 = clock()  # when the display's tick 0 began (reset by run_display)
        self._waiting_for: tuple[float, float] | None = None  # a scripted view not shown yet
        # refinement layers in arrival order (dispatcher -> display), bounded
        self._layers: collections.deque[LayerItem] = collections.deque()
        self._layers_bytes = 0  # the chunks' bytes in _layers
        self._asked_again_s = -math.inf  # when a lost layer last made the view asked again
        self._layers_lock = threading.Lock()
        super().__init__(config, log=log)

    def use_presenter(self, presenter: Any, *, fps: float | None = None) -> None:
        """Show frames on ``presenter`` from now on (before the display loop runs), at
        ``fps`` display ticks per second (default `DEFAULT_FPS` for a window,
        `HEADLESS_FPS` without one)."""
        if fps is None:
            fps = HEADLESS_FPS if getattr(presenter, "headless", True) else DEFAULT_FPS
        if not fps > 0:
            raise ValueError(f"RuntimeDevice: fps={fps!r} must be > 0")
        self.presenter = presenter
        self.tick_s = 1.0 / float(fps)

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
        look = 0
        if self.look is not None:
            try:
                look = look_index(image, self.look)
            except ValueError as exc:
                self.log(f"{why}: slot {slot}: {exc}; showing its first look")
        try:
            model = LoadedModel.build(
                image,
                slot=slot,
                generation=info.image_generation,
                test=test,
                max_packet_bytes=None,
                want_standalone=self.standalone,
                want_predictor=self.predict,
                on_warp=self._scores.wake,
                look=look,
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
        looks = (f", looks {', '.join(model.looks)}: showing {model.look_name}"
                 if model.looks else "")
        self.log(f"{why}: slot {slot}: image generation {model.generation} loaded "
                 f"({image.image_shape[1]}x{image.image_shape[0]}, K={image.n_coefficients}"
                 f"{looks}{', test: confirmed after the first frame' if test else ''})")
        with self._decoder_lock:
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
        reply = dataclasses.replace(reply, score_versions=(*VERSIONS, *LAYER_VERSIONS), predicts=(
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
        if is_layer(msg.packet):
            if not self._for_look(model, msg):
                return
            self._on_layer(model, msg.packet)
            return
        if model.base is not None and (msg.look or 0) != model.look and (
                own_scores(model.base, msg.look or 0) or own_scores(model.base, model.look)):
            self._for_look(model, msg)  # another eigenspace's scores: not for this decoder
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
            self._wrong_image(exc)
            return
        except Exception as exc:  # ProtocolError, or anything else a packet provokes
            stats.decode_errors += 1
            self._log_limited("bad-scores", f"bad score packet dropped: "
                           f"{' '.join(str(exc).split())[:160]} ({stats.decode_errors} so far)")
            return
        decode_s = time.perf_counter() - t0
        stats.decode_s.add(decode_s)
        self._need_key = False
        if not self._for_look(model, msg):  # decoded all the same: delta chains stay whole
            return
        if decoded.predicted or decoded.synthesized:
            stats.correction_packets += 1
        elif decoded.is_key:
            stats.key_frames += 1
        else:
            stats.delta_frames += 1
        stats._bytes_ring.append(decoded.packet_bytes)
        self._scores.put(ScoreItem(model, decoded, msg.sequence, time.monotonic()))

    def _wrong_image(self, exc: Exception) -> None:
        """A packet or layer made for another image: counted, said once."""
        self.runtime_stats.wrong_image += 1
        if not self._wrong_image_logged:
            self._wrong_image_logged = True
            self.log(f"scores for another image dropped ({exc}); provision the host's image")

    def _for_look(self, model: LoadedModel, msg: m.Scores) -> bool:
        """Whether a packet was made for the look ``model`` shows (absent: the first);
        one for another look (the user switched while it was on its way) is counted."""
        if (msg.look or 0) == model.look:
            return True
        self.runtime_stats.other_look += 1
        return False

    def _on_layer(self, model: LoadedModel, packet: bytes) -> None:
        """A refinement layer (`protocol.layers`): its header and declared size checked here,
        queued for the display (in order, bounded: the oldest goes when it is full), which
        decodes and applies it to the resting view's frame it belongs to."""
        stats = self.runtime_stats
        stats.layer_packets += 1
        try:
            layer = decode_layer(packet, image_digest=model.image.digest or bytes(32),
                                 image_shape=model.image.image_shape,
                                 max_packet_bytes=self._frame_limit())
        except ImageMismatch as exc:
            self._wrong_image(exc)
            return
        except Exception as exc:  # ProtocolError, or anything else a packet provokes
            stats.layers_bad += 1
            self._log_limited("bad-layer", f"bad layer dropped: "
                              f"{' '.join(str(exc).split())[:160]} ({stats.layers_bad} so far)")
            return
        bound = max_file_bytes(model.image.image_shape) + self._frame_limit()
        with self._layers_lock:  # chunks held: a file's worth and a frame at most
            self._layers.append(LayerItem(model, layer))
            self._layers_bytes += len(layer.data)
            while self._layers_bytes > bound or len(self._layers) > LAYER_QUEUE:
                self._layers_bytes -= len(self._layers.popleft().packet.data)
                stats.layers_dropped += 1
        self._scores.wake()

    def _frame_limit(self) -> int:
        """The largest frame this device takes (its ``--max-frame``, else its transport's)."""
        transport = getattr(self.link, "transport", None)
        return int(self.config.max_frame_bytes
                   or getattr(transport, "max_frame_bytes", None) or LAYER_MAX_BYTES)

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
            model = self._model
            look = model.look if model is not None and model.base is not None else None
            link.send(m.ViewRequest(phi_deg=view[0], theta_deg=view[1],
                                    sequence=self._sequence, look=look))
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
        elif isinstance(action, CycleLook):
            model = self._model
            if model is not None and model.looks:
                self.show_look((model.look + 1) % len(model.looks))

    def show_look(self, look: int | str) -> bool:
        """Show another look of the image on show (display thread): its model
        (`LoadedModel.for_look`) replaces the old look's whole, at once, and its own frame
        of the view is shown (a served device asks the host for the view in the new look);
        then the old look's model is closed (its warp worker stopped).
        Returns False when there is no image or it has one look.

        Raises
        ------
        ValueError
            No such look.
        """
        model = self._model
        if model is None or model.base is None:
            return False
        index = look_index(model.base, look)
        self.look = model.looks[index]
        if index == model.look:
            return True
        # the new look's first frame first; then its warp worker's thread starts and the
        # old look is closed
        new = model.for_look(index, on_warp=self._scores.wake, start_worker=False)
        with self._decoder_lock:
            if self._decoder_model is model:
                self._decoder_model = new
        self.runtime_stats.look_switches += 1
        self._model = new
        worker = new.warp_worker  # asked for the view's warp: it waits for the frame
        try:
            with worker.display_first() if worker is not None else contextlib.nullcontext():
                self._swap_model(new)
        finally:
            if worker is not None:
                worker.start()
        model.close()
        return True

    def overlay_lines(self) -> list[str]:
        """The overlay's text: the look on show (an image with several), fps, bytes per
        frame, link rate, the current view."""
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
        model = self._model
        looks = ([f"look {model.look_name}  ({model.look + 1}/{len(model.looks)}, l: next)"]
                 if model is not None and model.looks else [])
        return [
            *looks,
            (f"{fps:5.1f} fps" if fps > 0 else " idle    ") + f"   frame {stats.frames_presented}",
            f"{stats.bytes_per_frame():6.0f} B/frame  key {stats.key_frames} "
            f"delta {stats.delta_frames}"
            + (f"  warp {stats.synthesized_frames}" if stats.synthesized_frames else ""),
            f"link {rate / 1024:6.1f} KiB/s  ({mode})",
            f"view phi {phi:6.1f}  theta {theta:5.1f}",
        ]

    def _present(self, model: LoadedModel, y: np.ndarray, info: dict, *,
                 frame: np.ndarray | None = None, settled: bool = False) -> None:
        """Show a frame: ``frame`` as made (an own frame, a corrected frame), else ``y``
        reconstructed (a host's frame). ``settled``: it is the best frame of its view (a
        scripted view moves on)."""
        stats = self.runtime_stats
        t0 = time.perf_counter()
        if frame is None:
            frame = model.reconstructor.update(y)
        t1 = time.perf_counter()
        overlay = self.overlay_lines() if self.presenter.overlay else None
        self.presenter.present(frame, info, overlay_lines=overlay)
        t2 = time.perf_counter()
        now = self.clock()
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
        view = (info.get("phi_deg"), info.get("theta_deg"))
        self._shown_view = view
        shown = model.shown
        if settled or not model.own_frames:
            shown.settled = view
        if "layer" not in info:  # what layers may refine now (a layer keeps its frame's)
            own = info.get("synthesized") or (info.get("predicted")
                                               and model.warp_worker is None)
            shown.base = ((view, int(info.get("frame", 0))) if info.get("corrected")
                          else (view, 0) if own else None)
            if shown.rest is not None and (shown.base is None or shown.rest.view != view
                                           or shown.rest.base_frame != shown.base[1]):
                shown.rest = None
        self._shown_frame = frame
        model.shown.last_y = y
        self._confirm(model)
        if self.on_frame is not None:
            self.on_frame(frame, info)
        if self.max_frames is not None and stats.frames_presented >= self.max_frames:
            self.stop_event.set()

    def run_display(self, stop: threading.Event | None = None) -> None:
        """The display loop (call on the main thread); returns when stopped or finished.

        One `display_turn` after another, waiting in between for a host packet, a warp
        made, or the next tick (ticks of ``1 / fps`` seconds from the loop's start: input is
        read and a moved view's frame made at the start of each). Stops on ``stop`` /
        :attr:`stop_event`, Esc or a closed window, ``max_frames``, or when a finite orbit
        or view script has shown its last view.
        """
        stop_events = [self.stop_event] + ([stop] if stop is not None else [])
        self._tick0 = self.clock()
        self._orbit = (self.orbit_spec.start(self._tick0, phi0_deg=0.0)
                       if self.orbit_spec else None)
        self._waiting_for = None
        item = None
        switch = sys.getswitchinterval()
        # the display's thread takes the interpreter back from the warp worker within a
        # millisecond, not Python's default 5 ms (a third of a board's tick at 3x)
        sys.setswitchinterval(min(switch, SWITCH_INTERVAL_S))
        try:
            while not any(e.is_set() for e in stop_events):
                wait = self.display_turn(item)
                if wait is None:
                    break
                item = self._scores.take(wait)
        finally:
            sys.setswitchinterval(switch)
            self.stop_event.set()

    def display_turn(self, item: ScoreItem | None = None) -> float | None:
        """One turn of the display loop, without waiting: input, a new image, the orbit or
        script, the host packet ``item`` (taken from the slot), the frame the policy picks
        (`FrameScheduler`), the requests due. Returns how long the loop may wait for the
        next packet or warp before the next turn, seconds; None: a finite orbit or script
        is over."""
        worker = self._model.warp_worker if self._model is not None else None
        with worker.display_first() if worker is not None else contextlib.nullcontext():
            return self._turn(item)

    def _turn(self, item: ScoreItem | None) -> float | None:
        """`display_turn`'s work."""
        now = self.clock()
        for action in self.presenter.poll():
            self.apply(action)
        new = self._models.take(0.0)
        if new is not None:
            self._swap_model(new)
        model = self._model
        if model is not None and not self._drive_view(model, now):
            return None
        if item is not None and item.model is model:
            self._show_item(item)
        wait = self.tick_s
        if (model is not None and self._layers and not self._view_dirty
                and self._apply_layer(model)):
            wait = 0.0  # one layer per turn: the next at once, input first
        if model is not None and not self.standalone:
            self._check_layers(model, now)
        if self._view_dirty and model is not None:
            blend_in = self._blend_wait(model, now)
            if blend_in > 0.0:
                wait = blend_in
            else:
                self._view_dirty = False
                self._show_view(model, now)
        elif model is not None and model.shown.warp_due is not None:
            self._show_due_warp(model)
        elif self._redraw and model is not None and model.shown.last_y is not None:
            self._redraw = False
            overlay = self.overlay_lines() if self.presenter.overlay else None
            self.presenter.present(self._shown_frame, None, overlay_lines=overlay)
        elif (self.presenter.overlay and not getattr(self.presenter, "headless", True)
              and model is not None and now - self._overlay_s > 0.25):
            # keep the overlay's numbers fresh a few times a second
            self._overlay_s = now
            self.presenter.present(self._shown_frame if model.shown.last_y is not None
                                   else model.reconstructor.frame, None,
                                   overlay_lines=self.overlay_lines())
        if not self.standalone:
            view = self.limiter.due(now)
            if view is not None:
                self._send_view_request(view, now)
            if self._need_key:
                self._request_keyframe()
            if self.limiter.pending:
                wait = min(wait, self.limiter.min_interval_s)
        return max(0.0, min(wait, self._next_tick(now) - now))

    def _tick_of(self, t: float) -> int:
        """The display tick ``t`` falls in (ticks counted from the loop's start; -inf: before
        any)."""
        if not math.isfinite(t):
            return -(1 << 62)
        return math.floor((t - self._tick0) / self.tick_s)

    def _next_tick(self, now: float) -> float:
        """When the display tick after ``now`` begins."""
        return self._tick0 + (self._tick_of(now) + 1) * self.tick_s

    def _drive_view(self, model: LoadedModel, now: float) -> bool:
        """Move the view along the orbit or script: a ``turn`` follows the clock one tick at
        a time, ``steps`` and scripted views advance once the previous view's best frame is
        on show (`ShownState.settled`). False: the orbit or script is over."""
        orbit = self._orbit
        if orbit is None and not self._script and self._waiting_for is None:
            return True
        if orbit is not None and orbit.spec.kind == "turn":
            # the orbit's view at this tick: steady steps the warp worker can predict
            view = orbit.next_view(self._next_tick(now) - self.tick_s)
            if view is None:
                return False
            if view != self.view:
                self.set_view(*view)
            return True
        if self._waiting_for is None or model.shown.settled == self._waiting_for:
            view = (orbit.next_view(now) if orbit is not None
                    else self._script.popleft() if self._script else None)
            if view is None:
                return False
            self.set_view(*view)
            self._waiting_for = self.view
        return True

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
            "looks": list(model.looks), "look": model.look_name,
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
