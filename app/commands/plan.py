"""``lenslesscam plan`` and ``lenslesscam recon auto``: plan the simplest model, and run it.

``plan`` analyses a measurement with its calibration and prints the plan (model, K, region,
downsampling, method for the budget) with the reason for each choice, or its JSON.
``recon auto`` makes the plan (or reads one with ``--plan``), applies ``--set`` overrides and
runs it. The ``recon`` command calls :func:`register_auto` to add ``auto`` to its methods.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

from app.commands._common import ProgressBar
from app.commands._inputs import add_layout_arguments, problem_spec
from app.commands._options import (
    NONNEG_INT,
    add_overwrite_option,
    check_command_outputs,
)
from app.commands._tau import tau_type

_UNITS = {"ms": 1e-3, "s": 1.0, "sec": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0, "": 1.0}


def parse_budget(value: str | None) -> float | None:
    """'60s', '5min', '2h', '500ms' or a bare number of seconds; None or 'none' for none."""
    if value is None or value.strip().lower() in ("", "none"):
        return None
    m = re.fullmatch(r"\s*(-?[0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*(ms|s|sec|min|m|h)?\s*",
                     value)  # a sign read, so that -5s is "must be positive"
    if not m:
        raise ValueError(f"cannot read {value!r} as a time budget (examples: 60s, 5min, 2h)")
    seconds = float(m.group(1)) * _UNITS[m.group(2) or ""]
    if seconds <= 0:
        raise ValueError(f"the time budget must be positive, got {value!r}")
    return seconds


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``--set KEY=VALUE`` items; VALUE is read as JSON when it parses, else as a string."""
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        out[key.strip().replace("-", "_")] = value
    return out




def add_plan_inputs(p: argparse.ArgumentParser) -> None:
    """Inputs shared by ``plan`` and ``recon auto``."""
    p.add_argument("--psf", help="PSF file")
    p.add_argument("--psf-stack", help="depth PSF stack (multi-page TIFF, (K,H,W) array, folder)")
    p.add_argument("--meas", required=True, help="measurement file")
    p.add_argument("--shutter", help="finest shutter function M (K, rows) (.npy/.npz/.tif)")
    p.add_argument("--timing", help="sensor timing JSON (SensorTiming fields, or a frame's "
                   "metadata with a 'timing' key)")
    p.add_argument("--mask", help="dead-pixel / erasure mask (1 = measured)")
    p.add_argument("--budget", help="time budget of the reconstruction: 60s, 5min, 2h (the "
                   "analysis and the automatic tau's search come on top: plan_s, "
                   "tau_search_s; --tau skips the search)")
    p.add_argument("--trade", help="a trade.csv from `lenslesscam trade` on similar data: the "
                                   "method, tau and iterations for the budget come from it "
                                   "(its full-resolution settings in the precision the run "
                                   "uses: float32, or float64 with recon auto --float64)")
    p.add_argument("--field", default="sensor", help="scene field: sensor, full (2x) or HxW")
    from app.commands._inputs import add_dark_arguments

    add_dark_arguments(p)
    p.add_argument("--rgb", action="store_true", help="colour measurement and PSF")
    p.add_argument("--tau", type=tau_type, default=None, metavar="TAU|auto",
                   help="TV weight of a FISTA-TV plan; 'auto' (default) chooses it and the "
                   "iterations from held-out measured pixels (recon.autotau)")
    p.add_argument("--seed", type=NONNEG_INT, default=0, help="seed of the held-out pixels")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a plan field (repeatable), e.g. --set model=video --set k=8")
    add_layout_arguments(p)


def register(sub: Any) -> None:
    """Add ``plan``."""
    p = sub.add_parser("plan", help="choose the simplest model the scene needs, and say why")
    add_plan_inputs(p)
    p.add_argument("--json", action="store_true", help="print the plan as JSON")
    p.add_argument("--out", help="also save the plan as JSON here (for recon auto --plan)")
    p.add_argument("--no-probe", action="store_true",
                   help="do not time the planned model (no time estimate)")
    add_overwrite_option(p)
    p.set_defaults(func=run_plan)


def register_auto(methods: Any) -> None:
    """Add ``auto`` to ``recon``'s methods (called by app/commands/recon.py)."""
    p = methods.add_parser("auto", help="plan the simplest model the scene needs and run it")
    add_plan_inputs(p)
    p.add_argument("--plan", help="run this saved plan (from lenslesscam plan --out)")
    p.add_argument("--out", required=True, help="output TIFF (previews are written beside it)")
    p.add_argument("--float64", action="store_true", help="compute in float64")
    p.add_argument("--quiet", action="store_true", help="do not print the plan to stderr")
    add_overwrite_option(p)
    p.set_defaults(func=run_auto)


def load_inputs(args: argparse.Namespace) -> dict[str, Any]:
    """Load measurement, PSF (or stack), shutter / timing and mask named on the command line.

    Through :func:`recon.problem.load_problem` at full resolution (the plan chooses the
    downsampling, with the same mask rule); the shutter through its one reader.
    """
    import numpy as np

    from recon.problem import load_problem, read_shutter

    if not (args.psf or args.psf_stack):
        raise ValueError("give --psf (or --psf-stack for a depth measurement)")
    depth = bool(args.psf_stack)
    if depth and (args.shutter or getattr(args, "timing", None)):
        raise ValueError("a PSF stack (depth) plan takes no --shutter or --timing: give them "
                         "with --psf for a video plan")
    spec = problem_spec(args, model="depth" if depth else "2d", downsample=1, shutter=None,
                        filters=None, truth=None)
    prob = load_problem(spec)
    shutter = None
    if args.shutter:
        shutter, _ = read_shutter(args.shutter)
        if spec.flip_rows:
            shutter = np.ascontiguousarray(shutter[:, ::-1])
    timing = None
    if args.timing:
        path = Path(args.timing)
        if not path.is_file():
            raise FileNotFoundError(f"timing file not found: {args.timing}")
        data = _timing_source(path)
        raw = data.get("timing", data) if isinstance(data, dict) else None
        if not isinstance(raw, dict):
            raise ValueError(f"{args.timing}: expected a JSON object with the timing fields")
        from drivers.timing import SensorTiming

        try:
            timing = SensorTiming.from_dict(raw)
        except (KeyError, TypeError, ValueError, OverflowError) as e:  # Infinity: Overflow
            raise ValueError(f"{args.timing}: not a sensor timing ({e})") from e
    if shutter is not None and timing is not None:
        raise ValueError("give --shutter or --timing, not both")
    if prob.metadata["psf_grid"] == "padded" and (shutter is not None or timing is not None):
        raise ValueError("plan: a padded-grid PSF is not supported with a shutter or timing; "
                         "give the PSF on the sensor grid")
    sensor = (int(prob.meas.shape[-2]), int(prob.meas.shape[-1]))
    return {"meas": prob.meas, "psf": None if depth else prob.psf_per_channel(),
            "stack": prob.psf if depth else None, "shutter": shutter, "timing": timing,
            "mask": prob.mask, "sensor": sensor,
            "field": tuple(int(n) for n in prob.model.scene_shape[2:]), "problem": prob}


def check_field_reach(field: Any, inputs: dict[str, Any]) -> None:
    """The one field rule (:func:`recon.checks.check_field`, as ``--field``) for a plan's field.

    On the real sensor and PSF of the inputs: a plan knows only its own grid, which for a PSF
    on the padded grid is the padded grid, so its own check (twice that grid) is looser than
    the light's reach from the real sensor. A malformed value is left to ``Plan.override``.
    """
    from recon.checks import check_field

    if not (isinstance(field, list | tuple) and len(field) == 2 and all(
            isinstance(n, int) and not isinstance(n, bool) for n in field)):
        return
    prob = inputs["problem"]
    check_field(field, prob.sensor, tuple(prob.psf.shape[-2:]), "plan field 'field'")


def _make(args: argparse.Namespace, inputs: dict[str, Any], probe: bool = True) -> Any:
    from recon.plan import make_plan

    overrides = parse_overrides(args.set)
    if "field" in overrides:  # before the analysis: a field past the light's reach costs GBs
        check_field_reach(overrides["field"], inputs)

    def progress(msg: str) -> None:
        if sys.stderr.isatty():
            print(f"plan: {msg}", file=sys.stderr)

    plan = make_plan(
        inputs["psf"], inputs["meas"], shutter=inputs["shutter"], timing=inputs["timing"],
        psf_stack=inputs["stack"], mask=inputs["mask"],
        field=inputs["field"], sensor=_window(inputs),
        budget_s=parse_budget(args.budget),
        tau=args.tau, seed=args.seed, probe=probe,
        progress=progress)
    if getattr(args, "trade", None):
        plan = plan_from_trade(plan, args.trade, inputs,
                               who=f"lenslesscam {getattr(args, 'command', None) or 'plan'}",
                               precision="float64" if getattr(args, "float64", False)
                               else "float32")
    plan = plan.override(**overrides) if overrides else plan
    warn_region(plan, args)
    if (args.tau is None and not getattr(args, "trade", None) and plan.method == "fista-tv"
            and "tau" not in overrides):
        from recon.plan import auto_tau_plan

        plan = auto_tau_plan(plan, inputs["psf"], inputs["meas"], shutter=inputs["shutter"],
                             timing=inputs["timing"], psf_stack=inputs["stack"],
                             mask=inputs["mask"])
    return plan


def warn_region(plan: Any, args: argparse.Namespace) -> None:
    """Print, on stderr, the plan's warning about a region or field the user set too small.

    :func:`recon.plan.planner.region_energy_warning`: it holds less of the scene's energy than
    the plan's extent analysis found (the plan's reasons say it too).
    """
    from recon.plan.planner import region_energy_warning

    warning = region_energy_warning(plan)
    if warning is not None:
        who = f"lenslesscam {getattr(args, 'command', None) or 'plan'}"
        print(f"{who}: warning: {warning}", file=sys.stderr)


def _timing_source(path: Path) -> Any:
    """The JSON of a timing file.

    A JSON file, or a saved frame (TIFF) whose metadata holds its ``timing``
    (``lenslesscam snap``, the app's Snap & save).
    """
    if path.suffix.lower() in (".tif", ".tiff"):
        from drivers.camera import read_frame_metadata

        return read_frame_metadata(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, RecursionError) as exc:  # not UTF-8, not JSON, nested past reason
        raise ValueError(f"{path}: not a JSON timing file or a saved frame ({exc})") from None


def tau_search_seconds(plan: Any) -> float | None:
    """Seconds :func:`recon.plan.auto_tau_plan` took for ``plan`` (None: tau was not searched)."""
    found = plan.evidence.get("tau_search") if isinstance(plan.evidence, dict) else None
    if not isinstance(found, dict) or not isinstance(found.get("seconds"), int | float):
        return None
    return float(found["seconds"])


def trade_data_warning(trade: Any, inputs: dict[str, Any], who: str = "plan") -> str | None:
    """One line when ``trade`` (a :class:`recon.trade.TradeFile`) was measured on other data.

    The plan's data (its measurement, PSF or stack, mask and field as :func:`load_inputs`
    reads them) against each case the trade records (:func:`recon.trade.case_differences`:
    measurement shape, scene field, PSF); None when every case matches. A trade.csv from
    before the header records no case: that is said too, as it cannot be checked.
    """
    from recon.trade import Case, case_differences, case_record

    if not trade.cases:
        return (f"{who}: warning: {trade.path} records no data it was measured on (a trade.csv "
                "from before format version 1): not checked against this plan's data")
    prob = inputs["problem"]
    psf = inputs["psf"] if inputs["psf"] is not None else inputs["stack"]
    data = case_record(Case("plan", psf, inputs["meas"], inputs["mask"],
                            field=tuple(inputs["field"]),
                            source={"psf_file_hash": prob.hashes.get("psf")}))
    off = [(c.get("name"), d) for c in trade.cases if (d := case_differences(c, data))]
    if not off:
        return None
    name, diffs = off[0]
    which = (f"case {name!r}" if len(trade.cases) == 1 else
             f"{len(off)} of its {len(trade.cases)} cases, e.g. {name!r}")
    return (f"{who}: warning: {trade.path} was measured on other data than this plan's "
            f"({which}: {', '.join(diffs)}); its timings and tau may not hold here")


def check_trade_option(args: argparse.Namespace) -> None:
    """``--trade`` names a file: one line for a folder (it said "[Errno 21] Is a directory")."""
    path = getattr(args, "trade", None)
    if path and Path(path).is_dir():
        inside = Path(path) / "trade.csv"
        hint = (f": give the trade.csv in it (--trade {inside})" if inside.is_file() else
                ": give the trade.csv that 'lenslesscam trade --out' wrote")
        raise ValueError(f"--trade {path} is a folder, not a trade.csv{hint}")


def _udn_row_problem(row: Any, plan: Any) -> str | None:
    """Why a UDN row of a trade cannot run as measured in ``plan`` (None: it can).

    The row must record the settings it ran (``udn_settings``, :func:`recon.trade.udn_settings`)
    and each must be one this release runs (:func:`recon.plan.planner.udn_configs`): a plan
    never runs another network than the one measured.
    """
    if row.udn_settings is None:
        return ("its trade.csv row does not record the network settings it ran (a trade.csv "
                "written before they were recorded: run lenslesscam trade again)")
    try:
        from recon.plan.planner import udn_configs

        net, _ = udn_configs(row.udn_settings)
    except ImportError:
        return "recon.udn cannot be imported here"
    except ValueError as exc:
        return f"its {exc}"
    if net.variant == "2d" and plan.k > 1:
        return (f"its network reconstructs one image (variant 2d) and the plan has K = "
                f"{plan.k}")
    return None


def plan_from_trade(plan: Any, trade_csv: str, inputs: dict[str, Any] | None = None,
                    who: str = "plan", precision: str = "float32") -> Any:
    """Take method, tau, iterations and a UDN's settings from the best trade setting.

    The best setting within the plan's budget. With the plan's ``inputs``
    (:func:`load_inputs`), a trade measured on other data is warned about on stderr
    (:func:`trade_data_warning`); the plan still uses it.

    Only settings the plan's run reproduces are candidates: full resolution; FISTA-TV (the
    plan's solver; an ADMM-TV row is another image short of convergence) in the
    ``precision`` it will compute in (a plan records no solver precision:
    ``recon auto`` runs it in float32, in float64 with ``--float64``); a UDN whose row records
    the network and run settings it measured (the plan carries them in ``udn``, its precision
    among them, and runs them). A better setting that is not a candidate is named in the
    reason, with why.
    """
    import dataclasses

    from recon.plan.planner import udn_text
    from recon.trade import best_for_budgets, read_trade

    if plan.budget_s is None:
        raise ValueError("--trade needs --budget (the time the reconstruction may take)")
    trade = read_trade(trade_csv)
    if inputs is not None and (warning := trade_data_warning(trade, inputs, who)):
        print(warning, file=sys.stderr)
    full = [r for r in trade.rows if r.downsample == 1]

    def problem(r: Any) -> str | None:
        if r.method == "udn":
            return _udn_row_problem(r, plan)
        if r.method != "fista":
            # short of convergence (where a budget puts a trade's best rows) the two solvers
            # give different images: an ADMM row run as FISTA-TV scored 17.99 dB, not its 18.20
            return (f"is {r.method.upper()}-TV, which a plan does not run (its FISTA-TV at the "
                    f"same tau and iterations is another image; recon {r.method} --tau "
                    f"{r.tau:g} --iters {r.iterations} runs it)")
        if r.precision != precision:
            how = ("; recon auto --float64 chooses among the float64 ones"
                   if r.precision == "float64" else "")
            return (f"computes in {r.precision}, which the plan does not record, so its run "
                    f"could not reproduce it{how}")
        return None

    why_not = {id(r): problem(r) for r in full}
    rows = [r for r in full if why_not[id(r)] is None]
    key = "psnr" if full and all(r.psnr is not None for r in full) else "heldout_psnr"
    best = best_for_budgets(rows, [plan.budget_s], key)[plan.budget_s]
    if best is None:
        other = sorted({r.precision for r in full if r.method != "udn"} - {precision})
        also = (f" in {precision} (its {', '.join(other)} settings are not candidates: the "
                f"plan runs in {precision})" if other else f" in {precision}")
        out = best_for_budgets([r for r in full if why_not[id(r)] is not None and (
            r.method == "udn" or r.precision == precision)], [plan.budget_s],
            key)[plan.budget_s]  # (rows of another precision are said above)
        if out is not None:
            also += f"; {out.setting} fits but {why_not[id(out)]}"
        raise ValueError(f"{trade_csv}: no measured setting fits the budget of "
                         f"{plan.budget_s:g} s{also}")
    method = "udn" if best.method == "udn" else "fista-tv"
    carried: dict[str, Any] = ({"udn": best.udn_settings} if method == "udn" else
                               {"tau": best.tau})
    new = plan.override(method=method, iterations=best.iterations, **carried)
    quality = getattr(best, key)
    unit = "PSNR" if key == "psnr" else "held-out"
    why = (f"from the trade ({trade_csv}): the best of {len(rows)} measured settings a "
           f"{precision} plan reproduces within {plan.budget_s:g} s was {best.setting} at "
           f"{best.iterations} iterations ({best.wall_s:.2f} s, {quality:.2f} dB {unit})")
    if method == "udn":
        why += f"; the plan runs the network it measured: {udn_text(best.udn_settings)}"
    top = best_for_budgets(full, [plan.budget_s], key)[plan.budget_s]
    if top is not None and why_not[id(top)] is not None and getattr(top, key) > quality:
        why += f"; {top.setting} ({getattr(top, key):.2f} dB) was better but {why_not[id(top)]}"
    reasons = {**new.reasons, "method": why, "tau": why, "iterations": why}
    if method == "udn":
        reasons["udn"] = why
    # chosen from the trade's measurements, not set by the user
    return dataclasses.replace(new, reasons=reasons, overridden=plan.overridden)


def run_plan(args: argparse.Namespace) -> int:
    """Print (and optionally save) the plan."""
    from recon.atomic import atomic_write_json

    if args.out:
        check_command_outputs(args, [args.out])
    check_trade_option(args)
    inputs = load_inputs(args)
    plan = _make(args, inputs, probe=not args.no_probe)
    window = _window(inputs)
    d = plan.to_json()
    if window is not None:  # "sensor" is the padded grid the plan runs on
        d["measurement_window"] = list(window)
    if args.out:
        saved = dict(d)
        if getattr(args, "meas", None) and getattr(args, "psf", None):
            import datetime as _dt

            from recon.suggest import input_hashes_of_files

            # which measurement the plan is for: the app's job dialog offers it for that frame
            saved["inputs"] = input_hashes_of_files(args.meas, args.psf)
            saved["created_utc"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        atomic_write_json(args.out, saved)
    if args.json:
        print(json.dumps(d, indent=2, default=str))
    else:
        print(plan.describe(window))
    return 0


def plan_data_check(saved: Any, args: argparse.Namespace) -> dict[str, Any] | None:
    """Whether a saved plan was made on this measurement and PSF (its ``inputs`` hashes).

    One line on stderr when they differ: its tau and iterations were chosen on that data (a
    plan of another scene of the same size ran without a word, its metadata saying tau was
    "chosen from held-out measured pixels"). Returns what the result's metadata records
    (``recorded``, ``this``, ``match``), None for a plan that records no data (older, or
    made from Python) or a PSF stack.
    """
    recorded = saved.get("inputs") if isinstance(saved, dict) else None
    if (not isinstance(recorded, dict) or not args.psf or not recorded.get("measurement")
            or not recorded.get("psf")):  # nothing recorded ("inputs": {} too)
        return None
    from recon.suggest import input_hashes_of_files, inputs_match

    this = input_hashes_of_files(args.meas, args.psf)
    match = inputs_match(recorded, this)
    if not match:
        which = [k for k in ("measurement", "psf") if recorded.get(k) != this.get(k)]
        print(f"recon auto: warning: plan file {args.plan} was made on another "
              f"{' and '.join('PSF' if k == 'psf' else k for k in which)} (hashes differ): "
              "its settings were chosen for that data; plan again for this one",
              file=sys.stderr)
    return {"recorded": {k: recorded.get(k) for k in ("measurement", "psf")}, "this": this,
            "match": match}


def check_plan_matches(saved: Any, inputs: dict[str, Any], name: str) -> None:
    """Refuse a saved plan (its JSON) made for another measurement size, naming both.

    A plan's ``sensor`` is the grid it runs on: the measurement's size, or the padded PSF grid
    it is embedded in (``plan --out`` then records the real size as ``measurement_window``).
    Both are compared with this measurement's (its field, chosen for the real sensor, means
    another scene on another one); the message names the real sizes of both. A plan whose
    ``sensor`` is not two integers is left to :meth:`recon.plan.Plan.from_json`.
    """
    if not isinstance(saved, dict):
        return
    sensor = saved.get("sensor")
    if not (isinstance(sensor, list) and len(sensor) == 2 and all(
            isinstance(n, int) and not isinstance(n, bool) for n in sensor)):
        return
    grid = tuple(int(n) for n in inputs["sensor"])
    window = _window(inputs)
    plan_window = saved.get("measurement_window")
    plan_window = (tuple(plan_window) if isinstance(plan_window, list) and len(plan_window) == 2
                   else None)
    # `plan --out` records the window of a padded grid (and its inputs); a plan without
    # either (Plan.to_json from Python, or an older plan) is checked on its grid alone: it
    # cannot say which sensor inside the grid it was made for
    says_window = "measurement_window" in saved or "inputs" in saved
    if tuple(sensor) == grid and (plan_window == window or not says_window):
        return

    def size(grid_hw: Any, window: Any) -> str:
        g = f"{grid_hw[0]}x{grid_hw[1]}"
        if isinstance(window, list | tuple) and len(window) == 2:
            return f"{window[0]}x{window[1]} measurement (on a {g} padded PSF grid)"
        return f"{g} measurement"

    raise ValueError(f"plan file {name} is for a {size(sensor, plan_window)}; this is a "
                     f"{size(grid, window)}: the plan does not fit it; "
                     "make a plan for this measurement (lenslesscam plan ... --out)")


def _window(inputs: dict[str, Any]) -> tuple[int, int] | None:
    """The real sensor's size on the plan's grid when the PSF is on a padded grid, else None."""
    prob = inputs["problem"]
    if prob.metadata.get("psf_grid") != "padded":
        return None
    return (int(prob.sensor[0]), int(prob.sensor[1]))


def warn_small_budget(plan: Any) -> None:
    """One line on stderr when a FISTA-TV plan's budget affords too few iterations to be useful.

    Fewer than ``recon.plan.cost.MIN_ITERS`` iterations under a budget (the planner already
    went to its coarsest grid): the line names the budget a useful result needs at the
    plan's measured cost per iteration.
    """
    from recon.plan.cost import MIN_ITERS
    from recon.plan.planner import budget_room, min_useful_budget_s

    if (plan.method != "fista-tv" or plan.budget_s is None or plan.iterations >= MIN_ITERS
            or not plan.seconds_per_iter):
        return
    if plan.budget_s >= min_useful_budget_s(plan.seconds_per_iter):
        # the budget affords more: the count came from elsewhere (a trade's measured best,
        # --set iterations=N), and "give --budget X" named an X below the budget given
        return
    n = plan.iterations
    setup = budget_room(plan.budget_s, plan.seconds_per_iter) <= 0  # as the plan's reason
    verdict = ("too few to reconstruct anything useful (the budget does not even cover the "
               "set-up)" if setup else "too few to converge")
    print(f"lenslesscam recon auto: warning: under the budget of {plan.budget_s:g} s the plan "
          f"runs {n} iteration{'s' if n != 1 else ''} of FISTA-TV (on the {plan.downsample}x "
          f"downsampled grid), {verdict}; give --budget "
          f"{min_useful_budget_s(plan.seconds_per_iter):.2g}s or more ({MIN_ITERS} iterations "
          "and their set-up at this grid)", file=sys.stderr)


def warn_udn_budget_spent(plan: Any, res: Any) -> None:
    """One line on stderr when a UDN plan stopped at its budget before a tenth of its iterations.

    A 1 s budget, most of it the network's set-up, ran 1 of 500 iterations, and the result
    was saved as if nothing happened.
    """
    if (plan.method != "udn" or res.stop_reason != "time_limit" or plan.iterations < 1
            or res.iterations * 10 >= plan.iterations):
        return
    print(f"lenslesscam recon auto: warning: the UDN ran only {res.iterations} of the plan's "
          f"{plan.iterations} iterations within the {plan.budget_s:g} s budget (the network's "
          "set-up counts towards it): far from a reconstruction; give a larger --budget",
          file=sys.stderr)


def check_auto_result(res: Any, dtype: Any) -> None:
    """The result check of every reconstruction command (:func:`app.commands.recon.check_explains`).

    On a FISTA-TV plan's result, with the model and measurement the run solved
    (``res.prepared``) and the plan's tau. A UDN plan's result is not checked here (its run
    can be hours long: it is never refused).
    """
    import torch

    from app.commands.recon import check_explains
    from recon.plan.planner import plan_tv

    plan, prep = res.plan, res.prepared
    if plan.method != "fista-tv" or prep is None:
        return
    tau, tv = plan_tv(plan, plan.tau / plan.downsample)
    b = torch.as_tensor(prep.b, dtype=dtype)
    x = torch.as_tensor(res.x, dtype=dtype)
    budget = "" if plan.budget_s is None else f"a larger --budget (than {plan.budget_s:g} s), "
    check_explains(
        x, prep.model, b, method="recon auto (fista-tv)", iterations=res.iterations,
        reason=res.stop_reason, tau=tau, tv=tv, who="lenslesscam recon",
        refuse_hint="an extreme plan setting (--set tau=..., --set iterations=...) can hold "
        "the solver at 0",
        flat_hint=f"it needs {budget}more iterations (--set iterations=N), or a plan setting "
        "(--set tau=...) holds the solver back",
        objective_hint=f"it needs {budget}more iterations (--set iterations=N)")


def run_auto(args: argparse.Namespace) -> int:
    """Plan (or load a plan), run it and save the reconstruction with the plan in its metadata."""
    import torch

    from recon.io import reconstruction_paths, save_reconstruction
    from recon.plan import Plan, execute

    check_command_outputs(args, reconstruction_paths(args.out, "image"))
    check_trade_option(args)
    inputs = load_inputs(args)
    if args.plan:
        # the plan fixed what these choose: taking them silently would run another plan
        given = [opt for opt, on in (("--tau", args.tau is not None),
                                     ("--budget", args.budget is not None),
                                     ("--trade", args.trade is not None),
                                     ("--field", args.field != "sensor"),
                                     ("--seed", args.seed != 0)) if on]
        if given:
            raise ValueError(f"{', '.join(given)} cannot change a saved plan (--plan fixed "
                             "them); use --set KEY=VALUE (for example --set tau=1e-3), or "
                             "plan again")
        path = Path(args.plan)
        if not path.is_file():
            raise FileNotFoundError(f"plan file not found: {args.plan}")
        try:
            saved = json.loads(path.read_text(encoding="utf-8"))
            # which measurement it is for, before its own checks (they know only its numbers)
            check_plan_matches(saved, inputs, args.plan)
            plan = Plan.from_json(saved)
            plan_data = plan_data_check(saved, args)
        except (ValueError, RecursionError) as exc:  # bad JSON, not UTF-8, a bad field
            msg = str(exc)
            raise ValueError(msg if msg.startswith(f"plan file {args.plan}") else
                             f"plan file {args.plan}: {msg}") from None
        overrides = parse_overrides(args.set)
        if overrides:
            plan = plan.override(**overrides)
        check_field_reach(list(plan.field), inputs)  # the saved plan's, or the one set
        warn_region(plan, args)
    else:
        plan = _make(args, inputs)
        plan_data = None
    kind = {"2d": "image", "video": "video", "depth": "depth"}[plan.model]
    check_command_outputs(args, reconstruction_paths(args.out, kind))  # the plan's previews
    if not args.quiet:
        print(plan.describe(_window(inputs)), file=sys.stderr)
    warn_small_budget(plan)
    bar = ProgressBar(max(plan.iterations, 1), f"recon auto ({plan.model}, K={plan.k})")

    def on_step(step: Any) -> None:
        bar.update(int(step.iteration))

    res = execute(plan, inputs["psf"], inputs["meas"], shutter=inputs["shutter"],
                  timing=inputs["timing"], psf_stack=inputs["stack"], mask=inputs["mask"],
                  dtype=torch.float64 if args.float64 else torch.float32, callback=on_step)
    bar.close()
    warn_udn_budget_spent(plan, res)
    check_auto_result(res, torch.float64 if args.float64 else torch.float32)
    meta = res.metadata()
    meta["inputs"] = {"psf": args.psf or args.psf_stack, "meas": args.meas,
                      "shutter": args.shutter, "timing": args.timing, "mask": args.mask}
    meta["input_hashes"] = {k: v for k, v in inputs["problem"].hashes.items() if v is not None}
    meta["preprocessing"] = inputs["problem"].metadata
    if plan_data is not None:  # which data the saved plan was made on, and whether it is this
        meta["plan_inputs"] = plan_data
    paths = save_reconstruction(args.out, res.x, meta, kind=kind)
    summary = {"out": [str(p) for p in paths], "model": plan.model, "k": plan.k,
               "region": list(plan.region), "downsample": plan.downsample,
               "iterations": res.iterations, "stop_reason": res.stop_reason,
               "wall_time_s": round(res.wall_s, 3), "plan_s": round(plan.plan_s, 3),
               # the automatic tau's search in this command (None: none ran; a saved plan's
               # was paid when it was made); plan_s is the analysis alone
               "tau_search_s": None if args.plan else tau_search_seconds(plan)}
    print(json.dumps(summary))
    return 0
