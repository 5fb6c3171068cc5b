"""Fixtures: the real simulated camera and the simulated point-source firmware on a real PTY."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.lightsource import SerialPointSource
from drivers.pointsource_sim import SimulatedSource, spawn_simulated_source
from drivers.simcam import SimulatedCamera
from recon.simulate import render_frames, synthetic_psf

ROWS, COLS = 64, 80
#: The on-axis point: a delta at (H//2, W//2) of the scene plane images to exactly the PSF.
ON_AXIS = (ROWS // 2, COLS // 2)


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    """FISTA on 64x80 runs ~50x slower with 2 threads on a busy 2-vCPU machine: use one."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture(scope="module")
def true_psf() -> np.ndarray:
    """The simulator's PSF (unit sum, 64x80)."""
    return synthetic_psf((ROWS, COLS), n_points=40, blur=1.0, seed=3)


@pytest.fixture
def firmware(tmp_path: Path) -> Iterator[SimulatedSource]:
    """The simulated point-source firmware in its own process on a PTY."""
    sim = spawn_simulated_source(tmp_path / "light-state.json")
    try:
        yield sim
    finally:
        sim.stop()


@pytest.fixture
def source(firmware: SimulatedSource) -> Iterator[SerialPointSource]:
    """The serial driver talking to the firmware through pyserial."""
    with SerialPointSource(firmware.port, timeout_s=2.0) as src:
        yield src


@pytest.fixture
def make_camera(
    true_psf: np.ndarray, firmware: SimulatedSource
) -> Iterator[Callable[..., SimulatedCamera]]:
    """Factory of open simulated cameras that see the firmware's light (closed at teardown)."""
    cams: list[SimulatedCamera] = []

    def make(**overrides: Any) -> SimulatedCamera:
        kw: dict[str, Any] = {
            "renderer": render_frames(true_psf),
            "light_state": firmware.state_path,
            "point_position": ON_AXIS,
            "point_flux_e_per_ms": 5e6,
            "exposure_us": 100.0,
            "pacing": False,
            "seed": 7,
        }
        kw.update(overrides)
        cam = SimulatedCamera(COLS, ROWS, **kw)
        cam.open()
        cams.append(cam)
        return cam

    yield make
    for cam in cams:
        cam.close()


def out_dir_files(path: Path) -> list[str]:
    """Every entry of a folder (temporary files included)."""
    return sorted(p.name for p in path.iterdir())
