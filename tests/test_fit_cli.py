"""`eigencast fit` and `eigencast view` through the CLI on a small rendered database."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess

import numpy as np
import pytest
from cli_helpers import CLI, render_tooth, run_cli, wait_for_views
from PIL import Image

from device_runtime.orbit import canonical_view
from device_runtime.standalone import standalone_table
from host.fit.model import HostModel, auto_score_step
from host.render.cinema import CinemaDB
from protocol.image import read_image


@pytest.fixture(scope="module")
def small_db(tmp_path_factory):
    return render_tooth(tmp_path_factory.mktemp("fit") / "tooth.cdb", "grid:24x6", 48, 150)


def test_fit_writes_a_model_whose_training_views_reconstruct(small_db, tmp_path):
    out = tmp_path / "m.ecs"
    res = run_cli("fit", str(small_db), "-o", str(out), "--cell", "16", "--threshold", "0.999")
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
    """Without depth, `view` is the blend of the quantized scores at the view as a device
    takes it (float32, `canonical_view`); the depth case: test_synthesis.py."""
    out = tmp_path / "m.ecs"
    run_cli("fit", str(small_db), "-o", str(out), "--method", "cell", "--cell", "12",
            "--components", "8", "--score-step", "2.5", "--no-depth")
    png = tmp_path / "v.png"
    res = run_cli("view", str(out), "--phi", "33.3", "--theta", "-17", "-o", str(png))
    assert "blend of the scores" in res.stdout
    model = HostModel.load(out)
    assert model.score_step == 2.5
    np.testing.assert_array_equal(np.asarray(Image.open(png)),
                                  model.view(*canonical_view(33.3, -17.0)))
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
        res = run_cli(*args, check=False)
        assert res.returncode == 1
        assert len(res.stderr.strip().splitlines()) == 1 and message in res.stderr
    bad = tmp_path / "bad.ecs"
    bad.write_bytes(b"ECS\x00garbage" * 10)
    res = run_cli("view", str(bad), "--phi", "0", "--theta", "0", "-o", str(tmp_path / "v.png"),
                  check=False)
    assert res.returncode == 1 and "Traceback" not in res.stderr


def _interrupted_render(db, views: str) -> subprocess.CompletedProcess:
    """Start the real render and Ctrl-C it once 10 views are written (the user's case)."""
    # Ctrl-C as at a terminal, also when the suite runs where SIGINT is ignored (a shell's
    # background job): an ignored SIGINT is inherited, and Python then never interrupts
    proc = subprocess.Popen([*CLI, "render", "builtin:tooth", "-o", str(db), "--views", views,
                             "--size", "40", "--samples", "150"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    wait_for_views(proc, db, 10)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_fit_refuses_an_interrupted_render_until_it_is_resumed(tmp_path):
    """An interrupted render's data.csv lists only the views done: fit says how many are
    missing and how to resume, in one line, and writes nothing; --incomplete fits them; the
    advice (rerun the same render) works."""
    db, out = tmp_path / "t.cdb", tmp_path / "t.ecs"
    views = "grid:30x6"
    stopped = _interrupted_render(db, views)
    assert stopped.returncode == 130 and "rerun the same command" in stopped.stderr
    kept = CinemaDB.open(db).n_views
    assert 10 <= kept < 180
    res = run_cli("fit", str(db), "-o", str(out), "--cell", "20", check=False)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 1 and len(lines) == 1, res.stderr
    assert f"{180 - kept} of its 180 views are missing" in lines[0]
    assert "rerun the same eigencast render command" in lines[0] and "--incomplete" in lines[0]
    assert not out.exists()
    res = run_cli("fit", str(db), "-o", str(out), "--cell", "20", "--incomplete")
    assert f"fitting {kept} of the view set's 180 views" in res.stderr
    assert f"{kept} views at 40x40" in res.stdout
    # a database rendered before the sidecar recorded the count: its spec says it
    sidecar = db / "eigencast.json"
    record = json.loads(sidecar.read_text())
    del record["views"]["count"]
    sidecar.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    assert CinemaDB.open(db).expected_views == 180
    res = run_cli("render", "builtin:tooth", "-o", str(db), "--views", views, "--size", "40",
                  "--samples", "150")
    assert f"{kept} valid images kept, {180 - kept} to render" in res.stderr
    res = run_cli("fit", str(db), "-o", str(out), "--cell", "20")
    assert "180 views at 40x40" in res.stdout


def test_fit_stores_depth_and_the_standalone_table_by_default(small_db, tmp_path):
    """The best path is the default: render stores depth (small_db), fit the depth
    eigenspace and the standalone table; --no-depth and --no-standalone opt out; a database
    without depth still fits, with one line on what the device will do instead."""
    assert CinemaDB.open(small_db).depth is not None
    runs, images = {}, {}
    for name, extra in (("default", []), ("nodepth", ["--no-depth"]),
                        ("notable", ["--no-standalone"]), ("old", ["--depth", "--standalone"])):
        out = tmp_path / f"{name}.ecs"
        runs[name] = run_cli("fit", str(small_db), "-o", str(out), "--cell", "16", *extra)
        images[name] = read_image(out)
    assert images["default"].synthesis["method"] == "warp-depth-3"  # with the noise floor
    assert "noise_floor" in images["default"].sections
    assert "standalone table" in runs["default"].stdout and "depth:" in runs["default"].stdout
    assert "noise floor: " in runs["default"].stdout
    assert "splat filter [1, " in runs["default"].stdout
    assert images["old"].synthesis == images["default"].synthesis  # old scripts still work
    assert images["nodepth"].synthesis is None and standalone_table(images["nodepth"])
    assert images["notable"].synthesis is None and standalone_table(images["notable"]) is None
    assert all("blend" not in r.stderr for r in runs.values())
    res = run_cli("fit", str(small_db), "-o", str(tmp_path / "x.ecs"), "--no-standalone",
                  "--depth", check=False)
    assert res.returncode == 1 and "--depth needs the standalone table" in res.stderr
    # a database without depth (here: rendered with --no-depth, as an old one is)
    flat = tmp_path / "flat.cdb"
    run_cli("render", "builtin:tooth", "-o", str(flat), "--views", "grid:8x3", "--size", "40",
            "--samples", "60", "--no-depth")
    res = run_cli("fit", str(flat), "-o", str(tmp_path / "flat.ecs"), "--cell", "20")
    lines = res.stderr.strip().splitlines()
    note = [line for line in lines if "blend" in line]
    assert len(note) == 1 and "has no depth maps" in note[0] and "eigencast render" in note[0]
    flat_image = read_image(tmp_path / "flat.ecs")
    assert flat_image.synthesis is None and standalone_table(flat_image) is not None
    res = run_cli("fit", str(flat), "-o", str(tmp_path / "y.ecs"), "--depth", check=False)
    assert res.returncode == 1 and "has no depth maps" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "y.ecs").exists()
    (flat / "eigencast.json").unlink()  # as another tool (ParaView) writes a database
    res = run_cli("fit", str(flat), "-o", str(tmp_path / "z.ecs"), "--cell", "20")
    note = [line for line in res.stderr.splitlines() if "blend" in line]
    assert len(note) == 1 and "render the volume with eigencast render" in note[0]


def test_fit_says_what_the_file_holds_beyond_the_device_image(small_db, tmp_path):
    out = tmp_path / "m.ecs"
    res = run_cli("fit", str(small_db), "-o", str(out), "--cell", "16")
    found = re.search(r"device image ([\d.]+) MB \+ host annex ([\d.]+) MB", res.stdout)
    assert found, res.stdout
    device, annex = float(found.group(1)), float(found.group(2))
    assert abs(device + annex - out.stat().st_size / 1e6) <= 0.011
    assert annex > 0


def test_fit_says_where_its_image_stack_stays_keeps_one_and_no_cache_keeps_none(small_db,
                                                                               tmp_path):
    """fit kept an uncompressed image stack per cell size in DB.cdb/.eigencast-cache (85 MB,
    4x the database, for one run in the report) and never said so. It says so in one line,
    the folder holds the last fit's stack only, and --no-cache keeps none."""
    cache = small_db / ".eigencast-cache"
    out = tmp_path / "m.ecs"
    first = run_cli("fit", str(small_db), "-o", str(out), "--cell", "12", "--no-depth")
    said = [line for line in first.stdout.splitlines() if "image stack" in line]
    size = sum(f.stat().st_size for f in cache.iterdir())
    assert len(said) == 1 and str(cache) in said[0] and f"{size / 1e6:.0f} MB" in said[0]
    assert "--no-cache" in said[0]
    run_cli("fit", str(small_db), "-o", str(out), "--cell", "16", "--no-depth")
    assert sorted(f.name for f in cache.iterdir()) == [
        "stack-48x48-cell16x16.u8", "stack-48x48-cell16x16.u8.json"]  # one stack, not two
    copy = tmp_path / "copy.cdb"
    shutil.copytree(small_db, copy, ignore=shutil.ignore_patterns(".eigencast-cache"))
    none = run_cli("fit", str(copy), "-o", str(out), "--cell", "12", "--no-depth", "--no-cache")
    assert not (copy / ".eigencast-cache").exists() and "image stack" not in none.stdout
    refused = run_cli("fit", str(copy), "-o", str(out), "--no-cache", "--cache", str(tmp_path),
                      check=False)
    assert refused.returncode == 1 and "pick one" in refused.stderr
