"""Small real lensless data shipped with the package, and the code that made it.

The files in ``recon/samples/`` are downsampled copies of public DiffuserCam data (Waller Lab,
UC Berkeley, BSD-3-Clause; provenance in ``recon/samples/README.md`` and
``recon/samples/samples.json``). :func:`build_samples` regenerates them from the full files in
the shared data folder (:func:`shared_data_dir`), so every number in them can be traced.

Accessors return arrays in the project's conventions (float32; PSF and measurement
``(C, H, W)``, PSF stack ``(K, H, W)``, scene ``(C, K, H, W)``), through the same loaders as
user files (:mod:`recon.io`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from recon import io as rio
from recon.atomic import atomic_write, atomic_write_json
from recon.formats import FORMAT_VERSION, file_hash, provenance

__all__ = [
    "DEPTH_AXIAL_BIN",
    "DEPTH_DARK",
    "DEPTH_DOWNSAMPLE",
    "DLMD_DOWNSAMPLE",
    "DLMD_PAIR",
    "LENSED_SCENES",
    "SAMPLES_DIR",
    "TUTORIAL_DOWNSAMPLE",
    "build_samples",
    "depth_measurement",
    "depth_planes",
    "depth_psf_stack",
    "dlmd_pair_paths",
    "false_color_calib_path",
    "lensed_scene",
    "lensed_scene_names",
    "prepare_lensed_scene",
    "sample_path",
    "shared_data_dir",
    "tutorial_measurement",
    "tutorial_psf",
]

F32 = npt.NDArray[np.float32]

#: Folder of the bundled sample files.
SAMPLES_DIR = Path(__file__).resolve().with_name("samples")

#: Lensed ground-truth scenes of the DiffuserCam Lensless MirFlickr dataset: name -> content.
LENSED_SCENES: dict[str, str] = {"im408": "bottle caps", "im740": "crab", "im65": "butterfly"}

#: Lateral downsampling of the DiffuserCam tutorial data (1200x1600 -> 150x200).
TUTORIAL_DOWNSAMPLE = 8
#: Lateral downsampling of the 3D data (270x320 -> 135x160).
DEPTH_DOWNSAMPLE = 2
#: Axial binning of the 44-plane PSF stack (pairs of planes averaged -> 22 planes), as the
#: DiffuserCam 3D code's ``axial_downsample = 2``.
DEPTH_AXIAL_BIN = 2
#: Camera bias of ``example_raw.png`` (DiffuserCam_settings.m: ``image_bias = 100``).
DEPTH_DARK = 100.0

#: The real measurement / lensed-truth pair of the DiffuserCam Lensless MirFlickr dataset that
#: is bundled (butterfly), with the dataset's effective PSF, and its lateral downsampling.
DLMD_PAIR = "im65"
DLMD_DOWNSAMPLE = 4

_FILES = {
    "tutorial_psf": "tutorial_psf.npy",
    "tutorial_measurement": "tutorial_hand.npy",
    "depth": "depth_usaf.npz",
    "false_color_calib": "false_color_calib.mat",
    "manifest": "samples.json",
    "dlmd_measurement": f"dlmd_{DLMD_PAIR}_diffuser.npy",
    "dlmd_truth": f"dlmd_{DLMD_PAIR}_lensed.npy",
    "dlmd_psf": "dlmd_psf_padded_bgr.npy",
    **{f"lensed_{n}": f"lensed_{n}.npy" for n in LENSED_SCENES},
}

#: Shape (H, W) of the tutorial samples and of the prepared lensed scenes.
TUTORIAL_SHAPE = (150, 200)


def sample_path(name: str) -> Path:
    """Path of a bundled sample file by its short name (see ``_FILES``) or file name.

    Raises FileNotFoundError if the file is missing from the installation.
    """
    fname = _FILES.get(name, name)
    p = SAMPLES_DIR / fname
    if fname not in _FILES.values():
        raise ValueError(f"unknown sample {name!r}; known: {', '.join(sorted(_FILES))}")
    if not p.is_file():
        raise FileNotFoundError(
            f"{p}: bundled sample file is missing (rebuild with recon.samples.build_samples)"
        )
    return p


def shared_data_dir() -> Path | None:
    """Folder of the full real data (``shared/data``), or None when it is not available.

    ``LENSLESSCAM_SHARED_DATA`` names it explicitly (None if that is not a folder); otherwise
    ``shared/data`` inside the repository root or beside it (``../shared/data``) is used.
    """
    env = os.environ.get("LENSLESSCAM_SHARED_DATA")
    if env:
        p = Path(env).expanduser()
        return p if p.is_dir() else None
    root = Path(__file__).resolve().parents[1]
    for cand in (root / "shared" / "data", root.parent / "shared" / "data"):
        if cand.is_dir():
            return cand
    return None


def false_color_calib_path() -> Path:
    """Bundled copy of SpectralDiffuserCam's ``false_color_calib.mat`` (red/green/blue, 65)."""
    return sample_path("false_color_calib")


def tutorial_psf(normalise: rio.NormMode | None = "sum") -> F32:
    """DiffuserCam tutorial PSF at 1/8 scale, ``(1, 150, 200)`` float32, unit sum by default.

    Dark level already subtracted (the tutorial's ``mean(psf[5:15, 5:15])`` of the full file).
    """
    return rio.load_psf(sample_path("tutorial_psf"), normalise=normalise)


def tutorial_measurement(normalise: rio.NormMode | None = "max") -> F32:
    """Raw hand measurement of the tutorial camera at 1/8 scale, ``(1, 150, 200)``, max 1.

    Same dark level as the PSF subtracted (as the tutorial does). No ground truth exists.
    """
    return rio.load_measurement(sample_path("tutorial_measurement"), normalise=normalise)


def lensed_scene_names() -> tuple[str, ...]:
    """Names of the bundled lensed scenes (``im408`` bottle caps, ``im740`` crab, ``im65``)."""
    return tuple(LENSED_SCENES)


def lensed_scene(name: str, *, rgb: bool = False) -> F32:
    """A prepared lensed scene ``(C, 1, 150, 200)`` float32 in [0, 1].

    Grayscale (``C = 1``) from the bundled file; ``rgb=True`` (``C = 3``) prepares it from the
    full file in the shared data folder (FileNotFoundError if that is absent).
    """
    if name not in LENSED_SCENES:
        raise ValueError(f"unknown lensed scene {name!r}; known: {', '.join(LENSED_SCENES)}")
    if rgb:
        shared = shared_data_dir()
        if shared is None:
            raise FileNotFoundError(
                "RGB lensed scenes need the full data (shared/data, or set "
                "LENSLESSCAM_SHARED_DATA); only grayscale versions are bundled"
            )
        src = shared / "lensless_learning" / "lensed" / f"{name}.npy"
        return prepare_lensed_scene(rio.load_image(src), TUTORIAL_SHAPE, gray=False)
    arr = rio.load_image(sample_path(f"lensed_{name}"))
    return np.ascontiguousarray(arr, dtype=np.float32)[np.newaxis, np.newaxis]


def depth_psf_stack(normalise: rio.NormMode | None = "max") -> F32:
    """The DiffuserCam 3D PSF stack at 1/2 scale, 22 planes: ``(22, 135, 160)`` float32.

    Plane ``k`` is the mean of original planes ``2k`` and ``2k + 1`` (see
    :func:`depth_planes`); whole stack scaled to max 1 by default.
    """
    return rio.load_psf_stack(sample_path("depth"), key="psf", normalise=normalise)


def depth_planes() -> list[tuple[int, ...]]:
    """For each plane of :func:`depth_psf_stack`, the original plane indices averaged into it."""
    with np.load(sample_path("depth"), allow_pickle=False) as z:
        planes = np.asarray(z["planes"])
    return [tuple(int(v) for v in row) for row in planes]


def dlmd_pair_paths() -> dict[str, Path]:
    """The bundled real pair, in the dataset's layout: ``measurement``, ``truth``, ``psf``.

    All (H, W, 3) float16, BGR and stored upside-down like the dataset's files, box-downsampled
    by :data:`DLMD_DOWNSAMPLE`: measurement and truth 67x120 (the sensor-size field; the first
    and last of the 270 rows dropped), the PSF 134x240 on the padded grid (exactly twice the
    sensor, its zero shift at the centre; rows 2..537 of 540 kept), scaled to max 1 (the
    dataset's per-channel gains kept). Read them like the full files (flip nothing between
    them), for example with ``recon.problem.ProblemSpec(..., color="rgb",
    channel_order="bgr", flip_rows=True)``.
    """
    return {k: sample_path(f"dlmd_{k}") for k in ("measurement", "truth", "psf")}


def depth_measurement(normalise: rio.NormMode | None = "max") -> F32:
    """Raw measurement of the tilted USAF target at 1/2 scale, ``(1, 135, 160)``, max 1.

    Camera bias (100 counts) subtracted, clipped at 0.
    """
    return rio.load_measurement(sample_path("depth"), key="meas", normalise=normalise)


def prepare_lensed_scene(
    array_hwc: npt.NDArray[Any], shape: tuple[int, int] = TUTORIAL_SHAPE, gray: bool = True
) -> F32:
    """Prepare a lensed MirFlickr image as a scene ``(C, 1, H, W)`` float32 of size ``shape``.

    The protocol: the stored arrays are BGR and upside down, so the rows are flipped and the
    channels reversed (-> upright RGB); the image is centre-cropped to the aspect ratio of
    ``shape`` and resized by area averaging (OpenCV ``INTER_AREA``) to ``shape``; with
    ``gray`` it is converted to luma (Rec. 601 weights, ``C = 1``), else ``C = 3`` (RGB).
    """
    import cv2

    a = np.asarray(array_hwc)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected a colour image (H, W, 3), got shape {a.shape}")
    th, tw = (int(shape[0]), int(shape[1]))
    if th < 1 or tw < 1:
        raise ValueError(f"target shape must be positive, got {shape}")
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise ValueError("image contains NaN or infinite values")
    rgb = np.ascontiguousarray(a[::-1, :, ::-1], dtype=np.float32)  # flip rows; BGR -> RGB
    h, w = rgb.shape[:2]
    if w * th > h * tw:  # too wide: crop columns
        cw = max(1, round(h * tw / th))
        x0 = (w - cw) // 2
        rgb = rgb[:, x0 : x0 + cw]
    elif w * th < h * tw:  # too tall: crop rows
        ch = max(1, round(w * th / tw))
        y0 = (h - ch) // 2
        rgb = rgb[y0 : y0 + ch]
    if rgb.shape[:2] != (th, tw):
        rgb = np.asarray(
            cv2.resize(np.ascontiguousarray(rgb), (tw, th), interpolation=cv2.INTER_AREA),
            dtype=np.float32,
        )
    chw = np.ascontiguousarray(np.moveaxis(np.asarray(rgb, dtype=np.float32), -1, 0))
    if gray:
        chw = rio.to_gray(chw)
    # Area resize and luma are convex combinations: clip float rounding back into the input's
    # range (so a [0, 1] image stays within [0, 1]).
    out = np.clip(chw, np.float32(a.min()), np.float32(a.max()))
    return np.ascontiguousarray(out[:, np.newaxis], dtype=np.float32)


# --------------------------------------------------------------------------------------------
# Building the bundled files
# --------------------------------------------------------------------------------------------


def _save_npy(path: Path, arr: npt.NDArray[Any]) -> Path:
    return atomic_write(path, lambda tmp: np.save(tmp, arr, allow_pickle=False))


def build_samples(
    shared_data_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str]
) -> list[Path]:
    """Regenerate every bundled sample file from the full data; returns the written paths.

    Steps (all recorded in ``samples.json``):

    - tutorial PSF and hand measurement: float32 of the uint16 files, minus the tutorial's
      dark level ``mean(psf[5:15, 5:15])`` of the full-resolution PSF (subtracted from both,
      as the tutorial does), 8x8 box mean -> 150x200, clipped at 0; saved in counts;
    - lensed scenes: :func:`prepare_lensed_scene` to 150x200 grayscale, [0, 1];
    - 3D: measurement minus the camera bias (100), 2x2 box mean -> 135x160, clipped at 0
      (float32 counts); PSF stack 2x2 box mean, pairs of planes averaged -> 22 planes, float16;
    - ``false_color_calib.mat`` copied unchanged.
    """
    src = Path(shared_data_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    sources: dict[str, str] = {}

    def _src(rel: str) -> Path:
        p = src / rel
        if not p.is_file():
            raise FileNotFoundError(f"{p}: source file for the samples is missing")
        sources[rel] = file_hash(p)
        return p

    # DiffuserCam tutorial: PSF and hand, dark from the PSF's corner (tutorial: loadData()).
    psf_raw = rio.load_image(_src("diffusercam_tutorial/psf_sample.tif")).astype(np.float32)
    hand_raw = rio.load_image(_src("diffusercam_tutorial/rawdata_hand_sample.tif")).astype(
        np.float32
    )
    tut_dark = float(rio.auto_dark_level(psf_raw).item())
    hand_corner = float(rio.auto_dark_level(hand_raw).item())
    f = TUTORIAL_DOWNSAMPLE
    psf = rio.clip_nonneg(rio.box_downsample(rio.subtract_dark(psf_raw, tut_dark), f))
    hand = rio.clip_nonneg(rio.box_downsample(rio.subtract_dark(hand_raw, tut_dark), f))
    written.append(_save_npy(out / _FILES["tutorial_psf"], psf.astype(np.float32)))
    written.append(_save_npy(out / _FILES["tutorial_measurement"], hand.astype(np.float32)))

    # Lensed scenes.
    for name in LENSED_SCENES:
        arr = rio.load_image(_src(f"lensless_learning/lensed/{name}.npy"))
        scene = prepare_lensed_scene(arr, TUTORIAL_SHAPE, gray=True)[0, 0]
        written.append(_save_npy(out / _FILES[f"lensed_{name}"], scene))

    # 3D: USAF target and PSF stack.
    meas_raw = rio.load_image(_src("diffusercam_3d/example_raw.png")).astype(np.float32)
    meas = rio.clip_nonneg(
        rio.box_downsample(meas_raw - np.float32(DEPTH_DARK), DEPTH_DOWNSAMPLE)
    ).astype(np.float32)
    psf_dir = src / "diffusercam_3d" / "psf"
    plane_files = sorted(psf_dir.glob("psf*.tiff"))
    if not plane_files:
        raise FileNotFoundError(f"{psf_dir}: no psf*.tiff planes")
    for pf in plane_files:
        sources[str(pf.relative_to(src))] = file_hash(pf)
    full = rio.load_psf_stack(plane_files, normalise=None)  # (44, 270, 320), max 1 already
    n_bin = DEPTH_AXIAL_BIN
    n_out = full.shape[0] // n_bin
    lateral = rio.box_downsample(full[: n_out * n_bin], DEPTH_DOWNSAMPLE)
    stack = lateral.reshape(n_out, n_bin, *lateral.shape[1:]).mean(axis=1)
    planes = np.arange(n_out * n_bin, dtype=np.int16).reshape(n_out, n_bin)

    def _write_npz(tmp: Path) -> None:
        np.savez_compressed(tmp, psf=stack.astype(np.float16), meas=meas, planes=planes)

    written.append(atomic_write(out / _FILES["depth"], _write_npz))

    calib = _src("spectral/false_color_calib.mat")
    data = calib.read_bytes()

    def _copy(tmp: Path) -> None:
        tmp.write_bytes(data)

    written.append(atomic_write(out / _FILES["false_color_calib"], _copy))

    # One real pair of the DiffuserCam Lensless MirFlickr dataset, in the dataset's layout.
    # 270 rows are not a multiple of 4: keep 268 (rows 1..268) of measurement and truth and
    # the matching 536 of the padded PSF (rows 2..537), so the PSF stays exactly twice the
    # sensor with its zero shift at the centre, as in the dataset
    d = DLMD_DOWNSAMPLE
    dl: dict[str, npt.NDArray[Any]] = {}
    for key, rel in (("measurement", f"dlmd/diffuser_{DLMD_PAIR}.npy"),
                     ("truth", f"dlmd/lensed_{DLMD_PAIR}.npy"),
                     ("psf", "dlmd/psf_estimated_padded_bgr.npy")):
        chw = rio.to_channel_first(rio.load_image(_src(rel)), "hwc").astype(np.float32)
        h = chw.shape[1]
        keep = h - h % (2 * d) if key == "psf" else h - h % d
        r0 = (h - keep) // 2
        small = rio.box_downsample(chw[:, r0:r0 + keep], d)
        if key == "psf":
            small = small / small.max()
        dl[key] = np.ascontiguousarray(np.moveaxis(small, 0, -1)).astype(np.float16)
        written.append(_save_npy(out / _FILES[f"dlmd_{key}"], dl[key]))

    manifest: dict[str, Any] = {
        "format": "lenslesscam.samples",
        "format_version": FORMAT_VERSION,
        "provenance": provenance(),
        "licence": "BSD-3-Clause, Waller Lab, UC Berkeley (see README.md)",
        "sources_sha256_16": sources,
        "tutorial": {
            "dark_level": tut_dark,
            "dark_rule": "mean(psf[5:15, 5:15]) of the full-resolution PSF, subtracted from "
            "PSF and measurement (DiffuserCam tutorial loadData)",
            "measurement_corner_mean": hand_corner,
            "measurement_corner_note": "mean(raw[5:15, 5:15]) of the hand measurement: scene "
            "light, not dark; informational only",
            "downsample": f,
            "shape": list(psf.shape),
            "units": "counts (dark subtracted, box-averaged, clipped at 0), float32",
        },
        "lensed": {
            "names": LENSED_SCENES,
            "protocol": "flip rows, BGR->RGB, centre crop to 4:3, INTER_AREA resize to 150x200, "
            "Rec.601 luma",
            "shape": list(TUTORIAL_SHAPE),
        },
        "depth": {
            "dark_level": DEPTH_DARK,
            "dark_rule": "camera bias image_bias = 100 (DiffuserCam_settings.m)",
            "downsample": DEPTH_DOWNSAMPLE,
            "axial_bin": n_bin,
            "psf_shape": list(stack.shape),
            "psf_dtype": "float16",
            "meas_shape": list(meas.shape),
            "planes": planes.tolist(),
        },
        "dlmd": {
            "pair": DLMD_PAIR,
            "downsample": d,
            "layout": "(H, W, 3) BGR, stored upside-down, as the dataset; PSF on the padded "
            "grid (zero shift at its centre), measurement and truth on the sensor-size field",
            "processing": "central rows kept so that d divides them (measurement, truth: rows "
            "1..268 of 270; PSF: rows 2..537 of 540, twice the sensor, zero shift at the "
            "centre), box mean over dxd blocks, float16; PSF scaled to max 1 first",
            "shapes": {k: list(v.shape) for k, v in dl.items()},
        },
        "files": {p.name: {"bytes": p.stat().st_size, "sha256_16": file_hash(p)} for p in written},
    }
    written.append(atomic_write_json(out / _FILES["manifest"], manifest))
    return written
