"""A snake with other numbers of control points: the exact L2 projection onto the new spline space.

``segment --init SNAKE.json --m1 N --m2 N`` starts from a saved snake of another size. The new
model is the one closest to the old surface in ``L2([0, 1]^2)`` over the parameter domain (the
inner product of :mod:`segsnake.priors`):

    p_new = B_new^-1 A_new^T integral b_new(u, v) sigma_old(u, v) du dv,

with ``B_new`` the exact Gram matrix of the new free parameters (:func:`segsnake.priors.param_gram`)
and ``A_new`` its constraint map. Both bases are smooth inside their own knot intervals, so the
right-hand side is integrated exactly (to rounding) by Gauss-Legendre on the union of the two
knot sets, :data:`segsnake.priors.GRAM_ORDER` nodes per piece. Every shape the new space holds is
reproduced exactly: an ellipsoid (sphere snakes) or a straight elliptic cylinder (cylinder snakes)
at any size, and any snake resampled to its own size.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from segsnake.priors import GRAM_ORDER, param_gram
from segsnake.surfaces import CylinderModel, SphereModel, SplineSurface

__all__ = ["resample", "poles_on_long_axis", "interpolate_tube"]

_KINDS = {"sphere": SphereModel, "cylinder": CylinderModel}


def _union_rule(n_a: int, n_b: int, order: int) -> tuple[NDArray, NDArray]:
    """Gauss-Legendre nodes and weights on [0, 1] split at the knots ``k / n_a`` and ``k / n_b``."""
    breaks = np.union1d(np.arange(n_a + 1) / n_a, np.arange(n_b + 1) / n_b)
    # Knots that coincide up to rounding (k/6 and 2k/12) would make empty pieces.
    breaks = breaks[np.concatenate([[True], np.diff(breaks) > 1e-14])]
    breaks[-1] = 1.0
    x, w = np.polynomial.legendre.leggauss(order)
    h = np.diff(breaks)
    nodes = (breaks[:-1, None] + (x[None, :] + 1) * h[:, None] / 2).ravel()
    weights = (w[None, :] * h[:, None] / 2).ravel()
    return nodes, weights


def resample(model: SplineSurface, m1: int, m2: int) -> SplineSurface:
    """The model of the same kind with ``m1 x m2`` control points closest to ``model`` in L2.

    Parameters
    ----------
    model : SplineSurface
        A sphere or cylinder snake (any coordinates: the projection commutes with affine maps).
    m1, m2 : int
        The new numbers of control points around and along.

    Returns
    -------
    SplineSurface
        The L2-orthogonal projection of ``model``'s surface onto the new spline space (at the
        model's own size: the model again, to rounding).
    """
    new = _KINDS[model.kind].unit(m1, m2)
    u, wu = _union_rule(model.m1, m1, GRAM_ORDER)
    v, wv = _union_rule(model.m2, m2, GRAM_ORDER)
    sigma = model.evaluate(u, v)[0]  # (nu, nv, 3)
    bu = new._basis_u(u, 0)  # (nu, M1)
    bv = new._basis_v(v, 0)  # (nv, L)
    # integral b_k(u) b_l(v) sigma(u, v): (M1, L, 3)
    rhs_grid = np.einsum("uk,u,uvd,v,vl->kld", bu, wu, sigma, wv, bv, optimize=True)
    rhs = new.constraint.T @ rhs_grid.reshape(-1, 3)
    return new.with_params(np.linalg.solve(param_gram(new), rhs))


def poles_on_long_axis(model: SphereModel, m1: int, m2: int) -> SphereModel:
    """A sphere snake with ``m1 x m2`` control points fitted to ``model``'s surface with its poles
    at the ends of the surface's long axis (:func:`segsnake.fit.fit_mesh` on the surface's own
    mesh, 4 vertices per control interval: :mod:`segsnake.parameterize`).

    The lat-long grid then runs around an elongated object's long axis, where its rings are
    short, instead of along it, where they would be stretched over its length: the perfect-edge
    hippocampus (53 x 34 x 15 mm, curved) reaches a given Dice with about 8 fewer control
    points a side (docs/benchmarks.md, session 19). Unlike :func:`resample` this is a
    least-squares fit over a new parameterization: it holds the surface to the fit's error,
    not exactly.
    """
    from segsnake.fit import fit_mesh

    points, faces = model.triangles(4 * model.m1, 4 * model.m2)  # (closed, genus 0)
    return fit_mesh(points, faces, m1=m1, m2=m2).model


def interpolate_tube(model: CylinderModel, m2: int) -> CylinderModel:
    """A cylinder with ``m2`` intervals along that passes through ``model`` at its new control
    points, its rings evenly spaced along the tube: ``c[k, l] = sigma(k / M1, v_l)``, ``l = 0 ..
    m2``, the ``v_l`` cutting the tube into stretches of equal mean length along it
    (:func:`segsnake.profile.even_rings`), and the two outer rows, which only set the ends'
    slope, extrapolated linearly (``c[., -1] = 2 c[., 0] - c[., 1]``).

    Nothing in the energies holds the rings where they are along the tube (a tube's bending
    is blind to a spacing that changes steadily, and the image to any motion within the
    surface): a tube grown from a click's stretch to its ends comes back with its end rings
    several times further apart than its middle ones, and misses a bulge between them (the
    region stages put a tube on even rings after its growth and before each later round). Even
    rings are what "two rings per diameter" (:func:`segsnake.surfaces.axial_rings`) assumes.

    Unlike the L2 projection it cannot overshoot where the surface changes fast along the tube:
    a tube whose end tapers to a tip keeps a tip with its rings the right way round (projected,
    such a tip came back with its last rings inside out). Any straight elliptic cylinder is
    reproduced exactly (the new space holds it, and interpolation keeps what it holds).
    """
    from segsnake.profile import even_rings

    u = np.arange(model.m1) / model.m1
    rows = model.evaluate(u, even_rings(model, m2))[0]  # (M1, m2 + 1, 3)
    grid = np.concatenate([2 * rows[:, :1] - rows[:, 1:2], rows,
                           2 * rows[:, -1:] - rows[:, -2:-1]], axis=1)
    return CylinderModel(model.m1, m2, grid.reshape(-1, 3))  # k-major like the parameters
