"""Transfer functions: presets, LUT sampling, windows, serialisation, ParaView import."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from host.errors import TransferFunctionError
from host.render.transfer import (
    PRESETS,
    TransferFunction,
    add_transfer_function_argument,
    default_transfer_function,
    hu_calibration,
    load_transfer_function,
    transfer_function_from_args,
)
from host.volume import Volume, load_volume


def _tf(**kwargs) -> TransferFunction:
    base = dict(
        name="t",
        color_points=[[0.0, 0.0, 0.0, 0.0], [0.5, 1.0, 0.5, 0.0], [1.0, 1.0, 1.0, 1.0]],
        opacity_points=[[0.0, 0.0], [0.25, 0.0], [1.0, 0.6]],
    )
    base.update(kwargs)
    return TransferFunction(**base)


# --------------------------------------------------------------------------
# LUT and presets
# --------------------------------------------------------------------------


def test_lut_matches_hand_computed_values():
    lut = _tf().lut(5)  # t = 0, 0.25, 0.5, 0.75, 1
    assert lut.shape == (5, 4) and lut.dtype == np.float32
    expected = [
        [0.0, 0.0, 0.0, 0.0],
        [0.5, 0.25, 0.0, 0.0],  # half way to (1, 0.5, 0); alpha still 0 at t=0.25
        [1.0, 0.5, 0.0, 0.2],  # alpha: 0.6 * (0.5 - 0.25) / 0.75
        [1.0, 0.75, 0.5, 0.4],
        [1.0, 1.0, 1.0, 0.6],
    ]
    np.testing.assert_allclose(lut, expected, atol=1e-6)


def test_repeated_t_makes_a_step():
    tf = _tf(opacity_points=[[0.0, 0.0], [0.5, 0.0], [0.5, 1.0], [1.0, 1.0]])
    lut = tf.lut(101)
    assert lut[49, 3] == 0.0 and lut[51, 3] == 1.0


def test_normalize_clips_to_window():
    t = _tf().normalize(np.array([-10.0, 0.0, 5.0, 10.0, 99.0]), (0.0, 10.0))
    np.testing.assert_allclose(t, [0.0, 0.0, 0.5, 1.0, 1.0])


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_is_valid(name):
    tf = PRESETS[name]
    for points in (tf.color_points, tf.opacity_points):
        assert np.all(np.diff(points[:, 0]) >= 0)
        assert points[0, 0] == 0.0 and points[-1, 0] == 1.0
        assert points.min() >= 0.0 and points[:, 1:].max() <= 1.0
    lut = tf.lut(256)
    assert np.all(np.isfinite(lut)) and lut[0, 3] == 0.0, "the lowest values must be invisible"
    assert tf.description


def test_required_presets_exist():
    assert {"ct-bone", "ct-skin", "ct-muscle", "mri-default", "tooth"} <= set(PRESETS)


def _alpha_at_hu(tf: TransferFunction, hu: float) -> float:
    lo, hi = tf.window
    return float(np.interp((hu - lo) / (hi - lo), tf.opacity_points[:, 0], tf.opacity_points[:, 1]))


def test_ct_presets_classify_tissues_by_hu():
    bone, skin, muscle = PRESETS["ct-bone"], PRESETS["ct-skin"], PRESETS["ct-muscle"]
    assert all(tf.window_units == "HU" for tf in (bone, skin, muscle))
    assert _alpha_at_hu(bone, 40.0) == 0.0 and _alpha_at_hu(bone, 1000.0) > 0.5
    assert _alpha_at_hu(skin, -1000.0) == 0.0 and _alpha_at_hu(skin, -100.0) > 0.5
    assert _alpha_at_hu(muscle, -100.0) == 0.0 and _alpha_at_hu(muscle, 100.0) > 0.1


# --------------------------------------------------------------------------
# windows
# --------------------------------------------------------------------------


def _volume(data, **metadata) -> Volume:
    return Volume(np.asarray(data, dtype=np.float32), metadata=metadata)


def test_explicit_data_window_is_used_as_is():
    assert _tf(window=(3.0, 7.0)).resolve_window(_volume(np.zeros((4, 4, 4)))) == (3.0, 7.0)


def test_percentile_window_follows_the_documented_rule():
    # 70 % background zeros, then 1..1000: the foreground floor (2 % of the range) drops
    # the zeros and the values up to 20
    values = np.concatenate([np.zeros(2400), np.arange(1.0, 1001.0)])
    values = np.concatenate([values, np.zeros(3400 - values.size)])
    data = values.reshape(17, 10, 20)
    lo, hi = _tf(percentiles=(1.0, 99.0)).resolve_window(_volume(data))
    p_min, p_max = np.percentile(values, [0.1, 99.9])
    floor = p_min + 0.02 * (p_max - p_min)
    expected = np.percentile(values[values > floor], [1.0, 99.0])
    assert (lo, hi) == pytest.approx(tuple(expected))
    assert 20.0 < lo < 40.0 and 980.0 < hi < 1000.0


def test_window_is_robust_to_outliers():
    rng = np.random.default_rng(1)
    data = np.where(rng.random((40, 40, 40)) < 0.5, 0.0, rng.normal(500.0, 80.0, (40, 40, 40)))
    clean = _tf().resolve_window(_volume(data))
    spiky = data.copy()
    spiky.flat[rng.choice(spiky.size, 12, replace=False)] = [1e9] * 6 + [-1e9] * 6
    noisy = _tf().resolve_window(_volume(spiky))
    width = clean[1] - clean[0]  # min/max would move to +-1e9; percentiles barely move
    assert np.abs(np.subtract(noisy, clean)).max() < 0.01 * width


def test_window_ignores_non_finite_voxels_and_constant_volumes():
    data = np.full((6, 6, 6), 3.0)
    lo, hi = _tf().resolve_window(_volume(data))
    assert lo < 3.0 < hi
    data[0, 0, 0] = np.nan
    data[1:3] = 7.0
    lo, hi = _tf().resolve_window(_volume(data))
    assert np.isfinite([lo, hi]).all() and lo < hi


def test_hu_window_on_hu_volume():
    head = load_volume("builtin:head")
    assert PRESETS["ct-bone"].resolve_window(head) == (-1000.0, 2000.0)
    assert hu_calibration(head) is None


def test_hu_window_calibrated_from_air_and_soft_tissue_peaks():
    head = load_volume("builtin:head")
    scaled = (head.data + 1000.0) / 8.0  # an 8-bit-style export: air 0, soft tissue ~130
    vol = Volume(scaled, head.spacing, modality="ct")
    scale, offset = hu_calibration(vol)
    assert scale == pytest.approx(8.0, rel=0.06) and offset == pytest.approx(-1000.0, abs=40.0)
    lo, hi = PRESETS["ct-bone"].resolve_window(vol)
    assert lo == pytest.approx(0.0, abs=6.0) and hi == pytest.approx(375.0, rel=0.06)


def test_hu_window_without_peaks_falls_back_to_percentiles():
    ramp = np.linspace(0.0, 1.0, 4096).reshape(16, 16, 16)  # flat histogram: no tissue peak
    vol = _volume(ramp)
    assert hu_calibration(vol) is None
    assert PRESETS["ct-bone"].resolve_window(vol) == PRESETS["generic"].resolve_window(vol)


# --------------------------------------------------------------------------
# serialisation and validation
# --------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_to_dict_from_dict_round_trip_through_json(name):
    tf = PRESETS[name]
    again = TransferFunction.from_dict(json.loads(json.dumps(tf.to_dict())))
    assert again == tf and hash(again) == hash(tf)
    np.testing.assert_array_equal(again.lut(), tf.lut())
    assert again.window == tf.window and again.window_units == tf.window_units


def test_round_trip_of_awkward_floats():
    tf = _tf(color_points=[[0.0, 0.1, 0.2, 1 / 3], [1.0, 0.7, 2 / 3, 0.3]], window=(-0.1, 1e-7))
    assert TransferFunction.from_dict(json.loads(json.dumps(tf.to_dict()))) == tf


@pytest.mark.parametrize(
    "kwargs,word",
    [
        ({"color_points": [[0.0, 0, 0, 0], [1.5, 1, 1, 1]]}, "[0, 1]"),
        ({"opacity_points": [[0.5, 0.1], [0.2, 0.1]]}, "non-decreasing"),
        ({"opacity_points": [[0.0, 0.1], [1.0, 1.2]]}, "values"),
        ({"color_points": [[0.0, 0, 0]]}, "shape"),
        ({"window": (5.0, 5.0)}, "window"),
        ({"window": (0.0, float("nan"))}, "window"),
        ({"percentiles": (90.0, 10.0)}, "percentiles"),
        ({"window_units": "HU"}, "window"),
        ({"window_units": "kelvin"}, "window_units"),
    ],
)
def test_invalid_fields_raise(kwargs, word):
    with pytest.raises(TransferFunctionError, match="t") as info:
        _tf(**kwargs)
    assert word in str(info.value)


def test_from_dict_rejects_unknown_and_missing_keys():
    with pytest.raises(TransferFunctionError, match="missing keys"):
        TransferFunction.from_dict({"name": "x"})
    data = PRESETS["tooth"].to_dict() | {"gamma": 2}
    with pytest.raises(TransferFunctionError, match="gamma"):
        TransferFunction.from_dict(data)


# --------------------------------------------------------------------------
# ParaView / VolView presets
# --------------------------------------------------------------------------

PARAVIEW_EXPORT = [
    {
        "ColorSpace": "RGB",
        "Name": "MyBone",
        "NanColor": [1, 1, 0],
        "Points": [-1000, 0, 0.5, 0, 200, 0, 0.5, 0, 1000, 0.8, 0.5, 0, 3000, 0.9, 0.5, 0],
        "RGBPoints": [-1000, 0, 0, 0, 200, 0.6, 0.3, 0.2, 1000, 1, 1, 0.9, 3000, 1, 1, 1],
    },
    {
        "ColorSpace": "Diverging",
        "Name": "Cool to Warm",
        "RGBPoints": [
            0,
            0.23137254902,
            0.298039215686,
            0.752941176471,
            1,
            0.705882352941,
            0.0156862745098,
            0.149019607843,
        ],
    },
]


def _write(tmp_path, document, name="preset.json"):
    path = tmp_path / name
    path.write_text(json.dumps(document))
    return path


def test_paraview_export_sets_absolute_window(tmp_path):
    tf = load_transfer_function(str(_write(tmp_path, PARAVIEW_EXPORT)))
    assert tf.name == "MyBone" and tf.window == (-1000.0, 3000.0)
    lut = tf.lut(4001)  # one entry per data unit: index = x + 1000
    np.testing.assert_allclose(lut[1200], [0.6, 0.3, 0.2, 0.0], atol=1e-6)  # x = 200
    np.testing.assert_allclose(lut[2000], [1.0, 1.0, 0.9, 0.8], atol=1e-6)  # x = 1000
    np.testing.assert_allclose(lut[1600, 3], 0.4, atol=1e-6)  # x = 600, linear opacity


def test_paraview_select_by_name_and_diverging_midpoint(tmp_path):
    path = _write(tmp_path, PARAVIEW_EXPORT)
    tf = load_transfer_function(f"{path}#Cool to Warm")
    mid = tf.lut(101)[50, :3]
    # ParaView's 3-point "Cool to Warm" lists the diverging midpoint as 0.865 grey
    np.testing.assert_allclose(mid, [0.865, 0.865, 0.865], atol=0.03)
    np.testing.assert_allclose(tf.opacity_points, [[0, 0], [1, 1]])  # ParaView's default ramp


def test_lab_interpolation_black_to_white_is_perceptual(tmp_path):
    preset = {"ColorSpace": "Lab", "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1], "Name": "grey"}
    tf = load_transfer_function(str(_write(tmp_path, preset)))
    # CIE L* = 50 is Y = 0.184, i.e. sRGB 0.466 -- not the RGB midpoint 0.5
    np.testing.assert_allclose(tf.lut(101)[50, :3], [0.466] * 3, atol=0.01)


def test_volview_opacity_pairs_and_relative_range(tmp_path):
    preset = {
        "Name": "rel",
        "AbsoluteRange": False,
        "RGBPoints": [10, 1, 0, 0, 20, 0, 0, 1],
        "OpacityPoints": [10, 0, 15, 0.5, 20, 1],
    }
    tf = load_transfer_function(str(_write(tmp_path, preset)))
    assert tf.window is None
    np.testing.assert_allclose(tf.opacity_points, [[0, 0], [0.5, 0.5], [1, 1]])


def test_opacity_midpoint_and_sharpness_follow_vtk(tmp_path):
    preset = {
        "Name": "curved",
        "RGBPoints": [0, 1, 1, 1, 100, 1, 1, 1],
        "Points": [0, 0.0, 0.25, 0.0, 100, 0.8, 0.5, 0.0],  # midpoint moved to x = 25
    }
    tf = load_transfer_function(str(_write(tmp_path, preset)))
    alpha = tf.lut(101)[:, 3]
    assert alpha[25] == pytest.approx(0.4, abs=1e-6)  # VTK: (y1 + y2) / 2 at the midpoint
    assert alpha[0] == 0.0 and alpha[100] == pytest.approx(0.8)
    sharp = dict(preset, Points=[0, 0.0, 0.5, 1.0, 100, 0.8, 0.5, 0.0])  # sharpness 1: a step
    alpha = load_transfer_function(str(_write(tmp_path, sharp, "s.json"))).lut(201)[:, 3]
    assert alpha[90] == 0.0 and alpha[110] == pytest.approx(0.8)


@pytest.mark.parametrize(
    "document,word",
    [
        ("{not json", "JSON"),
        ([{"Name": "x"}], "RGBPoints"),
        ([{"RGBPoints": [0, 1, 1]}], "multiple of 4"),
        ([{"RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1], "Points": [0, 0, 0.5]}], "Points"),
        ([{"IndexedColors": [1, 0, 0], "RGBPoints": [0, 0, 0, 0]}], "IndexedColors"),
        ([{"RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1], "UseLogScale": True}], "log"),
        ([{"RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1], "ColorSpace": "Wavy"}], "ColorSpace"),
        ([{"RGBPoints": [5, 0, 0, 0, 5, 1, 1, 1]}], "range"),
        ([{"RGBPoints": [0, 0, 0, 0, 1, 2, 1, 1]}], "[0, 1]"),
        ([], "no preset"),
    ],
)
def test_bad_paraview_files_name_the_file(tmp_path, document, word):
    path = tmp_path / "bad.json"
    path.write_text(document if isinstance(document, str) else json.dumps(document))
    with pytest.raises(TransferFunctionError) as info:
        load_transfer_function(str(path))
    assert "bad.json" in str(info.value) and word in str(info.value)
    assert "\n" not in str(info.value)


def test_unknown_preset_lists_presets():
    with pytest.raises(TransferFunctionError) as info:
        load_transfer_function("ct-lung")
    assert "ct-lung" in str(info.value) and all(name in str(info.value) for name in PRESETS)


def test_missing_file_and_missing_name(tmp_path):
    with pytest.raises(TransferFunctionError, match="not found"):
        load_transfer_function(str(tmp_path / "gone.json"))
    path = _write(tmp_path, PARAVIEW_EXPORT)
    with pytest.raises(TransferFunctionError, match="MyBone"):
        load_transfer_function(f"{path}#Nope")


# --------------------------------------------------------------------------
# defaults and CLI
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "modality,preset",
    [("ct", "ct-bone"), ("mri", "mri-default"), ("tooth", "tooth"), ("generic", "generic")],
)
def test_default_by_modality(modality, preset):
    vol = Volume(np.zeros((4, 4, 4), dtype=np.float32), modality=modality)
    assert default_transfer_function(vol).name == preset


def test_default_for_builtins():
    assert default_transfer_function(load_volume("builtin:head")).name == "ct-bone"
    assert default_transfer_function(load_volume("builtin:tooth")).name == "tooth"


def test_cli_argument(tmp_path):
    parser = argparse.ArgumentParser()
    add_transfer_function_argument(parser)
    head = load_volume("builtin:sphere")
    assert transfer_function_from_args(parser.parse_args([]), head).name == "generic"
    args = parser.parse_args(["--tf", "CT-Skin"])
    assert transfer_function_from_args(args, head).name == "ct-skin"
    path = _write(tmp_path, PARAVIEW_EXPORT)
    assert (
        transfer_function_from_args(parser.parse_args(["--tf", str(path)]), head).name == "MyBone"
    )
