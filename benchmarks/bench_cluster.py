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
import contextlib
import json
import math
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

import host.fit.model
from host.cli import main as cli
from host.cluster import Cluster, render_pngs
from host.render.cinema import CinemaWriter, atomic_write_bytes, encode_png


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


def _stream_summary(records: list[dict], prefix: str, rounds: int = 1) -> dict:
    """Compute seconds, transfer seconds and result bytes of the tasks whose key starts so
    (per round when the same work ran ``rounds`` times)."""
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
    return {"tasks": count // rounds, "compute_s": compute / rounds,
            "transfer_s": transfer / rounds, "result_bytes": nbytes // rounds}


class _RenderJob:
    """One database rendered slice by slice, in-process or through a cluster, as the CLI does
    (host/commands/render.py: same settings, cameras, writer and PNG bytes)."""

    def __init__(self, argv: list[str], cluster) -> None:
        from host.cli import build_parser
        from host.commands._render_options import camera_settings, parse_size, render_setup
        from host.commands.render import database_settings
        from host.render.camera import orbit_camera, parse_view_set

        self.args = args = build_parser().parse_args(argv)
        self.cluster = cluster
        self.width, self.height = parse_size(args.size)
        view_set = parse_view_set(args.views)
        self.scene = volume, tf, renderer = render_setup(args)
        cam = camera_settings(args, volume, renderer)
        self.cameras = [orbit_camera(v, cam["center_mm"], cam["radius_mm"],
                                     projection=args.projection, fov_deg=args.fov)
                        for v in view_set.views]
        rows = [(v.phi_deg, v.theta_deg, c.to_dict())
                for v, c in zip(view_set.views, self.cameras)]
        settings = database_settings(volume, tf, renderer, view_set,
                                     (self.width, self.height), cam)
        self.writer = CinemaWriter(args.output, settings, rows, (self.height, self.width))

    def render(self, indices: list[int]) -> None:
        w, h = self.width, self.height
        if self.cluster is None:
            renderer = self.scene[2]
            for i in indices:
                self.writer.write_png(i, encode_png(renderer.render_rgb8(self.cameras[i], w, h)))
        else:
            for i, png, _depth in render_pngs(self.cluster, self.args, self.scene,
                                              self.cameras, indices, w, h):
                self.writer.write_png(i, png)


CONFIGS = ("threads", "local1", "local2")


def _parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--volume", default="builtin:tooth")
    ap.add_argument("--views", default="fibonacci:1500")
    ap.add_argument("--size", default="256")
    ap.add_argument("--samples", default="1000")
    ap.add_argument("--cell", default="30")
    ap.add_argument("--rounds", type=int, default=6,
                    help="slices the render is cut into, each timed in every configuration "
                         "in turn (rotating order), so load changes hit all three alike")
    ap.add_argument("--gbps", type=float, default=1.0, help="network per machine (model)")
    ap.add_argument("--quick", action="store_true", help="60 views at 64x64")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--estimate-1080", type=int, metavar="N", default=0,
                    help="only time N views at 1080x1080 of the shared tooth and head")
    return ap.parse_args()


def main() -> int:
    args = _parse_args()
    if args.estimate_1080:
        return _estimate_1080(args.estimate_1080)
    if args.quick:
        args.views, args.size, args.cell, args.rounds = "fibonacci:60", "64", "16", 2
    render_opts = ["--views", args.views, "--size", args.size, "--samples", args.samples]
    work = Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    # the .ecs records its creation time: freeze it so the fits compare byte for byte
    host.fit.model.time = types.SimpleNamespace(time=lambda: 1.7e9, time_ns=lambda: 17 * 10**17)
    out: dict = {"volume": args.volume, "views": args.views, "size": args.size,
                 "cpus": os.cpu_count(), "load_1min_start": os.getloadavg()[0]}
    try:
        with contextlib.ExitStack() as stack:
            clusters: dict = {"threads": None}
            streams: dict = {}
            for n in (1, 2):
                start = time.perf_counter()
                lc = stack.enter_context(distributed.LocalCluster(
                    n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0"))
                clusters[f"local{n}"] = stack.enter_context(Cluster(lc.scheduler_address))
                out[f"local{n}"] = {"start_s": time.perf_counter() - start}
                streams[f"local{n}"] = stack.enter_context(
                    distributed.get_task_stream(clusters[f"local{n}"].client))
            out["threads"] = {}
            cli(["render", args.volume, "-o", str(work / "warm.cdb"), "--views", "list:0,0",
                 "--size", "16"])  # numba cache, imports
            jobs = {c: _RenderJob(["render", args.volume, "-o", str(work / f"{c}.cdb"),
                                   *render_opts], clusters[c]) for c in CONFIGS}
            n_views = len(jobs["threads"].cameras)
            per = math.ceil(n_views / args.rounds)
            spent = dict.fromkeys(CONFIGS, 0.0)
            loads = []
            for r, s0 in enumerate(range(0, n_views, per)):
                indices = list(range(s0, min(n_views, s0 + per)))
                for c in CONFIGS[r % 3:] + CONFIGS[:r % 3]:
                    start = time.perf_counter()
                    jobs[c].render(indices)
                    spent[c] += time.perf_counter() - start
                loads.append(os.getloadavg()[0])
            for c in CONFIGS:
                jobs[c].writer.write_csv()
            reference = _snapshot(work / "threads.cdb")
            png_bytes = sum(len(v) for k, v in reference.items() if k.startswith("images/"))
            # the client's own cost per image: the atomic write of its PNG
            scratch = work / "scratch"
            scratch.mkdir()
            start = time.perf_counter()
            for name, data in reference.items():
                if name.startswith("images/"):
                    atomic_write_bytes(scratch / Path(name).name, data)
            write_s = (time.perf_counter() - start) / n_views
            # fits: two rounds in opposite orders, each in-process fit with a fresh stack
            fit_s = dict.fromkeys(CONFIGS, 0.0)
            ref_db = str(work / "threads.cdb")
            for r, order in enumerate((CONFIGS, CONFIGS[::-1])):
                for c in order:
                    where = (["--cache", str(work / f"cache{r}")] if c == "threads" else
                             ["--scheduler", clusters[c].address])
                    fit_s[c] += _timed(["fit", ref_db, "-o", str(work / f"{c}.ecs"),
                                        "--cell", args.cell, "--no-standalone", *where]) / 2
                loads.append(os.getloadavg()[0])
            out["loads"] = loads
            for c in CONFIGS:
                rec = out[c]
                rec.update(render_s=spent[c], render_ratio=spent[c] / spent["threads"],
                           fit_s=fit_s[c], fit_ratio=fit_s[c] / fit_s["threads"])
                if c == "threads":
                    continue
                rec["identical"] = _snapshot(work / f"{c}.cdb") == reference
                rec["identical_fit"] = ((work / f"{c}.ecs").read_bytes()
                                        == (work / "threads.ecs").read_bytes())
                rec["worker_peak_rss_mb"] = sorted(clusters[c].client.run(_peak_rss_mb).values())
        for c in CONFIGS[1:]:  # a task stream's records arrive when its context exits
            data = streams[c].data
            out[c]["render_tasks"] = _stream_summary(data, "render-views-")
            out[c]["stack_tasks"] = _stream_summary(data, "stack-views-", rounds=2)
            out[c]["fit_tasks"] = _stream_summary(data, "fit-cells-", rounds=2)
        out["model"] = _scaling_model(out, n_views, png_bytes, write_s, args.gbps)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        print(json.dumps(out, indent=1, default=float))
    else:
        _print(out)
    same = all(out[c]["identical"] and out[c]["identical_fit"] for c in CONFIGS[1:])
    return 0 if same else 1


def _estimate_1080(n: int) -> int:
    """Time ``n`` views of grid:100x15 at 1080 (paper settings); extrapolate 1500 views."""
    import numpy as np

    from host.cli import build_parser
    from host.commands._render_options import camera_settings, render_setup
    from host.render.camera import orbit_camera, parse_view_set
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
    """Predicted wall time on N machines like this one (2 cores, 2 single-threaded workers).

    One machine's work is what the 2-worker LocalCluster measured. render(N) = max(render wall
    of 2 workers / N, client), where client = views * (write + PNG bytes / bandwidth): the
    client writes every image, so it bounds the speed-up. fit(N) = (stack + fit task compute)
    / (2 N) + shuffle + serial, where the shuffle moves the stack's pieces between machines
    (a fraction (N - 1) / N of the stack, over N links) and serial is the client's own part
    (2-worker fit wall minus its task compute spread over 2 workers: opening the database,
    bit allocation, int8 check, writing the image), which does not shrink with N.
    """
    two = out["local2"]
    bw = gbps * 1e9 / 8
    r = two["render_tasks"]
    client_render = n_views * (write_s + png_bytes / n_views / bw)
    stack, fitt = two["stack_tasks"], two["fit_tasks"]
    shuffled = stack["result_bytes"]
    compute = stack["compute_s"] + fitt["compute_s"]
    serial = max(0.0, two["fit_s"] - compute / 2)
    rows = []
    for n in (1, 2, 4, 8, 16, 32, 64):
        render = max(two["render_s"] / n, client_render)
        fit = compute / (2 * n) + shuffled * (n - 1) / (n * n * bw) + serial
        rows.append({"machines": n, "render_s": render, "fit_s": fit})
    return {"compute_s_per_view": r["compute_s"] / n_views,
            "render_tasks": r["tasks"],
            "png_bytes_per_view": png_bytes / n_views,
            "client_write_s_per_view": write_s,
            "client_render_bound_s": client_render,
            "stack_bytes_shuffled": shuffled,
            "fit_compute_s": compute,
            "fit_serial_s": serial,
            "gbps": gbps, "rows": rows}


def _print(out: dict) -> None:
    print(f"{out['volume']} {out['views']} at {out['size']}, {out['cpus']} cpus, "
          f"load {out['load_1min_start']:.1f} at start")
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
    print("1-minute load after each render round, then each fit round: "
          + ", ".join(f"{v:.1f}" for v in out["loads"]))
    m = out["model"]
    print(f"\nmodel inputs (2-worker run): {m['compute_s_per_view'] * 1e3:.0f} ms worker compute"
          f"/view in {m['render_tasks']} tasks, {m['png_bytes_per_view'] / 1e3:.1f} kB PNG/view, "
          f"client write {m['client_write_s_per_view'] * 1e3:.2f} ms/view; fit: "
          f"{m['fit_compute_s']:.1f} s task compute, {m['stack_bytes_shuffled'] / 1e6:.0f} MB "
          f"stack pieces, {m['fit_serial_s']:.1f} s client-serial; {m['gbps']:g} Gb/s links")
    print(f"{'machines (2 threads each)':<28}{'render s':>10}{'fit s':>8}")
    for row in m["rows"]:
        print(f"{row['machines']:<28}{row['render_s']:>10.1f}{row['fit_s']:>8.1f}")
    print(f"render is client-bound beyond {m['client_render_bound_s']:.1f} s")


if __name__ == "__main__":
    sys.exit(main())
