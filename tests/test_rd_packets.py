"""Tests of issue 6 part B: water-filled score packets, the delta-coded standalone table and
the eigenimages' bit allocation (docs/rate-distortion-packets.md)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from device_runtime.orbit import canonical_view
from device_runtime.standalone import (
    STANDALONE_DELTA_SECTION,
    STANDALONE_SECTION,
    StandaloneScores,
    standalone_table,
)
from host.errors import FitError
from host.fit.model import ANNEX_SCORES, HostModel, add_standalone_table
from host.fit.quantize import (
    MAX_BITS,
    allocate_bits,
    quantize_components,
    quantize_eigenspace,
    residual_mse,
)
from protocol.errors import ImageFormatError
from protocol.image import read_image, read_manifest, write_image


@pytest.fixture(scope="module")
def served(model_path):
    """The tiny model without its standalone table (a served image)."""
    image = read_image(model_path, require_annex=True)
    annex = image.annex
    image.sections.pop(STANDALONE_SECTION, None)
    image.sections.pop(STANDALONE_DELTA_SECTION, None)
    quant = {k: v for k, v in image.score_quantization.items() if k != "table_step"}
    image = dataclasses.replace(image, score_quantization=quant)
    return HostModel.from_image(image, annex)


# ----------------------------------------------------------------------------- water-filling


def test_waterfill_zeroes_exactly_the_components_below_the_noise(served):
    step = served.score_step
    mask = served.waterfill_mask()
    assert mask is not None
    np.testing.assert_array_equal(mask, served.eigenvalues < step * step / 12.0)
    # a coarser step puts more components under water
    coarse = served.waterfill_mask(step * 8)
    assert coarse.sum() > mask.sum() and np.all(coarse[mask])
    for view in [(10.0, 5.0), (200.0, -33.0)]:
        q = served.quantized_scores(*view)
        plain = np.rint(served.scores(*view) / step) * step
        np.testing.assert_array_equal(q[mask], 0.0)
        np.testing.assert_array_equal(q[~mask], plain[~mask].astype(np.float32))


def test_waterfill_is_off_when_the_manifest_says_so_or_without_eigenvalues(served):
    quant = {**served.image.score_quantization, "waterfill": False}
    off = HostModel.from_image(dataclasses.replace(served.image, score_quantization=quant),
                               served.annex())
    assert off.waterfill_mask() is None
    old = HostModel.from_image(served.image, {ANNEX_SCORES: served.training_scores})
    assert old.waterfill_mask() is None
    y = old.scores(10.0, 5.0)
    np.testing.assert_array_equal(old.quantized_scores(10.0, 5.0),
                                  (np.rint(y / old.score_step) * old.score_step).astype(np.float32))


# ----------------------------------------------------------------------------- standalone table


@pytest.mark.parametrize("delta", [True, False])
def test_device_interpolates_either_table_like_the_host(served, tmp_path, delta):
    image = dataclasses.replace(served.image, sections={})
    add_standalone_table(image, served.training_scores, eigenvalues=served.eigenvalues,
                         delta=delta)
    path = tmp_path / "standalone.ecs"
    write_image(path, image, annex=served.annex())
    names = [s["name"] for s in read_manifest(path)["sections"]]
    assert (STANDALONE_DELTA_SECTION in names) == delta
    assert (STANDALONE_SECTION in names) != delta
    host = HostModel.load(path)
    device = StandaloneScores(read_image(path))
    for view in [(0.0, 0.0), (33.3, 12.0), (359.0, -40.0), (181.0, 89.0)]:
        view = canonical_view(*view)
        np.testing.assert_array_equal(device.scores(*view), host.quantized_scores(*view))
    # the water-filled components are 0 in both, as a served packet would send them
    assert not np.any(device.scores(33.3, 12.0)[served.waterfill_mask()])


def test_delta_table_round_trips_exactly_with_wrap_around(served, tmp_path):
    image = dataclasses.replace(served.image, sections={})
    n_views, k = served.training_scores.shape
    rng = np.random.default_rng(1)
    # huge jumps between consecutive views: int16 differences wrap, the sum must unwrap them
    scores = rng.choice([-32000.0, 32000.0], size=(n_views, k)) * image.score_quantization[
        "step"]
    info = add_standalone_table(image, scores, delta=True)
    assert info["section"] == STANDALONE_DELTA_SECTION and info["dtype"] == "int16"
    delta = image.sections[STANDALONE_DELTA_SECTION]
    assert delta.shape == (k, 2, n_views) and delta.dtype == np.uint8
    path = tmp_path / "wrap.ecs"
    write_image(path, image)
    back = read_image(path)
    table, step = standalone_table(back)
    np.testing.assert_array_equal(table, np.rint(scores / step).astype(np.int16))
    # decoded once, in place: the section is now the table, and asking again gives the same
    assert STANDALONE_DELTA_SECTION not in back.sections
    again, _ = standalone_table(back)
    np.testing.assert_array_equal(again, table)


def test_water_filled_columns_are_zero_and_the_smaller_coding_is_kept(served, tmp_path):
    n_views, k = served.training_scores.shape
    rng = np.random.default_rng(4)
    slope, offset = rng.uniform(-300, 300, k), rng.uniform(-9000, 9000, k)
    smooth = (np.arange(n_views)[:, None] * slope + offset) * served.score_step  # ramps
    for scores in (served.training_scores, smooth):
        sizes = {}
        for delta in (False, True, None):
            image = dataclasses.replace(served.image, sections={})
            info = add_standalone_table(image, scores, eigenvalues=served.eigenvalues,
                                        delta=delta)
            path = tmp_path / f"table-{delta}.ecs"
            write_image(path, image)
            sizes[delta] = ({s["name"]: s["size"] for s in read_manifest(path)["sections"]}[
                info["section"]], info["section"])
            table, _ = standalone_table(read_image(path))
            mask = served.waterfill_mask()
            assert info["zero_columns"] == int(mask.sum())
            assert not np.any(table[:, mask])
            np.testing.assert_array_equal(
                table[:, ~mask], np.rint(scores[:, ~mask] / served.score_step))
        assert sizes[None][0] == min(sizes[True][0], sizes[False][0])
    assert sizes[None][1] == STANDALONE_DELTA_SECTION  # smooth scores: differences win
    assert sizes[True][0] < sizes[False][0] / 2


def test_table_step_and_bad_tables(served):
    image = dataclasses.replace(served.image, sections={})
    info = add_standalone_table(image, served.training_scores, table_step=4 * served.score_step,
                                delta=True)
    assert image.score_quantization["table_step"] == info["step"] == 4 * served.score_step
    with pytest.raises(FitError, match="table step"):
        add_standalone_table(image, served.training_scores, table_step=-1.0)
    with pytest.raises(FitError, match="eigenvalues"):
        add_standalone_table(image, served.training_scores, eigenvalues=np.ones(3))
    both = dataclasses.replace(image, sections={
        STANDALONE_DELTA_SECTION: image.sections[STANDALONE_DELTA_SECTION].copy(),
        STANDALONE_SECTION: np.zeros(served.training_scores.shape, np.int16)})
    with pytest.raises(ImageFormatError, match="both present"):
        standalone_table(both)
    bad = dataclasses.replace(image, sections={
        STANDALONE_DELTA_SECTION: image.sections[STANDALONE_DELTA_SECTION][:-1].copy()})
    with pytest.raises(ImageFormatError, match="expected uint8"):
        standalone_table(bad)
    no_views = dataclasses.replace(image, views=None, sections={
        STANDALONE_DELTA_SECTION: image.sections[STANDALONE_DELTA_SECTION].copy()})
    with pytest.raises(ImageFormatError, match="needs views"):
        standalone_table(no_views)


# ----------------------------------------------------------------------------- bit allocation


def test_allocate_bits_meets_the_budget_and_favours_high_variance():
    rng = np.random.default_rng(0)
    lam = np.sort(rng.exponential(100.0, 400))[::-1]
    peaks = rng.uniform(0.05, 0.3, 400)
    assert np.all(allocate_bits(lam, peaks, n_cells=10, mse_budget=0.0) == MAX_BITS)
    previous = 8 * 400
    for budget in (0.01, 0.1, 1.0):
        bits = allocate_bits(lam, peaks, n_cells=10, mse_budget=budget)
        limit = 2.0 ** (bits.astype(float) - 1) - 1
        added = np.sum(lam * ((peaks / limit) ** 2 - (peaks / 127) ** 2)) / (12 * 10)
        assert added <= budget * (1 + 1e-9)
        assert bits.sum() < previous and bits.min() >= 2
        previous = bits.sum()
    same_peak = allocate_bits(np.array([1000.0, 1.0]), np.array([0.1, 0.1]), n_cells=1,
                              mse_budget=0.01)
    assert same_peak[0] > same_peak[1]
    with pytest.raises(ValueError, match="differ"):
        allocate_bits(lam, peaks[:3], n_cells=1, mse_budget=1.0)
    with pytest.raises(ValueError, match="mse_budget"):
        allocate_bits(lam, peaks, n_cells=1, mse_budget=-1.0)


def test_quantize_components_with_bits_stays_within_each_rows_levels():
    rng = np.random.default_rng(2)
    v = rng.standard_normal((5, 60))
    bits = np.array([2, 3, 4, 6, 8], np.int8)
    q, scales = quantize_components(v, bits=bits)
    limit = 2 ** (bits.astype(int) - 1) - 1
    assert np.all(np.abs(q).max(axis=1) == limit)
    assert np.all(np.abs(v - scales[:, None] * q) <= scales[:, None] / 2 + 1e-6)
    np.testing.assert_array_equal(quantize_components(v, bits=np.full(5, 8, np.int8))[0],
                                  quantize_components(v)[0])
    with pytest.raises(ValueError, match="bits"):
        quantize_components(v, bits=np.array([1, 8, 8, 8, 8]))


def test_bit_budget_shrinks_the_image_at_a_bounded_cost(tmp_path):
    from host.fit.pca import CellEigenspace

    rng = np.random.default_rng(3)
    basis = rng.standard_normal((12, 8 * 8 * 3))
    coeff = rng.standard_normal((80, 12)) * np.geomspace(60, 1, 12)
    images = np.clip(120 + coeff @ basis + rng.standard_normal((80, 192)) * 2, 0, 255)
    images = images.astype(np.uint8).reshape(80, 8, 8, 3)
    model = CellEigenspace("cell", cell=8, components=10).fit(images)
    full = quantize_eigenspace(model)
    small = quantize_eigenspace(model, bit_budget=0.5)
    assert full.bits is not None and np.all(full.bits == 8)
    assert small.bits.mean() < 8 and small.bits.min() >= 2
    lam = np.concatenate(model.eigenvalues_)
    peaks = np.abs(np.concatenate(model.components_)).max(axis=1)
    limit = 2.0 ** (small.bits.astype(float) - 1) - 1
    added = np.sum(lam * ((peaks / limit) ** 2 - (peaks / 127) ** 2)) / (12 * full.mean.shape[0])
    assert 0 < added <= 0.5 * residual_mse(model) * (1 + 1e-9)
    with pytest.raises(ValueError, match="bit_budget"):
        quantize_eigenspace(model, bit_budget=-1)


def test_fit_bit_budget_option(model_path, tmp_path, capsys):
    from host.cli import main as eigencast

    db = model_path.parent / "tooth.cdb"
    out = {}
    for budget in ("0", "0.5"):
        path = tmp_path / f"b{budget}.ecs"
        assert eigencast(["fit", str(db), "-o", str(path), "--cell", "12", "--threshold",
                          "0.99", "--bit-budget", budget]) == 0
        out[budget] = read_image(path)
    bits0 = out["0"].provenance["eigen_bits"]
    bits5 = out["0.5"].provenance["eigen_bits"]
    assert bits0["mean_bits"] == 8.0 and bits0["histogram"] == {"8": out["0"].n_coefficients}
    assert bits5["bit_budget"] == 0.5 and bits5["mean_bits"] < 8.0
    np.testing.assert_array_equal(out["0"].n_components, out["0.5"].n_components)
    assert np.abs(out["0.5"].eigenimages).max(axis=1).min() < 127  # some rows use fewer levels
    capsys.readouterr()
    assert eigencast(["fit", str(db), "-o", str(tmp_path / "bad.ecs"), "--bit-budget",
                      "-1"]) == 1
    assert "--bit-budget -1" in capsys.readouterr().err


def test_zigzag_varints_is_the_public_varint_coder_the_scripts_size_layouts_with():
    from protocol.scores import zigzag_varints

    small = np.array([0, -1, 1, -2, 63, -64, 64], dtype=np.int64)
    assert zigzag_varints(small) == bytes([0, 1, 2, 3, 0x7E, 0x7F, 0x80, 0x01])
    values = np.array([8191, -8192, 8192, -(2**33), 2**34 - 1, 5], dtype=np.int64)

    def leb128(v: int) -> bytes:
        z, out = (v << 1) ^ (v >> 63), bytearray()
        while True:
            byte, z = z & 0x7F, z >> 7
            out.append(byte | (0x80 if z else 0))
            if not z:
                return bytes(out)

    assert zigzag_varints(values) == b"".join(leb128(int(v)) for v in values)
    assert zigzag_varints(np.array([], dtype=np.int64)) == b""
