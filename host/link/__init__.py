"""Stage 5, link: put a model on a device and stream score packets to it.

Owns provisioning (``provisioning.py``: handshake, chunked image transfer with retransmission
and resume, commit) and serving (``serving.py``: the session that answers view requests with
score packets: corrections of the device's own frames, ``correction.py``, or absolute
scores, ``encoding.py``, from the sparse ray-casts of `host.fit.MotionScores` that fit a
deadline; ``true_views.py``: the scores of ray-cast views; ``serve_stats.py``: `ServeStats`;
``errors.py``: `ServeError`; ``options.py``: what the user chooses for each, `ServeOptions`
and `ProvisionOptions`, validated from one table of constraints, and what a caller hands in,
`ServeParts` and `ProvisionParts`), and what a resting view gets once its ray-cast is whole
(``resting.py``: its complete correction and the refinement layers that end at the exact
ray-cast, planned by ``layers.py``: `RestPlanner`).
Both drive the shared protocol (`protocol.link`, `protocol.transport`, `protocol.scores`)
from the host end.

Named ``link`` rather than ``serve``: it holds provisioning too and it is the host end of
`protocol.link`. Its modules are ``provisioning.py``/``serving.py``, not ``provision.py``/
``serve.py``: a submodule named like the function the package exports would replace that
function on the package as soon as it is imported (``host.link.serve`` would be the module).

May import: `host.fit` (the `HostModel` whose packets it sends), `host.render` (ray-cast
views), `host.errors`, `protocol`, `device_runtime`; never
evaluate. ``eigencast provision`` and ``serve`` start here (``host/commands/provision.py``,
``serve.py``).
"""

from host.lazy import attach

__all__ = [
    "CHUNK_LATENCY_S",
    "DEFAULT_DEADLINE_S",
    "DEFAULT_TARGETS",
    "SCORE_MODES",
    "FrameEncoder",
    "ImageInfo",
    "OptionError",
    "ProvisionError",
    "ProvisionOptions",
    "ProvisionParts",
    "ProvisionResult",
    "RestPlanner",
    "ServeError",
    "ServeOptions",
    "ServeParts",
    "ServeStats",
    "TrueViewScores",
    "choose_chunk_bytes",
    "inspect_image",
    "open_true_view_scores",
    "provision",
    "serve",
]

__getattr__, __dir__ = attach(__name__, __all__)
