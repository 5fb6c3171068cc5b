"""A real measurement / lensed-truth pair in the dataset's layout: geometry through the loader.

The bundled sample (``recon.samples.dlmd_pair_paths``: im65 of the DiffuserCam Lensless
MirFlickr dataset at 1/4, BGR, stored upside-down, PSF on the padded grid) is read as a user
reads the dataset (``recon.problem``) and reconstructed with a few FISTA-TV iterations. The
reconstruction must correlate with its truth, and clearly less with the row-flipped truth (a
flip between the files is the classic mistake with this dataset). The benchmark's helpers
(``benchmarks.real_pairs``) are checked on the same sample and on their tables.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks import real_pairs as rp
from recon import samples
from recon.fista import Fista
from recon.problem import ProblemSpec, load_problem


@pytest.fixture(autouse=True)
def _one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def _spec(flip_rows: bool) -> ProblemSpec:
    p = samples.dlmd_pair_paths()
    return ProblemSpec(meas=str(p["measurement"]), psf=str(p["psf"]), truth=str(p["truth"]),
                       color="rgb", channel_order="bgr", flip_rows=flip_rows)


def _fista(model, meas, iters: int = 40) -> np.ndarray:
    solver = Fista(model.op, torch.as_tensor(meas), tau=1e-4, max_iter=iters, tol=0.0)
    for _ in solver.steps():
        pass
    return solver.x.detach().numpy()


def test_bundled_pair_layout() -> None:
    p = samples.dlmd_pair_paths()
    meas, truth, psf = (np.load(p[k]) for k in ("measurement", "truth", "psf"))
    assert meas.shape == truth.shape == (67, 120, 3)
    assert psf.shape == (134, 240, 3)  # the padded grid: exactly twice the sensor
    # the dataset's per-channel PSF gains B:G:R = 0.96 : 1 : 1.18 are kept (to 2 %)
    sums = psf.astype(np.float64).sum(axis=(0, 1))
    np.testing.assert_allclose(sums / sums[1], [0.96, 1.0, 1.18], atol=0.02)


@pytest.mark.parametrize("flip_rows", [True, False])
def test_reconstruction_correlates_with_truth_not_with_flipped_truth(flip_rows: bool) -> None:
    prob = load_problem(_spec(flip_rows))
    assert prob.sensor == (67, 120)
    assert prob.meas.shape == (3, 134, 240) and prob.mask is not None
    assert int(prob.mask.sum()) == 67 * 120  # the sensor window of the padded grid
    assert prob.truth is not None and prob.truth.shape == (3, 1, 67, 120)
    x = _fista(prob.model, prob.meas)
    truth = prob.truth
    right = _corr(x, truth)
    flipped = _corr(x, truth[:, :, ::-1])
    # measured: 0.80 and 0.29-0.33; the flip of all files alike changes nothing
    assert right > 0.7, right
    assert flipped < 0.45, flipped
    assert right - flipped > 0.3


def test_a_flip_between_the_files_is_seen() -> None:
    """Negative control: flipping only the truth's rows (a wrong frame) breaks the match."""
    prob = load_problem(_spec(True))
    x = _fista(prob.model, prob.meas)
    assert prob.truth is not None
    wrong = prob.truth[:, :, ::-1].copy()
    assert _corr(x, wrong) < 0.45
    # and the benchmark's score says the same (PSNR after a gain fit)
    assert rp.psnr_only(prob.truth[:, 0], x) > rp.psnr_only(wrong[:, 0], x) + 3.0


def test_benchmark_loader_and_erasures_on_the_bundled_pair() -> None:
    p = samples.dlmd_pair_paths()
    pair = rp.load_pair("im65", dict(p), 1)
    assert pair.truth.shape == (3, 67, 120)
    r0, c0 = pair.origin
    # the model crops the linear convolution at (h // 2, w // 2) and the PSF's zero shift
    # sits at the padded grid's centre (67, 120): the sensor starts at 67 - 33, 120 - 60
    assert (r0, c0) == (34, 60)
    assert pair.window[r0:r0 + 67, c0:c0 + 120].all()
    for e in (0.0, 0.9, 0.99):
        m = rp.sensor_mask(pair, e)
        assert m.shape == pair.window.shape
        assert not m[pair.window == 0].any()  # nothing measured outside the sensor
        assert int(m.sum()) == 67 * 120 - round(e * 67 * 120)
    # fixed seeds: the same mask every time, a different one per level
    np.testing.assert_array_equal(rp.sensor_mask(pair, 0.9), rp.sensor_mask(pair, 0.9))
    assert rp.erasure_seed(0.9) != rp.erasure_seed(0.95)


def test_scores_use_fewer_ms_ssim_scales_on_small_images() -> None:
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 1, (3, 67, 120)).astype(np.float32)
    s = rp.scores(truth, 2.0 * truth)  # a gain is fitted away
    assert s["psnr"] > 60 and s["ssim"] == pytest.approx(1.0, abs=1e-6)
    assert s["ms_ssim_scales"] == 3 and s["ms_ssim"] == pytest.approx(1.0, abs=1e-6)
    noisy = rp.scores(truth, truth + rng.normal(0, 0.2, truth.shape).astype(np.float32))
    assert noisy["psnr"] < 20 and noisy["ms_ssim"] < 0.9


def test_tables_average_per_level_and_list_every_case() -> None:
    def row(pair: str, e: float, f: float, u: float) -> dict:
        m = {"psnr": f, "ssim": 0.5, "ms_ssim": 0.6, "wall_s": 1.0, "tau": 1e-4,
             "iterations": 100}
        return {"pair": pair, "erasure": e, "fista_auto": m, "fista_oracle": dict(m),
                "udn": dict(m, psnr=u, peak_mb=80.0), "udn_clipped": 0.0,
                "fista_peak_mb": 20.0}

    rows = [row("im65", 0.9, 15.0, 14.0), row("im408", 0.9, 17.0, 18.0)]
    summary = rp.make_tables(rows)
    assert "| 90% | UDN (held-out stop) | 2 | 16.00 |" in summary
    assert "| 90% | FISTA-TV oracle tau | 2 | 16.00 |" in summary
    assert summary.splitlines()[-1].endswith("| 80 |")  # the UDN's peak memory
    cases = rp.case_table(rows)
    assert cases.count("\n") == 3 and "im408" in cases and "0.00%" in cases


def test_one_case_with_warm_start_and_a_seed_ensemble_on_the_bundled_pair() -> None:
    """The benchmark's row for one case: every method scored, the warm start recorded, and the
    ensemble the average of its members (each member a different seed)."""
    import argparse

    parser = argparse.ArgumentParser()
    rp.add_arguments(parser)
    args = parser.parse_args(["--fista-iters", "30", "--udn-iters", "8", "--warm-start", "4",
                              "--seeds", "2", "--channels", "8", "--scales", "2"])
    rp.fill_defaults(args)
    pair = rp.load_pair("im65", dict(samples.dlmd_pair_paths()), 1)
    keep: dict = {}
    row = rp.run_case(pair, 0.9, args, keep)
    for k in ("fista_auto", "fista_oracle", "admm", "udn", "udn_blend", "udn_ensemble"):
        assert np.isfinite(row[k]["psnr"]), k
    assert row["udn_warm_start"]["iterations"] == 4 and np.isfinite(row["udn_warm_start"]["mse"])
    ens = row["udn_ensemble"]
    assert ens["seeds"] == 2 and len(ens["members"]) == 2
    assert ens["members"][0] != ens["members"][1]  # two different seeds
    assert keep["udn_ensemble"].shape == keep["udn"].shape
    assert not np.allclose(keep["udn_ensemble"], keep["udn"])  # the second seed counts
    np.testing.assert_allclose(rp.psnr_only(pair.truth, keep["udn_ensemble"]), ens["psnr"],
                               rtol=1e-6)


def test_a_results_file_of_other_settings_is_refused(tmp_path) -> None:
    """Resuming into a results file whose cases ran with other settings would skip those cases
    and mix settings in one table: refused with one line naming the difference."""
    import argparse
    import json

    parser = argparse.ArgumentParser()
    rp.add_arguments(parser)
    results = tmp_path / "r.jsonl"
    args = parser.parse_args(["--udn-iters", "3000", "--seeds", "2", "--results", str(results),
                              "--data", str(tmp_path), "--threads", "1"])
    rp.fill_defaults(args)
    old = dict(rp._settings(args), udn_iters=300, seeds=1)
    fista = {"psnr": 20.0, "tau": 1e-4}
    results.write_text(json.dumps({"pair": "im65", "erasure": 0.9, "udn": {"psnr": 21.0},
                                   "fista_auto": fista, "fista_oracle": fista,
                                   "settings": old}) + "\n")
    with pytest.raises(ValueError, match=r"other settings .*seeds 1 not 2, udn_iters 300 not 3000"):
        rp.run(args)


def test_levers_change_what_they_say_and_the_oracle_stop_is_the_curve_max() -> None:
    """``--lever``: 'channel-gain' starts with one least-squares gain per colour channel (not
    all equal on this pair, whose PSF gains differ by channel) and learns each; 'precondition'
    keeps the loss but changes the path (its estimate after a few steps differs from the plain
    one's, from the same seed); 'block-holdout' holds out whole blocks. The bound row is the
    maximum of the PSNR curve."""
    import argparse

    from recon.models import build_model
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig

    parser = argparse.ArgumentParser()
    rp.add_arguments(parser)
    assert parser.parse_args([]).lever == "none"
    pair = rp.load_pair("im65", dict(samples.dlmd_pair_paths()), 1)
    h, w = pair.truth.shape[1:]
    mask = rp.sensor_mask(pair, 0.5)
    b = (pair.meas * mask).astype(np.float32)
    model = build_model("2d", pair.psf, mask=mask, field=(h, w))
    net = NetworkConfig(channels=8, scales=2)
    cfg = UDNConfig(max_iter=5, holdout=0.1, seed=0)
    runs = {lever: rp.make_runner(model, b, net, cfg, lever) for lever in rp.LEVERS}
    # 'sensor-gain': the prediction starts as the plain model's (the field is 1), the field
    # is a weight of the generator (snapshots and restores carry it), 1 outside the sensor
    sg = runs["sensor-gain"]
    x0 = sg._forward(noise=False).detach()
    assert torch.equal(sg.model.apply(x0), model.apply(x0))
    assert "sensor_log_gain" in sg.G.state_dict() and sg.model.gain_range() == [1.0, 1.0]
    assert sg.G.sensor_log_gain.shape == (3, 1, 5, 8)  # 5 points on 67 rows, 8 on 120
    gains = runs["channel-gain"].G.log_gain.detach().exp().reshape(-1)
    assert gains.numel() == 3 and float(gains.max() / gains.min()) > 1.05
    assert runs["channel-gain"].initial_gain == pytest.approx(float(gains.max()))
    plain_gain = runs["none"].initial_gain
    assert float(gains.min()) < plain_gain < float(gains.max())  # the scalar fit lies between
    for r in runs.values():
        for _ in r.steps():
            pass
    final = runs["channel-gain"].G.log_gain.detach().exp().reshape(-1)
    lo, hi = sg.model.gain_range()
    assert lo < 1.0 < hi  # learned with the network
    outside = sg.model.field()[..., mask.sum(axis=1) == 0, :]
    assert torch.equal(outside, torch.ones_like(outside))
    with torch.no_grad():  # however far its weights go, the field stays within its bounds
        sg.G.sensor_log_gain[0].fill_(50.0)
        sg.G.sensor_log_gain[1:].fill_(-50.0)
    assert sg.model.gain_range() == pytest.approx([1 / rp.SENSOR_GAIN_MAX, rp.SENSOR_GAIN_MAX])
    assert not torch.allclose(final, gains)  # learned, per channel
    plain, prec = runs["none"].final_estimate(), runs["precondition"].final_estimate()
    assert np.isfinite(prec).all() and not np.allclose(plain, prec, rtol=1e-3, atol=1e-6)
    # 'block-holdout': every channel of whole 4x4 blocks of measured pixels, about as many
    # values as the scattered design, which holds out values one by one
    from recon.holdout import block_labels

    held = runs["block-holdout"].heldout.numpy()
    assert held.shape == (3, *mask.shape) and (held == held[:1]).all()  # all channels alike
    lab = block_labels(*mask.shape, 4)
    taken = np.unique(lab[held[0]])
    assert np.array_equal(held[0], np.isin(lab, taken) & (mask > 0))
    n_plain = runs["none"].n_heldout
    assert n_plain * 0.9 <= runs["block-holdout"].n_heldout <= n_plain * 1.1 + 3 * 16
    scattered = runs["none"].heldout.numpy()
    assert not (scattered == scattered[:1]).all()  # the default: channels drawn apart
    # 'deep-decoder': another network, with fewer weights than the image has values, that
    # ignores the runner's input (its own is fixed) and gives a finite estimate of the scene
    dd = runs["deep-decoder"]
    assert type(dd.G.net).__name__ == "DeepDecoder"
    n_weights = sum(p.numel() for p in dd.G.net.parameters())
    assert n_weights < pair.truth.size and dd.G.gain > 0
    out = dd.final_estimate()
    assert out.shape == plain.shape and np.isfinite(out).all()
    with torch.no_grad():
        assert torch.equal(dd.G.net(dd.G.z), dd.G.net(dd.G.z + 1.0))  # the input is unused
    with pytest.raises(ValueError, match="lever must be one of"):
        rp.make_runner(model, b, net, cfg, "bogus")
    assert rp._oracle_stop({"50": 14.0, "100": 15.5, "150": 15.0}) == {"psnr": 15.5,
                                                                        "iterations": 100}
    assert rp._oracle_stop({}) is None


def _rerun(pair, args, iters: int):
    """The benchmark's UDN run of ``pair`` at 90 % (seed 0, 8 channels, 2 scales) again: its
    runner and its estimate after every iteration."""
    from recon.models import build_model
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig

    mask = rp.sensor_mask(pair, 0.9)
    b = (pair.meas * mask).astype(np.float32)
    model = build_model("2d", pair.psf, mask=mask, field=pair.truth.shape[1:])
    cfg = UDNConfig(max_iter=iters, holdout=args.holdout, patience=10**9, min_iter=0,
                    headroom=args.headroom, lr=args.lr, ema=args.ema, tv_weight=args.tv_weight,
                    seed=0)
    net = NetworkConfig(channels=8, scales=2, skip_channels=args.skip)
    runner = rp.make_runner(model, b, net, cfg)
    return runner, [s.preview for s in runner.steps(preview_every=1)]


def test_es_wmv_stop_is_the_iteration_of_least_running_variance() -> None:
    """The ES-WMV row (the running variance now computed where the estimate lives, on a GPU
    there) is the estimate of the iteration whose window of estimates varies least: checked
    against the same run's previews with the variance computed in NumPy."""
    import argparse


    parser = argparse.ArgumentParser()
    rp.add_arguments(parser)
    args = parser.parse_args(["--fista-iters", "30", "--udn-iters", "14", "--wmv-window", "3",
                              "--channels", "8", "--scales", "2"])
    rp.fill_defaults(args)
    pair = rp.load_pair("im65", dict(samples.dlmd_pair_paths()), 1)
    row = rp.run_case(pair, 0.9, args, {})
    # the same run again (seeded), its previews, the variance in NumPy
    _, previews = _rerun(pair, args, 14)
    var = {i + 1: float(np.stack(previews[i - 2:i + 1]).var(axis=0).mean())
           for i in range(2, len(previews))}
    it = min(var, key=var.__getitem__)
    assert row["udn_wmv"]["iterations"] == it
    np.testing.assert_allclose(row["udn_wmv"]["psnr"], rp.psnr_only(pair.truth, previews[it - 1]),
                               rtol=1e-5)
    # still improving: the held-out best in the last tenth (2 of 14 iterations)
    assert row["udn_still_improving"] is (row["udn"]["iterations"] > 12)
    walls = [row["udn_curve_wall"][k] for k in sorted(row["udn_curve_wall"], key=int)]
    assert walls == sorted(walls) and walls[-1] > 0


def test_an_unknown_device_is_one_line(tmp_path) -> None:
    import argparse

    parser = argparse.ArgumentParser()
    rp.add_arguments(parser)
    args = parser.parse_args(["--device", "tpu", "--data", str(tmp_path), "--downsample", "1"])
    with pytest.raises(ValueError, match=r"--device: unknown device 'tpu'"):
        rp.run(args)


def test_error_analysis_removes_a_shading_the_other_pairs_share_and_nothing_else() -> None:
    """A camera shading shared by every scene (an estimate that is the truth divided by one
    smooth field) is found from the *other* pairs and removed; an error of white noise is
    not smooth and gains nothing; one pair alone is not analysed (nothing to learn from)."""
    rng = np.random.default_rng(0)
    h, w = 128, 192  # a fine band of 2 px, a shading scale of 16 px
    yy, xx = np.mgrid[0:h, 0:w]
    shade = 0.6 + 0.8 * (xx / w) * (1 - 0.5 * yy / h)  # 0.6 .. 1.4, the same for all scenes
    images = {}
    for i, name in enumerate(("a", "b", "c", "d")):
        truth = np.clip(rng.random((3, h, w)) * 0.3 + 0.3 + 0.1 * i, 0, 1).astype(np.float32)
        images[(name, 0.5)] = {
            "truth": truth,
            "fista_oracle": (truth / shade).astype(np.float32),
            "udn": (truth + 0.05 * rng.standard_normal(truth.shape)).astype(np.float32)}
    images[("a", 0.99)] = dict(images[("a", 0.5)])  # one pair at that level
    # two pairs whose shadings are opposite: each is corrected with the other's, never its own
    for name, est in (("a", lambda t: t / shade), ("b", lambda t: t * shade)):
        t = images[(name, 0.5)]["truth"]
        images[(name, 0.9)] = {"truth": t, "fista_oracle": est(t).astype(np.float32)}
    out = rp.error_analysis(images)
    assert {r["erasure"] for r in out} == {0.5, 0.9}
    opposite = next(r for r in out if r["erasure"] == 0.9 and r["method"] == "fista_oracle")
    assert opposite["psnr_shaded"] < opposite["psnr"] - 3
    rows = {r["method"]: r for r in out if r["erasure"] == 0.5}
    shaded, noisy, content = rows["fista_oracle"], rows["udn"], rows["truth"]
    # the truths are white too (uniform, variance 0.3^2 / 12), so their own fine band is to the
    # noise's as their variances are (clipping aside)
    assert content["psnr"] is None
    assert content["fine"] / noisy["fine"] == pytest.approx((0.3 ** 2 / 12) / 0.05 ** 2, rel=0.1)
    assert shaded["smooth"] > 5 * (shaded["fine"] + shaded["mid"])  # a slow error
    assert noisy["fine"] > 5 * (noisy["mid"] + noisy["smooth"])  # white noise: the finest
    assert shaded["psnr_shaded"] > shaded["psnr"] + 10  # the shared shading is gone
    assert abs(noisy["psnr_shaded"] - noisy["psnr"]) < 0.1  # nothing shared to remove
    table = rp.error_table(list(rows.values()))
    assert "| 50% | FISTA-TV oracle tau | 4 |" in table and "+0.00 / +0.00" in table
    assert "| 50% | the truth's own content | 4 | - |" in table


def test_mid_factor_is_the_shrink_of_the_mid_band_that_gains_the_margin() -> None:
    """``_mid_factor``: shrinking only the mid band of each error by the factor it returns
    raises the mean PSNR by the asked gain; an error with (almost) nothing in the mid band
    cannot gain 1 dB there (None)."""
    from scipy.ndimage import gaussian_filter

    from recon.metrics import psnr

    rng = np.random.default_rng(1)
    h, w = 96, 128
    fs, sigma = 1.5, 12.0
    cases = []
    for _ in range(3):
        t = (0.4 + 0.2 * rng.random((3, h, w))).astype(np.float32)
        err = np.stack([gaussian_filter(rng.standard_normal((h, w)), 4.0) for _ in range(3)])
        err = 0.1 * err / err.std() + 0.02 * rng.standard_normal((3, h, w))
        cases.append((t, err.astype(np.float32), fs, sigma))
    f = rp._mid_factor(cases, 1.0)
    assert f is not None and 0.5 < f < 1.0

    def mean_psnr(a: float) -> float:
        out = []
        for t, err, s1, s2 in cases:
            e1, es = rp._smooth(err, s1), rp._smooth(err, s2)
            out.append(psnr(t, (t - (err - e1 + es) - a * (e1 - es)).astype(np.float32)))
        return float(np.mean(out))

    assert mean_psnr(f) - mean_psnr(1.0) == pytest.approx(1.0, abs=1e-3)
    white = [(t, (0.05 * rng.standard_normal(t.shape)).astype(np.float32), fs, sigma)
             for t, _, _, _ in cases]
    assert rp._mid_factor(white, 1.0) is None


def test_fista_input_lever_puts_the_image_in_the_first_input_channels() -> None:
    """``--lever fista-input``: z's first C channels become the given estimate over its 99.9th
    percentile (padded to the network's grid), the other channels stay the seeded noise, and
    the gain is fitted again to the new first output."""
    from recon.models import build_model
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig

    pair = rp.load_pair("im65", dict(samples.dlmd_pair_paths()), 1)
    c, h, w = pair.truth.shape
    mask = rp.sensor_mask(pair, 0.5)
    b = (pair.meas * mask).astype(np.float32)
    model = build_model("2d", pair.psf, mask=mask, field=(h, w))
    cfg = UDNConfig(max_iter=3, holdout=0.1, seed=0)
    r = rp.make_runner(model, b, NetworkConfig(channels=8, scales=2), cfg, "fista-input")
    z0 = r.G.z.clone()
    gain0 = r.initial_gain
    x = np.random.default_rng(1).random((c, 1, h, w)).astype(np.float32) * 4.0
    rp.fista_input(r, x)
    top = float(np.percentile(x, 99.9))
    got = r.G.z[0, :c, :h, :w].numpy()
    np.testing.assert_allclose(got, x[:, 0] / top, rtol=1e-5)
    assert r.G.z.shape == z0.shape and r.G.z.shape[-2:] != (h, w)  # padded grid kept
    assert torch.equal(r.G.z[:, c:], z0[:, c:])  # the noise channels untouched
    assert r.initial_gain != pytest.approx(gain0) and r.initial_gain == pytest.approx(r.G.gain)
    for _ in r.steps():
        pass
    assert np.isfinite(r.final_estimate()).all() and r.iteration == 3


def test_error_analysis_scores_the_mean_of_the_ensemble_and_fista_where_both_were_kept() -> None:
    """Two estimates whose errors are independent: their plain mean halves the error's
    variance, about +3 dB, and the row is the mean's, not either member's; a case without
    the ensemble has no such row (nothing is made up from one member)."""
    rng = np.random.default_rng(1)
    images = {}
    for name in ("a", "b", "c"):
        truth = (0.3 + 0.4 * rng.random((3, 48, 64))).astype(np.float32)
        images[(name, 0.9)] = {
            "truth": truth,
            "udn_ensemble": (truth + 0.05 * rng.standard_normal(truth.shape)).astype(np.float32),
            "fista_auto": (truth + 0.05 * rng.standard_normal(truth.shape)).astype(np.float32)}
        images[(name, 0.5)] = {"truth": truth, "fista_auto": images[(name, 0.9)]["fista_auto"]}
    out = rp.error_analysis(images)
    rows = {(r["erasure"], r["method"]): r for r in out}
    mean, ens = rows[(0.9, "ensemble_fista_mean")], rows[(0.9, "udn_ensemble")]
    assert mean["psnr"] - ens["psnr"] == pytest.approx(10 * np.log10(2), abs=0.3)
    # SSIM and MS-SSIM of the averaged row: the tables' scores of the averaged image, higher
    # than a member's (half the noise), and in the table beside the PSNR
    want = [rp.scores(images[(n, 0.9)]["truth"], 0.5 * (images[(n, 0.9)]["udn_ensemble"]
                                                        + images[(n, 0.9)]["fista_auto"]))
            for n in ("a", "b", "c")]
    for k in ("ssim", "ms_ssim"):
        assert mean[k] == pytest.approx(np.mean([w[k] for w in want]), rel=1e-6)
        assert mean[k] > ens[k] + 0.01
    assert (0.5, "ensemble_fista_mean") not in rows
    table = rp.error_table(out)
    assert "UDN seed ensemble and FISTA-TV auto, averaged" in table
    assert f"| {mean['psnr']:.2f} | {mean['ssim']:.3f} / {mean['ms_ssim']:.3f} |" in table
    # one seed (what jobs combine --with-fista writes for one run): only where it was kept
    assert (0.9, "udn_fista_mean") not in rows
    for name in ("a", "b", "c"):
        imgs = images[(name, 0.9)]
        imgs["udn"] = (imgs["truth"] + 0.05 * rng.standard_normal(imgs["truth"].shape)
                       ).astype(np.float32)
    rows = {(r["erasure"], r["method"]): r for r in rp.error_analysis(images)}
    one, udn = rows[(0.9, "udn_fista_mean")], rows[(0.9, "udn")]
    assert one["psnr"] - udn["psnr"] == pytest.approx(10 * np.log10(2), abs=0.3)


def test_mix_stop_is_the_iteration_whose_mix_with_fitted_pixel_fista_predicts_best(
        monkeypatch) -> None:
    """The averaged recipe's own stop: the UDN iterate (checked every MIX_EVERY iterations)
    whose half-and-half mix with FISTA-TV of the UDN's fitted pixels has the least held-out
    error; the row scores that iterate averaged with automatic-tau FISTA-TV, and its bound is
    the best of the mix's truth curve. Checked against the same run's previews."""
    import argparse


    parser = argparse.ArgumentParser()
    rp.add_arguments(parser)
    args = parser.parse_args(["--fista-iters", "30", "--udn-iters", "40", "--channels", "8",
                              "--scales", "2"])
    rp.fill_defaults(args)
    pair = rp.load_pair("im65", dict(samples.dlmd_pair_paths()), 1)
    keep: dict = {}
    monkeypatch.setattr(rp, "SNAPSHOT_EVERY", 15)  # iterations 15 and 30 of the 40
    row = rp.run_case(pair, 0.9, args, keep)
    runner, previews = _rerun(pair, args, 40)
    b = (pair.meas * rp.sensor_mask(pair, 0.9)).astype(np.float32)
    fit = runner.fit.cpu().numpy().astype(np.float32)
    x_fit = rp._fitted_pixels_fista(pair, b, fit, args, 30)  # min_iter: the run's (30 < 100)
    errs = {it: runner.heldout_error(torch.as_tensor(0.5 * (previews[it - 1] + x_fit)))
            for it in range(rp.MIX_EVERY, 41, rp.MIX_EVERY)}
    it = min(errs, key=errs.__getitem__)
    assert row["udn_mix_stop"]["iterations"] == it
    curve = {int(k): v for k, v in row["udn_mix_heldout_curve"].items()}
    assert sorted(curve) == sorted(errs)
    for k, v in errs.items():  # the mix's error, not the network's alone
        assert curve[k] == pytest.approx(v, rel=1e-4)
    np.testing.assert_allclose(keep["udn_mix_stop"], previews[it - 1], rtol=1e-5, atol=1e-6)
    x_auto = keep["fista_auto"]
    np.testing.assert_allclose(row["udn_mix_stop"]["psnr"],
                               rp.psnr_only(pair.truth, 0.5 * (previews[it - 1] + x_auto)),
                               rtol=1e-5)
    assert row["udn_mix_oracle_stop"]["psnr"] == max(row["udn_mix_curve"].values())
    # the averaged image of the error analysis is that iterate with FISTA-TV auto
    derived = rp._derived({"udn_mix_stop": keep["udn_mix_stop"], "fista_auto": x_auto})
    np.testing.assert_allclose(derived["udn_mix_fista_mean"],
                               0.5 * (keep["udn_mix_stop"] + x_auto))
    # iterate averaging: the mean of the estimates at every SNAPSHOT_EVERY iterations
    snap = 0.5 * (previews[14] + previews[29])
    np.testing.assert_allclose(keep["udn_snapshots"], snap, rtol=1e-5, atol=1e-6)
    assert row["udn_snapshots"]["count"] == 2
    np.testing.assert_allclose(row["udn_snapshots"]["psnr"], rp.psnr_only(pair.truth, snap),
                               rtol=1e-5)
    derived = rp._derived({"udn_snapshots": snap, "fista_auto": x_auto})
    np.testing.assert_allclose(derived["udn_snapshots_fista_mean"], 0.5 * (snap + x_auto))
