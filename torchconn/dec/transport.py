"""Gathering oriented transports from per-edge rotations (the shared primitive of all operators).

Convention (docs/conventions.md §1): ``R_ij`` maps coordinates at ``v_j`` to coordinates at ``v_i``;
``R_ji = R_ij^T``. A connection stores one rotation per *canonically oriented* edge
``edges[e] = (i, j)`` with ``i < j``: ``edge_rot[e] = R_ij``. A cell refers to an edge through
an index and a sign: sign ``+1`` means the cell traverses it as stored (``i -> j``), ``-1`` the
other way, in which case the transport is the transpose.

Local pair order of a simplex with ``s`` vertices ``(x_0, ..., x_{s-1})`` is lexicographic:
``(0,1), (0,2), ..., (0,s-1), (1,2), ..., (s-2,s-1)``; :func:`pair_list` (defined in
:mod:`torchconn.mesh.simplex`, re-exported here) returns it. For a tet
that is ``01, 02, 03, 12, 13, 23``, the order of ``TetMesh.tet_edges``.
"""
from __future__ import annotations

import torch

from ..mesh.simplex import pair_list

__all__ = ["pair_list", "orient", "path_product", "dense_simplex_transports", "transpose"]


def transpose(R: torch.Tensor) -> torch.Tensor:
    """Swap the last two dims (the inverse of a rotation)."""
    return R.transpose(-1, -2)


def orient(edge_rot: torch.Tensor, edge_idx: torch.Tensor, edge_sign: torch.Tensor) -> torch.Tensor:
    """Oriented transports of a batch of edge references.

    Args:
        edge_rot: ``(*batch, E, n, n)`` rotations ``R_ij`` of the canonically oriented edges
            (``batch`` may be empty: leading batch dims of a batch of connections).
        edge_idx: ``(S...)`` integer edge indices (no batch dims: the mesh is shared).
        edge_sign: ``(S...)`` ``+1`` (traverse as stored) or ``-1`` (reverse), same shape.

    Returns:
        ``(*batch, S..., n, n)``: ``edge_rot[..., edge_idx, :, :]`` where the sign is ``+1``,
        its transpose where ``-1``. Differentiable with respect to ``edge_rot``.
    """
    n = edge_rot.shape[-1]
    batch = edge_rot.shape[:-3]
    # index_select (backward: index_add) on the edge dim rather than advanced indexing
    dev = edge_rot.device
    edge_idx, edge_sign = torch.as_tensor(edge_idx, device=dev), torch.as_tensor(edge_sign, device=dev)
    R = edge_rot.index_select(-3, edge_idx.reshape(-1)).reshape(*batch, *edge_idx.shape, n, n)
    return torch.where((edge_sign > 0)[..., None, None], R, R.transpose(-1, -2))


def path_product(rots: torch.Tensor, dim: int = -3) -> torch.Tensor:
    """Ordered product ``R_0 R_1 ... R_{k-1}`` of ``rots (..., k, n, n)`` along ``dim``.

    With the transport convention this maps the fiber at the end of a path to its start
    (``T(p0..pk) = R_{p0p1} ... R_{p(k-1)pk}``). ``k = 0`` gives the identity. The loop runs
    over the (small) path length, never over cells.
    """
    rots = rots.movedim(dim, -3)
    k, n = rots.shape[-3], rots.shape[-1]
    if k == 0:
        eye = torch.eye(n, dtype=rots.dtype, device=rots.device)
        return eye.expand(*rots.shape[:-3], n, n).clone()
    out = rots[..., 0, :, :]
    for a in range(1, k):
        out = out @ rots[..., a, :, :]
    return out


def dense_simplex_transports(pair_rot: torch.Tensor, s: int) -> torch.Tensor:
    """Expand per-pair transports of simplices to a dense ``s x s`` table.

    Args:
        pair_rot: ``(..., P, n, n)`` with ``P = s(s-1)/2`` transports ``R_{x_i x_j}`` in the
            order of :func:`pair_list` (``i < j``).
        s: number of vertices of the simplex.

    Returns:
        ``(..., s, s, n, n)`` table ``T[..., i, j] = R_{x_i x_j}``, identity on the diagonal
        and ``T[..., j, i] = T[..., i, j]^T``.
    """
    pairs = pair_list(s)
    if pair_rot.shape[-3] != len(pairs):
        raise ValueError(f"expected {len(pairs)} pair transports for s={s}, got shape {tuple(pair_rot.shape)}")
    n = pair_rot.shape[-1]
    eye = torch.eye(n, dtype=pair_rot.dtype, device=pair_rot.device).expand(*pair_rot.shape[:-3], n, n)
    rows = []
    index = {p: a for a, p in enumerate(pairs)}
    for i in range(s):
        row = []
        for j in range(s):
            if i == j:
                row.append(eye)
            elif i < j:
                row.append(pair_rot[..., index[(i, j)], :, :])
            else:
                row.append(pair_rot[..., index[(j, i)], :, :].transpose(-1, -2))
        rows.append(torch.stack(row, -3))
    return torch.stack(rows, -4)
