"""Talking to the light source and describing the camera, with calibration-grade errors.

A failing source command (a timeout, an ``ERR`` reply, a vanished port) becomes a
:class:`~calibration.workflow.CalibrationError` that names the command and says what to check;
:func:`source_off_quietly` is for ``finally`` blocks (a workflow that failed still tries to
leave the light off, without hiding the original error).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, TypeVar

from calibration.workflow import CalibrationError
from drivers.camera import Camera, CameraError, Frame
from drivers.lightsource import LightSource, LightSourceError

__all__ = [
    "camera_description",
    "source_alive",
    "source_call",
    "source_identity",
    "source_off",
    "source_off_quietly",
    "source_on",
    "source_strobe",
]

_log = logging.getLogger(__name__)
T = TypeVar("T")


def _describe(source: LightSource) -> str:
    d = getattr(source, "describe", None)
    return str(d()) if callable(d) else type(source).__name__


def _require(source: LightSource | None, stage: str) -> LightSource:
    """The source, or a CalibrationError when none is connected.

    The app's point source can be disconnected between the wizard's pages (it gave "'NoneType'
    object has no attribute 'identify'").
    """
    if source is None:
        raise CalibrationError(f"{stage}: no point source is connected",
                               "Connect the point source (in the app: Controls, Point "
                               "source; on the command line: --source) and start again; "
                               "nothing was saved", stage=stage)
    return source


def source_call(source: LightSource, what: str, fn: Callable[[], T], *, stage: str) -> T:
    """Run ``fn`` (a source command described by ``what``); errors become CalibrationError."""
    try:
        return fn()
    except LightSourceError as exc:
        raise CalibrationError(
            f"{stage}: the point source failed to {what} ({exc})",
            f"Check the {_describe(source)}: power, cable and port; then run the calibration "
            "again; nothing was saved",
            stage=stage,
        ) from exc


def source_on(source: LightSource | None, intensity: float | None = None, *, stage: str) -> None:
    """Set the intensity (when given) and switch the continuous light on."""
    source = _require(source, stage)
    if intensity is not None:
        value = float(intensity)
        source_call(
            source, f"set intensity {value:g}", lambda: source.set_intensity(value), stage=stage
        )
    source_call(source, "switch on", source.on, stage=stage)


def source_off(source: LightSource | None, *, stage: str) -> None:
    """Switch the light (and any strobe) off."""
    source = _require(source, stage)
    source_call(source, "switch off", source.off, stage=stage)


def source_strobe(source: LightSource | None, delay_us: float, duration_us: float, *,
                  stage: str) -> None:
    """Arm one pulse per camera trigger."""
    source = _require(source, stage)
    source_call(
        source,
        f"strobe at {delay_us:g} us for {duration_us:g} us",
        lambda: source.strobe(delay_us, duration_us),
        stage=stage,
    )


def source_off_quietly(source: LightSource | None) -> None:
    """Best effort to switch off after a failure (logs instead of raising)."""
    if source is None:
        return
    try:
        source.off()
    except Exception as exc:  # the original error is what the user must see
        _log.warning("could not switch the point source off: %s", exc)


def source_alive(source: LightSource | None, *, stage: str) -> Callable[[], None]:
    """A per-frame check for :func:`calibration.frames.acquire_frames`: the light is unchanged.

    The source still answers and is as the stage set it. While the light must stay on, a source
    that died (its firmware, cable or port) would leave the camera looking at a stale scene,
    and one switched off or re-set (a firmware restart comes back off) would mix frames of
    another light into the average; querying its state after each frame turns either into a
    :class:`CalibrationError` within one frame time. The state to keep (mode, intensity,
    strobe timing) is read when the check is made.
    """
    source = _require(source, stage)
    # what the light was set to (read now, just after the stage set it): a source that
    # answers but was switched off, restarted (its READY state is off) or re-set by another
    # program would leave frames of another light in the average
    ref = source_call(source, "report its state", source.status, stage=stage)

    def check() -> None:
        st = source_call(source, "report its state", source.status, stage=stage)
        changed = [f"{name} {a} -> {b}" for name, a, b in (
            ("mode", _mode(ref), _mode(st)),
            ("intensity", f"{ref.intensity:g}", f"{st.intensity:g}"),
            ("strobe delay", f"{ref.strobe_delay_us:g} us", f"{st.strobe_delay_us:g} us"),
            ("strobe duration", f"{ref.strobe_duration_us:g} us",
             f"{st.strobe_duration_us:g} us")) if a != b]
        if changed:
            raise CalibrationError(
                f"{stage}: the point source changed while its frames were taken "
                f"({', '.join(changed)})",
                f"Leave the {_describe(source)} alone during the capture (another program on "
                "its port, a restart or a power cut changes it) and run the calibration "
                "again; nothing was saved",
                stage=stage,
            )

    return check


def _mode(st: Any) -> str:
    m = getattr(st, "mode", None)
    return str(getattr(m, "value", m))


def source_identity(source: LightSource | None, *, stage: str) -> str:
    """The source's identification string (also proves it answers)."""
    source = _require(source, stage)
    return source_call(source, "identify itself", source.identify, stage=stage)


def camera_description(camera: Camera, frame: Frame | None = None) -> dict[str, Any]:
    """Camera identity and settings for calibration metadata (plain JSON types)."""
    out: dict[str, Any] = {"backend": camera.backend, "camera_id": camera.camera_id}
    try:
        caps = camera.capabilities()
        out.update(
            model=caps.model, sensor_width=caps.sensor_width, sensor_height=caps.sensor_height
        )
    except CameraError as exc:
        _log.info("camera capabilities unavailable: %s", exc)
    if frame is not None:
        md = frame.metadata()
        for key in ("roi", "binning", "pixel_format", "bit_depth", "exposure_us", "gain"):
            out[key] = md[key]
    return out
