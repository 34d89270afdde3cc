"""Shared test helpers."""

import numpy as np


def central_difference_gradient(energy, params, h=1e-6):
    """Central differences of ``energy.value_and_grad(p)[0]`` for every entry of ``params``."""
    fd = np.zeros_like(params)
    for idx in np.ndindex(params.shape):
        p = params.copy()
        p[idx] += h
        up = energy.value_and_grad(p)[0]
        p[idx] -= 2 * h
        fd[idx] = (up - energy.value_and_grad(p)[0]) / (2 * h)
    return fd
