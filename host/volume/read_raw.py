"""Raw voxels (any extension, ``dims`` given; gzip data is inflated)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from host.volume.core import (
    RAW_DTYPES,
    _check_dims,
    _decode_raw,
    _fail,
    _inflate,
    _Loaded,
    _read_bytes,
)


def _raw_dtype(dtype: str, endian: str, path: object) -> np.dtype:
    key = str(dtype).lower()
    if key not in RAW_DTYPES:
        raise _fail(path, f"unknown dtype {dtype!r}; supported: {', '.join(RAW_DTYPES)}")
    return np.dtype(("<" if endian == "little" else ">") + RAW_DTYPES[key])


def _load_raw(path: Path, dims: tuple[int, int, int], dtype: str, endian: str) -> _Loaded:
    dims = _check_dims(dims, path)
    np_dtype = _raw_dtype(dtype, endian, path)
    blob = _read_bytes(path)
    if blob[:2] == b"\x1f\x8b":
        blob = _inflate(blob, path, "gzip data")
    data = _decode_raw(blob, dims, np_dtype, path)
    return _Loaded(data, (1.0, 1.0, 1.0), "raw", extra={"endian": endian})
