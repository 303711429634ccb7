"""Which frame the display presents: one policy for standalone and served devices.

`FrameScheduler` is mixed into `device_runtime.runtime.RuntimeDevice` (as `ImageReceiver`
is into `Device`) and runs on the display thread only. Each turn of the display loop it
presents the best frame ready for the view on show, and never waits for a warp:

1. the view moved: the view's warp if the worker made it already (warped ahead along
   steady motion), else the blend of the device's own scores of the view (at most one
   blend per display tick; the worker is asked for the warp), else, with no table, the
   last frame while the host is asked;
2. the worker made the warp of the view on show: the warp replaces the blend (a
   correction that came first is applied to it);
3. a host packet for the view on show: a correction of the device's own frame, shown at
   once when that frame is at hand, else once its warp is made; a full frame; a
   host-driven one (``serve --orbit``) moves the view.

The warp is made on the image's `WarpWorker` whatever the device's mode; a standalone
device at rest shows the view's warp, bit for bit `eigencast view`'s frame. Everything the
policy remembers about an image is in its `LoadedModel` (``model.shown``), replaced whole
when another image is activated.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from device_runtime.layers import LayerError, RestFrame, decode_file
from device_runtime.loaded import LoadedModel, ScoreItem
from device_runtime.prediction import corrected
from protocol.errors import ProtocolError

__all__ = ["LAYER_RETRY_S", "FrameScheduler"]

#: Shortest time between two requests of the view on show after a layer of it was lost.
LAYER_RETRY_S = 2.0


class FrameScheduler:
    """The display's frame policy (a mixin of `RuntimeDevice`; display thread only).

    Uses the runtime's ``view``, ``standalone``, ``presenter``, ``runtime_stats``,
    ``limiter``, ``tick_s``, ``clock`` and ``_present``.
    """

    view: tuple[float, float]
    standalone: bool
    tick_s: float
    _model: LoadedModel | None

    # ------------------------------------------------------------------ the view moved
    def _blend_wait(self, model: LoadedModel, now: float) -> float:
        """Seconds until the display may make the next blend of a moved view (0: now): one
        per display tick, so a view that moves on every turn of the loop (a drag, a
        clock-driven orbit) leaves the core to the warp worker and the link."""
        if not model.own_frames or self._tick_of(model.shown.blend_s) < self._tick_of(now):
            return 0.0
        return max(0.0, self._next_tick(now) - now)

    def _show_view(self, model: LoadedModel, now: float) -> None:
        """The view moved: its warp when the worker made it ahead, else its blend (the warp
        asked of the worker, shown by `_show_due_warp`), else nothing new while the host is
        asked; a served device asks the host for the view."""
        shown = model.shown
        shown.warp_due = None
        if shown.correction_due is not None:  # its view was left before its warp was made
            self.runtime_stats.stale_dropped += 1
            shown.correction_due = None
        worker = model.warp_worker
        if model.own_frames:
            made = None
            if worker is not None:
                worker.request(self.view)
                made = worker.take(self.view)
            if made is not None:
                shown.own_warp = (self.view, made)
                self._present_own(model, warped=made)
            else:
                shown.blend_s = now
                self._present_own(model)
                if worker is not None:
                    shown.warp_due = self.view
        if not self.standalone:
            self.limiter.offer(self.view)

    def _show_due_warp(self, model: LoadedModel | None, timeout_s: float = 0.0) -> None:
        """Replace the blend on show by the warp of its view once the worker has made it,
        unless the view moved on (or a host frame for it came) since the blend was shown."""
        if model is None:
            return
        shown = model.shown
        due = shown.warp_due
        if due is None or model.warp_worker is None:
            shown.warp_due = None
            return
        if due != self.view or self._view_dirty:
            shown.warp_due = None  # the user has moved on: a newer blend comes first
            return
        frame = model.warp_worker.take(due, timeout_s)
        if frame is None:
            return  # not made yet: the worker wakes the display when it is
        shown.warp_due = None
        shown.own_warp = (due, frame)
        item = shown.correction_due
        if item is not None and (item.scores.phi_deg, item.scores.theta_deg) == due:
            shown.correction_due = None
            self._show_corrected(item, frame)  # the host's correction came first
            return
        self._present_own(model, warped=frame)

    def _present_own(self, model: LoadedModel, *, warped: np.ndarray | None = None) -> None:
        """Show the device's own frame of the current view (no bytes, no latency): its
        blend, or ``warped`` (the worker's warp of the neighbours). The scores kept (a
        correction adds to them) are the device's own scores either way, the same on both
        sides (`device_runtime.prediction`)."""
        y = model.own_scores(self.view)
        info = {"phi_deg": self.view[0], "theta_deg": self.view[1], "key": self.standalone,
                "predicted": not self.standalone}
        if warped is None:
            self.runtime_stats.predicted_frames += 1
            frame = model.reconstructor.update(y)
            settled = model.warp_worker is None
        else:
            # a frame of its own, not the reconstructor's buffer: the reconstructor only
            # recomputes the cells whose scores changed, so the next blend or host frame
            # needs its buffer to still hold the last reconstruction
            info["synthesized"] = True
            self.runtime_stats.synthesized_frames += 1
            frame = warped
            settled = True
        self._present(model, y, info, frame=frame, settled=settled)

    # ------------------------------------------------------------------ host packets
    def _show_item(self, item: ScoreItem) -> None:
        """A decoded host packet for the image on show: a correction of the device's own
        frame (`_correct`) or a full frame, unless stale. A frame that cannot be shown is
        skipped and counted; the device goes on."""
        d = item.scores
        if self._keeps_exact(item.model, (d.phi_deg, d.theta_deg)):
            return
        try:
            if d.synthesized:
                self._correct(item)
                return
            y = self._shown_scores(item)
            if y is None:
                return
            self._present(item.model, y, {
                "frame": d.frame, "phi_deg": d.phi_deg, "theta_deg": d.theta_deg,
                "key": d.is_key, "packet_bytes": d.packet_bytes, "sequence": item.sequence,
                "decode_s": 0.0, "corrected": d.predicted,
            }, settled=True)
            if (d.phi_deg, d.theta_deg) == self.view:
                item.model.shown.warp_due = None  # the host's frame is the newer one
        except Exception as exc:
            # A frame that cannot be shown must not stop the device: skip it.
            self._frame_failed(d.frame, exc)

    def _correct(self, item: ScoreItem) -> None:
        """A correction of the device's own frame of the packet's view (version 3): show
        that frame corrected, at once when the frame is at hand (a blend, or the warp made
        already), else once the warp worker has made it (`_show_due_warp`). A correction for
        a view the user has left is dropped; a host-driven one (sequence 0: ``serve
        --orbit``) moves the view."""
        d, model = item.scores, item.model
        shown = model.shown
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
            synth = (None if shown.synth_view == view
                     else model.reconstructor.update(model.own_scores(view)))
            self._show_corrected(item, synth)
        elif shown.synth_view == view:
            self._show_corrected(item, None)
        elif shown.own_warp is not None and shown.own_warp[0] == view:
            self._show_corrected(item, shown.own_warp[1])
        else:  # the warp of the view is not made yet: show it corrected once it is
            if shown.correction_due is not None:  # a newer one replaces it, never shown
                self._superseded += 1
            shown.correction_due = item
            if shown.warp_due != view:
                model.warp_worker.request(view)
                shown.warp_due = view

    def _show_corrected(self, item: ScoreItem, synth: np.ndarray | None) -> None:
        """Present ``synth`` (None: the one the display reconstructor holds) corrected by
        the packet's scores (`Reconstructor.correct`)."""
        d, model = item.scores, item.model
        view = (d.phi_deg, d.theta_deg)
        t0 = time.perf_counter()
        frame = model.reconstructor.correct(d.y, synth)
        self.runtime_stats.correct_s.add(time.perf_counter() - t0)
        model.shown.synth_view = view
        self.runtime_stats.corrected_frames += 1
        if model.shown.warp_due == view:
            model.shown.warp_due = None  # the corrected frame is the newer one
        self._present(model, d.y, {
            "frame": d.frame, "phi_deg": d.phi_deg, "theta_deg": d.theta_deg, "key": False,
            "packet_bytes": d.packet_bytes, "sequence": item.sequence, "decode_s": 0.0,
            "corrected": True}, frame=frame, settled=True)

    def _shown_scores(self, item: ScoreItem) -> np.ndarray | None:
        """The scores to show for a full or version-2 packet, or None when it is stale.

        A device that predicts shows a packet answering a view request (sequence > 0) only
        while its view is still the one on show (else its own frame already shows a newer
        view); a version-2 correction is added to the prediction of the packet's view.
        Host-driven packets (sequence 0: ``serve --orbit``) are shown whatever the view.
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

    # ------------------------------------------------------------------ layers at rest
    def _apply_layer(self, model: LoadedModel) -> bool:
        """Join the queued chunks of the refinement layers that belong to the frame on show,
        and apply the next whole one (one decode per turn: it costs about half a blend);
        drop chunks of another view or frame, keep those whose correction waits for its
        warp. True: a layer was applied."""
        stats = self.runtime_stats
        while True:
            with self._layers_lock:
                if not self._layers:
                    return False
                item = self._layers[0]
                chunk = item.packet
                rest, wait = self._rest_for(model, item)
                if rest is None:
                    if wait:  # its frame is being made (a warp, a correction waiting for it)
                        return False
                    self._layers_bytes -= len(self._layers.popleft().packet.data)
                    stats.layers_dropped += 1
                    continue
                self._layers_bytes -= len(self._layers.popleft().packet.data)
            model.shown.layers_heard = (self.view, self.clock())
            if not rest.accepts(chunk):  # a layer before it was lost or dropped
                stats.layers_dropped += 1
                continue
            try:
                data = model.shown.assembly.add(chunk)
            except ProtocolError:  # a chunk lost: this layer cannot be joined
                stats.layers_dropped += 1
                self._ask_again()
                continue
            if data is None:
                continue  # more chunks to come
            t0 = time.perf_counter()
            try:
                pixels = decode_file(data, chunk.codec, rest.frame.shape[:2],
                                     row0=chunk.row0 if chunk.strip else None)
            except LayerError as exc:
                stats.layers_bad += 1
                self._frame_failed(chunk.frame, exc)
                self._ask_again()
                continue
            rest.apply(chunk, pixels)
            stats.layer_s.add(time.perf_counter() - t0)
            stats.layers_applied += 1
            stats.exact_frames += rest.is_exact
            self._present(model, model.shown.last_y, {
                "frame": chunk.frame, "phi_deg": chunk.phi_deg, "theta_deg": chunk.theta_deg,
                "key": False, "packet_bytes": chunk.packet_bytes, "sequence": 0,
                "layer": chunk.layer, "exact": rest.is_exact, "base_frame": chunk.base_frame},
                frame=rest.frame, settled=True)
            return True

    def _check_layers(self, model: LoadedModel, now: float) -> None:
        """Layers of the resting view on show came, but the host's last planned one has not
        for `LAYER_RETRY_S` (a chunk lost on the line, none left to notice it by): ask for
        the view again."""
        shown = model.shown
        heard = shown.layers_heard
        if heard is None or heard[0] != self.view or self._view_dirty or self._layers:
            return
        rest = shown.rest
        if rest is not None and rest.view == self.view and rest.finished:
            return
        if now - heard[1] >= LAYER_RETRY_S:
            shown.layers_heard = (heard[0], now)
            self._ask_again()

    def _ask_again(self) -> None:
        """A layer of the view on show was lost on the way: ask the host for the view again
        (a served device; at most once every `LAYER_RETRY_S`), which sends its layers
        again, so a noisy line still ends at the exact frame."""
        now = self.clock()
        if self.standalone or now - self._asked_again_s < LAYER_RETRY_S:
            return
        self._asked_again_s = now
        self.runtime_stats.layer_retries += 1
        self.limiter.offer(self.view)

    def _rest_for(self, model: LoadedModel, item: Any) -> tuple[RestFrame | None, bool]:
        """The resting frame ``item``'s layer refines, and whether to wait for it: the one
        being refined; else for base frame 0 the device's own frame of the view (its warp,
        or its blend), for another base the frame on show when it is that correction's.
        (None, True): that frame is still being made; (None, False): the layer belongs to
        no frame the device shows or will show."""
        layer = item.packet
        view = (layer.phi_deg, layer.theta_deg)
        shown = model.shown
        if item.model is not model or view != self.view or self._view_dirty:
            return None, False
        rest = shown.rest
        if rest is not None and rest.view == view and rest.base_frame == layer.base_frame:
            return rest, False
        if layer.base_frame == 0:
            own = self._own_frame(model, view)
            if own is None:
                return None, shown.warp_due == view
            shown.rest = RestFrame(view, 0, own)
            return shown.rest, False
        if shown.base == (view, layer.base_frame) and self._shown_frame is not None:
            shown.rest = RestFrame(view, layer.base_frame, self._shown_frame)
            return shown.rest, False
        due = shown.correction_due
        return None, due is not None and due.scores.frame == layer.base_frame

    def _own_frame(self, model: LoadedModel, view: tuple[float, float]) -> np.ndarray | None:
        """The device's own frame of ``view``: the warp made for it, or (an image without
        depth) the blend of its own scores; None while the warp is not made."""
        if model.warp_worker is None:
            return model.reconstructor.update(model.own_scores(view))
        own = model.shown.own_warp
        return own[1] if own is not None and own[0] == view else None

    def _keeps_exact(self, model: LoadedModel, view: tuple[float, float]) -> bool:
        """The view's exact frame is on show: a host frame of it must not replace it."""
        rest = model.shown.rest
        if rest is not None and rest.view == view and rest.is_exact:
            self.runtime_stats.kept_exact += 1
            return True
        return False

    # ------------------------------------------------------------------ a new image
    def _swap_model(self, model: LoadedModel) -> None:
        """Show another image: the old one (and all the display made of it) is closed and
        replaced whole; the new one's first frame is its own frame of the view (standalone,
        or a predicting device while the host is asked), else its mean image."""
        old = self._model
        self._model = model
        if old is not None and old is not model:
            old.close()
        resize = getattr(self.presenter, "set_image_shape", None)
        if resize is not None:
            resize(model.image.image_shape)
        if model.own_frames:
            self._show_view(model, self.clock())
        else:  # the image's own first frame (the mean), while the host is asked for the view
            y = np.zeros(model.image.n_coefficients, dtype=np.float32)
            self._present(model, y, {"frame": 0})
            self.limiter.offer(self.view)

    def _present(self, model: LoadedModel, y: np.ndarray, info: dict, *,
                 frame: np.ndarray | None = None, settled: bool = False) -> None:
        raise NotImplementedError  # RuntimeDevice's

    def _frame_failed(self, frame: int, exc: BaseException) -> None:
        raise NotImplementedError  # RuntimeDevice's

    # attributes RuntimeDevice provides
    _layers: Any
    _layers_bytes: int
    _layers_lock: Any
    _asked_again_s: float
    _shown_frame: Any
    presenter: Any
    runtime_stats: Any
    limiter: Any
    _view_dirty: bool
    _superseded: int

    def clock(self) -> float:  # RuntimeDevice's (monotonic seconds)
        raise NotImplementedError

    def _tick_of(self, t: float) -> int:  # RuntimeDevice's
        raise NotImplementedError

    def _next_tick(self, now: float) -> float:  # RuntimeDevice's
        raise NotImplementedError
