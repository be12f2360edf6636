"""The integer-grid map of a frame field: charts, seamless solve, quantization, stiffening, snapping.

:func:`integer_grid_map` runs the steps of HEXMESH.md 1-6 on a ``TetMesh`` and per-tet frames and
returns an :class:`IntegerGridMap`; :func:`torchconn.hexmesh.validity.check_map` says whether it is
valid and, if not, where and why.

Snapping (HexEx's sanitization): the continuous free unknowns are rounded to multiples of
``2**-grid_bits`` and the integer ones are exact integers; every corner parameter is a short
sum of them with coefficients ``±1`` (or ``±1/2``, ``±2`` at half turns), so the corner
parameters are dyadic rationals computed exactly in float64, and the transitions
``u_t1 = R_f u_t0 + s_f`` hold *exactly* on every face: the validity check and the extraction
decide topology with exact arithmetic.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .cut import TetCharts, group_matrices, tet_charts
from .inputs import tet_frames_of
from .quantize import param_volumes, round_greedy, solve_fixed
from .seamless import SeamlessProblem, build_problem, default_edge_length

__all__ = ["IntegerGridMap", "integer_grid_map", "GRID_BITS"]

GRID_BITS = 20
"""Parameters are snapped to multiples of ``2**-GRID_BITS`` (parameter magnitudes must stay below
``2**30`` so that every sum of a few of them is exact in float64)."""


@dataclass
class IntegerGridMap:
    """A piecewise-linear map ``u`` of a tet mesh into parameter space, one chart per tet.

    Attributes:
        mesh: the ``TetMesh`` the map lives on: the input mesh, or its refinement by
            :func:`~.split.split_for_map` (original vertices first, same coordinates);
            ``parent_tet (T,)`` the input tet of each of its tets.
        uvw: ``(T, 4, 3)`` float64, the parameter of local corner ``k`` of tet ``t``
            (vertex ``mesh.tets[t, k]``) in tet ``t``'s chart; dyadic, multiples of
            ``2**-grid_bits``.
        face_rot: ``(F,)`` int64 index into :func:`torchconn.frames.octahedral.group` and
            ``face_shift (F, 3)`` int64: on every interior face ``f = (t0, t1)``
            (``mesh.face_tets``) ``u_t1 = G[face_rot[f]] u_t0 + face_shift[f]`` (the shift of a
            face whose transition is broken is the one of its first vertex); zero on boundary
            faces.
        edge_length: the hex edge length ``h`` (parameter unit = ``h`` world units).
        charts: the :class:`~.cut.TetCharts` (combed frames, cut, edge holonomy).
        energy: the frame-fitting energy ``sum vol ||grad u (h F) - I||^2`` of the final map
            divided by the total volume, and ``energy_continuous`` of the unrounded optimum.
        grid_bits: the snapping grid.
        stats: sizes of the problem (:attr:`SeamlessProblem.counts`), rounding and stiffening
            figures, timings per step (seconds), the solver backend.
        problem: the :class:`~.seamless.SeamlessProblem` (constraints, objective).
    """

    mesh: object
    parent_tet: np.ndarray
    uvw: np.ndarray
    face_rot: np.ndarray
    face_shift: np.ndarray
    edge_length: float
    charts: TetCharts
    energy: float
    energy_continuous: float
    grid_bits: int
    stats: dict = field(default_factory=dict)
    problem: SeamlessProblem | None = field(default=None, repr=False)

    def flipped(self) -> np.ndarray:
        """``(T,)`` bool: tets whose parametric volume is not positive (exact predicate)."""
        from .predicates import orient3d

        return orient3d(self.uvw[:, 0], self.uvw[:, 1], self.uvw[:, 2], self.uvw[:, 3]) <= 0


def integer_grid_map(mesh, frames, *, edge_length: float | None = None, straighten: bool = True,
                     straighten_boundary: bool = True, touch_rounds: int = 0, split: bool = True,
                     features: bool = True,
                     feature_max_deg: float = 30.0, batch_error: float = 0.5, stiffening_iters: int = 10,
                     stiffening_factor: float = 4.0, grid_bits: int = GRID_BITS, backend: str = "auto",
                     progress: bool = False) -> IntegerGridMap:
    """The integer-grid map of a frame field (HEXMESH.md steps 2-6).

    Args:
        mesh: a ``TetMesh``.
        frames: a :class:`~torchconn.frames.design.FrameFieldResult` on ``mesh``, or frames
            ``(T, 3, 3)`` per tet or ``(V, 3, 3)`` per vertex (axes as columns; per-vertex frames
            become per-tet ones by :func:`torchconn.frames.design.tet_frames`).
        edge_length: the hex edge length ``h`` (default :func:`~.seamless.default_edge_length`:
            the mean edge length of ``mesh``).
        straighten: repair the face matchings so that singular edges run along their turn axis
            (:func:`~.straighten.straighten_singular_edges`).
        straighten_boundary: the search may also change faces with a boundary edge (it can then
            push a singular curve that runs along the boundary onto it).
        touch_rounds: rounds of "split the singular edges that touch the boundary about a
            tangent axis, straighten again" (0: none).
        split: split the edges that would collapse or flatten (:func:`~.split.split_for_map`);
            the map is then of the refined mesh (``result.mesh``).
        features: constrain feature curves and CAD corners (:func:`~.seamless.build_problem`).
        feature_max_deg: see :func:`~.seamless.build_problem`.
        batch_error, stiffening_iters, stiffening_factor: of the quantization
            (:mod:`~.quantize`).
        grid_bits: the snapping grid (module docstring).
        backend: sparse solver, ``"auto"`` / ``"cholmod"`` / ``"superlu"`` (:mod:`~.solver`).
        progress: show a progress bar on the rounding (tqdm).

    Returns:
        :class:`IntegerGridMap`. It may be invalid (flipped tets, a complex singular edge, a
        contradiction among the constraints): :func:`~.validity.check_map` says where and why.

    Raises:
        ValueError: frames of the wrong shape or not rotations, a field on another mesh, a
            non-positive edge length.
    """
    if edge_length is not None and not (isinstance(edge_length, (int, float)) and np.isfinite(edge_length)
                                        and edge_length > 0):
        raise ValueError(f"edge_length must be a positive number, got {edge_length!r}")
    if not (isinstance(grid_bits, int) and 8 <= grid_bits <= 40):
        raise ValueError(f"grid_bits must be an integer in [8, 40], got {grid_bits!r}")
    if stiffening_iters < 0:
        raise ValueError(f"stiffening_iters must be >= 0, got {stiffening_iters}")
    timings = {}
    t0 = time.perf_counter()
    Fr = tet_frames_of(mesh, frames)
    h = default_edge_length(mesh) if edge_length is None else float(edge_length)
    parent = np.arange(mesh.n_tets)
    splits, sinfo = {}, {}
    face_match = None
    if straighten:
        from .split import split_pairs
        from .straighten import straighten_singular_edges, touching_edges

        face_match, sinfo = straighten_singular_edges(mesh, Fr, boundary_moves=straighten_boundary)
        sinfo["touch_splits"] = 0
        for _ in range(touch_rounds):
            bad = touching_edges(mesh, Fr, face_match)
            if not bad.size:
                break
            # split them: the midpoints open routes for the curve off the boundary vertex
            mesh, Fr, par, face_match = split_pairs(mesh, Fr, mesh.edges[bad].cpu().numpy(), face_match)
            parent = parent[par]
            sinfo["touch_splits"] += int(bad.size)
            face_match, again = straighten_singular_edges(mesh, Fr, face_match, boundary_moves=straighten_boundary)
            sinfo["moves"] += again["moves"]
            for key in ("edge_cost_after", "singular_after", "across_after", "complex_after"):
                sinfo[key] = again[key]
        sinfo["touching_after"] = int(touching_edges(mesh, Fr, face_match).size)
    timings["straighten_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if split:
        from .split import split_for_map

        sr = split_for_map(mesh, Fr, face_match)
        mesh, Fr, splits, face_match = sr.mesh, sr.tet_frames, sr.splits, sr.face_match
        parent = parent[sr.parent_tet]
    timings["split_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    charts = tet_charts(mesh, Fr, face_match)
    timings["charts_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    prob = build_problem(mesh, charts, h, features=features, feature_max_deg=feature_max_deg)
    timings["constraints_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    A, b, c = prob.energy_matrices()
    int_mask = prob.free_is_int
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=int(int_mask.sum()), desc="rounding", unit="int", leave=False)

        def cb(done, total):
            bar.n = done
            bar.refresh()
    else:
        cb = None
    try:
        y, rinfo = round_greedy(A, b, int_mask, batch_error=batch_error, backend=backend, progress=cb,
                                flips=lambda yy: int((param_volumes(prob.corner_params(yy)) <= 0).sum()))
    finally:
        if bar is not None:
            bar.close()
    vol_total = float(prob.vol.sum())
    # the continuous optimum's energy (before rounding): from the same factorization route
    y_cont = solve_fixed(A, b, np.zeros_like(int_mask), np.zeros(0), backend=backend) if int_mask.any() else y
    e_cont = float(y_cont @ (A @ y_cont) - 2 * b @ y_cont + c) / vol_total
    timings["solve_and_round_s"] = time.perf_counter() - t0

    # stiffening: raise the weight of tets that are not positively oriented, re-solve
    t0 = time.perf_counter()
    weights = np.ones(prob.vol.size)
    uvw = prob.corner_params(y)
    n_flip_rounded = int((param_volumes(uvw) <= 0).sum())
    iters = 0
    for _ in range(stiffening_iters):
        flip = param_volumes(uvw) <= 0
        if not flip.any():
            break
        weights[flip] *= stiffening_factor
        Aw, bw, _ = prob.energy_matrices(weights)
        y = solve_fixed(Aw, bw, int_mask, y[int_mask], backend=backend)
        uvw = prob.corner_params(y)
        iters += 1
    timings["stiffening_s"] = time.perf_counter() - t0

    # snapping to the dyadic grid: exact corner parameters and transitions
    scale = float(2 ** grid_bits)
    ys = y.copy()
    ys[~int_mask] = np.round(y[~int_mask] * scale) / scale
    ys[int_mask] = np.round(y[int_mask])
    uvw = prob.corner_params(ys)
    if np.abs(uvw).max(initial=0.0) >= 2.0 ** 30:
        raise ValueError(f"the parameters reach {np.abs(uvw).max():.3g} >= 2**30: edge_length {h:g} is too small "
                         f"for this mesh")
    energy = float(ys @ (A @ ys) - 2 * b @ ys + c) / vol_total
    face_shift = _face_shifts(mesh, charts, uvw)
    stats = dict(prob.counts)
    stats["splits"] = splits
    stats["straighten"] = sinfo
    stats.update({"rounding_steps": rinfo["steps"], "integers": rinfo["n_integers"],
                  "max_rounding": rinfo["max_rounding"], "undetermined_integers": rinfo["undetermined"],
                  "flipped_after_rounding": n_flip_rounded, "stiffening_iterations": iters,
                  "solver": rinfo["backend"], "timings": timings})
    return IntegerGridMap(mesh=mesh, parent_tet=parent, uvw=uvw, face_rot=charts.face_rot.copy(), face_shift=face_shift, edge_length=h,
                          charts=charts, energy=energy, energy_continuous=e_cont, grid_bits=grid_bits, stats=stats,
                          problem=prob)


def _face_shifts(mesh, charts: TetCharts, uvw: np.ndarray) -> np.ndarray:
    """``s_f = u_t1(v) - R_f u_t0(v)`` at each interior face's first vertex (rounded to integers;
    the validity check compares all three vertices exactly)."""
    from .cut import face_corner_pairs

    tets = mesh.tets.cpu().numpy()
    faces = mesh.faces.cpu().numpy()
    face_tets = mesh.face_tets.cpu().numpy()
    fc = face_corner_pairs(tets, faces, mesh.tet_faces.cpu().numpy(), face_tets)
    F = faces.shape[0]
    out = np.zeros((F, 3), np.int64)
    fi = np.nonzero(charts.interior_face)[0]
    G = group_matrices().astype(np.float64)
    u0 = uvw[face_tets[fi, 0], fc[fi, 0, 0]]
    u1 = uvw[face_tets[fi, 1], fc[fi, 1, 0]]
    s = u1 - np.einsum("fij,fj->fi", G[charts.face_rot[fi]], u0)
    out[fi] = np.round(s).astype(np.int64)
    return out
