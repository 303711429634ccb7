"""Score packets: one quantized score vector per displayed view.

A packet is a fixed 32-byte header followed by a payload (little-endian throughout)::

    offset size field
    0      2    magic b"\\xecS"
    2      1    version (1; 2 when PREDICTED is set, 3 when SYNTHESIZED is set, below)
    3      1    flags: bit 0 DELTA; bit 1 ZSTD (payload is one zstd frame, content size
                recorded); bits 2-3 STEP_MODE (0 scalar, 1 per cell, 2 per component,
                3 reserved); bits 4-5 CODING (0 zigzag LEB128 varints; 1 per-cell
                end-of-block varints, below; 2-3 reserved); bit 6 PREDICTED (version 2
                only; reserved, 0, in versions 1 and 3); bit 7 SYNTHESIZED (version 3
                only; reserved, 0, in versions 1 and 2)
    4      4    frame number u32
    8      4    base frame number u32 (the frame a DELTA packet is relative to; 0 in a key)
    12     4    phi_deg float32
    16     4    theta_deg float32
    20     4    n_coefficients K u32 (must equal the image's)
    24     4    image tag: the first 4 bytes of the eigenspace image's SHA-256 digest
    28     4    step float32 (STEP_MODE 0; 0.0 otherwise)
    32     ..   payload (zstd-compressed when ZSTD is set):
                [float32 step array: n_cells (mode 1) or K (mode 2) entries] then the
                coded integers: CODING 0: K varints; CODING 1 (needs the image's per-cell
                component counts n_c): n_cells varints m_c (0 <= m_c <= n_c: how many of cell
                c's leading coefficients follow), then sum(m_c) varints, cell after cell; the
                last n_c - m_c coefficients of each cell are 0

Quantization: ``q_j = rint(y_j / step_j)`` as int32; the device uses ``y_j = q_j * step_j``
(float32), so ``|y_j - y'_j| <= step_j / 2``. A key packet codes q; a delta packet codes
``q - q_base`` against an earlier frame the decoder holds (a delta needs the base's steps:
the integer difference is only meaningful with the same step). Each integer is zigzag-mapped
(0, -1, 1, -2 ... -> 0, 1, 2, 3 ...) and written as a little-endian base-128 varint (at most 5
bytes, canonical: no overlong encodings). The encoder compresses the payload with zstd and keeps
whichever of compressed/raw is smaller.

Why varints and not int16: measured on real score vectors (the ``brainsmall`` MRI, 270
views of 84x96, adaptive cells of 12 px with T = 0.98 / 0.995, cell k = 20, standard k = 100;
steps 0.5, 2 and 8; mean packet payload bytes for key and consecutive-view delta packets),
zigzag varint + zstd was the smallest in all 24 cases: 15-40 % smaller than int16 + zstd and
5-30 % smaller than byte-planar int16 + zstd (e.g. adaptive T = 0.98, step 2: key 776 vs 1014
vs 930 bytes, delta 596 vs 853 vs 785), and int16 also cannot hold the scores of a standard
eigenspace at fine steps. Delta packets were 15-30 % smaller than key packets.

Why end-of-block coding (CODING 1): a cell's components are sorted by eigenvalue, and at the
coarse steps that are worth sending (docs/rate-distortion-packets.md) the tail of every cell
quantizes to 0 -- the encoder also zeroes components whose eigenvalue is below the rounding
noise (reverse water-filling, `host.fit.model.HostModel.quantized_scores`). Sending each cell's
count and dropping its trailing zeros cut key packets by 10-30 % at 4-32 times the 0.25-MSE
step (tooth and head, 256 and 512); at fine steps plain varints can be smaller, so the encoder
codes both and keeps the smaller. The encoder's zstd level is 19 (default `DEFAULT_LEVEL`):
10-25 % smaller than level 3 on these sub-10 kB payloads, about a millisecond per packet, and
decoding cost does not depend on the level. CODING 1 was a reserved value of version 1, which
decoders without it refuse with a clear error, so the packet version stays 1.

Predicted corrections (version 2, issue 14): with PREDICTED set the scores are a
*correction* to the device's own prediction of the header's view ``(phi_deg, theta_deg)``:
the device interpolates its standalone training-score table at exactly that view
(`device_runtime.prediction`, the same code the host runs) and shows ``prediction + q *
step``. The packet's base kind is therefore one of three: none (a key packet), an earlier
frame (DELTA) or the prediction (PREDICTED); DELTA and PREDICTED together are refused. A
correction is not kept as a delta base (its integers mean nothing without the prediction).
Only packets with PREDICTED carry version 2, so every other packet stays readable by
version-1 decoders; a version-1 decoder refuses a correction in one line ("unsupported
packet version 2"), and a version-2 decoder reads both. A host sends corrections only to a
device whose HELLO_REPLY says it predicts (docs/protocol.md, "Predicted corrections").

Corrections of the synthesized frame (version 3, issue 23): with SYNTHESIZED set the
scores are a correction of the device's own *synthesized frame* of the header's view (its
depth warp of the neighbouring training views, or the blend of its predicted scores for an
image without depth; `device_runtime.prediction.OwnFrames`, the code the host runs too):
the device shows, per cell, ``clip(rint(synth_c + sum_j q_j step_j scales_j E_j))``, the
eigenimages added to the picture it made itself, so the correction fixes what the
eigenspace can hold and keeps the detail the synthesis brings from outside it. Like a
PREDICTED packet it has no delta base and is never kept as one; SYNTHESIZED together with
DELTA or PREDICTED is refused, and its view must be canonical. Only packets with
SYNTHESIZED carry version 3; decoders of versions 1 and 2 refuse them in one line, and a
host sends them only to a device whose HELLO_REPLY lists version 3 and says it predicts.

Decoded scores are finite and bounded: every step (header or array) must be finite, > 0 and
at most ``max_abs_score``, and every decoded score ``|q * step|`` at most ``max_abs_score``
(else ``LimitExceeded``), checked before the frame is kept as a delta base. A device passes
:func:`score_bound` of its image: scores are orthonormal coordinates of a cell's pixel vector
minus its mean, so ``|y_j| <= 255 * sqrt(cell values)``; the bound allows 4 times that
(interpolation overshoot, rounding). Without one the decoder uses
``DEFAULT_MAX_ABS_SCORE`` (2**64), which keeps every product finite in float32.

Decoding is bounded: a packet longer than ``max_packet_bytes`` is refused before it is parsed;
the payload bound is computed from K (5 bytes per varint plus the step array, plus 5 bytes
per cell count with CODING 1) and a zstd frame
whose recorded content size is unknown or larger is refused before decompression, which then
runs with ``max_output_size`` on one reused ``ZstdDecompressor``; trailing bytes are refused.
"""

from __future__ import annotations

import struct
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import zstandard as zstd

from protocol.errors import LimitExceeded, MalformedMessage, ProtocolError

__all__ = [
    "CODING_EOB",
    "CODING_VARINT",
    "DEFAULT_LEVEL",
    "DEFAULT_MAX_ABS_SCORE",
    "HEADER_SIZE",
    "MAGIC",
    "VERSION",
    "VERSIONS",
    "DecodedScores",
    "EncodedScores",
    "ImageMismatch",
    "MissingBase",
    "PacketHeader",
    "ScoreDecoder",
    "ScorePacketError",
    "decode_header",
    "encode_scores",
    "max_packet_size",
    "score_bound",
    "zigzag_varints",
]

MAGIC = b"\xecS"
#: The newest packet version: 2 adds the PREDICTED base kind (bit 6), 3 the SYNTHESIZED
#: one (bit 7); packets with neither are still written as version 1.
VERSION = 3
#: Versions a decoder of this module reads.
VERSIONS = (1, 2, 3)
_HEADER = struct.Struct("<2sBBIIffI4sf")
HEADER_SIZE = _HEADER.size  # 32

FLAG_DELTA = 0x01
FLAG_ZSTD = 0x02
FLAG_PREDICTED = 0x40
FLAG_SYNTHESIZED = 0x80
_STEP_SHIFT = 2
_STEP_MASK = 0x0C
STEP_SCALAR, STEP_PER_CELL, STEP_PER_COMPONENT = 0, 1, 2
_CODING_SHIFT = 4
_CODING_MASK = 0x30
CODING_VARINT, CODING_EOB = 0, 1
_RESERVED_MASK = {1: 0xC0, 2: 0x80, 3: 0x40}  # per version
_MAX_VARINT_BYTES = 5
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
#: Largest |score| (and step) a decoder accepts unless told a bound (see the module docstring).
DEFAULT_MAX_ABS_SCORE = float(2.0**64)
_SCORE_BOUND_MARGIN = 4.0
#: zstd level of the encoder (decoding cost does not depend on it; see the module docstring).
DEFAULT_LEVEL = 19
_DEFAULT_LEVEL = DEFAULT_LEVEL
_local = threading.local()  # one reused ZstdCompressor per (thread, level)


def _compressor(level: int) -> zstd.ZstdCompressor:
    cache = getattr(_local, "compressors", None)
    if cache is None:
        cache = _local.compressors = {}
    if level not in cache:
        cache[level] = zstd.ZstdCompressor(level=level, write_content_size=True)
    return cache[level]


def score_bound(cell_values: int, *, value_range: float = 255.0) -> float:
    """Largest |score| an image with ``cell_values`` values per cell can need.

    A score is an orthonormal coordinate of a cell's pixel vector (``cell_values`` entries in
    0..``value_range``) minus its mean, so it is at most ``value_range * sqrt(cell_values)``;
    this returns 4 times that (interpolated views may overshoot a little).

    Parameters
    ----------
    cell_values : int
        Values per cell (cell pixels times channels), >= 1.
    value_range : float
        Pixel value range (uint8 images: 255).

    Returns
    -------
    float
    """
    if cell_values < 1:
        raise ValueError(f"score_bound: cell_values={cell_values} must be >= 1")
    return float(_SCORE_BOUND_MARGIN * value_range * np.sqrt(float(cell_values)))


class ScorePacketError(MalformedMessage):
    """A score packet is malformed (bad magic, sizes, varints, steps ...)."""


class ImageMismatch(ProtocolError):
    """A score packet was made for another eigenspace image (digest prefix or K differ)."""


class MissingBase(ProtocolError):
    """A delta packet refers to a base frame the decoder does not hold: ask for a key frame."""

    def __init__(self, message: str, *, base_frame: int) -> None:
        super().__init__(message)
        self.base_frame = base_frame


@dataclass(frozen=True, eq=False)
class EncodedScores:
    """A packet and the state the host keeps to send deltas against it.

    Attributes
    ----------
    packet : bytes
        The wire bytes.
    q : ndarray of shape (n_coefficients,), int32
        The quantized scores of this frame (the base of later deltas).
    frame : int
        Frame number.
    step : float or ndarray of float32
        The step(s) used (a delta must use the same).
    """

    packet: bytes
    q: np.ndarray
    frame: int
    step: float | np.ndarray


@dataclass(frozen=True, eq=False)
class DecodedScores:
    """A decoded packet.

    Attributes
    ----------
    frame : int
    base_frame : int or None
        ``None`` for a key packet.
    phi_deg, theta_deg : float
        The view the scores are for.
    y : ndarray of shape (n_coefficients,), float32
        Scores in orthonormal coordinates, ``q * step``.
    q : ndarray of shape (n_coefficients,), int32
    step : float or ndarray of float32
    packet_bytes : int
    predicted : bool
        ``y`` is a correction to the decoder's own prediction of the view (version 2).
    synthesized : bool
        ``y`` is a correction of the decoder's own synthesized frame of the view (version 3).
    """

    frame: int
    base_frame: int | None
    phi_deg: float
    theta_deg: float
    y: np.ndarray
    q: np.ndarray
    step: float | np.ndarray
    packet_bytes: int
    predicted: bool = False
    synthesized: bool = False

    @property
    def is_key(self) -> bool:
        """Whether this was a key packet (decodable on its own)."""
        return self.base_frame is None


@dataclass(frozen=True)
class PacketHeader:
    """The decoded fixed header of a packet (see the module docstring)."""

    flags: int
    frame: int
    base_frame: int
    phi_deg: float
    theta_deg: float
    n_coefficients: int
    image_tag: bytes
    step: float

    version: int = 1

    @property
    def is_delta(self) -> bool:
        return bool(self.flags & FLAG_DELTA)

    @property
    def is_predicted(self) -> bool:
        """A correction to the receiver's own prediction of the view (version 2)."""
        return bool(self.flags & FLAG_PREDICTED)

    @property
    def is_synthesized(self) -> bool:
        """A correction of the receiver's own synthesized frame of the view (version 3)."""
        return bool(self.flags & FLAG_SYNTHESIZED)

    @property
    def step_mode(self) -> int:
        return (self.flags & _STEP_MASK) >> _STEP_SHIFT

    @property
    def coding(self) -> int:
        """CODING field: `CODING_VARINT` or `CODING_EOB`."""
        return (self.flags & _CODING_MASK) >> _CODING_SHIFT


def max_packet_size(n_coefficients: int, n_step_values: int = 0, n_cells: int = 0) -> int:
    """Largest packet the encoder can produce for K coefficients (and a step array; with
    ``n_cells`` the end-of-block coding's cell counts)."""
    raw = _MAX_VARINT_BYTES * (n_coefficients + n_cells) + 4 * n_step_values
    return HEADER_SIZE + raw


# --------------------------------------------------------------------------- encoding


def _steps_array(
    step: Any, n_coefficients: int, n_components: np.ndarray | None, per_cell: bool
) -> tuple[int, float, np.ndarray | None, np.ndarray]:
    """Return (mode, header step, step array to send or None, per-coefficient float32 steps)."""
    arr = np.asarray(step, dtype=np.float32)
    if not np.all(np.isfinite(arr)) or (arr.size and arr.min() <= 0):
        raise ValueError(f"encode_scores: step must be finite and > 0, got {step!r}")
    if arr.ndim == 0:
        if per_cell:
            raise ValueError("encode_scores: per_cell=True needs a step array of n_cells entries")
        return STEP_SCALAR, float(arr), None, np.full(n_coefficients, arr, dtype=np.float32)
    if per_cell:
        if n_components is None or arr.shape != (len(n_components),):
            raise ValueError(
                f"encode_scores: per-cell step array of shape {arr.shape} needs n_components "
                "and one entry per cell"
            )
        return STEP_PER_CELL, 0.0, arr, np.repeat(arr, n_components)
    if arr.shape != (n_coefficients,):
        raise ValueError(
            f"encode_scores: step array of shape {arr.shape} must have n_coefficients="
            f"{n_coefficients} entries (or pass per_cell=True with n_cells entries)"
        )
    return STEP_PER_COMPONENT, 0.0, arr, arr


def zigzag_varints(values: np.ndarray) -> bytes:
    """Zig-zag LEB128 varints of integers: the body of a varint-coded score packet.

    Each value ``v`` maps to ``(v << 1) ^ (v >> 63)`` (small magnitudes, either sign, become
    small unsigned numbers), written 7 bits per byte, least significant first, the top bit set
    on every byte but the last. Public because the rate-distortion scripts size other
    layouts of the same integers with it.

    Parameters
    ----------
    values : 1-D ndarray of int
        Magnitudes below 2**34 (5 bytes at most; callers ``ravel`` other shapes first).

    Returns
    -------
    bytes
    """
    v = values.astype(np.int64)
    z = ((v << 1) ^ (v >> 63)).astype(np.uint64)
    nbytes = np.ones(z.shape, dtype=np.int64)
    for k in range(1, _MAX_VARINT_BYTES):
        nbytes += z >= np.uint64(1 << (7 * k))
    ends = np.cumsum(nbytes)
    starts = ends - nbytes
    out = np.empty(int(ends[-1]) if ends.size else 0, dtype=np.uint8)
    for k in range(_MAX_VARINT_BYTES):
        m = nbytes > k
        if not m.any():
            break
        byte = (z[m] >> np.uint64(7 * k)) & np.uint64(0x7F)
        cont = (nbytes[m] > k + 1).astype(np.uint64) << np.uint64(7)
        out[starts[m] + k] = (byte | cont).astype(np.uint8)
    return out.tobytes()


def _eob_integers(coded: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per-cell counts up to the last nonzero coefficient, then those coefficients."""
    offsets = np.zeros(counts.size + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    cell_of = np.repeat(np.arange(counts.size), counts)
    rank = np.arange(coded.size) - offsets[cell_of]
    last = np.zeros(counts.size, dtype=np.int64)  # 1 + rank of the last nonzero, per cell
    nz = coded != 0
    np.maximum.at(last, cell_of[nz], rank[nz] + 1)
    keep = rank < last[cell_of]
    return np.concatenate([last, coded[keep]])


def encode_scores(
    y: np.ndarray,
    *,
    step: float | np.ndarray,
    frame: int,
    view: tuple[float, float],
    image_digest: bytes,
    base: EncodedScores | None = None,
    n_components: np.ndarray | None = None,
    per_cell: bool = False,
    level: int = _DEFAULT_LEVEL,
    coding: int | None = None,
    predicted: bool = False,
    synthesized: bool = False,
) -> EncodedScores:
    """Quantize a score vector and encode it as a key or delta packet.

    Parameters
    ----------
    y : ndarray of shape (n_coefficients,), float
        Scores in orthonormal coordinates.
    step : float or ndarray of shape (n_coefficients,) or (n_cells,)
        Quantization step(s), > 0: one for all, one per component, or one per cell
        (``per_cell=True``, needs ``n_components``).
    frame : int
        Frame number, 0..2**32-1.
    view : (float, float)
        ``(phi_deg, theta_deg)`` of the view.
    image_digest : bytes
        SHA-256 digest of the eigenspace image (its first 4 bytes go into the packet).
    base : EncodedScores, optional
        Code a delta against this earlier frame (same step required); ``None``: key packet.
    n_components : ndarray of shape (n_cells,), int, optional
        Per-cell component counts (only for per-cell steps).
    per_cell : bool
        ``step`` holds one entry per cell.
    level : int
        zstd level for the payload.
    coding : {None, 0, 1}
        `CODING_VARINT`, `CODING_EOB` (needs ``n_components``), or None: with
        ``n_components`` both are tried and the smaller packet is kept, else varints.
    predicted : bool
        ``y`` is a correction to the device's own prediction of ``view`` (a version-2
        packet with PREDICTED; no ``base``). ``view`` must then be the canonical view the
        prediction was made at (`device_runtime.orbit.canonical_view`).
    synthesized : bool
        ``y`` is a correction of the device's own synthesized frame of ``view`` (a
        version-3 packet with SYNTHESIZED; no ``base``, ``view`` canonical).

    Returns
    -------
    EncodedScores
        The packet plus the quantized ``q`` the host keeps as a future base.
    """
    y, phi_deg, theta_deg, counts = _checked_scores(y, frame, view, image_digest, n_components)
    n_coeff = y.shape[0]
    mode, header_step, step_sent, per_coeff = _steps_array(step, n_coeff, counts, per_cell)
    q = _quantized(y, per_coeff)
    flags = mode << _STEP_SHIFT
    base_frame = 0
    coded = q.astype(np.int64)
    kept_step: float | np.ndarray = header_step if step_sent is None else step_sent
    flags |= _correction_flags(predicted, synthesized, base)
    if base is not None:
        if base.q.shape != q.shape or not _same_step(base.step, kept_step):
            raise ValueError(
                "encode_scores: a delta needs a base with the same K and the same step(s); "
                "send a key packet when the step changes"
            )
        flags |= FLAG_DELTA
        base_frame = base.frame
        coded = coded - base.q.astype(np.int64)
    prefix = b"" if step_sent is None else step_sent.astype("<f4").tobytes()
    coding_flags, payload = _smallest_payload(coded, counts, coding, prefix, level)
    flags |= coding_flags
    header = _HEADER.pack(
        MAGIC,
        3 if synthesized else 2 if predicted else 1,
        flags,
        frame,
        base_frame,
        phi_deg,
        theta_deg,
        n_coeff,
        bytes(image_digest[:4]),
        header_step,
    )
    return EncodedScores(packet=header + payload, q=q, frame=frame, step=kept_step)


def _checked_scores(y: np.ndarray, frame: int, view: tuple[float, float], image_digest: bytes,
                    n_components: np.ndarray | None
                    ) -> tuple[np.ndarray, float, float, np.ndarray | None]:
    """`encode_scores`' inputs checked: (y as an array, phi, theta, the per-cell component
    counts as int64 or None)."""
    y = np.asarray(y)
    if y.ndim != 1:
        raise ValueError(f"encode_scores: y must be 1-D (n_coefficients,), got shape {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError("encode_scores: y has NaN or infinite entries")
    if not 0 <= frame <= 0xFFFFFFFF:
        raise ValueError(f"encode_scores: frame={frame} must be in 0..2**32-1")
    if len(image_digest) < 4:
        raise ValueError("encode_scores: image_digest must have at least 4 bytes")
    phi_deg, theta_deg = (float(v) for v in view)
    if not (np.isfinite(phi_deg) and np.isfinite(theta_deg)):
        raise ValueError(f"encode_scores: view={view!r} must be finite")
    counts = None if n_components is None else np.asarray(n_components, dtype=np.int64)
    if counts is not None and counts.sum() != y.shape[0]:
        raise ValueError(
            f"encode_scores: n_components sums to {counts.sum()}, y has {y.shape[0]} entries"
        )
    return y, phi_deg, theta_deg, counts


def _quantized(y: np.ndarray, per_coeff: np.ndarray) -> np.ndarray:
    """``y / step`` rounded to int32 (an error beyond its range)."""
    ratio = y.astype(np.float64) / per_coeff
    if ratio.size and np.abs(ratio).max() > _INT32_MAX:
        raise ValueError(
            f"encode_scores: |y / step| reaches {np.abs(ratio).max():.3g}, over the int32 "
            "range; use a larger step"
        )
    return np.rint(ratio).astype(np.int32)


def _correction_flags(predicted: bool, synthesized: bool, base: EncodedScores | None) -> int:
    """FLAG_PREDICTED / FLAG_SYNTHESIZED of a correction (which has no delta base)."""
    if predicted and synthesized:
        raise ValueError("encode_scores: a packet corrects the prediction or the synthesized "
                         "frame, not both")
    if (predicted or synthesized) and base is not None:
        raise ValueError("encode_scores: a correction has no delta base")
    return (FLAG_PREDICTED if predicted else 0) | (FLAG_SYNTHESIZED if synthesized else 0)


def _smallest_payload(coded: np.ndarray, counts: np.ndarray | None, coding: int | None,
                      prefix: bytes, level: int) -> tuple[int, bytes]:
    """The smallest payload among the codings tried (``coding``, or both where the
    component counts allow end-of-block coding), raw or zstd: (its flags, its bytes)."""
    if coding not in (None, CODING_VARINT, CODING_EOB):
        raise ValueError(f"encode_scores: coding={coding!r} must be None, 0 or 1")
    if coding == CODING_EOB and counts is None:
        raise ValueError("encode_scores: end-of-block coding needs n_components")
    tries = [coding] if coding is not None else (
        [CODING_VARINT] if counts is None else [CODING_VARINT, CODING_EOB])
    best: tuple[int, bytes] | None = None
    for mode_ in tries:
        ints = coded if mode_ == CODING_VARINT else _eob_integers(coded, counts)
        raw = prefix + zigzag_varints(ints)
        for zflag, body in ((0, raw), (FLAG_ZSTD, _compressor(level).compress(raw))):
            if best is None or len(body) < len(best[1]):
                best = (zflag | (mode_ << _CODING_SHIFT), body)
    assert best is not None
    return best


def _same_step(a: float | np.ndarray, b: float | np.ndarray) -> bool:
    a_arr = np.asarray(a, dtype=np.float32)
    b_arr = np.asarray(b, dtype=np.float32)
    return a_arr.shape == b_arr.shape and bool(np.array_equal(a_arr, b_arr))


# --------------------------------------------------------------------------- decoding


def decode_header(packet: bytes, *, versions: tuple[int, ...] = VERSIONS) -> PacketHeader:
    """Decode and check the fixed header of a packet (no payload, no image checks).

    ``versions``: the packet versions accepted (``(1,)`` is what a version-1 decoder did).
    Raises `ScorePacketError` when it is short or malformed.
    """
    if len(packet) < HEADER_SIZE:
        raise ScorePacketError(
            f"decode scores: packet is {len(packet)} bytes, shorter than the "
            f"{HEADER_SIZE}-byte header"
        )
    magic, version, flags, frame, base_frame, phi, theta, n_coeff, tag, step = _HEADER.unpack_from(
        packet
    )
    if magic != MAGIC:
        raise ScorePacketError(f"decode scores: bad magic {magic!r} (expected {MAGIC!r})")
    if version not in versions:
        supported = ", ".join(str(v) for v in versions)
        raise ScorePacketError(
            f"decode scores: unsupported packet version {version} (supported: {supported})"
        )
    if flags & _RESERVED_MASK[version]:
        bits = {1: "6-7", 2: "7", 3: "6"}[version]
        raise ScorePacketError(
            f"decode scores: unknown flags 0x{flags:02x} (reserved bits {bits} must be 0 in "
            f"version {version})"
        )
    if flags & (FLAG_PREDICTED | FLAG_SYNTHESIZED) and flags & FLAG_DELTA:
        raise ScorePacketError(
            "decode scores: a packet is relative to a frame (DELTA), to the prediction "
            "(PREDICTED) or to the synthesized frame (SYNTHESIZED), not two of them"
        )
    if (flags & _CODING_MASK) >> _CODING_SHIFT > CODING_EOB:
        raise ScorePacketError(
            f"decode scores: unsupported coding {(flags & _CODING_MASK) >> _CODING_SHIFT} "
            f"(flags 0x{flags:02x}; supported: 0 varints, 1 end-of-block)"
        )
    header = PacketHeader(flags, frame, base_frame, phi, theta, n_coeff, tag, step, version)
    if header.step_mode > STEP_PER_COMPONENT:
        raise ScorePacketError(f"decode scores: unsupported step mode {header.step_mode}")
    if not (np.isfinite(phi) and np.isfinite(theta)):
        raise ScorePacketError(f"decode scores: view ({phi}, {theta}) is not finite")
    if (flags & (FLAG_PREDICTED | FLAG_SYNTHESIZED)
            and not (0.0 <= phi < 360.0 and -90.0 <= theta <= 90.0)):
        raise ScorePacketError(
            f"decode scores: a correction's view ({phi:.6g}, {theta:.6g}) is not canonical "
            "(phi in [0, 360), theta in [-90, 90])"
        )
    if header.step_mode == STEP_SCALAR:
        if not (np.isfinite(step) and step > 0):
            raise ScorePacketError(f"decode scores: step {step} must be finite and > 0")
    elif step != 0.0:
        raise ScorePacketError("decode scores: header step must be 0 with a step array")
    if not header.is_delta and base_frame != 0:
        raise ScorePacketError("decode scores: a key packet must have base frame 0")
    return header


def _decode_varints(data: np.ndarray, count: int) -> np.ndarray:
    """Decode exactly ``count`` zigzag varints filling ``data`` (uint8) -> int64."""
    if count == 0:
        if data.size:
            raise ScorePacketError(f"decode scores: {data.size} stray payload bytes")
        return np.zeros(0, dtype=np.int64)
    ends = np.flatnonzero(data < 0x80)
    if ends.size == 0 or ends[-1] != data.size - 1:
        raise ScorePacketError("decode scores: the payload ends inside a varint")
    if ends.size != count:
        raise ScorePacketError(
            f"decode scores: payload holds {ends.size} varints, expected {count}"
        )
    starts = np.empty_like(ends)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    lengths = ends - starts + 1
    if lengths.max() > _MAX_VARINT_BYTES:
        raise ScorePacketError(
            f"decode scores: a varint is {lengths.max()} bytes long (limit {_MAX_VARINT_BYTES})"
        )
    if np.any((lengths > 1) & (data[ends] == 0)):
        raise ScorePacketError("decode scores: overlong (non-canonical) varint")
    shifts = (np.arange(data.size, dtype=np.int64) - np.repeat(starts, lengths)) * 7
    parts = (data & 0x7F).astype(np.int64) << shifts
    z = np.add.reduceat(parts, starts)
    return (z >> 1) ^ -(z & 1)


class ScoreDecoder:
    """Decode score packets for one eigenspace image, holding recent frames as delta bases.

    Parameters
    ----------
    n_coefficients : int
        K of the image.
    image_digest : bytes
        The image's SHA-256 digest (packets for another image are refused).
    max_packet_bytes : int, optional
        Largest packet accepted; default: the largest the encoder can produce for this image.
    n_components : ndarray of shape (n_cells,), int, optional
        Per-cell component counts; needed to accept per-cell steps.
    keep_bases : int
        How many recent frames to hold as possible delta bases (a host may code against a
        frame older than the last one when acknowledgements were lost).
    max_abs_score : float, optional
        Largest step and |decoded score| accepted (default ``DEFAULT_MAX_ABS_SCORE``; a
        device passes :func:`score_bound` of its image).
    versions : tuple of int
        Packet versions accepted (default `VERSIONS`; ``(1,)`` behaves as a decoder written
        before predicted corrections).
    """

    def __init__(
        self,
        n_coefficients: int,
        image_digest: bytes,
        *,
        max_packet_bytes: int | None = None,
        n_components: np.ndarray | None = None,
        keep_bases: int = 4,
        max_abs_score: float | None = None,
        versions: tuple[int, ...] = VERSIONS,
    ) -> None:
        if n_coefficients < 0:
            raise ValueError(f"ScoreDecoder: n_coefficients={n_coefficients} must be >= 0")
        if len(image_digest) < 4:
            raise ValueError("ScoreDecoder: image_digest must have at least 4 bytes")
        if keep_bases < 1:
            raise ValueError(f"ScoreDecoder: keep_bases={keep_bases} must be >= 1")
        bound = DEFAULT_MAX_ABS_SCORE if max_abs_score is None else float(max_abs_score)
        if not 0 < bound <= DEFAULT_MAX_ABS_SCORE:
            raise ValueError(f"ScoreDecoder: max_abs_score={max_abs_score} must be in "
                             f"(0, {DEFAULT_MAX_ABS_SCORE:g}]")
        self.max_abs_score = bound
        self.versions = tuple(versions)
        self.n_coefficients = int(n_coefficients)
        self.image_tag = bytes(image_digest[:4])
        self.n_components = None
        if n_components is not None:
            counts = np.asarray(n_components, dtype=np.int64)
            if counts.sum() != n_coefficients:
                raise ValueError(
                    f"ScoreDecoder: n_components sums to {counts.sum()}, not {n_coefficients}"
                )
            self.n_components = counts
        n_cells = 0 if self.n_components is None else len(self.n_components)
        n_step_values = max(self.n_coefficients, n_cells)
        self.max_payload_bytes = (_MAX_VARINT_BYTES * (self.n_coefficients + n_cells)
                                  + 4 * n_step_values)
        bound = HEADER_SIZE + self.max_payload_bytes
        self.max_packet_bytes = bound if max_packet_bytes is None else int(max_packet_bytes)
        window = 1 << max(10, int(self.max_payload_bytes).bit_length())
        self._dctx = zstd.ZstdDecompressor(max_window_size=window)
        self.keep_bases = keep_bases
        self._bases: OrderedDict[int, tuple[np.ndarray, float | np.ndarray]] = OrderedDict()

    def reset(self) -> None:
        """Forget every held base (e.g. after a new image was activated)."""
        self._bases.clear()

    @property
    def base_frames(self) -> list[int]:
        """Frame numbers currently held as delta bases, oldest first."""
        return list(self._bases)

    def decode(self, packet: bytes | bytearray | memoryview) -> DecodedScores:
        """Decode one packet.

        Raises
        ------
        LimitExceeded
            Packet or payload over the bound.
        ImageMismatch
            Packet for another image (digest prefix or K).
        MissingBase
            A delta whose base frame is not held (ask for a key frame).
        ScorePacketError
            Anything else malformed.
        """
        packet = bytes(packet)
        if len(packet) > self.max_packet_bytes:
            raise LimitExceeded(
                f"decode scores: packet is {len(packet)} bytes, over the limit "
                f"max_packet_bytes={self.max_packet_bytes}"
            )
        header = decode_header(packet, versions=self.versions)
        if header.image_tag != self.image_tag:
            raise ImageMismatch(
                f"decode scores: packet is for image {header.image_tag.hex()}..., this "
                f"decoder holds {self.image_tag.hex()}..."
            )
        if header.n_coefficients != self.n_coefficients:
            raise ImageMismatch(
                f"decode scores: packet has K={header.n_coefficients} coefficients, the image "
                f"has {self.n_coefficients}"
            )
        payload = self._payload(packet[HEADER_SIZE:], header.flags & FLAG_ZSTD)
        data = np.frombuffer(payload, dtype=np.uint8)
        steps, per_coeff, data = self._steps(header, data)
        if header.coding == CODING_EOB:
            coded = self._decode_eob(data)
        else:
            coded = _decode_varints(data, self.n_coefficients)
        base_frame = None
        if header.is_delta:
            base_frame = header.base_frame
            held = self._bases.get(base_frame)
            if held is None:
                raise MissingBase(
                    f"decode scores: delta frame {header.frame} needs base frame {base_frame}, "
                    f"which is not held (held: {self.base_frames}); request a key frame",
                    base_frame=base_frame,
                )
            base_q, base_step = held
            if not _same_step(base_step, steps):
                raise ScorePacketError(
                    f"decode scores: delta frame {header.frame} uses other steps than its base "
                    f"frame {base_frame}"
                )
            coded = coded + base_q
        if coded.size and (coded.min() < _INT32_MIN or coded.max() > _INT32_MAX):
            raise ScorePacketError("decode scores: a quantized score is outside the int32 range")
        q = coded.astype(np.int32)
        # |q| <= 2**31 and step <= max_abs_score <= 2**64: |y| <= 2**95, finite in float32
        y = q.astype(np.float32) * per_coeff
        if y.size:
            peak = float(np.max(np.abs(y)))
            if not peak <= self.max_abs_score:
                raise LimitExceeded(
                    f"decode scores: frame {header.frame} has a score of magnitude {peak:.3g}, "
                    f"over the bound {self.max_abs_score:.3g} for this image"
                )
        if not (header.is_predicted or header.is_synthesized):  # a correction means nothing
            # without the prediction or the frame it corrects
            self._bases.pop(header.frame, None)
            self._bases[header.frame] = (q, steps)
            while len(self._bases) > self.keep_bases:
                self._bases.popitem(last=False)
        return DecodedScores(
            frame=header.frame,
            base_frame=base_frame,
            phi_deg=header.phi_deg,
            theta_deg=header.theta_deg,
            y=y,
            q=q,
            step=steps,
            packet_bytes=len(packet),
            predicted=header.is_predicted,
            synthesized=header.is_synthesized,
        )

    def _decode_eob(self, data: np.ndarray) -> np.ndarray:
        """CODING 1: n_cells counts, then the leading coefficients of each cell."""
        counts = self.n_components
        if counts is None:
            raise ScorePacketError(
                "decode scores: end-of-block coding needs the image's n_components"
            )
        n_cells = counts.size
        ends = np.flatnonzero(data < 0x80)
        if ends.size < n_cells:
            raise ScorePacketError(
                f"decode scores: payload holds {ends.size} varints, fewer than the "
                f"{n_cells} cell counts"
            )
        split = int(ends[n_cells - 1]) + 1 if n_cells else 0
        sent = _decode_varints(data[:split], n_cells)
        if sent.size and (sent.min() < 0 or np.any(sent > counts)):
            raise ScorePacketError(
                "decode scores: an end-of-block count is negative or over its cell's components"
            )
        values = _decode_varints(data[split:], int(sent.sum()))
        offsets = np.zeros(n_cells + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        cell_of = np.repeat(np.arange(n_cells), counts)
        keep = (np.arange(self.n_coefficients) - offsets[cell_of]) < sent[cell_of]
        coded = np.zeros(self.n_coefficients, dtype=np.int64)
        coded[keep] = values
        return coded

    def _payload(self, body: bytes, compressed: int) -> bytes:
        if not compressed:
            if len(body) > self.max_payload_bytes:
                raise LimitExceeded(
                    f"decode scores: payload is {len(body)} bytes, over the bound "
                    f"{self.max_payload_bytes} for K={self.n_coefficients}"
                )
            return body
        try:
            size = zstd.frame_content_size(body)
        except zstd.ZstdError as exc:
            raise ScorePacketError(f"decode scores: payload is not a zstd frame: {exc}") from None
        if size == zstd.CONTENTSIZE_UNKNOWN or size < 0:
            raise ScorePacketError("decode scores: zstd frame does not record its content size")
        if size > self.max_payload_bytes:
            raise LimitExceeded(
                f"decode scores: zstd frame declares {size} bytes, over the bound "
                f"{self.max_payload_bytes} for K={self.n_coefficients}"
            )
        try:
            out = self._dctx.decompress(
                body, max_output_size=self.max_payload_bytes, allow_extra_data=False
            )
        except zstd.ZstdError as exc:
            raise ScorePacketError(f"decode scores: corrupt zstd payload: {exc}") from None
        if len(out) != size:
            raise ScorePacketError(
                f"decode scores: zstd frame declares {size} bytes but holds {len(out)}"
            )
        return out

    def _steps(
        self, header: PacketHeader, data: np.ndarray
    ) -> tuple[float | np.ndarray, np.ndarray, np.ndarray]:
        mode = header.step_mode
        if mode == STEP_SCALAR:
            step32 = np.float32(header.step)
            if not float(step32) <= self.max_abs_score:
                raise ScorePacketError(
                    f"decode scores: step {float(step32):.3g} is over the bound "
                    f"{self.max_abs_score:.3g}"
                )
            return float(step32), np.full(self.n_coefficients, step32, np.float32), data
        if mode == STEP_PER_CELL:
            if self.n_components is None:
                raise ScorePacketError(
                    "decode scores: per-cell steps need the image's n_components"
                )
            count = len(self.n_components)
        else:
            count = self.n_coefficients
        if data.size < 4 * count:
            raise ScorePacketError(
                f"decode scores: payload of {data.size} bytes is too short for {count} steps"
            )
        steps = data[: 4 * count].view("<f4").astype(np.float32)
        if not np.all(np.isfinite(steps)) or (steps.size and steps.min() <= 0):
            raise ScorePacketError("decode scores: step array has entries that are not > 0")
        if steps.size and not float(steps.max()) <= self.max_abs_score:
            raise ScorePacketError(
                f"decode scores: step array has an entry of {float(steps.max()):.3g}, over the "
                f"bound {self.max_abs_score:.3g}"
            )
        per_coeff = steps if mode == STEP_PER_COMPONENT else np.repeat(steps, self.n_components)
        return steps, per_coeff, data[4 * count :]
