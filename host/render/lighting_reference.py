"""A slow, obviously correct Monte Carlo path tracer: the yardstick for world-fixed lighting.

`render_lighting_reference` estimates, per pixel, the single-scattering radiance of the
model in `host.render.lighting` without any of the fast renderer's discretisations:

* **The view ray** is sampled by delta (Woodcock) tracking against the majorant
  ``sigma_max = max(extinction_lut)``: free flights ``-ln(xi) / sigma_max``, a tentative
  collision at ``x`` is real with probability ``sigma(x) / sigma_max``. A real collision
  happens at ``t`` with density ``T_view(t) sigma(t)``, so averaging the source there
  (zero when the path leaves the box) estimates ``integral T_view sigma L dt``, the
  continuous form of the renderer's front-to-back compositing, and the fraction of paths
  that collide estimates the pixel's opacity ``1 - T_view``.
* **The light's transmittance** at a collision is estimated by ratio tracking from
  ``x + bias * l`` to the box along ``l``: the product of ``1 - sigma(x_i) / sigma_max``
  over tentative collisions ``x_i`` (unbiased, in [0, 1]). No light field, no grid, no
  midpoint rule.
* **The source** at a collision is `host.render.lighting.shade_world`'s formula, computed
  here in numpy from the same definitions (albedo and extinction from the transfer
  function's LUT at the trilinear field, gradient by central differences one voxel either
  side); the ambient channel, the model's own approximation (not a transport term), is
  taken from a given light field or left out.

Only the transfer function's LUT, the camera's rays and the trilinear sampling helpers of
`host.render.raycast_reference` are shared with the fast path. Vectorised over paths,
looping over collision events: fine for volumes of a few tens of voxels a side and images
of 16-32 pixels.
"""

from __future__ import annotations

import numpy as np

from host.render.camera import Camera
from host.render.lighting import LIGHT_AMBIENT, Lighting, extinction_lut
from host.render.raycast_reference import _sample, ray_box_segments
from host.render.transfer import TransferFunction
from host.volume import Volume

__all__ = ["render_lighting_reference", "transmittance_reference"]

_GRADIENT_EPSILON = 1e-3


class _Scene:
    """The volume as the model defines it, sampled anywhere in world mm."""

    def __init__(self, volume: Volume, tf: TransferFunction, window: tuple[float, float],
                 lut_size: int) -> None:
        lo, hi = float(window[0]), float(window[1])
        self.u = (volume.data.astype(np.float64) - lo) / (hi - lo)
        self.spacing = np.asarray(volume.spacing, dtype=np.float64)
        self.unit = float(self.spacing.min())
        nz, ny, nx = self.u.shape
        self.box_hi = np.array([nx - 1.0, ny - 1.0, nz - 1.0])
        self.lut = np.clip(tf.lut(lut_size).astype(np.float64), 0.0, 1.0)
        self.sigma_lut = extinction_lut(self.lut, self.unit)
        self.sigma_max = float(self.sigma_lut.max())
        self.lut_x = np.arange(lut_size, dtype=np.float64)
        self.volume = volume

    def index(self, pos_mm: np.ndarray) -> np.ndarray:
        return np.clip(pos_mm / self.spacing, 0.0, self.box_hi)

    def tval(self, pos_mm: np.ndarray) -> np.ndarray:
        n = self.lut.shape[0]
        return np.clip(_sample(self.u, self.index(pos_mm)), 0.0, 1.0) * (n - 1)

    def sigma(self, pos_mm: np.ndarray) -> np.ndarray:
        return np.interp(self.tval(pos_mm), self.lut_x, self.sigma_lut)

    def albedo(self, pos_mm: np.ndarray) -> np.ndarray:
        t = self.tval(pos_mm)
        return np.stack([np.interp(t, self.lut_x, self.lut[:, ch]) for ch in range(3)], axis=1)

    def gradient(self, pos_mm: np.ndarray) -> np.ndarray:
        pos = self.index(pos_mm)
        grad = np.zeros((len(pos), 3))
        for axis in range(3):
            plus, minus = pos.copy(), pos.copy()
            plus[:, axis] = np.minimum(pos[:, axis] + 1.0, self.box_hi[axis])
            minus[:, axis] = np.maximum(pos[:, axis] - 1.0, 0.0)
            grad[:, axis] = (_sample(self.u, plus) - _sample(self.u, minus)) / (
                (plus[:, axis] - minus[:, axis]) * self.spacing[axis])
        return grad

    def transmittance(self, origins: np.ndarray, direction: np.ndarray,
                      rng: np.random.Generator) -> np.ndarray:
        """Ratio-tracking estimate of the transmittance from each origin along ``direction``."""
        dirs = np.broadcast_to(direction, origins.shape)
        t_in, t_out = ray_box_segments(self.volume, origins, np.ascontiguousarray(dirs))
        weight = np.ones(len(origins))
        t = np.maximum(t_in, 0.0)
        active = np.flatnonzero(t_out > t)
        while active.size:
            t[active] += -np.log1p(-rng.random(active.size)) / self.sigma_max
            inside = t[active] < t_out[active]
            active = active[inside]
            if not active.size:
                break
            pos = origins[active] + t[active, None] * direction
            weight[active] *= 1.0 - self.sigma(pos) / self.sigma_max
            active = active[weight[active] > 0.0]
        return weight


def _shade(scene: _Scene, lighting: Lighting, pos: np.ndarray, w: np.ndarray,
           trans: np.ndarray, ambient: np.ndarray) -> np.ndarray:
    """`host.render.lighting.shade_world`'s source at ``pos`` for ray directions ``w``."""
    light = lighting.direction()
    c = scene.albedo(pos)
    grad = scene.gradient(pos)
    gmag = np.linalg.norm(grad, axis=1)
    is_surface = gmag >= _GRADIENT_EPSILON / scene.unit
    m = gmag * scene.unit
    surface = np.where(is_surface, m / (m + lighting.surface_gradient), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = grad / gmag[:, None]
    n = np.where((np.sum(n * w, axis=1) > 0.0)[:, None], -n, n)
    ndl = np.sum(n * light, axis=1)
    diffuse = np.where(is_surface & (ndl > 0.0), ndl, 0.0)
    h = light - w
    hn = np.linalg.norm(h, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ndh = np.sum(n * h, axis=1) / hn
    lit_face = is_surface & (ndl > 0.0) & (hn > 0.0) & (ndh > 0.0)
    spec = np.where(lit_face, lighting.specular * np.where(lit_face, ndh, 0.0)
                    ** lighting.shininess, 0.0)
    g = lighting.phase_g
    mu = w @ light
    phase = (1.0 - g * g) / (1.0 + g * g - 2.0 * g * mu) ** 1.5
    lit = trans * lighting.key_strength * (surface * diffuse + (1.0 - surface) * phase) + ambient
    return np.minimum(1.0, c * lit[:, None] + (trans * surface * spec)[:, None])


def render_lighting_reference(
    volume: Volume,
    tf: TransferFunction,
    camera: Camera,
    width: int,
    height: int,
    *,
    lighting: Lighting,
    paths_per_pixel: int,
    seed: int = 0,
    window: tuple[float, float] | None = None,
    field: np.ndarray | None = None,
    lut_size: int = 4096,
) -> tuple[np.ndarray, np.ndarray]:
    """Monte Carlo estimate of one image under a world-fixed light, with its standard error.

    Parameters
    ----------
    volume, tf, camera : the scene.
    width, height : int
    lighting : Lighting
        A world-lit look (`host.render.lighting.LIGHTINGS`).
    paths_per_pixel : int
        Independent paths per pixel, each one view path and one shadow path.
    seed : int
        Seed of the random generator (the estimate is reproducible).
    window : (lo, hi), optional
        Intensity window; default ``tf.resolve_window(volume)``.
    field : ndarray of shape (nz, ny, nx, 2), optional
        A light field whose ambient channel is added to the source (trilinear at the
        collision); None leaves the ambient term out.
    lut_size : int

    Returns
    -------
    mean : ndarray of shape (height, width, 4), float64
        Premultiplied RGB and opacity before the background, as `Renderer.render` returns.
    stderr : ndarray of shape (height, width, 4), float64
        The standard error of each mean (sample standard deviation / sqrt(paths)).
    """
    if not lighting.world_lit:
        raise ValueError(f"render_lighting_reference: lighting {lighting.name!r} is not "
                         "lit from the world")
    if window is None:
        window = tf.resolve_window(volume)
    scene = _Scene(volume, tf, window, lut_size)
    rng = np.random.default_rng(seed)
    origins, directions = camera.rays(width, height)
    origins = np.repeat(origins.reshape(-1, 3), paths_per_pixel, axis=0)
    directions = np.repeat(directions.reshape(-1, 3), paths_per_pixel, axis=0)
    n_paths = len(origins)
    t_in, t_out = ray_box_segments(volume, origins, directions)
    t = np.maximum(t_in, 0.0)
    hit_t = np.full(n_paths, np.nan)
    active = np.flatnonzero(t_out > t)
    while active.size:
        t[active] += -np.log1p(-rng.random(active.size)) / scene.sigma_max
        active = active[t[active] < t_out[active]]
        if not active.size:
            break
        pos = origins[active] + t[active, None] * directions[active]
        real = rng.random(active.size) * scene.sigma_max < scene.sigma(pos)
        hit_t[active[real]] = t[active[real]]
        active = active[~real]
    hit = np.flatnonzero(np.isfinite(hit_t))
    value = np.zeros((n_paths, 4))
    if hit.size:
        pos = origins[hit] + hit_t[hit, None] * directions[hit]
        light = lighting.direction()
        start = pos + (lighting.shadow_bias * scene.unit) * light
        inside = np.all((start >= 0.0) & (start <= np.asarray(volume.extent_mm)), axis=1)
        trans = np.ones(hit.size)
        trans[inside] = scene.transmittance(start[inside], light, rng)
        ambient = np.zeros(hit.size)
        if field is not None:
            ambient = _sample(np.ascontiguousarray(field[..., LIGHT_AMBIENT], dtype=np.float64),
                              scene.index(pos))
        value[hit, :3] = _shade(scene, lighting, pos, directions[hit], trans, ambient)
        value[hit, 3] = 1.0
    per_pixel = value.reshape(height * width, paths_per_pixel, 4)
    mean = per_pixel.mean(axis=1)
    stderr = per_pixel.std(axis=1, ddof=1) / np.sqrt(paths_per_pixel)
    return mean.reshape(height, width, 4), stderr.reshape(height, width, 4)


def transmittance_reference(
    volume: Volume,
    tf: TransferFunction,
    points_mm: np.ndarray,
    *,
    lighting: Lighting,
    paths: int,
    seed: int = 0,
    window: tuple[float, float] | None = None,
    lut_size: int = 4096,
) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-tracking estimate of the key light's transmittance at points, with its error.

    The same quantity as `host.render.raycast.Renderer.light_transmittance`: from ``p +
    bias l`` to the box along ``l`` (1 where that start lies outside the box).

    Parameters
    ----------
    volume, tf : the scene.
    points_mm : array-like of shape (n, 3)
        World mm.
    lighting : Lighting
    paths : int
        Shadow paths per point.
    seed : int
    window : (lo, hi), optional
    lut_size : int

    Returns
    -------
    mean, stderr : ndarray of shape (n,), float64
    """
    if window is None:
        window = tf.resolve_window(volume)
    scene = _Scene(volume, tf, window, lut_size)
    rng = np.random.default_rng(seed)
    light = lighting.direction()
    points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    start = np.repeat(points + (lighting.shadow_bias * scene.unit) * light, paths, axis=0)
    inside = np.all((start >= 0.0) & (start <= np.asarray(volume.extent_mm)), axis=1)
    values = np.ones(len(start))
    values[inside] = scene.transmittance(start[inside], light, rng)
    values = values.reshape(len(points), paths)
    return values.mean(axis=1), values.std(axis=1, ddof=1) / np.sqrt(paths)
