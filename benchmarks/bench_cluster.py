"""Render and fit through ``--scheduler``: overhead against in-process threads, and a scaling model.

Usage::

    .venv/bin/python benchmarks/bench_cluster.py                      # 1500 views at 256 (issue 16)
    .venv/bin/python benchmarks/bench_cluster.py --views fibonacci:300 --size 256
    .venv/bin/python benchmarks/bench_cluster.py --quick              # smoke run
    .venv/bin/python benchmarks/bench_cluster.py --estimate-1080 4    # only the estimate below

Measures, in one run and on one database (``builtin:tooth`` by default):

1. ``eigencast render`` with in-process threads (the baseline), then through a `LocalCluster`
   of 1 and of 2 single-threaded worker processes (``--scheduler ADDRESS``; the cluster's start
   is timed apart). Each cluster database is checked byte for byte against the baseline's.
   Overhead ratio = cluster render time / in-process time (issue 16's target: < 1.25x with 2
   workers for a 1500-view 256 render).
2. ``eigencast fit`` of that database the same three ways (adaptive, cells of 30), and each
   worker's peak RSS after it (``ru_maxrss``).
3. A scaling model for N machines, from this run's task stream: compute seconds per view and
   per stack/fit task, bytes each task returns, the client's write time per image, and an
   assumed network bandwidth (``--gbps``, default 1 Gb/s per machine and at the client).

``--estimate-1080 N`` instead ray-casts N views of the paper's 1500-view grid at 1080 x 1080
(1000 samples per ray) of the shared tooth and VisMale head in-process and extrapolates the
render time of the whole grid (issue 16's Table 1 reproduction, not run here).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import tempfile
import time
import types
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import distributed

import host.model
from host.cinema import atomic_write_bytes
from host.cli import main as cli


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(argv: list[str]) -> float:
    start = time.perf_counter()
    rc = cli(argv)
    if rc != 0:
        raise SystemExit(f"eigencast {' '.join(argv)}: exit {rc}")
    return time.perf_counter() - start


def _snapshot(db: Path) -> dict[str, bytes]:
    return {p.relative_to(db).as_posix(): p.read_bytes() for p in db.rglob("*") if p.is_file()
            and ".eigencast-cache" not in p.parts}


def _stream_summary(records: list[dict], prefix: str) -> dict:
    """Compute seconds, transfer seconds and result bytes of the tasks whose key starts so."""
    compute = transfer = 0.0
    nbytes = count = 0
    for r in records:
        key = r["key"] if isinstance(r["key"], str) else str(r["key"])
        if not key.startswith(prefix):
            continue
        count += 1
        nbytes += int(r.get("nbytes", 0) or 0)
        for ss in r.get("startstops", ()):
            if ss["action"] == "compute":
                compute += ss["stop"] - ss["start"]
            elif ss["action"] == "transfer":
                transfer += ss["stop"] - ss["start"]
    return {"tasks": count, "compute_s": compute, "transfer_s": transfer, "result_bytes": nbytes}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--volume", default="builtin:tooth")
    ap.add_argument("--views", default="fibonacci:1500")
    ap.add_argument("--size", default="256")
    ap.add_argument("--samples", default="1000")
    ap.add_argument("--cell", default="30")
    ap.add_argument("--gbps", type=float, default=1.0, help="network per machine (model)")
    ap.add_argument("--quick", action="store_true", help="60 views at 64x64")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--estimate-1080", type=int, metavar="N", default=0,
                    help="only time N views at 1080x1080 of the shared tooth and head")
    args = ap.parse_args()
    if args.estimate_1080:
        return _estimate_1080(args.estimate_1080)
    if args.quick:
        args.views, args.size, args.cell = "fibonacci:60", "64", "16"
    render_opts = ["--views", args.views, "--size", args.size, "--samples", args.samples]
    fit_opts = ["--cell", args.cell]
    work = Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    # the .ecs records its creation time: freeze it so the fits compare byte for byte
    host.model.time = types.SimpleNamespace(time=lambda: 1.7e9, time_ns=lambda: 17 * 10**17)
    out: dict = {"volume": args.volume, "views": args.views, "size": args.size,
                 "cpus": os.cpu_count(), "load_1min": os.getloadavg()[0]}
    try:
        ref = work / "threads.cdb"
        cli(["render", args.volume, "-o", str(work / "warm.cdb"), "--views", "list:0,0",
             "--size", "16"])  # numba cache, imports
        out["threads"] = {"render_s": _timed(["render", args.volume, "-o", str(ref),
                                              *render_opts])}
        reference = _snapshot(ref)
        n_views = sum(1 for k in reference if k.startswith("images/"))
        png_bytes = sum(len(v) for k, v in reference.items() if k.startswith("images/"))
        out["threads"]["fit_s"] = _timed(["fit", str(ref), "-o", str(work / "threads.ecs"),
                                          *fit_opts, "--cache", str(work / "cache")])
        # the client's own cost per image: the atomic write of its PNG
        scratch = work / "scratch"
        scratch.mkdir()
        start = time.perf_counter()
        for name, data in reference.items():
            if name.startswith("images/"):
                atomic_write_bytes(scratch / Path(name).name, data)
        write_s = (time.perf_counter() - start) / n_views
        for n_workers in (1, 2):
            start = time.perf_counter()
            with distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1,
                                          processes=True, dashboard_address=None) as lc, \
                    distributed.Client(lc) as client:
                started = time.perf_counter() - start
                db = work / f"cluster{n_workers}.cdb"
                with distributed.get_task_stream(client) as ts:
                    render_s = _timed(["render", args.volume, "-o", str(db), *render_opts,
                                       "--scheduler", lc.scheduler_address])
                render_stream = _stream_summary(ts.data, "render-views-")
                identical = _snapshot(db) == reference
                with distributed.get_task_stream(client) as ts:
                    fit_s = _timed(["fit", str(ref), "-o", str(work / f"c{n_workers}.ecs"),
                                    *fit_opts, "--scheduler", lc.scheduler_address])
                rss = client.run(_peak_rss_mb)
                same_fit = ((work / f"c{n_workers}.ecs").read_bytes()
                            == (work / "threads.ecs").read_bytes())
                out[f"local{n_workers}"] = {
                    "start_s": started, "render_s": render_s, "identical": identical,
                    "render_ratio": render_s / out["threads"]["render_s"], "fit_s": fit_s,
                    "fit_ratio": fit_s / out["threads"]["fit_s"], "identical_fit": same_fit,
                    "worker_peak_rss_mb": sorted(rss.values()),
                    "render_tasks": render_stream,
                    "stack_tasks": _stream_summary(ts.data, "stack-views-"),
                    "fit_tasks": _stream_summary(ts.data, "fit-cells-"),
                }
        out["model"] = _scaling_model(out, n_views, png_bytes, write_s, args.gbps)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        print(json.dumps(out, indent=1, default=float))
    else:
        _print(out)
    same = all(out[f"local{n}"]["identical"] and out[f"local{n}"]["identical_fit"]
               for n in (1, 2))
    return 0 if same else 1


def _estimate_1080(n: int) -> int:
    """Time ``n`` views of grid:100x15 at 1080 (paper settings); extrapolate 1500 views."""
    import numpy as np

    from host.camera import orbit_camera, parse_view_set
    from host.cli import build_parser
    from host.commands._render_options import camera_settings, render_setup
    from host.shared_data import shared_volume

    views = parse_view_set("grid:100x15").views
    pick = [views[int(i)] for i in np.linspace(0, len(views) - 1, n)]
    for name in ("tooth", "vismale_head"):
        path = shared_volume(name)
        if path is None:
            print(f"{name}: ../shared/data is absent")
            continue
        args = build_parser().parse_args(["render", str(path), "-o", "unused.cdb",
                                          "--size", "1080"])
        start = time.perf_counter()
        volume, _tf, renderer = render_setup(args)
        cam = camera_settings(args, volume, renderer)
        setup = time.perf_counter() - start
        renderer.render_rgb8(orbit_camera(pick[0], cam["center_mm"], cam["radius_mm"]), 64, 64)
        start = time.perf_counter()
        for v in pick:
            renderer.render_rgb8(orbit_camera(v, cam["center_mm"], cam["radius_mm"]), 1080, 1080)
        per_view = (time.perf_counter() - start) / n
        print(f"{name}: {per_view:.2f} s/view at 1080x1080 on {os.cpu_count()} cores "
              f"(load {os.getloadavg()[0]:.1f}), setup {setup:.1f} s -> 1500 views "
              f"{1500 * per_view / 60:.0f} min in-process")
    return 0


def _scaling_model(out: dict, n_views: int, png_bytes: int, write_s: float, gbps: float) -> dict:
    """Predicted wall time on N machines like this one (2 worker threads each).

    render(N) = max(compute / (2 N) + tasks * overhead / (2 N), client), where compute is the
    measured worker seconds of all views (1-worker run), overhead the measured per-task cost
    beyond compute, and client = views * (write + PNG bytes / bandwidth): the client writes
    every image, so it bounds the speed-up.
    fit(N) = (stack + fit compute) / (2 N) + shuffled bytes * (N - 1) / N / (N * bandwidth)
    + client (the model's bytes over the network + the client's serial work, measured as the
    1-worker fit time minus its task compute).
    """
    one = out["local1"]
    bw = gbps * 1e9 / 8
    r = one["render_tasks"]
    per_task_overhead = max(0.0, one["render_s"] - r["compute_s"]) / max(1, r["tasks"])
    client_render = n_views * (write_s + png_bytes / n_views / bw)
    stack, fitt = one["stack_tasks"], one["fit_tasks"]
    shuffled = stack["result_bytes"]
    client_fit = max(0.0, one["fit_s"] - stack["compute_s"] - fitt["compute_s"])
    rows = []
    for n in (1, 2, 4, 8, 16, 32, 64):
        threads = 2 * n
        render = max((r["compute_s"] + r["tasks"] * per_task_overhead) / threads, client_render)
        fit = ((stack["compute_s"] + fitt["compute_s"]) / threads
               + shuffled * (n - 1) / n / (n * bw) + client_fit + fitt["result_bytes"] / bw)
        rows.append({"machines": n, "render_s": render, "fit_s": fit})
    return {"compute_s_per_view": r["compute_s"] / n_views,
            "png_bytes_per_view": png_bytes / n_views,
            "client_write_s_per_view": write_s,
            "per_task_overhead_s": per_task_overhead,
            "client_render_bound_s": client_render,
            "stack_bytes_shuffled": shuffled,
            "fit_client_serial_s": client_fit,
            "gbps": gbps, "rows": rows}


def _print(out: dict) -> None:
    print(f"{out['volume']} {out['views']} at {out['size']}, {out['cpus']} cpus, "
          f"load {out['load_1min']:.1f} at start")
    t = out["threads"]
    print(f"{'config':<18}{'start s':>9}{'render s':>10}{'ratio':>7}{'fit s':>8}{'ratio':>7}"
          f"{'worker peak MB':>18}  same PNGs / .ecs")
    print(f"{'in-process':<18}{'':>9}{t['render_s']:>10.1f}{1.0:>7.2f}{t['fit_s']:>8.1f}"
          f"{1.0:>7.2f}{'':>18}")
    for n in (1, 2):
        c = out[f"local{n}"]
        rss = "/".join(f"{v:.0f}" for v in c["worker_peak_rss_mb"])
        print(f"{f'LocalCluster x{n}':<18}{c['start_s']:>9.1f}{c['render_s']:>10.1f}"
              f"{c['render_ratio']:>7.2f}{c['fit_s']:>8.1f}{c['fit_ratio']:>7.2f}{rss:>18}"
              f"  {c['identical']} / {c['identical_fit']}")
    m = out["model"]
    print(f"\nmodel inputs: {m['compute_s_per_view'] * 1e3:.1f} ms compute/view, "
          f"{m['png_bytes_per_view'] / 1e3:.1f} kB PNG/view, client write "
          f"{m['client_write_s_per_view'] * 1e3:.2f} ms/view, task overhead "
          f"{m['per_task_overhead_s'] * 1e3:.1f} ms, stack shuffled "
          f"{m['stack_bytes_shuffled'] / 1e6:.1f} MB, fit client-serial "
          f"{m['fit_client_serial_s']:.1f} s, {m['gbps']:g} Gb/s")
    print(f"{'machines (2 threads each)':<28}{'render s':>10}{'fit s':>8}")
    for row in m["rows"]:
        print(f"{row['machines']:<28}{row['render_s']:>10.1f}{row['fit_s']:>8.1f}")
    print(f"render is client-bound beyond {m['client_render_bound_s']:.1f} s")


if __name__ == "__main__":
    sys.exit(main())
