"""Average finished UDN runs of one problem with different seeds (an ensemble).

A deep-image-prior estimate carries seed-dependent detail where the measurement says nothing
(at 99 % erasures, almost everywhere); the seeds agree on what the data determine. Averaging the
estimates of a few seeds keeps the second and cancels much of the first: on the simulation
protocol at 99 % erasures the average of 4 seeds is 0.5-0.9 dB above the seeds' own mean
PSNR (docs/udn-vs-fista.md). Each run holds out its own pixels, so the members' held-out choices are
independent.

    lenslesscam jobs run job.toml --seed 0 --out runs/s0     (and 1, 2, 3; in parallel)
    lenslesscam jobs combine runs/s0 runs/s1 runs/s2 runs/s3 --out ensemble.tif

:func:`combine_runs` refuses runs of different inputs (PSF, measurement, mask, ... by file
hash; not the truth, which only scores a run and is never fitted), model or shape, runs that
share a seed, failed runs (their estimate is from before the failure: a diverged run's drags the
average down) and runs without a result. It never writes into a run folder.

``with_fista``: the average of the runs is averaged in turn, half and half, with FISTA-TV
with the automatic tau and iteration count (``recon fista``'s defaults) of the runs' own
problem, loaded again from their spec and checked against their input hashes. The network and
TV share most of their error, and what they do not share partly cancels: on the four real
DiffuserCam pairs at 1/4 resolution (docs/udn.md, "The ensemble averaged with FISTA-TV"),
one seed's held-out choice averaged with automatic-tau FISTA-TV scored +0.10 to +0.58 dB above
the seed alone at 0-99 % erasures, and the four-seed ensemble -0.06 to +0.24 dB against the
ensemble alone, with higher SSIM and MS-SSIM; the weight was fixed, not chosen with the
truth. On the simulation protocol at 99 % erasures (one seed of the defaults, three scenes)
+0.29 dB over the run and +0.27 over FISTA-TV alone (docs/udn.md). One run is enough for it.

    lenslesscam jobs combine runs/s0 --with-fista --out udn-fista.tif
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from recon.formats import FormatError
from recon.udn.state import JobState

__all__ = ["MIN_MEAN_COUNT", "EnsembleResult", "average_with_fista", "combine_runs",
           "fista_tv_member"]

F32 = npt.NDArray[np.float32]
Estimate = Literal["auto", "best", "final", "mean"]

#: record keys that must agree between the members
_SAME = ("scene_shape", "meas_shape")


@dataclass(frozen=True)
class EnsembleResult:
    """The averaged estimate and what it was made of."""

    x: F32
    members: list[dict[str, Any]]
    paths: list[Path]
    scores: dict[str, float | None] | None
    fista: dict[str, Any] | None = None  # the FISTA-TV member (with_fista): tau, iterations...
    estimate: str = "best"  # the members' estimate used (``auto`` resolved)
    note: str | None = None  # why ``auto`` did not take the runs' means


def _member(run_dir: Path, estimate: Estimate) -> tuple[dict[str, Any], F32, dict[str, Any]]:
    from recon.io import read_reconstruction
    from recon.udn.jobs import read_record

    rec = read_record(run_dir)
    status = rec.get("status")
    if status != JobState.FINISHED:  # running, or killed: its estimate is an earlier one
        from recon.udn.jobs import job_status

        if job_status(run_dir).state == JobState.INTERRUPTED:  # killed: nobody to wait for
            raise ValueError(f"{run_dir}: the run was interrupted (no process holds its "
                             f"folder): its {estimate} estimate is not its last; resume it "
                             f"('lenslesscam jobs resume {run_dir}') first")
        raise ValueError(f"{run_dir}: the run has not finished (status {status}): its "
                         f"{estimate} estimate is not its last; wait for it, or cancel it "
                         f"first ('lenslesscam jobs cancel {run_dir}')")
    results = rec.get("results") or {}
    if estimate not in results:
        state = rec.get("finish_reason") or rec.get("status") or "unknown"
        if estimate == "mean" and "best" in results:  # finished, but nothing was averaged
            raise ValueError(f"{run_dir}: the run wrote no mean estimate ({_why_no_mean(rec)}); "
                             "use --estimate best")
        raise ValueError(f"{run_dir}: the run has no {estimate} estimate yet ({state}); "
                         "let it finish or resume it")
    path = run_dir / results[estimate]
    x, meta = read_reconstruction(path)
    written = (results.get("data_hashes") or {}).get(estimate)
    if meta.get("method") != "udn" or (written is not None and meta.get("data_hash") != written):
        raise ValueError(f"{path} is not the {estimate} estimate this run wrote (replaced "
                         "since?); rerun or resume the run to write it again")
    return rec, x, meta


def _why_no_mean(rec: dict[str, Any]) -> str:
    """Why a finished run has no mean estimate, and what would give it one."""
    every = ((rec.get("spec") or {}).get("output") or {}).get("average_every")
    its = (rec.get("progress") or {}).get("iteration", "?")
    if every is None:
        return "a run from before the iterate average"
    if every == 0:
        return "averaging was off: average_every 0"
    if not isinstance(its, int) or its >= every:
        return "its record names none"
    return (f"it ran {its} iterations, fewer than its average_every {every}: 'lenslesscam jobs "
            f"resume RUN --max-iter {every}' or more would average")


def _mean_problem(run_dir: Path) -> str | None:
    """Why the run's mean estimate cannot be used (None: it can).

    An unreadable record is left to :func:`_member` to name (None here).
    """
    from recon.udn.jobs import read_record

    try:
        rec = read_record(run_dir)
    except (OSError, ValueError):
        return None
    results = rec.get("results") or {}
    if "mean" not in results:
        return _why_no_mean(rec)
    if not (run_dir / str(results["mean"])).is_file():
        return f"its {results['mean']} is missing"
    count = results.get("mean_count")
    if isinstance(count, int) and count < MIN_MEAN_COUNT:  # one early iterate, no average
        return (f"its mean is the one estimate of iteration "
                f"{results.get('mean_last_iteration', '?')}, not an average")
    return None


#: inputs a run records that its fit never uses (the truth only scores it)
_SCORING_ONLY = frozenset({"truth"})


def _inputs_key(rec: dict[str, Any]) -> dict[str, Any]:
    """The inputs the fit uses, by content: file hashes and the hashes of the arrays as processed.

    The array hashes come after dark subtraction, downsampling and normalisation, so runs of
    the same files read with other settings differ. The truth is left out: a run with
    ``--truth`` and one without fit the same problem.
    """
    out: dict[str, Any] = {}
    for name, info in (rec.get("inputs") or {}).items():
        if name not in _SCORING_ONLY:
            out[name] = (info.get("file_hash"), info.get("array_hash"))
    return out


def _differ(key: dict[str, Any], key0: dict[str, Any]) -> list[str]:
    """The inputs two runs differ in.

    A dark file one record names and the other does not (a run recorded before dark files
    were hashed) is not a difference.
    """
    from recon.problem import DARK_INPUTS

    return sorted(n for n in set(key) | set(key0) if key.get(n) != key0.get(n)
                  and not (n in DARK_INPUTS and (n not in key or n not in key0)))


def _refuse_failed(dirs: Sequence[Path]) -> None:
    """Refuse, in one line naming them, the members whose record says they failed.

    A record that cannot be read is left to :func:`_member`, which names it.
    """
    from recon.udn.jobs import read_record
    from recon.udn.state import FinishReason

    failed: list[str] = []
    for d in dirs:
        try:
            rec = read_record(d)
        except (OSError, ValueError):
            continue
        if rec.get("finish_reason") == FinishReason.FAILED:
            why = str(rec.get("detail") or "no detail").split(";")[0]
            if len(why) > 160:
                why = why[:160].rsplit(" ", 1)[0] + " ..."
            failed.append(f"{d} ({why})")
    if failed:
        raise ValueError(f"refusing {len(failed)} failed run(s): {'; '.join(failed)}: a failed "
                         "run's estimate is from before its failure and would pull the average "
                         "down; leave it out, or resume it ('lenslesscam jobs resume') first")


#: the FISTA-TV member's share of the average (``with_fista``): fixed, not tuned
FISTA_WEIGHT = 0.5
#: the fewest estimates a run's mean must hold to stand for the run in the averaged recipe
#: (one is a single early iterate): ``jobs combine``'s ``auto`` and a job's with_fista.tif
MIN_MEAN_COUNT = 2


def average_with_fista(x: Any, xf: Any) -> npt.NDArray[np.float64]:
    """The averaged recipe: ``x`` (the runs' average) and FISTA-TV's ``xf``, by FISTA_WEIGHT."""
    return np.asarray((1.0 - FISTA_WEIGHT) * np.asarray(x, dtype=np.float64)
                      + FISTA_WEIGHT * np.asarray(xf, dtype=np.float64).reshape(np.shape(x)))


def combine_runs(run_dirs: Sequence[str | Path], out: str | Path, *,
                 estimate: Estimate = "auto", with_fista: bool = False) -> EnsembleResult:
    """Average the ``estimate`` of finished runs.

    ``estimate``: ``best`` (the held-out choice), ``final``, ``mean`` (the run's iterate
    average, ``mean.tif``) or ``auto``: ``mean`` with ``with_fista`` where every run wrote one
    of at least two estimates (the measured recipe: docs/udn.md, "Iterate averaging"), else
    ``best`` (with a note saying why). The metadata's ``estimate`` names the one used.

    Writes ``out`` (a reconstruction TIFF with previews, :func:`recon.io.save_reconstruction`)
    with the members (run folder, seed, iteration) in its metadata; scores against the truth
    when the runs name one (``data.truth``). ``with_fista``: that average, half and half with
    FISTA-TV of the runs' problem (the module docstring; one run is then enough).

    Raises:
        ValueError: fewer than two runs (one with ``with_fista``), runs of different
            problems, a shared seed, a run without that estimate, inputs changed since the
            runs (``with_fista``).
        FileNotFoundError, FormatError: a folder without a readable run record or result.

    """
    if estimate not in ("auto", "best", "final", "mean"):
        raise ValueError(f"estimate must be 'auto', 'best', 'final' or 'mean', got {estimate!r}")
    dirs = [Path(d) for d in run_dirs]
    if not dirs:
        raise ValueError("no run to combine")
    if len(dirs) < 2 and not with_fista:
        raise ValueError("an ensemble needs at least two runs (or one run with the FISTA-TV "
                         "member, --with-fista)")
    if len({d.resolve() for d in dirs}) < len(dirs):
        raise ValueError("the same run folder is named twice")
    _refuse_failed(dirs)
    note = None
    if estimate == "auto":
        estimate = "best"
        if with_fista:
            problems = {d: _mean_problem(d) for d in dirs}
            missing = [f"{d} ({p})" for d, p in problems.items() if p is not None]
            estimate = "best" if missing else "mean"
            if missing:  # all or none: one kind of estimate per ensemble
                note = (f"the best estimates are averaged, not the iterate means, since "
                        f"{len(missing)} of {len(dirs)} run(s) have none: {'; '.join(missing)}")
    loaded = [_member(d, estimate) for d in dirs]
    target = Path(out).resolve()
    for d in dirs:  # a member's files are inputs of the ensemble: never written
        if d.resolve() in target.parents:
            raise ValueError(f"refusing to write {out} into the run folder {d}: its files are "
                             "inputs of the ensemble; write it elsewhere")
    from recon.atomic import check_outputs
    from recon.io import reconstruction_paths
    from recon.udn.jobs import refuse_outputs_in_run_folders

    # nor into any other run's folder: its files are what status, resume and cancel read
    refuse_outputs_in_run_folders(reconstruction_paths(out, "image"), "the ensemble")

    # nor are the members' own inputs (their PSF, measurement, ...): a run must stay resumable
    inputs = {f"data.{name} of {d}": info.get("path") for d, (rec, _, _) in zip(
        dirs, loaded, strict=True) for name, info in (rec.get("inputs") or {}).items()
        if isinstance(info, dict) and isinstance(info.get("path"), str)}
    check_outputs(reconstruction_paths(out, "image"), inputs, overwrite=True)
    rec0, x0, meta0 = loaded[0]
    key0 = _inputs_key(rec0)
    seeds: dict[int, Path] = {}
    members: list[dict[str, Any]] = []
    for d, (rec, xm, meta) in zip(dirs, loaded, strict=True):
        key = _inputs_key(rec)
        diff = _differ(key, key0)
        if diff:
            same_files = all((key.get(n) or (None,))[0] == (key0.get(n) or (None,))[0]
                             for n in diff)
            how = (" as read: the same files with other settings (downsample, dark, colour, "
                   "field ...)" if same_files else "")
            raise ValueError(f"{d} is a run of other data than {dirs[0]} (differs in: "
                             f"{', '.join('data.' + n for n in diff)}{how})")
        if meta.get("model") != meta0.get("model"):
            raise ValueError(f"{d} uses the {meta.get('model')} model, {dirs[0]} the "
                             f"{meta0.get('model')} model")
        for k in _SAME:
            if rec.get(k) != rec0.get(k):
                raise ValueError(f"{d}: {k} {rec.get(k)} differs from {dirs[0]}'s {rec0.get(k)}")
        if xm.shape != x0.shape:
            raise ValueError(f"{d}: estimate of shape {xm.shape}, {dirs[0]}'s is {x0.shape}")
        seed = int(rec["spec"]["optimizer"]["seed"])
        if seed in seeds:
            raise ValueError(f"{d} and {seeds[seed]} both ran with seed {seed}: the same "
                             "run twice adds nothing (use 'jobs run --seed N')")
        seeds[seed] = d
        members.append({"run_dir": str(d.resolve()), "seed": seed,
                        "iteration": meta.get("best_iteration" if estimate == "best"
                                              else "iterations"),
                        **({"mean_count": meta.get("mean_count"),
                            "average_every": meta.get("average_every"),
                            "mean_last_iteration": meta.get("mean_last_iteration")}
                           if estimate == "mean" else {}),
                        "finish_reason": rec.get("finish_reason"),
                        "data_hash": meta.get("data_hash")})
    mean = np.mean([m[1] for m in loaded], axis=0, dtype=np.float64)
    fista = None
    if with_fista:
        xf, fista = _fista_member(rec0, dirs[0], mean.shape)
        mean = average_with_fista(mean, xf)
    x: F32 = np.asarray(mean, dtype=np.float32)
    scores = None
    # the truth of the first member that names one (the truth is not part of the problem:
    # some members may have run without it)
    truths: dict[Any, list[str]] = {}
    for rec, _, _ in loaded:
        t = (rec.get("inputs") or {}).get("truth")
        if isinstance(t, dict) and rec["spec"]["data"].get("truth"):
            truths.setdefault(t.get("array_hash") or t.get("file_hash"), []).append(
                str(rec["spec"]["data"]["truth"]))
    if len(truths) > 1:  # scored against one of them silently, before
        raise ValueError("the runs name different truths ("
                         + "; ".join(sorted({p for ps in truths.values() for p in ps}))
                         + "): the ensemble would be scored against one of them; combine runs "
                         "of one truth, or runs without one")
    scorer = next((rec for rec, _, _ in loaded if rec["spec"]["data"].get("truth")), None)
    if scorer is not None:
        from recon.metrics import metrics_report
        from recon.problem import ProblemSpec, load_truth

        try:  # the truth on the runs' grid, prepared as the runs prepared it
            truth: Any = load_truth(ProblemSpec.from_data_section(scorer["spec"]["data"]),
                                    x.shape)
        except (OSError, FormatError, ValueError):
            truth = None  # the truth moved or changed: the ensemble is still written
        if truth is not None and truth.size == x.size:
            rep = metrics_report(truth.reshape(x.shape), x, gain_fit=True)
            # None where a score is undefined (SSIM of a tiny image, the gain of a zero one)
            scores = {k: None if v is None else float(v) for k, v in rep.items()
                      if k in ("psnr", "ssim", "gain", "mse")}
    from recon.io import save_reconstruction

    metadata = {
        "method": "udn-ensemble+fista-tv" if with_fista else "udn-ensemble",
        "model": meta0.get("model"), "estimate": estimate,
        **({"estimate_note": note} if note is not None else {}),
        "members": members, "inputs": rec0.get("inputs"), "scores": scores,
        **({"fista": fista} if fista is not None else {}),
        # the truth the scores are against (the first member's inputs may lack it)
        "scored_against": None if scorer is None or scores is None
        else (scorer.get("inputs") or {}).get("truth"),
    }
    if meta0.get("preprocessing") is not None:  # how the members read their inputs
        metadata["preprocessing"] = meta0["preprocessing"]
    paths = save_reconstruction(out, x, metadata, kind=meta0.get("kind", "image"))
    return EnsembleResult(x, members, paths, scores, fista, estimate, note)


def _fista_member(rec0: dict[str, Any], run0: Path,
                  shape: tuple[int, ...]) -> tuple[Any, dict[str, Any]]:
    """FISTA-TV of the first run's problem with ``recon fista``'s defaults: (x, metadata).

    The problem is read again from the run's spec (:func:`recon.problem.load_problem`, the one
    loader) and must be the data the run fitted (file and array hashes; refused otherwise).
    """
    from recon.problem import ProblemSpec, load_problem

    try:
        prob = load_problem(ProblemSpec.from_data_section(rec0["spec"]["data"]))
    except (OSError, FormatError, ValueError) as exc:
        raise ValueError(f"{run0}: cannot read the run's inputs again for the FISTA-TV "
                         f"member: {exc}") from exc
    diff = _differ(_inputs_key({"inputs": prob.inputs}), _inputs_key(rec0))
    if diff:
        raise ValueError(f"{run0}: {', '.join('data.' + n for n in diff)} changed since the run "
                         "(its hash differs from the run record's): the FISTA-TV member would "
                         "reconstruct other data; combine without --with-fista")
    out = fista_tv_member(prob.model, prob.meas)
    assert out is not None  # no cancel given
    xf, meta = out
    if xf.size != int(np.prod(shape)):
        raise ValueError(f"{run0}: FISTA-TV gave an estimate of shape {xf.shape}, the runs' is "
                         f"{tuple(shape)}")
    return xf.reshape(shape), meta


def fista_tv_member(model: Any, meas: Any, cancel: Any = None
                    ) -> tuple[npt.NDArray[np.float64], dict[str, Any]] | None:
    """FISTA-TV with ``recon fista``'s defaults (automatic tau and iterations): (x, metadata).

    The FISTA-TV half of the averaged recipe, for ``jobs combine --with-fista`` and a job's
    own ``with_fista.tif``. ``cancel()`` is asked between iterations (None back when it says
    stop).
    """
    import time

    import torch

    from recon.autotau import resolve
    from recon.fista import Fista
    from recon.tv import TV

    b = torch.as_tensor(meas, dtype=torch.float32, device=model.op.device)
    # recon fista's defaults: Fista's own (tol, restart, prox iterations, preconditioner), and
    # TV with weight 0.5 along k (its --tv-k) where there is a k axis
    tv = TV(weight_k=0.5 if model.k > 1 else 0.0)
    t0 = time.perf_counter()
    tau, iters, tau_meta = resolve(model, b, None, None, tv=tv)
    solver = Fista(model.op, b, tau=tau, tv=tv, max_iter=iters)
    for _ in solver.steps():
        if cancel is not None and cancel():
            return None
    xf = solver.x.detach().double().cpu().numpy()
    return xf, {
        "weight": FISTA_WEIGHT, "tau": tau, "iterations": solver.iteration,
        "tau_rule": tau_meta.get("tau_rule"), "iterations_rule": tau_meta.get("iterations_rule"),
        "wall_time_s": round(time.perf_counter() - t0, 3), "settings": "recon fista's defaults",
        "parameters": solver.params}
