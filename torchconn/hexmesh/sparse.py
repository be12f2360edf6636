"""Sparse symmetric positive definite solves as a differentiable torch operation.

``x = A^{-1} b`` for a sparse SPD matrix ``A (n, n)`` given by a pattern and its values, with
gradients with respect to the values and to ``b`` (implicit function theorem), exact to every
order: the backward pass is written in terms of the solve itself, as ``torch.linalg.solve``'s is.
The factorization is :class:`~.solver.SPDFactor` (CHOLMOD through cholespy, SciPy's SuperLU
otherwise), made once per matrix and reused by every solve of the forward and backward passes.

Conventions
-----------
* **The matrix.** ``indices (2, nnz)`` holds ``(rows, cols)`` of the stored entries and
  ``values (..., nnz)`` their values (a batch of matrices sharing one pattern). ``S`` is the
  matrix assembled from them (duplicate entries summed) and the op solves with its symmetric
  part ``A = (S + S^T) / 2``. The pattern must store **both triangles** (every ``(i, j)`` with
  its ``(j, i)``, as :class:`~.solver.SPDFactor` takes them); for values that are symmetric
  (``v_ij = v_ji``) ``A = S`` exactly. Solving with the symmetric part makes the op a smooth
  function of *any* values (``gradcheck`` perturbs one entry at a time) and makes its gradient
  symmetric, ``grad v_ij = grad v_ji``, so a gradient step keeps symmetric values symmetric.
* **Right-hand sides** as in ``torch.linalg.solve``: ``b`` is a batch of vectors ``(..., n)`` when
  ``b.ndim == 1`` or ``b.shape[:-1] == values.shape[:-1]`` (``b.shape == A.shape[:-1]``), otherwise
  a batch of ``k``-column matrices ``(..., n, k)``. Batch dimensions of ``values`` and ``b``
  broadcast; ``x`` has the broadcast batch shape. (So with one matrix, ``values (nnz,)``, a batch
  of vectors goes as the columns of ``b (n, k)``.)
* **Backward.** With ``x = A^{-1} b`` and the incoming gradient ``g_x``: ``g_b = A^{-1} g_x``
  (``A`` is symmetric) and ``g_A = -g_b x^T``; on the pattern, through the symmetric part,
  ``g_v[e] = -(g_b[r_e] . x[c_e] + g_b[c_e] . x[r_e]) / 2`` (the dot over the ``k`` columns).
  ``g_b`` is computed by this op (same factorization) and ``x`` is its saved output, so the
  backward is differentiable and double backward (``create_graph=True``, Hessians) is exact.
* **dtype and device.** ``values`` and ``b`` share a dtype, ``float32`` or ``float64``; the
  factorization and the solves run in float64 (float32 values convert exactly) and ``x`` is
  returned in the input dtype. CPU only: tensors on another device raise ``ValueError``
  (cholespy has a CUDA solver, but no CUDA path is implemented or tested here).
* **Errors.** A pattern that is not square (an index beyond ``n``), not symmetric, a
  non-positive diagonal entry, a matrix that CHOLMOD finds not positive definite raise
  (:class:`~.solver.NotPositiveDefinite`, a ``ValueError``), naming the entry or the batch item.
  With the SuperLU fallback (cholespy not installed) only the diagonal is checked: an
  indefinite matrix with a positive diagonal is then solved, not refused.

Why a ``torch.autograd.Function`` and not a ``torch.library.custom_op`` (as the hot ops of
:mod:`torchconn.ops` are): the factorization is state (a CHOLMOD factor, C memory behind a
Python object) that the forward makes and the backward and every later solve reuse; an op
schema carries tensors and scalars only, so a custom op would refactor ``A`` in every call,
forward and backward alike, or hide the factor in a cache keyed by tensor identity. The solve
is also not a kernel to fuse: its cost is CHOLMOD's. So it is an ``autograd.Function`` whose
state is an :class:`SPDSolve`, and ``torch.compile`` runs it outside the graph
(``torch.compiler.disable``: a graph break; ``fullgraph=True`` refuses it). With ``setup_context``,
``torch.func.grad`` and ``vjp`` work through a solve with a fixed factor (``SPDSolve(...)(b)``);
a factorization made inside a ``torch.func`` transform (of values it tracks) is not supported,
nor is ``vmap`` (batch dimensions of ``values`` and ``b`` are supported directly instead).
"""
from __future__ import annotations

import atexit
import gc
import weakref

import numpy as np
import scipy.sparse as sp
import torch

from .solver import NotPositiveDefinite, SPDFactor

__all__ = ["SPDSolve", "sparse_spd_solve"]

_DTYPES = (torch.float32, torch.float64)
_LIVE: "weakref.WeakSet[SPDSolve]" = weakref.WeakSet()


@atexit.register
def _release_factors() -> None:
    # An autograd graph alive at exit (``loss = energy(F); loss.backward()`` at module level)
    # holds its SPDSolve until after nanobind's leak check, which then prints "nanobind: leaked
    # ... cholespy.CholeskySolverD" on every such exit: drop the factors first.
    for solver in list(_LIVE):
        solver._factors = []
    gc.collect()


_COMPILE_REASON = ("the sparse SPD solve calls CHOLMOD / SuperLU on numpy arrays (a factorization is state the "
                   "graph cannot hold), so torch.compile runs it outside the graph")


def _check_tensor(t, name: str, who: str) -> torch.Tensor:
    if not torch.is_tensor(t):
        raise TypeError(f"{who}: {name} must be a torch.Tensor, got {type(t).__name__}")
    if t.device.type != "cpu":
        raise ValueError(f"{who}: {name} is on {t.device}; the sparse SPD solve runs on CPU only (CHOLMOD / "
                         f"SuperLU on host memory; no CUDA path is implemented): move it with .cpu()")
    return t


def _check_indices(indices, who: str) -> torch.Tensor:
    indices = _check_tensor(indices, "indices", who)
    if indices.dtype not in (torch.int64, torch.int32) or indices.dim() != 2 or indices.shape[0] != 2:
        raise ValueError(f"{who}: indices must be a (2, nnz) int64 tensor of (rows, cols), got "
                         f"{indices.dtype} of shape {tuple(indices.shape)}")
    if indices.numel() and int(indices.min()) < 0:
        e = int(torch.nonzero((indices < 0).any(0))[0])
        raise ValueError(f"{who}: indices has a negative entry (stored entry {e}: {indices[:, e].tolist()})")
    return indices.long()


def _check_values(values, nnz: int, who: str) -> torch.Tensor:
    values = _check_tensor(values, "values", who)
    if values.dtype not in _DTYPES:
        raise ValueError(f"{who}: values must be float32 or float64, got {values.dtype}")
    if values.dim() < 1 or values.shape[-1] != nnz:
        raise ValueError(f"{who}: values must have shape (..., nnz) = (..., {nnz}) for indices of {nnz} entries, "
                         f"got {tuple(values.shape)}")
    return values


class SPDSolve:
    """A factored sparse SPD matrix (module docstring for every convention), reusable.

    ``SPDSolve(indices, values)`` factors ``A`` once (once per batch item); ``solver(b)`` is
    :func:`sparse_spd_solve` with that factor: differentiable in ``b`` and, when ``values``
    requires grad, in ``values`` too (every backward solve reuses the factor). A caller with a
    fixed ``A`` builds one and calls it as often as it likes.

    Args:
        indices: ``(2, nnz)`` int64, ``(rows, cols)`` of the stored entries (both triangles).
        values: ``(..., nnz)`` float32 / float64 on CPU; kept as given (not copied), so its
            autograd graph, if any, is the one the solves differentiate.
        shape: ``n`` or ``(n, n)``; default ``1 + max(indices)``.
        backend: ``"auto"`` / ``"cholmod"`` / ``"superlu"`` (:class:`~.solver.SPDFactor`).

    Attributes:
        n: the order of ``A``; ``batch_shape``: ``values.shape[:-1]``; ``backend``: the one used.

    Raises:
        ValueError: bad shapes, dtypes or devices; a pattern not square or not symmetric;
            non-finite values. :class:`~.solver.NotPositiveDefinite` (a ``ValueError``): a
            diagonal entry that is not positive, or a matrix CHOLMOD cannot factor, naming the
            entry and the batch item.
    """

    def __init__(self, indices: torch.Tensor, values: torch.Tensor, shape=None, *, backend: str = "auto"):
        who = "SPDSolve"
        self.indices = _check_indices(indices, who)
        nnz = self.indices.shape[1]
        self.values = _check_values(values, nnz, who)
        self.n = _order(shape, self.indices, who)
        self.batch_shape = tuple(values.shape[:-1])
        v64 = values.detach().to(torch.float64).reshape(-1, nnz)
        if not torch.isfinite(v64).all():
            item, e = (int(i) for i in torch.nonzero(~torch.isfinite(v64))[0])
            raise ValueError(f"{who}: values has a non-finite entry (batch item {item}, stored entry {e})")
        self._values64 = v64
        rows, cols = self.indices.numpy()
        _check_symmetric_pattern(rows, cols, self.n, who)
        self._rows, self._cols = self.indices[0], self.indices[1]
        self._factors = []
        for item in range(v64.shape[0]):
            S = sp.csr_matrix((v64[item].numpy(), (rows, cols)), shape=(self.n, self.n))
            A = ((S + S.T) * 0.5).tocsr()
            d = A.diagonal()
            bad = np.nonzero(~(d > 0))[0]
            where = ""
            if self.batch_shape:
                where = f" (batch item {tuple(int(i) for i in np.unravel_index(item, self.batch_shape))})"
            if bad.size:
                i = int(bad[0])
                raise NotPositiveDefinite(f"{who}: A[{i}, {i}] = {d[i]:.6g} is not positive{where}, so A is not "
                                          f"positive definite ({bad.size} such diagonal entries)")
            try:
                self._factors.append(SPDFactor(A, backend))
            except NotPositiveDefinite as exc:
                raise NotPositiveDefinite(f"{who}: A is not positive definite{where}: {exc}") from exc
        self.backend = self._factors[0].backend if self._factors else backend
        _LIVE.add(self)

    def __call__(self, b: torch.Tensor) -> torch.Tensor:
        """``A^{-1} b`` for ``b (..., n)`` or ``(..., n, k)`` (module docstring), differentiable."""
        return sparse_spd_solve(self.indices, self.values, b, factor=self)

    def inv_quad(self, b: torch.Tensor) -> torch.Tensor:
        """``b^T A^{-1} b`` for vectors ``b (..., n)``: ``(...)`` (batch dims broadcast with ``values``').

        One solve for the value *and* the gradient ``2 A^{-1} b`` (the solve's output is the
        gradient, so no backward solve runs); the Hessian ``2 A^{-1}`` under ``create_graph`` is
        exact (the returned gradient is a differentiable function of ``b`` through the solve).
        When ``values`` requires grad this is ``(b * solver(b)).sum(-1)`` (exact, one backward
        solve more).
        """
        if not torch.is_tensor(b) or b.dim() == 0:
            raise ValueError(f"SPDSolve.inv_quad: b must be vectors (..., n), got "
                             f"{tuple(b.shape) if torch.is_tensor(b) else type(b).__name__}")
        x = self(b) if _is_vector(b, self.values) else self(b.unsqueeze(-1)).squeeze(-1)
        if self.values.requires_grad and torch.is_grad_enabled():
            return (b * x).sum(-1)
        return _InvQuad.apply(b, x)

    # ------------------------------------------------------------------ internals
    def _matches(self, indices: torch.Tensor, values: torch.Tensor) -> bool:
        if values is not self.values:
            if values.shape != self.values.shape:
                return False
            if not torch.equal(values.detach().to(torch.float64).reshape(-1, values.shape[-1]), self._values64):
                return False
        return indices is self.indices or torch.equal(indices.long(), self.indices)

    def _solve_tensor(self, b: torch.Tensor) -> torch.Tensor:
        """``A^{-1} b`` without autograd: ``b (..., n, k)`` -> ``(broadcast batch, n, k)`` in ``b.dtype``."""
        n, k = b.shape[-2], b.shape[-1]
        batch = torch.broadcast_shapes(self.batch_shape, tuple(b.shape[:-2]))
        b64 = b.detach().to(torch.float64)
        if len(self._factors) == 1:
            # one matrix: every right-hand side of the batch in one multi-column solve
            cols = b64.reshape(-1, n, k).permute(1, 0, 2).reshape(n, -1)
            x = torch.from_numpy(self._factors[0].solve(cols.numpy()))
            x = x.reshape(n, -1, k).permute(1, 0, 2).reshape(*b.shape[:-2], n, k)
            x = x.expand(*batch, n, k)
        else:
            bb = b64.expand(*batch, n, k).reshape(-1, n, k)
            item = torch.arange(len(self._factors)).reshape(self.batch_shape).expand(batch).reshape(-1)
            x = torch.empty_like(bb)
            for j in range(bb.shape[0]):  # one factor per batch item
                x[j] = torch.from_numpy(self._factors[int(item[j])].solve(bb[j].numpy()))
            x = x.reshape(*batch, n, k)
        return x.to(b.dtype).contiguous()


def _is_vector(b: torch.Tensor, values: torch.Tensor) -> bool:
    """``b`` is a batch of vectors (torch.linalg.solve's rule: ``b.shape == A.shape[:-1]``, or 1-d)."""
    return b.dim() == 1 or tuple(b.shape[:-1]) == tuple(values.shape[:-1])


def _order(shape, indices: torch.Tensor, who: str) -> int:
    top = int(indices.max()) + 1 if indices.numel() else 0
    if shape is None:
        return top
    if isinstance(shape, (int, np.integer)):
        shape = (int(shape), int(shape))
    shape = tuple(int(s) for s in shape)
    if len(shape) != 2 or shape[0] != shape[1]:
        raise ValueError(f"{who}: A must be square, got shape {shape}")
    n = shape[0]
    if top > n:
        r, c = (int(v) for v in indices.max(dim=1).values)
        raise ValueError(f"{who}: indices reach row {r}, column {c}, beyond A of shape ({n}, {n}): the matrix "
                         f"is not square of order {n}")
    return n


def _check_symmetric_pattern(rows: np.ndarray, cols: np.ndarray, n: int, who: str) -> None:
    """Raise unless every stored ``(i, j)`` has its mirror ``(j, i)`` stored (naming the first
    missing one in row-major order): the pattern ``P`` (duplicates merged) against ``P^T``, one
    sparse difference (not a sort of the keys: 0.33 s -> 0.008 s for the gear's map-energy matrix,
    297,360 stored entries, 2026-11-27)."""
    P = sp.csr_matrix((np.ones(rows.size, np.int32), (rows, cols)), shape=(n, n))
    P.data[:] = 1
    D = (P - P.T).tocoo()
    missing = D.data > 0
    if missing.any():
        k = int((D.row[missing].astype(np.int64) * n + D.col[missing]).min())
        raise ValueError(f"{who}: the pattern is not symmetric: entry ({k // n}, {k % n}) is stored but "
                         f"({k % n}, {k // n}) is not ({int(missing.sum())} such entries); store both triangles")


class _SparseSPDSolve(torch.autograd.Function):
    """``x = A(values)^{-1} b`` with the factor of ``solver``; ``b (..., n, k)`` (module docstring)."""

    @staticmethod
    def forward(values, b, solver):
        return solver._solve_tensor(b)

    @staticmethod
    def setup_context(ctx, inputs, output):
        values, b, solver = inputs
        ctx.solver = solver
        ctx.b_shape = b.shape
        ctx.save_for_backward(values, output)
        ctx.set_materialize_grads(False)  # no gradient reaching x (inv_quad's): no backward solve

    @staticmethod
    def backward(ctx, gx):
        if gx is None:
            return None, None, None
        values, x = ctx.saved_tensors
        solver = ctx.solver
        # g_b = A^{-1} g_x by the op itself: differentiable (in values and g_x) under create_graph
        gb = _SparseSPDSolve.apply(values, gx, solver)
        g_values = g_b = None
        if ctx.needs_input_grad[0]:
            r, c = solver._rows, solver._cols
            gv = (gb[..., r, :] * x[..., c, :]).sum(-1) + (gb[..., c, :] * x[..., r, :]).sum(-1)
            g_values = (-0.5 * gv).sum_to_size(values.shape)
        if ctx.needs_input_grad[1]:
            g_b = gb.sum_to_size(ctx.b_shape)
        return g_values, g_b, None


class _InvQuad(torch.autograd.Function):
    """``(b * x).sum(-1)`` for ``x = A^{-1} b``: the gradient ``2 x`` goes to ``b`` only (so the
    solve's backward never runs), and stays differentiable through ``x`` for double backward."""

    @staticmethod
    def forward(b, x):
        return (b * x).sum(-1)

    @staticmethod
    def setup_context(ctx, inputs, output):
        b, x = inputs
        ctx.b_shape = b.shape
        ctx.save_for_backward(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return (2.0 * g[..., None] * x).sum_to_size(ctx.b_shape), None


@torch.compiler.disable(reason=_COMPILE_REASON)
def sparse_spd_solve(indices: torch.Tensor, values: torch.Tensor, b: torch.Tensor, *, factor: SPDSolve | None = None,
                     backend: str = "auto") -> torch.Tensor:
    """``x = A^{-1} b`` for the sparse SPD matrix ``A`` of ``(indices, values)``, differentiable.

    Args:
        indices: ``(2, nnz)`` int64 ``(rows, cols)``, both triangles stored (module docstring).
        values: ``(..., nnz)`` float32 / float64: a batch of matrices on one pattern; the op
            solves with the symmetric part of each.
        b: ``(..., n)`` (when ``b.ndim == 1`` or ``b.shape[:-1] == values.shape[:-1]``) or
            ``(..., n, k)``, same dtype; ``n`` is the order of ``A``. Batch dimensions broadcast with
            those of ``values``.
        factor: an :class:`SPDSolve` of the same ``indices`` and ``values`` (its factorization
            is reused instead of factoring again; checked to match).
        backend: of a new factorization (:class:`~.solver.SPDFactor`).

    Returns:
        ``x`` with ``b``'s layout, the broadcast batch shape and the input dtype; gradients
        with respect to ``values`` and ``b`` (module docstring), double backward exact.

    Raises:
        ValueError: shapes, dtypes, device (CPU only), a pattern not square or not symmetric, a
            ``factor`` of another matrix. :class:`~.solver.NotPositiveDefinite`: ``A`` is not
            positive definite (a non-positive diagonal entry; CHOLMOD's failure).
    """
    who = "sparse_spd_solve"
    if not (isinstance(factor, SPDSolve) and indices is factor.indices):  # (a factor's own indices are checked)
        indices = _check_indices(indices, who)
    values = _check_values(values, indices.shape[1], who)
    b = _check_tensor(b, "b", who)
    if b.dtype != values.dtype:
        raise ValueError(f"{who}: b ({b.dtype}) and values ({values.dtype}) must have the same dtype")
    if b.dim() == 0:
        raise ValueError(f"{who}: b must be (..., n) or (..., n, k), got a 0-dim tensor")
    vector = _is_vector(b, values)
    bm = b.unsqueeze(-1) if vector else b
    n = bm.shape[-2]
    if factor is None:
        factor = SPDSolve(indices, values, (n, n), backend=backend)
    else:
        if not isinstance(factor, SPDSolve):
            raise TypeError(f"{who}: factor must be an SPDSolve, got {type(factor).__name__}")
        if not factor._matches(indices, values):
            raise ValueError(f"{who}: factor was made from other indices or values than the ones given")
    if factor.n != n:
        what = "(..., n) with n" if vector else "(..., n, k) with n"
        raise ValueError(f"{who}: b has shape {tuple(b.shape)}, read as {what} = {n}, but A is "
                         f"{factor.n} x {factor.n}")
    try:
        torch.broadcast_shapes(tuple(values.shape[:-1]), tuple(bm.shape[:-2]))
    except RuntimeError:
        raise ValueError(f"{who}: the batch shapes of values {tuple(values.shape[:-1])} and b "
                         f"{tuple(bm.shape[:-2])} do not broadcast") from None
    x = _SparseSPDSolve.apply(values, bm, factor)
    return x.squeeze(-1) if vector else x
