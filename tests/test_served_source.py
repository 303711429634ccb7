"""``ServeParts(motion=...)``: a sparse source passed in serves the sessions of its kind.

A source built with the device's own frames (``own``: its frames are corrections) serves a
device that corrects them, so a caller (a benchmark, a long-running host) can pass one
whose recovery factors are already computed (`MotionScores.prepare`) instead of having
the session compute them on its loop the first time a view rests.
"""

from __future__ import annotations

import threading

from provision_helpers import KEY, mem_name
from runtime_helpers import RuntimeThread, wait_until

from device_runtime.prediction import OwnFrames
from host.fit.motion import MotionScores
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import serve
from host.link.true_views import open_true_view_scores


def test_a_prepared_correcting_source_serves_a_device_that_corrects(tmp_path, model_path,
                                                                    model):
    renderer = open_true_view_scores(model).renderer
    source = MotionScores(model, renderer, own=OwnFrames(model.image))
    source.prepare()
    name = mem_name("prepared")
    frames: list = []
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b", predict=True,
                           on_frame=lambda f, info: frames.append(dict(info or {})))
    provision(model_path, f"mem://{name}?end=a", ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=lambda line: None))
    stop = threading.Event()
    result: dict = {}

    def host() -> None:
        result["stats"] = serve(model_path, f"mem://{name}?end=a", ServeOptions(key=KEY),
                                ServeParts(stop=stop, log=lambda line: None, model=model,
                                           renderer=renderer, motion=source))

    thread = threading.Thread(target=host, daemon=True)
    with device:
        thread.start()
        try:
            wait_until(lambda: any(i.get("corrected") for i in frames), 60,
                       "a correction")
            device.device.set_view(33.0, 12.0)
            wait_until(lambda: source.frames >= 2, 30, "the source's frame of a new view")
        finally:
            stop.set()
            thread.join(20)
    stats = result["stats"]
    assert stats.correction_frames >= 1 and stats.key_frames == 0
    assert source.frames >= 2 and source.pixels > 0  # the session used the source given
