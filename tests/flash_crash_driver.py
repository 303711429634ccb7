"""Power-cut driver for the flash store: a child process that tests kill.

Usage::

    python tests/flash_crash_driver.py DIR setup
    python tests/flash_crash_driver.py DIR update [--crash-at N] [--seed S]

``setup`` formats ``DIR`` and installs the *old* image (write, verify,
commit_test, boot, confirm). ``update`` does what a device does while it is
provisioned with the *new* image: boot, begin (or resume) the transfer, take
chunks in shuffled windows with duplicates, flush before every "ack", verify,
commit_test, reboot (a fresh ``FlashStore.open``), boot and confirm. If the
new image is already active it only confirms it.

``--crash-at N`` installs a :class:`~device_runtime._flash_io.FileOps` that
SIGKILLs this process at its N-th mutating file operation; when that
operation is a write, a random prefix of it (0 to all bytes) is written first,
a torn write. Without it the driver finishes and prints ``OPS <count>``. A
parent may also kill it after a random delay.

Imported as a module (tests, ``benchmarks/bench_powercut.py``) it offers the
images, :func:`run_driver` and :func:`power_cut_trial` (SIGKILL cuts), and
:class:`PageCacheModel` with :func:`lost_cache_trial`: an in-process cut that
also loses whatever was not fsynced (file contents and folder entries), the
part of a real power cut that SIGKILL cannot simulate.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import signal
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from device_runtime._flash_io import FileOps, install_file_ops  # noqa: E402
from device_runtime.flash import FlashStore  # noqa: E402

CAPACITY_BYTES = 1 << 20
CHUNK_BYTES = 8192
WINDOW_CHUNKS = 4
OLD_GENERATION, NEW_GENERATION = 1, 2


def image_bytes(name: str, size_bytes: int) -> bytes:
    """Deterministic pseudo-random image contents for ``name``."""
    return random.Random(name).randbytes(size_bytes)


OLD_IMAGE = image_bytes("old image", 200_003)
NEW_IMAGE = image_bytes("new image", 331_017)
OLD_SHA256 = hashlib.sha256(OLD_IMAGE).digest()
NEW_SHA256 = hashlib.sha256(NEW_IMAGE).digest()


class CrashingFileOps(FileOps):
    """Counts mutating operations and SIGKILLs the process at operation ``crash_at``."""

    def __init__(self, crash_at: int | None, rng: random.Random) -> None:
        self.crash_at = crash_at
        self.rng = rng
        self.count = 0

    def _tick(self) -> bool:
        self.count += 1
        return self.count == self.crash_at

    def _die(self) -> None:
        os.kill(os.getpid(), signal.SIGKILL)

    def open(self, path, flags, mode=0o644):
        if self._tick():
            if self.rng.random() < 0.5:
                super().open(path, flags, mode)
            self._die()
        return super().open(path, flags, mode)

    def pwrite(self, fd, data, offset):
        if self._tick():
            view = memoryview(data)
            super().pwrite(fd, view[: self.rng.randrange(len(view) + 1)], offset)
            self._die()
        super().pwrite(fd, data, offset)

    def fsync(self, fd):
        if self._tick():
            self._die()
        super().fsync(fd)

    def ftruncate(self, fd, length_bytes):
        if self._tick():
            self._die()
        super().ftruncate(fd, length_bytes)

    def replace(self, src, dst):
        if self._tick():
            if self.rng.random() < 0.5:
                super().replace(src, dst)
            self._die()
        super().replace(src, dst)

    def unlink(self, path):
        if self._tick():
            if self.rng.random() < 0.5:
                super().unlink(path)
            self._die()
        super().unlink(path)

    def fsync_dir(self, path):
        if self._tick():
            self._die()
        super().fsync_dir(path)


def install_image(store: FlashStore, image: bytes, generation: int) -> None:
    """Write, verify, commit, boot and confirm ``image`` in one go (the setup phase)."""
    writer = store.begin_image(size_bytes=len(image), sha256=hashlib.sha256(image).digest(),
                               image_generation=generation)
    writer.write_chunk(0, image)
    if not writer.verify():
        raise SystemExit("setup: verify failed")
    store.commit_test()
    store.boot()
    store.confirm()


def setup(folder: Path, rng: random.Random | None = None) -> None:
    """Format ``folder`` and install OLD_IMAGE, confirmed (``rng`` is unused)."""
    store = FlashStore.open(folder, capacity_bytes=CAPACITY_BYTES)
    install_image(store, OLD_IMAGE, OLD_GENERATION)


def update(folder: Path, rng: random.Random) -> None:
    """Provision NEW_IMAGE like a device under a host: resumable, windowed, acked."""
    store = FlashStore.open(folder)
    result = store.boot()
    if result.sha256 == NEW_SHA256:
        store.confirm()
        return
    writer = store.begin_image(size_bytes=len(NEW_IMAGE), sha256=NEW_SHA256,
                               image_generation=NEW_GENERATION)
    size = len(NEW_IMAGE)
    offset = writer.next_offset
    while offset < size:
        window = list(range(offset, min(offset + WINDOW_CHUNKS * CHUNK_BYTES, size), CHUNK_BYTES))
        rng.shuffle(window)
        for start in window:
            writer.write_chunk(start, NEW_IMAGE[start:start + CHUNK_BYTES])
            if rng.random() < 0.1:  # a duplicated frame
                writer.write_chunk(start, NEW_IMAGE[start:start + CHUNK_BYTES])
        writer.flush()  # the journal is durable before the ack
        offset = writer.next_offset
    if not writer.verify():
        raise SystemExit("update: verify failed")
    store.commit_test()
    rebooted = FlashStore.open(folder)
    result = rebooted.boot()
    if result.sha256 != NEW_SHA256:
        raise SystemExit(f"update: after reboot the active image is not the new one: {result}")
    rebooted.confirm()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("phase", choices=["setup", "update"])
    parser.add_argument("--crash-at", type=int, default=None,
                        help="SIGKILL at this mutating file operation (1-based)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = random.Random(args.seed)
    ops = CrashingFileOps(args.crash_at, random.Random(args.seed + 1))
    install_file_ops(ops)
    if args.phase == "setup":
        setup(args.folder)
    else:
        update(args.folder, rng)
    print(f"OPS {ops.count}", flush=True)
    return 0


# ----------------------------------------------------------- parent-side helpers
def run_driver(folder: Path, phase: str, *, crash_at: int | None = None, seed: int = 0,
               kill_after_s: float | None = None, timeout_s: float = 120.0
               ) -> subprocess.CompletedProcess[str]:
    """Run the driver as a child; with ``kill_after_s`` SIGKILL it after that delay."""
    cmd = [sys.executable, str(Path(__file__).resolve()), str(folder), phase, "--seed", str(seed)]
    if crash_at is not None:
        cmd += ["--crash-at", str(crash_at)]
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             cwd=REPO_ROOT)
    if kill_after_s is not None:
        try:
            child.wait(timeout=kill_after_s)
        except subprocess.TimeoutExpired:
            child.kill()  # SIGKILL
    stdout, stderr = child.communicate(timeout=timeout_s)
    return subprocess.CompletedProcess(cmd, child.returncode, stdout, stderr)


def count_ops(stdout: str) -> int:
    """The ``OPS n`` a finished driver printed."""
    for line in stdout.splitlines():
        if line.startswith("OPS "):
            return int(line.split()[1])
    raise AssertionError(f"driver printed no OPS line: {stdout!r}")


def check_boot(folder: Path, *, allow_none: bool = False) -> str:
    """Open and boot like a device after power-up; return "old" or "new" (asserts validity).

    With ``allow_none`` (a cut during the very first install) "none" is also fine.
    """
    store = FlashStore.open(folder)
    result = store.boot()
    if allow_none and not result.ok:
        return "none"
    assert result.ok, f"no bootable image after a power cut: {result.reason}"
    assert result.verified, result.reason
    # The record may only name images whose bytes were durable when it was written: a cut
    # must never need the digest fallback (that would be an fsync-ordering bug).
    assert not result.fell_back, f"boot had to fall back: {result.reason}"
    with store.open_active() as handle:
        digest = hashlib.sha256(handle.read()).digest()
    assert digest == result.sha256, "active slot bytes differ from its recorded digest"
    assert digest in (OLD_SHA256, NEW_SHA256), "active image is neither the old nor the new one"
    return "new" if digest == NEW_SHA256 else "old"


def power_cut_trial(template: Path, folder: Path, *, seed: int, crash_at: int | None = None,
                    kill_after_s: float | None = None) -> dict[str, object]:
    """One cut: copy the set-up ``template``, cut ``update``, boot, then resume to the end.

    Returns a dict: ``killed`` (the cut happened before the driver finished),
    ``after_cut`` ("old"/"new": the image booted right after the cut) and
    ``final`` ("new" once the resumed update finished and a reboot boots it).
    Raises AssertionError when any boot finds no valid image or the resume fails.
    """
    import shutil

    shutil.copytree(template, folder)
    cut = run_driver(folder, "update", crash_at=crash_at, seed=seed, kill_after_s=kill_after_s)
    killed = cut.returncode == -signal.SIGKILL
    assert killed or cut.returncode == 0, f"driver failed (rc {cut.returncode}): {cut.stderr}"
    after_cut = check_boot(folder)
    resumed = run_driver(folder, "update", seed=seed + 1000)
    assert resumed.returncode == 0, f"resume failed (rc {resumed.returncode}): {resumed.stderr}"
    final = check_boot(folder)
    assert final == "new", "after the resumed update the new image is not active"
    store = FlashStore.open(folder)
    assert store.slots["AB".index(store.active_slot)].state.label == "confirmed"
    return {"killed": killed, "after_cut": after_cut, "final": final}


class PowerCut(BaseException):
    """Raised by the model at the cut (BaseException: no handler in the store catches it)."""


class PageCacheModel(FileOps):
    """A disk that loses what was not fsynced: the power cut SIGKILL cannot simulate.

    Tracks, per file (inode), the content as of its last ``fsync`` and, per name,
    the folder entry as of the last ``fsync_dir``. At the cut, :meth:`materialize`
    builds the folder a reboot could find: each name's entry and each file's
    content is independently either the durable or the current one.
    """

    def __init__(self, folder: Path, cut_at: int) -> None:
        self.cut_at = cut_at
        self.count = 0
        self.inodes = 0
        self.names_now: dict[str, int] = {}
        self.durable: dict[int, bytes] = {}
        self.fd_inode: dict[int, int] = {}
        for entry in sorted(folder.iterdir()) if folder.exists() else ():
            self.names_now[entry.name] = self._new_inode(entry.read_bytes())
        self.names_durable = dict(self.names_now)

    def _new_inode(self, content: bytes) -> int:
        self.inodes += 1
        self.durable[self.inodes] = content
        return self.inodes

    def _tick(self) -> None:
        self.count += 1
        if self.count == self.cut_at:
            raise PowerCut

    def open(self, path, flags, mode=0o644):
        self._tick()
        name = os.path.basename(path)
        fd = super().open(path, flags, mode)
        if name not in self.names_now:
            self.names_now[name] = self._new_inode(b"")
        self.fd_inode[fd] = self.names_now[name]
        return fd

    def pwrite(self, fd, data, offset):
        self._tick()
        super().pwrite(fd, data, offset)

    def ftruncate(self, fd, length_bytes):
        self._tick()
        super().ftruncate(fd, length_bytes)

    def fsync(self, fd):
        self._tick()
        with open(f"/proc/self/fd/{fd}", "rb") as handle:
            self.durable[self.fd_inode[fd]] = handle.read()

    def replace(self, src, dst):
        self._tick()
        super().replace(src, dst)
        self.names_now[os.path.basename(dst)] = self.names_now.pop(os.path.basename(src))

    def unlink(self, path):
        self._tick()
        super().unlink(path)
        self.names_now.pop(os.path.basename(path), None)

    def fsync_dir(self, path):
        self._tick()
        self.names_durable = dict(self.names_now)

    def materialize(self, live: Path, out: Path, rng: random.Random) -> None:
        out.mkdir()
        for name in sorted(set(self.names_now) | set(self.names_durable)):
            inode = (self.names_durable if rng.random() < 0.5 else self.names_now).get(name)
            if inode is None:
                continue
            content = self.durable[inode]
            if self.names_now.get(name) == inode and rng.random() < 0.5:
                content = (live / name).read_bytes()  # the unsynced writes did reach the disk
            (out / name).write_bytes(content)


def lost_cache_trial(template: Path | None, workdir: Path, *, cut_at: int, seed: int,
                     n_outcomes: int = 2) -> dict[str, object]:
    """Run ``update`` in-process under :class:`PageCacheModel`, cut at ``cut_at``, boot.

    Copies ``template`` to ``workdir/live`` (or, when ``template`` is None,
    runs ``setup`` on an empty folder instead of ``update``), cuts, then
    materializes ``n_outcomes`` random post-cut disks and boots each
    (:func:`check_boot` asserts). Returns ``cut`` (False when the phase finished
    first) and ``after_cut``: the list of "none"/"old"/"new" outcomes.
    """
    import shutil

    live = workdir / "live"
    if template is not None:
        shutil.copytree(template, live)
    model = PageCacheModel(live, cut_at)
    previous = install_file_ops(model)
    cut = False
    try:
        (setup if template is None else update)(live, random.Random(seed))
    except PowerCut:
        cut = True
    finally:
        install_file_ops(previous)
    rng = random.Random(seed)
    outcomes = []
    for trial in range(n_outcomes):
        after = workdir / f"after{trial}"
        model.materialize(live, after, rng)
        outcomes.append(check_boot(after, allow_none=template is None))
        shutil.rmtree(after)
    shutil.rmtree(live)
    return {"cut": cut, "after_cut": outcomes}


if __name__ == "__main__":
    sys.exit(main())
