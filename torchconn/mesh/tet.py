"""Tetrahedral meshes: :class:`TetMesh`, full oriented incidence built once at construction.

Conventions (docs/architecture.md, docs/conventions.md §1):

- A tet ``[a b c d]`` is positively oriented when ``((b-a) x (c-a)) . (d-a) > 0``.
- Edges are canonical ``(i, j)``, ``i < j``, rows sorted lexicographically
  (:class:`~torchconn.mesh.base.MeshBase`).
- Faces are stored as sorted triangles ``[a < b < c]``, rows sorted lexicographically.
  ``∂[abcd] = [bcd] - [acd] + [abd] - [abc]`` and ``∂[abc] = [bc] - [ac] + [ab]`` define the
  incidence signs (:mod:`torchconn.mesh.simplex`).

Every validation failure raises :class:`MeshError` naming the offending element indices
(the first few and the count); a wrong index dtype raises :class:`TypeError`.
"""
from __future__ import annotations

import warnings

import numpy as np
import torch

from ..tolerances import get_eps
from .base import DEGENERATE_FACTOR, FaceGroup, MeshBase, _as_float_tensor, _as_index_array, _check_finite, _long, _meta_build
from .cells import CellComplex, tet_mesh_as_cell_complex
from .errors import MeshError, _few, _few_rows
from .simplex import TET_FACE_SIGNS, TET_FACES, pair_list

__all__ = ["TetMesh", "merge_duplicate_vertices"]


def _unique_rows(rows: np.ndarray):
    """Unique rows of an ``(N, k)`` integer array, sorted lexicographically.

    Returns ``(unique (U,k), inverse (N,), counts (U,))`` with ``unique[inverse] == rows``.
    """
    n = rows.shape[0]
    if n == 0:
        return rows.copy(), np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.lexsort(rows.T[::-1])
    srt = rows[order]
    new = np.ones(n, dtype=bool)
    new[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    group = np.cumsum(new) - 1
    inverse = np.empty(n, np.int64)
    inverse[order] = group
    unique = srt[new]
    counts = np.bincount(group, minlength=unique.shape[0]).astype(np.int64)
    return unique, inverse, counts


def _sort_parity(x: np.ndarray) -> np.ndarray:
    """``+1``/``-1`` parity of the permutation sorting each row of ``x (N, k)`` (distinct
    entries): ``(-1)^(number of inversions)``."""
    k = x.shape[1]
    inv = np.zeros(x.shape[0], np.int64)
    for i in range(k):  # loops over the k columns of a template, not over elements
        for j in range(i + 1, k):
            inv += x[:, i] > x[:, j]
    return np.where(inv % 2 == 0, 1, -1).astype(np.int64)


def _edge_keys(edges: np.ndarray, V: int) -> np.ndarray:
    return edges[:, 0] * V + edges[:, 1]


class TetMesh(MeshBase):
    """Tetrahedral mesh with its full oriented incidence, built once at construction.

    Args:
        vertices: ``(V, 3)`` float tensor or array (integer input is cast to the default dtype).
        tets: ``(T, 4)`` integer tensor or array of vertex indices.
        reorient: inverted tets (negative signed volume) raise :class:`MeshError` unless
            ``True``, in which case local vertices 2 and 3 of each inverted tet are swapped.
        unreferenced: what to do with vertices no tet uses: ``"warn"`` (default: warn with the
            count and first indices, keep them), ``"drop"`` (remove them and re-index tets;
            ``kept_vertices`` maps new to old indices) or ``"error"``.
        dtype, device: of the geometry (default: those of ``vertices``; integer vertices take
            ``torch.get_default_dtype()``). Integer buffers live on ``device`` too.
            ``device="meta"``: the mesh is built and validated on CPU (topology and checks need
            values) and then moved with ``.to("meta")`` (shapes only); vertices that are meta
            tensors raise ``MeshError``.

    Buffers (``torch.long`` unless said; see docs/architecture.md):
        - ``vertices (V,3)`` float, ``tets (T,4)`` positively oriented
          (``((b-a)x(c-a)).(d-a) > 0``).
        - ``edges (E,2)``: ``edges[:,0] < edges[:,1]``, rows sorted lexicographically.
        - ``faces (F,3)``: rows sorted ascending, rows sorted lexicographically.
        - ``tet_edges (T,6)``, ``tet_edge_signs (T,6)``: local pairs ``01,02,03,12,13,23``
          (``simplex.pair_list(4)``); sign ``+1`` iff ``edges[tet_edges[t,p]] ==
          (tets[t,i], tets[t,j])``.
        - ``tet_faces (T,4)``, ``tet_face_signs (T,4)``: face opposite local vertex ``k`` and its
          coefficient in ``∂[abcd] = [bcd] - [acd] + [abd] - [abc]``.
        - ``face_edges (F,3)``, ``face_edge_signs (F,3)``: edges ``bc, ac, ab`` of ``[a<b<c]``
          with coefficients ``+1, -1, +1`` from ``∂[abc] = [bc] - [ac] + [ab]``.
        - ``face_tets (F,2)``: the tet whose boundary contains the face with sign ``+1``
          (column 0) and ``-1`` (column 1), ``-1`` where there is none (boundary faces).
        - ``boundary_faces (B,3)`` outward-oriented triangles, ``boundary_face_index (B,)`` into
          ``faces``, ``boundary_vertices (Vb,)`` sorted, ``boundary_vertex_normals (Vb,3)``
          float area-weighted outward unit normals.
        - ``edge_barycenters (E,3)``, ``face_barycenters (F,3)``, ``tet_barycenters (T,3)``
          float (report Def. 4.1 points).
        - ``kept_vertices (V,)``: original index of each vertex (identity unless dropped).

    Raises:
        TypeError: non-integer ``tets`` or non-real ``vertices``.
        MeshError: wrong shapes, empty mesh, indices out of range, NaN/inf coordinates, a
            repeated vertex in a tet, duplicate tets, zero-volume tets
            (``|6 vol| <= 10 * get_eps("degenerate", dtype) * L_max^3``, ``L_max`` the tet's
            longest edge), tet volumes that overflow/underflow the dtype, inverted tets (unless
            ``reorient``), a face shared by more than two tets, two tets on the same side of a
            face (overlap), non-manifold vertices (tets meeting only at a vertex or along an
            edge, or a vertex link that is not a disc or sphere), unreferenced vertices with
            ``unreferenced="error"``.
    """

    kind = "tet"
    _INT_BUFFERS = (
        "tets", "edges", "faces", "tet_edges", "tet_edge_signs", "tet_faces", "tet_face_signs",
        "face_edges", "face_edge_signs", "face_tets", "boundary_faces", "boundary_face_index",
        "boundary_vertices", "kept_vertices",
    )
    _FLOAT_BUFFERS = (
        "vertices", "boundary_vertex_normals", "edge_barycenters", "face_barycenters",
        "tet_barycenters",
    )

    def __init__(self, vertices, tets, *, reorient: bool = False, unreferenced: str = "warn",
                 dtype: torch.dtype | None = None, device=None):
        if unreferenced not in ("warn", "drop", "error"):
            raise ValueError(f"unreferenced must be 'warn', 'drop' or 'error', got {unreferenced!r}")
        if _meta_build(vertices, device):  # build and validate on CPU, then shapes only
            cpu = TetMesh(vertices, tets, reorient=reorient, unreferenced=unreferenced, dtype=dtype, device="cpu")
            self.__dict__.update(cpu.to("meta").__dict__)
            return
        v = _as_float_tensor(vertices, dtype, device)
        device = v.device
        t = _as_index_array(tets, "tets")
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f"vertices must have shape (V, 3), got {tuple(v.shape)}")
        if t.ndim != 2 or t.shape[1] != 4:
            raise MeshError(f"tets must have shape (T, 4), got {tuple(t.shape)}")
        if v.shape[0] == 0:
            raise MeshError("empty mesh: no vertices")
        if t.shape[0] == 0:
            raise MeshError("empty mesh: no tets")
        V = v.shape[0]
        bad = np.nonzero(((t < 0) | (t >= V)).any(axis=1))[0]
        if bad.size:
            raise MeshError(f"tets with vertex indices out of range [0, {V}): tet indices {_few(bad)}, "
                            f"e.g. tet {int(bad[0])} = {t[bad[0]].tolist()}")
        _check_finite(v)
        st = np.sort(t, axis=1)
        bad = np.nonzero((st[:, 1:] == st[:, :-1]).any(axis=1))[0]
        if bad.size:
            raise MeshError(f"tets with a repeated vertex: tet indices {_few(bad)}, e.g. tet {int(bad[0])} = {t[bad[0]].tolist()}")
        _, inv, cnt = _unique_rows(st)
        dup = np.nonzero(cnt[inv] > 1)[0]
        if dup.size:
            raise MeshError(f"duplicate tets (same vertex set): tet indices {_few(dup)}")

        # --- unreferenced vertices
        used = np.zeros(V, dtype=bool)
        used[t.reshape(-1)] = True
        kept = np.arange(V, dtype=np.int64)
        if not used.all():
            unused = np.nonzero(~used)[0]
            msg = f"{unused.size} unreferenced vertices (used by no tet): indices {_few(unused)}"
            if unreferenced == "error":
                raise MeshError(msg)
            if unreferenced == "warn":
                warnings.warn(msg + "; kept (pass unreferenced='drop' to remove them)", stacklevel=2)
            else:
                kept = np.nonzero(used)[0]
                remap = np.full(V, -1, dtype=np.int64)
                remap[kept] = np.arange(kept.size)
                t = remap[t]
                v = v[torch.as_tensor(kept, device=device)]
                V = v.shape[0]

        # --- geometry checks: zero-volume and inverted tets (in the working dtype)
        tt = torch.as_tensor(t, device=device)
        vol6 = _signed_volumes6(v, tt)
        p = v[tt]
        L = torch.stack([(p[:, j] - p[:, i]).norm(dim=-1) for i, j in pair_list(4)], dim=1).amax(dim=1)
        tol = DEGENERATE_FACTOR * get_eps("degenerate", v.dtype)
        _check_volume_range(vol6, L)
        flat = (vol6.abs() <= tol * L**3).cpu().numpy()
        if flat.any():
            idx = np.nonzero(flat)[0]
            raise MeshError(f"zero-volume (degenerate) tets, |6 vol| <= {tol:g} * longest_edge^3: tet indices {_few(idx)}")
        neg = (vol6 < 0).cpu().numpy()
        if neg.any():
            idx = np.nonzero(neg)[0]
            if not reorient:
                raise MeshError(f"inverted tets (negative signed volume): tet indices {_few(idx)}; "
                                f"pass reorient=True to swap two vertices of each")
            t = t.copy()
            t[idx, 2], t[idx, 3] = t[idx, 3].copy(), t[idx, 2].copy()

        self._build(v, t, kept)

    # ------------------------------------------------------------------ construction
    def _build(self, v: torch.Tensor, t: np.ndarray, kept: np.ndarray) -> None:
        device = v.device
        V, T = v.shape[0], t.shape[0]
        lt = lambda a: _long(a, device)  # noqa: E731

        # edges
        pairs = np.array(pair_list(4))
        pe = t[:, pairs]  # (T,6,2)
        pe_s = np.sort(pe, axis=2).reshape(-1, 2)
        keys = _edge_keys(pe_s, V)
        ukeys, e_inv = np.unique(keys, return_inverse=True)
        edges = np.stack([ukeys // V, ukeys % V], axis=1)
        tet_edges = e_inv.reshape(T, 6)
        tet_edge_signs = np.where(pe[..., 0] < pe[..., 1], 1, -1)

        # faces
        lf = t[:, np.array(TET_FACES)]  # (T,4,3) local order
        lf_flat = lf.reshape(-1, 3)
        parity = _sort_parity(lf_flat).reshape(T, 4)
        faces, f_inv, f_cnt = _unique_rows(np.sort(lf_flat, axis=1))
        tet_faces = f_inv.reshape(T, 4)
        tet_face_signs = parity * np.array(TET_FACE_SIGNS)[None, :]
        bad = np.nonzero(f_cnt > 2)[0]
        if bad.size:
            tets_of = np.nonzero((tet_faces == bad[0]).any(axis=1))[0].tolist()
            raise MeshError(f"non-manifold: faces shared by more than two tets: {_few_rows(faces[bad])}; "
                            f"e.g. face {faces[bad[0]].tolist()} is in tets {tets_of}")
        # face -> tets by sign; two tets on the same side of a face overlap
        F = faces.shape[0]
        flat_sign = tet_face_signs.reshape(-1)
        flat_tet = np.repeat(np.arange(T), 4)
        face_tets = np.full((F, 2), -1, dtype=np.int64)
        col = np.where(flat_sign > 0, 0, 1)
        occ = np.bincount(f_inv * 2 + col, minlength=2 * F).reshape(F, 2)
        bad = np.nonzero((occ > 1).any(axis=1))[0]
        if bad.size:
            tets_of = np.nonzero((tet_faces == bad[0]).any(axis=1))[0].tolist()
            raise MeshError(f"overlapping tets: faces with both tets on the same side {_few_rows(faces[bad])}; "
                            f"e.g. face {faces[bad[0]].tolist()} with tets {tets_of}")
        face_tets[f_inv, col] = flat_tet
        _check_vertex_manifold(t, V, edges, faces, f_cnt, face_tets, v)

        # face edges: bc, ac, ab of the sorted face, coefficients +1, -1, +1
        fe = np.stack([_edge_keys(faces[:, [1, 2]], V), _edge_keys(faces[:, [0, 2]], V),
                       _edge_keys(faces[:, [0, 1]], V)], axis=1)
        face_edges = np.searchsorted(ukeys, fe)
        face_edge_signs = np.broadcast_to(np.array([1, -1, 1]), (F, 3))

        # boundary: faces of a single tet, oriented as induced by that (positive) tet
        bidx = np.nonzero(f_cnt == 1)[0]
        bsign = np.where(face_tets[bidx, 0] >= 0, 1, -1)
        bf = faces[bidx].copy()
        flip = bsign < 0
        bf[flip, 1], bf[flip, 2] = faces[bidx][flip, 2], faces[bidx][flip, 1]
        bverts = np.unique(bf.reshape(-1))

        self.vertices = v
        self.tets = lt(t)
        self.edges = lt(edges)
        self.faces = lt(faces)
        self.tet_edges = lt(tet_edges)
        self.tet_edge_signs = lt(tet_edge_signs)
        self.tet_faces = lt(tet_faces)
        self.tet_face_signs = lt(tet_face_signs)
        self.face_edges = lt(face_edges)
        self.face_edge_signs = lt(face_edge_signs)
        self.face_tets = lt(face_tets)
        self.boundary_faces = lt(bf)
        self.boundary_face_index = lt(bidx)
        self.boundary_vertices = lt(bverts)
        self.kept_vertices = lt(kept)
        self._geometry()

    def _geometry(self) -> None:
        """(Re)compute the float buffers from ``vertices`` (dtype/device of ``vertices``)."""
        v = self.vertices
        self.edge_barycenters = v[self.edges].mean(dim=1)
        self.face_barycenters = v[self.faces].mean(dim=1)
        self.tet_barycenters = v[self.tets].mean(dim=1)
        p = v[self.boundary_faces]
        area2 = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)  # 2 * area * n
        acc = torch.zeros_like(v)
        acc.index_add_(0, self.boundary_faces.reshape(-1), area2.repeat_interleave(3, dim=0))
        nb = acc[self.boundary_vertices]
        self.boundary_vertex_normals = nb / nb.norm(dim=1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)

    # ------------------------------------------------------------------ counts
    @property
    def n_faces(self) -> int:
        """Number of triangles ``F``."""
        return int(self.faces.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tets ``T``."""
        return int(self.tets.shape[0])

    @property
    def n_boundary_faces(self) -> int:
        """Number of boundary triangles ``B``."""
        return int(self.boundary_faces.shape[0])

    def __repr__(self) -> str:
        return (f"TetMesh(V={self.n_vertices}, E={self.n_edges}, F={self.n_faces}, T={self.n_tets}, "
                f"boundary_faces={self.n_boundary_faces}, dtype={self.dtype}, device={self.device})")

    # ------------------------------------------------------------------ geometry / topology
    def signed_volumes(self) -> torch.Tensor:
        """``(T,)`` signed volumes ``((b-a)x(c-a)).(d-a)/6`` (all positive for a valid mesh)."""
        return _signed_volumes6(self.vertices, self.tets) / 6

    def volume(self) -> torch.Tensor:
        """Total volume (0-dim tensor)."""
        return self.signed_volumes().sum()

    def euler_characteristic(self) -> int:
        """``V - E + F - T`` (1 for a ball, 0 for a solid torus)."""
        return self.n_vertices - self.n_edges + self.n_faces - self.n_tets

    def boundary_euler_characteristic(self) -> int:
        """``Vb - Eb + B`` of the boundary surface (2 per sphere component, 0 per torus)."""
        bf = self.boundary_faces.cpu().numpy()
        be = np.sort(bf[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        n_be = np.unique(_edge_keys(be, self.n_vertices)).size
        return int(self.boundary_vertices.numel()) - n_be + int(bf.shape[0])

    def face_loops(self) -> dict[int, FaceGroup]:
        """``{3: FaceGroup}``: face ``f`` as the loop ``a -> b -> c`` of ``faces[f] = [a<b<c]``,
        edges ``ab, bc, ca`` = ``face_edges[:, [2, 0, 1]]`` with signs ``+1, +1, -1`` (the loops
        of :func:`tet_mesh_as_cell_complex`). Cached by :meth:`require`."""
        def build(m: "TetMesh") -> dict[int, FaceGroup]:
            signs = torch.tensor([1, 1, -1], dtype=torch.long, device=m.device).expand(m.n_faces, 3)
            ids = torch.arange(m.n_faces, device=m.device)
            return {3: FaceGroup(m.faces, m.face_edges[:, [2, 0, 1]], signs, ids)}
        return self.require("face_loops", build)

    def face_adjacency(self) -> torch.Tensor:
        """``(Fi, 2)`` pairs of tets sharing an interior face: row ``k`` is
        ``face_tets[interior_faces[k]]`` (column 0 has the face with sign +1)."""
        ft = self.face_tets
        return ft[(ft >= 0).all(dim=1)]

    def boundary_surface(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The outward boundary surface as compact ``(V (Vb, 3) float, F (B, 3) long)`` tensors.

        Vertex ``i`` of the surface is mesh vertex ``boundary_vertices[i]``; face ``k`` is
        ``boundary_faces[k]`` re-indexed, outward oriented (counter-clockwise seen from
        outside). Same dtype/device as the mesh.
        """
        remap = torch.full((self.n_vertices,), -1, dtype=torch.long, device=self.device)
        remap[self.boundary_vertices] = torch.arange(self.boundary_vertices.numel(), device=self.device)
        return self.vertices[self.boundary_vertices], remap[self.boundary_faces]

    def boundary_complex(self, compact: bool = True) -> "CellComplex":
        """The boundary surface as a :class:`CellComplex` of outward triangles.

        With ``compact=True`` (default) it holds only the boundary vertices: its vertex ``i``
        is mesh vertex ``boundary_vertices[i]`` and its face ``k`` is ``boundary_faces[k]``
        re-indexed (:meth:`boundary_surface`). With ``compact=False`` it keeps all mesh
        vertices (interior ones unused).
        """
        if not compact:
            return CellComplex(self.vertices, self.boundary_faces)
        return CellComplex(*self.boundary_surface())

    def as_cell_complex(self) -> "CellComplex":
        """See :func:`tet_mesh_as_cell_complex`."""
        return tet_mesh_as_cell_complex(self)

    def subdivide(self) -> "TetMesh":
        """Regular 1 -> 8 red refinement with the shortest inner diagonal.

        New vertices: the ``V`` old ones followed by the ``E`` edge midpoints (vertex
        ``V + e`` is the midpoint of ``edges[e]``). Each tet gives its 4 corner tets and 4 tets
        of the inner octahedron, split along the *shortest* of its three diagonals
        (``m02-m13``, ``m01-m23``, ``m03-m12``); a fixed diagonal lets the shape quality decay
        level after level, the shortest one keeps it bounded (Zhang 1995; measured in
        ``tests/test_mesh.py``). All children are positively oriented; volume is preserved.
        """
        V = self.n_vertices
        v = torch.cat([self.vertices, self.edge_barycenters], dim=0)
        m = self.tet_edges + V  # (T,6) in local pair order 01,02,03,12,13,23
        a, b, c, d = self.tets.unbind(1)
        m01, m02, m03, m12, m13, m23 = m.unbind(1)
        corners = [
            torch.stack([a, m01, m02, m03], 1), torch.stack([m01, b, m12, m13], 1),
            torch.stack([m02, m12, c, m23], 1), torch.stack([m03, m13, m23, d], 1),
        ]

        def octa(p, q, ring):  # 4 tets around the diagonal p-q; ring = equator cycle
            return [torch.stack([p, q, ring[k], ring[(k + 1) % 4]], 1) for k in range(4)]

        # equator cycles: consecutive midpoints share a tet vertex
        options = [
            octa(m02, m13, [m01, m12, m23, m03]),
            octa(m01, m23, [m02, m03, m13, m12]),
            octa(m03, m12, [m01, m02, m23, m13]),
        ]
        diag = torch.stack([(v[p] - v[q]).norm(dim=-1) for p, q in ((m02, m13), (m01, m23), (m03, m12))], 1)
        choice = diag.argmin(dim=1)  # (T,)
        inner = [
            torch.where((choice == 0)[:, None], options[0][k], torch.where((choice == 1)[:, None], options[1][k], options[2][k]))
            for k in range(4)
        ]
        kids = torch.stack(corners + inner, dim=1).reshape(-1, 4)
        neg = _signed_volumes6(v, kids) < 0
        kids[neg] = kids[neg][:, [0, 1, 3, 2]]
        return TetMesh(v, kids, dtype=self.dtype, device=self.device)

    # ------------------------------------------------------------------ CAD tags
    @property
    def cad(self):
        """CAD entities (:class:`torchconn.mesh.cad.CadTags`) set by
        :func:`~torchconn.mesh.cad.load_cad` and :func:`~torchconn.mesh.cad.load_tagged_msh`;
        ``None`` on an untagged mesh. Read on the mesh's device (a copy made by :meth:`to` moves
        them when first read); :meth:`subdivide` drops them."""
        tags = self.__dict__.get("_cad")
        if tags is not None and tags.face_surface.device != self.device:
            tags = self.__dict__["_cad"] = tags.to(device=self.device)
        return tags

    @cad.setter
    def cad(self, tags) -> None:
        if tags is not None and tuple(tags.face_surface.shape) != (self.n_faces,):
            raise MeshError(f"CAD tags of another mesh: face_surface has shape {tuple(tags.face_surface.shape)}, "
                            f"this mesh has F = {self.n_faces} faces")
        self.__dict__["_cad"] = tags



def _check_volume_range(vol6: torch.Tensor, L: torch.Tensor) -> None:
    """MeshError when ``|6 vol|`` or ``L_max^3`` of a tet overflows to inf or underflows to 0 in
    the working dtype (float32 coordinates near 1e13 or 1e-13), which the zero-volume test
    would otherwise misreport as degenerate tets."""
    L3 = L**3
    over = ~(torch.isfinite(vol6) & torch.isfinite(L3))
    under = (L > 0) & (L3 < torch.finfo(L.dtype).tiny)
    for bad, what, fix in ((over, "overflow", "large"), (under, "underflow", "small")):
        if bool(bad.any()):
            idx = torch.nonzero(bad).flatten().cpu().numpy()
            raise MeshError(f"tet volumes {what} in {L.dtype} (longest edge {float(L[idx[0]]):.3g}, cubed is out of "
                            f"range): tet indices {_few(idx)}; the coordinates are too {fix} for this dtype: "
                            f"pass dtype=torch.float64 or rescale the vertices")


def merge_duplicate_vertices(vertices, cells) -> tuple[np.ndarray, np.ndarray]:
    """Re-index ``cells`` so that vertices with the same coordinates become one (their first copy).

    A mesh written per region, or with vertices split along a surface, repeats the vertices of
    that surface: the tets on its two sides then share no face, so the mesh is cut along a
    crack there (or, where the crack pinches, has non-manifold vertices).

    Args:
        vertices: ``(V, 3)`` float array or tensor; coordinates are compared bitwise.
        cells: ``(M, k)`` integer array or tensor of vertex indices (tets: ``k = 4``).

    Returns:
        ``(cells (M, k), merged (K, 2))`` int64 numpy arrays: the re-indexed cells and one row
        ``(copy, first)`` per vertex merged into an earlier one (the copies are then used by no
        cell: build with ``TetMesh(vertices, cells, unreferenced="drop")``). Nothing is merged
        when a coordinate is NaN/inf (:class:`TetMesh` reports those); indices out of range are
        left as they are (:class:`TetMesh` reports them).

    :func:`torchconn.io.load_tet_mesh` does this by default (``merge_duplicates=True``).
    """
    v = vertices.detach().cpu().numpy() if isinstance(vertices, torch.Tensor) else np.asarray(vertices)
    c = _as_index_array(cells, "cells")
    none = np.zeros((0, 2), np.int64)
    if v.ndim != 2 or v.shape[0] < 2 or c.size == 0 or not np.isfinite(v).all():
        return c, none
    _, first, inv = np.unique(v, axis=0, return_index=True, return_inverse=True)
    rep = first[inv.reshape(-1)]  # first vertex with the same coordinates
    dup = np.nonzero(rep != np.arange(v.shape[0]))[0]
    if dup.size == 0:
        return c, none
    inside = (c >= 0) & (c < v.shape[0])
    return np.where(inside, rep[np.where(inside, c, 0)], c), np.stack([dup, rep[dup]], axis=1)


def _check_vertex_manifold(t: np.ndarray, V: int, edges: np.ndarray, faces: np.ndarray, f_cnt: np.ndarray,
                           face_tets: np.ndarray, vertices: torch.Tensor) -> None:
    """MeshError naming the vertices whose star is not a ball or half-ball.

    A vertex ``v`` is manifold when its link (the triangles opposite ``v`` in its tets) is one
    connected sphere (interior vertex) or disc (boundary vertex):

    - connected: the tet corners at ``v`` form one component when corners of two tets sharing a
      face that contains ``v`` are joined (two tets meeting only at ``v`` or along an edge give
      two components);
    - sphere / disc: ``χ(link v) = deg_E(v) - deg_F(v) + deg_T(v)`` is 2 for an interior and 1
      for a boundary vertex (a connected link with handles or pinched points has a smaller χ).

    Vertices used by no tet are skipped (``unreferenced`` handles them). The usual cause is a
    crack of duplicated vertices (:func:`merge_duplicate_vertices`), so the message says when
    a bad vertex, or a vertex of its tets, has the same coordinates as another vertex.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    T = t.shape[0]
    inner = np.nonzero((face_tets >= 0).all(axis=1))[0]
    t0, t1 = face_tets[inner, 0], face_tets[inner, 1]
    fv = faces[inner]  # (Fi,3)
    loc0 = np.argmax(t[t0][:, None, :] == fv[:, :, None], axis=2)  # local index of each face vertex
    loc1 = np.argmax(t[t1][:, None, :] == fv[:, :, None], axis=2)
    a = (4 * t0[:, None] + loc0).reshape(-1)
    b = (4 * t1[:, None] + loc1).reshape(-1)
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(4 * T, 4 * T))
    _, label = connected_components(graph, directed=False)
    corner_vertex = t.reshape(-1)
    keys = np.unique(corner_vertex.astype(np.int64) * (4 * T) + label)  # distinct (vertex, component)
    n_comp = np.bincount(keys // (4 * T), minlength=V)
    deg_t = np.bincount(corner_vertex, minlength=V)
    chi = np.bincount(edges.reshape(-1), minlength=V) - np.bincount(faces.reshape(-1), minlength=V) + deg_t
    on_boundary = np.zeros(V, dtype=bool)
    on_boundary[faces[f_cnt == 1].reshape(-1)] = True
    expected = np.where(on_boundary, 1, 2)
    bad = np.nonzero((deg_t > 0) & ((n_comp > 1) | (chi != expected)))[0]
    if bad.size:
        # the error path only: which vertices coincide with another one (bitwise-equal coordinates)
        v = vertices.detach().cpu().numpy()
        _, group, size = np.unique(v, axis=0, return_inverse=True, return_counts=True)
        group = group.reshape(-1)
        twin = size[group] > 1
        bad_twin = bad[twin[bad]]
        v0 = int(bad_twin[0]) if bad_twin.size else int(bad[0])
        tets_of = np.nonzero((t == v0).any(axis=1))[0]
        how = (f"its {tets_of.size} tets {_few(tets_of)} form {int(n_comp[v0])} groups that meet only at the vertex "
               f"or along an edge" if n_comp[v0] > 1 else
               f"its link has Euler characteristic {int(chi[v0])}, not {int(expected[v0])}")
        msg = (f"non-manifold vertices (the tets around each do not form one ball or half-ball): vertex "
               f"indices {_few(bad)}; e.g. vertex {v0}: {how}")

        def at(i):
            return "(" + ", ".join(f"{float(x):.6g}" for x in v[i]) + ")"

        def copies(i):
            return np.nonzero(group == group[i])[0]

        merge = ("merge the coincident vertices: torchconn.io.load_tet_mesh does by default (merge_duplicates=True); "
                 "for arrays, TetMesh(vertices, torchconn.mesh.merge_duplicate_vertices(vertices, tets)[0], "
                 "unreferenced='drop')")
        near = np.unique(t[tets_of])
        near = near[twin[near]]
        if bad_twin.size:
            others = [int(i) for i in copies(v0) if i != v0]
            raise MeshError(f"{msg}. Vertex {v0} is a duplicated vertex: vertex {others[0] if len(others) == 1 else others} "
                            f"has the same coordinates {at(v0)} ({bad_twin.size} of the {bad.size} non-manifold vertices "
                            f"have coincident copies, {int(twin.sum())} vertices of the mesh in all): the mesh is cut "
                            f"along a crack of duplicated vertices; {merge}")
        if near.size:
            w = int(near[0])
            others = [int(i) for i in copies(w) if i != w]
            raise MeshError(f"{msg}. Its tets have duplicated vertices: vertex {w} at {at(w)} has the same coordinates "
                            f"as vertex {others[0] if len(others) == 1 else others} ({near.size} vertices of its tets, "
                            f"{int(twin.sum())} of the mesh in all, coincide with another vertex): the mesh is cut along a "
                            f"crack of duplicated vertices that leaves vertex {v0} shared; {merge}")
        raise MeshError(f"{msg}. Give each group of tets its own copy of the vertex, or remove the tets that touch "
                        f"only there")


def _signed_volumes6(v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    p = v[t]
    a = p[:, 0]
    return (torch.linalg.cross(p[:, 1] - a, p[:, 2] - a, dim=-1) * (p[:, 3] - a)).sum(-1)

