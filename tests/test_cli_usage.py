"""Command-line misuse through the real programs: the sub-command's own usage line, one
error line and exit code 1 (README, "Command line"); --version on both programs; the hint
for a TCP address given without its scheme."""

from __future__ import annotations

import subprocess
import sys

import pytest

from device_runtime.cli import USAGE

HOST = [sys.executable, "-m", "host.cli"]
DEVICE = [sys.executable, "-m", "device_runtime.cli"]


def _run(cmd):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize(
    ("argv", "usage", "error"),
    [
        (["fit", "x.cdb"], "usage: eigencast fit DB.cdb -o MODEL.ecs [options]",
         "eigencast fit: error: the following arguments are required: -o/--output"),
        (["fit", "x.cdb", "-o", "m.ecs", "--bogus"],
         "usage: eigencast fit DB.cdb -o MODEL.ecs [options]",
         "eigencast fit: error: unrecognized arguments: --bogus"),
        (["view", "m.ecs", "--phi", "x", "--theta", "0", "-o", "v.png"],
         "usage: eigencast view MODEL.ecs --phi DEG --theta DEG -o OUT.png [options]",
         "eigencast view: error: argument --phi: invalid float value: 'x'"),
        (["serve", "m.ecs"], "usage: eigencast serve MODEL.ecs --port URL [options]",
         "eigencast serve: error: the following arguments are required: --port"),
        (["nosuch"], "usage: eigencast [-h] [--version] COMMAND ...",
         "eigencast: error: argument COMMAND: invalid choice: 'nosuch'"),
    ],
)
def test_a_bad_command_line_is_its_usage_line_and_one_error(argv, usage, error):
    run = _run([*HOST, *argv])
    assert run.returncode == 1
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 2 and lines[0] == usage and lines[1].startswith(error), run.stderr
    assert run.stdout == ""


def test_the_device_answers_a_bad_command_line_alike_and_has_a_version():
    run = _run([*DEVICE, "--flash", "f", "--listen", "127.0.0.1:0", "--bogus"])
    assert run.returncode == 1
    assert run.stderr.strip().splitlines() == [
        f"usage: {USAGE}", "eigencast-device: error: unrecognized arguments: --bogus"]
    from importlib.metadata import version

    for cmd, name in ((DEVICE, "eigencast-device"), (HOST, "eigencast")):
        run = _run([*cmd, "--version"])
        assert run.returncode == 0 and run.stdout.startswith(f"{name} {version('eigencast')}")


def test_a_tcp_address_without_its_scheme_gets_a_hint(tmp_path, model_path):
    hint = ("open 127.0.0.1:5555: no such serial port; did you mean socket://127.0.0.1:5555?")
    run = _run([*HOST, "provision", str(model_path), "--port", "127.0.0.1:5555"])
    assert run.returncode == 1
    assert run.stderr.strip().splitlines() == [f"eigencast provision: error: {hint}"]
    run = _run([*DEVICE, "--flash", str(tmp_path / "f"), "--port", "127.0.0.1:5555"])
    assert run.returncode == 1
    assert run.stderr.strip().splitlines() == [f"eigencast-device: error: {hint}"]
    run = _run([*DEVICE, "--flash", str(tmp_path / "f"), "--port", str(tmp_path / "ttyNONE")])
    assert run.returncode == 1 and "did you mean" not in run.stderr  # a path: no hint
