"""Depth-aware view synthesis as a product (issue 15): render --depth, fit --depth, the
image's synthesis record, the device's refusal of unknown methods, and the device showing
exactly the host's warped frames. The warp itself on synthetic scenes: test_warp_views.py."""

from __future__ import annotations

import itertools
import subprocess
import sys
import time

import numpy as np
import pytest
from provision_helpers import KEY, REPO, DeviceProcess
from runtime_helpers import read_frames, steady_requests, wait_until

from device_runtime.image_receiver import image_problem, required_ram_bytes
from device_runtime.reconstruct import Reconstructor
from device_runtime.runtime import LoadedModel
from device_runtime.standalone import StandaloneScores
from device_runtime.synthesis import ViewSynthesizer
from host.cli import main as eigencast
from host.fit.model import HostModel
from host.link.options import ProvisionOptions, ProvisionParts
from host.link.provisioning import provision
from host.render.cinema import CinemaDB, depth_file
from protocol.errors import ImageFormatError
from protocol.image import read_image, read_manifest, write_image
from protocol.keys import write_key

VIEWS = "grid:24x6"


@pytest.fixture(scope="module")
def depth_db(tmp_path_factory):
    db = tmp_path_factory.mktemp("depth") / "tooth.cdb"
    assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", VIEWS, "--size", "48",
                      "--samples", "80", "--depth"]) == 0
    return db


@pytest.fixture(scope="module")
def depth_model(depth_db):
    key = depth_db.parent / "device.key"
    write_key(key, KEY, force=True)
    out = depth_db.parent / "tooth.ecs"
    assert eigencast(["fit", str(depth_db), "-o", str(out), "--cell", "12", "--threshold",
                      "0.99", "--depth", "--key", str(key)]) == 0
    return out


def test_render_depth_stores_half_resolution_depth_and_resumes(tmp_path, capsys):
    db = tmp_path / "t.cdb"
    args = ["render", "builtin:tooth", "-o", str(db), "--views", "grid:6x3", "--size", "32",
            "--samples", "60", "--depth"]
    assert eigencast(args) == 0
    opened = CinemaDB.open(db)
    assert opened.depth is not None and opened.depth_shape == (16, 16)
    first = [opened.read_depth(i) for i in range(opened.n_views)]
    assert all(np.isfinite(d).any() and np.isnan(d).any() for d in first)
    # depths are distances from the camera: around the camera distance
    finite = np.concatenate([d[np.isfinite(d)] for d in first])
    assert abs(float(np.median(finite)) - opened.depth["offset_mm"]) < 0.5 * (
        opened.depth["offset_mm"])
    (db / depth_file(opened.files[2])).unlink()  # depth lost: the view is rendered again
    (db / depth_file(opened.files[5])).write_bytes(b"garbage")  # corrupt: rendered again
    (db / opened.files[7]).unlink()  # PNG lost
    capsys.readouterr()
    assert eigencast(args) == 0
    err = capsys.readouterr().err
    assert "15 valid images kept, 3 to render" in err
    again = CinemaDB.open(db)
    for i in range(again.n_views):
        np.testing.assert_array_equal(again.read_depth(i), first[i])


def test_render_depth_is_refused_in_one_line_where_it_cannot_work(tmp_path, capsys):
    """Asked for (--depth), depth the warp cannot use is refused; by default such a render
    goes on without depth and says so in one line."""
    base = ["render", "builtin:tooth", "--views", "grid:4x3", "--samples", "40"]
    for name, setting, why in (("a", ["--size", "33"], "odd image size"),
                               ("b", ["--size", "32", "--projection", "orthographic"],
                                "orthographic projection"),
                               ("c", ["--size", "32", "--background", "0,0,1"], "not black")):
        assert eigencast([*base, "-o", str(tmp_path / f"{name}.cdb"), *setting, "--depth"]) != 0
        err = capsys.readouterr().err.strip()
        assert why in err and len(err.splitlines()) == 1
        assert eigencast([*base, "-o", str(tmp_path / f"{name}.cdb"), *setting]) == 0
        captured = capsys.readouterr()
        note = [line for line in captured.err.splitlines() if "no depth maps" in line]
        assert len(note) == 1 and why in note[0] and "blend" in note[0]
        assert "no depth" in captured.out
        assert CinemaDB.open(tmp_path / f"{name}.cdb").depth is None


def test_resuming_a_database_begun_without_depth_keeps_it_so(tmp_path, capsys):
    """A database begun without depth (before depth was the default, or --no-depth) resumes
    without it instead of rendering every view again; --depth does add it."""
    db = tmp_path / "old.cdb"
    args = ["render", "builtin:tooth", "-o", str(db), "--views", "grid:4x3", "--size", "32",
            "--samples", "40"]
    assert eigencast([*args, "--no-depth"]) == 0
    (db / "images" / "view_00003.png").unlink()
    capsys.readouterr()
    assert eigencast(args) == 0
    captured = capsys.readouterr()
    assert "rendered without depth so far" in captured.err
    assert "(1 rendered, 11 reused), no depth" in captured.out
    assert CinemaDB.open(db).depth is None
    assert eigencast([*args, "--depth"]) == 0
    assert "(12 rendered, 0 reused), with depth" in capsys.readouterr().out
    assert CinemaDB.open(db).depth is not None


def test_fit_depth_without_depth_maps_is_a_one_line_error(tooth_db, tmp_path, capsys):
    assert eigencast(["fit", str(tooth_db), "-o", str(tmp_path / "m.ecs"), "--depth"]) != 0
    err = capsys.readouterr().err.strip()
    assert "has no depth maps" in err and "eigencast render" in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "m.ecs").exists()


def test_fit_depth_stores_the_depth_eigenspace_and_names_the_method(depth_model, depth_db):
    image = read_image(depth_model, key=KEY)
    assert image.synthesis["method"] == "warp-depth-3"  # the warp with the noise floor
    assert read_manifest(depth_model)["synthesis"]["method"] == "warp-depth-3"
    assert image.synthesis["splat_tent"] in (6, 14, 30, 62)
    assert image.sections["noise_floor"].shape == (image.n_cells,)
    assert {"depth_counts", "depth_scales", "depth_mean", "depth_components"} <= set(
        image.sections)
    # one table: plain or delta-coded, whichever compresses smaller
    assert len({"depth_scores", "depth_scores_delta"} & set(image.sections)) == 1
    from device_runtime.synthesis import DepthEigenspace

    depth = DepthEigenspace.from_image(image)
    db = CinemaDB.open(depth_db)
    errors, others = [], []
    for i in (0, 40, 100):
        truth = db.read_depth(i)
        ok = np.isfinite(truth)
        errors.append(np.abs(depth.reconstruct(i)[ok] - truth[ok]).mean())
        others.append(np.abs(depth.reconstruct(i + 2)[ok] - truth[ok]).mean())
    # a tooth of radius ~11 mm at 24x24 depth pixels: within a mm, and each view's own
    # scores, not a neighbour's (30 degrees away) -- the table is in the views' order
    assert max(errors) < 1.0 and max(errors) < 0.5 * min(others), (errors, others)


def test_unknown_synthesis_method_is_refused_in_one_line(depth_model, tmp_path):
    image = read_image(depth_model, key=KEY)
    image.synthesis = {**image.synthesis, "method": "warp-depth-9"}
    forged = tmp_path / "forged.ecs"
    write_image(forged, image, key=KEY)
    with pytest.raises(ImageFormatError, match=r"warp-depth-9.*unknown to this device"):
        required_ram_bytes(read_manifest(forged))
    with open(forged, "rb") as f:
        problem = image_problem(f, key=KEY, ram_budget_bytes=1 << 30)
    assert problem is not None and "unknown to this device" in problem
    assert "\n" not in problem
    with open(depth_model, "rb") as f:
        assert image_problem(f, key=KEY, ram_budget_bytes=1 << 30) is None


def test_synthesis_beyond_the_warps_float32_indexing_is_refused_in_one_line(depth_model):
    from device_runtime.synthesis import MAX_WARP_PIXELS, check_synthesis

    record = dict(read_image(depth_model, key=KEY).synthesis)
    assert check_synthesis(record) is record
    side = int(MAX_WARP_PIXELS ** 0.5) // 2  # frames of 2 * side: the padded grid is over
    with pytest.raises(ImageFormatError, match=r"beyond this device's warp"):
        check_synthesis({**record, "depth_shape": [side, side]})
    check_synthesis({**record, "depth_shape": [side - 2, side - 2]})  # just inside


def test_an_image_without_depth_loads_and_shows_as_before(model_path):
    manifest = read_manifest(model_path)
    assert "synthesis" not in manifest  # nothing written: older devices see the same bytes
    image = read_image(model_path, key=KEY)
    assert image.synthesis is None
    loaded = LoadedModel.build(image, slot="A", generation=1, test=False, want_standalone=True)
    try:
        assert loaded.synthesis is None and loaded.standalone is not None
    finally:
        loaded.close()


def test_warping_a_training_view_to_its_own_camera_gives_its_reconstruction(depth_model,
                                                                            depth_db):
    image = read_image(depth_model, key=KEY)
    synth = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
    db = CinemaDB.open(depth_db)
    tent = image.synthesis["splat_tent"]
    for i in (7, 60, 130):
        frame = synth.frame(float(db.phi_deg[i]), float(db.theta_deg[i]))
        own = Reconstructor.from_image(image).update(synth.standalone.training_scores(i))
        obj = own.max(axis=2) > 2
        # every pixel lands on itself (whatever its depth: the same ray), so the frame is
        # the reconstruction, with the pixels at or below their cell's noise floor black,
        # through the splat filter, computed here apart
        shown = own * (own.max(axis=2) > _floor_per_pixel(image))[..., None]
        diff = np.abs(frame.astype(float) - _tent_normalised(shown.astype(float), obj, tent))
        assert diff[obj].mean() < 1.0, diff[obj].mean()
    misses = synth.misses
    synth.frame(float(db.phi_deg[7]) + 1.0, float(db.theta_deg[7]) + 1.0)
    synth.frame(float(db.phi_deg[7]) + 2.0, float(db.theta_deg[7]) + 1.0)
    assert synth.misses - misses <= 4  # neighbours cached between frames of one drag


def test_the_view_cache_keeps_a_frames_neighbours_and_evicts_only_others(depth_model):
    """A cache of 4 views (`CACHE_VIEWS`) along a drag: a frame reconstructs exactly its
    neighbours that are not cached, and never evicts one neighbour for another."""
    from device_runtime.synthesis import CACHE_VIEWS

    assert CACHE_VIEWS == 4
    image = read_image(depth_model, key=KEY)
    synth = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
    seen = set()
    rng = np.random.default_rng(3)
    view = (7.0, -30.0)
    for step in range(60):  # a drag that turns back and forth across grid lines
        view = ((view[0] + rng.uniform(-12.0, 16.0)) % 360.0,
                float(np.clip(view[1] + rng.uniform(-8.0, 9.0), -75.0, 75.0)))
        need = {int(i) for i in synth.neighbours(*view)[0]}
        cached = set(synth._cache)
        misses = synth.misses
        synth.frame(*view)
        assert synth.misses - misses == len(need - cached), (step, need, cached)
        assert need <= set(synth._cache) and len(synth._cache) <= CACHE_VIEWS
        seen |= need
    assert len(seen) > 2 * CACHE_VIEWS  # the drag crossed several grid cells


def test_depth_reconstruction_is_the_eigenspace_sum_and_only_the_cells_asked(depth_model):
    """Each depth cell is its mean plus its components times their scores (float64 here),
    and a miss' reconstruction of the cells under the object only is the full one there."""
    from device_runtime.synthesis import merge_cells

    image = read_image(depth_model, key=KEY)
    eig = synthesis_depth(image)
    ends = np.cumsum(eig.counts)
    for view in (0, 33, 101):
        coef = eig.scales.astype(np.float64) * eig.table[view] * eig.step
        cells = eig.mean.astype(np.float64)
        for c in range(eig.counts.size):
            a, b = ends[c] - eig.counts[c], ends[c]
            cells[c] += coef[a:b] @ eig.components[a:b].astype(np.float64)
        want = merge_cells(cells, eig.cell, eig.padded)[:eig.shape[0], :eig.shape[1]]
        full = eig.reconstruct(view)
        np.testing.assert_allclose(full, want + eig.offset, rtol=0, atol=1e-3)
        some = np.zeros(eig.counts.size, bool)
        some[::3] = True
        part = eig.reconstruct(view, some)
        cell_of = merge_cells(np.repeat(np.arange(eig.counts.size)[:, None], eig.cell ** 2, 1),
                              eig.cell, eig.padded)[:eig.shape[0], :eig.shape[1]]
        np.testing.assert_array_equal(part[some[cell_of]], full[some[cell_of]])
        assert not np.array_equal(part, full)  # the others were not reconstructed


def test_the_cells_a_miss_needs_cover_every_depth_the_upsampling_reads(depth_model):
    from device_runtime.synthesis import upsample2, upsample2_at

    image = read_image(depth_model, key=KEY)
    eig = synthesis_depth(image)
    h, w = image.image_shape
    rng = np.random.default_rng(5)
    obj = np.zeros((h, w), bool)
    obj[rng.integers(0, h, 12), rng.integers(0, w, 12)] = True
    obj[h // 3:h // 2, w // 4:w // 3] = True
    need = eig.needed_cells(obj)
    assert 0 < need.sum() < need.size
    src = np.flatnonzero(obj)
    for view in (4, 77):
        np.testing.assert_array_equal(upsample2_at(eig.reconstruct(view, need), src, w),
                                      upsample2(eig.reconstruct(view)).reshape(-1)[src])


def synthesis_depth(image):
    from device_runtime.synthesis import DepthEigenspace

    return DepthEigenspace.from_image(image)


def test_standalone_and_served_devices_warp_on_a_worker_with_its_own_reconstructor(
        depth_model):
    """Both kinds of device make their warps on a worker thread (the display never waits on
    one), with a reconstructor of its own beside the display's blends and host frames."""
    for mode in ("want_standalone", "want_predictor"):
        loaded = LoadedModel.build(read_image(depth_model, key=KEY), slot="A", generation=1,
                                   test=False, **{mode: True})
        try:
            assert loaded.warp_worker is not None, mode
            assert loaded.warp_worker.synthesis is loaded.synthesis
            assert loaded.synthesis.reconstructor is not loaded.reconstructor
        finally:
            loaded.close()


def _tent_normalised(img, covered, centre=6):
    """[1, c, 1] / (c + 2) in y and x over the covered pixels (zero outside), normalised
    (c = 6: [1/8, 3/4, 1/8])."""
    k = np.array([1.0, centre, 1.0]) / (centre + 2)
    h, w = covered.shape

    def filt(a):
        t = sum(k[i] * a[i:i + h] for i in range(3))
        return sum(k[j] * t[:, j:j + w] for j in range(3))

    num = filt(np.pad(img * covered[..., None], ((1, 1), (1, 1), (0, 0))))
    return num / np.maximum(filt(np.pad(covered.astype(float), 1)), 1e-12)[..., None]


def _with_splat_tent(depth_model, tmp_path, tent):
    """depth_model rewritten as if its fit had chosen the splat filter ``tent`` and measured
    no noise floor (``warp-depth-2``, as fits wrote it before the floor)."""
    image = read_image(depth_model, key=KEY)
    image.synthesis = {**image.synthesis, "method": "warp-depth-2", "splat_tent": tent}
    del image.sections["noise_floor"]
    out = tmp_path / f"tent{tent}.ecs"
    write_image(out, image, key=KEY)
    return out


def test_the_splat_filter_an_image_names_is_checked_and_warps_its_frames(depth_model, depth_db,
                                                                         tmp_path):
    """An image whose fit chose another splat filter (``warp-depth-2``, ``splat_tent``):
    the device warps with it, the host's frames are the device's, a training view warped to
    its own camera is its reconstruction through [1, c, 1] / (c + 2), and a record naming a
    filter the device does not know, or one without its method, is refused in one line."""
    from device_runtime.synthesis import check_synthesis
    from host.evaluate.warp import WarpFrames

    path = _with_splat_tent(depth_model, tmp_path, 30)
    image = read_image(path, key=KEY)
    loaded = LoadedModel.build(image, slot="A", generation=1, test=False, want_standalone=True)
    plain = ViewSynthesizer(read_image(depth_model, key=KEY),
                            StandaloneScores(read_image(depth_model, key=KEY)),
                            Reconstructor.from_image(read_image(depth_model, key=KEY)))
    try:
        assert loaded.synthesis.warper.tent == 30
        assert plain.warper.tent == read_image(depth_model, key=KEY).synthesis["splat_tent"]
        host = WarpFrames(HostModel.load(path))
        for view in ((12.5, 3.0), (100.0, -44.0)):
            frame = loaded.synthesis.frame(*view)
            np.testing.assert_array_equal(frame, host.frame(*view))
            assert np.abs(frame.astype(int) - plain.frame(*view)).max() > 0
        db = CinemaDB.open(depth_db)
        for i in (7, 60):
            frame = loaded.synthesis.frame(float(db.phi_deg[i]), float(db.theta_deg[i]))
            own = Reconstructor.from_image(image).update(
                loaded.synthesis.standalone.training_scores(i))
            obj = own.max(axis=2) > 2
            diff = np.abs(frame.astype(float) - _tent_normalised(own.astype(float), obj, 30))
            assert diff[obj].mean() < 1.0, diff[obj].mean()
    finally:
        loaded.close()
    record = image.synthesis
    for bad, why in (({**record, "splat_tent": 7}, "must be one of 6, 14, 30, 62"),
                     ({**record, "splat_tent": True}, "must be one of"),
                     ({k: v for k, v in record.items() if k != "splat_tent"}, "must be one of"),
                     ({**record, "method": "warp-depth-1"}, "belongs to method 'warp-depth-2'")):
        with pytest.raises(ImageFormatError, match=why) as err:
            check_synthesis(bad)
        assert "\n" not in str(err.value)


def test_fit_chooses_the_splat_filter_on_its_training_views_and_leaves_the_image_whole(
        depth_model, depth_db, monkeypatch):
    """`choose_splat_tent` warps training views from their row neighbours with each filter,
    keeps the default unless another beats it by the margin (the most spreading of filters
    tied with the best), and leaves every section as it was; a chosen filter is written as
    ``warp-depth-2``, and any filter of an image with the noise floor as ``warp-depth-3``."""
    import host.evaluate.splat_filter as splat
    from device_runtime.synthesis import SPLAT_TENTS

    pick = splat.pick_splat_tent
    assert pick({6: 0.80, 14: 0.81, 30: 0.8105, 62: 0.811}) == 14  # tied: the most spread
    assert pick({6: 0.80, 14: 0.801, 30: 0.8015, 62: 0.80}) == 6  # not by the margin
    assert pick({6: 0.80, 14: 0.79, 30: 0.78, 62: 0.77}) == 6
    assert pick({6: 0.80, 14: 0.80, 30: 0.81, 62: 0.83}) == 62
    db = CinemaDB.open(depth_db)
    for floored in (False, True):  # an image without the noise floor, then one with
        image = read_image(depth_model, key=KEY)
        if not floored:
            del image.sections["noise_floor"]
        before = {k: v.copy() for k, v in image.sections.items()}
        found = splat.choose_splat_tent(image, db, views=12, quiet=True)
        assert found["views"] == 12 and set(found["ssim"]) == set(SPLAT_TENTS)
        assert all(0.0 < v <= 1.0 for v in found["ssim"].values())
        assert found["tent"] == pick(found["ssim"])
        if floored:  # the warp with the floor names its filter, the default included
            assert image.synthesis["method"] == "warp-depth-3"
            assert image.synthesis["splat_tent"] == found["tent"]
        else:
            assert image.synthesis["method"] == ("warp-depth-1" if found["tent"] == 6
                                                 else "warp-depth-2")
        assert set(image.sections) == set(before)
        for k, v in before.items():
            np.testing.assert_array_equal(image.sections[k], v)
        with monkeypatch.context() as m:
            m.setattr(splat, "pick_splat_tent", lambda means, margin: 14)
            assert splat.choose_splat_tent(image, db, views=4, quiet=True)["tent"] == 14
            assert image.synthesis["method"] == ("warp-depth-3" if floored else "warp-depth-2")
            assert image.synthesis["splat_tent"] == 14
            m.setattr(splat, "pick_splat_tent", lambda means, margin: 6)
            splat.choose_splat_tent(image, db, views=4, quiet=True)  # chosen again: the default
        if floored:
            assert image.synthesis["method"] == "warp-depth-3"
            assert image.synthesis["splat_tent"] == 6
        else:
            assert image.synthesis["method"] == "warp-depth-1"
            assert "splat_tent" not in image.synthesis
    # row neighbours: each view between its previous and next in phi on its theta row
    phi = np.array([0.0, 90.0, 180.0, 270.0, 45.0, 10.0])
    theta = np.array([0.0, 0.0, 0.0, 0.0, 30.0, 60.0])
    triples = splat._row_triples(phi, theta, 10)
    assert [(v, pair) for v, pair, _ in triples] == [(0, (3, 1)), (1, (0, 2)), (2, (1, 3)),
                                                     (3, (2, 0))]
    assert all(np.allclose(w, 0.5) for _, _, w in triples)
    assert splat._row_triples(phi[4:], theta[4:], 10) == []  # no row of three: no choice


def test_standalone_device_shows_the_hosts_warped_frames(depth_model, tmp_path):
    """eigencast-device --standalone with a depth image shows exactly evaluate's pca_warp
    frames, which differ from the blended frames of the same image."""
    from host.evaluate.warp import WarpFrames

    flash = tmp_path / "flash"
    key = depth_model.parent / "device.key"
    device = DeviceProcess(flash, "--headless", key_file=key)
    try:
        provision(depth_model, device.url, ProvisionOptions(key=KEY, show_progress=False),
                  ProvisionParts(log=lambda _: None))
    finally:
        device.stop()
    frames = tmp_path / "frames"
    views = "12.5,3;100,-44;250,20;-1,0"
    run = subprocess.run([sys.executable, "-m", "device_runtime.cli", "--standalone", "--flash",
                          str(flash), "--key", str(key), "--headless", "--frames", str(frames),
                          "--views", views], capture_output=True, text=True, timeout=120,
                         cwd=REPO)
    assert run.returncode == 0, run.stderr
    # each view's blend while its warp is made, then the warp: every view is warped, in order
    rows = [row for row in read_frames(frames) if row["kind"] == "warp"]
    assert len(rows) == 4
    model = HostModel.load(depth_model)
    warp = WarpFrames(model)
    from PIL import Image

    differs = 0
    for row in rows:
        got = np.asarray(Image.open(frames / row["file"]))
        phi, theta = float(row["phi_deg"]), float(row["theta_deg"])
        np.testing.assert_array_equal(got, warp.frame(phi, theta))
        differs += int(np.abs(got.astype(int) - model.view(phi, theta)).max() > 8)
    assert differs >= 3
    # `eigencast view` at the views as the user typed them is the device's frame, bit for bit
    for k, pair in enumerate(views.split(";"), start=1):
        phi, theta = pair.split(",")
        png = tmp_path / f"view{k}.png"
        run = subprocess.run([sys.executable, "-m", "host.cli", "view", str(depth_model),
                              "--phi", phi, "--theta", theta, "-o", str(png)],
                             capture_output=True, text=True, timeout=120, cwd=REPO)
        assert run.returncode == 0 and "depth warp" in run.stdout, run.stderr
        np.testing.assert_array_equal(np.asarray(Image.open(png)),
                                      np.asarray(Image.open(frames / rows[k - 1]["file"])))
    assert eigencast(["view", str(depth_model), "--phi", "100", "--theta", "-44", "--blend",
                      "-o", str(tmp_path / "blend.png")]) == 0
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "blend.png")),
                                  model.view(100.0, -44.0))


def test_a_views_frame_is_the_same_whatever_the_cache_the_reconstructor_and_the_thread(
        depth_model):
    """`ViewSynthesizer.frame` is a function of the image and the view: a synthesizer that
    made other views first (its cache and its reconstructor's last cells differ), a fresh
    one per view, one with a lean reconstructor (a warp worker's: one thread, little
    scratch) or one with two threads, on another thread, all give the same bits. A host
    computes the device's frame this way (evaluate's pca_warp; a correction added to it)."""
    import threading

    from device_runtime.synthesis import WORKER_SCRATCH_BYTES

    image = read_image(depth_model, key=KEY)
    views = [(3.0, 14.0), (7.5, 14.5), (12.0, 17.9), (12.0, 18.0), (200.0, -40.0),
             (201.0, -38.0), (3.0, 14.0)]
    along = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
    drag = [along.frame(*v) for v in views]
    assert along.misses < 4 * len(views)  # the cache was used
    for i, view in enumerate(views):
        fresh = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
        np.testing.assert_array_equal(fresh.frame(*view), drag[i])
    lean = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(
        image, threads=1, scratch_bytes=WORKER_SCRATCH_BYTES))
    two = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(
        image, threads=2, scratch_bytes=4 << 20))
    got: dict[str, list] = {}

    def run(name, synth):
        got[name] = [synth.frame(*v) for v in reversed(views)]

    threads = [threading.Thread(target=run, args=a) for a in (("lean", lean), ("two", two))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    two.reconstructor.close()
    for name in ("lean", "two"):
        for a, b in zip(got[name], reversed(drag)):
            np.testing.assert_array_equal(a, b)
    assert any(not np.array_equal(a, b) for a, b in itertools.pairwise(drag))


def test_row_weights_warp_one_row_away_from_the_middle_and_fade_continuously():
    from device_runtime.synthesis import ROW_RAMP, row_weights

    theta = np.array([12.0, 12.0, 24.0, 24.0])
    # the bilinear weights of a view 3 degrees above row 12 (a quarter of the way to 24)
    w = np.array([0.6, 0.15, 0.2, 0.05])
    out = row_weights(theta, w)
    np.testing.assert_allclose(out, [0.8, 0.2, 0.0, 0.0])  # one row, its proportions kept
    assert row_weights(theta, w * 3.0).sum() == pytest.approx(3.0)  # the total kept
    # at the middle nothing changes; just past the ramp the far row comes in from 0
    mid = np.array([0.3, 0.2, 0.3, 0.2])
    np.testing.assert_allclose(row_weights(theta, mid), mid)
    prev = None
    for share in np.linspace(0.0, 0.5, 101):  # the far row's share of the weight
        out = row_weights(theta, np.array([0.5, 0.5, 0.5, 0.5]) * [1 - share, 1 - share,
                                                                   share, share])
        far = out[2:].sum() / out.sum()
        assert far == 0.0 if share <= ROW_RAMP else 0.0 < far <= share + 1e-12
        if prev is not None:
            assert abs(far - prev) <= 0.5 * 0.005 / (0.5 - ROW_RAMP) + 1e-9  # continuous
        prev = far
    # neighbours on one row, or on three, keep the interpolation's weights
    np.testing.assert_array_equal(row_weights(np.array([12.0, 12.0]), np.array([0.7, 0.3])),
                                  [0.7, 0.3])
    three = np.array([0.5, 0.3, 0.2])
    np.testing.assert_array_equal(row_weights(np.array([0.0, 12.0, 24.0]), three), three)


def test_a_drags_memory_stays_under_the_synthesis_declaration(depth_model):
    """tracemalloc over a drag that reconstructs neighbours (misses) and warps: everything
    the synthesis allocates beyond the image's sections (its view cache, the warp's grid and
    temporaries, a lean reconstructor's buffers and scratch, the frame) peaks under
    `synthesis_memory_bytes`, the figure a device checks against its RAM budget."""
    import tracemalloc

    from device_runtime.synthesis import WORKER_SCRATCH_BYTES, synthesis_memory_bytes

    image = read_image(depth_model, key=KEY)
    declared = synthesis_memory_bytes(read_manifest(depth_model))
    standalone = StandaloneScores(image)
    views = [(3.0 * i, 10.0 + 0.7 * i) for i in range(40)]
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        synth = ViewSynthesizer(image, standalone, Reconstructor.from_image(
            image, threads=1, scratch_bytes=WORKER_SCRATCH_BYTES))
        for view in views:
            frame = synth.frame(*view)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert synth.misses > 10 and frame.any()
    assert peak <= declared, (peak, declared)


# --------------------------------------------------------------------------- served devices


def _recorder():
    shown: list = []
    return shown, (lambda frame, info: shown.append((frame.copy(), dict(info or {}))))


def test_a_predicting_device_warps_its_own_frames_and_shows_host_frames_as_sent(
        depth_model, model_path, tmp_path):
    """Served, predicting, an image with depth: the device's own frame of a new view is the
    score blend at once, then (no newer input, no host frame) the warp (evaluate's pca_warp,
    bit for bit); a host frame after it is exactly the host's
    reconstruction (the warp must not leave pixels in the reconstructor's buffer, which
    recomputes only the cells whose scores changed). Without depth, or with --no-predict,
    nothing warps."""
    from device_runtime.device import DeviceConfig
    from device_runtime.prediction import corrected
    from device_runtime.runtime import RuntimeDevice
    from host.evaluate.warp import WarpFrames

    image = read_image(depth_model, key=KEY)
    warp = WarpFrames(HostModel.load(depth_model))
    shown, on_frame = _recorder()
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY), predict=True,
                           view=(37.0, 11.0), on_frame=on_frame, log=lambda _: None)
    loaded = LoadedModel.build(image, slot="A", generation=1, test=False, want_predictor=True)
    try:
        assert loaded.synthesis is not None
        assert loaded.synthesis.standalone is loaded.predictor.standalone  # one table
        blend = Reconstructor.from_image(image)
        device._swap_model(loaded)  # the image's first frame: its own prediction, the blend
        np.testing.assert_array_equal(shown[-1][0],
                                      blend.update(loaded.predictor(37.0, 11.0)))
        assert shown[-1][1].get("predicted") and not shown[-1][1].get("synthesized")
        assert loaded.warp_worker is not None
        device._show_due_warp(loaded, timeout_s=30)  # then the worker's warp
        np.testing.assert_array_equal(shown[-1][0], warp.frame(37.0, 11.0))
        assert shown[-1][1].get("predicted") and shown[-1][1].get("synthesized")
        device._show_due_warp(loaded)  # once only
        assert len(shown) == 2
        # a host frame for that view (a correction): the host's reconstruction, not warped
        y = corrected(loaded.predictor(37.0, 11.0),
                      np.linspace(-1, 1, image.n_coefficients).astype(np.float32))
        want = Reconstructor.from_image(image).update(y).copy()
        device._present(loaded, y, {"phi_deg": 37.0, "theta_deg": 11.0, "corrected": True})
        np.testing.assert_array_equal(shown[-1][0], want)
        assert not shown[-1][1].get("synthesized")
        device.set_view(161.0, -23.0)  # the user moves: the blend, then the warp
        device._view_dirty = False  # (what the display loop does before it predicts)
        device._show_view(loaded, time.monotonic())
        np.testing.assert_array_equal(shown[-1][0],
                                      blend.update(loaded.predictor(161.0, -23.0)))
        device._show_due_warp(loaded, timeout_s=30)
        np.testing.assert_array_equal(shown[-1][0], warp.frame(161.0, -23.0))
        np.testing.assert_array_equal(device._shown_frame, shown[-1][0])  # what redraws show
        assert np.abs(shown[-1][0].astype(int) - want).max() > 8
        # the same host scores again (an orbit packet, sequence 0): the host's frame exactly
        device._present(loaded, y, {"phi_deg": 37.0, "theta_deg": 11.0, "sequence": 0})
        np.testing.assert_array_equal(shown[-1][0], want)
        stats = device.runtime_stats.as_dict()
        assert stats["synthesized_frames"] == 2 and stats["predicted_frames"] == 2
        # a warp whose view the user has left since its blend is not shown
        device._show_view(loaded, time.monotonic())
        assert loaded.warp_worker.take(device.view, timeout_s=30) is not None  # it was made
        loaded.shown.warp_due = device.view
        device.set_view(200.0, 5.0)
        before = len(shown)
        device._show_due_warp(loaded, timeout_s=30)
        assert len(shown) == before and loaded.shown.warp_due is None
        # a host frame for the view before its warp: the warp is not shown after it
        device._view_dirty = False
        device._show_view(loaded, time.monotonic())
        loaded.shown.warp_due = None  # (what the display loop does when the host frame came)
        device._show_due_warp(loaded, timeout_s=30)
        assert len(shown) == before + 1 and not shown[-1][1].get("synthesized")
        assert "warp 2" in device.overlay_lines()[1]
    finally:
        device.close()
        loaded.close()
    # --no-predict with depth, and a predicting device without depth: no synthesis
    plain = LoadedModel.build(image, slot="A", generation=1, test=False)
    no_depth = LoadedModel.build(read_image(model_path, key=KEY), slot="A", generation=1,
                                 test=False, want_predictor=True)
    try:
        assert plain.synthesis is None and plain.predictor is None
        assert no_depth.synthesis is None and no_depth.predictor is not None
        shown, on_frame = _recorder()
        device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash2", key=KEY),
                               predict=True, view=(37.0, 11.0), on_frame=on_frame,
                               log=lambda _: None)
        try:
            device._swap_model(no_depth)
            want = Reconstructor.from_image(no_depth.image).update(
                no_depth.predictor(37.0, 11.0))
            np.testing.assert_array_equal(shown[-1][0], want)  # the score blend, as before
            assert device.runtime_stats.synthesized_frames == 0
        finally:
            device.close()
    finally:
        plain.close()
        no_depth.close()


def test_a_predicting_device_shows_at_most_one_blend_per_display_refresh(depth_model,
                                                                      tmp_path):
    """A view that moves on every turn of the display loop (a clock-driven orbit, a fast
    drag) gets one blend per display refresh (60 Hz), not one per turn: with a warp due the
    loop turns every few milliseconds, and a blend on each took the cores from the warp and
    the link."""
    from device_runtime.device import DeviceConfig
    from device_runtime.orbit import parse_orbit
    from device_runtime.runtime import RuntimeDevice

    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY), predict=True,
                           view=(0.0, 15.0), orbit=parse_orbit("turn:2:15:1"),
                           log=lambda _: None)
    loaded = LoadedModel.build(read_image(depth_model, key=KEY), slot="A", generation=1,
                               test=False, want_predictor=True)
    device._models.put(loaded)
    t0 = time.monotonic()
    try:
        device.run_display()
    finally:
        loaded.close()
    elapsed = time.monotonic() - t0
    stats = device.runtime_stats.as_dict()
    assert stats["predicted_frames"] >= 5  # the orbit moved and was shown
    # the first frame, then one per refresh at most (a loaded machine shows fewer, not more)
    assert stats["predicted_frames"] <= elapsed / device.tick_s + 2, (stats, elapsed)


def test_a_warp_superseded_by_a_newer_view_is_given_up(depth_model):
    """The worker gives up the warp in flight when another view is asked (the display
    would drop it anyway), makes the newer one, and keeps the neighbours it already made;
    asking the same view again does not restart it."""
    import threading

    from device_runtime.warp_worker import WarpWorker
    from device_runtime.warping import WarpCancelled

    first, second = (10.0, 5.0), (40.0, -20.0)
    started = threading.Event()

    class Slow:  # a warp of `first` that takes until it is cancelled (or 30 s)
        def frame(self, phi, theta, cancel=None):
            if (phi, theta) == first:
                started.set()
                end = time.monotonic() + 30.0
                while time.monotonic() < end:
                    if cancel():
                        raise WarpCancelled
                    time.sleep(0.001)  # the work being simulated, not a wait for a race
                return np.zeros((2, 2, 3), np.uint8)
            return np.full((2, 2, 3), 7, np.uint8)

    worker = WarpWorker(Slow())
    try:
        worker.request(first)
        assert started.wait(10)
        worker.request(first)  # the same view: not a reason to start again
        worker.request(second)
        got = worker.take(second, timeout_s=10.0)
        assert got is not None and got[0, 0, 0] == 7
        assert worker.cancelled == 1 and worker.made == 1 and worker.errors == 0
    finally:
        worker.close()
    # the real synthesizer: a cancel after the first miss keeps that neighbour cached
    image = read_image(depth_model, key=KEY)
    synth = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
    calls = []

    def cancel_on_second_ask():
        calls.append(1)
        return len(calls) >= 2

    with pytest.raises(WarpCancelled):
        synth.frame(123.0, 17.0, cancel=cancel_on_second_ask)
    assert synth.misses == 1 and len(synth._cache) == 1
    whole = synth.frame(123.0, 17.0)  # the rest made now, the same frame as uncancelled
    fresh = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
    np.testing.assert_array_equal(whole, fresh.frame(123.0, 17.0))
    with pytest.raises(WarpCancelled):  # inside the warp: every neighbour is cached now
        synth.frame(123.0, 17.0, cancel=lambda: True)


def test_the_warp_worker_holds_a_view_only_while_views_come_faster_than_warps():
    from device_runtime.warp_worker import WarpWorker

    hold = WarpWorker.hold_for
    assert hold(None, 0.016) == 0.0 and hold(0.04, None) == 0.0  # first warp; at rest
    assert hold(0.010, 0.016) == 0.0  # a warp fits between two requests: start at once
    assert hold(0.040, 0.016) == pytest.approx(0.032)  # 2 intervals: has the drag stopped?
    assert hold(0.020, 0.016) == pytest.approx(0.020)  # never longer than a warp


class _Sleepy:
    """A synthesizer whose warps take ``work_s`` (checking ``cancel``) and record what
    they were started for; the frame's first pixel holds the view's phi."""

    def __init__(self, work_s):
        self.work_s, self.started = work_s, []

    def frame(self, phi, theta, cancel=None):
        from device_runtime.synthesis import WarpCancelled

        self.started.append((phi, theta))
        end = time.monotonic() + self.work_s
        while time.monotonic() < end:
            if cancel is not None and cancel():
                raise WarpCancelled
            time.sleep(0.001)  # the work being simulated, not a wait for a race
        return np.full((2, 2, 3), int(phi) % 256, np.uint8)


def test_a_fast_drag_starts_no_warps_nobody_would_see_and_the_last_view_is_made():
    """Views asked every 2 ms of warps that take 60 ms: after the first warps tell the
    worker how long a warp takes, the requests are replaced before theirs start; once the
    drag stops, the last view's warp is made."""
    from device_runtime.warp_worker import WarpWorker

    synth = _Sleepy(0.06)
    worker = WarpWorker(synth)
    try:
        worker.request((0.0, 10.0))
        assert worker.take((0.0, 10.0), timeout_s=10.0) is not None  # learns a warp's time
        views = [(float(i), 10.0) for i in range(1, 301)]
        for view in views:
            worker.request(view)
            time.sleep(0.002)  # the drag's pace (the input being simulated)
        got = worker.take(views[-1], timeout_s=10.0)
        assert got is not None and got[0, 0, 0] == 300 % 256
        started = len(synth.started) - 1
        # the old worker started every one (each given up at the next request)
        assert worker.skipped > 200 and started < 100, (worker.skipped, started)
        assert synth.started[-1] == views[-1]
    finally:
        worker.close()


def test_a_drag_that_begins_while_the_neighbours_are_made_is_warped_once_they_are():
    """The first warp of a drag makes neighbours and is given up late for the next view:
    that is no warp's time (the neighbours stay cached), so the views after it are not
    held but warped (the worker used to hold every view of the drag until it stopped)."""
    from device_runtime.warp_worker import WarpWorker
    from device_runtime.warping import WarpCancelled

    class Cold(_Sleepy):
        misses = 0

        def frame(self, phi, theta, cancel=None):
            if self.misses:
                return super().frame(phi, theta, cancel)
            self.started.append((phi, theta))
            self.misses += 1  # a neighbour made, then the warp goes on until given up
            while not cancel():
                time.sleep(0.001)  # the work being simulated, not a wait for a race
            raise WarpCancelled

    synth = Cold(0.0)
    worker = WarpWorker(synth)
    try:
        worker.request((0.0, 10.0))
        time.sleep(0.05)  # the cold warp's work before the drag's next view
        views = [(float(i), 10.0) for i in range(1, 41)]
        for view in views:
            worker.request(view)
            time.sleep(0.005)  # the drag's pace (the input being simulated)
        assert worker.take(views[-1], timeout_s=10.0) is not None
        assert worker.cancelled == 1 and worker.warp_s is not None and worker.warp_s < 0.05
        assert len(synth.started) > 30 and worker.skipped < 10, (synth.started, worker.skipped)
    finally:
        worker.close()


def test_a_held_drag_measures_a_warp_again_and_warps_once_warps_are_quick():
    """The worker's estimate came from a slow warp (its neighbours made, another motion);
    views then come every 5 ms and each warp takes 1 ms. Held views are replaced unstarted,
    but a probe starts every `PROBE_S`, measures a quick warp, and the views after it are
    warped (the worker used to hold every view until the motion stopped)."""
    from device_runtime.warp_worker import WarpWorker

    synth = _Sleepy(0.001)
    worker = WarpWorker(synth)
    try:
        worker.request((0.0, 10.0))
        assert worker.take((0.0, 10.0), timeout_s=10.0) is not None
        worker.warp_s = 0.06  # as if that warp had made its neighbours
        views = [(float(i), 10.0) for i in range(1, 301)]
        for view in views:
            worker.request(view)
            time.sleep(0.005)  # the drag's pace (the input being simulated)
        assert worker.take(views[-1], timeout_s=10.0) is not None
        started = len(synth.started) - 1
        assert started > 150 and worker.warp_s < 0.005, (worker.warp_s, started)
    finally:
        worker.close()


def test_take_with_a_timeout_gets_a_held_or_unasked_view_at_once():
    """A caller that needs a view's frame (a host correction for it arrived) does not wait
    out the hold, and gets a view nobody asked for too."""
    from device_runtime.warp_worker import WarpWorker

    synth = _Sleepy(0.0)
    worker = WarpWorker(synth)
    try:
        worker.warp_s, worker.interval_s = 100.0, 60.0  # a hold of 90 s
        worker._last_request_t = time.monotonic()
        worker.request((7.0, 1.0))
        assert worker.hold_s() > 60.0
        got = worker.take((7.0, 1.0), timeout_s=30.0)
        assert got is not None and got[0, 0, 0] == 7
        got = worker.take((9.0, 2.0), timeout_s=30.0)  # never requested
        assert got is not None and got[0, 0, 0] == 9
        assert synth.started == [(7.0, 1.0), (9.0, 2.0)]
    finally:
        worker.close()


def test_the_next_view_of_steady_motion_is_predicted_exactly():
    """Evenly paced requests on a line in angle predict the next canonical view (also
    across 360 and at steps float32 cannot hold); a hand's uneven drag, a pause or a view
    at rest predict nothing."""
    from device_runtime.orbit import canonical_view
    from device_runtime.warp_worker import WarpWorker

    predict = WarpWorker.predicted_view

    def steady(start, step, theta=15.0, n=3):
        return [(0.1 * i, *canonical_view(start + step * i, theta)) for i in range(n)]

    assert predict(steady(10.0, 3.0)) == canonical_view(19.0, 15.0)
    assert predict(steady(355.0, 3.0)) == canonical_view(364.0, 15.0)  # across 360
    assert predict(steady(300.0, -2.5)) == canonical_view(292.5, 15.0)
    hits = sum(predict(steady(17.3 + 3.0 * k, 3.0)) == canonical_view(17.3 + 3.0 * (k + 3), 15.0)
               for k in range(100))
    assert hits >= 90  # float32 rounding of the views: the least-squares line averages it
    assert predict(steady(10.0, 3.0)[:2]) is None  # too few
    assert predict([(0.0, 10.0, 15.0), (0.1, 13.0, 15.0), (0.2, 19.0, 15.0)]) is None  # uneven
    assert predict([(0.0, 10.0, 15.0), (0.1, 13.0, 15.0), (0.5, 16.0, 15.0)]) is None  # pause
    assert predict([(0.0, 10.0, 15.0), (0.1, 10.0, 15.0), (0.2, 10.0, 15.0)]) is None  # at rest


def test_an_idle_worker_warps_the_next_view_of_steady_motion_ahead(depth_model):
    """During an orbit the worker warps the predicted next view while the current one is on
    show: asked for, it is there at once, bit for bit the view's frame; a view asked that
    was not predicted gives the guess up and is made as before."""
    from device_runtime.orbit import canonical_view
    from device_runtime.warp_worker import WarpWorker

    image = read_image(depth_model, key=KEY)
    fresh = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
    worker = WarpWorker(ViewSynthesizer(image, StandaloneScores(image),
                                        Reconstructor.from_image(image)))
    views = [canonical_view(40.0 + 3.0 * i, 12.0) for i in range(5)]
    try:
        for v in views[:3]:
            worker.request(v)
            assert worker.take(v, timeout_s=30.0) is not None
        steady_requests(worker, views[:3])
        wait_until(lambda: worker._ahead is not None, 30, "the warp made ahead")
        assert worker._ahead[0] == views[3] and worker.ahead_made == 1
        # the same motion's view a float32 step off is that view; one a degree off is not
        step = float(np.spacing(np.float32(views[3][0])))
        assert worker.snap((views[3][0] + step, views[3][1])) == views[3]
        assert worker.snap((views[3][0] + 1.0, views[3][1])) != views[3]
        worker.request(views[3])
        got = worker.take(views[3])  # no timeout: made already
        assert got is not None and worker.ahead_used == 1
        np.testing.assert_array_equal(got, fresh.frame(*views[3]))
        # a guess nobody asks for: another view is made, the guess is given up
        steady_requests(worker, views[1:4])
        wait_until(lambda: worker._ahead is not None, 30, "the second warp made ahead")
        assert worker._ahead[0] == views[4]
        other = canonical_view(200.0, -30.0)
        worker.request(other)
        assert worker._ahead is None
        got = worker.take(other, timeout_s=30.0)
        np.testing.assert_array_equal(got, fresh.frame(*other))
        assert worker.ahead_used == 1 and worker.errors == 0
    finally:
        worker.close()


# ----------------------------------------------------------------------------- depth storage


def _depth_fit(depth_db, thresholds=(0.99,), score_mse=0.05):
    from host.fit.depth import fill_nearest, fit_depth_eigenspaces

    db = CinemaDB.open(depth_db)
    depths = np.stack([fill_nearest(db.read_depth(i)) for i in range(db.n_views)])
    return db, depths, fit_depth_eigenspaces(depths, list(thresholds),
                                             float(db.depth["offset_mm"]), score_mse=score_mse)


def _with_depth_sections(image, eig, *, delta):
    """A copy of ``image`` holding ``eig`` as fit --depth stores it (plain or delta table)."""
    import dataclasses

    from device_runtime.standalone import standalone_order
    from host.fit.depth import depth_sections

    sections = {k: v for k, v in image.sections.items() if not k.startswith("depth_")}
    order = standalone_order(image, image.interpolation["n_views"]) if delta else None
    sections.update(depth_sections(eig, order))
    synthesis = {**image.synthesis, "depth_step": eig.step}
    return dataclasses.replace(image, sections=sections, synthesis=synthesis)


def test_delta_coded_depth_table_loads_as_the_plain_one(depth_model, depth_db, tmp_path):
    """The delta-coded depth table (depth_scores_delta) written to an .ecs and read back
    decodes to the fitted table; an image with the plain table (the first depth images)
    still loads; both show the same warped frames."""
    from device_runtime.synthesis import DepthEigenspace

    image = read_image(depth_model, key=KEY)
    _, _, fits = _depth_fit(depth_db)
    eig = fits[0.99]
    frames = []
    for delta in (True, False):
        path = tmp_path / f"d{int(delta)}.ecs"
        write_image(path, _with_depth_sections(image, eig, delta=delta), key=KEY)
        back = read_image(path, key=KEY)
        name = "depth_scores_delta" if delta else "depth_scores"
        assert name in back.sections and len(
            {"depth_scores", "depth_scores_delta"} & set(back.sections)) == 1
        if delta:
            assert back.sections[name].dtype == np.uint8
        loaded = DepthEigenspace.from_image(back)
        np.testing.assert_array_equal(loaded.table, eig.table)
        np.testing.assert_array_equal(loaded.reconstruct(5), eig.reconstruct(5))
        synth = ViewSynthesizer(back, StandaloneScores(back), Reconstructor.from_image(back))
        frames.append(synth.frame(33.0, 12.0))
    np.testing.assert_array_equal(frames[0], frames[1])


def test_depth_table_sections_that_disagree_are_refused_in_one_line(depth_model, depth_db):
    from device_runtime.synthesis import DepthEigenspace

    image = read_image(depth_model, key=KEY)
    _, _, fits = _depth_fit(depth_db)
    both = _with_depth_sections(image, fits[0.99], delta=True)
    both.sections["depth_scores"] = fits[0.99].table
    with pytest.raises(ImageFormatError, match="both present") as exc:
        DepthEigenspace.from_image(both)
    assert "\n" not in str(exc.value)
    short = _with_depth_sections(image, fits[0.99], delta=True)
    short.sections["depth_scores_delta"] = short.sections["depth_scores_delta"][:, :, :-1]
    with pytest.raises(ImageFormatError, match=r"depth_scores_delta.*expected uint8") as exc:
        DepthEigenspace.from_image(short)
    assert "\n" not in str(exc.value)


def test_coarse_depth_table_adds_its_noise_and_drops_unused_components(depth_db):
    """quantize_depth_table's rounding adds about its noise (mm^2 per pixel) to the depth
    maps, and the components whose score rounds to 0 in every view are gone without
    changing any map."""
    from host.fit.depth import drop_unused, quantize_depth_table

    _, _, fits = _depth_fit(depth_db, thresholds=(0.999,), score_mse=0.001)
    fine = fits[0.999]
    for noise in (0.5, 4.0):
        coarse = quantize_depth_table(fine, noise)
        added = np.mean([np.mean((coarse.reconstruct(i) - fine.reconstruct(i)) ** 2)
                         for i in range(0, fine.table.shape[0], 7)])
        assert 0.2 * noise < added < 1.5 * noise, (noise, added)
        assert (coarse.table != 0).any(axis=0).all()  # no all-zero column is kept
    coarse = quantize_depth_table(fine, 4.0)
    assert coarse.n_components < fine.n_components
    from device_runtime.synthesis import DepthEigenspace

    kept = DepthEigenspace(fine.cell, fine.shape, fine.mean, fine.components, fine.scales,
                           fine.counts, np.rint(fine.table * fine.step / coarse.step).astype(
                               np.int16), coarse.step, fine.offset)
    assert drop_unused(kept).n_components == coarse.n_components
    for i in (0, 50, 99):
        np.testing.assert_allclose(coarse.reconstruct(i), kept.reconstruct(i), atol=1e-3)


def test_fit_depth_default_rounds_to_a_fifth_of_the_z_tolerance_in_the_smaller_coding(
        depth_model, depth_db):
    """fit --depth's default table: rounding noise DEPTH_SCORE_NOISE_Z2 squared z-test
    tolerances (the first images had 0.05 mm^2: a step 3x finer on the tooth), stored in
    whichever coding (plain or delta) compresses smaller."""
    import zstandard

    from device_runtime.standalone import standalone_order
    from device_runtime.synthesis import DepthEigenspace
    from host.fit.depth import DEPTH_SCORE_NOISE_Z2, depth_sections, depth_table_step

    image = read_image(depth_model, key=KEY)
    noise = DEPTH_SCORE_NOISE_Z2 * image.synthesis["z_tolerance_mm"] ** 2
    _, _, fits = _depth_fit(depth_db, thresholds=(0.99,), score_mse=0.001)
    fine = fits[0.99]
    assert image.synthesis["depth_step"] == pytest.approx(
        depth_table_step(fine.counts, fine.cell, noise), rel=1e-6)
    def packed(a):
        return len(zstandard.ZstdCompressor(level=3).compress(np.ascontiguousarray(a).tobytes()))

    # before the load: the device decodes the delta-coded table in place
    stored = {k: packed(v) for k, v in image.sections.items() if k.startswith("depth_scores")}
    depth = DepthEigenspace.from_image(image)
    added = np.mean([np.mean((depth.reconstruct(i) - fine.reconstruct(i)) ** 2)
                     for i in range(0, depth.table.shape[0], 5)])
    assert 0.2 * noise < added < 1.5 * noise, (noise, added)

    plain = packed(depth_sections(depth)["depth_scores"])
    delta = packed(depth_sections(depth, standalone_order(image, depth.table.shape[0]))[
        "depth_scores_delta"])
    name = "depth_scores_delta" if delta < plain else "depth_scores"
    assert list(stored) == [name] and stored[name] == min(plain, delta)


# ----------------------------------------------------------------------------- noise floor


def _floor_per_pixel(image):
    """The image's noise floor (one per colour cell) at every pixel, uint8 (h, w)."""
    (h, w), (ch, cw), (ny, nx) = image.image_shape, image.cell_shape, image.grid_shape
    cells = image.sections["noise_floor"].reshape(ny, nx)
    return np.kron(cells, np.ones((ch, cw), np.uint8))[:h, :w]


def _without_floor(depth_model):
    """depth_model as fits wrote it before the noise floor: the same eigenspaces and splat
    filter (``warp-depth-2``), no floor section."""
    image = read_image(depth_model, key=KEY)
    image.synthesis = {**image.synthesis, "method": "warp-depth-2"}
    del image.sections["noise_floor"]
    return image


def test_the_own_frame_paints_no_haze_where_the_ray_cast_is_black(depth_model):
    """The device's own frame of novel views (the depth warp) is black where the ray-cast is
    black away from the object: more than 2 pixels from it (beyond the reach of the splat
    filter and the depth's upsampling), at most 1 % of those pixels show anything (above
    `OBJECT_LEVEL`). The same image warped without its noise floor (as fits wrote it
    before) painted the eigenspace's haze there on 5 % of them."""
    from scipy.ndimage import binary_dilation

    from device_runtime.prediction import OwnFrames, prediction_view
    from device_runtime.synthesis import OBJECT_LEVEL
    from host.render.settings import RenderSettings, ViewRenderer

    model = HostModel.load(depth_model)
    scene = ViewRenderer.open(RenderSettings.from_record(model.render_settings, what="test"))
    frames = {"floor": OwnFrames(model.image), "none": OwnFrames(_without_floor(depth_model))}
    assert frames["floor"].warps and frames["none"].warps
    painted = {k: 0 for k in frames}
    far_px = 0
    for phi, theta in zip(np.linspace(5.0, 355.0, 12), np.linspace(-50.0, 50.0, 12)):
        view = prediction_view(float(phi), float(theta))
        truth, _ = scene.render(*view)
        far = ~binary_dilation(truth.max(axis=2) > 0, np.ones((3, 3), bool), iterations=2)
        far_px += int(far.sum())
        for k, own in frames.items():
            painted[k] += int((far & (own.frame(*view).max(axis=2) > OBJECT_LEVEL)).sum())
    assert painted["floor"] <= 0.01 * far_px, (painted, far_px)
    assert painted["none"] > 0.03 * far_px, (painted, far_px)  # the haze this test is about


def test_a_training_view_warps_with_the_pixels_at_or_below_the_noise_floor_black(depth_model,
                                                                               depth_db):
    """``warp-depth-3``: every pixel of a training view above `OBJECT_LEVEL` is warped, those
    at or below their cell's floor black (their points stay: the neighbour still says where
    its picture is black); an image of the older methods warps every colour, with or
    without the section."""
    from device_runtime.synthesis import OBJECT_LEVEL, noise_levels

    image = read_image(depth_model, key=KEY)
    synth = ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
    older = _without_floor(depth_model)
    bare = ViewSynthesizer(older, StandaloneScores(older), Reconstructor.from_image(older))
    np.testing.assert_array_equal(synth.noise_level, _floor_per_pixel(image))
    assert bare.noise_level is None
    db = CinemaDB.open(depth_db)
    black = 0
    for i in (7, 60, 130):
        colour = Reconstructor.from_image(image).update(synth.standalone.training_scores(i))
        top = colour.max(axis=2)
        points, rgb = synth.view_cloud(i)
        kept, old_rgb = bare.view_cloud(i)
        np.testing.assert_array_equal(points, kept)  # the same points: all above OBJECT_LEVEL
        assert points.shape[1] == int((top > OBJECT_LEVEL).sum())
        dim = top[top > OBJECT_LEVEL] <= _floor_per_pixel(image)[top > OBJECT_LEVEL]
        assert not rgb[:, dim].any()
        np.testing.assert_array_equal(rgb[:, ~dim], old_rgb[:, ~dim])
        black += int(dim.sum())
        view = (float(db.phi_deg[i]) + 2.0, float(db.theta_deg[i]))
        assert np.abs(synth.frame(*view).astype(int) - bare.frame(*view)).max() > 0
    assert black > 0
    # the older methods ignore a section they do not know
    kept = read_image(depth_model, key=KEY)
    kept.synthesis = {**kept.synthesis, "method": "warp-depth-2"}
    assert noise_levels(kept, kept.synthesis) is None


def test_a_floor_image_without_a_good_floor_section_is_refused_in_one_line(depth_model):
    """``warp-depth-3`` needs its section, uint8, one value per colour cell."""
    cases = []
    image = read_image(depth_model, key=KEY)
    del image.sections["noise_floor"]
    cases.append((image, "needs the section 'noise_floor'"))
    for bad in (lambda f: f.astype(np.int16), lambda f: f[:-1]):
        image = read_image(depth_model, key=KEY)
        image.sections["noise_floor"] = bad(image.sections["noise_floor"])
        cases.append((image, "expected uint8 of shape"))
    for image, why in cases:
        with pytest.raises(ImageFormatError, match=why) as err:
            ViewSynthesizer(image, StandaloneScores(image), Reconstructor.from_image(image))
        assert "\n" not in str(err.value)


def test_the_noise_floor_is_the_level_at_or_below_which_black_is_closest_to_the_renderings(
        depth_model, depth_db):
    """`measure_noise_floor` (what fit --depth stores): per cell, the level at or below which
    the training views' reconstructions shown black are closest (squared error) to their
    renderings; `OBJECT_LEVEL` where the object never is. Checked here by summing the
    errors of whole floors directly: the fit's floor beats no floor and the floor moved a
    few levels either way."""
    from device_runtime.synthesis import OBJECT_LEVEL
    from host.fit.floor import measure_noise_floor

    image = read_image(depth_model, key=KEY)
    db = CinemaDB.open(depth_db)
    found = measure_noise_floor(image, db, views=None, progress=False)
    assert found.views == db.n_views
    np.testing.assert_array_equal(found.floor, image.sections["noise_floor"])
    assert found.floor.min() >= OBJECT_LEVEL and found.floor.max() > OBJECT_LEVEL
    table = StandaloneScores(read_image(depth_model, key=KEY))
    rec = Reconstructor.from_image(image)
    views = [(rec.update(table.training_scores(i)).astype(np.int64),
              db.read_image(i).astype(np.int64)) for i in range(db.n_views)]
    (h, w), (ch, cw), (ny, nx) = image.image_shape, image.cell_shape, image.grid_shape
    empty = np.ones((ny * ch, nx * cw), bool)
    for _, truth in views:
        empty[:h, :w] &= truth.max(axis=2) == 0
    never = empty.reshape(ny, ch, nx, cw).all(axis=(1, 3)).ravel()
    assert never.any() and (found.floor[never] == OBJECT_LEVEL).all()

    def error(floor):
        level = np.kron(floor.reshape(ny, nx), np.ones((ch, cw), np.int64))[:h, :w]
        return sum(int((((r * (r.max(axis=2) > level)[..., None]) - t) ** 2).sum())
                   for r, t in views)

    best = error(found.floor.astype(np.int64))
    assert best < error(np.full(found.floor.shape, OBJECT_LEVEL))
    for shift in (-3, -1, 1, 3):
        assert best <= error(np.maximum(found.floor.astype(np.int64) + shift, OBJECT_LEVEL))


def test_the_floor_of_a_cell_is_its_best_summed_gain_above_the_object_level():
    from host.fit.floor import FLOOR_LEVELS, floor_from_gains

    gains = np.zeros((4, FLOOR_LEVELS))
    gains[1, [0, 1, 2]] = 100.0  # at or below OBJECT_LEVEL: not the floor's to take
    gains[2, [5, 7, 10]] = (3.0, -2.0, 4.0)  # 3 at 5, 1 at 7..9, 5 at 10
    gains[3, [4, 6]] = (2.0, -5.0)
    gains[3, 9] = 3.0  # 2 at 4, -3 at 6, 0 at 9: the best is 4
    np.testing.assert_array_equal(floor_from_gains(gains), [2, 2, 10, 4])
    assert floor_from_gains(gains).dtype == np.uint8
    gains[2, 11] = -1.0
    gains[2, 12] = 1.0  # 5 again at 12: ties take the smaller level
    assert floor_from_gains(gains)[2] == 10


def test_steady_motion_faster_than_a_warp_is_led_by_warps_made_ahead():
    """Views come every 5 ms along a straight line and a warp takes 12 ms: a held view's
    warp would be gone before it is shown, so the worker warps the view as many steps ahead
    as a warp takes; those frames are there when their views are asked. (The old worker
    held every view, and its probes were given up at the next request: no warp was seen
    until the motion stopped.)"""
    from device_runtime.warp_worker import WarpWorker

    synth = _Sleepy(0.012)
    worker = WarpWorker(synth)
    try:
        worker.request((0.0, 10.0))
        assert worker.take((0.0, 10.0), timeout_s=10.0) is not None  # learns a warp's time
        views = [(float(i), 10.0) for i in range(1, 201)]
        used = 0
        for view in views:
            worker.request(view)
            used += worker.take(view) is not None  # the display's tick
            time.sleep(0.005)  # the motion's pace (the input being simulated)
        assert worker.ahead_used >= 20 and used >= 20, (worker.ahead_used, used)
        # every view warped (ahead or not) lay on the motion's line, one of its steps
        assert all(abs(theta - 10.0) < 1e-3 and abs(phi - round(phi)) < 1e-3
                   and 1 <= round(phi) <= 200 + WarpWorker.LEAD_STEPS
                   for phi, theta in synth.started[1:]), synth.started
    finally:
        worker.close()


def test_a_cold_warp_that_made_its_neighbours_does_not_hold_the_motion_after_it():
    """The first warp makes its neighbours (60 ms); the warps after it take 1 ms. That cold
    warp is no warp's time: views then asked every 5 ms are warped, not held. (The old worker
    took 60 ms as a warp's time and held every view of an unsteady drag until a probe.)"""
    from device_runtime.warp_worker import WarpWorker

    class ColdOnce(_Sleepy):
        misses = 0

        def frame(self, phi, theta, cancel=None):
            if not self.misses:
                self.misses += 1
                time.sleep(0.06)  # making the neighbours (the work being simulated)
            return super().frame(phi, theta, cancel)

    synth = ColdOnce(0.001)
    worker = WarpWorker(synth)
    try:
        worker.request((0.0, 10.0))
        assert worker.take((0.0, 10.0), timeout_s=10.0) is not None
        assert worker.warp_s is None
        # an unsteady drag (no line to warp ahead on): growing steps
        views = [(0.05 * i * i, 10.0) for i in range(1, 81)]
        for view in views:
            worker.request(view)
            time.sleep(0.005)  # the drag's pace (the input being simulated)
        assert len(synth.started) > 50 and worker.skipped < 20, (synth.started,
                                                                   worker.skipped)
    finally:
        worker.close()
