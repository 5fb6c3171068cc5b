"""``lenslesscam trade``: measure the speed/accuracy trade for a case (tables + Pareto plot)."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path
from typing import Any

from app.commands._options import (
    NONNEG_INT,
    POSITIVE_INT,
    add_overwrite_option,
    check_command_outputs,
)

PROTOCOL_SCENES = ("im408", "im740", "im65")
PROTOCOL_ERASURES = (0.9, 0.99)


#: What ``trade`` writes into ``--out``.
TRADE_FILES = ("trade.csv", "trade.md", "trade_pareto.png", "inputs.json")
#: The lock a trade holds on ``--out`` while it writes (left in place, as every RunLock's file).
LOCK_FILE = "trade.lock"


def register(sub: Any) -> None:
    """Add ``trade``."""
    p = sub.add_parser("trade", help="measure the speed/accuracy trade (methods x budgets)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--protocol", action="store_true",
                     help="the three shared scenes at 90%% and 99%% erasures (noise 0.01) and "
                          "the real DiffuserCam-Tutorial hand")
    src.add_argument("--sample", choices=["tutorial"], help="a bundled real measurement")
    src.add_argument("--meas", help="measurement file (with --psf)")
    p.add_argument("--psf", help="PSF file")
    p.add_argument("--mask", help="erasure mask (1 = measured)")
    p.add_argument("--truth", help="ground truth (C,1,H,W) or (H,W), if known")
    from app.commands._inputs import add_dark_arguments, add_layout_arguments

    add_dark_arguments(p)  # as plan and recon: the loader's refusals name --psf-dark

    add_layout_arguments(p)
    p.add_argument("--downsample", type=POSITIVE_INT, default=1,
                   help="box downsampling factor (default 1)")
    p.add_argument("--rgb", action="store_true", help="colour measurement and PSF")
    p.add_argument("--field", default="sensor", help="scene field: sensor, full (2x) or HxW")
    p.add_argument("--quick", action="store_true", help="a small grid")
    p.add_argument("--no-udn", action="store_true", help="leave the UDN out of the grid")
    p.add_argument("--budgets", default="0.5,2,10,60",
                   help="time budgets in seconds, comma-separated (default 0.5,2,10,60)")
    p.add_argument("--threads", type=NONNEG_INT, default=None,
                   help="torch threads (default: lenslesscam --threads N if given, else chosen "
                        "from cores and load, recon.threads; 0: choose)")
    p.add_argument("--out", required=True,
                   help="output folder (CSV, Markdown, PNG; not a UDN run folder)")
    add_overwrite_option(p)
    p.set_defaults(func=run)


def _budgets(text: str) -> list[float]:
    """``--budgets``: comma-separated seconds, each finite and > 0."""
    import math

    out = []
    for part in text.split(","):
        try:
            b = float(part)
        except ValueError:
            raise ValueError(f"--budgets must be seconds separated by commas, got {part!r}") \
                from None
        if not (math.isfinite(b) and b > 0):
            raise ValueError(f"--budgets must be finite and > 0, got {part!r}")
        out.append(b)
    return out


def _cases(args: argparse.Namespace) -> list[Any]:

    from recon import samples
    from recon.models import build_model
    from recon.simulate import simulate
    from recon.trade import Case

    if args.protocol:
        psf = samples.tutorial_psf()
        psf_src = _sample_files(psf="tutorial_psf")
        cases = []
        for er in PROTOCOL_ERASURES:
            for name in PROTOCOL_SCENES:
                sim = simulate(build_model("2d", psf), samples.lensed_scene(name), erasure=er,
                               noise=0.01, seed=0)
                cases.append(Case(f"{name} {er:.0%}", psf, sim.meas, sim.mask, sim.truth,
                                  source={**psf_src, "scene": f"sample {name}", "erasure": er,
                                          "noise": 0.01, "seed": 0}))
        cases.append(_tutorial_case())
        return cases
    if args.sample == "tutorial":
        return [_tutorial_case()]
    from app.commands._inputs import problem_spec
    from recon.problem import load_problem

    if not args.psf:
        raise ValueError("--meas needs --psf")
    prob = load_problem(problem_spec(args, model="2d"))
    psf, meas, mask, truth = prob.psf_per_channel(), prob.meas, prob.mask, prob.truth
    field = tuple(int(n) for n in prob.model.info["field"])
    source: dict[str, Any] = {}
    for key, path in (("psf", args.psf), ("meas", args.meas), ("mask", args.mask),
                      ("truth", args.truth)):
        if path:
            source[key] = str(path)
            source[f"{key}_file_hash"] = prob.hashes.get(key)
    source.update({k: prob.metadata.get(k) for k in ("downsample", "dark", "psf_dark", "color",
                                                     "channel_order", "flip_rows", "psf_grid")})
    return [Case(Path(args.meas).stem, psf, meas, mask, truth, field,  # type: ignore[arg-type]
                 source=source)]


def _sample_files(**files: str) -> dict[str, str]:
    """A case's ``source`` for bundled sample files: ``KEY: sample NAME``, ``KEY_file_hash``."""
    from recon import samples
    from recon.formats import file_hash

    out = {}
    for key, name in files.items():
        out[key] = f"sample {name}"
        out[f"{key}_file_hash"] = file_hash(samples.sample_path(name))
    return out


def _tutorial_case() -> Any:
    """The real DiffuserCam-Tutorial hand (no truth), with where it comes from."""
    from recon import samples
    from recon.trade import Case

    return Case("tutorial hand (real)", samples.tutorial_psf(), samples.tutorial_measurement(),
                source=_sample_files(psf="tutorial_psf", meas="tutorial_measurement"))


def run(args: argparse.Namespace) -> int:
    """Run the grid on each case; write trade.csv, trade.md and trade_pareto.png."""
    from recon.threads import apply_threads
    from recon.trade import default_grid, run_trade
    from recon.udn.jobs import refuse_outputs_in_run_folders
    from recon.udn.rundir import RunFolderBusy, RunLock

    outputs = [Path(args.out) / n for n in TRADE_FILES]
    refuse_outputs_in_run_folders(outputs, "--out", args.out)  # never beside a run's files
    check_command_outputs(args, outputs)
    requested = _requested_threads(args)
    threads = apply_threads(requested)
    budgets = _budgets(args.budgets)
    grid = default_grid(quick=args.quick, with_udn=not args.no_udn)
    out = Path(args.out)
    t_all = time.perf_counter()
    rows = []
    cases = _cases(args)
    made = not out.exists()
    journal: _Journal | None = None
    try:
        # one trade writes a folder at a time; its own lock file, so that a UDN job's or a
        # batch's run.lock is never taken for a trade's (the file stays, as every RunLock's)
        lock = RunLock(out, name=LOCK_FILE).acquire()
    except RunFolderBusy as exc:
        who = f" ({exc.holder})" if exc.holder else ""
        raise ValueError(f"{out}: another trade is writing this folder{who}: its {LOCK_FILE} "
                         "is held; wait for it, or choose another --out") from None
    try:
        journal = _Journal(out, cases, grid, requested, overwrite=args.overwrite,
                           also_threads=0 if args.threads is None else None)
        for case in cases:
            done = journal.done(case.name)
            rows.extend(r for s in done.values() for r in s)
            setting: list[Any] = []

            def keep(label: str, setting: list[Any] = setting) -> None:
                journal.add(label, setting, time.perf_counter() - t_all)
                setting.clear()

            for row in run_trade(case, grid, skip=frozenset(done), finished=keep):
                setting.append(row)
                rows.append(row)
                print(f"{row.case:22s} {row.setting:26s} it {row.iterations:5d} "
                      f"{row.wall_s:8.2f} s  held-out {row.heldout_psnr:6.2f} dB"
                      + (f"  PSNR {row.psnr:6.2f} dB" if row.psnr is not None else ""),
                      file=sys.stderr)
        rows = _in_grid_order(rows, cases, grid)
        _write_outputs(args, out, rows, cases, threads, budgets, t_all,
                       earlier_s=journal.earlier_s(), sessions=journal.sessions())
        journal.remove()
    except BaseException:
        # a trade that measured nothing leaves nothing: its empty journal refused the next
        # trade of other data into the folder ("the partial result of another trade")
        if journal is not None and not journal.entries and journal.path.is_file() \
                and len(journal.path.read_text(encoding="utf-8").splitlines()) <= 1:
            journal.remove()
            if made:
                lock.release()
                (out / LOCK_FILE).unlink(missing_ok=True)
                with contextlib.suppress(OSError):
                    out.rmdir()  # only when empty
        raise
    finally:
        lock.release()
    return 0


def _requested_threads(args: argparse.Namespace) -> int:
    """The thread request: ``trade --threads``, else ``lenslesscam --threads``, else 0 (choose).

    0 rather than None when neither is given: the journal records the request, and those of
    earlier releases recorded the default as 0.
    """
    if args.threads is not None:
        return int(args.threads)
    g = getattr(args, "global_threads", None)
    return 0 if g is None else int(g)


def _in_grid_order(rows: list[Any], cases: list[Any], grid: Any) -> list[Any]:
    """Rows by case, then setting as the grid lists them (resumed ones came first)."""
    case_at = {c.name: i for i, c in enumerate(cases)}
    setting_at = {c.label: i for i, c in enumerate(grid)}
    return sorted(rows, key=lambda r: (case_at.get(r.case, 0), setting_at.get(r.setting, 0),
                                       r.iterations))


class _Journal:
    """``trade.partial.jsonl``: each measured setting, written as it finishes.

    A run stopped by a kill, Ctrl-C or a crash goes on where it was when the same command is
    given again (a setting cut short runs again).
    Its first line names the cases (their data: arrays, field and source), the grid and the
    requested threads (--threads; the count chosen from the load may differ between sessions);
    a journal of another command in the folder is refused (it would mix measurements), or
    discarded with ``--overwrite``. Removed when the trade's files are written.
    Each setting's line says which session measured it (``session``: 0, 1, ...), the seconds
    that session had run when it finished (``session_s``) and the seconds it took since the
    session's previous one (``setting_s``), so trade.md's time counts every session (an earlier
    one up to its last measured setting: a setting cut short leaves no line).
    """

    NAME = "trade.partial.jsonl"
    FORMAT = "lenslesscam.trade_journal"

    def __init__(self, out: Path, cases: list[Any], grid: Any, threads: int | None,
                 overwrite: bool = False, also_threads: int | None = None) -> None:
        import hashlib
        import json

        from recon.atomic import atomic_write_bytes
        from recon.formats import FORMAT_VERSION, array_hash
        from recon.trade import case_record

        self.path = out / self.NAME
        # what trade.csv records of each case (shapes, field, PSF and measurement, source),
        # and the mask and truth the rows were scored with
        what = {"cases": [[case_record(c), *(None if a is None else array_hash(a)
                                             for a in (c.mask, c.truth))] for c in cases],
                "grid": [c.label for c in grid], "threads": threads}
        self.key = hashlib.sha256(json.dumps(what, default=str).encode()).hexdigest()[:16]
        # ``also_threads``: a request that keys the same trade (the earlier releases recorded
        # 0 when only the global --threads was given)
        self.keys = {self.key}
        if also_threads is not None and also_threads != threads:
            other = {**what, "threads": also_threads}
            self.keys.add(hashlib.sha256(json.dumps(other, default=str).encode()
                                         ).hexdigest()[:16])
        self.entries: dict[str, dict[str, list[Any]]] = {}
        #: earlier sessions: their number -> seconds they had run at their last setting
        self.earlier: dict[int, float] = {}
        #: an earlier session's time is not in the journal (written by an older release)
        self.unknown_time = False
        #: this session's number (one more than the journal's last)
        self.session = 0
        self._last_s = 0.0
        if self.path.is_file() and self._read(overwrite):
            self.session = max(self.earlier, default=-1) + 1
            return
        head = {"format": self.FORMAT, "format_version": FORMAT_VERSION, "key": self.key}
        atomic_write_bytes(self.path, (json.dumps(head) + "\n").encode())

    def _read(self, overwrite: bool) -> bool:
        """Take the journal's settings; False when it is another trade's and is discarded."""
        import json

        from recon.atomic import atomic_write_bytes
        from recon.trade import TradeRow

        text = self.path.read_text(encoding="utf-8")
        if text and not text.endswith("\n"):  # a line cut by a kill: that setting runs again
            text = text[:text.rfind("\n") + 1]
            atomic_write_bytes(self.path, text.encode("utf-8"))
        lines = text.splitlines()
        try:
            head = json.loads(lines[0]) if lines else {}
        except ValueError:
            head = {}
        from recon.formats import FORMAT_VERSION, whole_version

        version = whole_version(head.get("format_version"))
        if head.get("format") != self.FORMAT or head.get("key") not in self.keys:
            what, cause = "was another trade's partial result", (
                "is the partial result of another trade (other data, field, grid or "
                "--threads): give that command again to finish it")
        elif version is None or version > FORMAT_VERSION:
            # a newer release's rows may hold fields this one would drop
            what = (f"has format_version {head.get('format_version')!r}, which this release "
                    "does not read")
            cause = (f"{what} (1..{FORMAT_VERSION}): finish the trade with the release that "
                     "began it")
        else:
            what = cause = ""
        if what:
            if overwrite:
                print(f"trade: note: {self.path} {what} (--overwrite): discarded",
                      file=sys.stderr)
                return False
            raise ValueError(f"{self.path} {cause}, pass --overwrite to discard it, or choose "
                             "another --out")
        n, damaged = 0, 0
        for line in lines[1:]:
            try:
                e = json.loads(line)
                rows = [TradeRow(**r) for r in e["rows"]]
            except (ValueError, KeyError, TypeError):
                damaged += 1
                continue
            self.entries.setdefault(e["case"], {})[e["setting"]] = rows
            n += 1
            # a journal of an older release has no session: its time is not known
            k, t = e.get("session", 0), e.get("session_s")
            if not isinstance(t, int | float) or isinstance(t, bool):
                self.unknown_time = True
                t = 0.0
            if isinstance(k, int):
                self.earlier[k] = max(self.earlier.get(k, 0.0), float(t))
        print(f"trade: resuming from {self.path}: {n} settings already measured",
              file=sys.stderr)
        if damaged:
            print(f"trade: note: {damaged} line(s) of {self.path} could not be read (damaged): "
                  "their settings are measured again", file=sys.stderr)
        return True

    def done(self, case: str) -> dict[str, list[Any]]:
        """The settings of ``case`` measured by an earlier session, with their rows."""
        return self.entries.get(case, {})

    def add(self, label: str, rows: list[Any], session_s: float) -> None:
        """Record one finished setting (all its rows), ``session_s`` into this session."""
        from dataclasses import asdict

        if rows:
            self._append({"case": rows[0].case, "setting": label,
                          "rows": [asdict(r) for r in rows], "session": self.session,
                          "session_s": round(session_s, 3),
                          "setting_s": round(session_s - self._last_s, 3)})
        self._last_s = session_s

    def earlier_s(self) -> float | None:
        """The seconds of the earlier sessions (each up to its last measured setting).

        None when the journal does not say (an older release wrote it).
        """
        return None if self.unknown_time else sum(self.earlier.values())

    def sessions(self) -> int:
        """How many sessions measured this trade: the earlier ones and this one."""
        return len(self.earlier) + 1

    def _append(self, entry: dict[str, Any]) -> None:
        import json
        import os

        with open(self.path, "a", encoding="utf-8") as f:
            f.write(json.dumps(entry, default=str) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def _write_outputs(args: argparse.Namespace, out: Path, rows: list[Any], cases: list[Any],
                   threads: Any, budgets: list[float], t_all: float, *,
                   earlier_s: float | None = 0.0, sessions: int = 1) -> None:
    """trade.csv, inputs.json, trade.md and trade_pareto.png, and the summary on stdout.

    ``t_all``: when this session began; ``earlier_s``: the time of the ``sessions - 1``
    earlier ones (a resumed trade), counted in the time trade.md gives.
    """
    from recon.atomic import atomic_write_bytes
    from recon.trade import write_trade_csv

    argv = sys.argv[1:]
    command = " ".join(argv[argv.index("trade"):] if "trade" in argv else ["trade"])
    if getattr(args, "global_threads", None) is not None:  # lenslesscam --threads N trade ...
        command = f"--threads {args.global_threads} {command}"
    # CSV, with the data of every case in its header (plan --trade checks them)
    write_trade_csv(out / "trade.csv", rows, cases, command=f"lenslesscam {command}",
                    threads=threads.threads)
    if getattr(args, "meas", None) and getattr(args, "psf", None):
        from recon.suggest import input_hashes_of_files, write_trade_inputs

        # which measurement the trade was measured on: the app's job dialog offers it for that
        write_trade_inputs(out, input_hashes_of_files(args.meas, args.psf))
    # Markdown
    this = time.perf_counter() - t_all
    if earlier_s is None:  # a journal of an older release: the earlier sessions' time unknown
        took = this
        over = (f" in this session of {sessions} (resumed; the earlier sessions' time is not "
                "in their journal, written by an older release)")
    else:
        took = earlier_s + this
        over = (f" over {sessions} sessions (resumed; an interrupted session counted up to its "
                "last measured setting)" if sessions > 1 else "")
    from recon.trade import trade_markdown

    md = trade_markdown(rows, cases, budgets,
                        f"Produced by `lenslesscam {command}` in {took:.0f} s{over}, "
                        f"{threads.reason}.",
                        "Every point is in `trade.csv`; the plot is `trade_pareto.png`.")
    atomic_write_bytes(out / "trade.md", md.encode())
    _plot(cases, rows, out / "trade_pareto.png")
    print(md)


def _plot(cases: list[Any], rows: list[Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from recon.atomic import atomic_write
    from recon.trade import QUALITY_LABEL, pareto_front

    n = len(cases)
    cols = min(n, 4)
    nrows = -(-n // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 3.0 * nrows), squeeze=False)
    colours = {"fista": "tab:blue", "admm": "tab:orange", "udn": "tab:green"}
    for ax, case in zip(axes.flat, cases, strict=False):
        key = "psnr" if case.truth is not None else "heldout_psnr"
        cr = [r for r in rows if r.case == case.name]
        for method, colour in colours.items():
            pts = [r for r in cr if r.method == method]
            if pts:
                ax.scatter([r.wall_s for r in pts], [getattr(r, key) for r in pts], s=10,
                           c=colour, label=method, alpha=0.7)
        front = pareto_front(cr, key)
        ax.plot([r.wall_s for r in front], [getattr(r, key) for r in front], "k-", lw=0.8)
        ax.set_xscale("log")
        ax.set_title(case.name, fontsize=9)
        ax.set_xlabel("wall time (s)", fontsize=8)
        ax.set_ylabel(QUALITY_LABEL[key], fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    import json

    from recon.formats import FORMAT_VERSION, provenance

    # the PNG's text chunk says what made it, as the reconstruction previews' do
    meta = {"lenslesscam": json.dumps({"format": "lenslesscam.trade_plot",
                                       "format_version": FORMAT_VERSION,
                                       "provenance": provenance()}, default=str)}
    atomic_write(path, lambda p: fig.savefig(p, dpi=90, format="png", metadata=meta))
    plt.close(fig)
