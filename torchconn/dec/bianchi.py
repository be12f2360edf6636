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

The algebraic identity holds for rotations only (``R_ji = R_ijᵀ = R_ij⁻¹``): :func:`check`
first checks that the connection is orthogonal to its dtype's ``get_eps("rotation")``
tolerance and otherwise raises ``ValueError`` naming the worst edge and the remedy
(``so3.project_to_rotation``), rather than a :class:`BianchiError` that would blame the
identity (float32 rotations cast to float64 are orthogonal only to ~1e-7, and then fail the
float64 identity tolerance on almost every tet).

:func:`check` is an eager diagnostic: it reads values into Python floats and raises. It runs
under autograd and inside ``torch.func.grad`` / ``jacrev`` / ``jacfwd`` / ``jvp`` (on the
primal values), but not on a ``torch.func.vmap`` batch (``RuntimeError``: a vmapped item has
no Python value; call it on the whole batch, whose every item it checks) nor inside a
``torch.compile`` graph (it is excluded from compilation, ``torch.compiler.disable``: a graph
break, which ``fullgraph=True`` refuses with ``torch._dynamo.exc.Unsupported`` quoting the
reason; call it outside the compiled function).
"""
from __future__ import annotations

import torch

from . import dnabla
from ..lie._validate import rotation_defects
from ..tolerances import get_eps

__all__ = [
    "BianchiError",
    "differential_residual",
    "algebraic_residual",
    "primal_dual_residual",
    "assert_residual",
    "check",
    "run_check",
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


def _compile_reason(who: str) -> str:
    return (f"{who} is an eager diagnostic (it reads values into Python floats and raises BianchiError), "
            f"so torch.compile runs it outside the graph: a graph break, which fullgraph=True refuses; "
            f"call {who} outside the compiled function")


@torch.compiler.disable(reason=_compile_reason("torchconn.bianchi.check"))
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
        ValueError: the connection is not orthogonal (or has ``det -1``) to the dtype's
            ``get_eps("rotation")`` tolerance, naming the worst edge, its residual
            ``||RᵀR − I||_F`` and ``so3.project_to_rotation`` as the remedy (module doc);
            ``meta`` tensors (the check needs values; skipped nowhere silently).
        RuntimeError: inside ``torch.func.vmap`` (module doc).
        torch._dynamo.exc.Unsupported: inside ``torch.compile(fullgraph=True)`` (module doc).
    """
    return run_check("bianchi.check", edge_rot, mesh, atol, frames=frames, half_rot=half_rot, dual=dual)


def run_check(who: str, edge_rot: torch.Tensor, mesh, atol: float | None = None, *, frames=None, half_rot=None,
              dual=None) -> dict[str, float]:
    """:func:`check` with ``who`` (the caller's name, e.g. ``"BianchiCheck"``) leading its messages."""
    if not torch.is_tensor(edge_rot) or not edge_rot.is_floating_point():
        raise TypeError(f"{who}: edge_rot must be a floating tensor (..., E, n, n), got "
                        f"{edge_rot.dtype if torch.is_tensor(edge_rot) else type(edge_rot).__name__}")
    if _vmapped(edge_rot):
        raise RuntimeError(
            f"{who} cannot run inside torch.func.vmap: it is a diagnostic that reads values into Python "
            f"floats and raises on a failed identity, and a vmapped item has no Python value; call it "
            f"outside vmap on the whole batch (leading batch dims (..., E, 3, 3): every item is checked)")
    with torch.no_grad():  # a diagnostic: no graph is needed for the returned floats
        return _check(who, edge_rot, mesh, atol, frames, half_rot, dual)


def _vmapped(t: torch.Tensor) -> bool:
    """Whether ``t`` is (or wraps, under ``torch.func.grad`` / ``jvp`` levels) a vmap batch."""
    f = torch._C._functorch
    while f.is_functorch_wrapped_tensor(t):
        if f.is_batchedtensor(t):
            return True
        t = f.get_unwrapped(t)
    return False


def _check_orthogonal(who: str, edge_rot: torch.Tensor, mesh) -> float:
    """Raise ``ValueError`` unless every edge rotation is orthogonal with ``det > 0`` to the dtype's
    ``get_eps("rotation")``; return the largest ``||RᵀR − I||_F`` (NaN/inf entries are left to
    the residual checks, which name the tets they reach)."""
    tol = get_eps("rotation", edge_rot.dtype)
    _, not_orth, refl, err, _ = rotation_defects(edge_rot, tol)
    bad = not_orth | refl
    if not bool(bad.any()):
        return float(err.max()) if err.numel() else 0.0
    E, batch = edge_rot.shape[-3], tuple(edge_rot.shape[:-3])
    cast = ""
    if bool(not_orth.any()):
        k = int(torch.where(not_orth, err, -1.0).reshape(-1).argmax())
        worst = float(err.reshape(-1)[k])
        defect = f"||R_eᵀ R_e − I||_F = {worst:.2e}"
        if edge_rot.dtype == torch.float64 and worst < 1e-4:
            cast = " (rotations computed in float32 and cast to float64 are orthogonal only to ~1e-7 to 1e-6)"
    else:
        k = int(refl.reshape(-1).nonzero()[0])
        defect = "det R_e = −1 (a reflection)"
    item, e = divmod(k, E)
    i, j = (int(v) for v in mesh.edges[e].tolist())
    where = f" of batch item {tuple(int(b) for b in torch.unravel_index(torch.tensor(item), batch))}" if batch else ""
    raise ValueError(
        f"{who}: the connection is not a rotation to the {str(edge_rot.dtype).replace('torch.', '')} tolerance "
        f"{tol:.0e} on {int(bad.sum())} of {bad.numel()} edges; worst edge {e} = ({i}, {j}){where}: {defect}. "
        f"The Bianchi identities hold for rotations; project the connection first, "
        f"so3.project_to_rotation(edge_rot){cast}")


def _check(who, edge_rot, mesh, atol, frames, half_rot, dual) -> dict[str, float]:
    if edge_rot.device.type == "meta":
        raise ValueError(f"{who}: meta tensors carry no values to check; run it on a real device")
    eps = get_eps("identity", edge_rot.dtype) if atol is None else float(atol)
    n = edge_rot.shape[-1]
    out = {}
    T = dnabla.tet_transports(edge_rot, mesh)  # shared by both identities (checks the shapes first)
    orth = _check_orthogonal(who, edge_rot, mesh)
    diff = _norm_or_raw(_differential(T, False), True, 2)
    out["differential"] = assert_residual(diff, "differential", eps * n)
    theta = dnabla.tet_solder_sqrt(edge_rot, mesh, frames, half_rot)
    scale = 1.0 + torch.linalg.vector_norm(theta, dim=-1).flatten(-2).amax(-1)
    alg = torch.linalg.vector_norm(dnabla.averaged_dd_tet(T, theta) - dnabla.wedge_curvature_solder_tet(T, theta), dim=-1)
    try:
        out["algebraic"] = assert_residual(alg, "algebraic", eps * n * scale)
    except BianchiError as err:
        if orth > eps:  # orthogonal within the rotation tolerance, but not to round-off
            raise BianchiError(
                f"{err} — note: the connection is orthogonal only to {orth:.1e} (||RᵀR − I||_F, within the "
                f"rotation tolerance {get_eps('rotation', edge_rot.dtype):.0e}); the algebraic identity is "
                f"exact for rotations: project with so3.project_to_rotation(edge_rot)") from None
        raise
    if dual is not None:
        tfr, fer, ev = dual
        pd = primal_dual_residual(tfr, fer, ev, mesh)
        evs = torch.linalg.vector_norm(ev.detach(), dim=-1)[..., mesh.tet_edges.to(ev.device)].amax(-1)
        out["primal_dual"] = assert_residual(pd, "primal-dual", eps * n * (1.0 + evs))
    return out
