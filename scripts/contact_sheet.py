"""Render every shared volume and both built-ins through the CLI into one contact sheet.

    .venv/bin/python scripts/contact_sheet.py [-o docs/images/contact-sheet.png] [--size 256]
    .venv/bin/python scripts/contact_sheet.py --lighting headlight,cinematic \
        -o docs/images/lighting-contact-sheet.png

Each tile is `eigencast render-view VOLUME --phi 60 --theta 15` with the
volume's default transfer function; shared volumes are skipped (and named)
when ../shared/data is absent. With ``--lighting A,B`` each volume gets one tile per
look, side by side (``render-view --lighting A`` ...), labelled with the look.

Produces: README.md, the contact sheet at the top (docs/images/contact-sheet.png) and the
side-by-side sheet of "Lighting" (docs/images/lighting-contact-sheet.png).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

from PIL import Image, ImageDraw

from host.shared_data import SHARED_VOLUMES, shared_volume


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="docs/images/contact-sheet.png")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--columns", type=int, default=4)
    parser.add_argument("--lighting", default="headlight",
                        help="comma-separated looks, one tile each per volume (default headlight)")
    args = parser.parse_args()
    looks = args.lighting.split(",")
    specs = [("builtin:head", "builtin:head"), ("builtin:tooth", "builtin:tooth")]
    for name in SHARED_VOLUMES:
        path = shared_volume(name)
        if path is None:
            print(f"skipping {name}: ../shared/data absent", file=sys.stderr)
        else:
            specs.append((name, str(path)))
    tiles = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, spec in specs:
            for look in looks:
                out = Path(tmp) / f"{len(tiles)}.png"
                subprocess.run(
                    [sys.executable, "-m", "host.cli", "render-view", spec, "--phi", "60",
                     "--theta", "15", "--size", str(args.size), "-o", str(out),
                     "--lighting", look],
                    check=True, stdout=subprocess.DEVNULL,
                )
                tile = Image.open(out).convert("RGB")
                text = label if len(looks) == 1 else f"{label}, {look}"
                ImageDraw.Draw(tile).text((4, 4), text, fill=(255, 255, 0))
                tiles.append(tile)
    cols = args.columns
    rows = (len(tiles) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * args.size, rows * args.size))
    for k, tile in enumerate(tiles):
        sheet.paste(tile, ((k % cols) * args.size, (k // cols) * args.size))
    sheet.save(args.output, optimize=True)
    print(f"wrote {args.output} ({len(specs)} volumes, {len(looks)} look(s) each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
