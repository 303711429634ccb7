"""Several looks in one image: what they cost in flash and RAM, and what a switch costs.

Usage::

    OPENBLAS_NUM_THREADS=1 taskset -c 0 .venv/bin/python benchmarks/bench_looks.py \\
        MODEL.ecs [--single A.ecs B.ecs ...] [--switches 12] [--json OUT]

``MODEL.ecs`` is an image with several looks (``eigencast fit A.cdb B.cdb ...``); the
``--single`` images are the same databases fitted one by one (``eigencast fit A.cdb``), in
the looks' order. Printed:

* **storage**: the device image's bytes (what provisioning sends and the flash keeps) and
  the RAM a device needs for it (`device_runtime.image_receiver.required_ram_bytes`), against
  the first single-look image (the ratio the looks cost over one look) and against all the
  single-look images together (a separate image per look); and which sections the looks
  share and which each look adds;
* **switch** (a standalone device, this process, one core when run as above): at a resting
  view, `RuntimeDevice.show_look` of the next look, interleaved with a moved view's frame in
  the same look, ``--switches`` times: the switch's own cost (the new look's model:
  reconstructors, synthesis, warp worker, its thread started only after the new look's
  first frame) beside one frame (the blend
  of a moved view, what the display makes per tick), the first frame of the new look (its
  blend, shown by the switch) and the time until the new look's warp of the view is on show
  (its neighbours reconstructed afresh: the old look's cached views go with it) beside a
  moved view's warp in one look.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import ClassVar

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _storage(model: Path, singles: list[Path]) -> dict:
    from device_runtime.image_receiver import required_ram_bytes
    from protocol.image import read_manifest

    def sizes(path: Path) -> dict:
        manifest = read_manifest(path)
        return {"flash": manifest["header"]["image_size"], "ram": required_ram_bytes(manifest),
                "sections": {e["name"]: e["size"] for e in manifest["sections"]},
                "manifest": manifest["header"]["manifest_size"]}

    multi = sizes(model)
    out: dict = {"model": str(model), "flash": multi["flash"], "ram": multi["ram"],
                 "sections": multi["sections"]}
    manifest = read_manifest(model)
    looks = manifest.get("looks") or []
    own = {name for look in looks for name in (look.get("sections") or {}).values()}
    replaced = {key for look in looks for key in (look.get("sections") or {})}
    # the first look's own sections are the image's standard ones the others replace
    # (a plain depth table is replaced by a delta-coded one and the other way round)
    first = {k for k in multi["sections"] if k in replaced or (
        k.startswith("depth_") and any(r.startswith("depth_") for r in replaced))}
    out["looks"] = [look["name"] for look in looks]
    out["shared_bytes"] = sum(v for k, v in multi["sections"].items()
                              if k not in own and k not in first)
    out["per_look_bytes"] = {look["name"]: sum(multi["sections"][s] for s in (
        look.get("sections") or {}).values()) for look in looks}
    if looks:
        out["per_look_bytes"][looks[0]["name"]] = sum(multi["sections"][k] for k in first)
    if singles:
        one = [sizes(p) for p in singles]
        out["single"] = [{"path": str(p), "flash": s["flash"], "ram": s["ram"]}
                         for p, s in zip(singles, one)]
        out["flash_vs_first"] = multi["flash"] / one[0]["flash"]
        out["ram_vs_first"] = multi["ram"] / one[0]["ram"]
        out["flash_vs_separate"] = multi["flash"] / sum(s["flash"] for s in one)
        out["ram_vs_separate"] = multi["ram"] / sum(s["ram"] for s in one)
    return out


def _switch(model: Path, switches: int) -> dict:
    from device_runtime.device import DeviceConfig
    from device_runtime.display import CycleLook, HeadlessPresenter, ViewDelta
    from device_runtime.runtime import LoadedModel, RuntimeDevice
    from protocol.image import read_image

    image = read_image(model)
    frames: list = []
    with_tmp = Path(sys.argv[0]).resolve().parent.parent / "bench-out" / "looks-flash"

    class Keys(HeadlessPresenter):  # the key presses of a window
        queue: ClassVar[list] = []

        def poll(self) -> list:
            out, Keys.queue = Keys.queue, []
            return out

    device = RuntimeDevice(DeviceConfig(flash_dir=with_tmp), standalone=True,
                           presenter=Keys(None),
                           view=(30.0, 15.0), log=lambda line: None, fps=1000.0,
                           on_frame=lambda f, info: frames.append(
                               {**info, "t": time.perf_counter()}))
    loaded = LoadedModel.build(image, slot="A", generation=1, test=False,
                               want_standalone=True)
    device._decoder_model = loaded
    device._models.put(loaded)
    n = len(loaded.looks)

    def rest(timeout: float = 60.0) -> float:
        """Turns until the view's warp is on show; seconds it took."""
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < timeout:
            device.display_turn(None)
            if frames and frames[-1].get("synthesized") and (
                    frames[-1]["phi_deg"], frames[-1]["theta_deg"]) == device.view:
                return time.perf_counter() - t0
            time.sleep(0.0005)
        raise RuntimeError("the warp never came")

    out: dict = {"switch_s": [], "switch_to_blend_s": [], "switch_to_warp_s": [],
                 "blend_s": [], "moved_to_warp_s": []}
    try:
        rest()
        for i in range(switches):
            # a moved view in the same look: its blend (one frame), then its warp
            time.sleep(0.002)  # a new display tick: the moved view's blend is due at once
            device.apply(ViewDelta(7.0, 0.0))
            t0 = time.perf_counter()
            device.display_turn(None)
            out["blend_s"].append(time.perf_counter() - t0)
            out["moved_to_warp_s"].append(time.perf_counter() - t0 + rest())
            # the next look at the resting view: the switch shows its blend at once (the
            # warp worker idle first: no warp of a view ahead competes for the core)
            worker = device._model.warp_worker
            t_idle = time.perf_counter()
            while (worker._current is not None or worker._pending is not None) and (
                    time.perf_counter() - t_idle < 5.0):
                time.sleep(0.005)
            old = device._model
            t0 = time.perf_counter()
            new = old.for_look((old.look + 1) % n, on_warp=device._scores.wake,
                               start_worker=False)  # as the switch builds it
            built = time.perf_counter() - t0
            new.close()
            Keys.queue.append(CycleLook())  # key l, read by the next display turn
            first = len(frames)
            t0 = time.perf_counter()
            device.display_turn(None)
            shown = frames[first]["t"] - t0  # the new look's first frame presented (the
            # same turn may go on to show its warp when the worker makes it in time)
            out["switch_s"].append(built)
            out["switch_to_blend_s"].append(shown)
            out["switch_to_warp_s"].append(time.perf_counter() - t0 + rest())
            assert device._model.look == (old.look + 1) % n and i >= 0
    finally:
        device.close_display()
        device.close()
    summary = {k: statistics.median(v) for k, v in out.items()}
    summary["switches"] = switches
    summary["image_shape"] = list(image.image_shape)
    summary["looks"] = n
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--single", type=Path, nargs="*", default=[])
    parser.add_argument("--switches", type=int, default=12)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    storage = _storage(args.model, args.single)
    print(f"{args.model}: looks {', '.join(storage['looks'])}; device image "
          f"{storage['flash'] / 1e6:.3f} MB, RAM {storage['ram'] / 1e6:.2f} MB; shared "
          f"sections {storage['shared_bytes'] / 1e6:.3f} MB, per look " + ", ".join(
              f"{k} {v / 1e6:.3f} MB" for k, v in storage["per_look_bytes"].items()))
    if args.single:
        for s in storage["single"]:
            print(f"  single-look {s['path']}: {s['flash'] / 1e6:.3f} MB, RAM "
                  f"{s['ram'] / 1e6:.2f} MB")
        print(f"  looks image / first single: flash {storage['flash_vs_first']:.2f}x, RAM "
              f"{storage['ram_vs_first']:.2f}x; / all singles together: flash "
              f"{storage['flash_vs_separate']:.2f}x, RAM {storage['ram_vs_separate']:.2f}x")
    result = {"storage": storage}
    if args.switches > 0:
        switch = _switch(args.model, args.switches)
        result["switch"] = switch
        ms = {k: 1e3 * v for k, v in switch.items() if k.endswith("_s")}
        print(f"switch ({switch['switches']} times, medians, this process): the new look's "
              f"model {ms['switch_s']:.1f} ms vs one frame (a moved view's blend) "
              f"{ms['blend_s']:.1f} ms; its first frame (blend) on show "
              f"{ms['switch_to_blend_s']:.1f} ms after the key; its warp "
              f"{ms['switch_to_warp_s']:.1f} ms (a moved view's warp in one look: "
              f"{ms['moved_to_warp_s']:.1f} ms)")
        print(f"  ratios to one blend: the switch {switch['switch_s'] / switch['blend_s']:.2f}x "
              f"(target < 1), the key to the new look's first frame "
              f"{switch['switch_to_blend_s'] / switch['blend_s']:.2f}x (target < 2: one frame "
              f"plus its first frame); the new look's warp / a moved view's warp "
              f"{switch['switch_to_warp_s'] / switch['moved_to_warp_s']:.2f}x")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
