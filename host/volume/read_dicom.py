"""A DICOM series folder (or one ``.dcm`` file of it) through pydicom."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from host.volume.core import (
    _check_dims,
    _fail,
    _Loaded,
    _one_line,
)
from host.volume.orientation import (
    _axis_code_from_directions,
)


def _first_dicom(files: list[Path]) -> Path | None:
    import pydicom
    from pydicom.errors import InvalidDicomError

    for p in files[:50]:
        try:
            ds = pydicom.dcmread(p, stop_before_pixels=True, force=False)
        except (InvalidDicomError, OSError, ValueError, EOFError, KeyError, TypeError):
            continue
        if "SOPClassUID" in ds or "ImagePositionPatient" in ds or "Rows" in ds:
            return p
    return None


def _load_dicom(path: Path) -> _Loaded:
    folder = path if path.is_dir() else path.parent
    headers = _series_headers(path, folder)
    first = headers[0][1]
    rows, cols = int(first.Rows), int(first.Columns)
    have_geometry = all(
        "ImagePositionPatient" in ds and "ImageOrientationPatient" in ds for _, ds in headers
    )
    file_axes = None
    if have_geometry:
        order, sz, file_axes = _slice_geometry(headers, folder)
    else:
        numbers = [int(ds.get("InstanceNumber", i)) for i, (_, ds) in enumerate(headers)]
        order = np.argsort(numbers, kind="stable")
        sz = float(first.get("SpacingBetweenSlices", first.get("SliceThickness", 1.0)) or 1.0)
    pixel = first.get("PixelSpacing", [1.0, 1.0])
    sy, sx = float(pixel[0]), float(pixel[1])  # (between rows, between columns)
    volume = _read_slices(headers, order, rows, cols)

    modality_tag = str(first.get("Modality", "")).upper()
    modality = {"CT": "ct", "MR": "mri"}.get(modality_tag)
    name = str(first.get("SeriesDescription", "") or folder.name).strip() or folder.name
    name = re.sub(r"\s+", "_", name)
    return _Loaded(
        volume,
        (sx, sy, sz),
        "dicom",
        file_axes=file_axes,
        modality=modality,
        units="HU" if modality == "ct" else None,
        name=name,
        extra={"slices": len(headers), "dicom_modality": modality_tag},
    )


def _series_headers(path: Path, folder: Path) -> list[tuple[Path, Any]]:
    """The headers of the one series' image files (the series of ``path`` when it is a
    file), checked: one series, greyscale, one slice per file, 2 slices at least, every
    slice the first's size."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    only_series = None
    if path.is_file():
        try:
            only_series = str(pydicom.dcmread(path, stop_before_pixels=True).SeriesInstanceUID)
        except (InvalidDicomError, AttributeError, OSError, ValueError, EOFError) as exc:
            raise _fail(path, f"not a readable DICOM file: {_one_line(exc)}") from None
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    headers = []
    for p in files:
        try:
            ds = pydicom.dcmread(p, stop_before_pixels=True)
        except InvalidDicomError:
            continue
        except (OSError, ValueError, EOFError, KeyError, TypeError, AttributeError) as exc:
            raise _fail(p, f"corrupt DICOM file: {_one_line(exc)}") from None
        if "Rows" not in ds or "Columns" not in ds:
            continue  # DICOMDIR, structured reports ...
        if only_series is not None and str(ds.get("SeriesInstanceUID", "")) != only_series:
            continue
        headers.append((p, ds))
    if not headers:
        raise _fail(folder, f"no DICOM image files in this folder ({len(files)} files checked)")
    series = sorted({str(ds.get("SeriesInstanceUID", "")) for _, ds in headers})
    if len(series) > 1:
        raise _fail(
            folder,
            f"holds {len(series)} DICOM series; pass one of its .dcm files to pick a series "
            "or keep one series per folder",
        )
    first = headers[0][1]
    if int(first.get("NumberOfFrames", 1) or 1) > 1:
        raise _fail(headers[0][0], "multi-frame DICOM is not supported (one slice per file)")
    if int(first.get("SamplesPerPixel", 1)) != 1:
        raise _fail(headers[0][0], "colour DICOM is not supported: only greyscale slices")
    if len(headers) < 2:
        raise _fail(folder, "DICOM series has one slice; a volume needs at least 2")
    rows, cols = int(first.Rows), int(first.Columns)
    _check_dims((cols, rows, len(headers)), folder, "series size (columns, rows, slices)")
    for p, ds in headers:
        if (int(ds.Rows), int(ds.Columns)) != (rows, cols):
            raise _fail(
                p, f"slice is {ds.Columns}x{ds.Rows} but the series' first is {cols}x{rows}"
            )
    return headers


def _slice_geometry(headers: list[tuple[Path, Any]], folder: Path
                    ) -> tuple[np.ndarray, float, str]:
    """From the slices' positions and orientation: their order along the normal, the
    (even) spacing between them and the file's axis code (LPS directions)."""
    first = headers[0][1]
    iop = np.array([float(v) for v in first.ImageOrientationPatient], dtype=np.float64)
    if iop.size != 6:
        raise _fail(headers[0][0], f"ImageOrientationPatient has {iop.size} values, not 6")
    row_dir, col_dir = iop[:3], iop[3:]
    normal = np.cross(row_dir, col_dir)
    if np.linalg.norm(normal) < 1e-6:
        raise _fail(headers[0][0], "ImageOrientationPatient rows/columns are parallel")
    normal /= np.linalg.norm(normal)
    positions = np.array(
        [[float(v) for v in ds.ImagePositionPatient] for _, ds in headers], dtype=np.float64
    )
    depth = positions @ normal
    order = np.argsort(depth, kind="stable")
    depth = depth[order]
    gaps = np.diff(depth)
    if np.any(gaps < 1e-4):
        dup = headers[int(order[int(np.argmin(gaps)) + 1])][0]
        raise _fail(dup, "two slices of the series share one position (duplicate slice?)")
    sz = float(np.mean(gaps))
    if gaps.max() - gaps.min() > max(0.01 * sz, 1e-3):
        raise _fail(
            folder,
            f"slice positions are not evenly spaced (gaps {gaps.min():.4g} to "
            f"{gaps.max():.4g} mm): a missing slice or a tilted gantry",
        )
    return order, sz, _axis_code_from_directions(np.stack([row_dir, col_dir, normal]), "LPS")


def _read_slices(headers: list[tuple[Path, Any]], order: np.ndarray, rows: int, cols: int
                 ) -> np.ndarray:
    """The slices' pixels in ``order``, rescaled (slope, intercept), as float32
    (slices, rows, cols)."""
    import pydicom

    volume = np.empty((len(headers), rows, cols), dtype=np.float32)
    for out_index, src in enumerate(order):
        p, ds = headers[int(src)]
        try:
            ds = pydicom.dcmread(p)
            pixels = ds.pixel_array
        except Exception as exc:  # pydicom raises many types for undecodable pixel data
            syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", "?")
            raise _fail(
                p, f"cannot decode pixel data (transfer syntax {syntax}): {_one_line(exc)}"
            ) from None
        if pixels.shape != (rows, cols):
            raise _fail(p, f"pixel data has shape {pixels.shape}, expected {(rows, cols)}")
        slope = float(ds.get("RescaleSlope", 1.0) or 1.0)
        intercept = float(ds.get("RescaleIntercept", 0.0) or 0.0)
        volume[out_index] = pixels.astype(np.float32) * np.float32(slope) + np.float32(intercept)
    return volume
