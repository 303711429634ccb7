"""Score-packet rate-distortion experiments (issue 6 item 3; docs/rate-distortion-packets.md).

    .venv/bin/python research/rdp_packets.py MODEL.ecs TEST.cdb -o OUT.json
        [--views 100] [--factors 1,2,4,8,16,32] [--codec-views 40] [--flip]

For the held-out views of TEST.cdb (object pixels, `research/rdp_common.py`) and a sweep of
score steps (multiples of the model's own step, which `fit` chose from the 0.25 MSE rule):

* **quantizers**: ``uniform`` (``rint(y / s)``, what eigencast sent so far) and ``waterfill``
  (reverse water-filling: the same uniform step ``s``, i.e. distortion ``theta = s**2 / 12`` per
  component, but components whose eigenvalue is below ``theta`` are sent as 0, their
  distortion is their variance);
* **layouts** of the same integers: cell-major / component-major (all cells' first components,
  then their second ...), zigzag varints / int16 / byte-planar int16, each zstd level 3, with
  and without a zstd dictionary trained on the training views' payloads at that step (its size
  reported: it would ship once, in the eigenspace image); plus the ideal static entropy
  (empirical per-rank symbol statistics of the training views: a bound for any arithmetic
  coder keyed by component rank);
* **packets**: the real `protocol.scores.encode_scores` packet (its defaults: zstd 19, the
  smaller of varint and end-of-block coding) and the version-1 packet (zstd 3, varints);
* **orbits**: ``steps:120:THETA`` orbits (3 degree steps, off the 3.6 x 12 degree training
  grid) coded key-only and as deltas against the previous frame (real packets), and with the
  old coding as deltas and as deltas against the linear prediction ``2 q[t-1] - q[t-2]``;
* **codecs at equal quality**: per view, the smallest WebP and JPEG file of the ray-cast whose
  object SSIM (and FLIP with ``--flip``) is at least the eigencast frame's.

Produces: docs/rate-distortion-packets.md, section 1 "Score packets".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
import zstandard as zstd

sys.path.insert(0, str(Path(__file__).resolve().parent))

from rdp_common import Timer, case_parser, load_case, quality, save_json, smallest_codec_file

from protocol.scores import HEADER_SIZE, EncodedScores, encode_scores, zigzag_varints

LEVEL = 3


def ranks_of(counts: np.ndarray) -> np.ndarray:
    """Rank of each coefficient within its cell (0 = largest eigenvalue)."""
    offsets = np.concatenate([[0], np.cumsum(counts)])[:-1]
    return np.arange(int(counts.sum())) - np.repeat(offsets, counts)


def component_major(counts: np.ndarray) -> np.ndarray:
    """Permutation putting every cell's rank-0 coefficient first, then rank 1, ..."""
    r = ranks_of(counts)
    return np.lexsort((np.arange(r.size), r))


def quantize(y: np.ndarray, step: float, zero: np.ndarray | None) -> np.ndarray:
    q = np.rint(y / step).astype(np.int64)
    if zero is not None:
        q[zero] = 0
    return q


def packet(q: np.ndarray, step: float, counts: np.ndarray, *, frame: int = 1,
           base: EncodedScores | None = None) -> EncodedScores:
    """The real packet (`protocol.scores.encode_scores` defaults: level, coding choice)."""
    return encode_scores(q * step, step=step, frame=frame, view=(0.0, 0.0),
                         image_digest=bytes(4), n_components=counts, base=base)


def payloads(q: np.ndarray, perm: np.ndarray) -> dict[str, bytes]:
    """The raw (uncompressed) payload of each layout."""
    cm = q[perm]
    c16 = np.clip(q, -32768, 32767).astype("<i2")
    return {
        "cell_varint": zigzag_varints(q),
        "comp_varint": zigzag_varints(cm),
        "cell_int16": c16.tobytes(),
        "cell_planar16": c16.view(np.uint8).reshape(-1, 2).T.tobytes(),
        "comp_planar16": np.clip(cm, -32768, 32767).astype("<i2").view(np.uint8)
        .reshape(-1, 2).T.tobytes(),
    }


class Sizer:
    """zstd sizes of payloads, plain and with a trained dictionary per layout."""

    def __init__(self, train: list[dict[str, bytes]], dict_bytes: int) -> None:
        self.plain = zstd.ZstdCompressor(level=LEVEL, write_content_size=True)
        self.dicts: dict[str, zstd.ZstdCompressor] = {}
        self.dict_sizes: dict[str, int] = {}
        for name in ("cell_varint", "comp_varint"):
            samples = [p[name] for p in train]
            try:
                d = zstd.train_dictionary(dict_bytes, samples, level=LEVEL)
            except zstd.ZstdError:
                continue
            self.dicts[name] = zstd.ZstdCompressor(level=LEVEL, dict_data=d,
                                                   write_content_size=True)
            self.dict_sizes[name] = len(d.as_bytes())

    def sizes(self, p: dict[str, bytes]) -> dict[str, int]:
        out = {k: HEADER_SIZE + min(len(v), len(self.plain.compress(v))) for k, v in p.items()}
        for k, c in self.dicts.items():
            out[f"{k}_dict"] = HEADER_SIZE + min(len(p[k]), len(c.compress(p[k])))
        return out


def entropy_bits(train_q: np.ndarray, test_q: np.ndarray, ranks: np.ndarray) -> float:
    """Mean ideal code length (bits per view) of ``test_q`` under per-rank symbol statistics
    of ``train_q`` (ranks over 24 pooled; unseen symbols cost an escape of 20 bits)."""
    bucket = np.minimum(ranks, 24)
    total = 0.0
    for b in np.unique(bucket):
        cols = bucket == b
        tr = train_q[:, cols].ravel()
        te = test_q[:, cols].ravel()
        vals, cnt = np.unique(tr, return_counts=True)
        p = dict(zip(vals.tolist(), (cnt + 0.5) / (cnt.sum() + 0.5 * len(cnt) + 1)))
        bits = np.array([-np.log2(p[v]) if v in p else 20.0 for v in te.tolist()])
        total += bits.sum()
    return total / test_q.shape[0]


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = case_parser(__doc__.splitlines()[0], views=100)
    ap.add_argument("--factors", default="1,2,4,8,16,32")
    ap.add_argument("--codec-views", type=int, default=40,
                    help="views of the equal-quality WebP/JPEG search (slow)")
    ap.add_argument("--codec-factors", default=None,
                    help="step factors to run the codec search at (default: all)")
    ap.add_argument("--flip", action="store_true", help="match FLIP too (slow)")
    ap.add_argument("--orbit-thetas", default="15,42")
    ap.add_argument("--dict-bytes", type=int, default=4096)
    return ap.parse_args(argv)


def _orbit_sizes(q: np.ndarray, step: float, counts: np.ndarray) -> dict:
    """Bytes per frame of one orbit's quantized scores ``q``: real key and delta packets,
    and the old coding as deltas and as deltas against the linear prediction."""
    comp = zstd.ZstdCompressor(level=LEVEL, write_content_size=True)

    def size(v: np.ndarray, c: zstd.ZstdCompressor = comp) -> int:
        p = zigzag_varints(v)
        return HEADER_SIZE + min(len(p), len(c.compress(p)))

    pred = [size(q[0]), size(q[1] - q[0])] + [
        size(q[i] - 2 * q[i - 1] + q[i - 2]) for i in range(2, len(q))]
    delta3 = [size(q[0])] + [size(q[i] - q[i - 1]) for i in range(1, len(q))]
    key, delta, prev = [], [], None
    for i, v in enumerate(q):
        k = packet(v, step, counts, frame=i + 1)
        key.append(len(k.packet))
        d = k if prev is None else packet(v, step, counts, frame=i + 1, base=prev)
        delta.append(len(d.packet))
        prev = d
    return {"key": float(np.mean(key)), "delta": float(np.mean(delta)),
            "delta_v1_level3": float(np.mean(delta3)),
            "pred2_v1_level3": float(np.mean(pred))}


def _kind_entry(case: Any, step: float, z: np.ndarray | None, train_q: np.ndarray,
                y_test: np.ndarray, orbit_y: dict, ctx: dict) -> dict:
    """One quantizer at one step: quality, packet and layout sizes, entropy, orbits."""
    model, perm, counts = case.model, ctx["perm"], ctx["counts"]
    sizer = Sizer([payloads(q, perm) for q in train_q], ctx["dict_bytes"])
    qs = np.stack([quantize(y, step, z) for y in y_test])
    qual = [quality(case.truth[i], model.reconstruct((qs[i] * step).astype(np.float32)),
                    case.masks[i]) for i in range(case.n_views)]
    sizes = [sizer.sizes(payloads(q, perm)) for q in qs]
    packet_v1 = [len(encode_scores(q * step, step=step, frame=1, view=(0.0, 0.0),
                                   image_digest=bytes(4), level=3,
                                   coding=0).packet) for q in qs]
    pk = [len(packet(q, step, counts).packet) for q in qs]
    entry = {
        "quality": {k: float(np.mean([v[k] for v in qual])) for k in qual[0]},
        "per_view_ssim": [v["ssim"] for v in qual],
        "packet_bytes": float(np.mean(pk)),
        "packet_bytes_v1_level3": float(np.mean(packet_v1)),
        "layout_bytes": {k: float(np.mean([s[k] for s in sizes])) for k in sizes[0]},
        "dict_sizes": sizer.dict_sizes,
        "entropy_bytes": HEADER_SIZE + entropy_bits(train_q, qs, ctx["ranks"]) / 8,
        "nonzero_per_view": float(np.mean(np.count_nonzero(qs, axis=1))),
    }
    entry["orbits"] = {str(th): _orbit_sizes(np.stack([quantize(y, step, z) for y in ys]),
                                             step, counts)
                       for th, ys in orbit_y.items()}
    return entry


def _codecs(case: Any, args: argparse.Namespace, row: dict, y_test: np.ndarray, step: float,
            zero: np.ndarray) -> dict:
    """The smallest WebP and JPEG files of equal object SSIM (and FLIP with --flip)."""
    model = case.model
    ref = row["waterfill"]["per_view_ssim"]
    n = min(args.codec_views, case.n_views)
    flips: list = [None] * n
    if args.flip:
        flips = [quality(case.truth[i], model.reconstruct(
            (quantize(y_test[i], step, zero) * step).astype(np.float32)),
            case.masks[i], flip=True)["flip"] for i in range(n)]
    codecs = {}
    for codec in ("webp", "jpeg"):
        got = [smallest_codec_file(case.truth[i], case.masks[i], codec, ssim=ref[i],
                                   flip=flips[i]) for i in range(n)]
        codecs[codec] = {"bytes": float(np.mean([g[0] for g in got])),
                         "quality": float(np.mean([g[1] for g in got])),
                         "ssim": float(np.mean([g[2]["ssim"] for g in got]))}
    codecs["views"] = n
    if args.flip:
        codecs["pca_flip_same_views"] = float(np.mean(flips))
    codecs["pca_ssim_same_views"] = float(np.mean(ref[:n]))
    codecs["pca_bytes_same_views"] = float(
        np.mean([row["waterfill"]["packet_bytes"]]))
    return codecs


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    t = Timer()
    case = load_case(args.model, args.test_db, views=args.views)
    model = case.model
    img = model.image
    counts = np.asarray(img.n_components, np.int64)
    lam = np.asarray(model.eigenvalues, np.float64)
    ctx = {"counts": counts, "ranks": ranks_of(counts), "perm": component_major(counts),
           "dict_bytes": args.dict_bytes}
    base_step = model.score_step
    t.say(f"{case.name}: {case.n_views} views, K={img.n_coefficients}, cells={img.n_cells}, "
          f"step={base_step:.4g}")
    y_test = np.stack([model.scores(p, th) for p, th in zip(case.phi, case.theta)])
    float_q = [quality(case.truth[i], model.reconstruct(y_test[i]), case.masks[i])
               for i in range(case.n_views)]
    result: dict = {
        "case": case.name, "views": case.n_views, "K": img.n_coefficients,
        "n_cells": img.n_cells, "model_step": base_step,
        "image_shape": list(img.image_shape),
        "float": {k: float(np.mean([f[k] for f in float_q])) for k in float_q[0]},
        "steps": [],
    }
    t.say(f"float scores: {result['float']}")
    train_idx = np.arange(0, model.training_scores.shape[0], 3)
    orbit_thetas = [float(v) for v in args.orbit_thetas.split(",") if v]
    orbit_y = {th: np.stack([model.scores(360.0 * i / 120, th) for i in range(120)])
               for th in orbit_thetas}
    codec_factors = (None if args.codec_factors is None
                     else {float(v) for v in args.codec_factors.split(",")})
    for factor in [float(v) for v in args.factors.split(",")]:
        step = base_step * factor
        theta_w = step * step / 12.0
        zero = lam < theta_w
        row: dict = {"factor": factor, "step": step, "zeroed_fraction": float(zero.mean())}
        for kind, z in (("uniform", None), ("waterfill", zero)):
            train_q = np.stack([quantize(model.training_scores[i], step, z) for i in train_idx])
            entry = _kind_entry(case, step, z, train_q, y_test, orbit_y, ctx)
            row[kind] = entry
            t.say(f"x{factor:g} {kind}: ssim {entry['quality']['ssim']:.4f} psnr "
                  f"{entry['quality']['psnr']:.2f} packet {entry['packet_bytes']:.0f} "
                  f"layouts {({k: round(v) for k, v in entry['layout_bytes'].items()})} "
                  f"entropy {entry['entropy_bytes']:.0f} orbits {entry['orbits']}")
        if codec_factors is None or factor in codec_factors:
            row["codecs"] = _codecs(case, args, row, y_test, step, zero)
            t.say(f"x{factor:g} equal-SSIM codecs: {row['codecs']}")
        result["steps"].append(row)
        save_json(args.output, result)
    t.say(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
