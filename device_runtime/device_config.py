"""What a device is and counts: :class:`DeviceConfig` (built from ``eigencast-device``'s
flags) and :class:`DeviceStats` (what :class:`~device_runtime.device.Device` refused and did),
with the defaults they use. Importable from :mod:`device_runtime.device` as before."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

__all__ = [
    "DEFAULT_DEVICE_ID",
    "DEFAULT_RAM_BUDGET_BYTES",
    "DEFAULT_RX_WINDOW_FRAMES",
    "DeviceConfig",
    "DeviceStats",
]

DEFAULT_DEVICE_ID = "eigencast-device"
DEFAULT_RAM_BUDGET_BYTES = 256 * 1024 * 1024
"""RAM the eigenspace may use unless ``--ram-budget`` says otherwise (256 MiB)."""
DEFAULT_RX_WINDOW_FRAMES = 32
"""Image receive buffers advertised in HELLO_REPLY (chunks in flight)."""


@dataclass(frozen=True)
class DeviceConfig:
    """What a device is and declares (the CLI builds it from flags).

    Attributes
    ----------
    flash_dir : Path
        The flash folder.
    key : bytes or None
        32-byte device key; None: no key (provisioning refused unless ``insecure``).
    insecure : bool
        Accept provisioning without authentication and unsigned images (no key only).
    device_id : str
        1..64 UTF-8 bytes; enters the AUTH proofs.
    ram_budget_bytes : int
        RAM an eigenspace may use; larger images are refused (TOO_LARGE_FOR_RAM).
    slot_size_bytes : int or None
        Flash slot capacity when formatting a new folder (None: the store's default,
        or what an existing store has).
    rx_window_frames : int
        Image receive buffers (chunks in flight), 1..65535.
    rx_buffer_bytes : int or None
        Largest chunk accepted (None: what the frame size allows).
    max_frame_bytes : int or None
        Largest frame (None: the transport's).
    display_width, display_height : int
        Pixels (0: headless).
    flush_interval_s : float
        Longest time received chunks stay un-journalled (durability for resume
        after a reboot), seconds.
    idle_timeout_s : float
        A TCP host that sends no valid frame for this long is dropped, seconds.
    auth_timeout_s : float
        Keyed device on TCP: a connection that has not completed AUTH this long after the
        device began to serve it (or after its session lost authentication) is dropped,
        whatever else it sends, seconds; one still waiting for its turn this long after it
        was accepted, too (:mod:`device_runtime.lobby`).
    """

    flash_dir: Path
    key: bytes | None = None
    insecure: bool = False
    device_id: str = DEFAULT_DEVICE_ID
    ram_budget_bytes: int = DEFAULT_RAM_BUDGET_BYTES
    slot_size_bytes: int | None = None
    rx_window_frames: int = DEFAULT_RX_WINDOW_FRAMES
    rx_buffer_bytes: int | None = None
    max_frame_bytes: int | None = None
    display_width: int = 0
    display_height: int = 0
    flush_interval_s: float = 1.0
    idle_timeout_s: float = 120.0
    auth_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "flash_dir", Path(self.flash_dir))
        if self.key is not None and (not isinstance(self.key, bytes) or len(self.key) != 32):
            raise ValueError("DeviceConfig: key must be 32 bytes")
        if self.key is not None and self.insecure:
            raise ValueError(
                "DeviceConfig: insecure=True cannot be combined with a key (a device with a "
                "key always authenticates)"
            )
        ident = self.device_id.encode("utf-8", "replace")
        if not 1 <= len(ident) <= 64:
            raise ValueError(f"device_id={self.device_id!r} must be 1..64 UTF-8 bytes")
        if not isinstance(self.ram_budget_bytes, int) or self.ram_budget_bytes < 1:
            raise ValueError(f"ram_budget_bytes={self.ram_budget_bytes!r} must be >= 1")
        if not 1 <= self.rx_window_frames <= 0xFFFF:
            raise ValueError(f"rx_window_frames={self.rx_window_frames} must be in 1..65535")
        if self.rx_buffer_bytes is not None and self.rx_buffer_bytes < 1:
            raise ValueError(f"rx_buffer_bytes={self.rx_buffer_bytes} must be >= 1")
        if not 0 < self.auth_timeout_s < float("inf"):
            raise ValueError(f"auth_timeout_s={self.auth_timeout_s} must be > 0 and finite")


@dataclass
class DeviceStats:
    """Counters of a running device (all sessions).

    The ``dropped_*`` counters are SCORES / IMAGE_CHUNK / KEYFRAME_REQUEST frames dropped
    before they were decoded or stored: ``dropped_no_session`` before any HELLO,
    ``dropped_unauthenticated`` on a keyed device outside an authenticated session or
    without an event tag, ``dropped_bad_tag`` with a tag that does not verify,
    ``dropped_replayed`` with a counter not above the last accepted one on its channel.
    ``auth_timeouts`` and ``preempted`` count TCP connections dropped for not
    authenticating in time or replaced by a waiting connection (`device_runtime.lobby`).
    """

    sessions: int = 0
    chunks: int = 0
    chunk_bytes: int = 0
    chunks_stale: int = 0
    chunks_out_of_window: int = 0
    acks: int = 0
    flushes: int = 0
    errors_sent: int = 0
    refused: dict[str, int] = field(default_factory=dict)
    dropped_no_session: int = 0
    dropped_unauthenticated: int = 0
    dropped_bad_tag: int = 0
    dropped_replayed: int = 0
    auth_timeouts: int = 0
    preempted: int = 0
