"""What the cinematic look costs to render: the training set with both looks, interleaved.

Usage::

    .venv/bin/python benchmarks/bench_lighting.py [--volumes builtin:head,tooth]
        [--views grid:100x15] [--size 256] [--stride 1] [--output DIR] [--json] [--quick]

For each volume, in one process and on every core the machine lets numba use, renders the
view set twice the way ``eigencast render`` does (a ray-cast with depth, the PNG and the
depth map encoded, and with ``--output`` written into a Cinema database): once with the
``headlight`` and once with the ``cinematic`` lighting, view by view in turn, so both looks
see the same load. Each look's time includes building its renderer; the cinematic one
computes its light field there with the caches off, as a first render would. Prints the
totals and their ratio (the bound: at most 2x). ``--stride N`` renders every N-th view only
(and extrapolates nothing: the figures are for the views rendered).

With ``--output DIR`` the databases ``DIR/NAME-headlight.cdb`` and ``DIR/NAME-cinematic.cdb``
are kept (the input of ``research/lighting_warp.py``); the headlight one is what ``eigencast
render VOLUME --size SIZE`` writes, byte for byte.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
os.environ["EIGENCAST_CACHE_DIR"] = ""  # the cinematic look pays for its light field

from host.cli import build_parser
from host.commands._render_options import camera_settings, render_setup
from host.commands.render import _depth_offset, database_settings
from host.render.camera import orbit_camera, parse_view_set
from host.render.cinema import CinemaWriter, encode_depth, encode_png
from host.render.raycast import warmup
from host.shared_data import shared_volume

LOOKS = ("headlight", "cinematic")


def _spec(name: str) -> str:
    if name.startswith("builtin:") or Path(name).exists():
        return name
    path = shared_volume(name)
    if path is None:
        raise SystemExit(f"bench_lighting: {name}: not a built-in and not in ../shared/data")
    return str(path)


class _Look:
    """One look's renderer, cameras and (optional) database, timed."""

    def __init__(self, spec: str, look: str, size: int, views: str, output: Path | None) -> None:
        argv = ["render", spec, "-o", str(output or "unused.cdb"), "--size", str(size),
                "--views", views, "--lighting", look]
        self.args = build_parser().parse_args(argv)
        start = time.perf_counter()
        volume, tf, self.renderer = render_setup(self.args)
        framing = camera_settings(self.args, volume, self.renderer)
        self.view_set = parse_view_set(views)
        self.cameras = [orbit_camera(v, framing["center_mm"], framing["radius_mm"],
                                     projection=self.args.projection, fov_deg=self.args.fov)
                        for v in self.view_set.views]
        settings = database_settings(volume, tf, self.renderer, self.view_set, (size, size),
                                     framing)
        self.depth_offset = _depth_offset(self.args, settings, (size, size))
        self.writer = None
        if output is not None:
            rows = [(v.phi_deg, v.theta_deg, c.to_dict())
                    for v, c in zip(self.view_set.views, self.cameras)]
            self.writer = CinemaWriter(output, settings, rows, (size, size), overwrite=True,
                                       depth_offset_mm=self.depth_offset)
        self.size = size
        self.seconds = time.perf_counter() - start
        self.setup_s = self.seconds

    def render(self, index: int) -> None:
        start = time.perf_counter()
        rgba, depth = self.renderer.render_with_depth(self.cameras[index], self.size, self.size)
        png = encode_png(self.renderer.composite(rgba))
        npz = encode_depth(depth, self.depth_offset) if self.depth_offset is not None else None
        if self.writer is not None:
            if npz is not None:
                self.writer.write_depth(index, npz)
            self.writer.write_png(index, png)
        self.seconds += time.perf_counter() - start

    def close(self) -> None:
        if self.writer is not None:
            self.writer.write_csv()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--volumes", default="builtin:head,tooth",
                        help="comma-separated built-ins, shared-data names or paths")
    parser.add_argument("--views", default="grid:100x15")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--stride", type=int, default=1, help="render every N-th view")
    parser.add_argument("--output", type=Path, help="keep the databases in this folder")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: builtin:head, grid:20x3 at 64 px")
    args = parser.parse_args(argv)
    if args.quick:
        args.volumes, args.views, args.size = "builtin:head", "grid:20x3", 64
    import numba

    warmup()
    results = []
    for name in args.volumes.split(","):
        spec = _spec(name)
        label = name.replace("builtin:", "")
        outputs = {look: (args.output / f"{label}-{look}.cdb" if args.output else None)
                   for look in LOOKS}
        looks = {look: _Look(spec, look, args.size, args.views, outputs[look]) for look in LOOKS}
        chosen = range(0, len(looks["headlight"].cameras), args.stride)
        for i in chosen:
            for look in LOOKS:
                looks[look].render(i)
        for look in looks.values():
            look.close()
        head, cine = looks["headlight"], looks["cinematic"]
        results.append({
            "volume": label, "views": len(chosen), "size": args.size,
            "threads": int(numba.config.NUMBA_NUM_THREADS),
            "headlight_s": head.seconds, "cinematic_s": cine.seconds,
            "cinematic_setup_s": cine.setup_s, "ratio": cine.seconds / head.seconds,
            "load_1min": os.getloadavg()[0],
        })
        if not args.json:
            r = results[-1]
            print(f"{label:>14}: {r['views']} views at {args.size}, {r['threads']} threads: "
                  f"headlight {r['headlight_s']:.1f} s, cinematic {r['cinematic_s']:.1f} s "
                  f"(light field and setup {r['cinematic_setup_s']:.1f} s): ratio "
                  f"{r['ratio']:.2f} (bound 2.0), load {r['load_1min']:.1f}", flush=True)
    if args.json:
        print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
