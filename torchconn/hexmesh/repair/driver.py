"""The iterated repair of the singular graph: rounds of one-ring moves until LMFF's conditions are gone.

:func:`repair_singular_graph` is the structure stage the map stage runs between the matching
search (:func:`~torchconn.hexmesh.straighten.straighten_singular_edges`) and the edge splits
(:func:`~torchconn.hexmesh.split.split_for_map`): each round visits the vertices the repair works
on (:meth:`.graph.SingularGraph.bad_vertices`, worst first), makes at each the cone move that
lowers the cost most (:func:`.ops.best_move`) or, at a vertex with a condition where no single
move does, a chain of moves (:func:`chain_move`); a vertex that found no move is not tried again
until a move changes its neighbourhood. When a round makes no move, the constrained edges
around the stuck vertices are split (:func:`room_edges`, at most ``split_passes`` times, and again
only when the rounds after the last split made a move) and the rounds go on; after a split a
vertex that had found no move is tried again only when a split edge is within two rings of it.
It stops when no vertex is left, when a round makes no move and no split helps,
or after ``max_rounds`` rounds (the budget: LMFF runs about a hundred rounds of
repair and relocation; a round here costs about one candidate evaluation per pair of special
edges, product and path at every bad vertex). The cost falls at every move, so the rounds
terminate. The frames are not changed: the re-optimization with the matchings fixed is
:func:`torchconn.frames.fixed_holonomy.fixed_holonomy_frames`.
"""
from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import torch

from .disk import MeshLookup
from .graph import SingularGraph
from .ops import MOVE_KINDS, best_move, candidate_moves

__all__ = ["RepairReport", "repair_singular_graph", "chain_move"]


@dataclass
class RepairReport:
    """What :func:`repair_singular_graph` did.

    Attributes:
        before, after: condition counts (:meth:`.graph.SingularGraph.counts`) before and after.
        cost_before, cost_after: :meth:`.graph.SingularGraph.cost`.
        rounds: rounds run; ``stopped``: why the rounds ended (``"meshable"`` no vertex left to
            work on, ``"no_move"`` a round without a move, ``"budget"`` ``max_rounds`` spent).
        moves: per kind (:data:`.ops.MOVE_KINDS`), the moves made.
        faces_changed: faces whose matching differs from the input; ``misfit_added_rad``: the
            summed rotation (radians) by which those matchings now depart from the best ones,
            minus what the input's did.
        left: per vertex still worked on, its class and position (``{"vertex", "class", "boundary"}``),
            at most 50.
        splits: edges split to make room around stuck vertices (:func:`room_edges`).
        mesh, tet_frames, parent_tet: the mesh the returned matchings live on (the input mesh
            unless edges were split: then its refinement, original vertices first with their
            coordinates, each child tet with its parent's frame, ``parent_tet (T',)``); and
            ``seconds``, the wall time.
    """

    before: dict
    after: dict
    cost_before: float
    cost_after: float
    rounds: int
    stopped: str
    moves: dict = field(default_factory=dict)
    faces_changed: int = 0
    misfit_added_rad: float = 0.0
    left: list = field(default_factory=list)
    splits: int = 0
    mesh: object = field(default=None, repr=False)
    tet_frames: object = field(default=None, repr=False)
    parent_tet: object = field(default=None, repr=False)
    seconds: float = 0.0

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"before": self.before, "after": self.after, "cost_before": self.cost_before,
                "cost_after": self.cost_after, "rounds": self.rounds, "stopped": self.stopped,
                "moves": dict(self.moves), "faces_changed": self.faces_changed,
                "misfit_added_rad": self.misfit_added_rad, "left": self.left, "splits": self.splits,
                "seconds": self.seconds}


def room_edges(g: SingularGraph, lookup: MeshLookup, vs: np.ndarray) -> np.ndarray:
    """``(K, 2)`` vertex pairs of the interior edges in the stars of the vertices ``vs`` whose two
    ends are constrained (on the boundary or on the singular graph): splitting them puts free
    vertices into the one-rings, so that a cone has a way around (AlgoHex splits a vertex's
    one-ring before it detaches an arc there). Splits keep every walk product (:mod:`..split`)."""
    special_v = np.zeros(g.V, bool)
    special_v[g.edges[g.cls >= 0].reshape(-1)] = True  # the singular edges themselves are not split
    con = g.on_b | special_v
    out = []
    for v in np.asarray(vs, np.int64).tolist():  # loop over the stuck vertices (a few dozen)
        fs = lookup.vertex_faces(v)
        es = np.unique(lookup.face_edges[fs])
        es = es[~g.boundary[es]]
        a, b = g.edges[es, 0], g.edges[es, 1]
        out.append(g.edges[es[con[a] & con[b] & (g.cls[es] < 0)]])
    return np.unique(np.concatenate(out), axis=0) if out else np.zeros((0, 2), np.int64)


def chain_move(g: SingularGraph, lookup: MeshLookup, v: int, depth: int = 8, kinds=None, width: int = 3,
               branch: int = 4) -> list:
    """A chain of cone moves from ``v`` that lowers the cost though its first moves may raise it.

    A beam search: each partial chain continues at one of two bad vertices its last move made
    (the zipper tip or the pushed curve's new end, conditions first) with the ``branch`` cheapest moves
    there (of ``kinds``, :data:`.ops.MOVE_KINDS`; default all); the ``width`` partial chains of
    lowest summed cost change (one per singular graph they make) are kept, up to ``depth`` moves. The chain with the lowest summed
    change is made on ``g`` if that change is negative. A chain changes every face at most once
    (no move undoes an earlier one). Returns the moves made.

    This is how a tip travels: zipping a hairpin or pushing a curve off the boundary one vertex
    at a time leaves the conditions' count unchanged until the last move, which removes them.
    """
    beams = [([], 0.0, int(v))]
    best_total, best_moves = -1e-9, []
    seen = set()
    for _ in range(depth):
        grown = []
        for moves, total, cur in beams:
            tokens = [g.set_matchings(m.faces, m.values) for m in moves]
            touched = np.zeros(g.match.size, bool)
            for m in moves:
                touched[m.faces] = True
            visited = {int(v)} | {m.vertex for m in moves}
            cands = sorted((c for c in candidate_moves(g, lookup, cur, kinds) if not touched[c.faces].any()),
                           key=lambda c: c.delta)[:branch]
            for c in cands:
                tok = g.set_matchings(c.faces, c.values)
                t = total + c.delta
                if t < best_total:
                    best_total, best_moves = t, moves + [c]
                vs = np.unique(g.edges[np.unique(g.face_edges[c.faces])])
                bad = g.bad_vertices_mask()
                nxt = [int(x) for x in vs if bad[x] and int(x) not in visited]
                es = np.unique(np.concatenate([g.face_edges[m.faces].reshape(-1) for m in moves + [c]]))
                key = (tuple(es.tolist()), tuple(g.cls[es].tolist()))  # partial chains with one graph: keep one
                g.undo(tok)
                if nxt and key not in seen:
                    seen.add(key)
                    nxt.sort(key=lambda x: -g.vertex_cost(np.array([x]))[0])
                    grown += [(moves + [c], t, x) for x in nxt[:2]]
            for tok in reversed(tokens):
                g.undo(tok)
        if not grown:
            break
        grown.sort(key=lambda b: b[1])
        beams = grown[:width]
    for m in best_moves:
        g.set_matchings(m.faces, m.values)
    return best_moves


def repair_singular_graph(mesh, tet_frames, face_match: np.ndarray | None = None, *, max_rounds: int = 30,
                          chain_depth: int = 8, split_passes: int = 3, slide: bool = False, weights: dict | None = None, features: bool = True, progress: bool = False
                          ) -> tuple[np.ndarray, RepairReport]:
    """Repair the face matchings so that the edge-based singular graph meets LMFF's conditions.

    Args:
        mesh: a ``TetMesh``; tet_frames: ``(T, 3, 3)`` rotations (axes as columns).
        face_match: ``(F,)`` starting matchings (default the best ones).
        max_rounds: the budget of rounds (module docstring).
        chain_depth: where no single move lowers the cost, a chain of up to this many moves
            (:func:`chain_move`; 0: single moves only).
        split_passes: when a round makes no move, split the constrained edges around the stuck
            vertices (:func:`room_edges`) and go on, at most this many times and only while the
            last split led to a move (0: never split; then the returned matchings are on the
            input mesh).
        slide: also slide the ends of arcs that touch the boundary about a tangent axis along
            the surface (:func:`.ops.slide_moves`: single moves at touching ends, and within the
            chains that start at a condition; no chain starts at a touching end — on the 35 HexMe
            ``c`` models those chains took 14% of the jobs' time, 2,667 s against 2,295 s, and
            changed no verdict, docs/results/hexmesh.md). On the 17 simple HexMe models (SH
            fields) it leaves 9 touching edges instead of 19 and no zipper node instead of 1, and
            the repair takes about twice as long (docs/results/structures.md). Alone it made no map
            valid; with feature edges constrained only within 15 degrees of an axis it does (s13c):
            the map stage turns it on (``repair_slide``,
            :data:`~torchconn.hexmesh.seamless.FEATURE_MAX_DEG`).
        weights: overrides of :data:`.graph.REPAIR_WEIGHTS`.
        features: take sharp features from the mesh.
        progress: a tqdm bar over the rounds.

    Returns:
        ``(face_match, RepairReport)``: the matchings live on ``report.mesh`` (the input mesh, or
        its refinement when edges were split; ``report.tet_frames`` and ``report.parent_tet``).

    Raises:
        ValueError: frames or matchings that do not fit the mesh, unknown weights.
    """
    if not (isinstance(max_rounds, int) and max_rounds >= 0):
        raise ValueError(f"max_rounds must be an integer >= 0, got {max_rounds!r}")
    t0 = time.perf_counter()
    g = SingularGraph(mesh, tet_frames, face_match, weights=weights, features=features)
    start = g.match.copy()
    lookup = MeshLookup(mesh)
    before, cost0 = g.counts(), g.cost()
    moves = Counter()
    parent = np.arange(mesh.n_tets)
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_rounds, desc="repair", unit="round", leave=False)
    stopped, r, n_split, passes, since_split = "budget", 0, 0, 0, 0
    clock, stamp, failed = 1, np.ones(g.V, np.int64), np.zeros(g.V, np.int64)
    kinds = None if slide else tuple(k for k in MOVE_KINDS if k != "slide_end")
    try:
        while r < max_rounds:
            r += 1
            bad = g.bad_vertices()
            if not bad.size:
                stopped, r = "meshable", r - 1
                break
            order = bad[np.argsort(-g.vertex_cost(bad), kind="stable")]
            made, stuck = 0, []
            for v in order.tolist():  # loop over the bad vertices of this round (a few hundred at most)
                if not g.bad_vertices_mask()[v]:
                    continue
                if failed[v] >= stamp[v]:  # nothing changed near v since it found no move
                    stuck.append(v)
                    continue
                mv = best_move(g, lookup, v, kinds)
                if mv is not None:
                    g.set_matchings(mv.faces, mv.values)
                    kept = [mv]
                elif chain_depth > 0 and g.vertex_cost(np.array([v]))[0] > 0:
                    kept = chain_move(g, lookup, v, chain_depth, kinds)  # chains start at conditions only
                else:
                    kept = []
                for mv in kept:
                    moves[mv.kind] += 1
                    clock += 1
                    near = np.unique(g.edges[np.unique(g.face_edges[mv.faces])])
                    near = np.unique(np.concatenate([g.edges[lookup.vertex_edges(int(x))].reshape(-1) for x in near]))
                    stamp[near] = clock
                made += len(kept)
                since_split += len(kept)
                if not kept:
                    failed[v] = clock
                    stuck.append(v)
            if bar is not None:
                c = g.counts()
                bar.update(1)
                bar.set_postfix(zipper=c["zipper_nodes"], invalid=c["invalid_nodes"], moves=made)
            if not made:
                # another split pass only when the last one led to a move (a pass that made room
                # for none is not repeated around the same stuck vertices)
                more = passes < split_passes and (passes == 0 or since_split > 0)
                pairs = room_edges(g, lookup, np.asarray(stuck, np.int64)) if more else np.zeros((0, 2))
                if not len(pairs):
                    stopped = "no_move"
                    break
                from ..split import split_pairs

                _, _, _, start = split_pairs(mesh, Fr, pairs, start)  # the input's matchings, carried
                mesh, Fr, par, fm = split_pairs(mesh, Fr, pairs, g.match)
                parent = parent[par]
                n_split += int(len(pairs))
                passes, since_split = passes + 1, 0
                g = SingularGraph(mesh, Fr, fm, weights=weights, features=features)
                lookup = MeshLookup(mesh)
                # the split keeps the old vertices' indices and appends the midpoints: a vertex
                # that found no move keeps that verdict unless a split edge is in its two rings
                # (the rule by which a move re-opens its neighbours, above)
                clock += 1
                V_old = stamp.size
                near = np.unique(np.concatenate([np.asarray(pairs, np.int64).reshape(-1), np.arange(V_old, g.V)]))
                for _ in range(2):  # loop over the two rings
                    near = np.unique(g.edges[np.isin(g.edges, near).any(1)].reshape(-1))
                stamp = np.concatenate([stamp, np.zeros(g.V - V_old, np.int64)])
                failed = np.concatenate([failed, np.zeros(g.V - V_old, np.int64)])
                stamp[near] = clock
    finally:
        if bar is not None:
            bar.close()
    changed = np.nonzero(g.match != start)[0]
    mis = float((g.misfit_tab[changed, g.match[changed]] - g.misfit_tab[changed, start[changed]]).sum())
    left = [{"vertex": int(v), "class": ["regular", "arc", "node", "zipper", "invalid", "complex"][int(g.vcls[v])],
             "boundary": bool(g.on_b[v])} for v in g.bad_vertices()[:50]]
    report = RepairReport(before=before, after=g.counts(), cost_before=cost0, cost_after=g.cost(), rounds=r,
                          stopped=stopped, moves=dict(moves), faces_changed=int(changed.size), misfit_added_rad=mis,
                          left=left, splits=n_split, mesh=mesh, tet_frames=Fr, parent_tet=parent,
                          seconds=time.perf_counter() - t0)
    return g.match.copy(), report

