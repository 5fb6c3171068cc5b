"""Tests of recon.metrics and the ``lenslesscam metrics`` command."""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from recon import metrics as M

RNG = np.random.default_rng(7)


def _smooth_image(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    img = 0.5 + 0.3 * np.sin(x / 5.0) * np.cos(y / 7.0) + 0.1 * RNG.random((h, w))
    return img.astype(np.float64)


# ------------------------------------------------------------------------------------------
# A direct, slow SSIM straight from Wang et al. 2004, written independently of the module:
# explicit 11x11 Gaussian weights applied to every valid window via sliding_window_view.
# ------------------------------------------------------------------------------------------


def _gauss2d() -> np.ndarray:
    r = np.arange(11) - 5
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * 1.5**2))
    return g / g.sum()


def _slow_maps(x: np.ndarray, y: np.ndarray, L: float) -> tuple[np.ndarray, np.ndarray]:
    """(ssim map, cs map) over the valid windows of 2D images x, y."""
    w = _gauss2d()
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    wx = np.lib.stride_tricks.sliding_window_view(x, (11, 11))
    wy = np.lib.stride_tricks.sliding_window_view(y, (11, 11))
    mx = np.einsum("ijkl,kl->ij", wx, w)
    my = np.einsum("ijkl,kl->ij", wy, w)
    vx = np.einsum("ijkl,kl->ij", (wx - mx[..., None, None]) ** 2, w)
    vy = np.einsum("ijkl,kl->ij", (wy - my[..., None, None]) ** 2, w)
    cxy = np.einsum("ijkl,kl->ij", (wx - mx[..., None, None]) * (wy - my[..., None, None]), w)
    lum = (2 * mx * my + c1) / (mx**2 + my**2 + c1)
    cs = (2 * cxy + c2) / (vx + vy + c2)
    return lum * cs, cs


def _slow_ssim(x: np.ndarray, y: np.ndarray, L: float) -> float:
    return float(_slow_maps(x, y, L)[0].mean())


def _slow_ms_ssim(x: np.ndarray, y: np.ndarray, L: float, n: int = 5) -> float:
    weights = [0.0448, 0.2856, 0.3001, 0.2363, 0.1333][:n]
    if n < 5:  # the published 5 weights are used as they are (they sum to 1.0001)
        weights = [w / sum(weights) for w in weights]
    out = 1.0
    for j, wj in enumerate(weights):
        s_map, cs_map = _slow_maps(x, y, L)
        val = s_map.mean() if j == len(weights) - 1 else cs_map.mean()
        out *= max(val, 0.0) ** wj
        h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
        x = 0.25 * (x[:h:2, :w:2] + x[1:h:2, :w:2] + x[:h:2, 1:w:2] + x[1:h:2, 1:w:2])
        y = 0.25 * (y[:h:2, :w:2] + y[1:h:2, :w:2] + y[:h:2, 1:w:2] + y[1:h:2, 1:w:2])
    return out


# ------------------------------------------------------------------------------------------
# MSE / PSNR
# ------------------------------------------------------------------------------------------


def test_mse_psnr_hand_values() -> None:
    ref = np.zeros((4, 5))
    ref[0, 0] = 1.0  # range 1
    est = ref + 0.1  # MSE 0.01
    assert M.mse(ref, est) == pytest.approx(0.01)
    assert M.psnr(ref, est) == pytest.approx(20.0)
    assert M.psnr(ref, est, data_range=2.0) == pytest.approx(20.0 + 20 * math.log10(2))
    ref255 = np.full((3, 3), 100.0)
    ref255[0, 0] = 355.0  # range 255
    assert M.psnr(ref255, ref255 + 1.0) == pytest.approx(10 * math.log10(255**2))
    assert M.psnr(ref, ref) == math.inf


def test_psnr_errors() -> None:
    with pytest.raises(ValueError, match="ref is constant"):
        M.psnr(np.ones((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"shapes differ: ref \(3, 3\) vs est \(3, 4\)"):
        M.psnr(np.ones((3, 3)), np.ones((3, 4)))
    bad = np.ones((3, 3))
    bad[0, :2] = np.nan
    with pytest.raises(ValueError, match="est contains 2 NaN values"):
        M.mse(np.ones((3, 3)), bad)
    with pytest.raises(ValueError, match="ref contains 1 infinite values"):
        M.mse(np.array([np.inf, 1.0]), np.ones(2))
    with pytest.raises(ValueError, match="data_range must be positive"):
        M.psnr(np.eye(3), np.eye(3) * 0.5, data_range=0.0)


# ------------------------------------------------------------------------------------------
# SSIM / MS-SSIM
# ------------------------------------------------------------------------------------------


def test_ssim_identity_symmetry_and_noise() -> None:
    x = _smooth_image(40, 48)
    assert M.ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    y = x + 0.05 * RNG.standard_normal(x.shape)
    assert M.ssim(x, y, data_range=1.0) == pytest.approx(M.ssim(y, x, data_range=1.0), abs=1e-12)
    values = [M.ssim(x, x + s * RNG.standard_normal(x.shape)) for s in (0.01, 0.05, 0.2, 0.5)]
    assert all(a > b for a, b in itertools.pairwise(values)), values
    assert -1.0 <= M.ssim(x, -x + 1.0) < 0.5


def test_ssim_matches_direct_formula() -> None:
    x = _smooth_image(20, 24)
    y = 0.8 * x + 0.05 * RNG.standard_normal(x.shape)
    L = float(x.max() - x.min())
    assert M.ssim(x, y) == pytest.approx(_slow_ssim(x, y, L), rel=1e-10)
    # several slices: mean of per-slice values
    stack_x = np.stack([x, x[::-1]])
    stack_y = np.stack([y, y[::-1] ** 2])
    expected = np.mean([_slow_ssim(a, b, 1.0) for a, b in zip(stack_x, stack_y, strict=True)])
    assert M.ssim(stack_x[None], stack_y[None], data_range=1.0) == pytest.approx(expected)


def test_ssim_too_small() -> None:
    with pytest.raises(ValueError, match="smaller than 11x11"):
        M.ssim(np.eye(10), np.eye(10))


def test_ms_ssim_matches_direct_and_properties() -> None:
    assert M.ms_ssim_min_size() == 176
    x = _smooth_image(176, 184)
    assert M.ms_ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    y = x + 0.1 * RNG.standard_normal(x.shape)
    L = float(x.max() - x.min())
    assert M.ms_ssim(x, y) == pytest.approx(_slow_ms_ssim(x, y, L), rel=1e-10)
    z = x + 0.3 * RNG.standard_normal(x.shape)
    assert M.ms_ssim(x, z) < M.ms_ssim(x, y) < 1.0
    with pytest.raises(ValueError, match=r"image 150x200 is smaller than 176x176"):
        M.ms_ssim(np.ones((150, 200)), np.ones((150, 200)))


def test_ms_ssim_fewer_scales_for_small_images() -> None:
    assert [M.ms_ssim_scales((s, 200)) for s in (176, 175, 88, 87, 44, 22, 21)] == [
        5, 4, 4, 3, 3, 2, 0]
    x = _smooth_image(100, 120)
    y = x + 0.05 * RNG.standard_normal(x.shape)
    L = float(x.max() - x.min())
    # the first 4 weights renormalised to sum 1, checked against the direct loop
    assert M.ms_ssim(x, y, scales=4) == pytest.approx(_slow_ms_ssim(x, y, L, n=4), rel=1e-10)
    assert M.ms_ssim(x, x, scales=4) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match=r"scales must be 2\.\.5"):
        M.ms_ssim(x, y, scales=1)


# ------------------------------------------------------------------------------------------
# gain fit, per frame, spectral
# ------------------------------------------------------------------------------------------


def test_gain_fit() -> None:
    ref = RNG.random((2, 3, 8, 8)).astype(np.float32)
    scaled, g = M.gain_fit(ref, 0.5 * ref)
    assert g == pytest.approx(2.0)
    assert scaled.dtype == np.float32
    np.testing.assert_allclose(scaled, ref, rtol=1e-6)
    noisy = ref + 0.1 * RNG.standard_normal(ref.shape).astype(np.float32)
    s2, g2 = M.gain_fit(ref, noisy)
    assert M.mse(ref, s2) <= M.mse(ref, noisy)  # the LS gain never increases the error
    assert M.mse(ref, s2) <= M.mse(ref, noisy * (g2 * 1.01))
    zero_scaled, g0 = M.gain_fit(ref, np.zeros_like(ref))
    assert g0 == 1.0 and not zero_scaled.any()


def test_per_frame() -> None:
    ref = RNG.random((1, 3, 16, 16))
    est = ref.copy()
    est[:, 1] += 0.1
    vals = M.per_frame(ref, est, "psnr")
    assert len(vals) == 3 and vals[0] == math.inf and vals[2] == math.inf
    assert vals[1] == pytest.approx(M.psnr(ref[:, 1], est[:, 1]))
    fn: Callable[[np.ndarray, np.ndarray], float] = M.mse
    assert M.per_frame(ref, est, fn)[1] == pytest.approx(0.01)
    with pytest.raises(ValueError, match=r"\(C, K, H, W\)"):
        M.per_frame(ref[0], est[0], "mse")
    with pytest.raises(ValueError, match="unknown metric"):
        M.per_frame(ref, est, "lpips")


def test_spectral_cosine_distance() -> None:
    ref = RNG.random((1, 6, 5, 5)) + 0.1
    assert M.spectral_cosine_distance(ref, ref) == pytest.approx(0.0, abs=1e-12)
    # scale per pixel does not change the angle
    assert M.spectral_cosine_distance(ref, ref * RNG.random((1, 1, 5, 5))) == pytest.approx(
        0.0, abs=1e-12
    )
    a = np.zeros((2, 1, 1))
    b = np.zeros((2, 1, 1))
    a[0] = 1.0
    b[1] = 1.0
    assert M.spectral_cosine_distance(a, b) == pytest.approx(1.0)  # orthogonal spectra
    # an all-zero pixel is left out
    a2 = np.zeros((2, 1, 2))
    b2 = np.zeros((2, 1, 2))
    a2[:, 0, 0] = [1.0, 1.0]
    b2[:, 0, 0] = [1.0, 0.0]
    a2[:, 0, 1] = [1.0, 0.0]
    assert M.spectral_cosine_distance(a2, b2) == pytest.approx(1 - 1 / math.sqrt(2))
    with pytest.raises(ValueError, match="all-zero spectrum"):
        M.spectral_cosine_distance(np.zeros((2, 2, 2)), np.zeros((2, 2, 2)))


# ------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------


def test_metrics_report_small_image() -> None:
    ref = _smooth_image(150, 200)[None, None]
    est = 0.5 * ref
    rep = M.metrics_report(ref, est, gain_fit=False)
    assert rep["gain_fit"] is False and rep["gain"] == 1.0
    # 150 px is too small for 5 scales (176), enough for 4 (88): scored, and the count is said
    assert rep["ms_ssim_scales"] == 4
    assert rep["ms_ssim"] == pytest.approx(M.ms_ssim(ref, est, scales=4))
    assert rep["ms_ssim_note"].startswith("4 scales, not 5: image 150x200 smaller than 176x176")
    tiny = M.metrics_report(ref[..., :20, :20], est[..., :20, :20])
    assert tiny["ms_ssim"] is None and tiny["ms_ssim_scales"] == 0
    assert tiny["ms_ssim_note"].startswith("not computed, image 20x20 smaller than 22x22")
    assert rep["data_range_source"] == "ref.max() - ref.min()"
    assert rep["psnr"] == pytest.approx(M.psnr(ref, est))
    fitted = M.metrics_report(ref, est, gain_fit=True)
    assert fitted["gain_fit"] is True and fitted["gain"] == pytest.approx(2.0)
    assert fitted["mse"] == pytest.approx(0.0, abs=1e-20)
    assert fitted["ssim"] == pytest.approx(1.0)
    json.dumps(rep)


def test_metrics_report_large_and_errors() -> None:
    ref = _smooth_image(180, 180)
    est = ref + 0.05 * RNG.standard_normal(ref.shape)
    rep = M.metrics_report(ref, est)
    assert rep["ms_ssim"] == pytest.approx(M.ms_ssim(ref, est))
    assert 0 < rep["ssim"] < 1
    with pytest.raises(ValueError, match="shapes differ"):
        M.metrics_report(ref, est[:-1])


# ------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------


@pytest.fixture
def cli_main(monkeypatch: pytest.MonkeyPatch) -> Callable[[list[str]], int]:
    """``app.cli.main`` with only the metrics subcommand (others are tested elsewhere)."""
    from app import cli

    monkeypatch.setattr(cli, "COMMAND_MODULES", ("app.commands.metrics",))
    return cli.main


def test_cli_metrics_json(
    tmp_path: Path, cli_main: Callable[[list[str]], int], capsys: pytest.CaptureFixture[str]
) -> None:
    from PIL import Image

    from recon.io import save_reconstruction

    ref = (_smooth_image(30, 40) * 200).clip(0, 255).astype(np.uint8)
    Image.fromarray(ref).save(tmp_path / "gt.png")
    est = (ref.astype(np.float32) / 2)[None, None]
    save_reconstruction(tmp_path / "est.tif", est, {"method": "test"})
    np.save(tmp_path / "est.npy", ref.astype(np.float32))

    assert (
        cli_main(
            [
                "metrics",
                "--ref",
                str(tmp_path / "gt.png"),
                "--est",
                str(tmp_path / "est.tif"),
                "--gain-fit",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert {"mse", "psnr", "ssim", "ms_ssim", "gain", "gain_fit"} <= set(out)
    assert out["gain_fit"] is True and out["gain"] == pytest.approx(2.0)
    # 30x40 allows 2 scales; identical after the gain fit
    assert out["psnr"] == "inf" and out["ms_ssim_scales"] == 2
    assert out["ms_ssim"] == pytest.approx(1.0, abs=1e-12)  # float64 rounding only

    assert (
        cli_main(["metrics", "--ref", str(tmp_path / "gt.png"), "--est", str(tmp_path / "est.tif")])
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["gain_fit"] is False and out["gain"] == 1.0
    assert out["psnr"] == pytest.approx(M.psnr(ref.astype(float), ref / 2.0))

    assert (
        cli_main(["metrics", "--ref", str(tmp_path / "gt.png"), "--est", str(tmp_path / "est.npy")])
        == 0
    )
    assert json.loads(capsys.readouterr().out)["mse"] == 0.0


def test_cli_metrics_errors(
    tmp_path: Path, cli_main: Callable[[list[str]], int], capsys: pytest.CaptureFixture[str]
) -> None:
    np.save(tmp_path / "a.npy", np.ones((20, 20)))
    np.save(tmp_path / "b.npy", np.ones((20, 24)))
    code = cli_main(["metrics", "--ref", str(tmp_path / "a.npy"), "--est", str(tmp_path / "b.npy")])
    assert code != 0
    err = capsys.readouterr().err
    assert "shapes differ" in err and "(1, 1, 20, 20)" in err and "(1, 1, 20, 24)" in err
    code = cli_main(
        ["metrics", "--ref", str(tmp_path / "missing.png"), "--est", str(tmp_path / "b.npy")]
    )
    assert code == 2
    assert "missing.png" in capsys.readouterr().err


def test_scores_hold_at_the_limits_of_float64() -> None:
    """Values of 1e300 overflowed the squares (OverflowError from SSIM's constants, inf MSE
    inside PSNR), the gain fit of a 1e300 estimate overflowed to 0, and a data range of 1e-300
    stopped PSNR with 'math domain error'. Scores are scale-free: the same at any scale."""
    ref = _smooth_image(30, 40)
    est = ref + 0.05 * RNG.random((30, 40))
    base = M.metrics_report(ref, est)
    for s in (1e300, 1e-300):
        rep = M.metrics_report(ref * s, est * s)
        for key in ("psnr", "ssim", "ms_ssim"):
            assert rep[key] == pytest.approx(base[key], rel=1e-9), (s, key)
        assert rep["mse"] == pytest.approx(base["mse"] * s * s, rel=1e-9)
    assert M.mse(ref * 1e300, est * 1e300) == math.inf  # 1e600 is beyond float64: said so
    scaled, g = M.gain_fit(ref, est * 1e300)
    assert g == pytest.approx(M.gain_fit(ref, est)[1] * 1e-300, rel=1e-12)
    assert M.psnr(ref, scaled) == pytest.approx(M.psnr(ref, M.gain_fit(ref, est)[0]), rel=1e-9)
    assert M.psnr(ref, est, data_range=1e300) == pytest.approx(
        M.psnr(ref, est, data_range=1.0) + 6000.0)
    assert M.psnr(ref, est, data_range=1e-300) == pytest.approx(
        M.psnr(ref, est, data_range=1.0) - 6000.0)
    assert 0.0 <= M.ssim(ref, est, data_range=1e-300) <= 1.0
    assert M.ssim(ref, est, data_range=1e300) == pytest.approx(1.0)
    cube = RNG.random((1, 4, 6, 6))
    assert M.spectral_cosine_distance(cube * 1e300, cube * 1e-300) == pytest.approx(0.0,
                                                                                  abs=1e-12)
