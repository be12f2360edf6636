"""Mesh input: tet-mesh files, triangle/polygon surfaces, tetrahedralization, built-in meshes.

- Tet meshes (:func:`load_tet_mesh`): ``.mesh`` (MEDIT), ``.msh`` (gmsh 2.2 ascii/binary and
  4.1), ``.vtk``, ``.vtu``, ``.node``/``.ele`` (tetgen) through meshio, with libigl as a fallback
  for ``.mesh``/``.msh``. Only the tetrahedra of a file are used: the boundary is always
  recomputed from the tets (some files, e.g. ``sphere_r0.17.mesh``, list boundary triangles
  twice).
- Surfaces (:func:`load_surface`): ``.obj/.ply/.off/.stl`` through pymeshlab (triangles);
  :func:`load_polygon_surface` keeps polygons as a :class:`~torchconn.mesh.CellComplex`.
- :func:`tetrahedralize` wraps ``igl.copyleft.tetgen.tetrahedralize`` after checking that the
  surface is closed, edge-manifold, consistently oriented and free of degenerate triangles.
- Built-ins without files: :func:`box` (Kuhn split of a cube grid), :func:`ball`,
  :func:`cylinder`, :func:`torus` (pymeshlab primitives + tetgen).

All loaders return positively oriented :class:`~torchconn.mesh.TetMesh` objects; coordinates
are read as float64 unless a ``dtype`` is passed through.
"""
from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import torch

from .complex import CellComplex, MeshError, TetMesh

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


# ----------------------------------------------------------------------------- tetgen
def _regular_tet_volume(edge_length: float) -> float:
    return edge_length**3 / (6.0 * math.sqrt(2.0))


def tetrahedralize(V, F, max_volume: float | None = None, edge_length: float | None = None,
                   quality: float = 1.414, keep_surface: bool = False, **kwargs) -> TetMesh:
    """Tetrahedralize the inside of a closed triangle surface with tetgen (libigl).

    Args:
        V: ``(N, 3)`` surface vertices; F: ``(M, 3)`` triangles.
        max_volume: tetgen volume bound ``a``.
        edge_length: target edge length, turned into the volume of the regular tet of that
            edge, ``L^3 / (6 sqrt 2)`` (the smaller bound wins when both are given).
        quality: radius–edge ratio bound ``q``.
        keep_surface: keep the input triangles unsplit (tetgen ``Y``); this tends to leave
            slivers near the surface.
        **kwargs: passed to :class:`TetMesh` (``dtype``, ``device``).

    The tetgen switches are ``pq{quality}[a{vol}][Y]Q``. The surface is checked first.

    Raises:
        MeshError: the surface is not closed / not edge-manifold / not consistently oriented
            (naming the edges as vertex pairs), has degenerate triangles (naming them), or
            tetgen fails or returns no tets.
    """
    import igl.copyleft.tetgen as tg

    V = np.ascontiguousarray(np.asarray(V, dtype=np.float64))
    F = np.ascontiguousarray(np.asarray(F)).astype(np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise MeshError(f"tetrahedralize needs V (N, 3) and F (M, 3), got {V.shape} and {F.shape}")
    surf = CellComplex(V, F, dtype=torch.float64)
    surf.check_closed_manifold()
    deg = surf.degenerate_faces().numpy()
    if deg.size:
        from .complex import _few

        raise MeshError(f"surface has degenerate (zero-area) triangles: face indices {_few(deg)}")
    flags = f"pq{quality:g}"
    vols = [v for v in (max_volume, None if edge_length is None else _regular_tet_volume(edge_length)) if v]
    if vols:
        flags += f"a{min(vols):.9g}"
    if keep_surface:
        flags += "Y"
    flags += "Q"
    try:
        out = tg.tetrahedralize(V, F, flags=flags)
    except Exception as err:  # noqa: BLE001 - tetgen errors come as RuntimeError or worse
        raise MeshError(f"tetgen failed with flags {flags!r}: {err}") from err
    TV, TT = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)
    if TT.ndim != 2 or TT.shape[0] == 0:
        raise MeshError(f"tetgen returned no tets (flags {flags!r})")
    # tetgen's orientation convention is opposite to ours; orient each tet explicitly
    p = TV[TT]
    vol6 = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    neg = vol6 < 0
    TT[neg] = TT[neg][:, [0, 1, 3, 2]]
    kwargs.setdefault("unreferenced", "drop")
    return TetMesh(TV, TT, **kwargs)


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


# ----------------------------------------------------------------------------- built-ins
def box(n=4, size=1.0, origin=(0.0, 0.0, 0.0), *, dtype: torch.dtype = torch.float64, device=None) -> TetMesh:
    """Structured grid of ``n^3`` cubes on ``[origin, origin + size]``, each split into 6 tets.

    Args:
        n: cubes per axis (int or 3 ints). size: box side (float or 3 floats).

    The split is Kuhn/Freudenthal: every cube is cut along its diagonal from its lowest to its
    highest corner into the tets ``[c, c+e_p, c+e_p+e_q, c+1]`` for the 6 axis orders
    ``(p, q, r)``, so neighbouring cubes match and the mesh is conforming. Tets of odd axis
    orders are flipped to positive orientation. ``V = prod(n+1)``, ``T = 6 prod(n)``,
    boundary faces ``4 (n_x n_y + n_y n_z + n_z n_x)``.
    """
    nx, ny, nz = (n, n, n) if np.isscalar(n) else tuple(int(k) for k in n)
    if min(nx, ny, nz) < 1:
        raise MeshError(f"box needs at least one cube per axis, got n={n}")
    sx, sy, sz = (size, size, size) if np.isscalar(size) else tuple(float(s) for s in size)
    gx, gy, gz = (np.linspace(0, s, k + 1) + o for s, k, o in zip((sx, sy, sz), (nx, ny, nz), origin))
    X, Y, Z = np.meshgrid(gx, gy, gz, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def vid(i, j, k):
        """Grid vertex id of lattice point ``(i, j, k)`` (arrays)."""
        return (i * (ny + 1) + j) * (nz + 1) + k

    I, J, K = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    I, J, K = I.ravel(), J.ravel(), K.ravel()
    tets = []
    for perm in itertools.permutations(range(3)):  # the 6 tets of the cube template
        off = np.zeros(3, np.int64)
        corners = [vid(I, J, K)]
        for axis in perm:
            off[axis] += 1
            corners.append(vid(I + off[0], J + off[1], K + off[2]))
        t = np.stack(corners, axis=1)
        inversions = sum(perm[a] > perm[b] for a in range(3) for b in range(a + 1, 3))
        if inversions % 2:  # odd axis order: negatively oriented, swap the last two
            t = t[:, [0, 1, 3, 2]]
        tets.append(t)
    T = np.stack(tets, axis=1).reshape(-1, 4)
    return TetMesh(V, T, dtype=dtype, device=device)


def _primitive(name: str, **params):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    getattr(ms, name)(**params)
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), dtype=np.float64), np.asarray(m.face_matrix(), dtype=np.int64)


def _orient_outward(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Flip all triangles when the enclosed volume is negative (after the closedness check)."""
    surf = CellComplex(V, F, dtype=torch.float64)
    if float(surf.enclosed_volume()) < 0:
        F = F[:, [0, 2, 1]]
    return F


def ball(radius: float = 1.0, edge_length: float = 0.25, center=(0.0, 0.0, 0.0), **kwargs) -> TetMesh:
    """Tet mesh of a ball: pymeshlab icosphere (subdivision level chosen so its edges are
    about ``edge_length``) tetrahedralized with the same target edge length. Boundary vertices
    of the icosphere lie on the sphere; extra tetgen surface points lie on its flat facets.
    ``kwargs`` go to :func:`tetrahedralize`."""
    # icosahedron edge is 1.051 r; each subdivision halves it
    level = int(np.clip(round(math.log2(1.051 * radius / edge_length)), 0, 6))
    V, F = _primitive("create_sphere", radius=float(radius), subdiv=level)
    V = V + np.asarray(center, dtype=np.float64)
    return tetrahedralize(V, _orient_outward(V, F), edge_length=edge_length, **kwargs)


def cylinder(radius: float = 1.0, height: float = 2.0, edge_length: float = 0.3, **kwargs) -> TetMesh:
    """Tet mesh of a solid cylinder with axis ``z``, centered at the origin
    (``|z| <= height/2``): pymeshlab ``create_cone`` with equal radii (rotated from its ``y``
    axis) tetrahedralized with target ``edge_length``. ``kwargs`` go to :func:`tetrahedralize`."""
    sides = max(6, math.ceil(2 * math.pi * radius / edge_length))
    V, F = _primitive("create_cone", r0=float(radius), r1=float(radius), h=float(height), subdiv=sides)
    V = np.stack([V[:, 0], -V[:, 2], V[:, 1]], axis=1)  # proper rotation taking y to z
    return tetrahedralize(V, _orient_outward(V, F), edge_length=edge_length, **kwargs)


def torus(major_radius: float = 1.0, minor_radius: float = 0.4, edge_length: float = 0.25, **kwargs) -> TetMesh:
    """Tet mesh of a solid torus around the ``z`` axis (centre circle of radius
    ``major_radius`` in the ``xy`` plane, tube radius ``minor_radius``): pymeshlab
    ``create_torus`` tetrahedralized with target ``edge_length``. Boundary χ = 0, mesh
    ``V - E + F - T = 0``. ``kwargs`` go to :func:`tetrahedralize`."""
    if not 0 < minor_radius < major_radius:
        raise MeshError(f"torus needs 0 < minor_radius < major_radius, got {minor_radius}, {major_radius}")
    hs = max(8, math.ceil(2 * math.pi * major_radius / edge_length))
    vs = max(6, math.ceil(2 * math.pi * minor_radius / edge_length))
    V, F = _primitive("create_torus", hradius=float(major_radius), vradius=float(minor_radius), hsubdiv=hs, vsubdiv=vs)
    return tetrahedralize(V, _orient_outward(V, F), edge_length=edge_length, **kwargs)
