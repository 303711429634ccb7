"""Tests of host.fit.quantize: the int8 model and the measured quantization loss."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from host.fit.pca import CellEigenspace
from host.fit.quantize import (
    QuantizedEigenspace,
    int8_loss_db,
    quantize_components,
    quantize_eigenspace,
    quantize_mean,
)
from protocol.image import read_image, write_image


def view_images(n_views=36, height=21, width=18):
    """Smooth, view-dependent RGB images (a realistic, decaying PCA spectrum)."""
    phi = np.linspace(0, 2 * np.pi, n_views, endpoint=False)[:, None, None]
    yy, xx = np.mgrid[0:height, 0:width]
    r = 128 + 90 * np.sin(phi + xx / 5.0) * np.cos(yy / 7.0)
    g = 120 + 60 * np.cos(2 * phi - yy / 4.0)
    b = 100 + 50 * np.sin(phi) * (xx / width)
    return np.clip(np.stack([r, g, b], -1), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def fitted():
    images = view_images()
    model = CellEigenspace("adaptive", cell=8, threshold=0.995, components=30).fit(images)
    return model, images


def test_quantize_components_bound_and_scale():
    rng = np.random.default_rng(0)
    v = rng.standard_normal((20, 300)) * rng.uniform(0.01, 5, (20, 1))
    v[3] = 0.0
    q, scales = quantize_components(v)
    assert q.dtype == np.int8 and scales.dtype == np.float32
    assert q.shape == v.shape and scales.shape == (20,)
    nonzero = np.arange(20) != 3
    assert np.allclose(scales[nonzero], np.abs(v[nonzero]).max(1) / 127, rtol=1e-6)
    assert np.all(np.abs(q[nonzero]).max(1) == 127)  # the peak maps to +-127
    assert q.min() >= -127
    error = np.abs(v - scales[:, None].astype(np.float64) * q)
    assert np.all(error <= scales[:, None] / 2 * (1 + 1e-5) + 1e-12)
    assert scales[3] == 0 and not q[3].any()
    with pytest.raises(ValueError, match="NaN"):
        quantize_components(np.array([[np.nan]]))


def test_quantize_mean_rounds_and_clips():
    out = quantize_mean(np.array([[-3.2, 0.4, 0.6, 254.6, 300.0, 17.5]]))
    assert out.dtype == np.uint8
    assert out.tolist() == [[0, 0, 1, 255, 255, 18]]


def test_quantize_eigenspace_layout_with_a_stand_in_model():
    rng = np.random.default_rng(1)
    comps = [rng.standard_normal((2, 12)), np.zeros((0, 12)), rng.standard_normal((3, 12))]
    model = SimpleNamespace(
        mean_=rng.uniform(-10, 300, (3, 12)).astype(np.float32),
        components_=comps,
        n_components_=np.array([2, 0, 3]),
        image_shape_=(2, 5),
        cell_shape_=(2, 2),
    )
    qe = quantize_eigenspace(model)
    assert qe.n_components.dtype == np.int32 and qe.n_components.tolist() == [2, 0, 3]
    assert qe.eigenimages.shape == (5, 12) and qe.n_coefficients == 5
    stacked = np.concatenate([comps[0], comps[2]])  # cell-major order
    expected_q, expected_s = quantize_components(stacked)
    assert np.array_equal(qe.eigenimages, expected_q)
    assert np.array_equal(qe.scales, expected_s)
    assert np.array_equal(qe.mean, quantize_mean(model.mean_))
    assert (qe.image_shape, qe.cell_shape) == ((2, 5), (2, 2))


def test_unfitted_or_inconsistent_models_are_refused():
    with pytest.raises(ValueError, match=r"lacks fitted attributes .*call fit first"):
        quantize_eigenspace(CellEigenspace())
    model = SimpleNamespace(
        mean_=np.zeros((2, 12)),
        components_=[np.zeros((1, 12))],
        n_components_=np.array([1]),
        image_shape_=(2, 4),
        cell_shape_=(2, 2),
    )
    with pytest.raises(ValueError, match="mean_ has 2 cells but components_ has 1"):
        quantize_eigenspace(model)


def test_int8_model_reconstructs_close_to_the_float_model(fitted):
    model, images = fitted
    qe = quantize_eigenspace(model)
    assert qe.n_components.sum() == model.component_offsets_[-1]
    rec = qe.reconstructor()
    worst = 0
    for i in range(0, len(images), 5):
        float_image = np.clip(np.rint(model.inverse_transform(model.scores_[i])), 0, 255)
        worst = max(worst, np.abs(rec.update(model.scores_[i]) - float_image).max())
    # |y| <= sqrt(cell_values) * 255 in the worst case, but in practice a few levels
    assert worst <= 4


def direct_psnr(reference, test):
    mse = np.mean((reference.astype(np.float64) - test.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else 10 * math.log10(255**2 / mse)


def test_int8_loss_db_matches_a_direct_computation(fitted):
    model, images = fitted
    qe = quantize_eigenspace(model)
    scores = model.scores_
    loss = int8_loss_db(model, images, scores=scores, quantized=qe)
    offsets = model.component_offsets_
    float_images = np.clip(np.rint(model.inverse_transform(scores)), 0, 255)
    # the int8 formula of model.md written out here in float64
    int8_images = []
    for i in range(len(images)):
        cells = qe.mean.astype(np.float64).copy()
        for c in range(len(qe.n_components)):
            a, b = offsets[c], offsets[c + 1]
            w = scores[i, a:b].astype(np.float64) * qe.scales[a:b]
            cells[c] += w @ qe.eigenimages[a:b].astype(np.float64)
        ny, nx = model.grid_shape_
        ch, cw = model.cell_shape_
        full = cells.reshape(ny, nx, ch, cw, 3).transpose(0, 2, 1, 3, 4)
        full = full.reshape(ny * ch, nx * cw, 3)[: images.shape[1], : images.shape[2]]
        int8_images.append(np.clip(np.rint(full), 0, 255))
    int8_images = np.stack(int8_images)
    assert loss.n_views == len(images)
    assert loss.psnr_float_db == pytest.approx(direct_psnr(images, float_images), abs=1e-9)
    assert loss.psnr_int8_db == pytest.approx(direct_psnr(images, int8_images), abs=0.01)
    assert loss.loss_db == pytest.approx(loss.psnr_float_db - loss.psnr_int8_db)
    assert loss.psnr_float_vs_int8_db == pytest.approx(
        direct_psnr(float_images, int8_images), abs=0.05
    )
    # int8 rounding noise (about scale/sqrt(12) per entry, summed over a cell's components)
    # keeps the two reconstructions within about a grey level of each other
    assert 30 < loss.psnr_int8_db <= loss.psnr_float_db + 0.05
    assert loss.psnr_float_vs_int8_db > 45


def test_int8_loss_db_defaults_and_errors(fitted):
    model, images = fitted
    loss = int8_loss_db(model, images[:4])  # scores from model.transform
    assert loss.n_views == 4 and math.isfinite(loss.psnr_int8_db)
    with pytest.raises(ValueError, match="images must be uint8"):
        int8_loss_db(model, images.astype(np.float32))
    with pytest.raises(ValueError, match="scores must have shape"):
        int8_loss_db(model, images[:2], scores=model.scores_[:3])
    with pytest.raises(ValueError, match="the model is 21x18"):
        int8_loss_db(model, images[:, :10])


def test_to_image_round_trips_through_ecs(fitted, tmp_path):
    model, _ = fitted
    qe = quantize_eigenspace(model)
    image = qe.to_image(method="adaptive", provenance={"solver": model.solver_})
    write_image(tmp_path / "m.ecs", image, annex={"scores": model.scores_})
    back = read_image(tmp_path / "m.ecs")
    assert isinstance(qe, QuantizedEigenspace)
    for name in ("mean", "eigenimages", "scales", "n_components"):
        assert np.array_equal(getattr(back, name), getattr(qe, name))
    assert np.array_equal(back.annex["scores"], model.scores_)
