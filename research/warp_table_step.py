"""The colour standalone table's step against the warp's quality (issue 15).

    .venv/bin/python research/warp_table_step.py IMAGE.ecs [IMAGE.ecs ...] \\
        [--factors 1,2,4,8] [--views random:20:15] [--out /work/cache/tablestep]

A standalone image with depth (``eigencast fit --standalone --depth``) stores the training
views' colour scores at the packet step, and that table is its largest part
(docs/design-notes.md, "Storage against image databases": the reason a WebP + depth
database is smaller). The warp blends
4 neighbours and filters its splats, so it may need less precision than the packet step.
For each image and each factor, this writes the image again with the table re-quantized at
factor x the packet step (`host.fit.model.add_standalone_table`, as ``fit --standalone``
writes it, the depth and colour eigenspaces untouched, the annex kept), reads back the
table's and the device image's sizes, and runs ``eigencast evaluate`` on it (``pca_warp``:
the standalone device's frame against a fresh ray-cast; codecs are measured too, as
evaluate always does; the WebP image database, motion, nearest and the rate-distortion
sweep are skipped). Results: OUT/results.json, and a table on stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.fit.model import HostModel, add_standalone_table
from protocol.image import HEADER_SIZE, image_size, read_image, write_image
from research.warp_storage import zsize

REPO = Path(__file__).resolve().parent.parent


def requantized(path: Path, factor: float, out: Path) -> dict:
    """``path`` written to ``out`` with its standalone table at ``factor`` x the packet
    step; the table's section name and compressed bytes, the device image's bytes."""
    model = HostModel.load(path)
    image = read_image(path)
    image = dataclasses.replace(image, sections={
        k: v for k, v in image.sections.items()
        if k not in ("standalone_scores", "standalone_scores_delta")})
    step = float(image.score_quantization["step"])
    info = add_standalone_table(image, model.training_scores, eigenvalues=model.eigenvalues,
                                table_step=factor * step)
    write_image(out, image)
    with open(out, "rb") as f:
        device = image_size(f.read(HEADER_SIZE))
    return {"factor": factor, "table_step": factor * step, "section": info["section"],
            "table_bytes": zsize(image.sections[info["section"]]), "device_bytes": int(device)}


def evaluate(path: Path, views: str) -> dict:
    run = subprocess.run(
        [str(REPO / ".venv/bin/eigencast"), "evaluate", str(path), "--views", views, "--json",
         "--rd-views", "0", "--motion-deadline", "0", "--webp-db-quality", "0",
         "--no-nearest"], capture_output=True, text=True, cwd=REPO)
    if run.returncode != 0:
        raise SystemExit(f"evaluate {path.name} failed: {run.stderr.strip()[-300:]}")
    result = json.loads(run.stdout)
    return {k: result[k] for k in ("pca_warp", "pca", "webp", "avif") if k in result}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", nargs="+", type=Path)
    ap.add_argument("--factors", default="1,2,4,8")
    ap.add_argument("--views", default="random:20:15")
    ap.add_argument("--out", type=Path, default=Path("/work/cache/tablestep"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results_path = args.out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    factors = [float(f) for f in args.factors.split(",")]
    for path in args.images:
        for factor in factors:
            key = f"{path.stem}@{factor:g}"
            if key in results:
                continue
            out = args.out / f"{path.stem}-tf{factor:g}.ecs"
            row = requantized(path, factor, out)
            row.update(evaluate(out, args.views))
            results[key] = row
            results_path.write_text(json.dumps(results, indent=1))
            w = row["pca_warp"]
            print(f"{key}: table {row['table_bytes'] / 1e6:.2f} MB, device image "
                  f"{row['device_bytes'] / 1e6:.2f} MB, pca_warp object SSIM "
                  f"{w['ssim_object']:.4f} FLIP {w['flip_object']:.4f}", flush=True)
            out.unlink()  # the file is rebuilt from the original on demand
    print("\n| image | factor | table MB | device image MB | pca_warp object SSIM / FLIP |")
    print("|---|---|---|---|---|")
    for key, row in results.items():
        w = row["pca_warp"]
        print(f"| {key.split('@')[0]} | x{row['factor']:g} | {row['table_bytes'] / 1e6:.2f} | "
              f"{row['device_bytes'] / 1e6:.2f} | {w['ssim_object']:.4f} / "
              f"{w['flip_object']:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
