"""``lenslesscam metrics``: score a reconstruction against a reference image, print JSON."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    """Add the ``metrics`` subcommand."""
    p = subparsers.add_parser(
        "metrics",
        help="score an estimate against a reference (MSE, PSNR, SSIM, MS-SSIM) as JSON",
        description=(
            "Compare EST with the reference GT and print JSON: mse, psnr, ssim, ms_ssim, gain, "
            "gain_fit. Files: a lenslesscam reconstruction TIFF (C, K, H, W), any TIFF, PNG, "
            "NPY, NPZ or MAT image. data_range defaults to ref.max() - ref.min()."
        ),
    )
    p.add_argument("--ref", required=True, type=Path, metavar="GT", help="reference file")
    p.add_argument("--est", required=True, type=Path, metavar="EST", help="estimate file")
    p.add_argument(
        "--gain-fit",
        action="store_true",
        help="scale EST by the least-squares gain <ref,est>/<est,est> before scoring",
    )
    p.add_argument(
        "--data-range",
        type=float,
        default=None,
        metavar="L",
        help="dynamic range L for PSNR/SSIM (default: range of the reference)",
    )
    p.add_argument("--key", default=None, help="variable name inside NPZ/MAT files")
    p.set_defaults(func=run)


def _load(path: Path, key: str | None) -> Any:
    """Load as (C, K, H, W) float64: our TIFF directly, other files by layout."""
    import numpy as np

    from recon import io as rio
    from recon.formats import FormatError

    if path.suffix.lower() in (".tif", ".tiff"):
        try:
            arr, _ = rio.read_reconstruction(path)
            return arr.astype(np.float64)
        except FormatError:
            pass  # a plain TIFF: read it as an image below
    a = np.asarray(rio.load_image(path, key=key))
    if a.dtype.kind not in "biuf":
        raise ValueError(f"{path}: not a numeric image (dtype {a.dtype})")
    a = a.astype(np.float64)
    if a.ndim == 2:
        return a[np.newaxis, np.newaxis]
    if a.ndim == 3:
        if a.shape[0] in (1, 3) and a.shape[2] not in (3, 4):
            return a[:, np.newaxis]  # (C, H, W)
        if a.shape[2] in (3, 4):
            return np.moveaxis(a[..., :3], -1, 0)[:, np.newaxis]  # (H, W, C) colour
        return a[np.newaxis]  # (K, H, W) stack
    if a.ndim == 4:
        return a
    raise ValueError(f"{path}: cannot interpret an image of shape {a.shape}")


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return "inf" if v > 0 else ("-inf" if v < 0 else "nan")
    return v


def run(args: argparse.Namespace) -> int:
    """Load both files, compute :func:`recon.metrics.metrics_report`, print it as JSON."""
    import json

    from recon.metrics import metrics_report

    ref = _load(args.ref, args.key)
    est = _load(args.est, args.key)
    if ref.shape != est.shape:
        raise ValueError(
            f"shapes differ: ref {args.ref} is {tuple(ref.shape)} (C, K, H, W), est {args.est} "
            f"is {tuple(est.shape)}"
        )
    report = metrics_report(ref, est, gain_fit=args.gain_fit, data_range=args.data_range)
    report = {"ref": str(args.ref), "est": str(args.est), **report}
    print(json.dumps({k: _jsonable(v) for k, v in report.items()}, indent=2))
    return 0
