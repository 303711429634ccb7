"""The eigenspace image (``.ecs``): an authenticated container for a quantized eigenspace.

File layout (format version 1; 2 or 3 for an image with several looks; every integer
little-endian)::

    offset  size  field
    0       8     magic  b"\\x89ECS\\r\\n\\x1a\\n"  (PNG-style: catches text-mode mangling)
    8       2     format_version  u16 (1; 2: the manifest has ``looks`` sharing one
                  eigenspace's scores; 3: ``looks`` each with its own eigenspace)
    10      2     flags  u16: bit 0 = SIGNED (tag is an HMAC), other bits must be 0
    12      2     header_size  u16 (32 in version 1; the digest covers the whole header)
    14      2     reserved u16 = 0
    16      4     manifest_size  u32, bytes of the CBOR manifest that follows the header
    20      8     image_size  u64, bytes of this container from the magic to the end of the tag
    28      4     header_crc32  u32 over bytes 0..27 (a corrupt header is refused at once)
    32      ..    manifest: one canonical CBOR map (text keys, below)
    ..      ..    sections: one zstd frame each (content size recorded), contiguous, in the
                  order of the manifest's section table
    end-64  32    digest: SHA-256 of every byte before it
    end-32  32    tag: HMAC-SHA256(device key, digest), or 32 zero bytes when unsigned

The *device image* is exactly ``image_size`` bytes (read it from the first 32 bytes with
`image_size`); provisioning sends only that, and the flash store keeps only that. A ``.ecs``
file on the host may continue with a **host annex**: a second container of the same format
(manifest ``kind`` = ``"annex"``, always unsigned) holding what only the host needs (the float
training-score table for interpolation, eigenvalues, ...). The device image's manifest records the
annex's digest and size, so the device image's digest -- and therefore its tag -- covers the annex
transitively, while the device never stores or receives it. Anything after the image (and its
annex, when one is declared) is refused as trailing bytes.

Manifest keys (device image, ``kind`` = ``"image"``):

``image_shape`` [H, W]; ``cell_shape`` [cell_h, cell_w]; ``method`` str;
``image_generation`` int (monotonic, newer images have larger values); ``score_quantization``
map (defaults for score packets, e.g. ``{"step": 1.0}``); ``views`` map or null (the training
view set); ``interpolation`` map or null (data for standalone score interpolation);
``provenance`` map (opaque: fit parameters, solver, sign convention, render settings, creation
time); optional ``synthesis`` map (absent: the device blends; ``{"method": "warp-depth-1",
...}``: depth-aware view synthesis, see `device_runtime.synthesis`); ``annex`` null or
``{"sha256": 32 bytes, "size": int}``; ``looks`` (format versions 2 and 3 only, and required
there) a list of 2..`MAX_LOOKS` maps ``{"name": str, "sections": {standard name: section
name}, "synthesis": map (optional), "score_quantization": map (optional, version 3)}``: the
image shows one look at a time, each the image with the sections its map names in place of
the standard ones (`LOOK_SECTION_NAMES`; the first look usually names none) and its own
``synthesis`` and ``score_quantization`` records when it has them (`device_runtime.looks`).
In version 2 the looks share the first look's scores (``n_components`` and the standalone
table: one eigenspace of all looks); version 3 lets a look name its own (`LOOK_SCORE_SECTIONS`:
an eigenspace of its own, with its own score step); ``sections`` list of
``{"name", "dtype", "shape", "offset", "size", "raw_size"}`` where ``dtype`` is a numpy
little-endian type string (``"|u1"``, ``"|i1"``, ``"<f4"`` ...), ``offset`` counts from the
first byte after the manifest, ``size`` is the compressed and ``raw_size`` the decompressed byte
count. The device image's sections are, in this order, ``n_components`` int32 (n_cells,),
``scales`` float32 (K,), ``mean`` uint8 (n_cells, cell_pixels*3), ``eigenimages`` int8
(K, cell_pixels*3), then any extra named sections. The annex has ``kind``, ``sections`` and an
optional ``meta`` map.

Reading is streaming and bounded: the header and the manifest are checked against the caller's
limits *before* any array is allocated; each zstd frame's recorded content size must equal the
manifest's ``raw_size`` (frames without one are refused); each section is decompressed straight
into its preallocated numpy array; the digest is checked at the end, then the tag. When a
malformed section or manifest is met, the reader first hashes the rest of the image: if the
digest does not match either, it reports the digest mismatch (the root cause of a corrupted
file), chained to the parse error.

This module stays one file (over 1,000 lines) because it is one idea, the ``.ecs`` file
format: the layout above, its writer and its reader (with the manifest and model checks
the reader applies) change together whenever the format does, as one specification.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import io
import math
import os
import struct
import tempfile
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import cbor2
import numpy as np
import zstandard as zstd

from protocol.errors import AuthenticationError, ImageFormatError

__all__ = [
    "DEFAULT_LEVEL",
    "DEVICE_SECTIONS",
    "DIGEST_SIZE",
    "FLAG_SIGNED",
    "FORMAT_VERSION",
    "HEADER_SIZE",
    "LOOKS_FORMAT_VERSION",
    "LOOK_SCORES_FORMAT_VERSION",
    "LOOK_SCORE_SECTIONS",
    "LOOK_SECTION_NAMES",
    "MAGIC",
    "MAX_LOOKS",
    "MAX_LOOK_NAME",
    "MAX_MANIFEST_BYTES",
    "MAX_SECTION_BYTES",
    "MAX_TOTAL_BYTES",
    "MAX_WINDOW_BYTES",
    "SUPPORTED_VERSIONS",
    "TAG_SIZE",
    "EigenspaceImage",
    "ImageHeader",
    "ImageTagError",
    "ImageTruncatedError",
    "image_size",
    "parse_header",
    "read_image",
    "read_manifest",
    "verify_stream",
    "write_image",
]

MAGIC = b"\x89ECS\r\n\x1a\n"
FORMAT_VERSION = 1
#: The format version of an image with several looks (manifest ``looks``): a reader that
#: predates looks refuses it in one line ("unsupported format version 2") instead of
#: showing one of its looks as if it were the whole image.
LOOKS_FORMAT_VERSION = 2
#: The format version of an image whose looks have eigenspaces of their own (a look names its
#: own ``n_components`` and standalone table): a reader of version 2 refuses it in one line.
LOOK_SCORES_FORMAT_VERSION = 3
SUPPORTED_VERSIONS: tuple[int, ...] = (1, LOOKS_FORMAT_VERSION, LOOK_SCORES_FORMAT_VERSION)
#: Most looks one image holds.
MAX_LOOKS = 16
#: Longest look name, in characters.
MAX_LOOK_NAME = 32
#: The sections a look may replace: the colour eigenspace's (the first four of every
#: image) and the named extra sections a view synthesis reads. A look names, for each one it
#: replaces, the image section that holds its own (e.g. ``{"mean": "look1_mean"}``).
LOOK_SECTION_NAMES = frozenset({
    "n_components", "mean", "scales", "eigenimages", "noise_floor", "depth_counts",
    "depth_scales", "depth_mean", "depth_components", "depth_scores", "depth_scores_delta",
    "standalone_scores", "standalone_scores_delta"})
#: The sections of a look's own scores: only in format version 3.
LOOK_SCORE_SECTIONS = frozenset({"n_components", "standalone_scores",
                                 "standalone_scores_delta"})
FLAG_SIGNED = 0x0001
_KNOWN_FLAGS = FLAG_SIGNED

_HEADER = struct.Struct("<8sHHHHIQI")
HEADER_SIZE = _HEADER.size  # 32
_CRC_SPAN = HEADER_SIZE - 4
DIGEST_SIZE = 32
TAG_SIZE = 32
_TRAILER_SIZE = DIGEST_SIZE + TAG_SIZE
_ZERO_TAG = bytes(TAG_SIZE)

#: Default limits of `read_image` (a device passes limits derived from its RAM budget).
MAX_MANIFEST_BYTES = 1 << 20
MAX_SECTION_BYTES = 2 << 30
MAX_TOTAL_BYTES = 4 << 30
#: Largest zstd window a reader accepts (levels <= 19 never need more than 8 MiB).
MAX_WINDOW_BYTES = 1 << 23

#: zstd level of `write_image` (1..19; higher levels would need a larger decoder window).
#: Measured on int8 eigenimages of a real adaptive fit (brainsmall, 776 components x 432):
#: level 3 -> 0.859 of the raw size at ~240 MB/s, level 9 -> 0.854 at ~27 MB/s, level 19 ->
#: 0.833 at ~2 MB/s; quantized eigenimages are close to incompressible, so 3 it is.
DEFAULT_LEVEL = 3
_MAX_LEVEL = 19
_CHUNK_BYTES = 1 << 20
_READ_BYTES = 1 << 16
_ZSTD_MAX_FRAME_HEADER = 18
_MAX_NAME_CHARS = 64
_MAX_NDIM = 8
_MAX_SECTIONS = 256
_MAX_IMAGE_SIDE = 65535

#: The four sections every image starts with, in this order (the colour eigenspace; the
#: `EigenspaceImage` fields of the same names); a look may name its own of each.
DEVICE_SECTIONS = ("n_components", "scales", "mean", "eigenimages")
_ALLOWED_DTYPES = frozenset(
    ["|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"]
)


class ImageTagError(ImageFormatError, AuthenticationError):
    """The image's authentication tag is wrong or missing where one is required."""


@dataclass(frozen=True)
class ImageHeader:
    """The fixed 32-byte header of a container (see the module docstring)."""

    format_version: int
    flags: int
    header_size: int
    manifest_size: int
    image_size: int

    @property
    def signed(self) -> bool:
        """Whether the tag is an HMAC (``False``: the tag is 32 zero bytes)."""
        return bool(self.flags & FLAG_SIGNED)


@dataclass(eq=False)
class EigenspaceImage:
    """A quantized eigenspace and its manifest, as stored in an ``.ecs`` file.

    Parameters
    ----------
    image_shape : tuple of int
        ``(height, width)`` of the reconstructed images in pixels.
    cell_shape : tuple of int
        ``(cell_h, cell_w)``; the image is zero-padded at the bottom/right to whole cells.
    mean : ndarray of shape (n_cells, cell_pixels * 3), uint8
        Per-cell mean image, cells in row-major order.
    eigenimages : ndarray of shape (n_components_total, cell_pixels * 3), int8
        Quantized components, cell-major (cell c's rows are offsets[c]:offsets[c+1]).
    scales : ndarray of shape (n_components_total,), float32
        ``component_j ~= scales[j] * eigenimages[j]``.
    n_components : ndarray of shape (n_cells,), int32
        Components kept per cell (0: the cell shows its mean).
    method : str
        ``"standard"``, ``"cell"`` or ``"adaptive"`` (informational).
    image_generation : int
        Monotonic generation number (a device refuses to roll back to an older one).
    score_quantization : dict
        Score-packet quantization defaults, e.g. ``{"step": 1.0}``.
    views : dict or None
        The training view set (e.g. ``{"spec": "grid:100x15", "phi_deg": [...], ...}``).
    interpolation : dict or None
        Data for standalone score interpolation on the device.
    provenance : dict
        Opaque record of how the image was made (CBOR-encodable values only).
    sections : dict of str to ndarray
        Extra named device sections (e.g. a training score table for standalone mode).
    annex : dict of str to ndarray or None
        Host-only arrays stored in the annex (``None``: no annex).
    synthesis : dict or None
        How a device makes novel views from the training views beyond blending them
        (``{"method": "warp-depth-1", ...}``, `device_runtime.synthesis`); written to the
        manifest only when set, so images without it are byte-identical to older ones.
    looks : list of dict or None
        Several looks of the same views (``[{"name": ..., "sections": {...}}, ...]``, the
        module docstring); written only when set, with format version 2 (None: one look,
        format version 1, byte-identical to images that predate looks).

    Attributes
    ----------
    digest : bytes or None
        SHA-256 digest of the device image (set by `read_image` / `write_image` callers).
    signed : bool
        Whether the image read carried an HMAC tag.
    tag_verified : bool
        Whether that tag was checked against a key and matched.
    """

    image_shape: tuple[int, int]
    cell_shape: tuple[int, int]
    mean: np.ndarray
    eigenimages: np.ndarray
    scales: np.ndarray
    n_components: np.ndarray
    method: str = "adaptive"
    image_generation: int = 0
    score_quantization: dict = field(default_factory=lambda: {"step": 1.0})
    views: dict | None = None
    interpolation: dict | None = None
    provenance: dict = field(default_factory=dict)
    sections: dict[str, np.ndarray] = field(default_factory=dict)
    synthesis: dict | None = None
    looks: list[dict] | None = None
    annex: dict[str, np.ndarray] | None = None
    digest: bytes | None = None
    signed: bool = False
    tag_verified: bool = False

    @property
    def grid_shape(self) -> tuple[int, int]:
        """``(n_cells_y, n_cells_x)``."""
        return _grid_shape(self.image_shape, self.cell_shape)

    @property
    def n_cells(self) -> int:
        """Number of cells, ``n_cells_y * n_cells_x``."""
        ny, nx = self.grid_shape
        return ny * nx

    @property
    def cell_values(self) -> int:
        """Entries of one cell vector, ``cell_h * cell_w * 3``."""
        return self.cell_shape[0] * self.cell_shape[1] * 3

    @property
    def n_coefficients(self) -> int:
        """Total number of components K (the length of a score vector)."""
        return int(self.eigenimages.shape[0])

    @property
    def component_offsets(self) -> np.ndarray:
        """int64 (n_cells + 1,): ``[0, cumsum(n_components)]``."""
        return np.concatenate([[0], np.cumsum(self.n_components, dtype=np.int64)])

    def check(self) -> None:
        """Raise ``ValueError`` naming the first inconsistency between fields and arrays."""
        problem = _model_problem(
            self.image_shape,
            self.cell_shape,
            self.mean,
            self.eigenimages,
            self.scales,
            self.n_components,
        )
        if problem:
            raise ValueError(f"EigenspaceImage: {problem}")
        for name, arr in {**self.sections, **(self.annex or {})}.items():
            _check_extra_section(name, arr)
        reserved = set(self.sections) & set(DEVICE_SECTIONS)
        if reserved:
            raise ValueError(
                f"EigenspaceImage: extra section names {sorted(reserved)} are reserved"
            )
        if not isinstance(self.image_generation, int) or self.image_generation < 0:
            raise ValueError(
                f"EigenspaceImage: image_generation={self.image_generation!r} must be an int >= 0"
            )
        if self.looks is not None:
            problem = _looks_problem(self.looks, {"n_components", "mean", "scales",
                                                  "eigenimages", *self.sections},
                                     LOOK_SCORES_FORMAT_VERSION)
            if problem:
                raise ValueError(f"EigenspaceImage: {problem}")

    @property
    def format_version(self) -> int:
        """The format version this image is written with: 3 with looks that have their
        own scores, 2 with looks sharing the first's, else 1."""
        if self.looks is None:
            return FORMAT_VERSION
        if any(LOOK_SCORE_SECTIONS & set(look.get("sections") or ()) for look in self.looks):
            return LOOK_SCORES_FORMAT_VERSION
        return LOOKS_FORMAT_VERSION


# --------------------------------------------------------------------------- header


def parse_header(
    data: bytes, *, max_manifest_bytes: int = MAX_MANIFEST_BYTES, what: str = "image"
) -> ImageHeader:
    """Decode and check the fixed 32-byte header at the start of ``data``.

    Parameters
    ----------
    data : bytes
        At least the first `HEADER_SIZE` bytes of a container.
    max_manifest_bytes : int
        Largest manifest accepted.
    what : str
        Name of the source for error messages.

    Returns
    -------
    ImageHeader

    Raises
    ------
    ImageFormatError
        Short input, bad magic, header CRC mismatch, unsupported version, unknown flags or
        inconsistent sizes.
    """
    if len(data) < HEADER_SIZE:
        raise ImageFormatError(
            f"read {what}: truncated header: expected {HEADER_SIZE} bytes, got {len(data)}"
        )
    magic, version, flags, header_size, reserved, manifest_size, size, crc = _HEADER.unpack_from(
        data
    )
    if magic != MAGIC:
        raise ImageFormatError(
            f"read {what}: bad magic {magic!r} (expected {MAGIC!r}): not an eigencast image"
        )
    computed = zlib.crc32(data[:_CRC_SPAN])
    if crc != computed:
        raise ImageFormatError(
            f"read {what}: header CRC mismatch: stored 0x{crc:08x}, computed 0x{computed:08x}"
        )
    if version not in SUPPORTED_VERSIONS:
        raise ImageFormatError(
            f"read {what}: unsupported format version {version} "
            f"(supported: {', '.join(map(str, SUPPORTED_VERSIONS))})"
        )
    if flags & ~_KNOWN_FLAGS:
        raise ImageFormatError(
            f"read {what}: unknown header flags 0x{flags & ~_KNOWN_FLAGS:04x} "
            f"(known: 0x{_KNOWN_FLAGS:04x})"
        )
    if header_size != HEADER_SIZE or reserved != 0:
        raise ImageFormatError(
            f"read {what}: header_size={header_size}, reserved={reserved} "
            f"(version {version} needs {HEADER_SIZE} and 0)"
        )
    if manifest_size > max_manifest_bytes:
        raise ImageFormatError(
            f"read {what}: manifest too large: {manifest_size} bytes "
            f"(limit max_manifest_bytes={max_manifest_bytes})"
        )
    if size < HEADER_SIZE + manifest_size + _TRAILER_SIZE:
        raise ImageFormatError(
            f"read {what}: image_size={size} is smaller than header + manifest + trailer "
            f"({HEADER_SIZE + manifest_size + _TRAILER_SIZE})"
        )
    return ImageHeader(version, flags, header_size, manifest_size, size)


def image_size(header_bytes: bytes) -> int:
    """Return the device image's size in bytes from its first `HEADER_SIZE` bytes.

    Raises `ImageFormatError` when the header is malformed.
    """
    return parse_header(header_bytes).image_size


# --------------------------------------------------------------------------- writing


def write_image(
    path: str | os.PathLike,
    image: EigenspaceImage,
    *,
    key: bytes | None = None,
    annex: Mapping[str, np.ndarray] | None = None,
    level: int = DEFAULT_LEVEL,
    annex_meta: Mapping[str, Any] | None = None,
) -> bytes:
    """Write ``image`` to ``path`` atomically; return the device image's SHA-256 digest.

    The file is written to a temporary file in the same folder, fsynced and renamed over
    ``path``; a failure leaves no partial file. Sections are compressed chunk by chunk into a
    temporary spool file (the manifest, which precedes them, records their compressed sizes), so
    memory does not grow with the file beyond the arrays already in memory.

    Parameters
    ----------
    path : path-like
        Destination file.
    image : EigenspaceImage
        The image; ``image.annex`` is used when ``annex`` is not given.
    key : bytes, optional
        Device key (>= 16 bytes, normally 32); signs the image with HMAC-SHA256 over its digest.
        Without a key the tag is 32 zero bytes and the SIGNED flag is clear.
    annex : mapping of str to ndarray, optional
        Host-only arrays, written as a host annex after the device image.
    level : int
        zstd level, 1..19.
    annex_meta : mapping, optional
        Small CBOR-encodable map stored in the annex manifest.

    Returns
    -------
    bytes
        The 32-byte SHA-256 digest of the device image (what the tag signs).
    """
    image.check()
    if annex is None:
        annex = image.annex
    if key is not None and (not isinstance(key, bytes | bytearray) or len(key) < 16):
        raise ValueError("write_image: key must be bytes of length >= 16 (normally 32)")
    if not isinstance(level, int) or not 1 <= level <= _MAX_LEVEL:
        raise ValueError(f"write_image: level={level!r} must be an int in 1..{_MAX_LEVEL}")
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp_name = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_current_umask())
        with os.fdopen(fd, "wb") as out, contextlib.ExitStack() as stack:
            annex_file = None
            annex_record = None
            if annex is not None:
                arrays = [(name, np.asarray(arr)) for name, arr in annex.items()]
                for name, arr in arrays:
                    _check_extra_section(name, arr)
                annex_file = stack.enter_context(tempfile.TemporaryFile(dir=folder))
                manifest = {"kind": "annex", "meta": dict(annex_meta or {})}
                annex_digest, annex_size = _write_container(
                    annex_file, manifest, arrays, key=None, level=level, tmp_dir=folder
                )
                annex_record = {"sha256": annex_digest, "size": annex_size}
            manifest, arrays = _image_manifest(image, annex_record)
            digest, _ = _write_container(
                out, manifest, arrays, key=key, level=level, tmp_dir=folder,
                version=image.format_version,
            )
            if annex_file is not None:
                annex_file.seek(0)
                while chunk := annex_file.read(_CHUNK_BYTES):
                    out.write(chunk)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        raise
    _fsync_folder(folder)
    return digest


def _image_manifest(image: EigenspaceImage, annex_record: dict | None
                    ) -> tuple[dict[str, Any], list[tuple[str, np.ndarray]]]:
    """The device image's manifest (its annex's digest and size in it) and its sections, in
    the order they are written."""
    manifest: dict[str, Any] = {
        "kind": "image",
        "image_shape": [int(v) for v in image.image_shape],
        "cell_shape": [int(v) for v in image.cell_shape],
        "method": str(image.method),
        "image_generation": int(image.image_generation),
        "score_quantization": dict(image.score_quantization),
        "views": image.views,
        "interpolation": image.interpolation,
        "provenance": dict(image.provenance),
        "annex": annex_record,
    }
    if image.synthesis is not None:
        manifest["synthesis"] = dict(image.synthesis)
    if image.looks is not None:
        manifest["looks"] = [dict(look) for look in image.looks]
    arrays = [
        ("n_components", np.asarray(image.n_components, dtype=np.int32)),
        ("scales", np.asarray(image.scales, dtype=np.float32)),
        ("mean", image.mean),
        ("eigenimages", image.eigenimages),
        *image.sections.items(),
    ]
    return manifest, arrays


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_folder(folder: Path) -> None:
    try:
        dir_fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(dir_fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(dir_fd)


def _write_container(
    out: BinaryIO,
    manifest: dict,
    arrays: list[tuple[str, np.ndarray]],
    *,
    key: bytes | None,
    level: int,
    tmp_dir: Path,
    version: int = FORMAT_VERSION,
) -> tuple[bytes, int]:
    """Write one complete container to ``out``; return (digest, size in bytes)."""
    cctx = zstd.ZstdCompressor(level=level, write_content_size=True, write_checksum=False)
    table = []
    with tempfile.TemporaryFile(dir=tmp_dir) as spool:
        offset = 0
        for name, arr in arrays:
            little = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
            flat = little.reshape(-1).view(np.uint8)
            with cctx.stream_writer(spool, size=flat.size, closefd=False) as writer:
                for start in range(0, flat.size, _CHUNK_BYTES):
                    writer.write(flat[start : start + _CHUNK_BYTES])
            end = spool.tell()
            table.append(
                {
                    "name": name,
                    "dtype": little.dtype.str,
                    "shape": [int(v) for v in little.shape],
                    "offset": offset,
                    "size": end - offset,
                    "raw_size": int(flat.size),
                }
            )
            offset = end
        manifest = {**manifest, "sections": table}
        try:
            manifest_bytes = cbor2.dumps(manifest, canonical=True)
        except (cbor2.CBOREncodeError, TypeError, ValueError) as exc:
            raise ValueError(f"write_image: manifest is not CBOR-encodable: {exc}") from exc
        if len(manifest_bytes) > MAX_MANIFEST_BYTES:
            raise ValueError(
                f"write_image: manifest is {len(manifest_bytes)} bytes, over the "
                f"{MAX_MANIFEST_BYTES}-byte limit readers apply (store big data in a section)"
            )
        size = HEADER_SIZE + len(manifest_bytes) + offset + _TRAILER_SIZE
        flags = FLAG_SIGNED if key is not None else 0
        head = _HEADER.pack(
            MAGIC, version, flags, HEADER_SIZE, 0, len(manifest_bytes), size, 0
        )[:_CRC_SPAN]
        head += struct.pack("<I", zlib.crc32(head))
        hasher = hashlib.sha256()
        for piece in (head, manifest_bytes):
            hasher.update(piece)
            out.write(piece)
        spool.seek(0)
        while chunk := spool.read(_CHUNK_BYTES):
            hasher.update(chunk)
            out.write(chunk)
    digest = hasher.digest()
    tag = hmac.new(bytes(key), digest, hashlib.sha256).digest() if key is not None else _ZERO_TAG
    out.write(digest + tag)
    return digest, size


# --------------------------------------------------------------------------- reading


class ImageTruncatedError(ImageFormatError):
    """The data ends before the length its header declares."""


class _Source:
    """A sequential byte source with position tracking, optional hashing and clear errors."""

    def __init__(self, f: BinaryIO, name: str, size: int | None) -> None:
        self.f = f
        self.name = name
        self.size = size
        self.pos = 0
        self.hasher: Any = None
        self.expected_end: int | None = None
        self._pushback = b""

    def at_eof(self) -> bool:
        """Whether no byte follows (peeks one byte from a stream of unknown size)."""
        if self.size is not None:
            return self.pos >= self.size
        if not self._pushback:
            self._pushback = bytes(self.f.read(1) or b"")
        return not self._pushback

    def read_some(self, n: int) -> bytes:
        if n <= 0:
            return b""
        if self._pushback:
            data, self._pushback = self._pushback, b""
            if n > 1:
                data += bytes(self.f.read(n - 1) or b"")
        else:
            data = bytes(self.f.read(n) or b"")
        self.pos += len(data)
        if self.hasher is not None:
            self.hasher.update(data)
        return data

    def read_exact(self, n: int, what: str) -> bytes:
        parts = []
        remaining = n
        while remaining > 0:
            chunk = self.read_some(min(remaining, _CHUNK_BYTES))
            if not chunk:
                expected = self.expected_end if self.expected_end is not None else n
                raise ImageTruncatedError(
                    f"read {self.name}: truncated in {what}: expected {expected} bytes, "
                    f"the data ends after {self.pos}"
                )
            parts.append(chunk)
            remaining -= len(chunk)
        return b"".join(parts)


class _BoundedReader(io.RawIOBase):
    """At most ``limit`` bytes of a `_Source`, preceded by already-read ``head`` bytes."""

    def __init__(self, src: _Source, head: bytes, limit: int) -> None:
        super().__init__()
        self.src = src
        self.head = head
        self.remaining = limit

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        if self.head:
            out, self.head = (
                (self.head, b"") if n < 0 or n >= len(self.head) else (self.head[:n], self.head[n:])
            )
            return out
        if n < 0 or n > self.remaining:
            n = self.remaining
        data = self.src.read_some(n) if n else b""
        self.remaining -= len(data)
        if n and not data:
            raise ImageTruncatedError(
                f"read {self.src.name}: truncated in a section: expected "
                f"{self.src.expected_end} bytes, the data ends after {self.src.pos}"
            )
        return data

    def readinto(self, buffer: Any) -> int:  # pragma: no cover - zstd calls read()
        data = self.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)


@contextlib.contextmanager
def _open_source(source: str | os.PathLike | BinaryIO) -> Iterator[_Source]:
    if isinstance(source, str | os.PathLike):
        name = f"'{os.fspath(source)}'"
        try:
            f = open(source, "rb")  # noqa: SIM115 - closed below
        except FileNotFoundError:
            raise ImageFormatError(f"read image {name}: no such file") from None
        except IsADirectoryError:
            raise ImageFormatError(f"read image {name}: is a folder, not an image file") from None
        with f:
            yield _Source(f, f"image {name}", os.fstat(f.fileno()).st_size)
    else:
        raw_name = getattr(source, "name", None)
        name = f"image '{raw_name}'" if isinstance(raw_name, str) else "image stream"
        yield _Source(source, name, None)


def read_manifest(
    source: str | os.PathLike | BinaryIO, *, max_manifest_bytes: int = MAX_MANIFEST_BYTES
) -> dict:
    """Read only the header and manifest (cheap; no digest or tag check).

    Returns the manifest map with an extra ``"header"`` entry: ``format_version``, ``flags``,
    ``signed``, ``manifest_size`` and ``image_size``.
    """
    with _open_source(source) as src:
        header = parse_header(
            src.read_exact(HEADER_SIZE, "the header"),
            max_manifest_bytes=max_manifest_bytes,
            what=src.name,
        )
        manifest = _decode_manifest(src.read_exact(header.manifest_size, "the manifest"), src)
    manifest["header"] = {
        "format_version": header.format_version,
        "flags": header.flags,
        "signed": header.signed,
        "manifest_size": header.manifest_size,
        "image_size": header.image_size,
    }
    return manifest


def verify_stream(fileobj: BinaryIO, key: bytes | None = None) -> tuple[bytes, bool]:
    """Check a device image's digest (and tag) from a stream, with bounded memory.

    Reads exactly the image's ``image_size`` bytes (not what may follow, e.g. an annex).

    Parameters
    ----------
    fileobj : binary file
        Positioned at the image's first byte.
    key : bytes, optional
        Device key to check the tag with.

    Returns
    -------
    digest : bytes
        The verified 32-byte SHA-256 digest.
    tag_ok : bool
        ``True`` only when a key was given, the image is signed and its tag matches.

    Raises
    ------
    ImageFormatError
        Malformed header, truncation or digest mismatch.
    """
    src = _Source(fileobj, "image stream", None)
    src.hasher = hashlib.sha256()
    header = parse_header(src.read_exact(HEADER_SIZE, "the header"), what=src.name)
    src.expected_end = header.image_size
    remaining = header.image_size - HEADER_SIZE - _TRAILER_SIZE
    while remaining > 0:
        remaining -= len(src.read_exact(min(remaining, _CHUNK_BYTES), "the image body"))
    digest = src.hasher.digest()
    src.hasher = None
    stored = src.read_exact(DIGEST_SIZE, "the digest")
    tag = src.read_exact(TAG_SIZE, "the tag")
    _check_digest(stored, digest, src.name)
    if not header.signed:
        if tag != _ZERO_TAG:
            raise ImageFormatError(f"read {src.name}: unsigned image has a non-zero tag")
        return digest, False
    if key is None:
        return digest, False
    return digest, hmac.compare_digest(tag, hmac.new(bytes(key), digest, hashlib.sha256).digest())


def read_image(
    source: str | os.PathLike | BinaryIO,
    *,
    key: bytes | None = None,
    require_tag: bool = False,
    max_manifest_bytes: int = MAX_MANIFEST_BYTES,
    max_section_bytes: int = MAX_SECTION_BYTES,
    max_total_bytes: int = MAX_TOTAL_BYTES,
    max_window_bytes: int = MAX_WINDOW_BYTES,
    read_annex: bool = True,
    require_annex: bool = False,
) -> EigenspaceImage:
    """Read, bound-check and verify an eigenspace image (streaming, single pass).

    Parameters
    ----------
    source : path-like or binary file
        A ``.ecs`` file, or a stream positioned at the image's first byte.
    key : bytes, optional
        Device key; when given, a signed image's tag must match it.
    require_tag : bool
        Refuse unsigned images (needs ``key``).
    max_manifest_bytes, max_section_bytes, max_total_bytes : int
        Limits checked before allocating: manifest size, decompressed size of one section and
        of all sections of one container together.
    max_window_bytes : int
        Largest zstd window accepted (decoder memory).
    read_annex : bool
        Also read the host annex when the manifest declares one (``False``: stop after the
        device image and ignore what follows).
    require_annex : bool
        Refuse a file whose declared annex is missing (by default a device-only copy is fine
        and ``annex`` is ``None``).

    Returns
    -------
    EigenspaceImage
        With ``digest``, ``signed`` and ``tag_verified`` set.

    Raises
    ------
    ImageFormatError
        Any malformed, truncated, oversize or corrupted input (one line naming the problem);
        `ImageTagError` (also an ``AuthenticationError``) for a wrong or missing tag.
    """
    if require_tag and key is None:
        raise ValueError("read_image: require_tag=True needs a key")
    limits = _Limits(max_manifest_bytes, max_section_bytes, max_total_bytes, max_window_bytes)
    with _open_source(source) as src:
        manifest, arrays, digest, signed, tag_ok = _read_container(
            src, "image", limits, key=key, require_tag=require_tag
        )
        annex_arrays = None
        annex_record = manifest["annex"]
        if read_annex:
            if annex_record is not None:
                start = src.pos
                if src.at_eof():
                    if require_annex:
                        raise ImageFormatError(
                            f"read {src.name}: the manifest declares a "
                            f"{annex_record['size']}-byte annex but the data ends at byte {start}"
                        )
                else:
                    _, annex_arrays, annex_digest, _, _ = _read_container(
                        src, "annex", limits, key=None, require_tag=False
                    )
                    size = src.pos - start
                    if size != annex_record["size"] or annex_digest != annex_record["sha256"]:
                        raise ImageFormatError(
                            f"read {src.name}: annex digest mismatch: the manifest records "
                            f"{annex_record['sha256'].hex()[:16]}... ({annex_record['size']} "
                            f"bytes), the annex is {annex_digest.hex()[:16]}... ({size} bytes)"
                        )
            _check_no_trailing(src)
    image = EigenspaceImage(
        image_shape=tuple(manifest["image_shape"]),
        cell_shape=tuple(manifest["cell_shape"]),
        mean=arrays.pop("mean"),
        eigenimages=arrays.pop("eigenimages"),
        scales=arrays.pop("scales"),
        n_components=arrays.pop("n_components"),
        method=manifest["method"],
        image_generation=manifest["image_generation"],
        score_quantization=manifest["score_quantization"],
        views=manifest["views"],
        interpolation=manifest["interpolation"],
        provenance=manifest["provenance"],
        sections=arrays,
        synthesis=manifest.get("synthesis"),
        looks=manifest.get("looks"),
        annex=annex_arrays,
        digest=digest,
        signed=signed,
        tag_verified=tag_ok,
    )
    return image


def _check_no_trailing(src: _Source) -> None:
    if src.at_eof():
        return
    extra = f"{src.size - src.pos} trailing bytes" if src.size is not None else "trailing bytes"
    raise ImageFormatError(f"read {src.name}: {extra} after the image end at byte {src.pos}")


@dataclass(frozen=True)
class _Limits:
    manifest: int
    section: int
    total: int
    window: int


def _read_container(
    src: _Source, kind: str, limits: _Limits, *, key: bytes | None, require_tag: bool
) -> tuple[dict, dict[str, np.ndarray], bytes, bool, bool]:
    start = src.pos
    src.hasher = hashlib.sha256()
    what = src.name if kind == "image" else f"{src.name} annex"
    header = parse_header(
        src.read_exact(HEADER_SIZE, f"the {kind} header"),
        max_manifest_bytes=limits.manifest,
        what=what,
    )
    end = start + header.image_size
    src.expected_end = end
    if src.size is not None and src.size < end:
        raise ImageTruncatedError(
            f"read {what}: truncated: expected {end} bytes, the file has {src.size}"
        )
    body_end = end - _TRAILER_SIZE
    try:
        manifest = _decode_manifest(src.read_exact(header.manifest_size, "the manifest"), src)
        data_start = src.pos
        table = _check_manifest(manifest, kind, body_end - data_start, limits, what,
                                version=header.format_version)
        dctx = zstd.ZstdDecompressor(max_window_size=limits.window)
        arrays: dict[str, np.ndarray] = {}
        for entry in table:
            arrays[entry["name"]] = _read_section(src, entry, dctx, limits, what)
            if entry["name"] == "n_components":
                _check_n_components(arrays["n_components"], table, what)
        if kind == "image":
            bad = np.flatnonzero(~np.isfinite(arrays["scales"]) | (arrays["scales"] < 0))
            if bad.size:
                raise ImageFormatError(
                    f"read {what}: scales[{bad[0]}]={arrays['scales'][bad[0]]!r} must be "
                    "finite and >= 0"
                )
    except ImageTruncatedError:
        raise
    except ImageFormatError as exc:
        _drain_and_check_digest(src, body_end, exc)
        raise
    digest = src.hasher.digest()
    src.hasher = None
    stored = src.read_exact(DIGEST_SIZE, "the digest")
    tag = src.read_exact(TAG_SIZE, "the tag")
    _check_digest(stored, digest, what)
    tag_ok = False
    if header.signed:
        if key is not None:
            expected = hmac.new(bytes(key), digest, hashlib.sha256).digest()
            if not hmac.compare_digest(tag, expected):
                raise ImageTagError(
                    f"read {what}: tag mismatch: the image was signed with another key "
                    "(or altered after signing)"
                )
            tag_ok = True
    else:
        if tag != _ZERO_TAG:
            raise ImageFormatError(f"read {what}: unsigned image has a non-zero tag")
        if require_tag:
            raise ImageTagError(
                f"read {what}: the image is not signed and a signed image is required "
                "(write it with a key, e.g. `eigencast fit --key KEYFILE`)"
            )
    return manifest, arrays, digest, header.signed, tag_ok


def _drain_and_check_digest(src: _Source, body_end: int, exc: ImageFormatError) -> None:
    """After a parse error: hash the rest; a digest mismatch is the better report."""
    try:
        while src.pos < body_end:
            if not src.read_some(min(body_end - src.pos, _CHUNK_BYTES)):
                return
        if src.pos != body_end:  # a section reader overran the body: nothing to compare
            return
        digest = src.hasher.digest()
        src.hasher = None
        stored = src.read_exact(DIGEST_SIZE, "the digest")
    except (ImageFormatError, OSError):
        return
    if stored != digest:
        raise ImageFormatError(
            f"read {src.name}: digest mismatch: stored {stored.hex()[:16]}..., computed "
            f"{digest.hex()[:16]}... (the file is corrupted; first problem found: {exc})"
        ) from exc


def _check_digest(stored: bytes, digest: bytes, what: str) -> None:
    if stored != digest:
        raise ImageFormatError(
            f"read {what}: digest mismatch: stored {stored.hex()[:16]}..., computed "
            f"{digest.hex()[:16]}..."
        )


def _decode_manifest(data: bytes, src: _Source) -> dict:
    stream = io.BytesIO(data)
    try:
        manifest = cbor2.CBORDecoder(stream).decode()
    except (cbor2.CBORDecodeError, ValueError, TypeError, OverflowError, RecursionError) as exc:
        raise ImageFormatError(f"read {src.name}: manifest is not valid CBOR: {exc}") from None
    if stream.tell() != len(data):
        raise ImageFormatError(
            f"read {src.name}: {len(data) - stream.tell()} stray bytes after the CBOR manifest"
        )
    if not isinstance(manifest, dict):
        raise ImageFormatError(
            f"read {src.name}: manifest is a CBOR {type(manifest).__name__}, expected a map"
        )
    return manifest


def _field(manifest: dict, key: str, types: type | tuple[type, ...], what: str) -> Any:
    if key not in manifest:
        raise ImageFormatError(f"read {what}: manifest lacks the '{key}' entry")
    value = manifest[key]
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in _as_tuple(types)):
        names = " or ".join(t.__name__ for t in _as_tuple(types))
        raise ImageFormatError(
            f"read {what}: manifest '{key}' is a {type(value).__name__}, expected {names}"
        )
    return value


def _as_tuple(types: type | tuple[type, ...]) -> tuple[type, ...]:
    return types if isinstance(types, tuple) else (types,)


def _int_pair(manifest: dict, key: str, what: str) -> tuple[int, int]:
    value = _field(manifest, key, list, what)
    if (
        len(value) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)
        or not all(1 <= v <= _MAX_IMAGE_SIDE for v in value)
    ):
        raise ImageFormatError(
            f"read {what}: manifest '{key}'={value!r} must be two ints in 1..{_MAX_IMAGE_SIDE}"
        )
    return value[0], value[1]


def _check_manifest(
    manifest: dict, kind: str, body_size: int, limits: _Limits, what: str,
    *, version: int = FORMAT_VERSION,
) -> list[dict]:
    """Check the manifest and its section table against sizes and limits; return the table."""
    found = _field(manifest, "kind", str, what)
    if found != kind:
        raise ImageFormatError(f"read {what}: manifest kind is '{found}', expected '{kind}'")
    table = _field(manifest, "sections", list, what)
    if len(table) > _MAX_SECTIONS:
        raise ImageFormatError(f"read {what}: {len(table)} sections (limit {_MAX_SECTIONS})")
    offset = 0
    total_raw = 0
    names: set[str] = set()
    for i, entry in enumerate(table):
        if not isinstance(entry, dict):
            raise ImageFormatError(f"read {what}: section table entry {i} is not a map")
        name = _field(entry, "name", str, what)
        where = f"{what} section '{name[:_MAX_NAME_CHARS]}'"
        if not name or len(name) > _MAX_NAME_CHARS or name in names:
            raise ImageFormatError(
                f"read {where}: names must be 1..{_MAX_NAME_CHARS} characters and unique"
            )
        names.add(name)
        dtype = _field(entry, "dtype", str, where)
        if dtype not in _ALLOWED_DTYPES:
            raise ImageFormatError(
                f"read {where}: dtype '{dtype}' not allowed (allowed: "
                f"{', '.join(sorted(_ALLOWED_DTYPES))})"
            )
        shape = _field(entry, "shape", list, where)
        if len(shape) > _MAX_NDIM or not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in shape
        ):
            raise ImageFormatError(
                f"read {where}: shape {shape!r} must be <= {_MAX_NDIM} ints >= 0"
            )
        raw_size = math.prod(shape) * np.dtype(dtype).itemsize
        declared_raw = _field(entry, "raw_size", int, where)
        if declared_raw != raw_size:
            raise ImageFormatError(
                f"read {where}: raw_size={declared_raw} disagrees with shape {shape} x "
                f"{np.dtype(dtype).itemsize} bytes = {raw_size}"
            )
        if raw_size > limits.section:
            raise ImageFormatError(
                f"read {where}: {raw_size} bytes decompressed, over the limit "
                f"max_section_bytes={limits.section}"
            )
        total_raw += raw_size
        if total_raw > limits.total:
            raise ImageFormatError(
                f"read {what}: sections need {total_raw}+ bytes decompressed, over the limit "
                f"max_total_bytes={limits.total}"
            )
        section_offset = _field(entry, "offset", int, where)
        size = _field(entry, "size", int, where)
        if section_offset != offset or size < 0 or offset + size > body_size:
            raise ImageFormatError(
                f"read {where}: section out of bounds: offset {section_offset} size {size} "
                f"(expected offset {offset}, {body_size} section bytes in the image)"
            )
        if size > raw_size + (raw_size >> 7) + 1024:
            raise ImageFormatError(
                f"read {where}: {size} compressed bytes for {raw_size} raw bytes is more than "
                "zstd ever needs"
            )
        offset += size
    if offset != body_size:
        raise ImageFormatError(
            f"read {what}: sections cover {offset} bytes but the image has {body_size} "
            "section bytes"
        )
    if kind == "image":
        _check_image_manifest(manifest, table, what)
        _check_looks_manifest(manifest, names, version, what)
    elif version != FORMAT_VERSION:
        raise ImageFormatError(f"read {what}: format version {version} (an annex is version "
                               f"{FORMAT_VERSION})")
    else:
        meta = manifest.get("meta", {})
        if not isinstance(meta, dict):
            raise ImageFormatError(f"read {what}: annex 'meta' must be a map")
    return table


def _check_image_manifest(manifest: dict, table: list[dict], what: str) -> None:
    image_shape = _int_pair(manifest, "image_shape", what)
    cell_shape = _int_pair(manifest, "cell_shape", what)
    _field(manifest, "method", str, what)
    generation = _field(manifest, "image_generation", int, what)
    if generation < 0:
        raise ImageFormatError(f"read {what}: image_generation={generation} must be >= 0")
    _field(manifest, "score_quantization", dict, what)
    _field(manifest, "provenance", dict, what)
    for key in ("views", "interpolation"):
        _field(manifest, key, (dict, type(None)), what)
    if not isinstance(manifest.get("synthesis"), (dict, type(None))):
        raise ImageFormatError(f"read {what}: manifest 'synthesis' must be a map or null")
    annex = _field(manifest, "annex", (dict, type(None)), what)
    if annex is not None:
        sha = _field(annex, "sha256", bytes, f"{what} annex record")
        size = _field(annex, "size", int, f"{what} annex record")
        if len(sha) != DIGEST_SIZE or size < HEADER_SIZE + _TRAILER_SIZE:
            raise ImageFormatError(
                f"read {what}: annex record needs a 32-byte sha256 and a size >= "
                f"{HEADER_SIZE + _TRAILER_SIZE}"
            )
    names = [entry["name"] for entry in table[: len(DEVICE_SECTIONS)]]
    if tuple(names) != DEVICE_SECTIONS:
        raise ImageFormatError(
            f"read {what}: sections start with {names}, expected {list(DEVICE_SECTIONS)}"
        )
    ny, nx = _grid_shape(image_shape, cell_shape)
    n_cells = ny * nx
    values = cell_shape[0] * cell_shape[1] * 3
    n_coeff = table[3]["shape"][0] if len(table[3]["shape"]) == 2 else -1
    expected = {
        "n_components": ("<i4", [n_cells]),
        "scales": ("<f4", [n_coeff]),
        "mean": ("|u1", [n_cells, values]),
        "eigenimages": ("|i1", [n_coeff, values]),
    }
    for entry in table[:4]:
        dtype, shape = expected[entry["name"]]
        if entry["dtype"] != dtype or entry["shape"] != shape:
            raise ImageFormatError(
                f"read {what}: section '{entry['name']}' is {entry['dtype']} {entry['shape']}, "
                f"expected {dtype} {shape} for image {list(image_shape)} with cells "
                f"{list(cell_shape)}"
            )


def _check_looks_manifest(manifest: dict, names: set[str], version: int, what: str) -> None:
    """``looks``: required by format versions 2 and 3, refused by version 1; well formed,
    and naming sections the image has (a look's own scores: version 3 only)."""
    looks = manifest.get("looks")
    if version == FORMAT_VERSION:
        if "looks" in manifest:
            raise ImageFormatError(f"read {what}: manifest 'looks' needs format version "
                                   f"{LOOKS_FORMAT_VERSION} (the header says {version})")
        return
    if looks is None:
        raise ImageFormatError(f"read {what}: format version {version} needs the manifest's "
                               "'looks' list")
    problem = _looks_problem(looks, names, version)
    if problem:
        raise ImageFormatError(f"read {what}: {problem}")


def _looks_problem(looks: Any, sections: set[str], version: int) -> str | None:
    """What is wrong with a ``looks`` list of an image of format ``version`` (module
    docstring), or None."""
    if not isinstance(looks, list) or not 2 <= len(looks) <= MAX_LOOKS:
        return f"'looks' must be a list of 2..{MAX_LOOKS} maps"
    seen: set[str] = set()
    for i, look in enumerate(looks):
        if not isinstance(look, dict):
            return f"looks[{i}] is not a map"
        name = look.get("name")
        if (not isinstance(name, str) or not 1 <= len(name) <= MAX_LOOK_NAME
                or not name.isprintable() or name in seen):
            return (f"looks[{i}] needs a unique printable 'name' of 1..{MAX_LOOK_NAME} "
                    "characters")
        seen.add(name)
        mapping = look.get("sections", {})
        if not isinstance(mapping, dict):
            return f"look '{name}': 'sections' must be a map"
        for standard, section in mapping.items():
            if standard not in LOOK_SECTION_NAMES:
                return (f"look '{name}': section '{str(standard)[:_MAX_NAME_CHARS]}' cannot "
                        f"be replaced (a look replaces {', '.join(sorted(LOOK_SECTION_NAMES))})")
            if standard in LOOK_SCORE_SECTIONS and version < LOOK_SCORES_FORMAT_VERSION:
                return (f"look '{name}': its own '{standard}' needs format version "
                        f"{LOOK_SCORES_FORMAT_VERSION}")
            if not isinstance(section, str) or section not in sections:
                return (f"look '{name}': its '{standard}' names section "
                        f"'{str(section)[:_MAX_NAME_CHARS]}', which the image lacks")
        if not isinstance(look.get("synthesis"), (dict, type(None))):
            return f"look '{name}': 'synthesis' must be a map or null"
        quant = look.get("score_quantization")
        if quant is not None and (version < LOOK_SCORES_FORMAT_VERSION
                                  or not isinstance(quant, dict) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool)
                and math.isfinite(v) and v > 0 for v in quant.values())):
            return (f"look '{name}': 'score_quantization' must be a map of positive numbers "
                    f"(format version {LOOK_SCORES_FORMAT_VERSION})")
    return None


def _check_n_components(counts: np.ndarray, table: list[dict], what: str) -> None:
    if counts.size and counts.min() < 0:
        raise ImageFormatError(f"read {what}: n_components has a negative entry")
    n_coeff = table[3]["shape"][0]
    total = int(counts.sum(dtype=np.int64))
    if total != n_coeff:
        raise ImageFormatError(
            f"read {what}: n_components sums to {total}, but eigenimages has {n_coeff} rows"
        )


def _read_section(
    src: _Source, entry: dict, dctx: zstd.ZstdDecompressor, limits: _Limits, what: str
) -> np.ndarray:
    where = f"{what} section '{entry['name']}'"
    size = entry["size"]
    raw_size = entry["raw_size"]
    head = src.read_exact(min(size, _ZSTD_MAX_FRAME_HEADER), f"section '{entry['name']}'")
    try:
        params = zstd.get_frame_parameters(head)
    except zstd.ZstdError as exc:
        raise ImageFormatError(f"read {where}: not a zstd frame: {exc}") from None
    if params.content_size == zstd.CONTENTSIZE_UNKNOWN:
        raise ImageFormatError(f"read {where}: zstd frame does not record its content size")
    if params.content_size != raw_size:
        raise ImageFormatError(
            f"read {where}: decompressed size mismatch: frame records {params.content_size} "
            f"bytes, manifest declares {raw_size}"
        )
    if params.window_size > limits.window:
        raise ImageFormatError(
            f"read {where}: zstd window {params.window_size} bytes over the limit "
            f"max_window_bytes={limits.window}"
        )
    buffer = np.empty(raw_size, dtype=np.uint8)
    bounded = _BoundedReader(src, head, size - len(head))
    reader = dctx.stream_reader(
        bounded, read_size=_READ_BYTES, read_across_frames=True, closefd=False
    )
    filled = 0
    view = memoryview(buffer)
    try:
        while filled < raw_size:
            got = reader.readinto(view[filled:])
            if not got:
                break
            filled += got
        extra = reader.read(1) if filled == raw_size else b""
    except zstd.ZstdError as exc:
        raise ImageFormatError(f"read {where}: corrupt zstd data: {exc}") from None
    if filled != raw_size or extra:
        raise ImageFormatError(
            f"read {where}: decompressed size mismatch: expected {raw_size} bytes, got "
            f"{filled if not extra else 'more'}"
        )
    if bounded.remaining:
        raise ImageFormatError(
            f"read {where}: {bounded.remaining} stray bytes after the zstd frame"
        )
    dtype = np.dtype(entry["dtype"])
    array = buffer.view(dtype).reshape(entry["shape"])
    return array if dtype.isnative else array.astype(dtype.newbyteorder("="))


# --------------------------------------------------------------------------- model checks


def _grid_shape(image_shape: tuple[int, int], cell_shape: tuple[int, int]) -> tuple[int, int]:
    return (-(-image_shape[0] // cell_shape[0]), -(-image_shape[1] // cell_shape[1]))


def _model_problem(
    image_shape: Any,
    cell_shape: Any,
    mean: Any,
    eigenimages: Any,
    scales: Any,
    n_components: Any,
) -> str | None:
    """Return a description of the first inconsistency, or None."""
    for name, pair in (("image_shape", image_shape), ("cell_shape", cell_shape)):
        if (
            len(tuple(pair)) != 2
            or not all(isinstance(v, int | np.integer) for v in pair)
            or not all(1 <= int(v) <= _MAX_IMAGE_SIDE for v in pair)
        ):
            return f"{name}={pair!r} must be two ints in 1..{_MAX_IMAGE_SIDE}"
    ny, nx = _grid_shape(tuple(image_shape), tuple(cell_shape))
    n_cells = ny * nx
    values = int(cell_shape[0]) * int(cell_shape[1]) * 3
    checks = [
        ("n_components", n_components, np.int32, (n_cells,)),
        ("mean", mean, np.uint8, (n_cells, values)),
    ]
    for name, arr, dtype, shape in checks:
        if not isinstance(arr, np.ndarray) or arr.dtype != dtype or arr.shape != shape:
            return (
                f"{name} must be a {np.dtype(dtype).name} array of shape {shape}, got "
                f"{_describe(arr)}"
            )
    if n_components.size and n_components.min() < 0:
        return "n_components has a negative entry"
    n_coeff = int(n_components.sum(dtype=np.int64))
    for name, arr, dtype, shape in (
        ("eigenimages", eigenimages, np.int8, (n_coeff, values)),
        ("scales", scales, np.float32, (n_coeff,)),
    ):
        if not isinstance(arr, np.ndarray) or arr.dtype != dtype or arr.shape != shape:
            return (
                f"{name} must be a {np.dtype(dtype).name} array of shape {shape} "
                f"(K = sum(n_components) = {n_coeff}), got {_describe(arr)}"
            )
    if not np.all(np.isfinite(scales)) or (scales.size and scales.min() < 0):
        return "scales must be finite and >= 0"
    return None


def _describe(arr: Any) -> str:
    if isinstance(arr, np.ndarray):
        return f"{arr.dtype.name} {arr.shape}"
    return type(arr).__name__


def _check_extra_section(name: str, arr: Any) -> None:
    if not isinstance(name, str) or not 1 <= len(name) <= _MAX_NAME_CHARS:
        raise ValueError(f"section name {name!r} must be a str of 1..{_MAX_NAME_CHARS} chars")
    if not isinstance(arr, np.ndarray):
        raise ValueError(f"section '{name}' must be a numpy array, got {type(arr).__name__}")
    if arr.dtype.newbyteorder("<").str not in _ALLOWED_DTYPES or arr.ndim > _MAX_NDIM:
        raise ValueError(
            f"section '{name}' has dtype {arr.dtype} / {arr.ndim} dims; allowed dtypes: "
            f"{', '.join(sorted(_ALLOWED_DTYPES))}, at most {_MAX_NDIM} dims"
        )
