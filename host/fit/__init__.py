"""Stage 3, fit: a Cinema database in, an eigenspace image (MODEL.ecs) out.

Owns the cell layout and the streamed cell-major training store (``cells.py``: `CellStack`),
per-cell PCA (``pca.py``: `CellEigenspace`), quantization of the
eigenspace to a bit budget (``quantize.py``), view interpolation of scores
(``interpolate.py``: `ScoreInterpolator`, the host twin of
``device_runtime/interpolation.py``) and the host model: fitting a database, building and
saving the ``.ecs`` image with its annex, loading it back as a `HostModel` that reconstructs
exactly what a device shows (``model.py``), the noise floor of the colour eigenspace, at or
below which the device's warp shows black (``floor.py``: `add_noise_floor`), and the recovery
of a view's scores from a sparse ray-cast with a prior (``recover.py``: `SparseRecovery`,
`ProgressiveRecovery`) and the frames that fit a deadline while the view moves
(``motion.py``: `MotionScores`, used by ``serve`` and evaluate's ``pca_motion``).

May import: `host.render` (the database and its settings), `host.errors`, `host.progress`,
`protocol` (the image format) and `device_runtime` (the device's own reconstruction and
interpolation, so host and device agree bit for bit); never evaluate or link.
``eigencast fit`` starts here (``host/commands/fit.py``); its ``--target`` search is in
`host.evaluate.target`.
"""

from host.lazy import attach

__all__ = [
    "ANNEX_EIGENVALUES",
    "ANNEX_SCORES",
    "ANNEX_TOTAL_VARIANCE",
    "BUDGET_SHARE",
    "DEFAULT_BIT_BUDGET",
    "DEFAULT_COARSE",
    "DEFAULT_LAMBDA",
    "DEFAULT_MOTION_FPS",
    "DEFAULT_SCORE_MSE",
    "DEFAULT_STRIDES",
    "GRID_DEFAULT",
    "INT8_CHECK_VIEWS",
    "MAX_BITS",
    "METHODS",
    "MIN_BITS",
    "PRIOR_SWITCH_DEG",
    "PROBE_EVERY",
    "SIGN_CONVENTION",
    "CellEigenspace",
    "CellStack",
    "HostModel",
    "InvalidParameterError",
    "MotionFrame",
    "MotionScores",
    "NoiseFloor",
    "NotFittedError",
    "ProgressiveRecovery",
    "QuantizationLoss",
    "QuantizedEigenspace",
    "SamplePattern",
    "ScoreInterpolator",
    "SparseRecovery",
    "add_noise_floor",
    "add_standalone_table",
    "allocate_bits",
    "angle_between",
    "auto_score_step",
    "build_image",
    "cell_grid",
    "components_for_threshold",
    "fit_database",
    "int8_loss_db",
    "int8_report",
    "measure_noise_floor",
    "merge_cells",
    "offset_order",
    "quantize_components",
    "quantize_eigenspace",
    "quantize_mean",
    "read_model_image",
    "residual_mse",
    "save_model",
    "score_step_for",
    "sparse_samples",
    "split_cells",
    "stack_cache",
    "stack_for",
    "standalone_scores",
    "subset_database",
    "triangulate_views",
    "truncate_eigenspace",
]

__getattr__, __dir__ = attach(__name__, __all__)
