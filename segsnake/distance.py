"""Euclidean distance maps (mm) on anisotropic grids.

ITK's Maurer distance transform (through SimpleITK): exact like
``scipy.ndimage.distance_transform_edt`` (to float32 rounding), linear time, multithreaded, and
without the three int32 index volumes scipy's feature transform builds (measured on a
181 x 217 x 181 grid: 0.15 s on 2 threads against 0.9 s). Below :data:`ITK_MIN_VOXELS` scipy's
transform is used: importing SimpleITK (0.2 s) costs more than it saves there (64^3: 0.03 s).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.parallel import threads

__all__ = ["distance_to", "ITK_MIN_VOXELS"]

ITK_MIN_VOXELS = 1 << 21


def distance_to(mask: NDArray[np.bool_], spacing: Sequence[float]) -> NDArray[np.float32]:
    """Distance in mm from every voxel centre to the nearest voxel of ``mask`` (0 on it).

    Parameters
    ----------
    mask : bool ndarray, 3D
        The voxels distances are measured to; with none, every distance is ``inf``.
    spacing : sequence of 3 float
        Voxel size in mm along the array axes.
    """
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return np.full(mask.shape, np.inf, dtype=np.float32)
    if mask.size < ITK_MIN_VOXELS:
        from scipy import ndimage

        return ndimage.distance_transform_edt(~mask, sampling=spacing).astype(np.float32)
    import SimpleITK as sitk

    # SimpleITK reads the array's last axis as its x: the spacing goes in reversed.
    image = sitk.GetImageFromArray(mask.view(np.uint8))
    image.SetSpacing([float(s) for s in reversed(tuple(spacing))])
    dist = sitk.SignedMaurerDistanceMapImageFilter()
    dist.SetUseImageSpacing(True)
    dist.SetSquaredDistance(False)
    dist.SetInsideIsPositive(False)  # outside the mask (where we measure) positive
    dist.SetNumberOfThreads(threads())
    out = sitk.GetArrayFromImage(dist.Execute(image))
    # Inside the mask Maurer measures to the mask's own border (negative): those voxels are on it.
    return np.maximum(out, np.float32(0.0), out=out)
