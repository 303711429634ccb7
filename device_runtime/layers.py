"""Refinement layers on the device: decode a strip through pygame, apply it to the frame at
rest (`protocol.layers` specifies the packets).

`decode_strip` turns a checked `LayerPacket`'s file into pixels with pygame's image loader
(SDL_image: PNG, JPEG, WebP), which the device has already; the file's declared size was
checked against the strip before (`protocol.layers.decode_layer`), and the decoded surface
is checked again. `RestFrame` is the frame a resting view shows once its correction is on
show (a copy the device owns), with each row's count of layers applied; `RestFrame.apply`
follows the protocol's rule (a residual strip only on rows that had exactly the layers before
it, an absolute one on rows that had at most its own), so a lost or stale strip is never
misapplied, and says when every row has had an exact strip: the frame is then the host's
ray-cast bit for bit.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from protocol.layers import CODECS, LayerPacket

__all__ = ["LayerError", "RestFrame", "decode_strip"]


class LayerError(ValueError):
    """A layer's file does not decode to its strip."""


def decode_strip(packet: LayerPacket, width: int) -> np.ndarray:
    """The strip's pixels, uint8 (rows, width, 3), decoded by pygame's image loader.

    Raises
    ------
    LayerError
        pygame cannot decode the file, or it decodes to another size.
    """
    import pygame

    try:
        surface = pygame.image.load(io.BytesIO(packet.data), CODECS[packet.codec][1])
    except (pygame.error, ValueError, OSError) as exc:
        raise LayerError(f"layer {packet.layer}: {CODECS[packet.codec][0]} does not decode "
                         f"({' '.join(str(exc).split())[:80]})") from None
    if surface.get_size() != (width, packet.rows):
        raise LayerError(f"layer {packet.layer}: decoded {surface.get_size()}, the strip is "
                         f"{(width, packet.rows)}")
    to_bytes = getattr(pygame.image, "tobytes", None) or pygame.image.tostring
    return np.frombuffer(to_bytes(surface, "RGB"), np.uint8).reshape(packet.rows, width, 3)


@dataclass
class RestFrame:
    """The frame of a resting view that layers refine, and how far each row has come.

    Attributes
    ----------
    view : (float, float)
    base_frame : int
        The correction packet whose frame this is (0: the device's own frame, uncorrected).
    frame : ndarray (height, width, 3) uint8
        The device's copy, refined in place.
    layers : ndarray (height,) int16
        Per row, the layers applied since the correction.
    exact : ndarray (height,) bool
        Per row, whether an exact strip has been applied.
    """

    view: tuple[float, float]
    base_frame: int
    frame: np.ndarray
    layers: np.ndarray = field(init=False)
    exact: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.frame = np.array(self.frame, dtype=np.uint8, copy=True)
        self.layers = np.zeros(self.frame.shape[0], np.int16)
        self.exact = np.zeros(self.frame.shape[0], bool)

    @property
    def is_exact(self) -> bool:
        """Every row has had an exact strip: the frame is the ray-cast."""
        return bool(self.exact.all())

    def accepts(self, packet: LayerPacket) -> bool:
        """Whether ``packet`` applies now to every row of its strip (module docstring)."""
        rows = self.layers[packet.y0:packet.y0 + packet.rows]
        if packet.residual:
            return bool((rows == packet.layer).all())
        return bool((rows <= packet.layer).all())

    def apply(self, packet: LayerPacket, pixels: np.ndarray) -> None:
        """Apply a decoded strip that `accepts` said applies: its rows replaced (absolute)
        or corrected (residual: ``clip(F + ((D - 128) << shift))`` in int16)."""
        out = self.frame[packet.y0:packet.y0 + packet.rows]
        if packet.residual:
            delta = pixels.astype(np.int16)
            delta -= 128
            if packet.shift:
                delta <<= packet.shift
            delta += out
            np.clip(delta, 0, 255, out=delta)
            out[...] = delta
        else:
            out[...] = pixels
        self.layers[packet.y0:packet.y0 + packet.rows] = packet.layer + 1
        self.exact[packet.y0:packet.y0 + packet.rows] = packet.exact
