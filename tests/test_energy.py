"""Flux energy: divergence theorem on analytic fields, exact gradient vs finite differences."""

import numpy as np
import pytest
from conftest import central_difference_gradient

from segsnake.energy import FluxTerm, SumEnergy
from segsnake.optimize import minimize_energy
from segsnake.surfaces import CylinderModel, SphereModel


class AnalyticSampler:
    """G(x, y, z) = integral_{-inf}^x h, for h given in closed form (test stand-in for Lookup)."""

    def __init__(self, kind, center=(0.0, 0.0, 0.0), s=3.0):
        self.kind, self.c, self.s = kind, np.asarray(center, float), s

    def sample(self, p):
        if self.kind == "volume":  # h = 1
            return p[:, 0].copy(), np.tile([1.0, 0.0, 0.0], (len(p), 1))
        # h = exp(-|p-c|^2 / (2 s^2)) integrated along x (erf), a smooth blob
        from scipy.special import erf

        d = p - self.c
        s = self.s
        ryz = np.exp(-(d[:, 1] ** 2 + d[:, 2] ** 2) / (2 * s * s))
        gx = s * np.sqrt(np.pi / 2) * (1 + erf(d[:, 0] / (np.sqrt(2) * s)))
        G = gx * ryz
        dG = np.stack([np.exp(-d[:, 0] ** 2 / (2 * s * s)) * ryz,
                       -d[:, 1] / (s * s) * G, -d[:, 2] / (s * s) * G], axis=1)
        return G, dG


def _perturbed(model, seed, amp=0.1):
    rng = np.random.default_rng(seed)
    return model.with_params(model.params + amp * rng.normal(size=model.params.shape))


@pytest.mark.parametrize("model", [SphereModel.ellipsoid([1, 2, 3], [2, 3, 4], m1=6, m2=5),
                                   CylinderModel.from_axis([0, 0, 0], [0, 0, 4], 1.5, m1=6, m2=3),
                                   CylinderModel.from_axis([1, 2, 3], [1, 9, 3], 2.0)])
def test_flux_of_unit_field_is_the_volume(model):
    # h = 1: the flux of (x, 0, 0) through the closed surface is the enclosed volume. For a
    # cylinder along y or z the caps have n_x = 0, so the lateral flux is the capped volume.
    term = FluxTerm(model, AnalyticSampler("volume"), order=6)
    value, _ = term.value_and_grad(model.params)
    assert abs(value - model.volume()) < 1e-9
    assert abs(FluxTerm(model.reversed(), AnalyticSampler("volume"), order=6)
               .value_and_grad(model.reversed().params)[0] + model.volume()) < 1e-9


def test_flux_of_gaussian_blob_matches_volume_integral():
    # A sphere of radius R around the blob centre: integral of exp(-r^2/2s^2) over the ball.
    from scipy.special import erf

    R, s = 4.0, 1.5
    model = SphereModel.ellipsoid([0.3, -0.2, 0.1], [R, R, R], m1=12, m2=12)
    term = FluxTerm(model, AnalyticSampler("blob", center=(0.3, -0.2, 0.1), s=s), order=8)
    value, _ = term.value_and_grad(model.params)
    a = R / (np.sqrt(2) * s)
    exact = (2 * np.pi * s * s) ** 1.5 * (erf(a) - 2 * a / np.sqrt(np.pi) * np.exp(-a * a))
    assert abs(value - exact) / exact < 1e-6


@pytest.mark.parametrize("make", [lambda: SphereModel.unit(5, 4), lambda: SphereModel.unit(9, 9),
                                  lambda: SphereModel.unit(12, 7),
                                  lambda: CylinderModel.unit(6, 3), lambda: CylinderModel.unit(9, 5),
                                  lambda: CylinderModel.from_axis([0.1, 0, 0], [0.5, 0.3, 0.6], 0.3,
                                                                  m1=6, m2=3)])  # oblique: gradient only
@pytest.mark.parametrize("seed", [0, 1])
def test_gradient_matches_central_differences(make, seed):
    base = make()
    model = _perturbed(base.transformed(np.diag([3.0, 2.5, 4.0]), [0.5, 0.2, -0.3]), seed, 0.2)
    energy = SumEnergy([FluxTerm(model, AnalyticSampler("blob", s=2.0), weight=-1.0),
                        FluxTerm(model, AnalyticSampler("volume"), weight=0.01)])
    _, grad = energy.value_and_grad(model.params)
    fd = central_difference_gradient(energy, model.params)
    rel = np.linalg.norm(grad - fd) / np.linalg.norm(fd)
    assert rel < 1e-5


def test_minimizing_blob_flux_grows_sphere_to_the_laplacian_zero_crossing():
    # E = -integral_V (h - h0): the optimum sphere is where h = h0 on the surface, r* = s sqrt(2 ln(1/h0)).
    s, h0 = 2.0, 0.3

    class Shifted(AnalyticSampler):
        def sample(self, p):
            G, dG = super().sample(p)
            return G - h0 * p[:, 0], dG - np.array([h0, 0, 0])

    model = SphereModel.ellipsoid([0, 0, 0], [1.0, 1.2, 0.8], m1=6, m2=6)
    res = minimize_energy(model, FluxTerm(model, Shifted("blob", s=s), weight=-1.0), tol=1e-5)
    r_star = s * np.sqrt(2 * np.log(1 / h0))
    sig, _, _ = res.model.evaluate(np.linspace(0, 1, 20), np.linspace(0, 1, 20))
    assert np.abs(np.linalg.norm(sig, axis=-1) - r_star).max() < 0.02


class _LevelBlob(AnalyticSampler):
    """The blob minus a level h0: the optimum sphere is the blob's h = h0 level set."""

    def sample(self, p):
        G, dG = super().sample(p)
        return G - 0.3 * p[:, 0], dG - np.array([0.3, 0, 0])


def test_stationarity_is_the_first_order_decrease_and_a_restart_at_it_takes_no_step():
    from scipy.linalg import cho_factor, cho_solve

    from segsnake.optimize import _DisplacementOperator, stationarity, surface_metric

    model = SphereModel.ellipsoid([0, 0, 0], [1.0, 1.2, 0.8], m1=6, m2=6)
    energy = FluxTerm(model, _LevelBlob("blob", s=2.0), weight=-1.0)
    # The number is the relative decrease of a step_mm move along -M^-1 g, to first order.
    f, g = energy.value_and_grad(model.params)
    d = -cho_solve(cho_factor(surface_metric(model)), g)
    step = 1e-4
    d *= step / np.max(np.linalg.norm(_DisplacementOperator(model) @ d, axis=1))
    decrease = (f - energy.value_and_grad(model.params + d)[0]) / abs(f)
    assert abs(stationarity(model, f, g, step) - decrease) < 1e-3 * decrease
    # Minimized to stationarity, restarted at its end: no step, the same energy to the bit.
    res = minimize_energy(model, energy, tol=1e-5, stationary_tol=1e-5)
    assert res.message.startswith("stationary") and res.stationarity <= 1e-5
    again = minimize_energy(res.model, energy, tol=1e-5, stationary_tol=1e-5)
    assert again.iterations == 0 and again.energy == res.energy
    assert np.array_equal(again.model.params, res.model.params)
    # The relative-change rule alone needs `window` iterations before it can stop, and moves.
    plain = minimize_energy(res.model, energy, tol=1e-5)
    assert plain.iterations >= 5 and not np.array_equal(plain.model.params, res.model.params)


def test_an_iteration_that_finds_no_admissible_step_is_not_counted():
    # Every shape away from the start refused: the minimization ends where it started, after
    # no step (a restart from a surface at rest among refused shapes reports 0 iterations,
    # as one from a stationary surface does).
    model = SphereModel.ellipsoid([0, 0, 0], [1.0, 1.2, 0.8], m1=6, m2=6)
    energy = FluxTerm(model, _LevelBlob("blob", s=2.0), weight=-1.0)
    start = model.params.copy()
    res = minimize_energy(model, energy, tol=1e-5, stationary_tol=1e-9,
                          admissible=lambda x: np.array_equal(x, start))
    assert res.message == "no further admissible decrease"
    assert res.iterations == 0 and np.array_equal(res.model.params, start)
    # ... and one held within a small box ends at its face: every iteration counted took a step
    # (the history holds the start and each accepted step's energy)
    boxed = minimize_energy(model, energy, tol=0.0, step_tol_mm=0.0,
                            admissible=lambda x: np.abs(x - start).max() <= 0.05)
    assert boxed.message == "no further admissible decrease"
    assert boxed.iterations >= 1 and boxed.iterations == len(boxed.history) - 1


def test_axial_tension_is_the_distance_between_the_end_rings_centres():
    from segsnake.energy import AxialTension

    model = CylinderModel.from_axis([1, 2, 3], [9, 4, 2], 2.0, m1=6, m2=3)
    model = _perturbed(model, 4, 0.2)
    term = AxialTension(model, weight=0.7)
    value, grad = term.value_and_grad(model.params)
    r0, r1 = model.end_rings(4000)  # the rings' mean points by dense sampling
    assert abs(value - 0.7 * np.linalg.norm(r1.mean(axis=0) - r0.mean(axis=0))) < 1e-9
    fd = central_difference_gradient(term, model.params)
    assert np.linalg.norm(grad - fd) / np.linalg.norm(fd) < 1e-6
    # A pull along the axis only: scaling the tube scales it, widening alone costs nothing.
    assert abs(term.value_and_grad(model.transformed(1.3 * np.eye(3)).params)[0]
               - 1.3 * value) < 1e-9
    a = (r1.mean(axis=0) - r0.mean(axis=0)) / np.linalg.norm(r1.mean(axis=0) - r0.mean(axis=0))
    widen = np.eye(3) + 0.5 * (np.eye(3) - np.outer(a, a))  # stretch across the axis only
    c = r0.mean(axis=0)
    assert abs(term.value_and_grad(model.transformed(widen, c - widen @ c).params)[0]
               - value) < 1e-9


def test_axial_tension_lets_go_where_an_end_ring_reaches_past_the_field_of_view():
    from segsnake.energy import AxialTension

    # A straight tube along x, radius 2: its end rings reach 2 mm along y and z, none along x.
    tube = CylinderModel.from_axis([0, 0, 0], [10, 0, 0], 2.0, m1=8, m2=3)
    far = 50.0
    # The volume ends at x = 6: the axis is pulled on from 0 to 6 only.
    cut = AxialTension(tube, weight=0.7, box=(np.array([-far, -far, -far]),
                                              np.array([6.0, far, far])))
    assert abs(cut.value_and_grad(tube.params)[0] - 0.7 * 6.0) < 1e-9
    # A face 1.5 mm from the axis: every ring reaches past it, nothing is pulled on.
    grazed = AxialTension(tube, weight=0.7, box=(np.array([-far, -1.5, -far]), np.full(3, far)))
    value, grad = grazed.value_and_grad(tube.params)
    assert value == 0.0 and not grad.any()
    # A slab thinner than an oblique tube's rings: no ring is ever wholly inside.
    oblique = CylinderModel.from_axis([0, 0, 0], [10, 0, 3], 2.0, m1=8, m2=3)
    slab = AxialTension(oblique, weight=0.7, box=(np.array([-far, -far, 0.5]),
                                                  np.array([far, far, 2.5])))
    value, grad = slab.value_and_grad(oblique.params)
    assert value == 0.0 and not grad.any()
    # Far from every face it is the whole pull, value and gradient.
    model = _perturbed(CylinderModel.from_axis([1, 2, 3], [9, 4, 2], 2.0, m1=6, m2=3), 4, 0.2)
    whole = AxialTension(model, weight=0.7)
    inside = AxialTension(model, weight=0.7, box=(np.full(3, -far), np.full(3, far)))
    assert np.allclose(inside.value_and_grad(model.params)[1],
                       whole.value_and_grad(model.params)[1], rtol=1e-12, atol=1e-12)
    # Cut by one face, then by two, the gradient is the clipped length's.
    for lo_x, hi_x in ((-far, 8.0), (3.0, 8.0)):
        term = AxialTension(model, weight=0.7, box=(np.array([lo_x, -far, -far]),
                                                    np.array([hi_x, far, far])))
        value, grad = term.value_and_grad(model.params)
        assert 0 < value < whole.value_and_grad(model.params)[0]
        fd = central_difference_gradient(term, model.params)
        assert np.linalg.norm(grad - fd) / np.linalg.norm(fd) < 1e-6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_closed_cylinder_flux_is_the_capped_volume_in_any_orientation(seed):
    # Oblique, bent and uneven: the lateral surface alone misses its caps' flux (the open
    # tube's value differs by far more than the tolerance); with the caps it is the volume.
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    model = _perturbed(CylinderModel.from_axis([0.5, -1.0, 2.0], 6 * axis / np.linalg.norm(axis),
                                               1.7, m1=7, m2=4), seed, 0.2)
    closed = FluxTerm(model, AnalyticSampler("volume"), order=8, closed=True)
    open_ = FluxTerm(model, AnalyticSampler("volume"), order=8)
    volume = model.volume(order=8)
    assert closed.value_and_grad(model.params)[0] == pytest.approx(volume, rel=1e-9)
    assert abs(open_.value_and_grad(model.params)[0] - volume) > 1e-2 * volume
    # traversed the other way round, the closed surface faces inwards: minus the volume
    rev = model.reversed()
    assert FluxTerm(rev, AnalyticSampler("volume"), order=8, closed=True).value_and_grad(
        rev.params)[0] == pytest.approx(-volume, rel=1e-9)


@pytest.mark.parametrize("model", [
    SphereModel.ellipsoid([1.0, 0.5, 1.5], [2.0, 3.0, 2.5], m1=7, m2=6),
    CylinderModel.from_axis([0.3, 0.2, -0.4], [2.0, 1.5, 3.0], 1.2, m1=6, m2=3)])
def test_value_alone_is_the_value_of_value_and_grad_to_the_last_bit(model):
    # (the quadrature check compares energies only: the same numbers, without the gradient)
    model = _perturbed(model, 3, 0.2)
    sampler = AnalyticSampler("blob", center=(1.0, 0.8, 1.0), s=1.5)
    for order in (4, (7, 5)):
        term = FluxTerm(model, sampler, weight=-0.7, order=order, closed=True)
        assert term.value(model.params) == term.value_and_grad(model.params)[0]
        assert term.value(model.params) != 0.0


def _numpy_integrand(G, dG, su, sv, weights, orientation):
    # flux_integrand_grads as numpy wrote it before it was compiled (segsnake/_flux.c)
    o = float(orientation)
    nx = o * (sv[..., 1] * su[..., 2] - sv[..., 2] * su[..., 1])
    wG = weights * G * o
    zero = np.zeros_like(wG)
    return (float(np.sum(weights * G * nx)), (weights * nx)[..., None] * dG,
            np.stack([zero, -wG * sv[..., 2], wG * sv[..., 1]], axis=-1),
            np.stack([zero, wG * su[..., 2], -wG * su[..., 1]], axis=-1))


@pytest.mark.parametrize("orientation", [1, -1])
def test_compiled_integrand_is_numpys_to_the_last_bit(orientation):
    from segsnake.energy import flux_integrand_grads, flux_value

    rng = np.random.default_rng(7)
    grid = (37, 23)
    G = rng.normal(size=grid) * 1e3
    dG, su, sv = (rng.normal(size=(*grid, 3)) * 10.0 ** rng.integers(-3, 4, size=(*grid, 3))
                  for _ in range(3))
    weights = rng.random(grid[0])[:, None] * rng.random(grid[1])[None, :]
    # (strided inputs, as a cap's broadcast tangents are, are read as numpy reads them)
    sv_strided = np.broadcast_to(sv[:, :1], sv.shape)
    for a, b in ((su, sv), (su, sv_strided)):
        expected = _numpy_integrand(G, dG, a, b, weights, orientation)
        got = flux_integrand_grads(G, dG, a, b, weights, orientation)
        assert got[0] == expected[0] == flux_value(G, a, b, weights, orientation)[0]
        for x, y in zip(got[1:], expected[1:]):
            assert x.shape == y.shape and np.array_equal(x, y)
    # inputs that broadcast together (one tangent row for all), and a transposed layout: the
    # same products, summed in C order as flux_value sums them
    got = flux_integrand_grads(G, dG, su[:1], sv, weights, orientation)
    expected = _numpy_integrand(G, dG, np.broadcast_to(su[:1], su.shape), sv, weights,
                                orientation)
    assert all(np.array_equal(x, y) for x, y in zip(got[1:], expected[1:]))
    Gt, dGt, sut, svt = (np.asfortranarray(a) for a in (G, dG, su, sv))
    assert flux_integrand_grads(Gt, dGt, sut, svt, weights, orientation)[0] == \
        flux_value(Gt, sut, svt, weights, orientation)[0]


def test_compiled_integrand_refuses_wrong_sizes_and_overlapping_outputs():
    from segsnake._flux import integrand

    n = 5
    G, W, term = np.ones(n), np.ones(n), np.empty(n)
    dG, su, sv = np.ones((n, 3)), np.ones((n, 3)), np.ones((n, 3))
    g, gu, gv = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    with pytest.raises(ValueError, match="dG"):
        integrand(G, dG[:4], su, sv, W, 1.0, term, g, gu, gv)
    with pytest.raises(ValueError, match="g_u_out"):
        integrand(G, dG, su, sv, W, 1.0, term, g, gu.astype(np.float32), gv)
    with pytest.raises(ValueError, match="g_sigma_out overlaps su"):
        integrand(G, dG, su, sv, W, 1.0, term, su, gu, gv)
    with pytest.raises(ValueError, match="term_out overlaps g_v_out"):
        block = np.empty(4 * n)  # (g_v_out's first value is term_out's last)
        integrand(G, dG, su, sv, W, 1.0, block[:n], g, gu, block[n - 1:4 * n - 1].reshape(n, 3))
    with pytest.raises(ValueError):  # (read-only output)
        ro = np.empty(n)
        ro.flags.writeable = False
        integrand(G, dG, su, sv, W, 1.0, ro, g, gu, gv)
    integrand(G, dG, su, sv, W, -1.0, term, g, gu, gv)
    # (n_x = 0 for parallel tangents; W G o = -1)
    assert np.all(term == 0.0) and np.all(g == 0.0)
    assert np.all(gu == [0.0, 1.0, -1.0]) and np.all(gv == [0.0, -1.0, 1.0])


def test_the_basis_gives_contiguous_tangents_and_its_stacked_adjoint_is_the_adjoint():
    model = _perturbed(SphereModel.ellipsoid([1.0, 0.5, 1.5], [2.0, 3.0, 2.5], m1=7, m2=6),
                       4, 0.2)
    basis, _ = model.quadrature((5, 3))
    s, su, sv = basis.evaluate(model.control_points())
    assert all(x.flags.c_contiguous and x.shape == (35, 18, 3) for x in (s, su, sv))
    rng = np.random.default_rng(3)
    g, g_u, g_v = (rng.normal(size=s.shape) for _ in range(3))
    stacked = basis.adjoint_stacked(np.stack([g, g_u]), g_v)
    assert np.array_equal(stacked, basis.adjoint(g, g_u, g_v))
    # the transpose of evaluate: <evaluate(C), (g, g_u, g_v)> = <C, adjoint(g, g_u, g_v)>
    C = rng.normal(size=model.control_points().shape)
    lhs = sum(np.vdot(a, b) for a, b in zip(basis.evaluate(C), (g, g_u, g_v)))
    assert np.vdot(C, stacked) == pytest.approx(lhs, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_closed_cylinder_gradient_matches_central_differences(seed):
    model = _perturbed(CylinderModel.from_axis([0.3, 0.2, -0.4], [2.0, 1.5, 3.0], 1.2, m1=6,
                                               m2=3), seed, 0.2)
    energy = FluxTerm(model, AnalyticSampler("blob", center=(1.0, 0.8, 1.0), s=1.5), order=6,
                      closed=True)
    _, grad = energy.value_and_grad(model.params)
    fd = central_difference_gradient(energy, model.params)
    assert np.linalg.norm(grad - fd) / np.linalg.norm(fd) < 1e-5


def test_ring_barrier_is_zero_until_a_ring_narrows_past_its_floor_and_exact():
    from segsnake.energy import RingBarrier

    tube = CylinderModel.from_axis([0, 0, 0], [0, 0, 30], 4.0, m1=8, m2=4)
    barrier = RingBarrier(tube, tube.params, weight=2.0)

    def narrowed(factor):  # control row 1 scaled about its centre
        g = tube.params.reshape(8, 7, 3).copy()
        centre = g[:, 1].mean(axis=0)
        g[:, 1] = centre + factor * (g[:, 1] - centre)
        return g.reshape(-1, 3)

    assert barrier.value_and_grad(tube.params)[0] == 0.0
    assert barrier.value_and_grad(narrowed(0.6))[0] == 0.0  # narrower, above a tenth of its area
    pinched = narrowed(0.2)
    value, grad = barrier.value_and_grad(pinched)
    assert value > 1.0
    fd = central_difference_gradient(barrier, pinched)
    assert np.linalg.norm(grad - fd) / np.linalg.norm(fd) < 1e-6
    # descending the barrier opens the ring
    opened = pinched - 1e-3 * grad
    assert barrier.value_and_grad(opened)[0] < value
    assert barrier.value_and_grad(narrowed(0.0))[0] > 1e6  # pinched shut: without bound


@pytest.mark.parametrize("model", [SphereModel.ellipsoid([1, 2, 3], [4.0, 5.0, 6.0], m1=9, m2=9),
                                   CylinderModel.from_axis([0, 0, 0], [3, 4, 30], 5.0, m1=13,
                                                           m2=11)])
def test_the_displacement_operator_is_the_surface_moved_by_a_parameter_change(model):
    # op @ d is sigma(params + d) - sigma(params) on the grid of four samples per knot interval
    # (sigma is linear in the parameters), whatever the pole constraints.
    from segsnake.optimize import _DisplacementOperator

    d = np.random.default_rng(3).normal(size=model.params.shape)
    u = (np.arange(4 * model.m1) + 0.5) / (4 * model.m1)
    v = np.linspace(0.0, 1.0, 4 * model.m2 + 1)
    moved = model.with_params(model.params + d).evaluate(u, v)[0] - model.evaluate(u, v)[0]
    np.testing.assert_allclose(_DisplacementOperator(model) @ d, moved.reshape(-1, 3),
                               atol=1e-12)


def test_crossing_penalty_is_zero_when_embedded_and_its_gradient_undoes_a_crossing():
    from segsnake.energy import CrossingPenalty
    from segsnake.rasterize import crossing_volume

    ball = SphereModel.ellipsoid((20, 20, 20), (10, 10, 10))
    penalty = CrossingPenalty(ball, weight=2.0, order=8)
    value, grad = penalty.value_and_grad(ball.params)
    assert value == 0.0 and not grad.any()
    # Its control points beyond x = 25 moved 25 mm to -x: that cap passes through the far side.
    crossed = ball.params.copy()
    crossed[crossed[:, 0] > 25, 0] -= 25.0
    value, grad = penalty.value_and_grad(crossed)
    assert value == pytest.approx(2.0 * crossing_volume(ball.with_params(crossed)))
    assert value > 2.0 * 1000  # mm^3
    # The gradient is the shape derivative: the slope of the crossing volume along random
    # directions (fitted over +-0.3 mm: the measured volume has ray noise of ~1 mm^3), to the
    # accuracy of the measuring mesh (measured: 2-30 %, 1-10 % on a mesh 3 x finer).
    rng = np.random.default_rng(1)
    for _ in range(4):
        d = rng.normal(size=crossed.shape)
        t = np.linspace(-0.3, 0.3, 13)
        slope = np.polyfit(t, [penalty.value_and_grad(crossed + ti * d)[0] for ti in t], 1)[0]
        assert slope == pytest.approx(np.sum(grad * d), rel=0.35, abs=30.0)
    # A step against it removes crossing volume at the rate it predicts.
    unit = grad / np.linalg.norm(grad)
    drop = value - penalty.value_and_grad(crossed - 1.0 * unit)[0]
    assert drop == pytest.approx(np.linalg.norm(grad), rel=0.2)


def test_minimizing_the_crossing_penalty_alone_undoes_a_crossing():
    from segsnake.energy import CrossingPenalty
    from segsnake.rasterize import crossing_volume

    ball = SphereModel.ellipsoid((20, 20, 20), (10, 10, 10))
    crossed = ball.params.copy()
    crossed[crossed[:, 0] > 25, 0] -= 25.0  # one cap through the far side: turned inside out
    start = ball.with_params(crossed)
    assert start.volume(order=8) < 0 and crossing_volume(start) > 1000.0
    res = minimize_energy(start, CrossingPenalty(start, weight=2.0), max_iter=100)
    # (measured: 1871 -> 6 mm^3 in 10 iterations, the volume -1617 -> +1502 mm^3)
    assert crossing_volume(res.model) < 0.01 * crossing_volume(start)
    assert res.model.volume(order=8) > 1000.0
