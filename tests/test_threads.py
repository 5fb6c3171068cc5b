"""The thread policy (recon.threads): free cores from core count and load, explicit wins."""

from __future__ import annotations

import pytest
import torch

from recon.threads import MAX_AUTO_THREADS, apply_threads, choose_threads


@pytest.mark.parametrize(
    ("cores", "load", "expected"),
    [
        (2, 0.0, 2),  # idle 2-core machine: both cores
        (2, 0.3, 2),
        (2, 0.6, 1),  # anything else running: one thread (2 can be 10x slower then)
        (2, 2.9, 1),
        (2, 9.0, 1),  # overloaded: never below 1
        (1, 0.0, 1),
        (16, 10.2, 6),
        (16, 4.2, MAX_AUTO_THREADS),
        (64, 0.0, MAX_AUTO_THREADS),
    ],
)
def test_auto_uses_free_cores(cores: int, load: float, expected: int) -> None:
    c = choose_threads(None, cores=cores, load=load, env={})
    assert (c.threads, c.source) == (expected, "auto")
    assert f"{cores} cores" in c.reason and f"load {load:.2f}" in c.reason


def test_explicit_request_and_env_win() -> None:
    assert choose_threads(3, cores=2, load=9.0, env={}).threads == 3
    assert choose_threads("4", cores=2, load=0.0, env={}).source == "requested"
    env = {"OMP_NUM_THREADS": "1"}
    c = choose_threads(None, cores=2, load=0.0, env=env)
    assert (c.threads, c.source) == (1, "OMP_NUM_THREADS")
    assert choose_threads(2, cores=2, load=0.0, env=env).threads == 2  # request beats env
    for auto in (0, "auto", "0"):
        assert choose_threads(auto, cores=2, load=0.0, env={}).source == "auto"


@pytest.mark.parametrize("bad", [-1, "two", 1.5, True])
def test_bad_request_is_one_clear_error(bad: object) -> None:
    with pytest.raises(ValueError, match="threads must be a whole number"):
        choose_threads(bad, cores=2, load=0.0, env={})  # type: ignore[arg-type]


def test_apply_sets_torch() -> None:
    before = torch.get_num_threads()
    try:
        c = apply_threads(2)
        assert torch.get_num_threads() == c.threads == 2
        assert "requested" in str(c)
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(
    ("work", "expected"),
    [
        (150 * 200, 1),  # the demo (1/8-scale tutorial): one thread even on an idle machine
        (256 * 256, 1),  # up to one FFT_PIXELS_PER_THREAD: one
        (384 * 384, 2),
        (16 * 128 * 128, 2),  # a 16-bin video counts its slices
        (1024 * 1024, 2),  # never above the free cores
    ],
)
def test_auto_is_capped_by_the_fft_work(work: int, expected: int) -> None:
    c = choose_threads(None, cores=2, load=0.0, env={}, work=work)
    assert (c.threads, c.source, c.work) == (expected, "auto", work)
    assert f"{work} scene pixels" in c.reason
    assert choose_threads(None, cores=2, load=1.5, env={}, work=10**7).threads == 1  # busy
    assert choose_threads(2, cores=2, load=0.0, env={}, work=100).threads == 2  # asked: kept


def test_fit_threads_refines_only_an_automatic_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    import recon.threads as th

    before = torch.get_num_threads()
    try:
        monkeypatch.setattr(th, "_process_choice", None)
        torch.set_num_threads(2)
        assert th.fit_threads((1, 1, 64, 64)) is None  # the policy never applied: untouched
        assert torch.get_num_threads() == 2
        monkeypatch.setattr(th, "_process_choice", th.ThreadChoice(2, 2, 0.0, "auto"))
        small = th.fit_threads((1, 1, 150, 200))
        assert small is not None and small.threads == 1 == torch.get_num_threads()
        big = th.fit_threads((3, 1, 256, 256))  # a later, larger problem: both threads again
        assert big is not None and big.threads == 2 == torch.get_num_threads()
        asked = th.ThreadChoice(2, 2, 0.0, "requested")
        monkeypatch.setattr(th, "_process_choice", asked)
        assert th.fit_threads((1, 1, 8, 8)) is asked and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_absurd_thread_counts_are_refused_before_reaching_openmp() -> None:
    """--threads 5000 hung, 20000 failed in libgomp, 100000 crashed: more than 4 threads per
    core is a one-line error from the option, and cut from OMP_NUM_THREADS."""
    assert choose_threads(8, cores=2, load=0.0, env={}).threads == 8
    with pytest.raises(ValueError, match=r"threads 9 is more than 4x this machine's 2 cores"):
        choose_threads(9, cores=2, load=0.0, env={})
    # an environment's count (a scheduler's, for another machine) is cut, with a note
    c = choose_threads(None, cores=2, load=0.0, env={"OMP_NUM_THREADS": "100000"})
    assert c.threads == 8 and "OMP_NUM_THREADS 100000 cut to 4x cores" in c.reason
