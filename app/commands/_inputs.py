"""Command-line inputs -> :class:`recon.problem.ProblemSpec` (the one way commands load data).

Every command that reads a measurement (``recon fista|udn|auto``, ``plan``, ``trade``) builds
its spec with :func:`problem_spec` and loads it with :func:`recon.problem.load_problem`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from app.commands._common import parse_dark


def add_layout_arguments(p: Any) -> None:
    """The dataset-layout options every loading command takes (see recon.problem)."""
    p.add_argument("--channel-order", choices=["rgb", "bgr"], default="rgb",
                   help="colour order stored in the files (bgr: the DiffuserCam MirFlickr "
                        "dataset); PSF, measurement and truth alike")
    p.add_argument("--flip-rows", action="store_true",
                   help="files stored upside down (the DiffuserCam MirFlickr dataset): flip the "
                        "rows of PSF, measurement, mask, shutter, filters and truth alike, a "
                        "plain flip (on upright files with an even number of rows it also "
                        "moves the PSF's centre row, and the result, by one row)")


def field_value(value: str | None) -> Any:
    """``--field`` as a ProblemSpec field: 'sensor', 'full' or (H, W)."""
    if value in (None, "sensor", "full"):
        return value or "sensor"
    from app.commands._options import parse_hw

    try:  # the one size parser: ' 9x9' and 9X9 too, 0x5 and 10^23 x 5 named as --field
        return parse_hw(value or "", "--field")
    except ValueError:
        if value and value.strip().lower() in ("sensor", "full"):
            return value.strip().lower()
        if re.fullmatch(r"\s*\d+\s*[xX,]\s*\d+\s*", value or ""):
            raise
        raise ValueError(f"--field must be 'sensor', 'full' or HxW, got {value!r}") from None


def add_dark_arguments(p: Any, dark_help: str = "dark level: a number, a dark-frame file or "
                       "'auto' (the black level a frame saved by lenslesscam records, else the "
                       "measurement's 1st percentile; the PSF's: the mean of its corner patch "
                       "[5:15, 5:15])") -> None:
    """``--dark`` and ``--psf-dark``: one wording in every command the problem loader serves."""
    p.add_argument("--dark", help=dark_help)
    p.add_argument("--psf-dark", help="dark level of the PSF: a number, 'auto' or a dark-frame "
                   "file (default: the --dark level; leave it out for a calibrated PSF file, "
                   "which is dark-subtracted already, or give 0)")


def dark_value(value: str | None, option: str = "--dark") -> Any:
    """``--dark`` (or ``option``): None, a number, 'auto' or an existing file (absolute)."""
    d = parse_dark(value, option)
    return str(Path(d).expanduser().resolve()) if isinstance(d, Path) else d


def problem_spec(args: Any, **changes: Any) -> Any:
    """The :class:`recon.problem.ProblemSpec` that a command's arguments describe.

    Reads the arguments a command has (``--model``, ``--psf``, ``--psf-stack``, ``--meas``,
    ``--mask``, ``--shutter``, ``--filters``, ``--truth``, ``--dark``, ``--psf-dark``,
    ``--downsample``, ``--field``, ``--rgb``, ``--channel-order``, ``--flip-rows``); missing
    ones take the spec's defaults. ``changes`` override fields.
    """
    from recon.problem import ProblemSpec

    def get(name: str) -> Any:
        return getattr(args, name, None)

    def path(value: Any) -> Any:
        return None if value is None else str(Path(value).expanduser().resolve())

    if get("psf") and get("psf_stack"):
        raise ValueError("give --psf or --psf-stack, not both (a stack makes a depth model)")
    model = get("model") or ("depth" if get("psf_stack") else "2d")
    if get("psf_stack") and model != "depth" and "model" not in changes:
        raise ValueError(f"--psf-stack needs --model depth (a PSF stack is a depth model; left "
                         f"out, --model is inferred), not --model {model}")
    kw: dict[str, Any] = {
        "meas": path(get("meas")), "model": model,
        "psf": path(get("psf")) if model != "depth" else None,
        "psf_stack": path(get("psf_stack")) if model == "depth" else None,
        "mask": path(get("mask")), "shutter": path(get("shutter")),
        "filters": path(get("filters")), "truth": path(get("truth")),
        "dark": dark_value(get("dark")),
        "psf_dark": dark_value(get("psf_dark"), "--psf-dark"),
        "downsample": int(get("downsample") or 1),
        "field": field_value(get("field")),
        "color": "rgb" if get("rgb") else "gray",
        "channel_order": get("channel_order") or "rgb",
        "flip_rows": bool(get("flip_rows")),
    }
    kw.update(changes)
    from recon.problem import ProblemSpecError

    try:
        return ProblemSpec(**kw)
    except ProblemSpecError as exc:  # named as the user wrote it: --field, not "problem: field"
        raise ValueError(exc.for_command_line()) from None
