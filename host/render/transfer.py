"""Transfer functions: piecewise-linear RGBA over normalised intensity.

A transfer function maps a scalar value ``v`` to colour and opacity in two
steps: ``t = clip((v - lo) / (hi - lo), 0, 1)`` with an intensity window
``(lo, hi)`` -- given, or found automatically from robust percentiles of the
volume -- then piecewise-linear colour and opacity curves over ``t``.

Opacity convention: an opacity point's alpha is the opacity of a slab one
*unit* thick, where the unit is the volume's smallest voxel spacing. The
ray-caster corrects it for its step: ``alpha' = 1 - (1 - alpha)**(step/unit)``.

How the window is found (`TransferFunction.resolve_window`)
-----------------------------------------------------------
* ``window_units == "data"`` and ``window`` set: that window, as given.
* ``window_units == "HU"`` (the CT presets): the preset's window is in
  Hounsfield units, so bone is bone whatever the volume's contents. If the
  volume says its values are HU (``metadata["units"] == "HU"``: DICOM CT after
  rescale, MetaImage ``Modality = MET_MOD_CT``, ``builtin:head``) the window
  is used as is. Otherwise (8/16-bit CT exports without a rescale) the values
  are calibrated to HU from two histogram peaks every head/body CT has --
  air (taken as -1000 HU) and soft tissue (+40 HU) -- see `hu_calibration`;
  when no such peaks exist the percentile rule below is used instead.
* otherwise: robust percentiles of the *foreground*. Let ``p0.1`` and
  ``p99.9`` be the 0.1st and 99.9th percentiles of all voxels and
  ``floor = p0.1 + 0.02 * (p99.9 - p0.1)``; the foreground is every voxel
  above ``floor`` (this drops the air/background that fills most scans) and
  the window is ``percentiles`` (default 0.5, 99.5) of the foreground.
  Percentiles ignore a few extreme voxels, so outliers do not move the window.
  Volumes over 4 M voxels are subsampled with a fixed stride (deterministic).

ParaView / VolView presets (`load_transfer_function` with a ``.json`` path)
----------------------------------------------------------------------------
The file is what ParaView's *Export* writes (``ExportTransferFunction``): a
list of preset objects (or one object) with ``RGBPoints`` as flat
``[x, r, g, b, ...]``, ``Points`` as flat ``[x, alpha, midpoint, sharpness,
...]`` (the opacity curve) and ``ColorSpace``; VolView-style ``OpacityPoints``
are flat ``[x, alpha, ...]`` pairs. ``x`` values are data units and set an
*absolute* window ``(min x, max x)``, unless the object says
``"AbsoluteRange": false`` (then the curves are stretched over the automatic
window, as ParaView does when it rescales a preset). Non-linear opacity
segments (midpoint != 0.5 or sharpness != 0, VTK's formula) and colour spaces
other than RGB (Lab, Diverging, HSV, Step) are resampled into extra linear
points. Without an opacity curve, opacity ramps linearly 0 -> 1 (ParaView's
default). Opacities are taken as per-voxel alphas (ParaView's scalar opacity
unit distance equal to the voxel size). ``path.json#NAME`` picks a preset by
name from a list; without it the first preset is used.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from host.errors import TransferFunctionError
from host.volume.modality import AIR_HU, SOFT_TISSUE_HU, sample_values, tissue_peaks

if TYPE_CHECKING:
    from host.volume import Volume

__all__ = [
    "PRESETS",
    "TransferFunction",
    "add_transfer_function_argument",
    "default_transfer_function",
    "describe_transfer_function",
    "hu_calibration",
    "load_transfer_function",
    "transfer_function_from_args",
]

WINDOW_UNITS = ("data", "HU")
_MAX_JSON_BYTES = 16 << 20


def _points(value: object, columns: int, what: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TransferFunctionError(f"{what} must be a list of numbers") from None
    if arr.ndim != 2 or arr.shape[1] != columns or arr.shape[0] < 1:
        raise TransferFunctionError(
            f"{what} must have shape (n, {columns}) with n >= 1, got {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise TransferFunctionError(f"{what} contains NaN or infinite values")
    return arr


@dataclass(frozen=True, eq=False)
class TransferFunction:
    """Piecewise-linear RGBA transfer function.

    Parameters
    ----------
    name : str
    color_points : ndarray of shape (n, 4)
        Rows ``(t, r, g, b)`` with ``t`` non-decreasing in [0, 1] (a repeated
        ``t`` makes a step), colours in [0, 1].
    opacity_points : ndarray of shape (m, 2)
        Rows ``(t, alpha)`` with ``t`` non-decreasing in [0, 1], alpha in [0, 1]
        (alpha per unit length, see the module docstring).
    window : tuple (lo, hi) or None
        Absolute intensity window in `window_units`; None means automatic.
    percentiles : tuple (p_lo, p_hi)
        Percentiles of the foreground used for the automatic window.
    window_units : {"data", "HU"}
        ``"HU"``: `window` is in Hounsfield units (CT presets); see the module
        docstring for how it maps onto volumes that are not in HU.
    description : str
        One line for ``--help`` and reports.

    Raises
    ------
    TransferFunctionError
        When a field is out of range; the message names it.
    """

    name: str
    color_points: np.ndarray
    opacity_points: np.ndarray
    window: tuple[float, float] | None = None
    percentiles: tuple[float, float] = (0.5, 99.5)
    window_units: str = "data"
    description: str = ""

    def __post_init__(self) -> None:
        where = f"transfer function {self.name!r}"
        c = _points(self.color_points, 4, f"{where}: color_points")
        o = _points(self.opacity_points, 2, f"{where}: opacity_points")
        for arr, label in ((c, "color_points"), (o, "opacity_points")):
            t = arr[:, 0]
            if t.min() < 0.0 or t.max() > 1.0:
                raise TransferFunctionError(f"{where}: {label} t must lie in [0, 1]")
            if np.any(np.diff(t) < 0):
                raise TransferFunctionError(f"{where}: {label} t must be non-decreasing")
            if arr[:, 1:].min() < 0.0 or arr[:, 1:].max() > 1.0:
                raise TransferFunctionError(f"{where}: {label} values must lie in [0, 1]")
        c.flags.writeable = False
        o.flags.writeable = False
        object.__setattr__(self, "color_points", c)
        object.__setattr__(self, "opacity_points", o)
        if self.window is not None:
            try:
                lo, hi = (float(v) for v in self.window)
            except (TypeError, ValueError):
                raise TransferFunctionError(
                    f"{where}: window={self.window!r} must be two numbers (lo, hi)"
                ) from None
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise TransferFunctionError(
                    f"{where}: window=({lo}, {hi}) must be finite with lo < hi"
                )
            object.__setattr__(self, "window", (lo, hi))
        try:
            p_lo, p_hi = (float(v) for v in self.percentiles)
        except (TypeError, ValueError):
            raise TransferFunctionError(
                f"{where}: percentiles={self.percentiles!r} must be two numbers"
            ) from None
        if not 0.0 <= p_lo < p_hi <= 100.0:
            raise TransferFunctionError(
                f"{where}: percentiles=({p_lo}, {p_hi}) must satisfy 0 <= lo < hi <= 100"
            )
        object.__setattr__(self, "percentiles", (p_lo, p_hi))
        if self.window_units not in WINDOW_UNITS:
            raise TransferFunctionError(
                f"{where}: window_units={self.window_units!r} must be one of {WINDOW_UNITS}"
            )
        if self.window_units == "HU" and self.window is None:
            raise TransferFunctionError(f"{where}: window_units='HU' needs a window")

    # ------------------------------------------------------------------ lookup

    def lut(self, n: int = 1024) -> np.ndarray:
        """Sample the curves at ``n`` evenly spaced ``t`` in [0, 1].

        Returns
        -------
        ndarray of shape (n, 4), float32
            RGBA rows; row ``i`` is at ``t = i / (n - 1)``.
        """
        if int(n) < 2:
            raise ValueError(f"n={n} must be >= 2")
        t = np.linspace(0.0, 1.0, int(n))
        c, o = self.color_points, self.opacity_points
        out = np.empty((int(n), 4), dtype=np.float32)
        for ch in range(3):
            out[:, ch] = np.interp(t, c[:, 0], c[:, 1 + ch])
        out[:, 3] = np.interp(t, o[:, 0], o[:, 1])
        return out

    def normalize(self, values: np.ndarray, window: tuple[float, float]) -> np.ndarray:
        """``t = clip((values - lo) / (hi - lo), 0, 1)`` as float32."""
        lo, hi = window
        scale = np.float32(1.0 / (hi - lo))
        return np.clip((np.asarray(values, dtype=np.float32) - np.float32(lo)) * scale, 0.0, 1.0)

    # ------------------------------------------------------------------ window

    def resolve_window(self, volume: Volume) -> tuple[float, float]:
        """Intensity window ``(lo, hi)`` in the volume's data units.

        See the module docstring for the rules. Always returns ``lo < hi``.
        """
        if self.window is not None and self.window_units == "data":
            return self.window
        if self.window is not None and self.window_units == "HU":
            if volume.metadata.get("units") == "HU":
                return self.window
            calibration = hu_calibration(volume)
            if calibration is not None:
                scale, offset = calibration  # HU = scale * v + offset
                lo, hi = ((w - offset) / scale for w in self.window)
                return float(lo), float(hi)
        return _percentile_window(volume.data, self.percentiles)

    # ------------------------------------------------------------------ serialisation

    def to_dict(self) -> dict:
        """JSON-able description; `from_dict` gives back an equal function."""
        return {
            "name": self.name,
            "description": self.description,
            "color_points": self.color_points.tolist(),
            "opacity_points": self.opacity_points.tolist(),
            "window": None if self.window is None else list(self.window),
            "window_units": self.window_units,
            "percentiles": list(self.percentiles),
        }

    @classmethod
    def from_dict(cls, data: dict) -> TransferFunction:
        """Inverse of `to_dict`; bad input raises `TransferFunctionError`."""
        if not isinstance(data, dict):
            raise TransferFunctionError(
                f"transfer function must be a JSON object, got {type(data).__name__}"
            )
        required = {"name", "color_points", "opacity_points"}
        allowed = required | {"description", "window", "window_units", "percentiles"}
        missing = sorted(required - data.keys())
        unknown = sorted(data.keys() - allowed)
        if missing or unknown:
            raise TransferFunctionError(
                f"transfer function dict: missing keys {missing}, unknown keys {unknown}"
            )
        window = data.get("window")
        return cls(
            name=str(data["name"]),
            color_points=data["color_points"],
            opacity_points=data["opacity_points"],
            window=None if window is None else tuple(window),
            percentiles=tuple(data.get("percentiles", (0.5, 99.5))),
            window_units=str(data.get("window_units", "data")),
            description=str(data.get("description", "")),
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, TransferFunction):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(json.dumps(self.to_dict(), sort_keys=True))


# --------------------------------------------------------------------------
# automatic windows
# --------------------------------------------------------------------------


def _sample(data: np.ndarray) -> np.ndarray:
    """At most about 4 M finite voxels (fixed stride), as a flat float32 array."""
    return sample_values(data)


def _percentile_window(data: np.ndarray, percentiles: tuple[float, float]) -> tuple[float, float]:
    flat = _sample(data)
    if flat.size == 0:
        return 0.0, 1.0
    p_min, p_max = np.percentile(flat, [0.1, 99.9])
    floor = p_min + 0.02 * (p_max - p_min)
    foreground = flat[flat > floor]
    if foreground.size < 16:
        foreground = flat
    lo, hi = (float(v) for v in np.percentile(foreground, percentiles))
    if not hi > lo:  # constant volume (or nearly): any non-empty window will do
        lo, hi = float(flat.min()), float(flat.max())
        if not hi > lo:
            lo, hi = lo - 0.5, lo + 0.5
    return lo, hi


def hu_calibration(volume: Volume) -> tuple[float, float] | None:
    """Linear map ``HU = scale * value + offset`` estimated from histogram peaks.

    Air is the lowest values (0.5th percentile, taken as -1000 HU); soft
    tissue is the most populated 1/128-wide histogram bin among values at
    least 10 % of the robust range above air (taken as +40 HU). Returns None
    when the volume is already in HU (``metadata["units"] == "HU"``) or shows no
    such peak (flat histogram, soft-tissue bin under 2 % of the voxels).
    """
    if volume.metadata.get("units") == "HU":
        return None
    peaks = tissue_peaks(_sample(volume.data))
    if peaks is None:
        return None
    air, soft = peaks
    scale = (SOFT_TISSUE_HU - AIR_HU) / (soft - air)
    return float(scale), float(AIR_HU - scale * air)


# --------------------------------------------------------------------------
# presets
# --------------------------------------------------------------------------

_CT_WINDOW = (-1000.0, 2000.0)


def _hu(points: list[tuple[float, ...]]) -> list[list[float]]:
    """Points given in HU -> t over the CT presets' window."""
    lo, hi = _CT_WINDOW
    return [[(p[0] - lo) / (hi - lo), *p[1:]] for p in points]


PRESETS: dict[str, TransferFunction] = {
    tf.name: tf
    for tf in (
        TransferFunction(
            "ct-bone",
            _hu(
                [
                    (-1000, 0, 0, 0),
                    (120, 0.55, 0.24, 0.16),
                    (300, 0.88, 0.66, 0.46),
                    (600, 0.95, 0.88, 0.74),
                    (1200, 1, 0.98, 0.93),
                    (2000, 1, 1, 1),
                ]
            ),
            _hu([(-1000, 0), (150, 0), (300, 0.12), (500, 0.55), (900, 0.85), (2000, 0.9)]),
            window=_CT_WINDOW,
            window_units="HU",
            description="CT bone: opaque bone from ~300 HU, ivory shading, soft tissue hidden",
        ),
        TransferFunction(
            "ct-skin",
            _hu(
                [
                    (-1000, 0, 0, 0),
                    (-500, 0.55, 0.25, 0.15),
                    (-250, 0.88, 0.6, 0.45),
                    (0, 0.95, 0.78, 0.66),
                    (400, 1, 0.9, 0.84),
                    (2000, 1, 1, 1),
                ]
            ),
            _hu([(-1000, 0), (-550, 0), (-300, 0.35), (-100, 0.8), (2000, 0.9)]),
            window=_CT_WINDOW,
            window_units="HU",
            description="CT skin: the air/skin boundary as an opaque skin-coloured surface",
        ),
        TransferFunction(
            "ct-muscle",
            _hu(
                [
                    (-1000, 0, 0, 0),
                    (-150, 0.55, 0.25, 0.15),
                    (40, 0.78, 0.32, 0.26),
                    (220, 0.88, 0.6, 0.29),
                    (420, 1, 0.94, 0.95),
                    (2000, 0.83, 0.66, 1),
                ]
            ),
            _hu([(-1000, 0), (-20, 0), (40, 0.18), (220, 0.6), (420, 0.8), (2000, 0.8)]),
            window=_CT_WINDOW,
            window_units="HU",
            description="CT muscle: soft tissue in red, fat hidden, bone bright",
        ),
        TransferFunction(
            "mri-default",
            [
                [0, 0, 0, 0],
                [0.1, 0.17, 0, 0],
                [0.2, 0.4, 0.15, 0.08],
                [0.5, 0.78, 0.61, 0.38],
                [0.8, 0.85, 0.84, 0.79],
                [1, 1, 1, 1],
            ],
            [[0, 0], [0.12, 0], [0.25, 0.12], [0.5, 0.3], [0.8, 0.4], [1, 0.5]],
            percentiles=(1.0, 99.5),
            description="MRI: foreground percentile window, dark red -> beige -> white",
        ),
        TransferFunction(
            "tooth",
            [
                [0, 0, 0, 0],
                [0.12, 0.62, 0.16, 0.12],
                [0.3, 0.8, 0.38, 0.3],
                [0.55, 0.93, 0.85, 0.66],
                [0.8, 0.97, 0.94, 0.84],
                [1, 0.92, 0.96, 1],
            ],
            [
                [0, 0],
                [0.1, 0],
                [0.2, 0.25],
                [0.4, 0.05],
                [0.55, 0.05],
                [0.62, 0.35],
                [0.8, 0.6],
                [1, 0.95],
            ],
            percentiles=(0.5, 99.5),
            description="tooth: pulp red, dentin translucent ivory, enamel opaque white",
        ),
        TransferFunction(
            "generic",
            [[0, 0.05, 0.05, 0.2], [0.3, 0.3, 0.45, 0.75], [0.7, 0.9, 0.85, 0.6], [1, 1, 1, 1]],
            [[0, 0], [0.15, 0], [0.5, 0.3], [1, 0.8]],
            description="any data: foreground percentile window, blue -> beige -> white ramp",
        ),
    )
}

_DEFAULT_FOR_MODALITY = {"ct": "ct-bone", "mri": "mri-default", "tooth": "tooth"}


def default_transfer_function(volume: Volume) -> TransferFunction:
    """The preset that suits ``volume``: by ``metadata["default_tf"]``, else modality.

    ct -> ``ct-bone``, mri -> ``mri-default``, tooth -> ``tooth``, anything
    else -> ``generic``.
    """
    name = volume.metadata.get("default_tf") or _DEFAULT_FOR_MODALITY.get(
        volume.modality, "generic"
    )
    return PRESETS[name]


_MODALITY_SOURCES = {
    "user": "--modality",
    "header": "the file's header",
    "known-dataset": "a known dataset",
    "builtin": "the built-in volume",
}


def describe_transfer_function(volume: Volume, tf: TransferFunction, spec: str | None) -> str:
    """One line for the user: which transfer function, for which modality and why, and its
    window in the volume's values.

    Parameters
    ----------
    volume : Volume
    tf : TransferFunction
        The one chosen (`transfer_function_from_args`).
    spec : str or None
        ``--tf`` as given (None: the default for the modality).
    """
    lo, hi = tf.resolve_window(volume)
    units = " HU" if volume.metadata.get("units") == "HU" else ""
    window = f"window {lo:.4g} to {hi:.4g}{units}"
    if spec is not None:
        return f"transfer function {tf.name} (--tf), {window}"
    source = volume.metadata.get("modality_source")
    if source == "data":
        why = f" (not in the header; the data say so: {volume.metadata.get('modality_note')})"
    elif source in _MODALITY_SOURCES:
        why = f" (from {_MODALITY_SOURCES[source]})"
    elif volume.modality == "generic":
        why = (" (nothing in the header, and the data do not look like CT in Hounsfield "
               "units; --modality or --tf choose another look)")
    else:
        why = ""
    return f"transfer function {tf.name} for modality {volume.modality}{why}, {window}"


# --------------------------------------------------------------------------
# ParaView / VolView JSON
# --------------------------------------------------------------------------


def load_transfer_function(spec: str | Path) -> TransferFunction:
    """A preset name (see `PRESETS`) or a ParaView/VolView preset JSON file.

    ``FILE.json#NAME`` selects the preset called NAME from a file holding a
    list of presets. See the module docstring for the format.

    Raises
    ------
    TransferFunctionError
        Unknown preset (listing the known ones), unreadable or malformed file.
    """
    text = str(spec)
    if text.lower() in PRESETS:
        return PRESETS[text.lower()]
    path_text, _, wanted = text.partition("#")
    path = Path(path_text).expanduser()
    if not path.is_file():
        if path.suffix.lower() == ".json" or "/" in path_text or path.exists():
            raise TransferFunctionError(f"{path}: transfer function file not found")
        raise TransferFunctionError(
            f"unknown transfer function {text!r}; presets: {', '.join(PRESETS)}, "
            "or a ParaView/VolView preset .json file"
        )
    try:
        size = path.stat().st_size
        if size > _MAX_JSON_BYTES:
            raise TransferFunctionError(
                f"{path}: {size} bytes is over the {_MAX_JSON_BYTES} byte limit for presets"
            )
        document = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TransferFunctionError(f"{path}: not valid JSON: {exc}") from None
    except OSError as exc:
        raise TransferFunctionError(f"{path}: cannot read: {exc.strerror or exc}") from None
    presets = document if isinstance(document, list) else [document]
    presets = [p for p in presets if isinstance(p, dict)]
    if not presets:
        raise TransferFunctionError(f"{path}: no preset objects in the file")
    if wanted:
        chosen = [p for p in presets if str(p.get("Name", "")) == wanted]
        if not chosen:
            names = [str(p.get("Name", "?")) for p in presets]
            raise TransferFunctionError(f"{path}: no preset named {wanted!r}; has {names}")
        preset = chosen[0]
    else:
        preset = presets[0]
    try:
        return _from_paraview(preset, path)
    except TransferFunctionError as exc:
        message = str(exc)
        if not message.startswith(str(path)):
            message = f"{path}: {message}"
        raise TransferFunctionError(message) from None


def _flat(preset: dict, key: str, group: int) -> np.ndarray | None:
    if key not in preset:
        return None
    values = preset[key]
    if not isinstance(values, list) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in values
    ):
        raise TransferFunctionError(f"{key} must be a flat list of numbers")
    if len(values) == 0 or len(values) % group:
        raise TransferFunctionError(
            f"{key} has {len(values)} numbers; expected a non-empty multiple of {group}"
        )
    arr = np.array(values, dtype=np.float64).reshape(-1, group)
    if not np.all(np.isfinite(arr)):
        raise TransferFunctionError(f"{key} contains NaN or infinite values")
    return arr[np.argsort(arr[:, 0], kind="stable")]


def _from_paraview(preset: dict, path: Path) -> TransferFunction:
    if "IndexedColors" in preset:
        raise TransferFunctionError("categorical (IndexedColors) presets are not supported")
    if preset.get("UseLogScale"):
        raise TransferFunctionError("log-scale presets (UseLogScale) are not supported")
    rgb = _flat(preset, "RGBPoints", 4)
    if rgb is None:
        raise TransferFunctionError("preset has no RGBPoints")
    opacity = _flat(preset, "Points", 4)
    if opacity is None:
        pairs = _flat(preset, "OpacityPoints", 2)
        if pairs is not None:
            opacity = np.column_stack([pairs, np.full(len(pairs), 0.5), np.zeros(len(pairs))])
    if np.any((rgb[:, 1:] < 0) | (rgb[:, 1:] > 1)):
        raise TransferFunctionError("RGBPoints colours must lie in [0, 1]")
    if opacity is not None and np.any((opacity[:, 1] < 0) | (opacity[:, 1] > 1)):
        raise TransferFunctionError("opacity values must lie in [0, 1]")

    xs = rgb[:, 0] if opacity is None else np.concatenate([rgb[:, 0], opacity[:, 0]])
    lo, hi = float(xs.min()), float(xs.max())
    if not hi > lo:
        raise TransferFunctionError(f"all points sit at x={lo}: the range is empty")
    absolute = preset.get("AbsoluteRange", True)
    if not isinstance(absolute, bool):
        raise TransferFunctionError(f"AbsoluteRange={absolute!r} must be true or false")

    def to_t(x: np.ndarray) -> np.ndarray:
        return np.clip((x - lo) / (hi - lo), 0.0, 1.0)

    space = str(preset.get("ColorSpace", "RGB"))
    color_points = _resample_colors(
        to_t(rgb[:, 0]), rgb[:, 1:], space, bool(preset.get("HSVWrap", False))
    )
    if opacity is None:
        opacity_points = np.array([[0.0, 0.0], [1.0, 1.0]])
    else:
        opacity_points = _resample_opacity(to_t(opacity[:, 0]), opacity[:, 1:])
    name = str(preset.get("Name", path.stem))
    return TransferFunction(
        name=name,
        color_points=_pad_ends(color_points),
        opacity_points=_pad_ends(opacity_points),
        window=(lo, hi) if absolute else None,
        description=f"imported from {path.name} (ParaView/VolView preset, ColorSpace {space})",
    )


def _pad_ends(points: np.ndarray) -> np.ndarray:
    """Make the curve start at t=0 and end at t=1 (constant beyond the points)."""
    if points[0, 0] > 0.0:
        points = np.vstack([np.concatenate([[0.0], points[0, 1:]]), points])
    if points[-1, 0] < 1.0:
        points = np.vstack([points, np.concatenate([[1.0], points[-1, 1:]])])
    return points


_SEGMENT_SAMPLES = 16


def _vtk_piecewise(s: np.ndarray, y1: float, y2: float, mid: float, sharp: float) -> np.ndarray:
    """VTK's vtkPiecewiseFunction value between two nodes at fractions ``s``."""
    mid = min(max(mid, 1e-5), 1.0 - 1e-5)
    s = np.where(s < mid, 0.5 * s / mid, 0.5 + 0.5 * (s - mid) / (1.0 - mid))
    if sharp > 0.99:
        return np.where(s < 0.5, y1, y2)
    if sharp < 0.01:
        return (1.0 - s) * y1 + s * y2
    power = 1.0 + 10.0 * sharp
    s = np.where(
        s < 0.5,
        0.5 * np.power(np.clip(s * 2.0, 0.0, None), power),
        np.where(s > 0.5, 1.0 - 0.5 * np.power(np.clip((1.0 - s) * 2.0, 0.0, None), power), s),
    )
    ss, sss = s * s, s * s * s
    h1, h2 = 2 * sss - 3 * ss + 1, -2 * sss + 3 * ss
    h3, h4 = sss - 2 * ss + s, sss - ss
    slope = (1.0 - sharp) * (y2 - y1)
    value = h1 * y1 + h2 * y2 + (h3 + h4) * slope
    return np.clip(value, min(y1, y2), max(y1, y2))


def _resample_opacity(t: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Rows (t, alpha); segments with midpoint/sharpness become several linear pieces."""
    rows = [[t[0], rest[0, 0]]]
    for i in range(len(t) - 1):
        y1, y2 = rest[i, 0], rest[i + 1, 0]
        mid, sharp = float(rest[i, 1]), float(rest[i, 2])
        if sharp > 0.99:  # VTK: piecewise constant, jumping at the midpoint
            t_mid = t[i] + min(max(mid, 1e-5), 1.0 - 1e-5) * (t[i + 1] - t[i])
            rows += [[t_mid, y1], [t_mid, y2]]
        elif abs(mid - 0.5) > 1e-9 or sharp >= 0.01:
            s = np.linspace(0.0, 1.0, _SEGMENT_SAMPLES + 1)[1:-1]
            for sv, yv in zip(s, _vtk_piecewise(s, y1, y2, mid, sharp)):
                rows.append([t[i] + sv * (t[i + 1] - t[i]), float(yv)])
        rows.append([t[i + 1], y2])
    return np.array(rows, dtype=np.float64)


def _resample_colors(t: np.ndarray, rgb: np.ndarray, space: str, hsv_wrap: bool) -> np.ndarray:
    """Rows (t, r, g, b) linear in RGB that follow ParaView's interpolation in ``space``."""
    key = space.strip().lower()
    if key == "rgb" or len(t) == 1:
        return np.column_stack([t, rgb])
    if key == "step":
        rows = []
        for i in range(len(t)):
            if i > 0:
                rows.append([t[i], *rgb[i - 1]])
            rows.append([t[i], *rgb[i]])
        return np.array(rows)
    interpolators = {
        "lab": _lerp_lab,
        "cielab": _lerp_lab,
        "diverging": _lerp_diverging,
        "hsv": lambda a, b, f: _lerp_hsv(a, b, f, hsv_wrap),
    }
    if key not in interpolators:
        raise TransferFunctionError(
            f"ColorSpace {space!r} unsupported; supported: RGB, Lab, CIELAB, Diverging, HSV, Step"
        )
    lerp = interpolators[key]
    rows = [[t[0], *rgb[0]]]
    f = np.linspace(0.0, 1.0, _SEGMENT_SAMPLES + 1)[1:]
    for i in range(len(t) - 1):
        colors = lerp(rgb[i], rgb[i + 1], f)
        for fv, col in zip(f, colors):
            rows.append([t[i] + fv * (t[i + 1] - t[i]), *np.clip(col, 0.0, 1.0)])
    return np.array(rows, dtype=np.float64)


# colour-space helpers (sRGB D65, as VTK's vtkMath)
_XYZ_WHITE = np.array([0.9505, 1.0, 1.089])
_RGB_TO_XYZ = np.array(
    [[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]
)


def _rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    c = np.asarray(rgb, dtype=np.float64)
    linear = np.where(c > 0.04045, ((c + 0.055) / 1.055) ** 2.4, c / 12.92)
    xyz = linear @ _RGB_TO_XYZ.T / _XYZ_WHITE
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16.0 / 116.0)
    return np.stack(
        [
            116.0 * f[..., 1] - 16.0,
            500.0 * (f[..., 0] - f[..., 1]),
            200.0 * (f[..., 1] - f[..., 2]),
        ],
        axis=-1,
    )


def _lab_to_rgb(lab: np.ndarray) -> np.ndarray:
    lab = np.asarray(lab, dtype=np.float64)
    fy = (lab[..., 0] + 16.0) / 116.0
    f = np.stack([fy + lab[..., 1] / 500.0, fy, fy - lab[..., 2] / 200.0], axis=-1)
    xyz = np.where(f**3 > 0.008856, f**3, (f - 16.0 / 116.0) / 7.787) * _XYZ_WHITE
    linear = xyz @ np.linalg.inv(_RGB_TO_XYZ).T
    linear = np.clip(linear, 0.0, None)
    return np.where(linear > 0.0031308, 1.055 * linear ** (1 / 2.4) - 0.055, 12.92 * linear)


def _lerp_lab(a: np.ndarray, b: np.ndarray, f: np.ndarray) -> np.ndarray:
    la, lb = _rgb_to_lab(a), _rgb_to_lab(b)
    return _lab_to_rgb(la[None, :] * (1 - f[:, None]) + lb[None, :] * f[:, None])


def _lab_to_msh(lab: np.ndarray) -> np.ndarray:
    m = float(np.linalg.norm(lab))
    s = math.acos(max(-1.0, min(1.0, lab[0] / m))) if m > 0 else 0.0
    h = math.atan2(lab[2], lab[1])
    return np.array([m, s, h])


def _msh_to_lab(msh: np.ndarray) -> np.ndarray:
    m, s, h = msh
    return np.array([m * math.cos(s), m * math.sin(s) * math.cos(h), m * math.sin(s) * math.sin(h)])


def _adjust_hue(msh: np.ndarray, m_unsat: float) -> float:
    m, s, h = msh
    if m >= m_unsat - 0.1:
        return float(h)
    spin = s * math.sqrt(m_unsat**2 - m**2) / (m * math.sin(s))
    return float(h + spin if h > -math.pi / 3 else h - spin)


def _lerp_diverging(a: np.ndarray, b: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Moreland's diverging interpolation in Msh space (ParaView's 'Diverging')."""
    out = []
    for fv in f:
        m1, m2 = _lab_to_msh(_rgb_to_lab(a)), _lab_to_msh(_rgb_to_lab(b))
        x = float(fv)
        if m1[1] > 0.05 and m2[1] > 0.05 and _angle_diff(m1[2], m2[2]) > math.pi / 3:
            mid = max(m1[0], m2[0], 88.0)
            if x < 0.5:
                m2, x = np.array([mid, 0.0, 0.0]), 2.0 * x
            else:
                m1, x = np.array([mid, 0.0, 0.0]), 2.0 * x - 1.0
        if m1[1] < 0.05 and m2[1] > 0.05:
            m1[2] = _adjust_hue(m2, m1[0])
        elif m2[1] < 0.05 and m1[1] > 0.05:
            m2[2] = _adjust_hue(m1, m2[0])
        out.append(_lab_to_rgb(_msh_to_lab((1 - x) * m1 + x * m2)))
    return np.array(out)


def _angle_diff(a: float, b: float) -> float:
    d = abs(a - b)
    return d if d <= math.pi else 2 * math.pi - d


def _lerp_hsv(a: np.ndarray, b: np.ndarray, f: np.ndarray, wrap: bool) -> np.ndarray:
    import colorsys

    ha, hb = colorsys.rgb_to_hsv(*a), colorsys.rgb_to_hsv(*b)
    h1, h2 = ha[0], hb[0]
    if wrap and abs(h2 - h1) > 0.5:
        h2 = h2 - 1.0 if h2 > h1 else h2 + 1.0
    out = []
    for fv in f:
        h = ((1 - fv) * h1 + fv * h2) % 1.0
        s = (1 - fv) * ha[1] + fv * hb[1]
        v = (1 - fv) * ha[2] + fv * hb[2]
        out.append(colorsys.hsv_to_rgb(h, s, v))
    return np.array(out)


# --------------------------------------------------------------------------
# command-line helpers
# --------------------------------------------------------------------------


def add_transfer_function_argument(parser: Any, *, foreign: bool = False) -> None:
    """Add ``--tf PRESET|FILE`` (default: chosen per volume) to ``parser`` (or a group).

    ``foreign``: ``evaluate``'s, which only a model fitted from another tool's database
    takes (an eigencast model's recorded transfer function always wins)."""
    what = (f"a preset ({', '.join(PRESETS)}) or a ParaView/VolView preset .json "
            "(FILE.json#NAME picks one of several)")
    parser.add_argument(
        "--tf",
        metavar="PRESET|FILE",
        default=None,
        help=(f"the transfer function its images were rendered with: {what}; required for "
              "it" if foreign else
              f"transfer function: {what}; default: chosen from the volume's modality"),
    )


def transfer_function_from_args(args: argparse.Namespace, volume: Volume) -> TransferFunction:
    """The ``--tf`` choice from ``args``, or `default_transfer_function` of ``volume``."""
    spec = getattr(args, "tf", None)
    if spec is None:
        return default_transfer_function(volume)
    return load_transfer_function(spec)
