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

More sections (``--sections fuzz,lockout,flood,rest`` by default, ``lobby`` on request):

* ``lockout``: keyless peers (``tests/keyless_peers.py``, a process of their own) attack a
  keyed ``eigencast-device`` process: none (the baseline), 3, 16 and 64 threads looping
  HELLO-and-reconnect, and the flood of connections judged worst, from the key holder's own
  address and from another one. Under each, the key holder runs ``eigencast provision
  --key`` ``--tries`` times (10) and ``eigencast serve --key`` (one frame) 3 times; each
  must succeed within ``--auth-timeout`` + 2 s, measured from the command's start (Python's
  start-up included, as a user waits for it). Recorded: successes, median and worst times,
  the attack's connections, the device's log lines during the attack.
* ``flood``: a keyed device process on one core drives its own orbit (``--standalone
  --orbit``); its frame rate idle, then while an unauthenticated peer (another core) floods
  PINGs, VIEW_REQUESTs, zero bytes or bytes with no frame delimiter (and while 32 peers
  flood PINGs or such bytes), as a ratio of idle
  in the same run (>= 0.8 asked).
  The device shows ``--flood-model`` (default: the tooth rendered at 256 px from 144 views
  with depth and fitted ``--depth --key``, built in the run, about 2 minutes; ``--quick``:
  the tiny model), so its frames cost what a real device's do.
* ``lobby``: the CPU time the device's thread really spends under one unauthenticated peer
  flooding each kind (``garbage``: bytes with no frame delimiter), against what the lobby
  charges the peer, over ``--flood-seconds`` windows (its own clock, so load barely moves it).
* ``rest``: ``eigencast serve`` for ``--rest-seconds`` (60) against a device process resting
  on a view, one at a pole and an in-process device dragged then released, in each of the
  ways serve can serve (`REST_MODES`: corrections of the device's own frames, the ray-cast
  scores an older device gets, interpolated scores when the volume cannot be loaded) at
  once per case; no traceback, exit 0, frames sent.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

import keyless_peers  # noqa: E402
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
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts  # noqa: E402
from protocol import messages as m  # noqa: E402
from protocol.transport import open_transport  # noqa: E402

ROLES = ("raw", "hello", "auth")
KEY_FILE = Path()
"""The key file of ``KEY`` (written beside the tiny model by ``main``)."""


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
    serve(model_path, url,
          ServeOptions(key=KEY, orbit=parse_orbit(f"steps:1:{theta:g}"), fps=0, reconnect=False,
                       stats_every_s=60), ServeParts(log=_quiet))
    wait_until(lambda: any((float(r["phi_deg"]), float(r["theta_deg"])) == (0.0, theta)
                           for r in read_frames(frames)), 30, f"the served view (0, {theta})")


def run_tcp(work: Path, model_path: Path, args: argparse.Namespace, k: int,
            tag: bytes) -> dict[str, Any]:
    flash, frames = work / "tcp-flash", work / "tcp-frames"
    keyf = model_path.parent / "device.key"
    device = DeviceProcess(flash, "--headless", "--frames", str(frames), key_file=keyf)
    provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=_quiet))
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
    provision(model_path, url_a, ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=_quiet))

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


# --------------------------------------------------------------------------- lockout

LOCKOUT_ATTACKS = (
    ("none", 0, None),
    ("loop", 3, None),
    ("loop", 16, None),
    ("loop", 64, None),
    ("flood", 16, "127.0.0.2"),
    ("flood", 16, None),
)
"""(mode, threads, source address): the baseline, the finding's loop at 3/16/64 threads, and
the flood of connections from another address and from the key holder's own."""


def _keyed_device(work: Path, name: str, model_path: Path, *extra: str) -> DeviceProcess:
    """A keyed device process holding ``model_path`` (signed with ``KEY``)."""
    flash = work / f"{name}-flash"
    device = DeviceProcess(flash, "--headless", *extra, key_file=KEY_FILE)
    provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=_quiet))
    return device


def run_lockout(work: Path, model_path: Path, args: argparse.Namespace) -> list[dict[str, Any]]:
    """The key holder's provision and serve under each attack of ``LOCKOUT_ATTACKS``."""
    limit = args.auth_timeout + 2.0
    keyf = str(KEY_FILE)
    cli = [sys.executable, "-m", "host.cli"]
    device = _keyed_device(work, "lockout", model_path, "--auth-timeout", f"{args.auth_timeout:g}")
    results = []
    try:
        for mode, threads, bind in LOCKOUT_ATTACKS:
            label = "no attack" if mode == "none" else (
                f"{mode} x{threads}" + (f" from {bind}" if bind else ""))
            print(f"  lockout: {label} ...", flush=True)
            lines_before = len(device.lines)
            peers = (None if mode == "none" else
                     keyless_peers.spawn(device.url, mode, threads, bind=bind))
            try:
                if peers is not None:
                    time.sleep(1.0)  # the attack is under way before the key holder comes
                provisions = [keyless_peers.timed(
                    [*cli, "provision", str(model_path), "--port", device.url, "--key", keyf],
                    limit, cwd=str(REPO)) for _ in range(args.tries)]
                serves = [keyless_peers.timed(
                    [*cli, "serve", str(model_path), "--port", device.url, "--key", keyf,
                     "--orbit", "steps:1", "--fps", "0", "--no-reconnect"], limit,
                    cwd=str(REPO)) for _ in range(3)]
            finally:
                counts = keyless_peers.finish(peers) if peers is not None else {}
            alive = device.proc.poll() is None
            times = sorted(t for _, t, _ in provisions)
            results.append({
                "attack": label, "limit_s": limit, "device_alive": alive,
                "provision_ok": sum(ok for ok, _, _ in provisions), "tries": len(provisions),
                "provision_median_s": times[len(times) // 2], "provision_max_s": times[-1],
                "provision_failures": [tail for ok, _, tail in provisions if not ok][:3],
                "serve_ok": sum(ok for ok, _, _ in serves), "serve_tries": len(serves),
                "serve_max_s": max(t for _, t, _ in serves),
                "peer_counts": counts,
                "device_log_lines": len(device.lines) - lines_before,
            })
            if not alive:
                break
    finally:
        device.stop()
    return results


def report_lockout(results: list[dict[str, Any]], args: argparse.Namespace) -> None:
    print(f"\n### Lockout: keyless peers against a keyed TCP device (--auth-timeout "
          f"{args.auth_timeout:g} s; bound {args.auth_timeout + 2:g} s per command)\n")
    print("| attack | peer connections | `provision --key` within bound | median / worst | "
          "`serve --key` frames within bound | worst | device log lines |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        conns = r["peer_counts"].get("connections", 0)
        print(f"| {r['attack']} | {conns:,} | {r['provision_ok']}/{r['tries']} | "
              f"{r['provision_median_s']:.1f} / {r['provision_max_s']:.1f} s | "
              f"{r['serve_ok']}/{r['serve_tries']} | {r['serve_max_s']:.1f} s | "
              f"{r['device_log_lines']} |")
    for r in results:
        if r["provision_failures"]:
            print(f"\n{r['attack']}: " + "; ".join(r["provision_failures"]))


# --------------------------------------------------------------------------- flood

FLOODS = (("ping", 1), ("view", 1), ("zeros", 1), ("garbage", 1), ("ping", 32),
          ("garbage", 32))
"""(what, peers): one unauthenticated peer flooding each kind (``garbage``: bytes with no frame
delimiter), and 32 flooding PINGs or such bytes (every place in the lobby)."""


def _presented(stats_file: Path) -> tuple[float, int]:
    """(time, frames presented) from a device's ``--stats`` file, once it was rewritten."""
    start = time.time_ns()
    wait_until(lambda: stats_file.exists() and stats_file.stat().st_mtime_ns > start, 10,
               "a fresh --stats file")
    return time.monotonic(), json.loads(stats_file.read_text())["frames_presented"]


def _flood_model(work: Path, args: argparse.Namespace, tiny: Path) -> Path:
    """``--flood-model``, or the 256 px depth model built here (the tiny one with --quick)."""
    if args.flood_model:
        return Path(args.flood_model)
    if args.quick:
        return tiny
    from host.cli import main as eigencast

    db, out = work / "flood.cdb", work / "flood.ecs"
    print("  flood: rendering and fitting the 256 px depth model ...", flush=True)
    assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", "grid:24x6",
                      "--size", "256", "--samples", "160", "--depth"]) == 0
    assert eigencast(["fit", str(db), "-o", str(out), "--depth", "--key",
                      str(tiny.parent / "device.key")]) == 0
    return out


def run_flood(work: Path, model_path: Path, args: argparse.Namespace) -> list[dict[str, Any]]:
    """The device's own orbit frame rate idle and under each unauthenticated flood, with the
    device on one core and the peer on the other (a one-core board, the attacker elsewhere),
    then with both free to use either core."""
    model_path = _flood_model(work, args, model_path)
    device = _keyed_device(work, "flood", model_path)
    assert device.stop() == 0
    return [_flood_runs(work, model_path, args, pinned) for pinned in (True, False)]


def _flood_runs(work: Path, model_path: Path, args: argparse.Namespace,
                pinned: bool) -> dict[str, Any]:
    stats_file = work / "flood-stats.json"
    cmd_prefix = ["taskset", "-c", "0"] if pinned else []
    flash = work / "flood-flash"
    env_note = ("device on core 0, peer on core 1" if pinned
                else "device and peer on either core")
    env = dict(os.environ, PYTHONUNBUFFERED="1", OPENBLAS_NUM_THREADS="1",
               OMP_NUM_THREADS="1")
    proc = subprocess.Popen(
        [*cmd_prefix, sys.executable, "-m", "device_runtime.cli", "--listen", "127.0.0.1:0",
         "--flash", str(flash), "--key", str(KEY_FILE), "--headless",
         "--standalone", "--orbit", "turn:10", "--stats", str(stats_file)],
        cwd=REPO, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
    url = None
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if "listening on" in line:
            url = "socket://" + line.rsplit("tcp-listen://", 1)[1].strip()
            break
    assert url, "".join(lines)
    threading.Thread(target=lambda: [lines.append(x) for x in proc.stderr], daemon=True).start()
    out: dict[str, Any] = {"note": env_note, "window_s": args.flood_seconds, "runs": [],
                           "model": model_path.name}
    try:
        time.sleep(2.0)  # the orbit is running
        for flood, n in (("idle", 0), *FLOODS, ("idle", 0)):
            peers = None if flood == "idle" else keyless_peers.spawn(
                url, flood, n, cpu=1 if pinned else None)
            try:
                time.sleep(1.0)
                t0, f0 = _presented(stats_file)
                time.sleep(args.flood_seconds)
                t1, f1 = _presented(stats_file)
            finally:
                counts = keyless_peers.finish(peers) if peers is not None else {}
            out["runs"].append({"flood": flood if n <= 1 else f"{flood} x{n}",
                                "fps": (f1 - f0) / (t1 - t0),
                                "peer_bytes": counts.get("bytes", 0),
                                "peer_reconnects": counts.get("connections", 0)})
    finally:
        proc.terminate()
        proc.wait(10)
    idle = [r["fps"] for r in out["runs"] if r["flood"] == "idle"]
    out["idle_fps"] = sum(idle) / len(idle)
    for r in out["runs"]:
        r["ratio"] = r["fps"] / out["idle_fps"]
    return out


def report_flood(out: dict[str, Any]) -> None:
    print(f"\n### Unauthenticated floods against the device's own orbit ({out['model']}, "
          f"{out['note']}, {out['window_s']:g} s windows)\n")
    print("| flood | frames/s | / idle | peer bytes sent | peer connections |")
    print("|---|---|---|---|---|")
    for r in out["runs"]:
        print(f"| {r['flood']} | {r['fps']:.1f} | {r['ratio']:.2f} | {r['peer_bytes']:,} | "
              f"{r['peer_reconnects']} |")


# --------------------------------------------------------------------------- lobby CPU

LOBBY_FLOODS = ("ping", "view", "zeros", "garbage")


def run_lobby_cpu(work: Path, args: argparse.Namespace) -> list[dict[str, Any]]:
    """The CPU time the device's thread really spends under each one-peer flood (its own
    clock, ``pthread_getcpuclockid``) against what the lobby charges to the peer
    (`LobbyStats.cpu_s`), after its idle rate measured in the same run; an in-process keyed
    device on TCP, the peer a process of its own."""
    from provision_helpers import DeviceThread

    out = []
    for flood in LOBBY_FLOODS:
        flash = work / f"lobby-{flood}"
        with DeviceThread("tcp-listen://127.0.0.1:0", flash, key=KEY,
                          auth_timeout_s=600) as dev:
            clock = time.pthread_getcpuclockid(dev.thread.ident)
            t0, c0 = time.monotonic(), time.clock_gettime(clock)
            time.sleep(2.0)
            idle = (time.clock_gettime(clock) - c0) / (time.monotonic() - t0)
            peers = keyless_peers.spawn(f"socket://127.0.0.1:{dev.transport.port}", flood, 1)
            try:
                wait_until(lambda: dev.device.lobby is not None
                           and dev.device.lobby.stats.cpu_s > 0, 20, "the flood")
                lobby = dev.device.lobby
                t0, c0 = time.monotonic(), time.clock_gettime(clock)
                charged0, read0 = lobby.stats.cpu_s, lobby.stats.bytes_read
                time.sleep(args.flood_seconds)
                elapsed = time.monotonic() - t0
                out.append({"flood": flood, "idle": idle, "window_s": elapsed,
                            "thread": (time.clock_gettime(clock) - c0) / elapsed,
                            "charged": (lobby.stats.cpu_s - charged0) / elapsed,
                            "read_mb_s": (lobby.stats.bytes_read - read0) / elapsed / 1e6})
            finally:
                keyless_peers.finish(peers)
    return out


def report_lobby_cpu(rows: list[dict[str, Any]]) -> None:
    print(f"\n### The device thread's CPU under one unauthenticated peer's flood "
          f"({rows[0]['window_s']:.0f} s windows)\n")
    print("| flood | device thread, % of a core | charged to the peer | read MB/s | idle |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['flood']} | {100 * r['thread']:.1f} % | {100 * r['charged']:.1f} % | "
              f"{r['read_mb_s']:.2f} | {100 * r['idle']:.1f} % |")


# --------------------------------------------------------------------------- rest

REST_CASES = {"resting": "30,10", "pole": "0,-90", "dragged": None}


def _dragged_device(flash: Path, model_path: Path, seconds: float, *,
                    predict: bool = True) -> tuple[Any, str, Any]:
    """An in-process keyed device on TCP holding the model, and a thread that drags its view
    for ``seconds`` (input actions, as a window sends them) and then lets go."""
    from device_runtime.display import ViewDelta

    device = RuntimeThread(flash, "tcp-listen://127.0.0.1:0", frames=None, predict=predict,
                           config=DeviceConfig(flash_dir=flash, key=KEY))
    wait_until(lambda: device.device.transport is not None, 10, "the device listening")
    url = f"socket://127.0.0.1:{device.device.transport.port}"
    provision(model_path, url, ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=_quiet))

    def drag() -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not device.stop_event.is_set():
            device.device.apply(ViewDelta(2.0, -1.0))
            time.sleep(0.03)

    return device, url, threading.Thread(target=drag, daemon=True)


#: How ``serve`` serves in the rest section: (serve's extra arguments, the device's): the one
#: path to a device that makes its own frames, ray-cast scores to one that does not (an
#: older device), interpolated scores when the volume cannot be loaded.
REST_MODES = {"correct": ((), ()), "motion": ((), ("--no-predict",)),
              "interpolate": (("--volume", "/nonexistent/volume.mhd"), ("--no-predict",))}


def run_rest(work: Path, model_path: Path, args: argparse.Namespace) -> list[dict[str, Any]]:
    """Every way of serving (`REST_MODES`) for ``--rest-seconds`` to a resting, a pole and a
    dragged then released device, the modes of a case at once (one device each)."""
    modes = tuple(REST_MODES)

    keyf = KEY_FILE
    base = _keyed_device(work, "rest", model_path)
    assert base.stop() == 0
    results = []
    for case, view in REST_CASES.items():
        print(f"  rest: {case}, {len(modes)} modes x {args.rest_seconds:g} s ...",
              flush=True)
        devices, serves = [], []
        for mode in modes:
            flash = work / f"rest-{case}-{mode}"
            shutil.copytree(work / "rest-flash", flash)
            serve_args, device_args = REST_MODES[mode]
            if view is None:
                device, url, drag = _dragged_device(flash, model_path, args.rest_seconds / 3,
                                                    predict=not device_args)
            else:
                device = DeviceProcess(flash, "--headless", "--view", view, *device_args,
                                       key_file=keyf)
                url, drag = device.url, None
            devices.append(device)
            serves.append(subprocess.Popen(
                [sys.executable, "-m", "host.cli", "serve", str(model_path), "--port", url,
                 "--key", str(keyf), *serve_args, "--duration", f"{args.rest_seconds:g}"],
                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
            if drag is not None:
                drag.start()
        for mode, proc, device in zip(modes, serves, devices, strict=True):
            try:
                out, err = proc.communicate(timeout=args.rest_seconds + 120)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, err = proc.communicate()
            line = next((x for x in out.splitlines() if x.startswith("served")), "")
            frames = int(line.split(": ", 1)[1].split()[0]) if line else 0
            ok = proc.returncode == 0 and "Traceback" not in err and frames >= 1
            results.append({"case": case, "mode": mode, "ok": ok, "exit": proc.returncode,
                            "frames": frames, "traceback": "Traceback" in err,
                            "last_line": (err.strip().splitlines() or [""])[-1][:160]})
            stopped = device.stop()
            if isinstance(device, DeviceProcess) and stopped != 0:
                results[-1]["ok"] = False
    return results


def report_rest(results: list[dict[str, Any]], args: argparse.Namespace) -> None:
    print(f"\n### serve against a resting device ({args.rest_seconds:g} s per run)\n")
    modes = list(dict.fromkeys(r["mode"] for r in results))
    print("| device | " + " | ".join(modes) + " |")
    print("|---|" + "---|" * len(modes))
    for case in dict.fromkeys(r["case"] for r in results):
        cells = []
        for mode in modes:
            r = next(x for x in results if x["case"] == case and x["mode"] == mode)
            cells.append(f"{'ok' if r['ok'] else 'FAILED'}, {r['frames']} frames")
        print(f"| {case} | " + " | ".join(cells) + " |")
    for r in results:
        if not r["ok"]:
            print(f"\n{r['case']} / {r['mode']}: exit {r['exit']}: {r['last_line']}")


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
    print("\nA PING had to be sent again (no PONG within 0.25 s: a window's frames dropped by a "
          "full receive queue, or on TCP held back by the lobby's CPU budget for peers that "
          "have not authenticated) in "
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
    parser.add_argument("--sections", default="fuzz,lockout,flood,rest")
    parser.add_argument("--tries", type=int, default=10,
                        help="lockout: key-holder provisions per attack")
    parser.add_argument("--auth-timeout", type=float, default=5.0,
                        help="lockout: the device's --auth-timeout")
    parser.add_argument("--flood-seconds", type=float, default=10.0,
                        help="flood: seconds of each measurement window")
    parser.add_argument("--flood-model", metavar="ECS",
                        help="flood: a standalone model signed with the tests' key")
    parser.add_argument("--rest-seconds", type=float, default=60.0,
                        help="rest: seconds each serve runs")
    args = parser.parse_args()
    if args.quick:
        args.inputs, args.tries, args.flood_seconds, args.rest_seconds = 5_000, 3, 4.0, 10.0
    sections = args.sections.split(",")
    work = Path(tempfile.mkdtemp(prefix="bench-fuzz-"))
    try:
        model_path = tiny_model(_Factory(work), name="fuzz")
        global KEY_FILE
        KEY_FILE = model_path.parent / "device.key"
        from host.fit.model import HostModel

        model = HostModel.load(model_path)
        k, tag = model.image.n_coefficients, model.digest[:4]
        results, failed = [], False
        if "fuzz" in sections:
            for name in args.transports.split(","):
                print(f"{name}: {args.inputs:,} inputs ...", flush=True)
                run = run_tcp if name == "tcp" else run_mem
                results.append(run(work, model_path, args, k, tag))
            report(results, args)
            failed |= any(r["restarts"] or r.get("pids", 1) != 1 for r in results)
        extra: dict[str, Any] = {}
        if "lockout" in sections:
            extra["lockout"] = run_lockout(work, model_path, args)
            report_lockout(extra["lockout"], args)
            failed |= any(r["provision_ok"] < r["tries"] or r["serve_ok"] < r["serve_tries"]
                          or not r["device_alive"] for r in extra["lockout"])
        if "flood" in sections:
            extra["flood"] = run_flood(work, model_path, args)
            for out in extra["flood"]:
                report_flood(out)
                failed |= any(r["ratio"] < 0.8 for r in out["runs"])
        if "lobby" in sections:
            extra["lobby"] = run_lobby_cpu(work, args)
            report_lobby_cpu(extra["lobby"])
            # the lobby's budget (docs/protocol.md 5.2): 2 % a second per peer, and crumbs
            failed |= any(r["thread"] > 0.06 for r in extra["lobby"])
        if "rest" in sections:
            extra["rest"] = run_rest(work, model_path, args)
            report_rest(extra["rest"], args)
            failed |= any(not r["ok"] for r in extra["rest"])
        if args.json:
            print(json.dumps({"fuzz": results, **extra}, indent=1))
        return 1 if failed else 0
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
