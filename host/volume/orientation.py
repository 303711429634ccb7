"""Orientation: axis codes, reorienting file order to RAS, the known-datasets table.

See `host.volume` for the precedence (caller, header, `KNOWN_DATASETS`, none). Every fix in
`KNOWN_DATASETS` is a proper rotation: when a header says nothing about left/right we never
mirror.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from host.errors import VolumeError

__all__ = [
    "KNOWN_DATASETS",
    "KnownDataset",
]

_OPPOSITE = {"R": "L", "L": "R", "A": "P", "P": "A", "S": "I", "I": "S"}
_WORLD_AXIS = {"R": 0, "L": 0, "A": 1, "P": 1, "S": 2, "I": 2}
_POSITIVE = ("R", "A", "S")


def _parse_axis_code(code: str, what: str = "orientation") -> str:
    """Validate a 3-letter axis code such as ``"LPS"``; return it upper-case."""
    text = str(code).strip().upper()
    if (
        len(text) != 3
        or any(c not in _WORLD_AXIS for c in text)
        or sorted(_WORLD_AXIS[c] for c in text) != [0, 1, 2]
    ):
        raise VolumeError(
            f"{what}={code!r} must be 3 letters naming where +x, +y, +z of the file point, "
            "one of R/L, one of A/P and one of S/I (e.g. LPS, RAS, LPI)"
        )
    return text


def _axis_code_from_directions(directions: np.ndarray, world: str) -> str:
    """Axis code of index axes whose world directions are the rows of ``directions``.

    ``world`` names the positive world axes, e.g. ``"LPS"`` for DICOM/ITK or
    ``"RAS"`` for NIfTI; each index axis gets the world axis it is most
    aligned with (greedy, largest cosine first, like nibabel's io_orientation).
    """
    d = np.asarray(directions, dtype=np.float64)
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    if d.shape != (3, 3) or not np.all(np.isfinite(d)) or np.any(norms == 0):
        raise ValueError(f"direction matrix must be 3x3 finite non-zero, got {d.tolist()}")
    d = np.abs(d / norms)
    letters = [""] * 3
    free_rows, free_cols = {0, 1, 2}, {0, 1, 2}
    while free_rows:
        best = max(((r, c) for r in free_rows for c in free_cols), key=lambda rc: d[rc])
        r, c = best
        sign = np.sign(np.asarray(directions, dtype=np.float64)[r, c])
        letters[r] = world[c] if sign >= 0 else _OPPOSITE[world[c]]
        free_rows.discard(r)
        free_cols.discard(c)
    return "".join(letters)


def _reorient_to_ras(
    data: np.ndarray, spacing: tuple[float, ...], code: str
) -> tuple[np.ndarray, tuple[float, float, float]]:
    """Transpose/flip ``data`` (file order (k, j, i)) so its axes are RAS.

    Parameters
    ----------
    data : ndarray of shape (nk, nj, ni)
    spacing : (si, sj, sk) in file axis order
    code : axis code of the file's (i, j, k)

    Returns
    -------
    data : ndarray of shape (nz, ny, nx), a view where possible
    spacing : (sx, sy, sz)
    """
    src_for_world = [0, 0, 0]
    for n, letter in enumerate(code):
        src_for_world[_WORLD_AXIS[letter]] = n
    # numpy axis of file axis n is 2 - n; output numpy axes are world (z, y, x)
    out = np.transpose(data, [2 - src_for_world[w] for w in (2, 1, 0)])
    flips = tuple(2 - w for w in range(3) if code[src_for_world[w]] not in _POSITIVE)
    if flips:
        out = np.flip(out, axis=flips)
    new_spacing = tuple(float(spacing[src_for_world[w]]) for w in range(3))
    return out, new_spacing  # type: ignore[return-value]


def _is_proper_rotation(code: str) -> bool:
    """True when going from ``code`` to RAS is a rotation (no mirror)."""
    m = np.zeros((3, 3))
    for n, letter in enumerate(code):
        m[n, _WORLD_AXIS[letter]] = 1.0 if letter in _POSITIVE else -1.0
    return bool(np.linalg.det(m) > 0)


@dataclass(frozen=True)
class KnownDataset:
    """Orientation and modality of a well-known volume that has no such metadata."""

    file_axes: str
    modality: str
    note: str


#: (lower-case file stem, file dims (x, y, z), dtype name) -> facts. Checked by
#: looking at maximum-intensity projections; every fix is a proper rotation.
KNOWN_DATASETS: dict[tuple[str, tuple[int, int, int], str], KnownDataset] = {
    ("tooth", (140, 120, 161), "uint8"): KnownDataset(
        "RPI",
        "tooth",
        "paper's Tooth: crown stored at z=0; rotated 180 deg about x so the crown is up",
    ),
    ("vismale_head", (128, 256, 256), "uint8"): KnownDataset(
        "RPI",
        "ct",
        "Visible Male head: slices run top of head -> neck and +y points posterior; "
        "rotated 180 deg about x (left/right unknown, not mirrored)",
    ),
    ("headsq", (64, 64, 93), "uint16"): KnownDataset(
        "LAI",
        "ct",
        "VTK headsq: slices run top of head -> neck (VTK examples use view-up -z), "
        "+y anterior; rotated 180 deg about y (not mirrored)",
    ),
    ("brainsmall", (128, 128, 84), "uint8"): KnownDataset(
        "PIR",
        "mri",
        "VolPack brainsmall: sagittal slices, +x posterior, +y inferior; rotated so the "
        "head is upright and faces +y (left/right unknown, not mirrored)",
    ),
}
