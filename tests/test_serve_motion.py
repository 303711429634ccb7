"""``serve --scores motion``: sparse ray-casts within a frame deadline (issue 13, item 4)."""

from __future__ import annotations

import copy
import dataclasses
import threading

import numpy as np
import pytest
from PIL import Image
from provision_helpers import KEY, mem_name
from runtime_helpers import FakeClock, RuntimeThread, read_frames, serve_cli, wait_until

from device_runtime.runtime import canonical_view, parse_orbit
from host.fit.motion import BUDGET_SHARE, PROBE_EVERY, MotionScores, angle_between
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import _Pace, open_true_view_scores, serve


@pytest.fixture(scope="module")
def renderer(model):
    return open_true_view_scores(model).renderer


def _quiet(line: str) -> None:
    pass


class _SlowRays:
    """The real ray-caster, charging ``per_ray`` seconds of a fake clock per ray cast."""

    def __init__(self, inner, clock: FakeClock, per_ray: float) -> None:
        self.inner, self.clock, self.per_ray = inner, clock, per_ray

    def render_pixels(self, camera, width, height, rows, cols):
        self.clock.now += self.per_ray * len(rows)
        return self.inner.render_pixels(camera, width, height, rows, cols)

    def composite(self, rgba):
        return self.inner.composite(rgba)

    def coarser(self, factor):
        return _SlowRays(self.inner.coarser(factor), self.clock, self.per_ray / factor)


class _SlowRenderer:
    def __init__(self, renderer, clock: FakeClock, per_ray: float) -> None:
        self.settings = renderer.settings
        self.image_shape = renderer.image_shape
        self.renderer = _SlowRays(renderer.renderer, clock, per_ray)


def _drag(source: MotionScores, n: int, step_deg: float = 3.0) -> list:
    return [source.frame(canonical_view(20.0 + step_deg * i, 10.0)) for i in range(n)]


def test_a_slower_renderer_gets_sparser_frames_that_still_fit_the_budget(model, renderer):
    h, w = model.image.image_shape
    budget = 0.05
    strides = {}
    for per_ray in (1e-6, 2e-4):  # a full frame: a fraction of the budget / several budgets
        clock = FakeClock()
        source = MotionScores(model, _SlowRenderer(renderer, clock, per_ray), budget_s=budget,
                              clock=clock)
        frames = _drag(source, 6)
        assert frames[0].stride == source.strides[-1]  # nothing measured yet: the sparsest
        for f in frames[1:]:
            assert f.seconds <= BUDGET_SHARE * budget + 1e-12  # never behind the deadline
        strides[per_ray] = frames[-1].stride
        assert frames[-1].pixels * per_ray / source.coarse <= BUDGET_SHARE * budget
    assert strides[1e-6] == 1  # the whole view fits: a full ray-cast, the projection
    assert strides[2e-4] > 1
    # the densest stride that fits
    dense = [s for s in source.strides if s < strides[2e-4]]
    assert all((-(-h // s)) * (-(-w // s)) * 2e-4 / source.coarse > BUDGET_SHARE * budget
               for s in dense)


def test_a_host_too_slow_for_any_stride_sends_the_prior_and_probes_again(model, renderer):
    clock = FakeClock()
    source = MotionScores(model, _SlowRenderer(renderer, clock, 1e-2), budget_s=0.05,
                          clock=clock)
    frames = _drag(source, 2 + PROBE_EVERY)
    assert frames[0].stride == source.strides[-1]  # measured: far over the budget
    skipped = frames[1:PROBE_EVERY]
    assert [f.stride for f in skipped] == [0] * (PROBE_EVERY - 1)
    assert all(f.pixels == 0 for f in skipped)
    view = canonical_view(23.0, 10.0)  # the second frame's
    np.testing.assert_array_equal(frames[1].scores, model.scores(*view).astype(np.float32))
    assert frames[PROBE_EVERY].stride == source.strides[-1]  # measured again
    assert source.refine(canonical_view(20.0 + 3.0 * (1 + PROBE_EVERY), 10.0)) is not None


def test_a_full_stride_frame_is_the_projection(model, renderer):
    source = MotionScores(model, renderer, strides=(1,), coarse=1.0)
    view = canonical_view(33.0, 21.0)
    frame = source.frame(view)
    rgb, _alpha = renderer.render(*view)
    np.testing.assert_array_equal(frame.scores, model.project(rgb))
    assert frame.complete and source.converged(view) and source.refine(view) is None


def test_a_resting_view_converges_to_the_projection(model, renderer):
    clock = FakeClock()
    source = MotionScores(model, _SlowRenderer(renderer, clock, 1e-4), strides=(4,),
                          budget_s=0.05, clock=clock, coarse=1.0)
    view = canonical_view(101.0, -12.0)
    first = source.frame(view)
    assert first.stride == 4 and not first.complete and first.prior == "interpolated"
    truth, _alpha = renderer.render(*view)
    errors = [np.mean((model.reconstruct(first.scores).astype(float) - truth) ** 2)]
    steps = []
    while (step := source.refine(view)) is not None:
        steps.append(step)
        assert step.seconds <= 0.05  # each step within the budget
        if step.scores is not None:
            errors.append(np.mean((model.reconstruct(step.scores).astype(float) - truth) ** 2))
    assert len(steps) >= 2 and steps[-1].complete and not steps[0].complete
    assert sum(s.pixels for s in steps) + first.pixels == truth.shape[0] * truth.shape[1]
    np.testing.assert_array_equal(steps[-1].scores, model.project(truth))
    assert errors[-1] < errors[0]
    assert source.refine(canonical_view(102.0, -12.0)) is None  # not the rendered view


def test_slow_drags_use_the_previous_frame_as_the_prior(model, renderer):
    source = MotionScores(model, renderer, strides=(4,))
    fast = _drag(source, 3, step_deg=3.0)
    slow = _drag(source, 3, step_deg=0.2)
    assert [f.prior for f in fast] == ["interpolated"] * 3
    assert [f.prior for f in slow][1:] == ["previous"] * 2
    assert angle_between((0.0, 0.0), (3.0, 0.0)) == pytest.approx(3.0)
    assert angle_between((10.0, 90.0), (190.0, 90.0)) == pytest.approx(0.0, abs=1e-6)


def test_the_budget_follows_the_slower_of_deadline_fps_and_link():
    pace = _Pace(0.03, 60.0)
    assert pace.budget_s == pytest.approx(0.03)
    assert _Pace(0.03, 10.0).budget_s == pytest.approx(0.1)
    pace.left(0.2)  # a packet took 200 ms to leave: no point casting more often
    assert pace.budget_s == pytest.approx(0.2)


def _provisioned_device(tmp_path, model_path, name, **kwargs):
    frames = tmp_path / "frames"
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", frames=frames,
                           **kwargs)
    result = provision(model_path, f"mem://{name}?end=a&pace=0",
                       ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
    assert result.confirmed is True
    return device, frames


class _Recording(MotionScores):
    """Remembers the scores it made per view (what the device must show)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.made: dict = {}

    def frame(self, view):
        out = super().frame(view)
        self.made.setdefault(view, []).append(out.scores)
        return out

    def refine(self, view):
        out = super().refine(view)
        if out is not None:
            self.made.setdefault(view, []).append(out.scores)
        return out


def test_orbit_frames_on_a_device_are_the_recovered_scores(tmp_path, model_path, model, renderer):
    name = mem_name("motion-orbit")
    device, frames = _provisioned_device(tmp_path, model_path, name)
    source = _Recording(model, renderer, strides=(2,))
    with device:
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, orbit=parse_orbit("steps:5:25"), fps=0,
                                   scores="motion",
                                   deadline_s=10.0),  # stride 2 fits however loaded the CPU
                      ServeParts(model=model, log=_quiet, motion=source))
        assert stats.frames == 5 and stats.motion_frames == 5 and stats.stride_frames == {"2": 5}
        assert "5 sparse" in stats.line()
        wait_until(lambda: any(float(r["phi_deg"]) == 288.0 for r in read_frames(frames)), 10,
                   "the orbit's last view")
    rows = read_frames(frames)
    # a device that falls behind (a loaded machine) shows the newest frame and counts the
    # ones it skipped: every one of the 5 is shown or counted, none lost otherwise
    assert len(rows) + device.device.stats_dict()["coalesced"] == 5
    for row in rows:
        view = (float(row["phi_deg"]), float(row["theta_deg"]))
        got = np.asarray(Image.open(frames / row["file"]))
        np.testing.assert_array_equal(got, model.reconstruct(model.quantize(source.made[view][0])))
        assert not np.array_equal(got, model.view(*view))  # not the interpolated frame


def test_a_resting_view_on_a_device_converges_to_the_projection(tmp_path, model_path, model,
                                                                 renderer):
    name = mem_name("motion-rest")
    device, frames = _provisioned_device(tmp_path, model_path, name, request_rate_hz=1000)
    stop = threading.Event()
    result: dict = {}
    logs: list[str] = []
    source = MotionScores(model, renderer, strides=(3,))

    def host() -> None:
        result["stats"] = serve(model_path, f"mem://{name}?end=a&pace=0",
                                ServeOptions(key=KEY, scores="motion"),
                                ServeParts(model=model, stop=stop, log=logs.append, motion=source))

    view = canonical_view(123.25, -17.5)
    truth, _alpha = renderer.render(*view)
    projected = model.reconstruct(model.quantize(model.project(truth)))
    thread = threading.Thread(target=host, daemon=True)
    thread.start()

    def shown() -> list[dict]:
        return [r for r in read_frames(frames)
                if (float(r["phi_deg"]), float(r["theta_deg"])) == view]

    def last_is_projection() -> bool:
        rows = shown()
        return bool(rows) and np.array_equal(
            np.asarray(Image.open(frames / rows[-1]["file"])), projected)

    try:
        wait_until(lambda: device.device.runtime_stats.frames_presented >= 1, 20, "first frame")
        device.device.set_view(*view)
        wait_until(last_is_projection, 30, "the full projection")
    finally:
        stop.set()
        thread.join(10)
        device.stop()
    stats = result["stats"]
    assert stats.converged_frames >= 1 and stats.refined_frames >= 1, logs
    assert any("ray-cast scores" in line for line in logs)
    rows = shown()
    assert len(rows) >= 2 and rows[-1]["key"] == "0"  # refinements are deltas
    first = np.asarray(Image.open(frames / rows[0]["file"]))
    assert not np.array_equal(first, projected)  # the first frame was the sparse one


@pytest.mark.parametrize("value", ["0", "-5", "nan"])
def test_cli_deadline_must_be_positive(model_path, value):
    run = serve_cli(str(model_path), "--port", "mem://nobody", "--deadline", value)
    assert run.returncode != 0 and "--deadline" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr


def test_a_coarser_renderer_looks_the_same_with_fewer_samples(model, renderer):
    settings = dataclasses.replace(renderer.settings, samples=800)  # fine enough to compare
    exact = settings.renderer(renderer.volume)
    camera = settings.camera(48.0, 12.0)
    full = exact.render_rgb8(camera, settings.width, settings.height)
    same = exact.coarser(1.0).render_rgb8(camera, settings.width, settings.height)
    np.testing.assert_array_equal(same, full)
    coarse = exact.coarser(2.0)
    assert coarse.step_mm == pytest.approx(2 * exact.step_mm)
    half = coarse.render_rgb8(camera, settings.width, settings.height)
    uncorrected = copy.copy(coarse)
    uncorrected._lut = exact._lut
    plain = uncorrected.render_rgb8(camera, settings.width, settings.height)
    diff = np.abs(half.astype(float) - full).mean()
    # without the opacity correction the longer steps would show a fainter object
    assert 0 < diff < 0.5 * np.abs(plain.astype(float) - full).mean(), diff
    with pytest.raises(ValueError, match="factor"):
        exact.coarser(0.5)


def test_coarse_moving_frames_still_rest_on_the_exact_projection(model, renderer):
    source = MotionScores(model, renderer, strides=(2,), coarse=2.0)
    view = canonical_view(77.0, 5.0)
    source.frame(view)
    while (step := source.refine(view)) is not None:
        last = step
    truth, _alpha = renderer.render(*view)
    assert last.complete
    np.testing.assert_array_equal(last.scores, model.project(truth))
