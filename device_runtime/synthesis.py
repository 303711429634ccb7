"""Depth-aware view synthesis on the device (issue 15): warp the neighbours, do not blend them.

A standalone device used to show a novel view as the eigenspace reconstruction of the
interpolated training scores: a weighted sum of the 4 neighbouring training views, 12 degrees
apart, which shows every edge twice (docs/rate-distortion.md, section 9). An image fitted with
``eigencast fit --depth`` also carries a cell eigenspace of every training view's depth (the
distance along each pixel's ray where the opacity crosses one half, at half resolution) and
names the synthesis method in its manifest (``"synthesis": {"method": "warp-depth-1", ...}``,
:data:`SYNTHESIS_METHOD`). For a novel view the device then

1. takes the interpolator's neighbours and weights (:class:`StandaloneScores`' interpolator);
2. reconstructs each neighbour's colour (the int8 eigenspace, the device's `Reconstructor`)
   and depth (:class:`DepthEigenspace`, upsampled 2x by :func:`upsample2`), and unprojects
   its object pixels once into points in that camera's frame (int16, packed: 9 bytes per
   object pixel with the colour); they are cached per training view (:class:`ViewSynthesizer`,
   the :data:`CACHE_VIEWS` views of one frame: while a drag moves, the neighbours change
   only every grid step);
3. forward-warps every neighbour's points into the new camera with a z-test, blends them by
   the interpolation weights and fills the cracks (:func:`forward_warp`, :func:`fill_holes`).

Everything is numpy, float32, with no per-pixel Python loop. Memory is bounded by the frame
size (:func:`synthesis_memory_bytes`) and kept to what a device's RAM bound allows
(docs/rate-distortion.md 9.9): the warp works one view at a time on a grid it reuses, and a
standalone device reconstructs the neighbours with the display's reconstructor. The same
code makes the host's frames
(``eigencast evaluate``'s ``pca_warp``) so host and device frames are identical, and
``scripts/warp_views.py`` (the go/no-go measurement) imports it.

Geometry: the orbit cameras of an eigencast database look at the bounding sphere's centre
from ``distance = radius / sin(fov / 2)`` (`host.render.camera.orbit_camera`); only relative
poses matter for a warp, so the device places the centre at the origin (:func:`orbit_pose`).
Perspective databases only (``fit --depth`` refuses the others).
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

from device_runtime.standalone import delta_decode, standalone_order
from protocol.errors import ImageFormatError

__all__ = [
    "CACHE_VIEWS",
    "DEPTH_DELTA_SECTION",
    "DEPTH_SECTIONS",
    "KNOWN_SYNTHESIS",
    "SYNTHESIS_METHOD",
    "WORKER_SCRATCH_BYTES",
    "DepthEigenspace",
    "ViewSynthesizer",
    "WarpCancelled",
    "WarpWorker",
    "Warper",
    "check_synthesis",
    "fill_holes",
    "forward_warp",
    "orbit_pose",
    "row_weights",
    "synthesis_memory_bytes",
    "upsample2",
    "upsample2_at",
]

#: The one synthesis method this device knows: forward warp by half-opacity depth.
SYNTHESIS_METHOD = "warp-depth-1"
KNOWN_SYNTHESIS = frozenset({SYNTHESIS_METHOD})
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
#: drag at 512), for 6 MB more.
CACHE_VIEWS = 4

#: A view's neighbours on two theta rows of the grid (12 degrees apart on the paper's
#: grid): the farther row is faded out below this share of the interpolation weight and
#: dropped below it (`row_weights`), so away from the rows' middle one row's two views are
#: warped. Fewer, nearer sources blend fewer misaligned reconstructions: object SSIM +0.005
#: (tooth) and +0.015 (head) at 256 against all four (docs/rate-distortion.md 9.10), and
#: a drag along a row reconstructs half the neighbours.
ROW_RAMP = 0.4
#: z-test tolerance as a fraction of the bounding-sphere diameter: samples of one pixel
#: within this of the nearest one are blended, the rest are hidden.
Z_TOLERANCE = 0.02
#: Nearest-pixel splats are spread by a [1/8, 3/4, 1/8] x [1/8, 3/4, 1/8] filter over the
#: covered pixels (the accumulators are filtered before the blend is normalised): in
#: expectation over where a point lands, the spread of a bilinear splat. Coverage is the
#: unfiltered one: a pixel is covered when a splat lands on it.
SPLAT_TENT = True
#: The warp indexes its padded grid in float32, exact below 2**24 pixels (4094 x 4094).
MAX_WARP_PIXELS = 1 << 24
#: Pixels or points per pass of the work on a view (a cache miss' rays and depth
#: upsampling, the warp's passes): bounds the temporaries to a few hundred kilobytes
#: whatever the frame size.
CHUNK = 1 << 15
#: Scratch of a predicting device's warp worker's own reconstructor (one thread): a third
#: of the display's, for 1.5x its time per neighbour (a cache miss, ~1.7 per drag frame),
#: on a thread that shares the 2 cores with the display anyway.
WORKER_SCRATCH_BYTES = 1 << 20
#: Hole filling: passes of a 3x3 normalised average over covered neighbours, for holes with
#: at least HOLE_NEIGHBOURS of their 8 neighbours covered (cracks, not the silhouette).
HOLE_PASSES = 2
HOLE_NEIGHBOURS = 4
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


class WarpCancelled(Exception):
    """A warp given up because its ``cancel`` callable said so (a newer view was asked)."""


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
    planes, and the warped frame on show (its own array). A predicting device's worker
    also has its own reconstructor (frame buffers and `WORKER_SCRATCH_BYTES`), counted
    here; a standalone device shares the display's.
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
    colour = 2 * n * 3 + WORKER_SCRATCH_BYTES
    return int(cache + depth + warp + colour)


# ----------------------------------------------------------------------------- geometry


def orbit_pose(phi_deg: float, theta_deg: float, distance: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """The orbit camera of a view with the sphere's centre at the origin.

    Returns
    -------
    position : ndarray (3,), float64
    rotation : ndarray (3, 3), float64
        Columns right, up, forward (`host.render.camera.Camera.basis`).
    """
    phi, theta = math.radians(phi_deg), math.radians(theta_deg)
    cp, sp, ct, st = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta)
    # forward f = -direction, up u, right r = f x u normalised: in Python floats (a frame
    # needs five poses; numpy's cross and norm cost more than the arithmetic)
    f = (-ct * cp, -ct * sp, -st)
    u = (-st * cp, -st * sp, ct)
    r = (f[1] * u[2] - f[2] * u[1], f[2] * u[0] - f[0] * u[2], f[0] * u[1] - f[1] * u[0])
    n = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    position = np.array([distance * ct * cp, distance * ct * sp, distance * st])
    return position, np.array([[r[i] / n, u[i], f[i]] for i in range(3)])


class Warper:
    """Forward warping between the orbit cameras of one framing, at one image size.

    Every orbit camera has the same intrinsics: a pixel's unit ray in camera coordinates
    (right, up, forward) follows from its row and column (`unproject_at`). The warper also
    owns the warp's working set, allocated on the first frame and reused (`forward_warp`):
    the padded grid's z-buffer (then blend weights), coverage and three colour accumulators
    (`grid`), and each splat's target pixel (`splats`, grown, never shrunk). One warper
    serves one thread.

    Parameters
    ----------
    fov_deg : float
        Vertical field of view.
    distance_mm : float
        Camera distance from the orbit centre.
    width, height : int
    z_tolerance_mm : float
        Splats within this of a pixel's nearest one are blended (`Z_TOLERANCE` x the
        bounding-sphere diameter).
    """

    def __init__(self, fov_deg: float, distance_mm: float, width: int, height: int,
                 z_tolerance_mm: float) -> None:
        self.width, self.height = int(width), int(height)
        self.distance = float(distance_mm)
        self.half = math.tan(math.radians(fov_deg) / 2.0)
        # packed points (`unproject_at(packed=True)`): int16 steps from the orbit centre, which
        # sits at (0, 0, distance) in every orbit camera, over twice the bounding sphere's
        # radius (distance * sin(fov / 2)); a step is 6e-5 of the radius (1/100 of a pixel at
        # 1080) and points beyond are clamped (outside the sphere: noise of the depth fit)
        self.point_step = 2.0 * self.distance * math.sin(math.radians(fov_deg) / 2.0) / 32767
        # the rays' tangents per column and per row (float64: a ray is normalised from them)
        self._gx = ((np.arange(self.width) + 0.5) / self.width * 2.0 - 1.0) * (
            self.width / self.height) * self.half
        self._gy = (1.0 - (np.arange(self.height) + 0.5) / self.height * 2.0) * self.half
        self.tol_mm = float(z_tolerance_mm)
        self._splats: np.ndarray | None = None
        self._grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        #: What the last frame wrote in the z-buffer: its rectangle (rows r0:r1, columns
        #: c0:c1) and its first ``run`` pixels, (r0, r1, c0, c1, run); None: clean.
        self.dirty: tuple[int, int, int, int, int] | None = None

    def splats(self, total: int) -> np.ndarray:
        """The target pixel of each of ``total`` splats (int32), reused between frames
        (grown with a sixteenth to spare when short, never shrunk)."""
        if self._splats is None or self._splats.size < total:
            self._splats = None  # the old one goes before the new one is made
            self._splats = np.empty(int(total * 1.0625), np.int32)
        return self._splats[:total]

    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The warp's working set, made once, reused by every frame: the padded grid's
        z-buffer (h + 2, w + 2) float32, returned clean (inf), and scratch for the compact
        grid of the splats' rectangle: three colour accumulators (one flat float32 run of
        3 x (grid + 1)) and coverage (bool, grid size).

        A frame dirties the z-buffer's rectangle its splats land in and the z-buffer's
        first pixels, where it accumulates the blend weights (`dirty`, set by
        `forward_warp`); only those are cleaned here."""
        shape = (self.height + 2, self.width + 2)
        if self._grid is None:
            size = shape[0] * shape[1]
            self._grid = (np.full(shape, np.inf, np.float32),
                          np.empty(3 * (size + 1), np.float32), np.empty(size, bool))
            self.dirty = None
        zgrid = self._grid[0]
        if self.dirty is not None:
            r0, r1, c0, c1, run = self.dirty
            zgrid[r0:r1, c0:c1] = np.inf
            zgrid.reshape(-1)[:run] = np.inf
            self.dirty = None
        return self._grid

    def pose(self, phi_deg: float, theta_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """`orbit_pose` at this warper's distance."""
        return orbit_pose(phi_deg, theta_deg, self.distance)

    def unproject(self, colour: np.ndarray, depth: np.ndarray, valid: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """A source view's object pixels as points in its camera frame, and their colours.

        Planar (3, n) arrays, so the per-frame projection (`forward_warp`) is one small
        matrix product and contiguous passes.

        Returns
        -------
        points : ndarray (3, n) float32
            ``ray * depth`` of each valid pixel with a finite depth.
        rgb : ndarray (3, n)
            ``colour``'s dtype: uint8 for the device's reconstructions, a quarter of float32
            in the view cache (the warp converts each splat's colour as it uses it).
        """
        src = np.flatnonzero(valid)
        return self.unproject_at(colour, depth.reshape(-1)[src], src)

    def unproject_at(self, colour: np.ndarray, t: np.ndarray, src: np.ndarray, *,
                     packed: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """`unproject` of the pixels ``src`` (flat indices) given their depths ``t``.

        The rays are made for these pixels only, `CHUNK` at a time (a frame's worth of
        rays would be 12 bytes per pixel held for good). With ``packed`` the points are
        int16 (3, n) in `point_step`s from the orbit centre (half of float32's bytes: the
        view cache's form, which `forward_warp` takes as well)."""
        t = np.asarray(t, dtype=np.float32)
        finite = np.isfinite(t)
        if not finite.all():
            src, t = src[finite], t[finite]
        points = np.empty((3, src.size), np.int16 if packed else np.float32)
        for a in range(0, src.size, CHUNK):
            b = min(a + CHUNK, src.size)
            row, col = np.divmod(src[a:b], self.width)
            gx, gy = self._gx[col], self._gy[row]
            norm = gx * gx
            norm += gy * gy
            norm += 1.0
            np.sqrt(norm, out=norm)
            np.divide(gx, norm, out=gx)
            np.divide(gy, norm, out=gy)
            del row, col
            rays = (gx, gy, np.reciprocal(norm, out=norm))
            p = np.empty(b - a, np.float32)
            for r in range(3):
                p[...] = rays[r]
                p *= t[a:b]
                if packed:
                    if r == 2:
                        p -= np.float32(self.distance)
                    p *= np.float32(1.0 / self.point_step)
                    np.rint(p, out=p)
                    np.clip(p, -32767, 32767, out=p)
                points[r, a:b] = p
            del gx, gy, norm, rays, p
        rgb = np.empty((3, src.size), colour.dtype)
        flat = colour.reshape(-1, 3)
        for c in range(3):
            rgb[c] = flat[src, c]
        return points, rgb

    def cloud_at(self, colour: np.ndarray, half_depth: np.ndarray, src: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """A cached view: the pixels ``src`` (flat indices) of ``colour`` unprojected, packed.

        `unproject_at(colour, upsample2_at(half_depth, src, width), src, packed=True)` in
        one pass of float32 arithmetic, `CHUNK` pixels at a time: each pixel's depth from
        the half-resolution map ``half_depth`` (h / 2, w / 2) by `upsample2`'s bilinear
        weights, its ray from float32 tangents, the point in int16 `point_step`s from the
        orbit centre (what `forward_warp` takes). Non-finite depths are dropped.

        Returns
        -------
        points : ndarray (3, n) int16
        rgb : ndarray (3, n) uint8
        """
        d = np.asarray(half_depth, dtype=np.float32)
        hh, hw = d.shape
        flat = d.reshape(-1)
        qa, qb = np.float32(0.75), np.float32(0.25)
        k = np.float32(1.0 / self.point_step)
        dist = np.float32(self.distance)
        gx32, gy32 = self._gx.astype(np.float32), self._gy.astype(np.float32)
        points = np.empty((3, src.size), np.int16)
        keep = np.ones(src.size, bool)
        shift = self.width.bit_length() - 1  # a power-of-two width: shifts, not a division
        pow2 = self.width == 1 << shift
        for lo in range(0, src.size, CHUNK):
            hi = min(lo + CHUNK, src.size)
            if pow2:
                y, x = src[lo:hi] >> shift, src[lo:hi] & (self.width - 1)
            else:
                y, x = np.divmod(src[lo:hi], self.width)
            # the depth: even output rows/columns take the previous half-resolution one,
            # odd the next (clamped)
            iy, ix = y >> 1, x >> 1
            ny = iy + ((y & 1) * 2 - 1)
            np.clip(ny, 0, hh - 1, out=ny)
            nx = ix + ((x & 1) * 2 - 1)
            np.clip(nx, 0, hw - 1, out=nx)
            iy *= hw
            ny *= hw
            near = qa * flat[iy + ix]
            near += qb * flat[ny + ix]
            far = qa * flat[iy + nx]
            far += qb * flat[ny + nx]
            del iy, ix, ny, nx
            near *= qa
            far *= qb
            t = near
            t += far
            del far
            ok = np.isfinite(t)
            if not ok.all():
                keep[lo:hi] = ok
                t[~ok] = 0.0
            # the ray's tangents; the point's forward coordinate is t / |(gx, gy, 1)|
            gx, gy = gx32[x], gy32[y]
            del x, y
            inv = gx * gx
            inv += gy * gy
            inv += np.float32(1.0)
            np.sqrt(inv, out=inv)
            np.divide(t, inv, out=t)  # t: the forward coordinate now
            del inv
            t *= k
            for r, p in enumerate((gx, gy)):
                p *= t
                np.rint(p, out=p)
                np.clip(p, -32767, 32767, out=p)
                points[r, lo:hi] = p
            t -= dist * k
            np.rint(t, out=t)
            np.clip(t, -32767, 32767, out=t)
            points[2, lo:hi] = t
            del gx, gy, t
        if not keep.all():
            src, points = src[keep], np.ascontiguousarray(points[:, keep])
        rgb = np.empty((3, src.size), colour.dtype)
        cflat = np.ascontiguousarray(colour).reshape(-1)
        at = src * 3
        for c in range(3):
            np.take(cflat, at + c if c else at, out=rgb[c])
        return points, rgb

    def warp(self, colours: list[np.ndarray], depths: list[np.ndarray],
             valid: list[np.ndarray], sources: list[tuple[np.ndarray, np.ndarray]],
             weights: np.ndarray, target: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Unproject each source and `forward_warp` it; uint8 (h, w, 3)."""
        clouds = [self.unproject(c, d, ok) for c, d, ok in zip(colours, depths, valid)]
        return forward_warp(self, clouds, sources, weights, target)


def forward_warp(w: Warper, clouds: list[tuple[np.ndarray, np.ndarray]],
                 sources: list[tuple[np.ndarray, np.ndarray]], weights: np.ndarray,
                 target: tuple[np.ndarray, np.ndarray],
                 cancel: Callable[[], bool] | None = None) -> np.ndarray:
    """Forward-warp source views into the target camera, z-test, blend, fill holes.

    Each source point (a pixel unprojected with its depth, `Warper.unproject`) is projected
    into the target camera and splats onto the one pixel it lands in (nearest-pixel
    splatting: one splat per point, a quarter of bilinear splatting's). A z-buffer
    (``np.minimum.at``) keeps, per target pixel, the nearest splat's forward distance;
    splats within the z tolerance of it are blended with the view's interpolation weight,
    the rest are hidden. The accumulated weights and weighted colours are filtered by
    `SPLAT_TENT`'s [1/8, 3/4, 1/8] kernel before the blend is normalised (the spread a
    bilinear splat has on average). A pixel no splat lands on is a hole (a pixel one view
    alone sees is covered, however small that view's weight); `fill_holes` closes the
    cracks among covered pixels. Splats land on a grid one pixel larger on every side
    (points beyond it are clamped onto that border, which is then emptied), so nothing
    needs masking.

    Memory and time: three passes over the sources, `CHUNK` points at a time (the z-buffer;
    the z-test, which moves a hidden splat to the border pixel; the blend), so a frame's
    temporaries are a chunk's; what persists is the warper's grid and each splat's target
    pixel (4 bytes, `Warper.splats`). Accumulation is float32 in place (``np.add.at``),
    never a float64 copy of the grid. Everything after the splats (filter, blend, hole
    filling, the frame) works on the rectangle the splats landed in, 3 pixels larger on
    every side (what the filter and hole filling reach), not the whole grid; the grid is
    left clean outside it (`Warper.grid`).

    Parameters
    ----------
    w : Warper
    clouds : list of (points (3, n) float32 or int16 packed, rgb (3, n) uint8 or float32)
        Each source's object points in its camera frame and their colours.
    sources, target : (position (3,), rotation (3, 3)) from `Warper.pose`
    weights : ndarray (m,)
        Interpolation weights of the sources.
    cancel : callable, optional
        Asked before every chunk of the three passes and before the filter; True gives the
        warp up.

    Returns
    -------
    ndarray (h, w, 3) uint8

    Raises
    ------
    WarpCancelled
        ``cancel`` returned True.
    """
    h, wd = w.height, w.width
    w2 = wd + 2
    p_t, r_t = target
    f32 = np.float32
    used = [(pts, rgb, src, float(wv)) for (pts, rgb), src, wv in zip(clouds, sources, weights)
            if wv > 0.0 and pts.shape[1] > 0]
    frame = np.zeros((h, wd, 3), dtype=np.uint8)
    if not used:
        return frame
    # target camera -> padded pixel coordinates: col + 1 = x / z * sx + ox, row + 1 = ...,
    # as one projective 3 x 3 (x' / z, y' / z are the padded column and row)
    sx = 0.5 * h / w.half
    scale = np.array([[sx, 0.0, 0.5 * wd + 1.0], [0.0, -sx, 0.5 * h + 1.0], [0.0, 0.0, 1.0]])
    idx = w.splats(sum(u[0].shape[1] for u in used))
    zgrid, acc, cover = w.grid()  # the z-buffer clean (inf); scratch
    w.dirty = (0, h + 2, 0, w2, zgrid.size)  # until pass 2 ends (a cancelled warp: all)
    zbuf = zgrid.reshape(-1)
    pieces = []  # (slice of idx, the points and colours there, the view's m, b and weight)
    o = 0
    for pts, col, (p_s, r_s), wv in used:
        m = scale @ (r_t.T @ r_s)
        b = scale @ (r_t.T @ (p_s - p_t))
        if pts.dtype == np.int16:  # packed (`Warper.unproject_at`): steps from the centre
            b = b + m @ np.array([0.0, 0.0, w.distance])
            m = m * w.point_step
        m, b = m.astype(f32), b.astype(f32)
        k = pts.shape[1]
        for a in range(0, k, CHUNK):  # CHUNK points at a time: small temporaries
            e = min(a + CHUNK, k)
            pieces.append((slice(o + a, o + e), pts[:, a:e], col[:, a:e], m, b, f32(wv)))
        o += k
    x0, x1, y0, y1 = w2, 0.0, h + 2.0, 0.0  # the rectangle the splats land in
    for s, pts, _, m, b, _ in pieces:  # pass 1: where each splat lands, the z-buffer
        _give_up_if(cancel)
        # einsum, not matmul: (3, 3) @ (3, n) float32 through BLAS is ~50x slower here
        xyz = np.einsum("ij,jk->ik", m, pts)
        xyz += b[:, None]
        cx, cy, z = xyz
        if float(z.min()) > 1e-3:
            div, behind = z, None
        else:  # points behind the camera land on the border (pixel 0), emptied below
            behind = z <= f32(1e-3)
            div = np.maximum(z, f32(1e-3))
        np.divide(cx, div, out=cx)
        np.divide(cy, div, out=cy)
        del div
        if behind is not None:
            cx[behind] = 0.0
            cy[behind] = 0.0
        lo_x, hi_x, lo_y, hi_y = (float(cx.min()), float(cx.max()), float(cy.min()),
                                  float(cy.max()))
        if lo_x < 0.0 or hi_x > w2 - 1:  # strays beyond the grid land on its border
            np.clip(cx, 0, w2 - 1, out=cx)
        if lo_y < 0.0 or hi_y > h + 1:
            np.clip(cy, 0, h + 1, out=cy)
        x0, x1 = min(x0, max(lo_x, 0.0)), max(x1, min(hi_x, w2 - 1.0))
        y0, y1 = min(y0, max(lo_y, 0.0)), max(y1, min(hi_y, h + 1.0))
        # the pixel the point lands in: truncation of values >= 0, row * w2 + col in float32
        # (exact: the grid has fewer than MAX_WARP_PIXELS, check_synthesis), one cast
        np.trunc(cx, out=cx)
        np.trunc(cy, out=cy)
        cy *= f32(w2)
        cx += cy
        idx[s] = cx
        np.minimum.at(zbuf, idx[s], z)
        del xyz, cx, cy, z
    # from here on the rectangle the splats landed in, 3 pixels to spare on every side (what
    # the filter and hole filling reach), as a compact grid of its own: each plane one
    # contiguous run (rows of a rectangle inside the grid are strided: 4x slower per pixel)
    r0, r1 = max(0, int(y0) - 3), min(h + 2, int(y1) + 4)
    c0, c1 = max(0, int(x0) - 3), min(w2, int(x1) + 4)
    rh, rw = r1 - r0, c1 - c0
    n = rh * rw
    shift, base = w2 - rw, r0 * rw + c0
    # pass 2: a splat beyond the z tolerance of its pixel's nearest is hidden; it moves to
    # the compact grid's spare last pixel (n) so the blend needs no per-splat weight; the
    # others to their pixel in the compact grid
    tol = f32(w.tol_mm)
    for s, pts, _, m, b, _ in pieces:
        _give_up_if(cancel)
        at = idx[s]
        zmax = zbuf[at]
        zmax += tol
        hidden = _forward(m, b, pts) > zmax
        del zmax
        if shift:
            y = at // w2
            y *= shift
            at -= y
            del y
        at -= base
        at[hidden] = n
        del hidden
    cov = cover[:n]
    np.isfinite(zgrid[r0:r1, c0:c1], out=cov.reshape(rh, rw))
    w.dirty = (r0, r1, c0, c1, n + 1)  # the z-buffer's run holds the weights now
    flat_w = zbuf[:n + 1]  # the z-buffer is done with: it accumulates the blend weights
    flat_w[...] = 0.0
    flat_acc = acc[:3 * (n + 1)].reshape(3, n + 1)
    flat_acc[...] = 0.0
    for s, _, col, _, _, wv in pieces:  # pass 3: the blend
        _give_up_if(cancel)
        at = idx[s]
        np.add.at(flat_w, at, wv)
        for c in range(3):
            np.add.at(flat_acc[c], at, np.multiply(col[c], wv, dtype=f32))
    wb, pb = flat_w[:n], flat_acc[:, :n]
    # the grid's border (clamped strays) emptied where the rectangle meets it
    for a_ in (cov, wb, *pb):
        a2 = a_.reshape(rh, rw)
        if r0 == 0:
            a2[0] = 0
        if r1 == h + 2:
            a2[-1] = 0
        if c0 == 0:
            a2[:, 0] = 0
        if c1 == w2:
            a2[:, -1] = 0
    _give_up_if(cancel)
    if SPLAT_TENT:
        _tent(pb, rw)
        _tent(wb[None], rw)
    np.divide(f32(1.0), wb, out=wb, where=cov)
    np.multiply(wb, cov, out=wb)  # 1 / weight where covered, else 0
    pb *= wb
    _fill_holes_padded(flat_acc, cov, rw)
    # rounded by truncation: every value is a mean of colours in 0..255 with positive
    # weights (to float32's precision), so none leaves 0..255.5 and the cast needs no clip
    pb += f32(0.5)
    # the frame's pixels inside the rectangle (padded pixel (y, x) is the frame's
    # (y - 1, x - 1))
    fr0, fr1, fc0, fc1 = max(r0, 1), min(r1, h + 1), max(c0, 1), min(c1, wd + 1)
    out = frame[fr0 - 1:fr1 - 1, fc0 - 1:fc1 - 1]
    for c in range(3):
        out[..., c] = pb[c].reshape(rh, rw)[fr0 - r0:fr1 - r0, fc0 - c0:fc1 - c0]
    return frame


def _give_up_if(cancel: Callable[[], bool] | None) -> None:
    """Raise `WarpCancelled` if ``cancel`` (when given) says the warp is no longer wanted."""
    if cancel is not None and cancel():
        raise WarpCancelled


def _forward(m: np.ndarray, b: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The target camera's forward distance of points (``m @ pts + b``, row 2), float32:
    the same operations in each pass, so equal values."""
    z = np.einsum("j,jk->k", m[2], pts)
    z += b[2]
    return z


def _tent(a: np.ndarray, width: int) -> np.ndarray:
    """Separable [1, 6, 1] filter of rows ``width`` long, times 64 (zero outside), float32,
    in place: ``a`` (planes, n) holds each plane's rows end to end (contiguous), with a
    zero first and last column (the grid's border), so a shift by one pixel along the run
    never carries a value from one row into the next. One plane of scratch.

    64 times the [1/8, 3/4, 1/8] filter exactly (a power of two), which the blend's
    normalisation cancels bit for bit: weights and weighted colours are both filtered."""
    six = np.float32(6.0)
    t = np.empty(a.shape[1:], a.dtype)
    for k in range(a.shape[0]):
        p = a[k]
        np.multiply(p, six, out=t)
        t[width:] += p[:-width]
        t[:-width] += p[width:]
        np.multiply(t, six, out=p)
        p[1:] += t[:-1]
        p[:-1] += t[1:]
    return a


def fill_holes(frame: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Fill uncovered pixels with the mean of their covered 3x3 neighbours where at least
    `HOLE_NEIGHBOURS` of the 8 are covered, `HOLE_PASSES` times (cracks close, the
    silhouette does not grow). ``frame`` (h, w, 3) float32 is filled in place and returned."""
    h, w = covered.shape
    cov = np.zeros((h + 2, w + 2), bool)
    cov[1:-1, 1:-1] = covered
    planes = np.zeros((frame.shape[2], h + 2, w + 2), np.float32)
    planes[:, 1:-1, 1:-1] = np.moveaxis(frame, 2, 0)
    planes *= cov
    _fill_holes_padded(planes.reshape(planes.shape[0], -1), cov.reshape(-1), w + 2)
    filled = cov[1:-1, 1:-1] & ~covered
    frame[filled] = np.moveaxis(planes[:, 1:-1, 1:-1], 0, 2)[filled]
    return frame


def _fill_holes_padded(planes: np.ndarray, covered: np.ndarray, width: int) -> np.ndarray:
    """`fill_holes` on planar channels (c, >= n) float32 (C-contiguous; the pixels past n are
    left alone) of a grid of n = ``covered.size`` pixels in rows ``width`` long whose first
    and last rows and columns are empty and never filled, 0 at every uncovered pixel;
    ``covered`` (n,) bool is updated. In place.

    The neighbour counts are sums of the run shifted by a pixel and by a row (uint8, at
    most 8): a shift by one pixel carries the last column of a row into the next row's
    first, which is empty."""
    c, n = planes.shape[0], covered.size
    wp = int(width)
    if n < 3 * wp:
        return planes
    c8 = covered.view(np.uint8)
    inner = slice(wp + 1, n - wp - 1)  # pixel k = j + wp + 1 for count[j]
    offsets = [dy * wp + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
    for _ in range(HOLE_PASSES):
        h3 = c8[:-2] + c8[1:-1]
        h3 += c8[2:]
        count = h3[:-2 * wp] + h3[wp:-wp]
        count += h3[2 * wp:]
        del h3
        count -= c8[inner]  # the 8 neighbours
        fill = count >= HOLE_NEIGHBOURS
        np.greater(fill, covered[inner], out=fill)  # and not covered
        fill[wp - 1::wp] = False  # the first column
        fill[wp - 2::wp] = False  # and the last
        at = np.flatnonzero(fill)
        del fill
        if at.size == 0:
            break
        k = count[at].astype(np.float32)
        at += wp + 1
        # the mean of the covered neighbours (uncovered ones are 0) at the filled pixels only
        acc = np.take(planes, at + offsets[0], axis=1)
        for off in offsets[1:]:
            acc += np.take(planes, at + off, axis=1)
        acc *= np.float32(1.0) / k
        for p in range(c):
            planes[p, at] = acc[p]
        covered[at] = True
    return planes


def upsample2(d: np.ndarray) -> np.ndarray:
    """Bilinear x2 upsampling with pixel centres aligned (edges clamped), float32."""
    d = np.asarray(d, dtype=np.float32)

    def along(a: np.ndarray, axis: int) -> np.ndarray:
        a = np.moveaxis(a, axis, 0)
        prev = np.concatenate([a[:1], a[:-1]])
        nxt = np.concatenate([a[1:], a[-1:]])
        out = np.empty((2 * a.shape[0], *a.shape[1:]), np.float32)
        out[0::2] = np.float32(0.75) * a + np.float32(0.25) * prev
        out[1::2] = np.float32(0.75) * a + np.float32(0.25) * nxt
        return np.moveaxis(out, 0, axis)

    return along(along(d, 0), 1)


def upsample2_at(d: np.ndarray, src: np.ndarray, width: int) -> np.ndarray:
    """`upsample2` of ``d`` (h, w) at the flat indices ``src`` of the (2h, 2w) result only
    (the same float32 operations in the same order: equal values), float32 (len(src),).

    `CHUNK` indices at a time: the index temporaries stay small."""
    d = np.asarray(d, dtype=np.float32)
    hh, hw = d.shape
    flat = d.reshape(-1)
    a, b = np.float32(0.75), np.float32(0.25)
    out = np.empty(src.size, np.float32)
    for lo in range(0, src.size, CHUNK):
        y, x = np.divmod(src[lo:lo + CHUNK], width)
        iy, ix = y >> 1, x >> 1
        # even output rows/columns take the previous half-resolution one, odd the next
        # (clamped)
        ny = iy + ((y & 1) * 2 - 1)
        np.clip(ny, 0, hh - 1, out=ny)
        nx = ix + ((x & 1) * 2 - 1)
        np.clip(nx, 0, hw - 1, out=nx)
        r0 = iy * hw
        r1 = ny * hw
        del y, x, iy, ny
        near = a * flat[r0 + ix] + b * flat[r1 + ix]
        far = a * flat[r0 + nx] + b * flat[r1 + nx]
        del r0, r1, ix, nx
        near *= a
        far *= b
        np.add(near, far, out=out[lo:lo + CHUNK])
        del near, far
    return out


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
        self._ends = np.cumsum(self.counts)

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
        `needed_cells`). Each cell is one vector-matrix product of its components, scaled
        to float32 one cell at a time (at most ``cell ** 4`` values), never all at once."""
        y = self.table[view].astype(np.float32) * np.float32(self.step)
        coef = self.scales * y
        out = self.mean.astype(np.float32)
        todo = self.counts > 0
        if cells is not None:
            todo &= cells
        for c in np.flatnonzero(todo):
            a, b = int(self._ends[c] - self.counts[c]), int(self._ends[c])
            out[c] += coef[a:b] @ self.components[a:b].astype(np.float32)
        full = merge_cells(out, self.cell, self.padded)[:self.shape[0], :self.shape[1]]
        return full + np.float32(self.offset)

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
        No synthesis record, unknown method, or malformed depth sections.
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
                             record["z_tolerance_mm"])
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
        del top
        src = np.flatnonzero(obj).astype(np.int32)
        cells = self.depth.needed_cells(obj)
        del obj
        cloud = self.warper.cloud_at(colour, self.depth.reconstruct(view, cells), src)
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


class WarpWorker:
    """The warp of the latest requested view, made on a thread of its own.

    A served device that predicts shows the score blend of a new view at once (a
    reconstruction) and asks for the view's warp here; its display thread keeps taking input
    and host frames while the warp is made (numpy releases the GIL in its array work, and a
    warp costs several blends), and shows the warp only if its view is still the one on show
    and no host frame for it came first. At most one warp is in flight.

    Never a warp whose view will be gone before it is shown: while views are requested
    faster than a warp takes (a fast drag, a 60 Hz orbit), a requested view waits before
    its warp starts (`hold_s`: two recent request intervals, at most a warp's time); a
    newer request in that time replaces it unstarted (``skipped``), and the warp starts
    once the view rests. A view requested while a warp is in flight gives that warp up at
    its next check (`ViewSynthesizer.frame`'s ``cancel``: a neighbour already made stays
    cached). Where warps take less than the request interval every view's warp starts at
    once, as before.

    Any caller can always get the frame of a view: ``take(view, timeout_s)`` with a timeout
    asks for the view if it is neither asked nor made, starts it at once (no hold) and
    waits for it; the frame is `ViewSynthesizer.frame`'s, bit for bit.

    Parameters
    ----------
    synthesis : ViewSynthesizer
        Used by this worker's thread only (it has its own reconstructor and cache).

    Attributes
    ----------
    made, dropped, cancelled, skipped, errors : int
        Warps made; made but superseded by a newer request before anyone took them; given
        up for a newer request; requests replaced before their warp started; failed
        (counted, never raised: the blend stays on show).
    warp_s : float or None
        The recent time a warp takes (exponential average of the warps made, raised by a
        warp given up later than that); None until the first.
    """

    #: Request intervals longer than this are a view at rest, not a drag.
    REST_S = 0.25
    #: Weight of the newest sample in the averages of warp time and request interval.
    SMOOTHING = 0.3

    def __init__(self, synthesis: Any) -> None:
        self.synthesis = synthesis
        self._cond = threading.Condition()
        self._pending: tuple[float, float] | None = None
        self._pending_t = 0.0
        self._urgent = False  # someone waits for the pending view: start it at once
        self._result: tuple[tuple[float, float], np.ndarray] | None = None
        self._current: tuple[float, float] | None = None  # the view being warped
        self._closed = False
        self._last_request_t: float | None = None
        self.interval_s: float | None = None  # recent request interval (None: at rest)
        self.warp_s: float | None = None
        self.made = self.dropped = self.cancelled = self.skipped = self.errors = 0
        self._thread = threading.Thread(target=self._run, name="eigencast-warp", daemon=True)
        self._thread.start()

    @staticmethod
    def hold_for(warp_s: float | None, interval_s: float | None) -> float:
        """How long a requested view waits before its warp starts (`hold_s`): 0 when warps
        are known to take no longer than the interval between requests (or either is
        unknown: a view at rest, the first warp), else two intervals (a request that did
        not come: the drag stopped or slowed; one late request is not a stop), at most one
        warp's time."""
        if warp_s is None or interval_s is None or warp_s <= interval_s:
            return 0.0
        return min(2.0 * interval_s, warp_s)

    def hold_s(self) -> float:
        """The hold of a view requested now (`hold_for` of the current averages)."""
        return self.hold_for(self.warp_s, self.interval_s)

    def request(self, view: tuple[float, float]) -> None:
        """Warp ``view`` next (any thread); an older result not taken is forgotten."""
        now = time.monotonic()
        with self._cond:
            view = (float(view[0]), float(view[1]))
            if self._last_request_t is not None:
                gap = now - self._last_request_t
                if gap > self.REST_S:
                    self.interval_s = None
                else:
                    self.interval_s = gap if self.interval_s is None else (
                        self.interval_s + self.SMOOTHING * (gap - self.interval_s))
            self._last_request_t = now
            if self._pending is not None and self._pending != view:
                self.skipped += 1
                self._urgent = False
            self._pending, self._pending_t = view, now
            self._result = None
            self._cond.notify_all()

    def take(self, view: tuple[float, float], timeout_s: float = 0.0) -> np.ndarray | None:
        """The warp of ``view`` if it is made (waiting up to ``timeout_s``), else None.

        With a timeout, a view neither made, in flight nor asked is asked now, and its warp
        starts at once (no hold): the caller waits for it."""
        want = (float(view[0]), float(view[1]))
        with self._cond:
            if timeout_s > 0:
                made = self._result is not None and self._result[0] == want
                if not made and self._current != want and self._pending != want:
                    self._pending, self._pending_t = want, time.monotonic()
                    self._result = None
                if self._pending == want:
                    self._urgent = True
                    self._cond.notify_all()
                self._cond.wait_for(lambda: self._closed or (
                    self._result is not None and self._result[0] == want), timeout_s)
            if self._result is None or self._result[0] != want:
                return None
            frame, self._result = self._result[1], None
            return frame

    def close(self) -> None:
        """Stop the thread (a warp in flight is given up at its next check)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout=10.0)

    def _superseded(self) -> bool:
        """Another view was asked (or the worker is closing): the warp in flight is moot.
        Read without the lock: attribute reads, and a stale answer only delays the give-up
        to the next check."""
        pending = self._pending
        return self._closed or (pending is not None and pending != self._current)

    def _next_view(self) -> tuple[float, float] | None:
        """The view to warp next, once it has waited its hold (under the lock); None:
        closing."""
        while True:
            self._cond.wait_for(lambda: self._pending is not None or self._closed)
            if self._closed:
                return None
            wait = self._pending_t + self.hold_s() - time.monotonic()
            if self._urgent or wait <= 0.0:
                view, self._pending, self._urgent = self._pending, None, False
                return view
            self._cond.wait(wait)  # a newer request, a waiting caller, or the hold is over

    def _run(self) -> None:
        while True:
            with self._cond:
                view = self._next_view()
                if view is None:
                    return
                self._current = view
            t0 = time.monotonic()
            try:
                frame = self.synthesis.frame(*view, cancel=self._superseded)
            except WarpCancelled:
                with self._cond:
                    self.cancelled += 1
                    spent = time.monotonic() - t0
                    if self.warp_s is None or spent > self.warp_s:
                        self.warp_s = spent  # a warp takes at least this long
                    self._current = None
                continue
            except Exception:  # the blend stays on show; a device must not stop on it
                with self._cond:
                    self.errors += 1
                    self._current = None
                    self._cond.notify_all()
                continue
            spent = time.monotonic() - t0
            with self._cond:
                self.made += 1
                self.warp_s = spent if self.warp_s is None else (
                    self.warp_s + self.SMOOTHING * (spent - self.warp_s))
                self._current = None
                if self._pending == view or self._pending is None:
                    if self._pending == view:
                        self._pending, self._urgent = None, False
                    self._result = (view, frame)
                    self._cond.notify_all()
                else:
                    self.dropped += 1
