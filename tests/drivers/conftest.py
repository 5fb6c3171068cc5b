"""Fixtures for the driver tests: GenTL producers, recorded frames, simulated point sources.

``TLSimu.cti`` ships only in the ``genicam==1.5.0`` wheel; installing that version would
replace 1.6.0, so the session fixture downloads the wheel with pip (no install) and extracts
the producer and its one library into ``~/.cache/lenslesscam/gentl/genicam-1.5.0`` (reused
afterwards; ``LENSLESSCAM_TLSIMU_CTI`` points at another copy).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.genicam import find_producers, gentl_cache_dir
from drivers.pointsource_sim import SimulatedSource, spawn_simulated_source

TLSIMU_FILES = ("TLSimu.cti", "libVirtualFG.so")


def _extract_tlsimu(wheel: Path, dest: Path) -> None:
    """Extract the producer files from the wheel into ``dest`` atomically (rename a folder)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".tlsimu-", dir=dest.parent))
    try:
        with zipfile.ZipFile(wheel) as zf:
            for name in zf.namelist():
                base = name.rsplit("/", 1)[-1]
                if base in TLSIMU_FILES:
                    (tmp / base).write_bytes(zf.read(name))
        missing = [f for f in TLSIMU_FILES if not (tmp / f).exists()]
        if missing:
            raise RuntimeError(f"{wheel.name} lacks {missing}")
        try:
            tmp.rename(dest)
        except OSError:
            if not (dest / "TLSimu.cti").exists():  # someone else won the race if it exists
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _find_tlsimu() -> Path:
    env = os.environ.get("LENSLESSCAM_TLSIMU_CTI")
    if env:
        return Path(env)
    dest = gentl_cache_dir() / "genicam-1.5.0"
    if (dest / "TLSimu.cti").exists():
        return dest / "TLSimu.cti"
    for p in sys.path:  # a genicam 1.5.0 installed somewhere else
        cand = Path(p) / "genicam" / "TLSimu.cti"
        if cand.exists():
            return cand
    with tempfile.TemporaryDirectory() as d:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:"]
        cmd += ["--disable-pip-version-check", "genicam==1.5.0", "-d", d]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        if r.returncode != 0:
            raise RuntimeError(f"pip download genicam==1.5.0 failed:\n{r.stdout}\n{r.stderr}")
        wheels = sorted(Path(d).glob("genicam-1.5.0-*.whl"))
        if not wheels:
            raise RuntimeError(f"pip download left no genicam 1.5.0 wheel in {d}")
        _extract_tlsimu(wheels[0], dest)
    return dest / "TLSimu.cti"


@pytest.fixture(scope="session")
def tlsimu_cti() -> Path:
    """Path of TLSimu.cti (downloaded and cached on first use)."""
    path = _find_tlsimu()
    assert path.exists(), path
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
