"""Per-tet energies of a map's Jacobians, their derivatives, and the first fold along a step.

The energies of :mod:`.injective` on ``J (T, 3, 3)`` (a map's per-tet Jacobians relative to the
target frames, module docstring there):

* :func:`barrier_terms` — frame fitting ``w_fit |J - I|^2`` plus the shifted symmetric Dirichlet
  barrier ``w_sd (|J|^2 + |adj J|^2 / (det J + eps)^2 - 6)``;
* :func:`untangling_terms` — frame fitting plus Garanzha et al.'s (2021) untangling energy
  ``|J|^2 / (3 chi^(2/3)) + (det J^2 + 1) / (2 chi)``, ``chi = (det J + sqrt(eps^2 + det J^2)) / 2``;

each with its per-tet gradient ``(T, 9)`` in closed form and its Hessian ``(T, 9, 9)`` projected
onto the positive semidefinite cone. Both energies are isotropic (functions of ``|J|^2``,
``|adj J|^2`` and ``det J``), so the projected Hessian comes from the Hessian's analytic
eigensystem (:func:`_isotropic_psd`: a signed ``3 x 3`` SVD and a ``3 x 3`` eigenproblem per tet,
Smith et al. 2019) instead of a ``9 x 9`` eigen-decomposition. The references, kept for the
tests: the full Hessians in closed form (:func:`_sd_derivatives`, :func:`_untangling_derivatives`;
``det``'s Hessian and ``J J^T J``'s derivative are constant linear maps), equal to batched autograd
(:func:`_rowwise_derivatives`), and their projection by eigen-decomposition
(:func:`_project_psd`). :func:`first_root` is the first root of the cubic ``det(J + s dJ) + eps``
along a step: the line search's cap.
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


def _det_parts(J: torch.Tensor, hessian: bool = True):
    """``det J (T,)``, the cofactor matrix ``C (T, 3, 3)`` (its gradient), and its Hessian
    ``d2 det / dJ_ij dJ_kl = sum_mn e_ikm e_jln J_mn`` as ``(T, 9, 9)`` (``None`` without ``hessian``)."""
    K, _, _ = _linear_tables(J.dtype, J.device)
    C = _adj(J).transpose(-1, -2)
    det = (J * C).sum((-2, -1)) / 3.0  # Euler: det is cubic, J : C = 3 det
    Hd = (J.reshape(-1, 9) @ K.T).reshape(-1, 9, 9) if hessian else None
    return det, C, Hd


def _sd_derivatives(j: torch.Tensor, eps: torch.Tensor, hessian: bool):
    """``(f, g, H)`` of :func:`_sd` in closed form (the autograd reference is
    :func:`_rowwise_derivatives`, tests). With ``d = det J``, ``C`` its cofactors and
    ``q = |C|^2 = (|J|^4 - |J^T J|^2) / 2``: ``f = |J|^2 + q (d + eps)^-2 - 6``,
    ``dq/dJ = 2 (|J|^2 J - J J^T J)``."""
    T = j.shape[0]
    J = j.reshape(T, 3, 3)
    det, C, Hd = _det_parts(J, hessian)
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


def _untangling_scalars(det: torch.Tensor, eps: torch.Tensor):
    """``(phi, phi', phi'', psi, psi', psi'')`` of ``d = det J`` for :func:`_untangling` (``phi =
    chi^(-2/3) / 3``, ``psi = (d^2 + 1) / (2 chi)``; primes are derivatives in ``d``)."""
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
    return phi, phi1, phi2, psi, psi1, psi2


def _untangling_derivatives(j: torch.Tensor, eps: torch.Tensor, hessian: bool):
    """``(f, g, H)`` of :func:`_untangling` in closed form: ``f = |J|^2 phi(d) + psi(d)`` with
    ``phi = chi^(-2/3) / 3`` and ``psi = (d^2 + 1) / (2 chi)`` of ``d = det J``, so
    ``g = 2 phi J + (|J|^2 phi' + psi') C`` and
    ``H = 2 phi I + 2 phi' (J (x) C + C (x) J) + (|J|^2 phi'' + psi'') C (x) C + (|J|^2 phi' + psi') d2det``."""
    T = j.shape[0]
    J = j.reshape(T, 3, 3)
    det, C, Hd = _det_parts(J, hessian)
    n2 = j.square().sum(-1)
    phi, phi1, phi2, psi, psi1, psi2 = _untangling_scalars(det, eps)
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
    largest block's). The reference of :func:`_isotropic_psd` (tests)."""
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


# pairs (i, j) with the third index k: the twist and flip modes of an isotropic energy's Hessian
_PAIRS = ((0, 1, 2), (0, 2, 1), (1, 2, 0))


def _signed_svd(J: torch.Tensor):
    """``J = U diag(s) V^T`` with ``U, V`` rotations and ``s (T, 3)`` the signed singular values
    (``s_1 >= s_2 >= |s_3|``, ``s_1 s_2 s_3 = det J``)."""
    U, s, Vh = torch.linalg.svd(J)
    du, dv = torch.linalg.det(U), torch.linalg.det(Vh)
    U = torch.cat([U[..., :2], U[..., 2:] * du[:, None, None]], -1)
    Vh = torch.cat([Vh[:, :2], Vh[:, 2:] * dv[:, None, None]], 1)
    s = torch.cat([s[:, :2], s[:, 2:] * (du * dv)[:, None]], 1)
    return U, s, Vh


def _isotropic_psd(J: torch.Tensor, d1: torch.Tensor, d2: torch.Tensor) -> torch.Tensor:
    """The Hessian ``(T, 9, 9)`` (row-major entries of ``J``) of an isotropic energy
    ``Psi(I2, IA, I3)`` of ``J (T, 3, 3)`` — ``I2 = |J|^2``, ``IA = |adj J|^2``, ``I3 = det J`` — projected
    onto the positive semidefinite cone in closed form, from its analytic eigensystem (Smith, De
    Goes & Kim 2019, "Analytic eigensystems for isotropic distortion energies"; the projection is the
    Hessian with its negative eigenvalues set to 0).

    With ``J = U diag(s) V^T`` (:func:`_signed_svd`) the nine eigenvectors are ``U M V^T`` for
    ``M = diag(w)``, ``w`` an eigenvector of the ``3 x 3`` Hessian of ``Psi`` in ``s`` (three
    *scaling* modes), and ``M = (E_ij -+ E_ji) / sqrt(2)`` for each pair ``i < j`` with the third index
    ``k`` (six *twist* / *flip* modes), of eigenvalues (written without a division, so equal singular
    values need no limit)::

        symmetric  M: (dPsi/ds_i - dPsi/ds_j) / (s_i - s_j) = 2 Psi_2 + 2 (s_k^2 - s_i s_j) Psi_A - s_k Psi_3
        antisym.   M: (dPsi/ds_i + dPsi/ds_j) / (s_i + s_j) = 2 Psi_2 + 2 (s_k^2 + s_i s_j) Psi_A + s_k Psi_3

    Args:
        J: ``(T, 3, 3)``.
        d1: ``(T, 3)`` the first derivatives ``(Psi_2, Psi_A, Psi_3)`` in ``(I2, IA, I3)``.
        d2: ``(T, 3, 3)`` the second derivatives in the same order.

    Returns:
        ``(T, 9, 9)`` symmetric positive semidefinite; equal to the Hessian where it is already PSD
        (tested against :func:`_project_psd` of the closed-form Hessians).

    Raises:
        FloatingPointError: a derivative overflowed (``det J + eps`` at 0: a tet nearly flat).
    """
    if not (bool(torch.isfinite(d1).all()) and bool(torch.isfinite(d2).all())):
        raise FloatingPointError("the barrier's Hessian overflowed (a tet is nearly flat)")
    T = J.shape[0]
    U, s, Vh = _signed_svd(J)
    s2 = s * s
    S2 = s2.sum(1, keepdim=True)
    p = torch.stack([s[:, 1] * s[:, 2], s[:, 0] * s[:, 2], s[:, 0] * s[:, 1]], 1)  # d I3 / d s
    g = torch.stack([2.0 * s, 2.0 * s * (S2 - s2), p], 1)  # (T, 3 invariants, 3 s): d I / d s
    eye = torch.eye(3, dtype=J.dtype, device=J.device)
    # second derivatives of the invariants in s
    hA = 4.0 * s[:, :, None] * s[:, None, :]
    hA = hA + torch.diag_embed(2.0 * (S2 - s2) - 4.0 * s2)
    h3 = torch.zeros(T, 3, 3, dtype=J.dtype, device=J.device)
    h3[:, 0, 1] = h3[:, 1, 0] = s[:, 2]
    h3[:, 0, 2] = h3[:, 2, 0] = s[:, 1]
    h3[:, 1, 2] = h3[:, 2, 1] = s[:, 0]
    Hs = (g.transpose(1, 2) @ d2 @ g + 2.0 * d1[:, 0, None, None] * eye + d1[:, 1, None, None] * hA
          + d1[:, 2, None, None] * h3)
    lam_s, W = torch.linalg.eigh(Hs)
    # O[t, a, b] = vec(u_a v_b^T): the rank-one basis of the modes
    O = (U.transpose(1, 2)[:, :, None, :, None] * Vh[:, None, :, None, :]).reshape(T, 3, 3, 9)
    diag = torch.stack([O[:, 0, 0], O[:, 1, 1], O[:, 2, 2]], 1)  # (T, 3, 9)
    modes = [W.transpose(1, 2) @ diag]  # (T, 3, 9) scaling modes
    lams = [lam_s]
    r = 0.5 ** 0.5
    for i, j, k in _PAIRS:
        sk, sij = s[:, k], s[:, i] * s[:, j]
        base = 2.0 * d1[:, 0] + 2.0 * sk * sk * d1[:, 1]
        lams.append(torch.stack([base - 2.0 * sij * d1[:, 1] - sk * d1[:, 2],
                                 base + 2.0 * sij * d1[:, 1] + sk * d1[:, 2]], 1))
        modes.append(torch.stack([r * (O[:, i, j] + O[:, j, i]), r * (O[:, i, j] - O[:, j, i])], 1))
    Q = torch.cat(modes, 1)  # (T, 9 modes, 9 entries)
    lam = torch.cat(lams, 1).clamp_min(0.0)
    return Q.transpose(1, 2) @ (lam[:, :, None] * Q)


def _sd_hessian_psd(J: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """The PSD-projected Hessian ``(T, 9, 9)`` of :func:`_sd` (``Psi = I2 + IA (I3 + eps)^-2 - 6``)
    by :func:`_isotropic_psd`."""
    det = torch.linalg.det(J)
    IA = _adj(J).square().sum((-2, -1))
    u = det + eps
    d1 = torch.stack([torch.ones_like(u), u.pow(-2), -2.0 * IA * u.pow(-3)], 1)
    d2 = torch.zeros(J.shape[0], 3, 3, dtype=J.dtype, device=J.device)
    d2[:, 1, 2] = d2[:, 2, 1] = -2.0 * u.pow(-3)
    d2[:, 2, 2] = 6.0 * IA * u.pow(-4)
    return _isotropic_psd(J, d1, d2)


def _untangling_hessian_psd(J: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """The PSD-projected Hessian ``(T, 9, 9)`` of :func:`_untangling` (``Psi = I2 phi(I3) + psi(I3)``)
    by :func:`_isotropic_psd`."""
    det = torch.linalg.det(J)
    I2 = J.square().sum((-2, -1))
    phi, phi1, phi2, _, psi1, psi2 = _untangling_scalars(det, eps)
    d1 = torch.stack([phi, torch.zeros_like(phi), I2 * phi1 + psi1], 1)
    d2 = torch.zeros(J.shape[0], 3, 3, dtype=J.dtype, device=J.device)
    d2[:, 0, 2] = d2[:, 2, 0] = phi1
    d2[:, 2, 2] = I2 * phi2 + psi2
    return _isotropic_psd(J, d1, d2)


def untangling_terms(J: torch.Tensor, eps: float, w_fit: float, *, hessian: bool = True):
    """Per-tet energy, gradient and PSD-projected Hessian of the untangling energy
    ``w_fit |J - I|^2 + |J|^2 / (3 chi^(2/3)) + (det^2 + 1) / (2 chi)`` (``chi`` of ``det J`` and the
    global ``eps``; Garanzha et al. 2021), in the Jacobian's 9 entries: the shapes of
    :func:`barrier_terms`."""
    j = J.reshape(-1, 9)
    eye = torch.eye(3, dtype=J.dtype, device=J.device).reshape(9)
    e = torch.tensor(float(eps), dtype=J.dtype)
    f, g, _ = _untangling_derivatives(j, e, False)
    f = f + w_fit * (j - eye).square().sum(1)
    g = g + 2.0 * w_fit * (j - eye)
    H = None
    if hessian:
        H = _untangling_hessian_psd(J.reshape(-1, 3, 3), e) + 2.0 * w_fit * torch.eye(
            9, dtype=J.dtype, device=J.device)
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
        symmetric Dirichlet term's Hessian projected onto the PSD cone (its negative eigenvalues
        set to 0, :func:`_isotropic_psd`), so ``H >= 2 w_fit I``.
    """
    j = J.reshape(-1, 9)
    eye = torch.eye(3, dtype=J.dtype, device=J.device).reshape(9)
    r = j - eye
    f = w_fit * r.square().sum(1)
    g = 2.0 * w_fit * r
    Hs = None
    if w_sd:
        fs, gs, _ = _sd_derivatives(j, eps, False)
        f = f + w_sd * fs
        g = g + w_sd * gs
    if not hessian:
        return f, g, None
    H = 2.0 * w_fit * torch.eye(9, dtype=J.dtype, device=J.device).expand(j.shape[0], 9, 9)
    if w_sd:
        H = H + w_sd * _sd_hessian_psd(J.reshape(-1, 3, 3), eps)
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
