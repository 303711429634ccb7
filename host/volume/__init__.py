"""Stage 1, volume: the `Volume` type, one reader per file format, the built-in phantoms.

Conventions (shared by every host module):

* ``Volume.data`` has numpy shape ``(nz, ny, nx)`` -- x varies fastest in
  memory, as in every raw volume file -- dtype float32, C-contiguous, holding
  the scanner's values after any rescale (e.g. Hounsfield units for CT).
* ``Volume.spacing`` is ``(sx, sy, sz)`` in millimetres (x first).
* World coordinates: voxel ``data[k, j, i]`` sits at ``(i*sx, j*sy, k*sz)``;
  +z is "up" (superior for medical data) so an orbit camera with up = +z shows
  a head upright.

Orientation
-----------
Loaders bring every volume whose anatomy is known into **RAS** index order:
+x towards the patient's Right, +y Anterior, +z Superior (nibabel's
"closest canonical"). A file's own axes are described by a three-letter
*axis code* naming where +i, +j and +k point, e.g. ``"LPS"`` for DICOM/ITK
index order or ``"LPI"`` for a stack sliced from the top of the head down.
The code comes from, in order of precedence:

1. the caller (``orientation="LPI"``, CLI ``--orientation LPI``);
2. the file's header: NIfTI affine (via nibabel), NRRD ``space`` + ``space
   directions``, MetaImage ``AnatomicalOrientation`` or a non-identity
   ``TransformMatrix`` (ITK/LPS convention; an identity matrix is what every
   tool writes by default, so it is not taken as information), DICOM
   ``ImageOrientationPatient``;
3. `KNOWN_DATASETS`: a short table of well-known volumes without orientation
   metadata (the paper's tooth, the Visible Male head, ...), matched by file
   name stem, dims and dtype, each entry with the reason for its fix;
4. otherwise the file order is kept (code ``"RAS"`` assumed, recorded as
   ``metadata["orientation"]["source"] == "none"``).

Fixes from `KNOWN_DATASETS` are proper rotations (determinant +1): when a
header says nothing about left/right we never mirror.

Formats
-------
raw (any extension, ``dims`` given; ``.gz`` data is inflated), volvis ``.dat``
(text header, or the 6-byte binary TU Wien header), MetaImage ``.mhd``/``.mha``,
NRRD ``.nrrd``/``.nhdr``, NIfTI ``.nii``/``.nii.gz``, a DICOM series folder (or
one ``.dcm`` file of it), TIFF stacks (multi-page file or a folder of
single-page files), uncompressed Roettger ``.pvm`` and NumPy ``.npy``/``.npz`` (one array
``(z, y, x)``; ``--spacing`` gives its voxel size). Every problem with a file
raises `VolumeError` with one line naming the file.

Built-in volumes
----------------
``builtin:head`` (CT-like phantom in HU, 112x136x144 at 1.6 mm, modality ct),
``builtin:tooth`` (two-rooted molar on the paper's tooth scale 0-255,
120x104x160 at 0.15 mm, crown up, modality tooth) and ``builtin:sphere``
(ball of ones, 64^3). Deterministic, float32, no files; see `list_builtins`.

Layout
------
``core.py`` (`Volume`, what readers share), ``load.py`` (`load_volume`: format detection,
the `READERS` registry, orientation and overrides, the ``--dims ...`` CLI options),
``orientation.py`` (axis codes, `KNOWN_DATASETS`), ``modality.py`` (what the values say
about the modality when nothing else does: CT in Hounsfield units), ``read_<format>.py``
(one reader per format, as pyserial keeps one ``protocol_*.py`` per URL scheme) and
``phantoms.py``
(``builtin:NAME``). A new format: a ``read_NAME.py`` returning a ``core._Loaded``, an entry in
`READERS` and its extension/magic bytes in ``load._detect_format``.

May import: stdlib, numpy, `host.errors`; the format libraries (pydicom, pynrrd, nibabel,
tifffile, scipy) only inside the function that needs them. Nothing from a later stage.
"""

from host.lazy import attach

__all__ = [
    "KNOWN_DATASETS",
    "MODALITIES",
    "RAW_DTYPES",
    "READERS",
    "SUPPORTED_FORMATS",
    "KnownDataset",
    "Volume",
    "add_volume_arguments",
    "builtin_volume",
    "list_builtins",
    "load_volume",
    "volume_from_args",
]

__getattr__, __dir__ = attach(__name__, __all__)
