"""Batch manifests without Ray: parsing, globs, checks with the recon parser, item hashes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.batch.manifest import input_hashes, item_hash, read_manifest
from app.cli import main
from tests.batch.conftest import make_data, write_udn_spec


@pytest.fixture
def data(tmp_path: Path) -> Path:
    return make_data(tmp_path / "data", 3)


def test_simplest_csv_with_a_glob(data: Path) -> None:
    (data / "m.csv").write_text("measurement,psf,method\nmeas/m*.npy,psf.npy,fista\n")
    items = read_manifest(data / "m.csv")
    assert [it.id for it in items] == ["m00-fista", "m01-fista", "m02-fista"]
    it = items[1]
    assert it.method == "fista"
    meas = str((data / "meas" / "m01.npy").resolve())
    assert it.argv == ("--meas", meas, "--psf", str((data / "psf.npy").resolve()))
    assert dict(it.inputs)["measurement"] == meas


def test_ray_is_imported_only_to_run_a_batch(data: Path) -> None:
    """Reading manifests, the task code, status and cancel never import Ray (seconds)."""
    (data / "m.csv").write_text("measurement,psf,method\nmeas/m*.npy,psf.npy,fista\n")
    code = ("import sys\n"
            "from app.batch.manifest import read_manifest\n"
            "import app.batch.task, app.batch.state, app.batch.driver, app.commands.batch\n"
            f"assert len(read_manifest({str(data / 'm.csv')!r})) == 3\n"
            "from app.cli import main\n"
            f"assert main(['batch', 'status', {str(data)!r}]) == 2\n"
            "print('ray' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).parents[2], timeout=120, check=True)
    assert out.stdout.strip() == "False"


def test_toml_defaults_items_and_overrides(data: Path) -> None:
    write_udn_spec(data, 10, 5)
    (data / "m.toml").write_text(
        '[defaults]\npsf = "psf.npy"\nmethod = "fista"\ntau = 1e-4\n\n'
        '[[item]]\nmeasurement = "meas/m0[01].npy"\niters = 50\n\n'
        '[[item]]\nmeasurement = "meas/m00.npy"\nmethod = "udn"\nspec = "udn.toml"\n'
        'truth = "meas/t00.npy"\niters = 7\n\n'
        '[[item]]\nmeasurement = "meas/m00.npy"\nname = "again"\nno_restart = true\n')
    items = read_manifest(data / "m.toml")
    assert [it.id for it in items] == ["m00-fista", "m01-fista", "m00-udn", "again"]
    assert items[0].argv[-4:] == ("--tau", "0.0001", "--iters", "50")
    udn = items[2]
    assert udn.spec == str((data / "udn.toml").resolve())
    assert ("stopping", "max_iter", 7) in udn.spec_data
    assert ("data", "truth", str((data / "meas" / "t00.npy").resolve())) in udn.spec_data
    assert "--no-restart" in items[3].argv


def test_dataset_layout_columns_reach_a_udn_spec(data: Path) -> None:
    """channel_order and flip_rows from [defaults] reach a udn item's spec like rgb does (they
    were dropped silently from TOML and refused from CSV)."""
    write_udn_spec(data, 10, 5)
    (data / "m.toml").write_text(
        '[defaults]\npsf = "psf.npy"\nmethod = "fista"\nchannel_order = "bgr"\n'
        'flip_rows = true\n\n'
        '[[item]]\nmeasurement = "meas/m00.npy"\n\n'
        '[[item]]\nmeasurement = "meas/m00.npy"\nmethod = "udn"\nspec = "udn.toml"\n')
    fista, udn = read_manifest(data / "m.toml")
    assert "--flip-rows" in fista.argv and "bgr" in fista.argv
    assert ("data", "channel_order", "bgr") in udn.spec_data
    assert ("data", "flip_rows", True) in udn.spec_data
    (data / "m.csv").write_text("measurement,psf,method,spec,channel_order,flip_rows\n"
                                "meas/m00.npy,psf.npy,udn,udn.toml,bgr,false\n")
    (item,) = read_manifest(data / "m.csv")
    assert ("data", "flip_rows", False) in item.spec_data


def test_a_numeric_dark_reaches_a_udn_spec_as_a_number(data: Path) -> None:
    """dark = 100 for a udn item with a spec was passed on as the text '100', which the spec
    read as a file name ('data.dark: file not found: .../100'); a file and 'auto' still work."""
    write_udn_spec(data, 10, 5)
    (data / "m.toml").write_text(
        '[defaults]\npsf = "psf.npy"\ndark = 100\npsf_dark = 0\n\n'
        '[[item]]\nmeasurement = "meas/m00.npy"\nmethod = "udn"\nspec = "udn.toml"\n\n'
        '[[item]]\nmeasurement = "meas/m01.npy"\nmethod = "udn"\nspec = "udn.toml"\n'
        'dark = "auto"\nname = "auto"\n\n'
        '[[item]]\nmeasurement = "meas/m02.npy"\nmethod = "udn"\nspec = "udn.toml"\n'
        'dark = "meas/m00.npy"\nname = "file"\n')
    number, auto, file = read_manifest(data / "m.toml")
    assert ("data", "dark", 100.0) in number.spec_data
    assert ("data", "psf_dark", 0.0) in number.spec_data
    assert ("data", "dark", "auto") in auto.spec_data
    assert ("data", "dark", str((data / "meas" / "m00.npy").resolve())) in file.spec_data
    (data / "m.csv").write_text("measurement,psf,method,spec,dark\n"
                                "meas/m00.npy,psf.npy,udn,udn.toml,12.5\n")
    (item,) = read_manifest(data / "m.csv")
    assert ("data", "dark", 12.5) in item.spec_data


def test_a_manifest_that_is_not_utf8_is_named(data: Path) -> None:
    (data / "m.csv").write_bytes(b"measurement,psf,method\nm\xe9.npy,psf.npy,fista\n")
    with pytest.raises(ValueError, match=r"m\.csv: not UTF-8 text \(byte 0xe9 at offset 24\)"):
        read_manifest(data / "m.csv")
    (data / "m.toml").write_bytes(b"\xef\xbb\xbf[[item]]\nmeasurement = 'meas/m00.npy'\n"
                                  b"psf = 'psf.npy'\nmethod = 'fista'\n")
    assert [it.id for it in read_manifest(data / "m.toml")] == ["m00-fista"]  # a BOM is fine


def test_duplicate_names_are_numbered(data: Path) -> None:
    (data / "m.csv").write_text("measurement,psf,method,tau\nmeas/m00.npy,psf.npy,fista,1e-3\n"
                                "meas/m00.npy,psf.npy,fista,1e-2\n")
    assert [it.id for it in read_manifest(data / "m.csv")] == ["m00-fista", "m00-fista-2"]


def test_item_names_never_collide(data: Path) -> None:
    """Two items got the id m00-fista-2 (the second m00 numbered into a name a third item was
    given), so two items wrote one result file; and 'a/b' and 'a_b' both became 'a_b'."""
    (data / "m.csv").write_text("measurement,psf,method,name\nmeas/m00.npy,psf.npy,fista,\n"
                                "meas/m00.npy,psf.npy,fista,\n"
                                "meas/m01.npy,psf.npy,fista,m00-fista-2\n")
    ids = [it.id for it in read_manifest(data / "m.csv")]
    assert ids == ["m00-fista", "m00-fista-3", "m00-fista-2"] and len(set(ids)) == 3
    (data / "m.csv").write_text("measurement,psf,method,name\nmeas/m00.npy,psf.npy,fista,a/b\n"
                                "meas/m01.npy,psf.npy,fista,a_b\n")
    with pytest.raises(ValueError, match=r"name 'a_b' is given to another item too"):
        read_manifest(data / "m.csv")
    (data / "m.csv").write_text("measurement,psf,method,name\nmeas/m00.npy,psf.npy,fista,a_b\n"
                                "meas/m01.npy,psf.npy,fista,a/b\n")
    with pytest.raises(ValueError, match=r"name 'a/b' \(as the file name 'a_b'\) is given"):
        read_manifest(data / "m.csv")


@pytest.mark.parametrize(("text", "message"), [
    ("measurement,psf,method\nmeas/none*.npy,psf.npy,fista\n", "matches no file"),
    ("measurement,psf,method\nmeas/m00.npy,psf.npy,magic\n", "not a method of"),
    ("measurement,psf,method,colour\nmeas/m00.npy,psf.npy,fista,red\n",
     "column 'colour' is not an option"),
    ("measurement,psf,method,iters\nmeas/m00.npy,psf.npy,fista,-3\n", "--iters"),
    # read as the command line reads it: '-1e3' is a value ('expected one argument' before)
    ("measurement,psf,method,iters\nmeas/m00.npy,psf.npy,fista,-1e3\n",
     "argument --iters: must be 'auto' or an integer >= 1, got '-1e3'"),
    ("measurement,psf,method,spec\nmeas/m00.npy,psf.npy,fista,x.toml\n", "is for method udn"),
    ("psf,method\npsf.npy,fista\n", "'measurement' is missing"),
    ("measurement,psf,method,rgb\nmeas/m00.npy,psf.npy,fista,maybe\n", "is a flag"),
    ("measurement,psf,method\n", "lists no items"),
])
def test_bad_rows_name_the_row(data: Path, text: str, message: str) -> None:
    (data / "m.csv").write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        read_manifest(data / "m.csv")
    assert "\n" not in str(err.value)
    if "lists no items" not in message:
        assert "m.csv:2" in str(err.value)


def test_udn_spec_column_checked_when_read(data: Path) -> None:
    write_udn_spec(data, 10, 5)
    (data / "m.csv").write_text("measurement,psf,method,spec,tau\n"
                                "meas/m00.npy,psf.npy,udn,udn.toml,1e-3\n")
    with pytest.raises(ValueError, match="column 'tau' cannot change a job spec"):
        read_manifest(data / "m.csv")
    (data / "bad.toml").write_text('[stopping]\nmax_iters = 3\n')
    (data / "m.csv").write_text("measurement,psf,method,spec\n"
                                "meas/m00.npy,psf.npy,udn,bad.toml\n")
    with pytest.raises(ValueError, match=r"unknown key 'stopping\.max_iters'"):
        read_manifest(data / "m.csv")


def test_item_hash_follows_contents_and_options(data: Path) -> None:
    (data / "m.csv").write_text("measurement,psf,method,tau\nmeas/m*.npy,psf.npy,fista,1e-3\n")
    a = read_manifest(data / "m.csv")
    before = [item_hash(it) for it in a]
    assert len(set(before)) == 3
    assert [item_hash(it) for it in read_manifest(data / "m.csv")] == before  # stable
    np.save(data / "meas" / "m01.npy", np.load(data / "meas" / "m01.npy") * 1.01)
    after = [item_hash(it) for it in a]
    assert [b == c for b, c in zip(before, after, strict=True)] == [True, False, True]
    (data / "m.csv").write_text("measurement,psf,method,tau\nmeas/m*.npy,psf.npy,fista,1e-2\n")
    changed = [item_hash(it) for it in read_manifest(data / "m.csv")]
    assert not set(changed) & set(after)  # another tau: every item is new
    assert input_hashes(a[0])["psf"] is not None


def test_second_driver_is_refused(data: Path) -> None:
    from app.batch.driver import run_batch
    from app.batch.state import BatchBusy, BatchLock

    (data / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    out = data / "out"
    out.mkdir()
    with BatchLock(out), pytest.raises(BatchBusy, match="in use by another batch driver"):
        run_batch(data / "m.csv", out)
    assert not (out / "state.json").exists()


def test_cli_bad_manifest_is_one_line(data: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (data / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista,extra\n")
    rc = main(["batch", "run", str(data / "m.csv"), "--out", str(data / "out")])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.count("\n") == 0 and "more cells than columns" in err
    rc = main(["batch", "status", str(data)])
    assert rc == 2
    assert "not a batch folder" in capsys.readouterr().err


def test_udn_item_without_a_spec_gets_the_recon_udn_spec(data: Path) -> None:
    """A ``udn`` row with only the simplest columns builds the spec ``recon udn`` would (the
    options not given take the spec's defaults; they used to arrive as None and fail)."""
    from app.batch.task import build_udn_spec

    (data / "m.csv").write_text("measurement,psf,method,iters\nmeas/m00.npy,psf.npy,udn,7\n")
    (item,) = read_manifest(data / "m.csv")
    spec, _ = build_udn_spec(item, threads=1)
    assert spec["stopping"]["max_iter"] == 7 and spec["device"]["threads"] == 1
    assert "time_limit_s" not in spec["stopping"]  # not given: the spec's default applies


def test_a_batch_folder_of_another_manifest_or_of_other_files_is_refused(data: Path,
                                                                        tmp_path: Path) -> None:
    """A second manifest run into a batch folder overwrote and orphaned the first batch's
    results; an --out that is the input folder read the batch's own files as measurements on
    the rerun. Both are refused before anything runs (no Ray is started)."""
    import json

    from app.batch.driver import _check_batch_folder, run_batch
    from app.batch.state import STATE_FORMAT

    for name in ("m1.csv", "m2.csv"):
        (data / name).write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    out = tmp_path / "b"
    out.mkdir()
    (out / "state.json").write_text(json.dumps({"format": STATE_FORMAT,
                                                "manifest": str((data / "m1.csv").resolve())}))
    with pytest.raises(ValueError, match=r"is the batch of .*m1\.csv; run that manifest"):
        run_batch(data / "m2.csv", out)
    with pytest.raises(ValueError, match="is not empty and holds no batch"):
        run_batch(data / "m1.csv", data / "meas")
    # an input inside the batch's own folder (a result fed back in) was retried three times
    own = tmp_path / "own"
    (own / "results").mkdir(parents=True)
    np.save(own / "results" / "x.npy", np.load(data / "meas" / "m00.npy"))
    (data / "m3.csv").write_text(f"measurement,psf,method\n{own / 'results' / 'x.npy'},"
                                 "psf.npy,fista\n")
    (own / "state.json").write_text(json.dumps({"format": STATE_FORMAT,
                                                "manifest": str((data / "m3.csv").resolve())}))
    with pytest.raises(ValueError, match=r"lies in the batch folder .* which the batch writes"):
        run_batch(data / "m3.csv", own)
    # what a driver stopped before its first state.json leaves is no obstacle
    left = tmp_path / "left"
    for d in ("items", "results", "runs"):
        (left / d).mkdir(parents=True)
    (left / "run.lock").write_text("")
    _check_batch_folder(left, (data / "m1.csv").resolve())


def test_ids_keep_letters_of_any_script_and_explicit_names_are_unique(data: Path) -> None:
    """Non-ASCII letters became _ (two frames 'ä frame' and 'ö frame' got _frame and _frame-2,
    renumbered when a third file sorted between them); two rows named alike were renamed."""
    import shutil

    for stem in ("ä frame", "ö frame"):
        shutil.copy(data / "meas" / "m00.npy", data / "meas" / f"{stem}.npy")
    (data / "m.csv").write_text("measurement,psf,method\nmeas/[äö] frame.npy,psf.npy,fista\n",
                                encoding="utf-8")
    assert [it.id for it in read_manifest(data / "m.csv")] == ["ä_frame-fista", "ö_frame-fista"]
    (data / "n.csv").write_text("measurement,psf,method,name\nmeas/m00.npy,psf.npy,fista,same\n"
                                "meas/m01.npy,psf.npy,fista,same\n")
    with pytest.raises(ValueError, match=r"n\.csv:3: name 'same' is given to another item too"):
        read_manifest(data / "n.csv")


def test_an_item_needing_more_cpus_than_the_embedded_ray_has_is_refused(data: Path,
                                                                        tmp_path: Path) -> None:
    """--num-cpus 1 --cpus-per-item 3 waited for ever."""
    from app.batch.driver import BatchOptions, run_batch

    (data / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    with pytest.raises(ValueError, match=r"an item needs 3 CPUs .* has 1: it would wait"):
        run_batch(data / "m.csv", tmp_path / "b", BatchOptions(num_cpus=1, cpus_per_item=3))
    assert not (tmp_path / "b").exists()


def test_true_false_columns_of_on_off_options_reach_the_spec(data: Path) -> None:
    """with_fista = false went on as '--with-fista false' ("unrecognized arguments: false");
    the on/off options (--with-fista / --no-with-fista, --channels-last) now take true/false
    as docs/batch.md says flags do, under either name."""
    from app.batch.task import build_udn_spec

    (data / "m.csv").write_text(
        "measurement,psf,method,iters,with_fista,channels_last\n"
        "meas/m00.npy,psf.npy,udn,7,false,true\nmeas/m01.npy,psf.npy,udn,7,true,false\n")
    off, on = read_manifest(data / "m.csv")
    assert "--no-with-fista" in off.argv and "--channels-last" in off.argv
    assert "--with-fista" in on.argv and "--no-channels-last" in on.argv
    assert build_udn_spec(off, threads=1)[0]["output"]["with_fista"] is False
    assert build_udn_spec(on, threads=1)[0]["output"]["with_fista"] is True
    (data / "n.csv").write_text("measurement,psf,method,no_with_fista\n"
                                "meas/m00.npy,psf.npy,udn,true\n")
    (item,) = read_manifest(data / "n.csv")
    assert build_udn_spec(item, threads=1)[0]["output"]["with_fista"] is False
    (data / "t.toml").write_text('[defaults]\nmethod = "udn"\npsf = "psf.npy"\n'
                                 'with_fista = false\n\n[[item]]\nmeasurement = "meas/m00.npy"\n')
    (item,) = read_manifest(data / "t.toml")
    assert build_udn_spec(item, threads=1)[0]["output"]["with_fista"] is False
    # both names in one row: the last won without a word
    (data / "b.csv").write_text("measurement,psf,method,with_fista,no_with_fista\n"
                                "meas/m00.npy,psf.npy,udn,true,true\n")
    with pytest.raises(ValueError, match=r"b\.csv:2: columns 'with_fista' and 'no_with_fista' "
                       r"both set --with-fista"):
        read_manifest(data / "b.csv")
    # an option with an optional value: compile = true is --compile ('invalid choice: true')
    (data / "c.csv").write_text("measurement,psf,method,compile\n"
                                "meas/m00.npy,psf.npy,udn,true\nmeas/m01.npy,psf.npy,udn,false\n"
                                "meas/m02.npy,psf.npy,udn,reduce-overhead\n")
    on, off, mode = read_manifest(data / "c.csv")
    assert "--compile" in on.argv and "--compile" not in off.argv
    assert mode.argv[mode.argv.index("--compile") + 1] == "reduce-overhead"
