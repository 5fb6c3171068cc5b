"""The calibration wizard's runs, saves and settings: what a review found and what it now does.

A Finish during a strobe scan left it running out of reach; saves replaced files of the same
second; the shutter function took its own path (other bins, no checks, no metadata); the
output folder was checked only at the save (and stored relative); pulses off the source's
grid were sent rounded; a cancelled re-capture forgot the saved PSF; a cancel said "failed";
reopening lost what was typed; an emptied intensity box became 0.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QWizard

pytestmark = pytest.mark.gui


def _open(w: Any, qtbot: Any, out: Path, *, frames: int = 4) -> Any:
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    wiz = w.open_calibration_wizard()
    wiz.setup_page.out_dir.setText(str(out))
    wiz.setup_page.n_frames.setValue(frames)
    wiz.setup_page.n_darks.setValue(frames)
    return wiz


def _button(wiz: Any, which: str) -> Any:
    return wiz.button(getattr(QWizard.WizardButton, which))


def _shutter(qtbot: Any, sp: Any) -> Any:
    """Run the shutter page's timing-model path to its end."""
    sp.method.setCurrentIndex(sp.method.findData("timing"))
    sp.box.start.click()
    qtbot.waitUntil(sp.box.start.isEnabled, timeout=20_000)  # the run ended
    return sp.result


def _type(qtbot: Any, box: Any, text: str) -> None:
    box.setFocus()
    edit = box.lineEdit()
    edit.selectAll()
    qtbot.keyClick(edit, Qt.Key.Key_Backspace)
    if text:
        qtbot.keyClicks(edit, text)
    box.interpretText()  # the edit ends (as on Return or leaving the box): Qt corrects it


# 1 -------------------------------------------------------------------------------------------

def test_a_running_scan_holds_its_page_and_finish_cancels_it(
        bench_window: Any, qtbot: Any, tmp_path: Path) -> None:
    """Next was enabled during a strobe scan; Finish closed the wizard with the scan still
    running (camera "calibrating", Devices locked) and a new wizard that could not reach it."""
    w = bench_window
    wiz = _open(w, qtbot, tmp_path / "cal")
    wiz.next()
    wiz.next()  # the PSF is optional to reach the shutter page from code
    sp = wiz.shutter_page
    assert wiz.currentPage() is sp
    sp.method.setCurrentIndex(sp.method.findData("measured"))
    sp.box.start.click()
    qtbot.waitUntil(lambda: sp.box.progress.value() > 0, timeout=10_000)
    assert not _button(wiz, "NextButton").isEnabled()
    assert not _button(wiz, "BackButton").isEnabled()
    assert sp.running and not sp.isComplete()
    wiz.next()
    wiz.back()
    assert wiz.currentPage() is sp  # neither way while it runs
    wiz.accept()  # Finish (or closing): the run is cancelled, never orphaned
    qtbot.waitUntil(sp.box.start.isEnabled, timeout=10_000)
    assert sp.box.stage.text().startswith("cancelled")
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    assert w.bench.light.is_on is False
    assert w.open_calibration_wizard() is wiz  # one wizard per window
    qtbot.waitUntil(lambda: _button(wiz, "NextButton").isEnabled(), timeout=10_000)


# 2 -------------------------------------------------------------------------------------------

def test_saves_never_replace_a_file(bench_window: Any, qtbot: Any, tmp_path: Path,
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Names were unique to the second and the write replaced whatever had the name: 6 quick
    saves left 2 files, and a user's file of that name was gone."""
    import app.gui.calibration_wizard as cw
    from recon.calibfile import load_shutter

    monkeypatch.setattr(cw, "_stamp", lambda: "20260101-120000")  # every save in one second
    w = bench_window
    out = tmp_path / "cal"
    out.mkdir()
    theirs = out / "shutter-20260101-120000.npz"
    theirs.write_bytes(b"someone's data")
    wiz = _open(w, qtbot, out)
    sp = wiz.shutter_page
    saved = []
    for width in (250, 300, 350):
        sp.bin_lines.setValue(width)
        _shutter(qtbot, sp)
        assert sp.save() is not None
        saved.append(sp.saved_path)
        qtbot.waitUntil(lambda: w.camera_state.ready, timeout=10_000)
    assert theirs.read_bytes() == b"someone's data"
    assert [p.name for p in saved] == ["shutter-20260101-120000-2.npz",
                                       "shutter-20260101-120000-3.npz",
                                       "shutter-20260101-120000-4.npz"]
    assert [load_shutter(p)[1]["bin_lines"] for p in saved] == [250, 300, 350]
    assert sorted(p.name for p in out.iterdir()) == sorted([theirs.name, *(p.name for p in
                                                                            saved)])


def test_write_new_claims_a_free_name_with_or_without_hard_links(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The preview's PSF (or any file) under the chosen name is never the one written."""
    from recon.atomic import write_new

    def save(path: Path) -> Path:
        path.write_bytes(b"new")
        return path

    preview_psf = tmp_path / "psf-1.tif"
    preview_psf.write_bytes(b"the preview's PSF")
    assert write_new(save, tmp_path, "psf-1", ".tif") == tmp_path / "psf-1-2.tif"

    def no_links(src: Any, dst: Any) -> None:
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_links)  # a file system without hard links
    assert write_new(save, tmp_path, "psf-1", ".tif") == tmp_path / "psf-1-3.tif"
    assert preview_psf.read_bytes() == b"the preview's PSF"
    assert (tmp_path / "psf-1-2.tif").read_bytes() == (tmp_path / "psf-1-3.tif").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["psf-1-2.tif", "psf-1-3.tif",
                                                          "psf-1.tif"]  # no temporary left
    # (diff review) the file has a plain open()'s permissions, not mkstemp's 0600
    old = os.umask(0o022)
    try:
        made = write_new(save, tmp_path, "perm", ".tif")
    finally:
        os.umask(old)
    assert made.stat().st_mode & 0o777 == 0o644
    # a failed move in the no-link fallback leaves no empty file under the final name
    monkeypatch.setattr(os, "replace", lambda a, b: (_ for _ in ()).throw(OSError("disk")))
    with pytest.raises(OSError, match="disk"):
        write_new(save, tmp_path, "gone", ".tif")
    assert not (tmp_path / "gone.tif").exists()


# 3 -------------------------------------------------------------------------------------------

def test_the_shutter_takes_the_clis_path_defaults_checks_and_metadata(
        bench_window: Any, qtbot: Any, tmp_path: Path) -> None:
    """The wizard defaulted to 100-line bins (11 where the CLI makes 135), saved 1-line bins
    that recon refuses (1074 bins for 150 rows), and left the camera out of the file."""
    from recon.calibfile import load_shutter

    w = bench_window
    wiz = _open(w, qtbot, tmp_path / "cal")
    sp = wiz.shutter_page
    assert sp.bin_lines.text() == "auto"
    from calibration.shutter import shutter_model
    sf = _shutter(qtbot, sp)
    assert sf is not None, sp.box.stage.text()
    cli = shutter_model(w.last_frame)  # what `calibrate shutter` chooses without --bin-lines
    assert sf.bin_lines == cli.bin_lines
    assert np.array_equal(sf.shutter, cli.shutter)
    k, rows = sf.shutter.shape
    assert rows // 2 < k <= rows
    _, md = load_shutter(sp.save())
    assert md["camera"]["backend"] == w.bench.camera.backend and md["method"] == "timing"
    before = sorted((tmp_path / "cal").iterdir())
    qtbot.waitUntil(lambda: w.camera_state.ready, timeout=10_000)
    sp.bin_lines.setValue(1)  # more bins than rows: refused before anything is made
    sp.box.start.click()
    qtbot.waitUntil(sp.box.start.isEnabled, timeout=20_000)
    assert sp.result is None
    assert "time bins for 150 rows" in sp.box.stage.text()
    assert sorted((tmp_path / "cal").iterdir()) == before


# 4 -------------------------------------------------------------------------------------------

def test_the_output_folder_is_checked_before_any_capture_and_stored_absolute(
        bench_window: Any, qtbot: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An empty folder saved into the working folder, a relative one was stored relative (the
    PSF was lost in the next session), a file or unwritable one failed only at the save."""
    w = bench_window
    wiz = _open(w, qtbot, tmp_path / "cal")
    setup = wiz.setup_page
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    cases = {"": "name an output folder",
             str(a_file): f"output folder {a_file} is a file, not a folder",
             str(a_file / "cal"): f"output folder {a_file / 'cal'}: {a_file} is a file, not a "
                                  "folder"}
    for text, line in cases.items():
        setup.out_dir.setText(text)
        assert not setup.isComplete()
        assert setup.out_error.text() == line
        wiz.next()
        assert wiz.currentPage() is setup
    setup.out_dir.setText("/sys/kernel/lenslesscam-cal")  # read-only, for root too
    wiz.next()
    assert wiz.currentPage() is setup
    assert "is not writable" in setup.out_error.text()
    assert "\n" not in setup.out_error.text()
    monkeypatch.chdir(tmp_path)
    setup.out_dir.setText("relcal")
    assert setup.isComplete() and setup.out_error.text() == ""
    wiz.next()
    assert wiz.currentPage() is wiz.psf_page
    assert setup.out_dir.text() == str(tmp_path / "relcal")
    assert w.settings.calibration_dir == str(tmp_path / "relcal")


# 5 -------------------------------------------------------------------------------------------

def test_strobe_times_are_on_the_sources_grid_by_the_clis_rule(
        bench_window: Any, qtbot: Any, tmp_path: Path) -> None:
    """A 0.05 us pulse started a 1975-delay scan, sent as 0.1 us and analysed as 0.05."""
    wiz = _open(bench_window, qtbot, tmp_path / "cal")
    sp = wiz.shutter_page
    for box in (sp.pulse, sp.step):
        assert box.decimals() == 1 and box.singleStep() == pytest.approx(0.1)
        assert box.text() == "auto"
    assert sp.shutter_settings().pulse_us is None and sp.shutter_settings().step_us is None
    _type(qtbot, sp.pulse, "0.26")
    _type(qtbot, sp.step, "0.04")  # below one step of the source: "auto", not 0.04
    s = sp.shutter_settings()
    assert s.pulse_us == pytest.approx(0.3) and s.step_us is None
    # the one rule, in the CLI's words
    from calibration import strobe_time

    assert strobe_time(0.26, "--pulse 0.26us") == (
        pytest.approx(0.3), "--pulse 0.26us is rounded to 0.3 us, the point source's 0.1 us "
        "resolution")
    with pytest.raises(ValueError, match=r"in steps of 0\.1 us; use 0\.1us or more"):
        strobe_time(0.04, "strobe pulse 0.04 us")


# 6 -------------------------------------------------------------------------------------------

def test_a_cancelled_recapture_keeps_the_saved_psf(
        bench_window: Any, qtbot: Any, tmp_path: Path) -> None:
    """A re-capture cleared the saved PSF at its start: cancelled, Next stayed off and Finish
    said "nothing saved" (and did not give the preview the saved PSF)."""
    w = bench_window
    wiz = _open(w, qtbot, tmp_path / "cal")
    wiz.next()
    page = wiz.psf_page
    page.box.start.click()
    qtbot.waitUntil(page.box.start.isEnabled, timeout=60_000)
    assert page.result is not None, page.box.stage.text()
    saved = page.save()
    assert saved is not None and page.isComplete()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    wiz.setup_page.n_darks.setValue(200)
    page.box.start.click()
    qtbot.waitUntil(lambda: page.box.progress.value() > 0, timeout=10_000)
    assert not page.isComplete()  # while it runs
    page.box.cancel.click()
    qtbot.waitUntil(page.box.start.isEnabled, timeout=10_000)
    assert page.saved_path == saved and page.isComplete()
    assert _button(wiz, "NextButton").isEnabled()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    wiz.next()
    wiz.next()
    assert str(saved) in wiz.finish_page.summary.text()
    wiz.accept()
    assert w.settings.psf_path == str(saved)
    assert saved.name in w.psf_source


# 7 -------------------------------------------------------------------------------------------

def test_a_cancel_says_cancelled_not_failed(
        bench_window: Any, qtbot: Any, tmp_path: Path) -> None:
    """The shutter page said "failed: shutter cancelled ..."; the PSF page said "refused /
    failed" for the worker's cancel when the main window closed mid-capture."""
    from app.gui.workers import Cancelled

    w = bench_window
    wiz = _open(w, qtbot, tmp_path / "cal")
    sp = wiz.shutter_page
    sp.method.setCurrentIndex(sp.method.findData("measured"))
    sp.box.start.click()
    qtbot.waitUntil(lambda: sp.box.progress.value() > 0, timeout=10_000)
    sp.box.cancel.click()
    qtbot.waitUntil(sp.box.start.isEnabled, timeout=10_000)
    assert sp.box.stage.text().startswith("cancelled: "), sp.box.stage.text()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    wiz.psf_page._failed(Cancelled("PSF capture: cancelled"))  # the worker's, at shutdown
    assert wiz.psf_page.box.stage.text() == "cancelled: PSF capture: cancelled"


# 8 -------------------------------------------------------------------------------------------

def test_the_reopened_wizard_is_the_same_one_with_what_was_typed(
        live_window: Any, qtbot: Any, tmp_path: Path) -> None:
    """Each reopening made a new wizard (the old ones stayed alive) with the defaults back."""
    from app.gui.calibration_wizard import CalibrationWizard

    w = live_window
    wiz = w.open_calibration_wizard()
    wiz.setup_page.out_dir.setText(str(tmp_path / "mine"))
    wiz.setup_page.n_frames.setValue(5)
    wiz.setup_page.intensity.setValue(0.5)
    wiz.shutter_page.bin_lines.setValue(40)
    wiz.reject()
    assert not wiz.isVisible()
    again = w.open_calibration_wizard()
    assert again is wiz and again.currentPage() is again.setup_page
    assert again.setup_page.out_dir.text() == str(tmp_path / "mine")
    assert again.setup_page.n_frames.value() == 5
    assert again.setup_page.intensity.value() == pytest.approx(0.5)
    assert again.shutter_page.bin_lines.value() == 40
    again.close()
    w.open_calibration_wizard().close()
    assert len(w.findChildren(CalibrationWizard)) == 1


# 9 -------------------------------------------------------------------------------------------

def test_the_source_intensity_is_above_zero_and_junk_keeps_the_value(
        live_window: Any, qtbot: Any) -> None:
    """An emptied or junk box became 0.00, and a PSF capture at 0 can only fail."""
    box = live_window.open_calibration_wizard().setup_page.intensity
    assert box.minimum() > 0
    box.setValue(0.5)
    for junk in ("", "abc", "nan"):
        _type(qtbot, box, junk)
        assert box.value() == pytest.approx(0.5), junk
    _type(qtbot, box, "0")
    assert box.value() == pytest.approx(box.minimum())
    _type(qtbot, box, "0.7")
    assert box.value() == pytest.approx(0.7)
