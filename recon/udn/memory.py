"""Memory estimate of a UDN run before it starts, and a clear refusal when it will not fit.

The estimate walks the network's levels at the configured sizes and counts what one training
step keeps alive:

- parameters, their gradients and Adam's two moments (4 x parameters, float32), plus the
  in-memory "last good state" copy used for divergence recovery (3 x parameters);
- activations saved for the backward pass, per level: every conv -> BN -> LeakyReLU block
  keeps about three tensors of its output size (conv output, BN output, activation), the up
  path's BN over the concatenation keeps two of the concatenated size; with gradient checkpointing
  (one segment per block) only the segments' inputs stay, plus one block recomputed at a time
  (for this network that saves about 40%: the full-resolution level dominates);
- the forward model's FFT buffers and the estimate's copies (EMA, best), which are small.

Activations are counted at 4 bytes (float32) or 2 bytes (bf16 autocast); a 1.25 margin covers
the transient gradient buffers of the backward pass. The check compares the peak to expect, the
estimate times the factor measured on the device type (:data:`PEAK_FACTOR`), with the memory
available. ``tests/udn/test_memory.py`` checks the
activation count against the tensors autograd actually saves.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from recon.udn.network import NetworkConfig, padded_grid, parameter_count

__all__ = [
    "MemoryEstimate",
    "MemoryRefusal",
    "available_memory",
    "check_memory",
    "estimate_udn_memory",
    "format_bytes",
    "parse_bytes",
]

_MARGIN = 1.25

#: The measured peak over :func:`estimate_udn_memory`'s total, by device type: on a GPU the CUDA
#: caching allocator's max allocated was 1.15-1.3x the estimate (one H200, the default network
#: on a 3 x 270 x 480 colour scene, docs/udn.md "Memory"); on a CPU the process's resident peak
#: 1.2-2x (oneDNN's reordered copies of activations, the allocator's freed blocks). The check
#: compares the estimate times this factor with the memory available, so a run that passes it
#: does not fail later with the device's own out-of-memory error.
PEAK_FACTOR = {"cuda": 1.3, "cpu": 2.0}
_OTHER_PEAK_FACTOR = 1.3  # mps and the rest: not measured; the GPU's


class MemoryRefusal(ValueError):
    """A run would not fit in the memory available; the message says what to change."""


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a run needs, and where they go."""

    parameters: int
    parameter_bytes: int
    activation_bytes: int
    model_bytes: int
    total_bytes: int
    per_scale_bytes: tuple[int, ...]
    precision: str
    gradient_checkpointing: bool
    notes: list[str] = field(default_factory=list)
    device_type: str = "cpu"

    @property
    def peak_factor(self) -> float:
        """:data:`PEAK_FACTOR` of this estimate's device type."""
        return PEAK_FACTOR.get(self.device_type, _OTHER_PEAK_FACTOR)

    @property
    def peak_bytes(self) -> int:
        """The peak to expect on the device: ``total_bytes`` x :attr:`peak_factor`."""
        return int(self.total_bytes * self.peak_factor)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for the run record."""
        return {
            "parameters": self.parameters,
            "parameter_bytes": self.parameter_bytes,
            "activation_bytes": self.activation_bytes,
            "model_bytes": self.model_bytes,
            "total_bytes": self.total_bytes,
            "per_scale_bytes": list(self.per_scale_bytes),
            "precision": self.precision,
            "gradient_checkpointing": self.gradient_checkpointing,
            "notes": list(self.notes),
            "device_type": self.device_type,
            "peak_factor": self.peak_factor,
            "peak_bytes": self.peak_bytes,
        }


def format_bytes(n: float) -> str:
    """Human-readable bytes: ``1.5 GiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError("unreachable")  # pragma: no cover


def parse_bytes(text: str | int | float) -> int:
    """Parse ``'2GB'``, ``'512MiB'``, ``'1e9'`` or a number of bytes."""
    if isinstance(text, int | float) and not isinstance(text, bool):
        value = float(text)
    else:
        s = str(text).strip().upper().replace(" ", "")
        units = {"TIB": 1024**4, "GIB": 1024**3, "MIB": 1024**2, "KIB": 1024, "TB": 1e12,
                 "GB": 1e9, "MB": 1e6, "KB": 1e3, "T": 1024**4, "G": 1024**3, "M": 1024**2,
                 "K": 1024, "B": 1}
        mult = 1.0
        for suffix, m in units.items():
            if s.endswith(suffix):
                s, mult = s[: -len(suffix)], float(m)
                break
        try:
            value = float(s) * mult
        except ValueError:
            raise ValueError(f"cannot read a memory size from {text!r} (try '2GB' or "
                             f"'512MiB')") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"memory size must be > 0, got {text!r}")
    return int(value)


def _level_sizes(config: NetworkConfig, scene_shape: Sequence[int]) -> tuple[list[int], int, int]:
    """Spatial sizes (elements per channel) at each level's input and after the last level."""
    c, k, _, _ = (int(s) for s in scene_shape)
    padded, halvings = padded_grid(config, scene_shape)
    sizes = []
    for i in range(config.scales + 1):
        dims = [p // (1 << min(i, m)) for p, m in zip(padded, halvings, strict=True)]
        sizes.append(math.prod(dims))
    out_ch = c if config.variant == "3d" else c * k
    return sizes, out_ch, sizes[0]


def estimate_udn_memory(config: NetworkConfig, scene_shape: Sequence[int],
                        meas_shape: Sequence[int] | None = None, *, precision: str = "float32",
                        batch: int = 1, device: torch.device | str = "cpu") -> MemoryEstimate:
    """Estimate the bytes one training step of ``config`` on ``scene_shape`` needs.

    Args:
        config: the network.
        scene_shape: (C, K, H, W) of the reconstruction.
        meas_shape: (C, H, W) of the measurement (for the forward model's buffers; default the
            scene's field).
        precision: ``float32`` or ``bf16`` (autocast).
        batch: number of inputs per step (1 for UDN; kept for what-if estimates).
        device: where the run will be (its type sets :attr:`MemoryEstimate.peak_bytes`).

    """
    if precision not in ("float32", "bf16"):
        raise ValueError(f"precision must be float32 or bf16, got {precision!r}")
    c, k, h, w = (int(s) for s in scene_shape)
    params = parameter_count(config, scene_shape)
    sizes, out_ch, s0 = _level_sizes(config, scene_shape)
    act = 2 if precision == "bf16" else 4
    ch, skip = config.channels, config.skip_channels
    per_level_el: list[int] = []
    boundary_el: list[int] = []
    segment_el: list[int] = []
    for i in range(config.scales):
        s_in, s_out = sizes[i], sizes[i + 1]
        down = 2 * 3 * ch * s_out
        skip_el = 3 * skip * s_in
        up = 2 * (ch + skip) * s_in + 3 * ch * s_in + 3 * ch * s_in
        per_level_el.append(down + skip_el + up)
        # with checkpointing (one segment per block): the segments' inputs stay alive
        boundary_el.append(2 * ch * s_out + 2 * (ch + skip) * s_in + 2 * ch * s_in)
        segment_el.append(max(3 * ch * s_out, 3 * skip * s_in, 3 * ch * s_in))
    head_el = config.input_channels * s0 + 2 * out_ch * s0
    if config.gradient_checkpointing:
        act_el = sum(boundary_el) + max(segment_el) + head_el
    else:
        act_el = sum(per_level_el) + head_el
    per_scale = tuple(int(e * act * batch) for e in per_level_el)
    activation_bytes = int(act_el * act * batch * _MARGIN)
    parameter_bytes = int(params * 4 * 7)  # weights, grads, 2 Adam moments, 3 for the snapshot
    mh, mw = (int(meas_shape[-2]), int(meas_shape[-1])) if meas_shape is not None else (h, w)
    py, px = h + mh, w + mw
    # FFT buffers (complex, a few copies) + EMA, best and the current estimate (float32)
    model_bytes = int(c * k * py * (px // 2 + 1) * 8 * 4 + 4 * c * k * h * w * 4)
    total = activation_bytes + parameter_bytes + model_bytes
    notes = [f"{config.scales} scales x {config.channels} channels, variant {config.variant}, "
             f"scene {c}x{k}x{h}x{w}"]
    return MemoryEstimate(params, parameter_bytes, activation_bytes, model_bytes, total,
                          per_scale, precision, config.gradient_checkpointing, notes,
                          torch.device(device).type)


def available_memory(device: torch.device | str) -> tuple[int | None, str]:
    """Bytes the device can still give, and where that number comes from (None if unknown)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        free, _total = torch.cuda.mem_get_info(dev)
        return int(free), "torch.cuda.mem_get_info (free)"
    if dev.type == "mps":
        try:
            limit = int(torch.mps.recommended_max_memory())
            used = int(torch.mps.driver_allocated_memory())
            return max(0, limit - used), "torch.mps recommended_max_memory - driver allocated"
        except (AttributeError, RuntimeError):
            return None, "unknown (mps)"
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "/proc/meminfo MemAvailable"
    except OSError:
        pass
    try:
        pages = os.sysconf("SC_AVPHYS_PAGES")
        size = os.sysconf("SC_PAGE_SIZE")
        return int(pages * size), "sysconf available pages"
    except (ValueError, OSError, AttributeError):
        return None, "unknown"


def check_memory(estimate: MemoryEstimate, config: NetworkConfig, scene_shape: Sequence[int],
                 device: torch.device | str, max_memory: int | None = None,
                 meas_shape: Sequence[int] | None = None) -> dict[str, Any]:
    """Raise :class:`MemoryRefusal` if the peak to expect exceeds what the device has.

    The limit is ``device``'s free memory, or ``max_memory`` when that is lower. The peak is
    ``estimate``'s :attr:`~MemoryEstimate.peak_bytes` on ``device``'s type (the estimate
    times :data:`PEAK_FACTOR`). Returns a dict for the run record (estimate with its peak,
    available, source).
    """
    dev_type = torch.device(device).type
    if estimate.device_type != dev_type:
        estimate = dataclasses.replace(estimate, device_type=dev_type)
    avail, source = available_memory(device)
    limit = avail
    if max_memory is not None:
        limit = max_memory if avail is None else min(avail, max_memory)
        source = f"max_memory limit {format_bytes(max_memory)}" if (
            avail is None or max_memory <= avail) else source
    info = {"estimate": estimate.to_dict(), "available_bytes": avail, "limit_bytes": limit,
            "limit_source": source}
    if limit is None or estimate.peak_bytes <= limit:
        return info
    hints = []
    dev = estimate.device_type
    if not config.gradient_checkpointing:
        with_ckpt = estimate_udn_memory(
            NetworkConfig(**{**config.to_dict(), "gradient_checkpointing": True}),
            scene_shape, meas_shape, precision=estimate.precision, device=dev)
        hints.append(f"enable gradient checkpointing (network.gradient_checkpointing = true: "
                     f"about {format_bytes(with_ckpt.peak_bytes)})")
    half = NetworkConfig(**{**config.to_dict(), "channels": max(1, config.channels // 2)})
    half_est = estimate_udn_memory(half, scene_shape, meas_shape, precision=estimate.precision,
                                   device=dev)
    hints.append(f"use fewer channels (network.channels = {half.channels}: about "
                 f"{format_bytes(half_est.peak_bytes)})")
    h, w = int(scene_shape[-2]), int(scene_shape[-1])
    if h >= 4 and w >= 4:
        hints.append("downsample the data (data.downsample twice as large: about a quarter of "
                     "the activations)")
    if estimate.precision == "float32":
        hints.append("use device.precision = 'bf16' on a GPU (halves the activations)")
    raise MemoryRefusal(
        f"this UDN run needs about {format_bytes(estimate.peak_bytes)} at its peak on "
        f"{dev} (the estimate, {format_bytes(estimate.total_bytes)}, x "
        f"{estimate.peak_factor:g} measured there; activations "
        f"{format_bytes(estimate.activation_bytes)}, parameters and optimiser "
        f"{format_bytes(estimate.parameter_bytes)}, forward model "
        f"{format_bytes(estimate.model_bytes)}; {estimate.notes[0]}) but only "
        f"{format_bytes(limit)} is available ({source}). To make it fit: " + "; ".join(hints)
    )
