"""pyserial handler for ``mem://``: one end of an in-memory serial line.

URL format::

    mem://NAME?end=a|b[&pace=0|1][&latency_ms=F][&rx_buffer=N][&flow=0|1]
              [&ber=F][&drop=F][&dup=F][&reorder=F][&burst=F][&burst_bytes=N]
              [&disconnect_after=N][&seed=N][&tick_ms=F]

``NAME`` is shared by both ends (process-wide, threads only); ``end`` picks the
side. The other options describe what *this* end sends and receives (see
:mod:`protocol.wireline` for the model): ``pace`` (default 1) paces at the
port's ``baudrate``; ``latency_ms`` (0); ``rx_buffer`` bytes this end buffers
(4096); ``flow`` 1 = writers block when that buffer is full, 0 = excess bytes
are lost; ``ber`` bit error rate and ``drop``/``dup``/``reorder``/``burst``
per-byte rates of this end's transmissions; ``burst_bytes`` (64) lost per
burst; ``disconnect_after`` cuts the line once this end has sent N bytes;
``seed`` (0) of the fault generator; ``tick_ms`` (1) how often a waiting reader
polls a paced line. Unknown options are rejected.

Example::

    import serial
    from protocol.transport import register_url_handlers
    register_url_handlers()
    host = serial.serial_for_url("mem://demo?end=a&ber=1e-5&seed=3", baudrate=921600, timeout=1)
    device = serial.serial_for_url("mem://demo?end=b", baudrate=921600, timeout=1)
"""

from __future__ import annotations

import logging
import urllib.parse

from serial.serialutil import (
    PortNotOpenError,
    SerialBase,
    SerialException,
    SerialTimeoutException,
)

from protocol.wireline import (
    EndOptions,
    LineEnd,
    LineError,
    LineTimeout,
    open_end,
)

__all__ = ["URL_FORMAT", "Serial", "parse_mem_url"]

URL_FORMAT = (
    "mem://NAME?end=a|b[&pace=0|1][&latency_ms=F][&rx_buffer=N][&flow=0|1][&ber=F]"
    "[&drop=F][&dup=F][&reorder=F][&burst=F][&burst_bytes=N][&disconnect_after=N]"
    "[&seed=N][&tick_ms=F]"
)

_logger = logging.getLogger("protocol.urlhandler.mem")


def _flag(text: str) -> bool:
    if text not in ("0", "1"):
        raise ValueError(f"must be 0 or 1, got {text!r}")
    return text == "1"


# option -> (EndOptions field, parser)
_OPTIONS = {
    "pace": ("pace", _flag),
    "latency_ms": ("latency_s", lambda t: float(t) / 1000.0),
    "rx_buffer": ("rx_buffer_bytes", int),
    "flow": ("flow_control", _flag),
    "ber": ("ber", float),
    "drop": ("drop_rate", float),
    "dup": ("dup_rate", float),
    "reorder": ("reorder_rate", float),
    "burst": ("burst_rate", float),
    "burst_bytes": ("burst_bytes", int),
    "disconnect_after": ("disconnect_after", int),
    "seed": ("seed", int),
    "tick_ms": ("rx_tick_s", lambda t: float(t) / 1000.0),
}


def parse_mem_url(url: str, *, baud: int = 115200) -> tuple[str, str, EndOptions]:
    """Parse a ``mem://`` URL.

    Parameters
    ----------
    url : str
        See the module docstring for the format.
    baud : int
        The port's baud rate (pyserial ``baudrate``).

    Returns
    -------
    (name, end, options) : tuple of str, str, EndOptions

    Raises
    ------
    ValueError
        Naming the bad part and quoting the expected format.
    """
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != "mem":
        raise ValueError(f"expected {URL_FORMAT}: scheme {parts.scheme!r} is not mem")
    name = parts.netloc + parts.path
    if not name:
        raise ValueError(f"expected {URL_FORMAT}: missing NAME in {url!r}")
    query = urllib.parse.parse_qs(parts.query, keep_blank_values=True, strict_parsing=False)
    end = None
    fields: dict[str, object] = {"baud": baud}
    for option, values in query.items():
        if len(values) != 1:
            raise ValueError(f"expected {URL_FORMAT}: option {option!r} given {len(values)} times")
        value = values[0]
        if option == "end":
            if value not in ("a", "b"):
                raise ValueError(f"expected {URL_FORMAT}: end={value!r} must be a or b")
            end = value
            continue
        if option not in _OPTIONS:
            raise ValueError(
                f"expected {URL_FORMAT}: unknown option {option!r} "
                f"(known: end, {', '.join(sorted(_OPTIONS))})"
            )
        field, parse = _OPTIONS[option]
        try:
            fields[field] = parse(value)
        except ValueError as exc:
            raise ValueError(f"expected {URL_FORMAT}: {option}={value!r}: {exc}") from None
    if end is None:
        raise ValueError(f"expected {URL_FORMAT}: missing end=a or end=b in {url!r}")
    try:
        options = EndOptions(**fields)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"expected {URL_FORMAT}: {exc}") from None
    return name, end, options


class Serial(SerialBase):
    """pyserial port on one end of an in-memory line (see the module docstring).

    Modem lines (RTS/DTR/break) are ignored and logged; CTS/DSR/CD read True.
    """

    def __init__(self, *args: object, **kwargs: object) -> None:
        self._end: LineEnd | None = None
        super().__init__(*args, **kwargs)

    # ------------------------------------------------------------------ open/close
    def open(self) -> None:
        """Open the end named by ``self.port``."""
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        try:
            name, end, options = parse_mem_url(self._port, baud=int(self._baudrate))
            self._end = open_end(name, end, options)
        except (ValueError, LineError) as exc:
            raise SerialException(f"Could not open port {self._port}: {exc}") from None
        self.is_open = True

    def close(self) -> None:
        """Close this end (the peer keeps its end; bytes sent to it are then lost)."""
        if self._end is not None:
            self._end.close()
            self._end = None
        self.is_open = False

    def _reconfigure_port(self) -> None:
        """Apply a baud change; other settings have no meaning on this line."""
        if self._end is not None:
            self._end.set_baud(int(self._baudrate))

    def _line(self) -> LineEnd:
        if not self.is_open or self._end is None:
            raise PortNotOpenError()
        return self._end

    @property
    def line_end(self) -> LineEnd:
        """The underlying :class:`protocol.wireline.LineEnd` (for stats in tests)."""
        return self._line()

    # ------------------------------------------------------------------ data
    @property
    def in_waiting(self) -> int:
        """Bytes that have arrived and not been read."""
        return self._line().in_waiting

    @property
    def out_waiting(self) -> int:
        """Bytes written that have not arrived at the peer yet."""
        return self._line().out_waiting

    def read(self, size: int = 1) -> bytes:
        """Read up to ``size`` bytes, waiting at most ``timeout`` (pyserial semantics)."""
        line = self._line()
        try:
            return line.read(size, self._timeout)
        except LineError as exc:  # LineBroken, or this end closed meanwhile
            raise SerialException(str(exc)) from None

    def read_available(self, max_bytes: int, timeout_s: float) -> bytes:
        """Return as soon as any byte is there (up to ``max_bytes``), or b"" after ``timeout_s``.

        The transport adapter prefers this to ``read`` (no timeout juggling).
        """
        line = self._line()
        try:
            return line.read(max_bytes, timeout_s, first_only=True)
        except LineError as exc:
            raise SerialException(str(exc)) from None

    def write(self, data: bytes) -> int:
        """Queue ``data``; blocks while the peer's buffer is full, up to ``write_timeout``."""
        line = self._line()
        try:
            return line.write(data, self._write_timeout)
        except LineTimeout as exc:
            raise SerialTimeoutException(f"Write timeout: {exc}") from None
        except LineError as exc:
            raise SerialException(str(exc)) from None

    def flush(self) -> None:
        """Wait until all written bytes have left this end."""
        self._line().flush(self._write_timeout)

    def reset_input_buffer(self) -> None:
        """Discard received and in-flight bytes."""
        self._line().reset_input()

    def reset_output_buffer(self) -> None:
        """Nothing to discard: written bytes are already on the wire."""
        _logger.debug("ignored reset_output_buffer")

    # ------------------------------------------------------------------ modem lines
    def _update_rts_state(self) -> None:
        _logger.debug("ignored RTS=%s", self._rts_state)

    def _update_dtr_state(self) -> None:
        _logger.debug("ignored DTR=%s", self._dtr_state)

    def _update_break_state(self) -> None:
        _logger.debug("ignored break=%s", self._break_state)

    @property
    def cts(self) -> bool:
        """Always True (flow control is modelled inside the line)."""
        return True

    @property
    def dsr(self) -> bool:
        """Always True."""
        return True

    @property
    def ri(self) -> bool:
        """Always False."""
        return False

    @property
    def cd(self) -> bool:
        """Always True."""
        return True
