"""Serving the scores of fresh ray-casts: ``HostModel.project``, ``serve --scores render|refine``.

Interpolated scores blend neighbouring training views (docs/rate-distortion.md); a host that
holds the volume can instead ray-cast the view asked for and send the scores that best
reproduce it on the device's own eigenimages.
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from provision_helpers import KEY, mem_name
from runtime_helpers import RuntimeThread, read_frames, serve_cli, wait_until

from device_runtime.orbit import canonical_view, parse_orbit
from host.fit.model import HostModel
from host.link.provisioning import provision
from host.link.serving import TrueViewScores, open_true_view_scores, serve
from host.render.cinema import CinemaDB
from host.render.settings import RenderSettings, ViewRenderer


@pytest.fixture(scope="module")
def true_views(model):
    return open_true_view_scores(model)


def _quiet(line: str) -> None:
    pass


def _mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))


def _projected(model: HostModel, true_views: TrueViewScores, view) -> np.ndarray:
    return model.reconstruct(model.quantize(true_views(view)))


def test_projection_fits_a_training_view_at_least_as_well_as_its_own_scores(model, model_path):
    db = CinemaDB.open(Path(model_path).parent / "tooth.cdb")
    for i in (0, 7, 33):
        truth = db.read_image(i)
        own = model.reconstruct(model.training_scores[i])
        fitted = model.reconstruct(model.project(truth))
        # least squares on the int8 basis is optimal per cell; rounding to uint8 is the slack
        assert _mse(fitted, truth) <= _mse(own, truth) + 0.3


def test_projection_of_a_novel_view_beats_interpolation(model, true_views):
    gains = []
    for view in [(11.0, 13.0), (200.0, -40.0), (97.5, 51.0)]:
        truth, _alpha = true_views.renderer.render(*view)
        interpolated = _mse(model.view(*view), truth)
        projected = _mse(_projected(model, true_views, view), truth)
        gains.append(interpolated / projected)
    assert min(gains) > 1.5, gains  # the blend of views 72 x 36 degrees apart is far off


def test_projection_refuses_an_image_of_another_size(model):
    with pytest.raises(ValueError, match="model's is"):
        model.project(np.zeros((8, 8, 3), np.uint8))


def test_true_view_scores_cache_repeated_views(true_views):
    before = true_views.renders
    a = true_views((5.0, 5.0))
    b = true_views((5.0, 5.0))
    assert a is b and true_views.renders == before + 1


def test_true_view_scores_refuse_a_renderer_of_another_size(model):
    settings = RenderSettings.from_record(model.render_settings, what="test")
    renderer = ViewRenderer.open(dataclasses.replace(settings, width=20, height=20))
    with pytest.raises(Exception, match="20x20 images"):
        TrueViewScores(model, renderer)


def _provisioned_device(tmp_path, model_path, name, **kwargs):
    frames = tmp_path / "frames"
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", frames=frames,
                           **kwargs)
    result = provision(model_path, f"mem://{name}?end=a&pace=0", key=KEY, show_progress=False,
                       log=_quiet)
    assert result.confirmed is True
    return device, frames


def _frame(folder: Path, row: dict) -> np.ndarray:
    return np.asarray(Image.open(folder / row["file"]))


def test_render_mode_streams_the_projection_of_every_orbit_view(tmp_path, model_path, model,
                                                                true_views):
    name = mem_name("render")
    device, frames = _provisioned_device(tmp_path, model_path, name)
    with device:
        stats = serve(model_path, f"mem://{name}?end=a&pace=0", key=KEY, model=model,
                      orbit=parse_orbit("steps:5:25"), fps=0, log=_quiet, scores="render",
                      true_views=true_views)
        assert stats.frames == 5 and stats.rendered_frames == 5 and stats.key_frames == 1
        assert "5 ray-cast" in stats.line()
        wait_until(lambda: any(float(r["phi_deg"]) == 288.0 for r in read_frames(frames)), 10,
                   "the orbit's last view")
    rows = read_frames(frames)
    # a device that falls behind (a loaded machine) shows the newest frame and counts the
    # ones it skipped: every one of the 5 is shown or counted, none lost otherwise
    assert len(rows) + device.device.stats_dict()["coalesced"] == 5
    for row in rows:
        view = (float(row["phi_deg"]), float(row["theta_deg"]))
        got = _frame(frames, row)
        np.testing.assert_array_equal(got, _projected(model, true_views, view))
        assert not np.array_equal(got, model.view(*view))  # not the interpolated frame


def test_refine_sends_the_interpolated_frame_then_the_ray_cast_one(tmp_path, model_path, model,
                                                                   true_views):
    name = mem_name("refine")
    device, frames = _provisioned_device(tmp_path, model_path, name, request_rate_hz=1000)
    stop = threading.Event()
    result: dict = {}
    logs: list[str] = []

    def host() -> None:
        result["stats"] = serve(model_path, f"mem://{name}?end=a&pace=0", key=KEY, model=model,
                                stop=stop, log=logs.append, scores="refine",
                                true_views=true_views, refine_delay_s=0.05)

    view = canonical_view(123.25, -17.5)
    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    try:
        wait_until(lambda: device.device.runtime_stats.frames_presented >= 1, 20, "first frame")
        device.device.set_view(*view)

        def shown() -> list[dict]:
            return [r for r in read_frames(frames)
                    if (float(r["phi_deg"]), float(r["theta_deg"])) == view]

        wait_until(lambda: len(shown()) >= 2, 30, "the refined frame")
    finally:
        stop.set()
        thread.join(10)
        device.stop()
    stats = result["stats"]
    assert stats.refined_frames >= 1 and stats.rendered_views >= 1, logs
    assert f"{stats.refined_frames} refined" in stats.line()
    assert any("refine scores" in line for line in logs)  # the mode is logged
    rows = shown()
    np.testing.assert_array_equal(_frame(frames, rows[0]), model.view(*view))
    np.testing.assert_array_equal(_frame(frames, rows[-1]), _projected(model, true_views, view))
    assert rows[-1]["key"] == "0"  # the refinement is a delta against the interpolated frame


class _BrokenRenderer:
    renders = 0
    render_seconds = 0.0

    def __call__(self, view):
        raise RuntimeError("the GPU fell off")


def test_refine_falls_back_to_interpolation_when_ray_casting_fails(tmp_path, model_path, model):
    name = mem_name("refine-broken")
    device, _frames = _provisioned_device(tmp_path, model_path, name, request_rate_hz=1000)
    stop = threading.Event()
    logs: list[str] = []
    result: dict = {}

    def host() -> None:
        result["stats"] = serve(model_path, f"mem://{name}?end=a&pace=0", key=KEY, model=model,
                                stop=stop, log=logs.append, scores="refine",
                                true_views=_BrokenRenderer(), refine_delay_s=0.0)

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    try:
        wait_until(lambda: device.device.runtime_stats.frames_presented >= 1, 20, "first frame")
        device.device.set_view(40.0, 10.0)
        wait_until(lambda: any("ray-casting failed" in line for line in logs), 20,
                   "the fallback notice")
        device.device.set_view(50.0, 10.0)  # still served, interpolated
        wait_until(lambda: device.device._shown_view == (50.0, 10.0), 20, "the next view")
    finally:
        stop.set()
        thread.join(10)
        device.stop()
    assert result["stats"].refined_frames == 0
    assert any("the GPU fell off" in line for line in logs)


def test_serve_rejects_an_unknown_score_mode(model_path):
    with pytest.raises(ValueError, match="scores='magic'"):
        serve(model_path, "mem://nowhere", scores="magic", log=_quiet)


@pytest.mark.parametrize("mode", ["render", "motion"])
def test_cli_ray_cast_modes_without_the_volume_are_one_line(tmp_path, model_path, mode):
    run = serve_cli(str(model_path), "--port", "mem://nobody", "--scores", mode, "--volume",
                    str(tmp_path / "missing.mhd"))
    assert run.returncode != 0
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and f"--scores {mode}" in lines[0] and "Traceback" not in run.stderr


def test_cli_refine_delay_must_not_be_negative(model_path):
    run = serve_cli(str(model_path), "--port", "mem://nobody", "--refine-delay", "-1")
    assert run.returncode != 0 and "--refine-delay" in run.stderr
    assert "Traceback" not in run.stderr
