"""Build the scene a command ray-casts from its parsed render options.

The volume, its transfer function, the `host.render.raycast.Renderer` and the orbit
framing, from the options ``host.commands._render_options.add_render_arguments`` adds.
The commands (render, render-view, evaluate, demo) and the cluster's workers
(`host.cluster`, which rebuild the renderer from the client's options) both build it here,
below both of them.
"""

from __future__ import annotations

import argparse
from typing import Any

from host.errors import EigencastError

__all__ = ["camera_settings", "render_setup", "renderer_from_args"]


def _parse_background(text: str) -> tuple[float, float, float]:
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise EigencastError(f"--background {text!r}: expected R,G,B with values in [0,1]")
    return rgb  # type: ignore[return-value]


def renderer_from_args(args: argparse.Namespace, volume: Any, tf: Any) -> Any:
    """Build a `host.render.raycast.Renderer` from parsed options."""
    from host.render.raycast import Renderer

    if args.samples is not None and args.samples < 2:
        raise EigencastError(f"--samples {args.samples}: must be at least 2")
    if args.step is not None and not args.step > 0:
        raise EigencastError(f"--step {args.step}: must be positive")
    if args.workers is not None and args.workers < 1:
        raise EigencastError(f"--workers {args.workers}: must be at least 1")
    if not 1.0 <= args.fov <= 150.0:
        raise EigencastError(f"--fov {args.fov}: must be within [1, 150] degrees")
    samples = args.samples if (args.samples is not None or args.step is not None) else 1000
    lighting = getattr(args, "lighting", None) or "headlight"
    if args.no_shading and lighting != "headlight":
        raise EigencastError(f"--no-shading: not with --lighting {lighting}, which shades by "
                             "the gradient")
    return Renderer(
        volume,
        tf,
        samples=samples if args.step is None else None,
        step=args.step,
        shading=not args.no_shading,
        background=_parse_background(args.background),
        workers=args.workers,
        lighting=lighting,
    )


def render_setup(args: argparse.Namespace) -> tuple[Any, Any, Any]:
    """Load the volume and transfer function and build the renderer: (volume, tf, renderer).
    ``host.commands._render_options.say_transfer_function`` says which transfer function
    that chose, once the command is sure to render."""
    from host.render.transfer import transfer_function_from_args
    from host.volume import volume_from_args

    volume = volume_from_args(args.volume, args)
    tf = transfer_function_from_args(args, volume)
    renderer = renderer_from_args(args, volume, tf)
    return volume, tf, renderer


def camera_settings(args: argparse.Namespace, volume: Any, renderer: Any) -> dict:
    """Orbit framing for the chosen --frame: projection, fov, centre and radius (JSON-able).

    Recorded in the database sidecar (and from there in the eigenspace image)
    so novel views are ray-cast with exactly the training cameras' framing.
    """
    if args.frame == "visible":
        center, radius = renderer.visible_sphere()
    else:
        center, radius = volume.center_mm, volume.radius_mm
    return {
        "projection": args.projection,
        "fov_deg": float(args.fov),
        "frame": args.frame,
        "center_mm": [float(c) for c in center],
        "radius_mm": float(radius),
    }
