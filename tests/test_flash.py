"""Tests of the device flash store (device_runtime/flash.py): A/B slots, journal, power cuts.

The writer of one transfer (chunks in any order, the window) is tested in test_image_writer.py."""

from __future__ import annotations

import hashlib
import json
import os
import random
import struct
import tracemalloc
import zlib
from pathlib import Path

import flash_crash_driver as driver
import pytest
from flash_helpers import BLOCK, CAPACITY, make_image, sha

from device_runtime._flash_format import RECORD_SIZE
from device_runtime.errors import FlashError
from device_runtime.flash import (
    FlashStore,
    ImageTooLarge,
    NoImage,
    RollbackRefused,
    SlotBusy,
    SlotDigestMismatch,
    SlotState,
    format_status,
)


def write_image(store: FlashStore, image: bytes, generation: int, *, chunk: int = 10_000,
                **kwargs) -> None:
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image),
                               image_generation=generation, **kwargs)
    for offset in range(0, len(image), chunk):
        writer.write_chunk(offset, image[offset:offset + chunk])
    assert writer.verify()


def install(store: FlashStore, image: bytes, generation: int) -> None:
    write_image(store, image, generation)
    store.commit_test()
    store.boot()
    store.confirm()


def active_bytes(store: FlashStore) -> bytes:
    with store.open_active() as handle:
        return handle.read()


def reboot(folder: Path) -> FlashStore:
    return FlashStore.open(folder)


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    return tmp_path / "flash"


@pytest.fixture
def old_new(folder: Path):
    """A store with OLD confirmed in slot A and NEW committed as a test image in slot B."""
    old, new = make_image(1, 150_001), make_image(2, 170_017)
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    install(store, old, 1)
    write_image(store, new, 2)
    store.commit_test()
    return store, old, new


# ------------------------------------------------------------------ cycle
def test_write_verify_commit_boot_confirm_cycle(folder):
    image = make_image(3, 200_000)
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    assert store.active_slot is None
    assert not store.boot().ok
    write_image(store, image, 1)
    store.commit_test()
    assert store.active_slot == "A"
    assert store.slots[0].state is SlotState.TEST

    result = reboot(folder).boot()
    assert (result.slot, result.state, result.boot_attempts) == ("A", "test", 1)
    assert result.verified and result.sha256 == sha(image) and result.size_bytes == len(image)

    store = reboot(folder)
    store.confirm()
    store = reboot(folder)
    assert store.slots[0].state is SlotState.CONFIRMED
    assert active_bytes(store) == image
    for _ in range(2):  # a confirmed image stays active across reboots
        result = reboot(folder).boot()
        assert (result.slot, result.state, result.reverted) == ("A", "confirmed", False)


def test_unconfirmed_test_image_reverts_at_next_boot(old_new, folder):
    _, old, new = old_new
    first = reboot(folder).boot()
    assert (first.slot, first.sha256, first.state) == ("B", sha(new), "test")
    second = reboot(folder).boot()  # never confirmed -> back to A
    assert second.reverted and second.slot == "A" and second.sha256 == sha(old)
    assert "not confirmed" in second.reason
    store = reboot(folder)
    assert store.slots[1].state is SlotState.BAD
    assert active_bytes(store) == old


def test_confirmed_test_image_stays(old_new, folder):
    _, _, new = old_new
    store = reboot(folder)
    store.boot()
    store.confirm()
    for _ in range(2):
        result = reboot(folder).boot()
        assert (result.slot, result.state, result.sha256) == ("B", "confirmed", sha(new))


def test_first_image_not_confirmed_boots_again_when_nothing_to_revert_to(folder):
    image = make_image(4, 5000)
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    write_image(store, image, 1)
    store.commit_test()
    reboot(folder).boot()
    result = reboot(folder).boot()
    assert result.slot == "A" and not result.reverted and result.boot_attempts == 2
    assert "no confirmed image to revert to" in result.reason


def flip_byte(path: Path, offset: int) -> None:
    with open(path, "r+b") as handle:
        handle.seek(offset)
        byte = handle.read(1)
        handle.seek(offset)
        handle.write(bytes([byte[0] ^ 0x01]))


def test_corrupt_active_slot_falls_back_to_other(old_new, folder):
    store, old, _ = old_new
    store.boot()
    store.confirm()  # B confirmed, A confirmed fallback
    flip_byte(folder / "slot_b.img", 12_345)
    result = reboot(folder).boot()
    assert result.fell_back and result.slot == "A" and result.sha256 == sha(old)
    assert "slot B: digest mismatch" in result.reason and "fell back to slot A" in result.reason
    store = reboot(folder)
    assert store.slots[1].state is SlotState.BAD
    assert active_bytes(store) == old


def test_both_slots_bad_boot_reports_no_image(old_new, folder):
    store, _, _ = old_new
    store.boot()
    store.confirm()
    flip_byte(folder / "slot_a.img", 7)
    os.truncate(folder / "slot_b.img", 1000)
    result = reboot(folder).boot()
    assert not result.ok and result.slot is None and result.state == "none"
    assert "no bootable image" in result.reason
    store = reboot(folder)
    assert store.active_slot is None
    with pytest.raises(NoImage, match="no image is active"):
        store.open_active()
    assert [s["verifies"] for s in store.status()["slots"]] == [False, False]


def test_reject_active_marks_the_slot_bad_and_falls_back_durably(old_new, folder):
    """A slot the device cannot load (its digest is fine) is given up for the confirmed one."""
    store, old, _ = old_new
    store.boot()
    store.confirm()  # B confirmed and active, A confirmed fallback
    assert store.reject_active() == "A"
    for _ in range(2):  # durable: every later boot stays on A
        store = reboot(folder)
        assert store.boot().slot == "A" and active_bytes(store) == old
    assert store.slots[1].state is SlotState.BAD
    status = store.status()
    assert status["slots"][1]["bad_reason"] == "the device could not load it; fell back at boot"
    assert "could not load" in format_status(status)
    # nothing to fall back to: no image is active, nothing can be shown from the bad slot
    assert reboot(folder).reject_active() is None
    store = reboot(folder)
    assert store.active_slot is None and not store.boot().ok
    with pytest.raises(NoImage):
        store.reject_active()


def test_status_reports_why_a_slot_would_not_load(old_new, folder):
    store, _, new = old_new
    seen = []

    def check(stream):
        data = stream.read()
        seen.append(len(data))
        return "not signed" if data == new else None

    status = store.status(check_image=check)
    assert [s["verifies"] for s in status["slots"]] == [True, False]
    assert [s["problem"] for s in status["slots"]] == [None, "not signed"]
    assert sorted(seen) == sorted([150_001, 170_017])
    assert "DOES NOT VERIFY: not signed" in format_status(status)
    flip_byte(folder / "slot_a.img", 5)  # a digest mismatch is reported without loading
    status = reboot(folder).status(check_image=check)
    assert status["slots"][0]["verifies"] is False
    assert status["slots"][0]["problem"].startswith("digest mismatch")


@pytest.mark.parametrize("cut_at", range(1, 8))
def test_reject_active_survives_a_power_cut_at_every_operation(old_new, folder, tmp_path, cut_at):
    store, old, new = old_new
    store.boot()
    store.confirm()
    model = driver.PageCacheModel(folder, cut_at)
    previous = driver.install_file_ops(model)
    try:
        store.reject_active()
    except driver.PowerCut:
        pass
    finally:
        driver.install_file_ops(previous)
    rng = random.Random(cut_at)
    for trial in range(3):
        after = tmp_path / f"after{trial}"
        model.materialize(folder, after, rng)
        store = FlashStore.open(after)
        result = store.boot()
        if result.slot == "B":  # the old state: B still active, as confirmed
            assert active_bytes(store) == new and store.slots[1].state is SlotState.CONFIRMED
        else:  # the new state: A active, B marked bad
            assert result.slot == "A" and active_bytes(store) == old
            assert store.slots[1].state is SlotState.BAD


def test_boot_without_verify_skips_digest(old_new, folder):
    flip_byte(folder / "slot_b.img", 3)
    result = reboot(folder).boot(verify=False)
    assert result.slot == "B" and not result.verified


# ------------------------------------------------------------ state record
def test_record_layout_matches_documentation(old_new, folder):
    store, _, new = old_new
    generation = store.record_generation
    raw = (folder / f"state_{generation % 2}.rec").read_bytes()
    assert len(raw) == RECORD_SIZE == 148
    assert raw[:4] == b"ECFS"
    assert struct.unpack_from("<Q", raw, 8)[0] == generation
    assert struct.unpack_from("<Q", raw, 16)[0] == CAPACITY
    assert struct.unpack_from("<b", raw, 24)[0] == 1  # active = B
    assert raw[84] == int(SlotState.TEST) and raw[84 + 24:84 + 56] == sha(new)
    assert struct.unpack_from("<I", raw, 144)[0] == zlib.crc32(raw[:144])


def record_paths(folder: Path) -> list[Path]:
    return [folder / "state_0.rec", folder / "state_1.rec"]


@pytest.mark.parametrize("damage", ["truncate", "garble"])
def test_torn_state_record_picks_old_or_new_state(old_new, folder, damage):
    """Damage each copy at every byte: boot still finds the state before or after the write."""
    store, old, new = old_new
    newest = store.record_generation % 2
    saved = {p: p.read_bytes() for p in record_paths(folder)}
    for index, path in enumerate(record_paths(folder)):
        for position in range(RECORD_SIZE):
            for p, data in saved.items():
                p.write_bytes(data)
            data = bytearray(saved[path])
            if damage == "truncate":
                del data[position:]
            else:
                data[position] ^= 0x5A
            path.write_bytes(bytes(data))
            result = FlashStore.open(folder).boot()
            # damaging the newest copy loses the commit (old image); the older copy is spare
            expected = sha(old) if index == newest else sha(new)
            assert result.ok and result.verified and result.sha256 == expected, (index, position)


def test_both_records_broken_is_refused_as_corrupt(old_new, folder):
    for path in record_paths(folder):
        flip_byte(path, 30)
    with pytest.raises(FlashError, match=r"corrupt flash store, no valid state record.*CRC"):
        FlashStore.open(folder)


def test_second_store_object_is_refused_after_state_changed(old_new, folder):
    first, _, _ = old_new
    second = reboot(folder)
    first.boot()
    with pytest.raises(FlashError, match="changed underneath"):
        second.boot()


# ----------------------------------------------------------------- open
def test_open_errors(tmp_path):
    with pytest.raises(FlashError, match="no such folder"):
        FlashStore.open(tmp_path / "missing", create=False)
    (tmp_path / "file").write_bytes(b"x")
    with pytest.raises(FlashError, match="not a folder"):
        FlashStore.open(tmp_path / "file")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FlashError, match="not a flash store"):
        FlashStore.open(tmp_path / "empty", create=False)
    store = FlashStore.open(tmp_path / "empty", capacity_bytes=4096)
    assert store.capacity_bytes == 4096
    assert FlashStore.open(tmp_path / "empty").capacity_bytes == 4096
    with pytest.raises(FlashError, match=r"formatted with 4096 bytes per slot.*8192"):
        FlashStore.open(tmp_path / "empty", capacity_bytes=8192)
    with pytest.raises(ValueError, match="capacity_bytes=0"):
        FlashStore.open(tmp_path / "other", capacity_bytes=0)


def test_size_over_capacity_refused(folder):
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    with pytest.raises(ImageTooLarge, match=rf"is {CAPACITY + 1} bytes .* at most {CAPACITY}"):
        store.begin_image(size_bytes=CAPACITY + 1, sha256=bytes(32), image_generation=1)
    with pytest.raises(FlashError, match="size_bytes=0"):
        store.begin_image(size_bytes=0, sha256=bytes(32), image_generation=1)
    with pytest.raises(FlashError, match="sha256 must be 32 bytes, got 31"):
        store.begin_image(size_bytes=10, sha256=bytes(31), image_generation=1)


# -------------------------------------------------------------- rollback
def test_rollback_refused_unless_forced(folder):
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    old, new = make_image(5, 20_000), make_image(6, 30_000)
    install(store, new, 5)
    with pytest.raises(RollbackRefused, match=r"generation 4 is older than .* generation 5"):
        store.begin_image(size_bytes=len(old), sha256=sha(old), image_generation=4)
    write_image(store, old, 4, force=True)
    store.commit_test()
    store.boot()
    store.confirm()
    assert (store.active_slot, store.slots[1].image_generation) == ("B", 4)
    # going back to generation 5 is fine; from there, to 4 again needs force
    store.set_active("A")
    store.boot()
    store.confirm()
    with pytest.raises(RollbackRefused):
        store.set_active("B")
    with pytest.raises(RollbackRefused):
        store.revert()
    store.revert(force=True)
    assert store.active_slot == "B" and store.slots[0].state is SlotState.BAD


def test_new_image_refused_while_test_image_unconfirmed(old_new):
    store, _, _ = old_new
    image = make_image(7, 1000)
    with pytest.raises(SlotBusy, match="not confirmed yet"):
        store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=3)
    write_image(store, image, 3, force=True)
    store.commit_test()
    assert store.slots[1].state is SlotState.BAD  # the abandoned test image
    assert store.active_slot == "A"


def test_revert_and_set_active_commands(old_new, folder):
    store, _, _ = old_new
    store.revert()  # the unconfirmed test image goes, A (confirmed) comes back
    assert store.active_slot == "A" and store.slots[1].state is SlotState.BAD
    with pytest.raises(SlotBusy, match="marked bad"):
        store.set_active("B")
    store.set_active("b", force=True)
    assert store.active_slot == "B" and store.slots[1].state is SlotState.TEST
    flip_byte(folder / "slot_a.img", 0)
    store.boot()
    with pytest.raises(SlotDigestMismatch, match="slot A: digest mismatch"):
        store.revert()
    with pytest.raises(ValueError, match="slot='C'"):
        store.set_active("C")


# ----------------------------------------------------------------- resume
def start_partial(folder: Path, image: bytes, upto: int, generation: int = 2) -> None:
    """Install an old image, then send ``image[:upto]`` and flush; leave like a crash."""
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    install(store, make_image(99, 10_000), 1)
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image),
                               image_generation=generation)
    writer.write_chunk(0, image[:upto])
    writer.flush()
    # no close: the process "dies" here


def test_resume_after_reboot_claims_verified_prefix(folder):
    image = make_image(11, 10 * BLOCK + 777)
    start_partial(folder, image, 5 * BLOCK + 100)
    store = reboot(folder)
    assert store.image_status(sha(image)) == 5 * BLOCK  # partial block 5 is not claimed
    assert store.status()["journal"]["verified_offset"] == 5 * BLOCK
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=2)
    assert writer.next_offset == writer.durable_offset == 5 * BLOCK
    writer.write_chunk(writer.next_offset, image[writer.next_offset:])
    assert writer.verify()
    store.commit_test()
    assert active_bytes(reboot(folder)) == image


def test_resume_after_disconnect_without_reboot(folder):
    image = make_image(12, 4 * BLOCK)
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=1)
    writer.write_chunk(0, image[:BLOCK + 10])
    assert store.image_status(sha(image)) == BLOCK + 10  # the live session answers
    again = store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=1)
    assert writer.closed and again.next_offset == BLOCK
    again.write_chunk(BLOCK, image[BLOCK:])
    assert again.verify()


def test_resume_stops_before_a_corrupted_journalled_block(folder):
    image = make_image(13, 8 * BLOCK)
    start_partial(folder, image, 8 * BLOCK)
    flip_byte(folder / "slot_b.img", 3 * BLOCK + 999)
    store = reboot(folder)
    assert store.image_status(sha(image)) == 3 * BLOCK
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=2)
    assert writer.next_offset == 3 * BLOCK
    # block 3 is rewritten; blocks 4.. verified on resume, so re-sending them only compares
    writer.write_chunk(3 * BLOCK, image[3 * BLOCK:4 * BLOCK])
    assert writer.next_offset == len(image)
    writer.write_chunk(5 * BLOCK, image[5 * BLOCK:6 * BLOCK])
    assert writer.verify()


def test_torn_journal_tail_is_ignored(folder):
    image = make_image(14, 6 * BLOCK)
    start_partial(folder, image, 6 * BLOCK)
    journal = folder / "journal_b.jnl"
    size = journal.stat().st_size
    os.truncate(journal, size - 7)  # the last entry (block 5) is torn
    store = reboot(folder)
    assert store.image_status(sha(image)) == 5 * BLOCK
    garbled = bytearray(journal.read_bytes())
    garbled[64 + 40 * 2 + 5] ^= 0xFF  # third entry (block 2) garbled: the rest is ignored
    journal.write_bytes(bytes(garbled))
    assert reboot(folder).image_status(sha(image)) == 2 * BLOCK


def test_different_image_or_abort_invalidates_journal(folder):
    image, other = make_image(15, 4 * BLOCK), make_image(16, 4 * BLOCK)
    start_partial(folder, image, 3 * BLOCK)
    store = reboot(folder)
    assert store.image_status(sha(other)) == 0
    writer = store.begin_image(size_bytes=len(other), sha256=sha(other), image_generation=2)
    assert writer.next_offset == 0
    writer.write_chunk(0, other[:2 * BLOCK])
    writer.close()
    store = reboot(folder)
    assert store.image_status(sha(image)) == 0  # the first session's journal is gone
    assert store.image_status(sha(other)) == 2 * BLOCK
    store.abort_image()
    assert store.image_status(sha(other)) == 0
    writer = reboot(folder).begin_image(size_bytes=len(other), sha256=sha(other),
                                        image_generation=2)
    assert writer.next_offset == 0


def test_commit_removes_journal_and_status_reports(old_new, folder):
    store, _, new = old_new
    assert not any(p.name.startswith("journal") for p in folder.iterdir())
    flip_byte(folder / "slot_a.img", 1)
    status = store.status()
    json.dumps(status)
    by_slot = {s["slot"]: s for s in status["slots"]}
    assert by_slot["A"]["state"] == "confirmed" and by_slot["A"]["verifies"] is False
    assert by_slot["B"]["state"] == "test" and by_slot["B"]["verifies"] is True
    assert by_slot["B"]["active"] and by_slot["B"]["sha256"] == sha(new).hex()
    text = format_status(status)
    assert "slot A" in text and "DOES NOT VERIFY" in text and "slot B *" in text
    assert store.status(verify=False)["slots"][0]["verifies"] is None


def test_open_active_streams_and_seeks(old_new, folder):
    store, _, new = old_new
    with store.open_active() as handle:
        assert handle.read(10) == new[:10]
        handle.seek(-5, os.SEEK_END)
        assert handle.read() == new[-5:]
        handle.seek(1000)
        assert handle.read(20) == new[1000:1020]


# ---------------------------------------------------------------- memory
def test_writing_64mb_keeps_traced_memory_bounded(folder):
    size = 64 * 1024 * 1024
    chunk = 64 * 1024
    base = make_image(17, chunk)

    def chunk_at(offset: int) -> bytes:
        return offset.to_bytes(8, "little") + base[8:]

    hasher = hashlib.sha256()
    for offset in range(0, size, chunk):
        hasher.update(chunk_at(offset))
    store = FlashStore.open(folder, capacity_bytes=size)
    tracemalloc.start()
    try:
        writer = store.begin_image(size_bytes=size, sha256=hasher.digest(), image_generation=1)
        for offset in range(0, size, chunk):
            writer.write_chunk(offset, chunk_at(offset))
        assert writer.verify()
        store.commit_test()
        assert store.boot().verified
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 4 * 1024 * 1024, f"peak traced memory {peak} bytes"


# ------------------------------------------------------------- power cuts
@pytest.fixture(scope="module")
def crash_template(tmp_path_factory):
    """A folder with the old image installed, and the op count of a full update."""
    base = tmp_path_factory.mktemp("powercut")
    template = base / "template"
    setup = driver.run_driver(template, "setup")
    assert setup.returncode == 0, setup.stderr
    probe = base / "probe"
    import shutil

    shutil.copytree(template, probe)
    full = driver.run_driver(probe, "update", seed=0)
    assert full.returncode == 0, full.stderr
    return template, driver.count_ops(full.stdout), driver.count_ops(setup.stdout)


N_CUTS = 15


@pytest.mark.parametrize("cut", range(N_CUTS))
def test_power_cut_at_random_operation_boots_verified_image(crash_template, tmp_path, cut):
    """Kill the update at a random file operation (stratified over the whole sequence)."""
    template, total_ops, _ = crash_template
    rng = random.Random(1000 + cut)
    low = 1 + cut * total_ops // N_CUTS
    high = max(low, (cut + 1) * total_ops // N_CUTS)
    outcome = driver.power_cut_trial(template, tmp_path / "flash", seed=cut,
                                     crash_at=rng.randint(low, high))
    assert outcome["killed"]
    assert outcome["after_cut"] in ("old", "new") and outcome["final"] == "new"


def test_power_cut_after_random_delay_boots_verified_image(crash_template, tmp_path):
    template, _, _ = crash_template
    rng = random.Random(7)
    for trial in range(2):
        outcome = driver.power_cut_trial(template, tmp_path / f"flash{trial}", seed=50 + trial,
                                         kill_after_s=rng.uniform(0.03, 0.15))
        assert outcome["after_cut"] in ("old", "new") and outcome["final"] == "new"


def test_power_cut_outcomes_cover_old_and_new(crash_template, tmp_path):
    """A cut before the commit leaves the old image, one after the confirm the new one."""
    template, total_ops, _ = crash_template
    early = driver.power_cut_trial(template, tmp_path / "early", seed=1, crash_at=2)
    late = driver.power_cut_trial(template, tmp_path / "late", seed=2, crash_at=total_ops)
    assert (early["after_cut"], late["after_cut"]) == ("old", "new")


def test_lost_page_cache_at_every_operation_boots_verified_image(crash_template, tmp_path):
    """Cut at every file operation of the update, losing unsynced data and folder entries."""
    template, total_ops, _ = crash_template
    outcomes = set()
    for cut_at in range(1, total_ops + 1):
        outcome = driver.lost_cache_trial(template, tmp_path / f"cut{cut_at}", cut_at=cut_at,
                                          seed=cut_at, n_outcomes=2)
        assert outcome["cut"], f"the update finished before operation {cut_at}"
        outcomes.update(outcome["after_cut"])
    assert outcomes == {"old", "new"}


def test_lost_page_cache_during_first_install_never_boots_a_broken_image(crash_template,
                                                                          tmp_path):
    """Cut the very first install at every operation: no image yet, or the verified one."""
    _, _, setup_ops = crash_template
    outcomes = set()
    for cut_at in range(1, setup_ops + 1):
        outcome = driver.lost_cache_trial(None, tmp_path / f"cut{cut_at}", cut_at=cut_at,
                                          seed=cut_at, n_outcomes=2)
        assert outcome["cut"]
        outcomes.update(outcome["after_cut"])
    assert outcomes == {"none", "old"}
