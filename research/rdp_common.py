"""Shared helpers of the ``research/rdp_*.py`` rate-distortion experiments (issue 6, part B).

A *case* is a fitted model (``.ecs`` with its annex) plus a database of held-out views
rendered with the same settings (``/work/cache/rd/NAME-SIZE-test.cdb``). Quality is measured
on the object's pixels only: the ray-casts have a black background, so a pixel is an object
pixel when any channel exceeds ``host.evaluate.OBJECT_LEVEL`` (`host.evaluate.object_mask`;
``host.evaluate`` metric helpers, ``mask=``).

Produces no doc section itself: helpers of the rdp_*.py scripts.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from host.evaluate import compare_images, encode_image, object_mask, webp_database_frames
from host.fit.model import HostModel
from host.render.cinema import CinemaDB


@dataclass
class Case:
    """One model and its held-out views (images, masks, angles)."""

    name: str
    model: HostModel
    phi: np.ndarray
    theta: np.ndarray
    truth: list[np.ndarray]
    masks: list[np.ndarray]

    @property
    def n_views(self) -> int:
        return len(self.truth)


def case_parser(description: str, *, views: int) -> argparse.ArgumentParser:
    """The arguments every rdp_*.py script takes: a model, its held-out views' database, the
    JSON output and how many of those views to measure (default ``views``)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("model")
    ap.add_argument("test_db")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--views", type=int, default=views)
    return ap


def load_case(model_path: str | Path, test_db: str | Path, *, views: int | None = None,
              name: str | None = None) -> Case:
    """Load a model and up to ``views`` held-out views."""
    model = HostModel.load(model_path)
    db = CinemaDB.open(test_db)
    n = db.n_views if views is None else min(views, db.n_views)
    truth = [db.read_image(i) for i in range(n)]
    return Case(name or Path(model_path).stem, model, np.asarray(db.phi_deg[:n], float),
                np.asarray(db.theta_deg[:n], float), truth, [object_mask(t) for t in truth])


def quality(truth: np.ndarray, test: np.ndarray, mask: np.ndarray, *,
            flip: bool = False) -> dict[str, float]:
    """Object-pixel PSNR, SSIM (and FLIP) of ``test`` against ``truth``."""
    metrics = ("psnr", "ssim", "flip") if flip else ("psnr", "ssim")
    c = compare_images(truth, test, mask=mask, metrics=metrics)
    out = {"psnr": c.psnr_object, "ssim": c.ssim_object}
    if flip:
        out["flip"] = c.flip_object
    return out


def smallest_codec_file(truth: np.ndarray, mask: np.ndarray, codec: str, *, ssim: float,
                        flip: float | None = None) -> tuple[int, int, dict[str, float]]:
    """The smallest ``codec`` file of ``truth`` whose object SSIM >= ``ssim`` (and FLIP <=
    ``flip``): bisection over quality 1..100 (quality is monotone enough for this).

    Returns
    -------
    (bytes, quality, metrics)
        Quality 100's file when none reaches the target.
    """
    cache: dict[int, tuple[int, dict[str, float]]] = {}

    def at(q: int) -> tuple[int, dict[str, float]]:
        if q not in cache:
            coded = encode_image(truth, codec, q)
            cache[q] = (coded.size_bytes,
                        quality(truth, coded.decode(), mask, flip=flip is not None))
        return cache[q]

    def ok(q: int) -> bool:
        m = at(q)[1]
        return m["ssim"] >= ssim and (flip is None or m["flip"] <= flip)

    lo, hi = 0, 100  # invariant: hi meets the target (or is 100), lo does not (or is 0)
    if not ok(100):
        return at(100)[0], 100, at(100)[1]
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ok(mid):
            hi = mid
        else:
            lo = mid
    size, metrics = at(hi)
    return size, hi, metrics


def save_json(path: str | Path, data: Any) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=1, default=float) + "\n")


class Timer:
    """Prints elapsed seconds with a label (progress of long experiment runs)."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    def say(self, what: str) -> None:
        print(f"[{time.perf_counter() - self.t0:7.1f}s] {what}", flush=True)


def webp_db_sweep(train_db: str, case: Case, weights: list, qualities: list[int],
                  t: Timer) -> list[dict]:
    """The WebP image-database baseline at each quality: its bytes and object quality.

    `host.evaluate.webp_database_frames` over the training database ``train_db``, measured
    against the case's held-out views (`quality`).
    """
    db = CinemaDB.open(train_db)
    out = []
    for qv in qualities:
        total, frames = webp_database_frames(db, weights, qv)
        qual = [quality(case.truth[k], frame, case.masks[k]) for k, frame in enumerate(frames)]
        row = {"quality": qv, "bytes": total,
               "metrics": {m: float(np.mean([q[m] for q in qual])) for m in qual[0]}}
        out.append(row)
        t.say(f"webp db q{qv}: {row}")
    return out
