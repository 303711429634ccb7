"""``eigencast-device``: --status [--json], --pair, the --insecure banner, and one-line errors."""

from __future__ import annotations

import json
import os
import stat

import pytest
from provision_helpers import KEY, DeviceProcess, DeviceThread, make_image, mem_name

from device_runtime.cli import KEY_FILE_NAME, USAGE, build_parser, main
from host.link.options import ProvisionOptions, ProvisionParts
from host.link.provisioning import provision
from protocol.keys import key_fingerprint, load_key, write_key


def _one_error_line(capsys) -> str:
    """The error line; a command line argparse cannot parse has the usage line above it."""
    lines = capsys.readouterr().err.strip().splitlines()
    if len(lines) == 2:
        assert lines[0] == f"usage: {USAGE}", lines
        lines = lines[1:]
    assert len(lines) == 1, lines
    assert lines[0].startswith("eigencast-device: error: "), lines
    return lines[0]


@pytest.fixture
def provisioned(tmp_path):
    """A flash folder with one confirmed image in slot A; returns (flash_dir, image bytes)."""
    path = tmp_path / "m.ecs"
    image = make_image(path, size_bytes=30_000)
    name = mem_name("cli")
    with DeviceThread(f"mem://{name}?end=b&pace=0", tmp_path / "flash"):
        provision(path, f"mem://{name}?end=a&pace=0",
                  ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=lambda line: None))
    return tmp_path / "flash", image


def test_status_prints_each_slot_and_whether_it_verifies(provisioned, capsys):
    flash, image = provisioned
    assert main(["--flash", str(flash), "--status"]) == 0
    out = capsys.readouterr().out
    assert "slot A *" in out and "confirmed" in out and "verifies" in out
    assert f"{len(image)} bytes" in out and "slot B" in out and "empty" in out
    assert "key: none paired" in out


def test_status_json_is_machine_readable_and_notices_a_corrupt_slot(provisioned, capsys):
    flash, image = provisioned
    assert main(["--flash", str(flash), "--status", "--json"]) == 0
    status = json.loads(capsys.readouterr().out)
    slot_a = status["slots"][0]
    assert status["active_slot"] == "A" and slot_a["verifies"] is True
    assert slot_a["size_bytes"] == len(image) and slot_a["state"] == "confirmed"
    with open(flash / "slot_a.img", "r+b") as handle:  # one flipped byte in flash
        handle.seek(1000)
        byte = handle.read(1)
        handle.seek(1000)
        handle.write(bytes([byte[0] ^ 0xFF]))
    assert main(["--flash", str(flash), "--status", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["slots"][0]["verifies"] is False


def test_pair_installs_the_key_with_mode_0600_and_the_device_uses_it(tmp_path, capsys):
    write_key(tmp_path / "k.key", KEY)
    flash = tmp_path / "flash"
    assert main(["--pair", str(tmp_path / "k.key"), "--flash", str(flash)]) == 0
    installed = flash / KEY_FILE_NAME
    assert load_key(installed) == KEY
    assert stat.S_IMODE(os.stat(installed).st_mode) == 0o600
    assert key_fingerprint(KEY) in capsys.readouterr().out
    # A device started on that folder without --key authenticates with the paired key.
    dev = DeviceProcess(flash)
    try:
        path = tmp_path / "m.ecs"
        make_image(path, size_bytes=20_000)
        result = provision(path, dev.url, ProvisionOptions(key=KEY, show_progress=False),
                           ProvisionParts(log=lambda s: None))
    finally:
        assert dev.stop() == 0
    assert result.outcome == "installed"
    assert any(key_fingerprint(KEY) in line for line in dev.lines)
    assert main(["--flash", str(flash), "--status"]) == 0
    assert f"paired, fingerprint {key_fingerprint(KEY)}" in capsys.readouterr().out


def test_ctrl_c_exits_130_and_a_service_stop_0(tmp_path):
    """Ctrl-C (SIGINT) ends the device with 130 as every eigencast command (it was 0);
    SIGTERM, a service manager's stop, still 0."""
    import signal

    dev = DeviceProcess(tmp_path / "flash", "--insecure")
    dev.proc.send_signal(signal.SIGINT)
    assert dev.proc.wait(timeout=30) == 130
    dev.stop()
    assert dev.lines[-1].endswith("interrupted"), dev.lines[-3:]
    assert not any("Traceback" in line for line in dev.lines)
    dev = DeviceProcess(tmp_path / "flash", "--insecure")
    assert dev.stop() == 0 and dev.lines[-1].endswith("stopped")


def test_insecure_is_announced_loudly_and_the_device_stops_cleanly(tmp_path):
    dev = DeviceProcess(tmp_path / "flash", "--insecure")
    rc = dev.stop()
    assert rc == 0
    banner = [line for line in dev.lines if "--insecure" in line]
    assert banner and "WARNING" in banner[0] and "ANYONE" in banner[0]
    assert dev.lines[-1].endswith("stopped")


def test_a_device_without_a_key_says_provisioning_is_refused(tmp_path):
    dev = DeviceProcess(tmp_path / "flash")
    dev.stop()
    assert any("no key: provisioning is refused" in line for line in dev.lines)


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--flash", "{d}/f", "--bogus"], "unrecognized arguments: --bogus"),
        (["--status"], "required: --flash"),
        (["--flash", "{d}/f", "--port", "nope://x"], "unknown scheme 'nope'"),
        (["--flash", "{d}/f", "--listen", "nohost"], "is not HOST:PORT"),
        (["--flash", "{d}/f", "--listen", "127.0.0.1:0", "--key", "{d}/missing.key"],
         "not found"),
        (["--flash", "{d}/f", "--listen", "127.0.0.1:0", "--key", "{d}/k.key", "--insecure"],
         "--insecure cannot be combined"),
        (["--flash", "{d}/f"], "give --port URL or --listen"),
        (["--flash", "{d}/f", "--json"], "--json goes with --status"),
        (["--flash", "{d}/missing", "--status"], "no flash folder"),
        (["--flash", "{d}/f", "--port", "x", "--listen", "h:1"], "not allowed with argument"),
        (["--flash", "{d}/f", "--listen", "127.0.0.1:0", "--ram-budget", "-3"], "> 0 MB"),
        (["--flash", "{d}/f", "--listen", "127.0.0.1:0", "--max-frame", "10"], "--max-frame"),
        (["--pair", "{d}/missing.key", "--flash", "{d}/f"], "not found"),
        (["--flash", "{d}/f", "--listen", "127.0.0.1:0", "--auth-timeout", "0"],
         "--auth-timeout 0.0 must be in"),
        (["--flash", "{d}/f", "--listen", "127.0.0.1:0", "--auth-timeout", "nan"],
         "--auth-timeout nan must be in"),
    ],
)
def test_bad_usage_is_one_line_and_exit_code_1(tmp_path, capsys, argv, needle):
    write_key(tmp_path / "k.key", KEY)
    args = [a.format(d=tmp_path) for a in argv]
    assert main(args) == 1
    assert needle in _one_error_line(capsys)
    assert not (tmp_path / "f").exists()  # nothing was formatted on the way to the error


def test_a_corrupt_flash_folder_is_one_line(tmp_path, capsys):
    flash = tmp_path / "f"
    flash.mkdir()
    (flash / "state_0.rec").write_bytes(b"garbage" * 30)
    assert main(["--flash", str(flash), "--status"]) == 1
    assert "corrupt flash store" in _one_error_line(capsys)


def test_the_parser_takes_the_runtime_flags():
    args = build_parser().parse_args(["--flash", "x", "--listen", "h:1", "--headless"])
    assert args.headless and args.listen == "h:1"


def test_auth_timeout_drops_an_unauthenticated_hog_of_the_tcp_slot(tmp_path):
    """Issue 11: HELLO then PINGs held the only TCP slot; now --auth-timeout ends it."""
    from protocol import messages as m
    from protocol.link import Link
    from protocol.transport import open_transport

    write_key(tmp_path / "k.key", KEY)
    dev = DeviceProcess(tmp_path / "flash", "--auth-timeout", "0.5", key_file=tmp_path / "k.key")
    try:
        link = Link(open_transport(dev.url, timeout_s=5), owns_transport=True).start()
        version = m.PROTOCOL_VERSION
        link.request(m.Hello(min_version=version, max_version=version, nonce=bytes(16)))
        assert link.wait_closed(15)  # dropped after 0.5 s (PINGs do not extend it)
        link.close()
        path = tmp_path / "m.ecs"
        make_image(path, size_bytes=20_000)
        result = provision(path, dev.url, ProvisionOptions(key=KEY, show_progress=False),
                           ProvisionParts(log=lambda s: None))
        assert result.outcome == "installed"
    finally:
        assert dev.stop() == 0
    assert any("did not authenticate within 0.5 s; dropped" in line for line in dev.lines)


def test_the_window_opens_once_at_the_size_of_the_image(tmp_path, tmp_path_factory,
                                                       monkeypatch):
    """A standalone device with a window: the window is made once, at the image's size
    (it was made at 256 x 256 and then again at the image's, and input sent to the first
    was lost), and the display runs at a window's rate unless --fps says otherwise."""
    from runtime_helpers import key_file, tiny_model

    from device_runtime import display
    from device_runtime.display import Quit
    from device_runtime.runtime import RuntimeDevice

    model_path = tiny_model(tmp_path_factory)
    flash = tmp_path / "flash"
    device = DeviceProcess(flash, "--headless", key_file=key_file(model_path))
    provision(model_path, device.url, ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=lambda line: None))
    assert device.stop() == 0
    made, resized, ticks = [], [], []

    class FakeWindow:
        headless = False
        overlay = False
        zoom = 1.0

        def __init__(self, image_shape, **kwargs):
            made.append(tuple(image_shape))
            self.shape = tuple(image_shape)
            self.polls = 0

        def set_image_shape(self, shape):
            if tuple(shape) != self.shape:
                resized.append(tuple(shape))

        def poll(self):
            self.polls += 1
            return [Quit()] if self.polls > 3 else []

        def present(self, frame, info=None, *, overlay_lines=None):
            assert frame.shape[:2] == self.shape
            return True

        def close(self):
            pass

    original = RuntimeDevice.run_display

    def run_display(self, stop=None):
        ticks.append(self.tick_s)
        return original(self, stop)

    monkeypatch.setattr(display, "Window", FakeWindow)
    monkeypatch.setattr(RuntimeDevice, "run_display", run_display)
    args = ["--standalone", "--flash", str(flash), "--key", str(key_file(model_path))]
    assert main(args) == 0
    from protocol.image import read_image

    shape = tuple(read_image(model_path, key=KEY).image_shape)
    assert made == [shape] and resized == [] and ticks == [pytest.approx(1 / 60)]
    assert main([*args, "--fps", "24"]) == 0
    assert ticks[-1] == pytest.approx(1 / 24)
