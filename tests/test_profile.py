"""The tube profile (issue 16, item 4) against closed forms: area, equivalent, minimum and maximum
diameter along the centerline, and the arc length they are sampled at."""

from __future__ import annotations

import numpy as np
import pytest

from segsnake.profile import PROFILE_COLUMNS, ring_centroids, tube_profile
from segsnake.surfaces import CylinderModel, SphereModel


def test_straight_circular_cylinder_oblique_axis():
    start, end, r = np.array([1.0, 2.0, 3.0]), np.array([4.0, -5.0, 60.0]), 3.0
    p = tube_profile(CylinderModel.from_axis(start, end, r, m1=8, m2=5))
    length = float(np.linalg.norm(end - start))
    assert p.length_mm == pytest.approx(length, abs=1e-9)
    np.testing.assert_allclose(p.arc_mm[:-1], np.arange(len(p.arc_mm) - 1))  # every 1 mm
    assert p.arc_mm[-1] == pytest.approx(length)  # and the far end
    np.testing.assert_allclose(p.area, np.pi * r * r, rtol=1e-12)
    np.testing.assert_allclose(p.equivalent_diameter, 2 * r, rtol=1e-12)
    np.testing.assert_allclose(p.min_diameter, 2 * r, rtol=1e-7)
    np.testing.assert_allclose(p.max_diameter, 2 * r, rtol=1e-7)
    # The centerline is the axis, at the sampled arc lengths.
    axis = (end - start) / length
    np.testing.assert_allclose(p.centerline, start + p.arc_mm[:, None] * axis, atol=1e-9)
    np.testing.assert_allclose(p.tangent, np.broadcast_to(axis, p.tangent.shape), atol=1e-12)


def test_elliptic_cylinder():
    a, b = 4.0, 2.0
    model = CylinderModel.unit(8, 5).transformed(np.diag([a, b, 30.0]), [1.0, 1.0, 1.0])
    p = tube_profile(model, spacing_mm=2.5)
    np.testing.assert_allclose(p.arc_mm, np.arange(13) * 2.5)
    np.testing.assert_allclose(p.area, np.pi * a * b, rtol=1e-12)
    np.testing.assert_allclose(p.min_diameter, 2 * b, rtol=1e-6)
    np.testing.assert_allclose(p.max_diameter, 2 * a, rtol=1e-6)


def test_oblique_cylinder_is_measured_across_its_axis():
    # Circular rings in z planes, axis tilted: the cut normal to the axis is an ellipse of
    # semi-axes r and r cos(tilt).
    tilt_x, length, r = 10.0, 40.0, 3.0
    shear = np.array([[r, 0, tilt_x], [0, r, 0], [0, 0, length]])
    p = tube_profile(CylinderModel.unit(8, 4).transformed(shear))
    cos = length / np.hypot(tilt_x, length)
    assert p.length_mm == pytest.approx(np.hypot(tilt_x, length), rel=1e-12)
    np.testing.assert_allclose(p.area, np.pi * r * r * cos, rtol=1e-12)
    np.testing.assert_allclose(p.min_diameter, 2 * r * cos, rtol=1e-6)
    np.testing.assert_allclose(p.max_diameter, 2 * r, rtol=1e-6)


def test_tapered_cylinder():
    # c[k, l] = (r(l) cos, r(l) sin, L l / M2), r linear in l: the Keys kernel reproduces the
    # linear radius, so the surface is the exact truncated cone r(v) = r0 + (r1 - r0) v.
    m1, m2, r0, r1, length = 8, 6, 5.0, 2.0, 30.0
    k = np.arange(m1)[:, None]
    l = np.arange(-1, m2 + 2)[None, :]
    rad = r0 + (r1 - r0) * l / m2
    th = 2 * np.pi * k / m1
    grid = np.stack(np.broadcast_arrays(rad * np.cos(th), rad * np.sin(th), length * l / m2), -1)
    p = tube_profile(CylinderModel(m1, m2, grid.reshape(-1, 3)))
    r = r0 + (r1 - r0) * p.arc_mm / length
    np.testing.assert_allclose(p.area, np.pi * r * r, rtol=1e-12)
    np.testing.assert_allclose(p.equivalent_diameter, 2 * r, rtol=1e-12)
    np.testing.assert_allclose(p.min_diameter, 2 * r, rtol=1e-6)
    np.testing.assert_allclose(p.max_diameter, 2 * r, rtol=1e-6)


def test_curved_tube_keeps_its_diameter_and_length():
    arc_r, r = 30.0, 3.0
    t = np.linspace(0.0, np.pi, 9)
    line = np.column_stack([arc_r * np.cos(t), arc_r * np.sin(t), np.zeros_like(t)])
    p = tube_profile(CylinderModel.from_centerline(line, r, m2=16))
    assert p.length_mm == pytest.approx(np.pi * arc_r, rel=2e-3)
    np.testing.assert_allclose(np.linalg.norm(p.centerline, axis=1), arc_r, rtol=2e-3)
    np.testing.assert_allclose(p.equivalent_diameter, 2 * r, rtol=1e-2)


def test_ring_centroids_are_the_rings_means():
    rng = np.random.default_rng(3)
    model = CylinderModel.from_axis([0, 0, 0], [0, 0, 10], 2.0)
    model = model.with_params(model.params + rng.normal(scale=0.3, size=model.params.shape))
    v = np.array([0.0, 0.3, 0.77, 1.0])
    c, dc = ring_centroids(model, v)
    u = np.arange(512) / 512  # the periodic rings: the rectangle rule is spectrally exact
    s, _, sv = model.evaluate(u, v)
    np.testing.assert_allclose(c, s.mean(axis=0), atol=1e-10)
    np.testing.assert_allclose(dc, sv.mean(axis=0), atol=1e-9)


def test_compact_record_and_refusals():
    p = tube_profile(CylinderModel.from_axis([0, 0, 0], [0, 0, 3.5], 1.0))
    d = p.to_dict()
    assert d["columns"] == list(PROFILE_COLUMNS) and len(d["rows"]) == 5  # 0, 1, 2, 3, 3.5
    assert d["rows"][-1][0] == 3.5 and d["rows"][0][5] == 2.0
    with pytest.raises(ValueError, match="cylinder"):
        tube_profile(SphereModel.unit())
    with pytest.raises(ValueError, match="spacing"):
        tube_profile(CylinderModel.unit(), spacing_mm=0.0)
