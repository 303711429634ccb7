"""Several looks in one image: ``eigencast fit A B C`` (host/fit/looks.py), the single-look
image of each look (device_runtime/looks.py), a device switching looks, ``serve`` correcting
the look on show, and devices that predate looks refusing such an image in one line. The
format itself (versions 2 and 3, the manifest's ``looks``): test_image.py."""

from __future__ import annotations

import contextlib
import hashlib
import struct
import threading
from pathlib import Path

import numpy as np
import pytest
from provision_helpers import KEY, mem_name
from runtime_helpers import (
    TINY_LOOKS,
    TINY_VIEWS,
    RuntimeThread,
    tiny_looks_model,
    wait_until,
)

from device_runtime.device import DeviceConfig
from device_runtime.display import CycleLook, HeadlessPresenter
from device_runtime.looks import look_image, look_index, look_names
from device_runtime.prediction import OwnFrames
from device_runtime.reconstruct import Reconstructor
from device_runtime.runtime import LoadedModel, RuntimeDevice
from device_runtime.standalone import StandaloneScores
from host.cli import main as eigencast
from host.errors import FitError
from host.evaluate.warp import WarpFrames
from host.fit.model import HostModel
from host.link import provision, serve
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import ProvisionError
from host.render.cinema import CinemaDB
from protocol import image as image_format
from protocol import messages as m
from protocol.errors import ImageFormatError
from protocol.image import read_image, read_manifest
from protocol.layers import is_layer
from protocol.scores import decode_header

NAMES = tuple(name for _, name in TINY_LOOKS)
GOLDEN = Path(__file__).parent / "golden"


@pytest.fixture(scope="module")
def looks_path(tmp_path_factory):
    return tiny_looks_model(tmp_path_factory)


def _dbs(looks_path):
    return [CinemaDB.open(looks_path.parent / f"look{i}.cdb") for i in range(len(NAMES))]


def _quiet(line: str) -> None:
    pass


def test_fit_writes_one_image_whose_looks_have_their_own_eigenspaces_and_share_the_depth(
        looks_path):
    """Three databases of the same views make one version-3 image: each look its own K,
    standalone table and score step, as its database fitted alone makes them (the same
    arrays), the lighting variants sharing the depth and the other transfer function with
    its own; each look's eigenspace reconstructs its own training views, far closer than
    any other look's."""
    image = read_image(looks_path, key=KEY)
    assert read_manifest(looks_path)["header"]["format_version"] == 3
    assert look_names(image) == NAMES
    own = [look.get("sections", {}) for look in image.looks]
    assert own[0] == {}
    for look in (1, 2):
        assert {"n_components", "mean", "scales", "eigenimages", "noise_floor",
                "standalone_scores_delta"} <= set(own[look])
        assert "score_quantization" in image.looks[look]
    assert not any(k.startswith("depth_") for k in own[1])
    assert any(k.startswith("depth_") for k in own[2])
    records = image.provenance["looks"]
    assert [r["name"] for r in records] == list(NAMES)
    assert records[1]["render"]["renderer"]["lighting"]["name"] == "cinematic"
    dbs = _dbs(looks_path)
    views = [look_image(image, look) for look in range(len(NAMES))]
    assert len({v.n_coefficients for v in views}) > 1  # each look its own K
    for look, view in enumerate(views):
        assert view.looks is None and view.n_coefficients == records[look]["components"]
        assert view.provenance["render"] == dbs[look].settings
        rec, table = Reconstructor.from_image(view), StandaloneScores(view)
        for i in (0, 37, 61):
            frame = rec.update(table.training_scores(i)).astype(float)
            err = [float(np.mean((frame - db.read_image(i)) ** 2)) for db in dbs]
            others = [e for j, e in enumerate(err) if j != look]
            assert err[look] < 0.25 * min(others), (look, i, err)
    # the host's model of a look: its own annex (float training scores of its own K)
    model = HostModel.load(looks_path, key=KEY, look=2)
    assert model.image.n_coefficients == views[2].n_coefficients
    assert model.training_scores.shape[1] == views[2].n_coefficients


def test_an_image_whose_looks_share_the_scores_still_shows(looks_path, tmp_path):
    """Format version 2 (looks sharing the first look's scores, as images fitted before
    each look had an eigenspace of its own) is still read and shown: a switch keeps the
    decoder and the table, and a look with the first look's sections shows its frames."""
    import dataclasses

    from protocol.image import write_image

    first = look_image(read_image(looks_path, key=KEY), 0, decode=False)
    colour = ("mean", "scales", "eigenimages")
    shared = dataclasses.replace(first, sections=dict(first.sections), looks=[
        {"name": "a", "sections": {}},
        {"name": "b", "sections": {k: f"look1_{k}" for k in colour}}])
    for k in colour:
        shared.sections[f"look1_{k}"] = getattr(first, k).copy()
    path = tmp_path / "shared.ecs"
    write_image(path, shared, key=KEY)
    assert read_manifest(path)["header"]["format_version"] == 2
    model = LoadedModel.build(read_image(path, key=KEY), slot="A", generation=1, test=False,
                              want_standalone=True)
    other = model.for_look(1, start_worker=False)
    try:
        assert other.decoder is model.decoder and other.standalone is model.standalone
        y = model.standalone.scores(40.0, 10.0)
        np.testing.assert_array_equal(model.reconstructor.update(y).copy(),
                                      other.reconstructor.update(y))
    finally:
        other.close()
        model.close()


def test_looks_are_named_and_picked_by_name_or_index(looks_path, tmp_path, capsys):
    image = read_image(looks_path)
    assert look_index(image, "lamp") == 1 and look_index(image, "2") == 2
    assert look_index(image, None) == 0
    with pytest.raises(ValueError, match=r"no look 'bone' in the image \(its looks: plain, "):
        look_index(image, "bone")
    with pytest.raises(ValueError, match="look 3 is out of range"):
        look_index(image, 3)
    out = tmp_path / "lamp.png"
    assert eigencast(["view", str(looks_path), "--phi", "30", "--theta", "10", "--look",
                      "lamp", "-o", str(out)]) == 0
    assert "look lamp" in capsys.readouterr().out
    assert eigencast(["view", str(looks_path), "--phi", "30", "--theta", "10", "--look",
                      "bone", "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no look 'bone'" in err[0]
    with pytest.raises(FitError, match="no look 'bone'"):
        HostModel.load(looks_path, look="bone")


def test_fit_refuses_databases_of_other_views(looks_path, tmp_path, capsys):
    other = tmp_path / "other.cdb"
    assert eigencast(["render", "builtin:tooth", "-o", str(other), "--views", "grid:8x5",
                      "--size", "32", "--samples", "40", "--no-depth"]) == 0
    capsys.readouterr()
    first = str(looks_path.parent / "look0.cdb")
    assert eigencast(["fit", first, str(other), "-o", str(tmp_path / "x.ecs")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "are not the same views" in err[-1]
    assert eigencast(["fit", first, first, "-o", str(tmp_path / "x.ecs"),
                      "--look-names", "a"]) == 1
    assert "1 names for 2 databases" in capsys.readouterr().err
    assert not (tmp_path / "x.ecs").exists()


def _standalone_device(image, tmp_path, frames: list, look: int = 0) -> RuntimeDevice:
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY),
                           standalone=True, view=(40.0, 10.0), log=_quiet,
                           on_frame=lambda f, info: frames.append((f.copy(), dict(info))))
    model = LoadedModel.build(image, slot="A", generation=1, test=False, want_standalone=True,
                              look=look)
    device._decoder_model = model  # as `_activate` leaves it
    device._models.put(model)
    return device


def _rest(device: RuntimeDevice, frames: list) -> None:
    """Display turns until the warp of the view on show is on show."""
    wait_until(lambda: device.display_turn(None) is not None and frames
               and frames[-1][1].get("synthesized")
               and (frames[-1][1]["phi_deg"], frames[-1][1]["theta_deg"]) == device.view,
               30, "the warp of the view")


def test_a_device_switches_looks_at_once_and_shows_what_eigencast_view_shows(
        looks_path, tmp_path):
    """Key ``l`` (`CycleLook`) on a standalone device: the new look's own frame of the view
    is shown on the same turn (its blend), then its warp, bit for bit the host's frame of
    that look (``eigencast view --look``); the old look's model (its worker, its cached
    views) is closed; after the last look comes the first; the overlay names the look."""
    image = read_image(looks_path, key=KEY)
    frames: list = []
    device = _standalone_device(image, tmp_path, frames)
    warps = {name: WarpFrames(HostModel.load(looks_path, look=name)) for name in NAMES}
    try:
        _rest(device, frames)
        first = device._model
        assert first.look_name == "plain"
        np.testing.assert_array_equal(frames[-1][0], warps["plain"].frame(*device.view))
        for step, name in enumerate((*NAMES[1:], NAMES[0])):
            shown = len(frames)
            old = device._model
            device.apply(CycleLook())
            assert device._model is not old and device._model.look_name == name
            assert device._decoder_model is device._model
            assert not old.warp_worker._thread.is_alive()
            assert len(frames) == shown + 1 and not frames[-1][1].get("synthesized")
            blend = Reconstructor.from_image(look_image(image, name))
            np.testing.assert_array_equal(
                frames[-1][0], blend.update(device._model.own_scores(device.view)))
            _rest(device, frames)
            np.testing.assert_array_equal(frames[-1][0], warps[name].frame(*device.view))
            assert device.runtime_stats.look_switches == step + 1
        device.presenter.overlay = True
        assert device.overlay_lines()[0].startswith("look plain  (1/3")
        assert device.stats_dict()["image"]["looks"] == list(NAMES)
    finally:
        device.close_display()
        device.close()


def test_a_device_starts_on_the_look_it_is_told(looks_path, tmp_path):
    image = read_image(looks_path, key=KEY)
    frames: list = []
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY),
                           standalone=True, view=(40.0, 10.0), log=_quiet, look="generic",
                           on_frame=lambda f, info: frames.append((f.copy(), dict(info))))
    try:
        device._models.put(LoadedModel.build(image, slot="A", generation=1, test=False,
                                             want_standalone=True,
                                             look=look_index(image, device.look)))
        _rest(device, frames)
        want = WarpFrames(HostModel.load(looks_path, look="generic")).frame(*device.view)
        np.testing.assert_array_equal(frames[-1][0], want)
        assert device.show_look("plain") and device._model.look == 0
        with pytest.raises(ValueError, match="no look 'x'"):
            device.show_look("x")
    finally:
        device.close_display()
        device.close()


class _Keys(HeadlessPresenter):
    """A headless presenter whose `poll` hands out queued actions (keys pressed)."""

    def __init__(self) -> None:
        super().__init__(None)
        self.queue: list = []

    def poll(self):
        out, self.queue = self.queue, []
        return out


def test_serve_corrects_the_look_on_show(looks_path, tmp_path):
    """A served device switches to the cinematic look: its VIEW_REQUESTs say so, the host
    marks its packets with that look, and the corrected frames the device shows are its
    own frames of that look plus the host's corrections (never the first look's); the
    complete correction at rest brings the frame closer to the cinematic ray-cast than to
    the headlight one (the host ray-casts the look on show)."""
    name = mem_name("looks")
    frames: list = []
    keys = _Keys()
    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b", predict=True,
                           presenter=keys,
                           on_frame=lambda f, info: frames.append((f.copy(), dict(info or {}))))
    provision(looks_path, f"mem://{name}?end=a", ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=_quiet))
    packets: dict = {}
    original = device.device.on_scores

    def on_scores(msg):
        if not is_layer(msg.packet):  # (layers are not asked for here)
            header = decode_header(msg.packet)
            packets[header.frame] = msg.look or 0
        original(msg)

    device.device.on_scores = on_scores
    stop = threading.Event()
    result: dict = {}
    lines: list[str] = []
    thread = threading.Thread(target=lambda: result.setdefault("stats", serve(
        looks_path, f"mem://{name}?end=a",
        ServeOptions(key=KEY, rest="correction", stats_every_s=0),
        ServeParts(stop=stop, log=lines.append))), daemon=True)
    lamp = HostModel.load(looks_path, look="lamp")
    with device:
        thread.start()
        try:
            wait_until(lambda: any(i.get("corrected") for _, i in frames), 60,
                       "the first correction")
            keys.queue.append(CycleLook())
            wait_until(lambda: device.device._model.look == 1, 20, "the switch")
            switched = len(frames)
            wait_until(lambda: any(i.get("corrected") and packets.get(i.get("frame")) == 1
                                   for _, i in frames[switched:]), 60,
                       "a correction of the cinematic look")
            view = device.device.view
            wait_until(lambda: result.get("stats") is None and any(
                i.get("corrected") and (i["phi_deg"], i["theta_deg"]) == view
                and packets.get(i["frame"]) == 1 for _, i in frames[switched:]), 30, "rest")
            threading.Event().wait(1.0)  # the complete correction of the resting view
        finally:
            stop.set()
            thread.join(20)
    stats = result["stats"]
    assert stats.look_switches == 1
    assert any("the device shows look lamp" in ln for ln in lines), lines
    after = [(f, i) for f, i in frames[switched:] if i.get("corrected")]
    assert after and all(packets[i["frame"]] == 1 for _, i in after)
    assert device.device.runtime_stats.as_dict()["look_switches"] == 1
    f, info = after[-1]
    synth = OwnFrames(lamp.image).frame(info["phi_deg"], info["theta_deg"])
    truth_lamp = _ray_cast(lamp, info)
    truth_plain = _ray_cast(HostModel.load(looks_path, look="plain"), info)

    def err(a, b):
        return float(np.mean((a.astype(float) - b.astype(float)) ** 2))

    assert err(f, truth_lamp) < err(synth, truth_lamp)
    assert err(f, truth_lamp) < 0.5 * err(f, truth_plain)


def _ray_cast(model: HostModel, info: dict) -> np.ndarray:
    from host.link.true_views import open_true_view_scores

    return open_true_view_scores(model, None).renderer.render_rgb8(info["phi_deg"],
                                                                   info["theta_deg"])


def test_a_device_that_predates_looks_refuses_the_image_in_one_line(looks_path, tmp_path,
                                                                    monkeypatch):
    """An image with looks is format version 3: a reader of versions 1 (no looks) and 2
    (looks sharing scores) only refuses it in one line; a host will not send it to a device
    whose HELLO lists those only, and such a device refuses IMAGE_BEGIN of version 3
    (UNSUPPORTED_FORMAT)."""
    import device_runtime.device as device_module
    import device_runtime.image_receiver as receiver_module

    versions = image_format.SUPPORTED_VERSIONS
    monkeypatch.setattr(image_format, "SUPPORTED_VERSIONS", (1, 2))
    with pytest.raises(ImageFormatError,
                       match=r"unsupported format version 3 \(supported: 1, 2\)") as info:
        read_image(looks_path)
    assert "\n" not in str(info.value)
    # the host reads it; the device is the old one
    monkeypatch.setattr(image_format, "SUPPORTED_VERSIONS", versions)
    monkeypatch.setattr(device_module, "SUPPORTED_VERSIONS", (1, 2))
    monkeypatch.setattr(receiver_module, "SUPPORTED_VERSIONS", (1, 2))
    name = mem_name("old")
    with RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b") as device:
        with pytest.raises(ProvisionError, match="reads image format versions 1, 2; this "
                           "image is version 3") as info:
            provision(looks_path, f"mem://{name}?end=a",
                      ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
        assert "\n" not in str(info.value)
        begin = m.ImageBegin(digest=bytes(32), size_bytes=4096, image_tag=bytes(32),
                             format_version=3, generation=1)
        with pytest.raises(Exception, match="format version 3 is not supported") as info:
            device.device.handle_image_begin(begin, None)
        assert info.value.code == m.ErrorCode.UNSUPPORTED_FORMAT


#: sha256 of `_one_look_fit`'s image, made by the code before images had looks (the
#: commit this branch started from; to check again: run `_one_look_fit` with that code).
ONE_LOOK_SHA256 = (GOLDEN / "one_look_fit.sha256").read_text().split()[0]


def _one_look_fit(folder) -> bytes:
    """``eigencast fit`` of one small database (relative paths, the clock fixed: the bytes
    depend on nothing else)."""
    from unittest import mock

    with contextlib.chdir(folder), mock.patch("time.time", return_value=1.7e9), \
            mock.patch("time.time_ns", return_value=1_700_000_000_000_000_000):
        assert eigencast(["render", "builtin:tooth", "-o", "db.cdb", "--views", "grid:16x5",
                          "--size", "32", "--samples", "80"]) == 0
        assert eigencast(["fit", "db.cdb", "-o", "one.ecs", "--cell", "12", "--threshold",
                          "0.99", "--no-cache"]) == 0
        return Path("one.ecs").read_bytes()


def test_an_image_with_one_look_is_the_same_bytes_as_before_looks(tmp_path, capsys):
    data = _one_look_fit(tmp_path)
    assert hashlib.sha256(data).hexdigest() == ONE_LOOK_SHA256
    assert struct.unpack_from("<H", data, 8)[0] == 1
    assert "looks" not in read_manifest(tmp_path / "one.ecs")


def test_the_window_key_l_switches_looks_on_the_real_window(looks_path, tmp_path):
    """The real pygame window (SDL dummy driver): key ``l`` shows the next look at once --
    the window's pixels become the new look's frame of the view (its blend or its warp),
    never the old look's."""
    from device_runtime.display import Window

    image = read_image(looks_path, key=KEY)
    window = Window(image.image_shape, screenshot_dir=tmp_path, zoom=1.0)
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY),
                           standalone=True, view=(40.0, 10.0), log=_quiet, presenter=window)
    try:
        model = LoadedModel.build(image, slot="A", generation=1, test=False,
                                  want_standalone=True)
        device._decoder_model = model
        device._models.put(model)
        device.display_turn(None)
        h, w = image.image_shape
        before = window.window_pixels()[:h, :w]
        window._pg.event.get()  # drop start-up events
        window._pg.event.post(window._pg.event.Event(window._pg.KEYDOWN, key=window._pg.K_l,
                                                     mod=0, unicode="l"))
        device.display_turn(None)
        assert device._model.look_name == "lamp" and model.warp_worker._thread.is_alive() \
            is False
        shown = window.window_pixels()
        blend = Reconstructor.from_image(look_image(image, "lamp")).update(
            device._model.own_scores(device.view))
        warp = WarpFrames(HostModel.load(looks_path, look="lamp")).frame(*device.view)
        # its blend, or already its warp when the worker made it within the turn
        assert np.array_equal(shown, blend) or np.array_equal(shown, warp)
        assert not np.array_equal(shown, before)
    finally:
        device.close_display()
        device.close()


def test_a_packet_for_the_look_left_is_never_shown(looks_path, tmp_path):
    """A served device switches looks while host frames of the old look are on their way:
    one decoded before the switch (its model closed) and one that arrives after (marked
    with the old look) are both dropped; one for the new look is shown."""
    from host.link.encoding import FrameEncoder

    image = read_image(looks_path, key=KEY)
    frames: list = []
    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash", key=KEY),
                           predict=True, view=(40.0, 10.0), log=_quiet,
                           on_frame=lambda f, info: frames.append((f.copy(), dict(info))))
    try:
        model = LoadedModel.build(image, slot="A", generation=1, test=False,
                                  want_predictor=True, on_warp=device._scores.wake)
        device._decoder_model = model
        device._models.put(model)
        device.display_turn(None)
        encoder = FrameEncoder(HostModel.load(looks_path, key=KEY, look="plain"))
        device.on_scores(m.Scores(sequence=0, packet=encoder.encode(device.view,
                                                                    key=True).packet))
        early = device._scores.take()
        assert early is not None and early.model is model
        device.show_look("lamp")
        shown = len(frames)
        late = encoder.encode(device.view)
        device.on_scores(m.Scores(sequence=0, packet=late.packet, look=0))
        assert device.runtime_stats.other_look == 1 and device._scores.take() is None
        device.display_turn(early)
        host_frames = {i.get("frame") for _, i in frames[shown:]}
        assert early.scores.frame not in host_frames and late.frame not in host_frames
        right = FrameEncoder(HostModel.load(looks_path, key=KEY, look="lamp"))
        device.on_scores(m.Scores(sequence=0, packet=right.encode(device.view,
                                                                  key=True).packet, look=1))
        item = device._scores.take()
        assert item is not None and item.model is device._model
        device.display_turn(item)
        assert frames[-1][1].get("frame") == item.scores.frame
    finally:
        device.close_display()
        device.close()


def test_bad_look_input_is_one_line_with_an_exit_code(looks_path, tmp_path, capsys):
    """Databases of other sizes, repeated look names, an interpolation the views cannot
    have, a --look the image lacks (evaluate, the device): one line each, exit code 1, and
    no look fitted first."""
    first = str(looks_path.parent / "look0.cdb")
    small = tmp_path / "small.cdb"
    assert eigencast(["render", "builtin:tooth", "-o", str(small), "--views", TINY_VIEWS,
                      "--size", "24", "--samples", "40"]) == 0
    scattered = [tmp_path / f"scattered{i}.cdb" for i in range(2)]
    for i, db in enumerate(scattered):
        assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", "random:30:1",
                          "--size", "24", "--samples", "40"] + (["--tf", "ct-skin"] if i else
                                                                [])) == 0
    capsys.readouterr()
    cases = [
        (["fit", first, str(small), "-o", str(tmp_path / "x.ecs")], "render the looks at one"),
        (["fit", *map(str, scattered), "-o", str(tmp_path / "x.ecs"), "--interpolation",
          "bilinear"], "needs a full phi x theta grid"),
        (["fit", first, str(looks_path.parent / "look1.cdb"), "-o", str(tmp_path / "x.ecs"),
          "--look-names", "a,a"], "look names repeat"),
        (["evaluate", str(looks_path), "--look", "bone", "--rd-views", "0"],
         "no look 'bone'"),
    ]
    for argv, needle in cases:
        assert eigencast(argv) == 1, argv
        out, err = capsys.readouterr()
        err = err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], (argv, err)
        assert "fitting" not in out  # refused before any look is fitted
    assert not (tmp_path / "x.ecs").exists()


def test_evaluate_takes_each_look_against_its_own_ray_casts_or_the_one_asked(
        looks_path, tmp_path, capsys):
    """``evaluate`` on an image with looks: every look in turn (own frame, moving, at rest,
    the codecs), each against ray-casts with its own render settings, one report folder per
    look; ``--look`` evaluates just that one, with the same figures."""
    import json

    common = ["--views", "grid:4x2", "--rd-views", "0", "--no-nearest", "--motion-deadline",
              "0", "--webp-db-quality", "0", "--json"]
    assert eigencast(["evaluate", str(looks_path), *common, "--report",
                      str(tmp_path / "report")]) == 0
    every = json.loads(capsys.readouterr().out)
    assert every["look_names"] == list(NAMES)
    for name in NAMES:
        summary = every["looks"][name]
        assert {"pca_warp", "pca_predict", "rest", "jpeg", "webp"} <= set(summary)
        assert summary["pca_predict"]["psnr"] > 24.0, (name, summary["pca_predict"])
        assert (tmp_path / "report" / name / "index.html").exists()
    assert every["looks"]["lamp"]["pca"] != every["looks"]["plain"]["pca"]
    assert eigencast(["evaluate", str(looks_path), *common, "--look", "lamp"]) == 0
    one = json.loads(capsys.readouterr().out)
    assert one["pca_predict"] == every["looks"]["lamp"]["pca_predict"]


def test_the_device_command_starts_on_the_look_named_or_refuses_one_it_lacks(
        looks_path, tmp_path, capsys):
    """``eigencast-device --look``: the frames are that look's (``eigencast view --look``);
    a name the image lacks is one error line and exit code 1."""
    from PIL import Image

    from device_runtime.cli import main as device_main

    flash = tmp_path / "flash"
    name = mem_name("cli-look")
    with RuntimeThread(flash, f"mem://{name}?end=b"):
        provision(looks_path, f"mem://{name}?end=a",
                  ProvisionOptions(key=KEY, show_progress=False), ProvisionParts(log=_quiet))
    capsys.readouterr()
    frames = tmp_path / "frames"
    assert device_main(["--flash", str(flash), "--standalone", "--headless", "--frames",
                        str(frames), "--views", "30,15", "--look", "generic"]) == 0
    want = tmp_path / "want.png"
    assert eigencast(["view", str(looks_path), "--look", "generic", "--phi", "30", "--theta",
                      "15", "-o", str(want)]) == 0
    last = sorted(frames.glob("frame-*.png"))[-1]
    assert np.array_equal(np.asarray(Image.open(last)), np.asarray(Image.open(want)))
    capsys.readouterr()
    assert device_main(["--flash", str(flash), "--standalone", "--headless", "--views",
                        "30,15", "--look", "bone"]) == 1
    errors = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert errors == ["eigencast-device: error: --look bone: no look 'bone' in the image "
                      "(its looks: plain, lamp, generic)"]
