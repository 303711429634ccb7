"""Refinement layers at rest, host side: from a resting view's frame to the exact ray-cast,
in as few bytes as each step's quality allows (`protocol.layers` is the format,
`device_runtime.layers` the device's side; research/rest_layers.md the measurements).

Once a view rests, ``serve`` has the view's full ray-cast ``R``, the device's own frame ``S``
of it and the frame ``F`` its complete correction would make (the device's code, run on the
host). `RestPlanner.plan` then lays out the layers:

1. **The first lossy layer** reaches the lowest target (object SSIM, `DEFAULT_TARGETS`) the
   own frame does not: the cheapest of the correction alone (when ``F`` reaches it), and a
   WebP (`method` 6, at the lowest quality setting that reaches it: a bisection) of the
   residual ``R - S`` offset by 128 or of ``R`` itself, sent without the correction. The
   residual against the own frame was the cheapest first step on 53 of 60 views of five
   shared volumes at 0.95 (0.35-0.97x the smallest WebP of ``R``); sending the correction
   first paid on 1 of 180 view and target pairs (its cell-wise changes cost a residual more
   than they save), so a correction followed by a residual is not tried.
2. **Later lossy layers** (more targets): the cheaper of the residual against the device's
   frame after the layers before and ``R`` itself, as above.
3. **The exact layer**: ``R`` itself, lossless (WebP lossless, or PNG when smaller), never
   coded against the device's frame: on a CPU whose float32 arithmetic differs from the
   host's in a level here and there (docs/protocol.md) the frame still ends exactly ``R``.
   A frame of more than ``strip_pixels`` pixels (a device that reads strips) is sent in
   strips of at most that many, each its own file the device decodes in its own display
   tick: at 512 px four WebP lossless strips cost 0.96-1.03x the whole file, and each
   decodes in about half the tooth's blend where the whole file takes 1.4x it.

A layer is one file of the whole frame (independent tiles cost 4-32 % more bytes), cut into
chunks no larger than ``max_packet_bytes``: the device's largest frame, and on a slow line
what it carries in a quarter of a second (`serve` sets it), so a new view's correction never
waits behind more than one chunk. pygame decodes a whole frame's file in half a blend's time
or less (research/rest_layers.md). What the device will show after each layer (its frame, as
pygame decodes the file) is in the plan, so its quality and cumulative bytes are known
before anything is sent.
"""

from __future__ import annotations

import dataclasses
import io
import itertools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from device_runtime.layers import RestFrame, decode_file
from protocol.layers import (
    CODEC_PNG,
    CODEC_WEBP,
    LAYER_HEADER_SIZE,
    STRIP_PIXELS,
    LayerChunk,
    encode_layer,
    marked_last,
)

__all__ = [
    "DEFAULT_TARGETS",
    "EncodedLayer",
    "Plan",
    "PlannedLayer",
    "RestPlanner",
    "object_ssim",
]

#: Object SSIM each lossy layer reaches, before the exact layer.
DEFAULT_TARGETS = (0.95,)
#: A pixel whose largest channel is above this shows the object (black background).
OBJECT_LEVEL = 2
_SSIM_WIN = 7
#: The residual's shift: R - F offset by 128, clipped (the exact layer fixes what a clip
#: loses; halving it cost more at every quality, research/rest_layers.md).
RESIDUAL_SHIFT = 0
_WEBP_METHOD = 6


@dataclass
class PlannedLayer:
    """One layer of a plan.

    Attributes
    ----------
    packets : list of bytes
        The chunks of its file, in order.
    frame : ndarray (height, width, 3) uint8
        The device's frame once it is applied (decoded as the device decodes it).
    quality : float
        Object SSIM of ``frame`` against the ray-cast (1.0 exact).
    residual, exact : bool
        Coded against the device's frame; the ray-cast's pixels losslessly.
    codec : str
        ``"webp"``, ``"webp-lossless"`` or ``"png"``.
    """

    packets: list[bytes]
    frame: np.ndarray
    quality: float
    residual: bool
    exact: bool
    codec: str

    @property
    def size_bytes(self) -> int:
        return sum(len(p) for p in self.packets)


@dataclass(frozen=True)
class EncodedLayer:
    """One chunk's packet as ``serve`` sends it.

    Attributes
    ----------
    packet : bytes
    frame : int
        Its frame number.
    layer : int
        The layer it belongs to (0 first).
    last : bool
        The layer's last chunk: once it is in, the device shows ``quality``.
    exact : bool
        A chunk of the exact layer.
    quality : float
        Object SSIM of the device's frame once the whole layer is applied.
    """

    packet: bytes
    frame: int
    layer: int
    last: bool
    exact: bool
    quality: float
    step: None = None  # (a score packet's step: a layer has none)

    def numbered(self, frame: int) -> EncodedLayer:
        """The same chunk as frame number ``frame`` (its packet's header rewritten)."""
        packet = self.packet[:4] + int(frame).to_bytes(4, "little") + self.packet[8:]
        return dataclasses.replace(self, packet=packet, frame=int(frame))


@dataclass
class Plan:
    """The layers of one resting view and whether its complete correction is sent first."""

    skip_correction: bool
    layers: list[PlannedLayer] = field(default_factory=list)

    def sends(self) -> list[EncodedLayer]:
        """Every chunk's packet in the order it is sent."""
        out = []
        for index, layer in enumerate(self.layers):
            for k, packet in enumerate(layer.packets):
                frame = int.from_bytes(packet[4:8], "little")
                assert len(packet) > LAYER_HEADER_SIZE
                out.append(EncodedLayer(packet, frame, index, k == len(layer.packets) - 1,
                                        layer.exact, layer.quality))
        return out

    @property
    def size_bytes(self) -> int:
        return sum(layer.size_bytes for layer in self.layers)


class RestPlanner:
    """Plans the refinement layers of resting views (module docstring).

    Parameters
    ----------
    image_digest : bytes
        The model's digest (each packet carries its first 4 bytes).
    quality : callable, optional
        ``quality(truth, frame) -> float``; default `object_ssim`.
    targets : sequence of float
        Object SSIM of each lossy layer, increasing; layers whose target the frame already
        reaches are skipped.
    exact : bool
        End with the exact layer (else stop after the last target).
    max_packet_bytes : int
        A chunk's packet at most (the device's largest frame, a slow line's quarter
        second).
    strip_pixels : int or None
        The exact layer of a frame with more pixels goes in strips of at most this many
        (default `protocol.layers.STRIP_PIXELS`; None: one file, for a device that reads
        no strips).
    """

    def __init__(self, image_digest: bytes,
                 quality: Callable[[np.ndarray, np.ndarray], float] | None = None,
                 *, targets: tuple[float, ...] = DEFAULT_TARGETS, exact: bool = True,
                 max_packet_bytes: int = 1 << 16,
                 strip_pixels: int | None = STRIP_PIXELS) -> None:
        targets = tuple(float(t) for t in targets)
        if any(not 0.0 < t < 1.0 for t in targets) or list(targets) != sorted(targets):
            raise ValueError(f"targets={targets}: increasing object SSIMs in (0, 1) expected")
        if max_packet_bytes < 256:
            raise ValueError(f"max_packet_bytes={max_packet_bytes} must be >= 256")
        if strip_pixels is not None and strip_pixels < 1:
            raise ValueError(f"strip_pixels={strip_pixels} must be >= 1 (or None)")
        self.digest = bytes(image_digest)
        self.quality = quality if quality is not None else object_ssim
        self.targets = targets
        self.exact = bool(exact)
        self.max_packet_bytes = int(max_packet_bytes)
        self.strip_pixels = None if strip_pixels is None else int(strip_pixels)
        self._settings: dict[tuple[bool, float], int] = {}  # last WebP quality per choice

    # ------------------------------------------------------------------ the plan
    def plan(self, view: tuple[float, float], truth: np.ndarray, corrected: np.ndarray,
             own: np.ndarray, correction_bytes: int, *, base_frame: int,
             first_frame: int) -> Plan:
        """The layers of a resting view whose full ray-cast is ``truth``: either after its
        complete correction (``corrected``: the device's frame with it, ``correction_bytes``;
        its packet's frame number ``base_frame``), or, when that costs more, refining the
        device's ``own`` frame without it (base frame 0). Packets are numbered from
        ``first_frame``."""
        truth = np.asarray(truth, dtype=np.uint8)
        corrected = np.asarray(corrected, dtype=np.uint8)
        own = np.asarray(own, dtype=np.uint8)
        skip, first = self._first(view, truth, corrected, own, correction_bytes, base_frame,
                                  first_frame)
        start, base = (own, 0) if skip else (corrected, base_frame)
        return Plan(skip, self._layers(view, truth, start, base, first_frame, first=first))

    def _first(self, view: tuple[float, float], truth: np.ndarray, corrected: np.ndarray,
               own: np.ndarray, correction_bytes: int, base_frame: int, frame: int
               ) -> tuple[bool, PlannedLayer | None]:
        """Whether to skip the correction, and the first lossy layer (None: none). The first
        target is the lowest the own frame does not reach (none: the own frame needs no
        correction and no lossy layer); the cheaper way to reach it wins: the correction
        alone (when its frame reaches it), or a layer over the own frame alone (module
        docstring)."""
        target = next((t for t in self.targets if t > self.quality(truth, own)), None)
        if target is None:
            return True, None
        options: list[tuple[int, bool, PlannedLayer | None]] = []
        if base_frame and self.quality(truth, corrected) >= target:
            options.append((correction_bytes, False, None))
        layer = self._lossy(view, truth, own, target, 0, frame, 0, residual=True)
        if layer is not None:
            options.append((layer.size_bytes, True, layer))
        if not options:  # nothing reaches it: the exact layer after the correction, if any
            return base_frame == 0, None
        _, skip, layer = min(options, key=lambda o: o[0])
        return skip, layer

    def _layers(self, view: tuple[float, float], truth: np.ndarray, current: np.ndarray,
                base_frame: int, frame: int, *,
                first: PlannedLayer | None = None) -> list[PlannedLayer]:
        """The lossy layers from ``current`` (the first one given, when planned already),
        then the exact one."""
        layers: list[PlannedLayer] = []
        if first is not None:
            layers.append(first)
            frame += len(first.packets)
            current = first.frame
        reached = first.quality if first is not None else self.quality(truth, current)
        for target in self.targets:
            if reached >= target:
                continue
            layer = self._lossy(view, truth, current, target, base_frame, frame, len(layers),
                                residual=True)
            if layer is None:
                break
            layers.append(layer)
            frame += len(layer.packets)
            current, reached = layer.frame, layer.quality
        if self.exact:
            layers.append(self._exact(view, truth, current, base_frame, frame, len(layers)))
        if layers:  # the device knows no more are coming once the last one is in
            layers[-1].packets = [marked_last(p) for p in layers[-1].packets]
        return layers

    def _lossy(self, view: tuple[float, float], truth: np.ndarray, current: np.ndarray,
               target: float, base_frame: int, frame: int, index: int, *,
               residual: bool) -> PlannedLayer | None:
        """The cheaper of the residual and the absolute WebP layer reaching ``target``
        (None: neither does, even at the best setting)."""
        best = None
        for as_residual in ((True, False) if residual else (False,)):
            layer = self._search(view, truth, current, target, base_frame, frame, index,
                                 as_residual)
            if layer is not None and (best is None or layer.size_bytes < best.size_bytes):
                best = layer
        return best

    def _search(self, view: tuple[float, float], truth: np.ndarray, current: np.ndarray,
                target: float, base_frame: int, frame: int, index: int,
                residual: bool) -> PlannedLayer | None:
        """The WebP layer at the lowest quality setting that reaches ``target``: a bisection
        from the setting the last view needed."""
        source = _residual(truth, current) if residual else truth
        memo: dict[int, PlannedLayer] = {}

        def at(q: int) -> PlannedLayer:
            if q not in memo:
                memo[q] = self._layer(view, source, truth, current, base_frame, frame, index,
                                      residual=residual, codec=CODEC_WEBP,
                                      encode=lambda px, q=q: _webp(px, quality=q))
            return memo[q]

        lo, hi = 0, 100
        if at(hi).quality < target:
            return None
        guess = self._settings.get((residual, target))
        if guess is not None:  # narrow the bracket around last view's setting
            if at(guess).quality >= target:
                hi = guess
                lo = max(0, guess - 16)
                if at(lo).quality >= target:
                    lo, hi = 0, lo
            else:
                lo = guess
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if at(mid).quality >= target:
                hi = mid
            else:
                lo = mid
        if at(lo).quality >= target:
            hi = lo
        self._settings[(residual, target)] = hi
        return at(hi)

    def _exact(self, view: tuple[float, float], truth: np.ndarray, current: np.ndarray,
               base_frame: int, frame: int, index: int) -> PlannedLayer:
        """The ray-cast, lossless: the smaller of WebP lossless and PNG, in strips of at
        most ``strip_pixels`` when the frame has more."""
        height, width = truth.shape[:2]
        if self.strip_pixels is None or height * width <= self.strip_pixels:
            return self._layer(view, truth, truth, current, base_frame, frame, index,
                               residual=False, codec=None, encode=None)
        n = -(-height * width // self.strip_pixels)
        bounds = np.linspace(0, height, min(n, height) + 1).round().astype(int)
        packets: list[bytes] = []
        strips = []
        for r0, r1 in itertools.pairwise(bounds):
            strips.append(self._layer(view, truth[r0:r1], truth[r0:r1], current[r0:r1],
                                      base_frame, frame + len(packets), index,
                                      residual=False, codec=None, encode=None, row0=int(r0)))
            packets += strips[-1].packets
        return PlannedLayer(packets, np.concatenate([s.frame for s in strips]), 1.0, False,
                            True, "+".join(sorted({s.codec for s in strips})))

    # ------------------------------------------------------------------ a layer
    def _layer(self, view: tuple[float, float], source: np.ndarray, truth: np.ndarray,
               current: np.ndarray, base_frame: int, frame: int, index: int, *,
               residual: bool, codec: int | None,
               encode: Callable[[np.ndarray], bytes] | None,
               row0: int | None = None) -> PlannedLayer:
        """``source`` coded as one file (``codec`` None: the exact layer, lossless: the
        smaller of WebP lossless and PNG) in chunks, and the device's frame after it (a
        strip from ``row0``: ``source`` and ``current`` are its rows)."""
        if codec is None:
            options = [(CODEC_WEBP, "webp-lossless", _webp(source, lossless=True)),
                       (CODEC_PNG, "png", _png(source))]
            codec, name, data = min(options, key=lambda o: len(o[2]))
        else:
            assert encode is not None
            name, data = "webp", encode(source)
        exact = name != "webp"
        shift = RESIDUAL_SHIFT if residual else 0
        packets = encode_layer(data, codec=codec, frame=frame, base_frame=base_frame,
                               view=view, image_digest=self.digest, layer=index,
                               residual=residual, shift=shift, exact=exact,
                               max_chunk_bytes=self.max_packet_bytes - LAYER_HEADER_SIZE,
                               row0=row0)
        rest = RestFrame(view, base_frame, current)
        chunk = LayerChunk(frame, base_frame, view[0], view[1], index, codec, residual, shift,
                           exact, False, len(data), 0, 0, b"", 0)  # (a strip as a whole)
        rest.apply(chunk, decode_file(data, codec, source.shape[:2]))
        quality = 1.0 if exact else self.quality(truth, rest.frame)
        return PlannedLayer(packets, rest.frame, quality, residual, exact, name)


def object_ssim(truth: np.ndarray, frame: np.ndarray) -> float:
    """Object SSIM of ``frame`` against the ray-cast ``truth`` (uint8 (h, w, 3)): scikit-
    image's SSIM map (7 x 7 window, ``data_range=255``, averaged over the channels) averaged
    over the pixels where ``truth`` shows the object (a channel above `OBJECT_LEVEL`), the
    image's 3-pixel border left out as scikit-image's mean does; evaluate's
    ``structural_similarity`` with its ``object_mask`` (a test checks they agree).

    The map is computed on the object's bounding box and 3 pixels around it only: every
    window of an object pixel lies inside it, so the values are the whole image's."""
    from skimage.metrics import structural_similarity as sk_ssim

    mask = truth.max(axis=2) > OBJECT_LEVEL
    if not mask.any():
        return 1.0
    h, w = mask.shape
    pad = (_SSIM_WIN - 1) // 2
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    r0, r1 = max(0, rows[0] - pad), min(h, rows[-1] + pad + 1)
    c0, c1 = max(0, cols[0] - pad), min(w, cols[-1] + pad + 1)
    if min(r1 - r0, c1 - c0) < _SSIM_WIN:  # too small a box for the window: the whole image
        r0, r1, c0, c1 = 0, h, 0, w
    _, full = sk_ssim(truth[r0:r1, c0:c1].astype(np.float64),
                      frame[r0:r1, c0:c1].astype(np.float64), data_range=255,
                      channel_axis=-1, full=True)
    ssim = np.zeros((h, w))
    ssim[r0:r1, c0:c1] = full.mean(axis=2)
    inner, m = ssim[pad:-pad, pad:-pad], mask[pad:-pad, pad:-pad]
    if not m.any():
        return float(ssim[mask].mean(dtype=np.float64))
    return float(inner[m].mean(dtype=np.float64))


def _residual(truth: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """``(truth - frame) >> RESIDUAL_SHIFT`` offset by 128, uint8 (floor division, as the
    device's shift back)."""
    d = truth.astype(np.int16) - frame.astype(np.int16)
    d >>= RESIDUAL_SHIFT
    d += 128
    return np.clip(d, 0, 255).astype(np.uint8)


def _webp(pixels: np.ndarray, *, quality: int = 100, lossless: bool = False) -> bytes:
    """A WebP file: lossy at ``quality`` (method 6), or lossless at method 4, quality 100
    (0.2-1.1 % fewer bytes than libwebp's default quality 80 at 1.3-1.5x its time, ~70 ms at
    256: more than a layer's 40-byte header; method 6 is 10x slower for little more)."""
    from PIL import Image

    out = io.BytesIO()
    if lossless:
        Image.fromarray(pixels).save(out, "WEBP", lossless=True, exact=True, quality=100,
                                     method=4)
    else:
        Image.fromarray(pixels).save(out, "WEBP", quality=quality, method=_WEBP_METHOD)
    return out.getvalue()


def _png(pixels: np.ndarray) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "PNG", optimize=True)
    return out.getvalue()
