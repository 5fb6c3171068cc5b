"""One problem loader: every command, job and the GUI read, correct and downsample inputs here.

API::

    spec = ProblemSpec(model="2d", meas="meas.npy", psf="psf.npy", mask="mask.npy",
                       downsample=4, color="rgb", channel_order="bgr", flip_rows=False,
                       field="sensor", truth="truth.npy")
    prob = load_problem(spec, dtype=torch.float32, device="cpu")
    prob.model      # recon.models.ForwardModel
    prob.meas       # (C, H, W) float32, max 1 on the measured pixels
    prob.mask       # (H, W) float32 0/1 (the model's mask) or None
    prob.truth      # (C, K, Hs, Ws) float32 on the reconstruction grid, or None
    prob.inputs     # name -> {path, file_hash, array_hash, shape} (what a run record stores;
                    # dark-frame files by their file hash alone)
    prob.hashes     # name -> file hash
    prob.metadata   # the preprocessing (mask_hash, psf_grid, filters_scale, ...), for a
                    # result's metadata; metadata['warnings']: the input warnings
                    # (measurement, PSF) as text;
                    # metadata['meas_scale']: what the measurement was divided by (its
                    # normalisation, in the file's units after dark subtraction; 1.0: none)
    prob.sensor     # the real sensor on the reconstruction grid (rows, cols)
    ProblemSpec.from_data_section(d) / spec.to_data_section()   # the [data] table of a job
    load_truth(spec, scene_shape)   # only the truth, prepared as load_problem prepares it

Command-line arguments become a spec through ``app.commands._inputs.problem_spec(args)``.

Readers, one per file kind: :func:`read_mask`, :func:`read_shutter`, :func:`read_filters`,
:func:`read_truth` (PSFs and measurements: :func:`recon.readers.load_psf`,
:func:`recon.readers.load_measurement`, :func:`recon.readers.load_psf_stack`).

Rules (the same for every command):

- **Order**: read -> dark -> channel order and colour -> row flip -> (padded PSF: embed the
  sensor in the padded grid) -> downsample -> normalise -> check.
- **Mask** (1 = measured, 0 = erased): integer or boolean files: nonzero = measured; float
  files must hold only 0 and 1 (other values are refused), no NaN. Downsampling
  (:func:`recon.preprocess.downsample_mask`): a coarse pixel is measured when ANY sensor pixel
  under it is, and its value is the mean of the measured ones
  (:func:`recon.preprocess.downsample_masked`), so no measured pixel is lost. A mask may also
  be given at the reconstruction resolution (then the measurement is box-downsampled as it
  is).
- **Shutter** M (K, rows): at the sensor's rows (then averaged over ``downsample`` rows,
  :func:`recon.preprocess.downsample_rows`) or already at the reconstruction's rows. The
  ``.npz`` of ``lenslesscam calibrate shutter`` is read with its hashes checked.
- **Filters** (K, H, W): at sensor or reconstruction resolution (box-downsampled), then
  scaled to a maximum of 1 (``metadata['filters_scale']``: the maximum divided by), so a cube
  in percent and one in [0, 1] make the same problem and a fixed tau means one thing.
- **Colour**: ``gray`` (Rec. 601 luma) or ``rgb``; ``channel_order='bgr'`` for files that
  store B, G, R (the DiffuserCam Lensless MirFlickr dataset); PSF, measurement, truth and
  dark frames are reordered alike, so the problem is always R, G, B.
- **Row flip**: ``flip_rows`` flips the rows of PSF, measurement, mask, shutter, filters and
  truth alike, a plain flip (row r to H - 1 - r), for files stored upside down: it turns them
  upright. The model takes a PSF's zero shift at row H // 2; a plain flip moves row H // 2 to
  H / 2 - 1 when H is even, so on upright files it is not a mere turn of the result: it moves
  the reconstruction by one row (14.4 against 43.8 dB on a sharp simulated scene of 48
  rows). On the MirFlickr pairs, stored upside down, it is what lines the result up with the
  lensed truth: a flip that keeps the zero shift at row H // 2 scored 0.20 dB lower with
  oracle FISTA-TV at 1/4 resolution (16.86 against 17.06 dB, all four pairs at 0 %).
- **PSF grid**: a PSF of the measurement's size (sensor grid), or of twice its size (the
  padded grid, zero shift at its centre, as the DiffuserCam MirFlickr PSF). A padded PSF is
  exact for scenes up to the padded size: the sensor is embedded in the centre of a virtual
  sensor of the PSF's size whose other pixels are masked out, so the model's measurement is
  the padded grid (``prob.sensor`` is the real sensor, ``metadata['window']`` its place).
- **Field** (the scene): ``sensor`` (the real sensor's size), ``full`` (twice it) or an
  explicit (H, W) in pixels of the reconstruction grid (after downsampling).
- **Truth**: (H, W), (H, W, 3), (C, H, W) or (C, K, H, W) (a gray scene of K frames, bands
  or planes also takes a (K, H, W) stack) on the scene field, or one larger and cut to it, at
  sensor or reconstruction resolution; colour, channel order, row flip and downsampling as
  above (it is never normalised: score it with a gain fit). One preparation,
  :func:`recon.truth.prepare_truth_like`, which ``lenslesscam metrics`` takes too; a truth of
  a smaller field than the scene's is refused here (a run scores whole arrays; ``metrics``
  scores its window), and so is a size that is one field on the grid and the other at sensor
  resolution.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from dataclasses import field as dc_field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import numpy.typing as npt

from recon.calibfile import DARK_CORRECTED_KINDS, calibration_kind
from recon.checks import (
    MeasurementWarning,
    check_field,
    check_filter_cube,
    check_pair,
    check_shutter,
    check_shutter_frames,
    warn_downsample_remainder,
)
from recon.formats import array_hash
from recon.inputwarnings import warn_input
from recon.preprocess import (
    box_downsample,
    downsample_masked,
    downsample_rows,
    normalise,
    normalise_factor,
    to_channel_first,
    to_gray,
)
from recon.readers import (
    FILTER_KEYS,
    EmptyPsfError,
    load_image,
    load_measurement,
    load_psf,
    load_psf_stack,
)

if TYPE_CHECKING:
    import torch

    from recon.models import ForwardModel

__all__ = [
    "MODEL_KINDS",
    "RECONSTRUCTION_KIND",
    "Problem",
    "ProblemSpec",
    "ProblemSpecError",
    "load_problem",
    "load_truth",
    "prepare_truth",
    "read_filters",
    "read_mask",
    "read_shutter",
    "read_truth",
]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
Array = npt.NDArray[Any]
PathLike = str | os.PathLike[str]
Dark = float | str | None

MODEL_KINDS: tuple[str, ...] = ("2d", "video", "spectral", "depth")
#: model kind -> ``kind`` of :func:`recon.reconfile.save_reconstruction`.
RECONSTRUCTION_KIND: dict[str, str] = {
    "2d": "image", "video": "video", "spectral": "spectral", "depth": "depth",
}
_NORMS = ("sum", "max", "l2", "none")


class ProblemSpecError(ValueError):
    """A :class:`ProblemSpec` value that cannot be; it names the value as each user wrote it.

    ``str()`` is ``problem: field must be ...``; :meth:`for_command_line` names the option
    (``--field must be ...``), :meth:`for_spec` the job spec's key (``data.field must be
    ...``): "problem: shutter (K, rows) is required" named neither.
    """

    #: what a message calls the value -> (its command-line option or None, its [data] key)
    NAMES: ClassVar[dict[str, tuple[str | None, str]]] = {
        "model": ("--model", "model"), "measurement": ("--meas", "measurement"),
        "psf": ("--psf", "psf"), "psf stack": ("--psf-stack", "psf"),
        "shutter": ("--shutter", "shutter"), "filters": ("--filters", "filters"),
        "downsample": ("--downsample", "downsample"), "field": ("--field", "field"),
        "color": ("--rgb", "color"), "channel order": ("--channel-order", "channel_order"),
        "dark": ("--dark / --psf-dark", "dark / data.psf_dark"),
        "psf normalisation": (None, "psf_normalise"),
        "measurement normalisation": (None, "measurement_normalise"),
    }

    def __init__(self, what: str, message: str, command_line: str | None = None) -> None:
        super().__init__(f"problem: {what} {message}")
        self.what, self.message = what, message
        self.command_line = command_line  # the whole message where the option reads otherwise

    def for_command_line(self) -> str:
        """The message naming the option (``--field must be ...``)."""
        if self.command_line is not None:
            return self.command_line
        option = self.NAMES.get(self.what, (None, ""))[0]
        return f"{option} {self.message}" if option else str(self)

    def for_spec(self) -> str:
        """The message naming the job spec's key (``data.field must be ...``)."""
        key = self.NAMES.get(self.what, (None, self.what))[1]
        return f"data.{key} {self.message}"


@dataclass(frozen=True)
class ProblemSpec:
    """What to load: files, dark levels and preprocessing (see the module docstring).

    ``psf`` is the PSF file of the 2d, video and spectral models; ``psf_stack`` the depth
    model's stack (a multi-page file, a folder of planes or a tuple of plane files).
    ``dark``/``psf_dark``: a number, ``'auto'`` or a dark-frame file (``psf_dark`` None: the
    same as ``dark``, except for a calibrated PSF or stack file, which is dark-subtracted
    already: none). ``psf_normalise``: ``auto`` is ``sum`` for a PSF, ``max`` for a stack.
    """

    meas: str
    model: str = "2d"
    psf: str | None = None
    psf_stack: str | tuple[str, ...] | None = None
    mask: str | None = None
    shutter: str | None = None
    filters: str | None = None
    truth: str | None = None
    dark: Dark = None
    psf_dark: Dark = None
    downsample: int = 1
    field: str | tuple[int, int] = "sensor"
    color: str = "gray"
    channel_order: str = "rgb"
    flip_rows: bool = False
    psf_normalise: str = "auto"
    meas_normalise: str = "max"

    def __post_init__(self) -> None:
        def bad(what: str, msg: str, command_line: str | None = None) -> ValueError:
            return ProblemSpecError(what, msg, command_line)

        if self.model not in MODEL_KINDS:
            raise bad("model", f"must be one of {', '.join(MODEL_KINDS)}, got {self.model!r}")
        if not self.meas:
            raise bad("measurement", "file is required")
        if self.model == "depth":
            if not self.psf_stack:
                raise bad("psf stack", "is required for the depth model")
            if self.psf:
                raise bad("psf", "is not used by the depth model (give the PSF stack)")
        else:
            if not self.psf:
                raise bad("psf", f"file is required for the {self.model} model")
            if self.psf_stack:
                raise bad("psf stack", "is only for the depth model")
        if self.model == "video" and not self.shutter:
            raise bad("shutter", "(K, rows) is required for the video model")
        if self.model != "video" and self.shutter:
            raise bad("shutter", f"is only for the video model (model is {self.model!r})")
        if self.model == "spectral" and not self.filters:
            raise bad("filters", "(K, H, W) cube is required for the spectral model")
        if self.model != "spectral" and self.filters:
            raise bad("filters", f"are only for the spectral model (model is {self.model!r})")
        ds = self.downsample
        if isinstance(ds, bool) or not isinstance(ds, int | np.integer) or ds < 1:
            raise bad("downsample", f"must be an integer >= 1, got {ds!r}")
        f = self.field
        if isinstance(f, str):
            if f not in ("sensor", "full"):
                raise bad("field", f"must be 'sensor', 'full' or (H, W), got {f!r}")
        elif (len(f) != 2 or not all(isinstance(n, int | np.integer)
                                     and not isinstance(n, bool) and n > 0 for n in f)):
            raise bad("field", f"must be (H, W) with positive integers, got {f!r}")
        else:
            object.__setattr__(self, "field", (int(f[0]), int(f[1])))
        if self.color not in ("gray", "rgb"):
            raise bad("color", f"must be 'gray' or 'rgb', got {self.color!r}")
        if self.channel_order not in ("rgb", "bgr"):
            raise bad("channel order", f"must be 'rgb' or 'bgr', got {self.channel_order!r}")
        if self.psf_normalise not in (*_NORMS, "auto"):
            raise bad("psf normalisation", f"must be auto, sum, max, l2 or none, got "
                      f"{self.psf_normalise!r}")
        if self.meas_normalise not in _NORMS:
            raise bad("measurement normalisation", f"must be sum, max, l2 or none, got "
                      f"{self.meas_normalise!r}")
        if self.model == "depth" and self.color == "rgb":
            raise bad("color", "must be gray for the depth model",
                      "--rgb is not for the depth model (its PSF stack reconstructs gray)")
        if isinstance(self.psf_stack, list):
            object.__setattr__(self, "psf_stack", tuple(self.psf_stack))
        for d in (self.dark, self.psf_dark):
            if isinstance(d, bool) or not (d is None or isinstance(d, int | float | str)):
                raise bad("dark", f"must be a number, 'auto' or a file, got {d!r}")

    # -- the [data] table of a job spec ------------------------------------------------------
    @classmethod
    def from_data_section(cls, d: Mapping[str, Any]) -> ProblemSpec:
        """The spec of a (normalised) ``[data]`` table of a UDN job spec."""
        depth = d.get("model", "2d") == "depth"
        psf = d.get("psf")
        fld = d.get("field", "sensor")
        return cls(
            meas=d["measurement"], model=d.get("model", "2d"),
            psf=None if depth else psf,
            psf_stack=(tuple(psf) if isinstance(psf, list) else psf) if depth else None,
            mask=d.get("mask"), shutter=d.get("shutter"), filters=d.get("filters"),
            truth=d.get("truth"), dark=d.get("dark"), psf_dark=d.get("psf_dark"),
            downsample=int(d.get("downsample", 1)),
            field=fld if isinstance(fld, str) else (int(fld[0]), int(fld[1])),
            color=d.get("color", "gray"), channel_order=d.get("channel_order", "rgb"),
            flip_rows=bool(d.get("flip_rows", False)),
            psf_normalise=d.get("psf_normalise", "auto"),
            meas_normalise=d.get("measurement_normalise", "max"),
        )

    def to_data_section(self) -> dict[str, Any]:
        """The ``[data]`` table of a job spec (None values left out)."""
        stack = self.psf_stack
        out: dict[str, Any] = {
            "model": self.model,
            "psf": list(stack) if isinstance(stack, tuple) else (stack or self.psf),
            "measurement": self.meas, "mask": self.mask, "shutter": self.shutter,
            "filters": self.filters, "truth": self.truth, "dark": self.dark,
            "psf_dark": self.psf_dark, "downsample": int(self.downsample),
            "field": self.field if isinstance(self.field, str) else list(self.field),
            "color": self.color, "channel_order": self.channel_order,
            "flip_rows": self.flip_rows, "psf_normalise": self.psf_normalise,
            "measurement_normalise": self.meas_normalise,
        }
        return {k: v for k, v in out.items() if v is not None}

    def with_changes(self, **changes: Any) -> ProblemSpec:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for metadata)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, v in out.items():
            if isinstance(v, tuple):
                out[k] = list(v)
        return out


@dataclass
class Problem:
    """A loaded problem: the forward model, the measurement, and what was done to get them."""

    spec: ProblemSpec
    model: ForwardModel
    meas: F32
    mask: F32 | None
    psf: F32
    truth: F32 | None
    shutter: F64 | None
    filters: F64 | None
    sensor: tuple[int, int]
    inputs: dict[str, dict[str, Any]]
    hashes: dict[str, str | None]
    metadata: dict[str, Any] = dc_field(default_factory=dict)

    @property
    def kind(self) -> str:
        """The model kind (2d, video, spectral, depth)."""
        return self.spec.model

    @property
    def reconstruction_kind(self) -> str:
        """``kind`` for :func:`recon.reconfile.save_reconstruction`."""
        return RECONSTRUCTION_KIND[self.spec.model]

    def psf_per_channel(self) -> F32:
        """The PSF with one plane per measurement channel.

        A gray PSF read for colour data (``--rgb``; the model shares it across the channels)
        is repeated for each, for the callers that take one PSF per channel (plan, trade).
        Any other PSF as it is.
        """
        c = int(self.meas.shape[0])
        if self.psf.ndim == 3 and self.psf.shape[0] == 1 and c > 1 and self.kind != "depth":
            return np.repeat(self.psf, c, axis=0)
        return self.psf


# --------------------------------------------------------------------------------------------
# Readers, one per file kind
# --------------------------------------------------------------------------------------------


def _is_calibration_npz(p: Path) -> bool:
    if p.suffix.lower() != ".npz" or not p.is_file():
        return False
    try:
        with np.load(p, allow_pickle=False) as z:
            return "metadata" in z.files
    except Exception:
        return False


def _read(path: PathLike, what: str, prefer: Sequence[str], key: str | None = None) -> Array:
    p = Path(path)
    try:
        return np.asarray(load_image(p, key=key, prefer=prefer))
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} file not found: {p}") from None
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if str(p) in msg else f"{what} file {p}: {msg}") from None


def read_mask(path: PathLike) -> F32:
    """A mask file as (H, W) float32 0/1 (1 = measured); the rule is in the module docstring.

    Reads arrays and images, and the pixel-maps ``.npz`` of ``calibrate darks``.
    """
    p = Path(path)
    if _is_calibration_npz(p):
        from recon.calibfile import load_pixel_mask

        raw: Array = load_pixel_mask(p)
    else:
        raw = _read(p, "mask", ("mask", "arr_0", "data", "image"))
    if raw.ndim == 3 and raw.shape[0] == 1:
        raw = raw[0]
    if raw.ndim != 2:
        raise ValueError(f"mask file {p} must be a 2D (H, W) array, got shape {raw.shape}")
    if raw.dtype.kind == "b":
        return np.asarray(raw, dtype=np.float32)
    if raw.dtype.kind in "iu":
        return np.asarray(raw != 0, dtype=np.float32)
    if raw.dtype.kind != "f":
        raise ValueError(f"mask file {p} has unsupported dtype {raw.dtype}")
    n_nan = int(np.count_nonzero(~np.isfinite(raw)))
    if n_nan:
        raise ValueError(f"mask file {p} has {n_nan} NaN or infinite values "
                         f"({100 * n_nan / raw.size:.3g}% of its pixels)")
    other = (raw != 0) & (raw != 1)
    if other.any():
        v = float(raw[other].flat[0])
        raise ValueError(f"mask file {p} has {int(other.sum())} values other than 0 and 1 "
                         f"(e.g. {v:g}); a mask is 1 = measured, 0 = erased")
    return raw.astype(np.float32)


def read_shutter(path: PathLike, rows: int | None = None) -> tuple[F64, dict[str, Any]]:
    """A shutter function M (K, rows) and its metadata (the calibration ``.npz`` checked).

    Reads the ``.npz`` that ``lenslesscam calibrate shutter`` writes (hashes checked, its
    ``timing``/``row_factor`` in the metadata) and plain arrays (``.npy``, ``.npz`` with a
    ``shutter`` entry, TIFF). Refuses (ValueError, one line) non-finite or negative values, an
    all-zero function, an all-zero time bin and more bins than rows
    (:func:`recon.checks.check_shutter`, :func:`recon.checks.check_shutter_frames`); rows that
    integrate no light are named in a :class:`~recon.checks.MeasurementWarning`. ``rows``: the
    measurement's rows, when known: a file stored (rows, K) is named as transposed (it was
    "K = 48 time bins for 9 rows").
    """
    p = Path(path)
    meta: dict[str, Any] = {}
    if _is_calibration_npz(p):
        from recon.calibfile import load_shutter

        arr, meta = load_shutter(p)
        m = np.asarray(arr, dtype=np.float64)
    else:
        m = _read(p, "shutter", ("shutter", "M", "arr_0", "data")).astype(np.float64)
    if m.ndim != 2:
        raise ValueError(f"shutter file {p} must be a (K, rows) array, got shape {m.shape}")
    if not np.all(np.isfinite(m)) or np.any(m < 0):
        raise ValueError(f"shutter file {p} must be finite and non-negative")
    if not np.any(m > 0):
        raise ValueError(f"shutter file {p} is all zero: no row integrates any light")
    if rows is not None and m.shape[0] == rows and m.shape[1] != rows:
        raise ValueError(f"shutter file {p} has shape {m.shape}: the shutter function is "
                         f"(K, rows), (K, {rows}) for this measurement; this one looks "
                         "transposed (rows, K)")
    check_shutter_frames(m.shape[0], m.shape[1], f"shutter file {p}")
    check_shutter(m, f"shutter file {p}")
    return m, meta


def read_filters(path: PathLike, sensors: Sequence[tuple[int, int]] = ()) -> F64:
    """A spectral filter cube (K, H, W) (arrays, ``.mat``, the filter-cube TIFF).

    ``sensors``: the (H, W) a band may have (the sensor at the resolutions the caller takes).
    A cube whose first two axes are one of them and whose last two are not is in (H, W, K)
    layout (SpectralDiffuserCam's ``.mat``) and is returned as (K, H, W), as ``lenslesscam
    calibrate filters`` reads it; one that fits both layouts is refused. The values follow the
    one rule of ``calibrate filters`` (:func:`recon.checks.check_filter_cube`: no NaN, no
    negative transmission, no all-zero band; rounding below 0 clipped).
    """
    p = Path(path)
    f = _read(p, "filter cube", FILTER_KEYS).astype(np.float64)
    if f.ndim != 3:
        raise ValueError(f"filter cube file {p} must be a (K, H, W) array, got shape {f.shape}")
    fits = {tuple(int(n) for n in s) for s in sensors}
    khw, hwk = tuple(f.shape[1:]) in fits, tuple(f.shape[:2]) in fits
    if khw and hwk:
        raise ValueError(f"filter cube file {p} of shape {f.shape} fits the sensor as (K, H, W) "
                         "and as (H, W, K): say which with lenslesscam calibrate filters --cube "
                         "FILE --sensor HxW --layout khw|hwk --out cube.tif (it writes the "
                         "layout recon reads)")
    if hwk:
        f = np.ascontiguousarray(np.moveaxis(f, -1, 0))
    return np.asarray(check_filter_cube(f, f"filter cube file {p}"), dtype=np.float64)


def read_truth(path: PathLike, *, color: str = "gray", channel_order: str = "rgb",
               key: str | None = None) -> F32:
    """A ground-truth scene as (C, K, H, W) float32, R, G, B (or gray) as ``color`` asks.

    Accepts (H, W), (H, W, 3|4) (alpha dropped), (C, H, W) and (C, K, H, W); ``key``: the
    variable of an NPZ/MAT file.
    """
    p = Path(path)
    t = _read(p, "truth", ("truth", "scene", "x", "arr_0", "data"), key=key).astype(np.float32)
    if t.ndim == 3 and t.shape[-1] == 4 and t.shape[0] not in (1, 3, 4):
        t = t[..., :3]  # RGBA: the alpha channel is not light
    if not np.all(np.isfinite(t)):
        raise ValueError(f"truth file {p} has NaN or infinite values")
    if t.ndim in (2, 3):
        try:
            t = to_channel_first(t)[:, None]
        except ValueError as exc:
            raise ValueError(f"truth file {p}: {exc}") from None
    if t.ndim != 4:
        raise ValueError(f"truth file {p} has shape {t.shape}: expected (H, W), (H, W, 3), "
                         "(C, H, W) or (C, K, H, W)")
    if t.shape[0] not in (1, 3):
        raise ValueError(f"truth file {p} has {t.shape[0]} channels: expected 1 or 3")
    if channel_order == "bgr" and t.shape[0] == 3:
        t = t[::-1]
    if color == "gray" and t.shape[0] == 3:
        t = to_gray(t)
    elif color == "rgb" and t.shape[0] == 1:
        raise ValueError(f"truth file {p} is grayscale; the reconstruction is rgb")
    return np.ascontiguousarray(t, dtype=np.float32)


def load_truth(spec: ProblemSpec, scene_shape: Sequence[int], *,
               sensor: tuple[int, int] | None = None) -> F32:
    """The truth of ``spec`` on the reconstruction grid of a scene (C, K, H, W).

    Prepared as :func:`prepare_truth` prepares it, with the spec's colour, channel order, row
    flip and downsampling, the scene's field (its H, W) and the sensor's field on the grid
    (``sensor``; by default from ``spec.field``: the scene's for ``sensor``, half of it for
    ``full``, the measurement file's size over the downsampling for an explicit field).
    """
    if spec.truth is None:
        raise ValueError("problem: no truth file given")
    if sensor is None:
        sensor = _sensor_on_grid(spec, scene_shape)
    return prepare_truth(spec.truth, scene_shape, color=spec.color,
                         channel_order=spec.channel_order, flip_rows=spec.flip_rows,
                         downsample=spec.downsample, sensor=sensor,
                         kind=RECONSTRUCTION_KIND[spec.model])


def _sensor_on_grid(spec: ProblemSpec, scene_shape: Sequence[int]) -> tuple[int, int] | None:
    """The sensor's field on the reconstruction grid of a scene of ``spec`` (None: unknown)."""
    h, w = int(scene_shape[-2]), int(scene_shape[-1])
    if spec.field == "sensor":
        return h, w
    if spec.field == "full":
        return h // 2, w // 2
    from recon.readers import _MEAS_KEYS

    try:  # an explicit field: the measurement's size (its file only read, nothing checked)
        a = np.asarray(load_image(Path(spec.meas), prefer=_MEAS_KEYS))
        hw = a.shape if a.ndim == 2 else to_channel_first(a).shape[-2:]
    except (OSError, ValueError):
        return None
    ds = int(spec.downsample)
    return int(hw[0]) // ds, int(hw[1]) // ds


def prepare_truth(path: PathLike, scene_shape: Sequence[int], *, color: str = "gray",
                  channel_order: str = "rgb", flip_rows: bool = False,
                  downsample: int = 1, key: str | None = None,
                  sensor: tuple[int, int] | None = None, kind: str | None = None) -> F32:
    """A truth file read and prepared as a measurement with these settings is (C, K, H, W).

    :func:`recon.truth.prepare_truth_like`, the one preparation (``lenslesscam metrics``
    takes it too): colour, channel order, row flip; a ``(K, H, W)`` stack for a gray scene of
    K frames, bands or planes; a truth of the scene's field or of the ``sensor``'s (on the
    grid, or at sensor resolution: box-downsampled), one larger than the scene's cut to it.
    Refused in one line: a truth of a smaller field than the scene's (what a run scores, in
    its run record, ``jobs combine`` and a batch, is the whole array: ``lenslesscam metrics``
    scores such a truth on its window), a size that could be either field, and a constant
    truth (all zero or one value: no range to score against; ``lenslesscam metrics`` scores
    a flat target with an explicit ``--data-range``).
    """
    from recon.truth import prepare_truth_like

    scene = tuple(int(n) for n in scene_shape)
    layout = {"color": color, "channel_order": channel_order, "flip_rows": bool(flip_rows),
              "downsample": int(downsample)}
    t, prepared = prepare_truth_like(path, scene, layout, kind=kind, field=(scene[2], scene[3]),
                                     sensor=sensor, key=key, dtype=np.float32)
    if "scored_window" in prepared:
        th, tw = prepared["field"]["truth"]
        raise ValueError(f"truth file {path} covers {th}x{tw} on the reconstruction grid, part "
                         f"of the scene field {scene[2]}x{scene[3]}: a run's scores (run "
                         "record, jobs combine, batch) compare whole arrays and the scene "
                         "around the truth is unknown; give a truth of the scene field, or "
                         "score the result with lenslesscam metrics (it scores the truth's "
                         "window)")
    lo, hi = float(t.min()), float(t.max())
    if lo == hi:  # scored at the end of the work: trade stopped after its first setting
        raise ValueError(f"truth file {path} is constant (every value is {lo:g} on the "
                         "reconstruction grid): nothing to score against (PSNR and SSIM need "
                         "the truth's range); give the scene's truth, or no truth")
    return t


# --------------------------------------------------------------------------------------------
# The loader
# --------------------------------------------------------------------------------------------


def _dark_arg(d: Dark) -> Any:
    if isinstance(d, str) and d != "auto":
        return Path(d)
    return d


#: the inputs a problem names by file hash alone, when they are dark-frame files (a run record
#: written before they were hashed lacks them: such a record is not of other data)
DARK_INPUTS = frozenset({"dark", "psf_dark"})


def _file_hash(path: Any) -> str | None:
    from recon.formats import file_hash

    if isinstance(path, str | os.PathLike) and Path(path).is_file():
        return file_hash(path)
    return None


def _describe(path: Any, arr: Array | None) -> dict[str, Any]:
    from recon.formats import file_hash

    out: dict[str, Any] = {"path": list(path) if isinstance(path, tuple) else path}
    if isinstance(path, tuple | list):
        out["file_hash"] = [file_hash(p) for p in path]
    elif path is not None and Path(path).is_file():
        out["file_hash"] = file_hash(path)
    if arr is not None:
        out["array_hash"] = array_hash(arr)
        out["shape"] = list(arr.shape)
    return out


def _embed(a: Array, shape: tuple[int, int], offset: tuple[int, int]) -> Array:
    """``a`` (..., h, w) placed at ``offset`` in zeros of (..., *shape)."""
    out = np.zeros((*a.shape[:-2], *shape), dtype=a.dtype)
    h, w = a.shape[-2:]
    out[..., offset[0]:offset[0] + h, offset[1]:offset[1] + w] = a
    return out


def _norm(mode: str) -> Any:
    return None if mode == "none" else mode


def load_problem(spec: ProblemSpec, *, dtype: torch.dtype | None = None,
                 device: torch.device | str = "cpu") -> Problem:
    """Read, dark-correct, downsample and check the inputs of ``spec``; build the model.

    Raises FileNotFoundError or ValueError with one line naming the file at fault.

    The :class:`~recon.checks.MeasurementWarning` s and :class:`~recon.psfcheck.PsfWarning` s
    the inputs raise (a raw frame read without a dark level, many zero pixels without a mask,
    saturation, a constant or clipped PSF) are kept, as text, in
    ``metadata['warnings']`` (so a run record, a batch item and a result's metadata say them
    too), whatever the warning filters say; the filters decide, as ever, what is shown. They
    are collected in this thread only (:mod:`recon.inputwarnings`): loads in other threads, and
    their warnings, are neither blocked nor recorded here.
    """
    from recon.inputwarnings import collect_input_warnings

    with collect_input_warnings() as got:
        prob = _load_problem(spec, dtype=dtype, device=device)
    prob.metadata["warnings"] = list(got)
    return prob


def _load_problem(spec: ProblemSpec, *, dtype: torch.dtype | None,
                  device: torch.device | str) -> Problem:
    """:func:`load_problem` without its collection of warnings."""
    import torch

    from recon.models import build_model

    dt = torch.float32 if dtype is None else dtype
    ds = int(spec.downsample)
    color: Any = spec.color
    order: Any = spec.channel_order
    dark = _dark_arg(spec.dark)
    psf_dark = _dark_arg(spec.psf_dark) if spec.psf_dark is not None else dark
    psf_file = spec.psf_stack if spec.model == "depth" else spec.psf
    # a calibrated PSF (or stack) is dark-subtracted already: the measurement's dark level
    # would take a second one off it (a quarter of a simulated bench PSF's energy)
    psf_dark_corrected = isinstance(psf_file, str) and calibration_kind(psf_file) in (
        DARK_CORRECTED_KINDS)
    if spec.psf_dark is None and psf_dark_corrected:
        psf_dark = None
    elif psf_dark_corrected and psf_dark not in (None, 0, 0.0):
        # given by the user: taken, and said (a second dark off a calibrated PSF)
        warn_input(f"PSF file {psf_file} is a calibrated PSF, dark-subtracted already: the "
                      f"PSF dark {spec.psf_dark} takes a second dark level off it (leave "
                      "psf_dark out, or 0)", MeasurementWarning, stacklevel=2)

    # the mask first, when it reads: the measurement's check of negative pixels counts the
    # measured ones (a mask that does not read is said below, after the measurement's checks)
    file_mask = None
    if spec.mask is not None:
        try:
            file_mask = read_mask(spec.mask)
        except (OSError, ValueError):
            file_mask = None

    # measurement (full resolution, counts)
    meas = load_measurement(spec.meas, dark=dark, channels=color, channel_order=order,
                            normalise=None, unmasked=spec.mask is None, measured=file_mask)
    if spec.flip_rows:
        meas = np.ascontiguousarray(meas[:, ::-1])
    c, h_full, w_full = (int(s) for s in meas.shape)
    coarse = (h_full // ds, w_full // ds)
    if min(coarse) < 1:
        raise ValueError(f"measurement file {spec.meas} ({h_full}x{w_full}) is smaller than "
                         f"the downsampling factor {ds}")

    # PSF or stack (full resolution, not normalised)
    psf_label = spec.psf_stack if spec.model == "depth" else spec.psf
    try:
        if spec.model == "depth":
            stack_arg: Any = spec.psf_stack
            psf = load_psf_stack(list(stack_arg) if isinstance(stack_arg, tuple) else stack_arg,
                                 dark=psf_dark, normalise=None)
        else:
            # a gray PSF file with a colour measurement: one PSF shared by R, G and B (the layout
            # of the MirFlickr dataset's original code); a colour file gives one PSF per channel
            psf = load_psf(str(spec.psf), dark=psf_dark, channels=color, channel_order=order,
                           normalise=None, shared_gray=color == "rgb")
    except EmptyPsfError as exc:
        if spec.psf_dark is None and dark is not None:
            # the measurement's dark level reached a PSF that has its own (or none)
            raise ValueError(f"{exc}: the measurement's dark ({spec.dark}) is subtracted from "
                             "the PSF too unless a PSF dark is given (--psf-dark, psf_dark; 0: "
                             "none)") from None
        raise
    if spec.flip_rows:
        psf = np.ascontiguousarray(psf[:, ::-1])
    psf_hw = (int(psf.shape[-2]), int(psf.shape[-1]))
    if psf_hw == (h_full, w_full):
        padded = False
    elif psf_hw == (2 * h_full, 2 * w_full):
        padded = True
    else:
        raise ValueError(
            f"PSF file {psf_label} has shape {tuple(psf.shape)}: expected the measurement's size "
            f"{h_full}x{w_full} (sensor grid) or twice it, {2 * h_full}x{2 * w_full} (padded "
            f"grid), before downsampling")
    offset = (h_full - h_full // 2, w_full - w_full // 2)

    # mask
    raw_mask = None
    mask_coarse = False
    if spec.mask is not None:
        raw_mask = file_mask if file_mask is not None else read_mask(spec.mask)
        if spec.flip_rows:
            raw_mask = np.ascontiguousarray(raw_mask[::-1])
        if raw_mask.shape == (h_full, w_full):
            pass
        elif ds > 1 and raw_mask.shape == coarse:
            if padded:
                raise ValueError(f"mask file {spec.mask} is at the reconstruction resolution "
                                 f"{coarse}; with a padded-grid PSF give it at the sensor's "
                                 f"{h_full}x{w_full}")
            mask_coarse = True
        else:
            more = f" or {coarse[0]}x{coarse[1]} (downsampled)" if ds > 1 else ""
            raise ValueError(f"mask file {spec.mask} is {raw_mask.shape[0]}x"
                             f"{raw_mask.shape[1]}; the measurement is {h_full}x{w_full}{more}")
        if not raw_mask.any():
            raise ValueError(f"mask file {spec.mask} marks no pixel as measured (all erased)")


    if not padded:
        warn_downsample_remainder(h_full, w_full, ds)

    # embed the sensor in the padded grid of a padded PSF
    grid_full = psf_hw
    if padded:
        window = np.zeros(grid_full, np.float32)
        window[offset[0]:offset[0] + h_full, offset[1]:offset[1] + w_full] = (
            1.0 if raw_mask is None else raw_mask)
        meas = _embed(meas, grid_full, offset)
        raw_mask = window

    # downsample measurement and mask (the one mask rule)
    mask: F32 | None = None
    if raw_mask is None:
        meas_d = box_downsample(meas, ds).astype(np.float32)
    elif mask_coarse:
        mask = (raw_mask > 0.5).astype(np.float32)
        # erased coarse pixels hold no data: 0, whatever the file held (a hot pixel set the
        # measurement's scale and the residual)
        meas_d = np.where(mask > 0, box_downsample(meas, ds), 0.0).astype(np.float32)
    else:
        meas_d, mask = downsample_masked(meas, raw_mask, ds)  # the one mask rule
    sel = slice(None) if mask is None else (mask > 0)
    meas_sel = meas_d[:, sel] if mask is not None else meas_d
    if not np.any(meas_sel > 0):
        where = " on its measured pixels" if spec.mask is not None else ""
        raise ValueError(f"measurement file {spec.meas} is all zero{where} (after dark "
                         "subtraction and downsampling)")
    mn = _norm(spec.meas_normalise)
    # the factor divided out (file units after dark subtraction, on the reconstruction grid):
    # a result times it is the scene in the measurement's units (for a unit-sum PSF)
    meas_scale = 1.0
    if mn is not None:
        meas_scale = normalise_factor(meas_d, mn)
        meas_d = normalise(meas_d, mn).astype(np.float32)

    # PSF downsampling and normalisation
    psf_d = box_downsample(psf, ds).astype(np.float32)
    for i in range(psf_d.shape[0]):
        if not np.any(psf_d[i] > 0):
            what = f"plane {i}" if spec.model == "depth" else f"channel {i}"
            raise ValueError(f"PSF file {psf_label}: {what} is all zero after downsampling")
    pn: Any = spec.psf_normalise
    if pn == "auto":
        pn = "max" if spec.model == "depth" else "sum"
    if _norm(pn) is not None:
        psf_d = normalise(psf_d, pn).astype(np.float32)
    check_pair(psf_d, meas_d, psf_is_stack=spec.model == "depth")
    if spec.model == "depth" and c != 1:
        raise ValueError(f"measurement file {spec.meas}: the depth model takes a grayscale "
                         "measurement")
    grid = (int(meas_d.shape[-2]), int(meas_d.shape[-1]))

    # shutter (video) and filters (spectral), on the model's grid
    shutter: F64 | None = None
    shutter_meta: dict[str, Any] = {}
    if spec.model == "video":
        m, shutter_meta = read_shutter(str(spec.shutter), rows=h_full)
        if spec.flip_rows:
            m = np.ascontiguousarray(m[:, ::-1])
        if m.shape[1] == h_full:
            if padded:
                m = _embed(m[:, :, None], (grid_full[0], 1), (offset[0], 0))[:, :, 0]
            shutter = downsample_rows(m, ds) if ds > 1 else m
        elif ds > 1 and m.shape[1] == coarse[0] and not padded:
            shutter = m
        else:
            more = f" or (K, {coarse[0]}) (downsampled)" if ds > 1 and not padded else ""
            raise ValueError(f"shutter file {spec.shutter} has shape {m.shape}: the shutter "
                             f"function must be (K, {h_full}) for a measurement of {h_full} "
                             f"rows{more}")
        # again on the reconstruction grid: K against the sensor's rows there (a padded
        # grid's other rows see no light), and the bins (downsampling drops the last rows)
        where = f" (downsampled {ds}x)" if ds > 1 and m.shape[1] == h_full else ""
        check_shutter_frames(shutter.shape[0], coarse[0], f"shutter file {spec.shutter}{where}",
                             downsample=ds)
        check_shutter(shutter, f"shutter file {spec.shutter}{where}", rows_warning=False)
    filters: F64 | None = None
    filters_scale: float | None = None
    if spec.model == "spectral":
        # (H, W, K) cubes (SpectralDiffuserCam's .mat) are read as calibrate filters reads them
        f = read_filters(str(spec.filters), sensors=[(h_full, w_full), coarse] if ds > 1
                         else [(h_full, w_full)])
        if spec.flip_rows:
            f = np.ascontiguousarray(f[:, ::-1])
        if f.shape[1:] == (h_full, w_full):
            if padded:
                f = _embed(f, grid_full, offset)
            filters = box_downsample(f, ds).astype(np.float64) if ds > 1 else f
        elif ds > 1 and f.shape[1:] == coarse and not padded:
            filters = f
        else:
            more = f" or {coarse[0]}x{coarse[1]} (downsampled)" if ds > 1 and not padded else ""
            raise ValueError(f"filter cube file {spec.filters} has shape {f.shape}: its bands "
                             f"must be the measurement's {h_full}x{w_full}{more}, as (K, H, W) "
                             "or (H, W, K); lenslesscam calibrate filters --cube FILE --sensor "
                             "HxW --out cube.tif checks and converts a cube")
        if filters is not f:  # a band that only the pixels downsampling drops held
            check_filter_cube(filters, f"filter cube file {spec.filters} (downsampled {ds}x)")
        # scaled to a maximum of 1, as the measurement: a cube in percent or in [0, 1] makes
        # one problem, so a fixed tau means one thing (calibrate filters' default 'max')
        filters_scale = float(filters.max())
        filters = filters / filters_scale

    # scene field, in pixels of the reconstruction grid
    if spec.field == "sensor":
        fld = coarse
    elif spec.field == "full":
        fld = (2 * coarse[0], 2 * coarse[1])
    else:
        fld = (int(spec.field[0]), int(spec.field[1]))
    # a scene point farther out than the PSF reaches sends no light to the sensor
    check_field(fld, coarse, (int(psf_d.shape[-2]), int(psf_d.shape[-1])))
    psf_arg: Any = psf_d
    if spec.model != "depth" and psf_d.shape[0] == 1:
        psf_arg = psf_d[0]
    model = build_model(spec.model, psf_arg, channels=c if spec.model != "depth" else None,
                        mask=mask, shutter=shutter, filters=filters, field=fld, dtype=dt,
                        device=device)

    truth = (None if spec.truth is None else
             load_truth(spec, tuple(model.scene_shape), sensor=coarse))

    inputs: dict[str, dict[str, Any]] = {
        "psf": _describe(psf_label, psf_d),
        "measurement": {**_describe(spec.meas, meas_d), "meas_scale": meas_scale}}
    if spec.mask is not None:
        inputs["mask"] = _describe(spec.mask, mask)
    if shutter is not None:
        inputs["shutter"] = _describe(spec.shutter, shutter)
    if filters is not None:
        inputs["filters"] = _describe(spec.filters, filters)
    if truth is not None:
        inputs["truth"] = _describe(spec.truth, truth)
    for key, d in (("dark", spec.dark), ("psf_dark", spec.psf_dark)):  # DARK_INPUTS
        if isinstance(d, str) and d != "auto":  # a dark-frame file: its hash (what it did is
            inputs[key] = _describe(d, None)    # in the measurement's / PSF's array hash)
    hashes = {"psf": _file_hash(psf_label), "meas": _file_hash(spec.meas),
              "mask": _file_hash(spec.mask), "shutter": _file_hash(spec.shutter),
              "filters": _file_hash(spec.filters), "truth": _file_hash(spec.truth)}
    meta: dict[str, Any] = {
        "downsample": ds, "dark": spec.dark, "psf_dark": spec.psf_dark,
        "psf_dark_corrected_file": psf_dark_corrected,
        # the dark level the PSF was read with (psf_dark is the one given: None takes the
        # measurement's, or none for a calibrated PSF)
        "psf_dark_applied": (spec.psf_dark if spec.psf_dark is not None else
                             None if psf_dark_corrected else spec.dark),
        "color": spec.color,
        "channel_order": spec.channel_order, "flip_rows": spec.flip_rows,
        "field": list(fld), "sensor": list(coarse), "grid": list(grid),
        "psf_grid": "padded" if padded else "sensor",
        "mask_rule": "a coarse pixel is measured when any sensor pixel under it is; its value "
                     "is the mean of the measured ones",
        "measured_fraction": None if mask is None else float(mask.mean()),
        "mask_hash": None if mask is None else array_hash(mask),
        "psf_normalise": pn, "meas_normalise": spec.meas_normalise,
        # what the measurement was divided by (meas_normalise; 1.0 for none), in the file's
        # units after dark subtraction, so a result's absolute scale can be recovered
        "meas_scale": meas_scale,
        # what the filter cube was divided by (its maximum; spectral only)
        **({} if filters_scale is None else {"filters_scale": filters_scale}),
    }
    if spec.model != "depth" and color == "rgb" and psf.shape[0] == 1:
        meta["psf_channels"] = "one gray PSF shared by R, G and B"
    if padded:
        meta["window"] = {"offset_sensor_px": list(offset), "sensor_px": [h_full, w_full]}
    if shutter_meta:
        meta["shutter_file"] = {k: shutter_meta.get(k) for k in ("method", "bin_lines",
                                                                 "row_factor", "format")}
    return Problem(spec, model, meas_d, mask, psf_d, truth, shutter, filters, coarse, inputs,
                   hashes, meta)
