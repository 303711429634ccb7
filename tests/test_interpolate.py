"""Tests of score interpolation: host/fit/interpolate.py and device_runtime/interpolation.py."""

from __future__ import annotations

import json

import cbor2
import numpy as np
import pytest

from device_runtime.interpolation import (
    GridInterpolator,
    InterpolationError,
    TriangleInterpolator,
    detect_grid,
    direction_from_angles,
    interpolate,
    interpolator_from_manifest,
)
from host.errors import ViewSpecError
from host.fit.interpolate import GRID_DEFAULT, ScoreInterpolator, triangulate_views


def grid_views(n_phi=100, n_theta=15, shuffle_seed=None):
    """grid:NPHIxNTHETA angles (phi_i = i*360/N, theta centred, poles excluded)."""
    phi = np.tile(np.arange(n_phi) * 360.0 / n_phi, n_theta)
    theta = np.repeat(-90.0 + (np.arange(n_theta) + 0.5) * 180.0 / n_theta, n_phi)
    if shuffle_seed is not None:
        perm = np.random.default_rng(shuffle_seed).permutation(phi.size)
        phi, theta = phi[perm], theta[perm]
    return phi, theta


def fibonacci_views(n):
    """Near-uniform golden-spiral directions as (phi_deg, theta_deg)."""
    i = np.arange(n) + 0.5
    theta = np.degrees(np.arcsin(1.0 - 2.0 * i / n))
    phi = np.mod(i * 180.0 * (3.0 - np.sqrt(5.0)), 360.0)
    return phi, theta


def smooth_table(phi, theta, k_random=3, seed=0):
    """Scores that are smooth functions of the direction: x, y, z, z*x, then noise columns."""
    d = direction_from_angles(phi, theta)
    rng = np.random.default_rng(seed)
    cols = [d, (d[:, 2] * d[:, 0])[:, None], rng.standard_normal((phi.size, k_random))]
    return np.concatenate(cols, axis=1).astype(np.float32)


# interpolation-error bound for x, y, z of the direction on the 3.6 x 12 deg grid
SMOOTH_BOUND = (np.radians(3.6) ** 2 + np.radians(12.0) ** 2) / 8 * 1.01  # +1 % round-off


@pytest.fixture(scope="module")
def grid_set():
    phi, theta = grid_views(shuffle_seed=1)
    table = smooth_table(phi, theta)
    return phi, theta, table


@pytest.fixture(scope="module")
def grid_pair(grid_set):
    phi, theta, table = grid_set
    return (
        ScoreInterpolator(phi, theta, table, method="bilinear"),
        ScoreInterpolator(phi, theta, table, method="barycentric"),
    )


@pytest.fixture(scope="module")
def fib_set():
    phi, theta = fibonacci_views(300)
    table = smooth_table(phi, theta, seed=2)
    return phi, theta, table, ScoreInterpolator(phi, theta, table)


# ---------------------------------------------------------------------------
# method choice and grid detection


def test_auto_picks_the_grid_default_for_a_shuffled_grid_and_barycentric_otherwise(
    grid_set, grid_pair, fib_set
):
    assert ScoreInterpolator(*grid_set).method_ == GRID_DEFAULT
    assert grid_pair[0].method_ == "bilinear"
    assert grid_pair[1].method_ == "barycentric"
    assert fib_set[3].method_ == "barycentric"


def test_detect_grid_any_order_and_phase():
    phi, theta = grid_views(8, 3, shuffle_seed=4)
    axes, reason = detect_grid(phi + 10.0, theta)  # a phase-shifted grid is a grid too
    assert reason == "" and axes.n_phi == 8
    assert axes.phi0_deg == pytest.approx(10.0)
    np.testing.assert_allclose(axes.theta_deg, [-60.0, 0.0, 60.0])
    for i in range(8):
        for j in range(3):
            v = axes.view_index[i, j]
            assert np.mod(phi[v] + 10.0, 360.0) == pytest.approx(10.0 + 45.0 * i)
            assert theta[v] == pytest.approx(axes.theta_deg[j])
    axes, reason = detect_grid(phi[1:], theta[1:])
    assert axes is None and "rows" in reason
    bad_phi = phi.copy()
    bad_phi[0] += 1.0
    assert detect_grid(bad_phi, theta)[0] is None
    repeated_phi, repeated_theta = phi.copy(), theta.copy()
    repeated_phi[1], repeated_theta[1] = phi[0], theta[0]
    assert "missing or repeated" in detect_grid(repeated_phi, repeated_theta)[1]


def test_grid_with_rounded_angles_is_still_exact_at_nodes():
    # angles as read back from a CSV: off by up to 1e-7 deg, first column near 360
    phi, theta = grid_views(20, 4, shuffle_seed=2)
    rng = np.random.default_rng(3)
    noisy_phi = np.where(phi == 0.0, 360.0 - 1e-7, phi + rng.uniform(-1e-7, 1e-7, phi.size))
    noisy_theta = theta + rng.uniform(-1e-7, 1e-7, theta.size)
    table = smooth_table(phi, theta)
    for method in ("auto", "bilinear", "bicubic"):
        interp = ScoreInterpolator(noisy_phi, noisy_theta, table, method=method)
        assert interp.method_ == (GRID_DEFAULT if method == "auto" else method)
        np.testing.assert_array_equal(interp(noisy_phi, noisy_theta), table)
        np.testing.assert_array_equal(interp(phi, theta), table)


def test_bilinear_on_scattered_views_is_refused(fib_set):
    phi, theta, table, _ = fib_set
    with pytest.raises(ViewSpecError, match="method='bilinear' needs a full phi x theta grid"):
        ScoreInterpolator(phi, theta, table, method="bilinear")
    with pytest.raises(ValueError, match=r"method='cubic' is unknown; use one of \['auto'"):
        ScoreInterpolator(phi, theta, table, method="cubic")


# ---------------------------------------------------------------------------
# exactness, weights, continuity


@pytest.mark.parametrize("which", ["grid-bilinear", "grid-barycentric", "fibonacci"])
def test_exact_at_training_views(which, grid_set, grid_pair, fib_set):
    if which == "fibonacci":
        phi, theta, table, interp = fib_set
    else:
        phi, theta, table = grid_set
        interp = grid_pair[0] if which == "grid-bilinear" else grid_pair[1]
    np.testing.assert_array_equal(interp(phi, theta), table)
    for v in range(0, phi.size, 37):  # scalar queries too
        idx, w = interp.weights(phi[v], theta[v])
        assert w.max() == 1.0 and idx[np.argmax(w)] == v
        np.testing.assert_array_equal(interp(phi[v], theta[v]), table[v])


@pytest.mark.parametrize("which", ["bilinear", "barycentric", "fibonacci", "hemisphere"])
def test_weights_are_a_partition_of_unity(which, grid_pair, fib_set):
    rng = np.random.default_rng(5)
    phi = np.concatenate([rng.uniform(-720, 720, 500), [0, 90, 180, 359.999999, 360, 725]])
    theta = np.concatenate([rng.uniform(-90, 90, 500), [90, -90, 90, -90, 0, 45]])
    if which == "fibonacci":
        interp = fib_set[3]
    elif which == "hemisphere":
        p, t = fibonacci_views(400)
        keep = t > 10
        interp = ScoreInterpolator(p[keep], t[keep], smooth_table(p[keep], t[keep]))
    else:
        interp = grid_pair[0] if which == "bilinear" else grid_pair[1]
    idx, w = interp.weights(phi, theta)
    m = interp.interpolator_.entries
    assert idx.shape == w.shape == (phi.size, m)
    assert idx.dtype == np.int32 and w.dtype == np.float32
    assert idx.min() >= 0 and idx.max() < interp.scores.shape[0]
    assert (w >= 0).all() and np.isfinite(w).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    values = interp(phi, theta)
    assert values.shape == (phi.size, interp.scores.shape[1]) and np.isfinite(values).all()
    # vectorised == one query at a time
    for q in range(0, phi.size, 50):
        np.testing.assert_array_equal(interp(phi[q], theta[q]), values[q])


@pytest.mark.parametrize("which", ["bilinear", "barycentric", "fibonacci"])
def test_continuous_across_the_phi_seam(which, grid_pair, fib_set):
    interp = fib_set[3] if which == "fibonacci" else grid_pair[which == "barycentric"]
    table = interp.scores
    theta = np.linspace(-80, 80, 41)
    below = interp(np.full_like(theta, 359.999), theta)
    above = interp(np.full_like(theta, 0.001), theta)
    # a move of 0.002 deg shifts at most 0.002 / (smallest view spacing ~1.5 deg) of
    # the weight between neighbours: bound 0.002 * |table| (tight for either method)
    bound = 0.002 * np.abs(table).max()
    assert np.abs(below - above).max() < bound
    np.testing.assert_allclose(interp(np.full_like(theta, 360.0), theta), interp(0 * theta, theta))
    np.testing.assert_allclose(
        interp(np.full_like(theta, -0.25), theta),
        interp(np.full_like(theta, 359.75), theta),
        atol=1e-6,
    )


@pytest.mark.parametrize("which", ["bilinear", "barycentric", "fibonacci"])
def test_poles_have_no_nan(which, grid_pair, fib_set):
    interp = fib_set[3] if which == "fibonacci" else grid_pair[which == "barycentric"]
    phi = np.linspace(0, 360, 25)
    for pole in (90.0, -90.0):
        values = interp(phi, np.full_like(phi, pole))
        assert np.isfinite(values).all()
        _, w = interp.weights(phi, np.full_like(phi, pole))
        np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)


def test_bilinear_clamps_beyond_the_outermost_rows(grid_pair):
    bilinear = grid_pair[0]
    phi = np.array([0.0, 1.8, 100.0])
    np.testing.assert_array_equal(bilinear(phi, np.full(3, 90.0)), bilinear(phi, np.full(3, 84.0)))
    np.testing.assert_array_equal(
        bilinear(phi, np.full(3, -88.0)), bilinear(phi, np.full(3, -84.0))
    )


def test_bilinear_is_linear_in_each_coordinate(grid_set, grid_pair):
    table = grid_set[2]
    axes = grid_pair[0].interpolator_.axes
    vi = axes.view_index
    # midpoint of a cell: mean of its 4 corners; a third along phi on a row: 2:1 blend
    i, j = 17, 6
    corners = table[[vi[i, j], vi[i + 1, j], vi[i, j + 1], vi[i + 1, j + 1]]]
    mid = grid_pair[0](i * 3.6 + 1.8, axes.theta_deg[j] + 6.0)
    np.testing.assert_allclose(mid, corners.mean(axis=0), atol=1e-6)
    third = grid_pair[0](i * 3.6 + 1.2, axes.theta_deg[j])
    np.testing.assert_allclose(third, (2 * corners[0] + corners[1]) / 3, atol=1e-6)


def test_grid_and_barycentric_agree_on_a_grid(grid_set, grid_pair):
    phi, theta, table = grid_set
    bilinear, bary = grid_pair
    axes = bilinear.interpolator_.axes
    vi, rows = axes.view_index, axes.theta_deg

    # 1) exact agreement at every grid node (both exact there)
    np.testing.assert_array_equal(bilinear(phi, theta), bary(phi, theta))

    # 2) along meridian grid edges (constant phi between two rows) the triangle edge
    # is the same great-circle arc, so both use only its two end nodes. Bilinear
    # weights them linearly in theta; the gnomonic barycentric weight of the far
    # end at a fraction u of an arc of length D is sin(uD) / (sin(uD) + sin((1-u)D)).
    # The two agree up to max_u of that difference (6.9e-4 for D = 12 deg).
    d_rad = np.radians(rows[1] - rows[0])
    u = np.linspace(0, 1, 2001)
    gnomonic = np.sin(u * d_rad) / (np.sin(u * d_rad) + np.sin((1 - u) * d_rad))
    max_dev = np.abs(gnomonic - u).max()
    assert max_dev < 1e-3
    rng = np.random.default_rng(6)
    i = rng.integers(0, 100, 300)
    j = rng.integers(0, rows.size - 1, 300)
    f = rng.uniform(0, 1, 300)
    q_phi, q_theta = i * 3.6, rows[j] + f * (rows[j + 1] - rows[j])
    idx_b, w_b = bary.weights(q_phi, q_theta)
    ends = np.stack([vi[i, j], vi[i, j + 1]], axis=1)
    for q in range(300):  # only the two end nodes carry weight
        assert set(idx_b[q][w_b[q] > 0]) <= set(ends[q])
    span = np.abs(table[ends[:, 0]] - table[ends[:, 1]])
    diff = np.abs(bilinear(q_phi, q_theta) - bary(q_phi, q_theta))
    assert (diff <= max_dev * span + 1e-6).all()

    # 3) inside a grid cell both blend the same four nodes: bilinear by construction,
    # barycentric because the triangulation splits each quad along a diagonal (its
    # sides are hull edges). Away from the rows by more than the sagitta of the
    # 3.6 deg great-circle edges (< 0.015 deg), no other node gets weight, so the two
    # agree up to the spread of those four values (a wrong node would break this).
    # On the smooth columns (x, y, z of the direction) each is within the
    # interpolation-error bound of the truth (next test), so they agree to twice it.
    n = 2000
    i = rng.integers(0, 100, n)
    j = rng.integers(0, rows.size - 1, n)
    fp, ft = rng.uniform(0, 1, n), rng.uniform(0.005, 0.995, n)
    q_phi, q_theta = (i + fp) * 3.6, rows[j] + ft * (rows[j + 1] - rows[j])
    nodes = np.stack([vi[i, j], vi[(i + 1) % 100, j], vi[i, j + 1], vi[(i + 1) % 100, j + 1]], 1)
    idx_b, w_b = bary.weights(q_phi, q_theta)
    for q in range(n):
        assert set(idx_b[q][w_b[q] > 0]) <= set(nodes[q])
    c = table[nodes.T]  # (4, n, K)
    diff = np.abs(bilinear(q_phi, q_theta) - bary(q_phi, q_theta))
    assert (diff <= c.max(axis=0) - c.min(axis=0) + 1e-6).all()
    assert diff[:, :3].max() <= 2 * SMOOTH_BOUND


def test_both_methods_approximate_a_smooth_function(grid_pair):
    # x, y, z of the direction have second derivatives of magnitude <= 1 (per radian^2)
    # along phi, theta and any great circle. Bilinear (tensor-product) error <=
    # (h_phi^2 + h_theta^2) / 8 * 1; linear on a triangle <= R^2 / 2 * 1 with R the
    # circumradius, here half the cell diagonal: both = SMOOTH_BOUND (3.6 x 12 deg).
    rng = np.random.default_rng(7)
    q_phi, q_theta = rng.uniform(0, 360, 1000), rng.uniform(-84, 84, 1000)
    truth = direction_from_angles(q_phi, q_theta)
    for interp in grid_pair:
        err = np.abs(interp(q_phi, q_theta)[:, :3] - truth).max()
        assert err <= SMOOTH_BOUND, (interp.method_, err)


# ---------------------------------------------------------------------------
# partial (hemisphere) view sets


@pytest.mark.parametrize("which", ["grid", "fibonacci"])
def test_barycentric_weights_match_a_brute_force_reference(which, grid_pair, fib_set):
    # reference: for every triangle solve q = alpha a + beta b + gamma c and take the
    # one with all coefficients >= 0; weights = coefficients / their sum
    interp = grid_pair[1] if which == "grid" else fib_set[3]
    tri = interp.interpolator_.triangles
    dirs = interp.interpolator_.directions
    rng = np.random.default_rng(11)
    q_phi = rng.uniform(0, 360, 150)
    q_theta = np.degrees(np.arcsin(rng.uniform(-1, 1, 150)))  # uniform on the sphere
    q_theta[:20] = rng.uniform(84, 90, 20)  # polar caps: fans of many triangles
    idx, w = interp.weights(q_phi, q_theta)
    verts = dirs[tri]  # (t, 3 vertices, 3)
    for q, v in enumerate(direction_from_angles(q_phi, q_theta)):
        rhs = np.broadcast_to(v, (tri.shape[0], 3))[..., None]
        coef = np.linalg.solve(verts.transpose(0, 2, 1), rhs)[..., 0]
        inside = np.flatnonzero((coef >= -1e-12).all(axis=1))
        assert inside.size >= 1
        ref = dict(zip(tri[inside[0]].tolist(), coef[inside[0]] / coef[inside[0]].sum()))
        got = {}
        for i, wt in zip(idx[q].tolist(), w[q].tolist()):
            got[i] = got.get(i, 0.0) + wt
        for i in set(ref) | set(got):
            assert abs(ref.get(i, 0.0) - got.get(i, 0.0)) < 1e-6


def test_hemisphere_set_clamps_outside_continuously():
    phi, theta = fibonacci_views(600)
    keep = theta > 0
    phi, theta = phi[keep], theta[keep]
    table = smooth_table(phi, theta, seed=3)
    interp = ScoreInterpolator(phi, theta, table, method="barycentric")
    tri = interp.interpolator_.triangles
    assert tri.shape[0] > 0
    # every kept triangle lies in the upper hemisphere's cap (no closing faces)
    dirs = direction_from_angles(phi, theta)
    centroids = dirs[tri].mean(axis=1)
    assert (centroids[:, 2] > 0).all()
    # crossing the boundary of the covered region downwards is continuous
    rim = theta.min()
    q_phi = np.linspace(0, 360, 181)
    values = [interp(q_phi, np.full_like(q_phi, t)) for t in (rim - 20.0, rim - 1e-3, -90.0)]
    assert all(np.isfinite(v).all() for v in values)
    # sample across the rim every 1e-4 deg: the thinnest rim triangles (~0.2 deg) make
    # weights change by <= ~5 per degree, so a step changes values by < 1e-3 * |table|;
    # a jump (a discontinuity at the boundary) would be of order |table|
    near = np.linspace(rim - 0.5, rim + 0.5, 10001)
    for p in (13.0, 200.0):
        track = interp(np.full_like(near, p), near)
        steps = np.abs(np.diff(track, axis=0)).max()
        assert steps < 0.01 * np.abs(table).max(), steps
    # training views are still exact
    np.testing.assert_array_equal(interp(phi, theta), table)


# ---------------------------------------------------------------------------
# manifests: host -> device, bit-identical evaluation


@pytest.mark.parametrize("which", ["bilinear", "barycentric"])
@pytest.mark.parametrize("codec", ["json", "cbor"])
def test_manifest_round_trip_is_bit_identical(which, codec, grid_pair, fib_set):
    host = grid_pair[0] if which == "bilinear" else fib_set[3]
    manifest = host.to_manifest()
    assert manifest["method"] == which and manifest["version"] == 1
    if codec == "json":
        wire = json.loads(json.dumps(manifest))
    else:
        wire = cbor2.loads(cbor2.dumps(manifest))
    device = interpolator_from_manifest(wire)
    rng = np.random.default_rng(8)
    q_phi, q_theta = rng.uniform(0, 360, 300), rng.uniform(-90, 90, 300)
    a = host.weights(q_phi, q_theta)
    b = device.weights(q_phi, q_theta)
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.weights, b.weights)
    np.testing.assert_array_equal(interpolate(host.scores, *b), host(q_phi, q_theta))
    again = ScoreInterpolator.from_manifest(wire, host.scores)
    np.testing.assert_array_equal(again(q_phi, q_theta), host(q_phi, q_theta))


def _refused_when_mutated(interpolator, mutate, message: str) -> None:
    """``interpolator``'s manifest (its lists copied), changed by ``mutate``, is refused with
    an `InterpolationError` matching ``message``."""
    manifest = interpolator.to_manifest()
    manifest = {k: list(v) if isinstance(v, list) else v for k, v in manifest.items()}
    mutate(manifest)
    with pytest.raises(InterpolationError, match=message):
        interpolator_from_manifest(manifest)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda m: m.update(method="spline"), r"method='spline' is unknown; known: \["),
        (lambda m: m.update(version=2), r"version 2 is not supported \(supported: 1\)"),
        (lambda m: m.update(n_views=7), r"n_views=7 but the data describe"),
        (lambda m: m.update(triangles=m["triangles"][:-1]), "3 entries per item"),
        (lambda m: m["triangles"].__setitem__(0, 10**6), r"indices must be in \[0, "),
        (lambda m: m["triangles"].__setitem__(0, -1), "out-of-range"),
        (lambda m: m["directions"].__setitem__(0, float("nan")), "non-finite"),
        (lambda m: m.update(directions="abc"), "directions must be a list of numbers"),
        (lambda m: m.update(triangles=[0.5, 1, 2]), "triangles must be a list of integers"),
        (lambda m: m.update(outside="extrapolate"), r"outside='extrapolate' is not supported"),
    ],
)
def test_malformed_triangle_manifests_are_refused(mutate, message, fib_set):
    _refused_when_mutated(fib_set[3], mutate, message)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda m: m.update(view_index=m["view_index"][:-1]), "view_index has 1499 entries"),
        (lambda m: m["view_index"].__setitem__(0, 1), "permutation of the views"),
        (lambda m: m.update(theta_deg=m["theta_deg"][::-1]), "increasing"),
        (lambda m: m.update(phi0_deg=400.0), r"phi0_deg=400.0 must be in \[0, 360\)"),
        (lambda m: m.update(n_phi="100"), "n_phi='100' must be int"),
        (
            lambda m: m.update(poles="blend"),
            r"poles='blend' is not supported \(supported: \['clamp'\]\)",
        ),
    ],
)
def test_malformed_grid_manifests_are_refused(mutate, message, grid_pair):
    _refused_when_mutated(grid_pair[0], mutate, message)
    assert issubclass(InterpolationError, ValueError)


# ---------------------------------------------------------------------------
# bad inputs


def test_bad_queries_and_inputs(grid_pair):
    bilinear = grid_pair[0]
    with pytest.raises(InterpolationError, match=r"theta_deg=95 is outside \[-90, 90\]"):
        bilinear(0.0, 95.0)
    with pytest.raises(InterpolationError, match="must be finite"):
        bilinear(float("nan"), 0.0)
    phi, theta = grid_views(8, 3)
    with pytest.raises(ValueError, match=r"scores must be \(n_views=24, K\), got \(23, 2\)"):
        ScoreInterpolator(phi, theta, np.zeros((23, 2)))
    with pytest.raises(ValueError, match="finite"):
        ScoreInterpolator(phi, theta, np.full((24, 2), np.inf))
    with pytest.raises(ValueError, match=r"theta_deg must lie in \[-90, 90\]"):
        ScoreInterpolator(phi, theta + 40.0, np.zeros((24, 2)))
    with pytest.raises(InterpolationError, match="needs a full grid"):
        GridInterpolator(phi[:-1], theta[:-1])


def test_degenerate_view_sets():
    # one ring of views: a 1-row grid works bilinearly (phi only), but cannot be triangulated
    phi = np.arange(12) * 30.0
    theta = np.zeros(12)
    table = np.arange(24, dtype=np.float32).reshape(12, 2)
    ring = ScoreInterpolator(phi, theta, table, method="bilinear")
    assert ring.method_ == "bilinear"
    assert ScoreInterpolator(phi, theta, table).method_ == GRID_DEFAULT
    np.testing.assert_allclose(ring(15.0, 40.0), (table[0] + table[1]) / 2)
    with pytest.raises(ViewSpecError, match="span no 3-D hull"):
        ScoreInterpolator(phi, theta, table, method="barycentric")
    with pytest.raises(ViewSpecError, match=r"views \[0, 3\] have the same direction"):
        triangulate_views([0, 90, 180, 0, 45], [0, 0, 0, 0, 60])
    with pytest.raises(ViewSpecError, match="at least 3 views"):
        triangulate_views([0, 90], [0, 0])
    with pytest.raises(InterpolationError, match="degenerate"):
        TriangleInterpolator(direction_from_angles([0, 90, 180], [0, 0, 0]), [[0, 1, 2]])


def test_triangulation_is_deterministic_and_oriented(fib_set):
    phi, theta, _, interp = fib_set
    tri = triangulate_views(phi, theta)
    np.testing.assert_array_equal(tri, triangulate_views(phi, theta))
    np.testing.assert_array_equal(tri, interp.interpolator_.triangles)
    # a closed triangulation of the sphere: 2n - 4 triangles, positively oriented
    assert tri.shape == (2 * phi.size - 4, 3)
    d = direction_from_angles(phi, theta)
    det = np.einsum("ij,ij->i", d[tri[:, 0]], np.cross(d[tri[:, 1]], d[tri[:, 2]]))
    assert (det > 0).all()
    assert (tri[:, 0] < tri[:, 1]).all() and (tri[:, 0] < tri[:, 2]).all()
