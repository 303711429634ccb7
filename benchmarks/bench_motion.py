"""Frames while the view moves: ``serve --scores motion`` against interpolated scores and the
full projection (issue 13, "What done means").

Usage::

    .venv/bin/python benchmarks/bench_motion.py [MODEL.ecs ...] [--quick] \\
        [--frames 40] [--step 3] [--theta 17.5] [--deadline-ms 33] [--rest 3] [--json out.json]

Without a model it renders and fits a small one of the built-in tooth first (128 px, a
minute on 2 cores; what ``make bench`` runs). ``--quick``: 10 frames, 1 resting view.

For each model (its render settings name the volume), in one run on this machine:

1. **A drag**: ``--frames`` views along phi, ``--step`` degrees apart, at elevation
   ``--theta`` (between grid rows), made by `host.fit.motion.MotionScores` at the deadline,
   in real time (each frame's ray-cast, recovery and packet encoding), after a few warm-up
   frames. **Host frames/s** = frames delivered / wall time, beside a full ray-cast's time
   measured in the same run (median of 3), and the strides used.
2. **Object SSIM** (`host.evaluate.structural_similarity` over alpha >= `OBJECT_ALPHA_MIN`)
   of the device frames of the drag's scores, of the interpolated scores at the same views
   and of `HostModel.project` of the full ray-cast (the oracle), and the **gap closed**
   ``(motion - interpolated) / (projection - interpolated)``.
3. **Bytes per frame as streamed**: the three score streams along the drag coded as
   `serve` codes them (`FrameEncoder`: a key frame, then deltas).
4. **At rest**: ``--rest`` views each given one moving frame, then `MotionScores.refine`
   until the full projection; the wall time from the first frame's start to the projection.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from device_runtime.runtime import canonical_view
from host.evaluate import structural_similarity
from host.fit.model import HostModel
from host.fit.motion import DEFAULT_COARSE, MotionScores
from host.link.serving import FrameEncoder
from host.render.settings import OBJECT_ALPHA_MIN, RenderSettings, ViewRenderer


def _stream_bytes(model: HostModel, views: list, scores: list | None) -> float:
    enc = FrameEncoder(model, first_frame=1)
    sizes = [len(enc.encode(v, scores=None if scores is None else scores[i]).packet)
             for i, v in enumerate(views)]
    return float(np.mean(sizes))


def measure(path: Path, *, frames: int, step: float, theta: float, deadline_s: float,
            rest: int, coarse: float = DEFAULT_COARSE, warmup: int = 5) -> dict:
    """The figures of one model (module docstring)."""
    model = HostModel.load(path)
    settings = RenderSettings.from_record(model.render_settings, what=str(path))
    renderer = ViewRenderer.open(settings, what=str(path))
    renderer.render(0.0, 0.0)  # compile and warm
    full = []
    for phi in (33.0, 151.0, 262.0):
        t0 = time.perf_counter()
        renderer.render(phi, theta)
        full.append(time.perf_counter() - t0)
    source = MotionScores(model, renderer, budget_s=deadline_s, coarse=coarse)
    t0 = time.perf_counter()
    source.prepare()
    prepare_s = time.perf_counter() - t0
    views = [canonical_view(7.0 + step * i, theta) for i in range(warmup + frames)]
    enc = FrameEncoder(model, first_frame=1)
    for v in views[:warmup]:
        enc.encode(v, scores=source.frame(v).scores)
    made = []
    t0 = time.perf_counter()
    for v in views[warmup:]:
        f = source.frame(v)
        enc.encode(v, scores=f.scores)
        made.append(f)
    wall = time.perf_counter() - t0
    views = views[warmup:]
    strides: dict[str, int] = {}
    for f in made:
        strides[str(f.stride)] = strides.get(str(f.stride), 0) + 1
    ssim: dict[str, list[float]] = {"interpolated": [], "motion": [], "projection": []}
    projected = []
    for v, f in zip(views, made, strict=True):
        truth, alpha = renderer.render(*v)
        mask = alpha >= OBJECT_ALPHA_MIN
        y = model.project(truth)
        projected.append(y)
        for key, scores in (("interpolated", model.scores(*v)), ("motion", f.scores),
                            ("projection", y)):
            frame = model.reconstruct(model.quantize(scores))
            ssim[key].append(structural_similarity(truth, frame, mask=mask))
    mean = {k: float(np.mean(v)) for k, v in ssim.items()}
    gap = mean["projection"] - mean["interpolated"]
    rest_s = []
    for i in range(rest):
        v = canonical_view(40.0 + 97.0 * i, theta - 5.0)
        source.frame(canonical_view(v[0] - step, v[1]))  # arriving from a drag
        t0 = time.perf_counter()
        f = source.frame(v)
        while not f.complete:
            f = source.refine(v)
        rest_s.append(time.perf_counter() - t0)
    return {
        "model": str(path),
        "image": list(model.image.image_shape),
        "cells": list(model.image.cell_shape),
        "deadline_ms": deadline_s * 1e3,
        "coarse": coarse,
        "step_deg": step,
        "frames": frames,
        "ssim": mean,
        "gap_closed": (mean["motion"] - mean["interpolated"]) / gap if gap > 0 else None,
        "host_fps": frames / wall,
        "full_raycast_s": float(np.median(full)),
        "strides": strides,
        "prepare_s": prepare_s,
        "bytes_per_frame": {
            "interpolated": _stream_bytes(model, views, None),
            "motion": _stream_bytes(model, views, [f.scores for f in made]),
            "projection": _stream_bytes(model, views, projected),
        },
        "rest_to_projection_s": rest_s,
    }


def _builtin_model() -> Path:
    import tempfile

    from host.cli import main as eigencast

    work = Path(tempfile.mkdtemp(prefix="bench-motion-"))
    db, model = work / "tooth.cdb", work / "tooth.ecs"
    for cmd in (["render", "builtin:tooth", "-o", str(db), "--views", "grid:36x9", "--size",
                 "128", "--samples", "300", "--no-depth"],
                ["fit", str(db), "-o", str(model), "--cell", "16", "--threshold", "0.99",
                 "--no-standalone"]):
        if eigencast(cmd) != 0:
            raise SystemExit(f"bench_motion: eigencast {cmd[0]} failed")
    return model


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="*", type=Path)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--step", type=float, default=3.0, help="degrees per frame")
    ap.add_argument("--theta", type=float, default=17.5)
    ap.add_argument("--deadline-ms", type=float, default=1000.0 / 30.0)
    ap.add_argument("--rest", type=int, default=3)
    ap.add_argument("--coarse", type=float, default=None,
                    help="moving frames' sample-step factor (default: MotionScores')")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.quick:
        args.frames, args.rest = 10, 1
    if not args.models:
        args.models = [_builtin_model()]
    out = []
    for path in args.models:
        r = measure(path, frames=args.frames, step=args.step, theta=args.theta,
                    deadline_s=args.deadline_ms / 1e3, rest=args.rest,
                    **({} if args.coarse is None else {"coarse": args.coarse}))
        out.append(r)
        b = r["bytes_per_frame"]
        print(f"{path.name}: {r['image'][1]}x{r['image'][0]} cells {r['cells'][0]}, "
              f"{r['step_deg']:g} deg/frame, deadline {r['deadline_ms']:.0f} ms, coarse "
              f"{r['coarse']:g}")
        print(f"  object SSIM interpolated {r['ssim']['interpolated']:.3f}, motion "
              f"{r['ssim']['motion']:.3f}, projection {r['ssim']['projection']:.3f}: gap closed "
              f"{100 * (r['gap_closed'] or 0):.0f} %")
        print(f"  host {r['host_fps']:.1f} frames/s (strides {r['strides']}); a full ray-cast "
              f"{r['full_raycast_s'] * 1e3:.0f} ms ({1 / r['full_raycast_s']:.1f}/s); factors "
              f"{r['prepare_s']:.1f} s once")
        print(f"  bytes/frame as streamed: interpolated {b['interpolated']:.0f}, motion "
              f"{b['motion']:.0f} ({b['motion'] / b['interpolated']:.2f}x), projection "
              f"{b['projection']:.0f}")
        rest = ", ".join(f"{s:.2f}" for s in r["rest_to_projection_s"])
        print(f"  at rest: the projection after {rest} s")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
