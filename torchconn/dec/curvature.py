"""Discrete curvature of a connection on polygons (report Sec. 3.2; docs/conventions.md §1).

Conventions
-----------
* A polygon is a vertex loop ``[x0, x1, ..., x_{m-1}]``; ``loop_rot (..., m, n, n)`` holds
  ``loop_rot[..., k] = R_{x_k x_{k+1 mod m}}`` (``transport.orient(edge_rot, loop_edges,
  loop_signs)``). ``R_ij`` maps the fiber at ``v_j`` to the fiber at ``v_i``; path products
  ``T(p0..pk) = R_{p0p1} ... R_{p(k-1)pk}`` map the fiber at ``pk`` to the fiber at ``p0``.
* ``x0`` is the evaluation vertex. A cut ``c`` in ``[1, m-1]`` splits the loop into the prongs
  ``gamma1 = x0 -> x1 -> ... -> x_c`` and ``gamma2 = x0 -> x_{m-1} -> ... -> x_c``; the two-prong
  curvature ``<Omega, f>_{x0}^{x_c} = T(gamma1) - T(gamma2)`` maps the fiber at ``x_c`` to the
  fiber at ``x0`` (left index: evaluation fiber, right index: cut fiber).
* ``cut = 0`` means "cut = evaluation": ``gamma1`` is the whole loop and ``gamma2`` is empty, so
  the value is the holonomy form ``R_{x0x1} ... R_{x_{m-1}x0} - I`` (3.2.1). Internally the cut
  ``0`` is the position ``m`` (the end of the unrolled loop), which makes every formula below
  uniform. Negative cuts count from the end like Python indices (``-1`` is ``x_{m-1}``).

Invariants (mirrored by ``tests/test_curvature.py``):

* ``two_prong(L, c) = holonomy(L) @ T(gamma2)``  (the two prongs differ by the loop).
* ``two_prong(L, 0) = holonomy(L)``.
* Summability (3.2.2): two faces traversing a shared chain in opposite directions, evaluated
  with the chain's ends as prongs, add up to the value of their union.
* Gauge ``R'_ij = G_i R_ij G_j^T``: two-prong ``X -> G_{x0} X G_{x_c}^T``; holonomy
  ``X -> G_{x0} X G_{x0}^T``.
* Re-expression: moving the evaluation vertex is a pre-multiplication, moving the cut a
  post-multiplication, by boundary transports (:func:`eval_transport`, :func:`cut_transport`).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..ops import curvature as _ops_curvature
from ._batch import ask_op, edge_batch
from .transport import orient, path_product

__all__ = [
    "holonomy",
    "two_prong",
    "prong_transports",
    "roll",
    "reexpress",
    "eval_transport",
    "cut_transport",
    "merge",
    "face_loops",
    "face_curvature",
]


def _check_loop_rot(loop_rot: torch.Tensor, fn: str) -> tuple[int, int]:
    if loop_rot.ndim < 3 or loop_rot.shape[-1] != loop_rot.shape[-2]:
        raise ValueError(f"{fn}: loop_rot must have shape (..., m, n, n), got {tuple(loop_rot.shape)}")
    m = loop_rot.shape[-3]
    if m < 2:
        raise ValueError(f"{fn}: a loop needs at least 2 edges, got m={m}")
    return m, loop_rot.shape[-1]


def _normalize_cut(cut: Any, m: int, fn: str, what: str = "cut") -> Any:
    """Map a cut (int or integer tensor) in ``[-m, m-1]`` to the position in ``[1, m]``."""
    if isinstance(cut, torch.Tensor):
        if cut.dtype.is_floating_point or cut.dtype == torch.bool:
            raise ValueError(f"{fn}: {what} must be an integer tensor, got dtype {cut.dtype}")
        if cut.numel() and (bool((cut < -m).any()) or bool((cut >= m).any())):
            bad = cut[(cut < -m) | (cut >= m)].flatten()[:5].tolist()
            raise ValueError(f"{fn}: {what} out of range [-{m}, {m - 1}] for a loop of {m} vertices: {bad}")
        c = torch.remainder(cut, m)
        return torch.where(c == 0, torch.full_like(c, m), c)
    if not isinstance(cut, int) or isinstance(cut, bool):
        raise ValueError(f"{fn}: {what} must be an int or an integer tensor, got {type(cut).__name__}")
    if not -m <= cut < m:
        raise ValueError(f"{fn}: {what} {cut} out of range [-{m}, {m - 1}] for a loop of {m} vertices")
    c = cut % m
    return m if c == 0 else c


def _prefix_products(loop_rot: torch.Tensor) -> torch.Tensor:
    """``P[..., k] = loop_rot[..., 0] ... loop_rot[..., k-1]`` for ``k = 0..m`` -> ``(..., m+1, n, n)``.

    ``P[k] = T(x0 .. x_k)`` maps the fiber at ``x_k`` to ``x0`` going forward. Loop over ``m``.
    """
    m, n = loop_rot.shape[-3], loop_rot.shape[-1]
    eye = torch.eye(n, dtype=loop_rot.dtype, device=loop_rot.device).expand(*loop_rot.shape[:-3], n, n)
    out = [eye]
    for k in range(m):
        out.append(out[-1] @ loop_rot[..., k, :, :])
    return torch.stack(out, -3)


def _suffix_products(loop_rot: torch.Tensor) -> torch.Tensor:
    """``S[..., k] = loop_rot[..., k] ... loop_rot[..., m-1]`` for ``k = 0..m`` (``S[m] = I``).

    ``S[k] = T(x_k .. x_m = x0)`` maps the fiber at ``x0`` to ``x_k`` going forward; its transpose
    is the backward prong ``T(x0 -> x_{m-1} -> ... -> x_k)``.
    """
    m, n = loop_rot.shape[-3], loop_rot.shape[-1]
    eye = torch.eye(n, dtype=loop_rot.dtype, device=loop_rot.device).expand(*loop_rot.shape[:-3], n, n)
    out = [eye]
    for k in range(m - 1, -1, -1):
        out.append(loop_rot[..., k, :, :] @ out[-1])
    return torch.stack(out[::-1], -3)


def _gather_k(P: torch.Tensor, c: Any) -> torch.Tensor:
    """Pick ``P[..., c, :, :]`` with ``c`` an int or an integer tensor broadcastable to the batch."""
    if isinstance(c, int):
        return P[..., c, :, :]
    n = P.shape[-1]
    # numpy's broadcast rule (torch.broadcast_shapes lazily imports torch._refs: ~1 s on first use)
    batch = tuple(np.broadcast_shapes(tuple(P.shape[:-3]), tuple(c.shape)))
    P = P.expand(*batch, *P.shape[-3:])
    idx = c.expand(batch)[..., None, None, None].expand(*batch, 1, n, n)
    return torch.gather(P, -3, idx).squeeze(-3)


def prong_transports(loop_rot: torch.Tensor, cut: Any = -1) -> tuple[torch.Tensor, torch.Tensor]:
    """Transports along the two prongs, ``(T(gamma1), T(gamma2))``, each ``(..., n, n)``.

    Both map the cut fiber ``x_c`` to the evaluation fiber ``x0`` (Sec. 3.2): ``gamma1`` runs
    forward ``x0 -> x1 -> ... -> x_c``, ``gamma2`` backward ``x0 -> x_{m-1} -> ... -> x_c``.
    ``cut = 0``: ``gamma1`` is the whole loop, ``T(gamma2) = I``.

    Args:
        loop_rot: ``(..., m, n, n)``, ``loop_rot[..., k] = R_{x_k x_{k+1}}``.
        cut: int or integer tensor broadcastable to the batch dims, in ``[-m, m-1]``.
    """
    m, _ = _check_loop_rot(loop_rot, "prong_transports")
    c = _normalize_cut(cut, m, "prong_transports")
    P = _prefix_products(loop_rot)
    S = _suffix_products(loop_rot)
    return _gather_k(P, c), _gather_k(S, c).transpose(-1, -2)


def holonomy(loop_rot: torch.Tensor) -> torch.Tensor:
    """Holonomy form ``<Omega, f>_{x0} = R_{x0x1} R_{x1x2} ... R_{x_{m-1}x0} - I`` (3.2.1).

    Args:
        loop_rot: ``(..., m, n, n)``, ``loop_rot[..., k] = R_{x_k x_{k+1 mod m}}``, any ``SO(n)``.

    Returns:
        ``(..., n, n)`` in the fiber of the evaluation vertex ``x0`` (an endomorphism of it);
        equals :func:`two_prong` with ``cut=0``. Gauge: ``X -> G_{x0} X G_{x0}^T``.
    """
    m, n = _check_loop_rot(loop_rot, "holonomy")
    eye = torch.eye(n, dtype=loop_rot.dtype, device=loop_rot.device)
    return path_product(loop_rot) - eye


def two_prong(loop_rot: torch.Tensor, cut: Any = -1) -> torch.Tensor:
    """Two-prong curvature ``<Omega, f>_{x0}^{x_c} = T(gamma1) - T(gamma2)`` (report Sec. 3.2).

    ``gamma1 = x0 -> x1 -> ... -> x_c``, ``gamma2 = x0 -> x_{m-1} -> ... -> x_c`` (docs/conventions.md §1).
    On a triangle ``[abc]`` with ``cut=2``: ``R_ab R_bc - R_ac``. ``cut=0`` ("cut = evaluation")
    gives the holonomy form (3.2.1). Relation: ``two_prong = holonomy @ T(gamma2)``.

    Args:
        loop_rot: ``(..., m, n, n)``, ``loop_rot[..., k] = R_{x_k x_{k+1 mod m}}``, any ``SO(n)``.
        cut: position of the cut vertex, int in ``[-m, m-1]`` (default ``-1``: ``x_{m-1}``) or an
            integer tensor broadcastable to the batch dims (one cut per loop).

    Returns:
        ``(..., n, n)`` mapping the fiber at ``x_c`` to the fiber at ``x0``. Gauge covariance:
        ``X -> G_{x0} X G_{x_c}^T``. Differentiable in ``loop_rot``.

    Raises:
        ValueError: bad shape, or cut out of range.
    """
    m, _ = _check_loop_rot(loop_rot, "two_prong")
    c = _normalize_cut(cut, m, "two_prong")
    if isinstance(c, int):
        t1 = path_product(loop_rot[..., :c, :, :])
        t2 = path_product(loop_rot[..., c:, :, :]).transpose(-1, -2)
        return t1 - t2
    t1, t2 = prong_transports(loop_rot, cut)
    return t1 - t2


def roll(loop_rot: torch.Tensor, k: int) -> torch.Tensor:
    """The same loop started at ``x_k``: ``out[..., j] = loop_rot[..., (j + k) mod m]``.

    Use it to evaluate at another vertex: ``two_prong(roll(L, k), (c - k) mod m)`` is
    ``<Omega, f>_{x_k}^{x_c}``.
    """
    m, _ = _check_loop_rot(loop_rot, "roll")
    if not isinstance(k, int) or not -m <= k < m:
        raise ValueError(f"roll: shift {k!r} out of range [-{m}, {m - 1}] for a loop of {m} vertices")
    return torch.roll(loop_rot, shifts=-k, dims=-3)


def reexpress(value: torch.Tensor, pre: torch.Tensor | None = None, post: torch.Tensor | None = None) -> torch.Tensor:
    """Re-express a two-prong value with other prongs: ``pre @ value @ post`` (Sec. 3.2).

    ``pre`` (from :func:`eval_transport`) maps the old evaluation fiber to the new one, ``post``
    (from :func:`cut_transport`) the new cut fiber to the old one. ``None`` means identity.
    """
    out = value
    if pre is not None:
        out = pre @ out
    if post is not None:
        out = out @ post
    return out


def eval_transport(loop_rot: torch.Tensor, cut: int, new_eval: int) -> tuple[torch.Tensor, int]:
    """Pre-multiplier moving the evaluation vertex from ``x0`` to ``x_k`` with the cut kept.

    "Changing the evaluation fiber requires a pre-multiplication by the accumulated parallel
    transport" (Sec. 3.2): the transport from ``x_k`` to ``x0`` along the arc of the loop that
    does not contain the cut, i.e. ``T(x_k -> x_{k-1} -> ... -> x0)`` if ``x_k`` lies on
    ``gamma1`` and ``T(x_k -> x_{k+1} -> ... -> x_m = x0)`` if it lies on ``gamma2``.

    Returns:
        ``(pre (..., n, n), new_cut)`` such that
        ``pre @ two_prong(L, cut) == two_prong(roll(L, new_eval), new_cut)``. With ``cut=0`` (the
        holonomy form) the cut stays at ``x0``, seen from the end of the loop.

    Raises:
        ValueError: ``new_eval`` equals the cut vertex (the prongs would collapse), or out of range.
    """
    m, _ = _check_loop_rot(loop_rot, "eval_transport")
    c = _normalize_cut(cut, m, "eval_transport")
    k = _normalize_cut(new_eval, m, "eval_transport", "new_eval") % m
    if k == c % m and k != 0:
        raise ValueError(f"eval_transport: new evaluation vertex x_{k} is the cut vertex; move the cut first")
    if k == 0:
        n = loop_rot.shape[-1]
        eye = torch.eye(n, dtype=loop_rot.dtype, device=loop_rot.device).expand(*loop_rot.shape[:-3], n, n)
        return eye, cut % m
    if k < c:  # on gamma1: go back along gamma1
        pre = path_product(loop_rot[..., :k, :, :]).transpose(-1, -2)
    else:  # on gamma2: go forward to the end of the loop
        pre = path_product(loop_rot[..., k:, :, :])
    return pre, (c - k) % m


def cut_transport(loop_rot: torch.Tensor, cut: int, new_cut: int) -> torch.Tensor:
    """Post-multiplier moving the cut from ``x_c`` to ``x_{c'}`` with the evaluation kept at ``x0``.

    The transport from ``x_c`` to ``x_{c'}`` along the arc not passing through ``x0`` (Sec. 3.2:
    "the two evaluations only differ by a post-multiplication"): forward
    ``T(x_c -> ... -> x_{c'})`` if ``c < c'``, backward otherwise. A cut of ``0`` is the end of
    the loop, so ``cut_transport(L, c, 0) = T(gamma2)^{-1}`` turns a two-prong value into the
    holonomy form and ``cut_transport(L, 0, c) = T(gamma2)``.

    Returns:
        ``post (..., n, n)`` with ``two_prong(L, cut) @ post == two_prong(L, new_cut)``.
    """
    m, _ = _check_loop_rot(loop_rot, "cut_transport")
    c = _normalize_cut(cut, m, "cut_transport")
    c2 = _normalize_cut(new_cut, m, "cut_transport", "new_cut")
    if c2 >= c:
        return path_product(loop_rot[..., c:c2, :, :])
    return path_product(loop_rot[..., c2:c, :, :]).transpose(-1, -2)


def merge(value_f: torch.Tensor, value_g: torch.Tensor) -> torch.Tensor:
    """Curvature of the 2-chain ``f + g`` from its parts: a plain sum (3.2.2).

    Valid when both values are expressed at the same evaluation vertex and cut, which are the
    two ends of the 1-chain shared by ``f`` and ``g`` (traversed in opposite directions by the
    two faces): ``<Omega,f>_{vi}^{vl} + <Omega,g>_{vi}^{vl} = <Omega,f+g>_{vi}^{vl}``.
    """
    if value_f.shape[-2:] != value_g.shape[-2:]:
        raise ValueError(f"merge: values of shapes {tuple(value_f.shape)} and {tuple(value_g.shape)} differ")
    return value_f + value_g


def _edge_rot_of(edge_rot: Any) -> torch.Tensor:
    """Accept a tensor ``(..., E, n, n)`` or any object with an ``edge_rot`` attribute (``Connection``)."""
    R = getattr(edge_rot, "edge_rot", edge_rot)
    if not isinstance(R, torch.Tensor) or R.ndim < 3 or R.shape[-1] != R.shape[-2]:
        shape = tuple(R.shape) if isinstance(R, torch.Tensor) else type(R).__name__
        raise ValueError(f"edge_rot must be an (..., E, n, n) tensor (optional leading batch dims) "
                         f"or a Connection, got {shape}")
    return R


def face_loops(cells: Any) -> tuple[int, list[tuple[torch.Tensor | None, torch.Tensor, torch.Tensor, torch.Tensor]]]:
    """Faces of a mesh as groups of edge loops: ``(F, [(face_ids, loop_edges, loop_signs, loops), ...])``.

    * ``CellComplex`` (``kind == "cells"``): one entry per face size ``m``.
    * ``TetMesh`` (``kind == "tet"``): the sorted faces
      ``[a<b<c]`` with loop ``a -> b -> c -> a``; edges ``ab, bc, ca`` are ``face_edges[:, [2, 0, 1]]``
      with the incidence signs of ``d[abc] = [bc] - [ac] + [ab]`` (``+1, +1, -1``: ``c -> a``
      runs against the canonical edge ``(a, c)``).

    ``face_ids`` is ``None`` when the faces are already in global order. The mesh kind is read
    from ``kind`` (not ``isinstance``) so that :class:`torchconn.nn.MeshBuffers` is accepted.
    """
    kind = getattr(cells, "kind", None)
    if kind == "cells":
        groups = []
        F = 0
        for m, g in sorted(cells.face_groups.items()):
            groups.append((g.face_ids, g.loop_edges, g.loop_signs, g.loops))
            F += int(g.face_ids.numel())
        return F, groups
    if kind == "tet":
        perm = [2, 0, 1]
        return int(cells.faces.shape[0]), [(None, cells.face_edges[:, perm], cells.face_edge_signs[:, perm], cells.faces)]
    raise ValueError(
        f"expected a CellComplex or a TetMesh (kind 'cells' or 'tet'), got {type(cells).__name__}"
    )


def face_curvature(edge_rot: Any, cells: Any, cut: int = -1, kind: str = "two_prong") -> torch.Tensor:
    """Curvature of every face of a mesh, batched per face size (Sec. 3.2, (3.2.1)).

    Args:
        edge_rot: ``(*batch, E, n, n)`` rotations ``R_ij`` of the canonical edges ``(i<j)`` of
            ``cells`` (``batch`` may be empty: a batch of connections on one mesh), or a
            ``Connection`` (its ``edge_rot`` is used). Any ``SO(n)``.
        cells: a ``CellComplex`` (faces of any size, evaluation vertex = first vertex of each
            loop) or a ``TetMesh`` (sorted faces ``[a<b<c]``, loop ``a -> b -> c``).
        cut: cut position in each loop, ``[-m, m-1]`` for every face size present (default
            ``-1``: the last vertex; on a tet-mesh face that is ``c``, giving
            ``<Omega,[abc]>_a^c = R_ab R_bc - R_ac``). Ignored for ``kind="holonomy"``.
        kind: ``"two_prong"`` or ``"holonomy"`` (``R_{x0x1} ... R_{x_{m-1}x0} - I``).

    Returns:
        ``(*batch, F, n, n)`` in global face order; face ``f``'s value maps the fiber of its cut
        vertex to the fiber of its evaluation vertex.

    The op :func:`torchconn.ops.curvature.face_curvature` is asked first (sorted triangles;
    with the batched tensor), else the loop formula below (:mod:`torchconn.dec._batch`). Works
    under ``vmap`` and ``torch.func.jvp`` and on ``meta`` tensors.
    """
    if kind not in ("two_prong", "holonomy"):
        raise ValueError(f"face_curvature: kind must be 'two_prong' or 'holonomy', got {kind!r}")
    R = _edge_rot_of(edge_rot)
    E = getattr(cells, "edges", None)
    batch = edge_batch(R, int(E.shape[0]), "face_curvature") if E is not None else tuple(R.shape[:-3])
    # sorted triangles [a<b<c]: the written-out products of the op (same values), else None
    fused = ask_op(lambda: _ops_curvature.face_curvature(R, cells, cut=cut, kind=kind), R)
    if fused is not None:
        return fused
    F, groups = face_loops(cells)
    n = R.shape[-1]
    out = R.new_zeros(*batch, F, n, n) if groups[0][0] is not None else None
    for face_ids, le, ls, _ in groups:
        if le.device.type != "meta" and le.numel() and int(le.max()) >= R.shape[-3]:
            raise ValueError(f"face_curvature: edge index {int(le.max())} out of range for {R.shape[-3]} edge rotations")
        L = orient(R, le.to(R.device), ls.to(R.device))
        val = holonomy(L) if kind == "holonomy" else two_prong(L, cut)
        if face_ids is None:
            return val
        out = out.index_copy(-3, face_ids.to(out.device), val)
    return out
