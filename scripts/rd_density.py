"""How dense must a training grid be for view blending to reach the oracle?

Any score interpolation is a linear blend of (projected) training views, so the blend of the
*true* training images with the same weights shows what interpolation can reach at a given
view density, independently of the eigenspace. For each grid density ``grid:NPHIxNTHETA`` this
ray-casts only the training views that the held-out test views need (4 per view for
``bilinear``, 16 for ``bicubic``), blends them with the interpolation weights and compares with
the test database's ray-casts (SSIM, FLIP, PSNR on object pixels: ray-cast alpha >= 0.5/255).

Usage::

    .venv/bin/python scripts/rd_density.py TEST.cdb -o density.json --views 40 \\
        --grids 100x15,100x30,100x60,200x30 [--methods bilinear,bicubic]

Produces: docs/rate-distortion.md, section 2 "View interpolation" (the density study).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.evaluate import compare_images
from host.fit.interpolate import ScoreInterpolator
from host.render.camera import parse_view_set
from host.render.cinema import CinemaDB
from host.render.settings import OBJECT_ALPHA_MIN, RenderSettings, ViewRenderer


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("test_db")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--grids", default="100x15,100x30,100x60,200x30")
    ap.add_argument("--methods", default="bilinear,bicubic")
    args = ap.parse_args(argv)

    test = CinemaDB.open(args.test_db)
    settings = RenderSettings.from_record(test.settings, what=args.test_db)
    scene = ViewRenderer.open(settings, what=args.test_db)
    n = min(args.views, test.n_views)
    phis, thetas = np.mod(test.phi_deg[:n], 360.0), test.theta_deg[:n]
    truths, masks = [], []
    for k in range(n):
        truth = test.read_image(k)
        rgb, alpha = scene.render(phis[k], thetas[k])  # the mask; checks the settings too
        if not np.array_equal(rgb, truth):
            raise SystemExit(f"view {k}: the renderer does not reproduce the test database")
        truths.append(truth)
        masks.append(alpha >= OBJECT_ALPHA_MIN)
    results = []
    for grid in [g for g in args.grids.split(",") if g]:
        views = parse_view_set(f"grid:{grid}")
        tphi = np.array([v.phi_deg for v in views.views])
        ttheta = np.array([v.theta_deg for v in views.views])
        cache: dict[int, np.ndarray] = {}
        t0 = time.perf_counter()
        for method in [m for m in args.methods.split(",") if m]:
            interp = ScoreInterpolator(tphi, ttheta, np.zeros((tphi.size, 1)), method=method)
            rows = []
            for k in range(n):
                idx, w = interp.weights(phis[k], thetas[k])
                acc = np.zeros(truths[k].shape, np.float32)
                for i, wi in zip(idx.tolist(), w.tolist()):
                    if wi == 0.0:
                        continue
                    if i not in cache:
                        cache[i] = scene.render_rgb8(tphi[i], ttheta[i])
                    acc += np.float32(wi) * cache[i].astype(np.float32)
                frame = np.clip(np.rint(acc), 0, 255).astype(np.uint8)
                rows.append(compare_images(truths[k], frame, mask=masks[k]).values())
            mean = {key: float(np.mean([r[key] for r in rows])) for key in rows[0]}
            n_phi, n_theta = (int(v) for v in grid.split("x"))
            results.append({"grid": grid, "method": method, "views": n,
                            "training_views": int(tphi.size),
                            "phi_step_deg": 360.0 / n_phi, "theta_step_deg": 180.0 / n_theta,
                            **mean})
            print(f"grid:{grid} {method}: SSIM obj {mean['ssim_object']:.4f}, FLIP obj "
                  f"{mean['flip_object']:.4f}, SSIM {mean['ssim']:.4f} "
                  f"({len(cache)} renders, {time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    Path(args.output).write_text(json.dumps({"test_db": args.test_db, "results": results},
                                            indent=1))
    print("| grid | method | step phi x theta | SSIM obj | FLIP obj | SSIM | FLIP |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['grid']} | {r['method']} | {r['phi_step_deg']:.2f} x "
              f"{r['theta_step_deg']:.1f} | {r['ssim_object']:.4f} | {r['flip_object']:.4f} | "
              f"{r['ssim']:.4f} | {r['flip']:.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
