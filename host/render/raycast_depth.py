"""The ray-caster's depth kernel: `host.render.raycast.Renderer.render_with_depth`.

`_cast_ray_depth` is `host.render.raycast._cast_ray` statement for statement plus the depth
bookkeeping (where the accumulated opacity crosses 0.5; the opacity-weighted mean distance;
with `render_depth_layers`, also where it crosses 1/4 and 3/4), kept apart so the
colour-only kernel carries none of it and stays as fast as it was. A test
(``tests/test_raycast_depth.py``) checks that the RGBA of both is bit-identical, so the two
cannot drift apart unnoticed. Imported only when depth is asked for.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from host.render.lighting import ray_phase, shade_world
from host.render.raycast import BLOCK_SIZE, _axis_exit, _check_size, _trilinear

__all__ = ["DEPTH_QUARTER", "DEPTH_THREE_QUARTERS", "render_depth_layers"]

#: Channels `render_depth_layers` adds to `Renderer.render_with_depth`'s two
#: (``DEPTH_HALF``, ``DEPTH_MEAN``): where the accumulated opacity crosses 1/4 and 3/4.
DEPTH_QUARTER = 2
DEPTH_THREE_QUARTERS = 3


def render_depth_layers(renderer: object, camera: object, width: int, height: int
                        ) -> tuple[np.ndarray, np.ndarray]:
    """`Renderer.render_with_depth` with two more depths per pixel: where the accumulated
    opacity crosses 1/4 (`DEPTH_QUARTER`) and 3/4 (`DEPTH_THREE_QUARTERS`), linear within
    the crossing sample like the half-opacity depth, NaN where it never does. A
    translucent pixel's colour comes from the depths between them (a second depth layer
    for view synthesis: docs/design-notes.md).

    Returns
    -------
    rgba : ndarray (height, width, 4) float32
        Bit-identical to ``renderer.render``'s.
    depth : ndarray (height, width, 4) float32
        ``DEPTH_HALF``, ``DEPTH_MEAN`` (`Renderer.render_with_depth`'s), ``DEPTH_QUARTER``,
        ``DEPTH_THREE_QUARTERS``.
    """
    width, height = _check_size(width, height)
    out = np.zeros((height, width, 4), dtype=np.float32)
    depth = np.full((height, width, 4), np.nan, dtype=np.float32)
    renderer._run_kernel(_render_depth_kernel, camera, width, height, out, depth)
    return out, depth


@njit(cache=True, nogil=True)
def _cast_ray_depth(
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
    depth: np.ndarray,
    row: int,
    col: int,
) -> None:
    """`host.render.raycast._cast_ray` that also stores the ray's two depths in ``depth``.

    The colour arithmetic is `_cast_ray`'s, statement for statement (a test checks the
    RGBA is bit-identical); it is a separate function so the colour-only kernel carries
    no depth bookkeeping. ``depth[row, col, 0]``: the distance (mm from the ray origin)
    at which the accumulated opacity crosses 0.5, linear within the crossing sample's
    step; ``depth[row, col, 1]``: the opacity-weighted mean distance ``sum(w t) /
    sum(w)`` with ``w`` each sample's contribution to the colour. NaN where the opacity
    never reaches 0.5 (0) or no sample contributes (1). With four channels (``depth``
    (h, w, 4), `render_depth_layers`) also where the opacity crosses 1/4 (2) and 3/4 (3).
    """
    layers = depth.shape[2] >= 4
    depth[row, col, 0] = np.nan
    depth[row, col, 1] = np.nan
    if layers:
        depth[row, col, 2] = np.nan
        depth[row, col, 3] = np.nan
    nz, ny, nx = u.shape
    isx, isy, isz = inv_spacing[0], inv_spacing[1], inv_spacing[2]
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
    t_half = np.nan
    t_q1 = np.nan
    t_q3 = np.nan
    wt_sum = 0.0
    k = 0
    k_block_end = 0
    while k < n_samples:
        t = t0 + (k + 0.5) * step_mm
        x = min(max(ox + t * dx, 0.0), nx - 1.0)
        y = min(max(oy + t * dy, 0.0), ny - 1.0)
        z = min(max(oz + t * dz, 0.0), nz - 1.0)
        if use_skip and k >= k_block_end:
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
                k = k_block_end
                continue
        value = _trilinear(u, x, y, z)
        tpos = value * (n_lut - 1)
        if not tpos > 0.0:
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
            before = ca
            ca += w
            wt_sum += w * t
            if before < 0.5 and ca >= 0.5:
                # the sample's opacity is spread over its step [t - step/2, t + step/2]
                t_half = t - 0.5 * step_mm + (0.5 - before) / w * step_mm
            if layers:
                if before < 0.25 and ca >= 0.25:
                    t_q1 = t - 0.5 * step_mm + (0.25 - before) / w * step_mm
                if before < 0.75 and ca >= 0.75:
                    t_q3 = t - 0.5 * step_mm + (0.75 - before) / w * step_mm
            if ca > early_alpha:
                break
        k += 1
    out[row, col, 0] = cr
    out[row, col, 1] = cg
    out[row, col, 2] = cb
    out[row, col, 3] = ca
    depth[row, col, 0] = t_half
    if ca > 0.0:
        depth[row, col, 1] = wt_sum / ca
    if layers:
        depth[row, col, 2] = t_q1
        depth[row, col, 3] = t_q3


@njit(parallel=True, cache=True, nogil=True)
def _render_depth_kernel(
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
    depth: np.ndarray,
) -> None:
    """`_render_kernel` with `_cast_ray_depth`: RGBA in ``out``, depths in ``depth``."""
    height, width = out.shape[0], out.shape[1]
    for s in prange(n_strips):
        for row in range(s, height, n_strips):
            for col in range(width):
                _cast_ray_depth(
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
                    depth,
                    row,
                    col,
                )
