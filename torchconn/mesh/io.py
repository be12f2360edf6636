"""Mesh input: tet-mesh files and triangle/polygon surfaces.

- Tet meshes (:func:`load_tet_mesh`): ``.mesh`` (MEDIT), ``.msh`` (gmsh 2.2 ascii/binary and
  4.1), ``.vtk``, ``.vtu``, ``.node``/``.ele`` (tetgen). ASCII ``.mesh`` is parsed here at full
  float64 precision (:func:`_read_medit`); the others go through meshio, with libigl as a
  fallback for ``.msh``. A reader failure (meshio even calls ``sys.exit`` on some files) is a
  :class:`MeshError` naming the file and the format. Only the tetrahedra of a file are used: the
  boundary is always recomputed from the tets (some files, e.g. ``sphere_r0.17.mesh``, list
  boundary triangles twice). Coincident vertices are merged and unused ones dropped, each with
  a warning that says how many.
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

import contextlib
import io
import re
import sys
import warnings
from pathlib import Path

import numpy as np

from .builtin import ball, box, cylinder, tetrahedralize, torus
from . import cad as _cad
from .cad import CAD_SUFFIXES as _CAD_SUFFIXES
from .cells import CellComplex
from .errors import MeshError, _checked_path, _few
from .tet import TetMesh, merge_duplicate_vertices

__all__ = [
    "load_tet_mesh", "load_surface", "load_polygon_surface", "load_mesh", "tetrahedralize",
    "box", "ball", "cylinder", "torus", "TET_SUFFIXES", "SURFACE_SUFFIXES",
]

TET_SUFFIXES = (".mesh", ".msh", ".vtk", ".vtu", ".node", ".ele")
SURFACE_SUFFIXES = (".obj", ".ply", ".off", ".stl")


# ----------------------------------------------------------------------------- tet files
# MEDIT keywords whose sections this reader parses, with the numbers per entry after the count
# (Vertices: x y z ref; Triangles: a b c ref; Tetrahedra: a b c d ref). Every other section
# (Edges, Corners, Ridges, Normals, ...) is skipped: a section runs to the next keyword.
_MEDIT_WIDTH = {"vertices": 4, "triangles": 4, "tetrahedra": 5}
_MEDIT_KEYWORD = re.compile(r"^[ \t]*([A-Za-z][A-Za-z0-9_]*)", re.M)


def _read_medit(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(V (N,3) float64, T (M,4) int64)`` from an ASCII MEDIT ``.mesh`` file, at full float64
    precision whatever ``MeshVersionFormatted`` says (meshio reads version 1 as float32).

    Sections start at a keyword at the beginning of a line; ``Vertices`` and ``Tetrahedra`` are
    parsed in one vectorized ``np.fromstring`` each; ``#`` comments are removed first. Indices
    in the file are 1-based.

    Raises:
        MeshError: empty or binary file, ``Dimension`` other than 3, no ``Vertices`` section, a
            section whose count does not match its numbers (naming the section), non-integer
            or out-of-range tet indices are left to :class:`TetMesh`.
    """
    raw = path.read_bytes()
    if not raw.strip():
        raise MeshError(f"{path} is empty: a MEDIT .mesh file needs 'Vertices' and 'Tetrahedra' sections")
    if b"\0" in raw:
        raise MeshError(f"{path} is not an ASCII MEDIT .mesh file (it contains binary data); "
                        f"binary MEDIT files use the suffix .meshb: rename it or convert it to ASCII")
    text = raw.decode("utf-8", errors="replace")
    if "#" in text:
        text = re.sub(r"#[^\n]*", "", text)
    marks = [(m.group(1).lower(), m.start(1), m.end(1)) for m in _MEDIT_KEYWORD.finditer(text)]
    keys = [k for k, _, _ in marks]
    if "vertices" not in keys:
        raise MeshError(f"{path} is not a MEDIT .mesh file: no 'Vertices' section "
                        f"(keywords found: {sorted(set(keys))[:8]}); check the file's format and suffix")
    body = {}
    for n, (key, _, end) in enumerate(marks):
        stop = marks[n + 1][1] if n + 1 < len(marks) else len(text)
        if key == "dimension":
            dim = text[end:stop].split()
            if dim != ["3"]:
                raise MeshError(f"{path}: 'Dimension {' '.join(dim)}' is not a 3-D mesh; tet meshes need 'Dimension 3'")
        elif key in _MEDIT_WIDTH and key not in body:
            body[key] = text[end:stop]
    out = {}
    for key, sec in body.items():
        width = _MEDIT_WIDTH[key]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # a short parse is checked below
            nums = np.fromstring(sec, dtype=np.float64, sep=" ")
        count = int(nums[0]) if nums.size and np.isfinite(nums[0]) and nums[0] == int(nums[0]) and nums[0] >= 0 else -1
        if count < 0 or nums.size != 1 + count * width:
            got = "no count" if count < 0 else f"{nums.size - 1} numbers"
            raise MeshError(f"{path}: section '{key.capitalize()}' is malformed: expected a count N then N rows of "
                            f"{width} numbers, got {got} (count {count}); the section ends at the first token "
                            f"that is not a number: check that row of the file")
        out[key] = nums[1:].reshape(count, width)
    V = np.ascontiguousarray(out["vertices"][:, :3])
    cells = out.get("tetrahedra", np.zeros((0, 5)))[:, :4]
    if not np.array_equal(cells, np.round(cells)):
        bad = np.nonzero((cells != np.round(cells)).any(axis=1))[0]
        raise MeshError(f"{path}: 'Tetrahedra' rows with non-integer vertex indices: rows {_few(bad)}")
    return V, cells.astype(np.int64) - 1


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


def _guarded(reader, path: Path):
    """``(reader(path), None)``, or ``(None, "what the reader said")`` on any failure.

    meshio prints its reason and ends the interpreter with ``sys.exit(1)`` on some unreadable
    files, so ``SystemExit`` is caught too (``KeyboardInterrupt`` is not) and what the reader
    printed becomes part of the message; after a successful read it is passed on to stderr.
    """
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            res = reader(path)
    except (Exception, SystemExit) as err:  # noqa: BLE001 - every reader failure becomes a MeshError
        said = " ".join(buf.getvalue().split())
        msg = f"exit status {err.code}" if isinstance(err, SystemExit) else str(err) or "no message"
        return None, f"{type(err).__name__} ({msg})" + (f": {said}" if said else "")
    sys.stderr.write(buf.getvalue())
    return res, None




def _clean_vertices(V: np.ndarray, T: np.ndarray, path: Path, merge_duplicates: bool):
    """Merge coincident vertices (bitwise-equal coordinates) into their first copy
    (:func:`~torchconn.mesh.tet.merge_duplicate_vertices`), with a warning that says how many;
    ``(V, T)`` unchanged when there are none or ``merge_duplicates`` is False. Copies that no tet
    uses afterwards are dropped by :class:`TetMesh`.

    Returns:
        ``(T (M,4), merged (K,))``: re-indexed tets and the ids of the merged copies.
    """
    if not merge_duplicates:
        return T, np.zeros(0, np.int64)
    T, pairs = merge_duplicate_vertices(V, T)
    if pairs.shape[0]:
        warnings.warn(f"{path}: merged {pairs.shape[0]} duplicate vertices (same coordinates as an earlier vertex), "
                      f"e.g. vertex {int(pairs[0, 0])} into vertex {int(pairs[0, 1])}: indices {_few(pairs[:, 0])}; "
                      f"pass merge_duplicates=False to keep them", stacklevel=3)
    return T, pairs[:, 0]


def load_tet_mesh(path, *, merge_duplicates: bool = True, **kwargs) -> TetMesh:
    """Load a tetrahedral mesh file into a :class:`TetMesh`.

    Args:
        path: ``.mesh``, ``.msh`` (gmsh 2.2 ascii/binary, 4.1), ``.vtk``, ``.vtu``, ``.node`` or
            ``.ele`` (either file of a tetgen pair).
        merge_duplicates: merge vertices with identical coordinates (a duplicated vertex
            otherwise cuts the mesh along an internal boundary), warning with the count.
        **kwargs: passed to :class:`TetMesh` (``reorient``, ``unreferenced``, ``dtype``,
            ``device``). Coordinates are read as float64 when no ``dtype`` is given.

    ASCII ``.mesh`` (MEDIT) is read by :func:`_read_medit` at full float64 precision; the other
    formats by meshio, with libigl as a fallback for ``.msh``. Only the tetrahedra are used;
    file triangles are ignored (the boundary is computed from the tets). Vertices used by no
    tet (gmsh geometry points, merged duplicates) are dropped with a warning that says how many
    (``kept_vertices`` maps to the file's indices) unless ``unreferenced`` is passed.

    Raises:
        MeshError: unsupported suffix, unreadable file (naming the file, the format tried and
            the reader's message), or no tetrahedra; any validation error of :class:`TetMesh`.
    """
    path, suf = _checked_path(path, TET_SUFFIXES, "tet-mesh")
    if suf == ".mesh":
        V, T = _read_medit(path)
    else:
        fmt = {".msh": "gmsh", ".vtk": "VTK", ".vtu": "VTU", ".node": "tetgen", ".ele": "tetgen"}[suf]
        res, err_meshio = _guarded(_read_tets_meshio, path)
        if res is None and suf == ".msh":
            res, err_igl = _guarded(_read_tets_igl, path)
            err_meshio = f"meshio: {err_meshio}; libigl: {err_igl}"
        if res is None:
            empty = " (the file is empty)" if path.stat().st_size == 0 else ""
            raise MeshError(f"could not read {path} as a {fmt} {suf} file{empty}: {err_meshio}; "
                            f"check that the file is a valid {fmt} file and that its suffix matches its content")
        V, T = res
    if T.shape[0] == 0:
        raise MeshError(f"{path} contains no tetrahedra")
    T, merged = _clean_vertices(V, T, path, merge_duplicates)
    if "unreferenced" not in kwargs:
        used = np.zeros(V.shape[0], dtype=bool)
        used[T[(T >= 0) & (T < V.shape[0])]] = True
        used[merged] = True  # already reported as merged
        if not used.all():
            unused = np.nonzero(~used)[0]
            warnings.warn(f"{path}: dropped {unused.size} vertices used by no tet: indices {_few(unused)}; "
                          f"pass unreferenced='warn' to keep them", stacklevel=2)
        kwargs["unreferenced"] = "drop"
    return TetMesh(V, T, **kwargs)


# ----------------------------------------------------------------------------- surfaces
def load_surface(path) -> tuple[np.ndarray, np.ndarray]:
    """Load a triangle surface ``.obj/.ply/.off/.stl`` through pymeshlab.

    Returns:
        ``(V (N, 3) float64, F (M, 3) int64)`` numpy arrays, faces as stored in the file
        (polygons are triangulated by the reader).

    Raises:
        MeshError: unsupported suffix, empty file, unreadable file or a file without faces
            (each naming the file).
    """
    import pymeshlab

    path, suf = _checked_path(path, SURFACE_SUFFIXES, "surface")
    _check_not_empty(path)
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except Exception as err:  # noqa: BLE001 - pymeshlab raises its own exception types
        raise MeshError(f"could not read surface {path} as {suf}: {err}; check that the file is a valid "
                        f"{suf} file and that its suffix matches its content") from err
    m = ms.current_mesh()
    V = np.ascontiguousarray(m.vertex_matrix(), dtype=np.float64)
    F = np.ascontiguousarray(m.face_matrix(), dtype=np.int64)
    if F.shape[0] == 0:
        raise MeshError(f"empty surface: no faces in {path} ({V.shape[0]} vertices); a surface to "
                        f"tetrahedralize needs triangles or polygons ('f' lines in .obj)")
    return V, F


def _check_not_empty(path: Path) -> None:
    """MeshError for a surface file with nothing but whitespace (pymeshlab says only "Unable
    to open file")."""
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if not head.strip():
        raise MeshError(f"empty surface: no faces in {path} (the file is empty); "
                        f"export the surface again or pass the right file")


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

        _check_not_empty(path)
        m, err = _guarded(lambda p: meshio.read(str(p)), path)
        if m is None:
            raise MeshError(f"could not read surface {path} as {suf}: {err}; check that the file is a valid "
                            f"{suf} file and that its suffix matches its content")
        V = np.asarray(m.points, dtype=np.float64)
        faces = [list(r) for c in m.cells if c.dim == 2 for r in np.asarray(c.data).tolist()]
    if not faces:
        raise MeshError(f"surface {path} has no faces")
    return CellComplex(V, faces, **kwargs)


def load_mesh(path, edge_length: float | None = None, max_volume: float | None = None, **kwargs) -> TetMesh:
    """Load any supported file as a :class:`TetMesh`: tet formats directly (the size
    arguments are ignored), surface formats through :func:`tetrahedralize` (``kwargs`` such as
    ``max_tets`` go there; its errors are prefixed with the file name), CAD models
    (``.step .stp .brep .geo .iges .igs``, the ``cad`` extra) through
    :func:`torchconn.mesh.cad.load_cad` with ``size=edge_length`` (``mesh.cad`` holds the CAD
    surfaces, curves and corners), and a HexMe parameter file (``.yaml``) through
    :func:`torchconn.mesh.cad.load_hexme`."""
    suf = Path(path).suffix.lower()
    if suf in _CAD_SUFFIXES or suf in (".yaml", ".yml"):
        if max_volume is not None:
            raise MeshError(f"{path}: CAD models are meshed by gmsh with an edge length; pass edge_length, "
                            f"not max_volume")
        kwargs.pop("max_tets", None)
        load = _cad.load_hexme if suf in (".yaml", ".yml") else _cad.load_cad
        return load(path, edge_length, **kwargs)
    if suf in TET_SUFFIXES:
        kwargs.pop("max_tets", None)  # a size argument of tetrahedralize, ignored like edge_length
        return load_tet_mesh(path, **kwargs)
    if suf in SURFACE_SUFFIXES:
        V, F = load_surface(path)
        try:
            return tetrahedralize(V, F, max_volume=max_volume, edge_length=edge_length, **kwargs)
        except MeshError as err:
            raise MeshError(f"{path}: {err}") from err
    raise MeshError(f"unsupported mesh suffix {suf!r} of {path}; supported: "
                    f"{', '.join(TET_SUFFIXES + SURFACE_SUFFIXES + _CAD_SUFFIXES)}, .yaml (HexMe parameters)")
