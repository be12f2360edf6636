"""Cell complexes: tetrahedral meshes and polygonal surface complexes, topology built once.

Conventions (docs/architecture.md, CONVENTIONS §1):

- A tet ``[a b c d]`` is positively oriented when ``((b-a) x (c-a)) . (d-a) > 0``.
- Edges are stored canonically ``(i, j)`` with ``i < j``, rows sorted lexicographically.
  A cell refers to an edge by index and sign: ``+1`` when the cell traverses it as stored.
- Faces of a tet mesh are stored as sorted triangles ``[a < b < c]``, rows sorted
  lexicographically. ``∂[abcd] = [bcd] - [acd] + [abd] - [abc]`` and
  ``∂[abc] = [bc] - [ac] + [ab]`` define the incidence signs.
- Topology is built once, vectorized, into integer (``torch.long``) buffers; geometry
  (barycenters, normals) follows the dtype and device of ``vertices``. Nothing here is meant
  to be differentiated through the topology.

Every validation failure raises :class:`MeshError` naming the offending element indices
(the first few and the count); a wrong index dtype raises :class:`TypeError`.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from ..tolerances import get_eps
from ..dec.transport import pair_list

__all__ = ["MeshError", "TetMesh", "CellComplex", "FaceGroup", "tet_mesh_as_cell_complex"]

# Multiplier of get_eps("degenerate", dtype): a tet is degenerate when
# |6 vol| <= DEGENERATE_FACTOR * eps * (longest edge)^3. The factor leaves room for the
# rounding error of the 3x3 determinant (a few ulps of L^3) in float32.
DEGENERATE_FACTOR = 10.0

# Local faces of a tet: face k is opposite local vertex k, vertices in ascending local order,
# with coefficient (-1)^k in ∂[abcd] = [bcd] - [acd] + [abd] - [abc].
_TET_FACES = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
_TET_FACE_COEF = (1, -1, 1, -1)


class MeshError(ValueError):
    """Invalid mesh or complex (shape, range, geometry or topology); the message names the
    offending elements."""


# ----------------------------------------------------------------------------- helpers
def _few(idx, k: int = 5) -> str:
    """``"[3, 17, 20, ...] (count 12)"`` for an index array."""
    idx = np.asarray(idx).reshape(-1)
    head = ", ".join(str(int(i)) for i in idx[:k])
    more = ", ..." if idx.size > k else ""
    return f"[{head}{more}] (count {idx.size})"


def _few_rows(rows, k: int = 5) -> str:
    """``"(3, 17), (4, 9), ... (count 12)"`` for a 2-D integer array."""
    rows = np.asarray(rows)
    head = ", ".join("(" + ", ".join(str(int(x)) for x in r) + ")" for r in rows[:k])
    more = ", ..." if len(rows) > k else ""
    return f"{head}{more} (count {len(rows)})"


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


def _as_float_tensor(vertices, dtype, device, what="vertices") -> torch.Tensor:
    if isinstance(vertices, torch.Tensor):
        v = vertices.detach()
    else:
        v = torch.as_tensor(np.asarray(vertices))
    if v.dtype == torch.bool or v.is_complex():
        raise TypeError(f"{what} must be real numbers, got dtype {v.dtype}")
    if dtype is None:
        dtype = v.dtype if v.is_floating_point() else torch.get_default_dtype()
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch dtype, got {dtype}")
    return v.to(device=device if device is not None else v.device, dtype=dtype)


def _as_index_array(idx, what: str) -> np.ndarray:
    """Integer index array as int64 numpy; float/bool input raises TypeError."""
    if isinstance(idx, torch.Tensor):
        if idx.is_floating_point() or idx.is_complex() or idx.dtype == torch.bool:
            raise TypeError(f"{what} must have an integer dtype, got {idx.dtype}")
        return idx.detach().cpu().numpy().astype(np.int64)
    a = np.asarray(idx)
    if a.size == 0 and a.dtype.kind == "f":
        a = a.astype(np.int64)
    if a.dtype.kind not in "iu":
        raise TypeError(f"{what} must have an integer dtype, got {a.dtype}")
    return a.astype(np.int64)


def _check_finite(v: torch.Tensor, what: str = "vertices") -> None:
    bad = ~torch.isfinite(v).all(dim=1)
    if bool(bad.any()):
        raise MeshError(f"{what} have NaN/inf coordinates at vertex indices {_few(bad.nonzero().flatten().cpu().numpy())}")


def _edge_keys(edges: np.ndarray, V: int) -> np.ndarray:
    return edges[:, 0] * V + edges[:, 1]


# ----------------------------------------------------------------------------- TetMesh
class _Derived:
    """Derived data cached by the mesh itself (geometry-central's ``requireX()``).

    ``mesh.require(name, builder)`` returns ``builder(mesh)`` built once per mesh and cached
    under ``name`` (tables of gather indices, kernel layouts, ...). ``to()`` gives the copy an
    empty cache, so derived data always lives on the copy's device. Builders must depend only
    on the mesh (topology and geometry), never on values passed to an operator.
    """

    def require(self, name: str, builder):
        cache = self.__dict__.setdefault("_derived", {})
        if name not in cache:
            cache[name] = builder(self)
        return cache[name]

    def _fresh_copy(self):
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.__dict__["_derived"] = {}
        return new


class TetMesh(_Derived):
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

    Buffers (``torch.long`` unless said; see docs/architecture.md):
        - ``vertices (V,3)`` float, ``tets (T,4)`` positively oriented
          (``((b-a)x(c-a)).(d-a) > 0``).
        - ``edges (E,2)``: ``edges[:,0] < edges[:,1]``, rows sorted lexicographically.
        - ``faces (F,3)``: rows sorted ascending, rows sorted lexicographically.
        - ``tet_edges (T,6)``, ``tet_edge_signs (T,6)``: local pairs ``01,02,03,12,13,23``
          (``transport.pair_list(4)``); sign ``+1`` iff ``edges[tet_edges[t,p]] ==
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
            longest edge), inverted tets (unless ``reorient``), a face shared by more than two
            tets, two tets on the same side of a face (overlap), unreferenced vertices with
            ``unreferenced="error"``.
    """

    _INT_BUFFERS = (
        "tets", "edges", "faces", "tet_edges", "tet_edge_signs", "tet_faces", "tet_face_signs",
        "face_edges", "face_edge_signs", "face_tets", "boundary_faces", "boundary_face_index",
        "boundary_vertices", "kept_vertices", "_edge_keys",
    )
    _FLOAT_BUFFERS = (
        "vertices", "boundary_vertex_normals", "edge_barycenters", "face_barycenters",
        "tet_barycenters",
    )

    def __init__(self, vertices, tets, *, reorient: bool = False, unreferenced: str = "warn",
                 dtype: torch.dtype | None = None, device=None):
        if unreferenced not in ("warn", "drop", "error"):
            raise ValueError(f"unreferenced must be 'warn', 'drop' or 'error', got {unreferenced!r}")
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
        lt = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.long, device=device)  # noqa: E731

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
        lf = t[:, np.array(_TET_FACES)]  # (T,4,3) local order
        lf_flat = lf.reshape(-1, 3)
        parity = _sort_parity(lf_flat).reshape(T, 4)
        faces, f_inv, f_cnt = _unique_rows(np.sort(lf_flat, axis=1))
        tet_faces = f_inv.reshape(T, 4)
        tet_face_signs = parity * np.array(_TET_FACE_COEF)[None, :]
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

        # face edges: bc, ac, ab of the sorted face, coefficients +1, -1, +1
        self._V = V
        self._edge_keys = lt(ukeys)
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
    def n_vertices(self) -> int:
        """Number of vertices ``V``."""
        return int(self.vertices.shape[0])

    @property
    def n_edges(self) -> int:
        """Number of edges ``E``."""
        return int(self.edges.shape[0])

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

    @property
    def dtype(self) -> torch.dtype:
        """Float dtype of the geometry (``vertices.dtype``)."""
        return self.vertices.dtype

    @property
    def device(self) -> torch.device:
        """Device of all buffers."""
        return self.vertices.device

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
        n_be = np.unique(_edge_keys(be, self._V)).size
        return int(self.boundary_vertices.numel()) - n_be + int(bf.shape[0])

    def edge_index(self, i, j) -> tuple[torch.Tensor, torch.Tensor]:
        """Canonical edge ids of vertex pairs.

        Args:
            i, j: integer tensors (or arrays) of the same shape ``(...)``.

        Returns:
            ``(edge_id (...), sign (...))``: ``edges[edge_id] == (min(i,j), max(i,j))`` and
            sign ``+1`` where ``i < j`` (the pair runs as stored), ``-1`` otherwise.

        Raises:
            MeshError: a pair that is not an edge (the message lists the first few).
        """
        i = torch.as_tensor(i, device=self.device).long()
        j = torch.as_tensor(j, device=self.device).long()
        lo, hi = torch.minimum(i, j), torch.maximum(i, j)
        ok = (lo >= 0) & (hi < self._V) & (lo != hi)
        key = lo.clamp(0, self._V - 1) * self._V + hi.clamp(0, self._V - 1)
        pos = torch.searchsorted(self._edge_keys, key.reshape(-1)).reshape(key.shape)
        pos_c = pos.clamp(max=self._edge_keys.numel() - 1)
        ok = ok & (self._edge_keys[pos_c] == key)
        if not bool(ok.all()):
            bad = (~ok).nonzero()
            pairs = torch.stack([i[~ok], j[~ok]], dim=1).cpu().numpy()
            raise MeshError(f"vertex pairs that are not edges: {_few_rows(pairs)} at positions {_few_rows(bad.cpu().numpy())}")
        return pos_c, torch.where(i < j, 1, -1).to(torch.long)

    def face_adjacency(self) -> torch.Tensor:
        """``(Fi, 2)`` pairs of tets sharing an interior face: row ``k`` is
        ``face_tets[interior_faces[k]]`` (column 0 has the face with sign +1)."""
        ft = self.face_tets
        return ft[(ft >= 0).all(dim=1)]

    def to(self, device=None, dtype: torch.dtype | None = None) -> "TetMesh":
        """Copy on ``device`` with float buffers in ``dtype`` (topology is not rebuilt)."""
        if dtype is not None and not dtype.is_floating_point:
            raise TypeError(f"dtype must be a floating torch dtype, got {dtype}")
        new = self._fresh_copy()
        for name in self._INT_BUFFERS:
            setattr(new, name, getattr(self, name).to(device=device))
        for name in self._FLOAT_BUFFERS:
            setattr(new, name, getattr(self, name).to(device=device, dtype=dtype))
        return new

    def boundary_complex(self, compact: bool = True) -> "CellComplex":
        """The boundary surface as a :class:`CellComplex` of outward triangles.

        With ``compact=True`` (default) it holds only the boundary vertices: its vertex ``i``
        is mesh vertex ``boundary_vertices[i]`` and its face ``k`` is ``boundary_faces[k]``
        re-indexed. With ``compact=False`` it keeps all mesh vertices (interior ones unused).
        """
        if not compact:
            return CellComplex(self.vertices, self.boundary_faces)
        remap = torch.full((self.n_vertices,), -1, dtype=torch.long, device=self.device)
        remap[self.boundary_vertices] = torch.arange(self.boundary_vertices.numel(), device=self.device)
        return CellComplex(self.vertices[self.boundary_vertices], remap[self.boundary_faces])

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


def _signed_volumes6(v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    p = v[t]
    a = p[:, 0]
    return (torch.linalg.cross(p[:, 1] - a, p[:, 2] - a, dim=-1) * (p[:, 3] - a)).sum(-1)


# ----------------------------------------------------------------------------- CellComplex
@dataclass(frozen=True)
class FaceGroup:
    """All faces of one size ``m`` of a :class:`CellComplex`.

    Attributes:
        loops: ``(F_m, m)`` vertex loops ``x_0 .. x_{m-1}`` (``x_0`` the evaluation vertex).
        loop_edges: ``(F_m, m)`` canonical edge id of ``x_k -> x_{k+1 mod m}``.
        loop_signs: ``(F_m, m)`` ``+1`` where the stored edge ``(i<j)`` runs as traversed.
        face_ids: ``(F_m,)`` index of each face in the global face order.
    """

    loops: torch.Tensor
    loop_edges: torch.Tensor
    loop_signs: torch.Tensor
    face_ids: torch.Tensor

    def to(self, device=None) -> "FaceGroup":
        """Copy with all index tensors on ``device``."""
        return FaceGroup(*(x.to(device=device) for x in (self.loops, self.loop_edges, self.loop_signs, self.face_ids)))


class CellComplex(_Derived):
    """Polygonal 2-complex (faces of any size), optionally with polyhedral 3-cells.

    Args:
        vertices: ``(V, 3)`` float tensor/array.
        faces: list of vertex loops (sequences of length ``>= 3``) or an ``(F, m)`` integer
            array/tensor. Face ``f`` keeps its position ``f`` in the global face order.
        cells: optional 3-cells, either a list of lists of ``(face_id, sign)`` or a pair
            ``(face_ids (C, k), signs (C, k))`` of integer arrays. Stored CSR-style as
            ``cell_faces (N,)``, ``cell_face_signs (N,)``, ``cell_offsets (C+1,)``.
        dtype, device: of the geometry (default those of ``vertices``).

    Attributes:
        ``vertices (V,3)``, ``edges (E,2)`` canonical (``i<j``, rows sorted),
        ``face_groups: dict[int, FaceGroup]`` keyed by face size ``m``,
        ``face_sizes (F,)``, ``edge_face_count (E,)`` number of faces using each edge.

    Validation at construction (raises :class:`MeshError` naming indices): wrong shapes, no
    faces, NaN/inf coordinates, indices out of range, faces with fewer than 3 vertices, faces
    with a repeated vertex (degenerate loops), bad cell face ids or signs. Edges used by more
    than two faces, boundary edges and inconsistent orientation are allowed (a tet mesh as a
    complex has them); :meth:`is_edge_manifold`, :meth:`is_closed`,
    :meth:`is_consistently_oriented` report them and :meth:`check_closed_manifold` raises.
    """

    def __init__(self, vertices, faces, cells=None, *, dtype: torch.dtype | None = None, device=None):
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
        self._V = V
        self._edge_keys_np = ukeys
        lt = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.long, device=device)  # noqa: E731
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
        lt = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.long, device=device)  # noqa: E731
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
    def n_vertices(self) -> int:
        """Number of vertices ``V``."""
        return int(self.vertices.shape[0])

    @property
    def n_edges(self) -> int:
        """Number of edges ``E``."""
        return int(self.edges.shape[0])

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

    def to(self, device=None, dtype: torch.dtype | None = None) -> "CellComplex":
        """Copy on ``device`` with ``vertices`` in ``dtype``."""
        new = self._fresh_copy()
        new.vertices = self.vertices.to(device=device, dtype=dtype)
        for name in ("edges", "edge_face_count", "face_sizes", "cell_faces", "cell_face_signs", "cell_offsets"):
            setattr(new, name, getattr(self, name).to(device=device))
        new.face_groups = {m: g.to(device) for m, g in self.face_groups.items()}
        return new

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

    def edge_index(self, i, j) -> tuple[torch.Tensor, torch.Tensor]:
        """Canonical edge ids and signs (``+1`` where ``i < j``) of vertex pairs ``i, j (...)``;
        raises :class:`MeshError` naming pairs that are not edges."""
        i = np.asarray(torch.as_tensor(i).cpu()).astype(np.int64)
        j = np.asarray(torch.as_tensor(j).cpu()).astype(np.int64)
        key = np.minimum(i, j) * self._V + np.maximum(i, j)
        pos = np.searchsorted(self._edge_keys_np, key).clip(max=self._edge_keys_np.size - 1)
        ok = (self._edge_keys_np[pos] == key) & (i != j)
        if not ok.all():
            raise MeshError(f"vertex pairs that are not edges: {_few_rows(np.stack([i[~ok], j[~ok]], 1))}")
        dev = self.edges.device
        return (torch.as_tensor(pos, dtype=torch.long, device=dev),
                torch.as_tensor(np.where(i < j, 1, -1), dtype=torch.long, device=dev))


def tet_mesh_as_cell_complex(mesh: TetMesh) -> CellComplex:
    """All triangles and tets of ``mesh`` as a :class:`CellComplex`.

    Faces are the mesh's ``faces`` in order (loop ``a -> b -> c`` of the sorted triangle, so
    face id ``f`` is ``mesh.faces[f]``); cells are the tets with ``cell_faces`` =
    ``tet_faces`` and ``cell_face_signs`` = ``tet_face_signs`` (4 per cell, CSR offsets
    ``4 t``). Edges coincide with ``mesh.edges``. Its Euler characteristic is
    ``V - E + F - T``.
    """
    return CellComplex(mesh.vertices, mesh.faces, cells=(mesh.tet_faces, mesh.tet_face_signs))
