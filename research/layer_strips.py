"""What a refinement layer's file costs cut into full-width strips: bytes against the whole
file, and the costliest strip's pygame decode on one core against the whole file's.

For each shared database (``/work/cache/NAME-SIZE.cdb``, its training ray-casts) and a few
of its views, WebP lossless (quality 100, method 4: the exact layer) and lossy WebP (quality
60, method 6) of the view as 1, 2 and 4 strips of equal height. Backs `protocol.layers`'
``STRIP_PIXELS``: strips only for the lossless layer of frames over 65,536 pixels.

    OPENBLAS_NUM_THREADS=1 taskset -c 0 .venv/bin/python research/layer_strips.py \\
        tooth-256 head-256 vismale_head-256 engine-256 tooth-512 [--views 50,100,400,700,900,1300]
"""

from __future__ import annotations

import argparse
import io
import itertools
import os
import time
from pathlib import Path

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import numpy as np
import pygame
from PIL import Image

CODINGS = {"lossless": {"lossless": True, "quality": 100, "method": 4},
           "lossy q60": {"quality": 60, "method": 6}}


def _webp(pixels: np.ndarray, **kwargs) -> bytes:
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "WEBP", **kwargs)
    return out.getvalue()


def _decode_ms(data: bytes, repeat: int = 9) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.thread_time()
        pygame.image.load(io.BytesIO(data), "x.webp")
        times.append(time.thread_time() - t0)
    return 1e3 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("databases", nargs="+", help="NAME-SIZE under --cache")
    ap.add_argument("--cache", type=Path, default=Path("/work/cache"))
    ap.add_argument("--views", default="50,100,400,700,900,1300")
    args = ap.parse_args()
    print(f"layer_strips: {time.strftime('%Y-%m-%d')}, load {os.getloadavg()[0]:.1f}; per "
          "database: bytes of n strips / the whole file (min-max over the views), the "
          "costliest strip's decode (ms, max over the views)\n")
    print("| database | coding | whole: bytes, decode ms | 2 strips: x bytes, ms | "
          "4 strips: x bytes, ms |\n|---|---|---|---|---|")
    for name in args.databases:
        images = args.cache / f"{name}.cdb" / "images"
        for coding, kwargs in CODINGS.items():
            whole_b, whole_ms, rows = [], [], {2: ([], []), 4: ([], [])}
            for v in (int(x) for x in args.views.split(",")):
                pixels = np.asarray(Image.open(images / f"view_{v:05d}.png").convert("RGB"))
                whole = _webp(pixels, **kwargs)
                whole_b.append(len(whole))
                whole_ms.append(_decode_ms(whole))
                for n, (ratio, ms) in rows.items():
                    bounds = np.linspace(0, pixels.shape[0], n + 1).round().astype(int)
                    parts = [_webp(pixels[a:b], **kwargs)
                             for a, b in itertools.pairwise(bounds)]
                    ratio.append(sum(map(len, parts)) / len(whole))
                    ms.append(max(_decode_ms(p) for p in parts))
            cells = [f"{min(r):.3f}-{max(r):.3f}, {max(m):.2f}" for r, m in rows.values()]
            print(f"| {name} | {coding} | {int(np.median(whole_b))}, {max(whole_ms):.2f} | "
                  + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
