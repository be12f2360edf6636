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

:func:`relax_to_matchings` is one ``"soft"`` round with *prescribed* matchings instead of the
frames' own: the frames follow a singular structure chosen elsewhere (the repair of
:mod:`torchconn.frames.matching_search`).

Measured on the 35 HexMe ``c`` meshes (2026-11-25: ``docs/results/hexme.md`` at commit f4941d1 in git history,
``studies/frame_quality.py``): the
soft path gives the lowest energies but lets the tangent drift where a singular curve meets a
feature curve; the tangent path holds the curves; the checkpoints of both are candidates of
:func:`~torchconn.frames.candidates.connection_candidates`.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..lie import so3
from .kernels.edge_terms import matched_edge_terms
from . import octahedral
from .constraints import BoundaryConstraint
from .loss import axis_angle_loss
from .param import constrained_frames
from .singular import classify_holonomy, face_holonomy_from_matchings

__all__ = ["PATH_KINDS", "DIRICHLET_WEIGHTS", "Checkpoint", "quality_path", "relax_to_matchings", "snap_axes"]

#: Kinds of :func:`quality_path` (module docstring).
PATH_KINDS = ("soft", "tangent")
#: Default Dirichlet weights ``lambda`` of a path, one checkpoint each (the options schema's
#: default). The path ends at 0.5: in every run of the jobs' hex chooser over the 35 HexMe ``c``
#: models of 2026-11-26 and 27 whose job files were kept, every good hex mesh came from an
#: optimized field or a checkpoint at 8, 4 (a tangent path, no longer run), 2, 1 or 0.5, never
#: from the last one, 0.25; its two rounds were a sixth of the paths' time.
DIRICHLET_WEIGHTS = (8.0, 4.0, 2.0, 1.0, 0.5)


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
    a_ref = max(float(a_ref), 1e-4)
    d_ref = max(float(d_ref), 1e-8)
    n_edges = max(int(mesh.edges.shape[0]), 1)
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
    out = []
    for lam in lams:
        for _ in range(rounds):
            with torch.no_grad():
                idx, g = octahedral.match_edges(F, mesh.edges)
                typ = None
                if complex_weight or tv is not None:  # holonomy types of the round's matchings
                    typ = classify_holonomy(face_holonomy_from_matchings(g, mesh)[2])[0]
                ew = None
                if complex_weight:
                    bad = mesh.face_edges[typ == 3].reshape(-1)
                    if bad.numel():
                        ew = torch.ones(mesh.edges.shape[0], dtype=dtype, device=F.device)
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
            F = _lbfgs_round(mesh, F, idx, G, ew, cons, axis, fv, fn, free_v, free_d, iters=iters,
                             s_a=1.0 / (n_edges * a_ref), s_d=lam / (n_edges * d_ref), a_ref=a_ref,
                             feature_weight=feature_weight, tangent_weight=tangent_weight, eps=eps,
                             align_eps=align_eps)
        out.append(Checkpoint(kind, lam, F))
    return out


def _lbfgs_round(mesh, Fb, idx, G, ew, cons, axis, fv, fn, free_v, free_d, *, iters, s_a, s_d, a_ref,
                 feature_weight, tangent_weight, eps, align_eps) -> torch.Tensor:
    """One round of a path: ``iters`` L-BFGS iterations on ``w (V, 3)`` with the matchings ``idx (E,)``
    fixed, from ``Fb (V, 3, 3)``; returns the rotations ``F = exp(hat(w')) Fb`` (detached)."""
    w = torch.zeros_like(Fb[:, :, 0], requires_grad=True)
    opt = torch.optim.LBFGS([w], lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-10, tolerance_change=1e-13)

    def closure():
        opt.zero_grad(set_to_none=True)
        Fc = constrained_frames(w, Fb, cons, axis)
        loss = matched_edge_terms(Fc, mesh.edges, idx, G, ew, s_a=s_a, s_d=s_d, eps=eps)
        if feature_weight and fv.numel():
            loss = loss + feature_weight * axis_angle_loss(Fc[fv], fn, align_eps) / a_ref
        if free_v is not None:
            loss = loss + tangent_weight * axis_angle_loss(Fc[free_v], free_d, align_eps) / a_ref
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    with torch.no_grad():
        return so3.project_to_rotation(constrained_frames(w, Fb, cons, axis))


def relax_to_matchings(mesh, frames: torch.Tensor, matchings: torch.Tensor, *, a_ref: float, d_ref: float,
                       dirichlet_weight: float = 8.0, iters: int = 100, feature_weight: float = 1.0,
                       edge_weights: torch.Tensor | None = None, eps: float = 1e-3, align_eps: float = 1e-3,
                       angle_deg: float = 30.0) -> torch.Tensor:
    """The frames moved towards prescribed edge matchings: one ``"soft"`` round of a path with
    ``matchings`` held.

    Minimizes ``mean_e a_e / a_ref + lambda mean_e ||F_i g_ij - F_j||^2 / D_ref + feature term``
    (module docstring, ``lambda = dirichlet_weight``) with ``g_ij = group()[matchings]`` fixed
    instead of re-matched, by ``iters`` L-BFGS iterations from ``frames``; aligned boundary
    vertices rotate about their normal only. The singular structure of the result's own
    (re-computed) matchings is the prescribed one where the frames moved far enough; it is the
    start of the repair paths of :func:`~torchconn.frames.candidates.connection_candidates`
    (:mod:`torchconn.frames.matching_search`).

    Args:
        mesh: ``TetMesh``.
        frames: ``(V, 3, 3)`` start field.
        matchings: ``(E,)`` long indices into :func:`~torchconn.frames.octahedral.group`, one
            per edge of ``mesh.edges`` (``frames[i] @ g ~ frames[j]`` for the edge ``(i, j)``).
        a_ref, d_ref: normalizations as in :func:`quality_path` (floored the same way).
        edge_weights: ``(E,)`` positive weights of the edges in both edge terms (``None``: 1), e.g.
            heavier on the edges whose matching was changed, so that the frames follow them.

    Returns:
        ``(V, 3, 3)`` rotations, detached.
    """
    E = mesh.edges.shape[0]
    if not torch.is_tensor(matchings) or matchings.shape != (E,) or matchings.is_floating_point():
        raise ValueError(f"relax_to_matchings: matchings must be an ({E},) integer tensor of group indices, got "
                         f"{tuple(matchings.shape) if torch.is_tensor(matchings) else type(matchings).__name__}")
    if matchings.numel() and (int(matchings.min()) < 0 or int(matchings.max()) >= 24):
        raise ValueError("relax_to_matchings: matchings must index the 24 elements of the octahedral group")
    if iters < 1 or not (math.isfinite(dirichlet_weight) and dirichlet_weight >= 0):
        raise ValueError(f"relax_to_matchings: need iters >= 1 and a finite dirichlet_weight >= 0, got "
                         f"{iters}, {dirichlet_weight}")
    dtype = mesh.vertices.dtype
    if edge_weights is not None:
        if not torch.is_tensor(edge_weights) or edge_weights.shape != (E,):
            raise ValueError(f"relax_to_matchings: edge_weights must be an ({E},) tensor")
        if not bool((edge_weights > 0).all()) or not bool(torch.isfinite(edge_weights).all()):
            raise ValueError("relax_to_matchings: edge_weights must be finite and > 0")
        edge_weights = edge_weights.to(dtype=dtype, device=frames.device)
    F = frames.detach().to(dtype)
    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    fv, fn = bc.feature_targets()
    a_ref = max(float(a_ref), 1e-4)
    d_ref = max(float(d_ref), 1e-8)
    n_edges = max(int(E), 1)
    G = octahedral.group(dtype, F.device)
    return _lbfgs_round(mesh, F, matchings.to(F.device), G, edge_weights, bc.constrained, bc.normals.to(dtype), fv,
                        fn.to(dtype), None, None, iters=iters, s_a=1.0 / (n_edges * a_ref),
                        s_d=float(dirichlet_weight) / (n_edges * d_ref), a_ref=a_ref, feature_weight=feature_weight,
                        tangent_weight=0.0, eps=eps, align_eps=align_eps)
