"""A contact sheet of the looks of one image: each look as the device shows it.

    .venv/bin/python scripts/looks_sheet.py MODEL.ecs [-o docs/images/looks-contact-sheet.png]
        [--views 30,15;120,15;250,-10]

One row per look of ``MODEL.ecs`` (an image with several: ``eigencast fit A.cdb B.cdb ...``),
one tile per view: ``eigencast view MODEL.ecs --look NAME``, the frame a standalone device
shows after pressing ``l`` to that look (bit for bit), labelled with the look's name.

Produces: README.md's sheet of "Several looks in one image"
(docs/images/looks-contact-sheet.png).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

from PIL import Image, ImageDraw

from device_runtime.looks import look_names
from protocol.image import read_image


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("-o", "--output", type=Path,
                        default=Path("docs/images/looks-contact-sheet.png"))
    parser.add_argument("--views", default="30,15;120,15;250,-10",
                        help="PHI,THETA;... in degrees (default: three)")
    args = parser.parse_args()
    names = look_names(read_image(args.model))
    if not names:
        print(f"{args.model}: has one look", file=sys.stderr)
        return 1
    views = [tuple(float(v) for v in item.split(",")) for item in args.views.split(";")]
    exe = str(Path(sys.executable).with_name("eigencast"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            tiles = []
            for i, (phi, theta) in enumerate(views):
                out = Path(tmp) / f"{name}-{i}.png"
                subprocess.run([exe, "view", str(args.model), "--look", name, "--phi",
                                str(phi), "--theta", str(theta), "-o", str(out)],
                               check=True, stdout=subprocess.DEVNULL)
                tiles.append(Image.open(out).convert("RGB"))
            rows.append((name, tiles))
    w, h = rows[0][1][0].size
    label = 16
    sheet = Image.new("RGB", (w * len(views), (h + label) * len(rows)), (0, 0, 0))
    draw = ImageDraw.Draw(sheet)
    for r, (name, tiles) in enumerate(rows):
        y = r * (h + label)
        draw.text((4, y + 2), f"look {name}", fill=(255, 255, 255))
        for c, tile in enumerate(tiles):
            sheet.paste(tile, (c * w, y + label))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.output, optimize=True)
    print(f"wrote {args.output} ({len(rows)} looks x {len(views)} views)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
