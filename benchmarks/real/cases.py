"""The real-data cases: how each reference mask and each click is derived from the public sources.

Pure functions on arrays (no files): :mod:`fetch` reads the sources and writes what these return.

Sources (see ``benchmarks/real/README.md`` for where they come from and their licences):

- Colin27 (``ch2.nii.gz``, T1 with skull and scalp, 181 x 217 x 181 at 1 mm), its brain
  (``ch2bet.nii.gz``) and the AAL atlas (``aal.nii.gz``) on the same grid, from Debian's
  ``mricron-data``.
- The chest CT ``lung2`` (HU, 512 x 512 x 61 at 0.63 x 0.63 x 5 mm, NRRD in LPS space) and its
  tumour label, from the ``pyradiomics`` 3.0.1 source archive.

References:

- brain: the non-zero voxels of ``ch2bet``, largest 6-connected component;
- an AAL structure: its label(s); the cerebellum (labels 91-116) with its holes filled;
- tumour: ``lung2_label`` == 1;
- trachea: see :func:`trachea_reference`.

Clicks (:func:`sphere_click`, :func:`tube_click`) follow issue 14: a sphere at the reference's
deepest point (the maximum of its Euclidean distance transform in mm) with half that depth as
its radius; a tube from its axis shortened by 15 % at each end, with half its radius.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from peer_methods import largest as largest_component  # benchmarks/ is on sys.path

#: Air in a CT (HU): issue 14's definition of the airway lumen.
AIR_HU = -950.0
#: Body in a CT (HU): soft tissue and bone are above it, lung parenchyma and air below.
BODY_HU = -500.0
#: Fraction of a tube's axis left out of its click at each end (issue 14).
TUBE_END_FRACTION = 0.15


def brain_reference(bet: NDArray) -> NDArray[np.bool_]:
    """Colin27's brain: the non-zero voxels of ``ch2bet``, largest component."""
    return largest_component(bet != 0)


def atlas_reference(atlas: NDArray, labels: Sequence[int], fill_holes: bool = False) -> NDArray[np.bool_]:
    """The voxels of an atlas carrying any of ``labels``, optionally with holes filled."""
    mask = np.isin(atlas, np.asarray(labels))
    return ndimage.binary_fill_holes(mask) if fill_holes else mask


def sphere_click(truth: NDArray, spacing: Sequence[float]) -> dict:
    """A sphere at the deepest point of ``truth`` with half its depth as radius (voxel indices).

    The deepest point is the voxel whose centre is farthest (in mm) from the background; ties go
    to the first in C order (``numpy.argmax``), so the click is deterministic.
    """
    sp = np.asarray(spacing, dtype=float)
    # Padded with background: outside the array is not part of the structure.
    depth = ndimage.distance_transform_edt(np.pad(truth, 1), sampling=sp)[1:-1, 1:-1, 1:-1]
    idx = np.unravel_index(int(np.argmax(depth)), truth.shape)
    r_mm = 0.5 * float(depth[idx])
    return {"shape": "sphere", "center": [int(i) for i in idx],
            "radii": np.round(r_mm / sp, 3).tolist()}


def body_mask(hu: NDArray) -> NDArray[np.bool_]:
    """The patient's body in a CT: above :data:`BODY_HU`, largest component, each axial slice
    (array axis 2) with its holes filled (the lungs and airways are holes in it)."""
    body = largest_component(hu > BODY_HU)
    for k in range(body.shape[2]):
        body[:, :, k] = ndimage.binary_fill_holes(body[:, :, k])
    return body


def trachea_reference(hu: NDArray, air_hu: float = AIR_HU) -> tuple[NDArray[np.bool_], list[int]]:
    """The trachea above the carina: air below ``air_hu`` (default :data:`AIR_HU`) inside the
    body, tracked slice by slice.

    Axis 2 must run from inferior (index 0) to superior. The lumen is tracked downwards from the
    most superior axial slice: there it is the largest air component inside the body; in each
    next slice it is the air component overlapping the previous slice's lumen. The cut above
    the carina is the first slice where two or more components overlap it (the main bronchi; on
    lung2, 5 mm slices, the bifurcation shows within one slice) or none does; that slice and
    everything below are left out.

    Returns
    -------
    mask : ndarray of bool
        The trachea.
    slices : list of int
        The axial slices it occupies, superior first.
    """
    air = (hu < air_hu) & body_mask(hu)
    mask = np.zeros(hu.shape, bool)
    top = hu.shape[2] - 1
    labels, n = ndimage.label(air[:, :, top])
    if n == 0:
        raise ValueError("no air inside the body in the most superior slice: no trachea to track")
    prev = labels == int(np.argmax(np.bincount(labels.ravel())[1:])) + 1
    mask[:, :, top] = prev
    slices = [top]
    for k in range(top - 1, -1, -1):
        labels, _ = ndimage.label(air[:, :, k])
        touching = np.unique(labels[prev & (labels > 0)])
        if len(touching) != 1:
            break
        cur = labels == touching[0]
        mask[:, :, k] = cur
        slices.append(k)
        prev = cur
    return mask, slices


def tube_click(truth: NDArray, slices: list[int], spacing: Sequence[float]) -> dict:
    """A cylinder along a tube that runs across axial slices (array axis 2), in voxel indices.

    The axis joins the centroids of the tube's first and last slices, shortened by
    :data:`TUBE_END_FRACTION` of its length at each end; the radius is half the median over
    slices of the equivalent-circle radius ``sqrt(area / pi)``, in voxels across the axis.
    """
    from segsnake.pipeline import perpendicular_spacing

    sp = np.asarray(spacing, dtype=float)
    ends = [np.asarray(ndimage.center_of_mass(truth[:, :, k]), dtype=float).tolist() + [k]
            for k in (slices[0], slices[-1])]
    a0, a1 = (np.asarray(e) * sp for e in ends)
    b0 = a0 + TUBE_END_FRACTION * (a1 - a0)
    b1 = a1 - TUBE_END_FRACTION * (a1 - a0)
    pixel = sp[0] * sp[1]
    r_mm = float(np.median([np.sqrt(truth[:, :, k].sum() * pixel / np.pi) for k in slices]))
    return {"shape": "cylinder", "axis_start": np.round(b0 / sp, 3).tolist(),
            "axis_end": np.round(b1 / sp, 3).tolist(),
            "radius": round(0.5 * r_mm / perpendicular_spacing(sp, b1 - b0), 3)}
