"""Quality paths of a frame field: L-BFGS on the frames along an annealed mean-angle / Dirichlet trade-off.

A *path* moves a start field ``F^0 (V, 3, 3)`` through a sequence of objectives

    L_lambda(F) = mean_e a_e / a_ref  +  lambda mean_e d_e^2 / D_ref  +  feature terms

with ``d_e^2 = ||F_i g_ij - F_j||_F^2`` the matched Dirichlet energy of edge ``(i, j)`` (Ray et al.
2016, Palmer et al. 2020; the metric ``dirichlet_energy_mean`` of
:func:`~torchconn.frames.metrics.frame_metrics`), ``a_e = 2 asin(sqrt(d_e^2 + eps^2) / (2 sqrt 2))``
the smoothed geodesic angle of the same residual rotation (the metric ``smoothness_mean_deg``),
``a_ref``, ``D_ref`` a reference field's mean angle and energy (so both terms are ~1 on any mesh),
and ``lambda`` decreasing over the path (:data:`DIRICHLET_WEIGHTS`): it starts near the Dirichlet
minimum and moves towards the L1 one, and every ``lambda`` leaves a checkpoint (:class:`Checkpoint`).

Each ``lambda`` runs ``rounds`` rounds; a round fixes the matchings ``g_ij``
(:func:`~torchconn.frames.octahedral.match_edges` of the round's start field), which makes the
objective smooth, and runs ``iters`` L-BFGS iterations (strong Wolfe line search) on per-vertex
rotation vectors ``F_i = exp(hat(w_i')) F_i^round`` (:mod:`torchconn.frames.param`); the next round
re-matches. No Python loop runs over mesh elements.

Constraints (:class:`~torchconn.frames.constraints.BoundaryConstraint`), two path kinds
(:data:`PATH_KINDS`):

* every path: at aligned boundary vertices (boundary, not on a feature curve) the frame rotates
  about the normal only, so the axis on the normal stays exact;
* ``"soft"``: feature vertices are free; the feature term is
  ``feature_weight x`` :func:`~torchconn.frames.loss.axis_angle_loss` over
  :meth:`~torchconn.frames.constraints.BoundaryConstraint.feature_targets` (incident face normals and, on
  CAD curves, the curve tangent) divided by ``a_ref``;
* ``"tangent"``: at every vertex inside a feature curve the axis closest to the curve tangent is
  snapped onto it and the frame rotates about the tangent only (exact tangent alignment),
  **except** at the vertices of singular faces of the round's start field (matched holonomy
  ``!= I``, :func:`~torchconn.frames.singular.classify_holonomy` of the round's matchings): there the frame is singular and a
  frame axis along the curve is not defined, so those vertices are free and carry the soft
  tangent term ``tangent_weight x axis_angle_loss / a_ref``. The set is re-detected every round.
  The feature term covers the incident face normals.

Measured on the 35 HexMe ``c`` meshes (``docs/results/hexme.md``, ``studies/frame_quality.py``): the
soft path gives the lowest energies but lets the tangent drift where a singular curve meets a
feature curve; the tangent path holds the curves; the guard of
:func:`~torchconn.frames.polish.quality_polish` picks among the checkpoints of both.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..lie import so3
from . import octahedral
from .constraints import BoundaryConstraint
from .loss import axis_angle_loss
from .param import constrained_frames
from .singular import classify_holonomy, face_holonomy_from_matchings

__all__ = ["PATH_KINDS", "DIRICHLET_WEIGHTS", "Checkpoint", "quality_path", "snap_axes"]

#: Kinds of :func:`quality_path` (module docstring).
PATH_KINDS = ("soft", "tangent")
#: Default Dirichlet weights ``lambda`` of a path, one checkpoint each.
DIRICHLET_WEIGHTS = (8.0, 4.0, 2.0, 1.0, 0.5, 0.25)


@dataclass(frozen=True)
class Checkpoint:
    """One field of a path: ``frames (V, 3, 3)`` after the rounds of weight ``dirichlet_weight``."""

    kind: str
    dirichlet_weight: float
    frames: torch.Tensor


def snap_axes(frames: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Rotate each frame ``(N, 3, 3)`` minimally so that its axis closest to ``±directions (N, 3)``
    (unit) lies exactly on it (a rotation by the angle between the two, about their cross product)."""
    c = (frames * directions[:, :, None]).sum(-2)  # (N, 3): a_k . t
    k = c.abs().argmax(-1, keepdim=True)
    a = torch.gather(frames, -1, k[:, None, :].expand(-1, 3, 1)).squeeze(-1)
    a = a * torch.where(torch.gather(c, -1, k) >= 0, 1.0, -1.0).to(a.dtype)
    v = torch.linalg.cross(a, directions, dim=-1)
    cos = (a * directions).sum(-1)
    K = so3.hat(v)
    # I + K + K^2 / (1 + cos): a . t >= 1/sqrt(3) here, so the denominator is >= 1.5
    R = torch.eye(3, dtype=frames.dtype, device=frames.device) + K + (K @ K) / (1.0 + cos)[:, None, None]
    return so3.project_to_rotation(R @ frames)


def _signed_permutation(g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(index (E, 3, 3), sign (E, 1, 3))`` of signed permutations ``g (E, 3, 3)`` (elements of O):
    ``X @ g == X.gather(-1, index) * sign`` for any ``X (E, 3, 3)``, a gather instead of a matmul."""
    k = g.abs().argmax(-2)  # (E, 3): the row of the nonzero entry of each column
    sign = torch.gather(g, -2, k[:, None, :])  # (E, 1, 3)
    return k[:, None, :].expand(-1, 3, -1).contiguous(), sign


class _EdgeTerms(torch.autograd.Function):
    """``sum_e w_e (s_a a_e + s_d d_e^2)`` of the frames ``F (V, 3, 3)`` with fixed matchings ``g``
    (``w (E,)``, ``None``: all 1).

    ``g`` is given as the :func:`_signed_permutation` pairs of ``g`` and of ``g^T``.
    ``d_e^2 = ||F_i g - F_j||^2 = 6 - 2 <F_i g, F_j>`` (rotations), ``a_e = 2 asin(sqrt(d_e^2 + eps^2)
    / (2 sqrt 2))``. One fused pass instead of an autograd graph over the ``E`` edges: the gradient
    is ``k_e (-2 F_j g^T)`` at ``i`` and ``k_e (-2 F_i g)`` at ``j`` with ``k_e = d(term)/d(d_e^2)``,
    scattered with ``index_add``. Under ``create_graph`` the backward recomputes its parts from
    ``F`` with differentiable torch operations, so second derivatives are exact.
    """

    @staticmethod
    def _parts(F, e0, e1, gi, gs, eps):
        B = F.index_select(0, e1)
        Ag = F.index_select(0, e0).gather(-1, gi) * gs
        d2 = (6.0 - 2.0 * (Ag * B).sum((-2, -1))).clamp_min(0.0)
        r = torch.sqrt(d2 + eps * eps)
        h = (r / (2.0 * math.sqrt(2.0))).clamp(max=1.0 - 1e-12)
        return Ag, B, d2, r, h

    @staticmethod
    def forward(ctx, F, e0, e1, gi, gs, gti, gts, s_a, s_d, eps, weight):
        Ag, B, d2, r, h = _EdgeTerms._parts(F, e0, e1, gi, gs, eps)
        ctx.save_for_backward(F, e0, e1, gi, gs, gti, gts, Ag, B, r, h, weight)
        ctx.s_a, ctx.s_d, ctx.eps = s_a, s_d, eps
        terms = s_a * (2.0 * torch.asin(h)) + s_d * d2
        return (terms * weight).sum() if weight is not None else terms.sum()

    @staticmethod
    def backward(ctx, grad):
        F, e0, e1, gi, gs, gti, gts, Ag, B, r, h, weight = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: rebuild the parts from F so the gradient is differentiable
            Ag, B, _, r, h = _EdgeTerms._parts(F, e0, e1, gi, gs, ctx.eps)
        # d a / d d2 = 2 / sqrt(1 - h^2) * 1 / (2 sqrt 2) * 1 / (2 r)
        k = (-2.0 * grad) * (ctx.s_a / (2.0 * math.sqrt(2.0) * r * torch.sqrt(1.0 - h * h)) + ctx.s_d)
        if weight is not None:
            k = k * weight
        k = k[:, None, None]
        gF = torch.zeros_like(F).index_add_(0, e0, k * (B.gather(-1, gti) * gts)).index_add_(0, e1, k * Ag)
        return gF, None, None, None, None, None, None, None, None, None, None


def quality_path(mesh, start: torch.Tensor, *, kind: str = "soft", a_ref: float, d_ref: float,
                 dirichlet_weights: Sequence[float] = DIRICHLET_WEIGHTS, rounds: int = 2, iters: int = 20,
                 feature_weight: float = 1.0, tangent_weight: float = 0.25, complex_weight: float = 0.0,
                 eps: float = 1e-3, align_eps: float = 1e-3, angle_deg: float = 30.0) -> list[Checkpoint]:
    """One quality path from ``start`` (module docstring): a :class:`Checkpoint` per Dirichlet weight.

    Args:
        mesh: ``TetMesh``.
        start: ``(V, 3, 3)`` start field (non-feature boundary frames aligned to their normals).
        kind: ``"soft"`` or ``"tangent"`` (:data:`PATH_KINDS`).
        a_ref, d_ref: the reference mean angle (radians) and mean matched Dirichlet energy that
            normalize the two terms (floored at ``1e-4`` rad and ``1e-8``: an exact field, e.g. a
            cube's, has both ~0).
        dirichlet_weights: the ``lambda`` of each stage, in order.
        rounds: re-matchings per stage; iters: L-BFGS iterations per round.
        feature_weight, tangent_weight: weights of the feature and (free-vertex) tangent terms.
        complex_weight: ``c >= 0``; each round the edges of the faces whose matched holonomy is
            neither the identity nor a quarter or half turn (complex type,
            :func:`~torchconn.frames.singular.classify_holonomy` of the round's matchings) weigh
            ``1 + c`` in both edge terms: the frames around such a face are pulled together.
        eps: smoothing of the edge angle (radians); align_eps: of the alignment angles.
        angle_deg: feature-edge threshold of the boundary constraint.

    Returns:
        ``[Checkpoint(kind, lambda, frames), ...]``, one per weight, frames detached rotations.
    """
    if kind not in PATH_KINDS:
        raise ValueError(f"quality_path: kind must be one of {PATH_KINDS}, got {kind!r}")
    if rounds < 1 or iters < 1:
        raise ValueError(f"quality_path: need rounds >= 1 and iters >= 1, got {rounds}, {iters}")
    if not (math.isfinite(complex_weight) and complex_weight >= 0):
        raise ValueError(f"quality_path: complex_weight must be finite and >= 0, got {complex_weight}")
    lams = [float(x) for x in dirichlet_weights]
    if not lams or not all(math.isfinite(x) and x >= 0 for x in lams):
        raise ValueError(f"quality_path: dirichlet_weights must be finite numbers >= 0, got {dirichlet_weights}")
    dtype = mesh.vertices.dtype
    F = start.detach().to(dtype)
    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    e0, e1 = mesh.edges[:, 0], mesh.edges[:, 1]
    a_ref = max(float(a_ref), 1e-4)
    d_ref = max(float(d_ref), 1e-8)
    n_edges = max(int(e0.numel()), 1)
    cons0, axis0 = bc.constrained, bc.normals.to(dtype)
    has_curves = bc.tangent_vertices is not None and bool((~bc.tangent_at_corner).any())
    if kind == "tangent" and has_curves:
        inner = ~bc.tangent_at_corner
        tv, td = bc.tangent_vertices[inner], bc.tangent_dirs[inner].to(dtype)
        fv, fn = bc.pair_vertices, bc.pair_normals.to(dtype)
    else:
        tv = td = None
        fv, fn = bc.feature_targets()
        fn = fn.to(dtype)

    G = octahedral.group(dtype, F.device)
    perm_tables = (*_signed_permutation(G), *_signed_permutation(G.transpose(-1, -2)))
    out = []
    for lam in lams:
        for _ in range(rounds):
            with torch.no_grad():
                idx, g = octahedral.match_edges(F, mesh.edges)
                # gathers from the 24 elements' tables (an argmax over (E, 3, 3) per round costs
                # ~12% of a path on HexMe i02u)
                gi, gs, gti, gts = (t[idx] for t in perm_tables)
                typ = None
                if complex_weight or tv is not None:  # holonomy types of the round's matchings
                    typ = classify_holonomy(face_holonomy_from_matchings(g, mesh)[2])[0]
                ew = None
                if complex_weight:
                    bad = mesh.face_edges[typ == 3].reshape(-1)
                    if bad.numel():
                        ew = torch.ones(e0.shape[0], dtype=dtype, device=F.device)
                        ew[bad] = 1.0 + float(complex_weight)
                cons, axis, free_v, free_d = cons0, axis0, None, None
                if tv is not None:
                    on_sing = torch.zeros(F.shape[0], dtype=torch.bool, device=F.device)
                    on_sing[mesh.faces[typ != 0].reshape(-1)] = True
                    lock = ~on_sing[tv]
                    F = F.clone()
                    F[tv[lock]] = snap_axes(F[tv[lock]], td[lock])
                    cons, axis = cons0.clone(), axis0.clone()
                    cons[tv[lock]] = True
                    axis[tv[lock]] = td[lock]
                    if tangent_weight and not bool(lock.all()):
                        free_v, free_d = tv[~lock], td[~lock]
            Fb = F
            w = torch.zeros_like(Fb[:, :, 0], requires_grad=True)
            opt = torch.optim.LBFGS([w], lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe",
                                    tolerance_grad=1e-10, tolerance_change=1e-13)

            def closure():
                opt.zero_grad(set_to_none=True)
                Fc = constrained_frames(w, Fb, cons, axis)
                loss = _EdgeTerms.apply(Fc, e0, e1, gi, gs, gti, gts, 1.0 / (n_edges * a_ref), lam / (n_edges * d_ref),
                                        eps, ew)
                if feature_weight and fv.numel():
                    loss = loss + feature_weight * axis_angle_loss(Fc[fv], fn, align_eps) / a_ref
                if free_v is not None:
                    loss = loss + tangent_weight * axis_angle_loss(Fc[free_v], free_d, align_eps) / a_ref
                loss.backward()
                return loss

            with torch.enable_grad():
                opt.step(closure)
            with torch.no_grad():
                F = so3.project_to_rotation(constrained_frames(w, Fb, cons, axis))
        out.append(Checkpoint(kind, lam, F))
    return out
