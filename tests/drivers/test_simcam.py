"""The simulated camera: forward model, shutter, point source, sensor physics, faults."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.camera import CameraError, CameraTimeout, Roi
from drivers.lightstate import LightMode, LightState, write_light_state
from drivers.simcam import (
    CropRenderer,
    MovingScene,
    SimulatedCamera,
    SpectralScene,
    StillScene,
    crop_center,
    shutter_at,
)
from drivers.timing import ReadoutPattern, SensorTiming, row_start_lines, shutter_function

pytestmark = pytest.mark.timeout(60)

ROWS, COLS = 16, 20


# --------------------------------------------------------------------------------------------
# a small forward model written here (the camera must not care where its renderer comes from)


def _fft_conv_crop(h: np.ndarray, v: np.ndarray, out_shape: tuple[int, int]) -> np.ndarray:
    """Centre crop of the full linear convolution h * v, by zero-padded FFTs."""
    fh, fw = h.shape[0] + v.shape[0] - 1, h.shape[1] + v.shape[1] - 1
    full = np.fft.irfft2(np.fft.rfft2(h, (fh, fw)) * np.fft.rfft2(v, (fh, fw)), (fh, fw))
    return crop_center(full, out_shape)


class FFTRenderer:
    """sum_k M_k . crop(h * v_k) with numpy FFTs; records what it was given."""

    def __init__(self, psf: np.ndarray, cols: int) -> None:
        self.psf = psf.astype(np.float64)
        self.cols = cols
        self.calls: list[tuple[np.ndarray, np.ndarray]] = []

    def __call__(self, frames: np.ndarray, shutter: np.ndarray) -> np.ndarray:
        assert frames.ndim == 3 and shutter.ndim == 2 and frames.shape[0] == shutter.shape[0]
        assert frames.dtype == np.float32
        self.calls.append((frames.copy(), shutter.copy()))
        rows = shutter.shape[1]
        out = np.zeros((rows, self.cols))
        for k in range(frames.shape[0]):
            out += shutter[k][:, None] * _fft_conv_crop(self.psf, frames[k], (rows, self.cols))
        return out


def _direct_conv_crop(h: np.ndarray, v: np.ndarray, out_shape: tuple[int, int]) -> np.ndarray:
    """Same as _fft_conv_crop, by explicit sums over the PSF taps."""
    fh, fw = h.shape[0] + v.shape[0] - 1, h.shape[1] + v.shape[1] - 1
    full = np.zeros((fh, fw))
    for i in range(h.shape[0]):
        for j in range(h.shape[1]):
            full[i : i + v.shape[0], j : j + v.shape[1]] += h[i, j] * v
    oy, ox = (fh - out_shape[0]) // 2, (fw - out_shape[1]) // 2
    return full[oy : oy + out_shape[0], ox : ox + out_shape[1]]


def _ideal_camera(**kw: object) -> SimulatedCamera:
    args: dict[str, object] = dict(
        noise=False,
        pacing=False,
        pixel_format="Mono16",
        dark_offset_adu=0.0,
        full_well_e=1e7,
        line_time_us=10.0,
    )
    args.update(kw)
    return SimulatedCamera(COLS, ROWS, **args)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# 4. dual rolling shutter of a moving scene = sum_k M_k . crop(h * v_k)


@pytest.mark.parametrize("pattern", [ReadoutPattern.OUTSIDE_IN, ReadoutPattern.CENTRE_OUT])
def test_dual_rolling_shutter_frame_matches_forward_model(pattern: ReadoutPattern) -> None:
    rng = np.random.default_rng(7)
    n_scene, period = 9, 3  # scene frames, scene frame period in lines
    scene = rng.uniform(0, 1e5, size=(n_scene, ROWS, COLS)).astype(np.float32)
    psf = rng.uniform(0, 1, size=(ROWS, COLS))
    psf /= psf.sum()
    renderer = FFTRenderer(psf, COLS)
    exposure_lines = 6
    cam = _ideal_camera(
        renderer=renderer,
        scene=MovingScene(scene, frame_period_lines=period),
        exposure_us=exposure_lines * 10.0,
        readout_pattern=pattern,
        frame_rate_hz=1000.0,  # frame period 1 ms = 100 lines: the 2nd frame is off-grid
        full_well_e=65535.0,  # 1 code per electron
    )
    with cam:
        frames = [cam.snap(), cam.snap()]
    starts = [0, 100]

    for frame, t0 in zip(frames, starts, strict=True):
        # direct per-row computation: row r integrates [t0 + s_r, t0 + s_r + E) lines
        expected_e = np.zeros((ROWS, COLS))
        r_idx = np.arange(ROWS)
        dist = np.minimum(r_idx, ROWS - 1 - r_idx)
        s = dist if pattern is ReadoutPattern.OUTSIDE_IN else (ROWS - 1) // 2 - dist
        for r in range(ROWS):
            a, b = t0 + s[r], t0 + s[r] + exposure_lines
            for j in range(a // period, -(-b // period)):
                overlap = min(b, (j + 1) * period) - max(a, j * period)
                if overlap > 0:
                    conv = _direct_conv_crop(psf, scene[j % n_scene], (ROWS, COLS))
                    expected_e[r] += overlap * 10.0 / 1000.0 * conv[r]  # lines -> ms
        expected_adu = np.rint(expected_e * cam.adu_per_electron)
        assert expected_adu.max() > 1000  # a real signal, not a few codes
        diff = np.abs(frame.pixels.astype(np.int64) - expected_adu)
        assert diff.max() <= 1, diff.max()  # rounding of float32 vs float64 only

    # what the renderer got: M from shutter_function on the scene's frame grid
    timing = SensorTiming(ROWS, 10.0, exposure_lines, pattern)
    frames0, shutter0 = renderer.calls[0]
    np.testing.assert_allclose(shutter0, shutter_function(timing, period), rtol=1e-6)
    np.testing.assert_array_equal(frames0, scene[: shutter0.shape[0]])
    frames1, shutter1 = renderer.calls[1]
    j0, m1 = shutter_at(timing, period, 100)
    assert j0 == 100 // period
    np.testing.assert_allclose(shutter1, m1, rtol=1e-6)
    np.testing.assert_array_equal(frames1, scene[(j0 + np.arange(m1.shape[0])) % n_scene])


def test_shutter_at_matches_shutter_function_on_and_off_the_grid() -> None:
    timing = SensorTiming(12, 5.0, 7, ReadoutPattern.OUTSIDE_IN)
    j0, m = shutter_at(timing, 4, 8)
    assert j0 == 2
    np.testing.assert_array_equal(m, shutter_function(timing, 4))
    j0, m = shutter_at(timing, 4, 9)  # one line late
    fine = shutter_function(timing, 1)  # (lines, rows), bins of one line from t=0
    padded = np.zeros((m.shape[0] * 4, 12))
    padded[1 : 1 + fine.shape[0]] = fine  # shift by (9 - 4*2) = 1 line
    np.testing.assert_allclose(m, padded.reshape(-1, 4, 12).mean(axis=1))
    np.testing.assert_allclose(m.sum(axis=0), 7 / 4)


# --------------------------------------------------------------------------------------------
# scenes and the default renderer


def test_default_renderer_is_a_centre_crop() -> None:
    big = np.arange(30 * 40, dtype=np.float32).reshape(30, 40)
    cam = _ideal_camera(scene=big, exposure_us=1000.0)
    with cam:
        frame = cam.snap()
    expected = crop_center(big, (ROWS, COLS)) * 1.0 * cam.adu_per_electron  # 1 ms
    np.testing.assert_allclose(frame.pixels, np.rint(expected), atol=1)
    small = np.ones((4, 4), dtype=np.float32)
    padded = crop_center(small, (ROWS, COLS))
    assert padded.sum() == 16 and padded[6:10, 8:12].sum() == 16


def test_still_scene_scales_with_exposure_and_gain() -> None:
    scene = np.full((ROWS, COLS), 100.0, dtype=np.float32)  # 100 e-/ms
    with _ideal_camera(scene=scene, exposure_us=1000.0) as cam:
        a = cam.snap().pixels.astype(float)
        cam.exposure_us = 2000.0
        b = cam.snap().pixels.astype(float)
        cam.gain = 4.0
        c = cam.snap().pixels.astype(float)
    np.testing.assert_allclose(b, 2 * a, atol=1)
    np.testing.assert_allclose(c, 4 * b, atol=1)
    expected = 100.0 * 1.0 * 65535 / 1e7
    assert a.mean() == pytest.approx(round(expected), abs=1)


def test_spectral_cube_goes_to_the_renderer_as_bands() -> None:
    cube = np.random.default_rng(0).uniform(0, 10, (5, ROWS, COLS)).astype(np.float32)
    got: list[tuple[int, ...]] = []

    def renderer(frames: np.ndarray, shutter: np.ndarray) -> np.ndarray:
        got.append((frames.shape[0], shutter.shape[0]))
        return CropRenderer(COLS)(frames, shutter)

    with _ideal_camera(scene=SpectralScene(cube), renderer=renderer, exposure_us=500.0) as cam:
        frame = cam.snap()
    assert got == [(5, 5)]
    np.testing.assert_allclose(
        frame.pixels, np.rint(cube.sum(axis=0) * 0.5 * cam.adu_per_electron), atol=1
    )


def test_renderer_with_wrong_output_shape_is_a_clear_error() -> None:
    def bad(frames: np.ndarray, shutter: np.ndarray) -> np.ndarray:
        return np.zeros((3, 3))

    with _ideal_camera(scene=np.ones((ROWS, COLS)), renderer=bad) as cam:
        with pytest.raises(CameraError, match="renderer returned shape"):
            cam.snap()


# --------------------------------------------------------------------------------------------
# the point source


def _row_renderer(frames: np.ndarray, shutter: np.ndarray) -> np.ndarray:
    """Every row sees the total flux times its shutter weight (a PSF filling the sensor)."""
    total = frames.reshape(frames.shape[0], -1).sum(axis=1)
    return np.repeat((shutter * total[:, None]).sum(axis=0)[:, None], COLS, axis=1)


def test_point_source_lights_the_frame_only_when_on() -> None:
    with _ideal_camera(light_state=LightState(LightMode.OFF, 1.0), exposure_us=1000.0) as cam:
        assert cam.snap().pixels.max() == 0
    with _ideal_camera(
        light_state=LightState(LightMode.ON, 0.5),
        exposure_us=1000.0,
        point_flux_e_per_ms=1e4,
        full_well_e=65535.0,  # 1 code per electron
    ) as cam:
        px = cam.snap().pixels
    # the default point sits on the on-axis pixel (H // 2, W // 2): all of it in one pixel
    assert px[ROWS // 2, COLS // 2] == 5000  # 0.5 x 1e4 e-/ms x 1 ms
    assert px.sum() == 5000
    with _ideal_camera(
        light_state=LightState(LightMode.ON, 1.0), point_position=(3.0, 5.0), full_well_e=1e5
    ) as cam:
        px = cam.snap().pixels
    assert np.unravel_index(np.argmax(px), px.shape) == (3, 5)


def test_strobe_lights_only_rows_whose_exposure_overlaps_the_pulse() -> None:
    line_us, exposure_lines = 10.0, 4
    delay, duration = 55.0, 20.0  # pulse [55, 75) us after the trigger
    state = LightState(LightMode.STROBE, 1.0, delay, duration)
    with _ideal_camera(
        renderer=_row_renderer,
        light_state=state,
        readout_pattern=ReadoutPattern.TOP_DOWN,
        exposure_us=exposure_lines * line_us,
        point_flux_e_per_ms=1e5,
    ) as cam:
        px = cam.snap().pixels[:, 0].astype(float)
    starts = row_start_lines(ROWS, ReadoutPattern.TOP_DOWN) * line_us
    overlap = np.clip(
        np.minimum(starts + exposure_lines * line_us, delay + duration) - np.maximum(starts, delay),
        0,
        None,
    )
    lit = overlap > 0
    assert np.flatnonzero(lit).tolist() == [2, 3, 4, 5, 6, 7]  # rows starting 20..70 us
    np.testing.assert_allclose(px, np.rint(overlap / 1000 * 1e5 * 65535 / 1e7), atol=1)


def test_camera_follows_the_state_file(tmp_path: object) -> None:
    from pathlib import Path

    path = Path(str(tmp_path)) / "state.json"
    with _ideal_camera(light_state=path, exposure_us=1000.0) as cam:
        assert cam.snap().pixels.max() == 0  # no file yet: dark
        write_light_state(path, LightState(LightMode.ON, 1.0, counter=1))
        f = cam.snap()
        assert f.pixels.max() > 0 and f.extra["light"]["counter"] == 1
        write_light_state(path, LightState(LightMode.OFF, 1.0, counter=2))
        assert cam.snap().pixels.max() == 0


# --------------------------------------------------------------------------------------------
# sensor physics


def test_noise_statistics_match_shot_and_read_noise() -> None:
    scene = np.full((48, 64), 500.0, dtype=np.float32)  # 500 e-/ms x 2 ms = 1000 e-
    cam = SimulatedCamera(
        64, 48, scene=scene, exposure_us=2000.0, pacing=False, pixel_format="Mono16",
        dark_offset_adu=100.0, read_noise_e=5.0, full_well_e=65535.0, seed=3,
    )  # fmt: skip
    with cam:
        px = np.stack([cam.snap().pixels for _ in range(4)]).astype(float)
    electrons = px - 100.0  # 1 ADU per electron at gain 1
    assert electrons.mean() == pytest.approx(1000.0, rel=0.01)
    assert electrons.std() == pytest.approx(np.sqrt(1000.0 + 25.0), rel=0.05)


def test_seeded_noise_is_reproducible() -> None:
    def frames(seed: int) -> np.ndarray:
        cam = SimulatedCamera(16, 12, scene=np.full((12, 16), 50.0), pacing=False, seed=seed)
        with cam:
            return np.stack([cam.snap().pixels for _ in range(2)])

    np.testing.assert_array_equal(frames(1), frames(1))
    assert not np.array_equal(frames(1), frames(2))


def test_saturation_and_bit_depth() -> None:
    scene = np.full((ROWS, COLS), 1e9, dtype=np.float32)
    for fmt, top, dtype in (("Mono8", 255, np.uint8), ("Mono12", 4095, np.uint16)):
        with SimulatedCamera(COLS, ROWS, scene=scene, pacing=False, pixel_format=fmt) as cam:
            px = cam.snap().pixels
        assert px.dtype == dtype and (px == top).all()


def test_dead_and_hot_pixels_in_a_dark_frame() -> None:
    cam = SimulatedCamera(
        40, 30, pacing=False, noise=False, dead_pixel_fraction=0.02, hot_pixel_fraction=0.01,
        hot_pixel_e_per_ms=1000.0, exposure_us=10_000.0, dark_offset_adu=50.0,
        scene=np.full((30, 40), 100.0, dtype=np.float32), pixel_format="Mono16",
        full_well_e=65535.0,
    )  # fmt: skip
    dead, hot = cam.defect_maps
    assert dead.sum() == 24 and hot.sum() == 12 and not (dead & hot).any()
    with cam:
        px = cam.snap().pixels.astype(float)
    assert (px[dead] == 50).all()  # no signal: the dark offset
    assert (px[hot] == 50 + 1000 + 10_000).all()  # scene + dark current
    assert (px[~dead & ~hot] == 50 + 1000).all()


def test_roi_and_binning_cut_and_sum() -> None:
    scene = np.arange(ROWS * COLS, dtype=np.float32).reshape(ROWS, COLS)
    with _ideal_camera(scene=scene, exposure_us=1000.0, full_well_e=65535.0) as cam:
        first = cam.snap()
        full = first.pixels.astype(float)
        cam.roi = Roi(4, 2, 8, 6)
        cut = cam.snap()
        part = cut.pixels.astype(float)
        cam.binning = 2
        binned = cam.snap()
    np.testing.assert_array_equal(part, full[2:8, 4:12])
    assert binned.shape == (3, 4) and binned.binning == 2
    # every frame names its whole sensor (unbinned rows, columns), ROI and binning or not
    assert cam.capabilities().sensor_height == ROWS and cam.capabilities().sensor_width == COLS
    assert [f.sensor for f in (first, cut, binned)] == [(ROWS, COLS)] * 3
    assert binned.metadata()["sensor"] == [ROWS, COLS]
    np.testing.assert_allclose(binned.pixels, part.reshape(3, 2, 4, 2).sum(axis=(1, 3)), atol=2)
    with pytest.raises(ValueError, match="outside"):
        cam.roi = Roi(10, 0, 20, 4)


def test_frame_rate_pacing() -> None:
    with SimulatedCamera(8, 8, frame_rate_hz=50.0, exposure_us=100.0) as cam:
        t0 = time.monotonic()
        cam.start_acquisition(n_frames=6)
        frames = [cam.pop_frame(2.0) for _ in range(6)]
        elapsed = time.monotonic() - t0
        cam.stop()
    assert elapsed >= 5 / 50 * 0.9
    assert frames[-1].timestamp - frames[0].timestamp == pytest.approx(0.1, abs=0.05)


def test_the_resulting_frame_rate_is_what_the_exposure_allows() -> None:
    """The set rate while a frame fits its period; 1 / frame time once the exposure makes a
    frame longer (the app showed the set 20 Hz while 5 came)."""
    with SimulatedCamera(8, 8, frame_rate_hz=20.0, exposure_us=10_000.0) as cam:
        assert cam.resulting_frame_rate_hz == pytest.approx(20.0)
        cam.exposure_us = 200_000.0
        assert cam.frame_rate_hz == pytest.approx(20.0)  # the setting is kept
        frame_us = cam.timing.frame_time_us
        assert frame_us > 200_000.0
        assert cam.resulting_frame_rate_hz == pytest.approx(1e6 / frame_us)
        assert cam.resulting_frame_rate_hz == pytest.approx(1e6 / cam.frame_period_us())
        cam.exposure_us = 1_000.0
        assert cam.resulting_frame_rate_hz == pytest.approx(20.0)


def test_a_long_exposure_is_not_a_stall() -> None:
    """Live view ended with 'no frame for 2 s while streaming' at a 3 s exposure the camera
    accepts: the stall timeout now allows two frame times more, also for an exposure set
    while streaming."""
    with SimulatedCamera(8, 8, frame_rate_hz=50.0, exposure_us=1000.0) as cam:
        cam.stream_timeout_s = 0.2
        cam.start_live()
        assert cam.latest_frame(timeout_s=2.0) is not None
        cam.exposure_us = 600_000.0  # 0.6 s a frame: three stall timeouts
        assert cam.expected_frame_s() == pytest.approx(1 / cam.resulting_frame_rate_hz)
        assert cam.expected_frame_s() > 0.6
        got = 0
        deadline = time.monotonic() + 2.5
        while time.monotonic() < deadline:  # no CameraTimeout while frames come slowly
            f = cam.latest_frame(timeout_s=1.5)
            got += f is not None
        assert got >= 2
        cam.stop()


def test_a_shorter_exposure_keeps_the_frame_under_way_from_being_a_stall() -> None:
    """A 6 s exposure set to 10 ms while streaming: the stall allowance fell to the new frame
    time at once, and the frame being exposed made the stream 'lost'. The shorter time now
    holds from the next good frame."""
    with SimulatedCamera(8, 8, frame_rate_hz=50.0, exposure_us=700_000.0) as cam:
        cam.stream_timeout_s = 0.2
        cam.start_live()
        assert cam.latest_frame(timeout_s=3.0) is not None  # a frame: the next is under way
        cam.exposure_us = 1000.0
        got = 0
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            got += cam.latest_frame(timeout_s=0.5) is not None
        assert got >= 2
        cam.stop()


def test_frame_timing_metadata_rebuilds_the_shutter() -> None:
    with _ideal_camera(exposure_us=123.0, readout_pattern="centre-out") as cam:
        f = cam.snap()
    t = SensorTiming.from_dict(f.metadata()["timing"])
    assert t == f.timing and t.rows == ROWS and t.exposure_lines == 12
    assert t.pattern is ReadoutPattern.CENTRE_OUT


# --------------------------------------------------------------------------------------------
# faults


def test_unplug_makes_snaps_time_out_and_replug_recovers() -> None:
    with SimulatedCamera(8, 8, pacing=False) as cam:
        cam.simulate_unplug()
        t0 = time.monotonic()
        with pytest.raises(CameraTimeout, match="no frame within"):
            cam.snap(timeout_s=0.2)
        assert 0.15 < time.monotonic() - t0 < 2.0
        cam.simulate_replug()
        assert cam.snap().shape == (8, 8)


def test_unplug_ends_a_live_stream_with_a_timeout() -> None:
    with SimulatedCamera(8, 8, frame_rate_hz=500.0, exposure_us=100.0) as cam:
        cam.stream_timeout_s = 0.3
        cam.start_live()
        assert cam.latest_frame(timeout_s=2.0) is not None
        cam.simulate_unplug()
        with pytest.raises(CameraTimeout, match="while streaming"):
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                cam.latest_frame(timeout_s=0.5)
        cam.stop()
        cam.simulate_replug()
        cam.start_live()
        assert cam.latest_frame(timeout_s=2.0) is not None
        cam.stop()


def test_invalid_settings_are_rejected() -> None:
    cam = SimulatedCamera(8, 8)
    with pytest.raises(ValueError):
        cam.exposure_us = -1.0
    with pytest.raises(ValueError):
        cam.gain = float("nan")
    with pytest.raises(ValueError):
        cam.pixel_format = "RGB8"
    with pytest.raises(ValueError):
        cam.binning = 3
    with pytest.raises(ValueError, match="exactly one"):
        MovingScene(np.zeros((2, 4, 4)))
    with pytest.raises(ValueError, match="3-D"):
        MovingScene(np.zeros((4, 4)), frame_period_lines=2)
    assert StillScene(np.zeros((3, 5))).shape == (3, 5)
