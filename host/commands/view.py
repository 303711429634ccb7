"""``eigencast view``: one novel view from an eigenspace image, as a device shows it.

The frame is made by the device's own code on the image's own data, bit for bit what
``eigencast-device --standalone`` shows at that view: for an image with depth (``fit`` stores
it by default) the neighbouring training views warped by their depth
(`host.evaluate.warp.WarpFrames`, `device_runtime.synthesis`); otherwise the blend of the
interpolated, quantized scores (`HostModel.view`). ``--blend`` asks for the blend of a depth
image (what a served device shows for an instant before its warp). A served device's other
frames depend on the host's ray-casts of the volume: ``eigencast evaluate`` scores those.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from host.errors import EigencastError
from host.fit.model import HostModel
from host.render.cinema import atomic_write_bytes, encode_png

HELP = ("synthesise a novel view from MODEL.ecs to a PNG: what a device with no host shows, "
        "bit for bit (the depth warp for an image with depth, else the score blend)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="MODEL.ecs")
    parser.add_argument("--phi", type=float, required=True, metavar="DEG", help="azimuth")
    parser.add_argument("--theta", type=float, required=True, metavar="DEG",
                        help="elevation, -90..90")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.png")
    parser.add_argument("--key", metavar="KEYFILE", help="verify the image's tag with this key")
    parser.add_argument("--look", metavar="NAME",
                        help="the look to show of an image with several (a name or an index; "
                             "default the first)")
    parser.add_argument("--blend", action="store_true",
                        help="the blend of the interpolated scores even for an image with depth "
                             "(what a device shows without the warp)")


def run(args: argparse.Namespace) -> int:
    from device_runtime.orbit import canonical_view
    from protocol.keys import load_key

    if not -90.0 <= args.theta <= 90.0:
        raise EigencastError(f"--theta {args.theta}: elevation must be within [-90, 90]")
    out = Path(args.output)
    if not out.parent.exists():
        raise EigencastError(f"{out.parent}: output folder does not exist")
    model = HostModel.load(args.model, key=load_key(args.key) if args.key else None,
                           look=args.look)
    phi, theta = canonical_view(args.phi, args.theta)  # the view as a device takes it
    warp = model.image.synthesis is not None and not args.blend
    if warp:
        from host.evaluate.warp import WarpFrames

        frame = WarpFrames(model).frame(phi, theta)
    else:
        frame = model.view(phi, theta)
    atomic_write_bytes(out, encode_png(frame))
    h, w = model.image.image_shape
    print(f"wrote {out} ({w}x{h}, phi={args.phi:g}, theta={args.theta:g}; "
          f"{'depth warp of the neighbouring views' if warp else 'blend of the scores'}"
          f"{f'; look {model.look}' if model.look else ''})")
    return 0
