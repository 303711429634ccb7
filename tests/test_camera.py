"""Cameras and view sets: exact grids, sphere coverage, orbit geometry, bad specs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from host.errors import ViewSpecError
from host.render.camera import Camera, View, ViewSet, orbit_camera, parse_view_set


def unit_vectors(view_set: ViewSet) -> np.ndarray:
    a = np.radians(view_set.angles_deg())
    phi, theta = a[:, 0], a[:, 1]
    return np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)], 1)


def nearest_neighbour_angles(points: np.ndarray) -> np.ndarray:
    cos = np.clip(points @ points.T, -1.0, 1.0)
    np.fill_diagonal(cos, -1.0)
    return np.arccos(cos.max(axis=1))


# --------------------------------------------------------------------------- grids
def test_paper_grid_has_exact_angles_in_documented_order():
    vs = parse_view_set("grid:100x15")
    assert vs.kind == "grid" and vs.spec == "grid:100x15"
    assert len(vs) == 1500 and vs.grid_shape == (100, 15)
    angles = vs.angles_deg().reshape(100, 15, 2)  # phi outer, theta inner
    phi_expected = np.arange(100) * 3.6
    theta_expected = -84.0 + 12.0 * np.arange(15)
    np.testing.assert_allclose(angles[:, :, 0], phi_expected[:, None] * np.ones(15), atol=1e-9)
    np.testing.assert_allclose(angles[:, :, 1], np.ones(100)[:, None] * theta_expected, atol=1e-9)
    assert vs.views[0] == View(0.0, -84.0)
    assert vs.views[1].theta_deg == pytest.approx(-72.0)
    assert vs.views[15].phi_deg == pytest.approx(3.6)
    phis, thetas = vs.grid_axes_deg()
    np.testing.assert_allclose(phis, phi_expected, atol=1e-12)
    np.testing.assert_allclose(thetas, theta_expected, atol=1e-12)


@pytest.mark.parametrize("n_theta", [1, 2, 3, 15, 16])
def test_grid_excludes_poles_and_is_centred(n_theta):
    vs = parse_view_set(f"GRID:4X{n_theta}")
    thetas = vs.angles_deg()[:, 1]
    assert np.all(np.abs(thetas) < 90.0)
    np.testing.assert_allclose(np.sort(thetas), np.sort(-thetas), atol=1e-9)  # symmetric
    spacing = 180.0 / n_theta
    assert thetas.max() == pytest.approx(90.0 - spacing / 2)


def test_grid_axes_only_for_grids():
    with pytest.raises(ValueError, match="not a grid"):
        parse_view_set("fibonacci:10").grid_axes_deg()


# --------------------------------------------------------------------------- fibonacci / random
def test_fibonacci_is_near_uniform():
    n = 600
    vs = parse_view_set("fibonacci:600")
    assert len(vs) == n and vs.grid_shape is None and vs.kind == "fibonacci"
    pts = unit_vectors(vs)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 1.0)
    nn = nearest_neighbour_angles(pts)
    # Area per point is 4*pi/n; a hexagonal packing of that density has neighbour
    # spacing sqrt(8*pi/(sqrt(3)*n)), the best possible. The golden spiral keeps
    # every nearest-neighbour distance within 0.75..1.1 of it (n=600: 0.81..0.92);
    # uniform random points get far closer pairs (checked below).
    hex_spacing = math.sqrt(8 * math.pi / (math.sqrt(3) * n))
    assert nn.min() > 0.75 * hex_spacing
    assert nn.max() < 1.1 * hex_spacing
    assert nn.max() / nn.min() < 1.3
    # equal areas: each z band of height 0.5 holds a quarter of the points
    counts = np.histogram(pts[:, 2], bins=4, range=(-1, 1))[0]
    assert np.all(np.abs(counts - n / 4) <= 2)
    rnd = nearest_neighbour_angles(unit_vectors(parse_view_set("random:600")))
    assert rnd.min() < 0.5 * nn.min()  # the spread measure can tell the difference


def test_random_is_reproducible_and_uniform():
    a = parse_view_set("random:2000:7")
    b = parse_view_set("random:2000:7")
    c = parse_view_set("random:2000:8")
    assert a.views == b.views and a.views != c.views
    assert parse_view_set("random:50").views == parse_view_set("random:50:0").views
    pts = unit_vectors(a)
    # z and the x, y means of uniform points on the sphere have std 1/sqrt(3n) = 0.013
    assert np.all(np.abs(pts.mean(axis=0)) < 0.06)
    counts = np.histogram(pts[:, 2], bins=4, range=(-1, 1))[0]
    assert np.all(np.abs(counts - 500) < 5 * math.sqrt(500))  # uniform in z: equal bands
    phi = a.angles_deg()[:, 0]
    assert phi.min() >= 0.0 and phi.max() < 360.0


# --------------------------------------------------------------------------- list / csv
def test_list_parses_and_normalises_phi():
    vs = parse_view_set("list: 10,20 ; -30, -45;370,90;")
    assert vs.kind == "list"
    assert [(v.phi_deg, v.theta_deg) for v in vs.views] == [
        (10.0, 20.0),
        (330.0, -45.0),
        (pytest.approx(10.0), 90.0),
    ]


def test_csv_file_with_phi_theta_columns(tmp_path):
    path = tmp_path / "views.csv"
    path.write_text("FILE,Theta,phi\na.png,12.5,3.6\nb.png,-84,356.4\n\n", encoding="utf-8")
    vs = parse_view_set(str(path))
    assert vs.kind == "csv" and len(vs) == 2
    assert vs.views[0] == View(3.6, 12.5) and vs.views[1] == View(356.4, -84.0)


@pytest.mark.parametrize(
    "content, problem",
    [
        ("", "empty"),
        ("a,b\n1,2\n", "no phi and theta"),
        ("phi,theta\n", "no views"),
        ("phi,theta\n1,x\n", "line 2: theta 'x'"),
        ("phi,theta\n1,95\n", "line 2: theta=95.0"),
        ("phi,theta\n1\n", "line 2 of"),
    ],
)
def test_bad_csv_files_raise_view_spec_error(tmp_path, content, problem):
    path = tmp_path / "views.csv"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(ViewSpecError, match=problem) as info:
        parse_view_set(str(path))
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    "spec",
    [
        "",
        "   ",
        "grid:",
        "grid:10",
        "grid:0x5",
        "grid:10x0",
        "grid:axb",
        "grid:10x10x2",
        "grid:-3x4",
        "grid:2000000x1",
        "grid:99999999999999x1",
        "grid:1000x1001",
        "fibonacci:",
        "fibonacci:-3",
        "fibonacci:1.5",
        "fibonacci:0",
        "random:",
        "random:5:abc",
        "random:5:1:2",
        "random:5:-1",
        "list:",
        "list:;;",
        "list:1",
        "list:1,2,3",
        "list:0,91",
        "list:nan,0",
        "list:inf,0",
        "list:a,b",
        "spiral:5",
        "no/such/file.csv",
        "grid 10x10",
    ],
)
def test_malformed_specs_raise_one_line_view_spec_error(spec):
    with pytest.raises(ViewSpecError) as info:
        parse_view_set(spec)
    message = str(info.value)
    assert "\n" not in message
    assert repr(spec.strip()) in message or repr(spec) in message
    assert "grid:NPHIxNTHETA" in message and "fibonacci:N" in message


# --------------------------------------------------------------------------- views
def test_view_normalises_and_checks():
    assert View(-90.0, 0.0).phi_deg == 270.0
    assert View(720.0, 0.0).phi_deg == 0.0
    assert View(-1e-18, 0.0).phi_deg == 0.0  # -tiny + 360 would round to 360
    with pytest.raises(ValueError, match="theta_deg=91"):
        View(0.0, 91.0)
    with pytest.raises(ValueError, match="finite"):
        View(float("nan"), 0.0)


# --------------------------------------------------------------------------- orbit cameras
CENTER = np.array([10.0, -5.0, 3.0])
RADIUS = 7.0


def test_orbit_camera_position_follows_paraview_convention():
    cases = {
        (0, 0): (1, 0, 0),
        (90, 0): (0, 1, 0),
        (180, 0): (-1, 0, 0),
        (0, 90): (0, 0, 1),
        (45, -90): (0, 0, -1),
    }
    for (phi, theta), direction in cases.items():
        cam = orbit_camera(View(phi, theta), CENTER, RADIUS)
        offset = cam.position - CENTER
        d = np.linalg.norm(offset)
        np.testing.assert_allclose(offset / d, direction, atol=1e-12)
        np.testing.assert_allclose(cam.look_at, CENTER)


@pytest.mark.parametrize("fov_deg", [10.0, 30.0, 60.0])
def test_bounding_sphere_exactly_fills_vertical_fov(fov_deg):
    cam = orbit_camera(View(37.0, 21.0), CENTER, RADIUS, fov_deg=fov_deg)
    f, _, u = cam.basis()
    half = math.radians(fov_deg) / 2
    for sign in (1, -1):  # the top and bottom edges of the image are tangent to the sphere
        edge = math.cos(half) * f + sign * math.sin(half) * u
        distance_to_centre = np.linalg.norm(np.cross(CENTER - cam.position, edge))
        assert distance_to_centre == pytest.approx(RADIUS, rel=1e-12)
    # and the edge-row pixel centres of a tall image just hit it
    _, dirs = cam.rays(3, 1001)
    for row in (0, -1):
        d = dirs[row, 1]
        assert np.linalg.norm(np.cross(CENTER - cam.position, d)) < RADIUS


def test_orthographic_view_is_two_radii_high():
    cam = orbit_camera(View(200.0, -30.0), CENTER, RADIUS, projection="orthographic")
    assert cam.ortho_height_mm == pytest.approx(2 * RADIUS)
    origins, dirs = cam.rays(5, 101)
    f, _, u = cam.basis()
    np.testing.assert_allclose(dirs, np.broadcast_to(f, dirs.shape), atol=1e-15)
    heights = (origins - cam.position) @ u
    assert heights[0, 2] == pytest.approx(RADIUS * (1 - 1 / 101))  # row 0 is the top
    assert heights[-1, 2] == pytest.approx(-RADIUS * (1 - 1 / 101))
    assert np.linalg.norm(cam.position - CENTER) > RADIUS  # the eye plane is outside the sphere


def test_up_vector_orthogonal_and_continuous_through_the_poles():
    for phi in np.linspace(0, 360, 13):
        for theta in np.linspace(-90, 90, 37):
            cam = orbit_camera(View(phi, theta), CENTER, RADIUS)
            f, r, u = cam.basis()
            assert abs(f @ cam.up) < 1e-12  # the stored up is already orthogonal
            assert np.linalg.norm(cam.up) == pytest.approx(1.0)
            np.testing.assert_allclose(u, cam.up, atol=1e-12)
            np.testing.assert_allclose(r, np.cross(f, u), atol=1e-12)
            if abs(theta) < 90:
                assert cam.up[2] > 0  # +z projected, never flipped
        for pole in (90.0, -90.0):
            at = orbit_camera(View(phi, pole), CENTER, RADIUS).up
            near = orbit_camera(View(phi, pole - np.sign(pole) * 1e-6), CENTER, RADIUS).up
            np.testing.assert_allclose(at, near, atol=1e-7)
        # documented pole choice: the limit at the same phi, pointing away from / towards it
        phi_rad = math.radians(phi)
        np.testing.assert_allclose(
            orbit_camera(View(phi, 90.0), CENTER, RADIUS).up,
            [-math.cos(phi_rad), -math.sin(phi_rad), 0.0],
            atol=1e-12,
        )
        np.testing.assert_allclose(
            orbit_camera(View(phi, -90.0), CENTER, RADIUS).up,
            [math.cos(phi_rad), math.sin(phi_rad), 0.0],
            atol=1e-12,
        )


def test_image_axes_row_zero_top_column_zero_left():
    cam = orbit_camera(View(0.0, 0.0), CENTER, RADIUS)  # at +x, looking towards -x
    _, dirs = cam.rays(4, 4)
    assert dirs[0, 1, 2] > 0 > dirs[-1, 1, 2]  # row 0 looks up (+z)
    assert dirs[1, 0, 1] < 0 < dirs[1, -1, 1]  # right = forward x up = +y
    _, wide = cam.rays(8, 4)  # vertical fov fixed, horizontal grows with the aspect
    assert abs(wide[0, 0, 1]) > abs(dirs[0, 0, 1])


def test_camera_dict_round_trip_and_validation():
    cam = orbit_camera(View(12.0, 34.0), CENTER, RADIUS, projection="orthographic", fov_deg=40)
    d = cam.to_dict()
    json.dumps(d)
    assert set(d) >= {"position", "look_at", "up", "projection", "fov_deg", "ortho_height_mm"}
    back = Camera.from_dict(json.loads(json.dumps(d)))
    for name in ("position", "look_at", "up"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cam, name))
    assert back.projection == "orthographic" and back.fov_deg == 40.0
    with pytest.raises(ValueError, match="projection"):
        Camera(cam.position, cam.look_at, cam.up, projection="fisheye")
    with pytest.raises(ValueError, match="parallel"):
        Camera([0, 0, 5], [0, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="coincide"):
        Camera([1, 2, 3], [1, 2, 3], [0, 0, 1])
    with pytest.raises(ValueError, match="fov_deg"):
        orbit_camera(View(0, 0), CENTER, RADIUS, fov_deg=180)
    with pytest.raises(ValueError, match="radius_mm"):
        orbit_camera(View(0, 0), CENTER, 0.0)
    with pytest.raises(ValueError, match="position"):
        Camera([0, 0, float("nan")], [0, 0, 0], [0, 0, 1])
