"""The built-in procedural volumes: ``builtin:head``, ``builtin:tooth``, ``builtin:sphere``.

``builtin:head`` (CT-like phantom in HU, 112x136x144 at 1.6 mm, modality ct),
``builtin:tooth`` (two-rooted molar on the paper's tooth scale 0-255,
120x104x160 at 0.15 mm, crown up, modality tooth) and ``builtin:sphere``
(ball of ones, 64^3). Deterministic, float32, no files; see `list_builtins`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from host.errors import VolumeError
from host.volume.core import (
    Volume,
)

__all__ = [
    "builtin_volume",
    "list_builtins",
]

# Each phantom is painted back to front on a grid centred at the origin (mm,
# RAS): a region is a signed distance field (negative inside) and paints its
# value through a soft 1.3-2 voxel edge, so iso-surfaces are smooth and shading
# looks organic rather than voxelated. A little deterministic noise (B-spline
# upsampled random lattices, fixed seeds) gives texture. Results are cached;
# callers get a fresh copy.


class _Grid:
    """Voxel-centre coordinates (mm, centred at 0) and sub-box access."""

    def __init__(self, dims: tuple[int, int, int], spacing_mm: float) -> None:
        self.dims = dims
        self.spacing = float(spacing_mm)
        self.axes = [
            ((np.arange(n, dtype=np.float32) - (n - 1) / 2.0) * np.float32(self.spacing))
            for n in dims
        ]
        self.shape = (dims[2], dims[1], dims[0])

    def coarse(self, factor: int) -> _Grid:
        """A grid ``factor`` times coarser covering at least the same box."""
        return _Grid(
            tuple(int(np.ceil((n - 1) / factor)) + 3 for n in self.dims), self.spacing * factor
        )

    def box(
        self, lo: tuple[float, float, float], hi: tuple[float, float, float]
    ) -> tuple[tuple[slice, slice, slice], np.ndarray, np.ndarray, np.ndarray] | None:
        """Slices of the sub-grid covering [lo, hi] (mm) and its broadcast X, Y, Z."""
        idx = []
        for a, low, high in zip(self.axes, lo, hi):
            i0 = int(np.searchsorted(a, low - 2 * self.spacing))
            i1 = int(np.searchsorted(a, high + 2 * self.spacing))
            if i1 <= i0:
                return None
            idx.append(slice(i0, i1))
        sx, sy, sz = idx
        x = self.axes[0][sx][None, None, :]
        y = self.axes[1][sy][None, :, None]
        z = self.axes[2][sz][:, None, None]
        return (sz, sy, sx), x, y, z

    def full(self) -> tuple[tuple[slice, slice, slice], np.ndarray, np.ndarray, np.ndarray]:
        out = self.box((-1e9, -1e9, -1e9), (1e9, 1e9, 1e9))
        assert out is not None
        return out


def _bspline_weights(pos: np.ndarray, n_in: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices and weights, each (len(pos), 4), of cubic B-spline taps at ``pos``.

    ``pos`` are positions in lattice index units; indices are clamped to the lattice.
    """
    base = np.floor(pos).astype(np.intp)
    f = pos - base
    weights = np.stack(
        [
            (1 - f) ** 3 / 6,
            (3 * f**3 - 6 * f**2 + 4) / 6,
            (-3 * f**3 + 3 * f**2 + 3 * f + 1) / 6,
            f**3 / 6,
        ],
        axis=1,
    )
    index = np.clip(base[:, None] + np.arange(-1, 3)[None, :], 0, n_in - 1)
    return index, weights


def _bspline_taps(n_out: int, n_in: int) -> tuple[np.ndarray, np.ndarray]:
    """B-spline taps spreading ``n_out`` samples over the inner part of a lattice."""
    return _bspline_weights(np.linspace(1.0, n_in - 2.0, n_out), n_in)


def _resample_axis(a: np.ndarray, axis: int, taps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Apply interpolation ``taps`` along ``axis`` (element-wise, no BLAS threads)."""
    index, weights = taps
    weights = weights.astype(np.float32)
    moved = np.ascontiguousarray(np.moveaxis(a, axis, 0), dtype=np.float32)
    out = np.empty((index.shape[0], *moved.shape[1:]), dtype=np.float32)
    scratch = np.empty(moved.shape[1:], dtype=np.float32)
    for i in range(index.shape[0]):  # one contiguous output plane at a time
        plane = out[i]
        np.multiply(moved[index[i, 0]], weights[i, 0], out=plane)
        for t in range(1, index.shape[1]):
            np.multiply(moved[index[i, t]], weights[i, t], out=scratch)
            plane += scratch
    return out if axis == 0 else np.ascontiguousarray(np.moveaxis(out, 0, axis))


class _Upsampler:
    """Smooth (cubic B-spline) resampling of coarse-grid fields onto a fine grid.

    Smooth rather than trilinear so that iso-surfaces of resampled distance
    fields have continuous normals (no facets in shaded renders).
    """

    def __init__(self, coarse: _Grid, fine: _Grid) -> None:
        self.taps = [
            _bspline_weights((f - c[0]) / (c[1] - c[0]), c.size)
            for f, c in zip(fine.axes, coarse.axes)
        ]

    def __call__(self, field: np.ndarray) -> np.ndarray:
        out = field.astype(np.float32)
        for numpy_axis, world_axis in ((2, 0), (1, 1), (0, 2)):
            out = _resample_axis(out, numpy_axis, self.taps[world_axis])
        return out


def _ellipsoid(x, y, z, c, r):  # noqa: ANN001 - internal, broadcast float32 arrays
    """Approximate signed distance (mm) to an axis-aligned ellipsoid."""
    px, py, pz = (x - c[0]) / r[0], (y - c[1]) / r[1], (z - c[2]) / r[2]
    k0 = np.sqrt(px * px + py * py + pz * pz)
    qx, qy, qz = px / r[0], py / r[1], pz / r[2]
    k1 = np.sqrt(qx * qx + qy * qy + qz * qz) + np.float32(1e-6)
    return k0 * (k0 - 1.0) / k1


def _round_cone(x, y, z, a, b, ra, rb):  # noqa: ANN001
    """Approximate signed distance to a capsule from a (radius ra) to b (radius rb)."""
    ax, ay, az = a
    bx, by, bz = b[0] - ax, b[1] - ay, b[2] - az
    length2 = bx * bx + by * by + bz * bz
    px, py, pz = x - ax, y - ay, z - az
    t = np.clip((px * bx + py * by + pz * bz) / length2, 0.0, 1.0)
    dx, dy, dz = px - t * bx, py - t * by, pz - t * bz
    return np.sqrt(dx * dx + dy * dy + dz * dz) - (ra + (rb - ra) * t)


def _smin(a, b, k):  # noqa: ANN001
    """Smooth minimum (union) of two distance fields with blend radius k (mm)."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * (k * 0.25)


def _paint(vol: np.ndarray, sl, sdf, value, edge_mm: float) -> None:  # noqa: ANN001
    """Blend ``value`` into ``vol[sl]`` where ``sdf < 0`` with a soft edge."""
    m = np.clip(0.5 - sdf * np.float32(1.0 / edge_mm), 0.0, 1.0)
    region = vol[sl]
    region += m * (np.asarray(value, dtype=np.float32) - region)


def _noise(shape: tuple[int, int, int], cell_vox: float, seed: int) -> np.ndarray:
    """Smooth deterministic noise, std 0.5, feature size about ``cell_vox`` voxels."""
    rng = np.random.default_rng(seed)
    lattice = [max(4, int(np.ceil(n / cell_vox)) + 3) for n in shape]
    out = rng.uniform(-1.0, 1.0, size=lattice).astype(np.float32)
    for axis in (2, 1, 0):
        out = _resample_axis(out, axis, _bspline_taps(shape[axis], lattice[axis]))
    out *= np.float32(0.5 / max(float(out.ravel()[::7].std()), 1e-6))
    return out


# Small parts of the head phantom, painted in order after the large fields.
# ("ellipsoid", centre, radii), ("capsule", a, b, radius_a, radius_b),
# ("box", centre, half_size), ("ring", centre_xy, z_range, r_out, r_in) (vertical),
# ("arch", centre_xy, radii_xy, half_thickness, z_range, min_y) (U-shaped bar);
# each with the value it paints (HU) and optionally "skull" to stay inside the
# skull's outer surface (default: 2.5 mm under the skin).
def _face_bones() -> tuple[list[tuple], list[tuple]]:
    """Facial bones blended smoothly into the face shell: (unions, holes), each (shape, k)."""
    unions: list[tuple] = [
        (("arch", (0, 22), (38, 48), 5.0, (-80, -62), 6.0), 5.0),  # mandible body
        (("arch", (0, 20), (33, 50), 5.0, (-53, -41), 10.0), 5.0),  # upper alveolar ridge
        (("ellipsoid", (0, 68, -76), (14, 6, 9)), 5.0),  # chin
    ]
    holes: list[tuple] = [
        (("ellipsoid", (0, 82, -30), (10, 16, 15)), 4.0),  # nasal aperture
    ]
    for sx in (-1.0, 1.0):
        unions += [
            (("ellipsoid", (sx * 44, 60, -24), (10, 10, 9)), 6.0),  # cheekbone
            (("capsule", (sx * 46, 56, -24), (sx * 56, 0, -20), 4.5, 4.0), 6.0),  # zyg. arch
            (("capsule", (sx * 36, 12, -72), (sx * 46, -4, -30), 6.0, 4.5), 6.0),  # ramus
        ]
        holes.append((("ellipsoid", (sx * 31, 64, -12), (15, 30, 14)), 4.0))  # orbit
    return unions, holes


def _head_parts() -> list[tuple]:
    """Small parts painted in order: (shape, value HU[, "skull"])."""
    parts: list[tuple] = [
        (("ellipsoid", (0, -50, -22), (42, 24, 13)), 36.0),  # cerebellum
        (("capsule", (0, -16, -8), (0, -24, -115), 11.0, 6.0), 32.0),  # brain stem, cord
        (("ellipsoid", (0, -6, 10), (2.5, 13, 8)), 5.0),  # third ventricle
        (("ellipsoid", (0, -34, -16), (5, 4, 5)), 5.0),  # fourth ventricle
        (("ellipsoid", (0, 58, -26), (9, 32, 20)), -1000.0),  # nasal cavity
        (("box", (0, 58, -26), (1.0, 28, 16)), 700.0),  # nasal septum
        (("ellipsoid", (0, 70, 12), (12, 3.0, 8)), -1000.0, "skull"),  # frontal sinus
        (("capsule", (0, 30, -28), (0, 30, -130), 8.0, 8.0), -1000.0),  # pharynx, trachea
    ]
    for sx in (-1.0, 1.0):
        parts += [
            # lateral ventricle (two pieces) and temporal horn
            (("capsule", (sx * 10, -34, 26), (sx * 10, -6, 34), 5.0, 6.0), 5.0),
            (("capsule", (sx * 10, -6, 34), (sx * 9, 22, 27), 6.0, 4.0), 5.0),
            (("capsule", (sx * 12, -30, 24), (sx * 20, 6, -14), 3.5, 2.0), 5.0),
            # orbit fat, eyeball (sclera), vitreous, lens
            (("ellipsoid", (sx * 31, 55, -12), (14, 20, 13)), -80.0),
            (("ellipsoid", (sx * 31, 53, -12), (11.5, 11.5, 11.5)), 40.0),
            (("ellipsoid", (sx * 31, 53, -12), (10.3, 10.3, 10.3)), 10.0),
            (("ellipsoid", (sx * 31, 63, -12), (4, 2, 4)), 90.0),
            # maxillary sinus: thin bone wall, air inside
            (("ellipsoid", (sx * 25, 44, -32), (15, 17, 12)), 1000.0),
            (("ellipsoid", (sx * 25, 44, -32), (13, 15, 10)), -1000.0),
            # ear canal
            (("capsule", (sx * 82, -12, -8), (sx * 60, -12, -8), 3.0, 2.0), -1000.0),
        ]
    for row_z, ry in ((-48.0, 50.0), (-57.0, 46.0)):  # upper and lower teeth
        for ang in np.linspace(-1.35, 1.35, 12):
            centre = (31.0 * float(np.sin(ang)), 20.0 + ry * float(np.cos(ang)), row_z)
            parts.append((("ellipsoid", centre, (4.0, 3.6, 5.0)), 2400.0))
    for zc in (-50.0, -68.0, -86.0, -104.0, -122.0):  # cervical vertebrae
        parts += [
            (("capsule", (0, -12, zc - 5), (0, -12, zc + 5), 12.0, 12.0), 1100.0),
            (("ring", (0, -30), (zc - 5, zc + 5), 12.0, 7.0), 1100.0),
            (("box", (0, -48, zc - 2), (3.0, 9.0, 4.0)), 1100.0),
        ]
    parts.append((("capsule", (0, -30, -40), (0, -30, -130), 5.0, 5.0), 30.0))  # spinal cord
    return parts


def _part_box(shape: tuple) -> tuple[tuple[float, ...], tuple[float, ...]]:
    kind = shape[0]
    if kind == "ellipsoid":
        c, r = np.array(shape[1]), np.array(shape[2])
        return tuple(c - r), tuple(c + r)
    if kind == "capsule":
        a, b = np.array(shape[1]), np.array(shape[2])
        r = max(shape[3], shape[4])
        return tuple(np.minimum(a, b) - r), tuple(np.maximum(a, b) + r)
    if kind == "box":
        c, h = np.array(shape[1]), np.array(shape[2])
        return tuple(c - h), tuple(c + h)
    if kind == "ring":
        (cx, cy), (z0, z1), r = shape[1], shape[2], shape[3]
        return (cx - r, cy - r, z0), (cx + r, cy + r, z1)
    (cx, cy), (rx, ry), t, (z0, z1), _ = shape[1:]  # arch
    return (cx - rx - t, cy - ry - t, z0), (cx + rx + t, cy + ry + t, z1)


def _part_sdf(shape: tuple, x, y, z):  # noqa: ANN001 - broadcast float32 arrays
    kind = shape[0]
    if kind == "ellipsoid":
        return _ellipsoid(x, y, z, shape[1], shape[2])
    if kind == "capsule":
        return _round_cone(x, y, z, *shape[1:])
    if kind == "box":
        (cx, cy, cz), (hx, hy, hz) = shape[1], shape[2]
        return np.maximum(np.maximum(np.abs(x - cx) - hx, np.abs(y - cy) - hy), np.abs(z - cz) - hz)
    if kind == "ring":
        (cx, cy), (z0, z1), r_out, r_in = shape[1:]
        rho = np.sqrt((x - cx) ** 2 + (y - cy) ** 2)
        slab = np.abs(z - 0.5 * (z0 + z1)) - 0.5 * (z1 - z0)
        return np.maximum(np.maximum(rho - r_out, r_in - rho), slab)
    (cx, cy), (rx, ry), half, (z0, z1), min_y = shape[1:]  # arch
    rho = np.sqrt(((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2)
    bar = np.abs(rho - 1.0) * (0.5 * (rx + ry)) - half
    slab = np.abs(z - 0.5 * (z0 + z1)) - 0.5 * (z1 - z0)
    return np.maximum(np.maximum(bar, slab), min_y - y)


def _build_head() -> tuple[np.ndarray, float]:
    """CT-like head phantom in HU, RAS, (nz, ny, nx) = (144, 136, 112), 1.6 mm.

    The large smooth distance fields (skin, cranium, face) are computed on a
    2x coarser grid and resampled with cubic B-splines; the small parts of
    `_head_parts` are evaluated at full resolution inside their own boxes.
    """
    g = _Grid((112, 136, 144), 1.6)
    c = g.coarse(2)
    up = _Upsampler(c, g)
    edge = 1.6 * 2.0
    _, X, Y, Z = c.full()

    # z of the skull base as a function of y (anterior, middle, posterior fossae)
    fossa_y, fossa_z = [-95, -30, -12, 22, 34, 95], [-36, -36, -24, -24, -4, -4]
    zb_c = np.interp(c.axes[1], fossa_y, fossa_z).astype(np.float32)[None, :, None]
    zb = np.interp(g.axes[1], fossa_y, fossa_z).astype(np.float32)[None, :, None]

    # ---- coarse fields: skin (cranium + face + jaw + neck + nose + ears), skull, face bones
    cran = _ellipsoid(X, Y, Z, (0, -10, 26), (72, 92, 82))
    face = _ellipsoid(X, Y, Z, (0, 24, -26), (56, 62, 56))
    jaw = _ellipsoid(X, Y, Z, (0, 38, -62), (48, 44, 28))
    neck = np.maximum((np.sqrt((X / 50.0) ** 2 + ((Y + 10) / 52.0) ** 2) - 1.0) * 50.0, Z + 40.0)
    skin = _smin(_smin(cran, face, 18.0), _smin(jaw, neck, 16.0), 14.0)
    skin = _smin(skin, _ellipsoid(X, Y, Z, (0, 70, 2), (48, 14, 10)), 8.0)  # brow ridge
    skin = _smin(skin, _ellipsoid(X, Y, Z, (0, 78, -54), (22, 9, 9)), 5.0)  # lips
    skin = _smin(skin, _ellipsoid(X, Y, Z, (0, 74, -80), (18, 10, 13)), 8.0)  # chin
    skin = _smin(skin, _ellipsoid(X, Y + 0.3 * (Z + 22), Z, (0, 84, -22), (12, 18, 25)), 6.0)
    for sx in (-1, 1):
        skin = _smin(skin, _ellipsoid(X, Y, Z, (sx * 38, 54, -30), (18, 16, 16)), 14.0)  # cheek
        skin = _smin(skin, _ellipsoid(X, Y, Z, (sx * 72, -12, -4), (8, 13, 24)), 5.0)  # ear
        socket = _ellipsoid(X, Y, Z, (sx * 31, 84, -12), (15, 9, 8))
        skin = -_smin(-skin, socket, 6.0)  # shallow eye socket
    outer_c = cran + 5.0
    occipital = np.clip(-(Y + 30) / 40.0, 0.0, 1.0) * np.clip(1.0 - (Z - 20) / 60.0, 0.0, 1.0)
    temporal = np.clip((np.abs(X) - 50.0) / 15.0, 0.0, 1.0)
    wobble = _noise(c.shape, 7.0, seed=11)
    thick_c = np.maximum(6.5 + 2.0 * wobble + 2.5 * occipital - 2.5 * temporal, 3.0)
    face_bone_c = np.maximum(face + 7.0, -(face + 12.0))
    face_bone_c = np.maximum(face_bone_c, Z - (zb_c + 2.0) * (Y > 30))
    face_bone_c = np.maximum(face_bone_c, np.maximum(-50.0 - Z, 12.0 - Y))
    skin, outer, thick, face_bone = (up(f) for f in (skin, outer_c, thick_c, face_bone_c))

    full, Xf, _, Zf = g.full()
    fine = _noise(g.shape, 4.0, seed=12)  # ~6 mm texture; also folds the cortex
    vol = np.full(g.shape, -1000.0, dtype=np.float32)
    skin += fine * np.float32(0.4)
    _paint(vol, full, skin, 45.0, edge)
    fat = np.maximum(np.maximum(skin + 2.0, -(skin + 6.0)), Zf - (zb + 6.0))
    _paint(vol, full, fat, -90.0, edge)  # subcutaneous fat of face and neck
    vol += fine * np.float32(6.0)

    # ---- skull vault (outer/inner tables, diploe), skull base with the foramen magnum
    vault = np.maximum(np.maximum(outer, -(outer + thick)), (zb - 6.0) - Zf)
    depth = np.clip(-outer / thick, 0.0, 1.0)
    _paint(vol, full, vault, 1750.0 - 1050.0 * np.exp(-(((depth - 0.5) / 0.24) ** 2)), edge)
    s, x, y, z = g.box((-80, -100, -60), (80, 100, 10))
    plate = np.maximum(np.maximum(outer[s] + 2.0, z - zb[:, s[1]]), (zb[:, s[1]] - 7.0) - z)
    _paint(vol, s, np.maximum(plate, 13.0 - np.sqrt(x * x + (y + 24) ** 2)), 1300.0, edge)

    # ---- CSF, then brain with gyri (sulci where the noise crosses zero) and midline fissure
    inner = outer + thick
    _paint(vol, full, np.maximum(inner, zb - Zf), 8.0, edge)
    brain = inner + 2.5
    brain += 5.0 * np.exp(-((fine / 0.22) ** 2)) * np.clip(1.0 + brain / 14.0, 0.0, 1.0)
    brain = np.maximum(brain, (zb + 3.0) - Zf)
    brain = np.maximum(brain, np.where(Zf > zb + 24.0, 1.5 - np.abs(Xf), -1e3))
    grey = np.clip(1.0 - (-brain - 2.5) / 2.0, 0.0, 1.0)
    _paint(vol, full, brain, 28.0 + 10.0 * grey, edge)

    # ---- facial skeleton: the face shell with bones blended in and openings cut out
    s, x, y, z = g.box((-70, -15, -95), (70, 100, 10))
    bone = face_bone[s]
    unions, holes = _face_bones()
    for shape, k in unions:
        bone = _smin(bone, _part_sdf(shape, x, y, z), k)
    for shape, k in holes:
        bone = -_smin(-bone, _part_sdf(shape, x, y, z), k)
    bone = np.maximum(bone, skin[s] + 2.5)
    _paint(vol, s, bone, 1250.0 + fine[s] * 80.0, edge)

    # ---- the small parts
    for shape, value, *within in _head_parts():
        sl = g.box(*_part_box(shape))
        if sl is not None:  # every part stays under the skin (or inside the skull)
            s, x, y, z = sl
            limit = outer[s] + 1.5 if within == ["skull"] else skin[s] + 2.5
            _paint(vol, s, np.maximum(_part_sdf(shape, x, y, z), limit), value, edge)
    return vol, g.spacing


def _build_tooth() -> tuple[np.ndarray, float]:
    """Molar phantom on the paper's tooth scale (0..255), crown up, 0.15 mm voxels.

    Distance fields are computed on a 2x coarser grid and resampled.
    """
    g = _Grid((120, 104, 160), 0.15)
    c = g.coarse(2)
    up = _Upsampler(c, g)
    edge = 0.15 * 1.3
    _, x, y, z = c.full()

    # occlusal surface: four cusps around a central fossa
    cusps = np.zeros((1, *(x * y).shape[1:]), dtype=np.float32)
    for cx, cy in ((-2.3, -1.9), (2.3, -1.9), (-2.2, 2.0), (2.4, 2.0)):
        cusps = cusps + np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 3.2)
    weight = np.clip((z - 4.5) / 3.0, 0.0, 1.0)
    crown = _ellipsoid(x, y, z - weight * (1.3 * cusps - 0.9), (0, 0, 4.2), (5.6, 5.0, 5.6))
    crown = np.maximum(crown, 2.6 - z)  # enamel ends at the cemento-enamel junction
    trunk = _ellipsoid(x, y, z, (0, 0, 2.2), (5.1, 4.4, 3.6))
    roots = np.minimum(
        *(
            _round_cone(x, y, z, (sx * 2.4, 0.0, 1.5), (sx * 3.0, 0.3, -10.4), 2.8, 1.0)
            for sx in (-1, 1)
        )
    )
    enamel_thick = 1.35 * np.clip((z - 2.6) / 4.0, 0.0, 1.0) ** 0.7
    dentin = _smin(_smin(crown + enamel_thick, trunk, 1.2), roots, 1.5)
    outer = np.minimum(crown, dentin)
    pulp = _ellipsoid(x, y, z, (0, 0, 3.4), (2.7, 2.0, 1.7))
    for cx, cy in ((-1.7, -1.3), (1.7, -1.3), (-1.6, 1.4), (1.7, 1.4)):
        pulp = _smin(pulp, _ellipsoid(x, y, z, (cx, cy, 5.0), (0.6, 0.6, 1.3)), 0.6)
    for sx in (-1, 1):
        canal = _round_cone(x, y, z, (sx * 2.3, 0.0, 2.6), (sx * 2.9, 0.3, -9.6), 0.65, 0.18)
        pulp = _smin(pulp, canal, 0.5)

    fine = _noise(g.shape, 4.0, seed=22)
    _, _, _, zf = g.full()
    full = g.full()[0]
    vol = np.full(g.shape, 4.0, dtype=np.float32)
    vol += fine * np.float32(3.0)
    top = np.clip((zf - 5.0) / 4.0, 0.0, 1.0)
    _paint(vol, full, up(outer), 235.0 + 8.0 * fine + 6.0 * top, edge)
    _paint(vol, full, up(dentin), 158.0 + 5.0 * fine - 8.0 * np.clip(-zf / 10.0, 0.0, 1.0), edge)
    _paint(vol, full, up(pulp), 55.0 + 4.0 * fine, edge)
    return vol, g.spacing


def _build_sphere() -> tuple[np.ndarray, float]:
    """Homogeneous ball of value 1 (radius 24 voxels) in a 64^3 grid of zeros."""
    g = _Grid((64, 64, 64), 1.0)
    vol = np.zeros(g.shape, dtype=np.float32)
    full, x, y, z = g.full()
    _paint(vol, full, np.sqrt(x * x + y * y + z * z) - 24.0, 1.0, 1.0)
    return vol, g.spacing


@dataclass(frozen=True)
class _Builtin:
    build: Callable[[], tuple[np.ndarray, float]]
    modality: str
    description: str
    units: str | None = None
    # Gaussian band-limit (in voxels) applied last: painted edges leave terraces
    # that trilinear sampling turns into concentric "wood-grain" rings on smooth
    # surfaces (visible at any step size); sigma = 1 voxel removes them.
    smooth_voxels: float = 0.0


_BUILTINS: dict[str, _Builtin] = {
    "head": _Builtin(
        _build_head,
        "ct",
        "CT-like head phantom in HU: skin, skull with diploe, brain with gyri, ventricles, "
        "sinuses, eyes, jaw, teeth, cervical spine; 112x136x144 at 1.6 mm",
        units="HU",
        smooth_voxels=1.0,
    ),
    "tooth": _Builtin(
        _build_tooth,
        "tooth",
        "two-rooted molar on a 0-255 scale: enamel crown (up), dentin, pulp cavity and "
        "canals; 120x104x160 at 0.15 mm",
        smooth_voxels=1.0,
    ),
    "sphere": _Builtin(
        _build_sphere, "generic", "homogeneous ball (value 1, radius 24) in 64^3 zeros, 1 mm"
    ),
}


def list_builtins() -> list[str]:
    """Names accepted by ``builtin:NAME``, sorted."""
    return sorted(_BUILTINS)


@functools.cache
def _built(name: str) -> tuple[np.ndarray, float]:
    spec = _BUILTINS[name]
    data, spacing = spec.build()
    if spec.smooth_voxels:
        from scipy import ndimage

        data = ndimage.gaussian_filter(data, spec.smooth_voxels, mode="nearest")
    data.flags.writeable = False
    return data, spacing


def builtin_volume(name: str) -> Volume:
    """The procedural volume ``name`` (see `list_builtins`); deterministic.

    Raises
    ------
    VolumeError
        For an unknown name, listing the known ones.
    """
    key = str(name).strip().lower()
    if key not in _BUILTINS:
        raise VolumeError(
            f"builtin:{name}: unknown built-in volume; known: "
            + ", ".join(f"builtin:{n}" for n in list_builtins())
        )
    spec = _BUILTINS[key]
    data, spacing = _built(key)
    data = data.copy()
    metadata = {
        "format": "builtin",
        "description": spec.description,
        "file_dims": [int(data.shape[2]), int(data.shape[1]), int(data.shape[0])],
        "file_dtype": "float32",
        "value_range": [float(data.min()), float(data.max())],
        "orientation": {"file_axes": "RAS", "source": "builtin", "note": ""},
        "modality_source": "builtin",
    }
    if spec.units:
        metadata["units"] = spec.units
    return Volume(
        data,
        (spacing, spacing, spacing),
        name=key,
        modality=spec.modality,
        source=f"builtin:{key}",
        metadata=metadata,
    )
