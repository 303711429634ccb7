"""NIfTI ``.nii`` / ``.nii.gz`` through nibabel."""

from __future__ import annotations

import gzip
import zlib
from pathlib import Path

import numpy as np

from host.volume.core import (
    _check_spacing,
    _fail,
    _Loaded,
    _one_line,
    _read_head,
    _verify_compressed,
)


def _load_nifti(path: Path) -> _Loaded:
    import nibabel as nib
    from nibabel.filebasedimages import ImageFileError

    if _read_head(path, 2) == b"\x1f\x8b":  # .nii.gz: nibabel reads lazily, never the CRC
        try:
            with open(path, "rb") as fh:
                _verify_compressed(fh, "gzip", path, "data")
        except OSError as exc:
            raise _fail(path, f"cannot read NIfTI: {exc.strerror or _one_line(exc)}") from None
    try:
        img = nib.load(str(path))
        canonical = nib.as_closest_canonical(img)
        data = np.asanyarray(canonical.dataobj)
        slope, inter = (
            img.header.get_slope_inter()
            if hasattr(img.header, "get_slope_inter")
            else (
                None,
                None,
            )
        )
        zooms = canonical.header.get_zooms()
    except (zlib.error, EOFError, gzip.BadGzipFile) as exc:
        raise _fail(path, f"corrupt compressed data: {_one_line(exc)}") from None
    except (ImageFileError, ValueError, TypeError, KeyError) as exc:
        raise _fail(path, f"cannot read NIfTI: {_one_line(exc)}") from None
    except OSError as exc:
        raise _fail(path, f"cannot read NIfTI: {exc.strerror or _one_line(exc)}") from None
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise _fail(path, f"NIfTI image has shape {data.shape}: only 3-D scalar volumes")
    data = np.transpose(data, (2, 1, 0))  # nibabel gives (x, y, z)
    sp = _check_spacing(zooms[:3], path, "pixdim")
    extra = {}
    if slope not in (None, 1.0) or inter not in (None, 0.0):
        extra["rescale"] = [float(slope or 1.0), float(inter or 0.0)]
    return _Loaded(data, sp, "nifti", file_axes="RAS", modality="mri", extra=extra)
