"""An image's affine map to a template's world (the atlas start; SimpleITK's registration).

The atlas start (:mod:`segsnake.atlas`) needs, for every voxel of the user's image, the point of
the atlas' template that shows the same anatomy. This module finds the affine map between the two
worlds the way FSL FLIRT's and ANTs' affine stages do: Mattes mutual information (intensities of
two scanners, or of a scan and an average, need not be alike), read on the template's side within
its head (the template's non-zero voxels grown by :attr:`RegistrationParams.mask_margin_mm`: a
skull-stripped template's brain and its boundary, not the neck and air of the image), coarse to
fine, first a similarity (rotation, translation, one scale) from the best of several starts
(:func:`_best_start`), then a full affine from that (:func:`register_affine`). A second affine stage
(:func:`refine_around`), as FSL FIRST's second stage with its subcortical mask, reads only the
structure of interest and its surroundings (:attr:`RegistrationParams.focus_margin_mm`), finer:
a whole-head map is a compromise over the head, and a nucleus is where it must hold.

Arrays are in index order ``(i, j, k)`` with NIfTI affines (index -> world mm), as
:mod:`segsnake.io` reads them; the map returned is a 4 x 4 matrix between the worlds. Random
metric samples take a seed and SimpleITK runs on one thread while it registers
(:func:`_sitk_work`), so one image registers to the same map every time.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["RegistrationParams", "RegistrationError", "grid_problem", "register_affine",
           "refine_around"]


class RegistrationError(ValueError):
    """The images cannot be registered (a grid SimpleITK cannot represent, no overlap)."""


@dataclass(frozen=True)
class RegistrationParams:
    """The registration's settings (each with its unit).

    mask_margin_mm : float
        How far beyond the template's non-zero voxels the metric reads (mm): the brain's boundary
        (brain against CSF and skull) is what places a skull-stripped template on a head.
    levels_mm : tuple of float
        The voxel sizes (mm) the images are read at, coarse to fine (each level shrinks the images
        to about that voxel and smooths them by half of it).
    bins : int
        Histogram bins of the mutual information.
    sample_fraction : float
        Fraction of the template's masked voxels the metric reads at each level (random, seeded).
    iterations : int
        Most optimizer steps per level and stage.
    search_mm : float
        How far (mm) the head's starts are moved along each axis from the two centred ones
        (:func:`_best_start`): a sixth of a head, within the optimizer's reach of each other.
    focus_margin_mm : float
        How far around the structure :func:`refine_around` reads (mm): its boundary and the
        neighbours that place it, not the rest of the head.
    focus_levels_mm : tuple of float
        :func:`refine_around`'s voxel sizes (mm), coarse to fine.
    focus_sample_fraction : float
        Fraction of the focus' voxels its metric reads (a small region needs more of them).
    seed : int
        Seed of the metric's random samples (from 1: SimpleITK reads 0 as "seed from the clock").
    """

    mask_margin_mm: float = 4.0
    levels_mm: tuple[float, ...] = (4.0, 2.0)
    bins: int = 32
    sample_fraction: float = 0.1
    iterations: int = 200
    seed: int = 1
    search_mm: float = 30.0
    focus_margin_mm: float = 10.0
    focus_levels_mm: tuple[float, ...] = (2.0, 1.0)
    focus_sample_fraction: float = 0.5


def grid_problem(affine: NDArray) -> str | None:
    """What keeps a grid from registration (SimpleITK's images have orthogonal axes), or None."""
    affine = np.asarray(affine, dtype=np.float64)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if not np.all(np.isfinite(affine)) or np.any(spacing <= 0):
        return "its affine has a zero or undefined voxel size"
    direction = affine[:3, :3] / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-4):
        return "its affine is sheared (its axes are not orthogonal), which registration cannot use"
    return None


def _to_sitk(array: NDArray, affine: NDArray, what: str):
    """A SimpleITK image of ``array`` (index order i, j, k, as float32) on the grid of
    ``affine``, its physical frame the affine's world (both images of a registration alike)."""
    from segsnake.io import sitk_image

    problem = grid_problem(affine)
    if problem is not None:
        raise RegistrationError(f"the {what}: {problem}")
    return sitk_image(np.asarray(array, dtype=np.float32), affine)


#: Serializes the registrations of one process: each sets SimpleITK's process-wide thread count
#: to one while it runs (threads of a batch run in one process would otherwise restore it under
#: each other).
_ONE_THREAD = threading.Lock()


@contextmanager
def _sitk_work(what: str):
    """SimpleITK's work on one thread (filters, metric and initializers: sums in one order, the
    same map to the last bit on every run; with threads maps differed by 1e-13 to 1e-8), its
    exceptions as :class:`RegistrationError`."""
    import SimpleITK as sitk

    with _ONE_THREAD:
        threads = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
        try:
            yield
        except RuntimeError as exc:  # (SimpleITK's: e.g. too few samples in both images)
            line = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
            raise RegistrationError(f"{what} failed: {line}") from None
        finally:
            sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)


def _matrix(transform) -> NDArray:
    """A SimpleITK matrix-offset transform as a 4 x 4 matrix (fixed world -> moving world)."""
    out = np.eye(4)
    a = np.asarray(transform.GetMatrix(), dtype=np.float64).reshape(3, 3)
    c = np.asarray(transform.GetCenter(), dtype=np.float64)
    t = np.asarray(transform.GetTranslation(), dtype=np.float64)
    out[:3, :3] = a
    out[:3, 3] = t + c - a @ c
    return out


def _stage(fixed, moving, fixed_mask, initial, params: RegistrationParams, max_step_mm: float,
           levels_mm: tuple[float, ...], sample_fraction: float):
    """One optimization (similarity or affine) from ``initial``, coarse to fine; its result."""
    import SimpleITK as sitk

    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsMattesMutualInformation(params.bins)
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    reg.SetMetricSamplingPercentage(sample_fraction, seed=max(1, params.seed))
    reg.SetMetricFixedMask(fixed_mask)
    # (the gradients at the samples only, not filtered over both whole images at every level:
    # half the time, the same map to 0.1 mm on Colin27)
    reg.SetMetricUseFixedImageGradientFilter(False)
    reg.SetMetricUseMovingImageGradientFilter(False)
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsRegularStepGradientDescent(max_step_mm, 1e-4, params.iterations,
                                                 relaxationFactor=0.7)
    reg.SetOptimizerScalesFromPhysicalShift()
    voxel = min(fixed.GetSpacing())
    reg.SetShrinkFactorsPerLevel([max(1, int(round(mm / voxel))) for mm in levels_mm])
    reg.SetSmoothingSigmasPerLevel([0.5 * mm for mm in levels_mm])
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    reg.SetInitialTransform(initial, inPlace=False)
    reg.SetNumberOfThreads(1)  # (the metric's own threads too: see _sitk_work)
    found = reg.Execute(fixed, moving)
    if isinstance(found, sitk.CompositeTransform):
        found = found.GetNthTransform(0)
    return found.Downcast()


def _check_extent(array: NDArray, affine: NDArray, coarse_mm: float, what: str) -> None:
    """Refuse an image too thin to read at the coarsest level (four of its voxels an axis)."""
    extent = np.asarray(array.shape[:3]) * np.linalg.norm(np.asarray(affine)[:3, :3], axis=0)
    if array.ndim != 3 or np.any(extent < 4 * coarse_mm):
        raise RegistrationError(
            f"the {what} spans {' x '.join(f'{e:.0f}' for e in extent)} mm; registration reads "
            f"it at {coarse_mm:g} mm voxels and needs at least 4 of them along each axis")


def _best_start(fixed, moving, mask, params: RegistrationParams):
    """The similarity the head's registration starts from: of the two grids' centres aligned,
    the two intensity centroids aligned, and each of these moved by ``params.search_mm`` along
    each axis, the one the metric (at the coarsest level) finds best. A scan that reaches far
    below the head (the neck, the shoulders) puts its grid's centre far from the brain's, and a
    bright scalp or neck pulls its centroid: one of the starts lies near enough for the
    optimizer to reach the brain."""
    import SimpleITK as sitk

    # (the images at the coarsest level once, smoothed and shrunk to about its voxel along each
    # axis: each start's metric then reads every masked voxel of those small images, as
    # MetricEvaluate does whatever the sampling set)
    coarse = params.levels_mm[0]

    def shrunk(image):
        factors = [max(1, int(round(coarse / s))) for s in image.GetSpacing()]
        smooth = sitk.SmoothingRecursiveGaussian(image, 0.5 * coarse)
        return sitk.Shrink(smooth, factors)

    small_fixed, small_moving = shrunk(fixed), shrunk(moving)
    small_mask = sitk.Resample(mask, small_fixed, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsMattesMutualInformation(params.bins)
    reg.SetMetricFixedMask(small_mask)
    reg.SetMetricUseFixedImageGradientFilter(False)
    reg.SetMetricUseMovingImageGradientFilter(False)
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetNumberOfThreads(1)
    best, best_value = None, np.inf
    for how in (sitk.CenteredTransformInitializerFilter.GEOMETRY,
                sitk.CenteredTransformInitializerFilter.MOMENTS):
        try:
            centred = sitk.CenteredTransformInitializer(fixed, moving,
                                                        sitk.Similarity3DTransform(), how)
        except RuntimeError:  # (the centroids of an image with no mass: the centres remain)
            continue
        for axis in range(4):
            for sign in ((0,) if axis == 3 else (-1, 1)):
                candidate = sitk.Similarity3DTransform(centred)
                shift = np.asarray(candidate.GetTranslation(), dtype=np.float64)
                if axis < 3:
                    shift[axis] += sign * params.search_mm
                candidate.SetTranslation(tuple(shift))
                reg.SetInitialTransform(candidate, inPlace=False)
                try:
                    value = reg.MetricEvaluate(small_fixed, small_moving)
                except RuntimeError:  # (a start that leaves too few samples in the image)
                    continue
                if value < best_value:
                    best, best_value = candidate, value
    if best is None:
        raise RegistrationError("the image and the template do not overlap from any start")
    return best


def register_affine(image: NDArray, affine: NDArray, template: NDArray, template_affine: NDArray,
                    params: RegistrationParams | None = None) -> NDArray:
    """The affine map from ``image``'s world to ``template``'s (4 x 4, world mm to world mm).

    Parameters
    ----------
    image, affine : ndarray
        The image (index order i, j, k) and its NIfTI affine.
    template, template_affine : ndarray
        The template (its non-zero voxels, grown by ``params.mask_margin_mm``, are where the
        metric reads) and its affine.
    params : RegistrationParams, optional

    Returns
    -------
    ndarray
        ``M`` with ``M @ [x, y, z, 1]`` the template's world point of the image's world point.

    Raises
    ------
    RegistrationError
        A grid SimpleITK cannot represent, an empty (all zero) template or image, one less than
        four coarsest-level voxels thick, or a registration that fails.
    """
    import SimpleITK as sitk

    p = params or RegistrationParams()
    template = np.asarray(template)
    for what, array in (("template", template), ("image", np.asarray(image))):
        if not np.any(array != 0):
            raise RegistrationError(f"the {what} is empty (all zero)")
    for what, array, grid in (("template", template, template_affine),
                              ("image", np.asarray(image), affine)):
        problem = grid_problem(grid)
        if problem is not None:
            raise RegistrationError(f"the {what}: {problem}")
        _check_extent(array, grid, p.levels_mm[0], what)
    with _sitk_work("the registration"):
        fixed = _to_sitk(template, template_affine, "template")
        moving = _to_sitk(np.asarray(image), affine, "image")
        grow = [max(1, int(round(p.mask_margin_mm / s))) for s in fixed.GetSpacing()]
        mask = sitk.BinaryDilate(sitk.Cast(fixed != 0, sitk.sitkUInt8), grow)
        start = _best_start(fixed, moving, mask, p)
        similar = _stage(fixed, moving, mask, start, p, 1.0, p.levels_mm, p.sample_fraction)
        general = sitk.AffineTransform(3)
        general.SetCenter(similar.GetCenter())
        general.SetMatrix(similar.GetMatrix())
        general.SetTranslation(similar.GetTranslation())
        found = _stage(fixed, moving, mask, general, p, 1.0, p.levels_mm, p.sample_fraction)
    # The transform maps the template's (fixed) points to the image's (moving): invert it.
    return np.linalg.inv(_matrix(found))


def refine_around(image: NDArray, affine: NDArray, template: NDArray, template_affine: NDArray,
                  start: NDArray, focus: NDArray, focus_affine: NDArray,
                  params: RegistrationParams | None = None) -> NDArray:
    """:func:`register_affine`'s map refined where one structure lies (an affine again, from it).

    Parameters
    ----------
    image, affine, template, template_affine : ndarray
        As :func:`register_affine`.
    start : ndarray
        The map to refine (image world -> template world, 4 x 4).
    focus, focus_affine : ndarray
        The structure in the template's world: a boolean array on its own grid (an atlas' label
        set) and that grid's affine. The metric reads the template within
        ``params.focus_margin_mm`` of it.
    params : RegistrationParams, optional

    Returns
    -------
    ndarray
        The refined map (image world -> template world).
    """
    p = params or RegistrationParams()
    if not np.any(focus):
        raise RegistrationError("the structure to register around is empty")
    with _sitk_work("the registration around the structure"):
        return _refined(image, affine, template, template_affine, start, focus, focus_affine, p)


def _refined(image, affine, template, template_affine, start, focus, focus_affine, p):
    """:func:`refine_around`'s work (within :func:`_sitk_work`)."""
    import SimpleITK as sitk

    fixed = _to_sitk(template, template_affine, "template")
    moving = _to_sitk(np.asarray(image), affine, "image")
    region = _to_sitk(np.asarray(focus, dtype=np.uint8), focus_affine, "structure")
    grow = [max(1, int(round(p.focus_margin_mm / s))) for s in region.GetSpacing()]
    region = sitk.BinaryDilate(sitk.Cast(region, sitk.sitkUInt8), grow)
    # The map from the template to the image, about the structure's centre (rotations and
    # scalings about a far origin would move it most for the smallest turn: ill-conditioned).
    inverse = np.linalg.inv(np.asarray(start, dtype=np.float64))  # template -> image
    idx = np.argwhere(focus).mean(axis=0)
    centre = np.asarray(focus_affine, dtype=np.float64)[:3] @ np.r_[idx, 1.0]
    initial = sitk.AffineTransform(3)
    initial.SetCenter(tuple(centre))
    initial.SetMatrix(tuple(inverse[:3, :3].ravel()))
    initial.SetTranslation(tuple(inverse[:3, :3] @ centre + inverse[:3, 3] - centre))
    found = _stage(fixed, moving, region, initial, p, 0.5, p.focus_levels_mm,
                   p.focus_sample_fraction)
    return np.linalg.inv(_matrix(found))
