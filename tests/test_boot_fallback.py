"""Boot falls back to the other slot whenever the active image cannot be LOADED (issue 11,
item 5), ``eigencast-device --status`` says so truthfully, and ``--insecure`` is refused on a
paired flash folder.

The images that do not load are written straight into slot B with the flash API (what a
device started ``--insecure`` before it was paired, or any other path, could leave there):
their slot digest is right, so only loading them finds the problem.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from flash_helpers import commit_image
from provision_helpers import KEY, OTHER_KEY, make_image, mem_name
from runtime_helpers import RuntimeThread, check_frames, read_frames, wait_until

from device_runtime.cli import main as device_main
from device_runtime.device import Device, DeviceConfig
from device_runtime.flash import FlashStore, SlotState
from device_runtime.image_receiver import required_ram_bytes
from host.link import provision, serve
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from protocol.image import read_manifest
from protocol.keys import write_key


def _quiet(line: str) -> None:
    pass


def _ram(path) -> int:
    return required_ram_bytes(read_manifest(path))


@pytest.fixture
def good_flash(tmp_path):
    """Slot A: an image signed with KEY, confirmed. Returns (flash dir, its bytes)."""
    image = make_image(tmp_path / "good.ecs", size_bytes=20_000, key=KEY, generation=1)
    flash = tmp_path / "flash"
    assert commit_image(flash, image, generation=1) == "A"
    return flash, image


def _bad_image(kind: str, tmp_path) -> tuple[bytes, dict]:
    """Slot-B contents that a KEY device cannot load, and the DeviceConfig overrides."""
    path = tmp_path / f"{kind}.ecs"
    if kind == "unsigned":
        return make_image(path, size_bytes=20_000, key=None, generation=2), {}
    if kind == "other-key":
        return make_image(path, size_bytes=20_000, key=OTHER_KEY, generation=2), {}
    if kind == "inner-digest":  # corrupt inside; the flash digest covers the corrupt bytes
        data = bytearray(make_image(path, size_bytes=20_000, key=KEY, generation=2))
        data[len(data) // 2] ^= 0xFF
        return bytes(data), {}
    if kind == "format":
        return b"\x89not an eigencast image" * 500, {}
    if kind == "ram":
        data = make_image(path, size_bytes=300_000, key=KEY, generation=2)
        small = tmp_path / "small.ecs"
        make_image(small, size_bytes=20_000, key=KEY)
        budget = (_ram(small) + _ram(path)) // 2  # A fits, B does not
        return data, {"ram_budget_bytes": budget}
    raise AssertionError(kind)


WHY = {"unsigned": "not signed", "other-key": "tag", "inner-digest": "digest",
       "format": "image", "ram": "RAM"}


@pytest.mark.parametrize("state", ["confirmed", "test"])
@pytest.mark.parametrize("kind", sorted(WHY))
def test_boot_falls_back_when_the_active_image_does_not_load(good_flash, tmp_path, kind, state):
    flash, good = good_flash
    bad, overrides = _bad_image(kind, tmp_path)
    assert commit_image(flash, bad, generation=2, confirm=state == "confirmed") == "B"
    lines: list[str] = []
    device = Device(DeviceConfig(flash_dir=flash, key=KEY, **overrides), log=lines.append)
    try:
        assert device.store.active_slot == "A"
        assert device.store.slots[1].state is SlotState.BAD
        with device.store.open_active() as stream:
            assert stream.read() == good
    finally:
        device.close()
    why = [line for line in lines if "slot B: the image does not load" in line]
    assert len(why) == 1 and WHY[kind].lower() in why[0].lower(), lines
    assert any("fell back to slot A" in line for line in lines), lines
    # durable: a later start (or a plain flash boot) stays on A
    store = FlashStore.open(flash)
    assert store.boot().slot == "A" and store.slots[1].state is SlotState.BAD


def test_nothing_to_fall_back_to_leaves_no_image_active(tmp_path):
    flash = tmp_path / "flash"
    unsigned = make_image(tmp_path / "u.ecs", size_bytes=20_000, key=None)
    commit_image(flash, unsigned, generation=1)
    lines: list[str] = []
    device = Device(DeviceConfig(flash_dir=flash, key=KEY), log=lines.append)
    device.close()
    assert device.store.active_slot is None
    assert any("nothing to show" in line for line in lines), lines


def test_the_issue_scenario_pair_unsigned_commit_boot_falls_back_and_status_tells(
    tmp_path, model_path, model, capsys
):
    """Pair, install a signed image, get an unsigned one committed and confirmed in the other
    slot; the next start shows the signed slot's frames, and --status names the bad slot."""
    flash = tmp_path / "flash"
    write_key(tmp_path / "k.key", KEY)
    assert device_main(["--pair", str(tmp_path / "k.key"), "--flash", str(flash)]) == 0
    name = mem_name("pair")
    with RuntimeThread(flash, f"mem://{name}?end=b&pace=0", frames=tmp_path / "f0"):
        result = provision(model_path, f"mem://{name}?end=a&pace=0",
                           ProvisionOptions(key=KEY, show_progress=False),
                           ProvisionParts(log=_quiet))
    assert result.confirmed and result.slot == "A"
    unsigned = make_image(tmp_path / "u.ecs", size_bytes=20_000, key=None, generation=1 << 40)
    assert commit_image(flash, unsigned, generation=1 << 40) == "B"
    capsys.readouterr()

    assert device_main(["--flash", str(flash), "--status", "--json"]) == 0
    slots = json.loads(capsys.readouterr().out)["slots"]
    assert (slots[1]["active"], slots[1]["state"], slots[1]["verifies"]) == (True, "confirmed",
                                                                              False)
    assert "not signed" in slots[1]["problem"]
    assert slots[0]["verifies"] is True and slots[0]["problem"] is None

    frames = tmp_path / "frames"
    name = mem_name("pair")
    with RuntimeThread(flash, f"mem://{name}?end=b&pace=0", frames=frames) as device:
        assert any("slot B: the image does not load" in line and "not signed" in line
                   for line in device.lines), device.lines
        assert any("fell back to slot A" in line for line in device.lines), device.lines
        from device_runtime.orbit import parse_orbit

        stats = serve(model_path, f"mem://{name}?end=a&pace=0",
                      ServeOptions(key=KEY, scores="interpolate", orbit=parse_orbit("steps:3:10")),
                      ServeParts(log=_quiet))
        assert stats.frames == 3
        wait_until(lambda: len(read_frames(frames)) >= 1, 10, "a frame of slot A")
    assert check_frames(model, frames) >= 1  # the signed image's frames, nothing else

    assert device_main(["--flash", str(flash), "--status"]) == 0
    out = capsys.readouterr().out
    line_b = next(line for line in out.splitlines() if "slot B" in line)
    assert "DOES NOT VERIFY" in line_b and "not signed" in line_b and "bad" in line_b
    assert "slot A *" in out


def test_status_uses_the_given_key_and_ram_budget(good_flash, tmp_path, capsys):
    flash, _ = good_flash
    assert device_main(["--flash", str(flash), "--status", "--json"]) == 0  # no key paired
    assert json.loads(capsys.readouterr().out)["slots"][0]["verifies"] is True
    write_key(tmp_path / "other.key", OTHER_KEY)
    assert device_main(["--flash", str(flash), "--status", "--json", "--key",
                        str(tmp_path / "other.key")]) == 0
    slot_a = json.loads(capsys.readouterr().out)["slots"][0]
    assert slot_a["verifies"] is False and "tag" in slot_a["problem"].lower()
    assert device_main(["--flash", str(flash), "--status", "--json", "--ram-budget",
                        "0.01"]) == 0
    slot_a = json.loads(capsys.readouterr().out)["slots"][0]
    assert slot_a["verifies"] is False and "RAM" in slot_a["problem"]


def test_insecure_on_a_paired_flash_folder_is_refused_until_unpaired(tmp_path, capsys):
    flash = tmp_path / "flash"
    write_key(tmp_path / "k.key", KEY)
    assert device_main(["--pair", str(tmp_path / "k.key"), "--flash", str(flash)]) == 0
    capsys.readouterr()
    run = subprocess.run([sys.executable, "-m", "device_runtime.cli", "--flash", str(flash),
                          "--listen", "127.0.0.1:0", "--headless", "--insecure"],
                         capture_output=True, text=True, timeout=30)  # refused: never serves
    assert run.returncode == 1, run.stderr
    err = run.stderr.strip()
    assert err.count("\n") == 0 and err.startswith("eigencast-device: error: --insecure")
    assert str(flash / "device.key") in err and "--unpair" in err
    assert (flash / "device.key").exists()
    assert device_main(["--unpair", "--flash", str(flash)]) == 0
    assert not (flash / "device.key").exists()
    capsys.readouterr()
    assert device_main(["--unpair", "--flash", str(flash)]) == 1
    assert "no paired key" in capsys.readouterr().err
