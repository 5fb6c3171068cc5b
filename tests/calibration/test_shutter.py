"""Shutter functions: from the timing model, and measured by strobing the simulated source."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.shutter import (
    ShutterSettings,
    analyse_strobe_scan,
    measure_shutter,
    shutter_for_frame,
    shutter_from_timing,
)
from calibration.workflow import CalibrationError, Workflow
from drivers.camera import Roi
from drivers.lightstate import LightMode
from drivers.timing import (
    ReadoutPattern,
    SensorTiming,
    row_start_lines,
    shutter_function,
)
from recon.calibfile import load_shutter
from recon.preprocess import downsample_rows
from tests.calibration.conftest import ROWS


def test_measured_line_time_matches_the_timing_model(make_camera, source, tmp_path):
    # a line time and trigger delay unlike the defaults, so nothing is taken for granted
    cam = make_camera(line_time_us=12.5, trigger_delay_us=30.0, exposure_us=160.0)
    truth = cam.timing
    out = tmp_path / "shutter.npz"
    settings = ShutterSettings(intensity=1.0, n_darks=4, settle_frames=0)
    wf = Workflow(measure_shutter(cam, source, settings, bin_lines=1, out=out), "shutter")
    stages = [p.stage for p in wf]
    sf = wf.result
    m = sf.measurement
    assert m is not None and {"darks", "scan", "fit", "save"} <= set(stages)
    assert source.status().mode is LightMode.OFF

    # line time within 1%, offset and exposure within a fraction of a line
    assert abs(m.line_time_us - truth.line_time_us) / truth.line_time_us < 0.01
    assert m.line_time_error is not None and abs(m.line_time_error) < 0.01
    assert m.offset_us == pytest.approx(truth.trigger_delay_us, abs=0.5 * truth.line_time_us)
    assert m.exposure_us == pytest.approx(truth.exposure_us, abs=0.5 * truth.line_time_us)
    assert m.model_residual_us is not None and m.model_residual_us < 0.25 * truth.line_time_us
    assert m.valid_rows.sum() > ROWS // 2

    # the measured windows follow the readout pattern row by row
    model_start = truth.row_start_us()
    ok = np.isfinite(m.row_start_us)
    assert np.max(np.abs(m.row_start_us[ok] - model_start[ok])) < 0.25 * truth.line_time_us

    # the measured timing gives the model's shutter function
    assert m.timing().exposure_lines == truth.exposure_lines
    model = shutter_function(truth, 1)
    assert sf.shutter.shape == model.shape
    assert np.allclose(sf.shutter, model, atol=1e-6)

    # saved with the timing it came from and the scan
    shutter, meta = load_shutter(out)
    assert np.array_equal(shutter, sf.shutter)
    assert meta["method"] == "measured"
    assert meta["measurement"]["model_timing"] == truth.to_dict()
    assert abs(meta["measurement"]["line_time_error"]) < 0.01


def test_shutter_from_timing_bins_rows_and_roi(tmp_path):
    timing = SensorTiming(
        rows=64, line_time_us=10.0, exposure_lines=12, pattern=ReadoutPattern.OUTSIDE_IN
    )
    sf = shutter_from_timing(timing, bin_lines=4, roi_rows=(8, 48), binning=2, row_factor=2)
    full = shutter_function(timing, 4)
    assert np.allclose(sf.shutter, downsample_rows(full[:, 8:56], 4))
    assert sf.shutter.shape == (full.shape[0], 12)
    assert np.allclose(sf.shutter.sum(axis=0), 12 / 4)  # each row integrates E / w bins
    assert sf.bin_us == 40.0
    path = sf.save(tmp_path / "s.npz")
    m, meta = load_shutter(path)
    assert np.array_equal(m, sf.shutter)
    assert SensorTiming.from_dict(meta["timing"]) == timing
    assert meta["bin_lines"] == 4 and meta["row_factor"] == 2 and meta["binning"] == 2
    assert meta["roi_rows"] == [8, 48] and meta["method"] == "timing"


def test_shutter_for_a_binned_roi_frame(make_camera):
    cam = make_camera()
    cam.roi = Roi(0, 16, 80, 32)
    cam.binning = 2
    frame = cam.snap()
    sf = shutter_for_frame(frame, bin_lines=2)
    expected = downsample_rows(shutter_function(frame.timing, 2)[:, 16:48], 2)
    assert sf.shutter.shape[1] == frame.shape[0] == 16
    assert np.allclose(sf.shutter, expected)


def test_analysis_of_an_exact_scan_is_exact():
    rows, lt, offset, exposure, pulse = 40, 8.0, 5.0, 96.0, 8.0
    lines = row_start_lines(rows, ReadoutPattern.TOP_DOWN).astype(float)
    starts = offset + lt * lines
    delays = np.arange(0.0, 500.0, 3.0)
    # light per row: overlap of [d, d + pulse) with [start, start + exposure)
    resp = (
        np.clip(
            np.minimum(delays[:, None] + pulse, starts[None, :] + exposure)
            - np.maximum(delays[:, None], starts[None, :]),
            0.0,
            None,
        )
        * np.linspace(50, 100, rows)[None, :]
    )
    m = analyse_strobe_scan(
        delays,
        resp,
        lines,
        np.ones(rows),
        pulse_us=pulse,
        pattern=ReadoutPattern.TOP_DOWN,
        sensor_rows=rows,
    )
    assert m.line_time_us == pytest.approx(lt, rel=1e-9)
    assert m.offset_us == pytest.approx(offset, abs=1e-6)
    assert m.exposure_us == pytest.approx(exposure, abs=1e-6)
    assert m.fit_residual_us < 1e-6


def test_analysis_refuses_a_scan_without_light():
    rows = 16
    resp = np.random.default_rng(0).normal(0, 1, (50, rows))
    with pytest.raises(CalibrationError, match="rows saw the strobe"):
        analyse_strobe_scan(
            np.arange(50.0),
            resp,
            np.arange(rows, dtype=float),
            np.ones(rows),
            pulse_us=2.0,
            pattern=ReadoutPattern.TOP_DOWN,
            sensor_rows=rows,
        )


def test_global_shutter_line_time_is_undetermined():
    rows = 8
    delays = np.arange(0.0, 100.0, 1.0)
    resp = np.clip(np.minimum(delays + 4, 60) - np.maximum(delays, 20), 0, None)
    resp = np.repeat(resp[:, None], rows, axis=1) * 10
    with pytest.raises(CalibrationError, match="undetermined"):
        analyse_strobe_scan(
            delays,
            resp,
            np.zeros(rows),
            np.ones(rows),
            pulse_us=4.0,
            pattern=ReadoutPattern.GLOBAL,
            sensor_rows=rows,
        )


def test_automatic_step_fits_a_long_exposure_into_the_delay_limit(make_camera, source, tmp_path):
    """At a 10 ms exposure the default step (half the pulse) needed thousands of delays and
    the scan was refused; the automatic step grows to fit max_delays and still measures."""
    cam = make_camera(line_time_us=12.5, trigger_delay_us=30.0, exposure_us=10_000.0)
    settings = ShutterSettings(intensity=1.0, n_darks=4, settle_frames=0, max_delays=200)
    wf = Workflow(measure_shutter(cam, source, settings, bin_lines=1, out=tmp_path / "s.npz"),
                  "shutter")
    list(wf)
    m = wf.result.measurement
    assert m is not None and m.delays_us.size <= 200
    assert abs(m.line_time_us - 12.5) / 12.5 < 0.02


@pytest.mark.parametrize(("kw", "message"), [
    ({"span_us": 1.0}, r"the scan has 1 delay\(s\): too few"),
    ({"step_us": 400.0}, r"the scan has \d delay\(s\): too few"),
    ({"pulse_us": 500.0}, "longer than half the 100 us exposure"),
])
def test_a_scan_that_cannot_find_edges_is_refused_in_words(make_camera, source, tmp_path, kw,
                                                          message):
    """A tiny span or a huge step raised IndexError; a pulse longer than the exposure gave a
    line time 30 % off as a result."""
    cam = make_camera()
    settings = ShutterSettings(intensity=1.0, n_darks=2, settle_frames=0, **kw)
    with pytest.raises(CalibrationError, match=message):
        list(Workflow(measure_shutter(cam, source, settings, out=tmp_path / "s.npz"), "s"))
    assert not (tmp_path / "s.npz").exists()


def test_default_pulse_and_step_are_on_the_sources_time_grid(make_camera, source, tmp_path):
    """A line time of 12.37 us made a 12.37 us default pulse and 6.185 us steps; the source
    sent 12.4 us and delays rounded to 0.1 us while the analysis used the exact values."""
    cam = make_camera(line_time_us=12.37, trigger_delay_us=30.0, exposure_us=160.0)
    settings = ShutterSettings(intensity=1.0, n_darks=2, settle_frames=0)
    wf = Workflow(measure_shutter(cam, source, settings, bin_lines=1, out=tmp_path / "s.npz"),
                  "shutter")
    list(wf)
    m = wf.result.measurement
    assert m.pulse_us == pytest.approx(12.3)  # what the source sends (down: within the line)
    # every delay is a multiple of 0.1 us, as the source sends it
    assert np.allclose(m.delays_us, np.round(m.delays_us, 1), atol=1e-9)


def test_the_grid_keeps_the_pulse_within_half_the_exposure_and_the_scan_within_its_limit(
        make_camera, source, tmp_path):
    """Rounding to the nearest 0.1 us made a 6.185 us default pulse 6.2 us, over half a
    12.37 us exposure (refused), and a span-limited step shorter, one delay over max_delays
    (refused): the pulse goes down to the grid, the step up."""
    cam = make_camera(line_time_us=12.37, trigger_delay_us=30.0, exposure_us=12.37)
    settings = ShutterSettings(intensity=1.0, n_darks=2, settle_frames=0)
    wf = Workflow(measure_shutter(cam, source, settings, bin_lines=1, out=tmp_path / "a.npz"),
                  "shutter")
    list(wf)
    assert wf.result.measurement.pulse_us == pytest.approx(6.1)
    cam = make_camera(line_time_us=12.5, trigger_delay_us=30.0, exposure_us=160.0)
    span = 730.25
    limit = 111  # span / (limit - 1) = 6.639 us: 6.6 would need 112 delays
    settings = ShutterSettings(intensity=1.0, n_darks=2, settle_frames=0, span_us=span,
                               max_delays=limit, pulse_us=10.0)
    wf = Workflow(measure_shutter(cam, source, settings, bin_lines=1, out=tmp_path / "b.npz"),
                  "shutter")
    list(wf)
    d = wf.result.measurement.delays_us
    assert d.size <= limit and np.diff(d)[0] == pytest.approx(6.7)


def test_the_front_ends_path_chooses_the_bins_and_records_camera_and_source(
        make_camera, source, tmp_path):
    """The wizard measured without ``out`` and its file had no camera or source; it chose its
    own bins (100 lines: one bin on 64 rows) and saved 1-line bins recon refuses. The CLI
    and the wizard now take one path, :func:`calibrate_shutter`."""
    from calibration.shutter import calibrate_shutter, shutter_model
    from recon.checks import check_shutter_frames

    cam = make_camera(line_time_us=12.5, trigger_delay_us=30.0, exposure_us=160.0)
    settings = ShutterSettings(intensity=1.0, n_darks=2, settle_frames=0)
    wf = Workflow(measure_shutter(cam, source, settings, bin_lines=4), "shutter")
    list(wf)
    md = wf.result.metadata()  # measured, not saved: what it was measured with all the same
    assert md["camera"]["backend"] == cam.backend and md["source"] == source.identify()

    timing = Workflow(calibrate_shutter(cam, None, out=tmp_path / "t.npz"), "shutter")
    list(timing)
    sf = timing.result
    assert sf.bin_lines == shutter_model(cam.snap()).bin_lines  # the finest the rows resolve
    check_shutter_frames(*sf.shutter.shape)
    k, rows = sf.shutter.shape
    assert rows // 2 < k <= rows
    assert load_shutter(sf.path)[1]["camera"]["backend"] == cam.backend
    with pytest.raises(ValueError, match="time bins for"):
        list(Workflow(calibrate_shutter(cam, source, settings, bin_lines=1, row_factor=8,
                                        out=tmp_path / "m.npz"), "shutter"))
    assert not (tmp_path / "m.npz").exists()
