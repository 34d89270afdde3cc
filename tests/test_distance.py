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


@pytest.mark.parametrize("shape", [(1, 9, 8), (2, 9, 8), (9, 2, 1), (2, 2, 2), (7, 1, 2)])
def test_distance_within_on_thin_grids_and_in_any_memory_order(shape):
    # Axes of one or two voxels (a pass along a one-voxel axis is skipped; along two it is not),
    # and a mask in Fortran order (the kernel reads C order: it is copied).
    rng = np.random.default_rng(5)
    sp = (0.7, 1.1, 2.0)
    mask = rng.random(shape) < 0.15
    mask.flat[0] = True
    ref = ndimage.distance_transform_edt(~mask, sampling=sp)
    for m in (mask, np.asfortranarray(mask)):
        got = distance.distance_within(m, sp, 3.0)
        near = ref <= 3.0
        assert np.allclose(got[near], ref[near], rtol=1e-6, atol=1e-5)
        assert np.all(np.isinf(got[~near]))


def _shifted_minima(d2, sp):
    # The squared distance's passes as numpy's shifted minima over every offset along each axis
    # (what distance_within computed before its compiled envelope): the reference, to the bit.
    for axis, s in enumerate(sp):
        out = d2.copy()
        n = d2.shape[axis]
        for a in range(1, n):
            cost = np.float32((a * s) ** 2)
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(0, n - a), slice(a, n)
            np.minimum(out[tuple(lo)], d2[tuple(hi)] + cost, out=out[tuple(lo)])
            np.minimum(out[tuple(hi)], d2[tuple(lo)] + cost, out=out[tuple(hi)])
        d2 = out
    return d2


@pytest.mark.parametrize("shape, sp", [((21, 17, 13), (1.0, 1.0, 1.0)),
                                       ((19, 23, 11), (0.6, 0.7, 2.5)),
                                       ((1, 30, 9), (0.8, 1.3, 1.1))])
def test_the_compiled_envelope_gives_the_shifted_minima_to_float32_rounding(shape, sp):
    # Felzenszwalb and Huttenlocher's envelope picks the lowest parabola by breakpoints in double:
    # where two tie to within rounding it may take the other, one unit in the last place apart;
    # everywhere else the very numbers. Lines without a mask voxel stay inf (the first pass's
    # lines through the last axis' first plane hold none).
    from segsnake._distance import envelope

    rng = np.random.default_rng(3)
    mask = rng.random(shape) < 0.03
    mask[:, :, 0] = False
    assert mask.any()
    d2 = np.where(mask, np.float32(0.0), np.float32(np.inf))
    want = _shifted_minima(d2, sp)
    got = d2
    for axis, s in enumerate(sp):
        out = np.empty_like(got)
        lines = got.size // shape[axis]
        envelope(got, out, shape, axis, s, 0, lines)
        got = out
    finite = np.isfinite(want)
    assert np.array_equal(finite, np.isfinite(got))
    np.testing.assert_array_max_ulp(got[finite], want[finite], maxulp=1)
    assert np.mean(got[finite] == want[finite]) > 0.99


def test_the_compiled_envelope_refuses_what_it_cannot_read():
    from segsnake._distance import envelope

    a = np.zeros((4, 5, 6), np.float32)
    with pytest.raises(ValueError, match="shares memory"):
        envelope(a, a, a.shape, 0, 1.0, 0, 30)
    with pytest.raises(ValueError, match="lines"):
        envelope(a, np.empty_like(a), a.shape, 0, 1.0, 0, 31)
    with pytest.raises(ValueError, match="float32"):
        envelope(a.astype(np.float64), np.empty_like(a), a.shape, 0, 1.0, 0, 30)
    with pytest.raises(ValueError, match="axis"):
        envelope(a, np.empty_like(a), a.shape, 3, 1.0, 0, 30)
    with pytest.raises(ValueError, match="too many voxels"):  # (a product that would wrap)
        envelope(a, np.empty_like(a), (3, 2, 3074457345618258603), 1, 1.0, 0, 1)
