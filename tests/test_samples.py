"""Tests of the bundled sample data and recon.samples."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon import io as rio
from recon import samples
from recon.formats import file_hash
from recon.psfcheck import PsfWarning


def _finite_nonneg(a: np.ndarray) -> None:
    assert a.dtype == np.float32
    assert np.isfinite(a).all()
    assert a.min() >= 0


def test_tutorial_samples() -> None:
    psf = samples.tutorial_psf()
    meas = samples.tutorial_measurement()
    assert psf.shape == (1, 150, 200) and meas.shape == (1, 150, 200)
    _finite_nonneg(psf)
    _finite_nonneg(meas)
    assert psf.sum() == pytest.approx(1.0, rel=1e-5)
    assert meas.max() == pytest.approx(1.0)
    rio.check_pair(psf, meas)
    counts = samples.tutorial_psf(normalise=None)
    assert counts.max() > 1000  # stored in counts, dark subtracted


def test_lensed_scenes() -> None:
    assert samples.lensed_scene_names() == ("im408", "im740", "im65")
    for name in samples.lensed_scene_names():
        s = samples.lensed_scene(name)
        assert s.shape == (1, 1, 150, 200)
        _finite_nonneg(s)
        assert s.max() <= 1.0 and s.std() > 0.05
    with pytest.raises(ValueError, match="unknown lensed scene 'im1'"):
        samples.lensed_scene("im1")


def test_depth_samples() -> None:
    stack = samples.depth_psf_stack()
    meas = samples.depth_measurement()
    assert stack.shape == (22, 135, 160) and meas.shape == (1, 135, 160)
    _finite_nonneg(stack)
    _finite_nonneg(meas)
    assert stack.max() == pytest.approx(1.0)
    assert all(stack[k].sum() > 0 for k in range(22))
    rio.check_pair(stack, meas, psf_is_stack=True)
    planes = samples.depth_planes()
    assert planes[0] == (0, 1) and planes[-1] == (42, 43) and len(planes) == 22


def test_bundle_size_and_manifest() -> None:
    files = [p for p in samples.SAMPLES_DIR.iterdir() if p.is_file()]
    assert sum(p.stat().st_size for p in files) < 2_000_000
    manifest = json.loads(samples.sample_path("manifest").read_text())
    assert manifest["format"] == "lenslesscam.samples"
    for name, info in manifest["files"].items():
        p = samples.SAMPLES_DIR / name
        assert p.stat().st_size == info["bytes"]
        assert file_hash(p) == info["sha256_16"], f"{name} differs from its manifest"
    assert manifest["tutorial"]["dark_level"] == pytest.approx(34.08)
    assert manifest["depth"]["dark_level"] == 100.0
    assert "BSD-3-Clause" in (samples.SAMPLES_DIR / "README.md").read_text()
    with pytest.raises(ValueError, match="unknown sample"):
        samples.sample_path("nope")


def test_prepare_lensed_scene_orientation() -> None:
    # An upright RGB image with a distinct value everywhere, stored as the dataset stores it.
    h, w = 6, 8
    rgb = np.arange(h * w * 3, dtype=np.float32).reshape(h, w, 3) / (h * w * 3)
    stored = rgb[::-1, :, ::-1]  # upside down, BGR
    out = samples.prepare_lensed_scene(stored, (h, w), gray=False)
    assert out.shape == (3, 1, h, w) and out.dtype == np.float32
    np.testing.assert_array_equal(out[:, 0], np.moveaxis(rgb, -1, 0))
    # red channel of the top-left pixel is the first value of the upright image
    assert out[0, 0, 0, 0] == rgb[0, 0, 0] == 0.0

    gray = samples.prepare_lensed_scene(stored, (h, w), gray=True)
    expected = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
    np.testing.assert_allclose(gray[0, 0], expected, rtol=1e-5, atol=1e-7)


def test_prepare_lensed_scene_crop_and_resize() -> None:
    wide = np.zeros((6, 12, 3), dtype=np.float32)
    wide[:, 2:10] = 1.0  # the central 4:3 part is 1, the margins 0
    out = samples.prepare_lensed_scene(wide, (6, 8), gray=False)
    assert (out == 1.0).all()
    tall = np.zeros((10, 8, 3), dtype=np.float32)
    tall[2:8] = 0.5
    assert (samples.prepare_lensed_scene(tall, (6, 8)) == 0.5).all()
    big = np.ones((12, 16, 3), dtype=np.float32)
    big[::-1][:6, :8] = 0.0  # stored bottom half-left... upright top-left quadrant is 0
    down = samples.prepare_lensed_scene(big, (3, 4), gray=True)
    assert down.shape == (1, 1, 3, 4)
    assert down[0, 0, 0, 0] == 0.0 and down[0, 0, -1, -1] == pytest.approx(1.0)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        samples.prepare_lensed_scene(np.zeros((6, 8)), (6, 8))


def test_shared_data_dir_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LENSLESSCAM_SHARED_DATA", str(tmp_path))
    assert samples.shared_data_dir() == tmp_path
    monkeypatch.setenv("LENSLESSCAM_SHARED_DATA", str(tmp_path / "absent"))
    assert samples.shared_data_dir() is None


# ------------------------------------------------------------------------------------------
# Against the full data (skipped when ../shared/data is absent)
# ------------------------------------------------------------------------------------------

SHARED = samples.shared_data_dir()
needs_shared = pytest.mark.skipif(SHARED is None, reason="shared real data not available")


def assert_rebuilt_close(rebuilt: np.ndarray, bundled: np.ndarray, what: str) -> None:
    """A rebuilt float sample equals the bundled one up to the last bits of its dtype.

    Why a tolerance: the samples are box means (sums of 4-64 float32 values) and numpy's
    SIMD kernels sum in a different order on different CPUs (AVX-512 vs AVX2), so a few
    elements differ in the last bit (8 of 30000 on an AVX-512 machine; float16 samples
    inherit a flip when a float32 sum sits on a rounding boundary). Allowed: 4 units of the
    dtype's epsilon times the array's peak, on at most 1 % of the elements. The bundled
    files themselves are checked bit for bit against samples.json by their hashes
    (test_bundle_size_and_manifest).
    """
    assert rebuilt.shape == bundled.shape and rebuilt.dtype == bundled.dtype, what
    if rebuilt.dtype.kind != "f":
        np.testing.assert_array_equal(rebuilt, bundled, err_msg=what)
        return
    a, b = rebuilt.astype(np.float64), bundled.astype(np.float64)
    tol = 4 * float(np.finfo(rebuilt.dtype).eps) * float(np.abs(b).max())
    np.testing.assert_allclose(a, b, rtol=0, atol=tol, err_msg=what)
    assert np.count_nonzero(a != b) <= 0.01 * a.size, f"{what}: too many elements differ"


def test_assert_rebuilt_close_catches_real_changes() -> None:
    base = np.linspace(0, 1000, 30000, dtype=np.float32)
    last_bit = base.copy()
    last_bit[::3750] = np.nextafter(last_bit[::3750], np.float32(np.inf))  # 8 elements
    assert_rebuilt_close(last_bit, base, "last bit")
    with pytest.raises(AssertionError):
        assert_rebuilt_close(base * np.float32(1.001), base, "0.1 % change")
    many = np.nextafter(base, np.float32(np.inf))  # every element one ulp off
    with pytest.raises(AssertionError, match="too many"):
        assert_rebuilt_close(many, base, "all elements")


@pytest.mark.realdata
@needs_shared
def test_build_samples_reproduces_bundle(tmp_path: Path) -> None:
    assert SHARED is not None
    written = samples.build_samples(SHARED, tmp_path)
    for p in written:
        if p.suffix == ".npy":
            assert_rebuilt_close(np.load(p), np.load(samples.SAMPLES_DIR / p.name), p.name)
        elif p.suffix == ".npz":
            with np.load(p) as a, np.load(samples.SAMPLES_DIR / p.name) as b:
                assert sorted(a.files) == sorted(b.files)
                for k in a.files:
                    assert_rebuilt_close(a[k], b[k], f"{p.name}:{k}")
        elif p.suffix == ".mat":
            assert p.read_bytes() == (samples.SAMPLES_DIR / p.name).read_bytes()


@pytest.mark.realdata
@needs_shared
def test_loaders_on_full_files_match_samples() -> None:
    assert SHARED is not None
    tut = SHARED / "diffusercam_tutorial"
    with pytest.warns(PsfWarning, match=r"psf_sample.tif looks saturated: 192 pixels"):
        psf = rio.load_psf(tut / "psf_sample.tif", dark="auto", downsample=8)  # 12-bit clipped
    np.testing.assert_allclose(psf, samples.tutorial_psf(), rtol=1e-5, atol=1e-9)
    dark = float(rio.auto_dark_level(rio.load_image(tut / "psf_sample.tif")).item())
    meas = rio.load_measurement(tut / "rawdata_hand_sample.tif", dark=dark, downsample=8)
    np.testing.assert_allclose(meas, samples.tutorial_measurement(), rtol=1e-5, atol=1e-7)
    d3 = rio.load_measurement(SHARED / "diffusercam_3d" / "example_raw.png", dark=100, downsample=2)
    np.testing.assert_allclose(d3, samples.depth_measurement(), rtol=1e-5, atol=1e-7)


@pytest.mark.realdata
@needs_shared
def test_rgb_lensed_scene_matches_gray() -> None:
    rgb = samples.lensed_scene("im65", rgb=True)
    assert rgb.shape == (3, 1, 150, 200)
    _finite_nonneg(rgb)
    np.testing.assert_allclose(rio.to_gray(rgb), samples.lensed_scene("im65"), atol=1e-6)
    # the butterfly is orange: red above blue on average in the upright RGB image
    assert rgb[0].mean() > rgb[2].mean()
