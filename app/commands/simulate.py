"""``lenslesscam simulate``: a measurement of a known scene through a forward model.

``--model 2d`` (default), ``video`` (rolling shutter, ``--shutter`` M (K, rows)) or ``spectral``
(filter array, ``--filters`` (K, H, W)): the same forward models the solvers invert
(:func:`recon.models.build_model`) and the same noise / erasure chain
(:func:`recon.simulate.simulate`); no separate simulation path.

A scene of another shape than the sensor is resized to it (said on stderr and recorded in
``simulation.json``); its files are written all or none, and nothing else in the output folder
is touched (:func:`recon.atomic.atomic_files`).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.commands._common import parse_dark
from app.commands._options import (
    BITS,
    FRACTION,
    NONNEG,
    NONNEG_INT,
    POSITIVE,
    POSITIVE_INT,
    add_overwrite_option,
    check_command_outputs,
)

#: Files written into ``--out`` (``shutter`` / ``filters`` only for those models).
OUTPUT_NAMES = ("meas", "truth", "psf", "mask", "shutter", "filters")


def register(sub: Any) -> None:
    """Add ``simulate``."""
    p = sub.add_parser("simulate", help="simulate a measurement of a scene with a PSF")
    p.add_argument("--model", choices=["2d", "video", "spectral"], default="2d",
                   help="forward model: 2d, video (needs --shutter) or spectral (needs "
                   "--filters)")
    p.add_argument("--psf", required=True, help="PSF file ('sample:tutorial' for the bundled one)")
    p.add_argument("--scene", required=True,
                   help="scene image, or sample:NAME for a bundled lensed scene "
                   "(im408, im740, im65); video/spectral: a (K, H, W) stack or one image "
                   "(the same in every frame / band)")
    p.add_argument("--shutter", help="video: shutter function M (K, rows) (.npy/.npz/.tif)")
    p.add_argument("--filters", help="spectral: filter cube (K, H, W) (.npy/.npz/.mat/.tif)")
    p.add_argument("--erasure", type=FRACTION, default=0.0,
                   help="fraction of erased pixels, 0 <= f < 1 (default 0)")
    p.add_argument("--noise", type=NONNEG, default=0.0,
                   help="Gaussian noise sigma, >= 0, measurement max = 1 (default 0)")
    p.add_argument("--photons", type=POSITIVE, default=None,
                   help="Poisson noise: photons at value 1, > 0 (default none)")
    p.add_argument("--bits", type=BITS, default=None, help="quantise to this many bits (1..32)")
    p.add_argument("--seed", type=NONNEG_INT, default=0,
                   help="seed of the noise and the erasures (default 0)")
    p.add_argument("--downsample", type=POSITIVE_INT, default=1,
                   help="box downsampling of the PSF (and of the shutter / filters)")
    p.add_argument("--dark", help="dark level of the PSF file: a number, 'auto' or a file")
    p.add_argument("--out", required=True, help="output folder")
    add_overwrite_option(p)
    p.set_defaults(func=run)


#: How a scene of another shape than the sensor is resized (each output pixel is the mean of
#: the scene's pixels it covers, by area; the same rule shrinking and enlarging).
RESIZE_METHOD = "OpenCV INTER_AREA (pixel-area averaging)"


def _resize(img: Any, shape: tuple[int, int]) -> Any:
    import cv2
    import numpy as np

    if img.shape == shape:
        return np.asarray(img, dtype=np.float32)
    return cv2.resize(np.ascontiguousarray(img, dtype=np.float32), (shape[1], shape[0]),
                      interpolation=cv2.INTER_AREA)


def _stretched(src: tuple[int, int], dst: tuple[int, int]) -> bool:
    """Whether resizing ``src`` (H, W) to ``dst`` changes the aspect ratio.

    Beyond the rounding of one pixel: 150x200 -> 37x50 keeps it, 10x12 -> 24x32 does not.
    """
    (h, w), (hh, ww) = src, dst
    return abs(h * ww / w - hh) >= 1 or abs(w * hh / h - ww) >= 1


@dataclass
class Scene:
    """A scene ready for the forward model, and what was done to it on the way."""

    array: Any  #: (1, K, H, W) float32 in [0, 1], H x W the sensor's shape
    meta: dict[str, Any] = field(default_factory=dict)  #: recorded in simulation.json
    notes: list[str] = field(default_factory=list)  #: one line each, printed on stderr


def load_scene(spec: str, shape: tuple[int, int], k: int = 1) -> Scene:
    """A grayscale scene (1, K, H, W) in [0, 1] of the sensor's shape.

    A 2D image (or an (H, W, 3) colour one, made gray) is the same in each of the K frames;
    a stack (K', H, W) must have K' = K. A scene of another shape is resized to the sensor's
    (:data:`RESIZE_METHOD`, stretched when the aspect ratios differ; never cropped); the
    returned :class:`Scene` says so in ``notes`` and ``meta``.
    """
    import numpy as np

    from recon import samples
    from recon.io import load_image, to_channel_first, to_gray

    notes: list[str] = []
    dtype = None
    if spec.startswith("sample:"):
        frames = samples.lensed_scene(spec.split(":", 1)[1])[0, :1]
    else:
        raw = np.asarray(load_image(spec))
        if raw.dtype.kind not in "biuf":
            raise ValueError(f"scene {spec} has dtype {raw.dtype}: a scene is real numbers")
        dtype = str(raw.dtype)
        if raw.dtype.kind == "b":
            # Accepted, and said. A measurement refuses bool (recon.readers: "unsupported dtype
            # bool") because it is sensor counts, which no camera writes as True/False. A scene
            # is light, reflectance in [0, 1] here: a binary target (a resolution chart, text)
            # is one, and the truth reader (recon.problem.read_truth) reads bool as 0/1 too.
            notes.append(f"scene {spec} is boolean: read as reflectance 0/1 (True = 1)")
        raw = raw.astype(np.float64)
        if raw.ndim == 4 and raw.shape[0] == 1:  # (1, K, H, W): a truth simulate wrote
            raw = raw[0]
        if raw.ndim == 3 and raw.shape[0] == 1:
            raw = raw[0]
        if raw.ndim == 3 and k > 1 and raw.shape[-1] == k and raw.shape[0] != k:
            # (H, W, K): the bands (or frames) last, as a filter cube may be stored; 3 or 4 of
            # them were made gray and copied into every band, others "has H frames"
            frames = np.moveaxis(raw, -1, 0)
            notes.append(f"scene {spec} is (H, W, K) = {raw.shape}: its last axis read as the "
                         f"model's K = {k}")
        elif raw.ndim == 3 and raw.shape[-1] not in (3, 4):
            frames = raw  # a (K, H, W) stack
        elif raw.ndim in (2, 3):
            frames = to_gray(to_channel_first(raw))
            if raw.ndim == 3:  # the forward model is gray: said, as the resize is
                notes.append(f"scene {spec} has {raw.shape[-1]} colour channels: made gray "
                             "with the Rec. 601 luma weights of channels 1-3 read as R, G, B "
                             "(a file stored B, G, R is weighted the wrong way round)")
        else:
            raise ValueError(f"scene {spec} must be an image (H, W) or (H, W, 3), a stack "
                             f"(K, H, W) or a truth (1, K, H, W); got shape {raw.shape}")
        if not np.isfinite(frames).all():
            raise ValueError(f"scene {spec} contains NaN or inf values")
        if frames.min() < 0:
            raise ValueError(f"scene {spec} has negative values (min {frames.min():.3g}): a "
                             "scene is light, >= 0")
        top = float(frames.max())
        if top <= 0:
            raise ValueError(f"scene {spec} is all zero: its measurement would be too")
        frames = frames / top
    if frames.shape[0] not in (1, k):
        raise ValueError(f"scene {spec} has {frames.shape[0]} frames; the model has K = {k}")
    src = (int(frames.shape[-2]), int(frames.shape[-1]))
    resized = src != tuple(shape)
    stretched = resized and _stretched(src, shape)
    if resized:
        line = (f"scene {spec} is {src[0]}x{src[1]} (H x W), the sensor field is "
                f"{shape[0]}x{shape[1]}: resized with {RESIZE_METHOD}")
        if stretched:
            line += (f"; its aspect ratio W/H changes from {src[1] / src[0]:.3g} to "
                     f"{shape[1] / shape[0]:.3g}: the scene is stretched to fill the field, "
                     "not cropped")
        notes.append(line)
    out = np.stack([_resize(f, shape) for f in frames])
    if out.shape[0] == 1 and k > 1:
        out = np.repeat(out, k, axis=0)
    # scene_shape is a frame's H, W; the frames (or bands, planes) the file held beside it
    meta = {"scene_shape": list(src), "scene_frames": int(frames.shape[0]), "scene_dtype": dtype,
            "scene_resized_from": list(src) if resized else None,
            "scene_resize_method": RESIZE_METHOD if resized else None,
            "scene_stretched": stretched if resized else None}
    return Scene(np.asarray(out, dtype=np.float32)[None], meta, notes)


def load_psf_spec(spec: str, downsample: int, dark: Any) -> Any:
    """The PSF named by ``--psf`` (unit sum, grayscale)."""
    from recon import samples
    from recon.io import box_downsample, load_psf, normalise

    if spec == "sample:tutorial":
        if dark is not None:  # it was ignored silently
            raise ValueError("--dark applies to a PSF file; the bundled sample:tutorial PSF "
                             "has its dark level (34.08) removed already")
        psf = samples.tutorial_psf()
        return normalise(box_downsample(psf, downsample), "sum") if downsample > 1 else psf
    return load_psf(spec, dark=dark, downsample=downsample)


def _model_inputs(args: argparse.Namespace, sensor: tuple[int, int]) -> dict[str, Any]:
    """The shutter (video) or filter cube (spectral), downsampled to the sensor."""
    from recon.io import box_downsample, downsample_rows
    from recon.problem import read_filters, read_shutter

    if args.model != "video" and args.shutter:
        raise ValueError("--shutter is only for --model video")
    if args.model != "spectral" and args.filters:
        raise ValueError("--filters is only for --model spectral")
    if args.model == "video":
        if not args.shutter:
            raise ValueError("--model video needs --shutter (a (K, rows) shutter function)")
        m, _ = read_shutter(args.shutter)  # the one shutter reader (calibration .npz too)
        if m.ndim == 2 and args.downsample > 1 and m.shape[1] != sensor[0]:
            m = downsample_rows(m, args.downsample)
        return {"shutter": m}
    if args.model == "spectral":
        if not args.filters:
            raise ValueError("--model spectral needs --filters (a (K, H, W) filter cube)")
        # (H, W, K) cubes (SpectralDiffuserCam's .mat) read as recon and calibrate filters do
        ds = args.downsample
        f = read_filters(args.filters, sensors=[sensor] if ds == 1 else
                         [sensor, (sensor[0] * ds, sensor[1] * ds)])
        if f.ndim == 3 and args.downsample > 1 and f.shape[1:] != sensor:
            f = box_downsample(f, args.downsample)
        return {"filters": f}
    return {}


def _written_before(out: Path) -> list[str]:
    """The files an earlier simulate wrote into ``out`` (its simulation.json lists them)."""
    from recon.formats import read_utf8

    names = ["simulation.json"]
    try:
        old = json.loads(read_utf8(out / "simulation.json"))
    except (OSError, ValueError, RecursionError):
        return names
    listed = old.get("files") if isinstance(old, dict) else None
    if isinstance(listed, dict):
        names += [v for v in listed.values() if isinstance(v, str) and Path(v).name == v]
    return names


def _write_files(folder: Path, files: dict[str, Any], meta: dict[str, Any]) -> None:
    import numpy as np

    from recon.atomic import atomic_write, atomic_write_json

    for name, arr in files.items():
        atomic_write(folder / f"{name}.npy", lambda p, a=arr: np.save(p, a, allow_pickle=False))
    atomic_write_json(folder / "simulation.json", meta)


def run(args: argparse.Namespace) -> int:
    """Simulate and write meas.npy, mask.npy, truth.npy, psf.npy and simulation.json.

    Everything is computed first; the files are then staged in a hidden folder inside
    ``--out`` and moved into place together (:func:`recon.atomic.atomic_files`), so an error
    or Ctrl-C during the save leaves no partial set (and an existing one as it was); other
    files in ``--out`` are not touched.
    """
    import numpy as np

    from recon.atomic import atomic_files
    from recon.formats import FORMAT_VERSION, array_hash, provenance
    from recon.models import build_model
    from recon.simulate import simulate

    out = Path(args.out)
    check_command_outputs(args, [out / f"{n}.npy" for n in OUTPUT_NAMES]
                          + [out / "simulation.json"])
    psf = load_psf_spec(args.psf, args.downsample, parse_dark(args.dark))
    sensor = (int(psf.shape[-2]), int(psf.shape[-1]))
    extra = _model_inputs(args, sensor)
    model = build_model(args.model, psf, **extra)
    loaded = load_scene(args.scene, sensor, k=model.k)
    scene = loaded.array
    if scene.shape != model.scene_shape:
        raise ValueError(f"scene {args.scene} gives {scene.shape}, the model needs "
                         f"{model.scene_shape}")
    for line in loaded.notes:
        print(f"simulate: note: {line}", file=sys.stderr)
    sim = simulate(model, scene, erasure=args.erasure, noise=args.noise, photons=args.photons,
                   bits=args.bits, seed=args.seed)
    files = {"meas": sim.meas, "truth": sim.truth, "psf": psf,
             "mask": sim.mask if sim.mask is not None else np.ones(sim.meas.shape[-2:], np.float32)}
    files.update({k: np.asarray(v, dtype=np.float32) for k, v in extra.items()})
    meta = {"format": "lenslesscam.simulation", "format_version": FORMAT_VERSION,
            "provenance": provenance(), "model": args.model, "psf": args.psf,
            "scene": args.scene, **loaded.meta, "shutter": args.shutter,
            "filters": args.filters, "downsample": args.downsample, "params": sim.params,
            "scale": sim.scale, "saturated_pixels": sim.saturated,
            "hashes": {k: array_hash(v) for k, v in files.items()},
            "files": {k: f"{k}.npy" for k in files}, "notes": list(loaded.notes)}
    # files an earlier simulate wrote here and this one does not (a shutter.npy of a video
    # run) are removed; every other entry of the folder is left as it is
    with atomic_files(out, owned=_written_before(out), last=("simulation.json",)) as tmp:
        _write_files(tmp, files, meta)
    print(json.dumps({"out": str(out), "model": args.model, "shape": list(sim.meas.shape),
                      "k": model.k, "erased": int((files["mask"] == 0).sum())}))
    measured = files["mask"] > 0
    if not measured.any():
        print("simulate: warning: every pixel is erased", file=sys.stderr)
    elif not np.any(sim.meas[:, measured] != 0):
        print(f"simulate: warning: the measurement is 0 on all {int(measured.sum())} measured "
              f"pixels (photons {args.photons}, bits {args.bits}): a reconstruction will "
              "refuse it", file=sys.stderr)
    return 0
