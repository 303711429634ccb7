"""Power-cut benchmark of the flash store: 100 random cuts, the device must boot every time.

Each cut copies a flash folder holding a confirmed *old* image, starts the
provisioning of a *new* image (``tests/flash_crash_driver.py update``: boot,
begin or resume, windowed chunks with duplicates, flush before each ack,
verify, commit_test, reboot, boot, confirm) and cuts it in one of three ways:

* ``op``: the child SIGKILLs itself at a uniformly random mutating file
  operation, tearing that write at a random byte;
* ``delay``: the parent SIGKILLs the child after a random delay within the
  duration of an uncut update (measured in this run);
* ``cache``: in-process, at a random operation, losing everything not
  fsynced (file contents and folder entries, each independently), which a
  SIGKILL cannot simulate; two post-cut disks are booted per cut.

After every cut the folder is opened and booted: the active image must verify
(without the digest fallback) and be the old or the new one. SIGKILL cuts are
then resumed to the end and must finish with the new image confirmed. Prints
the tally; exit status 1 if any cut failed.

Usage::

    .venv/bin/python benchmarks/bench_powercut.py [--cuts 100] [--seed 0] [--quick] [--json]
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import flash_crash_driver as driver

MODES = ("op", "delay", "cache")
MODE_WEIGHTS = (0.6, 0.2, 0.2)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cuts", type=int, default=100, help="number of cuts (default 100)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="20 cuts (smoke run)")
    parser.add_argument("--json", action="store_true", help="print the tally as JSON")
    args, unknown = parser.parse_known_args()
    if unknown:
        print(f"bench_powercut: ignoring {' '.join(unknown)}", file=sys.stderr)
    cuts = 20 if args.quick else args.cuts
    if cuts < 1:
        parser.error(f"--cuts={cuts} must be at least 1")
    rng = random.Random(args.seed)

    with tempfile.TemporaryDirectory(prefix="bench_powercut_") as tmp:
        work = Path(tmp)
        template = work / "template"
        setup = driver.run_driver(template, "setup")
        if setup.returncode != 0:
            print(f"setup failed: {setup.stderr}", file=sys.stderr)
            return 1
        shutil.copytree(template, work / "probe")
        start = time.perf_counter()
        full = driver.run_driver(work / "probe", "update", seed=0)
        uncut_s = time.perf_counter() - start
        if full.returncode != 0:
            print(f"uncut update failed: {full.stderr}", file=sys.stderr)
            return 1
        total_ops = driver.count_ops(full.stdout)

        tally: Counter[str] = Counter()
        failures: list[str] = []
        start = time.perf_counter()
        for cut in range(cuts):
            mode = rng.choices(MODES, MODE_WEIGHTS)[0]
            folder = work / f"cut{cut}"
            try:
                if mode == "op":
                    outcome = driver.power_cut_trial(template, folder, seed=cut,
                                                     crash_at=rng.randint(1, total_ops))
                    after = [outcome["after_cut"]]
                    landed = outcome["killed"]
                elif mode == "delay":
                    outcome = driver.power_cut_trial(template, folder, seed=cut,
                                                     kill_after_s=rng.uniform(0.0, uncut_s))
                    after = [outcome["after_cut"]]
                    landed = outcome["killed"]
                else:
                    outcome = driver.lost_cache_trial(template, folder, seed=cut, n_outcomes=2,
                                                      cut_at=rng.randint(1, total_ops))
                    after = outcome["after_cut"]
                    landed = outcome["cut"]
                tally[f"{mode}: cut landed" if landed else f"{mode}: finished first"] += 1
                for image in after:
                    tally[f"{mode}: booted {image} image"] += 1
                tally["verified boots"] += len(after)
            except AssertionError as exc:
                failures.append(f"cut {cut} ({mode}): {exc}")
                tally["FAILED"] += 1
            shutil.rmtree(folder, ignore_errors=True)
        elapsed_s = time.perf_counter() - start

    result = {
        "cuts": cuts,
        "failures": len(failures),
        "file_operations_per_update": total_ops,
        "uncut_update_s": round(uncut_s, 3),
        "seconds_per_cut": round(elapsed_s / cuts, 3),
        "tally": dict(sorted(tally.items())),
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{cuts} power cuts over an update of {total_ops} file operations "
              f"(uncut update {uncut_s:.2f} s; {elapsed_s / cuts:.2f} s per cut incl. resume)")
        for key, count in sorted(tally.items()):
            print(f"  {key:<28} {count:>4}")
        verdict = "every boot found a verified old or new image" if not failures else "FAILED"
        print(f"result: {verdict}; {len(failures)} failure(s)")
    for failure in failures:
        print(failure, file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
