"""Ray-caster throughput on the paper's VisMale head, against the numpy reference.

Usage::

    .venv/bin/python benchmarks/bench_render.py [--quick] [--full] [--json] [--workers N]

Measures, in one run:

1. **Ray samples per second** of `host.render.raycast.Renderer` at 256x256 with 1000
   samples per ray (across the bounding sphere), and of the numpy reference
   `host.render.raycast_reference.render_reference` on a smaller image with the same
   settings and views, plus their ratio. A "ray sample" is a sample position
   inside the volume box (what a naive ray-caster evaluates), counted
   identically for both, so the rate measures how fast the same job gets done
   (both stop rays at the same opacity; only the numba kernel skips empty
   blocks).
2. **Time for the paper's training set**: the 1500-view ``grid:100x15`` at
   300x300 with 1000 samples, extrapolated from 30 views spread evenly over
   the grid (or rendered in full with ``--full``).

The head is rendered with a fixed skin + bone transfer function defined here
(window 0..255 on the uint8 CT values), so figures stay comparable over time.
Timings on a shared machine are noisy: compare ratios, not absolute figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.render.camera import orbit_camera, parse_view_set
from host.render.raycast import Renderer, warmup
from host.render.raycast_reference import render_reference, samples_in_box
from host.render.transfer import TransferFunction
from host.shared_data import shared_volume
from host.volume import Volume

SAMPLES = 1000
PAPER_GRID = "grid:100x15"
PAPER_SIZE = 300

# skin (soft tissue ~ 60..100 of 255) semi-transparent, bone (> 130) opaque
SKIN_BONE = TransferFunction(
    name="bench-skin-bone",
    color_points=np.array(
        [
            [0.00, 0.00, 0.00, 0.00],
            [0.20, 0.85, 0.55, 0.45],
            [0.35, 0.90, 0.70, 0.60],
            [0.50, 1.00, 0.97, 0.90],
            [1.00, 1.00, 1.00, 1.00],
        ]
    ),
    opacity_points=np.array(
        [
            [0.00, 0.00],
            [0.18, 0.00],
            [0.26, 0.15],
            [0.40, 0.15],
            [0.48, 0.00],
            [0.50, 0.00],
            [0.60, 0.80],
            [1.00, 0.90],
        ]
    ),
    window=(0.0, 255.0),
)


def load_head() -> tuple[Volume, str]:
    """The VisMale head: via host.volume.load_volume when it exists, else pynrrd."""
    path = shared_volume("vismale_head")
    if path is None:
        raise SystemExit(
            "bench_render: ../shared/data/vismale_head is missing (set EIGENCAST_SHARED_DATA)"
        )
    try:
        from host.volume import load_volume
    except ImportError:
        load_volume = None
    if load_volume is not None:
        return load_volume(str(path)), "host.volume.load_volume"
    import nrrd

    data, header = nrrd.read(str(path), index_order="C")
    spacing = tuple(float(s) for s in header["spacings"])
    volume = Volume(
        data.astype(np.float32), spacing, name="vismale_head", modality="ct", source=str(path)
    )
    return volume, "pynrrd (host.volume.load_volume not available)"


def spread(views: tuple, count: int) -> list:
    """``count`` views evenly spaced through the set's order (phi outer, theta inner)."""
    idx = np.linspace(0, len(views) - 1, count).round().astype(int)
    return [views[i] for i in idx]


def time_renders(renderer: Renderer, cameras: list, size: int) -> list[float]:
    times = []
    for camera in cameras:
        start = time.perf_counter()
        renderer.render(camera, size, size)
        times.append(time.perf_counter() - start)
    return times


def _rows(results: dict, dims: tuple, fast_times: list, grid_times: list
          ) -> list[tuple[str, str]]:
    """The table ``main`` prints: (what, value) per line."""
    numba_, ref, grid = results["numba"], results["reference"], results["paper_grid"]
    rate_size, fast_rate = numba_["image"], numba_["ray_samples_per_s"]
    ref_size, ref_rate, ref_s = ref["image"], ref["ray_samples_per_s"], ref["seconds"]
    setup_s, empty = results["renderer_setup_s"], results["empty_block_fraction"]
    per_view_s, total_s = grid["per_view_s_mean"], grid["total_s"]
    how = (
        f"measured in full ({grid['views_measured']} views)"
        if not grid["extrapolated"]
        else f"extrapolated from {grid['views_measured']} views"
    )
    return [
        ("volume", f"vismale_head {dims} via {results['volume']['loader']}"),
        ("transfer function", results["transfer_function"]),
        ("threads", str(results["threads"])),
        ("compile / cache load", f"{results['compile_or_cache_load_s']:.2f} s"),
        (
            "renderer setup",
            f"{setup_s:.2f} s  ({100 * empty:.0f} % of blocks empty)",
        ),
        (
            f"numba, {rate_size}x{rate_size}, {SAMPLES} samples",
            f"{fast_rate / 1e6:8.1f} M ray samples/s  ({np.mean(fast_times):.3f} s/view)",
        ),
        (
            f"numpy reference, {ref_size}x{ref_size}",
            f"{ref_rate / 1e6:8.2f} M ray samples/s  ({ref_s:.2f} s/view)",
        ),
        ("speedup vs reference", f"{fast_rate / ref_rate:8.1f} x  (target >= 20 x)"),
        ("max |numba - reference|", f"{ref['max_abs_diff_vs_numba']:.2e}"),
        (
            f"paper grid {PAPER_GRID} at {PAPER_SIZE}x{PAPER_SIZE}",
            f"{per_view_s:.3f} s/view mean ({np.min(grid_times):.3f}..{np.max(grid_times):.3f})",
        ),
        ("  1500 views total", f"{total_s / 60:.1f} min, {how}  (target <= 10 min)"),
    ]


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: small sizes, few views")
    parser.add_argument(
        "--full", action="store_true", help="render all 1500 paper views instead of extrapolating"
    )
    parser.add_argument("--json", action="store_true", help="print results as JSON")
    parser.add_argument("--workers", type=int, default=None, help="render threads")
    parser.add_argument(
        "--tf",
        default=None,
        metavar="PRESET",
        help="a host.render.transfer preset instead of the fixed skin+bone function",
    )
    return parser.parse_args(argv)


def _transfer_function(preset: str | None) -> TransferFunction:
    """The fixed skin+bone function, or a `host.render.transfer` preset."""
    if preset is None:
        return SKIN_BONE
    from host.render.transfer import load_transfer_function

    return load_transfer_function(preset)


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    tf = _transfer_function(args.tf)

    rate_size, ref_size, rate_views, grid_sample = (
        (96, 12, 2, 6) if args.quick else (256, 40, 4, 30)
    )

    t0 = time.perf_counter()
    warmup()
    compile_s = time.perf_counter() - t0
    volume, loader = load_head()
    t0 = time.perf_counter()
    renderer = Renderer(volume, tf, samples=SAMPLES, workers=args.workers)
    setup_s = time.perf_counter() - t0
    import numba

    threads = args.workers or numba.config.NUMBA_NUM_THREADS
    center, radius = volume.center_mm, volume.radius_mm

    # 1. ray samples per second, numba vs numpy reference, same views and settings
    views = spread(parse_view_set("fibonacci:64").views, rate_views)
    cams = [orbit_camera(v, center, radius) for v in views]
    fast_times = time_renders(renderer, cams, rate_size)
    fast_samples = sum(
        samples_in_box(volume, c, rate_size, rate_size, renderer.step_mm) for c in cams
    )
    fast_rate = fast_samples / sum(fast_times)
    ref_cam = cams[0]
    t0 = time.perf_counter()
    ref_image = render_reference(
        volume, tf, ref_cam, ref_size, ref_size, step_mm=renderer.step_mm, window=renderer.window
    )
    ref_s = time.perf_counter() - t0
    ref_rate = samples_in_box(volume, ref_cam, ref_size, ref_size, renderer.step_mm) / ref_s
    fast_first = renderer.render(ref_cam, ref_size, ref_size)
    max_abs = float(np.abs(fast_first - ref_image).max())

    # 2. the paper's 1500-view training grid at 300x300
    grid = parse_view_set(PAPER_GRID)
    chosen = grid.views if args.full else spread(grid.views, grid_sample)
    grid_cams = [orbit_camera(v, center, radius) for v in chosen]
    grid_times = time_renders(renderer, grid_cams, PAPER_SIZE)
    per_view_s = float(np.mean(grid_times))
    total_s = per_view_s * len(grid) if not args.full else float(np.sum(grid_times))

    results = {
        "volume": {
            "name": "vismale_head",
            "dims": list(volume.dims),
            "spacing": list(volume.spacing),
            "loader": loader,
        },
        "transfer_function": tf.name,
        "samples_per_ray": SAMPLES,
        "step_mm": renderer.step_mm,
        "threads": threads,
        "compile_or_cache_load_s": compile_s,
        "renderer_setup_s": setup_s,
        "empty_block_fraction": renderer.empty_block_fraction,
        "numba": {
            "image": rate_size,
            "views": len(cams),
            "ray_samples": fast_samples,
            "seconds": float(sum(fast_times)),
            "ray_samples_per_s": fast_rate,
        },
        "reference": {
            "image": ref_size,
            "views": 1,
            "seconds": ref_s,
            "ray_samples_per_s": ref_rate,
            "max_abs_diff_vs_numba": max_abs,
        },
        "speedup_vs_reference": fast_rate / ref_rate,
        "paper_grid": {
            "spec": PAPER_GRID,
            "size": PAPER_SIZE,
            "views_total": len(grid),
            "views_measured": len(chosen),
            "extrapolated": not args.full,
            "per_view_s_mean": per_view_s,
            "per_view_s_min": float(np.min(grid_times)),
            "per_view_s_max": float(np.max(grid_times)),
            "total_s": total_s,
        },
        "quick": args.quick,
    }
    if args.json:
        print(json.dumps(results, indent=2))
        return 0

    rows = _rows(results, volume.dims, fast_times, grid_times)
    width = max(len(name) for name, _ in rows)
    print("bench_render" + ("  [--quick]" if args.quick else ""))
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
