"""Face curvature of sorted-triangle meshes as an op (report Sec. 3.2, (3.2.1)).

Written-out 3x3 products on unbound components, component-major, with a hand-written backward
(:class:`_FaceCurvatureFn`) that is itself differentiable (double backward, ``create_graph``
and Hessian-vector products are exact); other ranks use batched matrix products. The gather table is
built once per mesh (``mesh.require``). :func:`face_curvature` is the op that
:func:`torchconn.dec.curvature.face_curvature` (the public entry point) calls; it returns
``None`` where it does not apply (a mesh without sorted triangles, a non-integer cut), and the
caller then evaluates its generic loop formula.
"""
from __future__ import annotations

import torch

from ._cache import require as _require

__all__ = ["face_curvature"]


def _sorted_triangles(mesh) -> bool:
    """A tet mesh (or its ``nn.MeshBuffers``): sorted faces ``[a<b<c]`` with ``face_edges``.

    Read from the mesh's ``kind`` attribute (:class:`torchconn.mesh.base.MeshBase`): ops sits
    below the mesh layer and does not import its classes."""
    return getattr(mesh, "kind", None) == "tet"


def _face_rots(edge_rot: torch.Tensor, mesh) -> torch.Tensor:
    """``(F, 3, n, n)`` = ``R_ab, R_bc, R_ac`` of every sorted face ``[a<b<c]``.

    All three are canonical edges (``a<b<c``), so no transposes: ``face_edges`` lists
    ``bc, ac, ab``. ``index_select`` (backward: ``index_add_``) rather than advanced indexing,
    whose backward is an accumulating ``index_put_``.
    """
    fe = mesh.face_edges.to(edge_rot.device)[:, [2, 0, 1]]
    F, n = fe.shape[0], edge_rot.shape[-1]
    return edge_rot.index_select(0, fe.reshape(-1)).reshape(F, 3, n, n)


def _mm(A, B):
    """``A B`` on unbound row-major components (9 tensors each)."""
    return tuple(torch.addcmul(torch.addcmul(A[3 * i] * B[j], A[3 * i + 1], B[3 + j]), A[3 * i + 2], B[6 + j])
                 for i in range(3) for j in range(3))


def _tr(A):
    """Transpose of unbound row-major components (a relabeling, no arithmetic)."""
    return tuple(A[3 * j + i] for i in range(3) for j in range(3))


def _face_formula(kind: int, ab, bc, ac):
    """Curvature of ``[a<b<c]`` on components: kind 2 (cut c), 1 (cut b), 0 (holonomy, no ``- I``)."""
    if kind == 2:
        return tuple(x - y for x, y in zip(_mm(ab, bc), ac))
    if kind == 1:
        return tuple(x - y for x, y in zip(ab, _mm(ac, _tr(bc))))
    return _mm(_mm(ab, bc), _tr(ac))


def _gather(edge_rot: torch.Tensor, face_index: torch.Tensor) -> torch.Tensor:
    """``(9, 3, F)``: component ``q`` of ``R_ab, R_bc, R_ac`` of every face (``index_select``, differentiable)."""
    E, F = edge_rot.shape[0], face_index.shape[1]
    table = edge_rot.reshape(E, 9).t().contiguous()  # (9, E)
    flat = face_index.reshape(-1)
    return torch.stack([table[q].index_select(0, flat) for q in range(9)], 0).reshape(9, 3, F)


class _FaceCurvatureFn(torch.autograd.Function):
    """Gather + written-out 3x3 products + scatter for the face curvature, component-major.

    Forward ``(edge_rot (E, 3, 3), face_index (3, F)) -> (F, 3, 3)``; the three rows of
    ``face_index`` are the canonical edges ``ab, bc, ac`` of each sorted face. Backward
    (hand-written) with ``G = ∂L/∂H``:

    * cut c, ``H = R_ab R_bc - R_ac``: ``G R_bcᵀ``, ``R_abᵀ G``, ``-G``;
    * cut b, ``H = R_ab - R_ac R_bcᵀ``: ``G``, ``-Gᵀ R_ac``, ``-G R_bc``;
    * holonomy, ``H = P R_acᵀ - I`` with ``P = R_ab R_bc``: ``(G R_ac) R_bcᵀ``,
      ``R_abᵀ (G R_ac)``, ``Gᵀ P``;

    scattered onto the edges with ``index_add_`` (the gradients of ``R_ab, R_bc, R_ac``).
    The backward is made of differentiable torch operations on the saved input ``edge_rot``
    and on ``G``: when it is recorded (``create_graph=True``, i.e. grad mode on inside the
    backward: double backward, ``autograd.grad(..., create_graph=True)``, Hessian-vector
    products) it re-gathers the face rotations from ``edge_rot`` so that autograd sees their
    dependence on the input; otherwise it reuses the gathered table saved by the forward.
    """

    @staticmethod
    def forward(ctx, edge_rot, face_index, kind):
        F = face_index.shape[1]
        g = _gather(edge_rot, face_index)
        ab, bc, ac = (tuple(g[q, k] for q in range(9)) for k in range(3))
        H = _face_formula(kind, ab, bc, ac)
        if kind == 0:
            H = tuple(h - 1.0 if q in (0, 4, 8) else h for q, h in enumerate(H))
        ctx.save_for_backward(edge_rot, g, face_index)
        ctx.kind = kind
        # component-major (9, F) viewed as (F, 3, 3) (strides (1, 3F, F)): stacking along a new
        # leading dim is a plain copy, twice as fast as interleaving the 9 components
        return torch.stack(H, 0).t().reshape(F, 3, 3)

    @staticmethod
    def backward(ctx, grad):
        edge_rot, g, face_index = ctx.saved_tensors
        if torch.is_grad_enabled():
            # a recorded backward: the saved table g carries no graph, so gather again from the
            # input (the forward ran without recording); every step below is differentiable
            g = _gather(edge_rot, face_index)
        kind, E = ctx.kind, edge_rot.shape[0]
        F = face_index.shape[1]
        ab, bc, ac = (tuple(g[q, k] for q in range(9)) for k in range(3))
        Gt = grad.reshape(F, 9).t().contiguous()  # no copy when grad kept the output's layout
        G = tuple(Gt[q] for q in range(9))
        if kind == 2:
            gab, gbc, gac = _mm(G, _tr(bc)), _mm(_tr(ab), G), tuple(-x for x in G)
        elif kind == 1:
            gab, gbc, gac = G, tuple(-x for x in _mm(_tr(G), ac)), tuple(-x for x in _mm(G, bc))
        else:
            GR = _mm(G, ac)
            gab, gbc, gac = _mm(GR, _tr(bc)), _mm(_tr(ab), GR), _mm(_tr(G), _mm(ab, bc))
        vals = torch.stack([x for q in range(9) for x in (gab[q], gbc[q], gac[q])], 0).reshape(9, -1)
        # out-of-place index_add: one call for the 9 components, and differentiable in vals
        gtab = vals.new_zeros(9, E).index_add(1, face_index.reshape(-1), vals)
        return gtab.t().reshape(E, 3, 3), None, None


def face_curvature(edge_rot: torch.Tensor, mesh, cut=-1, kind: str = "two_prong") -> torch.Tensor | None:
    """Curvature of every sorted face ``[a<b<c]`` of a tet mesh: ``(F, n, n)`` (Sec. 3.2, (3.2.1)).

    Same values as the generic loop formula of :func:`torchconn.dec.curvature.face_curvature`
    on a ``TetMesh`` (loop ``a -> b -> c``, evaluation ``a``), written out for the triangle:

    * cut ``c`` (``-1`` or ``2``): ``R_ab R_bc - R_ac``;
    * cut ``b`` (``1`` or ``-2``): ``R_ab - R_ac R_bcᵀ``;
    * holonomy (``kind="holonomy"``, or cut ``0`` / ``-3``): ``R_ab R_bc R_acᵀ - I``.

    For ``n = 3`` the fused component-major kernel ``_FaceCurvatureFn`` (hand-written
    backward, itself differentiable: higher-order gradients are exact); other ranks use batched matrix products. ``None`` for a mesh without sorted
    triangles or a ``cut`` that is not an integer in ``[-3, 2]`` (two-prong). ``edge_rot`` with
    another number of rows than ``mesh.edges`` raises ``ValueError`` naming both shapes.
    """
    if not _sorted_triangles(mesh) or not (kind == "holonomy" or (type(cut) is int and -3 <= cut <= 2)):
        return None
    E = int(mesh.edges.shape[0])
    if edge_rot.dim() < 3 or edge_rot.shape[0] != E:
        short = f" (mesh edge index {E - 1} out of range)" if edge_rot.dim() and edge_rot.shape[0] < E else ""
        raise ValueError(f"face_curvature: edge_rot must have shape ({E}, n, n), one rotation per mesh edge "
                         f"in mesh.edges order, got {tuple(edge_rot.shape)}{short}")
    c = cut % 3 if kind == "two_prong" else 0
    if edge_rot.shape[-1] == 3 and edge_rot.dim() == 3:
        return _FaceCurvatureFn.apply(edge_rot, _face_index(mesh, edge_rot.device), c)
    F3 = _face_rots(edge_rot, mesh)
    Rab, Rbc, Rac = F3.unbind(1)
    if c == 2:
        return Rab @ Rbc - Rac
    if c == 1:
        return Rab - Rac @ Rbc.transpose(-1, -2)
    n = edge_rot.shape[-1]
    eye = torch.eye(n, dtype=edge_rot.dtype, device=edge_rot.device)
    return (Rab @ Rbc) @ Rac.transpose(-1, -2) - eye


def _face_index(mesh, device) -> torch.Tensor:
    """``(3, F)`` canonical edges ``ab, bc, ac`` of the sorted faces (cached with ``mesh.require``)."""
    idx = _require(mesh, "ops.face_index", lambda m: m.face_edges[:, [2, 0, 1]].t().contiguous())
    if idx.device == torch.device(device):
        return idx
    dev = torch.device(device)
    return _require(mesh, f"ops.face_index.{dev}", lambda m: idx.to(dev))
