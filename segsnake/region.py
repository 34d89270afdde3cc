"""The region energy: what the object looks like inside, as a density whose volume integral the
snake minimizes (docs/design.md, "The region energy").

The user's click says what the object looks like: the intensities inside the initial surface
give a robust Gaussian model ``N(mu, sigma)`` (median and 1.4826 x MAD of the image smoothed at
:data:`REGION_SMOOTH_MM`). Nothing is assumed about the outside but that it lies somewhere in
the image's range ``R`` (max - min): a uniform density ``1 / R``. A voxel's
evidence for the outside is the log-likelihood ratio

    llr(x) = -log N(I(x); mu, sigma) + log(1 / R)
           = z^2 / 2 + log(sigma sqrt(2 pi) / R),        z = (I(x) - mu) / sigma,

negative for intensities within ``sqrt(2 log(R / (sigma sqrt(2 pi))))`` sigma of the click's
and positive beyond. Its volume integral over the inside is the region energy; bounded as
``w = tanh(llr / 2)`` (about ``llr / 2`` near the boundary, at most 1 per mm^3 far from it), so
that a few voxels of very different intensity (a vessel, a calcification) count as a few
voxels, not as a wall. Like every image term here it is one lookup pre-integrated along x
(:meth:`segsnake.lookup.Lookup.from_field`), so its value on a surface is a surface integral.

The region energy finds the object from inside, whatever its size, with no distance field and
no trap on internal edges; it places the surface where the intensity leaves the click's band.
An edge term then moves it onto the step: the flux of ``grad I`` through the surface (the
volume integral of ``lap I``) divided by the peak gradient ``g`` of a step of the measured
contrast ``C``, which is about minus the area on a step of the right polarity, weighted by
:data:`EDGE_LENGTH_MM`. Both are one density, ``h = w + s * EDGE_LENGTH_MM * lap(I) / g``
(``s`` = +1 for a bright object, -1 for a dark one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.errors import SegmentationError
from segsnake.parallel import gaussian_filter

__all__ = ["RegionParams", "IntensityModel", "smoothed", "image_range", "region_density",
           "boundary_fraction", "step_beyond", "step_widths", "widest_step", "along_normals",
           "weighted_median", "blend", "two_class_blend", "local_outside_mean",
           "two_class_density", "edge_density", "step_contrast", "class_separation",
           "click_depth", "coarse_factors", "JUDGING_FIELDS", "PASS_FIELDS"]

@dataclass(frozen=True)
class RegionParams:
    """The region energy's constants, each with its unit and meaning (docs/design.md; the
    sweeps that chose them are in docs/benchmarks.md)."""

    #: Gaussian smoothing (standard deviation, mm) of the image the intensity model, the
    #: click's band, the outside's mean and the class statistics read: averages the noise over
    #: about a voxel of a 1 mm scan, finer than the structures asked for. (The two-class term,
    #: which places the surface, reads the image as acquired: :func:`two_class_density`.)
    smooth_mm: float = 1.0
    #: Smoothing (mm) of the image whose Laplacian the edge term integrates.
    edge_smooth_mm: float = 1.5
    #: Weight of the edge term, a length (mm): one mm^2 of surface on a step gains about as much
    #: as this many mm^3 of the region term (0: no edge term).
    edge_length_mm: float = 0.0
    #: The outside's intensity is read in the voxels between ``shell_gap_mm`` and ``shell_mm``
    #: outside the current surface: beyond the smoothing width, where the step has ended ...
    shell_gap_mm: float = 1.0
    shell_mm: float = 4.0
    #: ... and beyond the step's own blur, point by point: the gap at each point of the
    #: surface is at least this many widths of the blur of the step there
    #: (:func:`step_widths` at the round's starting surface, less the smoothing ``smooth_mm``
    #: in quadrature), the shell keeping its thickness beyond it (0: the fixed gap alone). A
    #: Gaussian step has made 97.7 % of its contrast two widths from its centre; read nearer,
    #: the outside's mean is part of the step, which holds the surface inside it.
    blur_gaps: float = 2.0
    #: ... the blur read along the normal this far inside and outside the surface (mm): a
    #: step's fall is read to where it has dropped to half its peak, 1.18 widths from its
    #: centre: a blur of 3 mm (3.2 with the smoothing) in full from a surface up to 2 mm off
    #: its centre, and up to about 5 mm from one on it.
    blur_reach_mm: float = 6.0
    #: ... and averaged along the surface over this width (mm): the outside changes along a
    #: structure (white matter on one side, CSF on the other), not within a few mm.
    outside_smooth_mm: float = 5.0
    #: The two classes' density counts a voxel whose intensity lies within this many spreads
    #: (the click's ``sigma``) of either class mean as wholly that class, and ramps linearly in
    #: the intensity between (:func:`two_class_density`, which says why; dimensionless; 0: the
    #: ramp spans the whole step; swept 0-2 in docs/benchmarks.md, session 38).
    pure_spreads: float = 1.0
    #: Two-class stages, each reading the outside afresh beyond the previous one's surface (a
    #: surface inside the step reads part of the object as outside, which pulls it inwards).
    two_class_rounds: int = 3
    #: Coarse to fine (``coarse_to_fine``, on by default; ``--no-coarse-to-fine``;
    #: docs/design.md, "Coarse to fine"): after the two-class rounds on the 9 x 9 grid (a sphere
    #: whose M1, M2 are not given), the last round again on these finer grids (M1 = M2) in
    #: turn, each from the surface before it (:attr:`long_axis_poles`); a tube's (M1 not given)
    #: on these numbers of control points around, its rings along staying those its calibre
    #: chose. The schedule ends at
    #: the first grid refused (:attr:`finer_departure`), at the first after 13 that gains less
    #: than :attr:`finer_gain`, or at its last, 37: about 1.5 mm between control points on the
    #: hippocampus, the edge term's smoothing width (docs/benchmarks.md, session 19).
    finer_m: tuple[int, ...] = (13, 17, 21, 25, 29, 33, 37)
    #: ... each kept while it *refines* the surface rather than moving it
    #: (:func:`segsnake.departure.departure`): the volume between the finer and the coarser
    #: surface farther than the coarser grid's control spacing from the coarser surface stays
    #: below this fraction of the coarser volume (dimensionless). Detail that a coarser grid
    #: smoothed over is shorter than its control spacing, and so is the distance by which a
    #: finer grid moves the surface to bring it back; a finer grid that leaks through a gap into
    #: a neighbour of the same intensity carries part of the surface much farther. (No test on
    #: the image energy's gain for keeping a grid: on a near-tie it flipped results; nor on the
    #: enclosed volume's change, which a refinement of an elongated structure takes to 10 %
    #: and a leak that starts small to 14 %, so that the perfect-edge hippocampus flipped under
    #: 1e-12 gradient perturbations; docs/design.md, "Coarse to fine".) Measured on the real
    #: benchmark's clicks, perturbed clicks and perfect edges (143 grids; docs/benchmarks.md,
    #: session 29): every grid on a perfect-edge structure, the brain or the trachea departed by
    #: 0.000-0.005; every grid that lowered a Dice by more than 0.03, by 0.053 or more. Every
    #: decision is the same from 0.005 to 0.026.
    finer_departure: float = 0.02
    #: The schedule goes on past a kept grid while that grid lowered the image energy by at
    #: least this fraction of it (dimensionless, (E_coarse - E_fine) / |E_coarse| at a resolved
    #: quadrature): a grid that gains less shows the detail left is below what the next one
    #: would pay for in time (each finer grid costs more than the one before; on the
    #: perfect-edge structures the gains are 0.7-15 % at 13 x 13 and fall below 1 % by 21-33).
    #: The grid that gained less is kept: this only decides whether to try the next. The first
    #: finer grid's gain, read against the last round's surface (one of several minima on a
    #: noisy image), decides nothing: the second finer grid is always tried.
    finer_gain: float = 0.01
    #: A sphere's first finer grid is fitted to the surface with its poles at the ends of the
    #: surface's long axis (:func:`segsnake.resample.poles_on_long_axis`) rather than projected
    #: with the poles where the click's ball had them (the image's third axis): an elongated
    #: structure's rings then run around it, where they are short (the perfect-edge
    #: hippocampus, 53 x 34 x 15 mm: 0.941 -> 0.970). The finer grids after it are exact L2
    #: projections (:func:`segsnake.resample.resample`).
    long_axis_poles: bool = True
    #: Relative energy change per iteration at which the stages before the last stop: each
    #: only places the surface for the next one's reading of the outside (measured on a lobed
    #: blob: the first stage crept by 4e-5 per iteration for 200 iterations into the lobes,
    #: which the next rounds reach anyway); the last stage uses the ``tol`` option. The finer
    #: grids run to it too; the one kept last is then taken on to ``tol``
    #: (:func:`segsnake.region_stages.polish`).
    interim_tol: float = 1e-4
    #: Price of the volume the surface wraps other than once, per mm^3, in units of the
    #: density's scale (the two-class density lies in [-1, 1]; :class:`CrossingPenalty`). A
    #: volume integral counts a region wrapped twice twice, so a surface that passes one part
    #: through another gains up to 1 per mm^3 of it: at 2 no crossing pays. (It replaced a
    #: refusal of steps that crossed by more than 2 % of the volume, which the surfaces spent:
    #: the perfect-edge hippocampus folded within it and stayed folded, Dice 0.824; sweep in
    #: docs/benchmarks.md, session 14.)
    crossing_weight: float = 2.0
    #: A sphere's region stage grows from its click one band at a time (mm): each pass
    #: minimizes the same energy with everything farther than this beyond the pass's starting
    #: surface counted as outside (:data:`segsnake.stage.FOV_DENSITY`), from where the pass
    #: before stopped. The surface then stops at the first boundary around the click rather
    #: than the energy's deepest minimum, which can lie past it: the Colin27 brain from its
    #: click in one unbounded pass reached through the skull into the temporal muscle (2.00
    #: dm^3 against the reference's 1.74; Dice 0.933); in 8 mm bands it stops at the brain
    #: (0.952). A band must reach across what varies inside an object (at 4 mm the lung
    #: tumour's passes stall inside it); a band as wide as the object leaves the one pass's
    #: course (at 15 mm the brain's click leaks again, 0.936; at 20 mm not, 0.953): measured
    #: flat from 6 to 10 mm on the brain's and the tumour's six starts each (docs/benchmarks.md,
    #: session 18).
    #: 0: one unbounded pass.
    growth_mm: float = 8.0
    #: ... until a pass adds less than this fraction of the volume (dimensionless).
    growth_stop: float = 0.01
    #: The passes run on the image's grid coarsened by an integer factor along each axis, the
    #: largest that keeps the coarse voxel within this fraction of the start's smallest radius
    #: and within twice this fraction of ``growth_mm`` (:func:`coarse_factors`): eight voxels
    #: across the start's radius, four across the band a pass grows in, both of which a pass's
    #: surface must resolve. The passes only bring the surface to the boundary; the two-class
    #: rounds place it on the image's own grid. On 1 mm voxels a start of less than 16 mm
    #: runs its passes on the image's grid; a large organ's on 2 mm voxels, an eighth of the
    #: voxels. (Measured, docs/benchmarks.md session 22: the Colin27 brain's click and
    #: perturbed clicks the same Dice with 1, 2 and 3 mm passes; at a quarter of the radius the
    #: lung tumour's 8.4 mm start on 1.9 mm pixels lost 0.025 on a perturbed click, a
    #: cerebellum start of 8.9 mm on 2 mm voxels 0.25.) The coarse grid reads the image
    #: smoothed at ``smooth_mm`` (no further smoothing: coarse voxel i stays the image's voxel
    #: f i), well sampled at the default 2 mm; a ``growth_mm`` far beyond 8 mm would read it
    #: sparser than its smoothing. 0: every pass on the image's grid.
    coarse_fraction: float = 0.125
    #: Longest move of the surface per optimizer step (mm): about the smoothing widths, so that a
    #: step cannot jump across a boundary it has not seen.
    step_mm: float = 2.0
    #: Below this contrast between inside and outside, in units of the click's spread, the
    #: first stage found no boundary (a step of one spread is what noise alone gives).
    min_separation: float = 1.0
    #: Quality score (reported, not acted on): the surface is on a step where the intensity
    #: ``step_depth_mm`` inside and outside it differ, with the object's polarity, by more than
    #: ``step_spreads`` click spreads (twice the noise's spread is what a real step exceeds;
    #: the weakest step whose blur :attr:`blur_gaps` reads beyond, too).
    #: (A warning below half of the area was tried: on the real benchmark it flagged brains of
    #: Dice 0.92-0.94 and missed a thalamus of 0.11, so it is not a failure test.)
    step_depth_mm: float = 2.0
    step_spreads: float = 2.0
    #: The failure warning: a result whose inside and outside (the shell just beyond it) have
    #: medians closer than this many of their pooled robust spreads (:func:`class_separation`)
    #: overlaps its surroundings in intensity, and the surface is not a boundary between them.
    #: One spread apart, a boundary at the midpoint between two Gaussians misassigns 31 % of
    #: either class. (Measured: every phantom result >= 5.4; the Colin27 brain 1.8-2.5; the
    #: leaked thalamus and caudate results 0.1-1.0; docs/benchmarks.md.)
    min_class_separation: float = 1.0
    #: The failure warning for a result that grew away from its click (a sphere started about
    #: a point): the click lies less deep in it than this fraction of its deepest point's depth
    #: (:func:`click_depth`; 1 at the deepest point, 0 outside). A click is placed in the
    #: middle of what is meant, and a surface that grows from it around what looks like the
    #: click stays around it; one that ran on into a neighbour of like intensity (the Colin27
    #: thalamus down the brainstem) leaves the click near its edge. Measured on the real
    #: benchmark (docs/benchmarks.md, session 21): its clicks and their perturbed ones lie at
    #: 0.79-1.00 of their reference's greatest depth; every result above Dice 0.9 at 0.64-1.00;
    #: the thalamus results, which ran down the brainstem, at 0.08-0.44, the cerebellum's at
    #: 0.12-0.64. Half way is a round number inside that gap, not fitted to it.
    min_click_depth: float = 0.5
    #: The failure warning for a result that stopped inside its object, short of its boundary
    #: (:func:`step_beyond`): on half its area or more, a step of the object's polarity at
    #: least this many times the one the surface sits on is centred within ``step_reach_mm``
    #: beyond it. A surface on its boundary sees beyond it its own step's flank (half of a sharp
    #: step, up to about all of a blurred one or a small ball's) and its surroundings' texture;
    #: one left on a ramp inside a brighter core sees the rim's step several times its own.
    #: (Measured: docs/benchmarks.md, session 32.)
    max_step_beyond: float = 2.0
    #: ... centred up to this far beyond the surface (mm; read across ``step_depth_mm`` more):
    #: the distance by which a surface that stopped inside its object may have stopped short,
    #: within the passes' band.
    step_reach_mm: float = 6.0
    #: Smallest spread of the intensity model, as a fraction of the image's range: intensities
    #: closer than this are one tissue (a noise-free image has no spread at all).
    min_sigma_fraction: float = 0.01
    #: The click's intensities are read within this fraction of its radius from its centre (the
    #: centre is what a click places best; a perturbed or generous radius reaches outside).
    core_fraction: float = 0.5
    #: The stages work in a window of the volume around the surface (:mod:`segsnake.window`):
    #: its bounding box plus this margin (mm), enough for the shell the outside is read in and
    #: that reading's smoothing along the surface. A surface that comes within ``shell_mm`` of
    #: a face of the window runs its stage again in a window around it.
    window_mm: float = 20.0
    #: A tube's cross-section *branches* (:mod:`segsnake.branching`) when its second lumen piece
    #: holds this fraction of the tube's lumen area (the median of the largest pieces of the
    #: sections nearer its middle): a division's branches are of the trunk's order of size (the
    #: lung2 carina's smaller: 0.6 of the trachea's), a noise speck or a ragged rim is not.
    branch_fraction: float = 0.25
    #: Beyond the plane of a tube's division the density is the field of view's within this many
    #: lumen radii (of a disk of the lumen's area) of its centre, or a lumen radius past the
    #: tube's own reach beyond the plane, whichever is further: the branches' roots, which the
    #: end would have to cross to reach them, and what the tube already crept into.
    cut_radii: float = 2.0


def coarse_factors(radius_mm: float, spacing: Sequence[float], growth_mm: float,
                   fraction: float) -> tuple[int, int, int]:
    """Integer factors by which the growth passes coarsen each axis of the grid: the largest
    that keep the coarse voxel within ``fraction`` of ``radius_mm`` (the start's smallest
    radius) and within ``2 fraction`` of ``growth_mm`` (the passes' band, positive), at least
    1 (:attr:`RegionParams.coarse_fraction`). A ratio within 1e-9 of an integer counts as
    that integer: a start of exactly the bound's size (16 mm on 1 mm voxels at 1/8) does not
    hang on the rounding of its sampled radius.

    Examples
    --------
    >>> coarse_factors(23.0, (1.0, 1.0, 1.0), 8.0, 0.125)
    (2, 2, 2)
    >>> coarse_factors(8.4, (0.63, 0.63, 5.0), 8.0, 0.125)
    (1, 1, 1)
    """
    voxel = fraction * min(radius_mm, 2.0 * growth_mm)
    return tuple(max(1, int(math.floor(voxel / s + 1e-9))) for s in spacing)


#: The :class:`RegionParams` fields that only judge a result (its "no boundary found" test, its
#: quality scores and failure warnings) and do not enter the energy: a restart record
#: (:func:`segsnake.pipeline.restart_options`) does not depend on them, so a result saved before
#: one of them was added or changed still restarts unchanged.
JUDGING_FIELDS = frozenset({"min_separation", "step_depth_mm", "min_class_separation",
                            "min_click_depth", "max_step_beyond", "step_reach_mm"})

#: The :class:`RegionParams` fields that only shape a sphere's growth passes (stage 1), which a
#: run from a saved surface never runs: a restart record does not depend on them either, so a
#: result saved before ``coarse_fraction`` was added, or with other bands, still restarts
#: unchanged (its record holds everything its last stage's energy needs).
PASS_FIELDS = frozenset({"growth_mm", "growth_stop", "coarse_fraction"})

#: Fewest voxels the click's intensity model is estimated from (a sphere around the click's
#: centre grows until it holds them): below ~20 samples the MAD is not a spread.
MIN_SAMPLES = 20


@dataclass(frozen=True)
class IntensityModel:
    """The inside's robust Gaussian ``N(mu, sigma)`` and the image's range ``R`` (the outside's
    uniform density is ``1 / R``), all in image units."""

    mu: float
    sigma: float
    range: float

    @classmethod
    def from_samples(cls, inside: NDArray, image_range: float,
                     min_sigma_fraction: float = RegionParams.min_sigma_fraction
                     ) -> "IntensityModel":
        """Median and 1.4826 x MAD (at least ``min_sigma_fraction`` of the range) of ``inside``
        (the smoothed image under the click)."""
        inside = np.asarray(inside, dtype=np.float64)
        if inside.size < MIN_SAMPLES:
            raise SegmentationError(f"the click holds {inside.size} voxels; the intensity model "
                                    f"needs at least {MIN_SAMPLES}: give a larger radius")
        if not image_range > 0:
            raise SegmentationError("the image is constant: no intensity model")
        mu = float(np.median(inside))
        sigma = max(1.4826 * float(np.median(np.abs(inside - mu))),
                    min_sigma_fraction * image_range)
        return cls(mu, sigma, float(image_range))

    def to_dict(self) -> dict[str, float]:
        return {"mu": self.mu, "sigma": self.sigma, "range": self.range}


def smoothed(image: NDArray, spacing: Sequence[float], sigma_mm: float) -> NDArray:
    """The image (float32) smoothed by a Gaussian of ``sigma_mm`` along every axis."""
    return gaussian_filter(image, [sigma_mm / s for s in spacing], mode="nearest")


def image_range(image_s: NDArray) -> float:
    """The (smoothed) image's range, max - min: what the outside's uniform density spans. (A
    percentile range is 0 on a binary image of a small structure; the smoothing has already
    removed single-voxel outliers, and ``R`` enters the density only through its logarithm.)"""
    return float(np.max(image_s)) - float(np.min(image_s))


def region_density(image_s: NDArray, model: IntensityModel,
                   out: NDArray | None = None) -> NDArray:
    """``w = tanh(llr / 2)`` per voxel (float32, see the module docstring; into ``out`` if
    given, e.g. the inside of a padded array)."""
    out = _output(image_s, out)
    for i in range(image_s.shape[0]):  # plane by plane: no float64 copy of the volume
        out[i] = _click_plane(image_s[i], model)
    return out


def _output(image_s: NDArray, out: NDArray | None) -> NDArray:
    if out is None:
        return np.empty(image_s.shape, dtype=np.float32)
    if out.shape != image_s.shape:
        raise ValueError(f"out has shape {out.shape}, the image {image_s.shape}")
    return out


def _click_plane(plane: NDArray, model: IntensityModel) -> NDArray:
    """:func:`region_density` of one plane."""
    offset = np.float32(math.log(model.sigma * math.sqrt(2 * math.pi) / model.range))
    z = (plane - np.float32(model.mu)) * np.float32(1.0 / model.sigma)
    return np.tanh(np.float32(0.25) * z * z + np.float32(0.5) * offset)


def step_contrast(image_s: NDArray, inside: NDArray, shell: NDArray) -> tuple[float, int]:
    """Contrast ``C`` and polarity (+1: the object is brighter) of the step between the voxels
    ``inside`` and those of a ``shell`` just outside, from their medians."""
    a, b = float(np.median(image_s[inside])), float(np.median(image_s[shell]))
    return abs(a - b), (1 if a >= b else -1)


def class_separation(image_s: NDArray, inside: NDArray, shell: NDArray) -> float:
    """How far apart the intensities of the voxels ``inside`` and of a ``shell`` just outside
    are: the difference of their medians over their pooled robust spread,
    ``|m_in - m_out| / sqrt((s_in^2 + s_out^2) / 2)``, ``s = 1.4826 MAD`` (for two Gaussians of
    one spread, the distance of their means in spreads; infinite for two different constant
    classes, 0 for one)."""
    a, b = image_s[inside], image_s[shell]
    m_in, m_out = float(np.median(a)), float(np.median(b))
    s_in = 1.4826 * float(np.median(np.abs(a - np.float32(m_in))))
    s_out = 1.4826 * float(np.median(np.abs(b - np.float32(m_out))))
    spread = math.sqrt((s_in * s_in + s_out * s_out) / 2)
    contrast = abs(m_in - m_out)
    return contrast / spread if spread > 0 else (math.inf if contrast > 0 else 0.0)


#: Voxels of the result's inside :func:`click_depth` measures on at most (the mask is read at
#: every k-th voxel above that: a brain's depth then to 2 of its 50 mm, in 0.03 s, not 0.4).
DEPTH_VOXELS = 1 << 18


def click_depth(inside: NDArray[np.bool_], spacing: Sequence[float],
                point_mm: Sequence[float]) -> float:
    """How deep ``point_mm`` (mm, in ``inside``'s grid: voxel ``i`` at ``i * spacing``) lies in
    the mask ``inside``: the distance of its nearest voxel to the nearest voxel outside, over the
    largest such distance of any voxel inside (1 at the deepest point, a voxel's depth next to
    the surface, 0 outside; on a grid of at most about :data:`DEPTH_VOXELS` inside voxels, every
    k-th voxel along each axis; beyond the array is outside).

    Parameters
    ----------
    inside : bool ndarray, 3D
        The result's voxels.
    spacing : sequence of 3 float
        Voxel size in mm along the array axes.
    point_mm : sequence of 3 float
        The point, usually the click.
    """
    from scipy import ndimage

    inside = np.asarray(inside, dtype=bool)
    count = int(np.count_nonzero(inside))
    if count == 0:
        return 0.0
    k = max(1, math.ceil(round((count / DEPTH_VOXELS) ** (1 / 3), 9)))
    sp = np.asarray(spacing, dtype=np.float64) * k
    box = ndimage.find_objects(inside.view(np.uint8))[0]
    lo = np.array([b.start for b in box])
    coarse = np.pad(inside[tuple(slice(b.start, b.stop, k) for b in box)], 1)
    depth = ndimage.distance_transform_edt(coarse, sampling=sp)
    deepest = float(depth.max())  # (0: every k-th voxel missed a mask of thin threads)
    idx = np.rint((np.asarray(point_mm, dtype=np.float64) - lo * sp / k) / sp).astype(int) + 1
    if deepest == 0.0 or np.any(idx < 0) or np.any(idx >= depth.shape):
        return 0.0
    return float(depth[tuple(idx)]) / deepest


#: A Gaussian's full width at half maximum in standard deviations, ``2 sqrt(2 ln 2)``.
FWHM_PER_WIDTH = 2.0 * math.sqrt(2.0 * math.log(2.0))


def widest_step(reach_mm: float) -> float:
    """The widest step :func:`step_widths` can read with this reach (mm): a fall whose
    half-maximum lies at both ends of its profile, ``2 reach_mm`` long."""
    return 2.0 * reach_mm / FWHM_PER_WIDTH


def _along_normals(image_s: NDArray, samples: tuple[NDArray, NDArray], spacing: Sequence[float],
                   offsets_mm: NDArray) -> NDArray:
    """``I_s(x + t n)`` for each offset ``t`` (rows) and each point ``x`` with its outward unit
    normal ``n`` of ``samples`` (columns; linear interpolation, the image's edge value beyond
    it)."""
    from scipy import ndimage

    pts, unit = samples
    sp = np.asarray(spacing, dtype=np.float64)
    return np.stack([ndimage.map_coordinates(image_s, ((pts + t * unit) / sp).T, order=1,
                                             mode="nearest") for t in offsets_mm])


def _steps_along_normals(image_s: NDArray, model, spacing: Sequence[float], polarity: int,
                         depth_mm: float, offsets_mm: NDArray) -> tuple[NDArray, NDArray]:
    """The step ``polarity * (I_s(y - d n) - I_s(y + d n))`` at ``y = x + t n`` for each offset
    ``t`` (rows) and each of the surface's area samples ``x`` (columns; ``n`` the outward unit
    normal, ``d = depth_mm``; the image's edge value beyond it), and the samples' area weights."""
    pts, unit, area = model.area_samples(4)
    offsets = np.asarray(offsets_mm, dtype=np.float64)
    values = _along_normals(image_s, (pts, unit), spacing,
                            np.concatenate([offsets - depth_mm, offsets + depth_mm]))
    return polarity * (values[:offsets.size] - values[offsets.size:]), area


def step_widths(image_s: NDArray, samples: tuple[NDArray, NDArray], spacing: Sequence[float],
                polarity: int, reach_mm: float, min_step: float) -> NDArray:
    """The Gaussian width (mm) of the step at each point of ``samples`` (points and outward unit
    normals), from its steepest fall's full width at half maximum: along the normal, between
    ``reach_mm`` inside and ``reach_mm`` outside (read every quarter of the finest voxel), the
    fall of ``image_s`` of the object's ``polarity`` per mm, its peak, and where on either side
    of the peak it has dropped to half of it (interpolated; the profile's end where it has
    not), over ``2 sqrt(2 ln 2)``. A step blurred by a Gaussian of ``s`` falls as that Gaussian:
    its width is ``s`` (the smoothing of ``image_s`` and the voxels' own box included), read
    near the step alone, whatever lies farther along the profile; less the spread the linear
    interpolation between voxels adds to the reading. 0 where the profile's ends differ by less
    than ``min_step`` in the object's polarity (no step of it there).
    """
    sp = np.asarray(spacing, dtype=np.float64)
    dt = 0.25 * float(sp.min())
    n = max(1, int(math.ceil(reach_mm / dt)))
    values = polarity * _along_normals(image_s, samples, sp, np.arange(-n, n + 1) * dt)
    fall = -np.diff(values, axis=0) / dt  # (at the midpoints between samples)
    peak = fall.argmax(axis=0)
    cols = np.arange(fall.shape[1])
    top = fall[peak, cols]
    half = 0.5 * top
    k = np.arange(fall.shape[0])[:, None]
    below = fall < half
    # the last sample below half before the peak, the first after it (none: the profile's end)
    left = np.where(below & (k < peak), k, -1).max(axis=0)
    right = np.where(below & (k > peak), k, fall.shape[0]).min(axis=0)

    def crossing(j: NDArray, inner: NDArray) -> NDArray:
        # where the fall crosses half between sample j (below) and its neighbour inner (above)
        jj, ii = np.clip(j, 0, fall.shape[0] - 1), np.clip(inner, 0, fall.shape[0] - 1)
        a, b = fall[jj, cols], fall[ii, cols]
        frac = np.where(a < b, (half - a) / np.where(a < b, b - a, 1.0), 0.0)
        return np.where((j >= 0) & (j < fall.shape[0]), j + frac * (inner - j), inner)

    fwhm = (crossing(right, right - 1) - crossing(left, left + 1)) * dt
    width = fwhm / FWHM_PER_WIDTH
    ok = (top > 0) & (values[0] - values[-1] >= min_step)
    # (less the linear interpolation's own spread along the normal: a triangle one voxel wide,
    # of variance voxel^2 / 6, which the reading adds and the image does not hold)
    interpolation = np.sum((samples[1] * sp) ** 2, axis=1) / 6.0
    return np.where(ok, np.sqrt(np.maximum(width ** 2 - interpolation, 0.0)), 0.0)


def along_normals(values: NDArray, samples: tuple[NDArray, NDArray], shape: Sequence[int],
                  spacing: Sequence[float], reach_mm: float, default: float, bin_mm: float,
                  offset: Sequence[int] = (0, 0, 0)) -> NDArray:
    """A field on the grid (float32) that carries each point's value out along its normal: at
    each voxel, the mean of the ``values`` of the points of ``samples`` (points in the grid's mm,
    outward unit normals) whose normal passes within ``reach_mm`` outside through its bin,
    shared with the neighbouring bins by a normalized Gaussian of one bin, so that normals that
    diverge leave no gaps; ``default`` where none passes near. The bins are the image's voxels
    grouped by the integer factor along each axis that keeps a bin within ``bin_mm``, counted
    from the image's first voxel (``offset``: the index of the grid's first voxel in the image),
    so that grids cut from one image at different places bin it alike; the normal is read every
    half of the finest voxel."""
    pts, unit = samples
    sp = np.asarray(spacing, dtype=np.float64)
    shape = np.array([int(n) for n in shape])
    off = np.asarray(offset, dtype=np.int64)
    factor = np.maximum(1, np.floor(bin_mm / sp + 1e-9)).astype(np.int64)
    first = off // factor  # (the image's bin of the grid's first voxel)
    coarse = tuple(int(n) for n in (off + shape - 1) // factor - first + 1)
    ts = np.arange(0.0, reach_mm + 1e-9, 0.5 * float(sp.min()))
    idx = np.floor((pts[None] + ts[:, None, None] * unit[None]) / sp + 0.5).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < shape), axis=-1)
    vals = np.broadcast_to(np.asarray(values, dtype=np.float64)[None], ok.shape)[ok]
    flat, inverse = np.unique(
        np.ravel_multi_index(tuple(((idx[ok] + off) // factor - first).T), coarse),
        return_inverse=True)
    total = np.zeros(coarse, dtype=np.float32)
    count = np.zeros(coarse, dtype=np.float32)
    total.flat[flat] = np.bincount(inverse, weights=vals)
    count.flat[flat] = np.bincount(inverse)
    total = _weighted_mean(gaussian_filter(total, (1.0,) * 3, mode="constant", copy=False),
                           gaussian_filter(count, (1.0,) * 3, mode="constant", copy=False),
                           default)
    return total[np.ix_(*((np.arange(n) + o) // f - b
                          for n, o, f, b in zip(shape, off, factor, first)))]


def boundary_fraction(image_s: NDArray, model, spacing: Sequence[float], polarity: int,
                      min_step: float, depth_mm: float) -> float:
    """The fraction of the surface's area that lies on a step: where ``polarity * (I_s(x - d n) -
    I_s(x + d n)) > min_step`` (``n`` the outward unit normal, ``d = depth_mm``). A surface that
    leaked into tissue like the object's, or stopped inside it, has little of its area there."""
    step, area = _steps_along_normals(image_s, model, spacing, polarity, depth_mm,
                                      np.zeros(1))
    return float(np.sum(area[step[0] > min_step]) / max(np.sum(area), 1e-300))


def step_beyond(image_s: NDArray, model, spacing: Sequence[float], polarity: int,
                depth_mm: float, reach_mm: float, min_step: float) -> float:
    """How much stronger a step of the object's polarity lies just beyond the surface than the
    one it sits on: at each area sample ``x`` the largest step (as :func:`boundary_fraction`
    measures it, across ``2 depth_mm``) centred between ``depth_mm`` and ``reach_mm`` beyond
    ``x`` along the outward normal, over the step at ``x`` itself (at least ``min_step``, the
    weakest step that is one); the area-weighted median of that ratio over the surface.

    About 1 or less on a surface that sits on its object's boundary (the steps beyond it are
    its surroundings' texture, or its own step's flank: half of a sharp step, more of a blurred
    one or a small ball's, 0.5-1.1 measured); large where the
    surface stopped inside its object short of a boundary, on a ramp or an inner step (an
    object brighter in its middle than at its rim). The offsets are spaced half the finest
    voxel apart, so no step between them is missed."""
    sp = np.asarray(spacing, dtype=np.float64)
    offsets = np.arange(depth_mm, reach_mm + 1e-9, 0.5 * float(sp.min()))
    if offsets.size == 0:
        return 0.0
    steps, area = _steps_along_normals(image_s, model, sp, polarity, depth_mm,
                                       np.concatenate([[0.0], offsets]))
    ratio = steps[1:].max(axis=0) / np.maximum(steps[0], min_step)
    return weighted_median(ratio, area)


def weighted_median(values: NDArray, weights: NDArray) -> float:
    """The value below which half the total weight lies (the lower one at an exact tie)."""
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def local_outside_mean(image_s: NDArray, shell: NDArray, spacing: Sequence[float],
                       smooth_mm: float) -> NDArray:
    """The outside's mean intensity near each voxel (float32): the image averaged over the
    ``shell`` voxels with a Gaussian of ``smooth_mm`` (normalized convolution); far from the
    shell, where the weights vanish, the shell's median."""
    sigma = [smooth_mm / s for s in spacing]
    # (in place: at 256^3 the straightforward form held 4.5 x the image at once)
    weight = gaussian_filter(shell.astype(np.float32), sigma, mode="nearest", copy=False)
    total = gaussian_filter(np.where(shell, image_s, np.float32(0)), sigma, mode="nearest",
                            copy=False)
    return _weighted_mean(total, weight, np.float32(np.median(image_s[shell])))


def _weighted_mean(total: NDArray, weight: NDArray, default) -> NDArray:
    """A normalized convolution's result: the smoothed weighted values ``total`` over the
    smoothed weights ``weight``, ``default`` where the weights vanish (1e-3 or less); in place
    in ``total``, whose ``weight`` it overwrites."""
    floor = np.float32(1e-3)
    far = weight <= floor
    total /= np.maximum(weight, floor, out=weight)
    total[far] = default
    return total


#: The narrowest ramp of :func:`two_class_density`, in spreads: where the two means lie within
#: ``2 pure_spreads`` spreads of each other the pure bands would meet, and the density becomes
#: a steep but continuous step across this width (no division by zero). It matters little:
#: there :func:`blend` weights the click's band by 0.45 or more (with ``pure_spreads`` = 1).
RAMP_FLOOR = 0.1


def two_class_density(image: NDArray, model: IntensityModel, outside_mean: NDArray,
                      pure_spreads: float = RegionParams.pure_spreads) -> NDArray:
    """The fraction of a voxel outside the object, as the inside's mean ``mu`` and the local
    outside's ``mu_out`` say, mapped onto [-1, 1] (float32): -1 at ``mu``, +1 at ``mu_out``,
    zero at their midpoint, which on a step blurred symmetrically is the step, and between them
    ``(2 I - mu - mu_out) / r`` with the step's sign, a ramp linear in ``I`` across
    ``r = |mu - mu_out| - 2 pure_spreads sigma``: within ``pure_spreads`` spreads of either mean
    a voxel is wholly that class (:attr:`RegionParams.pure_spreads`). Where the means lie within
    ``2 pure_spreads + RAMP_FLOOR`` spreads of each other the ramp is held at
    :data:`RAMP_FLOOR` spreads wide, and where they lie within one spread ``|mu - mu_out|`` is
    replaced by ``sigma`` in the denominator (the ramp then ``RAMP_FLOOR sigma^2 / |mu - mu_out|``
    wide): :func:`blend` reads the click's band by 0.45 or more there, wholly within one spread.

    Linear because a voxel's intensity is linear in the share of it the object fills, whatever
    the scanner's blur and slice profile: a voxel the boundary crosses counts in proportion to
    that share, and the surface comes to rest where the interpolated share is one half, between
    the samples (docs/design.md, "Stage 2, two classes"). A density that saturates within the step
    (``tanh`` of the log-likelihood ratio, before session 37) counts such a voxel as wholly
    inside or outside, and the surface comes to rest half way between the last sample inside and
    the first outside: across 2.5 mm slices, a 6 mm vessel 5-8 % wide. Flat within a spread of
    each mean (session 38) because a deviation that small is the class's own noise or texture
    (the cerebellum's folia), not a share of the other class.

    ``image`` is the image as acquired, not smoothed: the density is odd about the midpoint and
    linear in ``I`` near it, so under noise symmetric about the signal its expectation is still
    zero exactly where the signal crosses the midpoint, and the volume integral averages the
    noise. Smoothing would move that crossing on a curved boundary: inwards by about
    ``s^2 (k1 + k2) / 2`` for a Gaussian of ``s``, ``s^2 / R`` on a sphere of radius ``R``
    (0.36 mm on a 3 mm ball at ``s`` = 1 mm, docs/design.md)."""
    out = _output(image, None)
    for i in range(image.shape[0]):  # plane by plane: no float64 copy of the volume
        out[i] = _two_class_plane(image[i], outside_mean[i], model, pure_spreads)
    return out


def _two_class_plane(plane: NDArray, outside_mean: NDArray, model: IntensityModel,
                     pure_spreads: float) -> NDArray:
    """:func:`two_class_density` of one plane: ``(a^2 - b^2) / (|step| ramp)`` is
    ``(2 I - mu - mu_out) / ramp`` with the sign of ``step``. (``max(|step|, sigma)`` only keeps
    ``0 / 0`` away where the local outside equals the inside: :func:`blend` gives the two
    classes no weight within a spread.)"""
    a = plane - np.float32(model.mu)
    b = plane - outside_mean
    sigma = np.float32(model.sigma)
    step = np.abs(outside_mean - np.float32(model.mu))
    ramp = np.maximum(step - np.float32(2 * pure_spreads) * sigma, np.float32(RAMP_FLOOR) * sigma)
    share = (a * a - b * b) / (np.maximum(step, sigma) * ramp)
    return np.clip(share, -1, 1, out=share)


def blend(two_class: NDArray, click: NDArray, outside_mean: NDArray,
          model: IntensityModel) -> NDArray:
    """``a * two_class + (1 - a) * click``, ``a = clip((|mu_out - mu| / sigma - 1) / 2, 0, 1)``:
    where the local outside differs from the inside by 3 spreads or more, the two classes;
    where it looks like the inside (within one spread: a same-intensity neighbour, about which
    the two classes say nothing), the click's band. (Measured on the phantoms: the two classes
    alone or the blend 0.970-0.987, the larger of the two densities 0.829-0.873.)"""
    a = np.abs(outside_mean - np.float32(model.mu), dtype=np.float32)
    a /= np.float32(model.sigma)
    a -= 1
    a /= 2
    np.clip(a, 0, 1, out=a)
    return a * two_class + (1 - a) * click


def two_class_blend(image: NDArray, image_s: NDArray, model: IntensityModel,
                    outside_mean: NDArray, out: NDArray | None = None,
                    pure_spreads: float = RegionParams.pure_spreads) -> NDArray:
    """:func:`blend` of :func:`two_class_density` (of ``image``, as acquired) and
    :func:`region_density` (of ``image_s``, smoothed: its ``z^2`` is not linear in the
    intensity, and noise would raise it everywhere), plane by plane (float32; into ``out`` if
    given): the density of the two-class stages without their three full-size arrays
    (issue 18)."""
    if image.shape != image_s.shape:
        raise ValueError(f"image has shape {image.shape}, the smoothed image {image_s.shape}")
    out = _output(image_s, out)
    for i in range(image_s.shape[0]):
        out[i] = blend(_two_class_plane(image[i], outside_mean[i], model, pure_spreads),
                       _click_plane(image_s[i], model), outside_mean[i], model)
    return out


def edge_density(image: NDArray, spacing: Sequence[float], polarity: int, contrast: float,
                 length_mm: float, smooth_mm: float) -> NDArray:
    """``polarity * length_mm * lap(I_s) / g`` (float32; ``I_s`` smoothed at ``smooth_mm``,
    ``g = contrast / (sqrt(2 pi) smooth_mm)`` the peak gradient of a sharp step of that
    contrast after the smoothing): its volume integral is ``length_mm / g`` times the flux of
    ``grad I_s`` through the surface, about ``-length_mm`` per mm^2 on a step of the given
    polarity (less on a step blurred beyond ``smooth_mm``)."""
    from segsnake.features import gaussian_derivatives

    d = gaussian_derivatives(image, spacing, smooth_mm, [(2, 0, 0), (0, 2, 0), (0, 0, 2)])
    lap = d.pop((2, 0, 0))
    for v in d.values():
        lap += v
    peak_gradient = contrast / (math.sqrt(2 * math.pi) * smooth_mm)
    lap *= np.float32(polarity * length_mm / peak_gradient)
    return lap
