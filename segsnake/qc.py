"""The QC picture ``qc.png``: three slices through the user's click and a 3D view of the surface.

Each slice shows the final contour (red), the initial one (yellow, dashed) and, with ``--truth``,
the truth's (cyan), with a legend. Slices pass through the click (``--center``, ``--seed-point``,
or the middle of a cylinder's axis), else through the result's centre. With the image affine the
panels are laid out as a viewer shows them (:mod:`segsnake.anatomy`): axial, coronal and sagittal
views, axes in world millimetres, the patient's right on the left, anterior and superior up, and
the sides labelled R/L, A/P, S/I. A cylinder adds a fifth panel, its tube profile (diameters
against arc length, :mod:`segsnake.profile`). matplotlib is imported on use only.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["click_index", "slice_panel", "profile_panel", "qc_figure", "write_qc_picture"]

FINAL = ("red", "solid", 1.0)
INITIAL = ("yellow", "dashed", 0.8)
TRUTH = ("cyan", "solid", 0.8)
CLICK = "lime"
_AXIS_NAMES = ("x", "y", "z")


def click_index(config, volume) -> np.ndarray | None:
    """Where the user clicked, as continuous voxel indices, or None without a click.

    Parameters
    ----------
    config : SegmentConfig
        ``center``, else ``seed_point``, else the middle of ``axis_start``-``axis_end``, else the
        middle point of a ``centerline`` (its rows, once read); world millimetres with
        ``config.world``.
    volume : Volume
        Converts world positions to indices.
    """
    if config.center is not None:
        point = np.asarray(config.center, dtype=np.float64)
    elif config.seed_point is not None:
        point = np.asarray(config.seed_point, dtype=np.float64)
    elif config.axis_start is not None and config.axis_end is not None:
        point = 0.5 * (np.asarray(config.axis_start, dtype=np.float64)
                       + np.asarray(config.axis_end, dtype=np.float64))
    elif config.centerline is not None and not isinstance(config.centerline, str):
        rows = config.centerline
        point = np.asarray(rows[len(rows) // 2][:3], dtype=np.float64)
    else:
        return None
    return volume.world_to_index(point) if config.world else point


def _slice_index_panel(ax, image, sp, axis, index, contours, levels) -> None:
    """The affine-free panel (index x spacing axes), as the real-data montages draw it."""
    sl = [slice(None)] * 3
    sl[axis] = index
    sl = tuple(sl)
    other = [d for d in range(3) if d != axis]
    extent = (0, image.shape[other[0]] * sp[other[0]], 0, image.shape[other[1]] * sp[other[1]])
    lo, hi = levels if levels is not None else np.percentile(image[sl], [1, 99.5])
    ax.imshow(image[sl].T, cmap="gray", origin="lower", vmin=lo, vmax=hi, extent=extent,
              interpolation="nearest")
    xs = (np.arange(image.shape[other[0]]) + 0.5) * sp[other[0]]
    ys = (np.arange(image.shape[other[1]]) + 0.5) * sp[other[1]]
    for mask, colour, style, width in contours:
        if mask[sl].any():
            ax.contour(xs, ys, mask[sl].T.astype(float), [0.5], colors=colour, linestyles=style,
                       linewidths=width)
    names = ("i (x)", "j (y)", "k (z)")
    ax.set_title(f"{names[axis]} = {index}", fontsize=9)
    ax.set_xlabel(f"{names[other[0]]} mm", fontsize=8)
    ax.set_ylabel(f"{names[other[1]]} mm", fontsize=8)
    ax.tick_params(labelsize=7)


def slice_panel(ax, image: np.ndarray, spacing, axis: int, index: int,
                contours: list[tuple[np.ndarray, str, str, float]],
                levels: tuple[float, float] | None = None, *,
                affine: np.ndarray | None = None,
                point: Sequence[float] | None = None) -> None:
    """One slice of ``image`` across array ``axis`` at ``index``, with mask contours.

    Parameters
    ----------
    ax : matplotlib Axes
        Where to draw.
    image : ndarray, shape (nx, ny, nz)
        The volume.
    spacing : 3 floats
        Voxel size in mm.
    axis, index : int
        The array axis the slice is across and its index.
    contours : list of (mask, colour, line style, width)
        Masks on the image's grid, drawn as contours (a mask absent from the slice is skipped).
    levels : (float, float), optional
        The grey range (default the slice's 1st and 99.5th percentiles).
    affine : ndarray (4, 4), optional
        Voxel to world (RAS+). Given, the slice is shown as a viewer shows it: axes in world mm
        (for an oblique grid, the dominant world axis, exact at ``point``), R/A/S left and up, the
        sides labelled with the anatomical directions. Without it, axes are index x spacing mm.
    point : 3 floats, optional
        Voxel indices of a point to mark with a cross (the click); with ``affine`` it is also
        where the world coordinates of an oblique grid are exact (default: the grid's centre).
    """
    sp = np.asarray(spacing, dtype=float)
    if affine is None:
        _slice_index_panel(ax, image, sp, axis, index, contours, levels)
        if point is not None:
            other = [d for d in range(3) if d != axis]
            ax.plot((point[other[0]] + 0.5) * sp[other[0]], (point[other[1]] + 0.5) * sp[other[1]],
                    "+", color=CLICK, markersize=10, markeredgewidth=1.2)
        return
    from segsnake.anatomy import LETTERS, VIEW_NAMES, axis_directions, is_oblique, view_axes

    aff = np.asarray(affine, dtype=np.float64)
    world, sign = axis_directions(aff)
    h, v, wh, wv = view_axes(aff, axis)
    ref = np.array(point if point is not None else (np.array(image.shape) - 1) / 2.0, dtype=float)
    ref[axis] = index
    ref_world = ref @ aff[:3, :3].T + aff[:3, 3]

    def coords(d: int, w: int) -> np.ndarray:
        # Along array axis d, world axis w: exact for a grid parallel to the world axes; for an
        # oblique one the distance along d (true aspect ratio), exact at the reference point.
        return ref_world[w] + sign[d] * sp[d] * (np.arange(image.shape[d]) - ref[d])

    def plane(vol: np.ndarray) -> np.ndarray:
        s = np.take(vol, index, axis=axis)  # axes: the other two, in increasing order
        s = s if h < v else s.T  # -> (h, v)
        return s[:: sign[h], :: sign[v]]  # world coordinates increase along both

    xs = np.sort(coords(h, wh))
    ys = np.sort(coords(v, wv))
    sl = plane(image)
    lo, hi = levels if levels is not None else np.percentile(sl, [1, 99.5])
    dx, dy = sp[h] / 2.0, sp[v] / 2.0
    ax.imshow(sl.T, cmap="gray", origin="lower", vmin=lo, vmax=hi, interpolation="nearest",
              extent=(xs[0] - dx, xs[-1] + dx, ys[0] - dy, ys[-1] + dy))
    for mask, colour, style, width in contours:
        m = plane(mask)
        if m.any():
            ax.contour(xs, ys, m.T.astype(float), [0.5], colors=colour, linestyles=style,
                       linewidths=width)
    if point is not None:
        ax.plot(ref_world[wh], ref_world[wv], "+", color=CLICK, markersize=10,
                markeredgewidth=1.2)
    # The positive end (R, A, S) on the left horizontally and at the top, as viewers show it.
    ax.set_xlim(xs[-1] + dx, xs[0] - dx)
    ax.set_ylim(ys[0] - dy, ys[-1] + dy)
    ax.set_aspect("equal")
    oblique = " (dominant; oblique grid)" if is_oblique(aff) else ""
    ax.set_xlabel(f"{_AXIS_NAMES[wh]} (mm){oblique}", fontsize=8)
    ax.set_ylabel(f"{_AXIS_NAMES[wv]} (mm)", fontsize=8)
    style = dict(transform=ax.transAxes, color="orange", fontsize=10, fontweight="bold")
    ax.text(0.02, 0.5, LETTERS[wh][1], ha="left", va="center", **style)
    ax.text(0.98, 0.5, LETTERS[wh][0], ha="right", va="center", **style)
    ax.text(0.5, 0.98, LETTERS[wv][1], ha="center", va="top", **style)
    ax.text(0.5, 0.02, LETTERS[wv][0], ha="center", va="bottom", **style)
    n = world[axis]
    ax.set_title(f"{VIEW_NAMES[n]}: {'ijk'[axis]} = {index}, {_AXIS_NAMES[n]} = "
                 f"{ref_world[n]:.1f} mm", fontsize=9)
    ax.tick_params(labelsize=7)


def profile_panel(ax, profile) -> None:
    """A tube's diameters against arc length along its centerline (:mod:`segsnake.profile`).

    Parameters
    ----------
    ax : matplotlib Axes
    profile : segsnake.profile.TubeProfile
    """
    s = profile.arc_mm
    ax.fill_between(s, profile.min_diameter, profile.max_diameter, color="tomato", alpha=0.25,
                    linewidth=0, label="min-max caliper")
    for d in (profile.min_diameter, profile.max_diameter):
        ax.plot(s, d, color="tomato", linewidth=0.6)
    ax.plot(s, profile.equivalent_diameter, color="red", linewidth=1.2,
            label="equivalent 2 sqrt(A/pi)")
    capped = np.asarray(profile.capped, dtype=bool)
    if capped.any():  # sections an end cap closes (a tube leaving through an oblique face)
        ax.plot(s[capped], profile.equivalent_diameter[capped], "o", markersize=2.5,
                markerfacecolor="none", markeredgecolor="darkred", label="closed by an end cap")
    ax.set_xlabel("arc length along the centerline (mm)", fontsize=8)
    ax.set_ylabel("diameter (mm)", fontsize=8)
    top = float(np.max(profile.max_diameter)) if len(s) else 1.0
    ax.set_ylim(0.0, 1.1 * top)
    ax.set_title(f"tube profile ({profile.length_mm:.1f} mm)", fontsize=9)
    ax.legend(fontsize=7, loc="lower center", frameon=False)
    ax.tick_params(labelsize=7)


def qc_figure(image: np.ndarray, spacing, mask: np.ndarray, model, init_model=None, *,
              affine: np.ndarray | None = None, truth: np.ndarray | None = None,
              click: Sequence[float] | None = None, profile=None):
    """The QC figure: three orthogonal slices and a 3D view of the surface, with a legend.

    Parameters
    ----------
    image : ndarray, shape (nx, ny, nz)
        The image.
    spacing : 3 floats
        Voxel size in mm.
    mask : ndarray of bool, same shape
        The result.
    model : SplineSurface
        The snake (mm of scaled index space).
    init_model : SplineSurface, optional
        The initial snake, drawn dashed.
    affine : ndarray (4, 4), optional
        Voxel to world (RAS+): world-mm axes with anatomical labels (default: index x spacing).
    truth : ndarray, same shape, optional
        A truth mask, drawn in cyan.
    click : 3 floats, optional
        Voxel indices the slices go through (the user's click); default the mask's centroid.
    profile : segsnake.profile.TubeProfile, optional
        A cylinder's profile: a fifth panel, its diameters against arc length.

    Returns
    -------
    matplotlib.figure.Figure
    """
    # The object-oriented API without pyplot: nothing global (a notebook keeps its backend).
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from mpl_toolkits.mplot3d import Axes3D  # noqa: F401 - registers the "3d" projection
    from segsnake.moments import mask_moments
    from segsnake.rasterize import rasterize

    sp = np.asarray(spacing, dtype=float)
    shape = np.array(mask.shape)
    if click is not None:
        point = np.asarray(click, dtype=float)
        centre = np.clip(np.round(point), 0, shape - 1).astype(int)
    else:
        point = None
        centre = (np.round(mask_moments(mask)[0]).astype(int) if mask.any()
                  else shape // 2)
    init_mask = rasterize(init_model, mask.shape, spacing) if init_model is not None else None
    # Grey levels from the three slices shown (a percentile of the whole volume costs 0.2 s).
    shown = [np.take(image, int(centre[axis]), axis=axis).ravel() for axis in range(3)]
    lo, hi = np.percentile(np.concatenate(shown), [1, 99.5])
    contours = [(mask, *FINAL)]
    handles = [Line2D([], [], color=FINAL[0], linestyle=FINAL[1], label="final surface")]
    if init_mask is not None:
        contours.insert(0, (init_mask, *INITIAL))
        handles.append(Line2D([], [], color=INITIAL[0], linestyle=INITIAL[1],
                              label="initial surface"))
    if truth is not None:
        contours.insert(0, (np.asarray(truth) != 0, *TRUTH))
        handles.append(Line2D([], [], color=TRUTH[0], linestyle=TRUTH[1], label="truth"))
    if point is not None:
        handles.append(Line2D([], [], color=CLICK, marker="+", linestyle="none", markersize=9,
                              label="click (slices through it)"))
    panels = 5 if profile is not None else 4
    fig = Figure(figsize=(13 + 3.3 * (panels - 4), 4.0), dpi=90)
    if affine is not None:
        from segsnake.anatomy import axis_directions

        world, _ = axis_directions(affine)
        axes = [world.index(n) for n in (2, 1, 0)]  # axial, coronal, sagittal
    else:
        axes = [2, 1, 0]
    for panel, axis in enumerate(axes):
        ax = fig.add_subplot(1, panels, panel + 1)
        slice_panel(ax, image, sp, axis, int(centre[axis]), contours, levels=(lo, hi),
                    affine=affine, point=point)
    ax3 = fig.add_subplot(1, panels, 4, projection="3d")
    # max(2 m, min(4 m, 36)) samples along each direction for m control intervals (a thumbnail:
    # with a 21 x 21 brain's 84 x 84 the figure took 0.33 s, with 42 x 42 0.09 s)
    pts, faces = model.triangles(*(max(2 * m, min(4 * m, 36)) for m in (model.m1, model.m2)))
    pts = np.asarray(pts, dtype=np.float64)
    if affine is not None:  # the same world millimetres as the slices and surface.vtp
        aff = np.asarray(affine, dtype=np.float64)
        pts = (pts / sp) @ aff[:3, :3].T + aff[:3, 3]
    ax3.plot_trisurf(pts[:, 0], pts[:, 1], faces, pts[:, 2], color="tomato", alpha=0.8,
                     linewidth=0.1, edgecolor="k")
    ax3.set_box_aspect(np.ptp(pts, axis=0) + 1e-9)
    if affine is not None:
        ax3.set_title("surface (world mm)", fontsize=9)
        for setter, name in zip((ax3.set_xlabel, ax3.set_ylabel, ax3.set_zlabel),
                                ("x: L to R", "y: P to A", "z: I to S")):
            setter(name, fontsize=7)
    else:
        ax3.set_title("surface (mm)", fontsize=9)
    ax3.tick_params(labelsize=6)
    if profile is not None:
        profile_panel(fig.add_subplot(1, panels, 5), profile)
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=8,
               frameon=False)
    # Fixed margins: tight_layout measured 0.15 s of text extents for the same result.
    fig.subplots_adjust(left=0.045, right=0.985, bottom=0.13, top=0.84, wspace=0.32)
    return fig


def write_qc_picture(path: str, image: np.ndarray, spacing, mask: np.ndarray, model,
                     init_model=None, *, affine: np.ndarray | None = None,
                     truth: np.ndarray | None = None,
                     click: Sequence[float] | None = None, profile=None) -> None:
    """Write :func:`qc_figure` as a PNG at ``path`` (same parameters)."""
    fig = qc_figure(image, spacing, mask, model, init_model, affine=affine, truth=truth,
                    click=click, profile=profile)
    fig.savefig(path, format="png")
