"""The edge stages: thin sheets (``feature: surface``) and ``energy: edge``.

How the edge stages get the surface onto the boundary (design.md, "Where the minimum sits"):

1. *Edges.* The detector's edge map (``features.edge_map``), minus what cannot be the boundary:
   edges enclosed by the initial surface (the start lies inside the object, so they are internal
   structures), and in sheet mode sheets that do not face the snake's centre (sulci, septa).
2. *Capture.* The flux of ``grad(-d)``, ``d`` the distance to the remaining edges: the surface
   is pulled out towards its nearest edges from any distance, whatever the object's thickness.
   Its minimum lies about two smoothing widths inside the edge.
3. *Refinement.* The region integral of ``n_out . grad f`` (``f`` the smooth edge map, ``n_out``
   the detected normal oriented outward: down the step for a bright object, up it for a dark
   one, away from the centre for a sheet). Its first variation on the surface is
   ``n_out . grad f``, which vanishes exactly on the ridge of ``f``: no inward bias, and an edge
   of the wrong polarity repels.
4. *Inner face* (sheet mode with a polarity): for an object enclosed by a sheet (a brain in its
   CSF), capture and refinement again on the steps just inside the sheet.

Every stage minimizes its image term plus the internal energy (:mod:`segsnake.regularize`),
plus, in the edge stages, an axial pull on a cylinder's ends, and the user's shape prior, with
the step-limited L-BFGS of :mod:`segsnake.optimize` (:mod:`segsnake.stage`; the edge stages refuse
steps that fold the surface).
"""

from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from segsnake.distance import distance_to
from segsnake.errors import NoBoundaryError, SegmentationError
from segsnake.parallel import gaussian_filter, pieces, thread_map
from segsnake.pipeline import SegmentResult
from segsnake.stage import REGULARIZATION, Run
from segsnake.surfaces import SplineSurface, model_from_dict

__all__ = ["segment_edges", "with_record", "edge_support", "EdgeRun"]

#: Sheet mode with a polarity: the inner face is searched this deep inside the sheet's mid-surface
#: (mm; at least 3 detector scales). A brain's CSF and skull together are 5-10 mm thick.
INNER_FACE_DEPTH_MM = 10.0
#: ... after a refinement of the sheet stopped at this relative energy change per iteration.
INNER_FACE_SHEET_TOL = 1e-4
#: Below this mean edge strength under the final surface the segmentation is a failure.
MIN_EDGE_SUPPORT = 0.15
#: A-priori quadrature of the capture stage: nodes this many feature widths apart (see
#: :meth:`EdgeRun.capture`; the inner face's capture starts a few mm from its edges and takes
#: INNER_CAPTURE_NODE_SPACING: measured on the T1 brain, 1.9 s -> 0.8 s, same Dice).
CAPTURE_NODE_SPACING = 0.75
INNER_CAPTURE_NODE_SPACING = 2.0
#: The capture runs again at this fraction of its smoothing width (:meth:`EdgeRun.capture`): at
#: 1.5 mm it stops about 4 mm inside a hollow tube's mid-surface, where the refinement's ridge
#: term is flat and its tension shortened the tube instead (docs/benchmarks.md, session 15: the
#: sweep, which is not flat, and held-out tubes).
CAPTURE_CONTINUATION = 0.5
#: A-priori quadrature of the refinement: nodes this many feature widths apart. Its integrand
#: lives within about a ridge width of the ridge, which the surface starts within reach of;
#: at the stages' four widths (``stage.NODE_SPACING``) its rounds were accepted at 2-4 times
#: the a-priori order (Table 7.2: 8 x 9 -> 32 x 36 at std 50, 11 x 12 -> 22 x 24 at std 0; the
#: random tubes: 6 x 7 -> 12 x 14 or 18 x 18, 7 x 16 -> 28 x 48), and a round at the coarse
#: order could spend the stage's iterations before a check caught it (a short tube, 275 of
#: 300: Jaccard 0.9472 against 0.9654 as a 1e-12 perturbation went). Swept (docs/benchmarks.md,
#: session 24), the tubes' largest Dice difference under 1e-12 perturbations (the suite's
#: tubes / held-out tubes) and Table 7.2's: 4: 0.0095 / 0.0090, 0.0007; 2: 0.0030 / 0.0051,
#: 0.0000; 1: 0.0059 / 0.0058, 0.0001. The price: the brain sweep's cases 0.5-1 s slower.
REFINE_NODE_SPACING = 2.0


def _center_and_axis(model: SplineSurface) -> tuple[NDArray, NDArray | None]:
    """The centre of a sphere snake; for a cylinder its axis as (start point, end - start)."""
    if model.kind == "cylinder":
        return model.axis_and_radius()[:2]
    return model.control_points().reshape(-1, 3).mean(axis=0), None


def _radial_cosine(normals: NDArray, spacing: Sequence[float], center: NDArray,
                   axis: NDArray | None) -> NDArray:
    """``n . r`` per voxel (float32), ``r`` the unit vector pointing away from a centre, or from
    the nearest point of an axis segment.

    For a cylinder, ``center`` is the axis start and ``axis`` runs to its end: inside the
    segment's slab ``r`` is radial, beyond an end it points away from that end's centre (so the
    ends of a tube are pushed along it). Computed in slabs of planes in threads: the whole
    field as float64 arrays took 0.25 s on a 128^3 tube.
    """
    shape = normals.shape[:3]
    sp = [float(s) for s in spacing]
    c = [float(x) for x in center]
    length = float(np.linalg.norm(axis)) if axis is not None else 0.0
    a = [float(x) / max(length, 1e-12) for x in axis] if axis is not None else None
    out = np.empty(shape, dtype=np.float32)
    ys = (np.arange(shape[1], dtype=np.float32) * sp[1] - c[1])[None, :, None]
    zs = (np.arange(shape[2], dtype=np.float32) * sp[2] - c[2])[None, None, :]

    def slab(sl: slice) -> None:
        xs = (np.arange(sl.start, sl.stop, dtype=np.float32) * sp[0] - c[0])[:, None, None]
        d = [xs, ys, zs]
        if a is not None:
            along = np.clip(xs * a[0] + ys * a[1] + zs * a[2], 0.0, length)
            d = [di - along * ai for di, ai in zip(d, a)]
        n = normals[sl]
        norm = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) + 1e-6
        out[sl] = (n[..., 0] * d[0] + n[..., 1] * d[1] + n[..., 2] * d[2]) / norm

    thread_map(slab, pieces(shape[0], 16))
    return out


def _polarity(model: SplineSurface, gradient: NDArray, spacing: Sequence[float]) -> int:
    """+1 when the object is brighter than its surroundings along the current surface."""
    u = np.linspace(0, 1, 4 * model.m1, endpoint=False)
    v = np.linspace(0.05, 0.95, 4 * model.m2)
    pts = model.evaluate(u, v)[0].reshape(-1, 3)
    n = model.normals(u, v).reshape(-1, 3)
    idx = np.round(pts / np.asarray(spacing)).astype(int)
    idx = np.clip(idx, 0, np.asarray(gradient.shape[:3]) - 1)
    g = gradient[idx[:, 0], idx[:, 1], idx[:, 2]]
    return 1 if float(np.sum(g * n)) <= 0 else -1


def _default_scale(spacing: Sequence[float]) -> float:
    """The detector scale without ``--scale``: 1.5 voxels of the largest size, at least 1 mm."""
    return max(1.0, 1.5 * max(spacing))


def _final_mask(model: SplineSurface, shape, spacing) -> NDArray[np.bool_]:
    from segsnake.rasterize import rasterize

    mask = rasterize(model, shape, spacing)
    if not mask.any():
        raise SegmentationError("the final surface encloses no voxel centre")
    return mask


def segment_edges(image, sp, config, model, progress, extra_energy, init_s,
             on_boundary: bool = False, record: dict | None = None,
             first: SplineSurface | None = None) -> SegmentResult:
    """:func:`segment_volume` from the initial snake on, with the edge stages (``on_boundary``:
    the snake is a saved result, no enclosed-edge discard and no first capture).

    ``record`` (with ``on_boundary``): the saved result's restart record, usable here. Then the
    edges are discarded as the first run did, from its initial surface ``first``; the
    refinement's normals are oriented (and an automatic polarity decided) on its recorded
    starting surface, an inner face's band placed around its recorded sheet; the stages before
    the last are skipped, and the last runs on its recorded reference and order: a stationary
    result comes back unchanged (:func:`segsnake.stage.run_stage`). The last stage ends stationary, and what
    it needs is returned in ``settings["restart"]``."""
    from segsnake.features import auto_levels, edge_map, hysteresis_threshold
    from segsnake.rasterize import rasterize

    shape = image.shape
    report = progress or (lambda stage, frac: None)
    run = EdgeRun(config, sp, shape, extra_energy)
    init = model
    run.timings["init_s"] = init_s

    t0 = time.perf_counter()
    scale = config.scale if config.scale is not None else _default_scale(sp)
    seed = None if config.seed_point is None else np.asarray(config.seed_point, dtype=float)
    sheet = config.feature == "surface"
    # Thin dark sheets (the CSF around a brain in T1) are thin bright sheets of -image.
    dark_sheet = sheet and config.polarity == "dark"
    em = edge_map(-image if dark_sheet else image, sp, mode=config.feature, scale_mm=scale,
                  threshold=config.threshold, seed=seed)
    # The initial surface lies inside the object (that is the contract of an initialization):
    # edges it encloses are internal structures (ventricles, vessels), never the boundary.
    # (A saved result encloses its own boundary's edges: nothing is discarded for it, unless
    # its record gives the first run's initial surface.)
    first = model if first is None else first
    if not on_boundary or record is not None:
        inside_init = rasterize(first, shape, sp)
        _discard(em, ~ndimage.binary_dilation(inside_init) if inside_init.any() else None)
    if sheet:
        # A sheet around the object faces its centre (thesis sec. 7.2.2: keep the voxels whose
        # normal points to the centre); sheets that run radially (sulci, septa) are not it.
        _discard(em, np.abs(_radial_cosine(em.normals, sp, *_center_and_axis(first))) >= 0.5)
    run.timings["edge_map_s"] = time.perf_counter() - t0
    report("edge map", 0.15)

    if not on_boundary:
        model = run.capture(model, em.mask, em.smooth_mm)
    report("snake", 0.5)
    # (the surface the refinement starts from orients its normals)
    start = model if record is None else model_from_dict(record["refine_start"])
    if sheet:
        out = np.sign(_radial_cosine(em.normals, sp, *_center_and_axis(start)))[..., None] \
            * em.normals
        polarity = "sheet"
    elif config.polarity in ("auto", "bright", "dark"):
        pol = _polarity(start, em.gradient, sp) if config.polarity == "auto" else \
            (1 if config.polarity == "bright" else -1)
        polarity = "bright" if pol > 0 else "dark"
        out = -pol * em.normals  # normals point to the brighter side
    else:
        out = np.sign(_radial_cosine(em.normals, sp, *_center_and_axis(start)))[..., None] \
            * em.normals
        polarity = "none"
    inner_face = sheet and config.polarity in ("bright", "dark")
    resume = None if record is None else \
        (model_from_dict(record["reference"]), tuple(record["order"]))
    if record is None or not inner_face:
        # Before an inner face, the sheet only has to be found well enough to place the band
        # inside it: the capture's tolerance (measured on the T1 brain: its last three stages
        # took 345 iterations, now 242; same Dice).
        model = run.refine(model, em, out, min(em.smooth_mm, scale),
                           tol=INNER_FACE_SHEET_TOL if inner_face else None,
                           stationary=not inner_face, resume=None if inner_face else resume)
    support = edge_support(model, em.f, sp)
    sheet_model = model if record is None or not inner_face else \
        model_from_dict(record["sheet"])

    if inner_face:
        # An object enclosed by a sheet (a brain in its CSF) ends at the sheet's inner face:
        # the step from the object to the sheet, just inside the sheet's mid-surface. For a
        # dark sheet the inside is brighter than the sheet, for a bright one darker.
        report("inner face", 0.75)
        t0 = time.perf_counter()
        # Every step that survives non-maximum suppression, thresholded among the candidates
        # of the band only: the inner face can be far weaker than the sheet's outer face.
        inside = rasterize(sheet_model, shape, sp)
        depth = distance_to(~inside, sp)
        band = inside & (depth <= max(INNER_FACE_DEPTH_MM, 3 * scale))
        del depth
        # The sheet's pass already smoothed this image (or its negative) at this scale, and
        # Gaussian filtering commutes exactly with the sign: its derivatives are reused.
        sign = np.float32(-1.0 if dark_sheet else 1.0)
        derivs = {(0, 0, 0): sign * em.image_smooth}
        derivs.update({o: sign * em.gradient[..., d]
                       for d, o in enumerate([(1, 0, 0), (0, 1, 0), (0, 0, 1)])})
        face = edge_map(image, sp, mode="edge", scale_mm=scale, threshold=None, region=band,
                        _derivs=derivs)
        del derivs
        pol = 1 if config.polarity == "dark" else -1  # +1: the object is brighter than the sheet
        # steps that face the sheet
        band &= -pol * _radial_cosine(face.normals, sp, *_center_and_axis(sheet_model)) >= 0.5
        low, high = auto_levels(face.response[face.mask & band])
        _discard(face, band & hysteresis_threshold(np.where(band, face.response, -1.0), low, high))
        run.timings["edge_map_s"] += time.perf_counter() - t0
        if record is None:
            model = run.capture(model, face.mask, face.smooth_mm, INNER_CAPTURE_NODE_SPACING)
        model = run.refine(model, face, -pol * face.normals, min(face.smooth_mm, scale),
                           stationary=True, resume=resume)
        support = edge_support(model, face.f, sp)
        polarity = f"inner face of a {config.polarity} sheet"

    if support < MIN_EDGE_SUPPORT:
        raise NoBoundaryError(
            f"no boundary found: the final surface lies on almost no detected edge (mean edge "
            f"strength {support:.2f}, expected about 1); check the initialization or --scale")
    t0 = time.perf_counter()
    mask = _final_mask(model, shape, sp)
    run.timings["mask_s"] = time.perf_counter() - t0
    report("done", 1.0)
    settings = {"edge_support": support, "scale_mm": scale, "smooth_mm": em.smooth_mm,
                "regularization": REGULARIZATION,
                "levels": None if em.levels is None else list(map(float, em.levels)),
                "edge_voxels": int(em.mask.sum()),
                "restart": {"refine_start": start.to_dict(),
                            "sheet": sheet_model.to_dict() if inner_face else None,
                            "stage": run.last["stage"],
                            "reference": run.last["reference"].to_dict(),
                            "order": run.last["order"]}}
    return SegmentResult(model, mask, run.history[-1]["energy"], run.iterations, run.history,
                         run.timings, polarity, init, settings)


def with_record(res: SegmentResult, options: dict[str, Any], first: SplineSurface,
                 on_boundary: bool, record_use: str | None) -> SegmentResult:
    """An edge-stage result with its restart record completed: the options, and the initial
    surface its discards came from."""
    res.settings["restart"] = {**options, "initial": first.to_dict(),
                               **res.settings["restart"]}
    if on_boundary:
        res.settings["restart_record"] = record_use
    return res


def _discard(em, keep: NDArray | None) -> None:
    """Keep only the edges where ``keep`` is True, in the mask and in the smooth map f."""
    if keep is None:
        return
    em.mask &= keep
    em.f *= gaussian_filter(keep, [em.smooth_mm / x for x in em.spacing])


class EdgeRun(Run):
    """The edge stages' :class:`segsnake.stage.Run`: the capture and the refinement."""

    def capture(self, model, edges: NDArray, smooth_mm: float,
                node_spacing: float = CAPTURE_NODE_SPACING):
        """The flux of ``grad(-d)``, d the distance to the edges (smoothed to be differentiable).

        Inside an object, ``grad(-d)`` points to the nearest edge, so the flux pulls the surface
        out towards the edges from any distance, whatever the object's thickness (a wide Gaussian
        ridge collapses snakes in objects thinner than its width). The pull is the curvature of
        the distance's level sets: strong in front of round edges, weak in front of large flat
        walls. Its minimum lies about two smoothing widths inside the edge: so it runs again at
        :data:`CAPTURE_CONTINUATION` times its width from where it stopped (continuation in
        scale), which ends within the refinement's reach. (A region integral of ``r .
        grad(-d)``, r radial, pulls with unit strength in front of flat walls too, but turns
        negative in the concave necks of lobed shapes and folds them.)

        Beyond the field of view ``lap(-d)`` is zero (:data:`FOV_PAD`; no edge is known there):
        a tube that leaves the volume feels nothing past the face, and its tension lets go
        where its end ring reaches past the face (:class:`segsnake.energy.AxialTension`).
        """
        if not edges.any():
            raise SegmentationError("no edges found outside the initial surface")
        t0 = time.perf_counter()
        dist = distance_to(edges, self.sp)
        self.timings["lookup_s"] += time.perf_counter() - t0
        first = max(smooth_mm, 1.5)
        widths = (first, CAPTURE_CONTINUATION * first)
        for k, sigma in enumerate(widths):
            t0 = time.perf_counter()
            # -d, filtered in place (the last pass takes dist itself)
            f_d = np.negative(dist, out=None if k < len(widths) - 1 else dist)
            f_d = gaussian_filter(f_d, [sigma / x for x in self.sp], mode="nearest", copy=False)
            lookup = self.field_lookup(f_d, divergence_of_gradient=True)
            del f_d
            self.timings["lookup_s"] += time.perf_counter() - t0
            # -d varies on the scale of sigma only near edges and medial axes: nodes 2 sigma
            # apart. The capture surface crosses the features of -d on its way out, so its
            # a-priori quadrature is fine from the start: a coarse first round can run into a
            # spurious minimum that the finer rounds do not leave (measured on the PD brain:
            # -28311 against -51907, Dice 0.53).
            model = self._stage(f"capture (edge distance, sigma={sigma:.2f}mm)", model, lookup,
                                sigma, 2 * sigma, tol=1e-4, node_spacing=node_spacing)
            del lookup
        return model

    def refine(self, model, em, out: NDArray, feature_mm: float, tol: float | None = None,
               stationary: bool = False, resume=None):
        """The region integral of n_out . grad f, n_out the detected normal oriented outward.

        Its first variation is n_out . grad f on the surface, which vanishes exactly on the
        ridge of f. (The flux of f n_out would add f div(n_out) = 2 H f, and its optimum would
        sit 2 s^2 H outside the ridge: +15 % volume on a 10 mm ball.)
        """
        t0 = time.perf_counter()
        along = sum(out[..., d] * np.gradient(em.f, h, axis=d) for d, h in enumerate(self.sp))
        lookup = self.field_lookup(along.astype(np.float32), divergence_of_gradient=False)
        del along
        self.timings["lookup_s"] += time.perf_counter() - t0
        return self._stage("refine", model, lookup, em.smooth_mm, feature_mm, tol=tol,
                           node_spacing=REFINE_NODE_SPACING, stationary=stationary,
                           resume=resume)


def edge_support(model: SplineSurface, f: NDArray, spacing: Sequence[float]) -> float:
    """Area-weighted mean of the edge map over the surface (about 1 on a detected boundary).

    The edge map is an area density that peaks at about 1 on every detected surface, so this is
    the fraction of the snake that found an edge; a snake that ended in empty space or in
    noise has almost none.
    """
    pts, _, area = model.area_samples(4)
    values = ndimage.map_coordinates(f, (pts / np.asarray(spacing)).T, order=1, mode="constant",
                                     cval=0.0)
    return float(np.sum(area * values) / max(np.sum(area), 1e-300))
