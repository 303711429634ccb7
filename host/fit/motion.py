"""Frames within a deadline while the view moves: what ``serve`` sends (issue 13; with the
device's own frames, corrections of them, issue 23).

`MotionScores` makes the scores of each frame from a *sparse* ray-cast of the true view, as
dense as the frame's time budget allows:

* **Moving.** Each new view ray-casts every ``s``-th pixel in both directions (offset
  (0, 0)) and recovers the scores per cell (`host.fit.SparseRecovery`, cached factors per
  stride). ``s`` is the smallest of `DEFAULT_STRIDES` whose measured cost fits the budget
  (``BUDGET_SHARE`` of ``budget_s``); stride 1 is a full ray-cast and sends
  `HostModel.project` of it. The prior is the interpolated scores, or the previous frame's
  when the view moved less than ``prior_switch_deg`` since it (slow drags: docs/
  design-notes.md, "Sparse ray-casts while moving").
* **Resting.** `refine` continues a view that was not replaced: each step ray-casts as many
  of the missing pixels as fit the budget, towards the next denser stride; once that
  stride's grid is complete its recovered scores are sent (cached factors, ~1 ms), and
  with the last pixel `HostModel.project` of the assembled full ray-cast: the frame is then
  exactly the projection of the view's ray-cast. (`host.fit.ProgressiveRecovery`'s
  per-offset accumulation was measured too slow for this: a solve per cell per offset,
  13-45 s to the projection from stride 16 at 256.)

Corrections of the device's own frame (issue 23): given ``own`` (the device's synthesis,
`device_runtime.prediction.OwnFrames`, the same code the device runs), a frame is not the
view's scores but the *correction* of the frame ``S`` the device made itself: the sparse
samples' residual ``x_S - S_S`` is recovered with prior zero
(`SparseRecovery.recover_residual`), so no samples means no change, and the complete
frame is ``project(x) - project(S)``, the correction that makes ``S`` the closest frame to
the view the eigenspace can hold. The residual's prior (per-component variance, and λ, the
residual's power outside the eigenspace) is `ResidualPrior`, measured.

The cost model is measured, not assumed: the seconds per frame at the two strides used
last (ray-cast and recovery, exponential averages) give a fixed cost and a cost per ray,
which predict the other strides. A slower host (or a larger model) therefore gets sparser
frames, never later ones.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.errors import EigencastError
from host.fit.recover import DEFAULT_LAMBDA, SamplePattern, SparseRecovery

#: A pixel of a frame whose largest channel is above this (0..255) shows the object (the
#: renderings have a black background; `device_runtime.synthesis.OBJECT_LEVEL`).
_OBJECT_LEVEL = 2

__all__ = [
    "BUDGET_SHARE",
    "CORRECTION_STRIDES",
    "DEFAULT_COARSE",
    "DEFAULT_MOTION_FPS",
    "DEFAULT_STRIDES",
    "PRIOR_SWITCH_DEG",
    "PROBE_EVERY",
    "MotionFrame",
    "MotionScores",
    "ResidualPrior",
    "angle_between",
]

#: Strides a moving frame may use (1: a full ray-cast, the projection itself). Sparser
#: grids were measured to do worse than the interpolated prior alone (tooth at 256, cells
#: 16: strides 12 and 16 lose 10 % of the gap).
DEFAULT_STRIDES = (1, 2, 3, 4, 6, 8)
#: Strides a moving *correction* of the device's own frame may use. Sparser ones gain
#: nothing over the warp the device already shows (stride 8 on eight shared volumes: mean
#: object SSIM gain -0.0005 to +0.0004, five of eight at or below zero; stride 4: -0.0003 to
#: +0.0044), so a host that cannot afford stride 4 sends nothing while the view moves (the
#: device's own frame stands) and corrects it completely at rest.
CORRECTION_STRIDES = (1, 2, 3, 4)
#: When not even the sparsest stride fits, moving frames send the prior alone (no ray), but
#: every this many frames one is ray-cast anyway to measure the host again.
PROBE_EVERY = 8
#: Below this angle between successive frames the previous frame's scores are the prior.
PRIOR_SWITCH_DEG = 0.5
#: Share of the frame budget a frame's ray-cast and recovery may take (the rest: encoding,
#: the link, the scheduler).
BUDGET_SHARE = 0.8
#: Moving frames' sample-step factor (`Renderer.coarser`): half the samples per ray, a mean
#: pixel difference of 0.4 (of 255) on the tooth at 256 (1000 samples).
DEFAULT_COARSE = 2.0
#: The frame rate the budget aims at when neither ``--fps`` nor the link sets one.
DEFAULT_MOTION_FPS = 30.0
_EMA = 0.3


def angle_between(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Great-circle angle in degrees between two views ``(phi, theta)`` (degrees)."""
    def unit(view: tuple[float, float]) -> np.ndarray:
        phi, theta = math.radians(view[0]), math.radians(view[1])
        return np.array([math.cos(theta) * math.cos(phi), math.cos(theta) * math.sin(phi),
                         math.sin(theta)])

    c = float(np.clip(unit(a) @ unit(b), -1.0, 1.0))
    return math.degrees(math.acos(c))


class ResidualPrior:
    """The statistics of a correction of the device's own frame: the MAP prior of the sparse
    recovery (`SparseRecovery.recover_residual`).

    The device's synthesis (a warp or blend of its neighbouring training views) already
    gets a cell's leading components nearly right; what it misses lives in the later ones.
    So a correction's component of rank ``r`` in its cell (0 the leading one) has variance
    ``eigenvalue * clip((r + 0.5) / RANK_SCALE, RATIO_FLOOR, 1)``, and the residual outside
    the eigenspace (the noise the samples carry) variance `LAMBDA` per value.

    Measured (docs/design-notes.md, "Serving"; 12 views each of the tooth and the head
    at 256): the median of (correction component)**2 / eigenvalue is 0.001-0.002 at rank 0,
    0.01 at ranks 2-3, 0.07-0.09 at 8-15, 0.16 at 16-31, 0.29-0.32 at 32-63 and 0.49-0.54
    beyond, on both volumes; with this prior the sparse correction gains at every stride
    (head +0.040 / +0.012 / +0.003 object SSIM over the warp at strides 2 / 4 / 8, tooth
    +0.013 / +0.003 / +0.000), where the views' own eigenvalues as the prior make strides
    3-8 worse than no correction, and it does as well as the variance learned from the 12
    views themselves. The recovery depends only on ``LAMBDA / variance``.
    """

    #: A component of rank ``r`` varies ``(r + 0.5) / RANK_SCALE`` of its eigenvalue.
    RANK_SCALE = 160.0
    #: ... but at least this fraction.
    RATIO_FLOOR = 0.002
    #: The residual's power outside the eigenspace, squared levels per value.
    LAMBDA = 100.0

    def __init__(self, eigenvalues: np.ndarray, n_components: np.ndarray) -> None:
        ev = np.maximum(np.asarray(eigenvalues, dtype=np.float64), 0.0)
        counts = np.asarray(n_components, dtype=np.int64)
        rank = np.concatenate([np.arange(c) for c in counts]) if counts.size else np.zeros(0)
        if rank.shape != ev.shape:
            raise ValueError(f"ResidualPrior: {ev.size} eigenvalues for {rank.size} components")
        self.variance = ev * np.clip((rank + 0.5) / self.RANK_SCALE, self.RATIO_FLOOR, 1.0)
        self.lam = self.LAMBDA

    @classmethod
    def for_model(cls, model: Any) -> ResidualPrior:
        """From the model's annexed eigenvalues (else its training scores' variance)."""
        ev = (model.eigenvalues if model.eigenvalues is not None else
              np.asarray(model.training_scores, dtype=np.float64).var(axis=0, ddof=1))
        return cls(ev, model.image.n_components)


@dataclass
class MotionFrame:
    """One frame's scores and how they were made.

    Attributes
    ----------
    scores : ndarray of shape (K,), float32, or None
        None: a resting view's step that only ray-cast more pixels (nothing new to send).
    stride : int
        Of the sample grid (1: full ray-cast; 0: none fitted the budget, the scores are the
        prior's).
    pixels : int
        Rays cast for this frame.
    seconds : float
        Host time for the frame (ray-cast and recovery).
    prior : str
        ``"interpolated"``, ``"previous"`` (moving frames) or ``"progressive"`` (a resting
        view's refinement).
    complete : bool
        The scores are `HostModel.project` of the full ray-cast.
    weights : ndarray of shape (n_cells,), or None
        Corrections: the SSIM cell weights of the best image of the view at hand (the
        ray-cast when complete, else the device's own frame) for the quantizer.
    """

    scores: np.ndarray | None
    stride: int
    pixels: int
    seconds: float
    prior: str
    complete: bool
    weights: np.ndarray | None = None


class MotionScores:
    """Scores of views from sparse ray-casts that fit a frame budget (module docstring).

    Parameters
    ----------
    model : HostModel
    renderer : host.render.settings.ViewRenderer
        The model's recorded render settings and volume.
    budget_s : float
        Seconds per frame (`serve` updates it from ``--fps`` and the link's measured rate).
    lam : float
        λ of the recovery.
    strides : sequence of int, optional
        Candidate strides for moving frames (sorted; 1 means a full ray-cast). Default
        `DEFAULT_STRIDES`, with ``own`` `CORRECTION_STRIDES`.
    prior_switch_deg : float
        Use the previous frame's scores as the prior below this angle per frame.
    coarse : float
        Moving frames sample their rays ``coarse`` times farther apart
        (`Renderer.coarser`; 1: the training database's exact renderer; default
        `DEFAULT_COARSE`). Resting views are always refined with the exact one.
    clock : callable
        Seconds (monotonic); tests pass a fake one.
    own : device_runtime.prediction.OwnFrames, optional
        The device's own frames: frames are then *corrections* of them (module docstring),
        whose prior is ``prior``.
    prior : ResidualPrior, optional
        Default: `ResidualPrior.for_model` (with ``own`` only).

    Attributes
    ----------
    frames, refinements, pixels : int
        Moving frames and resting refinement steps made, rays cast.
    seconds : float
        Host time spent on them.
    stride_frames : dict
        Moving frames per stride.
    """

    def __init__(self, model: Any, renderer: Any, *, budget_s: float = 1.0 / DEFAULT_MOTION_FPS,
                 lam: float = DEFAULT_LAMBDA, strides: tuple[int, ...] | None = None,
                 prior_switch_deg: float = PRIOR_SWITCH_DEG, coarse: float = DEFAULT_COARSE,
                 clock: Callable[[], float] = time.perf_counter, own: Any = None,
                 prior: ResidualPrior | None = None) -> None:
        h, w = (int(v) for v in model.image.image_shape)
        if tuple(renderer.image_shape) != (h, w):
            raise EigencastError(
                f"the renderer makes {renderer.image_shape[1]}x{renderer.image_shape[0]} "
                f"images, the model is {w}x{h}")
        if strides is None:
            strides = DEFAULT_STRIDES if own is None else CORRECTION_STRIDES
        strides = tuple(sorted({int(s) for s in strides}))
        if not strides or strides[0] < 1:
            raise ValueError(f"strides={strides}: positive integers expected")
        if not (coarse >= 1.0 and math.isfinite(coarse)):
            raise ValueError(f"coarse={coarse} must be >= 1")
        if not budget_s > 0:
            raise ValueError(f"budget_s={budget_s} must be > 0")
        self.model = model
        self.renderer = renderer
        self.shape = (h, w)
        self.budget_s = float(budget_s)
        self.strides = strides
        self.prior_switch_deg = float(prior_switch_deg)
        self.coarse = float(coarse)
        self.clock = clock
        self.own = own
        self.prior = None
        if own is not None:
            self.prior = prior if prior is not None else ResidualPrior.for_model(model)
            self.recovery = SparseRecovery(model, lam=self.prior.lam,
                                           variance=self.prior.variance,
                                           max_patterns=4 * len(strides))
        else:
            self.recovery = SparseRecovery(model, lam=lam, max_patterns=4 * len(strides))
        self._patterns = {s: SamplePattern.strided(w, h, s) for s in strides}
        self._times: dict[int, float] = {}  # seconds per frame at each stride, EMA
        self._recent: list[int] = []  # strides measured, the most recent last
        self._moving = (renderer.renderer if coarse == 1.0
                        else renderer.renderer.coarser(coarse))
        self._view: tuple[float, float] | None = None
        self._scores: np.ndarray | None = None
        self._prior: np.ndarray | None = None
        self._stride = 1
        self._complete = False
        self._skipped = 0
        self._synth: np.ndarray | None = None  # corrections: the device's frame of the view
        self._image = np.zeros((h, w, 3), dtype=np.uint8)  # the view's ray-cast pixels
        self._known = np.zeros((h, w), dtype=bool)  # ... those cast exactly
        self.frames = self.refinements = self.pixels = 0
        self.seconds = 0.0
        self.stride_frames: dict[int, int] = {}

    # ------------------------------------------------------------------ cost model
    def _n_pixels(self, stride: int) -> int:
        h, w = self.shape
        return (-(-h // stride)) * (-(-w // stride))

    def _fit(self) -> tuple[float, float]:
        """``(fixed, per_ray)`` seconds: the line through the two strides measured last
        (through 0 when only one was, or when they disagree)."""
        last = self._recent[-1]
        n1, t1 = self._n_pixels(last), self._times[last]
        if len(self._recent) >= 2:
            other = self._recent[-2]
            n0, t0 = self._n_pixels(other), self._times[other]
            per_ray = (t1 - t0) / (n1 - n0)
            fixed = t1 - per_ray * n1
            if per_ray > 0 and fixed >= 0:
                return fixed, per_ray
        return 0.0, t1 / n1

    def estimate(self, stride: int) -> float:
        """Expected seconds of a frame at ``stride`` (0 before anything was measured)."""
        if not self._recent:
            return 0.0
        fixed, per_ray = self._fit()
        return fixed + per_ray * self._n_pixels(stride)

    def _measured(self, stride: int, seconds: float) -> None:
        if stride in self._times and self._recent[-1] == stride:
            seconds = (1 - _EMA) * self._times[stride] + _EMA * seconds
        self._times[stride] = seconds
        if stride in self._recent:
            self._recent.remove(stride)
        self._recent.append(stride)

    def choose_stride(self) -> int:
        """The densest stride whose estimated cost fits ``BUDGET_SHARE * budget_s``; the
        sparsest before the first measurement; 0 (no ray: the prior alone) when none fits,
        except every `PROBE_EVERY`-th such frame, which re-measures the sparsest."""
        if not self._recent:
            return self.strides[-1]
        room = BUDGET_SHARE * self.budget_s
        for s in self.strides:
            if self.estimate(s) <= room:
                return s
        return self.strides[-1] if self._skipped + 1 >= PROBE_EVERY else 0

    def prepare(self) -> None:
        """Compute the recovery factors of every stride and the model's projection now (not
        during the first frames: together 1-2 s at 256 on 2 cores, which a first resting
        view would otherwise wait for)."""
        for s in self.strides:
            if s > 1:
                self.recovery.factor(self._patterns[s])
        self.model.project(np.zeros((*self.shape, 3), dtype=np.uint8))

    # ------------------------------------------------------------------ frames
    def _cast(self, phi_theta: tuple[float, float], rows: np.ndarray, cols: np.ndarray, *,
              exact: bool = True) -> np.ndarray:
        settings = self.renderer.settings
        camera = settings.camera(*phi_theta)
        caster = self.renderer.renderer if exact else self._moving
        rgba = caster.render_pixels(camera, settings.width, settings.height, rows, cols)
        return caster.composite(rgba)

    @property
    def corrects(self) -> bool:
        """Frames are corrections of the device's own frames (``own`` was given)."""
        return self.own is not None

    def _weights(self, image: np.ndarray) -> np.ndarray:
        from host.fit.rate import ssim_cell_weights

        return ssim_cell_weights(image, self.model.image.cell_shape,
                                 image.max(axis=2) > _OBJECT_LEVEL)

    def _full(self) -> np.ndarray:
        """The scores of the whole ray-cast, or (corrections) the full correction."""
        y = self.model.project(self._image)
        if self._synth is not None:
            y = y - self.model.project(self._synth)
        return y

    def _recover(self, pattern: SamplePattern, rgb: np.ndarray, prior: np.ndarray
                 ) -> np.ndarray:
        if self._synth is None:
            return self.recovery.recover(pattern, rgb, prior)
        synth = self._synth[pattern.rows, pattern.cols].astype(np.float32)
        return self.recovery.recover_residual(pattern, rgb.reshape(-1, 3) - synth)

    def frame(self, view: tuple[float, float]) -> MotionFrame:
        """The scores (or correction) of a new view (canonical ``(phi, theta)``), at the
        stride that fits."""
        t0 = self.clock()
        stride = self.choose_stride()
        previous = self._view
        h, w = self.shape
        self._image = np.zeros((h, w, 3), dtype=np.uint8)
        self._known = np.zeros((h, w), dtype=bool)
        self._synth = None
        if self.own is not None:
            prior, prior_kind = np.zeros(self.model.image.n_coefficients, np.float32), "zero"
        elif (previous is not None and self._scores is not None
                and angle_between(previous, view) < self.prior_switch_deg):
            prior, prior_kind = self._scores, "previous"
        else:
            prior, prior_kind = self.model.scores(*view), "interpolated"
        if stride == 0:  # nothing fits: the prior alone, ray-cast when the view rests
            self._skipped += 1
            self._view, self._scores, self._prior = view, prior, prior
            self._stride, self._complete = self.strides[-1] + 1, False
            self.frames += 1
            self.stride_frames[0] = self.stride_frames.get(0, 0) + 1
            seconds = self.clock() - t0
            self.seconds += seconds
            return MotionFrame(np.asarray(prior, dtype=np.float32), 0, 0, seconds, prior_kind,
                               False)
        self._skipped = 0
        if self.own is not None:
            self._synth = self.own.frame(*view)
        pattern = self._patterns[stride]
        if stride > 1:
            self.recovery.factor(pattern)  # cached after the first use of the stride
        exact = self._moving is self.renderer.renderer
        rgb = self._cast(view, pattern.rows, pattern.cols, exact=exact)
        self._image[pattern.rows, pattern.cols] = rgb
        y = self._full() if stride == 1 else self._recover(pattern, rgb, prior)
        self._known[pattern.rows, pattern.cols] = exact
        seconds = self.clock() - t0
        self._measured(stride, seconds)
        complete = stride == 1 and exact
        self._view, self._scores, self._prior = view, y, prior
        self._stride, self._complete = stride, complete
        self.frames += 1
        self.pixels += pattern.n_pixels
        self.seconds += seconds
        self.stride_frames[stride] = self.stride_frames.get(stride, 0) + 1
        weights = None
        if self._synth is not None:
            weights = self._weights(self._image if complete else self._synth)
        return MotionFrame(y, stride, pattern.n_pixels, seconds, prior_kind, complete,
                           weights)

    def rest_images(self, view: tuple[float, float]) -> tuple[np.ndarray, np.ndarray] | None:
        """The resting ``view``'s full ray-cast and the device's own frame of it (uint8
        (h, w, 3) each, the source's own arrays: not to be changed), once its correction is
        complete; None otherwise (another view, not complete yet, or no ``own``)."""
        if view != self._view or not self._complete or self._synth is None:
            return None
        return self._image, self._synth

    def converged(self, view: tuple[float, float]) -> bool:
        """``view`` is the last frame's and its scores are already the full projection
        (False for another view: it has not been ray-cast yet)."""
        return view == self._view and self._complete

    def refine(self, view: tuple[float, float]) -> MotionFrame | None:
        """The next step of the resting ``view``; None when it is not the last frame's view
        or is already the full projection.

        Each step ray-casts (exactly) as many of the pixels still missing as fit the budget,
        towards the next denser stride of `strides` (then every pixel). A step that
        completes that stride's grid carries its recovered scores, the last one
        `HostModel.project` of the whole ray-cast (corrections: the full correction); a
        step in between carries ``scores=None`` (nothing new to show yet).
        """
        if view != self._view or self._complete:
            return None
        t0 = self.clock()
        if self.own is not None and self._synth is None:  # a frame that cast nothing
            self._synth = self.own.frame(*view)
        target = next((s for s in reversed(self.strides) if s < self._stride), 1)
        pattern = self._patterns.get(target) or SamplePattern.strided(
            self.shape[1], self.shape[0], 1)
        todo = ~self._known[pattern.rows, pattern.cols]
        rows, cols = pattern.rows[todo], pattern.cols[todo]
        if self._recent:  # as many rays as the budget holds (at least a stride's worth)
            fixed, per_ray = self._fit()
            room = max(BUDGET_SHARE * self.budget_s - fixed, 0.0)
            cap = max(int(room / per_ray), self._n_pixels(self.strides[-1]))
            rows, cols = rows[:cap], cols[:cap]
        rgb = self._cast(view, rows, cols)
        self._image[rows, cols] = rgb
        self._known[rows, cols] = True
        y = None
        complete = False
        if self._known[pattern.rows, pattern.cols].all():
            if target == 1:
                y = self._full()
                complete = True
            else:
                y = self._recover(pattern, self._image[pattern.rows, pattern.cols],
                                  self._prior)
            self._scores, self._stride, self._complete = y, target, complete
        weights = None
        if y is not None and self._synth is not None:
            weights = self._weights(self._image if complete else self._synth)
        seconds = self.clock() - t0
        self.refinements += 1
        self.pixels += int(rows.size)
        self.seconds += seconds
        return MotionFrame(y, target, int(rows.size), seconds, "progressive", complete,
                           weights)

    def stats(self) -> dict[str, Any]:
        """JSON-able counters."""
        return {"motion_frames": self.frames, "motion_refinements": self.refinements,
                "motion_pixels": self.pixels, "motion_seconds": self.seconds,
                "stride_frames": {str(k): v for k, v in sorted(self.stride_frames.items())}}
