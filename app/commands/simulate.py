"""``lenslesscam simulate``: a measurement of a known scene through a forward model."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from app.commands._common import parse_dark


def register(sub: Any) -> None:
    """Add ``simulate``."""
    p = sub.add_parser("simulate", help="simulate a measurement of a scene with a PSF")
    p.add_argument("--psf", required=True, help="PSF file ('sample:tutorial' for the bundled one)")
    p.add_argument("--scene", required=True,
                   help="scene image, or sample:NAME for a bundled lensed scene "
                   "(im408, im740, im65)")
    p.add_argument("--erasure", type=float, default=0.0, help="fraction of erased pixels")
    p.add_argument("--noise", type=float, default=0.0, help="Gaussian noise sigma (max = 1)")
    p.add_argument("--photons", type=float, default=None, help="Poisson: photons at max 1")
    p.add_argument("--bits", type=int, default=None, help="quantise to this many bits")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--downsample", type=int, default=1, help="box downsampling of the PSF")
    p.add_argument("--dark", help="dark level of the PSF file: a number, 'auto' or a file")
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=run)


def load_scene(spec: str, shape: tuple[int, int]) -> Any:
    """A grayscale scene (1, 1, H, W) in [0, 1] of the sensor's shape."""
    import cv2
    import numpy as np

    from recon import samples
    from recon.io import load_image, to_channel_first, to_gray

    if spec.startswith("sample:"):
        scene = samples.lensed_scene(spec.split(":", 1)[1])[0, 0]
    else:
        raw = np.asarray(load_image(spec), dtype=np.float64)
        if raw.ndim not in (2, 3):
            raise ValueError(f"scene {spec} must be an image (H, W) or (H, W, 3), got {raw.shape}")
        scene = to_gray(to_channel_first(raw))[0]
        if not np.isfinite(scene).all():
            raise ValueError(f"scene {spec} contains NaN or inf values")
        top = float(scene.max())
        scene = scene / top if top > 0 else scene
    if scene.shape != shape:
        scene = cv2.resize(np.ascontiguousarray(scene, dtype=np.float32), (shape[1], shape[0]),
                           interpolation=cv2.INTER_AREA)
    return np.asarray(scene, dtype=np.float32)[None, None]


def load_psf_spec(spec: str, downsample: int, dark: Any) -> Any:
    """The PSF named by ``--psf`` (unit sum, grayscale)."""
    from recon import samples
    from recon.io import box_downsample, load_psf, normalise

    if spec == "sample:tutorial":
        psf = samples.tutorial_psf()
        return normalise(box_downsample(psf, downsample), "sum") if downsample > 1 else psf
    return load_psf(spec, dark=dark, downsample=downsample)


def run(args: argparse.Namespace) -> int:
    """Simulate and write meas.npy, mask.npy, truth.npy, psf.npy and simulation.json."""
    import numpy as np

    from recon.formats import (
        FORMAT_VERSION,
        array_hash,
        atomic_write,
        atomic_write_json,
        provenance,
    )
    from recon.models import build_model
    from recon.simulate import simulate

    psf = load_psf_spec(args.psf, args.downsample, parse_dark(args.dark))
    scene = load_scene(args.scene, (int(psf.shape[-2]), int(psf.shape[-1])))
    model = build_model("2d", psf)
    sim = simulate(model, scene, erasure=args.erasure, noise=args.noise, photons=args.photons,
                   bits=args.bits, seed=args.seed)
    out = Path(args.out)
    files = {"meas": sim.meas, "truth": sim.truth, "psf": psf,
             "mask": sim.mask if sim.mask is not None else np.ones(sim.meas.shape[-2:], np.float32)}
    for name, arr in files.items():
        atomic_write(out / f"{name}.npy", lambda p, a=arr: np.save(p, a, allow_pickle=False))
    meta = {"format": "lenslesscam.simulation", "format_version": FORMAT_VERSION,
            "provenance": provenance(), "psf": args.psf, "scene": args.scene,
            "downsample": args.downsample, "params": sim.params, "scale": sim.scale,
            "saturated_pixels": sim.saturated,
            "hashes": {k: array_hash(v) for k, v in files.items()},
            "files": {k: f"{k}.npy" for k in files}}
    atomic_write_json(out / "simulation.json", meta)
    print(json.dumps({"out": str(out), "shape": list(sim.meas.shape),
                      "erased": int((files["mask"] == 0).sum())}))
    return 0
