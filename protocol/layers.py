"""Refinement layers: the packets that take a resting view to the exact ray-cast.

Once a resting view's correction is on show, the host sends *layers*, coarse to fine, until
the device's frame is the host's ray-cast bit for bit. A layer is a score packet of version
4 (the same magic and SCORES message as the other versions; a decoder that does not list 4
refuses it in one line) whose payload is a coded image of one horizontal strip of the frame
(a *tile*: the whole width, rows ``y0 .. y0 + rows``), in a codec the device decodes
through pygame (PNG, JPEG, WebP lossy or lossless). Little-endian, 32-byte header::

    offset size field
    0      2    magic b"\\xecS"
    2      1    version 4
    3      1    flags: bit 0 RESIDUAL (the strip is a residual, else the pixels themselves);
                bits 1-2 SHIFT s (a residual's values are v = (R - F) >> s offset by 128);
                bit 3 EXACT (an absolute strip coded losslessly: the ray-cast's pixels
                exactly); bits 4-7 reserved, 0
    4      4    frame number u32 (the host's packet counter)
    8      4    base frame number u32: the correction whose frame the layer refines (the
                frame number of the version-3 packet on show; 0: the device's own frame of
                the view, uncorrected)
    12     4    phi_deg float32 (canonical, as in version 3)
    16     4    theta_deg float32
    20     1    layer u8: the layer's place in the chain (0 first)
    21     1    codec u8: 1 PNG, 2 JPEG, 3 WebP (lossy or lossless, as the file says)
    22     2    reserved, 0
    24     4    image tag: the first 4 bytes of the eigenspace image's SHA-256 digest
    28     2    y0 u16: the strip's first row
    30     2    rows u16: the strip's height (>= 1; y0 + rows <= the image's height)
    32     ..   the coded strip: an image file of width x rows pixels, RGB

How the device applies a strip (`device_runtime.layers`) to its frame ``F`` of the view:
an absolute strip replaces its rows (``F = D``); a residual strip adds to them
(``F = clip(F + ((D - 128) << s), 0, 255)``, int16). Per row the device counts the layers
applied since the correction: a residual strip of layer ``L`` applies only to rows that
have had exactly the layers before it (``L``), an absolute one to rows that have had at
most ``L``; each sets its rows' count to ``L + 1``. A lost or dropped residual therefore
never misapplies the next one, and an absolute strip repairs any row. EXACT strips end the
chain: once every row has had one, the frame is the ray-cast, whatever float32 arithmetic
made the device's own frame (the host never codes the exact step against it).

Decoding is bounded: the packet is checked against ``max_packet_bytes`` before anything
else, and the image's declared width and height are read from its header
(`declared_size`: PNG's IHDR, JPEG's SOF, WebP's VP8/VP8L/VP8X chunk) and must equal the
strip's before the device decodes a byte of it, so no file can make it allocate more than
one strip.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from protocol.errors import LimitExceeded
from protocol.scores import MAGIC, ImageMismatch, ScorePacketError

__all__ = [
    "CODECS",
    "CODEC_JPEG",
    "CODEC_PNG",
    "CODEC_WEBP",
    "FLAG_EXACT",
    "FLAG_RESIDUAL",
    "LAYER_HEADER_SIZE",
    "LAYER_VERSION",
    "MAX_SHIFT",
    "LayerPacket",
    "declared_size",
    "decode_layer",
    "encode_layer",
    "is_layer",
]

#: The score packet version of a layer.
LAYER_VERSION = 4
_HEADER = struct.Struct("<2sBBIIffBBH4sHH")
LAYER_HEADER_SIZE = _HEADER.size  # 32
FLAG_RESIDUAL = 0x01
_SHIFT_MASK, _SHIFT_BIT = 0x06, 1
FLAG_EXACT = 0x08
_RESERVED = 0xF0
#: The largest residual shift (a residual of 8-bit pixels needs at most one bit more).
MAX_SHIFT = 2
CODEC_PNG, CODEC_JPEG, CODEC_WEBP = 1, 2, 3
#: codec -> (name, what pygame's loader is told the file is)
CODECS = {CODEC_PNG: ("png", "x.png"), CODEC_JPEG: ("jpeg", "x.jpg"),
          CODEC_WEBP: ("webp", "x.webp")}


@dataclass(frozen=True)
class LayerPacket:
    """A decoded layer header and its coded strip (see the module docstring).

    Attributes
    ----------
    frame, base_frame : int
    phi_deg, theta_deg : float
    layer : int
    codec : int
    residual : bool
    shift : int
    exact : bool
    y0, rows : int
        The strip: rows ``y0 .. y0 + rows`` of the whole width.
    data : bytes
        The coded strip (an image file).
    packet_bytes : int
    """

    frame: int
    base_frame: int
    phi_deg: float
    theta_deg: float
    layer: int
    codec: int
    residual: bool
    shift: int
    exact: bool
    y0: int
    rows: int
    data: bytes
    packet_bytes: int


def is_layer(packet: bytes | bytearray | memoryview) -> bool:
    """Whether a score packet is a layer (magic and version 4), from its first 3 bytes."""
    return len(packet) >= 3 and bytes(packet[:2]) == MAGIC and packet[2] == LAYER_VERSION


def encode_layer(data: bytes, *, codec: int, frame: int, base_frame: int,
                 view: tuple[float, float], image_digest: bytes, layer: int, y0: int,
                 rows: int, residual: bool = False, shift: int = 0,
                 exact: bool = False) -> bytes:
    """A layer packet carrying the coded strip ``data`` (see the module docstring).

    Raises
    ------
    ValueError
        A field out of its range (the codec, the shift, the strip, EXACT on a residual).
    """
    if codec not in CODECS:
        raise ValueError(f"encode_layer: codec={codec!r} must be one of {sorted(CODECS)}")
    if not 0 <= shift <= MAX_SHIFT or (shift and not residual):
        raise ValueError(f"encode_layer: shift={shift!r} must be 0..{MAX_SHIFT}, on residuals")
    if exact and residual:
        raise ValueError("encode_layer: an EXACT strip is absolute, not a residual")
    for name, value, top in (("frame", frame, 0xFFFFFFFF), ("base_frame", base_frame,
                                                            0xFFFFFFFF),
                             ("layer", layer, 0xFF), ("y0", y0, 0xFFFF), ("rows", rows, 0xFFFF)):
        if not 0 <= int(value) <= top:
            raise ValueError(f"encode_layer: {name}={value!r} must be within 0..{top}")
    if rows < 1:
        raise ValueError(f"encode_layer: rows={rows!r} must be >= 1")
    flags = (FLAG_RESIDUAL if residual else 0) | (shift << _SHIFT_BIT) | (
        FLAG_EXACT if exact else 0)
    head = _HEADER.pack(MAGIC, LAYER_VERSION, flags, frame, base_frame, float(view[0]),
                        float(view[1]), layer, codec, 0, bytes(image_digest[:4]), y0, rows)
    return head + bytes(data)


def decode_layer(packet: bytes | bytearray | memoryview, *, image_digest: bytes,
                 image_shape: tuple[int, int], max_packet_bytes: int) -> LayerPacket:
    """Parse and check a layer packet: its size, header, image tag, strip and the declared
    size of the coded image (which is not decoded here).

    Raises
    ------
    LimitExceeded
        The packet is longer than ``max_packet_bytes``.
    ImageMismatch
        Made for another eigenspace image.
    ScorePacketError
        Anything malformed: magic, version, reserved bits, codec, shift, EXACT with
        RESIDUAL, a view that is not finite, a strip outside the frame, an image file whose
        declared size is not the strip's (or unreadable).
    """
    n = len(packet)
    if n > max_packet_bytes:
        raise LimitExceeded(f"decode layer: packet of {n} bytes exceeds the limit of "
                            f"{max_packet_bytes}")
    if n < LAYER_HEADER_SIZE + 1:
        raise ScorePacketError(f"decode layer: {n} bytes is shorter than a header and a file")
    (magic, version, flags, frame, base, phi, theta, layer, codec, reserved, tag, y0,
     rows) = _HEADER.unpack_from(bytes(packet[:LAYER_HEADER_SIZE]))
    if magic != MAGIC or version != LAYER_VERSION:
        raise ScorePacketError(f"decode layer: not a layer packet (magic {magic!r}, version "
                               f"{version})")
    if flags & _RESERVED or reserved:
        raise ScorePacketError(f"decode layer: reserved bits set (flags 0x{flags:02x})")
    residual, exact = bool(flags & FLAG_RESIDUAL), bool(flags & FLAG_EXACT)
    shift = (flags & _SHIFT_MASK) >> _SHIFT_BIT
    if shift > MAX_SHIFT or (shift and not residual) or (exact and residual):
        raise ScorePacketError(f"decode layer: bad flags 0x{flags:02x}")
    if codec not in CODECS:
        raise ScorePacketError(f"decode layer: unknown codec {codec}")
    if tag != bytes(image_digest[:4]):
        raise ImageMismatch(f"decode layer: made for image {tag.hex()}, this device shows "
                            f"{bytes(image_digest[:4]).hex()}")
    if not (abs(phi) < float("inf") and abs(theta) <= 90.0):
        raise ScorePacketError(f"decode layer: bad view ({phi}, {theta})")
    height, width = image_shape
    if rows < 1 or y0 + rows > height:
        raise ScorePacketError(f"decode layer: strip of rows {y0}..{y0 + rows} outside the "
                               f"image's {height}")
    data = bytes(packet[LAYER_HEADER_SIZE:])
    declared = declared_size(data, codec)
    if declared != (width, rows):
        raise ScorePacketError(f"decode layer: the {CODECS[codec][0]} file declares "
                               f"{declared[0]}x{declared[1]}, the strip is {width}x{rows}")
    return LayerPacket(frame, base, phi, theta, layer, codec, residual, shift, exact, y0,
                       rows, data, n)


def declared_size(data: bytes, codec: int) -> tuple[int, int]:
    """(width, height) an image file declares in its header, read without decoding it.

    Raises
    ------
    ScorePacketError
        The file is not of ``codec``, or its header is truncated.
    """
    try:
        if codec == CODEC_PNG:
            if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
                raise ValueError("no PNG signature and IHDR")
            return struct.unpack(">II", data[16:24])
        if codec == CODEC_WEBP:
            return _webp_size(data)
        if codec == CODEC_JPEG:
            return _jpeg_size(data)
    except (ValueError, struct.error, IndexError) as exc:
        raise ScorePacketError(f"decode layer: unreadable {CODECS[codec][0]} header "
                               f"({exc})") from None
    raise ScorePacketError(f"decode layer: unknown codec {codec}")


def _webp_size(data: bytes) -> tuple[int, int]:
    if data[:4] != b"RIFF" or data[8:12] != b"WEBP":
        raise ValueError("no RIFF/WEBP signature")
    chunk = data[12:16]
    if chunk == b"VP8 ":  # lossy: a key frame's start code, then 14-bit sizes
        if data[23:26] != b"\x9d\x01\x2a":
            raise ValueError("no VP8 start code")
        w, h = struct.unpack("<HH", data[26:30])
        return w & 0x3FFF, h & 0x3FFF
    if chunk == b"VP8L":  # lossless: signature 0x2f, then 14-bit sizes minus one
        if data[20] != 0x2F:
            raise ValueError("no VP8L signature")
        bits = int.from_bytes(data[21:25], "little")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8X":  # extended: 24-bit canvas sizes minus one
        w = int.from_bytes(data[24:27], "little") + 1
        h = int.from_bytes(data[27:30], "little") + 1
        return w, h
    raise ValueError(f"unknown WebP chunk {chunk!r}")


def _jpeg_size(data: bytes) -> tuple[int, int]:
    if data[:2] != b"\xff\xd8":
        raise ValueError("no SOI marker")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ValueError(f"no marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = struct.unpack(">H", data[i + 2:i + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # SOFn
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        if length < 2:
            raise ValueError("bad segment length")
        i += 2 + length
    raise ValueError("no SOF marker")
