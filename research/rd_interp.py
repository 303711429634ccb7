"""Score interpolation, WebP database and cell seams on held-out views (docs/design-notes.md).

For one fitted model (``.ecs`` from a grid training database) and a database of held-out test
views rendered with the same settings, every novel view is made by several methods and
compared with the true ray-cast (SSIM, FLIP, PSNR; whole image and object pixels):

``oracle``
    The true view projected onto the model's int8 eigenspace and sent through the score
    packet (no view interpolation): the best the eigenspace can do.
``bilinear``, ``bicubic``, ``barycentric``
    The device's interpolation methods (`host.fit.interpolate.METHODS`), scores rounded to the
    model's score step, reconstructed by the device code.
``bspline``
    Diagnostic: the interpolating cubic B-spline (cardinal spline; the table prefiltered
    periodically in phi and with mirror ends in theta, then 16 B-spline taps).
``ls16``
    Diagnostic bound: per view, the least-squares weights (summing to 1) over the 16 views
    ``bicubic`` uses that best reproduce the oracle's scores. No rule that blends those 16
    training views can do better (in the eigenspace's L2 sense).
``blend_<method>``
    The *true* training images blended with ``<method>``'s weights (a lossless image
    database): what the weights can do without the eigenspace.
``webp_db_q<Q>``
    The training images stored as WebP at quality Q and blended with the default method's
    weights (`host.evaluate.WebPDatabase`); its storage is the sum of the WebP files.

It also measures cell seams for every method (gradient error across cell boundaries vs inside
cells, object pixels), a cheap deblocking filter's effect and its cost per frame next to the
device reconstruction's, and writes everything to one JSON file.

Object pixels are the ray-cast's non-background pixels (the databases store RGB only; the
background is black, so a pixel is object when any channel is non-zero).

Usage::

    .venv/bin/python research/rd_interp.py MODEL.ecs TEST.cdb -o results.json \\
        [--webp-db-qualities 60,80,95] [--views N] [--workers 2]

Produces: docs/design-notes.md, "The blend's weights: bilinear" (and "Tried and not kept")
(through rd_plots.py).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.evaluate import (
    DevicePath,
    TrainingImages,
    WebPDatabase,
    compare_images,
    eigenspace_bytes,
    json_safe,
)
from host.fit.interpolate import ScoreInterpolator
from host.fit.model import HostModel, standalone_scores
from host.render.cinema import CinemaDB

GRID_METHODS = ("bilinear", "bicubic", "barycentric")


# ----------------------------------------------------------------------------- seams


def seam_sums(truth: np.ndarray, frame: np.ndarray, mask: np.ndarray,
              cell_shape: tuple[int, int]) -> np.ndarray:
    """[seam error sum, seam pairs, inside error sum, inside pairs] over object pixel pairs.

    The error of a pair of neighbouring pixels is the absolute difference between the frame's
    and the truth's finite difference (mean over RGB). A pair is a *seam* pair when its two
    pixels lie in different cells.
    """
    t = truth.astype(np.float32)
    f = frame.astype(np.float32)
    ch, cw = cell_shape
    out = np.zeros(4)
    for axis, size in ((1, cw), (0, ch)):
        dt = np.diff(t, axis=axis)
        df = np.diff(f, axis=axis)
        err = np.abs(df - dt).mean(axis=2)
        if axis == 1:
            both = mask[:, 1:] & mask[:, :-1]
            seam = ((np.arange(err.shape[1]) + 1) % size == 0)[None, :]
        else:
            both = mask[1:, :] & mask[:-1, :]
            seam = ((np.arange(err.shape[0]) + 1) % size == 0)[:, None]
        s = both & seam
        i = both & ~seam
        out += [err[s].sum(), s.sum(), err[i].sum(), i.sum()]
    return out


def deblock(frame: np.ndarray, cell_shape: tuple[int, int], *, strength: float = 4.0,
            edge: float = 24.0) -> np.ndarray:
    """A cheap deblocking filter across cell boundaries (H.264-like weak filter, numpy).

    For the pixels p1 p0 | q0 q1 across each boundary, ``d = ((q0 - p0) * 4 + (p1 - q1)) / 8``
    clipped to +-``strength`` moves p0 by +d and q0 by -d, only where ``|q0 - p0| < edge``
    (a real edge is left alone). Vertical boundaries first, then horizontal ones.
    """
    out = frame.astype(np.int16)
    ch, cw = cell_shape
    for axis, size in ((1, cw), (0, ch)):
        n = out.shape[axis]
        c = np.arange(size, n - 1, size)
        c = c[c >= 2]
        if c.size == 0:
            continue
        take = (lambda k: out[:, k]) if axis == 1 else (lambda k: out[k, :])
        p1, p0, q0, q1 = take(c - 2), take(c - 1), take(c), take(c + 1)
        d = ((q0 - p0) * 4 + (p1 - q1)) / 8.0
        d = np.clip(np.rint(d), -strength, strength).astype(np.int16)
        d[np.abs(q0 - p0) >= edge] = 0
        if axis == 1:
            out[:, c - 1] = p0 + d
            out[:, c] = q0 - d
        else:
            out[c - 1, :] = p0 + d
            out[c, :] = q0 - d
    return np.clip(out, 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------- weights


def bspline_scores(interp: ScoreInterpolator, phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The interpolating cubic B-spline of the grid's scores at (phi, theta) (diagnostic)."""
    from scipy.ndimage import spline_filter1d

    axes = interp.interpolator_.axes
    grid = interp.scores[axes.view_index]  # (n_phi, n_theta, K)
    coef = spline_filter1d(grid, order=3, axis=0, mode="grid-wrap")
    coef = spline_filter1d(coef, order=3, axis=1, mode="mirror")
    step = 360.0 / axes.n_phi
    u = np.mod(phi - axes.phi0_deg, 360.0) / step
    i0 = np.floor(u).astype(np.int64)
    f = u - i0
    rows = axes.theta_deg
    # uniform rows assumed (grid:NxM); the position in row units
    v = (np.clip(theta, rows[0], rows[-1]) - rows[0]) / (rows[1] - rows[0])
    j0 = np.minimum(np.floor(v).astype(np.int64), rows.size - 2)
    g = v - j0

    def basis(t: np.ndarray) -> np.ndarray:
        return np.stack([(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1,
                         t**3], axis=-1) / 6.0

    wp, wt = basis(f), basis(g)
    out = np.zeros((phi.size, grid.shape[2]), dtype=np.float64)
    last = rows.size - 1
    for a in range(4):
        cols = (i0 + a - 1) % axes.n_phi
        for b in range(4):
            r = j0 + b - 1
            r = np.where(r < 0, -r, np.where(r > last, 2 * last - r, r))  # mirror
            out += (wp[:, a] * wt[:, b])[:, None] * coef[cols, r]
    return out.astype(np.float32)


def ls16_scores(cubic: ScoreInterpolator, phi: float, theta: float,
                target: np.ndarray) -> np.ndarray:
    """Best blend (weights summing to 1) of bicubic's 16 views for the target scores."""
    idx, _w = cubic.weights(phi, theta)
    idx = np.unique(idx)
    y = cubic.scores[idx].astype(np.float64)  # (m, K)
    # minimise |y^T w - t|^2 with sum(w) = 1: w = w0 + N z (N spans sum-zero vectors)
    m = idx.size
    if m == 1:
        return y[0].astype(np.float32)
    base = np.full(m, 1.0 / m)
    null = np.eye(m)[:, :-1] - np.eye(m)[:, -1:]
    a = y.T @ null
    z, *_ = np.linalg.lstsq(a, target - y.T @ base, rcond=None)
    w = base + null @ z
    return (w @ y).astype(np.float32)


# ----------------------------------------------------------------------------- main


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("test_db")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--views", type=int, default=0, help="first N test views (0: all)")
    ap.add_argument("--webp-db-qualities", default="60,80,95")
    ap.add_argument("--methods", default="oracle,bilinear,bicubic,barycentric,bspline,ls16,"
                    "blend_bilinear,blend_bicubic")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--webp-db-estimate", action="store_true",
                    help="encode only the training views the test views use and estimate the "
                         "database's storage from their mean size (fast at 512)")
    return ap.parse_args(argv)


class _Study:
    """The model, the held-out views and every method's scores or database, set up once."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.model = model = HostModel.load(args.model)
        self.test = test = CinemaDB.open(args.test_db)
        self.n = n = test.n_views if args.views <= 0 else min(args.views, test.n_views)
        views = model.image.views
        tphi = np.asarray(views["phi_deg"], dtype=np.float64)
        ttheta = np.asarray(views["theta_deg"], dtype=np.float64)
        self.step = model.score_step
        self.cell = tuple(int(v) for v in model.image.cell_shape)
        self.methods = [m for m in args.methods.split(",") if m]
        self.qualities = [int(q) for q in args.webp_db_qualities.split(",") if q]
        self.interps = {}
        for m in GRID_METHODS:
            self.interps[m] = ScoreInterpolator(tphi, ttheta, model.training_scores, method=m)
        self.default_method = model.interpolator.method_
        self.device = DevicePath(model)
        self.training = TrainingImages(model, None)
        if self.training.db is None:
            raise SystemExit("the model's training database is not available")
        self.phis = np.mod(test.phi_deg[:n], 360.0)
        self.thetas = test.theta_deg[:n]
        self.precomputed = {m: self.interps[m](self.phis, self.thetas) for m in GRID_METHODS}
        if "bspline" in self.methods:
            self.precomputed["bspline"] = bspline_scores(self.interps["bilinear"], self.phis,
                                                         self.thetas)
        self.webp_dbs = {}
        for q in self.qualities:
            t0 = time.perf_counter()
            self.webp_dbs[q] = WebPDatabase(model, self.training, q, progress=True,
                                            encode_all=not args.webp_db_estimate)
            print(f"webp db q{q}: {self.webp_dbs[q].storage_bytes / 1e6:.2f} MB "
                  f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
        self.deblocked = [m for m in ("oracle", self.default_method, "bicubic")
                          if m in self.methods]
        self.names = list(self.methods) + [f"webp_db_q{q}" for q in self.qualities]
        self.names += [f"{m}+deblock" for m in dict.fromkeys(self.deblocked)]
        self.timing = {"reconstruct": 0.0, "deblock": 0.0, "frames": 0}

    def frames(self, k: int, phi: float, theta: float,
               truth: np.ndarray) -> dict[str, np.ndarray]:
        """Every method's frame of held-out view ``k``."""
        frames: dict[str, np.ndarray] = {}
        oracle_y: list[np.ndarray | None] = [None]
        for m in self.methods:
            frames[m] = self._method_frame(m, k, phi, theta, truth, oracle_y)
        for q in self.qualities:
            frames[f"webp_db_q{q}"] = self.webp_dbs[q].frame(phi, theta)
        for m in dict.fromkeys(self.deblocked):
            t0 = time.perf_counter()
            frames[f"{m}+deblock"] = deblock(frames[m], self.cell)
            if m == self.default_method:
                self.timing["deblock"] += time.perf_counter() - t0
        return frames

    def _method_frame(self, m: str, k: int, phi: float, theta: float, truth: np.ndarray,
                      oracle_y: list[np.ndarray | None]) -> np.ndarray:
        model, step = self.model, self.step
        if m == "oracle":
            frame, _ = self.device.projection_frame(truth)
            return frame
        if m in self.precomputed:
            y = np.rint(self.precomputed[m][k] / step) * step
            t0 = time.perf_counter()
            frame = model.reconstruct(y.astype(np.float32))
            if m == self.default_method:
                self.timing["reconstruct"] += time.perf_counter() - t0
                self.timing["frames"] += 1
            return frame
        if m == "ls16":
            if oracle_y[0] is None:
                oracle_y[0] = _projection_scores(model, truth)
            y = ls16_scores(self.interps["bicubic"], phi, theta, oracle_y[0])
            return model.reconstruct((np.rint(y / step) * step).astype(np.float32))
        if m.startswith("blend_"):
            idx, w = self.interps[m[len("blend_"):]].weights(phi, theta)
            acc = np.zeros(truth.shape, np.float32)
            for i, wi in zip(idx.tolist(), w.tolist()):
                if wi != 0.0:
                    acc += np.float32(wi) * self.training.db.read_image(int(i)).astype(
                        np.float32)
            return np.clip(np.rint(acc), 0, 255).astype(np.uint8)
        raise SystemExit(f"unknown method {m}")


def _measure_views(study: _Study, workers: int) -> tuple[list[dict], dict[str, np.ndarray]]:
    """Every view's metrics per method (compared in ``workers`` processes) and seam sums."""
    pool = None
    if workers > 0:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))

    def submit(truth: np.ndarray, frame: np.ndarray, mask: np.ndarray):
        if pool is None:
            from concurrent.futures import Future

            fut: Future = Future()
            fut.set_result(compare_images(truth, frame, mask=mask))
            return fut
        return pool.submit(compare_images, truth, frame, mask=mask)

    per_view: list[dict] = []
    seams = {m: np.zeros(4) for m in study.names}
    pending = []
    t_start = time.perf_counter()
    n = study.n
    for k in range(n):
        phi, theta = float(study.phis[k]), float(study.thetas[k])
        truth = study.test.read_image(k)
        mask = truth.max(axis=2) > 0
        frames = study.frames(k, phi, theta, truth)
        for m, fr in frames.items():
            seams[m] += seam_sums(truth, fr, mask, study.cell)
        rec = {"phi_deg": phi, "theta_deg": theta, "object_fraction": float(mask.mean())}
        pending.append((rec, {m: submit(truth, fr, mask) for m, fr in frames.items()}))
        while len(pending) > 2 * max(1, workers):
            per_view.append(_finish(*pending.pop(0)))
        if (k + 1) % 10 == 0:
            el = time.perf_counter() - t_start
            print(f"{k + 1}/{n} views, {el:.0f} s", file=sys.stderr)
    while pending:
        per_view.append(_finish(*pending.pop(0)))
    if pool is not None:
        pool.shutdown()
    return per_view, seams


def _means(names: list[str], per_view: list[dict], seams: dict[str, np.ndarray]) -> dict:
    means = {}
    for m in names:
        vals = {}
        for key in ("psnr", "ssim", "flip", "psnr_object", "ssim_object", "flip_object"):
            arr = np.array([v[m][key] for v in per_view], dtype=np.float64)
            arr = arr[np.isfinite(arr)]
            vals[key] = float(arr.mean()) if arr.size else math.nan
        s = seams[m]
        vals["seam_grad_err"] = float(s[0] / max(s[1], 1))
        vals["inside_grad_err"] = float(s[2] / max(s[3], 1))
        vals["seam_ratio"] = vals["seam_grad_err"] / max(vals["inside_grad_err"], 1e-12)
        means[m] = vals
    return means


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    study = _Study(args)
    model, timing = study.model, study.timing
    per_view, seams = _measure_views(study, args.workers)
    result = {
        "model": str(args.model),
        "test_db": str(args.test_db),
        "views": study.n,
        "image_shape": list(model.image.image_shape),
        "cell_shape": list(study.cell),
        "components_per_cell": float(np.mean(model.image.n_components)),
        "threshold": model.threshold,
        "score_step": study.step,
        "default_method": study.default_method,
        "eigenspace_bytes": eigenspace_bytes(model),
        "standalone": standalone_scores(model.image) is not None,
        "webp_db_storage_bytes": {str(q): study.webp_dbs[q].storage_bytes
                                  for q in study.qualities},
        "webp_db_storage_estimated": bool(args.webp_db_estimate),
        "timing_ms_per_frame": {
            "reconstruct": 1e3 * timing["reconstruct"] / max(timing["frames"], 1),
            "deblock": 1e3 * timing["deblock"] / max(timing["frames"], 1),
        },
        "means": _means(study.names, per_view, seams),
        "per_view": per_view,
    }
    Path(args.output).write_text(json.dumps(json_safe(result), indent=1))
    _print_table(result)
    return 0


def _projection_scores(model: HostModel, truth: np.ndarray) -> np.ndarray:
    """The true view's scores on the int8 eigenspace (unquantized; see DevicePath)."""
    from host.fit.cells import split_cells

    img = model.image
    cells = split_cells(np.asarray(truth)[None], img.cell_shape)[0].astype(np.float32)
    centred = cells - img.mean.astype(np.float32)
    cell_of = np.repeat(np.arange(img.n_cells), np.asarray(img.n_components, np.int64))
    v = img.eigenimages.astype(np.float32) * img.scales[:, None]
    norm2 = np.maximum(np.einsum("kd,kd->k", v, v), np.float32(1e-30))
    return (np.einsum("kd,kd->k", v, centred[cell_of]) / norm2).astype(np.float64)


def _finish(rec: dict, futures: dict) -> dict:
    for m, fut in futures.items():
        rec[m] = fut.result().values()
    return rec


def _print_table(r: dict) -> None:
    h, w = r["image_shape"]
    print(f"{Path(r['model']).name} on {r['views']} views of {Path(r['test_db']).name} "
          f"({w}x{h}, {r['components_per_cell']:.2f} comp/cell, eigenspace "
          f"{r['eigenspace_bytes'] / 1e6:.2f} MB)")
    print("| method | SSIM obj | FLIP obj | PSNR obj | SSIM | FLIP | seam/inside grad err |")
    print("|---|---|---|---|---|---|---|")
    for m, v in r["means"].items():
        print(f"| {m} | {v['ssim_object']:.4f} | {v['flip_object']:.4f} | "
              f"{v['psnr_object']:.2f} | {v['ssim']:.4f} | {v['flip']:.4f} | "
              f"{v['seam_grad_err']:.2f} / {v['inside_grad_err']:.2f} = "
              f"{v['seam_ratio']:.2f} |")
    for q, b in r["webp_db_storage_bytes"].items():
        print(f"webp_db q{q}: {b / 1e6:.2f} MB")
    print("ms per frame:", r["timing_ms_per_frame"])


if __name__ == "__main__":
    raise SystemExit(main())
