"""What every complex shares: vertices, canonical edges, one edge lookup, face loops, buffers,
device moves and the ``require(name, builder)`` cache of derived data.

Conventions (docs/architecture.md, docs/conventions.md §1):

- Edges are stored canonically ``(i, j)`` with ``i < j``, rows sorted lexicographically, so the
  keys ``i * V + j`` are sorted and a vertex pair is found by ``searchsorted``. A cell refers
  to an edge by index and sign: ``+1`` when the cell traverses it as stored.
- Topology lives in integer (``torch.long``) buffers, geometry in float buffers that follow the
  dtype and device of ``vertices``. Nothing is meant to be differentiated through topology.
- ``kind`` (``"tet"`` or ``"cells"``) tells the complexes apart for code that must not import
  this package (``torchconn.ops``); code above the mesh layer uses ``isinstance``.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from .errors import MeshError, _few

__all__ = ["MeshBase", "FaceGroup", "lookup_edges"]

# Multiplier of get_eps("degenerate", dtype): a cell is degenerate when its measure is at most
# DEGENERATE_FACTOR * eps * (longest edge)^dim. The factor leaves room for the rounding error
# of a 3x3 determinant (a few ulps of L^3) in float32.
DEGENERATE_FACTOR = 10.0

_MAX_LISTED = 10


def lookup_edges(sorted_keys: torch.Tensor, n_vertices: int, i, j, *, perm: torch.Tensor | None = None,
                 owner: str = "mesh") -> tuple[torch.Tensor, torch.Tensor]:
    """Edge ids and signs of vertex pairs, by ``searchsorted`` on keys ``min * V + max``.

    Args:
        sorted_keys: ``(E,)`` ascending keys ``i * V + j`` of the canonical edges (``i < j``).
        n_vertices: ``V``.
        i, j: integer tensors or arrays, broadcastable to a common shape ``S``.
        perm: ``(E,)`` edge id of each sorted key (``None``: the keys are in edge order).
        owner: what the edges belong to, for the error message.

    Returns:
        ``(edge_id S, sign S)``: ``edges[edge_id] == (min(i,j), max(i,j))``, sign ``+1`` where
        ``i < j`` (the pair runs as stored), ``-1`` otherwise.

    Raises:
        TypeError: non-integer indices.
        MeshError: naming the pairs that are not edges (``i == j``, out of range or absent).

    Checks every pair, so it synchronizes with the device; operators read precomputed
    ``(edge_idx, edge_sign)`` buffers instead.
    """
    dev = sorted_keys.device
    i, j = torch.as_tensor(i, device=dev), torch.as_tensor(j, device=dev)
    if not (_is_integer(i) and _is_integer(j)):
        raise TypeError(f"vertex indices must be integer tensors, got {i.dtype} and {j.dtype}")
    i, j = torch.broadcast_tensors(i.long(), j.long())
    V, E = int(n_vertices), sorted_keys.numel()
    lo, hi = torch.minimum(i, j), torch.maximum(i, j)
    key = lo * V + hi
    found = (lo >= 0) & (hi < V) & (lo != hi)
    if E == 0:
        pos = torch.zeros_like(key)
        found = torch.zeros_like(found)
    else:
        pos = torch.searchsorted(sorted_keys, key.reshape(-1)).reshape(key.shape).clamp(max=E - 1)
        found = found & (sorted_keys[pos] == key)
    if not bool(found.all()):
        bad = torch.nonzero(~found.reshape(-1)).flatten()
        pairs = torch.stack((i.reshape(-1)[bad], j.reshape(-1)[bad]), 1)[:_MAX_LISTED].tolist()
        more = f" (and {bad.numel() - _MAX_LISTED} more)" if bad.numel() > _MAX_LISTED else ""
        raise MeshError(f"{bad.numel()} vertex pairs are not edges of the {owner}: {pairs}{more}")
    idx = pos if perm is None or E == 0 else perm[pos]
    return idx, torch.where(i < j, 1, -1).to(torch.long)


def _is_integer(x: torch.Tensor) -> bool:
    return not (x.is_floating_point() or x.is_complex() or x.dtype == torch.bool)


# ----------------------------------------------------------------------------- input checks
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
        if not _is_integer(idx):
            raise TypeError(f"{what} must have an integer dtype, got {idx.dtype}")
        return idx.detach().cpu().numpy().astype(np.int64)
    a = np.asarray(idx)
    if a.size == 0 and a.dtype.kind == "f":
        a = a.astype(np.int64)
    if a.dtype.kind not in "iu":
        raise TypeError(f"{what} must have an integer dtype, got {a.dtype}")
    return a.astype(np.int64)


def _meta_build(vertices, device) -> bool:
    """Whether a mesh is asked for on the ``meta`` device: then the constructor builds and
    validates it on CPU (topology and checks need values) and moves the result with
    ``.to("meta")``. Vertices that are meta tensors themselves carry no values: ``MeshError``."""
    if isinstance(vertices, torch.Tensor) and vertices.device.type == "meta":
        raise MeshError("vertices on the meta device carry no values, and building a mesh needs them "
                        "(topology, validation); build it on CPU and move it with mesh.to('meta'), or pass "
                        "CPU vertices with device='meta'")
    return device is not None and torch.device(device).type == "meta"


def _check_finite(v: torch.Tensor, what: str = "vertices") -> None:
    bad = ~torch.isfinite(v).all(dim=1)
    if bool(bad.any()):
        raise MeshError(f"{what} have NaN/inf coordinates at vertex indices {_few(bad.nonzero().flatten().cpu().numpy())}")


def _long(a, device) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.long, device=device)


# ----------------------------------------------------------------------------- face loops
@dataclass(frozen=True)
class FaceGroup:
    """All faces of one size ``m`` of a complex, as vertex loops.

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

    FIELDS = ("loops", "loop_edges", "loop_signs", "face_ids")

    def to(self, device=None) -> "FaceGroup":
        """Copy with all index tensors on ``device``."""
        return FaceGroup(*(getattr(self, f).to(device=device) for f in self.FIELDS))


# ----------------------------------------------------------------------------- base class
class _Derived:
    """Derived data cached by the mesh itself (geometry-central's ``requireX()``).

    ``mesh.require(name, builder)`` returns ``builder(mesh)`` built once per mesh and cached
    under ``name`` (tables of gather indices, kernel layouts, ...). ``to()`` gives the copy an
    empty cache, so derived data always lives on the copy's device. Builders must depend only
    on the mesh (topology and geometry), never on values passed to an operator.
    """

    def require(self, name: str, builder: Callable):
        cache = self.__dict__.get("_derived")
        if cache is None:  # plain get/assign: torch.compile (2.11) cannot trace dict.setdefault here
            cache = self.__dict__["_derived"] = {}
        if name not in cache:
            cache[name] = builder(self)
        return cache[name]

    def _fresh_copy(self):
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.__dict__["_derived"] = {}
        return new


class MeshBase(_Derived, abc.ABC):
    """Shared base of :class:`~torchconn.mesh.TetMesh` and :class:`~torchconn.mesh.CellComplex`.

    A subclass stores ``vertices (V,3)`` float and ``edges (E,2)`` long (canonical, sorted) and
    declares the attribute names of its tensors in ``_INT_BUFFERS`` (moved by :meth:`to`,
    dtype kept) and ``_FLOAT_BUFFERS`` (moved and cast). :meth:`buffers` is the mapping of all
    tensors the mesh owns; :meth:`_set_buffers` is its inverse, used by :meth:`to`.
    """

    kind: str = ""
    _INT_BUFFERS: tuple[str, ...] = ()
    _FLOAT_BUFFERS: tuple[str, ...] = ()

    vertices: torch.Tensor
    edges: torch.Tensor

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
    def dtype(self) -> torch.dtype:
        """Float dtype of the geometry (``vertices.dtype``)."""
        return self.vertices.dtype

    @property
    def device(self) -> torch.device:
        """Device of all buffers."""
        return self.vertices.device

    # ------------------------------------------------------------------ buffers and moves
    def buffers(self) -> dict[str, torch.Tensor]:
        """All tensors the mesh owns, by name (integer topology first, then float geometry)."""
        return {name: getattr(self, name) for name in self._INT_BUFFERS + self._FLOAT_BUFFERS}

    def _set_buffers(self, buffers: dict[str, torch.Tensor]) -> None:
        for name, t in buffers.items():
            setattr(self, name, t)

    def to(self, device=None, dtype: torch.dtype | None = None):
        """Copy on ``device`` with the float buffers in ``dtype``; topology is not rebuilt and
        the copy's :meth:`require` cache starts empty."""
        if dtype is not None and not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise TypeError(f"dtype must be a floating torch dtype, got {dtype}")
        new = self._fresh_copy()
        new._set_buffers({
            name: t.to(device=device, dtype=dtype) if t.is_floating_point() else t.to(device=device)
            for name, t in self.buffers().items()
        })
        return new

    # ------------------------------------------------------------------ topology
    def edge_index(self, i, j) -> tuple[torch.Tensor, torch.Tensor]:
        """Canonical edge ids and signs of vertex pairs (:func:`lookup_edges`).

        Args:
            i, j: integer tensors or arrays, broadcastable to a common shape ``(...)``.

        Returns:
            ``(edge_id (...), sign (...))``: ``edges[edge_id] == (min(i,j), max(i,j))`` and
            sign ``+1`` where ``i < j`` (the pair runs as stored), ``-1`` otherwise.

        Raises:
            MeshError: naming the pairs that are not edges.
        """
        return lookup_edges(self.edge_keys(), self.n_vertices, i, j, owner=type(self).__name__)

    def edge_keys(self) -> torch.Tensor:
        """``(E,)`` ascending keys ``edges[:,0] * V + edges[:,1]`` (cached by :meth:`require`)."""
        return self.require("edge_keys", lambda m: m.edges[:, 0] * m.n_vertices + m.edges[:, 1])

    @abc.abstractmethod
    def face_loops(self) -> dict[int, FaceGroup]:
        """Faces as oriented vertex loops grouped by size ``m`` (:class:`FaceGroup`); each
        complex defines its own (sorted triangles of a tet mesh, polygons of a cell complex)."""
