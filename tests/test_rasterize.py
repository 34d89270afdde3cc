"""Masks from closed surfaces (segsnake.rasterize): voxel centres inside, every ray's crossings
counted once, even where it meets an edge or a vertex of the mesh exactly."""

import numpy as np
import pytest

from segsnake.rasterize import rasterize, scan_convert
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
