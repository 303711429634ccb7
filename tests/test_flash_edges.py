"""Flash folder edge cases (issue 21, item 4): a store file replaced by a directory or a FIFO,
a journal header claiming 2^62 bytes, and a paired folder whose key file is gone.

Boot falls back to the good slot or refuses in one line, never hangs and never prints a
traceback; ``eigencast-device --status`` tells the truth (which slot the device would boot)
and exits 0 when the folder can be read. The device and ``--status`` run as processes with a
timeout: a hang is a failure, not a stuck test run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import pytest
from flash_helpers import commit_image
from provision_helpers import KEY, REPO, make_image

from device_runtime._flash_format import JournalHeader, encode_journal_header
from device_runtime.flash import FlashStore
from protocol.keys import write_key

DEVICE = [sys.executable, "-m", "device_runtime.cli"]


@pytest.fixture
def two_slots(tmp_path):
    """Slot A generation 1 and slot B generation 2, both confirmed, B active; a paired key."""
    flash = tmp_path / "flash"
    write_key(tmp_path / "k.key", KEY)
    for generation in (1, 2):
        image = make_image(tmp_path / f"g{generation}.ecs", size_bytes=20_000, key=KEY,
                           generation=generation, seed=generation)
        commit_image(flash, image, generation=generation)
    subprocess.run([*DEVICE, "--pair", str(tmp_path / "k.key"), "--flash", str(flash)],
                   check=True, capture_output=True, timeout=60, cwd=REPO)
    assert FlashStore.open(flash, create=False).active_slot == "B"
    return flash


def _status(flash) -> dict:
    try:
        run = subprocess.run([*DEVICE, "--flash", str(flash), "--status", "--json"],
                             capture_output=True, text=True, timeout=30, cwd=REPO)
    except subprocess.TimeoutExpired:
        pytest.fail("eigencast-device --status hung")
    assert run.returncode == 0 and "Traceback" not in run.stderr, run.stderr
    return json.loads(run.stdout)


def _boot(flash, *extra: str) -> tuple[int | None, list[str]]:
    """Start a listening device; return (exit code or None while it serves, its lines)."""
    proc = subprocess.Popen([*DEVICE, "--flash", str(flash), "--listen", "127.0.0.1:0",
                             "--headless", *extra], stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, text=True, cwd=REPO)
    lines: list[str] = []
    listening = threading.Event()

    def drain() -> None:
        for line in proc.stderr:
            lines.append(line.rstrip("\n"))
            if "listening on" in line:
                listening.set()

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    deadline = time.monotonic() + 30
    while not listening.is_set() and proc.poll() is None and time.monotonic() < deadline:
        listening.wait(0.05)
    code = proc.poll()
    if code is None:
        proc.terminate()
        proc.wait(10)
        reader.join(5)
        assert listening.is_set(), "the device hung before listening:\n" + "\n".join(lines)
        return None, lines
    reader.join(5)
    return code, lines


def _replace(path, kind: str) -> None:
    path.unlink()
    if kind == "directory":
        path.mkdir()
    else:
        os.mkfifo(path)


@pytest.mark.parametrize("kind", ["directory", "fifo"])
def test_an_active_slot_that_is_not_a_file_falls_back(two_slots, kind):
    """Boot refused to start (a directory) or hung (a FIFO), and so did --status."""
    _replace(two_slots / "slot_b.img", kind)
    status = _status(two_slots)
    slot_b = status["slots"][1]
    assert slot_b["active"] and slot_b["verifies"] is False, slot_b
    assert "not a regular file" in slot_b["problem"], slot_b
    assert status["slots"][0]["verifies"] is True and status["boots"] == "A", status
    code, lines = _boot(two_slots)
    assert code is None, lines
    assert any("fell back to slot A" in line for line in lines), lines
    assert not any("Traceback" in line for line in lines), lines
    assert _status(two_slots)["active_slot"] == "A"


@pytest.mark.parametrize(("name", "kind"), [("slot_a.img", "fifo"), ("journal_a.jnl", "fifo"),
                                          ("state_1.rec", "directory")])
def test_other_store_files_that_are_not_files_never_hang(two_slots, name, kind):
    """The inactive slot, a journal, a state-record copy: a directory or a FIFO in their
    place is a slot that does not verify, an absent journal, an invalid copy."""
    path = two_slots / name
    if path.exists():
        path.unlink()
    _replace_new(path, kind)
    status = _status(two_slots)
    assert status["boots"] == "B", status
    if name == "slot_a.img":
        assert "not a regular file" in status["slots"][0]["problem"]
    else:
        assert status["journal"] is None and status["slots"][1]["verifies"] is True
    code, lines = _boot(two_slots)
    assert code is None and not any("Traceback" in line for line in lines), lines


def _replace_new(path, kind: str) -> None:
    if kind == "directory":
        path.mkdir()
    else:
        os.mkfifo(path)


def test_a_journal_header_claiming_2_62_bytes_is_ignored(two_slots):
    """--status died with a MemoryError traceback (one flag per claimed block)."""
    header, _ = encode_journal_header(JournalHeader(block_bytes=65536, size_bytes=2**62,
                                                    image_generation=3, sha256=bytes(32)))
    (two_slots / "journal_a.jnl").write_bytes(header)
    status = _status(two_slots)
    assert status["journal"] is None and status["boots"] == "B", status
    code, lines = _boot(two_slots)
    assert code is None and not any("Traceback" in line for line in lines), lines


def test_a_paired_folder_without_its_key_file_refuses_to_start(two_slots, tmp_path):
    """It ran keyless without a word; a paired device fails closed, as for an empty key."""
    (two_slots / "device.key").unlink()
    code, lines = _boot(two_slots)
    assert code == 1 and len(lines) == 1, lines
    assert lines[0].startswith("eigencast-device: error:") and "device.key" in lines[0]
    assert "--unpair" in lines[0] and "--key" in lines[0], lines
    status = subprocess.run([*DEVICE, "--flash", str(two_slots), "--status"],
                            capture_output=True, text=True, timeout=30, cwd=REPO)
    assert status.returncode == 0 and "key file is missing" in status.stdout, status.stdout
    code, lines = _boot(two_slots, "--key", str(tmp_path / "k.key"))  # the key given: serves
    assert code is None, lines
    unpaired = subprocess.run([*DEVICE, "--unpair", "--flash", str(two_slots)],
                              capture_output=True, text=True, timeout=30, cwd=REPO)
    assert unpaired.returncode == 0, unpaired.stderr
    code, lines = _boot(two_slots)  # unpaired on purpose: keyless, as asked
    assert code is None and any("no key" in line for line in lines), lines
