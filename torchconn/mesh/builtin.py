"""Meshes without files: :func:`tetrahedralize` a closed surface, and the built-ins :func:`box`
(Kuhn split of a cube grid), :func:`ball`, :func:`cylinder`, :func:`torus` (pymeshlab primitives
+ tetgen).

:func:`tetrahedralize` wraps ``igl.copyleft.tetgen.tetrahedralize`` after checking that the
surface is closed, edge-manifold, consistently oriented and free of degenerate triangles.
libigl and pymeshlab are imported inside the functions that use them. All meshes are positively
oriented :class:`~torchconn.mesh.TetMesh` objects.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
import torch

from .cells import CellComplex
from .errors import MeshError, _few
from .tet import TetMesh

__all__ = ["tetrahedralize", "box", "ball", "cylinder", "torus"]


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
