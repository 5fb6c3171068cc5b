"""Hyperspectral filter cubes: load, validate, normalise, save.

A filter cube F (K, H, W) holds the transmission of every sensor pixel in each of K bands
(the spectral model's M_k). It comes from the instrument maker or a monochromator scan as a
MATLAB ``.mat``, ``.npy`` or TIFF file, in (K, H, W) or (H, W, K) layout (SpectralDiffuserCam
stores (H, W, K)). :func:`load_filter_cube` reads it (through :func:`recon.io.load_image`),
:func:`validate_filter_cube` checks it against the sensor (shape, NaN/inf, negative values,
an empty band) and :func:`normalise_filter_cube` scales it; :meth:`FilterCube.save` writes the
calibration file (:func:`recon.calibfile.save_filter_cube`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from recon.checks import check_filter_cube

__all__ = [
    "FilterCube",
    "load_filter_cube",
    "normalise_filter_cube",
    "validate_filter_cube",
]

Layout = Literal["auto", "khw", "hwk"]
Norm = Literal["max", "none"]


@dataclass(frozen=True)
class FilterCube:
    """A validated filter cube (K, H, W) float32 with its metadata."""

    cube: np.ndarray
    metadata: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def bands(self) -> int:
        """Number of bands K."""
        return int(self.cube.shape[0])

    def save(self, path: str | os.PathLike[str]) -> FilterCube:
        """Write the calibration file (atomically); returns the cube with its path."""
        from recon.calibfile import save_filter_cube

        return replace(self, path=save_filter_cube(path, self.cube, self.metadata))


def validate_filter_cube(
    raw: Any,
    sensor_shape: tuple[int, int],
    *,
    layout: Layout = "auto",
    what: str = "filter cube",
    tolerance: float = 1e-6,
) -> np.ndarray:
    """Check a cube against the sensor and return it as (K, H, W) float32.

    ``layout='auto'`` takes (K, H, W) when the last two axes match the sensor, else (H, W, K)
    when the first two do. Raises ValueError naming the problem: wrong number of axes or a
    shape that fits the sensor in neither layout, NaN or infinite values, negative
    transmissions (below ``-tolerance`` x the maximum; smaller ones are clipped to 0), an
    all-zero cube or band.
    """
    arr = np.asarray(raw)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be numeric, got dtype {arr.dtype}")
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ValueError(f"{what} must have 3 axes (bands and the sensor's 2), got {arr.shape}")
    h, w = int(sensor_shape[0]), int(sensor_shape[1])
    if layout == "auto":
        if arr.shape[1:] == (h, w) and arr.shape[:2] == (h, w):
            raise ValueError(
                f"{what} of shape {arr.shape} fits the {h}x{w} sensor as (K, H, W) and as "
                "(H, W, K): say which (layout 'khw' or 'hwk', --layout)")
        if arr.shape[1:] == (h, w):
            layout = "khw"
        elif arr.shape[:2] == (h, w):
            layout = "hwk"
        else:
            raise ValueError(
                f"{what} of shape {arr.shape} does not match the {h}x{w} sensor in either "
                f"(K, {h}, {w}) or ({h}, {w}, K) layout"
            )
    if layout == "hwk":
        arr = np.moveaxis(arr, -1, 0)
    elif layout != "khw":
        raise ValueError(f"layout must be 'auto', 'khw' or 'hwk', got {layout!r}")
    if arr.shape[1:] != (h, w):
        raise ValueError(f"{what} has bands of {arr.shape[1:]}, the sensor is {h}x{w}")
    cube = np.ascontiguousarray(arr, dtype=np.float32)
    # the one rule for the values, shared with recon's reader (recon.problem.read_filters)
    return np.asarray(check_filter_cube(cube, what, tolerance=tolerance), dtype=np.float32)


def normalise_filter_cube(cube: np.ndarray, mode: Norm = "max") -> tuple[np.ndarray, float]:
    """Scale the cube so its largest transmission is 1 (``'max'``), or keep it (``'none'``).

    ``'none'`` requires values in [0, 1]. Returns (cube, factor applied).
    """
    if mode == "none":
        top = float(cube.max())
        if top > 1.0 + 1e-6:
            raise ValueError(
                f"filter cube values reach {top:.4g}, above 1: a transmission is in [0, 1]; "
                "normalise it ('max')"
            )
        return cube, 1.0
    if mode != "max":
        raise ValueError(f"normalisation must be 'max' or 'none', got {mode!r}")
    factor = 1.0 / float(cube.max())
    return (cube * np.float32(factor)).astype(np.float32), factor


def load_filter_cube(
    path: str | os.PathLike[str],
    sensor_shape: tuple[int, int],
    *,
    key: str | None = None,
    layout: Layout = "auto",
    normalise: Norm = "max",
    downsample: int = 1,
    wavelengths_nm: list[float] | None = None,
) -> FilterCube:
    """Load (MAT, NPY, NPZ, TIFF), optionally box-downsample, validate and normalise a cube.

    ``key`` names the variable of a ``.mat``/``.npz`` file; ``wavelengths_nm`` (one per
    band) is stored in the metadata when given.
    """
    from recon.formats import file_hash
    from recon.io import box_downsample, load_image
    from recon.readers import FILTER_KEYS

    p = Path(path)
    raw = np.asarray(load_image(p, key=key, prefer=FILTER_KEYS))
    if downsample > 1:
        if raw.ndim != 3:
            raise ValueError(f"filter cube {p} must have 3 axes, got {raw.shape}")
        want = (sensor_shape[0] * downsample, sensor_shape[1] * downsample)
        if raw.shape[1:] != want and raw.shape[:2] != want:
            raise ValueError(
                f"filter cube {p} of shape {raw.shape} is not the {sensor_shape[0]}x"
                f"{sensor_shape[1]} sensor at {downsample}x: its bands must be {want[0]}x"
                f"{want[1]} (as (K, H, W) or (H, W, K))")
        moved = layout == "hwk" or (
            layout == "auto"
            and raw.shape[:2] == (sensor_shape[0] * downsample, sensor_shape[1] * downsample)
        )
        khw = np.moveaxis(raw, -1, 0) if moved else raw
        raw = box_downsample(khw, downsample)
        layout = "khw"
    cube = validate_filter_cube(raw, sensor_shape, layout=layout, what=f"filter cube {p.name}")
    cube, factor = normalise_filter_cube(cube, normalise)
    if wavelengths_nm is not None and len(wavelengths_nm) != cube.shape[0]:
        raise ValueError(
            f"{len(wavelengths_nm)} wavelengths given for a cube of {cube.shape[0]} bands"
        )
    metadata: dict[str, Any] = {
        "source": {"file": str(p), "file_hash": file_hash(p), "key": key},
        "normalisation": {"mode": normalise, "factor": factor},
        "downsample": int(downsample),
        "sensor_shape": [int(sensor_shape[0]), int(sensor_shape[1])],
        "bands": int(cube.shape[0]),
        "wavelengths_nm": None if wavelengths_nm is None else [float(x) for x in wavelengths_nm],
    }
    return FilterCube(cube, metadata)
