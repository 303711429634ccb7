"""Tests of protocol.image (the .ecs container) and protocol.keys / `eigencast keygen`.

The golden vector tests/golden/tiny.ecs pins the file format: it is decoded both by the
reader and by an independent reading of the documented layout written here (struct, cbor2,
zstd, hashlib, hmac), compared with arrays built from formulas, and re-encoded to the same
bytes. Changing it means bumping the format version.
Regenerate (deliberately) with ``.venv/bin/python tests/test_image.py --regenerate``.
"""

from __future__ import annotations

import hashlib
import hmac
import io
import os
import stat
import struct
import sys
import tracemalloc
import zlib
from pathlib import Path

import cbor2
import numpy as np
import pytest
import zstandard as zstd
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from host.cli import main as cli_main
from protocol.errors import AuthenticationError, ImageFormatError
from protocol.image import (
    HEADER_SIZE,
    MAGIC,
    EigenspaceImage,
    ImageTagError,
    ImageTruncatedError,
    image_size,
    parse_header,
    read_image,
    read_manifest,
    verify_stream,
    write_image,
)
from protocol.keys import KeyFileError, key_fingerprint, load_key, write_key

GOLDEN = Path(__file__).parent / "golden" / "tiny.ecs"
GOLDEN_KEY = bytes(range(32))
KEY = b"k" * 32


# ----------------------------------------------------------------------------- helpers


def tiny_image(provenance=None):
    """The golden image, from formulas: 5x7 px, cells 4x4 (2x2 grid), K = 6."""
    counts = np.array([2, 0, 1, 3], np.int32)
    values = 4 * 4 * 3
    i = np.arange(values)
    mean = np.stack([(c * 50 + i * 5) % 256 for c in range(4)]).astype(np.uint8)
    eig = np.stack([(j * 37 + i * 11) % 255 - 127 for j in range(6)]).astype(np.int8)
    scales = (np.arange(1, 7) / 1024).astype(np.float32)
    return EigenspaceImage(
        image_shape=(5, 7),
        cell_shape=(4, 4),
        mean=mean,
        eigenimages=eig,
        scales=scales,
        n_components=counts,
        method="adaptive",
        image_generation=42,
        score_quantization={"step": 0.5},
        views={
            "spec": "fibonacci:4",
            "phi_deg": [0.0, 137.5, 275.0, 52.5],
            "theta_deg": [-48.6, -14.5, 14.5, 48.6],
        },
        interpolation=None,
        provenance=provenance
        or {
            "created": "2024-01-01T00:00:00Z",
            "solver": "gram",
            "sign_convention": "largest |entry| positive",
            "zstd": ".".join(map(str, zstd.ZSTD_VERSION)),
        },
        sections={"training_scores": (np.arange(24, dtype=np.float32) / 8).reshape(4, 6)},
    )


TINY_ANNEX = {"eigenvalues": np.array([6.0, 5.0, 4.0, 3.0, 2.0, 1.0])}


def random_image(seed=0, height=37, width=23, cell=8, k_max=4):
    rng = np.random.default_rng(seed)
    ny, nx = -(-height // cell), -(-width // cell)
    n = ny * nx
    values = cell * cell * 3
    counts = rng.integers(0, k_max + 1, n).astype(np.int32)
    k = int(counts.sum())
    return EigenspaceImage(
        (height, width),
        (cell, cell),
        rng.integers(0, 256, (n, values), dtype=np.uint8),
        rng.integers(-127, 128, (k, values), dtype=np.int8),
        rng.random(k).astype(np.float32),
        counts,
        provenance={"seed": seed},
    )


def assert_same_image(a, b):
    assert a.image_shape == b.image_shape and a.cell_shape == b.cell_shape
    for name in ("mean", "eigenimages", "scales", "n_components"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert a.method == b.method and a.image_generation == b.image_generation
    assert a.views == b.views and a.provenance == b.provenance
    assert a.score_quantization == b.score_quantization
    assert sorted(a.sections) == sorted(b.sections)
    for name in a.sections:
        assert np.array_equal(a.sections[name], b.sections[name])


def build_container(manifest, body, *, key=None, version=1, flags=None):
    """Assemble a container from the documented layout (independent of write_image)."""
    mbytes = cbor2.dumps(manifest, canonical=True)
    size = HEADER_SIZE + len(mbytes) + len(body) + 64
    flags = (1 if key else 0) if flags is None else flags
    head = struct.pack("<8sHHHHIQ", MAGIC, version, flags, 32, 0, len(mbytes), size)
    head += struct.pack("<I", zlib.crc32(head))
    digest = hashlib.sha256(head + mbytes + body).digest()
    tag = hmac.new(key, digest, hashlib.sha256).digest() if key else bytes(32)
    return head + mbytes + body + digest + tag


def section(name, arr, *, compress=True, content_size=True, offset=0):
    raw = np.ascontiguousarray(arr).tobytes()
    data = zstd.ZstdCompressor(write_content_size=content_size).compress(raw) if compress else raw
    entry = {
        "name": name,
        "dtype": arr.dtype.str,
        "shape": list(arr.shape),
        "offset": offset,
        "size": len(data),
        "raw_size": len(raw),
    }
    return entry, data


def device_manifest(image, **overrides):
    """Manifest and body of ``image`` built by hand."""
    arrays = [
        ("n_components", image.n_components),
        ("scales", image.scales),
        ("mean", image.mean),
        ("eigenimages", image.eigenimages),
    ]
    table, body = [], b""
    for name, arr in arrays:
        entry, data = section(name, arr, offset=len(body))
        table.append(entry)
        body += data
    manifest = {
        "kind": "image",
        "image_shape": list(image.image_shape),
        "cell_shape": list(image.cell_shape),
        "method": "cell",
        "image_generation": 1,
        "score_quantization": {"step": 1.0},
        "views": None,
        "interpolation": None,
        "provenance": {},
        "annex": None,
        "sections": table,
    }
    manifest.update(overrides)
    return manifest, body


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("key", [None, KEY])
@pytest.mark.parametrize("annex", [None, {"scores": np.arange(12.0).reshape(3, 4)}])
def test_round_trip(tmp_path, key, annex):
    image = random_image(1)
    image.sections = {"extra": np.arange(7, dtype=np.int16)}
    path = tmp_path / "m.ecs"
    digest = write_image(path, image, key=key, annex=annex)
    back = read_image(path, key=key, require_tag=key is not None, require_annex=bool(annex))
    assert_same_image(image, back)
    assert back.digest == digest and back.signed == (key is not None)
    assert back.tag_verified == (key is not None)
    if annex:
        assert np.array_equal(back.annex["scores"], annex["scores"])
    else:
        assert back.annex is None
    with open(path, "rb") as f:  # streaming from a file object gives the same
        assert_same_image(image, read_image(f, key=key))
    assert stat.S_IMODE(path.stat().st_mode) & 0o644 == 0o644 & ~_umask()
    assert [p.name for p in tmp_path.iterdir()] == ["m.ecs"]


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_device_image_without_annex_and_helpers(tmp_path):
    path = tmp_path / "m.ecs"
    image = random_image(2)
    digest = write_image(path, image, key=KEY, annex={"ev": np.ones(3)})
    data = path.read_bytes()
    size = image_size(data[:HEADER_SIZE])
    assert size < len(data)  # the annex follows the device image
    device = data[:size]
    assert verify_stream(io.BytesIO(device), KEY) == (digest, True)
    assert verify_stream(io.BytesIO(device)) == (digest, False)
    assert verify_stream(io.BytesIO(device), b"x" * 32) == (digest, False)
    assert verify_stream(io.BytesIO(data), KEY) == (digest, True)  # stops at the image end
    back = read_image(io.BytesIO(device), key=KEY, require_tag=True)
    assert back.annex is None and back.tag_verified
    with pytest.raises(ImageFormatError, match=r"declares a .*annex but the data ends"):
        read_image(io.BytesIO(device), require_annex=True)
    only = read_image(path, read_annex=False)
    assert only.annex is None
    manifest = read_manifest(path)
    assert manifest["header"]["image_size"] == size and manifest["header"]["signed"]
    assert manifest["annex"]["sha256"] == hashlib.sha256(data[size:-64]).digest()
    assert manifest["image_shape"] == [37, 23]
    assert [s["name"] for s in manifest["sections"]] == [
        "n_components",
        "scales",
        "mean",
        "eigenimages",
    ]


def test_reader_accepts_an_independently_built_container():
    image = random_image(3)
    manifest, body = device_manifest(image)
    back = read_image(io.BytesIO(build_container(manifest, body, key=KEY)), key=KEY)
    for name in ("mean", "eigenimages", "scales", "n_components"):
        assert np.array_equal(getattr(back, name), getattr(image, name))
    assert back.tag_verified


# ----------------------------------------------------------------------------- golden


def test_golden_tiny_ecs(tmp_path):
    data = GOLDEN.read_bytes()
    # independent reading of the documented layout
    magic, version, flags, hsize, reserved, msize, size, crc = struct.unpack_from(
        "<8sHHHHIQI", data
    )
    assert (magic, version, flags, hsize, reserved) == (MAGIC, 1, 1, 32, 0)
    assert crc == zlib.crc32(data[:28])
    manifest = cbor2.loads(data[32 : 32 + msize])
    body = data[32 + msize : size - 64]
    digest = hashlib.sha256(data[: size - 64]).digest()
    assert data[size - 64 : size - 32] == digest
    assert data[size - 32 : size] == hmac.new(GOLDEN_KEY, digest, hashlib.sha256).digest()
    expected = tiny_image(provenance=manifest["provenance"])
    arrays = {}
    for entry in manifest["sections"]:
        frame = body[entry["offset"] : entry["offset"] + entry["size"]]
        raw = zstd.ZstdDecompressor().decompress(frame)
        arrays[entry["name"]] = np.frombuffer(raw, entry["dtype"]).reshape(entry["shape"])
    for name in ("mean", "eigenimages", "scales", "n_components"):
        assert np.array_equal(arrays[name], getattr(expected, name)), name
    assert np.array_equal(arrays["training_scores"], expected.sections["training_scores"])
    assert manifest["image_generation"] == 42 and manifest["method"] == "adaptive"
    annex = data[size:]
    assert manifest["annex"] == {"sha256": hashlib.sha256(annex[:-64]).digest(), "size": len(annex)}
    # the reader gives the same
    back = read_image(GOLDEN, key=GOLDEN_KEY, require_tag=True, require_annex=True)
    assert_same_image(expected, back)
    assert np.array_equal(back.annex["eigenvalues"], TINY_ANNEX["eigenvalues"])
    # and re-encoding the same inputs gives the same bytes (with the zstd that made them)
    out = tmp_path / "tiny.ecs"
    write_image(out, expected, key=GOLDEN_KEY, annex=TINY_ANNEX)
    if manifest["provenance"]["zstd"] == ".".join(map(str, zstd.ZSTD_VERSION)):
        assert out.read_bytes() == data
    else:  # another zstd may compress differently: the content must still agree
        assert_same_image(read_image(out), back)


def regenerate():  # pragma: no cover - a deliberate, manual act
    write_image(GOLDEN, tiny_image(), key=GOLDEN_KEY, annex=TINY_ANNEX)
    print(f"wrote {GOLDEN} ({GOLDEN.stat().st_size} bytes)")


# ----------------------------------------------------------------------------- corruption


@pytest.fixture(scope="module")
def signed_bytes(tmp_path_factory):
    path = tmp_path_factory.mktemp("img") / "s.ecs"
    write_image(
        path,
        random_image(4, height=9, width=10, cell=4, k_max=2),
        key=KEY,
        annex={"a": np.arange(5.0)},
    )
    return path.read_bytes()


def test_every_truncation_fails_cleanly(signed_bytes, tmp_path):
    size = image_size(signed_bytes)
    for cut in range(len(signed_bytes)):
        if cut == size:  # a device-only copy: valid without its annex
            continue
        with pytest.raises(ImageFormatError):
            read_image(io.BytesIO(signed_bytes[:cut]), key=KEY)
    path = tmp_path / "t.ecs"
    path.write_bytes(signed_bytes[: size - 10])
    with pytest.raises(ImageTruncatedError, match=f"expected {size} bytes, the file has"):
        read_image(path)


def test_trailing_bytes_are_refused(signed_bytes, tmp_path):
    with pytest.raises(ImageFormatError, match="trailing bytes"):
        read_image(io.BytesIO(signed_bytes + b"\x00"))
    path = tmp_path / "t.ecs"
    path.write_bytes(signed_bytes + b"abc")
    with pytest.raises(ImageFormatError, match="3 trailing bytes"):
        read_image(path)
    image = random_image(5)
    manifest, body = device_manifest(image)
    with pytest.raises(ImageFormatError, match="trailing bytes"):
        read_image(io.BytesIO(build_container(manifest, body) + b"\x01"))


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_random_byte_flips_are_digest_errors(signed_bytes, data):
    position = data.draw(st.integers(0, len(signed_bytes) - 1))
    flip = data.draw(st.integers(1, 255))
    corrupt = bytearray(signed_bytes)
    corrupt[position] ^= flip
    size = image_size(signed_bytes)
    with pytest.raises(ImageFormatError) as info:
        read_image(io.BytesIO(bytes(corrupt)), key=KEY)
    message = str(info.value)
    if position < HEADER_SIZE or size <= position < size + HEADER_SIZE:
        assert "magic" in message or "CRC" in message
    elif size - 32 <= position < size:
        assert isinstance(info.value, ImageTagError) and "tag mismatch" in message
    elif position >= len(signed_bytes) - 32:  # the annex's tag: always zero (unsigned)
        assert "non-zero tag" in message
    else:
        assert "digest mismatch" in message


@settings(max_examples=100, deadline=None)
@given(tail=st.binary(max_size=600), keep=st.integers(0, 200), seed=st.integers(0, 3))
def test_garbage_never_raises_anything_else(tail, keep, seed):
    image = random_image(seed, height=9, width=9, cell=4, k_max=2)
    manifest, body = device_manifest(image)
    good = build_container(manifest, body)
    with pytest.raises(ImageFormatError):
        read_image(io.BytesIO(good[:keep] + tail))


def test_wrong_key_and_missing_tag(tmp_path):
    path = tmp_path / "s.ecs"
    write_image(path, random_image(6), key=KEY)
    with pytest.raises(ImageTagError, match="tag mismatch") as info:
        read_image(path, key=b"z" * 32)
    assert isinstance(info.value, AuthenticationError)
    unsigned = tmp_path / "u.ecs"
    write_image(unsigned, random_image(6))
    assert not read_image(unsigned, key=KEY).tag_verified  # allowed unless required
    with pytest.raises(ImageTagError, match="not signed"):
        read_image(unsigned, key=KEY, require_tag=True)
    with pytest.raises(ValueError, match="require_tag=True needs a key"):
        read_image(unsigned, require_tag=True)
    signed_no_key = read_image(path)
    assert signed_no_key.signed and not signed_no_key.tag_verified
    data = bytearray(unsigned.read_bytes())
    data[-1] = 1  # unsigned with a non-zero tag
    with pytest.raises(ImageFormatError, match="non-zero tag"):
        read_image(io.BytesIO(bytes(data)))


# ----------------------------------------------------------------------------- hostile headers


def test_bad_magic_version_flags_and_header():
    image = random_image(7)
    manifest, body = device_manifest(image)
    good = build_container(manifest, body)
    with pytest.raises(ImageFormatError, match=r"bad magic .*not an eigencast image"):
        read_image(io.BytesIO(b"GIF89a" + good[6:]))
    with pytest.raises(ImageFormatError,
                       match=r"unsupported format version 4 \(supported: 1, 2, 3\)"):
        read_image(io.BytesIO(build_container(manifest, body, version=4)))
    with pytest.raises(ImageFormatError, match="format version 2 needs the manifest's 'looks'"):
        read_image(io.BytesIO(build_container(manifest, body, version=2)))
    with pytest.raises(ImageFormatError, match="unknown header flags 0x0004"):
        read_image(io.BytesIO(build_container(manifest, body, flags=4)))
    corrupt = bytearray(good)
    corrupt[20] ^= 0xFF  # image_size
    with pytest.raises(ImageFormatError, match="header CRC mismatch: stored 0x"):
        read_image(io.BytesIO(bytes(corrupt)))
    with pytest.raises(ImageFormatError, match="truncated header: expected 32 bytes, got 5"):
        parse_header(good[:5])
    with pytest.raises(ImageFormatError, match="manifest too large"):
        read_image(io.BytesIO(good), max_manifest_bytes=10)
    with pytest.raises(ImageFormatError, match="no such file"):
        read_image("/nonexistent/x.ecs")


def test_huge_declared_sizes_are_refused_before_allocating():
    image = random_image(8)
    manifest, body = device_manifest(image)
    n = 10**9  # 48 GB of eigenimages, declared consistently
    for entry in manifest["sections"]:
        if entry["name"] == "eigenimages":
            entry["shape"] = [n, 192]
            entry["raw_size"] = n * 192
        if entry["name"] == "scales":
            entry["shape"] = [n]
            entry["raw_size"] = 4 * n
    hostile = build_container(manifest, body)
    tracemalloc.start()
    try:
        with pytest.raises(ImageFormatError, match="max_section_bytes"):
            read_image(io.BytesIO(hostile))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2_000_000, f"peak {peak} B"
    small_manifest, small_body = device_manifest(image)
    with pytest.raises(ImageFormatError, match="max_total_bytes=1000"):
        read_image(io.BytesIO(build_container(small_manifest, small_body)), max_total_bytes=1000)


def test_zstd_frame_claiming_more_than_the_manifest_is_refused_before_allocating():
    image = random_image(9)
    manifest, body = device_manifest(image)
    entry = manifest["sections"][3]  # eigenimages, true sizes in the manifest
    frame = bytearray(zstd.ZstdCompressor(write_content_size=True).compress(b"\x00" * 70000))
    assert frame[4] >> 6 == 2  # 4-byte frame content size field
    frame[5:9] = struct.pack("<I", 1_000_000_000)  # the frame claims 1 GB
    body = body[: entry["offset"]] + bytes(frame)
    entry["size"] = len(frame)
    tracemalloc.start()
    try:
        with pytest.raises(ImageFormatError, match="frame records 1000000000 bytes, manifest"):
            read_image(io.BytesIO(build_container(manifest, body)))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2_000_000


def _rebuild(mutate, seed=10):
    image = random_image(seed)
    manifest, body = device_manifest(image)
    body = mutate(manifest, body) or body
    return io.BytesIO(build_container(manifest, body))


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda m, b: m.update(kind="annex"), "kind is 'annex', expected 'image'"),
        (lambda m, b: m.pop("image_shape") and None, "lacks the 'image_shape' entry"),
        (lambda m, b: m.update(image_shape=[5, "x"]), "must be two ints"),
        (lambda m, b: m.update(method=3), "'method' is a int, expected str"),
        (lambda m, b: m.update(image_generation=True), "expected int"),
        (lambda m, b: m["sections"][2].update(offset=10**9), "section out of bounds"),
        (lambda m, b: m["sections"][0].update(dtype="<c16"), "dtype '<c16' not allowed"),
        (lambda m, b: m["sections"][0].update(raw_size=7), "raw_size=7 disagrees"),
        (lambda m, b: m["sections"][0].update(name="zz"), "sections start with"),
        (lambda m, b: m["sections"][2].update(shape=[30, 96]), "section 'mean' is"),
        (lambda m, b: m.update(annex={"sha256": b"x", "size": 1}), "annex record"),
        (lambda m, b: m.update(sections={}), "'sections' is a dict, expected list"),
    ],
)
def test_malformed_manifests(mutate, match):
    with pytest.raises(ImageFormatError, match=match):
        read_image(_rebuild(mutate))


def test_malformed_sections():
    def unknown_size(m, b):
        image = random_image(10)
        table, body = [], b""
        for i, (name, arr) in enumerate(
            [
                ("n_components", image.n_components),
                ("scales", image.scales),
                ("mean", image.mean),
                ("eigenimages", image.eigenimages),
            ]
        ):
            entry, data = section(name, arr, offset=len(body), content_size=i != 2)
            table.append(entry)
            body += data
        m["sections"] = table
        return body

    with pytest.raises(ImageFormatError, match="does not record its content size"):
        read_image(_rebuild(unknown_size))

    def counts_off(m, b):
        entry = m["sections"][0]
        counts = np.frombuffer(zstd.ZstdDecompressor().decompress(b[: entry["size"]]), "<i4").copy()
        counts[0] += 1
        new = zstd.ZstdCompressor(write_content_size=True).compress(counts.tobytes())
        shift = len(new) - entry["size"]
        entry["size"] = len(new)
        for e in m["sections"][1:]:
            e["offset"] += shift
        return new + b[len(new) - shift :]

    with pytest.raises(ImageFormatError, match="n_components sums to"):
        read_image(_rebuild(counts_off))

    def not_zstd(m, b):
        m["sections"][0]["size"] += 0
        return b"\x00" * m["sections"][0]["size"] + b[m["sections"][0]["size"] :]

    with pytest.raises(ImageFormatError, match="not a zstd frame"):
        read_image(_rebuild(not_zstd))

    def junk_after_frame(m, b):
        e = m["sections"][-1]
        e["size"] += 4
        return b + b"junk"

    with pytest.raises(ImageFormatError, match="corrupt zstd data"):
        read_image(_rebuild(junk_after_frame))

    def bad_scale(m, b):
        e = m["sections"][1]
        scales = np.frombuffer(
            zstd.ZstdDecompressor().decompress(b[e["offset"] : e["offset"] + e["size"]]), "<f4"
        ).copy()
        scales[0] = np.nan
        new = zstd.ZstdCompressor(write_content_size=True).compress(scales.tobytes())
        shift = len(new) - e["size"]
        body = b[: e["offset"]] + new + b[e["offset"] + e["size"] :]
        e["size"] = len(new)
        for later in m["sections"][2:]:
            later["offset"] += shift
        return body

    with pytest.raises(ImageFormatError, match=r"scales\[0\]=.* must be finite"):
        read_image(_rebuild(bad_scale))


def test_not_cbor_manifest():
    head = struct.pack("<8sHHHHIQ", MAGIC, 1, 0, 32, 0, 4, 32 + 4 + 64)
    head += struct.pack("<I", zlib.crc32(head))
    data = head + b"\xff\xff\xff\xff"
    data += hashlib.sha256(data).digest() + bytes(32)
    with pytest.raises(ImageFormatError, match="manifest is not valid CBOR"):
        read_image(io.BytesIO(data))


# ----------------------------------------------------------------------------- writing


def test_write_failure_leaves_no_partial_file(tmp_path):
    path = tmp_path / "m.ecs"
    write_image(path, random_image(11))
    before = path.read_bytes()
    bad = random_image(12)
    bad.provenance = {"not cbor": object()}
    with pytest.raises(ValueError, match="not CBOR-encodable"):
        write_image(path, bad)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.ecs"]
    with pytest.raises(ValueError, match="eigenimages must be a int8 array"):
        broken = random_image(13)
        broken.eigenimages = broken.eigenimages.astype(np.int16)
        write_image(tmp_path / "b.ecs", broken)
    with pytest.raises(ValueError, match="key must be bytes"):
        write_image(tmp_path / "b.ecs", random_image(13), key=b"short")
    with pytest.raises(ValueError, match="level=25"):
        write_image(tmp_path / "b.ecs", random_image(13), level=25)
    assert [p.name for p in tmp_path.iterdir()] == ["m.ecs"]


def test_writer_streams_sections(tmp_path, monkeypatch):
    # sections are compressed in chunks: force tiny chunks and check the result still reads
    monkeypatch.setattr("protocol.image._CHUNK_BYTES", 1000)
    image = random_image(14, height=64, width=64, cell=16, k_max=8)
    write_image(tmp_path / "c.ecs", image, key=KEY)
    assert_same_image(image, read_image(tmp_path / "c.ecs", key=KEY))


# ----------------------------------------------------------------------------- keys


def test_key_file_round_trip_and_mode(tmp_path):
    path = tmp_path / "device.key"
    key = write_key(path)
    assert len(key) == 32 and load_key(path) == key
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    text = path.read_text()
    assert text.startswith("#") and key.hex() in text
    assert key_fingerprint(key) in text
    with pytest.raises(KeyFileError, match="already exists; use --force"):
        write_key(path)
    assert load_key(path) == key
    key2 = write_key(path, force=True)
    assert key2 != key and load_key(path) == key2
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


@pytest.mark.parametrize(
    "content,match",
    [
        ("# only a comment\n", "0 key lines"),
        ("zz" * 32 + "\n", "not hexadecimal"),
        ("ab" * 31 + "\n", "31 bytes, expected 32"),
        ("ab" * 32 + "\n" + "cd" * 32 + "\n", "2 key lines"),
    ],
)
def test_bad_key_files(tmp_path, content, match):
    path = tmp_path / "k"
    path.write_text(content)
    with pytest.raises(KeyFileError, match=match):
        load_key(path)


def test_missing_and_binary_key_files(tmp_path):
    with pytest.raises(KeyFileError, match=r"not found .*eigencast keygen"):
        load_key(tmp_path / "absent.key")
    (tmp_path / "bin").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(KeyFileError, match="not text"):
        load_key(tmp_path / "bin")
    (tmp_path / "big").write_bytes(b"a" * 10000)
    with pytest.raises(KeyFileError, match="larger than"):
        load_key(tmp_path / "big")


def test_keygen_command(tmp_path, capsys):
    path = tmp_path / "dev.key"
    assert cli_main(["keygen", "-o", str(path)]) == 0
    out = capsys.readouterr().out
    key = load_key(path)
    assert key_fingerprint(key) in out and key.hex() not in out
    assert cli_main(["keygen", "-o", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already exists" in err
    assert load_key(path) == key
    assert cli_main(["keygen", "-o", str(path), "--force", "--json"]) == 0
    assert '"fingerprint"' in capsys.readouterr().out and load_key(path) != key


if __name__ == "__main__" and "--regenerate" in sys.argv:  # pragma: no cover
    regenerate()


# ----------------------------------------------------------------------------- looks


def _looks_image(seed=11):
    image = random_image(seed)
    image.sections = {"look1_mean": image.mean[::-1].copy(),
                      "look1_scales": image.scales * 2,
                      "look1_eigenimages": -image.eigenimages}
    image.looks = [{"name": "bone", "sections": {}},
                   {"name": "skin", "sections": {k: f"look1_{k}"
                                                 for k in ("mean", "scales", "eigenimages")}}]
    return image


def test_an_image_with_looks_is_format_version_2_and_round_trips(tmp_path):
    """``looks`` is written (and only then) with format version 2, read back as written;
    an image without it stays version 1 with no ``looks`` key."""
    image = _looks_image()
    path = tmp_path / "looks.ecs"
    write_image(path, image, key=KEY)
    assert struct.unpack_from("<H", path.read_bytes(), 8)[0] == 2
    back = read_image(path, key=KEY, require_tag=True)
    assert back.looks == image.looks
    assert np.array_equal(back.sections["look1_eigenimages"], -image.eigenimages)
    plain = tmp_path / "plain.ecs"
    write_image(plain, random_image(11))
    assert struct.unpack_from("<H", plain.read_bytes(), 8)[0] == 1
    assert "looks" not in read_manifest(plain) and read_image(plain).looks is None


@pytest.mark.parametrize("looks,match", [
    ([{"name": "a"}], "list of 2..16 maps"),
    ([{"name": "a"}, {"name": "a"}], "unique printable 'name'"),
    ([{"name": "a"}, {"name": ""}], "unique printable 'name'"),
    ([{"name": "a"}, {"name": "b", "sections": {"interpolation": "look1_mean"}}],
     "section 'interpolation' cannot be replaced"),
    ([{"name": "a"}, {"name": "b", "sections": {"mean": "nope"}}], "which the image lacks"),
    ([{"name": "a"}, {"name": "b", "synthesis": 3}], "'synthesis' must be a map or null"),
])
def test_malformed_looks_are_refused_by_the_writer_and_the_reader(tmp_path, looks, match):
    image = _looks_image()
    image.looks = looks
    with pytest.raises(ValueError, match=match):
        write_image(tmp_path / "bad.ecs", image)
    manifest, body = device_manifest(image)
    manifest["looks"] = looks
    with pytest.raises(ImageFormatError, match=match):
        read_image(io.BytesIO(build_container(manifest, body, version=2)))


def test_looks_with_their_own_scores_are_format_version_3(tmp_path):
    """A look naming its own counts and standalone table (an eigenspace of its own) makes
    the image version 3, with its score step in its entry; version 2 may not name them, and
    a score step must be positive numbers."""
    image = _looks_image()
    image.sections["look1_n_components"] = image.n_components.copy()
    image.looks[1]["sections"]["n_components"] = "look1_n_components"
    image.looks[1]["score_quantization"] = {"step": 2.5, "table_step": 2.5}
    path = tmp_path / "own.ecs"
    write_image(path, image)
    assert struct.unpack_from("<H", path.read_bytes(), 8)[0] == 3
    assert read_image(path).looks[1]["score_quantization"] == {"step": 2.5, "table_step": 2.5}
    manifest, body = device_manifest(image)
    manifest["looks"] = [{"name": "a"}, {"name": "b", "sections": {
        "n_components": "look1_n_components"}}]
    with pytest.raises(ImageFormatError, match="its own 'n_components' needs format version 3"):
        read_image(io.BytesIO(build_container(manifest, body, version=2)))
    image.looks[1]["score_quantization"] = {"step": -1.0}
    with pytest.raises(ValueError, match="'score_quantization' must be a map of positive"):
        write_image(tmp_path / "bad.ecs", image)


def test_looks_in_a_version_1_manifest_are_refused():
    image = random_image(12)
    manifest, body = device_manifest(image)
    manifest["looks"] = [{"name": "a"}, {"name": "b"}]
    with pytest.raises(ImageFormatError, match="'looks' needs format version 2"):
        read_image(io.BytesIO(build_container(manifest, body, version=1)))
