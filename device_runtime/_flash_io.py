"""The one seam through which the flash store changes files on disk.

Every *mutating* system call of :mod:`device_runtime.flash` (create, write,
truncate, fsync, rename, unlink, fsync of the folder) goes through the
:class:`FileOps` object returned by :func:`file_ops`. Reads go straight to
:mod:`os`. Production code never replaces it; the power-cut tests install a
subclass (see ``tests/flash_crash_driver.py``) that counts the operations and
kills its own process with SIGKILL at a chosen one, tearing a write half way,
which lets a test cut the power at every step of a provisioning sequence.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import stat
from collections.abc import Callable
from typing import Any, TypeVar

from device_runtime.errors import FlashError

__all__ = ["READ_CHUNK_BYTES", "FileOps", "NotARegularFile", "file_ops", "install_file_ops",
           "open_regular"]

READ_CHUNK_BYTES = 1 << 20
"""Buffer of every streaming read (verification, open_active)."""


class FileOps:
    """Thin wrappers over the POSIX calls the flash store uses to change files."""

    def open(self, path: str, flags: int, mode: int = 0o644) -> int:
        """Open ``path`` with ``os.open`` flags (``O_CLOEXEC`` added); return the fd."""
        return os.open(path, flags | getattr(os, "O_CLOEXEC", 0), mode)

    def pwrite(self, fd: int, data: bytes | memoryview, offset: int) -> None:
        """Write all of ``data`` at byte ``offset`` of ``fd`` (loops over short writes)."""
        view = memoryview(data)
        while view:
            written = os.pwrite(fd, view, offset)
            view = view[written:]
            offset += written

    def fsync(self, fd: int) -> None:
        """Flush ``fd``'s data and metadata to stable storage."""
        os.fsync(fd)

    def ftruncate(self, fd: int, length_bytes: int) -> None:
        """Cut or extend the file behind ``fd`` to ``length_bytes``."""
        os.ftruncate(fd, length_bytes)

    def replace(self, src: str, dst: str) -> None:
        """Atomically rename ``src`` over ``dst`` (same folder)."""
        os.replace(src, dst)

    def unlink(self, path: str) -> None:
        """Remove ``path``; a missing file is not an error."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)

    def fsync_dir(self, path: str) -> None:
        """Make the folder's entries (creations, renames, removals) durable."""
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


_current: FileOps = FileOps()


def file_ops() -> FileOps:
    """Return the :class:`FileOps` in use (the plain one unless a test installed another)."""
    return _current


def install_file_ops(ops: FileOps) -> FileOps:
    """Use ``ops`` for every later flash-store write; return the previous object (tests only)."""
    global _current
    previous, _current = _current, ops
    return previous


# ------------------------------------------------------------------ shared by store and writer


_F = TypeVar("_F", bound=Callable[..., Any])


def _wrap_os_errors(operation: str) -> Callable[[_F], _F]:
    """Turn an ``OSError`` inside a public method into one-line :class:`FlashError`."""

    def decorate(func: _F) -> _F:
        @functools.wraps(func)
        def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
            try:
                return func(self, *args, **kwargs)
            except OSError as exc:
                where = exc.filename or getattr(self, "path", "")
                raise FlashError(f"flash {operation}: {where}: {exc.strerror or exc}") from exc

        return wrapper  # type: ignore[return-value]

    return decorate


class NotARegularFile(OSError):
    """A store file's name holds a directory, a FIFO, a device... instead of a file."""


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a file"


def check_regular(fd: int, path: str) -> None:
    """Raise :class:`NotARegularFile` (``fd`` left open) unless ``fd`` is a regular file."""
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        raise NotARegularFile(0, f"not a regular file ({_kind(mode)})", path)


def open_regular(path: str | os.PathLike[str]) -> int:
    """Open an existing store file for reading; return the fd (blocking reads).

    Never blocks: the open is non-blocking, so a FIFO in the file's place (whose plain open
    waits for a writer forever) is opened at once and refused with the rest. Raises
    :class:`NotARegularFile` for anything but a regular file, FileNotFoundError when absent.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        check_regular(fd, str(path))
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _hash_fd(fd: int, offset: int, length: int) -> tuple[bytes | None, int]:
    """SHA-256 of ``length`` bytes at ``offset`` (streaming); (None, bytes read) when short."""
    hasher = hashlib.sha256()
    buffer = bytearray(min(READ_CHUNK_BYTES, max(length, 1)))
    view = memoryview(buffer)
    done = 0
    while done < length:
        want = min(len(buffer), length - done)
        got = os.preadv(fd, [view[:want]], offset + done)
        if got == 0:
            return None, done
        hasher.update(view[:got])
        done += got
    return hasher.digest(), done


def _check_uint(name: str, value: object, *, low: int, high: int, error: type[Exception]) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if not low <= value <= high:
        raise error(f"{name}={value} must be in [{low}, {high}]")
    return value
