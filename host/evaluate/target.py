"""Automatic threshold: the cheapest model whose held-out views reach a quality target.

The paper chose its threshold T by hand (section 5) and names automating it as future work.
``eigencast fit --target ssim=0.95`` does it: it fits once at a high T (or many components),
then searches a ladder of lower settings *without refitting* -- a fitted model truncates to
any lower T per cell from its eigenvalues (`host.fit.model.HostModel.truncated`) -- and measures
each try on held-out views through exactly the device's path: interpolated scores -> a real
key score packet at the score step -> decoder -> int8 reconstruction
(`host.evaluate.DevicePath`). The cost of a try is its mean score-packet size over the
held-out views (bytes per view).

Search. The ladder holds the distinct per-cell component counts of
``T = 1 - 10**-x`` for x = 0.5, 0.6, ... (adaptive; plus the fitted T) or of
``k = 1 .. components`` (cell/standard), cheapest first. Quality is monotone-ish along it, so
for each score-step factor (the step is that multiple of `host.fit.model.score_step_for`, the
step whose rounding noise adds `host.fit.model.DEFAULT_SCORE_MSE`) a bisection finds the cheapest
rung that reaches the target; a coarser step can only need a higher rung, so its bisection
starts where the finer one ended. The choice is the try with the fewest bytes per view
among those that reached the target; every cheaper try missed it (by construction). A target
the top rung misses is unreachable: the error names the best quality reached.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.errors import EigencastError
from host.progress import progress as _progress

__all__ = [
    "TARGET_METRICS",
    "TARGET_STEP_FACTORS",
    "HeldOutViews",
    "Target",
    "TargetError",
    "TargetResult",
    "Try",
    "holdout_indices",
    "level_ladder",
    "parse_target",
    "search_target",
]

#: Metric -> whether larger is better; the metric ranges accepted by `parse_target`.
TARGET_METRICS = {"ssim": (True, 0.0, 1.0), "flip": (False, 0.0, 1.0), "psnr": (True, 1.0, 99.0)}
#: Score-step multiples tried (1 = the default step).
TARGET_STEP_FACTORS = (1.0, 2.0, 4.0, 8.0, 16.0)
#: Exponents x of the adaptive ladder T = 1 - 10**-x.
_LADDER_EXPONENTS = np.round(np.arange(0.5, 5.0001, 0.1), 2)


class TargetError(EigencastError):
    """A quality target is malformed or cannot be reached."""


@dataclass(frozen=True)
class Target:
    """A quality target, e.g. ``ssim >= 0.95`` or ``flip <= 0.05``.

    Attributes
    ----------
    metric : {"ssim", "flip", "psnr"}
    value : float
    """

    metric: str
    value: float

    @property
    def higher_is_better(self) -> bool:
        return TARGET_METRICS[self.metric][0]

    def met(self, achieved: float) -> bool:
        """Whether a mean quality ``achieved`` reaches the target."""
        if not math.isfinite(achieved):
            return achieved == math.inf and self.higher_is_better
        return achieved >= self.value if self.higher_is_better else achieved <= self.value

    def better(self, a: float, b: float) -> bool:
        """Whether quality ``a`` is better than ``b``."""
        return a > b if self.higher_is_better else a < b

    def __str__(self) -> str:
        return f"{self.metric}{'>=' if self.higher_is_better else '<='}{self.value:g}"


def parse_target(text: str) -> Target:
    """Parse ``METRIC=VALUE`` (``ssim=0.95``, ``flip=0.05``, ``psnr=35``).

    Raises
    ------
    TargetError
        Unknown metric, missing ``=``, or a value outside the metric's range.
    """
    metric, sep, value = str(text).partition("=")
    metric = metric.strip().lower()
    known = ", ".join(f"{m}=VALUE" for m in TARGET_METRICS)
    if not sep or metric not in TARGET_METRICS:
        raise TargetError(f"--target {text!r}: expected one of {known}")
    _, lo, hi = TARGET_METRICS[metric]
    try:
        number = float(value)
    except ValueError:
        raise TargetError(f"--target {text!r}: {value!r} is not a number") from None
    if not (math.isfinite(number) and lo < number < hi):
        raise TargetError(f"--target {text!r}: {metric} must be within ({lo:g}, {hi:g})")
    return Target(metric, number)


@dataclass(frozen=True, eq=False)
class HeldOutViews:
    """Reference images of views the model was not fitted on.

    Attributes
    ----------
    phi_deg, theta_deg : ndarray of shape (n_views,), float64
    images : ndarray of shape (n_views, height, width, 3), uint8
    source : str
        Where they came from, for the output (``"test database X"``, ``"ray-cast random:30"``,
        ``"30 views held out of the training database"``).
    """

    phi_deg: np.ndarray
    theta_deg: np.ndarray
    images: np.ndarray
    source: str

    def __post_init__(self) -> None:
        n = len(self.images)
        if n < 1 or self.images.ndim != 4 or self.images.shape[3] != 3:
            raise ValueError(f"HeldOutViews: images must be (n >= 1, h, w, 3), got "
                             f"{self.images.shape}")
        if self.phi_deg.shape != (n,) or self.theta_deg.shape != (n,):
            raise ValueError("HeldOutViews: phi_deg/theta_deg must have one entry per image")


def holdout_indices(n_views: int, count: int, *, seed: int = 0) -> np.ndarray:
    """``count`` distinct view indices (sorted) drawn with ``numpy.random.default_rng(seed)``."""
    if not 1 <= count < n_views:
        raise TargetError(
            f"cannot hold out {count} of {n_views} training views (need 1 <= count < n_views)"
        )
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n_views, size=count, replace=False))


@dataclass(frozen=True, eq=False)
class Try:
    """One setting measured on the held-out views.

    Attributes
    ----------
    knob : {"threshold", "components"}
    level : float
        The threshold T, or the components per cell.
    step_factor : float
        Score step as a multiple of the default rule's.
    score_step : float
    components_per_cell : float
        Mean over cells.
    bytes_per_view : float
        Mean key score-packet size over the held-out views.
    quality : float
        Mean of the target metric over the held-out views.
    met : bool
    counts : ndarray of shape (n_cells,), int32
    """

    knob: str
    level: float
    step_factor: float
    score_step: float
    components_per_cell: float
    bytes_per_view: float
    quality: float
    met: bool
    counts: np.ndarray = field(repr=False)

    def record(self) -> dict:
        """JSON/CBOR-able summary (for provenance)."""
        return {
            self.knob: float(self.level) if self.knob == "threshold" else int(self.level),
            "step_factor": float(self.step_factor),
            "score_step": float(self.score_step),
            "components_per_cell": round(float(self.components_per_cell), 4),
            "bytes_per_view": round(float(self.bytes_per_view), 2),
            "quality": float(self.quality),
            "met": bool(self.met),
        }


@dataclass
class TargetResult:
    """The tries and the choice of `search_target`."""

    target: Target
    tries: list[Try]
    choice: Try
    source: str

    def table(self) -> str:
        """The tries, cheapest first, as a text table with the choice marked."""
        knob = self.choice.knob
        head = f"{'T' if knob == 'threshold' else 'k':>9} {'step x':>6} {'step':>8} " \
               f"{'dims/cell':>9} {'bytes/view':>10} {self.target.metric:>8}  "
        lines = [f"target {self.target} on {self.source}", head]
        for t in sorted(self.tries, key=lambda t: (t.bytes_per_view, -t.level)):
            level = f"{t.level:.6g}" if knob == "threshold" else f"{int(t.level)}"
            mark = "<- chosen" if t is self.choice else ("met" if t.met else "")
            lines.append(f"{level:>9} {t.step_factor:>6g} {t.score_step:>8.4g} "
                         f"{t.components_per_cell:>9.2f} {t.bytes_per_view:>10.1f} "
                         f"{t.quality:>8.4f}  {mark}")
        c = self.choice
        lines.append(
            f"chose {knob} {c.level:.6g}, score step {c.score_step:.4g} (x{c.step_factor:g}): "
            f"{c.components_per_cell:.2f} components/cell, {c.bytes_per_view:.0f} bytes/view, "
            f"held-out {self.target.metric} {c.quality:.4f}"
        )
        return "\n".join(lines)

    def provenance(self) -> dict:
        """The search as recorded in the image's provenance."""
        return {
            "metric": self.target.metric,
            "value": self.target.value,
            "holdout": self.source,
            "choice": self.choice.record(),
            "tries": [t.record() for t in self.tries],
        }


def level_ladder(model: Any) -> tuple[str, list[tuple[float, np.ndarray]]]:
    """The settings `search_target` may pick, cheapest first (distinct counts only).

    Parameters
    ----------
    model : host.fit.model.HostModel

    Returns
    -------
    knob : {"threshold", "components"}
    ladder : list of (level, counts (n_cells,) int32)
        For adaptive models with annexed eigenvalues: thresholds up to the model's own; for
        the others: components per cell 1 .. the most any cell keeps.
    """
    counts = np.asarray(model.image.n_components, dtype=np.int32)
    own_t = model.threshold
    rungs: list[tuple[float, np.ndarray]] = []
    if model.image.method == "adaptive" and own_t is not None and model.eigenvalues is not None:
        knob = "threshold"
        levels = sorted({*(float(1.0 - 10.0 ** -x) for x in _LADDER_EXPONENTS), float(own_t)})
        for t in levels:
            if t <= own_t + 1e-12:
                rungs.append((t, model.components_for(threshold=t)))
    else:
        knob = "components"
        for k in range(1, int(counts.max(initial=0)) + 1):
            rungs.append((float(k), model.components_for(components=k)))
    ladder: list[tuple[float, np.ndarray]] = []
    for level, c in rungs:
        if ladder and np.array_equal(ladder[-1][1], c):
            continue  # the same model as a lower (cheaper-labelled) rung
        if int(c.sum()) == 0 and int(counts.sum()) > 0:
            continue  # means only: never a useful model
        ladder.append((level, c))
    if not ladder:
        ladder.append((float(own_t) if knob == "threshold" and own_t else 1.0, counts))
    return knob, ladder


def search_target(
    model: Any,
    heldout: HeldOutViews,
    target: Target,
    *,
    step_factors: Sequence[float] = TARGET_STEP_FACTORS,
    score_step: float | None = None,
    progress: bool = True,
) -> TargetResult:
    """Find the setting with the fewest bytes per view that reaches ``target`` on ``heldout``.

    Parameters
    ----------
    model : host.fit.model.HostModel
        Fitted at the highest setting the search may pick (the ladder's top).
    heldout : HeldOutViews
        Same image size as the model.
    target : Target
    step_factors : sequence of float
        Score-step multiples to try (ascending; 1 is the default rule's step).
    score_step : float, optional
        A fixed score step (then ``step_factors`` is ignored).
    progress : bool

    Returns
    -------
    TargetResult

    Raises
    ------
    TargetError
        When even the top rung at the finest step misses the target (names the best reached).
    """
    from host.evaluate.device_path import DevicePath
    from host.evaluate.metrics import compare_images
    from host.fit.model import score_step_for

    if tuple(heldout.images.shape[1:3]) != tuple(model.image.image_shape):
        raise TargetError(
            f"held-out views are {heldout.images.shape[2]}x{heldout.images.shape[1]}, the model "
            f"is {model.image.image_shape[1]}x{model.image.image_shape[0]}"
        )
    knob, ladder = level_ladder(model)
    factors = (1.0,) if score_step is not None else tuple(sorted(float(f) for f in step_factors))
    if not factors or min(factors) <= 0:
        raise ValueError(f"step_factors={step_factors!r} must be positive")
    d = model.image.cell_values
    memo: dict[tuple[int, float], Try] = {}
    tries: list[Try] = []

    def measure(i: int, factor: float, bar: Any) -> Try:
        if (i, factor) in memo:
            return memo[(i, factor)]
        level, counts = ladder[i]
        step = score_step if score_step is not None else factor * score_step_for(counts, d)
        m = model.truncated(counts, score_step=step)
        path = DevicePath(m)
        sizes, values = [], []
        for phi, theta, image in zip(heldout.phi_deg, heldout.theta_deg, heldout.images):
            frame, size = path.frame(float(phi), float(theta))
            sizes.append(size)
            values.append(getattr(compare_images(image, frame, metrics=(target.metric,)),
                                  target.metric))
        # an exact frame has PSNR inf: count it as the top of the accepted range
        quality = float(np.mean(np.minimum(np.array(values, dtype=np.float64), 99.0)))
        t = Try(knob, level, factor, float(step), float(np.mean(counts)),
                float(np.mean(sizes)), quality, target.met(quality), counts)
        memo[(i, factor)] = t
        tries.append(t)
        bar.advance()
        return t

    n = len(ladder)
    estimate = len(factors) * (2 + math.ceil(math.log2(max(2, n))))
    with _progress("target search", estimate, unit=" tries", quiet=not progress) as bar:
        lo_start = -1
        for j, factor in enumerate(factors):
            top = measure(n - 1, factor, bar)
            if not top.met:
                break  # coarser steps only lose quality
            lo, hi = lo_start, n - 1  # invariant: rung hi meets the target, lo does not
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if measure(mid, factor, bar).met:
                    hi = mid
                else:
                    lo = mid
            if j == 0:
                lo_start = hi - 1
        bar.update(estimate)
    return TargetResult(target, tries, _cheapest_met(tries, target, knob), heldout.source)


def _cheapest_met(tries: list[Try], target: Target, knob: str) -> Try:
    """The try with the fewest bytes per view (then the lowest level) that met ``target``;
    when none did, one line naming the best quality reached and how to reach further."""
    met = [t for t in tries if t.met]
    if not met:
        best = max(tries, key=lambda t: t.quality if target.higher_is_better else -t.quality)
        setting = (f"T={best.level:.6g}" if knob == "threshold" else f"k={int(best.level)}")
        raise TargetError(
            f"--target {target.metric}={target.value:g} is unreachable: the best held-out "
            f"{target.metric} is {best.quality:.4f} ({setting}, "
            f"{best.components_per_cell:.1f} components/cell); fit with a higher --threshold or "
            "--components, or render more training views"
        )
    return min(met, key=lambda t: (t.bytes_per_view, t.level))
