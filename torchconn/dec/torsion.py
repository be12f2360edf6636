"""Discrete torsion of a connection with a solder form (report Sec. 3.3; docs/conventions.md §1, §3).

Conventions
-----------
* Polygon ``[x0, ..., x_{m-1}]``, ``loop_rot[..., k] = R_{x_k x_{k+1 mod m}}`` (fiber of
  ``x_{k+1}`` -> fiber of ``x_k``), evaluation vertex ``x0``, cut ``c`` as in
  :mod:`torchconn.curvature`: ``gamma1 = x0 -> ... -> x_c``, ``gamma2 = x0 -> x_{m-1} -> ... -> x_c``;
  ``cut = 0`` means ``gamma1`` is the whole loop and ``gamma2`` is empty (loop torsion).
* A vector-valued 1-form is given per loop edge in both directions:
  ``theta_fwd[..., k]`` is its value on ``x_k -> x_{k+1}``, stored in the fiber of ``x_k``;
  ``theta_bwd[..., k]`` its value on ``x_{k+1} -> x_k``, stored in the fiber of ``x_{k+1}``.
* Torsion values are vectors in the fiber of the evaluation vertex ``x0`` (Def. 3.2);
  a gauge ``G`` acts as ``Theta -> G_{x0} Theta``. Barycentric torsion (3.3.1) lives in the fiber
  of the face centroid.

Variants: :func:`naive` (``theta_ij = v_j - v_i``, does not converge), :func:`sqrt`
(``theta~_ij = sqrt(R_ij) theta_ij``, Def. 3.2, converges), :func:`barycentric` (3.3.1).
"""
from __future__ import annotations

from typing import Any

import torch

from ..ops import torsion as _ops_torsion
from ..lie import so3
from .curvature import _check_loop_rot, _edge_rot_of, _normalize_cut, _prefix_products, _suffix_products, face_loops
from ._batch import ask_op, check_frames, edge_batch, on_device
from .transport import orient

__all__ = ["two_prong", "naive", "sqrt", "barycentric", "solder_form", "face_torsion"]


def _check_theta(theta: torch.Tensor, m: int, n: int, what: str) -> None:
    if theta.ndim < 2 or theta.shape[-2:] != (m, n):
        raise ValueError(f"torsion: {what} must have shape (..., {m}, {n}) to match loop_rot, got {tuple(theta.shape)}")


def two_prong(loop_rot: torch.Tensor, theta_fwd: torch.Tensor, theta_bwd: torch.Tensor, cut: Any = -1) -> torch.Tensor:
    """Prong-sum torsion ``<Theta, f>_{x0}^{x_c}`` of Def. 3.2 for any edge values.

    ``sum_{k<c} T(x0..x_k) theta_fwd[k]  -  sum_{k>=c} T(x0 -> x_{m-1} -> ... -> x_{k+1}) theta_bwd[k]``:
    along ``gamma1`` every oriented edge ``x_k -> x_{k+1}`` contributes its value carried back to
    ``x0`` by the forward prefix; along ``gamma2`` every edge ``x_{k+1} -> x_k`` its value carried
    back to ``x0`` by the backward prefix.

    Args:
        loop_rot: ``(..., m, n, n)`` loop transports.
        theta_fwd: ``(..., m, n)`` values on ``x_k -> x_{k+1}`` in the fiber of ``x_k``.
        theta_bwd: ``(..., m, n)`` values on ``x_{k+1} -> x_k`` in the fiber of ``x_{k+1}``.
        cut: int in ``[-m, m-1]`` or integer tensor broadcastable to the batch dims
            (``0``: the loop sum, ``gamma2`` empty).

    Returns:
        ``(..., n)`` vector in the fiber of ``x0``. Differentiable in all tensor inputs.
    """
    m, n = _check_loop_rot(loop_rot, "torsion.two_prong")
    _check_theta(theta_fwd, m, n, "theta_fwd")
    _check_theta(theta_bwd, m, n, "theta_bwd")
    c = _normalize_cut(cut, m, "torsion.two_prong")
    P = _prefix_products(loop_rot)[..., :m, :, :]  # P[k] = T(x0..x_k): fiber x_k -> x0
    Q = _suffix_products(loop_rot)[..., 1:, :, :].transpose(-1, -2)  # Q[k] = T(x0 -> back -> x_{k+1})
    fwd = (P @ theta_fwd[..., None]).squeeze(-1)  # (..., m, n)
    bwd = (Q @ theta_bwd[..., None]).squeeze(-1)
    k = torch.arange(m, device=loop_rot.device)
    if isinstance(c, int):
        on1 = (k < c).to(loop_rot.dtype)
    else:
        on1 = (k < c[..., None]).to(loop_rot.dtype)
    return (on1[..., None] * fwd - (1 - on1)[..., None] * bwd).sum(-2)


def _loop_edge_vectors(loop_points: torch.Tensor) -> torch.Tensor:
    if loop_points.ndim < 2:
        raise ValueError(f"torsion: loop_points must have shape (..., m, d), got {tuple(loop_points.shape)}")
    return torch.roll(loop_points, shifts=-1, dims=-2) - loop_points


def naive(loop_rot: torch.Tensor, loop_points: torch.Tensor, cut: Any = -1) -> torch.Tensor:
    """Naive discrete torsion with the plain solder form ``theta_ij = v_j - v_i`` (Sec. 3.3).

    ``theta_fwd[k] = x_{k+1} - x_k``, ``theta_bwd[k] = x_k - x_{k+1}``, not transported. The
    report shows that this "suggestive definition" does not converge to the smooth torsion
    (the frame rotation along an edge is counted twice); it is kept as the baseline.

    Args:
        loop_rot: ``(..., m, n, n)``; loop_points: ``(..., m, n)`` vertex coordinates (the frame
            of every vertex is the global one); cut as in :func:`two_prong`.

    Returns:
        ``(..., n)`` in the fiber of ``x0``.
    """
    d = _loop_edge_vectors(loop_points)
    return two_prong(loop_rot, d, -d, cut)


def sqrt(loop_rot: torch.Tensor, loop_half_rot: torch.Tensor, loop_points: torch.Tensor, cut: Any = -1) -> torch.Tensor:
    """Torsion of Def. 3.2 with the half-transported solder form (report Sec. 3.3).

    ``theta~_{x_k x_{k+1}} = H_k (x_{k+1} - x_k)`` with ``H_k = loop_half_rot[..., k]`` the transport
    from the midpoint of the edge to ``x_k`` (``sqrt(R_{x_k x_{k+1}})`` in the report), and the
    reverse value ``theta~_{x_{k+1} x_k} = -R_{x_{k+1} x_k} theta~_{x_k x_{k+1}}`` (docs/conventions.md §1,
    erratum 9). The edge vector ``x_{k+1} - x_k`` is read in the frame of the edge midpoint; a
    gauge ``G`` at the vertices (midpoint frames kept) acts by ``H_k -> G_{x_k} H_k``,
    ``R_ij -> G_i R_ij G_j^T`` and then ``Theta -> G_{x0} Theta``.

    Args:
        loop_rot: ``(..., m, n, n)`` loop transports ``R_{x_k x_{k+1}}``.
        loop_half_rot: ``(..., m, n, n)`` half transports ``H_k``.
        loop_points: ``(..., m, n)`` the loop's vertices.
        cut: as in :func:`two_prong`.

    Returns:
        ``(..., n)`` in the fiber of ``x0``.
    """
    m, n = _check_loop_rot(loop_rot, "torsion.sqrt")
    if loop_half_rot.shape[-3:] != loop_rot.shape[-3:]:
        raise ValueError(f"torsion.sqrt: loop_half_rot {tuple(loop_half_rot.shape)} must match loop_rot {tuple(loop_rot.shape)}")
    d = _loop_edge_vectors(loop_points)
    fwd = (loop_half_rot @ d[..., None]).squeeze(-1)
    bwd = -(loop_rot.transpose(-1, -2) @ fwd[..., None]).squeeze(-1)
    return two_prong(loop_rot, fwd, bwd, cut)


def barycentric(center_to_edge_rot: torch.Tensor, edge_vectors: torch.Tensor) -> torch.Tensor:
    """Barycentric torsion ``<Theta, f>_{c_f} = sum_e R_{c_f, c_e} theta_e`` (3.3.1).

    Args:
        center_to_edge_rot: ``(..., m, n, n)``, ``R_{c, c_e}``: transport from the midpoint
            ``c_e`` of the ``k``-th loop edge to the face centroid ``c`` (along ``[c, c_e]``).
            Using the inverse transport converges to ``-Theta`` (docs/conventions.md §1 pitfall).
        edge_vectors: ``(..., m, n)``, ``v_end - v_start`` of the oriented loop edges, in the frame
            of the edge midpoint.

    Returns:
        ``(..., n)`` in the fiber of the face centroid ``c``.
    """
    if center_to_edge_rot.ndim < 3 or edge_vectors.shape[-2:] != center_to_edge_rot.shape[-3:-1]:
        raise ValueError(
            f"torsion.barycentric: shapes {tuple(center_to_edge_rot.shape)} and {tuple(edge_vectors.shape)} "
            "must be (..., m, n, n) and (..., m, n)"
        )
    return (center_to_edge_rot @ edge_vectors[..., None]).squeeze(-1).sum(-2)


def solder_form(vertices: torch.Tensor, edges: torch.Tensor, frames: torch.Tensor | None = None) -> torch.Tensor:
    """Solder form per canonical edge ``(i, j)``: ``theta_ij = F_i^T (v_j - v_i)`` (Sec. 3.3).

    The edge vector expressed in the frame at ``v_i`` (columns of ``frames[i]`` are the frame
    vectors). ``frames=None`` means identity frames: ``theta_ij = v_j - v_i``, the global
    coordinates of the report's numerical tests.

    Args:
        vertices: ``(V, 3)``; edges: ``(E, 2)`` integer; frames: ``(V, 3, 3)`` or ``None``.

    Returns:
        ``(E, 3)`` in the fiber of ``v_i`` (the first vertex of each edge).
    """
    if vertices.ndim != 2 or edges.ndim != 2 or edges.shape[1] != 2:
        raise ValueError(f"solder_form: expected vertices (V, d) and edges (E, 2), got {tuple(vertices.shape)}, {tuple(edges.shape)}")
    if edges.numel() and (int(edges.min()) < 0 or int(edges.max()) >= vertices.shape[0]):
        raise ValueError(f"solder_form: edge vertex indices out of range [0, {vertices.shape[0]})")
    d = vertices[edges[:, 1]] - vertices[edges[:, 0]]
    if frames is None:
        return d
    if frames.shape != (vertices.shape[0], vertices.shape[1], vertices.shape[1]):
        raise ValueError(f"solder_form: frames must have shape {(vertices.shape[0], vertices.shape[1], vertices.shape[1])}, got {tuple(frames.shape)}")
    return (frames[edges[:, 0]].transpose(-1, -2) @ d[..., None]).squeeze(-1)


def face_torsion(edge_rot: Any, cells: Any, kind: str = "sqrt", cut: int = -1, frames: torch.Tensor | None = None) -> torch.Tensor:
    """Torsion of every face of a mesh, batched per face size (Def. 3.2).

    Without frames (``frames=None``, the global coordinate frame of the numerical tests), the
    solder form of the loop edge ``x_k -> x_{k+1}`` is ``theta = x_{k+1} - x_k`` and

    * ``kind="naive"``: these values as they are (diverges under refinement, report Sec. 3.3);
    * ``kind="sqrt"``: ``theta~_ij = sqrt(R_ij) theta_ij`` with the principal root ``so3.sqrt``
      (``n = 3``), ``theta~_ji = -R_ji theta~_ij`` — exactly :func:`sqrt` on each loop.

    With a frame field ``frames (V, n, n)`` (columns = frame axes in world coordinates), the
    rotations ``edge_rot`` are read in those vertex frames. The same convention as
    :func:`torchconn.dnabla.tet_solder_sqrt`: the connection is carried to the ambient frame,
    ``R^amb_ij = F_i R_ij F_j^T``, the torsion is computed there and expressed in the frame of
    the evaluation vertex, ``F_{x0}^T Θ^amb``. This is exactly gauge covariant (the principal
    root is taken of the frame-independent ``R^amb``), so the flat connection ``R_ij = F_i^T F_j``
    of any frame field has zero torsion of both kinds. For the naive kind it equals the solder
    form expressed per vertex, ``theta_ij = F_i^T (x_j - x_i)``.

    Args:
        edge_rot: ``(*batch, E, n, n)`` (``batch`` may be empty: a batch of connections on one
            mesh) or a ``Connection``; cells: ``CellComplex`` or ``TetMesh`` (its ``vertices``
            and ``edges`` are used, shared by the batch); kind, cut as above (cut convention of
            :func:`two_prong`); frames: ``(V, n, n)`` (shared), ``(*batch, V, n, n)`` or ``None``.

    Returns:
        ``(*batch, F, n)`` in global face order, each in the fiber of its evaluation vertex
        (first loop vertex; ``a`` of a sorted tet-mesh face ``[a<b<c]``).

    The op :func:`torchconn.ops.torsion.face_torsion` is asked first (with the batched
    tensors), else the loop formula (:mod:`torchconn.dec._batch`); works under ``vmap``,
    ``torch.func.jvp`` and on ``meta`` tensors.
    """
    if kind not in ("sqrt", "naive"):
        raise ValueError(f"face_torsion: kind must be 'sqrt' or 'naive', got {kind!r}")
    R = _edge_rot_of(edge_rot)
    n = R.shape[-1]
    if kind == "sqrt" and n != 3:
        raise ValueError(f"face_torsion: kind='sqrt' uses so3.sqrt and needs n=3, got n={n}")
    batch = edge_batch(R, int(cells.edges.shape[0]), "face_torsion")
    V = cells.vertices.to(dtype=R.dtype, device=R.device)
    if V.shape[-1] != n:
        raise ValueError(f"face_torsion: vertices of dimension {V.shape[-1]} do not match rotations of size {n}")
    check_frames(frames, V.shape[0], n, batch, "face_torsion")
    # sorted triangles [a<b<c], cut c: per-edge solder form + one product (the op), else None
    fused = ask_op(lambda: _ops_torsion.face_torsion(R, cells, kind, frames, cut=cut), R, frames)
    if fused is not None:
        return fused
    if frames is not None:
        frames = frames.to(R)
        e = on_device(cells, "edges", R.device)
        fi = frames.index_select(-3, e[:, 0])
        fj = frames.index_select(-3, e[:, 1])
        R = fi @ R @ fj.transpose(-1, -2)  # ambient connection
    H = so3.sqrt(R) if kind == "sqrt" else None
    F, groups = face_loops(cells)
    out = R.new_zeros(*batch, F, n)
    for face_ids, le, ls, loops in groups:
        le, ls, loops = le.to(R.device), ls.to(R.device), loops.to(R.device)
        L = orient(R, le, ls)
        pts = V[loops]
        d = torch.roll(pts, shifts=-1, dims=-2) - pts  # x_{k+1} - x_k
        fwd, bwd = d, -d
        if H is not None:
            Hf = orient(H, le, ls)  # sqrt(R_{x_k x_{k+1}}), transpose for the reversed edge
            fwd = (Hf @ fwd[..., None]).squeeze(-1)
            bwd = (Hf.transpose(-1, -2) @ bwd[..., None]).squeeze(-1)
        val = two_prong(L, fwd, bwd, cut)
        if frames is not None:  # express in the frame of the evaluation vertex x0
            f0 = frames.index_select(-3, loops[:, 0])
            val = (f0.transpose(-1, -2) @ val[..., None]).squeeze(-1)
        if face_ids is None:
            return val
        out = out.index_copy(-2, face_ids.to(out.device), val)
    return out
