"""Roettger ``.pvm`` (uncompressed PVM, PVM2, PVM3)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from host.volume.core import (
    _check_dims,
    _check_spacing,
    _decode_raw,
    _fail,
    _Loaded,
    _read_bytes,
)


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
