"""Score interpolation on the view sphere: evaluation in pure numpy.

The training views' scores are a function on the sphere of view directions.
This module turns a query view ``(phi_deg, theta_deg)`` into a few training
views and blend weights (`InterpolationWeights`), and blends rows of a table
with them (`interpolate`). The host builds the interpolator's data (it may use
scipy to triangulate) and ships it in the eigenspace image manifest; a
standalone device rebuilds the same interpolator from that manifest
(`interpolator_from_manifest`) and gets bit-identical weights, because the
host evaluates with this very module.

Conventions (the camera's): ``phi_deg`` is the azimuth, any finite value,
wrapped to [0, 360); ``theta_deg`` the elevation in [-90, 90]; the view
direction is ``(cos(theta) cos(phi), cos(theta) sin(phi), sin(theta))``.

Methods (`INTERPOLATORS`, keyed by the manifest's ``method``):

``bilinear`` (`GridInterpolator`)
    Training views on a full grid: ``n_phi`` equally spaced azimuths (any
    phase) times ``n_theta`` elevation rows (any increasing values), in any
    order. Bilinear in (phi, theta); phi wraps at 360. Beyond the outermost
    rows (towards the poles) theta is *clamped* to that row, so the value at
    a pole is the phi-interpolated outermost row (it depends on phi there);
    blending towards the pole average is the alternative to measure later.
    Four entries per query. (Manifest field ``poles``: ``"clamp"``, the only
    mode so far.)
``bicubic`` (`GridCubicInterpolator`)
    The same grids, interpolated with cubic Hermite splines whose slopes are
    the central differences of the neighbouring nodes (Catmull-Rom; on
    unevenly spaced theta rows the slope at row j is ``(y[j+1] - y[j-1]) /
    (t[j+1] - t[j-1])``): periodic in phi, and in theta the slope at the
    outermost rows is the one-sided difference. It reproduces linear
    functions, is exact at the nodes, C1 inside the grid and continuous
    across the phi seam. Weights are the tensor product of 4 weights in phi
    and 4 in theta (16 entries; some are negative, they still sum to 1).
    theta beyond the outermost rows is clamped as for ``bilinear``.
``barycentric`` (`TriangleInterpolator`)
    Scattered views: a triangulation of the unit directions (the spherical
    Delaunay triangulation = the convex hull's faces). Inside a triangle
    (a, b, c) the weights are the *gnomonic* barycentric coordinates: q is
    written as ``alpha a + beta b + gamma c`` (the point where the ray along
    q meets the triangle's plane), i.e. ``alpha : beta : gamma =
    det(q,b,c) : det(a,q,c) : det(a,b,q)``, normalised to sum 1. They are
    exact at vertices, non-negative inside, and continuous across edges (on
    an edge the third weight vanishes and the other two do not depend on
    it). A direction outside the triangulated region (a partial,
    hemisphere-only view set) is *clamped* to the nearest point of the
    region's boundary (nearest boundary arc or vertex, by angle) and takes
    that point's edge weights, so the result is continuous across the
    boundary. Three entries per query. (Manifest field ``outside``:
    ``"clamp"``.)

Each returns a fixed number ``m`` of entries per query (repeated indices with
zero weight where fewer are needed), so many queries vectorise. A method name
is never reused for different weights: a device that does not know a method
refuses the manifest (`interpolator_from_manifest`) instead of guessing.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from device_runtime.errors import DeviceError

__all__ = [
    "INTERPOLATORS",
    "MANIFEST_VERSION",
    "GridAxes",
    "GridCubicInterpolator",
    "GridInterpolator",
    "InterpolationError",
    "InterpolationWeights",
    "TriangleInterpolator",
    "detect_grid",
    "direction_from_angles",
    "interpolate",
    "interpolator_from_manifest",
]

#: Version of the interpolation manifest dictionaries.
MANIFEST_VERSION = 1
# Grid detection tolerance (degrees; a query this close to a grid node is that
# node) and snapping of near-zero triangle weights.
_GRID_TOL_DEG = 1e-6
_SNAP = 1e-9
# Queries per vectorised chunk of the triangle search (bounds scratch memory).
_CHUNK_ELEMENTS = 4_000_000
# Triangles tried around the nearest view before the full search.
_MAX_CANDIDATES = 32


class InterpolationError(DeviceError, ValueError):
    """Interpolation data or a query is malformed; the message names the value."""


class InterpolationWeights(NamedTuple):
    """Training views and blend weights for one query (or many).

    Attributes
    ----------
    indices : ndarray of shape (..., m), int32
        Training-view indices (rows of the score table).
    weights : ndarray of shape (..., m), float32
        Non-negative blend weights summing to 1 along the last axis.
    """

    indices: np.ndarray
    weights: np.ndarray


def direction_from_angles(phi_deg: Any, theta_deg: Any) -> np.ndarray:
    """Unit view directions from angles in degrees.

    Parameters
    ----------
    phi_deg, theta_deg : float or ndarray of shape (...)
        Azimuth and elevation in degrees (broadcast together).

    Returns
    -------
    ndarray of shape (..., 3), float64
        ``(cos(theta) cos(phi), cos(theta) sin(phi), sin(theta))``.
    """
    phi = np.radians(np.asarray(phi_deg, dtype=np.float64))
    theta = np.radians(np.asarray(theta_deg, dtype=np.float64))
    phi, theta = np.broadcast_arrays(phi, theta)
    ct = np.cos(theta)
    return np.stack([ct * np.cos(phi), ct * np.sin(phi), np.sin(theta)], axis=-1)


def interpolate(table: np.ndarray, indices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Blend rows of a table with interpolation weights.

    Parameters
    ----------
    table : ndarray of shape (n_views, K)
        E.g. the training scores (float32).
    indices : ndarray of shape (..., m), int
    weights : ndarray of shape (..., m), float

    Returns
    -------
    ndarray of shape (..., K)
        ``sum_i weights[..., i] * table[indices[..., i]]``, in the table's
        float dtype (float32 for float32 tables). Exact at training views
        (weights 1, 0, ...).
    """
    table = np.asarray(table)
    dtype = np.result_type(table.dtype, np.float32)
    rows = table[np.asarray(indices)].astype(dtype, copy=False)  # (..., m, K)
    w = np.asarray(weights, dtype=dtype)
    return np.einsum("...m,...mk->...k", w, rows)


def _check_query(phi_deg: Any, theta_deg: Any) -> tuple[np.ndarray, np.ndarray]:
    try:
        phi = np.asarray(phi_deg, dtype=np.float64)
        theta = np.asarray(theta_deg, dtype=np.float64)
        phi, theta = np.broadcast_arrays(phi, theta)
    except (TypeError, ValueError) as exc:
        raise InterpolationError(f"interpolation query: bad phi/theta: {exc}") from None
    if not (np.isfinite(phi).all() and np.isfinite(theta).all()):
        raise InterpolationError("interpolation query: phi_deg and theta_deg must be finite")
    if theta.size and (theta.min() < -90.0 - 1e-9 or theta.max() > 90.0 + 1e-9):
        bad = theta[(theta < -90.0) | (theta > 90.0)].flat[0]
        raise InterpolationError(f"interpolation query: theta_deg={bad:g} is outside [-90, 90]")
    return phi, np.clip(theta, -90.0, 90.0)


# --------------------------------------------------------------------------
# grids


class GridAxes(NamedTuple):
    """A detected full phi x theta grid of training views.

    Attributes
    ----------
    phi0_deg : float
        Azimuth of the first column, in [0, 360 / n_phi).
    n_phi : int
        Equally spaced azimuths: ``phi0_deg + i * 360 / n_phi``.
    theta_deg : ndarray of shape (n_theta,), float64
        Elevation rows, strictly increasing.
    view_index : ndarray of shape (n_phi, n_theta), int32
        Training-view index at each node.
    """

    phi0_deg: float
    n_phi: int
    theta_deg: np.ndarray
    view_index: np.ndarray


def _clusters(values: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Group sorted-able values within tol: (representatives, label per value)."""
    order = np.argsort(values, kind="stable")
    sorted_v = values[order]
    breaks = np.flatnonzero(np.diff(sorted_v) > tol) + 1
    labels_sorted = np.zeros(values.size, dtype=np.int64)
    labels_sorted[breaks] = 1
    labels_sorted = np.cumsum(labels_sorted)
    labels = np.empty_like(labels_sorted)
    labels[order] = labels_sorted
    reps = sorted_v[np.concatenate([[0], breaks])] if values.size else sorted_v
    return reps, labels


def detect_grid(phi_deg: Any, theta_deg: Any) -> tuple[GridAxes | None, str]:
    """Detect whether views form a full phi x theta grid (in any order).

    Parameters
    ----------
    phi_deg, theta_deg : array-like of shape (n_views,)

    Returns
    -------
    axes : GridAxes or None
        None when the views are not a full grid.
    reason : str
        Why not (empty when they are).
    """
    phi = np.mod(np.asarray(phi_deg, dtype=np.float64).ravel(), 360.0)
    theta = np.asarray(theta_deg, dtype=np.float64).ravel()
    n = phi.size
    if n == 0 or theta.size != n:
        return None, f"need equal, non-empty phi/theta lists (got {n} and {theta.size})"
    rows, row_of = _clusters(theta, _GRID_TOL_DEG)
    n_theta = rows.size
    if n % n_theta:
        return None, f"{n} views do not split into {n_theta} equal elevation rows"
    n_phi = n // n_theta
    step = 360.0 / n_phi
    phase = np.mod(phi, step)
    phase = np.where(phase > step - _GRID_TOL_DEG, phase - step, phase)
    phi0 = float(phase[0])
    if np.abs(phase - phi0).max() > _GRID_TOL_DEG:
        return None, f"azimuths are not {n_phi} equally spaced values ({step:g} deg apart)"
    col = np.rint((phi - phi0) / step).astype(np.int64) % n_phi
    flat = col * n_theta + row_of
    if np.bincount(flat, minlength=n).max() != 1:
        return None, f"some (phi, theta) node of the {n_phi}x{n_theta} grid is missing or repeated"
    view_index = np.empty(n, dtype=np.int32)
    view_index[flat] = np.arange(n, dtype=np.int32)
    phi0 = max(phi0, 0.0)  # within the tolerance of 0 when slightly negative
    return GridAxes(phi0, n_phi, rows.copy(), view_index.reshape(n_phi, n_theta)), ""


class GridInterpolator:
    """Bilinear interpolation in (phi, theta) over a full grid of training views.

    Parameters
    ----------
    phi_deg, theta_deg : array-like of shape (n_views,)
        The training views, in the score table's row order (any grid order).

    Raises
    ------
    InterpolationError
        The views are not a full phi x theta grid (the message says why).

    Notes
    -----
    phi wraps at 360 (continuous across the seam); theta beyond the outermost
    rows is clamped to them (see the module docstring).
    """

    method = "bilinear"
    entries = 4

    def __init__(self, phi_deg: Any, theta_deg: Any):
        axes, reason = detect_grid(phi_deg, theta_deg)
        if axes is None:
            raise InterpolationError(f"bilinear interpolation needs a full grid: {reason}")
        self._set_axes(axes)

    def _set_axes(self, axes: GridAxes) -> None:
        self.axes = axes
        self.n_views = int(axes.view_index.size)
        self._step = 360.0 / axes.n_phi

    def _locate(
        self, phi: np.ndarray, theta: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Grid cell and fractions of checked queries.

        Returns ``(i0, f, j0, g)``: the column ``i0`` (int64, in [0, n_phi)) left of the
        query and the fraction ``f`` in [0, 1) towards the next column (phi wraps); the row
        ``j0`` (int64) below and the fraction ``g`` in [0, 1] towards row ``j0 + 1`` (theta
        clamped to the outermost rows; ``j0 = 0, g = 0`` for a single row). Queries within
        the grid tolerance of a node get fraction 0 (or 1 on the last row), so every method
        is exact there.
        """
        axes = self.axes
        u = np.mod(phi - axes.phi0_deg, 360.0) / self._step
        i0 = np.floor(u)
        f = u - i0
        # queries within the grid tolerance of a node are that node (exact there)
        up = (1.0 - f) * self._step < _GRID_TOL_DEG
        i0 = np.where(up, i0 + 1.0, i0)
        f = np.where(up | (f * self._step < _GRID_TOL_DEG), 0.0, f)
        i0 = i0.astype(np.int64) % axes.n_phi
        rows = axes.theta_deg
        if rows.size == 1:
            return i0, f, np.zeros(theta.shape, dtype=np.int64), np.zeros(theta.shape)
        tc = np.clip(theta, rows[0], rows[-1])
        j0 = np.clip(np.searchsorted(rows, tc, side="right") - 1, 0, rows.size - 2)
        gap = rows[j0 + 1] - rows[j0]
        g = (tc - rows[j0]) / gap
        g = np.where(g * gap < _GRID_TOL_DEG, 0.0, g)
        g = np.where((1.0 - g) * gap < _GRID_TOL_DEG, 1.0, g)
        return i0, f, j0.astype(np.int64), g

    @classmethod
    def from_axes(cls, axes: GridAxes) -> GridInterpolator:
        """Build from explicit axes (checked)."""
        self = cls.__new__(cls)
        theta = np.asarray(axes.theta_deg, dtype=np.float64)
        index = np.asarray(axes.view_index)
        n_phi = int(axes.n_phi)
        if n_phi < 1 or theta.ndim != 1 or theta.size < 1:
            raise InterpolationError("grid axes: need n_phi >= 1 and at least one theta row")
        if not np.isfinite(theta).all() or np.any(np.diff(theta) <= 0):
            raise InterpolationError("grid axes: theta rows must be finite and increasing")
        if theta[0] < -90.0 or theta[-1] > 90.0:
            raise InterpolationError("grid axes: theta rows must lie in [-90, 90]")
        phi0 = float(axes.phi0_deg)
        if not (np.isfinite(phi0) and 0.0 <= phi0 < 360.0):
            raise InterpolationError(f"grid axes: phi0_deg={phi0!r} must be in [0, 360)")
        if index.shape != (n_phi, theta.size) or not np.issubdtype(index.dtype, np.integer):
            raise InterpolationError(
                f"grid axes: view_index must be integers of shape ({n_phi}, {theta.size}), "
                f"got {index.dtype} {index.shape}"
            )
        if not np.array_equal(np.sort(index.ravel()), np.arange(index.size)):
            raise InterpolationError("grid axes: view_index must be a permutation of the views")
        self._set_axes(GridAxes(phi0, n_phi, theta, index.astype(np.int32)))
        return self

    def weights(self, phi_deg: Any, theta_deg: Any) -> InterpolationWeights:
        """Training views and weights for query views.

        Parameters
        ----------
        phi_deg, theta_deg : float or ndarray of shape (...)

        Returns
        -------
        InterpolationWeights
            ``indices`` int32 and ``weights`` float32 of shape (..., 4).
        """
        phi, theta = _check_query(phi_deg, theta_deg)
        i0, f, j0, g = self._locate(phi, theta)
        n_phi = self.axes.n_phi
        i1 = (i0 + 1) % n_phi
        j1 = np.minimum(j0 + 1, self.axes.theta_deg.size - 1)
        vi = self.axes.view_index
        indices = np.stack([vi[i0, j0], vi[i1, j0], vi[i0, j1], vi[i1, j1]], axis=-1)
        weights = np.stack([(1 - f) * (1 - g), f * (1 - g), (1 - f) * g, f * g], axis=-1)
        return InterpolationWeights(indices.astype(np.int32), weights.astype(np.float32))

    def to_manifest(self) -> dict:
        """JSON/CBOR-able description (see `interpolator_from_manifest`)."""
        return {
            "method": self.method,
            "version": MANIFEST_VERSION,
            "n_views": self.n_views,
            "phi0_deg": float(self.axes.phi0_deg),
            "n_phi": int(self.axes.n_phi),
            "theta_deg": [float(t) for t in self.axes.theta_deg],
            "view_index": [int(i) for i in self.axes.view_index.ravel()],
            "poles": "clamp",
        }

    @classmethod
    def from_manifest(cls, manifest: Mapping) -> GridInterpolator:
        """Rebuild from `to_manifest` output; malformed data -> InterpolationError."""
        _check_option(manifest, "poles", ("clamp",))
        n_phi = _field(manifest, "n_phi", int)
        theta = _float_array(manifest, "theta_deg")
        index = _int_array(manifest, "view_index")
        if index.size != n_phi * theta.size:
            raise InterpolationError(
                f"interpolation manifest: view_index has {index.size} entries, expected "
                f"n_phi * n_theta = {n_phi * theta.size}"
            )
        self = cls.from_axes(
            GridAxes(
                _field(manifest, "phi0_deg", float),
                n_phi,
                theta,
                index.reshape(n_phi, theta.size) if n_phi > 0 else index,
            )
        )
        _check_n_views(manifest, self.n_views)
        return self


class GridCubicInterpolator(GridInterpolator):
    """Bicubic (Catmull-Rom) interpolation in (phi, theta) over a full grid of training views.

    Same grids, checks, clamping and manifest fields as `GridInterpolator` (manifest
    ``method`` ``"bicubic"``); 16 entries per query: 4 columns (periodic in phi) times 4
    rows. See the module docstring for the slopes.

    Parameters
    ----------
    phi_deg, theta_deg : array-like of shape (n_views,)
        The training views, in the score table's row order (any grid order).
    """

    method = "bicubic"
    entries = 16

    def weights(self, phi_deg: Any, theta_deg: Any) -> InterpolationWeights:
        """Training views and weights for query views.

        Parameters
        ----------
        phi_deg, theta_deg : float or ndarray of shape (...)

        Returns
        -------
        InterpolationWeights
            ``indices`` int32 and ``weights`` float32 of shape (..., 16): column-major over
            the 4 columns ``i0 - 1 .. i0 + 2`` and the 4 rows ``j0 - 1 .. j0 + 2`` (clamped
            at the outermost rows, so indices may repeat). Weights sum to 1; some are
            negative.
        """
        phi, theta = _check_query(phi_deg, theta_deg)
        i0, f, j0, g = self._locate(phi, theta)
        axes = self.axes
        n_phi = axes.n_phi
        cols = (i0[..., None] + np.arange(-1, 3)) % n_phi  # (..., 4)
        f2, f3 = f * f, f * f * f
        wphi = 0.5 * np.stack(
            [-f + 2 * f2 - f3, 2 - 5 * f2 + 3 * f3, f + 4 * f2 - 3 * f3, f3 - f2], axis=-1
        )
        rows_t = axes.theta_deg
        last = rows_t.size - 1
        if last == 0:
            rows = np.zeros((*theta.shape, 4), dtype=np.int64)
            wtheta = np.zeros((*theta.shape, 4))
            wtheta[..., 1] = 1.0
        else:
            j1 = j0 + 1
            jm, jp = np.maximum(j0 - 1, 0), np.minimum(j1 + 1, last)
            h = rows_t[j1] - rows_t[j0]
            # slopes times h, as multiples of node differences: one-sided at the ends
            a = h / (rows_t[j1] - rows_t[jm])
            b = h / (rows_t[jp] - rows_t[j0])
            g2, g3 = g * g, g * g * g
            h00, h10 = 2 * g3 - 3 * g2 + 1, g3 - 2 * g2 + g
            h01, h11 = 3 * g2 - 2 * g3, g3 - g2
            rows = np.stack([jm, j0, j1, jp], axis=-1)
            wtheta = np.stack([-a * h10, h00 - b * h11, h01 + a * h10, b * h11], axis=-1)
        vi = axes.view_index
        indices = vi[cols[..., :, None], rows[..., None, :]]  # (..., 4, 4)
        weights = wphi[..., :, None] * wtheta[..., None, :]
        shape = (*phi.shape, 16)
        return InterpolationWeights(
            indices.reshape(shape).astype(np.int32), weights.reshape(shape).astype(np.float32)
        )


# --------------------------------------------------------------------------
# triangulations


class TriangleInterpolator:
    """Barycentric interpolation on a spherical triangulation of the training views.

    Parameters
    ----------
    directions : ndarray of shape (n_views, 3)
        Unit view directions (normalised here) in the score table's order.
    triangles : ndarray of shape (n_triangles, 3), int
        Vertex indices; each triangle spans less than a hemisphere. The
        orientation is fixed here (counter-clockwise seen from outside).

    Raises
    ------
    InterpolationError
        Bad shapes, indices out of range, non-finite or zero directions, or a
        degenerate triangle.

    Notes
    -----
    The containing triangle is searched first among the triangles around the
    nearest training view (almost always one of them), then among all
    triangles (one small matrix product per query), then the boundary clamp
    applies. On a shared edge or vertex the lowest-numbered candidate wins;
    all of them give the same weights there up to round-off.
    """

    method = "barycentric"
    entries = 3

    def __init__(self, directions: Any, triangles: Any):
        dirs = np.asarray(directions, dtype=np.float64)
        if dirs.ndim != 2 or dirs.shape[1] != 3 or dirs.shape[0] < 3:
            raise InterpolationError(
                f"triangle interpolation: directions must be (n_views >= 3, 3), got {dirs.shape}"
            )
        norms = np.linalg.norm(dirs, axis=1)
        if not np.isfinite(dirs).all() or norms.min() <= 0:
            raise InterpolationError("triangle interpolation: directions must be finite, non-zero")
        dirs = dirs / norms[:, None]
        tri = np.asarray(triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] < 1:
            raise InterpolationError(
                f"triangle interpolation: triangles must be (n_triangles >= 1, 3), got {tri.shape}"
            )
        if not np.issubdtype(tri.dtype, np.integer):
            raise InterpolationError(
                f"triangle interpolation: triangles must be integers, got {tri.dtype}"
            )
        if tri.min() < 0 or tri.max() >= dirs.shape[0]:
            raise InterpolationError(
                f"triangle interpolation: triangle indices must be in [0, {dirs.shape[0]}), "
                f"got [{tri.min()}, {tri.max()}]"
            )
        tri = tri.astype(np.int64)
        a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        if np.abs(det).min() < 1e-14:
            bad = int(np.argmin(np.abs(det)))
            raise InterpolationError(
                f"triangle interpolation: triangle {bad} {tri[bad].tolist()} is degenerate"
            )
        flip = det < 0
        tri[flip] = tri[flip][:, [0, 2, 1]]
        a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
        self.directions = dirs
        self.triangles = tri.astype(np.int32)
        self.n_views = dirs.shape[0]
        # rows of E[t] give det(q,b,c), det(a,q,c), det(a,b,q) as E[t] @ q
        self._edges = np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=1)
        self._flat = self._edges.reshape(-1, 3)
        self._boundary = self._boundary_edges(tri)
        # the first triangles around each view, ascending, -1 padded:
        # (n_views, <= _MAX_CANDIDATES); a view with more (a fan over a polar
        # cap) keeps the first ones, the full search covers the rest
        vert = tri.ravel()
        owner = np.repeat(np.arange(tri.shape[0]), 3)
        order = np.lexsort((owner, vert))
        vert, owner = vert[order], owner[order]
        degree = np.bincount(vert, minlength=self.n_views)
        start = np.concatenate([[0], np.cumsum(degree)[:-1]])
        slot = np.arange(vert.size) - start[vert]
        width = int(min(max(1, degree.max()), _MAX_CANDIDATES))
        keep = slot < width
        self._incident = np.full((self.n_views, width), -1, dtype=np.int64)
        self._incident[vert[keep], slot[keep]] = owner[keep]

    @staticmethod
    def _boundary_edges(tri: np.ndarray) -> np.ndarray:
        """Undirected edges used by exactly one triangle, (n_edges, 2) int64."""
        edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        edges = np.sort(edges, axis=1)
        uniq, counts = np.unique(edges, axis=0, return_counts=True)
        return uniq[counts == 1]

    @classmethod
    def from_angles(cls, phi_deg: Any, theta_deg: Any, triangles: Any) -> TriangleInterpolator:
        """Build from view angles in degrees (see `direction_from_angles`)."""
        return cls(direction_from_angles(phi_deg, theta_deg), triangles)

    def weights(self, phi_deg: Any, theta_deg: Any) -> InterpolationWeights:
        """Training views and weights for query views.

        Parameters
        ----------
        phi_deg, theta_deg : float or ndarray of shape (...)

        Returns
        -------
        InterpolationWeights
            ``indices`` int32 and ``weights`` float32 of shape (..., 3).
        """
        phi, theta = _check_query(phi_deg, theta_deg)
        q = direction_from_angles(phi, theta).reshape(-1, 3)
        idx = np.empty((q.shape[0], 3), dtype=np.int32)
        wts = np.empty((q.shape[0], 3), dtype=np.float64)
        n_tri = self.triangles.shape[0]
        chunk = max(1, _CHUNK_ELEMENTS // (3 * n_tri))
        for s in range(0, q.shape[0], chunk):
            self._inside(q[s : s + chunk], idx[s : s + chunk], wts[s : s + chunk])
        shape = (*phi.shape, 3)
        return InterpolationWeights(idx.reshape(shape), wts.astype(np.float32).reshape(shape))

    def _inside(self, q: np.ndarray, idx: np.ndarray, wts: np.ndarray) -> None:
        # 1) the triangles around the nearest training view (almost always enough)
        nearest = np.argmax(q @ self.directions.T, axis=1)
        cand = self._incident[nearest]  # (nq, max_degree), -1 padded
        dets = np.einsum("qcij,qj->qci", self._edges[np.maximum(cand, 0)], q)
        found, tri, w = _first_containing(dets, cand >= 0)
        tri = np.take_along_axis(cand, tri[:, None], axis=1)[:, 0]
        hit = np.flatnonzero(found)
        idx[hit] = self.triangles[tri[hit]]
        wts[hit] = w[hit]
        # 2) the rest: every triangle
        rest = np.flatnonzero(~found)
        if rest.size:
            dets = (q[rest] @ self._flat.T).reshape(rest.size, -1, 3)  # (nr, t, 3)
            found, tri, w = _first_containing(dets, None)
            hit = rest[found]
            idx[hit] = self.triangles[tri[found]]
            wts[hit] = w[found]
            missing = rest[~found]
            # 3) outside every triangle: clamp to the boundary
            if missing.size:
                self._clamp(q[missing], idx, wts, missing)

    def _clamp(self, q: np.ndarray, idx: np.ndarray, wts: np.ndarray, where: np.ndarray) -> None:
        """Weights at the nearest boundary point for directions outside every triangle."""
        if self._boundary.shape[0] == 0:  # a closed triangulation covers the sphere
            raise InterpolationError("triangle interpolation: query outside a closed mesh")
        ea = self.directions[self._boundary[:, 0]]  # (e, 3)
        eb = self.directions[self._boundary[:, 1]]
        normal = np.cross(ea, eb)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        # projection of each query onto each edge's great circle
        p = q[:, None, :] - (q @ normal.T)[..., None] * normal[None]  # (nq, e, 3)
        pn = np.linalg.norm(p, axis=2)
        with np.errstate(invalid="ignore", divide="ignore"):
            p = p / pn[..., None]
            alpha = np.einsum("qej,ej->qe", np.cross(p, eb[None]), normal)
            beta = np.einsum("qej,ej->qe", np.cross(ea[None], p), normal)
            on_arc = (pn > 1e-12) & (alpha >= 0) & (beta >= 0)
            cos_arc = np.where(on_arc, np.einsum("qej,qj->qe", p, q), -np.inf)
        cos_a = q @ ea.T
        cos_b = q @ eb.T
        best = np.stack([cos_arc, cos_a, cos_b], axis=2).reshape(q.shape[0], -1)
        pick = np.argmax(best, axis=1)
        edge, kind = pick // 3, pick % 3
        rows = np.arange(q.shape[0])
        va, vb = self._boundary[edge, 0], self._boundary[edge, 1]
        al, be = alpha[rows, edge], beta[rows, edge]
        with np.errstate(invalid="ignore", divide="ignore"):
            s = al + be
            wa = np.where(kind == 0, al / s, np.where(kind == 1, 1.0, 0.0))
        wb = 1.0 - wa
        idx[where] = np.stack([va, vb, va], axis=1)
        wts[where] = _clean(np.stack([wa, wb, np.zeros_like(wa)], axis=1))

    def to_manifest(self) -> dict:
        """JSON/CBOR-able description (see `interpolator_from_manifest`)."""
        return {
            "method": self.method,
            "version": MANIFEST_VERSION,
            "n_views": int(self.n_views),
            "directions": [float(v) for v in self.directions.ravel()],
            "triangles": [int(i) for i in self.triangles.ravel()],
            "outside": "clamp",
        }

    @classmethod
    def from_manifest(cls, manifest: Mapping) -> TriangleInterpolator:
        """Rebuild from `to_manifest` output; malformed data -> InterpolationError."""
        _check_option(manifest, "outside", ("clamp",))
        dirs = _float_array(manifest, "directions")
        tri = _int_array(manifest, "triangles")
        if dirs.size % 3 or tri.size % 3:
            raise InterpolationError(
                "interpolation manifest: directions and triangles must have 3 entries per item"
            )
        self = cls(dirs.reshape(-1, 3), tri.reshape(-1, 3))
        _check_n_views(manifest, self.n_views)
        return self


def _first_containing(
    dets: np.ndarray, valid: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First candidate triangle containing each query.

    dets (nq, c, 3) are det(q,b,c), det(a,q,c), det(a,b,q) per candidate.
    Returns found (nq,) bool, the candidate position (nq,) and the clean
    weights (nq, 3) (rows of queries not found are undefined).
    """
    total = dets.sum(axis=2)
    ok = (total > 0) & (dets.min(axis=2) >= -_SNAP * total)
    if valid is not None:
        ok &= valid
    found = ok.any(axis=1)
    first = np.argmax(ok, axis=1)
    rows = np.arange(dets.shape[0])
    sel = dets[rows, first]
    tot = np.where(found, total[rows, first], 1.0)
    w = np.zeros((dets.shape[0], 3))
    w[found] = _clean(sel[found] / tot[found, None])
    return found, first, w


def _clean(w: np.ndarray) -> np.ndarray:
    """Clip tiny negatives, snap near-zero weights to 0 and renormalise."""
    w = np.where(w < _SNAP, 0.0, w)
    return w / w.sum(axis=1, keepdims=True)


# --------------------------------------------------------------------------
# manifests

#: method name -> interpolator class (each has ``from_manifest``).
INTERPOLATORS: dict[str, type] = {
    GridInterpolator.method: GridInterpolator,
    GridCubicInterpolator.method: GridCubicInterpolator,
    TriangleInterpolator.method: TriangleInterpolator,
}


def interpolator_from_manifest(
    manifest: Mapping,
) -> GridInterpolator | GridCubicInterpolator | TriangleInterpolator:
    """Rebuild the interpolator a host described with ``to_manifest()``.

    Parameters
    ----------
    manifest : mapping
        ``{"method": ..., "version": 1, ...}`` as written by ``to_manifest``.

    Raises
    ------
    InterpolationError
        Unknown method or version, or malformed fields.
    """
    if not isinstance(manifest, Mapping):
        raise InterpolationError(
            f"interpolation manifest must be a mapping, got {type(manifest).__name__}"
        )
    method = manifest.get("method")
    if method not in INTERPOLATORS:
        raise InterpolationError(
            f"interpolation manifest: method={method!r} is unknown; known: {sorted(INTERPOLATORS)}"
        )
    version = manifest.get("version")
    if version != MANIFEST_VERSION:
        raise InterpolationError(
            f"interpolation manifest: version {version!r} is not supported "
            f"(supported: {MANIFEST_VERSION})"
        )
    return INTERPOLATORS[method].from_manifest(manifest)


def _check_option(manifest: Mapping, key: str, supported: tuple[str, ...]) -> None:
    value = manifest.get(key, supported[0])
    if value not in supported:
        raise InterpolationError(
            f"interpolation manifest: {key}={value!r} is not supported "
            f"(supported: {list(supported)})"
        )


def _field(manifest: Mapping, key: str, kind: type) -> Any:
    value = manifest.get(key)
    ok = isinstance(value, (int, float) if kind is float else int) and not isinstance(value, bool)
    if not ok:
        raise InterpolationError(f"interpolation manifest: {key}={value!r} must be {kind.__name__}")
    return kind(value)


def _float_array(manifest: Mapping, key: str) -> np.ndarray:
    value = manifest.get(key)
    if not isinstance(value, (list, tuple)) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    ):
        raise InterpolationError(f"interpolation manifest: {key} must be a list of numbers")
    arr = np.asarray(value, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise InterpolationError(f"interpolation manifest: {key} has non-finite values")
    return arr


def _int_array(manifest: Mapping, key: str) -> np.ndarray:
    value = manifest.get(key)
    if not isinstance(value, (list, tuple)) or not all(
        isinstance(v, int) and not isinstance(v, bool) for v in value
    ):
        raise InterpolationError(f"interpolation manifest: {key} must be a list of integers")
    arr = np.asarray(value, dtype=np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= 2**31):
        raise InterpolationError(f"interpolation manifest: {key} has out-of-range values")
    return arr


def _check_n_views(manifest: Mapping, n_views: int) -> None:
    declared = manifest.get("n_views")
    if declared != n_views:
        raise InterpolationError(
            f"interpolation manifest: n_views={declared!r} but the data describe {n_views} views"
        )
