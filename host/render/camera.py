"""Cameras and view sets: where the ray-caster looks from.

Conventions (ParaView's phi-theta orbit, up = +z)
-------------------------------------------------
* ``phi_deg`` is the azimuth in degrees, normalised to ``[0, 360)``;
  ``theta_deg`` is the elevation in ``[-90, 90]`` (+90 looks down from +z).
* An orbit camera for view ``(phi, theta)`` sits at
  ``center + d * (cos(theta)cos(phi), cos(theta)sin(phi), sin(theta))`` and
  looks at ``center``.
* Its up vector is +z projected orthogonal to the view direction, which is
  the unit tangent of increasing elevation,
  ``e_theta = (-sin(theta)cos(phi), -sin(theta)sin(phi), cos(theta))``.
  That formula is used for every theta, so at the poles (theta = +-90, where
  +z is parallel to the view direction) the up vector is
  ``(-+cos(phi), -+sin(phi), 0)``: the limit of the nearby views at the same
  phi, continuous in theta.
* Perspective: the distance ``d = radius / sin(fov/2)`` makes the bounding
  sphere exactly fill the vertical field of view (its silhouette touches the
  top and bottom image rows' outer edges). Orthographic: the camera sits at
  the same distance and the view is ``ortho_height_mm = 2 * radius`` high.
* Images: row 0 is the top (towards ``up``), column 0 the left; pixel
  ``(row, col)`` is sampled at its centre. The horizontal field of view
  follows from the aspect ratio ``width / height``.

View sets
---------
``parse_view_set`` understands

* ``grid:NPHIxNTHETA`` -- ``phi_i = i*360/NPHI`` (i = 0..NPHI-1) and
  ``theta_j = -90 + (j + 0.5)*180/NTHETA`` (centred, poles excluded); the
  paper's ``grid:100x15`` is 3.6 deg x 12 deg with theta = -84..84. Order:
  **phi outer, theta inner** -- view ``i*NTHETA + j`` is ``(phi_i, theta_j)``,
  so per-view arrays reshape to ``grid_shape = (NPHI, NTHETA)`` in C order.
* ``fibonacci:N`` -- the golden-spiral lattice: ``z_k = 1 - (2k+1)/N``,
  ``theta_k = asin(z_k)``, ``phi_k = k * 137.507...deg`` (mod 360), k = 0..N-1
  (from the north pole down).
* ``random:N[:SEED]`` -- uniform on the sphere (z uniform in [-1, 1], phi
  uniform in [0, 360)) from ``numpy.random.default_rng(SEED)``, default seed 0.
* ``list:P,T;P,T;...`` -- explicit ``phi,theta`` pairs in degrees.
* a path to a CSV file with a header naming ``phi`` and ``theta`` columns
  (other columns are ignored) -- e.g. a Cinema database's ``data.csv``.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from host.errors import ViewSpecError

__all__ = [
    "MAX_VIEWS",
    "PROJECTIONS",
    "VIEW_SET_FORMS",
    "Camera",
    "View",
    "ViewSet",
    "orbit_camera",
    "parse_view_set",
]

PROJECTIONS = ("perspective", "orthographic")
MAX_VIEWS = 1_000_000
VIEW_SET_FORMS = (
    "grid:NPHIxNTHETA, fibonacci:N, random:N[:SEED], list:P,T;P,T;... "
    "or the path of a CSV file with phi,theta columns"
)
GOLDEN_ANGLE_DEG = 180.0 * (3.0 - math.sqrt(5.0))  # 137.50776... degrees


def _normalise_phi(phi_deg: float) -> float:
    phi = math.fmod(float(phi_deg), 360.0)
    if phi < 0.0:
        phi += 360.0
    if phi >= 360.0:  # -tiny + 360 rounds to 360.0
        phi = 0.0
    return phi + 0.0  # turns -0.0 into 0.0


@dataclass(frozen=True)
class View:
    """One viewing direction on the sphere.

    Parameters
    ----------
    phi_deg : float
        Azimuth in degrees; stored normalised to ``[0, 360)``.
    theta_deg : float
        Elevation in degrees, within ``[-90, 90]``.
    """

    phi_deg: float
    theta_deg: float

    def __post_init__(self) -> None:
        phi, theta = float(self.phi_deg), float(self.theta_deg)
        if not (math.isfinite(phi) and math.isfinite(theta)):
            raise ValueError(f"view phi_deg={phi}, theta_deg={theta}: angles must be finite")
        if not -90.0 <= theta <= 90.0:
            raise ValueError(f"view theta_deg={theta} must be within [-90, 90]")
        object.__setattr__(self, "phi_deg", _normalise_phi(phi))
        object.__setattr__(self, "theta_deg", theta + 0.0)


@dataclass(frozen=True)
class ViewSet:
    """An ordered set of views, as parsed from a spec string.

    Parameters
    ----------
    spec : str
        The specification it was parsed from (a path for CSV files).
    kind : {"grid", "fibonacci", "random", "list", "csv"}
    views : tuple of View
        In set order (grids: phi outer, theta inner).
    grid_shape : (n_phi, n_theta) or None
        For grids: per-view arrays reshape to this in C order.
    """

    spec: str
    kind: str
    views: tuple[View, ...]
    grid_shape: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self) -> Iterator[View]:
        return iter(self.views)

    def angles_deg(self) -> np.ndarray:
        """All views as float64 array of shape (n_views, 2): columns ``phi_deg, theta_deg``."""
        return np.array([(v.phi_deg, v.theta_deg) for v in self.views], dtype=np.float64)

    def grid_axes_deg(self) -> tuple[np.ndarray, np.ndarray]:
        """For grids: ``(phi_values_deg (n_phi,), theta_values_deg (n_theta,))``, float64."""
        if self.grid_shape is None:
            raise ValueError(f"view set {self.spec!r} is a {self.kind} set, not a grid")
        n_phi, n_theta = self.grid_shape
        return _grid_phi_deg(n_phi), _grid_theta_deg(n_theta)


def _grid_phi_deg(n_phi: int) -> np.ndarray:
    return np.arange(n_phi, dtype=np.float64) * (360.0 / n_phi)


def _grid_theta_deg(n_theta: int) -> np.ndarray:
    return -90.0 + (np.arange(n_theta, dtype=np.float64) + 0.5) * (180.0 / n_theta)


def _bad(spec: str, problem: str) -> ViewSpecError:
    return ViewSpecError(f"view set {spec!r}: {problem}; expected {VIEW_SET_FORMS}")


def _count(spec: str, text: str, what: str) -> int:
    if re.fullmatch(r"\d{10,}", text):
        raise _bad(spec, f"{what}={text} must be within [1, {MAX_VIEWS}]")
    if not re.fullmatch(r"\d{1,9}", text):
        raise _bad(spec, f"{what} {text!r} is not a whole number")
    n = int(text)
    if not 1 <= n <= MAX_VIEWS:
        raise _bad(spec, f"{what}={n} must be within [1, {MAX_VIEWS}]")
    return n


def _angle(spec: str, text: str, what: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise _bad(spec, f"{where}: {what} {text.strip()!r} is not a number") from None
    if not math.isfinite(value):
        raise _bad(spec, f"{where}: {what}={value} is not finite")
    if what == "theta" and not -90.0 <= value <= 90.0:
        raise _bad(spec, f"{where}: theta={value} must be within [-90, 90] degrees")
    return value


def _grid(spec: str, body: str) -> ViewSet:
    m = re.fullmatch(r"\s*(\w+)\s*[xX]\s*(\w+)\s*", body)
    if m is None:
        raise _bad(spec, "a grid needs NPHIxNTHETA, e.g. grid:100x15")
    n_phi = _count(spec, m.group(1), "NPHI")
    n_theta = _count(spec, m.group(2), "NTHETA")
    if n_phi * n_theta > MAX_VIEWS:
        raise _bad(spec, f"{n_phi}x{n_theta} = {n_phi * n_theta} views exceeds {MAX_VIEWS}")
    phis, thetas = _grid_phi_deg(n_phi), _grid_theta_deg(n_theta)
    views = tuple(View(float(p), float(t)) for p in phis for t in thetas)
    return ViewSet(spec, "grid", views, (n_phi, n_theta))


def _fibonacci(spec: str, body: str) -> ViewSet:
    n = _count(spec, body.strip(), "N")
    k = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * k + 1.0) / n
    theta = np.degrees(np.arcsin(np.clip(z, -1.0, 1.0)))
    phi = np.mod(k * GOLDEN_ANGLE_DEG, 360.0)
    views = tuple(View(float(p), float(t)) for p, t in zip(phi, theta))
    return ViewSet(spec, "fibonacci", views)


def _random(spec: str, body: str) -> ViewSet:
    parts = body.split(":")
    if len(parts) > 2:
        raise _bad(spec, "random takes N or N:SEED")
    n = _count(spec, parts[0].strip(), "N")
    seed = 0
    if len(parts) == 2:
        if not re.fullmatch(r"\d{1,19}", parts[1].strip()):
            raise _bad(spec, f"SEED {parts[1]!r} is not a non-negative whole number")
        seed = int(parts[1])
    rng = np.random.default_rng(seed)
    z = rng.uniform(-1.0, 1.0, n)
    phi = rng.uniform(0.0, 360.0, n)
    theta = np.degrees(np.arcsin(z))
    views = tuple(View(float(p), float(t)) for p, t in zip(phi, theta))
    return ViewSet(spec, "random", views)


def _list(spec: str, body: str) -> ViewSet:
    items = [item for item in body.split(";") if item.strip()]
    if not items:
        raise _bad(spec, "list: needs at least one P,T pair")
    if len(items) > MAX_VIEWS:
        raise _bad(spec, f"{len(items)} views exceeds {MAX_VIEWS}")
    views = []
    for n, item in enumerate(items, start=1):
        pair = item.split(",")
        if len(pair) != 2:
            raise _bad(spec, f"item {n} {item.strip()!r} is not a P,T pair")
        phi = _angle(spec, pair[0], "phi", f"item {n}")
        theta = _angle(spec, pair[1], "theta", f"item {n}")
        views.append(View(phi, theta))
    return ViewSet(spec, "list", tuple(views))


def _csv(spec: str, path: Path) -> ViewSet:
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise _bad(spec, f"CSV file {path} is empty")
            names = [h.strip().lower() for h in header]
            if "phi" not in names or "theta" not in names:
                raise _bad(spec, f"CSV file {path} has no phi and theta columns (header {header})")
            i_phi, i_theta = names.index("phi"), names.index("theta")
            views = []
            for line_no, row in enumerate(reader, start=2):
                if not row or not any(c.strip() for c in row):
                    continue
                if len(row) <= max(i_phi, i_theta):
                    raise _bad(spec, f"line {line_no} of {path} has {len(row)} columns")
                where = f"line {line_no}"
                views.append(
                    View(
                        _angle(spec, row[i_phi], "phi", where),
                        _angle(spec, row[i_theta], "theta", where),
                    )
                )
                if len(views) > MAX_VIEWS:
                    raise _bad(spec, f"{path} lists more than {MAX_VIEWS} views")
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise _bad(spec, f"cannot read CSV file {path}: {exc}") from None
    if not views:
        raise _bad(spec, f"CSV file {path} lists no views")
    return ViewSet(str(path), "csv", tuple(views))


_PARSERS = {"grid": _grid, "fibonacci": _fibonacci, "random": _random, "list": _list}


def parse_view_set(spec: str) -> ViewSet:
    """Parse a view-set specification (see the module docstring for the forms).

    Parameters
    ----------
    spec : str
        ``grid:NPHIxNTHETA``, ``fibonacci:N``, ``random:N[:SEED]``,
        ``list:P,T;P,T;...`` or a path to a CSV file with phi,theta columns.

    Returns
    -------
    ViewSet

    Raises
    ------
    ViewSpecError
        One line naming the spec, the problem and the accepted forms.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise _bad(str(spec), "empty specification")
    text = spec.strip()
    kind, sep, body = text.partition(":")
    parser = _PARSERS.get(kind.strip().lower()) if sep else None
    if parser is not None:
        return parser(text, body)
    path = Path(text)
    if path.is_file():
        return _csv(text, path)
    if sep and len(kind) > 1 and "/" not in kind and "\\" not in kind:
        raise _bad(text, f"unknown kind {kind!r}")
    raise _bad(text, "not a view-set form and no such CSV file")


# --------------------------------------------------------------------------- cameras
def _vec3(name: str, value: object) -> np.ndarray:
    arr = np.array(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"camera {name}={value!r} must be 3 finite numbers")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole (perspective) or orthographic camera in world millimetres.

    Parameters
    ----------
    position, look_at : ndarray of shape (3,), float64
        Eye and target points in world mm.
    up : ndarray of shape (3,), float64
        Up hint; the image's up is its part orthogonal to the view direction.
    projection : {"perspective", "orthographic"}
    fov_deg : float
        Vertical field of view (perspective), in (0, 180).
    ortho_height_mm : float
        Height of the view (orthographic), > 0.
    """

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    projection: str = "perspective"
    fov_deg: float = 30.0
    ortho_height_mm: float = 1.0

    def __post_init__(self) -> None:
        for name in ("position", "look_at", "up"):
            object.__setattr__(self, name, _vec3(name, getattr(self, name)))
        if self.projection not in PROJECTIONS:
            raise ValueError(f"camera projection={self.projection!r} must be one of {PROJECTIONS}")
        fov, height = float(self.fov_deg), float(self.ortho_height_mm)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"camera fov_deg={fov} must be within (0, 180)")
        if not (math.isfinite(height) and height > 0.0):
            raise ValueError(f"camera ortho_height_mm={height} must be positive")
        object.__setattr__(self, "fov_deg", fov)
        object.__setattr__(self, "ortho_height_mm", height)
        forward = self.look_at - self.position
        if np.linalg.norm(forward) == 0.0:
            raise ValueError("camera position and look_at coincide")
        f = forward / np.linalg.norm(forward)
        u = self.up - np.dot(self.up, f) * f
        if np.linalg.norm(u) < 1e-9 * max(1.0, float(np.linalg.norm(self.up))):
            raise ValueError(f"camera up={self.up.tolist()} is parallel to the view direction")

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Orthonormal ``(forward, right, up)``, each float64 (3,); right = forward x up."""
        f = self.look_at - self.position
        f = f / np.linalg.norm(f)
        u = self.up - np.dot(self.up, f) * f
        u = u / np.linalg.norm(u)
        r = np.cross(f, u)
        return f, r / np.linalg.norm(r), u

    def rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel rays through pixel centres.

        Returns
        -------
        origins : ndarray of shape (height, width, 3), float64
            World mm (the eye for perspective, the image plane for orthographic).
        directions : ndarray of shape (height, width, 3), float64
            Unit vectors.
        """
        xs, ys = self._pixel_centres(width, height)
        gx, gy = np.meshgrid(xs, ys)
        return self._rays_through(gx, gy)

    def rays_at(
        self, width: int, height: int, rows: np.ndarray, cols: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The rays of `rays` at pixels ``(rows[i], cols[i])`` only, bit-identical to them.

        Parameters
        ----------
        width, height : int
            The full image size the pixels belong to.
        rows, cols : ndarray of shape (n,), int
            Pixel indices, within the image (not checked here).

        Returns
        -------
        origins, directions : ndarray of shape (n, 3), float64
        """
        xs, ys = self._pixel_centres(width, height)
        return self._rays_through(xs[np.asarray(cols)], ys[np.asarray(rows)])

    @staticmethod
    def _pixel_centres(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Pixel centres in [-1, 1] (x scaled by the aspect); row 0 at the top (+up)."""
        width, height = int(width), int(height)
        xs = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * (width / height)
        ys = 1.0 - (np.arange(height) + 0.5) / height * 2.0
        return xs, ys

    def _rays_through(self, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions (gx.shape + (3,)) through image-plane points."""
        f, r, u = self.basis()
        if self.projection == "perspective":
            half = math.tan(math.radians(self.fov_deg) / 2.0)
            d = f + (gx * half)[..., None] * r + (gy * half)[..., None] * u
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            o = np.broadcast_to(self.position, d.shape).copy()
        else:
            half = self.ortho_height_mm / 2.0
            o = self.position + (gx * half)[..., None] * r + (gy * half)[..., None] * u
            d = np.broadcast_to(f, o.shape).copy()
        return o, d

    def to_dict(self) -> dict:
        """JSON-able description: ``position``, ``look_at``, ``up`` (lists), the rest scalars."""
        return {
            "position": [float(v) for v in self.position],
            "look_at": [float(v) for v in self.look_at],
            "up": [float(v) for v in self.up],
            "projection": self.projection,
            "fov_deg": self.fov_deg,
            "ortho_height_mm": self.ortho_height_mm,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        """Inverse of `to_dict`."""
        return cls(
            position=d["position"],
            look_at=d["look_at"],
            up=d["up"],
            projection=d.get("projection", "perspective"),
            fov_deg=d.get("fov_deg", 30.0),
            ortho_height_mm=d.get("ortho_height_mm", 1.0),
        )


def orbit_camera(
    view: View,
    center_mm: object,
    radius_mm: float,
    *,
    projection: str = "perspective",
    fov_deg: float = 30.0,
) -> Camera:
    """The orbit camera for ``view`` around a bounding sphere (see module docstring).

    Parameters
    ----------
    view : View
    center_mm : array-like of shape (3,)
        Sphere centre (the volume's ``center_mm``).
    radius_mm : float
        Bounding-sphere radius (``volume.radius_mm``), > 0.
    projection : {"perspective", "orthographic"}
    fov_deg : float
        Vertical field of view, in (0, 180); sets the distance for both projections.

    Returns
    -------
    Camera
    """
    radius = float(radius_mm)
    if not (math.isfinite(radius) and radius > 0.0):
        raise ValueError(f"radius_mm={radius_mm} must be positive")
    if not 0.0 < float(fov_deg) < 180.0:
        raise ValueError(f"fov_deg={fov_deg} must be within (0, 180)")
    center = _vec3("center_mm", center_mm)
    phi, theta = math.radians(view.phi_deg), math.radians(view.theta_deg)
    cp, sp, ct, st = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta)
    distance = radius / math.sin(math.radians(fov_deg) / 2.0)
    position = center + distance * np.array([ct * cp, ct * sp, st])
    up = np.array([-st * cp, -st * sp, ct])
    return Camera(
        position=position,
        look_at=center,
        up=up,
        projection=projection,
        fov_deg=float(fov_deg),
        ortho_height_mm=2.0 * radius,
    )
