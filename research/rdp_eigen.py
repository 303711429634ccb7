"""Bit allocation for the eigenimages (issue 6 item 4b; docs/rate-distortion-packets.md).

    .venv/bin/python research/rdp_eigen.py MODEL.ecs TEST.cdb -o OUT.json [--views 60]
        [--budgets 0,0.05,0.1,0.2,0.4,0.8]

Component ``j`` (eigenvalue ``lambda_j``) quantized with step ``s_j`` adds, in expectation,
``lambda_j * s_j**2 / 12`` to the squared error of its cell summed over its ``d`` values
(independent rounding errors, scores of variance ``lambda_j``). `host.fit.quantize.allocate_bits`
gives each component ``b_j`` in 2..8 bits (``s_j = max|v_j| / (2**(b_j - 1) - 1)``) so that
the total added MSE per pixel value stays within a budget at the fewest bits. The levels are
still stored one per int8 byte (the device's format is unchanged); zstd's entropy coder turns
the smaller alphabets into fewer bytes. Also measured: the same levels nibble-packed (two per
byte) before zstd, to see what an explicit int4 layout would add.

Reported per budget: the eigenimages section's compressed bytes, the bit histogram, the
object PSNR/SSIM of held-out views (interpolated scores at the model's step) and the PSNR
between the int8 frames and the re-quantized ones (what the bit allocation alone costs).
The components are re-quantized from the image's int8 eigenimages (``scales * int8``), so the
8-bit row is the image itself.

Produces: docs/rate-distortion-packets.md, section 3 "Bit allocation for the eigenimages".
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import zstandard as zstd

sys.path.insert(0, str(Path(__file__).resolve().parent))

from rdp_common import Timer, case_parser, load_case, quality, save_json

from host.fit.quantize import QuantizedEigenspace, allocate_bits, quantize_components


def main(argv: list[str] | None = None) -> int:
    ap = case_parser(__doc__.splitlines()[0], views=60)
    ap.add_argument("--budgets", default="0,0.05,0.1,0.2,0.4,0.8,1.6")
    args = ap.parse_args(argv)
    t = Timer()
    case = load_case(args.model, args.test_db, views=args.views)
    model = case.model
    img = model.image
    lam = np.asarray(model.eigenvalues, np.float64)
    v = img.eigenimages.astype(np.float64) * img.scales[:, None].astype(np.float64)
    cctx = zstd.ZstdCompressor(level=3, write_content_size=True)
    ys = [(np.rint(model.scores(p, th) / model.score_step) * model.score_step).astype(np.float32)
          for p, th in zip(case.phi, case.theta)]
    base_frames = [model.reconstruct(y) for y in ys]
    result: dict = {"case": case.name, "views": case.n_views, "K": img.n_coefficients,
                    "cell_values": img.cell_values, "n_cells": img.n_cells, "rows": []}
    for budget in [float(b) for b in args.budgets.split(",")]:
        bits = allocate_bits(lam, np.abs(v).max(axis=1) if v.size else np.zeros(0),
                             n_cells=img.n_cells, mse_budget=budget)
        e, s = quantize_components(v, bits=bits)
        q = QuantizedEigenspace(img.mean, e, s, img.n_components, img.image_shape,
                                img.cell_shape)
        rec = q.reconstructor()
        frames = [rec.update(y).copy() for y in ys]
        rec.close()
        qual = [quality(case.truth[i], frames[i], case.masks[i]) for i in range(case.n_views)]
        diff = np.mean([np.mean((f.astype(float) - b.astype(float)) ** 2)
                        for f, b in zip(frames, base_frames)])
        low = bits <= 4
        packed = e[low].astype(np.int16) & 0x0F
        if packed.shape[1] % 2:
            packed = np.pad(packed, ((0, 0), (0, 1)))
        nibbles = (packed[:, 0::2] | (packed[:, 1::2] << 4)).astype(np.uint8)
        row = {
            "budget": budget,
            "bits_hist": {int(b): int((bits == b).sum()) for b in np.unique(bits)},
            "mean_bits": float(bits.mean()) if bits.size else 0.0,
            "eigen_bytes": len(cctx.compress(e.tobytes())),
            "eigen_bytes_low_int8": len(cctx.compress(e[low].tobytes())) if low.any() else 0,
            "eigen_bytes_low_nibbles": len(cctx.compress(nibbles.tobytes())) if low.any() else 0,
            "predicted_added_mse": float(np.sum(
                lam * (s.astype(float) ** 2 - img.scales.astype(float) ** 2)) / 12.0
                / img.n_cells),
            "measured_mse_vs_int8": float(diff),
            "quality": {k: float(np.mean([o[k] for o in qual])) for k in qual[0]},
        }
        result["rows"].append(row)
        t.say(f"budget {budget}: {row}")
        save_json(args.output, result)
    t.say(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
