"""Numbers in messages: a share as a percentage that never rounds a part to all or none.

``f"{100 * part / whole:.0f} %"`` said "100 % of its pixels are 0" for a measurement with
1849 of its 1850 pixels at 0, and "100% ... negative" for a frame with a few pixels left
positive: a user reads that as "all", which it was not. :func:`percent` rounds as usual, but a
share within 1 % of none or of all gets the decimals that show one significant figure of its
distance to it ("99.95 %", "0.05 %", "99.7 %"), and beyond ``max_decimals`` says so
(">99.99 %", "<0.01 %"). Exactly none is "0 %", all is "100 %".
"""

from __future__ import annotations

import math

__all__ = ["percent"]


def percent(part: float, whole: float = 1.0, *, decimals: int = 0, max_decimals: int = 2,
            sep: str = " ") -> str:
    """``part`` of ``whole`` as a percentage, never rounded to 0 or 100 unless it is.

    ``part`` / ``whole``: counts (1849, 1850) or a fraction (``whole`` 1). ``decimals``: the
    usual number of decimals; more are used (up to ``max_decimals``) within 1 % of none or
    all, to show one significant figure of the distance to it; past that, ``"<0.01"`` /
    ``">99.99"``. ``sep``: between the number and the sign (``" "``: "99.95 %", ``""``:
    "99.95%"). ValueError for a ``whole`` <= 0 or a value that is not a finite number.
    """
    if not (math.isfinite(part) and math.isfinite(whole)):
        raise ValueError(f"percent needs finite numbers, got {part} of {whole}")
    if whole <= 0:
        raise ValueError(f"percent needs a whole > 0, got {whole}")
    if decimals < 0 or max_decimals < decimals:
        raise ValueError(f"need 0 <= decimals <= max_decimals, got {decimals}, {max_decimals}")
    share = 100.0 * part / whole
    if part <= 0 or part >= whole:  # none, all (or outside: said as it is)
        return f"{share:.{decimals}f}{sep}%"
    # within 1 % of none or all: one significant figure of the distance to it
    gap = min(share, 100.0 - share)
    first = decimals if gap >= 1.0 else max(decimals, math.ceil(-math.log10(gap)))
    for d in range(first, max_decimals + 1):
        text = f"{share:.{d}f}"
        if 0.0 < float(text) < 100.0:
            return f"{text}{sep}%"
    bound = 10.0 ** -max_decimals
    return (f"<{bound:.{max_decimals}f}{sep}%" if share < 50.0
            else f">{100.0 - bound:.{max_decimals}f}{sep}%")
