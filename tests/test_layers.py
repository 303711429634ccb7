"""Refinement layers: the version-4 packet (protocol/layers.py) and the device's side
(device_runtime/layers.py): decode through pygame, apply to the resting frame in order,
refuse what is bad in one counted drop."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from device_runtime.layers import LayerError, RestFrame, decode_strip
from protocol.errors import LimitExceeded
from protocol.layers import (
    CODEC_JPEG,
    CODEC_PNG,
    CODEC_WEBP,
    LAYER_HEADER_SIZE,
    declared_size,
    decode_layer,
    encode_layer,
    is_layer,
)
from protocol.scores import ImageMismatch, ScoreDecoder, ScorePacketError

GOLDEN = Path(__file__).parent / "golden" / "layer_packets.jsonl"
DIGEST = bytes(range(32))
SHAPE = (24, 40)  # (height, width)


def _file(pixels: np.ndarray, codec: str, **kwargs) -> bytes:
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, codec, **kwargs)
    return out.getvalue()


def _pixels(rows: int, width: int = SHAPE[1], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.linspace(0, 255, width, dtype=np.float32)[None, :, None]
    img = base + rng.normal(0, 12, (rows, width, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _packet(data: bytes, *, codec=CODEC_PNG, y0=0, rows=8, **kwargs) -> bytes:
    fields = {"frame": 11, "base_frame": 10, "view": (30.0, 15.0), "image_digest": DIGEST,
              "layer": 0, "y0": y0, "rows": rows} | kwargs
    return encode_layer(data, codec=codec, **fields)


def _decode(packet: bytes, **kwargs):
    return decode_layer(packet, image_digest=DIGEST, image_shape=SHAPE,
                        max_packet_bytes=kwargs.pop("max_packet_bytes", 1 << 20), **kwargs)


@pytest.mark.parametrize("codec,fmt,kwargs", [
    (CODEC_PNG, "PNG", {}), (CODEC_JPEG, "JPEG", {"quality": 90}),
    (CODEC_WEBP, "WEBP", {"quality": 80}), (CODEC_WEBP, "WEBP", {"lossless": True}),
])
def test_a_layer_round_trips_and_its_file_decodes_through_pygame(codec, fmt, kwargs):
    pixels = _pixels(8)
    data = _file(pixels, fmt, **kwargs)
    assert declared_size(data, codec) == (SHAPE[1], 8)
    packet = _packet(data, codec=codec, y0=16, rows=8, residual=codec != CODEC_PNG, shift=1
                     if codec == CODEC_JPEG else 0, layer=2)
    assert is_layer(packet) and packet[2] == 4
    layer = _decode(packet)
    assert (layer.frame, layer.base_frame, layer.layer, layer.y0, layer.rows) == (11, 10, 2, 16,
                                                                                  8)
    assert (layer.phi_deg, layer.theta_deg, layer.codec, layer.data) == (30.0, 15.0, codec,
                                                                         data)
    decoded = decode_strip(layer, SHAPE[1])
    want = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    if fmt == "PNG" or kwargs.get("lossless"):
        np.testing.assert_array_equal(decoded, pixels)  # lossless: the pixels exactly
    assert np.abs(decoded.astype(int) - want).max() <= 2  # pygame decodes as Pillow does


def test_bad_layers_are_refused_before_their_file_is_decoded():
    data = _file(_pixels(8), "PNG")
    good = _packet(data)
    with pytest.raises(LimitExceeded):
        _decode(good, max_packet_bytes=len(good) - 1)
    with pytest.raises(ImageMismatch):
        decode_layer(good, image_digest=bytes(32), image_shape=SHAPE, max_packet_bytes=1 << 20)
    for bad, what in [
        (good[:LAYER_HEADER_SIZE], "shorter"),  # truncated: no file
        (good[:3] + bytes([0x10]) + good[4:], "reserved"),  # reserved flag bit
        (good[:21] + bytes([9]) + good[22:], "codec"),  # unknown codec
        (_packet(data, y0=20, rows=8), "outside"),  # strip beyond the image
        (_packet(data, rows=9), "declares"),  # the file is 8 rows, the strip 9
        (_packet(_file(_pixels(8, 41), "PNG")), "declares"),  # another width
        (_packet(data[:20]), "header"),  # a truncated file header
        (_packet(b"GIF89a" + data[6:]), "header"),  # not a PNG
        (_packet(_file(_pixels(8), "WEBP"), codec=CODEC_PNG), "header"),
    ]:
        with pytest.raises(ScorePacketError, match=what):
            _decode(bad)
    with pytest.raises(ValueError, match="EXACT"):
        _packet(data, residual=True, exact=True)
    with pytest.raises(ValueError, match="shift"):
        _packet(data, shift=1)
    # an older decoder refuses a layer in one line
    with pytest.raises(ScorePacketError, match="unsupported packet version 4"):
        ScoreDecoder(6, DIGEST, max_packet_bytes=1 << 16).decode(good)


def test_a_file_that_lies_about_its_size_is_not_shown():
    """A PNG whose header says the strip's size but whose data is another image's."""
    small = _file(_pixels(4), "PNG")
    lying = bytearray(small)
    lying[16:24] = (SHAPE[1]).to_bytes(4, "big") + (8).to_bytes(4, "big")
    layer = _decode(_packet(bytes(lying)))
    with pytest.raises(LayerError):
        decode_strip(layer, SHAPE[1])


def test_the_rest_frame_applies_layers_in_order_and_ends_exact():
    truth = _pixels(SHAPE[0], seed=1)
    own = np.clip(truth.astype(int) + 9, 0, 255).astype(np.uint8)
    rest = RestFrame((30.0, 15.0), 10, own)
    residual = np.clip((truth.astype(int) - own) // 2 + 128, 0, 255).astype(np.uint8)

    def layer(pixels, y0, rows, **kwargs):
        fmt = kwargs.pop("fmt", "PNG")
        return _decode(_packet(_file(pixels[y0:y0 + rows], fmt), y0=y0, rows=rows, **kwargs))

    top = layer(residual, 0, 8, residual=True, shift=1, layer=0)
    assert rest.accepts(top)
    rest.apply(top, decode_strip(top, SHAPE[1]))
    assert np.abs(rest.frame[:8].astype(int) - truth[:8]).max() <= 1
    # a residual of layer 1 needs layer 0 on every row of its strip: rows 8.. have none
    skip = layer(residual, 8, 8, residual=True, layer=1)
    assert not rest.accepts(skip)
    # an absolute exact strip applies over any earlier layers and makes its rows exact
    for y0 in (0, 8, 16):
        exact = layer(truth, y0, 8, layer=1, exact=True)
        assert rest.accepts(exact) and not rest.is_exact
        rest.apply(exact, decode_strip(exact, SHAPE[1]))
    assert rest.is_exact
    np.testing.assert_array_equal(rest.frame, truth)
    # an older layer (0) no longer applies anywhere
    assert not rest.accepts(layer(truth, 0, 8, layer=0))
    assert own is not rest.frame  # the device's copy, not the frame it was made from


def test_layer_golden_vectors_both_directions():
    cases = [json.loads(line) for line in GOLDEN.read_text().splitlines()]
    assert {c["name"] for c in cases} >= {"absolute_png", "residual_webp", "exact_png"}
    for case in cases:
        data = bytes.fromhex(case["file"])
        packet = encode_layer(data, image_digest=bytes.fromhex(case["digest"]),
                              view=tuple(case["view"]), **case["fields"])
        assert packet.hex() == case["hex"], case["name"]
        layer = decode_layer(bytes.fromhex(case["hex"]),
                             image_digest=bytes.fromhex(case["digest"]),
                             image_shape=tuple(case["image_shape"]), max_packet_bytes=4096)
        for name, value in case["fields"].items():
            assert getattr(layer, name) == value, (case["name"], name)
        assert layer.data == data


def _regenerate() -> None:
    """Write tests/golden/layer_packets.jsonl (tiny fixed files, fixed fields)."""
    digest = bytes(range(100, 132))
    strip = np.arange(2 * 4 * 3, dtype=np.uint8).reshape(2, 4, 3) * 10
    png = _file(strip, "PNG")
    webp = _file(strip, "WEBP", lossless=True)
    cases = [
        ("absolute_png", png, dict(codec=CODEC_PNG, frame=1000, base_frame=999, layer=0, y0=0,
                                   rows=2)),
        ("residual_webp", webp, dict(codec=CODEC_WEBP, frame=1001, base_frame=999, layer=1,
                                     y0=2, rows=2, residual=True, shift=1)),
        ("exact_png", png, dict(codec=CODEC_PNG, frame=1002, base_frame=0, layer=2, y0=4,
                                rows=2, exact=True)),
    ]
    lines = []
    for name, data, fields in cases:
        packet = encode_layer(data, image_digest=digest, view=(12.5, -30.0), **fields)
        lines.append(json.dumps({"name": name, "digest": digest.hex(), "view": [12.5, -30.0],
                                 "image_shape": [6, 4], "fields": fields, "file": data.hex(),
                                 "hex": packet.hex()}))
    GOLDEN.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--regenerate"]:
        sys.exit("usage: python tests/test_layers.py --regenerate")
    _regenerate()


# --------------------------------------------------------------------------- on a device


@pytest.fixture(scope="module")
def resting_device(tmp_path_factory):
    """A predicting RuntimeDevice (no link) resting on a view of the tiny depth model, its
    own warp on show; and the truth a layer would bring."""
    from provision_helpers import KEY
    from runtime_helpers import tiny_model

    from device_runtime.device import DeviceConfig
    from device_runtime.runtime import LoadedModel, RuntimeDevice
    from protocol.image import read_image

    image = read_image(tiny_model(tmp_path_factory, name="tiny-depth", depth=True), key=KEY)
    shown: list = []
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path_factory.mktemp("flash"), key=KEY),
                           predict=True, view=(40.0, 10.0), log=lambda _: None,
                           on_frame=lambda f, info: shown.append((f.copy(), dict(info))))
    model = LoadedModel.build(image, slot="A", generation=1, test=False, want_predictor=True)
    device._decoder_model = model  # (what activation does: the dispatcher decodes with it)
    device._swap_model(model)
    device._show_due_warp(model, timeout_s=30)
    assert shown[-1][1].get("synthesized")
    yield device, model, shown, image
    device.close()
    model.close()


def _layer_for(device, image, pixels, **kwargs) -> bytes:
    h = image.image_shape[0]
    fields = {"frame": 5, "base_frame": 0, "view": device.view, "image_digest": image.digest,
              "layer": 0, "y0": 0, "rows": h} | kwargs
    return encode_layer(_file(pixels, "PNG"), codec=CODEC_PNG, **fields)


def test_a_device_drops_every_bad_layer_and_shows_a_good_one_exactly(resting_device):
    """Mutated, truncated, oversized and misdirected layers reach a resting device: none is
    shown, none stops it; each is counted; then a good exact layer makes the frame on show
    exactly its pixels, and a later host frame of the view does not replace it."""
    from protocol import messages as m

    device, _, shown, image = resting_device
    h, w = image.image_shape
    rng = np.random.default_rng(7)
    truth = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    good = _layer_for(device, image, truth, exact=True)
    bad = [good[:n] for n in (3, 20, LAYER_HEADER_SIZE, LAYER_HEADER_SIZE + 30)]
    for _ in range(60):  # random byte flips anywhere
        packet = bytearray(good)
        for _ in range(rng.integers(1, 5)):
            packet[rng.integers(0, len(packet))] = rng.integers(0, 256)
        bad.append(bytes(packet))
    huge = bytearray(good)  # a PNG that declares 60000 x 60000 pixels (an image bomb)
    huge[LAYER_HEADER_SIZE + 16:LAYER_HEADER_SIZE + 24] = (60000).to_bytes(4, "big") * 2
    bad += [bytes(huge),
            _layer_for(device, image, truth, view=(device.view[0] + 5, device.view[1])),
            _layer_for(device, image, truth, base_frame=12345, residual=True),
            _layer_for(device, image, truth[: h // 2], rows=h // 2, y0=h // 2 + 1),
            _layer_for(device, image, truth, image_digest=bytes(32))]
    frames_before = len(shown)
    on_show = device._shown_frame.copy()
    for packet in bad:
        device.on_scores(m.Scores(sequence=0, packet=packet))
        while device._layers:
            device.display_turn(None)
    stats = device.runtime_stats
    assert stats.exact_frames == 0
    for _, info in shown[frames_before:]:  # whatever a flipped pixel byte made, it is
        assert info.get("layer") is not None and not info.get("exact")  # never "exact"
    np.testing.assert_array_equal(on_show if len(shown) == frames_before else shown[-1][0],
                                  device._shown_frame)
    # each one a layer accounted for, or (its magic or version flipped) a bad score packet
    assert stats.layer_packets + stats.decode_errors == len(bad)
    assert (stats.layers_bad + stats.layers_dropped + stats.wrong_image
            + stats.layers_applied) == stats.layer_packets
    device.on_scores(m.Scores(sequence=0, packet=good))
    device.display_turn(None)
    assert shown[-1][1].get("exact") and stats.exact_frames == 1
    np.testing.assert_array_equal(shown[-1][0], truth)
    np.testing.assert_array_equal(device._shown_frame, truth)
