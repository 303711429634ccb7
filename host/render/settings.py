"""Rebuild a ray-caster and its cameras from recorded render settings.

A database rendered by ``eigencast render`` carries a JSON sidecar
(`host.render.cinema.SIDECAR`) that ``fit`` copies into the eigenspace image's
provenance (``provenance["render"]``). It records everything that determines
the images: the volume (source, dims, spacing), the transfer function and its
resolved intensity window, the orbit framing (projection, field of view,
centre and radius), the renderer settings and the image size. `RenderSettings`
reads that record back and `ViewRenderer` ray-casts any ``(phi, theta)`` with
exactly the training cameras, so novel views (``evaluate``), held-out views
(``fit --target``) and later ``serve``/``demo`` compare like with like.

The ray-caster is deterministic, so a view rendered here is bit-identical to
the same view in the training database.

Examples
--------
>>> settings = RenderSettings.from_record(model.render_settings, what="MODEL.ecs")  # doctest: +SKIP
>>> scene = ViewRenderer.open(settings)  # loads the recorded volume  # doctest: +SKIP
>>> rgb8, alpha = scene.render(30.0, 12.0)  # doctest: +SKIP
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.errors import EigencastError
from host.render.camera import Camera, View, orbit_camera
from host.volume import Volume

__all__ = [
    "OBJECT_ALPHA_MIN",
    "RenderSettings",
    "SettingsError",
    "ViewRenderer",
]

#: A pixel belongs to the object when the ray-cast's alpha reaches this
#: (half an 8-bit step: below it the pixel is the background after rounding).
OBJECT_ALPHA_MIN = 0.5 / 255.0

#: Relative tolerance when comparing a volume's spacing with the recorded one.
SPACING_RTOL = 1e-5

_REQUIRED = ("volume", "transfer_function", "window", "camera", "renderer", "image")


class SettingsError(EigencastError):
    """Render settings are missing, malformed or do not match the volume given."""


@dataclass(frozen=True)
class RenderSettings:
    """The render settings of a database (its sidecar) in typed form.

    Parameters
    ----------
    record : dict
        The sidecar as written by ``eigencast render`` (kept verbatim).
    volume_source : str
        Path or ``builtin:NAME`` the database was rendered from.
    volume_dims : (int, int, int)
        Grid size ``(nx, ny, nz)`` of the volume as loaded (after reorientation).
    volume_spacing : (float, float, float)
        Voxel size in mm, same axis order.
    transfer_function : dict
        `host.render.transfer.TransferFunction.to_dict` of the transfer function.
    window : (float, float)
        The intensity window actually used, in the volume's data units.
    projection : {"perspective", "orthographic"}
    fov_deg : float
    center_mm : (float, float, float)
        Orbit centre in world mm.
    radius_mm : float
        Orbit bounding-sphere radius in mm.
    samples : int or None
        Samples across the bounding-sphere diameter (None when ``step_voxels`` rules).
    step_voxels : float
        Ray step in units of the smallest voxel spacing.
    shading : bool
    background : (float, float, float)
    opacity_correction : bool
    early_termination : bool
    renderer_version : str
    width, height : int
        Image size in pixels.
    lighting : host.render.lighting.Lighting
        The recorded lighting look (``renderer["lighting"]``); a record without one (a
        database rendered before lighting was recorded) reads as the headlight.
    """

    record: dict
    volume_source: str
    volume_dims: tuple[int, int, int]
    volume_spacing: tuple[float, float, float]
    transfer_function: dict
    window: tuple[float, float]
    projection: str
    fov_deg: float
    center_mm: tuple[float, float, float]
    radius_mm: float
    samples: int | None
    step_voxels: float
    shading: bool
    background: tuple[float, float, float]
    opacity_correction: bool
    early_termination: bool
    renderer_version: str
    width: int
    height: int
    lighting: Any = None

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_record(cls, record: Mapping | None, *, what: str) -> RenderSettings:
        """Parse a sidecar / ``provenance["render"]`` record.

        Parameters
        ----------
        record : mapping or None
            The recorded settings; None or ``{}`` for databases from other tools.
        what : str
            Names the source in error messages (a path).

        Raises
        ------
        SettingsError
            No record (a foreign database), or a key missing / malformed.
        """
        from host.render.lighting import lighting_from_record  # (loads numba: only here)

        if not record:
            raise SettingsError(
                f"{what}: no render settings recorded (a database from another tool); "
                "give the render options explicitly (--tf, --size ...)"
            )
        if not isinstance(record, Mapping):
            raise SettingsError(f"{what}: render settings must be a mapping, got "
                                f"{type(record).__name__}")
        missing = [k for k in _REQUIRED if k not in record]
        if missing:
            raise SettingsError(
                f"{what}: render settings lack {', '.join(missing)} (found "
                f"{', '.join(sorted(record))})"
            )
        try:
            vol = record["volume"]
            cam = record["camera"]
            ren = record["renderer"]
            img = record["image"]
            window = tuple(float(v) for v in record["window"])
            settings = cls(
                record=dict(record),
                volume_source=str(vol["source"]),
                volume_dims=tuple(int(v) for v in vol["dims"]),  # type: ignore[arg-type]
                volume_spacing=tuple(float(v) for v in vol["spacing"]),  # type: ignore[arg-type]
                transfer_function=dict(record["transfer_function"]),
                window=window,  # type: ignore[arg-type]
                projection=str(cam.get("projection", "perspective")),
                fov_deg=float(cam.get("fov_deg", 30.0)),
                center_mm=tuple(float(v) for v in cam["center_mm"]),  # type: ignore[arg-type]
                radius_mm=float(cam["radius_mm"]),
                samples=None if ren.get("samples") is None else int(ren["samples"]),
                step_voxels=float(ren["step_voxels"]),
                shading=bool(ren.get("shading", True)),
                background=tuple(float(v) for v in ren.get("background", (0, 0, 0))),  # type: ignore[arg-type]
                opacity_correction=bool(ren.get("opacity_correction", True)),
                early_termination=ren.get("early_termination_alpha", 1.0) is not None,
                renderer_version=str(ren.get("renderer", "")),
                width=int(img["width"]),
                height=int(img["height"]),
                lighting=lighting_from_record(ren.get("lighting")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise SettingsError(f"{what}: malformed render settings: {exc!r}") from None
        settings._check(what)
        return settings

    def _check(self, what: str) -> None:
        problems = []
        if len(self.volume_dims) != 3 or min(self.volume_dims) < 2:
            problems.append(f"volume dims {self.volume_dims}")
        if len(self.volume_spacing) != 3 or not all(
            math.isfinite(s) and s > 0 for s in self.volume_spacing
        ):
            problems.append(f"volume spacing {self.volume_spacing}")
        if len(self.window) != 2 or not self.window[0] < self.window[1]:
            problems.append(f"window {self.window}")
        if len(self.center_mm) != 3 or not (math.isfinite(self.radius_mm) and self.radius_mm > 0):
            problems.append(f"camera centre/radius {self.center_mm}/{self.radius_mm}")
        if not (self.step_voxels > 0 and math.isfinite(self.step_voxels)):
            problems.append(f"step_voxels {self.step_voxels}")
        if not (1 <= self.width <= 8192 and 1 <= self.height <= 8192):
            problems.append(f"image size {self.width}x{self.height}")
        if self.lighting.world_lit and not self.shading:
            problems.append(f"lighting {self.lighting.name!r} without shading")
        if problems:
            raise SettingsError(f"{what}: malformed render settings: {'; '.join(problems)}")

    # ------------------------------------------------------------------ volume

    def check_volume(self, volume: Volume, *, what: str) -> None:
        """Refuse a volume whose grid or spacing differ from the recorded ones.

        Raises
        ------
        SettingsError
            One line with both sides of the mismatch.
        """
        if tuple(volume.dims) != tuple(self.volume_dims):
            raise SettingsError(
                f"{volume.source or volume.name}: dims {'x'.join(map(str, volume.dims))} differ "
                f"from the {'x'.join(map(str, self.volume_dims))} that {what} was rendered from "
                f"({self.volume_source})"
            )
        if not np.allclose(volume.spacing, self.volume_spacing, rtol=SPACING_RTOL, atol=0.0):
            raise SettingsError(
                f"{volume.source or volume.name}: spacing "
                f"{', '.join(f'{s:g}' for s in volume.spacing)} mm differs from the "
                f"{', '.join(f'{s:g}' for s in self.volume_spacing)} mm that {what} was "
                f"rendered from ({self.volume_source})"
            )

    def load_volume(
        self, spec: str | None = None, args: argparse.Namespace | None = None, *, what: str
    ) -> Volume:
        """Load ``spec`` (default: the recorded source) and check it matches.

        Parameters
        ----------
        spec : str, optional
            A volume path or ``builtin:NAME``; default the recorded ``volume.source``.
        args : argparse.Namespace, optional
            Volume options (``--dims``, ``--spacing`` ...) from `host.volume.add_volume_arguments`.
        what : str
            Names the model/database in error messages.
        """
        from host.volume import load_volume, volume_from_args

        source = spec or self.volume_source
        if args is not None:
            volume = volume_from_args(source, args)
        else:
            volume = load_volume(source)
        self.check_volume(volume, what=what)
        return volume

    # ------------------------------------------------------------------ rendering

    def transfer_function_object(self) -> Any:
        """The recorded transfer function with its window pinned to the recorded one."""
        from host.render.transfer import TransferFunction

        data = dict(self.transfer_function)
        data["window"] = list(self.window)
        data["window_units"] = "data"
        return TransferFunction.from_dict(data)

    def renderer(self, volume: Volume, *, workers: int | None = None) -> Any:
        """A `host.render.raycast.Renderer` with these settings for ``volume``."""
        from host.render.raycast import RENDERER_VERSION, Renderer

        if self.renderer_version and self.renderer_version != RENDERER_VERSION:
            raise SettingsError(
                f"render settings were recorded by renderer {self.renderer_version!r}; this is "
                f"{RENDERER_VERSION!r}, whose images may differ"
            )
        kwargs: dict[str, Any] = {}
        if self.samples is not None:
            kwargs["samples"] = self.samples
        else:
            kwargs["step"] = self.step_voxels
        return Renderer(
            volume,
            self.transfer_function_object(),
            shading=self.shading,
            background=self.background,
            workers=workers,
            opacity_correction=self.opacity_correction,
            early_termination=self.early_termination,
            lighting=self.lighting,
            **kwargs,
        )

    def camera(self, phi_deg: float, theta_deg: float) -> Camera:
        """The orbit camera of view ``(phi_deg, theta_deg)`` with the recorded framing."""
        return orbit_camera(
            View(float(phi_deg), float(theta_deg)),
            self.center_mm,
            self.radius_mm,
            projection=self.projection,
            fov_deg=self.fov_deg,
        )


class ViewRenderer:
    """Ray-cast views of one volume with recorded settings.

    Parameters
    ----------
    settings : RenderSettings
    volume : Volume
        Checked against ``settings`` (dims and spacing).
    workers : int, optional
        Render threads (default all cores).
    what : str
        Names the model/database in error messages.

    Attributes
    ----------
    settings : RenderSettings
    volume : Volume
    renderer : host.render.raycast.Renderer
    image_shape : (int, int)
        ``(height, width)``.
    """

    def __init__(
        self,
        settings: RenderSettings,
        volume: Volume,
        *,
        workers: int | None = None,
        what: str = "the model",
    ) -> None:
        settings.check_volume(volume, what=what)
        self.settings = settings
        self.volume = volume
        self.renderer = settings.renderer(volume, workers=workers)
        self.image_shape = (settings.height, settings.width)

    @classmethod
    def open(
        cls,
        settings: RenderSettings,
        volume_spec: str | None = None,
        volume_args: argparse.Namespace | None = None,
        *,
        workers: int | None = None,
        what: str = "the model",
    ) -> ViewRenderer:
        """Load the volume (``volume_spec`` or the recorded source) and build the renderer."""
        volume = settings.load_volume(volume_spec, volume_args, what=what)
        return cls(settings, volume, workers=workers, what=what)

    def render(self, phi_deg: float, theta_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """Ray-cast one view.

        Returns
        -------
        rgb8 : ndarray of shape (height, width, 3), uint8
            Composited over the background, exactly as ``eigencast render`` writes it.
        alpha : ndarray of shape (height, width), float32
            Accumulated opacity (``alpha >= OBJECT_ALPHA_MIN``: object pixels).
        """
        camera = self.settings.camera(phi_deg, theta_deg)
        rgba = self.renderer.render(camera, self.settings.width, self.settings.height)
        return self.renderer.composite(rgba), np.ascontiguousarray(rgba[..., 3])

    def render_with_depth(
        self, phi_deg: float, theta_deg: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ray-cast one view with its depths (`host.render.raycast.Renderer.render_with_depth`).

        Returns
        -------
        rgb8 : ndarray of shape (height, width, 3), uint8
            Bit-identical to `render`'s.
        alpha : ndarray of shape (height, width), float32
        depth : ndarray of shape (height, width, 2), float32
            Distances in mm along each pixel's ray from the camera
            (``self.settings.camera(phi_deg, theta_deg).rays``): channel 0 where the
            opacity crosses 0.5, channel 1 the opacity-weighted mean; NaN where none.
        """
        camera = self.settings.camera(phi_deg, theta_deg)
        rgba, depth = self.renderer.render_with_depth(
            camera, self.settings.width, self.settings.height
        )
        return self.renderer.composite(rgba), np.ascontiguousarray(rgba[..., 3]), depth

    def render_rgb8(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """Ray-cast one view: uint8 (height, width, 3)."""
        return self.render(phi_deg, theta_deg)[0]
