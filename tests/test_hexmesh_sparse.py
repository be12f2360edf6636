"""The differentiable sparse SPD solve (torchconn.hexmesh.sparse) on small random SPD systems.

* values against ``torch.linalg.solve`` on the dense matrix: vectors, ``(n, k)`` and batched
  right-hand sides, batched matrices, broadcasting, float32 and float64, both backends;
* ``gradcheck`` / ``gradgradcheck`` in float64 (values and b), and the gradients and Hessian-vector
  products equal those of ``torch.linalg.solve`` through the dense symmetric part (the obviously
  correct reference); the gradient is symmetric on the pattern;
* one factorization per matrix across forward, backward and double backward; ``inv_quad``: one
  solve for value and gradient;
* errors: not square, pattern not symmetric, not positive definite, dtypes, devices, a factor of
  another matrix — a clear error, never a crash.

Cost: about 2 s (matrices of order <= 12).
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchconn.hexmesh import solver as solver_mod
from torchconn.hexmesh.solver import NotPositiveDefinite, available_backends
from torchconn.hexmesh.sparse import SPDSolve, sparse_spd_solve

BACKENDS = available_backends()


def random_spd(n: int, seed: int, density: float = 0.35, dtype=torch.float64):
    """A random sparse SPD matrix: its dense form, pattern (both triangles, diagonal included) and values."""
    g = torch.Generator().manual_seed(seed)
    M = torch.randn(n, n, generator=g, dtype=torch.float64) * (torch.rand(n, n, generator=g) < density)
    A = M @ M.T + 0.5 * n * torch.eye(n, dtype=torch.float64)
    idx = torch.nonzero(A != 0).T.contiguous()
    return A.to(dtype), idx, A[idx[0], idx[1]].to(dtype)


def dense_sym(idx, values, n):
    """The reference: the dense symmetric part of the assembled matrix, differentiable in ``values``."""
    if values.dim() > 1:
        return torch.stack([dense_sym(idx, v, n) for v in values])
    S = torch.zeros(n, n, dtype=values.dtype).index_put((idx[0], idx[1]), values, accumulate=True)
    return 0.5 * (S + S.T)

# ----------------------------------------------------------------------------- values
@pytest.mark.parametrize("backend", BACKENDS)
def test_solve_matches_dense_vectors_matrices_and_batches(backend):
    A, idx, v = random_spd(9, 0)
    g = torch.Generator().manual_seed(1)
    for b in (torch.randn(9, generator=g, dtype=torch.float64),
              torch.randn(9, 4, generator=g, dtype=torch.float64),
              torch.randn(2, 3, 9, 2, generator=g, dtype=torch.float64)):
        x = sparse_spd_solve(idx, v, b, backend=backend)
        assert x.shape == b.shape and x.dtype == torch.float64
        torch.testing.assert_close(x, torch.linalg.solve(A, b), rtol=1e-12, atol=1e-12)
    # a batch of matrices on one pattern, broadcast against vectors and matrices
    vb = torch.stack([v, 2.0 * v, v + 0.5 * (idx[0] == idx[1])])
    Ab = torch.stack([A, 2.0 * A, A + 0.5 * torch.eye(9, dtype=torch.float64)])
    for b in (torch.randn(9, generator=g, dtype=torch.float64),          # (n,): broadcast vector
              torch.randn(3, 9, generator=g, dtype=torch.float64),       # (B, n): b.ndim == values.ndim
              torch.randn(9, 2, generator=g, dtype=torch.float64),       # (n, k) for every matrix
              torch.randn(4, 1, 9, 2, generator=g, dtype=torch.float64)):  # batch dims broadcast
        x = sparse_spd_solve(idx, vb, b, backend=backend)
        ref = torch.linalg.solve(Ab, b) if b.dim() != 1 else torch.linalg.solve(Ab, b.expand(3, 9))
        torch.testing.assert_close(x, ref, rtol=1e-12, atol=1e-12)


def test_float32_solves_in_float64_and_returns_float32():
    A, idx, v = random_spd(10, 2)
    b = torch.randn(10, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x32 = sparse_spd_solve(idx, v.float(), b.float())
    assert x32.dtype == torch.float32
    # the only error is float32 rounding of the inputs and the output, not of the factorization
    ref = torch.linalg.solve(dense_sym(idx, v.float().double(), 10), b.float().double())
    torch.testing.assert_close(x32.double(), ref, rtol=2 * torch.finfo(torch.float32).eps, atol=1e-7)
    vv = v.float().requires_grad_()
    bb = b.float().requires_grad_()
    sparse_spd_solve(idx, vv, bb).square().sum().backward()
    assert vv.grad.dtype == torch.float32 and bb.grad.dtype == torch.float32


def test_values_that_are_not_symmetric_solve_with_the_symmetric_part():
    A, idx, v = random_spd(7, 4)
    noise = 0.3 * torch.randn(v.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    b = torch.randn(7, dtype=torch.float64)
    x = sparse_spd_solve(idx, v + noise, b)
    torch.testing.assert_close(x, torch.linalg.solve(dense_sym(idx, v + noise, 7), b), rtol=1e-12, atol=1e-12)
    # duplicate entries are summed
    idx2 = torch.cat([idx, idx], 1)
    torch.testing.assert_close(sparse_spd_solve(idx2, torch.cat([0.25 * v, 0.75 * v]), b), torch.linalg.solve(A, b))


# ----------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("rhs", ["vector", "matrix", "batched"])
def test_gradcheck_and_gradgradcheck(rhs):
    _, idx, v = random_spd(6, 6)
    g = torch.Generator().manual_seed(7)
    shape = {"vector": (6,), "matrix": (6, 2), "batched": (2, 6, 2)}[rhs]
    b = torch.randn(shape, generator=g, dtype=torch.float64).requires_grad_()
    vv = v.clone().requires_grad_()
    f = lambda values, rhs_: sparse_spd_solve(idx, values, rhs_)  # noqa: E731
    assert torch.autograd.gradcheck(f, (vv, b))
    assert torch.autograd.gradgradcheck(f, (vv, b))


def test_gradcheck_batched_matrices():
    _, idx, v = random_spd(5, 8)
    vb = torch.stack([v, 1.5 * v]).requires_grad_()
    b = torch.randn(5, dtype=torch.float64, requires_grad=True)  # broadcast to both matrices
    f = lambda values, rhs: sparse_spd_solve(idx, values, rhs)  # noqa: E731
    assert torch.autograd.gradcheck(f, (vb, b))
    assert torch.autograd.gradgradcheck(f, (vb, b))


def test_gradients_and_hvp_equal_dense_solve_and_are_symmetric():
    n = 8
    _, idx, v = random_spd(n, 9)
    g = torch.Generator().manual_seed(10)
    b = torch.randn(n, 3, generator=g, dtype=torch.float64)
    w = torch.randn(n, 3, generator=g, dtype=torch.float64)  # a fixed test functional
    dv = torch.randn(v.shape, generator=g, dtype=torch.float64)
    db = torch.randn(b.shape, generator=g, dtype=torch.float64)

    def loss(solve, values, rhs):
        x = solve(values, rhs)
        return (w * x).sum() + 0.5 * x.square().sum()

    ours = lambda values, rhs: sparse_spd_solve(idx, values, rhs)  # noqa: E731
    dense = lambda values, rhs: torch.linalg.solve(dense_sym(idx, values, n), rhs)  # noqa: E731
    out = {}
    for name, solve in (("ours", ours), ("dense", dense)):
        vv, bb = v.clone().requires_grad_(), b.clone().requires_grad_()
        gv, gb = torch.autograd.grad(loss(solve, vv, bb), (vv, bb), create_graph=True)
        hv = torch.autograd.grad((gv * dv).sum() + (gb * db).sum(), (vv, bb))  # Hessian-vector product
        out[name] = (gv.detach(), gb.detach(), *hv)
    for a, r in zip(out["ours"], out["dense"]):
        torch.testing.assert_close(a, r, rtol=1e-10, atol=1e-12)
    # symmetric gradient on the pattern: entry (i, j) and its mirror (j, i) get the same gradient
    key = {(int(i), int(j)): e for e, (i, j) in enumerate(idx.T.tolist())}
    mirror = torch.tensor([key[(j, i)] for i, j in idx.T.tolist()])
    torch.testing.assert_close(out["ours"][0], out["ours"][0][mirror], rtol=0, atol=0)


def test_one_factorization_for_forward_backward_and_double_backward(monkeypatch):
    made = []
    real = solver_mod.SPDFactor.__init__

    def counting(self, *args, **kwargs):
        made.append(1)
        real(self, *args, **kwargs)

    monkeypatch.setattr(solver_mod.SPDFactor, "__init__", counting)
    _, idx, v = random_spd(7, 11)
    vv = v.clone().requires_grad_()
    b = torch.randn(7, dtype=torch.float64, requires_grad=True)
    x = sparse_spd_solve(idx, vv, b)
    gv, gb = torch.autograd.grad(x.square().sum(), (vv, b), create_graph=True)
    torch.autograd.grad(gv.sum() + gb.sum(), (vv, b))
    assert len(made) == 1
    # a reusable factor: built once, then called (and differentiated) without refactoring
    s = SPDSolve(idx, vv)
    for _ in range(3):
        torch.autograd.grad(s(b).sum(), (vv, b))
    assert len(made) == 2


def test_inv_quad_one_solve_exact_gradient_and_hessian():
    n = 9
    A, idx, v = random_spd(n, 12)
    s = SPDSolve(idx, v)
    solves = []
    fac = s._factors[0]
    real_solve = fac.solve
    fac.solve = lambda b: (solves.append(1), real_solve(b))[1]
    b = torch.randn(2, n, dtype=torch.float64, generator=torch.Generator().manual_seed(13), requires_grad=True)
    q = s.inv_quad(b)
    q.sum().backward()
    assert len(solves) == 1  # the value and the gradient from one solve
    torch.testing.assert_close(q.detach(), torch.einsum("bi,ij,bj->b", b.detach(), torch.linalg.inv(A), b.detach()))
    torch.testing.assert_close(b.grad, 2 * torch.linalg.solve(A, b.detach().T).T)
    assert torch.autograd.gradgradcheck(s.inv_quad, (b.detach().clone().requires_grad_(),))
    # with values requiring grad: exact in values too (d/dA b^T A^-1 b = -x x^T, symmetrized)
    vv = v.clone().requires_grad_()
    bb = b.detach()[0].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda values, rhs: SPDSolve(idx, values).inv_quad(rhs), (vv, bb))


# ----------------------------------------------------------------------------- errors
def test_errors_are_clear():
    A, idx, v = random_spd(5, 14)
    b = torch.ones(5, dtype=torch.float64)
    with pytest.raises(ValueError, match="must be square"):
        SPDSolve(idx, v, shape=(5, 6))
    with pytest.raises(ValueError, match="beyond A of shape"):
        sparse_spd_solve(idx, v, torch.ones(4, dtype=torch.float64))  # b's 4 rows: A would be 4 x 4
    with pytest.raises(ValueError, match="pattern is not symmetric"):
        lower = idx[0] >= idx[1]
        sparse_spd_solve(idx[:, lower], v[lower], b)
    # the first entry without its mirror (row-major) and their number, against a per-entry reference
    full = torch.cartesian_prod(torch.arange(5), torch.arange(5)).T.contiguous()  # every entry of A
    idx, v = full, A[full[0], full[1]]
    keep = ~((idx[0] == 3) & (idx[1] == 1)) & ~((idx[0] == 4) & (idx[1] == 0))
    rows, cols = idx[:, keep].tolist()
    stored = set(zip(rows, cols))
    lonely = sorted((i, j) for i, j in stored if (j, i) not in stored)
    assert lonely == [(0, 4), (1, 3)]
    with pytest.raises(ValueError, match=r"entry \(0, 4\) is stored but \(4, 0\) is not \(2 such entries\)"):
        sparse_spd_solve(idx[:, keep], v[keep], b)
    with pytest.raises(ValueError, match="same dtype"):
        sparse_spd_solve(idx, v.float(), b)
    with pytest.raises(ValueError, match="float32 or float64"):
        sparse_spd_solve(idx, v.to(torch.int64), b.to(torch.int64))
    with pytest.raises(ValueError, match=r"\(2, nnz\)"):
        sparse_spd_solve(idx.T, v, b)
    with pytest.raises(ValueError, match="shape \\(\\.\\.\\., nnz\\)"):
        sparse_spd_solve(idx, v[:-1], b)
    with pytest.raises(ValueError, match="CPU only"):
        sparse_spd_solve(idx, v.to("meta"), b.to("meta"))
    with pytest.raises(ValueError, match="non-finite"):
        sparse_spd_solve(idx, torch.where(idx[0] == 2, torch.nan, v), b)
    with pytest.raises(ValueError, match="do not broadcast"):
        sparse_spd_solve(idx, torch.stack([v, v]), torch.ones(3, 5, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="other indices or values"):
        sparse_spd_solve(idx, 2 * v, b, factor=SPDSolve(idx, v))
    with pytest.raises(ValueError, match="negative"):
        SPDSolve(idx - 1, v)
    # not positive definite: a non-positive (or missing) diagonal entry, with the batch item
    diag = idx[0] == idx[1]
    with pytest.raises(NotPositiveDefinite, match=r"A\[\d+, \d+\] = -1 is not positive"):
        sparse_spd_solve(idx, torch.where(diag, -1.0, v), b)
    with pytest.raises(NotPositiveDefinite, match=r"batch item \(1,\)"):
        sparse_spd_solve(idx, torch.stack([v, torch.where(diag, 0.0, v)]), b)
    with pytest.raises(NotPositiveDefinite, match="not positive"):
        keep = ~(diag & (idx[0] == 3))
        sparse_spd_solve(idx[:, keep], v[keep], b)


@pytest.mark.skipif("cholmod" not in BACKENDS, reason="an indefinite matrix with a positive diagonal is refused by "
                    "CHOLMOD only (cholespy not installed; SuperLU solves it)")
def test_indefinite_matrix_with_positive_diagonal_is_refused():
    # [[1, 2], [2, 1]] has eigenvalues 3 and -1
    idx = torch.tensor([[0, 0, 1, 1], [0, 1, 0, 1]])
    val = torch.tensor([1.0, 2.0, 2.0, 1.0], dtype=torch.float64)
    with pytest.raises(NotPositiveDefinite, match="not positive definite"):
        sparse_spd_solve(idx, val, torch.ones(2, dtype=torch.float64), backend="cholmod")


@pytest.mark.skipif("pardiso" not in BACKENDS, reason="pypardiso is not installed (an optional backend)")
def test_pardiso_refuses_an_indefinite_matrix_and_matches_cholmod_on_a_laplacian():
    SPDFactor = solver_mod.SPDFactor
    # [[1, 2], [2, 1]] has eigenvalues 3 and -1: PARDISO's SPD factorization finds a bad pivot
    idx = torch.tensor([[0, 0, 1, 1], [0, 1, 0, 1]])
    val = torch.tensor([1.0, 2.0, 2.0, 1.0], dtype=torch.float64)
    with pytest.raises(NotPositiveDefinite, match="PARDISO"):
        sparse_spd_solve(idx, val, torch.ones(2, dtype=torch.float64), backend="pardiso")
    # a shifted 1D Laplacian: the same solution as the default backend, one and several right-hand sides
    n = 40
    A = sp.diags([-np.ones(n - 1), 2.01 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    b = np.random.default_rng(0).standard_normal((n, 3))
    x, ref = SPDFactor(A, "pardiso").solve(b), SPDFactor(A, BACKENDS[0]).solve(b)
    assert x.shape == (n, 3) and np.allclose(x, ref, rtol=1e-10, atol=1e-12)
    assert np.allclose(SPDFactor(A, "pardiso").solve(b[:, 0]), ref[:, 0], rtol=1e-10, atol=1e-12)


def test_asking_which_backends_imports_none():
    """``available_backends`` (what ``"auto"`` asks) finds the packages without importing them: a
    fresh process that asks has neither cholespy nor pypardiso in ``sys.modules`` afterwards, and
    lists exactly the ones installed."""
    import importlib.util
    import subprocess
    import sys

    import ast

    code = ("import sys; from torchconn.hexmesh.solver import available_backends as a; b = a(); "
            "print(repr((b, 'cholespy' in sys.modules, 'pypardiso' in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    want = (["cholmod"] if importlib.util.find_spec("cholespy") else []) + ["superlu"] + \
        (["pardiso"] if importlib.util.find_spec("pypardiso") else [])
    assert ast.literal_eval(out.stdout.strip().splitlines()[-1]) == (want, False, False)
