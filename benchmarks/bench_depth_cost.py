"""What depth by default costs: render time and disk per view, fit time and device image.

Usage::

    .venv/bin/python benchmarks/bench_depth_cost.py [--quick] [--views N] [--size N]
                                                    [--db DB.cdb ...]

``eigencast render`` stores each view's depth and ``fit`` a depth eigenspace and the standalone
table unless ``--no-depth`` / ``--no-standalone``; their ``--help`` quotes these figures.

1. **render**: per volume (the built-in tooth and head, and the shared tooth and VisMale head
   when ``../shared/data`` exists), N views of the paper's grid at the given size, each
   ray-cast colour-only (``render --no-depth``: `Renderer.render_rgb8`, PNG) and with depth
   (`Renderer.render_with_depth`, PNG + `encode_depth` npz), interleaved view by view so load
   drifts hit both alike: the time ratio and the bytes per view of each file.
2. **fit** (``--db``, e.g. the shared 1500-view databases rendered with depth): the colour fit
   (`fit_database` + `build_image`, ``fit``'s defaults: adaptive, cells 30, T 0.98) against
   the standalone table (`add_standalone_table`) and the depth eigenspace (`add_depth`), times
   in the same process, and each one's share of the device image (compressed sections).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _render_section(volumes: list[str], n_views: int, size: int, samples: int) -> list[dict]:
    from host.commands._render_options import camera_settings, render_setup
    from host.commands.render import add_arguments
    from host.render.camera import orbit_camera, parse_view_set
    from host.render.cinema import encode_depth, encode_png

    grid = parse_view_set("grid:100x15").views
    pick = [grid[int(i)] for i in np.linspace(0, len(grid) - 1, n_views)]
    out = []
    for volume in volumes:
        parser = argparse.ArgumentParser()
        add_arguments(parser)
        args = parser.parse_args([volume, "-o", "unused.cdb", "--size", str(size),
                                  "--samples", str(samples)])
        vol, _tf, renderer = render_setup(args)
        cam = camera_settings(args, vol, renderer)
        offset = cam["radius_mm"] / math.sin(math.radians(args.fov) / 2.0)
        cams = [orbit_camera(v, cam["center_mm"], cam["radius_mm"]) for v in pick]
        renderer.render_with_depth(cams[0], 32, 32)  # compile both kernels
        renderer.render_rgb8(cams[0], 32, 32)
        plain_s = depth_s = 0.0
        png_bytes = npz_bytes = 0
        for c in cams:
            t0 = time.perf_counter()
            encode_png(renderer.render_rgb8(c, size, size))
            t1 = time.perf_counter()
            rgba, depth = renderer.render_with_depth(c, size, size)
            png = encode_png(renderer.composite(rgba))
            npz = encode_depth(depth, offset)
            t2 = time.perf_counter()
            plain_s += t1 - t0
            depth_s += t2 - t1
            png_bytes += len(png)
            npz_bytes += len(npz)
        row = {"volume": volume, "views": n_views, "size": size, "samples": samples,
               "plain_s_per_view": plain_s / n_views, "depth_s_per_view": depth_s / n_views,
               "time_ratio": depth_s / plain_s, "png_bytes": png_bytes / n_views,
               "npz_bytes": npz_bytes / n_views, "disk_ratio": (png_bytes + npz_bytes)
               / png_bytes}
        print(f"render {volume} {size}x{size}, {n_views} views: {row['plain_s_per_view']:.3f} "
              f"s/view colour, {row['depth_s_per_view']:.3f} s/view with depth = "
              f"{row['time_ratio']:.2f}x; PNG {row['png_bytes'] / 1e3:.1f} kB + depth "
              f"{row['npz_bytes'] / 1e3:.1f} kB = {row['disk_ratio']:.2f}x the disk", flush=True)
        out.append(row)
    return out


def _fit_section(databases: list[str]) -> list[dict]:
    from host.fit.depth import add_depth
    from host.fit.model import (
        ANNEX_EIGENVALUES,
        ANNEX_SCORES,
        add_standalone_table,
        build_image,
        fit_database,
        save_model,
    )
    from host.render.cinema import CinemaDB
    from protocol.image import HEADER_SIZE, image_size, read_manifest

    out = []
    for path in databases:
        db = CinemaDB.open(path)
        if db.depth is None:
            print(f"fit {path}: no depth maps, skipped", flush=True)
            continue
        t0 = time.perf_counter()
        model = fit_database(db, method="adaptive", cell=30, components=100, threshold=0.98)
        image, annex = build_image(model, db)
        t1 = time.perf_counter()
        add_standalone_table(image, annex[ANNEX_SCORES], eigenvalues=annex.get(ANNEX_EIGENVALUES))
        t2 = time.perf_counter()
        add_depth(image, db, 0.98)
        t3 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            ecs = Path(tmp) / "m.ecs"
            save_model(ecs, image, annex)
            with open(ecs, "rb") as f:
                device = image_size(f.read(HEADER_SIZE))
            sizes = {e["name"]: e["size"] for e in read_manifest(ecs)["sections"]}
        depth_b = sum(v for k, v in sizes.items() if k.startswith("depth"))
        table_b = sum(v for k, v in sizes.items() if k.startswith("standalone"))
        row = {"db": path, "views": db.n_views, "size": db.image_shape[1],
               "colour_fit_s": t1 - t0, "table_s": t2 - t1, "depth_s": t3 - t2,
               "device_bytes": device, "depth_bytes": depth_b, "table_bytes": table_b}
        print(f"fit {path} ({db.n_views} views at {db.image_shape[1]}): colour "
              f"{row['colour_fit_s']:.1f} s, table +{row['table_s']:.1f} s "
              f"({100 * row['table_s'] / row['colour_fit_s']:.0f} %), depth "
              f"+{row['depth_s']:.1f} s ({100 * row['depth_s'] / row['colour_fit_s']:.0f} %); "
              f"device image {device / 1e6:.2f} MB: table {100 * table_b / device:.0f} %, "
              f"depth {100 * depth_b / device:.0f} %", flush=True)
        out.append(row)
    return out


def main() -> int:
    from host.shared_data import shared_volume

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 views at 64 px, built-ins only")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--db", nargs="*", default=[], help="databases with depth to fit")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    volumes = ["builtin:tooth", "builtin:head"]
    if args.quick:
        args.views, args.size, args.samples = 4, 64, 200
    else:
        volumes += [str(p) for p in (shared_volume("tooth"), shared_volume("vismale_head"))
                    if p is not None]
    result = {"render": _render_section(volumes, args.views, args.size, args.samples),
              "fit": _fit_section(args.db)}
    if args.json:
        print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
