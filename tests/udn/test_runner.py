"""The stepwise UDN solver: masked loss, held-out pixels, early stopping, divergence, NaN, state."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch

from recon.holdout import MIN_RELIABLE_HELDOUT
from recon.metrics import gain_fit, psnr
from recon.models import build_model
from recon.stepwise import StopReason
from recon.udn.network import NetworkConfig
from recon.udn.runner import NumericalError, UDNConfig, UDNRunner
from tests.udn.conftest import TINY_NET, tiny_problem

NET = NetworkConfig(**TINY_NET)


def make_runner(meas=None, erasure=0.5, **cfg):
    psf, sim = tiny_problem(erasure=erasure)
    model = build_model("2d", psf, mask=sim.mask)
    b = sim.meas if meas is None else meas
    return UDNRunner(model, b, network=NET, config=UDNConfig(**cfg)), sim


def weights(r):
    return [p.detach().clone() for p in r.G.parameters()]


def same(a, b):
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_loss_ignores_erased_pixels():
    """Changing the value of erased pixels (even to NaN) changes nothing in the fit."""
    r1, sim = make_runner(max_iter=10)
    meas = sim.meas.copy()
    erased = sim.mask == 0
    assert erased.sum() > 10
    meas[0][erased] = np.random.default_rng(5).uniform(0, 5, int(erased.sum()))
    meas[0][np.argwhere(erased)[0][0], np.argwhere(erased)[0][1]] = np.nan
    r2, _ = make_runner(meas=meas, max_iter=10)
    for _ in range(3):
        s1, s2 = r1.step(), r2.step()
        assert s1.loss == s2.loss
    assert same(weights(r1), weights(r2))
    # ... while a measured pixel does matter
    meas3 = sim.meas.copy()
    y, x = np.argwhere((sim.mask == 1) & ~r1.heldout.numpy()[0])[0]
    meas3[0, y, x] += 0.5
    r3, _ = make_runner(meas=meas3, max_iter=10)
    r3.step()
    r1b, _ = make_runner(max_iter=10)
    r1b.step()
    assert not same(weights(r1b), weights(r3))


def test_heldout_pixels_are_excluded_from_the_fit():
    r1, sim = make_runner(holdout=0.2)
    held = r1.heldout.numpy()
    measured = sim.mask[None] == 1
    assert held.sum() == round(0.2 * measured.sum())
    assert not (held & ~measured).any()  # only measured pixels are held out
    assert not (held & r1.fit.numpy()).any()
    assert r1.n_fit + r1.n_heldout == int(measured.sum())
    meas = sim.meas.copy()
    meas[held] += 0.3  # change only the held-out pixels
    r2, _ = make_runner(meas=meas, holdout=0.2)
    for _ in range(3):
        s1, s2 = r1.step(), r2.step()
    assert same(weights(r1), weights(r2))  # the fit never saw them
    assert s1.heldout != s2.heldout  # but they are what the held-out error measures


def test_early_stopping_returns_the_best_estimate(monkeypatch):
    r, _ = make_runner(holdout=0.3, patience=5, min_iter=0, max_iter=100, ema=0.5)
    assert r.n_heldout >= MIN_RELIABLE_HELDOUT and r.stops_early
    # a scripted held-out error: falls until iteration 8, then rises (overfitting)
    script = iter([1.0 / i if i <= 8 else 0.125 + 0.01 * i for i in range(1, 101)])
    monkeypatch.setattr(r, "heldout_error_tensor", lambda x: torch.tensor(next(script)))
    estimates = {}
    for s in r.steps(preview_every=1):
        estimates[s.iteration] = s.preview
    assert r.reason is StopReason.STOPPED_EARLY
    assert r.iteration == 8 + 5
    assert r.best_iteration == 8
    np.testing.assert_array_equal(r.best_estimate(), estimates[8])
    assert not np.array_equal(r.final_estimate(), estimates[8])
    res = r.result()
    assert res.best_iteration == 8 and res.reason is StopReason.STOPPED_EARLY


def test_too_few_heldout_pixels_do_not_stop_the_run_early(monkeypatch):
    """34 held-out pixels (fewer than MIN_RELIABLE_HELDOUT) know their error to about a
    quarter of itself: the same scripted rise that stops a run with enough of them does not
    stop this one; it runs to its limit, keeps their best iteration and says why."""
    r, _ = make_runner(holdout=0.1, patience=5, min_iter=0, max_iter=30, ema=0.5)
    assert r.n_heldout < MIN_RELIABLE_HELDOUT and not r.stops_early
    script = iter([1.0 / i if i <= 8 else 0.125 + 0.01 * i for i in range(1, 101)])
    monkeypatch.setattr(r, "heldout_error_tensor", lambda x: torch.tensor(next(script)))
    estimates = {s.iteration: s.preview for s in r.steps(preview_every=1)}
    assert r.reason is StopReason.MAX_ITER and r.iteration == 30
    assert r.best_iteration == 8
    np.testing.assert_array_equal(r.best_estimate(), estimates[8])
    assert any("does not stop early on them" in n for n in r.notes), r.notes


def test_divergence_restores_the_last_good_state():
    r, _ = make_runner(snapshot_every=5, max_iter=100, lr_backoff=0.5)
    for _ in range(10):
        r.step()
    good = weights(r)
    good_ema = r.ema.clone()
    lr = r.lr
    r.step()  # iteration 11 moves away from the snapshot
    with torch.no_grad():
        r.G.log_gain.add_(12.0)  # the output 160000x too bright: the loss jumps
    s = r.step()
    assert s.restored
    assert same(weights(r), good)
    assert torch.equal(r.ema, good_ema)
    assert r.lr == pytest.approx(lr * 0.5)
    assert all(g["lr"] == pytest.approx(lr * 0.5) for g in r.opt.param_groups)
    assert any("restored the state of iteration 10" in n for n in r.notes)
    s2 = r.step()
    assert not s2.restored and math.isfinite(s2.loss)


def test_nan_in_the_loss_stops_with_a_clear_message():
    r, _ = make_runner(max_backoffs=2, snapshot_every=2)
    for _ in range(3):
        r.step()
    real_apply = r.model.op.apply
    r.model.op.apply = lambda x: real_apply(x) * float("nan")  # type: ignore[method-assign]
    restored = [r.step().restored for _ in range(2)]
    assert restored == [True, True]
    with pytest.raises(NumericalError, match=r"not finite at iteration 6.*2 restores.*lower"):
        r.step()


def test_state_dict_roundtrip_continues_identically():
    a, _ = make_runner(max_iter=20, snapshot_every=4)
    a.run()
    b, _ = make_runner(max_iter=20, snapshot_every=4)
    for _ in range(9):
        b.step()
    buf = io.BytesIO()
    torch.save(b.state_dict(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)
    c, _ = make_runner(max_iter=20, snapshot_every=4)
    c.load_state_dict(state)
    assert c.iteration == 9
    c.run()
    assert c.iteration == 20
    assert same(weights(a), weights(c))
    assert torch.equal(a.ema, c.ema) and torch.equal(a.best, c.best)


def test_the_mean_estimate_averages_the_estimate_every_average_every_iterations():
    """Iterate averaging: the mean of the EMA estimate at iterations 5, 10, 15 (not 17); the
    final estimate before the first; none with average_every 0; and it survives a checkpoint
    (a resumed run ends with the same mean as an uninterrupted one)."""
    a, _ = make_runner(max_iter=17, average_every=5, snapshot_every=4)
    np.testing.assert_array_equal(a.mean_estimate(), a.final_estimate())  # nothing yet
    seen = []
    for s in a.steps():
        if s.iteration % 5 == 0:
            seen.append(a.final_estimate().astype(np.float64))
    assert a.mean_count == 3 and len(seen) == 3
    np.testing.assert_allclose(a.mean_estimate(), np.mean(seen, axis=0), rtol=1e-6, atol=1e-7)
    assert not np.allclose(a.mean_estimate(), a.final_estimate(), atol=1e-4)
    # resumed at 12 (two estimates in the sum): the same mean at the end
    b, _ = make_runner(max_iter=17, average_every=5, snapshot_every=4)
    for _ in range(12):
        b.step()
    buf = io.BytesIO()
    torch.save(b.state_dict(), buf)
    buf.seek(0)
    c, _ = make_runner(max_iter=17, average_every=5, snapshot_every=4)
    c.load_state_dict(torch.load(buf, weights_only=True))
    c.run()
    assert c.mean_count == 3
    np.testing.assert_array_equal(c.mean_estimate(), a.mean_estimate())
    # a checkpoint from before iterate averaging: resumed, its mean starts there, noted
    old = b.state_dict()
    del old["mean_sum"], old["mean_count"]
    del old["identity"]["config"]["average_every"]
    d, _ = make_runner(max_iter=17, average_every=5, snapshot_every=4)
    d.load_state_dict(old)
    d.run()
    assert d.mean_count == 1 and any("without the iterate average" in n for n in d.notes)
    # off: the final estimate, nothing summed
    e, _ = make_runner(max_iter=6, average_every=0)
    e.run()
    assert e.mean_count == 0
    np.testing.assert_array_equal(e.mean_estimate(), e.final_estimate())
    with pytest.raises(ValueError, match="average_every must be an integer >= 0"):
        UDNConfig(average_every=-1)


def test_state_from_another_network_is_refused():
    a, _ = make_runner()
    state = a.state_dict()
    psf, sim = tiny_problem()
    other = UDNRunner(build_model("2d", psf, mask=sim.mask), sim.meas,
                      network=NetworkConfig(**{**TINY_NET, "channels": 8}))
    with pytest.raises(ValueError, match=r"different run.*network.channels"):
        other.load_state_dict(state)


def test_udn_improves_psnr_end_to_end():
    """On a small simulated case (no erasures) the estimate gains well over its first iterate."""
    r, sim = make_runner(erasure=0.0, max_iter=250, holdout=0.05, lr=0.01)
    truth = sim.truth
    first = None
    for _ in r.steps():
        if first is None:
            first = r.final_estimate()
    score = lambda x: psnr(truth, gain_fit(truth, x)[0])  # noqa: E731
    p0, p_best = score(first), score(r.best_estimate())
    assert p_best > p0 + 4.0, (p0, p_best)
    assert r.reason is StopReason.MAX_ITER


def test_scale_invariant_loss_keeps_the_measurement_scale():
    r, sim = make_runner(loss="scale_invariant", gain=100.0, max_iter=30)
    res = r.run()
    ax = r.model.apply(torch.as_tensor(res.final)).numpy()
    m = sim.mask[None] == 1
    # the estimate is rescaled to the data, whatever the network's gain
    assert np.sum(ax[m] * sim.meas[m]) / np.sum(ax[m] ** 2) == pytest.approx(1.0, rel=0.2)


def test_bf16_autocast_and_channels_last_run_on_cpu():
    r, _ = make_runner(precision="bf16", channels_last=True, max_iter=5)
    res = r.run()
    assert res.final.dtype == np.float32 and np.isfinite(res.final).all()


def test_compile_failure_falls_back_with_a_note(monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(torch, "compile", broken)
    r, _ = make_runner(compile=True, max_iter=3)
    r.run()
    assert r.iteration == 3 and not r._compiled
    assert any("torch.compile failed" in n and "no compiler" in n for n in r.notes)


def test_compile_error_at_first_call_falls_back(monkeypatch):
    def lazy(module, **options):  # torch.compile(module, mode=...)
        def call(z):
            raise RuntimeError("inductor failed")
        return call

    monkeypatch.setattr(torch, "compile", lazy)
    r, _ = make_runner(compile=True, max_iter=3)  # the gain fit makes the first call
    r.run()
    assert r.iteration == 3
    assert any("first call" in n for n in r.notes)


def test_cancel_and_time_limit():
    r, _ = make_runner(max_iter=100)
    res = r.run(cancel=lambda: True)
    assert res.reason is StopReason.CANCELLED and res.iterations == 1
    r2, _ = make_runner(max_iter=10_000, time_limit_s=1e-6)
    res2 = r2.run()
    assert res2.reason is StopReason.TIME_LIMIT and res2.iterations == 1


def test_progress_reports_eta_and_preview():
    r, _ = make_runner(max_iter=6)
    steps = list(r.steps(preview_every=3))
    assert [s.preview is not None for s in steps] == [False, False, True, False, False, True]
    assert steps[2].preview.shape == r.model.scene_shape
    assert steps[-1].eta_s == 0.0 and steps[1].eta_s > 0
    assert steps[-1].elapsed_s > steps[0].elapsed_s


def test_measurement_with_nan_at_a_measured_pixel_is_refused():
    _, sim = tiny_problem()
    meas = sim.meas.copy()
    y, x = np.argwhere(sim.mask == 1)[0]
    meas[0, y, x] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        make_runner(meas=meas)


def test_tv_weight_enters_the_loss_and_smooths_the_output():
    """A TV weight adds TV(x)/n to the loss (differentiably) and gives a smoother estimate."""
    from recon.tv import TV

    r0, _ = make_runner(max_iter=40, holdout=0.0, seed=3, reg_noise=0.0, ema=0.0)
    r1, _ = make_runner(max_iter=40, holdout=0.0, seed=3, reg_noise=0.0, ema=0.0, tv_weight=0.5)
    x = r1._forward(noise=False)
    pen = r1._tv_penalty(x)
    assert pen.requires_grad
    assert float(pen.detach()) == pytest.approx(TV().value(x.detach()) / x.numel(), rel=1e-5)
    s0, s1 = r0.step(), r1.step()  # same weights and input: the loss differs by the penalty
    assert s1.loss == pytest.approx(s0.loss + 0.5 * float(pen.detach()), rel=1e-4)
    for _ in range(39):
        r0.step(), r1.step()
    tv = TV()
    assert tv.value(torch.as_tensor(r1.final_estimate())) < 0.5 * tv.value(
        torch.as_tensor(r0.final_estimate()))


def test_a_gradient_beyond_float32_is_an_error_not_a_network_that_stops_moving():
    """tv_weight 1e30: the loss stays finite (~1e27) but Adam's second moment overflows, its
    steps become 0 and the run ended with its untrained first output, without a word."""
    r, _ = make_runner(max_iter=5, holdout=0.0, seed=3, tv_weight=1e30)
    with pytest.raises(NumericalError, match=r"gradient overflowed torch.float32 at iteration 1 "
                                             r"\(Adam's exp_avg_sq is not finite.*far above "
                                             r"their usual range: optimizer.tv_weight = 1e\+30 "
                                             r"\(default 0\); lower it"):
        r.step()
    r, _ = make_runner(max_iter=3, holdout=0.0, seed=3, tv_weight=1.0)  # large, in range
    for _ in r.steps():
        pass
    assert r.iteration == 3 and np.isfinite(r.final_estimate()).all()


def test_tv_diffs_match_the_in_place_differences():
    from recon.tv import TV

    for shape, wk in (((1, 3, 5, 6), 0.7), ((2, 1, 4, 1), 0.7), ((1, 4, 3, 5), 0.0)):
        x = torch.rand(*shape, dtype=torch.float64, requires_grad=True)
        tv = TV(weight_k=wk)
        d = tv.diffs(x)
        assert len(d) == tv.n_dirs(x)
        for a, b in zip(d, tv.grad(x.detach()), strict=True):
            assert torch.equal(a.detach(), b)
        # autograd through diffs is the adjoint of the differences
        p = [torch.rand_like(a) for a in d]
        (g,) = torch.autograd.grad(sum((a * q).sum() for a, q in zip(d, p, strict=True)), x)
        torch.testing.assert_close(g, tv.grad_adj(p))


def test_headroom_scales_the_fitted_gain_only():
    r1, _ = make_runner(max_iter=5, seed=2)
    r3, _ = make_runner(max_iter=5, seed=2, headroom=3.0)
    assert r3.initial_gain == pytest.approx(3.0 * r1.initial_gain, rel=1e-6)
    rg, _ = make_runner(max_iter=5, seed=2, gain=0.7, headroom=3.0)  # an explicit gain wins
    assert rg.initial_gain == pytest.approx(0.7, rel=1e-6)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="headroom"):
            UDNConfig(headroom=bad)


def test_warm_start_fits_the_output_to_the_image_and_leaves_the_run_at_iteration_zero():
    r, sim = make_runner(erasure=0.0, max_iter=5, holdout=0.05)
    truth = np.asarray(sim.truth, dtype=np.float32) * 3.0  # brighter than the fitted gain's cap
    score = lambda x: psnr(truth, x)  # noqa: E731  (no gain fit: the level must match too)
    before = score(r.G.to_scene(r.G.raw()).detach().numpy())
    g0 = r.G.gain
    mse = r.warm_start(truth, 150)
    after = score(r.G.to_scene(r.G.raw()).detach().numpy())
    assert after > before + 6.0, (before, after)
    assert math.isfinite(mse) and r.iteration == 0
    assert r.G.gain > 1.5 * g0  # raised for the image's highlights (then learnt)
    # Adam's moments carry over to the data term (a fresh Adam's first steps, about lr in
    # every weight, wreck a fitted network: see UDNRunner.warm_start)
    assert all(len(r.opt.state[p]) for p in r.G.parameters() if p.requires_grad)
    assert any("warm start: 150 of 150 iterations" in n for n in r.notes)
    r.step()  # the data term takes over
    with pytest.raises(RuntimeError, match="before the first iteration"):
        r.warm_start(truth, 10)


def test_warm_steps_report_progress_cancel_and_restore_on_nan(monkeypatch):
    r, sim = make_runner(erasure=0.0, max_iter=5)
    truth = np.asarray(sim.truth, dtype=np.float32)
    t0 = r.elapsed_s
    steps = r.warm_steps(truth, 50)
    seen = [next(steps) for _ in range(5)]
    steps.close()  # cancel after 5 of 50
    assert [i for i, _ in seen] == [1, 2, 3, 4, 5] and all(math.isfinite(m) for _, m in seen)
    assert any("warm start: 5 of 50 iterations" in n for n in r.notes) and r.elapsed_s > t0
    # a non-finite loss: the network goes back to where the warm start found it
    r2, _ = make_runner(erasure=0.0, max_iter=5)
    w0 = weights(r2)
    calls = {"n": 0}
    real = r2._forward

    def poisoned(noise):
        calls["n"] += 1
        out = real(noise)
        return out * float("nan") if calls["n"] == 3 else out

    monkeypatch.setattr(r2, "_forward", poisoned)
    with pytest.raises(NumericalError, match="as it was before the warm start"):
        r2.warm_start(truth, 10)
    assert same(weights(r2), w0) and not any("warm start" in n for n in r2.notes)


def test_warm_start_refuses_a_wrong_image():
    r, sim = make_runner(erasure=0.0, max_iter=5)
    with pytest.raises(ValueError, match="warm-start image has shape"):
        r.warm_start(np.zeros((3, 4)), 5)
    bad = np.asarray(sim.truth, dtype=np.float32).copy()
    bad.flat[0] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        r.warm_start(bad, 5)
    with pytest.raises(ValueError, match=">= 1"):
        r.warm_start(sim.truth, 0)


def test_a_stop_on_few_held_out_pixels_is_noted():
    """4 held-out pixels chose a 99 %-erased video's stopping iteration, and no note said so."""
    r, _ = make_runner(erasure=0.99, max_iter=2)
    assert 0 < r.n_heldout < 100
    assert any(n.startswith(f"only {r.n_heldout} held-out pixels choose the stopping "
                            "iteration") and "raise holdout" in n for n in r.notes)
    r, _ = make_runner(erasure=0.0, max_iter=2, holdout=0.3)
    assert r.n_heldout >= 100 and not any("held-out pixels choose" in n for n in r.notes)


def test_a_step_reads_back_from_the_device_once():
    """On a GPU every scalar read (``float(t)``, ``bool(t)``) and every boolean-mask index (its
    output size depends on the data) makes the host wait for the device, which then idles while
    the next kernels are queued. A plain iteration (not the first, not a snapshot, no preview)
    dispatches none of them: its loss, clip fraction, gain and held-out error come back in one
    ``tolist`` at its end (which dispatches no op). Adam's step counters are read too, but they
    are host tensors on every device (``capturable`` off), so those reads wait for nothing."""
    from torch.utils._python_dispatch import TorchDispatchMode

    waits = ("aten._local_scalar_dense", "aten.nonzero", "aten.masked_select", "aten.item")

    class Record(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.found = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            name = str(func)
            bool_index = name.startswith("aten.index.") and any(
                isinstance(i, torch.Tensor) and i.dtype == torch.bool
                for a in args if isinstance(a, list | tuple) for i in a)
            host_counter = any(a is t for a in args for t in counters)
            if (name.startswith(waits) and not host_counter) or bool_index:
                self.found.append(name)
            return func(*args, **(kwargs or {}))

    r, _ = make_runner(holdout=0.2, snapshot_every=100, max_iter=50)
    assert r.n_heldout > 0
    for _ in range(3):
        r.step()
    counters = [st["step"] for st in r.opt.state.values()]
    assert counters and all(t.device.type == "cpu" for t in counters)
    with Record() as rec:
        s = r.step()
    assert rec.found == []
    assert s.heldout is not None and math.isfinite(s.loss) and s.clip_fraction is not None
    assert s.heldout == pytest.approx(r.heldout_error(r.ema), rel=1e-6)


def test_compile_mode_is_checked_and_reaches_the_spec(tmp_path):
    from recon.udn.spec import SpecError, normalise_spec, udn_config

    with pytest.raises(ValueError, match="compile_mode must be one of default, reduce-overhead"):
        UDNConfig(compile_mode="fast")
    for name in ("m.npy", "p.npy"):
        np.save(tmp_path / name, np.ones((8, 8), dtype=np.float32))
    data = {"measurement": "m.npy", "psf": "p.npy"}
    spec = normalise_spec({"data": data, "device": {"compile": True,
                                                    "compile_mode": "reduce-overhead"}},
                          base_dir=tmp_path)
    assert udn_config(spec).compile_mode == "reduce-overhead"
    assert udn_config(normalise_spec({"data": data}, base_dir=tmp_path)).compile_mode == "default"
    with pytest.raises(SpecError, match="compile_mode"):
        normalise_spec({"data": data, "device": {"compile_mode": "fast"}}, base_dir=tmp_path)
