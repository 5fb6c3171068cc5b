"""``lenslesscam bench``: outputs, option checks and tables (a hostile tester's findings).

Each test failed on the code before its fix: every bench output silently replaced an existing
file (no ``--overwrite``), ``udn-vs-fista --fista-iters 49`` and ``protocol --iters 5`` stopped
on an assertion / a message naming no option, a second ``bench batch --keep DIR`` resumed the
old batch folders against new data (RuntimeError), ``udn --ratio`` headed a float32 comparison
"bf16", ``preview --loads -1`` ran, ``batch --workers 0`` ran as "0 worker(s)", and several
options ended in raw Python messages ("invalid literal for int()", "high <= 0", "[Errno 2]",
"'utf-8' codec can't decode").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.cli import build_parser
from tests.clirun import run_cli

ROOT = Path(__file__).resolve().parents[1]
KEPT = b"an earlier result: keep me\n"


def _run(capsys, *argv):
    """``run_cli`` that also returns argparse's exit (code, stdout, stderr)."""
    try:
        return run_cli(capsys, *argv)
    except SystemExit as exc:
        out = capsys.readouterr()
        return int(exc.code or 0), out.out, out.err


def _one_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert "Traceback" not in err
    return lines[0]


def _bench_parsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    bench = sub.choices["bench"]
    which = next(a for a in bench._actions if isinstance(a, argparse._SubParsersAction))
    return dict(which.choices)


def _action(bench: str, option: str) -> argparse.Action:
    p = _bench_parsers()[bench]
    return next(a for a in p._actions if option in a.option_strings)


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    """Default caches and results (protocol-cases.jsonl, real-pairs.jsonl) land in tmp."""
    monkeypatch.chdir(tmp_path)


# ------------------------------------------------------------------------------------------
# 1. outputs: --overwrite on every writer, checked before any work
# ------------------------------------------------------------------------------------------

#: the options of bench subcommands that name files or folders they write
WRITER_OPTIONS = ("--out", "--json", "--figure", "--keep")


def test_every_bench_that_writes_files_has_overwrite():
    writers = {name: [o for a in p._actions for o in a.option_strings if o in WRITER_OPTIONS]
               for name, p in _bench_parsers().items()}
    writers = {k: v for k, v in writers.items() if v}
    assert set(writers) >= {"fista", "udn", "protocol", "preview", "plan", "udn-video",
                            "udn-vs-fista", "real-pairs", "tau-rules", "admm-penalty", "batch"}
    missing = [name for name in writers
               if not any("--overwrite" in a.option_strings
                          for a in _bench_parsers()[name]._actions)]
    assert not missing, missing


EXISTING = [
    (["protocol", "--quick", "--no-reference", "--iters", "5"], "--out"),
    (["fista", "--sizes", "32", "--rounds", "3"], "--json"),
    (["udn", "--cases", "2d-75x100", "--channels", "4", "--scales", "2"], "--json"),
    (["preview", "--seconds", "0.1", "--configs", "4x1"], "--json"),
    (["plan", "--size", "32x32", "--iters", "5", "--cases", "static"], "--json"),
    (["udn-video", "--iters", "5", "--scenes", "im65"], "--out"),
    (["udn-vs-fista", "--iters", "5", "--scenes", "im65", "--jobs", "1"], "--out"),
    (["real-pairs", "--table-only"], "--out"),
    (["real-pairs", "--table-only"], "--figure"),
    (["tau-rules", "--cases", "sim", "--iters", "5"], "--out"),
    (["admm-penalty", "--cases", "sim"], "--out"),
]


@pytest.mark.parametrize(("argv", "option"), EXISTING,
                         ids=[f"{a[0]} {o}" for a, o in EXISTING])
def test_an_existing_output_is_refused_without_overwrite(argv, option, tmp_path, capsys):
    # `bench protocol --out sim/meas.npy` replaced a measurement with Markdown
    target = tmp_path / "sim" / "meas.npy"
    target.parent.mkdir()
    target.write_bytes(KEPT)
    code, out, err = _run(capsys, "bench", *argv, option, target)
    assert code == 2, (out, err)
    line = _one_line(err)
    assert "exists" in line and "--overwrite" in line and str(target) in line, line
    assert target.read_bytes() == KEPT


def test_an_output_that_is_an_input_or_a_folder_is_refused(tmp_path, capsys):
    # the cache read and appended to is an input: --out may not replace it, even --overwrite
    cache = tmp_path / "cases.jsonl"
    cache.write_text('{"scene": "im65"}\n')
    code, _, err = _run(capsys, "bench", "protocol", "--cache", cache, "--out", cache,
                        "--overwrite")
    assert code == 2 and "--cache" in _one_line(err)
    assert cache.read_text() == '{"scene": "im65"}\n'
    # `bench protocol --out sim` (a folder) ended in "[Errno 21] Is a directory"
    (tmp_path / "sim").mkdir()
    code, _, err = _run(capsys, "bench", "protocol", "--out", "sim")
    line = _one_line(err)
    assert code == 2 and "sim is a folder" in line and "Errno" not in line
    # two outputs naming one file: the figure would be replaced by the Markdown
    code, _, err = _run(capsys, "bench", "real-pairs", "--table-only", "--out", "a.md",
                        "--figure", "a.md")
    line = _one_line(err)
    assert code == 2 and "--out and --figure" in line


def test_overwrite_replaces_and_fista_iters_below_the_first_checkpoint(tmp_path, capsys):
    # 2: --fista-iters 49 (below the first checkpoint, 50) was an AssertionError at the end of
    # the FISTA grid; now scored at its last iteration. And --overwrite replaces --out.
    out = tmp_path / "udn-vs-fista.md"
    out.write_bytes(KEPT)
    argv = ["bench", "udn-vs-fista", "--iters", "5", "--seeds", "1", "--channels", "4",
            "--scales", "2", "--fista-iters", "49", "--jobs", "1", "--scenes", "im65",
            "--out", out]
    code, _, err = _run(capsys, *argv)
    assert code == 2 and out.read_bytes() == KEPT
    code, stdout, err = _run(capsys, *argv, "--overwrite")
    assert code == 0, err
    assert "49 iterations, mean PSNR" in err
    text = out.read_text()
    assert text.startswith("# UDN vs FISTA-TV") and "checkpoints 49)" in text
    assert "| im65 |" in stdout


def test_fista_checkpoints_keep_the_protocol_and_end_at_the_limit():
    from benchmarks.udn_vs_fista import FISTA_CHECKPOINTS, fista_checkpoints

    assert fista_checkpoints(500) == list(FISTA_CHECKPOINTS)  # the default run is unchanged
    assert fista_checkpoints(49) == [49]
    assert fista_checkpoints(250) == [50, 100, 200, 250]


# ------------------------------------------------------------------------------------------
# 3. bench batch --keep
# ------------------------------------------------------------------------------------------

BATCH = ["bench", "batch", "--items", "3", "--workers", "1", "--size", "32x32", "--iters", "5",
         "--noop", "1"]


def test_batch_refuses_a_folder_that_is_not_empty(tmp_path, capsys):
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    code, _, err = _run(capsys, *BATCH, "--keep", keep)
    line = _one_line(err)
    assert code == 2 and "--keep" in line and "not empty" in line and "--overwrite" in line
    # --overwrite removes only what the bench wrote: a "data" it did not write is refused
    (keep / "data").mkdir()
    code, _, err = _run(capsys, *BATCH, "--keep", keep, "--overwrite")
    line = _one_line(err)
    assert code == 2 and "data" in line and "did not write" in line
    assert sorted(p.name for p in keep.iterdir()) == ["data", "notes.txt"]
    # a file is not a folder
    code, _, err = _run(capsys, *BATCH, "--keep", keep / "notes.txt")
    assert code == 2 and "is a file" in _one_line(err)


@pytest.mark.slow
def test_batch_run_twice_with_one_keep_folder(tmp_path, capsys):
    """The second run with the same --keep was a RuntimeError (the old batch folders resumed
    against newly written data): now refused in one line, and with --overwrite a fresh run
    that removes what the first wrote and nothing else."""
    keep = tmp_path / "keep"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}

    def cli(*extra):
        return subprocess.run([sys.executable, "-m", "app.cli", *map(str, BATCH), "--keep",
                               str(keep), *extra], env=env, capture_output=True, text=True,
                              timeout=240)

    first = cli()
    assert first.returncode == 0, first.stderr
    wrote = {p.name for p in keep.iterdir()}
    assert {"data", "seq-cold", "seq-warm", "ray1-cold", "ray1-warm"} <= wrote
    code, _, err = _run(capsys, *BATCH, "--keep", keep)
    assert code == 2 and "not empty" in _one_line(err)
    (keep / "notes.txt").write_text("mine")
    stale = keep / "ray1-warm" / "stale-file"
    stale.write_text("from the first run")
    again = cli("--overwrite")
    assert again.returncode == 0, again.stderr
    assert "| Ray, 1 worker(s), warm |" in again.stdout
    assert (keep / "notes.txt").read_text() == "mine"
    assert not stale.exists()  # the first run's folders were removed, not resumed
    marker = json.loads((keep / ".lenslesscam-bench-batch.json").read_text())
    assert "ray1-warm" in marker["entries"]


# ------------------------------------------------------------------------------------------
# 4. bench udn --ratio: the headings follow what was compared
# ------------------------------------------------------------------------------------------


def test_profile_table_is_headed_by_the_variant_compared():
    from benchmarks.bench_udn import profile_table

    base = {"convolution (forward and backward)": 0.004,
            "dtype casts and copies (autocast)": 0.001}
    other = {"convolution (forward and backward)": 0.003,
             "dtype casts and copies (autocast)": 0.001}
    text = profile_table(base, other, "float32 channels-last")
    head = text.splitlines()[0]
    assert "float32 channels-last (ms)" in head and "float32 channels-last / float32" in head
    assert "bf16" not in text and "autocast" not in text
    text = profile_table(base, other, "bf16 channels-last")
    assert "bf16 channels-last (ms)" in text and "(autocast)" in text


def test_udn_ratio_table_names_the_profiled_variant(capsys):
    code, out, err = _run(capsys, "bench", "udn", "--ratio", "--cases", "2d-75x100",
                          "--channels", "4", "--scales", "2", "--rounds", "2", "--warmup", "1")
    assert code == 0, err
    compared = out.split("(profile: float32 against ")[1].split(")")[0]
    head = next(ln for ln in out.splitlines() if ln.startswith("| kind of op"))
    assert f"| {compared} (ms) |" in head and f"| {compared} / float32 |" in head
    if not compared.startswith("bf16"):
        assert "bf16" not in head


def test_profile_counts_waits_launches_and_device_time():
    """bench udn --profile (GPU only, so its parsing is tested on made-up events): synchronize calls
    and launches are counted on the CPU side, device time summed on the device side, all per
    iteration."""
    from types import SimpleNamespace

    from benchmarks.bench_udn import profile_counts

    def ev(name, device, start=0, end=0):
        return SimpleNamespace(name=name, device_type=f"DeviceType.{device}",
                               time_range=SimpleNamespace(start=start, end=end))

    events = [ev("cudaLaunchKernel", "CPU")] * 6 + [ev("cuLaunchKernelEx", "CPU")] * 2 + [
        ev("cudaStreamSynchronize", "CPU"), ev("cudaMemcpyAsync", "CPU"),
        ev("aten::conv2d", "CPU", 0, 900),
        ev("void cudnn::conv_kernel", "CUDA", 10, 310), ev("Memcpy DtoH", "CUDA", 400, 500)]
    c = profile_counts(events, iters=2)
    assert c == {"waits_per_iter": 0.5, "launches_per_iter": 4.0,
                 "device_s_per_iter": pytest.approx(200e-6)}


def test_udn_profile_on_a_cpu_says_it_profiled_nothing(capsys):
    code, out, err = _run(capsys, "bench", "udn", "--profile", "--cases", "2d-75x100",
                          "--channels", "4", "--scales", "2", "--iters", "1", "--warmup", "0",
                          "--precision", "float32", "--compile", "off", "--device", "cpu")
    assert code == 0, err
    assert "only on a CUDA device" in out and "launches / it." not in out


def test_udn_ratio_refuses_json(capsys, tmp_path):
    code, _, err = _run(capsys, "bench", "udn", "--ratio", "--json", tmp_path / "r.json")
    assert code == 2 and "--json" in _one_line(err) and not (tmp_path / "r.json").exists()


# ------------------------------------------------------------------------------------------
# 5-7. option values: refused at the command line, in one line naming the option
# ------------------------------------------------------------------------------------------

BAD = [
    (["preview", "--loads", "-1"], "--loads", ">= 0"),
    (["preview", "--loads", "0,x"], "--loads", ">= 0"),
    (["preview", "--configs", "abc"], "--configs", "DOWNSAMPLExITERATIONS"),
    (["preview", "--configs", "0x5"], "--configs", "DOWNSAMPLE 1..16"),
    (["plan", "--size", "abc"], "--size", "HxW"),
    (["plan", "--size", "16x64"], "--size", "at least 32x32"),
    (["plan", "--cases", "static,nope"], "--cases", "static"),
    (["batch", "--size", "1x1"], "--size", "at least 16x16"),
    (["batch", "--workers", "0"], "--workers", ">= 1"),
    (["batch", "--workers", "1,0"], "--workers", ">= 1"),
]


@pytest.mark.parametrize(("argv", "option", "rule"), BAD, ids=[" ".join(a) for a, _, _ in BAD])
def test_bad_values_stop_at_the_command_line(argv, option, rule, capsys):
    code, _, err = _run(capsys, "bench", *argv)
    line = _one_line(err)
    assert code == 2
    assert f"argument {option}" in line and "must be" in line and rule in line, line
    assert "invalid literal" not in line


def test_list_and_size_options_parse():
    p = _bench_parsers()
    a = p["preview"].parse_args(["--loads", "0,2", "--configs", "1x3,2x5"])
    assert a.loads == [0, 2] and a.configs == [(1, 3), (2, 5)]
    a = p["preview"].parse_args([])
    assert a.loads == [0] and a.configs == [(1, 3), (1, 5), (1, 10), (2, 5)]
    assert p["batch"].parse_args([]).size == (48, 64)
    assert p["batch"].parse_args([]).workers == [1, 2]
    assert p["plan"].parse_args(["--size", "40x50"]).size == (40, 50)
    # a repeated value would be measured twice, its second row timing nothing (ray1 reused)
    with pytest.raises(SystemExit):
        p["batch"].parse_args(["--workers", "1,1"])


def test_preview_config_ranges_are_the_engines():
    from app.gui.preview_engine import RANGES
    from benchmarks.bench_preview import DOWNSAMPLE_RANGE, ITERS_RANGE

    assert tuple(RANGES["downsample"]) == DOWNSAMPLE_RANGE
    assert tuple(RANGES["iters_per_frame"]) == ITERS_RANGE


def test_help_says_what_the_code_does():
    loads = _action("preview", "--loads")
    assert loads.default == "0" and "default 0" in loads.help and "(0,2)" not in loads.help
    threads = _action("udn", "--threads")
    assert "torch default" not in threads.help and "thread policy" in threads.help
    jobs = _action("udn-vs-fista", "--jobs")
    assert "min(2, CPU count)" in jobs.help and f": {jobs.default} here" in jobs.help
    assert "(2)" not in jobs.help


def test_protocol_auto_runs_below_100_iterations():
    # `bench protocol --iters 5` stopped on "need 1 <= min_iter <= max_iter, got 100, 5"
    from benchmarks.sim_protocol import run_auto, simulate_case
    from recon.simulate import synthetic_psf

    psf = synthetic_psf((32, 40), seed=3)
    y, x = np.mgrid[0:32, 0:40] / 40
    scene = (0.2 + 0.6 * ((x - 0.4) ** 2 + (y - 0.4) ** 2 < 0.05)).astype(np.float32)
    res = run_auto(simulate_case(psf, scene[None, None], 0.5, 0.01), 5)
    assert 1 <= res["iterations"] <= 5 and res["search_iterations"] > 0


def test_files_named_by_options_give_one_line(tmp_path, capsys):
    # a binary --cache: "'utf-8' codec can't decode byte ..."
    np.save(tmp_path / "meas.npy", np.ones((4, 4), np.float32))
    code, _, err = _run(capsys, "bench", "protocol", "--cache", tmp_path / "meas.npy")
    line = _one_line(err)
    assert code == 2 and "--cache" in line and "not a JSON-lines file" in line
    assert "codec" not in line
    # a text file that is not JSON lines, appended to by tau-rules --results
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    code, _, err = _run(capsys, "bench", "tau-rules", "--cases", "sim", "--results", notes)
    line = _one_line(err)
    assert code == 2 and "--results" in line and "line 1" in line
    assert notes.read_text() == "my notes\n"
    # a missing --admm-baseline: "[Errno 2] No such file or directory"
    code, _, err = _run(capsys, "bench", "fista", "--sizes", "32", "--rounds", "3",
                        "--admm-baseline", tmp_path / "nonexist.py")
    line = _one_line(err)
    assert code == 2 and "--admm-baseline" in line and "no such file" in line
    assert "Errno" not in line
    bad = tmp_path / "admm.py"
    bad.write_text("def broken(:\n")
    code, _, err = _run(capsys, "bench", "fista", "--sizes", "32", "--rounds", "3",
                        "--admm-baseline", bad)
    line = _one_line(err)
    assert code == 2 and "--admm-baseline" in line and "SyntaxError" in line


def test_tau_rules_block_larger_than_the_sensor_allows(capsys):
    from benchmarks.tau_rules import block_limit, check_block

    # on the 150x200 simulation a block of 1000 held everything out in one block and the
    # search silently picked the largest tau
    code, _, err = _run(capsys, "bench", "tau-rules", "--cases", "sim", "--block", "1000")
    line = _one_line(err)
    assert code == 2 and "--block 1000" in line and "150x200" in line and "at most 38" in line
    assert block_limit(150, 200) == 38
    check_block(38, {"sim": (150, 200)})  # the limit itself runs
    check_block(19, {"sim": (150, 200)})  # a side measured in docs/auto-tau.md
    with pytest.raises(ValueError, match="at most 38"):
        check_block(39, {"sim": (150, 200)})
