"""Score interpolation: scores of novel views from the training views' scores.

The training views' scores are a function on the sphere of view directions.
`ScoreInterpolator` picks a method (`METHODS`), builds its data on the host
(scipy's convex hull for scattered view sets) and evaluates it with
`device_runtime.interpolation`, the same pure-numpy code a standalone device
runs from the manifest (`ScoreInterpolator.to_manifest`), so host and device
agree bit for bit.

Methods (see `device_runtime.interpolation` for the exact rules):

``bilinear``
    Full ``phi x theta`` grid view sets (e.g. ``grid:100x15``), in any order:
    bilinear in (phi, theta), phi wrapping at 360, theta clamped beyond the
    outermost rows.
``bicubic``
    The same grids: cubic Hermite (Catmull-Rom) in phi (periodic) and theta
    (central-difference slopes, one-sided at the outermost rows), 16 views
    per query. Exact at training views, C1 inside the grid.
``barycentric``
    Any view set: gnomonic barycentric weights on the spherical Delaunay
    triangulation (the faces of the convex hull of the unit directions whose
    plane has the origin strictly on the inner side; for a partial view set
    the hull's closing faces are dropped and directions outside are clamped
    to the nearest boundary point).
``auto``
    `GRID_DEFAULT` when the views form a full grid, else ``barycentric``.
    (Chosen by measurement on held-out views: ``docs/design-notes.md``.)

Examples
--------
>>> import numpy as np
>>> phi = np.repeat(np.arange(8) * 45.0, 3)
>>> theta = np.tile([-60.0, 0.0, 60.0], 8)
>>> scores = np.stack([phi, theta], axis=1).astype(np.float32)
>>> interp = ScoreInterpolator(phi, theta, scores)
>>> interp.method_
'bilinear'
>>> interp(22.5, 30.0).tolist()
[22.5, 30.0]
>>> cubic = ScoreInterpolator(phi, theta, scores, method="bicubic")
>>> cubic(67.5, 30.0).tolist()  # cubic reproduces linear functions away from the phi seam
[67.5, 30.0]
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from device_runtime.interpolation import (
    GridCubicInterpolator,
    GridInterpolator,
    InterpolationError,
    InterpolationWeights,
    TriangleInterpolator,
    detect_grid,
    direction_from_angles,
    interpolate,
    interpolator_from_manifest,
)
from host.errors import ViewSpecError

__all__ = [
    "GRID_DEFAULT",
    "METHODS",
    "ScoreInterpolator",
    "triangulate_views",
]


def triangulate_views(phi_deg: Any, theta_deg: Any) -> np.ndarray:
    """Spherical Delaunay triangulation of view directions.

    Parameters
    ----------
    phi_deg, theta_deg : array-like of shape (n_views,)
        View angles in degrees.

    Returns
    -------
    triangles : ndarray of shape (n_triangles, 3), int32
        Vertex indices, counter-clockwise seen from outside, each row rotated
        to start at its smallest index, rows sorted (deterministic).

    Raises
    ------
    ViewSpecError
        Fewer than 3 views, repeated directions, or views that span no
        3-D hull (all on one great circle).

    Notes
    -----
    The faces of the convex hull of points on a sphere are the spherical
    Delaunay triangles, except for faces whose plane passes through or
    beyond the origin: those close the hull over an uncovered region (a
    hemisphere-only view set) and are dropped. Co-circular views (grid rows)
    make coplanar faces that qhull merges and re-triangulates; zero-area
    triangles are dropped.
    """
    from scipy.spatial import ConvexHull, QhullError

    dirs = direction_from_angles(phi_deg, theta_deg).reshape(-1, 3)
    n = dirs.shape[0]
    if n < 3:
        raise ViewSpecError(f"barycentric interpolation needs at least 3 views, got {n}")
    _check_distinct(dirs)
    try:
        hull = ConvexHull(dirs)
    except QhullError:
        raise ViewSpecError(
            f"cannot triangulate the {n} view directions: they span no 3-D hull "
            "(all on one great circle?); use a view set with several elevations"
        ) from None
    tri = hull.simplices.astype(np.int64)
    offsets = hull.equations[:, 3]  # normal . x + offset <= 0 inside
    tri = tri[offsets < -1e-9]
    a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    tri = tri[np.abs(det) > 1e-12]
    det = det[np.abs(det) > 1e-12]
    tri[det < 0] = tri[det < 0][:, [0, 2, 1]]
    if tri.shape[0] == 0:
        raise ViewSpecError(f"cannot triangulate the {n} view directions: no spherical triangles")
    start = np.argmin(tri, axis=1)
    roll = (np.arange(3)[None, :] + start[:, None]) % 3
    tri = np.take_along_axis(tri, roll, axis=1)
    tri = tri[np.lexsort(tri.T[::-1])]
    unused = np.setdiff1d(np.arange(n), tri.ravel())
    if unused.size:
        raise ViewSpecError(
            f"views {unused[:5].tolist()} are not vertices of the view triangulation"
        )
    return tri.astype(np.int32)


def _check_distinct(dirs: np.ndarray) -> None:
    key = np.round(dirs, 9)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    if counts.max() > 1:
        dup = int(first[np.argmax(counts)])
        same = np.flatnonzero((key == key[dup]).all(axis=1))
        raise ViewSpecError(
            f"views {same[:5].tolist()} have the same direction; interpolation needs "
            "distinct views (drop the repeats)"
        )


def _build_bilinear(phi_deg: np.ndarray, theta_deg: np.ndarray) -> GridInterpolator:
    axes, reason = detect_grid(phi_deg, theta_deg)
    if axes is None:
        raise ViewSpecError(
            f"method='bilinear' needs a full phi x theta grid of views: {reason}; "
            "use method='barycentric' or 'auto'"
        )
    return GridInterpolator.from_axes(axes)


def _build_bicubic(phi_deg: np.ndarray, theta_deg: np.ndarray) -> GridCubicInterpolator:
    axes, reason = detect_grid(phi_deg, theta_deg)
    if axes is None:
        raise ViewSpecError(
            f"method='bicubic' needs a full phi x theta grid of views: {reason}; "
            "use method='barycentric' or 'auto'"
        )
    return GridCubicInterpolator.from_axes(axes)


def _build_barycentric(phi_deg: np.ndarray, theta_deg: np.ndarray) -> TriangleInterpolator:
    return TriangleInterpolator.from_angles(
        phi_deg, theta_deg, triangulate_views(phi_deg, theta_deg)
    )


#: method name -> builder(phi_deg (n,), theta_deg (n,)) returning a device-side
#: interpolator (with ``weights``, ``entries``, ``to_manifest``).
METHODS: dict[str, Callable[[np.ndarray, np.ndarray], Any]] = {
    "bilinear": _build_bilinear,
    "bicubic": _build_bicubic,
    "barycentric": _build_barycentric,
}

#: The method ``auto`` uses on full grids. Measured on held-out views of the tooth and the
#: head at 256 and 512 (docs/design-notes.md): ``bicubic`` lowers object-pixel FLIP by
#: 1-4.5 % but never raises object-pixel SSIM (the issue's target measure; -0.006 to +0.0001),
#: and both are 0.2-0.3 SSIM below the oracle; ``bilinear`` stays, at 4 rows instead of 16.
GRID_DEFAULT = "bilinear"


class ScoreInterpolator:
    """Interpolate training scores at novel view directions.

    Parameters
    ----------
    phi_deg, theta_deg : array-like of shape (n_views,)
        Training view angles in degrees (theta in [-90, 90]), in the row
        order of ``scores``.
    scores : ndarray of shape (n_views, K)
        Training scores (e.g. ``CellEigenspace.scores_``); kept as float32.
    method : {"auto", "bilinear", "bicubic", "barycentric"}
        See the module docstring; ``auto`` picks `GRID_DEFAULT` for a full grid.

    Attributes
    ----------
    method_ : str
        The method used.
    interpolator_ : GridInterpolator, GridCubicInterpolator or TriangleInterpolator
        The device-side evaluator.
    scores : ndarray of shape (n_views, K), float32

    Raises
    ------
    ValueError
        Bad shapes, non-finite values, theta outside [-90, 90], unknown method.
    ViewSpecError
        The view set does not suit the method (not a grid for ``bilinear``,
        repeated or degenerate directions for ``barycentric``).
    """

    def __init__(self, phi_deg: Any, theta_deg: Any, scores: Any, *, method: str = "auto"):
        phi = np.asarray(phi_deg, dtype=np.float64)
        theta = np.asarray(theta_deg, dtype=np.float64)
        table = np.asarray(scores)
        if phi.ndim != 1 or theta.shape != phi.shape or phi.size < 1:
            raise ValueError(
                f"ScoreInterpolator: phi_deg and theta_deg must be 1-D of equal, non-zero "
                f"length, got {phi.shape} and {theta.shape}"
            )
        if not (np.isfinite(phi).all() and np.isfinite(theta).all()):
            raise ValueError("ScoreInterpolator: phi_deg and theta_deg must be finite")
        if theta.min() < -90.0 or theta.max() > 90.0:
            raise ValueError(
                f"ScoreInterpolator: theta_deg must lie in [-90, 90], got "
                f"[{theta.min():g}, {theta.max():g}]"
            )
        if table.ndim != 2 or table.shape[0] != phi.size:
            raise ValueError(
                f"ScoreInterpolator: scores must be (n_views={phi.size}, K), got {table.shape}"
            )
        if not np.issubdtype(table.dtype, np.number) or not np.isfinite(table).all():
            raise ValueError("ScoreInterpolator: scores must be finite numbers")
        if method != "auto" and method not in METHODS:
            raise ValueError(
                f"ScoreInterpolator: method={method!r} is unknown; use one of {['auto', *METHODS]}"
            )
        if method == "auto":
            method = GRID_DEFAULT if detect_grid(phi, theta)[0] is not None else "barycentric"
        self.method_ = method
        self.interpolator_ = METHODS[method](phi, theta)
        self.scores = np.ascontiguousarray(table, dtype=np.float32)

    def __repr__(self) -> str:
        return (
            f"ScoreInterpolator(n_views={self.scores.shape[0]}, K={self.scores.shape[1]}, "
            f"method_={self.method_!r})"
        )

    def weights(self, phi_deg: Any, theta_deg: Any) -> InterpolationWeights:
        """Training views and blend weights for query views.

        Parameters
        ----------
        phi_deg, theta_deg : float or ndarray of shape (...)

        Returns
        -------
        InterpolationWeights
            ``indices`` int32 and ``weights`` float32, shape (..., m).

        Raises
        ------
        ValueError
            Non-finite angles or theta outside [-90, 90].
        """
        return self.interpolator_.weights(phi_deg, theta_deg)

    def __call__(self, phi_deg: Any, theta_deg: Any) -> np.ndarray:
        """Interpolated scores.

        Parameters
        ----------
        phi_deg, theta_deg : float or ndarray of shape (...)

        Returns
        -------
        ndarray of shape (..., K), float32
            ``(K,)`` for scalar angles.
        """
        idx, w = self.weights(phi_deg, theta_deg)
        return interpolate(self.scores, idx, w)

    def to_manifest(self) -> dict:
        """JSON/CBOR-able interpolation data for the eigenspace image.

        Returns
        -------
        dict
            ``{"method", "version", "n_views", ...}``: grid axes and the view
            index table for ``bilinear``, unit directions and triangles for
            ``barycentric``. The score table is not included (it is a section
            of its own). `device_runtime.interpolation.interpolator_from_manifest`
            rebuilds the evaluator.
        """
        return self.interpolator_.to_manifest()

    @classmethod
    def from_manifest(cls, manifest: Mapping, scores: Any) -> ScoreInterpolator:
        """Rebuild from a manifest written by `to_manifest` (no re-triangulation).

        Raises
        ------
        ValueError
            (`InterpolationError`) malformed manifest, or one that does not
            match the score table.
        """
        self = cls.__new__(cls)
        interp = interpolator_from_manifest(manifest)
        table = np.ascontiguousarray(scores, dtype=np.float32)
        if table.ndim != 2 or table.shape[0] != interp.n_views:
            raise InterpolationError(
                f"interpolation manifest describes {interp.n_views} views but the score "
                f"table is {table.shape}"
            )
        self.method_ = interp.method
        self.interpolator_ = interp
        self.scores = table
        return self
