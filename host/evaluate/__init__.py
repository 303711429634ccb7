"""Stage 4, evaluate: how good are the frames a device shows, at what cost on the link?

Owns the image metrics (``metrics.py``: PSNR, SSIM, FLIP, over the object's pixels),
object masks (``masks.py``), the baselines the eigenspace is compared with (``baselines.py``:
equal-bytes JPEG/WebP, nearest training view, the on-device WebP image database), the
device path (``device_path.py``: scores -> real score packet -> device reconstruction; the
one served path's frames, the device's own frame and its corrections, and given ``serve``'s
planner the resting views' layers), the resting steps measured against the codecs
(``resting.py``), the evaluation engine with its rate-distortion sweep (``engine.py``), the
HTML report
(``report.py``) and the quality-target search of ``eigencast fit --target``
(``target.py``: it picks the cheapest model whose frames, measured through the device path,
reach a target, so it needs this stage and lives here rather than in `host.fit`), and, for
the same reason, ``fit --depth``'s choice of the warp's splat filter (``splat_filter.py``).

May import: `host.volume`, `host.render`, `host.fit`, `host.errors`, `host.progress`,
`protocol`, `device_runtime`; never link. ``eigencast evaluate`` starts here
(``host/commands/evaluate.py``).
"""

from host.lazy import attach

__all__ = [
    "CODECS",
    "DEFAULT_QUALITIES",
    "DEFAULT_STEP_FACTORS",
    "DEFAULT_THRESHOLDS",
    "DEFAULT_WEBP_DB_QUALITY",
    "HIGHER_IS_BETTER",
    "MAX_QUALITY",
    "METHODS",
    "METRICS",
    "OBJECT_LEVEL",
    "TARGET_METRICS",
    "TARGET_STEP_FACTORS",
    "TENT_MARGIN",
    "TENT_TIE",
    "TENT_VIEWS",
    "CodecLadder",
    "CodedImage",
    "DevicePath",
    "Evaluation",
    "HeldOutViews",
    "ImageComparison",
    "RestStep",
    "RestSteps",
    "ServedFrames",
    "SlowRenderer",
    "Target",
    "TargetError",
    "TargetResult",
    "TrainingImages",
    "Try",
    "WebPDatabase",
    "alpha_object_mask",
    "blockiness",
    "choose_splat_tent",
    "codec_equivalent",
    "compare_images",
    "compose_side_by_side",
    "decode_image",
    "default_metric_workers",
    "eigenspace_bytes",
    "encode_image",
    "encode_within_budget",
    "evaluate_model",
    "flip_error",
    "flip_error_map",
    "holdout_indices",
    "json_safe",
    "level_ladder",
    "model_info",
    "nearest_training_view",
    "object_mask",
    "parse_target",
    "peak_signal_noise_ratio",
    "pick_splat_tent",
    "search_target",
    "structural_similarity",
    "webp_database_frames",
    "write_report",
]

__getattr__, __dir__ = attach(__name__, __all__)
