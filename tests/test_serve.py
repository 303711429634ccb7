"""``eigencast serve``: score packets for view requests and orbits, deltas, coalescing, loss."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest
from provision_helpers import KEY, mem_name
from runtime_helpers import RuntimeThread, check_frames, read_frames, wait_until

from device_runtime.orbit import parse_orbit
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import FrameEncoder, ServeError, serve
from protocol.scores import ScoreDecoder


def _quiet(line: str) -> None:
    pass


def test_frame_encoder_codes_key_then_deltas_that_decode_to_the_host_scores(model):
    encoder = FrameEncoder(model, first_frame=7)
    decoder = ScoreDecoder(model.image.n_coefficients, model.digest,
                           n_components=model.image.n_components)
    views = [(float(p), 10.0) for p in range(0, 60, 6)]
    sizes = {True: [], False: []}
    for i, view in enumerate(views):
        packet = encoder.encode(view)
        assert encoder.last_was_key == (i == 0)
        decoded = decoder.decode(packet.packet)
        assert decoded.frame == 7 + i and decoded.is_key == (i == 0)
        # the device's y is exactly the host's quantized scores: same frame as `view`
        np.testing.assert_array_equal(decoded.y, model.quantized_scores(*view))
        sizes[decoded.is_key].append(len(packet.packet))
    # neighbouring views: a delta is smaller than a key frame of the same view
    key_again = FrameEncoder(model).encode(views[-1])
    assert np.mean(sizes[False]) < len(key_again.packet)
    only_keys = FrameEncoder(model, keyframe_interval=1)
    assert all(decoder.decode(only_keys.encode(v).packet).is_key for v in views[:3])
    every_3 = FrameEncoder(model, keyframe_interval=3)
    kinds = []
    for v in views[:7]:
        every_3.encode(v)
        kinds.append(every_3.last_was_key)
    assert kinds == [True, False, False, True, False, False, True]


def _provisioned_device(tmp_path, model_path, name, **kwargs):
    frames = tmp_path / "frames"
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", frames=frames,
                           **kwargs)
    result = provision(model_path, f"mem://{name}?end=a&pace=0",
                       ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
    assert result.confirmed is True  # the runtime confirmed after showing the first frame
    return device, frames


def test_orbit_frames_are_identical_to_eigencast_view(tmp_path, model_path, model):
    name = mem_name("serve")
    device, frames = _provisioned_device(tmp_path, model_path, name)
    with device:
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit("steps:9:20"),
                                   fps=60), ServeParts(log=_quiet))
        assert stats.frames == 9 and stats.key_frames == 1 and stats.delta_frames == 8
        wait_until(lambda: any(float(r["phi_deg"]) == 320.0 for r in read_frames(frames)), 10,
                   "the orbit's last view on the device")
    rows = read_frames(frames)
    assert check_frames(model, frames, rows) >= 2
    assert {float(r["theta_deg"]) for r in rows} == {20.0}
    assert rows[0]["key"] == "1"


def test_view_requests_are_answered_and_coalesced_on_a_slow_line(tmp_path, model_path, model):
    name = mem_name("slow")
    device, frames = _provisioned_device(tmp_path, model_path, name, request_rate_hz=1000)
    # 9600 baud: ~1 kB/s, a few hundred bytes per packet -> requests pile up
    slow = f"mem://{name}-x?end=b"
    device.stop()
    device = RuntimeThread(tmp_path / "flash", slow, frames=frames, request_rate_hz=1000,
                           baud=9600)
    stop = threading.Event()
    result = {}

    def host():
        result["stats"] = serve(model_path, f"mem://{name}-x?end=a",
                                ServeOptions(baud=9600, key=KEY, scores="interpolate"),
                                ServeParts(stop=stop, log=_quiet))

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    try:
        wait_until(lambda: device.device.runtime_stats.frames_presented >= 2, 20, "first frame")
        for i in range(40):  # a fast drag: 40 views in a burst
            device.device.set_view(100.0 + i, 5.0)
            threading.Event().wait(0.005)
        wait_until(lambda: device.device._shown_view == (139.0, 5.0), 30, "the last view")
    finally:
        stop.set()
        thread.join(10)
        device.stop()
    stats = result["stats"]
    assert stats.coalesced > 0 and stats.frames < 40  # superseded requests were not answered
    assert check_frames(model, frames) >= 2


def test_lossy_line_recovers_with_key_frames(tmp_path, model_path, model):
    name = mem_name("lossy")
    device, frames = _provisioned_device(tmp_path, model_path, name)
    device.stop()
    # the host -> device direction loses whole packets now and then
    lossy_b = f"mem://{name}-l?end=b"
    lossy_a = f"mem://{name}-l?end=a&burst=0.0002&burst_bytes=64&seed=3"
    device = RuntimeThread(tmp_path / "flash", lossy_b, frames=frames, baud=921600)
    with device:
        stats = serve(model_path, lossy_a,
                      ServeOptions(baud=921600, key=KEY, scores="interpolate",
                                   orbit=parse_orbit("steps:120:-10"), fps=0, max_reconnects=20),
                      ServeParts(log=_quiet))
        wait_until(lambda: any(float(r["phi_deg"]) == 357.0 for r in read_frames(frames)), 20,
                   "the orbit's last view")
    rs = device.device.runtime_stats
    assert rs.missing_base > 0 and rs.keyframe_requests > 0  # a delta lost its base
    assert stats.keyframe_requests > 0 and stats.key_frames > 1  # ... and a key frame came
    assert check_frames(model, frames) > 10  # every frame shown is still exact


def test_serve_refuses_a_device_without_the_image_unless_provisioning(tmp_path, model_path,
                                                                    model):
    name = mem_name("noimg")
    frames = tmp_path / "frames"
    with RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", frames=frames):
        with pytest.raises(ServeError, match=r"does not hold .*eigencast provision"):
            serve(model_path, f"mem://{name}?end=a&pace=0",
                  ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit(
                "steps:2")), ServeParts(log=_quiet))
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, scores="interpolate", provision_missing=True,
                                   orbit=parse_orbit("steps:3:0")), ServeParts(log=_quiet))
        assert stats.provisioned and stats.frames == 3
        wait_until(lambda: len(read_frames(frames)) >= 1, 10, "a frame")
    assert check_frames(model, frames) >= 1


def test_serve_cli_errors_are_one_line(tmp_path, model_path):
    cli = [sys.executable, "-m", "host.cli", "serve"]
    for args, text in [
        ([str(model_path), "--port", "mem://x?end=a", "--orbit", "spin:3"], "turn:SECONDS"),
        ([str(model_path), "--port", "mem://x?end=a", "--orbit", "steps:0"], "N=0"),
        ([str(tmp_path / "none.ecs"), "--port", "mem://x?end=a"], "none.ecs"),
        ([str(model_path), "--port", "socket://127.0.0.1:9", "--no-reconnect"], "127.0.0.1:9"),
    ]:
        res = subprocess.run([*cli, *args], capture_output=True, text=True, timeout=60)
        assert res.returncode == 1, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1 and text in res.stderr, res.stderr


def test_a_packet_larger_than_the_devices_frames_is_a_one_line_error(tmp_path, model_path,
                                                                     monkeypatch):
    """A device on a serial line takes 4 KiB frames by default; a model whose key packets are
    larger must not crash serve with a traceback but say what to change."""
    import dataclasses

    from device_runtime.device import DeviceConfig

    name = mem_name("bigpkt")
    config = DeviceConfig(flash_dir=tmp_path / "flash", key=KEY, max_frame_bytes=1024)
    with RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", config=config):
        provision(model_path, f"mem://{name}?end=a&pace=0",
                  ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
        real = FrameEncoder.encode

        def padded(self, view, *, key=False, scores=None):  # a model with 2 kB packets
            encoded = real(self, view, key=key, scores=scores)
            return dataclasses.replace(encoded, packet=encoded.packet + bytes(2000))

        monkeypatch.setattr(FrameEncoder, "encode", padded)
        with pytest.raises(ServeError, match=r"max_frame_bytes=1024.*--max-frame"):
            serve(model_path, f"mem://{name}?end=a&pace=0",
                  ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit("steps:2")),
                  ServeParts(log=_quiet))
    # a device that takes large frames gets them, although the host's serial line would
    # default to 4 KiB frames
    name = mem_name("bigpkt2")
    config = DeviceConfig(flash_dir=tmp_path / "flash", key=KEY, max_frame_bytes=16384)
    with RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", config=config):
        monkeypatch.setattr(FrameEncoder, "encode", lambda self, view, *, key=False,
                            scores=None: (
            dataclasses.replace(real(self, view, key=key), packet=real(
                self, view, key=key).packet + bytes(6000))))
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit("steps:2")),
                      ServeParts(log=_quiet))
    assert stats.frames == 2 and stats.packet_bytes > 12000


def test_serve_with_a_key_refuses_a_device_that_says_it_holds_none(tmp_path, model_path, model):
    """Item 4 of issue 11: a keyless device (an impostor, or has_key cleared on the way) gets
    no SCORES from ``serve --key`` unless ``--insecure`` is given."""
    from device_runtime.device import DeviceConfig
    from protocol import messages as m
    from protocol.errors import AuthenticationError

    name = mem_name("impostor")
    frames = tmp_path / "frames"
    config = DeviceConfig(flash_dir=tmp_path / "flash", key=None, insecure=True)
    with RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", frames=frames,
                       config=config) as device:
        provision(model_path, f"mem://{name}?end=a&pace=0",
                  ProvisionOptions(key=None, show_progress=False), ProvisionParts(log=_quiet))
        seen = []
        on_scores = device.device.handle_scores
        device.device.on(m.MessageType.SCORES,
                         lambda msg, frame: (seen.append(msg), on_scores(msg, frame))[1])
        with pytest.raises(AuthenticationError, match=r"holds no key.*--insecure"):
            serve(model_path, f"mem://{name}?end=a&pace=0",
                  ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit("steps:3:0")),
                  ServeParts(log=_quiet))
        assert seen == [] and read_frames(frames) == []
        lines = []
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, scores="interpolate", insecure=True,
                                   orbit=parse_orbit("steps:3:0")), ServeParts(log=lines.append))
        assert stats.frames == 3
        wait_until(lambda: len(seen) == 3, 10, "the three packets on the device")
    assert sum("--insecure" in line for line in lines) == 1


def test_serve_cli_with_a_key_to_a_keyless_device_is_one_line(tmp_path, model_path):
    from provision_helpers import DeviceProcess

    from protocol.keys import write_key

    write_key(tmp_path / "k.key", KEY)
    device = DeviceProcess(tmp_path / "flash", "--insecure", "--headless")
    try:
        res = subprocess.run([sys.executable, "-m", "host.cli", "serve", str(model_path),
                              "--port", device.url, "--key", str(tmp_path / "k.key"),
                              "--orbit", "steps:2", "--no-reconnect"],
                             capture_output=True, text=True, timeout=60)
    finally:
        device.stop()
    assert res.returncode == 1, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "holds no key" in res.stderr
    assert any("presented 0 frames" in line for line in device.lines), device.lines
