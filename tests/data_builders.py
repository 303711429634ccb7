"""Write tiny volume files in every supported format, for loader tests.

Every writer takes ``data`` of shape (nz, ny, nx) -- x fastest, as on disk --
and returns the path to pass to `host.volume.load_volume`. The writers use the
format's own library (pynrrd, nibabel, tifffile, pydicom) or the format's
documented text header, never eigencast's loaders.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

__all__ = [
    "small_volume",
    "write_dat",
    "write_dicom_series",
    "write_mha",
    "write_mhd",
    "write_nifti",
    "write_nrrd",
    "write_pvm",
    "write_raw",
    "write_tiff_folder",
    "write_tiff_stack",
]

_MET = {
    "uint8": "MET_UCHAR",
    "int8": "MET_CHAR",
    "uint16": "MET_USHORT",
    "int16": "MET_SHORT",
    "uint32": "MET_UINT",
    "int32": "MET_INT",
    "float32": "MET_FLOAT",
    "float64": "MET_DOUBLE",
}


def small_volume(dtype: str = "uint16", shape: tuple[int, int, int] = (8, 10, 12), seed: int = 0):
    """Random (nz, ny, nx) array of ``dtype`` with distinct-looking values."""
    rng = np.random.default_rng(seed)
    if np.dtype(dtype).kind == "f":
        return rng.normal(0.0, 100.0, size=shape).astype(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, endpoint=True).astype(dtype)


def write_raw(path: Path, data: np.ndarray, endian: str = "little") -> Path:
    """Headerless voxels, x fastest, in the given byte order."""
    order = "<" if endian == "little" else ">"
    data.astype(data.dtype.newbyteorder(order)).tofile(path)
    return path


def _mhd_header(data: np.ndarray, spacing, extra: dict[str, str], big_endian: bool) -> str:
    nz, ny, nx = data.shape
    lines = {
        "ObjectType": "Image",
        "NDims": "3",
        "BinaryData": "True",
        "BinaryDataByteOrderMSB": "True" if big_endian else "False",
        "DimSize": f"{nx} {ny} {nz}",
        "ElementSpacing": " ".join(str(s) for s in spacing),
        "ElementType": _MET[data.dtype.name],
    }
    lines.update(extra)
    return "".join(f"{k} = {v}\n" for k, v in lines.items())


def write_mhd(
    path: Path,
    data: np.ndarray,
    spacing=(1.0, 1.0, 1.0),
    *,
    compressed: bool = False,
    big_endian: bool = False,
    extra: dict[str, str] | None = None,
    data_name: str | None = None,
) -> Path:
    """MetaImage header + separate data file (optionally zlib-compressed)."""
    data_name = data_name or path.with_suffix(".raw").name
    payload = data.astype(data.dtype.newbyteorder(">" if big_endian else "<")).tobytes()
    fields = dict(extra or {})
    if compressed:
        payload = zlib.compress(payload)
        fields["CompressedData"] = "True"
        fields["CompressedDataSize"] = str(len(payload))
    fields["ElementDataFile"] = data_name
    path.write_text(_mhd_header(data, spacing, fields, big_endian))
    (path.parent / data_name).write_bytes(payload)
    return path


def write_mha(path: Path, data: np.ndarray, spacing=(1.0, 1.0, 1.0)) -> Path:
    """MetaImage with the data in the same file (ElementDataFile = LOCAL)."""
    header = _mhd_header(data, spacing, {"ElementDataFile": "LOCAL"}, False)
    path.write_bytes(header.encode() + data.astype(data.dtype.newbyteorder("<")).tobytes())
    return path


def write_nrrd(path: Path, data: np.ndarray, header: dict | None = None, **kwargs) -> Path:
    """NRRD via pynrrd; ``.nhdr`` paths get a detached data file."""
    import nrrd

    nrrd.write(str(path), data, header=header or {}, index_order="C", **kwargs)
    return path


def write_nifti(path: Path, data: np.ndarray, affine: np.ndarray, slope_inter=None) -> Path:
    """NIfTI-1 via nibabel; ``affine`` maps (i, j, k) to RAS mm."""
    import nibabel as nib

    img = nib.Nifti1Image(np.transpose(data, (2, 1, 0)), affine)
    if slope_inter is not None:
        img.header.set_slope_inter(*slope_inter)
    nib.save(img, str(path))
    return path


def write_tiff_stack(path: Path, data: np.ndarray, **kwargs) -> Path:
    """Multi-page TIFF via tifffile, one page per z."""
    import tifffile

    tifffile.imwrite(str(path), data, **kwargs)
    return path


def write_tiff_folder(folder: Path, data: np.ndarray) -> Path:
    """One single-page TIFF per z slice, numbered without zero padding."""
    import tifffile

    folder.mkdir(parents=True, exist_ok=True)
    for k, plane in enumerate(data):
        tifffile.imwrite(str(folder / f"slice_{k + 1}.tif"), plane)
    return folder


def write_dat(path: Path, data: np.ndarray, spacing=(1.0, 1.0, 1.0)) -> Path:
    """volvis text header (``Key: value``) plus little-endian raw data."""
    nz, ny, nx = data.shape
    fmt = {"uint8": "UCHAR", "uint16": "USHORT"}[data.dtype.name]
    raw_name = path.with_suffix(".raw").name
    path.write_text(
        f"ObjectFileName: {raw_name}\nTaggedFileName: ---\nResolution:     {nx} {ny} {nz}\n"
        f"SliceThickness: {' '.join(str(s) for s in spacing)}\nFormat:         {fmt}\n"
        "NbrTags:        0\nObjectType:     TEXTURE_VOLUME_OBJECT\nObjectModel:    I\n"
        "GridType:       EQUIDISTANT\n"
    )
    write_raw(path.parent / raw_name, data)
    return path


def write_pvm(path: Path, data: np.ndarray, spacing=(1.0, 1.0, 1.0)) -> Path:
    """Uncompressed PVM3: text header, 8-bit or big-endian 16-bit voxels, then strings."""
    nz, ny, nx = data.shape
    components = data.dtype.itemsize
    header = f"PVM3\n{nx} {ny} {nz}\n{' '.join(str(s) for s in spacing)}\n{components}\n"
    body = data.astype(data.dtype.newbyteorder(">")).tobytes()
    path.write_bytes(header.encode() + body + b"description\x00courtesy\x00\x00\x00")
    return path


def write_dicom_series(
    folder: Path,
    stored: np.ndarray,
    *,
    pixel_spacing=(0.7, 0.5),
    slice_spacing: float = 2.5,
    slope: float = 2.0,
    intercept: float = -1024.0,
    origin=(10.0, -20.0, 30.0),
    orientation=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0),
    modality: str = "CT",
    shuffle_seed: int | None = 0,
    positions=None,
) -> Path:
    """A CT-style series, one uint16 slice per file, written with pydicom.

    ``stored`` is (n_slices, rows, columns) uint16 in slice order along the
    normal ``row x column``; file names are shuffled so loaders must sort by
    ImagePositionPatient. ``pixel_spacing`` is DICOM's (row spacing, column
    spacing).
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    n, rows, cols = stored.shape
    row_dir = np.array(orientation[:3], dtype=float)
    col_dir = np.array(orientation[3:], dtype=float)
    normal = np.cross(row_dir, col_dir)
    if positions is None:
        positions = [np.array(origin) + k * slice_spacing * normal for k in range(n)]
    order = np.arange(n)
    if shuffle_seed is not None:
        order = np.random.default_rng(shuffle_seed).permutation(n)
    series_uid, study_uid = generate_uid(), generate_uid()
    for file_index, k in enumerate(order):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.Modality = modality
        ds.SeriesDescription = "test series"
        ds.InstanceNumber = int(k) + 1
        ds.ImagePositionPatient = [float(v) for v in positions[k]]
        ds.ImageOrientationPatient = [float(v) for v in orientation]
        ds.PixelSpacing = [float(v) for v in pixel_spacing]
        ds.SliceThickness = float(slice_spacing)
        ds.Rows, ds.Columns = rows, cols
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 0
        ds.RescaleSlope = slope
        ds.RescaleIntercept = intercept
        ds.PixelData = np.ascontiguousarray(stored[k], dtype="<u2").tobytes()
        ds.save_as(folder / f"IM{file_index:04d}.dcm", enforce_file_format=True)
    return folder
