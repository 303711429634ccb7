"""``eigencast serve`` and the link, with the real commands: a device that is not there, a
device lost mid-session while ``--duration`` runs, and ``--provision`` of an older image
(``--force``)."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys
import threading

import pytest
from provision_helpers import KEY, REPO, DeviceProcess
from runtime_helpers import key_file

from device_runtime.runtime import parse_orbit
from host.cli import main as eigencast
from host.link import provision, serve
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts

CLI = [sys.executable, "-m", "host.cli"]


def _quiet(line: str) -> None:
    pass


def _closed_port() -> int:
    """A local TCP port nothing listens on (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_serve_to_a_port_where_nothing_listens_is_one_line(model_path):
    """It retried forever (``reconnecting in 2.00 s``) and ignored --duration; reconnecting
    is for a link that was up."""
    url = f"socket://127.0.0.1:{_closed_port()}"
    try:
        run = subprocess.run([*CLI, "serve", str(model_path), "--port", url, "--key",
                              str(key_file(model_path)), "--duration", "3"],
                             capture_output=True, text=True, timeout=60, cwd=REPO)
    except subprocess.TimeoutExpired:
        pytest.fail("serve to a closed port did not end")
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 1 and len(lines) == 1, run.stderr
    assert "refused" in lines[0] and url in lines[0], lines
    assert "reconnecting" not in run.stderr and run.stdout == "", run.stdout


def _provision_and_serve(device: DeviceProcess, model_path,
                         *args: str) -> tuple[subprocess.Popen, str]:
    """Provision ``model_path`` onto ``device`` and start ``eigencast serve`` to it (more
    ``args``); once it streams, the process and the first line it logged."""
    provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=_quiet))
    serving = subprocess.Popen(
        [*CLI, "serve", str(model_path), "--port", device.url, "--key",
         str(key_file(model_path)), *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    first = serving.stderr.readline()  # "serving tooth.ecs to device ..." once it streams
    assert "serving" in first, first
    return serving, first


def test_duration_holds_while_reconnecting(tmp_path, model_path):
    """A device killed mid-session: serve reconnects, and stops when --duration is over."""
    device = DeviceProcess(tmp_path / "flash", "--headless", key_file=key_file(model_path))
    try:
        serving, first = _provision_and_serve(device, model_path, "--duration", "4")
    finally:
        device.kill()
    try:
        out, err = serving.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        serving.kill()
        pytest.fail("serve --duration 4 went on reconnecting after the device was gone")
    err = first + err
    assert serving.returncode == 0, err
    assert "reconnecting" in err and "Traceback" not in err, err
    assert "served" in out and "to device 'eigencast-device'" in out, out


@pytest.fixture(scope="module")
def newer_model(tmp_path_factory, model_path):
    """The tiny model fitted again: a newer image generation of the same database."""
    out = tmp_path_factory.mktemp("newer") / "newer.ecs"
    assert eigencast(["fit", str(model_path.parent / "tooth.cdb"), "-o", str(out), "--cell",
                      "12", "--threshold", "0.99", "--standalone", "--key",
                      str(key_file(model_path))]) == 0
    return out


def test_serve_provision_of_an_older_image_says_force_and_has_it(tmp_path, model_path,
                                                                newer_model):
    """``serve --provision`` told the user to pass a --force it did not have."""
    device = DeviceProcess(tmp_path / "flash", "--headless", key_file=key_file(model_path))
    keyf = str(key_file(model_path))
    try:
        provision(newer_model, device.url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=_quiet))
        base = [*CLI, "serve", str(model_path), "--port", device.url, "--key", keyf,
                "--provision", "--max-frames", "1", "--orbit",
                "steps:1", "--fps", "0"]
        refused = subprocess.run(base, capture_output=True, text=True, timeout=60, cwd=REPO)
        lines = refused.stderr.strip().splitlines()
        assert refused.returncode == 1, refused.stderr
        assert "ROLLBACK_REFUSED" in lines[-1] and "--force" in lines[-1], lines
        forced = subprocess.run([*base, "--force"], capture_output=True, text=True,
                                timeout=60, cwd=REPO)
        assert forced.returncode == 0, forced.stderr
        assert "1 frames" in forced.stdout, forced.stdout
        alone = subprocess.run([*CLI, "serve", str(model_path), "--port", device.url,
                                "--force"], capture_output=True, text=True, timeout=60,
                               cwd=REPO)
        assert alone.returncode == 1 and "--provision" in alone.stderr, alone.stderr
        assert len(alone.stderr.strip().splitlines()) == 1, alone.stderr
    finally:
        assert device.stop() == 0, "\n".join(device.lines[-10:])


class _Door:
    """A TCP port in front of a device that hangs up on the first ``drops`` connections once
    they have sent something (as a keyed device's lobby does when it gives a slow host's
    place to another connection) and joins the later ones to the device."""

    def __init__(self, device_port: int, drops: int) -> None:
        self.device_port, self.drops = device_port, drops
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.accepted = 0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.accepted += 1
            if self.accepted <= self.drops:
                conn.recv(64)  # the host's HELLO
                conn.close()
                continue
            device = socket.create_connection(("127.0.0.1", self.device_port))
            for a, b in ((conn, device), (device, conn)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(src: socket.socket, dst: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := src.recv(65536):
                dst.sendall(data)
        with contextlib.suppress(OSError):
            dst.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        self.server.close()


def test_a_device_that_hangs_up_before_the_session_is_tried_again(tmp_path, model_path):
    """A keyed device's lobby may give a slow host's place to another connection before it
    authenticated (all keyless peers on one address): serve tries again a few times, also
    with reconnect off (that is for a link that was up); past that it is one line, exit 1.
    A port where nothing listens is still one line at once (above)."""
    device = DeviceProcess(tmp_path / "flash", "--headless", key_file=key_file(model_path))
    try:
        provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=_quiet))
        port = int(device.url.rsplit(":", 1)[1])
        door = _Door(port, drops=2)
        said: list[str] = []
        stats = serve(model_path, door.url,
                      ServeOptions(key=KEY, orbit=parse_orbit("steps:1:20"), fps=0,
                                   reconnect=False, stats_every_s=0), ServeParts(log=said.append))
        door.close()
        assert stats.frames == 1 and door.accepted == 3, said
        assert sum("hung up before the session began" in line for line in said) == 2, said
        shut = _Door(port, drops=100)
        run = subprocess.run([*CLI, "serve", str(model_path), "--port", shut.url, "--key",
                              str(key_file(model_path)), "--duration", "30"],
                             capture_output=True, text=True, timeout=60, cwd=REPO)
        shut.close()
        assert run.returncode == 1, run.stderr
        assert shut.accepted == 5, run.stderr  # the first and its four tries again
        last = run.stderr.strip().splitlines()[-1]
        assert "eigencast serve: error:" in last and "Traceback" not in run.stderr, run.stderr
    finally:
        assert device.stop() == 0, "\n".join(device.lines[-10:])


def test_ctrl_c_ends_serve_with_130_after_its_summary(tmp_path, model_path):
    """Ctrl-C ends serving cleanly (BYE, the summary) and exits 130 as every command (it
    exited 0)."""
    device = DeviceProcess(tmp_path / "flash", "--headless", key_file=key_file(model_path))
    try:
        serving, first = _provision_and_serve(device, model_path)
        serving.send_signal(signal.SIGINT)
        try:
            out, err = serving.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            serving.kill()
            pytest.fail("serve did not end on Ctrl-C")
    finally:
        device.stop()
    assert serving.returncode == 130, first + err
    assert "served" in out and "Traceback" not in err, (out, err)
