"""Calibration at the bench: PSF capture, dark and bad-pixel maps, shutter and filter functions.

Every capture is a stepwise workflow (a generator of :class:`~calibration.workflow.Progress`
events, wrapped in :class:`~calibration.workflow.Workflow` for cancellation), shared by the CLI
(``lenslesscam calibrate ...``) and the GUI wizard. The files they write are defined in
:mod:`recon.calibfile`.

- :mod:`calibration.psf`: :func:`capture_psf`, :func:`capture_depth_stack`, quality report.
- :mod:`calibration.darks`: dark frames, hot/dead pixel maps (the erasure mask), repair.
- :mod:`calibration.shutter`: shutter function from timing, and measured by strobing
  (:func:`calibrate_shutter`: the one path of the CLI and the wizard).
- :mod:`calibration.filters`: hyperspectral filter cubes.
"""

from calibration.darks import PixelMaps, calibrate_pixel_maps, capture_darks, pixel_maps
from calibration.filters import FilterCube, load_filter_cube
from calibration.psf import (
    DepthStack,
    PsfCalibration,
    PsfQuality,
    PsfSettings,
    capture_depth_stack,
    capture_psf,
)
from calibration.shutter import (
    ShutterFunction,
    ShutterMeasurement,
    ShutterSettings,
    calibrate_shutter,
    measure_shutter,
    shutter_from_timing,
    strobe_time,
)
from calibration.workflow import CalibrationCancelled, CalibrationError, Progress, Workflow

__all__ = [
    "CalibrationCancelled",
    "CalibrationError",
    "DepthStack",
    "FilterCube",
    "PixelMaps",
    "Progress",
    "PsfCalibration",
    "PsfQuality",
    "PsfSettings",
    "ShutterFunction",
    "ShutterMeasurement",
    "ShutterSettings",
    "Workflow",
    "calibrate_pixel_maps",
    "calibrate_shutter",
    "capture_darks",
    "capture_depth_stack",
    "capture_psf",
    "load_filter_cube",
    "measure_shutter",
    "pixel_maps",
    "shutter_from_timing",
    "strobe_time",
]
