"""The untrained network: a deep-image-prior encoder-decoder with skips, and its fixed input.

Architecture (Ulyanov et al., "Deep image prior"; Monakhova et al., untrained networks for
compressive lensless photography), per scale ``i`` of ``scales``:

- down: conv 3 stride 2 -> BN -> LeakyReLU -> conv 3 -> BN -> LeakyReLU (``channels`` out);
- skip: conv 1 -> BN -> LeakyReLU (``skip_channels`` out, none when 0), taken before the down;
- up:   upsample (bilinear / trilinear) to the skip's size -> concat with the skip -> BN ->
  conv 3 -> BN -> LeakyReLU -> conv 1 -> BN -> LeakyReLU.

A 1x1 convolution and a sigmoid give the output, multiplied by a *learnable* gain
``exp(log_gain)``: a max-1 measurement through a unit-sum PSF is explained by a scene brighter
than 1, which a bare sigmoid cannot reach. Convolutions pad by reflection.

Variants (``NetworkConfig.variant``):

- ``2d``:     one image (K = 1); the C colour channels are the output channels.
- ``frames``: 2D convolutions with the C x K frames / bands as output channels.
- ``3d``:     3D convolutions over (k, y, x); C output channels. The k axis is only halved
  while it stays >= 2 and uses kernel size 1 when K = 1.

Field sizes that are not multiples of the total downsampling are handled by building the
input ``z`` on a padded grid (each axis padded up to a multiple of ``2**n`` for its ``n``
halvings, H and W to at least 2; :func:`padded_grid`) and cropping the output to the field, so
every skip lines up exactly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any, Literal, cast

import torch
from torch import nn
from torch.nn import functional as F
from torch.utils.checkpoint import checkpoint

__all__ = [
    "VARIANTS",
    "Generator",
    "NetworkConfig",
    "SkipNet",
    "axis_halvings",
    "padded_grid",
    "parameter_count",
]

Variant = Literal["2d", "frames", "3d"]
#: Network variants, see the module docstring.
VARIANTS: tuple[str, ...] = ("2d", "frames", "3d")


@dataclass(frozen=True)
class NetworkConfig:
    """Shape of the network and its input.

    Attributes:
        variant: ``2d``, ``frames`` or ``3d`` (see the module docstring).
        scales: number of encoder/decoder levels.
        channels: feature channels at every level.
        skip_channels: channels of each skip connection (0: no skips).
        input_channels: channels of the fixed random input ``z``.
        input_scale: ``z`` is uniform noise in [0, ``input_scale``).
        leaky_slope: negative slope of the LeakyReLU.
        gradient_checkpointing: recompute each level in the backward pass instead of storing
            its activations (less memory, about one extra forward pass of time).

    """

    variant: Variant = "2d"
    scales: int = 5
    channels: int = 32
    skip_channels: int = 4
    input_channels: int = 32
    input_scale: float = 0.1
    leaky_slope: float = 0.2
    gradient_checkpointing: bool = False

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(
                f"network variant must be one of {', '.join(VARIANTS)}, got {self.variant!r}"
            )
        for name in ("scales", "channels", "input_channels"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"network {name} must be an integer >= 1, got {value!r}")
        from recon.udn import MAX_SCALES

        if self.scales > MAX_SCALES:
            raise ValueError(f"network scales must be at most {MAX_SCALES} (more than any axis "
                             f"can halve), got {self.scales!r}")
        if (not isinstance(self.skip_channels, int) or isinstance(self.skip_channels, bool)
                or self.skip_channels < 0):
            raise ValueError(f"network skip_channels must be an integer >= 0, got "
                             f"{self.skip_channels!r}")
        if not (math.isfinite(self.input_scale) and self.input_scale > 0):
            raise ValueError(f"network input_scale must be > 0, got {self.input_scale!r}")
        if not (math.isfinite(self.leaky_slope) and 0 <= self.leaky_slope < 1):
            raise ValueError(f"network leaky_slope must be in [0, 1), got {self.leaky_slope!r}")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for metadata."""
        return asdict(self)


def axis_halvings(size: int, scales: int) -> int:
    """How many of ``scales`` stride-2 levels halve an axis of ``size``.

    The coarsest level must keep at least 2 samples (a reflection-padded 3-tap convolution
    needs them), so an axis is halved at most ``floor(log2(size)) - 1`` times.
    """
    if size < 1:
        raise ValueError(f"axis size must be >= 1, got {size}")
    if size < 4:
        return 0
    return max(0, min(scales, math.floor(math.log2(size)) - 1))


def parameter_count(config: NetworkConfig, scene_shape: Sequence[int]) -> int:
    """Trainable parameters of :class:`Generator` for ``config`` and ``scene_shape`` (exact).

    Counted without building the network (tests/udn check it against the built one).
    """
    c, k = int(scene_shape[0]), int(scene_shape[1])
    if config.variant == "3d":
        k3 = 9 * (3 if k >= 2 else 1)
        out = c
    else:
        k3 = 9
        out = c * k
    ch, sk = config.channels, config.skip_channels

    def conv(cin: int, cout: int, taps: int) -> int:
        return cin * cout * taps + cout

    total = 0
    cin = config.input_channels
    for _ in range(config.scales):
        total += conv(cin, ch, k3) + 2 * ch + conv(ch, ch, k3) + 2 * ch
        if sk > 0:
            total += conv(cin, sk, 1) + 2 * sk
        total += 2 * (ch + sk) + conv(ch + sk, ch, k3) + 2 * ch + conv(ch, ch, 1) + 2 * ch
        cin = ch
    return total + conv(ch, out, 1) + 1


def _pad_to(size: int, halvings: int, least: int = 1) -> int:
    m = 1 << halvings
    return max(-(-size // m) * m, least)


def padded_grid(config: NetworkConfig, scene_shape: Sequence[int]
                ) -> tuple[tuple[int, ...], list[int]]:
    """The network's grid for a scene (C, K, H, W): padded axes and the halvings of each.

    The axes are (H, W), or (K, H, W) for the ``3d`` variant; each is padded up to a multiple
    of ``2**n`` for its ``n`` halvings, and H and W to at least 2 (a reflection-padded 3-tap
    convolution needs 2 samples: a 1-row or 1-column scene is computed on 2 and cropped).
    """
    _, k, h, w = (int(s) for s in scene_shape)
    axes = (k, h, w) if config.variant == "3d" else (h, w)
    halvings = [axis_halvings(n, config.scales) for n in axes]
    first_xy = len(axes) - 2
    padded = tuple(_pad_to(n, m, 2 if i >= first_xy else 1)
                   for i, (n, m) in enumerate(zip(axes, halvings, strict=True)))
    return padded, halvings


class _Block(nn.Sequential):
    """conv (reflection padded) -> BN -> LeakyReLU."""

    def __init__(self, dims: int, cin: int, cout: int, kernel: Sequence[int],
                 stride: Sequence[int], slope: float) -> None:
        conv_cls = nn.Conv2d if dims == 2 else nn.Conv3d
        bn_cls = nn.BatchNorm2d if dims == 2 else nn.BatchNorm3d
        pad: Any = tuple(k // 2 for k in kernel)
        size: Any = tuple(kernel)
        step: Any = tuple(stride)
        super().__init__(
            conv_cls(cin, cout, size, stride=step, padding=pad,
                     padding_mode="reflect" if any(pad) else "zeros", bias=True),
            bn_cls(cout),
            nn.LeakyReLU(slope, inplace=False),
        )


class _Level(nn.Module):
    """One encoder/decoder level: down path, skip path, up path."""

    def __init__(self, dims: int, cin: int, ch: int, skip: int, k3: Sequence[int],
                 k1: Sequence[int], stride: Sequence[int], slope: float) -> None:
        super().__init__()
        ones = [1] * dims
        self.down = nn.Sequential(
            _Block(dims, cin, ch, k3, stride, slope),
            _Block(dims, ch, ch, k3, ones, slope),
        )
        self.skip = _Block(dims, cin, skip, k1, ones, slope) if skip > 0 else None
        bn_cls = nn.BatchNorm2d if dims == 2 else nn.BatchNorm3d
        self.up = nn.Sequential(
            bn_cls(ch + skip),
            _Block(dims, ch + skip, ch, k3, ones, slope),
            _Block(dims, ch, ch, k1, ones, slope),
        )


class SkipNet(nn.Module):
    """The encoder-decoder with skip connections (input and output (1, C, [K,] H, W))."""

    def __init__(self, dims: int, in_channels: int, out_channels: int, config: NetworkConfig,
                 strides: Sequence[Sequence[int]], depth_kernel: int = 3) -> None:
        super().__init__()
        if dims not in (2, 3):
            raise ValueError(f"SkipNet works in 2 or 3 dimensions, got {dims}")
        if len(strides) != config.scales:
            raise ValueError(f"need one stride per scale ({config.scales}), got {len(strides)}")
        self.dims = dims
        self.config = config
        k3 = [3] * dims
        k1 = [1] * dims
        if dims == 3:
            k3[0] = depth_kernel
        levels = []
        cin = in_channels
        for i in range(config.scales):
            levels.append(_Level(dims, cin, config.channels, config.skip_channels, k3, k1,
                                 strides[i], config.leaky_slope))
            cin = config.channels
        self.levels = nn.ModuleList(levels)
        conv_cls = nn.Conv2d if dims == 2 else nn.Conv3d
        self.head = conv_cls(config.channels, out_channels, 1, bias=True)
        self._mode = "bilinear" if dims == 2 else "trilinear"

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Map the input to sigmoid outputs in (0, 1)."""
        use_ckpt = self.config.gradient_checkpointing and torch.is_grad_enabled()
        run = _run_checkpointed if use_ckpt else _run
        h = z
        skips: list[torch.Tensor | None] = []
        sizes: list[Sequence[int]] = []
        levels = cast(list[_Level], list(self.levels))
        for level in levels:
            sizes.append(h.shape[2:])
            skips.append(None if level.skip is None else run(level.skip, h))
            h = run(level.down, h)
        for level, skip, size in zip(reversed(levels), reversed(skips), reversed(sizes),
                                     strict=True):
            h = F.interpolate(h, size=tuple(size), mode=self._mode, align_corners=False)
            if skip is not None:
                h = torch.cat([skip, h], dim=1)
            h = run(level.up, h)
        return torch.sigmoid(self.head(h))


def _run(module: nn.Module, h: torch.Tensor) -> torch.Tensor:
    out: torch.Tensor = module(h)
    return out


def _run_checkpointed(module: nn.Module, h: torch.Tensor) -> torch.Tensor:
    """Run ``module`` (each child of a Sequential separately) under activation checkpointing."""
    parts = list(module.children()) if isinstance(module, nn.Sequential) and not isinstance(
        module, _Block) else [module]
    for part in parts:
        h = cast(torch.Tensor, checkpoint(part, h, use_reentrant=False))
    return h


class Generator(nn.Module):
    """G(z; W) for a scene shape (C, K, H, W): fixed input, network, learnable output gain.

    ``forward(noise_std, generator)`` returns the scene estimate (C, K, H, W) in float32;
    with ``noise_std > 0`` the input is perturbed by Gaussian noise drawn from ``generator``
    (the regularisation noise of deep image prior). ``z`` is a buffer, so it is saved and
    restored with the state dict.
    """

    z: torch.Tensor
    log_gain: nn.Parameter

    def __init__(self, config: NetworkConfig, scene_shape: Sequence[int], *, seed: int = 0,
                 gain: float = 1.0) -> None:
        super().__init__()
        if len(scene_shape) != 4:
            raise ValueError(f"scene shape must be (C, K, H, W), got {tuple(scene_shape)}")
        c, k, h, w = (int(s) for s in scene_shape)
        if min(c, k, h, w) < 1:
            raise ValueError(f"scene shape must be positive, got {tuple(scene_shape)}")
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"output gain must be > 0, got {gain}")
        self.config = config
        self.scene_shape = (c, k, h, w)
        if config.variant == "2d" and k != 1:
            raise ValueError(
                f"network variant '2d' reconstructs one image (K = 1) but the scene has K = {k} "
                f"frames/bands/planes: use variant 'frames' or '3d'"
            )
        if config.variant == "3d":
            dims, out_ch = 3, c
        else:
            dims, out_ch = 2, c * k
        self.padded, halvings = padded_grid(config, self.scene_shape)
        strides = [[2 if i < m else 1 for m in halvings] for i in range(config.scales)]
        depth_kernel = 3 if (dims == 3 and k >= 2) else 1
        self.net = SkipNet(dims, config.input_channels, out_ch, config, strides, depth_kernel)
        gen = torch.Generator(device="cpu").manual_seed(int(seed))
        z = torch.rand((1, config.input_channels, *self.padded), generator=gen)
        self.register_buffer("z", z * config.input_scale)
        self.log_gain = nn.Parameter(torch.tensor(math.log(gain), dtype=torch.float32))

    @property
    def gain(self) -> float:
        """Current output gain."""
        return float(self.log_gain.detach().exp())

    def set_gain(self, gain: float) -> None:
        """Set the output gain (for example from a least-squares fit of the first output)."""
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"output gain must be > 0, got {gain}")
        with torch.no_grad():
            self.log_gain.fill_(math.log(gain))

    def raw(self, noise_std: float = 0.0,
            generator: torch.Generator | None = None) -> torch.Tensor:
        """The network's sigmoid output on the padded grid, before gain and reshaping."""
        z = self.z
        if noise_std > 0:
            noise = torch.randn(z.shape, generator=generator, device=z.device, dtype=z.dtype)
            z = z + noise_std * noise
        out: torch.Tensor = self.net(z)
        return out

    def to_scene(self, raw: torch.Tensor) -> torch.Tensor:
        """Crop the padded output to the field, reshape to (C, K, H, W) and apply the gain."""
        c, k, h, w = self.scene_shape
        x = raw.float()
        if self.config.variant == "3d":
            x = x[0, :, :k, :h, :w]
        else:
            x = x[0, :, :h, :w].reshape(c, k, h, w)
        return x * self.log_gain.exp()

    def forward(self, noise_std: float = 0.0,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """Scene estimate (C, K, H, W), float32."""
        return self.to_scene(self.raw(noise_std, generator))

    def parameter_count(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)
