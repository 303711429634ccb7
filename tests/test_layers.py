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

from device_runtime.layers import LayerError, RestFrame, decode_file
from protocol.errors import LimitExceeded
from protocol.layers import (
    CODEC_JPEG,
    CODEC_PNG,
    CODEC_WEBP,
    FIRST_CHUNK_MIN,
    LAYER_HEADER_SIZE,
    LayerAssembly,
    declared_size,
    decode_layer,
    encode_layer,
    is_layer,
    max_file_bytes,
)
from protocol.scores import ImageMismatch, ScoreDecoder, ScorePacketError

GOLDEN = Path(__file__).parent / "golden" / "layer_packets.jsonl"
DIGEST = bytes(range(32))
SHAPE = (24, 40)  # (height, width)


def _file(pixels: np.ndarray, codec: str, **kwargs) -> bytes:
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, codec, **kwargs)
    return out.getvalue()


def _pixels(rows: int = SHAPE[0], width: int = SHAPE[1], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.linspace(0, 255, width, dtype=np.float32)[None, :, None]
    img = base + rng.normal(0, 12, (rows, width, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _packets(data: bytes, *, codec=CODEC_PNG, **kwargs) -> list[bytes]:
    fields = {"frame": 11, "base_frame": 10, "view": (30.0, 15.0), "image_digest": DIGEST,
              "layer": 0} | kwargs
    return encode_layer(data, codec=codec, **fields)


def _decode(packet: bytes, **kwargs):
    return decode_layer(packet, image_digest=DIGEST, image_shape=SHAPE,
                        max_packet_bytes=kwargs.pop("max_packet_bytes", 1 << 20), **kwargs)


def _join(packets: list[bytes]) -> bytes | None:
    assembly, out = LayerAssembly(), None
    for packet in packets:
        out = assembly.add(_decode(packet))
    return out


@pytest.mark.parametrize("codec,fmt,kwargs", [
    (CODEC_PNG, "PNG", {}), (CODEC_JPEG, "JPEG", {"quality": 90}),
    (CODEC_WEBP, "WEBP", {"quality": 80}), (CODEC_WEBP, "WEBP", {"lossless": True}),
])
def test_a_layer_round_trips_and_its_file_decodes_through_pygame(codec, fmt, kwargs):
    pixels = _pixels()
    data = _file(pixels, fmt, **kwargs)
    assert declared_size(data, codec) == (SHAPE[1], SHAPE[0])
    (packet,) = _packets(data, codec=codec, residual=codec != CODEC_PNG,
                         shift=1 if codec == CODEC_JPEG else 0, layer=2)
    assert is_layer(packet) and packet[2] == 4
    chunk = _decode(packet)
    assert (chunk.frame, chunk.base_frame, chunk.layer, chunk.offset, chunk.file_bytes) == (
        11, 10, 2, 0, len(data))
    assert (chunk.phi_deg, chunk.theta_deg, chunk.codec, chunk.data) == (30.0, 15.0, codec, data)
    assert chunk.last and LayerAssembly().add(chunk) == data
    decoded = decode_file(data, codec, SHAPE)
    want = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    if fmt == "PNG" or kwargs.get("lossless"):
        np.testing.assert_array_equal(decoded, pixels)  # lossless: the pixels exactly
    assert np.abs(decoded.astype(int) - want).max() <= 2  # pygame decodes as Pillow does


@pytest.mark.parametrize("mode", ["RGB", "RGBA", "P", "L"])
def test_a_png_decodes_to_its_rgb_pixels_whatever_surface_pygame_makes(mode):
    """pygame loads an RGB PNG as a 24-bit surface, RGBA as 32-bit, palette and grey as
    8-bit: every one must give the same (height, width, 3) pixels, odd widths included."""
    pixels = _pixels(width=SHAPE[1] - 1)
    image = Image.fromarray(pixels)
    if mode == "P":
        image = image.quantize(64)
    elif mode == "L":
        image = image.convert("L")
    elif mode == "RGBA":
        image = image.convert("RGBA")
    data = _file(np.asarray(image), "PNG") if mode != "P" else _png(image)
    decoded = decode_file(data, CODEC_PNG, (SHAPE[0], SHAPE[1] - 1))
    assert decoded.shape == (SHAPE[0], SHAPE[1] - 1, 3) and decoded.flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(decoded, np.asarray(image.convert("RGB")))


def _png(image: Image.Image) -> bytes:
    out = io.BytesIO()
    image.save(out, "PNG")
    return out.getvalue()


def test_a_file_in_chunks_is_joined_in_order_and_only_in_order():
    """One file cut in chunks (numbered on from the first frame): joined it is the file; a
    lost, repeated or reordered chunk, a chunk of another file or a wrong CRC is refused and
    the file dropped."""
    data = _file(_pixels(seed=3), "PNG")
    packets = _packets(data, max_chunk_bytes=FIRST_CHUNK_MIN)
    assert len(packets) == -(-len(data) // FIRST_CHUNK_MIN) > 2
    assert [_decode(p).frame for p in packets] == list(range(11, 11 + len(packets)))
    assert _join(packets) == data
    assert _join(packets[:-1]) is None  # incomplete: nothing yet
    for broken in (packets[:1] + packets[2:], packets[:2] + packets[1:], packets[1:]):
        with pytest.raises(ScorePacketError, match="continues no file"):
            _join(broken)
    other = _packets(_file(_pixels(seed=4), "PNG"), max_chunk_bytes=FIRST_CHUNK_MIN)
    with pytest.raises(ScorePacketError, match="continues no file"):
        _join(packets[:1] + other[1:2])
    bad_crc = [p[:36] + bytes(4) + p[40:] for p in packets]
    with pytest.raises(ScorePacketError, match="CRC"):
        _join(bad_crc)
    # a new first chunk starts over: the earlier file's chunks so far are forgotten
    assert _join(packets[:2] + packets) == data


def test_bad_layers_are_refused_before_their_file_is_decoded():
    data = _file(_pixels(), "PNG")
    (good,) = _packets(data)
    with pytest.raises(LimitExceeded):
        _decode(good, max_packet_bytes=len(good) - 1)
    with pytest.raises(ImageMismatch):
        decode_layer(good, image_digest=bytes(32), image_shape=SHAPE, max_packet_bytes=1 << 20)
    huge = good[:28] + (max_file_bytes(SHAPE) + 1).to_bytes(4, "little") + good[32:]
    with pytest.raises(LimitExceeded, match="file of"):
        _decode(huge)
    for bad, what in [
        (good[:LAYER_HEADER_SIZE], "shorter"),  # truncated: no chunk
        (good[:3] + bytes([0x20]) + good[4:], "reserved"),  # reserved flag bit
        (good[:21] + bytes([9]) + good[22:], "codec"),  # unknown codec
        (good[:32] + (len(data) - 5).to_bytes(4, "little") + good[36:], "outside"),
        (_packets(_file(_pixels(rows=23), "PNG"))[0], "declares"),  # another height
        (_packets(_file(_pixels(width=41), "PNG"))[0], "declares"),  # another width
        (good[:LAYER_HEADER_SIZE + 20], "first chunk"),  # a first chunk without the header
        (_packets(b"GIF89a" + data[6:])[0], "header"),  # not a PNG
        (_packets(_file(_pixels(), "WEBP"), codec=CODEC_PNG)[0], "header"),
    ]:
        with pytest.raises(ScorePacketError, match=what):
            _decode(bad)
    with pytest.raises(ValueError, match="EXACT"):
        _packets(data, residual=True, exact=True)
    with pytest.raises(ValueError, match="shift"):
        _packets(data, shift=1)
    # an older decoder refuses a layer in one line
    with pytest.raises(ScorePacketError, match="unsupported packet version 4"):
        ScoreDecoder(6, DIGEST, max_packet_bytes=1 << 16).decode(good)


def test_a_file_that_lies_about_its_size_is_not_shown():
    """A PNG whose header says the image's size but whose data is a smaller image's."""
    lying = bytearray(_file(_pixels(rows=4), "PNG"))
    lying[16:24] = SHAPE[1].to_bytes(4, "big") + SHAPE[0].to_bytes(4, "big")
    data = _join(_packets(bytes(lying)))
    with pytest.raises(LayerError):
        decode_file(data, CODEC_PNG, SHAPE)


def test_the_rest_frame_applies_layers_in_order_and_ends_exact():
    truth = _pixels(seed=1)
    own = np.clip(truth.astype(int) + 9, 0, 255).astype(np.uint8)
    rest = RestFrame((30.0, 15.0), 10, own)
    residual = np.clip((truth.astype(int) - own) // 2 + 128, 0, 255).astype(np.uint8)

    def layer(pixels, **kwargs):
        data = _file(pixels, "PNG")
        return _decode(_packets(data, **kwargs)[0]), decode_file(data, CODEC_PNG, SHAPE)

    first, pixels = layer(residual, residual=True, shift=1, layer=0)
    assert rest.accepts(first)
    rest.apply(first, pixels)
    assert np.abs(rest.frame.astype(int) - truth).max() <= 1 and not rest.is_exact
    # a residual of layer 2 needs layer 1 first; a residual of layer 0 again does not apply
    assert not rest.accepts(layer(residual, residual=True, layer=2)[0])
    assert not rest.accepts(layer(residual, residual=True, layer=0)[0])
    # an absolute exact layer applies over any earlier ones and makes the frame exact
    exact, pixels = layer(truth, layer=2, exact=True)
    assert rest.accepts(exact)
    rest.apply(exact, pixels)
    assert rest.is_exact
    np.testing.assert_array_equal(rest.frame, truth)
    assert not rest.accepts(layer(truth, layer=0)[0])  # an older layer no longer applies
    assert own is not rest.frame  # the device's copy, not the frame it was made from


def test_a_strip_names_its_rows_and_one_outside_the_image_is_refused():
    """Version 5: a file of the image's width from ``row0``, as many rows as it declares;
    a strip of another width, or past the last row, is refused on its first chunk; version
    4 keeps the field reserved."""
    pixels = _pixels()
    (packet,) = _packets(_file(pixels[8:20], "PNG"), row0=8, exact=True)
    assert packet[2] == 5 and is_layer(packet)
    chunk = _decode(packet)
    assert (chunk.strip, chunk.row0) == (True, 8)
    np.testing.assert_array_equal(
        decode_file(chunk.data, CODEC_PNG, SHAPE, row0=chunk.row0), pixels[8:20])
    whole = _decode(_packets(_file(pixels, "PNG"), row0=0)[0])  # a strip may be all rows
    assert whole.strip and whole.row0 == 0
    for data, row0, why in ((_file(pixels[8:20, :-1], "PNG"), 8, "declares 39x12"),
                            (_file(pixels[8:20], "PNG"), 13, "from row 13")):
        with pytest.raises(ScorePacketError, match=why):
            _decode(_packets(data, row0=row0)[0])
    later = _packets(_file(_pixels(seed=3), "PNG"), row0=30, max_chunk_bytes=FIRST_CHUNK_MIN)
    with pytest.raises(ScorePacketError, match="from row 30"):  # a later chunk, too
        _decode(later[1])
    v4 = bytearray(_packets(_file(pixels, "PNG"))[0])
    v4[22] = 8  # a row in version 4's reserved field
    with pytest.raises(ScorePacketError, match="reserved"):
        _decode(bytes(v4))
    with pytest.raises(LayerError, match="rows from row 20"):  # the device checks it again
        decode_file(_file(pixels[8:20], "PNG"), CODEC_PNG, SHAPE, row0=20)
    with pytest.raises(ValueError, match="row0"):
        _packets(_file(pixels, "PNG"), row0=1 << 16)


def test_a_layer_in_strips_counts_once_every_row_is_in():
    """A residual layer in two strips: the count moves only when both are in, and a strip
    that came twice is not added twice; an exact layer in three strips with one lost leaves
    the frame not exact and the next residual refused, until an absolute layer repairs it."""
    truth, own = _pixels(seed=1), _pixels(seed=2)
    rest = RestFrame((30.0, 15.0), 10, own)
    residual = np.clip(truth.astype(np.int16) - own + 128, 0, 255).astype(np.uint8)

    def strip(pixels, r0, r1, **kwargs):
        (packet,) = _packets(_file(pixels[r0:r1], "PNG"), row0=r0, **kwargs)
        chunk = _decode(packet)
        return chunk, decode_file(chunk.data, CODEC_PNG, SHAPE, row0=r0)

    top, bottom = strip(residual, 0, 12, residual=True), strip(residual, 12, 24, residual=True)
    assert rest.accepts(top[0])
    rest.apply(*top)
    assert rest.layers == 0 and not rest.accepts(top[0])  # the same rows: not twice
    assert rest.accepts(bottom[0])
    rest.apply(*bottom)
    assert rest.layers == 1
    np.testing.assert_array_equal(rest.frame, truth)  # (no clip on these pixels)
    parts = [strip(truth, r0, r1, layer=1, exact=True) for r0, r1 in ((0, 8), (8, 16),
                                                                      (16, 24))]
    for part in (parts[2], parts[0]):  # the middle strip lost, the others out of order
        assert rest.accepts(part[0])
        rest.apply(*part)
    assert not rest.is_exact and rest.layers == 1
    assert not rest.accepts(strip(residual, 0, 24, residual=True, layer=2)[0])
    rest.apply(*parts[1])  # it came after all (or a whole absolute layer would repair)
    assert rest.is_exact and rest.layers == 2
    np.testing.assert_array_equal(rest.frame, truth)


def test_layer_golden_vectors_both_directions():
    cases = [json.loads(line) for line in GOLDEN.read_text().splitlines()]
    assert {c["name"] for c in cases} >= {"absolute_png", "residual_webp_chunks", "exact_png",
                                          "exact_webp_strip"}
    for case in cases:
        data = bytes.fromhex(case["file"])
        packets = encode_layer(data, image_digest=bytes.fromhex(case["digest"]),
                               view=tuple(case["view"]), **case["fields"])
        assert [p.hex() for p in packets] == case["packets"], case["name"]
        assembly, joined = LayerAssembly(), None
        for hexed in case["packets"]:
            chunk = decode_layer(bytes.fromhex(hexed),
                                 image_digest=bytes.fromhex(case["digest"]),
                                 image_shape=tuple(case["image_shape"]), max_packet_bytes=4096)
            for name in ("codec", "base_frame", "layer"):
                assert getattr(chunk, name) == case["fields"][name], (case["name"], name)
            assert (chunk.strip, chunk.row0) == ("row0" in case["fields"],
                                                 case["fields"].get("row0", 0))
            assert bytes.fromhex(hexed)[2] == (5 if chunk.strip else 4)
            joined = assembly.add(chunk)
        assert joined == data


def _regenerate() -> None:
    """Write tests/golden/layer_packets.jsonl (small fixed files, fixed fields)."""
    digest = bytes(range(100, 132))
    frame = np.arange(24 * 40 * 3, dtype=np.uint32).reshape(24, 40, 3) % 251
    png = _file(frame.astype(np.uint8), "PNG")
    webp = _file(frame.astype(np.uint8), "WEBP", lossless=True)
    strip = _file(frame[16:].astype(np.uint8), "WEBP", lossless=True)
    cases = [
        ("absolute_png", png, dict(codec=CODEC_PNG, frame=1000, base_frame=999, layer=0)),
        ("residual_webp_chunks", webp, dict(codec=CODEC_WEBP, frame=1001, base_frame=999,
                                            layer=1, residual=True, shift=1,
                                            max_chunk_bytes=FIRST_CHUNK_MIN)),
        ("exact_png", png, dict(codec=CODEC_PNG, frame=1003, base_frame=0, layer=2,
                                exact=True)),
        ("exact_webp_strip", strip, dict(codec=CODEC_WEBP, frame=1004, base_frame=0,
                                         layer=2, exact=True, row0=16)),
    ]
    lines = []
    for name, data, fields in cases:
        packets = encode_layer(data, image_digest=digest, view=(12.5, -30.0), **fields)
        lines.append(json.dumps({"name": name, "digest": digest.hex(), "view": [12.5, -30.0],
                                 "image_shape": [24, 40], "fields": fields, "file": data.hex(),
                                 "packets": [p.hex() for p in packets]}))
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


def _layer_for(device, image, pixels, **kwargs) -> list[bytes]:
    fields = {"frame": 5, "base_frame": 0, "view": device.view, "image_digest": image.digest,
              "layer": 0} | kwargs
    return encode_layer(_file(pixels, "PNG"), codec=CODEC_PNG, **fields)


def test_a_device_drops_every_bad_layer_and_shows_a_good_one_exactly(resting_device):
    """Mutated, truncated, oversized, incomplete and misdirected layers reach a resting
    device: none is shown exact, none stops it; each packet is counted; then a good exact
    layer (in chunks) makes the frame on show exactly its pixels."""
    from protocol import messages as m

    device, _, shown, image = resting_device
    h, w = image.image_shape
    rng = np.random.default_rng(7)
    truth = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    good = _layer_for(device, image, truth, exact=True, max_chunk_bytes=2048)
    assert len(good) > 2
    sends: list[list[bytes]] = [[good[0][:n]] for n in (3, 20, LAYER_HEADER_SIZE,
                                                        LAYER_HEADER_SIZE + 30)]
    for _ in range(60):  # random byte flips anywhere in one chunk of the file
        packets = [bytearray(p) for p in good]
        k = int(rng.integers(0, len(packets)))
        for _ in range(int(rng.integers(1, 5))):
            packets[k][int(rng.integers(0, len(packets[k])))] = int(rng.integers(0, 256))
        sends.append([bytes(p) for p in packets])
    huge = bytearray(good[0])  # a PNG that declares 60000 x 60000 pixels (an image bomb)
    huge[LAYER_HEADER_SIZE + 16:LAYER_HEADER_SIZE + 24] = (60000).to_bytes(4, "big") * 2
    sends += [[bytes(huge), *good[1:]],
              good[:1] + good[2:],  # a chunk lost
              good[1:],  # the first chunk lost
              _layer_for(device, image, truth, view=(device.view[0] + 5, device.view[1])),
              _layer_for(device, image, truth, base_frame=12345, residual=True),
              _layer_for(device, image, truth[: h // 2]),
              _layer_for(device, image, truth, image_digest=bytes(32))]
    frames_before = len(shown)
    said: list[str] = []
    device.log, device._wrong_image_logged = said.append, False
    for packets in sends:
        for packet in packets:
            device.on_scores(m.Scores(sequence=0, packet=packet))
            while device._layers:
                device.display_turn(None)
    stats = device.runtime_stats
    assert stats.exact_frames == 0
    assert stats.wrong_image >= 1  # another image's layer: counted, and said once
    assert sum("another image" in line for line in said) == 1
    for _, info in shown[frames_before:]:  # whatever a flipped pixel byte made, it is
        assert info.get("layer") is not None and not info.get("exact")  # never "exact"
    # each packet a layer's chunk, or (its magic or version flipped) a bad score packet
    assert stats.layer_packets + stats.decode_errors == sum(len(p) for p in sends)
    assert stats.layers_bad + stats.layers_dropped + stats.wrong_image > len(sends) // 2
    # a layer of the view on show lost on the way: the device asks for the view again
    assert stats.layer_retries >= 1 and device.limiter.pending
    for packet in good:
        device.on_scores(m.Scores(sequence=0, packet=packet))
    device.display_turn(None)
    assert shown[-1][1].get("exact") and stats.exact_frames == 1
    np.testing.assert_array_equal(shown[-1][0], truth)
    np.testing.assert_array_equal(device._shown_frame, truth)
