"""The integer-grid map of a frame field, in gated stages: structure, seamless map, quantization.

:func:`integer_grid_map` runs HEXMESH.md steps 1-6 on a ``TetMesh`` and per-tet frames, each stage
judged before the next (:class:`~.validity.Gate`):

1. **structure** (:func:`~.structure.map_structure`) — the face matchings straightened
   (:mod:`.straighten`) and, with ``repair=True``, repaired until LMFF's conditions are gone
   (:mod:`.repair`), or given (``face_match=``); edges split so that no tet is flattened by the
   constraints (:mod:`.split`; the flat tets are found exactly,
   :meth:`.seamless.SeamlessProblem.flat_tets`), the charts and the cut (:mod:`.cut`), the
   constraints eliminated (:mod:`.seamless`). Passes when the singular graph meets LMFF's local
   conditions (:mod:`.meshability`) and no tet is flat.
2. **frames** (with ``integrable=True``) — integrable coframes near the field's, by a continuation
   on the torsion of the coframes under the matched connection (:mod:`.integrable`); the seamless
   map then fits them. Passes when no coframe is inverted and the alignment does not conflict.
3. **seamless map** — the frame-fitting least squares with every integer relaxed; where it folds,
   the foldover-free solve (:mod:`.injective`: per-tet barrier, PSD-projected Newton). Snapped to
   the grid and checked exactly (:func:`~.validity.check_seamless`): no inverted or flat tet,
   seams, singular edges on parametric lines, boundary faces on parametric planes.
4. **quantization** — from a seamless map with no inverted tet, every integer rounded by
   injective moves (:func:`~.quantize.round_injective`: no tet ever folds; the tets the
   constraints flatten, which no map opens, are left out and stay flat); from one that folds,
   greedy rounding with the least-squares re-solves and stiffening (:func:`~.quantize.round_greedy`,
   :func:`~.quantize.stiffen`). Snapped and checked (:func:`~.validity.check_map`).

The map of an invalid stage is still carried to the end (its report says where it fails).

Snapping (HexEx's sanitization, :func:`~.quantize.snap`): the continuous free unknowns are rounded
to multiples of ``2**-grid_bits`` and the integer ones are exact integers, so that the corner
parameters are dyadic rationals and the transitions hold exactly on every face: the validity check
and the extraction decide topology with exact arithmetic.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from .cut import TetCharts, group_matrices
from .inputs import tet_frames_of
from .quantize import GRID_BITS, param_volumes, round_greedy, round_injective, snap, solve_fixed, stiffen
from .seamless import FEATURE_MAX_DEG, SeamlessProblem, build_problem, default_edge_length
from .structure import map_structure
from .validity import Gate, MapValidity, check_map, check_seamless

__all__ = ["IntegerGridMap", "integer_grid_map"]


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
        seamless_uvw: ``(T, 4, 3)`` the seamless map before quantization (snapped to the same
            grid; its translations real).
        face_rot: ``(F,)`` int64 index into :func:`torchconn.frames.octahedral.group` and
            ``face_shift (F, 3)`` int64: on every interior face ``f = (t0, t1)``
            (``mesh.face_tets``) ``u_t1 = G[face_rot[f]] u_t0 + face_shift[f]`` (the shift of a
            face whose transition is broken is the one of its first vertex); zero on boundary
            faces.
        edge_length: the hex edge length ``h`` (parameter unit = ``h`` world units).
        charts: the :class:`~.cut.TetCharts` (combed frames, cut, edge holonomy).
        energy: the frame-fitting energy ``sum vol ||grad u (h F) - I||^2`` of the final map
            divided by the total volume; ``energy_seamless`` of the seamless map,
            ``energy_continuous`` of the least-squares optimum (integers relaxed).
        grid_bits: the snapping grid.
        gates: ``{"structure", "seamless", "quantization"}`` -> :class:`~.validity.Gate`, each
            stage's verdict (``quantization``'s is the final map's :func:`~.validity.check_map`).
        validity: the :class:`~.validity.MapValidity` of the final map.
        meshability: the :class:`~.meshability.Meshability` report of the singular graph the
            map saw.
        stats: sizes of the problem (:attr:`SeamlessProblem.counts`), splits, the structure
            search, the foldover-free solve and the rounding, timings per step (seconds).
        problem: the :class:`~.seamless.SeamlessProblem` (constraints, objective).
        tet_frames: ``(T, 3, 3)`` float64 tensor, the field the map follows, on ``mesh``: the
            input's frames (a child tet has its parent's), re-optimized with the holonomy fixed
            where the structure stage changed matchings (``fixed_holonomy``); its best face
            matchings are the map's where ``stats["fixed_holonomy"]["agree"]`` is 1.
    """

    mesh: object
    parent_tet: np.ndarray
    uvw: np.ndarray
    seamless_uvw: np.ndarray
    face_rot: np.ndarray
    face_shift: np.ndarray
    edge_length: float
    charts: TetCharts
    energy: float
    energy_seamless: float
    energy_continuous: float
    grid_bits: int
    gates: dict = field(default_factory=dict)
    validity: MapValidity | None = None
    meshability: object | None = field(default=None, repr=False)
    stats: dict = field(default_factory=dict)
    problem: SeamlessProblem | None = field(default=None, repr=False)
    tet_frames: object | None = field(default=None, repr=False)

    def flipped(self) -> np.ndarray:
        """``(T,)`` bool: tets whose parametric volume is not positive (exact predicate)."""
        from .predicates import orient3d

        return orient3d(self.uvw[:, 0], self.uvw[:, 1], self.uvw[:, 2], self.uvw[:, 3]) <= 0

    @property
    def first_failed(self) -> str | None:
        """The first stage whose gate failed (``None``: the map is valid). LMFF's conditions
        predict, they do not decide: a structure gate that fails before a valid seamless map or a
        valid integer-grid map did not stop the map, and is not named."""
        from .validity import first_failed

        return first_failed(self.gates)


def integer_grid_map(mesh, frames, *, edge_length: float | None = None, face_match=None, straighten: bool = True,
                     straighten_boundary: bool = True, touch_rounds: int = 0, repair: bool = True,
                     repair_rounds: int = 30, repair_slide: bool = True, split: bool = True, collapse: bool = True,
                     features: bool = True, feature_max_deg: float = FEATURE_MAX_DEG, flat_rounds: int = 8,
                     relocate: bool = True, one_ring: bool = True, fixed_holonomy: bool = True, injective: bool = True,
                     fit_weight: float = 1.0, sd_weight: float = 1.0, refine_limit: int = 2,
                     integrable: bool = False, batch_error: float = 0.5, stiffening_iters: int = 10,
                     stiffening_factor: float = 4.0,
                     grid_bits: int = GRID_BITS, backend: str = "auto", progress: bool = False) -> IntegerGridMap:
    """The integer-grid map of a frame field, in gated stages (module docstring).

    Args:
        mesh: a ``TetMesh``.
        frames: a :class:`~torchconn.frames.design.FrameFieldResult` on ``mesh``, or frames
            ``(T, 3, 3)`` per tet or ``(V, 3, 3)`` per vertex (:func:`~.inputs.tet_frames_of`).
        edge_length: the hex edge length ``h`` (default :func:`~.seamless.default_edge_length`:
            half the mean edge length of ``mesh``).
        face_match: ``(F,)`` face matchings (indices into the 24 elements of O) to follow as
            they are: no search, no repair (e.g. a field's matchings repaired beforehand).
        straighten: repair the face matchings so that singular edges run along their turn axis
            (:func:`~.straighten.straighten_singular_edges`).
        straighten_boundary: the search may also change faces with a boundary edge.
        touch_rounds: rounds of "split the singular edges that touch the boundary about a
            tangent axis, straighten again" (0: none).
        repair: after the search, repair the singular graph until LMFF's conditions are gone
            (:func:`~.repair.repair_singular_graph`, at most ``repair_rounds`` rounds; its edge
            splits refine the mesh); its :class:`~.repair.RepairReport` is in
            ``stats["repair"]`` and the structure gate says what it left.
            On by default: on the 17 simple HexMe ``c`` models with the SH field it takes the good
            hex meshes from 8 to 10 (docs/results/hexmesh.md).
        repair_slide: the repair also slides the ends of arcs that touch the boundary about a
            tangent axis along the surface (:func:`~.repair.slide_moves`); on by default since
            2026-11-27, with ``feature_max_deg`` 15 (:data:`~.seamless.FEATURE_MAX_DEG`: what the
            two gain together, and what they cost).
        split: split the edges that would collapse or flatten (:func:`~.split.split_for_map`);
            the map is then of the refined mesh (``result.mesh``).
        collapse: collapse the tet edges that the constraints send to one point (collapsed tets,
            :func:`~.collapse.collapse_edges`): the map's mesh then has fewer vertices.
        features: constrain feature curves and CAD corners (:func:`~.seamless.build_problem`).
        feature_max_deg: see :func:`~.seamless.build_problem`.
        flat_rounds: rounds of "split an edge of every tet the constraints flatten (but do not
            collapse)" (:meth:`~.seamless.SeamlessProblem.flat_tets`).
        relocate: move the singular arcs' vertices onto their turn axes before the map
            (:func:`~.relocate.relocate_singular_vertices`; ``stats["relocation"]``): the boundary,
            CAD tags, tets and matchings kept (docs/results/hexmesh.md: what it changes).
        one_ring: LMFF's numeric one-ring test at the singular vertices of the structure
            (:func:`~.one_ring.one_ring_test`), reported in ``gates["structure"]`` (``counts``,
            ``info``); it does not decide the gate.
        fixed_holonomy: stage 2, when the structure gate passes and the structure stage changed
            face matchings (the search or the repair: the frames no longer match as the matchings
            say), re-optimize the frames there with the matchings fixed, by a connection
            (:func:`torchconn.frames.fixed_holonomy.fixed_holonomy_frames`), and fit the map to
            those (``result.tet_frames``; ``stats["fixed_holonomy"]``). Not run on a structure
            that fails its gate: it changed no verdict on the 17 simple HexMe models there, and
            costs up to 16 s per hex stage (docs/results/structures.md).
        injective: untangle a folded least-squares map with the foldover-free solve (where the
            structure gate passed: a structure that fails it has no valid map, and its
            least-squares map is kept) and round a valid seamless map by injective moves
            (``False``: the plain least-squares map, greedy rounding and stiffening, as CubeCover).
        fit_weight, sd_weight: weights of the frame fitting and the symmetric Dirichlet barrier
            in the foldover-free solve (:mod:`.injective`).
        refine_limit: where the injective rounding cannot round every integer, the map is
            rounded again at half the edge length (the same seamless map scaled by 2: its
            singularities and features twice as far apart in integer units), at most
            ``refine_limit`` times; ``result.edge_length`` is then the edge length used
            (``stats["quantization"]["refined"]``: the factor).
        integrable: stage 2, the integrable frames (:mod:`.integrable`): the seamless map fits
            coframes made integrable by the torsion continuation instead of the rotation field
            (``stats["integrable"]``: the torsion and the coframes' inverted tets per round;
            ``gates["frames"]``); the map's ``energy*`` figures are then those of the coframe fit,
            ``|grad u B^-1 - I|^2``.
        batch_error, stiffening_iters, stiffening_factor: of the greedy rounding and the
            stiffening (:mod:`.quantize`), used when the seamless map is not valid.
        grid_bits: the snapping grid (module docstring).
        backend: sparse solver, ``"auto"`` / ``"cholmod"`` / ``"superlu"`` (:mod:`.solver`).
        progress: a progress bar on the rounding (tqdm).

    Returns:
        :class:`IntegerGridMap`, with each stage's :class:`~.validity.Gate`. It may be invalid
        (a stage failed): its gates say which one first, where and why.

    Raises:
        ValueError: frames of the wrong shape or not rotations, a field on another mesh, a
            non-positive edge length, parameters too large for the snapping grid.
    """
    if edge_length is not None and not (isinstance(edge_length, (int, float)) and np.isfinite(edge_length)
                                        and edge_length > 0):
        raise ValueError(f"edge_length must be a positive number, got {edge_length!r}")
    if not (isinstance(grid_bits, int) and 8 <= grid_bits <= 40):
        raise ValueError(f"grid_bits must be an integer in [8, 40], got {grid_bits!r}")
    if stiffening_iters < 0:
        raise ValueError(f"stiffening_iters must be >= 0, got {stiffening_iters}")
    if not (isinstance(refine_limit, int) and refine_limit >= 0):
        raise ValueError(f"refine_limit must be an integer >= 0, got {refine_limit!r}")
    if not (isinstance(flat_rounds, int) and flat_rounds >= 0):
        raise ValueError(f"flat_rounds must be an integer >= 0, got {flat_rounds!r}")
    timings = {}
    stats = {}

    # ------------------------------------------------------------------ 1. structure
    Fr = tet_frames_of(mesh, frames)
    h = default_edge_length(mesh) if edge_length is None else float(edge_length)
    st = map_structure(mesh, Fr, h, face_match=face_match, straighten=straighten,
                       straighten_boundary=straighten_boundary, touch_rounds=touch_rounds, repair=repair,
                       repair_rounds=repair_rounds, repair_slide=repair_slide, split=split, collapse=collapse,
                       features=features, feature_max_deg=feature_max_deg, flat_rounds=flat_rounds,
                       relocate=relocate, one_ring=one_ring, progress=progress)
    mesh, parent, charts, prob = st.mesh, st.parent_tet, st.charts, st.problem
    flat, mesh_report = st.flat, st.meshability
    timings.update(st.timings)
    gates = {"structure": st.gate}

    # ------------------------------------------------------------------ 2. frames
    targets = None
    map_frames = st.tet_frames
    if fixed_holonomy and st.gate.passed and st.face_match is not None:  # None: the frames' own matchings
        from ..frames.fixed_holonomy import fixed_holonomy_frames

        t0 = time.perf_counter()
        fh = fixed_holonomy_frames(mesh, st.tet_frames, st.face_match)
        if fh.free_tets:
            # the same charts (cut, transitions: the matchings), combed frames of the new field
            map_frames = fh.tet_frames.detach().cpu().double()
            combed = map_frames.numpy() @ group_matrices()[charts.comb].astype(np.float64)
            charts = replace(charts, frames=combed)
            prob = replace(prob, charts=charts).with_targets(np.transpose(combed, (0, 2, 1)) / h)
        stats["fixed_holonomy"] = {"free_tets": int(fh.free_tets), "passes": int(fh.passes), "agree": fh.agree,
                                   "misfit_deg_before": fh.misfit_deg_before, "misfit_deg_after": fh.misfit_deg_after}
        timings["fixed_holonomy_s"] = time.perf_counter() - t0
    if integrable:
        from .integrable import integrable_frames

        t0 = time.perf_counter()
        intf = integrable_frames(mesh, charts, prob, backend=backend)
        targets = intf.targets()
        prob = prob.with_targets(targets)
        stats["integrable"] = intf.summary()
        gates["frames"] = intf.gate()
        timings["integrable_s"] = time.perf_counter() - t0

    # ------------------------------------------------------------------ 3. seamless map
    t0 = time.perf_counter()
    from .injective import DET_SAFE, TetJacobians, minimize_barrier

    A, b, c = prob.energy_matrices()
    int_mask = prob.free_is_int
    vol_total = float(prob.vol.sum())
    y_ls = solve_fixed(A, b, np.zeros_like(int_mask), np.zeros(0), backend=backend)
    timings["seamless.least_squares_s"] = time.perf_counter() - t0
    e_cont = float(y_ls @ (A @ y_ls) - 2 * b @ y_ls + c) / vol_total
    jac = TetJacobians.of_problem(prob)
    det_ls = np.linalg.det(jac(y_ls))
    y_s = y_ls
    inj = None
    opened = np.ones(det_ls.size, bool)
    opened[flat] = False  # the flat tets stay flat whatever the map: left out of the untangling
    if injective and gates["structure"].passed and (det_ls[opened] <= DET_SAFE).any():
        # a structure that fails LMFF's conditions has no valid map: the least-squares map is kept, and
        # shows where it folds (untangling it could not change the verdict; it cost 3-20 s a field)
        inj = minimize_barrier(jac, y_ls, ignore=flat, w_fit=fit_weight, w_sd=sd_weight, backend=backend)
        y_s = inj.y
    _, uvw_s = snap(prob, y_s, None, grid_bits, h)
    seamless_validity = check_seamless(mesh, charts, uvw_s, prob)
    gates["seamless"] = Gate.of_validity("seamless", seamless_validity)
    e_seam = float(y_s @ (A @ y_s) - 2 * b @ y_s + c) / vol_total
    stats["seamless"] = {"inverted_least_squares": int((det_ls[opened] <= 0).sum()), "flat": int(flat.size),
                         "injective": None if inj is None else {
                             "inverted_after": inj.n_inverted, "rounds": inj.rounds, "iterations": inj.iterations,
                             "converged": inj.converged, "min_det": inj.min_det, "seconds": inj.seconds}}
    timings["seamless_s"] = time.perf_counter() - t0

    # ------------------------------------------------------------------ 4. quantization
    t0 = time.perf_counter()
    bar = None
    cb = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=int(int_mask.sum()), desc="rounding", unit="int", leave=False)

        def cb(done, total):
            bar.n = done
            bar.refresh()
    qstats = {"integers": int(int_mask.sum())}
    try:
        # a seamless map with no inverted tet (but the flat ones, which no map opens) is rounded injectively
        if injective and (np.linalg.det(jac(y_s))[opened] > 0).all():
            refine = 1
            y_start = y_s
            lsq_map = inj is None
            while True:
                # the least-squares re-solves are tried first when the map rounded is the least-squares one
                y, rinfo = round_injective(jac, y_start, int_mask, ignore=flat, w_fit=fit_weight, w_sd=sd_weight,
                                           backend=backend, progress=cb, lsq=(A, b) if lsq_map else None)
                if not rinfo["failed"] or refine >= 2 ** refine_limit:
                    break
                # no injective rounding at this size: the map at half the edge length is the same map
                # scaled by 2 (the constraints are homogeneous), whose entities are twice as far apart
                refine *= 2
                h_q = h / refine
                prob = build_problem(mesh, charts, h_q, features=features, feature_max_deg=feature_max_deg,
                                     targets=targets)
                jac = TetJacobians.of_problem(prob)
                A, b, c = prob.energy_matrices()
                y_start = y_s * refine
                lsq_map = False  # the shortcut at the first size only (the scaled map may be untangled again)
                if (np.linalg.det(jac(y_start))[opened] <= 0).any():
                    y_start = minimize_barrier(jac, y_start, ignore=flat, w_fit=fit_weight, w_sd=sd_weight,
                                               backend=backend).y
            if refine > 1:
                h = h_q
            qstats.update(method="injective", rounded=rinfo["rounded"], failed=len(rinfo["failed"]),
                          rounded_away=rinfo["rounded_away"], moves=rinfo["moves"],
                          max_rounding=rinfo["max_rounding"], refined=refine,
                          lsq_tries=rinfo["lsq_tries"], lsq_accepted=rinfo["lsq_accepted"])
            if rinfo["failed"]:
                # what could not be rounded without a fold is rounded anyway, the rest untangled as far
                # as it goes: the map's report says where it folds
                I = np.asarray(rinfo["failed"], np.int64)
                y[I] = np.round(y[I])
                t1 = time.perf_counter()
                y = minimize_barrier(jac, y, fixed=int_mask, ignore=flat, w_fit=fit_weight, w_sd=sd_weight,
                                     backend=backend).y
                timings["quantization.untangle_failed_s"] = time.perf_counter() - t1
        else:
            y, rinfo = round_greedy(A, b, int_mask, batch_error=batch_error, backend=backend, progress=cb,
                                    flips=lambda yy: int((param_volumes(prob.corner_params(yy)) <= 0).sum()))
            n_flip = int((param_volumes(prob.corner_params(y)) <= 0).sum())
            y, iters = stiffen(prob, y, int_mask, iters=stiffening_iters, factor=stiffening_factor, backend=backend)
            qstats.update(method="greedy", rounding_steps=rinfo["steps"], max_rounding=rinfo["max_rounding"],
                          undetermined_integers=rinfo["undetermined"], flipped_after_rounding=n_flip,
                          stiffening_iterations=iters)
    finally:
        if bar is not None:
            bar.close()
    timings["quantization_s"] = time.perf_counter() - t0

    # snapping to the dyadic grid: exact corner parameters and transitions
    ys, uvw = snap(prob, y, int_mask, grid_bits, h)
    energy = float(ys @ (A @ ys) - 2 * b @ ys + c) / vol_total
    face_shift = _face_shifts(mesh, charts, uvw)
    out = IntegerGridMap(mesh=mesh, parent_tet=parent, uvw=uvw, seamless_uvw=uvw_s, face_rot=charts.face_rot.copy(),
                         face_shift=face_shift, edge_length=h, charts=charts, energy=energy, energy_seamless=e_seam,
                         energy_continuous=e_cont, grid_bits=grid_bits, gates=gates, meshability=mesh_report,
                         stats=stats, problem=prob, tet_frames=map_frames)
    t0 = time.perf_counter()
    out.validity = check_map(mesh, out)
    gates["quantization"] = Gate.of_validity("quantization", out.validity, before=seamless_validity.valid)
    if qstats.get("refined", 1) > 1:
        gates["quantization"].counts["refined"] = qstats["refined"]
    timings["validity_s"] = time.perf_counter() - t0
    stats.update(prob.counts)
    stats.update(st.stats)
    stats["quantization"] = qstats
    stats["solver"] = backend
    stats["timings"] = timings
    return out


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
