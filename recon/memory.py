"""Memory estimate of a FISTA or ADMM reconstruction, from shapes alone, and a clear refusal.

The estimate counts what one iteration keeps alive, in elements of the solver's real dtype
(4 bytes for float32, 8 for float64; a complex element counts twice):

- the forward model: the PSF transfer function(s) on the padded grid (complex, Py x (Px/2+1)
  per PSF), the erasure mask, the shutter or filter cube;
- the padded FFT buffers of one forward/adjoint pair: the zero-padded input and the output on
  the full grid (Py x Px per slice), the complex spectra (two), and the adjoint's output, which
  stays alive as the gradient (a view of the full grid);
- FISTA: the measurement-sized vectors (b, Ax, Ay, A x_new, ...), the iterates (x, y, the
  gradient step z, the prox output, the difference and the next y) and the TV prox's work
  buffers (the dual p, its extrapolation r and the dual gradient g, one per difference
  direction, plus three scene-sized buffers); the Fourier preconditioner of its first phase
  (a real multiplier per PSF slice in two memory layouts, one more spectrum and the
  preconditioned gradient);
- ADMM: eight grid-sized variables (v, M v, the data term's diagonal and right-hand side, the
  three dual variables, one per split) and about sixteen grid-sized transients of one step
  (the differences, the split variables, the shrinkage's temporaries, the next v and M v).

A 1.25 margin covers the allocator's slack and short-lived temporaries; a fixed
``FIXED_OVERHEAD_BYTES`` (8 MiB) covers what does not grow with the problem (torch's FFT plan
cache, allocator arenas): measured peaks of FISTA-TV runs as the CLI runs them (objective and
residual every step) were 0.8-0.95 x the estimate at 320 x 480 and 2048 x 2048 and up to 1.1 x
it (0.6 MB over) at 128 x 192, so the estimate plus this overhead bounds every measured peak
(``tests/test_cli_faults.py::test_memory_estimate_bounds_the_measured_peak``). ``check_fits``
compares the estimate with the memory available (``/proc/meminfo`` MemAvailable, else
``sysconf``; the free memory of a CUDA device) and raises :class:`ProblemTooLarge` naming the
size and what to change. ``tests/stability/test_memory.py`` checks the estimate against the
measured peak resident memory of real runs.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch

from recon.operators import fast_fft_size

__all__ = [
    "CHECK_THRESHOLD_BYTES",
    "FIXED_OVERHEAD_BYTES",
    "MARGIN",
    "MEMINFO_PATH",
    "ProblemTooLarge",
    "SolverMemoryEstimate",
    "available_memory",
    "check_fits",
    "estimate_model_memory",
    "estimate_solver_memory",
    "format_bytes",
]

#: Factor on the counted bytes for allocator slack and short-lived temporaries.
MARGIN = 1.25
#: Memory a solve needs whatever its size (FFT plan cache, allocator arenas); added by
#: ``check_fits``, not part of ``total_bytes`` (which stays proportional to the problem).
FIXED_OVERHEAD_BYTES = 8 * 2**20
#: ``build_model`` checks problems whose estimate is above this (smaller ones always fit).
CHECK_THRESHOLD_BYTES = 256 * 2**20

#: Where the available memory is read (Linux); elsewhere ``sysconf`` is used.
MEMINFO_PATH = "/proc/meminfo"

_METHODS = ("fista", "admm")
_DTYPES = {torch.float32: 4, torch.float64: 8}


class ProblemTooLarge(MemoryError):
    """A reconstruction would not fit in the memory available; the message says what to change."""

    def __init__(self, message: str, estimate: SolverMemoryEstimate, available: int) -> None:
        super().__init__(message)
        self.estimate = estimate
        self.available = available


def format_bytes(n: float) -> str:
    """Human-readable bytes: ``1.5 GiB``."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


@dataclass(frozen=True)
class SolverMemoryEstimate:
    """Bytes a FISTA or ADMM reconstruction needs, and where they go (before the margin)."""

    method: str
    dtype: str
    scene_shape: tuple[int, int, int, int]
    meas_shape: tuple[int, int, int]
    pad: tuple[int, int]
    model_bytes: int
    fft_bytes: int
    iterate_bytes: int
    tv_bytes: int
    total_bytes: int
    inputs: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for run records."""
        return asdict(self)

    def describe(self) -> str:
        """One line: the problem and its size."""
        c, k, hs, ws = self.scene_shape
        _, h, w = self.meas_shape
        return (f"a {self.method.upper()} reconstruction of a {c}x{k}x{hs}x{ws} scene (sensor "
                f"{h}x{w}, padded FFT grid {self.pad[0]}x{self.pad[1]}, {self.dtype})")


def estimate_solver_memory(
    sensor: Sequence[int],
    *,
    field: Sequence[int] | None = None,
    channels: int = 1,
    k: int = 1,
    psf_channels: int = 1,
    psf_planes: int = 1,
    dtype: torch.dtype = torch.float32,
    method: str = "fista",
    tv_dirs: int = 2,
    mask: bool = False,
    shutter: bool = False,
    filters: bool = False,
) -> SolverMemoryEstimate:
    """Estimate the bytes of a reconstruction from its shapes (nothing is allocated).

    Args:
        sensor: (H, W) of the sensor (= the PSF).
        field: (Hs, Ws) of the scene; default the sensor.
        channels: colour channels C.
        k: frames / bands / depth planes K.
        psf_channels: 1 (one PSF) or C (one per channel).
        psf_planes: 1, or K for a depth PSF stack.
        dtype: float32 or float64.
        method: ``fista`` or ``admm``.
        tv_dirs: difference directions of the TV prior (2, or 3 with a weight along k).
        mask: an erasure mask is present.
        shutter: a video shutter function M (K, H) is present.
        filters: a spectral filter cube (K, H, W) is present.

    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {', '.join(_METHODS)}, got {method!r}")
    if dtype not in _DTYPES:
        raise ValueError(f"FISTA and ADMM run in float32 or float64, not {dtype}")
    h, w = (int(s) for s in sensor)
    hs, ws = (int(s) for s in field) if field is not None else (h, w)
    c, kk = int(channels), int(k)
    if min(h, w, hs, ws, c, kk) < 1:
        raise ValueError(f"sizes must be >= 1 (sensor {h}x{w}, field {hs}x{ws}, C={c}, K={kk})")
    if method == "admm" and kk != 1:
        raise ValueError("ADMM-TV handles the 2d model (K = 1)")
    r = _DTYPES[dtype]
    py, px = fast_fft_size(hs + h - 1), fast_fft_size(ws + w - 1)
    nf = py * (px // 2 + 1)  # complex elements of one slice's spectrum
    scene = c * kk * hs * ws
    meas = c * h * w
    grid = c * kk * py * px
    spec = 2 * c * kk * nf  # one spectrum of every slice, in real elements
    per_k = c * kk * h * w  # cropped slices before the sum over k
    model = 2 * int(psf_channels) * int(psf_planes) * nf
    model += meas if mask else 0
    model += kk * h if shutter else 0
    model += kk * h * w if filters else 0
    if method == "fista":
        # the zero-padded input and the full-grid output of a transform, the adjoint's
        # full-grid output (kept as the gradient) and one more working grid; three spectra
        # (the transform's output and the working copies of the 2D FFT's two passes); the
        # masked / expanded slices
        fft = 4 * grid + 3 * spec + 2 * per_k
        # the Fourier preconditioner (recon.fista): its real multiplier in both memory
        # layouts, one more spectrum and the preconditioned gradient
        model += 2 * int(psf_channels) * int(psf_planes) * nf
        fft += spec + scene
        iterates = 7 * scene + 6 * meas
        tv = (3 * int(tv_dirs) + 3) * scene
    else:
        g1 = c * py * px
        # h2 (real half-spectrum), psi2, support and the two TV-domain masks
        model += c * nf + nf + 3 * py * px
        fft = 5 * spec + 4 * g1
        iterates = 8 * g1 + 16 * g1 + 2 * meas + scene
        tv = 0
    counted = (model + fft + iterates + tv) * r
    inputs = {"sensor": [h, w], "field": [hs, ws], "channels": c, "k": kk,
              "psf_channels": int(psf_channels), "psf_planes": int(psf_planes),
              "tv_dirs": int(tv_dirs), "mask": mask, "shutter": shutter, "filters": filters}
    return SolverMemoryEstimate(
        method=method, dtype=str(dtype).removeprefix("torch."), scene_shape=(c, kk, hs, ws),
        meas_shape=(c, h, w), pad=(py, px), model_bytes=model * r, fft_bytes=fft * r,
        iterate_bytes=iterates * r, tv_bytes=tv * r, total_bytes=math.ceil(counted * MARGIN),
        inputs=inputs)


def estimate_model_memory(model: Any, method: str = "fista", tv_weight_k: float = 0.0
                          ) -> SolverMemoryEstimate:
    """The estimate for an existing :class:`recon.models.ForwardModel`."""
    c, k, hs, ws = model.scene_shape
    _, h, w = model.meas_shape
    kind = model.kind.value
    psf_channels = psf_planes = 1
    for op in getattr(model.op, "ops", [model.op]):
        hf = getattr(op, "hf", None) if not hasattr(op, "conv") else op.conv.hf
        if hf is not None:
            psf_channels, psf_planes = int(hf.shape[0]), int(hf.shape[1])
    return estimate_solver_memory(
        (h, w), field=(hs, ws), channels=c, k=k, psf_channels=psf_channels,
        psf_planes=psf_planes, dtype=model.op.dtype, method=method,
        tv_dirs=3 if (tv_weight_k > 0 and k > 1) else 2, mask=model.mask is not None,
        shutter=kind == "video", filters=kind == "spectral")


def available_memory(device: torch.device | str = "cpu") -> tuple[int | None, str]:
    """Bytes the device can still give, and where that number comes from (None: unknown)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        free, _total = torch.cuda.mem_get_info(dev)
        return int(free), "torch.cuda.mem_get_info (free)"
    try:
        with open(MEMINFO_PATH, encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "/proc/meminfo MemAvailable"
    except (OSError, ValueError, IndexError):
        pass
    try:
        return (int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")),
                "sysconf available pages")
    except (ValueError, OSError, AttributeError):
        return None, "unknown"


def _hints(est: SolverMemoryEstimate) -> list[str]:
    inp = dict(est.inputs)
    base = {"field": inp["field"], "channels": inp["channels"], "k": inp["k"],
            "psf_channels": inp["psf_channels"], "psf_planes": inp["psf_planes"],
            "dtype": getattr(torch, est.dtype), "method": est.method,
            "tv_dirs": inp["tv_dirs"], "mask": inp["mask"], "shutter": inp["shutter"],
            "filters": inp["filters"]}

    def total(sensor: Sequence[int], **kw: Any) -> str:
        return format_bytes(estimate_solver_memory(sensor, **{**base, **kw}).total_bytes)

    h, w = inp["sensor"]
    hs, ws = inp["field"]
    hints = []
    if min(h, w, hs, ws) >= 2:
        hints.append(f"downsample by 2 (sensor {h // 2}x{w // 2}: about "
                     f"{total((h // 2, w // 2), field=(hs // 2, ws // 2))})")
    if (hs, ws) != (h, w):
        hints.append(f"reconstruct the sensor's field only (field {h}x{w} instead of "
                     f"{hs}x{ws}: about {total((h, w), field=(h, w))})")
    if est.dtype == "float64":
        hints.append(f"use float32 (about {total((h, w), dtype=torch.float32)})")
    if est.method == "admm":
        hints.append(f"use FISTA (about {total((h, w), method='fista')})")
    if inp["k"] > 1:
        hints.append("use fewer frames / bands / planes (memory grows with K)")
    return hints


def check_fits(estimate: SolverMemoryEstimate, available: int | None = None, *,
               device: torch.device | str = "cpu") -> int | None:
    """Raise :class:`ProblemTooLarge` if ``estimate`` needs more than ``available`` bytes.

    ``available`` defaults to what ``device`` can still give (see :func:`available_memory`);
    when that is unknown nothing is refused. Returns the limit used (None: unknown).
    """
    source = "given limit"
    if available is None:
        available, source = available_memory(device)
        if available is None:
            return None
    need = estimate.total_bytes + FIXED_OVERHEAD_BYTES
    if need <= available:
        return available
    raise ProblemTooLarge(
        f"{estimate.describe()} needs about {format_bytes(need)} but only "
        f"{format_bytes(available)} is available ({source}). To make it fit: "
        + "; ".join(_hints(estimate)) + ".",
        estimate, available)

