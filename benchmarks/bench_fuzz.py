"""Long fuzz of the device link (issue 11): at least 100,000 hostile inputs against a real
``eigencast-device`` process over TCP and against an in-process device on the ``mem://`` line.

The inputs (``tests/attack_helpers.py``, seeded): mutations of a valid frame of every host ->
device message type (byte flips, truncation, splices, a re-framed body under another header,
SCORES whose packet is mutated), random bytes, and one named attack per batch (huge declared
lengths, deep nesting, zstd bombs, overflowing / NaN / inf score packets, unsigned and forged
state changes). They go in batches of ``--batch`` inputs, each on a fresh connection in one of
three roles, in turn:

* ``raw``: never says HELLO;
* ``hello``: says HELLO, never authenticates;
* ``auth``: a key holder gone bad: HELLO + AUTH with the device key, then the same inputs plus
  mutated SCORES *with a valid event tag and a fresh counter*, so that hostile score packets
  get past authentication and reach the decoder and the reconstruction.

Each batch ends with a PING whose PONG shows the device dispatched it all. Recorded per
transport: inputs sent, inputs per second, device restarts (a device process that exited, or
an in-process device whose threads raised, is restarted and counted: must be 0), and for the
process its peak RSS (``VmHWM`` of /proc/PID/status) against its RSS once booted (the image
loaded and one frame shown by a real host) in the same run. Afterwards a real host serves each
device one view, which must be shown.

Run: ``.venv/bin/python benchmarks/bench_fuzz.py [--inputs 100000] [--seed 11] [--json]``
(``--inputs`` is per transport; ``--quick``: 5,000). Prints BENCHMARKS.md-ready lines.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from attack_helpers import (  # noqa: E402
    RawPeer,
    correction_attacks,
    mutated_frames,
    overflow_packets,
    parser_attacks,
    score_packet,
    unauthenticated_state_changes,
)
from provision_helpers import KEY, DeviceProcess, mem_name  # noqa: E402
from runtime_helpers import RuntimeThread, read_frames, tiny_model, wait_until  # noqa: E402

from device_runtime.device import DeviceConfig  # noqa: E402
from device_runtime.runtime import parse_orbit  # noqa: E402
from host.link import provision, serve  # noqa: E402
from protocol import messages as m  # noqa: E402
from protocol.transport import open_transport  # noqa: E402

ROLES = ("raw", "hello", "auth")


def _quiet(line: str) -> None:
    pass


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process, bytes (empty once it is gone)."""
    out = {}
    with contextlib.suppress(OSError), open(f"/proc/{pid}/status") as handle:
        for line in handle:
            if line.startswith(("VmRSS:", "VmHWM:")):
                name, value = line.split(":")
                out[name] = int(value.split()[0]) * 1024
    return out


class _Factory:
    """``tiny_model`` wants a pytest tmp_path_factory; this is the part it uses."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def getbasetemp(self) -> Path:
        return self.root


class Session:
    """One raw connection in a role; in ``auth`` it tags SCORES like a real host would."""

    def __init__(self, transport: Any, role: str) -> None:
        self.peer = RawPeer(transport)
        self.role = role
        self.session_key: bytes | None = None
        self.counter = 0
        if role == "raw":
            return
        nonce = random.randbytes(m.NONCE_BYTES)
        hello = self.peer.request(m.Hello(min_version=1, max_version=m.PROTOCOL_VERSION,
                                          nonce=nonce, host_id="fuzz"), 1)
        if not isinstance(hello, m.HelloReply):
            raise RuntimeError(f"HELLO answered {hello!r}")
        if role == "auth":
            proof = m.auth_proof(KEY, role="host", host_nonce=nonce, device_nonce=hello.nonce,
                                 device_id=hello.device_id)
            reply = self.peer.request(m.AuthChallenge(host_proof=proof), 2)
            if not isinstance(reply, m.AuthResponse):
                raise RuntimeError(f"AUTH_CHALLENGE answered {reply!r}")
            self.session_key = m.derive_session_key(KEY, nonce, hello.nonce)

    def tagged_scores(self, packet: bytes) -> bytes:
        assert self.session_key is not None
        self.counter += 1
        msg = m.tag_event(m.Scores(sequence=self.counter, packet=packet), self.session_key,
                          self.counter)
        return msg.encode()


def _mutated_packet(rng: random.Random, k: int, tag: bytes) -> bytes:
    # half of them predicted corrections (version 2, flags bit 6; issue 14), whose base kind,
    # view and version bytes the mutations below then hit like any other field
    predicted = rng.random() < 0.5
    packet = bytearray(score_packet(k, tag, q=[rng.randrange(-50, 50) for _ in range(8)],
                                    step=rng.choice([0.5, 14.4, 1e3]),
                                    view=(rng.uniform(0, 360), rng.uniform(-90, 90)),
                                    frame=rng.randrange(1, 1 << 32),
                                    flags=0x40 if predicted else 0,
                                    version=2 if predicted else 1))
    for _ in range(rng.randrange(0, 4)):
        at = rng.randrange(len(packet))
        packet[at] = rng.randrange(256)
    return bytes(packet)


def fuzz(open_peer, restart, n_inputs: int, *, seed: int, batch: int, k: int,
         tag: bytes, alive, window: int = 40) -> dict[str, Any]:
    """Send ``n_inputs`` hostile inputs in batches (roles in turn), a PING round trip after
    every ``window`` of them (the device's receive queue holds 48 frames: a peer that sends
    more without waiting has the excess dropped, which would hide them from the device);
    return the counts."""
    rng = random.Random(seed)
    stream = mutated_frames(rng, k, tag)
    named = (parser_attacks(random.Random(seed + 1), k, tag)
             + overflow_packets(k, tag, (123.0, 45.0))
             + correction_attacks(k, tag, (123.0, 45.0))
             + unauthenticated_state_changes(random.Random(seed + 2)))
    sent = restarts = batches = dropped = resent = 0
    per_role = dict.fromkeys(ROLES, 0)
    t0 = time.perf_counter()
    for role in itertools.cycle(ROLES):
        if sent >= n_inputs:
            break
        try:
            session = Session(open_peer(), role)
        except Exception as exc:  # the device refused or died: count a restart if it died
            if alive() is not None:
                restarts += 1
                restart()
                continue
            raise RuntimeError(f"cannot open a {role} session: {exc}") from exc
        try:
            n = min(batch, n_inputs - sent)
            wires = [next(stream) for _ in range(n - 1)]
            wires.append(rng.choice(named)[1])
            if role == "auth":  # a third of the inputs: tagged mutated score packets
                for i in range(0, len(wires), 3):
                    wires[i] = session.tagged_scores(_mutated_packet(rng, k, tag))
            ended = False
            for start in range(0, len(wires), window):
                for wire in wires[start:start + window]:
                    session.peer.send(wire)
                session.peer.send(b"\x00")
                if not session.peer.barrier(30):
                    ended = True  # the device ended the connection
                    break
                resent += session.peer.pings_sent > 1
            sent += n
            per_role[role] += n
            batches += 1
            dropped += ended
        finally:
            session.peer.close()
        if alive() is not None:
            restarts += 1
            restart()
    wall = time.perf_counter() - t0
    return {"inputs": sent, "batches": batches, "wall_s": wall, "inputs_per_s": sent / wall,
            "restarts": restarts, "sessions_ended_by_device": dropped,
            "barriers_with_lost_ping": resent, "per_role": per_role}


def _served(url: str, model_path: Path, frames: Path, theta: float) -> None:
    serve(model_path, url, key=KEY, orbit=parse_orbit(f"steps:1:{theta:g}"), fps=0,
          log=_quiet, reconnect=False, stats_every_s=60)
    wait_until(lambda: any((float(r["phi_deg"]), float(r["theta_deg"])) == (0.0, theta)
                           for r in read_frames(frames)), 30, f"the served view (0, {theta})")


def run_tcp(work: Path, model_path: Path, args: argparse.Namespace, k: int,
            tag: bytes) -> dict[str, Any]:
    flash, frames = work / "tcp-flash", work / "tcp-frames"
    keyf = model_path.parent / "device.key"
    device = DeviceProcess(flash, "--headless", "--frames", str(frames), key_file=keyf)
    provision(model_path, device.url, key=KEY, show_progress=False, log=_quiet)
    assert device.stop() == 0
    stats_file = work / "tcp-stats.json"
    box = {"device": DeviceProcess(flash, "--headless", "--frames", str(frames), "--stats",
                                   str(stats_file), key_file=keyf)}
    hwm_before = 0
    try:
        _served(box["device"].url, model_path, frames, 10.0)  # booted: image loaded, shown
        boot = proc_status(box["device"].proc.pid)
        pids = [box["device"].proc.pid]

        def alive() -> str | None:
            code = box["device"].proc.poll()
            return None if code is None else f"exited {code}"

        def restart() -> None:
            hwm = proc_status(box["device"].proc.pid).get("VmHWM", 0)
            nonlocal hwm_before
            hwm_before = max(hwm_before, hwm)
            print("  device process died:\n    " + "\n    ".join(box["device"].lines[-6:]))
            box["device"].kill()
            box["device"] = DeviceProcess(flash, "--headless", "--frames", str(frames),
                                          "--stats", str(stats_file), key_file=keyf)
            pids.append(box["device"].proc.pid)

        result = fuzz(lambda: open_transport(box["device"].url, timeout_s=5), restart,
                      args.inputs, seed=args.seed, batch=args.batch, k=k, tag=tag, alive=alive)
        peak = max(hwm_before, proc_status(box["device"].proc.pid).get("VmHWM", 0))
        _served(box["device"].url, model_path, frames, 20.0)
        after = proc_status(box["device"].proc.pid)
    finally:
        code = box["device"].stop()  # writes the --stats file a last time
    with contextlib.suppress(OSError, ValueError):
        result.update(_decode_counts(json.loads(stats_file.read_text())))
    result.update(transport="tcp (eigencast-device process, keyed)", boot_rss=boot["VmRSS"],
                  boot_hwm=boot["VmHWM"], peak_rss=peak, rss_after=after.get("VmRSS", 0),
                  peak_over_boot=peak / boot["VmRSS"], exit_code=code, pids=len(pids))
    return result


def run_mem(work: Path, model_path: Path, args: argparse.Namespace, k: int,
            tag: bytes) -> dict[str, Any]:
    flash, frames = work / "mem-flash", work / "mem-frames"
    line = mem_name("fuzz")
    url_a = f"mem://{line}?end=a&pace=0"
    config = DeviceConfig(flash_dir=flash, key=KEY)
    box = {"device": RuntimeThread(flash, f"mem://{line}?end=b&pace=0", frames=frames,
                                   config=config)}
    provision(model_path, url_a, key=KEY, show_progress=False, log=_quiet)

    def alive() -> str | None:
        dev = box["device"]
        if dev.errors:
            return repr(dev.errors[0])
        return None if all(t.is_alive() for t in dev.threads) else "a thread stopped"

    def restart() -> None:
        print(f"  in-process device died: {alive()}")
        with contextlib.suppress(BaseException):
            box["device"].stop()
        box["device"] = RuntimeThread(flash, f"mem://{line}?end=b&pace=0", frames=frames,
                                      config=config)

    try:
        result = fuzz(lambda: open_transport(url_a, timeout_s=5), restart, args.inputs,
                      seed=args.seed + 100, batch=args.batch, k=k, tag=tag, alive=alive)
        _served(url_a, model_path, frames, 20.0)
        result.update(_decode_counts(box["device"].device.runtime_stats.as_dict()))
    finally:
        box["device"].stop()
    result.update(transport="mem:// line (in-process device, keyed)")
    return result


def _decode_counts(stats: dict[str, Any]) -> dict[str, int]:
    """Score packets the device decoded (key + delta) and refused, from its statistics."""
    return {"packets_received": stats["packets"],
            "packets_decoded": stats["key_frames"] + stats["delta_frames"],
            "packets_refused": stats["decode_errors"] + stats["wrong_image"]
            + stats["missing_base"]}


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def report(results: list[dict[str, Any]], args: argparse.Namespace) -> None:
    total = sum(r["inputs"] for r in results)
    print(f"\n### Fuzz: `benchmarks/bench_fuzz.py` (seed {args.seed}, batches of {args.batch})\n")
    print("| transport | inputs | inputs/s | device restarts | sessions the device ended | "
          "peak RSS / RSS after boot |")
    print("|---|---|---|---|---|---|")
    for r in results:
        rss = (f"{_mb(r['peak_rss'])} / {_mb(r['boot_rss'])} = {r['peak_over_boot']:.2f}x"
               if "peak_rss" in r else "(in the test process)")
        print(f"| {r['transport']} | {r['inputs']:,} | {r['inputs_per_s']:,.0f} | "
              f"{r['restarts']} | {r['sessions_ended_by_device']} | {rss} |")
    print("\nA PING was lost (a window's frames dropped by a full receive queue) in "
          + ", ".join(f"{r['barriers_with_lost_ping']} of {r['inputs'] // 40} windows "
                      f"({r['transport'].split()[0]})" for r in results) + ".")
    print("\nScore packets that reached the decoder (tagged ones of the auth role, and the real "
          "host's): " + ", ".join(
              f"{r['transport'].split()[0]} {r.get('packets_received', '?')} received, "
              f"{r.get('packets_decoded', '?')} decoded and shown, "
              f"{r.get('packets_refused', '?')} refused" for r in results) + ".")
    print(f"\n{total:,} inputs in all; roles per transport: "
          + "; ".join(f"{r['transport'].split()[0]} {r['per_role']}" for r in results))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=100_000, help="inputs per transport")
    parser.add_argument("--batch", type=int, default=500, help="inputs per connection")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--quick", action="store_true", help="5,000 inputs per transport")
    parser.add_argument("--transports", default="tcp,mem")
    parser.add_argument("--json", action="store_true", help="also print the results as JSON")
    args = parser.parse_args()
    if args.quick:
        args.inputs = 5_000
    work = Path(tempfile.mkdtemp(prefix="bench-fuzz-"))
    try:
        model_path = tiny_model(_Factory(work), name="fuzz")
        from host.model import HostModel

        model = HostModel.load(model_path)
        k, tag = model.image.n_coefficients, model.digest[:4]
        results = []
        for name in args.transports.split(","):
            print(f"{name}: {args.inputs:,} inputs ...", flush=True)
            run = run_tcp if name == "tcp" else run_mem
            results.append(run(work, model_path, args, k, tag))
        report(results, args)
        if args.json:
            print(json.dumps(results, indent=1))
        bad = [r for r in results if r["restarts"] or r.get("pids", 1) != 1]
        return 1 if bad else 0
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
