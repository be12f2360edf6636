"""The boundary constraint of an octahedral frame field, built once per mesh and feature angle.

Every frame-field component (the SH baseline, the loss, the polish, the metrics, the studies)
constrains the same boundary data:

* **feature vertices**: endpoints of the sharp boundary edges
  (:func:`feature_edges`: the two boundary-face normals differ by more
  than ``feature_angle_deg``);
* **aligned vertices**: the other boundary vertices, each with its area-weighted unit vertex
  normal ``n_i`` (``mesh.boundary_vertex_normals``); a frame there must have an axis ``±n_i``
  and rotates only about ``n_i`` (:mod:`torchconn.frames.param`);
* **feature pairs**: one (feature vertex, incident boundary face) pair per corner of a boundary
  face at a feature vertex, with the face's outward unit normal; at a feature vertex the frame
  should follow every incident face normal.

:meth:`BoundaryConstraint.from_mesh` caches the object on the mesh (``mesh.require``), so it is
built once; ``mesh.to(...)`` returns a copy with an empty cache, which rebuilds it in the new
dtype/device.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["BoundaryConstraint", "boundary_face_normals", "feature_edges", "feature_vertices"]


@dataclass(frozen=True)
class BoundaryConstraint:
    """Boundary and feature constraints of a frame field on one mesh (see the module docstring).

    Attributes (``V`` vertices, ``B`` boundary vertices, ``A`` aligned vertices, ``P`` feature
    pairs; float tensors in the mesh's dtype, everything on the mesh's device):

    * ``feature_angle_deg``: the sharp-edge threshold the constraint was built with.
    * ``feature_vertices (Vf,) long``: sorted feature vertices.
    * ``is_feature (V,) bool``.
    * ``normals (V, 3)``: unit vertex normal at boundary vertices, 0 in the interior.
    * ``constrained (V,) bool``: aligned vertices (boundary and not feature).
    * ``align_vertices (A,) long`` and ``align_normals (A, 3)``: the aligned vertices in the
      order of ``mesh.boundary_vertices`` and their normals.
    * ``pair_vertices (P,) long``, ``pair_faces (P,) long`` (rows of ``mesh.boundary_faces``) and
      ``pair_normals (P, 3)``: the feature pairs, in boundary-face-major order (face ``f``'s
      corners ``0, 1, 2`` before face ``f + 1``'s).
    """

    feature_angle_deg: float
    feature_vertices: torch.Tensor
    is_feature: torch.Tensor
    normals: torch.Tensor
    constrained: torch.Tensor
    align_vertices: torch.Tensor
    align_normals: torch.Tensor
    pair_vertices: torch.Tensor
    pair_faces: torch.Tensor
    pair_normals: torch.Tensor

    @classmethod
    def from_mesh(cls, mesh, feature_angle_deg: float = 30.0) -> "BoundaryConstraint":
        """The constraint of ``mesh`` (a ``TetMesh``) for ``feature_angle_deg``, cached on the mesh."""
        angle = float(feature_angle_deg)
        if hasattr(mesh, "require"):
            return mesh.require(f"frames.boundary_constraint[{angle!r}]", lambda m: cls._build(m, angle))
        return cls._build(mesh, angle)

    @classmethod
    def _build(cls, mesh, angle: float) -> "BoundaryConstraint":

        V = mesh.vertices.shape[0]
        dtype, dev = mesh.vertices.dtype, mesh.vertices.device
        bv = mesh.boundary_vertices
        fv = feature_vertices(mesh, angle)
        is_feat = torch.zeros(V, dtype=torch.bool, device=dev)
        is_feat[fv] = True
        bnormals = mesh.boundary_vertex_normals.to(dtype)
        normals = torch.zeros(V, 3, dtype=dtype, device=dev)
        normals[bv] = bnormals
        constrained = torch.zeros(V, dtype=torch.bool, device=dev)
        constrained[bv] = True
        constrained &= ~is_feat
        keep = ~is_feat[bv]
        bf = mesh.boundary_faces
        vert = bf.reshape(-1)
        face = torch.arange(bf.shape[0], device=bf.device).repeat_interleave(3)
        sel = is_feat[vert]
        pair_faces = face[sel]
        return cls(
            feature_angle_deg=angle,
            feature_vertices=fv,
            is_feature=is_feat,
            normals=normals,
            constrained=constrained,
            align_vertices=bv[keep],
            align_normals=bnormals[keep],
            pair_vertices=vert[sel],
            pair_faces=pair_faces,
            pair_normals=boundary_face_normals(mesh).to(dtype)[pair_faces],
        )


def _require(mesh, *names: str) -> None:
    missing = [n for n in names if not hasattr(mesh, n)]
    if missing:
        raise TypeError(f"expected a TetMesh; {type(mesh).__name__} lacks {missing}")


def boundary_face_normals(mesh) -> torch.Tensor:
    """Outward unit normals ``(B, 3)`` of ``mesh.boundary_faces``."""
    _require(mesh, "vertices", "boundary_faces")
    p = mesh.vertices[mesh.boundary_faces]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(n.dtype).tiny)


def feature_edges(mesh, angle_deg: float = 30.0) -> torch.Tensor:
    """Sharp boundary edges ``(K, 2)`` long (rows ``i < j``, sorted lexicographically).

    A boundary edge is sharp when the normals of its two boundary faces make an angle larger
    than ``angle_deg``. Boundary edges not shared by exactly two boundary faces (non-manifold
    boundary) are ignored.
    """
    _require(mesh, "vertices", "boundary_faces")
    if not 0.0 <= angle_deg <= 180.0:
        raise ValueError(f"angle_deg must lie in [0, 180], got {angle_deg}")
    bf = mesh.boundary_faces
    device = bf.device
    nf = boundary_face_normals(mesh)
    half = torch.cat([bf[:, [1, 2]], bf[:, [2, 0]], bf[:, [0, 1]]], 0)  # (3B, 2) directed edges
    face_of = torch.arange(bf.shape[0], device=device).repeat(3)
    und = half.sort(dim=1).values
    V = mesh.vertices.shape[0]
    key = und[:, 0] * V + und[:, 1]
    ukey, inv, cnt = torch.unique(key, return_inverse=True, return_counts=True)
    # the two faces of each boundary edge: sort half-edges by edge key, then take pairs
    order = torch.argsort(inv, stable=True)
    start = torch.cumsum(cnt, 0) - cnt
    two = cnt == 2
    f0 = face_of[order[start[two]]]
    f1 = face_of[order[start[two] + 1]]
    n0, n1 = nf[f0], nf[f1]
    # angle between normals via atan2 (accurate for small and large angles)
    ang = torch.atan2(torch.linalg.cross(n0, n1, dim=-1).norm(dim=-1), (n0 * n1).sum(-1))
    sharp = ang > math.radians(angle_deg)
    k = ukey[two][sharp]
    return torch.stack([k // V, k % V], dim=1)


def feature_vertices(mesh, angle_deg: float = 30.0) -> torch.Tensor:
    """Sorted endpoints ``(Vf,)`` long of :func:`feature_edges`."""
    return torch.unique(feature_edges(mesh, angle_deg).reshape(-1))
