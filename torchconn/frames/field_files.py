"""Files of a frame field: VTK for viewing, and the per-tet frame files that hex meshers read.

VTK (written atomically; needs ``meshio``, imported on call): ``frames.vtu``, the tet mesh with
point data ``axis0, axis1, axis2 (V, 3)``, the columns ``frames[:, :, k]`` (axis ``k`` at each
vertex, world coordinates); ``singular_faces.vtu``, the singular faces ``(S, 3)`` as triangles on
the same vertices; ``singular_curves.vtu`` (or ``.vtk``), the curves of a
:class:`~torchconn.frames.singular.SingularGraph` as polylines (one ``line`` cell per segment,
:func:`write_singular_curves_vtk`; :func:`read_singular_curves_vtk` reads it back). Each file goes
to a temporary file in the target's directory first and is then moved over the target
(``os.replace``), so a crash leaves the old file or the new one.

Per-tet frame files:

- ``.fra`` (CubeCover, HexFrameFlow): :func:`write_fra` / :func:`read_fra`. Line 1 ``FRA 1``,
  line 2 ``<T> 3 4``, then for each tet three lines, one frame axis each, ``x y z``.
- ``.frame`` (mouette's ``FrameField3DCells.read_from_file`` / ``export_frames_to_file``):
  :func:`write_mouette_frame` / :func:`read_mouette_frame`. Line 1 ``FRAME``, line 2 ``<T>``,
  then one line per tet ``a_x a_y a_z b_x b_y b_z c_x c_y c_z`` (the three axes in turn), and a
  final ``END``.

Convention: ``frames (T, 3, 3)``, ``frames[t][:, k]`` is axis ``k`` of tet ``t`` in world
coordinates (the columns, as everywhere in :mod:`torchconn.frames`); both formats list the axes
in the order ``k = 0, 1, 2``, in the order of ``mesh.tets``. Numbers are written with
``repr``-exact 17 significant digits, so a float64 field reads back bit for bit.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

__all__ = ["write_frames_vtu", "read_frames_vtu", "FramesVTU", "write_singular_faces_vtu",
           "write_singular_curves_vtk", "read_singular_curves_vtk",
           "write_fra", "read_fra", "write_mouette_frame", "read_mouette_frame"]


class FramesVTU(NamedTuple):
    """A frame field read back from a ``frames.vtu`` file (:func:`read_frames_vtu`), as numpy arrays.

    A named tuple: ``vertices, tets, vertex_frames, tet_frames = read_frames_vtu(path)`` unpacks it
    in this order, and the fields read by name (``read_frames_vtu(path).vertex_frames``).
    """

    vertices: np.ndarray
    """``(V, 3)`` float64 vertex positions."""
    tets: np.ndarray
    """``(T, 4)`` int64 vertex indices of the tets."""
    vertex_frames: np.ndarray
    """``(V, 3, 3)`` float64 per-vertex frames, axes as columns (point data ``axis0..2``)."""
    tet_frames: np.ndarray | None
    """``(T, 3, 3)`` float64 per-tet frames, axes as columns (cell data ``tet_axis0..2``), or
    ``None`` when the file has none."""


def _write(path, mesh) -> None:
    import meshio

    path = Path(path)
    # meshio writes to a path and picks the format by suffix: keep the target's
    tmp = path.with_name(f".{path.name}.tmp{path.suffix or '.vtu'}")
    meshio.write(str(tmp), mesh)
    os.replace(tmp, path)


def write_frames_vtu(path, mesh, frames: torch.Tensor, tet_frames: torch.Tensor | None = None) -> None:
    """Write the tets of ``mesh`` with ``frames (V, 3, 3)`` as point data ``axis0..2`` (column
    ``k`` of each frame) to ``path``, and ``tet_frames (T, 3, 3)`` (e.g.
    :attr:`~torchconn.frames.design.FrameFieldResult.tet_frames`) as cell data ``tet_axis0..2``
    when given. ParaView: Glyph filter on ``axis0`` etc. :func:`read_frames_vtu` reads it back."""
    import meshio

    V = mesh.vertices.detach().cpu().double().numpy()
    T = mesh.tets.cpu().numpy().astype(np.int64)
    F = frames.detach().cpu().double().numpy()
    cell_data = {}
    if tet_frames is not None:
        if tuple(tet_frames.shape) != (T.shape[0], 3, 3):
            raise ValueError(f"tet_frames must have shape (T, 3, 3) = ({T.shape[0]}, 3, 3), got {tuple(tet_frames.shape)}")
        Ft = tet_frames.detach().cpu().double().numpy()
        cell_data = {f"tet_axis{k}": [Ft[:, :, k]] for k in range(3)}
    _write(path, meshio.Mesh(V, [("tetra", T)], point_data={f"axis{k}": F[:, :, k] for k in range(3)},
                             cell_data=cell_data))


def read_frames_vtu(path) -> FramesVTU:
    """Read a file of :func:`write_frames_vtu` as a :class:`FramesVTU` of numpy arrays:
    ``(vertices (V, 3), tets (T, 4), vertex_frames (V, 3, 3), tet_frames (T, 3, 3) or None)``,
    a named tuple that unpacks in that order."""
    import meshio

    m = meshio.read(path)
    T = np.concatenate([c.data for c in m.cells if c.type == "tetra"]).astype(np.int64)
    F = np.stack([np.asarray(m.point_data[f"axis{k}"], dtype=np.float64) for k in range(3)], axis=-1)
    Ft = None
    if "tet_axis0" in m.cell_data:
        Ft = np.stack([np.concatenate(m.cell_data[f"tet_axis{k}"]).astype(np.float64) for k in range(3)], axis=-1)
    return FramesVTU(np.asarray(m.points, dtype=np.float64), T, F, Ft)


def write_singular_faces_vtu(path, mesh, singular_faces: torch.Tensor) -> None:
    """Write the triangles ``singular_faces (S, 3)`` long (vertex indices of ``mesh``) to ``path``."""
    import meshio

    V = mesh.vertices.detach().cpu().double().numpy()
    S = singular_faces.cpu().numpy().astype(np.int64).reshape(-1, 3)
    _write(path, meshio.Mesh(V, [("triangle", S)]))


_EMPTY_VTU = """<?xml version="1.0"?>
<VTKFile type="UnstructuredGrid" version="0.1" byte_order="LittleEndian">
<UnstructuredGrid>
<Piece NumberOfPoints="0" NumberOfCells="0">
<Points><DataArray type="Float64" NumberOfComponents="3" format="ascii"></DataArray></Points>
<Cells>
<DataArray type="Int64" Name="connectivity" format="ascii"></DataArray>
<DataArray type="Int64" Name="offsets" format="ascii"></DataArray>
<DataArray type="UInt8" Name="types" format="ascii"></DataArray>
</Cells>
</Piece>
</UnstructuredGrid>
</VTKFile>
"""
_EMPTY_VTK = ("# vtk DataFile Version 5.1\nsingular curves (none)\nASCII\nDATASET UNSTRUCTURED_GRID\n"
              "POINTS 0 double\n\nCELLS 1 0\nOFFSETS vtktypeint64\n0\nCONNECTIVITY vtktypeint64\n\n"
              "CELL_TYPES 0\n\n")


def _write_empty(path) -> None:
    path = Path(path)
    if path.suffix not in (".vtu", ".vtk"):
        raise ValueError(f"{path}: singular curves are written as .vtu or .vtk, got suffix {path.suffix!r}")
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    tmp.write_text(_EMPTY_VTU if path.suffix == ".vtu" else _EMPTY_VTK)
    os.replace(tmp, path)


def write_singular_curves_vtk(path, graph) -> None:
    """Write the curves of ``graph`` (a :class:`~torchconn.frames.singular.SingularGraph`) to
    ``path`` (``.vtu`` or ``.vtk``) as polylines.

    Points: every curve's polyline points in order, curve after curve. Cells: one ``line``
    ``(p_k, p_k+1)`` per segment. Cell data (one value per segment, constant along a curve):
    ``curve`` (curve index), ``type`` (index into
    :data:`~torchconn.frames.singular.CURVE_TYPES`: valence3, valence5, half, complex, mixed),
    ``closed`` (0/1) and ``valid`` (the curve's valid quarter-turn faces over its quarter-turn
    faces, ``-1`` without any). A graph without curves writes a valid file with no points and
    no cells (which ParaView opens and :func:`read_singular_curves_vtk` reads as ``[]``).
    """
    import meshio

    from .singular import CURVE_TYPES

    if Path(path).suffix not in (".vtu", ".vtk"):
        raise ValueError(f"{path}: singular curves are written as .vtu or .vtk, got suffix {Path(path).suffix!r}")
    pts, segs, curve, typ, closed, valid = [], [], [], [], [], []
    start = 0
    for cid, c in enumerate(graph.curves):
        P = c.points.detach().cpu().double().numpy()
        n = P.shape[0] - 1
        pts.append(P)
        segs.append(start + np.stack([np.arange(n), np.arange(1, n + 1)], 1))
        curve.append(np.full(n, cid))
        typ.append(np.full(n, CURVE_TYPES.index(c.label)))
        closed.append(np.full(n, int(c.closed)))
        valid.append(np.full(n, c.n_valid / c.n_quarter if c.n_quarter else -1.0))
        start += P.shape[0]
    if not graph.curves:  # meshio cannot write (or read) a grid without cells: write it directly
        _write_empty(path)
        return
    cat = lambda xs, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt)  # noqa: E731
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    L = np.concatenate(segs).astype(np.int64) if segs else np.zeros((0, 2), np.int64)
    data = {"curve": [cat(curve, np.int64)], "type": [cat(typ, np.int64)],
            "closed": [cat(closed, np.int64)], "valid": [cat(valid, np.float64)]}
    _write(path, meshio.Mesh(P, [("line", L)], cell_data=data))


def read_singular_curves_vtk(path) -> list[dict]:
    """Read a file of :func:`write_singular_curves_vtk` back: one dict per curve with ``points``
    ``(m, 3)`` numpy, ``label`` (a :data:`~torchconn.frames.singular.CURVE_TYPES` entry),
    ``closed`` and ``valid`` (``nan`` where the curve has no quarter-turn face)."""
    import meshio

    from .singular import CURVE_TYPES

    with open(path, "rb") as f:
        head = f.read(4096)
    if b'NumberOfPoints="0"' in head or b"\nPOINTS 0 " in head:
        return []
    m = meshio.read(str(path))
    lines = [b.data for b in m.cells if b.type == "line"]
    if not lines:
        return []
    L = np.concatenate(lines)
    get = lambda k: np.concatenate(m.cell_data[k])  # noqa: E731
    curve, typ, closed, valid = get("curve"), get("type"), get("closed"), get("valid")
    out = []
    for cid in np.unique(curve):
        sel = np.nonzero(curve == cid)[0]
        idx = np.concatenate([L[sel, 0], L[sel[-1:], 1]])
        out.append({"points": m.points[idx], "label": CURVE_TYPES[int(typ[sel[0]])],
                    "closed": bool(closed[sel[0]]),
                    "valid": float(valid[sel[0]]) if valid[sel[0]] >= 0 else float("nan")})
    return out


# ----------------------------------------------------------------------------- per-tet frame files
def _frames_np(frames, n_tets: int | None) -> np.ndarray:
    a = frames.detach().cpu().numpy() if torch.is_tensor(frames) else np.asarray(frames)
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ValueError(f"frames must have shape (T, 3, 3), got {a.shape}")
    if n_tets is not None and a.shape[0] != n_tets:
        raise ValueError(f"frames has {a.shape[0]} rows but the mesh has T = {n_tets} tets (per-tet frames expected)")
    if not np.isfinite(a).all():
        bad = np.nonzero(~np.isfinite(a).reshape(a.shape[0], -1).all(axis=1))[0]
        raise ValueError(f"frames has NaN/inf entries at tets {bad[:10].tolist()}")
    return a.astype(np.float64)


def _n_tets(mesh) -> int | None:
    return None if mesh is None else int(mesh.tets.shape[0])


def write_fra(path, frames, mesh=None) -> Path:
    """Write per-tet frames ``(T, 3, 3)`` (axes as columns) as a ``.fra`` file.

    ``mesh`` (optional) checks that there is one frame per tet. Returns the path.
    """
    a = _frames_np(frames, _n_tets(mesh))
    axes = np.swapaxes(a, 1, 2).reshape(-1, 3)  # row 3t+k = axis k of tet t
    path = Path(path)
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"FRA 1\n{a.shape[0]} 3 4\n")
        np.savetxt(fh, axes, fmt="%.17g")
    return path


def _tokens(path: Path, magic: str) -> tuple[list[str], list[str]]:
    with open(path, encoding="ascii", errors="replace") as fh:
        lines = [ln.strip() for ln in fh if ln.strip()]
    if not lines or lines[0].split() != magic.split():
        first = lines[0] if lines else "<empty file>"
        raise ValueError(f"{path}: line 1 must be {magic!r}, got {first!r}")
    if len(lines) < 2:
        raise ValueError(f"{path}: line 2 (the counts) is missing")
    return lines, lines[1].split()


def _parse_rows(path: Path, rows: list[str], width: int, first_line: int) -> np.ndarray:
    out = np.empty((len(rows), width))
    for r, ln in enumerate(rows):
        parts = ln.split()
        try:
            if len(parts) != width:
                raise ValueError
            out[r] = [float(x) for x in parts]
        except ValueError:
            raise ValueError(f"{path}: line {first_line + r} must hold {width} numbers, got {ln!r}") from None
    return out


def read_fra(path, *, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """Read a ``.fra`` file into ``frames (T, 3, 3)`` (axes as columns).

    Raises:
        ValueError: a wrong header (naming the line), a count that does not match the rows,
            or a row that is not three numbers.
    """
    path = Path(path)
    lines, head = _tokens(path, "FRA 1")
    if len(head) != 3 or head[1:] != ["3", "4"] or not head[0].isdigit():
        raise ValueError(f"{path}: line 2 must be '<number of tets> 3 4', got {lines[1]!r}")
    T = int(head[0])
    rows = lines[2:]
    if len(rows) != 3 * T:
        raise ValueError(f"{path}: {T} tets need {3 * T} axis lines after the header, found {len(rows)}")
    axes = _parse_rows(path, rows, 3, 3).reshape(T, 3, 3)  # [t, k, :] = axis k
    return torch.as_tensor(np.swapaxes(axes, 1, 2).copy(), dtype=dtype, device=device)


def write_mouette_frame(path, frames, mesh=None) -> Path:
    """Write per-tet frames ``(T, 3, 3)`` (axes as columns) as mouette's ``.frame`` file.

    ``mesh`` (optional) checks that there is one frame per tet. Returns the path.
    """
    a = _frames_np(frames, _n_tets(mesh))
    rows = np.swapaxes(a, 1, 2).reshape(-1, 9)  # a_x a_y a_z b_x ... per tet
    path = Path(path)
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"FRAME\n{a.shape[0]}\n")
        np.savetxt(fh, rows, fmt="%.17g")
        fh.write("END\n")
    return path


def read_mouette_frame(path, *, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """Read mouette's ``.frame`` file into ``frames (T, 3, 3)`` (axes as columns); the final
    ``END`` line is optional, as in mouette's reader.

    Raises:
        ValueError: a wrong header, a count that does not match the rows, or a bad row.
    """
    path = Path(path)
    lines, head = _tokens(path, "FRAME")
    if len(head) != 1 or not head[0].isdigit():
        raise ValueError(f"{path}: line 2 must be the number of frames, got {lines[1]!r}")
    T = int(head[0])
    rows = lines[2:]
    if rows and rows[-1] == "END":
        rows = rows[:-1]
    if len(rows) != T:
        raise ValueError(f"{path}: {T} frames announced, found {len(rows)} frame lines")
    axes = _parse_rows(path, rows, 9, 3).reshape(T, 3, 3)
    return torch.as_tensor(np.swapaxes(axes, 1, 2).copy(), dtype=dtype, device=device)
