"""The foldover-free seamless map: a per-tet barrier energy minimized by PSD-projected Newton.

The least-squares seamless map (:mod:`.seamless`) has no notion of injectivity: where the frames
do not integrate it folds. This module minimizes, over the free unknowns ``y`` of the eliminated
constraints (``u = Z y + z0``, :mod:`.elimination`),

.. code-block:: text

    E(y) = sum_t vol_t [ w_fit |J_t - I|^2 + w_sd ( |J_t|^2 + |adj J_t|^2 / (det J_t + eps_t)^2 - 6 ) ]

with ``J_t = grad u_t (h F_t)`` the tet's Jacobian relative to its (combed) frame and the hex edge
length (``I`` for a map that follows the frames; ``det J_t > 0`` exactly when the tet keeps its
orientation): the frame-fitting term of :mod:`.seamless` plus the symmetric Dirichlet energy
(``|J|^2 + |J^-1|^2``, 6 at a rotation), whose ``|J^-1|^2 = |adj J|^2 / det^2`` is a barrier at
``det J = 0``. Tets that start inverted get a shift ``eps_t = 1/penalty - det J_t > 0`` (AlgoHex's
shifted barrier, Liu & Bommes 2023; the untangler of Garanzha et al. 2021 is of the same family)
so that every tet starts feasible, ``det J_t + eps_t > 0``; a tet whose determinant is positive has
``eps_t = 0`` and can never fold again. Rounds: minimize; set ``eps_t = 0`` on the tets that
became positive and a new shift ``1/penalty - det J_t`` on those that did not; repeat.

Each Newton step: the per-tet gradients and ``9 x 9`` Hessians in ``J`` (batched in torch:
``torch.func.vmap`` of ``torch.func.hessian``), each Hessian projected onto the positive
semidefinite cone (eigenvalues clamped at 0, only where a Cholesky attempt fails), assembled in
the eliminated space, ``H = (G Z)^T blockdiag(H_t) (G Z)``, and one sparse Cholesky solve
(:mod:`.solver`). The line search never crosses ``det J_t + eps_t = 0``: the step is capped at
0.9 times the first positive root of the cubic ``det(J_t + s dJ_t) + eps_t`` over all tets
(:func:`first_root`), then backtracked (Armijo).

Unknowns may be held fixed (``fixed``): the quantization moves integer unknowns to their rounded
values along a straight path while the others follow (:func:`move_fixed`), with the same barrier.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from .solver import NotPositiveDefinite, factorize

__all__ = ["TetJacobians", "InjectiveResult", "first_root", "barrier_terms", "minimize_barrier", "move_fixed",
           "PENALTY_START", "PENALTY_ROUND", "DET_SAFE"]

PENALTY_START = 1e3
"""The first shift of an inverted tet: ``eps = 1/PENALTY_START - det J`` (so ``det + eps = 1e-3``)."""
PENALTY_ROUND = 1e2
"""The shift of a tet still inverted after a round: ``eps = 1/PENALTY_ROUND - det J``."""
DET_SAFE = 1e-6
"""A tet is held by the plain barrier (``eps = 0``) once ``det J > DET_SAFE`` (``J`` is normalized:
1 at the target size); below, it keeps a shift, so that a nearly flat tet does not make the
barrier's Hessian overflow the solve."""
_STEP_FRACTION = 0.9  # of the first root of det(J + s dJ) + eps = 0


# ----------------------------------------------------------------------------- the Jacobians
@dataclass
class TetJacobians:
    """The affine map from the free unknowns to the per-tet Jacobians, ``J = (GZ y + j0)`` as ``(T, 3, 3)``.

    Attributes:
        GZ: ``(9T, m)`` CSR: row ``9t + 3i + k`` is entry ``(i, k)`` of ``J_t`` (parameter component
            ``i``, frame axis ``k``), over the ``m`` free unknowns.
        j0: ``(9T,)`` the constant part.
        vol: ``(T,)`` tet volumes (the weights).
    """

    GZ: sp.csr_matrix
    j0: np.ndarray
    vol: np.ndarray

    @classmethod
    def of_problem(cls, prob, weights: np.ndarray | None = None) -> "TetJacobians":
        """The Jacobians ``J_t = grad u_t (h F_t)`` of a :class:`~.seamless.SeamlessProblem`
        (``weights (T,)`` multiply the volumes)."""
        rows = prob.corner_var.reshape(-1)
        GZ = (prob.G @ prob.elim.Z[rows]).tocsr()
        j0 = prob.G @ prob.elim.z0[rows]
        vol = prob.vol if weights is None else prob.vol * weights
        return cls(GZ=GZ, j0=np.asarray(j0, np.float64), vol=np.asarray(vol, np.float64))

    @property
    def n_tets(self) -> int:
        return self.vol.size

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """``(T, 3, 3)`` Jacobians at ``y (m,)``."""
        return (self.GZ @ y + self.j0).reshape(-1, 3, 3)

    def step(self, d: np.ndarray) -> np.ndarray:
        """``(T, 3, 3)`` change of the Jacobians along ``d (m,)`` (no constant part)."""
        return (self.GZ @ d).reshape(-1, 3, 3)


# ----------------------------------------------------------------------------- per-tet terms
def _adj(J: torch.Tensor) -> torch.Tensor:
    """Adjugate of ``(..., 3, 3)`` (``adj J = det J * J^-1``), written entry by entry."""
    c0 = torch.cross(J[..., 1, :], J[..., 2, :], dim=-1)
    c1 = torch.cross(J[..., 2, :], J[..., 0, :], dim=-1)
    c2 = torch.cross(J[..., 0, :], J[..., 1, :], dim=-1)
    return torch.stack([c0, c1, c2], dim=-1)


def _sd(j: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """Symmetric Dirichlet ``|J|^2 + |adj J|^2 / (det J + eps)^2 - 6`` per row of ``j (T, 9)``."""
    J = j.reshape(-1, 3, 3)
    A = _adj(J)
    det = (J[:, 0, :] * A[:, :, 0]).sum(-1)
    return j.square().sum(-1) + A.square().sum((-2, -1)) / (det + eps).square() - 6.0


def barrier_terms(J: torch.Tensor, eps: torch.Tensor, w_fit: float, w_sd: float, *, hessian: bool = True):
    """Per-tet energy, gradient and (PSD-projected) Hessian in the Jacobian's 9 entries.

    Args:
        J: ``(T, 3, 3)`` Jacobians (float64); eps: ``(T,)`` shifts (``det J + eps > 0``).
        w_fit, w_sd: weights of the fitting and the symmetric Dirichlet terms (module docstring).
        hessian: also return the Hessians.

    Returns:
        ``(f (T,), g (T, 9), H (T, 9, 9) or None)``: the energy per unit volume, its gradient and
        its Hessian (row-major entry order ``3 i + k``): the fitting term's ``2 w_fit I`` plus the
        symmetric Dirichlet term's Hessian projected onto the PSD cone (eigenvalues clamped at 0
        where a Cholesky attempt fails), so ``H >= 2 w_fit I``.
    """
    j = J.reshape(-1, 9)
    eye = torch.eye(3, dtype=J.dtype, device=J.device).reshape(9)
    r = j - eye
    f = w_fit * r.square().sum(1)
    g = 2.0 * w_fit * r
    Hs = None
    if w_sd:
        # per-row derivatives by batched autograd (rows are independent): one backward for the
        # gradient, nine more for the Hessian's columns
        with torch.enable_grad():
            jj = j.detach().requires_grad_(True)
            fs = _sd(jj, eps)
            (gs,) = torch.autograd.grad(fs.sum(), jj, create_graph=hessian)
            if hessian:
                Hs = torch.stack([torch.autograd.grad(gs[:, k].sum(), jj, retain_graph=k < 8)[0] for k in range(9)], 1)
        f = f + w_sd * fs.detach()
        g = g + w_sd * gs.detach()
    if not hessian:
        return f, g, None
    H = 2.0 * w_fit * torch.eye(9, dtype=J.dtype, device=J.device).expand(j.shape[0], 9, 9)
    if w_sd:
        Hs = 0.5 * (Hs + Hs.transpose(1, 2))
        _, info = torch.linalg.cholesky_ex(Hs)
        bad = torch.nonzero(info != 0).flatten()
        if bad.numel():
            # each block eigen-decomposed at O(1) scale: its own round-off, not the largest block's
            Hb = Hs[bad]
            sc = Hb.abs().amax(dim=(1, 2), keepdim=True).clamp_min(torch.finfo(J.dtype).tiny)
            w, V = torch.linalg.eigh(Hb / sc)
            Hs[bad] = ((V * w.clamp_min(0.0)[:, None, :]) @ V.transpose(1, 2)) * sc
        H = H + w_sd * Hs
    return f, g, H


def _energy(jac: TetJacobians, y: np.ndarray, eps: np.ndarray, w_fit: float, w_sd: float) -> float:
    """``E(y)`` (``inf`` where a tet is not feasible)."""
    J = jac(y)
    det = np.linalg.det(J)
    if not np.all(det + eps > 0):
        return math.inf
    Jt = torch.from_numpy(J)
    f, _, _ = barrier_terms(Jt, torch.from_numpy(eps), w_fit, w_sd, hessian=False)
    return float((jac.vol * f.numpy()).sum())


# ----------------------------------------------------------------------------- line search bound
def _det_cubic(J: np.ndarray, dJ: np.ndarray):
    """Coefficients of ``det(J + s dJ) = a + b s + c s^2 + d s^3`` per tet."""
    def adj(M):
        return np.stack([np.cross(M[:, 1], M[:, 2]), np.cross(M[:, 2], M[:, 0]), np.cross(M[:, 0], M[:, 1])], -1)

    a = np.linalg.det(J)
    b = np.einsum("tij,tji->t", adj(J), dJ)
    c = np.einsum("tij,tji->t", adj(dJ), J)
    d = np.linalg.det(dJ)
    return a, b, c, d


def first_root(a, b, c, d, s_max: float = 1.0) -> np.ndarray:
    """The first root in ``(0, s_max]`` of each cubic ``p(s) = a + b s + c s^2 + d s^3`` with
    ``p(0) = a > 0`` (``inf`` where there is none).

    The interval is cut at the real roots of ``p'`` into monotone pieces; the first piece whose
    right end has ``p <= 0`` holds the first root, found by bisection (vectorized; 80 halvings).
    """
    a, b, c, d = (np.asarray(x, np.float64) for x in (a, b, c, d))
    n = a.size
    # critical points: 3 d s^2 + 2 c s + b = 0
    A2, B2, C2 = 3 * d, 2 * c, b
    crit = np.full((n, 2), np.inf)
    lin = np.abs(A2) <= 1e-300
    with np.errstate(divide="ignore", invalid="ignore"):
        s_lin = np.where(lin & (np.abs(B2) > 0), -C2 / np.where(B2 == 0, 1.0, B2), np.inf)
        disc = B2 * B2 - 4 * A2 * C2
        sq = np.sqrt(np.maximum(disc, 0.0))
        q = -0.5 * (B2 + np.copysign(sq, B2))
        r1 = np.where(q != 0, C2 / np.where(q == 0, 1.0, q), np.inf)
        r2 = np.where(A2 != 0, q / np.where(A2 == 0, 1.0, A2), np.inf)
    quad_ok = ~lin & (disc >= 0)
    crit[:, 0] = np.where(lin, s_lin, np.where(quad_ok, r1, np.inf))
    crit[:, 1] = np.where(quad_ok, r2, np.inf)
    crit = np.where((crit > 0) & (crit < s_max), crit, s_max)
    crit.sort(axis=1)
    knots = np.concatenate([np.zeros((n, 1)), crit, np.full((n, 1), s_max)], axis=1)  # (n, 4) ascending

    lo = np.zeros(n)
    hi = np.zeros(n)
    found = np.zeros(n, bool)
    for k in range(1, 4):  # monotone pieces [knots[k-1], knots[k]]; empty ones are skipped by the order
        end = knots[:, k]
        hit = ~found & (a + end * (b + end * (c + end * d)) <= 0)
        lo = np.where(hit, knots[:, k - 1], lo)
        hi = np.where(hit, end, hi)
        found |= hit
    out = np.full(n, np.inf)
    idx = np.nonzero(found)[0]
    if idx.size:
        lo_i, hi_i = lo[idx], hi[idx]
        ai, bi, ci, di = a[idx], b[idx], c[idx], d[idx]
        for _ in range(80):
            mid = 0.5 * (lo_i + hi_i)
            pm = ai + mid * (bi + mid * (ci + mid * di))
            pos = pm > 0
            lo_i = np.where(pos, mid, lo_i)
            hi_i = np.where(pos, hi_i, mid)
        out[idx] = lo_i
    return out


# ----------------------------------------------------------------------------- Newton
@dataclass
class InjectiveResult:
    """What :func:`minimize_barrier` returns.

    Attributes:
        y: ``(m,)`` the free unknowns.
        inverted: ``(k,)`` the tets whose ``det J <= 0`` at ``y`` (floating point; the exact verdict
            is :func:`~.validity.check_map`'s).
        energy: ``E(y) / sum vol`` (with the shifts of the last round).
        fit_energy: ``sum vol |J - I|^2 / sum vol`` (the least-squares objective's value).
        min_det: the smallest ``det J_t``.
        rounds, iterations: Newton rounds and steps taken.
        converged: the last round's Newton decrement fell under the tolerance.
        history: per step ``(round, energy, inverted, step)``.
        seconds: wall time.
    """

    y: np.ndarray
    inverted: np.ndarray
    energy: float
    fit_energy: float
    min_det: float
    rounds: int
    iterations: int
    converged: bool
    history: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def n_inverted(self) -> int:
        return int(self.inverted.size)


class _Hessian:
    """``(G Z)^T blockdiag(H_t) (G Z)`` restricted to the unfixed unknowns, for many ``H_t``."""

    def __init__(self, jac: TetJacobians, free: np.ndarray):
        self.jac = jac
        self.free = free
        self.GZf = jac.GZ[:, free].tocsr()
        T = jac.n_tets
        self._indptr = np.arange(T + 1)
        self._indices = np.arange(T)

    def __call__(self, Hb: np.ndarray) -> sp.csr_matrix:
        T = Hb.shape[0]
        B = sp.bsr_matrix((Hb, self._indices, self._indptr), shape=(9 * T, 9 * T))
        H = (self.GZf.T @ (B @ self.GZf)).tocsr()
        return 0.5 * (H + H.T)


def _newton(jac, y, eps, w_fit, w_sd, free, *, max_iter, tol, backend, history, rnd, fixed_dir=None):
    """Newton steps on the unfixed unknowns ``free`` (bool mask) from a feasible ``y``; returns
    ``(y, iterations, converged)``."""
    hess = _Hessian(jac, np.nonzero(free)[0])
    vol = jac.vol
    Etot = vol.sum()
    it = 0
    converged = False
    E = _energy(jac, y, eps, w_fit, w_sd)
    for it in range(1, max_iter + 1):
        J = jac(y)
        f, g, H = barrier_terms(torch.from_numpy(J), torch.from_numpy(eps), w_fit, w_sd)
        gJ = g.numpy() * vol[:, None]
        grad = jac.GZ.T @ gJ.reshape(-1)
        gf = grad[free]
        Hb = H.numpy() * vol[:, None, None]
        A = hess(Hb)
        # a tiny Tikhonov term keeps the factorization definite where the energy is flat
        A = A + sp.identity(A.shape[0], format="csr") * (1e-12 * max(float(np.abs(A.diagonal()).max(initial=0.0)), 1e-300))
        try:
            df = -factorize(A, backend).solve(gf)
        except NotPositiveDefinite:
            A = A + sp.identity(A.shape[0], format="csr") * (1e-8 * max(float(np.abs(A.diagonal()).max(initial=0.0)), 1e-300))
            df = -factorize(A, backend).solve(gf)
        dec = float(-gf @ df)
        if dec <= tol * max(E, 1e-300):
            converged = True
            it -= 1
            break
        d = np.zeros_like(y)
        d[free] = df
        dJ = jac.step(d)
        a, b, c, dd = _det_cubic(J, dJ)
        s_max = min(1.0, _STEP_FRACTION * float(first_root(a + eps, b, c, dd, 1.0 / _STEP_FRACTION).min(initial=np.inf)))
        s = s_max
        while s > 1e-12:
            y_new = y + s * d
            E_new = _energy(jac, y_new, eps, w_fit, w_sd)
            if E_new <= E - 1e-4 * s * dec:
                break
            s *= 0.5
        else:
            history.append((rnd, E / Etot, int((np.linalg.det(J) <= 0).sum()), 0.0))
            break
        y, E = y_new, E_new
        history.append((rnd, E / Etot, int((np.linalg.det(jac(y)) <= 0).sum()), s))
    return y, it, converged


def _shifts(det: np.ndarray, penalty: float) -> np.ndarray:
    return np.where(det > DET_SAFE, 0.0, 1.0 / penalty - np.minimum(det, 0.0))


def minimize_barrier(jac: TetJacobians, y0: np.ndarray, *, fixed: np.ndarray | None = None, w_fit: float = 1.0,
                     w_sd: float = 1.0, rounds: int = 4, max_iter: int = 50, tol: float = 1e-6,
                     backend: str = "auto") -> InjectiveResult:
    """Minimize the barrier energy of the module docstring from ``y0``.

    Args:
        jac: the :class:`TetJacobians` of the seamless problem.
        y0: ``(m,)`` start (inverted tets allowed: they get shifts).
        fixed: ``(m,)`` bool, unknowns held at their value in ``y0``.
        w_fit, w_sd: weights of the fitting and symmetric Dirichlet terms.
        rounds: shift updates (each a Newton solve); stops after the first round that leaves
            every ``det J > DET_SAFE``.
        max_iter: Newton steps per round; tol: a round ends when the Newton decrement
            ``-g^T d`` is below ``tol`` times the energy.
        backend: sparse solver (:mod:`.solver`).

    Returns:
        :class:`InjectiveResult`. A map that stays inverted somewhere is a result (its
        ``inverted`` tets say where), not an error.
    """
    t0 = time.perf_counter()
    y = np.array(y0, np.float64, copy=True)
    m = y.size
    free = np.ones(m, bool) if fixed is None else ~np.asarray(fixed, bool)
    det = np.linalg.det(jac(y))
    eps = _shifts(det, PENALTY_START)
    history = []
    iters = 0
    converged = False
    rnd = 0
    for rnd in range(1, rounds + 1):
        if free.any():
            y, it, converged = _newton(jac, y, eps, w_fit, w_sd, free, max_iter=max_iter, tol=tol, backend=backend,
                                       history=history, rnd=rnd)
            iters += it
        det = np.linalg.det(jac(y))
        if (det > DET_SAFE).all():
            break
        # tets that became positive lose their shift (they can never fold again); the others get a new one
        eps = _shifts(det, PENALTY_ROUND)
    J = jac(y)
    det = np.linalg.det(J)
    fit = float((jac.vol * ((J - np.eye(3)) ** 2).sum((1, 2))).sum() / jac.vol.sum())
    E = _energy(jac, y, eps, w_fit, w_sd)
    return InjectiveResult(y=y, inverted=np.nonzero(det <= 0)[0], energy=E / jac.vol.sum(), fit_energy=fit,
                           min_det=float(det.min(initial=np.inf)), rounds=rnd, iterations=iters, converged=converged,
                           history=history, seconds=time.perf_counter() - t0)


def move_fixed(jac: TetJacobians, y: np.ndarray, idx: np.ndarray, target: np.ndarray, *,
               held: np.ndarray | None = None, w_fit: float = 1.0, w_sd: float = 1.0, max_steps: int = 30,
               max_iter: int = 20, tol: float = 1e-6, backend: str = "auto") -> tuple[np.ndarray, bool, dict]:
    """Move the unknowns ``idx`` from their values in a map with no inverted tet to ``target``
    along a straight path, the other unknowns following, never crossing ``det J = 0``.

    Each step takes the linear response of the others to the remaining displacement (one Newton
    system with the moved unknowns as a prescribed change), caps it at the first root of the
    determinants, takes it, and re-minimizes the others with the moved unknowns held. The move
    fails when a step shrinks below ``1e-6`` of the path (a tet would have to fold): the map is
    then returned unchanged.

    ``held (m,)`` bool: other unknowns that stay where they are (the integers rounded before).

    Returns:
        ``(y, ok, info)``: the new unknowns (``y[idx] = target`` exactly when ``ok``), whether the
        move reached its target, and ``steps`` / ``iterations``.
    """
    y0 = np.array(y, np.float64, copy=True)
    y = y0.copy()
    idx = np.asarray(idx, np.int64)
    target = np.asarray(target, np.float64)
    m = y.size
    fixed = np.zeros(m, bool) if held is None else np.array(held, bool, copy=True)
    fixed[idx] = True
    free = ~fixed
    eps = np.zeros(jac.n_tets)
    if (np.linalg.det(jac(y)) <= 0).any():
        raise ValueError("move_fixed starts from a map with inverted tets")
    hess = _Hessian(jac, np.nonzero(free)[0])
    hess_fix = jac.GZ[:, idx].tocsr()
    vol = jac.vol
    info = {"steps": 0, "iterations": 0}
    history = []
    for step in range(max_steps):
        delta = target - y[idx]
        if not np.any(delta):
            break
        J = jac(y)
        _, g, H = barrier_terms(torch.from_numpy(J), torch.from_numpy(eps), w_fit, w_sd)
        Hb = H.numpy() * vol[:, None, None]
        A = hess(Hb)
        A = A + sp.identity(A.shape[0], format="csr") * (1e-12 * max(float(np.abs(A.diagonal()).max(initial=0.0)), 1e-300))
        # H_fF delta through the blocks: (G Z_f)^T blockdiag(H) (G Z_F) delta
        dJF = (hess_fix @ delta).reshape(-1, 9)
        rhs = hess.GZf.T @ np.einsum("tij,tj->ti", Hb, dJF).reshape(-1)
        gJ = g.numpy() * vol[:, None]
        grad_f = (jac.GZ.T @ gJ.reshape(-1))[free]
        try:
            df = -factorize(A, backend).solve(rhs + grad_f)
        except NotPositiveDefinite:
            break
        d = np.zeros(m)
        d[free] = df
        d[idx] = delta
        a, b, c, dd = _det_cubic(J, jac.step(d))
        root = float(first_root(a, b, c, dd, 1.0 / _STEP_FRACTION).min(initial=np.inf))
        s = min(1.0, _STEP_FRACTION * root)
        if s < 1e-6:
            break
        y = y + s * d
        if s >= 1.0:
            y[idx] = target
        info["steps"] += 1
        y, it, _ = _newton(jac, y, eps, w_fit, w_sd, free, max_iter=max_iter, tol=tol, backend=backend,
                           history=history, rnd=step)
        info["iterations"] += it
    ok = bool(np.array_equal(y[idx], target)) and bool((np.linalg.det(jac(y)) > 0).all())
    if not ok:
        return y0, False, info
    return y, True, info
