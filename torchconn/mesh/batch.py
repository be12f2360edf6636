"""Several tet meshes as one: the disjoint union :class:`TetMeshBatch` (:func:`join_meshes`).

A learning pipeline that trains on many meshes runs every operator once on their disjoint
union, as pytorch3d's ``join_meshes_as_batch`` and PyG's ``Batch.from_data_list`` do: the
union is a :class:`~torchconn.mesh.TetMesh` (so every operator, module and loss takes it as
it is) that also keeps, per mesh, where its vertices, edges, faces, tets and boundary
elements start, and splits any per-element result back into one tensor per mesh.

Order of the union (canonical orders hold, docs/architecture.md):

- vertices and tets: mesh 0's, then mesh 1's, ... (mesh ``k``'s vertex ``i`` is union vertex
  ``vertex_offsets[k] + i``, its tet ``t`` union tet ``tet_offsets[k] + t``);
- edges, faces, boundary faces and boundary vertices: the same concatenation. This *is* the
  canonical order of the union: mesh ``k``'s vertex ids all lie in
  ``[vertex_offsets[k], vertex_offsets[k + 1])``, so sorting the union's edges ``(i < j)`` or
  sorted triangles lexicographically puts mesh 0's rows first, then mesh 1's, ..., and adding
  one offset to a block keeps its own sorted order. Boundary faces follow the face order and
  boundary vertices are sorted, so they concatenate too. The buffers are therefore built by
  offsetting and concatenating (no re-sorting, no re-validation) and equal those of
  ``TetMesh(cat(vertices), cat(tets + vertex offset))`` (``tests/test_mesh_batch.py``).
- every index buffer is offset by the count of the element kind it indexes (``tet_edges`` by
  edges, ``tet_faces`` and ``boundary_face_index`` by faces, ``face_tets`` by tets with ``-1``
  kept, ...); signs and geometry are copied.

:meth:`TetMeshBatch.split` undoes the concatenation for values: ``split(x, "face")`` cuts the
face dimension of ``x (*batch, F, ...)`` at the face offsets into ``(*batch, F_k, ...)`` views.
The inverse, joining per-mesh values (a connection per mesh, a frame field per mesh), is
``torch.cat(values, dim)`` along the element dimension.
"""
from __future__ import annotations

from typing import Sequence

import torch

from .cad import CadTags
from .errors import MeshError
from .tet import TetMesh

__all__ = ["TetMeshBatch", "join_meshes", "ELEMENT_KINDS"]

#: Element kinds a :class:`TetMeshBatch` splits by, with the buffer whose rows they count.
ELEMENT_KINDS = {
    "vertex": "vertices",
    "edge": "edges",
    "face": "faces",
    "tet": "tets",
    "boundary_face": "boundary_faces",
    "boundary_vertex": "boundary_vertices",
}

# index buffer -> element kind its entries index (offset by that kind's counts when joining)
_INDEX_OF = {
    "tets": "vertex", "edges": "vertex", "faces": "vertex", "boundary_faces": "vertex",
    "boundary_vertices": "vertex",
    "tet_edges": "edge", "face_edges": "edge",
    "tet_faces": "face", "boundary_face_index": "face",
    "face_tets": "tet",
}
_SIGNS = ("tet_edge_signs", "tet_face_signs", "face_edge_signs")


class TetMeshBatch(TetMesh):
    """The disjoint union of tet meshes, with the offsets to split results back per mesh.

    Args:
        meshes: a non-empty sequence of :class:`~torchconn.mesh.TetMesh` with one float dtype and
            one device (a ``TetMeshBatch`` among them counts as one mesh).

    A ``TetMeshBatch`` *is* a :class:`~torchconn.mesh.TetMesh` (``V = sum V_k``, ``E = sum E_k``,
    ...; buffers in the order of the module docstring), so ``Curvature(batch)``,
    ``Torsion(batch)``, ``CovariantD(batch)``, ``AveragedCovariantD(batch)``,
    ``BianchiCheck(batch)``, ``ConnectionField(batch.edges, batch.n_vertices)``,
    ``Connection.random_on_mesh(batch)`` and ``frames.loss.FrameFieldLoss(batch, ...)`` take it
    unchanged. Per-element results equal those of separate calls on each mesh, concatenated
    (the operators are local: nothing couples two meshes). Reductions over elements are over
    the whole union: a mean (``FrameFieldLoss``'s terms) is the element-count-weighted mean of
    the per-mesh means, a max (``BianchiCheck``) the max over the meshes; per-mesh reductions
    come from :meth:`split` or :meth:`mesh_index` (e.g. ``index_add_``).

    Per mesh: :attr:`n_meshes` ``B``; :meth:`counts` and :meth:`offsets` of each element kind
    (:data:`ELEMENT_KINDS`) as Python ints (no device sync); :meth:`mesh_index`; :meth:`split`.

    CAD tags (``mesh.cad``, :class:`~torchconn.mesh.cad.CadTags`): carried when every mesh has
    them (faces, feature edges and corners offset; the tag values are kept, so the same tag in
    two meshes names two different CAD entities); ``None`` when none has them; a mix raises
    :class:`MeshError` (a tagged mesh takes its feature curves from its tags, an untagged one
    from dihedral angles, and the union could not do both).

    ``kept_vertices`` of the union is the identity (its vertices are the meshes' vertices, none
    dropped). :meth:`to` keeps the offsets; :meth:`subdivide` returns a plain ``TetMesh``
    (its new vertices are not grouped by mesh).

    Raises:
        TypeError: an element that is not a ``TetMesh``.
        ValueError: no meshes.
        MeshError: meshes of different dtypes or devices (naming the first mismatch and how to
            convert), or CAD tags on some meshes only.
    """

    def __init__(self, meshes: Sequence[TetMesh]):
        if isinstance(meshes, TetMesh):
            raise TypeError("join_meshes takes a sequence of TetMesh, got a single TetMesh; pass [mesh]")
        meshes = list(meshes)
        if not meshes:
            raise ValueError("join_meshes needs at least one TetMesh, got an empty sequence")
        for k, m in enumerate(meshes):
            if not isinstance(m, TetMesh):
                raise TypeError(f"join_meshes: meshes[{k}] is a {type(m).__name__}, not a TetMesh")
        first = meshes[0]
        for k, m in enumerate(meshes[1:], 1):
            if m.dtype != first.dtype:
                raise MeshError(f"join_meshes: meshes[{k}] has dtype {m.dtype} but meshes[0] has {first.dtype}; "
                                f"convert first, e.g. mesh.to(dtype={first.dtype})")
            if m.device != first.device:
                raise MeshError(f"join_meshes: meshes[{k}] is on {m.device} but meshes[0] is on {first.device}; "
                                f"move first, e.g. mesh.to({str(first.device)!r})")
        counts = {kind: tuple(int(getattr(m, buf).shape[0]) for m in meshes) for kind, buf in ELEMENT_KINDS.items()}
        self.__dict__["_counts"] = counts
        self.__dict__["_offsets"] = {kind: _cumsum(c) for kind, c in counts.items()}
        self.__dict__["_derived"] = {}

        # the union's vertices are the meshes' vertices, none dropped: kept_vertices is the identity
        buffers = {"kept_vertices": torch.arange(sum(counts["vertex"]), dtype=torch.long, device=first.device)}
        for name in self._INT_BUFFERS:
            if name == "kept_vertices":
                continue
            parts = [getattr(m, name) for m in meshes]
            kind = _INDEX_OF.get(name)
            if kind is not None:
                off = self._offsets[kind]
                if name == "face_tets":  # -1 marks a boundary face's missing tet: kept
                    parts = [torch.where(p >= 0, p + off[k], p) for k, p in enumerate(parts)]
                else:
                    parts = [p + off[k] for k, p in enumerate(parts)]
            elif name not in _SIGNS:
                raise AssertionError(f"TetMeshBatch does not know how to join the buffer {name!r}")
            buffers[name] = torch.cat(parts, dim=0)
        for name in self._FLOAT_BUFFERS:
            buffers[name] = torch.cat([getattr(m, name) for m in meshes], dim=0)
        self._set_buffers(buffers)
        self.cad = self._join_cad(meshes)

    def _join_cad(self, meshes: list[TetMesh]) -> CadTags | None:
        tags = [m.cad for m in meshes]
        has = [t is not None for t in tags]
        if not any(has):
            return None
        if not all(has):
            with_tags = [k for k, h in enumerate(has) if h]
            without = [k for k, h in enumerate(has) if not h]
            raise MeshError(f"join_meshes: meshes {with_tags} have CAD tags (mesh.cad) and meshes {without} do not; "
                            f"a tagged mesh takes its features from the tags, an untagged one from dihedral angles, "
                            f"and one union cannot do both: join only tagged or only untagged meshes, or drop the "
                            f"tags of a copy (m = mesh.to(); m.cad = None)")
        off = self._offsets
        dev = self.device

        def cat(name, kind=None):
            parts = [getattr(t, name).to(dev) for t in tags]
            if kind is not None:
                parts = [p + off[kind][k] for k, p in enumerate(parts)]
            return torch.cat(parts, dim=0)

        return CadTags(
            face_surface=cat("face_surface"),
            boundary_face_surface=cat("boundary_face_surface"),
            feature_edges=cat("feature_edges", "vertex"),
            feature_edge_index=cat("feature_edge_index", "edge"),
            feature_edge_curve=cat("feature_edge_curve"),
            corner_vertices=cat("corner_vertices", "vertex"),
            corner_point=cat("corner_point"),
        )

    # ------------------------------------------------------------------ offsets
    @property
    def n_meshes(self) -> int:
        """Number of meshes ``B`` in the union."""
        return len(self._counts["vertex"])

    def counts(self, kind: str) -> tuple[int, ...]:
        """Per-mesh counts ``(B,)`` of ``kind`` (:data:`ELEMENT_KINDS`: ``"vertex"``, ``"edge"``,
        ``"face"``, ``"tet"``, ``"boundary_face"``, ``"boundary_vertex"``), Python ints."""
        return self._counts[_kind(kind)]

    def offsets(self, kind: str) -> tuple[int, ...]:
        """Per-mesh offsets ``(B + 1,)`` of ``kind``: mesh ``k``'s elements are the union's
        ``offsets[k] : offsets[k + 1]``. Python ints."""
        return self._offsets[_kind(kind)]

    def mesh_index(self, kind: str) -> torch.Tensor:
        """``(N,)`` long: the mesh each element of ``kind`` belongs to (PyG's ``batch`` vector),
        on the mesh's device; e.g. per-mesh sums of a per-face value ``x (F,)`` are
        ``torch.zeros(B).index_add_(0, batch.mesh_index("face"), x)``."""
        c = torch.tensor(self.counts(kind), dtype=torch.long)
        return torch.repeat_interleave(torch.arange(self.n_meshes), c).to(self.device)

    def split(self, x: torch.Tensor, kind: str, dim: int | None = None) -> tuple[torch.Tensor, ...]:
        """Per-mesh pieces of a per-element tensor: ``x (..., N, ...) -> B`` views ``(..., N_k, ...)``.

        Args:
            x: a tensor with one dimension of size ``N`` = the union's number of ``kind``
                elements, in the union's order (e.g. ``(*batch, F, 3, 3)`` curvatures,
                ``(*batch, T, 3)`` covariant derivatives, ``(*batch, E, 3, 3)`` rotations).
            kind: ``"vertex"``, ``"edge"``, ``"face"``, ``"tet"``, ``"boundary_face"`` or
                ``"boundary_vertex"``.
            dim: the element dimension. ``None``: the one dimension of ``x`` of size ``N``
                (``ValueError`` when several have that size: pass ``dim``).

        Returns:
            a tuple of ``B`` views of ``x`` (``torch.split``: differentiable, no copy); piece
            ``k`` is what the same computation gives on mesh ``k`` alone. Index-valued tensors
            (vertex ids, ...) keep the union's numbering: subtract ``offsets(kind)[k]``.

        Raises:
            KeyError: an unknown ``kind``; ValueError: no dimension (or the given ``dim``) of size ``N``.
        """
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"TetMeshBatch.split: x must be a tensor, got {type(x).__name__}")
        N = self.offsets(kind)[-1]
        if dim is None:
            dims = [d for d in range(x.dim()) if x.shape[d] == N]
            if len(dims) != 1:
                why = "none has" if not dims else f"dims {dims} have"
                raise ValueError(f"TetMeshBatch.split: x has shape {tuple(x.shape)} and {why} the size {N} of the "
                                 f"union's {kind} count; pass dim= (the {kind} dimension)")
            dim = dims[0]
        elif not -x.dim() <= dim < x.dim() or x.shape[dim] != N:
            raise ValueError(f"TetMeshBatch.split: dim {dim} of x (shape {tuple(x.shape)}) is not of size {N}, the "
                             f"union's {kind} count")
        return torch.split(x, list(self.counts(kind)), dim=dim)

    def __repr__(self) -> str:
        return (f"TetMeshBatch(meshes={self.n_meshes}, V={self.n_vertices}, E={self.n_edges}, F={self.n_faces}, "
                f"T={self.n_tets}, dtype={self.dtype}, device={self.device})")


def join_meshes(meshes: Sequence[TetMesh]) -> TetMeshBatch:
    """The disjoint union of ``meshes`` as one :class:`TetMeshBatch` (pytorch3d's
    ``join_meshes_as_batch``, PyG's disjoint union): see :class:`TetMeshBatch` for the order,
    the offsets and :meth:`TetMeshBatch.split`."""
    return TetMeshBatch(meshes)


def _kind(kind: str) -> str:
    if kind not in ELEMENT_KINDS:
        raise KeyError(f"unknown element kind {kind!r}; known: {list(ELEMENT_KINDS)}")
    return kind


def _cumsum(counts: tuple[int, ...]) -> tuple[int, ...]:
    out = [0]
    for c in counts:
        out.append(out[-1] + c)
    return tuple(out)
