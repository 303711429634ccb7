"""What a volume's values say about its modality when nothing else does.

A header names the modality (DICOM ``Modality``, MetaImage ``Modality``), `KNOWN_DATASETS`
knows a few files, the user passes ``--modality``; when none of them says anything,
`guess_modality` looks at the values, and only for CT, whose values are calibrated:

* **Hounsfield units.** A signed voxel type (int16, int32, float) with at least 1 % of the
  voxels within 100 of -1000 (air) and values above +100 (tissue, bone): the values are HU.
* **Hounsfield units with an offset.** A 16-bit integer type (the 12-bit scanners' exports,
  usually HU + 1024) whose histogram has air at its bottom and a soft-tissue peak
  (`tissue_peaks`) 900-1200 above it: a scale within a quarter of 1 HU per unit.

Anything else (8-bit data, MRI, an industrial CT of metal with no soft tissue) is left
``generic``: its transfer function windows the data by percentiles, which suits any data.
`tissue_peaks` is also what the CT transfer functions calibrate such exports with
(`host.render.transfer.hu_calibration`).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["guess_modality", "tissue_peaks"]

_SAMPLE_VOXELS = 4_000_000
AIR_HU = -1000.0
SOFT_TISSUE_HU = 40.0
_AIR_SHARE = 0.01  # at least this share of the voxels is air
_OFFSET_SOFT = (900.0, 1200.0)  # soft tissue above air in a 16-bit HU export, in file units


def sample_values(data: np.ndarray) -> np.ndarray:
    """At most about 4 M finite voxels of ``data`` (fixed stride), as a flat float32 array."""
    flat = np.asarray(data, dtype=np.float32).ravel()
    if flat.size > _SAMPLE_VOXELS:
        flat = flat[:: math.ceil(flat.size / _SAMPLE_VOXELS)]
    finite = np.isfinite(flat)
    if not finite.all():
        flat = flat[finite]
    return flat


def tissue_peaks(flat: np.ndarray) -> tuple[float, float] | None:
    """``(air, soft)``: the values of air and soft tissue in a head or body CT, or None.

    Air is the lowest values (0.5th percentile); soft tissue is the most populated
    1/128-wide histogram bin among values at least 10 % of the robust range above air.
    None when there is no such peak (a flat histogram, the bin under 2 % of the voxels).

    Parameters
    ----------
    flat : ndarray of shape (n_voxels,), float32
        Finite values (`sample_values`).
    """
    if flat.size == 0:
        return None
    air, top = (float(v) for v in np.percentile(flat, [0.5, 99.9]))
    if not top > air:
        return None
    start = air + 0.10 * (top - air)
    counts, edges = np.histogram(flat, bins=128, range=(start, top))
    if counts.sum() == 0 or counts.max() < 0.02 * flat.size:
        return None
    peak = int(np.argmax(counts))
    soft = 0.5 * (edges[peak] + edges[peak + 1])
    if not soft > air:
        return None
    return air, float(soft)


def guess_modality(data: np.ndarray, file_dtype: str) -> tuple[str, str | None, str] | None:
    """``(modality, units, why)`` when the values say CT (module docstring), else None.

    Parameters
    ----------
    data : ndarray
        The volume's values (any order).
    file_dtype : str
        The voxel type as stored in the file (``"uint16"``, ``"int16"``, ``"float32"`` ...).

    Returns
    -------
    tuple or None
        ``("ct", "HU", why)`` for values in Hounsfield units, ``("ct", None, why)`` for a
        16-bit export with an offset; ``why`` is a phrase for the user.
    """
    flat = sample_values(data)
    if flat.size == 0:
        return None
    kind = np.dtype(file_dtype).kind
    low, high = float(flat.min()), float(flat.max())
    if kind in "if":
        air = np.count_nonzero(np.abs(flat - AIR_HU) <= 100.0) / flat.size
        if air >= _AIR_SHARE and high > 100.0:
            return ("ct", "HU", f"{file_dtype} values from {low:g} to {high:g} with air at "
                    "-1000: Hounsfield units")
    if kind in "iu" and np.dtype(file_dtype).itemsize == 2 and low > -200.0:
        peaks = tissue_peaks(flat)
        if peaks is not None:
            air, soft = peaks
            if _OFFSET_SOFT[0] <= soft - air <= _OFFSET_SOFT[1]:
                return ("ct", None, f"{file_dtype} values from {low:g} to {high:g} with air "
                        f"at {air:g} and soft tissue {soft - air:.0f} above it: Hounsfield "
                        "units with an offset")
    return None
