"""NRRD ``.nrrd`` / ``.nhdr`` through pynrrd."""

from __future__ import annotations

import contextlib
import gzip
import zlib
from pathlib import Path

import numpy as np

from host.volume.core import (
    _check_dims,
    _check_spacing,
    _fail,
    _Loaded,
    _one_line,
    _verify_compressed,
)
from host.volume.orientation import (
    _axis_code_from_directions,
)

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
