"""``lenslesscam calibrate``: the same workflows from the command line."""

from __future__ import annotations

import numpy as np
import pytest

from app.cli import main
from recon.calibfile import load_calibration
from tests.procs import HAS_PROC, alive, children_of


def test_calibrate_psf_with_simulated_camera_and_source(tmp_path, capsys):
    out = tmp_path / "psf.tif"
    rc = main(
        [
            "calibrate",
            "psf",
            "--camera",
            "sim",
            "--source",
            "sim",
            "--frames",
            "4",
            "--darks",
            "4",
            "--settle",
            "0",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert f"wrote {out}" in text and "0 saturated" in text
    cal = load_calibration(out, expect="psf")
    assert cal.data.shape == (64, 80) and cal.metadata["quality"]["saturated_pixels"] == 0


def test_calibrate_psf_refusal_is_one_line_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "psf.tif"
    rc = main(
        [
            "calibrate",
            "psf",
            "--camera",
            "sim",
            "--source",
            "sim",
            "--intensity",
            "0",
            "--max-exposure",
            "2ms",
            "--frames",
            "2",
            "--darks",
            "2",
            "--settle",
            "0",
            "--out",
            str(out),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.startswith("lenslesscam calibrate: error: no light from the point source")
    assert "intensity 0" in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []


def test_calibrate_shutter_from_timing_and_darks(tmp_path, capsys):
    sh = tmp_path / "shutter.npz"
    assert (
        main(
            [
                "calibrate",
                "shutter",
                "--camera",
                "sim",
                "--exposure",
                "200us",
                "--bin-lines",
                "4",
                "--downsample",
                "2",
                "--out",
                str(sh),
            ]
        )
        == 0
    )
    cal = load_calibration(sh, expect="shutter")
    assert cal.data.shape[1] == 32 and cal.metadata["timing"]["exposure_lines"] == 20
    dk = tmp_path / "darks.npz"
    assert (
        main(
            [
                "calibrate",
                "darks",
                "--camera",
                "sim",
                "--source",
                "sim",
                "--frames",
                "4",
                "--settle",
                "0",
                "--out",
                str(dk),
            ]
        )
        == 0
    )
    assert load_calibration(dk).kind == "pixel-maps"
    assert "hot" in capsys.readouterr().out


def test_calibrate_darks_reports_the_simulated_read_noise(tmp_path, capsys):
    """It printed "noise 0": the median per-pixel std of quantised frames."""
    import re

    from drivers.simcam import SimulatedCamera

    out = tmp_path / "darks.npz"
    argv = ["calibrate", "darks", "--camera", "sim", "--no-prompt", "--frames", "16",
            "--settle", "0", "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    m = re.search(r"noise (\S+) ADU rms \(sqrt of the mean per-pixel temporal variance", text)
    assert m, text
    cam = SimulatedCamera(80, 64)  # calibrate's simulated camera: default noise and gain
    configured = cam.read_noise_e * cam.adu_per_electron
    assert configured / 2 < float(m.group(1)) < 2 * configured
    meta = load_calibration(out, expect="pixel-maps").metadata
    assert meta["dark_noise_adu"] == pytest.approx(float(m.group(1)), rel=1e-2)


def test_calibrate_filters(tmp_path, capsys):
    cube = np.random.default_rng(0).uniform(0, 2, (16, 20, 5)).astype(np.float32)
    np.save(tmp_path / "cube.npy", cube)
    out = tmp_path / "cube.tif"
    assert (
        main(
            [
                "calibrate",
                "filters",
                "--cube",
                str(tmp_path / "cube.npy"),
                "--sensor",
                "16x20",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert load_calibration(out).data.shape == (5, 16, 20)
    assert (
        main(
            [
                "calibrate",
                "filters",
                "--cube",
                str(tmp_path / "cube.npy"),
                "--sensor",
                "16x21",
                "--out",
                str(tmp_path / "bad.tif"),
            ]
        )
        == 2
    )
    assert "does not match the 16x21 sensor" in capsys.readouterr().err
    assert not (tmp_path / "bad.tif").exists()


def test_calibrate_needs_a_subcommand():
    with pytest.raises(SystemExit):
        main(["calibrate"])


def test_snap_and_calibrate_use_one_simulated_camera(tmp_path, capsys):
    """A PSF calibrated on the simulated camera reconstructs a frame snapped from it (the two
    commands simulated different cameras: 64x80 through a PSF, 96x128 without one)."""
    from drivers.simcam import demo_pattern
    from recon.io import read_reconstruction

    psf, frame, rec = tmp_path / "psf.tif", tmp_path / "f.tif", tmp_path / "r.tif"
    assert main(["calibrate", "psf", "--camera", "sim", "--source", "sim", "--frames",
                 "2", "--darks", "2", "--settle", "0", "--out", str(psf)]) == 0
    assert main(["snap", "--camera", "sim", "--out", str(frame)]) == 0
    assert main(["recon", "fista", "--psf", str(psf), "--meas", str(frame), "--dark",
                 "100", "--out", str(rec)]) == 0
    capsys.readouterr()
    x = read_reconstruction(rec)[0][0, 0]
    truth = demo_pattern(64, 80)
    # 0.994; 0.985 while --dark was taken off the (dark-subtracted) calibrated PSF too
    assert np.corrcoef(x.ravel(), truth.ravel())[0, 1] > 0.99


def test_sigterm_during_a_capture_cleans_up_like_ctrl_c(tmp_path):
    """kill / timeout / a closed terminal left the light on, the simulated firmware running
    and its temporary folder behind; SIGTERM now stops the command as Ctrl-C does."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    env = {**os.environ, "TMPDIR": str(tmp_path), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "app", "calibrate", "psf", "--camera", "sim", "--source", "sim",
         "--frames", "100000", "--settle", "0", "--out", str(tmp_path / "p.tif")],
        cwd=Path(__file__).resolve().parents[2], env=env, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob("lenslesscam-cal-*/light-state.json")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.2)
        time.sleep(2.0)  # into the capture
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert not list(tmp_path.glob("lenslesscam-cal-*"))  # firmware stopped, folder removed
    assert not (tmp_path / "p.tif").exists()


def _live_children(pid: int) -> list[int]:
    return [p for p, _ in children_of(pid)]


def _start_capture(tmp_path):
    """A ``calibrate psf`` run with the simulated source, as the foreground job of a terminal
    (its own process group); returns it and its firmware's pid once it is capturing."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    env = {**os.environ, "TMPDIR": str(tmp_path), "OMP_NUM_THREADS": "1"}

    def foreground() -> None:
        # a terminal's foreground job takes SIGINT; a test run started in the background of a
        # shell (`cmd &`) ignores it, and children inherit that: the command then never saw
        # the test's Ctrl-C (60 s timeout in CI runs started with `&`)
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    proc = subprocess.Popen(
        [sys.executable, "-m", "app", "calibrate", "psf", "--camera", "sim", "--source", "sim",
         "--frames", "100000", "--settle", "0", "--out", str(tmp_path / "p.tif")],
        cwd=Path(__file__).resolve().parents[2], env=env, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=foreground)
    try:
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob("lenslesscam-cal-*/light-state.json")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.2)
        firmware = _live_children(proc.pid)
        assert len(firmware) == 1, firmware
        time.sleep(2.0)  # into the capture
    except BaseException:
        proc.kill()
        proc.communicate()
        raise
    return proc, firmware[0]


@pytest.mark.skipif(not HAS_PROC, reason="reads processes from Linux /proc")
def test_ctrl_c_in_the_terminal_switches_the_source_off_quietly(tmp_path):
    """Ctrl-C sends SIGINT to the whole foreground process group: the simulated firmware died
    first and the clean-up then warned "could not switch the point source off". The firmware
    now runs in its own session: the light goes off, then the firmware is stopped."""
    import os
    import signal

    proc, fw = _start_capture(tmp_path)
    try:
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal does on Ctrl-C
        _out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert "could not switch the point source off" not in err, err
    assert not alive(fw)  # no orphan firmware
    assert not list(tmp_path.glob("lenslesscam-cal-*"))  # folder removed
    assert not (tmp_path / "p.tif").exists()


@pytest.mark.skipif(not HAS_PROC, reason="reads processes from Linux /proc")
def test_firmware_exits_when_the_calibrate_process_is_killed(tmp_path):
    """SIGKILL gives the command no clean-up: its firmware (in its own session, out of reach
    of the terminal's signals) notices that its parent is gone and exits by itself, removing
    the command's temporary folder (before, /tmp/lenslesscam-cal-* was left behind)."""
    import os
    import signal
    import time

    proc, fw = _start_capture(tmp_path)
    try:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        deadline = time.monotonic() + 10
        while alive(fw) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not alive(fw), "the simulated firmware outlived its parent"
        # and took the command's temporary folder (its state file) with it
        assert not list(tmp_path.glob("lenslesscam-cal-*"))
    finally:
        if alive(fw):
            os.kill(fw, signal.SIGKILL)
        proc.communicate(timeout=30)  # the firmware held its stderr open


def test_a_darks_calibration_is_a_dark_file(tmp_path, capsys):
    """`calibrate darks`'s own file as `--dark` was "contains several arrays (dark_mean, ...):
    choose one with --key" (recon has no --key); its mean dark is the dark frame."""
    from recon.io import read_reconstruction
    from recon.simulate import synthetic_psf

    darks = tmp_path / "darks.npz"
    assert main(["calibrate", "darks", "--camera", "sim", "--no-prompt", "--frames", "4",
                 "--settle", "0", "--out", str(darks)]) == 0
    dark_mean = np.load(darks)["dark_mean"]
    np.save(tmp_path / "dark_frame.npy", dark_mean)
    rng = np.random.default_rng(0)
    frame = (dark_mean + rng.integers(0, 2000, dark_mean.shape)).astype(np.uint16)
    np.save(tmp_path / "frame.npy", frame)
    np.save(tmp_path / "psf.npy", synthetic_psf(dark_mean.shape, seed=1))
    out = {}
    for name, dark in (("maps", darks), ("plain", tmp_path / "dark_frame.npy")):
        argv = ["recon", "fista", "--psf", str(tmp_path / "psf.npy"), "--meas",
                str(tmp_path / "frame.npy"), "--dark", str(dark), "--psf-dark", "0", "--tau",
                "1e-3", "--iters", "10", "--out", str(tmp_path / f"{name}.tif")]
        assert main(argv) == 0, capsys.readouterr().err
        out[name] = read_reconstruction(tmp_path / f"{name}.tif")[0]
    np.testing.assert_allclose(out["maps"], out["plain"], rtol=0, atol=1e-6)


def test_one_dark_frame_reports_the_noise_unknown_and_is_still_a_dark_file(tmp_path, capsys):
    """`calibrate darks --frames 1` printed and saved "noise 0": one frame has no temporal
    noise. The file (noise None in its metadata) still serves as --dark and --mask."""
    from recon.simulate import synthetic_psf

    darks = tmp_path / "darks.npz"
    assert main(["calibrate", "darks", "--camera", "sim", "--no-prompt", "--frames", "1",
                 "--settle", "0", "--out", str(darks)]) == 0
    text = capsys.readouterr().out
    assert "noise: unknown (one dark frame; capture 2 or more with --frames)" in text
    assert "noise 0" not in text
    meta = load_calibration(darks, expect="pixel-maps").metadata
    assert meta["dark_noise_adu"] is None
    dark_mean = np.load(darks)["dark_mean"]
    frame = (dark_mean + np.random.default_rng(0).integers(0, 2000, dark_mean.shape))
    np.save(tmp_path / "frame.npy", frame.astype(np.uint16))
    np.save(tmp_path / "psf.npy", synthetic_psf(dark_mean.shape, seed=1))
    argv = ["recon", "fista", "--psf", str(tmp_path / "psf.npy"), "--meas",
            str(tmp_path / "frame.npy"), "--dark", str(darks), "--mask", str(darks),
            "--psf-dark", "0", "--tau", "1e-3", "--iters", "5", "--out", str(tmp_path / "r.tif")]
    assert main(argv) == 0, capsys.readouterr().err
    capsys.readouterr()


def test_calibrate_psf_prints_the_report_of_the_cropped_psf(tmp_path, capsys):
    """--shape printed the uncropped capture's report; a crop that cuts off much of the PSF's
    light is warned about in one line."""
    from calibration.psf import psf_quality

    out = tmp_path / "psf.tif"
    assert main(["calibrate", "psf", "--camera", "sim", "--source", "sim", "--frames", "2",
                 "--darks", "2", "--settle", "0", "--shape", "32x40", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    cal = load_calibration(out, expect="psf")
    q = cal.metadata["quality"]
    assert cal.data.shape == (32, 40)
    assert f"wrote {out} (32x40)" in captured.out
    assert f"peak {float(cal.data.max()):.4g} ADU" in captured.out
    assert f"support {q['support_pixels']} px ({100 * q['support_fraction']:.1f}%)" in captured.out
    again = psf_quality(cal.data, noise_adu=q["noise_adu"], peak_fraction=q["peak_fraction"],
                        saturated_pixels=0)
    assert again.summary() in captured.out  # the report of what was saved
    assert cal.metadata["quality_as_captured"]["peak_adu"] > q["peak_adu"]
    warnings = [ln for ln in captured.err.splitlines() if "warning" in ln]
    assert len(warnings) == 1, captured.err
    assert warnings[0].startswith("lenslesscam: warning: the crop to 32x40 of the 64x80 "
                                  "capture leaves out ")


def test_pixel_maps_of_another_size_are_one_line_naming_both_sizes(tmp_path, capsys):
    """Pixel maps of a 32x40 sensor with a 64x80 camera: "operands could not be broadcast
    together with shapes (64,80) (32,40)"; as --dark, shapes as tuples and no dark file."""
    small = tmp_path / "small.npz"
    assert main(["calibrate", "darks", "--camera", "sim", "--sim-size", "32x40", "--no-prompt",
                 "--frames", "2", "--settle", "0", "--out", str(small)]) == 0
    capsys.readouterr()
    out = tmp_path / "psf.tif"
    assert main(["calibrate", "psf", "--camera", "sim", "--source", "sim", "--frames", "2",
                 "--darks", "2", "--settle", "0", "--pixel-maps", str(small),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "broadcast" not in err
    assert err.startswith(f"lenslesscam calibrate: error: --pixel-maps {small} is 32x40 (rows x "
                          "columns) and the camera's frames are 64x80")
    assert not out.exists()
    np.save(tmp_path / "frame.npy", np.full((64, 80), 500, dtype=np.uint16))
    np.save(tmp_path / "psf.npy", np.ones((64, 80), dtype=np.float32))
    argv = ["recon", "fista", "--psf", str(tmp_path / "psf.npy"), "--meas",
            str(tmp_path / "frame.npy"), "--dark", str(small), "--psf-dark", "0",
            "--iters", "2", "--out", str(tmp_path / "r.tif")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert (f"dark file {small} is 32x40 (rows x columns) and the measurement file "
            f"{tmp_path / 'frame.npy'} is 64x80") in err


def test_calibrate_shutter_bins_follow_the_downsampling_and_an_unusable_file_is_not_written(
        tmp_path, capsys):
    """--downsample 3 with the default 1-line bins wrote 41 bins for 21 rows, a file recon
    and simulate then refused (K > rows): the bins now default to the rows' width, and more
    bins than rows are refused before anything is written, in the words recon uses."""
    from recon.checks import check_shutter_frames

    sh = tmp_path / "sh.npz"
    assert main(["calibrate", "shutter", "--camera", "sim", "--downsample", "3",
                 "--out", str(sh)]) == 0
    capsys.readouterr()
    k, rows = load_calibration(sh, expect="shutter").data.shape
    check_shutter_frames(k, rows)  # what recon and simulate check: usable
    assert rows == 21
    bad = tmp_path / "bad.npz"
    assert main(["calibrate", "shutter", "--camera", "sim", "--downsample", "3",
                 "--bin-lines", "1", "--out", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "time bins for 21 rows" in err and "--bin-lines" in err, err
    assert not bad.exists()
    # a long exposure: the default bins widen until the rows resolve them (1-line bins made
    # 331 for 64 rows), with the scan (--source) as without it
    for extra in ([], ["--source", "sim", "--frames-per-delay", "1"]):
        long = tmp_path / f"long{len(extra)}.npz"
        assert main(["calibrate", "shutter", "--camera", "sim", "--exposure", "3ms", *extra,
                     "--out", str(long)]) == 0, capsys.readouterr().err
        capsys.readouterr()
        k, rows = load_calibration(long, expect="shutter").data.shape
        check_shutter_frames(k, rows)
        assert k > rows // 2  # as fine as the rows allow, not needlessly coarse


def test_a_camera_that_fails_or_lacks_a_feature_is_one_line(tmp_path, capsys):
    """`calibrate` printed a traceback for a camera that does not open (CameraError) and for
    --exposure on a camera without that feature (FeatureNotAvailable); snap said one line."""
    import cv2

    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(20):
        cv2.imwrite(str(seq / f"{i:04d}.png"),
                    np.random.default_rng(i).integers(0, 4000, (24, 32)).astype(np.uint16))
    cases = [
        (["calibrate", "darks", "--camera", "v4l2:/dev/null", "--out", tmp_path / "a.npz",
          "--no-prompt"], "cannot open v4l2 file '/dev/null'"),
        (["calibrate", "darks", "--camera", f"v4l2:{seq}/%04d.png", "--out", tmp_path / "b.npz",
          "--no-prompt", "--exposure", "1ms"], "exposure"),
    ]
    for argv, words in cases:
        code = main([str(a) for a in argv])
        err = capsys.readouterr().err
        assert code == 2, err
        lines = [ln for ln in err.strip().splitlines() if ln]
        assert len(lines) == 1 and lines[0].startswith("lenslesscam calibrate: error: "), err
        assert words in lines[0], err
    assert not (tmp_path / "a.npz").exists() and not (tmp_path / "b.npz").exists()


def test_a_file_sequence_is_never_looped_by_a_calibration(tmp_path, capsys):
    """16 darks from a 5-file sequence: the sequence looped, each file was averaged about three
    times as if new, and the noise and hot-pixel maps were computed on copies."""
    import cv2

    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(5):
        cv2.imwrite(str(seq / f"{i:04d}.png"),
                    np.random.default_rng(i).integers(0, 4000, (24, 32)).astype(np.uint16))
    base = ["calibrate", "darks", "--camera", f"v4l2:{seq}/%04d.png", "--no-prompt"]
    code = main([*base, "--out", str(tmp_path / "a.npz")])
    err = capsys.readouterr().err
    assert code == 2 and "the file source ended after 5 of the 17 frames this stage reads (16 " \
        "to average, 1 skipped first to settle)" in err, err
    assert "Ask for fewer frames" in err and not (tmp_path / "a.npz").exists()
    code = main([*base, "--frames", "4", "--out", str(tmp_path / "b.npz")])
    assert code == 0, capsys.readouterr().err
    assert load_calibration(tmp_path / "b.npz").metadata["frames_averaged"] == 4


@pytest.mark.parametrize(("span", "says"), [
    ("9s", "a 9e+06 us span in at most 2000 delays needs steps of"),
    ("100s", "a 1e+08 us span ends beyond the point source's longest strobe delay"),
])
def test_a_span_the_scan_cannot_resolve_is_refused_before_the_scan(tmp_path, capsys, span,
                                                                   says):
    """--span 9s coarsened the step to milliseconds on a 100 us exposure, scanned for 13 s
    and blamed the light and its wiring ("only 0 rows saw the strobe pulses"); --span 100s
    failed on "strobe delay_us ... outside [0, 1e+07]", which does not name --span."""
    out = tmp_path / "shutter.npz"
    code = main(["calibrate", "shutter", "--source", "sim", "--span", span, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and says in err and "--span" in err, err
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
    assert not out.exists()


def test_pixel_maps_are_recorded_and_another_cameras_are_said(tmp_path, capsys):
    """A PSF's metadata did not say which pixel maps repaired it, and maps of another camera
    of the same size (a file source) were taken without a word."""
    import cv2

    from recon.formats import file_hash

    same = tmp_path / "same.npz"
    assert main(["calibrate", "darks", "--camera", "sim", "--sim-size", "32x40", "--no-prompt",
                 "--frames", "4", "--out", str(same)]) == 0
    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(6):
        cv2.imwrite(str(seq / f"{i:04d}.png"),
                    np.random.default_rng(i).integers(0, 4000, (32, 40)).astype(np.uint16))
    other = tmp_path / "other.npz"
    assert main(["calibrate", "darks", "--camera", f"v4l2:{seq}/%04d.png", "--no-prompt",
                 "--frames", "4", "--out", str(other)]) == 0
    capsys.readouterr()
    for maps, warned in ((same, False), (other, True)):
        out = tmp_path / f"psf-{maps.stem}.tif"
        assert main(["calibrate", "psf", "--source", "sim", "--sim-size", "32x40", "--frames",
                     "4", "--darks", "4", "--pixel-maps", str(maps), "--out", str(out)]) == 0
        err = capsys.readouterr().err
        meta = load_calibration(out).metadata["pixel_maps"]
        assert meta["file"] == str(maps.resolve()) and meta["file_hash"] == file_hash(maps)
        said = [ln for ln in err.splitlines() if "were taken with another camera" in ln]
        assert bool(said) == warned, err
        if warned:
            assert "backend v4l2 vs sim" in said[0] and meta["warning"] in said[0]


def test_the_simulated_source_is_the_default_with_the_simulated_camera(tmp_path, capsys):
    """`calibrate psf --out p.tif` with nothing attached: "the following arguments are
    required: --source", though the camera defaults to the simulated one."""
    out = tmp_path / "p.tif"
    assert main(["calibrate", "psf", "--frames", "4", "--darks", "4", "--out", str(out)]) == 0
    assert load_calibration(out, expect="psf").data.shape == (64, 80)
    capsys.readouterr()
    code = main(["calibrate", "psf", "--camera", "v4l2:0", "--out", str(tmp_path / "q.tif")])
    err = capsys.readouterr().err
    assert code == 2 and "--source is needed with --camera v4l2:0" in err, err
    assert not (tmp_path / "q.tif").exists()


@pytest.mark.parametrize(("argv", "says"), [
    (["psf", "--centre", "a,b"], "--centre must be 'none', 'centroid' or ROW,COL"),
    (["psf", "--centre", "nan,5"], "--centre must be 'none', 'centroid' or ROW,COL"),
    (["psf", "--source", ""], "--source is empty: give sim or the point source's serial port"),
    (["depth", "--source", "sim", "--positions", "10mm,,20mm", "--no-prompt"],
     "--positions '10mm,,20mm' has an empty entry"),
])
def test_option_typos_are_named(tmp_path, capsys, argv, says):
    """'could not convert string to float: a' did not name --centre; an empty --positions
    entry was dropped; --source '' answered in the app's words."""
    out = tmp_path / "x.tif"
    code = main(["calibrate", *argv, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and says in err, err
    assert not out.exists()


def test_calibrate_filters_takes_the_sensor_size_like_a_calibration_file(tmp_path, capsys):
    """--like darks.npz (its help: 'a PSF or calibration file of the sensor's size') was refused
    as 'several arrays'; a shutter file, whose array is (time bins, rows), is not a size."""
    pm = tmp_path / "pm.npz"
    assert main(["calibrate", "darks", "--camera", "sim", "--sim-size", "32x40", "--no-prompt",
                 "--frames", "2", "--out", str(pm)]) == 0
    np.save(tmp_path / "cube.npy", np.random.default_rng(0).random((3, 32, 40)))
    out = tmp_path / "cube.tif"
    code = main(["calibrate", "filters", "--cube", str(tmp_path / "cube.npy"), "--like", str(pm),
                 "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert load_calibration(out).data.shape == (3, 32, 40)
    shutter = tmp_path / "shutter.npz"
    assert main(["calibrate", "shutter", "--camera", "sim", "--sim-size", "32x40",
                 "--out", str(shutter)]) == 0
    capsys.readouterr()
    code = main(["calibrate", "filters", "--cube", str(tmp_path / "cube.npy"), "--like",
                 str(shutter), "--out", str(tmp_path / "c2.tif")])
    err = capsys.readouterr().err
    assert code == 2 and "is a shutter calibration" in err, err


def test_calibrate_depth_uses_and_records_its_pixel_maps(tmp_path, capsys):
    """`calibrate depth --pixel-maps` was accepted and ignored: no pixel was repaired and the
    stack did not say which maps it had."""
    from recon.formats import file_hash

    pm = tmp_path / "pm.npz"
    assert main(["calibrate", "darks", "--camera", "sim", "--sim-size", "32x40", "--no-prompt",
                 "--frames", "4", "--out", str(pm)]) == 0
    out = tmp_path / "stack.tif"
    assert main(["calibrate", "depth", "--source", "sim", "--sim-size", "32x40", "--positions",
                 "a,b", "--no-prompt", "--frames", "4", "--darks", "4", "--pixel-maps", str(pm),
                 "--out", str(out)]) == 0, capsys.readouterr().err
    meta = load_calibration(out).metadata
    assert meta["pixel_maps"]["file_hash"] == file_hash(pm)
    # a size that does not fit the maps is refused, as for calibrate psf
    code = main(["calibrate", "depth", "--source", "sim", "--sim-size", "24x40", "--positions",
                 "a", "--no-prompt", "--frames", "2", "--darks", "2", "--pixel-maps", str(pm),
                 "--out", str(tmp_path / "s2.tif")])
    err = capsys.readouterr().err
    assert code == 2 and "the maps belong to another sensor size" in err, err


def test_calibrate_filters_key_on_a_file_without_variables_is_named(tmp_path, capsys):
    """--key nope on a .npy cube was ignored without a word (a typo of the file, or of the
    key, passed unnoticed)."""
    np.save(tmp_path / "cube.npy", np.random.default_rng(0).random((3, 8, 10)))
    code = main(["calibrate", "filters", "--cube", str(tmp_path / "cube.npy"), "--key", "nope",
                 "--sensor", "8x10", "--out", str(tmp_path / "c.tif")])
    err = capsys.readouterr().err
    assert code == 2 and "--key nope names a variable of a .mat or .npz file" in err, err
    assert not (tmp_path / "c.tif").exists()
