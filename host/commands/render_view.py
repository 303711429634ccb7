"""``eigencast render-view``: ray-cast one view to a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from host.commands._render_options import (
    add_render_arguments,
    camera_settings,
    parse_size,
    render_setup,
    say_transfer_function,
)
from host.errors import EigencastError
from host.render.camera import View, orbit_camera
from host.render.cinema import atomic_write_bytes, encode_png
from host.render.transfer import add_transfer_function_argument
from host.volume import add_volume_arguments

HELP = "ray-cast one view of a volume to a PNG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("volume", metavar="VOLUME", help="a volume file or folder, or builtin:NAME")
    parser.add_argument("--phi", type=float, default=0.0, metavar="DEG",
                        help="azimuth in degrees (default 0)")
    parser.add_argument("--theta", type=float, default=0.0, metavar="DEG",
                        help="elevation in degrees, -90..90 (default 0)")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.png")
    add_volume_arguments(parser)
    add_transfer_function_argument(parser)
    add_render_arguments(parser)


def run(args: argparse.Namespace) -> int:
    if not -90.0 <= args.theta <= 90.0:
        raise EigencastError(f"--theta {args.theta}: elevation must be within [-90, 90]")
    width, height = parse_size(args.size)
    volume, tf, renderer = render_setup(args)
    out = Path(args.output)
    if not out.parent.exists():
        raise EigencastError(f"{out.parent}: output folder does not exist")
    say_transfer_function(args, volume, tf)
    framing = camera_settings(args, volume, renderer)
    camera = orbit_camera(View(args.phi % 360.0, args.theta), framing["center_mm"],
                          framing["radius_mm"], projection=args.projection, fov_deg=args.fov)
    image = renderer.render_rgb8(camera, width, height)
    atomic_write_bytes(out, encode_png(image))
    print(f"wrote {out} ({width}x{height}, phi={args.phi:g}, theta={args.theta:g})")
    return 0
