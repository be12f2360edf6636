"""Cell complexes built once: :class:`TetMesh`, :class:`CellComplex`, their I/O and built-in meshes.

Topology (edges ``i<j``, faces, incidence with signs, boundary) is built once as integer
buffers when a mesh is constructed; operators read those buffers and never recompute or
differentiate through them. Shapes and orientations: ``docs/architecture.md``.
"""
from . import io
from .complex import CellComplex, FaceGroup, MeshError, TetMesh, tet_mesh_as_cell_complex
from .io import ball, box, cylinder, load_mesh, load_polygon_surface, load_surface, load_tet_mesh, tetrahedralize, torus

__all__ = [
    "io",
    "MeshError", "TetMesh", "CellComplex", "FaceGroup", "tet_mesh_as_cell_complex",
    "load_tet_mesh", "load_surface", "load_polygon_surface", "load_mesh", "tetrahedralize",
    "box", "ball", "cylinder", "torus",
]
