"""Cinema database: format, atomic writes, resume, reading foreign databases."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from PIL import Image

from host.errors import CinemaError
from host.render.cinema import CinemaDB, CinemaWriter, format_float

CAM = {"position": [1.0, 2.0, 3.0], "look_at": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0]}


def _rows(n):
    return [(360.0 * i / n, -30.0 + 60.0 * (i % 2), CAM) for i in range(n)]


def _image(i, shape=(6, 8)):
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, size=(*shape, 3), dtype=np.uint8)


def test_format_float_always_has_a_decimal_point():
    assert format_float(0) == "0.0"
    assert format_float(3.6) == "3.6"
    assert format_float(-84) == "-84.0"
    assert format_float(1e-12) != "1e-12" and "." in format_float(1e-12)
    assert float(format_float(1 / 3)) == pytest.approx(1 / 3, rel=1e-12)


def test_write_then_read_round_trip(tmp_path):
    db_path = tmp_path / "a.cdb"
    w = CinemaWriter(db_path, {"k": 1}, _rows(5), (6, 8))
    for i in w.pending:
        w.write_image(i, _image(i))
    w.write_csv()
    db = CinemaDB.open(db_path)
    assert db.n_views == 5 and db.image_shape == (6, 8)
    assert db.settings == {"k": 1}
    np.testing.assert_allclose(db.phi_deg, [r[0] for r in _rows(5)])
    for i in range(5):
        np.testing.assert_array_equal(db.read_image(i), _image(i))
    with open(db_path / "data.csv", newline="") as f:
        header = next(csv.reader(f))
    assert header[:2] == ["phi", "theta"] and header[-1] == "FILE"


def test_csv_lists_only_written_images(tmp_path):
    w = CinemaWriter(tmp_path / "p.cdb", {}, _rows(4), (6, 8))
    w.write_image(2, _image(2))
    w.write_csv()
    db = CinemaDB.open(tmp_path / "p.cdb")
    assert db.files == ["images/view_00002.png"]


def test_resume_keeps_valid_images_and_drops_corrupt_ones(tmp_path):
    path = tmp_path / "r.cdb"
    w = CinemaWriter(path, {"s": 2}, _rows(4), (6, 8))
    for i in (0, 1, 3):
        w.write_image(i, _image(i))
    (path / "images/view_00003.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    mtime0 = (path / "images/view_00000.png").stat().st_mtime_ns
    w2 = CinemaWriter(path, {"s": 2}, _rows(4), (6, 8))
    assert w2.pending == [2, 3]
    assert (path / "images/view_00000.png").stat().st_mtime_ns == mtime0


def test_different_settings_refused_unless_overwrite(tmp_path):
    path = tmp_path / "s.cdb"
    w = CinemaWriter(path, {"a": 1}, _rows(2), (6, 8))
    w.write_image(0, _image(0))
    with pytest.raises(CinemaError, match="different settings"):
        CinemaWriter(path, {"a": 2}, _rows(2), (6, 8))
    w2 = CinemaWriter(path, {"a": 2}, _rows(2), (6, 8), overwrite=True)
    assert w2.pending == [0, 1]


def test_foreign_folder_refused(tmp_path):
    (tmp_path / "x.cdb").mkdir()
    (tmp_path / "x.cdb" / "notes.txt").write_text("mine")
    with pytest.raises(CinemaError, match="not empty"):
        CinemaWriter(tmp_path / "x.cdb", {}, _rows(1), (6, 8))


def test_reads_a_foreign_database_with_other_columns_and_rgba(tmp_path):
    root = tmp_path / "pv.cdb"
    root.mkdir()
    rows = []
    for i, (phi, theta) in enumerate([(0, -45), (90, 0), (-90, 45)]):
        rgba = np.dstack([_image(i, (5, 7)), np.full((5, 7), 255, np.uint8)])
        Image.fromarray(rgba, mode="RGBA").save(root / f"img{i}.png")
        rows.append(f"{i * 0.5},{phi},{theta},img{i}.png")
    (root / "data.csv").write_text("time,Phi,Theta,FILE\n" + "\n".join(rows) + "\n")
    db = CinemaDB.open(root)
    np.testing.assert_allclose(db.phi_deg, [0, 90, 270])
    np.testing.assert_array_equal(db.read_image(2), _image(2, (5, 7)))
    assert db.settings is None


@pytest.mark.parametrize(
    "content, message",
    [
        ("phi,FILE\n0,a.png\n", "missing column"),
        ("phi,theta,FILE\nx,0,a.png\n", "not numbers"),
        ("phi,theta,FILE\n0,0,missing.png\n", "does not exist"),
        ("phi,theta,FILE\n0,120,a.png\n", "theta outside"),
        ("phi,theta,FILE\n", "no image rows"),
    ],
)
def test_malformed_databases_give_one_line_errors(tmp_path, content, message):
    root = tmp_path / "bad.cdb"
    root.mkdir()
    Image.fromarray(_image(0)).save(root / "a.png")
    (root / "data.csv").write_text(content)
    with pytest.raises(CinemaError, match=message) as info:
        CinemaDB.open(root)
    assert "\n" not in str(info.value)


def test_corrupt_image_reported_with_its_path(tmp_path):
    root = tmp_path / "c.cdb"
    root.mkdir()
    (root / "a.png").write_bytes(b"not a png")
    (root / "data.csv").write_text("phi,theta,FILE\n0.0,0.0,a.png\n")
    with pytest.raises(CinemaError, match=r"a\.png: not a readable image"):
        CinemaDB.open(root)
