"""Metrics, equal-bytes codecs, the device path, render settings and `eigencast evaluate`."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from cli_helpers import run_cli
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio as sk_psnr
from skimage.metrics import structural_similarity as sk_ssim

from host.evaluate import (
    DevicePath,
    compare_images,
    encode_image,
    encode_within_budget,
    flip_error,
    nearest_training_view,
    peak_signal_noise_ratio,
    structural_similarity,
)
from host.fit.model import HostModel, build_image, fit_database, save_model
from host.fit.motion import DEFAULT_STRIDES
from host.render.cinema import CinemaDB
from host.render.settings import RenderSettings, SettingsError, ViewRenderer
from protocol.scores import encode_scores


def _smooth_image(size=64, seed=0):
    """A smooth colour image with some texture (compresses like a rendering)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    base = np.stack([0.5 + 0.4 * np.sin(6 * x + 2 * y), 0.5 + 0.4 * np.cos(5 * y),
                     0.5 + 0.3 * np.sin(3 * x * y + 1)], axis=-1)
    noise = rng.normal(0, 0.03, size=base.shape)
    return np.clip((base + noise) * 255, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def small_model(tooth_db, tmp_path_factory):
    db = CinemaDB.open(tooth_db)
    model = fit_database(db, method="adaptive", cell=16, threshold=0.995, progress=False)
    image, annex = build_image(model, db)
    path = tmp_path_factory.mktemp("model") / "m.ecs"
    save_model(path, image, annex)
    return path


# ----------------------------------------------------------------------------- metrics


def test_identical_images_are_perfect():
    a = _smooth_image()
    assert peak_signal_noise_ratio(a, a) == math.inf
    assert structural_similarity(a, a) == pytest.approx(1.0)
    assert flip_error(a, a) == pytest.approx(0.0, abs=1e-7)
    c = compare_images(a, a, mask=np.ones(a.shape[:2], bool))
    assert c.psnr == math.inf and c.psnr_object == math.inf
    assert c.ssim == pytest.approx(1.0) and c.ssim_object == pytest.approx(1.0)
    assert c.flip == pytest.approx(0.0, abs=1e-7)


def test_psnr_of_a_known_error_level():
    a = np.full((32, 32, 3), 100, np.uint8)
    b = a.copy()
    b[::2] += 5  # half the rows off by 5, half exact: MSE = 12.5
    b[1::2] -= 5  # now every pixel off by 5: MSE = 25
    expected = 10 * math.log10(255**2 / 25.0)
    assert peak_signal_noise_ratio(a, b) == pytest.approx(expected, abs=1e-9)
    assert peak_signal_noise_ratio(a, b, mask=np.ones((32, 32), bool)) == pytest.approx(expected)
    rng = np.random.default_rng(1)
    c, d = _smooth_image(seed=2), _smooth_image(seed=3)
    assert peak_signal_noise_ratio(c, d) == pytest.approx(sk_psnr(c, d, data_range=255))
    assert structural_similarity(c, d) == pytest.approx(
        sk_ssim(c, d, data_range=255, channel_axis=-1))
    noisy = np.clip(c + rng.normal(0, 4, c.shape), 0, 255).astype(np.uint8)
    assert compare_images(c, noisy).psnr == pytest.approx(peak_signal_noise_ratio(c, noisy))


def test_mask_restricts_every_metric_to_its_pixels():
    a = _smooth_image(96)
    b = a.copy()
    b[:, :24] = 255 - b[:, :24]  # damage only the left quarter
    mask = np.zeros(a.shape[:2], bool)
    mask[:, 60:] = True  # far from the damage (FLIP's filters reach a few pixels)
    assert peak_signal_noise_ratio(a, b, mask=mask) == math.inf
    assert structural_similarity(a, b, mask=mask) == pytest.approx(1.0)
    assert flip_error(a, b, mask=mask) < 1e-3 < flip_error(a, b)
    # the unmasked mean is the mask-weighted mix of both halves
    left = np.zeros_like(mask)
    left[:, :24] = True
    sq = ((a.astype(float) - b) ** 2).mean(axis=2)
    assert peak_signal_noise_ratio(a, b, mask=left) == pytest.approx(
        10 * math.log10(255**2 / sq[left].mean()))
    c = compare_images(a, b, mask=mask)
    assert c.psnr_object == math.inf and c.psnr < 20
    assert c.ssim_object == pytest.approx(1.0) and c.ssim < 0.9


def test_metric_inputs_are_checked():
    a = _smooth_image(32)
    with pytest.raises(ValueError, match="shapes differ"):
        peak_signal_noise_ratio(a, a[:16])
    with pytest.raises(ValueError, match="outside"):
        flip_error(a.astype(np.float32) * 2, a.astype(np.float32) * 2)
    with pytest.raises(ValueError, match="no pixels"):
        structural_similarity(a, a, mask=np.zeros((32, 32), bool))
    with pytest.raises(ValueError, match="mask must be bool"):
        flip_error(a, a, mask=np.ones((16, 16), bool))
    # an empty object mask in compare_images gives NaN object metrics, not an error
    c = compare_images(a, a, mask=np.zeros((32, 32), bool))
    assert math.isnan(c.ssim_object) and c.ssim == pytest.approx(1.0)


# ----------------------------------------------------------------------------- codecs


@pytest.mark.parametrize("codec", ["jpeg", "webp", "avif"])
def test_equal_bytes_search_returns_the_highest_quality_within_budget(codec):
    image = _smooth_image(64)
    for budget in (encode_image(image, codec, 30).size_bytes + 7,
                   encode_image(image, codec, 75).size_bytes - 1):
        coded = encode_within_budget(image, budget, codec=codec)
        assert coded.within_budget and coded.size_bytes <= budget
        assert encode_image(image, codec, coded.quality + 1).size_bytes > budget
        assert coded.decode().shape == image.shape
        # a hint (right, too low, too high) changes the work, not the answer's property
        for hint in (coded.quality, 1, 100, coded.quality + 9):
            again = encode_within_budget(image, budget, codec=codec, hint=hint)
            assert again.size_bytes <= budget
            assert again.quality == 100 or encode_image(
                image, codec, again.quality + 1).size_bytes > budget
    tiny = encode_within_budget(image, 10, codec=codec)
    assert tiny.quality == 1 and not tiny.within_budget and tiny.size_bytes > 10
    assert encode_within_budget(image, 10, codec=codec, hint=50).quality == 1
    huge = encode_within_budget(image, 10**9, codec=codec)
    assert huge.quality == 100 and huge.within_budget
    assert encode_within_budget(image, 10**9, codec=codec, hint=3).quality == 100
    with pytest.raises(ValueError, match="codec"):
        encode_within_budget(image, 100, codec="gif")
    # what comes back is the image, not just a file of the right size
    def error(coded):
        return np.abs(coded.decode().astype(int) - image.astype(int)).mean()

    assert error(huge) < error(tiny)
    with pytest.raises(ValueError, match="budget_bytes"):
        encode_within_budget(image, 0, codec=codec)


@pytest.mark.parametrize("codec", ["jpeg", "webp", "avif"])
def test_the_smallest_file_reaching_a_quality_reaches_it_and_the_setting_below_does_not(codec):
    from host.evaluate import CodecLadder

    image = _smooth_image(64)
    measured = []

    def measure(decoded, name):  # one call gives every value of a family
        measured.append(name)
        if name == "error":
            return {"error": float(np.abs(decoded.astype(int) - image.astype(int)).mean())}
        return {"ssim": structural_similarity(image, decoded),
                "psnr": peak_signal_noise_ratio(image, decoded)}

    ladder = CodecLadder(image, codec, measure)
    low, best = ladder.value(1, "ssim"), ladder.value(100, "ssim")
    assert low < best
    for target in (low + 0.3 * (best - low), low + 0.8 * (best - low), best):
        for hint in (None, 1, 40, 99):
            coded = ladder.smallest(target, "ssim", hint=hint)
            assert coded is not None and coded.codec == codec
            # a real file of the image that reaches the target ...
            assert structural_similarity(image, coded.decode()) >= target
            assert coded.data == encode_image(image, codec, coded.quality).data
            # ... where the setting below it misses (the bisection's bracket)
            assert coded.quality == 1 or structural_similarity(
                image, encode_image(image, codec, coded.quality - 1).decode()) < target
    assert ladder.smallest(best + 1e-6, "ssim") is None  # out of reach: None, not the best
    n = len(measured)
    assert ladder.value(100, "psnr") > ladder.value(1, "psnr") and len(measured) == n
    # lower is better: no larger an error than the file at quality 50, no larger a file
    limit = ladder.value(50, "error")
    coded = ladder.smallest(limit, "error", higher_is_better=False)
    assert ladder.value(coded.quality, "error") <= limit
    assert coded.size_bytes <= ladder.file(50).size_bytes


# ----------------------------------------------------------------------------- nearest


def test_nearest_training_view_is_the_angularly_nearest():
    rng = np.random.default_rng(5)
    phi = rng.uniform(0, 360, 200)
    theta = np.degrees(np.arcsin(rng.uniform(-1, 1, 200)))

    def unit(p, t):
        p, t = np.radians(p), np.radians(t)
        return np.stack([np.cos(t) * np.cos(p), np.cos(t) * np.sin(p), np.sin(t)], axis=-1)

    for q_phi, q_theta in zip(rng.uniform(-30, 400, 40), rng.uniform(-90, 90, 40)):
        i, angle = nearest_training_view(q_phi, q_theta, phi, theta)
        brute = np.degrees(np.arccos(np.clip(unit(phi, theta) @ unit(q_phi, q_theta), -1, 1)))
        assert i == int(np.argmin(brute))
        assert angle == pytest.approx(brute.min(), abs=1e-6)
    # across the phi seam: 359.5 is nearer to 0 than to 350
    assert nearest_training_view(359.5, 0.0, [0.0, 350.0], [0.0, 0.0])[0] == 0


# ----------------------------------------------------------------------------- device path


def test_device_path_is_the_device_frame_and_packet(small_model):
    model = HostModel.load(small_model)
    path = DevicePath(model)
    frame, size = path.frame(123.4, 21.0)
    packet = encode_scores(model.quantized_scores(123.4, 21.0), step=model.score_step,
                           frame=7, view=(123.4, 21.0), image_digest=model.digest,
                           n_components=model.image.n_components).packet
    assert size == len(packet)
    diff = np.abs(frame.astype(int) - model.view(123.4, 21.0).astype(int))
    assert diff.max() <= 1  # float32 vs float64 rounding of the same quantized scores


def test_projection_of_a_training_view_matches_its_own_scores(small_model, tooth_db):
    model = HostModel.load(small_model)
    db = CinemaDB.open(tooth_db)
    path = DevicePath(model)
    for i in (5, 90):
        frame, _ = path.projection_frame(db.read_image(i))
        own = model.view(db.phi_deg[i], db.theta_deg[i])  # interpolation is exact here
        assert np.abs(frame.astype(float) - own).mean() < 1.0


def test_metric_workers_give_the_same_results_as_inline(small_model):
    from host.evaluate import evaluate_model

    model = HostModel.load(small_model)
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what="m"))
    views = [(10.0, 5.0), (200.0, -40.0), (300.0, 70.0)]
    inline = evaluate_model(model, scene, views, rd_views=1, metric_workers=0, progress=False,
                            sample_views=1, motion_stride=2)  # the deadline's would vary
    pooled = evaluate_model(model, scene, views, rd_views=1, metric_workers=2, progress=False,
                            sample_views=1, motion_stride=2)
    assert inline.views == pooled.views
    assert [p["ssim"] for p in inline.rd] == [p["ssim"] for p in pooled.rd]
    np.testing.assert_array_equal(inline.samples[0]["flip_pca"], pooled.samples[0]["flip_pca"])
    # the per-view records hold what the metric functions give on the same images
    truth, _ = scene.render(*views[0])
    frame, size = DevicePath(model).frame(*views[0])
    assert inline.views[0]["pca"]["bytes_per_view"] == size
    assert inline.views[0]["pca"]["ssim"] == pytest.approx(structural_similarity(truth, frame))


# ----------------------------------------------------------------------------- render settings


def test_view_renderer_reproduces_training_images_bit_for_bit(tooth_db):
    db = CinemaDB.open(tooth_db)
    settings = RenderSettings.from_record(db.settings, what=str(tooth_db))
    scene = ViewRenderer.open(settings, what="db")
    for i in (0, 77):
        rgb8, alpha = scene.render(db.phi_deg[i], db.theta_deg[i])
        np.testing.assert_array_equal(rgb8, db.read_image(i))
        assert alpha.shape == rgb8.shape[:2] and 0 < (alpha > 0).mean() < 1


def test_render_settings_refuse_missing_or_mismatched(tooth_db):
    db = CinemaDB.open(tooth_db)
    with pytest.raises(SettingsError, match="no render settings"):
        RenderSettings.from_record({}, what="x.ecs")
    broken = {k: v for k, v in db.settings.items() if k != "camera"}
    with pytest.raises(SettingsError, match="lack camera"):
        RenderSettings.from_record(broken, what="x.ecs")
    settings = RenderSettings.from_record(db.settings, what="x.ecs")
    with pytest.raises(SettingsError, match="dims"):
        settings.load_volume("builtin:head", what="x.ecs")


# ----------------------------------------------------------------------------- the command


def test_evaluate_cli_json_and_report(small_model, tmp_path):
    report = tmp_path / "report"
    res = run_cli("evaluate", str(small_model), "--views", "random:5", "--report", str(report),
                  "--json", "--rd-views", "2", "--samples-shown", "2")
    summary = json.loads(res.stdout)  # exactly one JSON object on stdout
    for key in ("method", "threshold", "components_per_cell", "eigenspace_bytes", "views",
                "pca", "pca_render", "pca_motion", "jpeg", "webp", "avif", "nearest", "webp_db"):
        assert key in summary
    assert summary["method"] == "adaptive" and summary["threshold"] == pytest.approx(0.995)
    assert summary["views"] == 5
    # the ray-cast's own scores (serve --scores render) beat interpolated ones, view by view
    for v in summary["per_view"]:
        assert v["pca_render"]["psnr_object"] > v["pca"]["psnr_object"], v
        assert v["pca_render"]["bytes_per_view"] > 16  # a real key packet
    for method in ("pca", "pca_render", "pca_motion", "jpeg", "webp", "avif", "nearest",
                   "webp_db"):
        for key in ("bytes_per_view", "psnr", "ssim", "flip", "psnr_object", "ssim_object",
                    "flip_object"):
            assert isinstance(summary[method][key], float), (method, key)
    # AVIF: the same fields as WebP, in the table, the sweep and the per-view records
    assert set(summary["avif"]) == set(summary["webp"])
    assert {p["kind"] for p in summary["rate_distortion"]} >= {"jpeg", "webp", "avif"}
    assert all(set(v["avif"]) == set(v["webp"]) for v in summary["per_view"])
    # the frames serve --scores motion sends while moving: a stride, a deadline, delta bytes
    motion = summary["pca_motion"]
    assert motion["stride"] in DEFAULT_STRIDES and motion["deadline_ms"] == pytest.approx(1e3 / 30)
    assert motion["step_deg"] == 3.0 and all(
        v["pca_motion"]["bytes_per_view"] > 0 for v in summary["per_view"])
    # the on-device WebP database: nothing per frame, every training view stored
    db = summary["webp_db"]
    assert db["bytes_per_view"] == 0 and db["quality"] == 80
    assert db["storage_estimated"] is False and db["storage_bytes"] > 144 * 60
    assert 0 < db["ssim_object"] <= 1 and all(
        v["webp_db"]["bytes_per_view"] == 0 for v in summary["per_view"])
    for point in summary["rate_distortion"]:  # object metrics on the sweep too
        assert "ssim_object" in point and "flip_object" in point
    model = HostModel.load(small_model)
    assert summary["components_per_cell"] == pytest.approx(np.mean(model.image.n_components))
    # equal bytes: a codec file is never larger than the packet unless even q=1 is
    if summary["jpeg"]["over_budget_views"] == 0:
        assert summary["jpeg"]["bytes_per_view"] <= summary["pca"]["bytes_per_view"]
    assert summary["int8"]["train_loss_db"] < 0.3
    assert (report / "index.html").is_file() and (report / "rd.png").is_file()
    views = sorted((report / "views").glob("*.png"))
    assert len(views) == 2
    with Image.open(views[0]) as im:
        assert im.width > 4 * 40  # several panels side by side
    html = (report / "index.html").read_text()
    assert "Table 1" in html and "rd.png" in html and "view_00.png" in html
    assert "ray-cast scores" in html
    assert "AVIF, equal bytes" in html and "served while moving" in html
    assert "Traceback" not in res.stderr and "evaluate" in res.stderr  # progress on stderr


def test_webp_database_blends_decoded_training_views_with_the_model_weights(small_model):
    from host.evaluate import WebPDatabase, decode_image
    from host.evaluate.baselines import TrainingImages

    model = HostModel.load(small_model)
    training = TrainingImages(model, None)
    assert training.db is not None
    q = 70
    webp_db = WebPDatabase(model, training, q)
    coded = [encode_image(training.db.read_image(i), "webp", q) for i in range(training.db.n_views)]
    assert webp_db.storage_bytes == sum(c.size_bytes for c in coded)
    # at a training view the blend is that view's decoded WebP, bit for bit
    i = 31
    np.testing.assert_array_equal(webp_db.frame(training.phi[i], training.theta[i]),
                                  coded[i].decode())
    # between views: the model's interpolation weights applied to the decoded files
    phi, theta = 100.0, 10.0
    idx, w = model.interpolator.weights(phi, theta)
    expected = sum(np.float32(wi) * decode_image(coded[j].data).astype(np.float32)
                   for j, wi in zip(idx.tolist(), w.tolist()) if wi != 0)
    np.testing.assert_array_equal(webp_db.frame(phi, theta),
                                  np.clip(np.rint(expected), 0, 255).astype(np.uint8))
    assert np.count_nonzero(w) > 1
    lazy = WebPDatabase(model, training, q, encode_all=False)
    lazy.frame(phi, theta)
    assert lazy.storage_estimated and lazy.storage_bytes > 0
    with pytest.raises(ValueError, match="quality"):
        WebPDatabase(model, training, 0)


def test_webp_database_frames_is_the_webp_database_of_a_whole_cinema_database(small_model):
    # the scripts' baseline (no model needed) must agree with the evaluation's WebPDatabase
    from host.evaluate import TrainingImages, WebPDatabase, webp_database_frames

    model = HostModel.load(small_model)
    training = TrainingImages(model, None)
    views = [(100.0, 10.0), (training.phi[5], training.theta[5]), (233.0, -20.0)]
    weights = [model.interpolator.weights(phi, theta) for phi, theta in views]
    total, frames = webp_database_frames(training.db, weights, 60)
    webp_db = WebPDatabase(model, training, 60)
    assert total == webp_db.storage_bytes
    assert len(frames) == len(views)
    for (phi, theta), frame in zip(views, frames):
        assert frame.dtype == np.uint8 and frame.shape == (*model.image.image_shape, 3)
        np.testing.assert_array_equal(frame, webp_db.frame(phi, theta))


def test_object_masks_from_the_image_and_from_the_opacity():
    from host.evaluate import OBJECT_LEVEL, alpha_object_mask, object_mask
    from host.render.settings import OBJECT_ALPHA_MIN

    image = np.zeros((4, 5, 3), np.uint8)
    image[1, 2, 1] = OBJECT_LEVEL + 1  # one channel above the level is enough
    image[3, 0] = OBJECT_LEVEL  # at the level is background
    mask = object_mask(image)
    assert mask.shape == (4, 5) and mask.dtype == bool
    assert mask.sum() == 1 and mask[1, 2]
    alpha = np.array([[0.0, OBJECT_ALPHA_MIN * 0.99, OBJECT_ALPHA_MIN, 1.0]])
    np.testing.assert_array_equal(alpha_object_mask(alpha), [[False, False, True, True]])


def test_evaluate_refuses_a_mismatched_volume_in_one_line(small_model, tmp_path):
    res = run_cli("evaluate", str(small_model), "builtin:head", "--views", "random:2",
                  check=False)
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "dims" in lines[0] and "builtin:head" in lines[0]
    res = run_cli("evaluate", str(small_model), "--tf", "ct-bone", "--views", "random:2",
                  check=False)
    assert res.returncode == 1 and "--tf" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_evaluate_help_says_the_models_recorded_settings_win(small_model):
    """--help listed "--size (default 300)" and a --tf "chosen from the volume's modality"
    while the model's recorded settings were used: it says which wins, and those options
    are refused for a model that records its settings (one line each)."""
    text = " ".join(run_cli("evaluate", "--help").stdout.split())
    assert "default 300" not in text and "chosen from the volume's modality" not in text
    assert "evaluate always ray-casts novel views that way" in text
    assert "--size N|WxH its images' size (default and only value: the model's)" in text
    assert "required for it" in text
    for option in (["--size", "64"], ["--samples", "50"], ["--tf", "generic"]):
        res = run_cli("evaluate", str(small_model), *option, "--views", "random:2", check=False)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 1 and len(lines) == 1, res.stderr
        assert "records its render settings and evaluate ray-casts with them" in lines[0]
        assert option[0] in lines[0]


def test_evaluate_foreign_model_needs_explicit_render_options(tooth_db, tmp_path):
    foreign = tmp_path / "foreign.cdb"
    shutil.copytree(tooth_db, foreign, ignore=shutil.ignore_patterns(".eigencast-cache"))
    (foreign / "eigencast.json").unlink()
    db = CinemaDB.open(foreign)
    model = fit_database(db, method="cell", cell=20, components=6, progress=False)
    image, annex = build_image(model, db)
    path = tmp_path / "f.ecs"
    save_model(path, image, annex)
    res = run_cli("evaluate", str(path), "--views", "random:2", check=False)
    assert res.returncode == 1 and "--tf" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    # with the options the database was rendered with, the novel views are ray-cast
    res = run_cli("evaluate", str(path), "builtin:tooth", "--tf", "tooth", "--samples", "120",
                  "--views", "random:2", "--json", "--rd-views", "0", "--no-nearest")
    summary = json.loads(res.stdout)
    assert summary["pca"]["ssim"] > 0.5 and "nearest" not in summary


def test_pca_motion_ray_casts_at_its_stride_however_slow_the_machine(small_model, monkeypatch):
    import host.fit.motion as motion
    from host.evaluate import evaluate_model

    model = HostModel.load(small_model)
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what="m"))
    # a host that takes 10 s per ray-cast: none fits serve's deadline, evaluate's must still
    monkeypatch.setattr(motion.MotionScores, "estimate", lambda self, stride: 10.0)
    views = [(10.0, 5.0), (200.0, -40.0)]
    result = evaluate_model(model, scene, views, rd_views=1, metric_workers=0, progress=False,
                            sample_views=0, motion_stride=2)
    for record in result.views:  # the prior alone would be the interpolated frame again
        assert record["pca_motion"]["ssim_object"] != record["pca"]["ssim_object"]


def test_evaluate_reports_the_served_path_for_a_model_with_the_table(model_path, small_model,
                                                                     tmp_path):
    """For a model with the standalone table: its own frame (``pca_warp``, a blend here), that
    frame served at rest and while moving, against the own frame, the codecs' equal-quality
    bytes and every method's blockiness, in the JSON, the table and the report; nothing of
    it for a model without the table."""
    report = tmp_path / "report"
    res = run_cli("evaluate", str(model_path), "--views", "random:3", "--json", "--rd-views", "3",
                  "--samples-shown", "1", "--no-nearest", "--motion-stride", "0",
                  "--webp-db-quality", "0", "--report", str(report), "--rd-codecs-only")
    summary = json.loads(res.stdout)
    assert {p["kind"] for p in summary["rate_distortion"]} == {"jpeg", "webp", "avif"}
    assert summary["pca_warp"]["own_frame"] == "blend" and summary["pca_warp"][
        "bytes_per_view"] == 0
    for v in summary["per_view"]:
        # at rest the complete correction lifts the own frame towards the ray-cast
        assert v["pca_predict"]["psnr_object"] > v["pca_warp"]["psnr_object"], v
        assert v["pca_predict"]["bytes_per_view"] > 0
        # stride 0 (no ray-cast fits): while moving the device shows its own frame, 0 bytes
        assert v["pca_motion"]["bytes_per_view"] == 0 and v["pca_motion"]["stride"] == 0
        assert v["pca_motion"]["ssim_object"] == v["pca_warp"]["ssim_object"]
        assert v["raycast_blockiness"] > 0 and all(
            v[m]["blockiness"] > 0 for m in ("pca", "pca_warp", "pca_predict", "webp"))
    rest = summary["pca_predict"]
    assert rest["views_below_own"] == 0 and rest["worst_gain_over_own"] > 0
    assert summary["pca_motion"]["gain_over_own"] == 0.0
    eq = rest["equal_quality"]
    assert eq["views"] == 3 and eq["ssim_object"] == pytest.approx(rest["ssim_object"])
    for codec in ("webp", "avif"):
        assert set(eq[codec]) == {"bytes_for_ssim", "ssim_at_bytes", "min_bytes"}
        assert eq[codec]["min_bytes"] > 0
    html = (report / "index.html").read_text()
    assert "served at rest" in html and "blockiness" in html and "WebP bytes for" in html
    # at rest, serve's layers to the exact frame: in the JSON, the plot and the strip
    rest = summary["rest"]
    assert rest["views"] == 3 and rest["stages"]["exact"]["x_webp_lossless"]["median"] > 0
    assert all(v["rest"]["steps"][-1]["kind"] == "exact" for v in summary["per_view"])
    assert (report / "rest.png").is_file() and "At rest: layers to the exact frame" in html
    table = run_cli("evaluate", str(model_path), "--views", "random:2", "--rd-views", "0",
                    "--no-nearest", "--motion-deadline", "0", "--webp-db-quality", "0").stdout
    assert "pca_predict: served, at rest" in table and "score blend" in table
    plain = run_cli("evaluate", str(small_model), "--views", "random:2", "--json", "--rd-views",
                    "0", "--no-nearest", "--motion-deadline", "0", "--webp-db-quality", "0")
    plain = json.loads(plain.stdout)
    assert "pca_predict" not in plain and "pca_warp" not in plain and "rest" not in plain
    assert plain["pca"]["blockiness"] > 0


@pytest.fixture(scope="module", params=["blend", "depth"])
def served_model(request, model_path, tmp_path_factory):
    """(path, HostModel) of a standalone model whose own frames are blends, and one with depth
    (warps)."""
    from runtime_helpers import tiny_model

    path = (model_path if request.param == "blend" else
            tiny_model(tmp_path_factory, name="tiny-depth", depth=True))
    return path, HostModel.load(path)


def test_served_frames_are_what_a_correcting_device_shows(served_model):
    """evaluate's own frame, at-rest and moving frames and their bytes are those of serve's
    correction packets (`CorrectionEncoder`) decoded and added by the device's own code
    (`LoadedModel`: its warp worker or blend, decoder and reconstructor), bit for bit."""
    from provision_helpers import KEY

    from device_runtime.orbit import canonical_view
    from device_runtime.prediction import OwnFrames
    from device_runtime.runtime import LoadedModel
    from host.evaluate import ServedFrames
    from host.fit.motion import MotionScores
    from host.link.correction import CorrectionEncoder
    from protocol.image import read_image

    path, model = served_model
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what="m"))
    served = ServedFrames(model, scene)
    served.set_stride(4)
    assert served.kind == ("warp" if model.image.synthesis is not None else "blend")
    rest = MotionScores(model, scene, own=OwnFrames(model.image), strides=(1,), coarse=1.0,
                        budget_s=3600.0)
    moving = MotionScores(model, scene, own=OwnFrames(model.image), strides=(4,),
                          budget_s=3600.0)
    encoder = CorrectionEncoder(model)
    device = LoadedModel.build(read_image(path, key=KEY), slot="A", generation=1, test=False,
                               want_predictor=True)
    try:
        for view in ((33.0, 12.0), (250.5, -41.0)):
            view = canonical_view(*view)
            if device.warp_worker is not None:
                device.warp_worker.request(view)
                theirs = device.warp_worker.take(view, 30.0)
            else:
                theirs = device.reconstructor.update(device.predictor(*view)).copy()
            np.testing.assert_array_equal(served.own_frame(*view), theirs)
            for source, fine, (frame, size) in ((rest, True, served.at_rest(*view)),
                                                (moving, False, served.moving(*view))):
                step = source.frame(view)
                sent = encoder.encode(view, scores=step.scores, fine=fine, weights=step.weights)
                if sent is None:  # nothing worth sending: the device keeps its own frame
                    want, want_size = theirs, 0
                else:
                    y = device.decoder.decode(sent.packet).y
                    want = device.reconstructor.correct(y, theirs).copy()
                    want_size = len(sent.packet)
                np.testing.assert_array_equal(frame, want)
                assert size == want_size
                if fine:  # at rest the complete correction is always worth its bytes here
                    assert size > 0 and not np.array_equal(frame, theirs)
    finally:
        device.close()
    served.set_stride(0)
    frame, size = served.moving(*view)
    assert size == 0
    np.testing.assert_array_equal(frame, served.own_frame(*view))


def test_the_resting_chain_is_what_serve_plans_from_what_serve_plans_it_from(served_model):
    """`ServedFrames.rest` gives serve's planner serve's inputs (the view's full ray-cast, the
    device's own frame, that frame with the decoded complete correction: `RestSender.start`)
    and reports its plan step by step: the own frame, the correction where the plan sends
    it, each layer's frame as the device decodes it, the exact frame = the ray-cast; the
    bytes are cumulative."""
    from device_runtime.orbit import canonical_view
    from device_runtime.prediction import OwnFrames
    from host.evaluate import ServedFrames
    from host.fit.motion import MotionScores
    from host.link.correction import CorrectionEncoder
    from host.link.layers import RestPlanner
    from protocol.scores import ScoreDecoder

    _, model = served_model
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what="m"))
    served = ServedFrames(model, scene, planner=RestPlanner(model.digest))
    assert ServedFrames(model, scene).rest(10.0, 5.0) is None  # no planner: no layers
    source = MotionScores(model, scene, own=OwnFrames(model.image), strides=(1,), coarse=1.0,
                          budget_s=3600.0)
    planner, encoder = RestPlanner(model.digest), CorrectionEncoder(model)
    decoder = ScoreDecoder(model.image.n_coefficients, model.digest,
                           n_components=model.image.n_components)
    for view in ((33.0, 12.0), (250.5, -41.0), (120.0, 60.0)):
        view = canonical_view(*view)
        rest = served.rest(*view)
        step = source.frame(view)
        truth, own = source.rest_images(view)
        sent = encoder.encode(view, scores=step.scores, fine=True, weights=step.weights)
        corrected = own if sent is None else source.own.corrected(
            own, decoder.decode(sent.packet).y)
        size = 0 if sent is None else len(sent.packet)
        plan = planner.plan(view, truth, corrected, own, size,
                            base_frame=0 if sent is None else sent.frame, first_frame=1)
        np.testing.assert_array_equal(rest.truth, scene.render(*view)[0])
        assert rest.correction_bytes == size
        assert rest.skip_correction == (plan.skip_correction or sent is None)
        kinds = [s.kind for s in rest.steps]
        assert kinds == ["own", *([] if rest.skip_correction else ["correction"]),
                         *("exact" if layer.exact else "layer" for layer in plan.layers)]
        np.testing.assert_array_equal(rest.steps[0].frame, own)
        if not rest.skip_correction:
            np.testing.assert_array_equal(rest.steps[1].frame, corrected)
        layers = rest.steps[len(kinds) - len(plan.layers):]
        for ours, theirs in zip(layers, plan.layers, strict=True):
            assert ours.step_bytes == theirs.size_bytes
            # the same packets but for their frame numbers (bytes 4..12: frame, base frame)
            assert [q[:4] + q[12:] for q in ours.packets] == [
                q[:4] + q[12:] for q in theirs.packets]
            np.testing.assert_array_equal(ours.frame, theirs.frame)
        total = 0
        for s in rest.steps:
            total += s.step_bytes
            assert s.bytes == total
        assert rest.exact is rest.steps[-1]
        np.testing.assert_array_equal(rest.exact.frame, truth)
        # at_rest of the same view is the same correction, its ray-cast made once
        frame, at_rest_size = served.at_rest(*view)
        assert at_rest_size == size
        np.testing.assert_array_equal(frame, corrected)


def test_evaluate_measures_each_resting_step_against_the_codecs(model):
    """evaluate's resting chain per view: each step's metrics against the ray-cast, the
    cumulative bytes, on the sweep's views the smallest JPEG/WebP/AVIF reaching each lossy
    step's object SSIM (real files: coded again they are the bytes, decoded they reach it),
    and for the exact frame the ray-cast's optimized PNG and WebP lossless files."""
    import io

    from device_runtime.orbit import canonical_view
    from host.evaluate import alpha_object_mask, evaluate_model
    from host.link.layers import RestPlanner

    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what="m"))
    views = [canonical_view(33.0, 12.0), canonical_view(250.5, -41.0)]
    result = evaluate_model(model, scene, views, rd_views=1, sample_views=1, metric_workers=0,
                            progress=False, nearest=False, webp_db_quality=None,
                            motion_deadline_s=None, rd_pca=False,
                            rest_planner=RestPlanner(model.digest))
    assert result.info["rest"]["targets"] == [0.95]
    for i, (view, record) in enumerate(zip(views, result.views, strict=True)):
        truth, alpha = scene.render(*view)
        mask = alpha_object_mask(alpha)
        rest = record["rest"]
        steps = rest["steps"]
        assert steps[0]["kind"] == "own" and steps[0]["bytes"] == 0
        assert steps[0]["ssim_object"] == pytest.approx(record["pca_warp"]["ssim_object"])
        assert steps[-1]["kind"] == "exact" and steps[-1]["ssim_object"] == 1.0
        assert steps[-1]["flip"] == 0.0
        assert [s["bytes"] for s in steps] == list(np.cumsum([s["step_bytes"] for s in steps]))
        png, webp = io.BytesIO(), io.BytesIO()
        Image.fromarray(truth).save(png, "PNG", optimize=True)
        Image.fromarray(truth).save(webp, "WEBP", lossless=True, exact=True)
        assert steps[-1]["png_bytes"] == len(png.getvalue())
        assert steps[-1]["webp_lossless_bytes"] == len(webp.getvalue())
        lossy = [s for s in steps if s["kind"] != "exact"]
        if i >= 1:  # past the sweep's views: no codec searches
            assert not any("codecs" in s for s in lossy)
            continue
        for s in lossy:
            for codec in ("jpeg", "webp", "avif"):
                eq = s["codecs"][codec]
                coded = encode_image(truth, codec, eq["quality"])
                assert coded.size_bytes == eq["bytes"]
                got = structural_similarity(truth, coded.decode(), mask=mask)
                assert got == pytest.approx(eq["ssim_object"]) and got >= s["ssim_object"]
                assert eq["bytes_same_ssim"] is None or eq["bytes_same_ssim"] > 0
                assert eq["bytes_same_flip"] is None or eq["bytes_same_flip"] > 0
    summary = result.summary()["rest"]
    assert summary["views"] == 2 and set(summary["stages"]) >= {"own", "exact"}
    exact = summary["stages"]["exact"]
    assert exact["x_webp_lossless"]["median"] > 0 and exact["png_bytes"] > 0
    # the report's strip: each layer, then the exact frame (the ray-cast) with its bytes
    from host.evaluate.report import _rest_panels

    sample = result.samples[0]
    panels = _rest_panels(sample)
    layers = [s for s in result.views[0]["rest"]["steps"] if s["kind"] in ("layer", "exact")]
    assert len(panels) == len(layers) and panels[-1][0].startswith("exact at rest")
    assert f"{layers[-1]['bytes']} B" in panels[-1][0]
    np.testing.assert_array_equal(panels[-1][1], scene.render(*views[0])[0])


def test_the_deadline_picks_the_stride_a_drag_settles_on(model, monkeypatch):
    """The warm-up drag's usual stride: none when nothing fits the deadline (a host that
    needs 10 s a frame: its moving frames are the own frames), the densest when everything
    does; a slower renderer only slows the ray-casts."""
    import host.fit.motion as motion
    from host.evaluate import ServedFrames, SlowRenderer

    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what="m"))
    served = ServedFrames(model, scene)
    monkeypatch.setattr(motion.MotionScores, "estimate", lambda self, stride: 10.0)
    assert served.pick_stride(1 / 30, (10.0, 5.0), slowdown=2.0) == 0
    monkeypatch.setattr(motion.MotionScores, "estimate", lambda self, stride: 0.0)
    assert served.pick_stride(1 / 30, (10.0, 5.0)) == motion.DEFAULT_STRIDES[0]
    slow = SlowRenderer(scene, 1.5)
    settings = scene.settings
    rows, cols = np.array([3, 20]), np.array([7, 30])
    camera = settings.camera(12.0, 3.0)
    np.testing.assert_array_equal(
        slow.renderer.coarser(2.0).render_pixels(camera, settings.width, settings.height,
                                                 rows, cols),
        scene.renderer.coarser(2.0).render_pixels(camera, settings.width, settings.height,
                                                  rows, cols))
    with pytest.raises(ValueError, match="factor"):
        SlowRenderer(scene, 0.5)


def test_blockiness_is_the_border_to_inside_ratio_of_neighbour_differences():
    from host.evaluate import blockiness

    y, x = np.mgrid[0:32, 0:32].astype(np.float64)
    ramp = np.repeat((4 * x + 2 * y)[..., None], 3, axis=2).astype(np.uint8)
    assert blockiness(ramp, (8, 8)) == pytest.approx(1.0)  # the same step everywhere
    rng = np.random.default_rng(3)
    tiles = np.kron(rng.integers(0, 200, (4, 4)), np.ones((8, 8)))  # flat 8x8 tiles ...
    blocky = np.repeat((tiles + (x % 2))[..., None], 3, axis=2).astype(np.uint8)  # + texture
    assert blockiness(blocky, (8, 8)) > 10
    assert blockiness(blocky, (16, 16)) > 10 and blockiness(blocky, (6, 6)) < blockiness(
        blocky, (8, 8)) / 3  # borders that are not the tiles' see less
    mask = np.zeros((32, 32), bool)
    mask[9:15, 9:15] = True  # inside one tile: no pair crosses a border
    assert math.isnan(blockiness(blocky, (8, 8), mask))
    mask[9:15, 9:18] = True  # one border crossed: the tile jump against the texture
    assert blockiness(blocky, (8, 8), mask) > 10
    with pytest.raises(ValueError, match="mask"):
        blockiness(blocky, (8, 8), mask[:16])


def test_codec_equivalent_interpolates_the_curve_in_quality():
    from host.evaluate import codec_equivalent

    points = [{"setting": {"quality": q}, "bytes_per_view": b, "ssim_object": s}
              for q, b, s in ((90, 1600.0, 0.9), (10, 100.0, 0.5), (50, 400.0, 0.7))]
    eq = codec_equivalent(points, 0.6, 800.0)
    assert eq["bytes_for_ssim"] == pytest.approx(200.0)  # halfway in SSIM, log bytes
    assert eq["ssim_at_bytes"] == pytest.approx(0.8)  # halfway in log bytes
    assert eq["min_bytes"] == 100.0
    out = codec_equivalent(points, 0.95, 50.0)  # above the best, below the smallest file
    assert out["bytes_for_ssim"] is None and out["ssim_at_bytes"] is None


def _report_evaluation():
    """An evaluation as the report draws it: every kind of curve, marker and per-view method,
    so both legends are as full as a real report's."""
    from types import SimpleNamespace

    rng = np.random.default_rng(3)
    rd = []
    for kind, labels in (("pca", ["T=0.8", "T=0.9", "T=0.95", "T=0.98"]),
                         ("jpeg", [f"q={q}" for q in range(10, 100, 10)]),
                         ("webp", [f"q={q}" for q in range(10, 100, 10)]),
                         ("avif", [f"q={q}" for q in range(10, 100, 10)])):
        for i, label in enumerate(labels):
            rd.append({"kind": kind, "label": label, "bytes_per_view": 60.0 * 1.4 ** i,
                       "ssim": 0.8 + 0.02 * i, "flip": 0.1 - 0.008 * i,
                       "ssim_object": 0.78 + 0.02 * i})
    rd += [{"kind": "pca", "label": f"step x{2 ** i}", "bytes_per_view": 150.0 / 2 ** i,
            "ssim": 0.88 - 0.02 * i, "flip": 0.07 + 0.01 * i} for i in range(1, 5)]
    rd.append({"kind": "projection", "label": "oracle", "bytes_per_view": 180.0, "ssim": 0.94,
               "flip": 0.04})
    point = {"bytes_per_view": 170.0, "ssim": 0.9, "flip": 0.07, "ssim_object": 0.88}
    summary = {m: dict(point) for m in ("pca", "pca_render", "pca_motion", "pca_predict",
                                         "pca_warp", "jpeg", "webp", "avif")}
    summary["webp_db"] = {**point, "quality": 80, "storage_bytes": 58_000}
    methods = ("nearest", "jpeg", "webp", "avif", "webp_db", "pca", "pca_motion",
               "pca_render", "pca_predict", "pca_warp")
    views = [{"theta_deg": float(theta),
              **{m: {"ssim": float(rng.uniform(0.7, 1.0)), "flip": float(rng.uniform(0.02, 0.2))}
                 for m in methods}}
             for theta in rng.uniform(-85, 85, 24)]
    for v in views:  # the resting chain: own frame, correction, a layer, exact
        q = float(rng.uniform(0.75, 0.85))
        steps = [("own", 0, q), ("correction", 400, q + 0.05), ("layer", 2000, 0.95),
                 ("exact", 30000, 1.0)]
        v["rest"] = {"skip_correction": False, "steps": [
            {"kind": k, "bytes": b, "ssim_object": sq, "flip": (1.0 - sq) / 2}
            for k, b, sq in steps]}
    summary["rest"] = {"stages": {
        "own": {"bytes": 0.0, "ssim_object": 0.8, "flip": 0.1},
        "correction": {"bytes": 400.0, "ssim_object": 0.85, "flip": 0.075},
        "layer1": {"bytes": 2000.0, "ssim_object": 0.95, "flip": 0.025},
        "exact": {"bytes": 30000.0, "ssim_object": 1.0, "flip": 0.0, "png_bytes": 40000.0,
                  "webp_lossless_bytes": 27000.0}}}
    return SimpleNamespace(rd=rd, views=views, info={"rd_views": 8}, summary=lambda: summary)


@pytest.mark.parametrize("plot", ["_rd_plot", "_per_view_plot", "_rest_plot"])
def test_report_legends_cover_no_axis_title_and_no_data(plot, tmp_path, monkeypatch):
    """The legend covered the axis title in rd.png and data points in per_view.png: every
    legend lies outside both plots' data areas and clear of their axis titles."""
    import matplotlib.pyplot as plt

    from host.evaluate import report

    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: None)  # keep the figure to measure it
    before = set(plt.get_fignums())
    getattr(report, plot)(_report_evaluation(), tmp_path / "plot.png")
    (number,) = set(plt.get_fignums()) - before
    fig = plt.figure(number)
    try:
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend())]
        assert len(legends) == 1
        box = legends[0].get_window_extent(renderer)
        for ax in fig.axes:
            assert not box.overlaps(ax.get_window_extent(renderer)), plot
            for title in (ax.xaxis.label, ax.yaxis.label):
                assert not box.overlaps(title.get_window_extent(renderer)), (plot, title)
    finally:
        close(fig)
