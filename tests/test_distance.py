"""Distance maps: ITK's and scipy's transforms agree with scipy's float64 reference."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from segsnake import distance
from segsnake.distance import distance_to


@pytest.mark.parametrize("itk", [False, True])
def test_distance_to_matches_scipy_on_anisotropic_grids(monkeypatch, itk):
    monkeypatch.setattr(distance, "ITK_MIN_VOXELS", 0 if itk else 1 << 40)
    rng = np.random.default_rng(9)
    for shape, sp in [((17, 23, 9), (0.7, 1.0, 2.5)), ((12, 1, 30), (1.0, 0.5, 0.8))]:
        mask = rng.random(shape) < 0.01
        mask[3, 0, 4] = True
        got = distance_to(mask, sp)
        ref = ndimage.distance_transform_edt(~mask, sampling=sp)
        assert got.dtype == np.float32 and got.shape == shape
        assert np.allclose(got, ref, rtol=1e-6, atol=1e-5)
        assert np.all(got[mask] == 0)
    assert np.all(np.isinf(distance_to(np.zeros((4, 5, 6), bool), (1, 1, 1))))
    assert np.all(distance_to(np.ones((4, 5, 6), bool), (1, 2, 3)) == 0)


def test_distance_within_is_the_exact_distance_up_to_its_bound():
    # The band transform: every distance up to max_mm as scipy's full transform gives it, inf
    # beyond, on anisotropic grids and with a bound between voxel steps.
    rng = np.random.default_rng(11)
    for shape, sp, bound in [((30, 26, 20), (1.0, 1.0, 1.0), 4.0),
                             ((40, 36, 14), (0.6, 0.7, 2.5), 4.0),
                             ((24, 24, 24), (0.8, 1.3, 1.1), 3.3)]:
        mask = ndimage.binary_dilation(rng.random(shape) < 0.002, iterations=2)
        ref = ndimage.distance_transform_edt(~mask, sampling=sp)
        got = distance.distance_within(mask, sp, bound)
        near = ref <= bound
        assert got.dtype == np.float32 and got.shape == shape
        assert np.allclose(got[near], ref[near], rtol=1e-6, atol=1e-5)
        assert np.all(np.isinf(got[~near]))
    assert np.all(np.isinf(distance.distance_within(np.zeros((5, 6, 7), bool), (1, 1, 1), 3.0)))
    assert np.all(distance.distance_within(np.ones((5, 6, 7), bool), (1, 2, 3), 3.0) == 0)
