"""Device keys: 32 random bytes shared by the host and one device.

The key signs eigenspace images (HMAC-SHA256 over the image digest, see `protocol.image`) and
authenticates link sessions. A key file is UTF-8 text: comment lines starting with ``#``, then
one line of 64 hexadecimal digits; it is created with mode 0600 and never overwritten unless
asked. Only a fingerprint (the first 8 bytes of the key's SHA-256, in hex) is ever printed.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import secrets
from pathlib import Path

from protocol.errors import ProtocolError

__all__ = [
    "KEY_SIZE",
    "KeyFileError",
    "generate_key",
    "key_fingerprint",
    "load_key",
    "write_key",
]

KEY_SIZE = 32
_MAX_KEY_FILE_BYTES = 4096


class KeyFileError(ProtocolError):
    """A key file is missing, unreadable or malformed, or would be overwritten."""


def generate_key() -> bytes:
    """Return `KEY_SIZE` (32) bytes from the operating system's CSPRNG (`secrets`)."""
    return secrets.token_bytes(KEY_SIZE)


def key_fingerprint(key: bytes) -> str:
    """Return a short public identifier of ``key``: 16 hex digits of its SHA-256."""
    return hashlib.sha256(key).hexdigest()[:16]


def write_key(path: str | os.PathLike, key: bytes | None = None, *, force: bool = False) -> bytes:
    """Write a key file with mode 0600 and return the key.

    Parameters
    ----------
    path : path-like
        Key file to create.
    key : bytes, optional
        The 32-byte key; a new random one when omitted.
    force : bool
        Replace an existing file (atomically). Without it an existing file is refused.

    Raises
    ------
    KeyFileError
        The file exists and ``force`` is false.
    """
    if key is None:
        key = generate_key()
    if not isinstance(key, bytes) or len(key) != KEY_SIZE:
        raise ValueError(f"write_key: key must be {KEY_SIZE} bytes")
    path = Path(path)
    text = (
        "# eigencast device key (HMAC-SHA256). Keep it secret; "
        f"fingerprint {key_fingerprint(key)}\n{key.hex()}\n"
    ).encode()
    if not force:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            raise KeyFileError(
                f"key file '{path}' already exists; use --force to replace it "
                "(devices provisioned with the old key will refuse images signed with the new one)"
            ) from None
        _write_all(fd, text, path)
        return key
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        _write_all(fd, text, tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return key


def _write_all(fd: int, data: bytes, path: Path) -> None:
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(path)
        raise


def load_key(path: str | os.PathLike) -> bytes:
    """Read a key file written by `write_key` (or by hand: comments, then 64 hex digits).

    Returns
    -------
    bytes
        The 32-byte key.

    Raises
    ------
    KeyFileError
        Missing or unreadable file, no key line, not hexadecimal, or not 32 bytes.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(_MAX_KEY_FILE_BYTES + 1)
    except FileNotFoundError:
        raise KeyFileError(
            f"key file '{path}' not found (create one with `eigencast keygen -o {path}`)"
        ) from None
    except OSError as exc:
        raise KeyFileError(f"key file '{path}': cannot read: {exc.strerror or exc}") from None
    if len(raw) > _MAX_KEY_FILE_BYTES:
        raise KeyFileError(
            f"key file '{path}' is larger than {_MAX_KEY_FILE_BYTES} bytes: not a key file"
        )
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise KeyFileError(f"key file '{path}' is not text: not a key file") from None
    lines = [line.strip() for line in text.splitlines()]
    lines = [line for line in lines if line and not line.startswith("#")]
    if len(lines) != 1:
        raise KeyFileError(
            f"key file '{path}' has {len(lines)} key lines, expected exactly 1 line of "
            f"{2 * KEY_SIZE} hex digits"
        )
    try:
        key = bytes.fromhex(lines[0])
    except ValueError:
        raise KeyFileError(
            f"key file '{path}': the key line is not hexadecimal (expected {2 * KEY_SIZE} hex "
            "digits)"
        ) from None
    if len(key) != KEY_SIZE:
        raise KeyFileError(
            f"key file '{path}': the key is {len(key)} bytes, expected {KEY_SIZE} "
            f"({2 * KEY_SIZE} hex digits)"
        )
    return key
