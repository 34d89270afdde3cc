"""A click alone (``--center`` without ``--radii``): the initial sphere from the image around it
(:mod:`segsnake.click`)."""

import numpy as np
import pytest

from segsnake.click import click_radius
from segsnake.config import SegmentConfig
from segsnake.metrics import dice
from segsnake.pipeline import initial_model, segment_volume


def _two_balls(seed: int, noise: float = 5.0):
    """A 12 mm ball (100) and a 4 mm one (60) apart on a background of 20, 1 mm voxels."""
    shape = (64, 48, 48)
    x, y, z = np.indices(shape, dtype=np.float64)
    big = (x - 20) ** 2 + (y - 24) ** 2 + (z - 24) ** 2 <= 12 ** 2
    small = (x - 48) ** 2 + (y - 24) ** 2 + (z - 24) ** 2 <= 6 ** 2
    image = np.full(shape, 20.0)
    image[big], image[small] = 100.0, 60.0
    image += np.random.default_rng(seed).normal(0.0, noise, shape)
    return image.astype(np.float32), big, small


@pytest.mark.parametrize("seed", [0, 1])
def test_the_radius_is_the_largest_ball_of_the_clicked_tissue(seed):
    image, _, _ = _two_balls(seed)
    # At the centre of the 12 mm ball: a ball inside it, not a sliver.
    r = click_radius(image, (1.0, 1.0, 1.0), (20.0, 24.0, 24.0))
    assert 6.0 <= r <= 12.0, r
    # Off its centre by 7 mm, 5 mm from its boundary: a boundary off to one side is a minority
    # of the ball until it has crossed it by about one step of radius (2^(1/3)); the core the
    # intensity model reads (half the radius) stays inside.
    r = click_radius(image, (1.0, 1.0, 1.0), (27.0, 24.0, 24.0))
    assert 3.0 <= r <= 5.0 * 2 ** (1 / 3) * 1.1, r
    # In the 6 mm ball, with the big one 16 mm away.
    r = click_radius(image, (1.0, 1.0, 1.0), (48.0, 24.0, 24.0))
    assert 3.0 <= r <= 6.0 * 2 ** (1 / 3) * 1.1, r


def test_anisotropic_voxels_give_the_same_ball_in_mm():
    image, _, _ = _two_balls(0)
    coarse = image[:, :, ::2]  # 1 x 1 x 2 mm
    r1 = click_radius(image, (1.0, 1.0, 1.0), (20.0, 24.0, 24.0))
    r2 = click_radius(coarse, (1.0, 1.0, 2.0), (20.0, 24.0, 24.0))
    assert abs(r1 - r2) <= 0.3 * r1, (r1, r2)


def test_a_click_alone_segments_the_clicked_object_not_the_largest_one():
    # Before: the radius was half the largest object's size, so a click in the small ball
    # started a sphere around both and segmented the big one.
    image, big, small = _two_balls(2)
    config = SegmentConfig(center=(48, 24, 24))
    model = initial_model(config, (1.0, 1.0, 1.0), image.shape, image=image)
    radius = np.linalg.norm(model.control_points().reshape(-1, 3) - [48, 24, 24], axis=1)
    assert radius.max() <= 6.0 * 2 ** (1 / 3) * 1.1, radius.max()
    result = segment_volume(image, (1.0, 1.0, 1.0), config)
    assert dice(result.mask, small) >= 0.9
    assert not (result.mask & big).any()
