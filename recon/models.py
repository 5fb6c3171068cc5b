"""Forward models b = sum_k M_k . crop(h_k * v_k), built from the operators in ``operators``.

=============  ==========================================  =================================
kind           operator chain                               scene (C, K, Hs, Ws)
=============  ==========================================  =================================
``2d``         [Mask] @ SumK @ Crop @ Conv2D(h)            K = 1
``video``      [Mask] @ SumK @ Mask(M_k) @ Crop @ Conv2D(h) K = time bins, M from the shutter
``spectral``   [Mask] @ SumK @ Mask(F_k) @ Crop @ Conv2D(h) K = bands, F the filter cube
``depth``      [Mask] @ Crop @ StackConvSum(h_k)           K = depth planes, one PSF each
=============  ==========================================  =================================

The optional leading Mask is the erasure / dead-pixel mask on the sensor (1 = measured).
The sensor is the PSF's size (H, W); the scene field defaults to the sensor size and may be any
other size (``field``), for example the full padded field (2H, 2W) to explain light from outside
the sensor's view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np
import torch

from recon.memory import CHECK_THRESHOLD_BYTES, ProblemTooLarge, check_fits, estimate_solver_memory
from recon.operators import (
    Compose,
    Conv2D,
    Crop,
    LinearOperator,
    Mask,
    StackConvSum,
    SumK,
    as_tensor,
)

__all__ = ["ForwardModel", "ModelKind", "build_model"]


class ModelKind(str, Enum):
    """Which physical model a measurement follows."""

    TWO_D = "2d"
    VIDEO = "video"
    SPECTRAL = "spectral"
    DEPTH = "depth"


@dataclass
class ForwardModel:
    """A forward model: the operator plus what it means."""

    kind: ModelKind
    op: LinearOperator
    scene_shape: tuple[int, ...]
    meas_shape: tuple[int, ...]
    mask: torch.Tensor | None = None
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def k(self) -> int:
        """Number of frames / bands / planes."""
        return self.scene_shape[1]

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Forward model A x."""
        return self.op.apply(x)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """Adjoint A^T y."""
        return self.op.adjoint(y)




def _check_memory(kind: ModelKind, psf: Any, channels: int | None, mask: Any, shutter: Any,
                  filters: Any, field: Sequence[int] | None, dtype: torch.dtype,
                  device: torch.device | str) -> None:
    """Refuse a model whose FISTA reconstruction will not fit, from shapes alone."""
    shape = tuple(int(s) for s in np.shape(psf))
    if len(shape) not in (2, 3) or min(shape) < 1:
        return  # build_model reports the bad shape itself
    sensor = shape[-2:]
    k, c, psf_c, psf_k = 1, channels or 1, 1, 1
    if kind is ModelKind.DEPTH and len(shape) == 3:
        k = psf_k = shape[0]
    elif len(shape) == 3:
        c = psf_c = shape[0]
    if kind is ModelKind.VIDEO and shutter is not None and len(np.shape(shutter)) == 2:
        k = int(np.shape(shutter)[0])
    if kind is ModelKind.SPECTRAL and filters is not None and len(np.shape(filters)) == 3:
        k = int(np.shape(filters)[0])
    est = estimate_solver_memory(sensor, field=field, channels=c, k=k, psf_channels=psf_c,
                                 psf_planes=psf_k, dtype=dtype, mask=mask is not None,
                                 shutter=kind is ModelKind.VIDEO,
                                 filters=kind is ModelKind.SPECTRAL)
    if est.total_bytes <= CHECK_THRESHOLD_BYTES:
        return
    try:
        check_fits(est, device=device)
    except ProblemTooLarge as exc:
        raise ProblemTooLarge(f"{exc} (build_model(..., check_memory=False) skips this check)",
                              exc.estimate, exc.available) from None


def build_model(
    kind: ModelKind | str,
    psf: Any,
    *,
    channels: int | None = None,
    mask: Any = None,
    shutter: Any = None,
    filters: Any = None,
    field: Sequence[int] | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    check_memory: bool = True,
) -> ForwardModel:
    """Build a forward model.

    Args:
        kind: ``2d``, ``video``, ``spectral`` or ``depth``.
        psf: (H, W) or (C, H, W) per channel; for ``depth`` the stack (K, H, W).
        channels: colour channels C (default: from the PSF, else 1).
        mask: sensor mask (H, W) or (C, H, W), 1 = measured, 0 = erased.
        shutter: ``video`` only: M (K, H), the fraction of bin k each row integrates.
        filters: ``spectral`` only: filter cube (K, H, W) transmissions.
        field: scene field (Hs, Ws); default the sensor size.
        dtype: torch dtype, float32 or float64.
        device: torch device.
        check_memory: before anything is allocated, estimate the memory of a FISTA
            reconstruction with this model (:mod:`recon.memory`) and, when it is above
            ``recon.memory.CHECK_THRESHOLD_BYTES``, raise
            :class:`recon.memory.ProblemTooLarge` if it will not fit in the device's available
            memory.

    """
    kind = ModelKind(kind)
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(
            f"operators run in float32 or float64, not {dtype} (reduced precision such as "
            "bf16 is supported only for the UDN network, through autocast)"
        )
    if check_memory:
        _check_memory(kind, psf, channels, mask, shutter, filters, field, dtype, device)
    h = as_tensor(psf, dtype, device)
    if kind is ModelKind.DEPTH:
        if h.ndim != 3:
            raise ValueError(f"depth model needs a PSF stack (K, H, W), got {tuple(h.shape)}")
        k = int(h.shape[0])
        c = channels or 1
        psf_c = h
    else:
        if h.ndim == 2:
            c = channels or 1
            psf_c = h
        elif h.ndim == 3:
            c = int(h.shape[0])
            if channels not in (None, c):
                raise ValueError(f"PSF has {c} channels but channels={channels}")
            psf_c = h[:, None]  # (C, 1, H, W): one PSF per colour channel
        else:
            raise ValueError(f"PSF must be (H, W) or (C, H, W), got {tuple(h.shape)}")
        k = 1
    sensor = (int(h.shape[-2]), int(h.shape[-1]))
    if min(sensor) < 1:
        raise ValueError(f"PSF has an empty shape {tuple(h.shape)}")

    m_k: torch.Tensor | None = None
    if kind is ModelKind.VIDEO:
        if shutter is None:
            raise ValueError("video model needs a shutter function M (K, H)")
        m = as_tensor(shutter, dtype, device)
        if m.ndim != 2 or m.shape[1] != sensor[0]:
            raise ValueError(
                f"shutter function must be (K, {sensor[0]}) for a sensor of {sensor[0]} rows, "
                f"got {tuple(m.shape)}"
            )
        k = int(m.shape[0])
        m_k = m[None, :, :, None]  # (1, K, H, 1)
    elif kind is ModelKind.SPECTRAL:
        if filters is None:
            raise ValueError("spectral model needs a filter cube (K, H, W)")
        f = as_tensor(filters, dtype, device)
        if f.ndim != 3 or tuple(f.shape[1:]) != sensor:
            raise ValueError(
                f"filter cube must be (K, {sensor[0]}, {sensor[1]}), got {tuple(f.shape)}"
            )
        k = int(f.shape[0])
        m_k = f[None]
    elif shutter is not None or filters is not None:
        raise ValueError(f"{kind.value} model takes no shutter or filter cube")

    hs, ws = (int(field[0]), int(field[1])) if field is not None else sensor
    scene_shape = (c, k, hs, ws)
    op, mask_t = assemble(kind, psf_c, scene_shape, sensor, (hs // 2, ws // 2), m_k, mask,
                          dtype, device)
    info = {"sensor": sensor, "field": (hs, ws), "pad": op.ops[-1].out_shape[-2:]}
    return ForwardModel(kind, op, scene_shape, (c, *sensor), mask_t, info)


def assemble(
    kind: ModelKind,
    psf_c: torch.Tensor,
    scene_shape: tuple[int, int, int, int],
    sensor: tuple[int, int],
    offset: tuple[int, int],
    m_k: torch.Tensor | None,
    mask: Any,
    dtype: torch.dtype,
    device: torch.device | str,
) -> tuple[Compose, torch.Tensor | None]:
    """The operator chain of a model (see the table above) and its sensor mask tensor.

    ``psf_c`` is (1|C, 1|K, h, w) as Conv2D takes it; ``offset`` is where the sensor window
    starts in the padded grid; ``m_k`` the shutter / filter weights or None.
    """
    ops: list[LinearOperator]
    if kind is ModelKind.DEPTH:
        conv_sum = StackConvSum(psf_c, scene_shape, dtype=dtype, device=device)
        crop = Crop(conv_sum.out_shape, sensor, offset, dtype=dtype, device=device)
        ops = [crop, conv_sum]
    else:
        conv = Conv2D(psf_c, scene_shape, dtype=dtype, device=device)
        crop = Crop(conv.out_shape, sensor, offset, dtype=dtype, device=device)
        ops = [crop, conv]
        if m_k is not None:
            ops.insert(0, Mask(m_k, crop.out_shape, dtype=dtype, device=device))
        ops.insert(0, SumK(crop.out_shape, dtype=dtype, device=device))
    mask_t: torch.Tensor | None = None
    if mask is not None:
        mask_t = as_tensor(mask, dtype, device)
        if tuple(mask_t.shape[-2:]) != sensor:
            raise ValueError(
                f"mask of shape {tuple(mask_t.shape)} does not match the sensor {sensor}"
            )
        ops.insert(0, Mask(mask_t, (scene_shape[0], *sensor), dtype=dtype, device=device))
    return Compose(ops), mask_t
