"""Two-level basis for small images (issue 14): a whole-image eigenspace plus cell residuals.

    .venv/bin/python scripts/rd_twolevel.py [--cache /work/cache] [--sizes 128,256]
        [--volumes tooth,vismale_head] [--views 8] [--coarse 0,16,64] [--out DIR]

At 128 and 256 a key frame's bytes go into the per-cell coefficients (docs/rate-distortion.md
8.3: every cell pays for its own leading components, although neighbouring cells move
together as the view turns). A two-level basis takes the shared part out first: a PCA of the
whole images (``--coarse`` K0 components, the paper's *standard* eigenspace) and, on what it
leaves, one PCA per cell (the *cell-based* eigenspace of the residuals). A view is sent as
K0 global scores followed by the residual cells' scores; the device adds the two
reconstructions.

For each cached training database (``CACHE/VOLUME-SIZE.cdb``, the paper's grid, with its model
``VOLUME-SIZE.ecs`` giving the cell size and the ray-caster), every scheme is fitted here in
float64 from the same training images (K0 = 0 is the plain cell eigenspace, fitted by the same
code, so the comparison is like for like), then for ``--views`` held-out random views (fresh
ray-casts): project, quantize with one step, code as a real key packet
(`protocol.scores.encode_scores`, the cells' component counts given so empty tails cost
nothing), reconstruct in float and score object SSIM (ray-cast alpha). Operating points are
swept over the cells' threshold T (``--thresholds``) and the step (``--steps``, multiples of
the model's step); each scheme's lower convex hull of (bytes, SSIM) is its rate-distortion
curve. The report gives the bytes each scheme needs for a few SSIM levels and the ratio to the
plain cell eigenspace, plus the device's extra storage (K0 whole-image eigenimages) and the
smallest WebP of equal object SSIM.

Produces: docs/rate-distortion.md section 8.4 (tables, ``docs/images/rd-twolevel.png``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

from host.evaluate import alpha_object_mask, compare_images, decode_image, encode_image
from host.fit import HostModel
from host.link import open_true_view_scores
from host.render import CinemaDB
from protocol.scores import encode_scores


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def load_images(db_path: Path) -> np.ndarray:
    """(n_views, h*w*3) float32 training images."""
    db = CinemaDB.open(db_path)
    first = db.read_image(0)
    out = np.empty((db.n_views, first.size), np.float32)
    for i, img in enumerate(db.iter_images()):
        out[i] = img.reshape(-1)
    return out


def to_cells(flat: np.ndarray, shape: tuple[int, int], cell: int) -> np.ndarray:
    """(n, h*w*3) -> (n, n_cells, cell*cell*3), cells in row-major order."""
    h, w = shape
    n = flat.shape[0]
    a = flat.reshape(n, h // cell, cell, w // cell, cell, 3)
    return a.transpose(0, 1, 3, 2, 4, 5).reshape(n, (h // cell) * (w // cell), cell * cell * 3)


def from_cells(cells: np.ndarray, shape: tuple[int, int], cell: int) -> np.ndarray:
    h, w = shape
    a = cells.reshape(h // cell, w // cell, cell, cell, 3)
    return a.transpose(0, 2, 1, 3, 4).reshape(h, w, 3)


class Global:
    """Whole-image PCA (mean + K0 components) through the Gram matrix."""

    def __init__(self, x: np.ndarray, k0: int) -> None:
        self.mean = x.mean(axis=0)
        self.k0 = k0
        if k0 == 0:
            self.basis = np.zeros((0, x.shape[1]), np.float32)
            return
        xc = x - self.mean
        gram = xc @ xc.T
        vals, vecs = np.linalg.eigh(gram.astype(np.float64))
        order = np.argsort(vals)[::-1][:k0]
        basis = (vecs[:, order].T.astype(np.float32) @ xc)
        basis /= np.linalg.norm(basis, axis=1, keepdims=True)
        self.basis = basis

    def scores(self, x: np.ndarray) -> np.ndarray:
        return (x - self.mean) @ self.basis.T

    def image(self, s: np.ndarray) -> np.ndarray:
        return self.mean + s @ self.basis


class Cells:
    """Per-cell PCA of the residuals: eigenvalues and eigenvectors of each cell's covariance."""

    def __init__(self, r: np.ndarray) -> None:   # r: (n, n_cells, d)
        n, n_cells, d = r.shape
        self.mean = r.mean(axis=0)
        self.vals = np.empty((n_cells, d))
        self.vecs = np.empty((n_cells, d, d), np.float32)
        for c in range(n_cells):
            rc = (r[:, c, :] - self.mean[c]).astype(np.float64)
            v, e = np.linalg.eigh(rc.T @ rc / n)
            order = np.argsort(v)[::-1]
            self.vals[c] = np.maximum(v[order], 0)
            self.vecs[c] = e[:, order].T.astype(np.float32)

    def kept(self, threshold: float) -> np.ndarray:
        """Components per cell: the fewest whose eigenvalues reach ``threshold`` of the cell's."""
        cum = np.cumsum(self.vals, axis=1)
        total = cum[:, -1:]
        need = np.where(total > 0, cum / np.where(total > 0, total, 1), 1.0)
        return (need < threshold - 1e-12).sum(axis=1) + 1


def measure(name: str, cache: Path, n_views: int, coarse: list[int], thresholds: list[float],
            steps: list[float], seed: int = 0) -> dict:
    model = HostModel.load(cache / f"{name}.ecs")
    cell = int(model.image.cell_shape[0])
    size = (int(model.image.image_shape[0]), int(model.image.image_shape[1]))
    renderer = open_true_view_scores(model, workers=1).renderer
    rng = np.random.default_rng(seed)
    views = [(float(rng.uniform(0, 360)), float(rng.uniform(-80, 80))) for _ in range(n_views)]
    truth = []
    for v in views:
        rgb, alpha = renderer.render(*v)
        truth.append((rgb, alpha_object_mask(alpha)))
    log(f"{name}: {n_views} held-out views ray-cast; loading training images")
    x = load_images(cache / f"{name}.cdb")
    xt = np.stack([t[0].reshape(-1).astype(np.float32) for t in truth])
    base_step = float(model.score_step)
    webp = []
    for rgb, mask in truth:
        ladder = []
        for q in (1, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 95, 100):
            c = encode_image(rgb, "webp", q)
            ladder.append((c.size_bytes, ssim(rgb, decode_image(c.data), mask)))
        webp.append(ladder)
    out: dict = {"cell": cell, "size": size, "step": base_step, "schemes": {}, "webp": webp}
    for k0 in coarse:
        t0 = time.perf_counter()
        g = Global(x, k0)
        r = to_cells(x - g.image(g.scores(x)), size, cell)
        cells = Cells(r)
        del r
        gs_t = g.scores(xt)
        rt = to_cells(xt - g.image(gs_t), size, cell)
        points = []
        for t in thresholds:
            kept = cells.kept(t)
            for f in steps:
                step = base_step * f
                rows = []
                for i, (rgb, mask) in enumerate(truth):
                    cs = [cells.vecs[c, :kept[c]] @ (rt[i, c] - cells.mean[c])
                          for c in range(len(kept))]
                    y = np.concatenate([gs_t[i], *cs])
                    counts = np.concatenate([[k0] if k0 else [], kept]).astype(np.int64)
                    pkt = encode_scores(y, step=step, frame=1, view=(0.0, 0.0),
                                        image_digest=bytes(32), n_components=counts)
                    yq = np.round(y / step) * step
                    gq, off = yq[:k0], k0
                    rec_cells = np.empty_like(rt[i])
                    for c in range(len(kept)):
                        k = kept[c]
                        rec_cells[c] = cells.mean[c] + yq[off:off + k] @ cells.vecs[c, :k]
                        off += kept[c]
                    rec = g.image(gq).reshape((*size, 3)) + from_cells(rec_cells, size, cell)
                    rec = np.clip(np.round(rec), 0, 255).astype(np.uint8)
                    rows.append((len(pkt.packet), ssim(rgb, rec, mask)))
                b, s = np.mean(rows, axis=0)
                points.append({"T": t, "step_x": f, "bytes": float(b), "ssim": float(s),
                               "coeffs": int(k0 + kept.sum())})
        out["schemes"][str(k0)] = {
            "points": points,
            "extra_storage_bytes": int(k0 * x.shape[1]),  # int8 whole-image eigenimages
            "fit_s": round(time.perf_counter() - t0, 1)}
        log(f"{name}: K0 {k0} done in {time.perf_counter() - t0:.0f} s")
    return out


def ssim(ref: np.ndarray, img: np.ndarray, mask: np.ndarray) -> float:
    return float(compare_images(ref, img, mask=mask, metrics=("ssim",)).ssim_object)


def hull(points: list[dict]) -> list[tuple[float, float]]:
    """Upper-left convex hull of (bytes, SSIM): the best SSIM for each byte count."""
    pts = sorted((p["bytes"], p["ssim"]) for p in points)
    best: list[tuple[float, float]] = []
    for b, s in pts:
        if best and s <= best[-1][1]:
            continue
        best.append((b, s))
    # keep the concave (upper) hull only
    h: list[tuple[float, float]] = []
    for p in best:
        while len(h) >= 2:
            (x1, y1), (x2, y2) = h[-2], h[-1]
            if (x2 - x1) * (p[1] - y1) - (y2 - y1) * (p[0] - x1) >= 0:
                h.pop()
            else:
                break
        h.append(p)
    return h


def bytes_at(h: list[tuple[float, float]], level: float) -> float:
    """Bytes the hull needs for object SSIM ``level`` (log-linear between hull points)."""
    for (b1, s1), (b2, s2) in itertools.pairwise(h):
        if s1 <= level <= s2:
            if s2 == s1:
                return b1
            f = (level - s1) / (s2 - s1)
            return float(np.exp(np.log(b1) + f * (np.log(b2) - np.log(b1))))
    return float("nan")


def webp_bytes_at(ladders: list, level: float) -> float:
    out = []
    for ladder in ladders:
        ok = [b for b, s in ladder if s >= level]
        out.append(min(ok) if ok else np.nan)
    return float(np.nanmedian(out))


def table(name: str, res: dict, levels: list[float]) -> str:
    lines = [f"**two-level: {name}, cells {res['cell']}, step {res['step']:.1f}**", "",
             "| K0 global | extra storage | " + " | ".join(f"bytes @ SSIM {v}" for v in levels)
             + " |", "|---|---|" + "---|" * len(levels)]
    base = hull(res["schemes"]["0"]["points"])
    for k0, sch in res["schemes"].items():
        h = hull(sch["points"])
        cells = []
        for v in levels:
            b, b0 = bytes_at(h, v), bytes_at(base, v)
            cells.append("–" if np.isnan(b) else f"{b:.0f} ({b / b0:.2f}x)")
        lines.append(f"| {k0} | {sch['extra_storage_bytes'] / 1e6:.1f} MB | "
                     + " | ".join(cells) + " |")
    lines.append("| WebP (equal object SSIM, median) | | "
                 + " | ".join(f"{webp_bytes_at(res['webp'], v):.0f}" for v in levels) + " |")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.4), squeeze=False)
    for ax, (name, res) in zip(axes[0], results.items()):
        for k0, sch in res["schemes"].items():
            h = hull(sch["points"])
            ax.plot([p[0] for p in h], [p[1] for p in h], marker=".",
                    label="cells only" if k0 == "0" else f"{k0} global + cells")
        levels = np.linspace(min(s for ladder in res["webp"] for _, s in ladder), 0.99, 30)
        ax.plot([webp_bytes_at(res["webp"], v) for v in levels], levels, "k--", label="WebP")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("bytes per key frame")
        ax.set_ylabel("object SSIM")
        ax.set_ylim(0.6, 1.0)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", type=Path, default=Path("/work/cache"))
    p.add_argument("--sizes", default="128,256")
    p.add_argument("--volumes", default="tooth,vismale_head")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--coarse", default="0,16,64")
    p.add_argument("--thresholds", default="0.95,0.98,0.99,0.997")
    p.add_argument("--steps", default="1,2,4")
    p.add_argument("--levels", default="0.8,0.85,0.9")
    p.add_argument("--out", type=Path, default=Path("/work/cache/twolevel"))
    p.add_argument("--image", type=Path, default=None, help="write the plot here too")
    a = p.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    coarse = [int(v) for v in a.coarse.split(",")]
    if 0 not in coarse:
        coarse = [0, *coarse]
    results = {}
    for size in a.sizes.split(","):
        for vol in a.volumes.split(","):
            name = f"{vol}-{size}"
            if not (a.cache / f"{name}.ecs").exists():
                log(f"skipping {name}: no {name}.ecs in {a.cache}")
                continue
            results[name] = measure(name, a.cache, a.views, coarse,
                                    [float(v) for v in a.thresholds.split(",")],
                                    [float(v) for v in a.steps.split(",")])
            (a.out / "results.json").write_text(json.dumps(results, indent=1))
    levels = [float(v) for v in a.levels.split(",")]
    text = "\n\n".join(table(n, r, levels) for n, r in results.items())
    (a.out / "results.md").write_text(text + "\n")
    print(text)
    plot(results, a.out / "rd-twolevel.png")
    if a.image:
        plot(results, a.image)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
