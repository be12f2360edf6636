"""The foldover-free seamless map: untangling, then a per-tet barrier, by PSD-projected Newton.

The least-squares seamless map (:mod:`.seamless`) has no notion of injectivity: where the frames
do not integrate it folds. This module works over the free unknowns ``y`` of the eliminated
constraints (``u = Z y + z0``, :mod:`.elimination`) on the per-tet Jacobians
``J_t = grad u_t (h F_t)`` (the tet's Jacobian relative to its combed frame and the hex edge
length: ``I`` for a map that follows the frames; ``det J_t > 0`` exactly when the tet keeps its
orientation), with two energies:

.. code-block:: text

    barrier:    E(y) = sum_t vol_t [ w_fit |J_t - I|^2 + w_sd ( |J_t|^2 + |adj J_t|^2 / (det J_t + eps_t)^2 - 6 ) ]
    untangling: E(y) = sum_t vol_t [ w_fit |J_t - I|^2 + |J_t|^2 / (3 chi_t^(2/3)) + (det J_t^2 + 1) / (2 chi_t) ]

The barrier energy is the frame-fitting term of :mod:`.seamless` plus the symmetric Dirichlet
energy (``|J|^2 + |J^-1|^2``, 6 at a rotation), whose ``|J^-1|^2 = |adj J|^2 / det^2`` is a barrier at
``det J = -eps_t``: with ``eps_t = 0`` a positive tet can never fold; a tet that is inverted gets a
shift ``eps_t = 1/penalty - det J_t > 0`` (AlgoHex's shifted barrier, Liu & Bommes 2023). The
untangling energy (Garanzha et al. 2021, "Foldover-free maps in 50 lines of code") replaces the
determinant by ``chi_t = (det J_t + sqrt(eps^2 + det J_t^2)) / 2 > 0``: finite for inverted tets
too, it lets a tangle pass through folds on its way out, and becomes a barrier as ``eps -> 0``.
:func:`minimize_barrier` runs untangling (``eps`` lowered after each solve), AlgoHex's shifted
rounds where tets stay inverted — both with the fitting term relieved (:data:`FIT_RELIEF`) — then
the barrier energy at the full fitting weight with every tet held positive.

Each Newton step: the per-tet gradients and ``9 x 9`` Hessians in ``J`` (batched closed forms in
torch, :mod:`.tet_energies`), each Hessian projected onto the positive semidefinite cone
(its negative eigenvalues set to 0, from the isotropic energies' analytic eigensystem), assembled in
the eliminated space, ``H = (G Z)^T blockdiag(H_t) (G Z)``, and one sparse Cholesky solve
(:mod:`.solver`). With the barrier energy the line search never crosses ``det J_t + eps_t = 0``: the step is capped at
0.9 times the first positive root of the cubic ``det(J_t + s dJ_t) + eps_t`` over all tets
(:func:`~.tet_energies.first_root`), then backtracked (Armijo).

Unknowns may be held fixed: the quantization moves integer unknowns to their rounded values along
a straight path while the others follow (:func:`move_fixed`), with the barrier (no tet folds).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from .solver import NotPositiveDefinite, factorize
from .tet_energies import _det_cubic, barrier_terms, first_root, untangling_terms

__all__ = ["TetJacobians", "InjectiveResult", "minimize_barrier", "move_fixed", "PENALTY_START", "PENALTY_ROUND",
           "DET_SAFE", "FIT_RELIEF"]

PENALTY_START = 1e3
"""The first shift of an inverted tet: ``eps = 1/PENALTY_START - det J`` (so ``det + eps = 1e-3``)."""
PENALTY_ROUND = 1e2
"""The shift of a tet still inverted after a round: ``eps = 1/PENALTY_ROUND - det J``."""
FIT_RELIEF = 0.01
"""The fitting weight of the untangling and shifted-barrier phases, relative to ``w_fit``: while
tets are inverted the map may turn away from the frames; the last phase fits them at ``w_fit``
with every tet held positive (:func:`minimize_barrier`)."""
DET_SAFE = 1e-6
"""A tet is held by the plain barrier (``eps = 0``) once ``det J > DET_SAFE`` (``J`` is normalized:
1 at the target size); below, it keeps a shift, so that a nearly flat tet does not make the
barrier's Hessian overflow the solve."""
_STEP_FRACTION = 0.9  # of the first root of det(J + s dJ) + eps = 0
_DET_MOVE_MIN = 1e-9  # a move that squeezes a tet below this has failed (its barrier would overflow)


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
def _fit_terms(J: np.ndarray, w_fit: float):
    """The fitting term ``w_fit |J - I|^2`` alone: energy, gradient, Hessian ``(T,), (T, 9), (T, 9, 9)``."""
    j = torch.from_numpy(J.reshape(-1, 9))
    r = j - torch.eye(3, dtype=j.dtype).reshape(9)
    H = 2.0 * w_fit * torch.eye(9, dtype=j.dtype).expand(j.shape[0], 9, 9)
    return w_fit * r.square().sum(1), 2.0 * w_fit * r, H


class _Model:
    """A per-tet energy (a subclass's ``_active_terms(J, hessian)``) on the ``active (T,)`` tets;
    the others get the fitting term only and no barrier (tets the constraints flatten, whose
    determinant no map can change)."""

    def __init__(self, w_fit: float, active: np.ndarray | None):
        self.w_fit = w_fit
        self.active = None if active is None or bool(np.all(active)) else np.asarray(active, bool)

    def terms(self, J: np.ndarray, hessian: bool = True):
        if self.active is None:
            return self._active_terms(J, hessian)
        f, g, H = _fit_terms(J, self.w_fit)
        H = H.clone() if hessian else None
        fa, ga, Ha = self._active_terms(J[self.active], hessian)
        idx = torch.from_numpy(np.nonzero(self.active)[0])
        f, g = f.clone(), g.clone()
        f[idx], g[idx] = fa, ga
        if hessian:
            H[idx] = Ha
        return f, g, H

    def energy(self, J: np.ndarray, vol: np.ndarray) -> float:
        if not self.feasible(J):
            return math.inf
        f, _, _ = self.terms(J, hessian=False)
        return float((vol * f.numpy()).sum())

    def feasible(self, J: np.ndarray) -> bool:
        return True

    def cap(self, J: np.ndarray, dJ: np.ndarray) -> float:
        return 1.0


class _Barrier(_Model):
    """The shifted-barrier energy (:func:`barrier_terms`) with per-tet shifts ``eps (T,)``."""

    def __init__(self, eps: np.ndarray, w_fit: float, w_sd: float, active: np.ndarray | None = None):
        super().__init__(w_fit, active)
        self.eps, self.w_sd = eps, w_sd

    def _active_terms(self, J, hessian):
        eps = self.eps if self.active is None else self.eps[self.active]
        return barrier_terms(torch.from_numpy(J), torch.from_numpy(eps), self.w_fit, self.w_sd, hessian=hessian)

    def feasible(self, J: np.ndarray) -> bool:
        ok = np.linalg.det(J) + self.eps > 0
        return bool(np.all(ok if self.active is None else ok[self.active]))

    def cap(self, J: np.ndarray, dJ: np.ndarray) -> float:
        """The longest step along ``dJ`` that stays ``_STEP_FRACTION`` of the way to a zero of
        ``det + eps`` on the active tets (at most 1)."""
        if self.active is not None:
            J, dJ, eps = J[self.active], dJ[self.active], self.eps[self.active]
        else:
            eps = self.eps
        a, b, c, d = _det_cubic(J, dJ)
        root = float(first_root(a + eps, b, c, d, 1.0 / _STEP_FRACTION).min(initial=np.inf))
        return min(1.0, _STEP_FRACTION * root)


class _Untangling(_Model):
    """The untangling energy (:func:`untangling_terms`) with the global regularization ``eps``."""

    def __init__(self, eps: float, w_fit: float, active: np.ndarray | None = None):
        super().__init__(w_fit, active)
        self.eps = eps

    def _active_terms(self, J, hessian):
        return untangling_terms(torch.from_numpy(J), self.eps, self.w_fit, hessian=hessian)


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


def _newton(jac, y, model, free, *, max_iter, tol, backend, history, rnd, quad=None, until=None):
    """Newton steps of ``model``'s energy on the unfixed unknowns ``free`` (bool mask) from a
    feasible ``y``: PSD-projected Hessian, one sparse solve, the step capped by ``model.cap``,
    Armijo backtracking. ``quad = (P, q)``: a quadratic ``y^T P y - 2 q^T y`` added to the energy
    (``P (m, m)`` sparse, symmetric positive semidefinite). ``until``: a test of the per-tet
    determinants ``(T,)`` after each step that ends the steps when true (the solve's goal met:
    not counted as converged). Returns ``(y, iterations, converged)``."""
    hess = _Hessian(jac, np.nonzero(free)[0])
    vol = jac.vol
    Etot = vol.sum()
    it = 0
    converged = False
    if quad is not None:
        P, q = sp.csr_matrix(quad[0]), np.asarray(quad[1], np.float64)
        Pff = P[free][:, free].tocsr()

        def energy(yy):
            return model.energy(jac(yy), vol) + float(yy @ (P @ yy) - 2.0 * q @ yy)
    else:
        def energy(yy):
            return model.energy(jac(yy), vol)
    E = energy(y)
    for it in range(1, max_iter + 1):
        J = jac(y)
        try:
            _, g, H = model.terms(J)
        except FloatingPointError:
            break
        grad = jac.GZ.T @ (g.numpy() * vol[:, None]).reshape(-1)
        A = hess(H.numpy() * vol[:, None, None])
        if quad is not None:
            grad = grad + 2.0 * (P @ y - q)
            A = A + 2.0 * Pff
        gf = grad[free]
        # a tiny Tikhonov term keeps the factorization definite where the energy is flat
        scale = max(float(np.abs(A.diagonal()).max(initial=0.0)), 1e-300)
        A = A + sp.identity(A.shape[0], format="csr") * (1e-12 * scale)
        try:
            df = -factorize(A, backend).solve(gf)
        except NotPositiveDefinite:
            df = -factorize(A + sp.identity(A.shape[0], format="csr") * (1e-8 * scale), backend).solve(gf)
        dec = float(-gf @ df)
        if dec <= tol * max(abs(E), 1e-300):
            converged = True
            it -= 1
            break
        d = np.zeros_like(y)
        d[free] = df
        s = model.cap(J, jac.step(d))
        while s > 1e-12:
            y_new = y + s * d
            E_new = energy(y_new)
            if E_new <= E - 1e-4 * s * dec:
                break
            s *= 0.5
        else:
            break
        y, E = y_new, E_new
        det = np.linalg.det(jac(y))
        history.append((rnd, E / Etot, int((det <= 0).sum()), s))
        if until is not None and until(det):
            break
    return y, it, converged


def _shifts(det: np.ndarray, penalty: float) -> np.ndarray:
    return np.where(det > DET_SAFE, 0.0, 1.0 / penalty - np.minimum(det, 0.0))


def minimize_barrier(jac: TetJacobians, y0: np.ndarray, *, fixed: np.ndarray | None = None,
                     ignore: np.ndarray | None = None, w_fit: float = 1.0, w_sd: float = 1.0,
                     untangle_rounds: int = 3, rounds: int = 4, max_iter: int = 50, tol: float = 1e-6,
                     backend: str = "auto") -> InjectiveResult:
    """A map with no inverted tet near ``y0``, and the barrier energy of the module docstring
    minimized there.

    Three phases:

    1. where a tet is not safely positive (``det J <= DET_SAFE``): untangling (Garanzha et al.
       2021): Newton on the untangling energy (:func:`untangling_terms`), finite for inverted
       tets too, with its regularization ``eps`` lowered after each solve so that ``chi`` of the
       smallest determinant falls by the relative energy decrease (at least 10%), until every
       tet is positive or ``untangle_rounds`` solves are spent;
    2. if tets are still inverted: AlgoHex's shifted barrier (per-tet shifts, at most ``rounds``
       rounds: a tet that became positive loses its shift, the others get a new one; the rounds
       end when one leaves as many tets inverted as the round before it);
    3. with every tet positive: Newton on the barrier energy with no shift (no tet can fold).

    The solves of phases 1 and 2 end at the step that leaves every tet safely positive (their
    goal; phase 3 then minimizes from there) rather than converging first. They fit the frames at
    ``w_fit * FIT_RELIEF`` (1/100): while tets are inverted the map may turn away from the frames,
    and phase 3 fits them again at ``w_fit`` with every tet held positive. At the full weight the
    fit held n10c's seamless map at 8 inverted tets after 179 Newton steps; with the relief its
    first shifted round opens all of them (docs/results/hexmesh.md). A map whose start has no
    inverted tet runs phase 3 only, as before.

    Args:
        jac: the :class:`TetJacobians` of the seamless problem.
        y0: ``(m,)`` start (inverted tets allowed).
        fixed: ``(m,)`` bool, unknowns held at their value in ``y0``.
        ignore: ``(k,)`` tets left out of the untangling and the barrier (their fitting term
            stays): the tets the constraints flatten (:meth:`~.seamless.SeamlessProblem.flat_tets`),
            which no value of the unknowns opens; they are not counted as inverted.
        w_fit, w_sd: weights of the fitting and symmetric Dirichlet terms (``w_fit *
            FIT_RELIEF`` in phases 1 and 2).
        untangle_rounds, rounds: the budgets of phases 1 and 2. Three untangling solves: on 14
            HexMe ``c`` models (SH fields, 2026-11-27) the solves past the third changed no map's
            verdict and took 42% of the Newton steps of the six maps where they ran
            (docs/results/hexmesh.md).
        max_iter: Newton steps per solve; tol: a solve ends when the Newton decrement ``-g^T d``
            is below ``tol`` times the energy.
        backend: sparse solver (:mod:`.solver`).

    Returns:
        :class:`InjectiveResult`. A map that stays inverted somewhere is a result (its
        ``inverted`` tets say where), not an error.
    """
    t0 = time.perf_counter()
    w_relief = w_fit * FIT_RELIEF
    y = np.array(y0, np.float64, copy=True)
    m = y.size
    free = np.ones(m, bool) if fixed is None else ~np.asarray(fixed, bool)
    active = np.ones(jac.n_tets, bool)
    if ignore is not None:
        active[np.asarray(ignore, np.int64)] = False
    history = []
    iters = 0
    converged = False
    rnd = 0

    def dets(yy):
        d = np.linalg.det(jac(yy))
        d[~active] = np.inf  # never inverted, never limiting
        return d

    def untangled(d):  # the goal of phases 1 and 2: their solves end as soon as it is met
        return bool((d[active] > DET_SAFE).all())

    det = dets(y)
    # ---- phase 1: untangling with a shrinking regularization
    if free.any() and (det <= DET_SAFE).any():
        dmin = float(det.min())
        eps = math.sqrt(1e-12 + 0.04 * min(dmin, 0.0) ** 2) if dmin <= 0 else 1e-3
        for k in range(untangle_rounds):
            model = _Untangling(eps, w_relief, active)
            E0 = model.energy(jac(y), jac.vol)
            y, it, _ = _newton(jac, y, model, free, max_iter=10, tol=tol, backend=backend, history=history,
                               rnd=("untangle", k), until=untangled)
            iters += it
            det = dets(y)
            if (det > DET_SAFE).all():
                break
            E1 = model.energy(jac(y), jac.vol)
            sigma = max(1.0 - E1 / E0, 0.1) if E0 > 0 else 0.1
            dmin = float(det.min())
            mu = (1.0 - sigma) * 0.5 * (dmin + math.sqrt(eps * eps + dmin * dmin))
            eps = 2.0 * math.sqrt(mu * (mu - dmin)) if dmin < mu else 1e-10
    # ---- phase 2: shifted barrier where tets are still inverted
    if free.any() and (det <= DET_SAFE).any():
        eps_t = _shifts(det, PENALTY_START)
        left = int((det <= DET_SAFE).sum())
        for rnd in range(1, rounds + 1):
            y, it, converged = _newton(jac, y, _Barrier(eps_t, w_relief, w_sd, active), free, max_iter=max_iter,
                                       tol=tol, backend=backend, history=history, rnd=("shifted", rnd),
                                       until=untangled)
            iters += it
            det = dets(y)
            now = int((det <= DET_SAFE).sum())
            if now == 0 or (rnd > 1 and now >= left):  # untangled, or a round that opened no tet
                break
            left = now
            # tets that became positive lose their shift (they can never fold again); the others get a new one
            eps_t = _shifts(det, PENALTY_ROUND)
    # ---- phase 3: the barrier energy, every tet held positive
    eps_t = _shifts(det, PENALTY_ROUND)
    if free.any():
        y, it, converged = _newton(jac, y, _Barrier(eps_t, w_fit, w_sd, active), free, max_iter=max_iter, tol=tol,
                                   backend=backend, history=history, rnd=("barrier", 0))
        iters += it
    J = jac(y)
    det = dets(y)
    fit = float((jac.vol * ((J - np.eye(3)) ** 2).sum((1, 2))).sum() / jac.vol.sum())
    E = _Barrier(_shifts(det, PENALTY_ROUND), w_fit, w_sd, active).energy(J, jac.vol)
    return InjectiveResult(y=y, inverted=np.nonzero(det <= 0)[0], energy=E / jac.vol.sum(), fit_energy=fit,
                           min_det=float(det.min(initial=np.inf)), rounds=rnd, iterations=iters, converged=converged,
                           history=history, seconds=time.perf_counter() - t0)


def move_fixed(jac: TetJacobians, y: np.ndarray, idx: np.ndarray, target: np.ndarray, *,
               held: np.ndarray | None = None, ignore: np.ndarray | None = None, w_fit: float = 1.0,
               w_sd: float = 1.0, max_steps: int = 8, max_iter: int = 10, tol: float = 1e-6,
               backend: str = "auto") -> tuple[np.ndarray, bool, dict]:
    """Move the unknowns ``idx`` from their values in a map with no inverted tet to ``target``
    along a straight path, the other unknowns following, never crossing ``det J = 0``.

    Each step takes the linear response of the others to the remaining displacement (one Newton
    system with the moved unknowns as a prescribed change), caps it at the first root of the
    determinants, takes it, and re-minimizes the others with the moved unknowns held. The move
    fails (the map is then returned unchanged) when a tet would have to fold: a step squeezes a
    tet below ``det J = 1e-9``, the smallest determinant falls fourfold at two capped steps in a
    row (it goes to 0 at the target), or ``max_steps`` steps do not reach the target.

    ``held (m,)`` bool: other unknowns that stay where they are (the integers rounded before);
    ``ignore (k,)``: tets left out as in :func:`minimize_barrier` (flat whatever the unknowns).

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
    model = _Barrier(eps, w_fit, w_sd)
    if ignore is not None and np.size(ignore):
        active = np.ones(jac.n_tets, bool)
        active[np.asarray(ignore, np.int64)] = False
        model = _Barrier(eps, w_fit, w_sd, active)
    act = model.active if model.active is not None else slice(None)

    def min_det(yy):
        return float(np.linalg.det(jac(yy))[act].min(initial=np.inf))

    if min_det(y) <= 0:
        raise ValueError("move_fixed starts from a map with inverted tets")
    hess = _Hessian(jac, np.nonzero(free)[0])
    hess_fix = jac.GZ[:, idx].tocsr()
    vol = jac.vol
    info = {"steps": 0, "iterations": 0}
    history = []
    short = 0
    md_prev = min_det(y)
    for step in range(max_steps):
        delta = target - y[idx]
        if not np.any(delta):
            break
        J = jac(y)
        try:
            _, g, H = model.terms(J)
        except FloatingPointError:
            break
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
        s = model.cap(J, jac.step(d))
        if s < 1e-6:
            break
        y_try = y + s * d
        if s >= 1.0:
            y_try[idx] = target
        md = min_det(y_try)
        if md < _DET_MOVE_MIN:  # the move squeezes a tet flat: it would fold
            break
        # the smallest determinant falling fourfold at each capped step goes to 0 at the target: a fold
        short = short + 1 if (s < 1.0 and md < 0.25 * md_prev) else 0
        if short >= 2:
            break
        md_prev = md
        y = y_try
        info["steps"] += 1
        y, it, _ = _newton(jac, y, model, free, max_iter=max_iter, tol=tol, backend=backend,
                           history=history, rnd=("move", step))
        info["iterations"] += it
    # a tet the integers leave at round-off size (a collapse the steps did not see) is a failure too
    ok = bool(np.array_equal(y[idx], target)) and min_det(y) > DET_SAFE
    if not ok:
        return y0, False, info
    return y, True, info
