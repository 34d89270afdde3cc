"""Affine shape prior: projector identities, invariance, gradient."""

import numpy as np
import pytest

from segsnake.priors import SPACES, AffinePrior
from segsnake.surfaces import CylinderModel, SphereModel


def _perturbed(model, seed, amp):
    rng = np.random.default_rng(seed)
    return model.with_params(model.params + amp * rng.normal(size=model.params.shape))


@pytest.mark.parametrize("ref", [SphereModel.unit(7, 6), CylinderModel.unit(7, 4)])
def test_affine_images_of_the_reference_cost_nothing(ref):
    rng = np.random.default_rng(0)
    prior = AffinePrior(ref, ref, space="affine")
    moved = ref.transformed(rng.normal(size=(3, 3)), rng.normal(size=3))
    assert prior.value_and_grad(moved.params)[0] < 1e-18 * max(1.0, np.abs(moved.params).max() ** 2)
    bumped = _perturbed(ref, 1, 0.1)
    assert prior.value_and_grad(bumped.params)[0] > 1e-4


def test_translation_space_allows_only_translations():
    ref = SphereModel.unit(6, 5)
    prior = AffinePrior(ref, ref, space="translation")
    assert prior.value_and_grad(ref.transformed(np.eye(3), [1, 2, 3]).params)[0] < 1e-20
    assert prior.value_and_grad(ref.transformed(2 * np.eye(3)).params)[0] > 0.1


def test_prior_equals_dense_quadrature_distance_to_the_best_affine_fit():
    ref = SphereModel.unit(6, 5)
    snake = _perturbed(ref.transformed(np.diag([2.0, 1.0, 0.5]), [1, 0, 0]), 2, 0.2)
    value = AffinePrior(ref, ref, space="affine", order=8).value_and_grad(snake.params)[0]
    # Brute force: least squares fit of A, b on a dense midpoint grid, then the L2 residual.
    u = (np.arange(400) + 0.5) / 400
    v = (np.arange(400) + 0.5) / 400
    s = snake.evaluate(u, v)[0].reshape(-1, 3)
    r = ref.evaluate(u, v)[0].reshape(-1, 3)
    X = np.column_stack([r, np.ones(len(r))])
    coef, *_ = np.linalg.lstsq(X, s, rcond=None)
    dense = np.mean(np.sum((s - X @ coef) ** 2, axis=1))
    assert abs(value - dense) / dense < 1e-4


@pytest.mark.parametrize("space", SPACES)
@pytest.mark.parametrize("ref", [SphereModel.unit(6, 5), CylinderModel.unit(6, 3)])
def test_prior_gradient_matches_central_differences(space, ref):
    prior = AffinePrior(ref, ref, weight=0.7, space=space)
    snake = _perturbed(ref.transformed(np.diag([2.0, 1.5, 1.0])), 3, 0.2)
    _, grad = prior.value_and_grad(snake.params)
    h = 1e-6
    fd = np.zeros_like(grad)
    for i in range(grad.shape[0]):
        for d in range(3):
            p = snake.params.copy()
            p[i, d] += h
            ep = prior.value_and_grad(p)[0]
            p[i, d] -= 2 * h
            fd[i, d] = (ep - prior.value_and_grad(p)[0]) / (2 * h)
    assert np.linalg.norm(grad - fd) / np.linalg.norm(fd) < 1e-6
