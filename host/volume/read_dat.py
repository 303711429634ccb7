"""volvis ``.dat``: a text header naming the data file, or the 6-byte binary TU Wien header."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from host.volume.core import (
    _MAX_HEADER_BYTES,
    _check_dims,
    _check_spacing,
    _decode_raw,
    _fail,
    _floats,
    _inflate,
    _ints,
    _Loaded,
    _read_bytes,
    _read_head,
)

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
