"""MetaImage ``.mhd`` / ``.mha`` (ITK), local or detached data, zlib-compressed or not."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from host.errors import VolumeError
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
    _one_line,
    _read_bytes,
)
from host.volume.orientation import (
    _OPPOSITE,
    _axis_code_from_directions,
    _parse_axis_code,
)

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

    file_axes = _file_axes(fields, path)
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


def _file_axes(fields: dict[str, str], path: Path) -> str | None:
    """The file's axis code from AnatomicalOrientation, else a direction matrix
    (TransformMatrix, Orientation or Rotation) that is not the identity; None: neither."""
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
    return file_axes
