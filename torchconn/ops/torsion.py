"""Face torsion of sorted-triangle meshes as an op (report Def. 3.2), and the per-edge gathers it shares.

The solder form is formed once per *edge* (:func:`edge_solder_frames`) and combined per face
with one product. :func:`face_torsion` is the op that :func:`torchconn.dec.torsion.face_torsion`
(the public entry point) calls, and :func:`edge_frames` the per-edge gathers the frame-field
loss shares between its ``tie`` and ``torsion`` terms; both return ``None`` where they do not
apply, and the caller then evaluates its generic formula.
"""
from __future__ import annotations

import torch

from ._mat import _matTvec, _matvec
from .curvature import _sorted_triangles
from .so3 import sqrt as _sqrt

__all__ = ["edge_frames", "edge_solder_frames", "face_torsion"]


def edge_frames(edge_rot: torch.Tensor, mesh, frames: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Per-edge frame gathers and the transported frame, shared by the frame-field loss terms.

    Args:
        edge_rot: ``(E, 3, 3)`` ``R_ij`` of the canonical edges ``mesh.edges (E, 2)``.
        frames: ``(V, 3, 3)`` (columns = frame axes in world coordinates).

    Returns:
        ``(F_i, F_i R_ij, F_j)``, each ``(E, 3, 3)``. ``index_select`` (backward: ``index_add_``)
        rather than advanced indexing (backward: accumulating ``index_put_``). ``None`` unless
        ``mesh`` has sorted triangles and ``edge_rot`` is ``(E, 3, 3)``.
    """
    if not (_sorted_triangles(mesh) and edge_rot.dim() == 3 and edge_rot.shape[-1] == 3):
        return None
    e = mesh.edges.to(edge_rot.device)
    Fi, Fj = frames.index_select(0, e[:, 0]), frames.index_select(0, e[:, 1])
    return Fi, Fi @ edge_rot, Fj


def edge_solder_frames(edge_rot: torch.Tensor, mesh, kind: str = "sqrt",
                       frames: torch.Tensor | None = None,
                       edge_frame_rot: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
                       ) -> torch.Tensor:
    """Solder form of each canonical edge ``(i, j)`` in the fiber of ``i``: ``(E, 3)``.

    ``kind="sqrt"``: ``θ̃_ij = √R_ij (v_j - v_i)`` (report Def. 3.2); ``"naive"``: ``v_j - v_i``.
    With ``frames (V, 3, 3)`` the conventions of :func:`torchconn.dec.torsion.face_torsion`: the
    root is taken of the ambient ``F_i R_ij F_jᵀ`` and the value is expressed in ``F_i``,
    ``θ̃'_ij = F_iᵀ √(F_i R_ij F_jᵀ) (v_j - v_i)``. ``edge_frame_rot``: the triple
    ``(F_i, F_i R_ij, F_j)`` of :func:`edge_frames` when the caller has it already (the same
    values; saves the gathers and one product).
    """
    dev, dt = edge_rot.device, edge_rot.dtype
    e = mesh.edges.to(dev)
    verts = mesh.vertices.to(device=dev, dtype=dt)
    vec = verts.index_select(0, e[:, 1]) - verts.index_select(0, e[:, 0])
    if frames is None and edge_frame_rot is None:
        return _matvec(_sqrt(edge_rot), vec) if kind == "sqrt" else vec
    if edge_frame_rot is None:
        Fi, Fj = frames.index_select(0, e[:, 0]), frames.index_select(0, e[:, 1])
        FiR = Fi @ edge_rot if kind == "sqrt" else None
    else:
        Fi, FiR, Fj = edge_frame_rot
    if kind == "sqrt":
        vec = _matvec(_sqrt(FiR @ Fj.transpose(-1, -2)), vec)
    return _matTvec(Fi, vec)


def face_torsion(edge_rot: torch.Tensor, mesh, kind: str = "sqrt", frames: torch.Tensor | None = None,
                 cut=-1, edge_frame_rot: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
                 ) -> torch.Tensor | None:
    """Torsion of every sorted face ``[a<b<c]`` with cut ``c``: ``(F, 3)`` in the fiber of ``a``.

    ``Θ = θ̃_ab + R_ab θ̃_bc - θ̃_ac`` (Def. 3.2: prongs ``a -> b -> c`` and ``a -> c``), with the
    per-edge solder form of :func:`edge_solder_frames` formed once per *edge*. Equals the
    generic loop formula of :func:`torchconn.dec.torsion.face_torsion` with ``cut=-1`` (with
    frames, ``F_aᵀ Θ^amb = F_aᵀ θ̃^amb_ab + R_ab F_bᵀ θ̃^amb_bc - F_aᵀ θ̃^amb_ac`` since
    ``R^amb_ab = F_a R_ab F_bᵀ``). ``frames`` is converted to the dtype and device of
    ``edge_rot``. ``edge_frame_rot``: optional ``(F_i, F_i R_ij, F_j)`` from
    :func:`edge_frames` (replaces ``frames``; the frame-field loss shares it with its ``tie``
    term). ``None`` unless ``mesh`` has sorted triangles and ``cut`` is ``-1`` or ``2``;
    ``edge_rot`` with another number of rows than ``mesh.edges`` raises ``ValueError``.
    """
    if not (_sorted_triangles(mesh) and type(cut) is int and cut in (-1, 2)):
        return None
    E = int(mesh.edges.shape[0])
    if edge_rot.dim() != 3 or edge_rot.shape[0] != E:
        raise ValueError(f"face_torsion: edge_rot must have shape ({E}, 3, 3), one rotation per mesh edge "
                         f"in mesh.edges order, got {tuple(edge_rot.shape)}")
    if frames is not None:
        frames = frames.to(edge_rot)
    th = edge_solder_frames(edge_rot, mesh, kind, frames, edge_frame_rot)
    fe = mesh.face_edges.to(edge_rot.device)
    F = fe.shape[0]
    t = th.index_select(0, fe[:, [2, 0, 1]].reshape(-1)).reshape(F, 3, 3)  # θ̃_ab, θ̃_bc, θ̃_ac
    Rab = edge_rot.index_select(0, fe[:, 2])
    return t[:, 0] - t[:, 2] + _matvec(Rab, t[:, 1])
