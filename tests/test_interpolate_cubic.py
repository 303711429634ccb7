"""Tests of bicubic (Catmull-Rom) grid interpolation and manifest compatibility."""

from __future__ import annotations

import json

import cbor2
import numpy as np
import pytest
from cli_helpers import render_tooth, run_cli

from device_runtime.interpolation import (
    GridCubicInterpolator,
    GridInterpolator,
    InterpolationError,
    interpolate,
    interpolator_from_manifest,
)
from host.errors import ViewSpecError
from host.fit.interpolate import GRID_DEFAULT, METHODS, ScoreInterpolator
from tests.test_interpolate import fibonacci_views, grid_views, smooth_table


@pytest.fixture(scope="module")
def cubic_set():
    phi, theta = grid_views(shuffle_seed=3)
    table = smooth_table(phi, theta, seed=4)
    return phi, theta, table, ScoreInterpolator(phi, theta, table, method="bicubic")


def _uneven_grid(n_phi=24):
    rows = np.array([-80.0, -50.0, -20.0, -5.0, 10.0, 40.0, 75.0])
    return np.tile(np.arange(n_phi) * 360.0 / n_phi + 2.5, rows.size), np.repeat(rows, n_phi)


def test_bicubic_is_registered_and_rejects_scattered_views():
    assert "bicubic" in METHODS and GRID_DEFAULT in METHODS
    p, t = fibonacci_views(200)
    with pytest.raises(ViewSpecError, match="method='bicubic' needs a full phi x theta grid"):
        ScoreInterpolator(p, t, smooth_table(p, t), method="bicubic")


def test_bicubic_is_exact_at_training_views(cubic_set):
    phi, theta, table, interp = cubic_set
    np.testing.assert_array_equal(interp(phi, theta), table)
    for v in range(0, phi.size, 53):
        idx, w = interp.weights(phi[v], theta[v])
        assert w.max() == 1.0 and idx[np.argmax(w)] == v
        assert np.count_nonzero(w) == 1


def test_bicubic_exact_on_uneven_rows_and_reproduces_linear_theta():
    phi, theta = _uneven_grid()
    table = np.stack([theta, np.cos(np.radians(phi))], axis=1).astype(np.float64)
    interp = ScoreInterpolator(phi, theta, table, method="bicubic")
    np.testing.assert_allclose(interp(phi, theta), table, atol=1e-4)
    rng = np.random.default_rng(0)
    qp, qt = rng.uniform(0, 360, 400), rng.uniform(-80, 75, 400)
    # a linear function of theta is reproduced exactly, even on uneven rows
    np.testing.assert_allclose(interp(qp, qt)[:, 0], qt, atol=1e-3)


def test_bicubic_weights_partition_of_unity_and_vectorised(cubic_set):
    interp = cubic_set[3]
    rng = np.random.default_rng(5)
    phi = np.concatenate([rng.uniform(-720, 720, 400), [0, 359.999999, 360, 725]])
    theta = np.concatenate([rng.uniform(-90, 90, 400), [90, -90, 0, 45]])
    idx, w = interp.weights(phi, theta)
    assert idx.shape == w.shape == (phi.size, 16) == (phi.size, interp.interpolator_.entries)
    assert idx.dtype == np.int32 and w.dtype == np.float32
    assert idx.min() >= 0 and idx.max() < interp.scores.shape[0]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    assert (w < 0).any()  # Catmull-Rom has negative lobes: not a bilinear in disguise
    values = interp(phi, theta)
    for q in range(0, phi.size, 50):
        np.testing.assert_array_equal(interp(phi[q], theta[q]), values[q])


def test_bicubic_is_more_accurate_than_bilinear_on_smooth_scores(cubic_set):
    phi, theta, table, cubic = cubic_set
    linear = ScoreInterpolator(phi, theta, table, method="bilinear")
    rng = np.random.default_rng(6)
    qp, qt = rng.uniform(0, 360, 2000), rng.uniform(-78, 78, 2000)  # inside the rows
    d = np.stack([np.cos(np.radians(qt)) * np.cos(np.radians(qp)),
                  np.cos(np.radians(qt)) * np.sin(np.radians(qp)), np.sin(np.radians(qt))], 1)
    truth = np.concatenate([d, (d[:, 2] * d[:, 0])[:, None]], axis=1)
    err_cubic = np.abs(cubic(qp, qt)[:, :4] - truth).max()
    err_linear = np.abs(linear(qp, qt)[:, :4] - truth).max()
    assert err_cubic < err_linear / 3


def test_bicubic_continuous_and_smooth_across_the_phi_seam(cubic_set):
    interp = cubic_set[3]
    table = interp.scores
    theta = np.linspace(-80, 80, 41)
    below = interp(np.full_like(theta, 359.999), theta)
    above = interp(np.full_like(theta, 0.001), theta)
    assert np.abs(below - above).max() < 0.002 * np.abs(table).max()
    np.testing.assert_allclose(interp(np.full_like(theta, 360.0), theta), interp(0 * theta, theta))
    # C1: the slope just left of the seam node equals the slope just right of it
    h = 1e-3
    left = (interp(np.full_like(theta, 360.0), theta) - interp(np.full_like(theta, 360 - h),
                                                               theta)) / h
    right = (interp(np.full_like(theta, h), theta) - interp(0 * theta, theta)) / h
    scale = np.abs(left).max()
    assert np.abs(left - right).max() < 0.02 * scale
    # bilinear is not C1 there (what the test would miss if the slopes were one-sided)
    bil = ScoreInterpolator(*cubic_set[:3], method="bilinear")
    bl = (bil(np.full_like(theta, 360.0), theta) - bil(np.full_like(theta, 360 - h), theta)) / h
    br = (bil(np.full_like(theta, h), theta) - bil(0 * theta, theta)) / h
    assert np.abs(bl - br).max() > 0.1 * scale


def test_bicubic_clamps_beyond_the_outermost_rows(cubic_set):
    interp = cubic_set[3]
    rows = interp.interpolator_.axes.theta_deg
    phi = np.linspace(0, 360, 37)
    for pole, row in ((90.0, rows[-1]), (-90.0, rows[0])):
        np.testing.assert_array_equal(interp(phi, np.full_like(phi, pole)),
                                      interp(phi, np.full_like(phi, row)))
        assert np.isfinite(interp(phi, np.full_like(phi, pole))).all()


@pytest.mark.parametrize(("n_phi", "n_theta"), [(1, 5), (2, 1), (3, 2), (4, 3)])
def test_bicubic_tiny_grids(n_phi, n_theta):
    phi, theta = grid_views(n_phi, n_theta)
    table = np.random.default_rng(n_phi).standard_normal((phi.size, 3)).astype(np.float32)
    interp = ScoreInterpolator(phi, theta, table, method="bicubic")
    np.testing.assert_allclose(interp(phi, theta), table, atol=1e-6)
    _idx, w = interp.weights(np.array([17.0, 200.0]), np.array([-33.0, 50.0]))
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    assert np.isfinite(interp(np.array([17.0, 200.0]), np.array([-33.0, 50.0]))).all()


@pytest.mark.parametrize("codec", ["json", "cbor"])
def test_bicubic_manifest_round_trip_is_bit_identical(codec, cubic_set):
    host = cubic_set[3]
    manifest = host.to_manifest()
    assert manifest["method"] == "bicubic" and manifest["version"] == 1
    wire = json.loads(json.dumps(manifest)) if codec == "json" else cbor2.loads(
        cbor2.dumps(manifest))
    device = interpolator_from_manifest(wire)
    assert isinstance(device, GridCubicInterpolator)
    rng = np.random.default_rng(8)
    q_phi, q_theta = rng.uniform(0, 360, 300), rng.uniform(-90, 90, 300)
    a, b = host.weights(q_phi, q_theta), device.weights(q_phi, q_theta)
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.weights, b.weights)
    np.testing.assert_array_equal(interpolate(host.scores, *b), host(q_phi, q_theta))
    again = ScoreInterpolator.from_manifest(wire, host.scores)
    assert again.method_ == "bicubic"
    np.testing.assert_array_equal(again(q_phi, q_theta), host(q_phi, q_theta))


def test_old_bilinear_manifests_still_load_as_bilinear():
    # a manifest as written before bicubic existed (2 x 2 grid, literal)
    old = {"method": "bilinear", "version": 1, "n_views": 4, "phi0_deg": 0.0, "n_phi": 2,
           "theta_deg": [-30.0, 30.0], "view_index": [0, 1, 2, 3], "poles": "clamp"}
    interp = interpolator_from_manifest(old)
    assert type(interp) is GridInterpolator and interp.entries == 4
    idx, w = interp.weights(90.0, 0.0)
    np.testing.assert_array_equal(np.sort(idx), [0, 1, 2, 3])
    np.testing.assert_allclose(w, 0.25)
    table = np.eye(4, dtype=np.float32)
    np.testing.assert_allclose(ScoreInterpolator.from_manifest(old, table)(90.0, 0.0), 0.25)


def test_unknown_methods_are_refused_not_guessed(cubic_set):
    manifest = dict(cubic_set[3].to_manifest())
    manifest["method"] = "bicubic-v2"
    with pytest.raises(InterpolationError, match="method='bicubic-v2' is unknown"):
        interpolator_from_manifest(manifest)
    manifest = dict(cubic_set[3].to_manifest(), view_index=[0, 1])
    with pytest.raises(InterpolationError, match="view_index has 2 entries"):
        interpolator_from_manifest(manifest)


# ---------------------------------------------------------------------------
# fit --interpolation, and the device's standalone mode with a bicubic manifest


@pytest.fixture(scope="module")
def tiny_grid_db(tmp_path_factory):
    return render_tooth(tmp_path_factory.mktemp("cubic") / "t.cdb", "grid:12x4", 24, 60)


def test_fit_interpolation_option_and_standalone_device_agree(tiny_grid_db, tmp_path):
    from device_runtime.standalone import StandaloneScores
    from host.fit.model import HostModel

    out = tmp_path / "m.ecs"
    run_cli("fit", str(tiny_grid_db), "-o", str(out), "--cell", "12", "--threshold", "0.99",
            "--standalone", "--interpolation", "bicubic", "--cache", str(tmp_path / "c"))
    model = HostModel.load(out)
    assert model.image.interpolation["method"] == "bicubic"
    assert model.interpolator.method_ == "bicubic"
    device = StandaloneScores(model.image)
    assert isinstance(device.interpolator, GridCubicInterpolator)
    for phi, theta in ((10.0, 5.0), (359.9, -70.0), (123.4, 88.0)):
        np.testing.assert_array_equal(device.scores(phi, theta),
                                      model.quantized_scores(phi, theta))
    # truncating a standalone model (evaluate's rate-distortion sweep) drops the old table
    counts = np.minimum(model.image.n_components, 1)
    small = model.truncated(counts)
    assert small.scores(10.0, 5.0).shape == (int(counts.sum()),)
    assert small.interpolator.method_ == "bicubic"
    # the same model read with another method on the host (evaluation of alternatives)
    other = HostModel.load(out, interpolation="bilinear")
    assert other.interpolator.method_ == "bilinear"
    assert not np.array_equal(other.scores(10.0, 5.0), model.scores(10.0, 5.0))


def test_fit_refuses_a_grid_method_on_scattered_views_in_one_line(tmp_path):
    db = tmp_path / "f.cdb"
    run_cli("render", "builtin:tooth", "-o", str(db), "--views", "fibonacci:30", "--size", "24",
            "--samples", "60")
    res = run_cli("fit", str(db), "-o", str(tmp_path / "m.ecs"), "--cell", "12",
                  "--interpolation", "bicubic", "--cache", str(tmp_path / "c"), check=False)
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "bicubic" in lines[-1] and "grid" in lines[-1]
