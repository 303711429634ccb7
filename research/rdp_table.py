"""Standalone score-table experiments (issue 6 item 4a; docs/rate-distortion-packets.md).

    .venv/bin/python research/rdp_table.py MODEL.ecs TEST.cdb -o OUT.json [--views 100]
        [--factors 1,2,4,8,16] [--train-db TRAIN.cdb --webp-qualities 5,20,50,80]

The training views' scores (the annex's float table, ``n_views x K``) are what a standalone
device interpolates. Coded here, each zstd level 3 over int16/varints:

* ``int16`` -- ``rint(T / s)`` at the score step ``s`` (what ``fit --standalone`` stored so
  far);
* ``standalone_delta`` / ``standalone_plain_waterfilled`` -- what ``fit --standalone`` now
  writes (`host.fit.model.add_standalone_table`): water-filled columns zeroed (the components
  packets send as 0), then either the delta-coded section (differences along theta rings,
  zigzag, byte planes) or the plain int16 table;
* ``phidelta`` -- the same integers, differenced along phi within each theta ring (the first
  view of a ring is kept), zigzag varints, component-major (lossless: the device restores the
  int16 table with a cumulative sum);
* the same at coarser table steps (``factor x s``): a lossy knob;
* ``dct`` -- an orthonormal DCT-II along phi per ring and component, coefficients quantized at
  the step (same rounding noise per coefficient as the table), varints, zstd.

Quality: the held-out views' scores are interpolated from each decoded table, quantized at the
packet step and reconstructed through the device code; object PSNR/SSIM against the ray-cast.
With ``--train-db`` the WebP image database is measured too: every training view as WebP at
each quality, novel views blended from the decoded training images with the model's own
interpolation weights (object SSIM), and the database's total bytes.

Produces: docs/rate-distortion-packets.md, section 2 "Standalone table" (and the WebP
database rows of section 4).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import zstandard as zstd

sys.path.insert(0, str(Path(__file__).resolve().parent))

from rdp_common import Timer, case_parser, load_case, quality, save_json, webp_db_sweep

from host.fit.model import add_standalone_table
from protocol.scores import zigzag_varints

LEVEL = 3


def ring_layout(phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(n_theta, n_phi) view indices of a full grid, phi ascending in each ring."""
    thetas = np.unique(np.round(theta, 6))
    rows = []
    for th in thetas:
        idx = np.flatnonzero(np.isclose(theta, th))
        rows.append(idx[np.argsort(np.mod(phi[idx], 360.0))])
    if len({len(r) for r in rows}) != 1:
        raise SystemExit("not a full phi x theta grid")
    return np.stack(rows)


def zsize(data: bytes) -> int:
    return len(zstd.ZstdCompressor(level=LEVEL, write_content_size=True).compress(data))


def dct_matrix(n: int) -> np.ndarray:
    k = np.arange(n)[:, None]
    x = np.arange(n)[None, :]
    m = np.cos(np.pi * (x + 0.5) * k / n) * np.sqrt(2.0 / n)
    m[0] /= np.sqrt(2.0)
    return m  # orthonormal: m @ m.T == I


def main(argv: list[str] | None = None) -> int:
    ap = case_parser(__doc__.splitlines()[0], views=100)
    ap.add_argument("--factors", default="1,2,4,8,16")
    ap.add_argument("--train-db", default=None)
    ap.add_argument("--webp-qualities", default="5,20,50,80")
    args = ap.parse_args(argv)
    t = Timer()
    case = load_case(args.model, args.test_db, views=args.views)
    model = case.model
    table = np.asarray(model.training_scores, np.float64)
    views = model.image.views
    grid = ring_layout(np.asarray(views["phi_deg"]), np.asarray(views["theta_deg"]))
    step = model.score_step
    interp = model.interpolator
    weights = [interp.weights(p, th) for p, th in zip(case.phi, case.theta)]

    def evaluate(tab: np.ndarray) -> dict[str, float]:
        tab32 = tab.astype(np.float32)
        out = []
        for i, (idx, w) in enumerate(weights):
            y = (w.astype(np.float32)[:, None] * tab32[idx]).sum(axis=0)
            yq = (np.rint(y / step) * step).astype(np.float32)
            out.append(quality(case.truth[i], model.reconstruct(yq), case.masks[i]))
        return {k: float(np.mean([o[k] for o in out])) for k in out[0]}

    result: dict = {"case": case.name, "views": case.n_views, "K": int(table.shape[1]),
                    "n_training_views": int(table.shape[0]), "step": step,
                    "grid": list(grid.shape), "variants": []}
    sections = _section_sizes(args.model)
    result["image_sections"] = sections
    t.say(f"{case.name}: table {table.shape}, grid {grid.shape}, step {step:.4g}, "
          f"sections {sections}")
    result["float_table"] = evaluate(table)
    t.say(f"float table: {result['float_table']}")
    dct = dct_matrix(grid.shape[1])
    for factor in [float(v) for v in args.factors.split(",")]:
        s = step * factor
        q = np.rint(table / s).astype(np.int64)
        q16 = np.clip(q, -32768, 32767).astype("<i2")
        ringed = q[grid]  # (n_theta, n_phi, K)
        d = ringed.copy()
        d[:, 1:] -= ringed[:, :-1]
        comp_major = np.ascontiguousarray(d.transpose(2, 0, 1))
        lam = np.asarray(model.eigenvalues, np.float64)
        qw = q.copy()
        qw[:, lam < step * step / 12.0] = 0  # water-filled columns (the packets' zeros)
        shipped = {}
        for delta in (True, False):  # what fit --standalone writes (add_standalone_table)
            image = dataclasses.replace(model.image, sections={}, annex=None)
            info = add_standalone_table(image, table, eigenvalues=model.eigenvalues,
                                        table_step=s, delta=delta)
            shipped[delta] = zsize(image.sections[info["section"]].tobytes())
        sizes = {
            "int16": zsize(q16.tobytes()),
            "standalone_delta": shipped[True],
            "standalone_plain_waterfilled": shipped[False],
            "phidelta": zsize(zigzag_varints(comp_major.ravel())),
            "phidelta_viewmajor": zsize(zigzag_varints(d.ravel())),
        }
        qual = evaluate(q * s)
        qual_w = evaluate(qw * s)
        result["variants"].append({"kind": "table_waterfill", "factor": factor,
                                   "table_step": s, "quality": qual_w})
        result["variants"].append({"kind": "table", "factor": factor, "table_step": s,
                                   "bytes": sizes, "quality": qual})
        t.say(f"table x{factor:g}: {sizes} {qual} waterfilled {qual_w}")
        # DCT along phi per ring, coefficients at step s
        coef = np.einsum("kp,tpc->tkc", dct, table[grid])
        cq = np.rint(coef / s).astype(np.int64)
        rec = np.einsum("kp,tkc->tpc", dct, cq * s)
        tab = np.empty_like(table)
        tab[grid] = rec
        size = zsize(zigzag_varints(np.ascontiguousarray(cq.transpose(2, 0, 1)).ravel()))
        qual = evaluate(tab)
        result["variants"].append({"kind": "dct", "factor": factor, "table_step": s,
                                   "bytes": {"dct": size}, "quality": qual})
        t.say(f"dct x{factor:g}: {size} {qual}")
        save_json(args.output, result)
    if args.train_db:
        result["webp_db"] = webp_db_sweep(args.train_db, case, weights,
                                     [int(v) for v in args.webp_qualities.split(",")], t)
    save_json(args.output, result)
    t.say(f"wrote {args.output}")
    return 0


def _section_sizes(path: str) -> dict[str, int]:
    """Compressed bytes of each device section and the device image's size."""
    from protocol.image import image_size, read_manifest

    with open(path, "rb") as f:
        head = f.read(32)
    manifest = read_manifest(path)
    out = {s["name"]: int(s["size"]) for s in manifest["sections"]}
    out["device_image"] = image_size(head)
    return out


if __name__ == "__main__":
    raise SystemExit(main())
