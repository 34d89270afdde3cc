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
