"""recon.textfmt.percent: a share never rounded to all or none unless it is.

A measurement with 1849 of its 1850 pixels at 0 was said to have "100 % of its pixels" at 0,
and a frame dark-subtracted at 4094 "100% ... negative" with pixels left positive.
"""

from __future__ import annotations

import pytest

from recon.textfmt import percent


def test_a_part_is_never_shown_as_all_or_none():
    assert percent(1849, 1850) == "99.95 %"
    assert percent(1, 1850) == "0.05 %"
    assert percent(1999999, 2_000_000) == ">99.99 %"
    assert percent(1, 2_000_000) == "<0.01 %"
    assert percent(0.9996) == "99.96 %"  # a fraction: whole 1
    assert percent(997, 1000) == "99.7 %" and percent(3, 1000) == "0.3 %"
    assert percent(0.5) == "50 %" and percent(0.99) == "99 %" and percent(0.01) == "1 %"
    for n in range(1, 2000, 7):  # every part of 2000 strictly between none and all
        text = percent(n, 2000)
        assert text not in ("0 %", "100 %") and not text.startswith(("0.00", "100.")), text


def test_usual_shares_round_as_usual():
    assert percent(1, 3) == "33 %"
    assert percent(2, 3, decimals=1) == "66.7 %"
    assert percent(0, 10) == "0 %" and percent(10, 10) == "100 %"
    assert percent(1849, 1850, sep="") == "99.95%"  # the style of "...% of its pixels"
    assert percent(5, 10, decimals=1) == "50.0 %"


@pytest.mark.parametrize(("args", "kw"), [((1, 0), {}), ((float("nan"), 1), {}),
                                          ((1, 2), {"decimals": 3, "max_decimals": 2})])
def test_bad_arguments_are_refused(args, kw):
    with pytest.raises(ValueError):
        percent(*args, **kw)


def test_the_input_warnings_never_say_all_for_not_all():
    """"100 % of its pixels are 0" for 1849 of 1850; "100% ... negative" with one left."""
    import warnings

    import numpy as np

    from recon.checks import negative_measurement
    from recon.readers import _check_unmasked_zeros

    b = np.full((1, 10, 185), -1.0, np.float32)
    b[0, 0, 0] = 1.0
    said = negative_measurement(b)
    assert said is not None and said.startswith("99.95% of its measured pixels are negative")
    z = np.zeros((1, 10, 185), np.float32)
    z[0, 0, 0] = 1.0
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        _check_unmasked_zeros(z, "m.npy")
    assert "99.95 % of its pixels are 0" in str(rec[0].message)
