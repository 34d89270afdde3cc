"""Priors that use a shape model's modes (issue 19, item 4)."""

import json

import numpy as np
import pytest
import scipy.optimize as opt

from segsnake.model_prior import ModePrior, RotationModePrior, build_prior, residual_variance
from segsnake.priors import AffinePrior, shape_space_columns, stack, unstack
from segsnake.procrustes import ProcrustesPrior
from segsnake.shapes import build_shape_model
from segsnake.surfaces import SphereModel

BASE = SphereModel.ellipsoid((20, 30, 25), (9, 7, 6), m1=6, m2=5)


def _deformation(k: int) -> np.ndarray:
    """Smooth displacement fields of the control points (radial bulges)."""
    rng = np.random.default_rng(100 + k)
    return rng.normal(size=BASE.params.shape) * np.r_[np.ones(BASE.n_params - 4), np.zeros(4)][:, None]


def _training(n=10, seed=0):
    rng = np.random.default_rng(seed)
    shapes = []
    for _ in range(n):
        a = rng.normal(size=3) * np.array([1.5, 0.8, 0.4])
        p = BASE.params + sum(a[k] * _deformation(k) for k in range(3))
        p = p + 0.02 * rng.normal(size=p.shape)
        A = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
        shapes.append(BASE.with_params(p).transformed(A, rng.normal(size=3)))
    return build_shape_model(shapes)


SM = _training()


def test_zero_modes_is_the_affine_prior_of_the_mean():
    snake = SM.mean.with_params(SM.mean.params + 0.3 * _deformation(5))
    ours = ModePrior(SM.mean, SM, weight=2.0, n_modes=0).value_and_grad(snake.params)
    ref = AffinePrior(SM.mean, SM.mean, weight=2.0).value_and_grad(snake.params)
    assert ours[0] == pytest.approx(ref[0], rel=1e-10)
    assert np.allclose(ours[1], ref[1], rtol=1e-8, atol=1e-10 * np.abs(ref[1]).max())


def test_energy_is_the_minimum_over_space_and_mode_coefficients():
    K = 2
    prior = ModePrior(SM.mean, SM, weight=1.0, n_modes=K)
    snake = SM.mean.with_params(SM.mean.params + 0.7 * _deformation(0) + 0.2 * _deformation(6))
    C = shape_space_columns(SM.mean, "affine")
    Xi = np.column_stack([stack(m) for m in SM.modes[:K]])
    rho2 = residual_variance(SM.variances, K)
    from segsnake.priors import param_gram
    import scipy.linalg as la

    Bf = la.block_diag(*[param_gram(SM.mean)] * 3)
    g = stack(snake.params)

    def objective(x):
        theta, c = x[:C.shape[1]], x[C.shape[1]:]
        r = g - C @ theta - Xi @ c
        return r @ Bf @ r + rho2 * np.sum(c * c / SM.variances[:K])

    x0 = np.zeros(C.shape[1] + K)
    x0[[0, 4, 8]] = 1.0
    best = opt.minimize(objective, x0, method="BFGS", options={"gtol": 1e-10}).fun
    assert prior.distance2(snake.params) == pytest.approx(best, rel=1e-6)
    # the first mode is cheap, a direction outside the model is not
    along = SM.mean.with_params(SM.mean.params + np.sqrt(SM.variances[0]) * SM.modes[0])
    outside = SM.mean.with_params(SM.mean.params + np.sqrt(SM.variances[0]) * unstack(
        np.linalg.qr(np.column_stack([Xi, stack(_deformation(7))]))[0][:, -1]
        * np.sqrt(3 * SM.mean.n_params)))
    assert prior.distance2(along.params) < 0.2 * ModePrior(SM.mean, SM, n_modes=0).distance2(along.params)
    assert prior.distance2(outside.params) > 10 * prior.distance2(along.params)


@pytest.mark.parametrize("space", ["affine", "linear", "scaling", "translation"])
def test_gradient_matches_central_differences(space):
    prior = ModePrior(SM.mean, SM, weight=0.7, space=space, n_modes=3)
    snake = SM.mean.with_params(SM.mean.params + 0.5 * _deformation(8) + 0.9 * _deformation(1))
    value, grad = prior.value_and_grad(snake.params)
    rng = np.random.default_rng(9)
    direction = rng.normal(size=grad.shape)
    h = 1e-5
    fd = (prior.value_and_grad(snake.params + h * direction)[0]
          - prior.value_and_grad(snake.params - h * direction)[0]) / (2 * h)
    assert value > 0 and fd == pytest.approx(np.sum(grad * direction), rel=1e-7)


@pytest.mark.parametrize("space", ["rigid", "similarity"])
def test_rotation_with_modes(space):
    from scipy.spatial.transform import Rotation

    prior = RotationModePrior(SM.mean, SM, weight=0.7, space=space, n_modes=2)
    R = Rotation.from_rotvec([0.4, -1.0, 2.0]).as_matrix()
    s = 1.0 if space == "rigid" else 1.3
    c = np.array([1.5, -0.4])
    shape = SM.mean.params + np.einsum("k,kpd->pd", c, SM.modes[:2])
    moved = s * shape @ R.T + (~SM.mean.is_vector)[:, None] * np.array([5.0, -2, 9])
    fitted, c_fit, value = prior.fit(moved)
    # the mode coefficients are found back (up to the small PPCA shrinkage), the residual is ~0
    assert np.allclose(c_fit, c, rtol=0.05, atol=0.05)
    assert value < 0.05 * ProcrustesPrior(SM.mean, SM.mean, space=space).distance2(moved)
    # never above the rotation prior without modes (c = 0 is one of the candidates)
    snake = SM.mean.with_params(SM.mean.params + 0.5 * _deformation(8)).transformed(R, (1, 2, 3))
    assert prior.distance2(snake.params) <= ProcrustesPrior(SM.mean, SM.mean, space=space
                                                            ).distance2(snake.params) + 1e-12
    # gradient at the alternating minimum against central differences
    value, grad = prior.value_and_grad(snake.params)
    direction = np.random.default_rng(12).normal(size=grad.shape)
    h = 1e-5
    fd = (prior.value_and_grad(snake.params + h * direction)[0]
          - prior.value_and_grad(snake.params - h * direction)[0]) / (2 * h)
    assert fd == pytest.approx(np.sum(grad * direction), rel=1e-5)


def test_build_prior_picks_and_refuses():
    assert isinstance(build_prior(SM.mean, SM.reference, 1.0, "rigid"), ProcrustesPrior)
    assert isinstance(build_prior(SM.mean, SM.reference, 1.0, "affine", SM, 2), ModePrior)
    assert isinstance(build_prior(SM.mean, SM.reference, 1.0, "affine", SM, 0), AffinePrior)
    with pytest.raises(ValueError, match="needs a shape model"):
        build_prior(SM.mean, SM.reference, 1.0, "affine", None, 2)
    assert isinstance(build_prior(SM.mean, SM.reference, 1.0, "similarity", SM, 2), RotationModePrior)
    with pytest.raises(ValueError, match="has 9 modes"):
        build_prior(SM.mean, SM.reference, 1.0, "affine", SM, 12)


def test_segment_prior_options_pick_the_prior_and_refuse_contradictions(tmp_path):
    from segsnake.config import SegmentConfig
    from segsnake.errors import InputError
    from segsnake.runner import _prior_energy

    path = tmp_path / "model.json"
    SM.save(path)
    plain = tmp_path / "ref.json"
    SM.reference.save(plain)

    def config(**kw):
        base = dict(prior=str(path), prior_weight=1.0, prior_space="affine", prior_modes=0,
                    shape="sphere", m1=None, m2=None)
        base.update(kw)
        return SegmentConfig(**base)

    snake = SM.mean
    assert isinstance(_prior_energy(config(prior_modes=3))(snake), ModePrior)
    assert isinstance(_prior_energy(config(prior_space="rigid"))(snake), ProcrustesPrior)
    assert isinstance(_prior_energy(config())(snake), AffinePrior)
    with pytest.raises(InputError, match="ref.json: --prior-modes needs a shape model"):
        _prior_energy(config(prior=str(plain), prior_modes=2))
    with pytest.raises(InputError, match="model.json: .*has 9 modes"):
        _prior_energy(config(prior_modes=10))
    assert isinstance(_prior_energy(config(prior_modes=1, prior_space="rigid"))(snake),
                      RotationModePrior)


@pytest.mark.slow
def test_modes_beat_the_affine_prior_on_a_phantom_with_a_gap(tmp_path):
    """Ten segmented phantoms -> shape model -> a gapped test phantom (benchmarks/bench_shapes.py)."""
    import os
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(__file__)), "benchmarks"))
    import bench_shapes

    runs = {(r["prior"], r["weight"]): r for r in bench_shapes.prior_gap(str(tmp_path), (1.0,))["runs"]}
    affine, modes = runs[("affine", 1.0)], runs[("affine + 3 modes", 1.0)]
    assert modes["dice"] > affine["dice"] + 0.005 and modes["assd_mm"] < affine["assd_mm"]
