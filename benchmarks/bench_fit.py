"""Benchmark eigenspace fitting: time and peak memory of `CellEigenspace.fit`.

For each image size (300 and 512 by default, 1080 with ``--big``) it builds a
cell-major `CellStack` of ``--views`` training images, then fits it in a fresh
child process (so the child's peak RSS is the fit's own: the stack build and
the image generator are not counted) and prints, from the same run:

* the fit time and the child's peak RSS (``VmHWM``: the stack is read with
  positioned reads, so the page cache is not part of it),
* baseline A: reading the whole stack once (the I/O floor of any streamed fit),
* baseline B: a plain ``np.linalg.svd`` of one busy cell's centred data
  (float64), times the number of non-constant cells: what a naive per-cell
  full SVD would cost,
* the ratios fit / baseline.

Without ``--db`` the images are synthetic but realistic: an analytic
orthographic "render" of a rotating, textured, shaded ellipsoid with an
off-centre inner body (3-D procedural texture, Lambert + headlight), on a
black background, over the paper's ``grid:100x15`` view set. Its silhouette,
occlusion and view-dependent shading give a decaying eigen-spectrum much like
a volume rendering's; the black corners give zero-variance cells.

Usage::

    .venv/bin/python benchmarks/bench_fit.py [--sizes 300,512] [--big] [--views 1500] [--quick]
        [--method adaptive] [--cell 30] [--threshold 0.98] [--components 100]
        [--db DB.cdb] [--workdir DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

from host.fit.cells import CellStack
from host.fit.pca import CellEigenspace


def grid_views(n_views: int) -> list[tuple[float, float]]:
    """(phi_deg, theta_deg) of a grid:NPHIx15 view set (or NPHIx1 for few views)."""
    n_theta = 15 if n_views >= 150 and n_views % 15 == 0 else 1
    n_phi = n_views // n_theta
    return [
        (i * 360.0 / n_phi, -90.0 + (j + 0.5) * 180.0 / n_theta)
        for j in range(n_theta)
        for i in range(n_phi)
    ]


def _rotation(phi_deg: float, theta_deg: float) -> np.ndarray:
    """Rows = camera right, up, forward (towards the object) in object coordinates."""
    p, t = np.radians(phi_deg), np.radians(theta_deg)
    eye = np.array([np.cos(t) * np.cos(p), np.cos(t) * np.sin(p), np.sin(t)])
    fwd = -eye
    up0 = np.array([0.0, 0.0, 1.0])
    right = np.cross(fwd, up0)
    if np.linalg.norm(right) < 1e-9:
        right = np.array([-np.sin(p), np.cos(p), 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return np.stack([right, up, fwd])


_BODIES = np.array(
    [
        # centre xyz, semi-axes xyz, opacity: a translucent shell and an inner body
        [0.0, 0.0, 0.0, 1.0, 0.75, 0.6, 0.55],
        [0.25, -0.1, 0.1, 0.35, 0.3, 0.45, 1.0],
    ]
)


@numba.njit(parallel=True, cache=True)
def _render(rot: np.ndarray, size: int, bodies: np.ndarray, out: np.ndarray) -> None:
    fx, fy, fz = rot[2, 0], rot[2, 1], rot[2, 2]
    for row in numba.prange(size):
        py = -((row + 0.5) / size * 2.4 - 1.2)
        for col in range(size):
            px = (col + 0.5) / size * 2.4 - 1.2
            ox = px * rot[0, 0] + py * rot[1, 0] - 3.0 * fx
            oy = px * rot[0, 1] + py * rot[1, 1] - 3.0 * fy
            oz = px * rot[0, 2] + py * rot[1, 2] - 3.0 * fz
            r = 0.0
            g = 0.0
            b = 0.0
            alpha = 0.0
            for k in range(bodies.shape[0]):
                cx, cy, cz = bodies[k, 0], bodies[k, 1], bodies[k, 2]
                ax, ay, az = bodies[k, 3], bodies[k, 4], bodies[k, 5]
                qx, qy, qz = (ox - cx) / ax, (oy - cy) / ay, (oz - cz) / az
                dx, dy, dz = fx / ax, fy / ay, fz / az
                qa = dx * dx + dy * dy + dz * dz
                qb = 2.0 * (qx * dx + qy * dy + qz * dz)
                qc = qx * qx + qy * qy + qz * qz - 1.0
                disc = qb * qb - 4.0 * qa * qc
                if disc <= 0.0:
                    continue
                t = (-qb - np.sqrt(disc)) / (2.0 * qa)
                hx, hy, hz = ox + t * fx, oy + t * fy, oz + t * fz
                nx_, ny_, nz_ = (hx - cx) / ax**2, (hy - cy) / ay**2, (hz - cz) / az**2
                norm = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_) + 1e-12
                lam = -(nx_ * fx + ny_ * fy + nz_ * fz) / norm
                lam = min(1.0, max(0.0, lam))
                tex = (
                    0.5
                    + 0.25 * np.sin(7.0 * hx + 3.0 * hz)
                    + 0.15 * np.sin(19.0 * hy - 11.0 * hx)
                    + 0.10 * np.sin(41.0 * hz + 23.0 * hy)
                )
                shade = 0.25 + 0.75 * lam
                w = (1.0 - alpha) * bodies[k, 6]
                r += w * min(1.0, max(0.0, tex)) * shade
                g += w * min(1.0, max(0.0, 0.6 * tex + 0.3 * hz)) * shade
                b += w * min(1.0, max(0.0, 0.4 + 0.3 * hx)) * shade
                alpha += w
            out[row, col, 0] = np.uint8(min(255.0, max(0.0, np.rint(r * 255.0))))
            out[row, col, 1] = np.uint8(min(255.0, max(0.0, np.rint(g * 255.0))))
            out[row, col, 2] = np.uint8(min(255.0, max(0.0, np.rint(b * 255.0))))


def synthetic_view(phi_deg: float, theta_deg: float, size: int) -> np.ndarray:
    """One synthetic training image, (size, size, 3) uint8 (orthographic, black background)."""
    out = np.empty((size, size, 3), dtype=np.uint8)
    _render(_rotation(phi_deg, theta_deg), size, _BODIES, out)
    return out


def build_synthetic_stack(
    path: Path, n_views: int, size: int, cell_shape: tuple[int, int]
) -> tuple[CellStack, float]:
    views = grid_views(n_views)
    images = (synthetic_view(p, t, size) for p, t in views)
    t0 = time.perf_counter()
    stack = CellStack.build(
        images, len(views), size, size, *cell_shape, path, source=None, progress=True
    )
    return stack, time.perf_counter() - t0


def build_db_stack(db: Path, path: Path, cell_shape: tuple[int, int]) -> tuple[CellStack, float]:
    """A Cinema Spec D database (data.csv with a FILE column) as a stack."""
    import csv

    from PIL import Image

    with open(db / "data.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    files = [db / r["FILE"] for r in rows]
    first = np.asarray(Image.open(files[0]).convert("RGB"))
    h, w = first.shape[:2]
    # (0, 0): the whole image (standard); larger cells are clamped like the fit does
    cs = (min(cell_shape[0], h), min(cell_shape[1], w)) if cell_shape[0] > 0 else (h, w)
    images = (np.asarray(Image.open(p).convert("RGB")) for p in files)
    t0 = time.perf_counter()
    stack = CellStack.build(images, len(files), h, w, *cs, path, progress=True)
    return stack, time.perf_counter() - t0


def child_fit(args: argparse.Namespace) -> None:
    """Runs in the child: fit the stack and print one JSON line."""
    stack = CellStack.open(args.child_fit)
    model = CellEigenspace(
        args.method,
        cell=args.cell,
        components=args.components,
        threshold=args.threshold,
        progress=True,
    )
    t0 = time.perf_counter()
    model.fit(stack)
    fit_s = time.perf_counter() - t0
    busy = np.flatnonzero(model.total_variance_ > 0)
    print(
        json.dumps(
            {
                "fit_s": fit_s,
                "solver": model.solver_,
                "n_cells": int(model.n_components_.size),
                "busy_cells": int(busy.size),
                "mean_k": float(model.n_components_.mean()),
                "mean_k_busy": float(model.n_components_[busy].mean()) if busy.size else 0.0,
                "K": int(model.component_offsets_[-1]),
                "busiest_cell": int(np.argmax(model.total_variance_)),
                "fit_s_per_busy_cell": fit_s / max(1, busy.size),
                "peak_rss_bytes": _peak_rss_bytes(),
            }
        )
    )


def baselines(stack: CellStack, busiest_cell: int, busy_cells: int) -> dict:
    """Baseline A: read the whole stack once; B: full SVD of the busiest cell x busy cells."""
    t0 = time.perf_counter()
    step = max(1, (64 * 2**20) // max(1, stack.n_views * stack.cell_size))
    acc = 0
    for c0 in range(0, stack.n_cells, step):
        block = stack.read_cells(c0, min(stack.n_cells, c0 + step))
        acc ^= int(block[:, :, 0].sum())  # touch the data, cheaply
    read_s = time.perf_counter() - t0
    svd_s = float("nan")  # skipped when one cell's float64 data exceeds 2 GiB
    if stack.n_views * stack.cell_size * 8 <= 2 * 2**30:
        x = stack.read_cells(busiest_cell, busiest_cell + 1)[0].astype(np.float64)
        x -= x.mean(axis=0)
        t0 = time.perf_counter()
        np.linalg.svd(x, full_matrices=False)
        svd_s = time.perf_counter() - t0
    return {"read_once_s": read_s, "svd_one_cell_s": svd_s, "svd_all_s": svd_s * busy_cells}


def _peak_rss_bytes() -> int:
    """This process's own peak RSS: VmHWM (ru_maxrss survives exec on Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="300,512", help="comma-separated square image sizes")
    ap.add_argument("--big", action="store_true", help="also 1080x1080")
    ap.add_argument("--views", type=int, default=1500)
    ap.add_argument("--method", default="adaptive")
    ap.add_argument("--cell", type=int, default=30)
    ap.add_argument("--components", type=int, default=100)
    ap.add_argument("--threshold", type=float, default=0.98)
    ap.add_argument("--db", type=Path, help="fit this Cinema database instead (one size)")
    ap.add_argument("--workdir", type=Path, help="where the stacks go (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the stack files")
    ap.add_argument("--json", action="store_true", help="print one JSON object at the end")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: 128x128, 300 views (overrides --sizes/--views/--big)")
    ap.add_argument("--child-fit", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_fit:
        child_fit(args)
        return 0
    if args.quick:
        args.sizes, args.views, args.big = "128", 300, False

    sizes = [int(s) for s in args.sizes.split(",") if s]
    if args.big:
        sizes.append(1080)
    own_workdir = args.workdir is None
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="eigencast-bench-fit-"))
    workdir.mkdir(parents=True, exist_ok=True)
    results = []
    runs = [("db", None)] if args.db else [("synthetic", s) for s in sizes]
    for kind, size in runs:
        path = workdir / f"bench_{kind}_{size}_{args.cell}.cells"
        cell_shape = (args.cell, args.cell) if args.method != "standard" else (size or 0,) * 2
        if args.db:
            stack, build_s = build_db_stack(args.db, path, cell_shape)
        else:
            stack, build_s = build_synthetic_stack(path, args.views, size, cell_shape)
        cmd = [sys.executable, __file__, "--child-fit", str(path), "--method", args.method]
        cmd += ["--cell", str(args.cell), "--components", str(args.components)]
        cmd += ["--threshold", str(args.threshold)]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True)
        wall_s = time.perf_counter() - t0
        child = json.loads(proc.stdout.strip().splitlines()[-1])
        base = baselines(stack, child["busiest_cell"], child["busy_cells"])
        row = {
            "source": kind,
            "size": f"{stack.image_shape[0]}x{stack.image_shape[1]}",
            "views": stack.n_views,
            "method": args.method,
            "cell": args.cell,
            "threshold": args.threshold,
            "stack_bytes": stack.size_bytes,
            "build_s (incl. generating images)": build_s,
            "child_wall_s": wall_s,
            **child,
            **base,
            "fit / read_once": child["fit_s"] / base["read_once_s"],
            "fit / svd_all": child["fit_s"] / base["svd_all_s"],
        }
        results.append(row)
        print(f"\n== {row['size']} x {row['views']} views, {args.method} cell {args.cell} ==")
        for key, value in row.items():
            if isinstance(value, float):
                print(f"  {key:36s} {value:12.3f}")
            else:
                print(f"  {key:36s} {value!s:>12}")
        print(f"  {'peak RSS (GiB)':36s} {child['peak_rss_bytes'] / 2**30:12.2f}")
        if not args.keep:
            path.unlink(missing_ok=True)
            path.with_name(path.name + ".json").unlink(missing_ok=True)
    if own_workdir and not args.keep:
        shutil.rmtree(workdir, ignore_errors=True)
    print(f"\nload average during the run: {os.getloadavg()}")
    if args.json:
        print(json.dumps(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
