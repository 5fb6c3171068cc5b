"""Forward models on a region of the scene field (a crop of the field, anywhere in it).

:func:`recon.models.build_model` centres its scene field on the sensor axis: the crop that cuts
the sensor window out of the padded convolution starts at ``(Hs // 2, Ws // 2)``, so a scene
point at field pixel ``(Hs // 2, Ws // 2)`` images to the PSF itself. A region ``(top, left,
h, w)`` of that field is reconstructed by a model whose own field is ``h x w`` and whose crop
starts at ``(Hs // 2 - top, Ws // 2 - left)``. That offset is negative for a region below or
right of the field centre; then the PSF gets as many leading zero rows (columns) and the crop
starts at 0, which is the same linear map (the convolution output is shifted by the padding).
Trailing zero rows (columns) make the convolution grid reach past the crop's end where needed.

The result is exactly the full-field model applied to a scene that is zero outside the region
(tests/plan/test_roi.py checks it, and the adjoints by dot-product tests). With ``downsample``
the model works on a coarser grid with the exact coarse kernel of :mod:`recon.plan.coarse`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from recon.models import ForwardModel, ModelKind, assemble, build_model
from recon.operators import as_tensor
from recon.plan.coarse import coarse_psf
from recon.preprocess import downsample_rows

__all__ = ["Region", "build_region_model", "embed_region"]


@dataclass(frozen=True)
class Region:
    """A rectangle ``(top, left, height, width)`` of a scene field ``(field_h, field_w)``."""

    top: int
    left: int
    height: int
    width: int
    field_h: int
    field_w: int

    def __post_init__(self) -> None:
        vals = (self.top, self.left, self.height, self.width, self.field_h, self.field_w)
        if any(int(v) != v for v in vals):
            raise ValueError(f"region values must be integers, got {vals}")
        if self.height < 1 or self.width < 1 or self.field_h < 1 or self.field_w < 1:
            raise ValueError(f"region {vals} has an empty size")
        if (self.top < 0 or self.left < 0 or self.top + self.height > self.field_h
                or self.left + self.width > self.field_w):
            raise ValueError(
                f"region {self.height}x{self.width} at ({self.top}, {self.left}) lies outside "
                f"the field {self.field_h}x{self.field_w}"
            )

    @classmethod
    def whole(cls, field: Sequence[int]) -> Region:
        """The whole field."""
        return cls(0, 0, int(field[0]), int(field[1]), int(field[0]), int(field[1]))

    @property
    def is_whole(self) -> bool:
        """True if the region is the whole field."""
        return (self.top, self.left, self.height, self.width) == (0, 0, self.field_h,
                                                                  self.field_w)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return (self.height, self.width)

    @property
    def area_fraction(self) -> float:
        """Area of the region over the area of the field."""
        return self.height * self.width / (self.field_h * self.field_w)

    def scaled(self, factor: int) -> Region:
        """The region on a grid ``factor`` times coarser (outward to whole coarse pixels).

        The field becomes ``field // factor`` (the box downsampling of the sensor drops a
        remainder the same way) and the region is clipped to it.
        """
        if factor == 1:
            return self
        fh, fw = self.field_h // factor, self.field_w // factor
        top, left = self.top // factor, self.left // factor
        bottom = min(fh, -(-(self.top + self.height) // factor))
        right = min(fw, -(-(self.left + self.width) // factor))
        top, left = min(top, fh - 1), min(left, fw - 1)
        return Region(top, left, max(1, bottom - top), max(1, right - left), fh, fw)

    def to_list(self) -> list[int]:
        """``[top, left, height, width]``."""
        return [self.top, self.left, self.height, self.width]




def build_region_model(
    kind: ModelKind | str,
    psf: Any,
    region: Region,
    *,
    downsample: int = 1,
    mask: Any = None,
    shutter: Any = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> ForwardModel:
    """Forward model whose scene is ``region`` of the (centred) field ``region.field_*``.

    Args:
        kind: ``2d``, ``video`` or ``depth``.
        psf: (H, W) or (C, H, W) at full resolution; for ``depth`` the stack (K, H, W).
        region: the part of the field to reconstruct, in full-resolution pixels.
        downsample: reconstruct on a grid this many times coarser: the measurement is then
            the box-downsampled one (H // d, W // d), the region is
            ``region.scaled(d)`` and the kernel is the exact coarse kernel of
            :func:`recon.plan.coarse.coarse_psf`.
        mask: sensor mask on the model's sensor grid ((H // d, W // d)), 1 = measured.
        shutter: ``video`` only: M (K, H) at full resolution (rows are averaged by d).
        dtype: float32 or float64.
        device: torch device.

    With ``downsample=1`` and the whole field this is :func:`recon.models.build_model`.

    """
    kind = ModelKind(kind)
    if kind is ModelKind.SPECTRAL:
        raise ValueError("region models cover 2d, video and depth, not spectral")
    d = int(downsample)
    if d < 1:
        raise ValueError(f"downsample must be an integer >= 1, got {downsample!r}")
    h_full = np.asarray(psf) if not isinstance(psf, torch.Tensor) else psf.cpu().numpy()
    sensor_full = (int(h_full.shape[-2]), int(h_full.shape[-1]))
    if shutter is not None and d > 1:
        m_full = np.asarray(shutter, dtype=np.float64)
        if m_full.ndim != 2 or m_full.shape[1] != sensor_full[0]:
            raise ValueError(f"shutter function must be (K, {sensor_full[0]}), "
                             f"got {m_full.shape}")
        shutter = downsample_rows(m_full, d)
    if d == 1 and region.is_whole:
        return build_model(kind, psf, mask=mask, shutter=shutter,
                           field=(region.field_h, region.field_w), dtype=dtype, device=device)
    origin = (0, 0)
    if d > 1:
        kernel, origin = coarse_psf(h_full, d, (region.field_h, region.field_w))
        h = as_tensor(kernel, dtype, device)
        region = region.scaled(d)
        sensor = (sensor_full[0] // d, sensor_full[1] // d)
    else:
        h = as_tensor(psf, dtype, device)
        sensor = sensor_full
    if kind is ModelKind.DEPTH:
        if h.ndim != 3:
            raise ValueError(f"depth model needs a PSF stack (K, H, W), got {tuple(h.shape)}")
        c, k = 1, int(h.shape[0])
        psf_c = h
    elif h.ndim == 2:
        c, k = 1, 1
        psf_c = h
    elif h.ndim == 3:
        c, k = int(h.shape[0]), 1
        psf_c = h[:, None]
    else:
        raise ValueError(f"PSF must be (H, W) or (C, H, W), got {tuple(h.shape)}")
    m_k: torch.Tensor | None = None
    if kind is ModelKind.VIDEO:
        if shutter is None:
            raise ValueError("video model needs a shutter function M (K, H)")
        m = as_tensor(shutter, dtype, device)
        if m.ndim != 2 or m.shape[1] != sensor[0]:
            raise ValueError(f"shutter function must be (K, {sensor[0]}), got {tuple(m.shape)}")
        k = int(m.shape[0])
        m_k = m[None, :, :, None]
    elif shutter is not None:
        raise ValueError(f"{kind.value} model takes no shutter function")

    # crop offset of the full field, moved by the region's corner and the kernel's origin
    oy = region.field_h // 2 - region.top + origin[0]
    ox = region.field_w // 2 - region.left + origin[1]
    pad_y, pad_x = max(0, -oy), max(0, -ox)
    if pad_y or pad_x:
        psf_c = torch.nn.functional.pad(psf_c, (pad_x, 0, pad_y, 0))
        oy, ox = oy + pad_y, ox + pad_x
    # zero rows (columns) after the PSF so the convolution grid reaches past the crop's end
    hp, wp = int(psf_c.shape[-2]), int(psf_c.shape[-1])
    more_y = max(0, oy + sensor[0] + 1 - region.height - hp)
    more_x = max(0, ox + sensor[1] + 1 - region.width - wp)
    if more_y or more_x:
        psf_c = torch.nn.functional.pad(psf_c, (0, more_x, 0, more_y))
    scene_shape = (c, k, region.height, region.width)
    op, mask_t = assemble(kind, psf_c, scene_shape, sensor, (oy, ox), m_k, mask, dtype, device)
    info = {"sensor": sensor, "field": (region.field_h, region.field_w),
            "region": region.to_list(), "pad": op.ops[-1].out_shape[-2:], "downsample": d}
    return ForwardModel(kind, op, scene_shape, (c, *sensor), mask_t, info)


def embed_region(x: np.ndarray, region: Region) -> np.ndarray:
    """Place a region's reconstruction (..., h, w) into a zero field (..., Hs, Ws)."""
    a = np.asarray(x)
    if a.shape[-2:] != region.shape:
        raise ValueError(f"array of shape {a.shape} does not fit the region {region.shape}")
    out = np.zeros((*a.shape[:-2], region.field_h, region.field_w), dtype=a.dtype)
    out[..., region.top:region.top + region.height,
        region.left:region.left + region.width] = a
    return out
