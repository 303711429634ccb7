"""``eigencast serve --scores predict``: the device predicts, the host corrects (issue 14).

A device whose image carries the standalone table shows its own prediction of every new
view at once (`device_runtime.prediction`); the host then ray-casts the view, projects it
on the eigenspace (`TrueViewScores`, as ``--scores render`` does), subtracts the device's
prediction (the same `Predictor`, so the same float32 scores bit for bit) and sends the
difference, rate-distortion quantized (`host.fit.rate.rd_quantize` with SSIM cell weights
at ``step_factor`` times the model's score step and ``kappa``: step x2 and kappa 0.15, the
best setting of benchmarks/bench_link.py), as a version-2 score packet with the PREDICTED
base kind. It also codes the full frame (an RD-quantized delta against the last full frame
sent, or a key frame) and sends whichever packet is smaller.

* :class:`CorrectedViews` is `TrueViewScores` that also keeps each view's SSIM cell weights
  (from the ray-cast's image and object mask);
* :class:`CorrectionEncoder` is the `FrameEncoder` of ``predict`` sessions (with
  ``enabled`` off it is a plain `FrameEncoder`, for a device that cannot predict);
* :func:`cannot_predict` reads the device's HELLO_REPLY: why it cannot take corrections,
  or None.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from typing import Any

import numpy as np

from device_runtime.prediction import PREDICTION_PACKET_VERSION, Predictor, corrected
from host.fit.model import HostModel
from host.fit.rate import (
    DEFAULT_CORRECTION_KAPPA,
    DEFAULT_CORRECTION_STEP_FACTOR,
    encode_correction,
    rd_delta,
    ssim_cell_weights,
)
from host.link.serving import SCORE_LEVEL, FrameEncoder
from host.link.true_views import TrueViewScores
from protocol import messages as m
from protocol.scores import EncodedScores, decode_header, encode_scores

__all__ = [
    "DEFAULT_CORRECTION_KAPPA",
    "DEFAULT_CORRECTION_STEP_FACTOR",
    "CorrectedViews",
    "CorrectionEncoder",
    "begin_predict",
    "cannot_predict",
    "model_predictor",
    "predict_encoder",
    "sharpen_at_rest",
]



def model_predictor(model: HostModel) -> Predictor | None:
    """The device's predictor for ``model``'s image, or None when it has no standalone table."""
    from device_runtime.prediction import can_predict

    return Predictor(model.image) if can_predict(model.image) else None


def cannot_predict(hello: m.HelloReply) -> str | None:
    """Why the device of ``hello`` cannot take corrections (one phrase), or None."""
    versions = hello.score_versions or (1,)
    if PREDICTION_PACKET_VERSION not in versions:
        return (f"reads score packets of version {'/'.join(map(str, versions))} only "
                "(an older device)")
    if not hello.predicts:
        return "does not predict (its image has no standalone table, or --no-predict)"
    return None


def predict_encoder(model: HostModel, true_views: TrueViewScores | None,
                    keyframe_interval: int = 0) -> tuple[CorrectedViews, CorrectionEncoder]:
    """The ray-caster and encoder of a ``serve --scores predict`` run.

    Raises
    ------
    ServeError
        The model has no standalone table (one line: refit with ``--standalone``).
    """
    from host.link.errors import ServeError
    from host.link.true_views import open_true_view_scores

    predictor = model_predictor(model)
    if predictor is None:
        raise ServeError(
            f"--scores predict: {model.path or 'the model'} has no standalone score table, so "
            "no device can predict from it; refit it with eigencast fit --standalone")
    if true_views is None:
        true_views = open_true_view_scores(model)
    views = (true_views if isinstance(true_views, CorrectedViews)
             else CorrectedViews(model, true_views.renderer))
    return views, CorrectionEncoder(model, predictor, views=views,
                                    keyframe_interval=keyframe_interval)


def sharpen_at_rest(run: Any, conn: Any, now: float) -> bool | None:
    """``predict`` sessions, no newer request (``_Serving._resting``): once the view on show
    has rested ``refine_delay_s``, its correction is sent again at the model's own score
    step (``fine``), so a resting view is as sharp as today's key frames; the coarse
    corrections (step x2) are what moving views get. True: send the fine frame now; None:
    not yet (waited); False: nothing to sharpen (the caller goes on as for other modes)."""
    shown = run.current
    if (run.scores != "predict" or not getattr(run.encoder, "enabled", False)
            or shown.view is None or shown.scores is None or shown.fine):
        return False
    rest = shown.requested_at + run.settings.refine_delay_s - now
    if rest > 0:
        conn.events.wait(rest)
        return None
    return True


def begin_predict(run: Any, hello: m.HelloReply) -> None:
    """At the start of a ``predict`` session (``host.link.serving._Serving._begin``): send
    corrections if the device predicts, else say why in one line and serve ``motion``
    (today's default) to it; a later session with a device that predicts corrects again."""
    encoder = run.encoder
    why = cannot_predict(hello)
    encoder.enabled = why is None
    if why is None:
        if run.scores != "predict":
            run.say(f"device '{hello.device_id}' predicts: sending corrections again")
        run.scores, run.motion = "predict", None  # no sparse refinements between corrections
        return
    if encoder.fallback is None:
        from host.fit.motion import MotionScores

        encoder.fallback = MotionScores(encoder.model, run.true_views.renderer)
    run.motion = encoder.fallback
    run.motion.budget_s = run.pace.budget_s
    if run.scores == "predict":
        run.say(f"device '{hello.device_id}' {why}: sending motion scores instead of "
                "corrections")
    run.scores = "motion"


class CorrectedViews(TrueViewScores):
    """`TrueViewScores` that also keeps each ray-cast view's SSIM cell weights.

    ``views(view)`` is the projection (float32 (K,)); ``views.weights(view)`` the
    `host.fit.rate.ssim_cell_weights` of the same ray-cast (its image and alpha mask), which
    the correction's RD quantizer uses.
    """

    def __init__(self, model: HostModel, renderer: Any, *, cache: int = 64) -> None:
        super().__init__(model, renderer, cache=cache)
        self._weights: OrderedDict[tuple[float, float], np.ndarray] = OrderedDict()

    def __call__(self, view: tuple[float, float]) -> np.ndarray:
        """Float32 scores (K,) of ``view`` (canonical); its weights are kept beside them."""
        from host.render.settings import OBJECT_ALPHA_MIN

        key = (float(view[0]), float(view[1]))
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None and key in self._weights:
                self._cache.move_to_end(key)
                return hit
        t0 = time.perf_counter()
        rgb, alpha = self.renderer.render(*key)
        y = self.model.project(rgb)
        w = ssim_cell_weights(rgb, self.model.image.cell_shape,
                              np.asarray(alpha) >= OBJECT_ALPHA_MIN)
        with self._lock:
            self.renders += 1
            self.render_seconds += time.perf_counter() - t0
            self._cache[key], self._weights[key] = y, w
            while len(self._cache) > self._size:
                old, _ = self._cache.popitem(last=False)
                self._weights.pop(old, None)
        return y

    def weights(self, view: tuple[float, float]) -> np.ndarray | None:
        """The SSIM cell weights of a view ray-cast by this object (None if not cached)."""
        with self._lock:
            return self._weights.get((float(view[0]), float(view[1])))


class CorrectionEncoder(FrameEncoder):
    """The packets of a ``predict`` session: a correction to the device's prediction, or the
    full frame when that is smaller.

    Parameters
    ----------
    model : HostModel
        Fitted ``--standalone`` (its table is the device's).
    predictor : Predictor
        `model_predictor` of ``model``.
    views : CorrectedViews, optional
        Gives the SSIM weights of the views whose projections ``encode`` receives (None:
        unweighted).
    step_factor, kappa : float
        The correction's (and the full frame's) step, in model score steps, and RD factor.
    keyframe_interval, level, first_frame
        As `FrameEncoder` (they apply while ``enabled`` is off).

    Attributes
    ----------
    enabled : bool
        The device predicts (set per session from its HELLO_REPLY); off, this is a plain
        `FrameEncoder`.
    last_kind : {"key", "delta", "correction"}
        What the last packet was.
    """

    def __init__(self, model: HostModel, predictor: Predictor, *,
                 views: CorrectedViews | None = None,
                 step_factor: float = DEFAULT_CORRECTION_STEP_FACTOR,
                 kappa: float = DEFAULT_CORRECTION_KAPPA, keyframe_interval: int = 0,
                 level: int = SCORE_LEVEL, first_frame: int | None = None) -> None:
        super().__init__(model, keyframe_interval=keyframe_interval, level=level,
                         first_frame=first_frame)
        if not (step_factor > 0 and np.isfinite(step_factor)):
            raise ValueError(f"step_factor={step_factor} must be > 0")
        if not (kappa >= 0 and np.isfinite(kappa)):
            raise ValueError(f"kappa={kappa} must be >= 0")
        self.predictor = predictor
        self.views = views
        self.step = float(model.score_step * step_factor)
        self.kappa = float(kappa)
        self.enabled = True
        self.fallback: Any = None  # the motion source of sessions with a device that cannot
        self.last_kind = "key"
        self._full: EncodedScores | None = None  # the last full frame sent (delta base)
        self._full_y: np.ndarray | None = None

    def reset(self) -> None:
        """A new session: the next full frame is a key frame."""
        super().reset()
        self._full, self._full_y = None, None

    def encode(self, view: tuple[float, float], *, key: bool = False,
               scores: np.ndarray | None = None, fine: bool = False) -> EncodedScores:
        """The packet for ``view`` (canonical) whose true scores are ``scores`` (the
        projection of a fresh ray-cast): the correction, or the full frame when smaller.

        ``fine``: the view has come to rest, so quantize at the model's own score step by
        plain rounding (the quality of today's key frames) instead of ``step_factor`` and
        ``kappa`` (`sharpen_at_rest`). Without ``scores`` (nothing ray-cast) or while
        ``enabled`` is off this is `FrameEncoder.encode`."""
        if not self.enabled or scores is None:
            encoded = super().encode(view, key=key, scores=scores)
            self.last_kind = "key" if self.last_was_key else "delta"
            return encoded
        frame = self.next_frame
        if frame > 0xFFFFFFFF:
            frame, self._full = 1, None
        self.next_frame = frame + 1
        model = self.model
        s = float(model.score_step) if fine else self.step
        weights = None if self.views is None else self.views.weights(view)
        rd = {"step": s, "kappa": 0.0 if fine else self.kappa, "weights": weights}
        y = np.asarray(scores, dtype=np.float64)
        prediction = self.predictor(*view)
        common = {"step": s, "frame": frame, "view": view, "image_digest": model.digest,
                  "level": self.level, "n_components": model.image.n_components}
        correction = encode_correction(model, y, prediction, view, frame=frame,
                                       level=self.level, **rd)
        base = None if key else self._full
        if base is not None and not (np.ndim(base.step) == 0
                                     and math.isclose(float(base.step), s, rel_tol=1e-6)):
            base = None  # a fine frame after coarse ones (or back): steps differ, no delta
        full_y = rd_delta(model, y, None if base is None else self._full_y, **rd)
        full = encode_scores(full_y, base=base, **common)
        if len(full.packet) < len(correction.packet):
            self._full, self._full_y = full, full_y.astype(np.float64)
            self.last_was_key = base is None
            self.last_kind = "key" if base is None else "delta"
            return full
        self.last_was_key = False
        self.last_kind = "correction"
        return correction

    def shown(self, encoded: EncodedScores, view: tuple[float, float]) -> np.ndarray:
        """The scores (K,) float32 a predicting device shows for a packet of this encoder.

        A correction is added to the prediction exactly as the device adds it
        (`device_runtime.prediction.corrected` of the packet's float32 values)."""
        step = np.asarray(encoded.step, dtype=np.float32)
        y = (encoded.q.astype(np.float32) * step).astype(np.float32)
        if decode_header(encoded.packet).is_predicted:
            return corrected(self.predictor(*view), y)
        return y
