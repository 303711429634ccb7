"""Several looks, one spatial basis: how much of each look the first look's eigenimages span.

Per cell, each look's training views (centred on its own mean) are projected on the first
look's components (``fit`` defaults: adaptive, T = 0.98); printed per look: the share of its
variance they capture, and how many components of the residual's own PCA it would need on
top to reach T of its variance (an image whose extra looks shared the first look's
eigenimages and stored only scores and those extra components). Backs docs/design-notes.md,
"Several looks in one image".

    OPENBLAS_NUM_THREADS=1 .venv/bin/python research/looks_shared_basis.py FIRST.cdb OTHER.cdb ...
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.fit.model import fit_database, stack_for
from host.render.cinema import CinemaDB

THRESHOLD = 0.98


def main(paths: list[str]) -> None:
    dbs = [CinemaDB.open(p) for p in paths]
    first = fit_database(dbs[0], threshold=THRESHOLD, progress=False)
    cell = tuple(int(v) for v in first.cell_shape_)
    print(f"first look {dbs[0].path.name}: K = {int(first.n_components_.sum())}")
    for db in dbs[1:]:
        stack = stack_for(db, cell, progress=False)
        total = captured = 0.0
        extra = 0
        for c in range(stack.n_cells):
            x = stack.read_cells(c, c + 1)[0].astype(np.float64)
            x -= x.mean(axis=0)
            basis = np.asarray(first.components_[c], dtype=np.float64)
            scores = x @ basis.T
            trace, kept = float((x * x).sum()), float((scores * scores).sum())
            total, captured = total + trace, captured + kept
            missing = THRESHOLD * trace - kept
            if missing > 0:
                s2 = np.linalg.svd(x - scores @ basis, compute_uv=False) ** 2
                extra += int(np.searchsorted(np.cumsum(s2), missing)) + 1
        own = fit_database(db, threshold=THRESHOLD, progress=False)
        print(f"{db.path.name}: the first look's basis captures {captured / total:.4f}; "
              f"{extra} more components reach T (its own eigenspace: K = "
              f"{int(own.n_components_.sum())})")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    main(sys.argv[1:])
