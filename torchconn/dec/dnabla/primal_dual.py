"""Primal-dual covariant exterior derivative on the generalized dual complex (report Defs. 4.1-4.2).

Values sit at cell barycenters; a face value is ``Σ_e R_{c_f c_e} α_e`` (= 3.3.1 for θ), a tet
value ``Σ_f sign_f R_{c_t c_f} (face value)`` with straight-segment transports between
barycenters (docs/conventions.md, "primal-dual").
"""
from __future__ import annotations

from functools import lru_cache

import torch

from ..transport import pair_list
from .simplex import FACE_EDGE_SIGNS, TET_FACE_SIGNS, TET_FACES

__all__ = [
    "primal_dual_face",
    "primal_dual_tet",
    "primal_dual_dd",
    "primal_dual_wedge",
    "primal_dual_dd_mesh",
    "primal_dual_wedge_mesh",
]

# ----------------------------------------------------------------------------- primal-dual

def _check_pd(rot: torch.Tensor, values: torch.Tensor, m: int, fn: str, what: str) -> None:
    if rot.ndim < 3 or rot.shape[-3] != m or rot.shape[-1] != rot.shape[-2]:
        raise ValueError(f"{fn}: {what} transports must have shape (..., {m}, n, n), got {tuple(rot.shape)}")
    if values.shape[-2:] != (m, rot.shape[-1]):
        raise ValueError(f"{fn}: {what} values must have shape (..., {m}, {rot.shape[-1]}), got {tuple(values.shape)}")


def _signs_like(signs, default, like: torch.Tensor, m: int, fn: str) -> torch.Tensor:
    if signs is None:
        return torch.tensor(default, dtype=like.dtype, device=like.device)
    signs = torch.as_tensor(signs, device=like.device).to(like.dtype)
    if signs.shape[-1:] != (m,):
        raise ValueError(f"{fn}: signs must have shape (..., {m}), got {tuple(signs.shape)}")
    return signs


def primal_dual_face(face_edge_rot: torch.Tensor, edge_values: torch.Tensor, signs=None) -> torch.Tensor:
    """Primal-dual d∇ of an edge-centred 1-form on a triangle (Def. 4.2; eq. 3.3.1 for θ).

    ``⟨d∇α, f⟩_{c_f} = Σ_e sign_e R_{c_f c_e} ⟨α, e⟩_{c_e}``.

    Args:
        face_edge_rot: ``(..., 3, n, n)``, ``R_{c_f c_e}`` (edge barycentre -> face barycentre).
        edge_values: ``(..., 3, n)`` values at ``c_e`` for the edges in their stored orientation.
        signs: ``(..., 3)`` incidence coefficients; default ``(+1, -1, +1)``
            (edges ``bc, ac, ab`` of ``[a<b<c]``, as ``TetMesh.face_edges``).

    Returns:
        ``(..., n)`` at the face barycentre.
    """
    fn = "primal_dual_face"
    _check_pd(face_edge_rot, edge_values, 3, fn, "face-edge")
    sg = _signs_like(signs, FACE_EDGE_SIGNS, edge_values, 3, fn)
    return ((face_edge_rot @ edge_values.unsqueeze(-1)).squeeze(-1) * sg.unsqueeze(-1)).sum(-2)


def primal_dual_tet(tet_face_rot: torch.Tensor, face_values: torch.Tensor, signs=None) -> torch.Tensor:
    """Primal-dual d∇ of a face-centred 2-form on a tet (Def. 4.2).

    ``⟨d∇α, t⟩_{c_t} = Σ_f sign_f R_{c_t c_f} ⟨α, f⟩_{c_f}``.

    Args:
        tet_face_rot: ``(..., 4, n, n)``, ``R_{c_t c_f}``; face ``k`` opposite local vertex ``k``.
        face_values: ``(..., 4, n)`` at ``c_f``.
        signs: ``(..., 4)``; default ``(+1, -1, +1, -1)`` from ``∂[abcd] = [bcd]-[acd]+[abd]-[abc]``.

    Returns:
        ``(..., n)`` at the tet barycentre.
    """
    fn = "primal_dual_tet"
    _check_pd(tet_face_rot, face_values, 4, fn, "tet-face")
    sg = _signs_like(signs, TET_FACE_SIGNS, face_values, 4, fn)
    return ((tet_face_rot @ face_values.unsqueeze(-1)).squeeze(-1) * sg.unsqueeze(-1)).sum(-2)


@lru_cache(maxsize=None)
def _tet_face_edge_table() -> tuple[tuple[tuple[int, ...], ...], tuple[tuple[int, ...], ...]]:
    """Local tet template: ``edge[k][m]`` = pair_list(4) index of the edge opposite slot ``m`` of
    face ``k``; ``coef[k][m]`` = ``TET_FACE_SIGNS[k] * FACE_EDGE_SIGNS[m]`` (orientation i<j)."""
    index = {p: a for a, p in enumerate(pair_list(4))}
    edge, coef = [], []
    for k, (p, q, r) in enumerate(TET_FACES):
        opp = ((q, r), (p, r), (p, q))
        edge.append(tuple(index[e] for e in opp))
        coef.append(tuple(TET_FACE_SIGNS[k] * FACE_EDGE_SIGNS[m] for m in range(3)))
    return tuple(edge), tuple(coef)


@lru_cache(maxsize=None)
def _tet_edge_slots() -> tuple[tuple[int, ...], tuple[int, ...]]:
    """For each local edge (pair_list(4) order): flat slot ``3k+m`` with coefficient ``+1`` and ``-1``."""
    edge, coef = _tet_face_edge_table()
    plus, minus = [0] * 6, [0] * 6
    for k in range(4):
        for m in range(3):
            (plus if coef[k][m] > 0 else minus)[edge[k][m]] = 3 * k + m
    return tuple(plus), tuple(minus)


def _check_pd_tet(tet_face_rot, face_edge_rot, edge_values, fn):
    if tet_face_rot.ndim < 3 or tet_face_rot.shape[-3] != 4 or tet_face_rot.shape[-1] != tet_face_rot.shape[-2]:
        raise ValueError(f"{fn}: tet_face_rot must have shape (..., 4, n, n), got {tuple(tet_face_rot.shape)}")
    n = tet_face_rot.shape[-1]
    if face_edge_rot.shape[-4:] != (4, 3, n, n):
        raise ValueError(f"{fn}: face_edge_rot must have shape (..., 4, 3, {n}, {n}), got {tuple(face_edge_rot.shape)}")
    if edge_values.shape[-2:] != (6, n):
        raise ValueError(f"{fn}: edge_values must have shape (..., 6, {n}), got {tuple(edge_values.shape)}")


def primal_dual_dd(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor) -> torch.Tensor:
    """Primal-dual ``d∇d∇α`` on one tet template (Def. 4.2 twice, Ch. 4).

    ``Σ_f sign_f R_{c_t c_f} Σ_{e ⊂ f} sign_{fe} R_{c_f c_e} α_e``.

    Local template: face ``k`` = ``TET_FACES[k]`` (opposite vertex ``k``, ascending), slot ``m``
    of face ``[p<q<r]`` = the edge opposite its ``m``-th vertex (``qr, pr, pq``).

    Args:
        tet_face_rot: ``(..., 4, n, n)`` ``R_{c_t c_f}``.
        face_edge_rot: ``(..., 4, 3, n, n)`` ``R_{c_f c_e}`` for face ``k``, slot ``m``.
        edge_values: ``(..., 6, n)`` at ``c_e``, local edges in ``pair_list(4)`` order, oriented
            ``i -> j`` with ``i < j``.

    Returns:
        ``(..., n)`` at the tet barycentre.
    """
    fn = "primal_dual_dd"
    _check_pd_tet(tet_face_rot, face_edge_rot, edge_values, fn)
    edge, _ = _tet_face_edge_table()
    idx = torch.tensor(edge, dtype=torch.long, device=edge_values.device)  # (4, 3)
    vals = edge_values[..., idx, :]  # (..., 4, 3, n)
    faces = primal_dual_face(face_edge_rot, vals)  # default FACE_EDGE_SIGNS per slot
    return primal_dual_tet(tet_face_rot, faces)


def primal_dual_wedge(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor) -> torch.Tensor:
    """Curvature-pair form of the primal-dual ``d∇d∇α`` = discrete ``Ω∧α`` (Ch. 4).

    ``Σ_{(e,e')} ⟨Ω,[c_{f_e}, c_e, c_{f_e'}, c_t]⟩_{c_t}^{c_e} α_e`` with the two-prong
    ``R_{c_t c_{f_e}} R_{c_{f_e} c_e} - R_{c_t c_{f_e'}} R_{c_{f_e'} c_e}``: for each tet edge
    ``e = (i<j)``, ``f_e`` is the face in whose induced boundary it appears with coefficient
    ``+1`` and ``f_e'`` the one with ``-1``. Equals :func:`primal_dual_dd` for any transports.
    Same arguments and output as :func:`primal_dual_dd`.
    """
    fn = "primal_dual_wedge"
    _check_pd_tet(tet_face_rot, face_edge_rot, edge_values, fn)
    plus, minus = _tet_edge_slots()
    dev = edge_values.device
    plus = torch.tensor(plus, dtype=torch.long, device=dev)
    minus = torch.tensor(minus, dtype=torch.long, device=dev)
    path = tet_face_rot.unsqueeze(-3) @ face_edge_rot  # (..., 4, 3, n, n): R_{c_t c_f} R_{c_f c_e}
    path = path.flatten(-4, -3)  # (..., 12, n, n), slot 3k+m
    omega = path[..., plus, :, :] - path[..., minus, :, :]  # (..., 6, n, n) two-prongs
    return (omega @ edge_values.unsqueeze(-1)).squeeze(-1).sum(-2)


def _mesh_pd_gather(tet_face_rot, face_edge_rot, edge_values, mesh, fn):
    """Checks (leading batch dims allowed, broadcast together) and the per-tet ``(T, 4, 3)``
    face ids, edge ids and incidence coefficients; returns ``(tf, fe, coef, batch)``."""
    Tn, F, E = mesh.tets.shape[0], mesh.faces.shape[0], mesh.edges.shape[0]
    n = edge_values.shape[-1] if edge_values.ndim >= 2 else -1
    if edge_values.ndim < 2 or edge_values.shape[-2] != E:
        raise ValueError(f"{fn}: edge_values must have shape (..., E, n) with E={E}, got {tuple(edge_values.shape)}")
    if tet_face_rot.ndim < 4 or tet_face_rot.shape[-4:] != (Tn, 4, n, n):
        raise ValueError(f"{fn}: tet_face_rot must have shape (..., T, 4, n, n) = (..., {Tn}, 4, {n}, {n}), "
                         f"got {tuple(tet_face_rot.shape)}")
    if face_edge_rot.ndim < 4 or face_edge_rot.shape[-4:] != (F, 3, n, n):
        raise ValueError(f"{fn}: face_edge_rot must have shape (..., F, 3, n, n) = (..., {F}, 3, {n}, {n}), "
                         f"got {tuple(face_edge_rot.shape)}")
    try:
        batch = tuple(torch.broadcast_shapes(tet_face_rot.shape[:-4], face_edge_rot.shape[:-4], edge_values.shape[:-2]))
    except RuntimeError:
        raise ValueError(f"{fn}: the leading batch dims of tet_face_rot {tuple(tet_face_rot.shape)}, face_edge_rot "
                         f"{tuple(face_edge_rot.shape)} and edge_values {tuple(edge_values.shape)} do not broadcast") from None
    dev = edge_values.device
    tf = mesh.tet_faces.to(dev)
    fe = mesh.face_edges.to(dev)[tf]  # (T, 4, 3) edge ids
    coef = mesh.tet_face_signs.to(dev)[..., None] * mesh.face_edge_signs.to(dev)[tf]  # (T, 4, 3)
    return tf, fe, coef, batch


def _take(x: torch.Tensor, idx: torch.Tensor, dim: int) -> torch.Tensor:
    """``x`` indexed by ``idx (S...)`` along ``dim`` (negative): ``(..., S..., trailing)``."""
    out = x.index_select(dim, idx.reshape(-1))
    return out.reshape(*x.shape[:dim], *idx.shape, *x.shape[dim + 1:] if dim != -1 else ())


def primal_dual_dd_mesh(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor,
                        mesh) -> torch.Tensor:
    """Primal-dual ``d∇d∇α`` on every tet of a mesh (Def. 4.2 twice): ``(*batch, T, n)`` at ``c_t``.

    Args:
        tet_face_rot: ``(*batch, T, 4, n, n)`` ``R_{c_t c_f}`` for ``f = mesh.tet_faces[t, k]``.
        face_edge_rot: ``(*batch, F, 3, n, n)`` ``R_{c_f c_e}`` for ``e = mesh.face_edges[f, m]``.
        edge_values: ``(*batch, E, n)`` at ``c_e``, canonical edge orientation ``mesh.edges``.
        mesh: :class:`torchconn.mesh.TetMesh` (incidence signs ``tet_face_signs``, ``face_edge_signs``).

    The leading dims ``batch`` (may be empty) of the three inputs broadcast together.
    """
    fn = "primal_dual_dd_mesh"
    tf, _, _, _ = _mesh_pd_gather(tet_face_rot, face_edge_rot, edge_values, mesh, fn)
    dev = edge_values.device
    face_vals = primal_dual_face(face_edge_rot, _take(edge_values, mesh.face_edges.to(dev), -2),
                                 mesh.face_edge_signs.to(dev))  # (..., F, n)
    return primal_dual_tet(tet_face_rot, _take(face_vals, tf, -2), mesh.tet_face_signs.to(dev))


def primal_dual_wedge_mesh(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor,
                           mesh) -> torch.Tensor:
    """Curvature-pair form ``Σ_(e,e') ⟨Ω,[c_fe, c_e, c_fe', c_t]⟩_{c_t}^{c_e} α_e`` on every tet: ``(*batch, T, n)``.

    Pairs the two slots (face, edge) of each tet edge by their combined incidence coefficient
    (``+1`` -> ``f_e``, ``-1`` -> ``f_e'``; ``α_e`` in canonical orientation carries the sign of
    the ``+1`` slot, which is ``+1`` by construction). Arguments as :func:`primal_dual_dd_mesh`.
    """
    fn = "primal_dual_wedge_mesh"
    tf, fe, coef, _ = _mesh_pd_gather(tet_face_rot, face_edge_rot, edge_values, mesh, fn)
    Tn = tf.shape[0]
    n = tet_face_rot.shape[-1]
    path = tet_face_rot.unsqueeze(-3) @ _take(face_edge_rot, tf, -4)  # (..., T, 4, 3, n, n)
    path = path.reshape(*path.shape[:-5], Tn, 12, n, n)
    fe, coef = fe.reshape(Tn, 12), coef.reshape(Tn, 12)
    # sort slots by (edge id, coefficient): each edge gives consecutive (-1, +1) slots
    key = fe * 2 + (coef > 0).long()
    order = torch.argsort(key, dim=1)
    path = _take(path.reshape(*path.shape[:-4], Tn * 12, n, n), (order + 12 * torch.arange(Tn, device=order.device)[:, None]), -3)
    fe_sorted = torch.gather(fe, 1, order)
    omega = path[..., 1::2, :, :] - path[..., 0::2, :, :]  # (..., T, 6, n, n): plus-prong minus minus-prong
    vals = _take(edge_values, fe_sorted[:, 1::2], -2)  # (..., T, 6, n)
    return (omega @ vals.unsqueeze(-1)).squeeze(-1).sum(-2)
