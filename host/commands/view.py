"""``eigencast view``: synthesise one novel view from an eigenspace image."""

from __future__ import annotations

import argparse
from pathlib import Path

from host.errors import EigencastError
from host.fit.model import HostModel
from host.render.cinema import atomic_write_bytes, encode_png

HELP = "synthesise a novel view from MODEL.ecs (exactly what a device shows) to a PNG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="MODEL.ecs")
    parser.add_argument("--phi", type=float, required=True, metavar="DEG", help="azimuth")
    parser.add_argument("--theta", type=float, required=True, metavar="DEG",
                        help="elevation, -90..90")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.png")
    parser.add_argument("--key", metavar="KEYFILE", help="verify the image's tag with this key")


def run(args: argparse.Namespace) -> int:
    from protocol.keys import load_key

    if not -90.0 <= args.theta <= 90.0:
        raise EigencastError(f"--theta {args.theta}: elevation must be within [-90, 90]")
    out = Path(args.output)
    if not out.parent.exists():
        raise EigencastError(f"{out.parent}: output folder does not exist")
    model = HostModel.load(args.model, key=load_key(args.key) if args.key else None)
    atomic_write_bytes(out, encode_png(model.view(args.phi % 360.0, args.theta)))
    h, w = model.image.image_shape
    print(f"wrote {out} ({w}x{h}, phi={args.phi:g}, theta={args.theta:g})")
    return 0
