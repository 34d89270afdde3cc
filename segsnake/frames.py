"""The frame a cylinder snake is segmented in: one whose lookups integrate across the cylinder.

Every flux term is a surface integral of ``G n_x`` with ``G`` pre-integrated along the array's
first axis (:mod:`segsnake.energy`). For an open cylinder only the lateral surface is
integrated, which is the flux through the closed surface when the planar end caps carry no
``G n_x``: when the cylinder's axis is perpendicular to the integration axis. So a cylinder is
segmented in a frame where it is:

- a cyclic permutation of the array axes (a rotation, so orientations are kept; no resampling),
  putting first the array axis most perpendicular to the cylinder, when the caps then tilt by
  less than :data:`OBLIQUE_TOL` (as a sine) from that axis;
- otherwise a rotated grid with axes ``(e1, e2, a)``, ``a`` the cylinder's axis: the image is
  resampled (trilinear, isotropic at the smallest voxel size) into a rotated box that holds the
  volume's whole extent along the tube and :data:`REACH` initial radii (plus :data:`MARGIN_MM`)
  around its axis, and the snake is mapped back afterwards (the spline models are affine
  invariant). Without it an oblique tube feels its caps' missing flux as a force on its ends
  (measured before, std 50: a tube along (1, 1, 1) Jaccard 0.90, a short one 0.12). A rotated
  grid of more than :data:`MAX_VOXEL_RATIO` times the image's voxels falls back to the permuted
  frame (a thin tube across a large, anisotropic CT would otherwise cost tens of GB).

Positions are in mm of "scaled index space" (voxel ``(i, j, k)`` at ``(i sx, j sy, k sz)``) in
both frames; ``x_orig = M x_frame + t``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from segsnake.parallel import pieces, thread_map
from segsnake.surfaces import SplineSurface

__all__ = ["Frame", "flux_frame", "OBLIQUE_TOL"]

#: Largest sine of the angle between a cylinder's caps and the integration axis that a
#: permuted frame may leave (about 6 degrees); beyond it the image is resampled.
OBLIQUE_TOL = 0.1
#: The rotated grid reaches this many initial radii, plus MARGIN_MM, around the initial axis
#: (an initial tube lies inside the structure: the phantoms start at half the radius; this
#: leaves room for a quarter).
REACH = 4.0
MARGIN_MM = 15.0
#: Largest rotated grid, in voxels of the image.
MAX_VOXEL_RATIO = 2.0
#: Frame voxels resampled per piece (float64 indices: about 50 bytes per voxel at once).
_PIECE = 1 << 20


@dataclass
class Frame:
    """A rotated frame: ``x_orig = M x_frame + t`` (mm), with its grid.

    Attributes
    ----------
    M : ndarray (3, 3)
        Rotation; its columns are the frame's axes in the original frame.
    t : ndarray (3,)
        The frame's origin (its voxel (0, 0, 0)) in the original frame, mm.
    shape, spacing : tuple
        The frame's grid.
    perm : tuple of int or None
        For a permutation of the array axes (``frame axis j = original axis perm[j]``): the
        image is transposed instead of resampled.
    """

    M: NDArray
    t: NDArray
    shape: tuple[int, int, int]
    spacing: tuple[float, float, float]
    perm: tuple[int, int, int] | None = None

    @property
    def integration_direction(self) -> list[float]:
        """The frame's first axis (the lookups' integration axis) in the original frame."""
        return [float(x) for x in self.M[:, 0]]

    def model_in(self, model: SplineSurface) -> SplineSurface:
        """The snake in frame coordinates."""
        return model.transformed(self.M.T, -self.M.T @ self.t)

    def model_out(self, model: SplineSurface) -> SplineSurface:
        """The snake back in the original frame."""
        return model.transformed(self.M, self.t)

    def index_in(self, index: Sequence[float], spacing: Sequence[float]) -> list[float]:
        """Voxel indices of the original grid -> voxel indices of the frame's grid."""
        x = self.M.T @ (np.asarray(index, dtype=np.float64) * np.asarray(spacing) - self.t)
        return [float(v) for v in x / np.asarray(self.spacing)]

    def energy_in(self, energy, is_vector: NDArray) -> "_InFrame":
        """An energy of the original frame, evaluated on parameters in this frame
        (``is_vector``: the snake's parameter rows that are directions, not points)."""
        return _InFrame(energy, self, is_vector)

    def image_in(self, image: NDArray, spacing: Sequence[float]) -> NDArray:
        """The image on the frame's grid (transposed, or resampled trilinearly)."""
        if self.perm is not None:
            return np.ascontiguousarray(np.transpose(image, self.perm))
        out = np.empty(self.shape, dtype=np.float32)
        sp = np.asarray(spacing, dtype=np.float64)
        # Original voxel index = (M x + t) / sp, x = spacing * (i, j, k): one column of the
        # affine per frame axis, summed by broadcasting over a piece of frame rows.
        cols = [self.M[:, d] * self.spacing[d] / sp for d in range(3)]
        j = np.arange(self.shape[1])[:, None, None] * cols[1]
        k = np.arange(self.shape[2])[None, :, None] * cols[2]
        plane = j + k + self.t / sp  # (ny, nz, 3)

        def piece(rows: slice) -> None:
            i = np.arange(rows.start, rows.stop)[:, None, None, None] * cols[0]
            idx = np.moveaxis(i + plane[None], -1, 0)
            out[rows] = ndimage.map_coordinates(image, idx, order=1, mode="nearest",
                                                output=np.float32)

        per = max(1, _PIECE // max(self.shape[1] * self.shape[2], 1))
        thread_map(piece, pieces(self.shape[0], per))
        return out


class _InFrame:
    """An energy of the original frame, evaluated on a snake in a rotated frame."""

    def __init__(self, energy, frame: Frame, is_vector: NDArray) -> None:
        self.energy, self.frame = energy, frame
        self.shift = (~np.asarray(is_vector, dtype=bool))[:, None] * frame.t[None, :]

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        # Rows of params are points (x_orig = M x + t) or directions (M x): d x_orig / d x = M.
        value, grad = self.energy.value_and_grad(params @ self.frame.M.T + self.shift)
        return value, grad @ self.frame.M


def flux_frame(model: SplineSurface, spacing: Sequence[float],
               shape: Sequence[int]) -> Frame | None:
    """The frame to segment ``model`` in (see the module docstring); None to keep the array's.

    Spheres keep the array's frame: they are closed.
    """
    if model.kind != "cylinder":
        return None
    c0, axis, radius = model.axis_and_radius()
    a = axis / max(float(np.linalg.norm(axis)), 1e-300)
    sp = np.asarray(spacing, dtype=np.float64)
    k = int(np.argmin(np.abs(a)))
    rotated = None
    if abs(a[k]) > OBLIQUE_TOL:
        rotated = _rotated(a, k, c0 + axis / 2, radius, sp, shape)
    if rotated is not None:
        return rotated
    if abs(a[k]) >= abs(a[0]) - 1e-9:
        return None  # x is (as good as) the best axis already
    perm = (k, (k + 1) % 3, (k + 2) % 3)  # cyclic: a rotation
    M = np.zeros((3, 3))
    M[list(perm), [0, 1, 2]] = 1.0
    return Frame(M, np.zeros(3), tuple(int(shape[p]) for p in perm),
                 tuple(float(sp[p]) for p in perm), perm)


def _rotated(a: NDArray, k: int, centre: NDArray, radius: float, sp: NDArray,
             shape: Sequence[int]) -> Frame | None:
    """The rotated frame of a cylinder along ``a`` (None when its grid would be too large)."""
    e1 = np.eye(3)[k] - a[k] * a  # the array axis most across the cylinder, made perpendicular
    e1 /= np.linalg.norm(e1)
    M = np.stack([e1, np.cross(a, e1), a], axis=1)  # det +1
    corners = np.array([[i, j, kk] for i in (0, 1) for j in (0, 1) for kk in (0, 1)],
                       dtype=np.float64) * ((np.asarray(shape) - 1) * sp)
    q = corners @ M  # the volume's corners in frame axes
    lo, hi = q.min(axis=0), q.max(axis=0)
    # Across the tube, only its reach around the initial axis.
    reach = REACH * radius + MARGIN_MM
    qc = centre @ M
    lo[:2] = np.maximum(lo[:2], qc[:2] - reach)
    hi[:2] = np.minimum(hi[:2], qc[:2] + reach)
    s = float(sp.min())
    frame_shape = tuple(int(n) for n in np.ceil((hi - lo) / s - 1e-9).astype(int) + 1)
    if np.prod(frame_shape, dtype=np.float64) > MAX_VOXEL_RATIO * np.prod(shape, dtype=np.float64):
        return None
    return Frame(M, M @ lo, frame_shape, (s, s, s))
