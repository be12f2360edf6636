"""The Ch. 5 tetrahedron formulas and their mesh-level evaluation (report Ch. 5, Def. 5.2).

Per-tet dense forms follow the template conventions of :mod:`torchconn.dec.dnabla.simplex`
(``T (..., 4, 4, n, n)``, ``T[..., i, j] = R_{x_i x_j}``; vector values in the fiber of the first
label). The mesh wrappers evaluate ``𝔡∇ Alt 𝔡∇ Alt θ̃`` and the explicit ``Ω∧θ`` on every tet of
a :class:`torchconn.mesh.TetMesh` at once; for ``n = 3`` they run the fused kernel of
:mod:`torchconn.ops`.
"""
from __future__ import annotations

import torch

from ...ops import tet_solder as _ops_tet_solder
from .._batch import ask_op, check_frames, edge_batch, expand_to, on_device
from ..transport import dense_simplex_transports, orient
from .simplex import (
    ListForm, _check_T, averaged, behs21, distinct_tuples, faces_of, solder_form, solder_form_sqrt,
)

__all__ = [
    "wedge_curvature_solder_tet",
    "averaged_dd_tet",
    "behs21_dd_tet",
    "tet_transports",
    "tet_solder_sqrt",
    "averaged_dd_solder",
    "behs21_dd_solder",
    "wedge_solder",
]

# ----------------------------------------------------------------------------- tet formulas

_TET = torch.tensor([[0, 1, 2, 3]], dtype=torch.long)
_TET_FACES = faces_of(_TET)  # once, not per call: torch.unique has a data-dependent size under torch.compile


def _check_tet(T: torch.Tensor, theta: torch.Tensor, fn: str) -> None:
    batch_nd, s, n = _check_T(T, fn)
    if s != 4:
        raise ValueError(f"{fn}: expects tet transports (..., 4, 4, n, n), got {tuple(T.shape)}")
    if theta.shape[-3:] != (4, 4, n):
        raise ValueError(f"{fn}: expects a dense 1-form (..., 4, 4, {n}), got {tuple(theta.shape)}")


def wedge_curvature_solder_tet(T: torch.Tensor, theta_tilde: torch.Tensor) -> torch.Tensor:
    """Explicit discrete ``Ω∧θ`` on a tet ``[abcd]`` at vertex ``a`` (end of report Ch. 5).

    With ``R_xy = T[x, y]`` and ``θ̃_xy = theta_tilde[x, y]`` (labels ``a,b,c,d = 0,1,2,3``)::

        1/6 ( (R_ac R_cb - R_ad R_db) θ̃_ba - (R_ab R_bc - R_ad R_dc) θ̃_ca + (R_ac - R_ab R_bd R_dc) θ̃_cb
            + (R_ab R_bd - R_ac R_cd) θ̃_da - (R_ad - R_ab R_bc R_cd) θ̃_db + (R_ad - R_ab R_bd) θ̃_dc )
      + 1/3 ( (R_ac - R_ab R_bc) θ̃_cb - (R_ad - R_ab R_bd) θ̃_db + (R_ad - R_ab R_bd) θ̃_dc )
      + 1/2 (R_ab R_bc - R_ac) θ̃_cd

    Every bracket is a curvature evaluation; equals ``𝔡∇ Alt 𝔡∇ Alt θ̃`` at ``[abcd]`` to
    round-off whenever ``θ̃_ji = -R_ji θ̃_ij``.

    Args:
        T: ``(..., 4, 4, n, n)``; theta_tilde: ``(..., 4, 4, n)``.

    Returns:
        ``(..., n)`` in the fiber of ``a``.
    """
    _check_tet(T, theta_tilde, "wedge_curvature_solder_tet")
    R = lambda i, j: T[..., i, j, :, :]  # noqa: E731
    th = lambda i, j: theta_tilde[..., i, j, :].unsqueeze(-1)  # noqa: E731
    a, b, c, d = 0, 1, 2, 3
    Rab, Rac, Rad, Rbc, Rbd, Rcd = R(a, b), R(a, c), R(a, d), R(b, c), R(b, d), R(c, d)
    Rcb, Rdb, Rdc = R(c, b), R(d, b), R(d, c)
    RabRbd = Rab @ Rbd
    RabRbc = Rab @ Rbc
    sixth = ((Rac @ Rcb - Rad @ Rdb) @ th(b, a)
             - (RabRbc - Rad @ Rdc) @ th(c, a)
             + (Rac - RabRbd @ Rdc) @ th(c, b)
             + (RabRbd - Rac @ Rcd) @ th(d, a)
             - (Rad - RabRbc @ Rcd) @ th(d, b)
             + (Rad - RabRbd) @ th(d, c))
    third = ((Rac - RabRbc) @ th(c, b)
             - (Rad - RabRbd) @ th(d, b)
             + (Rad - RabRbd) @ th(d, c))
    half = (RabRbc - Rac) @ th(c, d)
    return (sixth / 6.0 + third / 3.0 + half / 2.0).squeeze(-1)


def averaged_dd_tet(T: torch.Tensor, theta_tilde: torch.Tensor) -> torch.Tensor:
    """``⟨d∇d∇θ, [abcd]⟩_a = 𝔡∇ Alt 𝔡∇ Alt θ̃`` at ``[0123]`` (Def. 5.2 twice, docs/conventions.md §1).

    Computed through the generic operators. ``T (..., 4, 4, n, n)``, ``theta_tilde (..., 4, 4, n)``
    -> ``(..., n)`` in the fiber of local vertex 0. Equals :func:`wedge_curvature_solder_tet` to
    round-off. The first Alt is a no-op on ``θ̃`` (``Alt(θ̃)_ij = ½(θ̃_ij - R_ij θ̃_ji) = θ̃_ij``
    since ``θ̃_ji = -R_ji θ̃_ij``); it matters for forms without that symmetry (plain θ).
    """
    _check_tet(T, theta_tilde, "averaged_dd_tet")
    # only distinct-label entries are ever read: 12 pairs -> 24 triples -> 4 faces -> [0123]
    triples = distinct_tuples(4, 3)
    two = ListForm(averaged(T, theta_tilde, triples), triples)
    return averaged(T, two, _TET).squeeze(-2)


def behs21_dd_tet(T: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """BEHS21 twice on the plain solder form at ``[0123]``: ``(R_ab R_bc - R_ac) θ_cd`` (Ch. 4).

    ``T (..., 4, 4, n, n)``, ``theta (..., 4, 4, n)`` -> ``(..., n)`` in the fiber of vertex 0.
    """
    _check_tet(T, theta, "behs21_dd_tet")
    return behs21(T, ListForm(behs21(T, theta, _TET_FACES), _TET_FACES), _TET).squeeze(-2)


# ----------------------------------------------------------------------------- mesh wrappers

def _check_mesh_rot(edge_rot: torch.Tensor, mesh, fn: str) -> tuple[int, ...]:
    """Check ``edge_rot (*batch, E, n, n)`` against the mesh; return ``batch``."""
    if not torch.is_tensor(edge_rot):
        raise ValueError(f"{fn}: edge_rot must be a tensor of shape (..., E, n, n), got {type(edge_rot).__name__}")
    return edge_batch(edge_rot, int(mesh.edges.shape[0]), fn)


def tet_transports(edge_rot: torch.Tensor, mesh) -> torch.Tensor:
    """Dense per-tet transports ``(*batch, T, 4, 4, n, n)``, ``[..., t, i, j] = R_{tets[t,i] tets[t,j]}``.

    Args:
        edge_rot: ``(*batch, E, n, n)`` rotations ``R_ij`` of the canonical edges ``mesh.edges``
            (``batch`` may be empty).
        mesh: a :class:`torchconn.mesh.TetMesh` (uses ``tet_edges``, ``tet_edge_signs``).
    """
    _check_mesh_rot(edge_rot, mesh, "tet_transports")
    dev = edge_rot.device
    pair = orient(edge_rot, on_device(mesh, "tet_edges", dev), on_device(mesh, "tet_edge_signs", dev))
    return dense_simplex_transports(pair, 4)


def _check_frames(frames, mesh, edge_rot, fn):
    """``frames`` ``(V, 3, 3)`` or ``(*batch, V, 3, 3)`` in the dtype/device of ``edge_rot``."""
    V = mesh.vertices.shape[0]
    n = edge_rot.shape[-1]
    if n != 3:
        raise ValueError(f"{fn}: frames need a rank n = 3 connection, got n = {n}")
    check_frames(frames, V, 3, tuple(edge_rot.shape[:-3]), fn)
    return frames.to(device=edge_rot.device, dtype=edge_rot.dtype)


def _tet_points(edge_rot, mesh):
    """``(T, 4, 3)`` vertex positions of every tet (no batch dims: the mesh is shared)."""
    dev = edge_rot.device
    return mesh.vertices.to(device=dev, dtype=edge_rot.dtype)[on_device(mesh, "tets", dev)]


def _frames_of_tets(F: torch.Tensor, mesh, dev) -> torch.Tensor:
    """``(..., T, 4, 3, 3)`` frames of every tet's vertices from ``F (..., V, 3, 3)``."""
    tets = on_device(mesh, "tets", dev)
    return F.index_select(-3, tets.reshape(-1)).reshape(*F.shape[:-3], *tets.shape, 3, 3)


def _tet_theta(edge_rot: torch.Tensor, mesh, frames, fn: str) -> torch.Tensor:
    """Plain per-tet ``θ[..., t, i, j] = F_i^T (v_j - v_i)`` ``(*batch, T, 4, 4, n)`` (fiber of ``tets[t,i]``)."""
    batch = tuple(edge_rot.shape[:-3])
    pts = _tet_points(edge_rot, mesh)
    theta = solder_form(pts)
    if frames is None:
        if edge_rot.shape[-1] != pts.shape[-1]:
            raise ValueError(f"{fn}: rank n={edge_rot.shape[-1]} differs from the ambient dimension "
                             f"{pts.shape[-1]}; the solder form needs n = 3")
        return expand_to(theta, batch)
    F = _frames_of_tets(_check_frames(frames, mesh, edge_rot, fn), mesh, edge_rot.device)  # (..., T, 4, 3, 3)
    out = (F.unsqueeze(-3).transpose(-1, -2) @ theta.unsqueeze(-1)).squeeze(-1)
    return out.expand(*batch, *out.shape[-4:]) if batch else out


def tet_solder_sqrt(edge_rot: torch.Tensor, mesh, frames=None, half_rot=None) -> torch.Tensor:
    """Per-tet dense ``θ̃[..., t, i, j] = √R_ij θ_ij`` ``(*batch, T, 4, 4, n)``, value in the fiber of ``tets[t,i]``.

    Without ``frames`` every fiber uses the global coordinate frame (report Sec. 3.3):
    ``θ_ij = v_j - v_i`` and ``√R_ij = half_rot`` (default ``so3.sqrt(edge_rot)``; pass
    ``half_rot (*batch, E, n, n)`` for ``n != 3`` or for the experiments' ``exp(½ ω_m[v_j - v_i])``).

    With ``frames (V, 3, 3)`` or ``(*batch, V, 3, 3)`` (column ``c`` of ``frames[v]`` = frame
    vector ``c`` of the fiber at ``v`` in ambient coordinates) ``edge_rot`` is read in those
    frames, ``R'_ij = F_i^T R_ij F_j`` with ``R`` in ambient coordinates. The edge midpoint keeps
    the ambient frame as in the report, so ``θ̃'_ij = F_i^T √R_ij (v_j - v_i)`` with
    ``√R_ij = sqrt(F_i R'_ij F_j^T)``, or ``√R_ij = F_i half_rot_ij F_j^T`` when ``half_rot``
    (in vertex frames) is given. This makes the result exactly gauge covariant (``G_i = F_i^T``)
    and keeps ``θ̃_ji = -R'_ji θ̃_ij``. ``edge_rot`` may carry leading batch dims ``batch``;
    the mesh is shared.
    """
    fn = "tet_solder_sqrt"
    batch = _check_mesh_rot(edge_rot, mesh, fn)
    if half_rot is not None and half_rot.shape != edge_rot.shape:
        raise ValueError(f"{fn}: half_rot shape {tuple(half_rot.shape)} must equal edge_rot shape {tuple(edge_rot.shape)}")
    pts = expand_to(_tet_points(edge_rot, mesh), batch)
    if frames is None:
        if half_rot is None:
            if edge_rot.shape[-1] != 3:
                raise ValueError(f"{fn}: half transports √R are computed with so3.sqrt only for n = 3; "
                                 f"pass half_rot for n = {edge_rot.shape[-1]}")
            from ...lie import so3
            half_rot = so3.sqrt(edge_rot)
        if edge_rot.shape[-1] != pts.shape[-1]:
            raise ValueError(f"{fn}: rank n={edge_rot.shape[-1]} differs from the ambient dimension "
                             f"{pts.shape[-1]}; the solder form needs n = 3")
        return solder_form_sqrt(tet_transports(half_rot, mesh), pts)
    from ...lie import so3
    Fv = _check_frames(frames, mesh, edge_rot, fn)
    e = on_device(mesh, "edges", edge_rot.device)
    Fi, Fj = Fv.index_select(-3, e[:, 0]), Fv.index_select(-3, e[:, 1])
    if half_rot is None:
        half_amb = so3.sqrt(Fi @ edge_rot @ Fj.transpose(-1, -2))
    else:
        half_amb = Fi @ half_rot @ Fj.transpose(-1, -2)
    th_amb = solder_form_sqrt(tet_transports(half_amb, mesh), pts)
    F = _frames_of_tets(Fv, mesh, edge_rot.device)  # (..., T, 4, 3, 3)
    return (F.unsqueeze(-3).transpose(-1, -2) @ th_amb.unsqueeze(-1)).squeeze(-1)


def averaged_dd_solder(edge_rot: torch.Tensor, mesh, frames=None, half_rot=None) -> torch.Tensor:
    """Averaged ``d∇d∇θ = 𝔡∇ Alt 𝔡∇ Alt θ̃`` on every tet: ``(*batch, T, n)`` in the fiber of ``tets[t,0]``.

    Report Def. 5.2 twice (docs/conventions.md §1); arguments as in :func:`tet_solder_sqrt`. Divide by
    the tet volume to compare with the smooth ``Ω∧θ``. For ``n = 3`` this is evaluated by the
    fused closed form :func:`torchconn.ops.tet_solder.tet_dd_solder` (the Ch. 5 tet formula, equal to
    the generic ``averaged_dd_tet`` on the dense tables to round-off); other ranks use the
    generic operators. ``edge_rot (*batch, E, n, n)`` may carry leading batch dims (the op is
    asked with them; see :mod:`torchconn.dec._batch` for when the generic operators run instead).
    """
    return _dd_solder(edge_rot, mesh, frames, half_rot, "averaged_dd_solder", averaged_dd_tet)


def _dd_solder(edge_rot, mesh, frames, half_rot, fn, generic) -> torch.Tensor:
    """:func:`averaged_dd_solder` and :func:`wedge_solder` (the same value, two formulas): the
    argument checks (every rank), then the fused ``n = 3`` kernel or ``generic(T, θ̃)`` on the
    dense per-tet tables."""
    _check_mesh_rot(edge_rot, mesh, fn)
    if half_rot is not None and half_rot.shape != edge_rot.shape:
        raise ValueError(f"{fn}: half_rot shape {tuple(half_rot.shape)} must equal edge_rot shape {tuple(edge_rot.shape)}")
    if frames is not None:
        _check_frames(frames, mesh, edge_rot, fn)
    fused = ask_op(lambda: _ops_tet_solder.tet_dd_solder(edge_rot, mesh, half_rot=half_rot, frames=frames),
                   edge_rot, half_rot, frames)
    if fused is not None:
        return fused
    return generic(tet_transports(edge_rot, mesh), tet_solder_sqrt(edge_rot, mesh, frames, half_rot))


def behs21_dd_solder(edge_rot: torch.Tensor, mesh, frames=None) -> torch.Tensor:
    """BEHS21 twice on the plain solder form on every tet: ``(*batch, T, n)``, ``(R_ab R_bc - R_ac) θ_cd`` (Ch. 4)."""
    _check_mesh_rot(edge_rot, mesh, "behs21_dd_solder")
    T = tet_transports(edge_rot, mesh)
    return behs21_dd_tet(T, _tet_theta(edge_rot, mesh, frames, "behs21_dd_solder"))


def wedge_solder(edge_rot: torch.Tensor, mesh, frames=None, half_rot=None) -> torch.Tensor:
    """Explicit Ch. 5 ``Ω∧θ`` (:func:`wedge_curvature_solder_tet`) on every tet: ``(*batch, T, n)`` at ``tets[t,0]``.

    For ``n = 3`` evaluated by the fused regrouping of the same formula
    (:func:`torchconn.ops.tet_solder.tet_dd_solder`); other ranks use the dense tables.
    """
    return _dd_solder(edge_rot, mesh, frames, half_rot, "wedge_solder", wedge_curvature_solder_tet)
