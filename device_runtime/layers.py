"""Refinement layers on the device: decode a layer's file through pygame, apply it to the
frame at rest (`protocol.layers` specifies the packets and how their chunks are joined).

`decode_file` turns a joined layer file into pixels with pygame's image loader (SDL_image:
PNG, JPEG, WebP), which the device has already; the file's declared size was checked against
the image's when its first chunk came (`protocol.layers.decode_layer`), and the decoded
surface is checked again. `RestFrame` is the frame a resting view shows while layers refine
it (a copy the device owns), with the count of layers applied; `RestFrame.apply` follows the
protocol's rule (a residual only after every layer before it, an absolute one after at most
its own; a layer in strips counts once all its rows are in), so a lost or stale layer is
never misapplied, and says when an exact layer has made the frame the host's ray-cast, bit
for bit.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from protocol.layers import CODECS, LayerChunk, declared_size
from protocol.scores import ScorePacketError

__all__ = ["LayerError", "RestFrame", "decode_file"]


class LayerError(ValueError):
    """A layer's file does not decode to the image's size."""


def decode_file(data: bytes, codec: int, image_shape: tuple[int, int], *,
                row0: int | None = None) -> np.ndarray:
    """A layer file's pixels, uint8 (height, width, 3), decoded by pygame's image loader:
    the whole image's, or (``row0`` given) a strip's from that row, as many rows as the
    file declares.

    Raises
    ------
    LayerError
        pygame cannot decode the file, or it decodes to another size (a strip: not the
        image's width, or rows past the image's last).
    """
    import pygame

    height, width = image_shape
    if row0 is not None:
        try:
            rows = declared_size(data, codec)[1]
        except ScorePacketError as exc:
            raise LayerError(f"layer: {exc}") from None
        if not 1 <= rows <= height - row0:
            raise LayerError(f"layer: a strip of {rows} rows from row {row0}, the image has "
                             f"{height}")
        height = rows
    try:
        surface = pygame.image.load(io.BytesIO(data), CODECS[codec][1])
    except (pygame.error, ValueError, OSError) as exc:
        raise LayerError(f"layer: {CODECS[codec][0]} does not decode "
                         f"({' '.join(str(exc).split())[:80]})") from None
    if surface.get_size() != (width, height):
        raise LayerError(f"layer: decoded {surface.get_size()}, the image is {(width, height)}")
    if surface.get_bitsize() in (24, 32):
        # A view of the surface's own pixels, copied once: tobytes' conversion was a
        # quarter of a 256 WebP lossless layer's decode, this is a fiftieth.
        view = pygame.surfarray.pixels3d(surface)
        try:
            return np.array(view.transpose(1, 0, 2), dtype=np.uint8, order="C")
        finally:
            del view  # unlocks the surface
    to_bytes = getattr(pygame.image, "tobytes", None) or pygame.image.tostring
    return np.frombuffer(to_bytes(surface, "RGB"), np.uint8).reshape(height, width, 3)


@dataclass
class RestFrame:
    """The frame of a resting view that layers refine, and how far it has come.

    Attributes
    ----------
    view : (float, float)
    base_frame : int
        The correction packet whose frame this is (0: the device's own frame, uncorrected).
    frame : ndarray (height, width, 3) uint8
        The device's copy, refined in place.
    layers : int
        Layers applied since the frame named by ``base_frame`` (a layer in strips once
        every row is in).
    is_exact : bool
        The last layer applied was exact: the frame is the ray-cast.
    finished : bool
        The host's last planned layer is applied: no more are coming.
    """

    view: tuple[float, float]
    base_frame: int
    frame: np.ndarray
    layers: int = field(default=0, init=False)
    is_exact: bool = field(default=False, init=False)
    finished: bool = field(default=False, init=False)
    #: (layer, rows applied) of a layer in strips not yet complete
    _partial: tuple[int, np.ndarray] | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.frame = np.array(self.frame, dtype=np.uint8, copy=True)

    def accepts(self, chunk: LayerChunk) -> bool:
        """Whether the layer ``chunk`` belongs to applies now (module docstring)."""
        if chunk.residual:
            partial = self._partial
            return self.layers == chunk.layer and not (
                chunk.strip and partial is not None and partial[0] == chunk.layer
                and partial[1][chunk.row0])
        return self.layers <= chunk.layer

    def apply(self, chunk: LayerChunk, pixels: np.ndarray) -> None:
        """Apply a decoded layer (or strip) that `accepts` said applies: its rows of the
        frame replaced (absolute) or corrected (residual: ``clip(F + ((D - 128) << shift))``
        in int16)."""
        rows = slice(chunk.row0, chunk.row0 + pixels.shape[0]) if chunk.strip else slice(None)
        target = self.frame[rows]
        if chunk.residual:
            delta = pixels.astype(np.int16)
            delta -= 128
            if chunk.shift:
                delta <<= chunk.shift
            delta += target
            np.clip(delta, 0, 255, out=delta)
            target[...] = delta
        else:
            target[...] = pixels
        if chunk.strip:
            if self._partial is None or self._partial[0] != chunk.layer:
                self._partial = (chunk.layer, np.zeros(self.frame.shape[0], dtype=bool))
            done = self._partial[1]
            done[rows] = True
            if not done.all():
                return
        self._partial = None
        self.layers = chunk.layer + 1
        self.is_exact = chunk.exact
        self.finished = chunk.last_layer
