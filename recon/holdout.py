"""Held-out measured pixels in whole blocks: choosing settings without ground truth.

The automatic tau (:mod:`recon.autotau`) leaves some measured pixels out of the fit and scores
the prediction there. On a real camera the measurement's departure from the forward
model (the PSF's estimate, vignetting, the sensor's response) is not independent from pixel to
pixel: it is smooth across the sensor. A held-out pixel between fitted ones then has its
error predicted by its neighbours, so a solution that fits the mismatch (too little
regularisation, too many iterations) also scores well on scattered held-out pixels. Holding out
contiguous blocks, so that a held-out pixel's nearest neighbours are held out with it
(*blocked cross-validation*: Roberts et al. 2017, "Cross-validation strategies for data with
temporal, spatial, hierarchical, or phylogenetic structure", Ecography 40:913), scores
predictions that were not interpolated from fitted neighbours; with independent noise alone it
chooses nearly as scattered pixels do.

The blocks tile the sensor: squares of ``BLOCK_SIDE`` (4) pixels, or 1/``FRAME_FRACTION``
(1/32) of the sensor's shorter side (the extent of the measured pixels) where that is more
(from 160 pixels up: 8 at 270x480), so that a block keeps its size on the sensor when the same
optics is read at a higher resolution; smaller on a frame under 32 pixels on its short side, so
that it keeps 8 blocks across. They are drawn in a seeded random order until the held-out
measured pixels reach the number asked for (erased pixels are never held out). Standard errors
of held-out scores are taken over blocks (:func:`block_mean_se`), the unit that was drawn. The
side was measured (``lenslesscam bench tau-rules --block N``, docs/auto-tau.md): on the four
real DiffuserCam pairs at 1/4 resolution the automatic tau gains 0.25 / 0.52 / 0.10 dB on
average with sides 2 / 4 / 8 over single pixels; on the simulation protocol (1/8 scale) sides 4
/ 9 / 19 cost 0.19 / 0.63 / 0.80 dB, the side-4 cost almost all in its noise-free 0 % cases
(results of 35-44 dB), where the held-out blocks prefer about 3x the best tau. On the real
pairs the best side grows with the resolution: 4 at 1/4 (67x120), 8 better than 4 by 0.14 dB at
1/2, and at the full 270x480 sides 4 / 8 / 16 give 16.02 / 16.31 / 16.46 dB on average over
five erasure levels (oracle 17.01): 1/16 of the shorter side is best at all three resolutions.
The simulation (150x200, no model mismatch) prefers small blocks (side 9 costs it 0.44 dB), so
the side is 1/32 of the shorter side with 4 pixels at least: unchanged wherever 4 was measured,
+0.29 dB at full resolution (docs/auto-tau.md, "Full resolution").

The UDN's stopping rule (:mod:`recon.udn.runner`) keeps scattered held-out values: with blocks
(``lenslesscam bench real-pairs --lever block-holdout``) its results on the real pairs moved by
-0.16 to +0.57 dB per erasure level, +0.05 dB on average, with its held-out minimum near the
last iteration on most cases either way (docs/udn.md).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = [
    "BLOCK_SIDE",
    "FRAME_FRACTION",
    "MIN_RELIABLE_HELDOUT",
    "block_labels",
    "block_mean_se",
    "block_side",
    "block_side_for",
    "few_heldout_note",
    "heldout_blocks",
    "sensor_extent",
]

#: Side in pixels of the held-out blocks (at least; see FRAME_FRACTION).
BLOCK_SIDE = 4
#: On large frames the side is the shorter side over this, where that is above BLOCK_SIDE.
FRAME_FRACTION = 32
#: A frame keeps at least this many blocks across its shorter side.
MIN_BLOCKS_ACROSS = 8


def block_side(h: int, w: int) -> int:
    """Side in pixels of the held-out blocks of an ``h`` x ``w`` measurement."""
    short = min(h, w)
    side = max(BLOCK_SIDE, short // FRAME_FRACTION)
    return max(1, min(side, short // MIN_BLOCKS_ACROSS))


def sensor_extent(measured: npt.NDArray[np.bool_]) -> tuple[slice, slice] | None:
    """The sensor's extent: the bounding box (rows, columns) of the measured pixels.

    Of an (H, W) mask, or of any channel's of a (C, H, W) one; None when nothing is measured.
    A measurement embedded in a larger padded grid counts its window, not the grid.
    """
    m = np.asarray(measured, dtype=bool)
    m = m.reshape(-1, *m.shape[-2:]).any(axis=0)
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    if rows.size == 0:
        return None
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def block_side_for(measured: npt.NDArray[np.bool_]) -> int:
    """:func:`block_side` of the sensor's extent (:func:`sensor_extent`)."""
    box = sensor_extent(measured)
    if box is None:
        return block_side(*np.shape(measured)[-2:])
    return block_side(box[0].stop - box[0].start, box[1].stop - box[1].start)


def block_labels(h: int, w: int, side: int) -> npt.NDArray[np.int64]:
    """(h, w) block index of every pixel, for squares of ``side`` pixels (row-major)."""
    if side < 1:
        raise ValueError(f"block side must be >= 1, got {side}")
    nbx = math.ceil(w / side)
    ys = np.arange(h) // side
    xs = np.arange(w) // side
    return np.asarray(ys[:, None] * nbx + xs[None, :], dtype=np.int64)


def heldout_blocks(measured: npt.NDArray[np.bool_], n_hold: int, rng: np.random.Generator,
                   side: int | None = None) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int64]]:
    """Held-out pixels (H, W) in whole blocks, and the block label of every pixel.

    Blocks that hold measured pixels are taken in ``rng``'s random order until at least
    ``n_hold`` measured pixels are held out (so one block more than ``n_hold`` needs, at most);
    ``side`` None: :func:`block_side_for` the measured pixels; 1: single pixels.
    """
    measured = np.asarray(measured, dtype=bool)
    if measured.ndim != 2:
        raise ValueError(f"measured must be (H, W), got shape {measured.shape}")
    n_meas = int(measured.sum())
    if not 0 < n_hold < n_meas:
        raise ValueError(f"cannot hold out {n_hold} of {n_meas} measured pixels")
    h, w = measured.shape
    side = block_side_for(measured) if side is None else side
    labels = block_labels(h, w, side)
    counts = np.bincount(labels[measured], minlength=int(labels.max()) + 1)
    order = rng.permutation(np.flatnonzero(counts))
    upto = int(np.searchsorted(np.cumsum(counts[order]), n_hold)) + 1
    hold = np.isin(labels, order[:upto]) & measured
    return hold, labels


def block_mean_se(values: npt.NDArray[np.floating], labels: npt.NDArray[np.integer]
                  ) -> tuple[float, float]:
    """Mean of per-pixel ``values`` and its standard error with blocks as the sampling unit.

    The cluster-robust (ratio-estimator) form: block sums D_g over n_g pixels, mean
    m = sum D_g / sum n_g, SE = sqrt(G / (G - 1) sum (D_g - m n_g)^2) / sum n_g over the G
    blocks. With single-pixel blocks it is the usual standard error of a mean (the standard
    deviation with ddof 1 over sqrt(G)). Infinite with fewer than 2 blocks.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    lab = np.asarray(labels).ravel()
    if v.shape != lab.shape:
        raise ValueError(f"values {v.shape} and labels {lab.shape} differ in size")
    if v.size == 0:
        return math.nan, math.inf
    _, inv = np.unique(lab, return_inverse=True)
    sums = np.bincount(inv, weights=v)
    ns = np.bincount(inv).astype(np.float64)
    n = float(ns.sum())
    m = float(sums.sum()) / n
    g = sums.size
    if g < 2:
        return m, math.inf
    se = math.sqrt(g / (g - 1) * float(np.sum((sums - m * ns) ** 2))) / n
    return m, se


#: fewer held-out pixels than this make the choice uncertain (their mean squared error is
#: known to about sqrt(2 / n) of itself for Gaussian errors: 14 % at 100, 33 % at 18, while
#: the held-out errors of neighbouring taus differ by a few per cent): said with the choice
MIN_RELIABLE_HELDOUT = 100


def few_heldout_note(n: int, what: str,
                     against: str = "more than the taus' differences") -> str | None:
    """One line when ``n`` held-out pixels are too few to choose ``what`` on; else None.

    ``against``: what that uncertainty is compared with, in words.
    """
    if n >= MIN_RELIABLE_HELDOUT:
        return None
    return (f"only {n} held-out pixels choose {what} (fewer than {MIN_RELIABLE_HELDOUT}: their "
            f"error is known to about {100 * math.sqrt(2 / max(n, 1)):.0f} % of itself, "
            f"{against}): the choice is uncertain")
