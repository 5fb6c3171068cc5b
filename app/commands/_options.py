"""Range-checked ``type=`` functions for every numeric command-line option.

One set, reused by every subcommand and benchmark: a bad value (``--bits 0``, ``--erasure 1.0``,
``--noise nan``) stops at the command line with the allowed range in a one-line message
(argparse prints ``argument --bits: must be an integer >= 1, got '0'``, exit code 2) instead of
producing NaN files or invalid JSON later. Floats are finite only (no nan, no inf).
``tests/test_cli_faults.py`` walks the whole parser and fails on any bare ``type=int`` or
``type=float``.
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable, Iterable

from recon.formats import INT_LIMIT

__all__ = [
    "BITS",
    "FINITE",
    "FRACTION",
    "NONNEG",
    "NONNEG_INT",
    "POSITIVE",
    "POSITIVE_INT",
    "UNIT",
    "add_overwrite_option",
    "check_command_outputs",
    "check_output_folders",
    "finite_float",
    "integer",
    "parse_hw",
    "refuse_run_folder_outputs",
]


def _bound(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    return " and ".join(parts)


def finite_float(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                 hi_open: bool = False) -> Callable[[str], float]:
    """A ``type=`` for a finite float in [lo, hi] (open ends with ``lo_open`` / ``hi_open``)."""
    bound = _bound(lo, hi, lo_open, hi_open)
    what = f"a finite number {bound}".rstrip()

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
        bad = not math.isfinite(value)
        bad = bad or (lo is not None and (value <= lo if lo_open else value < lo))
        bad = bad or (hi is not None and (value >= hi if hi_open else value > hi))
        if bad:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    parse.__name__ = f"float {bound}".strip()
    parse.range_text = what  # type: ignore[attr-defined]
    return parse




def integer(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """A ``type=`` for an integer in [lo, hi], never beyond +-2**62 (``INT_LIMIT``)."""
    bound = _bound(lo, hi, False, False)
    what = f"an integer {bound}".rstrip()

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        if abs(value) > INT_LIMIT:
            raise argparse.ArgumentTypeError(f"must be {what} and at most 2**62 in magnitude, "
                                             f"got {text!r}")
        return value

    parse.__name__ = f"int {bound}".strip()
    parse.range_text = what  # type: ignore[attr-defined]
    return parse


#: iterations, downsampling factors, frame counts, network sizes
POSITIVE_INT = integer(1)
#: seeds, patience, thread counts where 0 means "choose for me"
NONNEG_INT = integer(0)
#: quantisation bits of a simulated sensor
BITS = integer(1, 32)
#: any finite number (gain, motion)
FINITE = finite_float()
#: weights, noise levels, tolerances
NONNEG = finite_float(0)
#: learning rates, photon counts, durations, timeouts
POSITIVE = finite_float(0, lo_open=True)
#: fractions of pixels that may be removed (erasure, held-out): 1 would leave nothing
FRACTION = finite_float(0, 1, hi_open=True)
#: fractions in [0, 1] (EMA decay, intensity, target peak)
UNIT = finite_float(0, 1)


#: Namespace attributes that name input files of some command (checked against its outputs).
INPUT_OPTIONS = ("psf", "psf_stack", "meas", "mask", "shutter", "filters", "dark", "psf_dark",
                 "timing", "plan", "scene", "light_state", "cube", "like", "pixel_maps",
                 "sim_psf", "trade", "truth")


#: the largest side of a sensor or PSF shape given as HxW: the largest sCMOS sensors are about
#: 14000 pixels wide (more is a typo, and an allocation of many GiB)
MAX_SIDE = 16384


def parse_hw(value: str, what: str, least: tuple[int, int] = (1, 1)) -> tuple[int, int]:
    """A size ``HxW`` (also ``HXW``, ``H,W``): (rows, columns).

    The one parser of every command and benchmark that takes a size; ValueError in one line
    naming ``what`` otherwise.
    """
    m = re.fullmatch(r"\s*(\d+)\s*[xX,]\s*(\d+)\s*", value)
    if not m:
        raise ValueError(f"{what} must be HxW (for example 64x80), got {value!r}")
    h, w = int(m.group(1)), int(m.group(2))
    if h < least[0] or w < least[1]:
        raise ValueError(f"{what} must be at least {least[0]}x{least[1]} pixels (HxW), got "
                         f"{value!r}")
    if max(h, w) > MAX_SIDE:
        raise ValueError(f"{what} must be at most {MAX_SIDE} pixels a side, got {value!r}")
    return h, w


def add_overwrite_option(p: argparse.ArgumentParser) -> None:
    """``--overwrite``: the only way a command replaces an existing output file."""
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing output files (an input of the same command never)")


def check_command_outputs(args: argparse.Namespace, outputs: Iterable[str | os.PathLike[str]]
                          ) -> None:
    """Refuse outputs that lie in a run folder, are inputs, exist, or cannot be written.

    An output may not lie inside a UDN run folder (whatever ``--overwrite`` says), be an input
    of this command, exist without ``--overwrite``, or lie in a folder that cannot be created
    or written. One rule for every writer command (:func:`refuse_run_folder_outputs`,
    :func:`recon.atomic.check_outputs`, then :func:`check_output_folders`), called before any
    work is done.
    """
    from recon.atomic import check_outputs

    outputs = list(outputs)
    refuse_run_folder_outputs(outputs, "output")
    inputs = {f"--{name.replace('_', '-')}": value for name in INPUT_OPTIONS
              if isinstance(value := getattr(args, name, None), (str, os.PathLike))}
    check_outputs(outputs, inputs, overwrite=bool(getattr(args, "overwrite", False)))
    check_output_folders(outputs)


def check_output_folders(outputs: Iterable[str | os.PathLike[str]]) -> None:
    """Refuse, before any work, outputs whose folder cannot be created or written.

    The nearest existing folder above each output is probed by creating and deleting a
    temporary file in it (when it is the output's folder) or a temporary folder (when the
    output's folder is still to be made): a permission bit, a read-only file system, ``/proc``
    and root's exemptions are all answered by the system itself, which ``os.access`` is not
    (for root it says yes to ``/proc``). Raises :class:`PermissionError` (exit code 2 in
    ``app.cli``) with one line naming the output and the folder. Before this a read-only
    ``--out`` folder was found at the save, after the whole reconstruction.
    """
    import tempfile
    from pathlib import Path

    probed: set[Path] = set()
    for o in outputs:
        out = Path(os.path.abspath(o))
        folder = out.parent
        existing = folder
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        if existing in probed:
            continue
        if not existing.is_dir():
            raise PermissionError(f"cannot write {o}: {existing} is a file, not a folder")
        try:
            if existing == folder:
                fd, tmp = tempfile.mkstemp(prefix=".lenslesscam-write-test-", dir=existing)
                os.close(fd)
                os.unlink(tmp)
            else:
                os.rmdir(tempfile.mkdtemp(prefix=".lenslesscam-write-test-", dir=existing))
        except OSError as exc:
            why = exc.strerror or type(exc).__name__
            where = (f"the folder {existing} is not writable" if existing == folder else
                     f"the folder {folder} cannot be made in {existing}, which is not writable")
            raise PermissionError(f"cannot write {o}: {where} ({why}); choose another output "
                                  "location") from None
        probed.add(existing)


def refuse_run_folder_outputs(outputs: Iterable[str | os.PathLike[str]], option: str) -> None:
    """Refuse outputs inside a UDN run folder (:func:`recon.udn.jobs.is_run_folder`).

    A run's folder holds only the run's files (``jobs status/resume/combine`` read them). The
    check walks the outputs' folders for a ``run.json`` and imports the job module (and torch)
    only when one is there: among the folders above the output as given and above the path it
    leads to through symbolic links (``LINK/x`` with ``LINK`` to ``RUN/deep``: ``RUN`` is in
    neither the given path's folders nor ``LINK``'s own ``run.json``).
    """
    import contextlib
    from pathlib import Path

    def above(o: str | os.PathLike[str]) -> list[Path]:
        folders = list(Path(os.path.abspath(o)).parents)
        with contextlib.suppress(OSError, RuntimeError):
            folders += Path(o).resolve().parents
        return folders

    outs = list(outputs)
    near = any((parent / "run.json").is_file() for o in outs for parent in above(o))
    if near:
        from recon.udn.jobs import refuse_outputs_in_run_folders

        refuse_outputs_in_run_folders(outs, option)
