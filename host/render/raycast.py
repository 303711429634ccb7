"""The ray-caster: emission-absorption volume rendering on all cores (numba).

Model (the numpy reference in `host.render.raycast_reference` implements the same one)
-----------------------------------------------------------------------------
* **Scalar field.** ``u = (v - lo) / (hi - lo)`` with the transfer function's
  window ``(lo, hi) = tf.resolve_window(volume)``, sampled trilinearly in
  world space: voxel ``data[k, j, i]`` sits at
  ``(i*sx, j*sy, k*sz)`` mm. The field exists only inside the box spanned by
  the voxel centres; rays sample nothing outside it. Because the normalisation
  is affine, interpolating ``u`` equals interpolating the raw values.
  NaN voxels read as ``lo`` (``u = 0``); +-inf and absurd values are clamped
  to ``u = +-1e6``.
* **Classification.** ``t = clip(u, 0, 1)`` indexes a float32 LUT of
  ``LUT_SIZE`` entries, ``tf.lut(LUT_SIZE)``, interpolated linearly between
  entries; colours are straight (not premultiplied) and sRGB-coded, and are
  composited as they are (no linearisation, like ParaView/VTK).
* **Opacity correction.** The LUT's alpha is the opacity of one *unit* of
  path, ``unit = min(volume.spacing)``; a step of ``step_mm`` uses
  ``alpha' = 1 - (1 - alpha)**(step_mm / unit)``, applied to the LUT entries
  (the numpy reference applies it after interpolation; with 4096 entries the
  two agree to ~1e-6).
* **Sampling.** A ray enters the box at ``t_in`` and leaves at ``t_out``
  (distances in mm along the unit world direction). Its samples sit at
  ``t_k = t_in + (k + 0.5) * step_mm`` for every ``k >= 0`` with
  ``t_k < t_out`` -- the midpoint rule, so a homogeneous path of length ``L``
  gets ``round(L / step_mm)`` samples. The step is ``2 * radius_mm / samples``
  (``samples`` across the bounding-sphere diameter; default 1000, the paper's
  rate) or ``step * unit`` (``step`` in units of the smallest spacing).
* **Shading** (``shading=True``). At samples with alpha > 0: the gradient
  ``g`` of ``u`` by central differences of the trilinear field one voxel
  either side along each axis (one-sided at the box faces), in 1/mm; where
  ``|g| * unit >= GRADIENT_EPSILON`` the colour becomes Blinn-Phong with a
  white headlight (light and eye at the camera, so the half vector is the light
  vector), two-sided: ``c' = min(1, c * (AMBIENT + DIFFUSE * n.l) +
  SPECULAR * (n.l)**SHININESS)`` with ``n.l = |g . d| / |g|``; elsewhere ``c``
  is unshaded. That is the ``headlight`` lighting (the default); a light fixed in the
  world (``lighting="cinematic"``, `host.render.lighting`) shades the same samples from
  the same gradient with its shadows, ambient occlusion and scattering instead.
* **Compositing.** Front to back: ``C += (1 - A) * a * c``,
  ``A += (1 - A) * a``; the ray stops once ``A > 1 - 1/255``
  (`EARLY_TERMINATION_ALPHA`).
* **Empty-space skipping.** The box is cut into blocks of 8 x 8 x 8 cells;
  a block whose ``[min(u), max(u)]`` (over the 9^3 voxels its cells touch)
  meets only zero-opacity LUT entries is empty, and a ray that samples in an
  empty block jumps to its first sample past the block's exit. Every skipped
  sample would have had alpha = 0 exactly, so skipping does not change the
  image.

`Renderer.render` returns premultiplied RGBA before the background;
`Renderer.render_pixels` / `Renderer.render_strided` cast only a subset of the same
pixel grid (same rays, same kernel), equal bit for bit to those pixels of `render`;
`Renderer.render_with_depth` also returns two representative depths per pixel (a separate
kernel, so the colour-only path is unchanged); `Renderer.render_rgb8` composites over the
background:
``rgb8 = round(255 * clip(C + (1 - A) * background, 0, 1))``.
Every pixel is computed independently in a fixed order, in float64, without
fastmath, so the output is identical run to run and for any thread count.
"""

from __future__ import annotations

import copy
import math
import threading
from collections.abc import Callable

import numba
import numpy as np
from numba import njit, prange

from host.errors import TransferFunctionError
from host.render.camera import Camera
from host.render.lighting import (
    Lighting,
    extinction_lut,
    light_field,
    ray_phase,
    resolve_lighting,
    shade_world,
    transmittance_at,
    trilinear_in_box,
)
from host.render.transfer import TransferFunction
from host.volume import Volume

__all__ = [
    "AMBIENT",
    "BLOCK_SIZE",
    "DEFAULT_SAMPLES",
    "DEPTH_HALF",
    "DEPTH_MEAN",
    "DIFFUSE",
    "EARLY_TERMINATION_ALPHA",
    "LUT_SIZE",
    "MAX_IMAGE_SIDE",
    "MAX_SAMPLES",
    "RENDERER_VERSION",
    "SHININESS",
    "SPECULAR",
    "Renderer",
    "resolve_window",
    "strided_pixels",
    "warmup",
]

RENDERER_VERSION = "eigencast-raycast/1"
#: Channels of `Renderer.render_with_depth`'s depth: where the opacity crosses 0.5, and
#: the opacity-weighted mean depth.
DEPTH_HALF = 0
DEPTH_MEAN = 1
DEFAULT_SAMPLES = 1000
MAX_SAMPLES = 100_000  # samples across the bounding-sphere diameter
MAX_IMAGE_SIDE = 8192
LUT_SIZE = 4096
BLOCK_SIZE = 8
EARLY_TERMINATION_ALPHA = 1.0 - 1.0 / 255.0
AMBIENT = 0.25
DIFFUSE = 0.75
SPECULAR = 0.3
SHININESS = 24.0
GRADIENT_EPSILON = 1e-3  # |grad u| per smallest voxel spacing below which no shading
_PIXEL_CHUNK = 32  # consecutive listed pixels one thread casts at a time (render_pixels)

# The workqueue threading layer must not be entered from two threads at once.
_KERNEL_LOCK = threading.Lock()


def resolve_window(volume: Volume, tf: TransferFunction) -> tuple[float, float]:
    """The intensity window ``(lo, hi)`` a renderer uses: ``tf.resolve_window(volume)``.

    Raises
    ------
    TransferFunctionError
        A window that is not finite or has ``hi <= lo``.
    """
    lo, hi = (float(v) for v in tf.resolve_window(volume))
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise TransferFunctionError(
            f"transfer function {tf.name!r}: window ({lo}, {hi}) on volume {volume.name!r} "
            "must be finite with lo < hi"
        )
    return lo, hi


# --------------------------------------------------------------------------- numba kernels
@njit(cache=True, nogil=True)
def _trilinear(u: np.ndarray, x: float, y: float, z: float) -> float:
    """Trilinear value of ``u`` (nz, ny, nx) at index-space ``(x, y, z)``, clamped to the box."""
    nz, ny, nx = u.shape
    x = min(max(x, 0.0), nx - 1.0)
    y = min(max(y, 0.0), ny - 1.0)
    z = min(max(z, 0.0), nz - 1.0)
    return trilinear_in_box(u, x, y, z)


@njit(cache=True, nogil=True)
def _axis_exit(o: float, d: float, lo: float, hi: float) -> float:
    """Distance along ``o + t d`` at which the ray leaves ``[lo, hi]`` (inf when d == 0)."""
    if d > 0.0:
        return (hi - o) / d
    if d < 0.0:
        return (lo - o) / d
    return np.inf


@njit(cache=True, nogil=True)
def _cast_ray(
    u: np.ndarray,
    block_empty: np.ndarray,
    ox: float,
    oy: float,
    oz: float,
    wx: float,
    wy: float,
    wz: float,
    inv_spacing: np.ndarray,
    step_mm: float,
    lut: np.ndarray,
    use_skip: bool,
    shading: bool,
    params: np.ndarray,
    field: np.ndarray,
    light: np.ndarray,
    out: np.ndarray,
    row: int,
    col: int,
) -> None:
    """Cast the ray through pixel ``(row, col)`` and store its premultiplied RGBA in ``out``.

    ``light[0] == 0``: the headlight; otherwise a world-fixed light with the light field
    ``field`` (`host.render.lighting.shade_world`).
    """
    nz, ny, nx = u.shape
    isx, isy, isz = inv_spacing[0], inv_spacing[1], inv_spacing[2]
    # ray in index space; t stays in world mm along the unit direction (wx, wy, wz)
    ox *= isx
    oy *= isy
    oz *= isz
    dx = wx * isx
    dy = wy * isy
    dz = wz * isz
    t0 = 0.0
    t1 = np.inf
    for axis in range(3):
        if axis == 0:
            o, d, hi = ox, dx, nx - 1.0
        elif axis == 1:
            o, d, hi = oy, dy, ny - 1.0
        else:
            o, d, hi = oz, dz, nz - 1.0
        if d == 0.0:
            if o < 0.0 or o > hi:
                return
        else:
            ta = (0.0 - o) / d
            tb = (hi - o) / d
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if not t1 > t0:
        return
    n_samples = math.ceil((t1 - t0) / step_mm - 0.5)
    n_lut = lut.shape[0]
    ambient, diffuse, specular, shininess = params[0], params[1], params[2], params[3]
    early_alpha, grad_eps = params[4], params[5]
    world_lit = light[0] != 0.0
    phase = ray_phase(light, wx, wy, wz) if world_lit else 0.0
    cr = 0.0
    cg = 0.0
    cb = 0.0
    ca = 0.0
    k = 0
    k_block_end = 0
    while k < n_samples:
        t = t0 + (k + 0.5) * step_mm
        x = min(max(ox + t * dx, 0.0), nx - 1.0)
        y = min(max(oy + t * dy, 0.0), ny - 1.0)
        z = min(max(oz + t * dz, 0.0), nz - 1.0)
        if use_skip and k >= k_block_end:
            # entering a block: find the first sample past its exit
            bi = min(int(x), nx - 2) // BLOCK_SIZE
            bj = min(int(y), ny - 2) // BLOCK_SIZE
            bk = min(int(z), nz - 2) // BLOCK_SIZE
            t_exit = min(
                _axis_exit(ox, dx, bi * 1.0 * BLOCK_SIZE, min((bi + 1.0) * BLOCK_SIZE, nx - 1.0)),
                _axis_exit(oy, dy, bj * 1.0 * BLOCK_SIZE, min((bj + 1.0) * BLOCK_SIZE, ny - 1.0)),
                _axis_exit(oz, dz, bk * 1.0 * BLOCK_SIZE, min((bk + 1.0) * BLOCK_SIZE, nz - 1.0)),
            )
            k_block_end = max(k + 1, math.floor((t_exit - t0) / step_mm - 0.5) + 1)
            if block_empty[bk, bj, bi]:
                k = k_block_end  # every sample up to the exit has alpha = 0
                continue
            # samples before k_block_end lie in this non-empty block: evaluate them all
        value = _trilinear(u, x, y, z)
        tpos = value * (n_lut - 1)
        if not tpos > 0.0:  # also catches NaN
            tpos = 0.0
        elif tpos > n_lut - 1:
            tpos = n_lut - 1.0
        li = min(int(tpos), n_lut - 2)
        f = tpos - li
        a = lut[li, 3] + f * (lut[li + 1, 3] - lut[li, 3])
        if a > 0.0:
            r = lut[li, 0] + f * (lut[li + 1, 0] - lut[li, 0])
            g = lut[li, 1] + f * (lut[li + 1, 1] - lut[li, 1])
            b = lut[li, 2] + f * (lut[li + 1, 2] - lut[li, 2])
            if shading:
                xp = min(x + 1.0, nx - 1.0)
                xm = max(x - 1.0, 0.0)
                yp = min(y + 1.0, ny - 1.0)
                ym = max(y - 1.0, 0.0)
                zp = min(z + 1.0, nz - 1.0)
                zm = max(z - 1.0, 0.0)
                gx = (_trilinear(u, xp, y, z) - _trilinear(u, xm, y, z)) / (xp - xm) * isx
                gy = (_trilinear(u, x, yp, z) - _trilinear(u, x, ym, z)) / (yp - ym) * isy
                gz = (_trilinear(u, x, y, zp) - _trilinear(u, x, y, zm)) / (zp - zm) * isz
                gmag = math.sqrt(gx * gx + gy * gy + gz * gz)
                if world_lit:
                    r, g, b = shade_world(u, field, light, phase, x, y, z, gx, gy, gz, gmag,
                                          wx, wy, wz, r, g, b)
                elif gmag >= grad_eps:
                    ndl = abs(gx * wx + gy * wy + gz * wz) / gmag
                    lit = ambient + diffuse * ndl
                    spec = specular * ndl**shininess
                    r = min(1.0, r * lit + spec)
                    g = min(1.0, g * lit + spec)
                    b = min(1.0, b * lit + spec)
            w = (1.0 - ca) * a
            cr += w * r
            cg += w * g
            cb += w * b
            ca += w
            if ca > early_alpha:
                break
        k += 1
    out[row, col, 0] = cr
    out[row, col, 1] = cg
    out[row, col, 2] = cb
    out[row, col, 3] = ca


@njit(parallel=True, cache=True, nogil=True)
def _render_kernel(
    u: np.ndarray,
    block_empty: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    inv_spacing: np.ndarray,
    step_mm: float,
    lut: np.ndarray,
    use_skip: bool,
    shading: bool,
    params: np.ndarray,
    field: np.ndarray,
    light: np.ndarray,
    n_strips: int,
    out: np.ndarray,
) -> None:
    """Render every pixel of ``out`` (height, width, 4) in parallel over row strips."""
    height, width = out.shape[0], out.shape[1]
    # strips of interleaved rows balance the load (the volume sits mid-image)
    for s in prange(n_strips):
        for row in range(s, height, n_strips):
            for col in range(width):
                _cast_ray(
                    u,
                    block_empty,
                    origins[row, col, 0],
                    origins[row, col, 1],
                    origins[row, col, 2],
                    directions[row, col, 0],
                    directions[row, col, 1],
                    directions[row, col, 2],
                    inv_spacing,
                    step_mm,
                    lut,
                    use_skip,
                    shading,
                    params,
                    field,
                    light,
                    out,
                    row,
                    col,
                )


@njit(parallel=True, cache=True, nogil=True)
def _render_pixels_kernel(
    u: np.ndarray,
    block_empty: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    inv_spacing: np.ndarray,
    step_mm: float,
    lut: np.ndarray,
    use_skip: bool,
    shading: bool,
    params: np.ndarray,
    field: np.ndarray,
    light: np.ndarray,
    n_strips: int,
    out: np.ndarray,
) -> None:
    """Render the rays ``origins[i], directions[i]`` (n, 3) into ``out[i, 0]`` (n, 1, 4).

    The same `_cast_ray` as `_render_kernel`, in parallel over strips of interleaved
    chunks of the list, so each pixel equals the full render's bit for bit.
    """
    n = out.shape[0]
    n_chunks = (n + _PIXEL_CHUNK - 1) // _PIXEL_CHUNK
    # chunks of consecutive pixels keep neighbouring rays on one thread (cache locality);
    # interleaved chunks per strip balance the load
    for s in prange(n_strips):
        for chunk in range(s, n_chunks, n_strips):
            for i in range(chunk * _PIXEL_CHUNK, min(n, (chunk + 1) * _PIXEL_CHUNK)):
                _cast_ray(
                    u,
                    block_empty,
                    origins[i, 0],
                    origins[i, 1],
                    origins[i, 2],
                    directions[i, 0],
                    directions[i, 1],
                    directions[i, 2],
                    inv_spacing,
                    step_mm,
                    lut,
                    use_skip,
                    shading,
                    params,
                    field,
                    light,
                    out,
                    i,
                    0,
                )


@njit(parallel=True, cache=True, nogil=True)
def _block_minmax(u: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Per block of ``block``^3 cells: min and max of the voxels its cells touch."""
    nz, ny, nx = u.shape
    nbz = (nz - 2) // block + 1
    nby = (ny - 2) // block + 1
    nbx = (nx - 2) // block + 1
    lo = np.empty((nbz, nby, nbx), dtype=np.float32)
    hi = np.empty((nbz, nby, nbx), dtype=np.float32)
    for bk in prange(nbz):
        for bj in range(nby):
            for bi in range(nbx):
                vmin = np.inf
                vmax = -np.inf
                for k in range(bk * block, min(bk * block + block, nz - 1) + 1):
                    for j in range(bj * block, min(bj * block + block, ny - 1) + 1):
                        for i in range(bi * block, min(bi * block + block, nx - 1) + 1):
                            v = u[k, j, i]
                            vmin = min(vmin, v)
                            vmax = max(vmax, v)
                lo[bk, bj, bi] = vmin
                hi[bk, bj, bi] = vmax
    return lo, hi


# --------------------------------------------------------------------------- renderer
def _check_size(width: int, height: int) -> tuple[int, int]:
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ValueError(f"{name}={v!r} must be an integer")
        if not 1 <= v <= MAX_IMAGE_SIDE:
            raise ValueError(f"{name}={v} must be within [1, {MAX_IMAGE_SIDE}]")
    return int(width), int(height)


def strided_pixels(
    width: int, height: int, stride: int, offset: tuple[int, int] = (0, 0)
) -> tuple[np.ndarray, np.ndarray]:
    """The pixels ``(rows, cols)`` of a strided pattern: every ``stride``-th row and column
    starting at ``offset = (dy, dx)``, row-major.

    Returns
    -------
    rows, cols : ndarray of shape (n,), int64
        With ``ny = len(range(dy, height, stride))`` and ``nx`` alike, ``n = ny * nx``;
        reshaped to ``(ny, nx)`` they are ``image[dy::stride, dx::stride]``'s pixels.

    Raises
    ------
    ValueError
        ``stride`` not a positive integer, or an offset outside ``[0, stride)``.
    """
    width, height = _check_size(width, height)
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride={stride!r} must be a positive integer")
    dy, dx = (int(v) for v in offset)
    if not (0 <= dy < stride and 0 <= dx < stride):
        raise ValueError(f"offset={tuple(offset)} must lie within [0, {stride}) on both axes")
    ys = np.arange(dy, height, stride, dtype=np.int64)
    xs = np.arange(dx, width, stride, dtype=np.int64)
    rows, cols = np.meshgrid(ys, xs, indexing="ij")
    return rows.ravel(), cols.ravel()


def _ray_step(samples: int | None, step: float | None, diameter_mm: float, unit_mm: float
              ) -> tuple[int | None, float]:
    """(samples, step in mm): ``step`` voxels (``unit_mm`` each; samples None), else
    ``samples`` (default `DEFAULT_SAMPLES`) across the bounding sphere's diameter; at most
    `MAX_SAMPLES` samples either way."""
    if step is not None:
        step = float(step)
        if not (math.isfinite(step) and step > 0.0):
            raise ValueError(f"step={step} must be a positive number of voxels")
        step_mm = step * unit_mm
        if diameter_mm / step_mm > MAX_SAMPLES:
            raise ValueError(
                f"step={step} gives {diameter_mm / step_mm:.0f} samples across the "
                f"volume; at most {MAX_SAMPLES} are allowed"
            )
        return None, step_mm
    samples = DEFAULT_SAMPLES if samples is None else samples
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)):
        raise ValueError(f"samples={samples!r} must be an integer")
    if not 2 <= samples <= MAX_SAMPLES:
        raise ValueError(f"samples={samples} must be within [2, {MAX_SAMPLES}]")
    return int(samples), diameter_mm / int(samples)


def _checked_lut(tf: TransferFunction) -> np.ndarray:
    """The transfer function's float64 (LUT_SIZE, 4) RGBA table, clipped to [0, 1]."""
    lut = np.array(tf.lut(LUT_SIZE), dtype=np.float64)
    if lut.shape != (LUT_SIZE, 4) or not np.all(np.isfinite(lut)):
        raise TransferFunctionError(
            f"transfer function {tf.name!r}: LUT is not finite float (n, 4) RGBA"
        )
    return np.clip(lut, 0.0, 1.0)


class Renderer:
    """Ray-cast one volume with one transfer function from any camera.

    The constructor prepares everything that does not depend on the camera
    (normalised volume, opacity-corrected LUT, empty-space block grid), so make
    one Renderer and call `render` per view.

    Parameters
    ----------
    volume : Volume
    tf : TransferFunction
    samples : int, optional
        Samples across the bounding-sphere diameter: ``step_mm = 2 * radius_mm /
        samples``; within [2, MAX_SAMPLES]. Default `DEFAULT_SAMPLES` (1000,
        the paper's rate) when neither ``samples`` nor ``step`` is given.
    step : float, optional
        Step in units of the smallest voxel spacing; exclusive with ``samples``.
    shading : bool
        Gradient shading: the lighting's (see the module docstring); False draws the
        transfer function's colours as they are (headlight only).
    lighting : str or Lighting
        A name in `host.render.lighting.LIGHTINGS` (``headlight``, the default, or
        ``cinematic``) or a `Lighting`. A world-fixed light computes its light field here
        (once per volume, transfer function and light; cached, see
        `host.render.lighting.light_field`).
    background : (r, g, b)
        Background in [0, 1] (sRGB-coded) used by `render_rgb8`.
    workers : int, optional
        Threads, within [1, numba.config.NUMBA_NUM_THREADS]; default all.
    opacity_correction, empty_space_skipping, early_termination : bool
        Switches for tests and measurements; all on by default and recorded in
        `settings`. Turning off skipping does not change the image.

    Attributes
    ----------
    step_mm : float
        The step actually used.
    window : (lo, hi)
        The intensity window actually used.
    unit_mm : float
        The opacity unit, ``min(volume.spacing)``.
    """

    def __init__(
        self,
        volume: Volume,
        tf: TransferFunction,
        *,
        samples: int | None = None,
        step: float | None = None,
        shading: bool = True,
        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
        workers: int | None = None,
        opacity_correction: bool = True,
        empty_space_skipping: bool = True,
        early_termination: bool = True,
        lighting: str | Lighting | None = None,
    ) -> None:
        self.lighting = resolve_lighting(lighting)
        if self.lighting.world_lit and not shading:
            raise ValueError(f"lighting={self.lighting.name!r} shades by the gradient; it "
                             "cannot be combined with shading=False")
        if samples is not None and step is not None:
            raise ValueError(f"give samples={samples} or step={step}, not both")
        self.volume = volume
        self.tf = tf
        self.unit_mm = float(min(volume.spacing))
        self.samples, self.step_mm = _ray_step(samples, step, 2.0 * volume.radius_mm,
                                               self.unit_mm)
        background = tuple(float(c) for c in background)
        if len(background) != 3 or not all(0.0 <= c <= 1.0 for c in background):
            raise ValueError(f"background={background} must be 3 values within [0, 1]")
        self.background = background
        max_workers = int(numba.config.NUMBA_NUM_THREADS)
        if workers is not None and (
            isinstance(workers, bool)
            or not isinstance(workers, (int, np.integer))
            or not 1 <= workers <= max_workers
        ):
            raise ValueError(f"workers={workers!r} must be an integer within [1, {max_workers}]")
        self.workers = None if workers is None else int(workers)
        self.shading = bool(shading)
        self.opacity_correction = bool(opacity_correction)
        self.empty_space_skipping = bool(empty_space_skipping)
        self.early_termination = bool(early_termination)

        self.window = resolve_window(volume, tf)
        lo, hi = self.window
        u = (volume.data - np.float32(lo)) * np.float32(1.0 / (hi - lo))
        if not np.all(np.isfinite(u)):
            u = np.nan_to_num(u, nan=0.0, posinf=1e6, neginf=-1e6)
        np.clip(u, -1e6, 1e6, out=u)
        self._u = np.ascontiguousarray(u, dtype=np.float32)

        lut = _checked_lut(tf)
        lut_unit = lut.copy()  # opacity per unit, what the light field's extinction uses
        if self.opacity_correction:
            ratio = self.step_mm / self.unit_mm
            lut[:, 3] = 1.0 - np.power(1.0 - lut[:, 3], ratio)
        self._lut = np.ascontiguousarray(lut, dtype=np.float32)
        self._block_empty = self._empty_blocks()
        self._params = np.array(
            [
                AMBIENT,
                DIFFUSE,
                SPECULAR,
                SHININESS,
                EARLY_TERMINATION_ALPHA if self.early_termination else 2.0,
                GRADIENT_EPSILON / self.unit_mm,
            ],
            dtype=np.float64,
        )
        self._inv_spacing = 1.0 / np.array(volume.spacing, dtype=np.float64)
        self._light = self.lighting.kernel_params(
            volume.spacing, GRADIENT_EPSILON / self.unit_mm,
            extinction_lut(lut_unit, self.unit_mm))
        if self.lighting.world_lit:
            self._field = light_field(self._u, np.clip(lut_unit, 0.0, 1.0), self._block_empty,
                                      BLOCK_SIZE, volume.spacing, self.lighting)
        else:
            self._field = np.zeros((2, 2, 2, 2), dtype=np.float32)  # never read
            self._field.flags.writeable = False  # (one kernel signature for both looks)

    def _empty_blocks(self) -> np.ndarray:
        """uint8 (nbz, nby, nbx): 1 where every value the block can take has zero opacity."""
        lo, hi = _block_minmax(self._u, BLOCK_SIZE)
        n = LUT_SIZE
        # LUT entries a sample in the block can touch: a trilinear value lies within
        # the corners' [min, max] (up to one rounding, whose effect is ~1e-13)
        i_lo = np.floor(np.clip(lo, 0.0, 1.0).astype(np.float64) * (n - 1)).astype(np.int64)
        i_hi = np.ceil(np.clip(hi, 0.0, 1.0).astype(np.float64) * (n - 1)).astype(np.int64)
        opaque = np.concatenate([[0], np.cumsum(self._lut[:, 3] > 0.0)])
        empty = (opaque[i_hi + 1] - opaque[i_lo]) == 0
        return np.ascontiguousarray(empty, dtype=np.uint8)

    def visible_sphere(
        self, *, min_alpha: float = 0.02, trim: float = 1e-4
    ) -> tuple[np.ndarray, float]:
        """Bounding sphere of what the transfer function makes visible.

        Orbit cameras framed on this sphere fill the image with the object
        instead of the (often mostly transparent) volume box.

        Parameters
        ----------
        min_alpha : float
            A voxel counts as visible when its LUT opacity (per unit length)
            reaches this.
        trim : float
            Fraction of the farthest visible voxels ignored, so a few isolated
            noise voxels cannot inflate the sphere.

        Returns
        -------
        center_mm : ndarray of shape (3,), float64
            Centre of the visible voxels' bounding box, world millimetres.
        radius_mm : float
            Distance from the centre enclosing all but `trim` of them (plus
            one voxel). Falls back to the volume's sphere when nothing is visible.
        """
        n = LUT_SIZE
        index = np.rint(np.clip(self._u, 0.0, 1.0) * (n - 1)).astype(np.int32)
        visible = np.asarray(self.tf.lut(n))[:, 3][index] >= min_alpha
        k, j, i = np.nonzero(visible)
        if k.size == 0:
            return self.volume.center_mm, self.volume.radius_mm
        spacing = np.asarray(self.volume.spacing, dtype=np.float64)
        pts = np.stack([i, j, k], axis=1).astype(np.float64) * spacing
        lo = np.quantile(pts, trim, axis=0)
        hi = np.quantile(pts, 1.0 - trim, axis=0)
        center = (lo + hi) / 2.0
        dist = np.linalg.norm(pts - center, axis=1)
        radius = float(np.quantile(dist, 1.0 - trim)) + float(spacing.max())
        return center, min(radius, self.volume.radius_mm * 2.0)

    def light_transmittance(self, points_mm: np.ndarray) -> np.ndarray:
        """The key light's transmittance ``T`` at world points, as the shading uses it.

        Parameters
        ----------
        points_mm : array-like of shape (n, 3)
            World mm, inside the volume box.

        Returns
        -------
        ndarray of shape (n,), float64
            In [0, 1] (`host.render.lighting`, "The light's transmittance").

        Raises
        ------
        ValueError
            The headlight (no light in the world), or a point outside the box.
        """
        if not self.lighting.world_lit:
            raise ValueError(f"light_transmittance: lighting {self.lighting.name!r} has no "
                             "light fixed in the world")
        points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3) * self._inv_spacing
        return transmittance_at(self._u, self._field, self._light, points)

    @property
    def empty_block_fraction(self) -> float:
        """Share of the 8^3-cell blocks that are skipped as empty."""
        return float(self._block_empty.mean())

    def render(self, camera: Camera, width: int, height: int) -> np.ndarray:
        """Ray-cast one image.

        Parameters
        ----------
        camera : Camera
        width, height : int
            Image size in pixels, each within [1, MAX_IMAGE_SIDE].

        Returns
        -------
        ndarray of shape (height, width, 4), float32
            Premultiplied RGB and alpha, before the background; row 0 is the top.
        """
        width, height = _check_size(width, height)
        out = np.zeros((height, width, 4), dtype=np.float32)
        self._run_kernel(_render_kernel, camera, width, height, out)
        return out

    def _run_kernel(self, kernel: Callable[..., None], camera: Camera, width: int, height: int,
                    *outputs: np.ndarray) -> None:
        """Run a whole-image kernel (colour, or colour and depth) on the renderer's threads."""
        origins, directions = camera.rays(width, height)
        with _KERNEL_LOCK:
            previous = numba.get_num_threads()
            threads = self.workers or int(numba.config.NUMBA_NUM_THREADS)
            numba.set_num_threads(threads)
            try:
                kernel(self._u, self._block_empty, origins, directions, self._inv_spacing,
                       self.step_mm, self._lut, self.empty_space_skipping, self.shading,
                       self._params, self._field, self._light, 4 * threads, *outputs)
            finally:
                numba.set_num_threads(previous)

    def render_with_depth(
        self, camera: Camera, width: int, height: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Ray-cast one image and, per pixel, two representative depths.

        A separate kernel (`host.render.raycast_depth`), so `render` pays nothing for it;
        the RGBA is bit-identical to `render`'s. Depths are distances in mm along each
        pixel's unit ray from its origin (``camera.rays``), so the point a depth ``t`` stands
        for is ``origin + t * direction``.

        Parameters
        ----------
        camera : Camera
        width, height : int
            Image size in pixels, each within [1, MAX_IMAGE_SIDE].

        Returns
        -------
        rgba : ndarray of shape (height, width, 4), float32
            As `render` returns it.
        depth : ndarray of shape (height, width, 2), float32
            ``depth[..., DEPTH_HALF]``: where the accumulated opacity crosses 0.5 (linear
            within the crossing sample's step), NaN where it never does;
            ``depth[..., DEPTH_MEAN]``: the opacity-weighted mean ``sum(w_i t_i) /
            sum(w_i)``, ``w_i`` the sample's contribution to the colour, NaN where no
            sample contributes. NaN marks "no object here".
        """
        from host.render.raycast_depth import _render_depth_kernel

        width, height = _check_size(width, height)
        out = np.zeros((height, width, 4), dtype=np.float32)
        depth = np.full((height, width, 2), np.nan, dtype=np.float32)
        self._run_kernel(_render_depth_kernel, camera, width, height, out, depth)
        return out, depth

    def render_pixels(
        self, camera: Camera, width: int, height: int, rows: object, cols: object
    ) -> np.ndarray:
        """Ray-cast only the pixels ``(rows[i], cols[i])`` of a ``width`` x ``height`` image.

        Each pixel equals the same pixel of ``render(camera, width, height)`` bit for bit
        (same rays, same `_cast_ray`), on all the renderer's threads; the cost is
        proportional to the number of pixels. Pixels may repeat and come in any order.

        Parameters
        ----------
        camera : Camera
        width, height : int
            The full image size, each within [1, MAX_IMAGE_SIDE].
        rows, cols : array-like of shape (n,), int
            Pixel indices within ``[0, height)`` and ``[0, width)``; n may be 0.

        Returns
        -------
        ndarray of shape (n, 4), float32
            Premultiplied RGBA before the background (`composite` takes it as it is).

        Raises
        ------
        ValueError
            A size out of range, or indices that are not matching 1-D integer arrays
            inside the image.
        """
        width, height = _check_size(width, height)
        rows = np.asarray(rows)
        cols = np.asarray(cols)
        if rows.ndim != 1 or cols.shape != rows.shape:
            raise ValueError(
                f"render_pixels: rows {rows.shape} and cols {cols.shape} must be 1-D of one length"
            )
        if rows.size and not (
            np.issubdtype(rows.dtype, np.integer) and np.issubdtype(cols.dtype, np.integer)
        ):
            raise ValueError("render_pixels: rows and cols must be integer arrays")
        out = np.zeros((rows.size, 1, 4), dtype=np.float32)
        if rows.size == 0:
            return out[:, 0]
        if rows.min() < 0 or rows.max() >= height or cols.min() < 0 or cols.max() >= width:
            raise ValueError(
                f"render_pixels: pixel indices must lie within {height} rows x {width} columns"
            )
        origins, directions = camera.rays_at(width, height, rows, cols)
        with _KERNEL_LOCK:
            previous = numba.get_num_threads()
            threads = self.workers or int(numba.config.NUMBA_NUM_THREADS)
            numba.set_num_threads(threads)
            try:
                _render_pixels_kernel(
                    self._u,
                    self._block_empty,
                    np.ascontiguousarray(origins),
                    np.ascontiguousarray(directions),
                    self._inv_spacing,
                    self.step_mm,
                    self._lut,
                    self.empty_space_skipping,
                    self.shading,
                    self._params,
                    self._field,
                    self._light,
                    max(1, min(4 * threads, -(-rows.size // _PIXEL_CHUNK))),
                    out,
                )
            finally:
                numba.set_num_threads(previous)
        return out[:, 0]

    def render_strided(
        self,
        camera: Camera,
        width: int,
        height: int,
        stride: int,
        offset: tuple[int, int] = (0, 0),
    ) -> np.ndarray:
        """Ray-cast ``render(camera, width, height)[dy::stride, dx::stride]`` only.

        Bit-identical to that slice of the full render, at about ``1 / stride**2`` of its
        cost (see `render_pixels`, `strided_pixels`).

        Returns
        -------
        ndarray of shape (ny, nx, 4), float32
            Premultiplied RGBA, ``ny = len(range(dy, height, stride))``, ``nx`` alike.
        """
        rows, cols = strided_pixels(width, height, stride, offset)
        ny = len(range(int(offset[0]), int(height), int(stride)))
        nx = len(range(int(offset[1]), int(width), int(stride)))
        return self.render_pixels(camera, width, height, rows, cols).reshape(ny, nx, 4)

    def coarser(self, factor: float) -> Renderer:
        """A renderer of the same volume and settings whose rays take ``factor`` times
        longer steps (about ``1 / factor`` of the samples), for interactive frames.

        The opacity LUT is corrected for the longer step (``alpha' = 1 - (1 - alpha) **
        factor``), so the images look the same up to sampling error; they are *not*
        bit-identical to this renderer's (the training database keeps the exact one). The
        volume and the empty-block map are shared, not copied.

        Raises
        ------
        ValueError
            ``factor`` is not a finite number >= 1.
        """
        factor = float(factor)
        if not (math.isfinite(factor) and factor >= 1.0):
            raise ValueError(f"coarser: factor={factor} must be a finite number >= 1")
        out = copy.copy(self)
        out.step_mm = self.step_mm * factor
        out.samples = None if self.samples is None else max(1, round(self.samples / factor))
        lut = self._lut.astype(np.float64)
        lut[:, 3] = 1.0 - np.power(1.0 - lut[:, 3], factor)
        out._lut = np.ascontiguousarray(lut, dtype=np.float32)
        return out

    def composite(self, rgba: np.ndarray) -> np.ndarray:
        """Premultiplied float RGBA (h, w, 4) over the background: uint8 (h, w, 3)."""
        rgb = rgba[..., :3].astype(np.float64) + (
            1.0 - rgba[..., 3:4].astype(np.float64)
        ) * np.asarray(self.background, dtype=np.float64)
        return np.floor(np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)

    def render_rgb8(self, camera: Camera, width: int, height: int) -> np.ndarray:
        """Ray-cast one image composited over the background.

        Returns
        -------
        ndarray of shape (height, width, 3), uint8
            sRGB-coded colours, row 0 at the top.
        """
        return self.composite(self.render(camera, width, height))

    def settings(self) -> dict:
        """JSON-able record of everything that determines the images."""
        return {
            "renderer": RENDERER_VERSION,
            "samples": self.samples,
            "step_mm": self.step_mm,
            "step_voxels": self.step_mm / self.unit_mm,
            "opacity_unit_mm": self.unit_mm,
            "sample_placement": "t_in + (k + 0.5) * step_mm",
            "shading": self.shading,
            "shading_model": {
                "model": "blinn-phong headlight, two-sided",
                "ambient": AMBIENT,
                "diffuse": DIFFUSE,
                "specular": SPECULAR,
                "shininess": SHININESS,
                "gradient": "central differences of the trilinear field, 1 voxel",
                "gradient_epsilon": GRADIENT_EPSILON,
            },
            "lighting": self.lighting.record(),
            "background": list(self.background),
            "tf_window": list(self.window),
            "lut_size": LUT_SIZE,
            "opacity_correction": self.opacity_correction,
            "early_termination_alpha": (
                EARLY_TERMINATION_ALPHA if self.early_termination else None
            ),
            "empty_space_skipping": {
                "enabled": self.empty_space_skipping,
                "block_cells": BLOCK_SIZE,
            },
            "compositing": "front-to-back emission-absorption, sRGB-coded values",
        }


def warmup() -> None:
    """Compile (or load from the on-disk cache) every kernel with a tiny render."""
    from host.render.camera import View, orbit_camera

    z, y, x = np.mgrid[0:10, 0:10, 0:10].astype(np.float32)
    data = np.exp(-((x - 4.5) ** 2 + (y - 4.5) ** 2 + (z - 4.5) ** 2) / 8.0)
    volume = Volume(data=data.astype(np.float32))
    tf = TransferFunction(
        name="warmup",
        color_points=np.array([[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]]),
        opacity_points=np.array([[0.0, 0.0], [1.0, 0.5]]),
        window=(0.0, 1.0),
    )
    renderer = Renderer(volume, tf, samples=16)
    camera = orbit_camera(View(0.0, 0.0), volume.center_mm, volume.radius_mm)
    renderer.render(camera, 4, 4)
    renderer.render_strided(camera, 4, 4, 2)
