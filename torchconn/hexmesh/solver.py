"""Sparse symmetric positive definite solves: CHOLMOD through cholespy, SciPy's SuperLU otherwise.

Why CHOLMOD: the normal equations of the seamless map are SPD with the sparsity of a 3D
Laplacian times 3; a supernodal Cholesky with a fill-reducing ordering (CHOLMOD, through the
cholespy wheel: maintained, prebuilt for Linux/macOS/Windows, takes numpy or torch arrays,
raises ``ValueError`` on a matrix that is not positive definite instead of exiting) factors it
once, and the rounding loop reuses that factor for its multi-right-hand-side solves. SciPy's
SuperLU is the fallback when cholespy is not installed (``pip install cholespy``; it is in the
``hex`` extra). Timings of both on the same systems: docs/results/hexmesh.md
(``python -m benchmarks.hex_solver``).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["SPDFactor", "factorize", "available_backends", "NotPositiveDefinite"]


class NotPositiveDefinite(ValueError):
    """The matrix of a seamless-map system is singular or indefinite (an unknown the objective
    does not see, or a degenerate tet): raised with the backend's message."""


def available_backends() -> list[str]:
    """The backends that can run here, preferred first: ``"cholmod"`` (cholespy), ``"superlu"``."""
    out = []
    try:
        import cholespy  # noqa: F401

        out.append("cholmod")
    except ImportError:
        pass
    out.append("superlu")
    return out


class SPDFactor:
    """A factorization of a sparse SPD matrix ``A (n, n)`` that solves ``A x = b`` for
    ``b (n,)`` or ``(n, k)`` (float64).

    Args:
        A: scipy sparse matrix (both triangles stored).
        backend: ``"auto"`` (CHOLMOD when cholespy is installed), ``"cholmod"`` or ``"superlu"``.
    """

    def __init__(self, A, backend: str = "auto"):
        A = sp.csr_matrix(A, dtype=np.float64)
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"A must be square, got {A.shape}")
        if backend == "auto":
            backend = available_backends()[0]
        if backend not in ("cholmod", "superlu"):
            raise ValueError(f"backend must be 'auto', 'cholmod' or 'superlu', got {backend!r}")
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


def factorize(A, backend: str = "auto") -> SPDFactor:
    """:class:`SPDFactor` of ``A``."""
    return SPDFactor(A, backend)
