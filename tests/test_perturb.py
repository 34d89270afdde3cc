"""segsnake.perturb: seeded perturbations of an initialization (issue 14's definition)."""

import copy
import json

import numpy as np
import pytest

from segsnake.perturb import SCALE, SHIFT, TILT_DEG, perturb_init
from segsnake.pipeline import perpendicular_spacing

SEEDS = range(200)
# Outputs are rounded to 3 decimals of a voxel: allow that much per coordinate.
ROUND = 5e-4


def _sphere(spacing):
    """A sphere start in voxels whose radii are 6, 4 and 3 mm whatever the spacing."""
    sp = np.asarray(spacing, dtype=float)
    return {"shape": "sphere", "center": list(np.array([30.0, 31.0, 20.0])),
            "radii": list(np.array([6.0, 4.0, 3.0]) / sp)}


def _cylinder(axis_start, axis_end, radius):
    return {"shape": "cylinder", "axis_start": list(axis_start), "axis_end": list(axis_end),
            "radius": radius, "feature": "surface"}


def _ends_mm(init, sp):
    return np.asarray(init["axis_start"]) * sp, np.asarray(init["axis_end"]) * sp


def _radius_mm(init, sp):
    a0, a1 = _ends_mm(init, sp)
    return init["radius"] * perpendicular_spacing(sp, a1 - a0)


def test_same_seed_same_result_other_seed_other_result():
    for init, sp in ((_sphere((1.0, 1.0, 2.0)), (1.0, 1.0, 2.0)),
                     (_cylinder([10, 20, 5], [12, 21, 45], 6.0), (0.8, 0.9, 1.5))):
        a, b = perturb_init(init, sp, 7), perturb_init(init, sp, 7)
        assert a == b
        others = [perturb_init(init, sp, s) for s in (8, 9, 10)]
        assert all(o != a for o in others)
        assert len({json.dumps(o, sort_keys=True) for o in others}) == 3  # pairwise different
        assert a != init


def test_input_is_not_mutated_other_keys_are_copied_and_output_is_plain_json():
    for init, sp in ((_sphere((1.0, 1.0, 2.0)), (1.0, 1.0, 2.0)),
                     (_cylinder([10, 20, 5], [12, 21, 45], 6.0), (0.8, 0.9, 1.5))):
        init["m1"] = 8
        before = copy.deepcopy(init)
        out = perturb_init(init, sp, 3)
        assert init == before
        assert out is not init and out["shape"] == init["shape"] and out["m1"] == 8
        assert set(out) == set(init)
        assert json.loads(json.dumps(out)) == out  # plain floats and lists (CLI args, YAML)
        if init["shape"] == "cylinder":
            assert out["feature"] == "surface"


def test_unknown_shape_raises_value_error():
    with pytest.raises(ValueError, match="unknown initialization shape 'cube'"):
        perturb_init({"shape": "cube", "center": [1, 2, 3], "radii": [1, 1, 1]}, (1, 1, 1), 0)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (1.0, 1.0, 2.0), (0.7, 1.3, 2.5)])
def test_sphere_centre_shift_and_radius_factor_in_mm(spacing):
    sp = np.asarray(spacing)
    init = _sphere(spacing)
    radii_mm = np.asarray(init["radii"]) * sp
    r = float(np.exp(np.mean(np.log(radii_mm))))  # the geometric-mean radius, mm
    bound = SHIFT * r
    shifts, factors = [], []
    for seed in SEEDS:
        out = perturb_init(init, spacing, seed)
        assert out["shape"] == "sphere" and len(out["center"]) == len(out["radii"]) == 3
        shifts.append(np.linalg.norm((np.asarray(out["center"]) - init["center"]) * sp))
        # The shape in mm is kept: every axis' radius in mm scales by the same factor.
        f = np.asarray(out["radii"]) * sp / radii_mm
        assert np.ptp(f) < 2 * ROUND * sp.max() / radii_mm.min()
        factors.append(f.mean())
    shifts, factors = np.array(shifts), np.array(factors)
    tol = ROUND * np.linalg.norm(sp)
    assert shifts.max() <= bound + tol and shifts.max() > 0.9 * bound
    # uniform in the ball, not in the radius: about 1/8 of the moves are under half the bound
    assert 0.04 < np.mean(shifts < 0.5 * bound) < 0.25
    assert SCALE[0] - 1e-3 <= factors.min() < SCALE[0] + 0.05
    assert SCALE[1] - 0.05 < factors.max() <= SCALE[1] + 1e-3
    assert abs(factors.mean() - np.mean(SCALE)) < 0.06


def test_sphere_moves_in_every_direction():
    init, sp = _sphere((1.0, 1.0, 2.0)), np.array([1.0, 1.0, 2.0])
    moves = np.array([(np.asarray(perturb_init(init, sp, s)["center"]) - init["center"]) * sp
                      for s in SEEDS])
    assert np.all(moves.min(axis=0) < -1.0) and np.all(moves.max(axis=0) > 1.0)
    assert np.all(np.abs(moves.mean(axis=0)) < 0.4)  # no preferred direction


def test_keyword_ranges_are_honoured():
    init, sp = _sphere((1.0, 1.0, 2.0)), np.array([1.0, 1.0, 2.0])
    radii_mm = np.asarray(init["radii"]) * sp
    r = float(np.exp(np.mean(np.log(radii_mm))))
    outs = [perturb_init(init, sp, s, shift=0.1, scale=(0.9, 1.1)) for s in range(50)]
    shifts = [np.linalg.norm((np.asarray(o["center"]) - init["center"]) * sp) for o in outs]
    factors = [np.mean(np.asarray(o["radii"]) * sp / radii_mm) for o in outs]
    assert max(shifts) <= 0.1 * r + 2e-3 and min(factors) >= 0.9 - 1e-3 and max(factors) <= 1.1 + 1e-3
    # no change at all: the start comes back (to the rounding)
    same = perturb_init(init, sp, 5, shift=0.0, scale=(1.0, 1.0), tilt_deg=0.0)
    assert np.allclose(same["center"], init["center"]) and np.allclose(same["radii"], init["radii"],
                                                                        atol=1e-3)
    cyl = _cylinder([10, 20, 5], [12, 21, 45], 6.0)
    same = perturb_init(cyl, (0.8, 0.9, 1.5), 5, shift=0.0, scale=(1.0, 1.0), tilt_deg=0.0)
    for key in ("axis_start", "axis_end"):
        assert np.allclose(same[key], cyl[key], atol=1e-3)
    assert same["radius"] == pytest.approx(6.0, abs=1e-3)


@pytest.mark.parametrize("start,end,spacing", [
    ([40, 40, 10], [40, 40, 70], (1.0, 1.0, 1.0)),
    ([40, 40, 10], [40, 40, 70], (1.0, 1.0, 2.0)),     # along the coarse axis
    ([10, 40, 30], [70, 40, 30], (1.0, 1.0, 2.0)),     # across it: the perpendicular spacing matters
    ([10, 20, 5], [32, 41, 25], (0.8, 1.1, 2.5)),      # oblique on an anisotropic grid
])
def test_cylinder_length_tilt_shift_and_radius(start, end, spacing):
    sp = np.asarray(spacing)
    init = _cylinder(start, end, 6.0)
    a0, a1 = _ends_mm(init, sp)
    length, mid, u = np.linalg.norm(a1 - a0), 0.5 * (a0 + a1), (a1 - a0) / np.linalg.norm(a1 - a0)
    r = _radius_mm(init, sp)
    bound = SHIFT * r
    tilts, shifts, factors = [], [], []
    for seed in SEEDS:
        out = perturb_init(init, spacing, seed)
        b0, b1 = _ends_mm(out, sp)
        tol = 2 * ROUND * np.linalg.norm(sp)
        assert np.linalg.norm(b1 - b0) == pytest.approx(length, abs=tol)  # length kept
        w = (b1 - b0) / np.linalg.norm(b1 - b0)
        tilts.append(np.degrees(np.arccos(np.clip(w @ u, -1.0, 1.0))))
        shifts.append(np.linalg.norm(0.5 * (b0 + b1) - mid))
        factors.append(_radius_mm(out, sp) / r)
    tilts, shifts, factors = map(np.array, (tilts, shifts, factors))
    assert tilts.max() <= TILT_DEG + 0.01 and tilts.max() > 0.9 * TILT_DEG
    assert 4.0 < tilts.mean() < 6.0  # uniform in [0, 10] degrees
    tol = ROUND * np.linalg.norm(sp)
    assert shifts.max() <= bound + tol and shifts.max() > 0.9 * bound
    assert SCALE[0] - 2e-3 <= factors.min() < SCALE[0] + 0.05
    assert SCALE[1] - 0.05 < factors.max() <= SCALE[1] + 2e-3


def test_cylinder_tilts_in_every_direction_about_its_midpoint():
    init, sp = _cylinder([40, 40, 10], [40, 40, 70], 6.0), np.ones(3)
    ends = [np.asarray(perturb_init(init, sp, s, shift=0.0)["axis_end"]) for s in SEEDS]
    sideways = np.array(ends)[:, :2] - 40.0  # where the end moved across the axis (no shift)
    assert np.all(sideways.min(axis=0) < -3.0) and np.all(sideways.max(axis=0) > 3.0)
    starts = [np.asarray(perturb_init(init, sp, s, shift=0.0)["axis_start"]) for s in SEEDS]
    assert np.allclose((np.array(starts) + np.array(ends)) / 2, [40, 40, 40], atol=1e-3)
