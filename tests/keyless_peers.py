"""Keyless peers that try to keep a key holder out of a TCP device, or to slow its display.

Run as a process of its own (so the attack does not share an interpreter, and its lock, with
the key holder or the device being measured)::

    python tests/keyless_peers.py socket://127.0.0.1:PORT --mode loop --threads 16 \\
        [--seconds S] [--bind 127.0.0.2] [--hold N]

It prints ``started`` once each thread has connected (or after 10 s), and at the end
(``--seconds``, SIGTERM or SIGINT) one JSON line of counts. Modes:

* ``loop`` (the finding): each thread opens a connection, says HELLO and, the moment the
  device answers, opens the next one; it keeps its last ``--hold`` connections open
  (default 2: the previous one stays until the next is answered).
* ``flood``: each thread opens connections as fast as it can, says HELLO on each without
  waiting for any answer, and keeps its last ``--hold`` open (default 32): the reconnect
  loop judged worst, bounded only by how fast the device (or the kernel) accepts.
* ``ping``, ``view``, ``zeros``, ``garbage``: one connection per thread says HELLO, then
  sends PINGs, VIEW_REQUESTs, zero bytes (empty frames) or bytes with no frame delimiter
  (no 0x00: reads that complete no frame) as fast as the socket takes them (work for a
  peer that holds a slot without authenticating).

``--bind`` sends from another local address (127.0.0.2...: every 127/8 address is the
loopback on Linux), as peers on other machines would.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from protocol import messages as m

MODES = ("loop", "flood", "ping", "view", "zeros", "garbage")


def _hello() -> bytes:
    return m.Hello(min_version=1, max_version=m.PROTOCOL_VERSION, nonce=os.urandom(16),
                   host_id="keyless").encode(request_id=1)


class Peers:
    """``threads`` attack threads against ``url`` (``socket://HOST:PORT``) in ``mode``."""

    def __init__(self, url: str, mode: str, threads: int, *, bind: str | None = None,
                 hold: int | None = None) -> None:
        if mode not in MODES:
            raise ValueError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
        parts = urllib.parse.urlsplit(url)
        self.address = (parts.hostname, parts.port)
        self.mode, self.bind = mode, bind
        self.hold = hold or (32 if mode == "flood" else 2)
        self.stop = threading.Event()
        self.counts = collections.Counter()
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._run, daemon=True, name=f"peer-{i}")
                         for i in range(threads)]

    def start(self) -> Peers:
        for thread in self._threads:
            thread.start()
        return self

    def close(self) -> dict[str, int]:
        self.stop.set()
        for thread in self._threads:
            thread.join(10)
        return dict(self.counts)

    def _count(self, what: str, n: int = 1) -> None:
        with self._lock:
            self.counts[what] += n

    def _connect(self) -> socket.socket | None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            if self.bind:
                sock.bind((self.bind, 0))
            sock.settimeout(2.0)
            sock.connect(self.address)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.sendall(_hello())
        except OSError:
            sock.close()
            self._count("connect_failed")
            self.stop.wait(0.01)
            return None
        self._count("connections")
        return sock

    def _run(self) -> None:
        held: collections.deque[socket.socket] = collections.deque()
        try:
            if self.mode in ("loop", "flood"):
                self._reconnect(held)
            else:
                self._flood_one(held)
        finally:
            for sock in held:
                sock.close()

    def _reconnect(self, held: collections.deque) -> None:
        while not self.stop.is_set():
            sock = self._connect()
            if sock is None:
                continue
            held.append(sock)
            while len(held) > self.hold:
                held.popleft().close()
            if self.mode == "loop":  # wait for the device's answer (or for it to drop us)
                while not self.stop.is_set():
                    ready, _, _ = select.select([sock], [], [], 0.1)
                    if ready:
                        with contextlib.suppress(OSError):
                            if sock.recv(4096):
                                self._count("answered")
                        break

    def _flood_one(self, held: collections.deque) -> None:
        payload = {
            "ping": m.Ping(payload=b"p" * 8, sent_us=1).encode(request_id=9) * 64,
            "view": m.ViewRequest(phi_deg=10.0, theta_deg=5.0, sequence=1).encode() * 64,
            "zeros": bytes(4096),
            "garbage": bytes(range(1, 256)) * 16,
        }[self.mode]
        while not self.stop.is_set():
            sock = self._connect()
            if sock is None:
                continue
            held.append(sock)
            sock.setblocking(False)
            while not self.stop.is_set():
                try:
                    _, ready, _ = select.select([], [sock], [], 0.1)
                    if ready:
                        self._count("bytes", sock.send(payload))
                    ready, _, _ = select.select([sock], [], [], 0)
                    if ready and not sock.recv(1 << 16):
                        break  # the device dropped us: connect again
                except OSError:
                    break
            held.remove(sock)
            sock.close()
            self._count("dropped")


def spawn(url: str, mode: str, threads: int, *, bind: str | None = None,
          hold: int | None = None, cpu: int | None = None) -> subprocess.Popen:
    """Start the peers as a process of their own (pinned to core ``cpu`` if given); return
    once each thread has connected (the attack is under way)."""
    cmd = [sys.executable, os.path.abspath(__file__), url, "--mode", mode, "--threads",
           str(threads), *(["--bind", bind] if bind else []),
           *(["--hold", str(hold)] if hold else [])]
    if cpu is not None:
        cmd = ["taskset", "-c", str(cpu), *cmd]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if line.strip() != "started":
        proc.kill()
        raise RuntimeError(f"keyless peers did not start: {line!r}")
    return proc


def finish(proc: subprocess.Popen) -> dict[str, int]:
    """Stop peers started by :func:`spawn`; return their counts."""
    proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        return {"killed": 1}
    lines = out.strip().splitlines()
    return json.loads(lines[-1]) if lines else {}


def timed(cmd: list[str], limit_s: float, *, cwd: str | None = None) -> tuple[bool, float, str]:
    """Run ``cmd``; (exit 0 within ``limit_s``, seconds it took, its stderr's last line).
    It is killed at ``limit_s`` + 10 s (then it did not succeed)."""
    t0 = time.monotonic()
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=limit_s + 10,
                             cwd=cwd)
    except subprocess.TimeoutExpired:
        return False, time.monotonic() - t0, "killed: no answer"
    seconds = time.monotonic() - t0
    tail = (run.stderr.strip().splitlines() or [""])[-1]
    return run.returncode == 0 and seconds <= limit_s, seconds, tail


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("url")
    parser.add_argument("--mode", choices=MODES, default="loop")
    parser.add_argument("--threads", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3600.0)
    parser.add_argument("--bind")
    parser.add_argument("--hold", type=int)
    args = parser.parse_args(argv)
    peers = Peers(args.url, args.mode, args.threads, bind=args.bind, hold=args.hold).start()
    deadline = time.monotonic() + 10.0
    while peers.counts["connections"] < args.threads and time.monotonic() < deadline:
        time.sleep(0.01)
    done = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: done.set())
    print("started", flush=True)
    done.wait(args.seconds)
    print(json.dumps(peers.close()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
