"""Truncation without refitting, the target search and ``eigencast fit --target``."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from cli_helpers import run_cli

from host.evaluate import DevicePath, structural_similarity
from host.evaluate.target import (
    HeldOutViews,
    Target,
    TargetError,
    level_ladder,
    parse_target,
    search_target,
)
from host.fit.model import (
    HostModel,
    build_image,
    components_for_threshold,
    fit_database,
    save_model,
)
from host.render.cinema import CinemaDB
from host.render.settings import RenderSettings, ViewRenderer
from protocol.image import read_image


@pytest.fixture(scope="module")
def high_model(tooth_db):
    """An adaptive model fitted at a high threshold, in memory."""
    db = CinemaDB.open(tooth_db)
    model = fit_database(db, method="adaptive", cell=16, threshold=0.999, progress=False)
    image, annex = build_image(model, db, measure_int8=False)
    return HostModel.from_image(image, annex)


@pytest.fixture(scope="module")
def heldout(tooth_db):
    db = CinemaDB.open(tooth_db)
    scene = ViewRenderer.open(RenderSettings.from_record(db.settings, what="db"))
    rng = np.random.default_rng(3)
    phi = rng.uniform(0, 360, 8)
    theta = np.degrees(np.arcsin(rng.uniform(-0.9, 0.9, 8)))
    images = np.stack([scene.render_rgb8(p, t) for p, t in zip(phi, theta)])
    return HeldOutViews(phi, theta, images, "8 test views")


# ----------------------------------------------------------------------------- truncation


def test_components_for_threshold_matches_the_rule_by_hand():
    counts = np.array([3, 0, 1, 2])
    eig = np.array([5.0, 3.0, 2.0, 4.0, 0.6, 0.4])
    total = np.array([10.0, 0.0, 5.0, 1.0])
    # cell 0: 5/10=.5, 8/10=.8, 10/10=1; cell 2: 4/5=.8 (cap 1); cell 3: .6, 1.0
    assert components_for_threshold(eig, counts, total, 0.5).tolist() == [1, 0, 1, 1]
    assert components_for_threshold(eig, counts, total, 0.8).tolist() == [2, 0, 1, 2]
    assert components_for_threshold(eig, counts, total, 0.95).tolist() == [3, 0, 1, 2]
    with pytest.raises(ValueError, match="threshold"):
        components_for_threshold(eig, counts, total, 1.5)


def test_truncating_equals_fitting_at_the_lower_threshold(tooth_db, high_model):
    db = CinemaDB.open(tooth_db)
    lower = fit_database(db, method="adaptive", cell=16, threshold=0.97, progress=False)
    counts = high_model.components_for(threshold=0.97)
    np.testing.assert_array_equal(counts, lower.n_components_)
    # at 8 bits for every component (bit allocation depends on the whole model's residual)
    image_high, annex_high = build_image(
        fit_database(db, method="adaptive", cell=16, threshold=0.999, progress=False), db,
        measure_int8=False, bit_budget=0.0)
    eight = HostModel.from_image(image_high, annex_high)
    cut = eight.truncated(counts)
    image, _ = build_image(lower, db, measure_int8=False, bit_budget=0.0)
    np.testing.assert_array_equal(cut.image.eigenimages, image.eigenimages)
    np.testing.assert_allclose(cut.image.scales, image.scales, rtol=1e-6)
    np.testing.assert_allclose(cut.training_scores, lower.scores_, rtol=1e-5, atol=1e-3)
    # and the truncated model still reconstructs through the device path
    assert cut.view(10.0, 5.0).shape == (40, 40, 3)
    assert cut.image.n_coefficients < high_model.image.n_coefficients


def test_truncated_model_survives_a_round_trip(high_model, tmp_path):
    cut = high_model.truncated(high_model.components_for(threshold=0.95), score_step=3.0)
    path = tmp_path / "cut.ecs"
    save_model(path, cut.image, cut.annex())
    back = HostModel.load(path)
    assert back.score_step == 3.0
    np.testing.assert_array_equal(back.image.n_components, cut.image.n_components)
    np.testing.assert_array_equal(back.eigenvalues, cut.eigenvalues)
    np.testing.assert_array_equal(back.view(33.0, -12.0), cut.view(33.0, -12.0))


def test_ladder_is_cheapest_first_and_distinct(high_model):
    knob, ladder = level_ladder(high_model)
    assert knob == "threshold"
    assert ladder[-1][0] == pytest.approx(0.999)
    sums = [int(c.sum()) for _, c in ladder]
    assert sums == sorted(sums) and len(set(map(bytes, (c.tobytes() for _, c in ladder)))) == \
        len(ladder)
    np.testing.assert_array_equal(ladder[-1][1], high_model.image.n_components)


# ----------------------------------------------------------------------------- search


def test_parse_target_errors_are_clear():
    assert parse_target("ssim=0.95") == Target("ssim", 0.95)
    assert parse_target("FLIP=0.05") == Target("flip", 0.05)
    for text, message in [("sharpness=3", "expected one of"), ("ssim", "expected one of"),
                          ("ssim=high", "not a number"), ("ssim=1.5", "within")]:
        with pytest.raises(TargetError, match=message):
            parse_target(text)


def _ssim_of(model, heldout):
    """Held-out mean SSIM and bytes through the device path, computed here independently."""
    path = DevicePath(model)
    values, sizes = [], []
    for p, t, image in zip(heldout.phi_deg, heldout.theta_deg, heldout.images):
        frame, size = path.frame(p, t)
        values.append(structural_similarity(image, frame))
        sizes.append(size)
    return float(np.mean(values)), float(np.mean(sizes))


def test_search_picks_the_cheapest_setting_that_meets_the_target(high_model, heldout):
    _, ladder = level_ladder(high_model)
    top, _ = _ssim_of(high_model.truncated(ladder[-1][1], score_step=high_model.score_step),
                      heldout)
    low, _ = _ssim_of(high_model.truncated(ladder[0][1], score_step=high_model.score_step),
                      heldout)
    assert low < top
    target = Target("ssim", low + 0.6 * (top - low))
    result = search_target(high_model, heldout, target, progress=False)
    choice = result.choice
    # the choice really reaches the target on the held-out views (measured independently)
    quality, size = _ssim_of(high_model.truncated(choice.counts, score_step=choice.score_step),
                             heldout)
    assert quality == pytest.approx(choice.quality, abs=1e-9) and quality >= target.value
    assert size == pytest.approx(choice.bytes_per_view)
    # every cheaper try misses it, and the next rung down at the chosen step does too
    cheaper = [t for t in result.tries if t.bytes_per_view < choice.bytes_per_view]
    assert cheaper and not any(t.met for t in cheaper)
    below = [t for t in result.tries if t.step_factor == choice.step_factor
             and t.level < choice.level]
    assert below and not max(below, key=lambda t: t.level).met
    table = result.table()
    assert "<- chosen" in table and "chose threshold" in table


def test_search_reports_an_unreachable_target_with_the_best_reached(high_model, heldout):
    with pytest.raises(TargetError, match=r"unreachable: the best held-out ssim is 0\.\d+"):
        search_target(high_model, heldout, Target("ssim", 0.99999), progress=False)


def test_search_with_components_for_cell_models(tooth_db, heldout):
    db = CinemaDB.open(tooth_db)
    model = fit_database(db, method="cell", cell=20, components=12, progress=False)
    image, annex = build_image(model, db, measure_int8=False)
    host = HostModel.from_image(image, annex)
    knob, ladder = level_ladder(host)
    assert knob == "components" and ladder[0][0] == 1.0
    result = search_target(host, heldout, Target("flip", 0.2), step_factors=(1.0,),
                           progress=False)
    assert result.choice.knob == "components" and result.choice.met


# ----------------------------------------------------------------------------- the command


def test_fit_target_cli_writes_the_chosen_model(tooth_db, tmp_path):
    out = tmp_path / "auto.ecs"
    res = run_cli("fit", str(tooth_db), "-o", str(out), "--cell", "16", "--target", "ssim=0.8",
                  "--holdout", "random:6:2")
    assert "<- chosen" in res.stdout and "wrote" in res.stdout
    image = read_image(out)
    target = image.provenance["target"]
    assert target["metric"] == "ssim" and target["choice"]["met"]
    assert target["fitted_threshold"] == pytest.approx(0.999)
    assert image.provenance["fit"]["threshold"] == pytest.approx(target["choice"]["threshold"])
    assert image.score_quantization["step"] == pytest.approx(target["choice"]["score_step"],
                                                              rel=1e-6)
    assert "ray-cast" in target["holdout"]


def test_fit_target_with_a_test_database(tooth_db, tmp_path):
    test_db = tmp_path / "test.cdb"
    run_cli("render", "builtin:tooth", "-o", str(test_db), "--views", "random:5:9", "--size", "40",
            "--samples", "120")
    out = tmp_path / "t.ecs"
    res = run_cli("fit", str(tooth_db), "-o", str(out), "--cell", "16", "--target", "flip=0.2",
                  "--test-db", str(test_db))
    assert "test database" in res.stdout
    assert read_image(out).provenance["target"]["holdout"].startswith("test database")
    other = tmp_path / "other.cdb"
    run_cli("render", "builtin:tooth", "-o", str(other), "--views", "random:3", "--size", "40",
            "--samples", "60")
    res = run_cli("fit", str(tooth_db), "-o", str(out), "--cell", "16", "--target", "flip=0.2",
                  "--test-db", str(other), check=False)
    assert res.returncode == 1 and "renderer differ" in res.stderr


def test_fit_target_falls_back_to_own_views_without_render_settings(tooth_db, tmp_path):
    foreign = tmp_path / "foreign.cdb"
    shutil.copytree(tooth_db, foreign, ignore=shutil.ignore_patterns(".eigencast-cache"))
    (foreign / "eigencast.json").unlink()
    out = tmp_path / "f.ecs"
    res = run_cli("fit", str(foreign), "-o", str(out), "--method", "cell", "--cell", "20",
                  "--components", "10", "--target", "flip=0.3", "--holdout", "random:8")
    assert "held out of" in res.stdout
    image = read_image(out)
    assert image.provenance["target"]["refitted_on_all_views"] is True
    assert len(image.views["phi_deg"]) == 144  # the written model uses every view


def test_fit_target_errors_are_one_line(tooth_db, tmp_path):
    out = tmp_path / "x.ecs"
    for args, message in [
        (["--target", "beauty=1"], "expected one of"),
        (["--target", "ssim=0.99999", "--holdout", "random:4"], "best held-out ssim"),
        (["--test-db", str(tmp_path / "none.cdb")], "only with --target"),
    ]:
        res = run_cli("fit", str(tooth_db), "-o", str(out), "--cell", "16", *args, check=False)
        assert res.returncode == 1, res.stderr
        lines = res.stderr.strip().splitlines()
        assert message in lines[-1] and "Traceback" not in res.stderr
        assert all(not line.startswith("eigencast fit: error") for line in lines[:-1])
        assert not out.exists()
