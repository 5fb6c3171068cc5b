"""The speed/accuracy trade: run a grid of methods and budgets on one case and score each.

For every configuration (FISTA-TV and ADMM-TV over tau, UDN over network width and precision,
float32/float64, downsampling) this records, at several iteration counts taken from one run,
the wall time, the peak resident memory of the run and the quality:

- with ground truth: PSNR and SSIM after a least-squares gain fit;
- always (the normal case at the bench, where there is no truth): the *held-out proxy*. A
  random 5 % of the measured pixels is hidden from every reconstruction; the proxy is how well
  the reconstruction predicts them (held-out PSNR, in dB of the measurement's peak), beside the
  data residual on the fitted pixels. ``rank_correlation`` tells how well the proxy orders the
  configurations as true PSNR does (on simulated cases).

Peak memory is measured, not estimated: before each run the kernel's peak-RSS counter is reset
(``/proc/self/clear_refs``), and the run's peak is VmHWM minus the resident size before it.
Where that is unavailable (not Linux) the column is empty.

Everything here is stepwise: :func:`run_trade` is a generator of rows (progress and a
cancellation point between configurations); nothing prints or plots.

``trade.csv`` (:func:`write_trade_csv`; its one reader :func:`read_trade`) is a table with a
``# key: value`` header (:mod:`recon.csvmeta`): its format and version, provenance, and one
``case`` line per case (:func:`case_record`: shapes, field, PSF and measurement hashes,
erasure, where the case came from), so a plan can tell whether a trade was measured on its
kind of data (:func:`case_differences`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from recon.formats import FORMAT_VERSION, FormatError, array_hash
from recon.metrics import gain_fit, psnr, ssim
from recon.models import build_model
from recon.preprocess import box_downsample, downsample_masked

__all__ = [
    "QUALITY_LABEL",
    "TAU_MAX",
    "TRADE_FORMAT",
    "Case",
    "Config",
    "TradeFile",
    "TradeRow",
    "best_for_budgets",
    "case_differences",
    "case_record",
    "default_grid",
    "pareto_front",
    "rank_correlation",
    "read_trade",
    "read_trade_csv",
    "run_trade",
    "trade_markdown",
    "udn_settings",
    "write_trade_csv",
]

#: ``format`` of a ``trade.csv`` header (its ``format_version`` is :data:`FORMAT_VERSION`).
TRADE_FORMAT = "lenslesscam.trade"
#: the largest tau a ``trade.csv`` row may give: the TV weight on a max-1 measurement with a
#: unit-sum PSF (the grids reach 1e-2; the app's preview takes 0..1)
TAU_MAX = 1.0

F32 = npt.NDArray[np.float32]


@dataclass
class Case:
    """A measurement with its calibration, and the truth where there is one."""

    name: str
    psf: F32  # (C, H, W), unit sum
    meas: F32  # (C, H, W)
    mask: F32 | None = None  # (H, W), 1 = measured
    truth: F32 | None = None  # (C, 1, Hs, Ws)
    #: the scene field (Hs, Ws); None: the measurement's grid. A measurement embedded in a
    #: padded PSF grid (the DiffuserCam dataset layout) is reconstructed on its sensor's field,
    #: as ``recon fista`` does (``recon.problem``: the problem's ``model.info["field"]``)
    field: tuple[int, int] | None = None
    #: where the case comes from, recorded in trade.csv: the files and their hashes
    #: (``psf_file_hash``, ...), or the simulation (scene, erasure, noise, seed)
    source: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class Config:
    """One configuration of the grid; ``checkpoints`` are the iteration counts scored."""

    method: str  # fista | admm | udn
    tau: float = 0.0
    checkpoints: tuple[int, ...] = (50, 100, 200, 500)
    precision: str = "float32"  # float32 | float64 (fista/admm) | bf16 (udn)
    downsample: int = 1
    channels: int = 0  # udn width
    scales: int = 4

    @property
    def label(self) -> str:
        """Short human-readable name."""
        parts = [self.method]
        if self.method == "udn":
            parts.append(f"ch{self.channels}")
        else:
            parts.append(f"tau={self.tau:g}")
        if self.precision != "float32":
            parts.append(self.precision)
        if self.downsample > 1:
            parts.append(f"ds{self.downsample}")
        return " ".join(parts)


@dataclass
class TradeRow:
    """The score of one configuration at one iteration count."""

    case: str
    setting: str
    method: str
    tau: float
    precision: str
    downsample: int
    channels: int
    iterations: int
    wall_s: float
    peak_mem_mb: float | None
    heldout_psnr: float
    residual: float
    psnr: float | None = None
    ssim: float | None = None
    #: a UDN row's settings as run (:func:`udn_settings`): ``{"network": NetworkConfig fields,
    #: "config": UDNConfig fields}`` (the config's ``max_iter`` and ``time_limit_s`` left out:
    #: the row's ``iterations`` is the count); None for the other methods, and for a UDN row of
    #: a trade.csv written before they were recorded
    udn_settings: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Flat dict for CSV/JSON."""
        d = asdict(self)
        d.pop("extra")
        return d


def default_grid(quick: bool = False, with_udn: bool = True) -> list[Config]:
    """The grid of the issue; ``quick`` keeps a few points of each.

    FISTA-TV (tau x iterations), ADMM-TV, UDN (iterations, width, precision), float32 and
    float64, downsampling.
    """
    # the best tau spans 1e-7 .. 1e-3 over erasures and noise (docs/simulation-protocol.md)
    taus = (1e-7, 1e-5, 1e-3) if quick else (1e-7, 1e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 1e-2)
    its = (30, 100, 300) if quick else (25, 50, 100, 200, 500)
    grid = [Config("fista", t, its) for t in taus]
    grid += [Config("admm", t, its) for t in taus]
    grid.append(Config("fista", 1e-4, its, precision="float64"))
    grid += [Config("fista", t, its, downsample=2) for t in (1e-5, 1e-4)]
    if with_udn:
        udn_its = (100, 300) if quick else (100, 250, 500)
        grid.append(Config("udn", checkpoints=udn_its, channels=16))
        grid.append(Config("udn", checkpoints=udn_its, channels=32))
        grid.append(Config("udn", checkpoints=udn_its, channels=32, precision="bf16"))
    return grid


# --------------------------------------------------------------------------------------------
# Memory
# --------------------------------------------------------------------------------------------


def _status_kb(key: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


@functools.cache
def _libc() -> Any:
    """The C library (found once: find_library runs ldconfig), or None."""
    import ctypes
    import ctypes.util

    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def _reset_peak() -> int | None:
    """Return freed heap to the OS, reset the peak-RSS counter; return the RSS in kB.

    Without the trim, glibc keeps freed blocks mapped and a run that reuses them shows no
    growth. None where unsupported (not Linux/glibc).
    """
    import gc
    import threading

    # Collect only on the main thread: from a worker, a collection may finalise GUI objects
    # (Qt) away from their thread and deadlock (seen with the app's trade panel).
    if threading.current_thread() is threading.main_thread():
        gc.collect()
    libc = _libc()
    if libc is None or not hasattr(libc, "malloc_trim"):
        return None
    libc.malloc_trim(0)
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        return None
    return _status_kb("VmRSS")


def _peak_mb(base_kb: int | None) -> float | None:
    hwm = _status_kb("VmHWM")
    if base_kb is None or hwm is None:
        return None
    return round(max(hwm - base_kb, 0) / 1024.0, 1)


def peak_start(device: Any = "cpu") -> tuple[Any, ...]:
    """Start a peak-memory measurement of the work that follows on ``device``.

    The process's resident memory on a CPU (:func:`_reset_peak`), the allocated memory on a
    CUDA GPU (``torch.cuda.max_memory_allocated``). Read it with :func:`peak_mb_since`.
    """
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
        torch.cuda.reset_peak_memory_stats(dev)
        return ("cuda", dev, torch.cuda.memory_allocated(dev))
    return ("rss", dev, _reset_peak())


def peak_mb_since(start: tuple[Any, ...]) -> float | None:
    """The peak since :func:`peak_start` above its level then, MiB (None where unsupported)."""
    kind, dev, base = start
    if kind == "cuda":
        torch.cuda.synchronize(dev)
        return round(max(torch.cuda.max_memory_allocated(dev) - base, 0) / 2**20, 1)
    return _peak_mb(base)


# --------------------------------------------------------------------------------------------
# Running one configuration
# --------------------------------------------------------------------------------------------


def _downsample_case(psf: F32, meas: F32, mask: F32, d: int) -> tuple[F32, F32, F32]:
    """Downsample PSF (renormalised to unit sum) and masked measurement by ``d``."""
    if d == 1:
        return psf, meas, mask
    psf_d = box_downsample(psf, d)
    meas_d, mask_d = downsample_masked(meas, mask, d)
    return (psf_d / psf_d.sum()).astype(np.float32), meas_d, mask_d


def _upsample(x: F32, shape: tuple[int, int]) -> F32:
    """Nearest-neighbour upsampling of (C, K, h, w) by whole factors, padded to ``shape``."""
    c, k, h, w = x.shape
    fy, fx = shape[0] // h, shape[1] // w
    up = np.repeat(np.repeat(x, fy, axis=2), fx, axis=3)
    out = np.zeros((c, k, *shape), dtype=np.float32)
    out[..., : up.shape[2], : up.shape[3]] = up
    return out


def _udn_configs(cfg: Config, seed: int, max_iter: int) -> tuple[Any, Any]:
    """The UDN's NetworkConfig and UDNConfig of a grid setting.

    No early stop: the trade hides its own held-out pixels and scores every checkpoint.
    """
    from recon.udn import NetworkConfig, UDNConfig

    net = NetworkConfig(scales=cfg.scales, channels=cfg.channels)
    conf = UDNConfig(max_iter=max_iter, seed=seed, precision=cfg.precision,  # type: ignore[arg-type]
                     holdout=0.0)
    return net, conf


#: UDNConfig fields a trade row does not record: its ``iterations`` is the count and a wall
#: limit is the caller's (a plan's budget); the seed is each job's own; how a run stops (the
#: trade hides its own held-out pixels and runs without an early stop: a job made from the row
#: keeps its held-out stop); and the machine's (compile, channels-last, snapshots)
UDN_NOT_RECORDED = ("max_iter", "time_limit_s", "seed", "holdout", "patience", "min_iter",
                    "min_delta", "compile", "channels_last", "snapshot_every")


def udn_settings(cfg: Config, seed: int = 0) -> dict[str, Any]:
    """What a UDN setting of the grid runs: ``{"network": ..., "config": ...}`` (JSON-ready).

    Every field of :class:`recon.udn.NetworkConfig` and of :class:`recon.udn.UDNConfig`
    except :data:`UDN_NOT_RECORDED`; a trade row records it (``udn_settings``) so that a plan
    made from the row runs the network the row measured.
    """
    net, conf = _udn_configs(cfg, seed, max(cfg.checkpoints))
    run = {k: v for k, v in conf.to_dict().items() if k not in UDN_NOT_RECORDED}
    return {"network": net.to_dict(), "config": run}


def _iterate(cfg: Config, psf: F32, meas: F32, mask: F32, seed: int,
             field: tuple[int, int] | None = None) -> Iterator[tuple[int, F32, float]]:
    """Yield (iteration, estimate, elapsed) at each checkpoint of one run (scene ``field``)."""
    last = max(cfg.checkpoints)
    if cfg.method in ("fista", "admm"):
        dtype = torch.float64 if cfg.precision == "float64" else torch.float32
        if cfg.precision not in ("float32", "float64"):
            raise ValueError(f"{cfg.method} runs in float32 or float64, not {cfg.precision}")
        model = build_model("2d", psf, mask=mask, dtype=dtype, field=field)
        b = torch.as_tensor(meas, dtype=dtype)
        t0 = time.perf_counter()
        if cfg.method == "fista":
            from recon.fista import Fista

            solver: Any = Fista(model.op, b, tau=cfg.tau, max_iter=last, tol=0.0)
        else:
            from recon.admm import Admm

            solver = Admm(model, b, tau=cfg.tau, max_iter=last, tol=0.0)
        for step in solver.steps():
            if step.iteration in cfg.checkpoints:
                yield step.iteration, solver.x.detach().float().cpu().numpy(), (
                    time.perf_counter() - t0)
            if solver.done and step.iteration < last:  # stopped early: it serves the rest
                x, elapsed = solver.x.detach().float().cpu().numpy(), time.perf_counter() - t0
                for c in sorted(cfg.checkpoints):
                    if c > step.iteration:
                        yield c, x, elapsed
        return
    if cfg.method == "udn":
        from recon.udn import UDNRunner

        model = build_model("2d", psf, mask=mask, field=field)
        net, conf = _udn_configs(cfg, seed, last)
        runner = UDNRunner(model, meas, network=net, config=conf)
        t0 = time.perf_counter()
        for step in runner.steps():
            if step.iteration in cfg.checkpoints:
                yield step.iteration, runner.final_estimate(), time.perf_counter() - t0
        return
    raise ValueError(f"unknown method {cfg.method!r}: use fista, admm or udn")


def run_trade(
    case: Case,
    grid: Sequence[Config],
    *,
    holdout: float = 0.05,
    seed: int = 0,
    cancel: Callable[[], bool] | None = None,
    skip: Collection[str] = (),
    finished: Callable[[str], None] | None = None,
) -> Iterator[TradeRow]:
    """Run every configuration on ``case``; yield one row per (configuration, checkpoint).

    ``skip``: labels of configurations not to run (measured by an earlier session);
    ``finished(label)`` is called once a configuration's last row has been taken, before the
    next one starts (a caller keeps what is complete).
    """
    if not 0 < holdout < 0.5:
        raise ValueError(f"holdout must be in (0, 0.5), got {holdout}")
    h, w = case.meas.shape[-2:]
    measured = np.ones((h, w), np.float32) if case.mask is None else case.mask.astype(np.float32)
    idx = np.flatnonzero(measured > 0)
    if idx.size < 20:
        raise ValueError(f"case {case.name}: only {idx.size} measured pixels; the held-out "
                         "proxy needs at least 20")
    rng = np.random.default_rng(seed)
    # at least 200 held-out pixels while that leaves three quarters to fit (as recon.autotau):
    # 5 % of a 99 %-erased measurement is too few to rank settings
    n_hold = max(1, round(holdout * idx.size), min(200, idx.size // 4))
    hold = np.zeros(h * w, bool)
    hold[rng.choice(idx, n_hold, replace=False)] = True
    hold = hold.reshape(h, w)
    fit_mask = (measured > 0) & ~hold
    fh, fw = case.field if case.field is not None else (h, w)
    full = build_model("2d", case.psf, dtype=torch.float64, field=(fh, fw))
    peak = float(np.abs(case.meas[:, hold]).max()) or 1.0
    # warm-up: one-time costs (thread pools, FFT plans) must not land on the first setting
    for _ in _iterate(Config("fista", 0.0, (2,)), case.psf, case.meas, measured, seed,
                      (fh, fw)):
        pass
    for cfg in grid:
        if cancel is not None and cancel():
            return
        if cfg.label in skip:
            continue
        psf_d, meas_d, mask_d = _downsample_case(case.psf, case.meas,
                                                 fit_mask.astype(np.float32), cfg.downsample)
        settings = udn_settings(cfg, seed) if cfg.method == "udn" else None
        base = _reset_peak()
        field_d = (fh // cfg.downsample, fw // cfg.downsample)
        for it, x, elapsed in _iterate(cfg, psf_d, meas_d, mask_d, seed, field_d):
            mem = _peak_mb(base)
            xf = _upsample(x, (fh, fw)) if cfg.downsample > 1 else x
            with torch.no_grad():
                pred = full.apply(torch.as_tensor(xf, dtype=torch.float64)).numpy()
            fit = pred[:, fit_mask]
            g = float((fit * case.meas[:, fit_mask]).sum() / max((fit * fit).sum(), 1e-30))
            pred *= g
            err_hold = float(np.mean((pred[:, hold] - case.meas[:, hold]) ** 2))
            res_fit = float(np.linalg.norm(pred[:, fit_mask] - case.meas[:, fit_mask]) /
                            max(float(np.linalg.norm(case.meas[:, fit_mask])), 1e-30))
            row = TradeRow(
                case=case.name, setting=cfg.label, method=cfg.method, tau=cfg.tau,
                precision=cfg.precision, downsample=cfg.downsample, channels=cfg.channels,
                iterations=it, wall_s=round(elapsed, 3), peak_mem_mb=mem,
                heldout_psnr=10 * math.log10(peak**2 / max(err_hold, 1e-30)),
                residual=res_fit, udn_settings=settings,
            )
            if case.truth is not None:
                est = gain_fit(case.truth, xf)[0]
                row.psnr = psnr(case.truth, est)
                row.ssim = ssim(case.truth, est)
            yield row
        if finished is not None:
            finished(cfg.label)


# --------------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------------


def _quality(row: TradeRow, key: str) -> float:
    v = getattr(row, key)
    return -math.inf if v is None else float(v)


def pareto_front(rows: Sequence[TradeRow], key: str = "psnr") -> list[TradeRow]:
    """Rows not dominated in (less wall time, more ``key``), sorted by wall time."""
    ordered = sorted(rows, key=lambda r: (r.wall_s, -_quality(r, key)))
    front: list[TradeRow] = []
    best = -math.inf
    for r in ordered:
        q = _quality(r, key)
        if q > best:
            front.append(r)
            best = q
    return front


def best_for_budgets(rows: Sequence[TradeRow], budgets_s: Sequence[float],
                     key: str = "psnr") -> dict[float, TradeRow | None]:
    """For each time budget, the row of highest ``key`` whose wall time fits it."""
    out: dict[float, TradeRow | None] = {}
    for b in budgets_s:
        fitting = [r for r in rows if r.wall_s <= b and getattr(r, key) is not None]
        out[b] = max(fitting, key=lambda r: _quality(r, key)) if fitting else None
    return out


def rank_correlation(a: Sequence[float], b: Sequence[float]) -> float:
    """Spearman rank correlation (average ranks for ties)."""
    if len(a) != len(b) or len(a) < 3:
        raise ValueError("rank correlation needs two sequences of equal length >= 3")

    def ranks(v: Sequence[float]) -> npt.NDArray[np.float64]:
        arr = np.asarray(v, dtype=np.float64)
        order = arr.argsort(kind="mergesort")
        r = np.empty(len(arr), dtype=np.float64)
        r[order] = np.arange(len(arr), dtype=np.float64)
        for val in np.unique(arr):
            sel = arr == val
            r[sel] = r[sel].mean()
        return r

    ra, rb = ranks(a), ranks(b)
    ra -= ra.mean()
    rb -= rb.mean()
    den = math.sqrt(float((ra * ra).sum() * (rb * rb).sum()))
    return float((ra * rb).sum() / den) if den > 0 else 0.0


_FLOAT = {"tau", "wall_s", "heldout_psnr", "residual"}
_INT = {"downsample", "channels", "iterations"}


# --------------------------------------------------------------------------------------------
# trade.csv
# --------------------------------------------------------------------------------------------


def case_record(case: Case) -> dict[str, Any]:
    """What ``trade.csv`` records about the data of ``case`` (one ``case`` header line).

    ``shape`` (C, H, W) of the measurement as reconstructed, ``channels``, ``field`` (the scene
    field), ``psf_shape`` and ``psf_hash`` (:func:`recon.formats.array_hash` of the float32
    PSF as reconstructed), ``meas_hash``, ``measured_fraction`` and ``erasure`` (1 - it),
    ``truth`` (scored against one) and ``source`` (the files and their hashes, or the
    simulation) where the case names it.
    """
    meas = np.asarray(case.meas)
    h, w = meas.shape[-2:]
    measured = 1.0 if case.mask is None else float((np.asarray(case.mask) > 0).mean())
    rec: dict[str, Any] = {
        "name": case.name,
        "shape": [int(n) for n in meas.shape],
        "channels": int(meas.shape[0]) if meas.ndim >= 3 else 1,
        "field": [int(n) for n in (case.field if case.field is not None else (h, w))],
        "psf_shape": [int(n) for n in np.shape(case.psf)],
        "psf_hash": array_hash(np.asarray(case.psf, dtype=np.float32)),
        "meas_hash": array_hash(meas.astype(np.float32, copy=False)),
        "measured_fraction": round(measured, 6),
        "erasure": round(1.0 - measured, 6),
        "truth": case.truth is not None,
    }
    if case.source:
        rec["source"] = dict(case.source)
    return rec


def _dims(v: Any) -> str:
    return "x".join(str(n) for n in v) if isinstance(v, list | tuple) else str(v)


def case_differences(recorded: Mapping[str, Any], data: Mapping[str, Any]) -> list[str]:
    """How the data a trade case was measured on differs from ``data``; [] when they match.

    Both are :func:`case_record` dicts. They match when the measurement's shape (channels,
    rows, columns as reconstructed), the scene field and the PSF are the same: what a trade's
    timings and its tau (per pixel of a unit-sum PSF) are measured on. The PSF is the same
    when its array hash is, or when both name the same PSF file (``source['psf_file_hash']``;
    read with other dark or downsampling options, the shape check tells). The scene, its
    erasure and noise move the best setting by degrees and are not compared. A value the
    trade does not record is not compared.
    """
    out = []
    for key, label in (("shape", "measurement"), ("field", "scene field")):
        if recorded.get(key) is not None and recorded.get(key) != data.get(key):
            out.append(f"{label} {_dims(recorded.get(key))} (here {_dims(data.get(key))})")
    if recorded.get("psf_hash") is not None and recorded.get("psf_hash") != data.get("psf_hash"):
        rf = (recorded.get("source") or {}).get("psf_file_hash")
        df = (data.get("source") or {}).get("psf_file_hash")
        if not (rf and rf == df):
            out.append("another PSF")
    return out


@dataclass
class TradeFile:
    """A ``trade.csv`` as read: its rows, and the header of a file that has one."""

    path: Path
    rows: list[TradeRow]
    format_version: int  # 0: a file from before the header (no metadata, no cases)
    meta: dict[str, Any]  # the header's values (provenance, command, ...)
    cases: list[dict[str, Any]]  # the case_record of each case measured


def _csv_row(row: TradeRow) -> dict[str, Any]:
    """A row's cells: ``udn_settings`` as compact JSON (empty when there are none)."""
    import json

    d = row.as_dict()
    d["udn_settings"] = ("" if row.udn_settings is None else
                         json.dumps(row.udn_settings, separators=(",", ":")))
    return d


def _read_udn_settings(text: str, where: str) -> dict[str, Any] | None:
    """The ``udn_settings`` cell: None when empty, else ``{"network": {...}, "config": {...}}``."""
    import json

    if text in ("", "None"):
        return None
    try:
        v = json.loads(text)
    except ValueError:
        v = None
    if not (isinstance(v, dict) and set(v) == {"network", "config"}
            and all(isinstance(v[k], dict) for k in v)):
        raise ValueError(f"{where}: column udn_settings is {text!r:.80}, not a JSON object "
                         "with a 'network' and a 'config' object")
    return v


def write_trade_csv(path: str | Path, rows: Sequence[TradeRow], cases: Sequence[Case],
                    **meta: Any) -> Path:
    """Write ``trade.csv`` atomically: the header (format, provenance, ``meta``, cases), rows."""
    from recon.atomic import atomic_write_bytes
    from recon.csvmeta import format_table
    from recon.formats import provenance

    prov = provenance()
    items: list[tuple[str, Any]] = [("created_utc", prov["created_utc"]),
                                    ("host", prov["host"]), ("versions", prov["versions"])]
    items += [(k, v) for k, v in meta.items() if v is not None]
    items += [("case", case_record(c)) for c in cases]
    fields = [f.name for f in dataclasses.fields(TradeRow) if f.name != "extra"]
    text = format_table(TRADE_FORMAT, FORMAT_VERSION, items, fields,
                        [_csv_row(r) for r in rows])
    return atomic_write_bytes(path, text.encode("utf-8"))


def read_trade(path: str | Path) -> TradeFile:
    """Read a ``trade.csv`` written by ``lenslesscam trade``, with or without its header.

    The one reader of the file kind: a file from before the header (format version 0) reads
    with no cases; a newer format version or another file is refused (FormatError).
    """
    from recon.csvmeta import read_table

    table = read_table(path, TRADE_FORMAT, FORMAT_VERSION, "trade.csv", repeated=("case",))
    cases = table.meta.pop("case")
    for c in cases:
        if not isinstance(c, dict):
            raise FormatError(f"{path}: a case line of the header is not a JSON object: "
                              f"{c!r:.60}")
    needed = [f.name for f in dataclasses.fields(TradeRow) if f.name != "extra"
              and f.default is dataclasses.MISSING]
    missing = [n for n in needed if n not in table.fieldnames]
    if missing:
        raise ValueError(f"{path}: not a trade.csv from lenslesscam trade (no column "
                         f"{', '.join(missing)})")
    rows = []
    for line, rec in table.rows:
        kw: dict[str, Any] = {}
        for f in dataclasses.fields(TradeRow):
            if f.name == "extra":
                continue
            v = rec.get(f.name, "")
            if f.name == "udn_settings":  # a column of later files: absent reads as none
                kw[f.name] = _read_udn_settings(v or "", f"{path} line {line}")
                continue
            try:
                if f.name in _FLOAT:
                    kw[f.name] = float(v)
                elif f.name in _INT:
                    kw[f.name] = int(v)
                elif f.name in ("psnr", "ssim", "peak_mem_mb"):
                    kw[f.name] = float(v) if v not in ("", "None") else None
                else:
                    kw[f.name] = v
            except (TypeError, ValueError):
                raise ValueError(f"{path} line {line}: column {f.name} is {v!r}, not a "
                                 "number") from None
            x = kw[f.name]
            if isinstance(x, float) and not math.isfinite(x):  # a NaN score won the budget
                raise ValueError(f"{path} line {line}: column {f.name} is {v!r}, not a "
                                 "finite number")
        if kw["wall_s"] < 0 or kw["iterations"] < 0:
            raise ValueError(f"{path} line {line}: a negative wall time or iteration count")
        if not 0.0 <= kw["tau"] <= TAU_MAX:  # -5 or 1e300 was applied to the preview as is
            raise ValueError(f"{path} line {line}: column tau is {rec.get('tau')!r}, not in "
                             f"0..{TAU_MAX:g} (the TV weight on a max-1 measurement)")
        rows.append(TradeRow(**kw))
    if not rows:
        raise ValueError(f"{path}: no rows (is it a trade.csv from lenslesscam trade?)")
    return TradeFile(Path(path), rows, table.format_version, table.meta, cases)


def read_trade_csv(path: str | Path) -> list[TradeRow]:
    """Rows of a ``trade.csv`` written by ``lenslesscam trade`` (:func:`read_trade`)."""
    return read_trade(path).rows


#: the quality a trade is ranked by, as its tables and plots name it
QUALITY_LABEL = {"psnr": "PSNR vs truth (dB)", "heldout_psnr": "held-out prediction (dB)"}


def trade_markdown(rows: list[TradeRow], cases: list[Any], budgets: list[float],
                   produced: str, closing: str) -> str:
    """``trade.md``: the best setting per budget and the Pareto front of each case.

    ``produced`` says what made the trade (its first sentences), ``closing`` where the points
    are. The one writer of the file: the command and the app's trade panel (*Save trade…*).
    """
    md = [f"# Speed/accuracy trade\n\n{produced} Wall time "
          "is the time to reach the iteration count (one run per setting, scored at several "
          "counts); peak memory is the run's peak resident memory above its start.\n"]
    for case in cases:
        cr = [r for r in rows if r.case == case.name]
        key = "psnr" if case.truth is not None else "heldout_psnr"
        md.append(f"\n## {case.name}\n")
        if case.truth is not None:
            rho = rank_correlation([r.heldout_psnr for r in cr], [r.psnr or 0.0 for r in cr])
            md.append(f"Held-out proxy vs true PSNR over all {len(cr)} points: Spearman rank "
                      f"correlation **{rho:.3f}**.\n")
        md.append(f"\nBest setting per time budget (by {QUALITY_LABEL[key]}):\n\n"
                  "| budget (s) | setting | iterations | wall (s) | quality (dB) |\n"
                  "|---|---|---|---|---|")
        for b, r in best_for_budgets(cr, budgets, key).items():
            md.append(f"| {b:g} | " + (f"{r.setting} | {r.iterations} | {r.wall_s:.2f} | "
                                        f"{getattr(r, key):.2f} |" if r else "none fits | | | |"))
        md.append("\nPareto front (no other point is both faster and better):\n\n"
                  "| setting | iterations | wall (s) | peak MB | held-out (dB) | residual | "
                  "PSNR (dB) | SSIM |\n|---|---|---|---|---|---|---|---|")
        for r in pareto_front(cr, key):
            md.append(f"| {r.setting} | {r.iterations} | {r.wall_s:.2f} | {r.peak_mem_mb} | "
                      f"{r.heldout_psnr:.2f} | {r.residual:.4f} | "
                      + (f"{r.psnr:.2f} | {r.ssim:.3f} |" if r.psnr is not None else "- | - |"))
    md.append(f"\n{closing}\n")
    return "\n".join(md)
