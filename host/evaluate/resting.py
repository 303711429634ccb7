"""A resting view's steps, measured: quality and cumulative bytes after each packet ``serve``
sends, against the smallest JPEG, WebP and AVIF file of the same quality.

`ServedFrames.rest` gives the steps of a resting view (the device's own frame, the complete
correction when the plan sends it, each refinement layer, the exact layer) with the frame
the device shows after each. `measure_rest` (run in evaluate's metric workers) scores each
step's frame against the ray-cast the plan refines to (PSNR, SSIM and FLIP, whole frame and
object pixels, `compare_images`) and, when asked, finds per lossy step and codec the smallest
file of the ray-cast that reaches the step's object SSIM (`CodecLadder.smallest`, the
codecs' settings of `encode_image`: WebP method 6, AVIF speed 4, JPEG optimized), with that
file's whole-frame SSIM and FLIP, and the smallest files reaching the step's whole-frame SSIM
and its FLIP. For the exact step it codes the ray-cast as an optimized PNG and as WebP
lossless (Pillow's defaults: method 4, quality 80, ``exact``). `rest_record` makes the
per-view JSON record, `summarize_rest` the medians and worst ratios over the views
(``Evaluation.summary()["rest"]``).
"""

from __future__ import annotations

import io
import math
from typing import Any

import numpy as np

from host.evaluate.baselines import CODECS, CodecLadder
from host.evaluate.metrics import compare_images

__all__ = [
    "REST_BAR_SSIM",
    "measure_rest",
    "rest_record",
    "summarize_rest",
]

#: The summary's worst ratios to the codecs count the steps from this object SSIM up.
REST_BAR_SSIM = 0.9
#: What the codec equivalents are searched for: (the step's value, higher is better).
_CRITERIA = (("ssim_object", True), ("ssim", True), ("flip", False))
_GROUPS = {"ssim": ("ssim",), "ssim_object": ("ssim",), "flip": ("flip",),
           "flip_object": ("flip",), "psnr": ("psnr",), "psnr_object": ("psnr",)}


class _Measure:
    """``measure(decoded, name)`` of `CodecLadder`: one metric family against the ray-cast
    (SSIM gives the whole frame's and the object's from one map)."""

    def __init__(self, truth: np.ndarray, mask: np.ndarray | None) -> None:
        self.truth = truth
        self.mask = mask

    def __call__(self, decoded: np.ndarray, name: str) -> dict[str, float]:
        c = compare_images(self.truth, decoded, mask=self.mask, metrics=_GROUPS[name])
        return {k: v for k, v in c.values().items() if not math.isnan(v)}


def _lossless_sizes(image: np.ndarray) -> dict[str, int]:
    """Bytes of ``image`` as an optimized PNG and as WebP lossless (Pillow's defaults)."""
    from PIL import Image

    pil = Image.fromarray(image)
    png, webp = io.BytesIO(), io.BytesIO()
    pil.save(png, "PNG", optimize=True)
    pil.save(webp, "WEBP", lossless=True, exact=True)
    return {"png_bytes": len(png.getvalue()), "webp_lossless_bytes": len(webp.getvalue())}


def measure_rest(truth: np.ndarray, mask: np.ndarray | None, frames: list[np.ndarray],
                 kinds: list[str], *, codecs: bool, hints: dict[str, int] | None = None
                 ) -> dict[str, Any]:
    """Score a resting view's steps (module docstring).

    Parameters
    ----------
    truth : ndarray (height, width, 3) uint8
        The ray-cast the steps refine to.
    mask : ndarray (height, width) bool or None
        Its object pixels.
    frames, kinds : lists
        Each step's frame and kind (`RestStep.kind`).
    codecs : bool
        Also find the codec equivalents of the lossy steps (a few dozen encodes).
    hints : dict, optional
        Per codec, a quality setting to start the searches from (the last view's).

    Returns
    -------
    dict
        ``steps``: per step the metrics (`ImageComparison.values`) and, with ``codecs``,
        ``codecs``: per codec ``bytes``, ``quality``, ``ssim_object``, ``ssim``, ``flip`` of
        the smallest file reaching the step's object SSIM (None when quality 100 does not),
        ``bytes_same_ssim`` and ``bytes_same_flip``; ``exact``: ``png_bytes`` and
        ``webp_lossless_bytes`` of the ray-cast (when a step is exact); ``hints``: per codec
        the last quality found.
    """
    m = None if mask is None or not np.asarray(mask).any() else mask
    out: dict[str, Any] = {"steps": [], "hints": dict(hints or {})}
    measure = _Measure(truth, m)
    ladders = ({c: CodecLadder(truth, c, measure) for c in CODECS} if codecs else {})
    for frame, kind in zip(frames, kinds, strict=True):
        step: dict[str, Any] = {k: float(v) for k, v in
                                compare_images(truth, frame, mask=m).values().items()}
        if kind == "exact":
            out["exact"] = _lossless_sizes(truth)
        elif ladders:
            step["codecs"] = {}
            for codec, ladder in ladders.items():
                step["codecs"][codec] = _equivalent(ladder, step, out["hints"])
        out["steps"].append(step)
    return out


def _equivalent(ladder: CodecLadder, step: dict[str, Any], hints: dict[str, int]
                ) -> dict[str, Any] | None:
    """The smallest files of ``ladder``'s codec reaching ``step``'s object SSIM (with its
    SSIM and FLIP), whole-frame SSIM and FLIP; None where the object SSIM is out of reach."""
    found: dict[str, Any] = {}
    for name, higher in _CRITERIA:
        target = step.get(name)
        if target is None or not math.isfinite(target):
            found[name] = None
            continue
        found[name] = ladder.smallest(target, name, higher_is_better=higher,
                                      hint=hints.get(ladder.codec) if name == "ssim_object"
                                      else None)
    main = found["ssim_object"]
    if main is None:
        return None
    hints[ladder.codec] = main.quality
    return {"bytes": main.size_bytes, "quality": main.quality,
            "ssim_object": ladder.value(main.quality, "ssim_object"),
            "ssim": ladder.value(main.quality, "ssim"),
            "flip": ladder.value(main.quality, "flip"),
            "bytes_same_ssim": None if found["ssim"] is None else found["ssim"].size_bytes,
            "bytes_same_flip": None if found["flip"] is None else found["flip"].size_bytes}


def rest_record(rest: Any, measured: dict[str, Any]) -> dict[str, Any]:
    """The per-view JSON record of a resting view (``record["rest"]``): the plan's facts and
    each step's ``kind``, ``bytes`` (cumulative), ``step_bytes``, ``packets``, ``codec``,
    ``residual``, ``planned_quality``, metrics and codec equivalents (`measure_rest`); the
    exact step also with ``png_bytes`` and ``webp_lossless_bytes`` of the ray-cast."""
    steps = []
    for step, values in zip(rest.steps, measured["steps"], strict=True):
        rec = {"kind": step.kind, "bytes": step.bytes, "step_bytes": step.step_bytes,
               "packets": len(step.packets), "codec": step.codec, "residual": step.residual,
               "planned_quality": step.planned_quality, **values}
        if step.kind == "exact":
            rec.update(measured.get("exact") or {})
        steps.append(rec)
    return {"correction_bytes": rest.correction_bytes,
            "skip_correction": rest.skip_correction, "steps": steps}


def _stage_names(steps: list[dict]) -> list[str]:
    """Each step's stage: ``own``, ``correction``, ``layer1``, ``layer2`` ..., ``exact``."""
    names, n = [], 0
    for s in steps:
        if s["kind"] == "layer":
            n += 1
            names.append(f"layer{n}")
        else:
            names.append(s["kind"])
    return names


def _stats(values: list[float], worst: str) -> dict[str, float | None]:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    if not vals:
        return {"median": None, "worst": None}
    return {"median": float(np.median(vals)),
            "worst": float(max(vals) if worst == "max" else min(vals))}


def summarize_rest(views: list[dict]) -> dict[str, Any] | None:
    """Medians over the views of each stage (bytes, metrics; ratios of the cumulative bytes
    to the smallest codec file of the same object SSIM, median and worst), the exact step
    against PNG and WebP lossless, and the worst ratios from object SSIM `REST_BAR_SSIM` up
    (the correction and every lossy layer); None when no view rested."""
    recs = [v["rest"] for v in views if v.get("rest")]
    if not recs:
        return None
    stages: dict[str, list[dict]] = {}
    for r in recs:
        for name, step in zip(_stage_names(r["steps"]), r["steps"], strict=True):
            stages.setdefault(name, []).append(step)
    out: dict[str, Any] = {"views": len(recs),
                           "correction_skipped": sum(bool(r["skip_correction"]) for r in recs),
                           "stages": {}}
    for name, steps in stages.items():
        row: dict[str, Any] = {"views": len(steps)}
        for key in ("bytes", "step_bytes", "ssim_object", "ssim", "flip", "flip_object",
                    "psnr_object"):
            vals = [float(s[key]) for s in steps if s.get(key) is not None]
            row[key] = float(np.median(vals)) if vals else None
        for codec in CODECS:
            ratios = [s["bytes"] / s["codecs"][codec]["bytes"] for s in steps
                      if (s.get("codecs") or {}).get(codec)]
            if ratios:
                row[f"x_{codec}"] = _stats(ratios, "max")
        if name == "exact":
            for key, ref in (("x_webp_lossless", "webp_lossless_bytes"), ("x_png", "png_bytes")):
                row[key] = _stats([s["bytes"] / s[ref] for s in steps if s.get(ref)], "max")
            row["layer_x_webp_lossless"] = _stats(
                [s["step_bytes"] / s["webp_lossless_bytes"] for s in steps
                 if s.get("webp_lossless_bytes")], "max")
            for ref in ("png_bytes", "webp_lossless_bytes"):
                vals = [s[ref] for s in steps if s.get(ref)]
                row[ref] = float(np.median(vals)) if vals else None
        out["stages"][name] = row
    bars: dict[str, Any] = {}
    lossy = [s for r in recs for s in r["steps"] if s["kind"] in ("correction", "layer")
             and s.get("codecs") and (s.get("ssim_object") or 0.0) >= REST_BAR_SSIM]
    for codec in CODECS:
        ratios = [s["bytes"] / s["codecs"][codec]["bytes"] for s in lossy
                  if s["codecs"].get(codec)]
        bars[f"x_{codec}"] = _stats(ratios, "max")
    bars["steps"] = len(lossy)
    out[f"from_ssim_{REST_BAR_SSIM:g}"] = bars
    return out
