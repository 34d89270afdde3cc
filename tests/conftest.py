"""Shared test helpers."""

import numpy as np

from segsnake.perturb import perturb_init


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


def perturbed_init(phantom, seed: int) -> dict:
    """A phantom's suggested start, perturbed as a user's would be (issue 14).

    The phantom's ``init`` is derived from its truth; segmentation tests start instead from
    :func:`segsnake.perturb.perturb_init` of it (centre moved up to half the radius, radius
    x0.6-1.4, a cylinder's axis tilted up to 10 degrees) with a fixed ``seed`` per test.
    ``phantom`` is a :class:`~segsnake.phantoms.Phantom` or its ``phantom.json`` record.
    """
    if isinstance(phantom, dict):
        return perturb_init(phantom["init"], phantom["spacing"], seed)
    return perturb_init(phantom.init, phantom.spacing, seed)


def blas_threads() -> set[int]:
    """The thread counts of the BLAS libraries loaded in this process (threadpoolctl)."""
    from threadpoolctl import threadpool_info

    return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}
