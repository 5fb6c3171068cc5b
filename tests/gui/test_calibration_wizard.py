"""The calibration wizard with the simulated camera and point source (firmware on a PTY)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.gui


def test_wizard_captures_psf_and_shutter_saves_and_feeds_the_preview(
    bench_window: Any, qtbot: Any, tmp_path: Path
) -> None:
    pass
    from recon.calibfile import load_psf_calibration, load_shutter

    w = bench_window
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    wiz = w.open_calibration_wizard()
    setup = wiz.setup_page
    assert setup.isComplete()
    setup.out_dir.setText(str(tmp_path / "cal"))
    setup.n_frames.setValue(4)
    setup.n_darks.setValue(4)
    wiz.next()
    page = wiz.psf_page
    assert not page.isComplete()
    progress: list[float] = []
    page.box.progress.valueChanged.connect(progress.append)
    page.box.start.click()
    qtbot.waitUntil(lambda: w.camera_state == "calibrating", timeout=5_000)
    qtbot.waitUntil(lambda: page.result is not None or page.error != "", timeout=60_000)
    assert page.error == ""
    assert len(progress) > 5 and max(progress) == 1000
    q = page.result.quality
    assert q.saturated_pixels == 0 and q.snr > 10
    assert 0.65 <= q.peak_fraction <= 0.85
    assert page.box.image.image.shape == (150, 200)
    # the captured PSF is the simulator's true PSF (the scene was hidden meanwhile)
    truth = w.bench.sim_psf
    corr = np.corrcoef(page.result.normalised().ravel(), truth.ravel())[0, 1]
    assert corr > 0.8  # 4 noisy frames of a wide, dim caustic
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    assert w.bench.camera.scene is not None  # restored
    # every control shows what the camera runs at after the auto-exposure (and remembers it)
    cam_us = page.result.exposure_us
    assert abs(cam_us - 10_000.0) > 50  # auto-exposure moved it off the set 10 ms
    qtbot.waitUntil(lambda: abs(w.camera_controls.exposure.value() * 1000 - cam_us) < 1.0,
                    timeout=10_000)
    assert w.settings.exposure_us == pytest.approx(cam_us, abs=1.0)
    assert w.bench.camera.exposure_us == pytest.approx(cam_us, abs=1.0)
    # the PSF auto-levelled to its own range (not the darks' levels), a formatted report
    lo, hi = page.box.image.levels
    assert hi == pytest.approx(float(page.result.psf.max()), rel=1e-4)
    assert lo == pytest.approx(float(page.result.psf.min()), rel=1e-4, abs=1e-3)
    report = page.box.report.toPlainText()
    assert "peak" in report and "SNR" in report and "{" not in report
    page.box.save.click()
    assert page.isComplete() and page.saved_path is not None
    psf, meta = load_psf_calibration(page.saved_path)
    assert psf.shape == (150, 200) and meta["quality"]["saturated_pixels"] == 0

    wiz.next()
    sp = wiz.shutter_page
    sp.bin_lines.setValue(250)
    sp.box.start.click()
    qtbot.waitUntil(lambda: sp.result is not None, timeout=20_000)
    assert sp.result.shutter.shape[1] == 150
    # the shutter function as an image on axes (time across, rows down), a formatted report
    assert sp.box.plot.isVisible() and not sp.box.image.isVisible()
    item = sp.box.plot.getPlotItem()
    assert "time" in item.getAxis("bottom").labelText
    assert "row" in item.getAxis("left").labelText
    rect = sp.box.plot_image.mapRectToParent(sp.box.plot_image.boundingRect())
    k = sp.result.shutter.shape[0]
    assert rect.width() == pytest.approx(k * sp.result.bin_us, rel=1e-6)
    assert rect.height() == pytest.approx(150, rel=1e-6)
    text = sp.box.report.toPlainText()
    assert "line time" in text and "{" not in text and "'rows'" not in text
    sp.box.save.click()
    m, smeta = load_shutter(sp.saved_path)
    assert m.shape == sp.result.shutter.shape and smeta["method"] == "timing"

    wiz.next()
    assert "PSF:" in wiz.finish_page.summary.text()
    wiz.accept()
    assert "calibration psf-" in w.psf_source
    n = w.previews_shown
    qtbot.waitUntil(lambda: w.previews_shown > n + 2, timeout=20_000)


def test_wizard_cancel_saves_nothing_and_resumes_live(
    bench_window: Any, qtbot: Any, tmp_path: Path
) -> None:
    pass

    w = bench_window
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    wiz = w.open_calibration_wizard()
    wiz.setup_page.out_dir.setText(str(tmp_path / "cal"))
    wiz.setup_page.n_darks.setValue(50)
    wiz.next()
    page = wiz.psf_page
    page.box.start.click()
    qtbot.waitUntil(lambda: page.box.progress.value() > 0, timeout=10_000)
    page.box.cancel.click()
    qtbot.waitUntil(lambda: page.error != "", timeout=10_000)
    assert "cancelled" in page.box.stage.text()
    assert page.result is None and not (tmp_path / "cal").exists()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    assert w.bench.light.is_on is False
    wiz.reject()
