"""Tests of recon.io: loaders for every format, preprocessing, validation, saving."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import scipy.io
import tifffile
from PIL import Image

from recon import io as rio
from recon.formats import FORMAT_VERSION, FormatError
from recon.psfcheck import PsfWarning

RNG = np.random.default_rng(1234)


def _u16(shape: tuple[int, ...]) -> np.ndarray:
    return RNG.integers(0, 65535, size=shape, dtype=np.uint16)


# ------------------------------------------------------------------------------------------
# load_image: every format
# ------------------------------------------------------------------------------------------


def test_tiff_single_and_multipage(tmp_path: Path) -> None:
    a = _u16((20, 30))
    tifffile.imwrite(tmp_path / "one.tif", a)
    got = rio.load_image(tmp_path / "one.tif")
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, a)

    stack = _u16((4, 20, 30))
    with tifffile.TiffWriter(tmp_path / "stack.tiff") as tw:
        for page in stack:
            tw.write(page, contiguous=False)
    got = rio.load_image(tmp_path / "stack.tiff")
    assert got.shape == (4, 20, 30)
    np.testing.assert_array_equal(got, stack)


def test_png_8bit_gray_and_rgb_order(tmp_path: Path) -> None:
    g = RNG.integers(0, 255, size=(10, 12), dtype=np.uint8)
    Image.fromarray(g).save(tmp_path / "g.png")
    got = rio.load_image(tmp_path / "g.png")
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, g)

    rgb = np.zeros((10, 12, 3), dtype=np.uint8)
    rgb[..., 0] = 200  # red
    rgb[..., 2] = 10  # a little blue
    Image.fromarray(rgb).save(tmp_path / "c.png")
    got = rio.load_image(tmp_path / "c.png")
    assert got.shape == (10, 12, 3)
    np.testing.assert_array_equal(got, rgb)  # RGB, not OpenCV's BGR


def test_png_16bit_kept(tmp_path: Path) -> None:
    g = _u16((9, 11))
    assert cv2.imwrite(str(tmp_path / "g16.png"), g)
    got = rio.load_image(tmp_path / "g16.png")
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, g)

    rgb = _u16((9, 11, 3))
    assert cv2.imwrite(str(tmp_path / "c16.png"), rgb[..., ::-1])  # cv2 writes BGR
    got = rio.load_image(tmp_path / "c16.png")
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, rgb)


def test_npy_npz(tmp_path: Path) -> None:
    a = RNG.random((5, 6)).astype(np.float32)
    np.save(tmp_path / "a.npy", a)
    np.testing.assert_array_equal(rio.load_image(tmp_path / "a.npy"), a)

    np.savez(tmp_path / "one.npz", whatever=a)
    np.testing.assert_array_equal(rio.load_image(tmp_path / "one.npz"), a)

    b = a * 2
    np.savez(tmp_path / "two.npz", psf=a, meas=b)
    np.testing.assert_array_equal(rio.load_image(tmp_path / "two.npz", key="meas"), b)
    np.testing.assert_array_equal(rio.load_image(tmp_path / "two.npz"), a)  # 'psf' preferred
    # The measurement loader prefers 'meas' in the same file.
    m = rio.load_measurement(tmp_path / "two.npz", normalise=None)
    np.testing.assert_allclose(m[0], b)

    np.savez(tmp_path / "amb.npz", x=a, y=b)
    with pytest.raises(ValueError, match=r"several arrays \(x, y\)"):
        rio.load_image(tmp_path / "amb.npz")
    # the command line has no key option: the message says which names are read
    with pytest.raises(ValueError, match=r"none is named psf, arr_0, image, data: choose one "
                                         r"with --key"):
        rio.load_psf(tmp_path / "amb.npz")
    with pytest.raises(ValueError, match=r"no variable 'z'; available: x, y"):
        rio.load_image(tmp_path / "amb.npz", key="z")


def test_mat_v5(tmp_path: Path) -> None:
    a = RNG.random((7, 9))
    scipy.io.savemat(tmp_path / "v5.mat", {"psf": a, "other": np.ones(3)})
    got = rio.load_image(tmp_path / "v5.mat", key="psf")
    np.testing.assert_array_equal(got, a)
    with pytest.raises(ValueError, match=r"no variable 'nope'; available: .*other.*psf"):
        rio.load_image(tmp_path / "v5.mat", key="nope")


def test_mat_v73_column_major(tmp_path: Path) -> None:
    # MATLAB writes an (H, W, K) array column-major: HDF5 sees shape (K, W, H).
    a = RNG.random((7, 9, 3))
    p = tmp_path / "v73.mat"
    with h5py.File(p, "w", userblock_size=512) as fh:
        fh.create_dataset("zstack", data=a.T)
        fh.create_dataset("aux", data=np.arange(4.0))
    with open(p, "r+b") as fh:  # MATLAB's text header lives in the user block
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 .")
    got = rio.load_image(p, key="zstack")
    assert got.shape == (7, 9, 3)
    np.testing.assert_array_equal(got, a)
    with pytest.raises(ValueError, match=r"no variable 'psf'; available: aux, zstack"):
        rio.load_image(p, key="psf")


@pytest.mark.parametrize(
    ("name", "pattern"),
    [
        ("bad.tif", r"cannot read .*bad\.tif as TIFF"),
        ("bad.png", r"cannot read .*bad\.png as PNG"),
        ("bad.npy", r"cannot read .*bad\.npy as NPY: not a NumPy \.npy file \(no NPY header\)$"),
        ("bad.npz", r"cannot read .*bad\.npz as NPZ"),
        ("bad.mat", r"cannot read .*bad\.mat as MATLAB"),
    ],
)
def test_corrupt_files(tmp_path: Path, name: str, pattern: str) -> None:
    p = tmp_path / name
    p.write_bytes(b"this is not an image at all" * 10)
    with pytest.raises(ValueError, match=pattern):
        rio.load_image(p)


def test_npy_of_python_objects_is_refused_without_advice_to_unpickle(tmp_path: Path) -> None:
    p = tmp_path / "obj.npy"
    np.save(p, np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="holds Python objects") as info:
        rio.load_image(p)
    assert "allow_pickle" not in str(info.value)


def test_truncated_tiff(tmp_path: Path) -> None:
    p = tmp_path / "t.tif"
    tifffile.imwrite(p, _u16((50, 50)))
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"t\.tif"):
        rio.load_image(p)


def test_missing_and_unknown(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nothere\.tif"):
        rio.load_image(tmp_path / "nothere.tif")
    p = tmp_path / "x.xyz"
    p.write_bytes(b"1")
    with pytest.raises(ValueError, match=r"unknown image file extension '\.xyz'"):
        rio.load_image(p)


# ------------------------------------------------------------------------------------------
# Preprocessing
# ------------------------------------------------------------------------------------------


def test_subtract_dark_modes() -> None:
    a = np.full((20, 20), 10, dtype=np.uint16)
    a[5:15, 5:15] = 4
    out = rio.subtract_dark(a, 3.0)
    assert out.dtype == np.float32
    assert out[0, 0] == 7.0
    auto = rio.subtract_dark(a, "auto")
    assert auto[5, 5] == 0.0 and auto[0, 0] == 6.0
    frame = np.arange(400, dtype=np.float32).reshape(20, 20)
    np.testing.assert_array_equal(rio.subtract_dark(a, frame), a.astype(np.float32) - frame)
    # per channel 'auto' level
    c = np.stack([a, a * 2]).astype(np.float32)
    lv = rio.auto_dark_level(c)
    np.testing.assert_array_equal(lv.ravel(), [4.0, 8.0])
    with pytest.raises(ValueError, match=r"dark frame shape \(3, 3\) does not match image shape"):
        rio.subtract_dark(a, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="smaller than the 15x15 corner"):
        rio.subtract_dark(np.ones((10, 10)), "auto")
    # a scalar level is the sensor's black offset: a negative one (a spec file's dark = -5)
    # would add a pedestal instead
    with pytest.raises(ValueError, match="dark level must be a finite number >= 0"):
        rio.subtract_dark(a, -5.0)


def test_box_downsample_values_and_remainder() -> None:
    a = np.arange(5 * 7, dtype=np.uint16).reshape(5, 7)
    out = rio.box_downsample(a, 2)
    assert out.shape == (2, 3) and out.dtype == np.float32
    assert out[0, 0] == (0 + 1 + 7 + 8) / 4
    assert out[1, 2] == (18 + 19 + 25 + 26) / 4
    stack = np.ones((3, 8, 8), dtype=np.float64)
    assert rio.box_downsample(stack, 4).shape == (3, 2, 2)
    assert rio.box_downsample(stack, 4).dtype == np.float64
    with pytest.raises(ValueError, match="positive integer"):
        rio.box_downsample(a, 0)
    with pytest.raises(ValueError, match="larger than the image"):
        rio.box_downsample(a, 8)


def test_normalise_clip_gray_layout() -> None:
    a = np.array([[1.0, 3.0], [0.0, -4.0]], dtype=np.float32)
    c = rio.clip_nonneg(a)
    np.testing.assert_array_equal(c, [[1, 3], [0, 0]])
    assert rio.normalise(c, "max").max() == pytest.approx(1.0)
    assert rio.normalise(c, "sum").sum() == pytest.approx(1.0)
    assert np.linalg.norm(rio.normalise(c, "l2")) == pytest.approx(1.0)
    assert rio.normalise(c, "sum").dtype == np.float32
    with pytest.raises(ValueError, match="cannot normalise by max"):
        rio.normalise(np.zeros((3, 3)), "max")
    # a sum beyond float32's range: the factor must not overflow to inf (it gave all zeros)
    huge = np.full((4, 4), 3e38, dtype=np.float32)
    n = rio.normalise(huge, "sum")
    assert n.dtype == np.float32 and n.sum() == pytest.approx(1.0)

    rgb = np.zeros((3, 2, 2), dtype=np.float32)
    rgb[1] = 1.0  # pure green
    assert rio.to_gray(rgb)[0, 0, 0] == pytest.approx(0.587)
    assert rio.to_gray(np.ones((3, 2, 2)))[0, 0, 0] == pytest.approx(1.0)

    assert rio.to_channel_first(np.zeros((5, 6))).shape == (1, 5, 6)
    assert rio.to_channel_first(np.zeros((5, 6, 3))).shape == (3, 5, 6)
    assert rio.to_channel_first(np.zeros((3, 5, 6))).shape == (3, 5, 6)
    with pytest.raises(ValueError, match="cannot tell the channel axis"):
        rio.to_channel_first(np.zeros((44, 5, 6)))


# ------------------------------------------------------------------------------------------
# load_psf / load_measurement / load_psf_stack validation
# ------------------------------------------------------------------------------------------


def _psf_file(tmp_path: Path, name: str = "psf.tif") -> tuple[Path, np.ndarray]:
    a = np.full((40, 48), 30, dtype=np.uint16)
    a[20:30, 20:34] = RNG.integers(100, 4000, size=(10, 14), dtype=np.uint16)
    p = tmp_path / name
    tifffile.imwrite(p, a)
    return p, a


def test_load_psf_pipeline(tmp_path: Path) -> None:
    p, a = _psf_file(tmp_path)
    psf = rio.load_psf(p, dark="auto", downsample=2)
    assert psf.shape == (1, 20, 24) and psf.dtype == np.float32
    assert psf.sum() == pytest.approx(1.0, rel=1e-5)
    assert psf.min() >= 0
    expected = rio.box_downsample(a.astype(np.float32) - 30.0, 2)
    np.testing.assert_allclose(psf[0], expected / expected.sum(), rtol=1e-5)
    # dark given as a file
    dark = np.full_like(a, 30)
    tifffile.imwrite(tmp_path / "dark.tif", dark)
    psf2 = rio.load_psf(p, dark=tmp_path / "dark.tif", downsample=2)
    np.testing.assert_allclose(psf2, psf, rtol=1e-6)
    # read without its dark level of 30 (17 % of its light): said (recon.psfcheck.psf_floor)
    with pytest.warns(PsfWarning, match=r"darkest pixels are at 30 counts, a floor that holds "
                      r"1\d % of its light"):
        raw = rio.load_psf(p, normalise=None)
    assert raw.max() == a.max()


def test_load_psf_rgb(tmp_path: Path) -> None:
    rgb = RNG.integers(1, 255, size=(16, 20, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "c.png")
    psf = rio.load_psf(tmp_path / "c.png", channels="rgb", normalise="max")
    assert psf.shape == (3, 16, 20)
    np.testing.assert_allclose(psf[0], rgb[..., 0] / rgb.max(), rtol=1e-6)
    gray = rio.load_psf(tmp_path / "c.png", channels="gray")
    assert gray.shape == (1, 16, 20)
    _psf_file(tmp_path, "g.tif")
    with pytest.raises(ValueError, match=r"g\.tif is grayscale; cannot load it with channels="):
        rio.load_psf(tmp_path / "g.tif", channels="rgb")


def test_load_psf_nan_inf(tmp_path: Path) -> None:
    a = np.ones((8, 8), dtype=np.float32)
    a[0:3, 0:4] = np.nan
    tifffile.imwrite(tmp_path / "n.tif", a)
    with pytest.raises(ValueError, match=r"PSF file .*n\.tif contains 12 NaN values"):
        rio.load_psf(tmp_path / "n.tif")
    b = np.ones((8, 8), dtype=np.float32)
    b[2, 2] = np.inf
    np.save(tmp_path / "i.npy", b)
    with pytest.raises(ValueError, match=r"contains 1 infinite values"):
        rio.load_measurement(tmp_path / "i.npy")


def test_load_psf_all_zero(tmp_path: Path) -> None:
    np.save(tmp_path / "z.npy", np.zeros((20, 20), dtype=np.float32))
    with pytest.raises(ValueError, match=r"PSF file .*z\.npy is all zero"):
        rio.load_psf(tmp_path / "z.npy")
    np.save(tmp_path / "flat.npy", np.full((20, 20), 7, dtype=np.uint16))
    with (
        pytest.warns(PsfWarning, match="is constant"),  # said first, then refused
        pytest.raises(ValueError, match=r"all zero or negative after dark subtraction "
                                       r"\(dark=auto\)"),
    ):
        rio.load_psf(tmp_path / "flat.npy", dark="auto")


def test_load_psf_bad_dtype_and_ndim(tmp_path: Path) -> None:
    np.save(tmp_path / "i64.npy", np.ones((8, 8), dtype=np.int64))
    with pytest.raises(ValueError, match="unsupported integer dtype int64"):
        rio.load_psf(tmp_path / "i64.npy")
    np.save(tmp_path / "b.npy", np.ones((8, 8), dtype=bool))
    with pytest.raises(ValueError, match="unsupported dtype bool"):
        rio.load_psf(tmp_path / "b.npy")
    np.save(tmp_path / "v.npy", np.ones(8, dtype=np.float32))
    with pytest.raises(ValueError, match=r"has shape \(8,\)"):
        rio.load_psf(tmp_path / "v.npy")
    tifffile.imwrite(tmp_path / "st.tif", np.ones((5, 8, 8), dtype=np.float32))
    with pytest.raises(ValueError, match="--model depth --psf-stack FILE"):
        rio.load_psf(tmp_path / "st.tif")


def test_load_measurement(tmp_path: Path) -> None:
    p, a = _psf_file(tmp_path, "m.tif")
    m = rio.load_measurement(p, dark=30)
    assert m.shape == (1, 40, 48) and m.dtype == np.float32
    assert m.max() == pytest.approx(1.0)
    raw = rio.load_measurement(p, dark=30, normalise=None)
    assert raw.max() == pytest.approx(float(a.max()) - 30)


def test_check_pair() -> None:
    rio.check_pair(np.zeros((1, 10, 12)), np.zeros((3, 10, 12)))
    with pytest.raises(
        ValueError,
        match=r"PSF shape \(1, 10, 12\) and measurement shape "
        r"\(1, 20, 24\) do not match",
    ):
        rio.check_pair(np.zeros((1, 10, 12)), np.zeros((1, 20, 24)))
    with pytest.raises(ValueError, match="has 2 channels, the measurement 3"):
        rio.check_pair(np.zeros((2, 10, 12)), np.zeros((3, 10, 12)))
    rio.check_pair(np.zeros((7, 10, 12)), np.zeros((1, 10, 12)), psf_is_stack=True)
    with pytest.raises(ValueError, match="3 axes"):
        rio.check_pair(np.zeros((10, 12)), np.zeros((1, 10, 12)))


def test_load_psf_stack_sources(tmp_path: Path) -> None:
    planes = RNG.random((3, 12, 16)).astype(np.float32) + 0.1
    files = []
    for k, pl in enumerate(planes):
        f = tmp_path / "dir" / f"psf{k:02d}.tiff"
        f.parent.mkdir(exist_ok=True)
        tifffile.imwrite(f, pl)
        files.append(f)
    s1 = rio.load_psf_stack(files)
    assert s1.shape == (3, 12, 16) and s1.dtype == np.float32
    assert s1.max() == pytest.approx(1.0)
    np.testing.assert_allclose(s1, planes / planes.max(), rtol=1e-6)
    s2 = rio.load_psf_stack(tmp_path / "dir")
    np.testing.assert_array_equal(s1, s2)
    tifffile.imwrite(tmp_path / "multi.tif", planes, photometric="minisblack")
    s3 = rio.load_psf_stack(tmp_path / "multi.tif", downsample=2, normalise=None)
    assert s3.shape == (3, 6, 8)
    np.testing.assert_allclose(s3, rio.box_downsample(planes, 2), rtol=1e-6)

    tifffile.imwrite(tmp_path / "odd.tiff", np.ones((10, 16), dtype=np.float32))
    with pytest.raises(ValueError, match=r"odd\.tiff has shape \(10, 16\), but the first plane"):
        rio.load_psf_stack([*files, tmp_path / "odd.tiff"])
    tifffile.imwrite(tmp_path / "zero.tiff", np.zeros((12, 16), dtype=np.float32))
    with pytest.raises(ValueError, match=r"plane 1 .*zero\.tiff.* is all zero"):
        rio.load_psf_stack([files[0], tmp_path / "zero.tiff"])


# ------------------------------------------------------------------------------------------
# Saving and reading reconstructions
# ------------------------------------------------------------------------------------------


def test_round_trip_image(tmp_path: Path) -> None:
    x = RNG.random((1, 1, 24, 32)).astype(np.float32)
    meta = {
        "method": "fista-tv",
        "parameters": {"tau": 1e-3, "iters": 300},
        "psf_hash": "abc",
        "np_scalar": np.float32(0.5),
    }
    paths = rio.save_reconstruction(tmp_path / "r.tif", x, meta)
    assert [p.name for p in paths] == ["r.tif", "r.png"]
    got, md = rio.read_reconstruction(tmp_path / "r.tif")
    assert got.dtype == np.float32 and got.shape == x.shape
    np.testing.assert_array_equal(got, x)
    assert md["format"] == "lenslesscam.reconstruction"
    assert md["format_version"] == FORMAT_VERSION
    assert {"versions", "host", "created_utc"} <= set(md["provenance"])
    assert md["method"] == "fista-tv" and md["parameters"]["iters"] == 300
    assert md["np_scalar"] == 0.5 and md["kind"] == "image"
    png = np.asarray(Image.open(tmp_path / "r.png"))
    assert png.shape == (24, 32) and png.dtype == np.uint8
    assert png.min() == 0 and png.max() == 255
    # our TIFF is an ordinary float32 TIFF for other tools
    assert tifffile.imread(tmp_path / "r.tif").dtype == np.float32


def test_round_trip_rgb_video(tmp_path: Path) -> None:
    x = RNG.random((3, 4, 16, 20)).astype(np.float32)
    paths = rio.save_reconstruction(tmp_path / "v.tiff", x, {"method": "udn"}, kind="video")
    assert {p.name for p in paths} == {"v.tiff", "v.png", "v.gif"}
    got, md = rio.read_reconstruction(tmp_path / "v.tiff")
    np.testing.assert_array_equal(got, x)
    assert md["shape"] == [3, 4, 16, 20] and md["kind"] == "video"
    with Image.open(tmp_path / "v.gif") as gif:
        assert gif.n_frames == 4
        assert gif.size == (20, 16)
    assert np.asarray(Image.open(tmp_path / "v.png")).ndim == 3  # RGB montage


def test_spectral_and_depth_previews(tmp_path: Path) -> None:
    k = 8
    x = np.zeros((1, k, 12, 14), dtype=np.float32)
    x[0, 0] = 1.0  # all energy in the first band
    w = np.zeros((3, k))
    w[2, 0] = 1.0  # band 0 -> blue
    paths = rio.save_reconstruction(tmp_path / "s.tif", x, kind="spectral", false_color=w)
    assert (tmp_path / "s_falsecolor.png") in paths
    fc = np.asarray(Image.open(tmp_path / "s_falsecolor.png"))
    assert fc.shape == (12, 14, 3)
    assert (fc[..., 2] == 255).all() and (fc[..., :2] == 0).all()  # pure blue
    with pytest.raises(ValueError, match=r"false_color weights must have shape \(3, K\)"):
        rio.save_reconstruction(
            tmp_path / "s2.tif", x, kind="spectral", false_color=np.ones((3, 2))
        )
    # default weights: the bundled SpectralDiffuserCam calibration
    rio.save_reconstruction(tmp_path / "s3.tif", RNG.random((1, k, 12, 14)), kind="spectral")
    assert (tmp_path / "s3_falsecolor.png").exists()

    d = np.zeros((1, 5, 10, 10), dtype=np.float32)
    d[0, 1, 2, 3] = 1.0
    d[0, 4, 7, 7] = 0.5
    rio.save_reconstruction(tmp_path / "d.tif", d, kind="depth")
    mip = np.asarray(Image.open(tmp_path / "d_mip.png"))
    assert mip[2, 3] == 255 and mip[7, 7] > 0


def test_save_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"\(C, K, H, W\)"):
        rio.save_reconstruction(tmp_path / "a.tif", np.zeros((4, 4)))
    with pytest.raises(ValueError, match="reserved"):
        rio.save_reconstruction(tmp_path / "a.tif", np.zeros((1, 1, 4, 4)), {"format": "x"})
    with pytest.raises(ValueError, match="not JSON-serialisable"):
        rio.save_reconstruction(tmp_path / "a.tif", np.zeros((1, 1, 4, 4)), {"f": object()})
    with pytest.raises(ValueError, match="kind must be one of"):
        rio.save_reconstruction(tmp_path / "a.tif", np.zeros((1, 1, 4, 4)), kind="movie")  # type: ignore[arg-type]
    assert not list(tmp_path.iterdir())


def test_read_rejects_foreign_and_corrupt(tmp_path: Path) -> None:
    tifffile.imwrite(tmp_path / "plain.tif", np.zeros((4, 4), dtype=np.float32))
    with pytest.raises(FormatError, match="not a lenslesscam reconstruction"):
        rio.read_reconstruction(tmp_path / "plain.tif")
    (tmp_path / "junk.tif").write_bytes(b"\x00" * 100)
    with pytest.raises(FormatError, match="cannot read"):
        rio.read_reconstruction(tmp_path / "junk.tif")
    with pytest.raises(FileNotFoundError):
        rio.read_reconstruction(tmp_path / "none.tif")

    x = RNG.random((1, 2, 6, 6)).astype(np.float32)
    rio.save_reconstruction(tmp_path / "ok.tif", x)
    _, md = rio.read_reconstruction(tmp_path / "ok.tif")
    # same metadata, other data: the hash check catches it
    tifffile.imwrite(
        tmp_path / "tampered.tif",
        (x + 1).reshape(2, 6, 6),
        description=json.dumps(md),
        metadata=None,
    )
    with pytest.raises(FormatError, match="hash does not match"):
        rio.read_reconstruction(tmp_path / "tampered.tif")
    newer = dict(md, format_version=FORMAT_VERSION + 1)
    tifffile.imwrite(
        tmp_path / "newer.tif", x.reshape(2, 6, 6), description=json.dumps(newer), metadata=None
    )
    with pytest.raises(FormatError, match="format_version"):
        rio.read_reconstruction(tmp_path / "newer.tif")
    wrong_shape = dict(md, shape=[1, 3, 6, 6])
    tifffile.imwrite(
        tmp_path / "shape.tif",
        x.reshape(2, 6, 6),
        description=json.dumps(wrong_shape),
        metadata=None,
    )
    with pytest.raises(FormatError, match="corrupt"):
        rio.read_reconstruction(tmp_path / "shape.tif")


def test_failed_write_keeps_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    old = RNG.random((1, 1, 8, 8)).astype(np.float32)
    rio.save_reconstruction(tmp_path / "r.tif", old, {"run": 1})
    before = sorted(p.name for p in tmp_path.iterdir())

    def broken_imwrite(path: Path, *args: object, **kwargs: object) -> None:
        Path(path).write_bytes(b"II*\x00half a file")  # partial output, then the crash
        raise OSError("disk full")

    monkeypatch.setattr(tifffile, "imwrite", broken_imwrite)
    with pytest.raises(OSError, match="disk full"):
        rio.save_reconstruction(tmp_path / "r.tif", old + 1, {"run": 2})
    monkeypatch.undo()
    got, md = rio.read_reconstruction(tmp_path / "r.tif")
    np.testing.assert_array_equal(got, old)
    assert md["run"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no temp files left


def test_contrast_stretch() -> None:
    a = np.linspace(0, 1, 10001)
    u = rio.contrast_stretch(a)
    assert u.dtype == np.uint8 and u[0] == 0 and u[-1] == 255
    assert rio.contrast_stretch(np.ones((3, 3))).max() == 0


def test_false_color_weights() -> None:
    from recon.samples import false_color_calib_path

    p = false_color_calib_path()
    m = scipy.io.loadmat(p)
    w65 = rio.load_false_color_weights(p, 65)
    assert w65.shape == (3, 65)
    np.testing.assert_allclose(w65[0], m["red"].ravel(), rtol=1e-6)
    np.testing.assert_allclose(w65[2], m["blue"].ravel(), rtol=1e-6)
    w13 = rio.load_false_color_weights(p, 13)
    assert w13.shape == (3, 13)
    np.testing.assert_allclose(w13.sum(axis=1), w65.sum(axis=1), rtol=1e-6)
    # 65 -> 13 bins of exactly 5 bands: each bin is the sum of its five bands
    np.testing.assert_allclose(w13[1], w65[1].reshape(13, 5).sum(axis=1), rtol=1e-6)
    with pytest.raises(ValueError, match="n_bands"):
        rio.load_false_color_weights(p, 0)


def test_downsample_masked_ignores_erased_pixels():
    from recon.io import downsample_masked

    meas = np.array([[[4.0, 0.0, 1.0, 3.0], [0.0, 0.0, 5.0, 7.0]]], dtype=np.float32)
    mask = np.array([[1, 0, 1, 1], [0, 0, 1, 1]], dtype=np.float32)
    out, m = downsample_masked(meas, mask, 2)
    # left block: one measured pixel (4) -> 4, not the box mean 1; right block: plain mean
    np.testing.assert_allclose(out, [[[4.0, 4.0]]])
    np.testing.assert_array_equal(m, [[1.0, 1.0]])
    out, m = downsample_masked(meas, np.zeros((2, 4)), 2)
    assert not m.any() and not out.any()
    with pytest.raises(ValueError, match="does not match"):
        downsample_masked(meas, np.ones((3, 4)), 2)


def test_every_png_carries_format_and_provenance(tmp_path: Path) -> None:
    """Previews are display images, but a file found alone still says what made it."""
    import json

    from recon.previews import PREVIEW_FORMAT, write_png

    p = write_png(tmp_path / "p.png", np.zeros((3, 4, 5), np.uint8))
    with Image.open(p) as im:
        meta = json.loads(im.text["lenslesscam"])
    assert meta["format"] == PREVIEW_FORMAT and meta["format_version"] >= 1
    assert "lenslesscam" in meta["provenance"]["versions"]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")
@pytest.mark.timeout(30)  # without the check the read waits for a writer forever
def test_a_named_pipe_is_refused_not_waited_on(tmp_path) -> None:
    """--meas given a FIFO hung forever, waiting for a writer."""
    fifo = tmp_path / "meas.npy"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="not a regular file"):
        rio.load_measurement(fifo)


def test_planes_first_read_as_colour_are_said_where_they_may_be_frames(tmp_path: Path) -> None:
    """A (4, H, W) stack was read as RGBA, its fourth frame dropped without a word, and three
    frames read as gray were mixed with the luma weights: both are said (the warning names the
    planes and what was done), while a colour image (H, W, 3) and three planes read as rgb,
    what was asked for, stay silent."""
    from recon.checks import MeasurementWarning

    rng = np.random.default_rng(0)
    frames = rng.random((4, 12, 16)).astype(np.float32) + 0.1
    for n in (4, 3):
        np.save(tmp_path / f"s{n}.npy", frames[:n])
        with pytest.warns(MeasurementWarning, match=f"has {n} planes first .*{n} frames"):
            rio.load_measurement(tmp_path / f"s{n}.npy")
    with pytest.warns(PsfWarning, match="the fourth plane is dropped"):
        rio.load_psf(tmp_path / "s4.npy", channels="rgb")
    np.save(tmp_path / "hwc.npy", np.moveaxis(frames[:3], 0, -1))
    rio.load_measurement(tmp_path / "hwc.npy")  # filterwarnings=error: silent
    rio.load_measurement(tmp_path / "s3.npy", channels="rgb")
