"""Depth-aware view synthesis on the device (issue 15): warp the neighbours, do not blend them.

A standalone device used to show a novel view as the eigenspace reconstruction of the
interpolated training scores: a weighted sum of the 4 neighbouring training views, 12 degrees
apart, which shows every edge twice (docs/design-notes.md). An image fitted with
``eigencast fit --depth`` also carries a cell eigenspace of every training view's depth (the
distance along each pixel's ray where the opacity crosses one half, at half resolution) and
names the synthesis method in its manifest (``"synthesis": {"method": "warp-depth-1", ...}``,
:data:`SYNTHESIS_METHOD`; :data:`SYNTHESIS_METHOD_TENT` with the splat filter the fit chose
for the volume; :data:`SYNTHESIS_METHOD_FLOOR` with that filter and the colour's noise floor,
:data:`NOISE_FLOOR_SECTION`). For a novel view the device then

1. takes the interpolator's neighbours and weights (:class:`StandaloneScores`' interpolator)
   and, where they lie on two theta rows, fades the farther row out unless the view is
   near the rows' middle (`row_weights`, issue 22: two views warped instead of four, better
   frames and half the reconstructions along a drag);
2. reconstructs each neighbour's colour (the int8 eigenspace, the device's `Reconstructor`)
   and depth (:class:`DepthEigenspace`: only the cells under the object), and unprojects its
   object pixels once into points in that camera's frame (`Warper.cloud_at`: the depth
   upsampled 2x at those pixels, int16 packed points, 9 bytes per object pixel with the
   colour); they are cached per training view (:class:`ViewSynthesizer`, the
   :data:`CACHE_VIEWS` views of one frame: while a drag moves, the neighbours change only
   every grid step); with the noise floor, the pixels at or below their cell's floor are
   warped black (`noise_levels`: the eigenspace's haze on the black background is not
   painted, and the neighbour still says where its picture is black);
3. forward-warps every neighbour's points into the new camera with a z-test, blends them by
   their weights and fills the cracks (`device_runtime.warping`: :func:`forward_warp`,
   :func:`fill_holes`; its names are re-exported here).

Everything is numpy, float32, with no per-pixel Python loop. Memory is bounded by the frame
size (:func:`synthesis_memory_bytes`) and kept to what a device's RAM bound allows
(BENCHMARKS.md, "The device's own frame"): the warp works one view at a time on a grid it
reuses, and a
standalone device reconstructs the neighbours with the display's reconstructor. A frame is a
function of the image and the view only (not of the cache, the reconstructor or the thread):
the same code makes the host's frames (``eigencast evaluate``'s ``pca_warp``), so host and
device frames are identical, and ``research/warp_views.py`` (the go/no-go measurement)
imports it. A device makes its warps on a thread of its own
(`device_runtime.warp_worker.WarpWorker`).

Geometry: the orbit cameras of an eigencast database look at the bounding sphere's centre
from ``distance = radius / sin(fov / 2)`` (`host.render.camera.orbit_camera`); only relative
poses matter for a warp, so the device places the centre at the origin (:func:`orbit_pose`).
Perspective databases only (``fit --depth`` refuses the others).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

from device_runtime.standalone import delta_decode, standalone_order
from device_runtime.warping import (
    CHUNK,
    HOLE_NEIGHBOURS,
    HOLE_PASSES,
    MAX_WARP_PIXELS,
    SPLAT_TENT,
    SPLAT_TENTS,
    Z_TOLERANCE,
    WarpCancelled,
    Warper,
    _give_up_if,
    fill_holes,
    forward_warp,
    orbit_pose,
    upsample2,
    upsample2_at,
)
from protocol.errors import ImageFormatError

# the warp's names (`device_runtime.warping`) are re-exported: the synthesis' callers and
# the research scripts import them from here
__all__ = [
    "CACHE_VIEWS",
    "CHUNK",
    "DEPTH_DELTA_SECTION",
    "DEPTH_SECTIONS",
    "HOLE_NEIGHBOURS",
    "HOLE_PASSES",
    "KNOWN_SYNTHESIS",
    "NOISE_FLOOR_SECTION",
    "OBJECT_LEVEL",
    "ROW_RAMP",
    "SPLAT_TENT",
    "SPLAT_TENTS",
    "SYNTHESIS_METHOD",
    "SYNTHESIS_METHOD_FLOOR",
    "SYNTHESIS_METHOD_TENT",
    "WORKER_SCRATCH_BYTES",
    "Z_TOLERANCE",
    "DepthEigenspace",
    "ViewSynthesizer",
    "WarpCancelled",
    "Warper",
    "check_synthesis",
    "fill_holes",
    "forward_warp",
    "noise_levels",
    "orbit_pose",
    "row_weights",
    "splat_tent",
    "synthesis_memory_bytes",
    "upsample2",
    "upsample2_at",
]

#: Forward warp by half-opacity depth, splats spread by the [1/8, 3/4, 1/8] filter.
SYNTHESIS_METHOD = "warp-depth-1"
#: The same warp with the splat filter the image names (``synthesis.splat_tent``, one of
#: `SPLAT_TENTS`), which ``fit --depth`` chooses for the volume: a device that predates it
#: refuses such an image in one line instead of showing (and being corrected against) frames
#: other than the host's.
SYNTHESIS_METHOD_TENT = "warp-depth-2"
#: `SYNTHESIS_METHOD_TENT` (``splat_tent`` named, 6 included) whose neighbours' pixels at or
#: below their cell's noise floor (`NOISE_FLOOR_SECTION`, which the fit measures on the
#: training views) are warped black: the eigenspace's haze on the black background is not
#: painted. The image must hold the section; a device that predates the method refuses the
#: image in one line (its frames would differ from the host's).
SYNTHESIS_METHOD_FLOOR = "warp-depth-3"
KNOWN_SYNTHESIS = frozenset({SYNTHESIS_METHOD, SYNTHESIS_METHOD_TENT, SYNTHESIS_METHOD_FLOOR})
#: Image section of `SYNTHESIS_METHOD_FLOOR`: uint8 (n_cells,), one per colour cell (the
#: image's cells, row-major). A reconstructed training view's pixel whose largest channel is
#: at most its cell's value shows black: the warp unprojects it as before (above
#: `OBJECT_LEVEL`) with colour 0. ``fit --depth`` measures it (`host.fit.floor`): per cell,
#: the level at or below which showing black instead of the reconstruction brings the
#: training views closest to their renderings.
NOISE_FLOOR_SECTION = "noise_floor"
#: Image sections of the depth eigenspace (``fit --depth``), in this order. The score table
#: is either the plain int16 ``depth_scores`` (the first images) or, smaller,
#: :data:`DEPTH_DELTA_SECTION` in its place.
DEPTH_SECTIONS = ("depth_counts", "depth_scales", "depth_mean", "depth_components",
                  "depth_scores")
#: The depth score table delta-coded along the standalone order of the views, like the
#: colour's (`device_runtime.standalone.delta_encode`): uint8 (K, 2, n_views). Decoded in
#: place when the image is loaded (`DepthEigenspace.from_image`). A device that predates it
#: finds no ``depth_scores`` and refuses the image in one line when it needs the synthesis
#: (a standalone device); a served device ignores the depth sections either way.
DEPTH_DELTA_SECTION = "depth_scores_delta"
#: Training views whose points and colours stay cached (a view at 512: ~1.5 MB): the
#: neighbours of one frame. While a drag moves they change only every grid step; a cache
#: of 8 made as many reconstructions (0.58 per frame of an orbit, 1.67 of a 3-degree
#: drag at 512, with four neighbours a frame; 0.30 and 0.83 since `row_weights`), for
#: 6 MB more.
CACHE_VIEWS = 4

#: A view's neighbours on two theta rows of the grid (12 degrees apart on the paper's
#: grid): the farther row is dropped while its share of the interpolation weight is below
#: this, and faded in linearly from here to half (`row_weights`), so away from the rows'
#: middle one row's two views are warped. Fewer, nearer sources blend fewer misaligned
#: reconstructions: object SSIM +0.003 to +0.016 on every shared volume against all four
#: (docs/design-notes.md, "Which neighbours"), and a drag along a row reconstructs half the
#: neighbours.
ROW_RAMP = 0.4
#: Scratch of a predicting device's warp worker's own reconstructor (one thread): a third
#: of the display's, for 1.5x its time per neighbour (a cache miss, ~0.8 per drag frame),
#: on a thread that shares the 2 cores with the display anyway.
WORKER_SCRATCH_BYTES = 1 << 20
#: A reconstructed pixel whose largest channel is above this (0..255) carries the object
#: (`host.evaluate.masks.OBJECT_LEVEL`; the renderings have a black background).
OBJECT_LEVEL = 2


def row_weights(theta_deg: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The warp's weights of a view's neighbours: the interpolation's, with the farther of
    two theta rows faded out unless the view is near their middle (`ROW_RAMP`).

    Where the neighbours lie on two rows of the grid (the bilinear interpolation's 2 x 2),
    the farther row's share ``wm`` of the weight becomes ``0.5 * clip((wm - ROW_RAMP) /
    (0.5 - ROW_RAMP), 0, 1)`` and the nearer row takes the rest, each row's views keeping
    their proportions: a continuous function of the view. Any other set of neighbours
    keeps its weights. ``theta_deg`` holds each neighbour's theta, ``weights`` (> 0) their
    interpolation weights; float64, a new array.
    """
    w = np.array(weights, dtype=np.float64)
    rows = np.unique(theta_deg)
    if rows.size != 2 or ROW_RAMP >= 0.5:
        return w
    first = theta_deg == rows[0]
    share = float(w[first].sum()) / float(w.sum())
    near = share >= 0.5
    wm = 1.0 - share if near else share
    if not wm > 0.0:
        return w
    keep = 0.5 * min(max((wm - ROW_RAMP) / (0.5 - ROW_RAMP), 0.0), 1.0)
    minor = ~first if near else first
    w[minor] *= keep / wm
    w[~minor] *= (1.0 - keep) / (1.0 - wm)
    return w


# ----------------------------------------------------------------------------- manifest


def check_synthesis(record: Any, image_shape: tuple[int, int] | None = None) -> dict | None:
    """Validate an image manifest's ``synthesis`` record; return it (None: no synthesis).

    Raises
    ------
    ImageFormatError
        The record is not a map, names a method this device does not know (one line:
        the device refuses such an image), or lacks a parameter the method needs.
    """
    if record is None:
        return None
    if not isinstance(record, dict):
        raise ImageFormatError("image manifest: 'synthesis' must be a map or null")
    method = record.get("method")
    if method not in KNOWN_SYNTHESIS:
        raise ImageFormatError(
            f"image manifest: synthesis method {str(method)[:40]!r} is unknown to this device "
            f"(it knows {', '.join(sorted(KNOWN_SYNTHESIS))}); update the device runtime"
        )
    numbers = ("fov_deg", "distance_mm", "depth_step", "z_tolerance_mm")
    for key in numbers:
        v = record.get(key)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not (
            math.isfinite(v) and v > 0
        ):
            raise ImageFormatError(f"image manifest: synthesis.{key}={v!r} must be a number > 0")
    if not 0 < record["fov_deg"] < 180:
        raise ImageFormatError("image manifest: synthesis.fov_deg must be within (0, 180)")
    for key in ("depth_shape",):
        v = record.get(key)
        if not (isinstance(v, list) and len(v) == 2 and all(
                isinstance(x, int) and not isinstance(x, bool) and 0 < x < 1 << 16 for x in v)):
            raise ImageFormatError(f"image manifest: synthesis.{key}={v!r} must be [h, w] > 0")
    cell = record.get("depth_cell")
    if not isinstance(cell, int) or isinstance(cell, bool) or not 0 < cell <= 256:
        raise ImageFormatError(f"image manifest: synthesis.depth_cell={cell!r} must be 1..256")
    offset = record.get("depth_offset_mm")
    if not isinstance(offset, (int, float)) or isinstance(offset, bool) or not math.isfinite(
            offset):
        raise ImageFormatError("image manifest: synthesis.depth_offset_mm must be a number")
    tent = record.get("splat_tent")
    if method in (SYNTHESIS_METHOD_TENT, SYNTHESIS_METHOD_FLOOR):
        if isinstance(tent, bool) or tent not in SPLAT_TENTS:
            raise ImageFormatError(f"image manifest: synthesis.splat_tent={tent!r} must be one of "
                                   f"{', '.join(map(str, SPLAT_TENTS))}")
    elif tent is not None:
        raise ImageFormatError(f"image manifest: synthesis.splat_tent belongs to method "
                               f"{SYNTHESIS_METHOD_TENT!r} or {SYNTHESIS_METHOD_FLOOR!r}, "
                               f"not {method!r}")
    if image_shape is not None and [2 * v for v in record["depth_shape"]] != list(image_shape):
        raise ImageFormatError(
            f"image manifest: synthesis.depth_shape {record['depth_shape']} is not half the "
            f"image shape {list(image_shape)}"
        )
    h, w = (2 * v for v in record["depth_shape"])
    if (h + 2) * (w + 2) >= MAX_WARP_PIXELS:
        raise ImageFormatError(
            f"image manifest: synthesis of {w}x{h} frames is beyond this device's warp "
            f"(frames up to {MAX_WARP_PIXELS} padded pixels)")
    return record


def splat_tent(record: dict) -> int:
    """The splat filter's centre weight a (checked) ``synthesis`` record names: its
    ``splat_tent`` for `SYNTHESIS_METHOD_TENT` and `SYNTHESIS_METHOD_FLOOR`, else 6."""
    return int(record.get("splat_tent", SPLAT_TENTS[0]))


def noise_levels(image: Any, record: dict) -> np.ndarray | None:
    """The level at or below which a reconstructed training view's pixel (largest channel)
    is warped black: per pixel, uint8 (h, w), its cell's noise floor (`NOISE_FLOOR_SECTION`)
    for `SYNTHESIS_METHOD_FLOOR`; None for the others (every pixel keeps its colour).

    Raises
    ------
    ImageFormatError
        `SYNTHESIS_METHOD_FLOOR` without the section, or a section of another dtype or
        shape.
    """
    if record.get("method") != SYNTHESIS_METHOD_FLOOR:
        return None
    floor = image.sections.get(NOISE_FLOOR_SECTION)
    if floor is None:
        raise ImageFormatError(f"image: synthesis {SYNTHESIS_METHOD_FLOOR!r} needs the section "
                               f"{NOISE_FLOOR_SECTION!r}")
    ny, nx = image.grid_shape
    if floor.dtype != np.uint8 or floor.shape != (ny * nx,):
        raise ImageFormatError(f"image section {NOISE_FLOOR_SECTION!r}: expected uint8 of shape "
                               f"({ny * nx},) (one per cell), got {_describe(floor)}")
    (h, w), (ch, cw) = image.image_shape, image.cell_shape
    cells = floor.reshape(ny, nx)
    return np.ascontiguousarray(np.repeat(np.repeat(cells, ch, axis=0), cw, axis=1)[:h, :w])


def synthesis_memory_bytes(manifest: dict) -> int:
    """RAM the synthesis needs beyond the sections: the view cache and the warp's scratch.

    Counted whatever the device's mode: a standalone device warps every frame, a served
    device that predicts warps its own frames while the host's are on their way (both
    share the image's one standalone table, a section). Per cached view: the object
    pixels' packed points and uint8 colours (9 bytes per pixel at most); on a miss, a
    view's indices, depths and masks and one depth cell's components as float32; per
    frame, the splats' target pixels of 4 views (4 bytes each, all pixels at most: the
    reused `Warper.splats`), one view's projection temporaries, the
    padded grid (z-buffer then weights, 3 accumulators, coverage) and the tent filter's
    planes, and the warped frame on show (its own array); `SYNTHESIS_METHOD_FLOOR`, the
    per-pixel levels of `noise_levels` (a byte each) and, on a miss, the object pixels'
    largest channels, levels and two flags (4 bytes each). A predicting device's worker
    also has its own reconstructor (frame buffers and `WORKER_SCRATCH_BYTES`) and a frame
    made ahead (`WarpWorker`), counted here; a standalone device shares the display's.
    """
    record = manifest.get("synthesis")
    if record is None:
        return 0
    h, w = (2 * v for v in record["depth_shape"])
    n = h * w
    padded = (h + 2) * (w + 2)
    cache = CACHE_VIEWS * n * 9
    cell = int(record.get("depth_cell") or 1)
    depth = 3 * 4 * (h // 2 + cell) * (w // 2 + cell) + n * (8 + 4 + 3)
    depth += 4 * cell * cell * cell * cell  # one cell's components as float32
    warp = 4 * n * 4 * 5 // 4 + n * (4 + 4 + 8 + 1 + 4 + 4) + padded * (4 + 12 + 1 + 8) + n * 6
    colour = 2 * n * 3 + WORKER_SCRATCH_BYTES + n * 3  # + the frame made ahead
    levels = n * 5 if record.get("method") == SYNTHESIS_METHOD_FLOOR else 0  # `noise_levels`
    return int(cache + depth + warp + colour + levels)


# ----------------------------------------------------------------------------- depth


def split_cells(img: np.ndarray, cell: int) -> np.ndarray:
    """(h, w) with h, w multiples of ``cell`` -> (n_cells, cell * cell), cells row-major."""
    h, w = img.shape
    return img.reshape(h // cell, cell, w // cell, cell).swapaxes(1, 2).reshape(-1, cell * cell)


def merge_cells(cells: np.ndarray, cell: int, shape: tuple[int, int]) -> np.ndarray:
    """Inverse of `split_cells` for the padded shape ``shape``."""
    h, w = shape
    return cells.reshape(h // cell, w // cell, cell, cell).swapaxes(1, 2).reshape(h, w)


class DepthEigenspace:
    """A cell PCA of depth maps (mm along the rays minus the camera distance).

    Device-style storage: float16 cell means, int8 components with a float32 scale each,
    an int16 score table (training view ``i``'s scores are ``table[i] * step``). The depth
    maps (``shape``: half the image) are edge-padded to whole cells by the fit and cropped
    here.

    Parameters
    ----------
    cell : int
    shape : (int, int)
        Depth map shape (before padding to whole cells).
    mean : ndarray (n_cells, cell * cell) float16 or float32
    components : ndarray (K, cell * cell) int8
    scales : ndarray (K,) float32
    counts : ndarray (n_cells,) int
    table : ndarray (n_views, K) int16
    step : float
    offset : float
        The camera distance subtracted before the fit.
    """

    def __init__(self, cell: int, shape: tuple[int, int], mean: np.ndarray,
                 components: np.ndarray, scales: np.ndarray, counts: np.ndarray,
                 table: np.ndarray, step: float, offset: float) -> None:
        self.cell = int(cell)
        self.shape = (int(shape[0]), int(shape[1]))
        self.padded = (-(-self.shape[0] // self.cell) * self.cell,
                       -(-self.shape[1] // self.cell) * self.cell)
        self.mean = np.asarray(mean, dtype=np.float32)
        # C order: each cell's rows cast and summed the same way whatever made the array (a
        # fit's components are Fortran-ordered; a transposed product rounds differently)
        self.components = np.ascontiguousarray(components)
        self.scales = np.asarray(scales, dtype=np.float32)
        self.counts = np.asarray(counts, dtype=np.int64)
        self.table = table
        self.step = float(step)
        self.offset = float(offset)
        ends = np.cumsum(self.counts)
        # each cell's component rows [start, end), as Python ints (a miss walks them)
        self._rows = list(zip((ends - self.counts).tolist(), ends.tolist(), strict=True))

    @property
    def n_components(self) -> int:
        return int(self.counts.sum())

    @classmethod
    def from_image(cls, image: Any) -> DepthEigenspace:
        """The depth eigenspace of an image with a ``synthesis`` record and depth sections.

        Raises
        ------
        ImageFormatError
            Missing or inconsistent sections.
        """
        record = check_synthesis(image.synthesis, image.image_shape)
        if record is None:
            raise ImageFormatError("the image has no depth (refit with eigencast fit --depth)")
        s = image.sections
        delta = s.get(DEPTH_DELTA_SECTION)
        if delta is not None and "depth_scores" in s:
            raise ImageFormatError(f"image sections 'depth_scores' and {DEPTH_DELTA_SECTION!r} "
                                   "are both present; an image holds one depth table")
        need = DEPTH_SECTIONS[:-1] if delta is not None else DEPTH_SECTIONS
        missing = [name for name in need if name not in s]
        if missing:
            raise ImageFormatError(f"image: synthesis needs the sections {missing}")
        cell = record["depth_cell"]
        shape = tuple(record["depth_shape"])
        n_cells = (-(-shape[0] // cell)) * (-(-shape[1] // cell))
        counts, scales, mean = s["depth_counts"], s["depth_scales"], s["depth_mean"]
        comps = s["depth_components"]
        k = int(np.asarray(counts, dtype=np.int64).sum()) if counts.size else 0
        n_views = (image.interpolation or {}).get("n_views")
        if delta is not None:
            if (not isinstance(n_views, int) or delta.dtype != np.uint8
                    or delta.shape != (k, 2, n_views)):
                raise ImageFormatError(
                    f"image section {DEPTH_DELTA_SECTION!r}: expected uint8 of shape (K={k}, 2, "
                    f"n_views={n_views}), got {_describe(delta)}")
            # decoded once, in place; the image then holds the plain table
            s["depth_scores"] = delta_decode(delta, standalone_order(image, n_views))
            del s[DEPTH_DELTA_SECTION]
        table = s["depth_scores"]
        if (counts.shape != (n_cells,) or counts.dtype != np.int32 or (counts < 0).any()
                or mean.shape != (n_cells, cell * cell) or mean.dtype != np.float16
                or comps.shape != (k, cell * cell) or comps.dtype != np.int8
                or scales.shape != (k,) or scales.dtype != np.float32
                or table.dtype != np.int16 or table.shape != (n_views, k)):
            raise ImageFormatError(
                "image: depth sections inconsistent (counts "
                f"{_describe(counts)}, mean {_describe(mean)}, components {_describe(comps)}, "
                f"scales {_describe(scales)}, scores {_describe(table)}; {n_cells} cells of "
                f"{cell}x{cell}, {n_views} views)"
            )
        return cls(cell, shape, mean, comps, scales, counts, table, record["depth_step"],
                   record["depth_offset_mm"])

    def reconstruct(self, view: int, cells: np.ndarray | None = None) -> np.ndarray:
        """Depth map (h, w) float32 in mm along the rays, of training view ``view``.

        ``cells`` (bool, one per cell, optional): only these cells are reconstructed, the
        others hold their mean (a cache miss needs the cells under the view's object only,
        `needed_cells`). Each cell is one vector-matrix product of its components, cast to
        float32 a run of cells at a time (at most ``cell ** 4`` values), never all at once."""
        y = self.table[view].astype(np.float32) * np.float32(self.step)
        coef = self.scales * y
        out = self.mean.astype(np.float32)
        todo = self.counts > 0
        if cells is not None:
            todo &= cells
        todo = np.flatnonzero(todo)
        if todo.size:
            out[todo] += self._products(coef, todo)
        full = merge_cells(out, self.cell, self.padded)[:self.shape[0], :self.shape[1]]
        return full + np.float32(self.offset)

    def _products(self, coef: np.ndarray, todo: np.ndarray) -> np.ndarray:
        """``coef_c @ components_c`` of the cells ``todo`` (ascending), float32 (len(todo),
        cell * cell): runs of consecutive cells' rows cast at once into a scratch of one
        cell's worth of values at most (``cell ** 4``), then one product per cell into its
        own row (a cast and a product per cell cost twice as much in call overhead)."""
        values = self.cell * self.cell
        scratch = np.empty((values, values), np.float32)
        prod = np.empty((todo.size, values), np.float32)

        def flush(run: list[tuple[int, int, int]], r0: int, r1: int) -> None:
            rows = scratch[:r1 - r0]
            np.copyto(rows, self.components[r0:r1], casting="unsafe")
            for j, a, b in run:
                np.matmul(coef[a:b], rows[a - r0:b - r0], out=prod[j])

        run: list[tuple[int, int, int]] = []
        r0 = r1 = 0
        for i, c in enumerate(todo.tolist()):
            a, b = self._rows[c]
            if run and (a != r1 or b - r0 > values):
                flush(run, r0, r1)
                run = []
            if not run:
                r0 = a
            run.append((i, a, b))
            r1 = b
        flush(run, r0, r1)
        return prod

    def needed_cells(self, obj: np.ndarray) -> np.ndarray:
        """The cells (bool, one each) whose depth the full-resolution object pixels ``obj``
        (bool (2h, 2w)) need through `upsample2_at`: each pixel's half-resolution pixel and
        its neighbours (the bilinear taps reach one pixel)."""
        hh, hw = self.shape
        need = np.zeros(self.padded, bool)
        occ = need[:hh, :hw]
        np.logical_or(obj[0::2, 0::2], obj[1::2, 0::2], out=occ)
        occ |= obj[0::2, 1::2]
        occ |= obj[1::2, 1::2]
        rows = need.copy()
        rows[1:] |= need[:-1]
        rows[:-1] |= need[1:]
        np.copyto(need, rows)
        need[:, 1:] |= rows[:, :-1]
        need[:, :-1] |= rows[:, 1:]
        cy, cx = self.padded[0] // self.cell, self.padded[1] // self.cell
        # any over each cell: the rows of a cell, then its columns (contiguous reductions)
        per_row = need.reshape(cy * self.cell, cx, self.cell).any(axis=2)
        return per_row.reshape(cy, self.cell, cx).any(axis=1).reshape(-1)


def _describe(a: np.ndarray) -> str:
    return f"{a.dtype} {tuple(a.shape)}"


# ----------------------------------------------------------------------------- the frame


class ViewSynthesizer:
    """Novel views of an image with depth: the neighbours warped by their depth, blended.

    Parameters
    ----------
    image : EigenspaceImage
        With a standalone score table (``fit --standalone``) and depth (``fit --depth``).
    standalone : StandaloneScores
        The image's table and interpolator.
    reconstructor : Reconstructor
        Reconstructs the neighbours' colours (its frame buffer is overwritten).
    cache_views : int
        Training views kept (colour points and depth) between frames.

    Raises
    ------
    ImageFormatError
        No synthesis record, unknown method, malformed depth sections, or a missing or
        malformed noise floor (`noise_levels`).
    """

    def __init__(self, image: Any, standalone: Any, reconstructor: Any,
                 cache_views: int = CACHE_VIEWS) -> None:
        record = check_synthesis(image.synthesis, image.image_shape)
        if record is None:
            raise ImageFormatError("the image has no depth (refit with eigencast fit --depth)")
        self.depth = DepthEigenspace.from_image(image)
        self.standalone = standalone
        self.reconstructor = reconstructor
        h, w = image.image_shape
        self.warper = Warper(record["fov_deg"], record["distance_mm"], w, h,
                             record["z_tolerance_mm"], splat_tent(record))
        #: Per pixel, the level at or below which a neighbour's pixel is warped black
        #: (`noise_levels`; None: none is).
        self.noise_level = noise_levels(image, record)
        views = image.views or {}
        try:
            self.phi = np.asarray(views["phi_deg"], dtype=np.float64)
            self.theta = np.asarray(views["theta_deg"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise ImageFormatError("image manifest: synthesis needs views.phi_deg/theta_deg"
                                   ) from None
        if self.phi.shape != (self.depth.table.shape[0],) or self.theta.shape != self.phi.shape:
            raise ImageFormatError("image manifest: views and the depth score table disagree")
        self.cache_views = max(4, int(cache_views))
        self._cache: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.misses = 0

    def view_cloud(self, view: int) -> tuple[np.ndarray, np.ndarray]:
        """Training view ``view``'s object points (its camera frame) and colours (cached)."""
        hit = self._cache.get(view)
        if hit is not None:
            self._cache.move_to_end(view)
            return hit
        self.misses += 1
        colour = self.reconstructor.update(self.standalone.training_scores(view))
        # the largest channel, as two element-wise maxima (a reduce over the last axis of
        # (h, w, 3) uint8 costs as much as the reconstruction)
        top = np.maximum(colour[..., 0], colour[..., 1])
        np.maximum(top, colour[..., 2], out=top)
        obj = top > OBJECT_LEVEL
        src = np.flatnonzero(obj).astype(np.int32)
        # the eigenspace's haze on black: where it is, and warped, but black
        black = (None if self.noise_level is None else
                 np.take(top, src, mode="clip") <= np.take(self.noise_level, src, mode="clip"))
        del top
        cells = self.depth.needed_cells(obj)
        del obj
        cloud = self.warper.cloud_at(colour, self.depth.reconstruct(view, cells), src,
                                     black=black)
        self._cache[view] = cloud
        while len(self._cache) > self.cache_views:
            self._cache.popitem(last=False)
        return cloud

    def neighbours(self, phi_deg: float, theta_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """The training views a frame of this view warps and their weights (> 0): the
        interpolator's neighbours with positive weight, reweighted by `row_weights`.

        Returns
        -------
        views : ndarray (m,) int64
        weights : ndarray (m,) float64
        """
        idx, wts = self.standalone.interpolator.weights(phi_deg, theta_deg)
        idx = np.asarray(idx).ravel().astype(np.int64)
        wts = np.asarray(wts, dtype=np.float64).ravel()
        used = wts > 0
        idx, wts = idx[used], row_weights(self.theta[idx[used]], wts[used])
        used = wts > 0  # a neighbour without weight is neither reconstructed nor warped
        return idx[used], wts[used]

    def frame(self, phi_deg: float, theta_deg: float,
              cancel: Callable[[], bool] | None = None) -> np.ndarray:
        """The synthesized view: uint8 (h, w, 3), a new array.

        ``cancel`` (a warp worker's: a newer view was asked) is asked before each
        neighbour missing from the cache is made (a neighbour made is kept: the next view
        most likely needs it) and inside the warp (`forward_warp`); True raises
        `WarpCancelled`."""
        idx, wts = self.neighbours(phi_deg, theta_deg)
        views = [int(i) for i in idx]
        self._make_room(views)
        clouds = []
        for i in views:
            if i not in self._cache:
                _give_up_if(cancel)
            clouds.append(self.view_cloud(i))
        sources = [self.warper.pose(float(self.phi[i]), float(self.theta[i])) for i in idx]
        return forward_warp(self.warper, clouds, sources, wts,
                            self.warper.pose(phi_deg, theta_deg), cancel=cancel)

    def _make_room(self, views: list[int]) -> None:
        """Keep this frame's cached neighbours, and evict the views it does not need before
        its misses are made (so no neighbour is evicted by another, and an evicted view's
        memory is free before a new one takes it)."""
        for v in views:
            if v in self._cache:
                self._cache.move_to_end(v)
        missing = sum(v not in self._cache for v in views)
        need = set(views)
        while self._cache and len(self._cache) + missing > self.cache_views:
            oldest = next(iter(self._cache))
            if oldest in need:
                break
            del self._cache[oldest]
