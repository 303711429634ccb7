"""The scores of fresh ray-casts (``HostModel.project``, `TrueViewScores`) and what ``serve``
does when it cannot ray-cast.

Interpolated scores blend neighbouring training views (docs/design-notes.md); a host that
holds the volume can instead ray-cast the view asked for and find the scores that best
reproduce it on the device's own eigenimages (evaluate's ``pca_render``, and what every
served frame converges to once its view rests).
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np
import pytest
from provision_helpers import KEY, mem_name
from runtime_helpers import RuntimeThread, serve_cli, wait_until

from device_runtime.orbit import parse_orbit
from host.fit.model import HostModel
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import serve
from host.link.true_views import TrueViewScores, open_true_view_scores
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
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", **kwargs)
    result = provision(model_path, f"mem://{name}?end=a&pace=0",
                       ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
    assert result.confirmed is True
    return device


class _BrokenRenderer:
    """A ray-caster that fails: the model's real one, whose pixels raise."""

    def __init__(self, real) -> None:
        self.real = real
        self.settings = real.settings
        self.image_shape = real.image_shape
        self.renderer = self

    def coarser(self, factor):
        return self

    def render_pixels(self, *args, **kwargs):
        raise RuntimeError("the GPU fell off")


class _FlakyRenderer:
    """The model's real ray-caster, whose ``render_pixels`` raises where ``fail(cameras)``
    says (``cameras``: the cameras of every call so far, this one last; the coarse caster
    of moving frames counts with the exact one); ``fail=None``: always."""

    def __init__(self, real, fail) -> None:
        self.real = real
        self.settings = real.settings
        self.image_shape = real.image_shape
        self.renderer = _FlakyCaster(real.renderer, fail, [])


class _FlakyCaster:
    def __init__(self, caster, fail, cameras) -> None:
        self.caster, self.fail, self.cameras = caster, fail, cameras

    def coarser(self, factor):
        return _FlakyCaster(self.caster.coarser(factor), self.fail, self.cameras)

    def composite(self, rgba):
        return self.caster.composite(rgba)

    def render_pixels(self, camera, *args, **kwargs):
        self.cameras.append(camera)
        if self.fail is None or self.fail(self.cameras):
            raise RuntimeError("the GPU fell off")
        return self.caster.render_pixels(camera, *args, **kwargs)


def _nth_call(n):
    return lambda cameras: len(cameras) == n + 1


def _refining_the_first_view(cameras):
    first = cameras[0].position
    return len(cameras) > 1 and bool(np.allclose(cameras[-1].position, first))


@pytest.mark.parametrize("predict", [True, False])
def test_serving_goes_on_when_ray_casting_fails(tmp_path, model_path, model, true_views,
                                               predict):
    """A ray-caster that always raises costs every view, never the session: a device that
    synthesizes its own frames keeps showing them, another one gets interpolated scores; the
    failures are counted and said in one line (not one per view)."""
    name = mem_name(f"broken-{predict}")
    device = _provisioned_device(tmp_path, model_path, name, predict=predict)
    stop = threading.Event()
    logs: list[str] = []
    result: dict = {}

    def host() -> None:
        result["stats"] = serve(model_path, f"mem://{name}?end=a&pace=0", ServeOptions(key=KEY),
                                ServeParts(model=model, stop=stop, log=logs.append,
                                           renderer=_FlakyRenderer(true_views.renderer, None)))

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    try:
        wait_until(lambda: any("ray-casting failed" in line for line in logs), 20,
                   "the failure notice")
        device.device.set_view(50.0, 10.0)
        # still served: interpolated scores, or (predicting) its own frame, uncorrected
        wait_until(lambda: device.device._shown_view == (50.0, 10.0), 20, "the next view")
    finally:
        stop.set()
        thread.join(10)
        device.stop()
    stats = result["stats"]
    assert stats.correction_frames == 0 and stats.motion_frames == 0
    assert stats.failed_views >= 1
    failed = [line for line in logs if "ray-casting failed" in line]
    assert 1 <= len(failed) <= 1 + stats.stream_seconds / 10  # said at most every 10 s
    assert "the GPU fell off" in failed[0] and "serving goes on" in failed[0]
    assert f"{stats.failed_views} views whose ray-cast failed" in logs[-1]
    if not predict:
        assert stats.key_frames + stats.delta_frames >= 1


@pytest.mark.parametrize("predict", [True, False])
def test_serve_keeps_ray_casting_after_one_failed_view(tmp_path, model_path, model, true_views,
                                                      predict):
    """One view whose ray-cast raises costs that view alone: it is counted, said once, and
    every later view of the orbit is ray-cast (corrected, on a predicting device) again."""
    name = mem_name(f"flaky-{predict}")
    device = _provisioned_device(tmp_path, model_path, name, predict=predict)
    logs: list[str] = []
    with device:
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, fps=0, orbit=parse_orbit("steps:6:10")),
                      ServeParts(model=model, log=logs.append,
                                 renderer=_FlakyRenderer(true_views.renderer, _nth_call(0))))
    assert stats.frames == 6
    assert stats.motion_frames == 5  # every view but the failed one was ray-cast
    assert stats.failed_views == 1
    failed = [line for line in logs if "ray-casting failed" in line]
    assert len(failed) == 1 and "view (0, 10)" in failed[0] and "1 failed view " in failed[0]
    if predict:
        assert stats.correction_frames == 6  # the failed view's correction is empty


def test_a_resting_view_whose_refinement_fails_is_not_tried_again(tmp_path, model_path, model,
                                                                  true_views):
    """Refining the first resting view raises (every time): that view is left as it is,
    not refined again turn after turn, and the next view is ray-cast and refined as usual."""
    name = mem_name("flaky-rest")
    device = _provisioned_device(tmp_path, model_path, name, predict=False)
    stop = threading.Event()
    logs: list[str] = []
    sent: list = []
    result: dict = {}

    def host() -> None:
        result["stats"] = serve(model_path, f"mem://{name}?end=a&pace=0",
                                ServeOptions(key=KEY, stats_every_s=0.3),
                                ServeParts(model=model, stop=stop, log=logs.append,
                                           on_frame=lambda e, v: sent.append(v),
                                           renderer=_FlakyRenderer(true_views.renderer,
                                                                   _refining_the_first_view)))

    def turns_after_the_failure() -> bool:  # a statistics line after the notice
        said = [i for i, line in enumerate(logs) if "ray-casting failed" in line]
        return bool(said) and any(" fps, link " in line for line in logs[said[0] + 1:])

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    try:
        wait_until(turns_after_the_failure, 20, "the failure notice, then a statistics line")
        device.device.set_view(80.0, 10.0)
        wait_until(lambda: sent.count((80.0, 10.0)) >= 2, 20, "the next view, refined")
    finally:
        stop.set()
        thread.join(10)
        device.stop()
    stats = result["stats"]
    assert stats.failed_views == 1
    assert stats.motion_frames >= 2 and stats.refined_frames >= 1


def test_serve_rejects_an_unknown_score_mode(model_path):
    with pytest.raises(ValueError, match="scores='magic'"):
        serve(model_path, "mem://nowhere", ServeOptions(scores="magic"), ServeParts(log=_quiet))


def test_serve_without_the_volume_says_so_once_and_interpolates(tmp_path, model_path, model):
    name = mem_name("novolume")
    device = _provisioned_device(tmp_path, model_path, name, predict=False)
    logs: list[str] = []
    with device:
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, fps=0, orbit=parse_orbit("steps:2:10"),
                                   volume=str(tmp_path / "missing.mhd")),
                      ServeParts(log=logs.append))
    notice = [line for line in logs if "cannot be ray-cast" in line]
    assert len(notice) == 1 and "missing.mhd" in notice[0]
    assert stats.frames == 2 and stats.motion_frames == 0


def test_cli_score_modes_and_refine_delay_are_gone(model_path):
    for option in (["--scores", "render"], ["--refine-delay", "1"]):
        run = serve_cli(str(model_path), "--port", "mem://nobody", *option)
        assert run.returncode != 0 and option[0] in run.stderr
        assert "Traceback" not in run.stderr
