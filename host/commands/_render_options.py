"""Options shared by the commands that ray-cast (render, render-view, evaluate, demo)."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from host.errors import EigencastError
from host.render.scene import camera_settings, render_setup, renderer_from_args

if TYPE_CHECKING:
    from host.volume import Volume

__all__ = [
    "LIGHTING_NAMES",
    "add_render_arguments",
    "camera_settings",
    "parse_size",
    "render_setup",
    "renderer_from_args",
    "settings_from_args",
]


def parse_size(text: str) -> tuple[int, int]:
    """``"300"`` -> (300, 300); ``"640x480"`` -> width 640, height 480: returns (width, height)."""
    try:
        parts = [int(p) for p in text.lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2 or not all(8 <= p <= 8192 for p in parts):
        raise EigencastError(f"--size {text!r}: expected N or WxH with 8 <= N <= 8192")
    return parts[0], parts[1]


#: ``--lighting`` choices: the names of `host.render.lighting.LIGHTINGS` (kept here as
#: text so ``--help`` does not load numba; a test checks they agree).
LIGHTING_NAMES = ("headlight", "cinematic")

#: ``evaluate``'s heading of these options: they describe only a foreign model's images.
FOREIGN_RENDERING = (
    "An eigencast model records how its images were ray-cast (volume, transfer function, "
    "size, camera, samples, lighting) and evaluate always ray-casts novel views that way: giving "
    "--tf or any option below but --workers is then an error. Only a model fitted from "
    "another tool's Cinema database records nothing; for it give VOLUME, --tf, and these "
    "where its images were made otherwise.")


def add_render_arguments(parser: argparse.ArgumentParser, *, size_default: str = "300",
                         foreign: bool = False) -> None:
    """Add --size, --samples/--step, --projection, --fov, --background, --workers,
    --no-shading, --lighting.

    ``foreign``: for ``evaluate``, where they describe only a model fitted from another
    tool's database (`FOREIGN_RENDERING`); --size then defaults to the model's size."""
    if foreign:
        g = parser.add_argument_group("rendering a model from another tool's database",
                                      FOREIGN_RENDERING)
        g.add_argument("--size", default=None, metavar="N|WxH",
                       help="its images' size (default and only value: the model's)")
    else:
        g = parser.add_argument_group("rendering")
        g.add_argument("--size", default=size_default, metavar="N|WxH",
                       help=f"image size in pixels (default {size_default})")
    step = g.add_mutually_exclusive_group()
    step.add_argument("--samples", type=int, metavar="N",
                      help="samples per ray across the volume's bounding sphere "
                           "(the paper uses 1000; default)")
    step.add_argument("--step", type=float, metavar="S",
                      help="ray step in units of the smallest voxel spacing")
    g.add_argument("--projection", choices=("perspective", "orthographic"),
                   default="perspective", help="camera projection (default perspective)")
    g.add_argument("--fov", type=float, default=30.0, metavar="DEG",
                   help="vertical field of view for perspective (default 30)")
    g.add_argument("--background", default="0,0,0", metavar="R,G,B",
                   help="background colour, components in [0,1] (default black)")
    g.add_argument("--no-shading", action="store_true", help="disable gradient shading")
    g.add_argument("--lighting", choices=LIGHTING_NAMES, default=None, metavar="NAME",
                   help="headlight (default: Blinn-Phong, the light at the camera) or "
                        "cinematic (a light fixed above the object, with soft shadows, "
                        "ambient occlusion and scattering; docs/lighting.md)")
    g.add_argument("--workers", type=int, metavar="N",
                   help="render threads (default: all cores)"
                        + ("; applies to every model" if foreign else ""))
    g.add_argument("--frame", choices=("visible", "volume"), default="visible",
                   help="orbit around the bounding sphere of what the transfer function "
                        "shows (default) or of the whole volume box")


def say_transfer_function(args: argparse.Namespace, volume, tf) -> None:  # noqa: ANN001
    """Print on stderr, in one line, which transfer function was chosen for which modality
    and why (`describe_transfer_function`): after every check of the command's options, so
    an error stays one line."""
    from host.render.transfer import describe_transfer_function

    print(describe_transfer_function(volume, tf, getattr(args, "tf", None)), file=sys.stderr)


def settings_from_args(args: argparse.Namespace, volume: Volume, size: tuple[int, int]) -> dict:
    """A render-settings record built from command-line render options (foreign databases).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed `add_render_arguments` and ``--tf`` options.
    volume : Volume
    size : (int, int)
        ``(width, height)`` in pixels.

    Returns
    -------
    dict
        The same record ``eigencast render`` writes as its sidecar (view set omitted).
    """
    from host.commands.render import database_settings
    from host.render.camera import ViewSet
    from host.render.transfer import transfer_function_from_args

    tf = transfer_function_from_args(args, volume)
    renderer = renderer_from_args(args, volume, tf)
    framing = camera_settings(args, volume, renderer)
    empty = ViewSet(spec="none", kind="list", views=())
    return database_settings(volume, tf, renderer, empty, size, framing)
