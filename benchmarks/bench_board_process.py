"""A real standalone device process on one busy core: frames per second and the warp's share.

``eigencast-device --standalone --headless --orbit turn:12:15:1 --stats FILE`` with IMAGE
provisioned, pinned to one core (``--cpu``, default 0; ``OPENBLAS_NUM_THREADS=1``), once
alone on it (the baseline) and once sharing it with ``--busy`` busy loops (default two: a
board's core that other work takes two thirds of, i.e. a board three times slower). Prints
per run the frames per second the device presented (its 30 Hz headless tick is the most),
the share of them that were the view's depth warp, and the busy run's fps as a ratio of the
baseline's.

Usage::

    .venv/bin/python benchmarks/bench_board_process.py IMAGE.ecs [--busy 2] [--cpu 0]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def run_device(flash0: Path, cpu: int, busy: int) -> dict:
    """One orbit of the device process on core ``cpu`` beside ``busy`` busy loops."""
    loops = [subprocess.Popen(["taskset", "-c", str(cpu), sys.executable, "-c",
                               "while True: pass"]) for _ in range(busy)]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            flash = Path(tmp) / "flash"
            shutil.copytree(flash0, flash)
            stats = Path(tmp) / "stats.json"
            device = Path(sys.executable).with_name("eigencast-device")
            env = dict(os.environ, OPENBLAS_NUM_THREADS="1", SDL_VIDEODRIVER="dummy")
            subprocess.run(["taskset", "-c", str(cpu), str(device), "--flash", str(flash),
                            "--standalone", "--headless", "--orbit", "turn:12:15:1",
                            "--stats", str(stats)], env=env, check=True, timeout=120,
                           stdout=subprocess.DEVNULL)
            return json.loads(stats.read_text())
    finally:
        for loop in loops:
            loop.kill()
            loop.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("image", type=Path)
    parser.add_argument("--busy", type=int, default=2)
    parser.add_argument("--cpu", type=int, default=0)
    parser.add_argument("--work", type=Path, default=Path("bench-out/board"))
    args = parser.parse_args()
    from link_real import provisioned_flash

    args.work.mkdir(parents=True, exist_ok=True)
    flash0 = provisioned_flash(args.image, args.work)
    print(f"{'run':>14} {'fps':>6} {'warp':>6} {'frames':>7}")
    base = None
    for busy in (0, args.busy):
        s = run_device(flash0, args.cpu, busy)
        n = max(1, s["frames_presented"])
        label = "alone" if busy == 0 else f"{busy} busy loops"
        print(f"{label:>14} {s['fps']:>6.1f} {s['synthesized_frames'] / n:>6.0%} {n:>7}"
              + (f"   fps {s['fps'] / base:.2f}x alone" if base else ""), flush=True)
        base = base or s["fps"]
    return 0


if __name__ == "__main__":
    sys.exit(main())
