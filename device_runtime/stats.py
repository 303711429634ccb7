"""What the device runtime counts and times: `RuntimeStats` (bounded: counters, moving
averages and rings of recent timings, read at any time by ``--stats`` and the overlay) and
the process's resident memory (`peak_rss_bytes`, `current_rss_bytes`). Split out of
`device_runtime.runtime`, whose names these still are."""

from __future__ import annotations

import collections
import contextlib
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["RuntimeStats", "current_rss_bytes", "peak_rss_bytes"]

_LATENCY_SAMPLES = 512
_RATE_WINDOW_S = 1.0


def peak_rss_bytes() -> int:
    """Peak resident set size of this process, bytes (0 where unknown).

    Linux's ``VmHWM`` where there is one: ``getrusage``'s ``ru_maxrss`` survives ``exec``, so
    in a process started from a large parent (the demo's host) it reports the parent's size.
    """
    with contextlib.suppress(OSError, ValueError, IndexError), open("/proc/self/status",
                                                                     "rb") as handle:
        for line in handle:
            if line.startswith(b"VmHWM:"):
                return int(line.split()[1]) * 1024
    try:
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024
    except (ImportError, OSError):
        return 0


def current_rss_bytes() -> int:
    """Resident set size of this process now, bytes (0 where unknown)."""
    try:
        with open("/proc/self/statm", "rb") as handle:
            return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


class _Ema:
    __slots__ = ("alpha", "value")

    def __init__(self, alpha: float = 0.1) -> None:
        self.alpha = alpha
        self.value: float | None = None

    def add(self, x: float) -> None:
        self.value = x if self.value is None else self.value + self.alpha * (x - self.value)


@dataclass
class RuntimeStats:
    """Counters and recent timings of the runtime (bounded; read them any time)."""

    frames_presented: int = 0
    packets: int = 0
    packet_bytes: int = 0
    key_frames: int = 0
    delta_frames: int = 0
    missing_base: int = 0
    keyframe_requests: int = 0
    decode_errors: int = 0
    wrong_image: int = 0
    dropped_no_image: int = 0
    view_requests: int = 0
    coalesced: int = 0
    sessions: int = 0
    frame_failures: int = 0
    correction_packets: int = 0
    predicted_frames: int = 0
    corrected_frames: int = 0
    stale_dropped: int = 0
    corrections_without_table: int = 0
    synthesized_frames: int = 0
    layer_packets: int = 0
    layers_applied: int = 0
    layers_dropped: int = 0
    layers_bad: int = 0
    exact_frames: int = 0
    kept_exact: int = 0
    layer_retries: int = 0
    look_switches: int = 0
    other_look: int = 0
    decode_s: _Ema = field(default_factory=_Ema)
    correct_s: _Ema = field(default_factory=_Ema)
    layer_s: _Ema = field(default_factory=_Ema)
    reconstruct_s: _Ema = field(default_factory=_Ema)
    present_s: _Ema = field(default_factory=_Ema)
    latencies_s: collections.deque = field(
        default_factory=lambda: collections.deque(maxlen=_LATENCY_SAMPLES))
    stage_samples: collections.deque = field(
        default_factory=lambda: collections.deque(maxlen=_LATENCY_SAMPLES))
    _present_times: collections.deque = field(default_factory=lambda: collections.deque(
        maxlen=256))
    _bytes_ring: collections.deque = field(default_factory=lambda: collections.deque(maxlen=64))

    def fps(self, now_s: float | None = None) -> float:
        """Frames presented per second over the last second."""
        now_s = time.monotonic() if now_s is None else now_s
        recent = [t for t in self._present_times if now_s - t <= _RATE_WINDOW_S]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)

    def bytes_per_frame(self) -> float:
        """Mean score-packet size over the last 64 packets, bytes."""
        return float(np.mean(self._bytes_ring)) if self._bytes_ring else 0.0

    def as_dict(self) -> dict[str, Any]:
        """JSON-able summary (latency percentiles in milliseconds)."""
        lat = sorted(self.latencies_s)

        def pct(p: float) -> float | None:
            return None if not lat else 1e3 * lat[min(len(lat) - 1, int(p * len(lat)))]

        def ms(e: _Ema) -> float | None:
            return None if e.value is None else 1e3 * e.value

        return {
            "frames_presented": self.frames_presented,
            "packets": self.packets,
            "packet_bytes": self.packet_bytes,
            "key_frames": self.key_frames,
            "delta_frames": self.delta_frames,
            "missing_base": self.missing_base,
            "keyframe_requests": self.keyframe_requests,
            "decode_errors": self.decode_errors,
            "wrong_image": self.wrong_image,
            "view_requests": self.view_requests,
            "coalesced": self.coalesced,  # frames decoded but never presented
            "frame_failures": self.frame_failures,  # frames the display could not show
            "sessions": self.sessions,
            "correction_packets": self.correction_packets,  # decoded corrections
            "predicted_frames": self.predicted_frames,  # own predictions shown (issue 14)
            "corrected_frames": self.corrected_frames,  # prediction + correction shown
            "stale_dropped": self.stale_dropped,  # packets for a view no longer on show
            "corrections_without_table": self.corrections_without_table,
            "synthesized_frames": self.synthesized_frames,  # warped by depth
            "layer_packets": self.layer_packets,  # refinement layers received
            "layers_applied": self.layers_applied,
            "layers_dropped": self.layers_dropped,  # for a frame no longer on show
            "layers_bad": self.layers_bad,  # malformed, or not decodable to their strip
            "exact_frames": self.exact_frames,  # resting views shown exactly
            "kept_exact": self.kept_exact,  # host frames of an exact view not shown
            "layer_retries": self.layer_retries,  # views asked again after a lost layer
            "look_switches": self.look_switches,  # another look shown (key l)
            "other_look": self.other_look,  # packets made for a look no longer on show
            "fps": self.fps(),
            "bytes_per_frame": self.bytes_per_frame(),
            "decode_ms": ms(self.decode_s),
            "correct_ms": ms(self.correct_s),  # a correction added to the own frame
            "layer_ms": ms(self.layer_s),  # a layer decoded and applied
            "reconstruct_ms": ms(self.reconstruct_s),
            "present_ms": ms(self.present_s),
            "latency_ms_p50": pct(0.5),
            "latency_ms_p90": pct(0.9),
            "latency_ms_p99": pct(0.99),
            "latency_ms_max": 1e3 * lat[-1] if lat else None,
            "latency_ms_mean": 1e3 * float(np.mean(lat)) if lat else None,
            "latency_samples": len(lat),
            "rss_bytes": current_rss_bytes(),
            "peak_rss_bytes": peak_rss_bytes(),
        }
