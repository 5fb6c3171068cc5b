"""Lensless image I/O: the one import point for readers, preprocessing, checks and files.

This module re-exports the public names of the modules that do the work, one responsibility
each:

- :mod:`recon.readers`: :func:`load_image` (raw arrays from TIFF, PNG/JPEG/BMP, ``.npy``,
  ``.npz``, ``.mat``) and the :func:`load_psf`, :func:`load_measurement`,
  :func:`load_psf_stack` loaders;
- :mod:`recon.preprocess`: :func:`subtract_dark`, :func:`auto_dark_level`,
  :func:`box_downsample`, :func:`clip_nonneg`, :func:`normalise`, :func:`to_gray`,
  :func:`to_channel_first`, and the downsampling rules :func:`downsample_masked`,
  :func:`downsample_mask` (a coarse pixel is measured when ANY sensor pixel under it is, its
  value the mean of the measured ones) and :func:`downsample_rows` (shutter functions);
- :mod:`recon.checks`: :func:`check_pair`, :func:`check_measurement`;
- :mod:`recon.reconfile`: the reconstruction file format (:func:`save_reconstruction`,
  :func:`read_reconstruction`, :func:`reconstruction_paths`);
- :mod:`recon.previews`: :func:`contrast_stretch` and the PNG/GIF preview writers;
- :mod:`recon.falsecolor`: :func:`load_false_color_weights`.

Whole problems (PSF, measurement, mask, shutter, filters, truth, downsampled and checked as one)
are loaded by :func:`recon.problem.load_problem`.

Array conventions (numpy at every file boundary, float32 unless stated):

- a scene or reconstruction is ``(C, K, H, W)``: colour channels, frames/bands/depth planes,
  rows, columns;
- a measurement is ``(C, H, W)``;
- a PSF is ``(C, H, W)`` and a PSF stack (one PSF per depth plane) is ``(K, H, W)``.
"""

from __future__ import annotations

from recon.checks import MeasurementCheck, MeasurementWarning, check_measurement, check_pair
from recon.falsecolor import load_false_color_weights
from recon.preprocess import (
    AUTO_DARK_PATCH,
    LUMA_WEIGHTS,
    ChannelOrder,
    Channels,
    NormMode,
    auto_dark_level,
    box_downsample,
    clip_nonneg,
    downsample_mask,
    downsample_masked,
    downsample_rows,
    normalise,
    subtract_dark,
    to_channel_first,
    to_gray,
)
from recon.previews import contrast_stretch, preview_frames, preview_image, write_gif, write_png
from recon.readers import (
    DarkSpec,
    PathLike,
    load_image,
    load_measurement,
    load_psf,
    load_psf_stack,
)
from recon.reconfile import (
    RECONSTRUCTION_FORMAT,
    RECONSTRUCTION_KINDS,
    Kind,
    data_hash,
    read_reconstruction,
    reconstruction_paths,
    save_reconstruction,
)

__all__ = [
    "AUTO_DARK_PATCH",
    "LUMA_WEIGHTS",
    "RECONSTRUCTION_FORMAT",
    "RECONSTRUCTION_KINDS",
    "ChannelOrder",
    "Channels",
    "DarkSpec",
    "Kind",
    "MeasurementCheck",
    "MeasurementWarning",
    "NormMode",
    "PathLike",
    "auto_dark_level",
    "box_downsample",
    "check_measurement",
    "check_pair",
    "clip_nonneg",
    "contrast_stretch",
    "data_hash",
    "downsample_mask",
    "downsample_masked",
    "downsample_rows",
    "load_false_color_weights",
    "load_image",
    "load_measurement",
    "load_psf",
    "load_psf_stack",
    "normalise",
    "preview_frames",
    "preview_image",
    "read_reconstruction",
    "reconstruction_paths",
    "save_reconstruction",
    "subtract_dark",
    "to_channel_first",
    "to_gray",
    "write_gif",
    "write_png",
]
