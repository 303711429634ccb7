"""What ``serve`` did: `ServeStats`, the counters of every session of one run, its
statistics line and its JSON form."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["ServeStats"]


@dataclass
class ServeStats:
    """What :func:`serve` did (all sessions).

    Attributes
    ----------
    frames, key_frames, delta_frames : int
        Score packets sent.
    packet_bytes, key_bytes, delta_bytes : int
        Their sizes (score packets, before framing).
    wire_bytes : int
        Bytes the links wrote (all frames, framing included) and read.
    requests, coalesced, keyframe_requests : int
        VIEW_REQUESTs received, those superseded before they were answered, KEYFRAME_REQUESTs.
    refined_frames : int
        Packets that refined a resting view.
    motion_frames, motion_pixels, motion_seconds : int, int, float
        Frames of moving views made from a sparse ray-cast, rays cast for them and their
        refinements, and the host time it took.
    converged_frames : int
        Refinements that reached the full ray-cast of a resting view.
    correction_frames, correction_bytes : int
        Corrections of the device's own frames sent (not counted as key or delta frames)
        and their bytes.
    unchanged_frames : int
        Views whose correction had nothing worth sending (the device keeps its own frame).
    failed_views : int
        Ray-casts (or codings) of a view that raised: each view was skipped (the device
        kept its own frame, or got interpolated scores) and serving went on.
    oversize_corrections : int
        Corrections larger than the device's frames: not sent (the device kept its own
        frame of that view; at rest the layers, which are chunked, refined it instead).
    layer_frames, layer_bytes : int
        Refinement layers' packets (chunks) sent to resting views, and their bytes.
    exact_views : int
        Resting views whose exact layer was sent whole.
    skipped_corrections : int
        Resting views whose complete correction was not sent because the layers alone
        reach their first quality in fewer bytes.
    stride_frames : dict
        Moving frames per stride (str keys; "0": none fitted the budget).
    look_switches : int
        Times the device switched to another look of an image with several (each served
        in its own look from then on).
    sessions, reconnects : int
    stream_seconds : float
        Time spent streaming (sessions, not connecting).
    device_id : str
    provisioned : bool
        The image was installed first (``provision_missing``).
    """

    frames: int = 0
    key_frames: int = 0
    delta_frames: int = 0
    packet_bytes: int = 0
    key_bytes: int = 0
    delta_bytes: int = 0
    wire_bytes_sent: int = 0
    wire_bytes_received: int = 0
    requests: int = 0
    coalesced: int = 0
    keyframe_requests: int = 0
    sessions: int = 0
    reconnects: int = 0
    stream_seconds: float = 0.0
    device_id: str = ""
    provisioned: bool = False
    last_view: tuple[float, float] | None = None
    refined_frames: int = 0
    motion_frames: int = 0
    motion_pixels: int = 0
    motion_seconds: float = 0.0
    converged_frames: int = 0
    correction_frames: int = 0
    correction_bytes: int = 0
    unchanged_frames: int = 0
    failed_views: int = 0
    oversize_corrections: int = 0
    layer_frames: int = 0
    layer_bytes: int = 0
    exact_views: int = 0
    skipped_corrections: int = 0
    look_switches: int = 0
    stride_frames: dict = field(default_factory=dict)
    views: list = field(default_factory=list, repr=False)

    @property
    def bytes_per_frame(self) -> float:
        """Mean score-packet size, bytes."""
        return self.packet_bytes / self.frames if self.frames else 0.0

    @property
    def fps(self) -> float:
        """Frames sent per second of streaming."""
        return self.frames / self.stream_seconds if self.stream_seconds > 0 else 0.0

    @property
    def link_bytes_per_s(self) -> float:
        """Wire bytes sent per second of streaming."""
        return self.wire_bytes_sent / self.stream_seconds if self.stream_seconds > 0 else 0.0

    def as_dict(self) -> dict[str, Any]:
        """JSON-able summary."""
        out = {k: v for k, v in self.__dict__.items() if k != "views"}
        out["last_view"] = list(self.last_view) if self.last_view else None
        out.update(bytes_per_frame=self.bytes_per_frame, fps=self.fps,
                   link_bytes_per_s=self.link_bytes_per_s,
                   mean_key_bytes=self.key_bytes / self.key_frames if self.key_frames else 0.0,
                   mean_delta_bytes=(self.delta_bytes / self.delta_frames
                                     if self.delta_frames else 0.0))
        return out

    def line(self) -> str:
        """One human line: frames by kind (with their mean bytes), bytes per frame, fps,
        link rate."""
        kinds = []
        if self.key_frames:
            kinds.append(f"{self.key_frames} key ({self.key_bytes / self.key_frames:.0f} B)")
        if self.delta_frames:
            kinds.append(f"{self.delta_frames} delta "
                         f"({self.delta_bytes / self.delta_frames:.0f} B)")
        if self.correction_frames:
            kinds.append(f"{self.correction_frames} corrections of the device's own frames "
                         f"({self.correction_bytes / self.correction_frames:.0f} B)")
        elif self.motion_frames:
            kinds.append(f"{self.motion_frames} sparse")
        if self.refined_frames:
            kinds.append(f"{self.refined_frames} refined")
        if self.unchanged_frames:
            kinds.append(f"{self.unchanged_frames} views left as the device made them")
        if self.failed_views:
            kinds.append(f"{self.failed_views} views whose ray-cast failed")
        if self.oversize_corrections:
            kinds.append(f"{self.oversize_corrections} corrections too large for the "
                         "device's frames")
        if self.layer_frames:
            kinds.append(f"{self.layer_frames} layer packets ({self.exact_views} views exact)")
        return (f"{self.frames} frames ({', '.join(kinds) or 'none'}), "
                f"{self.bytes_per_frame:.0f} B/frame, {self.fps:.1f} fps, "
                f"link {self.link_bytes_per_s / 1024:.1f} KiB/s")
