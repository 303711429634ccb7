"""The device predicts, the host corrects (issue 14): ``serve --scores predict``.

A device whose image holds the standalone table shows its own prediction of a new view at
once; the host sends a version-2 score packet that corrects that prediction towards the
projection of a fresh ray-cast. These tests check the shared prediction bit for bit, the
wire (version, base kind, view), a real paced session, staleness, the fallbacks and the CLI.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from provision_helpers import KEY, mem_name
from runtime_helpers import RuntimeThread, serve_cli, wait_until

from device_runtime.prediction import Predictor, corrected, prediction_view
from device_runtime.runtime import LoadedModel, RuntimeDevice, ScoreItem
from host.cli import main as eigencast
from host.link.correction import (
    CorrectedViews,
    CorrectionEncoder,
    cannot_predict,
    model_predictor,
    predict_encoder,
)
from host.link.errors import ServeError
from host.link.provisioning import provision
from host.link.serving import serve
from protocol import messages as m
from protocol.image import read_image
from protocol.scores import (
    HEADER_SIZE,
    ScoreDecoder,
    ScorePacketError,
    decode_header,
    encode_scores,
)

VIEWS = [(0.0, 0.0), (11.0, 13.0), (200.0, -40.0), (97.5, 51.0), (359.9, 89.0),
         (45.0, -90.0), (123.456, 7.891)]


def _quiet(line: str) -> None:
    pass


@pytest.fixture(scope="module")
def device_image(model_path):
    """The image exactly as a device reads it (no host annex)."""
    return read_image(model_path, key=KEY)


@pytest.fixture(scope="module")
def corrector(model):
    views, encoder = predict_encoder(model, None)
    return views, encoder


def _decoder(model, **kwargs) -> ScoreDecoder:
    return ScoreDecoder(model.image.n_coefficients, model.digest,
                        n_components=model.image.n_components, **kwargs)


# --------------------------------------------------------------------------- prediction


def test_host_and_device_predictions_are_bit_identical(model, device_image):
    host = model_predictor(model)
    device = LoadedModel.build(device_image, slot="A", generation=1, test=False,
                               want_predictor=True).predictor
    assert host is not None and device is not None
    for view in VIEWS:
        a, b = host(*view), device(*view)
        assert a.dtype == np.float32 and np.array_equal(a, b), view
        # and it is what the host has always served (interpolate) at that canonical view
        np.testing.assert_array_equal(a, model.quantized_scores(*prediction_view(*view)))


def test_a_device_without_the_table_or_asked_not_to_predicts_nothing(model, device_image):
    image = read_image_without_table(device_image)
    built = LoadedModel.build(image, slot="A", generation=1, test=False, want_predictor=True)
    assert built.predictor is None
    off = LoadedModel.build(device_image, slot="A", generation=1, test=False)
    assert off.predictor is None


def read_image_without_table(image):
    import dataclasses

    return dataclasses.replace(image, sections={
        k: v for k, v in image.sections.items() if not k.startswith("standalone")})


# --------------------------------------------------------------------------- wire


def test_correction_packets_are_version_2_and_decode_to_prediction_plus_correction(
        model, corrector):
    views, encoder = corrector
    decoder = _decoder(model)
    view = (33.0, 21.0)
    y = views(view)
    packet = encoder.encode(view, scores=y)
    assert encoder.last_kind == "correction"
    header = decode_header(packet.packet)
    assert header.version == 2 and header.is_predicted and not header.is_delta
    assert (header.phi_deg, header.theta_deg) == view
    d = decoder.decode(packet.packet)
    assert d.predicted and d.frame not in decoder.base_frames  # never a delta base
    shown = corrected(Predictor(model.image)(*view), d.y)
    np.testing.assert_array_equal(shown, encoder.shown(packet, view))
    # the correction moves the prediction towards the projection, within the step
    pred = model_predictor(model)(*view)
    assert np.abs(shown - y).max() < np.abs(pred - y).max()
    assert np.abs(shown - y).max() <= np.abs(pred - y).max() + encoder.step / 2


def test_other_packets_stay_version_1(model):
    enc = encode_scores(np.zeros(model.image.n_coefficients), step=1.0, frame=1,
                        view=(1.0, 2.0), image_digest=model.digest)
    assert enc.packet[2] == 1


def test_old_device_refuses_a_correction_in_one_line(model, corrector):
    views, encoder = corrector
    view = (60.0, -10.0)
    packet = encoder.encode(view, scores=views(view)).packet
    old = _decoder(model, versions=(1,))
    with pytest.raises(ScorePacketError) as info:
        old.decode(packet)
    assert "unsupported packet version 2 (supported: 1)" in str(info.value)
    assert "\n" not in str(info.value)


def test_new_device_reads_version_1_packets():
    """Every golden (version-1) packet still decodes with today's decoder."""
    path = Path(__file__).parent / "golden" / "score_packets.jsonl"
    n = 0
    for line in path.read_text().splitlines():
        case = json.loads(line)
        packet = bytes.fromhex(case["hex"])
        assert packet[2] == 1
        header = decode_header(packet)
        assert header.version == 1 and not header.is_predicted
        n += 1
    assert n > 0


def test_bad_base_kinds_and_views_are_refused(model, corrector):
    views, encoder = corrector
    view = (80.0, 5.0)
    good = bytearray(encoder.encode(view, scores=views(view)).packet)
    assert good[2] == 2
    both = bytearray(good)
    both[3] |= 0x01  # DELTA and PREDICTED
    bit7 = bytearray(good)
    bit7[3] |= 0x80
    v1 = bytearray(good)
    v1[2] = 1  # PREDICTED is a reserved bit in version 1
    for bad, match in [(both, "not both"), (bit7, "reserved bits 7"),
                       (v1, "reserved bits 6-7")]:
        with pytest.raises(ScorePacketError, match=match):
            _decoder(model).decode(bytes(bad))
    import struct

    for phi, theta in [(float("nan"), 0.0), (0.0, float("inf")), (720.0, 0.0),
                       (-1.0, 0.0), (10.0, 91.0), (3e38, 0.0)]:
        bad = bytearray(good)
        struct.pack_into("<ff", bad, 12, phi, theta)
        with pytest.raises(ScorePacketError):
            _decoder(model).decode(bytes(bad))
    assert len(good) > HEADER_SIZE


def test_full_frame_is_sent_when_smaller_than_the_correction(model, corrector):
    """A prediction that is far off makes the correction large: the encoder then sends the
    RD-quantized full frame instead (a key frame, then deltas against it), and a predicting
    device decodes both kinds."""
    views, _ = corrector
    rng = np.random.default_rng(0)

    class FarOff:
        def __call__(self, phi, theta):
            noise = rng.normal(0.0, 40.0 * model.score_step, model.image.n_coefficients)
            return (model.quantized_scores(phi, theta) + noise).astype(np.float32)

    encoder = CorrectionEncoder(model, FarOff(), views=views)
    decoder = _decoder(model)
    kinds = []
    for view in [(10.0, 10.0), (12.0, 10.0)]:
        d = decoder.decode(encoder.encode(view, scores=views(view)).packet)
        kinds.append(encoder.last_kind)
        assert not d.predicted
    assert kinds == ["key", "delta"]
    encoder.reset()  # a new session starts with a key frame again
    encoder.encode((14.0, 10.0), scores=views((14.0, 10.0)))
    assert encoder.last_kind == "key"


# --------------------------------------------------------------------------- device


def _device(tmp_path, **kwargs) -> RuntimeDevice:
    from device_runtime.device import DeviceConfig

    return RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY), predict=True,
                         log=_quiet, **kwargs)


def test_stale_corrections_are_dropped_and_current_ones_shown(tmp_path, model, device_image,
                                                             corrector):
    views, encoder = corrector
    device = _device(tmp_path)
    try:
        loaded = LoadedModel.build(device_image, slot="A", generation=1, test=False,
                                   want_predictor=True)
        decoder = loaded.decoder
        old, new = (20.0, 10.0), (40.0, 10.0)
        packet = encoder.encode(old, scores=views(old)).packet
        item = ScoreItem(loaded, decoder.decode(packet), sequence=3, received_s=0.0)
        device.view = new  # the user moved on
        assert device._shown_scores(item) is None
        assert device.runtime_stats.stale_dropped == 1
        device.view = old  # still on show: prediction + correction
        y = device._shown_scores(item)
        np.testing.assert_array_equal(y, corrected(loaded.predictor(*old), item.scores.y))
        assert device.runtime_stats.corrected_frames == 1
        device.view = new  # host-driven (sequence 0): shown whatever the view
        host_driven = ScoreItem(loaded, item.scores, sequence=0, received_s=0.0)
        assert device._shown_scores(host_driven) is not None
    finally:
        device.close()


def test_hello_says_whether_the_device_predicts(tmp_path, model_path):
    """HELLO_REPLY lists packet versions; a keyed device says ``predicts`` only in
    AUTH_RESPONSE, which the host session merges."""
    from protocol.host_session import HostSession
    from protocol.link import Link
    from protocol.transport import open_transport

    name = mem_name("hello")
    for predict in (True, False):
        url = f"mem://{name}{predict}?end=%s&pace=0"
        device = RuntimeThread(tmp_path / f"flash-{predict}", url % "b", predict=predict)
        with device:
            provision(model_path, url % "a", key=KEY, show_progress=False, log=_quiet)
            wait_until(lambda d=device: d.device._model is not None, 10, "the image loaded")
            assert device.device.predicts is predict
            bare = device.device.handle_hello(m.Hello(min_version=2, max_version=2,
                                                      nonce=bytes(16)), None)
            assert bare.score_versions == (1, 2) and bare.predicts is None  # keyed: hidden
            link = Link(open_transport(url % "a", timeout_s=5), owns_transport=True).start()
            try:
                session = HostSession(link, key=KEY)
                hello = session.start()
                session.bye("done")
            finally:
                link.close(flush_timeout_s=0.5)
            assert hello.predicts is predict
            assert (cannot_predict(hello) is None) is predict


def test_cannot_predict_reads_an_old_device_as_version_1():
    base = dict(min_version=2, max_version=2, device_id="d", nonce=bytes(16),
                max_frame_bytes=4096, ram_budget_bytes=0, slot_size_bytes=0, display_width=0,
                display_height=0, rx_window_frames=1, rx_buffer_bytes=1, slots=(),
                has_key=False)
    assert "older device" in cannot_predict(m.HelloReply(**base))
    assert "does not predict" in cannot_predict(m.HelloReply(**base, score_versions=(1, 2)))
    assert cannot_predict(m.HelloReply(**base, score_versions=(1, 2), predicts=True)) is None


# --------------------------------------------------------------------------- session


def _provisioned(tmp_path, model_path, name, **kwargs):
    frames: list = []
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b", predict=True,
                           on_frame=lambda f, info: frames.append((f.copy(), dict(info or {}))),
                           **kwargs)
    provision(model_path, f"mem://{name}?end=a", key=KEY, show_progress=False, log=_quiet)
    return device, frames


def test_served_session_shows_the_prediction_at_once_then_the_corrected_frame(
        tmp_path, model_path, model):
    """A real session over a paced 115200-baud mem:// line: a new view is shown predicted
    before any packet for it has arrived, then corrected to the host's frame."""
    name = mem_name("predict")
    device, frames = _provisioned(tmp_path, model_path, name)
    packets: list[tuple[tuple[float, float], int]] = []  # (view, frames shown) on arrival
    original = device.device.on_scores

    def on_scores(msg):
        header = decode_header(msg.packet)
        packets.append(((header.phi_deg, header.theta_deg), len(frames)))
        original(msg)

    device.device.on_scores = on_scores
    sent: list = []
    stop = threading.Event()
    result: dict = {}
    lines: list[str] = []

    def host():
        result["stats"] = serve(model_path, f"mem://{name}?end=a", key=KEY, scores="predict",
                                stop=stop, log=lines.append,
                                on_frame=lambda enc, view: sent.append((enc, view)))

    thread = threading.Thread(target=host, daemon=True)
    target = (47.0, 23.0)
    with device:
        thread.start()
        try:
            wait_until(lambda: device.device.runtime_stats.corrected_frames >= 1, 30,
                       "the first correction")
            device.device.set_view(*target)
            wait_until(lambda: any(i.get("corrected") and (i["phi_deg"], i["theta_deg"])
                                   == target for _, i in frames), 30, "the corrected target")
            # at rest, the correction again at the model's own step (sharpen_at_rest)
            wait_until(lambda: any(v == target and _fine(e, model) for e, v in sent), 30,
                       "the sharpened target at rest")
            wait_until(lambda: sum((i.get("phi_deg"), i.get("theta_deg")) == target
                                   for _, i in frames) >= 3, 30, "the sharp frame shown")
        finally:
            stop.set()
            thread.join(20)
    stats = result["stats"]
    assert stats.correction_frames >= 2 and not any("instead" in ln for ln in lines)
    at = [k for k, (_, i) in enumerate(frames) if (i.get("phi_deg"), i.get("theta_deg"))
          == target]
    first, last = frames[at[0]], frames[at[-1]]
    assert first[1].get("predicted") is True
    arrived = [n for v, n in packets if v == target]
    assert arrived and at[0] < arrived[0]  # shown before the first packet for it arrived
    pred_frame = model.reconstruct(model_predictor(model)(*target))
    np.testing.assert_array_equal(first[0], pred_frame)
    assert last[1].get("corrected") is True
    enc = [e for e, v in sent if v == target][-1]
    d = _decoder(model).decode(enc.packet)
    want = model.reconstruct(corrected(model_predictor(model)(*target), d.y))
    np.testing.assert_array_equal(last[0], want)  # exactly the host's frame
    projection = model.reconstruct(model.project(
        CorrectedViews(model, model_renderer(model)).renderer.render(*target)[0]))

    def err(a):
        return float(np.mean(np.abs(a.astype(float) - projection.astype(float))))

    assert err(last[0]) < err(first[0])  # the correction moved it towards the projection
    assert err(last[0]) < 6.0  # within the correction's quantization
    steps = [float(e.step) for e, v in sent if v == target]
    assert steps[0] == pytest.approx(2 * model.score_step)  # moving: the coarse correction
    assert [_fine(e, model) for e, v in sent if v == target][1:] == [True]  # at rest, once
    coarse = next(f for f, i in frames if i.get("corrected")
              and (i["phi_deg"], i["theta_deg"]) == target)
    assert err(last[0]) < err(coarse)  # sharper than the coarse correction


def _fine(encoded, model) -> bool:
    """A packet at the model's own score step (`sharpen_at_rest`), not the coarse x2."""
    return float(encoded.step) == pytest.approx(model.score_step, rel=1e-6)


def model_renderer(model):
    from host.link.true_views import open_true_view_scores

    return open_true_view_scores(model).renderer


def test_serve_falls_back_to_motion_for_a_device_that_does_not_predict(
        tmp_path, model_path, model):
    name = mem_name("nopredict")
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b&pace=0", predict=False)
    lines: list[str] = []
    with device:
        provision(model_path, f"mem://{name}?end=a&pace=0", key=KEY, show_progress=False,
                  log=_quiet)
        from device_runtime.orbit import parse_orbit

        stats = serve(model_path, f"mem://{name}?end=a&pace=0", key=KEY, scores="predict",
                      orbit=parse_orbit("steps:3:10"), fps=0, log=lines.append)
    notices = [ln for ln in lines if "instead of corrections" in ln]
    assert len(notices) == 1 and "does not predict" in notices[0]
    assert stats.frames == 3 and stats.correction_frames == 0 and stats.motion_frames == 3
    assert device.device.runtime_stats.corrections_without_table == 0


def test_predict_needs_a_standalone_model(model):
    truncated = model.truncated(model.image.n_components)
    with pytest.raises(ServeError, match="no standalone score table"):
        predict_encoder(truncated, None)


# --------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def plain_model(model_path, tmp_path_factory):
    """The tiny tooth fitted without the standalone table (--no-standalone)."""
    out = tmp_path_factory.mktemp("plain") / "plain.ecs"
    db = Path(model_path).parent / "tooth.cdb"
    assert eigencast(["fit", str(db), "-o", str(out), "--cell", "12", "--threshold",
                      "0.99", "--no-standalone"]) == 0
    return out


def test_cli_predict_without_a_table_is_one_line(plain_model):
    result = serve_cli(str(plain_model), "--port", "mem://nobody?end=a", "--scores", "predict")
    assert result.returncode == 1
    err = result.stderr.strip().splitlines()
    assert len(err) == 1 and "no standalone score table" in err[0], result.stderr
    assert "Traceback" not in result.stderr
