"""A closed genus-0 triangle mesh of a binary mask's boundary (input of ``segsnake fit``).

Marching cubes of a binary mask is a staircase, and a mask may have handles (a sulcus bridged
by a voxel, a tunnel) or cavities that make its boundary not a sphere. The mask's largest
connected component, with its cavities filled, is smoothed with a Gaussian of the smallest
width in :data:`SMOOTHING_VOXELS` whose 0.5 level set (marching cubes, in mm of scaled index
space) is one closed surface of genus 0; the width used and the RMS distance from the binary
mask's own marching-cubes surface are returned with the mesh, so a caller can say how far the
repaired surface is from the mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage as ndi

from segsnake.parameterize import TopologyError, euler_characteristic

__all__ = ["SMOOTHING_VOXELS", "MaskSurface", "mask_surface"]

#: Gaussian widths (voxels) tried in turn; the first giving one genus-0 surface is used.
SMOOTHING_VOXELS = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)


@dataclass
class MaskSurface:
    """The mesh and how it was made."""

    points: NDArray
    faces: NDArray
    sigma_voxels: float
    distance_to_mask_rms: float
    distance_to_mask_max: float


def _largest_piece(points: NDArray, faces: NDArray) -> tuple[NDArray, NDArray]:
    """The connected component of the mesh with the most triangles (re-indexed)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(points)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    face_label = labels[faces[:, 0]]
    keep = face_label == np.argmax(np.bincount(face_label))
    faces = faces[keep]
    used = np.unique(faces)
    remap = np.full(n, -1)
    remap[used] = np.arange(len(used))
    return points[used], remap[faces]


def _marching(field: NDArray, spacing: tuple[float, float, float]) -> tuple[NDArray, NDArray]:
    from skimage.measure import marching_cubes

    padded = np.pad(field.astype(np.float32), 2)
    verts, faces, _, _ = marching_cubes(padded, 0.5, spacing=tuple(float(s) for s in spacing))
    return verts - 2 * np.asarray(spacing), faces.astype(np.int64)


def mask_surface(mask: NDArray, spacing: tuple[float, float, float]) -> MaskSurface:
    """Closed genus-0 boundary mesh of a binary mask, in mm of scaled index space.

    Raises
    ------
    ValueError
        An empty mask.
    TopologyError
        No width in :data:`SMOOTHING_VOXELS` gives a genus-0 surface.
    """
    mask = np.asarray(mask) > 0
    if not mask.any():
        raise ValueError("the mask is empty")
    labels, n = ndi.label(mask)
    if n > 1:
        mask = labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1
    mask = ndi.binary_fill_holes(mask)
    reference, _ = _marching(mask, spacing)
    for sigma in SMOOTHING_VOXELS:
        field = ndi.gaussian_filter(mask.astype(np.float32), sigma)
        points, faces = _largest_piece(*_marching(field, spacing))
        if len(faces) and euler_characteristic(faces) == 2:
            from scipy.spatial import cKDTree

            d = cKDTree(points).query(reference)[0]  # mask boundary -> smoothed surface
            return MaskSurface(points, faces, sigma, float(np.sqrt(np.mean(d * d))), float(d.max()))
    raise TopologyError(f"the mask's boundary is not a sphere even after smoothing with "
                        f"{SMOOTHING_VOXELS[-1]} voxels (handles or several pieces)")
