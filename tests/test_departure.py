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
    # (a voxel's nearest sample is farther than the surface by about s^2 / 8h at the distance
    # h, s the samples' spacing: a few hundredths of a mm, a few voxels in all)
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


def test_a_surface_that_shrinks_away_from_part_of_the_coarser_one_departs():
    # A small ball hugging the inside of the coarser sphere: every sample of it lies within h of
    # the coarser surface, but most of the coarser surface lies far from it.
    coarse = SphereModel.ellipsoid(CENTRE, (10, 10, 10))
    off = CENTRE + np.array([8.5, 0.0, 0.0])
    fine = SphereModel.ellipsoid(off, (1.5, 1.5, 1.5), m1=13, m2=13)
    expected = _counted(lambda p: np.linalg.norm(p - CENTRE, axis=1) < 10,
                        lambda p: np.linalg.norm(p - off, axis=1) < 1.5,
                        lambda p: np.abs(np.linalg.norm(p - CENTRE, axis=1) - 10),
                        control_spacing(coarse), SP) / (4 / 3 * math.pi * 1000)
    assert departure(coarse, fine, SP) == pytest.approx(expected, rel=0.01)  # 0.224


def test_a_tube_departs_by_what_grows_past_its_end_cap():
    start = np.array([20.1, 19.9, 10.3])  # (the caps off the voxel centres)
    coarse = CylinderModel.from_axis(start, start + (0, 0, 20), 4.0, m1=8, m2=6)
    fine = CylinderModel.from_axis(start, start + (0, 0, 40), 4.0, m1=13, m2=6)

    def inside(p, length):
        return (np.hypot(p[:, 0] - start[0], p[:, 1] - start[1]) < 4) \
            & (p[:, 2] > start[2]) & (p[:, 2] < start[2] + length)

    # beyond the coarser tube's cap, the cap is the nearest of its surface
    expected = _counted(lambda p: inside(p, 20), lambda p: inside(p, 40),
                        lambda p: p[:, 2] - start[2] - 20, control_spacing(coarse),
                        SP) / (math.pi * 16 * 20)
    assert departure(coarse, fine, SP) == pytest.approx(expected, rel=0.01)  # 0.825
    # A cap that moves 2 mm, less than the spacing (8.9 mm at radius 10): nothing departs.
    coarse = CylinderModel.from_axis(start, start + (0, 0, 60), 10.0, m1=8, m2=6)
    assert departure(coarse, CylinderModel.from_axis(start, start + (0, 0, 62), 10.0, m1=13,
                                                     m2=6), SP) == 0
