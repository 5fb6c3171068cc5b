"""The stepwise UDN solver: fit the weights of G(z; W) so that A(G(z; W)) matches b.

One :meth:`UDNRunner.step` is one Adam iteration:

1. x = G(z + noise) (regularisation noise of std ``reg_noise``, drawn from the runner's own
   seeded generator), on the network's padded grid, cropped to the field, times the gain;
2. loss = mean over the *fitted* pixels of (A x - b)^2 (or of (s A x - b)^2 with the
   least-squares scale s, the scale-invariant form) + ``tv_weight`` * TV(x) / x.numel();
3. divergence check: a non-finite loss, or one above ``divergence_factor`` times the smoothed
   recent loss, restores the last good state (weights, optimiser, EMA; kept every
   ``snapshot_every`` iterations) and multiplies the learning rate by ``lr_backoff``; after
   ``max_backoffs`` restores the run stops with :class:`NumericalError`;
4. otherwise backward + Adam step; the estimate is the exponential moving average (EMA) of x;
5. early stopping without ground truth: a random ``holdout`` fraction of the measured pixels
   is left out of the loss; their prediction error, computed on the EMA estimate, is tracked
   and the estimate with the lowest error is kept as ``best``. When it has not improved by a
   relative ``min_delta`` for ``patience`` iterations (and at least ``min_iter`` were done)
   the run stops as ``stopped_early``. With fewer than
   :data:`recon.holdout.MIN_RELIABLE_HELDOUT` held-out pixels their error is too noisy to stop
   on: the run goes on to its limit (``best`` is still their choice) and its notes say so. On
   the simulation protocol at 99 % erasures (75x100, 4 held-out pixels, the defaults) the early
   stop fell at iterations 571-1110 with ``best`` at 71-610, and running on to 3000 raised the
   held-out choice from 13.81 to 14.64 dB in the mean of three scenes (docs/udn.md).

Pixels that are not measured (the erasure mask is 0) carry no information and never enter the
loss, whatever value b has there (even NaN).

Every step returns a :class:`UDNStep` progress report and is a cancellation point; nothing is
printed. :meth:`UDNRunner.state_dict` / :meth:`UDNRunner.load_state_dict` hold everything a
resumed run needs to continue bit for bit on CPU (weights, Adam state, EMA, best, held-out
mask, z, the noise generator and the global torch / numpy / python RNG states).
"""

from __future__ import annotations

import contextlib
import copy
import math
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, cast

import numpy as np
import numpy.typing as npt
import torch

from recon.holdout import MIN_RELIABLE_HELDOUT
from recon.models import ForwardModel
from recon.stepwise import NumericalError, Stepwise, StopReason
from recon.tv import TV
from recon.udn import COMPILE_MODES
from recon.udn.network import Generator, NetworkConfig

__all__ = [
    "NumericalError",
    "UDNConfig",
    "UDNResult",
    "UDNRunner",
    "UDNStep",
    "resolve_device",
]

LossKind = Literal["mse", "scale_invariant"]
Precision = Literal["float32", "bf16"]
F32 = npt.NDArray[np.float32]

#: ``format`` of :meth:`UDNRunner.state_dict`.
STATE_FORMAT = "lenslesscam.udn_state"
#: A sigmoid output at or above this counts as "at the cap" (clipped).
CLIP_LEVEL = 0.99
#: Iterations between clipping checks (the fraction itself is reported at every step).
CLIP_CHECK_EVERY = 20

#: A correction also scales the output layer (its logits) by this: pixels pinned deep in the
#: sigmoid's flat top get a gradient again and can move under the raised cap.
CLIP_LOGIT_SCALE = 0.5
#: Gain corrections allowed in one run.
CLIP_MAX_ADAPT = 30
#: A run that ends at a limit with its held-out best in this last fraction of its iterations
#: was still improving (:meth:`UDNRunner.still_improving`): at full resolution 3000 iterations
#: ended so on 11 of 12 real cases (docs/udn.md, "Full resolution on a GPU").
STILL_IMPROVING_TAIL = 0.1

#: The settings that scale the loss or its gradient, each with the value above which it is far
#: from anything a run needs (100x its default, or the range the docs give): a divergence or
#: an overflow names those above it, rather than a setting that is at its default.
OVERFLOW_LIMITS: dict[str, float] = {
    "optimizer.lr": 1.0,
    "optimizer.reg_noise": 5.0,
    "optimizer.headroom": 100.0,
    "optimizer.tv_weight": 1.0,
    "optimizer.gain": 1e3,
    "network.input_scale": 10.0,
}


@dataclass(frozen=True)
class UDNConfig:
    """Optimiser, loss, stopping and execution settings of a UDN run.

    Attributes:
        lr: Adam learning rate.
        reg_noise: std of the Gaussian noise added to z at every iteration (0: none).
        loss: ``mse`` or ``scale_invariant`` (least-squares scale of A x before comparing).
        tv_weight: weight of TV(x) / x.numel() in the loss (0: none).
        tv_isotropic, tv_weight_k: the TV variant (see :class:`recon.tv.TV`).
        ema: decay of the output's exponential moving average (0: the last output).
        gain: initial output gain; None fits it by least squares to the first output.
        headroom: factor on the least-squares gain (ignored when ``gain`` is given). The first
            output is a sigmoid near 0.5, so the plain fit lets the scene reach only about
            twice its mean level; highlights of natural scenes need more (the gain is learnable
            but moves slowly), see docs/udn-vs-fista.md.
        seed: seeds z, the weights, the held-out pixels and the noise.
        max_iter: iteration limit.
        time_limit_s: wall-time limit in seconds (None: none).
        holdout: fraction of measured pixels held out for early stopping (0: no early stop).
        patience: iterations without held-out improvement before stopping early.
        min_iter: never stop early before this many iterations.
        min_delta: relative improvement of the held-out error that counts.
        divergence_factor: a loss above this times the smoothed loss counts as divergence.
        max_backoffs: restores allowed before the run fails.
        lr_backoff: learning-rate factor applied at each restore.
        snapshot_every: iterations between in-memory "last good state" snapshots.
        precision: ``float32`` or ``bf16`` (autocast of the network; the model stays float32).
        compile: run the network through ``torch.compile`` (falls back to eager if it fails).
        compile_mode: its mode, one of :data:`COMPILE_MODES` (``reduce-overhead`` records CUDA
            graphs: one launch for the network's kernels on a GPU).
        channels_last: channels-last memory format for the network (the default: same
            numbers up to rounding, 0.83-0.89x the step time on a CPU; docs/udn.md).
        clip_adapt: watch the output for clipping at the network's cap (sigmoid output at
            or above :data:`CLIP_LEVEL`, i.e. x at ``CLIP_LEVEL x gain``) and correct it
            during the run: every :data:`CLIP_CHECK_EVERY` iterations, when more than
            ``clip_tolerance`` of the output pixels sit at the cap, the gain is multiplied by
            ``clip_gain_step`` and the output layer's logits are halved and lowered by the
            step's log (so pinned pixels get a gradient again and mid-range pixels move
            little); each correction is a note in the run's record and shows in the gain
            column of its history (``UDNStep.clip_fraction`` reports the fraction at every
            step). At most :data:`CLIP_MAX_ADAPT` times.
        clip_tolerance: fraction of output pixels allowed at the cap.
        clip_gain_step: gain factor of one correction (> 1).
        average_every: iterations between the estimates averaged into the run's *mean*
            estimate (iterate averaging: the estimate at iterations N, 2N, ...; the final
            estimate while none was taken; 0: none). Averaged half and half with automatic-tau
            FISTA-TV (``jobs combine --with-fista``) it scored 0.05-0.17 dB above the held-out
            choice's average on the real DiffuserCam pairs (docs/udn.md, "Iterate averaging").

    """

    lr: float = 0.01
    reg_noise: float = 0.05
    loss: LossKind = "mse"
    tv_weight: float = 0.0
    tv_isotropic: bool = True
    tv_weight_k: float = 0.0
    ema: float = 0.9
    gain: float | None = None
    headroom: float = 1.0
    seed: int = 0
    max_iter: int = 3000
    time_limit_s: float | None = None
    holdout: float = 0.05
    patience: int = 500
    min_iter: int = 100
    min_delta: float = 1e-3
    divergence_factor: float = 10.0
    max_backoffs: int = 5
    lr_backoff: float = 0.5
    snapshot_every: int = 100
    precision: Precision = "float32"
    compile: bool = False
    compile_mode: str = "default"
    channels_last: bool = True
    clip_adapt: bool = True
    clip_tolerance: float = 1e-3
    clip_gain_step: float = 1.5
    average_every: int = 500

    def __post_init__(self) -> None:
        def _pos(name: str, v: float, allow_zero: bool = False) -> None:
            ok = math.isfinite(v) and (v >= 0 if allow_zero else v > 0)
            if not ok:
                raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")

        _pos("lr", self.lr)
        _pos("reg_noise", self.reg_noise, True)
        _pos("tv_weight", self.tv_weight, True)
        _pos("tv_weight_k", self.tv_weight_k, True)
        _pos("min_delta", self.min_delta, True)
        if self.loss not in ("mse", "scale_invariant"):
            raise ValueError(f"loss must be 'mse' or 'scale_invariant', got {self.loss!r}")
        if self.compile_mode not in COMPILE_MODES:
            raise ValueError(f"compile_mode must be one of {', '.join(COMPILE_MODES)}, got "
                             f"{self.compile_mode!r}")
        if self.precision not in ("float32", "bf16"):
            raise ValueError(f"precision must be 'float32' or 'bf16', got {self.precision!r}")
        if not 0 <= self.ema < 1:
            raise ValueError(f"ema must be in [0, 1), got {self.ema!r}")
        if not 0 <= self.holdout < 1:
            raise ValueError(f"holdout must be in [0, 1), got {self.holdout!r}")
        if not 0 < self.lr_backoff < 1:
            raise ValueError(f"lr_backoff must be in (0, 1), got {self.lr_backoff!r}")
        if not (math.isfinite(self.divergence_factor) and self.divergence_factor > 1):
            raise ValueError(f"divergence_factor must be > 1, got {self.divergence_factor!r}")
        if self.gain is not None:
            _pos("gain", self.gain)
        _pos("headroom", self.headroom)
        if self.time_limit_s is not None:
            _pos("time_limit_s", self.time_limit_s)
        for name in ("max_iter", "patience", "min_iter", "max_backoffs", "snapshot_every",
                     "average_every"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {v!r}")
        if self.snapshot_every < 1:
            raise ValueError(f"snapshot_every must be >= 1, got {self.snapshot_every}")
        if not 0 <= self.clip_tolerance < 1:
            raise ValueError(f"clip_tolerance must be in [0, 1), got {self.clip_tolerance!r}")
        if not (math.isfinite(self.clip_gain_step) and self.clip_gain_step > 1):
            raise ValueError(f"clip_gain_step must be > 1, got {self.clip_gain_step!r}")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for metadata."""
        return asdict(self)


@dataclass(frozen=True)
class UDNStep:
    """Progress after one iteration."""

    iteration: int
    loss: float
    heldout: float | None
    best_heldout: float | None
    best_iteration: int
    lr: float
    gain: float
    elapsed_s: float
    eta_s: float | None
    restored: bool = False
    preview: F32 | None = field(default=None, repr=False, compare=False)
    #: fraction of this iteration's output pixels at the cap (see UDNConfig.clip_adapt)
    clip_fraction: float | None = None


@dataclass
class UDNResult:
    """Outcome of :meth:`UDNRunner.run`: the final (EMA) and best estimates, (C, K, H, W)."""

    final: F32
    best: F32
    best_iteration: int
    reason: StopReason
    iterations: int
    elapsed_s: float
    history: list[UDNStep]
    notes: list[str]


def describe_device(device: torch.device | str) -> str:
    """The device in words for tables and logs: ``cpu``, ``mps``, ``cuda (GPU name)``."""
    dev = torch.device(device)
    if dev.type == "cuda":
        return f"{dev} ({torch.cuda.get_device_name(dev)})"
    return str(dev)


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` picks cuda, then mps, then cpu; otherwise the named device (checked)."""
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        mps = getattr(torch.backends, "mps", None)
        if mps is not None and mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"unknown device {name!r} (use auto, cpu, cuda, cuda:N or mps)") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available on this machine")
    if dev.type == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            raise ValueError("device 'mps' requested but MPS is not available on this machine")
    if dev.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"unsupported device {name!r} (use auto, cpu, cuda or mps)")
    return dev


def _clone_to_cpu(obj: Any) -> Any:
    """Deep copy of a (nested) state with every tensor cloned to the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return {k: _clone_to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_clone_to_cpu(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_clone_to_cpu(v) for v in obj)
    return copy.deepcopy(obj)


def _at_cap_t(x: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """Fraction of ``x`` (= sigmoid x gain) at or above CLIP_LEVEL x gain, on the device.

    A 0-d tensor on ``x``'s device (no read-back).
    """
    return (x >= CLIP_LEVEL * gain.to(x.dtype)).float().mean()


def _at_cap(x: torch.Tensor, gain: torch.Tensor) -> float:
    """:func:`_at_cap_t` read back as a float."""
    return float(_at_cap_t(x, gain))


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _rng_states() -> dict[str, Any]:
    """Global RNG states as plain lists / tensors (loadable with ``weights_only=True``)."""
    np_state = cast(tuple[Any, ...], np.random.get_state(legacy=True))  # noqa: NPY002
    py_state = random.getstate()
    out: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {"name": str(np_state[0]), "keys": np.asarray(np_state[1]).tolist(),
                  "pos": int(np_state[2]), "has_gauss": int(np_state[3]),
                  "cached_gaussian": float(np_state[4])},
        "python": {"version": int(py_state[0]), "state": list(py_state[1]),
                   "gauss_next": py_state[2]},
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():  # type: ignore[no-untyped-call]
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


def _set_rng_states(s: dict[str, Any]) -> None:
    torch.set_rng_state(s["torch"])
    n = s["numpy"]
    np_state = (n["name"], np.asarray(n["keys"], dtype=np.uint32), n["pos"], n["has_gauss"],
                n["cached_gaussian"])
    np.random.set_state(np_state)  # noqa: NPY002
    p = s["python"]
    random.setstate((p["version"], tuple(p["state"]), p["gauss_next"]))
    if "cuda" in s and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(s["cuda"])


class UDNRunner(Stepwise[UDNStep]):
    """Stepwise UDN reconstruction of one measurement through a forward model.

    Use :meth:`step`, iterate :meth:`steps`, or call :meth:`run`. The device is the forward
    model's (build the model on the device you want).

    Args:
        model: the forward model (its erasure mask, if any, defines the measured pixels unless
            ``mask`` is given).
        b: the measurement (C, H, W).
        network: the network's shape.
        config: optimiser, loss, stopping and execution settings.
        mask: measured pixels (H, W) or (C, H, W), nonzero = measured (default: the model's
            mask, else every pixel).

    """

    def __init__(self, model: ForwardModel, b: Any, *, network: NetworkConfig | None = None,
                 config: UDNConfig | None = None, mask: Any = None) -> None:
        self.model = model
        self.network_config = network if network is not None else NetworkConfig()
        self.config = config if config is not None else UDNConfig()
        cfg = self.config
        self.device = model.op.device
        self.notes: list[str] = []
        meas_shape = tuple(model.meas_shape)
        bt = torch.as_tensor(np.asarray(b) if not isinstance(b, torch.Tensor) else b)
        bt = bt.to(device=self.device, dtype=torch.float32)
        if tuple(bt.shape) != meas_shape:
            raise ValueError(f"measurement has shape {tuple(bt.shape)}, the model expects "
                             f"{meas_shape}")
        m_src = mask if mask is not None else model.mask
        if m_src is None:
            measured = torch.ones(meas_shape, dtype=torch.bool, device=self.device)
        else:
            mt = torch.as_tensor(np.asarray(m_src) if not isinstance(m_src, torch.Tensor)
                                 else m_src).to(self.device)
            try:
                measured = torch.broadcast_to(mt != 0, meas_shape).clone()
            except RuntimeError as exc:
                raise ValueError(f"mask of shape {tuple(mt.shape)} does not match the "
                                 f"measurement {meas_shape}") from exc
        if not bool(torch.isfinite(bt[measured]).all()):
            raise ValueError("the measurement has NaN or inf values at measured pixels")
        n_measured = int(measured.sum())
        if n_measured == 0:
            raise ValueError("no pixel is measured (the mask is all zero)")
        self.b = torch.where(measured, bt, torch.zeros_like(bt))
        self.measured = measured
        heldout = torch.zeros(meas_shape, dtype=torch.bool)
        if cfg.holdout > 0:
            n_hold = max(1, round(cfg.holdout * n_measured))
            if n_hold >= n_measured:
                raise ValueError(f"holdout {cfg.holdout} leaves no measured pixel to fit "
                                 f"({n_measured} measured)")
            heldout = self._choose_heldout(measured.cpu(), n_hold)
        self._set_heldout(heldout)
        if self.n_heldout:
            from recon.holdout import few_heldout_note

            few = few_heldout_note(self.n_heldout, "the stopping iteration",
                                   "more than it changes over many iterations")
            if few is not None:  # kept in the run record's notes
                self.notes.append(f"{few}; the run does not stop early on them (it runs to "
                                  f"max_iter, {cfg.max_iter}, or its time limit, and keeps "
                                  f"their best iteration); raise holdout ({cfg.holdout:g}) or "
                                  "set the iteration count (max_iter) yourself")

        with torch.random.fork_rng(devices=[]):  # seeded weights; the global RNG is untouched
            torch.manual_seed(cfg.seed)
            self.G = Generator(self.network_config, model.scene_shape, seed=cfg.seed)
        self.G.to(self.device)
        if cfg.channels_last:
            fmt = (torch.channels_last_3d if self.network_config.variant == "3d"
                   else torch.channels_last)
            cast(Any, self.G.net).to(memory_format=fmt)
            self.G.z = self.G.z.contiguous(memory_format=fmt)
        self.G.train()
        self._net: Callable[[torch.Tensor], torch.Tensor] = self.G.net
        self._compiled = False
        if cfg.compile:
            try:
                self._net = torch.compile(self.G.net, mode=cfg.compile_mode)
                self._compiled = True
            except Exception as exc:  # any failure: fall back, and say so
                self.notes.append(f"torch.compile failed ({type(exc).__name__}: {exc}); "
                                  "running eagerly")
        self._noise_gen = torch.Generator(device=self.device).manual_seed(cfg.seed + 104729)
        self._autocast_enabled = cfg.precision == "bf16"
        self.tv = TV(isotropic=cfg.tv_isotropic, weight_k=cfg.tv_weight_k)

        if cfg.gain is None:
            self.G.set_gain(self._fit_gain() * cfg.headroom)
        else:
            self.G.set_gain(cfg.gain)
        self.initial_gain = self.G.gain
        self.clip_adaptations = 0
        self.last_clip_fraction: float | None = None
        self.opt = torch.optim.Adam(self.G.parameters(), lr=cfg.lr)
        self.iteration = 0
        self.elapsed_s = 0.0
        self.lr = cfg.lr
        self.ema: torch.Tensor | None = None
        self.best: torch.Tensor | None = None
        self.best_iteration = 0
        self.best_heldout: float | None = None
        self.last_heldout: float | None = None
        # sum of the estimates averaged, float64 on the CPU (MPS has no float64; one copy
        # every average_every iterations costs nothing)
        self.mean_sum: torch.Tensor | None = None
        self.mean_count = 0
        self.mean_last_iteration = 0  # the last iteration averaged
        self.loss_ref: float | None = None
        self.backoffs = 0
        self.reason: StopReason | None = None
        self._step_time: float | None = None
        self._snapshot: dict[str, Any] = self._take_snapshot()

    # -- pieces --------------------------------------------------------------------------------
    def _autocast(self) -> contextlib.AbstractContextManager[Any]:
        if not self._autocast_enabled:
            return contextlib.nullcontext()
        return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)

    def _call_net(self, z: torch.Tensor) -> torch.Tensor:
        with self._autocast():
            if not self._compiled:
                return self._net(z)
            try:
                return self._net(z)
            except Exception as exc:  # compilation happens at the first call
                self.notes.append(f"torch.compile failed at the first call "
                                  f"({type(exc).__name__}: {str(exc).splitlines()[0][:200]}); "
                                  "running eagerly")
                eager: Callable[[torch.Tensor], torch.Tensor] = self.G.net
                self._net = eager
                self._compiled = False
                return eager(z)

    def _forward(self, noise: bool) -> torch.Tensor:
        z = self.G.z
        if noise and self.config.reg_noise > 0:
            n = torch.randn(z.shape, generator=self._noise_gen, device=z.device, dtype=z.dtype)
            z = z + self.config.reg_noise * n
        return self.G.to_scene(self._call_net(z))

    def _set_heldout(self, heldout: torch.Tensor) -> None:
        """Set the held-out and fitted pixels, their counts and their float weights.

        The loss and the held-out error are masked sums over the weights: boolean indexing
        would make the host wait for the device every iteration.
        """
        self.heldout = heldout.to(self.device)
        self.fit = self.measured & ~self.heldout
        self.n_fit = int(self.fit.sum())
        self.n_heldout = int(self.heldout.sum())
        self._fit_w = self.fit.to(torch.float32)
        self._heldout_w = self.heldout.to(torch.float32)

    def _choose_heldout(self, measured: torch.Tensor, n_hold: int) -> torch.Tensor:
        """Held-out values: a seeded random subset of ``n_hold`` of the measured ones."""
        idx = torch.nonzero(measured.reshape(-1)).reshape(-1).numpy()
        pick = np.random.default_rng(self.config.seed + 7919).choice(idx, size=n_hold,
                                                                     replace=False)
        heldout = torch.zeros(measured.shape, dtype=torch.bool)
        heldout.reshape(-1)[torch.as_tensor(pick)] = True
        return heldout

    def _fit_gain(self) -> float:
        """Gain that makes the first output explain the measured pixels in the mean."""
        with torch.no_grad():
            self.G.set_gain(1.0)
            ax = self.model.apply(self._forward(noise=False))
            w = self.fit.to(ax.dtype)
            num = float((ax * self.b * w).sum())
            den = float((ax * ax * w).sum())
        if not (math.isfinite(num) and math.isfinite(den)) or den <= 0 or num <= 0:
            self.notes.append("least-squares gain fit failed (non-positive); gain set to 1")
            return 1.0
        return num / den

    def _scale(self, ax: torch.Tensor) -> torch.Tensor:
        """Least-squares scale of ``ax`` to b over the fitted pixels (scale-invariant loss)."""
        w = self.fit.to(ax.dtype)
        den = (ax * ax * w).sum().clamp_min(1e-30)
        return (ax * self.b * w).sum() / den

    def _tv_penalty(self, x: torch.Tensor) -> torch.Tensor:
        g = self.tv.diffs(x)
        if self.tv.isotropic:
            total = torch.sqrt(g[0] * g[0] + g[1] * g[1] + 1e-12).sum()
        else:
            total = g[0].abs().sum() + g[1].abs().sum()
        if len(g) > 2:
            total = total + g[2].abs().sum()
        return total / x.numel()

    def still_improving(self) -> bool:
        """Whether the held-out error was still improving when the run ended.

        True when its best is in the last :data:`STILL_IMPROVING_TAIL` of the iterations run;
        False without held-out pixels.
        """
        if self.n_heldout == 0 or self.iteration == 0:
            return False
        tail = max(1, math.ceil(STILL_IMPROVING_TAIL * self.iteration))
        return self.best_iteration > self.iteration - tail

    def clip_fraction(self) -> float:
        """Fraction of the current (noise-free) output pixels at the network's cap."""
        with torch.no_grad():
            return _at_cap(self._forward(noise=False), self.G.log_gain.detach().exp())

    def _widen_gain(self, fraction: float, it: int) -> None:
        """Correct clipping: raise the gain, compress and lower the output logits.

        gain x clip_gain_step; logits l -> ``CLIP_LOGIT_SCALE * l - log(clip_gain_step)``.
        """
        f = self.config.clip_gain_step
        old = self.G.gain
        head = self.G.net.head
        with torch.no_grad():
            self.G.log_gain.add_(math.log(f))
            head.weight.mul_(CLIP_LOGIT_SCALE)
            if head.bias is not None:
                head.bias.mul_(CLIP_LOGIT_SCALE).sub_(math.log(f))
        self.clip_adaptations += 1
        self.loss_ref = None  # the loss moves with the gain: no false divergence alarm
        self.notes.append(
            f"iteration {it}: {fraction:.2%} of the output at the network's cap (sigmoid >= "
            f"{CLIP_LEVEL:g}); gain {old:.4g} -> {self.G.gain:.4g} (x{f:g}, correction "
            f"{self.clip_adaptations} of at most {CLIP_MAX_ADAPT})")
        self._snapshot = self._take_snapshot()
        self._snapshot["iteration"] = it

    def heldout_error(self, x: torch.Tensor) -> float | None:
        """Mean squared prediction error of ``x`` on the held-out pixels (None if none)."""
        t = self.heldout_error_tensor(x)
        return None if t is None else float(t)

    def heldout_error_tensor(self, x: torch.Tensor) -> torch.Tensor | None:
        """:meth:`heldout_error` as a 0-d tensor on the device (None if none is held out).

        A masked sum, not boolean indexing, so nothing waits for the device.
        """
        if self.n_heldout == 0:
            return None
        with torch.no_grad():
            r = self.model.apply(x) - self.b
            return (r * r * self._heldout_w).sum() / self.n_heldout

    def _take_snapshot(self) -> dict[str, Any]:
        return {
            "iteration": self.iteration,
            "G": _clone_to_cpu(self.G.state_dict()),
            "opt": _clone_to_cpu(self.opt.state_dict()),
            "ema": None if self.ema is None else _clone_to_cpu(self.ema),
            "loss_ref": self.loss_ref,
        }

    def _restore_snapshot(self, backoff: bool = True) -> None:
        """Back to the last good state; ``backoff``: and lower the learning rate."""
        s = self._snapshot
        self.G.load_state_dict(s["G"])
        self.opt.load_state_dict(_clone_to_cpu(s["opt"]))
        self.ema = None if s["ema"] is None else s["ema"].to(self.device)
        self.loss_ref = s["loss_ref"]
        if backoff:
            self.lr *= self.config.lr_backoff
        for group in self.opt.param_groups:
            group["lr"] = self.lr

    def warm_start(self, x0: Any, iters: int) -> float:
        """Fit the network's output to the image ``x0`` before the data term; its final MSE.

        Runs :meth:`warm_steps` to the end (iterate that generator instead for progress and
        cancellation).
        """
        mse = math.nan
        for step in self.warm_steps(x0, iters):
            mse = step[1]
        return mse

    def warm_steps(self, x0: Any, iters: int) -> Iterator[tuple[int, float]]:
        """Fit the network's output to ``x0`` step by step; yields (step, MSE) after each.

        ``iters`` Adam steps on mean((G(z + noise) - x0)^2) over the scene (for example x0 =
        a FISTA-TV result of the same measurement computed from the fitted pixels only, its
        tau chosen on them too, so that the held-out choice stays unbiased). The gain is raised
        first if ``x0``'s highlights (its 99.9th percentile) would sit above 0.9 of the
        network's cap. Adam's moments are kept for the data term: reset, its first steps
        (about lr in every weight) wreck the fitted network (on a real pair at 90 % erasures
        the loss jumped 2400-fold and the divergence guard gave up). The iteration count
        stays 0 and the run then proceeds as usual from the warm network; the time counts in
        ``elapsed_s`` (and so towards ``time_limit_s``), ``initial_gain`` becomes the gain the
        data term starts from, and a note records what was done. Stopping the iteration
        early (cancel) keeps what was fitted so far. A non-finite loss restores the network
        as it was before the warm start and raises :class:`NumericalError`. Only before the
        first iteration.
        """
        if self.iteration:
            raise RuntimeError("warm_start is only possible before the first iteration")
        if iters < 1:
            raise ValueError(f"warm-start iterations must be >= 1, got {iters}")
        xt = torch.as_tensor(np.asarray(x0, dtype=np.float32)).to(self.device)
        shape = tuple(self.model.scene_shape)
        if tuple(xt.shape) != shape:
            raise ValueError(f"warm-start image has shape {tuple(xt.shape)}, the scene is "
                             f"{shape}")
        if not bool(torch.isfinite(xt).all()):
            raise ValueError("the warm-start image has NaN or inf values")
        before = self._take_snapshot()
        flat = xt.flatten()
        hi = float(torch.kthvalue(flat, max(1, math.ceil(0.999 * flat.numel()))).values)
        if hi > 0.9 * self.G.gain:
            self.G.set_gain(hi / 0.9)
        done, mse = 0, math.nan
        try:
            for i in range(1, int(iters) + 1):
                start = time.perf_counter()
                self.opt.zero_grad(set_to_none=True)
                d = self._forward(noise=True) - xt
                loss = (d * d).mean()
                mse = float(loss.detach())
                if not math.isfinite(mse):
                    done = 0  # nothing kept: no note, no new snapshot
                    self.G.load_state_dict(before["G"])
                    self.opt.load_state_dict(_clone_to_cpu(before["opt"]))
                    raise NumericalError(f"UDN warm start: the loss is {mse} at step {i}; "
                                         "the network is as it was before the warm start")
                loss.backward()  # type: ignore[no-untyped-call]
                self.opt.step()
                self.elapsed_s += time.perf_counter() - start
                done = i
                yield i, mse
        finally:
            if done:
                self.initial_gain = self.G.gain
                self._snapshot = self._take_snapshot()
                self.notes.append(f"warm start: {done} of {iters} iterations fitting the "
                                  f"output to a given image (last MSE {mse:.3g}, gain "
                                  f"{self.G.gain:.4g})")

    # -- stepping ------------------------------------------------------------------------------
    def _eta(self) -> float | None:
        if self._step_time is None:
            return None
        eta = max(0, self.config.max_iter - self.iteration) * self._step_time
        if self.config.time_limit_s is not None:
            eta = min(eta, max(0.0, self.config.time_limit_s - self.elapsed_s))
        return eta

    def overflow_suspects(self) -> str:
        """What a divergence or overflow message advises, from this run's settings.

        Names the settings above :data:`OVERFLOW_LIMITS` (value and default) when there are
        any; otherwise says that none is and points at the data.
        """
        cfg, net = self.config, self.network_config
        defaults, net_defaults = UDNConfig(), NetworkConfig()
        values = {
            "optimizer.lr": (cfg.lr, f"{defaults.lr:g}"),
            "optimizer.reg_noise": (cfg.reg_noise, f"{defaults.reg_noise:g}"),
            "optimizer.headroom": (cfg.headroom, f"{defaults.headroom:g}"),
            "optimizer.tv_weight": (cfg.tv_weight, f"{defaults.tv_weight:g}"),
            "optimizer.gain": (cfg.gain, "auto"),
            "network.input_scale": (net.input_scale, f"{net_defaults.input_scale:g}"),
        }
        far = [f"{name} = {v:g} (default {d})" for name, (v, d) in values.items()
               if v is not None and v > OVERFLOW_LIMITS.get(name, math.inf)]
        if far:
            return (f"settings far above their usual range: {', '.join(far)}; lower "
                    f"{'it' if len(far) == 1 else 'them'}, or check the data for NaN/inf")
        now = ", ".join(f"{name} {v:g}" for name, (v, _) in values.items() if v is not None)
        return (f"no setting that scales the loss or its gradient is far from its usual range "
                f"({now}): check the data for NaN/inf or its scale, or try a smaller "
                "optimizer.lr")

    def _check_optimizer_state(self, it: int) -> None:
        """Raise :class:`NumericalError` when Adam's moments are no longer finite.

        A gradient beyond float32's range (a huge ``tv_weight`` or ``input_scale``, say 1e30)
        makes the second moment infinite; Adam's steps are then 0 and the network stops moving
        while the loss stays finite, so nothing else would notice: the run would end with its
        first output.
        Checked at the first iteration and at every snapshot (cheap: one pass over the state).
        """
        with torch.no_grad():
            for state in self.opt.state.values():
                for name in ("exp_avg", "exp_avg_sq"):
                    t = state.get(name)
                    if t is not None and not bool(torch.isfinite(t).all()):
                        raise NumericalError(
                            f"UDN: the gradient overflowed {t.dtype} at iteration {it} (Adam's "
                            f"{name} is not finite, so the network stopped moving); "
                            f"{self.overflow_suspects()}")

    def step(self, preview: bool = False) -> UDNStep:
        """Do one iteration and report it (``preview``: attach the estimate as numpy).

        The loss, the fraction of the output at the cap, the gain and the held-out error are
        read back from the device together, once, at the end of the iteration (each read makes
        the host wait for the device, which then idles while the next iteration is queued). So
        the divergence guard looks at the loss after the optimiser's step; when it fires, the
        restore of the last good state discards that step, its EMA update and the Adam moments
        it wrote, as if it had never been taken.

        Raises :class:`~recon.stepwise.RunFinished` once the run is done.
        """
        self._check_running()
        cfg = self.config
        start = time.perf_counter()
        it = self.iteration + 1
        self.opt.zero_grad(set_to_none=True)
        x = self._forward(noise=True)
        clip_t = _at_cap_t(x.detach(), self.G.log_gain.detach().exp())
        ax = self.model.apply(x)
        scale: torch.Tensor | None = None
        if cfg.loss == "scale_invariant":
            scale = self._scale(ax)
            ax = ax * scale
        r = ax - self.b
        loss = (r * r * self._fit_w).sum() / self.n_fit
        if cfg.tv_weight > 0:
            loss = loss + cfg.tv_weight * self._tv_penalty(x)
        loss.backward()  # type: ignore[no-untyped-call]
        self.opt.step()
        with torch.no_grad():
            xd = x.detach() if scale is None else x.detach() * scale.detach()
            if self.ema is None or cfg.ema == 0:
                self.ema = xd.clone()
            else:
                self.ema.mul_(cfg.ema).add_(xd, alpha=1.0 - cfg.ema)
        est = self.ema
        err_t = self.heldout_error_tensor(est)
        read = [loss.detach().float().reshape(()), clip_t,
                self.G.log_gain.detach().float().amax().exp()]  # the (largest) gain
        if err_t is not None:
            read.append(err_t.float().reshape(()))
        values = torch.stack(read).tolist()  # the iteration's one read-back
        loss_val, clip_frac, gain = float(values[0]), float(values[1]), float(values[2])
        err = float(values[3]) if err_t is not None else None
        self.last_clip_fraction = clip_frac
        restored = False
        if not math.isfinite(loss_val) or (
                self.loss_ref is not None and loss_val > cfg.divergence_factor * self.loss_ref):
            self.backoffs += 1
            what = ("is not finite" if not math.isfinite(loss_val) else
                    f"jumped to {loss_val:.3g} (> {cfg.divergence_factor:g} x the recent "
                    f"{self.loss_ref:.3g})")
            if self.backoffs > cfg.max_backoffs:
                self._restore_snapshot(backoff=False)  # the failed step is not kept either
                raise NumericalError(
                    f"UDN: the loss {what} at iteration {it}, after {cfg.max_backoffs} restores "
                    f"of the last good state with the learning rate lowered to {self.lr:.3g}; "
                    f"giving up ({self.overflow_suspects()})"
                )
            self.notes.append(f"iteration {it}: loss {what}; restored the state of iteration "
                              f"{self._snapshot['iteration']}, lr -> "
                              f"{self.lr * cfg.lr_backoff:.3g}")
            self._restore_snapshot()
            restored = True
            est = self.ema if self.ema is not None else x.detach()
            err = self.heldout_error(est)
            gain = self.G.gain
        else:
            if it == 1 or it % cfg.snapshot_every == 0:
                self._check_optimizer_state(it)
            self.loss_ref = loss_val if self.loss_ref is None else (
                0.9 * self.loss_ref + 0.1 * loss_val)
            if (cfg.clip_adapt and it % CLIP_CHECK_EVERY == 0
                    and clip_frac > cfg.clip_tolerance
                    and self.clip_adaptations < CLIP_MAX_ADAPT):
                self._widen_gain(clip_frac, it)
                gain = self.G.gain
        self.last_heldout = err
        if not restored:
            if err is None:  # no held-out pixels: the best estimate is the final one
                self.best = None
                self.best_iteration = it
            elif self.best_heldout is None or err < self.best_heldout * (1 - cfg.min_delta):
                self.best_heldout = err
                self.best_iteration = it
                self.best = est.clone()
            if it % cfg.snapshot_every == 0:
                self._snapshot = self._take_snapshot()
                self._snapshot["iteration"] = it
        if cfg.average_every and it % cfg.average_every == 0:
            # the estimate at that iteration, whatever its history (a restored step too)
            xe = est.detach().to("cpu", torch.float64, copy=True)
            self.mean_sum = xe if self.mean_sum is None else self.mean_sum.add_(xe)
            self.mean_count += 1
            self.mean_last_iteration = it
        self.iteration = it
        dt = time.perf_counter() - start
        self.elapsed_s += dt
        self._step_time = dt if self._step_time is None else 0.9 * self._step_time + 0.1 * dt
        if (err is not None and self.stops_early and it - self.best_iteration >= cfg.patience
                and it >= cfg.min_iter):
            self.reason = StopReason.STOPPED_EARLY
        elif it >= cfg.max_iter:
            self.reason = StopReason.MAX_ITER
        elif cfg.time_limit_s is not None and self.elapsed_s >= cfg.time_limit_s:
            self.reason = StopReason.TIME_LIMIT
        pv = None
        if preview:
            pv = est.detach().float().cpu().numpy().copy()
        return UDNStep(it, loss_val, err, self.best_heldout, self.best_iteration, self.lr,
                       gain, self.elapsed_s, self._eta(), restored, pv,
                       clip_fraction=clip_frac)

    @property
    def stops_early(self) -> bool:
        """Whether the patience rule applies: only on enough held-out pixels (module docstring)."""
        return self.n_heldout >= MIN_RELIABLE_HELDOUT

    def steps(self, preview_every: int = 0) -> Iterator[UDNStep]:
        """Generator of steps until a stop criterion; stop iterating to cancel.

        ``preview_every`` > 0 attaches the estimate to every such iteration's report.
        """
        while not self.done:
            it = self.iteration + 1
            yield self.step(preview=preview_every > 0 and it % preview_every == 0)

    def run(self, callback: Callable[[UDNStep], None] | None = None,
            cancel: Callable[[], bool] | None = None, preview_every: int = 0) -> UDNResult:
        """Run to a stop criterion (or until ``cancel()`` returns True) and return the result."""
        history = self._drive(self.steps(preview_every), callback, cancel)
        if self.reason is None:
            self.reason = StopReason.MAX_ITER
        return self.result(history)

    def result(self, history: list[UDNStep] | None = None) -> UDNResult:
        """The current final and best estimates as a :class:`UDNResult`."""
        final = self.final_estimate()
        best = self.best_estimate()
        return UDNResult(final, best, self.best_iteration,
                         self.reason if self.reason is not None else StopReason.CANCELLED,
                         self.iteration, self.elapsed_s, history or [], list(self.notes))

    def final_estimate(self) -> F32:
        """The current estimate (EMA), numpy (C, K, H, W) float32."""
        if self.ema is None:
            with torch.no_grad():
                return np.asarray(self._forward(noise=False).float().cpu().numpy(),
                                  dtype=np.float32)
        return np.array(self.ema.float().cpu().numpy(), dtype=np.float32, copy=True)

    def best_estimate(self) -> F32:
        """The estimate with the lowest held-out error so far (the final one without holdout)."""
        if self.best is None:
            return self.final_estimate()
        return np.array(self.best.float().cpu().numpy(), dtype=np.float32, copy=True)

    def mean_estimate(self) -> F32:
        """The mean of the estimates at every ``average_every``-th iteration (iterate averaging).

        The final estimate while none was taken (a run shorter than ``average_every``, or
        ``average_every`` 0); :attr:`mean_count` says how many were averaged.
        """
        if self.mean_sum is None or self.mean_count == 0:
            return self.final_estimate()
        return np.asarray((self.mean_sum / self.mean_count).float().numpy(),
                          dtype=np.float32).copy()

    # -- state ---------------------------------------------------------------------------------
    def _identity(self) -> dict[str, Any]:
        cfg = self.config.to_dict()
        for volatile in ("max_iter", "time_limit_s", "compile", "compile_mode", "patience",
                         "min_iter"):
            cfg.pop(volatile)
        return {"network": self.network_config.to_dict(), "config": cfg,
                "scene_shape": list(self.model.scene_shape),
                "meas_shape": list(self.model.meas_shape)}

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue this run exactly (tensors on the CPU)."""
        return {
            "format": STATE_FORMAT,
            "identity": self._identity(),
            "iteration": self.iteration,
            "elapsed_s": self.elapsed_s,
            "G": _clone_to_cpu(self.G.state_dict()),
            "opt": _clone_to_cpu(self.opt.state_dict()),
            "lr": self.lr,
            "ema": None if self.ema is None else _clone_to_cpu(self.ema),
            "best": None if self.best is None else _clone_to_cpu(self.best),
            "best_iteration": self.best_iteration,
            "best_heldout": self.best_heldout,
            "last_heldout": self.last_heldout,
            "mean_sum": None if self.mean_sum is None else _clone_to_cpu(self.mean_sum),
            "mean_count": self.mean_count,
            "mean_last_iteration": self.mean_last_iteration,
            "loss_ref": self.loss_ref,
            "backoffs": self.backoffs,
            "step_time": self._step_time,
            "initial_gain": self.initial_gain,
            "clip_adaptations": self.clip_adaptations,
            "heldout": self.heldout.cpu().clone(),
            "snapshot": _clone_to_cpu(self._snapshot),
            "noise_rng": self._noise_gen.get_state(),
            "rng": _rng_states(),
            "notes": list(self.notes),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state from :meth:`state_dict` (the same network, scene and loss)."""
        if state.get("format") != STATE_FORMAT:
            raise ValueError(f"not a UDN state (format {state.get('format')!r})")
        mine, theirs = _flatten(self._identity()), _flatten(state["identity"])
        for k in mine:  # checkpoints from before the clipping correction or the iterate
            # average: they apply from now
            if (k.startswith("config.clip_") or k == "config.average_every") and k not in theirs:
                theirs[k] = mine[k]
        if mine != theirs:
            diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            raise ValueError("the checkpoint was written for a different run (differs in: "
                             f"{', '.join(diff)})")
        self.G.load_state_dict(state["G"])
        self.opt.load_state_dict(state["opt"])
        self.lr = float(state["lr"])
        self.iteration = int(state["iteration"])
        self.elapsed_s = float(state["elapsed_s"])
        self.ema = None if state["ema"] is None else state["ema"].to(self.device)
        self.best = None if state["best"] is None else state["best"].to(self.device)
        self.best_iteration = int(state["best_iteration"])
        self.best_heldout = state["best_heldout"]
        self.last_heldout = state["last_heldout"]
        ms = state.get("mean_sum")
        self.mean_sum = None if ms is None else ms.to("cpu", torch.float64)
        self.mean_count = int(state.get("mean_count", 0))
        self.mean_last_iteration = int(state.get("mean_last_iteration", 0))
        self.loss_ref = state["loss_ref"]
        self.backoffs = int(state["backoffs"])
        self._step_time = state["step_time"]
        self.initial_gain = float(state["initial_gain"])
        self.clip_adaptations = int(state.get("clip_adaptations", 0))
        self._set_heldout(state["heldout"])
        self._snapshot = state["snapshot"]
        self._noise_gen.set_state(state["noise_rng"])
        _set_rng_states(state["rng"])
        self.notes = list(state["notes"]) + [n for n in self.notes if n not in state["notes"]]
        if "mean_count" not in state and self.config.average_every:
            self.notes.append(f"resumed at iteration {self.iteration} from a checkpoint "
                              "without the iterate average: the mean estimate averages the "
                              "iterations after it only")
        self.reason = None
