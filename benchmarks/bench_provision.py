"""Provisioning throughput as a fraction of the raw link rate, measured in the same run.

Usage::

    python benchmarks/bench_provision.py [--quick | --full] [--json]
        [--serial-mb-115200 MB] [--serial-mb-921600 MB] [--tcp-mb MB]

Rows (each with an incompressible image, "raw", and one whose zstd sections compress well,
"zstd"):

* ``mem 115200`` / ``mem 921600``: the paced in-memory serial line (``mem://``, 8N1, flow
  control, 1 ms receive tick), device in a thread of this process. The link rate is given
  two ways: ``baud / 10`` bytes/s, and a raw byte blast of the same size through the same
  kind of line measured just before (what the line model really delivers).
* ``tcp``: TCP loopback to ``eigencast-device --listen`` in a separate process, against a raw
  socket blast of the same bytes between two processes measured in the same run.
* ``lossy 921600``: the paced line losing about 2-3 % of frames, with each loss-recovery
  strategy (``selective`` and ``go-back-n``), as a fraction of ``baud / 10``.
* ``ping during transfer``: round-trip times of PINGs sent while chunks stream at 115200 baud
  (how long a control or view request waits behind image chunks).

``wire B/s`` is image bytes delivered per second of transfer; ``eigenspace B/s`` is the
decompressed size of the image's sections per second (what the zstd sections buy).

By default the serial rows send a short image and *extrapolate* to 50 MB (the rate is
constant once the window is full); ``--full`` sends a real 50 MB image over the paced
921600-baud line (about 9-10 minutes). TCP always uses the full size unless ``--quick``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from provision_helpers import KEY, DeviceProcess, DeviceThread, make_image, mem_name  # noqa: E402

from host.link.options import ProvisionOptions, ProvisionParts  # noqa: E402
from host.link.provisioning import ProvisionResult, provision  # noqa: E402
from protocol import messages as m  # noqa: E402
from protocol.host_session import HostSession  # noqa: E402
from protocol.image import read_manifest  # noqa: E402
from protocol.image_transfer import send_image  # noqa: E402
from protocol.keys import write_key  # noqa: E402
from protocol.link import CHUNK_OVERHEAD_BYTES, Link  # noqa: E402
from protocol.transport import open_transport  # noqa: E402

MB = 1_000_000
QUIET = ProvisionParts(log=lambda line: None)


def eigenspace_bytes(path: Path) -> int:
    """Decompressed size of all sections of the device image."""
    return sum(int(s["raw_size"]) for s in read_manifest(path)["sections"])


def raw_line_blast(baud: int, size: int) -> float:
    """Bytes/s of a raw byte stream through a fresh paced mem line (writer + draining reader)."""
    name = mem_name("blast")
    a = open_transport(f"mem://{name}?end=a", baud=baud, timeout_s=30)
    b = open_transport(f"mem://{name}?end=b", baud=baud, timeout_s=30)
    data = os.urandom(size)
    got = [0]
    done = threading.Event()

    def reader() -> None:
        while got[0] < size:
            got[0] += len(b.read(1 << 16, 1.0))
        done.set()

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    start = time.perf_counter()
    for i in range(0, size, 4096):
        a.write(data[i:i + 4096])
    done.wait(size / (baud / 10) * 3 + 10)
    elapsed = time.perf_counter() - start
    a.close()
    b.close()
    return size / elapsed


def _blast_server(port_file: str, size: int) -> None:  # runs in a child process
    server = socket.create_server(("127.0.0.1", 0))
    Path(port_file).write_text(str(server.getsockname()[1]))
    conn, _ = server.accept()
    left = size
    while left > 0:
        chunk = conn.recv(1 << 20)
        if not chunk:
            break
        left -= len(chunk)
    conn.sendall(b"k")
    conn.close()


def raw_tcp_blast(size: int) -> float:
    """Bytes/s of ``size`` bytes over TCP loopback to another process (sendall, recv)."""
    with tempfile.TemporaryDirectory() as tmp:
        port_file = Path(tmp) / "port"
        child = subprocess.Popen([sys.executable, __file__, "--blast-server", str(port_file),
                                  str(size)])
        deadline = time.monotonic() + 20
        while not port_file.exists() or not port_file.read_text():
            if time.monotonic() > deadline:
                raise RuntimeError("blast server did not start")
            time.sleep(0.01)
        port = int(port_file.read_text())
        data = os.urandom(min(size, 8 << 20))
        with socket.create_connection(("127.0.0.1", port)) as sock:
            start = time.perf_counter()
            sent = 0
            while sent < size:
                piece = data[: min(len(data), size - sent)]
                sock.sendall(piece)
                sent += len(piece)
            sock.recv(1)
            elapsed = time.perf_counter() - start
        child.wait(timeout=20)
    return size / elapsed


def _transfer_row(result: ProvisionResult, path: Path) -> dict:
    """What one provisioning of the image at ``path`` measured (``result``: its
    provisioning result)."""
    return {
        "size_bytes": result.size_bytes,
        "eigenspace_bytes": eigenspace_bytes(path),
        "seconds": result.transfer_seconds,
        "wire_bytes_per_s": result.rate_bytes_per_s,
        "retransmitted_chunks": result.retransmitted_chunks,
        "verified": result.verified,
    }


def bench_mem(baud: int, size: int, compressible: bool, tmp: Path, *, faults: str = "",
              retransmit: str = "selective") -> dict:
    path = tmp / f"mem{baud}-{compressible}-{size}-{retransmit}.ecs"
    make_image(path, size_bytes=size, compressible=compressible)
    name = mem_name("bench")
    with DeviceThread(f"mem://{name}?end=b", tmp / f"flash-{name}", baud=baud):
        result = provision(path, f"mem://{name}?end=a{faults}",
                           ProvisionOptions(baud=baud, key=KEY, retransmit=retransmit,
                                            show_progress=False),
                           QUIET)
    return _transfer_row(result, path)


def bench_tcp(size: int, compressible: bool, tmp: Path) -> dict:
    path = tmp / f"tcp-{compressible}-{size}.ecs"
    make_image(path, size_bytes=size, compressible=compressible)
    write_key(tmp / f"tcp-{compressible}-{size}.key", KEY)
    dev = DeviceProcess(tmp / f"flash-tcp-{compressible}-{size}",
                        key_file=tmp / f"tcp-{compressible}-{size}.key")
    try:
        result = provision(path, dev.url, ProvisionOptions(key=KEY, show_progress=False),
                           QUIET)
    finally:
        dev.stop()
    return _transfer_row(result, path)


def ping_during_transfer(baud: int, tmp: Path, pings: int = 8) -> dict:
    """RTTs of PINGs sent while an image streams (chunks sized for the line)."""
    path = tmp / "ping.ecs"
    image = make_image(path, size_bytes=int(baud / 10 * 4))
    import hashlib

    name = mem_name("ping")
    with DeviceThread(f"mem://{name}?end=b", tmp / f"flash-{name}", baud=baud):
        link = Link(open_transport(f"mem://{name}?end=a", baud=baud), owns_transport=True)
        link.start()
        session = HostSession(link, key=KEY)
        hello = session.start()
        idle = [session.ping() for _ in range(3)]
        box: dict = {}
        ack = session.call(
            m.ImageBegin(size_bytes=len(image), digest=hashlib.sha256(image).digest(),
                         image_tag=image[-32:], format_version=1, generation=1),
            on_reply=lambda rid, reply: box.setdefault("id", rid))
        from host.link.provisioning import choose_chunk_bytes

        chunk = choose_chunk_bytes(link.transport, hello, link)
        link.tx_low_water_bytes = chunk + CHUNK_OVERHEAD_BYTES  # as provision() does
        sender = threading.Thread(target=send_image, args=(link, image), kwargs={
            "transfer_id": box["id"], "first_ack": ack, "chunk_bytes": chunk,
            "tag": session.tag_event}, daemon=True)
        sender.start()
        time.sleep(0.5)  # let the window fill
        busy = []
        for _ in range(pings):
            busy.append(session.ping())
            time.sleep(0.1)
        sender.join()
        link.close()
    return {"baud": baud, "chunk_bytes": chunk, "chunk_wire_ms": chunk / (baud / 10) * 1e3,
            "idle_rtt_ms": min(idle) * 1e3, "busy_rtt_ms_max": max(busy) * 1e3,
            "busy_rtt_ms_median": sorted(busy)[len(busy) // 2] * 1e3}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small images (smoke run)")
    parser.add_argument("--full", action="store_true",
                        help="send a real 50 MB image over the paced 921600 line (~9 min)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--serial-mb-115200", type=float, default=0.15)
    parser.add_argument("--serial-mb-921600", type=float, default=1.5)
    parser.add_argument("--tcp-mb", type=float, default=50.0)
    parser.add_argument("--target-mb", type=float, default=50.0,
                        help="size the serial rows are extrapolated to")
    parser.add_argument("--blast-server", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.blast_server:
        _blast_server(args.blast_server[0], int(args.blast_server[1]))
        return 0
    if args.quick:
        args.serial_mb_115200, args.serial_mb_921600, args.tcp_mb = 0.03, 0.2, 2.0
    if args.full:
        args.serial_mb_921600 = args.target_mb
    rows = []
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        for baud, mb in ((115200, args.serial_mb_115200), (921600, args.serial_mb_921600)):
            size = int(mb * MB)
            blast = raw_line_blast(baud, min(size, int(baud / 10 * 3)))
            for compressible in (False, True):
                r = bench_mem(baud, size, compressible, tmp)
                r.update(row=f"mem {baud}", image="zstd" if compressible else "raw",
                         link_bytes_per_s=baud / 10, blast_bytes_per_s=blast)
                rows.append(r)
        size = int(args.tcp_mb * MB)
        blast = raw_tcp_blast(size)
        for compressible in (False, True):
            r = bench_tcp(size, compressible, tmp)
            r.update(row="tcp", image="zstd" if compressible else "raw",
                     link_bytes_per_s=blast, blast_bytes_per_s=blast)
            rows.append(r)
        lossy = "&burst=5e-6&burst_bytes=200&drop=1e-6&seed=5"  # ~2-3 % of 4 KiB frames
        for strategy in ("selective", "go-back-n"):
            r = bench_mem(921600, int(min(args.serial_mb_921600, 1.5) * MB), False, tmp,
                          faults=lossy, retransmit=strategy)
            r.update(row=f"lossy 921600 {strategy}", image="raw", link_bytes_per_s=92160.0,
                     blast_bytes_per_s=None)
            rows.append(r)
        latency = ping_during_transfer(115200, tmp, pings=4 if args.quick else 8)
    for r in rows:
        r["fraction_of_link"] = r["wire_bytes_per_s"] / r["link_bytes_per_s"]
        r["fraction_of_blast"] = (r["wire_bytes_per_s"] / r["blast_bytes_per_s"]
                                  if r["blast_bytes_per_s"] else None)
        r["eigenspace_bytes_per_s"] = r["eigenspace_bytes"] / r["seconds"]
        r["extrapolated_50mb_s"] = args.target_mb * MB / r["wire_bytes_per_s"]
    if args.json:
        print(json.dumps({"rows": rows, "ping_during_transfer": latency}, indent=2))
        return 0
    print(f"{'row':<26}{'image':>6}{'size':>11}{'wire B/s':>12}{'of link':>9}{'of blast':>9}"
          f"{'eigensp B/s':>13}{'retx':>6}{'50 MB (s)':>11}")
    for r in rows:
        blast = "" if r["fraction_of_blast"] is None else f"{100 * r['fraction_of_blast']:.1f}%"
        print(f"{r['row']:<26}{r['image']:>6}{r['size_bytes']:>11}{r['wire_bytes_per_s']:>12.0f}"
              f"{100 * r['fraction_of_link']:>8.1f}%{blast:>9}{r['eigenspace_bytes_per_s']:>13.0f}"
              f"{r['retransmitted_chunks']:>6}{r['extrapolated_50mb_s']:>11.0f}")
    print("link: mem rows = baud/10 (8N1); tcp = raw socket blast between two processes. "
          "'50 MB (s)' extrapolates the measured rate" + ("" if args.full else
          " (serial rows sent a shorter image; --full sends 50 MB at 921600)."))
    print(f"ping during transfer at {latency['baud']} baud: chunk {latency['chunk_bytes']} B "
          f"({latency['chunk_wire_ms']:.0f} ms on the wire), RTT idle "
          f"{latency['idle_rtt_ms']:.1f} ms, busy median {latency['busy_rtt_ms_median']:.1f} ms,"
          f" max {latency['busy_rtt_ms_max']:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
