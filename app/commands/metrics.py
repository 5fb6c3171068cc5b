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
            "data_range defaults to ref.max() - ref.min()."
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
    from recon.formats import FormatError

    if path.suffix.lower() in (".tif", ".tiff"):
        try:
            arr, meta = rio.read_reconstruction(path)
            return arr.astype(np.float64), meta.get("kind"), meta
        except FormatError:
            pass  # a plain TIFF: read it as an image below
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


def _layout(meta: dict[str, Any] | None) -> dict[str, Any] | None:
    """How the measurement of a reconstruction was read, as ``prepare_truth`` takes it.

    From its metadata's ``preprocessing``; None when the metadata does not say.
    """
    pre = (meta or {}).get("preprocessing")
    if not isinstance(pre, dict) or "channel_order" not in pre:
        return None
    layout: dict[str, Any] = {
        "color": pre.get("color") or ("rgb" if pre.get("rgb") else "gray"),
        "channel_order": pre.get("channel_order") or "rgb",
        "flip_rows": bool(pre.get("flip_rows")),
        "downsample": int(pre.get("downsample") or 1)}
    plan = (meta or {}).get("plan")
    grid = (meta or {}).get("region_on_grid")
    if isinstance(plan, dict) and isinstance(grid, list) and len(grid) == 4:
        # recon auto: the plan downsampled the loaded problem again and may have cut a region
        # of its field; the truth takes the same path (field, then grid, then region)
        field = plan.get("field")
        if not (isinstance(field, list) and len(field) == 2):
            return None
        layout["plan"] = {"downsample": int(plan.get("downsample") or 1),
                          "field": [int(n) for n in field],
                          "region_on_grid": [int(n) for n in grid]}
        # and may merge time bins or keep some planes of a PSF stack: the truth's K follows
        for name in ("base_bins", "bin_factor"):
            if isinstance(plan.get(name), int):
                layout["plan"][name] = int(plan[name])
        planes = plan.get("planes")
        if isinstance(planes, list) and len(planes) == 2:
            layout["plan"]["planes"] = [int(n) for n in planes]
        if plan.get("model") is not None:
            layout["plan"]["model"] = str(plan["model"])
    return layout


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


#: the variables read_truth (recon.problem) prefers in an NPZ/MAT truth file
_TRUTH_KEYS = ("truth", "scene", "x", "arr_0", "data")
#: what the K axis of a reconstruction kind holds, in words
_K_WORDS = {"video": "frames", "spectral": "bands", "depth": "planes"}


def _read_ref(path: Path, est_shape: tuple[int, ...], layout: dict[str, Any],
              key: str | None, stack: bool, expect: int | None) -> Any:
    """The truth file as (C, K0, H, W) float64, colour and channel order as the layout says.

    :func:`recon.problem.read_truth`, the one way a problem's truth is read; a gray result
    that has (or is binned from) several frames, bands or planes also takes a (K, H, W) stack,
    which that reader would take for colour channels (a (3, H, W) file is a stack only when
    ``expect``, the number of slices wanted, is 3).
    """
    import numpy as np

    from recon.problem import read_truth
    from recon.readers import load_image

    if stack and est_shape[0] == 1:
        raw = np.asarray(load_image(path, key=key, prefer=_TRUTH_KEYS))
        hwc = raw.ndim == 3 and raw.shape[2] in (3, 4) and raw.shape[0] not in (1, 3, 4)
        if raw.ndim == 3 and not hwc and (raw.shape[0] != 3 or expect == 3):
            t = raw.astype(np.float64)[np.newaxis]  # (K, H, W): a gray stack of K slices
            if not np.all(np.isfinite(t)):
                raise ValueError(f"truth file {path} has NaN or infinite values")
            return t
    return read_truth(path, color=layout["color"], channel_order=layout["channel_order"],
                      key=key).astype(np.float64)


def _bin_frames(t: Any, factor: int) -> Any:
    """Frames (C, K0, H, W) merged ``factor`` at a time, as the plan merges shutter bins.

    The groups of :func:`recon.preprocess.bin_time` (THE time-binning rule; the last group may
    be partial) and the mean of the frames each group holds: a partial group's shutter row is
    the smaller exposure (bin_time averages it over ``factor``), its frame is still the scene.
    """
    import numpy as np

    from recon.preprocess import bin_time

    c, k0, h, w = t.shape
    summed = bin_time(np.moveaxis(t, 1, 0).reshape(k0, -1), factor)  # (K, C*H*W)
    present = bin_time(np.ones((k0, 1)), factor)  # share of each group's bins that exist
    out = (summed / present).reshape(-1, c, h, w)
    return np.ascontiguousarray(np.moveaxis(out, 0, 1))


def _slices(t: Any, path: Path, est_k: int, kind: str | None,
            plan: dict[str, Any] | None) -> tuple[Any, dict[str, Any] | None]:
    """The truth's frames, bands or planes brought to the result's K (and what was done).

    A video plan's K frames merge ``bin_factor`` of its ``base_bins`` shutter bins each (a
    2D plan of a video measurement merges them all); a plan of a PSF stack keeps its
    ``planes``. Otherwise the truth must have the result's K.
    """
    k0 = int(t.shape[1])
    what = _K_WORDS.get(kind or "", "frames")
    plan = plan or {}
    bins, factor, planes = plan.get("base_bins"), plan.get("bin_factor"), plan.get("planes")
    if bins and (factor or (plan.get("model") == "2d" and k0 > 1)):
        bins = int(bins)
        factor = int(factor) if factor else bins  # a 2D plan: one image of all the bins
        if k0 != bins:
            raise ValueError(f"truth file {path} has {k0} frames; the plan merged a shutter "
                             f"function of {bins} bins, {factor} at a time, into {est_k} "
                             f"frame(s): the truth needs one frame per shutter bin ({bins})")
        t = _bin_frames(t, factor)
        return t, {"from": bins, "bin_factor": factor, "to": int(t.shape[1]),
                   "rule": "mean of the frames each merged frame covers (the groups of "
                           "recon.preprocess.bin_time)"}
    if isinstance(planes, list) and len(planes) == 2 and k0 != est_k:
        first, last = int(planes[0]), int(planes[1])
        if last > k0:
            raise ValueError(f"truth file {path} has {k0} planes; the plan reconstructs "
                             f"planes {first}..{last - 1} of the PSF stack: the truth needs "
                             f"one plane per PSF plane")
        return t[:, first:last], {"from": k0, "kept": [first, last]}
    if k0 != est_k:
        result = f"the {kind} result" if kind in _K_WORDS else "the result"
        has = "is one image" if k0 == 1 else f"has {k0} {what}"
        is_ = f"has {est_k} {what}" if est_k > 1 else "is one image"
        raise ValueError(f"truth file {path} {has}; {result} {is_}")
    return t, None


def _place(t: Any, path: Path, field: tuple[int, int], sensor: tuple[int, int] | None,
           ds: int) -> tuple[Any, dict[str, Any] | None, tuple[int, int, int, int] | None]:
    """The truth on the loader's grid and the scene field, what was done, and where it is.

    A truth covers the scene field or the sensor's field (the fields share their centre, the
    sensor axis), on the loader's grid or at sensor resolution (box-downsampled by ``ds``, as
    the measurement was). One of another field is cropped, or placed the way the forward model
    places the sensor in the field (offset ``field // 2 - truth // 2``) with zeros around it;
    the window (rows r0:r1, columns c0:c1 of the field) where it has values is returned then,
    and only that window is scored (the scene outside it is unknown, not dark).
    """
    import numpy as np

    from recon.preprocess import box_downsample

    h, w = (int(n) for n in t.shape[-2:])
    names = {field: "the scene field"}
    if sensor is not None and sensor != field:
        names[sensor] = "the sensor's field"
    on_grid = (h, w) in names
    at_sensor = ds > 1 and (h // ds, w // ds) in names
    if on_grid and at_sensor:  # e.g. the sensor's field at sensor resolution, or the 2x field
        g, f = names[(h, w)], names[(h // ds, w // ds)]
        raise ValueError(f"truth file {path} is {h}x{w}: {g} on the reconstruction grid or "
                         f"{f} at sensor resolution ({ds}x), cannot tell which; give it on "
                         f"the reconstruction grid ({h // ds}x{w // ds} for {f})")
    if at_sensor:
        t = np.asarray(box_downsample(t, ds), dtype=np.float64)
    elif not on_grid:
        sizes = " or ".join(f"{n[0]}x{n[1]} ({what})" for n, what in names.items())
        res = f", on the reconstruction grid or {ds} times that (sensor resolution)" \
            if ds > 1 else ""
        raise ValueError(f"truth file {path} is {h}x{w}; it must cover {sizes}{res}")
    th, tw = (int(n) for n in t.shape[-2:])
    if (th, tw) == field:
        return t, None, None
    off = (field[0] // 2 - th // 2, field[1] // 2 - tw // 2)
    out = np.zeros((*t.shape[:-2], *field), dtype=t.dtype)
    # the part of the truth inside the field, at its place there
    r0, c0 = max(off[0], 0), max(off[1], 0)
    r1, c1 = min(off[0] + th, field[0]), min(off[1] + tw, field[1])
    out[..., r0:r1, c0:c1] = t[..., r0 - off[0]:r1 - off[0], c0 - off[1]:c1 - off[1]]
    inside = th >= field[0] and tw >= field[1]
    how = ("cut to the scene field" if inside else
           "placed in the scene field; scored on the truth's field only (rows "
           f"{r0}:{r1}, columns {c0}:{c1} of the field: the scene outside it is unknown)")
    return out, {"truth": [th, tw], "scene": list(field), "offset": list(off),
                 "how": f"{how}; both centred on the sensor axis"}, (
        None if inside else (r0, r1, c0, c1))


def _fields(meta: dict[str, Any] | None) -> tuple[tuple[int, int] | None,
                                                 tuple[int, int] | None]:
    """The scene field and the sensor's field on the loader's grid, from a result's metadata.

    None for what the metadata does not say (results from before they were recorded).
    """
    pre = (meta or {}).get("preprocessing") or {}
    out: list[tuple[int, int] | None] = []
    for name in ("field", "sensor"):
        v = pre.get(name)
        ok = isinstance(v, list) and len(v) == 2 and all(isinstance(n, int) for n in v)
        out.append((int(v[0]), int(v[1])) if ok else None)
    return out[0], out[1]


def _prepare_ref(path: Path, est_shape: tuple[int, ...], layout: dict[str, Any],
                 key: str | None, kind: str | None,
                 fields: tuple[tuple[int, int] | None, tuple[int, int] | None] = (None, None),
                 ) -> tuple[Any, dict[str, Any]]:
    """The reference in the frame of the reconstruction, and what was done to it.

    As a problem's truth is read (:func:`recon.problem.prepare_truth`: colour, channel order,
    row flip, sensor resolution downsampled), then its frames, bands or planes brought to the
    result's K (:func:`_slices`), its field to the scene's (:func:`_place`), and a plan's
    downsampling and region.
    """
    import numpy as np

    from recon.preprocess import box_downsample

    plan = layout.get("plan")
    ds = int(layout["downsample"])
    c, k = int(est_shape[0]), int(est_shape[1])
    stack = k > 1 or bool(plan and (plan.get("base_bins") or plan.get("planes")))
    # how many slices the truth should have: a plan's shutter bins, the result's K (a plan's
    # planes are of a stack of unknown size)
    expect = (plan.get("base_bins") if plan and plan.get("base_bins") else
              None if plan and plan.get("planes") else k)
    t = _read_ref(path, est_shape, layout, key, stack, expect)
    if layout["flip_rows"]:
        t = np.ascontiguousarray(t[:, :, ::-1])  # (C, K, H, W): the rows are axis 2
    if t.shape[0] != c:
        raise ValueError(f"truth file {path} has {t.shape[0]} colour channel(s); the result "
                         f"has {c}")
    prepared = {name: layout[name] for name in layout if name != "plan"}
    t, sliced = _slices(t, path, k, kind, plan)
    if sliced is not None:
        prepared[_K_WORDS.get(kind or "", "frames")] = sliced
    loader_field, sensor = fields
    if plan:
        field = (int(plan["field"][0]), int(plan["field"][1]))
    else:
        field = loader_field or (int(est_shape[2]), int(est_shape[3]))
    t, placed, window = _place(t, path, field, sensor, ds)
    if placed is not None:
        prepared["field"] = placed
    if plan is not None:
        d = plan["downsample"]
        if d > 1:
            t = np.asarray(box_downsample(t, d), dtype=np.float64)
        top, left, h, w = plan["region_on_grid"]
        t = t[..., top:top + h, left:left + w]
        prepared["plan"] = plan
        if window is not None:  # the coarse pixels wholly inside the truth's field
            r0, r1, c0, c1 = window
            window = (min(max(-(-r0 // d) - top, 0), h), min(max(r1 // d - top, 0), h),
                      min(max(-(-c0 // d) - left, 0), w), min(max(c1 // d - left, 0), w))
    if window is not None:
        r0, r1, c0, c1 = window
        if r1 <= r0 or c1 <= c0:
            raise ValueError(f"truth file {path}: the result does not cover any of the "
                             "truth's field")
        prepared["scored_window"] = [r0, r1, c0, c1]
    if t.shape != tuple(est_shape):
        where = (f"plan downsample {plan['downsample']}, region {plan['region_on_grid']}"
                 if plan else "no plan")
        raise ValueError(f"{path}: the reference prepared like the reconstruction is "
                         f"{tuple(t.shape)}, the reconstruction {tuple(est_shape)} (C, K, H, W) "
                         f"(field {field[0]}x{field[1]} at downsample {ds}, {where})")
    return t, prepared


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return "inf" if v > 0 else ("-inf" if v < 0 else "nan")
    return v


def run(args: argparse.Namespace) -> int:
    """Load both files, compute :func:`recon.metrics.metrics_report`, print it as JSON."""
    import json

    import numpy as np

    from recon.metrics import metrics_report, spectral_cosine_distance

    est, est_kind, est_meta = _load(args.est, args.key)
    ref, ref_kind, ref_meta = _load(args.ref, args.key)
    layout = _layout(est_meta)
    prepared = None
    # a result (an image, or frames, bands, planes) from a measurement that says how it was
    # read, scored against a plain file (not a reconstruction)
    if layout is not None and not args.ref_as_is and ref_meta is None:
        ref, prepared = _prepare_ref(args.ref, tuple(est.shape), layout, args.key, est_kind,
                                     _fields(est_meta))
        if "scored_window" in prepared:  # the truth covers part of the result's field
            r0, r1, c0, c1 = prepared["scored_window"]
            ref, est = ref[..., r0:r1, c0:c1], est[..., r0:r1, c0:c1]
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
    report = metrics_report(ref, est, gain_fit=args.gain_fit, data_range=args.data_range)
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
