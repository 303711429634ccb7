"""``eigencast render``: ray-cast a view set into a Cinema Spec D database."""

from __future__ import annotations

import argparse
import math
import sys
import time

from host import __version__
from host.commands._render_options import (
    add_render_arguments,
    camera_settings,
    parse_size,
    render_setup,
)
from host.errors import CinemaError
from host.progress import progress
from host.render.camera import orbit_camera, parse_view_set
from host.render.cinema import CinemaWriter, absolute_source, encode_depth, encode_png
from host.render.transfer import add_transfer_function_argument
from host.volume import add_volume_arguments

HELP = "ray-cast a volume from many views into a Cinema database (DB.cdb)"

CSV_EVERY_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("volume", metavar="VOLUME", help="a volume file or folder, or builtin:NAME")
    parser.add_argument("-o", "--output", required=True, metavar="DB.cdb",
                        help="database folder to create (or resume)")
    parser.add_argument("--views", default="grid:100x15", metavar="SPEC",
                        help="grid:NPHIxNTHETA, fibonacci:N, random:N[:SEED], list:P,T;P,T "
                             "or a CSV of phi,theta (default grid:100x15, the paper's)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a database rendered with different settings")
    add_volume_arguments(parser)
    add_transfer_function_argument(parser)
    add_render_arguments(parser)
    parser.add_argument("--depth", action="store_true",
                        help="also store each view's half-opacity depth at half resolution "
                             "(depth/*.npz, for fit --depth; perspective, even sizes, "
                             "in-process only)")
    from host.cluster import add_scheduler_argument

    add_scheduler_argument(parser)


def database_settings(volume, tf, renderer, view_set, size, camera_opts) -> dict:  # noqa: ANN001
    """The JSON sidecar: everything needed to reproduce (or extend) the database."""
    return {
        "eigencast": __version__,
        "volume": {
            "source": absolute_source(volume.source),
            "name": volume.name,
            "modality": volume.modality,
            "dims": list(volume.dims),
            "spacing": list(volume.spacing),
            "load": volume.metadata.get("load", {}),
        },
        "transfer_function": tf.to_dict(),
        "window": list(tf.resolve_window(volume)),
        "camera": camera_opts,
        "renderer": renderer.settings(),
        "views": {"spec": view_set.spec, "kind": view_set.kind,
                  "grid_shape": list(view_set.grid_shape) if view_set.grid_shape else None},
        "image": {"width": size[0], "height": size[1]},
    }


def _render_with_depth(renderer, cameras, pending, width, height, writer, offset):  # noqa: ANN001
    """Yield ``(index, png)`` like the colour path, each view's depth map written first
    (one ray-cast per view: `Renderer.render_with_depth`, the same colour bits)."""
    for i in pending:
        rgba, depth = renderer.render_with_depth(cameras[i], width, height)
        writer.write_depth(i, encode_depth(depth, offset))
        yield i, encode_png(renderer.composite(rgba))


def run(args: argparse.Namespace) -> int:
    width, height = parse_size(args.size)
    view_set = parse_view_set(args.views)
    volume, tf, renderer = render_setup(args)
    camera_opts = camera_settings(args, volume, renderer)
    cameras = [
        orbit_camera(v, camera_opts["center_mm"], camera_opts["radius_mm"],
                     projection=args.projection, fov_deg=args.fov)
        for v in view_set.views
    ]
    rows = [(v.phi_deg, v.theta_deg, c.to_dict()) for v, c in zip(view_set.views, cameras)]
    settings = database_settings(volume, tf, renderer, view_set, (width, height), camera_opts)
    depth_offset = None
    if getattr(args, "depth", False):
        if args.scheduler:
            raise CinemaError("--depth is in-process only (drop --scheduler)")
        if args.projection != "perspective":
            raise CinemaError("--depth needs --projection perspective (the warp's camera model)")
        if width % 2 or height % 2:
            raise CinemaError(f"--depth needs an even image size, got {width}x{height}")
        depth_offset = camera_opts["radius_mm"] / math.sin(math.radians(args.fov) / 2.0)
    writer = CinemaWriter(args.output, settings, rows, (height, width), overwrite=args.overwrite,
                          depth_offset_mm=depth_offset)
    pending = writer.pending
    kept = len(rows) - len(pending)
    if kept:
        print(f"resuming {args.output}: {kept} valid images kept, {len(pending)} to render",
              file=sys.stderr)
    from host.cluster import open_cluster, render_pngs

    cluster = open_cluster(args.scheduler)  # None: in-process threads
    if cluster is None and depth_offset is not None:
        pngs = _render_with_depth(renderer, cameras, pending, width, height, writer,
                                  depth_offset)
    elif cluster is None:
        pngs = ((i, encode_png(renderer.render_rgb8(cameras[i], width, height)))
                for i in pending)
    else:
        pngs = render_pngs(cluster, args, (volume, tf, renderer), cameras, pending, width,
                           height)
    last_csv = time.monotonic()
    try:
        with progress(f"render {width}x{height}", len(pending), unit=" views") as bar:
            for index, png in pngs:
                writer.write_png(index, png)
                bar.advance()
                if time.monotonic() - last_csv > CSV_EVERY_S:
                    writer.write_csv()
                    last_csv = time.monotonic()
    except KeyboardInterrupt:
        writer.write_csv()
        print(f"interrupted: {sum(writer.done)}/{len(rows)} images kept; rerun the same "
              "command to resume", file=sys.stderr)
        return 130
    finally:
        pngs.close()
        if cluster is not None:
            cluster.close()
    writer.write_csv()
    print(f"wrote {args.output}: {len(rows)} views at {width}x{height} "
          f"({len(pending)} rendered, {kept} reused)")
    return 0
