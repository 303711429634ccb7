"""NumPy ``.npy`` and ``.npz`` arrays, as numpy users save volumes.

The array is taken in the order `host.volume` keeps every volume in: shape ``(z, y, x)``,
x fastest (what ``np.save`` writes of an array indexed ``[z, y, x]``, and what a raw file
holds); other orders are turned with ``--orientation``. A ``.npy`` file records no voxel
size: ``--spacing SX,SY,SZ`` gives it (1 mm otherwise, as for any format without one). A
``.npz`` must hold one array (``np.savez(path, volume)``); with several, the error names
them. Arrays are read without pickles (``allow_pickle=False``), and the header's shape is
checked against the voxel limit before anything is allocated. Boolean masks are read as
0/1.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from host.volume.core import _check_dims, _fail, _Loaded, _one_line

_ERRORS = (ValueError, OSError, EOFError, zipfile.BadZipFile)


def _load_npy(path: Path) -> _Loaded:
    try:
        with open(path, "rb") as fh:
            _check_header(fh, path, "the array")
        data = np.load(path, mmap_mode="r", allow_pickle=False)
        return _loaded(path, np.array(data), "npy", {})
    except _ERRORS as exc:
        raise _fail(path, f"cannot read .npy: {_one_line(exc)}") from None


def _load_npz(path: Path) -> _Loaded:
    try:
        with zipfile.ZipFile(path) as archive:
            names = [n for n in archive.namelist() if n.endswith(".npy")]
            if len(names) != 1:
                listed = ", ".join(n[:-4] for n in names) or "none"
                raise _fail(path, f"a .npz volume holds one array; this one holds {len(names)} "
                                  f"arrays ({listed}): save the volume alone "
                                  "(np.savez(path, volume) or np.save)")
            name = names[0]
            with archive.open(name) as member:
                _check_header(member, path, f"array {name[:-4]!r}")
            with archive.open(name) as member:
                data = np.lib.format.read_array(member, allow_pickle=False)
    except _ERRORS as exc:
        raise _fail(path, f"cannot read .npz: {_one_line(exc)}") from None
    return _loaded(path, data, "npz", {"array": name[:-4]})


def _check_header(fh: BinaryIO, path: Path, what: str) -> None:
    """Refuse an array that is not 3-D or larger than the voxel limit, from its header."""
    version = np.lib.format.read_magic(fh)
    reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
              else np.lib.format.read_array_header_2_0)
    shape, _fortran, dtype = reader(fh)
    if dtype.hasobject:
        raise _fail(path, f"{what} holds Python objects ({dtype}), not voxel values")
    if len(shape) != 3:
        raise _fail(path, f"{what} has shape {tuple(shape)}: a volume is a 3-D array "
                          "(z, y, x)")
    _check_dims((shape[2], shape[1], shape[0]), path, f"{what}'s dims (x, y, z)")


def _loaded(path: Path, data: np.ndarray, fmt: str, extra: dict) -> _Loaded:
    if data.dtype == bool:
        data = data.astype(np.uint8)
    return _Loaded(np.ascontiguousarray(data), (1.0, 1.0, 1.0), fmt, extra=extra)
