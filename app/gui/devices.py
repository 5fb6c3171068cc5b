"""The devices at the bench, without Qt: a camera and a point source, real or simulated.

:class:`Bench` opens and closes them by spec. With no hardware it builds the simulated bench:
a :class:`~drivers.simcam.SimulatedCamera` that renders a bundled lensed scene through the
tutorial PSF with the same forward model the solvers invert
(:func:`recon.simulate.render_frames`, injected), and the simulated point-source firmware on a
PTY (:func:`drivers.pointsource_sim.spawn_simulated_source`) whose lit state the camera reads
from a state file, so switching the source on lights the next frame.

Every method may block (opening a GenICam device, spawning the firmware, a serial timeout):
the GUI calls them from a worker thread, never from its own.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "SCENES",
    "SIM_CAMERA",
    "SIM_PORT",
    "Bench",
    "CameraChoice",
    "PortChoice",
    "SimConfig",
    "list_camera_choices",
    "list_port_choices",
    "make_sim_camera",
    "scene_image",
    "set_sim_scene",
]

_log = logging.getLogger(__name__)


def best_effort(what: str, fn: Callable[[], object]) -> None:
    """Run a device call whose failure must not stop the caller; log the reason if it fails.

    For closing or stopping a device that may be gone already: never swallowed silently.
    """
    try:
        fn()
    except Exception as exc:  # any backend's error: the caller goes on, the log says why
        _log.warning("%s failed: %s", what, exc)

#: Camera spec of the simulated camera.
SIM_CAMERA = "sim"
#: Port name that means "spawn the simulated point-source firmware on a PTY".
SIM_PORT = "sim"
#: Scenes the simulated camera can show: name -> label ("none": dark, point source only).
SCENES: dict[str, str] = {
    "im65": "butterfly",
    "im740": "crab",
    "im408": "bottle caps",
    "none": "none (dark; point source only)",
}


class ReconnectCancelled(Exception):
    """A reconnect attempt ended by the user (Disconnect, another camera) before its check."""


@dataclass(frozen=True)
class CameraChoice:
    """A camera the user can pick: ``spec`` for :func:`drivers.open_camera`.

    ``label`` is what the list shows (short: the list is narrow at 1366x768); ``detail``, when
    there is one, goes with it into the tooltip.
    """

    spec: str
    backend: str
    label: str
    detail: str = ""

    @property
    def tooltip(self) -> str:
        """The whole description."""
        return f"{self.label} ({self.detail})" if self.detail else self.label


@dataclass(frozen=True)
class PortChoice:
    """A point-source port: a serial device path, or :data:`SIM_PORT`."""

    port: str
    label: str


#: the simulated camera, listed even before (and whatever) discovery finds
SIM_CAMERA_CHOICE = CameraChoice(SIM_CAMERA, "sim", "Simulated camera",
                                 "the Sim scene below through the bundled tutorial PSF")
#: the simulated point source, listed first
SIM_PORT_CHOICE = PortChoice(SIM_PORT, "Simulated point source (PTY)")


_producer_lines_seen: set[str] = set()


@contextlib.contextmanager
def _producer_output_logged_once() -> Iterator[None]:
    """Catch what GenTL producers print on stderr (C code) and log each line once per process.

    A producer prints the same "does not implement ..." lines at every discovery; they are
    logged at the first one and dropped after. Other stderr output is passed on.
    """
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to redirect
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
    for line in text.splitlines():
        if not line.strip():
            continue
        if line.startswith("GenTL producer"):
            if line not in _producer_lines_seen:
                _producer_lines_seen.add(line)
                _log.warning("%s", line)
        else:
            sys.stderr.write(line + "\n")


def list_camera_choices(show_demo: bool = False) -> list[CameraChoice]:
    """Hardware cameras first, then the simulated camera; demo cameras only on request.

    Demo cameras (the GenTL demo producers' and the test suite's cached simulator,
    :attr:`drivers.registry.CameraInfo.demo`) are listed after the others when ``show_demo``.
    """
    try:
        from drivers.registry import list_cameras

        with _producer_output_logged_once():
            infos = list_cameras()
    except Exception as exc:  # discovery must never stop the app from starting
        _log.warning("camera discovery failed: %s", exc)
        infos = []
    real = [CameraChoice(i.spec, i.backend, f"{i.spec}: {i.description}")
            for i in infos if i.spec != SIM_CAMERA and not i.demo]
    demo = [CameraChoice(i.spec, i.backend, f"{i.spec}: {i.description} (demo)")
            for i in infos if i.spec != SIM_CAMERA and i.demo]
    return [*real, SIM_CAMERA_CHOICE, *(demo if show_demo else [])]


def list_port_choices() -> list[PortChoice]:
    """The simulated point source first, then the serial ports pyserial finds."""
    out = [SIM_PORT_CHOICE]
    try:
        from drivers.registry import list_serial_ports

        for p in list_serial_ports():
            label = f"{p.device} {p.description}".strip()
            out.append(PortChoice(p.device, label))
    except Exception as exc:
        _log.warning("serial port discovery failed: %s", exc)
    return out


@dataclass(frozen=True)
class SimConfig:
    """What the simulated bench shows.

    ``psf`` None: the bundled DiffuserCam tutorial PSF (150 x 200). ``scene``: a key of
    :data:`SCENES`. ``peak_fraction``: the brightest pixel of the scene's measurement at
    ``exposure_us`` reaches this fraction of the full well (the PSF of the point source at
    full intensity likewise). ``scene_fill``: the object covers this fraction of the field
    (centred, black around it), as an object at the bench does; a scene that fills the whole
    field sends much of its light past the sensor and reconstructs poorly.
    """

    psf: npt.NDArray[np.float32] | None = None
    scene: str = "im65"
    exposure_us: float = 10_000.0
    frame_rate_hz: float = 20.0
    peak_fraction: float = 0.6
    scene_fill: float = 0.6
    noise: bool = True
    pacing: bool = True


def sim_psf(config: SimConfig) -> npt.NDArray[np.float32]:
    """The simulated bench's true PSF (H, W), unit sum."""
    if config.psf is not None:
        p = np.asarray(config.psf, dtype=np.float32)
        p = p[0] if p.ndim == 3 else p
    else:
        from recon.samples import tutorial_psf

        p = tutorial_psf()[0]
    return np.ascontiguousarray(p / p.sum(dtype=np.float64), dtype=np.float32)


def scene_image(
    name: str, shape: tuple[int, int], fill: float = 0.6
) -> npt.NDArray[np.float32] | None:
    """Bundled lensed scene ``name`` resized to ``fill`` of ``shape``, centred on black."""
    if name == "none":
        return None
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    if not 0 < fill <= 1:
        raise ValueError(f"scene fill must be in (0, 1], got {fill!r}")
    from scipy.ndimage import zoom

    from recon.samples import lensed_scene

    img = lensed_scene(name)[0, 0]
    h, w = max(1, round(shape[0] * fill)), max(1, round(shape[1] * fill))
    small = zoom(img, (h / img.shape[0], w / img.shape[1]), order=1)[:h, :w]
    out = np.zeros(shape, dtype=np.float32)
    y, x = (shape[0] - small.shape[0]) // 2, (shape[1] - small.shape[1]) // 2
    out[y : y + small.shape[0], x : x + small.shape[1]] = np.clip(small, 0.0, None)
    return out


def make_sim_camera(
    config: SimConfig, light_state: str | Path | None = None, **kwargs: Any
) -> Any:
    """A simulated camera for ``config`` (not opened), the renderer injected.

    The scene and the point source are scaled to ``config.peak_fraction`` of the full well at
    the configured exposure. ``kwargs`` go to :class:`~drivers.simcam.SimulatedCamera`.
    """
    from drivers.simcam import SimulatedCamera
    from recon.simulate import render_frames

    psf = sim_psf(config)
    h, w = psf.shape
    cam = SimulatedCamera(
        width=w,
        height=h,
        renderer=render_frames(psf),
        scene=None,
        scene_shape=(h, w),
        light_state=light_state,
        exposure_us=config.exposure_us,
        frame_rate_hz=config.frame_rate_hz,
        pacing=config.pacing,
        noise=config.noise,
        **kwargs,
    )
    exposure_ms = cam.exposure_us / 1000.0
    target = config.peak_fraction * cam.full_well_e
    cam.point_flux_e_per_ms = target / (float(psf.max()) * exposure_ms)
    set_sim_scene(cam, config.scene, config.peak_fraction, config.scene_fill)
    return cam


def set_sim_scene(cam: Any, name: str, peak_fraction: float = 0.6, fill: float = 0.6) -> None:
    """Show scene ``name`` (a key of :data:`SCENES`) on a simulated camera, scaled to the well.

    The scale is computed at the camera's current exposure.
    """
    h, w = cam.capabilities().sensor_height, cam.capabilities().sensor_width
    img = scene_image(name, (h, w), fill)
    if img is None:
        cam.scene = None
        return
    cam.scene = img
    electrons, _ = cam.render_electrons()
    peak = float(np.max(electrons))
    if peak > 0:
        cam.scene = img * np.float32(peak_fraction * cam.full_well_e / peak)


class Bench:
    """The camera and the point source the app works with (simulated or real).

    Not thread-safe by itself: the GUI serialises all calls on one worker thread.
    """

    def __init__(self, sim: SimConfig | None = None) -> None:
        self.sim = sim or SimConfig()
        self._tmp = Path(tempfile.mkdtemp(prefix="lenslesscam-bench-"))
        self.light_state_path = self._tmp / "light-state.json"
        self.sim_port_link = self._tmp / "pointsource"
        self.camera: Any = None
        self.camera_spec: str | None = None
        self.light: Any = None
        self.light_port: str | None = None
        self._sim_source: Any = None

    # -- camera --------------------------------------------------------------------------------

    @property
    def is_simulated(self) -> bool:
        """Whether the open camera is the simulated one."""
        return self.camera_spec == SIM_CAMERA

    @property
    def sim_psf(self) -> npt.NDArray[np.float32]:
        """True PSF of the simulated camera."""
        return sim_psf(self.sim)

    def open_camera(self, spec: str, **kwargs: Any) -> Any:
        """Close the current camera, open ``spec`` (``sim``: the simulated bench) and return it."""
        self.close_camera()
        if spec == SIM_CAMERA:
            cam = make_sim_camera(self.sim, light_state=self.light_state_path, **kwargs)
            cam.open()
        else:
            from drivers.registry import open_camera

            cam = open_camera(spec, **kwargs)
        self.camera = cam
        self.camera_spec = spec
        return cam

    def close_camera(self) -> None:
        """Stop and close the camera (errors are logged: the device may be gone)."""
        cam, self.camera, self.camera_spec = self.camera, None, None
        if cam is not None:
            try:
                cam.close()
            except Exception as exc:
                _log.warning("closing %r: %s", cam, exc)

    def reconnect_camera(self, check_timeout_s: float = 1.0,
                         cancel: threading.Event | None = None) -> Any:
        """Close and reopen the same camera object, start its live stream, wait for a frame.

        Returns the first frame; the stream keeps running. The wait allows
        ``check_timeout_s`` plus two frame times (a long exposure is not a lost camera), in
        slices of at most 0.2 s: setting ``cancel`` (Disconnect, another camera) ends it within
        one slice, where a blocking snap held the camera worker for the whole wait (21 s at a
        10 s exposure). Raises the camera's error (:class:`~drivers.camera.CameraTimeout` when
        no frame came, :class:`ReconnectCancelled`); the camera is then left closed.
        """
        from drivers.camera import CameraTimeout

        cam = self.camera
        if cam is None:
            raise RuntimeError("no camera to reconnect")
        best_effort(f"closing {cam.describe()} before reconnecting", cam.close)
        if cancel is not None and cancel.is_set():
            raise ReconnectCancelled("reconnect cancelled")
        try:
            cam.open()
            cam.start_live()
            wait_s = check_timeout_s + 2.0 * cam.expected_frame_s()
            deadline = time.monotonic() + wait_s
            while True:
                if cancel is not None and cancel.is_set():
                    raise ReconnectCancelled("reconnect cancelled")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise CameraTimeout(f"{cam.describe()}: no frame within {wait_s:.3g} s "
                                        "of reopening")
                frame = cam.latest_frame(timeout_s=min(0.2, left))
                if frame is not None:
                    return frame
        except BaseException:
            best_effort(f"stopping {cam.describe()} after a failed check", cam.stop)
            best_effort(f"closing {cam.describe()} after a failed check", cam.close)
            raise

    # -- point source --------------------------------------------------------------------------

    def open_light(self, port: str, *, timeout_s: float = 0.5) -> Any:
        """Close the current source and connect to ``port`` (:data:`SIM_PORT`: spawn it)."""
        self.close_light()
        from drivers.lightsource import SerialPointSource

        path = port
        if port == SIM_PORT:
            path = self._spawn_sim_source()
        light = SerialPointSource(path, timeout_s=timeout_s)
        light.open()
        self.light = light
        self.light_port = port
        return light

    def _spawn_sim_source(self) -> str:
        from drivers.pointsource_sim import spawn_simulated_source

        self._stop_sim_source()
        src = spawn_simulated_source(self.light_state_path, link=self.sim_port_link)
        self._sim_source = src
        return str(self.sim_port_link)

    def _stop_sim_source(self) -> None:
        src, self._sim_source = self._sim_source, None
        if src is not None:
            try:
                src.stop()
            except Exception as exc:
                _log.warning("stopping the simulated point source: %s", exc)

    @property
    def sim_source(self) -> Any:
        """The running simulated firmware (``SimulatedSource``), if any (tests kill it)."""
        return self._sim_source

    def check_light(self) -> Any:
        """Read the source's status (raises its error when it is gone)."""
        if self.light is None:
            raise RuntimeError("no point source connected")
        return self.light.status()

    def reconnect_light(self) -> Any:
        """Reconnect the point source; a dead simulator is started again on the same link."""
        if self.light is None or self.light_port is None:
            raise RuntimeError("no point source to reconnect")
        if self.light_port == SIM_PORT:
            src = self._sim_source
            if src is None or src.process.poll() is not None:
                self._spawn_sim_source()
        self.light.reconnect()
        return self.light

    def close_light(self) -> None:
        """Switch the source off where possible, close it, stop a simulator."""
        light, self.light, self.light_port = self.light, None, None
        if light is not None:
            if light.is_open:
                best_effort("switching the point source off", light.off)
            best_effort("closing the point source", light.close)
        self._stop_sim_source()

    # -- lifetime ------------------------------------------------------------------------------

    def close(self) -> None:
        """Close everything and remove the temporary folder."""
        self.close_camera()
        self.close_light()
        shutil.rmtree(self._tmp, ignore_errors=True)
