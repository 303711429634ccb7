"""`eigencast render` / `render-view` through the real CLI (subprocesses)."""

from __future__ import annotations

import csv
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import CLI, kill_render_halfway, png_count, run_cli, snapshot
from PIL import Image

from host.render.cinema import CinemaDB

SMALL = ["--size", "40", "--samples", "150"]


def test_killed_render_resumes_to_the_same_database(tmp_path):
    views = "grid:30x6"  # 180 views: long enough to be caught halfway
    ref, resumed = tmp_path / "ref.cdb", tmp_path / "resumed.cdb"
    run_cli("render", "builtin:tooth", "-o", str(ref), "--views", views, *SMALL)

    written = kill_render_halfway(["render", "builtin:tooth", "-o", str(resumed),
                                   "--views", views, *SMALL], resumed, 20)
    assert 20 <= written < 180
    # whatever the kill left must already be a consistent (partial) database
    if (resumed / "data.csv").exists():
        partial = CinemaDB.open(resumed)
        assert partial.n_views <= written

    out = run_cli("render", "builtin:tooth", "-o", str(resumed), "--views", views, *SMALL)
    assert "resuming" in out.stderr
    assert snapshot(resumed) == snapshot(ref)


def test_render_database_layout_and_sidecar(tmp_path):
    db = tmp_path / "t.cdb"
    run_cli("render", "builtin:head", "-o", str(db), "--views", "list:0,0;90,30;180,-30",
            *SMALL)
    opened = CinemaDB.open(db)
    assert opened.n_views == 3 and opened.image_shape == (40, 40)
    np.testing.assert_allclose(opened.phi_deg, [0, 90, 180])
    with open(db / "data.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0][-1] == "FILE" and all("." in v for v in rows[1][:2])
    settings = opened.settings
    assert settings["camera"]["frame"] == "visible"
    assert settings["renderer"]["samples"] == 150
    assert settings["views"]["spec"] == "list:0,0;90,30;180,-30"
    # the framed object fills the image: non-background pixels reach near the borders
    img = opened.read_image(0).max(axis=2) > 8
    rows_hit, _ = np.nonzero(img)
    assert rows_hit.min() <= 6 and rows_hit.max() >= 33


def test_render_view_writes_one_png(tmp_path):
    out = tmp_path / "one.png"
    run_cli("render-view", "builtin:tooth", "--phi", "30", "--theta", "10", "-o", str(out), *SMALL)
    assert Image.open(out).size == (40, 40)


def test_render_view_says_in_one_line_which_transfer_function_and_why(tmp_path):
    """The transfer function, the modality it is for and where that came from (here the
    values of a raw int16 CT: Hounsfield units), or that ``--tf`` chose it."""
    data = np.full((24, 28, 32), -1000, np.int16)
    data[6:18, 6:22, 6:26] = 40
    data[9:15, 9:19, 9:23] = 1200
    raw = tmp_path / "scan.raw"
    data.tofile(raw)
    volume = [str(raw), "--dims", "32,28,24", "--dtype", "int16"]
    for args, expected in [
        (volume, "transfer function ct-bone for modality ct (not in the header; the data say "
                 "so: int16 values from -1000 to 1200 with air at -1000: Hounsfield units), "
                 "window -1000 to 2000 HU"),
        ([*volume, "--tf", "generic"], "transfer function generic (--tf), window"),
        (["builtin:tooth"], "transfer function tooth for modality tooth (from the built-in "
                            "volume), window"),
    ]:
        res = run_cli("render-view", *args, "-o", str(tmp_path / "one.png"), *SMALL)
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(expected), res.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["render-view", "builtin:nope", "-o", "x.png"], "unknown built-in"),
        (["render-view", "missing.mhd", "-o", "x.png"], "missing.mhd"),
        (["render-view", "builtin:tooth", "--theta", "100", "-o", "x.png"], "theta"),
        (["render", "builtin:tooth", "-o", "d.cdb", "--views", "grid:0x3"], "grid"),
        (["render", "builtin:tooth", "-o", "d.cdb", "--size", "3"], "--size"),
        (["render", "builtin:tooth", "-o", "d.cdb", "--samples", "1"], "--samples"),
    ],
)
def test_bad_input_is_one_line_and_exit_1(tmp_path, args, message):
    res = subprocess.run([*CLI, *args], capture_output=True, text=True, cwd=tmp_path,
                         env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})
    assert res.returncode == 1, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.shared_data
@pytest.mark.parametrize("command", ["render-view", "render"])
def test_a_nii_gz_with_overwritten_bytes_is_one_line_and_writes_nothing(tmp_path, shared_path,
                                                                        command):
    """Issue 11: bytes 5000-8000 of the MNI .nii.gz overwritten still inflate, but the gzip
    CRC fails: that is an error, not a rendered image."""
    path = tmp_path / "mni.nii.gz"
    blob = bytearray(shared_path("mni152").read_bytes())
    blob[5000:8000] = bytes(3000)
    path.write_bytes(bytes(blob))
    out = tmp_path / ("out.png" if command == "render-view" else "out.cdb")
    res = run_cli(command, str(path), "-o", str(out), *SMALL, check=False)
    assert res.returncode == 1, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "corrupt compressed data" in lines[0] and "CRC" in lines[0]
    assert not out.exists()


def test_a_truncated_tiff_is_exactly_one_line(tmp_path):
    import tifffile

    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, (np.arange(16 * 32 * 32) % 251).astype(np.uint8).reshape(16, 32, 32))
    path.write_bytes(path.read_bytes()[:-100])
    res = run_cli("render-view", str(path), "-o", str(tmp_path / "o.png"), *SMALL, check=False)
    assert res.returncode == 1, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "stack.tif" in lines[0] and "truncated" in lines[0], res.stderr
    assert not (tmp_path / "o.png").exists()


def test_the_sidecar_records_an_absolute_volume_path_and_old_relative_ones_resume(tmp_path):
    import json

    from data_builders import write_mha

    from host.fit.model import HostModel

    vol_dir = tmp_path / "volumes"
    vol_dir.mkdir()
    data = np.zeros((24, 24, 24), np.uint8)
    data[6:18, 6:18, 6:18] = 200
    write_mha(vol_dir / "cube.mha", data)
    db = tmp_path / "cube.cdb"
    views = ["--views", "grid:4x3", *SMALL, "--tf", "generic"]
    run = subprocess.run([*CLI, "render", "volumes/cube.mha", "-o", str(db), *views],
                         capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    sidecar = db / "eigencast.json"
    recorded = json.loads(sidecar.read_text())["volume"]["source"]
    assert recorded == str((vol_dir / "cube.mha").resolve())  # usable from any folder
    # a model fitted from it finds its volume from elsewhere (serve --scores auto, evaluate)
    model = tmp_path / "cube.ecs"
    assert subprocess.run([*CLI, "fit", str(db), "-o", str(model), "--cell", "20"],
                          capture_output=True, text=True, cwd=vol_dir).returncode == 0
    from host.link.serving import open_true_view_scores

    assert open_true_view_scores(HostModel.load(model)).renderer is not None
    # a database written before sources were absolute (a path relative to the folder it
    # was rendered in) still resumes from that folder, whatever the spelling
    old = json.loads(sidecar.read_text())
    old["volume"]["source"] = "volumes/cube.mha"
    sidecar.write_text(json.dumps(old, indent=2, sort_keys=True) + "\n")
    before = png_count(db)
    (db / "images" / "view_00000.png").unlink()
    run = subprocess.run([*CLI, "render", "./volumes/../volumes/cube.mha", "-o", str(db),
                          *views], capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert png_count(db) == before
    assert json.loads(sidecar.read_text())["volume"]["source"] == recorded
    # a really different volume is still refused
    write_mha(vol_dir / "other.mha", data[:, :, ::-1].copy() // 2)
    run = subprocess.run([*CLI, "render", "other.mha", "-o", str(db), *views],
                         capture_output=True, text=True, cwd=vol_dir)
    assert run.returncode != 0 and "different settings" in run.stderr
