"""``eigencast render``: ray-cast a view set into a Cinema Spec D database."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from host import __version__
from host.commands._render_options import (
    add_render_arguments,
    camera_settings,
    parse_size,
    render_setup,
    say_transfer_function,
)
from host.errors import CinemaError
from host.progress import progress
from host.render.camera import orbit_camera, parse_view_set
from host.render.cinema import (
    DEPTH_DIR,
    DEPTH_JSON,
    IMAGE_DIR,
    CinemaWriter,
    absolute_source,
    depth_problem,
    encode_depth,
    encode_png,
)
from host.render.transfer import add_transfer_function_argument
from host.volume import add_volume_arguments

HELP = "ray-cast a volume from many views into a Cinema database (DB.cdb)"

CSV_EVERY_S = 5.0
#: What depth costs, as ``render --help`` says it (BENCHMARKS.md, "Depth by default").
DEPTH_COST = "5-20 %% more render time and 20-35 %% more disk"


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
    depth = parser.add_mutually_exclusive_group()
    depth.add_argument("--no-depth", dest="depth", action="store_false", default=None,
                       help="do not store each view's depth (depth/*.npz at half resolution; "
                            f"storing it costs {DEPTH_COST}): a device then blends neighbouring "
                            "views (edges show twice) where it would warp them by their depth")
    depth.add_argument("--depth", dest="depth", action="store_true",
                       help="store depth and refuse a setting it cannot work with (the default "
                            "stores it where it can: perspective, black background, even "
                            "sizes, and says so where it cannot)")
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
        "views": {"spec": view_set.spec, "kind": view_set.kind, "count": len(view_set),
                  "grid_shape": list(view_set.grid_shape) if view_set.grid_shape else None},
        "image": {"width": size[0], "height": size[1]},
    }


def _render_in_process(renderer, cameras, pending, width, height,  # noqa: ANN001
                       depth_offset):  # noqa: ANN001
    """Yield ``(index, png, depth npz or None)`` per pending view, ray-cast here; with a
    depth offset one ray-cast makes both (`Renderer.render_with_depth`, the same colour
    bits)."""
    for i in pending:
        if depth_offset is None:
            yield i, encode_png(renderer.render_rgb8(cameras[i], width, height)), None
        else:
            rgba, depth = renderer.render_with_depth(cameras[i], width, height)
            yield i, encode_png(renderer.composite(rgba)), encode_depth(depth, depth_offset)


def _depth_offset(args: argparse.Namespace, settings: dict, size: tuple[int, int]
                  ) -> float | None:
    """The depth maps' offset (the camera distance), or None for no depth: ``--no-depth``,
    or by default where the framing cannot carry it (one line says so) or the database was
    begun without depth (resuming keeps it so; ``--depth`` renders depth for every view)."""
    if args.depth is False:
        return None
    problem = depth_problem(settings, (size[1], size[0]))
    if problem is not None:
        if args.depth:
            raise CinemaError(f"--depth: not with {problem}")
        print(f"no depth maps: {problem}; a device will blend neighbouring views instead of "
              "warping them", file=sys.stderr)
        return None
    out = Path(args.output)
    begun = (out / IMAGE_DIR).is_dir() and any((out / IMAGE_DIR).glob("*.png"))
    no_depth = not (out / DEPTH_DIR / DEPTH_JSON).is_file()
    if args.depth is None and begun and no_depth and not args.overwrite:
        print(f"{out}: rendered without depth so far, so the rest is too (--depth adds depth "
              "to every view, rendering them again)", file=sys.stderr)
        return None
    camera = settings["camera"]
    return camera["radius_mm"] / math.sin(math.radians(camera["fov_deg"]) / 2.0)


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
    depth_offset = _depth_offset(args, settings, (width, height))
    writer = CinemaWriter(args.output, settings, rows, (height, width), overwrite=args.overwrite,
                          depth_offset_mm=depth_offset)
    pending = writer.pending
    kept = len(rows) - len(pending)
    if kept:
        print(f"resuming {args.output}: {kept} valid images kept, {len(pending)} to render",
              file=sys.stderr)
    from host.cluster import open_cluster, render_pngs

    cluster = open_cluster(args.scheduler)  # None: in-process threads
    say_transfer_function(args, volume, tf)
    if cluster is None:
        views = _render_in_process(renderer, cameras, pending, width, height, depth_offset)
    else:
        views = render_pngs(cluster, args, (volume, tf, renderer), cameras, pending, width,
                            height, depth_offset=depth_offset)
    last_csv = time.monotonic()
    try:
        with progress(f"render {width}x{height}", len(pending), unit=" views") as bar:
            for index, png, depth in views:
                if depth is not None:  # before its PNG: a view is done when both are
                    writer.write_depth(index, depth)
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
        views.close()
        if cluster is not None:
            cluster.close()
    writer.write_csv()
    print(f"wrote {args.output}: {len(rows)} views at {width}x{height} "
          f"({len(pending)} rendered, {kept} reused)"
          f"{', with depth' if depth_offset is not None else ', no depth'}")
    return 0
