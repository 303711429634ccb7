"""Volumes: the `Volume` type, file loaders and the built-in procedural volumes.

Conventions (shared by every host module):

* ``Volume.data`` has numpy shape ``(nz, ny, nx)`` -- x varies fastest in
  memory, as in every raw volume file -- dtype float32, C-contiguous, holding
  the scanner's values after any rescale (e.g. Hounsfield units for CT).
* ``Volume.spacing`` is ``(sx, sy, sz)`` in millimetres (x first).
* World coordinates: voxel ``data[k, j, i]`` sits at ``(i*sx, j*sy, k*sz)``;
  +z is "up" (superior for medical data) so an orbit camera with up = +z shows
  a head upright.

Orientation
-----------
Loaders bring every volume whose anatomy is known into **RAS** index order:
+x towards the patient's Right, +y Anterior, +z Superior (nibabel's
"closest canonical"). A file's own axes are described by a three-letter
*axis code* naming where +i, +j and +k point, e.g. ``"LPS"`` for DICOM/ITK
index order or ``"LPI"`` for a stack sliced from the top of the head down.
The code comes from, in order of precedence:

1. the caller (``orientation="LPI"``, CLI ``--orientation LPI``);
2. the file's header: NIfTI affine (via nibabel), NRRD ``space`` + ``space
   directions``, MetaImage ``AnatomicalOrientation`` or a non-identity
   ``TransformMatrix`` (ITK/LPS convention; an identity matrix is what every
   tool writes by default, so it is not taken as information), DICOM
   ``ImageOrientationPatient``;
3. `KNOWN_DATASETS`: a short table of well-known volumes without orientation
   metadata (the paper's tooth, the Visible Male head, ...), matched by file
   name stem, dims and dtype, each entry with the reason for its fix;
4. otherwise the file order is kept (code ``"RAS"`` assumed, recorded as
   ``metadata["orientation"]["source"] == "none"``).

Fixes from `KNOWN_DATASETS` are proper rotations (determinant +1): when a
header says nothing about left/right we never mirror.

Formats
-------
raw (any extension, ``dims`` given; ``.gz`` data is inflated), volvis ``.dat``
(text header, or the 6-byte binary TU Wien header), MetaImage ``.mhd``/``.mha``,
NRRD ``.nrrd``/``.nhdr``, NIfTI ``.nii``/``.nii.gz``, a DICOM series folder (or
one ``.dcm`` file of it), TIFF stacks (multi-page file or a folder of
single-page files) and uncompressed Roettger ``.pvm``. Every problem with a file
raises `VolumeError` with one line naming the file.

Built-in volumes
----------------
``builtin:head`` (CT-like phantom in HU, 112x136x144 at 1.6 mm, modality ct),
``builtin:tooth`` (two-rooted molar on the paper's tooth scale 0-255,
120x104x160 at 0.15 mm, crown up, modality tooth) and ``builtin:sphere``
(ball of ones, 64^3). Deterministic, float32, no files; see `list_builtins`.
"""

from __future__ import annotations

import argparse
import bz2
import contextlib
import functools
import gzip
import json
import logging
import re
import warnings
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from host.errors import VolumeError

__all__ = [
    "KNOWN_DATASETS",
    "MODALITIES",
    "RAW_DTYPES",
    "SUPPORTED_FORMATS",
    "Volume",
    "add_volume_arguments",
    "builtin_volume",
    "list_builtins",
    "load_volume",
    "volume_from_args",
]

MODALITIES = ("ct", "mri", "tooth", "generic")


@dataclass(frozen=True, eq=False)
class Volume:
    """A scalar volume on a regular grid.

    Parameters
    ----------
    data : ndarray of shape (nz, ny, nx), float32
        Scalar values (x fastest).
    spacing : tuple of 3 floats
        Voxel size ``(sx, sy, sz)`` in millimetres.
    name : str
        Short name for reports (``"tooth"``, ``"head"`` ...).
    modality : {"ct", "mri", "tooth", "generic"}
        Picks the default transfer function.
    source : str
        Where it came from (a path or ``builtin:NAME``), for provenance.
    metadata : dict
        JSON-able facts from the loader: ``format``, ``file_dims`` (x, y, z as
        stored), ``file_dtype``, ``value_range``, ``orientation`` (``file_axes``
        code, ``source``, ``note``), ``units`` (``"HU"`` when the values are
        Hounsfield units) and format-specific keys.
    """

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    name: str = "volume"
    modality: str = "generic"
    source: str = ""
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        data = np.ascontiguousarray(self.data, dtype=np.float32)
        if data.ndim != 3 or min(data.shape) < 2:
            raise ValueError(f"volume data must be 3-D with every side >= 2, got {data.shape}")
        spacing = tuple(float(s) for s in self.spacing)
        if len(spacing) != 3 or not all(np.isfinite(s) and s > 0 for s in spacing):
            raise ValueError(f"spacing must be 3 positive numbers, got {self.spacing}")
        if self.modality not in MODALITIES:
            raise ValueError(f"modality={self.modality!r} must be one of {MODALITIES}")
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "spacing", spacing)

    @property
    def dims(self) -> tuple[int, int, int]:
        """Grid size ``(nx, ny, nz)``."""
        nz, ny, nx = self.data.shape
        return nx, ny, nz

    @property
    def extent_mm(self) -> np.ndarray:
        """Physical size ``(x, y, z)`` of the box spanned by voxel centres."""
        return (np.array(self.dims, dtype=np.float64) - 1.0) * np.array(self.spacing)

    @property
    def center_mm(self) -> np.ndarray:
        """World position of the volume centre."""
        return self.extent_mm / 2.0

    @property
    def radius_mm(self) -> float:
        """Radius of the bounding sphere around `center_mm`."""
        return float(np.linalg.norm(self.extent_mm) / 2.0)

    @property
    def value_range(self) -> tuple[float, float]:
        """``(min, max)`` of `data` as Python floats."""
        return float(self.data.min()), float(self.data.max())


# --------------------------------------------------------------------------
# constants and small helpers
# --------------------------------------------------------------------------

#: dtypes accepted for raw files (``--dtype``), by name.
RAW_DTYPES: dict[str, str] = {
    "uint8": "u1",
    "int8": "i1",
    "uint16": "u2",
    "int16": "i2",
    "uint32": "u4",
    "int32": "i4",
    "float32": "f4",
    "float64": "f8",
}

#: Human-readable list of what `load_volume` reads, for error messages.
SUPPORTED_FORMATS = (
    "builtin:NAME, raw with --dims (.raw, .bin, .gz ...), volvis .dat, MetaImage .mhd/.mha, "
    "NRRD .nrrd/.nhdr, NIfTI .nii/.nii.gz, DICOM series folder or .dcm, "
    "TIFF stack .tif/.tiff or folder of TIFFs, Roettger .pvm"
)

_MAX_HEADER_BYTES = 1 << 20  # text headers longer than this are not headers
_MAX_VOXELS = 1 << 31  # refuse headers that declare absurd grids (8 GiB of float32)

_OPPOSITE = {"R": "L", "L": "R", "A": "P", "P": "A", "S": "I", "I": "S"}
_WORLD_AXIS = {"R": 0, "L": 0, "A": 1, "P": 1, "S": 2, "I": 2}
_POSITIVE = ("R", "A", "S")


def _fail(path: object, problem: str) -> VolumeError:
    """A `VolumeError` whose one line starts with the file."""
    return VolumeError(f"{path}: {problem}")


def _one_line(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def _check_dims(dims: tuple[int, ...], path: object, what: str = "dims") -> tuple[int, int, int]:
    if len(dims) != 3:
        raise _fail(path, f"{what}={tuple(dims)} must have 3 entries (x, y, z)")
    if any(int(d) < 2 for d in dims):
        raise _fail(path, f"{what}={tuple(dims)}: every side must be >= 2 voxels")
    out = tuple(int(d) for d in dims)
    if int(np.prod(out, dtype=np.int64)) > _MAX_VOXELS:
        raise _fail(path, f"{what}={out} declares more than {_MAX_VOXELS} voxels")
    return out  # type: ignore[return-value]


def _check_spacing(spacing: object, path: object, what: str = "spacing") -> tuple[float, ...]:
    try:
        values = tuple(float(s) for s in spacing)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise _fail(path, f"{what}={spacing!r} must be 3 positive numbers") from None
    if len(values) != 3 or not all(np.isfinite(s) and s > 0 for s in values):
        raise _fail(path, f"{what}={values} must be 3 positive numbers (mm)")
    return values


def _parse_axis_code(code: str, what: str = "orientation") -> str:
    """Validate a 3-letter axis code such as ``"LPS"``; return it upper-case."""
    text = str(code).strip().upper()
    if (
        len(text) != 3
        or any(c not in _WORLD_AXIS for c in text)
        or sorted(_WORLD_AXIS[c] for c in text) != [0, 1, 2]
    ):
        raise VolumeError(
            f"{what}={code!r} must be 3 letters naming where +x, +y, +z of the file point, "
            "one of R/L, one of A/P and one of S/I (e.g. LPS, RAS, LPI)"
        )
    return text


def _axis_code_from_directions(directions: np.ndarray, world: str) -> str:
    """Axis code of index axes whose world directions are the rows of ``directions``.

    ``world`` names the positive world axes, e.g. ``"LPS"`` for DICOM/ITK or
    ``"RAS"`` for NIfTI; each index axis gets the world axis it is most
    aligned with (greedy, largest cosine first, like nibabel's io_orientation).
    """
    d = np.asarray(directions, dtype=np.float64)
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    if d.shape != (3, 3) or not np.all(np.isfinite(d)) or np.any(norms == 0):
        raise ValueError(f"direction matrix must be 3x3 finite non-zero, got {d.tolist()}")
    d = np.abs(d / norms)
    letters = [""] * 3
    free_rows, free_cols = {0, 1, 2}, {0, 1, 2}
    while free_rows:
        best = max(((r, c) for r in free_rows for c in free_cols), key=lambda rc: d[rc])
        r, c = best
        sign = np.sign(np.asarray(directions, dtype=np.float64)[r, c])
        letters[r] = world[c] if sign >= 0 else _OPPOSITE[world[c]]
        free_rows.discard(r)
        free_cols.discard(c)
    return "".join(letters)


def _reorient_to_ras(
    data: np.ndarray, spacing: tuple[float, ...], code: str
) -> tuple[np.ndarray, tuple[float, float, float]]:
    """Transpose/flip ``data`` (file order (k, j, i)) so its axes are RAS.

    Parameters
    ----------
    data : ndarray of shape (nk, nj, ni)
    spacing : (si, sj, sk) in file axis order
    code : axis code of the file's (i, j, k)

    Returns
    -------
    data : ndarray of shape (nz, ny, nx), a view where possible
    spacing : (sx, sy, sz)
    """
    src_for_world = [0, 0, 0]
    for n, letter in enumerate(code):
        src_for_world[_WORLD_AXIS[letter]] = n
    # numpy axis of file axis n is 2 - n; output numpy axes are world (z, y, x)
    out = np.transpose(data, [2 - src_for_world[w] for w in (2, 1, 0)])
    flips = tuple(2 - w for w in range(3) if code[src_for_world[w]] not in _POSITIVE)
    if flips:
        out = np.flip(out, axis=flips)
    new_spacing = tuple(float(spacing[src_for_world[w]]) for w in range(3))
    return out, new_spacing  # type: ignore[return-value]


def _is_proper_rotation(code: str) -> bool:
    """True when going from ``code`` to RAS is a rotation (no mirror)."""
    m = np.zeros((3, 3))
    for n, letter in enumerate(code):
        m[n, _WORLD_AXIS[letter]] = 1.0 if letter in _POSITIVE else -1.0
    return bool(np.linalg.det(m) > 0)


# --------------------------------------------------------------------------
# well-known datasets without orientation metadata
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class KnownDataset:
    """Orientation and modality of a well-known volume that has no such metadata."""

    file_axes: str
    modality: str
    note: str


#: (lower-case file stem, file dims (x, y, z), dtype name) -> facts. Checked by
#: looking at maximum-intensity projections; every fix is a proper rotation.
KNOWN_DATASETS: dict[tuple[str, tuple[int, int, int], str], KnownDataset] = {
    ("tooth", (140, 120, 161), "uint8"): KnownDataset(
        "RPI",
        "tooth",
        "paper's Tooth: crown stored at z=0; rotated 180 deg about x so the crown is up",
    ),
    ("vismale_head", (128, 256, 256), "uint8"): KnownDataset(
        "RPI",
        "ct",
        "Visible Male head: slices run top of head -> neck and +y points posterior; "
        "rotated 180 deg about x (left/right unknown, not mirrored)",
    ),
    ("headsq", (64, 64, 93), "uint16"): KnownDataset(
        "LAI",
        "ct",
        "VTK headsq: slices run top of head -> neck (VTK examples use view-up -z), "
        "+y anterior; rotated 180 deg about y (not mirrored)",
    ),
    ("brainsmall", (128, 128, 84), "uint8"): KnownDataset(
        "PIR",
        "mri",
        "VolPack brainsmall: sagittal slices, +x posterior, +y inferior; rotated so the "
        "head is upright and faces +y (left/right unknown, not mirrored)",
    ),
}


# --------------------------------------------------------------------------
# the loader result before orientation, and the public entry point
# --------------------------------------------------------------------------


@dataclass
class _Loaded:
    """What a format reader returns: file-order data and what the header said."""

    data: np.ndarray  # (nk, nj, ni), any numeric dtype
    spacing: tuple[float, ...]  # (si, sj, sk)
    fmt: str
    file_axes: str | None = None  # from the header, None when it says nothing
    modality: str | None = None
    units: str | None = None
    name: str | None = None
    extra: dict = field(default_factory=dict)


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
        loaded = _READERS[fmt](path)
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

    mod = modality or (known.modality if known and loaded.modality is None else None)
    mod = mod or loaded.modality or "generic"
    metadata = {
        "format": loaded.fmt,
        "file_dims": list(file_dims),
        "file_dtype": file_dtype,
        "value_range": [float(values.min()), float(values.max())],
        "orientation": {"file_axes": file_axes, "source": source, "note": note},
    }
    if loaded.units:
        metadata["units"] = loaded.units
    metadata.update(loaded.extra)
    return Volume(values, sp, name=name, modality=mod, source=str(path), metadata=metadata)


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


def _read_head(path: Path, size: int) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(size)
    except OSError as exc:
        raise _fail(path, f"cannot read: {exc.strerror or _one_line(exc)}") from None


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


# --------------------------------------------------------------------------
# raw data
# --------------------------------------------------------------------------


def _decode_raw(
    payload: bytes | memoryview,
    dims: tuple[int, int, int],
    dtype: np.dtype,
    path: object,
    what: str = "data",
) -> np.ndarray:
    """Interpret ``payload`` as an (z, y, x) array; exact size or a clear error."""
    nx, ny, nz = dims
    need = nx * ny * nz * dtype.itemsize
    have = len(payload)
    if have != need:
        kind = "truncated" if have < need else "too long"
        raise _fail(
            path,
            f"{what} is {kind}: has {have} bytes, but dims {nx}x{ny}x{nz} of "
            f"{dtype.name} ({dtype.itemsize} bytes each) need {need} bytes",
        )
    return np.frombuffer(payload, dtype=dtype).reshape(nz, ny, nx)


def _raw_dtype(dtype: str, endian: str, path: object) -> np.dtype:
    key = str(dtype).lower()
    if key not in RAW_DTYPES:
        raise _fail(path, f"unknown dtype {dtype!r}; supported: {', '.join(RAW_DTYPES)}")
    return np.dtype(("<" if endian == "little" else ">") + RAW_DTYPES[key])


def _inflate(blob: bytes, path: object, what: str) -> bytes:
    """Inflate zlib or gzip data (auto-detected); corrupt data -> VolumeError."""
    try:
        d = zlib.decompressobj(wbits=47)  # 32 + 15: zlib or gzip header
        out = d.decompress(blob)
        out += d.flush()
    except zlib.error as exc:
        raise _fail(path, f"corrupt compressed {what}: {exc}") from None
    if not d.eof:
        raise _fail(path, f"corrupt compressed {what}: stream ends early (truncated)")
    return out


def _verify_compressed(fh: BinaryIO, codec: str, path: object, what: str) -> None:
    """Decompress ``fh`` from its position to the end, discarding the output, so that a
    corrupt stream (bad CRC, truncated, garbage after it) is an error.

    Readers that stop once they have the data they need (nibabel reads gzip lazily,
    pynrrd never looks at the gzip trailer) do not check the CRC; this full read does.
    ``codec``: ``"gzip"`` (all members) or ``"bzip2"``.
    """
    try:
        with (bz2.BZ2File(fh, mode="rb") if codec == "bzip2"
              else gzip.GzipFile(fileobj=fh, mode="rb")) as stream:
            while stream.read(1 << 22):
                pass
    except (OSError, EOFError, zlib.error, ValueError) as exc:  # BadGzipFile is an OSError
        raise _fail(path, f"corrupt compressed {what}: {_one_line(exc)}") from None


def _read_bytes(path: Path, what: str = "data file") -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise _fail(path, f"{what} not found") from None
    except OSError as exc:
        raise _fail(path, f"cannot read {what}: {exc.strerror or _one_line(exc)}") from None


def _load_raw(path: Path, dims: tuple[int, int, int], dtype: str, endian: str) -> _Loaded:
    dims = _check_dims(dims, path)
    np_dtype = _raw_dtype(dtype, endian, path)
    blob = _read_bytes(path)
    if blob[:2] == b"\x1f\x8b":
        blob = _inflate(blob, path, "gzip data")
    data = _decode_raw(blob, dims, np_dtype, path)
    return _Loaded(data, (1.0, 1.0, 1.0), "raw", extra={"endian": endian})


# --------------------------------------------------------------------------
# volvis .dat
# --------------------------------------------------------------------------

_DAT_FORMATS = {"UCHAR": "u1", "CHAR": "i1", "USHORT": "u2", "SHORT": "i2", "FLOAT": "f4"}


def _load_dat(path: Path) -> _Loaded:
    head = _read_head(path, _MAX_HEADER_BYTES)
    if not head.lstrip().startswith(b"ObjectFileName"):
        return _load_dat_binary(path)
    try:
        text = head.decode("ascii")
    except UnicodeDecodeError:
        raise _fail(path, "volvis .dat header is not ASCII text") from None
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if ":" in line:
            key, _, value = line.partition(":")
            fields[key.strip().lower()] = value.strip()
    for key in ("objectfilename", "resolution", "format"):
        if key not in fields:
            raise _fail(path, f".dat header lacks the {key!r} line")
    dims = _ints(fields["resolution"], path, "Resolution")
    dims = _check_dims(dims, path, "Resolution")
    sp = (1.0, 1.0, 1.0)
    if "slicethickness" in fields:
        sp = _check_spacing(_floats(fields["slicethickness"], path, "SliceThickness"), path)
    fmt = fields["format"].upper()
    if fmt not in _DAT_FORMATS:
        raise _fail(path, f"Format {fmt!r} unsupported; supported: {', '.join(_DAT_FORMATS)}")
    model = fields.get("objectmodel", "I").upper()
    if model not in ("I", ""):
        raise _fail(path, f"ObjectModel {model!r} unsupported: only scalar (I) volumes")
    data_path = path.parent / fields["objectfilename"]
    blob = _read_bytes(data_path, f"data file {fields['objectfilename']!r} named by {path.name}")
    if blob[:2] == b"\x1f\x8b":
        blob = _inflate(blob, data_path, "gzip data")
    data = _decode_raw(blob, dims, np.dtype("<" + _DAT_FORMATS[fmt]), data_path)
    return _Loaded(data, sp, "dat", extra={"data_file": data_path.name})


def _load_dat_binary(path: Path) -> _Loaded:
    """TU Wien .dat: three little-endian uint16 dims, then 12-bit values in uint16."""
    blob = _read_bytes(path)
    if len(blob) < 6:
        raise _fail(path, "not a volvis .dat: no text header and shorter than a 6-byte header")
    dims = tuple(int(v) for v in np.frombuffer(blob[:6], dtype="<u2"))
    if 6 + 2 * int(np.prod(dims, dtype=np.int64)) != len(blob):
        raise _fail(
            path,
            "not a volvis .dat: no 'ObjectFileName:' text header, and the binary header's "
            f"dims {dims} need {6 + 2 * int(np.prod(dims, dtype=np.int64))} bytes, "
            f"the file has {len(blob)}",
        )
    dims = _check_dims(dims, path)
    data = _decode_raw(memoryview(blob)[6:], dims, np.dtype("<u2"), path)
    return _Loaded(data, (1.0, 1.0, 1.0), "dat-binary")


def _ints(text: str, path: object, key: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split())
    except ValueError:
        raise _fail(path, f"{key} = {text!r} is not a list of integers") from None


def _floats(text: str, path: object, key: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split())
    except ValueError:
        raise _fail(path, f"{key} = {text!r} is not a list of numbers") from None


# --------------------------------------------------------------------------
# MetaImage .mhd / .mha
# --------------------------------------------------------------------------

_MET_TYPES = {
    "MET_UCHAR": "u1",
    "MET_CHAR": "i1",
    "MET_USHORT": "u2",
    "MET_SHORT": "i2",
    "MET_UINT": "u4",
    "MET_INT": "i4",
    "MET_ULONG_LONG": "u8",
    "MET_LONG_LONG": "i8",
    "MET_FLOAT": "f4",
    "MET_DOUBLE": "f8",
}
_MET_MODALITY = {"MET_MOD_CT": "ct", "MET_MOD_MR": "mri"}


def _read_metaimage_header(path: Path) -> tuple[dict[str, str], int]:
    """Key/value pairs (keys lower-cased) and the byte offset after ElementDataFile."""
    fields: dict[str, str] = {}
    try:
        with open(path, "rb") as f:
            while True:
                line = f.readline(_MAX_HEADER_BYTES)
                if not line:
                    raise _fail(path, "MetaImage header has no ElementDataFile line")
                if f.tell() > _MAX_HEADER_BYTES:
                    raise _fail(path, "MetaImage header is longer than 1 MiB: not a header")
                text = line.decode("latin-1").strip()
                if not text or text.startswith("#"):
                    continue
                if "=" not in text:
                    raise _fail(path, f"MetaImage header line {text[:60]!r} is not 'Key = Value'")
                key, _, value = text.partition("=")
                fields[key.strip().lower()] = value.strip()
                if key.strip().lower() == "elementdatafile":
                    return fields, f.tell()
    except OSError as exc:
        raise _fail(path, f"cannot read: {exc.strerror or _one_line(exc)}") from None


def _load_metaimage(path: Path) -> _Loaded:
    fields, data_offset = _read_metaimage_header(path)

    def need(key: str) -> str:
        if key.lower() not in fields:
            raise _fail(path, f"MetaImage header lacks {key}")
        return fields[key.lower()]

    ndims = _ints(need("NDims"), path, "NDims")
    dims = list(_ints(need("DimSize"), path, "DimSize"))
    if ndims != (len(dims),):
        raise _fail(path, f"NDims = {ndims} does not match DimSize = {dims}")
    while len(dims) > 3 and dims[-1] == 1:
        dims.pop()
    if len(dims) != 3:
        raise _fail(path, f"DimSize = {dims}: only 3-D volumes are supported")
    dims3 = _check_dims(tuple(dims), path, "DimSize")
    channels = int(_ints(fields.get("elementnumberofchannels", "1"), path, "channels")[0])
    if channels != 1:
        raise _fail(path, f"ElementNumberOfChannels = {channels}: only scalar volumes")
    etype = need("ElementType").upper()
    if etype not in _MET_TYPES:
        raise _fail(path, f"ElementType {etype} unsupported; supported: {', '.join(_MET_TYPES)}")
    msb_text = fields.get("elementbyteordermsb", fields.get("binarydatabyteordermsb", "False"))
    big = msb_text.strip().lower() in ("true", "1")
    np_dtype = np.dtype((">" if big else "<") + _MET_TYPES[etype])
    spacing_key = "elementspacing" if "elementspacing" in fields else "elementsize"
    sp: tuple[float, ...] = (1.0, 1.0, 1.0)
    if spacing_key in fields:
        sp = _floats(fields[spacing_key], path, spacing_key)[:3]
        sp = _check_spacing(sp, path, "ElementSpacing")

    data_file = need("ElementDataFile")
    if data_file.upper().startswith("LIST") or "%" in data_file:
        raise _fail(path, f"ElementDataFile = {data_file}: file lists/patterns are unsupported")
    compressed = fields.get("compresseddata", "False").lower() in ("true", "1")
    header_size = int(_ints(fields.get("headersize", "0"), path, "HeaderSize")[0])
    need_bytes = int(np.prod(dims3, dtype=np.int64)) * np_dtype.itemsize

    if data_file.upper() == "LOCAL":
        source = path
        blob = _read_bytes(path)[data_offset:]
        label = f"data after the header of {path.name}"
    else:
        source = path.parent / data_file
        if not source.is_file():
            raise _fail(path, f"ElementDataFile {data_file!r} not found (looked for {source})")
        blob = _read_bytes(source, f"ElementDataFile {data_file!r}")
        label = f"ElementDataFile {data_file!r}"
    if compressed:
        if "compresseddatasize" in fields:
            csize = int(_ints(fields["compresseddatasize"], path, "CompressedDataSize")[0])
            if csize > len(blob):
                raise _fail(
                    path,
                    f"{label} is truncated: CompressedDataSize = {csize} bytes, "
                    f"only {len(blob)} present",
                )
            blob = blob[:csize]
        payload: bytes | memoryview = _inflate(blob, path, label)
    else:
        if header_size == -1:
            payload = memoryview(blob)[max(0, len(blob) - need_bytes) :]
        else:
            payload = memoryview(blob)[header_size:]
        if data_file.upper() == "LOCAL" and len(payload) > need_bytes:
            payload = payload[:need_bytes]  # tolerate trailing bytes after LOCAL data
    data = _decode_raw(payload, dims3, np_dtype, path, label)

    file_axes = None
    anat = fields.get("anatomicalorientation", "").upper()
    if len(anat) == 3 and "?" not in anat:
        try:  # MetaIO letters say where each axis comes FROM ("RAI" == LPS)
            file_axes = _parse_axis_code("".join(_OPPOSITE.get(c, "?") for c in anat))
        except VolumeError:
            raise _fail(path, f"AnatomicalOrientation = {anat} is not a valid code") from None
    matrix_key = next(
        (k for k in ("transformmatrix", "orientation", "rotation") if k in fields), None
    )
    if matrix_key is not None and file_axes is None:
        m = np.array(_floats(fields[matrix_key], path, matrix_key))
        if m.size != 9:
            raise _fail(path, f"{matrix_key} has {m.size} numbers, expected 9")
        m = m.reshape(3, 3)  # row n = direction of index axis n in LPS (ITK convention)
        if not np.allclose(m, np.eye(3)):
            try:
                file_axes = _axis_code_from_directions(m, "LPS")
            except ValueError as exc:
                raise _fail(path, f"{matrix_key}: {exc}") from None
    modality = _MET_MODALITY.get(fields.get("modality", "").upper())
    extra = {"compressed": compressed}
    if data_file.upper() != "LOCAL":
        extra["data_file"] = data_file
    return _Loaded(
        data,
        sp,
        "metaimage",
        file_axes=file_axes,
        modality=modality,
        units="HU" if modality == "ct" else None,
        extra=extra,
    )


# --------------------------------------------------------------------------
# NRRD (pynrrd)
# --------------------------------------------------------------------------

_NRRD_SPACES = {
    "right-anterior-superior": "RAS",
    "ras": "RAS",
    "left-anterior-superior": "LAS",
    "las": "LAS",
    "left-posterior-superior": "LPS",
    "lps": "LPS",
    "scanner-xyz": "RAS",  # not anatomical: x, y, z taken as a right-handed frame
    "3d-right-handed": "RAS",
}


def _load_nrrd(path: Path) -> _Loaded:
    import nrrd

    try:
        header = nrrd.read_header(str(path))
    except (nrrd.NRRDError, ValueError, UnicodeDecodeError) as exc:
        raise _fail(path, f"bad NRRD header: {_one_line(exc)}") from None
    except OSError as exc:
        raise _fail(path, f"cannot read: {exc.strerror or _one_line(exc)}") from None
    sizes = [int(s) for s in header.get("sizes", [])]
    if len(sizes) != 3:
        raise _fail(path, f"NRRD sizes {sizes}: only 3-D scalar volumes are supported")
    _check_dims(tuple(sizes), path, "sizes")
    data_file = header.get("data file") or header.get("datafile")
    if data_file:
        data_path = path.parent / str(data_file)
        if not data_path.is_file():
            raise _fail(path, f"data file {str(data_file)!r} not found (looked for {data_path})")
    try:
        data, header = nrrd.read(str(path), index_order="C")
    except (zlib.error, EOFError, gzip.BadGzipFile) as exc:
        raise _fail(path, f"corrupt compressed data: {_one_line(exc)}") from None
    except (nrrd.NRRDError, ValueError, TypeError) as exc:
        raise _fail(
            path, f"cannot read NRRD data (truncated or corrupt?): {_one_line(exc)}"
        ) from None
    except OSError as exc:
        raise _fail(path, f"cannot read NRRD data: {exc.strerror or _one_line(exc)}") from None
    if tuple(data.shape) != tuple(reversed(sizes)):
        raise _fail(path, f"NRRD data has shape {data.shape}, header sizes {sizes} (truncated?)")
    encoding = str(header.get("encoding", "raw")).lower()
    if encoding in ("gzip", "gz", "bzip2", "bz2"):  # pynrrd skips the CRC and a lost end
        try:
            with open(path, "rb") as fh:
                nrrd.read_header(fh)  # leaves fh at attached data
                with open(data_path, "rb") if data_file else contextlib.nullcontext(fh) as src:
                    for _ in range(int(header.get("line skip", header.get("lineskip", 0)))):
                        src.readline()
                    _verify_compressed(src, "bzip2" if encoding.startswith("bz") else "gzip",
                                       path, "data")
        except OSError as exc:
            raise _fail(path, f"cannot read NRRD data: {exc.strerror or _one_line(exc)}") from None

    sp: tuple[float, ...] = (1.0, 1.0, 1.0)
    file_axes = None
    directions = header.get("space directions")
    space = str(header.get("space", "")).lower()
    if directions is not None:
        d = np.asarray(directions, dtype=np.float64)
        if d.shape != (3, 3) or not np.all(np.isfinite(d)):
            raise _fail(path, "'space directions' must give 3 spatial axes")
        sp = _check_spacing(np.linalg.norm(d, axis=1), path, "space directions")
        if space in _NRRD_SPACES:
            try:
                file_axes = _axis_code_from_directions(d, _NRRD_SPACES[space])
            except ValueError as exc:
                raise _fail(path, f"space directions: {exc}") from None
    elif "spacings" in header:
        values = np.asarray(header["spacings"], dtype=np.float64)
        values = np.where(np.isfinite(values), values, 1.0)
        sp = _check_spacing(values, path, "spacings")
    extra = {"encoding": str(header.get("encoding", "raw"))}
    if space:
        extra["space"] = space
    return _Loaded(data, sp, "nrrd", file_axes=file_axes, extra=extra)


# --------------------------------------------------------------------------
# NIfTI (nibabel)
# --------------------------------------------------------------------------


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


# --------------------------------------------------------------------------
# DICOM series (pydicom)
# --------------------------------------------------------------------------


def _load_dicom(path: Path) -> _Loaded:
    import pydicom
    from pydicom.errors import InvalidDicomError

    folder = path if path.is_dir() else path.parent
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

    have_geometry = all(
        "ImagePositionPatient" in ds and "ImageOrientationPatient" in ds for _, ds in headers
    )
    file_axes = None
    if have_geometry:
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
        file_axes = _axis_code_from_directions(np.stack([row_dir, col_dir, normal]), "LPS")
    else:
        numbers = [int(ds.get("InstanceNumber", i)) for i, (_, ds) in enumerate(headers)]
        order = np.argsort(numbers, kind="stable")
        sz = float(first.get("SpacingBetweenSlices", first.get("SliceThickness", 1.0)) or 1.0)
    pixel = first.get("PixelSpacing", [1.0, 1.0])
    sy, sx = float(pixel[0]), float(pixel[1])  # (between rows, between columns)

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


# --------------------------------------------------------------------------
# TIFF stacks (tifffile)
# --------------------------------------------------------------------------

_LENGTH_UNITS_MM = {
    "nm": 1e-6,
    "nanometer": 1e-6,
    "micron": 1e-3,
    "um": 1e-3,
    "\u00b5m": 1e-3,
    "\\u00b5m": 1e-3,
    "micrometer": 1e-3,
    "mm": 1.0,
    "millimeter": 1.0,
    "cm": 10.0,
    "centimeter": 10.0,
    "m": 1000.0,
    "meter": 1000.0,
}


def _tiff_pixel_size_mm(page: object, imagej: dict | None) -> tuple[float, float] | None:
    """(sx, sy) in mm from resolution tags, when they mean a physical size."""
    tags = page.tags  # type: ignore[attr-defined]

    def res(tag: str) -> float | None:
        if tag not in tags:
            return None
        value = tags[tag].value
        num, den = value if isinstance(value, tuple) else (value, 1)
        return float(num) / float(den) if den else None

    xres, yres = res("XResolution"), res("YResolution")
    if not xres or not yres:
        return None
    unit_tag = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else 2
    if imagej and str(imagej.get("unit", "")).lower() in _LENGTH_UNITS_MM:
        factor = _LENGTH_UNITS_MM[str(imagej["unit"]).lower()]
        return factor / xres, factor / yres
    if unit_tag == 3:  # centimetre
        return 10.0 / xres, 10.0 / yres
    return None  # NONE, or INCH: print DPI (72/96/300), not a voxel size


@contextlib.contextmanager
def _tifffile_messages() -> Iterator[list[str]]:
    """Collect what tifffile logs or warns while reading, instead of stray stderr lines.

    Yields the list that receives the text of every ERROR-level log record (a broken page
    chain, as in a truncated file: the one thing worth folding into the error); warnings
    are dropped.
    """
    logger = logging.getLogger("tifffile")
    errors: list[str] = []

    class _Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno >= logging.ERROR:
                errors.append(re.sub(r"^<[^>]*>\s*", "", record.getMessage()))

    handler = _Keep(logging.DEBUG)
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield errors
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _tiff_problem(exc: BaseException | None, errors: list[str]) -> str:
    parts = ([_one_line(exc)] if exc is not None else []) + errors[:1]
    return "; ".join(dict.fromkeys(parts)) + ("" if exc is not None else " (truncated or damaged)")


def _load_tiff(path: Path) -> _Loaded:
    import tifffile

    with _tifffile_messages() as errors:
        try:
            with tifffile.TiffFile(path) as tif:
                series = tif.series[0]
                axes = series.axes
                data = series.asarray()
                imagej = tif.imagej_metadata
                pixel_mm = _tiff_pixel_size_mm(tif.pages[0], imagej)
        except (tifffile.TiffFileError, ValueError, KeyError, IndexError, EOFError) as exc:
            raise _fail(path, f"cannot read TIFF: {_tiff_problem(exc, errors)}") from None
        except OSError as exc:
            raise _fail(path, f"cannot read TIFF: {exc.strerror or _one_line(exc)}") from None
    if errors:  # read, but tifffile found the page chain broken: pages may be missing
        raise _fail(path, f"cannot read TIFF: {_tiff_problem(None, errors)}")
    for ax in ("S", "C"):
        if ax in axes and data.shape[axes.index(ax)] > 1:
            raise _fail(path, f"TIFF has {data.shape[axes.index(ax)]} channels: only greyscale")
    squeeze = tuple(i for i, n in enumerate(data.shape) if n == 1)
    data = np.squeeze(data, axis=squeeze) if squeeze and data.ndim > 3 else data
    if data.ndim != 3:
        raise _fail(
            path,
            f"TIFF holds an array of shape {data.shape} (axes {axes}); "
            "a volume needs a multi-page stack (pages = z)",
        )
    return _tiff_result(data, pixel_mm, imagej, "tiff", {"tiff_axes": axes})


def _tiff_result(
    data: np.ndarray,
    pixel_mm: tuple[float, float] | None,
    imagej: dict | None,
    fmt: str,
    extra: dict,
) -> _Loaded:
    sp: tuple[float, ...] = (1.0, 1.0, 1.0)
    if pixel_mm is not None:
        factor = _LENGTH_UNITS_MM.get(str((imagej or {}).get("unit", "")).lower())
        if imagej and "spacing" in imagej and factor:
            sz = float(imagej["spacing"]) * factor
        else:
            sz = float(np.mean(pixel_mm))
            extra["z_spacing"] = "assumed equal to the pixel size"
        sp = (pixel_mm[0], pixel_mm[1], sz)
    return _Loaded(data, sp, fmt, extra=extra)


def _natural_key(path: Path) -> list[object]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def _load_tiff_folder(path: Path) -> _Loaded:
    import tifffile

    files = sorted(
        (p for p in path.iterdir() if p.suffix.lower() in (".tif", ".tiff")), key=_natural_key
    )
    slices = []
    pixel_mm = None
    for i, p in enumerate(files):
        with _tifffile_messages() as errors:
            try:
                with tifffile.TiffFile(p) as tif:
                    page = tif.series[0].asarray()
                    if i == 0:
                        pixel_mm = _tiff_pixel_size_mm(tif.pages[0], tif.imagej_metadata)
            except (tifffile.TiffFileError, ValueError, KeyError, IndexError, EOFError) as exc:
                raise _fail(p, f"cannot read TIFF slice: {_tiff_problem(exc, errors)}") from None
            except OSError as exc:
                raise _fail(
                    p, f"cannot read TIFF slice: {exc.strerror or _one_line(exc)}"
                ) from None
        if errors:
            raise _fail(p, f"cannot read TIFF slice: {_tiff_problem(None, errors)}")
        page = np.squeeze(page)
        if page.ndim != 2:
            raise _fail(p, f"TIFF slice has shape {page.shape}: expected one greyscale page")
        if slices and page.shape != slices[0].shape:
            raise _fail(
                p, f"slice is {page.shape}, the first slice {files[0].name} is {slices[0].shape}"
            )
        slices.append(page)
    if len(slices) < 2:
        raise _fail(path, f"folder holds {len(slices)} TIFF slice(s); a volume needs 2 or more")
    extra = {"slices": len(slices)}
    return _tiff_result(np.stack(slices), pixel_mm, None, "tiff-folder", extra)


# --------------------------------------------------------------------------
# Roettger .pvm (uncompressed PVM, PVM2, PVM3)
# --------------------------------------------------------------------------


def _load_pvm(path: Path) -> _Loaded:
    blob = _read_bytes(path)
    if blob.startswith(b"DDS v3"):
        raise _fail(
            path,
            "DDS-compressed PVM is not supported; decompress it with V^3's 'pvm2pvm' or "
            "'pvm2raw' tool first",
        )
    match = re.match(
        rb"(PVM3?|PVM2)\n\s*(\d+)\s+(\d+)\s+(\d+)\s*\n(?:\s*([-+.\deE]+)\s+([-+.\deE]+)\s+"
        rb"([-+.\deE]+)\s*\n)?\s*(\d+)\n",
        blob[:4096],
    )
    if match is None:
        raise _fail(path, "not a PVM file: bad header (expected 'PVM', 'PVM2' or 'PVM3')")
    version = match.group(1)
    dims = _check_dims(tuple(int(match.group(i)) for i in (2, 3, 4)), path)
    sp: tuple[float, ...] = (1.0, 1.0, 1.0)
    if version != b"PVM":
        if match.group(5) is None:
            raise _fail(path, f"{version.decode()} header lacks the voxel scale line")
        sp = _check_spacing(tuple(float(match.group(i)) for i in (5, 6, 7)), path, "scale")
    components = int(match.group(8))
    if components not in (1, 2):
        raise _fail(path, f"PVM with {components} bytes per voxel: only 1 (8-bit) or 2 (16-bit)")
    dtype = np.dtype("u1") if components == 1 else np.dtype(">u2")
    start = match.end()
    need = int(np.prod(dims, dtype=np.int64)) * dtype.itemsize
    payload = memoryview(blob)[start : start + need]
    data = _decode_raw(payload, dims, dtype, path)
    return _Loaded(data, sp, "pvm", extra={"pvm_version": version.decode()})


_READERS: dict[str, Callable[[Path], _Loaded]] = {
    "dat": _load_dat,
    "metaimage": _load_metaimage,
    "nrrd": _load_nrrd,
    "nifti": _load_nifti,
    "dicom": _load_dicom,
    "tiff": _load_tiff,
    "tiff-folder": _load_tiff_folder,
    "pvm": _load_pvm,
}


# --------------------------------------------------------------------------
# built-in procedural volumes
# --------------------------------------------------------------------------
#
# Each phantom is painted back to front on a grid centred at the origin (mm,
# RAS): a region is a signed distance field (negative inside) and paints its
# value through a soft 1.3-2 voxel edge, so iso-surfaces are smooth and shading
# looks organic rather than voxelated. A little deterministic noise (B-spline
# upsampled random lattices, fixed seeds) gives texture. Results are cached;
# callers get a fresh copy.


class _Grid:
    """Voxel-centre coordinates (mm, centred at 0) and sub-box access."""

    def __init__(self, dims: tuple[int, int, int], spacing_mm: float) -> None:
        self.dims = dims
        self.spacing = float(spacing_mm)
        self.axes = [
            ((np.arange(n, dtype=np.float32) - (n - 1) / 2.0) * np.float32(self.spacing))
            for n in dims
        ]
        self.shape = (dims[2], dims[1], dims[0])

    def coarse(self, factor: int) -> _Grid:
        """A grid ``factor`` times coarser covering at least the same box."""
        return _Grid(
            tuple(int(np.ceil((n - 1) / factor)) + 3 for n in self.dims), self.spacing * factor
        )

    def box(
        self, lo: tuple[float, float, float], hi: tuple[float, float, float]
    ) -> tuple[tuple[slice, slice, slice], np.ndarray, np.ndarray, np.ndarray] | None:
        """Slices of the sub-grid covering [lo, hi] (mm) and its broadcast X, Y, Z."""
        idx = []
        for a, low, high in zip(self.axes, lo, hi):
            i0 = int(np.searchsorted(a, low - 2 * self.spacing))
            i1 = int(np.searchsorted(a, high + 2 * self.spacing))
            if i1 <= i0:
                return None
            idx.append(slice(i0, i1))
        sx, sy, sz = idx
        x = self.axes[0][sx][None, None, :]
        y = self.axes[1][sy][None, :, None]
        z = self.axes[2][sz][:, None, None]
        return (sz, sy, sx), x, y, z

    def full(self) -> tuple[tuple[slice, slice, slice], np.ndarray, np.ndarray, np.ndarray]:
        out = self.box((-1e9, -1e9, -1e9), (1e9, 1e9, 1e9))
        assert out is not None
        return out


def _bspline_weights(pos: np.ndarray, n_in: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices and weights, each (len(pos), 4), of cubic B-spline taps at ``pos``.

    ``pos`` are positions in lattice index units; indices are clamped to the lattice.
    """
    base = np.floor(pos).astype(np.intp)
    f = pos - base
    weights = np.stack(
        [
            (1 - f) ** 3 / 6,
            (3 * f**3 - 6 * f**2 + 4) / 6,
            (-3 * f**3 + 3 * f**2 + 3 * f + 1) / 6,
            f**3 / 6,
        ],
        axis=1,
    )
    index = np.clip(base[:, None] + np.arange(-1, 3)[None, :], 0, n_in - 1)
    return index, weights


def _bspline_taps(n_out: int, n_in: int) -> tuple[np.ndarray, np.ndarray]:
    """B-spline taps spreading ``n_out`` samples over the inner part of a lattice."""
    return _bspline_weights(np.linspace(1.0, n_in - 2.0, n_out), n_in)


def _resample_axis(a: np.ndarray, axis: int, taps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Apply interpolation ``taps`` along ``axis`` (element-wise, no BLAS threads)."""
    index, weights = taps
    weights = weights.astype(np.float32)
    moved = np.ascontiguousarray(np.moveaxis(a, axis, 0), dtype=np.float32)
    out = np.empty((index.shape[0], *moved.shape[1:]), dtype=np.float32)
    scratch = np.empty(moved.shape[1:], dtype=np.float32)
    for i in range(index.shape[0]):  # one contiguous output plane at a time
        plane = out[i]
        np.multiply(moved[index[i, 0]], weights[i, 0], out=plane)
        for t in range(1, index.shape[1]):
            np.multiply(moved[index[i, t]], weights[i, t], out=scratch)
            plane += scratch
    return out if axis == 0 else np.ascontiguousarray(np.moveaxis(out, 0, axis))


class _Upsampler:
    """Smooth (cubic B-spline) resampling of coarse-grid fields onto a fine grid.

    Smooth rather than trilinear so that iso-surfaces of resampled distance
    fields have continuous normals (no facets in shaded renders).
    """

    def __init__(self, coarse: _Grid, fine: _Grid) -> None:
        self.taps = [
            _bspline_weights((f - c[0]) / (c[1] - c[0]), c.size)
            for f, c in zip(fine.axes, coarse.axes)
        ]

    def __call__(self, field: np.ndarray) -> np.ndarray:
        out = field.astype(np.float32)
        for numpy_axis, world_axis in ((2, 0), (1, 1), (0, 2)):
            out = _resample_axis(out, numpy_axis, self.taps[world_axis])
        return out


def _ellipsoid(x, y, z, c, r):  # noqa: ANN001 - internal, broadcast float32 arrays
    """Approximate signed distance (mm) to an axis-aligned ellipsoid."""
    px, py, pz = (x - c[0]) / r[0], (y - c[1]) / r[1], (z - c[2]) / r[2]
    k0 = np.sqrt(px * px + py * py + pz * pz)
    qx, qy, qz = px / r[0], py / r[1], pz / r[2]
    k1 = np.sqrt(qx * qx + qy * qy + qz * qz) + np.float32(1e-6)
    return k0 * (k0 - 1.0) / k1


def _round_cone(x, y, z, a, b, ra, rb):  # noqa: ANN001
    """Approximate signed distance to a capsule from a (radius ra) to b (radius rb)."""
    ax, ay, az = a
    bx, by, bz = b[0] - ax, b[1] - ay, b[2] - az
    length2 = bx * bx + by * by + bz * bz
    px, py, pz = x - ax, y - ay, z - az
    t = np.clip((px * bx + py * by + pz * bz) / length2, 0.0, 1.0)
    dx, dy, dz = px - t * bx, py - t * by, pz - t * bz
    return np.sqrt(dx * dx + dy * dy + dz * dz) - (ra + (rb - ra) * t)


def _smin(a, b, k):  # noqa: ANN001
    """Smooth minimum (union) of two distance fields with blend radius k (mm)."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * (k * 0.25)


def _paint(vol: np.ndarray, sl, sdf, value, edge_mm: float) -> None:  # noqa: ANN001
    """Blend ``value`` into ``vol[sl]`` where ``sdf < 0`` with a soft edge."""
    m = np.clip(0.5 - sdf * np.float32(1.0 / edge_mm), 0.0, 1.0)
    region = vol[sl]
    region += m * (np.asarray(value, dtype=np.float32) - region)


def _noise(shape: tuple[int, int, int], cell_vox: float, seed: int) -> np.ndarray:
    """Smooth deterministic noise, std 0.5, feature size about ``cell_vox`` voxels."""
    rng = np.random.default_rng(seed)
    lattice = [max(4, int(np.ceil(n / cell_vox)) + 3) for n in shape]
    out = rng.uniform(-1.0, 1.0, size=lattice).astype(np.float32)
    for axis in (2, 1, 0):
        out = _resample_axis(out, axis, _bspline_taps(shape[axis], lattice[axis]))
    out *= np.float32(0.5 / max(float(out.ravel()[::7].std()), 1e-6))
    return out


# Small parts of the head phantom, painted in order after the large fields.
# ("ellipsoid", centre, radii), ("capsule", a, b, radius_a, radius_b),
# ("box", centre, half_size), ("ring", centre_xy, z_range, r_out, r_in) (vertical),
# ("arch", centre_xy, radii_xy, half_thickness, z_range, min_y) (U-shaped bar);
# each with the value it paints (HU) and optionally "skull" to stay inside the
# skull's outer surface (default: 2.5 mm under the skin).
def _face_bones() -> tuple[list[tuple], list[tuple]]:
    """Facial bones blended smoothly into the face shell: (unions, holes), each (shape, k)."""
    unions: list[tuple] = [
        (("arch", (0, 22), (38, 48), 5.0, (-80, -62), 6.0), 5.0),  # mandible body
        (("arch", (0, 20), (33, 50), 5.0, (-53, -41), 10.0), 5.0),  # upper alveolar ridge
        (("ellipsoid", (0, 68, -76), (14, 6, 9)), 5.0),  # chin
    ]
    holes: list[tuple] = [
        (("ellipsoid", (0, 82, -30), (10, 16, 15)), 4.0),  # nasal aperture
    ]
    for sx in (-1.0, 1.0):
        unions += [
            (("ellipsoid", (sx * 44, 60, -24), (10, 10, 9)), 6.0),  # cheekbone
            (("capsule", (sx * 46, 56, -24), (sx * 56, 0, -20), 4.5, 4.0), 6.0),  # zyg. arch
            (("capsule", (sx * 36, 12, -72), (sx * 46, -4, -30), 6.0, 4.5), 6.0),  # ramus
        ]
        holes.append((("ellipsoid", (sx * 31, 64, -12), (15, 30, 14)), 4.0))  # orbit
    return unions, holes


def _head_parts() -> list[tuple]:
    """Small parts painted in order: (shape, value HU[, "skull"])."""
    parts: list[tuple] = [
        (("ellipsoid", (0, -50, -22), (42, 24, 13)), 36.0),  # cerebellum
        (("capsule", (0, -16, -8), (0, -24, -115), 11.0, 6.0), 32.0),  # brain stem, cord
        (("ellipsoid", (0, -6, 10), (2.5, 13, 8)), 5.0),  # third ventricle
        (("ellipsoid", (0, -34, -16), (5, 4, 5)), 5.0),  # fourth ventricle
        (("ellipsoid", (0, 58, -26), (9, 32, 20)), -1000.0),  # nasal cavity
        (("box", (0, 58, -26), (1.0, 28, 16)), 700.0),  # nasal septum
        (("ellipsoid", (0, 70, 12), (12, 3.0, 8)), -1000.0, "skull"),  # frontal sinus
        (("capsule", (0, 30, -28), (0, 30, -130), 8.0, 8.0), -1000.0),  # pharynx, trachea
    ]
    for sx in (-1.0, 1.0):
        parts += [
            # lateral ventricle (two pieces) and temporal horn
            (("capsule", (sx * 10, -34, 26), (sx * 10, -6, 34), 5.0, 6.0), 5.0),
            (("capsule", (sx * 10, -6, 34), (sx * 9, 22, 27), 6.0, 4.0), 5.0),
            (("capsule", (sx * 12, -30, 24), (sx * 20, 6, -14), 3.5, 2.0), 5.0),
            # orbit fat, eyeball (sclera), vitreous, lens
            (("ellipsoid", (sx * 31, 55, -12), (14, 20, 13)), -80.0),
            (("ellipsoid", (sx * 31, 53, -12), (11.5, 11.5, 11.5)), 40.0),
            (("ellipsoid", (sx * 31, 53, -12), (10.3, 10.3, 10.3)), 10.0),
            (("ellipsoid", (sx * 31, 63, -12), (4, 2, 4)), 90.0),
            # maxillary sinus: thin bone wall, air inside
            (("ellipsoid", (sx * 25, 44, -32), (15, 17, 12)), 1000.0),
            (("ellipsoid", (sx * 25, 44, -32), (13, 15, 10)), -1000.0),
            # ear canal
            (("capsule", (sx * 82, -12, -8), (sx * 60, -12, -8), 3.0, 2.0), -1000.0),
        ]
    for row_z, ry in ((-48.0, 50.0), (-57.0, 46.0)):  # upper and lower teeth
        for ang in np.linspace(-1.35, 1.35, 12):
            centre = (31.0 * float(np.sin(ang)), 20.0 + ry * float(np.cos(ang)), row_z)
            parts.append((("ellipsoid", centre, (4.0, 3.6, 5.0)), 2400.0))
    for zc in (-50.0, -68.0, -86.0, -104.0, -122.0):  # cervical vertebrae
        parts += [
            (("capsule", (0, -12, zc - 5), (0, -12, zc + 5), 12.0, 12.0), 1100.0),
            (("ring", (0, -30), (zc - 5, zc + 5), 12.0, 7.0), 1100.0),
            (("box", (0, -48, zc - 2), (3.0, 9.0, 4.0)), 1100.0),
        ]
    parts.append((("capsule", (0, -30, -40), (0, -30, -130), 5.0, 5.0), 30.0))  # spinal cord
    return parts


def _part_box(shape: tuple) -> tuple[tuple[float, ...], tuple[float, ...]]:
    kind = shape[0]
    if kind == "ellipsoid":
        c, r = np.array(shape[1]), np.array(shape[2])
        return tuple(c - r), tuple(c + r)
    if kind == "capsule":
        a, b = np.array(shape[1]), np.array(shape[2])
        r = max(shape[3], shape[4])
        return tuple(np.minimum(a, b) - r), tuple(np.maximum(a, b) + r)
    if kind == "box":
        c, h = np.array(shape[1]), np.array(shape[2])
        return tuple(c - h), tuple(c + h)
    if kind == "ring":
        (cx, cy), (z0, z1), r = shape[1], shape[2], shape[3]
        return (cx - r, cy - r, z0), (cx + r, cy + r, z1)
    (cx, cy), (rx, ry), t, (z0, z1), _ = shape[1:]  # arch
    return (cx - rx - t, cy - ry - t, z0), (cx + rx + t, cy + ry + t, z1)


def _part_sdf(shape: tuple, x, y, z):  # noqa: ANN001 - broadcast float32 arrays
    kind = shape[0]
    if kind == "ellipsoid":
        return _ellipsoid(x, y, z, shape[1], shape[2])
    if kind == "capsule":
        return _round_cone(x, y, z, *shape[1:])
    if kind == "box":
        (cx, cy, cz), (hx, hy, hz) = shape[1], shape[2]
        return np.maximum(np.maximum(np.abs(x - cx) - hx, np.abs(y - cy) - hy), np.abs(z - cz) - hz)
    if kind == "ring":
        (cx, cy), (z0, z1), r_out, r_in = shape[1:]
        rho = np.sqrt((x - cx) ** 2 + (y - cy) ** 2)
        slab = np.abs(z - 0.5 * (z0 + z1)) - 0.5 * (z1 - z0)
        return np.maximum(np.maximum(rho - r_out, r_in - rho), slab)
    (cx, cy), (rx, ry), half, (z0, z1), min_y = shape[1:]  # arch
    rho = np.sqrt(((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2)
    bar = np.abs(rho - 1.0) * (0.5 * (rx + ry)) - half
    slab = np.abs(z - 0.5 * (z0 + z1)) - 0.5 * (z1 - z0)
    return np.maximum(np.maximum(bar, slab), min_y - y)


def _build_head() -> tuple[np.ndarray, float]:
    """CT-like head phantom in HU, RAS, (nz, ny, nx) = (144, 136, 112), 1.6 mm.

    The large smooth distance fields (skin, cranium, face) are computed on a
    2x coarser grid and resampled with cubic B-splines; the small parts of
    `_head_parts` are evaluated at full resolution inside their own boxes.
    """
    g = _Grid((112, 136, 144), 1.6)
    c = g.coarse(2)
    up = _Upsampler(c, g)
    edge = 1.6 * 2.0
    _, X, Y, Z = c.full()

    # z of the skull base as a function of y (anterior, middle, posterior fossae)
    fossa_y, fossa_z = [-95, -30, -12, 22, 34, 95], [-36, -36, -24, -24, -4, -4]
    zb_c = np.interp(c.axes[1], fossa_y, fossa_z).astype(np.float32)[None, :, None]
    zb = np.interp(g.axes[1], fossa_y, fossa_z).astype(np.float32)[None, :, None]

    # ---- coarse fields: skin (cranium + face + jaw + neck + nose + ears), skull, face bones
    cran = _ellipsoid(X, Y, Z, (0, -10, 26), (72, 92, 82))
    face = _ellipsoid(X, Y, Z, (0, 24, -26), (56, 62, 56))
    jaw = _ellipsoid(X, Y, Z, (0, 38, -62), (48, 44, 28))
    neck = np.maximum((np.sqrt((X / 50.0) ** 2 + ((Y + 10) / 52.0) ** 2) - 1.0) * 50.0, Z + 40.0)
    skin = _smin(_smin(cran, face, 18.0), _smin(jaw, neck, 16.0), 14.0)
    skin = _smin(skin, _ellipsoid(X, Y, Z, (0, 70, 2), (48, 14, 10)), 8.0)  # brow ridge
    skin = _smin(skin, _ellipsoid(X, Y, Z, (0, 78, -54), (22, 9, 9)), 5.0)  # lips
    skin = _smin(skin, _ellipsoid(X, Y, Z, (0, 74, -80), (18, 10, 13)), 8.0)  # chin
    skin = _smin(skin, _ellipsoid(X, Y + 0.3 * (Z + 22), Z, (0, 84, -22), (12, 18, 25)), 6.0)
    for sx in (-1, 1):
        skin = _smin(skin, _ellipsoid(X, Y, Z, (sx * 38, 54, -30), (18, 16, 16)), 14.0)  # cheek
        skin = _smin(skin, _ellipsoid(X, Y, Z, (sx * 72, -12, -4), (8, 13, 24)), 5.0)  # ear
        socket = _ellipsoid(X, Y, Z, (sx * 31, 84, -12), (15, 9, 8))
        skin = -_smin(-skin, socket, 6.0)  # shallow eye socket
    outer_c = cran + 5.0
    occipital = np.clip(-(Y + 30) / 40.0, 0.0, 1.0) * np.clip(1.0 - (Z - 20) / 60.0, 0.0, 1.0)
    temporal = np.clip((np.abs(X) - 50.0) / 15.0, 0.0, 1.0)
    wobble = _noise(c.shape, 7.0, seed=11)
    thick_c = np.maximum(6.5 + 2.0 * wobble + 2.5 * occipital - 2.5 * temporal, 3.0)
    face_bone_c = np.maximum(face + 7.0, -(face + 12.0))
    face_bone_c = np.maximum(face_bone_c, Z - (zb_c + 2.0) * (Y > 30))
    face_bone_c = np.maximum(face_bone_c, np.maximum(-50.0 - Z, 12.0 - Y))
    skin, outer, thick, face_bone = (up(f) for f in (skin, outer_c, thick_c, face_bone_c))

    full, Xf, _, Zf = g.full()
    fine = _noise(g.shape, 4.0, seed=12)  # ~6 mm texture; also folds the cortex
    vol = np.full(g.shape, -1000.0, dtype=np.float32)
    skin += fine * np.float32(0.4)
    _paint(vol, full, skin, 45.0, edge)
    fat = np.maximum(np.maximum(skin + 2.0, -(skin + 6.0)), Zf - (zb + 6.0))
    _paint(vol, full, fat, -90.0, edge)  # subcutaneous fat of face and neck
    vol += fine * np.float32(6.0)

    # ---- skull vault (outer/inner tables, diploe), skull base with the foramen magnum
    vault = np.maximum(np.maximum(outer, -(outer + thick)), (zb - 6.0) - Zf)
    depth = np.clip(-outer / thick, 0.0, 1.0)
    _paint(vol, full, vault, 1750.0 - 1050.0 * np.exp(-(((depth - 0.5) / 0.24) ** 2)), edge)
    s, x, y, z = g.box((-80, -100, -60), (80, 100, 10))
    plate = np.maximum(np.maximum(outer[s] + 2.0, z - zb[:, s[1]]), (zb[:, s[1]] - 7.0) - z)
    _paint(vol, s, np.maximum(plate, 13.0 - np.sqrt(x * x + (y + 24) ** 2)), 1300.0, edge)

    # ---- CSF, then brain with gyri (sulci where the noise crosses zero) and midline fissure
    inner = outer + thick
    _paint(vol, full, np.maximum(inner, zb - Zf), 8.0, edge)
    brain = inner + 2.5
    brain += 5.0 * np.exp(-((fine / 0.22) ** 2)) * np.clip(1.0 + brain / 14.0, 0.0, 1.0)
    brain = np.maximum(brain, (zb + 3.0) - Zf)
    brain = np.maximum(brain, np.where(Zf > zb + 24.0, 1.5 - np.abs(Xf), -1e3))
    grey = np.clip(1.0 - (-brain - 2.5) / 2.0, 0.0, 1.0)
    _paint(vol, full, brain, 28.0 + 10.0 * grey, edge)

    # ---- facial skeleton: the face shell with bones blended in and openings cut out
    s, x, y, z = g.box((-70, -15, -95), (70, 100, 10))
    bone = face_bone[s]
    unions, holes = _face_bones()
    for shape, k in unions:
        bone = _smin(bone, _part_sdf(shape, x, y, z), k)
    for shape, k in holes:
        bone = -_smin(-bone, _part_sdf(shape, x, y, z), k)
    bone = np.maximum(bone, skin[s] + 2.5)
    _paint(vol, s, bone, 1250.0 + fine[s] * 80.0, edge)

    # ---- the small parts
    for shape, value, *within in _head_parts():
        sl = g.box(*_part_box(shape))
        if sl is not None:  # every part stays under the skin (or inside the skull)
            s, x, y, z = sl
            limit = outer[s] + 1.5 if within == ["skull"] else skin[s] + 2.5
            _paint(vol, s, np.maximum(_part_sdf(shape, x, y, z), limit), value, edge)
    return vol, g.spacing


def _build_tooth() -> tuple[np.ndarray, float]:
    """Molar phantom on the paper's tooth scale (0..255), crown up, 0.15 mm voxels.

    Distance fields are computed on a 2x coarser grid and resampled.
    """
    g = _Grid((120, 104, 160), 0.15)
    c = g.coarse(2)
    up = _Upsampler(c, g)
    edge = 0.15 * 1.3
    _, x, y, z = c.full()

    # occlusal surface: four cusps around a central fossa
    cusps = np.zeros((1, *(x * y).shape[1:]), dtype=np.float32)
    for cx, cy in ((-2.3, -1.9), (2.3, -1.9), (-2.2, 2.0), (2.4, 2.0)):
        cusps = cusps + np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 3.2)
    weight = np.clip((z - 4.5) / 3.0, 0.0, 1.0)
    crown = _ellipsoid(x, y, z - weight * (1.3 * cusps - 0.9), (0, 0, 4.2), (5.6, 5.0, 5.6))
    crown = np.maximum(crown, 2.6 - z)  # enamel ends at the cemento-enamel junction
    trunk = _ellipsoid(x, y, z, (0, 0, 2.2), (5.1, 4.4, 3.6))
    roots = np.minimum(
        *(
            _round_cone(x, y, z, (sx * 2.4, 0.0, 1.5), (sx * 3.0, 0.3, -10.4), 2.8, 1.0)
            for sx in (-1, 1)
        )
    )
    enamel_thick = 1.35 * np.clip((z - 2.6) / 4.0, 0.0, 1.0) ** 0.7
    dentin = _smin(_smin(crown + enamel_thick, trunk, 1.2), roots, 1.5)
    outer = np.minimum(crown, dentin)
    pulp = _ellipsoid(x, y, z, (0, 0, 3.4), (2.7, 2.0, 1.7))
    for cx, cy in ((-1.7, -1.3), (1.7, -1.3), (-1.6, 1.4), (1.7, 1.4)):
        pulp = _smin(pulp, _ellipsoid(x, y, z, (cx, cy, 5.0), (0.6, 0.6, 1.3)), 0.6)
    for sx in (-1, 1):
        canal = _round_cone(x, y, z, (sx * 2.3, 0.0, 2.6), (sx * 2.9, 0.3, -9.6), 0.65, 0.18)
        pulp = _smin(pulp, canal, 0.5)

    fine = _noise(g.shape, 4.0, seed=22)
    _, _, _, zf = g.full()
    full = g.full()[0]
    vol = np.full(g.shape, 4.0, dtype=np.float32)
    vol += fine * np.float32(3.0)
    top = np.clip((zf - 5.0) / 4.0, 0.0, 1.0)
    _paint(vol, full, up(outer), 235.0 + 8.0 * fine + 6.0 * top, edge)
    _paint(vol, full, up(dentin), 158.0 + 5.0 * fine - 8.0 * np.clip(-zf / 10.0, 0.0, 1.0), edge)
    _paint(vol, full, up(pulp), 55.0 + 4.0 * fine, edge)
    return vol, g.spacing


def _build_sphere() -> tuple[np.ndarray, float]:
    """Homogeneous ball of value 1 (radius 24 voxels) in a 64^3 grid of zeros."""
    g = _Grid((64, 64, 64), 1.0)
    vol = np.zeros(g.shape, dtype=np.float32)
    full, x, y, z = g.full()
    _paint(vol, full, np.sqrt(x * x + y * y + z * z) - 24.0, 1.0, 1.0)
    return vol, g.spacing


@dataclass(frozen=True)
class _Builtin:
    build: Callable[[], tuple[np.ndarray, float]]
    modality: str
    description: str
    units: str | None = None
    # Gaussian band-limit (in voxels) applied last: painted edges leave terraces
    # that trilinear sampling turns into concentric "wood-grain" rings on smooth
    # surfaces (visible at any step size); sigma = 1 voxel removes them.
    smooth_voxels: float = 0.0


_BUILTINS: dict[str, _Builtin] = {
    "head": _Builtin(
        _build_head,
        "ct",
        "CT-like head phantom in HU: skin, skull with diploe, brain with gyri, ventricles, "
        "sinuses, eyes, jaw, teeth, cervical spine; 112x136x144 at 1.6 mm",
        units="HU",
        smooth_voxels=1.0,
    ),
    "tooth": _Builtin(
        _build_tooth,
        "tooth",
        "two-rooted molar on a 0-255 scale: enamel crown (up), dentin, pulp cavity and "
        "canals; 120x104x160 at 0.15 mm",
        smooth_voxels=1.0,
    ),
    "sphere": _Builtin(
        _build_sphere, "generic", "homogeneous ball (value 1, radius 24) in 64^3 zeros, 1 mm"
    ),
}


def list_builtins() -> list[str]:
    """Names accepted by ``builtin:NAME``, sorted."""
    return sorted(_BUILTINS)


@functools.cache
def _built(name: str) -> tuple[np.ndarray, float]:
    spec = _BUILTINS[name]
    data, spacing = spec.build()
    if spec.smooth_voxels:
        from scipy import ndimage

        data = ndimage.gaussian_filter(data, spec.smooth_voxels, mode="nearest")
    data.flags.writeable = False
    return data, spacing


def builtin_volume(name: str) -> Volume:
    """The procedural volume ``name`` (see `list_builtins`); deterministic.

    Raises
    ------
    VolumeError
        For an unknown name, listing the known ones.
    """
    key = str(name).strip().lower()
    if key not in _BUILTINS:
        raise VolumeError(
            f"builtin:{name}: unknown built-in volume; known: "
            + ", ".join(f"builtin:{n}" for n in list_builtins())
        )
    spec = _BUILTINS[key]
    data, spacing = _built(key)
    data = data.copy()
    metadata = {
        "format": "builtin",
        "description": spec.description,
        "file_dims": [int(data.shape[2]), int(data.shape[1]), int(data.shape[0])],
        "file_dtype": "float32",
        "value_range": [float(data.min()), float(data.max())],
        "orientation": {"file_axes": "RAS", "source": "builtin", "note": ""},
    }
    if spec.units:
        metadata["units"] = spec.units
    return Volume(
        data,
        (spacing, spacing, spacing),
        name=key,
        modality=spec.modality,
        source=f"builtin:{key}",
        metadata=metadata,
    )


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
