"""Differential and algebraic Bianchi identities as residuals, and a one-call check.

* Differential (report Ch. 5, docs/conventions.md §1): with ``Ω = 𝔡∇w`` (``w = R - I`` as a vector
  1-form with matrix values, :func:`torchconn.dnabla.connection_form`),
  ``⟨𝔡∇Ω,[abcd]⟩_a^d = R_ab(R_bc R_cd - R_bd) - (R_ac R_cd - R_ad) + (R_ab R_bd - R_ad)
  - (R_ab R_bc - R_ac) R_cd = 0`` exactly. :func:`differential_residual` computes it through the
  generic operators (``unsymmetrized_vector`` then ``unsymmetrized_lie``, optionally with
  ``alt_lie`` in between since ``Alt(Ω) = Ω``), never through the closed form.
* Algebraic (Ch. 5): ``d∇d∇θ := 𝔡∇ Alt 𝔡∇ Alt θ̃`` equals the explicit discrete ``Ω∧θ``
  (:func:`torchconn.dnabla.wedge_curvature_solder_tet`) on every tet to round-off.
* Primal-dual (Ch. 4): Def. 4.2 twice equals its curvature-pair form for any dual transports.

Residuals are exact identities, so the threshold is ``get_eps("identity", dtype)`` times a
scale: ``1`` for curvature (rotation entries are O(1)), the tet's largest ``|θ̃|`` for the
algebraic identity, the tet's largest ``|α_e|`` for the primal-dual one.
"""
from __future__ import annotations

import torch

from . import dnabla
from ..tolerances import get_eps

__all__ = [
    "BianchiError",
    "differential_residual",
    "algebraic_residual",
    "primal_dual_residual",
    "assert_residual",
    "check",
]

_TET = torch.tensor([[0, 1, 2, 3]], dtype=torch.long)


class BianchiError(RuntimeError):
    """An exact Bianchi identity failed beyond round-off (or produced NaN/inf)."""


def _norm_or_raw(res: torch.Tensor, reduce: bool, value_nd: int) -> torch.Tensor:
    if not reduce:
        return res
    return torch.linalg.vector_norm(res, dim=tuple(range(-value_nd, 0)))


def differential_residual(edge_rot: torch.Tensor, mesh, reduce: bool = True, *, alternate: bool = False) -> torch.Tensor:
    """Differential Bianchi residual ``⟨𝔡∇Ω,[abcd]⟩_a^d`` on every tet (Ch. 5).

    ``Ω = unsymmetrized_vector(T, connection_form(T), matrix_values=True)`` on the triangles the
    next step reads (``[123], [023], [013], [012]``; all 24 orderings with ``alternate``), then
    ``unsymmetrized_lie`` at ``[0123]`` (evaluation ``tets[t,0]``, cut ``tets[t,3]``). With
    ``alternate=True`` the averaged ``d∇Ω = 𝔡∇ Alt Ω`` (Def. 5.2, Lie Alt of Ch. 5) is used.

    Args:
        edge_rot: ``(*batch, E, n, n)`` rotations of ``mesh.edges`` (``batch`` may be empty);
            mesh: a ``TetMesh``.
        reduce: return Frobenius norms ``(*batch, T)``; else the raw residual ``(*batch, T, n, n)``.
    """
    res = _differential(dnabla.tet_transports(edge_rot, mesh), alternate)
    return _norm_or_raw(res, reduce, 2)


def _differential(T: torch.Tensor, alternate: bool) -> torch.Tensor:
    faces = dnabla.faces_of(_TET)  # the four triangles 𝔡∇ reads on [0123]
    need = dnabla.permutations_of(faces) if alternate else faces  # Alt reads all reorderings
    w = dnabla.connection_form(T)
    omega = dnabla.ListForm(dnabla.unsymmetrized_vector(T, w, need, matrix_values=True), need)
    if alternate:
        omega = dnabla.ListForm(dnabla.alt_lie(T, omega, faces), faces)
    return dnabla.unsymmetrized_lie(T, omega, _TET).squeeze(-3)


def algebraic_residual(edge_rot: torch.Tensor, mesh, frames=None, half_rot=None, reduce: bool = True) -> torch.Tensor:
    """Algebraic Bianchi residual ``d∇d∇θ - Ω∧θ`` on every tet (Ch. 5).

    ``d∇d∇θ = 𝔡∇ Alt 𝔡∇ Alt θ̃`` (:func:`torchconn.dnabla.averaged_dd_solder`) minus the explicit
    wedge (:func:`torchconn.dnabla.wedge_solder`), both at ``tets[t,0]``.

    Args:
        edge_rot: ``(*batch, E, n, n)``; mesh: ``TetMesh``; frames ``([*batch,] V, 3, 3)`` and
            half_rot ``(*batch, E, n, n)`` as in :func:`torchconn.dnabla.tet_solder_sqrt`.
        reduce: norms ``(*batch, T)``; else raw ``(*batch, T, n)``.
    """
    T = dnabla.tet_transports(edge_rot, mesh)
    theta = dnabla.tet_solder_sqrt(edge_rot, mesh, frames, half_rot)
    res = dnabla.averaged_dd_tet(T, theta) - dnabla.wedge_curvature_solder_tet(T, theta)
    return _norm_or_raw(res, reduce, 1)


def primal_dual_residual(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor,
                         mesh, reduce: bool = True) -> torch.Tensor:
    """Primal-dual residual ``d∇d∇α - Σ_(e,e') ⟨Ω,[c_fe,c_e,c_fe',c_t]⟩ α_e`` on every tet (Ch. 4).

    Arguments as :func:`torchconn.dnabla.primal_dual_dd_mesh` (leading batch dims allowed);
    norms ``(*batch, T)`` or raw ``(*batch, T, n)``.
    """
    res = (dnabla.primal_dual_dd_mesh(tet_face_rot, face_edge_rot, edge_values, mesh)
           - dnabla.primal_dual_wedge_mesh(tet_face_rot, face_edge_rot, edge_values, mesh))
    return _norm_or_raw(res, reduce, 1)


def assert_residual(residual: torch.Tensor, name: str, tol: float | torch.Tensor, k: int = 5) -> float:
    """Raise :class:`BianchiError` if any per-tet residual is NaN/inf or exceeds ``tol``.

    Args:
        residual: ``(*batch, T)`` non-negative residual norms (``batch`` may be empty; a tet is
            reported with the batch item where it is worst relative to ``tol``).
        name: identity name used in the message.
        tol: scalar or ``(*batch, T)`` (broadcastable) per-tet threshold.
        k: how many of the worst tets the message names.

    Returns:
        The maximum residual (a Python float; this synchronizes, by design).

    Raises:
        ValueError: on ``meta`` tensors (a check needs values).
    """
    residual = residual.detach()
    if residual.device.type == "meta":
        raise ValueError(f"{name} Bianchi check: meta tensors carry no values to check; run it on a real device")
    tol = torch.as_tensor(tol, dtype=residual.dtype, device=residual.device).expand_as(residual)
    if residual.ndim > 1:  # worst batch item per tet (NaN first)
        Tn = residual.shape[-1]
        r, t = residual.reshape(-1, Tn), tol.reshape(-1, Tn)
        score = torch.where(torch.isfinite(r), r / t, torch.full_like(r, float("inf")))
        pick = score.argmax(0, keepdim=True)
        residual, tol = r.gather(0, pick).squeeze(0), t.gather(0, pick).squeeze(0)
    bad_nf = ~torch.isfinite(residual)
    if bad_nf.any():
        idx = torch.nonzero(bad_nf).flatten()[:k].tolist()
        raise BianchiError(f"{name} Bianchi residual is NaN/inf on {int(bad_nf.sum())} tets, e.g. tets {idx} "
                           f"(check the edge rotations / geometry of these tets)")
    excess = residual / tol
    over = excess > 1
    if over.any():
        order = torch.argsort(excess, descending=True)[:k]
        order = order[over[order]]
        worst = ", ".join(f"tet {int(i)}: {float(residual[i]):.3e} (tol {float(tol[i]):.1e})" for i in order)
        raise BianchiError(f"{name} Bianchi identity violated on {int(over.sum())} of {residual.numel()} tets; "
                           f"worst {worst}")
    return float(residual.max()) if residual.numel() else 0.0


def check(edge_rot: torch.Tensor, mesh, atol: float | None = None, *, frames=None, half_rot=None,
          dual=None) -> dict[str, float]:
    """Evaluate the exact Bianchi identities on every tet and raise if one fails.

    Args:
        edge_rot: ``(*batch, E, n, n)`` rotations of ``mesh.edges`` (``batch`` may be empty: every
            item is checked, the messages name the tets where an item is worst); mesh: ``TetMesh``.
        atol: relative tolerance (default ``get_eps("identity", dtype)``), multiplied by the
            per-tet scale (1 for the differential identity, ``1 + max |θ̃|`` for the algebraic one,
            ``1 + max |α_e|`` for the primal-dual one).
        frames, half_rot: forwarded to :func:`algebraic_residual`.
        dual: optional ``(tet_face_rot (...,T,4,n,n), face_edge_rot (...,F,3,n,n), edge_values
            (...,E,n))`` for the primal-dual identity.

    Returns:
        ``{"differential": max, "algebraic": max[, "primal_dual": max]}`` (Python floats).

    Raises:
        BianchiError: naming the worst tets and their residuals, or the NaN/inf tets.
        ValueError: on ``meta`` tensors (the check needs values; skipped nowhere silently).
    """
    with torch.no_grad():  # a diagnostic: no graph is needed for the returned floats
        return _check(edge_rot, mesh, atol, frames, half_rot, dual)


def _check(edge_rot, mesh, atol, frames, half_rot, dual) -> dict[str, float]:
    if not torch.is_tensor(edge_rot) or not edge_rot.is_floating_point():
        raise TypeError(f"check: edge_rot must be a floating tensor (..., E, n, n), got "
                        f"{edge_rot.dtype if torch.is_tensor(edge_rot) else type(edge_rot).__name__}")
    eps = get_eps("identity", edge_rot.dtype) if atol is None else float(atol)
    n = edge_rot.shape[-1]
    out = {}
    T = dnabla.tet_transports(edge_rot, mesh)  # shared by both identities
    diff = _norm_or_raw(_differential(T, False), True, 2)
    out["differential"] = assert_residual(diff, "differential", eps * n)
    theta = dnabla.tet_solder_sqrt(edge_rot, mesh, frames, half_rot)
    scale = 1.0 + torch.linalg.vector_norm(theta, dim=-1).flatten(-2).amax(-1)
    alg = torch.linalg.vector_norm(dnabla.averaged_dd_tet(T, theta) - dnabla.wedge_curvature_solder_tet(T, theta), dim=-1)
    out["algebraic"] = assert_residual(alg, "algebraic", eps * n * scale)
    if dual is not None:
        tfr, fer, ev = dual
        pd = primal_dual_residual(tfr, fer, ev, mesh)
        evs = torch.linalg.vector_norm(ev.detach(), dim=-1)[..., mesh.tet_edges.to(ev.device)].amax(-1)
        out["primal_dual"] = assert_residual(pd, "primal-dual", eps * n * (1.0 + evs))
    return out
