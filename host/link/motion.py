"""Frames within a deadline while the view moves: ``serve --scores motion`` (issue 13).

`MotionScores` makes the scores of each frame from a *sparse* ray-cast of the true view, as
dense as the frame's time budget allows:

* **Moving.** Each new view ray-casts every ``s``-th pixel in both directions (offset
  (0, 0)) and recovers the scores per cell (`host.fit.SparseRecovery`, cached factors per
  stride). ``s`` is the smallest of `DEFAULT_STRIDES` whose measured cost fits the budget
  (``BUDGET_SHARE`` of ``budget_s``); stride 1 is a full ray-cast and sends
  `HostModel.project` of it. The prior is the interpolated scores, or the previous frame's
  when the view moved less than ``prior_switch_deg`` since it (slow drags: docs/
  rate-distortion.md section 6).
* **Resting.** `refine` continues a view that was not replaced: it ray-casts the offsets of
  the stride not yet seen, as many per step as fit the budget, accumulates them
  (`host.fit.ProgressiveRecovery`) and, with the last one, sends `HostModel.project` of the
  assembled full ray-cast: the frame is then exactly ``--scores render``'s.

The cost model is measured, not assumed: the seconds of the last frames at the stride used
(render and recovery, an exponential average), scaled by the number of rays for the other
strides. A slower host (or a larger model) therefore gets sparser frames, never later ones.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.errors import EigencastError
from host.fit.recover import DEFAULT_LAMBDA, ProgressiveRecovery, SamplePattern, SparseRecovery

__all__ = [
    "BUDGET_SHARE",
    "DEFAULT_MOTION_FPS",
    "DEFAULT_STRIDES",
    "PRIOR_SWITCH_DEG",
    "MotionFrame",
    "MotionScores",
    "angle_between",
]

#: Strides a moving frame may use (1: a full ray-cast, the projection itself).
DEFAULT_STRIDES = (1, 2, 3, 4, 6, 8, 12, 16)
#: Below this angle between successive frames the previous frame's scores are the prior.
PRIOR_SWITCH_DEG = 0.5
#: Share of the frame budget a frame's ray-cast and recovery may take (the rest: encoding,
#: the link, the scheduler).
BUDGET_SHARE = 0.8
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


@dataclass
class MotionFrame:
    """One frame's scores and how they were made.

    Attributes
    ----------
    scores : ndarray of shape (K,), float32
    stride : int
        Of the sample grid (1: full ray-cast).
    pixels : int
        Rays cast for this frame.
    seconds : float
        Host time for the frame (ray-cast and recovery).
    prior : str
        ``"interpolated"``, ``"previous"`` (moving frames) or ``"progressive"`` (a resting
        view's refinement).
    complete : bool
        The scores are `HostModel.project` of the full ray-cast.
    """

    scores: np.ndarray
    stride: int
    pixels: int
    seconds: float
    prior: str
    complete: bool


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
    strides : sequence of int
        Candidate strides for moving frames (sorted; 1 means a full ray-cast).
    prior_switch_deg : float
        Use the previous frame's scores as the prior below this angle per frame.
    clock : callable
        Seconds (monotonic); tests pass a fake one.

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
                 lam: float = DEFAULT_LAMBDA, strides: tuple[int, ...] = DEFAULT_STRIDES,
                 prior_switch_deg: float = PRIOR_SWITCH_DEG,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        h, w = (int(v) for v in model.image.image_shape)
        if tuple(renderer.image_shape) != (h, w):
            raise EigencastError(
                f"the renderer makes {renderer.image_shape[1]}x{renderer.image_shape[0]} "
                f"images, the model is {w}x{h}")
        strides = tuple(sorted({int(s) for s in strides}))
        if not strides or strides[0] < 1:
            raise ValueError(f"strides={strides}: positive integers expected")
        if not budget_s > 0:
            raise ValueError(f"budget_s={budget_s} must be > 0")
        self.model = model
        self.renderer = renderer
        self.shape = (h, w)
        self.budget_s = float(budget_s)
        self.strides = strides
        self.prior_switch_deg = float(prior_switch_deg)
        self.clock = clock
        self.recovery = SparseRecovery(model, lam=lam, max_patterns=4 * len(strides))
        self._patterns = {s: SamplePattern.strided(w, h, s) for s in strides}
        self._cost: tuple[int, float] | None = None  # (stride, seconds per frame), EMA
        self._progress: dict[int, ProgressiveRecovery] = {}
        self._view: tuple[float, float] | None = None
        self._scores: np.ndarray | None = None
        self._prior: np.ndarray | None = None
        self._stride = 1
        self._image: np.ndarray | None = None  # the view's ray-cast pixels so far (h, w, 3)
        self._seen: list[tuple[int, int]] = []
        self.frames = self.refinements = self.pixels = 0
        self.seconds = 0.0
        self.stride_frames: dict[int, int] = {}

    # ------------------------------------------------------------------ cost model
    def _n_pixels(self, stride: int) -> int:
        h, w = self.shape
        return (-(-h // stride)) * (-(-w // stride))

    def estimate(self, stride: int) -> float:
        """Expected seconds of a frame at ``stride`` (0 before anything was measured)."""
        if self._cost is None:
            return 0.0
        ref, seconds = self._cost
        return seconds * self._n_pixels(stride) / self._n_pixels(ref)

    def _measured(self, stride: int, seconds: float) -> None:
        if self._cost is not None and self._cost[0] == stride:
            seconds = (1 - _EMA) * self._cost[1] + _EMA * seconds
        self._cost = (stride, seconds)

    def choose_stride(self) -> int:
        """The densest stride whose estimated cost fits ``BUDGET_SHARE * budget_s`` (the
        sparsest when none does, and before the first measurement)."""
        if self._cost is None:
            return self.strides[-1]
        room = BUDGET_SHARE * self.budget_s
        for s in self.strides:
            if self.estimate(s) <= room:
                return s
        return self.strides[-1]

    def prepare(self) -> None:
        """Compute the recovery factors of every stride now (not during the first frames)."""
        for s in self.strides:
            if s > 1:
                self.recovery.factor(self._patterns[s])

    # ------------------------------------------------------------------ frames
    def _cast(self, phi_theta: tuple[float, float], rows: np.ndarray,
              cols: np.ndarray) -> np.ndarray:
        settings = self.renderer.settings
        camera = settings.camera(*phi_theta)
        rgba = self.renderer.renderer.render_pixels(camera, settings.width, settings.height,
                                                    rows, cols)
        return self.renderer.renderer.composite(rgba)

    def frame(self, view: tuple[float, float]) -> MotionFrame:
        """The scores of a new view (canonical ``(phi, theta)``), at the stride that fits."""
        t0 = self.clock()
        stride = self.choose_stride()
        previous = self._view
        if (previous is not None and self._scores is not None
                and angle_between(previous, view) < self.prior_switch_deg):
            prior, prior_kind = self._scores, "previous"
        else:
            prior, prior_kind = self.model.scores(*view), "interpolated"
        pattern = self._patterns[stride]
        if stride > 1:
            self.recovery.factor(pattern)  # cached after the first use of the stride
        rgb = self._cast(view, pattern.rows, pattern.cols)
        h, w = self.shape
        image = np.zeros((h, w, 3), dtype=np.uint8)
        image[pattern.rows, pattern.cols] = rgb
        if stride == 1:
            y = self.model.project(image)
        else:
            y = self.recovery.recover(pattern, rgb, prior)
        seconds = self.clock() - t0
        self._measured(stride, seconds)
        self._view, self._scores, self._prior, self._stride = view, y, prior, stride
        self._image, self._seen = image, [(0, 0)]
        self.frames += 1
        self.pixels += pattern.n_pixels
        self.seconds += seconds
        self.stride_frames[stride] = self.stride_frames.get(stride, 0) + 1
        return MotionFrame(y, stride, pattern.n_pixels, seconds, prior_kind, stride == 1)

    def converged(self, view: tuple[float, float]) -> bool:
        """``view`` is the last frame's and its scores are already the full projection
        (False for another view: it has not been ray-cast yet)."""
        return view == self._view and len(self._seen) == self._stride ** 2

    def refine(self, view: tuple[float, float]) -> MotionFrame | None:
        """The next, denser frame of the resting ``view``; None when it is not the last
        frame's view or is already the full projection."""
        if view != self._view or self.converged(view):
            return None
        t0 = self.clock()
        s = self._stride
        progress = self._progress.get(s)
        if progress is None:
            progress = self._progress[s] = ProgressiveRecovery(self.recovery, s)
        if progress.offsets_seen != self._seen:  # (re)start from this view's first samples
            progress.reset(self._prior)
            first = self._patterns[s]
            progress.add((0, 0), self._image[first.rows, first.cols])
        todo = [o for o in progress.order if o not in self._seen]
        per_offset = self.estimate(s) or 0.0
        room = BUDGET_SHARE * self.budget_s
        n = len(todo) if per_offset * len(todo) <= room else max(1, int(room // per_offset)
                                                                  if per_offset else 1)
        batch = todo[:n]
        pats = [progress.pattern(o) for o in batch]
        rows = np.concatenate([p.rows for p in pats])
        cols = np.concatenate([p.cols for p in pats])
        rgb = self._cast(view, rows, cols)
        self._image[rows, cols] = rgb
        self._seen.extend(batch)
        complete = len(self._seen) == s * s
        if complete:
            y = self.model.project(self._image)
        else:
            start = 0
            for o, p in zip(batch, pats, strict=True):
                y = progress.add(o, rgb[start:start + p.n_pixels])
                start += p.n_pixels
        seconds = self.clock() - t0
        self._scores = y
        self.refinements += 1
        self.pixels += int(rows.size)
        self.seconds += seconds
        return MotionFrame(y, s, int(rows.size), seconds, "progressive", complete)

    def stats(self) -> dict[str, Any]:
        """JSON-able counters."""
        return {"motion_frames": self.frames, "motion_refinements": self.refinements,
                "motion_pixels": self.pixels, "motion_seconds": self.seconds,
                "stride_frames": {str(k): v for k, v in sorted(self.stride_frames.items())}}
