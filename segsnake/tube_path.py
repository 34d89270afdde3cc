"""A tube's centreline between two points inside it: the cheapest path through its intensity.

A user who gives a tube's two end points (``--axis-start``, ``--axis-end``) says where it begins
and ends, not how it runs between: a vessel or an airway bends, and a straight cylinder between
the points of an S-shaped vessel lies mostly outside it. The region energy then has to find the
bends by itself, which it does or not as the optimizer's path and iteration cap go (issue 16's S
vessel on 2.5 mm slices: Dice 0.978 at the default cap, 0.885 with every stage converged, and
"no boundary found" for the thinner one). As VMTK and 3D Slicer do from two seeds, the start
follows the cheapest path between them through a cost that is low where the image looks like
the tube's inside (:func:`traced_centerline`), a minimal path on the voxel grid (scikit-image's
``MCP_Geometric``, Dijkstra's front: it explores only the voxels cheaper to reach than the end).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ["traced_centerline"]


def traced_centerline(image_s: NDArray, spacing: Sequence[float], start_mm: NDArray,
                      end_mm: NDArray, mu: float, sigma: float, step_mm: float) -> NDArray:
    """Points (mm of scaled index space) along the cheapest path from ``start_mm`` to ``end_mm``.

    Parameters
    ----------
    image_s : ndarray, 3D
        The image, smoothed as the region energy reads it.
    spacing : sequence of 3 float
        Voxel size in mm.
    start_mm, end_mm : ndarray (3,)
        The two points (inside the volume).
    mu, sigma : float
        The tube's intensity model (median and robust spread of its inside near the points).
    step_mm : float
        Spacing of the returned points along the path (the path on the voxel grid zigzags:
        each point is the mean of the path's voxels within half a step of it along the path).

    Returns
    -------
    ndarray (N, 3)
        From ``start_mm`` to ``end_mm`` exactly, N >= 2.
    """
    from skimage.graph import MCP_Geometric

    sp = np.asarray(spacing, dtype=np.float64)
    # A millimetre through a voxel ``z`` of the tube's spreads from its median costs 1 + z^2
    # (the square: the log-likelihood's): 1-2 inside the tube, 26 through a background 5 spreads
    # away, so the path leaves the tube only where staying in it is that many times longer.
    z = (np.asarray(image_s, dtype=np.float64) - mu) / sigma
    cost = 1.0 + z * z
    last = np.asarray(image_s.shape) - 1
    s0 = tuple(int(i) for i in np.clip(np.rint(np.asarray(start_mm) / sp), 0, last))
    s1 = tuple(int(i) for i in np.clip(np.rint(np.asarray(end_mm) / sp), 0, last))
    mcp = MCP_Geometric(cost, sampling=tuple(sp), fully_connected=True)
    mcp.find_costs([s0], [s1])
    voxels = np.asarray(mcp.traceback(s1), dtype=np.float64) * sp
    path = np.concatenate([[start_mm], voxels[1:-1], [end_mm]]) if len(voxels) > 2 \
        else np.stack([start_mm, end_mm])
    # Arc length along the path, then one point per step: the mean of the path's points within
    # half a step (the zigzag of neighbouring voxels averaged out), the ends kept exactly.
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    n = max(int(round(arc[-1] / step_mm)), 1)
    stations = np.linspace(0.0, arc[-1], n + 1)
    half = max(0.5 * step_mm, float(sp.max()))  # (a window that always holds a voxel)
    out = [np.asarray(start_mm, dtype=np.float64)]
    for s in stations[1:-1]:
        out.append(path[np.abs(arc - s) <= half].mean(axis=0))
    out.append(np.asarray(end_mm, dtype=np.float64))
    return np.asarray(out)
