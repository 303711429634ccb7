"""The forward warp of cached views into a new orbit camera (issue 15, made fast in issue 22).

`Warper` holds one framing's cameras (every orbit camera of an eigencast database shares its
intrinsics; `orbit_pose` places the sphere's centre at the origin), unprojects a view's
object pixels into packed int16 points (`Warper.cloud_at`: the view cache's form) and owns
the warp's working set; `forward_warp` projects the points of the source views into the
target camera, z-tests, blends by the views' weights, filters and fills the cracks
(`fill_holes`). Numpy only, float32, no per-pixel Python loop, temporaries bounded by
`CHUNK` points and the splats' rectangle. `device_runtime.synthesis` builds the frames a
device shows on it (and re-exports these names); ``research/warp_views.py`` measures with it.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

__all__ = [
    "CHUNK",
    "HOLE_NEIGHBOURS",
    "HOLE_PASSES",
    "MAX_WARP_PIXELS",
    "SPLAT_TENT",
    "SPLAT_TENTS",
    "Z_TOLERANCE",
    "WarpCancelled",
    "Warper",
    "fill_holes",
    "forward_warp",
    "orbit_pose",
    "upsample2",
    "upsample2_at",
]

#: z-test tolerance as a fraction of the bounding-sphere diameter: samples of one pixel
#: within this of the nearest one are blended, the rest are hidden.
Z_TOLERANCE = 0.02
#: Nearest-pixel splats are spread by a [1/8, 3/4, 1/8] x [1/8, 3/4, 1/8] filter over the
#: covered pixels (the accumulators are filtered before the blend is normalised): in
#: expectation over where a point lands, the spread of a bilinear splat; an image may name a
#: weaker one (`SPLAT_TENTS`). Coverage is the unfiltered one: a pixel is covered when a
#: splat lands on it.
SPLAT_TENT = True
#: The filter's centre weights c of [1, c, 1] a warper may use (`Warper.tent`): c + 2 a power
#: of two, so the filter's scale ((c + 2) ** 2) is one the blend's normalisation cancels bit
#: for bit. 6 ([1/8, 3/4, 1/8]) unless the image names another (``synthesis.splat_tent``,
#: chosen by ``fit --depth``); the larger, the less the splats are spread.
SPLAT_TENTS = (6, 14, 30, 62)
#: The warp indexes its padded grid in float32, exact below 2**24 pixels (4094 x 4094).
MAX_WARP_PIXELS = 1 << 24
#: Pixels or points per pass of the work on a view (a cache miss' rays and depth
#: upsampling, the warp's passes): bounds the temporaries to a few hundred kilobytes
#: whatever the frame size.
CHUNK = 1 << 15
f32 = np.float32  # the warp's passes cast many scalars to float32
#: Hole filling: passes of a 3x3 normalised average over covered neighbours, for holes with
#: at least HOLE_NEIGHBOURS of their 8 neighbours covered (cracks, not the silhouette).
HOLE_PASSES = 2
HOLE_NEIGHBOURS = 4

class WarpCancelled(Exception):
    """A warp given up because its ``cancel`` callable said so (a newer view was asked)."""


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
    tent : int
        Centre weight c of the splat filter [1, c, 1] (one of `SPLAT_TENTS`).
    """

    def __init__(self, fov_deg: float, distance_mm: float, width: int, height: int,
                 z_tolerance_mm: float, tent: int = SPLAT_TENTS[0]) -> None:
        if tent not in SPLAT_TENTS:
            raise ValueError(f"splat filter centre {tent!r} is not one of {SPLAT_TENTS}")
        self.tent = int(tent)
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
        self._grid: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
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

    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The warp's working set, made once, reused by every frame: the padded grid's
        z-buffer (h + 2, w + 2) float32, returned clean (inf), the same buffer as one flat
        run with a spare last entry, and scratch for the compact grid of the splats'
        rectangle: three colour accumulators (one flat float32 run of 3 x (grid + 1)) and
        coverage (bool, grid size).

        The flat run is the z-buffer's pixels and one more: once the z-test is done it
        accumulates the blend weights of a compact grid of up to every pixel of the padded
        grid plus the spare entry hidden splats go to (a frame whose splats reach every
        border uses all of it).

        A frame dirties the z-buffer's rectangle its splats land in and the flat run's
        first entries, where it accumulates the blend weights (`dirty`, set by
        `forward_warp`); only those are cleaned here."""
        shape = (self.height + 2, self.width + 2)
        if self._grid is None:
            size = shape[0] * shape[1]
            zflat = np.full(size + 1, np.inf, np.float32)
            self._grid = (zflat[:size].reshape(shape), zflat,
                          np.empty(3 * (size + 1), np.float32), np.empty(size, bool))
            self.dirty = None
        zgrid, zflat = self._grid[0], self._grid[1]
        if self.dirty is not None:
            r0, r1, c0, c1, run = self.dirty
            zgrid[r0:r1, c0:c1] = np.inf
            zflat[:run] = np.inf
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

    def cloud_at(self, colour: np.ndarray, half_depth: np.ndarray, src: np.ndarray, *,
                 black: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A cached view: the pixels ``src`` (flat indices) of ``colour`` unprojected, packed.

        `unproject_at(colour, upsample2_at(half_depth, src, width), src, packed=True)` in
        one pass of float32 arithmetic, `CHUNK` pixels at a time: each pixel's depth from
        the half-resolution map ``half_depth`` (h / 2, w / 2) by `upsample2`'s bilinear
        weights, its ray from float32 tangents, the point in int16 `point_step`s from the
        orbit centre (what `forward_warp` takes). Non-finite depths are dropped. The pixels
        ``black`` flags (bool, one per ``src``) keep their points with colour 0.

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
            # np.take with mode="clip" (the indices are in range): a third faster than
            # indexing, and "raise" would buffer its output
            near = qa * np.take(flat, iy + ix, mode="clip")
            near += qb * np.take(flat, ny + ix, mode="clip")
            far = qa * np.take(flat, iy + nx, mode="clip")
            far += qb * np.take(flat, ny + nx, mode="clip")
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
            gx, gy = np.take(gx32, x, mode="clip"), np.take(gy32, y, mode="clip")
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
            black = None if black is None else black[keep]
        rgb = np.empty((3, src.size), colour.dtype)
        cflat = np.ascontiguousarray(colour).reshape(-1)
        at = src * 3
        for c in range(3):
            np.take(cflat, at + c if c else at, out=rgb[c], mode="clip")
        if black is not None:
            rgb *= ~black  # a multiply: 0.6x the time of a masked assignment
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
    the warper's [1, c, 1] / (c + 2) kernel (`Warper.tent`; c = 6: the spread a bilinear
    splat has on average) before the blend is normalised. A pixel no splat lands on is a
    hole (a pixel one view alone sees is covered, however small that view's weight);
    `fill_holes` closes the cracks among covered pixels. Splats land on a grid one pixel
    larger on every side (points beyond it are clamped onto that border, which is then
    emptied), so nothing needs masking.

    Memory and time: three passes over the sources, `CHUNK` points at a time (the z-buffer
    and the rectangle the splats land in; the z-test, which moves each splat to its pixel
    of a compact grid of that rectangle, 3 pixels larger on every side (what the filter and
    hole filling reach), a hidden one to its spare last pixel; the blend on that grid), so a
    frame's temporaries are a chunk's; what persists is the warper's z-buffer and scratch
    (`Warper.grid`) and each splat's target pixel (4 bytes, `Warper.splats`). Accumulation
    is float32 in place (``np.add.at``), never a float64 copy of the grid. The filter,
    normalisation, hole filling and rounding then run on the compact grid, each plane one
    contiguous run (a rectangle inside the padded grid is strided: 4x slower per pixel).

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
    used = [(pts, rgb, src, float(wv)) for (pts, rgb), src, wv in zip(clouds, sources, weights)
            if wv > 0.0 and pts.shape[1] > 0]
    frame = np.zeros((h, wd, 3), dtype=np.uint8)
    if not used:
        return frame
    idx = w.splats(sum(u[0].shape[1] for u in used))
    zgrid, zbuf, acc, cover = w.grid()  # the z-buffer clean (inf), flat; scratch
    w.dirty = (0, h + 2, 0, wd + 2, zbuf.size)  # until pass 2 ends (a cancelled warp: all)
    pieces = _pieces(w, used, target)
    landed = _land(w, pieces, idx, zbuf, cancel)  # pass 1
    rect = _rectangle(w, landed)
    _hide(w, pieces, idx, zbuf, rect, cancel)  # pass 2
    r0, r1, c0, c1 = rect
    rh, rw = r1 - r0, c1 - c0
    n = rh * rw
    cov = cover[:n]
    np.isfinite(zgrid[r0:r1, c0:c1], out=cov.reshape(rh, rw))
    w.dirty = (r0, r1, c0, c1, n + 1)  # the z-buffer's run holds the weights now
    flat_w, flat_acc = _blend(pieces, idx, zbuf, acc, n, cancel)  # pass 3
    wb, pb = flat_w[:n], flat_acc[:, :n]
    _empty_grid_border((cov, wb, *pb), rect, h + 2, wd + 2)
    _give_up_if(cancel)
    if SPLAT_TENT:
        _tent(pb, rw, w.tent)
        _tent(wb[None], rw, w.tent)
    np.divide(f32(1.0), wb, out=wb, where=cov)
    np.multiply(wb, cov, out=wb)  # 1 / weight where covered, else 0
    pb *= wb
    _fill_holes_padded(flat_acc, cov, rw)
    # rounded by truncation: every value is a mean of colours in 0..255 with positive
    # weights (to float32's precision), so none leaves 0..255.5 and the cast needs no clip
    pb += f32(0.5)
    _copy_into_frame(frame, pb, rect)
    return frame


#: A chunk of one source's points: (slice of the warper's splat indices, the points and
#: colours there, the view's projection m (3, 3) and b (3,) into padded pixel coordinates,
#: its interpolation weight).
_Piece = tuple[slice, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.float32]


def _pieces(w: Warper, used: list, target: tuple[np.ndarray, np.ndarray]) -> list[_Piece]:
    """Cut every used source into chunks of `CHUNK` points (small temporaries), each with
    its view's projection into the target camera's padded pixel coordinates."""
    h, wd = w.height, w.width
    p_t, r_t = target
    # target camera -> padded pixel coordinates: col + 1 = x / z * sx + ox, row + 1 = ...,
    # as one projective 3 x 3 (x' / z, y' / z are the padded column and row)
    sx = 0.5 * h / w.half
    scale = np.array([[sx, 0.0, 0.5 * wd + 1.0], [0.0, -sx, 0.5 * h + 1.0], [0.0, 0.0, 1.0]])
    pieces = []
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
    return pieces


def _land(w: Warper, pieces: list[_Piece], idx: np.ndarray, zbuf: np.ndarray,
          cancel: Callable[[], bool] | None) -> tuple[float, float, float, float]:
    """Pass 1: the padded pixel each splat lands in (into ``idx``), the z-buffer (nearest
    forward distance per pixel, into ``zbuf``); returns the rectangle the splats landed in,
    (x0, x1, y0, y1) in padded pixel coordinates."""
    h, w2 = w.height, w.width + 2
    x0, x1, y0, y1 = w2, 0.0, h + 2.0, 0.0
    for s, pts, _, m, b, _ in pieces:
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
        at = cx.astype(np.intp)  # ufunc.at converts other indices to intp on every call
        idx[s] = at
        np.minimum.at(zbuf, at, z)
        del xyz, cx, cy, z, at
    return x0, x1, y0, y1


def _rectangle(w: Warper, landed: tuple[float, float, float, float]
               ) -> tuple[int, int, int, int]:
    """The rows and columns ``(r0, r1, c0, c1)`` of the padded grid the rest of the warp
    works on: the rectangle the splats landed in, 3 pixels to spare on every side (what the
    filter and hole filling reach), as a compact grid of its own: each plane one contiguous
    run (rows of a rectangle inside the grid are strided: 4x slower per pixel)."""
    x0, x1, y0, y1 = landed
    r0, r1 = max(0, int(y0) - 3), min(w.height + 2, int(y1) + 4)
    c0, c1 = max(0, int(x0) - 3), min(w.width + 2, int(x1) + 4)
    return r0, r1, c0, c1


def _hide(w: Warper, pieces: list[_Piece], idx: np.ndarray, zbuf: np.ndarray,
          rect: tuple[int, int, int, int], cancel: Callable[[], bool] | None) -> None:
    """Pass 2: a splat beyond the z tolerance of its pixel's nearest is hidden; it moves to
    the compact grid's spare last pixel (n) so the blend needs no per-splat weight; the
    others to their pixel in the compact grid (``idx`` rewritten in place)."""
    r0, r1, c0, c1 = rect
    w2, rw = w.width + 2, c1 - c0
    n = (r1 - r0) * rw
    shift, base = w2 - rw, r0 * rw + c0
    tol = f32(w.tol_mm)
    for s, pts, _, m, b, _ in pieces:
        _give_up_if(cancel)
        at = idx[s]
        zmax = np.take(zbuf, at, mode="clip")
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


def _blend(pieces: list[_Piece], idx: np.ndarray, zbuf: np.ndarray, acc: np.ndarray, n: int,
           cancel: Callable[[], bool] | None) -> tuple[np.ndarray, np.ndarray]:
    """Pass 3: the blend weights (n + 1,) and weighted colours (3, n + 1) accumulated on the
    compact grid, float32 in place; the z-buffer is done with and holds the weights."""
    flat_w = zbuf[:n + 1]
    flat_w[...] = 0.0
    flat_acc = acc[:3 * (n + 1)].reshape(3, n + 1)
    flat_acc[...] = 0.0
    for s, _, col, _, _, wv in pieces:
        _give_up_if(cancel)
        at = idx[s].astype(np.intp)  # converted once, not by each of the four calls
        np.add.at(flat_w, at, wv)
        for c in range(3):
            np.add.at(flat_acc[c], at, np.multiply(col[c], wv, dtype=f32))
    return flat_w, flat_acc


def _empty_grid_border(planes: tuple[np.ndarray, ...], rect: tuple[int, int, int, int],
                       grid_h: int, grid_w: int) -> None:
    """Empty the padded grid's border (clamped strays) in each compact plane, where the
    rectangle meets it."""
    r0, r1, c0, c1 = rect
    for a_ in planes:
        a2 = a_.reshape(r1 - r0, c1 - c0)
        if r0 == 0:
            a2[0] = 0
        if r1 == grid_h:
            a2[-1] = 0
        if c0 == 0:
            a2[:, 0] = 0
        if c1 == grid_w:
            a2[:, -1] = 0


def _copy_into_frame(frame: np.ndarray, pb: np.ndarray, rect: tuple[int, int, int, int]
                     ) -> None:
    """Cast the compact grid's colours (3, n) into the frame's pixels inside the rectangle
    (padded pixel (y, x) is the frame's (y - 1, x - 1))."""
    h, wd = frame.shape[:2]
    r0, r1, c0, c1 = rect
    rh, rw = r1 - r0, c1 - c0
    fr0, fr1, fc0, fc1 = max(r0, 1), min(r1, h + 1), max(c0, 1), min(c1, wd + 1)
    out = frame[fr0 - 1:fr1 - 1, fc0 - 1:fc1 - 1]
    for c in range(3):
        out[..., c] = pb[c].reshape(rh, rw)[fr0 - r0:fr1 - r0, fc0 - c0:fc1 - c0]


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


def _tent(a: np.ndarray, width: int, centre: int = SPLAT_TENTS[0]) -> np.ndarray:
    """Separable [1, c, 1] filter (c = ``centre``) of rows ``width`` long, times (c + 2) ** 2
    (zero outside), float32, in place: ``a`` (planes, n) holds each plane's rows end to end
    (contiguous), with a zero first and last column (the grid's border), so a shift by one
    pixel along the run never carries a value from one row into the next. One plane of
    scratch.

    For c in `SPLAT_TENTS` the scale is a power of two (64 for the [1/8, 3/4, 1/8] filter),
    which the blend's normalisation cancels bit for bit: weights and weighted colours are
    both filtered."""
    c = np.float32(centre)
    t = np.empty(a.shape[1:], a.dtype)
    for k in range(a.shape[0]):
        p = a[k]
        np.multiply(p, c, out=t)
        t[width:] += p[:-width]
        t[:-width] += p[width:]
        np.multiply(t, c, out=p)
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
        acc = np.take(planes, at + offsets[0], axis=1, mode="clip")
        for off in offsets[1:]:
            acc += np.take(planes, at + off, axis=1, mode="clip")
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
