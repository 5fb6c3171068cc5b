"""``lenslesscam metrics``: score a reconstruction against a reference image, print JSON."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from app.commands._options import POSITIVE


def register(subparsers: Any) -> None:
    """Add the ``metrics`` subcommand."""
    p = subparsers.add_parser(
        "metrics",
        help="score an estimate against a reference (MSE, PSNR, SSIM, MS-SSIM) as JSON",
        description=(
            "Compare EST with the reference GT and print JSON: mse, psnr, ssim, ms_ssim (with "
            "the number of scales used), gain, gain_fit; for spectral results (a spectral "
            "reconstruction TIFF, or --spectral) also spectral_cosine_distance (mean 1 - cos "
            "of the spectral angle) and spectral_angle_deg. Files: a lenslesscam "
            "reconstruction TIFF (C, K, H, W), any TIFF, PNG, NPY, NPZ or MAT image. "
            "data_range defaults to ref.max() - ref.min(). An all-zero GT is refused: "
            "nothing to score against; a constant one needs --data-range (a flat field). "
            "Without --gain-fit, EST and GT whose "
            "largest magnitudes are more than 10 times apart (a 0..255 image against a 0..1 "
            "truth) get scale_note, also on stderr."
        ),
    )
    p.add_argument("--ref", required=True, type=Path, metavar="GT", help="reference file")
    p.add_argument("--est", required=True, type=Path, metavar="EST", help="estimate file")
    p.add_argument(
        "--gain-fit",
        action="store_true",
        help="scale EST by the least-squares gain <ref,est>/<est,est> before scoring (an "
        "all-zero EST has none: gain null, gain_fit false and gain_note, also on stderr)",
    )
    p.add_argument(
        "--data-range",
        type=POSITIVE,
        default=None,
        metavar="L",
        help="dynamic range L for PSNR/SSIM (default: range of the reference)",
    )
    p.add_argument("--key", default=None, help="variable name inside NPZ/MAT files")
    p.add_argument("--ref-as-is", action="store_true",
                   help="read GT exactly as stored; by default, when EST is a lenslesscam "
                   "reconstruction (an image, or frames, bands, planes: a (K, H, W) stack or "
                   "(C, K, H, W)), GT is prepared like the measurement it was made from "
                   "(colour, --channel-order, --flip-rows, --downsample from EST's metadata; "
                   "a truth of the sensor's field embedded in a larger scene field, zero "
                   "outside, or cut to a smaller one; for a recon auto result its plan's "
                   "merged time bins or PSF planes, downsampling and region; ref_prepared in "
                   "the JSON); when GT and EST are both lenslesscam reconstructions of a different "
                   "geometry (scene field, downsampling, region, colour, row flip, channel "
                   "order) they are refused unless this is given (geometry_differs in the JSON)")
    p.add_argument("--spectral", action="store_true",
                   help="K is the spectral axis: also report the spectral cosine (automatic "
                   "for spectral reconstruction TIFFs)")
    p.set_defaults(func=run)


def _load(path: Path, key: str | None) -> tuple[Any, str | None, dict[str, Any] | None]:
    """Load as (C, K, H, W) float64, the reconstruction kind and its metadata.

    Kind and metadata are None for anything but a lenslesscam reconstruction TIFF.
    """
    import numpy as np

    from recon import io as rio
    from recon.formats import NotOurFile

    if path.suffix.lower() in (".tif", ".tiff"):
        try:
            arr, meta = rio.read_reconstruction(path)
            return arr.astype(np.float64), meta.get("kind"), meta
        except NotOurFile:
            pass  # a plain TIFF: read it as an image below (a newer or corrupt one is refused)
    a = np.asarray(rio.load_image(path, key=key))
    if a.dtype.kind not in "biuf":
        raise ValueError(f"{path}: not a numeric image (dtype {a.dtype})")
    a = a.astype(np.float64)
    if a.ndim == 2:
        return a[np.newaxis, np.newaxis], None, None
    if a.ndim == 3:
        if a.shape[0] in (1, 3) and a.shape[2] not in (3, 4):
            return a[:, np.newaxis], None, None  # (C, H, W)
        if a.shape[2] in (3, 4):
            return np.moveaxis(a[..., :3], -1, 0)[:, np.newaxis], None, None  # (H, W, C)
        return a[np.newaxis], None, None  # (K, H, W) stack
    if a.ndim == 4:
        return a, None, None
    raise ValueError(f"{path}: cannot interpret an image of shape {a.shape}")


def _geometry(meta: dict[str, Any] | None) -> dict[str, Any] | None:
    """Where a reconstruction's pixels lie in the scene, from its metadata.

    Scene field and region in full-resolution pixels of the measurement (the field centred on
    the sensor axis), the total downsampling (the loader's, times a plan's), and how the
    inputs were read (colour, row flip, channel order). None when the metadata does not say
    (not a reconstruction, or one from before ``preprocessing`` recorded the field).
    """
    pre = (meta or {}).get("preprocessing")
    if not isinstance(pre, dict):
        return None
    try:
        ds = int(pre.get("downsample") or 1)
        plan = (meta or {}).get("plan")
        if isinstance(plan, dict) and "field" in plan:  # recon auto: the plan's field and grid
            pd = int(plan.get("downsample") or 1)
            field = [int(n) * ds for n in plan["field"]]
            grid = [int(n) for n in (meta or {})["region_on_grid"]]
        else:  # the loader's field, in pixels of its (downsampled) grid, all of it
            pd = 1
            field = [int(n) * ds for n in pre["field"]]
            grid = [0, 0, int(pre["field"][0]), int(pre["field"][1])]
    except (KeyError, TypeError, ValueError):
        return None
    if len(field) != 2 or len(grid) != 4:
        return None
    d = ds * pd
    # the field the grid covers: a remainder the downsampling drops is no difference (a
    # 270-row field at downsample 4 covers 268 rows, as a 268-row field does)
    field = [n // d * d for n in field]
    color = pre.get("color") or ("rgb" if pre.get("rgb") else "gray")
    geo: dict[str, Any] = {"field": field, "downsample": d,
                           "region": [n * d for n in grid], "color": color,
                           "flip_rows": bool(pre.get("flip_rows"))}
    if color == "rgb":  # a gray read takes no channel order
        geo["channel_order"] = pre.get("channel_order") or "rgb"
    return geo


def _geometry_differences(ref: dict[str, Any], est: dict[str, Any]) -> list[str]:
    """What differs between two reconstructions' geometries (:func:`_geometry`), in words."""
    def hw(v: list[int]) -> str:
        return f"{v[0]}x{v[1]}"

    def reg(v: list[int]) -> str:
        return f"{v[2]}x{v[3]} at ({v[0]}, {v[1]})"

    words = {"field": ("scene field", hw), "downsample": ("downsampling", str),
             "region": ("region (full-resolution px of the field)", reg),
             "color": ("colour", str), "flip_rows": ("rows flipped", str),
             "channel_order": ("channel order", str)}
    out = []
    for key, (name, fmt) in words.items():
        a, b = ref.get(key), est.get(key)
        if a != b and a is not None and b is not None:
            out.append(f"{name} {fmt(a)} vs {fmt(b)}")
    return out


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return "inf" if v > 0 else ("-inf" if v < 0 else "nan")
    return v


def run(args: argparse.Namespace) -> int:
    """Load both files, compute :func:`recon.metrics.metrics_report`, print it as JSON."""
    import json
    import sys

    import numpy as np

    from recon.metrics import metrics_report, spectral_cosine_distance
    from recon.truth import truth_for_result, truth_layout

    est, est_kind, est_meta = _load(args.est, args.key)
    ref, ref_kind, ref_meta = _load(args.ref, args.key)
    layout = truth_layout(est_meta)
    prepared = None
    # a result (an image, or frames, bands, planes) from a measurement that says how it was
    # read, scored against a plain file (not a reconstruction): the one preparation of a
    # truth, the problem loader's (recon.truth)
    if layout is not None and not args.ref_as_is and ref_meta is None:
        got = truth_for_result(args.ref, est, est_meta, key=args.key)
        assert got is not None  # the layout is known
        ref, est, prepared = got
    # two reconstructions: equal shapes do not make equal pixels (a 150x200 result of the
    # sensor field at downsample 1 and one of the 2x field at downsample 2 cover other scenes)
    ref_geo, est_geo = _geometry(ref_meta), _geometry(est_meta)
    differs = (_geometry_differences(ref_geo, est_geo)
               if ref_geo is not None and est_geo is not None else [])
    if differs and not args.ref_as_is:
        raise ValueError(f"ref {args.ref} and est {args.est} are reconstructions of different "
                         f"geometry (ref vs est): {'; '.join(differs)}; their pixels are not "
                         "the same scene points (--ref-as-is compares them as stored)")
    if ref.shape != est.shape:
        raise ValueError(
            f"shapes differ: ref {args.ref} is {tuple(ref.shape)} (C, K, H, W), est {args.est} "
            f"is {tuple(est.shape)}"
        )
    try:
        report = metrics_report(ref, est, gain_fit=args.gain_fit, data_range=args.data_range)
    except ValueError as exc:  # a constant ref, NaN values: say which files
        raise ValueError(f"{exc} (ref {args.ref}, est {args.est})") from None
    for key in ("scale_note", "gain_note"):  # also in the JSON
        if key in report:
            print(f"lenslesscam metrics: note: {report[key]}", file=sys.stderr)
    report = {"ref": str(args.ref), "est": str(args.est), **report}
    if prepared is not None:
        report["ref_prepared"] = prepared
    if differs:  # compared as stored on request (--ref-as-is)
        report["geometry_differs"] = "; ".join(differs)
    if args.spectral or "spectral" in (ref_kind, est_kind):
        if ref.shape[1] < 2:
            raise ValueError(f"a spectral score needs K >= 2 bands, got shape {ref.shape}")
        dist = spectral_cosine_distance(ref, est, axis=1)  # scale-free: no gain fit needed
        report["spectral_cosine_distance"] = dist
        report["spectral_angle_deg"] = float(np.degrees(np.arccos(np.clip(1 - dist, -1, 1))))
        report["spectral_note"] = ("mean over pixels of 1 - cos(angle between the spectra "
                                   "along K); spectral_angle_deg is the angle of that mean "
                                   "cosine; pixels with an all-zero spectrum are left out")
    print(json.dumps({k: _jsonable(v) for k, v in report.items()}, indent=2))
    return 0
