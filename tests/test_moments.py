"""Mask moments from projections (segsnake.moments) against the voxels' coordinates."""

import numpy as np
import pytest
from scipy import ndimage

from segsnake.moments import mask_moments


def test_centroid_and_covariance_are_those_of_the_voxel_coordinates():
    rng = np.random.default_rng(8)
    mask = ndimage.gaussian_filter(rng.random((30, 40, 20)), 3) > 0.5
    sp = (0.7, 1.2, 2.0)
    idx = np.argwhere(mask).astype(float)
    centre, cov = mask_moments(mask, sp)
    assert centre == pytest.approx(idx.mean(axis=0), abs=1e-12)
    assert np.allclose(cov, np.cov((idx * sp).T), rtol=1e-12, atol=1e-9)
    assert mask_moments(mask)[0] == pytest.approx(ndimage.center_of_mass(mask), abs=1e-12)
    few = np.zeros((4, 4, 4), bool)
    few[1, 2, 3] = True
    assert np.array_equal(mask_moments(few)[0], [1, 2, 3]) and np.array_equal(mask_moments(few)[1],
                                                                               np.eye(3))
