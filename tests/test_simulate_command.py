"""``lenslesscam simulate``: what it tells about the scene, and a save that is whole or absent."""

from __future__ import annotations

import errno
import hashlib
import json
import os

import numpy as np
import pytest

from recon.simulate import synthetic_psf
from tests.clirun import run_cli as _run


@pytest.fixture
def case(tmp_path):
    """A 24x32 PSF and a scene of the sensor's shape."""
    np.save(tmp_path / "psf.npy", synthetic_psf((24, 32), seed=2))
    np.save(tmp_path / "scene.npy",
            np.random.default_rng(0).random((24, 32)).astype(np.float32))
    return tmp_path


def _sim(case, *extra, scene="scene.npy", out="sim"):
    return ("simulate", "--psf", case / "psf.npy", "--scene", case / scene,
            "--out", case / out, *extra)


def _tree(folder):
    """{relative path: sha256} of every file under ``folder``."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _debris(parent):
    """Hidden staging folders a save left in ``parent`` or in its ``sim`` folder."""
    found = [p for p in parent.iterdir() if p.name.startswith((".sim.", ".partial-"))]
    if (parent / "sim").is_dir():
        found += [p for p in (parent / "sim").iterdir() if p.name.startswith(".partial-")]
    return sorted(p.name for p in found)


# --------------------------------------------------------------------------------------------
# 1. a scene of another shape is resized, and the user is told
# --------------------------------------------------------------------------------------------


def test_a_scene_of_another_shape_is_resized_and_said(case, capsys):
    """A 10x12 scene on a 24x32 sensor was stretched silently; now one line on stderr names
    both shapes, the method and the changed aspect ratio, and simulation.json records it."""
    np.save(case / "small.npy", np.random.default_rng(1).random((10, 12)))
    code, _, err = _run(capsys, *_sim(case, scene="small.npy"))
    assert code == 0, err
    notes = [ln for ln in err.splitlines() if "note:" in ln]
    assert len(notes) == 1, err
    line = notes[0]
    assert "10x12" in line and "24x32" in line and "INTER_AREA" in line
    assert "aspect ratio" in line and "stretched" in line and "not cropped" in line
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    assert meta["scene_resized_from"] == [10, 12]
    assert meta["scene_resize_method"].startswith("OpenCV INTER_AREA")
    assert meta["scene_stretched"] is True
    assert meta["notes"] == [line.split("note: ", 1)[1]]
    assert np.load(case / "sim" / "truth.npy").shape == (1, 1, 24, 32)


def test_a_scene_of_the_same_aspect_is_resized_without_stretching(case, capsys):
    """48x64 -> 24x32: resized (said), the aspect ratio kept (no 'stretched')."""
    np.save(case / "big.npy", np.random.default_rng(1).random((48, 64)))
    code, _, err = _run(capsys, *_sim(case, scene="big.npy"))
    assert code == 0, err
    assert "48x64" in err and "24x32" in err and "stretched" not in err
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    assert meta["scene_resized_from"] == [48, 64] and meta["scene_stretched"] is False


def test_a_small_stretch_along_one_axis_is_named(case, capsys):
    """24x33 -> 24x32: the rows keep their count, the columns are squeezed by 3 %; a rule
    that needed both axes off by a pixel called it unstretched."""
    np.save(case / "wide.npy", np.random.default_rng(2).random((24, 33)))
    code, _, err = _run(capsys, *_sim(case, scene="wide.npy"))
    assert code == 0, err
    assert "stretched" in err
    assert json.loads((case / "sim" / "simulation.json").read_text())["scene_stretched"]


def test_a_colour_scene_made_gray_is_said(case, capsys):
    np.save(case / "rgb.npy", np.random.default_rng(3).random((24, 32, 3)))
    code, _, err = _run(capsys, *_sim(case, scene="rgb.npy"))
    assert code == 0, err
    assert "3 colour channels: made gray" in err
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    assert any("made gray" in n for n in meta["notes"])


def test_a_scene_of_the_sensor_shape_gets_no_note(case, capsys):
    code, _, err = _run(capsys, *_sim(case))
    assert code == 0, err
    assert "note:" not in err
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    assert meta["scene_resized_from"] is None and meta["scene_shape"] == [24, 32]
    assert meta["scene_dtype"] == "float32" and meta["notes"] == []
    assert meta["scene_frames"] == 1  # a (9, H, W) video scene recorded only its H, W


def test_a_video_scene_records_its_frames(case, capsys):
    k = 3
    np.save(case / "shutter.npy", np.ones((k, 24), np.float32) / k)
    np.save(case / "frames.npy", np.random.default_rng(1).random((k, 24, 32)).astype(np.float32))
    code, _, err = _run(capsys, *_sim(case, "--model", "video", "--shutter",
                                      case / "shutter.npy", scene="frames.npy"))
    assert code == 0, err
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    assert meta["scene_shape"] == [24, 32] and meta["scene_frames"] == k


# --------------------------------------------------------------------------------------------
# 2. the save is whole or absent
# --------------------------------------------------------------------------------------------


def _fail_at_save(monkeypatch, n_ok, exc):
    """Let ``n_ok`` calls of np.save through, then raise ``exc`` (a save cut short)."""
    real = np.save
    calls = {"n": 0}

    def save(*a, **k):
        calls["n"] += 1
        if calls["n"] > n_ok:
            raise exc
        return real(*a, **k)

    monkeypatch.setattr(np, "save", save)
    return calls


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), OSError(errno.ENOSPC, "No space left")],
                         ids=["ctrl-c", "disk-full"])
def test_a_save_cut_short_leaves_no_output_folder(case, capsys, monkeypatch, exc):
    """Ctrl-C (or a full disk) after two of the files left sim/ with meas.npy and truth.npy
    and no simulation.json; now there is no sim/ and no hidden partial folder."""
    calls = _fail_at_save(monkeypatch, 2, exc)
    code, _, err = _run(capsys, *_sim(case))
    assert calls["n"] == 3
    assert code == (130 if isinstance(exc, KeyboardInterrupt) else 2), err
    assert not (case / "sim").exists()
    assert _debris(case) == []
    monkeypatch.undo()
    code, _, err = _run(capsys, *_sim(case))  # the rerun: nothing in its way
    assert code == 0, err


def test_a_failed_overwrite_leaves_the_old_folder_intact(case, capsys, monkeypatch):
    """--overwrite over an earlier simulation, cut short: the earlier folder (and a
    reconstruction saved in it) is byte for byte what it was."""
    code, _, err = _run(capsys, *_sim(case, "--noise", "0.01"))
    assert code == 0, err
    (case / "sim" / "recon.tif").write_bytes(b"a reconstruction")
    before = _tree(case / "sim")
    _fail_at_save(monkeypatch, 3, KeyboardInterrupt())
    code, _, _ = _run(capsys, *_sim(case, "--noise", "0.05", "--seed", "3", "--overwrite"))
    assert code == 130
    assert _tree(case / "sim") == before
    assert _debris(case) == []


def test_an_overwrite_replaces_its_files_and_keeps_the_others(case, capsys):
    """The new simulation replaces the old one's files; a file simulate did not write (a
    reconstruction, the user's own filters.npy) stays, an output of the earlier simulate
    that this model does not write (its shutter.npy) goes."""
    code, _, err = _run(capsys, *_sim(case, "--noise", "0.01"))
    assert code == 0, err
    (case / "sim" / "recon.tif").write_bytes(b"a reconstruction")
    (case / "sim" / "runs").mkdir()
    (case / "sim" / "runs" / "r.json").write_text("{}")
    np.save(case / "sim" / "shutter.npy", np.ones((2, 24), np.float32))
    np.save(case / "sim" / "filters.npy", np.ones((2, 24, 32), np.float32))  # the user's
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    meta["files"]["shutter"] = "shutter.npy"  # as an earlier video simulation lists it
    (case / "sim" / "simulation.json").write_text(json.dumps(meta))
    old_meas = np.load(case / "sim" / "meas.npy")
    code, _, err = _run(capsys, *_sim(case, "--noise", "0.05", "--seed", "3", "--overwrite"))
    assert code == 0, err
    names = sorted(p.name for p in (case / "sim").iterdir())
    assert names == ["filters.npy", "mask.npy", "meas.npy", "psf.npy", "recon.tif", "runs",
                     "simulation.json", "truth.npy"]
    assert (case / "sim" / "recon.tif").read_bytes() == b"a reconstruction"
    assert (case / "sim" / "runs" / "r.json").read_text() == "{}"
    assert np.array_equal(np.load(case / "sim" / "filters.npy"), np.ones((2, 24, 32)))
    assert not np.array_equal(np.load(case / "sim" / "meas.npy"), old_meas)
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    assert meta["params"]["noise"] == 0.05
    assert _debris(case) == []


def test_the_current_folder_and_a_read_only_parent_are_written_whole(case, capsys,
                                                                    monkeypatch):
    """`--out .` could not be renamed (EBUSY after all the work), `--out $PWD` swapped the
    shell's folder for a new one, and a folder in a parent that cannot be written was written
    file by file, with a note. The files are now staged inside the folder: all three are
    written whole, with no note, and the folder itself stays (the shell's folder)."""
    import tempfile

    sim = case / "sim"
    sim.mkdir()
    (sim / "notes.txt").write_text("mine")
    monkeypatch.chdir(sim)
    real = tempfile.mkdtemp

    def refuse_in_parent(*a, **kw):
        if str(kw.get("dir", "")) == str(case):
            raise PermissionError(errno.EACCES, "Permission denied")
        return real(*a, **kw)

    monkeypatch.setattr(tempfile, "mkdtemp", refuse_in_parent)
    inode = sim.stat().st_ino
    old = None
    for seed, out in (("1", "."), ("2", str(sim))):
        code, _, err = _run(capsys, "simulate", "--psf", case / "psf.npy", "--scene",
                            case / "scene.npy", "--out", out, "--overwrite", "--seed", seed,
                            "--noise", "0.05")
        assert code == 0, err
        assert "note" not in err, err
        assert os.getcwd() == str(sim) and sim.stat().st_ino == inode
        meas = np.load(sim / "meas.npy")
        assert old is None or not np.array_equal(meas, old)
        old = meas
        assert (sim / "notes.txt").read_text() == "mine"
    assert _debris(case) == []


def test_other_entries_of_the_folder_are_never_moved_or_copied(case, capsys):
    """`simulate --out DIR --overwrite` swapped DIR for a new folder holding links to its
    other entries: files another process wrote into DIR (a run folder inside it) between the
    copy and the swap were lost. The other entries are now left where they are."""
    code, _, err = _run(capsys, *_sim(case))
    assert code == 0, err
    runs = case / "sim" / "runs"
    runs.mkdir()
    (runs / "checkpoint.pt").write_bytes(b"weights")
    before = (runs.stat().st_ino, (runs / "checkpoint.pt").stat().st_ino,
              (case / "sim").stat().st_ino)
    code, _, err = _run(capsys, *_sim(case, "--seed", "9", "--overwrite"))
    assert code == 0, err
    after = (runs.stat().st_ino, (runs / "checkpoint.pt").stat().st_ino,
             (case / "sim").stat().st_ino)
    assert after == before  # the same folder, the same files: nothing moved or copied
    assert json.loads((case / "sim" / "simulation.json").read_text())["params"]["seed"] == 9


def test_an_existing_output_still_needs_overwrite(case, capsys):
    code, _, err = _run(capsys, *_sim(case))
    assert code == 0, err
    before = _tree(case / "sim")
    code, _, err = _run(capsys, *_sim(case, "--seed", "4"))
    assert code == 2 and "pass --overwrite" in err
    assert _tree(case / "sim") == before


def test_atomic_files_unit(tmp_path):
    """The helper alone: a new folder gets the set whole, with the process's default
    permissions; an exception removes the staging folder (and a folder it made); files of an
    earlier set it owns are removed, the record is moved in last, others stay; a symlinked
    folder is written through the link."""
    from recon.atomic import atomic_files

    with atomic_files(tmp_path / "a") as tmp:
        assert tmp.parent == tmp_path / "a" and tmp.name.startswith(f".partial-{os.getpid()}-")
        (tmp / "x").write_text("1")
        assert not (tmp_path / "a" / "x").exists()
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["x"]
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "a").stat().st_mode & 0o777 == 0o777 & ~mask
    with pytest.raises(RuntimeError), atomic_files(tmp_path / "b") as tmp:
        (tmp / "x").write_text("1")
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]
    with pytest.raises(RuntimeError), atomic_files(tmp_path / "a", owned=["x"]) as tmp:
        (tmp / "y").write_text("2")
        raise RuntimeError("boom")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["x"]  # as it was
    (tmp_path / "a" / "mine").write_text("3")
    (tmp_path / "link").symlink_to(tmp_path / "a")
    order = []
    real_replace = os.replace

    def replace(src, dst):
        order.append(os.path.basename(dst))
        real_replace(src, dst)

    import unittest.mock

    with unittest.mock.patch("os.replace", replace), \
            atomic_files(tmp_path / "link", owned=["x", "rec"], last=["rec"]) as tmp:
        for name in ("rec", "y", "z"):
            (tmp / name).write_text(name)
    assert order == ["y", "z", "rec"]  # the record last
    assert (tmp_path / "link").is_symlink()
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["mine", "rec", "y", "z"]


# --------------------------------------------------------------------------------------------
# 3. a boolean scene
# --------------------------------------------------------------------------------------------


def test_a_boolean_scene_is_read_as_zero_one_and_said(case, capsys):
    """Decision: a binary target (a resolution chart) is a legitimate scene, reflectance 0/1,
    as the truth reader reads it; a boolean *measurement* is refused because a sensor frame
    is counts, never True/False. The old code took the bool silently; now it is said in one
    line and recorded (scene_dtype, notes)."""
    target = np.zeros((24, 32), dtype=bool)
    target[4:20, 6:10] = True
    target[4:8, 10:26] = True
    np.save(case / "target.npy", target)
    code, _, err = _run(capsys, *_sim(case, scene="target.npy"))
    assert code == 0, err
    notes = [ln for ln in err.splitlines() if "note:" in ln]
    assert len(notes) == 1 and "boolean" in notes[0] and "0/1" in notes[0], err
    truth = np.load(case / "sim" / "truth.npy")
    assert truth.dtype == np.float32
    assert set(np.unique(truth).tolist()) == {0.0, 1.0}
    assert np.array_equal(truth[0, 0] == 1.0, target)
    meta = json.loads((case / "sim" / "simulation.json").read_text())
    assert meta["scene_dtype"] == "bool" and "boolean" in meta["notes"][0]
    # the measurement rule stays: a boolean measurement is refused
    np.save(case / "bmeas.npy", target)
    code, _, err = _run(capsys, "recon", "fista", "--psf", case / "psf.npy", "--meas",
                        case / "bmeas.npy", "--iters", "2", "--out", case / "r.tif")
    assert code == 2 and "unsupported dtype bool" in err


def test_dark_with_the_bundled_psf_is_refused(tmp_path, capsys):
    """`--psf sample:tutorial --dark 1e9` was ignored silently (the bundled PSF is
    dark-subtracted already); with a PSF file the same option is applied."""
    code, _, err = _run(capsys, "simulate", "--psf", "sample:tutorial", "--scene",
                        "sample:im65", "--dark", "1e9", "--out", tmp_path / "sim")
    assert code == 2 and "has its dark level (34.08) removed already" in err
    assert not (tmp_path / "sim").exists()


def test_atomic_files_checks_before_the_first_rename(tmp_path):
    """(diff review) A staged file onto a folder, or a staged folder, failed in the middle of
    the renames: some files new, the record old, the rest of the set deleted. Both are now
    refused before any rename, the folder as it was; parents made for a failed set go too."""
    from recon.atomic import atomic_files

    out = tmp_path / "sim"
    with atomic_files(out, last=["rec"]) as tmp:
        for name in ("a", "b", "rec"):
            (tmp / name).write_text("old")
    (out / "b").unlink()
    (out / "b").mkdir()  # a folder where the set writes a file
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(IsADirectoryError, match="never replaced"), \
            atomic_files(out, last=["rec"]) as tmp:
        for name in ("a", "b", "rec"):
            (tmp / name).write_text("new")
    assert sorted(p.name for p in out.iterdir()) == before
    assert (out / "a").read_text() == "old" and (out / "rec").read_text() == "old"
    with pytest.raises(ValueError, match="not a file"), atomic_files(out) as tmp:
        (tmp / "a").write_text("new")
        (tmp / "sub").mkdir()
    assert (out / "a").read_text() == "old"
    # an owned name that is a folder is left, not an error
    with atomic_files(out, owned=["b"], last=["rec"]) as tmp:
        (tmp / "rec").write_text("new")
    assert (out / "b").is_dir() and (out / "rec").read_text() == "new"
    deep = tmp_path / "x" / "y" / "z"
    with pytest.raises(RuntimeError), atomic_files(deep) as tmp:
        raise RuntimeError("boom")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("bands", [3, 5])
def test_a_spectral_scene_with_its_bands_last_keeps_them(tmp_path, capsys, bands):
    """(spectral/depth review) An (H, W, K) spectral scene with 3 or 4 bands was made gray and
    copied into every band (truth.npy with K equal bands); with 5 it failed as "has 32
    frames"."""
    np.save(tmp_path / "psf.npy", synthetic_psf((32, 40), seed=1))
    rng = np.random.default_rng(0)
    np.save(tmp_path / "f.npy", rng.random((bands, 32, 40)).astype(np.float32))
    scene = np.zeros((32, 40, bands), np.float32)
    for k in range(bands):
        scene[4 + 5 * k : 8 + 5 * k, 5:35, k] = 1.0
    np.save(tmp_path / "s.npy", scene)
    code, _, err = _run(capsys, "simulate", "--model", "spectral", "--psf", tmp_path / "psf.npy",
                        "--filters", tmp_path / "f.npy", "--scene", tmp_path / "s.npy",
                        "--out", tmp_path / "sim")
    assert code == 0, err
    assert f"its last axis read as the model's K = {bands}" in err
    truth = np.load(tmp_path / "sim" / "truth.npy")
    np.testing.assert_array_equal(truth[0], np.moveaxis(scene, -1, 0))
