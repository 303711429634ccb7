"""The evaluation engine: ray-cast novel views, compare every method, sweep rate-distortion.

`evaluate_model` ray-casts novel views with the model's own render settings
(`host.render.settings.ViewRenderer`) and compares, per view, with the ray-cast: the device
frame from interpolated scores (``pca``) and from the ray-cast's own scores (``pca_render``);
for a model with the standalone table the one served path (`ServedFrames`: the device's own
frame ``pca_warp``, that frame corrected at rest ``pca_predict`` and while moving
``pca_motion``, bit for bit what the device shows, with the bytes of the correction
packets, and given ``serve``'s planner the whole resting chain: the correction when sent, each
refinement layer and the exact frame, with cumulative bytes, against the smallest codec files
of the same quality: `host.evaluate.resting`); the equal-bytes JPEG, WebP and AVIF, the
angularly nearest training view and the
*WebP image database* (`WebPDatabase`: every training view stored as WebP on the device, the
novel view blended from the decoded training images with the model's own interpolation
weights; zero bytes per frame). Every frame also gets its cell-border figure
(`host.evaluate.metrics.blockiness`, beside the ray-cast's own). Then a rate-distortion sweep
over a subset of the views (the model truncated to lower thresholds / fewer components
through the annexed eigenvalues, coarser score steps, the *projection* of the true views onto
the eigenspace -- what the eigenspace can do without view interpolation -- and the codecs at
several qualities, whose curves give the bytes WebP and AVIF need for the served frames'
quality: `codec_equivalent`). `Evaluation.summary` is the JSON of ``eigencast evaluate
--json``; `host.evaluate.report.write_report` turns an `Evaluation` into HTML.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from host.errors import EigencastError
from host.evaluate.baselines import (
    CODECS,
    TrainingImages,
    WebPDatabase,
    encode_image,
    encode_within_budget,
    nearest_training_view,
)
from host.evaluate.device_path import MOTION_STEP_DEG, MOTION_WARMUP, DevicePath, ServedFrames
from host.evaluate.masks import alpha_object_mask
from host.evaluate.metrics import ImageComparison, blockiness, compare_images
from host.evaluate.resting import measure_rest, rest_record, summarize_rest
from host.progress import progress as _progress

__all__ = [
    "DEFAULT_QUALITIES",
    "DEFAULT_STEP_FACTORS",
    "DEFAULT_THRESHOLDS",
    "DEFAULT_WEBP_DB_QUALITY",
    "METHODS",
    "Evaluation",
    "codec_equivalent",
    "default_metric_workers",
    "eigenspace_bytes",
    "evaluate_model",
    "model_info",
]

#: Methods an evaluation reports: the device frame from interpolated scores (``pca``), the
#: device frame from the ray-cast's own scores (``pca_render``: key packets of the true view's
#: projection), the one served path for a model with the standalone table -- the device's own
#: frame (``pca_warp``: its depth warp, or the blend of its predicted scores for an image
#: without depth; 0 bytes), that frame at rest corrected by the complete correction at the
#: model's step (``pca_predict``, "served, at rest") and while moving by the sparse correction
#: the frame deadline allows (``pca_motion``, "served, while moving"; for a model without the
#: table: the sparse ray-cast's absolute scores as a delta packet) -- equal-bytes codecs, the
#: nearest training view and the on-device WebP image database.
METHODS = ("pca", "pca_motion", "pca_predict", "pca_render", "jpeg", "webp", "avif", "nearest",
           "webp_db", "pca_warp")
#: Methods whose frames are corrections of ``pca_warp`` (the device's own frame).
SERVED = ("pca_predict", "pca_motion")
#: A served view counts as below its own frame when its object SSIM is lower by more than this.
BELOW_OWN_SSIM = 0.01
#: Thresholds tried by the rate-distortion sweep of an adaptive model (those below its own T).
DEFAULT_THRESHOLDS = (0.8, 0.9, 0.95, 0.97, 0.98, 0.99, 0.995, 0.998, 0.999)
#: Score-step multiples tried by the rate-distortion sweep at the model's own components.
DEFAULT_STEP_FACTORS = (2.0, 4.0, 8.0, 16.0)
#: Codec qualities of the rate-distortion sweep.
DEFAULT_QUALITIES = (2, 5, 10, 20, 35, 50, 60, 70, 80, 90, 95)
#: WebP quality of the on-device image database baseline (``webp_db``).
DEFAULT_WEBP_DB_QUALITY = 80
_NOT_AVERAGED = {"index"}  # per-view entries whose mean means nothing


@dataclass
class Evaluation:
    """Everything ``eigencast evaluate`` measured.

    Attributes
    ----------
    info : dict
        Model facts: ``method``, ``threshold``, ``components_per_cell``, ``n_coefficients``,
        ``eigenspace_bytes``, ``score_step``, ``image_shape``, ``cell_shape``, ``int8``,
        ``volume`` ...
    views : list of dict
        One record per novel view: ``phi_deg``, ``theta_deg``, ``object_fraction``,
        ``raycast_blockiness`` and, per method (`METHODS`), a dict of ``bytes_per_view``,
        ``blockiness`` and the metrics (plus ``quality``/``within_budget`` for codecs,
        ``index``/``angle_deg`` for the nearest view, ``stride`` for ``pca_motion``), and
        given a planner ``rest`` (`host.evaluate.resting.rest_record`: each step of the
        resting view with its cumulative bytes, metrics and codec equivalents).
    rd : list of dict
        Rate-distortion points: ``kind`` (pca/projection/jpeg/webp), ``label``, ``setting``,
        ``bytes_per_view``, ``psnr``, ``ssim``, ``flip``, ``components_per_cell``.
    samples : list of dict
        A few views with their images (``raycast``, ``pca``, ``jpeg``, ``webp``,
        ``flip_pca``, ``flip_jpeg``) for the report.
    timing_s : dict
        Seconds spent per phase.
    """

    info: dict
    views: list[dict]
    rd: list[dict] = field(default_factory=list)
    samples: list[dict] = field(default_factory=list)
    timing_s: dict = field(default_factory=dict)

    def means(self, method: str) -> dict[str, float]:
        """Means over the views of every numeric entry of ``method``'s records."""
        keys: list[str] = []
        for rec in self.views:
            for k, v in rec[method].items():
                if k not in keys and k not in _NOT_AVERAGED and isinstance(v, (int, float)) \
                        and not isinstance(v, bool):
                    keys.append(k)
        out: dict[str, float] = {}
        for k in keys:
            vals = np.array([float(rec[method].get(k, math.nan)) for rec in self.views])
            finite = vals[~np.isnan(vals)]
            out[k] = float(finite.mean()) if finite.size else math.nan
        if method in CODECS:
            out["over_budget_views"] = int(
                sum(not rec[method]["within_budget"] for rec in self.views)
            )
        return out

    def over_own(self, method: str) -> dict[str, float]:
        """``method``'s object SSIM against the device's own frame (``pca_warp``), per view:
        the mean and the worst difference, and how many views are more than
        `BELOW_OWN_SSIM` below their own frame."""
        diff = np.array([rec[method]["ssim_object"] - rec["pca_warp"]["ssim_object"]
                         for rec in self.views], dtype=np.float64)
        diff = diff[np.isfinite(diff)]
        if not diff.size:
            return {"gain_over_own": math.nan, "worst_gain_over_own": math.nan,
                    "views_below_own": 0}
        return {"gain_over_own": float(diff.mean()), "worst_gain_over_own": float(diff.min()),
                "views_below_own": int(np.count_nonzero(diff < -BELOW_OWN_SSIM))}

    def equal_quality(self, method: str) -> dict:
        """What WebP and AVIF need for ``method``'s quality, and reach at its bytes.

        On the rate-distortion sweep's views (the first ``rd_views``): ``method``'s mean
        object SSIM and bytes there, and per codec (`codec_equivalent` of its sweep curve)
        ``bytes_for_ssim`` (the bytes per view at which the codec's mean object SSIM equals
        ``method``'s) and ``ssim_at_bytes`` (its mean object SSIM at ``method``'s bytes); None
        where that lies outside the swept qualities (``min_bytes``: the codec's smallest mean
        file, at the lowest quality)."""
        n = int(self.info.get("rd_views") or 0)
        recs = [rec[method] for rec in self.views[:n] if method in rec]
        ssim = float(np.nanmean([r["ssim_object"] for r in recs])) if recs else math.nan
        size = float(np.mean([r["bytes_per_view"] for r in recs])) if recs else math.nan
        out: dict[str, Any] = {"views": len(recs), "ssim_object": ssim, "bytes_per_view": size}
        for codec in ("webp", "avif"):
            points = [p for p in self.rd if p["kind"] == codec]
            if points:
                out[codec] = codec_equivalent(points, ssim, size)
        return out

    def summary(self) -> dict:
        """The ``--json`` object of ``eigencast evaluate``.

        Model facts, the per-method means over the views (`METHODS`: ``pca``, ``pca_motion``
        (with its ``stride``, ``deadline_ms``, ``coarse``, ``step_deg``, ``slowdown``),
        ``pca_render``, ``jpeg``, ``webp``, ``avif``, ``nearest``, ``webp_db``, and for a
        model with the standalone table ``pca_warp`` (with ``own_frame``: ``"warp"`` or
        ``"blend"``) and ``pca_predict``; the served methods (`SERVED`) also with
        `over_own` and `equal_quality`), ``raycast_blockiness``, ``rest`` (the resting
        chain's stages, `host.evaluate.resting.summarize_rest`; given a planner), the
        rate-distortion points, the time per phase and the per-view records; non-finite
        floats are ``None``.
        """
        info = self.info
        out = {
            "method": info["method"],
            "threshold": info["threshold"],
            "components_per_cell": info["components_per_cell"],
            "eigenspace_bytes": info["eigenspace_bytes"],
            "views": len(self.views),
            "view_spec": info.get("view_spec"),
            "image_size": [info["image_shape"][1], info["image_shape"][0]],
            "n_coefficients": info["n_coefficients"],
            "score_step": info["score_step"],
            "int8": info.get("int8"),
        }
        for method in METHODS:
            if self.views and method in self.views[0]:
                out[method] = self.means(method)
        if "pca_motion" in out and info.get("motion"):
            out["pca_motion"].update({k: info["motion"][k]
                                      for k in ("deadline_ms", "coarse", "step_deg",
                                                "slowdown", "stride_given")})
            out["pca_motion"]["stride"] = info["motion"]["stride"]
        if "pca_warp" in out:
            out["pca_warp"]["own_frame"] = info.get("own_frame")
        for method in SERVED:
            if method in out and "pca_warp" in out:
                out[method].update(self.over_own(method))
        if self.views:
            vals = np.array([rec.get("raycast_blockiness", math.nan) for rec in self.views],
                            dtype=np.float64)
            out["raycast_blockiness"] = (float(np.nanmean(vals)) if np.isfinite(vals).any()
                                         else math.nan)
        for method in SERVED:
            if method in out and self.rd:
                out[method]["equal_quality"] = self.equal_quality(method)
        rest = summarize_rest(self.views)
        if rest is not None:
            out["rest"] = rest
        if "webp_db" in out:
            out["webp_db"]["storage_bytes"] = info.get("webp_db_storage_bytes")
            out["webp_db"]["storage_estimated"] = info.get("webp_db_storage_estimated")
        out["rate_distortion"] = [
            {k: v for k, v in p.items() if k != "model"} for p in self.rd
        ]
        out["timing_s"] = dict(self.timing_s)
        out["per_view"] = self.views
        return json_safe(out)


def codec_equivalent(points: Sequence[dict], ssim: float, size: float) -> dict:
    """Interpolate a codec's rate-distortion curve (``points``: the sweep's points of one
    codec, each with ``setting.quality``, ``bytes_per_view`` and ``ssim_object``) in quality.

    ``bytes_for_ssim``: between the two swept qualities whose object SSIM brackets ``ssim``
    (the lowest such pair), the fraction ``t`` of the way in SSIM, and the bytes ``t`` of the
    way in log bytes (SSIM linear, bytes log-linear in quality). ``ssim_at_bytes``: the
    reverse at ``size`` (``t`` in log bytes). None outside the curve; ``min_bytes`` is the
    lowest quality's mean file size.
    """
    pts = sorted(points, key=lambda p: p["setting"]["quality"])
    b = np.array([p["bytes_per_view"] for p in pts], dtype=np.float64)
    q = np.array([p["ssim_object"] for p in pts], dtype=np.float64)
    out: dict[str, Any] = {"bytes_for_ssim": None, "ssim_at_bytes": None,
                           "min_bytes": float(b[0]) if b.size else None}
    lb = np.log(np.maximum(b, 1.0))
    for i in range(1, b.size):
        if out["bytes_for_ssim"] is None and math.isfinite(ssim) and q[i - 1] <= ssim <= q[i] \
                and q[i] > q[i - 1]:
            t = (ssim - q[i - 1]) / (q[i] - q[i - 1])
            out["bytes_for_ssim"] = float(np.exp(lb[i - 1] + t * (lb[i] - lb[i - 1])))
        if out["ssim_at_bytes"] is None and size > 0 and b[i - 1] <= size <= b[i] \
                and b[i] > b[i - 1]:
            t = (math.log(size) - lb[i - 1]) / (lb[i] - lb[i - 1])
            out["ssim_at_bytes"] = float(q[i - 1] + t * (q[i] - q[i - 1]))
    return out


def json_safe(value: Any) -> Any:
    """Non-finite floats become None (strict JSON); numpy scalars become Python ones."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def eigenspace_bytes(model: Any) -> int:
    """Size of the device image (what provisioning sends and a device stores), in bytes."""
    from protocol.image import HEADER_SIZE, image_size, write_image

    if model.path is not None and Path(model.path).is_file():
        with open(model.path, "rb") as f:
            return image_size(f.read(HEADER_SIZE))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.ecs"
        write_image(path, model.image, annex=None)
        with open(path, "rb") as f:
            return image_size(f.read(HEADER_SIZE))


def model_info(model: Any) -> dict:
    """Facts about a model for reports: method, T, components per cell, sizes ..."""
    image = model.image
    fit = image.provenance.get("fit") or {}
    render = model.render_settings
    return {
        "path": str(model.path) if model.path else None,
        "method": image.method,
        "threshold": model.threshold,
        "components": fit.get("components"),
        "components_per_cell": float(np.mean(image.n_components)),
        "n_cells": int(image.n_cells),
        "n_coefficients": int(image.n_coefficients),
        "image_shape": [int(v) for v in image.image_shape],
        "cell_shape": [int(v) for v in image.cell_shape],
        "score_step": model.score_step,
        "eigenspace_bytes": eigenspace_bytes(model),
        "training_views": len((image.views or {}).get("phi_deg", [])),
        "training_view_spec": (image.views or {}).get("spec"),
        "interpolation": (image.interpolation or {}).get("method"),
        "int8": image.provenance.get("int8"),
        "target": image.provenance.get("target"),
        "volume": (render.get("volume") or {}),
        "transfer_function": (render.get("transfer_function") or {}).get("name"),
    }


def _pca_settings(
    model: Any, thresholds: Sequence[float], step_factors: Sequence[float]
) -> list[dict]:
    """Truncations / score steps of ``model`` for the rate-distortion sweep."""
    from host.fit.model import score_step_for

    counts = np.asarray(model.image.n_components)
    d = model.image.cell_values
    auto = score_step_for(counts, d)
    factor = model.score_step / auto  # keep the model's step relative to the auto rule
    out: list[dict] = []
    seen: set[bytes] = set()
    levels: list[tuple[str, dict, np.ndarray]] = []
    own_t = model.threshold
    if model.image.method == "adaptive" and own_t is not None and model.eigenvalues is not None:
        for t in sorted({*[t for t in thresholds if t < own_t - 1e-9], own_t}):
            levels.append((f"T={t:g}", {"threshold": t}, model.components_for(threshold=t)))
    else:
        k_max = int(counts.max()) if counts.size else 0
        ks = sorted({max(1, k_max // 8), max(1, k_max // 4), max(1, k_max // 2), k_max})
        for k in ks:
            levels.append((f"k={k}", {"components": k}, model.components_for(components=k)))
    for label, setting, new in levels:
        key = new.tobytes()
        if key in seen or (int(new.sum()) == 0 and counts.sum() > 0):
            continue
        seen.add(key)
        own = np.array_equal(new, counts)
        step = model.score_step if own else score_step_for(new, d) * factor
        out.append({"label": label, "setting": {**setting, "step_factor": 1.0},
                    "counts": new, "step": step, "own": own})
    for f in step_factors:
        out.append({"label": f"step x{f:g}",
                    "setting": {"threshold": own_t, "step_factor": float(f)},
                    "counts": counts, "step": model.score_step * f, "own": False})
    return out


class _Metrics:
    """Run `compare_images` jobs in worker processes (or inline), returning futures.

    The metrics (FLIP above all) are single-threaded and dominate an evaluation, while the
    ray-caster already uses every core only while it renders; a few worker processes keep
    the cores busy in between. ``workers=0`` computes inline.
    """

    def __init__(self, workers: int) -> None:
        self.pool = None
        if workers > 0:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawn, not fork: the parent holds numba's threading layer
            self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(
                "spawn"))

    def submit(self, *args: Any, **kwargs: Any) -> Future:
        return self.call(_compare_job, *args, **kwargs)

    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Future:
        """``fn(*args, **kwargs)`` in a worker (a module-level function), or inline."""
        if self.pool is not None:
            return self.pool.submit(fn, *args, **kwargs)
        done: Future = Future()
        done.set_result(fn(*args, **kwargs))
        return done

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


def _compare_job(truth: np.ndarray, test: np.ndarray, mask: np.ndarray | None,
                 keep: bool) -> ImageComparison:
    return compare_images(truth, test, mask=mask, keep_flip_map=keep)


def default_metric_workers() -> int:
    """Metric worker processes by default: the CPU count, at most 2 (0 on one CPU)."""
    import os

    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
    return 0 if cpus < 2 else min(2, cpus)


def evaluate_model(
    model: Any,
    scene: Any,
    views: Any,
    *,
    nearest: bool = True,
    rd_views: int = 8,
    sample_views: int = 4,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    step_factors: Sequence[float] = DEFAULT_STEP_FACTORS,
    qualities: Sequence[int] = DEFAULT_QUALITIES,
    webp_db_quality: int | None = DEFAULT_WEBP_DB_QUALITY,
    motion_deadline_s: float | None = 1.0 / 30.0,
    motion_stride: int | None = None,
    motion_slowdown: float = 1.0,
    rd_pca: bool = True,
    rest_planner: Any = None,
    metric_workers: int | None = None,
    progress: bool = True,
    info: dict | None = None,
    on_view: Callable[[int, dict], None] | None = None,
) -> Evaluation:
    """Evaluate ``model`` on novel views ray-cast by ``scene``.

    Parameters
    ----------
    model : host.fit.model.HostModel
    scene : host.render.settings.ViewRenderer
        Ray-casts with the model's own render settings; its image size must be the model's.
    views : host.render.camera.ViewSet or sequence of (phi_deg, theta_deg)
    nearest : bool
        Also score the angularly nearest training view.
    rd_views : int
        Views (the first ones) used by the rate-distortion sweep; 0 skips it. The bytes WebP
        and AVIF need for the served frames' quality (``equal_quality``) come from its codec
        curves, on these views.
    sample_views : int
        Views whose images are kept for side-by-side figures.
    thresholds, step_factors, qualities
        The rate-distortion sweep's settings (see `DEFAULT_THRESHOLDS` ...).
    webp_db_quality : int or None
        WebP quality of the on-device image database baseline (`WebPDatabase`, method
        ``webp_db``); None skips it.
    motion_deadline_s : float or None
        ``pca_motion``: serve's frame deadline; None skips the method. A warm-up drag at
        `MOTION_STEP_DEG` per frame picks the stride that fits it on this machine
        (``info["motion"]``). With the standalone table each view's frame is then the
        device's own frame plus the sparse correction at that stride (0: no stride fits, the
        own frame), costing its correction packet (0 bytes when none is sent); without the
        table, the sparse ray-cast's scores as a delta packet against the frame
        `MOTION_STEP_DEG` before it.
    motion_stride : int, optional
        ``pca_motion`` at this stride instead of the one the deadline picks (reproducible
        across machines; 0 with the table: the own frames).
    motion_slowdown : float
        The warm-up drag's ray-casts take this many times longer (`SlowRenderer`): the
        stride a slower host's deadline picks.
    rd_pca : bool
        The rate-distortion sweep includes the model's truncations and coarser steps (else
        only the codecs' curves: what ``equal_quality`` needs, in a fraction of the time).
    rest_planner : host.link.layers.RestPlanner, optional
        For a model with the standalone table: plan each view's refinement layers at rest
        as ``serve`` does with this planner (`ServedFrames.rest`) and record every step
        (``record["rest"]``); on the first ``rd_views`` views also the smallest JPEG, WebP
        and AVIF of each lossy step's quality (`host.evaluate.resting.measure_rest`). None:
        no layers.
    metric_workers : int, optional
        Processes computing the metrics (default `default_metric_workers`; 0: inline).
    progress : bool
        Progress on stderr.
    info : dict, optional
        Extra facts merged into `Evaluation.info` (e.g. ``view_spec``).
    on_view : callable, optional
        Called as ``on_view(i, record)`` after each view, in order.

    Returns
    -------
    Evaluation
    """
    pairs = _view_pairs(model, scene, views)
    workers = default_metric_workers() if metric_workers is None else int(metric_workers)
    run = _Evaluating(model, scene, info, workers, nearest, sample_views, rd_views, on_view)
    try:  # (the metric workers start with the first view's metrics)
        run.open_baselines(webp_db_quality, rest_planner, progress)
        if motion_deadline_s is not None:
            run.open_motion(motion_deadline_s, pairs[0], motion_stride, motion_slowdown)
        with _progress("evaluate", len(pairs), unit=" views", quiet=not progress) as bar:
            for i, (phi, theta) in enumerate(pairs):
                run.view(i, phi, theta)
                while len(run.in_flight) > max(1, workers):
                    run.finish(bar)
            while run.in_flight:
                run.finish(bar)
        if run.rd_refs:
            run.rate_distortion(thresholds, step_factors, qualities, progress, rd_pca)
    finally:
        run.metrics.close()
    return run.result()


def _view_pairs(model: Any, scene: Any, views: Any) -> list[tuple[float, float]]:
    """``views`` as (phi, theta) pairs; one line when there are none or ``scene`` makes
    images of another size than the model's."""
    pairs = [(float(v.phi_deg), float(v.theta_deg)) if hasattr(v, "phi_deg") else
             (float(v[0]), float(v[1])) for v in views]
    if not pairs:
        raise EigencastError("evaluate: no views to evaluate")
    if tuple(scene.image_shape) != tuple(model.image.image_shape):
        raise EigencastError(
            f"evaluate: the renderer makes {scene.image_shape[1]}x{scene.image_shape[0]} images, "
            f"the model is {model.image.image_shape[1]}x{model.image.image_shape[0]}"
        )
    return pairs


#: The methods whose FLIP maps a sample view keeps for the report's figures.
_FLIP_MAPS = ("pca", "jpeg", "webp", "avif", "webp_db", "pca_warp", "pca_predict")


class _Evaluating:
    """One run of :func:`evaluate_model`: the sources of every method's frames, set up once
    (:meth:`open_baselines`, :meth:`open_motion`), then per view (:meth:`view`) the
    ray-cast, the device's frames (:meth:`_device_frames`), the served path's
    (:meth:`_served_frames`) or the sparse scores' (:meth:`_motion_frame`), the codecs'
    (:meth:`_codec_frames`), the baselines' (:meth:`_baseline_frames`), and the metrics
    submitted; :meth:`finish` collects a view's metrics in order."""

    def __init__(self, model: Any, scene: Any, info: dict | None, workers: int, nearest: bool,
                 sample_views: int, rd_views: int,
                 on_view: Callable[[int, dict], None] | None) -> None:
        self.model, self.scene = model, scene
        self.evaluation = Evaluation(info={**model_info(model), **(info or {})}, views=[])
        self.evaluation.info["metric_workers"] = workers
        self.metrics = _Metrics(workers)
        self.workers, self.nearest, self.sample_views = workers, nearest, sample_views
        self.rd_views, self.on_view = rd_views, on_view
        self.timing = {"raycast": 0.0, "nearest": 0.0, "device": 0.0, "motion": 0.0,
                       "codecs": 0.0, "webp_db": 0.0, "metrics_wait": 0.0,
                       "rate_distortion": 0.0}
        self.cells = tuple(model.image.cell_shape)
        self.device = DevicePath(model)
        self.training: TrainingImages | None = None
        self.webp_db: WebPDatabase | None = None
        self.served: ServedFrames | None = None
        self.motion: Any = None
        self.rd_refs: list[tuple[np.ndarray, np.ndarray, float, float]] = []
        self.hints: dict[str, int | None] = {c: None for c in CODECS}
        self.rest_hints: dict[str, int] = {}
        self.in_flight: list[tuple[int, dict, dict[str, Future], dict | None, Any]] = []

    def open_baselines(self, webp_db_quality: int | None, rest_planner: Any,
                       progress: bool) -> None:
        """The training images (nearest view, WebP database) and the served path."""
        from device_runtime.prediction import can_predict

        model, info, timing = self.model, self.evaluation.info, self.timing
        if self.nearest or webp_db_quality is not None:
            self.training = TrainingImages(model, self.scene)
            info["nearest_source"] = self.training.source
        if webp_db_quality is not None:
            t0 = time.perf_counter()
            self.webp_db = WebPDatabase(model, self.training, webp_db_quality,
                                        progress=progress)
            timing["webp_db"] += time.perf_counter() - t0
            info["webp_db_quality"] = self.webp_db.quality
        if can_predict(model.image):
            self.served = ServedFrames(model, self.scene, planner=rest_planner)
        if self.served is not None:
            timing["served"] = 0.0
            if rest_planner is not None:
                timing["rest"] = 0.0
                info["rest"] = {"targets": list(rest_planner.targets),
                                "exact": rest_planner.exact,
                                "max_packet_bytes": rest_planner.max_packet_bytes}
            info["own_frame"] = self.served.kind
            if model.image.synthesis is not None:
                info["synthesis"] = model.image.synthesis.get("method")

    def open_motion(self, deadline_s: float, start: tuple[float, float], stride: int | None,
                    slowdown: float) -> None:
        """``pca_motion``: the stride that fits ``deadline_s`` (or the one given)."""
        t0 = time.perf_counter()
        served = self.served
        if served is not None:
            if stride is None:
                served.pick_stride(deadline_s, start, slowdown=slowdown)
            else:
                served.set_stride(stride)
            picked, coarse = served.stride, _moving_coarse()
        else:
            self.motion = _motion_source(self.model, self.scene, deadline_s, start, stride,
                                         slowdown)
            picked, coarse = self.motion.strides[0], self.motion.coarse
        self.timing["motion"] += time.perf_counter() - t0
        self.evaluation.info["motion"] = {"deadline_ms": deadline_s * 1e3,
                                          "stride": picked, "coarse": coarse,
                                          "step_deg": MOTION_STEP_DEG,
                                          "slowdown": float(slowdown),
                                          "stride_given": stride is not None,
                                          "corrections": served is not None}

    def view(self, i: int, phi: float, theta: float) -> None:
        """Every method's frame of one view, its metrics submitted (`in_flight`)."""
        t0 = time.perf_counter()
        truth, alpha = self.scene.render(phi, theta)
        mask = alpha_object_mask(alpha)
        self.timing["raycast"] += time.perf_counter() - t0
        keep = i < self.sample_views
        frames: dict[str, np.ndarray] = {}
        record: dict[str, Any] = {"phi_deg": phi, "theta_deg": theta,
                                  "object_fraction": float(mask.mean()),
                                  "raycast_blockiness": blockiness(truth, self.cells, mask)}
        packet_bytes = self._device_frames(truth, phi, theta, frames, record)
        rest_job = None
        if self.served is not None:  # the one served path
            rest_job = self._served_frames(i, phi, theta, mask, frames, record)
        elif self.motion is not None:
            self._motion_frame(phi, theta, frames, record)
        self._codec_frames(truth, packet_bytes, frames, record)
        self._baseline_frames(phi, theta, frames, record)
        futures = {}
        for name, frame in frames.items():
            record[name]["blockiness"] = blockiness(frame, self.cells, mask)
            futures[name] = self.metrics.submit(truth, frame, mask, keep and name in _FLIP_MAPS)
        sample = None
        if keep:
            sample = {"phi_deg": phi, "theta_deg": theta, "raycast": truth,
                      **frames, "record": record}
            if rest_job is not None:  # the resting chain's frames, for the strip
                sample["rest_frames"] = [s.frame for s in rest_job[0].steps]
        if i < self.rd_views:
            self.rd_refs.append((truth, mask, phi, theta))
        self.in_flight.append((i, record, futures, sample, rest_job))

    def _device_frames(self, truth: np.ndarray, phi: float, theta: float, frames: dict,
                       record: dict) -> int:
        """``pca`` (interpolated scores) and ``pca_render`` (key packets of the ray-cast's
        own scores); the ``pca`` packet's bytes (the codecs' budget)."""
        t1 = time.perf_counter()
        frames["pca"], packet_bytes = self.device.frame(phi, theta)
        record["pca"] = {"bytes_per_view": packet_bytes}
        frames["pca_render"], render_bytes = self.device.projection_frame(truth)
        record["pca_render"] = {"bytes_per_view": render_bytes}
        self.timing["device"] += time.perf_counter() - t1
        return packet_bytes

    def _served_frames(self, i: int, phi: float, theta: float, mask: np.ndarray,
                       frames: dict, record: dict) -> Any:
        """The served path's frames: the own frame, at rest, the resting steps (measured
        in a worker: the job returned) and moving."""
        served, timing = self.served, self.timing
        t2 = time.perf_counter()
        frames["pca_warp"] = served.own_frame(phi, theta)
        record["pca_warp"] = {"bytes_per_view": 0}
        frames["pca_predict"], size = served.at_rest(phi, theta)
        record["pca_predict"] = {"bytes_per_view": size}
        t3 = time.perf_counter()
        timing["served"] += t3 - t2
        rest_job = None
        rest = served.rest(phi, theta)
        if rest is not None:
            rest_job = (rest, self.metrics.call(
                measure_rest, rest.truth, mask, [s.frame for s in rest.steps],
                [s.kind for s in rest.steps], codecs=i < self.rd_views,
                hints=dict(self.rest_hints)))
            t4 = time.perf_counter()
            timing["rest"] += t4 - t3
            t3 = t4
        if served.stride is not None:
            frames["pca_motion"], size = served.moving(phi, theta)
            record["pca_motion"] = {"bytes_per_view": size, "stride": served.stride}
            timing["motion"] += time.perf_counter() - t3
        return rest_job

    def _motion_frame(self, phi: float, theta: float, frames: dict, record: dict) -> None:
        """``pca_motion`` without the standalone table: the sparse ray-cast's scores as a
        delta packet against the frame `MOTION_STEP_DEG` before it."""
        from device_runtime.runtime import canonical_view

        t3 = time.perf_counter()
        motion = self.motion
        before = motion.frame(canonical_view(phi - MOTION_STEP_DEG, theta)).scores
        now = motion.frame(canonical_view(phi, theta)).scores
        frames["pca_motion"], size = self.device.motion_frame(before, now)
        self.timing["motion"] += time.perf_counter() - t3
        record["pca_motion"] = {"bytes_per_view": size, "stride": motion.strides[0]}

    def _codec_frames(self, truth: np.ndarray, packet_bytes: int, frames: dict,
                      record: dict) -> None:
        """JPEG, WebP and AVIF within the ``pca`` packet's bytes (each starts its search
        at the previous view's quality)."""
        t2 = time.perf_counter()
        coded = {c: encode_within_budget(truth, packet_bytes, codec=c, hint=self.hints[c])
                 for c in CODECS}
        self.hints = {c: coded[c].quality for c in CODECS}
        for c in CODECS:
            frames[c] = coded[c].decode()
            record[c] = {"bytes_per_view": coded[c].size_bytes,
                         "quality": coded[c].quality,
                         "within_budget": coded[c].within_budget}
        self.timing["codecs"] += time.perf_counter() - t2

    def _baseline_frames(self, phi: float, theta: float, frames: dict, record: dict) -> None:
        """The WebP database's frame and the nearest training view."""
        t3 = time.perf_counter()
        if self.webp_db is not None:
            frames["webp_db"] = self.webp_db.frame(phi, theta)
            self.timing["webp_db"] += time.perf_counter() - t3
            record["webp_db"] = {"bytes_per_view": 0, "quality": self.webp_db.quality}
        t3 = time.perf_counter()
        training = self.training
        if self.nearest and training is not None:
            index, angle = nearest_training_view(phi, theta, training.phi, training.theta)
            frames["nearest"], png_bytes = training.get(index)
            self.timing["nearest"] += time.perf_counter() - t3
            record["nearest"] = {"bytes_per_view": png_bytes, "index": index,
                                 "angle_deg": angle}

    def rate_distortion(self, thresholds: Sequence[float], step_factors: Sequence[float],
                        qualities: Sequence[int], progress: bool, pca: bool) -> None:
        """The rate-distortion sweep on the first ``rd_views`` views."""
        t0 = time.perf_counter()
        self.evaluation.rd = _rate_distortion(self.model, self.rd_refs, thresholds,
                                              step_factors, qualities, self.metrics,
                                              progress=progress, pca=pca)
        self.timing["rate_distortion"] = time.perf_counter() - t0
        self.evaluation.info["rd_views"] = len(self.rd_refs)

    def result(self) -> Evaluation:
        """The evaluation, with the WebP database's storage and the timings."""
        evaluation = self.evaluation
        if self.webp_db is not None:
            evaluation.info["webp_db_storage_bytes"] = self.webp_db.storage_bytes
            evaluation.info["webp_db_storage_estimated"] = self.webp_db.storage_estimated
        evaluation.timing_s = {k: round(v, 3) for k, v in self.timing.items()}
        return evaluation

    def finish(self, bar: Any) -> None:
        """Collect the oldest view's metrics into its record (and sample), in order."""
        i, record, futures, sample, rest_job = self.in_flight.pop(0)
        t0 = time.perf_counter()
        results = {name: f.result() for name, f in futures.items()}
        rest_measured = rest_job[1].result() if rest_job is not None else None
        self.timing["metrics_wait"] += time.perf_counter() - t0
        for name, c in results.items():
            record[name].update(c.values())
        if rest_measured is not None:
            record["rest"] = rest_record(rest_job[0], rest_measured)
            self.rest_hints.update(rest_measured["hints"])
        if sample is not None:
            sample.update({f"flip_{name}": results[name].flip_map
                           for name in _FLIP_MAPS if name in results})
            self.evaluation.samples.append(sample)
        self.evaluation.views.append(record)
        if self.on_view is not None:
            self.on_view(i, record)
        bar.advance()


def _moving_coarse() -> float:
    from host.fit.motion import DEFAULT_COARSE

    return float(DEFAULT_COARSE)


def _motion_source(model: Any, scene: Any, deadline_s: float, start: tuple[float, float],
                   stride: int | None = None, slowdown: float = 1.0) -> Any:
    """A model without the standalone table: `MotionScores` (absolute scores) at ``stride``,
    or the one a warm-up drag from ``start`` settles on (at least the sparsest: evaluate
    measures frames that ray-cast)."""
    from device_runtime.runtime import canonical_view
    from host.evaluate.device_path import UNBOUNDED_S, SlowRenderer
    from host.fit.motion import MotionScores

    if stride is None:
        probe = MotionScores(model, scene if slowdown == 1.0 else SlowRenderer(scene, slowdown),
                             budget_s=deadline_s)
        probe.prepare()
        for i in range(MOTION_WARMUP):
            probe.frame(canonical_view(start[0] + MOTION_STEP_DEG * i, start[1]))
        stride = probe.choose_stride() or probe.strides[-1]
    # Every measured frame ray-casts at that stride, however loaded the machine is now: with
    # the deadline's budget a slow moment would make a frame the prior alone (stride 0), and
    # the figures would depend on the load (and differ between two runs of the same views).
    return MotionScores(model, scene, budget_s=UNBOUNDED_S, strides=(max(1, int(stride)),))


def _mean_point(rows: list[dict]) -> dict:
    out = {}
    for k in ("bytes_per_view", "psnr", "ssim", "flip", "psnr_object", "ssim_object",
              "flip_object"):
        vals = np.array([r[k] for r in rows], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        out[k] = float(vals.mean()) if vals.size else math.nan
    return out


def _rate_distortion(
    model: Any,
    refs: list[tuple[np.ndarray, np.ndarray, float, float]],
    thresholds: Sequence[float],
    step_factors: Sequence[float],
    qualities: Sequence[int],
    metrics: _Metrics,
    *,
    progress: bool,
    pca: bool = True,
) -> list[dict]:
    settings = _pca_settings(model, thresholds, step_factors) if pca else []
    jobs: list[tuple[dict, list[tuple[int, Future]]]] = []
    total = len(settings) + len(CODECS) * len(qualities)
    with _progress("rate-distortion", total, unit=" settings", quiet=not progress) as bar:
        for s in settings:
            m = model if s["own"] else model.truncated(s["counts"], score_step=s["step"])
            path = DevicePath(m)
            point = {"kind": "pca", "label": s["label"], "setting": s["setting"],
                     "own": s["own"], "score_step": s["step"],
                     "components_per_cell": float(np.mean(s["counts"]))}
            rows = []
            for truth, mask, phi, theta in refs:
                frame, size = path.frame(phi, theta)
                rows.append((size, metrics.submit(truth, frame, mask, False)))
            jobs.append((point, rows))
            if s["own"]:  # the oracle: this eigenspace fed the true views' own scores
                rows = []
                for truth, mask, _phi, _theta in refs:
                    frame, size = path.projection_frame(truth)
                    rows.append((size, metrics.submit(truth, frame, mask, False)))
                jobs.append(({**point, "kind": "projection", "label": "projection",
                              "own": False}, rows))
            bar.advance()
        for codec in CODECS:
            for q in qualities:
                rows = []
                for truth, mask, _phi, _theta in refs:
                    coded = encode_image(truth, codec, int(q))
                    rows.append((coded.size_bytes,
                                 metrics.submit(truth, coded.decode(), mask, False)))
                jobs.append(({"kind": codec, "label": f"q={q}", "setting": {"quality": int(q)},
                              "own": False}, rows))
                bar.advance()
    points = []
    for point, rows in jobs:
        values = []
        for size, future in rows:
            c = future.result()
            values.append({"bytes_per_view": size, **c.values()})
        points.append({**point, **_mean_point(values)})
    return points
