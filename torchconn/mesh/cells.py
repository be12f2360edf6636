"""Polygonal complexes: :class:`CellComplex` (faces of any size, optional 3-cells).

Faces are vertex loops grouped by size into :class:`~torchconn.mesh.base.FaceGroup` s; edges are
canonical ``(i<j)``, rows sorted (:class:`~torchconn.mesh.base.MeshBase`). Validation failures
raise :class:`MeshError` naming the offending indices.
"""
from __future__ import annotations


import numpy as np
import torch

from ..tolerances import get_eps
from .base import DEGENERATE_FACTOR, FaceGroup, MeshBase, _as_float_tensor, _as_index_array, _check_finite, _long, _meta_build
from .errors import MeshError, _few, _few_rows

__all__ = ["CellComplex", "tet_mesh_as_cell_complex", "face_groups_from_buffers"]


def _group_buffer(m: int, field: str) -> str:
    """Buffer name of field ``field`` of the size-``m`` face group, e.g. ``face_group3_loops``."""
    return f"face_group{m}_{field}"


def face_groups_from_buffers(buffers) -> dict[int, FaceGroup]:
    """The face groups stored in a buffer mapping of a :class:`CellComplex`
    (:meth:`CellComplex.buffers`), keyed by size ``m``."""
    sizes = sorted(int(k[len("face_group"):-len("_loops")]) for k in buffers
                   if k.startswith("face_group") and k.endswith("_loops"))
    return {m: FaceGroup(*(buffers[_group_buffer(m, f)] for f in FaceGroup.FIELDS)) for m in sizes}


class CellComplex(MeshBase):
    """Polygonal 2-complex (faces of any size), optionally with polyhedral 3-cells.

    Args:
        vertices: ``(V, 3)`` float tensor/array.
        faces: list of vertex loops (sequences of length ``>= 3``) or an ``(F, m)`` integer
            array/tensor. Face ``f`` keeps its position ``f`` in the global face order.
        cells: optional 3-cells, either a list of lists of ``(face_id, sign)`` or a pair
            ``(face_ids (C, k), signs (C, k))`` of integer arrays. Stored CSR-style as
            ``cell_faces (N,)``, ``cell_face_signs (N,)``, ``cell_offsets (C+1,)``.
        dtype, device: of the geometry (default those of ``vertices``). ``device="meta"``:
            built and validated on CPU, then moved with ``.to("meta")`` (shapes only).

    Buffers: ``vertices (V,3)``, ``edges (E,2)`` canonical (``i<j``, rows sorted),
    ``face_groups`` (a dict of :class:`FaceGroup` keyed by face size ``m``),
    ``face_sizes (F,)``, ``edge_face_count (E,)`` number of faces using each edge.

    Validation at construction (raises :class:`MeshError` naming indices): wrong shapes, no
    faces, NaN/inf coordinates, indices out of range, faces with fewer than 3 vertices, faces
    with a repeated vertex (degenerate loops), bad cell face ids or signs. Edges used by more
    than two faces, boundary edges and inconsistent orientation are allowed (a tet mesh as a
    complex has them); :meth:`is_edge_manifold`, :meth:`is_closed`,
    :meth:`is_consistently_oriented` report them and :meth:`check_closed_manifold` raises.
    """

    kind = "cells"
    _INT_BUFFERS = ("edges", "edge_face_count", "face_sizes", "cell_faces", "cell_face_signs", "cell_offsets")
    _FLOAT_BUFFERS = ("vertices",)

    def __init__(self, vertices, faces, cells=None, *, dtype: torch.dtype | None = None, device=None):
        if _meta_build(vertices, device):  # build and validate on CPU, then shapes only
            cpu = CellComplex(vertices, faces, cells, dtype=dtype, device="cpu")
            self.__dict__.update(cpu.to("meta").__dict__)
            return
        v = _as_float_tensor(vertices, dtype, device)
        device = v.device
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f"vertices must have shape (V, 3), got {tuple(v.shape)}")
        _check_finite(v)
        V = v.shape[0]
        loops = self._parse_faces(faces)
        if sum(ids.size for _, ids in loops) == 0:
            raise MeshError("empty complex: no faces")
        # group loops by size, keeping global face ids
        groups_np: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for arr, ids in loops:
            m = arr.shape[1]
            if m in groups_np:
                a0, i0 = groups_np[m]
                groups_np[m] = (np.concatenate([a0, arr]), np.concatenate([i0, ids]))
            else:
                groups_np[m] = (arr, ids)
        F = sum(ids.size for _, ids in groups_np.values())
        face_sizes = np.zeros(F, np.int64)
        for m, (arr, ids) in groups_np.items():
            face_sizes[ids] = m
            if m < 3:
                raise MeshError(f"faces with fewer than 3 vertices (size {m}): face indices {_few(ids)}")
            bad = np.nonzero(((arr < 0) | (arr >= V)).any(axis=1))[0]
            if bad.size:
                raise MeshError(f"faces with vertex indices out of range [0, {V}): face indices {_few(ids[bad])}")
            s = np.sort(arr, axis=1)
            bad = np.nonzero((s[:, 1:] == s[:, :-1]).any(axis=1))[0]
            if bad.size:
                raise MeshError(f"degenerate faces (repeated vertex in loop): face indices {_few(ids[bad])}, "
                                f"e.g. face {int(ids[bad[0]])} = {arr[bad[0]].tolist()}")
        # edges
        all_keys = []
        for m, (arr, ids) in groups_np.items():
            nxt = np.roll(arr, -1, axis=1)
            all_keys.append(np.minimum(arr, nxt).reshape(-1) * V + np.maximum(arr, nxt).reshape(-1))
        keys = np.concatenate(all_keys)
        ukeys, counts = np.unique(keys, return_counts=True)
        lt = lambda a: _long(a, device)  # noqa: E731
        self.vertices = v
        self.edges = lt(np.stack([ukeys // V, ukeys % V], axis=1))
        self.edge_face_count = lt(counts)
        self.face_sizes = lt(face_sizes)
        self.face_groups: dict[int, FaceGroup] = {}
        for m in sorted(groups_np):
            arr, ids = groups_np[m]
            nxt = np.roll(arr, -1, axis=1)
            le = np.searchsorted(ukeys, np.minimum(arr, nxt) * V + np.maximum(arr, nxt))
            ls = np.where(arr < nxt, 1, -1)
            self.face_groups[m] = FaceGroup(lt(arr), lt(le), lt(ls), lt(ids))
        self._parse_cells(cells, F, device)

    @staticmethod
    def _parse_faces(faces):
        """List of ``(loops (n, m) int64, global ids (n,))`` blocks."""
        if isinstance(faces, (torch.Tensor, np.ndarray)):
            arr = _as_index_array(faces, "faces")
            if arr.ndim != 2:
                raise MeshError(f"faces array must have shape (F, m), got {arr.shape}")
            return [(arr, np.arange(arr.shape[0]))]
        faces = list(faces)
        lens = np.array([len(f) for f in faces], dtype=np.int64)
        out = []
        for m in np.unique(lens):
            ids = np.nonzero(lens == m)[0]
            arr = _as_index_array([list(faces[i]) for i in ids], "faces").reshape(ids.size, int(m))
            out.append((arr, ids))
        return out

    def _parse_cells(self, cells, F: int, device) -> None:
        lt = lambda a: _long(a, device)  # noqa: E731
        if cells is None:
            fid, sg, off = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(1, np.int64)
        elif isinstance(cells, tuple) and len(cells) == 2 and not isinstance(cells[0], (list, tuple)):
            fid2 = _as_index_array(cells[0], "cell face ids")
            sg2 = _as_index_array(cells[1], "cell signs")
            if fid2.shape != sg2.shape or fid2.ndim != 2:
                raise MeshError(f"cells as arrays must be (C, k) face ids and (C, k) signs, got {fid2.shape}, {sg2.shape}")
            fid, sg = fid2.reshape(-1), sg2.reshape(-1)
            off = np.arange(fid2.shape[0] + 1) * fid2.shape[1]
        else:
            cells = [list(c) for c in cells]
            lens = np.array([len(c) for c in cells], dtype=np.int64)
            off = np.concatenate([[0], np.cumsum(lens)])
            flat = np.array([fs for c in cells for fs in c], dtype=np.int64).reshape(-1, 2)
            fid, sg = flat[:, 0], flat[:, 1]
        cell_of = np.repeat(np.arange(off.size - 1), np.diff(off))
        bad = np.nonzero((fid < 0) | (fid >= F))[0]
        if bad.size:
            raise MeshError(f"cells referring to face ids out of range [0, {F}): cell indices {_few(np.unique(cell_of[bad]))}")
        bad = np.nonzero(np.abs(sg) != 1)[0]
        if bad.size:
            raise MeshError(f"cell face signs must be +1 or -1: cell indices {_few(np.unique(cell_of[bad]))}")
        self.cell_faces, self.cell_face_signs, self.cell_offsets = lt(fid), lt(sg), lt(off)

    # ------------------------------------------------------------------ counts / constructors
    @classmethod
    def from_triangles(cls, vertices, faces, **kw) -> "CellComplex":
        """Complex of triangles ``faces (F, 3)`` (loops ``x0 -> x1 -> x2`` as given)."""
        return cls(vertices, faces, **kw)

    @property
    def n_faces(self) -> int:
        """Number of polygonal faces ``F`` (all sizes)."""
        return int(self.face_sizes.shape[0])

    @property
    def n_cells(self) -> int:
        """Number of 3-cells ``C`` (0 without cells)."""
        return int(self.cell_offsets.shape[0]) - 1

    def __repr__(self) -> str:
        sizes = {m: int(g.face_ids.numel()) for m, g in self.face_groups.items()}
        return (f"CellComplex(V={self.n_vertices}, E={self.n_edges}, F={self.n_faces} {sizes}, "
                f"cells={self.n_cells}, dtype={self.vertices.dtype})")

    def euler_characteristic(self) -> int:
        """``V - E + F`` (``- C`` when there are 3-cells), with ``V`` all stored vertices."""
        return self.n_vertices - self.n_edges + self.n_faces - self.n_cells

    def buffers(self) -> dict[str, torch.Tensor]:
        """All tensors of the complex by name; face group ``m`` contributes
        ``face_group{m}_loops``, ``_loop_edges``, ``_loop_signs``, ``_face_ids``
        (:func:`face_groups_from_buffers` reads them back)."""
        out = super().buffers()
        for m, g in self.face_groups.items():
            out.update({_group_buffer(m, f): getattr(g, f) for f in FaceGroup.FIELDS})
        return out

    def _set_buffers(self, buffers: dict[str, torch.Tensor]) -> None:
        super()._set_buffers({k: v for k, v in buffers.items() if not k.startswith("face_group")})
        self.face_groups = face_groups_from_buffers(buffers)

    def face_loops(self) -> dict[int, FaceGroup]:
        """The face groups keyed by size ``m`` (``face_groups``)."""
        return self.face_groups

    # ------------------------------------------------------------------ geometry
    def face_vector_areas(self) -> torch.Tensor:
        """``(F, 3)`` vector areas ``½ Σ_k x_k × x_{k+1}`` (for a planar polygon: area × unit
        normal, right-hand rule along the loop)."""
        out = torch.zeros(self.n_faces, 3, dtype=self.vertices.dtype, device=self.vertices.device)
        for g in self.face_groups.values():
            p = self.vertices[g.loops]
            out[g.face_ids] = 0.5 * torch.linalg.cross(p, p.roll(-1, dims=1), dim=-1).sum(1)
        return out

    def face_areas(self) -> torch.Tensor:
        """``(F,)`` norms of the vector areas."""
        return self.face_vector_areas().norm(dim=-1)

    def face_normals(self) -> torch.Tensor:
        """``(F, 3)`` unit normals (vector area / its norm; zero for a zero-area face)."""
        a = self.face_vector_areas()
        return a / a.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(a.dtype).tiny)

    def face_barycenters(self) -> torch.Tensor:
        """``(F, 3)`` vertex averages of the loops."""
        out = torch.zeros(self.n_faces, 3, dtype=self.vertices.dtype, device=self.vertices.device)
        for g in self.face_groups.values():
            out[g.face_ids] = self.vertices[g.loops].mean(1)
        return out

    # ------------------------------------------------------------------ topology reports
    def _incidences(self):
        """``(edge, face, sign)`` numpy arrays of all loop-edge incidences."""
        e, f, s = [], [], []
        for g in self.face_groups.values():
            e.append(g.loop_edges.reshape(-1).cpu().numpy())
            s.append(g.loop_signs.reshape(-1).cpu().numpy())
            f.append(np.repeat(g.face_ids.cpu().numpy(), g.loops.shape[1]))
        return np.concatenate(e), np.concatenate(f), np.concatenate(s)

    def boundary_edges(self) -> torch.Tensor:
        """``(Eb,)`` ids of edges with exactly one incident face."""
        return (self.edge_face_count == 1).nonzero().flatten()

    def nonmanifold_edges(self) -> torch.Tensor:
        """``(En,)`` ids of edges used by more than two faces."""
        return (self.edge_face_count > 2).nonzero().flatten()

    def inconsistent_edges(self) -> torch.Tensor:
        """``(Ei,)`` ids of two-face edges that both faces traverse in the same direction."""
        e, _, s = self._incidences()
        ssum = np.bincount(e, weights=s, minlength=self.n_edges)
        cnt = self.edge_face_count.cpu().numpy()
        bad = np.nonzero((cnt == 2) & (ssum != 0))[0]
        return torch.as_tensor(bad, dtype=torch.long, device=self.edges.device)

    def is_closed(self) -> bool:
        """No edge has exactly one incident face."""
        return self.boundary_edges().numel() == 0

    def is_edge_manifold(self) -> bool:
        """No edge has more than two incident faces."""
        return self.nonmanifold_edges().numel() == 0

    def is_consistently_oriented(self) -> bool:
        """Every two-face edge is traversed once in each direction."""
        return self.inconsistent_edges().numel() == 0

    def check_closed_manifold(self) -> None:
        """Raise :class:`MeshError` unless the surface is closed, edge-manifold and
        consistently oriented; the message names the offending edges as vertex pairs."""
        ed = self.edges.cpu().numpy()
        b = self.boundary_edges().cpu().numpy()
        if b.size:
            raise MeshError(f"surface is not closed: {b.size} boundary edges, e.g. {_few_rows(ed[b])}")
        n = self.nonmanifold_edges().cpu().numpy()
        if n.size:
            raise MeshError(f"surface is not edge-manifold: {n.size} edges in more than two faces, e.g. {_few_rows(ed[n])}")
        i = self.inconsistent_edges().cpu().numpy()
        if i.size:
            raise MeshError(f"surface is not consistently oriented: {i.size} edges traversed twice in the same "
                            f"direction, e.g. {_few_rows(ed[i])}")

    def degenerate_faces(self, rel_tol: float | None = None) -> torch.Tensor:
        """``(Fd,)`` ids of faces whose area is ``<= rel_tol * (longest loop edge)^2``
        (default ``10 * get_eps("degenerate", dtype)``)."""
        if rel_tol is None:
            rel_tol = DEGENERATE_FACTOR * get_eps("degenerate", self.vertices.dtype)
        area = self.face_areas()
        lmax = torch.zeros_like(area)
        for g in self.face_groups.values():
            p = self.vertices[g.loops]
            lmax[g.face_ids] = (p.roll(-1, dims=1) - p).norm(dim=-1).amax(dim=1)
        return (area <= rel_tol * lmax**2).nonzero().flatten()

    def enclosed_volume(self) -> torch.Tensor:
        """Signed volume enclosed by a closed, manifold, consistently oriented surface
        (positive for outward orientation): ``Σ_f Σ_k det(x_0, x_k, x_{k+1}) / 6`` over fan
        triangles. Calls :meth:`check_closed_manifold` first."""
        self.check_closed_manifold()
        vol = self.vertices.new_zeros(())
        for g in self.face_groups.values():
            p = self.vertices[g.loops]
            x0 = p[:, :1].expand_as(p[:, 1:-1])
            vol = vol + (torch.linalg.cross(p[:, 1:-1], p[:, 2:], dim=-1) * x0).sum() / 6
        return vol

    def face_adjacency(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Pairs of faces sharing an edge.

        Returns:
            ``(pairs (P, 2), shared_edge (P,))`` with ``pairs[:,0] < pairs[:,1]`` global face
            ids; an edge with ``c`` faces contributes all ``c(c-1)/2`` pairs.
        """
        e, f, _ = self._incidences()
        order = np.lexsort((f, e))
        e, f = e[order], f[order]
        maxc = int(self.edge_face_count.max())
        pa, pb, pe = [], [], []
        for d in range(1, maxc):  # loop over the valence, not over elements
            same = e[d:] == e[:-d]
            pa.append(f[:-d][same]); pb.append(f[d:][same]); pe.append(e[d:][same])
        dev = self.edges.device
        if not pa:
            return torch.zeros(0, 2, dtype=torch.long, device=dev), torch.zeros(0, dtype=torch.long, device=dev)
        pa, pb, pe = np.concatenate(pa), np.concatenate(pb), np.concatenate(pe)
        pairs = np.stack([np.minimum(pa, pb), np.maximum(pa, pb)], axis=1)
        o = np.lexsort((pairs[:, 1], pairs[:, 0]))
        return (torch.as_tensor(pairs[o], dtype=torch.long, device=dev),
                torch.as_tensor(pe[o], dtype=torch.long, device=dev))


def tet_mesh_as_cell_complex(mesh: MeshBase) -> CellComplex:
    """All triangles and tets of ``mesh`` as a :class:`CellComplex`.

    Faces are the mesh's ``faces`` in order (loop ``a -> b -> c`` of the sorted triangle, so
    face id ``f`` is ``mesh.faces[f]``); cells are the tets with ``cell_faces`` =
    ``tet_faces`` and ``cell_face_signs`` = ``tet_face_signs`` (4 per cell, CSR offsets
    ``4 t``). Edges coincide with ``mesh.edges``. Its Euler characteristic is
    ``V - E + F - T``.
    """
    return CellComplex(mesh.vertices, mesh.faces, cells=(mesh.tet_faces, mesh.tet_face_signs))
