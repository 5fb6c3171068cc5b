"""``lenslesscam bench``: results files, reproduction commands, provenance and thread counts.

Each test failed on the code before its fix (a hostile review of the bench commands): the
"Produced by" commands were rebuilt from ``sys.argv`` (``lenslesscam bench real-pairs --threads
1 bench real-pairs ...``) or hardcoded (protocol); the Markdown claimed "shared 2-core VM";
results files had no format tag (a protocol run appended to a real-pairs file); a torn last
line refused the whole file; foreign files gave KeyError tracebacks; ``lenslesscam --threads N``
did not reach most benchmarks and a table mixed thread counts; ``bench fista --sizes`` took
repeats and sizes beyond memory; tau-rules and admm-penalty ran finished cases again and
counted them twice; ``--table-only`` ignored options silently.
"""

from __future__ import annotations

import argparse
import json
import shlex
import warnings
from pathlib import Path

import pytest

from app.cli import build_parser
from benchmarks import _cli
from tests.clirun import run_cli

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def _one_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip() and not ln.startswith("total")]
    assert len(lines) == 1, lines
    assert "Traceback" not in err
    return lines[0]


def _method(psnr: float, tau: float = 1e-4) -> dict:
    return {"psnr": psnr, "ssim": 0.5, "ms_ssim": 0.7, "tau": tau, "iterations": 100,
            "wall_s": 1.0}


def _rp_row(pair: str = "im65", erasure: float = 0.5, threads: int = 1, **over) -> dict:
    settings = {"downsample": 4, "udn_iters": 300, "channels": 32, "scales": 5, "skip": 4,
                "headroom": 1.0, "lr": 0.01, "ema": 0.9, "tv_weight": 0.0, "holdout": 0.1,
                "wmv_window": 50, "fista_iters": 50, "warm_start": 0, "seeds": 1,
                "lever": "none", "reg_noise": 0.05, "threads": threads, "device": "cpu"}
    row = {"pair": pair, "erasure": erasure, "shape": [3, 67, 120], "fista_peak_mb": 20.0,
           "fista_auto": _method(18.0), "fista_oracle": _method(18.5), "admm": _method(18.2),
           "load": [1.0, 1.0, 1.0], "settings": settings}
    row.update(over)
    return row


def _write(path: Path, rows: list[dict], tail: str = "") -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + tail)
    return path


def _reparse(cmd: str) -> argparse.Namespace:
    argv = shlex.split(cmd)
    assert argv[:2] == ["lenslesscam", "bench"] and argv.count("bench") == 1, cmd
    return build_parser().parse_args(argv[1:])


# ------------------------------------------------------------------------------------------
# 2. reproduction commands from the parsed options
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv", [
    ["bench", "real-pairs", "--pairs", "im65", "im408", "--erasures", "0.9", "--fista-iters",
     "50", "--channels", "8", "--scales", "3", "--lever", "precondition", "--no-udn",
     "--lr", "0.003", "--threads", "1", "--out", "x.md"],
    ["bench", "protocol", "--quick", "--iters", "5", "--no-reference", "--cache", "pc.jsonl",
     "--out", "p.md"],
    ["bench", "udn-vs-fista", "--scale", "16", "--seeds", "2", "--erasure", "0.9", "--out",
     "u.md"],
    ["bench", "udn-video", "--frames", "4", "--iters", "30", "--out", "v.md"],
])
def test_the_reproduction_command_parses_back_to_the_same_run(argv):
    """Every option that changes the run is in the command, and it parses to the same values."""
    parser = build_parser()
    args = parser.parse_args(["--threads", "1", *argv])
    module = __import__(args.func.__module__ if args.func.__module__.startswith("benchmarks")
                        else f"benchmarks.{args.func.__wrapped__.__module__.split('.')[-1]}",
                        fromlist=["add_arguments"])
    cmd = _cli.command_line(argv[1], args, module.add_arguments)
    again = _reparse(cmd)
    for action in _cli.option_defaults(module.add_arguments):
        assert getattr(again, action.dest) == getattr(args, action.dest), (action.dest, cmd)


def test_real_pairs_markdown_commands(tmp_path, capsys):
    results = _write(tmp_path / "r.jsonl", [_rp_row(erasure=e) for e in (0.5, 0.9)])
    code, _out, err = run_cli(capsys, "--threads", "1", "bench", "real-pairs", "--table-only",
                              "--results", results, "--out", tmp_path / "t.md")
    assert code == 0, err
    text = (tmp_path / "t.md").read_text()
    produced = text.split("Produced by `")[1].split("`")[0]
    assert produced.count("bench") == 1 and "--table-only" in produced
    one = text.split("In one go: `")[1].split("`")[0]
    again = _reparse(one)
    assert again.pairs == ["im65"] and again.erasures == [0.5, 0.9]
    assert again.fista_iters == 50 and again.no_udn and again.threads == 1
    assert "2-core VM" not in text and "Measured on" in text
    assert "wall (s) column" in text  # item 9: what each row's wall includes


def test_protocol_markdown_command_is_the_run(tmp_path, monkeypatch, capsys):
    from benchmarks import sim_protocol

    def fake_case(psf, scene, er, noise, iters, reference=True):
        return {"auto": {"psnr_ssim": [20.0, 0.5], "tau": 1e-4, "iterations": iters,
                         "holdout_block": 4}, "oracle": {"psnr_ssim": [21.0, 0.6], "tau": 1e-4}}

    monkeypatch.setattr(sim_protocol, "run_case", fake_case)
    monkeypatch.setattr(sim_protocol, "tables", lambda cases: f"{len(cases)} cases")
    code, _out, err = run_cli(capsys, "bench", "protocol", "--quick", "--iters", "5",
                              "--no-reference", "--cache", "pc.jsonl", "--out", "p.md",
                              "--threads", "1")
    assert code == 0, err
    text = Path("p.md").read_text()
    cmd = text.split("Produced by `")[1].split("`")[0]
    again = _reparse(cmd)
    assert again.quick and again.iters == 5 and again.no_reference
    assert again.cache == "pc.jsonl" and again.out == "p.md" and again.threads == 1
    assert "docs/simulation-protocol.md" not in text and "2-core machine" not in text
    rows = [json.loads(ln) for ln in Path("pc.jsonl").read_text().splitlines()]
    assert {r["format"] for r in rows} == {"lenslesscam.bench.protocol"}
    assert all(r["provenance"]["versions"]["lenslesscam"] for r in rows)


def test_no_benchmark_claims_a_machine_it_did_not_measure():
    for f in (ROOT / "benchmarks").glob("*.py"):
        text = f.read_text()
        assert "2-core VM" not in text and "loaded 2-core machine" not in text, f.name
        assert "sys.argv[1:]" not in text.replace("parse_args(", ""), f.name


def test_metadata_names_versions_cpu_and_threads():
    from recon.threads import choose_threads

    choice = choose_threads(1)
    meta = _cli.bench_metadata("plan", 1, choice)
    assert meta["format"] == "lenslesscam.bench.plan" and meta["format_version"] == 1
    assert {"lenslesscam", "numpy", "python"} <= set(meta["versions"])
    assert meta["cpu"]["count"] and meta["cpu"]["model"] and meta["threads"] == 1
    assert "1 torch thread(s)" in _cli.machine_text(choice)


# ------------------------------------------------------------------------------------------
# 4-6. results files: format tags, torn lines, foreign files
# ------------------------------------------------------------------------------------------

def test_a_file_of_another_benchmark_is_refused_naming_both(tmp_path, capsys):
    row = _cli.tagged("protocol", 1, {"scene": "im65", "erasure": 0.0, "noise": 0.0,
                                      "iters": 5, "auto": {}, "oracle": {}})
    results = _write(tmp_path / "p.jsonl", [row])
    code, _out, err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                              results)
    line = _one_line(err)
    assert code == 2 and "bench protocol" in line and "bench real-pairs" in line


def test_protocol_refuses_to_append_to_a_real_pairs_file(tmp_path, capsys):
    results = _write(tmp_path / "r.jsonl", [_rp_row()])
    before = results.read_bytes()
    code, _out, err = run_cli(capsys, "bench", "protocol", "--quick", "--iters", "5",
                              "--no-reference", "--cache", results)
    assert code == 2 and "not a record of bench protocol" in _one_line(err)
    assert results.read_bytes() == before


def test_a_torn_last_line_is_dropped_with_a_warning_and_cut_before_the_next_append(tmp_path,
                                                                                   capsys):
    results = _write(tmp_path / "r.jsonl", [_rp_row(erasure=0.5)],
                     tail=json.dumps(_rp_row(erasure=0.9))[:80])
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # the CLI prints it as one line
        code, out, err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                                 results)
    assert code == 0 and "50%" in out and "Traceback" not in err
    assert "lenslesscam: warning:" in err and "line 2 is torn" in err
    _cli.append_jsonl(results, _rp_row(erasure=0.95))
    lines = results.read_text().splitlines()
    assert [json.loads(ln)["erasure"] for ln in lines] == [0.5, 0.95]


def test_appends_are_fsynced(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(_cli.os, "fsync", lambda fd: synced.append(fd))
    _cli.append_jsonl(tmp_path / "a.jsonl", {"a": 1})
    assert synced


def test_real_pairs_saves_the_images_before_the_row(tmp_path, monkeypatch, capsys):
    from benchmarks import real_pairs as rp

    order = []
    monkeypatch.setattr(rp, "load_pair", lambda *a: None)
    monkeypatch.setattr(rp, "data_dir", lambda d: tmp_path)
    monkeypatch.setattr(rp, "run_case", lambda pair, e, args, keep: _rp_row(erasure=e))
    monkeypatch.setattr(rp, "_save_images", lambda *a: order.append("images"))
    real_append = rp.append_jsonl
    monkeypatch.setattr(rp, "append_jsonl", lambda *a: (order.append("row"), real_append(*a)))
    code, _out, err = run_cli(capsys, "bench", "real-pairs", "--no-udn", "--pairs", "im65",
                              "im65", "--erasures", "0.5", "0.5", "--threads", "1",
                              "--results", tmp_path / "r.jsonl")
    assert code == 0, err
    assert order == ["images", "row"]  # and the repeated pair and erasure ran once
    row = json.loads((tmp_path / "r.jsonl").read_text())
    assert row["format"] == "lenslesscam.bench.real-pairs" and row["format_version"] == 1


@pytest.mark.parametrize("bench, rows, missing", [
    ("real-pairs", [{"pair": "im65", "erasure": 0.5, "psnr": 20}], "fista_auto"),
    ("admm-penalty", [_rp_row()], "case"),
])
def test_a_foreign_file_is_one_line_naming_what_is_missing(bench, rows, missing, tmp_path,
                                                           capsys):
    results = _write(tmp_path / "f.jsonl", rows)
    code, _out, err = run_cli(capsys, "bench", bench, "--table-only", "--results", results)
    line = _one_line(err)
    assert code == 2 and str(results) in line and missing in line


def test_an_older_record_without_settings_gives_one_line_for_the_markdown(tmp_path, capsys):
    row = _rp_row()
    del row["settings"]
    results = _write(tmp_path / "r.jsonl", [row])
    code, out, _err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                              results)
    assert code == 0 and "50%" in out  # the table itself reads it
    code, _out, err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                              results, "--out", tmp_path / "t.md")
    assert code == 2 and "no stored settings" in _one_line(err)


# ------------------------------------------------------------------------------------------
# 7/8. threads
# ------------------------------------------------------------------------------------------

def test_the_global_threads_option_reaches_a_benchmark():
    from recon.threads import apply_threads

    args = build_parser().parse_args(["--threads", "1", "bench", "tau-rules"])
    args.thread_choice = apply_threads(args.global_threads)
    assert _cli.bench_threads(args).source == "requested" and args.threads == 1
    for name in ("real-pairs", "tau-rules", "admm-penalty", "protocol", "udn-video",
                 "udn-vs-fista", "plan", "time-to-quality", "udn"):
        args = build_parser().parse_args(["bench", name])
        assert args.threads is None, name  # a local default no longer overrides the global


def test_udn_vs_fistas_processes_share_the_policys_threads(monkeypatch):
    """(diff review) Each of its --jobs processes took the policy's whole count: 2 x 2
    threads on 2 cores. The policy's count is shared among them; a given count is kept."""
    import benchmarks.udn_vs_fista as uvf
    import recon.threads as rt

    monkeypatch.setattr(rt, "apply_threads", lambda n=None: rt.ThreadChoice(
        4 if n is None else int(n), 4, 0.0, "auto" if n is None else "requested"))

    class Stop(Exception):
        pass

    seen: list[int] = []

    def stop(*_a, **_k):
        seen.append(args.threads)
        raise Stop

    monkeypatch.setattr(uvf, "make_data", stop)
    for argv, want in ((["bench", "udn-vs-fista", "--jobs", "2"], 2),
                       (["bench", "udn-vs-fista", "--jobs", "2", "--threads", "3"], 3)):
        args = build_parser().parse_args(argv)
        with pytest.raises(Stop):
            uvf.run(args)
        assert seen[-1] == want, argv


def test_a_table_never_mixes_thread_counts(tmp_path, capsys):
    results = _write(tmp_path / "r.jsonl", [_rp_row(erasure=0.5, threads=1),
                                            _rp_row(erasure=0.9, threads=2)])
    code, _out, err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                              results)
    assert code == 2 and "[1, 2] torch threads" in _one_line(err)
    code, _out, err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                              results, "--erasures", "0.5")
    assert code == 0, err


# ------------------------------------------------------------------------------------------
# 10. bench fista --sizes
# ------------------------------------------------------------------------------------------

def test_fista_sizes_repeats_and_odd_sizes_are_refused(capsys):
    for bad, says in (("32,32", "twice"), ("17", "even")):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["bench", "fista", "--sizes", bad])
        assert says in capsys.readouterr().err


def test_fista_memory_is_checked_before_anything_is_built(monkeypatch, capsys):
    import recon.simulate

    def boom(*a, **k):
        raise AssertionError("built the PSF before the memory check")

    monkeypatch.setattr(recon.simulate, "synthetic_psf", boom)
    code, _out, err = run_cli(capsys, "bench", "fista", "--rounds", "3", "--methods", "fista",
                              "--sizes", "200000")
    assert code == 2 and "needs about" in _one_line(err)


# ------------------------------------------------------------------------------------------
# 11. tau-rules / admm-penalty: resume, no double counting
# ------------------------------------------------------------------------------------------

def _fake_tau_case(model, b, truth, iters, block=None):
    return {"search_s": 0.1, "block": 4, "min": {"tau": 1e-4, "iterations": 10, "psnr": 20.0},
            "1se": {"tau": 3e-4, "iterations": 10, "psnr": 20.5},
            "oracle": {"tau": 1e-4, "psnr": 21.0}}


def test_tau_rules_resumes_from_results_and_drops_repeated_erasures(tmp_path, monkeypatch,
                                                                    capsys):
    from benchmarks import tau_rules

    ran = []
    monkeypatch.setattr(tau_rules, "run_case",
                        lambda *a, **k: (ran.append(1), _fake_tau_case(*a, **k))[1])
    results = tmp_path / "t.jsonl"
    argv = ["bench", "tau-rules", "--cases", "sim", "--erasures", "0.9", "0.9", "--iters",
            "20", "--threads", "1", "--results", results]
    code, out, err = run_cli(capsys, *argv)
    assert code == 0, err
    first = len(ran)
    assert first == 6  # 3 scenes x 2 noises, 0.9 once
    code, out, err = run_cli(capsys, *argv)
    assert code == 0, err
    assert len(ran) == first  # nothing run again
    assert len(results.read_text().splitlines()) == first
    assert "sim (6 cases)" in out


def test_admm_penalty_table_counts_a_case_once_and_no_results_is_an_error(tmp_path, capsys):
    from benchmarks import admm_penalty

    run = {"gap": [0.1, 0.05, 0.01], "psnr": [19.0, 20.0, 21.0]}
    row = {"case": "sim im65 90% noise 0.01", "erasure": 0.9, "tau": 1e-4, "penalty": 1.0,
           "reference": 1.0, "fista": run, "admm_auto": run, "admm_fixed": run}
    assert "| sim 90% | 1 |" in admm_penalty.table([row, row])
    code, _out, err = run_cli(capsys, "bench", "admm-penalty", "--table-only", "--results",
                              tmp_path / "missing.jsonl")
    assert code == 1 and "no results" in err


# ------------------------------------------------------------------------------------------
# 13 and the minor ones
# ------------------------------------------------------------------------------------------

def test_table_only_refuses_run_options_and_filters_by_pairs_and_erasures(tmp_path, capsys):
    results = _write(tmp_path / "r.jsonl", [_rp_row(erasure=e) for e in (0.5, 0.9)])
    code, _out, err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                              results, "--fista-iters", "50")
    assert code == 2 and "--fista-iters" in _one_line(err)
    code, out, err = run_cli(capsys, "bench", "real-pairs", "--table-only", "--results",
                             results, "--erasures", "0.9")
    assert code == 0 and "| 90% |" in out and "| 50% |" not in out


def test_percent_in_a_description_is_shown_once():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    bench = next(a for a in sub.choices["bench"]._actions
                 if isinstance(a, argparse._SubParsersAction))
    for p in bench.choices.values():
        assert "%%" not in p.format_help()
    assert "long on a 2-core CPU" in bench.choices["real-pairs"].format_help()


def test_missing_shared_data_is_a_bench_error_naming_the_variable(monkeypatch, capsys):
    monkeypatch.setenv("LENSLESSCAM_SHARED_DATA", "/nonexistent")
    code, _out, err = run_cli(capsys, "bench", "tau-rules", "--cases", "real", "--threads", "1")
    line = _one_line(err)
    assert code == 2 and line.startswith("lenslesscam bench: error:")
    assert "LENSLESSCAM_SHARED_DATA" in line
