"""The swept-disk tube (the tube phantoms' truth): membership, volume and measured sections."""

from __future__ import annotations

import numpy as np
import pytest

from segsnake.swept_tube import SweptTube


def _straight(a, b, r0, r1=None, step=0.25):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = int(np.ceil(np.linalg.norm(b - a) / step)) + 1
    t = np.linspace(0.0, 1.0, n)
    return SweptTube(a + t[:, None] * (b - a), r0 + t * ((r0 if r1 is None else r1) - r0))


def test_straight_tube_sections_are_the_closed_form_disks():
    # Oblique, tapered from 6 to 3 mm over its length: area pi r(s)^2, every diameter 2 r(s).
    tube = _straight((10, 12, 5), (50, 40, 60), 6.0, 3.0)
    L = tube.length
    s = np.array([0.1, 0.3, 0.5, 0.9]) * L
    r = 6.0 - 3.0 * s / L
    prof = tube.profile(s)
    np.testing.assert_allclose(prof["area"], np.pi * r**2, rtol=1e-4)
    np.testing.assert_allclose(prof["area"], tube.area_analytic(s), rtol=1e-4)
    for key in ("equivalent_diameter", "min_diameter", "max_diameter"):
        np.testing.assert_allclose(prof[key], 2 * r, rtol=1e-4)
    np.testing.assert_allclose(prof["center"], tube.point_at(s), atol=1e-9)
    # A frustum's volume.
    assert tube.volume_analytic() == pytest.approx(np.pi * L * (36 + 18 + 9) / 3, rel=1e-5)


def test_section_clipped_by_a_box_face_is_a_disk_minus_a_segment():
    # Tube along the third axis at x = y = 0, radius 5; the box ends at x = 3.
    tube = _straight((0, 0, 0), (0, 0, 40), 5.0)
    box = (np.array([-50.0, -50.0, -50.0]), np.array([3.0, 50.0, 50.0]))
    prof = tube.profile([20.0], box=box)
    r, d = 5.0, 3.0
    segment = r * r * np.arccos(d / r) - d * np.sqrt(r * r - d * d)
    assert prof["area"][0] == pytest.approx(np.pi * r * r - segment, rel=1e-3)
    assert prof["min_diameter"][0] == pytest.approx(r + d, rel=1e-3)  # across the cut: 3 + 5
    assert prof["max_diameter"][0] == pytest.approx(2 * r, rel=1e-4)


def test_membership_has_flat_ends_and_a_signed_distance():
    tube = _straight((0, 0, 0), (0, 0, 40), 5.0)
    pts = np.array([[0, 0, 20], [4.9, 0, 20], [5.1, 0, 20], [0, 0, -0.1], [4.9, 0, 0.1],
                    [4.9, 0, -0.1], [0, 0, 40.1], [0, 3, 39.9]])
    np.testing.assert_array_equal(tube.inside(pts), [1, 1, 0, 0, 1, 0, 0, 1])
    f = tube.signed(np.array([[2.0, 0, 20], [8.0, 0, 20], [0, 0, 43.0]]))
    np.testing.assert_allclose(f, [-3.0, 3.0, 3.0], atol=1e-9)
    # Far points get the cap; the nearest-point query reports them as unresolved.
    assert tube.signed(np.array([[40.0, 0, 20]]), cap=2.0)[0] == 2.0
    s, d = tube.nearest(np.array([[3.0, 4.0, 12.5]]))
    assert s[0] == pytest.approx(12.5) and d[0] == pytest.approx(5.0)


def test_curved_centreline_sections_stay_disks():
    # A quarter circle of radius 20 mm, tube radius 4: the normal sections are disks of radius 4.
    ang = np.linspace(0.0, np.pi / 2, 400)
    tube = SweptTube(np.stack([20 * np.cos(ang), 20 * np.sin(ang), np.zeros_like(ang)], 1), 4.0)
    assert tube.length == pytest.approx(10 * np.pi, rel=1e-4)
    prof = tube.profile(np.linspace(2.0, tube.length - 2.0, 5))
    np.testing.assert_allclose(prof["area"], np.pi * 16, rtol=1e-3)
    np.testing.assert_allclose(prof["min_diameter"], 8.0, rtol=1e-3)
    np.testing.assert_allclose(prof["max_diameter"], 8.0, rtol=1e-3)
    with pytest.raises(ValueError, match="radii"):
        SweptTube(np.eye(3), [1.0, 0.0, 1.0])
