"""VTK export of a frame field, its singular faces and its singular curves, written atomically.

``frames.vtu``: the tet mesh with point data ``axis0, axis1, axis2 (V, 3)``, the columns
``frames[:, :, k]`` (axis ``k`` at each vertex, world coordinates). ``singular_faces.vtu``: the
singular faces ``(S, 3)`` as triangles on the same vertices. ``singular_curves.vtu`` (or
``.vtk``): the curves of a :class:`~torchconn.frames.singular.SingularGraph` as polylines (one
``line`` cell per segment, :func:`write_singular_curves_vtk`; :func:`read_singular_curves_vtk`
reads it back). Each file goes to a temporary file in the target's directory first and is then
moved over the target (``os.replace``), so a crash leaves the old file or the new one. Needs
``meshio`` (imported on call).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

__all__ = ["write_frames_vtu", "read_frames_vtu", "FramesVTU", "write_singular_faces_vtu",
           "write_singular_curves_vtk", "read_singular_curves_vtk"]


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
