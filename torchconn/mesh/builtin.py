"""Meshes without files: :func:`tetrahedralize` a closed surface, and the built-ins :func:`box`
(Kuhn split of a cube grid), :func:`ball`, :func:`cylinder`, :func:`torus` (pymeshlab primitives
+ tetgen).

:func:`tetrahedralize` wraps ``igl.copyleft.tetgen.tetrahedralize`` after checking that the
surface is closed, edge-manifold, consistently oriented, free of degenerate triangles and of
self-intersections, and that the estimated tet count (:func:`estimate_tets`) is below
``max_tets``. Sizes default to a fraction of the bounding-box diagonal.
libigl and pymeshlab are imported inside the functions that use them. All meshes are positively
oriented :class:`~torchconn.mesh.TetMesh` objects.
"""
from __future__ import annotations

import itertools
import math
import numbers
import warnings

import numpy as np
import torch

from .cells import CellComplex
from .errors import MeshError, _few
from .tet import TetMesh

__all__ = ["tetrahedralize", "box", "ball", "cylinder", "torus", "estimate_tets", "self_intersecting_faces",
           "DEFAULT_EDGE_FRACTION", "DEFAULT_MAX_TETS"]


# ----------------------------------------------------------------------------- tetgen
# Default target edge length when neither size is given, as a fraction of the surface's
# bounding-box diagonal, so a model in millimetres and the same model in metres get the same mesh.
DEFAULT_EDGE_FRACTION = 0.05
# Default limit of the estimated tet count above which tetrahedralize refuses to start.
DEFAULT_MAX_TETS = 5_000_000
# Tet-count estimate: tetgen's volume bound `a` is an upper bound, so its tets average about half
# the bound (measured: 1.8-2.0x the volume / bound ratio on ball and torus), and the quality bound
# alone makes about 2.3-2.6 tets per surface triangle (bunny, fandisk).
_TETS_PER_BOUND_VOLUME = 2.0
_TETS_PER_SURFACE_FACE = 2.5


def _regular_tet_volume(edge_length: float) -> float:
    return edge_length**3 / (6.0 * math.sqrt(2.0))


def _positive(name: str, value, what: str = "length in the model's units") -> float | None:
    """``float(value)``, or None for None; MeshError naming ``name`` unless finite and > 0."""
    if value is None:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if isinstance(value, bool) or not math.isfinite(x) or x <= 0:
        raise MeshError(f"{name} must be a positive finite number (a {what}), got {value!r}; pass None for "
                        f"the default ({DEFAULT_EDGE_FRACTION:g} x the bounding-box diagonal)")
    return x


def _max_tets(value) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise MeshError(f"max_tets must be a positive integer or None (no limit), got {value!r}")
    return int(value)


def estimate_tets(volume: float, cell_volume: float, n_surface_faces: int = 0) -> int:
    """Rough tetgen tet count (within about a factor 2) for a solid of ``volume`` meshed with
    the volume bound ``cell_volume`` (``a``) and a quality bound:
    ``2 volume / cell_volume + 2.5 n_surface_faces``."""
    return int(math.ceil(_TETS_PER_BOUND_VOLUME * volume / cell_volume + _TETS_PER_SURFACE_FACE * n_surface_faces))


def _check_budget(estimate: int, max_tets: int | None, detail: str) -> None:
    if max_tets is not None and estimate > max_tets:
        raise MeshError(f"mesh too large: about {estimate:,} tets estimated ({detail}), above the limit "
                        f"max_tets={max_tets:,}; pass a larger edge_length/max_volume (sizes are absolute, in "
                        f"the model's units) or raise the limit with max_tets=... (None: no limit)")


def self_intersecting_faces(V, F) -> np.ndarray:
    """``(K,)`` sorted ids of the triangles of ``F (M,3)`` over ``V (N,3)`` that intersect another
    triangle of the surface (pymeshlab ``compute_selection_by_self_intersections_per_face``;
    triangles that only share an edge or a vertex do not count)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(V, dtype=np.float64),
                               face_matrix=np.asarray(F, dtype=np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    return np.nonzero(ms.current_mesh().face_selection_array())[0].astype(np.int64)


def tetrahedralize(V, F, max_volume: float | None = None, edge_length: float | None = None,
                   quality: float = 1.414, keep_surface: bool = False,
                   max_tets: int | None = DEFAULT_MAX_TETS, **kwargs) -> TetMesh:
    """Tetrahedralize the inside of a closed triangle surface with tetgen (libigl).

    Args:
        V: ``(N, 3)`` surface vertices; F: ``(M, 3)`` triangles.
        max_volume: tetgen volume bound ``a`` (model units cubed).
        edge_length: target edge length, turned into the volume of the regular tet of that
            edge, ``L^3 / (6 sqrt 2)`` (the smaller bound wins when both are given). With
            neither size, ``edge_length = DEFAULT_EDGE_FRACTION (0.05) x`` the bounding-box
            diagonal of ``V``.
        quality: radius–edge ratio bound ``q`` (>= 1).
        keep_surface: keep the input triangles unsplit (tetgen ``Y``); this tends to leave
            slivers near the surface.
        max_tets: refuse to mesh when :func:`estimate_tets` exceeds it (``None``: no limit).
        **kwargs: passed to :class:`TetMesh` (``dtype``, ``device``).

    The tetgen switches are ``pq{quality}a{vol}[Y]Q``. Before tetgen runs, the surface is
    checked (closed, edge-manifold, consistently oriented, no degenerate triangles, no
    self-intersections: tetgen can crash the interpreter on those) and the tet count is
    estimated. A size coarser than the model (``edge_length`` above half the bounding-box
    diagonal) warns: the surface alone then sets the mesh.

    Raises:
        MeshError: a size that is not a positive finite number (naming the argument); the
            surface is not closed / not edge-manifold / not consistently oriented (naming the
            edges as vertex pairs), has degenerate or self-intersecting triangles (naming them);
            the estimate is above ``max_tets``; tetgen fails or returns no tets.
    """
    import igl.copyleft.tetgen  # noqa: F401  (fail here, in this process, when libigl is missing)

    V = np.ascontiguousarray(np.asarray(V, dtype=np.float64))
    F = np.ascontiguousarray(np.asarray(F)).astype(np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise MeshError(f"tetrahedralize needs V (N, 3) and F (M, 3), got {V.shape} and {F.shape}")
    edge_length = _positive("edge_length", edge_length)
    max_volume = _positive("max_volume", max_volume, "volume in the model's units cubed")
    if isinstance(quality, bool) or not (isinstance(quality, numbers.Real) and math.isfinite(quality) and quality >= 1):
        raise MeshError(f"quality must be a finite number >= 1 (tetgen's radius-edge bound; smaller bounds "
                        f"may never be met), got {quality!r}")
    max_tets = _max_tets(max_tets)
    surf = CellComplex(V, F, dtype=torch.float64)
    surf.check_closed_manifold()
    deg = surf.degenerate_faces().numpy()
    if deg.size:
        raise MeshError(f"surface has degenerate (zero-area) triangles: face indices {_few(deg)}")
    crossing = self_intersecting_faces(V, F)
    if crossing.size:
        raise MeshError(f"surface self-intersects: triangles {_few(crossing)} cross other triangles of the "
                        f"surface (e.g. face {int(crossing[0])} = {F[crossing[0]].tolist()}); tetgen cannot mesh "
                        f"it. Repair the surface first (separate or boolean-union overlapping parts)")
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    volume = abs(float(surf.enclosed_volume()))
    if edge_length is None and max_volume is None:
        edge_length = DEFAULT_EDGE_FRACTION * diag
    vols = [v for v in (max_volume, None if edge_length is None else _regular_tet_volume(edge_length)) if v]
    bound = min(vols)
    estimate = estimate_tets(volume, bound, F.shape[0])
    _check_budget(estimate, max_tets, f"enclosed volume {volume:.4g} / volume bound {bound:.4g}, "
                                      f"{F.shape[0]} surface triangles; bounding-box diagonal {diag:.4g}")
    if bound > _regular_tet_volume(0.5 * diag):
        size = f"edge_length {edge_length:g}" if edge_length is not None else f"max_volume {max_volume:g}"
        warnings.warn(f"tetrahedralize: the size ({size}, volume bound {bound:.4g}) is coarser "
                      f"than the model (bounding-box diagonal {diag:.4g}): the surface alone sets the mesh, about "
                      f"{estimate} tets. Sizes are absolute, in the model's units: pass e.g. "
                      f"edge_length={DEFAULT_EDGE_FRACTION * diag:.3g} ({DEFAULT_EDGE_FRACTION:g} x diagonal)",
                      stacklevel=2)
    flags = f"pq{quality:g}a{bound:.9g}"
    if keep_surface:
        flags += "Y"
    flags += "Q"
    TV, TT = _run_tetgen(V, F, flags, keep_surface)
    if TT.ndim != 2 or TT.shape[0] == 0:
        raise MeshError(f"tetgen returned no tets (flags {flags!r})")
    # tetgen's orientation convention is opposite to ours; orient each tet explicitly
    p = TV[TT]
    vol6 = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    neg = vol6 < 0
    TT[neg] = TT[neg][:, [0, 1, 3, 2]]
    kwargs.setdefault("unreferenced", "drop")
    return TetMesh(TV, TT, **kwargs)


def _tetgen_child(conn, V, F, flags) -> None:
    """Child side of :func:`_run_tetgen`: send ``("ok", TV, TT)`` or ``("error", message)``."""
    import faulthandler

    faulthandler.disable()  # a crash is reported by the parent as a MeshError, not as a C traceback
    try:
        import igl.copyleft.tetgen as tg

        out = tg.tetrahedralize(V, F, flags=flags)
        conn.send(("ok", np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)))
    except BaseException as err:  # noqa: BLE001 - everything goes back to the parent as a message
        conn.send(("error", f"{type(err).__name__}: {err}"))
    finally:
        conn.close()


def _run_tetgen(V: np.ndarray, F: np.ndarray, flags: str, keep_surface: bool) -> tuple[np.ndarray, np.ndarray]:
    """tetgen in a forked child process: tetgen can abort or segfault on some inputs (e.g. a
    refinement of long thin surface triangles without ``Y``), which would end the caller's
    interpreter; in a child that becomes a :class:`MeshError`. Without ``fork`` (Windows,
    macOS spawn) tetgen runs in-process."""
    import multiprocessing as mp

    if "fork" not in mp.get_all_start_methods():
        import igl.copyleft.tetgen as tg

        try:
            out = tg.tetrahedralize(V, F, flags=flags)
        except Exception as err:  # noqa: BLE001 - tetgen errors come as RuntimeError or worse
            raise MeshError(f"tetgen failed with flags {flags!r}: {err}") from err
        return np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)
    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_tetgen_child, args=(send, V, F, flags), daemon=True)
    proc.start()
    send.close()
    try:
        msg = recv.recv()
    except EOFError:  # the child died without answering (signal)
        msg = None
    finally:
        recv.close()
        proc.join()
    if msg is None:
        code = proc.exitcode
        how = f"signal {-code}" if code is not None and code < 0 else f"exit status {code}"
        hint = ("keep the surface (keep_surface=True)" if not keep_surface else "a different edge_length")
        raise MeshError(f"tetgen crashed ({how}) on this surface of {V.shape[0]} vertices / {F.shape[0]} "
                        f"triangles with flags {flags!r}; the surface is valid for us (closed, manifold, no "
                        f"self-intersection), so try {hint} or remesh the surface more uniformly")
    if msg[0] == "error":
        raise MeshError(f"tetgen failed with flags {flags!r}: {msg[1]}")
    return msg[1], msg[2]


def _builtin_budget(name: str, volume: float, edge_length, kwargs: dict) -> float:
    """Validate a built-in's ``edge_length`` and stop before building its surface when the
    estimated tet count is above ``kwargs['max_tets']`` (default :data:`DEFAULT_MAX_TETS`)."""
    L = _positive("edge_length", edge_length)
    if L is None:
        raise MeshError(f"{name} needs an edge_length (a positive length), got None")
    est = estimate_tets(volume, _regular_tet_volume(L))
    _check_budget(est, _max_tets(kwargs.get("max_tets", DEFAULT_MAX_TETS)),
                  f"{name} of volume {volume:.4g} with edge_length {L:g}")
    return L


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
    radius = _positive("radius", radius)
    edge_length = _builtin_budget("ball", 4.0 / 3.0 * math.pi * radius**3, edge_length, kwargs)
    # icosahedron edge is 1.051 r; each subdivision halves it
    level = int(np.clip(round(math.log2(1.051 * radius / edge_length)), 0, 6))
    V, F = _primitive("create_sphere", radius=float(radius), subdiv=level)
    V = V + np.asarray(center, dtype=np.float64)
    return tetrahedralize(V, _orient_outward(V, F), edge_length=edge_length, **kwargs)


def cylinder(radius: float = 1.0, height: float = 2.0, edge_length: float = 0.3, **kwargs) -> TetMesh:
    """Tet mesh of a solid cylinder with axis ``z``, centered at the origin
    (``|z| <= height/2``): pymeshlab ``create_cone`` with equal radii (rotated from its ``y``
    axis) tetrahedralized with target ``edge_length``. ``kwargs`` go to :func:`tetrahedralize`."""
    radius, height = _positive("radius", radius), _positive("height", height)
    edge_length = _builtin_budget("cylinder", math.pi * radius**2 * height, edge_length, kwargs)
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
    edge_length = _builtin_budget("torus", 2 * math.pi**2 * major_radius * minor_radius**2, edge_length, kwargs)
    hs = max(8, math.ceil(2 * math.pi * major_radius / edge_length))
    vs = max(6, math.ceil(2 * math.pi * minor_radius / edge_length))
    V, F = _primitive("create_torus", hradius=float(major_radius), vradius=float(minor_radius), hsubdiv=hs, vsubdiv=vs)
    return tetrahedralize(V, _orient_outward(V, F), edge_length=edge_length, **kwargs)
