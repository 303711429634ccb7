"""Volumes: the `Volume` type, file loaders and the built-in procedural volumes.

Conventions (shared by every host module):

* ``Volume.data`` has numpy shape ``(nz, ny, nx)`` -- x varies fastest in
  memory, as in every raw volume file -- dtype float32, C-contiguous, holding
  the scanner's values after any rescale (e.g. Hounsfield units for CT).
* ``Volume.spacing`` is ``(sx, sy, sz)`` in millimetres (x first).
* World coordinates: voxel ``data[k, j, i]`` sits at ``(i*sx, j*sy, k*sz)``;
  +z is "up" (superior for medical data) so an orbit camera with up = +z shows
  a head upright.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Volume"]

MODALITIES = ("ct", "mri", "tooth", "generic")


@dataclass(frozen=True, eq=False)
class Volume:
    """A scalar volume on a regular grid.

    Parameters
    ----------
    data : ndarray of shape (nz, ny, nx), float32
        Scalar values (x fastest).
    spacing : tuple of 3 floats
        Voxel size ``(sx, sy, sz)`` in millimetres.
    name : str
        Short name for reports (``"tooth"``, ``"head"`` ...).
    modality : {"ct", "mri", "tooth", "generic"}
        Picks the default transfer function.
    source : str
        Where it came from (a path or ``builtin:NAME``), for provenance.
    """

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    name: str = "volume"
    modality: str = "generic"
    source: str = ""
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        data = np.ascontiguousarray(self.data, dtype=np.float32)
        if data.ndim != 3 or min(data.shape) < 2:
            raise ValueError(f"volume data must be 3-D with every side >= 2, got {data.shape}")
        spacing = tuple(float(s) for s in self.spacing)
        if len(spacing) != 3 or not all(np.isfinite(s) and s > 0 for s in spacing):
            raise ValueError(f"spacing must be 3 positive numbers, got {self.spacing}")
        if self.modality not in MODALITIES:
            raise ValueError(f"modality={self.modality!r} must be one of {MODALITIES}")
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "spacing", spacing)

    @property
    def dims(self) -> tuple[int, int, int]:
        """Grid size ``(nx, ny, nz)``."""
        nz, ny, nx = self.data.shape
        return nx, ny, nz

    @property
    def extent_mm(self) -> np.ndarray:
        """Physical size ``(x, y, z)`` of the box spanned by voxel centres."""
        return (np.array(self.dims, dtype=np.float64) - 1.0) * np.array(self.spacing)

    @property
    def center_mm(self) -> np.ndarray:
        """World position of the volume centre."""
        return self.extent_mm / 2.0

    @property
    def radius_mm(self) -> float:
        """Radius of the bounding sphere around `center_mm`."""
        return float(np.linalg.norm(self.extent_mm) / 2.0)
