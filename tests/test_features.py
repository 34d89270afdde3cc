"""Steerable surface detector, step detector, NMS, thresholds and the edge map f."""

import numpy as np
from scipy import ndimage
import pytest

from segsnake.errors import SegmentationError
from segsnake.features import (
    EdgeMap,
    _smallest_eig,
    auto_levels,
    edge_map,
    gaussian_derivatives,
    hysteresis_threshold,
    keep_component_nearest,
    non_maximum_suppression,
    surface_detector,
)


# ----------------------------------------------------------------------------- phantoms
def radial(shape, center, spacing):
    g = np.indices(shape).astype(float)
    return np.sqrt(sum(((g[i] - center[i]) * spacing[i]) ** 2 for i in range(3)))


def shell(shape, center, radius, spacing, thickness):
    """Thin bright spherical sheet with a Gaussian profile of std ``thickness`` mm."""
    r = radial(shape, center, spacing)
    return np.exp(-((r - radius) ** 2) / (2 * thickness**2)).astype(np.float32)


def ball(shape, center, radius, spacing=(1.0, 1.0, 1.0), sub=4):
    """Filled ball with exact-ish partial volume (sub^3 supersampling)."""
    acc = np.zeros(shape)
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    for a in offs:
        for b in offs:
            for c in offs:
                shifted = (center[0] - a, center[1] - b, center[2] - c)
                acc += radial(shape, shifted, spacing) < radius
    return acc / sub**3


def radial_errors(em, center, radius):
    """Signed radial errors in voxel units along the normal: voxel centres and refined points."""
    sp = np.asarray(em.spacing)
    idx = np.flatnonzero(em.mask)
    ijk = np.stack(np.unravel_index(idx, em.mask.shape), 1)
    n = em.normals.reshape(-1, 3)[idx].astype(float)
    c = np.asarray(center) * sp
    step = 1.0 / np.linalg.norm(n / sp, axis=1)  # mm per voxel along the normal
    vox = (np.linalg.norm(ijk * sp - c, axis=1) - radius) / step
    ref = (np.linalg.norm(em.surface_points() - c, axis=1) - radius) / step
    radial_dir = (ijk * sp - c) / np.linalg.norm(ijk * sp - c, axis=1)[:, None]
    angle = np.degrees(np.arccos(np.clip(np.abs(np.sum(n * radial_dir, 1)), 0, 1)))
    return vox, ref, step, angle


# ----------------------------------------------------------------------------- building blocks
def test_closed_form_eigen_solver_matches_eigh():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((2000, 3, 3))
    h = a + a.transpose(0, 2, 1)
    h[:5] = np.diag([1.0, 1.0, 1.0])  # isotropic: any vector
    h[5:10] = np.diag([-2.0, 1.0, 1.0])  # double eigenvalue above the smallest
    lam, lam_max, vec = _smallest_eig(h[:, 0, 0], h[:, 1, 1], h[:, 2, 2],
                                      h[:, 0, 1], h[:, 0, 2], h[:, 1, 2])
    w, v = np.linalg.eigh(h)
    assert np.abs(lam - w[:, 0]).max() < 1e-10
    assert np.abs(lam_max - w[:, 2]).max() < 1e-10
    assert np.allclose(np.linalg.norm(vec, axis=1), 1.0)
    resid = np.einsum("nij,nj->ni", h, vec) - lam[:, None] * vec
    assert np.abs(resid).max() < 1e-8
    assert np.abs(np.abs(np.sum(vec[10:] * v[10:, :, 0], 1)) - 1).max() < 1e-6


def test_gaussian_derivatives_in_mm_with_anisotropic_spacing():
    sp = (0.7, 1.0, 2.0)
    shape = (64, 48, 30)
    g = np.indices(shape) * np.asarray(sp)[:, None, None, None]
    k = np.array([0.35, 0.25, 0.15])  # rad / mm
    img = np.sin(k[0] * g[0]) * np.cos(k[1] * g[1]) * np.sin(k[2] * g[2] + 0.4)
    s = 2.0
    d = gaussian_derivatives(img, sp, s, [(1, 0, 0), (0, 2, 0), (1, 0, 1)])
    att = np.exp(-0.5 * s**2 * np.sum(k**2))  # Gaussian attenuation of a plane wave
    inner = (slice(12, -12), slice(12, -12), slice(6, -6))
    ref_x = k[0] * np.cos(k[0] * g[0]) * np.cos(k[1] * g[1]) * np.sin(k[2] * g[2] + 0.4) * att
    ref_yy = -k[1] ** 2 * img * att
    ref_xz = (k[0] * k[2] * np.cos(k[0] * g[0]) * np.cos(k[1] * g[1])
              * np.cos(k[2] * g[2] + 0.4) * att)
    for key, ref in (((1, 0, 0), ref_x), ((0, 2, 0), ref_yy), ((1, 0, 1), ref_xz)):
        err = np.abs(d[key][inner] - ref[inner]).max() / np.abs(ref[inner]).max()
        assert err < 0.02, (key, err)


def test_hysteresis_keeps_diagonal_surfaces_connected():
    v = np.zeros((10, 10, 10), np.float32)
    for i in range(8):
        v[i + 1, i + 1, 5] = 1.0  # only corner-connected
    v[1, 1, 5] = 5.0
    kept = hysteresis_threshold(v, 0.5, 4.0)
    assert kept.sum() == 8
    assert hysteresis_threshold(v, 0.5, 6.0).sum() == 0


def test_keep_component_nearest_picks_the_inner_surface():
    shape = (40, 40, 40)
    c = (19.5, 19.5, 19.5)
    r = radial(shape, c, (1, 1, 1))
    mask = (np.abs(r - 8) < 0.5) | (np.abs(r - 15) < 0.5)
    inner = keep_component_nearest(mask, c)
    assert inner.sum() == (np.abs(r - 8) < 0.5).sum()
    outer = keep_component_nearest(mask, (19.5, 19.5, 37.0))
    assert outer.sum() == (np.abs(r - 15) < 0.5).sum()


def test_auto_levels_separates_two_modes():
    rng = np.random.default_rng(1)
    v = np.concatenate([rng.uniform(0.0, 0.1, 5000), rng.uniform(0.8, 1.0, 500)])
    low, high = auto_levels(v)
    assert np.mean(v[:5000] < high) > 0.99 and np.all(v[5000:] > high)
    assert low == pytest.approx(high / 2)


# ----------------------------------------------------------------------------- issue 3 checks
@pytest.mark.parametrize("spacing,shape,scale", [((1.0, 1.0, 1.0), (40, 40, 40), 1.5),
                                                 ((1.0, 1.0, 2.5), (40, 40, 16), 2.5)])
def test_planar_sheet_normal_within_3_degrees(spacing, shape, scale):
    rng = np.random.default_rng(2)
    sp = np.asarray(spacing)
    g = np.stack(np.indices(shape), -1) * sp
    worst_angle, worst_offset = 0.0, 0.0
    for _ in range(5):
        n = rng.standard_normal(3)
        n /= np.linalg.norm(n)
        c = (np.asarray(shape) - 1) * sp / 2 + rng.uniform(-1, 1, 3)
        img = np.exp(-(((g - c) @ n) ** 2) / (2 * 0.7**2)).astype(np.float32)
        em = edge_map(img, sp, mode="surface", scale_mm=scale)
        idx = np.flatnonzero(em.mask)
        ijk = np.stack(np.unravel_index(idx, shape), 1)
        # away from the volume's faces, where the nearest-value border bends the sheet
        far = (ijk * sp >= 3 * scale) & (ijk * sp <= (np.asarray(shape) - 1) * sp - 3 * scale)
        inner = np.all(far, 1)
        assert inner.sum() > 100
        normals = em.normals.reshape(-1, 3)[idx][inner]
        angle = np.degrees(np.arccos(np.clip(np.abs(normals @ n), 0, 1)))
        step = 1.0 / np.linalg.norm(n / sp)
        offset = np.abs((em.surface_points()[inner] - c) @ n) / step
        worst_angle = max(worst_angle, angle.max())
        worst_offset = max(worst_offset, offset.max())
    assert worst_angle < 3.0
    assert worst_offset < 0.5


@pytest.mark.parametrize("spacing,scale,thickness", [((1.0, 1.0, 1.0), 1.5, 0.5),
                                                     ((1.0, 1.0, 2.5), 2.5, 1.0)])
def test_spherical_shell_edges_at_radius(spacing, scale, thickness):
    R = 16.0
    shape = tuple(int(48 / s) for s in spacing)
    c = [(n - 1) / 2 + 0.3 for n in shape]
    img = shell(shape, c, R, spacing, thickness)
    em = edge_map(img, spacing, mode="surface", scale_mm=scale)
    vox, ref, step, angle = radial_errors(em, c, R)
    assert len(vox) > 0.5 * 4 * np.pi * R**2 / max(spacing) ** 2  # closed surface, not a few bits
    assert angle.max() < 6.0
    # refined (sub-voxel, curvature-corrected) edges: within half a voxel everywhere, unbiased
    assert np.abs(ref).max() < 0.5
    assert abs(ref.mean()) < 0.05
    # NMS voxels: within half a voxel of the detector's ridge, which sits 7/6 (s^2 + t^2) / R inside
    bias = 7 / 6 * (scale**2 + thickness**2) / R / step
    assert vox.max() < 0.6
    assert np.all(vox > -(0.5 + bias + 0.1))


def test_shell_curvature_bias_constant():
    """Without the correction the surface detector's ridge sits 7/6 s^2/R inside a thin shell."""
    R, s = 16.0, 2.0
    shape = (48, 48, 48)
    c = (23.8, 23.6, 23.7)
    img = shell(shape, c, R, (1, 1, 1), 0.3)
    em = edge_map(img, (1, 1, 1), mode="surface", scale_mm=s, curvature_correction=False)
    _, ref, _, _ = radial_errors(em, c, R)
    predicted = -7 / 6 * (s**2 + 0.3**2) / R
    assert ref.mean() == pytest.approx(predicted, abs=0.03)
    corrected = edge_map(img, (1, 1, 1), mode="surface", scale_mm=s)
    _, ref_c, _, _ = radial_errors(corrected, c, R)
    assert abs(ref_c.mean()) < 0.02


@pytest.fixture(scope="module")
def noisy_ball():
    shape = (48, 48, 48)
    c = (23.7, 23.4, 24.1)
    R = 14.0
    clean = ball(shape, c, R)
    img = (clean + 0.2 * np.random.default_rng(0).standard_normal(shape)).astype(np.float32)
    return img, c, R


@pytest.mark.parametrize("scale", [1.5, 2.0])
def test_edge_mode_places_filled_ball_boundary_within_half_voxel(noisy_ball, scale):
    img, c, R = noisy_ball
    em = edge_map(img, (1, 1, 1), mode="edge", scale_mm=scale, seed=c)
    vox, ref, _, angle = radial_errors(em, c, R)
    assert len(ref) > 0.8 * 4 * np.pi * R**2
    assert np.abs(ref).max() < 0.5
    assert abs(ref.mean()) < 0.05
    assert np.sqrt(np.mean(ref**2)) < 0.12
    assert angle.max() < 10.0
    # the normals point to the brighter side (inwards) and so does the smoothed gradient
    idx = np.flatnonzero(em.mask)
    ijk = np.stack(np.unravel_index(idx, em.mask.shape), 1)
    out = (ijk - np.asarray(c)) / np.linalg.norm(ijk - np.asarray(c), axis=1)[:, None]
    assert np.all(np.sum(em.normals.reshape(-1, 3)[idx] * out, 1) < 0)
    assert np.all(np.sum(em.gradient.reshape(-1, 3)[idx] * out, 1) < 0)
    # uncorrected: the gradient maximum of a smoothed ball sits s^2/R inside
    raw = edge_map(img, (1, 1, 1), mode="edge", scale_mm=scale, seed=c, curvature_correction=False)
    _, ref_raw, _, _ = radial_errors(raw, c, R)
    assert ref_raw.mean() == pytest.approx(-(scale**2) / R, abs=0.04)


def test_first_order_edge_detector_beats_second_order_on_gradient(noisy_ball):
    """Why ``edge`` mode is the gradient detector: on the noisy ball, the surface detector run on
    |grad I_s| has more bias and spread at the same scale."""
    img, c, R = noisy_ball
    first = edge_map(img, (1, 1, 1), mode="edge", scale_mm=1.5, seed=c, curvature_correction=False)
    gm = np.linalg.norm(first.gradient, axis=-1)
    second = edge_map(gm, (1, 1, 1), mode="surface", scale_mm=1.5, seed=c,
                      curvature_correction=False)
    _, e1, _, _ = radial_errors(first, c, R)
    _, e2, _, _ = radial_errors(second, c, R)
    assert np.sqrt(np.mean(e1**2)) < np.sqrt(np.mean(e2**2))
    assert np.abs(e1).max() < np.abs(e2).max()


def test_edge_map_f_profile_and_normalisation():
    shape = (40, 30, 30)
    img = np.zeros(shape, np.float32)
    img[20:] = 1.0  # a plane step at x = 19.5
    em = edge_map(img, (1, 1, 1), mode="edge", scale_mm=1.5, smooth_mm=2.0)
    assert isinstance(em, EdgeMap)
    prof = em.f[:, 15, 15].astype(float)
    x = np.arange(shape[0])
    mean = np.sum(prof * x) / prof.sum()
    std = np.sqrt(np.sum(prof * (x - mean) ** 2) / prof.sum())
    assert mean == pytest.approx(19.5, abs=0.02)
    assert std == pytest.approx(np.sqrt(2.0**2 + 1 / 6), rel=0.02)
    assert prof.max() == pytest.approx(1.0 * 2.0 / std, rel=0.03)  # area 1 per mm^2
    assert em.f.dtype == np.float32 and em.image_smooth.dtype == np.float32
    assert em.gradient.shape == shape + (3,) and em.normals.shape == shape + (3,)


@pytest.mark.parametrize("spacing,smooth", [((1.0, 1.0, 1.0), 1.0), ((1.0, 1.0, 2.0), 2.0)])
def test_ridge_of_f_lies_on_a_curved_boundary(spacing, smooth):
    # Blurring a sphere's surface density by s moves its ridge s^2 / R inwards (0.33 mm here at
    # s = 2); the edge map places its splat so that the ridge of f is the boundary itself.
    sp = np.asarray(spacing)
    R = 12.0
    shape = tuple(int(np.ceil(36 / s)) for s in sp)
    c = (np.asarray(shape) - 1) / 2  # voxel indices
    img = ball(shape, c, R, spacing).astype(np.float32)
    em = edge_map(img, sp, mode="edge", scale_mm=1.5 * sp.max(), smooth_mm=smooth)
    rng = np.random.default_rng(0)
    d = rng.standard_normal((64, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    r = np.linspace(R - 2.0, R + 2.0, 401)
    pts = (c * sp)[None, None] + r[None, :, None] * d[:, None, :]  # mm
    prof = ndimage.map_coordinates(em.f, (pts / sp).reshape(-1, 3).T, order=3).reshape(64, -1)
    peak = r[np.argmax(prof, axis=1)]
    assert abs(peak.mean() - R) < 0.08
    assert np.abs(peak - R).max() < 0.25


def test_edge_map_f_is_orientation_and_spacing_independent():
    """f integrates to the surface area (area density): ~1 per mm^2 whatever the orientation."""
    rng = np.random.default_rng(3)
    for sp, shape in (((1.0, 1.0, 1.0), (36, 36, 36)), ((1.0, 1.0, 2.5), (36, 36, 14))):
        sp = np.asarray(sp)
        g = np.stack(np.indices(shape), -1) * sp
        n = rng.standard_normal(3)
        n /= np.linalg.norm(n)
        c = (np.asarray(shape) - 1) * sp / 2
        img = ((g - c) @ n > 0).astype(np.float32)
        em = edge_map(img, sp, mode="edge", scale_mm=2.5, smooth_mm=2.5)
        inner = tuple(slice(int(8 / s), -int(8 / s)) for s in sp)
        # integral of f across the plane (mm) divided by the ridge's sqrt(2 pi) width = 1
        idx = np.argwhere(em.mask[inner]) + [s.start for s in inner]
        vals = em.f[tuple(idx.T)]
        assert np.median(vals) == pytest.approx(1.0, rel=0.12)


def test_constant_image_has_no_edges():
    with pytest.raises(SegmentationError, match="no edges found at scale 2 mm"):
        edge_map(np.full((20, 20, 20), 7.0, np.float32), (1, 1, 1), scale_mm=2.0)
    with pytest.raises(SegmentationError, match="no edges found at scale 1.5 mm"):
        edge_map(np.zeros((20, 20, 20), np.float32), (1, 1, 1), mode="surface", scale_mm=1.5)


def test_threshold_options():
    shape = (32, 32, 32)
    c = (15.6, 15.4, 15.8)
    img = ball(shape, c, 9.0, sub=2).astype(np.float32)
    auto = edge_map(img, (1, 1, 1), scale_mm=1.5)
    none = edge_map(img, (1, 1, 1), scale_mm=1.5, threshold=None)
    high = edge_map(img, (1, 1, 1), scale_mm=1.5, threshold=auto.levels[1])
    pair = edge_map(img, (1, 1, 1), scale_mm=1.5, threshold=auto.levels)
    assert none.levels is None and none.mask.sum() >= auto.mask.sum()
    assert np.array_equal(high.mask, auto.mask) and np.array_equal(pair.mask, auto.mask)
    with pytest.raises(SegmentationError):
        edge_map(img, (1, 1, 1), scale_mm=1.5, threshold=1e9)
    thick = edge_map(img, (1, 1, 1), scale_mm=1.5, nms=False)
    assert thick.mask.sum() > 2 * auto.mask.sum()


def test_nms_is_one_voxel_thick_on_a_plane():
    shape = (30, 20, 20)
    img = np.zeros(shape, np.float32)
    img[15:] = 1.0
    em = edge_map(img, (1, 1, 1), scale_mm=1.5, threshold=None)
    assert np.array_equal(np.unique(np.argwhere(em.mask)[:, 0]), [14])


def test_surface_detector_response_sign_and_units():
    """Response on a thin sheet: -4 I_nn at its centre, positive, scale-invariant shape in mm."""
    shape = (40, 16, 16)
    for sp in (1.0, 0.5):
        x = np.arange(shape[0]) * sp
        img = np.broadcast_to(np.exp(-((x - 19 * sp) ** 2) / (2 * 0.8**2))[:, None, None], shape)
        resp, normals = surface_detector(img.astype(np.float32), (sp, sp, sp), 2.0)
        i = int(np.argmax(resp[:, 8, 8]))
        assert i == 19
        # analytic: sheet of mass sqrt(2 pi) 0.8, smoothed std sqrt(4 + 0.64): -4 I_xx(0)
        st = np.sqrt(2.0**2 + 0.8**2)
        peak = 4 * 0.8 / st**3
        assert resp[:, 8, 8].max() == pytest.approx(peak, rel=0.03)
        assert abs(normals[i, 8, 8, 0]) > 0.999


def test_non_maximum_suppression_candidates():
    r = np.zeros((9, 9, 9), np.float32)
    r[4] = 1.0
    r[3] = r[5] = 0.5
    n = np.zeros((9, 9, 9, 3), np.float32)
    n[..., 0] = 1.0
    keep = non_maximum_suppression(r, n, (1, 1, 1))
    assert keep[4].all() and not keep[3].any() and not keep[5].any()
    cand = np.zeros_like(keep)
    cand[4, :4] = True
    assert non_maximum_suppression(r, n, (1, 1, 1), candidates=cand).sum() == 4 * 9
