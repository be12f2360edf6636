"""VTU export of a frame field and its singular faces (for ParaView), written atomically.

``frames.vtu``: the tet mesh with point data ``axis0, axis1, axis2 (V, 3)``, the columns
``frames[:, :, k]`` (axis ``k`` at each vertex, world coordinates). ``singular_faces.vtu``: the
singular faces ``(S, 3)`` as triangles on the same vertices. Each file goes to a temporary file
in the target's directory first and is then moved over the target (``os.replace``), so a crash
leaves the old file or the new one. Needs ``meshio`` (imported on call).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

__all__ = ["write_frames_vtu", "write_singular_faces_vtu"]


def _write(path, mesh) -> None:
    import meshio

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.vtu")  # meshio writes to a path and picks the format by suffix
    meshio.write(str(tmp), mesh)
    os.replace(tmp, path)


def write_frames_vtu(path, mesh, frames: torch.Tensor) -> None:
    """Write the tets of ``mesh`` with ``frames (V, 3, 3)`` as point data ``axis0..2`` to ``path``."""
    import meshio

    V = mesh.vertices.detach().cpu().double().numpy()
    T = mesh.tets.cpu().numpy().astype(np.int64)
    F = frames.detach().cpu().double().numpy()
    _write(path, meshio.Mesh(V, [("tetra", T)], point_data={f"axis{k}": F[:, :, k] for k in range(3)}))


def write_singular_faces_vtu(path, mesh, singular_faces: torch.Tensor) -> None:
    """Write the triangles ``singular_faces (S, 3)`` long (vertex indices of ``mesh``) to ``path``."""
    import meshio

    V = mesh.vertices.detach().cpu().double().numpy()
    S = singular_faces.cpu().numpy().astype(np.int64).reshape(-1, 3)
    _write(path, meshio.Mesh(V, [("triangle", S)]))
