"""A click alone (``--center`` without ``--radii``): the initial sphere from the image around it
(:mod:`segsnake.click`)."""

import numpy as np
import pytest

from segsnake.click import click_radius
from segsnake.cli import main
from segsnake.config import SegmentConfig
from segsnake.metrics import dice
from segsnake.pipeline import auto_init, initial_model, segment_volume

STEP = 2 ** (1 / 3)  # (click.SCALES_PER_OCTAVE radii to a doubling)
ISO = (1.0, 1.0, 1.0)


def _two_balls(seed: int = 0):
    """A 20 mm ball (100) and a 6 mm one (60) apart on a background of 20, 1 mm voxels, noise 5."""
    shape = (88, 56, 56)
    x, y, z = np.indices(shape, dtype=np.float64)
    big = (x - 24) ** 2 + (y - 28) ** 2 + (z - 28) ** 2 <= 20 ** 2
    small = (x - 70) ** 2 + (y - 28) ** 2 + (z - 28) ** 2 <= 6 ** 2
    image = np.full(shape, 20.0)
    image[big], image[small] = 100.0, 60.0
    image += np.random.default_rng(seed).normal(0.0, 5.0, shape)
    return image.astype(np.float32), big, small


def test_a_boundary_around_the_click_ends_the_ball_inside_it():
    image, _, _ = _two_balls()
    # At the centre of the 20 mm ball: the last ball before the shell that reaches its edge.
    assert 20.0 / STEP ** 2 <= click_radius(image, ISO, (24.0, 28.0, 28.0)) <= 20.0
    # In the 6 mm ball, with the big one 26 mm away.
    assert click_radius(image, ISO, (70.0, 28.0, 28.0)) <= 6.0


def test_a_neighbour_of_the_same_median_but_another_texture_ends_it_too():
    # A 10 mm ball of one tissue (100) in stripes of 70 and 130: the shell's median tells
    # nothing, the ball's spread does once stripes enter it (the radius before is taken).
    shape = (64, 64, 64)
    x, y, z = np.indices(shape)
    image = np.where((y // 4) % 2 == 0, 70.0, 130.0)
    image[(x - 32) ** 2 + (y - 32) ** 2 + (z - 32) ** 2 <= 10 ** 2] = 100.0
    image += np.random.default_rng(0).normal(0.0, 2.0, shape)
    r = click_radius(image.astype(np.float32), ISO, (32.0, 32.0, 32.0))
    assert 10.0 / STEP ** 2 <= r <= 10.0, r


def test_anisotropic_voxels_give_the_same_ball_in_mm():
    image, _, _ = _two_balls()
    r1 = click_radius(image, ISO, (24.0, 28.0, 28.0))
    r2 = click_radius(image[:, :, ::2], (1.0, 1.0, 2.0), (24.0, 28.0, 28.0))  # 1 x 1 x 2 mm
    assert r2 == pytest.approx(r1, rel=0.1)


def test_slices_far_thicker_than_the_pixels_skip_the_balls_without_a_spread():
    # 0.3 x 0.3 x 6 mm, a click between slices: the smallest balls hold no voxel.
    rng = np.random.default_rng(1)
    image = (100.0 + rng.normal(0.0, 2.0, (200, 200, 9))).astype(np.float32)
    r = click_radius(image, (0.3, 0.3, 6.0), (30.0, 30.0, 27.0))
    assert np.isfinite(r) and r > 0


def test_a_click_alone_starts_inside_the_clicked_object():
    # Before: the radius was half the largest object's size (here 10 mm), whatever was clicked.
    image, big, small = _two_balls()
    config = SegmentConfig(center=(70, 28, 28))
    model = initial_model(config, ISO, image.shape, image=image)
    radius = np.linalg.norm(model.control_points().reshape(-1, 3) - [70, 28, 28], axis=1)
    assert radius.max() == pytest.approx(click_radius(image, ISO, (70.0, 28.0, 28.0)), rel=1e-9)
    assert radius.max() <= 6.0 < auto_init(image, ISO)[1].min()
    result = segment_volume(image, ISO, config)
    assert dice(result.mask, small) >= 0.9
    assert not (result.mask & big).any()


@pytest.mark.parametrize("radius", [2.5, 3.0, 3.5])
def test_a_click_alone_on_an_object_as_small_as_the_smallest_ball_finds_it(radius):
    # A nodule of 2.5-3.5 voxels' radius (100 on 20, noise 8): the smallest ball (3.4 mm, so
    # that its core holds the intensity model's 20 voxels) already holds background, and so
    # did every larger one: the growth ran to half the image (17 mm), its core read the
    # background, and the run ended "no boundary found". Measured now: Dice 1.0 / 0.975 / 1.0.
    from segsnake.region import MIN_SAMPLES, RegionParams

    x = np.indices((40, 40, 40)).astype(np.float32) - 20.0
    truth = (x ** 2).sum(0) <= radius ** 2
    noise = np.random.default_rng(0).normal(0.0, 8.0, truth.shape)
    image = (np.where(truth, 100.0, 20.0) + noise).astype(np.float32)
    smallest = (3 * MIN_SAMPLES / (4 * np.pi)) ** (1 / 3) / RegionParams.core_fraction
    assert click_radius(image, ISO, (20.0, 20.0, 20.0)) == pytest.approx(smallest)
    result = segment_volume(image, ISO, SegmentConfig(center=(20, 20, 20)))
    assert dice(result.mask, truth) >= 0.95


def test_a_click_alone_that_finds_no_boundary_says_to_give_radii(tmp_path, capsys):
    # A click in the middle of fine stripes (a tissue of two): its ball is one stripe, whose
    # outside is the same stripes; the region energy finds no boundary, and says what to do.
    import nibabel as nib

    shape = (48, 48, 48)
    y = np.indices(shape)[1]
    image = np.where((y // 2) % 2 == 0, 40.0, 120.0).astype(np.float32)
    path = tmp_path / "stripes.nii.gz"
    nib.save(nib.Nifti1Image(image, np.eye(4)), path)
    rc = main(["segment", str(path), "--out", str(tmp_path / "o"), "--quiet",
               "--center", "24", "24", "24"])
    err = capsys.readouterr().err
    assert rc == 4, err
    assert "give --radii" in err
