"""Fixtures for the plan tests: one thread, a private cost cache, shared captures."""

from __future__ import annotations

import pytest
import torch

from benchmarks.plan_cases import moving_capture, object_capture, static_capture

H, W = 48, 64


@pytest.fixture(autouse=True)
def _one_thread_private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LENSLESSCAM_CACHE_DIR", str(tmp_path / "cache"))
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="session")
def static_cap():
    return static_capture(H, W, seed=0)


@pytest.fixture(scope="session")
def moving_cap():
    # frame of 23 + 13 = 36 lines; the scene jumps every 12 lines: 3 scene frames
    return moving_capture(H, W, period=12, seed=0)


@pytest.fixture(scope="session")
def object_cap():
    return object_capture(H, W, seed=0)
