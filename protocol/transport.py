"""Byte transports: one ``Transport`` protocol, opened from a URL.

``open_transport(url, *, baud, timeout_s)`` picks the back end from the URL
scheme. Our own schemes live in a plain dict (``OPENERS``): ``tcp-listen``
(a hyphen cannot be a ``protocol_<scheme>`` module name) and ``mem``. Anything
else goes to :func:`serial.serial_for_url` (device paths such as
``/dev/ttyUSB0``, ``socket://``, ``rfc2217://``, ``loop://``) wrapped in
:class:`SerialTransport`, which irons out pyserial's traps:

* ``socket://``: ``in_waiting`` is 0 or 1 (a ``select`` result, not a count) and
  ``read(n)`` blocks until n bytes or the timeout. The adapter waits with
  ``select`` on the port's file descriptor and then reads non-blockingly, so a
  read returns what has arrived. It also turns on TCP_NODELAY (pyserial does
  not), so small frames are not held back by Nagle's algorithm. pyserial's
  ``close()`` of a socket port sleeps 0.3 s.
* ``rfc2217://``: ``write_timeout`` raises NotImplementedError, so writes there
  block until sent; every timeout change renegotiates the port, so the
  adapter only sets it when it changes.
* ``loop://``: one port looped back to itself through a 4096-byte queue (not a
  pair; writes larger than the queue block without a concurrent reader), so
  its default ``max_frame_bytes`` is 1024.

Every transport: ``write(data) -> int`` (all bytes or ``TransportTimeout``),
``read(max_bytes, timeout_s) -> bytes`` (what has arrived, up to
``max_bytes``; b"" on timeout; never blocks longer than ``timeout_s``),
``close()``, ``max_frame_bytes``, ``url``, ``set_baud(baud)``. A vanished peer
raises ``TransportClosed``.

For host and device in *separate processes* use TCP (``tcp-listen://`` on the
device, ``socket://`` on the host) or a pty pair (:func:`open_pty_pair`); the
``mem://`` line works between threads of one process only.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import os
import pkgutil
import re
import select
import socket
import threading
import time
import urllib.parse
from typing import Any, Protocol, runtime_checkable

import serial
import serial.urlhandler
from serial.serialutil import SerialException, SerialTimeoutException

import protocol.urlhandler
from protocol.errors import TransportClosed, TransportError, TransportTimeout

__all__ = [
    "DEFAULT_MAX_FRAME_BYTES",
    "DEFAULT_TIMEOUT_S",
    "LISTEN_BACKLOG",
    "OPENERS",
    "FdTransport",
    "PtyPair",
    "SerialTransport",
    "TcpListenTransport",
    "Transport",
    "known_schemes",
    "open_pty_pair",
    "open_transport",
    "register_url_handlers",
]

_logger = logging.getLogger("protocol.transport")

DEFAULT_TIMEOUT_S = 5.0
"""Default write and connect timeout of ``open_transport``."""
LISTEN_BACKLOG = 128
"""Connections the kernel holds for a ``tcp-listen://`` device before it accepts them (a
backlog of 1 let looping peers keep a host's connection from being accepted at all)."""

DEFAULT_MAX_FRAME_BYTES = {
    "": 4096,  # device paths (real UARTs)
    "mem": 4096,
    "loop": 1024,
    "socket": 16384,
    "rfc2217": 4096,
    "tcp-listen": 16384,
}
"""Default ``max_frame_bytes`` by scheme (others: 4096)."""


@runtime_checkable
class Transport(Protocol):
    """What the link engine needs from a byte stream.

    Attributes
    ----------
    url : str
        The URL it was opened from.
    max_frame_bytes : int
        Largest frame (before COBS) this transport should carry, bytes.
    """

    url: str

    @property
    def max_frame_bytes(self) -> int:
        """Largest frame (header + body + CRC, before COBS) to send over it, bytes."""
        ...

    def write(self, data: bytes) -> int:
        """Send all of ``data``; return ``len(data)``.

        Raises TransportTimeout if it cannot within the transport's timeout,
        TransportClosed if the peer is gone.
        """
        ...

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        """Return 1..max_bytes bytes as soon as any arrive, or b"" after ``timeout_s``."""
        ...

    def set_baud(self, baud: int) -> None:
        """Change the line rate where that means something (logged as ignored elsewhere)."""
        ...

    def close(self) -> None:
        """Release the transport (idempotent)."""
        ...


def _check_read_args(max_bytes: int, timeout_s: float) -> None:
    if max_bytes < 1:
        raise ValueError(f"read: max_bytes={max_bytes} must be >= 1")
    if not timeout_s >= 0:
        raise ValueError(f"read: timeout_s={timeout_s} must be >= 0")


# --------------------------------------------------------------------------- pyserial


def register_url_handlers() -> None:
    """Make pyserial find our URL handlers (``mem://``); idempotent."""
    if "protocol.urlhandler" not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append("protocol.urlhandler")


def _pyserial_schemes() -> list[str]:
    names = set()
    for package in (serial.urlhandler, protocol.urlhandler):
        for module in pkgutil.iter_modules(package.__path__):
            if module.name.startswith("protocol_"):
                names.add(module.name[len("protocol_") :])
    return sorted(names)


def known_schemes() -> list[str]:
    """Return every URL scheme ``open_transport`` accepts (plus plain device paths)."""
    return sorted(set(OPENERS) | set(_pyserial_schemes()))


class SerialTransport:
    """A pyserial port adapted to :class:`Transport`.

    Parameters
    ----------
    port : serial.SerialBase
        An open port. Its ``timeout`` is managed here.
    url : str
    max_frame_bytes : int
    scheme : str
        URL scheme ("" for a device path); selects the trap fixes.
    """

    def __init__(self, port: Any, *, url: str, max_frame_bytes: int, scheme: str) -> None:
        self.port = port
        self.url = url
        self.scheme = scheme
        self._max_frame_bytes = max_frame_bytes
        self._timeout_now: float | None = port.timeout
        self._read_available = getattr(port, "read_available", None)
        self._fd: int | None = None
        if self._read_available is None:
            try:
                self._fd = port.fileno()
            except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
                self._fd = None
        if self._fd is not None:
            port.timeout = 0  # non-blocking reads; waiting is done with select
            self._timeout_now = 0
            if scheme == "socket":
                self._set_nodelay(self._fd)

    @staticmethod
    def _set_nodelay(fd: int) -> None:
        dup = socket.socket(fileno=os.dup(fd))
        try:
            dup.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:  # not TCP (e.g. a Unix socket): nothing to do
            _logger.debug("TCP_NODELAY not set on %s: %s", fd, exc)
        finally:
            dup.close()

    @property
    def max_frame_bytes(self) -> int:
        """Largest frame to send, bytes."""
        return self._max_frame_bytes

    @property
    def baud(self) -> int:
        """The port's baud rate."""
        return int(self.port.baudrate)

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        """Return what has arrived (1..max_bytes bytes), or b"" after ``timeout_s``."""
        _check_read_args(max_bytes, timeout_s)
        try:
            if self._read_available is not None:
                return self._read_available(max_bytes, timeout_s)
            if self._fd is not None:
                ready, _, _ = select.select([self._fd], [], [], timeout_s)
                if not ready:
                    return b""
                return self.port.read(max_bytes)
            # No descriptor (loop://, rfc2217://): block for the first byte, then
            # take what in_waiting (an exact count for these) says is there.
            if self._timeout_now != timeout_s:
                self.port.timeout = timeout_s
                self._timeout_now = timeout_s
            first = self.port.read(1)
            if not first or max_bytes == 1:
                return first
            more = min(self.port.in_waiting, max_bytes - 1)
            return first + self.port.read(more) if more else first
        except SerialTimeoutException as exc:  # not expected on reads; keep the type
            raise TransportTimeout(f"read {self.url}: {exc}") from None
        except (SerialException, OSError) as exc:
            raise TransportClosed(f"read {self.url}: {exc}") from None

    def write(self, data: bytes) -> int:
        """Send all of ``data``; return its length."""
        try:
            written = self.port.write(data)
        except SerialTimeoutException as exc:
            raise TransportTimeout(
                f"write {self.url}: {len(data)} bytes not sent within "
                f"{self.port.write_timeout} s ({exc})"
            ) from None
        except (SerialException, OSError) as exc:
            raise TransportClosed(f"write {self.url}: {exc}") from None
        if written is not None and written != len(data):
            raise TransportTimeout(f"write {self.url}: sent {written} of {len(data)} bytes")
        return len(data)

    def set_baud(self, baud: int) -> None:
        """Set the port's baud rate (pyserial ignores it for socket://, and logs that)."""
        if not isinstance(baud, int) or baud <= 0:
            raise ValueError(f"set_baud: baud={baud!r} must be a positive int")
        if self.scheme == "socket":
            _logger.info("set_baud(%d) ignored on %s", baud, self.url)
        try:
            self.port.baudrate = baud
        except (SerialException, ValueError) as exc:
            raise TransportError(f"set_baud {self.url}: {baud} refused: {exc}") from None

    def close(self) -> None:
        """Close the port (idempotent)."""
        try:
            self.port.close()
        except (SerialException, OSError) as exc:
            _logger.debug("close %s: %s", self.url, exc)

    def __enter__(self) -> SerialTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open_pyserial(
    url: str, scheme: str, baud: int, timeout_s: float, max_frame_bytes: int
) -> SerialTransport:
    kwargs: dict[str, Any] = {"baudrate": baud, "timeout": 0}
    if scheme != "rfc2217":  # rfc2217 raises NotImplementedError on write_timeout
        kwargs["write_timeout"] = timeout_s
    try:
        port = serial.serial_for_url(url, **kwargs)
    except (SerialException, ValueError, OSError) as exc:
        if not scheme and re.fullmatch(r"[\w.\-]+:\d{1,5}|\[[0-9A-Fa-f:]+\]:\d{1,5}", url):
            raise TransportError(f"open {url}: no such serial port; did you mean "
                                 f"socket://{url}?") from None  # HOST:PORT, no scheme
        raise TransportError(f"open {url}: {exc}") from None
    return SerialTransport(port, url=url, max_frame_bytes=max_frame_bytes, scheme=scheme)


# --------------------------------------------------------------------------- mem://


def _open_mem(url: str, *, baud: int, timeout_s: float, max_frame_bytes: int) -> SerialTransport:
    """``mem://NAME?end=a|b[&...]``: one end of an in-memory line (see protocol_mem)."""
    register_url_handlers()
    return _open_pyserial(url, "mem", baud, timeout_s, max_frame_bytes)


# --------------------------------------------------------------------------- tcp-listen://


class TcpListenTransport:
    """``tcp-listen://HOST:PORT``: the device side of TCP; one host at a time.

    Listens on HOST:PORT (PORT 0 picks a free port: see ``port``) with a backlog of
    ``LISTEN_BACKLOG``. ``read`` accepts a host when none is connected (within its
    timeout); further hosts wait in the backlog until the current one disconnects. When
    the host goes away, ``read``/``write`` raise ``TransportClosed`` once and the next
    ``read`` (or :meth:`accept`) waits for a new host. :meth:`disconnect` drops a silent
    host (the link engine's inactivity timeout). A keyed device accepts from
    :attr:`listener` itself (``device_runtime.lobby``: every pending connection, until one
    authenticates) and hands the one that did to :meth:`adopt`.

    Parameters
    ----------
    host : str
    port : int
    timeout_s : float
        Write timeout, seconds.
    max_frame_bytes : int
    """

    def __init__(self, host: str, port: int, *, timeout_s: float, max_frame_bytes: int) -> None:
        self._timeout_s = timeout_s
        self._max_frame_bytes = max_frame_bytes
        self._lock = threading.Lock()
        self._conn: socket.socket | None = None
        self.peer: tuple[Any, ...] | None = None
        try:
            self._listener = socket.create_server((host, port), backlog=LISTEN_BACKLOG)
        except OSError as exc:
            raise TransportError(f"open tcp-listen://{host}:{port}: {exc}") from None
        self._listener.setblocking(False)  # accept after select: never blocks
        self.host = host
        self.port: int = self._listener.getsockname()[1]
        self.url = f"tcp-listen://{host}:{self.port}"

    @property
    def max_frame_bytes(self) -> int:
        """Largest frame to send, bytes."""
        return self._max_frame_bytes

    @property
    def connected(self) -> bool:
        """True while a host is connected."""
        return self._conn is not None

    def accept(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a host; True once one is connected."""
        if self._conn is not None:
            return True
        try:
            ready, _, _ = select.select([self._listener], [], [], timeout_s)
        except (OSError, ValueError) as exc:
            raise TransportClosed(f"accept {self.url}: {exc}") from None
        if not ready:
            return False
        try:
            conn, peer = self._listener.accept()
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.ECONNABORTED):
                return False
            raise TransportClosed(f"accept {self.url}: {exc}") from None
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.settimeout(self._timeout_s)
        with self._lock:
            self._conn, self.peer = conn, peer
        _logger.info("%s: host %s connected", self.url, peer)
        return True

    @property
    def listener(self) -> socket.socket:
        """The listening socket (non-blocking), for a caller that accepts by itself."""
        return self._listener

    def adopt(self, conn: socket.socket, peer: tuple[Any, ...]) -> None:
        """Make ``conn`` (accepted from :attr:`listener`) the connected host.

        Raises
        ------
        TransportError
            A host is connected already.
        """
        with self._lock:
            if self._conn is not None:
                raise TransportError(f"adopt {self.url}: a host is connected already")
            conn.settimeout(self._timeout_s)
            self._conn, self.peer = conn, peer
        _logger.info("%s: host %s connected", self.url, peer)

    def disconnect(self) -> None:
        """Drop the current host (if any); the next read waits for a new one."""
        with self._lock:
            conn, self._conn, self.peer = self._conn, None, None
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
            conn.close()

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        """Return what a connected host sent (1..max_bytes), or b"" after ``timeout_s``."""
        _check_read_args(max_bytes, timeout_s)
        deadline = time.monotonic() + timeout_s
        if self._conn is None and not self.accept(timeout_s):
            return b""
        conn = self._conn
        if conn is None:
            return b""
        try:
            ready, _, _ = select.select([conn], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                return b""
            data = conn.recv(max_bytes)
        except (OSError, ValueError) as exc:
            self.disconnect()
            raise TransportClosed(f"read {self.url}: host connection failed: {exc}") from None
        if not data:
            self.disconnect()
            raise TransportClosed(f"read {self.url}: host disconnected")
        return data

    def write(self, data: bytes) -> int:
        """Send all of ``data`` to the connected host."""
        conn = self._conn
        if conn is None:
            raise TransportClosed(f"write {self.url}: no host connected")
        try:
            conn.sendall(data)
        except TimeoutError:
            raise TransportTimeout(
                f"write {self.url}: {len(data)} bytes not sent within {self._timeout_s} s"
            ) from None
        except OSError as exc:
            self.disconnect()
            raise TransportClosed(f"write {self.url}: host connection failed: {exc}") from None
        return len(data)

    def set_baud(self, baud: int) -> None:
        """Ignored (logged): TCP has no baud rate."""
        _logger.info("set_baud(%d) ignored on %s", baud, self.url)

    def close(self) -> None:
        """Drop the host and stop listening (idempotent)."""
        self.disconnect()
        self._listener.close()

    def __enter__(self) -> TcpListenTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open_tcp_listen(
    url: str, *, baud: int, timeout_s: float, max_frame_bytes: int
) -> TcpListenTransport:
    """``tcp-listen://HOST:PORT``: listen for one host at a time (PORT 0: any free port)."""
    del baud
    form = "tcp-listen://HOST:PORT"
    parts = urllib.parse.urlsplit(url)
    if parts.query or parts.path not in ("", "/"):
        raise TransportError(f"open {url}: expected {form} (no path or options)")
    try:
        port = parts.port
    except ValueError as exc:
        raise TransportError(f"open {url}: expected {form}: {exc}") from None
    if parts.hostname is None or port is None:
        raise TransportError(f"open {url}: expected {form}")
    return TcpListenTransport(
        parts.hostname, port, timeout_s=timeout_s, max_frame_bytes=max_frame_bytes
    )


# --------------------------------------------------------------------------- pty


class FdTransport:
    """A raw file descriptor (e.g. a pty master) as a :class:`Transport`.

    Parameters
    ----------
    fd : int
        Open descriptor; owned (closed by :meth:`close`) when ``owns_fd``.
    url : str
        A label for messages.
    timeout_s : float
        Write timeout, seconds.
    max_frame_bytes : int
    owns_fd : bool
    """

    def __init__(
        self,
        fd: int,
        *,
        url: str = "fd",
        timeout_s: float = DEFAULT_TIMEOUT_S,
        max_frame_bytes: int = 4096,
        owns_fd: bool = True,
    ) -> None:
        self.fd = fd
        self.url = url
        self._timeout_s = timeout_s
        self._max_frame_bytes = max_frame_bytes
        self._owns_fd = owns_fd
        self._closed = False
        os.set_blocking(fd, False)

    @property
    def max_frame_bytes(self) -> int:
        """Largest frame to send, bytes."""
        return self._max_frame_bytes

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        """Return what has arrived (1..max_bytes), or b"" after ``timeout_s``."""
        _check_read_args(max_bytes, timeout_s)
        try:
            ready, _, _ = select.select([self.fd], [], [], timeout_s)
            if not ready:
                return b""
            data = os.read(self.fd, max_bytes)
        except BlockingIOError:
            return b""
        except (OSError, ValueError) as exc:  # EIO: the pty's other side closed
            raise TransportClosed(f"read {self.url}: {exc}") from None
        if not data:
            raise TransportClosed(f"read {self.url}: end of file")
        return data

    def write(self, data: bytes) -> int:
        """Write all of ``data`` within the write timeout."""
        view = memoryview(bytes(data))
        deadline = time.monotonic() + self._timeout_s
        while view:
            left = deadline - time.monotonic()
            try:
                _, ready, _ = select.select([], [self.fd], [], max(0.0, left))
                if not ready:
                    raise TransportTimeout(
                        f"write {self.url}: {len(view)} of {len(data)} bytes not sent within "
                        f"{self._timeout_s} s"
                    )
                n = os.write(self.fd, view)
            except BlockingIOError:
                continue
            except (OSError, ValueError) as exc:
                raise TransportClosed(f"write {self.url}: {exc}") from None
            view = view[n:]
        return len(data)

    def set_baud(self, baud: int) -> None:
        """Ignored (logged): a pty has no real line rate."""
        _logger.info("set_baud(%d) ignored on %s", baud, self.url)

    def close(self) -> None:
        """Close the descriptor if owned (idempotent)."""
        if not self._closed:
            self._closed = True
            if self._owns_fd:
                os.close(self.fd)


class PtyPair:
    """A pseudo-terminal pair in raw mode: pyserial opens ``slave_path``, the
    other side talks through ``master_fd`` (e.g. wrapped in :class:`FdTransport`).

    The slave side is held open here until :meth:`close`, so the master never
    sees EIO merely because pyserial has not opened the path yet. A pty does not
    pace bytes at any baud rate.

    Attributes
    ----------
    master_fd : int
    slave_path : str
        E.g. ``/dev/pts/5``; pass it to ``open_transport`` or ``serial.Serial``.
    """

    def __init__(self, master_fd: int, slave_fd: int, slave_path: str) -> None:
        self.master_fd = master_fd
        self._slave_fd: int | None = slave_fd
        self.slave_path = slave_path
        self._master_owned = True

    def master_transport(
        self, *, timeout_s: float = DEFAULT_TIMEOUT_S, max_frame_bytes: int = 4096
    ) -> FdTransport:
        """Return the master side as a Transport (it then owns ``master_fd``)."""
        self._master_owned = False
        return FdTransport(
            self.master_fd,
            url=f"pty-master:{self.slave_path}",
            timeout_s=timeout_s,
            max_frame_bytes=max_frame_bytes,
        )

    def close(self) -> None:
        """Close the held slave descriptor and, unless handed out, the master."""
        if self._slave_fd is not None:
            os.close(self._slave_fd)
            self._slave_fd = None
        if self._master_owned:
            self._master_owned = False
            os.close(self.master_fd)

    def __enter__(self) -> PtyPair:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_pty_pair() -> PtyPair:
    """Create a pty pair in raw mode (POSIX only).

    Returns
    -------
    PtyPair
        ``master_fd`` and ``slave_path``; close it when done.

    Raises
    ------
    TransportError
        No pty support on this system.
    """
    try:
        import tty
    except ImportError:
        raise TransportError("open_pty_pair: ptys need a POSIX system") from None
    try:
        master_fd, slave_fd = os.openpty()
    except OSError as exc:
        raise TransportError(f"open_pty_pair: {exc}") from None
    tty.setraw(master_fd)
    tty.setraw(slave_fd)
    return PtyPair(master_fd, slave_fd, os.ttyname(slave_fd))


# --------------------------------------------------------------------------- registry


OPENERS = {
    "tcp-listen": _open_tcp_listen,
    "mem": _open_mem,
}
"""Our own schemes -> opener(url, *, baud, timeout_s, max_frame_bytes)."""


def open_transport(
    url: str,
    *,
    baud: int = 115200,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    max_frame_bytes: int | None = None,
) -> Transport:
    """Open a transport from a URL.

    Parameters
    ----------
    url : str
        ``tcp-listen://HOST:PORT``, ``mem://NAME?end=a|b[&...]``, or anything
        ``serial.serial_for_url`` opens: a device path (``/dev/ttyUSB0``,
        ``COM3``), ``socket://HOST:PORT``, ``rfc2217://HOST:PORT``, ``loop://``.
    baud : int
        Line rate for serial ports and ``mem://`` pacing.
    timeout_s : float
        Longest a ``write`` may block (and pyserial's connect), seconds.
    max_frame_bytes : int, optional
        Default by scheme (``DEFAULT_MAX_FRAME_BYTES``).

    Returns
    -------
    Transport

    Raises
    ------
    TransportError
        Unknown scheme (the message lists the known ones) or the port could
        not be opened.
    """
    if not isinstance(url, str) or not url:
        raise TransportError(f"open transport: url={url!r} must be a non-empty string")
    if not isinstance(baud, int) or baud <= 0:
        raise ValueError(f"open transport: baud={baud!r} must be a positive int")
    if not timeout_s > 0:
        raise ValueError(f"open transport: timeout_s={timeout_s} must be > 0")
    scheme = url.split("://", 1)[0].lower() if "://" in url else ""
    if max_frame_bytes is None:
        max_frame_bytes = DEFAULT_MAX_FRAME_BYTES.get(scheme, 4096)
    if not 64 <= max_frame_bytes <= 1 << 24:
        raise ValueError(
            f"open transport: max_frame_bytes={max_frame_bytes} must be in [64, 2**24]"
        )
    opener = OPENERS.get(scheme)
    if opener is not None:
        return opener(url, baud=baud, timeout_s=timeout_s, max_frame_bytes=max_frame_bytes)
    if scheme and scheme not in _pyserial_schemes():
        raise TransportError(
            f"open {url}: unknown scheme {scheme!r}; known: "
            f"{', '.join(s + '://' for s in known_schemes())} or a device path such as /dev/ttyUSB0"
        )
    return _open_pyserial(url, scheme, baud, timeout_s, max_frame_bytes)


register_url_handlers()
