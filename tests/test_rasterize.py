"""Masks from closed surfaces (segsnake.rasterize): voxel centres inside, every ray's crossings
counted once, even where it meets an edge or a vertex of the mesh exactly."""

import numpy as np
import pytest

from segsnake.rasterize import SelfCrossing, crossing_volume, rasterize, scan_convert, windings
from segsnake.surfaces import CylinderModel, SphereModel


def _grid(shape):
    return np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"),
                    axis=-1)


def test_an_ellipsoid_holds_the_voxel_centres_inside_it():
    # On an anisotropic grid, away from the surface (where the mesh's chords may differ from the
    # spline by ~1e-2 voxel) the mask is the analytic inside.
    shape, sp = (40, 34, 22), (0.7, 0.9, 1.6)
    centre, radii = np.array([13.0, 15.0, 17.0]), np.array([9.0, 11.0, 12.0])
    model = SphereModel.ellipsoid(centre, radii)
    mask = rasterize(model, shape, sp)
    r = np.sqrt((((_grid(shape) * sp - centre) / radii) ** 2).sum(axis=-1))
    assert mask.dtype == bool and mask.shape == shape
    assert mask[r < 0.97].all() and not mask[r > 1.03].any()
    # and the voxel count is the volume's to the boundary layer's rounding
    assert mask.sum() * np.prod(sp) == pytest.approx(4 / 3 * np.pi * np.prod(radii), rel=0.02)


def test_a_tube_leaving_the_grid_is_cut_by_its_faces():
    tube = CylinderModel.from_axis((-10.0, 20.0, 20.0), (60.0, 20.0, 20.0), 8.0, 8, 6)
    mask = rasterize(tube, (50, 40, 40), (1.0, 1.0, 1.0))
    g = _grid((50, 40, 40))
    radial = np.hypot(g[..., 1] - 20, g[..., 2] - 20)
    assert mask[radial < 7.9].all() and not mask[radial > 8.1].any()


def _cube(lo, hi):
    """An axis-aligned box as 12 outward triangles (each face split along a diagonal)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    p = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], float)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return p, np.array(tris)


def test_rays_through_edges_and_vertices_are_counted_once():
    # A box whose corners lie on rays: its top and bottom faces' edges and diagonals pass
    # exactly through voxel columns. A crossing counted twice or missed would fill a column up
    # to the top of the grid; the half-open rule gives 5 columns a side, exactly.
    points, tris = _cube((2.0, 2.0, 2.5), (7.0, 7.0, 7.5))
    mask = scan_convert(points, tris, (10, 10, 10))
    assert mask.sum() == 5 * 5 * 5
    assert mask[3:7, 3:7, 3:8].all() and not mask[:, :, :3].any() and not mask[:, :, 8:].any()
    # the reverse orientation gives the same mask (the even-odd rule)
    assert np.array_equal(scan_convert(points, tris[:, ::-1], (10, 10, 10)), mask)


def test_an_octahedron_with_its_vertices_on_rays():
    # Four faces meet at each vertex; the rays through them and through the edges between them
    # see every crossing once: every voxel centre strictly inside is in, none strictly outside.
    c = np.array([6.0, 6.0, 6.0])
    points = c + 4 * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1],
                               [0, 0, -1]], float)
    tris = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                     [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    mask = scan_convert(points, tris, (13, 13, 13))
    l1 = np.abs(_grid((13, 13, 13)) - c).sum(axis=-1)
    assert mask[l1 < 4].all() and not mask[l1 > 4].any()


def _ellipsoid_mesh(center, radii):
    return SphereModel.ellipsoid(np.asarray(center, float), np.asarray(radii, float),
                                 None, 9, 9).triangles(36, 36)


def test_windings_tell_embedded_from_inverted_and_doubled_meshes():
    points, tris = _ellipsoid_mesh((10, 11, 12), (6, 5, 4))
    assert windings(points, tris) == (0, 1, 0.0)
    lo, hi, inside_out = windings(points / 0.25, tris[:, ::-1])  # rays 0.25 mm apart
    assert (lo, hi) == (-1, 0)
    # the volume wound -1 times is the mesh's (by the divergence theorem)
    a, b, c = (points[tris[:, k]] for k in range(3))
    volume = np.einsum("fd,fd->", a, np.cross(b, c)) / 6
    assert inside_out * 0.25 ** 3 == pytest.approx(volume, rel=0.002)
    # two overlapping balls in one mesh wrap their overlap twice: a lens of
    # pi (4 r + d) (2 r - d)^2 / 12 for radius r = 5 and centres d = 4 apart; disjoint, none
    ball, tris2 = _ellipsoid_mesh((10, 11, 12), (5, 5, 5))
    other, _ = _ellipsoid_mesh((14, 11, 12), (5, 5, 5))
    twice = np.vstack([tris2, tris2 + len(ball)])
    lo, hi, lens = windings(np.vstack([ball, other]) / 0.25, twice)
    assert (lo, hi) == (0, 2)
    assert lens * 0.25 ** 3 == pytest.approx(np.pi * 24 * 36 / 12, rel=0.02)
    far, _ = _ellipsoid_mesh((40, 11, 12), (5, 5, 5))
    assert windings(np.vstack([ball, far]), twice) == (0, 1, 0.0)
    # a shell: a small ball inside, turned inward, bounds a cavity
    inner, tris3 = _ellipsoid_mesh((10, 11, 12), (2, 2, 2))
    shell = np.vstack([points, inner])
    assert windings(shell, np.vstack([tris, tris3[:, ::-1] + len(points)]))[:2] == (0, 1)
    assert windings(shell, np.vstack([tris, tris3 + len(points)]))[:2] == (0, 2)


def test_windings_count_rays_through_edges_and_vertices_once():
    # every vertex and edge of the box's faces and of the octahedron lies on rays: a crossing
    # counted twice or missed leaves a ray at winding -1 or 2
    points, tris = _cube((2.0, 2.0, 2.5), (7.0, 7.0, 7.5))
    assert windings(points, tris) == (0, 1, 0.0)
    c = np.array([6.0, 6.0, 6.0])
    octa = c + 4 * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1],
                             [0, 0, -1]], float)
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                      [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    assert windings(octa, faces) == (0, 1, 0.0)
    assert windings(octa, faces[:, ::-1])[:2] == (-1, 0)


def _squashed_sphere(top_scale):
    """A sphere's spline (radius 10 mm) whose upper half is scaled along z by ``top_scale`` (a
    number, or a function of x on the unit sphere)."""
    m1 = m2 = 9
    u = np.arange(m1) / m1
    v = np.arange(1, m2) / m2
    theta, phi = np.meshgrid(2 * np.pi * u, np.pi * v, indexing="ij")
    p = np.stack([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi)], -1)
    scale = top_scale(p[..., 0]) if callable(top_scale) else top_scale
    p[..., 2] = np.where(p[..., 2] > 0, scale * p[..., 2], p[..., 2])
    north = top_scale(0.0) if callable(top_scale) else top_scale
    return SphereModel.from_points(10 * p + 20, (20, 20, 20 + 10 * north), (20, 20, 10))


def test_crossing_volume_of_a_dented_surface_and_of_one_pushed_through_itself():
    assert crossing_volume(_squashed_sphere(1.0)) == 0.0
    assert crossing_volume(_squashed_sphere(0.3)) == 0.0  # flattened, still bounding a region
    # its top pushed down past its bottom: the lens between them is inside out, all of it
    inverted = _squashed_sphere(-1.5)
    assert crossing_volume(inverted) == pytest.approx(-inverted.volume(order=8), rel=0.03)
    # its top pushed down through its bottom on one side only: the two cross
    assert crossing_volume(_squashed_sphere(lambda x: -0.4 - x)) > 10.0
    # a tube, capped; one bent back on itself so that its legs overlap
    assert crossing_volume(CylinderModel.from_axis((10, 10, 5), (10, 10, 40), 5.0)) == 0.0
    # (legs' axes 6 mm apart, radius 3 mm: they touch, and overlap where they join the bend)
    hairpin = np.array([(10, 10, 5), (10, 10, 35), (13, 10, 42), (16, 10, 35), (16, 10, 5)])
    apart = hairpin + np.array([-8, -8, 0, 8, 8])[:, None] * [1, 0, 0]
    assert crossing_volume(CylinderModel.from_centerline(apart, 3.0, m2=12)) == 0.0
    assert crossing_volume(CylinderModel.from_centerline(hairpin, 3.0, m2=12)) > 20.0


def _surface_samples(model, n=12):
    """Points ``(n^2, 3)`` on the surface away from its poles and their outward normals."""
    u = (np.arange(n) + 0.5) / n
    v = 0.1 + 0.8 * (np.arange(n) + 0.5) / n
    s, su, sv = model.grid_basis(u, v).evaluate(model.control_points())
    return s.reshape(-1, 3), (model.orientation * np.cross(sv, su)).reshape(-1, 3)


def test_outside_windings_are_zero_on_an_embedded_surface_and_tell_where_it_crosses():
    ball = SelfCrossing(SphereModel.ellipsoid((20, 20, 20), (10, 10, 10)))
    assert ball.volume == 0 and ball.box is None
    # Its top pushed down past its bottom: the lens between them is wound -1 times, and the
    # outward normals of both sheets point into it.
    inverted = _squashed_sphere(-1.5)
    crossing = SelfCrossing(inverted)
    lo, hi = crossing.box
    np.testing.assert_allclose(lo[:2], [10, 10], atol=2 * crossing.h)  # the lens' extent
    np.testing.assert_allclose(hi[:2], [30, 30], atol=2 * crossing.h)
    points, normals = _surface_samples(inverted)
    k = crossing.outside_windings(points, normals)
    assert set(np.unique(k)) <= {-1, 0}
    assert np.mean(k == -1) > 0.9
    assert np.all(crossing.outside_windings(points, -normals) == 0)  # the lens' other side


def test_winding_at_counts_the_faces_above_each_point_and_refuses_bad_buffers():
    from segsnake._scan import winding_at

    ball = SphereModel.ellipsoid((20, 20, 20), (10, 10, 10))
    points, tris = ball.triangles(36, 18)
    corners = np.ascontiguousarray(points[tris])
    queries = np.array([[20.0, 20, 20], [20, 20, 35], [29.5, 20, 20], [30.5, 20, 20],
                        [20, 20, 10.5], [20, 20, 9.5], [-5, 3, 1]])
    out = np.zeros(len(queries), dtype=np.int64)
    winding_at(corners, queries, out)
    assert list(out) == [1, 0, 1, 0, 1, 0, 0]
    winding_at(np.ascontiguousarray(corners[:, ::-1]), queries, out)  # turned inside out
    assert list(out) == [-1, 0, -1, 0, -1, 0, 0]
    with pytest.raises(ValueError, match="points"):
        winding_at(corners, queries.astype(np.int64), out)
    with pytest.raises(ValueError, match="points"):
        winding_at(corners, queries, out.astype(np.float64))
    with pytest.raises(ValueError, match="too many cells"):
        winding_at(corners, np.array([[0.0, 0, 0], [2.0 ** 32, 2.0 ** 32, 0]]),
                   np.zeros(2, dtype=np.int64))


def test_the_compiled_edge_lengths_and_rays_are_numpys_to_the_bit_and_refuse_bad_buffers():
    # SelfCrossing's mesh spacing h and the windings kernel's input come from these two
    # compiled gathers; they must give numpy's numbers exactly (h decides the rays, so a last
    # bit of difference could move a crossing's volume).
    from segsnake._scan import edge_lengths, on_rays

    rng = np.random.default_rng(3)
    ball = SphereModel.ellipsoid((-7.5, 20, 3), (10, 6, 8))
    bumpy = ball.with_params(ball.params + rng.normal(0, 2.0, ball.params.shape))
    points, tris = bumpy.triangles(33, 21)
    tris = np.ascontiguousarray(tris)
    corners = points[tris]
    lengths = np.empty(tris.shape)
    edge_lengths(points, tris, lengths)
    assert np.array_equal(lengths, np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1))
    h = 0.5 * float(lengths.mean())
    rays = np.empty(corners.shape)
    ox, oy = on_rays(points, tris, h, rays)
    scaled = corners / h
    origin = np.floor(scaled.reshape(-1, 3).min(axis=0))
    assert (ox, oy) == (origin[0], origin[1]) and origin[0] < 0  # (x reaches below 0)
    assert np.array_equal(rays, scaled - [ox, oy, 0.0])
    assert rays[..., :2].min() >= 0 and rays[..., :2].min() < 1
    assert on_rays(points, tris[:0], h, rays[:0]) == (0.0, 0.0)  # no faces: no shift
    with pytest.raises(ValueError, match="faces"):
        edge_lengths(points, tris.astype(np.int32), lengths)
    for bad in (len(points), -1):  # an index past either end (read where it is used)
        with pytest.raises(ValueError, match="faces"):
            on_rays(points, np.where(tris == 0, bad, tris), h, rays)
        with pytest.raises(ValueError, match="faces"):
            edge_lengths(points, np.where(tris == 0, bad, tris), lengths)
    with pytest.raises(ValueError, match="shares memory"):  # would overwrite what it reads
        edge_lengths(points, tris, tris.view(np.float64))
    with pytest.raises(ValueError, match="points"):
        edge_lengths(np.where(points == points[0], np.nan, points), tris, lengths)
    with pytest.raises(ValueError, match="out"):
        on_rays(points, tris, h, lengths)
    with pytest.raises(ValueError, match="h"):
        on_rays(points, tris, 0.0, rays)
