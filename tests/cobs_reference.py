"""COBS as its reference describes it (Cheshire and Baker; Wikipedia's reference algorithm),
transcribed independently of ``protocol._cobs``: the framing and golden-file tests check the
protocol's encoder and decoder against these."""

from __future__ import annotations

__all__ = ["reference_cobs_decode", "reference_cobs_encode"]


def reference_cobs_encode(data: bytes) -> bytes:
    """Wikipedia's reference algorithm, transcribed (no trailing zero delimiter)."""
    out = bytearray([0])
    code_at, code = 0, 1
    for i, byte in enumerate(data):
        if byte:
            out.append(byte)
            code += 1
        if not byte or code == 0xFF:
            out[code_at] = code
            code, code_at = 1, len(out)
            if not byte or i < len(data) - 1:
                out.append(0)
    if code_at < len(out):
        out[code_at] = code
    return bytes(out)


def reference_cobs_decode(enc: bytes) -> bytes:
    """The inverse of `reference_cobs_encode` (``enc`` without its zero delimiter)."""
    out = bytearray()
    p = 0
    while p < len(enc):
        code = enc[p]
        out += enc[p + 1 : p + code]
        p += code
        if code < 0xFF and p < len(enc):
            out.append(0)
    return bytes(out)
