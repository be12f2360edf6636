"""The generic (torch) kernel of ``torchconn::frame_loss``: the terms and their gradient.

:func:`sweep` evaluates the four frame-field loss terms (definitions:
:mod:`torchconn.ops.frame_loss`) in torch operations on any device and floating dtype, with
leading batch dims, and, given weights ``w (*B, 4)``, the gradient of ``Σ_k w_k term_k``
written out by hand (the same chain rule as ``csrc/frame_loss.c``; no autograd, so it runs inside
an op kernel, below the autograd dispatch keys, and under any dispatch mode). The values are
ordinary differentiable torch operations: autograd through them (:func:`terms`) is the
reference the hand-written gradient is tested against, and what the backward op's own
autograd differentiates (double backward, Hessian-vector products).
"""
from __future__ import annotations

import torch

__all__ = ["terms", "sweep"]


def _rho(d2: torch.Tensor, power: float, eps: float) -> torch.Tensor:
    """``d2`` for ``power = 2``, else ``(d2 + eps²)^(power/2) - eps^power``."""
    if power == 2.0:
        return d2
    return (d2 + eps * eps) ** (0.5 * power) - eps**power


def _drho(d2: torch.Tensor, power: float, eps: float) -> torch.Tensor:
    """``d rho / d d2``."""
    if power == 2.0:
        return torch.ones_like(d2)
    return (0.5 * power) * (d2 + eps * eps) ** (0.5 * power - 1.0)


def _best(M: torch.Tensor, g9: torch.Tensor) -> torch.Tensor:
    """``argmax_k tr(g_kᵀ M)`` (first maximal index) for ``M (..., 3, 3)``: one GEMM on the 24 scores."""
    return (M.reshape(-1, 9) @ g9.t()).max(-1).indices.reshape(M.shape[:-2])


def _element(idx: torch.Tensor, g9: torch.Tensor) -> torch.Tensor:
    return g9.index_select(0, idx.reshape(-1)).reshape(*idx.shape, 3, 3)


def _t(M: torch.Tensor) -> torch.Tensor:
    return M.transpose(-1, -2)


def _dot(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Frobenius product over the last two dims, kept as ``(..., 1, 1)``."""
    return (A * B).sum((-2, -1), keepdim=True)


def sweep(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, face_edges: torch.Tensor,
          edge_vec: torch.Tensor, face_area: torch.Tensor, group: torch.Tensor, on, power: float, eps: float,
          wts: torch.Tensor | None = None):
    """``(values (*B, 4), grad_rot | None, grad_frames | None)``.

    Args:
        edge_rot: ``(*B, E, 3, 3)``; frames: ``(*B, V, 3, 3)`` (one batch shape).
        edges, face_edges, edge_vec, face_area: the tables of
            :func:`torchconn.ops.frame_loss.mesh_tables` (``face_edges`` = ``ab, bc, ac``).
        group: ``(24, 3, 3)`` the octahedral group (matchings: first maximal score).
        on: ``(smooth, tie, flat, torsion)`` bools; a term that is off is 0 (``torsion`` also
            runs the tie matching, which supplies its mask).
        wts: ``(*B, 4)`` (broadcast) weights of the gradient of ``Σ_k w_k term_k``; ``None``: values only.
    """
    smooth, tie, flat, torsion = on
    dt, dev = edge_rot.dtype, edge_rot.device
    g9 = group.to(dt).reshape(24, 9)
    eye = torch.eye(3, dtype=dt, device=dev)
    batch, E, F = edge_rot.shape[:-3], edge_rot.shape[-3], face_edges.shape[0]
    grad = wts is not None
    zero = edge_rot.new_zeros(batch)
    vals = [zero, zero, zero, zero]
    if grad:
        wts = wts.to(dt).expand(*batch, 4)
        w = [wts[..., k, None, None, None] for k in range(4)]  # (*B, 1, 1, 1)
        gR = torch.zeros_like(edge_rot, memory_format=torch.contiguous_format)
        gF = torch.zeros_like(frames, memory_format=torch.contiguous_format)
        gFiR = gFi = gFj = None  # per-edge gradients of F_i R, F_i, F_j
    if smooth:
        D = edge_rot - eye
        d2 = (D**2).sum((-2, -1))
        vals[0] = _rho(d2, power, eps).mean(-1)
        if grad:
            gR += (w[0] * (2.0 / E)) * _drho(d2, power, eps)[..., None, None] * D
    if tie or torsion:
        Fi = frames.index_select(-3, edges[:, 0])
        Fj = frames.index_select(-3, edges[:, 1])
        FiR = Fi @ edge_rot
        h = _best(_t(Fj) @ FiR, g9)  # F_j h ~ F_i R_ij
        if tie:
            gh = _element(h, g9)
            D = FiR - Fj @ gh
            d2 = (D**2).sum((-2, -1))
            vals[1] = _rho(d2, power, eps).mean(-1)
            if grad:
                gFiR = (w[1] * (2.0 / E)) * _drho(d2, power, eps)[..., None, None] * D
                gFj = -(gFiR @ _t(gh))
    if flat or torsion:
        fe = face_edges.reshape(-1)
        Rf = edge_rot.index_select(-3, fe).unflatten(-3, (F, 3))  # (*B, F, 3, 3, 3): R_ab, R_bc, R_ac
        Rab, Rbc, Rac = Rf.unbind(-3)
    if flat:
        P = Rab @ Rbc
        D = P @ _t(Rac)
        D = D - _element(_best(D, g9), g9)
        vals[2] = (D**2).sum((-2, -1)).mean(-1)
        if grad:
            G = (w[2] * (2.0 / F)) * D
            GR = G @ Rac
            gR.index_add_(-3, fe, torch.stack((GR @ _t(Rbc), _t(Rab) @ GR, _t(G) @ P), -3).flatten(-4, -3))
    if torsion:
        unrel = h == 0
        # safe-where: √ only of the unrelabeled edges' A (angle < ~63°); the others never enter
        A = torch.where(unrel[..., None, None], FiR @ _t(Fj), eye)
        s = torch.sqrt((1.0 + A.diagonal(dim1=-2, dim2=-1).sum(-1)).clamp_min(1e-30))[..., None, None]
        N = (1.0 + s) * eye + A + (A - _t(A)) / s
        vec = edge_vec.to(dt)[..., None]  # (E, 3, 1)
        u = (N / (2.0 + s)) @ vec  # √A (v_j - v_i)
        th = (_t(Fi) @ u).squeeze(-1)  # (*B, E, 3)
        t = th.index_select(-2, fe).unflatten(-2, (F, 3))  # (*B, F, 3, 3): θ_ab, θ_bc, θ_ac
        Th = t[..., 0, :] + (Rab @ t[..., 1, :, None]).squeeze(-1) - t[..., 2, :]
        area = face_area.to(dt)
        per = (Th**2).sum(-1) / area
        ok = unrel.index_select(-1, fe).unflatten(-1, (F, 3)).all(-1)
        n_ok = ok.sum(-1, keepdim=True).clamp_min(1).to(dt)
        vals[3] = (torch.where(ok, per, 0.0).sum(-1, keepdim=True) / n_ok).squeeze(-1)
        if grad:
            k = torch.where(ok, (wts[..., 3, None] * 2.0 / n_ok) / area, 0.0)  # (*B, F)
            GT = k[..., None] * Th  # dL/dΘ
            gt = torch.stack((GT, (_t(Rab) @ GT[..., None]).squeeze(-1), -GT), -2)  # -> θ_ab, θ_bc, θ_ac
            gth = torch.zeros_like(th).index_add_(-2, fe, gt.flatten(-3, -2))
            gR.index_add_(-3, face_edges[:, 0], GT[..., :, None] * t[..., 1, None, :])
            # θ = F_iᵀ u, u = √A v, A = (F_i R) F_jᵀ
            gFi_t = u @ gth[..., None, :]
            gS = (Fi @ gth[..., None]) @ _t(vec)
            c = (gS.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] / (2.0 + s)
                 - _dot(gS, A - _t(A)) / (s * s * (2.0 + s)) - _dot(gS, N) / (2.0 + s) ** 2) / (2.0 * s)
            gA = gS / (2.0 + s) + (gS - _t(gS)) / (s * (2.0 + s)) + c * eye
            gA = torch.where(unrel[..., None, None], gA, 0.0)
            gFiR = gA @ Fj if gFiR is None else gFiR + gA @ Fj
            gFj = _t(gA) @ FiR if gFj is None else gFj + _t(gA) @ FiR
            gFi = gFi_t
    if grad:
        if gFiR is not None:
            gR += _t(Fi) @ gFiR
            gFi = gFiR @ _t(edge_rot) if gFi is None else gFi + gFiR @ _t(edge_rot)
            gF.index_add_(-3, edges[:, 0], gFi)
            gF.index_add_(-3, edges[:, 1], gFj)
        return torch.stack(vals, -1), gR, gF
    return torch.stack(vals, -1), None, None


def terms(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, face_edges: torch.Tensor,
          edge_vec: torch.Tensor, face_area: torch.Tensor, group: torch.Tensor, on, power: float,
          eps: float) -> torch.Tensor:
    """The values ``(*B, 4)`` of :func:`sweep`: differentiable to any order (autograd, ``torch.func``)."""
    return sweep(edge_rot, frames, edges, face_edges, edge_vec, face_area, group, on, power, eps)[0]
