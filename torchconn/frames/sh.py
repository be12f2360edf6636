"""Spherical-harmonic octahedral frame fields: the Ray, Sokolov & Lévy 2016 baseline.

Reference: N. Ray, D. Sokolov, B. Lévy, "Practical 3D frame field generation", ACM TOG 35(6),
2016 (building on Huang et al. 2011, "Boundary aligned smooth 3D cross-frame field").

Representation
--------------
A frame ``F`` (``F[:, k]`` = axis ``k`` in world coordinates) is represented by the function
``f_F(x) = f_0(F^T x)`` on the unit sphere, ``f_0(x) ∝ x^4 + y^4 + z^4 - 3/5``, whose maxima
are the six directions ``±F[:, k]``. ``f_0`` lives in band ``l = 4`` of the real spherical
harmonics; we store the 9 coefficients in the order ``m = -4, ..., 4`` of the orthonormal real
basis :func:`sh_basis`. The canonical frame ``F = I`` has

    q_0 = sqrt(7/12) e_{m=0} + sqrt(5/12) e_{m=4}        (unit norm).

Rotations act by ``D(R)``, defined by ``(D(R) q) . Y(x) = q . Y(R^T x)`` (the coefficients of
the rotated function), so ``frame_to_sh(F) = D(F) q_0``. Invariants (mirrored in
``tests/test_sh_baseline.py``):

* ``D(R1 R2) = D(R1) D(R2)`` and ``D(R)^T D(R) = I`` (orthonormal basis);
* ``frame_to_sh(F g) = frame_to_sh(F)`` for ``g`` in the octahedral group O;
* ``D(exp(t hat(e_k))) = matrix_exp(t L_k)`` with the generators of :func:`sh_generators`.

How ``D(R)`` is computed: band 4 is closed under rotations, so for a fixed set ``X`` of ``N >= 9``
sphere points with full-rank ``Y(X) (N, 9)``, ``Y(X R) = Y(X) D(R)`` holds exactly and
``D(R) = Y(X)^+ Y(X R)`` (points as rows, ``x^T R = (R^T x)^T``). This is batched, exact to
round-off, differentiable and avoids Euler-angle round trips. The generators are its
derivative at the identity (computed once, in float64, by autograd).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from ..lie import so3
from .constraints import BoundaryConstraint

__all__ = [
    "sh_basis",
    "reference_sh",
    "sh_rotation",
    "sh_generators",
    "frame_to_sh",
    "sh_to_frame",
    "boundary_constraint",
    "sh_frame_field",
]

_C0 = math.sqrt(7.0 / 12.0)
_C4 = math.sqrt(5.0 / 12.0)
_M0 = 4  # index of m = 0 in the m = -4..4 order


def sh_basis(x: torch.Tensor) -> torch.Tensor:
    """Real orthonormal band-4 spherical harmonics ``Y_4^m(x)``, ``m = -4..4``: ``(..., 3) -> (..., 9)``.

    ``x`` are unit vectors (the polynomials are evaluated as given, no normalization). Standard
    real basis without the Condon–Shortley phase (e.g. Sloan, "Stupid spherical harmonics
    tricks", 2008, Appendix A2):

    * ``m=-4: 3/4 sqrt(35/pi) xy(x^2-y^2)``, ``m=-3: 3/4 sqrt(35/(2pi)) (3x^2-y^2) yz``,
    * ``m=-2: 3/4 sqrt(5/pi) xy(7z^2-1)``,   ``m=-1: 3/4 sqrt(5/(2pi)) yz(7z^2-3)``,
    * ``m=0: 3/16 sqrt(1/pi) (35z^4-30z^2+3)``,
    * ``m=1: 3/4 sqrt(5/(2pi)) xz(7z^2-3)``,  ``m=2: 3/8 sqrt(5/pi) (x^2-y^2)(7z^2-1)``,
    * ``m=3: 3/4 sqrt(35/(2pi)) (x^2-3y^2) xz``, ``m=4: 3/16 sqrt(35/pi) (x^4-6x^2y^2+y^4)``.
    """
    if x.shape[-1:] != (3,):
        raise ValueError(f"sh_basis expects points of shape (..., 3), got {tuple(x.shape)}")
    X, Y, Z = x.unbind(-1)
    x2, y2, z2 = X * X, Y * Y, Z * Z
    pi = math.pi
    return torch.stack(
        (
            0.75 * math.sqrt(35 / pi) * X * Y * (x2 - y2),
            0.75 * math.sqrt(35 / (2 * pi)) * (3 * x2 - y2) * Y * Z,
            0.75 * math.sqrt(5 / pi) * X * Y * (7 * z2 - 1),
            0.75 * math.sqrt(5 / (2 * pi)) * Y * Z * (7 * z2 - 3),
            (3 / 16) * math.sqrt(1 / pi) * (35 * z2 * z2 - 30 * z2 + 3),
            0.75 * math.sqrt(5 / (2 * pi)) * X * Z * (7 * z2 - 3),
            (3 / 8) * math.sqrt(5 / pi) * (x2 - y2) * (7 * z2 - 1),
            0.75 * math.sqrt(35 / (2 * pi)) * (x2 - 3 * y2) * X * Z,
            (3 / 16) * math.sqrt(35 / pi) * (x2 * x2 - 6 * x2 * y2 + y2 * y2),
        ),
        -1,
    )


def reference_sh(dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """``q_0 (9,)``: SH coefficients of the canonical frame ``I``, ``sqrt(7/12) e_0 + sqrt(5/12) e_4``."""
    q = torch.zeros(9, dtype=dtype or torch.get_default_dtype(), device=device)
    q[_M0] = _C0
    q[8] = _C4
    return q


@lru_cache(maxsize=None)
def _samples64() -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed Fibonacci-sphere points ``X (N, 3)`` and ``Y(X)^+ (9, N)`` in float64."""
    n = 32
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    X = torch.tensor(np.stack([r * np.cos(phi), r * np.sin(phi), z], 1), dtype=torch.float64)
    P = torch.linalg.pinv(sh_basis(X))
    return X, P


def _samples(dtype, device):
    X, P = _samples64()
    return X.to(dtype=dtype, device=device), P.to(dtype=dtype, device=device)


def _check_rot(R: torch.Tensor, name: str) -> None:
    if not torch.is_tensor(R) or R.shape[-2:] != (3, 3):
        shape = tuple(R.shape) if torch.is_tensor(R) else type(R).__name__
        raise ValueError(f"{name} expects rotations of shape (..., 3, 3), got {shape}")
    if not R.is_floating_point():
        raise TypeError(f"{name} expects a floating tensor, got {R.dtype}")


def sh_rotation(R: torch.Tensor) -> torch.Tensor:
    """Band-4 rotation matrices ``D(R)``: ``(..., 3, 3) -> (..., 9, 9)``, ``D(R) q`` rotates a function.

    ``D(R) = Y(X)^+ Y(X R)`` (see module docstring). Orthogonal for rotations; a homomorphism
    ``D(R1 R2) = D(R1) D(R2)``. Differentiable in ``R``.
    """
    _check_rot(R, "sh_rotation")
    X, P = _samples(R.dtype, R.device)
    return P @ sh_basis(X @ R)


@lru_cache(maxsize=None)
def _generators64() -> torch.Tensor:
    eye = torch.eye(3, dtype=torch.float64)
    gens = []
    for k in range(3):
        f = lambda t, k=k: sh_rotation(so3.exp(t * eye[k]))  # noqa: E731
        dD = torch.autograd.functional.jacobian(f, torch.zeros((), dtype=torch.float64))
        gens.append(0.5 * (dD - dD.T))  # exactly skew (it is, up to round-off)
    return torch.stack(gens)


def sh_generators(dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Band-4 generators ``L (3, 9, 9)`` (skew): ``L_k = d/dt D(exp(t hat(e_k)))`` at ``t = 0``.

    So ``D(exp(hat(w))) = matrix_exp(sum_k w_k L_k)`` and, to first order,
    ``D(exp(hat(w)) R) q0 ~ (I + sum_k w_k L_k) D(R) q0``.
    """
    return _generators64().to(dtype=dtype or torch.get_default_dtype(), device=device)


def frame_to_sh(F: torch.Tensor) -> torch.Tensor:
    """SH coefficients ``q = D(F) q_0``: frames ``(..., 3, 3) -> (..., 9)`` (unit norm).

    Closed form: ``f_F(x) = sum_k (a_k . x)^4 - 3/5`` with ``a_k = F[:, k]``, and by the addition
    theorem (Funk–Hecke) the band-4 part of ``(a . x)^4`` is proportional to
    ``sum_m Y_4^m(a) Y_4^m(x)``; hence ``q = kappa * sum_k Y(a_k)`` with ``kappa`` fixed by
    ``q(I) = q_0``, i.e. ``kappa = 1 / |sum_k Y(e_k)|`` (about 0.5157). Invariant under ``F -> F g``, ``g`` in O (the sum
    over the axes ``±a_k`` is permuted).
    """
    _check_rot(F, "frame_to_sh")
    Y = sh_basis(F.transpose(-1, -2))  # (..., 3, 9): Y of each axis a_k
    return _kappa() * Y.sum(-2)


@lru_cache(maxsize=None)
def _kappa() -> float:
    return 1.0 / float(sh_basis(torch.eye(3, dtype=torch.float64)).sum(0).norm())


@lru_cache(maxsize=None)
def _restarts64(n: int) -> torch.Tensor:
    # identity plus a fixed (seeded) spread of rotations; deterministic across calls
    g = torch.Generator().manual_seed(20161)
    R = so3.random_rotation(n - 1, generator=g, dtype=torch.float64)
    return torch.cat([torch.eye(3, dtype=torch.float64)[None], R])


def sh_to_frame(q: torch.Tensor, n_restarts: int = 8, n_iters: int = 12,
                init: torch.Tensor | None = None) -> torch.Tensor:
    """Nearest frame to SH vectors: ``q (..., 9) -> F (..., 3, 3)`` minimizing ``||q/|q| - D(F) q_0||``.

    Batched Gauss–Newton on SO(3) with left updates ``F <- exp(hat(w)) F``: with
    ``p = D(F) q_0`` and ``J = [L_x p, L_y p, L_z p] (9, 3)``, ``w = (J^T J)^{-1} J^T (q - p)``
    (steps clamped to 0.5 rad). ``n_restarts`` starts (identity plus fixed, seeded rotations)
    run together; the best final residual wins. With ``init (..., 3, 3)`` (rotations, e.g. the
    previous projection of a nearby field) the starts are ``init`` followed by the first
    ``n_restarts - 1`` fixed ones (``n_restarts = 1``: a warm start only). The result is defined
    up to the octahedral group (any ``F g`` is equally good). ``q = 0`` has no nearest frame: its
    result is arbitrary.
    """
    if not torch.is_tensor(q) or q.shape[-1:] != (9,):
        shape = tuple(q.shape) if torch.is_tensor(q) else type(q).__name__
        raise ValueError(f"sh_to_frame expects SH vectors of shape (..., 9), got {shape}")
    if not q.is_floating_point():
        raise TypeError(f"sh_to_frame expects a floating tensor, got {q.dtype}")
    if n_restarts < 1 or n_iters < 0:
        raise ValueError(f"need n_restarts >= 1 and n_iters >= 0, got {n_restarts}, {n_iters}")
    batch = q.shape[:-1]
    qn = q.reshape(-1, 9)
    qn = qn / qn.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    B = qn.shape[0]
    L = sh_generators(q.dtype, q.device)
    R0 = _restarts64(n_restarts).to(dtype=q.dtype, device=q.device)
    F = R0[None].expand(B, n_restarts, 3, 3)
    if init is not None:
        if not torch.is_tensor(init) or init.shape != (*batch, 3, 3):
            shape = tuple(init.shape) if torch.is_tensor(init) else type(init).__name__
            raise ValueError(f"sh_to_frame: init must have shape {(*batch, 3, 3)} (that of q with (3, 3) for the "
                             f"last dim), got {shape}")
        F = torch.cat((init.reshape(B, 1, 3, 3).to(F), F[:, : n_restarts - 1]), 1)
    F = F.reshape(-1, 3, 3)
    target = qn[:, None, :].expand(B, n_restarts, 9).reshape(-1, 9)
    max_step = 0.5
    for _ in range(n_iters):
        p = frame_to_sh(F)
        J = torch.einsum("kab,nb->nak", L, p)  # (n, 9, 3)
        JtJ = J.transpose(1, 2) @ J
        rhs = (J.transpose(1, 2) @ (target - p)[..., None])[..., 0]
        # J^T J is positive definite for a unit octahedral p (its stabilizer is the finite O);
        # a tiny ridge keeps the solve finite in any case
        ridge = torch.finfo(q.dtype).eps ** 0.5
        w = torch.linalg.solve(JtJ + ridge * torch.eye(3, dtype=q.dtype, device=q.device), rhs)
        nw = w.norm(dim=-1, keepdim=True)
        w = w * torch.clamp(max_step / nw.clamp_min(torch.finfo(q.dtype).tiny), max=1.0)
        F = so3.exp(w) @ F
    res = (frame_to_sh(F) - target).norm(dim=-1).reshape(B, n_restarts)
    best = res.argmin(-1)
    F = F.reshape(B, n_restarts, 3, 3)[torch.arange(B, device=q.device), best]
    # re-orthonormalize (accumulated products drift by round-off only)
    F = so3.project_to_rotation(F)
    return F.reshape(*batch, 3, 3)


def _rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Minimal rotation taking unit ``a`` to unit ``b`` (``(..., 3)`` each), requires ``a.b > -1``.

    ``R = I + K + K^2 / (1 + c)`` with ``K = hat(a x b)``, ``c = a.b``.
    """
    v = torch.linalg.cross(a, b, dim=-1)
    c = (a * b).sum(-1)
    K = so3.hat(v)
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    return eye + K + (K @ K) / (1.0 + c).clamp_min(torch.finfo(a.dtype).eps)[..., None, None]


def _z_to(n: torch.Tensor) -> torch.Tensor:
    """A rotation ``R_n`` with ``R_n e_z = n`` for unit ``n (..., 3)`` (any n, including -z)."""
    z = torch.zeros_like(n)
    z[..., 2] = 1.0
    up = n[..., 2] >= 0
    # for the lower hemisphere go to -n (stable) and compose with a half turn about x
    m = torch.where(up[..., None], n, -n)
    R = _rotation_between(z, m)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=n.dtype, device=n.device))
    return torch.where(up[..., None, None], R, R @ flip)


def boundary_constraint(normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear alignment constraint of Ray et al. 2016 (Sec. 4) for unit normals ``(..., 3)``.

    A frame has an axis along ``n`` iff ``q = D(R_n)(sqrt(7/12) e_0 + c1 e_4 + c2 e_{-4})``
    with ``c1^2 + c2^2 = 5/12`` (``R_n e_z = n``). Relaxing the circle and eliminating the free
    ``(c1, c2)`` leaves the 7 linear equations ``A q = t``: ``A = rows m = -3..3 of D(R_n)^T``,
    ``t = sqrt(7/12) e_{m=0}``.

    Returns:
        ``A (..., 7, 9)`` and ``t (..., 7)``.
    """
    if normals.shape[-1:] != (3,):
        raise ValueError(f"normals must have shape (..., 3), got {tuple(normals.shape)}")
    D = sh_rotation(_z_to(normals))
    A = D.transpose(-1, -2)[..., 1:8, :]
    t = torch.zeros(*normals.shape[:-1], 7, dtype=normals.dtype, device=normals.device)
    t[..., _M0 - 1] = _C0
    return A, t


def _snap_axis(F: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Rotate each frame minimally so that its axis closest to ``±n`` is exactly ``±n``."""
    c = (F * n[..., :, None]).sum(-2)
    k = c.abs().argmax(-1, keepdim=True)
    a = torch.gather(F, -1, k[..., None, :].expand(*F.shape[:-1], 1)).squeeze(-1)
    ck = torch.gather(c, -1, k)
    a = torch.where(ck >= 0, a, -a)  # a.n >= 0, so the minimal rotation is well defined
    return _rotation_between(a, n) @ F


def _penalty_rows(mesh, angle_deg: float, dtype):
    """Penalty rows of the :class:`BoundaryConstraint`: (vertex ids (C,), normals (C,3), weights (C,), smooth-vertex mask).

    One row per aligned vertex (weight 1) and one per feature pair (weight: the face's fraction of
    the boundary area around the vertex).
    """
    V = mesh.vertices.shape[0]
    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    smooth = bc.align_vertices
    n_smooth = bc.align_normals.to(dtype)
    # feature vertices: one constraint per incident boundary face, weights = area fractions
    bf = mesh.boundary_faces
    p = mesh.vertices[bf].to(dtype)
    area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)
    fvert, fface = bc.pair_vertices, bc.pair_faces
    tot = torch.zeros(V, dtype=dtype, device=bf.device).index_add_(0, fvert, area[fface])
    fw = area[fface] / tot[fvert]
    ids = torch.cat([smooth, fvert])
    normals = torch.cat([n_smooth, bc.pair_normals.to(dtype)])
    weights = torch.cat([torch.ones(smooth.shape[0], dtype=dtype, device=bf.device), fw])
    smooth_mask = bc.constrained
    return ids, normals, weights, smooth_mask


def _system(mesh, boundary_weight: float, ids, normals, weights):
    """``(K, Pen, b)`` of the quadratic energy ``q^T (K + Pen) q - 2 b^T q`` (+ const).

    ``K = Lap (x) I_9`` (uniform graph Laplacian over tet edges), ``Pen`` and ``b`` the
    weighted boundary rows ``w sum_c weight_c ||A_c q_{v_c} - t_c||^2`` (scipy, float64).
    """
    V = mesh.vertices.shape[0]
    e = mesh.edges.cpu().numpy()
    # uniform graph Laplacian (Ray et al. use the Dirichlet energy of the SH coefficients; the
    # uniform weights keep the system an M-matrix on any tet mesh, unlike tet cotan weights)
    ones = np.ones(e.shape[0])
    Adj = sp.coo_matrix((np.r_[ones, ones], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(V, V)).tocsr()
    Lap = sp.diags(np.asarray(Adj.sum(1)).ravel()) - Adj
    K = sp.kron(Lap, sp.identity(9), format="csr")
    A, t = boundary_constraint(normals.to(torch.float64))
    w = (boundary_weight * weights.to(torch.float64))[:, None, None]
    AtA = (w * (A.transpose(-1, -2) @ A)).cpu().numpy()  # (C, 9, 9)
    Atb = (w[..., 0] * (A.transpose(-1, -2) @ t[..., None])[..., 0]).cpu().numpy()  # (C, 9)
    vid = ids.cpu().numpy()
    rows = (9 * vid[:, None, None] + np.arange(9)[None, :, None]).repeat(9, 2)
    cols = (9 * vid[:, None, None] + np.arange(9)[None, None, :]).repeat(9, 1)
    Pen = sp.coo_matrix((AtA.ravel(), (rows.ravel(), cols.ravel())), shape=(9 * V, 9 * V)).tocsr()
    b = np.zeros(9 * V)
    np.add.at(b, (9 * vid[:, None] + np.arange(9)[None, :]).ravel(), Atb.ravel())
    return K, Pen, b


def _solve_linear(mesh, boundary_weight: float, ids, normals, weights, cg_rtol: float = 1e-10,
                  cg_maxiter: int = 20000) -> torch.Tensor:
    """Minimize ``sum_edges ||q_i - q_j||^2 + w sum_c weight_c ||A_c q_{v_c} - t_c||^2`` (sparse LS)."""
    V = mesh.vertices.shape[0]
    dtype = normals.dtype
    K, Pen, b = _system(mesh, boundary_weight, ids, normals, weights)
    M = (K + Pen).tocsr()
    # SPD system: Jacobi-preconditioned conjugate gradients (far faster here than SuperLU, whose
    # fill-in on 9 coupled channels of a 3D mesh is large)
    diag = M.diagonal()
    if np.any(diag <= 0):
        raise ValueError("SH system has an isolated vertex (no edge and no boundary constraint)")
    x, info = spla.cg(M, b, M=sp.diags(1.0 / diag), rtol=cg_rtol, maxiter=cg_maxiter)
    if info != 0 or not np.all(np.isfinite(x)):
        raise RuntimeError(f"SH linear solve did not converge (cg info={info}, rtol={cg_rtol}, maxiter={cg_maxiter})")
    return torch.as_tensor(x.reshape(V, 9), dtype=dtype, device=normals.device)


def _project_frames(q, smooth_mask, vnorm, n_restarts: int) -> torch.Tensor:
    """Step 3: nearest frames of ``q (V, 9)``; non-feature boundary frames snapped to ``±n_i``."""
    F = sh_to_frame(q, n_restarts=n_restarts).clone()
    F[smooth_mask] = _snap_axis(F[smooth_mask], vnorm[smooth_mask])
    return F


def sh_frame_field(
    mesh,
    boundary_weight: float = 100.0,
    n_smooth_iters: int = 30,
    feature_angle_deg: float = 30.0,
    n_restarts: int = 8,
    return_sh: bool = False,
):
    """Boundary-aligned smooth octahedral frame field (Ray, Sokolov & Lévy 2016).

    Steps:
      - (1) Boundary constraints (Sec. 4): at each non-feature boundary vertex the normal ``n_i``
        (area-weighted); at each feature vertex (endpoint of a boundary edge sharper than
        ``feature_angle_deg``) one constraint per incident boundary face normal, weighted by
        the face's area fraction — several normals can then be matched at once (box corners).
      - (2) Linear step: minimize ``sum_edges ||q_i - q_j||^2`` (uniform weights over tet edges)
        ``+ boundary_weight * sum_c weight_c ||A_c q - t_c||^2`` (:func:`boundary_constraint`),
        a sparse SPD system solved by Jacobi-preconditioned conjugate gradients
        (``scipy.sparse.linalg.cg``, relative residual ``1e-10``).
      - (3) Projection: each ``q_i`` normalized and projected to the nearest frame
        (:func:`sh_to_frame`); non-feature boundary frames snapped so an axis equals ``±n_i``.
      - (4) Nonlinear step (the paper's optimization in the frame domain): frames
        ``F_i = exp(hat(w_i)) F_i^0`` with ``w_i = phi_i n_i`` restricted to the normal at
        non-feature boundary vertices (alignment stays exact), minimizing the same energy with
        ``q_i = frame_to_sh(F_i)`` (unit, exactly octahedral) by L-BFGS for
        ``n_smooth_iters`` iterations (0 skips it).

    Args:
        mesh: a ``TetMesh`` with a non-empty boundary.
        boundary_weight: penalty weight of the boundary constraints (relative to unit edge
            weights).
        n_smooth_iters: L-BFGS iterations of step 4.
        feature_angle_deg: sharp-edge threshold.
        n_restarts: restarts of the per-vertex projection.
        return_sh: also return the linear-step SH vectors ``(V, 9)``.

    Returns:
        ``frames (V, 3, 3)`` in the mesh dtype/device (``frames[i][:, k]`` = axis ``k`` at vertex
        ``i`` in world coordinates); with ``return_sh`` the tuple ``(frames, q)``.
    """
    for name in ("vertices", "edges", "boundary_faces", "boundary_vertices", "boundary_vertex_normals"):
        if not hasattr(mesh, name):
            raise TypeError(f"sh_frame_field expects a TetMesh; {type(mesh).__name__} has no {name!r}")
    if mesh.boundary_faces.shape[0] == 0:
        raise ValueError("sh_frame_field needs a mesh with a boundary (no boundary faces found)")
    if not boundary_weight > 0:
        raise ValueError(f"boundary_weight must be positive, got {boundary_weight}")
    dtype = mesh.vertices.dtype
    ids, normals, weights, smooth_mask = _penalty_rows(mesh, feature_angle_deg, dtype)
    q = _solve_linear(mesh, boundary_weight, ids, normals, weights)

    vnorm = BoundaryConstraint.from_mesh(mesh, feature_angle_deg).normals.to(dtype)
    sm = smooth_mask
    F0 = _project_frames(q, sm, vnorm, n_restarts)

    if n_smooth_iters > 0:
        F0 = _nonlinear_smooth(mesh, F0, vnorm, sm, ids, normals, weights, boundary_weight, n_smooth_iters)
    return (F0, q) if return_sh else F0


def _nonlinear_smooth(mesh, F0, vnorm, smooth_mask, ids, normals, weights, boundary_weight, n_iters):
    """L-BFGS on per-vertex rotation updates (step 4 of :func:`sh_frame_field`)."""
    dtype = F0.dtype
    e0, e1 = mesh.edges[:, 0], mesh.edges[:, 1]
    feat = ~smooth_mask[ids]
    fid = ids[feat]
    A, t = boundary_constraint(normals[feat])
    fw = boundary_weight * weights[feat]
    # rotation vectors restricted to the normal at smooth boundary vertices
    s = smooth_mask.to(dtype)[:, None]
    w = torch.zeros_like(F0[:, :, 0], requires_grad=True)

    def frames_of(w):
        w_eff = w - s * (w - (w * vnorm).sum(-1, keepdim=True) * vnorm)
        return so3.exp(w_eff) @ F0

    def energy(w):
        q = frame_to_sh(frames_of(w))
        E = ((q[e0] - q[e1]) ** 2).sum()
        if fid.numel():
            r = (A @ q[fid][..., None])[..., 0] - t
            E = E + (fw * (r**2).sum(-1)).sum()
        return E

    opt = torch.optim.LBFGS([w], lr=1.0, max_iter=n_iters, history_size=10, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)

    def closure():
        opt.zero_grad()
        E = energy(w)
        E.backward()
        return E

    with torch.enable_grad():
        opt.step(closure)
    with torch.no_grad():
        return so3.project_to_rotation(frames_of(w))
