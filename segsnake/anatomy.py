"""Anatomical directions of an image's array axes, from its voxel-to-world (RAS+) affine.

A viewer labels the sides of a slice with the patient directions R/L, A/P, S/I. For each array
axis this module finds the world axis it runs along (for an oblique affine the dominant one, the
three chosen one-to-one) and which way, so that pictures can be oriented and labelled the way
3D Slicer or ITK-SNAP show them.
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["LETTERS", "VIEW_NAMES", "axis_directions", "is_oblique", "view_axes"]

# (negative end, positive end) of the RAS+ world axes x, y, z.
LETTERS = (("L", "R"), ("P", "A"), ("I", "S"))
# A slice across world axis n is, in a viewer's terms:
VIEW_NAMES = ("sagittal", "coronal", "axial")
# Screen axes of each view (horizontal, vertical world axis), as Slicer and ITK-SNAP lay them out:
# axial x/y, coronal x/z, sagittal y/z; the positive end (R, A, S) is on the left horizontally
# (radiological convention: the patient's right on the screen's left, the nose to the left in a
# sagittal view) and at the top vertically.
_SCREEN = {2: (0, 1), 1: (0, 2), 0: (1, 2)}


def axis_directions(affine: np.ndarray) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """The world axis and direction of each array axis.

    Parameters
    ----------
    affine : ndarray, shape (4, 4)
        Voxel index to world (RAS+, mm).

    Returns
    -------
    world : tuple of 3 int
        ``world[d]`` is the world axis (0 x, 1 y, 2 z) array axis ``d`` runs along: the one with
        the largest direction cosine, chosen one-to-one over the three axes (an oblique grid whose
        two axes lean towards the same world axis still gets three distinct labels).
    sign : tuple of 3 int
        +1 when index ``d`` increasing goes towards the positive end (R, A, S), else -1.
    """
    lin = np.asarray(affine, dtype=np.float64)[:3, :3]
    cosines = np.abs(lin / np.linalg.norm(lin, axis=0))
    world = max(itertools.permutations(range(3)),
                key=lambda p: sum(cosines[p[d], d] for d in range(3)))
    sign = tuple(1 if lin[world[d], d] >= 0 else -1 for d in range(3))
    return tuple(int(w) for w in world), sign  # type: ignore[return-value]


def is_oblique(affine: np.ndarray, tol: float = 1e-3) -> bool:
    """True when some array axis is not parallel to a world axis (direction cosine below 1 - tol)."""
    lin = np.asarray(affine, dtype=np.float64)[:3, :3]
    cosines = np.abs(lin / np.linalg.norm(lin, axis=0))
    return bool(np.any(cosines.max(axis=0) < 1.0 - tol))


def view_axes(affine: np.ndarray, axis: int) -> tuple[int, int, int, int]:
    """How a slice across array ``axis`` is laid out on screen.

    Returns
    -------
    horizontal, vertical : int
        The array axes shown across and up the screen.
    world_h, world_v : int
        The world axes they run along (their positive ends R/A/S go left and up).
    """
    world, _ = axis_directions(affine)
    wh, wv = _SCREEN[world[axis]]
    h = world.index(wh)
    v = world.index(wv)
    return h, v, wh, wv
