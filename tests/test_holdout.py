"""Held-out pixels in whole blocks (recon.holdout) and the standard error over blocks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from recon.holdout import (
    block_labels,
    block_mean_se,
    block_side,
    block_side_for,
    heldout_blocks,
)


def test_blocks_are_four_pixels_a_32nd_of_a_large_frame_and_eight_across_a_small_one():
    assert block_side(67, 120) == 4 == block_side(150, 200) == block_side(159, 4000)
    # the same optics read at full resolution: the block keeps its size on the sensor
    assert block_side(270, 480) == 8 and block_side(1080, 1920) == 33
    assert block_side(24, 64) == 3 and block_side(5, 9) == 1
    # a sensor embedded in a padded grid: its window's extent counts, not the grid's
    window = np.zeros((540, 960), bool)
    window[135:405, 240:720] = np.random.default_rng(0).random((270, 480)) >= 0.99
    assert block_side(540, 960) == 16 and block_side_for(window) == 8
    assert block_side_for(np.ones((67, 120), bool)) == 4
    lab = block_labels(67, 120, 8)
    assert lab.shape == (67, 120) and lab.max() + 1 == 9 * 15
    # a block is a square of side 8: its pixels share a label, its neighbours do not
    assert len(np.unique(lab[:8, :8])) == 1 and lab[0, 8] != lab[0, 0] != lab[8, 0]
    with pytest.raises(ValueError, match="block side"):
        block_labels(4, 4, 0)


@pytest.mark.parametrize("erasure", [0.0, 0.9])
def test_heldout_pixels_are_whole_blocks_of_measured_pixels(erasure):
    rng = np.random.default_rng(3)
    measured = rng.random((67, 120)) >= erasure
    n_meas = int(measured.sum())
    n_hold = max(20, round(0.1 * n_meas))
    hold, lab = heldout_blocks(measured, n_hold, np.random.default_rng(0))
    assert not (hold & ~measured).any()  # an erased pixel is never held out
    taken = np.unique(lab[hold])
    # every measured pixel of a chosen block is held out, and no other
    assert np.array_equal(hold, np.isin(lab, taken) & measured)
    # just enough blocks: at least n_hold pixels, fewer without the last block
    assert hold.sum() >= n_hold
    assert hold.sum() - max(int((hold & (lab == t)).sum()) for t in taken) < n_hold
    # seeded: the same seed the same pixels, another seed others
    again, _ = heldout_blocks(measured, n_hold, np.random.default_rng(0))
    other, _ = heldout_blocks(measured, n_hold, np.random.default_rng(1))
    assert np.array_equal(hold, again) and not np.array_equal(hold, other)


def test_single_pixel_blocks_hold_out_exactly_the_number_asked():
    measured = np.ones((20, 30), bool)
    hold, _ = heldout_blocks(measured, 60, np.random.default_rng(0), side=1)
    assert hold.sum() == 60
    with pytest.raises(ValueError, match="cannot hold out"):
        heldout_blocks(measured, 600, np.random.default_rng(0))


def test_standard_error_counts_blocks_not_pixels():
    rng = np.random.default_rng(0)
    v = rng.normal(size=400)
    m, se = block_mean_se(v, np.arange(400))  # single pixels: the textbook SE
    assert m == pytest.approx(v.mean()) and se == pytest.approx(v.std(ddof=1) / 20)
    # values shared within 20 blocks of 20: the same spread, but only 20 independent draws
    shared = np.repeat(rng.normal(size=20), 20)
    _, se_pixels = block_mean_se(shared, np.arange(400))
    _, se_blocks = block_mean_se(shared, np.arange(400) // 20)
    assert se_blocks == pytest.approx(shared.std(ddof=0) * math.sqrt(20 / 19) / math.sqrt(20),
                                      rel=1e-9)
    assert se_blocks > 3 * se_pixels
    assert block_mean_se(np.ones(5), np.zeros(5))[1] == math.inf  # one block: no spread
