"""The warnings a problem's inputs raise are kept by the load of the thread that raised them.

``load_problem`` once caught them with ``warnings.catch_warnings``, which swaps process-wide
state: a load in one thread recorded another thread's measurement warning (and hid it from
that thread), and the filters of the wrong thread could stay in force.
"""

from __future__ import annotations

import threading
import types
import warnings

import numpy as np
import pytest

import recon.problem as problem
from recon.checks import MeasurementWarning, check_measurement
from recon.inputwarnings import collect_input_warnings, warn_input

SATURATED = np.ones((8, 8), dtype=np.float32)  # every pixel at full scale 1


def test_a_load_keeps_its_own_warnings_not_another_threads(monkeypatch) -> None:
    inside, emitted = threading.Event(), threading.Event()

    def fake_load(spec, *, dtype, device):
        warn_input("measurement file mine.tif: mine", MeasurementWarning)
        inside.set()
        assert emitted.wait(10)
        return types.SimpleNamespace(metadata={})

    monkeypatch.setattr(problem, "_load_problem", fake_load)
    result: dict[str, object] = {}

    def load() -> None:
        with warnings.catch_warnings():  # (process-wide: the other thread's filters too)
            warnings.simplefilter("ignore")
            result["prob"] = problem.load_problem(None)  # type: ignore[arg-type]

    t = threading.Thread(target=load)
    t.start()
    try:
        assert inside.wait(10)
        try:  # this thread's warning, under the filters in force (no catch of its own)
            check_measurement(SATURATED, 1.0, warn=True)
        except MeasurementWarning:  # pytest's "error" filter, where the load's is not in force
            pass
    finally:
        emitted.set()
        t.join(10)
    assert result["prob"].metadata["warnings"] == ["measurement file mine.tif: mine"]


def test_kept_whatever_the_filters_say_once_each_and_nested() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # shown: nothing; kept: all
        with collect_input_warnings() as outer:
            check_measurement(SATURATED, 1.0, warn=True)
            with collect_input_warnings() as inner:
                check_measurement(SATURATED, 1.0, warn=True)
                warn_input("second", MeasurementWarning)
    assert len(outer) == 2 and "saturated" in outer[0] and outer[1] == "second"
    assert inner == outer
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_measurement(SATURATED, 1.0, warn=True)  # no collection open: nothing kept
    assert len(outer) == 2


def test_the_warning_points_at_the_checks_caller() -> None:
    with pytest.warns(MeasurementWarning) as rec:
        check_measurement(SATURATED, 1.0, warn=True)
    assert rec[0].filename == __file__


def test_a_quiet_collection_keeps_without_emitting() -> None:
    with collect_input_warnings() as outer, collect_input_warnings(emit=False) as quiet:
        check_measurement(SATURATED, 1.0, warn=True)  # pytest's "error" filter: not reached
    assert quiet == outer and "saturated" in quiet[0]


def test_a_warning_from_code_without_a_file_is_shown(tmp_path):
    """``python -W always -c ...`` ended in "ImportError: '__main__' is not a built-in
    module": the warning asked the -c code's loader for its source line."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = ("from recon.inputwarnings import warn_input\n"
            "from recon.checks import MeasurementWarning\n"
            "warn_input('the message', MeasurementWarning)\n")
    r = subprocess.run([sys.executable, "-W", "always", "-c", code], capture_output=True,
                       text=True, timeout=120, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})
    assert r.returncode == 0, r.stderr
    assert "MeasurementWarning: the message" in r.stderr
