"""Workflow mechanics: progress, results, cancellation, clean-up."""

from __future__ import annotations

import threading

import pytest

from calibration.workflow import (
    CalibrationCancelled,
    CalibrationError,
    Progress,
    Steps,
    Workflow,
    scaled,
)


def _counting(n: int, log: list[str]) -> Steps[int]:
    try:
        for i in range(n):
            yield Progress("count", f"step {i}", (i + 1) / n)
        return n * 10
    finally:
        log.append("cleaned")


def test_run_returns_the_result_and_reports_progress():
    log: list[str] = []
    seen: list[float] = []
    wf = Workflow(_counting(4, log))
    assert wf.run(lambda p: seen.append(p.fraction)) == 40
    assert seen == [0.25, 0.5, 0.75, 1.0] and log == ["cleaned"] and wf.done
    with pytest.raises(RuntimeError, match="only once"):
        list(wf)


def test_result_before_the_end_is_an_error():
    wf = Workflow(_counting(2, []))
    with pytest.raises(RuntimeError, match="not finished"):
        _ = wf.result


def test_cancel_from_another_thread_takes_effect_at_the_next_step():
    log: list[str] = []
    wf = Workflow(_counting(100, log), "counting")
    got = []
    with pytest.raises(CalibrationCancelled, match="counting cancelled during count"):
        for p in wf:
            got.append(p)
            if len(got) == 3:
                t = threading.Thread(target=wf.cancel)
                t.start()
                t.join()
    assert len(got) == 3 and log == ["cleaned"] and wf.cancelled and not wf.done


def test_a_consumer_that_stops_iterating_cleans_up():
    log: list[str] = []
    wf = Workflow(_counting(10, log))
    steps = iter(wf)
    next(steps)
    next(steps)
    steps.close()  # what a loop's break does once the iterator is dropped
    assert log == ["cleaned"] and not wf.done


def test_scaled_maps_fractions_and_returns_the_value():
    log: list[str] = []

    def outer() -> Steps[int]:
        a = yield from scaled(_counting(2, log), 0.0, 0.5)
        b = yield from scaled(_counting(2, log), 0.5, 1.0)
        return a + b

    wf = Workflow(outer())
    fractions = [p.fraction for p in wf]
    assert fractions == [0.25, 0.5, 0.75, 1.0] and wf.result == 40 and log == ["cleaned"] * 2


def test_calibration_error_says_what_to_change():
    e = CalibrationError("PSF saturated", "Lower the intensity", stage="quality")
    assert str(e) == "PSF saturated. Lower the intensity." and e.stage == "quality"
    assert isinstance(e, ValueError)  # the CLI prints it as one line
