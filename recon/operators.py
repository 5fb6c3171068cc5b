"""Linear operators with exact adjoints, composable, in PyTorch (CPU or GPU, float32/float64).

Layout: a scene is (C, K, H, W) (C independent colour channels, K frames / bands / depth
planes), a measurement is (C, H, W). Every operator knows ``in_shape`` and ``out_shape`` and has
``apply`` and ``adjoint``; ``A @ B`` composes (apply B first). The adjoints are exact: each is
checked by a dot-product test and against autograd (tests/test_operators.py).

Convolution follows DiffuserCam: the scene (Hs, Ws) and the PSF (H, W) are zero-padded to a fast
FFT size P >= Hs + H - 1 (so the circular convolution on the padded grid is the linear one);
:class:`Crop` then cuts the sensor window. The crop offset (Hs // 2, Ws // 2) puts the image of an
on-axis point (a delta at the scene centre) exactly on the sensor: it reproduces the PSF.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Any, cast

import torch

__all__ = [
    "Compose",
    "Conv2D",
    "Crop",
    "FourierFilter",
    "Identity",
    "LinearOperator",
    "Mask",
    "StackConvSum",
    "SumK",
    "as_tensor",
    "fast_fft_size",
    "power_norm",
]

Shape = tuple[int, ...]


def _rfft2(x: torch.Tensor, s: tuple[int, int] | None = None) -> torch.Tensor:
    return cast(torch.Tensor, torch.fft.rfft2(x, s=s))


def _irfft2(x: torch.Tensor, s: tuple[int, int]) -> torch.Tensor:
    return cast(torch.Tensor, torch.fft.irfft2(x, s=s))


def _in_layout(f: torch.Tensor, like: torch.Tensor,
               cache: dict[str, tuple[torch.Tensor, torch.Tensor]], key: str) -> torch.Tensor:
    """The constant factor ``f`` in the memory layout of the spectrum ``like`` it multiplies.

    A transform along the rows (``fft(..., dim=-2)``) returns its spectrum column-major in the
    last two axes; multiplying that by a row-major factor ran 3-4x slower than by one of the
    same layout (1 thread, CPU: 27 vs 8 us at 256x129, 132 vs 31 us at 512x257). The
    column-major copy is made once and cached (checked by identity, so a replaced factor is
    copied anew); the values are the same, only the strides differ.
    """
    if (like.ndim < 2 or like.stride(-2) != 1 or like.shape[-1] == 1 or f.stride(-2) == 1
            or f.requires_grad):
        return f
    hit = cache.get(key)
    if hit is None or hit[0] is not f:
        hit = (f, f.detach().transpose(-1, -2).contiguous().transpose(-1, -2))
        cache[key] = hit
    return hit[1]


def _broadcast(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(cast(Any, torch.broadcast_shapes)(a, b))


def fast_fft_size(n: int) -> int:
    """Smallest integer >= n whose prime factors are 2, 3 and 5 (fast for pocketfft/MKL/cuFFT)."""
    if n < 1:
        raise ValueError(f"FFT size must be >= 1, got {n}")
    best = 1 << (n - 1).bit_length()  # power of two is always acceptable
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            p = p35
            while p < n:
                p *= 2
            best = min(best, p)
            p35 *= 3
        p5 *= 5
    return best


class LinearOperator:
    """Base class: a linear map from ``in_shape`` to ``out_shape``.

    Subclasses implement :meth:`apply` and :meth:`adjoint`. The operator norm is estimated by
    power iteration on A^T A and cached on the instance.
    """

    in_shape: Shape
    out_shape: Shape
    dtype: torch.dtype
    device: torch.device

    def __init__(self, in_shape: Sequence[int], out_shape: Sequence[int],
                 dtype: torch.dtype, device: torch.device | str = "cpu") -> None:
        self.in_shape = tuple(int(s) for s in in_shape)
        self.out_shape = tuple(int(s) for s in out_shape)
        self.dtype = dtype
        self.device = torch.device(device)
        self._norm: float | None = None

    # -- interface -----------------------------------------------------------------------------
    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Forward map A x."""
        raise NotImplementedError  # abstract

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """Adjoint map A^T y."""
        raise NotImplementedError  # abstract

    # -- conveniences --------------------------------------------------------------------------
    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.apply(x)

    def __matmul__(self, other: LinearOperator) -> Compose:
        return Compose([self, other])

    @property
    def T(self) -> _Adjoint:
        """The adjoint as an operator."""
        return _Adjoint(self)

    def zeros_in(self) -> torch.Tensor:
        """A zero tensor of the input shape."""
        return torch.zeros(self.in_shape, dtype=self.dtype, device=self.device)

    def check_input(self, x: torch.Tensor, what: str = "input") -> None:
        """Raise ValueError naming the operator if ``x`` has the wrong shape."""
        if tuple(x.shape) != self.in_shape:
            raise ValueError(
                f"{type(self).__name__}: {what} has shape {tuple(x.shape)}, "
                f"expected {self.in_shape}"
            )

    def norm(self, iters: int = 50, seed: int = 0, tol: float = 1e-6,
             step: Callable[[], None] | None = None) -> float:
        """Spectral norm ||A|| by power iteration on A^T A (cached per operator).

        ``step``: called before every iteration; it may raise to stop (nothing is cached).
        """
        if self._norm is None:
            self._norm = power_norm(self, iters=iters, seed=seed, tol=tol, step=step)
        return self._norm

    def lipschitz(self, step: Callable[[], None] | None = None) -> float:
        """Lipschitz constant of the gradient of 0.5||Ax - b||^2, with a 2% safety margin.

        ``step``: as :meth:`norm`'s (a cancellation point per power iteration).
        """
        return 1.02 * self.norm(step=step) ** 2

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.in_shape} -> {self.out_shape}, {self.dtype})"


class _Adjoint(LinearOperator):
    def __init__(self, op: LinearOperator) -> None:
        super().__init__(op.out_shape, op.in_shape, op.dtype, op.device)
        self.op = op

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return self.op.adjoint(x)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return self.op.apply(y)


class Compose(LinearOperator):
    """Product of operators: ``Compose([A, B, C]).apply(x) == A(B(C(x)))``."""

    ops: list[LinearOperator]

    def __init__(self, ops: Sequence[LinearOperator]) -> None:
        flat: list[LinearOperator] = []
        for op in ops:
            flat.extend(op.ops if isinstance(op, Compose) else [op])
        if not flat:
            raise ValueError("Compose needs at least one operator")
        for outer, inner in itertools.pairwise(flat):
            if outer.in_shape != inner.out_shape:
                raise ValueError(
                    f"cannot compose {outer!r} after {inner!r}: shapes {inner.out_shape} -> "
                    f"{outer.in_shape} differ"
                )
        super().__init__(flat[-1].in_shape, flat[0].out_shape, flat[0].dtype, flat[0].device)
        self.ops = flat
        # the same maps, with each Crop right after a Conv2D done in one pruned pass
        steps: list[LinearOperator] = []
        i = 0
        while i < len(flat):
            if (i + 1 < len(flat) and isinstance(flat[i], Crop)
                    and isinstance(flat[i + 1], Conv2D)):
                steps.append(_CropConv(flat[i], flat[i + 1]))  # type: ignore[arg-type]
                i += 2
            else:
                steps.append(flat[i])
                i += 1
        self._steps = steps

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        for op in reversed(self._steps):
            x = op.apply(x)
        return x

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        for op in self._steps:
            y = op.adjoint(y)
        return y

    def __repr__(self) -> str:
        return " @ ".join(repr(o) for o in self.ops)


class Identity(LinearOperator):
    """The identity on a shape."""

    def __init__(self, shape: Sequence[int], dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu") -> None:
        super().__init__(shape, shape, dtype, device)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return x

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return y


def as_tensor(a: Any, dtype: torch.dtype, device: torch.device | str = "cpu") -> torch.Tensor:
    """``a`` (tensor, array or nested list) as a tensor of ``dtype`` on ``device``."""
    if isinstance(a, torch.Tensor):
        return a.to(dtype=dtype, device=device)
    import numpy as np

    return torch.as_tensor(np.asarray(a)).to(dtype=dtype, device=device)


class Conv2D(LinearOperator):
    """Linear 2D convolution of every (c, k) slice with a PSF, on the zero-padded FFT grid.

    ``psf`` is (H, W) (one PSF for all slices), (K, H, W) (one PSF per k, a PSF stack; also
    (C, K, H, W) per channel) or (C, 1, H, W) (one PSF per colour channel). The input
    (C, K, Hs, Ws) is zero-padded to (Py, Px) = fast sizes >= (Hs + H - 1, Ws + W - 1); the output
    is the full (C, K, Py, Px) grid (follow with :class:`Crop`).
    """

    def __init__(self, psf: Any, in_shape: Sequence[int], *,
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu",
                 pad_shape: Sequence[int] | None = None) -> None:
        if len(in_shape) != 4:
            raise ValueError(f"Conv2D input must be (C, K, H, W), got {tuple(in_shape)}")
        c, k, hs, ws = (int(s) for s in in_shape)
        h = as_tensor(psf, dtype, device)
        if h.ndim == 2:
            h = h[None, None]
        elif h.ndim == 3:
            h = h[None]
        if h.ndim != 4:
            raise ValueError(f"PSF must be (H, W), (K, H, W) or (C, K, H, W), got {tuple(h.shape)}")
        if h.shape[0] not in (1, c) or h.shape[1] not in (1, k):
            raise ValueError(
                f"PSF of shape {tuple(h.shape)} does not match the scene (C={c}, K={k})"
            )
        if not torch.isfinite(h).all():
            raise ValueError("PSF contains NaN or inf values")
        if not bool((h != 0).any()):
            raise ValueError("PSF is all zeros: nothing can be reconstructed")
        self.psf_shape = (int(h.shape[-2]), int(h.shape[-1]))
        if pad_shape is None:
            pad = (fast_fft_size(hs + self.psf_shape[0] - 1),
                   fast_fft_size(ws + self.psf_shape[1] - 1))
        else:
            pad = (int(pad_shape[0]), int(pad_shape[1]))
            if pad[0] < hs + self.psf_shape[0] - 1 or pad[1] < ws + self.psf_shape[1] - 1:
                raise ValueError(f"pad_shape {pad} too small for linear convolution")
        self.pad = pad
        super().__init__((c, k, hs, ws), (c, k, *pad), dtype, device)
        self.hf = _rfft2(h, s=pad)  # (1|C, 1|K, Py, Px//2+1)
        self.hf_conj = self.hf.conj()
        self._layouts: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        # the rfft2 of the zero-padded input, pruned: the row transforms run only on the
        # input's rows (the padding rows are zero), then the column transforms on all
        py, px = self.pad
        xf = cast(torch.Tensor, torch.fft.fft(torch.fft.rfft(x, n=px, dim=-1), n=py, dim=-2))
        xf.mul_(_in_layout(self.hf, xf, self._layouts, "hf"))
        return _irfft2(xf, s=self.pad)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        yf = _rfft2(y)
        yf.mul_(_in_layout(self.hf_conj, yf, self._layouts, "hf_conj"))
        # the irfft2 pruned to the rows the crop to the input keeps: the column transforms on
        # all, the row transforms only on the kept rows
        hs, ws = self.in_shape[2], self.in_shape[3]
        t = torch.fft.ifft(yf, dim=-2)[..., :hs, :]
        out = cast(torch.Tensor, torch.fft.irfft(t, n=self.pad[1], dim=-1))
        return out[..., :ws].contiguous()


class StackConvSum(LinearOperator):
    """Per-plane convolution with a PSF stack followed by the sum over planes, in one pass.

    Equivalent to ``SumK @ Conv2D(psf_stack)`` but sums in Fourier space, so it costs K forward
    FFTs and one inverse (apply), one forward and K inverse (adjoint). Output (C, Py, Px).
    """

    def __init__(self, psf_stack: Any, in_shape: Sequence[int], *,
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> None:
        self.conv = Conv2D(psf_stack, in_shape, dtype=dtype, device=device)
        c = self.conv.in_shape[0]
        super().__init__(self.conv.in_shape, (c, *self.conv.pad), dtype, device)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        xf = _rfft2(x, s=self.conv.pad)
        xf.mul_(self.conv.hf)
        return _irfft2(xf.sum(dim=1), s=self.conv.pad)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        yf = _rfft2(y)[:, None]
        out = _irfft2(yf * self.conv.hf_conj, s=self.conv.pad)
        return out[..., : self.in_shape[2], : self.in_shape[3]]


class Crop(LinearOperator):
    """Cut an (h, w) window at ``offset`` from the last two axes; the adjoint zero-pads."""

    def __init__(self, in_shape: Sequence[int], size: Sequence[int], offset: Sequence[int], *,
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> None:
        ins = tuple(int(s) for s in in_shape)
        h, w = (int(s) for s in size)
        oy, ox = (int(s) for s in offset)
        if oy < 0 or ox < 0 or oy + h > ins[-2] or ox + w > ins[-1]:
            raise ValueError(f"crop window {h}x{w} at ({oy}, {ox}) outside {ins[-2:]}")
        super().__init__(ins, (*ins[:-2], h, w), dtype, device)
        self.sl = (slice(oy, oy + h), slice(ox, ox + w))

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return x[..., self.sl[0], self.sl[1]]

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        out = y.new_zeros(y.shape[:-2] + self.in_shape[-2:])
        out[..., self.sl[0], self.sl[1]] = y
        return out


class _CropConv(LinearOperator):
    """``Crop @ Conv2D`` in one pass (used inside :class:`Compose`): the same map, cheaper FFTs.

    Forward: the row transforms of the padded scene run only on the scene's rows, the inverse
    ones only on the rows the crop keeps. Adjoint: the window is not zero-padded into the grid;
    its transform is that of the window at the origin times the phase of the crop offset
    (folded into the conjugate transfer function once), and the inverse row transforms run only
    on the scene's rows. About 3/4 of the row-transform work of the unfused pair.
    """

    def __init__(self, crop: Crop, conv: Conv2D) -> None:
        super().__init__(conv.in_shape, crop.out_shape, conv.dtype, conv.device)
        self.crop, self.conv = crop, conv
        self._hf_conj_shift: torch.Tensor | None = None
        self._layouts: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}

    def _shifted(self) -> torch.Tensor:
        if self._hf_conj_shift is None:
            py, px = self.conv.pad
            oy, ox = self.crop.sl[0].start, self.crop.sl[1].start
            real = torch.float64
            ky = torch.arange(py, dtype=real, device=self.device)[:, None]
            kx = torch.arange(px // 2 + 1, dtype=real, device=self.device)[None, :]
            angle = -2.0 * math.pi * (ky * oy / py + kx * ox / px)
            phase = torch.polar(torch.ones_like(angle), angle).to(self.conv.hf_conj.dtype)
            self._hf_conj_shift = self.conv.hf_conj * phase
        return self._hf_conj_shift

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        py, px = self.conv.pad
        xf = cast(torch.Tensor, torch.fft.fft(torch.fft.rfft(x, n=px, dim=-1), n=py, dim=-2))
        xf.mul_(_in_layout(self.conv.hf, xf, self._layouts, "hf"))
        sy, sx = self.crop.sl
        t = torch.fft.ifft(xf, dim=-2)[..., sy, :]
        return cast(torch.Tensor, torch.fft.irfft(t, n=px, dim=-1))[..., sx]

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        py, px = self.conv.pad
        yf = cast(torch.Tensor, torch.fft.fft(torch.fft.rfft(y, n=px, dim=-1), n=py, dim=-2))
        yf.mul_(_in_layout(self._shifted(), yf, self._layouts, "hf_conj_shift"))
        hs, ws = self.conv.in_shape[2], self.conv.in_shape[3]
        t = torch.fft.ifft(yf, dim=-2)[..., :hs, :]
        # contiguous: the solvers' passes over the gradient then run 2-5% faster per step
        # than the copy costs (FISTA, 1 thread, 256^2 to 1024^2 padded)
        return cast(torch.Tensor, torch.fft.irfft(t, n=px, dim=-1))[..., :ws].contiguous()


class FourierFilter(LinearOperator):
    """A real, symmetric Fourier multiplier on a :class:`Conv2D`'s padded grid, on its input.

    As a map of the input (scene) space: ``crop(irfft2(rfft2(pad(x)) * m))``.

    With ``m`` real, non-negative and even (m(f) = m(-f), as any function of |H(f)|^2 is) the
    map is self-adjoint and positive semi-definite, definite where m > 0 (it is C F^H diag(m) F
    C^T, C the crop to the scene). FISTA uses it as a preconditioner of the gradient
    (:mod:`recon.fista`). The transforms are pruned like :class:`Conv2D`'s (row transforms only on
    the scene's rows, both ways).
    """

    def __init__(self, conv: Conv2D, mult: torch.Tensor) -> None:
        super().__init__(conv.in_shape, conv.in_shape, conv.dtype, conv.device)
        self.pad = conv.pad
        self.mult = mult.to(device=conv.device)
        self._layouts: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        py, px = self.pad
        xf = cast(torch.Tensor, torch.fft.fft(torch.fft.rfft(x, n=px, dim=-1), n=py, dim=-2))
        xf.mul_(_in_layout(self.mult, xf, self._layouts, "mult"))
        hs, ws = self.in_shape[2], self.in_shape[3]
        t = torch.fft.ifft(xf, dim=-2)[..., :hs, :]
        return cast(torch.Tensor, torch.fft.irfft(t, n=px, dim=-1))[..., :ws].contiguous()

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return self.apply(y)


class Mask(LinearOperator):
    """Pointwise multiplication by a fixed array broadcast to the shape (self-adjoint).

    Serves for erasure masks (0/1 over the sensor), the rolling-shutter function (K, H, 1) and
    spectral filter cubes (K, H, W).
    """

    def __init__(self, mask: Any, shape: Sequence[int], *,
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> None:
        m = as_tensor(mask, dtype, device)
        shp = tuple(int(s) for s in shape)
        try:
            _broadcast(tuple(m.shape), shp)
        except RuntimeError as exc:
            raise ValueError(f"mask of shape {tuple(m.shape)} does not fit data {shp}") from exc
        if _broadcast(tuple(m.shape), shp) != shp:
            raise ValueError(f"mask of shape {tuple(m.shape)} would enlarge data {shp}")
        if not torch.isfinite(m).all():
            raise ValueError("mask contains NaN or inf values")
        super().__init__(shp, shp, dtype, device)
        self.mask = m

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.mask

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return y * self.mask


class SumK(LinearOperator):
    """Sum over the k axis: (C, K, H, W) -> (C, H, W); the adjoint repeats along k."""

    def __init__(self, in_shape: Sequence[int], *, dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu") -> None:
        ins = tuple(int(s) for s in in_shape)
        if len(ins) != 4:
            raise ValueError(f"SumK input must be (C, K, H, W), got {ins}")
        super().__init__(ins, (ins[0], ins[2], ins[3]), dtype, device)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] == 1:
            # one plane: a copy (a new tensor, as the sum gives), 2-3x faster than the sum over
            # a length-1 axis of a strided input (the cropped convolution's output)
            return x.squeeze(1).clone(memory_format=torch.contiguous_format)
        return x.sum(dim=1)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return y.unsqueeze(1).expand(self.in_shape).contiguous()


def power_norm(op: LinearOperator, iters: int = 50, seed: int = 0, tol: float = 1e-6,
               step: Callable[[], None] | None = None) -> float:
    """Estimate ||A|| (largest singular value) by power iteration on A^T A.

    Stops early when the estimate changes by less than ``tol`` (relative). The result is a lower
    bound that converges from below; callers add a small margin (see ``lipschitz``). ``step``
    is called before every iteration and may raise to stop (a cancel: a large video model
    takes seconds to minutes here).
    """
    gen = torch.Generator(device="cpu").manual_seed(seed)
    x = torch.rand(op.in_shape, generator=gen, dtype=torch.float64).to(op.dtype).to(op.device)
    x /= torch.linalg.vector_norm(x)
    est = 0.0
    with torch.no_grad():
        for _ in range(iters):
            if step is not None:
                step()
            y = op.adjoint(op.apply(x))
            n = float(torch.linalg.vector_norm(y))
            if not math.isfinite(n):
                raise FloatingPointError(f"power iteration on {op!r} produced a non-finite value")
            if n == 0.0:
                return 0.0
            x = y / n
            if abs(n - est) <= tol * n:
                est = n
                break
            est = n
    return math.sqrt(est)
