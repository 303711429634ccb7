"""Transfer functions: piecewise-linear RGBA over normalised intensity.

A transfer function maps a scalar value ``v`` to colour and opacity in two
steps: ``t = clip((v - lo) / (hi - lo), 0, 1)`` with an intensity window
``(lo, hi)`` -- given, or found automatically from robust percentiles of the
volume -- then piecewise-linear colour and opacity curves over ``t``.

Opacity convention: an opacity point's alpha is the opacity of a slab one
*unit* thick, where the unit is the volume's smallest voxel spacing. The
ray-caster corrects it for its step: ``alpha' = 1 - (1 - alpha)**(step/unit)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TransferFunction"]


@dataclass(frozen=True, eq=False)
class TransferFunction:
    """Piecewise-linear RGBA transfer function.

    Parameters
    ----------
    name : str
    color_points : ndarray of shape (n, 4)
        Rows ``(t, r, g, b)`` with ``t`` increasing in [0, 1], colours in [0, 1].
    opacity_points : ndarray of shape (m, 2)
        Rows ``(t, alpha)`` with ``t`` increasing in [0, 1], alpha in [0, 1].
    window : tuple (lo, hi) or None
        Absolute intensity window; None means automatic from `percentiles`.
    percentiles : tuple (p_lo, p_hi)
        Percentiles of the volume's values used for the automatic window.
    """

    name: str
    color_points: np.ndarray
    opacity_points: np.ndarray
    window: tuple[float, float] | None = None
    percentiles: tuple[float, float] = (0.5, 99.5)

    def lut(self, n: int = 1024) -> np.ndarray:
        """Sample the curves at ``n`` evenly spaced ``t``: float32 (n, 4) RGBA."""
        t = np.linspace(0.0, 1.0, n)
        c = np.asarray(self.color_points, dtype=np.float64)
        o = np.asarray(self.opacity_points, dtype=np.float64)
        out = np.empty((n, 4), dtype=np.float32)
        for ch in range(3):
            out[:, ch] = np.interp(t, c[:, 0], c[:, 1 + ch])
        out[:, 3] = np.interp(t, o[:, 0], o[:, 1])
        return out
