"""End to end: host and device as separate processes over TCP loopback and a pty pair.

Provision, stream an orbit, and check every frame the device wrote against ``eigencast
view`` for the same view (identical pixels); a link cut mid-stream recovers with a key
frame; a device killed mid-stream reboots from flash and resumes without re-provisioning;
a standalone device with no host shows any view.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import threading

import numpy as np
from PIL import Image
from provision_helpers import KEY, REPO, DeviceProcess
from runtime_helpers import check_frames, key_file, read_frames, wait_until

from device_runtime.orbit import parse_orbit
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import serve
from protocol.transport import FdTransport, open_pty_pair

CLI = [sys.executable, "-m", "host.cli"]
DEVICE = [sys.executable, "-m", "device_runtime.cli"]


def _quiet(line: str) -> None:
    pass


def _has_view(folder, phi, theta):
    return any(float(r["phi_deg"]) == phi and float(r["theta_deg"]) == theta
               for r in read_frames(folder))


def test_tcp_provision_and_orbit_frames_equal_eigencast_view(tmp_path, model_path, model):
    frames = tmp_path / "frames"
    keyf = key_file(model_path)
    device = DeviceProcess(tmp_path / "flash", "--headless", "--frames", str(frames),
                           key_file=keyf)
    try:
        run = subprocess.run([*CLI, "provision", str(model_path), "--port", device.url,
                              "--key", str(keyf)], capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, run.stderr
        assert "installed" in run.stdout and "confirmed" in run.stderr
        run = subprocess.run([*CLI, "serve", str(model_path), "--port", device.url, "--key",
                              str(keyf), "--orbit", "steps:12:10", "--fps", "0",
                              # no volume to ray-cast: the device shows its own frames,
                              # which are what `eigencast view` shows
                              "--volume", str(tmp_path / "gone.mhd")],
                             capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, run.stderr
        assert "cannot be ray-cast" in run.stderr
        assert "12 frames (12 corrections of the device's own frames" in run.stdout
        wait_until(lambda: _has_view(frames, 330.0, 10.0), 20, "the orbit's last frame")
    finally:
        assert device.stop() == 0
    assert any("decoded 0 key, 0 delta and 12 correction packets" in line
               for line in device.lines), device.lines[-3:]
    assert check_frames(model, frames) >= 2
    # and literally against the `eigencast view` command for one of them
    row = read_frames(frames)[-1]
    png = tmp_path / "view.png"
    run = subprocess.run([*CLI, "view", str(model_path), "--phi", row["phi_deg"], "--theta",
                          row["theta_deg"], "-o", str(png)], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    np.testing.assert_array_equal(np.asarray(Image.open(frames / row["file"])),
                                  np.asarray(Image.open(png)))


def test_pty_pair_provision_and_stream(tmp_path, model_path, model):
    frames = tmp_path / "frames"
    pty = open_pty_pair()
    proc = subprocess.Popen(
        [*DEVICE, "--port", pty.slave_path, "--flash", str(tmp_path / "flash"), "--key",
         str(key_file(model_path)), "--headless", "--frames", str(frames)],
        cwd=REPO, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"))

    def master(attempt):  # a fresh descriptor per connection; the pty stays open
        return FdTransport(os.dup(pty.master_fd), url=f"pty:{pty.slave_path}",
                           max_frame_bytes=4096)

    try:
        result = provision(model_path, pty.slave_path,
                           ProvisionOptions(key=KEY, show_progress=False),
                           ProvisionParts(log=_quiet, transport_factory=master))
        assert result.outcome == "installed" and result.confirmed
        stats = serve(model_path, pty.slave_path,
                      ServeOptions(key=KEY, scores="interpolate",
                                   orbit=parse_orbit("steps:10:-20"), fps=0),
                      ServeParts(log=_quiet, transport_factory=master))
        assert stats.frames == 10
        wait_until(lambda: _has_view(frames, 324.0, -20.0), 20, "the orbit's last frame")
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=20)
        pty.close()
    assert proc.returncode == 0, err
    assert check_frames(model, frames) >= 2


class CuttingProxy:
    """TCP proxy 127.0.0.1:port -> the device; :meth:`cut` drops the current connection."""

    def __init__(self, target_port: int):
        self.target = ("127.0.0.1", target_port)
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.pairs: list[tuple[socket.socket, socket.socket]] = []
        self.accepted = 0
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            upstream = socket.create_connection(self.target)
            self.pairs.append((client, upstream))
            self.accepted += 1
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(src, dst):
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)

    def cut(self):
        for client, upstream in self.pairs:
            for s in (client, upstream):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()
        self.pairs.clear()

    def close(self):
        self.cut()
        self.server.close()


def _provisioned_process(tmp_path, model_path, frames):
    device = DeviceProcess(tmp_path / "flash", "--headless", "--frames", str(frames),
                           key_file=key_file(model_path))
    provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=_quiet))
    return device


def test_link_cut_mid_stream_recovers_with_a_key_frame(tmp_path, model_path, model):
    frames = tmp_path / "frames"
    device = _provisioned_process(tmp_path, model_path, frames)
    proxy = CuttingProxy(device.port)
    cut_done = threading.Event()

    def on_frame(encoded, view):
        if stats_box.get("n", 0) == 15 and not cut_done.is_set():
            cut_done.set()
            proxy.cut()
        stats_box["n"] = stats_box.get("n", 0) + 1

    stats_box: dict = {}
    try:
        stats = serve(model_path, f"socket://127.0.0.1:{proxy.port}",
                      ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit("steps:40:30"),
                                   fps=40), ServeParts(log=_quiet, on_frame=on_frame))
        wait_until(lambda: _has_view(frames, 351.0, 30.0), 20, "the orbit's last frame")
    finally:
        proxy.close()
        device.stop()
    assert cut_done.is_set() and stats.sessions == 2 and stats.reconnects == 1
    assert proxy.accepted == 2
    rows = read_frames(frames)
    keys = [r for r in rows if r["key"] == "1"]
    assert len(keys) >= 2  # the stream resumed with a key frame after the cut
    assert rows.index(keys[-1]) > 0
    assert check_frames(model, frames, rows) >= 5


def test_device_restarted_mid_stream_boots_from_flash_and_resumes(tmp_path, model_path, model):
    frames = tmp_path / "frames"
    device = _provisioned_process(tmp_path, model_path, frames)
    port = device.port
    frames2 = tmp_path / "frames2"
    restarted = {}

    def on_frame(encoded, view):
        count = restarted.setdefault("n", 0)
        restarted["n"] = count + 1
        if count == 10:  # power cut: SIGKILL, then start again on the same port and flash
            device.kill()
            restarted["device"] = DeviceProcess(tmp_path / "flash", "--headless", "--frames",
                                                str(frames2), port=port,
                                                key_file=key_file(model_path))

    try:
        stats = serve(model_path, f"socket://127.0.0.1:{port}",
                      ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit("steps:36:-5"),
                                   fps=30), ServeParts(log=_quiet, on_frame=on_frame))
        wait_until(lambda: _has_view(frames2, 350.0, -5.0), 20, "the orbit's last frame")
    finally:
        device.stop()
        second = restarted.get("device")
        if second is not None:
            second.stop()
    assert second is not None and not stats.provisioned and stats.sessions == 2
    log = "\n".join(second.lines)
    assert "boot: slot A: confirmed image" in log and "image begin" not in log
    rows = read_frames(frames2)
    # the rebooted device first shows its own prediction of its view (no host frame: the
    # image has the standalone table, issue 14); the host's first packet is a key frame
    served = [r for r in rows if r["host_frame"]]
    assert served and served[0]["key"] == "1"
    assert check_frames(model, frames2, rows) >= 3


def test_standalone_device_shows_views_with_no_host(tmp_path, model_path, model):
    frames = tmp_path / "frames"
    device = _provisioned_process(tmp_path, model_path, tmp_path / "unused")
    device.stop()
    views = "12.5,3;100,-44;250,60;359,0"
    run = subprocess.run([*DEVICE, "--standalone", "--flash", str(tmp_path / "flash"), "--key",
                          str(key_file(model_path)), "--headless", "--frames", str(frames),
                          "--views", views], capture_output=True, text=True, timeout=60,
                         cwd=REPO)
    assert run.returncode == 0, run.stderr
    rows = read_frames(frames)
    assert [(float(r["phi_deg"]), float(r["theta_deg"])) for r in rows[1:]] == [
        (12.5, 3.0), (100.0, -44.0), (250.0, 60.0), (359.0, 0.0)]
    assert check_frames(model, frames, rows) == 5
    run = subprocess.run([*DEVICE, "--standalone", "--flash", str(tmp_path / "empty"),
                          "--headless"], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert run.returncode == 1 and "no image" in run.stderr
    assert len(run.stderr.strip().splitlines()) <= 3 and "Traceback" not in run.stderr


def test_a_wrong_key_is_said_in_plain_words_once(tmp_path, model_path):
    """provision and serve with a key that is not the device's: one line that says "wrong
    key" once (not the protocol's AUTH_FAILED / AUTH_CHALLENGE wording), exit 1."""
    from protocol.keys import write_key

    device_key = tmp_path / "device.key"
    write_key(device_key)  # a fresh key: not the one the host holds
    device = DeviceProcess(tmp_path / "flash", "--headless", key_file=device_key)
    try:
        for command in (["provision", str(model_path)],
                        ["serve", str(model_path), "--orbit", "steps:2:5", "--fps", "0"]):
            run = subprocess.run([*CLI, *command, "--port", device.url, "--key",
                                  str(key_file(model_path))], capture_output=True, text=True,
                                 timeout=60, cwd=REPO)
            lines = run.stderr.strip().splitlines()
            assert run.returncode == 1 and len(lines) == 1, run.stderr
            assert lines[0].count("wrong key") == 1 and "AUTH_" not in lines[0], lines[0]
            assert lines[0].startswith(f"eigencast {command[0]}: error: wrong key: ")
    finally:
        assert device.stop() == 0


def test_a_headless_device_says_what_it_does_and_keeps_the_last_frames(tmp_path, model_path):
    """--headless says in one line what drives the view and where frames go; --frames keeps
    the last --keep-frames PNGs (frames.csv lists them all); with no display and no
    --headless the device says so in its own words (not SDL's XDG_RUNTIME_DIR line) and runs
    headless; no pygame banner on stdout."""
    _provisioned_process(tmp_path, model_path, tmp_path / "unused").stop()
    frames = tmp_path / "frames"
    base = [*DEVICE, "--standalone", "--flash", str(tmp_path / "flash"), "--key",
            str(key_file(model_path))]
    run = subprocess.run([*base, "--headless", "--frames", str(frames), "--keep-frames", "2",
                          "--views", "0,0;60,0;120,0;180,0;240,0;300,0"],
                         capture_output=True, text=True, timeout=60, cwd=REPO)
    assert run.returncode == 0, run.stderr
    plan = [line for line in run.stderr.splitlines() if "headless:" in line]
    assert plan == [f"eigencast-device: headless: shows the --views; writes every frame to "
                    f"{frames} as PNG, keeping the last 2 (--keep-frames)"]
    rows = read_frames(frames)
    assert len(rows) == 7  # the image's first frame (the initial view), then the 6 views
    assert sorted(p.name for p in frames.glob("*.png")) == [rows[-2]["file"], rows[-1]["file"]]
    assert [float(r["phi_deg"]) for r in rows[-2:]] == [240.0, 300.0]
    env = {k: v for k, v in os.environ.items()
           if k not in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER", "XDG_RUNTIME_DIR",
                        "PYGAME_HIDE_SUPPORT_PROMPT")}
    run = subprocess.run([*base, "--views", "10,5"], capture_output=True, text=True,
                         timeout=60, cwd=REPO, env=env)
    assert run.returncode == 0, run.stderr
    assert "XDG_RUNTIME_DIR" not in run.stderr and run.stdout == ""
    said = [line for line in run.stderr.splitlines() if "no display" in line]
    assert said == ["eigencast-device: no display (neither DISPLAY nor WAYLAND_DISPLAY is "
                    "set): running headless: shows the --views; writes no frames (--frames "
                    "DIR writes them as PNGs)"]
    run = subprocess.run([*base, "--headless", "--max-frames", "1"], capture_output=True,
                         text=True, timeout=60, cwd=REPO)
    assert run.returncode == 0, run.stderr
    assert ("headless: shows the view 30,15 once, then waits (--orbit SPEC or --views LIST "
            "drive it), stopping after 1 frame; writes no frames") in run.stderr


def test_an_overflowing_score_packet_does_not_kill_the_device_process(tmp_path, model_path,
                                                                      model):
    """Issue 11 item 1 as reported: step 3e38 and q = 2**31 - 1 made ``eigencast-device``
    exit with status 1. Now the packet is refused at decode and a later frame is shown."""
    from test_scores import overflow_packet

    from protocol import messages as m
    from protocol.host_session import HostSession
    from protocol.link import Link
    from protocol.scores import encode_scores
    from protocol.transport import open_transport

    frames = tmp_path / "frames"
    stats = tmp_path / "stats.json"
    device = DeviceProcess(tmp_path / "flash", "--insecure", "--headless", "--frames",
                           str(frames), "--stats", str(stats))
    try:
        provision(model_path, device.url, ProvisionOptions(key=None, show_progress=False),
                  ProvisionParts(log=_quiet))
        # item 2: a packet from a peer that never sent HELLO is not shown
        stranger = Link(open_transport(device.url, timeout_s=5), owns_transport=True).start()
        stray = encode_scores(model.quantized_scores(44.0, 0.0), step=model.score_step,
                              frame=3, view=(44.0, 0.0), image_digest=model.digest)
        sent = threading.Event()
        stranger.send(m.Scores(sequence=0, packet=stray.packet), after_sent=sent.set)
        assert sent.wait(10)  # on the wire before the PING (control frames go first)
        stranger.request(m.Ping(sent_us=1))  # answered in order: the SCORES was handled
        stranger.close()
        link = Link(open_transport(device.url, timeout_s=5), owns_transport=True).start()
        session = HostSession(link, key=None, request_timeout_s=1.0)
        session.start()
        k = model.image.n_coefficients
        for mode in (0, 2):
            sent = threading.Event()  # each one on the wire (scores are latest-wins)
            session.send_scores(m.Scores(sequence=0, packet=overflow_packet(k, model.digest,
                                                                            mode=mode)),
                                after_sent=sent.set)
            assert sent.wait(10)
        good = encode_scores(model.quantized_scores(33.0, 12.0), step=model.score_step,
                             frame=9, view=(33.0, 12.0), image_digest=model.digest)
        session.send_scores(m.Scores(sequence=0, packet=good.packet))
        wait_until(lambda: _has_view(frames, 33.0, 12.0), 20, "the good frame")
        session.ping()  # still answering
        assert device.proc.poll() is None
        link.close()
    finally:
        assert device.stop() == 0
    assert any("bad score packet dropped" in line and "over the bound" in line
               for line in device.lines)
    check_frames(model, frames)
    assert not _has_view(frames, 44.0, 0.0)
    summary = json.loads(stats.read_text())
    assert summary["link_guard"]["dropped_no_session"] == 1
    assert summary["decode_errors"] == 2
