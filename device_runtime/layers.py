"""Refinement layers on the device: decode a layer's file through pygame, apply it to the
frame at rest (`protocol.layers` specifies the packets and how their chunks are joined).

`decode_file` turns a joined layer file into pixels with pygame's image loader (SDL_image:
PNG, JPEG, WebP), which the device has already; the file's declared size was checked against
the image's when its first chunk came (`protocol.layers.decode_layer`), and the decoded
surface is checked again. `RestFrame` is the frame a resting view shows while layers refine
it (a copy the device owns), with the count of layers applied; `RestFrame.apply` follows the
protocol's rule (a residual only after every layer before it, an absolute one after at most
its own), so a lost or stale layer is never misapplied, and says when an exact layer has
made the frame the host's ray-cast, bit for bit.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from protocol.layers import CODECS, LayerChunk

__all__ = ["LayerError", "RestFrame", "decode_file"]


class LayerError(ValueError):
    """A layer's file does not decode to the image's size."""


def decode_file(data: bytes, codec: int, image_shape: tuple[int, int]) -> np.ndarray:
    """A layer file's pixels, uint8 (height, width, 3), decoded by pygame's image loader.

    Raises
    ------
    LayerError
        pygame cannot decode the file, or it decodes to another size.
    """
    import pygame

    height, width = image_shape
    try:
        surface = pygame.image.load(io.BytesIO(data), CODECS[codec][1])
    except (pygame.error, ValueError, OSError) as exc:
        raise LayerError(f"layer: {CODECS[codec][0]} does not decode "
                         f"({' '.join(str(exc).split())[:80]})") from None
    if surface.get_size() != (width, height):
        raise LayerError(f"layer: decoded {surface.get_size()}, the image is {(width, height)}")
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
        Layers applied since the frame named by ``base_frame``.
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

    def __post_init__(self) -> None:
        self.frame = np.array(self.frame, dtype=np.uint8, copy=True)

    def accepts(self, chunk: LayerChunk) -> bool:
        """Whether the layer ``chunk`` belongs to applies now (module docstring)."""
        if chunk.residual:
            return self.layers == chunk.layer
        return self.layers <= chunk.layer

    def apply(self, chunk: LayerChunk, pixels: np.ndarray) -> None:
        """Apply a decoded layer that `accepts` said applies: the frame replaced (absolute)
        or corrected (residual: ``clip(F + ((D - 128) << shift))`` in int16)."""
        if chunk.residual:
            delta = pixels.astype(np.int16)
            delta -= 128
            if chunk.shift:
                delta <<= chunk.shift
            delta += self.frame
            np.clip(delta, 0, 255, out=delta)
            self.frame[...] = delta
        else:
            self.frame[...] = pixels
        self.layers = chunk.layer + 1
        self.is_exact = chunk.exact
        self.finished = chunk.last_layer
