"""Shape spaces from examples: unbiased affine alignment and functional PCA (thesis ch. 5).

Given snakes ``sigma_1 .. sigma_K`` of one kind and size, each spans the affine shape space
``S_i = {A sigma_i + b}``; ``P_i`` is its L2-orthogonal projector (exact, through the Gram
matrices of :mod:`segsnake.priors`).

*Reference* (003 Definition 5, Proposition 5): the surface closest to all the ``S_i``,
``argmax sum_i ||P_i sigma||^2`` subject to ``||sigma|| = 1``, i.e. the leading eigenvectors of
``sum_i P_i``. As printed, that problem is degenerate: the translations lie in every ``S_i``
(eigenvalue ``K``) and ``P_i`` acts on x, y and z separately with the same scalar projector
``Q_i`` onto ``span{1, x_i, y_i, z_i}``, so a flat ``(f, 0, 0)`` is as good as any surface. The
well-posed version solved here: the reference's three coordinates are the three leading
eigenfunctions of ``sum_i Q_i`` orthogonal to the constants (the 4-dimensional function space
closest to all the ``span{1, x_i, y_i, z_i}``, which is what "closest to all affine spaces"
means once the reference itself is only defined up to an affine map). The eigenproblem is solved
as an SVD of the stacked orthonormal bases in the Cholesky-whitened metric. The result is then
placed in the pose of the first example (its best affine image fitting ``sigma_1``): every
later step commutes with affine maps of the reference, so that choice only fixes units and
orientation (mm of the first snake's image).

*Aligned set*: ``sigma~_i = P_i sigma_ref = A_i sigma_i + b_i``, each example's best affine image
approximating the reference (003 Definition 4). Its parameters are ``A_i p_i + b_i`` (tangent
vectors without ``b``), so aligned shapes are snakes of the same model.

*Similarity or rigid alignment* (``build_shape_model(..., align="similarity")``, generalized
Procrustes analysis): each example is mapped onto the current reference by its exact L2
Procrustes fit ``s R sigma_i + b`` (:mod:`segsnake.procrustes`), the reference becomes the mean of
the aligned set (its centred L2 norm held at the first example's for ``similarity``, so that it
does not shrink), until it stops changing. The modes then keep the anisotropic variation that an
affine alignment removes, which is what a rigid or similarity prior with modes needs.

*Functional PCA* (003 Proposition 7, with the mean removed, as in the usual PCA): with
``D = [sigma~_i - mean]`` the Gram matrix ``G = D^T beta D`` (``K x K``, exact L2 inner products)
has eigenpairs ``(lambda_k, v_k)``; the principal shapes are ``xi_k = D v_k / sqrt(lambda_k)``
(unit L2 norm) and the variance of the aligned set along ``xi_k`` is ``lambda_k / (K - 1)``
(mm^2, the L2 norm being the mean over the parameter domain). Computed as the SVD of the
whitened data ``L^T D`` (same eigenpairs, without squaring the condition number).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import scipy.linalg as la
from numpy.typing import ArrayLike, NDArray

from segsnake.priors import inner_product, l2_norm, param_gram
from segsnake.priors import _param_cholesky  # noqa: PLC2701 (same package, shared factor)
from segsnake.surfaces import SplineSurface, model_from_dict

__all__ = [
    "ShapeModel",
    "affine_fit",
    "unbiased_reference",
    "align_to_reference",
    "functional_pca",
    "build_shape_model",
    "procrustes_alignment",
    "ALIGNMENTS",
    "load_shape_model",
    "FORMAT",
]

FORMAT = "segsnake-shape-model"
FORMAT_VERSION = 1


def _check_same(shapes: Sequence[SplineSurface]) -> None:
    if len(shapes) == 0:
        raise ValueError("no shapes given")
    k0 = (shapes[0].kind, shapes[0].m1, shapes[0].m2)
    for i, s in enumerate(shapes):
        if (s.kind, s.m1, s.m2) != k0:
            raise ValueError(f"shape {i} is a {s.kind} with M1={s.m1}, M2={s.m2}; shape 0 is a "
                             f"{k0[0]} with M1={k0[1]}, M2={k0[2]}")


def _translation(model: SplineSurface) -> NDArray:
    return (~model.is_vector).astype(np.float64)


def _centre(model: SplineSurface, params: NDArray) -> tuple[NDArray, NDArray]:
    """Parameters minus their L2 centroid (control points only), and that centroid."""
    t = _translation(model)
    Bt = param_gram(model) @ t
    centroid = (Bt @ params) / (Bt @ t)
    return params - t[:, None] * centroid[None, :], centroid


def affine_fit(source: SplineSurface, target: SplineSurface) -> tuple[NDArray, NDArray]:
    """``A, b`` minimizing ``||A sigma_source + b - sigma_target||_L2`` (exact Gram metric).

    ``source.transformed(A, b)`` is then the orthogonal projection of the target onto the affine
    shape space of the source. Solved as a least-squares problem in the Cholesky-whitened
    metric (``B = L L^T``), on the centred source for conditioning.
    """
    _check_same([source, target])
    L = _param_cholesky(source)
    centred, centroid = _centre(source, source.params)
    X = np.hstack([centred, _translation(source)[:, None]])  # (P, 4)
    coef, *_ = np.linalg.lstsq(L.T @ X, L.T @ target.params, rcond=None)  # (4, 3)
    A = coef[:3].T
    b = coef[3] - A @ centroid
    return A, b


def _whitened_basis(model: SplineSurface, L: NDArray) -> NDArray:
    """Orthonormal basis ``(P, <=4)`` of ``L^T span{1, x, y, z}`` of one shape."""
    centred, _ = _centre(model, model.params)
    Y = L.T @ np.hstack([centred, _translation(model)[:, None]])
    Y = Y / np.maximum(np.linalg.norm(Y, axis=0), 1e-300)
    U, s, _ = np.linalg.svd(Y, full_matrices=False)
    return U[:, s > 1e-10 * s[0]]


def unbiased_reference(shapes: Sequence[SplineSurface]) -> tuple[SplineSurface, NDArray]:
    """The surface closest to the affine spaces of all ``shapes`` (003 Proposition 5).

    Returns
    -------
    reference : SplineSurface
        In the pose of ``shapes[0]`` (its best affine image fitting the first shape).
    eigenvalues : ndarray (3,)
        The three leading eigenvalues of ``sum_i Q_i`` off the constants, divided by ``K``:
        1 means every example is an affine image of the reference.
    """
    shapes = list(shapes)
    _check_same(shapes)
    L = _param_cholesky(shapes[0])
    e = L.T @ _translation(shapes[0])
    e /= np.linalg.norm(e)
    W = np.hstack([_whitened_basis(s, L) for s in shapes])
    W -= np.outer(e, e @ W)  # the constants are in every space: solve on their complement
    U, s, _ = np.linalg.svd(W, full_matrices=False)
    Z = U[:, :3]
    params = la.solve_triangular(L.T, Z, lower=False)  # coordinates of the whitened reference
    white = shapes[0].with_params(params)
    A, b = affine_fit(white, shapes[0])
    return white.transformed(A, b), s[:3] ** 2 / len(shapes)


def align_to_reference(shapes: Sequence[SplineSurface], reference: SplineSurface
                       ) -> tuple[list[SplineSurface], list[tuple[NDArray, NDArray]], NDArray]:
    """Aligned set ``sigma~_i = P_i sigma_ref = A_i sigma_i + b_i`` (003 Definition 4).

    Returns the aligned snakes, the transforms ``(A_i, b_i)`` and the residuals
    ``||sigma_ref - sigma~_i||_L2`` (mm).
    """
    shapes = list(shapes)
    _check_same(shapes + [reference])
    aligned, transforms, residuals = [], [], []
    for s in shapes:
        A, b = affine_fit(s, reference)
        a = s.transformed(A, b)
        aligned.append(a)
        transforms.append((A, b))
        residuals.append(l2_norm(reference, a.params - reference.params))
    return aligned, transforms, np.asarray(residuals)


def functional_pca(shapes: Sequence[SplineSurface], rel_tol: float = 1e-12
                   ) -> tuple[SplineSurface, NDArray, NDArray]:
    """Mean, principal shapes and variances of a set of (aligned) snakes (003 Proposition 7).

    Returns
    -------
    mean : SplineSurface
    modes : ndarray (n, P, 3)
        Parameter directions of unit L2 norm, mutually L2-orthogonal, by decreasing variance.
    variances : ndarray (n,)
        ``lambda_k / (K - 1)`` in mm^2; modes with ``lambda_k <= rel_tol * lambda_1`` (or below
        the rounding floor ``1e-20 ||mean - centroid||^2``) are dropped.
    """
    shapes = list(shapes)
    _check_same(shapes)
    X = np.stack([s.params for s in shapes])  # (K, P, 3)
    K = len(X)
    mean = X.mean(axis=0)
    D = X - mean
    # G = D^T beta D = Y^T Y with Y = L^T D the whitened data (B = L L^T): its eigenpairs are
    # the SVD of Y, which keeps the small modes accurate (eigh of G would square their error),
    # and the modes L^-T U are L2-orthonormal to rounding.
    L = _param_cholesky(shapes[0])
    Y = np.stack([(L.T @ d).T.ravel() for d in D], axis=1)  # (3P, K), stacked coordinates
    U, sv, _ = np.linalg.svd(Y, full_matrices=False)
    lam = sv ** 2
    # Noise floor: rounding in the aligned parameters (~1e-13 of the shape's size) gives
    # eigenvalues ~1e-26 size^2 even for identical shapes; they are not modes.
    size2 = inner_product(shapes[0], *2 * (_centre(shapes[0], mean)[0],))
    floor = max(rel_tol * lam[0], 1e-20 * size2) if K > 1 else np.inf
    keep = lam > floor
    if not np.any(keep):
        return shapes[0].with_params(mean), np.zeros((0,) + mean.shape), np.zeros(0)
    U, lam = U[:, keep], lam[keep]
    P = L.shape[0]
    modes = np.stack([la.solve_triangular(L.T, u.reshape(3, P).T, lower=False) for u in U.T])
    # Fix the sign of each mode (eigenvectors are defined up to sign): largest entry positive.
    for m in modes:
        i = np.unravel_index(np.argmax(np.abs(m)), m.shape)
        if m[i] < 0:
            m *= -1
    return shapes[0].with_params(mean), modes, lam / (K - 1)


@dataclass
class ShapeModel:
    """A shape space learned from examples: reference, aligned set, mean and modes.

    Attributes
    ----------
    reference : SplineSurface
        Unbiased affine-aligned reference (pose of the first example); what a shape prior uses.
    mean : SplineSurface
        Mean of the aligned set.
    modes : ndarray (n, P, 3)
        Principal shapes (parameter directions of unit L2 norm).
    variances : ndarray (n,)
        Variance of the aligned set along each mode, mm^2.
    aligned : list of SplineSurface
        ``A_i sigma_i + b_i``, closest to the reference.
    transforms : list of (A, b)
    residuals : ndarray (K,)
        ``||sigma_ref - sigma~_i||_L2`` in mm.
    agreement : ndarray (3,)
        Leading eigenvalues of Proposition 5 over K (1 = affinely identical examples); empty for
        a similarity or rigid alignment.
    sources : list of str
        Where the examples came from (file names), for the record.
    """

    reference: SplineSurface
    mean: SplineSurface
    modes: NDArray
    variances: NDArray
    aligned: list[SplineSurface]
    transforms: list[tuple[NDArray, NDArray]]
    residuals: NDArray
    agreement: NDArray
    sources: list[str] = field(default_factory=list)
    space: str = "affine"

    @property
    def explained(self) -> NDArray:
        """Fraction of the aligned set's total variance along each mode."""
        total = float(np.sum(self.variances))
        return self.variances / total if total > 0 else np.zeros_like(self.variances)

    def instance(self, coefficients: ArrayLike) -> SplineSurface:
        """``mean + sum_k c_k sqrt(variance_k) xi_k`` (coefficients in standard deviations)."""
        c = np.asarray(coefficients, dtype=np.float64).ravel()
        if len(c) > len(self.variances):
            raise ValueError(f"{len(c)} coefficients for {len(self.variances)} modes")
        delta = np.einsum("n,npd->pd", c * np.sqrt(self.variances[: len(c)]), self.modes[: len(c)])
        return self.mean.with_params(self.mean.params + delta)

    def coefficients(self, shape: SplineSurface) -> NDArray:
        """Mode coefficients (in standard deviations) of a snake, after aligning it (with the
        model's own alignment)."""
        if self.space == "affine":
            aligned_params = align_to_reference([shape], self.reference)[0][0].params
        else:
            from segsnake.procrustes import procrustes_fit

            sc, R, b = procrustes_fit(shape, self.reference.params, shape.params, self.space)
            aligned_params = sc * shape.params @ R.T + _translation(shape)[:, None] * b[None, :]
        d = aligned_params - self.mean.params
        proj = np.array([inner_product(self.mean, d, m) for m in self.modes])
        return proj / np.sqrt(np.maximum(self.variances, 1e-300))

    # -- serialization ------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-able; the reference is stored under ``model`` so :func:`load_model` reads it."""
        return {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "model": self.reference.to_dict(),
            "space": self.space,
            "metric": "L2 over the parameter domain (u, v) in [0, 1]^2, exact Gram matrices",
            "units": "mm (scaled index space of the first example); variances in mm^2",
            "n_shapes": len(self.aligned),
            "agreement": self.agreement.tolist(),
            "mean": self.mean.to_dict(),
            "modes": self.modes.tolist(),
            "variances_mm2": self.variances.tolist(),
            "explained": self.explained.tolist(),
            "shapes": [
                {"source": src, "A": A.tolist(), "b": b.tolist(), "residual_mm": float(r),
                 "aligned_params": a.params.tolist()}
                for src, (A, b), r, a in zip(self._sources(), self.transforms, self.residuals,
                                             self.aligned)
            ],
        }

    def _sources(self) -> list[str]:
        return list(self.sources) + [""] * (len(self.aligned) - len(self.sources))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ShapeModel":
        """Inverse of :meth:`to_dict`."""
        if d.get("format") != FORMAT:
            raise ValueError(f"not a segsnake shape model (missing 'format: {FORMAT}')")
        reference = model_from_dict(d["model"])
        mean = model_from_dict(d["mean"])
        shapes = d.get("shapes", [])
        n_par = (reference.n_params, 3)
        modes = np.asarray(d["modes"], dtype=np.float64).reshape((-1,) + n_par)
        return cls(
            reference=reference, mean=mean, modes=modes,
            variances=np.asarray(d["variances_mm2"], dtype=np.float64),
            aligned=[reference.with_params(s["aligned_params"]) for s in shapes],
            transforms=[(np.asarray(s["A"], dtype=np.float64), np.asarray(s["b"], dtype=np.float64))
                        for s in shapes],
            residuals=np.asarray([s["residual_mm"] for s in shapes], dtype=np.float64),
            agreement=np.asarray(d.get("agreement", []), dtype=np.float64),
            sources=[s.get("source", "") for s in shapes],
            space=str(d.get("space", "affine")),
        )

    def save(self, path: str | os.PathLike, overwrite: bool = False) -> None:
        """Write :meth:`to_dict` as JSON atomically (OutputError if it exists, unless overwrite)."""
        from segsnake.io import atomic_write

        text = json.dumps(self.to_dict())

        def writer(tmp: str) -> None:
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write(text)

        atomic_write(path, writer, overwrite=overwrite)


#: Alignments :func:`build_shape_model` offers.
ALIGNMENTS = ("affine", "similarity", "rigid")

#: Generalized Procrustes: iterations at most, and the relative change of the reference that stops.
GPA_ITERATIONS = 100
GPA_TOL = 1e-12


def procrustes_alignment(shapes: Sequence[SplineSurface], space: str
                         ) -> tuple[SplineSurface, list[SplineSurface],
                                    list[tuple[NDArray, NDArray]], NDArray]:
    """Generalized Procrustes analysis (module docstring): reference, aligned set, ``(s R, b)``
    maps and residuals ``||ref - aligned_i||_L2`` (mm)."""
    from segsnake.procrustes import procrustes_fit

    shapes = list(shapes)
    _check_same(shapes)
    t = _translation(shapes[0])
    ref = shapes[0].params.copy()
    c0, _ = _centre(shapes[0], ref)
    norm0 = np.sqrt(inner_product(shapes[0], c0, c0))
    transforms: list[tuple[NDArray, NDArray]] = []
    aligned_params: list[NDArray] = []
    for _ in range(GPA_ITERATIONS):
        transforms, aligned_params = [], []
        for s in shapes:
            sc, R, b = procrustes_fit(s, ref, s.params, space)  # ref ~ sc R sigma_i + b
            transforms.append((sc * R, b))
            aligned_params.append(sc * s.params @ R.T + t[:, None] * b[None, :])
        new = np.mean(aligned_params, axis=0)
        if space == "similarity":
            centred, g = _centre(shapes[0], new)
            norm = np.sqrt(inner_product(shapes[0], centred, centred))
            new = centred * (norm0 / max(norm, 1e-300)) + t[:, None] * g[None, :]
        change = l2_norm(shapes[0], new - ref)
        ref = new
        if change <= GPA_TOL * max(norm0, 1e-300):
            break
    reference = shapes[0].with_params(ref)
    aligned = [shapes[0].with_params(p) for p in aligned_params]
    residuals = np.array([l2_norm(reference, ref - p) for p in aligned_params])
    return reference, aligned, transforms, residuals


def build_shape_model(shapes: Sequence[SplineSurface], sources: Sequence[str] | None = None,
                      align: str = "affine") -> ShapeModel:
    """Reference, aligned set and functional PCA of snakes of one kind and size.

    Parameters
    ----------
    shapes : sequence of SplineSurface
    sources : sequence of str, optional
        File names, for the record.
    align : {"affine", "similarity", "rigid"}
        The unbiased affine alignment (Proposition 5), or generalized Procrustes.

    Raises
    ------
    ValueError
        Fewer than two shapes, shapes of different kinds or sizes, an unknown alignment.
    """
    shapes = list(shapes)
    if len(shapes) < 2:
        raise ValueError(f"a shape model needs at least two shapes, got {len(shapes)}")
    if align not in ALIGNMENTS:
        raise ValueError(f"unknown alignment {align!r}; expected one of {', '.join(ALIGNMENTS)}")
    _check_same(shapes)
    if align == "affine":
        reference, agreement = unbiased_reference(shapes)
        aligned, transforms, residuals = align_to_reference(shapes, reference)
    else:
        reference, aligned, transforms, residuals = procrustes_alignment(shapes, align)
        agreement = np.zeros(0)
    mean, modes, variances = functional_pca(aligned)
    return ShapeModel(reference, mean, modes, variances, aligned, transforms, residuals,
                      agreement, list(sources or []), align)


def load_shape_model(path: str | os.PathLike) -> ShapeModel:
    """Read a ``MODEL.json`` written by :meth:`ShapeModel.save`."""
    with open(path, encoding="utf-8") as fh:
        return ShapeModel.from_dict(json.load(fh))
