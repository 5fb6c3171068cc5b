"""One preparation of a ground truth: a plain truth file put in the frame of a reconstruction.

API::

    t, prepared = prepare_truth_like(path, est_shape, layout, kind="video",
                                     field=(48, 64), sensor=(24, 32))
    layout = truth_layout(result_metadata)        # from a reconstruction's metadata, or None
    field, sensor = result_fields(result_metadata)

Used by ``lenslesscam metrics`` (with a result's metadata) and by the problem loader
(:func:`recon.problem.prepare_truth`, :func:`recon.problem.load_truth`: a run's ``--truth``,
a job spec's ``data.truth``, ``jobs combine``, a batch item's scores), so that a truth is put
in the result's frame one way. The steps, in the order of the measurement it was made from:

- **read** (:func:`recon.problem.read_truth`: colour, channel order); a gray result of several
  frames, bands or planes (or binned from them) also takes a ``(K, H, W)`` stack;
- **row flip** (axis 2 of (C, K, H, W));
- **K**: a plan's merged shutter bins (each merged frame the mean of its bins, the groups of
  :func:`recon.preprocess.bin_time`), a plan's kept planes; otherwise the result's K;
- **field**: a truth of the scene field or the sensor's field (same centre, the sensor axis),
  on the loader's grid or at sensor resolution (box-downsampled); a smaller one is placed in
  the field with zeros around it and only its window is to be scored
  (``prepared['scored_window']``), a larger one cut; a size that is one field on the grid
  and the other at sensor resolution is refused (it cannot be told which);
- a plan's **downsampling and region** (``recon auto``).

Every refusal is one line naming the file and what it would need.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from recon.preprocess import bin_time, box_downsample

__all__ = ["TRUTH_KEYS", "prepare_truth_like", "result_fields", "truth_for_result",
           "truth_layout"]

Array = npt.NDArray[Any]
PathLike = str | os.PathLike[str]
Window = tuple[int, int, int, int]

#: the variables a truth is read from in an NPZ/MAT file, in order of preference
TRUTH_KEYS: tuple[str, ...] = ("truth", "scene", "x", "arr_0", "data")
#: what the K axis of a reconstruction kind holds, in words
_K_WORDS = {"video": "frames", "spectral": "bands", "depth": "planes"}


def truth_layout(meta: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """How the measurement of a reconstruction was read, as :func:`prepare_truth_like` takes it.

    From its metadata's ``preprocessing`` (and a ``recon auto`` plan); None when the metadata
    does not say.
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


def result_fields(meta: Mapping[str, Any] | None) -> tuple[tuple[int, int] | None,
                                                          tuple[int, int] | None]:
    """The scene field and the sensor's field on the loader's grid, from a result's metadata.

    None for what the metadata does not say (results from before they were recorded).
    """
    pre = (meta or {}).get("preprocessing") or {}
    out: list[tuple[int, int] | None] = []
    for name in ("field", "sensor"):
        v = pre.get(name)
        if isinstance(v, list) and len(v) == 2 and all(isinstance(n, int) for n in v):
            out.append((int(v[0]), int(v[1])))
        else:
            out.append(None)
    return out[0], out[1]


def _read(path: PathLike, est_shape: Sequence[int], layout: Mapping[str, Any],
          key: str | None, stack: bool, expect: int | None, dtype: Any,
          gray_only: bool = False) -> Array:
    """The truth file as (C, K0, H, W), colour and channel order as the layout says.

    :func:`recon.problem.read_truth`, the one way a problem's truth is read; a gray result
    that has (or is binned from) several frames, bands or planes also takes a (K, H, W) stack,
    which that reader would take for colour channels (a (3, H, W) file is a stack only when
    ``expect``, the number of slices wanted, is 3, or for a model that has no colour,
    ``gray_only``: depth, whose recon auto result of 3 planes was scored against the luma of
    a 3-plane truth, "1 planes").
    """
    from recon.problem import read_truth
    from recon.readers import load_image

    if stack and est_shape[0] == 1:
        raw = np.asarray(load_image(Path(path), key=key, prefer=TRUTH_KEYS))
        hwc = raw.ndim == 3 and raw.shape[2] in (3, 4) and raw.shape[0] not in (1, 3, 4)
        if raw.ndim == 3 and not hwc and (raw.shape[0] != 3 or expect == 3 or gray_only):
            t = raw.astype(dtype)[np.newaxis]  # (K, H, W): a gray stack of K slices
            if not np.all(np.isfinite(t)):
                raise ValueError(f"truth file {path} has NaN or infinite values")
            return t
    return read_truth(path, color=layout["color"], channel_order=layout["channel_order"],
                      key=key).astype(dtype)


def _bin_frames(t: Array, factor: int) -> Array:
    """Frames (C, K0, H, W) merged ``factor`` at a time, as the plan merges shutter bins.

    The groups of :func:`recon.preprocess.bin_time` (THE time-binning rule; the last group may
    be partial) and the mean of the frames each group holds: a partial group's shutter row is
    the smaller exposure (bin_time averages it over ``factor``), its frame is still the scene.
    """
    c, k0, h, w = t.shape
    summed = bin_time(np.moveaxis(t, 1, 0).reshape(k0, -1), factor)  # (K, C*H*W)
    present = bin_time(np.ones((k0, 1)), factor)  # share of each group's bins that exist
    out = (summed / present).reshape(-1, c, h, w)
    return np.ascontiguousarray(np.moveaxis(out, 0, 1), dtype=t.dtype)


def _slices(t: Array, path: PathLike, est_k: int, kind: str | None,
            plan: Mapping[str, Any] | None) -> tuple[Array, dict[str, Any] | None]:
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
        colour = (" (a colour truth of a gray result: give it as an (H, W, 3) image, which is "
                  "taken to luma)" if k0 == 3 and int(t.shape[0]) == 1 else "")
        raise ValueError(f"truth file {path} {has}; {result} {is_}{colour}")
    return t, None


def _place(t: Array, path: PathLike, field: tuple[int, int], sensor: tuple[int, int] | None,
           ds: int) -> tuple[Array, dict[str, Any] | None, Window | None]:
    """The truth on the loader's grid and the scene field, what was done, and where it is.

    A truth covers the scene field or the sensor's field (the fields share their centre, the
    sensor axis), on the loader's grid or at sensor resolution (box-downsampled by ``ds``, as
    the measurement was). One of another field is cropped, or placed the way the forward model
    places the sensor in the field (offset ``field // 2 - truth // 2``) with zeros around it;
    the window (rows r0:r1, columns c0:c1 of the field) where it has values is returned then,
    and only that window is to be scored (the scene outside it is unknown, not dark).
    """
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
                         f"the reconstruction grid ({h // ds}x{w // ds} for {f}) or at sensor "
                         f"resolution ({h * ds}x{w * ds} for {g})")
    if at_sensor:
        t = np.asarray(box_downsample(t, ds), dtype=t.dtype)
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


def prepare_truth_like(path: PathLike, est_shape: Sequence[int], layout: Mapping[str, Any], *,
                       kind: str | None = None, field: tuple[int, int] | None = None,
                       sensor: tuple[int, int] | None = None, key: str | None = None,
                       dtype: Any = np.float64) -> tuple[Array, dict[str, Any]]:
    """A truth file in the frame of a reconstruction of ``est_shape`` (C, K, H, W), and how.

    ``layout``: how the measurement was read (``color``, ``channel_order``, ``flip_rows``,
    ``downsample``; ``plan`` for a ``recon auto`` result: :func:`truth_layout`); ``kind``: the
    result's kind (image, video, spectral, depth; for messages); ``field``, ``sensor``: the
    scene field and the sensor's field on the loader's grid (:func:`result_fields`; the field
    defaults to the result's H, W, and an unknown sensor field is not looked for); ``dtype``
    of the result (the file is read as float32 and cast, a ``(K, H, W)`` stack read as it is
    stored and cast).

    Returns the prepared truth, ``est_shape`` in ``dtype``, and what was done to it: the
    layout's settings, and ``frames``/``bands``/``planes`` (K brought to the result's),
    ``field`` (placed in or cut to the scene field), ``plan``, and ``scored_window``
    ([r0, r1, c0, c1] of the result) when the truth covers only part of the result's field:
    only that window is to be scored (the scene outside it is unknown, not dark).

    Raises ValueError (one line, naming the file) for a truth that cannot be prepared so.
    """
    plan = layout.get("plan")
    ds = int(layout["downsample"])
    c, k = int(est_shape[0]), int(est_shape[1])
    stack = k > 1 or bool(plan and (plan.get("base_bins") or plan.get("planes")))
    # how many slices the truth should have: a plan's shutter bins, the result's K (a plan's
    # planes are of a stack of unknown size)
    expect = (plan.get("base_bins") if plan and plan.get("base_bins") else
              None if plan and plan.get("planes") else k)
    # a gray result of frames, bands or planes: a (3, H, W) array is 3 of them, not colour
    # (a 3-frame truth of a K = 1 video was taken to luma and scored, silently)
    sliced_kind = kind == "depth" or (kind in ("video", "spectral") and c == 1)
    stack = stack or sliced_kind
    t = _read(path, est_shape, layout, key, stack, expect, dtype, gray_only=sliced_kind)
    if layout["flip_rows"]:
        t = np.ascontiguousarray(t[:, :, ::-1])  # (C, K, H, W): the rows are axis 2
    if t.shape[0] != c:
        raise ValueError(f"truth file {path} has {t.shape[0]} colour channel(s); the result "
                         f"has {c}")
    prepared = {name: layout[name] for name in layout if name != "plan"}
    t, sliced = _slices(t, path, k, kind, plan)
    if sliced is not None:
        prepared[_K_WORDS.get(kind or "", "frames")] = sliced
    if plan:
        field = (int(plan["field"][0]), int(plan["field"][1]))
    else:
        field = field or (int(est_shape[2]), int(est_shape[3]))
    t, placed, window = _place(t, path, field, sensor, ds)
    if placed is not None:
        prepared["field"] = placed
    if plan is not None:
        d = plan["downsample"]
        if d > 1:
            t = np.asarray(box_downsample(t, d), dtype=t.dtype)
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
    if t.shape != tuple(int(n) for n in est_shape):
        where = (f"plan downsample {plan['downsample']}, region {plan['region_on_grid']}"
                 if plan else "no plan")
        raise ValueError(f"{path}: the truth prepared like the reconstruction is "
                         f"{tuple(t.shape)}, the reconstruction {tuple(est_shape)} (C, K, H, W) "
                         f"(field {field[0]}x{field[1]} at downsample {ds}, {where})")
    return np.ascontiguousarray(t, dtype=dtype), prepared


def truth_for_result(path: PathLike, est: Array, meta: Mapping[str, Any] | None, *,
                     key: str | None = None) -> tuple[Array, Array, dict[str, Any]] | None:
    """A truth file and a reconstruction (C, K, H, W) with its metadata, ready to compare.

    The truth prepared like the result (:func:`prepare_truth_like` with the result's
    :func:`truth_layout`, :func:`result_fields` and kind), and both cut to the truth's window
    where it covers part of the result's field; with what was done. None when the metadata
    does not say how the measurement was read (the caller compares the files as stored).
    ``lenslesscam metrics`` and batch scores use it alike.
    """
    layout = truth_layout(meta)
    if layout is None:
        return None
    field, sensor = result_fields(meta)
    ref, prepared = prepare_truth_like(path, tuple(est.shape), layout,
                                       kind=(meta or {}).get("kind"), field=field,
                                       sensor=sensor, key=key, dtype=est.dtype)
    if "scored_window" in prepared:  # the truth covers part of the result's field
        r0, r1, c0, c1 = prepared["scored_window"]
        ref, est = ref[..., r0:r1, c0:c1], est[..., r0:r1, c0:c1]
    return ref, est, prepared
