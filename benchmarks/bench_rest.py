"""Refinement layers at rest: their bytes against the codecs, and what applying one costs the
device against its blend, on one core.

For each shared database (``--cache``: ``NAME-SIZE.cdb``, ready when ``NAME-SIZE.done``
exists; ``eigencast fit`` with the defaults into ``--work`` unless ``NAME-SIZE.ecs`` is
there) and ``--views`` random views (``random:N:SEED``), the resting chain ``serve`` sends
is planned exactly as ``serve`` plans it (`host.evaluate.ServedFrames.rest` with
``serve``'s `RestPlanner`: the view's full ray-cast, the device's own frame, that frame with
the complete correction), then:

**bytes** (`host.evaluate.resting.measure_rest`): per step (the own frame, the correction
when the plan sends it, each lossy layer, the exact layer) its object SSIM (mask: the
ray-cast's alpha) and cumulative bytes against the smallest WebP (method 6), AVIF (speed 4)
and JPEG of the ray-cast reaching the same object SSIM, and the exact step against the
ray-cast's WebP lossless and optimized PNG files. The layers are planned unsplit (packets up
to ``--packet-bytes``, default the planner's 64 KiB: one chunk at 256) and, for the chunk
columns, as ``serve`` splits each layer's file on each ``--splits`` packet size (2880: a
115200-baud line's quarter second; 16288: a TCP device's default 16 KiB frame); the exact
layer of a frame over `protocol.layers.STRIP_PIXELS` goes in strips, as ``serve`` sends it
to a device that reads them.

**device**: on one core (the process pins itself to ``--cpu``, ``OPENBLAS_NUM_THREADS=1``,
``Reconstructor(threads=1)``), each layer's packets taken as the device's scheduler takes
them (`protocol.layers.decode_layer` and `LayerAssembly.add` per chunk; the whole file's
`device_runtime.layers.decode_file` + `RestFrame.apply` with its last chunk), interleaved
with the device's blend (`Reconstructor.update` of a moved view's interpolated scores,
`StandaloneScores`); thread CPU time, median of ``--repeat``; the ratio layer / blend per
layer (all its chunks and strips) and per *tick* (its costliest chunk: the one whose file
decodes, which the device's scheduler takes in one display tick).

Usage (one command; the figures of BENCHMARKS.md "Refinement layers at rest")::

    nice .venv/bin/python benchmarks/bench_rest.py [--cache /work/cache] \\
        [--work bench-out/rest] [--volumes tooth,head,vismale_head,engine] [--sizes 256,512] \\
        [--views 12] [--splits 2880,16288] [--targets 0.95] [--repeat 7] [--write FILE.md] \
        [--json FILE]

Volumes whose database is not ready are skipped with one line.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: the device's one core
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: The issue's bars: from object SSIM 0.9 up at most 1.0x WebP and 1.1x AVIF; the first
#: step past the correction at most 0.8x WebP where the eigenspace is good; to exact at most
#: 1.3x WebP lossless, the exact layer alone at most 1x; a layer at most one blend.
BARS = {"x_webp": 1.0, "x_avif": 1.1, "first_x_webp": 0.8, "exact_x_wll": 1.3,
        "layer_x_wll": 1.0, "x_blend": 1.0}


def ensure_model(cache: Path, work: Path, name: str) -> Path | None:
    """``WORK/ecs/NAME.ecs``, fitted with the defaults from ``CACHE/NAME.cdb`` if missing;
    None when the database is not ready."""
    out = work / "ecs" / f"{name}.ecs"
    if out.exists():
        return out
    if not (cache / f"{name}.done").exists():
        print(f"skip {name}: database {cache / name}.cdb not ready", flush=True)
        return None
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp, fitcache = out.with_suffix(".tmp.ecs"), out.with_suffix(".fitcache")
    t0 = time.perf_counter()
    exe = Path(sys.executable).with_name("eigencast")
    code = subprocess.run([str(exe), "fit", str(cache / f"{name}.cdb"), "-o", str(tmp),
                           "--cache", str(fitcache)], stdout=subprocess.DEVNULL).returncode
    subprocess.run(["rm", "-rf", str(fitcache)], check=False)
    if code:
        print(f"skip {name}: fit failed (exit {code})", flush=True)
        return None
    tmp.replace(out)
    print(f"  fitted {out.name} in {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def plan_views(path: Path, n_views: int, seed: int, packet_bytes: int,
               splits: list[int], targets: tuple[float, ...] | None = None) -> dict[str, Any]:
    """Plan and measure the resting chain of ``n_views`` views of the model at ``path``
    (``targets``: the lossy layers' object SSIMs, default serve's)."""
    from host.evaluate import ServedFrames, alpha_object_mask
    from host.evaluate.resting import measure_rest, rest_record
    from host.fit.model import HostModel
    from host.link.layers import RestPlanner
    from host.render.camera import parse_view_set
    from host.render.settings import RenderSettings, ViewRenderer

    model = HostModel.load(path)
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what=str(path)))
    chosen = {} if targets is None else {"targets": targets}
    planner = RestPlanner(model.digest, max_packet_bytes=packet_bytes, **chosen)
    split_planners = {s: RestPlanner(model.digest, max_packet_bytes=s, **chosen)
                      for s in splits}
    served = ServedFrames(model, scene, planner=planner)
    views = parse_view_set(f"random:{n_views}:{seed}").views
    records, chains, split_records = [], [], []
    hints: dict[str, int] = {}
    t_plan, t_measure, t_split = [], 0.0, 0.0
    for k, v in enumerate(views):
        t0 = time.perf_counter()
        served.planner = planner
        rest = served.rest(v.phi_deg, v.theta_deg)
        assert rest is not None
        t1 = time.perf_counter()
        _, alpha = scene.render(*rest.view)
        measured = measure_rest(rest.truth, alpha_object_mask(alpha),
                                [s.frame for s in rest.steps], [s.kind for s in rest.steps],
                                codecs=True, hints=hints)
        hints.update(measured["hints"])
        t2 = time.perf_counter()
        records.append(rest_record(rest, measured))
        chains.append(rest)
        splits_of_view = {}
        for size, p in split_planners.items():  # the same view, as serve splits it
            served.planner = p
            other = served.rest(v.phi_deg, v.theta_deg)
            splits_of_view[size] = other
        split_records.append(splits_of_view)
        t_plan.append(t1 - t0)  # (the view's full ray-cast included)
        t_split += time.perf_counter() - t2
        t_measure += t2 - t1
        last = records[-1]["steps"]
        print(f"    view {k + 1}/{len(views)} ({rest.view[0]:.1f}, {rest.view[1]:.1f}): "
              + " > ".join(f"{s['kind']} {s['ssim_object']:.3f}@{s['bytes']}" for s in last),
              flush=True)
    return {"model": model, "records": records, "chains": chains, "splits": split_records,
            "plan_s": float(np.median(t_plan)), "measure_s": t_measure, "split_s": t_split}


def _med(values: list[float]) -> float:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(vals)) if vals else float("nan")


def _worst(values: list[float]) -> float:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(max(vals)) if vals else float("nan")


def bytes_row(name: str, planned: dict[str, Any]) -> dict[str, Any]:
    """The bytes figures of one model (medians and worst over its views)."""
    from host.evaluate.resting import REST_BAR_SSIM, summarize_rest
    from protocol.layers import LAYER_HEADER_SIZE

    recs = planned["records"]
    summary = summarize_rest([{"rest": r} for r in recs])
    assert summary is not None
    stages = summary["stages"]
    first = [next((s for s in r["steps"] if s["kind"] == "layer"), None) for r in recs]
    first = [s for s in first if s is not None]

    def ratio(steps: list[dict], codec: str) -> list[float]:
        return [s["bytes"] / s["codecs"][codec]["bytes"] for s in steps
                if (s.get("codecs") or {}).get(codec)]

    exact = [r["steps"][-1] for r in recs if r["steps"][-1]["kind"] == "exact"]
    # the same ratios without the layers' 32-byte packet headers (a WebP file has none)
    bare = []
    for r in recs:
        headers = 0
        for s in r["steps"]:
            if s["kind"] in ("layer", "exact"):
                headers += LAYER_HEADER_SIZE * s["packets"]
            if (s["kind"] in ("correction", "layer") and (s.get("codecs") or {}).get("webp")
                    and s["ssim_object"] >= REST_BAR_SSIM):
                bare.append((s["bytes"] - headers) / s["codecs"]["webp"]["bytes"])
    row = {"name": name, "views": len(recs),
           "own_ssim": stages["own"]["ssim_object"],
           "corrections_sent": sum(not r["skip_correction"] for r in recs),
           "correction_bytes": _med([r["correction_bytes"] for r in recs]),
           "first_views": len(first),
           "first_bytes": _med([s["bytes"] for s in first]),
           "first_ssim": _med([s["ssim_object"] for s in first]),
           "first_residual": sum(bool(s["residual"]) for s in first),
           "first_x_webp": _med(ratio(first, "webp")),
           "first_x_webp_worst": _worst(ratio(first, "webp")),
           "first_x_avif": _med(ratio(first, "avif")),
           "first_x_avif_worst": _worst(ratio(first, "avif")),
           "bar_steps": summary[f"from_ssim_{REST_BAR_SSIM:g}"]["steps"],
           "bar_x_webp_worst": summary[f"from_ssim_{REST_BAR_SSIM:g}"]["x_webp"]["worst"],
           "bar_x_avif_worst": summary[f"from_ssim_{REST_BAR_SSIM:g}"]["x_avif"]["worst"],
           "exact_bytes": _med([s["bytes"] for s in exact]),
           "wll_bytes": _med([s["webp_lossless_bytes"] for s in exact]),
           "png_bytes": _med([s["png_bytes"] for s in exact]),
           "exact_x_wll": _med([s["bytes"] / s["webp_lossless_bytes"] for s in exact]),
           "exact_x_wll_worst": _worst([s["bytes"] / s["webp_lossless_bytes"] for s in exact]),
           "layer_x_wll": _med([s["step_bytes"] / s["webp_lossless_bytes"] for s in exact]),
           "layer_x_wll_worst": _worst([s["step_bytes"] / s["webp_lossless_bytes"]
                                        for s in exact]),
           "bar_x_webp_worst_bare": _worst(bare),
           "layer_minus_wll": _med([s["step_bytes"] - s["webp_lossless_bytes"]
                                    for s in exact]),
           "exact_codec": sorted({s["codec"] for s in exact}),
           "splits": {}}
    # views whose own frame already reaches the target: no lossy layer
    row["no_lossy_layer"] = sum(not any(s["kind"] == "layer" for s in rec["steps"])
                                for rec in recs)
    wll = [r["steps"][-1].get("webp_lossless_bytes") for r in recs]
    for size in (planned["splits"][0] if planned["splits"] else {}):
        chains = [views[size] for views in planned["splits"]]
        exact_ratio = [c.steps[-1].bytes / w for c, w in zip(chains, wll, strict=True) if w]
        whole = [c.steps[-1].bytes / r["steps"][-1]["bytes"] for c, r in
                 zip(chains, recs, strict=True)]
        strips = [len(c.steps[-1].packets) for c in chains]
        row["splits"][size] = {"exact_x_wll": _med(exact_ratio),
                               "exact_x_wll_worst": _worst(exact_ratio),
                               "x_unsplit": _med(whole), "exact_strips": _med(strips)}
    return row


def time_device(planned: dict[str, Any], cpu: int, repeat: int,
                splits: list[int]) -> dict[str, Any]:
    """Thread CPU time of the device applying each layer (and strip) against its blend, on
    CPU ``cpu`` alone."""
    from device_runtime.layers import RestFrame, decode_file
    from device_runtime.reconstruct import Reconstructor
    from device_runtime.standalone import StandaloneScores
    from protocol.layers import LayerAssembly, decode_layer

    os.sched_setaffinity(0, {cpu})
    model = planned["model"]
    image = model.image
    height, width = image.image_shape
    blend = Reconstructor.from_image(image, threads=1)
    standalone = StandaloneScores(image)
    chains = planned["chains"]
    moved = [standalone.scores(c.view[0] + d, c.view[1]) for c in chains for d in (3.0, 6.0)]
    blend.update(moved[0])  # page in

    def blend_s(i: int) -> float:
        t0 = time.thread_time()
        blend.update(moved[i % len(moved)])
        return time.thread_time() - t0

    def layer_s(packets: list[bytes], before: np.ndarray, view: tuple[float, float],
                base: int) -> list[float]:
        """Per chunk as the device's scheduler takes it: its header checked, joined, and
        the last one's file decoded and applied (one decode per layer)."""
        rest = RestFrame(view, base, before)
        assembly = LayerAssembly()
        out = []
        for packet in packets:
            t0 = time.thread_time()
            chunk = decode_layer(packet, image_digest=model.digest,
                                 image_shape=(height, width),
                                 max_packet_bytes=max(len(packet), 1 << 16))
            data = assembly.add(chunk)
            if data is not None:
                rest.apply(chunk, decode_file(data, chunk.codec, (height, width),
                                              row0=chunk.row0 if chunk.strip else None))
            out.append(time.thread_time() - t0)
        return out

    # what to time: (label, packets, the frame before, view, base frame) per layer
    jobs: list[tuple[str, list[bytes], np.ndarray, tuple[float, float], int]] = []
    sets = [("", chains)] + [(f"@{s}", [v[s] for v in planned["splits"]]) for s in splits]
    for label, chain_set in sets:
        for chain in chain_set:
            for k, step in enumerate(chain.steps):
                if step.kind not in ("layer", "exact"):
                    continue
                base = int.from_bytes(step.packets[0][8:12], "little")  # its base frame
                kind = "exact" if step.kind == "exact" else "lossy"
                jobs.append((kind + label, step.packets, chain.steps[k - 1].frame, chain.view,
                             base))
    blends: list[float] = []
    per_layer: dict[str, list[float]] = {}
    per_tick: dict[str, list[float]] = {}
    ratios: dict[str, list[float]] = {}
    for i, (label, packets, before, view, base) in enumerate(jobs):
        layer_runs, tick_runs, blend_runs = [], [], []
        for r in range(repeat):
            blend_runs.append(blend_s(i * repeat + r))
            ticks = layer_s(packets, before, view, base)
            layer_runs.append(sum(ticks))
            tick_runs.append(max(ticks))
        b = float(np.median(blend_runs))
        blends += blend_runs
        per_layer.setdefault(label, []).append(float(np.median(layer_runs)))
        per_tick.setdefault(label, []).append(float(np.median(tick_runs)))
        ratios.setdefault(label, []).append(float(np.median(layer_runs)) / b)
        ratios.setdefault(label + " tick", []).append(float(np.median(tick_runs)) / b)
    return {"blend_ms": 1e3 * float(np.median(blends)),
            "layer_ms": {k: 1e3 * _med(v) for k, v in per_layer.items()},
            "tick_ms": {k: 1e3 * _med(v) for k, v in per_tick.items()},
            "x_blend": {k: _med(v) for k, v in ratios.items()},
            "x_blend_worst": {k: _worst(v) for k, v in ratios.items()}}


def _f(v: Any, d: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{d}f}"


def bytes_table(rows: list[dict], splits: list[int]) -> str:
    head = ("| image | views | own SSIM | correction sent (B) | first layer: SSIM @ B "
            "(residual) | first /WebP | first /AVIF | from 0.9 worst /WebP, /AVIF (/WebP "
            "without layer headers) | exact B (WebP lossless, PNG) | exact /WLL | exact layer "
            "/WLL (- WLL B) | "
            + " | ".join(f"chunks of {s} B: exact /WLL (chunks)" for s in splits) + " |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        split_cells = [f"{_f(c['exact_x_wll'])} ({_f(c['exact_x_wll_worst'])}; "
                       f"{c['exact_strips']:.0f})" for c in
                       (r["splits"][s] for s in splits if s in r["splits"])]
        lines.append(
            f"| {r['name']} | {r['views']} | {_f(r['own_ssim'], 3)} | {r['corrections_sent']} "
            f"({r['correction_bytes']:.0f}) | {_f(r['first_ssim'], 3)} @ {r['first_bytes']:.0f}"
            f" ({r['first_residual']}/{r['first_views']}) | {_f(r['first_x_webp'])} "
            f"({_f(r['first_x_webp_worst'])}) | {_f(r['first_x_avif'])} "
            f"({_f(r['first_x_avif_worst'])}) | {_f(r['bar_x_webp_worst'])}, "
            f"{_f(r['bar_x_avif_worst'])} ({_f(r['bar_x_webp_worst_bare'])}; "
            f"{r['bar_steps']} steps) | {r['exact_bytes']:.0f} "
            f"({r['wll_bytes']:.0f}, {r['png_bytes']:.0f}) | {_f(r['exact_x_wll'])} "
            f"({_f(r['exact_x_wll_worst'])}) | {_f(r['layer_x_wll'], 3)} "
            f"({_f(r['layer_x_wll_worst'], 3)}; {r['layer_minus_wll']:+.0f} B) | "
            + " | ".join(split_cells) + " |")
    return "\n".join(lines)


def device_table(rows: list[dict], splits: list[int]) -> str:
    labels = ["lossy", "exact"] + [f"{k}@{s}" for s in splits for k in ("lossy", "exact")]
    head = ("| image | blend ms | " + " | ".join(
        f"{lab}: ms (x blend, worst; tick x blend worst)" for lab in labels) + " |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        d = r["device"]
        cells = []
        for lab in labels:
            if lab not in d["layer_ms"]:
                cells.append("-")
                continue
            cells.append(f"{d['layer_ms'][lab]:.2f} ({_f(d['x_blend'][lab])}, "
                         f"{_f(d['x_blend_worst'][lab])}; "
                         f"{_f(d['x_blend_worst'][lab + ' tick'])})")
        lines.append(f"| {r['name']} | {d['blend_ms']:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdicts(rows: list[dict]) -> list[str]:
    """Each bar of the issue, per image: met or missed, with the number."""
    out = []
    for r in rows:
        checks = [("from 0.9 worst /WebP <= 1.0", r["bar_x_webp_worst"], BARS["x_webp"]),
                  ("from 0.9 worst /AVIF <= 1.1", r["bar_x_avif_worst"], BARS["x_avif"]),
                  *((("first layer median /WebP <= 0.8 (the tooth at 256)", r["first_x_webp"],
                      BARS["first_x_webp"]),) if r["name"] == "tooth-256" else ()),
                  ("exact worst /WLL <= 1.3", r["exact_x_wll_worst"], BARS["exact_x_wll"]),
                  ("exact layer worst /WLL <= 1.0", r["layer_x_wll_worst"],
                   BARS["layer_x_wll"])]
        if np.isfinite(r["bar_x_webp_worst_bare"]):
            checks.insert(1, ("(without the layers' headers)", r["bar_x_webp_worst_bare"],
                              BARS["x_webp"]))
        if "device" in r:
            d = r["device"]
            for lab in ("lossy", "exact"):
                if lab in d["x_blend_worst"]:
                    checks.append((f"{lab} layer worst x blend <= 1", d["x_blend_worst"][lab],
                                   BARS["x_blend"]))
                    checks.append((f"{lab} tick worst x blend <= 1",
                                   d["x_blend_worst"][lab + " tick"], BARS["x_blend"]))
        parts = []
        for text, value, bar in checks:
            if value is None or not np.isfinite(value):
                parts.append(f"{text}: n/a")
            else:
                parts.append(f"{text}: {value:.3f} {'met' if value <= bar else 'MISSED'}")
        out.append(f"* {r['name']}: " + "; ".join(parts))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", type=Path, default=Path("/work/cache"))
    ap.add_argument("--work", type=Path, default=ROOT / "bench-out" / "rest")
    ap.add_argument("--volumes", default="tooth,head,vismale_head,engine")
    ap.add_argument("--sizes", default="256,512")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--packet-bytes", type=int, default=1 << 16,
                    help="the unsplit plan's largest packet (default: the planner's)")
    ap.add_argument("--splits", default="2880,16288",
                    help="packet sizes serve splits layers to (comma list; '' none)")
    ap.add_argument("--targets", default=None,
                    help="the lossy layers' object SSIMs, increasing (comma list; default "
                         "serve's)")
    ap.add_argument("--parts", default="bytes,device")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--cpu", type=int, default=0, help="the one core of the device timings")
    ap.add_argument("--write", type=Path, default=None, help="append the tables to this file")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    splits = [int(s) for s in args.splits.split(",") if s]
    targets = (None if args.targets is None
               else tuple(float(t) for t in args.targets.split(",")))
    parts = set(args.parts.split(","))
    rows = []
    t_start = time.perf_counter()
    load = os.getloadavg()[0]
    for size in [int(s) for s in args.sizes.split(",")]:
        for vol in args.volumes.split(","):
            name = f"{vol}-{size}"
            path = ensure_model(args.cache, args.work, name)
            if path is None:
                continue
            print(f"{name}: planning {args.views} views", flush=True)
            planned = plan_views(path, args.views, args.seed, args.packet_bytes, splits,
                                 targets)
            row = bytes_row(name, planned)
            row.update(plan_s=planned["plan_s"], measure_s=planned["measure_s"],
                       split_s=planned["split_s"])
            print(f"  ray-cast + plan per view: median {planned['plan_s']:.1f} s (wall, load "
                  f"{os.getloadavg()[0]:.1f})", flush=True)
            if "device" in parts:
                affinity = os.sched_getaffinity(0)
                try:
                    row["device"] = time_device(planned, args.cpu, args.repeat, splits)
                finally:
                    os.sched_setaffinity(0, affinity)
            row["records"] = planned["records"]
            rows.append(row)
            print(bytes_table([row], splits), flush=True)
            if "device" in row:
                print(device_table([row], splits), flush=True)
            print("\n".join(verdicts([row])) + "\n", flush=True)
    text = [f"bench_rest: {time.strftime('%Y-%m-%d')}, load {load:.1f} at the start, "
            f"{time.perf_counter() - t_start:.0f} s; views random:{args.views}:{args.seed}", "",
            "**bytes**", "", bytes_table(rows, splits)]
    if any("device" in r for r in rows):
        text += ["", "**device (one core, thread CPU time, median)**", "",
                 device_table([r for r in rows if "device" in r], splits)]
    text += ["", *verdicts(rows)]
    print("\n".join(text))
    if args.write:
        with open(args.write, "a") as fh:
            fh.write("\n" + "\n".join(text) + "\n")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
