"""The boundary constraint of an octahedral frame field, built once per mesh and feature angle.

Every frame-field component (the SH baseline, the loss, the quality paths, the metrics, the studies)
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
* **tangent pairs**: along a feature curve one frame axis should lie on the curve tangent, the
  other two on the incident surfaces' normals as far as the dihedral angle allows (the feature
  pairs). At a vertex inside a curve (two incident feature edges, no corner) the tangent is
  ``(u_1 - u_2) / |u_1 - u_2|`` with ``u_1, u_2`` the unit edge vectors pointing away from the
  vertex. On a circle this is off the exact tangent by a quarter of the difference of the two
  edges' arc angles (exact for equal edges), where an edge's own direction is off by half its
  arc angle. At a **corner** (a CAD corner point, a vertex with other
  than two incident feature edges, or, without CAD tags, a turn sharper than the feature angle)
  there is one pair per incident feature edge with that edge's direction.
  :func:`feature_curve_alignment` measures the tangent part.

Where the feature edges come from (``features=``): a mesh with CAD tags (``mesh.cad``, a
:class:`~torchconn.mesh.cad.CadTags` from :func:`~torchconn.mesh.cad.load_cad` or
:func:`~torchconn.mesh.cad.load_tagged_msh`) uses its CAD curves, exactly: every tagged mesh edge
on the boundary whose two boundary faces lie on different CAD surfaces (a periodic surface's
seam, with the same surface on both sides, is no feature), and its CAD corner points on those
edges are corners of the curves. An untagged mesh (or ``features="dihedral"``) detects sharp edges by the
dihedral angle (:func:`feature_edges`).

:meth:`BoundaryConstraint.from_mesh` caches the object on the mesh (``mesh.require``), so it is
built once; ``mesh.to(...)`` returns a copy with an empty cache, which rebuilds it in the new
dtype/device.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["BoundaryConstraint", "boundary_face_normals", "feature_edges", "feature_vertices", "cad_feature_edges",
           "feature_curve_alignment", "FEATURE_SOURCES"]

FEATURE_SOURCES = ("auto", "cad", "dihedral")


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
    * ``feature_source``: ``"cad"`` (the edges are the mesh's CAD curves) or ``"dihedral"``.
    * ``feature_edges (K, 2) long``: the feature edges, rows ``i < j`` sorted lexicographically.
    * ``corner_vertices (C,) long``: the sorted corners of the feature curves.
    * ``tangent_vertices (Q,) long``, ``tangent_dirs (Q, 3)`` unit tangents (up to sign) and
      ``tangent_at_corner (Q,) bool``: the tangent pairs, first one per curve-interior feature
      vertex (ascending), then one per (corner, incident feature edge) in edge order.
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
    feature_source: str = "dihedral"
    feature_edges: torch.Tensor | None = None
    corner_vertices: torch.Tensor | None = None
    tangent_vertices: torch.Tensor | None = None
    tangent_dirs: torch.Tensor | None = None
    tangent_at_corner: torch.Tensor | None = None

    def feature_targets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(vertices (P', ) long, directions (P', 3))``: the directions a frame axis should follow
        at the feature vertices: every feature pair's face normal and, on CAD curves
        (``feature_source == "cad"``), the curve tangent at each curve-interior vertex.

        A CAD curve is a feature whatever its dihedral angle, so the incident face normals alone
        may leave the tangent free (a smooth crease); a dihedral feature edge is sharp, so its
        two normals already fix the tangent and no tangent pair is added (the field of an
        untagged mesh is the same as before CAD input existed). Corners keep only their normals:
        the curves meeting there generally cannot all be followed by one frame.
        """
        if self.feature_source != "cad" or self.tangent_vertices is None:
            return self.pair_vertices, self.pair_normals
        inner = ~self.tangent_at_corner
        return (torch.cat([self.pair_vertices, self.tangent_vertices[inner]]),
                torch.cat([self.pair_normals, self.tangent_dirs[inner].to(self.pair_normals.dtype)]))

    @classmethod
    def from_mesh(cls, mesh, feature_angle_deg: float = 30.0, *, features: str = "auto") -> "BoundaryConstraint":
        """The constraint of ``mesh`` (a ``TetMesh``), cached on the mesh.

        Args:
            mesh: a ``TetMesh``.
            feature_angle_deg: the dihedral threshold of :func:`feature_edges` (used when the
                feature edges come from dihedral angles).
            features: ``"auto"`` (CAD curves when ``mesh.cad`` is set, else dihedral angles),
                ``"cad"`` (require ``mesh.cad``) or ``"dihedral"`` (ignore CAD tags).

        Raises:
            ValueError: an unknown ``features``, or ``"cad"`` on a mesh without CAD tags.
        """
        angle = float(feature_angle_deg)
        if features not in FEATURE_SOURCES:
            raise ValueError(f"features must be one of {FEATURE_SOURCES}, got {features!r}")
        has_cad = getattr(mesh, "cad", None) is not None
        if features == "cad" and not has_cad:
            raise ValueError("features='cad' needs a mesh with CAD tags (mesh.cad, from torchconn.mesh.cad.load_cad "
                             "or load_tagged_msh); this mesh has none")
        source = "cad" if has_cad and features != "dihedral" else "dihedral"
        key = f"frames.boundary_constraint[{angle!r}]" + ("[cad]" if source == "cad" else "")
        if hasattr(mesh, "require"):
            return mesh.require(key, lambda m: cls._build(m, angle, source))
        return cls._build(mesh, angle, source)

    @classmethod
    def _build(cls, mesh, angle: float, source: str = "dihedral") -> "BoundaryConstraint":

        V = mesh.vertices.shape[0]
        dtype, dev = mesh.vertices.dtype, mesh.vertices.device
        bv = mesh.boundary_vertices
        if source == "cad":
            fe = cad_feature_edges(mesh)
            # CAD points off the feature curves (a sphere's poles on its seam) are no corners
            cad_corners = mesh.cad.corner_vertices.to(dev)
        else:
            fe = feature_edges(mesh, angle)
            cad_corners = None
        fv = torch.unique(fe.reshape(-1))
        corners, tv, td, tc = _curve_tangents(mesh.vertices, fe, cad_corners, angle)
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
            feature_source=source,
            feature_edges=fe,
            corner_vertices=corners,
            tangent_vertices=tv,
            tangent_dirs=td.to(dtype),
            tangent_at_corner=tc,
        )


def _curve_tangents(vertices: torch.Tensor, fe: torch.Tensor, cad_corners: torch.Tensor | None, angle: float):
    """Corners and tangent pairs of the feature curves ``fe (K, 2)`` (see the module docstring).

    Returns ``(corners (C,), tangent_vertices (Q,), tangent_dirs (Q, 3), tangent_at_corner (Q,))``.
    """
    V, dev = vertices.shape[0], vertices.device
    if fe.shape[0] == 0:
        none = torch.zeros(0, dtype=torch.long, device=dev)
        return none, none, vertices.new_zeros(0, 3), torch.zeros(0, dtype=torch.bool, device=dev)
    d = vertices[fe[:, 1]] - vertices[fe[:, 0]]
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(d.dtype).tiny)
    end = fe.reshape(-1)  # (2K,) endpoint of each half: i of edge k, then j
    away = torch.stack([d, -d], dim=1).reshape(-1, 3)  # unit edge vector pointing away from `end`
    deg = torch.bincount(end, minlength=V)
    # per endpoint, the first incident half (by position) is the reference u_1
    order = torch.argsort(end, stable=True)
    first = torch.full((V,), -1, dtype=torch.long, device=dev)
    first.scatter_reduce_(0, end[order], order, reduce="amin", include_self=False)
    ref = away[first[end]]
    s = torch.where((away * ref).sum(-1) >= 0, 1.0, -1.0).to(d.dtype)
    t = torch.zeros(V, 3, dtype=d.dtype, device=dev).index_add_(0, end, s[:, None] * away)
    corner = (deg != 2) & (deg > 0)
    if cad_corners is not None:
        on = torch.zeros(V, dtype=torch.bool, device=dev)
        on[cad_corners] = True
        corner |= on & (deg > 0)
    else:
        # a turn sharper than the feature angle: u_1 and -u_2 differ by more than `angle`
        not_ref = (first[end] != torch.arange(end.numel(), device=dev)).to(d.dtype)
        other = torch.zeros(V, 3, dtype=d.dtype, device=dev).index_add_(0, end, not_ref[:, None] * away)
        u1 = away[first.clamp_min(0)]
        turn = torch.atan2(torch.linalg.cross(u1, -other, dim=-1).norm(dim=-1), (u1 * -other).sum(-1))
        corner |= (deg == 2) & (turn > math.radians(angle))
    inner = ((deg == 2) & ~corner).nonzero().flatten()
    tn = t[inner]
    tn = tn / tn.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(d.dtype).tiny)
    at_c = corner[end]
    tv = torch.cat([inner, end[at_c]])
    td = torch.cat([tn, away[at_c]])
    tc = torch.cat([torch.zeros(inner.numel(), dtype=torch.bool, device=dev),
                    torch.ones(int(at_c.sum()), dtype=torch.bool, device=dev)])
    return corner.nonzero().flatten(), tv, td, tc


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
    key, f0, f1 = _boundary_edge_faces(mesh)
    nf = boundary_face_normals(mesh)
    n0, n1 = nf[f0], nf[f1]
    # angle between normals via atan2 (accurate for small and large angles)
    ang = torch.atan2(torch.linalg.cross(n0, n1, dim=-1).norm(dim=-1), (n0 * n1).sum(-1))
    k = key[ang > math.radians(angle_deg)]
    V = mesh.vertices.shape[0]
    return torch.stack([k // V, k % V], dim=1)


def _boundary_edge_faces(mesh) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Boundary edges shared by exactly two boundary faces: ``(key (Eb,), f0 (Eb,), f1 (Eb,))``,
    ascending keys ``i * V + j`` (``i < j``) and the two rows of ``mesh.boundary_faces``."""
    bf = mesh.boundary_faces
    half = torch.cat([bf[:, [1, 2]], bf[:, [2, 0]], bf[:, [0, 1]]], 0)  # (3B, 2) directed edges
    face_of = torch.arange(bf.shape[0], device=bf.device).repeat(3)
    und = half.sort(dim=1).values
    V = mesh.vertices.shape[0]
    ukey, inv, cnt = torch.unique(und[:, 0] * V + und[:, 1], return_inverse=True, return_counts=True)
    # the two faces of each boundary edge: sort half-edges by edge key, then take pairs
    order = torch.argsort(inv, stable=True)
    start = torch.cumsum(cnt, 0) - cnt
    two = cnt == 2
    return ukey[two], face_of[order[start[two]]], face_of[order[start[two] + 1]]


def cad_feature_edges(mesh) -> torch.Tensor:
    """Feature edges ``(K, 2)`` long of a mesh with CAD tags (rows ``i < j``, sorted).

    The mesh edges tagged with a CAD curve (``mesh.cad.feature_edges``) that are boundary edges
    of two boundary faces on different CAD surfaces (``mesh.cad.boundary_face_surface``; an
    untagged face, ``-1``, counts as different). Tagged edges inside the volume (a model
    embedded in a box) and seams of periodic surfaces are left out.

    Raises:
        ValueError: the mesh has no CAD tags.
    """
    _require(mesh, "vertices", "boundary_faces")
    tags = getattr(mesh, "cad", None)
    if tags is None:
        raise ValueError("cad_feature_edges needs a mesh with CAD tags (mesh.cad); this mesh has none")
    dev = mesh.vertices.device
    V = mesh.vertices.shape[0]
    key, f0, f1 = _boundary_edge_faces(mesh)
    surf = tags.boundary_face_surface.to(dev)
    s0, s1 = surf[f0], surf[f1]
    sharp_key = key[(s0 != s1) | (s0 < 0)]
    fe = tags.feature_edges.to(dev)
    fkey = fe[:, 0] * V + fe[:, 1]
    if sharp_key.numel() == 0:
        return fe[:0]
    pos = torch.searchsorted(sharp_key, fkey).clamp(max=sharp_key.numel() - 1)
    keep = sharp_key[pos] == fkey
    k = fkey[keep].sort().values
    return torch.stack([k // V, k % V], dim=1)


def feature_curve_alignment(frames: torch.Tensor, mesh, feature_angle_deg: float = 30.0, *,
                            features: str = "auto") -> dict:
    """Feature-curve alignment: the angle between the feature-curve tangent and the closest
    frame axis (the tangent pairs of :class:`BoundaryConstraint`).

    For each tangent pair ``(i, t)``: ``atan2(|a x t|, |a . t|)`` with ``a`` the axis of
    ``frames[i]`` maximizing ``|a . t|`` (no ``acos``; up to sign). Pairs inside the curves
    give ``feature_curve_alignment_*``; pairs at the corners, where curves meet at angles that
    one frame generally cannot all follow, give ``feature_curve_corner_alignment_*``.

    Args:
        frames: ``(V, 3, 3)``, ``frames[i][:, k]`` axis ``k`` at vertex ``i``.
        mesh: a ``TetMesh`` (with ``mesh.cad`` the edges are its CAD curves).
        feature_angle_deg, features: as in :meth:`BoundaryConstraint.from_mesh`.

    Returns:
        ``{"feature_curve_alignment_mean_deg", "feature_curve_alignment_max_deg",
        "feature_curve_corner_alignment_mean_deg", "feature_curve_corner_alignment_max_deg"}``
        floats (``nan`` for an empty set) and ``"n_feature_curve_edges"``,
        ``"n_feature_corners"`` ints.
    """
    V = mesh.vertices.shape[0]
    if not torch.is_tensor(frames) or frames.shape != (V, 3, 3):
        shape = tuple(frames.shape) if torch.is_tensor(frames) else type(frames).__name__
        raise ValueError(f"frames must have shape (V, 3, 3) = ({V}, 3, 3) for this mesh, got {shape}")
    bc = BoundaryConstraint.from_mesh(mesh, feature_angle_deg, features=features)
    F = frames[bc.tangent_vertices]
    t = bc.tangent_dirs.to(F.dtype)
    c = (F * t[:, :, None]).sum(-2)  # (Q, 3): a_k . t
    k = c.abs().argmax(-1, keepdim=True)
    a = torch.gather(F, -1, k[:, None, :].expand(-1, 3, 1)).squeeze(-1)
    ang = torch.rad2deg(torch.atan2(torch.linalg.cross(a, t, dim=-1).norm(dim=-1),
                                    torch.gather(c, -1, k).squeeze(-1).abs()))
    at_corner = bc.tangent_at_corner

    def _stat(x, f):
        return float(f(x)) if x.numel() else float("nan")

    return {
        "feature_curve_alignment_mean_deg": _stat(ang[~at_corner], torch.mean),
        "feature_curve_alignment_max_deg": _stat(ang[~at_corner], torch.max),
        "feature_curve_corner_alignment_mean_deg": _stat(ang[at_corner], torch.mean),
        "feature_curve_corner_alignment_max_deg": _stat(ang[at_corner], torch.max),
        "n_feature_curve_edges": int(bc.feature_edges.shape[0]),
        "n_feature_corners": int(bc.corner_vertices.numel()),
    }


def feature_vertices(mesh, angle_deg: float = 30.0) -> torch.Tensor:
    """Sorted endpoints ``(Vf,)`` long of :func:`feature_edges`."""
    return torch.unique(feature_edges(mesh, angle_deg).reshape(-1))
