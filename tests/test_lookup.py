"""Lookup volume: exact interpolant, derivatives, outside values, divergence theorem."""

import numpy as np
import pytest
from scipy import ndimage

from segsnake import _sampling
from segsnake.lookup import Lookup

SPACING = (0.8, 1.0, 1.3)
SHAPE = (60, 50, 40)


def _grid(shape=SHAPE, spacing=SPACING):
    return np.stack(np.indices(shape), axis=-1) * np.asarray(spacing)


def _rotation(a, b, c):
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return rz @ ry @ rx


# ----------------------------------------------------------------------------- analytic fields
C1, S1 = np.array([24.0, 25.0, 26.0]), np.array([6.0, 5.0, 7.0])
C2, S2 = np.array([30.0, 20.0, 22.0]), np.array([4.0, 6.0, 5.0])


def blobs(x):
    return 3 * np.exp(-np.sum(((x - C1) / S1) ** 2, -1) / 2) - 2 * np.exp(
        -np.sum(((x - C2) / S2) ** 2, -1) / 2)


def blobs_lap(x):
    out = 0.0
    for a, c, s in ((3, C1, S1), (-2, C2, S2)):
        g = a * np.exp(-np.sum(((x - c) / s) ** 2, -1) / 2)
        out = out + g * np.sum((x - c) ** 2 / s**4 - 1 / s**2, -1)
    return out


def blobs_grad(x):
    out = 0.0
    for a, c, s in ((3, C1, S1), (-2, C2, S2)):
        g = a * np.exp(-np.sum(((x - c) / s) ** 2, -1) / 2)
        out = out + (-(x - c) / s**2) * g[..., None]
    return out


def poly(x):
    X, Y, Z = (x[..., i] - 24.0 for i in range(3))
    return 1e-3 * (X**3 - 2 * X * Y * Z + 0.5 * Z**3 + 3 * Y**2 * X) + 0.05 * X * Y


def poly_lap(x):
    X, Y, Z = (x[..., i] - 24.0 for i in range(3))
    return 1e-3 * (6 * X + 3 * Z + 6 * X)


def trig(x):
    return np.sin(x[..., 0] / 5.0) * np.cos(x[..., 1] / 7.0) * np.sin(x[..., 2] / 6.0 + 0.3)


def trig_lap(x):
    return -(1 / 25 + 1 / 49 + 1 / 36) * trig(x)


# ----------------------------------------------------------------------------- quadratures
def ellipsoid_flux(lookup, center, radii, rot, nu=160, nv=80):
    """Surface integral of G dy^dz over a parametric ellipsoid, outward normal sigma_v x sigma_u."""
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    x, wv = np.polynomial.legendre.leggauss(nv)
    v, wv = (x + 1) * np.pi / 2, wv * np.pi / 2
    U, V = np.meshgrid(u, v, indexing="ij")
    a, b, c = radii
    s = np.stack([a * np.cos(U) * np.sin(V), b * np.sin(U) * np.sin(V), c * np.cos(V)], -1)
    su = np.stack([-a * np.sin(U) * np.sin(V), b * np.cos(U) * np.sin(V), 0 * U], -1)
    sv = np.stack([a * np.cos(U) * np.cos(V), b * np.sin(U) * np.cos(V), -c * np.sin(V)], -1)
    s, su, sv = s @ rot.T + center, su @ rot.T, sv @ rot.T
    G, _ = lookup.sample(s.reshape(-1, 3))
    nx = sv[..., 1] * su[..., 2] - sv[..., 2] * su[..., 1]
    return float(np.sum(G.reshape(nx.shape) * nx * (2 * np.pi / nu) * wv[None, :]))


def ellipsoid_volume_integral(fun, center, radii, rot, n=36):
    """Volume integral over the ellipsoid in ellipsoidal coordinates (Gauss-Legendre)."""
    xr, wr = np.polynomial.legendre.leggauss(n)
    r, wr = (xr + 1) / 2, wr / 2
    xt, wt = np.polynomial.legendre.leggauss(n)
    th, wt = (xt + 1) * np.pi / 2, wt * np.pi / 2
    ph = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    R, TH, PH = np.meshgrid(r, th, ph, indexing="ij")
    d = np.stack([np.cos(PH) * np.sin(TH), np.sin(PH) * np.sin(TH), np.cos(TH)], -1)
    x = (d * R[..., None] * np.asarray(radii)) @ rot.T + center
    w = (wr[:, None, None] * wt[None, :, None] * (np.pi / n)) * R**2 * np.sin(TH) * np.prod(radii)
    return float(np.sum(fun(x) * w))


SURFACES = [
    ((22.0, 24.0, 25.0), (8.0, 6.0, 7.0), _rotation(0.3, -0.5, 0.8)),
    ((28.0, 22.0, 30.0), (10.0, 9.0, 5.0), _rotation(1.1, 0.2, -0.4)),
    ((24.5, 25.5, 24.0), (4.0, 4.5, 3.5), np.eye(3)),
]


@pytest.fixture(scope="module")
def lookups():
    g = _grid()
    return {
        "blobs": Lookup.from_field(blobs(g).astype(np.float32), SPACING),
        "poly": Lookup.from_field(poly(g), SPACING),
        "trig": Lookup.from_field(trig(g), SPACING),
    }


# ----------------------------------------------------------------------------- tests
def test_interpolant_is_scipy_cubic_spline_and_passes_through_samples():
    rng = np.random.default_rng(0)
    values = rng.standard_normal((9, 7, 11))
    lk = Lookup(values, SPACING)
    # More points than one sampling block (lookup._BLOCK), so the blocks are stitched too.
    t = rng.uniform(0, 1, (20000, 3)) * (np.asarray(values.shape) - 1)
    g, _ = lk.sample(t * SPACING)
    coef = ndimage.spline_filter(values, order=3, mode="mirror")
    ref = ndimage.map_coordinates(coef, t.T, order=3, mode="mirror", prefilter=False)
    assert np.abs(g - ref).max() < 1e-12
    gi, _ = lk.sample(np.stack(np.indices(values.shape), -1).reshape(-1, 3) * SPACING)
    assert np.abs(gi - values.ravel()).max() < 1e-12


def test_weights_are_a_partition_of_unity():
    # A constant is reproduced exactly with a zero gradient only if the compiled kernel's four
    # weights sum to one and their derivatives to zero at every fractional position.
    lk = Lookup(np.full((6, 5, 7), 2.5), SPACING)
    t = np.random.default_rng(1).uniform(0, 1, (5000, 3)) * (np.asarray(lk.shape) - 1)
    g, dg = lk.sample(t * SPACING)
    assert np.abs(g - 2.5).max() < 1e-13 and np.abs(dg).max() < 1e-12


def test_kernel_rejects_mismatched_buffers():
    lk = Lookup(np.zeros((4, 4, 4)), SPACING)
    p = np.zeros((3, 3))
    with pytest.raises(ValueError, match="g_out"):
        _sampling.sample(lk._flat, lk._pshape, lk.shape, lk.spacing, p, np.empty(2),
                         np.empty((3, 3)))
    with pytest.raises(ValueError, match="padded_shape"):
        _sampling.sample(lk._flat, lk.shape, lk.shape, lk.spacing, p, np.empty(3),
                         np.empty((3, 3)))
    with pytest.raises(ValueError, match="points: expected a C-contiguous float64"):
        _sampling.sample(lk._flat, lk._pshape, lk.shape, lk.spacing, p.astype(np.int64),
                         np.empty(3), np.empty((3, 3)))  # same item size, not read as doubles
    with pytest.raises(ValueError, match="padded_shape"):  # a size that would overflow
        _sampling.sample(lk._flat, (2**61 + 5, 5, 5), (2**61 + 1, 1, 1), lk.spacing, p,
                         np.empty(3), np.empty((3, 3)))


@pytest.mark.parametrize("shape", [(12, 9, 10), (2, 5, 3), (1, 6, 7)])
def test_gradient_matches_central_differences_of_the_sampler(shape):
    rng = np.random.default_rng(1)
    lk = Lookup(rng.standard_normal(shape), SPACING)
    ext = (np.asarray(shape) - 1) * SPACING
    p = rng.uniform(-0.02, 1.02, (300, 3)) * ext + rng.uniform(-0.2, 0.2, (300, 3)) * (ext == 0)
    # (a few points outside the box too; on a single-sample axis every point is outside)
    _, dg = lk.sample(p)
    h = 1e-6
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        fd = (lk.sample(p + e)[0] - lk.sample(p - e)[0]) / (2 * h)
        scale = np.abs(dg[:, a]).max() + 1e-12
        # skip points within h of the box faces, where the clamp has a kink of the second kind
        ok = (np.abs(p[:, a]) > 2 * h) & (np.abs(p[:, a] - ext[a]) > 2 * h)
        assert ok.sum() > 250
        assert np.abs(fd - dg[:, a])[ok].max() < 1e-6 * scale


def test_gradient_is_continuous_across_knots():
    rng = np.random.default_rng(2)
    lk = Lookup(rng.standard_normal((10, 10, 10)), (1.0, 1.0, 1.0))
    knots = np.array([[4.0, 5.3, 2.7], [3.2, 6.0, 5.5], [7.1, 2.2, 3.0]])
    eps = 1e-9
    for a in range(3):
        e = np.zeros(3)
        e[a] = eps
        _, left = lk.sample(knots - e)
        _, right = lk.sample(knots + e)
        assert np.abs(left - right).max() < 1e-6


def test_outside_the_box_is_clamped_and_continuous():
    rng = np.random.default_rng(3)
    shape = (8, 9, 10)
    lk = Lookup(rng.standard_normal(shape), SPACING)
    ext = (np.asarray(shape) - 1) * np.asarray(SPACING)
    inside = np.array([[3.1, 4.2, 5.3]])
    for a in range(3):
        for face, beyond in ((0.0, -2.5), (ext[a], ext[a] + 2.5)):
            on = inside.copy()
            on[0, a] = face
            out = inside.copy()
            out[0, a] = beyond
            g_on, d_on = lk.sample(on)
            g_out, d_out = lk.sample(out)
            assert g_out[0] == pytest.approx(g_on[0], abs=1e-12)
            assert d_out[0, a] == 0.0
            # the mirror spline has zero slope across the face, so the clamp is C1 there
            assert abs(d_on[0, a]) < 1e-9
            assert np.allclose(d_out[0, [b for b in range(3) if b != a]],
                               d_on[0, [b for b in range(3) if b != a]])


def test_empty_and_nan_points():
    lk = Lookup(np.random.default_rng(7).random((5, 5, 5)), (1, 1, 1))
    g, dg = lk.sample(np.zeros((0, 3)))
    assert g.shape == (0,) and dg.shape == (0, 3)
    g, dg = lk.sample(np.array([[1.0, np.nan, 2.0], [1.0, 2.0, 3.0]]))
    assert np.isnan(g[0]) and np.all(np.isnan(dg[0])) and np.isfinite(g[1])
    g, dg = lk.sample(np.array([[np.inf, 1.0, 1.0], [1.0, -np.inf, 2.0]]))
    assert np.all(np.isnan(g)) and np.all(np.isnan(dg))


def test_single_point_and_float32_input():
    lk = Lookup.from_field(np.random.default_rng(4).random((6, 6, 6)).astype(np.float32), (1, 1, 1))
    g, dg = lk.sample(np.array([2.5, 2.5, 2.5]))
    assert np.ndim(g) == 0 and dg.shape == (3,)
    g2, dg2 = lk.sample(np.array([[2.5, 2.5, 2.5]]))
    assert g == g2[0] and np.array_equal(dg, dg2[0])


@pytest.mark.parametrize("name", ["blobs", "poly", "trig"])
def test_dG_dx_is_the_laplacian(lookups, name):
    lap = {"blobs": blobs_lap, "poly": poly_lap, "trig": trig_lap}[name]
    rng = np.random.default_rng(5)
    p = C1 + rng.uniform(-8, 8, (200, 3))
    _, dg = lookups[name].sample(p)
    ref = lap(p)
    assert np.abs(dg[:, 0] - ref).max() < 2e-3 * np.abs(ref).max()


@pytest.mark.parametrize("name", ["blobs", "poly", "trig"])
@pytest.mark.parametrize("surface", range(len(SURFACES)))
def test_divergence_theorem(lookups, name, surface):
    lap = {"blobs": blobs_lap, "poly": poly_lap, "trig": trig_lap}[name]
    center, radii, rot = SURFACES[surface]
    center = np.asarray(center)
    flux = ellipsoid_flux(lookups[name], center, radii, rot)
    vol = ellipsoid_volume_integral(lap, center, radii, rot)
    assert abs(flux - vol) <= 1e-3 * abs(vol), (flux, vol)


def test_divergence_theorem_vector_field_and_volume_integral():
    g = _grid()
    grad = blobs_grad(g)
    lk_v = Lookup.from_vector_field(grad[..., 0], grad[..., 1], grad[..., 2], SPACING)
    lk_f = Lookup.from_field(blobs(g), SPACING, divergence_of_gradient=False)
    for center, radii, rot in SURFACES:
        center = np.asarray(center)
        vol_lap = ellipsoid_volume_integral(blobs_lap, center, radii, rot)
        assert abs(ellipsoid_flux(lk_v, center, radii, rot) - vol_lap) <= 1e-3 * abs(vol_lap)
        vol_f = ellipsoid_volume_integral(blobs, center, radii, rot)
        assert abs(ellipsoid_flux(lk_f, center, radii, rot) - vol_f) <= 1e-4 * abs(vol_f)


def test_divergence_theorem_on_spline_sphere_model(lookups):
    surfaces = pytest.importorskip("segsnake.surfaces")
    if not hasattr(surfaces, "SphereModel"):
        pytest.skip("segsnake.surfaces has no SphereModel yet")
    for center, radii, rot in SURFACES:
        model = surfaces.SphereModel.ellipsoid(center, radii, rot, m1=9, m2=9)
        gb, w = model.quadrature(order=12)
        s, su, sv = gb.evaluate(model.control_points())
        G, _ = lookups["blobs"].sample(s.reshape(-1, 3))
        nx = model.orientation * (sv[..., 1] * su[..., 2] - sv[..., 2] * su[..., 1])
        flux = float(np.sum(w * G.reshape(nx.shape) * nx))
        vol = ellipsoid_volume_integral(blobs_lap, np.asarray(center), radii, rot)
        assert abs(flux - vol) <= 1e-3 * abs(vol), (flux, vol)



def test_padded_lookup_has_no_density_beyond_the_grid():
    # pad: the density (lap f, or f) is zero on the pad voxels around the grid, and sampled
    # there at points shifted by the pad: inside it is the same flux (the x part integrated from
    # f_xx instead of taken as f_x), outside none, where the clamped lookup continues the
    # grid's last planes outwards.
    g = _grid()
    pad = 2
    shift = pad * np.asarray(SPACING)
    f = blobs(g)

    class Shifted:
        def __init__(self, lookup):
            self.lookup = lookup

        def sample(self, points):
            return self.lookup.sample(np.asarray(points) + shift)

    padded = Shifted(Lookup.from_field(f, SPACING, pad=pad))
    for center, radii, rot in SURFACES:
        center = np.asarray(center)
        vol = ellipsoid_volume_integral(blobs_lap, center, radii, rot)
        assert abs(ellipsoid_flux(padded, center, radii, rot) - vol) <= 2e-3 * abs(vol)
    # A field whose Laplacian is 2 everywhere: a ball inside holds 2 x its volume; a ball past
    # the grid's +y face none padded, and clamped far from none (the face's planes go on).
    quad = g[..., 1] ** 2
    extent = (np.asarray(f.shape) - 1) * np.asarray(SPACING)
    inside = extent / 2
    outside = inside + np.array([0.0, extent[1] / 2 + 6.0, 0.0])
    ball = 4 / 3 * np.pi * 3.0 ** 3
    lk = Shifted(Lookup.from_field(quad, SPACING, pad=pad))
    eye = np.eye(3)
    assert abs(ellipsoid_flux(lk, inside, (3.0, 3.0, 3.0), eye) - 2 * ball) < 1e-3 * ball
    assert abs(ellipsoid_flux(lk, outside, (3.0, 3.0, 3.0), eye)) < 1e-3 * ball
    clamped = Lookup.from_field(quad, SPACING)
    assert abs(ellipsoid_flux(clamped, outside, (3.0, 3.0, 3.0), eye)) > ball


def test_a_density_written_in_place_gives_the_same_lookup():
    # Lookup.volume_integral: the density is written into the coefficients' own array and
    # integrated there (the region stages' lookups, issue 18): the same bits as from a
    # separate field, float32 or float64.
    f = blobs(_grid()).astype(np.float32)
    ref = Lookup.from_field(f, SPACING, divergence_of_gradient=False)

    def write(values):
        assert values.dtype == np.float64 and values.shape == f.shape
        values[...] = f

    got = Lookup.volume_integral(f.shape, SPACING, write)
    assert np.array_equal(got.coef, ref.coef)
    p = np.random.default_rng(2).uniform(0, 20, (50, 3))
    assert np.array_equal(got.sample(p)[1], ref.sample(p)[1])


def test_float32_coefficients_sample_the_same_integral():
    # Half the memory (the region stages' lookups): the volume integral through the surface
    # is the float64 lookup's to float32 rounding, and the kernel reads either type.
    f = blobs(_grid()).astype(np.float32)

    def write(values):
        values[...] = f

    lk64 = Lookup.volume_integral(f.shape, SPACING, write)
    lk32 = Lookup.volume_integral(f.shape, SPACING, write, dtype=np.float32)
    assert lk32.coef.dtype == np.float32 and lk32.coef.nbytes * 2 == lk64.coef.nbytes
    p = np.random.default_rng(2).uniform(0, 20, (500, 3))
    (g64, d64), (g32, d32) = lk64.sample(p), lk32.sample(p)
    assert np.abs(g32 - g64).max() <= 1e-6 * np.abs(g64).max()
    assert np.abs(d32 - d64).max() <= 1e-5 * np.abs(d64).max()
    for center, radii, rot in SURFACES:
        a, b = ellipsoid_flux(lk64, center, radii, rot), ellipsoid_flux(lk32, center, radii, rot)
        assert abs(a - b) <= 1e-6 * abs(a)
    with pytest.raises(ValueError, match="float64 or float32"):
        Lookup.volume_integral(f.shape, SPACING, write, dtype=np.float16)
    with pytest.raises(ValueError, match="coef: expected a C-contiguous float64"):
        _sampling.sample(lk64._flat.astype(np.int64), lk64._pshape, lk64.shape, lk64.spacing,
                         p, np.empty(len(p)), np.empty((len(p), 3)))
