"""`eigencast fit` and `eigencast view` through the CLI on a small rendered database."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from host.fit.model import HostModel, auto_score_step
from host.render.cinema import CinemaDB
from protocol.image import read_image

CLI = [sys.executable, "-m", "host.cli"]


def _run(*args, check=True):
    return subprocess.run([*CLI, *args], capture_output=True, text=True, check=check)


@pytest.fixture(scope="module")
def small_db(tmp_path_factory):
    db = tmp_path_factory.mktemp("fit") / "tooth.cdb"
    _run("render", "builtin:tooth", "-o", str(db), "--views", "grid:24x6", "--size", "48",
         "--samples", "150")
    return db


def test_fit_writes_a_model_whose_training_views_reconstruct(small_db, tmp_path):
    out = tmp_path / "m.ecs"
    res = _run("fit", str(small_db), "-o", str(out), "--cell", "16", "--threshold", "0.999")
    assert "components/cell" in res.stdout
    model = HostModel.load(out)
    db = CinemaDB.open(small_db)
    assert model.image.provenance["render"] == db.settings
    assert model.image.provenance["fit"]["method"] == "adaptive"
    # at a training view the interpolated scores are the view's own: the device frame
    # is the training image up to T=0.999 truncation, int8 and score quantization
    for i in (0, 37, 100):
        frame = model.view(db.phi_deg[i], db.theta_deg[i])
        err = frame.astype(float) - db.read_image(i)
        assert np.sqrt(np.mean(err**2)) < 4.0


def test_view_cli_matches_host_model(small_db, tmp_path):
    out = tmp_path / "m.ecs"
    _run("fit", str(small_db), "-o", str(out), "--method", "cell", "--cell", "12",
         "--components", "8", "--score-step", "2.5")
    png = tmp_path / "v.png"
    _run("view", str(out), "--phi", "33.3", "--theta", "-17", "-o", str(png))
    model = HostModel.load(out)
    assert model.score_step == 2.5
    np.testing.assert_array_equal(np.asarray(Image.open(png)), model.view(33.3, -17.0))
    image = read_image(out)
    # cell mode keeps K per cell, capped at the cell's rank (near-empty corners)
    assert image.n_components.max() == 8 and (image.n_components == 8).mean() > 0.5


def test_auto_score_step_meets_its_noise_budget():
    class M:
        n_components_ = np.array([0, 10, 30])
        cell_shape_ = (10, 10)

    step = auto_score_step(M(), mse=0.5)
    # mean k over cells with components = 20; d = 300: 20 * s^2 / 12 / 300 == 0.5
    assert 20 * step**2 / 12 / 300 == pytest.approx(0.5)


def test_fit_and_view_errors_are_one_line(tmp_path):
    for args, message in [
        (["fit", str(tmp_path / "none.cdb"), "-o", str(tmp_path / "m.ecs")], "none.cdb"),
        (["view", str(tmp_path / "none.ecs"), "--phi", "0", "--theta", "0", "-o",
          str(tmp_path / "v.png")], "none.ecs"),
    ]:
        res = _run(*args, check=False)
        assert res.returncode == 1
        assert len(res.stderr.strip().splitlines()) == 1 and message in res.stderr
    bad = tmp_path / "bad.ecs"
    bad.write_bytes(b"ECS\x00garbage" * 10)
    res = _run("view", str(bad), "--phi", "0", "--theta", "0", "-o", str(tmp_path / "v.png"),
               check=False)
    assert res.returncode == 1 and "Traceback" not in res.stderr
