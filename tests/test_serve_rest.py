"""``serve`` against a device whose view rests: every score mode, a real ``eigencast-device``
process resting on a view and at a pole, an in-process device dragged then released, and a
frame source that fails (one line, a clean end, never a traceback).

``benchmarks/bench_fuzz.py --section rest`` runs the same cases for 60 s each through the
``eigencast serve`` command.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from provision_helpers import KEY, REPO, DeviceProcess
from runtime_helpers import RuntimeThread, key_file, wait_until

from device_runtime.device import DeviceConfig
from device_runtime.display import ViewDelta
from host.link import provision, serve
from host.link.errors import ServeError
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.serving import SCORE_MODES, open_true_view_scores

REST_S = 1.5
"""Seconds each mode serves a resting device (the tiny model's motion source converges to
the full projection well within it: that is what crashed)."""
RESTING = {"resting": "30,10", "pole": "0,-90"}


def _quiet(line: str) -> None:
    pass


@pytest.fixture(scope="module")
def provisioned_flash(tmp_path_factory, model_path):
    """A keyed flash folder holding the tiny model (copied for each device)."""
    flash = tmp_path_factory.mktemp("rest") / "flash"
    device = DeviceProcess(flash, "--headless", key_file=key_file(model_path))
    try:
        provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=_quiet))
    finally:
        assert device.stop() == 0
    return flash


def _serve_every_mode(url: str, model_path, model, lines: list[str]) -> dict:
    """Each score mode for REST_S seconds against the device at ``url``; their statistics."""
    out = {}
    for mode in SCORE_MODES:
        start = time.monotonic()
        out[mode] = serve(model_path, url,
                          ServeOptions(key=KEY, scores=mode, duration_s=REST_S, reconnect=False,
                                       stats_every_s=0), ServeParts(model=model, log=lines.append))
        out[mode].wall_s = time.monotonic() - start
    return out


def test_every_score_mode_serves_resting_device_processes(provisioned_flash, tmp_path,
                                                         model_path, model):
    """Issue 21, item 1: a device resting on a view (or at a pole) made ``serve`` die with
    an AttributeError once ``motion`` had fully ray-cast the view. Both devices are served
    at the same time (one host thread each)."""
    devices, lines, stats, errors = {}, {}, {}, {}
    try:
        for case, view in RESTING.items():
            flash = tmp_path / case
            shutil.copytree(provisioned_flash, flash)
            devices[case] = DeviceProcess(flash, "--headless", "--view", view,
                                          key_file=key_file(model_path))
            lines[case] = []

        def host(case: str) -> None:
            try:
                stats[case] = _serve_every_mode(devices[case].url, model_path, model,
                                                lines[case])
            except BaseException as exc:  # reported below
                errors[case] = exc

        threads = [threading.Thread(target=host, args=(case,)) for case in RESTING]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
    finally:
        for case, device in devices.items():
            assert device.stop() == 0, (case, device.lines[-10:])
    assert not errors, errors
    for case in RESTING:
        for mode, got in stats[case].items():
            assert got.sessions == 1 and got.frames >= 1, (case, mode, got, lines[case])
            assert got.wall_s >= REST_S, (case, mode, got)  # ended by --duration
        # the path that crashed: the resting view refined until it is the full projection
        # (``auto``: the complete correction of the device's own frame), and serving went
        # on after that
        assert stats[case]["motion"].converged_frames >= 1, (case, stats[case]["motion"])
        auto = stats[case]["auto"]
        assert auto.converged_frames >= 1 and auto.correction_frames >= 1, (case, auto)
        assert not any("failed" in line for line in lines[case]), lines[case]


def test_every_score_mode_serves_a_view_dragged_then_released(tmp_path, model_path, model):
    """A device whose user drags the view (input actions, as the window sends them) and then
    lets go: the released view rests and is refined in every mode."""
    flash = tmp_path / "flash"
    config = DeviceConfig(flash_dir=flash, key=KEY)
    device = RuntimeThread(flash, "tcp-listen://127.0.0.1:0", config=config, frames=None,
                           predict=True)
    try:
        wait_until(lambda: device.device.transport is not None, 10, "the device listening")
        url = f"socket://127.0.0.1:{device.device.transport.port}"
        provision(model_path, url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=_quiet))
        wait_until(lambda: device.device.runtime_stats.frames_presented >= 1, 20, "first frame")
        lines: list[str] = []
        for mode in SCORE_MODES:
            start = device.device.runtime_stats.view_requests
            box: dict = {}

            def host(mode=mode, box=box) -> None:
                start = time.monotonic()
                try:
                    box["stats"] = serve(model_path, url,
                                         ServeOptions(key=KEY, scores=mode, duration_s=REST_S,
                                                      reconnect=False, stats_every_s=0),
                                         ServeParts(model=model, log=lines.append))
                    box["wall_s"] = time.monotonic() - start
                except BaseException as exc:  # reported below
                    box["error"] = exc

            thread = threading.Thread(target=host, daemon=True)
            thread.start()
            for _ in range(12):  # the drag: 12 moves, a few of them per request interval
                device.device.apply(ViewDelta(7.0, -3.0))
                threading.Event().wait(0.02)
            thread.join(30)
            assert "error" not in box, (mode, box.get("error"), lines[-5:])
            got = box["stats"]
            assert device.device.runtime_stats.view_requests > start, mode
            assert got.frames >= 1 and box["wall_s"] >= REST_S, (mode, got)
    finally:
        device.stop()
    assert not device.errors, device.errors


class _Exploding:
    """A frame source with a bug: it fails on every view, however it is called."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.budget_s = inner.budget_s

    def frame(self, view):
        raise ZeroDivisionError("a frame source bug")

    refine = frame


def test_a_failing_frame_source_is_one_line_and_serving_goes_on(provisioned_flash, tmp_path,
                                                                model_path, model,
                                                                monkeypatch):
    """A frame source that raises on every view is said in one line, each view is
    interpolated instead and serving goes on; an exception anywhere else in choosing a
    frame ends ``serve`` with one ServeError line (the device gets BYE and keeps serving
    the next host). Never a traceback."""
    from host.fit.motion import MotionScores
    from host.link.serving import _Serving

    flash = tmp_path / "flash"
    shutil.copytree(provisioned_flash, flash)
    device = DeviceProcess(flash, "--headless", "--view", "30,10", key_file=key_file(model_path))
    lines: list[str] = []
    try:
        source = _Exploding(MotionScores(model, open_true_view_scores(model).renderer))
        stats = serve(model_path, device.url,
                      ServeOptions(key=KEY, scores="motion", duration_s=REST_S, stats_every_s=0),
                      ServeParts(model=model, motion=source, log=lines.append))
        failed = [line for line in lines if "ray-casting failed" in line]
        assert len(failed) == 1 and "ZeroDivisionError: a frame source bug" in failed[0], lines
        # every view fails on its own and is interpolated; serving goes on
        assert stats.frames >= 1 and stats.motion_frames == 0 and stats.failed_views >= 1

        def bug(self, frame):
            raise ZeroDivisionError("a bug")

        monkeypatch.setattr(_Serving, "_score", bug)
        with pytest.raises(ServeError) as caught:
            serve(model_path, device.url,
                  ServeOptions(key=KEY, scores="interpolate", duration_s=10, stats_every_s=0),
                  ServeParts(model=model, log=_quiet))
        text = str(caught.value)
        assert "\n" not in text and "ZeroDivisionError" in text, text
        wait_until(lambda: any("bye from host" in line for line in device.lines), 10,
                   "the device's BYE line")
        monkeypatch.undo()
        stats = serve(model_path, device.url,
                      ServeOptions(key=KEY, scores="interpolate", max_frames=1, reconnect=False),
                      ServeParts(model=model, log=_quiet))
        assert stats.frames == 1
    finally:
        assert device.stop() == 0, "\n".join(device.lines[-10:])


def test_serve_cli_at_a_resting_device_has_no_traceback(provisioned_flash, tmp_path, model_path):
    """The issue's command, ``eigencast serve MODEL --port URL --key K`` (corrections of the
    device's own frames) against a device started with ``--view 30,10``."""
    flash = tmp_path / "flash"
    shutil.copytree(provisioned_flash, flash)
    device = DeviceProcess(flash, "--headless", "--view", "30,10", key_file=key_file(model_path))
    try:
        run = subprocess.run(
            [sys.executable, "-m", "host.cli", "serve", str(model_path), "--port", device.url,
             "--key", str(key_file(model_path)), "--duration", "2"],
            capture_output=True, text=True, timeout=60, cwd=REPO)
        assert run.returncode == 0 and "Traceback" not in run.stderr, run.stderr
        assert "served" in run.stdout, run.stdout
    finally:
        assert device.stop() == 0


def test_one_view_request_from_a_keyless_fake_device(model_path, model):
    """A fake keyless device (raw frames on a serial line) answers HELLO, asks for one view
    and falls silent: ``motion`` refines that view to the end and serving goes on."""
    from attack_helpers import RawPeer
    from provision_helpers import mem_name

    from host.link.provisioning import inspect_image
    from protocol import messages as m
    from protocol.transport import open_transport

    name = mem_name("fake")
    fake = RawPeer(open_transport(f"mem://{name}?end=b&pace=0", timeout_s=5))
    result: dict = {}

    def host() -> None:
        try:
            result["stats"] = serve(model_path, f"mem://{name}?end=a&pace=0",
                                    ServeOptions(scores="motion", duration_s=REST_S,
                                                 reconnect=False),
                                    ServeParts(model=model, log=_quiet))
        except BaseException as exc:  # reported below
            result["error"] = exc

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    try:
        hello = fake.wait_for(lambda rid, msg: isinstance(msg, m.Hello), 20)
        assert hello is not None, "no HELLO from serve"
        rid = next(r for r, msg in fake.received if msg is hello)
        digest = inspect_image(model_path).digest
        fake.send(m.HelloReply(
            min_version=m.PROTOCOL_VERSION, max_version=m.PROTOCOL_VERSION,
            device_id="fake", nonce=bytes(16), max_frame_bytes=65536,
            ram_budget_bytes=1 << 28, slot_size_bytes=1 << 26, display_width=0,
            display_height=0, rx_window_frames=32, rx_buffer_bytes=4096,
            slots=(m.SlotInfo(slot=0, state=m.SlotState.CONFIRMED, active=True, generation=1,
                              size_bytes=1, digest=digest),),
            has_key=False, image_format_versions=(1,), software="fake",
        ).encode(request_id=rid))
        fake.send(m.ViewRequest(phi_deg=30.0, theta_deg=-90.0, sequence=1).encode())
        thread.join(60)
    finally:
        fake.close()
    assert "error" not in result, result.get("error")
    stats = result["stats"]
    assert stats.frames >= 2 and stats.converged_frames == 1, stats


def test_sparse_step_none_means_nothing_left_to_refine(model):
    """``MotionScores.refine`` returns None once the view is fully ray-cast."""
    from host.fit.motion import MotionScores

    source = MotionScores(model, open_true_view_scores(model).renderer)
    view = (30.0, 10.0)
    source.frame(view)
    steps = []
    while len(steps) < 10_000 and (not steps or steps[-1] is not None):
        steps.append(source.refine(view))  # as many steps as the budget needs
    assert steps[-1] is None and steps[-2] is not None and steps[-2].complete
    assert np.isfinite(steps[-2].scores).all()
