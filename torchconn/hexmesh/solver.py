"""Sparse symmetric positive definite solves: CHOLMOD through cholespy, SciPy's SuperLU otherwise.

Why CHOLMOD: the normal equations of the seamless map are SPD with the sparsity of a 3D
Laplacian times 3; a supernodal Cholesky with a fill-reducing ordering (CHOLMOD, through the
cholespy wheel: maintained, prebuilt for Linux/macOS/Windows, takes numpy or torch arrays,
raises ``ValueError`` on a matrix that is not positive definite instead of exiting) factors it
once, and the rounding loop reuses that factor for its multi-right-hand-side solves. SciPy's
SuperLU is the fallback when cholespy is not installed (``pip install cholespy``; it is in the
``hex`` extra).

``backend="pardiso"``: Intel MKL PARDISO through pypardiso (``pip install pypardiso``; not a
dependency, never chosen by ``"auto"``), a supernodal Cholesky with a nested-dissection ordering.
On the Newton systems of the foldover-free map of a 58k-tet mesh (n = 29,273, 1.25 M nonzeros,
2026-11-27, this project's 2-core AMD VM) it factors in 1.3 s where cholespy's CHOLMOD takes
11–13 s and SuperLU 198 s (docs/results/hexmesh.md).
"""
from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["SPDFactor", "factorize", "available_backends", "NotPositiveDefinite"]


class NotPositiveDefinite(ValueError):
    """The matrix of a seamless-map system is singular or indefinite (an unknown the objective
    does not see, or a degenerate tet): raised with the backend's message."""


def available_backends() -> list[str]:
    """The backends that can run here: ``"cholmod"`` (cholespy) first when installed (what ``"auto"``
    takes), then ``"superlu"``, and ``"pardiso"`` when pypardiso is installed.

    Installed means found by the import system; nothing is imported (importing pypardiso walks
    ``sys.prefix`` for MKL's library: 1.8 s here, once per process, in every job that only asked
    which backend ``"auto"`` is). A package found but broken raises its ``ImportError`` when
    its backend is used."""
    from importlib.util import find_spec

    out = ["cholmod"] if find_spec("cholespy") is not None else []
    out.append("superlu")
    if find_spec("pypardiso") is not None:
        out.append("pardiso")
    return out


class SPDFactor:
    """A factorization of a sparse SPD matrix ``A (n, n)`` that solves ``A x = b`` for
    ``b (n,)`` or ``(n, k)`` (float64).

    Args:
        A: scipy sparse matrix (both triangles stored).
        backend: ``"auto"`` (CHOLMOD when cholespy is installed, else SuperLU), ``"cholmod"``,
            ``"superlu"`` or ``"pardiso"`` (module docstring).
    """

    def __init__(self, A, backend: str = "auto"):
        A = sp.csr_matrix(A, dtype=np.float64)
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"A must be square, got {A.shape}")
        if backend == "auto":
            backend = available_backends()[0]
        if backend not in BACKENDS:
            raise ValueError(f"backend must be 'auto', 'cholmod', 'superlu' or 'pardiso', got {backend!r}")
        self.n = n
        self.backend = backend
        if n == 0:
            self._solve = lambda b: np.zeros_like(b)
            return
        if backend == "cholmod":
            try:
                import cholespy
            except ImportError as exc:
                raise ImportError("backend='cholmod' needs cholespy: pip install cholespy") from exc
            A.sort_indices()
            try:
                self._f = cholespy.CholeskySolverD(n, A.indptr.astype(np.int32), A.indices.astype(np.int32),
                                                   A.data.copy(), cholespy.MatrixType.CSR)
            except ValueError as exc:
                raise NotPositiveDefinite(f"CHOLMOD: {exc} (n = {n})") from exc

            def solve(b):
                b = np.ascontiguousarray(b, dtype=np.float64)
                x = np.zeros_like(b)
                if b.ndim == 2 and b.shape[1] == 0:
                    return x
                self._f.solve(b, x)
                return x

            self._solve = solve
        elif backend == "pardiso":
            self._solve = _pardiso_solver(A, n)
        else:
            try:
                lu = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A")
            except RuntimeError as exc:
                raise NotPositiveDefinite(f"SuperLU: {exc} (n = {n})") from exc
            d = lu.U.diagonal()
            if not np.all(np.isfinite(d)) or np.any(d == 0):
                raise NotPositiveDefinite(f"SuperLU: singular matrix (n = {n})")
            self._solve = lambda b: lu.solve(np.asarray(b, dtype=np.float64))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^{-1} b`` for ``b (n,)`` or ``(n, k)``."""
        b = np.asarray(b, dtype=np.float64)
        if b.shape[0] != self.n:
            raise ValueError(f"b must have {self.n} rows, got {b.shape}")
        return self._solve(b)


def _pardiso_solver(A, n: int):
    """Factor the SPD ``A`` with PARDISO (matrix type 2: real symmetric positive definite, the upper
    triangle given); the solve closure of :class:`SPDFactor`."""
    try:
        import pypardiso
    except ImportError as exc:
        raise ImportError("backend='pardiso' needs pypardiso: pip install pypardiso") from exc
    U = sp.triu(A, format="csr")
    U.sort_indices()
    ps = pypardiso.PyPardisoSolver(mtype=2)
    if not os.environ.get("PYPARDISO_MKL_RT"):
        # pypardiso looks for MKL's library by walking sys.prefix on every solver it makes (~0.4 s
        # each in this environment); its documented variable lets the next ones load it directly
        os.environ["PYPARDISO_MKL_RT"] = ps.libmkl._name
    ps.set_statistical_info_off()
    try:
        ps.factorize(U)
    except pypardiso.pardiso_wrapper.PyPardisoError as exc:
        raise NotPositiveDefinite(f"PARDISO: {exc} (n = {n})") from exc

    def solve(b):
        b = np.ascontiguousarray(b, dtype=np.float64)
        if b.ndim == 2 and b.shape[1] == 0:
            return np.zeros_like(b)
        return np.asarray(ps.solve(U, b), dtype=np.float64).reshape(b.shape)

    return solve


BACKENDS = ("cholmod", "superlu", "pardiso")
"""The backends :class:`SPDFactor` knows (``"auto"`` picks among the first two)."""


def factorize(A, backend: str = "auto") -> SPDFactor:
    """:class:`SPDFactor` of ``A``."""
    return SPDFactor(A, backend)
