"""Conversions of a :class:`TetMesh` to and from meshio's meshes.

- :func:`to_meshio` / :func:`from_meshio`: a ``meshio.Mesh`` with a ``tetra`` block (and, for a
  mesh with CAD tags, ``triangle``/``line``/``vertex`` blocks carrying them as gmsh physical
  tags, so ``to_meshio(mesh).write("x.msh", file_format="gmsh22")`` is read back by
  :func:`~torchconn.mesh.cad.load_tagged_msh`).

Layering inside :mod:`torchconn.mesh`: this module sits above :mod:`torchconn.mesh.tet` and
:mod:`torchconn.mesh.cad` (it imports both, neither imports it), so the conversions are functions here, not ``TetMesh``
methods; the boundary surface, which needs no other library, is the method
:meth:`TetMesh.boundary_surface`. meshio is imported inside the functions that use it.
"""
from __future__ import annotations

import numpy as np
import torch

from .cad import _mesh_from_meshio
from .tet import TetMesh

__all__ = ["to_meshio", "from_meshio"]


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)


def to_meshio(mesh: TetMesh, *, point_data: dict | None = None, cell_data: dict | None = None,
              cad: bool = True):
    """The mesh as a ``meshio.Mesh``.

    Args:
        mesh: the :class:`TetMesh`.
        point_data: ``{name: (V, ...) array or tensor}`` per vertex.
        cell_data: ``{name: (T, ...) array or tensor}`` per tet.
        cad: when ``mesh.cad`` is set, add its tagged faces (``triangle``), feature edges
            (``line``) and corners (``vertex``) as cell blocks after the tets, with
            ``gmsh:physical`` and ``gmsh:geometrical`` cell data (the tets get tag 1); the
            user ``cell_data`` is padded with NaN (float) or -1 (integer) on those blocks.

    Returns:
        ``meshio.Mesh`` with float64 points (the mesh's vertices) and int64 cells.
    """
    import meshio

    T = mesh.n_tets
    cells = [("tetra", _np(mesh.tets).astype(np.int64))]
    data: dict[str, list] = {}
    for name, a in (cell_data or {}).items():
        a = _np(a)
        if a.shape[0] != T:
            raise ValueError(f"cell_data[{name!r}] has {a.shape[0]} rows, expected one per tet (T = {T})")
        data[name] = [a]
    tags = mesh.cad if cad else None
    if tags is not None:
        fs = _np(tags.face_surface)
        on = fs >= 0
        blocks = [("triangle", _np(mesh.faces)[on], fs[on]),
                  ("line", _np(tags.feature_edges), _np(tags.feature_edge_curve)),
                  ("vertex", _np(tags.corner_vertices)[:, None], _np(tags.corner_point))]
        blocks = [b for b in blocks if b[1].shape[0]]
        for kind, conn, _ in blocks:
            cells.append((kind, conn.astype(np.int64)))
        for name, lst in data.items():
            a = lst[0]
            fill = np.nan if a.dtype.kind == "f" else -1
            lst.extend(np.full((b[1].shape[0],) + a.shape[1:], fill, dtype=a.dtype) for b in blocks)
        tag_lists = [np.ones(T, np.int64)] + [b[2].astype(np.int64) for b in blocks]
        data["gmsh:physical"] = tag_lists
        data["gmsh:geometrical"] = [t.copy() for t in tag_lists]
    pdata = {}
    for name, a in (point_data or {}).items():
        a = _np(a)
        if a.shape[0] != mesh.n_vertices:
            raise ValueError(f"point_data[{name!r}] has {a.shape[0]} rows, expected one per vertex "
                             f"(V = {mesh.n_vertices})")
        pdata[name] = a
    return meshio.Mesh(_np(mesh.vertices).astype(np.float64), cells, point_data=pdata, cell_data=data)


def from_meshio(m, *, tags: str | None = "auto", **kwargs) -> TetMesh:
    """A :class:`TetMesh` from the ``tetra`` blocks of a ``meshio.Mesh``.

    Args:
        m: ``meshio.Mesh``.
        tags: ``"auto"`` (default): when the mesh has ``gmsh:physical`` (else
            ``gmsh:geometrical``) cell data, its tagged triangles, lines and vertices become
            ``mesh.cad`` (:class:`~torchconn.mesh.cad.CadTags`); ``"physical"`` /
            ``"geometrical"`` require that data; ``None`` ignores tags.
        **kwargs: passed to :class:`TetMesh` (``dtype``, ``device``, ``reorient``,
            ``unreferenced``); tags follow the vertices when unreferenced ones are dropped.

    Raises:
        MeshError: no tetrahedra; see :func:`~torchconn.mesh.cad.cad_tags_from_elements`.
    """
    return _mesh_from_meshio(m, tags, "meshio.Mesh", **kwargs)
