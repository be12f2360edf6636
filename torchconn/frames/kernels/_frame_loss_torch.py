"""The generic (torch) kernel of ``torchconn::frame_loss``: the five terms over the mesh tables.

:func:`terms` evaluates the frame-field loss terms of the op (definitions:
:mod:`torchconn.frames.kernels.frame_loss`) in torch operations on any device and floating
dtype, with leading batch dims; it is differentiable to any order (the matchings are index
choices), so the op's generic kernel and its backward take their gradients from it by
``torch.func.vjp`` (inside the kernel too: ``torch.func`` runs below the autograd dispatch keys),
and double backward / Hessian-vector products differentiate it again. The same formulas as
``csrc/frame_loss.c``; the loss's modules (:mod:`torchconn.frames.terms`) compute the same terms
through the library's operators, and the tests hold the three to round-off.
"""
from __future__ import annotations

import torch

__all__ = ["terms", "sweep", "face_regular"]


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


def _dot(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Frobenius product over the last two dims, kept as ``(..., 1, 1)``."""
    return (A * B).sum((-2, -1), keepdim=True)


def _best(M: torch.Tensor, g9: torch.Tensor) -> torch.Tensor:
    """``argmax_k tr(g_kᵀ M)`` (first maximal index) for ``M (..., 3, 3)``: one GEMM on the 24 scores."""
    return (M.reshape(-1, 9) @ g9.t()).max(-1).indices.reshape(M.shape[:-2])


def _element(idx: torch.Tensor, g9: torch.Tensor) -> torch.Tensor:
    return g9.index_select(0, idx.reshape(-1)).reshape(*idx.shape, 3, 3)


def _t(M: torch.Tensor) -> torch.Tensor:
    return M.transpose(-1, -2)


def _face_rot(edge_rot: torch.Tensor, face_edges: torch.Tensor):
    """``(R_ab, R_bc, R_ac)``, each ``(*B, F, 3, 3)``."""
    F = face_edges.shape[0]
    return edge_rot.index_select(-3, face_edges.reshape(-1)).unflatten(-3, (F, 3)).unbind(-3)


def face_regular(edge_rot: torch.Tensor, face_edges: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
    """``(*B, F)`` bool: the holonomy ``R_ab R_bc R_acᵀ`` is nearest the identity of O (no gradient)."""
    with torch.no_grad():
        Rab, Rbc, Rac = _face_rot(edge_rot, face_edges)
        return _best(Rab @ Rbc @ _t(Rac), group.to(edge_rot.dtype).reshape(24, 9)) == 0


def terms(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, face_edges: torch.Tensor,
          edge_vec: torch.Tensor, face_area: torch.Tensor, group: torch.Tensor, on, power: float,
          eps: float) -> torch.Tensor:
    """The values ``(*B, 5)`` of :func:`sweep`: differentiable to any order (autograd, ``torch.func``)."""
    return sweep(edge_rot, frames, edges, face_edges, edge_vec, face_area, group, on, power, eps)[0]


def sweep(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, face_edges: torch.Tensor,
          edge_vec: torch.Tensor, face_area: torch.Tensor, group: torch.Tensor, on, power: float, eps: float,
          wts: torch.Tensor | None = None):
    """``(values (*B, 5), grad_rot | None, grad_frames | None)``: ``smooth, tie, flat, torsion,
    dirichlet`` (0 for a term that is off) and, with ``wts``, the gradient of ``Σ_k w_k term_k``.

    Args:
        edge_rot: ``(*B, E, 3, 3)``; frames: ``(*B, V, 3, 3)`` (one batch shape).
        edges, face_edges, edge_vec, face_area: the tables of
            :func:`torchconn.frames.kernels.frame_loss.mesh_tables` (``face_edges`` = ``ab, bc, ac``).
        group: ``(24, 3, 3)`` the octahedral group (matchings: first maximal score).
        on: five bools, the terms to evaluate.
        wts: ``(*B, 5)`` (broadcast) weights of the gradient; ``None``: values only.
    """
    smooth, tie, flat, torsion, dirichlet = on
    dt, dev = edge_rot.dtype, edge_rot.device
    g9 = group.to(dt).reshape(24, 9)
    eye = torch.eye(3, dtype=dt, device=dev)
    batch, E, F = edge_rot.shape[:-3], edge_rot.shape[-3], face_edges.shape[0]
    grad = wts is not None
    zero = edge_rot.new_zeros(batch)
    vals = [zero] * 5
    if grad:
        wts = wts.to(dt).expand(*batch, 5)
        w = [wts[..., k, None, None, None] for k in range(5)]  # (*B, 1, 1, 1)
        gR = torch.zeros_like(edge_rot, memory_format=torch.contiguous_format)
        gF = torch.zeros_like(frames, memory_format=torch.contiguous_format)
    gFiR = gFi = gFj = None  # per-edge gradients of F_i R, F_i, F_j

    def acc(a, b):
        return b if a is None else a + b

    if smooth:
        D = edge_rot - eye
        d2 = (D**2).sum((-2, -1))
        vals[0] = _rho(d2, power, eps).mean(-1)
        if grad:
            gR += (w[0] * (2.0 / E)) * _drho(d2, power, eps)[..., None, None] * D
    if tie or torsion or dirichlet:
        Fi = frames.index_select(-3, edges[:, 0])
        Fj = frames.index_select(-3, edges[:, 1])
    if tie or torsion:
        FiR = Fi @ edge_rot
        gh = _element(_best(_t(Fj) @ FiR, g9), g9)  # F_j h ~ F_i R_ij
        Fjh = Fj @ gh
        if tie:
            D = FiR - Fjh
            d2 = (D**2).sum((-2, -1))
            vals[1] = _rho(d2, power, eps).mean(-1)
            if grad:
                gFiR = (w[1] * (2.0 / E)) * _drho(d2, power, eps)[..., None, None] * D
                gFj = -(gFiR @ _t(gh))
    if flat or torsion:
        fe = face_edges.reshape(-1)
        Rab, Rbc, Rac = edge_rot.index_select(-3, fe).unflatten(-3, (F, 3)).unbind(-3)
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
        # the matched connection M = R hᵀ carries F_i onto F_j as labeled; A = F_i M F_jᵀ = (F_i R)(F_j h)ᵀ
        # is within ~63 degrees of I (the covering radius of O), where the closed form of √A holds
        A = FiR @ _t(Fjh)
        s = torch.sqrt((1.0 + A.diagonal(dim1=-2, dim2=-1).sum(-1)).clamp_min(1e-30))[..., None, None]
        N = (1.0 + s) * eye + A + (A - _t(A)) / s
        vec = edge_vec.to(dt)[..., None]  # (E, 3, 1)
        u = (N / (2.0 + s)) @ vec  # √A (v_j - v_i)
        th = (_t(Fi) @ u).squeeze(-1)  # (*B, E, 3)
        t = th.index_select(-2, fe).unflatten(-2, (F, 3))  # (*B, F, 3, 3): θ_ab, θ_bc, θ_ac
        hab = gh.index_select(-3, face_edges[:, 0])
        Mab = Rab @ _t(hab)
        Th = t[..., 0, :] + (Mab @ t[..., 1, :, None]).squeeze(-1) - t[..., 2, :]
        area = face_area.to(dt)
        vals[3] = ((Th**2).sum(-1) / area).mean(-1)
        if grad:
            GT = ((wts[..., 3, None] * (2.0 / F)) / area)[..., None] * Th  # dL/dΘ (*B, F, 3)
            gt = torch.stack((GT, (_t(Mab) @ GT[..., None]).squeeze(-1), -GT), -2)  # -> θ_ab, θ_bc, θ_ac
            gth = torch.zeros_like(th).index_add_(-2, fe, gt.flatten(-3, -2))
            gR.index_add_(-3, face_edges[:, 0], (GT[..., :, None] * t[..., 1, None, :]) @ hab)  # dM h
            # θ = F_iᵀ u, u = √A v, A = (F_i R)(F_j h)ᵀ
            gFi = acc(gFi, u @ gth[..., None, :])
            gS = (Fi @ gth[..., None]) @ _t(vec)
            c = (gS.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] / (2.0 + s)
                 - _dot(gS, A - _t(A)) / (s * s * (2.0 + s)) - _dot(gS, N) / (2.0 + s) ** 2) / (2.0 * s)
            gA = gS / (2.0 + s) + (gS - _t(gS)) / (s * (2.0 + s)) + c * eye
            gFiR = acc(gFiR, gA @ Fjh)
            gFj = acc(gFj, (_t(gA) @ FiR) @ _t(gh))
    if dirichlet:
        g = _element(_best(_t(Fi) @ Fj, g9), g9)  # F_i g ~ F_j
        D = Fi @ g - Fj
        vals[4] = (D**2).sum((-2, -1)).mean(-1)
        if grad:
            G = (w[4] * (2.0 / E)) * D
            gFi = acc(gFi, G @ _t(g))
            gFj = acc(gFj, -G)
    if not grad:
        return torch.stack(vals, -1), None, None
    if gFiR is not None:
        gR += _t(Fi) @ gFiR
        gFi = acc(gFi, gFiR @ _t(edge_rot))
    if gFi is not None:
        gF.index_add_(-3, edges[:, 0], gFi)
    if gFj is not None:
        gF.index_add_(-3, edges[:, 1], gFj)
    return torch.stack(vals, -1), gR, gF
