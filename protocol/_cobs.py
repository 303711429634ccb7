"""Consistent Overhead Byte Stuffing (COBS), numpy-vectorised.

COBS (Cheshire and Baker, 1999) rewrites a byte string so that it contains no
0x00 byte; a frame on the wire is ``cobs_encode(payload) + b"\\x00"``. The
encoding is a chain of *blocks*: a code byte ``c`` (1..255) followed by
``c - 1`` non-zero data bytes. A block with ``c < 255`` stands for its data
bytes followed by one 0x00 (dropped after the last block); ``c == 255`` stands
for 254 data bytes with no zero. Overhead: at most one byte per 254 bytes plus
one (``cobs_max_encoded_size``).

This is the canonical encoding (as Wikipedia's reference C code): a payload
whose last zero-free run is a non-empty multiple of 254 bytes does not get a
trailing ``0x01`` block. The decoder accepts that trailing block too.

Kept in the protocol package (and not the ``cobs`` package from PyPI) because
the device may import only the standard library, numpy, pyserial, cbor2 and
zstandard.
"""

from __future__ import annotations

import re

import numpy as np

__all__ = ["CobsDecodeError", "cobs_decode", "cobs_encode", "cobs_max_encoded_size"]

_BLOCK = 254  # data bytes in a full (code 0xFF) block
_ONES = re.compile(b"\x01+")
# Below this share of zero bytes (encode) or 0x01 codes (decode) a plain loop over
# zero-free runs (bytes.split / slicing: memchr and memcpy in C) beats the
# vectorised path: 3x faster to encode and 1.25x to decode random-like data such
# as zstd sections. Zero-heavy data takes the numpy path, whose cost does not grow
# with the number of zeros.
_SPARSE = 1 / 64


class CobsDecodeError(ValueError):
    """An encoded string is not valid COBS (zero byte, or a block past the end)."""


def cobs_max_encoded_size(size_bytes: int) -> int:
    """Return the largest COBS encoding of a ``size_bytes``-byte payload.

    Parameters
    ----------
    size_bytes : int
        Payload length in bytes, >= 0.

    Returns
    -------
    int
        ``size_bytes + size_bytes // 254 + 1`` (no delimiter included).
    """
    if size_bytes < 0:
        raise ValueError(f"size_bytes={size_bytes} must be >= 0")
    return size_bytes + size_bytes // _BLOCK + 1


def cobs_encode(data: bytes | bytearray | memoryview) -> bytes:
    """Encode ``data`` with COBS; the result contains no 0x00 byte.

    Parameters
    ----------
    data : bytes-like of length n
        Any bytes.

    Returns
    -------
    bytes
        The encoding, ``n + 1 <= len <= cobs_max_encoded_size(n)`` bytes, without
        the 0x00 frame delimiter.
    """
    data = bytes(data)
    n = len(data)
    if n == 0:
        return b"\x01"
    if data.count(0) < n * _SPARSE:
        return _encode_runs(data)
    src = np.frombuffer(data, dtype=np.uint8)
    zeros = np.flatnonzero(src == 0)
    n_zeros = zeros.size
    # Zero-free segments between zeros: n_zeros + 1 of them.
    seg_start = np.empty(n_zeros + 1, dtype=np.int64)
    seg_start[0] = 0
    seg_start[1:] = zeros + 1
    seg_end = np.empty(n_zeros + 1, dtype=np.int64)
    seg_end[:-1] = zeros
    seg_end[-1] = n
    seg_len = seg_end - seg_start
    # Each segment is cut into blocks of 254; a segment closed by a zero always
    # ends with a short block (possibly empty: code 1). The last segment gets
    # that short block only when it is empty or not a multiple of 254.
    n_blocks = seg_len // _BLOCK + 1
    last = seg_len[-1]
    if last > 0 and last % _BLOCK == 0:
        n_blocks[-1] -= 1
    total_blocks = int(n_blocks.sum())
    first_block = np.cumsum(n_blocks) - n_blocks
    seg_of_block = np.repeat(np.arange(n_zeros + 1), n_blocks)
    block_in_seg = np.arange(total_blocks) - first_block[seg_of_block]
    block_len = np.minimum(_BLOCK, seg_len[seg_of_block] - _BLOCK * block_in_seg)
    # Where each block's data starts in the zero-free copy of the payload.
    nz_start = (seg_start - np.arange(n_zeros + 1))[seg_of_block] + _BLOCK * block_in_seg
    code_pos = nz_start + np.arange(total_blocks)
    out = np.empty(n - n_zeros + total_blocks, dtype=np.uint8)
    is_data = np.ones(out.size, dtype=bool)
    is_data[code_pos] = False
    out[code_pos] = (block_len + 1).astype(np.uint8)
    out[is_data] = src[src != 0]
    return out.tobytes()


def cobs_decode(encoded: bytes | bytearray | memoryview) -> bytes:
    """Decode one COBS encoding (without its 0x00 delimiter).

    Parameters
    ----------
    encoded : bytes-like
        A COBS encoding, at least one byte, no 0x00 byte.

    Returns
    -------
    bytes
        The payload.

    Raises
    ------
    CobsDecodeError
        If ``encoded`` is empty, contains 0x00, or its last block claims bytes
        past the end.
    """
    enc = bytes(encoded)
    n = len(enc)
    if n == 0:
        raise CobsDecodeError("cobs decode: empty input (the shortest encoding is b'\\x01')")
    if 0 in enc:
        raise CobsDecodeError(f"cobs decode: 0x00 at offset {enc.index(0)} of {n}")
    if enc.count(1) < n * _SPARSE:
        return _decode_runs(enc)
    # Walk the chain of code bytes (sequential by nature: each code says where
    # the next one is). A run of 0x01 codes (consecutive zeros in the payload)
    # is matched in C by a regex, so zero-heavy payloads do not cost one Python
    # step per byte. Runs are kept as (first position, count).
    run_start: list[int] = []
    run_count: list[int] = []
    match_ones = _ONES.match
    p = 0
    while p < n:
        code = enc[p]
        if code == 1:
            q = match_ones(enc, p).end()
            run_start.append(p)
            run_count.append(q - p)
            p = q
        else:
            run_start.append(p)
            run_count.append(1)
            p += code
    if p != n:
        last = run_start[-1] + run_count[-1] - 1
        raise CobsDecodeError(
            f"cobs decode: last block (code 0x{enc[last]:02x} at offset {last}) "
            f"runs {p - n} byte(s) past the end of {n}"
        )
    counts = np.asarray(run_count, dtype=np.int64)
    first = np.cumsum(counts) - counts
    pos = np.repeat(np.asarray(run_start, dtype=np.int64) - first, counts) + np.arange(
        int(counts.sum())
    )
    src = np.frombuffer(enc, dtype=np.uint8)
    codes = src[pos]
    # The byte at each later code position becomes the zero its previous block
    # implies (code < 255) or is removed (code == 255); the first code byte is
    # always removed.
    keep = np.ones(n, dtype=bool)
    keep[0] = False
    out = src.copy()
    later = pos[1:]
    out[later] = 0
    keep[later[codes[:-1] == 0xFF]] = False
    return out[keep].tobytes()


def _encode_runs(data: bytes) -> bytes:
    """`cobs_encode` as a loop over zero-free runs (fast when zeros are rare)."""
    out = bytearray()
    pieces = data.split(b"\x00")
    last = len(pieces) - 1
    for i, piece in enumerate(pieces):
        n = len(piece)
        if n < _BLOCK:
            out.append(n + 1)
            out += piece
            continue
        view = memoryview(piece)
        p = 0
        while n - p >= _BLOCK:
            out.append(0xFF)
            out += view[p : p + _BLOCK]
            p += _BLOCK
        if p < n or i != last:  # canonical: no trailing 0x01 after a full final run
            out.append(n - p + 1)
            out += view[p:]
    return bytes(out)


def _decode_runs(enc: bytes) -> bytes:
    """`cobs_decode` as a walk over the code chain (fast when blocks are long)."""
    n = len(enc)
    out = bytearray()
    p = 0
    while p < n:
        code = enc[p]
        q = p + code
        if q > n:
            raise CobsDecodeError(
                f"cobs decode: last block (code 0x{code:02x} at offset {p}) "
                f"runs {q - n} byte(s) past the end of {n}"
            )
        out += enc[p + 1 : q]
        if code != 0xFF and q < n:
            out.append(0)
        p = q
    return bytes(out)
