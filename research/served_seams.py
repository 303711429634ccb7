"""Do corrections of the device's own frame add cell seams, and what does smoothing them buy?

docs/design-notes.md, "Cell seams of a correction" (issue 23 item 6). For each model, on
random views, the
frames of the one served path (`host.evaluate.ServedFrames`: the own frame, at rest, while
moving at ``--stride``) computed with the device's seam smoothing off
(`Reconstructor.seam_strength` 0), and the same frames smoothed (`border_blend`, the device's
rule written out: the correction ``D = frame - own`` at the two pixels next to a border moves
by ``strength / 3`` of its jump towards the other side, only where the jump is below ``edge``
when given; the device ships strength `SEAM_STRENGTH`), against the ray-cast: object SSIM, FLIP and
PSNR, the blockiness figure (`host.evaluate.blockiness`) and the seam gradient error of
section 3 (the frame's finite differences against the ray-cast's, across borders over
inside). Then the cost on one core of a correction (`Reconstructor.correct`) with and without
the smoothing against a blend (`Reconstructor.update`) of the same image, in the same run,
and a check that the device's smoothing is `border_blend` bit for bit:

    .venv/bin/python research/served_seams.py /work/cache/db/tooth-256.ecs --views 12
    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 taskset -c 0 \\
        .venv/bin/python research/served_seams.py /work/cache/db/tooth-256.ecs --cost-only
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

#: (strength, edge) of the blends tried.
BLENDS = ((0.25, None), (0.5, None), (1.0, None), (0.5, 6.0))


def border_blend(frame: np.ndarray, own: np.ndarray, cell: tuple[int, int],
                 strength: float = 0.5, edge: float | None = None) -> np.ndarray:
    """``frame`` (the own frame ``own`` corrected) with the correction's jump at every cell
    border reduced, in the device's arithmetic (`Reconstructor.correct`): at the pixels
    ``p | q`` either side of a border, with the correction's jump ``J = (q - p) - (own_q -
    own_p)``, ``j = (J * W + 128) >> 8`` with ``W = round(256 * strength / 3)`` (zero where
    ``|J| >= edge``); ``p`` gains ``j``, ``q`` loses it (clipped). Vertical borders, then
    horizontal ones; a new array."""
    out = frame.copy()
    weight = round(256 * strength / 3)
    for axis, size in ((1, cell[1]), (0, cell[0])):
        b = np.arange(size, out.shape[axis], size)
        p = np.take(out, b - 1, axis=axis).astype(np.int32)
        q = np.take(out, b, axis=axis).astype(np.int32)
        jump = (q - p) - (np.take(own, b, axis=axis).astype(np.int32)
                          - np.take(own, b - 1, axis=axis))
        j = (jump * weight + 128) >> 8
        if edge is not None:
            j = np.where(np.abs(jump) < edge, j, 0)
        index: list = [slice(None)] * 3
        for at, value in ((b - 1, p + j), (b, q - j)):
            index[axis] = at
            out[tuple(index)] = np.clip(value, 0, 255).astype(np.uint8)
    return out


def seam_error(truth: np.ndarray, frame: np.ndarray, mask: np.ndarray,
               cell: tuple[int, int]) -> float:
    """Section 3's seam figure: |frame's finite difference - truth's| across borders over
    inside cells, on pairs of object pixels."""
    t, f = truth.astype(np.float32), frame.astype(np.float32)
    sums = np.zeros(4)
    for axis, size in ((1, cell[1]), (0, cell[0])):
        err = np.abs(np.diff(f, axis=axis) - np.diff(t, axis=axis)).mean(axis=2)
        border = (np.arange(err.shape[axis]) + 1) % size == 0
        border = border[None, :] if axis == 1 else border[:, None]
        both = (mask[:, 1:] & mask[:, :-1]) if axis == 1 else (mask[1:] & mask[:-1])
        sums += [err[both & border].sum(), (both & border).sum(),
                 err[both & ~border].sum(), (both & ~border).sum()]
    return float((sums[0] / sums[1]) / (sums[2] / sums[3]))


def quality(path: str, views: int, stride: int) -> None:
    from host.evaluate import ServedFrames, alpha_object_mask, blockiness, compare_images
    from host.fit.model import HostModel
    from host.render.camera import parse_view_set
    from host.render.settings import RenderSettings, ViewRenderer

    model = HostModel.load(path)
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what=path))
    served = ServedFrames(model, scene)
    served.own.own.reconstructor.seam_strength = 0.0  # as computed; smoothed below
    served.set_stride(stride)
    cell = tuple(model.image.cell_shape)
    rows: dict[str, list] = {}
    for v in parse_view_set(f"random:{views}:23").views:
        truth, alpha = scene.render(v.phi_deg, v.theta_deg)
        mask = alpha_object_mask(alpha)
        own = served.own_frame(v.phi_deg, v.theta_deg)
        frames = {"ray-cast": truth, "own frame": own}
        for kind, (frame, _) in (("at rest", served.at_rest(v.phi_deg, v.theta_deg)),
                                 (f"moving s{stride}", served.moving(v.phi_deg, v.theta_deg))):
            frames[kind] = frame
            for strength, edge in BLENDS:
                name = f"{kind} + blend {strength:g}" + (f" edge {edge:g}" if edge else "")
                frames[name] = border_blend(frame, own, cell, strength, edge)
        for name, frame in frames.items():
            c = compare_images(truth, frame, mask=mask)
            rows.setdefault(name, []).append(
                (c.ssim_object, c.flip_object, c.psnr_object, blockiness(frame, cell, mask),
                 seam_error(truth, frame, mask, cell) if name != "ray-cast" else 1.0))
    print(f"\n{path}: {views} views, cells {cell[0]}\n")
    print("| frame | SSIM obj | FLIP obj | PSNR obj | blockiness | seam gradient error |")
    print("|---|---|---|---|---|---|")
    for name, values in rows.items():
        a = np.array(values, dtype=np.float64)
        m = [float(np.mean(c[np.isfinite(c)])) if np.isfinite(c).any() else math.nan
             for c in a.T]  # the ray-cast's own PSNR is infinite
        print(f"| {name} | {m[0]:.4f} | {m[1]:.4f} | {m[2]:.2f} | {m[3]:.3f} | {m[4]:.3f} |")


def cost(path: str, repeat: int = 11, rounds: int = 5) -> None:
    from device_runtime.reconstruct import SEAM_STRENGTH, Reconstructor
    from protocol.image import read_image

    image = read_image(path)
    rec = Reconstructor.from_image(image, threads=1)
    rng = np.random.default_rng(0)
    ys = [rng.normal(0, 30, image.n_coefficients).astype(np.float32) for _ in range(4)]
    d = rng.normal(0, 5, image.n_coefficients).astype(np.float32)
    own = rec.update(ys[0]).copy()
    cell = tuple(image.cell_shape)
    rec.seam_strength = 0.0
    sharp = rec.correct(d, own).copy()
    rec.seam_strength = SEAM_STRENGTH
    same = np.array_equal(rec.correct(d, own), border_blend(sharp, own, cell, SEAM_STRENGTH))

    def correct(strength: float) -> np.ndarray:
        rec.seam_strength = strength
        return rec.correct(d, own)

    ops = {"blend": lambda i: rec.update(ys[i % 4]), "correct": lambda i: correct(0.0),
           "smoothed": lambda i: correct(SEAM_STRENGTH)}
    times: dict[str, list[float]] = {name: [] for name in ops}
    for _round in range(rounds):  # blocks in turn: a change of load hits all alike
        for name, op in ops.items():
            runs = []
            for i in range(repeat):
                t0 = time.perf_counter()
                op(i)
                runs.append(time.perf_counter() - t0)
            times[name].append(float(np.median(runs)))
    # the least median of the rounds: the shared machine's load only ever adds
    med = {k: min(v) for k, v in times.items()}
    print(f"{path}: blend {med['blend'] * 1e3:.2f} ms, correct without smoothing "
          f"{med['correct'] * 1e3:.2f} ms ({med['correct'] / med['blend']:.2f} blends), "
          f"smoothed {med['smoothed'] * 1e3:.2f} ms ({med['smoothed'] / med['blend']:.2f} "
          f"blends); the device's smoothing is border_blend bit for bit: {same}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--stride", type=int, default=2, help="the moving frames' stride")
    parser.add_argument("--cost-only", action="store_true")
    args = parser.parse_args(argv)
    for path in args.models:
        if not args.cost_only:
            quality(path, args.views, args.stride)
    for path in args.models:
        cost(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
