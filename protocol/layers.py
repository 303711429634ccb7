"""Refinement layers: the packets that take a resting view to the exact ray-cast.

Once a resting view's correction is on show (or in its place, research/rest_layers.md), the
host sends *layers*, coarse to fine, until the device's frame is the host's ray-cast bit for
bit. A layer is one image file of the whole frame in a codec the device decodes through
pygame (PNG, JPEG, WebP lossy or lossless), sent in one or more *chunks*, each a score packet
of version 4 (the same magic and SCORES message as the other versions; a decoder that does
not list 4 refuses it in one line). A file's bytes are cut into chunks that fit the device's
frames and a slow line's quarter second, and the device joins them.

Version 5 is the same packet whose file is a *strip*: the image's rows ``row0 .. row0 + h``
(``h`` the file's declared height; its width is the image's), so a large frame's layer can be
several files, each decoded in its own display tick (a 512 px WebP lossless frame takes two
of the tooth's blends to decode on one core, a quarter of it half of one). The host sends
version 5 only to a device that lists it (its HELLO reply's ``score_versions``), and only
where strips cost no bytes: lossless layers of frames over `STRIP_PIXELS` (at 512 px, four
strips of WebP lossless are 0.96-1.03x the whole file; two strips of a 256 px frame cost
0.5-2 % more, of a lossy WebP 2-5 %, research/rest_layers.md). Little-endian, 40-byte
header::

    offset size field
    0      2    magic b"\\xecS"
    2      1    version 4 (the whole frame) or 5 (a strip)
    3      1    flags: bit 0 RESIDUAL (the file is a residual, else the pixels themselves);
                bits 1-2 SHIFT s (a residual's values are v = (R - F) >> s offset by 128);
                bit 3 EXACT (absolute, lossless: the ray-cast's pixels exactly);
                bit 4 LAST (the last layer the host plans for this view);
                bits 5-7 reserved, 0
    4      4    frame number u32 (the host's packet counter)
    8      4    base frame number u32: the correction whose frame the layer refines (the
                frame number of the version-3 packet on show; 0: the device's own frame of
                the view, uncorrected)
    12     4    phi_deg float32 (canonical, as in version 3)
    16     4    theta_deg float32
    20     1    layer u8: the layer's place in the chain (0 first)
    21     1    codec u8: 1 PNG, 2 JPEG, 3 WebP (lossy or lossless, as the file says)
    22     2    version 4: reserved, 0; version 5: row0 u16, the strip's first row
    24     4    image tag: the first 4 bytes of the eigenspace image's SHA-256 digest
    28     4    file size u32: the whole file's bytes
    32     4    offset u32: where this chunk's bytes start in the file
    36     4    file CRC-32 (zlib's) of the whole file
    40     ..   the chunk: bytes offset .. offset + len of the file

Joining (`LayerAssembly`): a file's chunks come in order; its first chunk (offset 0) must
hold the file's header, whose declared width and height (`declared_size`: PNG's IHDR, JPEG's
SOF, WebP's VP8/VP8L/VP8X chunk) must be the image's (a strip: the image's width, and a
height of at least one row that ends within the image), and its file size must be within
`max_file_bytes` of the image, so no file makes a device allocate more than its bound; each
later chunk must continue the same file (same layer, base frame, view, sizes and CRC) at the
next byte. When the last byte is in, the CRC is checked and the file is ready to decode.

How the device applies a layer (`device_runtime.layers`) to its frame ``F`` of the view: an
absolute file replaces it (``F = D``); a residual adds to it (``F = clip(F + ((D - 128) <<
s), 0, 255)``, int16). The device counts the layers applied since the frame named by the base:
a residual of layer ``L`` applies only after exactly the layers before it (``L``), an absolute
one after at most ``L``; each sets the count to ``L + 1``. A layer in strips does so once
every row of the image has come in one of its strips (a residual strip applies only to rows
no strip of its layer has changed yet). A lost or dropped layer therefore
never misapplies the next one, and an absolute layer repairs any frame. The EXACT layer ends
the chain: the frame is then the ray-cast, whatever float32 arithmetic made the device's own
frame (the host never codes the exact step against it).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

from protocol.errors import LimitExceeded
from protocol.scores import MAGIC, ImageMismatch, ScorePacketError

__all__ = [
    "CODECS",
    "CODEC_JPEG",
    "CODEC_PNG",
    "CODEC_WEBP",
    "FIRST_CHUNK_MIN",
    "FLAG_EXACT",
    "FLAG_LAST",
    "FLAG_RESIDUAL",
    "LAYER_HEADER_SIZE",
    "LAYER_VERSION",
    "LAYER_VERSIONS",
    "MAX_SHIFT",
    "STRIP_PIXELS",
    "STRIP_VERSION",
    "LayerAssembly",
    "LayerChunk",
    "declared_size",
    "decode_header_flags",
    "decode_layer",
    "encode_layer",
    "is_layer",
    "marked_last",
    "max_file_bytes",
]

#: The score packet version of a layer of the whole frame, and of a strip of it.
LAYER_VERSION = 4
STRIP_VERSION = 5
LAYER_VERSIONS = (LAYER_VERSION, STRIP_VERSION)
#: Lossless layers of frames with more pixels than this go in strips of at most this many
#: (one 256 px frame: its WebP lossless decode is within the cheapest image's blend).
STRIP_PIXELS = 1 << 16
_HEADER = struct.Struct("<2sBBIIffBBH4sIII")
LAYER_HEADER_SIZE = _HEADER.size  # 40
FLAG_RESIDUAL = 0x01
_SHIFT_MASK, _SHIFT_BIT = 0x06, 1
FLAG_EXACT = 0x08
FLAG_LAST = 0x10
_RESERVED = 0xE0
#: The largest residual shift (a residual of 8-bit pixels needs at most one bit more).
MAX_SHIFT = 2
CODEC_PNG, CODEC_JPEG, CODEC_WEBP = 1, 2, 3
#: codec -> (name, what pygame's loader is told the file is)
CODECS = {CODEC_PNG: ("png", "x.png"), CODEC_JPEG: ("jpeg", "x.jpg"),
          CODEC_WEBP: ("webp", "x.webp")}
#: A file's first chunk holds at least this many bytes (or the whole file): every codec's
#: size fields lie within them.
FIRST_CHUNK_MIN = 512


def max_file_bytes(image_shape: tuple[int, int]) -> int:
    """The largest layer file a device of ``image_shape`` (height, width) takes: 4 bytes a
    pixel and 64 KiB (an incompressible frame, lossless, with any codec's overhead)."""
    return 4 * int(image_shape[0]) * int(image_shape[1]) + (1 << 16)


@dataclass(frozen=True)
class LayerChunk:
    """A decoded layer packet: one chunk of a layer's file (see the module docstring).

    Attributes
    ----------
    frame, base_frame : int
    phi_deg, theta_deg : float
    layer, codec : int
    residual : bool
    shift : int
    exact : bool
    last_layer : bool
        The last layer the host plans for the view (LAST).
    file_bytes, offset, crc : int
        The whole file's size and CRC-32, and where this chunk starts in it.
    data : bytes
        The chunk.
    packet_bytes : int
    row0 : int
        The first image row the file covers.
    strip : bool
        A strip (version 5): the file covers rows ``row0`` on, as many as it declares;
        else the whole image.
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
    last_layer: bool
    file_bytes: int
    offset: int
    crc: int
    data: bytes
    packet_bytes: int
    row0: int = 0
    strip: bool = False

    @property
    def last(self) -> bool:
        """The file's last chunk."""
        return self.offset + len(self.data) == self.file_bytes

    def same_file(self, other: LayerChunk) -> bool:
        """Whether ``other`` is a chunk of the same layer's file."""
        return (self.base_frame, self.phi_deg, self.theta_deg, self.layer, self.codec,
                self.residual, self.shift, self.exact, self.last_layer, self.file_bytes,
                self.crc, self.row0, self.strip) == (
            other.base_frame, other.phi_deg, other.theta_deg, other.layer, other.codec,
            other.residual, other.shift, other.exact, other.last_layer, other.file_bytes,
            other.crc, other.row0, other.strip)


def is_layer(packet: bytes | bytearray | memoryview) -> bool:
    """Whether a score packet is a layer (magic and version 4 or 5), from its first 3
    bytes."""
    return len(packet) >= 3 and bytes(packet[:2]) == MAGIC and packet[2] in LAYER_VERSIONS


def encode_layer(data: bytes, *, codec: int, frame: int, base_frame: int,
                 view: tuple[float, float], image_digest: bytes, layer: int,
                 residual: bool = False, shift: int = 0, exact: bool = False,
                 last: bool = False, max_chunk_bytes: int | None = None,
                 row0: int | None = None) -> list[bytes]:
    """The packets carrying the layer file ``data``: one, or chunks of at most
    ``max_chunk_bytes`` each (the first at least `FIRST_CHUNK_MIN`), numbered from
    ``frame`` (wrapping after 2**32 - 1 to 1). ``row0`` None: the file is the whole frame
    (version 4); a row: the file is the strip from that row (version 5).

    Raises
    ------
    ValueError
        A field out of its range (the codec, the shift, EXACT on a residual, an empty file).
    """
    if codec not in CODECS:
        raise ValueError(f"encode_layer: codec={codec!r} must be one of {sorted(CODECS)}")
    if not 0 <= shift <= MAX_SHIFT or (shift and not residual):
        raise ValueError(f"encode_layer: shift={shift!r} must be 0..{MAX_SHIFT}, on residuals")
    if exact and residual:
        raise ValueError("encode_layer: an EXACT layer is absolute, not a residual")
    for name, value, top in (("frame", frame, 0xFFFFFFFF),
                             ("base_frame", base_frame, 0xFFFFFFFF), ("layer", layer, 0xFF),
                             ("row0", row0 or 0, 0xFFFF)):
        if not 0 <= int(value) <= top:
            raise ValueError(f"encode_layer: {name}={value!r} must be within 0..{top}")
    if not data or len(data) > 0xFFFFFFFF:
        raise ValueError(f"encode_layer: a file of {len(data)} bytes")
    size = len(data)
    step = size if max_chunk_bytes is None else max(int(max_chunk_bytes), FIRST_CHUNK_MIN)
    flags = (FLAG_RESIDUAL if residual else 0) | (shift << _SHIFT_BIT) | (
        FLAG_EXACT if exact else 0) | (FLAG_LAST if last else 0)
    crc = zlib.crc32(data)
    packets = []
    for k, offset in enumerate(range(0, size, step)):
        number = (int(frame) + k - 1) % 0xFFFFFFFF + 1
        head = _HEADER.pack(MAGIC, LAYER_VERSION if row0 is None else STRIP_VERSION, flags,
                            number, base_frame, float(view[0]), float(view[1]), layer, codec,
                            row0 or 0, bytes(image_digest[:4]), size, offset, crc)
        packets.append(head + bytes(data[offset:offset + step]))
    return packets


def decode_header_flags(packet: bytes) -> tuple[int | None, int | None, int | None]:
    """(flags, offset, file size) of a layer packet's header; (None, None, None) for any
    other packet (tests, traces: nothing is checked)."""
    if not is_layer(packet) or len(packet) < LAYER_HEADER_SIZE:
        return None, None, None
    fields = _HEADER.unpack_from(bytes(packet[:LAYER_HEADER_SIZE]))
    return fields[2], fields[12], fields[11]


def marked_last(packet: bytes) -> bytes:
    """``packet`` with LAST set (its layer turned out to be the plan's last)."""
    return packet[:3] + bytes([packet[3] | FLAG_LAST]) + packet[4:]


def decode_layer(packet: bytes | bytearray | memoryview, *, image_digest: bytes,
                 image_shape: tuple[int, int], max_packet_bytes: int) -> LayerChunk:
    """Parse and check a layer packet: its size, header, image tag, the file's size, and
    (the first chunk) the image size its file declares. Nothing is decoded here.

    Raises
    ------
    LimitExceeded
        The packet is longer than ``max_packet_bytes``, or its file larger than
        `max_file_bytes` of the image.
    ImageMismatch
        Made for another eigenspace image.
    ScorePacketError
        Anything malformed: magic, version, reserved bits, codec, shift, EXACT with RESIDUAL,
        a view that is not finite, a chunk outside its file, a first chunk too short to hold
        the file's header, a file whose declared size is not the image's (a strip: not its
        width, or rows past its last).
    """
    n = len(packet)
    if n > max_packet_bytes:
        raise LimitExceeded(f"decode layer: packet of {n} bytes exceeds the limit of "
                            f"{max_packet_bytes}")
    if n < LAYER_HEADER_SIZE + 1:
        raise ScorePacketError(f"decode layer: {n} bytes is shorter than a header and a chunk")
    (magic, version, flags, frame, base, phi, theta, layer, codec, row0, tag, size,
     offset, crc) = _HEADER.unpack_from(bytes(packet[:LAYER_HEADER_SIZE]))
    if magic != MAGIC or version not in LAYER_VERSIONS:
        raise ScorePacketError(f"decode layer: not a layer packet (magic {magic!r}, version "
                               f"{version})")
    strip = version == STRIP_VERSION
    if flags & _RESERVED or (row0 and not strip):
        raise ScorePacketError(f"decode layer: reserved bits set (flags 0x{flags:02x})")
    residual, exact = bool(flags & FLAG_RESIDUAL), bool(flags & FLAG_EXACT)
    last_layer = bool(flags & FLAG_LAST)
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
    bound = max_file_bytes(image_shape)
    if size > bound:
        raise LimitExceeded(f"decode layer: a file of {size} bytes exceeds the limit of "
                            f"{bound}")
    data = bytes(packet[LAYER_HEADER_SIZE:])
    if offset + len(data) > size:
        raise ScorePacketError(f"decode layer: chunk {offset}..{offset + len(data)} outside "
                               f"a file of {size} bytes")
    if offset == 0:
        if len(data) < min(size, FIRST_CHUNK_MIN):
            raise ScorePacketError(f"decode layer: a first chunk of {len(data)} bytes cannot "
                                   "hold the file's header")
        height, width = image_shape
        declared = declared_size(data, codec)
        if strip and (declared[0] != width or not 1 <= declared[1] <= height - row0):
            raise ScorePacketError(f"decode layer: the {CODECS[codec][0]} strip declares "
                                   f"{declared[0]}x{declared[1]} from row {row0}, the image "
                                   f"is {width}x{height}")
        if not strip and declared != (width, height):
            raise ScorePacketError(f"decode layer: the {CODECS[codec][0]} file declares "
                                   f"{declared[0]}x{declared[1]}, the image is "
                                   f"{width}x{height}")
    elif strip and row0 >= image_shape[0]:
        raise ScorePacketError(f"decode layer: a strip from row {row0}, the image has "
                               f"{image_shape[0]}")
    return LayerChunk(frame, base, phi, theta, layer, codec, residual, shift, exact,
                      last_layer, size, offset, crc, data, n, row0, strip)


class LayerAssembly:
    """Joins a layer file's chunks (module docstring). One file at a time: a chunk of
    another file starts over (a first chunk) or is refused (a later one).

    Attributes
    ----------
    head : LayerChunk or None
        The first chunk of the file being joined.
    """

    def __init__(self) -> None:
        self.head: LayerChunk | None = None
        self._parts: list[bytes] = []
        self._have = 0

    def add(self, chunk: LayerChunk) -> bytes | None:
        """Take a chunk; return the whole file once its last byte is in (its CRC checked).

        Raises
        ------
        ScorePacketError
            A chunk that does not continue the file being joined (lost or reordered
            chunks), or a joined file whose CRC is wrong; the file is dropped.
        """
        if chunk.offset == 0:
            self.head, self._parts, self._have = chunk, [], 0
        elif self.head is None or not self.head.same_file(chunk) or chunk.offset != self._have:
            self.reset()
            raise ScorePacketError(f"decode layer: chunk at {chunk.offset} continues no file "
                                   "being joined (a chunk before it was lost)")
        self._parts.append(chunk.data)
        self._have += len(chunk.data)
        if self._have < chunk.file_bytes:
            return None
        data = b"".join(self._parts)
        self.reset()
        if zlib.crc32(data) != chunk.crc:
            raise ScorePacketError("decode layer: the joined file's CRC-32 is wrong")
        return data

    def reset(self) -> None:
        """Forget the file being joined."""
        self.head, self._parts, self._have = None, [], 0


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
