"""`load_volume`: a path or ``builtin:NAME`` in, a `Volume` in RAS order out.

Detects the format (extension, folder contents, magic bytes), hands the file to its reader
through the `READERS` registry, then applies orientation (`host.volume.orientation`) and the
caller's overrides. Also the ``--dims --dtype ...`` command-line options every command taking
a VOLUME shares (`add_volume_arguments`, `volume_from_args`). The conventions are in
`host.volume`.
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from host.errors import VolumeError
from host.volume.core import (
    MODALITIES,
    RAW_DTYPES,
    SUPPORTED_FORMATS,
    Volume,
    _check_spacing,
    _fail,
    _Loaded,
    _read_head,
)
from host.volume.modality import guess_modality
from host.volume.orientation import (
    KNOWN_DATASETS,
    KnownDataset,
    _parse_axis_code,
    _reorient_to_ras,
)
from host.volume.phantoms import builtin_volume
from host.volume.read_dat import _load_dat
from host.volume.read_dicom import _first_dicom, _load_dicom
from host.volume.read_metaimage import _load_metaimage
from host.volume.read_nifti import _load_nifti
from host.volume.read_nrrd import _load_nrrd
from host.volume.read_numpy import _load_npy, _load_npz
from host.volume.read_pvm import _load_pvm
from host.volume.read_raw import _load_raw
from host.volume.read_tiff import _load_tiff, _load_tiff_folder

__all__ = [
    "READERS",
    "add_volume_arguments",
    "load_volume",
    "volume_from_args",
]


def load_volume(
    spec: str | Path,
    *,
    dims: tuple[int, int, int] | None = None,
    dtype: str | None = None,
    endian: str = "little",
    spacing: tuple[float, float, float] | None = None,
    orientation: str | None = None,
    modality: str | None = None,
) -> Volume:
    """Load a volume from a file, a folder or ``builtin:NAME``.

    Parameters
    ----------
    spec : str or Path
        A path (format sniffed from the extension, folder contents or magic
        bytes) or ``builtin:NAME`` (see `list_builtins`).
    dims : (x, y, z) ints, optional
        Grid size of a raw file; required for raw data, refused for formats
        whose header declares it.
    dtype : str, optional
        Raw voxel type, one of `RAW_DTYPES` (default uint8); raw files only.
    endian : {"little", "big"}
        Byte order of raw files; ignored by self-describing formats.
    spacing : (sx, sy, sz) floats, optional
        Voxel size in mm, in the *file's* axis order; overrides the header.
    orientation : str, optional
        Axis code of the file's (+i, +j, +k), e.g. ``"LPI"``; overrides the
        header and `KNOWN_DATASETS` (see the module docstring).
    modality : {"ct", "mri", "tooth", "generic"}, optional
        Overrides the modality found from the header.

    Returns
    -------
    Volume
        ``data`` of shape (nz, ny, nx) float32 in RAS order when the
        orientation is known.

    Raises
    ------
    VolumeError
        One line naming the file and the problem.
    """
    spec_text = str(spec)
    if endian not in ("little", "big"):
        raise VolumeError(f"endian={endian!r} must be 'little' or 'big'")
    if modality is not None and modality not in MODALITIES:
        raise VolumeError(f"modality={modality!r} must be one of {', '.join(MODALITIES)}")
    code = _parse_axis_code(orientation) if orientation is not None else None
    if spec_text.startswith("builtin:"):
        if dims is not None or dtype is not None:
            raise VolumeError(f"{spec_text}: --dims/--dtype apply only to raw files")
        vol = builtin_volume(spec_text[len("builtin:") :])
        if spacing is not None or code is not None or modality is not None:
            vol = _apply_overrides(vol, spacing, code, modality)
        return vol

    path = Path(spec_text).expanduser()
    if not path.exists():
        raise VolumeError(f"{path}: no such file or folder")
    fmt = _detect_format(path, dims is not None)
    if fmt != "raw" and (dims is not None or dtype is not None):
        raise _fail(path, f"--dims/--dtype apply only to raw files; this is {fmt} with a header")
    if fmt == "raw":
        if dims is None:
            raise _fail(path, "raw data needs --dims X,Y,Z (and --dtype, --endian, --spacing)")
        loaded = _load_raw(path, dims, dtype or "uint8", endian)
    else:
        loaded = READERS[fmt](path)
    return _finish(path, loaded, spacing, code, modality)


def _apply_overrides(
    vol: Volume,
    spacing: tuple[float, float, float] | None,
    code: str | None,
    modality: str | None,
) -> Volume:
    data, sp = vol.data, vol.spacing
    meta = json.loads(json.dumps(vol.metadata))
    if spacing is not None:
        sp = _check_spacing(spacing, vol.source)
    if code is not None:
        data, sp = _reorient_to_ras(data, sp, code)
        meta["orientation"] = {"file_axes": code, "source": "user", "note": ""}
    if modality is not None:
        meta["modality_source"] = "user"
        meta.pop("modality_note", None)
    return Volume(
        np.ascontiguousarray(data),
        sp,
        name=vol.name,
        modality=modality or vol.modality,
        source=vol.source,
        metadata=meta,
    )


def _finish(
    path: Path,
    loaded: _Loaded,
    spacing: tuple[float, float, float] | None,
    code: str | None,
    modality: str | None,
) -> Volume:
    data = loaded.data
    if data.ndim != 3:
        raise _fail(path, f"expected a 3-D scalar volume, got an array of shape {data.shape}")
    file_dims = (int(data.shape[2]), int(data.shape[1]), int(data.shape[0]))
    if min(file_dims) < 2:
        raise _fail(path, f"dims {file_dims} (x, y, z): every side must be >= 2 voxels")
    if not np.issubdtype(data.dtype, np.number) or np.issubdtype(data.dtype, np.complexfloating):
        raise _fail(path, f"voxel type {data.dtype} is not a real scalar")
    file_dtype = str(data.dtype.name)
    sp = _check_spacing(spacing, path) if spacing is not None else loaded.spacing
    sp = _check_spacing(sp, path, "spacing from the header")
    name = loaded.name or _stem(path)
    known = KNOWN_DATASETS.get((name.lower(), file_dims, file_dtype))

    note = ""
    if code is not None:
        file_axes, source = code, "user"
    elif loaded.file_axes is not None:
        file_axes, source = loaded.file_axes, "header"
    elif known is not None:
        file_axes, source, note = known.file_axes, "known-dataset", known.note
    else:
        file_axes, source = "RAS", "none"
        note = "no orientation metadata; file order kept (+z taken as up)"
    oriented, sp = _reorient_to_ras(data, sp, file_axes)
    values = np.ascontiguousarray(oriented, dtype=np.float32)
    if not np.all(np.isfinite(values)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        raise _fail(path, f"{bad} voxels are NaN or infinite")

    mod, mod_source, mod_note, units = _modality(modality, loaded, known, values, file_dtype)
    metadata = {
        "format": loaded.fmt,
        "file_dims": list(file_dims),
        "file_dtype": file_dtype,
        "value_range": [float(values.min()), float(values.max())],
        "orientation": {"file_axes": file_axes, "source": source, "note": note},
        "modality_source": mod_source,
    }
    if mod_note:
        metadata["modality_note"] = mod_note
    if units:
        metadata["units"] = units
    metadata.update(loaded.extra)
    return Volume(values, sp, name=name, modality=mod, source=str(path), metadata=metadata)


def _modality(
    modality: str | None,
    loaded: _Loaded,
    known: KnownDataset | None,
    values: np.ndarray,
    file_dtype: str,
) -> tuple[str, str, str, str | None]:
    """``(modality, source, note, units)``: the caller's, the header's, a known dataset's, or
    what the values say (`guess_modality`: CT only); ``generic`` when nothing says."""
    if modality is not None:
        return modality, "user", "", loaded.units
    if loaded.modality is not None:
        return loaded.modality, "header", "", loaded.units
    if known is not None:
        return known.modality, "known-dataset", known.note, loaded.units
    guess = guess_modality(values, file_dtype)
    if guess is not None:
        mod, units, why = guess
        return mod, "data", why, loaded.units or units
    return "generic", "none", "", loaded.units


def _stem(path: Path) -> str:
    name = path.name
    for suffix in (".nii.gz", ".raw.gz", ".gz"):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return path.stem if path.is_file() else name


# --------------------------------------------------------------------------
# format detection
# --------------------------------------------------------------------------

_EXTENSIONS = {
    ".mhd": "metaimage",
    ".mha": "metaimage",
    ".nrrd": "nrrd",
    ".nhdr": "nrrd",
    ".nii": "nifti",
    ".nii.gz": "nifti",
    ".dcm": "dicom",
    ".tif": "tiff",
    ".tiff": "tiff",
    ".dat": "dat",
    ".pvm": "pvm",
    ".npy": "npy",
    ".npz": "npz",
    ".raw": "raw",
    ".raw.gz": "raw",
    ".bin": "raw",
}


def _detect_format(path: Path, have_dims: bool) -> str:
    if path.is_dir():
        return _detect_folder(path)
    lower = path.name.lower()
    for ext in sorted(_EXTENSIONS, key=len, reverse=True):
        if lower.endswith(ext):
            return _EXTENSIONS[ext]
    if have_dims:
        return "raw"
    head = _read_head(path, 512)
    sniffed = _sniff_magic(head)
    if sniffed:
        return sniffed
    ext = path.suffix or "(none)"
    raise _fail(
        path,
        f"unknown volume format (extension {ext}); supported: {SUPPORTED_FORMATS}",
    )


def _sniff_magic(head: bytes) -> str | None:
    if head.startswith(b"NRRD"):
        return "nrrd"
    if len(head) >= 348 and head[344:347] in (b"n+1", b"ni1"):
        return "nifti"
    if len(head) >= 132 and head[128:132] == b"DICM":
        return "dicom"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if head.startswith((b"PVM", b"DDS v3")):
        return "pvm"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    text = head.lstrip()
    if text.startswith((b"ObjectType", b"NDims")):
        return "metaimage"
    if text.startswith(b"ObjectFileName"):
        return "dat"
    return None


def _detect_folder(path: Path) -> str:
    files = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise _fail(path, "folder is empty: no DICOM series or TIFF slices in it")
    for p in files:
        head = _read_head(p, 132)
        if (len(head) >= 132 and head[128:132] == b"DICM") or p.suffix.lower() == ".dcm":
            return "dicom"
    if any(p.suffix.lower() in (".tif", ".tiff") for p in files):
        return "tiff-folder"
    # DICOM files without the 128-byte preamble: let pydicom decide
    if _first_dicom(files) is not None:
        return "dicom"
    raise _fail(
        path,
        f"folder holds no DICOM files and no .tif/.tiff slices ({len(files)} other files)",
    )


#: The reader registry: format name (from `_detect_format`) -> reader. A new format is a
#: ``read_NAME.py`` module, an entry here, its extensions/magic in `_detect_format`.
READERS: dict[str, Callable[[Path], _Loaded]] = {
    "dat": _load_dat,
    "metaimage": _load_metaimage,
    "nrrd": _load_nrrd,
    "nifti": _load_nifti,
    "dicom": _load_dicom,
    "tiff": _load_tiff,
    "tiff-folder": _load_tiff_folder,
    "pvm": _load_pvm,
    "npy": _load_npy,
    "npz": _load_npz,
}


# --------------------------------------------------------------------------
# command-line helpers
# --------------------------------------------------------------------------


def add_volume_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--dims --dtype --endian --spacing --orientation --modality`` to ``parser``.

    Every command taking a VOLUME uses these; pair with `volume_from_args`.
    """
    group = parser.add_argument_group(
        "volume options", "raw files need --dims; the others override the file's header"
    )
    group.add_argument("--dims", metavar="X,Y,Z", help="grid size of a raw file")
    group.add_argument(
        "--dtype", choices=sorted(RAW_DTYPES), help="voxel type of a raw file (default uint8)"
    )
    group.add_argument(
        "--endian",
        choices=("little", "big"),
        default="little",
        help="byte order of a raw file (default little)",
    )
    group.add_argument("--spacing", metavar="SX,SY,SZ", help="voxel size in mm (file axis order)")
    group.add_argument(
        "--orientation",
        metavar="CODE",
        help="where the file's +x,+y,+z point, e.g. LPS or LPI; the volume is turned so +z is up",
    )
    group.add_argument(
        "--modality", choices=MODALITIES, help="override the modality (picks the default --tf)"
    )


def _parse_triple(text: object, option: str, kind: type) -> tuple | None:
    if text is None:
        return None
    if isinstance(text, (tuple, list)):
        values = list(text)
    else:
        values = [v for v in re.split(r"[,x\s]+", str(text).strip()) if v]
    try:
        out = tuple(kind(v) for v in values)
    except (TypeError, ValueError):
        raise VolumeError(f"{option} {text!r} must be three {kind.__name__}s like 1,2,3") from None
    if len(out) != 3:
        raise VolumeError(f"{option} {text!r} must have three values (x, y, z), got {len(out)}")
    return out


def volume_from_args(spec: str, args: argparse.Namespace) -> Volume:
    """Load ``spec`` with the options `add_volume_arguments` added to ``args``."""
    dims = _parse_triple(getattr(args, "dims", None), "--dims", int)
    spacing = _parse_triple(getattr(args, "spacing", None), "--spacing", float)
    return load_volume(
        spec,
        dims=dims,
        dtype=getattr(args, "dtype", None),
        endian=getattr(args, "endian", None) or "little",
        spacing=spacing,
        orientation=getattr(args, "orientation", None),
        modality=getattr(args, "modality", None),
    )
