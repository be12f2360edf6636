"""The structure stage of the map (:func:`~.igm.integer_grid_map`'s stage 1): the singular graph the map will follow.

:func:`map_structure` runs, on a ``TetMesh`` with one frame per tet:

1. the face matchings: given (``face_match=``, taken as they are), or the matching search
   (:func:`~.straighten.straighten_singular_edges`) followed by the repair of LMFF's conditions
   (:func:`~.repair.repair_singular_graph`, with ``repair=True``; its edge splits make the mesh
   finer, ``parent_tet`` composed);
2. the edge splits that keep singular and boundary curves apart (:func:`~.split.split_for_map`),
   then the singular arcs' vertices moved onto their turn axes (:func:`~.relocate.relocate_singular_vertices`,
   ``relocate=True``: LMFF's relocation as a solve over the vertex positions);
3. rounds of "build the seamless problem, find the tets its constraints flatten
   (:meth:`~.seamless.SeamlessProblem.flat_tets`), split an edge of every flat tet that is not
   collapsed" (:func:`~.split.open_flat_tets`);
4. LMFF's conditions on the result (:func:`~.meshability.meshability_report`), beside them
   LMFF's numeric one-ring test at every singular vertex (:func:`~.one_ring.one_ring_test`,
   ``one_ring=True``), and the structure gate (:func:`~.validity.structure_gate`), with what
   the repair did and left.

The map stage then fits the seamless map on ``Structure.problem``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .cut import TetCharts, tet_charts
from .seamless import FEATURE_MAX_DEG, SeamlessProblem, build_problem
from .validity import Gate, structure_gate

__all__ = ["Structure", "map_structure", "check_face_match"]


@dataclass
class Structure:
    """What :func:`map_structure` returns.

    Attributes:
        mesh: the ``TetMesh`` the map lives on (the input or its refinement: original vertices
            first, same coordinates); ``tet_frames (T, 3, 3)`` float64 its frames (a child tet
            has its parent's); ``parent_tet (T,)`` the input tet of each tet.
        face_match: ``(F,)`` the face matchings the map follows.
        charts: their :class:`~.cut.TetCharts`; problem: the :class:`~.seamless.SeamlessProblem`.
        flat, collapsed, line_face: :meth:`~.seamless.SeamlessProblem.flat_tets` of ``problem``.
        meshability: the :class:`~.meshability.Meshability` report; gate: the structure
            :class:`~.validity.Gate`.
        one_ring: the :class:`~.one_ring.OneRingReport` (``None`` when the test did not run).
        repair: the :class:`~.repair.RepairReport` (``None`` when the repair did not run).
        stats: ``splits``, ``straighten`` (the search's info), ``repair`` (the report's dict);
            timings: seconds per step.
    """

    mesh: object
    tet_frames: torch.Tensor
    parent_tet: np.ndarray
    face_match: np.ndarray
    charts: TetCharts
    problem: SeamlessProblem
    flat: np.ndarray
    collapsed: np.ndarray
    line_face: np.ndarray
    meshability: object
    gate: Gate
    repair: object | None = None
    one_ring: object | None = None
    stats: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)


def check_face_match(mesh, face_match) -> np.ndarray:
    """``face_match`` as ``(F,)`` int64 indices into the 24 elements of O, or a ``ValueError``
    naming what does not fit ``mesh``."""
    F = int(mesh.faces.shape[0])
    fm = np.asarray(face_match.detach().cpu() if isinstance(face_match, torch.Tensor) else face_match)
    if fm.shape != (F,):
        raise ValueError(f"face_match must have shape (F,) = ({F},) for this mesh (one matching per face), "
                         f"got {fm.shape}")
    if not np.issubdtype(fm.dtype, np.integer):
        raise ValueError(f"face_match must hold integers (indices into the 24 elements of O), got dtype {fm.dtype}")
    bad = np.nonzero((fm < 0) | (fm > 23))[0]
    if bad.size:
        raise ValueError(f"face_match must index the 24 elements of O: face {int(bad[0])} has {int(fm[bad[0]])} "
                         f"({bad.size} faces out of range)")
    return fm.astype(np.int64)


def _flat_keep_edges(mesh, charts: TetCharts, prob: SeamlessProblem) -> tuple[np.ndarray, np.ndarray]:
    """``(keep, line_keep)`` ``(E,)`` bool: edges whose midpoint would be constrained (boundary,
    singular, feature edges), and those whose midpoint would stay on their ends' line (singular
    and feature edges)."""
    line_keep = charts.singular_edge.copy()
    fe = prob.feature_edges
    if fe.shape[0]:
        eid, _ = mesh.edge_index(torch.as_tensor(fe[:, 0]), torch.as_tensor(fe[:, 1]))
        line_keep[eid.cpu().numpy()] = True
    keep = line_keep.copy()
    bfe = mesh.face_edges.cpu().numpy()[mesh.boundary_face_index.cpu().numpy()].reshape(-1)
    keep[bfe] = True
    return keep, line_keep


def map_structure(mesh, tet_frames, edge_length: float, *, face_match=None, straighten: bool = True,
                  straighten_boundary: bool = True, touch_rounds: int = 0, repair: bool = True,
                  repair_rounds: int = 30, repair_slide: bool = True, split: bool = True, collapse: bool = True,
                  features: bool = True, feature_max_deg: float = FEATURE_MAX_DEG,
                  flat_rounds: int = 8, relocate: bool = True, one_ring: bool = True,
                  progress: bool = False) -> Structure:
    """The structure stage (module docstring).

    Args:
        mesh: a ``TetMesh``; tet_frames: ``(T, 3, 3)`` rotations; edge_length: the hex edge length.
        face_match: ``(F,)`` matchings to follow as they are (no search, no repair).
        straighten, straighten_boundary, touch_rounds: the matching search
            (:func:`~.igm.integer_grid_map`).
        repair: after the search, repair LMFF's conditions (:func:`~.repair.repair_singular_graph`)
            with ``repair_rounds`` rounds at most; ``repair_slide``: its ``slide`` option (touching
            arc ends slid along the surface; on by default with ``feature_max_deg`` 15:
            :data:`~.seamless.FEATURE_MAX_DEG`).
        split, features, feature_max_deg, flat_rounds: as :func:`~.igm.integer_grid_map`.
        collapse: in the flat-tet rounds, collapse the tet edges that the constraints send to one
            point (:func:`~.collapse.collapse_edges`; refused where it would invert a tet or move
            a pinned vertex), before splitting the other flat tets.
        relocate: move the singular arcs' vertices onto their turn axes before the map
            (:func:`~.relocate.relocate_singular_vertices`, after the splits for the map: the
            charts and the constraints are those of the relocated mesh).
        one_ring: run LMFF's numeric one-ring test on the result (:func:`~.one_ring.one_ring_test`;
            reported in the gate's ``counts`` and ``info``, it does not decide the gate).
        progress: a progress bar over the repair's rounds.

    Returns:
        :class:`Structure`.
    """
    if not (isinstance(flat_rounds, int) and flat_rounds >= 0):
        raise ValueError(f"flat_rounds must be an integer >= 0, got {flat_rounds!r}")
    if not (isinstance(repair_rounds, int) and repair_rounds >= 0):
        raise ValueError(f"repair_rounds must be an integer >= 0, got {repair_rounds!r}")
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    h = float(edge_length)
    timings, sinfo, rep = {}, {}, None
    parent = np.arange(mesh.n_tets)
    t0 = time.perf_counter()
    if face_match is not None:
        face_match = check_face_match(mesh, face_match)
        sinfo = {"given": True}
    elif straighten:
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
    if repair and not sinfo.get("given"):  # (without the search: from the best matchings)
        from .repair import repair_singular_graph

        t0 = time.perf_counter()
        face_match, rep = repair_singular_graph(mesh, Fr, face_match, max_rounds=repair_rounds, slide=repair_slide,
                                                features=features, progress=progress)
        mesh, Fr = rep.mesh, rep.tet_frames
        parent = parent[rep.parent_tet]
        timings["repair_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    splits = {}
    if split:
        from .split import split_for_map

        sr = split_for_map(mesh, Fr, face_match)
        mesh, Fr, splits, face_match = sr.mesh, sr.tet_frames, dict(sr.splits), sr.face_match
        parent = parent[sr.parent_tet]
    timings["split_s"] = time.perf_counter() - t0
    reloc = None
    if relocate:
        from .relocate import relocate_singular_vertices

        t0 = time.perf_counter()
        mesh, reloc = relocate_singular_vertices(mesh, tet_charts(mesh, Fr, face_match))
        timings["relocate_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    splits["flat"] = 0
    sub = {"charts": 0.0, "problem": 0.0, "flat": 0.0}
    for rnd in range(flat_rounds + 1):
        t1 = time.perf_counter()
        charts = tet_charts(mesh, Fr, face_match)
        t2 = time.perf_counter()
        prob = build_problem(mesh, charts, h, features=features, feature_max_deg=feature_max_deg)
        t3 = time.perf_counter()
        flat, collapsed, line_face = prob.flat_tets()
        sub["charts"] += t2 - t1
        sub["problem"] += t3 - t2
        sub["flat"] += time.perf_counter() - t3
        if rnd == flat_rounds or not split:
            break
        if collapse and collapsed.any():
            from .collapse import collapse_edges
            from .cut import face_matchings

            if face_match is None:
                face_match = face_matchings(mesh, Fr)
            pairs = _collapsed_pairs(mesh, charts, prob, flat[collapsed])
            mesh, Fr, par, face_match, n = collapse_edges(mesh, Fr, pairs, face_match)
            parent = parent[par]
            splits["collapsed"] = splits.get("collapsed", 0) + n["collapsed"]
            splits["collapse_refused"] = splits.get("collapse_refused", 0) + n["refused"]
            if n["collapsed"]:
                continue  # the charts and the problem of the new mesh
        if not (~collapsed).any():
            break
        from .split import open_flat_tets

        keep, line_keep = _flat_keep_edges(mesh, charts, prob)
        mesh, Fr, par, face_match, n = open_flat_tets(mesh, Fr, flat[~collapsed], line_face[~collapsed], face_match,
                                                      keep, line_keep)
        parent = parent[par]
        splits["flat"] += n["edge"]
        splits["flat_centroid"] = splits.get("flat_centroid", 0) + n["centroid"]
    timings["charts_and_constraints_s"] = time.perf_counter() - t0
    timings.update({f"charts_and_constraints.{k}_s": v for k, v in sub.items()})
    from .meshability import meshability_report

    t0 = time.perf_counter()
    report = meshability_report(mesh, charts.frames, charts=charts)
    timings["meshability_s"] = time.perf_counter() - t0
    ring = None
    if one_ring:
        from .one_ring import one_ring_test

        t0 = time.perf_counter()
        ring = one_ring_test(mesh, None, charts=charts, meshability=report, edge_length=h, features=features,
                             feature_max_deg=feature_max_deg)
        timings["one_ring_s"] = time.perf_counter() - t0
    gate = structure_gate(mesh, report, flat, collapsed, one_ring=ring)
    if rep is not None:
        gate.counts["repair_moves"] = int(sum(rep.moves.values()))
        if not gate.passed:
            gate.reasons.append(_repair_sentence(rep))
    stats = {"splits": splits, "straighten": sinfo}
    if rep is not None:
        stats["repair"] = rep.as_dict()
    if reloc is not None:
        stats["relocation"] = reloc.as_dict()
    return Structure(mesh=mesh, tet_frames=Fr, parent_tet=parent, face_match=face_match, charts=charts, problem=prob,
                     flat=flat, collapsed=collapsed, line_face=line_face, meshability=report, gate=gate, repair=rep,
                     one_ring=ring, stats=stats, timings=timings)


def _collapsed_pairs(mesh, charts: TetCharts, prob: SeamlessProblem, tets: np.ndarray, seed: int = 0) -> np.ndarray:
    """``(k, 2)`` the vertex pairs of the collapsed tets ``tets`` that the constraints send to one
    point (equal corner parameters at random integer unknowns, as
    :meth:`~.seamless.SeamlessProblem.flat_tets` decides; two samples). Pairs at a vertex of a
    complex singular edge are left out: no collapse may hide an unmeshable singularity."""
    from ..frames.singular import FACE_TYPES

    rng = np.random.default_rng(seed)
    T = mesh.tets.cpu().numpy()[tets]
    pa, pb = np.array([0, 0, 0, 1, 1, 2]), np.array([1, 2, 3, 2, 3, 3])
    same = np.ones((tets.size, 6), bool)
    for _ in range(2):
        uvw = prob.corner_params(rng.integers(-1024, 1025, size=prob.elim.free.size).astype(np.float64))[tets]
        same &= (uvw[:, pa] == uvw[:, pb]).all(-1)
    t, k = np.nonzero(same)
    pairs = np.sort(np.stack([T[t, pa[k]], T[t, pb[k]]], 1), axis=1)
    cx = np.zeros(mesh.n_vertices, bool)
    cx[mesh.edges.cpu().numpy()[charts.edge_type == FACE_TYPES.index("complex")].reshape(-1)] = True
    pairs = pairs[~(cx[pairs[:, 0]] | cx[pairs[:, 1]])]
    return np.unique(pairs, axis=0)


def _repair_sentence(rep) -> str:
    """What the repair did and left, in one sentence (for the structure gate's reasons)."""
    moves = sum(rep.moves.values())
    left = {k: rep.after[k] for k in ("complex_edges", "zipper_nodes", "invalid_nodes", "surface_valence2_edges",
                                      "touching_edges") if rep.after.get(k)}
    what = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in left.items()) or "none of LMFF's conditions"
    return (f"the repair made {moves} moves in {rep.rounds} rounds ({rep.stopped}) and left {what} "
            f"(before: {rep.before['zipper_nodes']} zipper, {rep.before['invalid_nodes']} invalid nodes)")
