"""UDN jobs from the GUI: launched as separate processes, survive the window, found again."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import pytest

pytestmark = pytest.mark.gui


@pytest.fixture(autouse=True)
def _reap_jobs() -> Iterator[None]:
    yield
    from app.gui.jobs_core import stop_children_for_tests

    stop_children_for_tests()


def _tiny(dlg: Any, iters: int) -> None:
    dlg.name.setText("tiny")
    dlg.downsample.setValue(4)
    dlg.scales.setValue(3)
    dlg.channels.setValue(8)
    dlg.max_iter.setValue(iters)
    dlg.device.setCurrentText("cpu")
    dlg.threads.setValue(1)
    dlg.checkpoint_every.setValue(10)
    dlg.preview_every.setValue(10)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_tiny_job_from_the_gui_completes_and_its_result_opens(live_window: Any,
                                                              qtbot: Any) -> None:
    w = live_window
    panel = w.jobs_panel
    dlg = panel.new_job_dialog()
    assert dlg is not None
    _tiny(dlg, 30)
    assert "about" in dlg.memory.text() and "available" in dlg.memory.text()
    dlg.accept()
    qtbot.waitUntil(lambda: len(panel.views) == 1, timeout=5_000)
    qtbot.waitUntil(lambda: panel.views[0].state in ("starting", "running", "finished"),
                    timeout=5_000)
    qtbot.waitUntil(lambda: panel.views[0].state == "finished", timeout=60_000)
    v = panel.views[0]
    assert v.finish_reason == "completed" and v.iteration == 30
    assert set(v.results) == {"best", "final"}
    panel.table.selectRow(0)
    qtbot.waitUntil(lambda: panel.open_button.isEnabled(), timeout=5_000)
    assert len(panel.loss_curve.getData()[0]) == 30
    assert panel.preview.image is not None
    dlg2 = panel.open_selected()
    assert dlg2 is not None
    assert dlg2.panels["best"].image.shape == (37, 50)
    assert dlg2.meta["final"]["method"] == "udn"


def test_job_survives_closing_the_window_and_is_found_again(make_window: Any,
                                                            qtbot: Any) -> None:
    w = make_window()
    qtbot.waitUntil(lambda: w.frames_shown >= 2, timeout=20_000)
    dlg = w.jobs_panel.new_job_dialog()
    _tiny(dlg, 1_000_000)
    dlg.accept()
    panel = w.jobs_panel
    qtbot.waitUntil(lambda: panel.views and panel.views[0].state == "running"
                    and panel.views[0].iteration > 0, timeout=30_000)
    pid = panel.views[0].pid
    assert pid is not None
    w.close()
    assert _alive(pid)

    w2 = make_window()
    p2 = w2.jobs_panel
    qtbot.waitUntil(lambda: p2.views and p2.views[0].state == "running", timeout=10_000)
    it0 = p2.views[0].iteration
    qtbot.waitUntil(lambda: p2.views[0].iteration > it0, timeout=15_000)
    p2.table.selectRow(0)
    p2.cancel_button.click()
    qtbot.waitUntil(lambda: p2.views[0].state == "finished", timeout=20_000)
    assert p2.views[0].finish_reason == "cancelled"
    stopped_at = p2.views[0].iteration
    # resume continues from the last checkpoint in a new process
    qtbot.waitUntil(lambda: p2.resume_button.isEnabled(), timeout=5_000)
    p2.resume_button.click()
    qtbot.waitUntil(lambda: p2.views[0].state == "running"
                    and p2.views[0].iteration > stopped_at, timeout=30_000)
    assert p2.views[0].pid != pid
    p2.cancel_button.click()
    qtbot.waitUntil(lambda: p2.views[0].state == "finished", timeout=20_000)


def test_seeds_queue_an_ensemble_that_combines(live_window: Any, qtbot: Any) -> None:
    """Seeds 3 queues three jobs (seeds 0-2, one after another); Combine averages them."""
    import numpy as np

    from recon.io import read_reconstruction

    panel = live_window.jobs_panel
    dlg = panel.new_job_dialog()
    assert dlg is not None
    _tiny(dlg, 20)
    dlg.seeds.setValue(3)
    dlg.accept()
    qtbot.waitUntil(lambda: len(panel.views) == 3, timeout=5_000)
    assert sorted(v.name for v in panel.views) == ["tiny-s0", "tiny-s1", "tiny-s2"]
    assert len(panel.selected_all()) == 3  # the new jobs are selected ...
    if not all(v.state == "finished" for v in panel.views):
        assert not panel.combine_button.isEnabled()  # ... and not all have finished yet
    qtbot.waitUntil(lambda: all(v.state == "finished" for v in panel.views), timeout=120_000)
    panel.refresh()
    assert len(panel.selected_all()) == 3  # the selection survives the polling
    qtbot.waitUntil(lambda: panel.combine_button.isEnabled(), timeout=5_000)
    panel.combine_button.click()
    msg = panel.message.text()
    assert "ensemble of 3 jobs written to" in msg, msg
    out = sorted((panel.queue.jobs_dir / "ensembles").glob("*.tif"))
    assert len(out) == 1
    x, meta = read_reconstruction(out[0])
    assert sorted(m["seed"] for m in meta["members"]) == [0, 1, 2]
    bests = [read_reconstruction(v.run_dir / "best.tif")[0] for v in panel.views]
    np.testing.assert_allclose(x, np.mean(bests, axis=0), rtol=1e-6, atol=1e-7)
    assert len(panel.views) == 3  # the ensembles folder is not taken for a job

    # one finished job alone cannot be combined; the core refuses it too
    panel._select_folders({panel.views[0].folder})
    panel._show_details()
    assert not panel.combine_button.isEnabled()
    panel.combine_selected()
    assert "cannot combine: an ensemble needs at least two runs" in panel.message.text()
