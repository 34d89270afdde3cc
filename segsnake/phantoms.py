"""Synthetic test volumes with known truth: balls, ellipsoids, blobs, tubes, a hollow cylinder, a head.

Every generator is pure numpy/scipy (no file I/O), deterministic for a ``seed``, and returns a
:class:`Phantom`: the image, the truth mask, the spacing and a NIfTI affine, the parameters that made
it (JSON-able) and a suggested initialisation in the ``segment`` command's terms (voxel index
units along the array axes, as ``--center``/``--radii``/``--axis-start``/``--radius`` take them;
``params["init_mm"]`` has the same in mm of scaled index space).

Conventions (see ``design.md``): arrays are indexed ``[i, j, k]``; a voxel centre sits at the
physical point ``p = (i sx, j sy, k sz)`` mm. Objects are defined in those physical coordinates, so
an anisotropic spacing keeps the physical object and only changes how finely it is sampled. By
default the field of view (``shape * spacing``) is the same whatever the spacing: leave ``shape``
out and it is derived from the default field of view and the spacing.

Truth is evaluated at voxel centres: a voxel is in the truth when its centre is inside the object.
The image carries partial volume: near the boundary the intensity ramps linearly across one voxel
width measured along the surface normal, so the 50 % level of the clean image is the truth surface.

Image formation order: clean partial-volume image -> Gaussian blur (``blur`` = sigma in mm) ->
smooth multiplicative bias field -> noise (Gaussian, or Rician = magnitude of complex Gaussian).
Each random ingredient (geometry, bias field, noise) draws from its own stream derived from
``seed``, so changing one option (say the noise) leaves the others' random draws unchanged.
"""

from __future__ import annotations

import dataclasses
import inspect
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial.transform import Rotation

from segsnake.errors import ConfigError
from segsnake.perturb import _in_ball
from segsnake.swept_tube import SweptTube

__all__ = [
    "Phantom",
    "PHANTOMS",
    "make_phantom",
    "ball",
    "ellipsoid",
    "blob",
    "hollow_cylinder",
    "tube",
    "s_vessel",
    "exiting_tube",
    "tube_truth",
    "truth_profile",
    "brain",
    "rasterize_init",
    "phantom_options",
    "bias_field",
    "TABLE_7_2",
    "BRAIN_INTENSITIES",
]

# Independent random streams per ingredient: np.random.default_rng([seed, stream]).
_GEOMETRY, _BIAS, _NOISE, _CLICK = 1, 2, 3, 4

# 003 Table 7.2: noise standard deviation (8-bit units) -> SNR [dB] printed in the thesis.
TABLE_7_2: dict[int, float] = {10: 9.91, 30: 0.27, 50: -4.17, 70: -7.10, 90: -9.21}

# Brain tissue intensities (brightest tissue = 100, so a noise fraction of 0.03 is a std of 3).
# T1 (what most users have): bright WM, grey cortex, dark CSF, dark skull, bright scalp fat.
# PD (the thesis' BrainWeb set): CSF brightest, GM above WM, skull dark, scalp bright-ish.
BRAIN_INTENSITIES: dict[str, dict[str, float]] = {
    "t1": {"wm": 80.0, "gm": 50.0, "csf": 15.0, "skull": 8.0, "scalp": 100.0, "background": 0.0},
    "pd": {"wm": 65.0, "gm": 80.0, "csf": 100.0, "skull": 10.0, "scalp": 90.0, "background": 0.0},
}


@dataclasses.dataclass
class Phantom:
    """A synthetic volume with its truth.

    Attributes
    ----------
    image : ndarray of float32
        The (noisy) image, indexed ``[i, j, k]``.
    truth : ndarray of uint8
        1 inside the object (evaluated at voxel centres), 0 outside.
    spacing : tuple of 3 floats
        Voxel size (sx, sy, sz) in mm.
    affine : ndarray (4, 4)
        NIfTI voxel-to-world affine; its columns encode the spacing (and the grid rotation if any).
    params : dict
        JSON-able record of the kind, seed, options and derived geometry.
    init : dict
        Suggested initialisation in the ``segment`` command's terms (voxel index units;
        ``params["init_mm"]`` gives it in mm of scaled index space):
        ``{"shape": "sphere", "center": [i, j, k], "radii": [ri, rj, rk]}`` or
        ``{"shape": "cylinder", "axis_start": [...], "axis_end": [...], "radius": r}``.
    labels : ndarray of uint8, optional
        Tissue label map at voxel centres (brain only: 0 background, 1 scalp, 2 skull, 3 CSF,
        4 GM, 5 WM; names in ``params["labels"]``).
    """

    image: NDArray[np.float32]
    truth: NDArray[np.uint8]
    spacing: tuple[float, float, float]
    affine: NDArray[np.float64]
    params: dict
    init: dict
    labels: NDArray[np.uint8] | None = None


# --------------------------------------------------------------------------------------------
# Shared helpers
# --------------------------------------------------------------------------------------------


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), stream])


def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def _grid(
    shape: Sequence[int] | None, spacing: Sequence[float], default_fov: Sequence[float]
) -> tuple[tuple[int, int, int], tuple[float, float, float]]:
    """Validate ``spacing`` and derive ``shape`` from the default field of view when not given."""
    try:
        sp = tuple(float(s) for s in spacing)
    except (TypeError, ValueError):
        raise ConfigError(f"spacing must be 3 positive numbers, got {spacing!r}") from None
    if len(sp) != 3 or not all(np.isfinite(s) and s > 0 for s in sp):
        raise ConfigError(f"spacing must be 3 positive numbers, got {spacing!r}")
    if shape is None:
        shp = tuple(max(1, int(round(f / s))) for f, s in zip(default_fov, sp))
    else:
        try:
            shp = tuple(int(n) for n in shape)
        except (TypeError, ValueError):
            raise ConfigError(f"shape must be 3 positive integers, got {shape!r}") from None
        if len(shp) != 3 or any(n < 8 for n in shp) or any(int(n) != n for n in shape):
            raise ConfigError(f"shape must be 3 integers >= 8, got {shape!r}")
    return shp, sp  # type: ignore[return-value]


def _check_fraction(name: str, value: float, upper: float = np.inf) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or v > upper:
        raise ConfigError(f"{name} must be in [0, {upper:g}], got {value!r}")
    return v


def _vector(name: str, value: Any, n: int = 3) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be {n} numbers, got {value!r}") from None
    if arr.size != n or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be {n} finite numbers, got {value!r}")
    return arr


def _affine(
    shape: Sequence[int], spacing: Sequence[float], grid_rotation: Sequence[float] | None
) -> NDArray[np.float64]:
    """Voxel-to-world affine: columns = spacing (rotated when asked), field-of-view centre at 0."""
    lin = np.diag(np.asarray(spacing, dtype=float))
    if grid_rotation is not None:
        angles = _vector("grid_rotation", grid_rotation)
        lin = Rotation.from_euler("xyz", angles, degrees=True).as_matrix() @ lin
    aff = np.eye(4)
    aff[:3, :3] = lin
    aff[:3, 3] = -lin @ ((np.asarray(shape, dtype=float) - 1.0) / 2.0)
    return aff


def _axes_mm(shape: Sequence[int], spacing: Sequence[float]) -> list[NDArray[np.float64]]:
    """Physical coordinates of voxel centres along each axis, shaped for broadcasting."""
    out = []
    for ax, (n, s) in enumerate(zip(shape, spacing)):
        a = np.arange(n, dtype=np.float64) * s
        sh = [1, 1, 1]
        sh[ax] = n
        out.append(a.reshape(sh))
    return out


def _fov_center(shape: Sequence[int], spacing: Sequence[float]) -> NDArray[np.float64]:
    return (np.asarray(shape, dtype=float) - 1.0) / 2.0 * np.asarray(spacing, dtype=float)


def _occupancy(F: NDArray, spacing: Sequence[float]) -> NDArray[np.float32]:
    """Partial-volume fraction inside the level set ``F < 0``.

    ``F / |grad F|`` approximates the signed distance d (mm) to the surface; the fraction ramps
    linearly from 1 to 0 as d goes from -w/2 to w/2, where ``w = sum_i |n_i| s_i`` is the width of
    one voxel measured along the normal n. At a voxel centre on the surface it is exactly 0.5.
    """
    grads = np.gradient(F.astype(np.float64, copy=False), *[float(s) for s in spacing])
    gn = np.sqrt(sum(g * g for g in grads))
    w = sum(np.abs(g) * s for g, s in zip(grads, spacing))
    safe = gn > 1e-12
    gn = np.where(safe, gn, 1.0)
    # Where the gradient vanishes (far from the surface, or a clipped plateau) use the voxel size.
    w = np.where(safe, w / gn, float(np.mean(spacing)))
    d = F / gn
    return np.clip(0.5 - d / w, 0.0, 1.0).astype(np.float32)


def _legendre_field(
    shape: Sequence[int], rng: np.random.Generator, degree: int = 2
) -> NDArray[np.float64]:
    """Smooth random field: a tensor-product Legendre polynomial of degree <= ``degree`` per axis.

    Evaluated by contracting one axis at a time, so it costs a few operations per voxel.
    """
    d = degree + 1
    coef = rng.standard_normal((d, d, d))
    a, b, c = np.meshgrid(np.arange(d), np.arange(d), np.arange(d), indexing="ij")
    coef /= 1.0 + (a + b + c)  # higher total degree -> smaller, so the field stays smooth
    coef[0, 0, 0] = 0.0
    basis = []
    for n in shape:
        t = np.linspace(-1.0, 1.0, n)
        basis.append(np.stack([np.polynomial.legendre.Legendre.basis(m)(t) for m in range(d)]))
    px, py, pz = basis
    t_abk = np.einsum("abc,ck->abk", coef, pz)
    u_ajk = np.einsum("bj,abk->ajk", py, t_abk)
    return np.einsum("ai,ajk->ijk", px, u_ajk)


def bias_field(
    shape: Sequence[int],
    amplitude: float,
    seed: int = 0,
    mask: NDArray[np.bool_] | None = None,
) -> NDArray[np.float32]:
    """Smooth multiplicative bias field whose range over ``mask`` (default: all voxels) is ``amplitude``.

    Parameters
    ----------
    shape : 3 ints
        Grid shape.
    amplitude : float
        Peak-to-peak range of the field, as a fraction (0.2 = BrainWeb "RF 20 %"): the field spans
        ``[1 - amplitude / 2, 1 + amplitude / 2]`` over the mask.
    seed : int
        Seed of the random polynomial.
    mask : bool ndarray, optional
        Region over which the range is normalised (the head for the brain phantom).

    Returns
    -------
    ndarray of float32
        The field (all ones when ``amplitude`` is 0).
    """
    if amplitude == 0:
        return np.ones(shape, dtype=np.float32)
    g = _legendre_field(shape, _rng(seed, _BIAS))
    vals = g[mask] if mask is not None and mask.any() else g
    lo, hi = float(vals.min()), float(vals.max())
    g = (g - 0.5 * (lo + hi)) / max(hi - lo, 1e-12)
    return (1.0 + amplitude * g).astype(np.float32)


def _form_image(
    clean: NDArray,
    spacing: Sequence[float],
    seed: int,
    *,
    blur: float,
    bias: float,
    noise_std: float,
    rician: bool,
    bias_mask: NDArray[np.bool_] | None = None,
) -> NDArray[np.float32]:
    """Blur -> multiplicative bias -> noise, each ingredient from its own random stream."""
    img = clean.astype(np.float32, copy=True)
    if blur > 0:
        sig = [blur / s for s in spacing]
        img = ndimage.gaussian_filter(img, sig, mode="nearest")
    if bias > 0:
        img *= bias_field(img.shape, bias, seed, bias_mask)
    if noise_std > 0:
        rng = _rng(seed, _NOISE)
        n1 = rng.standard_normal(img.shape, dtype=np.float32)
        if rician:
            n2 = rng.standard_normal(img.shape, dtype=np.float32)
            img = np.sqrt((img + noise_std * n1) ** 2 + (noise_std * n2) ** 2)
        else:
            img += np.float32(noise_std) * n1
    return img.astype(np.float32, copy=False)


def _common_checks(noise: float, bias: float, blur: float) -> tuple[float, float, float]:
    return (
        _check_fraction("noise", noise),
        _check_fraction("bias", bias, 0.99),
        _check_fraction("blur", blur),
    )


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays (recursively) to plain Python for JSON; inf/NaN -> None."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        # JSON has no infinity/NaN (e.g. the SNR of a noise-free image): write null.
        return float(obj) if np.isfinite(obj) else None
    return obj


def _r3(v: Any) -> list[float]:
    return [round(float(x), 3) for x in np.asarray(v, dtype=float).reshape(-1)]


def _sphere_init(center_mm: NDArray, radii_mm: Sequence[float]) -> dict:
    return {"shape": "sphere", "center": _r3(center_mm), "radii": _r3(radii_mm)}


def _cylinder_init(a0: NDArray, a1: NDArray, radius: float) -> dict:
    return {"shape": "cylinder", "axis_start": _r3(a0), "axis_end": _r3(a1),
            "radius": round(float(radius), 3)}


def _init_to_voxels(init: dict, spacing: Sequence[float]) -> dict:
    """The same initialisation in voxel index units.

    A cylinder radius is converted with :func:`segsnake.pipeline.perpendicular_spacing`, the
    voxel size across the axis (the rule ``segment --radius`` uses).
    """
    from segsnake.pipeline import perpendicular_spacing

    sp = np.asarray(spacing, dtype=float)
    out: dict[str, Any] = {"shape": init["shape"]}
    for key in ("center", "radii", "axis_start", "axis_end"):
        if key in init:
            out[key] = _r3(np.asarray(init[key], dtype=float) / sp)
    if "radius" in init:
        axis = np.asarray(init["axis_end"], dtype=float) - np.asarray(init["axis_start"], dtype=float)
        out["radius"] = round(float(init["radius"]) / perpendicular_spacing(sp, axis), 3)
    return out


def _finish(
    kind: str,
    seed: int,
    image: NDArray,
    truth: NDArray,
    spacing: tuple[float, float, float],
    grid_rotation: Sequence[float] | None,
    options: dict,
    geometry: dict,
    init: dict,
) -> Phantom:
    vox = float(np.prod(spacing))
    params = {
        "kind": kind,
        "seed": seed,
        "shape": list(truth.shape),
        "spacing": list(spacing),
        "options": options,
        "geometry": geometry,
        "truth_voxels": int(truth.sum()),
        "truth_volume_mm3": float(truth.sum()) * vox,
        "init_mm": init,
    }
    return Phantom(
        image=np.ascontiguousarray(image, dtype=np.float32),
        truth=np.ascontiguousarray(truth, dtype=np.uint8),
        spacing=spacing,
        affine=_affine(truth.shape, spacing, grid_rotation),
        params=_jsonable(params),
        init=_jsonable(_init_to_voxels(init, spacing)),
    )


def _fibonacci_sphere(n: int) -> NDArray[np.float64]:
    """n nearly uniform unit vectors (for sampling functions on the sphere)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5**0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


# --------------------------------------------------------------------------------------------
# Filled objects on a uniform background: ball, ellipsoid, blob
# --------------------------------------------------------------------------------------------

_DEFAULT_FOV = (64.0, 64.0, 64.0)


def _object_phantom(
    kind: str,
    seed: int,
    F: NDArray,
    shape: tuple[int, int, int],
    spacing: tuple[float, float, float],
    *,
    foreground: float,
    background: float,
    noise: float,
    rician: bool,
    bias: float,
    blur: float,
    grid_rotation: Sequence[float] | None,
    options: dict,
    geometry: dict,
    init: dict,
) -> Phantom:
    occ = _occupancy(F, spacing)
    clean = np.float32(background) + np.float32(foreground - background) * occ
    std = noise * abs(foreground - background)
    image = _form_image(
        clean, spacing, seed, blur=blur, bias=bias, noise_std=std, rician=rician
    )
    geometry = dict(geometry, noise_std=std)
    return _finish(kind, seed, image, F < 0, spacing, grid_rotation, options, geometry, init)


def _center_mm(
    center: Sequence[float] | None, shape, spacing, rng: np.random.Generator, jitter: float = 2.0
) -> NDArray[np.float64]:
    """The given centre (mm), or the field-of-view centre moved by a seeded sub-voxel-ish jitter."""
    if center is not None:
        return _vector("center", center)
    return _fov_center(shape, spacing) + rng.uniform(-jitter, jitter, 3)


def ball(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    radius: float | None = None,
    center: Sequence[float] | None = None,
    foreground: float = 100.0,
    background: float = 20.0,
    noise: float = 0.05,
    rician: bool = False,
    bias: float = 0.0,
    blur: float = 0.0,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """A filled ball on a uniform background.

    Parameters
    ----------
    seed : int
        Seed of every random draw (centre jitter, bias field, noise).
    shape : 3 ints, optional
        Grid shape; default: a 64 mm field of view divided by the spacing.
    spacing : 3 floats
        Voxel size in mm, e.g. (1, 1, 2) keeps the physical ball with half the slices.
    radius : float, optional
        Radius in mm; default 30 % of the smallest field-of-view extent.
    center : 3 floats, optional
        Centre in mm (scaled index space); default the field-of-view centre plus a seeded
        jitter of up to 2 mm per axis.
    foreground, background : float
        Intensities inside and outside; the contrast is their difference.
    noise : float
        Noise std as a fraction of the contrast.
    rician : bool
        Rician (magnitude) noise instead of additive Gaussian noise.
    bias : float
        Peak-to-peak range of the smooth multiplicative bias field over the volume (0-0.4).
    blur : float
        Gaussian blur sigma in mm.
    grid_rotation : 3 floats, optional
        Euler angles (degrees, "xyz") of an oblique acquisition grid, encoded in the affine only.

    Returns
    -------
    Phantom
        Truth is the set of voxel centres within ``radius`` of the centre; init a sphere of half
        the radius at the (voxel-rounded) true centre.
    """
    seed = _check_seed(seed)
    shape, spacing = _grid(shape, spacing, _DEFAULT_FOV)
    noise, bias, blur = _common_checks(noise, bias, blur)
    fov = np.asarray(shape) * np.asarray(spacing)
    r = 0.3 * float(fov.min()) if radius is None else _check_fraction("radius", radius)
    if r <= 0:
        raise ConfigError("radius must be positive")
    c = _center_mm(center, shape, spacing, _rng(seed, _GEOMETRY))
    x, y, z = _axes_mm(shape, spacing)
    F = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r
    options = dict(radius=r, foreground=foreground, background=background, noise=noise,
                   rician=rician, bias=bias, blur=blur, grid_rotation=grid_rotation)
    geometry = dict(center_mm=c, radius_mm=r, volume_mm3_analytic=4.0 / 3.0 * np.pi * r**3)
    init = _sphere_init(np.round(c / spacing) * spacing, [r / 2] * 3)
    return _object_phantom("ball", seed, F, shape, spacing, foreground=foreground,
                           background=background, noise=noise, rician=rician, bias=bias,
                           blur=blur, grid_rotation=grid_rotation, options=options,
                           geometry=geometry, init=init)


def ellipsoid(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    radii: Sequence[float] | None = None,
    rotation: Sequence[float] | None = None,
    center: Sequence[float] | None = None,
    foreground: float = 100.0,
    background: float = 20.0,
    noise: float = 0.05,
    rician: bool = False,
    bias: float = 0.0,
    blur: float = 0.0,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """A filled, rotated ellipsoid on a uniform background.

    Parameters
    ----------
    radii : 3 floats, optional
        Semi-axes in mm; default (0.36, 0.27, 0.2) times the smallest field-of-view extent.
    rotation : 3 floats, optional
        Euler angles (degrees, "xyz") of the ellipsoid's axes in scaled index space; default a
        random rotation drawn from the seed.
    Other parameters are as in :func:`ball`.

    Returns
    -------
    Phantom
        Init: an axis-aligned ellipsoid ("sphere" init with three radii) of half the mean semi-axis.
    """
    seed = _check_seed(seed)
    shape, spacing = _grid(shape, spacing, _DEFAULT_FOV)
    noise, bias, blur = _common_checks(noise, bias, blur)
    fov_min = float((np.asarray(shape) * np.asarray(spacing)).min())
    a = np.array([0.36, 0.27, 0.2]) * fov_min if radii is None else _vector("radii", radii)
    if np.any(a <= 0):
        raise ConfigError(f"radii must be positive, got {radii!r}")
    rng = _rng(seed, _GEOMETRY)
    c = _center_mm(center, shape, spacing, rng)
    if rotation is None:
        rot = Rotation.random(random_state=rng)
        angles = rot.as_euler("xyz", degrees=True)
    else:
        angles = _vector("rotation", rotation)
        rot = Rotation.from_euler("xyz", angles, degrees=True)
    R = rot.as_matrix()
    x, y, z = _axes_mm(shape, spacing)
    d = (x - c[0], y - c[1], z - c[2])
    # q = R^T (p - c) / a: coordinates in the ellipsoid's own frame, unit sphere = surface.
    q2 = 0.0
    for m in range(3):
        qm = (R[0, m] * d[0] + R[1, m] * d[1] + R[2, m] * d[2]) / a[m]
        q2 = q2 + qm * qm
    F = np.sqrt(q2) - 1.0
    options = dict(radii=a, rotation=angles, foreground=foreground, background=background,
                   noise=noise, rician=rician, bias=bias, blur=blur, grid_rotation=grid_rotation)
    geometry = dict(center_mm=c, radii_mm=a, rotation_matrix=R,
                    volume_mm3_analytic=4.0 / 3.0 * np.pi * float(np.prod(a)))
    init = _sphere_init(np.round(c / spacing) * spacing, [float(a.mean()) / 2] * 3)
    return _object_phantom("ellipsoid", seed, F, shape, spacing, foreground=foreground,
                           background=background, noise=noise, rician=rician, bias=bias,
                           blur=blur, grid_rotation=grid_rotation, options=options,
                           geometry=geometry, init=init)


def _harmonic_sum(
    rng: np.random.Generator, degrees: Sequence[int], terms_per_degree: int
) -> tuple[list[tuple[int, NDArray, float]], Callable[[NDArray], NDArray]]:
    """A random real spherical harmonic combination h(n), scaled so that max |h| = 1.

    ``P_l(n . u)`` (Legendre polynomial of a dot product with a fixed axis u) is a degree-l
    spherical harmonic (a rotated zonal one), so sums of them with random axes are random
    low-order harmonics without any special-function library.
    """
    terms = []
    for l in degrees:
        for _ in range(terms_per_degree):
            u = rng.standard_normal(3)
            u /= np.linalg.norm(u)
            terms.append((int(l), u, float(rng.standard_normal())))

    def raw(n: NDArray) -> NDArray:
        out = np.zeros(n.shape[:-1])
        for l, u, w in terms:
            out += w * np.polynomial.legendre.Legendre.basis(l)(n @ u)
        return out

    scale = float(np.abs(raw(_fibonacci_sphere(4000))).max())
    return terms, (lambda n: raw(n) / scale)


def blob(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    radius: float | None = None,
    amplitude: float = 0.25,
    degrees: Sequence[int] = (2, 3, 4),
    center: Sequence[float] | None = None,
    foreground: float = 100.0,
    background: float = 20.0,
    noise: float = 0.05,
    rician: bool = False,
    bias: float = 0.0,
    blur: float = 0.0,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """A smooth star-shaped ("organ-like") blob on a uniform background.

    Its surface is ``|p - c| = r0 (1 + amplitude h(n))`` where n is the direction from the centre
    and h a random combination of low-order real spherical harmonics (``degrees``, two terms
    each) scaled to ``max |h| = 1``; ``amplitude < 1`` keeps it star-shaped.

    Parameters
    ----------
    radius : float, optional
        Mean radius r0 in mm; default 28 % of the smallest field-of-view extent.
    amplitude : float
        Relative radial modulation, in [0, 0.9].
    degrees : ints
        Harmonic degrees used (low: smooth lobes).
    Other parameters are as in :func:`ball`.

    Returns
    -------
    Phantom
        ``params["geometry"]["volume_mm3_analytic"]`` is ``(1/3) integral r(n)^3 dn`` by
        quadrature on the sphere. Init: a sphere of radius ``r0 (1 - amplitude) / 2``.
    """
    seed = _check_seed(seed)
    shape, spacing = _grid(shape, spacing, _DEFAULT_FOV)
    noise, bias, blur = _common_checks(noise, bias, blur)
    amplitude = _check_fraction("amplitude", amplitude, 0.9)
    fov_min = float((np.asarray(shape) * np.asarray(spacing)).min())
    r0 = 0.28 * fov_min if radius is None else _check_fraction("radius", radius)
    if r0 <= 0:
        raise ConfigError("radius must be positive")
    try:
        degs = [int(d) for d in degrees]
    except (TypeError, ValueError):
        raise ConfigError(f"degrees must be integers, got {degrees!r}") from None
    if not degs or any(d < 1 or d > 12 for d in degs):
        raise ConfigError(f"degrees must be integers in 1..12, got {degrees!r}")
    rng = _rng(seed, _GEOMETRY)
    c = _center_mm(center, shape, spacing, rng)
    terms, h = _harmonic_sum(rng, degs, 2)
    x, y, z = _axes_mm(shape, spacing)
    d = np.stack(np.broadcast_arrays(x - c[0], y - c[1], z - c[2]), axis=-1)
    rho = np.linalg.norm(d, axis=-1)
    n = d / np.where(rho > 0, rho, 1.0)[..., None]
    F = rho - r0 * (1.0 + amplitude * h(n))
    dirs = _fibonacci_sphere(20000)
    vol = 4.0 * np.pi / 3.0 * float(np.mean((r0 * (1.0 + amplitude * h(dirs))) ** 3))
    options = dict(radius=r0, amplitude=amplitude, degrees=degs, foreground=foreground,
                   background=background, noise=noise, rician=rician, bias=bias, blur=blur,
                   grid_rotation=grid_rotation)
    geometry = dict(center_mm=c, radius_mm=r0, volume_mm3_analytic=vol,
                    harmonics=[{"degree": l, "axis": u, "weight": w} for l, u, w in terms])
    init = _sphere_init(np.round(c / spacing) * spacing, [r0 * (1 - amplitude) / 2] * 3)
    return _object_phantom("blob", seed, F, shape, spacing, foreground=foreground,
                           background=background, noise=noise, rician=rician, bias=bias,
                           blur=blur, grid_rotation=grid_rotation, options=options,
                           geometry=geometry, init=init)


# --------------------------------------------------------------------------------------------
# 003 section 7.3: the hollow cylinder of Table 7.2
# --------------------------------------------------------------------------------------------


def hollow_cylinder(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    std: float = 0.0,
    radius: float | None = None,
    thickness: float = 2.0,
    length: float | None = None,
    axis: Sequence[float] = (0.0, 0.0, 1.0),
    center: Sequence[float] | None = None,
    clip: bool = False,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """The noisy hollow cylinder of 003 section 7.3.4 / Table 7.2.

    A "perfect" 8-bit hollow cylinder: voxels whose centre lies in the wall (radial distance from
    the axis within ``thickness / 2`` of ``radius`` and axial position within ``length / 2`` of
    the centre) are 255, everything else 0; open ends. With the defaults on a 128^3 grid the wall
    is 1.52 % of the voxels, which is what the thesis' SNR column implies:
    ``SNR = 10 log10(var(clean) / std^2)`` with ``var(clean) = 255^2 p (1 - p)`` gives 9.91 dB at
    std 10 for p ~ 1.5 %, and the other rows (std 30 ... 90) agree with the same p to 0.1 dB.

    Additive white Gaussian noise of standard deviation ``std`` (8-bit units) is added. The image
    is *not* clipped to [0, 255] by default: the table's SNR values are those of the nominal
    additive noise, and clipping would rectify the noise in the 98.5 % of zero voxels (at std 90
    it would change the effective noise by several dB). ``clip=True`` gives the 8-bit version.

    Parameters
    ----------
    std : float
        Noise standard deviation in 8-bit units (the table uses 0, 10, 30, 50, 70, 90).
    radius : float, optional
        Radius of the wall's mid-surface in mm; default 26.2 mm scaled by the smallest
        field-of-view extent across the axis over 128 mm.
    thickness : float
        Wall thickness in mm.
    length : float, optional
        Length of the cylinder in mm; default 3/4 of the field of view along ``axis``.
    axis : 3 floats
        Axis direction in scaled index space (normalised).
    center : 3 floats, optional
        Centre in mm; default the field-of-view centre.
    clip : bool
        Clip the noisy image to [0, 255].

    Returns
    -------
    Phantom
        Truth: the closed region inside the wall's mid-surface (radius < ``radius``, between the
        two end planes). Init: a coaxial cylinder of half the radius and half the length, centred,
        its axis shifted by 2 mm off the true axis (still inside): its Jaccard index against the
        truth is ``(1/2)^2 (1/2) = 0.125``, the thesis' "0.12". ``params["geometry"]`` has the
        mid-surface radius, axis, end points, wall fraction and the SNR of this image.
    """
    seed = _check_seed(seed)
    shape, spacing = _grid(shape, spacing, (128.0, 128.0, 128.0))
    std = _check_fraction("std", std)
    thickness = _check_fraction("thickness", thickness)
    fov = np.asarray(shape) * np.asarray(spacing)
    ax = _vector("axis", axis)
    if np.linalg.norm(ax) == 0:
        raise ConfigError("axis must be a non-zero vector")
    ax = ax / np.linalg.norm(ax)
    c = _fov_center(shape, spacing) if center is None else _vector("center", center)
    # Extent of the field of view along the axis and across it (for the defaults).
    along = float(np.abs(ax) @ fov)
    across = float(np.min(fov[np.abs(ax) < 0.9])) if np.any(np.abs(ax) < 0.9) else float(fov.min())
    # 26.2 mm on 128^3: wall fraction 1.52 %, every SNR of Table 7.2 within 0.08 dB.
    R = 26.2 / 128.0 * across if radius is None else _check_fraction("radius", radius)
    L = 0.75 * along if length is None else _check_fraction("length", length)
    if R <= thickness / 2 or L <= 0:
        raise ConfigError(f"radius ({R:g}) must exceed thickness/2 and length ({L:g}) be positive")
    x, y, z = _axes_mm(shape, spacing)
    d = (x - c[0], y - c[1], z - c[2])
    s = d[0] * ax[0] + d[1] * ax[1] + d[2] * ax[2]
    rad = np.sqrt(np.maximum(d[0] ** 2 + d[1] ** 2 + d[2] ** 2 - s**2, 0.0))
    within = np.abs(s) <= L / 2
    wall = within & (np.abs(rad - R) <= thickness / 2)
    truth = within & (rad < R)
    clean = np.where(wall, np.float32(255.0), np.float32(0.0))
    image = _form_image(clean, spacing, seed, blur=0.0, bias=0.0, noise_std=std, rician=False)
    if clip:
        image = np.clip(image, 0.0, 255.0)
    var_clean = float(clean.var(dtype=np.float64))
    snr = float(10 * np.log10(var_clean / std**2)) if std > 0 else float("inf")
    # Init: a perpendicular to the axis for the 2 mm lateral shift.
    perp = np.cross(ax, [1.0, 0.0, 0.0] if abs(ax[0]) < 0.9 else [0.0, 1.0, 0.0])
    perp /= np.linalg.norm(perp)
    ic = c + 2.0 * perp
    a0, a1 = ic - ax * L / 4, ic + ax * L / 4
    init = _cylinder_init(a0, a1, R / 2)
    options = dict(std=std, radius=R, thickness=thickness, length=L, axis=ax, clip=clip,
                   grid_rotation=grid_rotation)
    geometry = dict(
        center_mm=c,
        axis=ax,
        mid_radius_mm=R,
        length_mm=L,
        axis_start_mm=c - ax * L / 2,
        axis_end_mm=c + ax * L / 2,
        wall_fraction=float(wall.mean()),
        var_clean=var_clean,
        snr_db=snr,  # null in JSON when std = 0 (infinite SNR)
        table_7_2_snr_db=TABLE_7_2.get(int(std)) if float(std).is_integer() else None,
        init_jaccard_analytic=0.125,
    )
    # The truth as a straight swept tube: its in-volume centreline and the clicks along it.
    record, ends_mm = _tube_record(_hollow_cylinder_tube(geometry, spacing), shape, spacing,
                                   _affine(shape, spacing, grid_rotation), seed)
    geometry.update(record, ends_init=_init_to_voxels(ends_mm, spacing), ends_init_mm=ends_mm)
    return _finish("hollow-cylinder", seed, image, truth, spacing, grid_rotation, options,
                   geometry, init)


# --------------------------------------------------------------------------------------------
# Tubes: an aortic arch, an S-shaped vessel, a straight tube leaving the volume
# --------------------------------------------------------------------------------------------
#
# Their truth is a swept-disk tube (segsnake.swept_tube): disks of radius r(s) normal to a
# centreline, flat ends, so the section normal to the centreline is exactly the disk of radius
# r(s). Each records in params["geometry"] the part of the centreline inside the volume
# ("centerline": points in mm, voxels and world mm, radius, arc length), the suggested clicks
# ("ends_init": a cylinder between the points at 15 % and 85 % of that length with half the
# median radius, the real-data benchmark's tube click; "click": five points along the same stretch,
# each moved by a seeded vector of up to CLICK_SHIFT times the local radius, radii halved), and
# the image's SNR as Table 7.2 defines it (10 log10(var(clean) / std^2)). tube_truth() rebuilds
# the truth's SweptTube from a record; truth_profile() measures its sections.

#: Largest move of a centreline click point, as a fraction of the local radius.
CLICK_SHIFT = 0.2
#: Fractions of the in-volume centreline length where the clicks start and end.
CLICK_SPAN = (0.15, 0.85)
#: Number of centreline click points.
CLICK_POINTS = 5


def _voxel_box(shape: Sequence[int], spacing: Sequence[float]) -> tuple[NDArray, NDArray]:
    """The volume's extent in mm: voxel centres span [0, (n-1) s], voxels half a voxel more."""
    sp = np.asarray(spacing, dtype=float)
    return -0.5 * sp, (np.asarray(shape, dtype=float) - 0.5) * sp


def _in_volume_span(tube: SweptTube, shape: Sequence[int], spacing: Sequence[float]
                    ) -> tuple[float, float]:
    """Arc-length range of the longest stretch of the centreline inside the volume's box."""
    lo, hi = _voxel_box(shape, spacing)
    inside = np.all((tube.points >= lo) & (tube.points <= hi), axis=1)
    if not inside.any():
        raise ConfigError("the tube's centreline does not cross the field of view")
    # Longest run of consecutive inside samples.
    edges = np.diff(np.concatenate([[0], inside.astype(int), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    k = int(np.argmax(stops - starts))
    first, last = starts[k], stops[k] - 1

    def crossing(s_in: float, s_out: float) -> float:
        # Bisection on arc length for where the centreline meets the box's face.
        for _ in range(40):
            mid = 0.5 * (s_in + s_out)
            p = tube.point_at(mid)
            if np.all((p >= lo) & (p <= hi)):
                s_in = mid
            else:
                s_out = mid
        return s_in

    s0 = float(tube.arc[first]) if first == 0 else crossing(tube.arc[first], tube.arc[first - 1])
    s1 = float(tube.arc[last]) if last == len(inside) - 1 else crossing(tube.arc[last],
                                                                          tube.arc[last + 1])
    return s0, s1


def _snr_db(clean: NDArray, std: float) -> float:
    """Table 7.2's SNR: ``10 log10(var(clean) / std^2)`` (inf without noise)."""
    return float(10 * np.log10(float(clean.var(dtype=np.float64)) / std**2)) if std > 0 \
        else float("inf")


def _tube_record(tube: SweptTube, shape: Sequence[int], spacing: Sequence[float],
                 affine: NDArray, seed: int) -> tuple[dict, dict]:
    """The truth's centreline record and the suggested clicks (see the section comment).

    Returns ``(record, ends_init_mm)``: ``record`` goes into ``params["geometry"]``, the second
    is the end-point cylinder in mm of scaled index space (``_cylinder_init`` form).
    """
    from segsnake.pipeline import perpendicular_spacing

    sp = np.asarray(spacing, dtype=float)
    s0, s1 = _in_volume_span(tube, shape, spacing)
    length = s1 - s0
    n = max(2, int(np.ceil(length)) + 1)  # about 1 mm apart
    s = np.linspace(s0, s1, n)
    pts = tube.point_at(s)
    r = tube.radius_at(s)
    world = (affine[:3, :3] @ (pts / sp).T).T + affine[:3, 3]
    closed = s0 <= tube.arc[0] + 1e-9 and s1 >= tube.length - 1e-9
    centerline = {
        "definition": "disks of radius r(s) normal to the centreline, flat ends "
                      "(segsnake.swept_tube); the part inside the volume",
        "arc_length_mm": s - s0,
        "arc_offset_mm": s0,
        "length_mm": length,
        "points_mm": pts,
        "points_voxels": pts / sp,
        "points_world_mm": world,
        "radius_mm": r,
        "closed": bool(closed),  # both ends inside the volume
    }
    if closed:
        centerline["volume_mm3_analytic"] = tube.volume_analytic()
    # Clicks over the middle CLICK_SPAN of the in-volume length.
    a, b = (s0 + f * length for f in CLICK_SPAN)
    ends_mm = (tube.point_at(a), tube.point_at(b), 0.5 * float(np.median(r)))
    sc = np.linspace(a, b, CLICK_POINTS)
    rc = tube.radius_at(sc)
    rng = _rng(seed, _CLICK)
    shift = np.stack([_in_ball(rng, CLICK_SHIFT * float(rr)) for rr in rc])
    cp = tube.point_at(sc) + shift
    tang = tube.tangent_at(sc)
    rc_half = 0.5 * rc
    click = {
        "arc_length_mm": sc - s0,
        "points_mm": cp,
        "points_voxels": cp / sp,
        "radius_mm": rc_half,
        # Radii in voxels by segment --radius' rule: the voxel size across the local direction.
        "radius_voxels": [float(rr) / perpendicular_spacing(sp, t) for rr, t in zip(rc_half, tang)],
        "shift_mm": np.linalg.norm(shift, axis=1),
    }
    return {"centerline": centerline, "click": click}, _cylinder_init(*ends_mm)


def _tube_phantom(
    kind: str, seed: int, tube: SweptTube, shape: tuple[int, int, int],
    spacing: tuple[float, float, float], *, foreground: float, background: float, noise: float,
    rician: bool, bias: float, blur: float, grid_rotation: Sequence[float] | None,
    options: dict, geometry: dict, init: dict | None,
) -> Phantom:
    """Rasterize a swept tube, form the image, attach the centreline record and the clicks.

    ``init`` is the phantom's suggested initialisation in mm; None takes the end-point cylinder.
    """
    # The signed function is capped a few voxels outside, so the partial-volume gradient sees
    # no artificial jumps.
    cap = 4.0 * float(max(spacing))
    F = tube.signed_grid(shape, spacing, cap)
    affine = _affine(shape, spacing, grid_rotation)
    record, ends_mm = _tube_record(tube, shape, spacing, affine, seed)
    occ = _occupancy(F, spacing)
    clean = np.float32(background) + np.float32(foreground - background) * occ
    std = noise * abs(foreground - background)
    geometry = dict(geometry, **record, noise_std=std, snr_db=_snr_db(clean, std),
                    ends_init=_init_to_voxels(ends_mm, spacing), ends_init_mm=ends_mm)
    image = _form_image(clean, spacing, seed, blur=blur, bias=bias, noise_std=std, rician=rician)
    return _finish(kind, seed, image, F < 0, spacing, grid_rotation, options, geometry,
                   ends_mm if init is None else init)


def _arch_centerline(
    fov: NDArray, arch_radius: float, rise: float, drift: float, step: float
) -> tuple[NDArray, NDArray, int]:
    """Centreline samples (N, 3) in mm, arc-length parameter in [0, 1], index where the arch starts.

    Ascending straight part (up the third axis) from below the field of view, a half turn of
    radius ``arch_radius`` in the first/third-axis plane that also moves ``2 drift`` along the
    second axis (as the aortic arch runs posteriorly; the turn is a half ellipse in a tilted
    plane, its tangent continuous with both straight parts), and a descending straight part
    leaving below the field of view.
    """
    cx, cy, cz = fov / 2.0
    top = cz + rise  # height of the arch's centre
    bottom = -0.15 * fov[2]
    n_up = max(2, int(np.ceil((top - bottom) / step)))
    up_z = np.linspace(bottom, top, n_up, endpoint=False)
    up = np.stack([np.full(n_up, cx - arch_radius), np.full(n_up, cy - drift), up_z], axis=1)
    n_arc = max(8, int(np.ceil(np.pi * arch_radius / step)))
    ang = np.linspace(np.pi, 0.0, n_arc, endpoint=False)
    arc = np.stack(
        [cx + arch_radius * np.cos(ang), cy + drift * np.cos(ang), top + arch_radius * np.sin(ang)],
        axis=1,
    )
    down_z = np.linspace(top, bottom, n_up)
    down = np.stack([np.full(n_up, cx + arch_radius), np.full(n_up, cy + drift), down_z], axis=1)
    pts = np.concatenate([up, arc, down])
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    return pts, s / s[-1], n_up


def _arch_geometry(seed: int, shape: tuple[int, int, int], spacing: tuple[float, float, float],
                   radius: float | None, taper: float, arch_radius: float | None
                   ) -> tuple[SweptTube, dict, int]:
    """The arch's swept tube, its geometry record and the index where the arch starts."""
    fov = np.asarray(shape) * np.asarray(spacing)
    fov_c = _fov_center(shape, spacing)
    r_a = 0.09 * fov[0] if radius is None else _check_fraction("radius", radius)
    Ra = 0.25 * fov[0] if arch_radius is None else _check_fraction("arch_radius", arch_radius)
    if r_a <= 0 or Ra <= r_a:
        raise ConfigError(f"need 0 < radius ({r_a:g}) < arch_radius ({Ra:g})")
    rng = _rng(seed, _GEOMETRY)
    drift = float(rng.uniform(0.05, 0.12) * fov[1])
    bulge = float(rng.uniform(0.1, 0.2))
    step = 0.25 * float(min(spacing))
    # Field-of-view centre convention: voxel centres span [0, (n-1) s]; use that box.
    pts, t, n_up = _arch_centerline(2 * fov_c, Ra, 0.1 * fov[2], drift, step)
    r = r_a * (1.0 + (taper - 1.0) * t + bulge * np.exp(-(((t - 0.12) / 0.06) ** 2)))
    geometry = dict(arch_radius_mm=Ra, drift_mm=drift, bulge=bulge,
                    radius_range_mm=[r.min(), r.max()], radius_mm=r_a)
    return SweptTube(pts, r), geometry, n_up


def tube(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    radius: float | None = None,
    taper: float = 0.7,
    arch_radius: float | None = None,
    foreground: float = 100.0,
    background: float = 20.0,
    noise: float = 0.05,
    rician: bool = False,
    bias: float = 0.0,
    blur: float = 0.0,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """A filled vessel along an arch bent through 180 degrees, radius varying along it (an aorta).

    The object is a swept-disk tube (see the tubes' section comment): an ascending part (radius
    ``radius`` with a sinus-like bulge near its start), a half turn of radius ``arch_radius``
    drifting along the second axis, and a descending part whose radius tapers to
    ``taper * radius``; both straight parts leave the field of view through its low third-axis
    face. The seed perturbs the radius profile and the drift.

    Parameters
    ----------
    radius : float, optional
        Vessel radius at the ascending part, mm; default 9 % of the first-axis field of view.
    taper : float
        Ratio of the descending to the ascending radius.
    arch_radius : float, optional
        Radius of the arch's centreline, mm; default 25 % of the first-axis field of view.
    Other parameters are as in :func:`ball`.

    Returns
    -------
    Phantom
        Init: a cylinder along the ascending straight part (inside the field of view, below the
        arch), of half the local vessel radius. ``params["geometry"]`` also holds the centreline
        record, the end-point click ``ends_init`` and the five-point ``click``.
    """
    seed = _check_seed(seed)
    shape, spacing = _grid(shape, spacing, (96.0, 72.0, 96.0))
    noise, bias, blur = _common_checks(noise, bias, blur)
    taper = _check_fraction("taper", taper, 2.0)
    sw, geometry, n_up = _arch_geometry(seed, shape, spacing, radius, taper, arch_radius)
    fov = np.asarray(shape) * np.asarray(spacing)
    # Init along the ascending part: from 15 % of the third-axis extent to just below the arch.
    up_pts, up_r = sw.points[:n_up], sw.radii[:n_up]
    z_lo, z_hi = 0.15 * fov[2], up_pts[-1, 2] - 0.5 * geometry["radius_mm"]
    sel = (up_pts[:, 2] >= z_lo) & (up_pts[:, 2] <= z_hi)
    init = _cylinder_init(up_pts[sel][0], up_pts[sel][-1], float(up_r[sel].min()) / 2)
    options = dict(radius=geometry["radius_mm"], taper=taper, arch_radius=geometry["arch_radius_mm"],
                   foreground=foreground, background=background, noise=noise, rician=rician,
                   bias=bias, blur=blur, grid_rotation=grid_rotation)
    return _tube_phantom("tube", seed, sw, shape, spacing, foreground=foreground,
                         background=background, noise=noise, rician=rician, bias=bias, blur=blur,
                         grid_rotation=grid_rotation, options=options, geometry=geometry,
                         init=init)


def _s_geometry(seed: int, shape: Sequence[int] | None, spacing: tuple[float, float, float],
                radius: float, taper: float, bend_radius: float, bend: float, straight: float,
                rotation: Sequence[float] | None
                ) -> tuple[SweptTube, dict, tuple[int, int, int]]:
    """The S vessel's swept tube, its geometry record and the grid shape (derived when None)."""
    if radius <= 0 or bend_radius <= 0 or straight < 0:
        raise ConfigError("radius and bend_radius must be positive, straight non-negative")
    if radius * max(1.0, taper) >= 0.8 * bend_radius:
        raise ConfigError(f"the radius ({radius:g} mm, x taper) must stay below 0.8 x bend_radius "
                          f"({bend_radius:g} mm): the tube would fold onto itself")
    if not 0 < bend <= 150:
        raise ConfigError(f"bend must be in (0, 150] degrees, got {bend!r}")
    rng = _rng(seed, _GEOMETRY)
    theta = np.deg2rad(bend)
    arc_len = bend_radius * theta
    length = 2 * straight + 2 * arc_len
    # Heading phi(s) from the third axis towards the first: 0, up to theta, back to 0, 0.
    h = 0.02
    s = np.arange(0.0, length + h / 2, h)
    phi = np.clip(s - straight, 0, arc_len) / bend_radius \
        - np.clip(s - straight - arc_len, 0, arc_len) / bend_radius
    d = np.stack([np.sin(phi), np.zeros_like(phi), np.cos(phi)], axis=1)
    pts = np.concatenate([[np.zeros(3)], np.cumsum(0.5 * (d[1:] + d[:-1]) * h, axis=0)])
    if rotation is None:
        angles = rng.uniform(-25.0, 25.0, 3)
    else:
        angles = _vector("rotation", rotation)
    pts = pts @ Rotation.from_euler("xyz", angles, degrees=True).as_matrix().T
    r_end = radius * taper
    r = radius + (r_end - radius) * s / length
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    margin = max(radius, r_end) + 8.0
    if shape is None:
        fov = np.ceil((hi - lo + 2 * margin) / 8.0) * 8.0  # a round field of view (mm)
        shape = tuple(max(8, int(round(f / sp))) for f, sp in zip(fov, spacing))
    pts = pts - 0.5 * (lo + hi) + _fov_center(shape, spacing)
    keep = max(1, int(round(0.25 * min(spacing) / h)))  # samples 1/4 voxel apart
    idx = np.unique(np.r_[np.arange(0, len(s), keep), len(s) - 1])
    geometry = dict(radius_mm=radius, end_radius_mm=r_end, bend_radius_mm=bend_radius,
                    bend_deg=bend, straight_mm=straight, rotation=angles, length_mm=length)
    return SweptTube(pts[idx], r[idx]), geometry, shape  # type: ignore[return-value]


def s_vessel(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    radius: float = 4.0,
    taper: float = 1.0,
    bend_radius: float = 20.0,
    bend: float = 90.0,
    straight: float = 15.0,
    rotation: Sequence[float] | None = None,
    foreground: float = 100.0,
    background: float = 20.0,
    noise: float = 0.05,
    rician: bool = False,
    bias: float = 0.0,
    blur: float = 0.0,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """An S-shaped vessel wholly inside the volume: straight, two opposite bends, straight.

    Its centreline runs ``straight`` mm, turns by ``bend`` degrees on a circle of radius
    ``bend_radius``, turns back by as much, and runs ``straight`` mm again (a planar S), turned
    by ``rotation`` so it is oblique to the grid. The radius varies linearly from ``radius`` to
    ``taper * radius``; the ends are flat.

    Parameters
    ----------
    shape : 3 ints, optional
        Grid shape; default: the S's bounding box grown by its radius + 8 mm on every side,
        rounded up to 8 mm, divided by the spacing (the tube centred in it).
    radius : float
        Radius at the start, mm.
    taper : float
        Ratio of the end radius to the start radius.
    bend_radius : float
        Radius of curvature of both bends, mm (above 1.25 x the largest radius).
    bend : float
        Angle of each bend, degrees.
    straight : float
        Length of each straight end part, mm.
    rotation : 3 floats, optional
        Euler angles (degrees, "xyz") of the S; default drawn from the seed in [-25, 25].
    Other parameters are as in :func:`ball`.

    Returns
    -------
    Phantom
        Init: the end-point cylinder (``params["geometry"]["ends_init"]``); the geometry also
        holds the centreline record (with ``volume_mm3_analytic`` = pi * integral r^2 ds), the
        five-point ``click`` and the SNR.
    """
    seed = _check_seed(seed)
    taper = _check_fraction("taper", taper, 2.0)
    radius = _check_fraction("radius", radius)
    bend_radius = _check_fraction("bend_radius", bend_radius)
    straight = _check_fraction("straight", straight)
    if shape is not None:
        shape, spacing = _grid(shape, spacing, (0.0, 0.0, 0.0))
    else:
        spacing = _grid((8, 8, 8), spacing, (0.0, 0.0, 0.0))[1]
    noise, bias, blur = _common_checks(noise, bias, blur)
    sw, geometry, shape = _s_geometry(seed, shape, spacing, radius, taper, bend_radius,
                                      float(bend), straight, rotation)
    options = dict(radius=radius, taper=taper, bend_radius=bend_radius, bend=float(bend),
                   straight=straight, rotation=geometry["rotation"], foreground=foreground,
                   background=background, noise=noise, rician=rician, bias=bias, blur=blur,
                   grid_rotation=grid_rotation)
    return _tube_phantom("s-vessel", seed, sw, shape, spacing, foreground=foreground,
                         background=background, noise=noise, rician=rician, bias=bias, blur=blur,
                         grid_rotation=grid_rotation, options=options, geometry=geometry,
                         init=None)


def _exit_geometry(seed: int, shape: tuple[int, int, int], spacing: tuple[float, float, float],
                   radius: float) -> tuple[SweptTube, dict]:
    """A straight tube entering through the low first-axis face, leaving through the high third."""
    fov = 2 * _fov_center(shape, spacing)  # voxel centres span [0, fov]
    rng = _rng(seed, _GEOMETRY)
    j = rng.uniform(-0.05, 0.05, 3)
    entry = np.array([0.0, (0.5 + j[0]) * fov[1], (0.3 + j[1]) * fov[2]])
    exit_ = np.array([(0.62 + j[2]) * fov[0], (0.55 - j[0]) * fov[1], fov[2]])
    d = _unit3(exit_ - entry)
    # Check the faces the tube touches: its section on each face stays off the other faces.
    for name, p, ax in (("entry", entry, 0), ("exit", exit_, 2)):
        # On a face normal to axis `ax`, the section is an ellipse whose extent along axis m is
        # r sqrt(1 - d_m^2) / |d_ax|.
        half = radius * np.sqrt(np.maximum(1 - d**2, 0)) / abs(d[ax])
        for m in range(3):
            if m != ax and (p[m] - half[m] < 1.0 or p[m] + half[m] > fov[m] - 1.0):
                raise ConfigError(f"radius {radius:g} mm is too large for this field of view: "
                                  f"the tube's {name} section would reach another face")
    ext = 2 * radius / max(abs(d[0]), abs(d[2])) + 4.0  # ends well outside the volume
    geometry = dict(radius_mm=radius, direction=d, entry_mm=entry, exit_mm=exit_,
                    faces=["i-", "k+"])
    return _straight_tube(entry - ext * d, exit_ + ext * d, radius, spacing), geometry


def _straight_tube(a: NDArray, b: NDArray, radius: float, spacing: Sequence[float]) -> SweptTube:
    """A straight swept tube from ``a`` to ``b`` (mm), sampled 1/4 of the smallest voxel apart."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    n = int(np.ceil(np.linalg.norm(b - a) / (0.25 * float(min(spacing))))) + 1
    return SweptTube(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a), np.full(n, float(radius)))


def _unit3(v: NDArray) -> NDArray:
    return np.asarray(v, dtype=float) / float(np.linalg.norm(v))


def exiting_tube(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    radius: float = 5.0,
    foreground: float = 100.0,
    background: float = 20.0,
    noise: float = 0.05,
    rician: bool = False,
    bias: float = 0.0,
    blur: float = 0.0,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """A straight oblique tube that leaves the volume through two faces.

    It enters through the low face of the first axis (i = 0) and leaves through the high face of
    the third (k = n - 1); its flat ends lie outside the volume, so the truth touches exactly
    those two faces (``params["geometry"]["faces"]``). The seed moves the crossing points by up
    to 5 % of the field of view.

    Parameters
    ----------
    shape : 3 ints, optional
        Grid shape; default a 64 x 64 x 80 mm field of view divided by the spacing.
    radius : float
        Tube radius, mm.
    Other parameters are as in :func:`ball`.

    Returns
    -------
    Phantom
        Init: the end-point cylinder over the middle 70 % of the in-volume centreline (whose
        ends lie on the two faces).
    """
    seed = _check_seed(seed)
    shape, spacing = _grid(shape, spacing, (64.0, 64.0, 80.0))
    noise, bias, blur = _common_checks(noise, bias, blur)
    radius = _check_fraction("radius", radius)
    if radius <= 0:
        raise ConfigError("radius must be positive")
    sw, geometry = _exit_geometry(seed, shape, spacing, radius)
    options = dict(radius=radius, foreground=foreground, background=background, noise=noise,
                   rician=rician, bias=bias, blur=blur, grid_rotation=grid_rotation)
    return _tube_phantom("exiting-tube", seed, sw, shape, spacing, foreground=foreground,
                         background=background, noise=noise, rician=rician, bias=bias, blur=blur,
                         grid_rotation=grid_rotation, options=options, geometry=geometry,
                         init=None)


def tube_truth(params: dict) -> SweptTube:
    """Rebuild the swept tube whose inside is a tube phantom's truth, from its ``params``.

    Parameters
    ----------
    params : dict
        ``Phantom.params`` (or ``phantom.json``'s ``params``) of a ``tube``, ``s-vessel``,
        ``exiting-tube`` or ``hollow-cylinder`` phantom.

    Returns
    -------
    SweptTube
        In mm of scaled index space; its arc length is ``params["geometry"]["centerline"]``'s
        plus ``arc_offset_mm``.
    """
    kind = params["kind"]
    seed, opts = int(params["seed"]), params["options"]
    shape = tuple(int(n) for n in params["shape"])
    spacing = tuple(float(s) for s in params["spacing"])
    if kind == "tube":
        return _arch_geometry(seed, shape, spacing, opts["radius"], opts["taper"],
                              opts["arch_radius"])[0]
    if kind == "s-vessel":
        return _s_geometry(seed, shape, spacing, opts["radius"], opts["taper"],
                           opts["bend_radius"], opts["bend"], opts["straight"],
                           opts["rotation"])[0]
    if kind == "exiting-tube":
        return _exit_geometry(seed, shape, spacing, opts["radius"])[0]
    if kind == "hollow-cylinder":
        return _hollow_cylinder_tube(params["geometry"], spacing)
    raise ConfigError(f"phantom kind {kind!r} is not a tube")


def truth_profile(params: dict, arc_length: Sequence[float] | None = None,
                  step: float = 1.0, tube: SweptTube | None = None) -> dict[str, NDArray]:
    """The truth's sections along its centreline, measured (see :meth:`SweptTube.profile`).

    Measured, not analytic: rays in the plane normal to the true centreline, boundary crossings
    by bisection on the truth's exact membership test (not on its voxels), clipped to the
    volume's box. For these phantoms it agrees with the closed form (area ``pi r(s)^2``,
    diameters ``2 r(s)``) except where the box cuts a section.

    Parameters
    ----------
    params : dict
        A tube phantom's ``params`` (see :func:`tube_truth`).
    arc_length : floats, optional
        Positions (mm) along the recorded in-volume centreline (``params["geometry"]
        ["centerline"]["arc_length_mm"]``'s origin); default every ``step`` mm from ``step / 2``
        to its length (the sections exactly at the ends are degenerate: a flat end's plane, or
        the face a tube leaves through).
    step : float
        Spacing of the default positions, mm.
    tube : SweptTube, optional
        ``tube_truth(params)``, when the caller has built it already.

    Returns
    -------
    dict
        ``arc_length``, ``center`` (mm of scaled index space), ``center_world`` (world mm),
        ``area`` (mm^2), ``equivalent_diameter``, ``min_diameter``, ``max_diameter`` (mm).
    """
    sw = tube if tube is not None else tube_truth(params)
    cl = params["geometry"]["centerline"]
    if arc_length is None:
        arc_length = np.arange(0.5 * step, float(cl["length_mm"]), step)
    s = np.asarray(arc_length, dtype=float)
    shape, spacing = params["shape"], params["spacing"]
    prof = sw.profile(s + float(cl["arc_offset_mm"]), box=_voxel_box(shape, spacing))
    affine = _affine(shape, spacing, params["options"].get("grid_rotation"))
    c = prof["center"]
    prof["center_world"] = (affine[:3, :3] @ (c / np.asarray(spacing)).T).T + affine[:3, 3]
    prof["arc_length"] = s
    del prof["s"]
    return prof


def _hollow_cylinder_tube(geometry: dict, spacing: Sequence[float]) -> SweptTube:
    """The hollow cylinder's truth (inside the wall's mid-surface) as a straight swept tube."""
    return _straight_tube(geometry["axis_start_mm"], geometry["axis_end_mm"],
                          geometry["mid_radius_mm"], spacing)


# --------------------------------------------------------------------------------------------
# Brain: a BrainWeb-like head
# --------------------------------------------------------------------------------------------

_BRAINWEB_FOV = np.array([181.0, 217.0, 181.0])


class _SphereTable:
    """A function of direction tabulated on a (theta, phi) grid, looked up bilinearly.

    theta in [0, pi] (angle from the third axis) sampled with its end points, phi in [-pi, pi)
    periodic (a wrap column is appended), so no seam or pole needs special handling.
    """

    def __init__(self, n_theta: int = 361, n_phi: int = 720) -> None:
        self.n_theta, self.n_phi = n_theta, n_phi
        th = np.linspace(0.0, np.pi, n_theta)
        ph = np.linspace(-np.pi, np.pi, n_phi, endpoint=False)
        T, P = np.meshgrid(th, ph, indexing="ij")
        self.dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1)

    def coords(self, dx: NDArray, dy: NDArray, dz: NDArray, rho: NDArray) -> NDArray:
        """Fractional table indices for direction vectors (full-size arrays)."""
        ct = np.clip(dz / np.where(rho > 0, rho, 1.0), -1.0, 1.0)
        ti = np.arccos(ct) * np.float32((self.n_theta - 1) / np.pi)
        pj = (np.arctan2(dy, dx) + np.float32(np.pi)) * np.float32(self.n_phi / (2 * np.pi))
        return np.stack([ti.ravel(), pj.ravel()])

    def lookup(self, table: NDArray, coords: NDArray, shape: Sequence[int]) -> NDArray[np.float32]:
        padded = np.concatenate([table, table[:, :1]], axis=1).astype(np.float32)
        out = ndimage.map_coordinates(padded, coords, order=1, mode="nearest", prefilter=False)
        return out.reshape(shape)


def _smooth_sphere_noise(
    rng: np.random.Generator, dirs: NDArray, corr: float, grid: int = 48
) -> NDArray:
    """Standardised smooth random field on the unit sphere with correlation length ``corr``.

    A Gaussian-filtered 3D white noise on [-1.1, 1.1]^3 sampled on the unit sphere: seamless and
    isotropic, unlike noise drawn directly in (theta, phi).
    """
    noise = rng.standard_normal((grid, grid, grid))
    cell = 2.2 / (grid - 1)
    field = ndimage.gaussian_filter(noise, corr / cell, mode="wrap")
    idx = (dirs.reshape(-1, 3).T + 1.1) / cell
    vals = ndimage.map_coordinates(field, idx, order=3, mode="nearest").reshape(dirs.shape[:-1])
    return (vals - vals.mean()) / vals.std()


def _ellipsoid_occupancy_into(
    out: NDArray, value: float, center: NDArray, radii: NDArray, R: NDArray,
    spacing: Sequence[float],
) -> NDArray[np.bool_]:
    """Blend ``value`` into ``out`` over a rotated ellipsoid (partial volume); return its mask."""
    sp = np.asarray(spacing, dtype=float)
    ext = float(np.max(radii)) + 2 * float(sp.max())
    lo = np.maximum(np.floor((center - ext) / sp).astype(int), 0)
    hi = np.minimum(np.ceil((center + ext) / sp).astype(int) + 1, out.shape)
    x = np.arange(lo[0], hi[0])[:, None, None] * sp[0] - center[0]
    y = np.arange(lo[1], hi[1])[None, :, None] * sp[1] - center[1]
    z = np.arange(lo[2], hi[2])[None, None, :] * sp[2] - center[2]
    q2 = 0.0
    for m in range(3):
        qm = (R[0, m] * x + R[1, m] * y + R[2, m] * z) / radii[m]
        q2 = q2 + qm * qm
    F = (np.sqrt(q2) - 1.0) * float(np.min(radii))  # ~ signed distance near the surface (mm)
    occ = _occupancy(F, spacing)
    sub = out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    sub += occ * (np.float32(value) - sub)
    mask = np.zeros(out.shape, dtype=bool)
    mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = F < 0
    return mask


def brain(
    seed: int = 0,
    *,
    shape: Sequence[int] | None = None,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    contrast: str = "t1",
    noise: float = 0.03,
    rician: bool = False,
    bias: float = 0.0,
    blur: float = 0.0,
    fold_depth: float = 10.0,
    cortex: float = 3.0,
    grid_rotation: Sequence[float] | None = None,
) -> Phantom:
    """A BrainWeb-like head: folded brain (WM, GM cortex, ventricles, deep GM) in CSF, skull, scalp.

    Geometry is radial about the head centre: every boundary is ``|p - c| = R(n)`` with R a
    function of the direction n tabulated on the sphere. The brain hull is an ellipsoid (BrainWeb
    proportions: 66 x 84 x 62 mm semi-axes) with a seeded low-order asymmetry; the pial surface
    dips by up to ``fold_depth`` mm along the zero lines of a smooth random field on the sphere
    (a network of narrow sulci filled with CSF); the WM surface lies ``cortex`` mm below the pial
    surface and dips along wider grooves, so the sulci are lined with grey matter. Outside the
    hull: 2.5 mm of CSF, a 6 mm skull (dark on both contrasts), a 5 mm scalp (bright fat on T1).
    Two lateral ventricles (CSF) and two deep grey nuclei sit inside the white matter. The whole
    head is scaled down when the field of view is smaller than BrainWeb's 181 x 217 x 181 mm.

    Parameters
    ----------
    shape : 3 ints, optional
        Grid shape; default BrainWeb's field of view (181, 217, 181 mm) divided by the spacing.
        A smaller grid (e.g. 96^3 at 2 mm) gives a proportionally scaled head.
    contrast : {"t1", "pd"}
        Tissue intensities (:data:`BRAIN_INTENSITIES`); the brightest tissue is 100 in both.
    noise : float
        Noise std as a fraction of the brightest tissue (BrainWeb's "%": 0.01 ... 0.09).
    rician : bool
        Rician (magnitude) noise instead of Gaussian.
    bias : float
        RF non-uniformity: peak-to-peak range of the multiplicative field over the head (0-0.4).
    blur : float
        Gaussian blur sigma in mm.
    fold_depth : float
        Depth of the sulci in mm (before scaling).
    cortex : float
        Cortical thickness in mm (before scaling).

    Returns
    -------
    Phantom
        Truth: the brain, i.e. every voxel centre inside the pial surface (WM, GM and the
        ventricles they enclose; sulcal and outer CSF excluded). Init: an ellipsoid ("sphere"
        init with three radii) with half the hull's semi-axes, at the head centre.
        ``Phantom.labels`` is the tissue label map; ``params["geometry"]["class_voxels"]`` counts
        the voxels per class.
    """
    seed = _check_seed(seed)
    shape, spacing = _grid(shape, spacing, _BRAINWEB_FOV)
    noise, bias, blur = _common_checks(noise, bias, blur)
    if contrast not in BRAIN_INTENSITIES:
        raise ConfigError(f"contrast must be one of {sorted(BRAIN_INTENSITIES)}, got {contrast!r}")
    fold_depth = _check_fraction("fold_depth", fold_depth, 30.0)
    cortex = _check_fraction("cortex", cortex, 10.0)
    I = BRAIN_INTENSITIES[contrast]
    sp = np.asarray(spacing)
    fov = np.asarray(shape) * sp
    scale = float(min(1.0, np.min(fov / _BRAINWEB_FOV)))
    c = _fov_center(shape, spacing) + np.array([0.0, 0.0, 4.0]) * scale
    rng = _rng(seed, _GEOMETRY)

    # ---- radial tables (mm) ----
    tab = _SphereTable()
    dirs = tab.dirs
    hull_axes = np.array([66.0, 84.0, 62.0]) * scale
    ell = 1.0 / np.sqrt(np.sum((dirs / hull_axes) ** 2, axis=-1))
    _, low = _harmonic_sum(rng, (2, 3), 2)
    hull = ell * (1.0 + 0.035 * low(dirs))
    h = _smooth_sphere_noise(rng, dirs, corr=0.045, grid=96)
    depth_mod = 0.6 + 0.4 * (0.5 + 0.5 * np.tanh(_smooth_sphere_noise(rng, dirs, corr=0.3)))
    D = fold_depth * scale * depth_mod
    # Super-Gaussian groove profiles: steep walls, so a sulcus is a slit of nearly constant width.
    w_pial, w_wm = 0.15, 0.5
    pial = hull - D * np.exp(-((h / w_pial) ** 4))
    wm = hull - cortex * scale - D * np.exp(-((h / w_wm) ** 4))
    wm = np.minimum(wm, pial - 0.5 * cortex * scale)
    csf = hull + 2.5 * scale  # outer CSF 2.5, skull 6, scalp 5 (x scale mm), as shells below

    # ---- per voxel: distance and direction from the centre ----
    x, y, z = _axes_mm(shape, spacing)
    dx = (x - c[0]).astype(np.float32)
    dy = (y - c[1]).astype(np.float32)
    dz = (z - c[2]).astype(np.float32)
    rho = np.sqrt(dx * dx + dy * dy + dz * dz)
    coords = tab.coords(*np.broadcast_arrays(dx, dy, dz), rho)
    # Width of one voxel along the radial direction, for the partial-volume ramps.
    width = (np.abs(dx) * sp[0] + np.abs(dy) * sp[1] + np.abs(dz) * sp[2]) / np.where(
        rho > 0, rho, 1.0
    )
    width = np.maximum(width, np.float32(sp.min()))

    def inside(table: NDArray) -> NDArray[np.float32]:
        R = tab.lookup(table, coords, shape)
        return np.clip(np.float32(0.5) - (rho - R) / width, 0.0, 1.0)

    R_pial = tab.lookup(pial, coords, shape)
    truth = rho < R_pial
    t_pial = np.clip(np.float32(0.5) - (rho - R_pial) / width, 0.0, 1.0)
    del R_pial
    t_wm = inside(wm)
    # Skull and scalp boundaries are smooth: evaluate the scalp ramp once, derive the others by
    # the constant offsets (they are parallel radial shells).
    R_csf = tab.lookup(csf, coords, shape)
    t_csf = np.clip(np.float32(0.5) - (rho - R_csf) / width, 0.0, 1.0)
    t_skull = np.clip(np.float32(0.5) - (rho - R_csf - np.float32(6.0 * scale)) / width, 0.0, 1.0)
    t_scalp = np.clip(np.float32(0.5) - (rho - R_csf - np.float32(11.0 * scale)) / width, 0.0, 1.0)
    # Dice of the unfolded hull against the truth: what a smooth surface that ignores the sulci
    # can reach at best (a yardstick for snake results).
    hull_mask = rho < R_csf - np.float32(2.5 * scale)
    hull_dice = 2.0 * float(np.count_nonzero(hull_mask & truth)) / float(
        np.count_nonzero(hull_mask) + np.count_nonzero(truth))
    del hull_mask
    del R_csf, coords
    # Telescoped sum of nested shells: I_wm t_wm + I_gm (t_pial - t_wm) + ... + I_scalp t_scalp.
    img = np.float32(I["wm"] - I["gm"]) * t_wm
    img += np.float32(I["gm"] - I["csf"]) * t_pial
    img += np.float32(I["csf"] - I["skull"]) * t_csf
    img += np.float32(I["skull"] - I["scalp"]) * t_skull
    img += np.float32(I["scalp"] - I["background"]) * t_scalp
    img += np.float32(I["background"])

    # Label map (at voxel centres) for class statistics: 0 bg, 1 scalp, 2 skull, 3 CSF, 4 GM, 5 WM.
    labels = (t_scalp > 0.5).astype(np.uint8)
    labels += t_skull > 0.5
    labels += t_csf > 0.5
    labels += truth
    labels += (t_wm > 0.5) & truth
    del t_wm, t_pial, t_csf, t_skull, t_scalp

    # Deep grey nuclei and lateral ventricles (in the white matter, well inside the brain).
    s = scale
    for sgn in (-1.0, 1.0):
        Rn = Rotation.from_euler("z", sgn * 10.0, degrees=True).as_matrix()
        m = _ellipsoid_occupancy_into(img, I["gm"], c + np.array([sgn * 14.0, -6.0, -2.0]) * s,
                                      np.array([8.0, 13.0, 9.0]) * s, Rn, spacing)
        labels[m & truth] = 4
    for sgn in (-1.0, 1.0):
        Rv = Rotation.from_euler("yz", [sgn * 20.0, sgn * 8.0], degrees=True).as_matrix()
        m = _ellipsoid_occupancy_into(img, I["csf"], c + np.array([sgn * 7.5, 4.0, 12.0]) * s,
                                      np.array([4.5, 26.0, 7.0]) * s, Rv, spacing)
        labels[m & truth] = 3

    std = noise * max(I.values())
    # The bias range is normalised over the head: every voxel with any tissue in it.
    image = _form_image(img, spacing, seed, blur=blur, bias=bias, noise_std=std, rician=rician,
                        bias_mask=img > np.float32(I["background"]))
    names = ["background", "scalp", "skull", "csf", "gm", "wm"]
    counts = np.bincount(labels.ravel(), minlength=6)
    options = dict(contrast=contrast, noise=noise, rician=rician, bias=bias, blur=blur,
                   fold_depth=fold_depth, cortex=cortex, grid_rotation=grid_rotation)
    geometry = dict(
        center_mm=c,
        scale=scale,
        hull_semi_axes_mm=hull_axes,
        intensities=I,
        noise_std=std,
        class_voxels={n: int(k) for n, k in zip(names, counts)},
        fold_depth_mm=fold_depth * scale,
        hull_dice=hull_dice,
    )
    init = _sphere_init(np.round(c / sp) * sp, hull_axes / 2)
    ph = _finish("brain", seed, image, truth, spacing, grid_rotation, options, geometry, init)
    ph.params["labels"] = names
    ph.labels = labels
    return ph


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

PHANTOMS: dict[str, Callable[..., Phantom]] = {
    "ball": ball,
    "ellipsoid": ellipsoid,
    "blob": blob,
    "hollow-cylinder": hollow_cylinder,
    "tube": tube,
    "s-vessel": s_vessel,
    "exiting-tube": exiting_tube,
    "brain": brain,
}


def phantom_options(kind: str) -> list[str]:
    """Names of the keyword options a phantom kind accepts."""
    fn = PHANTOMS[_kind_name(kind)]
    return [p.name for p in inspect.signature(fn).parameters.values()
            if p.kind is inspect.Parameter.KEYWORD_ONLY]


def _kind_name(kind: str) -> str:
    name = str(kind).replace("_", "-").lower()
    if name not in PHANTOMS:
        raise ConfigError(f"unknown phantom kind {kind!r} (kinds: {', '.join(PHANTOMS)})")
    return name


def make_phantom(kind: str, seed: int = 0, **options: Any) -> Phantom:
    """Build a phantom by name.

    Parameters
    ----------
    kind : str
        One of :data:`PHANTOMS` (``hollow_cylinder`` is accepted for ``hollow-cylinder``).
    seed : int
        Seed of every random draw.
    **options
        Keyword options of that kind's function.

    Returns
    -------
    Phantom

    Raises
    ------
    ConfigError
        Unknown kind, an option that kind does not take, or an invalid value.
    """
    name = _kind_name(kind)
    accepted = phantom_options(name)
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise ConfigError(
            f"phantom {name!r} does not take option(s) {', '.join(unknown)} "
            f"(accepted: {', '.join(accepted)})"
        )
    return PHANTOMS[name](seed, **options)


def rasterize_init(init: dict, shape: Sequence[int], spacing: Sequence[float]) -> NDArray[np.bool_]:
    """Voxel mask of an initialisation dict (sphere/ellipsoid or capped cylinder), for checks.

    Parameters
    ----------
    init : dict
        As in ``Phantom.params["init_mm"]`` (mm in scaled index space).
    shape : 3 ints
        Grid shape.
    spacing : 3 floats
        Voxel size in mm.

    Returns
    -------
    ndarray of bool
        True at voxel centres inside the initial surface.
    """
    x, y, z = _axes_mm(shape, spacing)
    if init["shape"] == "sphere":
        c = np.asarray(init["center"], dtype=float)
        r = np.asarray(init["radii"], dtype=float)
        return ((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((z - c[2]) / r[2]) ** 2 < 1
    if init["shape"] == "cylinder":
        a = np.asarray(init["axis_start"], dtype=float)
        b = np.asarray(init["axis_end"], dtype=float)
        r = float(init["radius"])
        u = b - a
        L = float(np.linalg.norm(u))
        u /= L
        d = (x - a[0], y - a[1], z - a[2])
        s = d[0] * u[0] + d[1] * u[1] + d[2] * u[2]
        rad2 = d[0] ** 2 + d[1] ** 2 + d[2] ** 2 - s**2
        return (s >= 0) & (s <= L) & (rad2 < r * r)
    raise ConfigError(f"unknown init shape {init.get('shape')!r}")
