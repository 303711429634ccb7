"""World-fixed lighting: closed forms, the Monte Carlo reference, determinism, records, CLI."""

from __future__ import annotations

import dataclasses
import json
import math

import numba
import numpy as np
import pytest

from host.cli import main
from host.commands._render_options import LIGHTING_NAMES
from host.render import lighting as lighting_module
from host.render.camera import View, orbit_camera
from host.render.cinema import SIDECAR, CinemaDB
from host.render.lighting import LIGHTINGS, Lighting, light_field, lighting_from_record
from host.render.lighting_reference import render_lighting_reference, transmittance_reference
from host.render.raycast import LUT_SIZE, Renderer
from host.render.settings import RenderSettings, SettingsError, ViewRenderer
from host.render.transfer import TransferFunction
from host.volume import Volume

CINEMATIC = LIGHTINGS["cinematic"]


def constant_tf(alpha: float, rgb=(0.8, 0.7, 0.6)) -> TransferFunction:
    return TransferFunction(name="constant", color_points=np.array([[0.0, *rgb], [1.0, *rgb]]),
                            opacity_points=np.array([[0.0, alpha], [1.0, alpha]]),
                            window=(0.0, 1.0))


def two_tissue_tf() -> TransferFunction:
    """u ~ 0.5: a translucent blue 'soft tissue' (alpha 0.08 per unit); u ~ 1: an opaque
    sandy 'bone' (alpha 0.9)."""
    return TransferFunction(
        name="two-tissue",
        color_points=np.array([[0.0, 0.5, 0.7, 0.9], [0.55, 0.5, 0.7, 0.9], [0.8, 0.9, 0.8, 0.6],
                               [1.0, 0.9, 0.8, 0.6]]),
        opacity_points=np.array([[0.0, 0.0], [0.3, 0.0], [0.45, 0.08], [0.6, 0.08],
                                 [0.8, 0.9], [1.0, 0.9]]),
        window=(0.0, 1.0),
    )


def linear_tissue_tf() -> TransferFunction:
    """`two_tissue_tf` whose soft-tissue opacity grows linearly from u = 0 (so a ball's
    one-voxel edge, where u ramps, attenuates as a sharp ball of the nominal radius would)."""
    return TransferFunction(
        name="linear-tissue", color_points=two_tissue_tf().color_points,
        opacity_points=np.array([[0.0, 0.0], [0.5, 0.08], [0.6, 0.08], [0.8, 0.9],
                                 [1.0, 0.9]]),
        window=(0.0, 1.0),
    )


def sphere_over_slab(shape=(32, 32, 32), center=(16.0, 16.0, 19.0), radius=8.5) -> Volume:
    """A translucent ball (u = 0.5) above an opaque slab (u = 1, z in [2, 7]), edges one
    voxel wide, spacing 1 mm; shape is (nz, ny, nx), centre (x, y, z)."""
    z, y, x = np.mgrid[0:shape[0], 0:shape[1], 0:shape[2]].astype(np.float64)
    slab = np.clip(7.5 - z, 0, 1) * np.clip(z - 1.5, 0, 1)
    r = np.sqrt((x - center[0]) ** 2 + (y - center[1]) ** 2 + (z - center[2]) ** 2)
    ball = np.clip(radius + 0.5 - r, 0, 1)
    return Volume(np.maximum(slab, 0.5 * ball).astype(np.float32))


def lit(name="test", **changes) -> Lighting:
    return dataclasses.replace(CINEMATIC, name=name, **changes)


def sigma_of(alpha: float, unit_mm: float) -> float:
    return -math.log1p(-alpha) / unit_mm


def exit_distance(points: np.ndarray, direction: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance from each point to the box [0, hi] along ``direction`` (slab method)."""
    with np.errstate(divide="ignore"):
        t = np.where(direction > 0, (hi - points) / direction,
                     np.where(direction < 0, -points / direction, np.inf))
    return t.min(axis=1)


# --------------------------------------------------------------------------- closed forms
@pytest.mark.parametrize("direction, atol_tau", [((0.0, 90.0), 1e-5), ((30.0, 40.0), 0.06)])
def test_transmittance_of_a_homogeneous_box_is_beer_lambert(direction, atol_tau):
    """Light straight up: the optical depth is linear in z, so the light field and its
    trilinear reading are exact; oblique: exact but where the light field is read across
    a plane on which the light's exit face changes (a kink the trilinear reading rounds)."""
    volume = Volume(np.full((20, 16, 18), 0.5, dtype=np.float32), spacing=(1.0, 1.5, 0.8))
    alpha = 0.05
    lighting = lit(light_phi_deg=direction[0], light_theta_deg=direction[1])
    renderer = Renderer(volume, constant_tf(alpha), samples=100, lighting=lighting)
    rng = np.random.default_rng(0)
    hi = np.asarray(volume.extent_mm)
    points = rng.uniform(0.0, 1.0, (400, 3)) * hi
    light = lighting.direction()
    start = points + lighting.shadow_bias * 0.8 * light
    inside = np.all((start >= 0) & (start <= hi), axis=1)
    length = np.where(inside, exit_distance(np.clip(start, 0, hi), light, hi), 0.0)
    expected_tau = sigma_of(alpha, 0.8) * length
    tau = -np.log(renderer.light_transmittance(points))
    error = np.abs(tau - expected_tau)
    assert np.median(error) <= 1e-5 and error.max() <= atol_tau
    assert expected_tau.max() > 0.8 and inside.mean() > 0.5  # a real test: deep shadows too
    # the Monte Carlo reference's ratio tracking gives the same transmittance
    mean, stderr = transmittance_reference(volume, constant_tf(alpha), points[:40],
                                           lighting=lighting, paths=400, window=(0.0, 1.0))
    assert np.all(np.abs(mean - np.exp(-expected_tau[:40])) <= 4 * stderr + 1e-9)


def test_a_homogeneous_spheres_shadow_on_a_slab_follows_its_chord():
    """Light from 45 degrees: the shadow of a ball of extinction sigma on the slab is
    ``exp(-sigma * chord)``, ``chord = 2 sqrt(R^2 - rho^2)`` at distance rho from the ray
    through the centre; seen from straight above (orthographic, ambient and highlight off)
    the slab's colour is the lit colour times that."""
    volume = sphere_over_slab(shape=(28, 32, 48), center=(12.0, 16.0, 19.0), radius=6.0)
    lighting = lit(light_phi_deg=180.0, light_theta_deg=45.0, ambient=0.0, scattering=0.0,
                   specular=0.0)
    renderer = Renderer(volume, linear_tissue_tf(), samples=400, lighting=lighting)
    light = lighting.direction()
    centre = np.array([12.0, 16.0, 19.0])
    sigma = sigma_of(0.08, 1.0)

    def closed_form(points):
        rel = points - centre
        rho = np.linalg.norm(rel - (rel @ light)[:, None] * light, axis=1)
        chord = 2.0 * np.sqrt(np.clip(6.0**2 - rho**2, 0.0, None))
        return np.exp(-sigma * chord), rho

    # 1. the transmittance on the slab's top, where the shadow falls
    xs, ys = np.meshgrid(np.linspace(20.0, 40.0, 41), np.linspace(8.0, 24.0, 33))
    top = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 6.5)], axis=1)
    expected, rho = closed_form(top)
    got = renderer.light_transmittance(top)
    beside = np.median(got[rho > 7.5])  # light through the slab's own soft top only
    assert np.all(np.abs(got[rho > 7.5] - beside) < 0.005) and beside > 0.9
    core = rho < 4.5  # away from the rim, where a voxel of blur moves the chord most
    assert expected[core].min() < 0.45  # a deep shadow
    np.testing.assert_allclose(-np.log(got[core] / beside), -np.log(expected[core]),
                               rtol=0.05)
    # 2. the image: the slab's colour relative to its unshadowed colour
    camera = orbit_camera(View(0.0, 90.0), volume.center_mm, volume.radius_mm,
                          projection="orthographic")
    image = renderer.render(camera, 64, 64)
    origins, directions = camera.rays(64, 64)
    hit = origins + ((6.5 - origins[..., 2]) / directions[..., 2])[..., None] * directions
    pix_expected, pix_rho = closed_form(hit.reshape(-1, 3))
    ball_free = np.linalg.norm((hit - centre)[..., :2], axis=-1).ravel() > 7.5  # not under it
    inside = (np.all((hit[..., :2] > 2) & (hit[..., :2] < [45, 29]), axis=-1)).ravel()
    luminance = image[..., 0].ravel()
    lit_level = np.median(luminance[ball_free & inside & (pix_rho > 7.5)])
    core = ball_free & inside & (pix_rho < 4.5)
    assert core.sum() > 20
    np.testing.assert_allclose(luminance[core] / lit_level, pix_expected[core], atol=0.05)


def test_a_light_fixed_in_the_world_stays_on_the_object():
    """A ball lit from +x: the camera on +x sees its lit face, the one on -x its dark
    face; the headlight shows both the same."""
    z, y, x = np.mgrid[0:24, 0:24, 0:24].astype(np.float64)
    ball = np.clip(8.5 - np.sqrt((x - 11.5) ** 2 + (y - 11.5) ** 2 + (z - 11.5) ** 2), 0, 1)
    volume = Volume(ball.astype(np.float32))
    tf = constant_tf(0.0)
    tf = TransferFunction(name="ball", color_points=tf.color_points,
                          opacity_points=np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.9],
                                                   [1.0, 0.9]]), window=(0.0, 1.0))
    world = Renderer(volume, tf, samples=200, lighting=lit(light_phi_deg=0.0,
                                                           light_theta_deg=0.0))
    head = Renderer(volume, tf, samples=200)

    def brightness(renderer, phi):
        camera = orbit_camera(View(phi, 0.0), volume.center_mm, volume.radius_mm)
        return float(renderer.render(camera, 32, 32)[..., :3].mean())

    assert brightness(world, 0.0) > 2.0 * brightness(world, 180.0)
    assert brightness(head, 0.0) == pytest.approx(brightness(head, 180.0), rel=0.02)


# --------------------------------------------------------------------------- the reference
def _scene():
    volume = sphere_over_slab()
    camera = orbit_camera(View(200.0, 35.0), volume.center_mm, volume.radius_mm,
                          projection="orthographic")
    return volume, two_tissue_tf(), camera


def _compare(fast: np.ndarray, mean: np.ndarray, stderr: np.ndarray) -> dict[str, float]:
    d = (fast.astype(np.float64) - mean)[..., :3]
    return {"bias": float(np.abs(d.mean(axis=(0, 1))).max()),
            "mean_abs": float(np.abs(d).mean() - stderr[..., :3].mean()),
            "excess": float((np.abs(d) - 4.0 * stderr[..., :3]).max())}


#: The bound of docs/lighting.md: per channel mean difference, mean absolute difference
#: beyond the reference's own standard error, and the largest difference beyond four
#: standard errors of any pixel (colours in [0, 1]).
BOUND = {"bias": 0.003, "mean_abs": 0.002, "excess": 0.1}


@pytest.mark.parametrize("look", ["key light only", "cinematic"])
def test_the_renderer_agrees_with_the_monte_carlo_reference(look):
    volume, tf, camera = _scene()
    lighting = lit(light_phi_deg=0.0, light_theta_deg=60.0)
    if look == "key light only":
        lighting = dataclasses.replace(lighting, ambient=0.0, scattering=0.0)
    renderer = Renderer(volume, tf, samples=300, lighting=lighting)
    fast = renderer.render(camera, 24, 24)
    field = light_field(renderer._u, tf.lut(LUT_SIZE), renderer._block_empty, 8,
                        volume.spacing, lighting) if lighting.ambient else None
    mean, stderr = render_lighting_reference(volume, tf, camera, 24, 24, lighting=lighting,
                                             paths_per_pixel=512, seed=3, window=(0.0, 1.0),
                                             field=field)
    assert mean[..., :3].max() < 1.0  # the clamp never acts: the estimate is unbiased
    assert (mean[..., 3] > 0.5).mean() > 0.2  # the scene covers the image
    found = _compare(fast, mean, stderr)
    assert all(found[k] <= BOUND[k] for k in BOUND), found
    # and the comparison would see a wrong light: the shadow falls elsewhere
    other = Renderer(volume, tf, samples=300,
                     lighting=dataclasses.replace(lighting, light_phi_deg=180.0))
    wrong = _compare(other.render(camera, 24, 24), mean, stderr)
    assert wrong["mean_abs"] > 3 * BOUND["mean_abs"] and wrong["excess"] > 2 * BOUND["excess"]


# --------------------------------------------------------------------------- properties
def test_lighting_changes_colours_only_and_every_kernel_agrees():
    volume, tf, camera = _scene()
    head = Renderer(volume, tf, samples=200)
    world = Renderer(volume, tf, samples=200, lighting="cinematic")
    rgba_h, depth_h = head.render_with_depth(camera, 30, 26)
    rgba_w, depth_w = world.render_with_depth(camera, 30, 26)
    np.testing.assert_array_equal(rgba_h[..., 3], rgba_w[..., 3])
    np.testing.assert_array_equal(depth_h, depth_w)
    assert np.abs(rgba_h[..., :3] - rgba_w[..., :3]).max() > 0.1
    full = world.render(camera, 30, 26)
    np.testing.assert_array_equal(full, rgba_w)  # the depth kernel shades the same
    np.testing.assert_array_equal(world.render_strided(camera, 30, 26, 3, (1, 2)),
                                  full[1::3, 2::3])


def test_deterministic_across_runs_thread_counts_and_the_cache(monkeypatch):
    volume, tf, camera = _scene()
    monkeypatch.setattr(lighting_module, "_MEMORY_CACHE", {})
    first = Renderer(volume, tf, samples=150, lighting="cinematic")
    image = first.render(camera, 27, 21)
    np.testing.assert_array_equal(image, first.render(camera, 27, 21))
    monkeypatch.setattr(lighting_module, "_MEMORY_CACHE", {})  # computed again: same bytes
    one = Renderer(volume, tf, samples=150, lighting="cinematic", workers=1)
    np.testing.assert_array_equal(image, one.render(camera, 27, 21))
    np.testing.assert_array_equal(first._field, one._field)
    assert first._field is not one._field
    if numba.config.NUMBA_NUM_THREADS > 1:
        two = Renderer(volume, tf, samples=150, lighting="cinematic", workers=2)
        np.testing.assert_array_equal(image, two.render(camera, 27, 21))


def test_the_light_field_is_computed_once_per_scene_and_cached_on_disk(tmp_path, monkeypatch):
    volume, tf, _ = _scene()
    monkeypatch.setenv("EIGENCAST_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(lighting_module, "_MEMORY_CACHE", {})
    computed = []
    original = lighting_module._compute_light_field

    def counting(*args, **kwargs):
        computed.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(lighting_module, "_compute_light_field", counting)
    a = Renderer(volume, tf, samples=100, lighting="cinematic")
    b = Renderer(volume, tf, samples=100, lighting="cinematic")  # memory
    assert len(computed) == 1 and a._field is b._field
    assert len(list(tmp_path.glob("light-field-*.npy"))) == 1
    monkeypatch.setattr(lighting_module, "_MEMORY_CACHE", {})  # a new process: the disk
    c = Renderer(volume, tf, samples=100, lighting="cinematic")
    assert len(computed) == 1
    np.testing.assert_array_equal(a._field, c._field)
    Renderer(volume, tf, samples=100, lighting=lit(light_theta_deg=10.0))  # another light
    assert len(computed) == 2 and len(list(tmp_path.glob("light-field-*.npy"))) == 2
    assert not a._field.flags.writeable  # shared: nobody may change it


def test_the_disk_cache_keeps_the_most_recently_used_within_its_bound(tmp_path, monkeypatch):
    volume, tf, _ = _scene()
    monkeypatch.setenv("EIGENCAST_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(lighting_module, "_MEMORY_CACHE", {})
    first = Renderer(volume, tf, samples=100, lighting="cinematic")
    (kept,) = tmp_path.glob("light-field-*.npy")
    monkeypatch.setattr(lighting_module, "DISK_CACHE_BYTES", kept.stat().st_size + 100)
    Renderer(volume, tf, samples=100, lighting=lit(light_theta_deg=10.0))
    (newest,) = tmp_path.glob("light-field-*.npy")  # the older one went
    assert newest != kept
    monkeypatch.setattr(lighting_module, "_MEMORY_CACHE", {})
    again = Renderer(volume, tf, samples=100, lighting="cinematic")  # computed again
    np.testing.assert_array_equal(first._field, again._field)


def test_bad_lightings_raise_value_error():
    volume, tf, _ = _scene()
    with pytest.raises(ValueError, match="expected one of headlight, cinematic"):
        Renderer(volume, tf, lighting="studio")
    with pytest.raises(ValueError, match="phase_g"):
        Renderer(volume, tf, lighting=lit(phase_g=1.0))
    with pytest.raises(ValueError, match="shading=False"):
        Renderer(volume, tf, lighting="cinematic", shading=False)
    with pytest.raises(ValueError, match="no light fixed in the world"):
        Renderer(volume, tf).light_transmittance([[1.0, 1.0, 1.0]])
    assert set(LIGHTING_NAMES) == set(LIGHTINGS)  # the CLI's choices are the looks


# --------------------------------------------------------------------------- records
def test_settings_record_the_lighting_and_rebuild_it():
    volume, tf, _ = _scene()
    renderer = Renderer(volume, tf, samples=120, lighting="cinematic")
    record = renderer.settings()["lighting"]
    assert record["name"] == "cinematic" and record["light_theta_deg"] == 50.0
    assert lighting_from_record(json.loads(json.dumps(record))) == CINEMATIC
    assert Renderer(volume, tf).settings()["lighting"] == {"name": "headlight",
                                                           "model": "headlight"}
    assert lighting_from_record(None) == LIGHTINGS["headlight"]  # old records
    with pytest.raises(ValueError, match="light field"):
        lighting_from_record({**record, "light_field": "eigencast-light-field/0"})
    with pytest.raises(ValueError, match="unknown keys"):
        lighting_from_record({**record, "lamp": 1})


def test_a_database_renders_its_views_with_its_recorded_lighting(tmp_path):
    db = tmp_path / "lit.cdb"
    args = ["render", "builtin:tooth", "-o", str(db), "--views", "list:30,10;200,-20",
            "--size", "24", "--samples", "80", "--lighting", "cinematic", "--no-depth"]
    assert main(args) == 0
    sidecar = json.loads((db / SIDECAR).read_text())
    assert sidecar["renderer"]["lighting"]["name"] == "cinematic"
    settings = RenderSettings.from_record(sidecar, what=str(db))
    assert settings.lighting == CINEMATIC
    scene = ViewRenderer.open(settings, what=str(db))

    stored = CinemaDB.open(db)
    first = next(iter(stored.iter_images()))
    np.testing.assert_array_equal(scene.render_rgb8(30.0, 10.0), first)
    # an old sidecar (no lighting recorded) reads, and resumes, as the headlight
    old = json.loads((db / SIDECAR).read_text())
    del old["renderer"]["lighting"]
    assert RenderSettings.from_record(old, what="old").lighting == LIGHTINGS["headlight"]
    broken = json.loads(json.dumps(old))
    broken["renderer"]["lighting"] = {**sidecar["renderer"]["lighting"], "phase_g": 3.0}
    with pytest.raises(SettingsError, match="phase_g"):
        RenderSettings.from_record(broken, what="broken")


def test_an_old_headlight_database_resumes(tmp_path):
    db = tmp_path / "old.cdb"
    args = ["render", "builtin:tooth", "-o", str(db), "--views", "list:30,10;200,-20",
            "--size", "24", "--samples", "60", "--no-depth"]
    assert main(args) == 0
    sidecar = json.loads((db / SIDECAR).read_text())
    del sidecar["renderer"]["lighting"]  # as a database rendered before lighting was recorded
    (db / SIDECAR).write_text(json.dumps(sidecar, indent=2, sort_keys=True) + "\n")
    (db / "images" / "view_00001.png").unlink()
    assert main(args) == 0
    assert (db / "images" / "view_00001.png").is_file()
    assert main([*args, "--lighting", "cinematic"]) == 1  # another look: not a resume


@pytest.mark.parametrize("argv, message", [
    (["--no-shading", "--lighting", "cinematic"], "--no-shading: not with --lighting"),
])
def test_bad_lighting_options_are_one_line(tmp_path, capsys, argv, message):
    code = main(["render-view", "builtin:tooth", "-o", str(tmp_path / "x.png"), "--size", "16",
                 "--samples", "20", *argv])
    err = capsys.readouterr().err.strip()
    assert code == 1 and message in err and len(err.splitlines()) == 1


def test_render_view_draws_the_chosen_look(tmp_path):
    from PIL import Image

    paths = {}
    for look in ("headlight", "cinematic"):
        paths[look] = tmp_path / f"{look}.png"
        assert main(["render-view", "builtin:head", "-o", str(paths[look]), "--size", "32",
                     "--samples", "100", "--phi", "60", "--theta", "15",
                     "--lighting", look]) == 0
    images = {k: np.asarray(Image.open(p), dtype=np.int16) for k, p in paths.items()}
    assert np.abs(images["headlight"] - images["cinematic"]).max() > 40


def test_a_model_ray_casts_novel_views_with_its_databases_lighting(tmp_path, capsys):
    """evaluate (and serve, fit --target) rebuild the renderer from the model's recorded
    settings: a cinematic model's fresh views are cinematic; --lighting is refused there."""
    from host.fit.model import HostModel, build_image, fit_database, save_model

    db = tmp_path / "lit.cdb"
    assert main(["render", "builtin:tooth", "-o", str(db), "--views", "grid:6x3", "--size",
                 "24", "--samples", "60", "--lighting", "cinematic", "--no-depth"]) == 0
    stored = CinemaDB.open(db)
    model = fit_database(stored, method="cell", cell=12, components=4, progress=False)
    path = tmp_path / "lit.ecs"
    save_model(path, *build_image(model, stored))
    settings = RenderSettings.from_record(HostModel.load(path).render_settings, what="lit")
    assert settings.lighting == CINEMATIC
    phi, theta = stored.phi_deg[4], stored.theta_deg[4]
    np.testing.assert_array_equal(ViewRenderer.open(settings).render_rgb8(phi, theta),
                                  list(stored.iter_images())[4])
    capsys.readouterr()
    assert main(["evaluate", str(path), "--views", "random:2", "--lighting", "headlight"]) == 1
    err = capsys.readouterr().err.strip()
    assert "--lighting" in err and "records its render settings" in err
    assert len(err.splitlines()) == 1


def test_fit_takes_a_test_database_of_either_age_and_refuses_another_look(tmp_path, capsys):
    """A training database rendered before lighting was recorded and a held-out one
    rendered now with the headlight are the same settings; a cinematic one is not."""
    common = ["builtin:tooth", "--size", "24", "--samples", "60", "--no-depth"]
    train, held, lit_db = tmp_path / "train.cdb", tmp_path / "held.cdb", tmp_path / "lit.cdb"
    assert main(["render", *common, "-o", str(train), "--views", "grid:8x3"]) == 0
    sidecar = json.loads((train / SIDECAR).read_text())
    del sidecar["renderer"]["lighting"]
    (train / SIDECAR).write_text(json.dumps(sidecar, indent=2, sort_keys=True) + "\n")
    assert main(["render", *common, "-o", str(held), "--views", "random:3"]) == 0
    assert main(["render", *common, "-o", str(lit_db), "--views", "random:3",
                 "--lighting", "cinematic"]) == 0
    fit = ["fit", str(train), "--target", "ssim=0.5", "--no-standalone", "--cell", "12"]
    assert main([*fit, "-o", str(tmp_path / "a.ecs"), "--test-db", str(held)]) == 0
    capsys.readouterr()
    assert main([*fit, "-o", str(tmp_path / "b.ecs"), "--test-db", str(lit_db)]) == 1
    err = capsys.readouterr().err
    assert "renderer differ" in err and len(err.strip().splitlines()) == 1
