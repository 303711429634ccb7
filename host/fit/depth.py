"""The depth eigenspace of ``eigencast fit --depth`` (issue 15): what a device warps with.

A database rendered with ``eigencast render --depth`` holds, per view, the half-opacity depth
at half resolution (`host.render.cinema.encode_depth`). `fit_depth_eigenspaces` fits a cell
PCA of those maps (background filled with the nearest object depth so the cells stay smooth,
the camera distance subtracted; cells of `DEPTH_CELL`, each keeping the fewest components
whose eigenvalues reach the threshold of its variance, the colour fit's rule), stored the
device's way: float16 means, int8 components with a float32 scale each, an int16 table of
every training view's scores (`device_runtime.synthesis.DepthEigenspace`). `add_depth`
puts it into an image as the sections `device_runtime.synthesis.DEPTH_SECTIONS` and names the
synthesis method in the manifest (``image.synthesis``). The research measurement
(``scripts/warp_views.py``, docs/rate-distortion.md section 9) fits with the same code.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from device_runtime.synthesis import (
    DEPTH_SECTIONS,
    SYNTHESIS_METHOD,
    Z_TOLERANCE,
    DepthEigenspace,
    split_cells,
)
from host.errors import FitError

__all__ = ["DEPTH_CELL", "DEPTH_SCORE_MSE", "add_depth", "fill_nearest",
           "fit_depth_eigenspaces"]

#: Side of the depth cells (pixels of the half-resolution depth map).
DEPTH_CELL = 16
#: Score quantization noise of the depth table, mm^2 per pixel.
DEPTH_SCORE_MSE = 0.05


def fill_nearest(depth: np.ndarray) -> np.ndarray:
    """NaN pixels take the nearest finite pixel's value (smooth silhouettes for the PCA);
    float32; all zeros when no pixel is finite."""
    from scipy.ndimage import distance_transform_edt

    bad = ~np.isfinite(depth)
    if not bad.any():
        return depth.astype(np.float32)
    if bad.all():
        return np.zeros_like(depth, dtype=np.float32)
    i = distance_transform_edt(bad, return_distances=False, return_indices=True)
    return depth[tuple(i)].astype(np.float32)


def fit_depth_eigenspaces(depths: Any, thresholds: list[float], offset: float,
                          cell: int = DEPTH_CELL) -> dict[float, DepthEigenspace]:
    """Adaptive cell PCA of filled depth maps, one eigenspace per threshold.

    Parameters
    ----------
    depths : array-like (n_views, h, w) float32
        Depth maps in mm along the rays with no NaN (`fill_nearest`).
    thresholds : list of float
        Cumulative variance each cell keeps; one eigendecomposition per cell serves all.
    offset : float
        Subtracted before the fit (the camera distance), added back by the reconstruction.
    cell : int

    Returns
    -------
    dict of float to DepthEigenspace
    """
    n, h, w = depths.shape
    ph, pw = -(-h // cell) * cell, -(-w // cell) * cell
    n_cells = (ph // cell) * (pw // cell)
    x = np.empty((n_cells, n, cell * cell), dtype=np.float32)  # cell-major stack
    for i in range(n):
        d = np.asarray(depths[i], dtype=np.float32) - np.float32(offset)
        if (ph, pw) != (h, w):
            d = np.pad(d, ((0, ph - h), (0, pw - w)), mode="edge")
        x[:, i, :] = split_cells(d, cell)
    per_t: dict[float, tuple[list, list, list]] = {t: ([], [], []) for t in thresholds}
    means = []
    for c in range(n_cells):
        xc = x[c].astype(np.float64)
        mu = xc.mean(axis=0)
        xc -= mu
        lam, vec = np.linalg.eigh(xc.T @ xc / max(n - 1, 1))
        lam, vec = lam[::-1], vec[:, ::-1]
        trace = float(lam.sum())
        means.append(mu.astype(np.float16))
        ks = {}
        for t in thresholds:
            ks[t] = 0 if trace <= 1e-12 else min(
                int(np.searchsorted(np.cumsum(lam) / trace, t - 1e-12) + 1), lam.size)
        y = xc @ vec[:, :max(ks.values(), default=0)]
        for t, k in ks.items():
            comps, counts, scores = per_t[t]
            comps.append(vec[:, :k].T)
            counts.append(k)
            scores.append(y[:, :k])
    del x
    out = {}
    for t, (comps, counts, scores) in per_t.items():
        counts = np.array(counts, dtype=np.int32)
        v = np.concatenate(comps) if comps else np.zeros((0, cell * cell))
        scale = (np.maximum(np.abs(v).max(axis=1), 1e-12) / 127.0) if v.size else np.zeros(0)
        vq = np.rint(v / scale[:, None]).astype(np.int8) if v.size else v.astype(np.int8)
        y = np.concatenate(scores, axis=1)
        kmean = max(float(counts[counts > 0].mean()), 1.0) if counts.any() else 1.0
        step = math.sqrt(12.0 * DEPTH_SCORE_MSE * cell * cell / kmean)
        table = np.clip(np.rint(y / step), -32768, 32767).astype(np.int16)
        out[t] = DepthEigenspace(cell, (h, w), np.stack(means), vq, scale.astype(np.float32),
                                 counts, table, step, offset)
    return out


def add_depth(image: Any, db: Any, threshold: float) -> dict:
    """Fit the database's depth maps and store them in ``image`` (in place).

    Parameters
    ----------
    image : EigenspaceImage
        Built from ``db`` (its views in the database's order).
    db : CinemaDB
        Rendered with ``--depth``.
    threshold : float
        Cumulative variance per depth cell.

    Returns
    -------
    dict
        ``components``, ``components_per_cell``, ``raw_bytes``, ``step``, ``threshold``.

    Raises
    ------
    FitError
        The database has no depth maps, or its framing does not allow the warp.
    """
    if db.depth is None:
        raise FitError(f"{db.path}: has no depth maps; render it with eigencast render --depth")
    camera = (db.settings or {}).get("camera") or {}
    if camera.get("projection", "perspective") != "perspective" or not isinstance(
            camera.get("fov_deg"), (int, float)) or not isinstance(camera.get("radius_mm"),
                                                                    (int, float)):
        raise FitError(f"{db.path}: --depth needs a perspective eigencast database (its sidecar "
                       "records the orbit framing)")
    background = ((db.settings or {}).get("renderer") or {}).get("background", [0, 0, 0])
    if any(float(b) != 0.0 for b in background):
        raise FitError(f"{db.path}: --depth needs a black background (the device finds the "
                       "object by its colour)")
    h, w = db.depth_shape
    if (2 * h, 2 * w) != tuple(image.image_shape):
        raise FitError(f"{db.path}: depth maps {w}x{h} are not half the image size")
    offset = float(db.depth["offset_mm"])
    depths = np.empty((db.n_views, h, w), dtype=np.float32)
    for i in range(db.n_views):
        depths[i] = fill_nearest(db.read_depth(i))
    eig = fit_depth_eigenspaces(depths, [threshold], offset)[threshold]
    del depths
    image.sections["depth_counts"] = eig.counts.astype(np.int32)
    image.sections["depth_scales"] = eig.scales.astype(np.float32)
    image.sections["depth_mean"] = eig.mean.astype(np.float16)
    image.sections["depth_components"] = eig.components
    image.sections["depth_scores"] = eig.table
    image.synthesis = {
        "method": SYNTHESIS_METHOD,
        "fov_deg": float(camera["fov_deg"]),
        "distance_mm": float(camera["radius_mm"]) / math.sin(math.radians(camera["fov_deg"]) / 2),
        "z_tolerance_mm": Z_TOLERANCE * 2.0 * float(camera["radius_mm"]),
        "depth_shape": [int(h), int(w)],
        "depth_cell": int(eig.cell),
        "depth_step": float(eig.step),
        "depth_offset_mm": offset,
        "depth_threshold": float(threshold),
    }
    raw = sum(int(image.sections[s].nbytes) for s in DEPTH_SECTIONS)
    return {"components": eig.n_components,
            "components_per_cell": float(eig.counts.mean()) if eig.counts.size else 0.0,
            "raw_bytes": raw, "step": eig.step, "threshold": threshold}
