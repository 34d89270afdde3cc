"""The initial sphere from a click alone (``--center`` without ``--radii``; docs/design.md, "One
click").

A click says "this tissue". The sphere about it is the largest ball that still looks like one
tissue: balls of growing radius (:data:`SCALES_PER_OCTAVE` to a doubling) about the click,
each read in the image smoothed as the intensity model reads it, and the first that fails one of
two tests ends the growth:

- *mixed*: its robust spread (as the intensity model's: 1.4826 x MAD, at least
  ``min_sigma_fraction`` of the image's range) exceeds :data:`SPREAD_GROWTH` x the smallest
  ball's, which is the tissue's own texture and noise: the ball now holds another tissue;
- *bounded*: the shell just beyond it (to the next radius) has a median more than
  :data:`SHELL_SPREADS` x the ball's spread from the ball's median: a boundary lies in that
  shell.

A mixed ball is one step too far (the radius before it is returned); a bounded one is the last
inside. The smallest ball is first tested against its own core (:func:`_bounded_within`): an
object about as small as it (a nodule of a few voxels' radius) fills the core but not the rest,
and the smallest ball is then the one returned. Both tests are medians, so they see a boundary
that curves around the click (a structure about it) at once, but one off to one side (a flat
face) only late: it fills less than half of any shell, and the spread grows only once a good
part of the ball lies beyond it. An off-centre click's sphere may then reach well past its
nearest boundary; the region stages pull it back (the review's plane and cube phantoms,
docs/benchmarks.md session 16). The smallest ball is the smallest whose core (``core_fraction``
of the radius, where the intensity model is read) holds about
:data:`segsnake.region.MIN_SAMPLES` voxels; a ball with fewer than that (very thick slices) is
passed over. Without a click the sphere comes from the whole image instead
(:func:`segsnake.pipeline.auto_init`).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.region import MIN_SAMPLES, IntensityModel, RegionParams, smoothed

#: Radii tried per doubling: each ball holds twice the previous one's volume.
SCALES_PER_OCTAVE = 3
#: How much the ball's spread may grow over the smallest ball's (its tissue's texture and noise)
#: before the ball counts as holding another tissue (the sweep, 1.25-2: docs/benchmarks.md,
#: session 16).
SPREAD_GROWTH = 1.5
#: How far (in the ball's spreads) the next shell's median may lie from the ball's before a
#: boundary counts as found in it (where the two-class rounds give the two classes half their
#: weight; flat from 1.5 to 3 on the benchmark: docs/benchmarks.md, session 16).
SHELL_SPREADS = 2.0


def smoothed_around(image: NDArray, spacing: Sequence[float], point_mm: Sequence[float],
                    pad_mm: float, smooth_mm: float) -> tuple[NDArray, NDArray]:
    """The image smoothed at ``smooth_mm`` in the block of voxels within ``pad_mm`` of a point
    (mm of scaled index space) along each axis, and each of its voxels' squared distance from the
    point (mm^2): what is read about a click without smoothing the whole image."""
    sp = np.asarray(spacing, dtype=np.float64)
    c = np.asarray(point_mm, dtype=np.float64)
    shape = np.asarray(image.shape)
    lo = np.clip(np.floor((c - pad_mm) / sp).astype(int), 0, shape - 1)
    hi = np.clip(np.ceil((c + pad_mm) / sp).astype(int) + 1, 1, shape)
    block = smoothed(image[tuple(slice(a, b) for a, b in zip(lo, hi))], sp, smooth_mm)
    axes = [(np.arange(a, b) * s - x) ** 2 for a, b, s, x in zip(lo, hi, sp, c)]
    return block, axes[0][:, None, None] + axes[1][None, :, None] + axes[2][None, None, :]


def click_radius(image: NDArray, spacing: Sequence[float], center_mm: Sequence[float], *,
                 spread_growth: float = SPREAD_GROWTH, shell_spreads: float = SHELL_SPREADS,
                 smooth_mm: float = RegionParams.smooth_mm,
                 core_fraction: float = RegionParams.core_fraction,
                 min_sigma_fraction: float = RegionParams.min_sigma_fraction) -> float:
    """Radius (mm) of the largest ball about ``center_mm`` that looks like one tissue.

    Parameters
    ----------
    image : ndarray (nx, ny, nz)
        The image (NaN-free).
    spacing : (sx, sy, sz)
        Voxel size in mm.
    center_mm : sequence of 3 floats
        The click, in mm of scaled index space.
    spread_growth, shell_spreads : float
        The two tests (module docstring).
    smooth_mm, core_fraction, min_sigma_fraction : float
        As the intensity model reads the click (:class:`segsnake.region.RegionParams`).

    Returns
    -------
    float
        The radius in mm: at most half the volume's smallest extent, or the smallest ball's if
        that is larger.
    """
    sp = np.asarray(spacing, dtype=np.float64)
    c = np.asarray(center_mm, dtype=np.float64)
    shape = np.asarray(image.shape)
    r_min = (3 * MIN_SAMPLES * float(np.prod(sp)) / (4 * math.pi)) ** (1 / 3) / core_fraction
    r_max = max(r_min, 0.5 * float(np.min((shape - 1) * sp)))
    step = 2.0 ** (1.0 / SCALES_PER_OCTAVE)
    radii = [r_min]
    while radii[-1] * step <= r_max:
        radii.append(radii[-1] * step)
    # The spread's floor is a share of the raw image's range; the intensity model's is of the
    # smoothed image's, a few % less (Colin27: 254 against 242), which smoothing the whole image
    # here would cost as much as the model's own smoothing to match.
    image_range = float(np.max(image)) - float(np.min(image))

    def around(reach: float) -> tuple[NDArray, NDArray]:
        # The smoothed intensities within ``reach`` of the click, nearest first (a ball is a
        # prefix), from a block that holds them and the Gaussian's support (4 widths).
        block, d2 = smoothed_around(image, sp, c, reach + 4 * smooth_mm, smooth_mm)
        dist = np.sqrt(d2)
        near = dist <= reach
        dist, block = dist[near], block[near]
        order = np.argsort(dist, kind="stable")
        return block[order], dist[order]

    base, reach, last = None, 0.0, radii[0]
    for r in radii:
        if r * step > reach:  # (a block four times as far: the work stays that of the last)
            reach = min(4 * r * step, radii[-1] * step)
            values, dist = around(reach)
        inner, outer = np.searchsorted(dist, [r, r * step], side="right")
        if inner < MIN_SAMPLES:  # (no spread yet: slices far thicker than the pixels)
            continue
        model = IntensityModel.from_samples(values[:inner], image_range, min_sigma_fraction)
        if base is None and _bounded_within(values[:inner], dist[:inner], core_fraction * r,
                                            image_range, min_sigma_fraction, shell_spreads):
            return r
        base = model.sigma if base is None else base
        if model.sigma > spread_growth * base:
            return last
        shell = values[inner:outer]
        if shell.size and abs(float(np.median(shell)) - model.mu) > shell_spreads * model.sigma:
            return r
        last = r
    return radii[-1]


def _bounded_within(values: NDArray, dist: NDArray, core_mm: float, image_range: float,
                    min_sigma_fraction: float, shell_spreads: float) -> bool:
    """Whether a boundary already lies within the smallest ball: the median of its voxels beyond
    its core (the voxels within ``core_mm``, its radius's ``core_fraction``, or the nearest
    :data:`MIN_SAMPLES` if that holds fewer: the fewest a spread is read from) lies more than
    ``shell_spreads`` of the core's spreads from the core's. An object about as small as the
    smallest ball (a nodule of a few voxels' radius) then fills its core but not the rest, and
    the ball's own spread, its background mixed in, would hide every boundary beyond it.
    (``values`` nearest first, ``dist`` their distances.)"""
    k = max(int(np.searchsorted(dist, core_mm, side="right")), MIN_SAMPLES)
    if k >= values.size:
        return False
    core = IntensityModel.from_samples(values[:k], image_range, min_sigma_fraction)
    return abs(float(np.median(values[k:])) - core.mu) > shell_spreads * core.sigma
