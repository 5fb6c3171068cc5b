"""A catalogue of every operator and forward model at small sizes, for the adjoint tests.

Add an entry here whenever a new operator or model is written: tests/test_operators.py runs
the dot-product test and the autograd cross-check over all of them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from recon.fista import _GramP, fourier_preconditioner
from recon.models import build_model
from recon.operators import (
    Compose,
    Conv2D,
    Crop,
    Identity,
    LinearOperator,
    Mask,
    StackConvSum,
    SumK,
)
from recon.preprocess import downsample_rows

__all__ = ["OPERATOR_FACTORIES", "make_operator"]

Factory = Callable[[torch.dtype], LinearOperator]


def _rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def _psf(h: int = 12, w: int = 10) -> np.ndarray:
    return _rng().random((h, w))


def _shutter(rows: int) -> np.ndarray:
    # Any non-negative (K, rows) array serves the adjoint tests: a random one with zeros (rows
    # that miss a time bin, as a rolling shutter's do), on the sensor rows then downsampled.
    m = _rng().random((5, rows * 2))
    m[m < 0.3] = 0.0
    return downsample_rows(m, 2)


def _erasure(h: int, w: int) -> np.ndarray:
    return (_rng().random((h, w)) > 0.5).astype(np.float64)


OPERATOR_FACTORIES: dict[str, Factory] = {
    "conv2d": lambda dt: Conv2D(_psf(), (1, 1, 12, 10), dtype=dt),
    "conv2d_field": lambda dt: Conv2D(_psf(), (2, 3, 7, 9), dtype=dt),
    "conv2d_stack": lambda dt: Conv2D(_rng().random((3, 6, 5)), (2, 3, 6, 5), dtype=dt),
    "stack_conv_sum": lambda dt: StackConvSum(_rng().random((3, 6, 5)), (1, 3, 6, 5), dtype=dt),
    "crop": lambda dt: Crop((2, 3, 9, 8), (4, 5), (2, 1), dtype=dt),
    "identity": lambda dt: Identity((2, 3, 4, 5), dtype=dt),
    "mask": lambda dt: Mask(_rng().random((3, 1, 8)), (2, 3, 4, 8), dtype=dt),
    "sum_k": lambda dt: SumK((2, 3, 4, 5), dtype=dt),
    "compose": lambda dt: Compose([
        SumK((1, 2, 6, 5), dtype=dt), Crop((1, 2, 16, 15), (6, 5), (3, 2), dtype=dt),
        Conv2D(_rng().random((6, 5)), (1, 2, 6, 5), pad_shape=(16, 15), dtype=dt),
    ]),
    "model_2d": lambda dt: build_model("2d", _psf(), dtype=dt).op,
    "model_2d_rgb": lambda dt: build_model("2d", _rng().random((3, 8, 9)), dtype=dt).op,
    "model_2d_full_field": lambda dt: build_model("2d", _psf(), field=(24, 20), dtype=dt).op,
    "model_2d_erasures": lambda dt: build_model("2d", _psf(), mask=_erasure(12, 10), dtype=dt).op,
    "model_video": lambda dt: build_model("video", _psf(), shutter=_shutter(12), dtype=dt).op,
    "model_spectral": lambda dt: build_model(
        "spectral", _psf(), filters=_rng().random((4, 12, 10)), dtype=dt).op,
    "model_depth": lambda dt: build_model("depth", _rng().random((3, 12, 10)), dtype=dt).op,
    "model_depth_erasures": lambda dt: build_model(
        "depth", _rng().random((3, 12, 10)), mask=_erasure(12, 10), dtype=dt).op,
    "model_2d_region": lambda dt: _region_model("2d", dt),
    "fourier_filter": lambda dt: _preconditioner(dt)[1],
    "fista_gram_p": lambda dt: _GramP(*_preconditioner(dt)),
    "model_video_region": lambda dt: _region_model("video", dt),
}


def _preconditioner(dt: torch.dtype) -> tuple[LinearOperator, LinearOperator]:
    """FISTA's Fourier preconditioner of an erased 2D model (recon.fista), with the model."""
    op = build_model("2d", _psf(), mask=_erasure(12, 10), dtype=dt).op
    found = fourier_preconditioner(op, 0.1)
    assert found is not None
    return op, found[0]


def _region_model(kind: str, dt: torch.dtype) -> LinearOperator:
    """The plan's model of an off-centre region of a 2x field (recon.plan.roi)."""
    from recon.plan.roi import Region, build_region_model

    region = Region(3, 13, 9, 6, 24, 20)
    shutter = _shutter(12) if kind == "video" else None
    return build_region_model(kind, _psf(), region, shutter=shutter, dtype=dt).op


def make_operator(name: str, dtype: torch.dtype = torch.float64) -> LinearOperator:
    """Build the catalogue entry ``name`` in ``dtype``."""
    return OPERATOR_FACTORIES[name](dtype)
