"""Session-wide test settings."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    """One torch thread: on a 2-core machine that is also running simulators and subprocesses,
    2 threads can be many times slower than 1 (measured: up to 50x). Benchmarks set their own."""
    import os

    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    # commands called in-process (app.cli.main) apply recon.threads' policy, which honours
    # OMP_NUM_THREADS: keep them at one thread too
    env_before = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"
    yield
    torch.set_num_threads(before)
    if env_before is None:
        os.environ.pop("OMP_NUM_THREADS", None)
    else:
        os.environ["OMP_NUM_THREADS"] = env_before


@pytest.fixture(scope="session")
def job_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """One fork server for the session (:class:`tests.udn.jobrunner.JobServer`): the job and
    app processes tests start through it are real processes forked from one that imported
    torch once, instead of new interpreters that each take seconds to import it on a busy
    machine."""
    from tests.udn.jobrunner import JobServer

    with JobServer(tmp_path_factory.mktemp("job-server")) as server:
        yield server
