"""The one served path: the device shows its own frame, the host corrects that frame.

A device whose image holds the standalone table synthesizes every new view itself (the
depth warp of its neighbours for an image with depth, the blend of its predicted scores
otherwise: `device_runtime.prediction.OwnFrames`); the host computes the same frame, ray-casts
the view and sends a version-3 packet whose scores the device adds to its own frame
(`Reconstructor.correct`). These tests check the arithmetic (full samples: the frame plus
the projection of the residual; no samples: no change), the bit-identity of host and device
frames for both kinds of image, the wire, how small arithmetic differences between a host
and a device stay bounded, a real paced session, staleness, and the fallbacks.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest
from provision_helpers import KEY, mem_name
from runtime_helpers import (
    RuntimeThread,
    provisioned_device,
    serve_cli,
    steady_requests,
    wait_until,
)

from device_runtime.device import DeviceConfig
from device_runtime.orbit import canonical_view
from device_runtime.prediction import OwnFrames, Predictor
from device_runtime.reconstruct import Reconstructor
from device_runtime.runtime import LoadedModel, RuntimeDevice, ScoreItem
from host.cli import main as eigencast
from host.fit.cells import split_cells
from host.fit.model import HostModel
from host.fit.motion import MotionScores, ResidualPrior
from host.fit.rate import rd_quantize
from host.link.correction import CorrectionEncoder, can_correct, cannot_correct
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import serve
from host.link.true_views import open_true_view_scores
from protocol import messages as m
from protocol.image import read_image
from protocol.scores import (
    ScoreDecoder,
    ScorePacketError,
    decode_header,
    encode_scores,
)

VIEWS = [(0.0, 0.0), (11.0, 13.0), (200.0, -40.0), (97.5, 51.0), (123.456, 7.891)]


def _quiet(line: str) -> None:
    pass


@pytest.fixture(scope="module")
def depth_model(depth_model_path):
    return HostModel.load(depth_model_path)


@pytest.fixture(scope="module", params=["blend", "depth"])
def kind(request, model_path, model, depth_model_path, depth_model):
    """(model path, HostModel) of an image without depth (own frames are blends) and one with
    depth (own frames are warps)."""
    return (model_path, model) if request.param == "blend" else (depth_model_path, depth_model)


def _renderer(model):
    return open_true_view_scores(model).renderer


def _decoder(model, **kwargs) -> ScoreDecoder:
    return ScoreDecoder(model.image.n_coefficients, model.digest,
                        n_components=model.image.n_components, **kwargs)


def _cells(model, image) -> np.ndarray:
    return split_cells(np.asarray(image)[None], model.image.cell_shape)[0].astype(np.float64)


# --------------------------------------------------------------------------- arithmetic


def test_full_samples_at_a_fine_step_give_the_frame_plus_the_projected_residual(kind):
    """With every pixel ray-cast and a fine step the frame is ``S + P(truth - S)``: per cell,
    ``S_c`` plus the least-squares fit of the residual on the cell's own basis."""
    _path, model = kind
    renderer = _renderer(model)
    own = OwnFrames(model.image)
    own.reconstructor.seam_strength = 0.0  # the arithmetic; the seams' smoothing is below
    source = MotionScores(model, renderer, own=own, strides=(1,), budget_s=3600.0, coarse=1.0)
    img = model.image
    counts = np.asarray(img.n_components)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    for view in VIEWS[:3]:
        view = canonical_view(*view)
        truth, _ = renderer.render(*view)
        synth = own.frame(*view)
        step = source.frame(view)
        assert step.complete and step.stride == 1
        d = rd_quantize(model, step.scores, step=1e-4, lam=0.0)  # a fine step
        frame = own.corrected(synth, d)
        # the reference, in float64: each cell's residual fitted on its own int8 basis
        resid = _cells(model, truth) - _cells(model, synth)
        want = _cells(model, synth)
        for c in range(img.n_cells):
            lo, hi = offsets[c], offsets[c + 1]
            if hi == lo:
                continue
            basis = img.eigenimages[lo:hi].astype(np.float64) * img.scales[lo:hi, None]
            coef = np.linalg.lstsq(basis.T, resid[c], rcond=None)[0]
            want[c] += basis.T @ coef
        want = np.clip(np.rint(want), 0, 255)
        got = _cells(model, frame)
        assert np.abs(got - want).max() <= 1.0, view  # rounding of float32 vs float64
        # and it never moved a cell away from the truth (the projection's guarantee)
        err = ((_cells(model, truth) - got) ** 2).sum(axis=1)
        before = ((_cells(model, truth) - _cells(model, synth)) ** 2).sum(axis=1)
        assert np.all(err <= before + 3.0 * img.cell_shape[0] * img.cell_shape[1]), view


def test_a_correction_smooths_the_jumps_it_makes_at_cell_borders(kind):
    """The correction is fitted cell by cell, so it steps at cell borders: the device moves
    the pixel either side of each border a third of half that step towards the other. Only
    the border strips change, the correction's jumps shrink (large ones to about 2/3), and the
    frame stays about as close to the truth (a least-squares fit, smoothed, is a little off
    it; on real volumes the object SSIM moves by at most 0.001)."""
    _path, model = kind
    renderer = _renderer(model)
    own = OwnFrames(model.image)
    source = MotionScores(model, renderer, own=own, strides=(1,), budget_s=3600.0, coarse=1.0)
    ch, cw = model.image.cell_shape
    h, w = model.image.image_shape
    border = np.zeros((h, w), dtype=bool)
    border[:, cw - 1 : -1 : cw] = border[:, cw::cw] = True
    border[ch - 1 : -1 : ch] = border[ch::ch] = True
    for view in VIEWS[:3]:
        view = canonical_view(*view)
        truth, _ = renderer.render(*view)
        synth = own.frame(*view)
        d = rd_quantize(model, source.frame(view).scores, step=1e-4, lam=0.0)
        own.reconstructor.seam_strength = 0.0
        sharp = own.corrected(synth, d).astype(np.int32)
        own.reconstructor.seam_strength = 0.5
        smooth = own.corrected(synth, d).astype(np.int32)
        assert np.array_equal(sharp[~border], smooth[~border])  # only the border strips
        assert not np.array_equal(sharp, smooth)
        jumps = []
        for frame in (sharp, smooth):
            corr = frame - synth.astype(np.int32)
            jumps.append(np.abs(np.diff(corr, axis=1)[:, cw - 1 :: cw]).sum()
                         + np.abs(np.diff(corr, axis=0)[ch - 1 :: ch]).sum())
        assert jumps[1] <= 0.85 * jumps[0], view  # 2/3 of a large jump; a 1-2 stays
        err = [np.abs(f - truth.astype(np.int32)).sum() for f in (sharp, smooth)]
        assert err[1] <= err[0] * 1.05, view  # at most a little further from the truth


def test_no_samples_means_no_change(kind):
    """A host with no time for a single ray sends nothing; a zero residual recovers a zero
    correction; a zero correction shows the device's own frame unchanged."""
    _path, model = kind
    own = OwnFrames(model.image)
    source = MotionScores(model, _renderer(model), own=own, strides=(4,))
    source.budget_s = 1e-9
    source.frame((10.0, 5.0))  # measures the host: far over that budget
    step = source.frame((13.0, 5.0))
    assert step.stride == 0 and step.pixels == 0 and not np.any(step.scores)
    encoder = CorrectionEncoder(model)
    assert encoder.encode((13.0, 5.0), scores=step.scores) is None
    assert encoder.encode((13.0, 5.0), scores=None) is None
    pattern = source._patterns[4]
    zero = source.recovery.recover_residual(pattern, np.zeros((pattern.n_pixels, 3)))
    assert not np.any(zero)
    synth = own.frame(13.0, 5.0)
    np.testing.assert_array_equal(own.corrected(synth, np.zeros_like(zero)), synth)


def test_corrections_reuse_the_frame_and_blends_after_them_are_whole_again(depth_model):
    """`Reconstructor.correct` keeps the corrected frame's cells: a second correction of
    the same frame needs no frame, and the next blend recomputes every cell (cells without
    components show their mean again)."""
    img = depth_model.image
    rec = Reconstructor.from_image(img)
    fresh = Reconstructor.from_image(img)
    rng = np.random.default_rng(1)
    synth = rng.integers(0, 256, (*img.image_shape, 3), dtype=np.uint8)
    d1 = rng.normal(0, 20, img.n_coefficients).astype(np.float32)
    d2 = rng.normal(0, 20, img.n_coefficients).astype(np.float32)
    a = rec.correct(d1, synth).copy()
    b = rec.correct(d2).copy()
    np.testing.assert_array_equal(b, fresh.correct(d2, synth))
    assert not np.array_equal(a, b)
    y = rng.normal(0, 50, img.n_coefficients).astype(np.float32)
    np.testing.assert_array_equal(rec.update(y), Reconstructor.from_image(img).update(y))
    with pytest.raises(ValueError, match="no synthesized frame"):
        Reconstructor.from_image(img).correct(d1)


def test_the_residual_prior_grows_with_a_components_rank(model):
    prior = ResidualPrior.for_model(model)
    counts = np.asarray(model.image.n_components)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])[counts > 1]
    ratio = prior.variance / np.maximum(model.eigenvalues, 1e-12)
    assert np.all(ratio[first] < ratio[first + 1])
    assert ratio.max() <= 1.0 and ratio.min() >= 0.0 and prior.lam > 0


# --------------------------------------------------------------------------- bit identity


def test_host_and_device_make_the_same_own_and_corrected_frames(kind):
    """The device's own frame (its display reconstructor for blends, its warp worker's
    lean reconstructor for warps) and the corrected frame are the host's bit for bit."""
    path, model = kind
    device = LoadedModel.build(read_image(path, key=KEY), slot="A", generation=1, test=False,
                               want_predictor=True)
    host = OwnFrames(model.image)
    encoder = CorrectionEncoder(model)
    renderer = _renderer(model)
    try:
        for view in VIEWS:
            view = canonical_view(*view)
            mine = host.frame(*view)
            if device.warp_worker is not None:
                device.warp_worker.request(view)
                theirs = device.warp_worker.take(view, 30.0)
            else:
                theirs = device.reconstructor.update(device.predictor(*view)).copy()
            np.testing.assert_array_equal(mine, theirs)
            truth, _ = renderer.render(*view)
            d = model.project(truth) - model.project(mine)
            packet = encoder.encode(view, scores=d, fine=True)
            y = device.decoder.decode(packet.packet).y
            np.testing.assert_array_equal(host.corrected(mine, y),
                                          device.reconstructor.correct(y, theirs))
    finally:
        device.close()


def test_arithmetic_differences_between_host_and_device_do_not_grow(depth_model):
    """A device on another CPU may make its own frame a level off here and there (float32
    last bits tipping a rounding), and add the correction with other rounding. The
    correction is added to the device's *own* frame and never fed back: the corrected frames
    differ by at most the own frames' difference plus one level, and at the pixels either
    side of a cell border (the smoothing moves each by a sixth of the correction's jump,
    which sees its partner's difference too) by at most the pair's larger own difference
    plus two; corrections of later views start from each view's own frame again (no
    drift)."""
    from scipy.ndimage import maximum_filter

    model = depth_model
    img = model.image
    renderer = _renderer(model)
    host = OwnFrames(model.image)
    # the device: its eigenimage scales 1 ulp off (different float32 products everywhere)
    scales = np.nextafter(img.scales, np.float32(np.inf)).astype(np.float32)
    other = Reconstructor(img.mean, img.eigenimages, scales, img.n_components,
                          img.image_shape, img.cell_shape)
    encoder = CorrectionEncoder(model)
    rng = np.random.default_rng(7)
    (h, w), (ch, cw) = img.image_shape, img.cell_shape
    border = np.zeros((h, w), dtype=bool)
    border[:, cw - 1 : -1 : cw] = border[:, cw::cw] = True
    border[ch - 1 : -1 : ch] = border[ch::ch] = True
    for view in VIEWS:
        view = canonical_view(*view)
        mine = host.frame(*view)
        truth, _ = renderer.render(*view)
        packet = encoder.encode(view, scores=model.project(truth) - model.project(mine),
                                fine=True)
        y = _decoder(model).decode(packet.packet).y
        theirs = mine.astype(np.int16)
        flip = rng.random(mine.shape[:2]) < 0.01  # 1 % of pixels off, by up to 8 levels
        theirs[flip] += rng.integers(-8, 9, (int(flip.sum()), 3)).astype(np.int16)
        theirs = np.clip(theirs, 0, 255).astype(np.uint8)
        a = host.corrected(mine, y).astype(np.int16)
        b = other.correct(y, theirs).astype(np.int16)
        own_diff = np.abs(mine.astype(np.int16) - theirs.astype(np.int16))
        gap = np.abs(a - b)
        inside = ~border
        assert np.all(gap[inside] <= own_diff[inside] + 1), view
        pair = maximum_filter(own_diff, size=(3, 3, 1))  # a border pixel and its partner
        assert np.all(gap[border] <= pair[border] + 2), view


# --------------------------------------------------------------------------- wire


def test_correction_packets_are_version_3_and_never_a_delta_base(depth_model):
    model = depth_model
    encoder = CorrectionEncoder(model)
    decoder = _decoder(model)
    view = canonical_view(33.0, 21.0)
    rng = np.random.default_rng(3)
    d = rng.normal(0, 3 * model.score_step, model.image.n_coefficients)
    packet = encoder.encode(view, scores=d)
    assert encoder.last_kind == "correction"
    header = decode_header(packet.packet)
    assert header.version == 3 and header.is_synthesized and not header.is_delta
    assert not header.is_predicted and (header.phi_deg, header.theta_deg) == view
    decoded = decoder.decode(packet.packet)
    assert decoded.synthesized and decoded.frame not in decoder.base_frames
    assert float(packet.step) == pytest.approx(2 * model.score_step)  # moving: step x2
    fine = encoder.encode(view, scores=d, fine=True)
    assert float(fine.step) == pytest.approx(model.score_step)
    # an empty correction is sent only when asked (a host-driven view)
    assert encoder.encode(view, scores=np.zeros_like(d)) is None
    empty = encoder.encode(view, scores=np.zeros_like(d), always=True)
    assert not np.any(decoder.decode(empty.packet).y)
    # other packets keep their versions
    key = encode_scores(d, step=1.0, frame=1, view=view, image_digest=model.digest)
    assert decode_header(key.packet).version == 1


def test_old_decoders_refuse_a_correction_in_one_line(depth_model):
    encoder = CorrectionEncoder(depth_model)
    packet = encoder.encode((10.0, 10.0), scores=np.full(depth_model.image.n_coefficients,
                                                         50.0)).packet
    for versions in ((1,), (1, 2)):
        with pytest.raises(ScorePacketError, match="unsupported packet version 3"):
            _decoder(depth_model, versions=versions).decode(packet)


def test_bad_synthesized_packets_are_refused(depth_model):
    model = depth_model
    y = np.ones(model.image.n_coefficients)
    good = encode_scores(y, step=1.0, frame=2, view=(10.0, 5.0), image_digest=model.digest,
                         synthesized=True)
    both = bytearray(good.packet)
    both[3] |= 0x01  # SYNTHESIZED and DELTA
    with pytest.raises(ScorePacketError, match="not two of them"):
        _decoder(model).decode(bytes(both))
    predicted = bytearray(good.packet)
    predicted[3] |= 0x40  # PREDICTED is reserved in version 3
    with pytest.raises(ScorePacketError, match="reserved bits 6"):
        _decoder(model).decode(bytes(predicted))
    off = encode_scores(y, step=1.0, frame=2, view=(400.0, 5.0), image_digest=model.digest,
                        synthesized=True)
    with pytest.raises(ScorePacketError, match="not canonical"):
        _decoder(model).decode(off.packet)
    with pytest.raises(ValueError, match="not both"):
        encode_scores(y, step=1.0, frame=2, view=(1.0, 1.0), image_digest=model.digest,
                      synthesized=True, predicted=True)


def test_cannot_correct_reads_the_hello_reply():
    base = dict(min_version=2, max_version=2, device_id="d", nonce=bytes(16),
                max_frame_bytes=4096, ram_budget_bytes=0, slot_size_bytes=0, display_width=0,
                display_height=0, rx_window_frames=1, rx_buffer_bytes=1, slots=(),
                has_key=False)
    assert "older eigencast-device" in cannot_correct(m.HelloReply(**base))
    assert "older" in cannot_correct(m.HelloReply(**base, score_versions=(1, 2),
                                                  predicts=True))
    assert "does not synthesize" in cannot_correct(m.HelloReply(**base,
                                                                score_versions=(1, 2, 3)))
    assert cannot_correct(m.HelloReply(**base, score_versions=(1, 2, 3), predicts=True)) is None


# --------------------------------------------------------------------------- device


def test_stale_corrections_are_dropped_and_current_ones_shown(tmp_path, model, model_path):
    """A correction for a view the user left is dropped; one for the view on show is added
    to the device's own frame; a host-driven one (sequence 0) moves the view."""
    from runtime_helpers import DeviceConfig

    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY), predict=True)
    shown: list = []
    device.on_frame = lambda frame, info: shown.append((frame.copy(), dict(info)))
    loaded = LoadedModel.build(read_image(model_path, key=KEY), slot="A", generation=1,
                               test=False, want_predictor=True)
    try:
        encoder = CorrectionEncoder(model)
        old, new = canonical_view(20.0, 10.0), canonical_view(40.0, 10.0)
        d = np.full(model.image.n_coefficients, 3 * model.score_step)
        item = ScoreItem(loaded, loaded.decoder.decode(encoder.encode(old, scores=d).packet),
                         sequence=3, received_s=0.0)
        device.view = new  # the user moved on
        device._correct(item)
        assert device.runtime_stats.stale_dropped == 1 and not shown
        device.view = old  # still on show: its own frame, corrected
        device._correct(item)
        own = OwnFrames(model.image)
        np.testing.assert_array_equal(shown[-1][0],
                                      own.corrected(own.frame(*old), item.scores.y))
        assert shown[-1][1]["corrected"] and device.runtime_stats.corrected_frames == 1
        device._correct(ScoreItem(loaded, item.scores, sequence=0, received_s=0.0))
        assert device.view == old and device.runtime_stats.corrected_frames == 2
        host_driven = ScoreItem(loaded, loaded.decoder.decode(
            encoder.encode(new, scores=d).packet), sequence=0, received_s=0.0)
        device._correct(host_driven)
        assert device.view == new and device.runtime_stats.corrected_frames == 3
    finally:
        loaded.close()


def test_hello_says_the_device_reads_version_3_and_whether_it_predicts(tmp_path, model_path):
    from protocol.host_session import HostSession
    from protocol.link import Link
    from protocol.transport import open_transport

    name = mem_name("hello3")
    for predict in (True, False):
        url = f"mem://{name}{predict}?end=%s&pace=0"
        device = RuntimeThread(tmp_path / f"flash-{predict}", url % "b", predict=predict)
        with device:
            provision(model_path, url % "a", ProvisionOptions(key=KEY, show_progress=False),
                      ProvisionParts(log=_quiet))
            wait_until(lambda d=device: d.device._model is not None, 10, "the image loaded")
            link = Link(open_transport(url % "a", timeout_s=5), owns_transport=True).start()
            try:
                session = HostSession(link, key=KEY)
                hello = session.start()
                session.bye("done")
            finally:
                link.close(flush_timeout_s=0.5)
            assert 3 in hello.score_versions and hello.predicts is predict
            assert (cannot_correct(hello) is None) is predict


# --------------------------------------------------------------------------- sessions


def test_served_session_shows_its_own_frame_at_once_then_the_hosts_correction(
        tmp_path, depth_model_path, depth_model):
    """A real session over a paced 115200-baud mem:// line with an image with depth: a new
    view is shown as the device's own frame before any packet for it arrived (the blend,
    then its warp), then corrected; every corrected frame is exactly the host's, and once
    the view rests the complete correction at the model's own step arrives and is closer
    to the ray-cast than the warp."""
    model = depth_model
    name = mem_name("served")
    frames: list = []
    device = provisioned_device(tmp_path, name, depth_model_path, frames)
    arrivals: list = []
    original = device.device.on_scores

    def on_scores(msg):
        header = decode_header(msg.packet)
        arrivals.append(((header.phi_deg, header.theta_deg), len(frames)))
        original(msg)

    device.device.on_scores = on_scores
    sent: list = []
    stop = threading.Event()
    result: dict = {}
    lines: list[str] = []

    def host():
        # rest="correction": the corrections themselves (layers after them: test_rest_exact)
        result["stats"] = serve(depth_model_path, f"mem://{name}?end=a",
                                ServeOptions(key=KEY, rest="correction"),
                                ServeParts(stop=stop, log=lines.append,
                                           on_frame=lambda enc, view: sent.append((enc, view))))

    thread = threading.Thread(target=host, daemon=True)
    target = canonical_view(47.0, 23.0)
    with device:
        thread.start()
        try:
            wait_until(lambda: any(i.get("corrected") for _, i in frames), 60,
                       "the first correction")
            device.device.set_view(*target)
            wait_until(lambda: any(v == target and _fine(e, model) for e, v in sent), 60,
                       "the complete correction at rest")
            wait_until(lambda: frames and frames[-1][1].get("frame") == [
                e for e, v in sent if v == target][-1].frame, 30, "it shown")
        finally:
            stop.set()
            thread.join(20)
    stats = result["stats"]
    assert any("corrections of the device's own frames" in ln for ln in lines), lines
    assert stats.correction_frames >= 1 and stats.key_frames == 0
    at = [(f, i) for f, i in frames if (i.get("phi_deg"), i.get("theta_deg")) == target]
    own = OwnFrames(model.image)
    synth = own.frame(*target)
    first_arrival = min(n for v, n in arrivals if v == target)
    before = frames[:first_arrival]
    assert any(i.get("predicted") for _, i in before[-3:])  # its own frame, before any byte
    warps = [f for f, i in at if i.get("synthesized")]
    if warps:  # the warp was ready before the host's correction
        np.testing.assert_array_equal(warps[0], synth)
    decoder = _decoder(model)
    by_frame = {e.frame: decoder.decode(e.packet).y for e, v in sent if v == target}
    corrected = [(f, i) for f, i in at if i.get("corrected")]
    assert corrected
    for f, i in corrected:
        np.testing.assert_array_equal(f, own.corrected(synth, by_frame[i["frame"]]))
    truth, _ = _renderer(model).render(*target)

    def err(a):
        return float(np.mean((a.astype(float) - truth.astype(float)) ** 2))

    assert err(corrected[-1][0]) < err(synth)


def test_a_served_device_in_steady_motion_shows_the_view_warped_ahead_at_once(
        tmp_path, depth_model_path, depth_model):
    """In steady motion the device's warp worker makes the next view ahead; when the user
    gets there (a float32 step off, as the same motion's views are) the device takes that
    view and shows its warp as its first frame of it, no blend first, bit for bit the
    device's own frame of the view."""
    frames: list = []
    device = provisioned_device(tmp_path, mem_name("ahead"), depth_model_path, frames)
    views = [canonical_view(60.0 + 3.0 * i, 20.0) for i in range(4)]

    def shown_warp(view) -> bool:
        return any(i.get("synthesized") and (i.get("phi_deg"), i.get("theta_deg")) == view
                   for _, i in frames)

    with device:
        runtime = device.device
        wait_until(lambda: runtime._model is not None and runtime._model.warp_worker
                   is not None, 60, "the image with depth loaded")
        worker = runtime._model.warp_worker
        for view in views[:3]:
            runtime.set_view(*view)
            wait_until(lambda view=view: shown_warp(view), 60, f"the warp of {view}")
        steady_requests(worker, views[:3])
        wait_until(lambda: worker._ahead is not None, 60, "the next view warped ahead")
        assert worker._ahead[0] == views[3]
        n = len(frames)
        runtime.set_view(views[3][0] + float(np.spacing(np.float32(views[3][0]))), views[3][1])
        assert runtime.view == views[3]  # the view made ahead, not one a float32 step off
        wait_until(lambda: len(frames) > n, 30, "the next frame")
    frame, info = frames[n]
    assert (info["phi_deg"], info["theta_deg"]) == views[3]
    assert info.get("synthesized") and not info.get("corrected")
    np.testing.assert_array_equal(frame, OwnFrames(depth_model.image).frame(*views[3]))
    assert worker.ahead_used == 1


def _fine(encoded, model) -> bool:
    """A resting view's complete correction (not a refinement layer's strip)."""
    return encoded.step is not None and float(encoded.step) == pytest.approx(
        model.score_step, rel=1e-6)


def test_serve_sends_ray_cast_scores_to_a_device_that_does_not_synthesize(
        tmp_path, model_path, model):
    name = mem_name("nopredict")
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", predict=False)
    lines: list[str] = []
    with device:
        provision(model_path, f"mem://{name}?end=a&pace=0",
                  ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
        from device_runtime.orbit import parse_orbit

        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, orbit=parse_orbit("steps:3:10"), fps=0),
                      ServeParts(log=lines.append))
    notices = [ln for ln in lines if "instead of corrections" in ln]
    assert len(notices) == 1 and "does not synthesize" in notices[0]
    assert stats.frames == 3 and stats.correction_frames == 0 and stats.motion_frames == 3


def _orbit_session(tmp_path, model_path, tag: str, orbit: str, log, then=None):
    """Provision a predicting device over a ``mem://`` line and serve it ``orbit``; run
    ``then(device)`` before the device stops. Returns serve's statistics and the device."""
    from device_runtime.orbit import parse_orbit

    name = mem_name(tag)
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", predict=True)
    with device:
        provision(model_path, f"mem://{name}?end=a&pace=0",
                  ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, orbit=parse_orbit(orbit), fps=0), ServeParts(log=log))
        if then is not None:
            then(device)
    return stats, device


def test_an_older_device_gets_ray_cast_scores(tmp_path, model_path, monkeypatch):
    """A device that reads packets up to version 2 (the previous release) is never sent a
    version-3 packet: it gets today's full frames, and one line says why."""
    import device_runtime.runtime as runtime

    monkeypatch.setattr(runtime, "VERSIONS", (1, 2))
    lines: list[str] = []
    stats, device = _orbit_session(tmp_path, model_path, "old", "steps:3:10", lines.append)
    assert any("older eigencast-device" in ln for ln in lines), lines
    assert stats.correction_frames == 0 and stats.frames == 3
    assert device.device.runtime_stats.decode_errors == 0


def test_an_orbit_to_a_device_that_synthesizes_moves_its_view_with_corrections(
        tmp_path, model_path, model):
    def last_view_shown(device: RuntimeThread) -> None:
        wait_until(lambda: device.device.view == canonical_view(270.0, 10.0), 20,
                   "the orbit's last view on the device")

    stats, _ = _orbit_session(tmp_path, model_path, "orbit3", "steps:4:10", _quiet,
                              then=last_view_shown)
    assert stats.frames == 4 and stats.correction_frames == 4 and stats.unchanged_frames == 0


def test_a_model_without_the_table_serves_ray_cast_scores(tmp_path, plain_model):
    assert not can_correct(HostModel.load(plain_model))
    lines: list[str] = []
    stats, _ = _orbit_session(tmp_path, plain_model, "plain", "steps:2:10", lines.append)
    assert any("fitted --no-standalone" in ln for ln in lines), lines
    assert stats.motion_frames == 2 and stats.correction_frames == 0


# --------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def plain_model(model_path, tmp_path_factory):
    """The tiny tooth fitted without the standalone table (--no-standalone)."""
    out = tmp_path_factory.mktemp("plain") / "plain.ecs"
    db = model_path.parent / "tooth.cdb"
    key = model_path.parent / "device.key"
    assert eigencast(["fit", str(db), "-o", str(out), "--cell", "12", "--threshold",
                      "0.99", "--no-standalone", "--key", str(key)]) == 0
    return out


def test_cli_has_one_path_and_no_score_modes(model_path):
    result = serve_cli(str(model_path), "--port", "mem://nobody?end=a", "--scores", "predict")
    assert result.returncode != 0 and "--scores" in result.stderr
    assert "Traceback" not in result.stderr


def test_a_device_image_without_depth_or_table_still_loads(model_path):
    image = read_image(model_path, key=KEY)
    bare = dataclasses.replace(image, sections={
        k: v for k, v in image.sections.items() if not k.startswith("standalone")})
    built = LoadedModel.build(bare, slot="A", generation=1, test=False, want_predictor=True)
    try:
        assert built.predictor is None and built.warp_worker is None
    finally:
        built.close()
    assert isinstance(Predictor(image), Predictor)


# --------------------------------------------------------------------------- image swaps


@pytest.fixture(scope="module")
def second_depth_model_path(depth_model_path):
    """Another image of the same database (another threshold: another eigenspace, another
    digest), signed with the same key."""
    root = depth_model_path.parent
    out = root / "tooth-b.ecs"
    assert eigencast(["fit", str(root / "tooth.cdb"), "-o", str(out), "--cell", "12",
                      "--threshold", "0.95", "--key", str(root / "device.key")]) == 0
    return out


def _serve_until_rest(url: str, image_path, target, frames: list) -> list:
    """Serve ``image_path`` to the device on ``url`` until the complete correction of
    ``target`` is shown; the (packet, view) pairs the host sent."""
    model = HostModel.load(image_path)
    sent: list = []
    stop = threading.Event()
    parts = ServeParts(stop=stop, log=_quiet, on_frame=lambda enc, view: sent.append((enc, view)))
    thread = threading.Thread(target=lambda: serve(image_path, url,
                                                   ServeOptions(key=KEY, rest="correction"), parts),
                              daemon=True)
    thread.start()
    try:
        wait_until(lambda: any(v == target and _fine(e, model) for e, v in sent), 60,
                   "the complete correction at rest")
        last = [e for e, v in sent if v == target][-1].frame
        wait_until(lambda: any(i.get("frame") == last and i.get("corrected")
                               for _, i in frames[-3:]), 30, "it shown")
    finally:
        stop.set()
        thread.join(20)
    return sent


def test_a_live_image_swap_at_rest_shows_the_new_images_corrected_frame(
        tmp_path, depth_model_path, second_depth_model_path):
    """Serve image A to a device resting on a view, provision image B, serve B: the device's
    frame at rest is B's own frame of the view corrected by B's packets, bit for bit what the
    host believes is on screen (a swap that kept A's warp or A's frame in the reconstructor
    dropped every correction, or corrected A's frame with B's scores)."""
    name = mem_name("swap")
    frames: list = []
    device = provisioned_device(tmp_path, name, depth_model_path, frames)
    target = canonical_view(47.0, 23.0)
    url = f"mem://{name}?end=a"
    with device:
        device.device.set_view(*target)
        _serve_until_rest(url, depth_model_path, target, frames)
        dropped = device.device.runtime_stats.stale_dropped
        provision(second_depth_model_path, url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=_quiet))
        wait_until(lambda: device.device._model is not None
                   and device.device._model.image.digest == read_image(
                       second_depth_model_path, key=KEY).digest, 30, "image B on show")
        swapped = len(frames)
        sent = _serve_until_rest(url, second_depth_model_path, target, frames)
        assert device.device.view == target  # the device rested on the view throughout
    b = HostModel.load(second_depth_model_path)
    own = OwnFrames(b.image)
    decoder = _decoder(b)
    by_frame = {e.frame: decoder.decode(e.packet).y for e, v in sent if v == target}
    corrected = [(f, i) for f, i in frames[swapped:] if i.get("corrected")]
    assert corrected and device.device.runtime_stats.stale_dropped == dropped
    for f, i in corrected:
        np.testing.assert_array_equal(f, own.corrected(own.frame(*target), by_frame[i["frame"]]))


def _reachable(root, depth: int = 3) -> list:
    """The objects reachable from ``root``'s attributes within ``depth`` steps (containers
    and dataclasses followed; arrays, images and threads are leaves)."""
    seen, out, todo = set(), [], [(v, 0) for v in vars(root).values()]
    while todo:
        obj, d = todo.pop()
        if id(obj) in seen or obj is None or isinstance(obj, (int, float, str, bytes, bool)):
            continue
        seen.add(id(obj))
        out.append(obj)
        if d >= depth or isinstance(obj, np.ndarray):
            continue
        if isinstance(obj, dict):
            todo += [(v, d + 1) for v in obj.values()]
        elif isinstance(obj, (list, tuple, set, frozenset)) or type(obj).__name__ == "deque":
            todo += [(v, d + 1) for v in obj]
        elif dataclasses.is_dataclass(obj):
            todo += [(getattr(obj, f.name), d + 1) for f in dataclasses.fields(obj)]
    return out


@pytest.mark.parametrize("state", ["resting", "moving", "warping ahead", "correcting"])
def test_an_image_swap_in_any_display_state_keeps_nothing_of_the_old_image(
        tmp_path, depth_model_path, second_depth_model_path, state):
    """Whatever the display was doing with image A (resting on a corrected warp, moving with
    a blend on show and its warp due, a view warped ahead, a correction waiting for its
    warp), activating image B replaces all of it: nothing of A is reachable from the device,
    A's worker is stopped, and B's first frame is B's own frame of the view."""
    image_a = read_image(depth_model_path, key=KEY)
    image_b = read_image(second_depth_model_path, key=KEY)
    shown: list = []
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY), predict=True,
                           view=(47.0, 23.0), log=_quiet,
                           on_frame=lambda f, info: shown.append((f.copy(), dict(info))))
    a = LoadedModel.build(image_a, slot="A", generation=1, test=False, want_predictor=True)
    b = LoadedModel.build(image_b, slot="B", generation=2, test=False, want_predictor=True)
    try:
        device._swap_model(a)
        view = device.view
        model_a = HostModel.load(depth_model_path)
        delta = np.random.default_rng(5).normal(0, 3 * model_a.score_step,
                                                image_a.n_coefficients)
        decoded = _decoder(model_a).decode(
            CorrectionEncoder(model_a).encode(view, scores=delta, fine=True).packet)
        item = ScoreItem(a, decoded, 1, 0.0)
        if state == "resting":  # the warp, then its correction
            device._show_due_warp(a, timeout_s=30)
            device._show_item(item)
            assert shown[-1][1].get("corrected")
        elif state == "moving":  # a new view's blend on show, its warp due
            device.set_view(120.0, -10.0)
            device._view_dirty = False
            device._show_view(a, time.monotonic())
            assert a.shown.warp_due == device.view
        elif state == "warping ahead":
            views = [canonical_view(60.0 + 3.0 * i, 20.0) for i in range(3)]
            for v in views:
                a.warp_worker.request(v)
                assert a.warp_worker.take(v, timeout_s=30) is not None
            steady_requests(a.warp_worker, views)
            wait_until(lambda: a.warp_worker._ahead is not None, 30, "a view warped ahead")
        else:  # a correction that came before its warp
            device.set_view(200.0, 5.0)
            device._view_dirty = False
            device._show_view(a, time.monotonic())
            moved = device.view
            item = ScoreItem(a, dataclasses.replace(decoded, phi_deg=moved[0],
                                                    theta_deg=moved[1]), 2, 0.0)
            a.shown.own_warp = None
            device._correct(item)
            assert a.shown.correction_due is item
        old = {id(x) for x in (a, a.shown, a.reconstructor, a.warp_worker, a.synthesis,
                               a.decoder, *(f for f, _ in shown))}
        # (views are plain tuples of floats, the same values whatever the image)
        kept = [getattr(a.shown, f.name) for f in dataclasses.fields(a.shown)]
        old |= {id(x) for x in kept if x is not None and not isinstance(x, tuple)}
        if a.shown.own_warp is not None:
            old.add(id(a.shown.own_warp[1]))
        device._swap_model(b)
        assert not a.warp_worker._thread.is_alive()
        leaked = [type(x).__name__ for x in _reachable(device) if id(x) in old]
        assert not leaked, leaked
        np.testing.assert_array_equal(shown[-1][0], Reconstructor.from_image(image_b).update(
            b.own_scores(device.view)))  # B's own frame: its blend, then its warp
        device._show_due_warp(b, timeout_s=30)
        np.testing.assert_array_equal(shown[-1][0], OwnFrames(image_b).frame(*device.view))
    finally:
        device.close()
        a.close()
        b.close()
