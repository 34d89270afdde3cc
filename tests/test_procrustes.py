"""Rigid and similarity priors with rotations (issue 19, item 4): exact projector and gradient."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from segsnake.priors import l2_norm
from segsnake.procrustes import ProcrustesPrior, procrustes_fit, procrustes_project
from segsnake.surfaces import CylinderModel, SphereModel

REFS = [SphereModel.ellipsoid((5, -2, 30), (6, 4, 3), m1=7, m2=6),
        CylinderModel.from_axis((0, 0, 0), (2, 1, 12), 3.0, m1=8, m2=4)]


def _bumpy(model, seed, amp=0.5):
    rng = np.random.default_rng(seed)
    return model.with_params(model.params + amp * rng.normal(size=model.params.shape))


@pytest.mark.parametrize("ref", REFS, ids=["sphere", "cylinder"])
@pytest.mark.parametrize("space", ["rigid", "similarity"])
def test_projector_is_idempotent_and_keeps_its_space(ref, space):
    ref = _bumpy(ref, 0)
    snake = _bumpy(ref, 1, 1.0).transformed(Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix(), (4, 5, 6))
    p1 = procrustes_project(ref, snake.params, ref.params, space)
    p2 = procrustes_project(ref, p1, ref.params, space)
    assert np.max(np.abs(p2 - p1)) < 1e-10 * np.max(np.abs(p1))
    # an element of the space is its own projection, with its rotation, scale and translation
    R = Rotation.from_rotvec([2.0, 0.4, -0.9]).as_matrix()
    s = 1.0 if space == "rigid" else 1.7
    element = s * ref.params @ R.T + (~ref.is_vector)[:, None] * np.array([10.0, -3, 8])
    s_fit, R_fit, b_fit = procrustes_fit(ref, element, ref.params, space)
    assert s_fit == pytest.approx(s, rel=1e-12) and np.allclose(R_fit, R, atol=1e-10)
    assert np.allclose(procrustes_project(ref, element, ref.params, space), element, atol=1e-10)
    # the projection is the closest element: better than the true pose of a perturbed shape
    d_proj = l2_norm(ref, snake.params - p1)
    for seed in range(5):
        rot = Rotation.random(random_state=seed).as_matrix()
        other = ref.params @ rot.T + (~ref.is_vector)[:, None] * np.array([4.0, 5, 6])
        assert d_proj <= l2_norm(ref, snake.params - other) + 1e-12


def test_rigid_distance_is_invariant_and_reflections_are_not_rotations():
    ref = _bumpy(REFS[0], 2)
    prior = ProcrustesPrior(ref, ref, space="rigid")
    snake = _bumpy(ref, 3)
    R = Rotation.from_rotvec([0.5, 0.5, -2.0]).as_matrix()
    moved = snake.transformed(R, (100, 0, -50))
    assert prior.distance2(moved.params) == pytest.approx(prior.distance2(snake.params), rel=1e-10)
    assert prior.distance2(ref.transformed(R, (1, 2, 3)).params) < 1e-20 * l2_norm(ref, ref.params) ** 2
    mirrored = ref.transformed(np.diag([1.0, 1.0, -1.0]))  # an asymmetric shape's mirror image
    assert prior.distance2(mirrored.params) > 1e-3
    # rigid does not forgive a change of size; similarity does
    bigger = ref.transformed(1.5 * R, (0, 0, 0))
    assert prior.distance2(bigger.params) > 1.0
    assert ProcrustesPrior(ref, ref, space="similarity").distance2(bigger.params) < 1e-18 * 1e4


@pytest.mark.parametrize("ref", REFS, ids=["sphere", "cylinder"])
@pytest.mark.parametrize("space", ["rigid", "similarity"])
def test_gradient_matches_central_differences(ref, space):
    ref = _bumpy(ref, 4)
    prior = ProcrustesPrior(ref, ref, weight=0.7, space=space)
    snake = _bumpy(ref, 5, 1.0).transformed(Rotation.from_rotvec([0.2, 0.9, -0.4]).as_matrix(), (3, 1, 2))
    value, grad = prior.value_and_grad(snake.params)
    assert value > 0
    h = 1e-6
    rng = np.random.default_rng(6)
    for _ in range(6):
        i, d = rng.integers(len(snake.params)), rng.integers(3)
        plus, minus = snake.params.copy(), snake.params.copy()
        plus[i, d] += h
        minus[i, d] -= h
        fd = (prior.value_and_grad(plus)[0] - prior.value_and_grad(minus)[0]) / (2 * h)
        assert fd == pytest.approx(grad[i, d], rel=1e-6, abs=1e-7 * np.max(np.abs(grad)))
    # and along a random direction (all parameters at once)
    direction = rng.normal(size=snake.params.shape)
    fd = (prior.value_and_grad(snake.params + h * direction)[0]
          - prior.value_and_grad(snake.params - h * direction)[0]) / (2 * h)
    assert fd == pytest.approx(np.sum(grad * direction), rel=1e-7)


def test_bad_space_and_size_are_refused():
    with pytest.raises(ValueError, match="rotation space"):
        ProcrustesPrior(REFS[0], REFS[0], space="affine")
    with pytest.raises(ValueError, match="M1=7"):
        ProcrustesPrior(SphereModel.unit(9, 6), REFS[0])
