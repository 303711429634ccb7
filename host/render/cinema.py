"""Cinema Spec D databases: the training and test images of eigencast.

A database is a folder ``NAME.cdb/`` holding

* ``data.csv`` -- one row per image: ``phi,theta`` (degrees, floats always
  written with a decimal point), the camera vectors (``cam_x..``, ``look_x..``,
  ``up_x..``) and ``FILE`` last (a path relative to the folder);
* the PNG images (``images/view_00000.png`` ...);
* ``eigencast.json`` -- the sidecar: volume, transfer function, camera and
  renderer settings, image size and view set (its spec and, since it is recorded, its
  count: a ``data.csv`` listing fewer views is an interrupted render, `expected_views`).
  Databases written by other tools (ParaView, VisIt, a path tracer) have no sidecar and are
  still valid input.

``eigencast render`` gives each view a depth map too (unless ``--no-depth``, or where the
framing cannot carry one: `depth_problem`), ``depth/view_00000.npz``
(the image's name with ``.npz``; `depth_file`): one float16 array ``depth`` of shape
(H/2, W/2), the distance in mm along each pixel's ray where the accumulated opacity crosses
one half (the opacity-weighted mean where it never does), averaged over each 2x2 block of
pixels, minus the camera distance ``offset_mm``; NaN off the object. float16 keeps depths
within the bounding sphere to ~0.06 mm at 128 mm, far below a voxel. ``depth/depth.json``
records the format (`DEPTH_RECORD`) and ``offset_mm``. A depth map is written before its PNG
and a view counts as done only when both are valid, so resume works as for the PNGs.

Writing is crash-safe: every PNG is written to a temporary name and renamed
into place, and ``data.csv`` is rewritten atomically listing only images that
exist, so a killed run never leaves a corrupt PNG or a row naming a missing
file. `CinemaWriter` resumes an interrupted database with the same settings,
keeping every valid image already written.
"""

from __future__ import annotations

import csv
import io
import json
import os
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from host.errors import CinemaError

__all__ = [
    "DEPTH_DIR",
    "DEPTH_RECORD",
    "SIDECAR",
    "CinemaDB",
    "CinemaWriter",
    "absolute_source",
    "atomic_write_bytes",
    "decode_depth",
    "depth_file",
    "depth_problem",
    "encode_depth",
    "format_float",
    "with_recorded_lighting",
]

SIDECAR = "eigencast.json"
DATA_CSV = "data.csv"
IMAGE_DIR = "images"
DEPTH_DIR = "depth"
DEPTH_JSON = "depth.json"
#: ``depth/depth.json``'s format name (``offset_mm`` is recorded beside it).
DEPTH_RECORD = "half-opacity-depth-f16-x2"
CAMERA_COLUMNS = (
    "cam_x", "cam_y", "cam_z", "look_x", "look_y", "look_z", "up_x", "up_y", "up_z",
)


def format_float(value: float) -> str:
    """Format a float for data.csv: shortest round-trip form, always with a decimal point."""
    text = repr(float(value))
    if "e" in text or "E" in text:
        text = f"{float(value):.9f}".rstrip("0")
    if "." not in text and text not in ("inf", "-inf", "nan"):
        text += ".0"
    if text.endswith("."):
        text += "0"
    return text


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder and a rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def encode_png(image: np.ndarray) -> bytes:
    """Deterministic PNG encoding of an (H, W, 3) uint8 image."""
    buf = io.BytesIO()
    Image.fromarray(image, mode="RGB").save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def depth_problem(settings: dict | None, image_shape: tuple[int, int]) -> str | None:
    """Why a database with these settings cannot carry the depth a device warps by, or None.

    The warp (`device_runtime.synthesis`) needs a perspective orbit whose framing the sidecar
    records (``camera.projection``, ``fov_deg``, ``radius_mm``), a black background (the
    device finds the object by its colour) and an even image size (depth is stored at half
    resolution). ``image_shape`` is (height, width).
    """
    camera = (settings or {}).get("camera") or {}
    if camera.get("projection", "perspective") != "perspective":
        return f"{camera.get('projection')} projection (the warp needs perspective)"
    if not isinstance(camera.get("fov_deg"), (int, float)) or not isinstance(
            camera.get("radius_mm"), (int, float)):
        return "no recorded perspective framing (not rendered by eigencast render)"
    background = ((settings or {}).get("renderer") or {}).get("background", [0, 0, 0])
    if any(float(b) != 0.0 for b in background):
        return "a background that is not black (the device finds the object by its colour)"
    if image_shape[0] % 2 or image_shape[1] % 2:
        return (f"an odd image size {image_shape[1]}x{image_shape[0]} (depth is stored at "
                "half resolution)")
    return None


def depth_file(image_file: str) -> str:
    """The depth map's path (relative to the database) of an image path: ``depth/NAME.npz``."""
    return f"{DEPTH_DIR}/{Path(image_file).stem}.npz"


def encode_depth(depth: np.ndarray, offset_mm: float) -> bytes:
    """A view's stored depth from `Renderer.render_with_depth`'s (H, W, 2), as npz bytes.

    The half-opacity depth (channel 0) with the mean (channel 1) where it is NaN, averaged
    over 2x2 blocks of finite values (NaN where none is), minus ``offset_mm``, float16.
    H and W must be even.
    """
    half = depth[..., 0]
    d = np.where(np.isfinite(half), half, depth[..., 1]).astype(np.float64)
    h, w = d.shape
    blocks = d.reshape(h // 2, 2, w // 2, 2).swapaxes(1, 2).reshape(h // 2, w // 2, 4)
    ok = np.isfinite(blocks)
    count = ok.sum(axis=2)
    total = np.where(ok, blocks, 0.0).sum(axis=2)
    out = np.full((h // 2, w // 2), np.nan, dtype=np.float64)
    np.divide(total, count, out=out, where=count > 0)
    out -= float(offset_mm)
    buf = io.BytesIO()
    np.savez_compressed(buf, depth=out.astype(np.float16))
    return buf.getvalue()


def decode_depth(path: Path, shape: tuple[int, int], offset_mm: float) -> np.ndarray:
    """Read a stored depth map: float32 ``shape`` in mm along the rays (NaN off the object).

    Raises
    ------
    CinemaError
        Unreadable, or not a float16 array of ``shape``.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            d = z["depth"]
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise CinemaError(f"{path}: not a readable depth map: {exc}") from None
    if d.dtype != np.float16 or d.shape != tuple(shape):
        raise CinemaError(f"{path}: depth map is {d.dtype} {d.shape}, expected float16 {shape}")
    return d.astype(np.float32) + np.float32(offset_mm)


@dataclass
class CinemaDB:
    """A Cinema Spec D database opened for reading.

    Attributes
    ----------
    path : Path
        The ``.cdb`` folder.
    phi_deg, theta_deg : ndarray of shape (n_views,), float64
    files : list of str
        Image paths relative to `path`, one per view.
    settings : dict or None
        The eigencast sidecar, or None for databases from other tools.
    image_shape : tuple (height, width)
    depth : dict or None
        ``depth/depth.json`` (``format``, ``offset_mm``) when every view has a depth map
        (``render --depth``), else None.
    """

    path: Path
    phi_deg: np.ndarray
    theta_deg: np.ndarray
    files: list[str]
    settings: dict | None
    image_shape: tuple[int, int]
    depth: dict | None = None

    @classmethod
    def open(cls, path: str | os.PathLike) -> CinemaDB:
        """Open a database; raise `CinemaError` (one line) when it is unusable."""
        root = Path(path)
        csv_path = root / DATA_CSV
        if not root.is_dir():
            raise CinemaError(f"{root}: not a Cinema database folder (no such directory)")
        if not csv_path.is_file():
            raise CinemaError(f"{root}: not a Cinema database (no {DATA_CSV})")
        try:
            with open(csv_path, newline="", encoding="utf-8") as f:
                rows = list(csv.reader(f))
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise CinemaError(f"{csv_path}: unreadable: {exc}") from None
        if not rows:
            raise CinemaError(f"{csv_path}: empty file")
        header = [h.strip() for h in rows[0]]
        lower = [h.lower() for h in header]
        missing = [c for c in ("phi", "theta") if c not in lower]
        file_col = next((i for i, h in enumerate(header) if h.upper() == "FILE"), None)
        if missing or file_col is None:
            need = ", ".join([*missing, *([] if file_col is not None else ["FILE"])])
            raise CinemaError(f"{csv_path}: missing column(s) {need}; header is {header}")
        i_phi, i_theta = lower.index("phi"), lower.index("theta")
        phis, thetas, files = [], [], []
        for line_no, row in enumerate(rows[1:], start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise CinemaError(
                    f"{csv_path}:{line_no}: {len(row)} fields, header has {len(header)}"
                )
            try:
                phis.append(float(row[i_phi]))
                thetas.append(float(row[i_theta]))
            except ValueError:
                raise CinemaError(
                    f"{csv_path}:{line_no}: phi/theta not numbers: {row[i_phi]!r}, "
                    f"{row[i_theta]!r}"
                ) from None
            files.append(row[file_col].strip())
        if not files:
            raise CinemaError(f"{csv_path}: no image rows")
        theta = np.array(thetas)
        if np.any(np.abs(theta) > 90.0 + 1e-9):
            raise CinemaError(f"{csv_path}: theta outside [-90, 90] (elevation in degrees)")
        for name in files:
            if not (root / name).is_file():
                raise CinemaError(f"{csv_path}: names {name}, which does not exist")
        settings = None
        if (root / SIDECAR).is_file():
            try:
                settings = json.loads((root / SIDECAR).read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise CinemaError(f"{root / SIDECAR}: unreadable sidecar: {exc}") from None
        first = _read_png(root / files[0])
        depth = None
        if (root / DEPTH_DIR / DEPTH_JSON).is_file():
            try:
                depth = json.loads((root / DEPTH_DIR / DEPTH_JSON).read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise CinemaError(f"{root / DEPTH_DIR / DEPTH_JSON}: unreadable: {exc}") from None
            if not isinstance(depth, dict) or depth.get("format") != DEPTH_RECORD or not (
                isinstance(depth.get("offset_mm"), (int, float))
            ):
                raise CinemaError(f"{root / DEPTH_DIR / DEPTH_JSON}: unknown depth format")
            if not all((root / depth_file(name)).is_file() for name in files):
                depth = None
        return cls(
            path=root,
            phi_deg=np.mod(np.array(phis), 360.0),
            theta_deg=theta,
            files=files,
            settings=settings,
            image_shape=first.shape[:2],
            depth=depth,
        )

    @property
    def n_views(self) -> int:
        return len(self.files)

    def read_image(self, index: int) -> np.ndarray:
        """Image ``index`` as uint8 (height, width, 3); alpha (if any) is dropped."""
        image = _read_png(self.path / self.files[index])
        if image.shape[:2] != self.image_shape:
            raise CinemaError(
                f"{self.path / self.files[index]}: size {image.shape[1]}x{image.shape[0]} "
                f"differs from the first image's {self.image_shape[1]}x{self.image_shape[0]}"
            )
        return image

    @property
    def expected_views(self) -> int | None:
        """How many views the sidecar's view set has (None when unknown: no sidecar, or a
        CSV view set rendered before the count was recorded whose file is gone).

        More than `n_views` means an interrupted render: ``data.csv`` lists only the views
        rendered so far (`CinemaWriter.write_csv`)."""
        views = (self.settings or {}).get("views")
        if not isinstance(views, dict):
            return None
        count = views.get("count")
        if isinstance(count, int) and count > 0:
            return count
        spec = views.get("spec")
        if not isinstance(spec, str):
            return None
        from host.errors import ViewSpecError
        from host.render.camera import parse_view_set

        try:
            return len(parse_view_set(spec))
        except ViewSpecError:
            return None

    @property
    def depth_shape(self) -> tuple[int, int]:
        """Shape of the stored depth maps: half the image's."""
        return (self.image_shape[0] // 2, self.image_shape[1] // 2)

    def read_depth(self, index: int) -> np.ndarray:
        """View ``index``'s depth (`encode_depth`): float32 (H/2, W/2), mm along the rays
        from the camera, NaN off the object. `CinemaError` when the database has no depth."""
        if self.depth is None:
            raise CinemaError(f"{self.path}: has no depth maps (render it with --depth)")
        return decode_depth(self.path / depth_file(self.files[index]), self.depth_shape,
                            float(self.depth["offset_mm"]))

    def iter_images(self) -> Iterator[np.ndarray]:
        """Yield every image in row order as uint8 (height, width, 3)."""
        for i in range(self.n_views):
            yield self.read_image(i)


def _read_png(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode != "RGB":
                im = im.convert("RGB")
            return np.asarray(im, dtype=np.uint8)
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise CinemaError(f"{path}: not a readable image: {exc}") from None


class CinemaWriter:
    """Write (or resume) a database image by image, crash-safely.

    Parameters
    ----------
    path : path-like
        The ``.cdb`` folder to create or resume.
    settings : dict
        JSON-able sidecar. Resuming requires an identical sidecar; otherwise
        `CinemaError` (or, with ``overwrite=True``, the old images are removed).
    rows : sequence of (phi_deg, theta_deg, camera_dict)
        One per view, in database order; ``camera_dict`` holds ``position``,
        ``look_at`` and ``up`` 3-vectors.
    image_shape : (height, width)
    depth_offset_mm : float or None
        Also keep a depth map per view (`encode_depth` with this offset; even sizes only):
        a view is done only when its PNG and its depth map are both valid.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        settings: dict,
        rows: Sequence[tuple[float, float, dict]],
        image_shape: tuple[int, int],
        *,
        overwrite: bool = False,
        depth_offset_mm: float | None = None,
    ) -> None:
        self.path = Path(path)
        self.settings = settings
        self.rows = list(rows)
        self.image_shape = tuple(image_shape)
        self.files = [f"{IMAGE_DIR}/view_{i:05d}.png" for i in range(len(self.rows))]
        self.depth_offset_mm = depth_offset_mm
        self._prepare(overwrite)
        self.done = [self._valid(i) for i in range(len(self.rows))]

    # -- setup -----------------------------------------------------------
    def _prepare(self, overwrite: bool) -> None:
        sidecar = self.path / SIDECAR
        text = json.dumps(self.settings, indent=2, sort_keys=True) + "\n"
        if self.path.exists() and not self.path.is_dir():
            raise CinemaError(f"{self.path}: exists and is not a folder")
        if sidecar.is_file():
            old_text = sidecar.read_text(encoding="utf-8")
            same = old_text == text or _same_settings(old_text, self.settings)
            if not same and not overwrite:
                raise CinemaError(
                    f"{self.path}: holds a database rendered with different settings; "
                    "choose another -o or pass --overwrite"
                )
            if not same:
                for old in (self.path / IMAGE_DIR).glob("*.png"):
                    old.unlink()
                (self.path / DATA_CSV).unlink(missing_ok=True)
        elif self.path.is_dir() and any(self.path.iterdir()) and not overwrite:
            raise CinemaError(
                f"{self.path}: folder is not empty and is not an eigencast database; "
                "choose another -o or pass --overwrite"
            )
        (self.path / IMAGE_DIR).mkdir(parents=True, exist_ok=True)
        for stale in self.path.glob(f"{IMAGE_DIR}/.*.tmp"):
            stale.unlink(missing_ok=True)
        atomic_write_bytes(sidecar, text.encode("utf-8"))
        if self.depth_offset_mm is not None:
            folder = self.path / DEPTH_DIR
            folder.mkdir(exist_ok=True)
            for stale in folder.glob(".*.tmp"):
                stale.unlink(missing_ok=True)
            record = {"format": DEPTH_RECORD, "offset_mm": float(self.depth_offset_mm)}
            old = folder / DEPTH_JSON
            if old.is_file():
                try:
                    same = json.loads(old.read_text(encoding="utf-8")) == record
                except ValueError:
                    same = False
                if not same:  # another framing: the old depth maps are meaningless
                    for stale in folder.glob("*.npz"):
                        stale.unlink()
            atomic_write_bytes(old, (json.dumps(record, indent=2) + "\n").encode("utf-8"))

    def _valid(self, index: int) -> bool:
        path = self.path / self.files[index]
        if not path.is_file():
            return False
        try:
            image = _read_png(path)
        except CinemaError:
            path.unlink(missing_ok=True)
            return False
        if image.shape[:2] != self.image_shape:
            path.unlink(missing_ok=True)
            return False
        if self.depth_offset_mm is not None:
            depth = self.path / depth_file(self.files[index])
            shape = (self.image_shape[0] // 2, self.image_shape[1] // 2)
            try:
                decode_depth(depth, shape, 0.0)
            except CinemaError:
                depth.unlink(missing_ok=True)
                return False
        return True

    # -- writing ---------------------------------------------------------
    @property
    def pending(self) -> list[int]:
        """Indices of the views still to render."""
        return [i for i, ok in enumerate(self.done) if not ok]

    def write_image(self, index: int, image: np.ndarray) -> None:
        """Store view ``index`` (uint8 (H, W, 3)) atomically."""
        if image.shape != (*self.image_shape, 3) or image.dtype != np.uint8:
            raise ValueError(f"image {index}: expected uint8 {(*self.image_shape, 3)}")
        self.write_png(index, encode_png(image))

    def write_depth(self, index: int, data: bytes) -> None:
        """Store view ``index``'s depth map from `encode_depth` bytes (before its PNG)."""
        atomic_write_bytes(self.path / depth_file(self.files[index]), data)

    def write_png(self, index: int, data: bytes) -> None:
        """Store view ``index`` from PNG bytes made by `encode_png` (e.g. on a cluster worker)."""
        atomic_write_bytes(self.path / self.files[index], data)
        self.done[index] = True

    def write_csv(self) -> None:
        """Rewrite data.csv atomically, listing only the images that exist."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["phi", "theta", *CAMERA_COLUMNS, "FILE"])
        for i, (phi, theta, cam) in enumerate(self.rows):
            if not self.done[i]:
                continue
            vec = [*cam["position"], *cam["look_at"], *cam["up"]]
            w.writerow([format_float(phi), format_float(theta),
                        *(format_float(v) for v in vec), self.files[i]])
        atomic_write_bytes(self.path / DATA_CSV, buf.getvalue().encode("utf-8"))


def absolute_source(source: str | None) -> str | None:
    """A volume source as recorded in a sidecar: ``builtin:NAME`` as is, a path absolute.

    A relative path would only resolve from the folder ``render`` ran in, while `serve`,
    `evaluate` and `fit --target` load the recorded volume from wherever they run.
    """
    if not source or source.startswith("builtin:"):
        return source
    return str(Path(source).expanduser().resolve())


def with_recorded_lighting(settings: dict) -> dict:
    """``settings`` (a sidecar) with ``renderer.lighting`` filled in where it was rendered
    before lighting was recorded: the headlight's record (`host.render.lighting`). For
    comparing the records of databases of both ages; a copy where it adds the record."""
    renderer = settings.get("renderer") if isinstance(settings, dict) else None
    if not isinstance(renderer, dict) or "lighting" in renderer:
        return settings
    from host.render.lighting import LIGHTINGS

    return {**settings, "renderer": {**renderer, "lighting": LIGHTINGS["headlight"].record()}}


def _same_settings(old_text: str, settings: dict) -> bool:
    """The sidecar ``old_text`` records ``settings`` once both volume sources are made
    absolute and the view count is left out where the old one lacks it (a database rendered
    before sources were recorded absolute, or before the count was, resumes); a renderer
    record without a lighting is the headlight's (a database rendered before lighting was
    recorded resumes with the headlight)."""
    try:
        old = json.loads(old_text)
    except ValueError:
        return False
    if not isinstance(old, dict) or not isinstance(old.get("volume"), dict):
        return False
    new = json.loads(json.dumps(settings))
    old_views, new_views = old.get("views"), new.get("views")
    if isinstance(old_views, dict) and isinstance(new_views, dict) and "count" not in old_views:
        new_views.pop("count", None)  # recorded since: the view spec says the same
    old = with_recorded_lighting(old)  # recorded since: no record means the headlight
    for record in (old, new):
        volume = record.get("volume")
        if isinstance(volume, dict) and isinstance(volume.get("source"), str):
            volume["source"] = absolute_source(volume["source"])
    return old == new
