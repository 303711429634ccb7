"""The display's frame policy (device_runtime/scheduler.py): the display never waits on a
warp. Each tick it presents the best frame ready: the view's warp, else its blend, else the
last frame; the warp replaces the blend when the worker has made it. One policy for
standalone and served devices."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from provision_helpers import KEY
from runtime_helpers import FakeClock, tiny_model

from device_runtime.device import DeviceConfig
from device_runtime.display import ViewDelta
from device_runtime.orbit import parse_orbit
from device_runtime.reconstruct import Reconstructor
from device_runtime.runtime import LoadedModel, RuntimeDevice
from protocol.image import read_image

TICK_S = 1.0 / 30.0


@pytest.fixture(scope="module")
def depth_image(tmp_path_factory):
    return read_image(tiny_model(tmp_path_factory, name="tiny-depth", depth=True), key=KEY)


class SlowWorker:
    """A warp worker whose warp of a view is ready ``ticks`` ticks of ``clock`` after the view
    was asked (the real warp, from the real worker's synthesis); it never blocks."""

    def __init__(self, real, clock: FakeClock, ticks: int) -> None:
        self.real, self.clock, self.ticks = real, clock, ticks
        self.asked: dict = {}

    def request(self, view) -> None:
        self.asked.setdefault(view, self.clock.now)

    def take(self, view, timeout_s: float = 0.0):
        assert timeout_s == 0.0, "the display waited on a warp"
        asked = self.asked.get(view)
        if asked is None or self.clock.now < asked + self.ticks * TICK_S - 1e-9:
            return None
        return self.real.synthesis.frame(*view)

    def snap(self, view):
        return view

    def display_first(self):
        return self.real.display_first()

    def close(self) -> None:
        self.real.close()


def _device(depth_image, tmp_path, clock, *, standalone: bool, shown: list) -> tuple:
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY),
                           standalone=standalone, predict=not standalone, view=(40.0, 10.0),
                           fps=1.0 / TICK_S, clock=clock, log=lambda _: None,
                           on_frame=lambda f, info: shown.append((clock.now, f.copy(),
                                                                  dict(info))))
    model = LoadedModel.build(depth_image, slot="A", generation=1, test=False,
                              want_standalone=standalone, want_predictor=not standalone)
    model.warp_worker = SlowWorker(model.warp_worker, clock, ticks=3)
    device._models.put(model)
    return device, model


@pytest.mark.parametrize("standalone", [True, False], ids=["standalone", "served"])
def test_a_warp_that_takes_three_ticks_never_holds_the_display(depth_image, tmp_path,
                                                               standalone):
    """With a fake clock and a warp that is ready 3 ticks after it is asked: a drag shows the
    blend of every view on its own tick, and once the view rests its warp follows 3 ticks
    later; in between the last frame stays. Every turn returns at once (never waits)."""
    clock, shown = FakeClock(1000.0), []
    device, model = _device(depth_image, tmp_path, clock, standalone=standalone, shown=shown)
    blend = Reconstructor.from_image(depth_image)
    on_screen = []  # per tick: (view, kind) of the frame on show at the end of the tick
    try:
        for tick in range(12):
            if 1 <= tick <= 5:  # a drag: the view moves on each of these ticks
                device.apply(ViewDelta(3.0, 0.0))
            t0 = time.perf_counter()
            wait = device.display_turn(None)
            assert wait is not None and wait <= TICK_S + 1e-9
            assert time.perf_counter() - t0 < 5.0  # (a hang guard, not a timing)
            _, _, info = shown[-1]
            on_screen.append(((info["phi_deg"], info["theta_deg"]),
                              "warp" if info.get("synthesized") else "blend"))
            clock.now += TICK_S
        views = [v for v, _ in on_screen]
        # the first frame, then each view of the drag on its own tick, as a blend
        assert [k for _, k in on_screen[:6]] == ["blend"] * 6
        assert len(set(views[:6])) == 6
        for view, _ in on_screen[:6]:
            frames = [f for ft, f, i in shown if (i["phi_deg"], i["theta_deg"]) == view]
            np.testing.assert_array_equal(frames[0], blend.update(model.own_scores(view)))
        # at rest: the blend stays for two more ticks, then the warp of the last view
        assert on_screen[6:8] == [(views[5], "blend")] * 2
        assert on_screen[8:] == [(views[5], "warp")] * 4
        np.testing.assert_array_equal(shown[-1][1],
                                      model.warp_worker.real.synthesis.frame(*views[5]))
        assert device.runtime_stats.synthesized_frames == 1
    finally:
        device.close()
        model.close()


def test_a_running_device_whose_warp_is_slowed_keeps_its_tick(depth_image, tmp_path):
    """A real display loop on an orbit that moves every tick, its warps slowed to 10 ticks
    each: the display still shows a frame of (nearly) every view, never holding one while a
    warp is made."""
    shown: list = []
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY), standalone=True,
                           orbit=parse_orbit("turn:2:15:0.5"), fps=1.0 / TICK_S,
                           log=lambda _: None,
                           on_frame=lambda f, info: shown.append((time.monotonic(), dict(info))))
    model = LoadedModel.build(depth_image, slot="A", generation=1, test=False,
                              want_standalone=True)
    synthesis = model.warp_worker.synthesis
    real_frame = synthesis.frame

    def slow_frame(*args, **kwargs):
        time.sleep(10 * TICK_S)
        return real_frame(*args, **kwargs)

    synthesis.frame = slow_frame
    device._models.put(model)
    done = threading.Event()
    thread = threading.Thread(target=lambda: (device.run_display(), done.set()), daemon=True)
    try:
        t0 = time.monotonic()
        thread.start()
        assert done.wait(60), "the orbit did not finish"
        elapsed = time.monotonic() - t0
    finally:
        device.stop_event.set()
        thread.join(10)
        device.close()
        model.close()
    blends = [i for _, i in shown if not i.get("synthesized")]
    ticks = elapsed / TICK_S
    # one blend per tick of the orbit's 1 s: a display that waited for each 10-tick warp
    # would show a tenth of them
    assert len(blends) >= 0.5 * min(ticks, 30), (len(blends), ticks)
    gaps = np.diff([t for t, _ in shown])
    assert np.percentile(gaps, 90) < 5 * TICK_S, gaps
