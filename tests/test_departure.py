"""The departure of a finer grid's surface from the coarser one (segsnake.departure)."""

import math

import numpy as np
import pytest

from segsnake.departure import control_spacing, departure
from segsnake.surfaces import CylinderModel, SphereModel

SP = (0.5, 0.5, 0.5)
CENTRE = np.array([30.3, 29.8, 30.1])


def _counted(inside_coarse, inside_fine, distance, reach, spacing):
    """The departure counted directly: the voxels inside exactly one surface (analytic insides)
    farther than ``reach`` from the coarser surface (an analytic distance), over its volume."""
    sp = np.asarray(spacing)
    idx = np.indices((120, 120, 120)).reshape(3, -1).T * sp  # (0-60 mm: every surface)
    between = inside_coarse(idx) ^ inside_fine(idx)
    return np.count_nonzero(between & (distance(idx) > reach)) * np.prod(sp)


def test_the_control_spacing_of_a_sphere_is_the_side_of_its_mean_patch():
    ball = SphereModel.ellipsoid(CENTRE, (10, 10, 10), m1=9, m2=9)
    assert control_spacing(ball) == pytest.approx(math.sqrt(400 * math.pi / 81), rel=1e-6)


def test_a_surface_within_a_control_spacing_departs_by_nothing():
    coarse = SphereModel.ellipsoid(CENTRE, (10, 10, 10))
    # 2 mm out everywhere, and a lobed surface of the same size: within h = 3.94 mm
    assert departure(coarse, SphereModel.ellipsoid(CENTRE, (12, 12, 12), m1=13, m2=13), SP) == 0
    assert departure(coarse, SphereModel.ellipsoid(CENTRE, (13, 9, 8), m1=13, m2=13), SP) == 0


@pytest.mark.parametrize("radii", [(20, 20, 20), (10, 10, 25), (4, 4, 4), (5, 20, 10)])
def test_the_departure_is_the_volume_beyond_a_control_spacing(radii):
    coarse = SphereModel.ellipsoid(CENTRE, (10, 10, 10))
    fine = SphereModel.ellipsoid(CENTRE, radii, m1=13, m2=13)
    h = control_spacing(coarse)
    r = np.asarray(radii, dtype=float)

    def in_fine(p):
        return (((p - CENTRE) / r) ** 2).sum(axis=1) < 1

    def in_coarse(p):
        return np.linalg.norm(p - CENTRE, axis=1) < 10

    def distance(p):
        return np.abs(np.linalg.norm(p - CENTRE, axis=1) - 10)

    expected = _counted(in_coarse, in_fine, distance, h, SP) / (4 / 3 * math.pi * 1000)
    assert expected > 0.05  # (each case moves a sizeable volume beyond h)
    # the nearest of the surface samples is at most half their spacing (h / 16) farther than
    # the surface: a few voxels' layer more
    assert departure(coarse, fine, SP) == pytest.approx(expected, rel=0.01)  # (0.1-0.8 %)


def test_the_departure_counts_the_image_voxels_wherever_the_surfaces_lie():
    coarse = SphereModel.ellipsoid(CENTRE, (10, 10, 10))
    fine = SphereModel.ellipsoid(CENTRE, (10, 10, 25), m1=13, m2=13)
    shift = np.array([3, -7, 11]) * np.asarray(SP)  # whole voxels: the same voxels
    moved = departure(coarse.transformed(np.eye(3), shift), fine.transformed(np.eye(3), shift),
                      SP)
    assert moved == pytest.approx(departure(coarse, fine, SP), rel=1e-12)
    # half a voxel: other voxel centres, the same volume to within their layer
    half = departure(coarse.transformed(np.eye(3), 0.25 * np.ones(3)),
                     fine.transformed(np.eye(3), 0.25 * np.ones(3)), SP)
    assert half != moved and half == pytest.approx(moved, rel=0.03)


def test_a_tube_that_grows_past_its_end_departs_by_its_new_length():
    coarse = CylinderModel.from_axis((20, 20, 10), (20, 20, 30), 4.0, m1=8, m2=6)
    fine = CylinderModel.from_axis((20, 20, 10), (20, 20, 50), 4.0, m1=13, m2=6)
    h = control_spacing(coarse)
    # the end cap at z = 30 moves 20 mm: the part of the longer tube beyond h of it
    expected = (20 - h) / 20
    assert departure(coarse, fine, SP) == pytest.approx(expected, rel=0.03)  # (1.1 %)
    assert departure(coarse, CylinderModel.from_axis((20, 20, 10), (20, 20, 31), 4.2, m1=13,
                                                     m2=6), SP) == 0
