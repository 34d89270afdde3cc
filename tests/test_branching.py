"""Where a tube branches, a single cylinder ends (segsnake.branching; the lung2 carina)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from segsnake.branching import Cut, find_cuts, section
from segsnake.config import SegmentConfig
from segsnake.metrics import dice
from segsnake.pipeline import segment_volume
from segsnake.region import IntensityModel, RegionParams, smoothed
from segsnake.surfaces import CylinderModel

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sweep():
    """benchmarks/branch_sweep.py: its Y-shaped phantom."""
    spec = importlib.util.spec_from_file_location("branch_sweep",
                                                  ROOT / "benchmarks" / "branch_sweep.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def y_tube(sweep):
    return sweep.y_tube


def _division(reference: np.ndarray) -> int:
    """The lowest axial slice of the reference (the trunk, above the division)."""
    return int(np.nonzero(reference.any(axis=(0, 1)))[0].min())


def test_a_section_of_two_branches_has_two_pieces_and_one_of_the_trunk_one(y_tube):
    image, reference = y_tube(1)[:2]
    model = IntensityModel(mu=100.0, sigma=8.0, range=200.0)
    image_s = smoothed(image, (1, 1, 1), 1.0)
    z, k = np.array([0.0, 0.0, 1.0]), _division(reference)
    trunk = section(image_s, (1, 1, 1), model, np.array([32, 24, k + 15.0]), z, 10.0).areas
    # one piece, the click's band a little inside the blurred step of radius 6
    assert len(trunk) == 1 and np.pi * 4 ** 2 < trunk[0] < np.pi * 6 ** 2
    below = section(image_s, (1, 1, 1), model, np.array([32, 24, k - 8.0]), z, 20.0).areas
    assert len(below) >= 2 and below[1] >= RegionParams.branch_fraction * trunk[0]


@pytest.mark.parametrize("past", [6, 7, 8, 9, 10, 11, 12])
def test_a_tube_past_a_division_is_cut_there_and_one_short_of_it_not(y_tube, past):
    image, reference = y_tube(1)[:2]
    model = IntensityModel(mu=100.0, sigma=8.0, range=200.0)
    image_s = smoothed(image, (1, 1, 1), 1.0)
    k = _division(reference)
    # a trunk-sized tube from the top face down to `past` mm below the division
    tube = CylinderModel.from_axis([32, 24, 71.0], [32, 24, k - past], 6.0, 8, 8)
    cuts = find_cuts(tube, image_s, (1, 1, 1), model)
    assert list(cuts) == [1]  # the end v = 1, below
    cut = cuts[1]
    assert np.dot(cut.normal, [0, 0, -1]) > 0.99  # pointing out of the tube, down
    assert k - 4 < cut.centre[2] < k + 2
    # its reach: past the tube's end beyond the plane (the rim of its end cap, a lumen radius
    # of 4.5-6 mm further), and at least cut_radii lumen radii
    rim = np.hypot(cut.centre[2] - (k - past), 6.0)
    assert rim + 4.5 < cut.radius < rim + 6 and cut.radius > 4.5 * RegionParams.cut_radii
    short = CylinderModel.from_axis([32, 24, 71.0], [32, 24, k + 10.0], 6.0, 8, 8)
    assert find_cuts(short, image_s, (1, 1, 1), model) == {}


def test_a_cut_holds_back_the_half_ball_beyond_its_plane():
    out = np.zeros((20, 20, 20), np.float32)
    cut = Cut((10.0, 10.0, 10.0), (0.0, 0.0, -1.0), 5.0, 2.0)
    cut.apply(out, (0, 0, 0), (1, 1, 1), 1.0)
    i, j, k = np.indices(out.shape)
    want = (k < 10) & ((i - 10) ** 2 + (j - 10) ** 2 + (k - 10) ** 2 <= 25)
    assert np.array_equal(out == 1, want)
    # in a window that starts at voxel (5, 5, 5): the same voxels
    win = np.zeros((15, 15, 15), np.float32)
    cut.apply(win, (5, 5, 5), (1, 1, 1), 1.0)
    assert np.array_equal(win == 1, want[5:, 5:, 5:])
    # voxels of 0.5 x 1 x 2 mm: the same ball in mm
    aniso = np.zeros((40, 20, 10), np.float32)
    cut.apply(aniso, (0, 0, 0), (0.5, 1, 2), 1.0)
    pts = np.stack(np.indices(aniso.shape), -1) * [0.5, 1, 2] - 10.0
    want = (pts[..., 2] < 0) & ((pts ** 2).sum(-1) <= 25)
    assert np.array_equal(aniso == 1, want)
    assert Cut.from_dict(cut.to_dict()) == cut
    # an end within a lumen radius of the plane, on either side, is on the division
    assert cut.holds((13.0, 9.0, 8.5)) and cut.holds((10.0, 10.0, 11.5))
    assert not cut.holds((10.0, 10.0, 7.0))


def test_a_tube_clicked_in_the_trunk_ends_at_the_division(y_tube):
    image, reference, click = y_tube(1)[:3]
    res = segment_volume(image, (1, 1, 1), SegmentConfig.from_mapping(click))
    assert res.settings["ends"] == ["field of view", "branching"]
    # without the cut the end crept on down both branches (Dice 0.809 before session 17)
    assert dice(res.mask, reference) >= 0.93
    assert _division(res.mask) >= _division(reference) - 2


def test_thick_slices_in_a_larger_volume_and_the_round_trip(y_tube):
    # 0.6 x 0.6 x 2.5 mm voxels, the Y 36 mm in from two low faces: the window the stages work
    # in does not start at the volume's first voxel
    sp = (0.6, 0.6, 2.5)
    image, reference, click = y_tube(0, sp)[:3]
    pad = ((60, 0), (60, 0), (0, 0))
    image = np.pad(image, pad, constant_values=20.0)
    reference = np.pad(reference, pad)
    click = {**click, "axis_start": list(np.add(click["axis_start"], [60, 60, 0])),
             "axis_end": list(np.add(click["axis_end"], [60, 60, 0]))}
    res = segment_volume(image, sp, SegmentConfig.from_mapping(click))
    assert min(res.settings["window"][0][:2]) > 0
    assert res.settings["ends"] == ["field of view", "branching"]
    assert dice(res.mask, reference) >= 0.93  # 0.864 before session 17
    # a run from the result and its record rebuilds the cut: nothing to do
    again = segment_volume(image, sp, SegmentConfig.from_mapping(click), init_model=res.model,
                           init_record=res.settings["restart"])
    assert again.settings["restart_record"] == "used" and again.iterations == 0
    assert np.array_equal(again.mask, res.mask)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_a_centerline_drawn_into_one_branch_follows_it(sweep, seed):
    image, _, _, segments = sweep.y_tube(seed)
    (_, fork, _), (_, end, _) = segments[:2]
    top = np.array([fork[0], fork[1], 60.0])
    points = [top, (top + fork) / 2, fork, fork + 0.3 * (end - fork), fork + 0.6 * (end - fork)]
    res = segment_volume(image, (1, 1, 1), SegmentConfig.from_mapping(
        {"shape": "cylinder", "centerline": [list(p) + [2.5] for p in points]}))
    # into the branch and out through the bottom face, not held back across it (a cut there
    # once took the branch out of the mask: Dice 0.79); a single tube through the fork also
    # takes some of the other branch's root (0.865 and 0.959 without any cut)
    assert res.settings["ends"] == ["field of view", "field of view"]
    assert res.settings["restart"]["cuts"] == {}
    trunk_and_branch = sweep._capsules(image.shape, (1, 1, 1), segments[:2])
    assert dice(res.mask, trunk_and_branch) >= 0.85


@pytest.mark.slow
def test_a_neighbour_alongside_is_no_branch(sweep):
    # a U whose legs are 16 mm apart: the ring of the leg that does not divide reaches the other
    # leg in its section, but that piece does not continue the lumen (it was cut there, Dice
    # 0.885, before the pieces were tracked from section to section)
    image, click = sweep.u_tube(16.0)
    res = segment_volume(image, (1, 1, 1), SegmentConfig.from_mapping(click))
    assert list(res.settings["restart"]["cuts"]) == ["1"]  # the right leg's division only
    assert res.settings["ends"][1] == "branching"
