"""Benchmark `device_runtime.reconstruct.Reconstructor`: time per frame vs two baselines.

Synthetic eigenspaces of realistic size: square cells of 30 px, 30 % of the cells are
background with 0 components, the others keep 20..60 components (40 on average), int8
eigenimages with random content (speed does not depend on the values). Every frame gets a new
random score vector, so every cell with components is recomputed (the worst case).

For each image size (256, 512, 1080 px square) it prints:

* the time per frame (median of ``--frames`` frames) and fps, with 1 and 2 threads;
* the *floor*: the fastest full read of the int8 eigenspace, measured in the same run with
  two candidates -- ``np.bitwise_or.reduce`` over a uint64 view and ``arr.sum(dtype=int64)``
  -- and reported with the one that won;
* Pillow decoding a JPEG (quality 90) of a smooth synthetic image of the same size;

and the ratios frame / floor (target <= 3 at 1080) and frame / JPEG decode.
Targets (issue 3): 512x512 >= 100 fps, 1080x1080 >= 30 fps on 2 cores.

Run: ``.venv/bin/python benchmarks/bench_reconstruct.py [--sizes 256,512,1080] [--frames 30]``
(``--json`` prints one JSON object per size; ``--quick``: 256 and 512, 5 frames).

**The blend on real images against older code** (``--images A.ecs,B.ecs``, standalone
images): ``Reconstructor.update`` over the views a standalone device shows -- a drag (3
degrees of phi a frame at theta 15, ``--frames`` of them), an orbit (1 degree a frame) and
training views (a synthesized frame's colour on a cache miss), the scores from the image's
own table (`StandaloneScores`) -- with this tree's code and with ``device_runtime/
reconstruct.py`` as of ``--baseline REV`` (loaded from git into this process), each with its
own reconstructor, interleaved frame by frame (the order alternating between passes), timed
in CPU time (the process's: all reconstructor threads). Prints per image and sequence the
median of each, the ratio of their sums and how many frame values differ (0: bit-identical).
Run it on one core::

    OPENBLAS_NUM_THREADS=1 taskset -c 0 .venv/bin/python benchmarks/bench_reconstruct.py \
        --images A.ecs,B.ecs --baseline REV [--frames 120] [--passes 4]
"""

from __future__ import annotations

import argparse
import importlib.util
import io
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np
from PIL import Image

from device_runtime.reconstruct import DEFAULT_SCRATCH_BYTES, Reconstructor

REPO = Path(__file__).resolve().parent.parent

CELL = 30
ZERO_FRACTION = 0.3
K_RANGE = (20, 61)


def make_eigenspace(size: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    n_side = -(-size // CELL)
    n_cells = n_side * n_side
    values = CELL * CELL * 3
    counts = rng.integers(*K_RANGE, n_cells).astype(np.int32)
    counts[rng.random(n_cells) < ZERO_FRACTION] = 0
    n_coeff = int(counts.sum())
    return {
        "mean": rng.integers(0, 256, (n_cells, values), dtype=np.uint8),
        "eigenimages": rng.integers(-127, 128, (n_coeff, values), dtype=np.int8),
        "scales": np.full(n_coeff, 0.01, dtype=np.float32),
        "n_components": counts,
        "image_shape": (size, size),
        "cell_shape": (CELL, CELL),
    }


def best_time(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def floor_read_s(eigenimages: np.ndarray, repeat: int) -> tuple[float, str]:
    flat = eigenimages.reshape(-1)
    words = flat[: flat.size // 8 * 8].view(np.uint64)
    candidates = {
        "np.bitwise_or.reduce(uint64 view)": lambda: np.bitwise_or.reduce(words),
        "arr.sum(dtype=np.int64)": lambda: flat.sum(dtype=np.int64),
    }
    times = {name: best_time(fn, repeat) for name, fn in candidates.items()}
    name = min(times, key=times.get)
    return times[name], name


def jpeg_decode_s(size: int, repeat: int) -> tuple[float, int]:
    yy, xx = np.mgrid[0:size, 0:size] / size
    img = np.stack(
        [128 + 100 * np.sin(6 * xx + 3 * yy), 128 + 90 * np.cos(5 * yy), 255 * xx * yy], -1
    ).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=90)
    data = buf.getvalue()

    def decode() -> None:
        with Image.open(io.BytesIO(data)) as im:
            im.load()

    return best_time(decode, repeat), len(data)


def frame_s(space: dict, threads: int, frames: int, scratch_bytes: int) -> float:
    rec = Reconstructor(
        space["mean"], space["eigenimages"], space["scales"], space["n_components"],
        space["image_shape"], space["cell_shape"], scratch_bytes=scratch_bytes,
        threads=threads,
    )
    rng = np.random.default_rng(1)
    ys = [
        (rng.standard_normal(rec.n_coefficients) * 100).astype(np.float32)
        for _ in range(frames + 2)
    ]
    rec.update(ys[0])  # warm up (page in the arrays, start the thread)
    times = []
    for y in ys[1:]:
        t0 = time.perf_counter()
        rec.update(y)
        times.append(time.perf_counter() - t0)
    rec.close()
    return statistics.median(times)


def baseline_module(rev: str) -> ModuleType:
    """``device_runtime/reconstruct.py`` as of git revision ``rev``, imported as a module of
    its own (it imports only numpy and the standard library)."""
    try:
        text = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:device_runtime/"
                               "reconstruct.py"], check=True, capture_output=True,
                              text=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise SystemExit(f"bench_reconstruct: --baseline {rev}: no reconstruct.py there "
                         f"({exc})") from None
    name = "baseline_reconstruct"
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(text)
    try:
        spec = importlib.util.spec_from_file_location(name, f.name)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up
        spec.loader.exec_module(module)
    finally:
        os.unlink(f.name)
    return module


def blend_sequences(image, frames: int) -> dict[str, list[np.ndarray]]:
    """The score vectors of a standalone device's views: a 3 degree/frame drag, a 1
    degree/frame orbit (both at theta 15) and ``frames`` training views spread over the set."""
    from device_runtime.orbit import canonical_view
    from device_runtime.standalone import StandaloneScores

    scores = StandaloneScores(image)
    n_views = scores.table.shape[0]
    step = max(1, n_views // frames)
    return {
        "drag": [scores.scores(*canonical_view(3.0 * i, 15.0)) for i in range(frames)],
        "orbit": [scores.scores(*canonical_view(1.0 * i, 15.0)) for i in range(frames)],
        "training": [scores.training_scores(v) for v in range(0, n_views, step)][:frames],
    }


def compare_blend(path: Path, old: ModuleType, frames: int, passes: int, threads: int) -> dict:
    """One image: old and new ``update`` interleaved over `blend_sequences`."""
    from protocol.image import read_image

    image = read_image(path, read_annex=False)
    sequences = blend_sequences(image, frames)
    recs = {"old": old.Reconstructor.from_image(image, threads=threads),
            "new": Reconstructor.from_image(image, threads=threads)}
    result: dict = {"image": path.name, "size": int(image.image_shape[0]),
                    "K": int(image.n_coefficients), "threads": threads, "sequences": {}}
    for name, ys in sequences.items():
        cpu: dict[str, list[float]] = {k: [] for k in recs}
        differ = values = 0
        for p in range(passes):
            for y in ys:
                order = list(recs.items())
                if p % 2:
                    order.reverse()
                for key, rec in order:
                    c0 = time.process_time()
                    rec.update(y)
                    cpu[key].append(time.process_time() - c0)
                differ += int(np.count_nonzero(recs["old"].frame != recs["new"].frame))
                values += recs["new"].frame.size
        zeros = float(np.mean([np.mean(y == 0) for y in ys]))
        result["sequences"][name] = {
            "frames": len(ys), "zero_scores": zeros,
            "old_ms": 1e3 * statistics.median(cpu["old"]),
            "new_ms": 1e3 * statistics.median(cpu["new"]),
            "ratio": sum(cpu["new"]) / sum(cpu["old"]),
            "differing_values": differ, "values": values}
    for rec in recs.values():
        rec.close()
    return result


def main_images(args: argparse.Namespace) -> None:
    old = baseline_module(args.baseline)
    print(f"blend, this tree vs {args.baseline}: CPU time per update, "
          f"{args.passes} passes interleaved; OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', '-')}, CPUs "
          f"{sorted(os.sched_getaffinity(0))}, load {os.getloadavg()[0]:.1f}", flush=True)
    for name in args.images.split(","):
        path = Path(name)
        if not path.is_file():
            raise SystemExit(f"bench_reconstruct: no such image: {path}")
        r = compare_blend(path, old, args.frames, args.passes, args.threads)
        if args.json:
            print(json.dumps(r))
            continue
        parts = [f"{seq} {v['old_ms']:.2f} -> {v['new_ms']:.2f} ms = {v['ratio']:.2f}x "
                 f"({v['differing_values']} of {v['values']} values differ; scores "
                 f"{100 * v['zero_scores']:.0f} % zero)" for seq, v in r["sequences"].items()]
        print(f"  {r['image']} ({r['size']} px, K {r['K']}): " + "; ".join(parts), flush=True)
    print(f"  (load {os.getloadavg()[0]:.1f} at the end)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="256,512,1080")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--scratch-bytes", type=int, default=DEFAULT_SCRATCH_BYTES)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--quick", action="store_true", help="smoke run: 256 and 512, 5 frames")
    parser.add_argument("--images", default=None,
                        help="A.ecs[,B.ecs]: the blend on real images vs --baseline")
    parser.add_argument("--baseline", default="HEAD",
                        help="git revision of the old reconstruct.py (--images; default HEAD)")
    parser.add_argument("--passes", type=int, default=4, help="--images: passes over each "
                        "sequence")
    parser.add_argument("--threads", type=int, default=1, help="--images: reconstructor threads")
    args = parser.parse_args()
    if args.images:
        main_images(args)
        return
    if args.quick:
        args.sizes, args.frames = "256,512", 5
    for size in (int(s) for s in args.sizes.split(",")):
        space = make_eigenspace(size)
        e = space["eigenimages"]
        floor, floor_name = floor_read_s(e, 7)
        jpeg, jpeg_bytes = jpeg_decode_s(size, 7)
        t1 = frame_s(space, 1, args.frames, args.scratch_bytes)
        t2 = frame_s(space, 2, args.frames, args.scratch_bytes)
        result = {
            "size": size,
            "cells": len(space["n_components"]),
            "zero_cells": int((space["n_components"] == 0).sum()),
            "n_coefficients": int(e.shape[0]),
            "eigenspace_mb": e.nbytes / 1e6,
            "frame_ms_1thread": t1 * 1e3,
            "frame_ms_2threads": t2 * 1e3,
            "fps_1thread": 1 / t1,
            "fps_2threads": 1 / t2,
            "floor_ms": floor * 1e3,
            "floor_method": floor_name,
            "jpeg_decode_ms": jpeg * 1e3,
            "jpeg_bytes": jpeg_bytes,
            "ratio_floor_1thread": t1 / floor,
            "ratio_floor_2threads": t2 / floor,
            "ratio_jpeg_best": min(t1, t2) / jpeg,
        }
        if args.json:
            print(json.dumps(result))
            continue
        print(
            f"{size}x{size}: {result['cells']} cells ({result['zero_cells']} with 0 components), "
            f"K={result['n_coefficients']}, int8 eigenspace {result['eigenspace_mb']:.1f} MB"
        )
        print(
            f"  frame: {t1 * 1e3:7.2f} ms ({1 / t1:6.1f} fps) 1 thread | "
            f"{t2 * 1e3:7.2f} ms ({1 / t2:6.1f} fps) 2 threads"
        )
        print(f"  floor: {floor * 1e3:7.2f} ms  [{floor_name}]")
        print(f"  JPEG decode (Pillow, q90, {jpeg_bytes} B): {jpeg * 1e3:7.2f} ms")
        print(
            f"  ratios: frame/floor {t1 / floor:.2f} (1 thr) {t2 / floor:.2f} (2 thr); "
            f"best frame/JPEG {min(t1, t2) / jpeg:.2f}"
        )


if __name__ == "__main__":
    main()
