"""The `Volume` type and what every format reader shares.

`Volume` holds float32 data ``(nz, ny, nx)`` in RAS order with its spacing in mm (the
conventions are in `host.volume`). A reader (``host/volume/read_*.py``) returns a `_Loaded`:
the data in *file* order with what its header said; `host.volume.load.load_volume` turns it
into a `Volume`. The underscore helpers here are the readers' shared toolkit (one-line
`VolumeError` s naming the file, size checks, raw decoding, zlib/gzip inflation); they are
internal to ``host/volume/``.
"""

from __future__ import annotations

import bz2
import gzip
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from host.errors import VolumeError

__all__ = [
    "MODALITIES",
    "RAW_DTYPES",
    "SUPPORTED_FORMATS",
    "Volume",
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
    "TIFF stack .tif/.tiff or folder of TIFFs, Roettger .pvm, NumPy .npy/.npz (z, y, x) with "
    "--spacing"
)

_MAX_HEADER_BYTES = 1 << 20  # text headers longer than this are not headers
_MAX_VOXELS = 1 << 31  # refuse headers that declare absurd grids (8 GiB of float32)


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


def _read_head(path: Path, size: int) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(size)
    except OSError as exc:
        raise _fail(path, f"cannot read: {exc.strerror or _one_line(exc)}") from None


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
