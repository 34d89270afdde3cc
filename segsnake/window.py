"""The part of a volume a snake works in: a box around the surface that grows with it.

The region energy's arrays (densities, the outside's statistics, the lookup) are needed only
where the surface can go in one stage, not over the whole scan: a trachea fills 0.3 % of a
chest CT, a nucleus less of a head. A :class:`Window` is an axis-aligned box of voxels around
a model plus a margin; the model moves into the window's coordinates (a translation in mm of
scaled index space) and back. Beyond the window the density is "not the object", as beyond the
field of view; a surface that comes near a face of the window that is not a face of the volume
would be held back by it from then on (:meth:`Window.reaches`): up to there the window's energy
is the whole volume's, so its stage stops there and goes on from that iterate, with the same
energy, in a window around the surface (the window only saves the work).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.surfaces import SplineSurface

__all__ = ["Window", "surface_box", "surface_samples"]


def surface_samples(model: SplineSurface, per_interval: int = 4) -> NDArray:
    """The surface sampled ``per_interval`` times per knot interval in u and v (ends and poles
    included), ``(n, 3)`` mm."""
    u = np.arange(per_interval * model.m1) / (per_interval * model.m1)
    v = np.linspace(0.0, 1.0, per_interval * model.m2 + 1)
    return model.positions(u, v).reshape(-1, 3)


def surface_box(model: SplineSurface, per_interval: int = 4) -> tuple[NDArray, NDArray]:
    """Lower and upper corners (mm) of :func:`surface_samples`."""
    pts = surface_samples(model, per_interval)  # (every iteration of a region stage)
    return pts.min(axis=0), pts.max(axis=0)


@dataclass(frozen=True)
class Window:
    """Voxels ``lo <= index < hi`` of a volume of shape ``full_shape`` and voxel size ``spacing``.

    Build it with :meth:`around`; :attr:`slices` crops an array, :meth:`model_in` and
    :meth:`model_out` move a model between the volume's and the window's coordinates.
    """

    lo: tuple[int, int, int]
    hi: tuple[int, int, int]
    full_shape: tuple[int, int, int]
    spacing: tuple[float, float, float]

    @classmethod
    def around(cls, model: SplineSurface, shape: Sequence[int], spacing: Sequence[float],
               margin_mm: float) -> "Window":
        """The voxels within ``margin_mm`` of the surface's bounding box (clipped to the
        volume; a surface outside the volume still gets at least one voxel)."""
        sp = np.asarray(spacing, dtype=np.float64)
        n = np.asarray(shape, dtype=np.int64)
        low, high = surface_box(model)
        lo = np.clip(np.floor((low - margin_mm) / sp), 0, n - 1).astype(np.int64)
        hi = np.clip(np.ceil((high + margin_mm) / sp) + 1, lo + 1, n).astype(np.int64)
        return cls(tuple(map(int, lo)), tuple(map(int, hi)), tuple(map(int, n)),
                   tuple(map(float, sp)))

    @property
    def slices(self) -> tuple[slice, slice, slice]:
        return tuple(slice(a, b) for a, b in zip(self.lo, self.hi))

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(b - a for a, b in zip(self.lo, self.hi))

    @property
    def origin_mm(self) -> NDArray:
        """The window's first voxel in the volume's coordinates (mm)."""
        return np.asarray(self.lo, dtype=np.float64) * np.asarray(self.spacing)

    @property
    def is_whole(self) -> bool:
        return self.lo == (0, 0, 0) and self.hi == self.full_shape

    def model_in(self, model: SplineSurface) -> SplineSurface:
        """The model in the window's coordinates."""
        return model.transformed(np.eye(3), -self.origin_mm)

    def model_out(self, model: SplineSurface) -> SplineSurface:
        """A model in the window's coordinates back in the volume's."""
        return model.transformed(np.eye(3), self.origin_mm)

    def model_from(self, model: SplineSurface, other: "Window") -> SplineSurface:
        """A model in ``other``'s coordinates in this window's (the same model, untouched, when
        the windows are the same: no rounding from a move out and back)."""
        return model if other == self else self.model_in(other.model_out(model))

    def embed(self, mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """A mask on the window as a mask on the whole volume (False outside the window)."""
        out = np.zeros(self.full_shape, dtype=bool)
        out[self.slices] = mask
        return out

    def within(self, other: "Window") -> "Window":
        """The part of ``other`` inside this window (at least one voxel: ``other`` is taken to
        overlap it)."""
        lo = tuple(map(max, self.lo, other.lo))
        hi = tuple(max(h, l + 1) for h, l in zip(map(min, self.hi, other.hi), lo))
        return Window(lo, hi, self.full_shape, self.spacing)

    def slices_in(self, outer: "Window") -> tuple[slice, slice, slice]:
        """This window's voxels in the arrays of a window that holds it."""
        return tuple(slice(a - o, b - o) for a, b, o in zip(self.lo, self.hi, outer.lo))

    def union(self, other: "Window") -> "Window":
        """The smallest window holding both."""
        return Window(tuple(map(min, self.lo, other.lo)), tuple(map(max, self.hi, other.hi)),
                      self.full_shape, self.spacing)

    def reaches(self, model: SplineSurface, guard_mm: float) -> bool:
        """Does the surface (in the volume's coordinates) come within ``guard_mm`` of a face of
        the window that is not a face of the volume?"""
        low, high = surface_box(model)
        lo_mm = self.origin_mm
        hi_mm = (np.asarray(self.hi) - 1) * np.asarray(self.spacing)
        inner_lo = np.asarray(self.lo) > 0
        inner_hi = np.asarray(self.hi) < np.asarray(self.full_shape)
        return bool(np.any(inner_lo & (low - lo_mm < guard_mm))
                    or np.any(inner_hi & (hi_mm - high < guard_mm)))
