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
(``research/warp_views.py``, docs/design-notes.md) fits with the same code.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from device_runtime.standalone import delta_encode
from device_runtime.synthesis import (
    DEPTH_DELTA_SECTION,
    DEPTH_SECTIONS,
    SYNTHESIS_METHOD,
    Z_TOLERANCE,
    DepthEigenspace,
    split_cells,
)
from host.errors import FitError
from host.render.cinema import depth_problem

__all__ = ["DEPTH_CELL", "DEPTH_SCORE_MSE", "DEPTH_SCORE_NOISE_Z2", "add_depth",
           "depth_sections", "depth_table_step",
           "drop_unused", "fill_nearest", "fit_depth_eigenspaces", "quantize_depth_table"]

#: Side of the depth cells (pixels of the half-resolution depth map).
DEPTH_CELL = 16
#: Score quantization noise of `fit_depth_eigenspaces`' table, mm^2 per pixel (the research
#: measurement's, and the first depth images').
DEPTH_SCORE_MSE = 0.05
#: ``fit --depth``'s depth table noise as a fraction of the squared z-test tolerance
#: (``synthesis.z_tolerance_mm``, 2 % of the bounding-sphere diameter): the rounding noise's
#: RMS is a fifth of the tolerance (0.44 mm^2 on the tooth, 1.8 mm^2 on the head, at any
#: image size). docs/design-notes.md, "The depth eigenspace": it costs at most 0.003 object
#: SSIM on both
#: volumes at 256 and 512, where the depth sections lose 10-30 % of their bytes; the warp's
#: sensitivity to depth noise scales with the volume, not with the pixel.
DEPTH_SCORE_NOISE_Z2 = 0.04


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
                          cell: int = DEPTH_CELL, score_mse: float = DEPTH_SCORE_MSE
                          ) -> dict[float, DepthEigenspace]:
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
    score_mse : float
        Rounding noise of the score table, mm^2 per pixel (`depth_table_step`); components
        whose score rounds to 0 in every view are dropped (`drop_unused`).

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
        step = depth_table_step(counts, cell, score_mse)
        table = np.clip(np.rint(y / step), -32768, 32767).astype(np.int16)
        out[t] = drop_unused(DepthEigenspace(cell, (h, w), np.stack(means), vq,
                                             scale.astype(np.float32), counts, table, step,
                                             offset))
    return out


def depth_table_step(counts: np.ndarray, cell: int, score_mse: float) -> float:
    """The depth table's step whose rounding adds ``score_mse`` mm^2 per pixel.

    Each kept component's score is rounded to the step (noise step^2 / 12, spread over the
    cell's ``cell * cell`` pixels by the orthonormal component), ``counts`` per cell: the
    mean over the cells that keep any, at least 1.
    """
    counts = np.asarray(counts)
    kmean = max(float(counts[counts > 0].mean()), 1.0) if counts.any() else 1.0
    return math.sqrt(12.0 * float(score_mse) * cell * cell / kmean)


def drop_unused(eig: DepthEigenspace) -> DepthEigenspace:
    """``eig`` without the components whose score is 0 in every training view.

    Their reconstruction adds nothing (a coarse table step rounds the small ones of every
    view to 0), so dropping them changes no depth map and saves their int8 components.
    """
    if eig.table.size == 0:
        return eig
    used = np.any(eig.table != 0, axis=0)
    if used.all():
        return eig
    cell_of = np.repeat(np.arange(eig.counts.size), eig.counts)
    counts = np.bincount(cell_of[used], minlength=eig.counts.size).astype(np.int32)
    return DepthEigenspace(eig.cell, eig.shape, eig.mean, eig.components[used],
                           eig.scales[used], counts, np.ascontiguousarray(eig.table[:, used]),
                           eig.step, eig.offset)


def quantize_depth_table(eig: DepthEigenspace, score_mse: float) -> DepthEigenspace:
    """``eig`` with its table re-quantized to the step of ``score_mse`` (`depth_table_step`
    from the counts before `drop_unused`), unused components dropped. From a fine table
    (``score_mse`` of the fit far below this one) the rounding is as good as from floats."""
    step = depth_table_step(eig.counts, eig.cell, score_mse)
    y = eig.table.astype(np.float64) * eig.step
    table = np.clip(np.rint(y / step), -32768, 32767).astype(np.int16)
    return drop_unused(DepthEigenspace(eig.cell, eig.shape, eig.mean, eig.components,
                                       eig.scales, eig.counts, table, step, eig.offset))


def depth_sections(eig: DepthEigenspace, order: np.ndarray | None = None
                   ) -> dict[str, np.ndarray]:
    """The image sections of a depth eigenspace, as ``fit --depth`` stores them.

    Parameters
    ----------
    eig : DepthEigenspace
    order : ndarray of int, optional
        The standalone coding order of the views (`device_runtime.standalone.standalone_order`):
        the table is stored delta-coded as ``depth_scores_delta``
        (`device_runtime.standalone.delta_encode`). None: the plain int16 ``depth_scores``.
    """
    secs = {"depth_counts": eig.counts.astype(np.int32),
            "depth_scales": eig.scales.astype(np.float32),
            "depth_mean": eig.mean.astype(np.float16),
            "depth_components": eig.components}
    if order is None:
        secs["depth_scores"] = eig.table
    else:
        secs[DEPTH_DELTA_SECTION] = delta_encode(eig.table, order)
    return secs


def add_depth(image: Any, db: Any, threshold: float, *, score_mse: float | None = None,
              delta: bool | None = None) -> dict:
    """Fit the database's depth maps and store them in ``image`` (in place).

    Parameters
    ----------
    image : EigenspaceImage
        Built from ``db`` (its views in the database's order).
    db : CinemaDB
        Rendered with ``--depth``.
    threshold : float
        Cumulative variance per depth cell.
    score_mse : float, optional
        Rounding noise of the depth score table, mm^2 per pixel (`depth_table_step`);
        default `DEPTH_SCORE_NOISE_Z2` times the squared z-test tolerance.
    delta : bool or None
        Store the table delta-coded (`DEPTH_DELTA_SECTION`, True), plain (``depth_scores``,
        False: what the first depth images hold), or the smaller once compressed (None).

    Returns
    -------
    dict
        ``components``, ``components_per_cell``, ``raw_bytes``, ``step``, ``threshold``,
        ``score_mse``, ``section`` (the table's).

    Raises
    ------
    FitError
        The database has no depth maps, or its framing does not allow the warp.
    """
    if db.depth is None:
        raise FitError(f"{db.path}: has no depth maps; render it with eigencast render (without "
                       "--no-depth)")
    problem = depth_problem(db.settings, db.image_shape)
    if problem is not None:
        raise FitError(f"{db.path}: its depth cannot be warped by: {problem}")
    camera = db.settings["camera"]
    h, w = db.depth_shape
    distance = float(camera["radius_mm"]) / math.sin(math.radians(camera["fov_deg"]) / 2)
    z_tolerance = Z_TOLERANCE * 2.0 * float(camera["radius_mm"])
    if score_mse is None:
        score_mse = DEPTH_SCORE_NOISE_Z2 * z_tolerance ** 2
    if not (math.isfinite(score_mse) and score_mse > 0):
        raise FitError(f"depth table noise {score_mse!r} must be > 0 mm^2")
    if (2 * h, 2 * w) != tuple(image.image_shape):
        raise FitError(f"{db.path}: depth maps {w}x{h} are not half the image size")
    offset = float(db.depth["offset_mm"])
    depths = np.empty((db.n_views, h, w), dtype=np.float32)
    for i in range(db.n_views):
        depths[i] = fill_nearest(db.read_depth(i))
    eig = fit_depth_eigenspaces(depths, [threshold], offset, score_mse=score_mse)[threshold]
    del depths
    secs = depth_sections(eig)
    if delta is not False:
        from device_runtime.standalone import standalone_order

        coded = depth_sections(eig, standalone_order(image, db.n_views))
        if delta or _zstd_size(coded[DEPTH_DELTA_SECTION]) < _zstd_size(secs["depth_scores"]):
            secs = coded
    for name in (*DEPTH_SECTIONS, DEPTH_DELTA_SECTION):
        image.sections.pop(name, None)
    image.sections.update(secs)
    image.synthesis = {
        "method": SYNTHESIS_METHOD,
        "fov_deg": float(camera["fov_deg"]),
        "distance_mm": distance,
        "z_tolerance_mm": z_tolerance,
        "depth_shape": [int(h), int(w)],
        "depth_cell": int(eig.cell),
        "depth_step": float(eig.step),
        "depth_offset_mm": offset,
        "depth_threshold": float(threshold),
    }
    raw = sum(int(a.nbytes) for a in secs.values())
    return {"components": eig.n_components,
            "components_per_cell": float(eig.counts.mean()) if eig.counts.size else 0.0,
            "raw_bytes": raw, "step": eig.step, "threshold": threshold,
            "score_mse": float(score_mse),
            "section": DEPTH_DELTA_SECTION if DEPTH_DELTA_SECTION in secs else "depth_scores"}


def _zstd_size(a: np.ndarray) -> int:
    import zstandard

    from protocol.image import DEFAULT_LEVEL

    return len(zstandard.ZstdCompressor(level=DEFAULT_LEVEL).compress(
        np.ascontiguousarray(a).tobytes()))
