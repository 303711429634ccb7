"""Lighting looks of the ray-caster: the headlight, and a light fixed in the world.

`Renderer(..., lighting=NAME)` (``render --lighting NAME``) picks one of `LIGHTINGS`:

* ``headlight`` (the default): Blinn-Phong with the light at the camera, as documented in
  `host.render.raycast`. Its shading moves with the camera.
* ``cinematic``: a key light fixed in the world (a lamp above the table), with volumetric
  shadows, a phase function for the tissue between surfaces, and ambient occlusion plus a
  multiple-scattering glow estimated from the extinction around each sample. Its shading
  stays on the object as the view turns, which is what a device's depth warp carries from
  one training view to the next.

The world-lit model (docs/lighting.md has the equations and the bound against the Monte
Carlo reference, `host.render.lighting_reference`)
-----------------------------------------------------------------------------------
* **Extinction.** ``sigma(u) = -ln(1 - min(alpha(u), ALPHA_MAX)) / unit`` per mm, with
  ``alpha(u)`` the transfer function's opacity per unit of path (``unit`` the smallest
  voxel spacing), tabulated on the same `LUT_SIZE` entries as the renderer's LUT and
  interpolated linearly between them; ``u`` is the trilinear normalised scalar field.
* **The light's transmittance** at a sample ``x`` is ``T(x) = exp(-tau(x + bias l))``,
  ``tau(y)`` the optical depth from ``y`` to the box along the unit direction ``l``
  towards the light. The bias (one unit) keeps an opaque surface from shadowing itself
  through the voxel its own samples interpolate from. ``tau`` is split where the volume's
  sharp features matter most: the first ``near_shadow`` units past the bias are marched
  per sample (``near_steps`` midpoint samples), the rest is read from the light field at
  ``x + (bias + near_shadow) l`` (trilinear, in optical depth, which is linear through a
  homogeneous medium); past the box nothing attenuates.
* **The light field** (`light_field`), computed once per volume, transfer function and
  light (the light does not move with the camera), on the voxel grid, float32
  ``(nz, ny, nx, 2)``:

  - channel `LIGHT_TAU`: ``tau(p)`` from each voxel, by the midpoint rule in steps of
    ``shadow_step`` units (the last one shortened to end at the box), skipping empty
    blocks (zero extinction) and stopping once ``tau > TAU_MAX``.
  - channel `LIGHT_AMBIENT`: ``ambient * O(p) + scattering * S(p)``. Occlusion ``O = 1 -
    mean_r(box_r(1 - exp(-sigma r)))``, the mean over ``occlusion_radii`` ``r`` of the
    box average (half-width ``r``) of each voxel's opacity over a path of length ``r``:
    1 in free space, 1/2 on a flat opaque wall, less in a crevice (for thin media it is
    ``exp(-r * mean sigma)``, the extinction-based estimate). Scattering ``S =
    box_s(exp(-tau))``, the key light's transmittance averaged over a box of half-width
    ``scattering_radius``: light that entered the neighbourhood and reaches the sample
    after more scattering events (a diffusion-like glow that softens shadow edges).

  Only voxels of non-empty blocks and their neighbour blocks carry ``tau`` (the others
  hold 0 and are never sampled); the box averages run over the whole grid.
* **Shading** of a sample with TF colour ``c`` (the albedo), gradient ``g`` (as the
  headlight's), view direction ``w`` and the ambient channel ``B`` interpolated
  trilinearly: with ``m = |g| unit``, the surface weight ``p = m / (m + surface_gradient)``
  (``p = 0`` where ``m`` is below the gradient epsilon), ``n = g / |g|`` turned to face
  the viewer, ``h = (l - w) / |l - w|``::

      key   = T * key_strength * (p * max(n.l, 0) + (1 - p) * phase(l . w))
      c'    = min(1, c * (key + B) + T * p * specular * max(n.h, 0)**shininess [n.l > 0])

  with ``phase`` the Henyey-Greenstein function times ``4 pi`` (1 for isotropic
  scattering), ``phase(mu) = (1 - g^2) / (1 + g^2 - 2 g mu)**1.5``, ``g = phase_g``:
  forward scattering for soft tissue. It depends only on the ray's direction, so it is
  computed once per ray. Compositing, opacity, early termination and depth are the
  headlight's: lighting changes colours only.

Everything is float64 arithmetic in a fixed order (no fastmath) over fixed grids, so the
light field and the images are the same bytes on every run, thread count and Dask worker.
The light field is cached per content (`light_field_key`): in memory for the process, and
on disk under `cache_dir` (``$EIGENCAST_CACHE_DIR``, default ``~/.cache/eigencast``; an
empty value turns the disk cache off; the least recently used beyond `DISK_CACHE_BYTES` are
deleted), so a resumed render and the Dask workers on the client's machine load it instead
of computing it again.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from numba import njit, prange
from scipy.ndimage import binary_dilation, uniform_filter

__all__ = [
    "ALPHA_MAX",
    "DEFAULT_LIGHTING",
    "DISK_CACHE_BYTES",
    "LIGHTINGS",
    "LIGHT_AMBIENT",
    "LIGHT_FIELD_VERSION",
    "LIGHT_TAU",
    "TAU_MAX",
    "Lighting",
    "cache_dir",
    "extinction_lut",
    "light_field",
    "light_field_key",
    "lighting_from_record",
    "resolve_lighting",
    "transmittance_at",
    "trilinear_in_box",
]

#: Version of the light field's algorithm (part of its cache key and its record).
LIGHT_FIELD_VERSION = "eigencast-light-field/1"
#: Channels of the light field.
LIGHT_TAU = 0
LIGHT_AMBIENT = 1
#: Largest per-unit opacity turned into extinction (an opaque voxel: ``sigma = 9.2 / unit``).
ALPHA_MAX = 1.0 - 1e-4
#: Optical depth past which the light's march stops (``T < 1e-6``; 0 after 8-bit rounding).
TAU_MAX = 14.0
#: Light fields kept in memory per process.
_MEMORY_CACHE_SIZE = 2
#: Bytes of light fields kept on disk; the least recently used go first.
DISK_CACHE_BYTES = 2 * 2**30
_MEMORY_CACHE: dict[str, np.ndarray] = {}
_CACHE_LOCK = threading.Lock()
_CACHE_ENV = "EIGENCAST_CACHE_DIR"
#: Values before the extinction LUT in the kernels' ``light`` array.
KERNEL_PARAMS = 17
#: Model codes passed to the kernels (``light[0]``).
MODEL_HEADLIGHT = 0
MODEL_WORLD = 1


@dataclass(frozen=True)
class Lighting:
    """One lighting look: a name and the parameters of its model.

    Parameters
    ----------
    name : str
        ``headlight`` (the ray-caster's Blinn-Phong headlight; no other field is used) or the
        name of a world-lit look.
    model : {"headlight", "world"}
    light_phi_deg, light_theta_deg : float
        Direction *towards* the light, in the orbit cameras' convention (azimuth,
        elevation; +z up): ``l = (cos t cos p, cos t sin p, sin t)``.
    key_strength : float
        Radiance of the key light reaching an unshadowed sample.
    ambient : float
        Weight of the ambient occlusion term ``O`` in the ambient channel.
    scattering : float
        Weight of the multiple-scattering estimate ``S`` in the ambient channel.
    specular, shininess : float
        Blinn-Phong highlight of the key light on surfaces (half vector).
    phase_g : float
        Henyey-Greenstein asymmetry in (-1, 1) of the volume scattering.
    surface_gradient : float
        Gradient magnitude (per unit) at which a sample is half surface, half volume.
    shadow_bias : float
        Where the light's march starts, in units towards the light.
    shadow_step : float
        The light field's march step, in units.
    near_shadow : float
        Length of the light's path marched per sample (the rest comes from the light
        field), in units past the bias.
    near_steps : int
        Midpoint samples of that near path.
    occlusion_radii : tuple of float
        Box half-widths of the ambient occlusion, in units.
    scattering_radius : float
        Box half-width of the scattering estimate, in units (at most 8, one block).
    """

    name: str
    model: str = "headlight"
    light_phi_deg: float = 0.0
    light_theta_deg: float = 0.0
    key_strength: float = 0.0
    ambient: float = 0.0
    scattering: float = 0.0
    specular: float = 0.0
    shininess: float = 1.0
    phase_g: float = 0.0
    surface_gradient: float = 0.1
    shadow_bias: float = 1.0
    shadow_step: float = 1.0
    near_shadow: float = 2.0
    near_steps: int = 4
    occlusion_radii: tuple[float, ...] = ()
    scattering_radius: float = 1.0

    @property
    def world_lit(self) -> bool:
        """True for a light fixed in the world (needs a light field)."""
        return self.model == "world"

    def direction(self) -> np.ndarray:
        """Unit vector towards the light, world axes: float64 (3,)."""
        p, t = math.radians(self.light_phi_deg), math.radians(self.light_theta_deg)
        v = np.array([math.cos(t) * math.cos(p), math.cos(t) * math.sin(p), math.sin(t)])
        v[np.abs(v) < 1e-12] = 0.0  # cos(90 deg) is 6e-17: a light straight up is along +z
        return v

    def record(self) -> dict:
        """JSON-able record (render settings, provenance): enough to rebuild it."""
        if not self.world_lit:
            return {"name": self.name, "model": "headlight"}
        out = asdict(self)
        out["occlusion_radii"] = list(self.occlusion_radii)
        out["light_field"] = LIGHT_FIELD_VERSION
        return out

    def check(self) -> Lighting:
        """Return self after checking every parameter; ValueError names the bad one."""
        if self.model not in ("headlight", "world"):
            raise ValueError(f"lighting {self.name!r}: model={self.model!r} must be "
                             "'headlight' or 'world'")
        if not self.world_lit:
            return self
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("name", "model"):
                continue
            values = v if isinstance(v, tuple) else (v,)
            if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in values):
                raise ValueError(f"lighting {self.name!r}: {f.name}={v!r} must be finite")
        checks = [
            ("key_strength", self.key_strength >= 0), ("ambient", self.ambient >= 0),
            ("scattering", self.scattering >= 0), ("specular", self.specular >= 0),
            ("shininess", self.shininess >= 1), ("phase_g", -1 < self.phase_g < 1),
            ("surface_gradient", self.surface_gradient > 0),
            ("shadow_bias", 0 <= self.shadow_bias <= 8),
            ("shadow_step", 0.05 <= self.shadow_step <= 8),
            ("near_shadow", 0 <= self.near_shadow <= 16),
            ("near_steps", float(self.near_steps).is_integer() and 1 <= self.near_steps <= 64),
            ("occlusion_radii", all(0 < r <= 64 for r in self.occlusion_radii)),
            ("scattering_radius", 0 < self.scattering_radius <= 8),
            ("light_theta_deg", -90 <= self.light_theta_deg <= 90),
        ]
        bad = [name for name, ok in checks if not ok]
        if bad:
            raise ValueError(f"lighting {self.name!r}: {bad[0]}={getattr(self, bad[0])!r} is "
                             "out of range")
        return self

    def kernel_params(self, spacing: tuple[float, float, float], grad_eps: float,
                      sigma: np.ndarray | None = None) -> np.ndarray:
        """The ``light`` array the ray-cast kernels read: float64, `KERNEL_PARAMS` values
        followed by the extinction LUT ``sigma`` (`extinction_lut`)."""
        if not self.world_lit:
            return np.zeros(KERNEL_PARAMS, dtype=np.float64)
        spacing_arr = np.asarray(spacing, dtype=np.float64)
        unit_mm = float(spacing_arr.min())
        lx, ly, lz = self.direction()
        head = [MODEL_WORLD, lx, ly, lz, self.key_strength, self.specular, self.shininess,
                self.phase_g, self.surface_gradient, unit_mm, grad_eps,
                lx / spacing_arr[0], ly / spacing_arr[1], lz / spacing_arr[2],
                self.shadow_bias * unit_mm, self.near_shadow * unit_mm, float(self.near_steps)]
        return np.concatenate([np.array(head, dtype=np.float64),
                               np.asarray(sigma, dtype=np.float64)])


#: The named looks. ``cinematic``: a lamp up and to the front-left of the default view
#: (phi 60, theta 15), 50 degrees above the horizon.
LIGHTINGS: dict[str, Lighting] = {
    "headlight": Lighting(name="headlight"),
    "cinematic": Lighting(
        name="cinematic", model="world", light_phi_deg=20.0, light_theta_deg=50.0,
        key_strength=1.0, ambient=0.45, scattering=0.3, specular=0.15, shininess=24.0,
        phase_g=0.25, surface_gradient=0.1, shadow_bias=1.0, shadow_step=1.0, near_shadow=1.0,
        near_steps=2,
        occlusion_radii=(2.0, 4.0, 8.0), scattering_radius=6.0,
    ),
}
DEFAULT_LIGHTING = "headlight"


def resolve_lighting(lighting: str | Lighting | None) -> Lighting:
    """A `Lighting` from a name in `LIGHTINGS`, a `Lighting`, or None (the default).

    Raises
    ------
    ValueError
        An unknown name (the message lists the known ones) or a bad parameter.
    """
    if lighting is None:
        return LIGHTINGS[DEFAULT_LIGHTING]
    if isinstance(lighting, Lighting):
        return lighting.check()
    if lighting not in LIGHTINGS:
        raise ValueError(f"lighting={lighting!r}: expected one of {', '.join(LIGHTINGS)}")
    return LIGHTINGS[lighting]


def lighting_from_record(record: Mapping | str | None) -> Lighting:
    """The `Lighting` of a render-settings record (``renderer["lighting"]``).

    None (a database rendered before lighting was recorded) reads as the headlight; a
    world-lit record is rebuilt from its own parameters, so it renders as it was recorded
    even if the named preset changes.

    Raises
    ------
    ValueError
        A malformed record, or one from another light-field version.
    """
    if record is None:
        return LIGHTINGS["headlight"]
    if isinstance(record, str):
        return resolve_lighting(record)
    if not isinstance(record, Mapping):
        raise ValueError(f"lighting record must be a mapping, got {type(record).__name__}")
    if record.get("model", "headlight") == "headlight":
        return LIGHTINGS["headlight"]
    version = record.get("light_field")
    if version != LIGHT_FIELD_VERSION:
        raise ValueError(f"lighting {record.get('name')!r} was recorded with light field "
                         f"{version!r}; this is {LIGHT_FIELD_VERSION!r}, whose images differ")
    known = {f.name for f in fields(Lighting)}
    unknown = sorted(set(record) - known - {"light_field"})
    if unknown:
        raise ValueError(f"lighting record has unknown keys {', '.join(unknown)}")
    try:
        kwargs = {k: record[k] for k in known if k in record}
        kwargs["name"] = str(kwargs["name"])
        kwargs["occlusion_radii"] = tuple(float(r) for r in kwargs.get("occlusion_radii", ()))
        for k in known - {"name", "model", "occlusion_radii", "near_steps"}:
            if k in kwargs:
                kwargs[k] = float(kwargs[k])
        if "near_steps" in kwargs:
            steps = float(kwargs["near_steps"])
            if not steps.is_integer():
                raise ValueError(f"near_steps={kwargs['near_steps']!r} must be an integer")
            kwargs["near_steps"] = int(steps)
        return Lighting(**kwargs).check()
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"malformed lighting record: {exc}") from None


# --------------------------------------------------------------------------- light field
def extinction_lut(tf_lut: np.ndarray, unit_mm: float) -> np.ndarray:
    """Extinction per mm for each LUT entry: ``-ln(1 - min(alpha, ALPHA_MAX)) / unit_mm``.

    Parameters
    ----------
    tf_lut : ndarray of shape (n, 4)
        The transfer function's RGBA LUT, opacity per unit (not step-corrected).
    unit_mm : float

    Returns
    -------
    ndarray of shape (n,), float64
    """
    alpha = np.clip(np.asarray(tf_lut, dtype=np.float64)[:, 3], 0.0, ALPHA_MAX)
    return -np.log1p(-alpha) / unit_mm


@njit(cache=True, nogil=True, inline="always")
def trilinear_in_box(u: np.ndarray, x: float, y: float, z: float) -> float:
    """Trilinear ``u`` (nz, ny, nx) at index-space ``(x, y, z)``, which must lie inside the
    box (the ray-caster's `_trilinear` clamps to it first)."""
    nz, ny, nx = u.shape
    i = min(int(x), nx - 2)
    j = min(int(y), ny - 2)
    k = min(int(z), nz - 2)
    fx = x - i
    fy = y - j
    fz = z - k
    c00 = u[k, j, i] + fx * (u[k, j, i + 1] - u[k, j, i])
    c10 = u[k, j + 1, i] + fx * (u[k, j + 1, i + 1] - u[k, j + 1, i])
    c01 = u[k + 1, j, i] + fx * (u[k + 1, j, i + 1] - u[k + 1, j, i])
    c11 = u[k + 1, j + 1, i] + fx * (u[k + 1, j + 1, i + 1] - u[k + 1, j + 1, i])
    c0 = c00 + fy * (c10 - c00)
    c1 = c01 + fy * (c11 - c01)
    return c0 + fz * (c1 - c0)


@njit(cache=True, nogil=True, inline="always")
def _exit(o: float, d: float, lo: float, hi: float) -> float:
    """Distance along ``o + t d`` at which the ray leaves ``[lo, hi]`` (inf when d == 0)."""
    if d > 0.0:
        return (hi - o) / d
    if d < 0.0:
        return (lo - o) / d
    return np.inf


@njit(parallel=True, cache=True, nogil=True)
def _optical_depth_kernel(
    u: np.ndarray,
    sigma: np.ndarray,
    block_needed: np.ndarray,
    block_empty: np.ndarray,
    block: int,
    spacing: np.ndarray,
    light: np.ndarray,
    step_mm: float,
    tau_max: float,
    out: np.ndarray,
) -> None:
    """``out[k, j, i] = tau``, the optical depth from the voxel to the box towards the light."""
    nz, ny, nx = u.shape
    n_lut = sigma.shape[0]
    isx, isy, isz = 1.0 / spacing[0], 1.0 / spacing[1], 1.0 / spacing[2]
    dx, dy, dz = light[0] * isx, light[1] * isy, light[2] * isz
    for k in prange(nz):
        bk = int(min(k, nz - 2)) // block
        for j in range(ny):
            bj = min(j, ny - 2) // block
            for i in range(nx):
                bi = min(i, nx - 2) // block
                if not block_needed[bk, bj, bi]:
                    out[k, j, i] = 0.0  # never sampled
                    continue
                ox = float(i)
                oy = float(j)
                oz = float(k)
                t_end = min(_exit(ox, dx, 0.0, nx - 1.0), _exit(oy, dy, 0.0, ny - 1.0),
                            _exit(oz, dz, 0.0, nz - 1.0))
                # samples at (m + 0.5) * step for m < n_full, each standing for one step,
                # then one for the shortened last step [n_full * step, t_end]
                n_full = math.floor(t_end / step_mm)
                tau = 0.0
                m = 0
                while m <= n_full and tau <= tau_max:
                    if m < n_full:
                        mid = (m + 0.5) * step_mm
                        seg = step_mm
                    else:
                        seg = t_end - n_full * step_mm
                        if not seg > 0.0:
                            break
                        mid = n_full * step_mm + 0.5 * seg
                    x = min(max(ox + mid * dx, 0.0), nx - 1.0)
                    y = min(max(oy + mid * dy, 0.0), ny - 1.0)
                    z = min(max(oz + mid * dz, 0.0), nz - 1.0)
                    ci = min(int(x), nx - 2) // block
                    cj = min(int(y), ny - 2) // block
                    ck = min(int(z), nz - 2) // block
                    if block_empty[ck, cj, ci]:
                        # zero extinction in the block: go to the first sample past its exit
                        t_block = min(
                            _exit(ox, dx, ci * 1.0 * block, min((ci + 1.0) * block, nx - 1.0)),
                            _exit(oy, dy, cj * 1.0 * block, min((cj + 1.0) * block, ny - 1.0)),
                            _exit(oz, dz, ck * 1.0 * block, min((ck + 1.0) * block, nz - 1.0)),
                        )
                        m = max(m + 1, math.floor(t_block / step_mm - 0.5) + 1)
                        continue
                    tpos = trilinear_in_box(u, x, y, z) * (n_lut - 1)
                    if not tpos > 0.0:
                        tpos = 0.0
                    elif tpos > n_lut - 1:
                        tpos = n_lut - 1.0
                    li = min(int(tpos), n_lut - 2)
                    f = tpos - li
                    tau += (sigma[li] + f * (sigma[li + 1] - sigma[li])) * seg
                    m += 1
                out[k, j, i] = tau


def _box_mean(field: np.ndarray, radius_units: float, spacing: np.ndarray,
              unit_mm: float) -> np.ndarray:
    """Mean of ``field`` over a box of half-width ``radius_units`` (per-axis voxels)."""
    half = np.maximum(0, np.rint(radius_units * unit_mm / spacing).astype(int))
    size = tuple(int(2 * h + 1) for h in half[::-1])  # (z, y, x)
    return uniform_filter(field, size=size, mode="nearest")


def light_field_key(u: np.ndarray, sigma: np.ndarray, spacing: tuple[float, ...],
                    lighting: Lighting) -> str:
    """SHA-256 (hex) of everything the light field depends on: the cache key."""
    h = hashlib.sha256()
    h.update(LIGHT_FIELD_VERSION.encode())
    h.update(json.dumps(lighting.record(), sort_keys=True).encode())
    h.update(json.dumps([float(s) for s in spacing]).encode())
    h.update(str(u.shape).encode())
    h.update(np.ascontiguousarray(u, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(sigma, dtype=np.float64).tobytes())
    return h.hexdigest()


def cache_dir() -> Path | None:
    """Where light fields are cached on disk: ``$EIGENCAST_CACHE_DIR`` (empty: nowhere),
    else ``$XDG_CACHE_HOME/eigencast`` or ``~/.cache/eigencast``."""
    env = os.environ.get(_CACHE_ENV)
    if env is not None:
        return Path(env) if env.strip() else None
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "eigencast"


def _load_cached(path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    try:
        field = np.load(path, allow_pickle=False)
        os.utime(path)  # recently used: pruned last
    except (OSError, ValueError):
        return None
    if field.shape != shape or field.dtype != np.float32:
        return None
    return np.ascontiguousarray(field)


def _prune_cache(folder: Path, keep_bytes: int) -> None:
    """Delete the least recently used light fields in ``folder`` beyond ``keep_bytes``."""
    try:
        files = [(p.stat().st_mtime, p.stat().st_size, p) for p in folder.glob("light-field-*.npy")]
    except OSError:
        return
    total = 0
    for _, size, path in sorted(files, key=lambda f: (-f[0], f[2].name)):
        total += size
        if total > keep_bytes:
            path.unlink(missing_ok=True)


def _store_cached(path: Path, field: np.ndarray) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        with open(tmp, "wb") as fh:
            np.save(fh, field, allow_pickle=False)
        os.replace(tmp, path)
        _prune_cache(path.parent, DISK_CACHE_BYTES)
    except OSError:
        pass  # a read-only or full cache only costs the next run the computation


def light_field(
    u: np.ndarray,
    tf_lut: np.ndarray,
    block_empty: np.ndarray,
    block: int,
    spacing: tuple[float, float, float],
    lighting: Lighting,
    *,
    use_cache: bool = True,
) -> np.ndarray:
    """The light field of a volume under ``lighting`` (module docstring), cached.

    Parameters
    ----------
    u : ndarray of shape (nz, ny, nx), float32
        The normalised scalar field the renderer samples.
    tf_lut : ndarray of shape (n, 4)
        The transfer function's LUT, opacity per unit (not corrected for the view step).
    block_empty : ndarray of shape (nbz, nby, nbx), uint8
        The renderer's empty-block map (1: zero opacity everywhere in the block).
    block : int
        Cells per block side.
    spacing : (sx, sy, sz)
        Voxel size in mm.
    lighting : Lighting
        A world-lit look.
    use_cache : bool
        Look the field up in (and store it to) the memory and disk caches.

    Returns
    -------
    ndarray of shape (nz, ny, nx, 2), float32
        `LIGHT_TAU` and `LIGHT_AMBIENT` per voxel.
    """
    spacing_arr = np.asarray(spacing, dtype=np.float64)
    unit_mm = float(spacing_arr.min())
    sigma = extinction_lut(tf_lut, unit_mm)
    key = light_field_key(u, sigma, spacing, lighting) if use_cache else ""
    path = None
    if use_cache:
        with _CACHE_LOCK:
            hit = _MEMORY_CACHE.get(key)
        if hit is not None:
            return hit
        folder = cache_dir()
        if folder is not None:
            path = folder / f"light-field-{key[:40]}.npy"
            loaded = _load_cached(path, (*u.shape, 2))
            if loaded is not None:
                loaded.flags.writeable = False
                _remember(key, loaded)
                return loaded
    field = _compute_light_field(u, sigma, block_empty, block, spacing_arr, unit_mm, lighting)
    field.flags.writeable = False  # shared by every renderer of the scene (and the cache)
    if use_cache:
        _remember(key, field)
        if path is not None:
            _store_cached(path, field)
    return field


def _remember(key: str, field: np.ndarray) -> None:
    with _CACHE_LOCK:
        while len(_MEMORY_CACHE) >= _MEMORY_CACHE_SIZE:
            _MEMORY_CACHE.pop(next(iter(_MEMORY_CACHE)))
        _MEMORY_CACHE[key] = field


def _compute_light_field(u: np.ndarray, sigma: np.ndarray, block_empty: np.ndarray, block: int,
                         spacing: np.ndarray, unit_mm: float, lighting: Lighting) -> np.ndarray:
    nz, ny, nx = u.shape
    needed = binary_dilation(block_empty == 0, structure=np.ones((3, 3, 3), dtype=bool))
    tau = np.empty((nz, ny, nx), dtype=np.float64)
    _optical_depth_kernel(
        np.ascontiguousarray(u, dtype=np.float32), np.ascontiguousarray(sigma),
        np.ascontiguousarray(needed, dtype=np.uint8), np.ascontiguousarray(block_empty),
        int(block), spacing, lighting.direction(), lighting.shadow_step * unit_mm, TAU_MAX, tau,
    )
    # per-voxel extinction, then the opacity of a path of length r through it
    n = sigma.shape[0]
    tpos = np.clip(u.astype(np.float64), 0.0, 1.0) * (n - 1)
    li = np.minimum(tpos.astype(np.int64), n - 2)
    f = tpos - li
    sigma_vox = sigma[li] + f * (sigma[li + 1] - sigma[li])
    del tpos, li, f
    occupancy = np.zeros((nz, ny, nx), dtype=np.float64)
    for r in lighting.occlusion_radii:
        occupancy += _box_mean(-np.expm1(-sigma_vox * (r * unit_mm)), r, spacing, unit_mm)
    occlusion = 1.0 - occupancy / max(1, len(lighting.occlusion_radii))
    scattered = _box_mean(np.exp(-tau), lighting.scattering_radius, spacing, unit_mm)
    field = np.empty((nz, ny, nx, 2), dtype=np.float32)
    field[..., LIGHT_TAU] = tau
    field[..., LIGHT_AMBIENT] = lighting.ambient * occlusion + lighting.scattering * scattered
    return field


# --------------------------------------------------------------------------- shading
@njit(cache=True, nogil=True, inline="always")
def ray_phase(light: np.ndarray, wx: float, wy: float, wz: float) -> float:
    """``4 pi`` times the Henyey-Greenstein phase for a ray of direction ``w`` (1: isotropic)."""
    g = light[7]
    mu = light[1] * wx + light[2] * wy + light[3] * wz
    return (1.0 - g * g) / (1.0 + g * g - 2.0 * g * mu) ** 1.5


@njit(cache=True, nogil=True, inline="always")
def _field_channel(field: np.ndarray, ch: int, i: int, j: int, k: int, fx: float, fy: float,
                   fz: float) -> float:
    """Trilinear channel ``ch`` of the light field in cell ``(i, j, k)`` at fractions ``f``."""
    c00 = field[k, j, i, ch] + fx * (field[k, j, i + 1, ch] - field[k, j, i, ch])
    c10 = field[k, j + 1, i, ch] + fx * (field[k, j + 1, i + 1, ch] - field[k, j + 1, i, ch])
    c01 = field[k + 1, j, i, ch] + fx * (field[k + 1, j, i + 1, ch] - field[k + 1, j, i, ch])
    c11 = field[k + 1, j + 1, i, ch] + fx * (
        field[k + 1, j + 1, i + 1, ch] - field[k + 1, j + 1, i, ch])
    c0 = c00 + fy * (c10 - c00)
    c1 = c01 + fy * (c11 - c01)
    return c0 + fz * (c1 - c0)


@njit(cache=True, nogil=True, inline="always")
def _sigma_at(u: np.ndarray, light: np.ndarray, x: float, y: float, z: float) -> float:
    """Extinction per mm at index-space ``(x, y, z)`` inside the box (LUT after the params)."""
    n_lut = light.shape[0] - KERNEL_PARAMS
    tpos = trilinear_in_box(u, x, y, z) * (n_lut - 1)
    if not tpos > 0.0:
        tpos = 0.0
    elif tpos > n_lut - 1:
        tpos = n_lut - 1.0
    li = min(int(tpos), n_lut - 2)
    f = tpos - li
    s0 = light[KERNEL_PARAMS + li]
    return s0 + f * (light[KERNEL_PARAMS + li + 1] - s0)


@njit(cache=True, nogil=True, inline="always")
def light_transmittance(u: np.ndarray, field: np.ndarray, light: np.ndarray, x: float,
                        y: float, z: float) -> float:
    """The key light's transmittance at index-space ``(x, y, z)`` (module docstring)."""
    nz, ny, nx = u.shape
    dx, dy, dz = light[11], light[12], light[13]
    bias, near = light[14], light[15]
    n_near = int(light[16])
    # where the light's path from x leaves the box: nothing attenuates past it
    s_exit = min(_exit(x, dx, 0.0, nx - 1.0), _exit(y, dy, 0.0, ny - 1.0),
                 _exit(z, dz, 0.0, nz - 1.0))
    if not s_exit > bias:
        return 1.0
    h = near / n_near
    tau = 0.0
    for q in range(n_near):
        s0 = bias + q * h
        seg = min(h, s_exit - s0)
        if not seg > 0.0:
            return math.exp(-tau)
        s = s0 + 0.5 * seg
        tau += _sigma_at(u, light, min(max(x + s * dx, 0.0), nx - 1.0),
                         min(max(y + s * dy, 0.0), ny - 1.0),
                         min(max(z + s * dz, 0.0), nz - 1.0)) * seg
    s = bias + near
    if s < s_exit:
        px = min(max(x + s * dx, 0.0), nx - 1.0)
        py = min(max(y + s * dy, 0.0), ny - 1.0)
        pz = min(max(z + s * dz, 0.0), nz - 1.0)
        i = min(int(px), nx - 2)
        j = min(int(py), ny - 2)
        k = min(int(pz), nz - 2)
        tau += _field_channel(field, LIGHT_TAU, i, j, k, px - i, py - j, pz - k)
    return math.exp(-tau)


@njit(cache=True, nogil=True)
def _transmittance_points(u: np.ndarray, field: np.ndarray, light: np.ndarray,
                          points: np.ndarray, out: np.ndarray) -> None:
    for n in range(points.shape[0]):
        out[n] = light_transmittance(u, field, light, points[n, 0], points[n, 1], points[n, 2])


def transmittance_at(u: np.ndarray, field: np.ndarray, light: np.ndarray,
                     points_index: np.ndarray) -> np.ndarray:
    """`light_transmittance` at many index-space points inside the box: float64 (n,)."""
    points = np.ascontiguousarray(points_index, dtype=np.float64).reshape(-1, 3)
    nz, ny, nx = u.shape
    if np.any(points < 0.0) or np.any(points > np.array([nx - 1.0, ny - 1.0, nz - 1.0])):
        raise ValueError("transmittance_at: points must lie inside the volume box")
    out = np.empty(len(points))
    _transmittance_points(u, field, light, points, out)
    return out


@njit(cache=True, nogil=True, inline="always")
def shade_world(
    u: np.ndarray,
    field: np.ndarray,
    light: np.ndarray,
    phase: float,
    x: float,
    y: float,
    z: float,
    gx: float,
    gy: float,
    gz: float,
    gmag: float,
    wx: float,
    wy: float,
    wz: float,
    r: float,
    g: float,
    b: float,
) -> tuple[float, float, float]:
    """A sample's colour under a world-fixed light (module docstring), from its albedo."""
    nz, ny, nx = field.shape[0], field.shape[1], field.shape[2]
    i = min(int(x), nx - 2)
    j = min(int(y), ny - 2)
    k = min(int(z), nz - 2)
    ambient = _field_channel(field, LIGHT_AMBIENT, i, j, k, x - i, y - j, z - k)
    trans = light_transmittance(u, field, light, x, y, z)
    lx, ly, lz = light[1], light[2], light[3]
    key, specular, shininess = light[4], light[5], light[6]
    surface_gradient, unit_mm, grad_eps = light[8], light[9], light[10]
    surface = 0.0
    diffuse = 0.0
    spec = 0.0
    if gmag >= grad_eps:
        m = gmag * unit_mm
        surface = m / (m + surface_gradient)
        inv = 1.0 / gmag
        nxv = gx * inv
        nyv = gy * inv
        nzv = gz * inv
        if nxv * wx + nyv * wy + nzv * wz > 0.0:  # face the viewer (who looks along w)
            nxv = -nxv
            nyv = -nyv
            nzv = -nzv
        ndl = nxv * lx + nyv * ly + nzv * lz
        if ndl > 0.0:
            diffuse = ndl
            hx = lx - wx
            hy = ly - wy
            hz = lz - wz
            hn = math.sqrt(hx * hx + hy * hy + hz * hz)
            if hn > 0.0:
                ndh = (nxv * hx + nyv * hy + nzv * hz) / hn
                if ndh > 0.0:
                    spec = specular * ndh**shininess
    lit = trans * key * (surface * diffuse + (1.0 - surface) * phase) + ambient
    highlight = trans * surface * spec
    return (min(1.0, r * lit + highlight), min(1.0, g * lit + highlight),
            min(1.0, b * lit + highlight))


def warmup_light_field() -> None:
    """Compile (or load from numba's cache) the light-field kernel with a tiny volume."""
    u = np.zeros((4, 4, 4), dtype=np.float32)
    lut = np.zeros((8, 4), dtype=np.float32)
    lut[:, 3] = 0.5
    light_field(u, lut, np.zeros((1, 1, 1), dtype=np.uint8), 8, (1.0, 1.0, 1.0),
                LIGHTINGS["cinematic"], use_cache=False)

