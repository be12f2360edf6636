"""Cell complexes built once: :class:`TetMesh`, :class:`CellComplex`, their I/O and built-in meshes.

Topology (edges ``i<j``, faces, incidence with signs, boundary) is built once as integer
buffers when a mesh is constructed; operators read those buffers and never recompute or
differentiate through them. Shapes and orientations: ``docs/architecture.md``.

Modules: :mod:`.base` (:class:`MeshBase`, what both complexes share: edge lookup, face loops,
buffers, device moves, the ``require`` cache), :mod:`.tet`, :mod:`.cells`, :mod:`.simplex`
(local simplex templates), :mod:`.errors`, :mod:`.io` (files), :mod:`.builtin` (meshes
without files), :mod:`.cad` (CAD models through gmsh, tagged ``.msh``; the ``cad`` extra),
:mod:`.convert` (meshio conversion), :mod:`.batch` (several meshes as one disjoint union,
:func:`join_meshes`).

Inside the package each module imports only modules to its left in ``errors, base, simplex,
cells, tet, cad, batch, convert, builtin, io`` (function-level imports included; no cycle,
``tests/test_layering.py``).
"""
from . import batch, builtin, cad, convert, io, simplex
from .base import FaceGroup, MeshBase
from .batch import TetMeshBatch, join_meshes
from .builtin import ball, box, cylinder, tetrahedralize, torus
from .cad import CadTags, load_cad, load_hexme, load_tagged_msh
from .cells import CellComplex, tet_mesh_as_cell_complex
from .convert import from_meshio, to_meshio
from .errors import MeshError
from .io import load_mesh, load_polygon_surface, load_surface, load_tet_mesh
from .tet import TetMesh, merge_duplicate_vertices

__all__ = [
    "io", "builtin", "simplex", "cad", "convert", "batch",
    "MeshError", "MeshBase", "TetMesh", "TetMeshBatch", "join_meshes", "CellComplex", "FaceGroup", "tet_mesh_as_cell_complex",
    "merge_duplicate_vertices",
    "load_tet_mesh", "load_surface", "load_polygon_surface", "load_mesh", "tetrahedralize",
    "box", "ball", "cylinder", "torus",
    "CadTags", "load_cad", "load_tagged_msh", "load_hexme", "to_meshio", "from_meshio",
]
