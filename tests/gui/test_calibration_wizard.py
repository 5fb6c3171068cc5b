"""The calibration wizard with the simulated camera and point source (firmware on a PTY)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.gui


def test_wizard_captures_psf_and_shutter_saves_and_feeds_the_preview(
    live_window: Any, qtbot: Any, tmp_path: Path
) -> None:
    from app.gui.calibration_wizard import open_wizard
    from recon.calibfile import load_psf_calibration, load_shutter

    w = live_window
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    wiz = open_wizard(w)
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
    live_window: Any, qtbot: Any, tmp_path: Path
) -> None:
    from app.gui.calibration_wizard import open_wizard

    w = live_window
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    wiz = open_wizard(w)
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
