"""Volume loading: every format round-trips, real volumes load upright, bad input fails cleanly."""

from __future__ import annotations

import argparse
import gzip
import json
import zlib

import numpy as np
import pytest
from data_builders import (
    small_volume,
    write_dat,
    write_dicom_series,
    write_mha,
    write_mhd,
    write_nifti,
    write_nrrd,
    write_pvm,
    write_raw,
    write_tiff_folder,
    write_tiff_stack,
)

from host.errors import VolumeError
from host.volume import (
    KNOWN_DATASETS,
    RAW_DTYPES,
    Volume,
    add_volume_arguments,
    list_builtins,
    load_volume,
    volume_from_args,
)

SHAPE = (8, 10, 12)  # (nz, ny, nx): file dims x, y, z = 12, 10, 8
DIMS = (12, 10, 8)


def _fg_centroid(mask: np.ndarray) -> np.ndarray:
    """Centroid of a boolean mask as fractions of the (z, y, x) extents."""
    return np.array(np.nonzero(mask), dtype=float).mean(axis=1) / np.array(mask.shape)


# --------------------------------------------------------------------------
# the real volumes in ../shared/data
# --------------------------------------------------------------------------

SHARED = {
    # name: (numpy shape (nz, ny, nx) from README dims x, y, z; spacing (x, y, z); modality)
    "tooth": ((161, 120, 140), (1.0, 1.0, 1.0), "tooth"),
    "vismale_head": ((256, 256, 128), (1.57774, 0.995861, 1.00797), "ct"),
    "engine": ((64, 128, 128), (2.0, 2.0, 2.0), "generic"),
    "headsq": ((93, 64, 64), (3.2, 3.2, 1.5), "ct"),
    "brainsmall": ((128, 128, 84), (1.0, 1.0, 1.0), "mri"),  # sagittal file, rotated to RAS
    "mni152": ((189, 233, 197), (1.0, 1.0, 1.0), "mri"),
}


@pytest.mark.shared_data
@pytest.mark.parametrize("name", sorted(SHARED))
def test_shared_volume_shape_spacing_modality(shared_path, name):
    shape, spacing, modality = SHARED[name]
    vol = load_volume(shared_path(name))
    assert vol.data.shape == shape
    assert vol.data.dtype == np.float32 and vol.data.flags.c_contiguous
    assert vol.spacing == pytest.approx(spacing)
    assert vol.modality == modality
    assert vol.metadata["value_range"] == [float(vol.data.min()), float(vol.data.max())]
    assert json.loads(json.dumps(vol.metadata)) == vol.metadata  # goes into render sidecars


@pytest.mark.shared_data
def test_tooth_crown_is_up(shared_path):
    data = load_volume(shared_path("tooth")).data
    enamel = _fg_centroid(data >= 220)  # the crown's enamel is the brightest tissue
    dentin = _fg_centroid((data > 120) & (data < 190))
    assert enamel[0] > 0.65, "enamel crown must sit in the upper part (+z)"
    assert enamel[0] > dentin[0] + 0.1, "enamel must be above the dentin and roots"


@pytest.mark.shared_data
@pytest.mark.parametrize("name,tissue", [("vismale_head", 30.0), ("headsq", 500.0)])
def test_ct_heads_are_upright_and_face_plus_y(shared_path, name, tissue):
    data = load_volume(shared_path(name)).data
    teeth = _fg_centroid(data >= np.percentile(data, 99.9))  # enamel and fillings
    assert teeth[0] < 0.5, "teeth must be in the lower half (top of head at +z)"
    assert teeth[1] > 0.5, "teeth must be in the anterior half (face towards +y)"
    k, j, _ = np.nonzero(data > tissue)
    low = k < k.min() + 0.15 * (k.max() - k.min())
    assert j[low].mean() < j.mean() - 0.05 * data.shape[1], "neck and spine: low and posterior"


@pytest.mark.shared_data
def test_brainsmall_mri_is_upright_and_faces_plus_y(shared_path):
    data = load_volume(shared_path("brainsmall")).data
    k, j, i = np.nonzero(data > 20)
    tip = j >= j.max() - 1  # the most anterior point of the head: the nose
    height = (k[tip].mean() - k.min()) / (k.max() - k.min())
    assert height < 0.5, "nose tip must be in the lower half of the head"
    assert abs(i[tip].mean() / data.shape[2] - 0.5) < 0.1, "nose tip on the midline"


@pytest.mark.shared_data
def test_mni152_superior_inferior_extents(shared_path):
    vol = load_volume(shared_path("mni152"))
    assert vol.metadata["orientation"]["source"] == "header"
    data = vol.data
    k, j, _ = np.nonzero(data > 40)
    # the brain stem reaches the bottom of the MNI box, the vertex is well below its top
    assert k.min() < 0.05 * data.shape[0] and 0.7 * data.shape[0] < k.max() < data.shape[0] - 5
    low = k < k.min() + 0.15 * (k.max() - k.min())  # cerebellum and brain stem
    assert j[low].mean() < j.mean() - 0.05 * data.shape[1]


@pytest.mark.shared_data
def test_engine_keeps_file_order_and_inflates_zlib(shared_path):
    path = shared_path("engine")
    vol = load_volume(path)
    raw = zlib.decompress((path.parent / "engine_small.raw").read_bytes())
    expected = np.frombuffer(raw, dtype=np.uint8).reshape(64, 128, 128)
    np.testing.assert_array_equal(vol.data, expected)
    assert vol.metadata["orientation"]["source"] == "none"


def test_known_dataset_fixes_are_rotations_not_mirrors():
    from host.volume.orientation import _is_proper_rotation

    for key, known in KNOWN_DATASETS.items():
        assert _is_proper_rotation(known.file_axes), key


# --------------------------------------------------------------------------
# round trips through files written with the formats' own tools
# --------------------------------------------------------------------------


def _assert_round_trip(write, path, dtype: str, spacing: tuple) -> None:
    """A small ``dtype`` volume written by ``write`` at ``path`` with ``spacing`` loads back
    as it was, with that spacing."""
    src = small_volume(dtype, SHAPE)
    vol = load_volume(write(path, src, spacing))
    np.testing.assert_array_equal(vol.data, src)
    assert vol.spacing == spacing


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int16", "float32"])
@pytest.mark.parametrize("endian", ["little", "big"])
def test_raw_round_trip(tmp_path, dtype, endian):
    src = small_volume(dtype, SHAPE)
    path = write_raw(tmp_path / "vol.bin", src, endian)
    vol = load_volume(path, dims=DIMS, dtype=dtype, endian=endian, spacing=(0.5, 0.6, 2.0))
    np.testing.assert_array_equal(vol.data, src.astype(np.float32))
    assert vol.spacing == (0.5, 0.6, 2.0)
    assert vol.metadata["format"] == "raw" and vol.metadata["file_dtype"] == dtype


def test_raw_gzip_round_trip(tmp_path):
    src = small_volume("uint16", SHAPE)
    path = tmp_path / "vol.raw.gz"
    path.write_bytes(gzip.compress(src.astype("<u2").tobytes()))
    np.testing.assert_array_equal(load_volume(path, dims=DIMS, dtype="uint16").data, src)


@pytest.mark.parametrize("compressed", [False, True])
@pytest.mark.parametrize("big_endian", [False, True])
def test_mhd_round_trip(tmp_path, compressed, big_endian):
    src = small_volume("int16", SHAPE)
    path = write_mhd(
        tmp_path / "v.mhd", src, (0.4, 0.5, 1.5), compressed=compressed, big_endian=big_endian
    )
    vol = load_volume(path)
    np.testing.assert_array_equal(vol.data, src)
    assert vol.spacing == pytest.approx((0.4, 0.5, 1.5))
    assert vol.metadata["compressed"] is compressed


def test_mha_local_round_trip(tmp_path):
    _assert_round_trip(write_mha, tmp_path / "v.mha", "float32", (1.0, 2.0, 3.0))


def test_mhd_transform_matrix_reorients_to_ras(tmp_path):
    src = small_volume("uint8", SHAPE)
    # ITK direction rows in LPS: +i -> L, +j -> P, +k -> I (slices from the top down)
    extra = {"TransformMatrix": "1 0 0 0 1 0 0 0 -1", "Modality": "MET_MOD_CT"}
    vol = load_volume(write_mhd(tmp_path / "v.mhd", src, (1, 2, 3), extra=extra))
    assert vol.metadata["orientation"] == {"file_axes": "LPI", "source": "header", "note": ""}
    np.testing.assert_array_equal(vol.data, src[::-1, ::-1, ::-1])  # all three flip to RAS
    assert vol.modality == "ct" and vol.metadata["units"] == "HU"


def test_mhd_anatomical_orientation_letters_mean_from(tmp_path):
    src = small_volume("uint8", SHAPE)
    extra = {"AnatomicalOrientation": "RAI"}  # ITK's RAI == LPS: x to L, y to P, z to S
    vol = load_volume(write_mhd(tmp_path / "v.mhd", src, extra=extra))
    assert vol.metadata["orientation"]["file_axes"] == "LPS"
    np.testing.assert_array_equal(vol.data, src[:, ::-1, ::-1])


def test_mhd_header_size_skips_bytes(tmp_path):
    src = small_volume("uint8", SHAPE)
    write_mhd(tmp_path / "v.mhd", src, extra={"HeaderSize": "7"})
    payload = (tmp_path / "v.raw").read_bytes()
    (tmp_path / "v.raw").write_bytes(b"JUNK123" + payload)
    np.testing.assert_array_equal(load_volume(tmp_path / "v.mhd").data, src)


def test_nrrd_attached_round_trip_with_spacings(tmp_path):
    src = small_volume("uint16", SHAPE)
    path = write_nrrd(tmp_path / "v.nrrd", src, {"spacings": [0.5, 0.75, 2.0]})
    vol = load_volume(path)
    np.testing.assert_array_equal(vol.data, src)
    assert vol.spacing == (0.5, 0.75, 2.0)
    assert vol.metadata["orientation"]["source"] == "none"


def test_nrrd_detached_gzip_with_space_directions(tmp_path):
    src = small_volume("int16", SHAPE)
    header = {
        "space": "left-posterior-superior",
        "space directions": np.diag([0.5, 0.6, 1.2]),
        "encoding": "gzip",
    }
    path = write_nrrd(tmp_path / "v.nhdr", src, header, detached_header=True)
    assert any(p.name != "v.nhdr" for p in tmp_path.iterdir()), "data must be detached"
    vol = load_volume(path)
    assert vol.metadata["orientation"]["file_axes"] == "LPS"
    np.testing.assert_array_equal(vol.data, src[:, ::-1, ::-1])  # L->R and P->A flips
    assert vol.spacing == pytest.approx((0.5, 0.6, 1.2))


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_nifti_round_trip(tmp_path, suffix):
    src = small_volume("int16", SHAPE)
    affine = np.diag([0.8, 0.9, 2.5, 1.0])  # RAS already
    vol = load_volume(write_nifti(tmp_path / f"v{suffix}", src, affine))
    np.testing.assert_array_equal(vol.data, src)
    assert vol.spacing == pytest.approx((0.8, 0.9, 2.5))
    assert vol.modality == "mri"


def test_nifti_lps_affine_and_scaling(tmp_path):
    src = small_volume("int16", SHAPE, seed=3)
    affine = np.diag([-1.0, -1.0, 2.0, 1.0])  # +i -> L, +j -> P
    vol = load_volume(write_nifti(tmp_path / "v.nii.gz", src, affine, slope_inter=(0.5, 10.0)))
    expected = src.astype(np.float64) * 0.5 + 10.0
    np.testing.assert_allclose(vol.data, expected[:, ::-1, ::-1], rtol=0, atol=1e-3)
    assert vol.spacing == pytest.approx((1.0, 1.0, 2.0))


def test_tiff_stack_round_trip_default_spacing(tmp_path):
    src = small_volume("uint16", SHAPE)
    vol = load_volume(write_tiff_stack(tmp_path / "v.tif", src))
    np.testing.assert_array_equal(vol.data, src)
    assert vol.spacing == (1.0, 1.0, 1.0)


def test_tiff_imagej_spacing(tmp_path):
    src = small_volume("uint8", SHAPE)
    path = write_tiff_stack(
        tmp_path / "v.tif",
        src,
        imagej=True,
        resolution=(1 / 0.25, 1 / 0.5),  # pixels per unit
        metadata={"spacing": 2.0, "unit": "mm", "axes": "ZYX"},
    )
    vol = load_volume(path)
    np.testing.assert_array_equal(vol.data, src)
    assert vol.spacing == pytest.approx((0.25, 0.5, 2.0))


def test_tiff_folder_in_natural_order(tmp_path):
    src = small_volume("uint8", (11, 10, 12))  # > 9 slices: slice_10 must follow slice_9
    vol = load_volume(write_tiff_folder(tmp_path / "stack", src))
    np.testing.assert_array_equal(vol.data, src)


def test_dicom_series_shuffled_rescaled_non_unit_spacing(tmp_path):
    stored = small_volume("uint16", SHAPE, seed=5) // 16
    folder = write_dicom_series(tmp_path / "series", stored, slope=2.0, intercept=-1024.0)
    vol = load_volume(folder)
    expected = stored.astype(np.float32) * 2.0 - 1024.0
    # DICOM index axes point L (columns) and P (rows); RAS flips both
    np.testing.assert_array_equal(vol.data, expected[:, ::-1, ::-1])
    assert vol.spacing == pytest.approx((0.5, 0.7, 2.5))  # (column, row, slice) spacing
    assert vol.modality == "ct" and vol.metadata["units"] == "HU"
    assert vol.metadata["orientation"]["file_axes"] == "LPS"
    assert json.loads(json.dumps(vol.metadata)) == vol.metadata
    one_file = sorted(folder.iterdir())[0]
    np.testing.assert_array_equal(load_volume(one_file).data, vol.data)


def test_dicom_series_sorted_by_position_not_file_name(tmp_path):
    stored = np.stack([np.full((10, 12), 100 * k, dtype=np.uint16) for k in range(8)])
    folder = write_dicom_series(tmp_path / "s", stored, slope=1.0, intercept=0.0, shuffle_seed=7)
    vol = load_volume(folder)
    np.testing.assert_array_equal(vol.data[:, 0, 0], 100.0 * np.arange(8))  # +z = superior


def test_dat_text_header_round_trip(tmp_path):
    _assert_round_trip(write_dat, tmp_path / "v.dat", "uint16", (3.2, 3.2, 1.5))


def test_dat_binary_tuwien_header(tmp_path):
    src = small_volume("uint16", SHAPE) % 4096
    path = tmp_path / "v.dat"
    path.write_bytes(np.array(DIMS, dtype="<u2").tobytes() + src.astype("<u2").tobytes())
    np.testing.assert_array_equal(load_volume(path).data, src)


@pytest.mark.parametrize("dtype", ["uint8", "uint16"])
def test_pvm_round_trip(tmp_path, dtype):
    _assert_round_trip(write_pvm, tmp_path / "v.pvm", dtype, (0.5, 0.5, 1.0))


def test_orientation_override_wins_over_header(tmp_path):
    src = small_volume("uint8", SHAPE)
    path = write_nifti(tmp_path / "v.nii", src, np.eye(4))
    vol = load_volume(path, orientation="lpi", modality="ct")
    assert vol.metadata["orientation"]["source"] == "user"
    np.testing.assert_array_equal(vol.data, src[::-1, ::-1, ::-1])
    assert vol.modality == "ct"


def test_orientation_permutes_axes_and_spacing(tmp_path):
    src = small_volume("uint8", SHAPE)
    path = write_raw(tmp_path / "v.raw", src)
    # file +x runs anterior, +y superior, +z right: a sagittal stack
    vol = load_volume(path, dims=DIMS, spacing=(1.0, 2.0, 3.0), orientation="ASR")
    assert vol.data.shape == (10, 12, 8)  # (z <- file y, y <- file x, x <- file z)
    assert vol.spacing == (3.0, 1.0, 2.0)
    np.testing.assert_array_equal(vol.data, np.transpose(src, (1, 2, 0)))


# --------------------------------------------------------------------------
# bad input: one VolumeError naming the file
# --------------------------------------------------------------------------


def _error(match_file, *args, **kwargs) -> str:
    with pytest.raises(VolumeError) as info:
        load_volume(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    assert str(match_file) in message
    return message


def test_raw_truncated_names_both_sizes(tmp_path):
    path = write_raw(tmp_path / "short.raw", small_volume("uint16", SHAPE))
    path.write_bytes(path.read_bytes()[:-10])
    message = _error("short.raw", path, dims=DIMS, dtype="uint16")
    assert "truncated" in message and "1910" in message and "1920" in message


def test_raw_dims_too_small_for_file(tmp_path):
    path = write_raw(tmp_path / "long.raw", small_volume("uint8", SHAPE))
    message = _error("long.raw", path, dims=(12, 10, 7), dtype="uint8")
    assert "960" in message and "840" in message


def test_raw_unknown_dtype_lists_allowed(tmp_path):
    path = write_raw(tmp_path / "v.raw", small_volume("uint8", SHAPE))
    message = _error("v.raw", path, dims=DIMS, dtype="complex64")
    assert all(name in message for name in RAW_DTYPES)


def test_raw_without_dims(tmp_path):
    path = write_raw(tmp_path / "v.raw", small_volume("uint8", SHAPE))
    assert "--dims" in _error("v.raw", path)


def test_mhd_missing_data_file_is_named(tmp_path):
    path = write_mhd(tmp_path / "v.mhd", small_volume("uint8", SHAPE), data_name="payload.raw")
    (tmp_path / "payload.raw").unlink()
    assert "payload.raw" in _error("v.mhd", path)


def test_mhd_corrupt_zlib(tmp_path):
    path = write_mhd(tmp_path / "v.mhd", small_volume("uint8", SHAPE), compressed=True)
    data = bytearray((tmp_path / "v.raw").read_bytes())
    data[2:12] = b"\xff" * 10
    (tmp_path / "v.raw").write_bytes(bytes(data))
    assert "corrupt" in _error("v.mhd", path)


def test_mhd_hostile_dims_refused_before_reading(tmp_path):
    path = tmp_path / "huge.mhd"
    path.write_text(
        "NDims = 3\nDimSize = 100000 100000 100000\nElementType = MET_UCHAR\n"
        "ElementDataFile = LOCAL\n"
    )
    assert "voxels" in _error("huge.mhd", path)


def test_mhd_unknown_element_type(tmp_path):
    path = write_mhd(tmp_path / "v.mhd", small_volume("uint8", SHAPE))
    path.write_text(path.read_text().replace("MET_UCHAR", "MET_FLOAT16"))
    assert "MET_UCHAR" in _error("v.mhd", path)


def test_nrrd_detached_corrupt_gzip(tmp_path):
    header = {"encoding": "gzip"}
    path = write_nrrd(
        tmp_path / "v.nhdr", small_volume("uint16", SHAPE), header, detached_header=True
    )
    data_file = next(p for p in tmp_path.iterdir() if p.name != "v.nhdr")
    blob = bytearray(data_file.read_bytes())
    data_file.write_bytes(bytes(blob[: len(blob) // 2]))  # truncated gzip stream
    _error("v.nhdr", path)


def test_nrrd_attached_gzip_with_flipped_bytes(tmp_path):
    path = write_nrrd(tmp_path / "v.nrrd", small_volume("uint16", SHAPE), {"encoding": "gzip"})
    blob = bytearray(path.read_bytes())
    start = blob.index(b"\n\n") + 2 + 10  # past the header and the gzip member header
    blob[start : start + 40] = bytes(40)
    path.write_bytes(bytes(blob))
    assert "corrupt" in _error("v.nrrd", path)


def test_nrrd_missing_data_file(tmp_path):
    path = write_nrrd(tmp_path / "v.nhdr", small_volume("uint8", SHAPE), detached_header=True)
    data_file = next(p for p in tmp_path.iterdir() if p.name != "v.nhdr")
    data_file.unlink()
    assert data_file.name in _error("v.nhdr", path)


def test_nifti_corrupt(tmp_path):
    path = tmp_path / "bad.nii.gz"
    path.write_bytes(gzip.compress(b"not a nifti header at all" * 20)[:-8])
    _error("bad.nii.gz", path)


def _damage_gzip_trailer(path, how: str) -> None:
    """Break only a gzip file's trailer: the deflate data still inflates to the full size,
    so a reader that stops at the data it needs sees nothing wrong; a CRC check does."""
    blob = bytearray(path.read_bytes())
    if how == "crc":
        blob[-8] ^= 0xFF  # CRC-32 of the data
    else:
        del blob[-4:]  # truncated: ISIZE lost
    path.write_bytes(bytes(blob))


@pytest.mark.parametrize("how, text", [("crc", "CRC check failed"), ("cut", "ended before")])
def test_nifti_gz_with_a_broken_gzip_trailer_is_an_error(tmp_path, how, text):
    path = write_nifti(tmp_path / "v.nii.gz", small_volume("uint16", SHAPE), np.eye(4))
    _damage_gzip_trailer(path, how)
    message = _error("v.nii.gz", path)
    assert "corrupt compressed" in message and text in message


@pytest.mark.parametrize("how", ["crc", "cut"])
def test_nrrd_gzip_with_a_broken_gzip_trailer_is_an_error(tmp_path, how):
    path = write_nrrd(tmp_path / "v.nrrd", small_volume("uint16", SHAPE), {"encoding": "gzip"})
    _damage_gzip_trailer(path, how)
    message = _error("v.nrrd", path)
    assert "corrupt compressed" in message


def test_nrrd_detached_gzip_with_a_lost_end_is_an_error(tmp_path):
    path = write_nrrd(tmp_path / "v.nhdr", small_volume("uint16", SHAPE), {"encoding": "gzip"},
                      detached_header=True)
    data_file = next(p for p in tmp_path.iterdir() if p.name != "v.nhdr")
    _damage_gzip_trailer(data_file, "cut")
    assert "corrupt compressed" in _error("v.nhdr", path)


def test_intact_compressed_volumes_still_load(tmp_path):
    vol = small_volume("uint16", SHAPE)
    nifti = write_nifti(tmp_path / "v.nii.gz", vol, np.eye(4))
    nrrd_gz = write_nrrd(tmp_path / "g.nrrd", vol, {"encoding": "gzip"})
    nrrd_bz2 = write_nrrd(tmp_path / "b.nrrd", vol, {"encoding": "bzip2"})
    for path in (nifti, nrrd_gz, nrrd_bz2):
        np.testing.assert_array_equal(load_volume(path).data, vol)


@pytest.mark.parametrize("keep", [0.5, -100])
def test_truncated_tiff_is_one_error_and_nothing_else_on_stderr(tmp_path, capsys, keep):
    path = write_tiff_stack(tmp_path / "t.tif", small_volume("uint8", (16, 32, 32)))
    blob = path.read_bytes()
    path.write_bytes(blob[: int(len(blob) * keep) if keep > 0 else keep])
    message = _error("t.tif", path)
    assert "invalid page offset" in message
    assert capsys.readouterr().err == ""  # tifffile's own log line is folded into the error


def test_folder_without_dicom(tmp_path):
    folder = tmp_path / "empty_series"
    folder.mkdir()
    (folder / "notes.txt").write_text("hello")
    assert "DICOM" in _error("empty_series", folder)


def test_dicom_missing_slice_detected(tmp_path):
    stored = small_volume("uint16", SHAPE) // 16
    folder = write_dicom_series(tmp_path / "gap", stored)
    files = sorted(folder.iterdir())
    import pydicom

    positions = {f: pydicom.dcmread(f).ImagePositionPatient[2] for f in files}
    middle = sorted(files, key=lambda f: positions[f])[4]
    middle.unlink()
    assert "evenly spaced" in _error("gap", folder)


def test_single_page_tiff_is_not_a_volume(tmp_path):
    path = write_tiff_stack(tmp_path / "flat.tif", small_volume("uint8", (10, 12)))
    assert "multi-page" in _error("flat.tif", path)


def test_unknown_extension_lists_formats(tmp_path):
    path = tmp_path / "mystery.xyz"
    path.write_bytes(b"\x00" * 100)
    message = _error("mystery.xyz", path)
    assert ".nrrd" in message and "DICOM" in message and "--dims" in message


def test_missing_file(tmp_path):
    _error("nowhere.nrrd", tmp_path / "nowhere.nrrd")


def test_unknown_builtin_lists_known():
    with pytest.raises(VolumeError) as info:
        load_volume("builtin:skull")
    assert "builtin:skull" in str(info.value)
    assert all(f"builtin:{n}" in str(info.value) for n in list_builtins())


def test_bad_orientation_code(tmp_path):
    with pytest.raises(VolumeError, match="LPS"):
        load_volume("builtin:sphere", orientation="LLS")


def test_dims_refused_for_self_describing_format(tmp_path):
    path = write_mha(tmp_path / "v.mha", small_volume("uint8", SHAPE))
    assert "--dims" in _error("v.mha", path, dims=DIMS)


# --------------------------------------------------------------------------
# built-in volumes
# --------------------------------------------------------------------------


def test_list_builtins():
    assert list_builtins() == ["head", "sphere", "tooth"]


@pytest.mark.parametrize(
    "name,shape,modality",
    [
        ("head", (144, 136, 112), "ct"),
        ("tooth", (160, 104, 120), "tooth"),
        ("sphere", (64, 64, 64), "generic"),
    ],
)
def test_builtin_shape_modality_and_determinism(name, shape, modality):
    a, b = load_volume(f"builtin:{name}"), load_volume(f"builtin:{name}")
    assert a.data.shape == shape and a.data.dtype == np.float32 and a.modality == modality
    assert a.data is not b.data
    np.testing.assert_array_equal(a.data, b.data)
    a.data[0, 0, 0] = 12345.0  # callers get their own copy
    assert load_volume(f"builtin:{name}").data[0, 0, 0] != 12345.0


def test_builtin_is_deterministic_across_builds():
    from host.volume.phantoms import _build_tooth

    first, _ = _build_tooth()
    second, _ = _build_tooth()
    np.testing.assert_array_equal(first, second)


def test_head_has_a_bone_shell_around_the_brain():
    vol = load_volume("builtin:head")
    assert vol.metadata["units"] == "HU"
    data, (sx, sy, sz) = vol.data, vol.spacing
    nz, ny, nx = data.shape
    centre = np.array([(nx - 1) / 2, (ny - 1) / 2 - 10 / sy, (nz - 1) / 2 + 40 / sz])  # mid-brain
    assert 0.0 <= data[tuple(np.round(centre[::-1]).astype(int))] <= 60.0
    directions = [(1, 0, 0), (-1, 0, 0), (0, 1, 0.3), (0, -1, 0), (0, 0, 1), (0.6, -0.6, 0.5)]
    for d in directions:
        d = np.array(d) / np.linalg.norm(d)
        profile = []
        for r in np.arange(0.0, 150.0, 0.5):  # walk outwards in mm
            p = centre + d * r / np.array([sx, sy, sz])
            if np.any(p < 0) or np.any(p > np.array([nx, ny, nz]) - 1):
                break
            profile.append(data[tuple(np.round(p[::-1]).astype(int))])
        profile = np.array(profile)
        first_bone = int(np.argmax(profile > 600))
        first_air = int(np.argmax(profile < -500))
        assert profile[first_bone] > 600, f"no bone along {d}"
        assert 0 < first_bone < first_air, f"bone must enclose the brain along {d}"
        assert np.all(np.abs(profile[: first_bone - 8]) < 120), f"soft brain/CSF inside {d}"
    assert data[0, 0, 0] == pytest.approx(-1000.0, abs=20.0)  # air in the corner


def test_tooth_enamel_above_dentin_and_pulp_inside():
    data = load_volume("builtin:tooth").data
    enamel = _fg_centroid(data > 215)
    dentin = _fg_centroid((data > 140) & (data < 180))
    assert enamel[0] > 0.6 and enamel[0] > dentin[0] + 0.15
    pulp = (data > 45) & (data < 65)
    k, j, i = np.nonzero(pulp)
    assert pulp.sum() > 500
    # the pulp chamber's centre column is wrapped in dentin on all four sides
    kc, jc, ic = int(np.median(k)), int(np.median(j)), int(np.median(i))
    row = data[kc, jc, :]
    assert row[ic] < 80 and row[:ic].max() > 140 and row[ic:].max() > 140
    assert data[0, 0, 0] < 20 and data[-1, -1, -1] < 20  # background


def test_sphere_values():
    data = load_volume("builtin:sphere").data
    assert data[32, 32, 32] == 1.0 and data[0, 0, 0] == 0.0


def test_builtin_overrides():
    vol = load_volume("builtin:sphere", spacing=(2.0, 2.0, 2.0), modality="ct")
    assert vol.spacing == (2.0, 2.0, 2.0) and vol.modality == "ct"


# --------------------------------------------------------------------------
# CLI helpers and the Volume type
# --------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    parser.add_argument("volume")
    add_volume_arguments(parser)
    return parser


def test_volume_from_args_raw(tmp_path):
    src = small_volume("uint16", SHAPE)
    path = write_raw(tmp_path / "v.raw", src, "big")
    args = _parser().parse_args(
        [
            str(path),
            "--dims",
            "12,10,8",
            "--dtype",
            "uint16",
            "--endian",
            "big",
            "--spacing",
            "1,1,2.5",
        ]
    )
    vol = volume_from_args(args.volume, args)
    np.testing.assert_array_equal(vol.data, src)
    assert vol.spacing == (1.0, 1.0, 2.5)


@pytest.mark.parametrize("dims", ["12,10", "a,b,c", "12,10,8,4"])
def test_volume_from_args_bad_dims(tmp_path, dims):
    path = write_raw(tmp_path / "v.raw", small_volume("uint8", SHAPE))
    args = _parser().parse_args([str(path), "--dims", dims])
    with pytest.raises(VolumeError, match="--dims"):
        volume_from_args(args.volume, args)


def test_volume_geometry_properties():
    vol = Volume(np.zeros((3, 4, 5), dtype=np.float32), (1.0, 2.0, 0.5))
    assert vol.dims == (5, 4, 3)
    np.testing.assert_allclose(vol.extent_mm, [4.0, 6.0, 1.0])
    np.testing.assert_allclose(vol.center_mm, [2.0, 3.0, 0.5])


# --------------------------------------------------------------------------
# what the values say when the header says nothing about the modality
# --------------------------------------------------------------------------


def _ct_head(offset: float, dtype: str) -> np.ndarray:
    """A CT-like head in HU (+ ``offset``): air around it, soft tissue, a bone shell."""
    z, y, x = np.mgrid[:24, :28, :32].astype(np.float32)
    r = np.sqrt(((x - 15.5) / 12) ** 2 + ((y - 13.5) / 10) ** 2 + ((z - 11.5) / 9) ** 2)
    hu = np.where(r < 1.0, 40.0, -1000.0)
    hu = np.where((r > 0.75) & (r < 0.9), 1200.0, hu)
    return (hu + offset).astype(dtype)


@pytest.mark.parametrize("case", ["int16 HU raw", "uint16 HU+1024 dat", "float32 HU raw"])
def test_the_data_say_ct_when_the_header_is_silent(tmp_path, case):
    """A CT with no modality in its header (raw, volvis .dat) is recognised by its values:
    signed values with air at -1000 (Hounsfield units), or 16-bit ones with air at the
    bottom and soft tissue about 1040 above it (HU with an offset)."""
    if case.startswith("uint16"):
        path = write_dat(tmp_path / "scan.dat", _ct_head(1024.0, "uint16"))
        vol = load_volume(path)
    else:
        dtype = case.split()[0]
        path = write_raw(tmp_path / "scan.raw", _ct_head(0.0, dtype))
        vol = load_volume(path, dims=(32, 28, 24), dtype=dtype)
    assert vol.modality == "ct"
    assert vol.metadata["modality_source"] == "data"
    assert "Hounsfield" in vol.metadata["modality_note"]
    assert vol.metadata.get("units") == (None if case.startswith("uint16") else "HU")


@pytest.mark.parametrize("case", ["uint8 ct", "uint16 mri", "uint16 ramp"])
def test_data_that_do_not_say_ct_stay_generic(tmp_path, case):
    """8-bit data (an industrial CT, a rescaled scan), a 16-bit MRI (tissue far from
    +1040 above air) and a plain ramp keep the generic look."""
    if case == "uint8 ct":
        data = ((_ct_head(1024.0, "float32") / 2224.0) * 255).astype(np.uint8)
    elif case == "uint16 mri":
        data = (_ct_head(1000.0, "float32") * 0.3).astype(np.uint16)  # air 0, tissue ~312
    else:
        data = (np.arange(24 * 28 * 32) % 4000).astype(np.uint16).reshape(24, 28, 32)
    path = write_raw(tmp_path / "scan.raw", data)
    vol = load_volume(path, dims=(32, 28, 24), dtype=data.dtype.name)
    assert vol.modality == "generic" and vol.metadata["modality_source"] == "none"


def test_the_header_and_the_user_win_over_the_data(tmp_path):
    data = _ct_head(0.0, "int16")
    path = write_mhd(tmp_path / "scan.mhd", data, extra={"Modality": "MET_MOD_MR"})
    header = load_volume(path)
    assert header.modality == "mri" and header.metadata["modality_source"] == "header"
    raw = write_raw(tmp_path / "scan.raw", data)
    user = load_volume(raw, dims=(32, 28, 24), dtype="int16", modality="generic")
    assert user.modality == "generic" and user.metadata["modality_source"] == "user"


@pytest.mark.shared_data
def test_shared_cts_without_their_name_are_told_by_their_values(shared_path, tmp_path):
    """headsq (a uint16 CT in a .dat header) under another name is CT by its values; the
    engine (an 8-bit industrial CT with no soft tissue) stays generic."""
    headsq = shared_path("headsq")
    text = headsq.read_text().replace("headsq.raw", "scan.raw")
    (tmp_path / "scan.dat").write_text(text)
    (tmp_path / "scan.raw").write_bytes((headsq.parent / "headsq.raw").read_bytes())
    vol = load_volume(tmp_path / "scan.dat")
    assert vol.modality == "ct" and vol.metadata["modality_source"] == "data", vol.metadata
    engine = load_volume(shared_path("engine"))
    assert engine.modality == "generic" and engine.metadata["modality_source"] == "none"


# --------------------------------------------------------------------------
# NumPy arrays
# --------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_numpy_volumes_round_trip_with_spacing(tmp_path, suffix):
    """.npy and .npz were refused ("unknown volume format"); a numpy user's array [z, y, x]
    loads as it is, with --spacing in x, y, z."""
    data = small_volume("int16")
    path = tmp_path / f"vol{suffix}"
    if suffix == ".npy":
        np.save(path, data)
    else:
        np.savez_compressed(path, data)
    vol = load_volume(path, spacing=(0.5, 0.75, 2.0))
    np.testing.assert_array_equal(vol.data, data.astype(np.float32))
    assert vol.spacing == (0.5, 0.75, 2.0)
    assert vol.metadata["format"] == suffix[1:] and vol.metadata["file_dims"] == list(DIMS)
    assert load_volume(path).spacing == (1.0, 1.0, 1.0)  # nothing says otherwise


def test_numpy_volume_through_the_command_line_options(tmp_path):
    path = tmp_path / "scan.npy"
    np.save(path, small_volume("float32"))
    args = argparse.Namespace(spacing="1,2,3", dims=None, dtype=None, endian="little",
                              orientation=None, modality=None)
    assert volume_from_args(str(path), args).spacing == (1.0, 2.0, 3.0)
    renamed = tmp_path / "scan.data"  # no extension: the .npy magic bytes say what it is
    renamed.write_bytes(path.read_bytes())
    assert load_volume(renamed).data.shape == SHAPE


@pytest.mark.parametrize("case, message", [
    ("several", "holds 3 arrays (a, b, mask)"),
    ("2d", "shape (10, 12): a volume is a 3-D array"),
    ("objects", "Python objects"),
    ("truncated", "cannot read .npy"),
])
def test_numpy_volumes_that_are_not_one_3d_array_are_one_line(tmp_path, case, message):
    path = tmp_path / ("v.npz" if case == "several" else "v.npy")
    if case == "several":
        np.savez(path, a=small_volume(), b=small_volume(), mask=small_volume())
    elif case == "2d":
        np.save(path, np.zeros((10, 12), np.uint8))
    elif case == "objects":
        np.save(path, np.array([[[None, 1], [2, 3]]] * 2, dtype=object), allow_pickle=True)
    else:
        np.save(path, small_volume())
        path.write_bytes(path.read_bytes()[:-50])
    with pytest.raises(VolumeError) as caught:
        load_volume(path)
    text = str(caught.value)
    assert "\n" not in text and text.startswith(str(path)) and message in text, text


def test_a_boolean_mask_loads_as_zeros_and_ones(tmp_path):
    path = tmp_path / "mask.npy"
    mask = small_volume("uint8") > 100
    np.save(path, mask)
    np.testing.assert_array_equal(load_volume(path).data, mask.astype(np.float32))
