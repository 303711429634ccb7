"""The noise floor of the colour eigenspace (``eigencast fit --depth``): below it, black.

A cell's eigenspace reconstructs every training view to within its truncation and rounding
noise, and that noise lands on the black background too: a cell that holds some of the
object shows small non-zero values on its background pixels, a haze bounded by the cell.
The device's warp took every reconstructed pixel above `device_runtime.synthesis.
OBJECT_LEVEL` for object and painted that haze into its frames (grey boxes along the cell
grid where the ray-cast is black).

`measure_noise_floor` measures, per cell, the level at or below which the training views are
better shown black than reconstructed: each training view is reconstructed exactly as the
device reconstructs a neighbour it warps (its standalone table row, the device's
`Reconstructor`) and compared with its rendering; a pixel whose largest channel is ``m``
gains ``|r - t|^2 - |t|^2`` (summed over channels, ``r`` the reconstruction, ``t`` the
rendering) when it is shown black instead: positive on the background (the haze goes),
negative where a dim object pixel is lost. Per cell, the floor is the level ``f`` whose
pixels ``OBJECT_LEVEL < m <= f`` gain most in total over the training views (the squared
error the eigenspace itself minimises); `OBJECT_LEVEL` (none) where no level gains.
`add_noise_floor` stores it as the image's `device_runtime.synthesis.NOISE_FLOOR_SECTION`:
the warp of `device_runtime.synthesis.SYNTHESIS_METHOD_FLOOR` warps those pixels black
(`device_runtime.synthesis.noise_levels`), so a training view warped to its own camera is
its reconstruction with them black, what the floor was measured on.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from device_runtime.synthesis import NOISE_FLOOR_SECTION, OBJECT_LEVEL
from host.errors import FitError

__all__ = ["FLOOR_LEVELS", "FLOOR_VIEWS", "NoiseFloor", "add_noise_floor", "floor_from_gains",
           "measure_noise_floor"]

#: Levels of a pixel's largest channel (uint8).
FLOOR_LEVELS = 256
#: Training views `measure_noise_floor` measures at most (evenly spread over the database):
#: a floor is a statistic of each cell's pixels over many views; at 256 pixels, the floors
#: of 500 of the 1500 views are within 3 levels of all 1500's (the tooth), in a third
#: of the time.
FLOOR_VIEWS = 500


class NoiseFloor:
    """What `measure_noise_floor` found.

    Attributes
    ----------
    floor : ndarray of shape (n_cells,), uint8
        Per cell, at least `OBJECT_LEVEL`.
    gains : ndarray of shape (n_cells, FLOOR_LEVELS), float64
        Per cell and level ``m`` of a pixel's largest channel: the squared error the
        training views lose (summed over pixels and views) when their pixels at ``m`` are
        shown black.
    views : int
        Training views measured.
    """

    def __init__(self, floor: np.ndarray, gains: np.ndarray, views: int) -> None:
        self.floor = floor
        self.gains = gains
        self.views = int(views)

    def summary(self) -> dict:
        """``views``, ``cells`` (where the floor is above `OBJECT_LEVEL`), and ``median`` and
        ``max`` over those cells (`OBJECT_LEVEL` when none)."""
        raised = self.floor[self.floor > OBJECT_LEVEL]
        return {"views": self.views, "cells": int(raised.size),
                "median": float(np.median(raised)) if raised.size else float(OBJECT_LEVEL),
                "max": int(raised.max()) if raised.size else OBJECT_LEVEL}


def floor_from_gains(gains: np.ndarray) -> np.ndarray:
    """Per cell, the level ``f >= OBJECT_LEVEL`` that maximises the summed gain of the levels
    ``OBJECT_LEVEL < m <= f`` (the smallest such level on ties; `OBJECT_LEVEL` when no level
    gains), uint8 (n_cells,), from ``gains`` (n_cells, FLOOR_LEVELS)."""
    g = np.asarray(gains, dtype=np.float64)
    total = np.cumsum(g[:, OBJECT_LEVEL + 1:], axis=1)
    best = np.argmax(total, axis=1)
    keep = total[np.arange(g.shape[0]), best] > 0.0
    return np.where(keep, best + OBJECT_LEVEL + 1, OBJECT_LEVEL).astype(np.uint8)


def measure_noise_floor(image: Any, db: Any, *, views: int | None = FLOOR_VIEWS,
                        progress: bool = True) -> NoiseFloor:
    """The noise floor of ``image``'s colour eigenspace on the training views of ``db``.

    Parameters
    ----------
    image : EigenspaceImage
        With the standalone table (`host.fit.model.add_standalone_table`), built from ``db``
        (its views in the database's order). Left as it is.
    db : CinemaDB
        The training views' renderings.
    views : int or None
        Measure this many training views at most, evenly spread (None: all).
    progress : bool

    Returns
    -------
    NoiseFloor

    Raises
    ------
    FitError
        The image has no standalone table, or ``db`` does not match it.
    """
    from device_runtime.reconstruct import Reconstructor
    from device_runtime.standalone import (
        STANDALONE_DELTA_SECTION,
        STANDALONE_SECTION,
        StandaloneScores,
    )
    from host.progress import progress as progress_bar

    if not {STANDALONE_SECTION, STANDALONE_DELTA_SECTION} & set(image.sections):
        raise FitError("noise floor: the image has no standalone table")
    if tuple(db.image_shape) != tuple(image.image_shape) or db.n_views != len(
            (image.views or {}).get("phi_deg", ())):
        raise FitError(f"noise floor: {db.path} does not match the image ({db.n_views} views "
                       f"of {db.image_shape}, the image {tuple(image.image_shape)})")
    # the table's loader decodes a delta-coded table in place: it gets a copy
    work = replace(image, sections={k: v.copy() if k == STANDALONE_DELTA_SECTION else v
                                    for k, v in image.sections.items()})
    table = StandaloneScores(work)
    reconstructor = Reconstructor.from_image(work)
    (h, w), (ch, cw), (ny, nx) = image.image_shape, image.cell_shape, image.grid_shape
    n_cells = ny * nx
    # each pixel's cell, times the levels: a pixel's bin is cell * FLOOR_LEVELS + level
    cell_of = ((np.arange(h)[:, None] // ch) * nx + np.arange(w)[None, :] // cw)
    base = (cell_of * FLOOR_LEVELS).astype(np.intp).ravel()
    gains = np.zeros(n_cells * FLOOR_LEVELS, np.float64)
    picked = (np.arange(db.n_views) if views is None or views >= db.n_views else
              np.unique(np.linspace(0, db.n_views - 1, max(1, int(views))).round().astype(int)))
    try:
        with progress_bar("noise floor", picked.size, unit=" views", quiet=not progress) as bar:
            for i in picked.tolist():
                r = reconstructor.update(table.training_scores(i))
                top = np.maximum(np.maximum(r[..., 0], r[..., 1]), r[..., 2]).ravel()
                r = r.reshape(-1, 3).astype(np.int32)
                t = db.read_image(i).reshape(-1, 3).astype(np.int32)
                # |r - t|^2 - |t|^2 = r . (r - 2 t), per pixel
                t *= -2
                t += r
                t *= r
                gain = t[:, 0] + t[:, 1]
                gain += t[:, 2]
                gains += np.bincount(base + top, weights=gain, minlength=gains.size)
                bar.advance()
    finally:
        reconstructor.close()
    gains = gains.reshape(n_cells, FLOOR_LEVELS)
    return NoiseFloor(floor_from_gains(gains), gains, picked.size)


def add_noise_floor(image: Any, db: Any, *, progress: bool = True) -> NoiseFloor:
    """Measure ``image``'s noise floor (`measure_noise_floor`) and store it as the section
    `device_runtime.synthesis.NOISE_FLOOR_SECTION` (in place). The synthesis record is left
    as it is: the warp reads the floor under `device_runtime.synthesis.SYNTHESIS_METHOD_FLOOR`
    (`host.evaluate.splat_filter.choose_splat_tent` names it)."""
    found = measure_noise_floor(image, db, progress=progress)
    image.sections[NOISE_FLOOR_SECTION] = found.floor
    return found
