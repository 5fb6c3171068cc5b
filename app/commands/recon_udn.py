"""``lenslesscam recon udn``: the one-shot form of a UDN job.

Builds a job spec from the command line, writes it as ``RUN_DIR/job.toml`` and runs it exactly
as ``lenslesscam jobs run`` would (same run folder, checkpoints, record; resumable with
``lenslesscam jobs resume RUN_DIR``). ``--write-spec FILE`` writes the spec and stops, to start
an overnight job later; it names data under FILE's folder relative to it (the folder can be
moved, copied or shared) and other data as given, made absolute (:func:`spec_file_path`).
``--out`` may not lie inside another run's folder.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path
from typing import Any

from app.commands._options import (
    FRACTION,
    NONNEG,
    NONNEG_INT,
    POSITIVE,
    POSITIVE_INT,
    add_overwrite_option,
    check_command_outputs,
    check_output_folders,
    integer,
    refuse_run_folder_outputs,
)
from recon.udn import COMPILE_MODES, MAX_SCALES


def register_udn(methods: Any) -> None:
    """Add the ``udn`` method to ``recon``'s subparsers."""
    from app.commands.recon import add_input_arguments

    u = methods.add_parser("udn", help="untrained deep network (deep image prior) as a job")
    add_input_arguments(u, float64=False)  # the network runs in float32 or bf16 (--precision)
    g = u.add_argument_group("network")
    g.add_argument("--variant", choices=["auto", "2d", "frames", "3d"], default="auto",
                   help="2d, frames (K as channels), 3d, auto (2d for K=1 else frames)")
    g.add_argument("--scales", type=integer(1, MAX_SCALES), default=5,
                   help=f"levels (default 5, at most {MAX_SCALES})")
    g.add_argument("--net-channels", type=POSITIVE_INT, default=32, help="channels (default 32)")
    g.add_argument("--skip-channels", type=NONNEG_INT, default=4, help="skip channels (default 4)")
    g.add_argument("--input-channels", type=POSITIVE_INT, default=32, help="channels of z (32)")
    g.add_argument("--grad-checkpoint", action="store_true", help="gradient checkpointing")
    o = u.add_argument_group("optimiser and stopping")
    o.add_argument("--iters", type=POSITIVE_INT, default=3000,
                   help="iteration limit (default 3000)")
    o.add_argument("--time-limit", type=POSITIVE, help="wall-time limit in seconds")
    o.add_argument("--lr", type=POSITIVE, default=0.01, help="Adam learning rate (0.01)")
    o.add_argument("--reg-noise", type=NONNEG, default=0.05, help="input noise std (0.05)")
    o.add_argument("--loss", choices=["mse", "scale_invariant"], default="mse",
                   help="data term: mse, or scale_invariant (fits a gain first)")
    o.add_argument("--tv-weight", type=NONNEG, default=0.0, help="TV weight (0)")
    o.add_argument("--ema", type=FRACTION, default=0.9, help="output EMA decay (0.9)")
    o.add_argument("--holdout", type=FRACTION, default=0.05,
                   help="held-out fraction of measured pixels for early stopping (0.05)")
    o.add_argument("--patience", type=POSITIVE_INT, default=500,
                   help="early-stopping patience (500)")
    o.add_argument("--seed", type=NONNEG_INT, default=0,
                   help="seed of the network input and weights (0)")
    o.add_argument("--truth", help="ground-truth scene (C,K,H,W) to score the result")
    d = u.add_argument_group("device and output")
    d.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:N, mps")
    d.add_argument("--precision", choices=["float32", "bf16"], default="float32",
                   help="network precision: float32 or bf16 (autocast)")
    d.add_argument("--compile", nargs="?", const="default", default=None, metavar="MODE",
                   choices=COMPILE_MODES,
                   help="torch.compile the network, in torch.compile's MODE (default; "
                   "reduce-overhead records CUDA graphs: on an H200 half the full-resolution "
                   "iteration time after a compile of about a minute)")
    d.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None,
                   help="channels-last memory format for the network (default on: 0.83-0.89x "
                   "the step time on this CPU, docs/udn.md)")
    d.add_argument("--threads", type=NONNEG_INT, default=0, help="torch CPU threads (0: default)")
    d.add_argument("--max-memory", help="refuse runs estimated above this (e.g. 2GB)")
    d.add_argument("--checkpoint-every", type=POSITIVE_INT, default=500,
                   help="iterations between checkpoints (500)")
    d.add_argument("--preview-every", type=NONNEG_INT, default=100,
                   help="iterations between preview images (100; 0: none)")
    d.add_argument("--average-every", type=NONNEG_INT, default=500,
                   help="iterations between the estimates averaged into mean.tif (500; 0: "
                   "none; 'jobs combine RUN --with-fista' uses it, docs/udn.md)")
    d.add_argument("--with-fista", action=argparse.BooleanOptionalAction, default=None,
                   help="at the end, also write with_fista.tif: the mean (or best) estimate "
                   "averaged half and half with FISTA-TV at recon fista's defaults, the best "
                   "measured recipe without ground truth (default on; docs/udn.md)")
    d.add_argument("--name", default="", help="a name for the run")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.add_argument("--write-spec", metavar="FILE",
                   help="only write the job spec (TOML) to FILE and exit (data under "
                   "FILE's folder is named relative to it)")
    u.add_argument("--out", help="run folder to create (required unless --write-spec)")
    add_overwrite_option(u)  # for --write-spec; a run folder that holds a run is always refused
    u.set_defaults(func=run_udn)


def build_spec(args: argparse.Namespace) -> dict[str, Any]:
    """The job spec (as a dict of TOML tables) that the command line describes.

    Its ``[data]`` table is the command line's :class:`recon.problem.ProblemSpec`.
    """
    from app.commands._inputs import problem_spec

    spec: dict[str, Any] = {
        "job": {"name": args.name},
        "data": problem_spec(args).to_data_section(),
        "network": {
            "variant": args.variant, "scales": args.scales, "channels": args.net_channels,
            "skip_channels": args.skip_channels, "input_channels": args.input_channels,
            "gradient_checkpointing": args.grad_checkpoint,
        },
        "optimizer": {"lr": args.lr, "reg_noise": args.reg_noise, "loss": args.loss,
                      "tv_weight": args.tv_weight, "ema": args.ema, "seed": args.seed},
        "stopping": {"max_iter": args.iters, "time_limit_s": args.time_limit,
                     "holdout": args.holdout, "patience": args.patience},
        "device": {"device": args.device, "precision": args.precision,
                   "compile": args.compile is not None,
                   "compile_mode": args.compile or "default",
                   "channels_last": args.channels_last,
                   "threads": args.threads or getattr(args, "global_threads", None),
                   "max_memory": args.max_memory},
        "output": {"checkpoint_every": args.checkpoint_every,
                   "preview_every": args.preview_every,
                   "average_every": getattr(args, "average_every", None),
                   "with_fista": getattr(args, "with_fista", None)},
    }
    # options not given are left out (the spec's defaults apply), for every caller: recon udn
    # and batch udn items alike
    return {sec: {k: v for k, v in keys.items() if v is not None} for sec, keys in spec.items()}


#: ``[data]`` keys that name files, and the option that gave each (the depth model's
#: ``data.psf`` is ``--psf-stack``)
_DATA_PATH_OPTIONS = {"psf": "psf", "measurement": "meas", "mask": "mask", "shutter": "shutter",
                      "filters": "filters", "truth": "truth", "dark": "dark",
                      "psf_dark": "psf_dark"}


def spec_file_path(value: str | os.PathLike[str], spec_file: str | os.PathLike[str]) -> str:
    """How a spec written to ``spec_file`` names the data file ``value`` (as the user gave it).

    Relative to the spec file's folder when the file lies under it (the folder of data and
    spec can then be moved, copied or shared; a spec's relative paths are read relative to
    it), as the path is or as both resolve through symbolic links; otherwise the path as
    given, made absolute against the current folder only (links and ``..`` kept). A relative
    path is written only when it leads to the very file, checked on the disk.
    """
    p = Path(value).expanduser()
    if not p.is_absolute():
        p = Path.cwd() / p
    folder = Path(spec_file).expanduser()
    folder = (folder if folder.is_absolute() else Path.cwd() / folder).parent
    if not folder.is_dir():
        return str(p)  # a folder still to be made holds no data
    tries = [(Path(os.path.normpath(p)), Path(os.path.normpath(folder)))]
    with contextlib.suppress(OSError, RuntimeError):
        tries.append((p.resolve(), folder.resolve()))
    for target, base in tries:
        try:
            rel = target.relative_to(base)
        except ValueError:
            continue
        with contextlib.suppress(OSError):
            if os.path.samefile(folder / rel, p):
                return rel.as_posix()
    return str(p)


def _portable_data_paths(spec: dict[str, Any], args: argparse.Namespace,
                         spec_file: str | os.PathLike[str]) -> dict[str, Any]:
    """``spec`` with its ``[data]`` files named as :func:`spec_file_path` writes them.

    :func:`build_spec` names them absolute and resolved through links (what a run folder's
    ``job.toml`` and the run record keep); a spec written for later names them as the user
    did, relative to the spec's folder where the data lies under it.
    """
    data = dict(spec["data"])
    for key, option in _DATA_PATH_OPTIONS.items():
        if key == "psf" and data.get("model") == "depth":
            option = "psf_stack"
        given = getattr(args, option, None)
        if not isinstance(data.get(key), str) or data[key] == "auto" or given is None:
            continue  # not a file (a dark level, 'auto'), or not given
        data[key] = spec_file_path(given, spec_file)
    return {**spec, "data": data}


def run_udn(args: argparse.Namespace) -> int:
    """Write the spec and run it as a job."""
    from app.commands.jobs import run_with_progress
    from recon.udn.jobs import run_job
    from recon.udn.spec import normalise_spec, spec_to_toml

    spec = build_spec(args)
    normalise_spec(spec, Path.cwd(), source="command line")  # fail early, before any file
    text = spec_to_toml(spec)  # written once, as RUN_DIR/job.toml (--write-spec: below)
    if args.write_spec:
        from recon.udn.jobs import refuse_outputs_in_run_folders

        # never into a run's folder (over its run.json, --overwrite or not: the run would be
        # unreadable)
        refuse_outputs_in_run_folders([args.write_spec], "--write-spec")
        check_command_outputs(args, [args.write_spec])
        if Path(args.write_spec).suffix.lower() != ".toml":  # (--overwrite replaced a .tif)
            raise ValueError(f"--write-spec {args.write_spec}: a job spec is saved as .toml")
        from recon.atomic import atomic_write_bytes

        # data under the spec's folder named relative to it (the folder can be moved or
        # shared), other files as given (absolute)
        text = spec_to_toml(_portable_data_paths(spec, args, args.write_spec))
        atomic_write_bytes(args.write_spec, text.encode("utf-8"))
        import shlex

        print(f"wrote {args.write_spec}; run it with: lenslesscam jobs run "
              f"{shlex.quote(str(args.write_spec))} --out RUN_DIR", file=sys.stdout)
        return 0
    if not args.out:
        raise ValueError("--out RUN_DIR is required (or --write-spec FILE)")
    # never a new run inside another run's folder (RUN itself: 'already holds a run')
    refuse_run_folder_outputs([args.out], "--out")
    out = Path(args.out)
    check_output_folders([out / "run.json"])  # a folder it cannot write: one line
    return run_with_progress(
        lambda progress, cancel: run_job(out / "job.toml", out, progress=progress,
                                         cancel=cancel, spec_text=text),
        args, args.iters, str(out))
