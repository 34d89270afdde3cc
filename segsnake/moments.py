"""Moments of a voxel mask (centroid and covariance) from its projections (issue 18: no
coordinate lists, no full-size temporaries)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ["mask_moments"]


def mask_moments(mask: NDArray[np.bool_],
                 spacing: Sequence[float] = (1.0, 1.0, 1.0)) -> tuple[NDArray, NDArray]:
    """The centroid (voxel indices) and the covariance (mm^2, unbiased) of the voxels of a 3D
    ``mask``.

    From its projections on the axes and on the coordinate planes: no list of the voxels'
    coordinates (for a brain, three float64 copies of 1.6 million points) and no float64 copy
    of the volume (``scipy.ndimage.center_of_mass``). With three voxels or fewer the
    covariance is the identity (no spread to measure); an empty mask has its centroid at 0.
    """
    sp = np.asarray(spacing, dtype=np.float64)
    n = int(np.count_nonzero(mask))
    if n <= 3:
        return (np.argwhere(mask).mean(axis=0) if n else np.zeros(3)), np.eye(3)
    idx = [np.arange(k, dtype=np.float64) for k in mask.shape]
    pairs = {(0, 1): mask.sum(axis=2), (0, 2): mask.sum(axis=1), (1, 2): mask.sum(axis=0)}
    first = [pairs[(0, 1)].sum(axis=1), pairs[(0, 1)].sum(axis=0), pairs[(0, 2)].sum(axis=0)]
    mean = np.array([idx[a] @ first[a] for a in range(3)]) / n
    second = np.empty((3, 3))
    for a in range(3):
        second[a, a] = (idx[a] ** 2) @ first[a]
    for (a, b), counts in pairs.items():
        second[a, b] = second[b, a] = idx[a] @ counts @ idx[b]
    cov = (second - n * np.outer(mean, mean)) / (n - 1) * np.outer(sp, sp)
    return mean, cov
