"""The internal energy (segsnake.regularize): what it leaves free and what it charges."""

import numpy as np
import pytest

from segsnake.regularize import BendingRegularizer
from segsnake.surfaces import CylinderModel, SphereModel


def _energy(model, tube=False):
    return BendingRegularizer(model, tube=tube).value_and_grad(model.params)[0]


def _arc(m2, kink=0.0):
    """A tube of radius 3 along a quarter circle of radius 25 (a kink of ``kink`` mm in the
    middle of its centerline)."""
    t = np.linspace(0, np.pi / 2, 41)
    pts = np.column_stack([25 * np.cos(t), 25 * np.sin(t), np.zeros_like(t)])
    pts[20] += kink * np.array([np.cos(t[20]), np.sin(t[20]), 0.0])
    return CylinderModel.from_centerline(pts, 3.0, m1=8, m2=m2)


@pytest.mark.parametrize("seed", [0, 1])
def test_affine_images_of_the_reference_cost_nothing(seed):
    rng = np.random.default_rng(seed)
    A, b = rng.normal(size=(3, 3)) * 5, rng.normal(size=3) * 10
    for model in (SphereModel.unit(9, 9), CylinderModel.unit(8, 6)):
        rough = model.with_params(model.params + 0.05 * rng.normal(size=model.params.shape))
        moved = model.transformed(A, b)
        assert _energy(moved) < 1e-10 * _energy(rough.transformed(A, b))
    # the tube's own bending: any straight elliptic cylinder too
    cyl = CylinderModel.unit(8, 6).transformed(A, b)
    assert _energy(cyl, tube=True) < 1e-10 * _energy(rough.transformed(A, b), tube=True)


def test_the_tube_bending_lets_a_tube_bend_and_charges_a_kink():
    arc = _arc(12)
    straight_pull = _energy(arc)  # the deviation from the nearest straight cylinder
    own = _energy(arc, tube=True)
    assert own < 0.05 * straight_pull  # measured 0.039
    # a 1.5 mm kink in the centerline costs more than the whole quarter turn
    assert _energy(_arc(12, kink=1.5), tube=True) > 5 * own
    # a ring that is no ellipse bends as before
    lumpy = arc.params.reshape(8, 15, 3).copy()
    lumpy[0, 7] += np.array([0.0, 0.0, 1.0])
    assert _energy(arc.with_params(lumpy.reshape(-1, 3)), tube=True) > 5 * own
