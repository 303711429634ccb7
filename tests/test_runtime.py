"""The device runtime: orbits, latest-wins slots, confirm-after-frame, deltas, memory."""

from __future__ import annotations

import threading
import time
import tracemalloc

import numpy as np
import pytest
from provision_helpers import KEY, mem_name
from runtime_helpers import RuntimeThread, wait_until

from device_runtime.device import DeviceConfig
from device_runtime.display import HeadlessPresenter, ViewDelta
from device_runtime.orbit import canonical_view
from device_runtime.runtime import LatestSlot, RequestLimiter, RuntimeDevice, ScoreItem
from host.fit.model import HostModel
from host.link.options import ProvisionOptions, ProvisionParts
from host.link.provisioning import provision
from protocol import auth
from protocol import messages as m
from protocol.host_session import HostSession
from protocol.image import read_image
from protocol.link import Link
from protocol.scores import DecodedScores, encode_scores
from protocol.transport import open_transport


def test_latest_slot_and_request_limiter_keep_only_the_newest():
    slot = LatestSlot()
    assert slot.take(0.0) is None
    for i in range(5):
        slot.put(i)
    assert slot.take(0.0) == 4 and slot.replaced == 4 and slot.take(0.01) is None
    limiter = RequestLimiter(10.0)  # one per 0.1 s
    limiter.offer("a")
    assert limiter.due(0.0) == "a" and limiter.due(0.01) is None
    limiter.offer("b")
    limiter.offer("c")
    assert limiter.due(0.05) is None  # too soon
    assert limiter.due(0.11) == "c" and limiter.coalesced == 1 and not limiter.pending


class FakeLink:
    """Captures what the runtime sends; looks like an open link with a session."""

    closed = False

    def __init__(self):
        self.sent = []

    def send(self, msg, **kwargs):
        self.sent.append(msg)

    def defer(self, task):
        task()


def _device(tmp_path, model_path, **kwargs):
    """A RuntimeDevice with the tiny model provisioned (confirmed) and a fake link."""
    name = mem_name("rt")
    with RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0"):
        provision(model_path, f"mem://{name}?end=a&pace=0",
                  ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=lambda line: None))
    presenter = kwargs.pop("presenter", None) or HeadlessPresenter(None)
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY),
                           presenter=presenter, log=lambda line: None, **kwargs)
    device.link = FakeLink()
    device.session.device_nonce = bytes(16)  # as after HELLO ...
    device.session.session_key = bytes(32)  # ... and AUTH (a keyed device asks only then)
    return device


def test_a_test_image_is_confirmed_only_once_a_frame_was_shown(tmp_path, model_path):
    name = mem_name("confirm")
    # a device whose display loop does not run: provisioning commits a TEST image ...
    rt = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", display=False)
    try:
        result = provision(model_path, f"mem://{name}?end=a&pace=0",
                           ProvisionOptions(key=KEY, show_progress=False, confirm_timeout_s=0.3),
                           ProvisionParts(log=lambda line: None))
        assert result.outcome == "installed" and result.confirmed is None
        assert rt.device.store.slots[0].state.name == "TEST"
        # ... which the first presented frame confirms
        frames = []
        rt.device.on_frame = lambda frame, info: frames.append(frame.copy())
        rt.device.max_frames = 1
        rt.device.run_display()
        assert len(frames) == 1
        wait_until(lambda: rt.device.store.slots[0].state.name == "CONFIRMED", 5, "confirm")
        # the first frame of an image is its mean (no scores yet)
        image = read_image(model_path)
        mean = np.zeros(image.n_coefficients, np.float32)
        np.testing.assert_array_equal(frames[0], HostModel.load(model_path).reconstruct(mean))
    finally:
        rt.stop()


def test_packets_are_decoded_in_order_and_only_the_newest_is_shown(tmp_path, model_path, model):
    shown = []
    device = _device(tmp_path, model_path, max_frames=2,
                     on_frame=lambda frame, info: shown.append((info.get("frame"), frame.copy())))
    base = None
    for i, phi in enumerate((10.0, 11.0, 12.0, 13.0)):
        view = canonical_view(phi, 0.0)
        base = encode_scores(model.quantized_scores(*view), step=model.score_step, frame=50 + i,
                             view=view, image_digest=model.digest, base=base)
        device.on_scores(m.Scores(sequence=0, packet=base.packet))  # display not running
    device.run_display()  # shows the mean, then the newest packet only
    assert [f for f, _ in shown] == [0, 53]
    np.testing.assert_array_equal(shown[1][1], model.view(13.0, 0.0))
    stats = device.stats_dict()
    assert stats["key_frames"] == 1 and stats["delta_frames"] == 3 and stats["coalesced"] == 3
    # the overlay: a rate while frames flow, "idle" (not "0.0 fps") once the view rests
    rt = device.runtime_stats
    link, device.link = device.link, None  # the fake link keeps no byte counters
    rt._present_times.clear()
    rt._present_times.extend([time.monotonic() - 0.2, time.monotonic() - 0.1])
    assert device.overlay_lines()[0].lstrip().startswith("10.0 fps")
    rt._present_times.clear()
    rt._present_times.extend([time.monotonic() - 5.1, time.monotonic() - 5.0])
    first = device.overlay_lines()[0]
    assert first.split()[0] == "idle" and "fps" not in first and "frame 2" in first
    device.link = link
    device.close_display()
    device.close()


def test_a_delta_without_its_base_asks_for_a_key_frame(tmp_path, model_path, model):
    device = _device(tmp_path, model_path)
    view = canonical_view(40.0, 10.0)
    key = encode_scores(model.quantized_scores(*view), step=model.score_step, frame=7,
                        view=view, image_digest=model.digest)
    lost = encode_scores(model.quantized_scores(41.0, 10.0), step=model.score_step, frame=8,
                         view=(41.0, 10.0), image_digest=model.digest, base=key)
    orphan = encode_scores(model.quantized_scores(42.0, 10.0), step=model.score_step, frame=9,
                           view=(42.0, 10.0), image_digest=model.digest, base=lost)
    device.on_scores(m.Scores(sequence=0, packet=key.packet))
    device.on_scores(m.Scores(sequence=0, packet=orphan.packet))  # frame 8 never arrived
    requests = [msg for msg in device.link.sent if isinstance(msg, m.KeyframeRequest)]
    assert len(requests) == 1 and requests[0].last_frame == 7
    assert device.runtime_stats.missing_base == 1
    # a new session forgets every base: a delta against frame 7 is refused now
    version = m.PROTOCOL_VERSION
    device.handle_hello(m.Hello(min_version=version, max_version=version, nonce=bytes(16)), None)
    device._last_keyframe_request = -1e9
    again = encode_scores(model.quantized_scores(43.0, 10.0), step=model.score_step, frame=10,
                          view=(43.0, 10.0), image_digest=model.digest, base=key)
    device.on_scores(m.Scores(sequence=0, packet=again.packet))
    assert device.runtime_stats.missing_base == 2
    other = encode_scores(model.quantized_scores(*view), step=model.score_step, frame=11,
                          view=view, image_digest=bytes(32))
    device.on_scores(m.Scores(sequence=0, packet=other.packet))  # another image's packet
    assert device.runtime_stats.wrong_image == 1
    device.close_display()
    device.close()


def test_input_becomes_rate_limited_view_requests(tmp_path, model_path):
    device = _device(tmp_path, model_path, view=(350.0, 85.0), request_rate_hz=5.0,
                     max_frames=1)
    device.run_display()  # shows the mean and requests the initial view
    first = [msg for msg in device.link.sent if isinstance(msg, m.ViewRequest)]
    assert [(r.phi_deg, r.theta_deg) for r in first] == [(350.0, 85.0)]
    device.link.sent.clear()
    for _ in range(4):  # a drag within one request interval: only the newest view is sent
        device.apply(ViewDelta(5.0, 5.0))
    device.max_frames = None
    device.stop_event.clear()
    timer = threading.Timer(0.5, device.stop_event.set)
    timer.start()
    device.run_display()
    sent = [msg for msg in device.link.sent if isinstance(msg, m.ViewRequest)]
    assert [(r.phi_deg, r.theta_deg) for r in sent] == [(10.0, 90.0)]  # wrapped and clamped
    assert sent[0].sequence == first[0].sequence + 1
    device.close_display()
    device.close()


def test_memory_stays_flat_over_many_frames(tmp_path, model_path, model):
    device = _device(tmp_path, model_path)
    device._models.take(0.0)
    loaded = device._decoder_model
    device._model = loaded
    packets = []
    base = None
    for i in range(50):
        view = canonical_view(7.2 * i, 10.0)
        base = encode_scores(model.quantized_scores(*view), step=model.score_step, frame=i + 1,
                             view=view, image_digest=model.digest, base=base)
        packets.append(base.packet)

    def run(n, start):
        for k in range(n):
            device.on_scores(m.Scores(sequence=0, packet=packets[(start + k) % 50]))
            item = device._scores.take(0.0)
            device._present(item.model, item.scores.y, {"frame": item.scores.frame,
                                                        "sequence": start + k + 1})
            device._request_times[start + k + 2] = 0.0  # as if a request were outstanding

    run(300, 0)  # warm up (caches, rings fill)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    run(2000, 300)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, "filename"))
    assert grown < 64 * 1024, f"grew {grown} bytes over 2000 frames"
    assert len(device._request_times) <= 64
    assert device.runtime_stats.frames_presented == 2300
    device.close_display()
    device.close()


def test_large_eigenspace_runs_on_two_threads_with_identical_frames():
    """LoadedModel picks 2 reconstruction threads for a large eigenspace on a 2-CPU machine;
    its frames equal the 1-thread reconstruction's bit for bit (what `eigencast view` shows)."""
    import os

    from device_runtime.reconstruct import Reconstructor
    from device_runtime.runtime import LoadedModel
    from protocol.image import EigenspaceImage

    rng = np.random.default_rng(4)
    cell = (30, 30)
    n_cells = 5 * 5
    values = 30 * 30 * 3
    # > 8 MB of int8; k * 2700 stays under OpenBLAS's own threading threshold (~460800)
    counts = rng.integers(110, 160, n_cells).astype(np.int32)
    counts[3] = 0
    k = int(counts.sum())
    image = EigenspaceImage(
        image_shape=(150, 150), cell_shape=cell,
        mean=rng.integers(0, 256, (n_cells, values), dtype=np.uint8),
        eigenimages=rng.integers(-127, 128, (k, values), dtype=np.int8),
        scales=np.full(k, 0.02, dtype=np.float32), n_components=counts, method="adaptive")
    assert image.eigenimages.nbytes > 8_000_000
    loaded = LoadedModel.build(image, slot="A", generation=1, test=False)
    single = Reconstructor.from_image(image, threads=1)
    try:
        assert loaded.reconstructor.threads == (2 if (os.cpu_count() or 1) >= 2 else 1)
        for _ in range(3):
            y = (rng.standard_normal(k) * 200).astype(np.float32)
            np.testing.assert_array_equal(loaded.reconstructor.update(y), single.update(y))
    finally:
        loaded.close()
        single.close()


def test_peak_rss_is_this_process_not_the_parent_before_exec():
    """ru_maxrss survives exec (a child of a big host would report the host's size); the
    runtime's peak RSS is VmHWM, this process's own."""
    import subprocess
    import sys

    from device_runtime.runtime import peak_rss_bytes

    ballast = np.ones(200 * 2**20, dtype=np.uint8)  # this process: > 200 MB resident
    code = "from device_runtime.runtime import peak_rss_bytes; print(peak_rss_bytes())"
    child = int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                               check=True).stdout)
    assert peak_rss_bytes() > 200 * 2**20
    assert 0 < child < 150 * 2**20, child
    del ballast


# ------------------------------------------------------------------ hostile peers (issue 11)


def _overflow_packet(model, mode: int) -> bytes:
    from test_scores import overflow_packet

    return overflow_packet(model.image.n_coefficients, model.digest, mode=mode)


def _key_packet(model, phi: float, theta: float, frame: int) -> bytes:
    view = canonical_view(phi, theta)
    return encode_scores(model.quantized_scores(*view), step=model.score_step, frame=frame,
                         view=view, image_digest=model.digest).packet


class _Shown:
    """Collects what a runtime presents: (phi_deg, theta_deg) of every frame with a view."""

    def __init__(self):
        self.views = []
        self.frames = {}

    def __call__(self, frame, info):
        if info.get("phi_deg") is not None:
            view = (info["phi_deg"], info["theta_deg"])
            self.views.append(view)
            self.frames[view] = frame.copy()


def _serving_runtime(tmp_path, model_path, *, key=KEY):
    """A RuntimeThread on mem:// with the tiny model installed; returns (rt, host url, shown)."""
    name = mem_name("hostile")
    flash = tmp_path / "flash"
    if key is None:  # install with a keyed device first; the keyless one boots the same flash
        with RuntimeThread(flash, f"mem://{name}-p?end=b&pace=0"):
            provision(model_path, f"mem://{name}-p?end=a&pace=0",
                      ProvisionOptions(key=KEY, show_progress=False),
                      ProvisionParts(log=lambda line: None))
    shown = _Shown()
    rt = RuntimeThread(flash, f"mem://{name}?end=b&pace=0", on_frame=shown,
                       config=DeviceConfig(flash_dir=flash, key=key))
    url = f"mem://{name}?end=a&pace=0"
    if key is not None:
        provision(model_path, url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=lambda line: None))
    return rt, url, shown


def _session(url, key=KEY):
    link = Link(open_transport(url, timeout_s=5), owns_transport=True).start()
    session = HostSession(link, key=key, request_timeout_s=0.5)
    session.start()
    return session


@pytest.mark.parametrize("mode", [0, 2], ids=["scalar-step", "per-component-step"])
def test_an_overflowing_score_packet_does_not_stop_the_device(tmp_path, model_path, model,
                                                              mode):
    rt, url, shown = _serving_runtime(tmp_path, model_path)
    try:
        session = _session(url)
        session.send_scores(m.Scores(sequence=0, packet=_overflow_packet(model, mode)))
        wait_until(lambda: rt.device.runtime_stats.decode_errors == 1, 10, "the refusal")
        session.send_scores(m.Scores(sequence=0, packet=_key_packet(model, 20.0, 10.0, 5)))
        wait_until(lambda: canonical_view(20.0, 10.0) in shown.views, 10, "the good frame")
        np.testing.assert_array_equal(shown.frames[canonical_view(20.0, 10.0)],
                                      model.view(20.0, 10.0))
        assert not rt.errors and all(t.is_alive() for t in rt.threads)
        session.link.close()
    finally:
        rt.stop()


def test_a_frame_the_display_cannot_show_is_skipped(tmp_path, model_path, model):
    shown = _Shown()
    device = _device(tmp_path, model_path, max_frames=2, on_frame=shown)
    k = model.image.n_coefficients

    def item(y, frame, phi):
        scores = DecodedScores(frame=frame, base_frame=None, phi_deg=phi, theta_deg=0.0, y=y,
                               q=np.zeros(k, np.int32), step=1.0, packet_bytes=40)
        return ScoreItem(device._decoder_model, scores, 0, time.monotonic())

    bad = np.full(k, np.inf, np.float32)  # what a decoder without bounds handed on
    good_y = model.quantized_scores(*canonical_view(30.0, 0.0))
    good = item(np.asarray(good_y, np.float32), 2, canonical_view(30.0, 0.0)[0])
    device._scores.put(item(bad, 1, 10.0))
    failed = device._frame_failed

    def then_a_good_one(frame, exc):
        failed(frame, exc)
        device._scores.put(good)

    device._frame_failed = then_a_good_one
    lines = []
    device._log = lines.append
    device.run_display()  # returns after the mean and the good frame: it did not die
    assert shown.views == [(canonical_view(30.0, 0.0)[0], 0.0)]
    assert device.runtime_stats.frame_failures == 1
    assert sum("frame 1 skipped" in line for line in lines) == 1
    device.close_display()
    device.close()


def test_scores_without_hello_are_not_shown(tmp_path, model_path, model):
    rt, url, shown = _serving_runtime(tmp_path, model_path, key=None)
    try:
        attacker = Link(open_transport(url, timeout_s=5), owns_transport=True).start()
        attacker.send(m.Scores(sequence=0, packet=_key_packet(model, 50.0, 5.0, 3)))
        wait_until(lambda: rt.device.stats.dropped_no_session == 1, 10, "the drop")
        assert rt.device.runtime_stats.packets == 0 and shown.views == []
        attacker.close()
        session = _session(url, key=None)  # keyless: after HELLO, untagged scores are shown
        session.send_scores(m.Scores(sequence=0, packet=_key_packet(model, 50.0, 5.0, 4)))
        wait_until(lambda: canonical_view(50.0, 5.0) in shown.views, 10, "the frame")
        session.link.close()
    finally:
        rt.stop()


def test_keyed_device_shows_only_tagged_fresh_scores_of_an_authenticated_session(
        tmp_path, model_path, model):
    rt, url, shown = _serving_runtime(tmp_path, model_path)
    stats = rt.device.stats
    try:
        # HELLO without AUTH: scores dropped, and a delta with an unknown base asks nothing
        got = []
        attacker = Link(open_transport(url, timeout_s=5), owns_transport=True,
                        handler=lambda msg, frame: got.append(msg)).start()
        version = m.PROTOCOL_VERSION
        attacker.request(m.Hello(min_version=version, max_version=version, nonce=bytes(16)))
        attacker.send(m.Scores(sequence=0, packet=_key_packet(model, 60.0, 0.0, 3)))
        wait_until(lambda: stats.dropped_unauthenticated == 1, 10, "the untagged drop")
        key = encode_scores(model.quantized_scores(61.0, 0.0), step=model.score_step, frame=7,
                            view=(61.0, 0.0), image_digest=model.digest)
        delta = encode_scores(model.quantized_scores(62.0, 0.0), step=model.score_step,
                              frame=8, view=(62.0, 0.0), image_digest=model.digest, base=key)
        attacker.send(m.Scores(sequence=0, packet=delta.packet))
        wait_until(lambda: stats.dropped_unauthenticated == 2, 10, "the delta drop")
        # an unauthenticated peer learns nothing: no key-frame (K probe) or view requests
        assert not any(isinstance(msg, (m.KeyframeRequest, m.ViewRequest)) for msg in got)
        assert rt.device.runtime_stats.packets == 0
        attacker.close()
        # an authenticated session: a wrong tag and a replay are dropped, fresh tags shown
        session = _session(url)
        wrong = auth.tag_event(m.Scores(sequence=0, packet=_key_packet(model, 70.0, 0.0, 10)),
                            bytes(32), 1)
        session.link.send(wrong)
        wait_until(lambda: stats.dropped_bad_tag == 1, 10, "the bad-tag drop")
        first = session.tag_event(m.Scores(sequence=0, packet=_key_packet(model, 71.0, 0.0, 11)))
        session.link.send(first)
        wait_until(lambda: canonical_view(71.0, 0.0) in shown.views, 10, "the first frame")
        session.send_scores(m.Scores(sequence=0, packet=_key_packet(model, 72.0, 0.0, 12)))
        wait_until(lambda: canonical_view(72.0, 0.0) in shown.views, 10, "the second frame")
        session.link.send(first)  # replayed
        wait_until(lambda: stats.dropped_replayed == 1, 10, "the replay drop")
        assert shown.views.count(canonical_view(71.0, 0.0)) == 1
        assert canonical_view(70.0, 0.0) not in shown.views
        assert not any(v[0] in (60.0, 61.0, 62.0) for v in shown.views)
        session.link.close()
    finally:
        rt.stop()
