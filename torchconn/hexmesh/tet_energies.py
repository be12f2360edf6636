"""Per-tet energies of a map's Jacobians, their derivatives, and the first fold along a step.

The energies of :mod:`.injective` on ``J (T, 3, 3)`` (a map's per-tet Jacobians relative to the
target frames, module docstring there):

* :func:`barrier_terms` — frame fitting ``w_fit |J - I|^2`` plus the shifted symmetric Dirichlet
  barrier ``w_sd (|J|^2 + |adj J|^2 / (det J + eps)^2 - 6)``;
* :func:`untangling_terms` — frame fitting plus Garanzha et al.'s (2021) untangling energy
  ``|J|^2 / (3 chi^(2/3)) + (det J^2 + 1) / (2 chi)``, ``chi = (det J + sqrt(eps^2 + det J^2)) / 2``;

each with its per-tet gradient ``(T, 9)`` and Hessian ``(T, 9, 9)`` in closed form (``det``'s
Hessian and ``J J^T J``'s derivative are constant linear maps), tested equal to batched autograd
(:func:`_rowwise_derivatives`, kept as the reference), the Hessians projected onto the positive
semidefinite cone (:func:`_project_psd`). :func:`first_root` is the first root of the cubic
``det(J + s dJ) + eps`` along a step: the line search's cap.
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["barrier_terms", "untangling_terms", "first_root"]


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


def _chi(d: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """``chi(d, eps) = (d + sqrt(eps^2 + d^2)) / 2``: a smooth positive stand-in for ``max(d, 0)``."""
    return 0.5 * (d + torch.sqrt(eps * eps + d * d))


def _untangling(j: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """Garanzha et al.'s regularized distortion per row of ``j (T, 9)`` (``eps`` scalar tensor):
    ``|J|^2 / (3 chi^(2/3)) + (det^2 + 1) / (2 chi)``, finite for every ``J``, inverted ones
    included, and ``2`` at a rotation."""
    J = j.reshape(-1, 3, 3)
    det = torch.linalg.det(J)
    c = _chi(det, eps)
    return j.square().sum(-1) / (3.0 * c.pow(2.0 / 3.0)) + (det * det + 1.0) / (2.0 * c)


def _rowwise_derivatives(fn, j: torch.Tensor, eps: torch.Tensor, hessian: bool):
    """``(f (T,), g (T, 9), H (T, 9, 9) or None)`` of a per-row function by batched autograd (rows
    are independent: one backward for the gradient, nine more for the Hessian's columns)."""
    with torch.enable_grad():
        jj = j.detach().requires_grad_(True)
        f = fn(jj, eps)
        (g,) = torch.autograd.grad(f.sum(), jj, create_graph=hessian)
        H = None
        if hessian:
            H = torch.stack([torch.autograd.grad(g[:, k].sum(), jj, retain_graph=k < 8)[0] for k in range(9)], 1)
    return f.detach(), g.detach(), H


def _linear_tables(dtype, device):
    """Constant ``(81, 9)`` maps: ``K[(ijkl), (mn)] = e_ikm e_jln`` (the Hessian of ``det`` is
    ``K vec J``), ``A[(ijkl), (lj)] = delta_ik`` and ``B[(ijkl), (ik)] = delta_jl``."""
    E = torch.zeros(3, 3, 3, dtype=dtype, device=device)
    E[0, 1, 2] = E[1, 2, 0] = E[2, 0, 1] = 1.0
    E[0, 2, 1] = E[2, 1, 0] = E[1, 0, 2] = -1.0
    K = torch.einsum("ikm,jln->ijklmn", E, E).reshape(81, 9)
    eye = torch.eye(3, dtype=dtype, device=device)
    A = torch.einsum("ik,la,jb->ijklab", eye, eye, eye).reshape(81, 9)  # picks M_lj
    B = torch.einsum("jl,ia,kb->ijklab", eye, eye, eye).reshape(81, 9)  # picks M_ik
    return K, A, B


def _det_parts(J: torch.Tensor):
    """``det J (T,)``, the cofactor matrix ``C (T, 3, 3)`` (its gradient), and its Hessian
    ``d2 det / dJ_ij dJ_kl = sum_mn e_ikm e_jln J_mn`` as ``(T, 9, 9)``."""
    K, _, _ = _linear_tables(J.dtype, J.device)
    C = _adj(J).transpose(-1, -2)
    det = (J * C).sum((-2, -1)) / 3.0  # Euler: det is cubic, J : C = 3 det
    Hd = (J.reshape(-1, 9) @ K.T).reshape(-1, 9, 9)
    return det, C, Hd


def _sd_derivatives(j: torch.Tensor, eps: torch.Tensor, hessian: bool):
    """``(f, g, H)`` of :func:`_sd` in closed form (the autograd reference is
    :func:`_rowwise_derivatives`, tests). With ``d = det J``, ``C`` its cofactors and
    ``q = |C|^2 = (|J|^4 - |J^T J|^2) / 2``: ``f = |J|^2 + q (d + eps)^-2 - 6``,
    ``dq/dJ = 2 (|J|^2 J - J J^T J)``."""
    T = j.shape[0]
    J = j.reshape(T, 3, 3)
    det, C, Hd = _det_parts(J)
    n2 = j.square().sum(-1)
    JtJ = J.transpose(1, 2) @ J
    JJt = J @ J.transpose(1, 2)
    q = C.square().sum((-2, -1))
    u = det + eps
    h = u.pow(-2)
    gq = 2.0 * (n2[:, None, None] * J - J @ JtJ)
    c9 = C.reshape(T, 9)
    gh = -2.0 * u.pow(-3)[:, None] * c9
    f = n2 + q * h - 6.0
    g = 2.0 * j + h[:, None] * gq.reshape(T, 9) + q[:, None] * gh
    if not hessian:
        return f, g, None
    # D[ij, kl] = d(J J^T J)_ij / dJ_kl = delta_ik (J^T J)_lj + J_il J_kj + delta_jl (J J^T)_ik
    _, A, B = _linear_tables(j.dtype, j.device)
    # the middle term J_il J_kj: the outer product [(il), (kj)] reordered to [(ij), (kl)]
    mid = (j[:, :, None] * j[:, None, :]).reshape(T, 3, 3, 3, 3).permute(0, 1, 4, 3, 2).reshape(T, 9, 9)
    D = (JtJ.reshape(T, 9) @ A.T + JJt.reshape(T, 9) @ B.T).reshape(T, 9, 9) + mid
    Hq = 2.0 * (2.0 * j[:, :, None] * j[:, None, :] + n2[:, None, None] * torch.eye(9, dtype=j.dtype, device=j.device)
                - D)
    Hh = 6.0 * u.pow(-4)[:, None, None] * c9[:, :, None] * c9[:, None, :] - 2.0 * u.pow(-3)[:, None, None] * Hd
    gq9 = gq.reshape(T, 9)
    H = (2.0 * torch.eye(9, dtype=j.dtype, device=j.device) + h[:, None, None] * Hq
         + gq9[:, :, None] * gh[:, None, :] + gh[:, :, None] * gq9[:, None, :] + q[:, None, None] * Hh)
    return f, g, H


def _untangling_derivatives(j: torch.Tensor, eps: torch.Tensor, hessian: bool):
    """``(f, g, H)`` of :func:`_untangling` in closed form: ``f = |J|^2 phi(d) + psi(d)`` with
    ``phi = chi^(-2/3) / 3`` and ``psi = (d^2 + 1) / (2 chi)`` of ``d = det J``, so
    ``g = 2 phi J + (|J|^2 phi' + psi') C`` and
    ``H = 2 phi I + 2 phi' (J (x) C + C (x) J) + (|J|^2 phi'' + psi'') C (x) C + (|J|^2 phi' + psi') d2det``."""
    T = j.shape[0]
    J = j.reshape(T, 3, 3)
    det, C, Hd = _det_parts(J)
    n2 = j.square().sum(-1)
    r = torch.sqrt(eps * eps + det * det)
    chi = 0.5 * (det + r)
    c1 = 0.5 * (1.0 + det / r)  # chi'
    c2 = 0.5 * eps * eps / r.pow(3)  # chi''
    phi = chi.pow(-2.0 / 3.0) / 3.0
    phi1 = -(2.0 / 9.0) * chi.pow(-5.0 / 3.0) * c1
    phi2 = (10.0 / 27.0) * chi.pow(-8.0 / 3.0) * c1 * c1 - (2.0 / 9.0) * chi.pow(-5.0 / 3.0) * c2
    dd1 = det * det + 1.0
    psi = dd1 / (2.0 * chi)
    psi1 = det / chi - dd1 * c1 / (2.0 * chi * chi)
    psi2 = 1.0 / chi - 2.0 * det * c1 / (chi * chi) - dd1 * c2 / (2.0 * chi * chi) + dd1 * c1 * c1 / chi.pow(3)
    c9 = C.reshape(T, 9)
    a1 = n2 * phi1 + psi1
    f = n2 * phi + psi
    g = 2.0 * phi[:, None] * j + a1[:, None] * c9
    if not hessian:
        return f, g, None
    H = (2.0 * phi[:, None, None] * torch.eye(9, dtype=j.dtype, device=j.device)
         + 2.0 * phi1[:, None, None] * (j[:, :, None] * c9[:, None, :] + c9[:, :, None] * j[:, None, :])
         + (n2 * phi2 + psi2)[:, None, None] * c9[:, :, None] * c9[:, None, :] + a1[:, None, None] * Hd)
    return f, g, H


def _project_psd(H: torch.Tensor) -> torch.Tensor:
    """Symmetrize ``(T, 9, 9)`` blocks and clamp the negative eigenvalues of those a Cholesky
    attempt rejects (each block eigen-decomposed at O(1) scale: its own round-off, not the
    largest block's)."""
    if not bool(torch.isfinite(H).all()):
        raise FloatingPointError("the barrier's Hessian overflowed (a tet is nearly flat)")
    H = 0.5 * (H + H.transpose(1, 2))
    _, info = torch.linalg.cholesky_ex(H)
    bad = torch.nonzero(info != 0).flatten()
    if bad.numel():
        Hb = H[bad]
        sc = Hb.abs().amax(dim=(1, 2), keepdim=True).clamp_min(torch.finfo(H.dtype).tiny)
        w, V = torch.linalg.eigh(Hb / sc)
        H[bad] = ((V * w.clamp_min(0.0)[:, None, :]) @ V.transpose(1, 2)) * sc
    return H


def untangling_terms(J: torch.Tensor, eps: float, w_fit: float, *, hessian: bool = True):
    """Per-tet energy, gradient and PSD-projected Hessian of the untangling energy
    ``w_fit |J - I|^2 + |J|^2 / (3 chi^(2/3)) + (det^2 + 1) / (2 chi)`` (``chi`` of ``det J`` and the
    global ``eps``; Garanzha et al. 2021), in the Jacobian's 9 entries: the shapes of
    :func:`barrier_terms`."""
    j = J.reshape(-1, 9)
    eye = torch.eye(3, dtype=J.dtype, device=J.device).reshape(9)
    f, g, H = _untangling_derivatives(j, torch.tensor(float(eps), dtype=J.dtype), hessian)
    f = f + w_fit * (j - eye).square().sum(1)
    g = g + 2.0 * w_fit * (j - eye)
    if hessian:
        H = _project_psd(H) + 2.0 * w_fit * torch.eye(9, dtype=J.dtype, device=J.device)
    return f, g, H


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
        fs, gs, Hs = _sd_derivatives(j, eps, hessian)
        f = f + w_sd * fs
        g = g + w_sd * gs
    if not hessian:
        return f, g, None
    H = 2.0 * w_fit * torch.eye(9, dtype=J.dtype, device=J.device).expand(j.shape[0], 9, 9)
    if w_sd:
        H = H + w_sd * _project_psd(Hs)
    return f, g, H


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
