"""A slow, obviously-correct numpy ray-caster: the yardstick for `host.render.raycast`.

It implements the model documented in `host.render.raycast` independently: it shares
only the camera (`Camera.rays`) and the transfer function's LUT
(`TransferFunction.lut`) with the numba kernel. Differences by design:

* trilinear sampling is `scipy.ndimage.map_coordinates` (order 1) on a float64
  copy of the normalised volume;
* opacity correction is applied after interpolating the LUT (the kernel
  corrects the LUT entries), which agrees to ~1e-6 with 4096 entries;
* no empty-space skipping; all rays advance together, one sample at a time.

Vectorised over rays, looping over samples; fine for 32 x 32 images, and used
by `benchmarks/bench_render.py` as the baseline rate.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

from host.render.camera import Camera
from host.render.transfer import TransferFunction
from host.volume import Volume

__all__ = ["ray_box_segments", "render_reference", "samples_in_box"]

_AMBIENT, _DIFFUSE, _SPECULAR, _SHININESS = 0.25, 0.75, 0.3, 24.0
_GRADIENT_EPSILON = 1e-3
_EARLY_ALPHA = 1.0 - 1.0 / 255.0


def ray_box_segments(
    volume: Volume, origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where rays enter and leave the box spanned by the voxel centres.

    Parameters
    ----------
    volume : Volume
    origins, directions : ndarray of shape (n_rays, 3), float64
        World mm; unit directions.

    Returns
    -------
    t_in, t_out : ndarray of shape (n_rays,), float64
        Distances in mm, ``t_in >= 0``; ``t_out <= t_in`` where the ray misses.
    """
    box_hi = np.asarray(volume.extent_mm, dtype=np.float64)
    t_in = np.zeros(len(origins))
    t_out = np.full(len(origins), np.inf)
    for axis in range(3):
        o, d = origins[:, axis], directions[:, axis]
        parallel = d == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (0.0 - o) / d
            tb = (box_hi[axis] - o) / d
        near = np.where(parallel, -np.inf, np.minimum(ta, tb))
        far = np.where(parallel, np.inf, np.maximum(ta, tb))
        outside = parallel & ((o < 0.0) | (o > box_hi[axis]))
        far = np.where(outside, -np.inf, far)
        t_in = np.maximum(t_in, near)
        t_out = np.minimum(t_out, far)
    return t_in, t_out


def _sample(u: np.ndarray, pos_idx: np.ndarray) -> np.ndarray:
    """Trilinear samples of u (nz, ny, nx) at index-space points (m, 3) ordered x, y, z."""
    return map_coordinates(u, pos_idx[:, ::-1].T, order=1, mode="nearest")


def render_reference(
    volume: Volume,
    tf: TransferFunction,
    camera: Camera,
    width: int,
    height: int,
    *,
    step_mm: float,
    window: tuple[float, float] | None = None,
    shading: bool = True,
    opacity_correction: bool = True,
    early_termination: bool = True,
    lut_size: int = 4096,
) -> np.ndarray:
    """Render one image with the documented model, slowly.

    Parameters
    ----------
    volume, tf, camera : the scene.
    width, height : int
    step_mm : float
        Distance between samples along a ray.
    window : (lo, hi), optional
        Intensity window; default ``tf.resolve_window(volume)``, as the renderer uses.
    shading, opacity_correction, early_termination : bool
    lut_size : int

    Returns
    -------
    ndarray of shape (height, width, 4), float32
        Premultiplied RGB and alpha, before the background.
    """
    if window is None:
        window = tf.resolve_window(volume)
    lo, hi = float(window[0]), float(window[1])
    u = (volume.data.astype(np.float64) - lo) / (hi - lo)
    nz, ny, nx = u.shape
    spacing = np.asarray(volume.spacing, dtype=np.float64)
    unit = float(spacing.min())
    lut = np.clip(tf.lut(lut_size).astype(np.float64), 0.0, 1.0)
    lut_x = np.arange(lut_size, dtype=np.float64)

    origins, directions = camera.rays(width, height)
    origins = origins.reshape(-1, 3)
    directions = directions.reshape(-1, 3)
    t_in, t_out = ray_box_segments(volume, origins, directions)
    hit = t_out > t_in
    count = np.zeros(len(origins), dtype=np.int64)
    count[hit] = np.ceil((t_out[hit] - t_in[hit]) / step_mm - 0.5).astype(np.int64)

    color = np.zeros((len(origins), 3))
    alpha = np.zeros(len(origins))
    box_hi = np.array([nx - 1.0, ny - 1.0, nz - 1.0])
    for k in range(int(count.max(initial=0))):
        active = k < count
        if early_termination:
            active &= alpha <= _EARLY_ALPHA
        rays = np.flatnonzero(active)
        if rays.size == 0:
            break
        t = t_in[rays] + (k + 0.5) * step_mm
        pos_mm = origins[rays] + t[:, None] * directions[rays]
        pos = np.clip(pos_mm / spacing, 0.0, box_hi)  # index space, (x, y, z)
        tval = np.clip(_sample(u, pos), 0.0, 1.0) * (lut_size - 1)
        a = np.interp(tval, lut_x, lut[:, 3])
        if opacity_correction:
            a = 1.0 - (1.0 - a) ** (step_mm / unit)
        c = np.stack([np.interp(tval, lut_x, lut[:, ch]) for ch in range(3)], axis=1)
        if shading:
            grad = np.zeros((rays.size, 3))
            for axis in range(3):
                plus, minus = pos.copy(), pos.copy()
                plus[:, axis] = np.minimum(pos[:, axis] + 1.0, box_hi[axis])
                minus[:, axis] = np.maximum(pos[:, axis] - 1.0, 0.0)
                grad[:, axis] = (_sample(u, plus) - _sample(u, minus)) / (
                    (plus[:, axis] - minus[:, axis]) * spacing[axis]
                )
            norm = np.linalg.norm(grad, axis=1)
            lit_here = (norm >= _GRADIENT_EPSILON / unit) & (a > 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                ndl = np.abs(np.sum(grad * directions[rays], axis=1)) / norm
            shaded = np.minimum(
                1.0,
                c * (_AMBIENT + _DIFFUSE * ndl)[:, None] + (_SPECULAR * ndl**_SHININESS)[:, None],
            )
            c = np.where(lit_here[:, None], shaded, c)
        weight = (1.0 - alpha[rays]) * a
        color[rays] += weight[:, None] * c
        alpha[rays] += weight
    out = np.concatenate([color, alpha[:, None]], axis=1).reshape(height, width, 4)
    return out.astype(np.float32)


def samples_in_box(volume: Volume, camera: Camera, width: int, height: int, step_mm: float) -> int:
    """Number of sample positions inside the box over all rays (the work of a naive caster)."""
    origins, directions = camera.rays(width, height)
    t_in, t_out = ray_box_segments(volume, origins.reshape(-1, 3), directions.reshape(-1, 3))
    hit = t_out > t_in
    return int(np.sum(np.ceil((t_out[hit] - t_in[hit]) / step_mm - 0.5)))
