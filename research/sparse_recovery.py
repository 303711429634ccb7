"""Sparse ray-cast recovery on held-out views (docs/design-notes.md, "Sparse ray-casts
while moving", issue 13).

For each fitted model (``.ecs`` whose render settings name the volume), on random
off-grid views, every frame is the device's reconstruction of quantized scores (the
model's step, water-filled, as `serve` sends them) and is compared with the full ray-cast by
object SSIM (`host.evaluate.structural_similarity` over the pixels with alpha >=
`OBJECT_ALPHA_MIN`):

``interpolated``
    The interpolated scores (what `serve` streams while the view moves).
``sparse s=S``
    `host.fit.recover.SparseRecovery` from a strided ray-cast (every S-th row and column, offset
    (0, 0); `Renderer.render_pixels`), the interpolated scores as the prior, for each λ given.
``projection``
    `HostModel.project` of the full ray-cast (the oracle; `serve --scores render`).
``progressive s=P after k``
    `host.fit.recover.ProgressiveRecovery` of a resting view: k successive frames ray-cast the
    first k offsets of stride P (`offset_order`) and accumulate them (the samples are cut
    from the full ray-cast, which they equal bit for bit); after P*P frames every pixel
    is known.

``orbit s=S prior=interpolated|previous`` (``--orbit N``)
    A drag: N frames along phi at ``--orbit-step`` degrees per frame (theta 17.5, between
    grid rows), each a stride-S sparse ray-cast at the next offset of `offset_order` (so a
    slow drag sees every pixel over S*S frames), the prior being the interpolated scores or
    the previous frame's recovered scores.

Timings on this machine, each the fastest of several runs (on a machine shared with other
work, the best estimate of the uncontended time): the full ray-cast and each sparse
ray-cast of one view (phi 33, theta 10), interleaved ``--repeats`` times, and their ratio;
one recovery with the pattern's factor cached and one progressive step (over the views);
the factor's one-off build (a single run).

Usage::

    .venv/bin/python research/sparse_recovery.py MODEL.ecs [MODEL.ecs ...] \\
        [--views 10] [--seed 1] [--strides 2,4,8] [--lambdas 100] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from host.evaluate import structural_similarity
from host.fit.model import HostModel
from host.fit.recover import (
    DEFAULT_LAMBDA,
    ProgressiveRecovery,
    SamplePattern,
    SparseRecovery,
    offset_order,
    sparse_samples,
)
from host.render.camera import parse_view_set
from host.render.settings import OBJECT_ALPHA_MIN, RenderSettings, ViewRenderer


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def measure(path: Path, *, views: int, seed: int, strides: list[int],
            lambdas: list[float], progressive: int, repeats: int = 9) -> dict:
    """Object SSIM and timings of one model (see the module docstring)."""
    model = HostModel.load(path)
    settings = RenderSettings.from_record(model.render_settings, what=str(path))
    renderer = ViewRenderer.open(settings, what=str(path))
    h, w = renderer.image_shape
    recoveries = {lam: SparseRecovery(model, lam=lam) for lam in lambdas}
    patterns = {s: SamplePattern.strided(w, h, s) for s in strides}
    factor_s: dict[str, float] = {}
    for lam, rec in recoveries.items():
        for s, p in patterns.items():
            t0 = time.perf_counter()
            rec.factor(p)
            factor_s[f"s={s} lam={lam:g}"] = time.perf_counter() - t0
    renderer.render(0.0, 0.0)  # warm the kernels
    sparse_samples(renderer, 0.0, 0.0, patterns[strides[0]])

    def frame(scores: np.ndarray) -> np.ndarray:
        return model.reconstruct(model.quantize(scores))

    ssim: dict[str, list[float]] = {}
    times: dict[str, list[float]] = {}

    def add(table: dict, key: str, value: float) -> None:
        table.setdefault(key, []).append(value)

    for view in parse_view_set(f"random:{views}:{seed}"):
        phi, theta = view.phi_deg, view.theta_deg
        t0 = time.perf_counter()
        truth, alpha = renderer.render(phi, theta)
        add(times, "full_render_s", time.perf_counter() - t0)
        mask = alpha >= OBJECT_ALPHA_MIN

        def score(key: str, scores: np.ndarray, truth: np.ndarray = truth,
                  mask: np.ndarray = mask) -> None:
            add(ssim, key, structural_similarity(truth, frame(scores), mask=mask))

        prior = model.scores(phi, theta)
        score("interpolated", prior)
        score("projection", model.project(truth))
        for s, pattern in patterns.items():
            t0 = time.perf_counter()
            samples, _ = sparse_samples(renderer, phi, theta, pattern)
            add(times, f"sparse_render_s s={s}", time.perf_counter() - t0)
            for lam, rec in recoveries.items():
                t0 = time.perf_counter()
                scores = rec.recover(pattern, samples, prior)
                add(times, f"recover_s s={s} lam={lam:g}", time.perf_counter() - t0)
                score(f"sparse s={s} lam={lam:g}", scores)
        if progressive:
            prog = ProgressiveRecovery(recoveries[lambdas[0]], progressive)
            prog.reset(prior)
            n = progressive * progressive
            marks = {1, 2, 4, n // 4, n // 2, n} - {0}
            for k, offset in enumerate(prog.order, start=1):
                p = prog.pattern(offset)
                t0 = time.perf_counter()
                scores = prog.add(offset, truth[p.rows, p.cols])
                add(times, f"progressive_add_s s={progressive}", time.perf_counter() - t0)
                if k in marks:
                    score(f"progressive s={progressive} after {k}", scores)
    # render timings: one view, full and sparse ray-casts interleaved, the fastest of each
    # (the per-view times above differ by view and by whatever else runs on the machine)
    del times["full_render_s"]
    for s in strides:
        del times[f"sparse_render_s s={s}"]
    camera = settings.camera(33.0, 10.0)
    for _ in range(repeats):
        t0 = time.perf_counter()
        renderer.renderer.render(camera, w, h)
        add(times, "full_render_s", time.perf_counter() - t0)
        for s, p in patterns.items():
            t0 = time.perf_counter()
            renderer.renderer.render_pixels(camera, w, h, p.rows, p.cols)
            add(times, f"sparse_render_s s={s}", time.perf_counter() - t0)
    medians = {k: min(v) for k, v in times.items()}
    full = medians["full_render_s"]
    for s in strides:
        medians[f"sparse_ratio s={s}"] = medians[f"sparse_render_s s={s}"] / full
    return {
        "model": str(path),
        "image_shape": [h, w],
        "cell_shape": list(model.image.cell_shape),
        "threshold": model.threshold,
        "n_coefficients": int(model.image.n_coefficients),
        "views": views,
        "seed": seed,
        "ssim_object": {k: float(np.mean(v)) for k, v in ssim.items()},
        "timing_min_s": medians,
        "factor_build_s": factor_s,
    }


def measure_orbit(path: Path, *, frames: int, step_deg: float, strides: list[int],
                  lam: float) -> dict:
    """Mean object SSIM along a drag (see ``orbit`` in the module docstring)."""
    model = HostModel.load(path)
    settings = RenderSettings.from_record(model.render_settings, what=str(path))
    renderer = ViewRenderer.open(settings, what=str(path))
    h, w = renderer.image_shape
    rec = SparseRecovery(model, lam=lam)
    out: dict[str, list[float]] = {}
    path_views = [(20.0 + k * step_deg, 17.5) for k in range(frames)]
    truths = []
    for phi, theta in path_views:
        truth, alpha = renderer.render(phi, theta)
        truths.append((truth, alpha >= OBJECT_ALPHA_MIN))
    for phi_theta, (truth, mask) in zip(path_views, truths):
        out.setdefault("interpolated", []).append(structural_similarity(
            truth, model.reconstruct(model.quantize(model.scores(*phi_theta))), mask=mask))
        out.setdefault("projection", []).append(structural_similarity(
            truth, model.reconstruct(model.quantize(model.project(truth))), mask=mask))
    for s in strides:
        order = offset_order(s)
        for mode in ("interpolated", "previous"):
            previous = None
            for k, (phi_theta, (truth, mask)) in enumerate(zip(path_views, truths)):
                pattern = SamplePattern.strided(w, h, s, order[k % len(order)])
                prior = model.scores(*phi_theta) if mode == "interpolated" or previous is None \
                    else previous
                scores = rec.recover(pattern, truth[pattern.rows, pattern.cols], prior)
                previous = scores
                out.setdefault(f"orbit s={s} prior={mode}", []).append(structural_similarity(
                    truth, model.reconstruct(model.quantize(scores)), mask=mask))
    return {k: float(np.mean(v)) for k, v in out.items()}


def table(results: list[dict], strides: list[int], lambdas: list[float]) -> str:
    """The markdown table of object SSIM (one column per model) and the timing rows."""
    names = [Path(r["model"]).stem + (f" (T {r['threshold']:g})" if r["threshold"] else "")
             for r in results]
    lines = ["| | " + " | ".join(names) + " |", "|---|" + "---|" * len(results)]

    def row(label: str, values: list[str]) -> None:
        lines.append(f"| {label} | " + " | ".join(values) + " |")

    row("interpolated scores", [f"{r['ssim_object']['interpolated']:.3f}" for r in results])
    for s in strides:
        for lam in lambdas:
            key = f"sparse s={s} lam={lam:g}"
            lam_txt = f", λ {lam:g}" if len(lambdas) > 1 else ""
            row(f"sparse ray-cast, s = {s} (1/{s * s} of the rays{lam_txt})",
                [f"{r['ssim_object'][key]:.3f}" for r in results])
    prog = sorted({k for r in results for k in r["ssim_object"] if k.startswith("progressive")},
                  key=lambda k: int(k.rsplit(" ", 1)[1]))
    for key in prog:
        stride, k = key.split()[1][2:], key.rsplit(" ", 1)[1]
        row(f"resting view, stride {stride} accumulated over {k} frame{'s' * (k != '1')}",
            [f"{r['ssim_object'].get(key, float('nan')):.3f}" for r in results])
    row("full ray-cast projection", [f"{r['ssim_object']['projection']:.3f}" for r in results])
    row("full ray-cast, ms", [f"{1e3 * r['timing_min_s']['full_render_s']:.0f}"
                               for r in results])
    for s in strides:
        row(f"sparse ray-cast s = {s}, ms (x full)", [
            f"{1e3 * r['timing_min_s'][f'sparse_render_s s={s}']:.1f} "
            f"({r['timing_min_s'][f'sparse_ratio s={s}']:.3f})" for r in results])
    for s in strides:
        for lam in lambdas:
            key = f"s={s} lam={lam:g}"
            row(f"recovery s = {s}{f', λ {lam:g}' if len(lambdas) > 1 else ''}, ms "
                "(factor build, s)", [
                    f"{1e3 * r['timing_min_s'][f'recover_s {key}']:.2f} "
                    f"({r['factor_build_s'][key]:.2f})" for r in results])
    if all("orbit" in r for r in results):
        for key in results[0]["orbit"]:
            label = {"interpolated": "drag: interpolated scores",
                     "projection": "drag: full ray-cast projection"}.get(key) or \
                f"drag: sparse {key.split()[1]}, prior = {key.split('=')[-1]} (offsets cycling)"
            row(label, [f"{r['orbit'][key]:.3f}" for r in results])
    if prog:
        stride = prog[0].split()[1][2:]
        row(f"accumulating one offset of stride {stride}, ms", [
            f"{1e3 * r['timing_min_s'][f'progressive_add_s s={stride}']:.1f}" for r in results])
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", type=Path, help="fitted .ecs models")
    parser.add_argument("--views", type=int, default=10, help="random held-out views")
    parser.add_argument("--seed", type=int, default=1, help="seed of the random views")
    parser.add_argument("--strides", type=_ints, default=[2, 4, 8])
    parser.add_argument("--lambdas", type=_floats, default=[DEFAULT_LAMBDA])
    parser.add_argument("--progressive", type=int, default=4,
                        help="stride of the resting-view accumulation (0: skip)")
    parser.add_argument("--orbit", type=int, default=0,
                        help="also measure a drag of this many frames (0: skip)")
    parser.add_argument("--orbit-step", type=float, default=3.0, help="degrees per frame")
    parser.add_argument("--repeats", type=int, default=9,
                        help="interleaved full/sparse ray-casts timed (the fastest counts)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    try:
        results = []
        for path in args.models:
            print(f"measuring {path} ...", file=sys.stderr, flush=True)
            results.append(measure(path, views=args.views, seed=args.seed,
                                   strides=args.strides, lambdas=args.lambdas,
                                   progressive=args.progressive, repeats=args.repeats))
        if args.orbit:
            for r in results:
                r["orbit"] = measure_orbit(Path(r["model"]), frames=args.orbit,
                                           step_deg=args.orbit_step, strides=args.strides,
                                           lam=args.lambdas[0])
    except Exception as exc:  # one line for the user, not a traceback
        print(f"sparse_recovery: {exc}", file=sys.stderr)
        return 1
    print(table(results, args.strides, args.lambdas))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
