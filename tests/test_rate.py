"""Rate-distortion optimal score quantization (`host.fit.rate`, issue 14).

The packet still carries integers times one scalar step, so the device is unchanged: these
tests check that the chosen values are on the step grid, decode exactly from a real packet,
cost fewer bytes as lambda grows, give empty (mean-only) cells nothing, follow the per-cell
weights, and pass through ``FrameEncoder`` unchanged (how ``serve`` would send them).
"""

from __future__ import annotations

import numpy as np
import pytest

from host.fit.rate import eg_bits, rd_delta, rd_lambda, rd_quantize, ssim_cell_weights
from host.link.serving import FrameEncoder
from protocol.scores import ScoreDecoder, encode_scores


def _scores(model, seed: int = 0) -> np.ndarray:
    """Float scores of a real frame: the projection of a training view plus some noise."""
    rng = np.random.default_rng(seed)
    y = model.training_scores[3].astype(np.float64)
    return y + rng.normal(0, 0.3 * model.score_step, y.shape)


def _packet_bytes(model, y: np.ndarray, step: float) -> int:
    return len(encode_scores(y, step=step, frame=1, view=(0.0, 0.0), image_digest=model.digest,
                             n_components=model.image.n_components).packet)


def test_exp_golomb_bits_of_zigzag_values():
    assert eg_bits(np.array([0, -1, 1, -2, 2, 3])).tolist() == [1, 3, 3, 5, 5, 5]


def test_lambda_zero_is_plain_rounding(model):
    y = _scores(model)
    np.testing.assert_array_equal(rd_quantize(model, y, lam=0.0), model.quantize(y))


def test_values_are_on_the_step_grid_and_decode_exactly(model):
    y = _scores(model)
    step = 2.0 * model.score_step
    v = rd_quantize(model, y, step=step, kappa=0.3)
    q = v / np.float32(step)
    np.testing.assert_allclose(q, np.rint(q), atol=1e-4)
    packet = encode_scores(v, step=step, frame=9, view=(1.0, 2.0), image_digest=model.digest,
                           n_components=model.image.n_components).packet
    decoded = ScoreDecoder(model.image.n_coefficients, model.digest,
                           n_components=model.image.n_components).decode(packet)
    np.testing.assert_allclose(decoded.y, v, rtol=1e-6)


def test_a_larger_lambda_costs_fewer_bytes_and_more_error(model):
    y = _scores(model)
    step = model.score_step
    sizes, errors = [], []
    for lam in (0.0, rd_lambda(step, 0.2), rd_lambda(step, 1.0), rd_lambda(step, 5.0)):
        v = rd_quantize(model, y, step=step, lam=lam)
        sizes.append(_packet_bytes(model, v, step))
        errors.append(float(np.sum((y - v) ** 2)))
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] < sizes[0], sizes
    assert errors == sorted(errors) and errors[-1] > errors[0], errors


def test_an_empty_cell_gets_nothing_and_each_cell_is_an_end_of_block_prefix(model):
    counts = np.asarray(model.image.n_components)
    ends = np.cumsum(counts)
    busy = int(np.argmax(counts))
    y = _scores(model)
    lo = int(ends[busy] - counts[busy])
    y[lo:ends[busy]] = 0.05 * model.score_step  # the cell shows its mean: nothing to send
    v = rd_quantize(model, y, kappa=0.2)
    assert not np.any(v[lo:ends[busy]])
    for c in range(counts.size):  # zeros may sit inside a cell, never values after its end
        seg = v[ends[c] - counts[c]:ends[c]]
        assert seg.size == 0 or np.all(np.diff((seg != 0).cumsum()[::-1]) <= 0)


def test_weights_move_bits_between_cells(model):
    counts = np.asarray(model.image.n_components)
    y = _scores(model)
    base = rd_quantize(model, y, kappa=0.5)
    busy = int(np.argmax(counts))
    ends = np.cumsum(counts)
    cell = slice(int(ends[busy] - counts[busy]), int(ends[busy]))
    w = np.ones(counts.size)
    w[busy] = 0.0  # errors there cost nothing: nothing is sent
    assert not np.any(rd_quantize(model, y, kappa=0.5, weights=w)[cell])
    w[busy] = 100.0  # errors there are expensive: at least as much as unweighted is sent
    heavy = rd_quantize(model, y, kappa=0.5, weights=w)[cell]
    assert np.count_nonzero(heavy) >= np.count_nonzero(base[cell])
    assert np.sum((heavy - y[cell]) ** 2) < np.sum((base[cell] - y[cell]) ** 2)


def test_frame_encoder_sends_rd_values_unchanged(model):
    y = rd_quantize(model, _scores(model), kappa=0.3)
    enc = FrameEncoder(model, first_frame=5).encode((10.0, 20.0), key=True, scores=y)
    decoded = ScoreDecoder(model.image.n_coefficients, model.digest,
                           n_components=model.image.n_components).decode(enc.packet)
    np.testing.assert_allclose(decoded.y, y, rtol=1e-6)


def test_rd_quantize_refuses_bad_arguments(model):
    y = _scores(model)
    with pytest.raises(ValueError, match="K="):
        rd_quantize(model, y[:-1])
    with pytest.raises(ValueError, match="step"):
        rd_quantize(model, y, step=0.0)
    with pytest.raises(ValueError, match="weights"):
        rd_quantize(model, y, weights=np.ones(3))


def test_ssim_weights_favour_smooth_object_cells():
    img = np.zeros((16, 32, 3), np.uint8)
    img[:, :16] = 120  # smooth object cell
    img[:, 16:] = (np.indices((16, 16)).sum(axis=0) % 2 * 200)[..., None]  # textured cell
    mask = np.ones((16, 32), bool)
    w = ssim_cell_weights(img, (16, 16), mask)
    assert w[0] > 10 * w[1] and np.isclose(w.mean(), 1.0)
    mask[:, :16] = False  # the smooth cell is background now: only the floor factor is left
    w2 = ssim_cell_weights(img, (16, 16), mask, floor=0.25)
    assert np.isclose(w2[0] / w2[1], 0.25 * w[0] / w[1])


def test_rd_delta_codes_the_difference_and_keeps_the_base_where_nothing_is_sent(model):
    step = model.score_step
    prev = rd_quantize(model, _scores(model, seed=1), step=step, lam=0.0)
    y = prev.astype(np.float64).copy()
    y[:5] += np.array([3.0, -2.0, 4.0, 0.1, 0.2]) * step  # a small change of the frame
    v = rd_delta(model, y, prev, step=step, kappa=0.2)
    q = v / np.float32(step)
    np.testing.assert_allclose(q, np.rint(q), atol=1e-3)  # still on the grid: a valid delta
    np.testing.assert_array_equal(v[5:], prev[5:])  # unchanged coefficients cost nothing
    assert np.any(v[:3] != prev[:3])
    base = encode_scores(prev, step=step, frame=1, view=(0.0, 0.0), image_digest=model.digest,
                         n_components=model.image.n_components)
    delta = encode_scores(v, step=step, frame=2, view=(0.0, 0.0), image_digest=model.digest,
                          n_components=model.image.n_components, base=base).packet
    assert len(delta) < len(base.packet)
