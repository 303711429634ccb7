"""``eigencast fit``: fit an eigenspace to a Cinema database and write MODEL.ecs."""

from __future__ import annotations

import argparse
from pathlib import Path

from host.cinema import CinemaDB
from host.errors import EigencastError
from host.model import build_image, fit_database, save_model

HELP = "fit a PCA eigenspace to a Cinema database and write the eigenspace image (MODEL.ecs)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("database", metavar="DB.cdb", help="Cinema Spec D database folder")
    parser.add_argument("-o", "--output", required=True, metavar="MODEL.ecs")
    parser.add_argument("--method", choices=("standard", "cell", "adaptive"), default="adaptive",
                        help="eigenspace layout (default adaptive)")
    parser.add_argument("--cell", type=int, default=30, metavar="S",
                        help="cell size in pixels for cell/adaptive (default 30)")
    parser.add_argument("--components", type=int, default=100, metavar="K",
                        help="components per cell (standard/cell), cap for adaptive "
                             "(default 100)")
    parser.add_argument("--threshold", type=float, default=0.98, metavar="T",
                        help="adaptive: cumulative variance each cell keeps (default 0.98)")
    parser.add_argument("--score-step", type=float, metavar="S",
                        help="score quantization step in orthonormal coordinates "
                             "(default: from a 0.25 MSE budget)")
    parser.add_argument("--key", metavar="KEYFILE", help="sign the image with this device key")
    parser.add_argument("--cache", metavar="DIR",
                        help="where to keep the memory-mapped image stack "
                             "(default DB.cdb/.eigencast-cache)")


def run(args: argparse.Namespace) -> int:
    from protocol.keys import load_key

    if not 0.0 < args.threshold <= 1.0:
        raise EigencastError(f"--threshold {args.threshold}: must be within (0, 1]")
    key = load_key(args.key) if args.key else None
    out = Path(args.output)
    if not out.parent.exists():
        raise EigencastError(f"{out.parent}: output folder does not exist")
    db = CinemaDB.open(args.database)
    model = fit_database(db, method=args.method, cell=args.cell, components=args.components,
                         threshold=args.threshold, cache_dir=args.cache)
    image, annex = build_image(model, db, score_step=args.score_step)
    save_model(out, image, annex, key=key)
    device_bytes = image_device_bytes(out)
    print(
        f"wrote {out}: {args.method}, {db.n_views} views at "
        f"{db.image_shape[1]}x{db.image_shape[0]}, {model.grid_shape_[0]}x"
        f"{model.grid_shape_[1]} cells, {model.n_components_.mean():.2f} components/cell "
        f"(K={int(model.n_components_.sum())}), device image {device_bytes / 1e6:.2f} MB"
        f"{', signed' if key else ''}; score step {image.score_quantization['step']:.3g}"
    )
    return 0


def image_device_bytes(path: Path) -> int:
    """Size of the device part of an .ecs (what provisioning sends)."""
    from protocol.image import HEADER_SIZE, image_size

    with open(path, "rb") as f:
        return image_size(f.read(HEADER_SIZE))
