"""Stage 2, render: ray-cast a volume from many views into a Cinema database (DB.cdb).

Owns the camera and view sets (``camera.py``), transfer functions and their presets
(``transfer.py``), the numba ray-caster (``raycast.py``; its depth kernel for
``Renderer.render_with_depth`` in ``raycast_depth.py``) and its slow numpy reference
(``raycast_reference.py``, for tests), its lighting looks (``lighting.py``: the headlight
and a light fixed in the world, `LIGHTINGS`) with their Monte Carlo reference
(``lighting_reference.py``), the recorded render settings that let any later
stage re-render a view exactly as the database was rendered (``settings.py``:
`RenderSettings`, `ViewRenderer`, `OBJECT_ALPHA_MIN`) and the Cinema database itself
(``cinema.py``: `CinemaWriter`, `CinemaDB`).

May import: `host.volume`, `host.errors`, `host.progress`; never fit, evaluate or link.
``eigencast render`` and ``render-view`` start here (``host/commands/render.py``,
``render_view.py``).
"""

from host.lazy import attach

__all__ = [
    "DEFAULT_LIGHTING",
    "DEFAULT_SAMPLES",
    "LIGHTINGS",
    "MAX_IMAGE_SIDE",
    "MAX_SAMPLES",
    "MAX_VIEWS",
    "OBJECT_ALPHA_MIN",
    "PRESETS",
    "PROJECTIONS",
    "RENDERER_VERSION",
    "SIDECAR",
    "VIEW_SET_FORMS",
    "Camera",
    "CinemaDB",
    "CinemaWriter",
    "Lighting",
    "RenderSettings",
    "Renderer",
    "SettingsError",
    "TransferFunction",
    "View",
    "ViewRenderer",
    "ViewSet",
    "absolute_source",
    "add_transfer_function_argument",
    "atomic_write_bytes",
    "default_transfer_function",
    "describe_transfer_function",
    "encode_png",
    "format_float",
    "hu_calibration",
    "light_field",
    "lighting_from_record",
    "load_transfer_function",
    "orbit_camera",
    "parse_view_set",
    "ray_box_segments",
    "render_lighting_reference",
    "render_reference",
    "resolve_lighting",
    "resolve_window",
    "samples_in_box",
    "transfer_function_from_args",
    "transmittance_reference",
    "warmup",
]

__getattr__, __dir__ = attach(__name__, __all__)
