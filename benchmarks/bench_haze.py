"""The device's own frame on the black background, before and after the noise floor.

Usage::

    .venv/bin/python benchmarks/bench_haze.py DB.cdb [DB.cdb ...] --fits DIR
        [--views random:40] [--rest] [--time] [--json OUT]

For each database (rendered with depth; e.g. the shared ``/work/cache/NAME-256.cdb``), the
model ``DIR/NAME.ecs`` is fitted with ``eigencast fit``'s defaults when it is not there yet
(its image carries the noise floor, `host.fit.floor`, and names ``warp-depth-3``). The
*before* image is the same image as the fit wrote it without the floor: the section removed
and the splat filter chosen again without it (`choose_splat_tent`: what the fit wrote
before), so both warp the same eigenspace and depth. Over the novel views (``--views``, as
``eigencast evaluate``'s), each ray-cast with the model's render settings:

* the **background**: pixels whose ray-cast is 0 on every channel; **near**: those within 8
  pixels (chessboard) of a pixel that is not;
* of each own frame (`device_runtime.prediction.OwnFrames`: the depth warp), the share of
  the background (and of near) whose largest channel is above 8, the largest channel's
  maximum and mean over the background, and the object SSIM (the ray-cast's opacity mask,
  `host.evaluate.alpha_object_mask`);
* the same for the blend of the predicted scores (the own frame of an image without depth,
  and what a served device shows before the warp is made: the floor does not change it);
* ``--rest``: the same for the frame at rest (the own frame plus the complete correction,
  evaluate's ``pca_predict``, `host.evaluate.ServedFrames.at_rest`);
* ``--time``: the own frame's time, before and after interleaved frame by frame (which one
  first alternating), along 5 passes of a drag of 24 3-degree steps through the neighbours
  (the cache misses included), in this process (run it as ``OPENBLAS_NUM_THREADS=1 taskset
  -c 0 ...`` for the device's one core).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

#: A background pixel of the own frame counts as painted when its largest channel is above
#: this (the issue's measure).
PAINTED = 8
#: Near the object: within this many pixels of a pixel the ray-cast shows.
NEAR_PX = 8
DRAG_FRAMES = 24
DRAG_STEP_DEG = 3.0
DRAG_PASSES = 5


class _Tally:
    """One kind of frame's background and object figures over the views."""

    def __init__(self) -> None:
        self.bg = self.near = self.painted = self.painted_near = 0
        self.total = 0.0
        self.top = 0
        self.ssim: list[float] = []

    def add(self, truth: np.ndarray, frame: np.ndarray, bg: np.ndarray, near: np.ndarray,
            mask: np.ndarray) -> None:
        from host.evaluate.metrics import structural_similarity

        top = frame.max(axis=2)
        self.bg += int(bg.sum())
        self.near += int(near.sum())
        self.painted += int((bg & (top > PAINTED)).sum())
        self.painted_near += int((near & (top > PAINTED)).sum())
        self.total += float(top[bg].sum())
        self.top = max(self.top, int(top[bg].max()) if bg.any() else 0)
        self.ssim.append(structural_similarity(truth, frame, mask=mask))

    def row(self) -> dict:
        return {"background_px": self.bg, "near_px": self.near,
                "painted": self.painted / max(self.bg, 1),
                "painted_near": self.painted_near / max(self.near, 1),
                "max": self.top, "mean": self.total / max(self.bg, 1),
                "ssim_object": float(np.mean(self.ssim))}


def _model(db: Path, fits: Path) -> Path:
    out = fits / (db.name.removesuffix(".cdb") + ".ecs")
    if not out.exists():
        from host.cli import main as eigencast

        cache = fits / (db.name.removesuffix(".cdb") + "-cache")
        if eigencast(["fit", str(db), "-o", str(out), "--cache", str(cache)]) != 0:
            raise SystemExit(f"bench_haze: fitting {db} failed")
    return out


def _before(image, db):
    """``image`` as the fit wrote it without the noise floor."""
    from device_runtime.synthesis import NOISE_FLOOR_SECTION
    from host.evaluate.splat_filter import choose_splat_tent

    old = replace(image, sections={k: v for k, v in image.sections.items()
                                   if k != NOISE_FLOOR_SECTION},
                  synthesis=dict(image.synthesis))
    choose_splat_tent(old, db, quiet=True)
    return old


def _volume(db_path: Path, fits: Path, spec: str, rest: bool, timing: bool) -> dict:
    from scipy import ndimage

    from device_runtime.prediction import OwnFrames, prediction_view
    from host.evaluate import ServedFrames, alpha_object_mask
    from host.fit.model import HostModel, read_model_image
    from host.render.camera import parse_view_set
    from host.render.cinema import CinemaDB
    from host.render.settings import RenderSettings, ViewRenderer

    path = _model(db_path, fits)
    db = CinemaDB.open(db_path)
    after = HostModel.load(path)
    images = {"before": _before(read_model_image(path), db), "after": after.image}
    models = {"before": HostModel.from_image(images["before"], after.annex()),
              "after": after}
    scene = ViewRenderer.open(RenderSettings.from_record(after.render_settings, what=str(path)))
    own = {k: OwnFrames(m.image) for k, m in models.items()}
    served = {k: ServedFrames(m, scene) for k, m in models.items()} if rest else {}
    tally = {f"{kind}_{k}": _Tally() for kind in ("own", "blend", "rest") for k in models}
    views = [prediction_view(v.phi_deg, v.theta_deg) for v in parse_view_set(spec).views]
    for view in views:
        truth, alpha = scene.render(*view)
        obj = truth.max(axis=2) > 0
        bg = ~obj
        near = bg & ndimage.binary_dilation(obj, structure=np.ones((3, 3), bool),
                                            iterations=NEAR_PX)
        mask = alpha_object_mask(alpha)
        for k in models:
            tally[f"own_{k}"].add(truth, own[k].frame(*view), bg, near, mask)
            blend = own[k].reconstructor.update(own[k].predictor(*view)).copy()
            tally[f"blend_{k}"].add(truth, blend, bg, near, mask)
            if rest:
                tally[f"rest_{k}"].add(truth, served[k].at_rest(*view)[0], bg, near, mask)
    out = {"volume": db_path.name.removesuffix(".cdb"), "views": len(views), "spec": spec,
           "methods": {k: m.image.synthesis["method"] for k, m in models.items()},
           "floor": _floor_summary(after.image)}
    out.update({name: t.row() for name, t in tally.items() if t.ssim})
    if timing:
        out["time"] = _time({k: m.image for k, m in models.items()}, views[0])
    return out


def _floor_summary(image) -> dict:
    from device_runtime.synthesis import NOISE_FLOOR_SECTION, OBJECT_LEVEL

    floor = image.sections[NOISE_FLOOR_SECTION]
    raised = floor[floor > OBJECT_LEVEL]
    return {"cells": int(raised.size), "of": int(floor.size),
            "median": float(np.median(raised)) if raised.size else float(OBJECT_LEVEL),
            "max": int(floor.max())}


def _time(images: dict, start: tuple[float, float]) -> dict:
    """Seconds per own frame along a drag (`DRAG_PASSES` passes, each with fresh caches),
    before and after interleaved frame by frame, which one first alternating."""
    from device_runtime.prediction import OwnFrames, prediction_view

    drag = [prediction_view(start[0] + DRAG_STEP_DEG * i, start[1])
            for i in range(DRAG_FRAMES)]
    spent = {k: [] for k in images}
    for rep in range(DRAG_PASSES):
        own = {k: OwnFrames(image) for k, image in images.items()}
        for k in own:  # warm: the warp's grid and scratch (the drag's far end: other views)
            own[k].frame(*drag[-1])
        for i, view in enumerate(drag):
            for k in (list(own) if (i + rep) % 2 else list(own)[::-1]):
                t0 = time.perf_counter()
                own[k].frame(*view)
                spent[k].append(time.perf_counter() - t0)
    b, a = (np.array(spent[k]) for k in ("before", "after"))
    return {"frames": b.size, "median_s": {"before": float(np.median(b)),
                                           "after": float(np.median(a))},
            "ratio_median": float(np.median(a / b)), "ratio_total": float(a.sum() / b.sum())}


def _table(rows: list[dict]) -> str:
    kinds = [k for k in ("own", "blend", "rest") if f"{k}_after" in rows[0]]
    head = ("| volume | frame | background > 8 before -> after | near > 8 | mean | max | "
            "object SSIM |\n|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        for kind in kinds:
            b, a = r[f"{kind}_before"], r[f"{kind}_after"]
            lines.append(
                f"| {r['volume']} | {kind} | {100 * b['painted']:.2f} % -> "
                f"{100 * a['painted']:.2f} % | {100 * b['painted_near']:.1f} % -> "
                f"{100 * a['painted_near']:.1f} % | {b['mean']:.2f} -> {a['mean']:.2f} | "
                f"{b['max']} -> {a['max']} | {b['ssim_object']:.4f} -> "
                f"{a['ssim_object']:.4f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("databases", nargs="+", type=Path)
    parser.add_argument("--fits", type=Path, required=True,
                        help="folder of the models (fitted there when absent)")
    parser.add_argument("--views", default="random:40")
    parser.add_argument("--rest", action="store_true", help="also the frames at rest")
    parser.add_argument("--time", action="store_true", help="also the own frame's time")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    args.fits.mkdir(parents=True, exist_ok=True)
    rows = []
    for db in args.databases:
        row = _volume(db, args.fits, args.views, args.rest, args.time)
        rows.append(row)
        print(_table([row]).split("\n", 2)[2], flush=True)
        if "time" in row:
            t = row["time"]
            print(f"  own frame time: median {1e3 * t['median_s']['before']:.2f} -> "
                  f"{1e3 * t['median_s']['after']:.2f} ms; after / before per frame: median "
                  f"x{t['ratio_median']:.3f}, total x{t['ratio_total']:.3f} over {t['frames']} "
                  "frames", flush=True)
    print(_table(rows))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
