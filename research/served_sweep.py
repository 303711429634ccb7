"""The one served path across volumes: docs/design-notes.md, "Serving" (issue 23).

For every case (a model with depth and the standalone table) this runs

1. ``eigencast evaluate MODEL --views random:N:SEED --rd-views N --rd-codecs-only --json``
   (no nearest view, no WebP database): the device's own frame (``pca_warp``), the frame
   served at rest (``pca_predict``) and while moving at the default deadline
   (``pca_motion``), ``pca_render``, the codecs' curves and every method's blockiness;
2. in this process, on the same views, the frames served while moving at the stride the
   default deadline picks now (the load of the machine changes it), at the stride a host
   whose ray-casts are ``--slowdown`` times slower picks, and at fixed strides
   (`host.evaluate.ServedFrames`, the code evaluate measures with), object SSIM only;

and prints the tables of section 10 (markdown). Results are cached as JSON under ``--out``
(one file per case and part), so an interrupted sweep resumes and ``--tables-only`` reprints.

    .venv/bin/python research/served_sweep.py                      # every case (hours)
    .venv/bin/python research/served_sweep.py --cases tooth-128 --views 8   # a quick look
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DB = Path("/work/cache/db")
VAR = Path("/work/cache/eval23/var")
#: (label, model, what varies): the shared volumes at 128/256/512, others at 256, variations.
#: The models under DB are named after their label.
CASES = [(label, DB / f"{label}.ecs", what) for label, what in (
    ("tooth-128", "cells 16"),
    ("vismale_head-128", "cells 16"),
    ("tooth-256", "cells 16"),
    ("vismale_head-256", "cells 16"),
    ("mni152-256", "cells 16"),
    ("brainsmall-256", "cells 16"),
    ("engine-256", "cells 16"),
    ("headsq-256", "cells 16"),
    ("tooth-512", "cells 30"),
    ("vismale_head-512", "cells 30"),
)] + [
    ("tooth-256-c30", VAR / "tooth-256-c30.ecs", "cells 30"),
    ("tooth-256-fib300", VAR / "tooth-256-fib300.ecs", "300 views (fibonacci)"),
    ("vismale_head-256-muscle", VAR / "vismale_head-256-muscle.ecs", "ct-muscle (translucent)"),
    ("vismale_head-256-skin", Path("/work/cache/warp22/tl/head-tl-256.ecs"),
     "skin-bone (translucent)"),
]
SEED = 23


def _main_json(label: str, model: Path, views: int, out: Path) -> dict:
    path = out / f"{label}.json"
    if path.exists():
        return json.loads(path.read_text())
    cmd = [str(REPO / ".venv/bin/eigencast"), "evaluate", str(model), "--views",
           f"random:{views}:{SEED}", "--rd-views", str(views), "--rd-codecs-only", "--json",
           "--no-nearest", "--webp-db-quality", "0", "--samples-shown", "0"]
    print(f"[{label}] {' '.join(cmd[1:])}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    result = json.loads(res.stdout)
    result["sweep_seconds"] = time.perf_counter() - t0
    path.write_text(json.dumps(result))
    return result


def _moving_json(label: str, model_path: Path, views: int, strides: list[int],
                 slowdown: float, deadline_s: float, out: Path) -> dict:
    """Object SSIM and bytes of the frames served while moving at fixed strides and at the
    stride a ``slowdown`` times slower ray-caster gets, per view, beside the own frame."""
    path = out / f"{label}-moving.json"
    if path.exists():
        return json.loads(path.read_text())
    from host.evaluate import ServedFrames, alpha_object_mask
    from host.fit.model import HostModel
    from host.render.camera import parse_view_set
    from host.render.settings import RenderSettings, ViewRenderer

    print(f"[{label}] moving: strides {strides}, slowdown {slowdown:g}", file=sys.stderr,
          flush=True)
    model = HostModel.load(model_path)
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what=label))
    pairs = [(v.phi_deg, v.theta_deg) for v in parse_view_set(f"random:{views}:{SEED}").views]
    served = ServedFrames(model, scene)
    variants = {"deadline": served.pick_stride(deadline_s, pairs[0]),
                f"slow x{slowdown:g}": served.pick_stride(deadline_s, pairs[0],
                                                          slowdown=slowdown),
                **{f"stride {s}": s for s in strides}}
    sources = {}
    for name, stride in variants.items():
        sources[name] = ServedFrames(model, scene)
        sources[name].set_stride(stride)
    rows = []
    for phi, theta in pairs:
        truth, alpha = scene.render(phi, theta)
        mask = alpha_object_mask(alpha)
        row = {"phi_deg": phi, "theta_deg": theta,
               "own": _ssim(truth, served.own_frame(phi, theta), mask)}
        for name, source in sources.items():
            frame, size = source.moving(phi, theta)
            row[name] = {"ssim_object": _ssim(truth, frame, mask), "bytes": size}
        rows.append(row)
    result = {"strides": variants, "views": rows, "slowdown": slowdown}
    path.write_text(json.dumps(result))
    return result


def _ssim(truth, frame, mask) -> float:  # noqa: ANN001
    from host.evaluate import compare_images

    return compare_images(truth, frame, mask=mask, metrics=("ssim",)).ssim_object


def _f(v, d: int = 3) -> str:  # noqa: ANN001
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{d}f}"


def _b(v) -> str:  # noqa: ANN001
    return "–" if v is None else f"{v:.0f}"


def tables(results: dict[str, dict], moving: dict[str, dict], groups: dict[str, str]) -> str:
    lines = ["### At rest (object SSIM; bytes per view of the correction)", "",
             "| case | varies | views | warp | render | **at rest** | ≥ both | bytes | "
             "WebP / AVIF bytes for that SSIM | WebP / AVIF SSIM at those bytes |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for label, s in results.items():
        w, r, p = (s[m]["ssim_object"] for m in ("pca_warp", "pca_render", "pca_predict"))
        eq = s["pca_predict"]["equal_quality"]
        lines.append(
            f"| {label} | {groups[label]} | {s['views']} | {_f(w)} | {_f(r)} | **{_f(p)}** | "
            f"{'yes' if p >= max(w, r) else '**no**'} | {_b(s['pca_predict']['bytes_per_view'])} | "
            f"{_b(eq['webp']['bytes_for_ssim'])} / {_b(eq['avif']['bytes_for_ssim'])} | "
            f"{_f(eq['webp']['ssim_at_bytes'])} / {_f(eq['avif']['ssim_at_bytes'])} |")
    lines += ["", "### While moving (3°/frame, default deadline 33 ms on this machine)", "",
              "| case | stride | warp | **moving** | mean gain | worst view | views < warp − 0.01 "
              "| bytes/frame | WebP / AVIF SSIM at those bytes (smallest file) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for label, s in results.items():
        mo = s["pca_motion"]
        eq = mo["equal_quality"]
        at = " / ".join(
            _f(eq[c]["ssim_at_bytes"]) if eq[c]["ssim_at_bytes"] is not None
            else f"< {_b(eq[c]['min_bytes'])} B" for c in ("webp", "avif"))
        lines.append(
            f"| {label} | {mo['stride']:.0f} | {_f(s['pca_warp']['ssim_object'])} | "
            f"**{_f(mo['ssim_object'])}** | {mo['gain_over_own']:+.4f} | "
            f"{mo['worst_gain_over_own']:+.4f} | {mo['views_below_own']} | "
            f"{_b(mo['bytes_per_view'])} | {at} |")
    if moving:
        names = list(next(iter(moving.values()))["strides"])
        lines += ["", "### While moving at fixed strides and on a slower host (object SSIM "
                  "gain over the own frame: mean / worst view, bytes per frame)", "",
                  "| case | own | " + " | ".join(names) + " |",
                  "|---|---|" + "---|" * len(names)]
        for label, mv in moving.items():
            cells = []
            for name in names:
                gains = [v[name]["ssim_object"] - v["own"] for v in mv["views"]]
                size = sum(v[name]["bytes"] for v in mv["views"]) / len(mv["views"])
                extra = (f" (stride {mv['strides'][name]})"
                         if not name.startswith("stride") else "")
                cells.append(f"{sum(gains) / len(gains):+.4f} / {min(gains):+.4f}, "
                             f"{size:.0f} B{extra}")
            own = sum(v["own"] for v in mv["views"]) / len(mv["views"])
            lines.append(f"| {label} | {own:.3f} | " + " | ".join(cells) + " |")
    lines += ["", "### Cell seams (blockiness: border / inside neighbour differences, object "
              "pixels; the ray-cast's own is the floor)", "",
              "| case | ray-cast | own frame | at rest | moving | interpolated (pca) | "
              "ray-cast scores | WebP | AVIF |", "|---|---|---|---|---|---|---|---|---|"]
    for label, s in results.items():
        lines.append(f"| {label} | {_f(s['raycast_blockiness'])} | " + " | ".join(
            _f(s[m]["blockiness"]) for m in ("pca_warp", "pca_predict", "pca_motion", "pca",
                                             "pca_render", "webp", "avif")) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", help="comma-separated labels (default: every case whose "
                                        "model exists)")
    parser.add_argument("--views", type=int, default=24, help="random views per case at "
                                                              "128/256 (default 24)")
    parser.add_argument("--views-512", type=int, default=16, help="... at 512 (default 16)")
    parser.add_argument("--strides", default="2,4,8",
                        help="fixed moving strides (default 2,4,8)")
    parser.add_argument("--slowdown", type=float, default=8.0,
                        help="the slower host's ray-casts take this many times longer "
                             "(default 8)")
    parser.add_argument("--out", type=Path, default=Path("/work/cache/eval23/sweep"))
    parser.add_argument("--tables-only", action="store_true",
                        help="print the tables of the cases already measured")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    wanted = set(args.cases.split(",")) if args.cases else None
    strides = [int(s) for s in args.strides.split(",") if s]
    results, moving, groups = {}, {}, {}
    for label, model, group in CASES:
        if wanted is not None and label not in wanted:
            continue
        groups[label] = group
        views = args.views_512 if "-512" in label else args.views
        if args.tables_only:
            if (args.out / f"{label}.json").exists():
                results[label] = json.loads((args.out / f"{label}.json").read_text())
            if (args.out / f"{label}-moving.json").exists():
                moving[label] = json.loads((args.out / f"{label}-moving.json").read_text())
            continue
        if not model.exists():
            print(f"[{label}] {model} not there yet: skipped", file=sys.stderr)
            continue
        results[label] = _main_json(label, model, views, args.out)
        moving[label] = _moving_json(label, model, views, strides, args.slowdown, 1 / 30,
                                     args.out)
    print(tables(results, moving, groups))
    return 0


if __name__ == "__main__":
    sys.exit(main())
