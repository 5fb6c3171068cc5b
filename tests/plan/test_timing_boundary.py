"""recon takes shutter functions and timing objects from its callers; it never imports drivers.

The time-binning rule lives in recon (``recon.preprocess.bin_time``); the sensor timing and its
shutter function live in drivers (``drivers.timing``). These tests tie the two together.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.timing import SensorTiming
from recon.plan.planner import base_shutter
from recon.preprocess import bin_time


def test_bin_time_means_groups_and_pads_the_last() -> None:
    m = np.arange(10, dtype=np.float64).reshape(5, 2)  # K=5 bins, 2 rows
    out = bin_time(m, 2)
    expected = np.array([[1.0, 2.0], [5.0, 6.0], [4.0, 4.5]])  # last: (8+0)/2, (9+0)/2
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bin_time(m, 1), m, rtol=0, atol=0)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="factor"):
            bin_time(m, bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"\(K, rows\)"):
        bin_time(np.ones(4), 2)


@pytest.mark.parametrize("pattern", ["outside-in", "centre-out", "top-down"])
@pytest.mark.parametrize("factor", [1, 2, 3, 5])
def test_binning_one_line_bins_equals_wider_bins(pattern: str, factor: int) -> None:
    # mean of f one-line overlaps = overlap with an f-line bin / f, the trailing group included
    t = SensorTiming(rows=17, line_time_us=2.0, exposure_lines=6, pattern=pattern)
    np.testing.assert_allclose(bin_time(t.shutter(1), factor), t.shutter(factor),
                               rtol=0, atol=1e-12)


def test_base_shutter_from_a_timing_object() -> None:
    t = SensorTiming(rows=12, line_time_us=1.0, exposure_lines=4, pattern="outside-in")
    m, note = base_shutter(None, t, 12)
    assert m is not None
    np.testing.assert_array_equal(m, t.shutter(1))
    assert "outside-in readout, exposure 4 lines" in note
    g = SensorTiming(rows=12, line_time_us=1.0, exposure_lines=4, pattern="global")
    assert base_shutter(None, g, 12) == (None, "global shutter: every row integrates the same "
                                               "window, no time resolution")
    with pytest.raises(ValueError, match="12 rows"):
        base_shutter(None, t, 10)


def test_base_shutter_refuses_a_timing_dict() -> None:
    t = SensorTiming(rows=12, line_time_us=1.0, exposure_lines=4)
    with pytest.raises(TypeError, match="sensor timing object"):
        base_shutter(None, t.to_dict(), 12)  # type: ignore[arg-type]


def test_plan_cli_reports_a_bad_timing_file_in_one_line(tmp_path, capsys) -> None:
    from app.cli import main

    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf.npy", rng.random((12, 10)))
    np.save(tmp_path / "meas.npy", rng.random((12, 10)))
    (tmp_path / "timing.json").write_text('{"timing": {"rows": 12}}')  # no line time
    code = main(["plan", "--psf", str(tmp_path / "psf.npy"), "--meas",
                 str(tmp_path / "meas.npy"), "--timing", str(tmp_path / "timing.json"),
                 "--no-probe"])
    err = capsys.readouterr().err
    assert code != 0
    assert "timing.json: not a sensor timing" in err and "line_time_us" in err
