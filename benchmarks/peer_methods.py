"""The generic peers, started from a region: shared by ``bench_peers.py`` (phantoms) and
``bench_real.py`` (public scans).

Each method takes the image (float32), the voxel size (mm), the initial region (a rasterized
sphere or cylinder) and its parameters, and returns a boolean mask and notes (iterations, stop).
None of these has a documented stopping rule that works on noisy data, so:

- morphological snakes run until the level set repeats one of its last 8 states (their
  evolution is deterministic, so it then cycles forever; on noisy data they end in a 2- or
  4-cycle that flips a few hundred voxels) or a cap of :data:`MORPH_CAP` iterations;
- the SimpleITK level set runs in chunks of :data:`ITK_CHUNK` iterations, each restarted from
  the signed distance of the previous result, until the region changes by less than
  :data:`ITK_STILL` of its volume between chunks (its RMS change stays around 0.05 on noisy
  data, far above any useful ``MaximumRMSError``) or :data:`ITK_CAP` iterations.

Methods:

``skimage MCV``
    ``morphological_chan_vese`` (3D) on the image rescaled to [0, 1] (1st-99th percentile),
    ``lambda1 = lambda2 = 1``, ``smoothing`` a parameter.
``skimage MGAC``
    ``morphological_geodesic_active_contour`` on ``inverse_gaussian_gradient(image01,
    alpha=100, sigma)``, ``balloon=1`` (expand), ``sigma``, ``smoothing`` and ``threshold``
    parameters (skimage's ``"auto"`` threshold is the 40th percentile of the edge-stopping
    image).
``SimpleITK GAC``
    ``GeodesicActiveContourLevelSetImageFilter`` (propagation 1, curvature and advection
    parameters) on ``Sigmoid(GradientMagnitudeRecursiveGaussian(image, sigma))`` with the ITK
    Software Guide's ``alpha = -(K1 - K2) / 6``, ``beta = (K1 + K2) / 2``: K1 (edge level) is
    Otsu's threshold of the gradient magnitude, K2 (inside level) its median over the initial
    region. Initial level set: signed distance of the initial region (mm, negative inside).
``SimpleITK confidence connected``
    ``ConfidenceConnected`` region growing from the initial region's centre voxel, ``multiplier``
    and ``iterations`` parameters (ITK-SNAP's and 3D Slicer's classic seeded region growing).
    ITK's initial neighbourhood is a box of half-width r voxels along every axis; r is the
    initial region's smallest half-extent in voxels (so the box stays inside it).
``Otsu + morphology``
    Gaussian pre-smoothing (``sigma`` voxels), ``threshold_otsu``, binary opening, the connected
    component containing the centre, binary closing and hole filling (6-connectivity: a
    3 x 3 x 3 cross as the structuring element).

Every region result is post-processed alike by :func:`region_post`: the connected component
that contains the initialization's centre (the largest if it does not), holes filled.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from scipy import ndimage

#: Iterations after which a morphological snake that has not started cycling is stopped.
MORPH_CAP = 300
#: Iterations of the SimpleITK level set between two checks of its change.
ITK_CHUNK = 50
#: Iterations after which the SimpleITK level set is stopped.
ITK_CAP = 400
#: Change of the region between two checks, as a fraction of its volume, that counts as still.
ITK_STILL = 0.002


class _Cycle(Exception):
    """Raised from the morphological snakes' callback to stop them once they cycle."""


def run_morph(fn: Callable, *args: Any, **kwargs: Any) -> tuple[np.ndarray, int, str]:
    """Run a morphological snake until its level set repeats a recent state, or MORPH_CAP."""
    recent: list[bytes] = []
    state = {"n": 0, "u": None}

    def callback(u: np.ndarray) -> None:
        state["n"] += 1
        key = np.packbits(u.astype(bool)).tobytes()
        if key in recent:
            state["u"] = u.astype(bool)
            raise _Cycle
        recent.append(key)
        del recent[:-8]

    try:
        u = fn(*args, num_iter=MORPH_CAP, iter_callback=callback, **kwargs)
        return u.astype(bool), state["n"], "cap"
    except _Cycle:
        return state["u"], state["n"], "cycle"


def unit(image: np.ndarray) -> np.ndarray:
    """The image rescaled to [0, 1] between its 1st and 99th percentiles (float32)."""
    lo, hi = np.percentile(image, [1, 99])
    return np.clip((image - lo) / max(hi - lo, 1e-12), 0.0, 1.0).astype(np.float32)


def component(mask: np.ndarray, center: tuple[int, ...]) -> np.ndarray:
    """The connected component containing ``center`` (the largest one if it is background)."""
    lab, n = ndimage.label(mask)
    if n == 0:
        return mask
    k = lab[center]
    if k == 0:
        k = int(np.argmax(np.bincount(lab.ravel())[1:])) + 1
    return lab == k


def largest(mask: np.ndarray) -> np.ndarray:
    """The largest connected component of ``mask``."""
    lab, n = ndimage.label(mask)
    if n == 0:
        return mask
    return lab == int(np.argmax(np.bincount(lab.ravel())[1:])) + 1


def region_post(mask: np.ndarray, center: tuple[int, ...]) -> np.ndarray:
    """The component containing ``center`` (else the largest), holes filled."""
    return ndimage.binary_fill_holes(component(mask, center))


def init_center(init: np.ndarray) -> tuple[int, ...]:
    """The initial region's centroid, rounded to a voxel."""
    return tuple(int(round(c)) for c in np.argwhere(init).mean(axis=0))


def mcv(img: np.ndarray, init: np.ndarray, params: dict) -> tuple[np.ndarray, dict]:
    """skimage's morphological Chan-Vese from ``init`` (raw result, not post-processed)."""
    from skimage.segmentation import morphological_chan_vese

    u, n, stop = run_morph(morphological_chan_vese, unit(img), init_level_set=init,
                           smoothing=params["smoothing"], lambda1=1, lambda2=1)
    return u, {"iterations": n, "stop": stop}


def mgac(img: np.ndarray, init: np.ndarray, params: dict) -> tuple[np.ndarray, dict]:
    """skimage's morphological geodesic active contour, expanding from ``init``."""
    from skimage.segmentation import (inverse_gaussian_gradient,
                                      morphological_geodesic_active_contour)

    g = inverse_gaussian_gradient(unit(img), alpha=100.0, sigma=params["sigma"])
    u, n, stop = run_morph(morphological_geodesic_active_contour, g, init_level_set=init,
                           smoothing=params["smoothing"], threshold=params["threshold"], balloon=1)
    return u, {"iterations": n, "stop": stop}


def sitk_gac(img: np.ndarray, spacing, init: np.ndarray, params: dict) -> tuple[np.ndarray, dict]:
    """SimpleITK's geodesic active contour level set from ``init`` (voxel spacing respected)."""
    import SimpleITK as sitk
    from skimage.filters import threshold_otsu

    # SimpleITK's axes are the numpy axes reversed; so is the spacing.
    im = sitk.GetImageFromArray(img)
    im.SetSpacing(tuple(float(s) for s in spacing)[::-1])
    gm = sitk.GradientMagnitudeRecursiveGaussian(im, float(params["sigma"]))
    garr = sitk.GetArrayViewFromImage(gm)
    k1 = float(threshold_otsu(garr))
    k2 = float(np.median(garr[init]))
    speed = sitk.Sigmoid(gm, -(k1 - k2) / 6.0, (k1 + k2) / 2.0, 1.0, 0.0)
    notes: dict[str, Any] = {"K1, K2": [round(k1, 3), round(k2, 3)]}
    mask, done, stop = init, 0, "cap"
    while done < ITK_CAP:
        m = sitk.GetImageFromArray(mask.astype(np.uint8))
        m.CopyInformation(im)
        ls = sitk.SignedMaurerDistanceMap(m, insideIsPositive=False, squaredDistance=False,
                                          useImageSpacing=True)
        f = sitk.GeodesicActiveContourLevelSetImageFilter()
        f.SetPropagationScaling(1.0)
        f.SetCurvatureScaling(float(params["curvature"]))
        f.SetAdvectionScaling(float(params["advection"]))
        f.SetMaximumRMSError(0.01)
        f.SetNumberOfIterations(ITK_CHUNK)
        new = sitk.GetArrayFromImage(f.Execute(ls, speed)) < 0
        done += int(f.GetElapsedIterations())
        change = np.count_nonzero(new ^ mask) / max(np.count_nonzero(new), 1)
        mask = new
        if change < ITK_STILL or f.GetElapsedIterations() < ITK_CHUNK:
            stop = "converged"
            break
    notes.update(iterations=done, stop=stop)
    return mask, notes


def confidence_connected(img: np.ndarray, init: np.ndarray, params: dict) -> tuple[np.ndarray, dict]:
    """SimpleITK's confidence-connected region growing seeded at the initial region's centre.

    The initial neighbourhood, whose mean and standard deviation start the interval, is ITK's
    box of half-width r voxels, r the initial region's smallest half-extent (at least 1).
    """
    import SimpleITK as sitk

    center = init_center(init)
    extent = [int(np.ptp(np.nonzero(init)[a])) // 2 for a in range(3)]
    radius = max(1, min(extent))
    im = sitk.GetImageFromArray(img)
    out = sitk.ConfidenceConnected(im, seedList=[tuple(int(c) for c in center[::-1])],
                                   numberOfIterations=int(params["iterations"]),
                                   multiplier=float(params["multiplier"]),
                                   initialNeighborhoodRadius=radius, replaceValue=1)
    return sitk.GetArrayFromImage(out).astype(bool), {"neighbourhood radius": radius}


def otsu_morphology(img: np.ndarray, center: tuple[int, ...], params: dict) -> np.ndarray:
    """Smoothed Otsu foreground, opened, the component at ``center``, closed, holes filled."""
    from skimage.filters import threshold_otsu

    sm = ndimage.gaussian_filter(img, params["sigma"]) if params["sigma"] > 0 else img
    fg = sm > threshold_otsu(sm)
    cross = ndimage.generate_binary_structure(3, 1)
    fg = ndimage.binary_opening(fg, cross)
    fg = component(fg, center)
    fg = ndimage.binary_closing(fg, cross, border_value=0)
    return ndimage.binary_fill_holes(fg)
