"""Fixtures for the driver tests: GenTL producers, recorded frames, simulated point sources.

``TLSimu.cti`` ships only in the ``genicam==1.5.0`` wheel; installing that version would
replace 1.6.0, so the project's install step (``python .ci/fetch_tlsimu.py``, run by
``.ci/run``) extracts the producer into ``<repo>/.gl/genicam-1.5.0``. The tests never download
anything: without that folder (or ``LENSLESSCAM_TLSIMU_CTI`` pointing at another copy) the
TLSimu tests skip and name the command.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.genicam import find_producers
from drivers.pointsource_sim import SimulatedSource, spawn_simulated_source

REPO = Path(__file__).resolve().parents[2]


def _find_tlsimu() -> Path | None:
    env = os.environ.get("LENSLESSCAM_TLSIMU_CTI")
    if env:
        return Path(env)
    cand = REPO / ".gl" / "genicam-1.5.0" / "TLSimu.cti"
    if cand.exists():
        return cand
    for p in sys.path:  # a genicam 1.5.0 installed somewhere else
        cand = Path(p) / "genicam" / "TLSimu.cti"
        if cand.exists():
            return cand
    return None


@pytest.fixture(scope="session")
def tlsimu_cti() -> Path:
    """Path of TLSimu.cti, installed by the install step (skip, naming it, when absent)."""
    path = _find_tlsimu()
    if path is None:
        pytest.skip(
            "TLSimu.cti (genicam 1.5.0's simulated camera) is not installed: run "
            "`python .ci/fetch_tlsimu.py` (the CI install step does)"
        )
    assert path.exists(), f"LENSLESSCAM_TLSIMU_CTI points at a missing file: {path}"
    return path


@pytest.fixture(scope="session")
def viky_cti() -> Path:
    """Path of viky.cti from the installed genicam package."""
    found = [
        p
        for p in find_producers(use_environment=False, include_cache=False)
        if p.name == "viky.cti"
    ]
    assert found, "viky.cti not found in the installed genicam package"
    return found[0]


# --------------------------------------------------------------------------------------------
# recorded frames for the V4L2/OpenCV file path

REC_SHAPE = (24, 32)
REC_FRAMES = 6


@pytest.fixture(scope="session")
def recorded_frames() -> np.ndarray:
    """Known 16-bit frames (N, H, W) using the full 16-bit range."""
    rng = np.random.default_rng(1234)
    frames = rng.integers(0, 65536, size=(REC_FRAMES, *REC_SHAPE), dtype=np.uint16)
    frames[:, 0, 0] = np.arange(REC_FRAMES)  # frame index in a corner pixel
    return frames


@pytest.fixture(scope="session")
def png_sequence(tmp_path_factory: pytest.TempPathFactory, recorded_frames: np.ndarray) -> str:
    """A 16-bit PNG sequence; returns its printf pattern."""
    import cv2

    d = tmp_path_factory.mktemp("pngseq")
    for i, f in enumerate(recorded_frames):
        assert cv2.imwrite(str(d / f"{i:04d}.png"), f)
    return str(d / "%04d.png")


@pytest.fixture(scope="session")
def ffv1_video(tmp_path_factory: pytest.TempPathFactory, recorded_frames: np.ndarray) -> str:
    """A lossless 16-bit grey FFV1 video in Matroska."""
    import cv2

    path = str(tmp_path_factory.mktemp("video") / "frames.mkv")
    params = [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U, cv2.VIDEOWRITER_PROP_IS_COLOR, 0]
    h, w = REC_SHAPE
    vw = cv2.VideoWriter(
        path, cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (w, h), params
    )
    assert vw.isOpened(), "OpenCV cannot write FFV1 16-bit video"
    for f in recorded_frames:
        vw.write(f)
    vw.release()
    return path


# --------------------------------------------------------------------------------------------
# simulated point source processes


class SourceFactory:
    """Starts simulated firmware processes and stops them all at teardown."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.link = tmp / "pointsource.tty"
        self.state_path = tmp / "light-state.json"
        self.started: list[SimulatedSource] = []

    def start(self, *extra: str) -> SimulatedSource:
        """A fresh simulator on the stable link path (replacing any earlier one there)."""
        src = spawn_simulated_source(self.state_path, link=self.link, extra_args=extra)
        self.started.append(src)
        return src

    def stop_all(self) -> None:
        for src in self.started:
            with contextlib.suppress(Exception):
                src.stop()


@pytest.fixture
def sources(tmp_path: Path) -> Iterator[SourceFactory]:
    """Factory of simulated point sources (stopped at teardown)."""
    f = SourceFactory(tmp_path)
    try:
        yield f
    finally:
        f.stop_all()


@pytest.fixture
def sim_source(sources: SourceFactory) -> SimulatedSource:
    """One running simulated point source."""
    return sources.start()
