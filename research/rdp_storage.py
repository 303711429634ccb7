"""Standalone device storage against quality (issue 6 item 4; docs/rate-distortion-packets.md).

    .venv/bin/python research/rdp_storage.py MODEL.ecs TEST.cdb -o OUT.json [--views 60]
        [--thresholds 0.9,0.95,0.98,0.99,0.995] [--bit-budgets 0,0.03,0.1]
        [--table-factors 1,2] [--tmp DIR]

For each threshold T (the model truncated through its annexed eigenvalues), eigenimage bit
budget (`host.fit.quantize.allocate_bits`, a fraction of the truncated model's residual MSE; the
rows are re-quantized from the image's int8 ones) and table step factor, a real standalone
image is written (`host.fit.model.add_standalone_table`, the smaller of the delta-coded and plain
table) and its device image size read back; quality is that of ``HostModel.view`` on the
held-out views (the frames a standalone device shows), object PSNR/SSIM against the
ray-casts. With ``--train-db`` the WebP image database it competes with is measured on the
same views (`research/rdp_table.py`'s ``_webp_db``).

Produces: docs/rate-distortion-packets.md, section 4 "Standalone device storage against the
WebP image database".
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from rdp_common import Timer, case_parser, load_case, quality, save_json, webp_db_sweep

from host.fit.model import HostModel, add_standalone_table
from host.fit.quantize import allocate_bits, quantize_components
from protocol.image import image_size, read_manifest, write_image


def residual(model: HostModel) -> float:
    img = model.image
    cell = np.repeat(np.arange(img.n_cells), np.asarray(img.n_components, np.int64))
    kept = np.bincount(cell, weights=model.eigenvalues, minlength=img.n_cells)
    return float(np.sum(model.total_variance - kept) / (img.n_cells * img.cell_values))


def main(argv: list[str] | None = None) -> int:
    ap = case_parser(__doc__.splitlines()[0], views=60)
    ap.add_argument("--thresholds", default="0.9,0.95,0.98,0.99,0.995")
    ap.add_argument("--bit-budgets", default="0,0.03,0.1")
    ap.add_argument("--table-factors", default="1,2")
    ap.add_argument("--tmp", default=None)
    ap.add_argument("--train-db", default=None,
                    help="also measure the WebP image database on the same views")
    ap.add_argument("--webp-qualities", default="1,5,20,50,80")
    args = ap.parse_args(argv)
    t = Timer()
    case = load_case(args.model, args.test_db, views=args.views)
    base = case.model
    rows = []
    fitted_t = base.threshold or 1.0
    tmp = Path(args.tmp or tempfile.mkdtemp(prefix="rdp_storage-"))
    tmp.mkdir(parents=True, exist_ok=True)
    for threshold in [float(v) for v in args.thresholds.split(",")]:
        if threshold > fitted_t:
            continue
        m = base.truncated(base.components_for(threshold=threshold))
        img = m.image
        v = img.eigenimages.astype(np.float64) * img.scales[:, None].astype(np.float64)
        res = residual(m)
        for budget in [float(b) for b in args.bit_budgets.split(",")]:
            bits = allocate_bits(m.eigenvalues, np.abs(v).max(axis=1), n_cells=img.n_cells,
                                 mse_budget=budget * res)
            e, s = quantize_components(v, bits=bits)
            for factor in [float(f) for f in args.table_factors.split(",")]:
                image = dataclasses.replace(img, eigenimages=e, scales=s, sections={},
                                            annex=None)
                info = add_standalone_table(image, m.training_scores,
                                            eigenvalues=m.eigenvalues,
                                            table_step=factor * m.score_step)
                path = tmp / "standalone.ecs"
                write_image(path, image, annex=m.annex())
                with open(path, "rb") as f:
                    device = image_size(f.read(32))
                sections = {x["name"]: int(x["size"]) for x in read_manifest(path)["sections"]}
                sa = HostModel.load(path)
                qual = [quality(case.truth[i], sa.view(case.phi[i], case.theta[i]),
                                case.masks[i]) for i in range(case.n_views)]
                row = {"threshold": threshold, "bit_budget": budget, "table_factor": factor,
                       "mean_components": float(np.mean(img.n_components)),
                       "K": img.n_coefficients, "mean_bits": float(bits.mean()),
                       "device_bytes": device, "sections": sections,
                       "table_section": info["section"],
                       "quality": {k: float(np.mean([q[k] for q in qual])) for k in qual[0]}}
                rows.append(row)
                t.say(f"T={threshold} bits={budget} table x{factor:g}: {device / 1e6:.3f} MB "
                      f"{row['quality']} ({info['section']}, eigen "
                      f"{sections['eigenimages'] / 1e6:.3f} MB, table "
                      f"{sections[info['section']] / 1e6:.3f} MB)")
                save_json(args.output, {"case": case.name, "views": case.n_views,
                                        "rows": rows})
    if args.train_db:
        weights = [base.interpolator.weights(p, th) for p, th in zip(case.phi, case.theta)]
        webp = webp_db_sweep(args.train_db, case, weights,
                        [int(v) for v in args.webp_qualities.split(",")], t)
        save_json(args.output, {"case": case.name, "views": case.n_views, "rows": rows,
                                "webp_db": webp})
    t.say(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
