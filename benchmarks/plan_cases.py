"""Reconstruction plans on simulated-camera cases: plan vs the model it avoids (docs/plan.md).

Each case captures one frame with the simulated camera (dual rolling shutter, outside-in,
Poisson and read noise, 16-bit codes) through ``render_frames(psf)``, plans it with
:func:`recon.plan.make_plan`, runs the plan and a baseline with the same solver settings
(FISTA-TV, same tau, same iteration limit), and scores both against the truth with a
least-squares gain fit:

1. static   - a still scene; baseline: the full video model (one frame per line of the frame).
2. moving   - a blob crossing a dim background, one scene frame every ``P`` lines; baseline: 2D.
              Scored per frame against the scene averaged over each of the plan's time bins.
3. object   - a small object in the full padded field (2H x 2W); baseline: the whole field.
              Scored on the object's box.
4. wide-psf - a PSF blurred so its autocorrelation is ~7 px wide; baseline: full resolution.
              Scored against the truth box-downsampled to the plan's grid.

    lenslesscam bench plan [--size 96x128] [--threads 1] [--markdown] [--json FILE]

Times are wall-clock seconds on this machine (a loaded shared machine: compare within a run).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.commands._options import NONNEG_INT, POSITIVE_INT, add_overwrite_option
from benchmarks._cli import check_outputs, hxw

#: The shutter: line time 10 us, exposure ``E`` lines with E = rows // 4 + 1.
LINE_US = 10.0
PEAK_E = 20_000.0


@dataclass
class Capture:
    """A captured frame (scaled to max 1), its timing, the PSF and the truth."""

    meas: np.ndarray
    timing: Any
    psf: np.ndarray
    truth: np.ndarray  # still: (Hs, Ws); moving: (N, Hs, Ws) scene frames
    period: int | None = None


def resize(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of a 2D image to ``shape`` (non-negative)."""
    from scipy.ndimage import zoom

    z = zoom(np.asarray(img, dtype=np.float64), (shape[0] / img.shape[0],
                                                  shape[1] / img.shape[1]), order=1)
    out = np.zeros(shape)
    out[: min(shape[0], z.shape[0]), : min(shape[1], z.shape[1])] = z[: shape[0], : shape[1]]
    return np.clip(out, 0.0, None)


def make_psf(h: int, w: int, blur: float = 1.0, seed: int = 1) -> np.ndarray:
    """A synthetic caustic PSF (unit sum) with about 40 points per 48x64 pixels."""
    from recon.simulate import synthetic_psf

    n = max(20, round(40 * h * w / (48 * 64)))
    return synthetic_psf((h, w), n_points=n, blur=blur, seed=seed)


def exposure_lines(h: int) -> int:
    """Exposure of the cases in lines."""
    return h // 4 + 1


def capture(psf: np.ndarray, scene: Any, *, seed: int = 0, noise: bool = True) -> Capture:
    """One frame of ``scene`` (a StillScene or MovingScene) through the simulated camera."""
    from drivers.simcam import MovingScene, SimulatedCamera, StillScene
    from recon.simulate import render_frames

    h, w = psf.shape
    cam = SimulatedCamera(
        width=w, height=h, renderer=render_frames(psf), scene=scene,
        readout_pattern="outside-in", line_time_us=LINE_US,
        exposure_us=exposure_lines(h) * LINE_US, pixel_format="Mono16", dark_offset_adu=0.0,
        noise=noise, pacing=False, seed=seed,
    )
    signal, _ = cam.render_electrons()
    scale = PEAK_E / float(signal.max())
    if isinstance(scene, StillScene):
        cam.scene = StillScene(scene.image * scale)
        truth = np.asarray(scene.image, dtype=np.float64)
        period = None
    else:
        assert isinstance(scene, MovingScene)
        period = scene.frame_period_lines
        cam.scene = MovingScene(scene.frames * scale, frame_period_lines=period, loop=False)
        truth = np.asarray(scene.frames, dtype=np.float64)
    with cam:
        frame = cam.snap(timeout_s=10.0)
    b = np.asarray(frame.pixels, dtype=np.float64)
    return Capture(np.asarray(b / b.max(), dtype=np.float32), frame.timing, psf, truth, period)


def background(h: int, w: int, name: str = "im408") -> np.ndarray:
    """A natural image (bundled lensed sample) resized to h x w."""
    from recon.samples import lensed_scene

    return resize(lensed_scene(name)[0, 0], (h, w))


def static_capture(h: int, w: int, seed: int = 0) -> Capture:
    """Case 1: a still scene filling the sensor field."""
    from drivers.simcam import StillScene

    return capture(make_psf(h, w), StillScene(background(h, w)), seed=seed)


def moving_frames(h: int, w: int, n: int) -> np.ndarray:
    """A Gaussian blob crossing a dim natural background in ``n`` frames."""
    bg = 0.3 * background(h, w)
    yy, xx = np.mgrid[0:h, 0:w]
    sigma = max(2.0, h / 12)
    frames = []
    for j in range(n):
        cx = 0.15 * w + j * 0.7 * w / max(n - 1, 1)
        frames.append(bg + np.exp(-((yy - h / 2) ** 2 + (xx - cx) ** 2) / (2 * sigma**2)))
    return np.asarray(frames)


def moving_capture(h: int, w: int, period: int, seed: int = 0) -> Capture:
    """Case 2: a moving scene, one scene frame every ``period`` lines (enough to cover it)."""
    from drivers.simcam import MovingScene

    psf = make_psf(h, w)
    frame_lines = (h - 1) // 2 + exposure_lines(h)
    n = -(-frame_lines // period)
    return capture(psf, MovingScene(moving_frames(h, w, n), frame_period_lines=period,
                                    loop=False), seed=seed)


def video_truth(cap: Capture, base_bins: int, factor: int) -> np.ndarray:
    """(1, K, H, W): the scene averaged over each bin of ``factor`` lines."""
    assert cap.period is not None
    n = cap.truth.shape[0]
    idx = np.clip(np.arange(base_bins) // cap.period, 0, n - 1)
    k = -(-base_bins // factor)
    return np.asarray([cap.truth[idx[i * factor:(i + 1) * factor]].mean(axis=0)
                       for i in range(k)])[None]


def object_capture(h: int, w: int, seed: int = 0) -> tuple[Capture, tuple[int, int, int, int]]:
    """Case 3: a small object off-centre in the full padded field (2H x 2W)."""
    from drivers.simcam import StillScene

    psf = make_psf(h, w)
    oh, ow = round(h * 0.42), round(w * 0.4)
    top, left = round(0.42 * h), round(1.1 * w)
    scene = np.zeros((2 * h, 2 * w))
    scene[top:top + oh, left:left + ow] = background(oh, ow, "im740")
    return capture(psf, StillScene(scene), seed=seed), (top, left, oh, ow)


def wide_psf_capture(h: int, w: int, seed: int = 0) -> Capture:
    """Case 4: a still scene seen through a PSF whose features are ~2.2 px blurred."""
    from drivers.simcam import StillScene

    return capture(make_psf(h, w, blur=2.2), StillScene(background(h, w, "im65")), seed=seed)


# ---------------------------------------------------------------------------------------------
# scoring helpers


def score(truth: np.ndarray, est: np.ndarray) -> float:
    """PSNR (dB) after a least-squares gain fit."""
    from recon.metrics import gain_fit, psnr

    g, _ = gain_fit(truth, est)
    return float(psnr(truth, g))


def score_frames(truth: np.ndarray, est: np.ndarray) -> float:
    """Mean per-frame PSNR of (1, K, H, W) videos after one gain fit over the video."""
    from recon.metrics import gain_fit, per_frame

    g, _ = gain_fit(truth, est)
    return float(np.mean(per_frame(truth, g, "psnr")))


def cost_units(plan: Any, psf: Any, cap: Capture, **kw: Any) -> int:
    """FLOP proxy of one iteration: C x K x FFT grid area of the planned model."""
    from recon.plan import planned_model
    from recon.plan.planner import base_shutter

    base, _ = base_shutter(None, cap.timing, plan.sensor[0])
    m = planned_model(plan, psf, shutter=base, **kw)
    py, px = m.info["pad"]
    return int(m.scene_shape[0] * m.scene_shape[1] * py * px)


# ---------------------------------------------------------------------------------------------
# the cases


def _row(case: str, plan: Any, res: Any, q: float, base_name: str, base: Any, qb: float,
         metric: str, units: tuple[int, int]) -> dict[str, Any]:
    g = plan.grid_region
    choice = f"{plan.model} K={plan.k}"
    if not plan.region_obj.is_whole:
        choice += f", region {plan.region[2]}x{plan.region[3]}"
    choice += f", ds {plan.downsample}"
    return {
        "case": case, "plan": choice, "grid": f"{g.height}x{g.width}",
        "plan_s": round(plan.plan_s, 2), "recon_s": round(res.wall_s, 2),
        "iters": res.iterations, "psnr": round(q, 2),
        "baseline": base_name, "baseline_s": round(base.wall_s, 2),
        "baseline_iters": base.iterations, "baseline_psnr": round(qb, 2), "metric": metric,
        "speedup": round(base.wall_s / max(res.wall_s, 1e-9), 1),
        "speedup_with_plan": round(base.wall_s / max(res.wall_s + plan.plan_s, 1e-9), 1),
        "cost_units_ratio": round(units[1] / units[0], 1),
    }


def run_static(h: int, w: int, iters: int = 300, seed: int = 0) -> dict[str, Any]:
    """Case 1."""
    from recon.plan import execute, make_plan

    cap = static_capture(h, w, seed)
    plan = make_plan(cap.psf, cap.meas, timing=cap.timing, seed=seed)
    plan = plan.override(iterations=iters) if plan.iterations != iters else plan
    res = execute(plan, cap.psf, cap.meas, timing=cap.timing)
    full = plan.override(model="video", k=plan.base_bins)
    base = execute(full, cap.psf, cap.meas, timing=cap.timing)
    truth = cap.truth[None, None]
    q = score(truth, res.x) if plan.k == 1 else score_frames(
        np.repeat(truth, plan.k, axis=1), res.x)
    qb = score_frames(np.repeat(truth, full.k, axis=1), base.x)
    units = (cost_units(plan, cap.psf, cap), cost_units(full, cap.psf, cap))
    return _row("static scene", plan, res, q, f"video K={full.k} (every line)", base, qb,
                "PSNR (video: mean per frame)", units)


def run_moving(h: int, w: int, period: int, iters: int = 300, seed: int = 0) -> dict[str, Any]:
    """Case 2."""
    from recon.plan import execute, make_plan

    cap = moving_capture(h, w, period, seed)
    plan = make_plan(cap.psf, cap.meas, timing=cap.timing, seed=seed)
    plan = plan.override(iterations=iters) if plan.iterations != iters else plan
    res = execute(plan, cap.psf, cap.meas, timing=cap.timing)
    two = plan.override(model="2d")
    base = execute(two, cap.psf, cap.meas, timing=cap.timing)
    assert plan.base_bins is not None
    factor = plan.bin_factor or plan.base_bins
    truth = video_truth(cap, plan.base_bins, factor)
    q = score_frames(truth, res.x if plan.k > 1 else np.repeat(res.x, truth.shape[1], axis=1))
    qb = score_frames(truth, np.repeat(base.x, truth.shape[1], axis=1))
    units = (cost_units(plan, cap.psf, cap), cost_units(two, cap.psf, cap))
    true_k = -(-plan.base_bins // period)
    row = _row(f"moving (scene K={true_k})", plan, res, q, "2d", base, qb,
               "mean per-frame PSNR", units)
    row["true_k"] = true_k
    return row


def run_object(h: int, w: int, iters: int = 300, seed: int = 0) -> dict[str, Any]:
    """Case 3."""
    from recon.plan import execute, make_plan

    cap, (top, left, oh, ow) = object_capture(h, w, seed)
    field = (2 * h, 2 * w)
    plan = make_plan(cap.psf, cap.meas, timing=cap.timing, field=field, seed=seed)
    plan = plan.override(iterations=iters) if plan.iterations != iters else plan
    res = execute(plan, cap.psf, cap.meas, timing=cap.timing)
    whole = plan.override(region="whole")
    base = execute(whole, cap.psf, cap.meas, timing=cap.timing)
    truth = cap.truth[top:top + oh, left:left + ow]
    img = res.field_image()[0, 0][top:top + oh, left:left + ow]
    img_b = base.x[0, 0][top:top + oh, left:left + ow]
    units = (cost_units(plan, cap.psf, cap), cost_units(whole, cap.psf, cap))
    return _row("small object, 2x field", plan, res, score(truth, img), "whole field", base,
                score(truth, img_b), "PSNR on the object", units)


def run_wide_psf(h: int, w: int, iters: int = 300, seed: int = 0) -> dict[str, Any]:
    """Case 4."""
    from recon.io import box_downsample
    from recon.plan import execute, make_plan

    cap = wide_psf_capture(h, w, seed)
    plan = make_plan(cap.psf, cap.meas, timing=cap.timing, seed=seed)
    plan = plan.override(iterations=iters) if plan.iterations != iters else plan
    res = execute(plan, cap.psf, cap.meas, timing=cap.timing)
    fullres = plan.override(downsample=1)
    base = execute(fullres, cap.psf, cap.meas, timing=cap.timing)
    d = plan.downsample
    truth = box_downsample(cap.truth, d)
    units = (cost_units(plan, cap.psf, cap), cost_units(fullres, cap.psf, cap))
    fwhm = min(plan.evidence["resolution"]["acf_fwhm_px"])
    return _row(f"wide PSF (ACF {fwhm:.0f} px)", plan, res, score(truth, res.x[0, 0]),
                "downsample 1", base, score(truth, box_downsample(base.x[0, 0], d)),
                f"PSNR at the plan's grid (truth box-downsampled by {d})", units)


CASES = ("static", "moving3", "moving6", "object", "wide")


def run_all(h: int, w: int, iters: int = 300, seed: int = 0,
            cases: tuple[str, ...] = CASES) -> list[dict[str, Any]]:
    """The named cases at sensor size h x w (moving3/6: the scene changes 3 or 6 times)."""
    frame_lines = (h - 1) // 2 + exposure_lines(h)
    rows: list[dict[str, Any]] = []
    for name in cases:
        if name == "static":
            rows.append(run_static(h, w, iters, seed))
        elif name in ("moving3", "moving6"):
            n = int(name[-1])
            rows.append(run_moving(h, w, -(-frame_lines // n), iters, seed))
        elif name == "object":
            rows.append(run_object(h, w, iters, seed))
        elif name == "wide":
            rows.append(run_wide_psf(h, w, iters, seed))
        else:
            raise ValueError(f"unknown case {name!r}; cases: {', '.join(CASES)}")
    return rows


# ---------------------------------------------------------------------------------------------
# command line


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench plan``."""
    p.add_argument("--size", type=hxw(32), default="96x128",
                   help="sensor HxW, both sides >= 32 (default 96x128)")
    p.add_argument("--iters", type=POSITIVE_INT, default=300, help="FISTA iteration limit (300)")
    p.add_argument("--threads", type=POSITIVE_INT, default=None,
                   help="torch threads (default: the global --threads, else the thread "
                   "policy, recon.threads)")
    p.add_argument("--seed", type=NONNEG_INT, default=0, help="camera noise and CV seed")
    p.add_argument("--cases", type=_case_list, default=",".join(CASES),
                   help=f"comma-separated cases (default all: {','.join(CASES)})")
    p.add_argument("--markdown", action="store_true", help="print a Markdown table")
    p.add_argument("--json", default=None, help="also write the rows as JSON here")
    add_overwrite_option(p)


def _case_list(text: str) -> tuple[str, ...]:
    """``--cases``: comma-separated names of :data:`CASES`, at least one."""
    names = tuple(c.strip() for c in text.split(",") if c.strip())
    if not names or set(names) - set(CASES):
        raise argparse.ArgumentTypeError(
            f"must be comma-separated cases of {', '.join(CASES)}, got {text!r}")
    return names


def _table(rows: list[dict[str, Any]], markdown: bool) -> str:
    head = ["case", "plan", "grid", "plan s", "recon s", "PSNR", "baseline", "baseline s",
            "baseline PSNR", "speed-up (with plan)", "cost/iter ratio", "metric"]
    body = [[r["case"], r["plan"], r["grid"], f"{r['plan_s']:.2f}", f"{r['recon_s']:.2f}",
             f"{r['psnr']:.2f}", r["baseline"], f"{r['baseline_s']:.2f}",
             f"{r['baseline_psnr']:.2f}", f"{r['speedup']:.1f}x ({r['speedup_with_plan']:.1f}x)",
             f"{r['cost_units_ratio']:.1f}x", r["metric"]] for r in rows]
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in body]
        return "\n".join(lines)
    widths = [max(len(str(x)) for x in col) for col in zip(head, *body, strict=True)]
    fmt = "  ".join(f"{{:<{wd}}}" for wd in widths)
    return "\n".join([fmt.format(*head)] + [fmt.format(*map(str, row)) for row in body])


def run(args: argparse.Namespace) -> int:
    """Run every case and print the table."""
    from benchmarks._cli import bench_metadata, bench_threads

    check_outputs(args, {"--json": args.json})
    choice = bench_threads(args)
    h, w = args.size
    t0 = time.perf_counter()
    rows = run_all(h, w, args.iters, args.seed, tuple(args.cases))
    print(f"lenslesscam bench plan: sensor {h}x{w}, torch threads {args.threads}, "
          f"FISTA-TV up to {args.iters} iterations, total {time.perf_counter() - t0:.0f} s")
    print(_table(rows, args.markdown))
    if args.json:
        from recon.atomic import atomic_write_json

        atomic_write_json(args.json, {**bench_metadata("plan", 1, choice), "rows": rows,
                                      "size": [h, w], "iters": args.iters, "seed": args.seed,
                                      "cases": list(args.cases)})
    bad = [r["case"] for r in rows if not math.isfinite(r["psnr"])]
    if bad:
        print(json.dumps({"non_finite": bad}))
        return 1
    return 0
