"""A TCP device that serves a host tells a second one at once that it is busy
(`device_runtime.busy_door`), and still serves, next, a host that connected as the first
one was leaving."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading

import pytest
from provision_helpers import KEY, REPO, DeviceProcess, DeviceThread
from runtime_helpers import key_file, wait_until

from device_runtime import busy_door
from host.link import provision
from host.link.options import ProvisionOptions, ProvisionParts
from protocol import messages as m
from protocol.errors import RemoteBusy
from protocol.host_session import HostSession
from protocol.link import Link
from protocol.transport import open_transport

GOLDEN = REPO / "tests" / "golden" / "messages.jsonl"


def _session(url: str, *, keyed: bool, retries: int = 1) -> HostSession:
    link = Link(open_transport(url, timeout_s=5), owns_transport=True).start()
    return HostSession(link, key=KEY if keyed else None, retries=retries)


@pytest.mark.parametrize("keyed", [True, False])
def test_a_second_host_is_told_busy_not_left_waiting(tmp_path, keyed):
    """It waited unanswered in the listen backlog until its HELLO timed out ("no reply to
    HELLO ... is the device running?", 23-36 s); now its HELLO gets ERROR BUSY."""
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      key=KEY if keyed else None) as dev:
        url = f"socket://127.0.0.1:{dev.transport.port}"
        first = _session(url, keyed=keyed)
        try:
            first.start()
            second = _session(url, keyed=keyed)  # one retry: 3 s unanswered before
            try:
                with pytest.raises(RemoteBusy, match="serving another host"):
                    second.start()
            finally:
                second.link.close()
            first.ping()  # the first host is still served
        finally:
            first.link.close()
        assert dev.device.door.answered == 1


def test_the_busy_answer_is_the_golden_frame(tmp_path):
    """The bytes a second host reads are pinned by tests/golden (``error_busy``), and the
    device closes the connection after them."""
    golden = next(c for c in map(json.loads, GOLDEN.read_text().splitlines())
                  if c["name"] == "error_busy")
    assert golden["kwargs"]["message"] == busy_door.BUSY_MESSAGE
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash", key=None) as dev:
        url = f"socket://127.0.0.1:{dev.transport.port}"
        first = _session(url, keyed=False)
        try:
            first.start()
            with socket.create_connection(("127.0.0.1", dev.transport.port), timeout=10) as sock:
                sock.sendall(m.Hello(min_version=1, max_version=m.PROTOCOL_VERSION,
                                     nonce=os.urandom(16), host_id="second").encode(
                                         request_id=golden["request_id"]))
                got = b""
                while chunk := sock.recv(4096):
                    got += chunk
        finally:
            first.link.close()
    assert got.hex() == golden["frame"]


@pytest.mark.parametrize("keyed", [True, False])
def test_a_host_that_came_as_the_first_left_is_served_next(tmp_path, keyed, monkeypatch):
    """A connection the door holds when the host leaves is the next session's (as if it
    had waited in the backlog): here it connects during the first session (the door holds
    it, its grace made long) and is served once the first host says BYE."""
    monkeypatch.setattr(busy_door, "GRACE_S", 30.0)
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      key=KEY if keyed else None) as dev:
        url = f"socket://127.0.0.1:{dev.transport.port}"
        first = _session(url, keyed=keyed)
        first.start()
        second = _session(url, keyed=keyed, retries=3)
        result: dict = {}

        def start() -> None:
            try:
                result["hello"] = second.start()
            except Exception as exc:  # surfaced below
                result["error"] = exc

        thread = threading.Thread(target=start, daemon=True)
        thread.start()
        try:
            wait_until(lambda: dev.device.door.held == 1, 10, "the door holding the second")
            first.bye("done")
            first.link.close()
            thread.join(30)
            assert "error" not in result, result
            assert isinstance(result["hello"], m.HelloReply)
            assert second.authenticated is keyed
            second.ping()
        finally:
            second.link.close()
        assert dev.device.door.answered == 0


def test_a_second_serve_says_busy_in_one_line(tmp_path, model_path):
    """The reproduction: ``eigencast serve`` to a device another ``serve`` holds."""
    device = DeviceProcess(tmp_path / "flash", "--headless", key_file=key_file(model_path))
    key = str(key_file(model_path))
    try:
        provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=lambda line: None))
        first = subprocess.Popen([sys.executable, "-m", "host.cli", "serve", str(model_path),
                                  "--port", device.url, "--key", key, "--duration", "60"],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                 cwd=REPO)
        try:
            assert "serving" in first.stderr.readline()
            second = subprocess.run([sys.executable, "-m", "host.cli", "serve",
                                     str(model_path), "--port", device.url, "--key", key,
                                     "--duration", "5"],
                                    capture_output=True, text=True, timeout=60, cwd=REPO)
        finally:
            first.terminate()
            first.wait(30)
    finally:
        device.kill()
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 1 and len(lines) == 1, second.stderr
    assert "BUSY" in lines[0] and "serving another host" in lines[0], lines
