"""``eigencast demo``: the equal-quality codec search, and a tiny headless demo run twice (the
second run reuses the render, the fit and the device's flash)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image
from runtime_helpers import read_frames

from host.demo import DemoSettings, equal_object_quality, run_demo
from host.evaluate import structural_similarity


def _jpeg(image, quality):
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=quality)
    return len(buf.getvalue()), np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"))


@pytest.fixture(scope="module")
def head_view(tmp_path_factory):
    """A 96 px ray-cast of the built-in head (dark, noisy background: where JPEG's SSIM jumps
    up and down with the quality) and its object mask."""
    from host.cli import main as eigencast

    db = tmp_path_factory.mktemp("head") / "head.cdb"
    assert eigencast(["render", "builtin:head", "-o", str(db), "--views", "list:30,15",
                      "--size", "96", "--samples", "120", "--no-depth"]) == 0
    image = np.asarray(Image.open(next((db / "images").iterdir())).convert("RGB"))
    return image, image.max(axis=2) > 2


@pytest.mark.parametrize("quality", [10, 30])
def test_equal_quality_is_the_smallest_file_reaching_the_object_ssim(head_view, quality):
    """Checked against every quality: a codec's SSIM is not monotone in the quality on a
    ray-cast, so a bisection picks a file 20-30 % too large here."""
    ref, mask = head_view
    test = _jpeg(ref, quality)[1]  # a frame exactly as good as that JPEG
    got = equal_object_quality(ref, test, mask, codecs=("jpeg",))
    target = structural_similarity(ref, test, mask=mask)
    assert got["object_ssim"] == pytest.approx(target)
    from host.evaluate import encode_image

    smallest = min(c.size_bytes for c in (encode_image(ref, "jpeg", q) for q in range(1, 101))
                   if structural_similarity(ref, c.decode(), mask=mask) >= target)
    assert got["jpeg_bytes"] == smallest
    assert got["jpeg_object_ssim"] >= target


def test_equal_quality_reports_the_best_file_when_none_reaches(head_view):
    ref, mask = head_view
    perfect = equal_object_quality(ref, ref, mask, codecs=("jpeg",))
    assert perfect["object_ssim"] == pytest.approx(1.0) and perfect["jpeg_object_ssim"] < 1.0


def _every_frame_shown_or_coalesced(summary: dict) -> None:
    """The device showed every served correction it kept up with, each on its own frame.

    A device that falls behind (a loaded CI machine) shows the newest frame and counts the
    ones it skipped as coalesced; none may be lost otherwise, and the orbit's last is shown.
    """
    device = summary["device"]
    assert device["decode_errors"] == 0 and device["stale_dropped"] == 0
    assert device["corrected_frames"] + device["coalesced"] == summary["serve"]["frames"]
    assert device["frames_presented"] > device["corrected_frames"] >= 1  # own frames too


def test_headless_demo_runs_and_reuses_its_cache(tmp_path, capsys):
    settings = DemoSettings(volume="builtin:tooth", views="grid:8x3", size=36, samples=40,
                            cell=12, orbit="steps:6:15", every=1, compare_views=2)
    work = tmp_path / "demo"
    first = run_demo(work, settings=settings, headless=True)
    out = capsys.readouterr()
    assert first["provision"] == "installed"
    # the one served path: every orbit view is a correction of the device's own frame
    assert first["serve"]["frames"] == 6 and first["serve"]["correction_frames"] == 6
    assert first["serve"]["key_frames"] == 0
    _every_frame_shown_or_coalesced(first)
    quality = first["quality"]
    assert quality["views"] == 2
    for kind in ("own", "streamed", "rest"):
        assert 0 < quality[f"{kind}_object_ssim"] <= 1
        for codec in ("jpeg", "webp", "avif"):
            assert quality[f"{kind}_{codec}_bytes"] > 0
    # at rest the complete correction: never below the device's own frame
    assert quality["rest_object_ssim"] >= quality["own_object_ssim"] - 1e-9
    assert "demo summary" in out.out and "the device's own frame" in out.out
    assert "at rest" in out.out and "AVIF" in out.out and "what it depends on" in out.out
    assert "comparing with JPEG, WebP and AVIF" in out.err  # progress while it is computed
    assert "with depth" in out.err
    assert "tcp-listen://127.0.0.1:" in out.err  # the local link is shown to the user
    model = work / "tooth.ecs"
    fitted = model.stat().st_mtime_ns
    rows = read_frames(work / "frames")
    assert {r["kind"] for r in rows} >= {"corrected"}
    assert float(rows[-1]["phi_deg"]) == pytest.approx(300.0)  # the orbit's last view is shown

    second = run_demo(work, settings=settings, headless=True)
    err = capsys.readouterr().err
    assert "0 to render" in err
    assert "fitted from this database with these settings; kept" in err
    assert model.stat().st_mtime_ns == fitted
    assert second["provision"] == "already-active"
    _every_frame_shown_or_coalesced(second)
