"""The true picture at rest: a resting view's frame ends the host's ray-cast bit for bit,
over the mem:// serial line and over TCP to a real device process, also when the device's
own float32 frames differ from the host's (another CPU); a new view cancels the layers; the
host plans layers that never cost more than coding the ray-cast itself."""

from __future__ import annotations

import csv
import threading

import numpy as np
import pytest
from PIL import Image
from provision_helpers import KEY, DeviceProcess, mem_name
from runtime_helpers import RuntimeThread, provisioned_device, wait_until

from device_runtime.device import DeviceConfig
from device_runtime.layers import RestFrame, decode_file
from device_runtime.orbit import canonical_view
from host.fit.model import HostModel
from host.link.layers import EncodedLayer, RestPlanner, object_ssim
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import serve
from host.link.true_views import open_true_view_scores
from protocol.layers import LayerAssembly, decode_layer


def _quiet(line: str) -> None:
    pass


@pytest.fixture(scope="module")
def truth_of(depth_model_path):
    renderer = open_true_view_scores(HostModel.load(depth_model_path, key=KEY)).renderer

    def truth(view):
        return renderer.render(*view)[0]

    return truth


def _serving(url: str, model_path, stop: threading.Event, sent: list, **kwargs):
    out: dict = {}

    def host() -> None:
        log = kwargs.pop("log", _quiet)
        out["stats"] = serve(model_path, url, ServeOptions(key=KEY, **kwargs),
                             ServeParts(stop=stop, log=log,
                                        on_frame=lambda enc, view: sent.append((enc, view))))

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    return thread, out


def _serve_until_exact(device: RuntimeThread, shown: list, url: str, model_path, view,
                       timeout_s: float) -> None:
    """Run ``device`` resting on ``view`` and serve ``model_path`` to it on ``url`` until the
    frames it ``shown`` include the exact frame of ``view``; then stop both."""
    stop, sent = threading.Event(), []
    with device:
        device.device.set_view(*view)
        thread, _ = _serving(url, model_path, stop, sent)
        try:
            wait_until(lambda: any(i.get("exact") and (i["phi_deg"], i["theta_deg"]) == view
                                   for _, i in shown), timeout_s, "the exact frame")
        finally:
            stop.set()
            thread.join(30)


def _perturbed(frame: np.ndarray, seed: int) -> np.ndarray:
    """``frame`` as another CPU's float32 arithmetic may leave it (docs/protocol.md): a level
    off on a tenth of the pixels, up to 8 on one in a hundred."""
    rng = np.random.default_rng(seed)
    out = frame.astype(np.int16)
    out += (rng.random(frame.shape) < 0.1) * rng.choice([-1, 1], frame.shape)
    out += (rng.random(frame.shape) < 0.01) * rng.integers(-8, 9, frame.shape)
    return np.clip(out, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("cpu,strips", [("same", False), ("other", True)])
def test_a_resting_view_ends_the_ray_cast_bit_for_bit_over_the_serial_line(
        tmp_path, depth_model_path, truth_of, cpu, strips, monkeypatch):
    """A served device resting on a view over a paced 115200-baud mem:// line: after its own
    frame and its correction, layers follow until the frame the display presents equals the
    host's ray-cast; with ``cpu="other"`` the device's own and corrected frames are off by
    the levels another CPU may differ by, and the exact frame is still exact; with
    ``strips`` the exact layer comes in strips (version 5, as a 512 px frame's would). Then
    a new view: the old view's layers stop, and the new view ends exact too."""
    if strips:  # this image's frames are small: strips of 1,000 pixels
        import protocol.layers

        monkeypatch.setattr(protocol.layers, "STRIP_PIXELS", 1000)
    name = mem_name(f"exact-{cpu}-{strips}")
    shown: list = []
    device = provisioned_device(tmp_path, name, depth_model_path, shown)
    views = [canonical_view(47.0, 23.0), canonical_view(200.0, -31.0)]
    stop, sent = threading.Event(), []
    with device:
        runtime = device.device
        if cpu == "other":  # the device's own arithmetic, a level or so off the host's
            wait_until(lambda: runtime._model is not None, 30, "the image loaded")
            model = runtime._model
            worker_synth, reconstructor = model.warp_worker.synthesis, model.reconstructor
            warp, correct = worker_synth.frame, reconstructor.correct
            worker_synth.frame = lambda *a, **k: _perturbed(warp(*a, **k), 1)
            reconstructor.correct = lambda *a, **k: _perturbed(correct(*a, **k), 2)
        runtime.set_view(*views[0])
        thread, out = _serving(f"mem://{name}?end=a", depth_model_path, stop, sent)
        try:
            for view in views:
                runtime.set_view(*view)
                wait_until(lambda view=view: any(
                    i.get("exact") and (i["phi_deg"], i["theta_deg"]) == view
                    for _, i in shown), 90, f"the exact frame of {view}")
                frame = next(f for f, i in reversed(shown) if i.get("exact"))
                np.testing.assert_array_equal(frame, truth_of(view))
                np.testing.assert_array_equal(runtime._shown_frame, truth_of(view))
        finally:
            stop.set()
            thread.join(30)
    stats = out["stats"]
    assert stats.exact_views >= 2 and stats.layer_frames >= 2
    versions = {enc.packet[2] for enc, _ in sent if isinstance(enc, EncodedLayer)}
    assert versions == ({4, 5} if strips else {4})  # (lossy layers stay whole)
    rs = runtime.runtime_stats
    assert rs.exact_frames >= 2 and rs.layers_bad == 0
    # what was shown of the first view: its own frame first, then the layers in order
    first = [i for _, i in shown if (i.get("phi_deg"), i.get("theta_deg")) == views[0]]
    kinds = [("layer" if i.get("layer") is not None else "other") for i in first]
    assert kinds[0] == "other" and kinds[-1] == "layer"


def test_a_noisy_line_still_ends_exact(tmp_path, depth_model_path, truth_of):
    """Over a 115200-baud line that flips bits (frames and chunks are lost to their CRCs):
    the device asks for a view again when a layer of it was lost, and the resting view
    still ends exactly the ray-cast."""
    name = mem_name("noisy")
    shown: list = []
    device = provisioned_device(tmp_path, name, depth_model_path, shown, host_query="&pace=0")
    view = canonical_view(130.0, -20.0)
    _serve_until_exact(device, shown, f"mem://{name}?end=a&ber=4e-5&seed=3", depth_model_path,
                       view, 180)
    frame = next(f for f, i in reversed(shown) if i.get("exact"))
    np.testing.assert_array_equal(frame, truth_of(view))


@pytest.mark.parametrize("lose", ["first chunk", "last chunk"])
def test_a_lost_chunk_of_the_exact_layer_is_asked_for_again(tmp_path, depth_model_path,
                                                            truth_of, lose):
    """The exact layer's first (or last) chunk never reaches the device: it notices (the
    next chunk continues no file, or the last planned layer does not come), asks for the view
    again, and the view still ends exactly the ray-cast."""
    from protocol.layers import decode_header_flags

    name = mem_name("lost")
    shown: list = []
    device = provisioned_device(tmp_path, name, depth_model_path, shown, host_query="&pace=0")
    runtime = device.device
    receive = runtime.on_scores
    lost: list = []

    def on_scores(msg):
        flags, offset, size = decode_header_flags(msg.packet)
        exact = flags is not None and flags & 0x08
        wanted = offset == 0 if lose == "first chunk" else (
            offset is not None and offset + len(msg.packet) - 40 == size)
        if exact and wanted and not lost:
            lost.append(offset)
            return
        receive(msg)

    runtime.on_scores = on_scores
    view = canonical_view(222.0, 33.0)
    _serve_until_exact(device, shown, f"mem://{name}?end=a", depth_model_path, view, 120)
    assert lost and runtime.runtime_stats.layer_retries >= 1
    frame = next(f for f, i in reversed(shown) if i.get("exact"))
    np.testing.assert_array_equal(frame, truth_of(view))


def test_a_real_device_process_over_tcp_presents_the_exact_frame(tmp_path, depth_model_path,
                                                                 truth_of):
    """``eigencast-device --headless --frames`` over TCP: the last frame it presents (the PNG
    its display wrote, named ``exact`` in frames.csv) is the ray-cast bit for bit."""
    key = depth_model_path.parent / "device.key"
    frames = tmp_path / "frames"
    device = DeviceProcess(tmp_path / "flash", "--headless", "--frames", str(frames),
                           "--view", "120,15", key_file=key)
    url = f"socket://127.0.0.1:{device.port}"
    stop, sent = threading.Event(), []
    try:
        provision(depth_model_path, url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=_quiet))
        thread, out = _serving(url, depth_model_path, stop, sent)

        def exact_rows():
            path = frames / "frames.csv"
            if not path.exists():
                return []
            with open(path) as handle:
                return [r for r in csv.DictReader(handle) if r["kind"] == "exact"]

        wait_until(lambda: exact_rows(), 90, "an exact frame")
        stop.set()
        thread.join(30)
    finally:
        stop.set()
        assert device.stop() == 0
    row = exact_rows()[-1]
    view = (float(row["phi_deg"]), float(row["theta_deg"]))
    got = np.asarray(Image.open(frames / row["file"]))
    np.testing.assert_array_equal(got, truth_of(view))
    assert out["stats"].exact_views >= 1


def test_the_planner_reaches_each_target_and_ends_exact_for_no_more_than_the_ray_cast(
        depth_model_path, truth_of):
    """The plan after a correction: each lossy layer reaches its target, the frame after the
    exact layer is the ray-cast, and the first step never costs more than coding the ray-cast
    itself at the same quality (the planner takes it when it is cheaper)."""
    from device_runtime.prediction import OwnFrames
    from host.fit.motion import MotionScores

    model = HostModel.load(depth_model_path, key=KEY)
    renderer = open_true_view_scores(model).renderer
    source = MotionScores(model, renderer, own=OwnFrames(model.image), strides=(1,), coarse=1.0)
    planner = RestPlanner(model.digest, targets=(0.9, 0.97))
    view = canonical_view(80.0, 10.0)
    step = source.frame(view)
    truth, own = source.rest_images(view)
    np.testing.assert_array_equal(truth, truth_of(view))
    from host.link.correction import CorrectionEncoder
    from protocol.scores import ScoreDecoder

    encoded = CorrectionEncoder(model).encode(view, scores=step.scores, fine=True)
    y = ScoreDecoder(model.image.n_coefficients, model.digest,
                     n_components=model.image.n_components).decode(encoded.packet).y
    corrected = source.own.corrected(own, y)
    plan = planner.plan(view, truth, corrected, own, len(encoded.packet),
                        base_frame=encoded.frame, first_frame=encoded.frame + 1)
    start = own if plan.skip_correction else corrected
    reached = object_ssim(truth, start)
    for layer, target in zip(plan.layers, [t for t in (0.9, 0.97) if t > reached]):
        assert layer.quality >= target and object_ssim(truth, layer.frame) == layer.quality
    assert plan.layers[-1].exact
    np.testing.assert_array_equal(plan.layers[-1].frame, truth)
    # the first lossy layer costs no more than the ray-cast itself coded to its quality
    lossy = [layer for layer in plan.layers if not layer.exact]
    if lossy:
        alone = planner._lossy(view, truth, own, lossy[0].quality - 1e-9, 0,
                               encoded.frame + 1, 0, residual=False)
        paid = lossy[0].size_bytes + (0 if plan.skip_correction else len(encoded.packet))
        assert alone is None or paid <= alone.size_bytes
    frames = [s.frame for s in plan.sends()]
    assert frames == list(range(encoded.frame + 1, encoded.frame + 1 + len(frames)))


def test_object_ssim_is_evaluates_measure():
    """The planner's object SSIM (computed on the object's box) is evaluate's, exactly,
    wherever the object lies (the frame's borders included)."""
    from host.evaluate import object_mask, structural_similarity

    rng = np.random.default_rng(4)
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(12, 80, 2))
        truth = np.zeros((h, w, 3), np.uint8)
        y0, x0 = int(rng.integers(0, h - 3)), int(rng.integers(0, w - 3))
        y1, x1 = int(rng.integers(y0 + 1, h + 1)), int(rng.integers(x0 + 1, w + 1))
        truth[y0:y1, x0:x1] = rng.integers(20, 255, (y1 - y0, x1 - x0, 3))
        test = np.clip(truth.astype(int) + rng.integers(-20, 21, truth.shape), 0, 255
                       ).astype(np.uint8)
        assert object_ssim(truth, test) == pytest.approx(
            structural_similarity(truth, test, mask=object_mask(truth)), abs=1e-12)


def test_a_correction_larger_than_the_devices_frames_costs_its_view_not_the_session(
        tmp_path, depth_model_path, truth_of, monkeypatch):
    """A correction that does not fit the device's frames (a 256 px tooth's complete one is
    28 kB, a serial device's frame 4 kB; here the room for scores is cut to 200 bytes so a
    48 px model's do not fit): serve used to stop there ("does not fit the device's
    frames"); now that correction is not sent (counted, said once), and the layers, chunked
    to fit, still take the frame to the ray-cast bit for bit."""
    import host.link.serving as serving

    monkeypatch.setattr(serving, "_SCORES_OVERHEAD", 1024 - 200)
    name = mem_name("small-frames")
    shown: list = []
    config = DeviceConfig(flash_dir=tmp_path / "flash", key=KEY, max_frame_bytes=1024)
    device = provisioned_device(tmp_path, name, depth_model_path, shown, host_query="&pace=0",
                                config=config)
    view = canonical_view(47.0, 23.0)
    stop, sent = threading.Event(), []
    lines: list[str] = []
    with device:
        device.device.set_view(*view)
        thread, out = _serving(f"mem://{name}?end=a", depth_model_path, stop, sent,
                               log=lines.append)
        try:
            wait_until(lambda: any(i.get("exact") for _, i in shown), 90, "the exact frame")
            np.testing.assert_array_equal(device.device._shown_frame, truth_of(view))
        finally:
            stop.set()
            thread.join(30)
    stats = out["stats"]
    assert stats.oversize_corrections >= 1 and stats.exact_views >= 1
    assert all(len(enc.packet) <= 200 or isinstance(enc, EncodedLayer) for enc, _ in sent)
    assert sum("does not fit the device's frames" in line for line in lines) == 1


SHAPE = (24, 40)  # (height, width): a frame of 960 pixels
DIGEST = bytes(range(32))


def _pixels(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.linspace(0, 255, SHAPE[1], dtype=np.float32)[None, :, None]
    return np.clip(base + rng.normal(0, 12, (*SHAPE, 3)), 0, 255).astype(np.uint8)


def test_the_planner_sends_a_large_frames_exact_layer_in_strips_that_end_exact():
    """With ``strip_pixels`` the exact layer of a larger frame is several version-5 files
    covering every row once; joined and applied as a device does, they end at the ray-cast;
    without it (a device that reads no strips), one version-4 file."""
    truth = _pixels(seed=4)
    own = _pixels(seed=5)
    for strip_pixels, want in ((None, {4}), (400, {5})):
        planner = RestPlanner(DIGEST, max_packet_bytes=300, strip_pixels=strip_pixels)
        plan = planner.plan((30.0, 15.0), truth, own, own, 0, base_frame=0, first_frame=7)
        exact = plan.layers[-1]
        assert exact.exact and {p[2] for p in exact.packets} == want
        rest, assembly, rows = RestFrame((30.0, 15.0), 0, plan.layers[-2].frame
                                         if len(plan.layers) > 1 else own), LayerAssembly(), []
        rest.layers = len(plan.layers) - 1
        for packet in exact.packets:
            chunk = decode_layer(packet, image_digest=DIGEST, image_shape=SHAPE,
                                 max_packet_bytes=1 << 20)
            data = assembly.add(chunk)
            if data is not None:
                pixels = decode_file(data, chunk.codec, SHAPE,
                                     row0=chunk.row0 if chunk.strip else None)
                rows.append((chunk.row0, pixels.shape[0]))
                rest.apply(chunk, pixels)
        assert rest.is_exact and rest.finished
        np.testing.assert_array_equal(rest.frame, truth)
        np.testing.assert_array_equal(exact.frame, truth)
        if strip_pixels:  # 960 pixels: three strips of 320, every row once
            assert rows == [(0, 8), (8, 8), (16, 8)]
