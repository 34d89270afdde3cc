"""Generator identities: interpolation, partition of unity, trigonometric reproduction, derivatives."""

import numpy as np
import pytest

from segsnake.basis import keys, phi, phi_periodic, phi_prime_at_one

MS = [3, 4, 5, 9, 20, 50, 200, 400]


@pytest.mark.parametrize("M", MS)
def test_phi_interpolates_and_has_compact_support(M):
    t = np.array([-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 2.5])
    np.testing.assert_allclose(phi(t, M), [0, 0, 0, 1, 0, 0, 0], atol=1e-14)
    x = np.linspace(-1.99, 1.99, 401)
    np.testing.assert_allclose(phi(x, M), phi(-x, M), atol=1e-15)  # even


@pytest.mark.parametrize("M", MS)
def test_phi_reproduces_constant_cos_sin(M):
    x = np.linspace(0.0, 7.0, 1401)
    k = np.arange(-3, 11)
    B = phi(x[:, None] - k[None, :], M)
    w = 2 * np.pi / M
    assert np.abs(B.sum(axis=1) - 1).max() < 1e-13
    assert np.abs(B @ np.cos(w * k) - np.cos(w * x)).max() < 1e-13
    assert np.abs(B @ np.sin(w * k) - np.sin(w * x)).max() < 1e-13
    # Derivatives of the reproduced sinusoid, away from knots for the second one (C1 only).
    dB = phi(x[:, None] - k[None, :], M, 1)
    assert np.abs(dB @ np.sin(w * k) - w * np.cos(w * x)).max() < 1e-13
    xm = x[np.abs(x - np.round(x)) > 1e-3]
    d2B = phi(xm[:, None] - k[None, :], M, 2)
    assert np.abs(d2B @ np.cos(w * k) + w * w * np.cos(w * xm)).max() < 1e-12


@pytest.mark.parametrize("M", [4, 9, 50])
def test_phi_derivatives_match_finite_differences(M):
    t = np.linspace(-1.95, 1.95, 157) + 1e-3  # avoid the knots, where phi'' jumps
    h = 1e-6
    np.testing.assert_allclose((phi(t + h, M) - phi(t - h, M)) / (2 * h), phi(t, M, 1), atol=1e-8)
    np.testing.assert_allclose((phi(t + h, M, 1) - phi(t - h, M, 1)) / (2 * h), phi(t, M, 2),
                               atol=1e-7)


@pytest.mark.parametrize("M", [4, 9, 50])
def test_phi_is_c1_at_knots(M):
    for knot in (-1.0, 0.0, 1.0):
        left, right = phi(np.array([knot - 1e-12, knot + 1e-12]), M, 1)
        assert abs(left - right) < 1e-9


def test_phi_prime_at_one_matches_exact_sphere_pole_scale():
    # For the exact unit sphere c[k,-1] - c[k,1] = -2 sin(pi/M2) (cos, sin, 0) must equal
    # (pi, 0, 0) cos / (M2 phi'_{2M2}(1)), i.e. phi'_{2M2}(1) = -pi / (2 M2 sin(pi/M2)).
    for m2 in (2, 4, 9, 50):
        assert abs(phi_prime_at_one(2 * m2) + np.pi / (2 * m2 * np.sin(np.pi / m2))) < 1e-12


def test_periodic_generator_sums_to_one_and_wraps():
    M = 6
    u = np.linspace(0, 1, 50, endpoint=False)
    t = M * u[:, None] - np.arange(M)[None, :]
    np.testing.assert_allclose(phi_periodic(t, M, M).sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(phi_periodic(t + M, M, M), phi_periodic(t, M, M), atol=1e-15)
    with pytest.raises(ValueError):
        phi_periodic(t, 3, 3)


def test_keys_interpolates_reproduces_quadratics_and_derivatives():
    x = np.linspace(0.0, 6.0, 601)
    k = np.arange(-3, 10)
    B = keys(x[:, None] - k[None, :])
    for poly in (lambda s: np.ones_like(s), lambda s: s, lambda s: s * s - 2 * s):
        assert np.abs(B @ poly(k.astype(float)) - poly(x)).max() < 1e-12
    np.testing.assert_allclose(keys(np.array([0.0, 1.0, -1.0, 2.0])), [1, 0, 0, 0], atol=1e-15)
    t = np.linspace(-1.9, 1.9, 77) + 1e-3
    h = 1e-6
    np.testing.assert_allclose((keys(t + h) - keys(t - h)) / (2 * h), keys(t, 1), atol=1e-8)
    np.testing.assert_allclose((keys(t + h, 1) - keys(t - h, 1)) / (2 * h), keys(t, 2), atol=1e-6)
