"""Mesh input: tet-mesh files and triangle/polygon surfaces.

- Tet meshes (:func:`load_tet_mesh`): ``.mesh`` (MEDIT), ``.msh`` (gmsh 2.2 ascii/binary and
  4.1), ``.vtk``, ``.vtu``, ``.node``/``.ele`` (tetgen) through meshio, with libigl as a fallback
  for ``.mesh``/``.msh``. Only the tetrahedra of a file are used: the boundary is always
  recomputed from the tets (some files, e.g. ``sphere_r0.17.mesh``, list boundary triangles
  twice).
- Surfaces (:func:`load_surface`): ``.obj/.ply/.off/.stl`` through pymeshlab (triangles);
  :func:`load_polygon_surface` keeps polygons as a :class:`~torchconn.mesh.CellComplex`.
- :func:`load_mesh` takes either kind, tetrahedralizing surfaces with
  :func:`~torchconn.mesh.builtin.tetrahedralize`.
- The built-in meshes and :func:`tetrahedralize` live in :mod:`torchconn.mesh.builtin` and are
  re-exported here (``torchconn.io.box``, ...).

The mesh-file libraries (meshio, libigl, pymeshlab) are imported inside the functions that use
them, so ``import torchconn`` works without them.

All loaders return positively oriented :class:`~torchconn.mesh.TetMesh` objects; coordinates
are read as float64 unless a ``dtype`` is passed through.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .builtin import ball, box, cylinder, tetrahedralize, torus
from .cells import CellComplex
from .errors import MeshError
from .tet import TetMesh

__all__ = [
    "load_tet_mesh", "load_surface", "load_polygon_surface", "load_mesh", "tetrahedralize",
    "box", "ball", "cylinder", "torus", "TET_SUFFIXES", "SURFACE_SUFFIXES",
]

TET_SUFFIXES = (".mesh", ".msh", ".vtk", ".vtu", ".node", ".ele")
SURFACE_SUFFIXES = (".obj", ".ply", ".off", ".stl")


# ----------------------------------------------------------------------------- tet files
def _read_tets_meshio(path: Path):
    import meshio

    m = meshio.read(str(path))
    blocks = [c.data for c in m.cells if c.type == "tetra"]
    tets = np.concatenate(blocks).astype(np.int64) if blocks else np.zeros((0, 4), np.int64)
    return np.asarray(m.points, dtype=np.float64), tets


def _read_tets_igl(path: Path):
    import igl

    if path.suffix.lower() == ".mesh":
        out = igl.readMESH(str(path))
    else:
        out = igl.readMSH(str(path))
    V, T = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)
    if T.ndim != 2 or T.shape[1] != 4:  # readMSH returns tets among its outputs; find them
        cands = [np.asarray(o) for o in out[1:] if isinstance(o, np.ndarray) and o.ndim == 2 and o.shape[1] == 4
                 and o.dtype.kind in "iu"]
        T = cands[0].astype(np.int64) if cands else np.zeros((0, 4), np.int64)
    return V, T


def _checked_path(path, suffixes, kind: str) -> tuple[Path, str]:
    """``(Path, lower-case suffix)``; MeshError for an unsupported suffix, FileNotFoundError if absent."""
    path = Path(path)
    suf = path.suffix.lower()
    if suf not in suffixes:
        raise MeshError(f"unsupported {kind} suffix {suf!r} of {path}; supported: {', '.join(suffixes)}")
    if not path.exists():
        raise FileNotFoundError(f"no such {kind} file: {path}")
    return path, suf


def load_tet_mesh(path, **kwargs) -> TetMesh:
    """Load a tetrahedral mesh file into a :class:`TetMesh`.

    Args:
        path: ``.mesh``, ``.msh`` (gmsh 2.2 ascii/binary, 4.1), ``.vtk``, ``.vtu``, ``.node`` or
            ``.ele`` (either file of a tetgen pair).
        **kwargs: passed to :class:`TetMesh` (``reorient``, ``unreferenced``, ``dtype``,
            ``device``). Coordinates are read as float64 when no ``dtype`` is given.

    Only the ``tetra`` cells are used; file triangles are ignored (the boundary is computed
    from the tets). Points used by no tet (e.g. gmsh geometry points) follow ``unreferenced``.

    Raises:
        MeshError: unsupported suffix, unreadable file, or no tetrahedra (the message names the
            file); any validation error of :class:`TetMesh`.
    """
    path, suf = _checked_path(path, TET_SUFFIXES, "tet-mesh")
    try:
        V, T = _read_tets_meshio(path)
    except Exception as err_meshio:  # noqa: BLE001 - any reader failure goes to the fallback
        if suf not in (".mesh", ".msh"):
            raise MeshError(f"could not read {path} with meshio: {err_meshio}") from err_meshio
        try:
            V, T = _read_tets_igl(path)
        except Exception as err_igl:  # noqa: BLE001
            raise MeshError(f"could not read {path}: meshio: {err_meshio}; libigl: {err_igl}") from err_igl
    if T.shape[0] == 0:
        raise MeshError(f"{path} contains no tetrahedra")
    return TetMesh(V, T, **kwargs)


# ----------------------------------------------------------------------------- surfaces
def load_surface(path) -> tuple[np.ndarray, np.ndarray]:
    """Load a triangle surface ``.obj/.ply/.off/.stl`` through pymeshlab.

    Returns:
        ``(V (N, 3) float64, F (M, 3) int64)`` numpy arrays, faces as stored in the file
        (polygons are triangulated by the reader).

    Raises:
        MeshError: unsupported suffix, unreadable file or a file without faces.
    """
    import pymeshlab

    path, suf = _checked_path(path, SURFACE_SUFFIXES, "surface")
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except Exception as err:  # noqa: BLE001 - pymeshlab raises its own exception types
        raise MeshError(f"could not read surface {path}: {err}") from err
    m = ms.current_mesh()
    V = np.ascontiguousarray(m.vertex_matrix(), dtype=np.float64)
    F = np.ascontiguousarray(m.face_matrix(), dtype=np.int64)
    if F.shape[0] == 0:
        raise MeshError(f"surface {path} has no faces")
    return V, F


def _parse_obj_polygons(path: Path):
    verts, faces = [], []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for line in fh:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                loop = []
                for tok in parts[1:]:
                    k = int(tok.split("/")[0])
                    loop.append(k - 1 if k > 0 else len(verts) + k)  # OBJ: 1-based, negative = relative
                faces.append(loop)
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), faces


def load_polygon_surface(path, **kwargs) -> CellComplex:
    """Load a polygon surface (triangles, quads, general polygons) as a :class:`CellComplex`.

    ``.obj`` is parsed directly (``v``/``f`` lines, ``f i/t/n`` and negative indices
    accepted, face order and loop order kept); other suffixes go through meshio, with faces
    in the order of meshio's cell blocks. ``kwargs`` go to :class:`CellComplex`
    (``dtype``, ``device``).
    """
    path, suf = _checked_path(path, SURFACE_SUFFIXES, "surface")
    if suf == ".obj":
        V, faces = _parse_obj_polygons(path)
    else:
        import meshio

        m = meshio.read(str(path))
        V = np.asarray(m.points, dtype=np.float64)
        faces = [list(r) for c in m.cells if c.dim == 2 for r in np.asarray(c.data).tolist()]
    if not faces:
        raise MeshError(f"surface {path} has no faces")
    return CellComplex(V, faces, **kwargs)


def load_mesh(path, edge_length: float | None = None, max_volume: float | None = None, **kwargs) -> TetMesh:
    """Load any supported file as a :class:`TetMesh`: tet formats directly (the size
    arguments are ignored), surface formats through :func:`tetrahedralize`."""
    suf = Path(path).suffix.lower()
    if suf in TET_SUFFIXES:
        return load_tet_mesh(path, **kwargs)
    if suf in SURFACE_SUFFIXES:
        V, F = load_surface(path)
        return tetrahedralize(V, F, max_volume=max_volume, edge_length=edge_length, **kwargs)
    raise MeshError(f"unsupported mesh suffix {suf!r} of {path}; supported: {', '.join(TET_SUFFIXES + SURFACE_SUFFIXES)}")
