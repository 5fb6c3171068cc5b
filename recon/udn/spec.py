"""UDN job specs: a TOML file naming the data, the network, the optimiser, limits and device.

Every key, its type and default is listed in :data:`SCHEMA` (and in ``docs/udn.md``). Loading
validates strictly: an unknown section or key, a wrong type, a value out of range or a missing
required key raises :class:`SpecError` naming the key (with a "did you mean" suggestion for
typos); a file named in ``[data]`` that does not exist raises FileNotFoundError naming the key
and the path. Relative paths are relative to the spec file's folder.

Example::

    [job]
    name = "hand at 1/8"

    [data]
    model = "2d"
    psf = "psf_sample.tif"
    measurement = "rawdata_hand_sample.tif"
    dark = "auto"
    downsample = 8

    [network]
    scales = 5
    channels = 128

    [stopping]
    max_iter = 5000
    time_limit_s = 28800

    [output]
    checkpoint_every = 500
    preview_every = 100
"""

from __future__ import annotations

import difflib
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from recon.formats import INT_LIMIT
from recon.udn import COMPILE_MODES, MAX_SCALES
from recon.udn.network import NetworkConfig
from recon.udn.runner import UDNConfig

__all__ = [
    "SCHEMA",
    "SpecError",
    "load_spec",
    "network_config",
    "normalise_spec",
    "spec_to_toml",
    "udn_config",
]


class SpecError(ValueError):
    """A job spec is invalid; the message names the offending key."""


@dataclass(frozen=True)
class Key:
    """One spec key: accepted types, default, help, allowed values, whether it is a path."""

    types: tuple[type, ...]
    default: Any
    help: str
    choices: tuple[Any, ...] | None = None
    required: bool = False
    path: bool = False
    minimum: float | None = None
    maximum: float | None = None


_NET = NetworkConfig()
_UDN = UDNConfig()

#: Section -> key -> :class:`Key`. ``None`` defaults mean "not set".
SCHEMA: dict[str, dict[str, Key]] = {
    "job": {
        "name": Key((str,), "", "a name for the run (shown by jobs status)"),
    },
    "data": {
        "model": Key((str,), "2d", "forward model", ("2d", "video", "spectral", "depth")),
        "psf": Key((str, list), None, "PSF file; depth: a PSF stack file, a folder of planes "
                   "or a list of plane files", required=True, path=True),
        "measurement": Key((str,), None, "measurement file", required=True, path=True),
        "mask": Key((str,), None, "erasure / dead-pixel mask, 1 = measured (sensor size at "
                    "full or reconstruction resolution; a coarse pixel is measured when any "
                    "of its sensor pixels is)", path=True),
        "shutter": Key((str,), None, "video: shutter function M (K, rows)", path=True),
        "filters": Key((str,), None, "spectral: filter cube (K, H, W)", path=True),
        "truth": Key((str,), None, "ground-truth scene (C, K, H, W), only to score the result "
                     "at the end (never used by the fit)", path=True),
        "downsample": Key((int,), 1, "box downsampling factor of PSF and measurement",
                          minimum=1),
        "dark": Key((str, float), None, "dark level of the measurement (and of the PSF unless "
                    "psf_dark is set or the PSF is a calibrated, dark-subtracted file): a "
                    "number, 'auto' or a dark-frame file"),
        "psf_dark": Key((str, float), None, "dark level of the PSF"),
        "color": Key((str,), "gray", "reconstruct gray or rgb", ("gray", "rgb")),
        "field": Key((str, list), "sensor", "scene field: 'sensor', 'full' (2H x 2W) or "
                     "[H, W]"),
        "channel_order": Key((str,), "rgb", "colour order stored in the files (bgr: the "
                             "DiffuserCam MirFlickr dataset)", ("rgb", "bgr")),
        "flip_rows": Key((bool,), False, "flip the rows of every sensor-frame input alike"),
        "psf_normalise": Key((str,), "auto", "PSF normalisation (auto: sum for a PSF, max for "
                             "a stack)", ("auto", "sum", "max", "l2", "none")),
        "measurement_normalise": Key((str,), "max", "measurement normalisation",
                                     ("max", "sum", "l2", "none")),
    },
    "network": {
        "variant": Key((str,), "auto", "2d, frames (K as output channels), 3d, or auto (2d "
                       "for K = 1, else frames)", ("auto", "2d", "frames", "3d")),
        "scales": Key((int,), _NET.scales, "encoder/decoder levels", minimum=1,
                      maximum=MAX_SCALES),
        "channels": Key((int,), _NET.channels, "feature channels per level", minimum=1),
        "skip_channels": Key((int,), _NET.skip_channels, "skip-connection channels",
                             minimum=0),
        "input_channels": Key((int,), _NET.input_channels, "channels of the input z",
                              minimum=1),
        "input_scale": Key((float,), _NET.input_scale, "z ~ uniform[0, input_scale)"),
        "leaky_slope": Key((float,), _NET.leaky_slope, "LeakyReLU negative slope"),
        "gradient_checkpointing": Key((bool,), _NET.gradient_checkpointing,
                                      "recompute activations in the backward pass"),
    },
    "optimizer": {
        "lr": Key((float,), _UDN.lr, "Adam learning rate"),
        "reg_noise": Key((float,), _UDN.reg_noise, "std of the noise added to z per iteration"),
        "loss": Key((str,), _UDN.loss, "mse or scale_invariant", ("mse", "scale_invariant")),
        "tv_weight": Key((float,), _UDN.tv_weight, "weight of TV(x) / x.numel()"),
        "tv_isotropic": Key((bool,), _UDN.tv_isotropic, "isotropic 2D TV"),
        "tv_weight_k": Key((float,), _UDN.tv_weight_k, "TV weight along k (3D TV)"),
        "ema": Key((float,), _UDN.ema, "decay of the output's moving average"),
        "gain": Key((str, float), "auto", "initial output gain, or 'auto' (least squares)"),
        "headroom": Key((float,), _UDN.headroom, "factor on the 'auto' gain (room for "
                        "highlights)"),
        "seed": Key((int,), _UDN.seed, "seed of z, weights, held-out pixels and noise",
                    minimum=0, maximum=2**32 - 1),
        "lr_backoff": Key((float,), _UDN.lr_backoff, "learning-rate factor at a divergence"),
        "divergence_factor": Key((float,), _UDN.divergence_factor,
                                 "loss jump (x the recent loss) that counts as divergence"),
        "max_backoffs": Key((int,), _UDN.max_backoffs, "restores before the run fails",
                            minimum=0),
        "snapshot_every": Key((int,), _UDN.snapshot_every,
                              "iterations between last-good-state snapshots", minimum=1),
        "clip_adapt": Key((bool,), _UDN.clip_adapt, "detect output clipping at the network's "
                          "cap during the run and raise the gain (recorded in the notes)"),
        "clip_tolerance": Key((float,), _UDN.clip_tolerance,
                              "fraction of output pixels allowed at the cap"),
        "clip_gain_step": Key((float,), _UDN.clip_gain_step,
                              "gain factor of one clipping correction (> 1)"),
    },
    "stopping": {
        "max_iter": Key((int,), _UDN.max_iter, "iteration limit", minimum=1),
        "time_limit_s": Key((float,), None, "wall-time limit in seconds"),
        "holdout": Key((float,), _UDN.holdout, "fraction of measured pixels held out for "
                       "early stopping (0: off)"),
        "patience": Key((int,), _UDN.patience, "iterations without held-out improvement",
                        minimum=1),
        "min_iter": Key((int,), _UDN.min_iter, "never stop early before this", minimum=0),
        "min_delta": Key((float,), _UDN.min_delta, "relative held-out improvement that counts"),
    },
    "device": {
        "device": Key((str,), "auto", "auto, cpu, cuda, cuda:N or mps"),
        "precision": Key((str,), _UDN.precision, "float32 or bf16 (autocast)",
                         ("float32", "bf16")),
        "compile": Key((bool,), _UDN.compile, "torch.compile the network (falls back)"),
        "compile_mode": Key((str,), _UDN.compile_mode, "torch.compile's mode; reduce-overhead: "
                            "CUDA graphs (on a GPU)", COMPILE_MODES),
        "channels_last": Key((bool,), _UDN.channels_last, "channels-last memory format"),
        "threads": Key((int,), 0, "torch CPU threads (0: recon.threads policy)", minimum=0),
        "max_memory": Key((str, int), None, "refuse runs estimated above this ('2GB')"),
    },
    "output": {
        "checkpoint_every": Key((int,), 500, "checkpoint every N iterations", minimum=1),
        "checkpoint_minutes": Key((float,), 10.0, "... or every this many minutes",
                                  minimum=0.0),
        "preview_every": Key((int,), 100, "preview PNG every M iterations (0: none)",
                             minimum=0),
        "status_seconds": Key((float,), 5.0, "how often run.json / loss.csv are refreshed",
                              minimum=0.0),
        "average_every": Key((int,), _UDN.average_every, "iterations between the estimates "
                             "averaged into mean.tif (iterate averaging; 0: none)", minimum=0),
        "with_fista": Key((bool,), True, "at the end, average the mean (or best) estimate half "
                          "and half with FISTA-TV at recon fista's defaults: with_fista.tif"),
    },
}


def _suggest(name: str, known: list[str]) -> str:
    close = difflib.get_close_matches(name, known, n=1)
    return f"; did you mean '{close[0]}'?" if close else ""


#: the largest float32 (numbers beyond it overflow the network's tensors); the largest
#: integer a spec takes is recon.formats.INT_LIMIT
FLOAT32_MAX = 3.4028234663852886e38


def _check_value(where: str, key: Key, value: Any) -> Any:
    """Type-check (int -> float where a float is wanted) and range-check one value."""
    if isinstance(value, bool) and bool not in key.types:
        raise SpecError(f"{where} must be {_type_names(key)}, got {value!r}")
    ok = False
    for t in key.types:
        if t is float and isinstance(value, int | float) and not isinstance(value, bool):
            value, ok = float(value), True
            break
        if isinstance(value, t):
            ok = True
            break
    if not ok:
        raise SpecError(f"{where} must be {_type_names(key)}, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise SpecError(f"{where} must be finite, got {value!r}")
    if key.choices is not None and isinstance(value, str) and value not in key.choices:
        raise SpecError(f"{where} must be one of {', '.join(map(str, key.choices))}, got "
                        f"{value!r}")
    if key.minimum is not None and isinstance(value, int | float) and value < key.minimum:
        raise SpecError(f"{where} must be >= {key.minimum:g}, got {value!r}")
    if key.maximum is not None and isinstance(value, int | float) and value > key.maximum:
        raise SpecError(f"{where} must be <= {key.maximum:.0f}, got {value!r}")
    if isinstance(value, float) and abs(value) > FLOAT32_MAX:
        raise SpecError(f"{where} must be within float32's range (|x| <= 3.4e38: the network "
                        f"computes in float32), got {value!r}")
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > INT_LIMIT:
        raise SpecError(f"{where} must be at most 2**62 in magnitude, got {value!r}")
    return value


def _type_names(key: Key) -> str:
    names = {str: "a string", int: "an integer", float: "a number", bool: "true or false",
             list: "a list"}
    return " or ".join(names[t] for t in key.types)


def normalise_spec(raw: Mapping[str, Any], base_dir: str | Path | None = None,
                   source: str = "spec") -> dict[str, Any]:
    """Validate a parsed spec and return it complete (defaults filled, paths absolute).

    Raises:
        SpecError: unknown section/key, wrong type or value, missing required key.
        FileNotFoundError: a file named in ``[data]`` does not exist.

    """
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    out: dict[str, dict[str, Any]] = {}
    for section, value in raw.items():
        if section not in SCHEMA:
            raise SpecError(f"{source}: unknown section [{section}]"
                            f"{_suggest(section, list(SCHEMA))} (sections: "
                            f"{', '.join(SCHEMA)})")
        if not isinstance(value, Mapping):
            raise SpecError(f"{source}: [{section}] must be a table, got {value!r}")
        for key in value:
            if key not in SCHEMA[section]:
                known = list(SCHEMA[section])
                raise SpecError(f"{source}: unknown key '{section}.{key}'{_suggest(key, known)}"
                                f" (keys of [{section}]: {', '.join(known)})")
    for section, keys in SCHEMA.items():
        given = raw.get(section, {})
        sec: dict[str, Any] = {}
        for name, key in keys.items():
            where = f"{source}: {section}.{name}"
            if name not in given:
                if key.required:
                    raise SpecError(f"{where} is required")
                sec[name] = key.default
                continue
            sec[name] = _check_value(where, key, given[name])
        out[section] = sec
    data = out["data"]
    for name in ("dark", "psf_dark"):
        v = data[name]
        if isinstance(v, str) and v != "auto":
            data[name] = _resolve(base, v, f"{source}: data.{name}")
        elif isinstance(v, int | float) and not (math.isfinite(v) and v >= 0):
            raise SpecError(f"{source}: data.{name} must be 'auto', a dark-frame file or a "
                            f"finite number >= 0 (the sensor's black offset), got {v!r}")
    for name, key in SCHEMA["data"].items():
        v = data[name]
        if not key.path or v is None:
            continue
        if isinstance(v, list):
            if not v or not all(isinstance(s, str) for s in v):
                raise SpecError(f"{source}: data.{name} must be a path or a non-empty list of "
                                "paths")
            if data["model"] != "depth":
                raise SpecError(f"{source}: data.{name} is a list; only the depth model takes "
                                "a list of PSF planes")
            data[name] = [_resolve(base, s, f"{source}: data.{name}") for s in v]
        else:
            data[name] = _resolve(base, v, f"{source}: data.{name}")
    field = data["field"]
    if isinstance(field, str) and field not in ("sensor", "full"):
        raise SpecError(f"{source}: data.field must be 'sensor', 'full' or [H, W], got "
                        f"{field!r}")
    if isinstance(field, list) and (len(field) != 2 or not all(
            isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in field)):
        raise SpecError(f"{source}: data.field must be [H, W] with positive integers, got "
                        f"{field!r}")
    # [data] is a recon.problem.ProblemSpec: its checks (files a model needs, field, colour)
    from recon.problem import ProblemSpec, ProblemSpecError

    try:
        ProblemSpec.from_data_section(data)
    except ProblemSpecError as exc:  # data.shutter, not "[data] problem: shutter"
        raise SpecError(f"{source}: {exc.for_spec()}") from None
    except ValueError as exc:
        raise SpecError(f"{source}: [data] {exc}") from None
    gain = out["optimizer"]["gain"]
    if isinstance(gain, str) and gain != "auto":
        raise SpecError(f"{source}: optimizer.gain must be 'auto' or a number, got {gain!r}")
    mm = out["device"]["max_memory"]
    if mm is not None:
        from recon.udn.memory import parse_bytes

        try:
            out["device"]["max_memory"] = parse_bytes(mm)
        except ValueError as exc:
            raise SpecError(f"{source}: device.max_memory: {exc}") from None
    # the dataclasses check ranges; name the key (section.name) in their messages
    try:
        network_config(out, k=1)
    except ValueError as exc:
        raise SpecError(f"{source}: {_keyed(exc, ('network',))}") from None
    try:
        udn_config(out)
    except ValueError as exc:
        raise SpecError(f"{source}: {_keyed(exc, ('optimizer', 'stopping', 'device'))}"
                        ) from None
    return out


def _keyed(exc: ValueError, sections: tuple[str, ...]) -> str:
    """A config's range message ('lr must be > 0, ...') as 'optimizer.lr must be > 0, ...'."""
    msg = str(exc)
    first = msg.split(maxsplit=1)[0] if msg else ""
    section = next((s for s in sections if first in SCHEMA[s]), None)
    if section is not None:
        return f"{section}.{msg}"
    return f"{'/'.join(f'[{s}]' for s in sections)} {msg}"


def _resolve(base: Path, value: str, where: str) -> str:
    p = Path(value).expanduser()
    if not p.is_absolute():
        p = base / p
    if not p.exists():
        raise FileNotFoundError(f"{where}: file not found: {p}")
    return str(p.resolve())


def read_spec_text(path: str | Path) -> str:
    """The text of a job spec file (the one reader): UTF-8, with or without a byte-order mark.

    Raises FileNotFoundError (no such file; a folder is named as one) or :class:`SpecError`
    (not UTF-8).
    """
    p = Path(path)
    if p.is_dir():
        raise FileNotFoundError(f"{p} is a folder, not a job spec (a .toml file; to continue a "
                                f"run in it: lenslesscam jobs resume {p})")
    if not p.is_file():
        raise FileNotFoundError(f"job spec not found: {p}")
    from recon.formats import read_utf8

    return read_utf8(p, error=SpecError, hint="; save the spec as UTF-8")


def parse_spec_text(text: str, where: str | Path) -> dict[str, Any]:
    """The TOML table of a spec's text; :class:`SpecError` naming ``where`` when it is not TOML."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{where}: not valid TOML: {exc}") from None


def load_spec(path: str | Path) -> dict[str, Any]:
    """Read and validate a TOML job spec (see :func:`normalise_spec`)."""
    p = Path(path)
    return normalise_spec(parse_spec_text(read_spec_text(p), p), p.parent, source=str(p))


def network_config(spec: Mapping[str, Any], k: int) -> NetworkConfig:
    """The :class:`NetworkConfig` of a normalised spec, for a scene with ``k`` frames."""
    n = dict(spec["network"])
    if n["variant"] == "auto":
        n["variant"] = "2d" if k == 1 else "frames"
    names = {f.name for f in fields(NetworkConfig)}
    return NetworkConfig(**{key: v for key, v in n.items() if key in names})


def udn_config(spec: Mapping[str, Any]) -> UDNConfig:
    """The :class:`UDNConfig` of a normalised spec."""
    o, s, d, out = spec["optimizer"], spec["stopping"], spec["device"], spec["output"]
    gain = None if o["gain"] == "auto" else float(o["gain"])
    return UDNConfig(
        lr=o["lr"], reg_noise=o["reg_noise"], loss=o["loss"], tv_weight=o["tv_weight"],
        tv_isotropic=o["tv_isotropic"], tv_weight_k=o["tv_weight_k"], ema=o["ema"], gain=gain,
        headroom=o["headroom"],
        seed=o["seed"], lr_backoff=o["lr_backoff"], divergence_factor=o["divergence_factor"],
        max_backoffs=o["max_backoffs"], snapshot_every=o["snapshot_every"],
        clip_adapt=o["clip_adapt"], clip_tolerance=o["clip_tolerance"],
        clip_gain_step=o["clip_gain_step"],
        max_iter=s["max_iter"], time_limit_s=s["time_limit_s"], holdout=s["holdout"],
        patience=s["patience"], min_iter=s["min_iter"], min_delta=s["min_delta"],
        precision=d["precision"], compile=d["compile"], compile_mode=d["compile_mode"],
        channels_last=d["channels_last"], average_every=out["average_every"],
    )


def spec_to_toml(spec: Mapping[str, Any]) -> str:
    """TOML text of a (partial or normalised) spec; ``None`` values are left out."""
    import tomli_w

    clean = {sec: {k: v for k, v in keys.items() if v is not None}
             for sec, keys in spec.items() if isinstance(keys, Mapping)}
    return tomli_w.dumps({sec: keys for sec, keys in clean.items() if keys})
