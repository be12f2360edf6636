"""The repair operations of the singular graph: one-ring moves at a vertex, chosen by the cost.

Every operation is a cone move (:func:`.disk.cone_disk`) at a vertex ``v``: two special edges
``e1 = (v, a)`` and ``e2 = (v, b)`` at ``v`` (interior singular edges, boundary edges whose fan
angle is not flat or not their feature's), a path ``a -> b`` in the link of ``v``, and the
matchings of the cone's faces re-solved (:func:`.disk.solve_disk`) so that ``e1`` takes a chosen
product (interior: the identity; boundary: a fan transport whose angle is the one the geometry
asks for) while the spokes inside the cone keep theirs. When ``e1`` and ``e2`` carry one arc
through ``v`` the arc now runs ``a -> p_1 -> ... -> b`` around ``v``; otherwise the move makes
other edges singular and the cost says so. Candidates: every ordered pair, every admissible
product of ``e1``, and up to four paths (the shortest, and the shortest around the first one's
inside, for each weighting of :data:`PATH_MODES`). The move kept is the one that lowers :meth:`.graph.SingularGraph.cost` the most.

The kinds (LMFF's repair operations, Liu & Bommes 2023, as AlgoHex names them), by the vertex
and the edges moved:

* ``push_inside``: a singular curve lying on a smooth part of the boundary (boundary edges
  with a convex or concave fan, ``crease``), pushed off it into the interior, one vertex at a
  time: LMFF's "push singular vertices on the boundary into the interior";
* ``move_off``: an arc touching the boundary (both edges interior, ``v`` on the boundary)
  detached from ``v``: LMFF's "arcs touching feature faces tangentially";
* ``slide_end``: an arc that ends at a boundary vertex about a tangent axis (a touching end:
  on a curved face, or on a feature curve whose other face is tangent to the axis) slides its
  end one ring along the surface (:func:`slide_moves`), chains of slides several rings, to
  where the axis is the surface normal: LMFF's "arcs touching feature faces tangentially" for
  an arc's end;
* ``detach``: an arc detached from an invalid interior node (the dual-path search for an
  anti-parallel partner arc at the node is the search over pairs and paths here);
* ``zip``: at a zipper node (an arc doubling back), the tip moved across the cone, which
  shortens the hairpin and merges zipper pairs (a cone move at a tip whose two branches are
  one edge apart zips them);
* ``feature_sector``: a boundary fan whose angle is not its sharp feature's (a constrained
  feature sector) given the angle the feature asks for;
* ``retract``: a hook, a zipper node one of whose branches reaches the boundary within a few
  edges, retracted through the boundary (:func:`retract_moves`): the arc's end moves from the
  short branch's boundary vertex to a boundary vertex next to the long branch, over the
  least-area disk (:func:`.disk.spanning_disk`) between the old arc, the new end edge and a
  path on the boundary (whose fans turn about their normal, when that is the arc's axis, and
  stay flat).

Each public function takes a mesh, per-tet frames and matchings and returns the new matchings
and a :class:`Move` (or ``None`` when no move lowers the cost); the driver
(:func:`.driver.repair_singular_graph`) calls :func:`best_move` on its state.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..meshability import INVALID, ZIPPER, boundary_edge_quarters
from .disk import MeshLookup, cone_disk, link_path, solve_disk, spanning_disk
from .graph import _AXIS, SingularGraph

__all__ = ["Move", "MOVE_KINDS", "best_move", "special_edges", "candidate_moves", "retract_moves", "slide_moves",
           "touching_ends", "push_inside", "move_off_boundary", "slide_touching_end", "detach_arc", "zip_zipper", "retract_hook", "repair_feature_sector"]

PATH_MODES = ("aligned", "monotone")
"""Weightings of :func:`.disk.link_path` the candidates are drawn with."""

MOVE_KINDS = ("push_inside", "move_off", "slide_end", "detach", "zip", "retract", "feature_sector", "other")
"""Kinds of :class:`Move` (module docstring)."""


@dataclass
class Move:
    """A cone move: ``vertex``, the two edges ``edges = (e1, e2)``, the link ``path``, the cone's
    ``faces`` and their new matchings ``values``, the cost change ``delta`` (negative: better),
    the ``kind`` (:data:`MOVE_KINDS`) and the condition counts ``before``/``after`` at its vertices."""

    vertex: int
    edges: tuple
    path: np.ndarray
    faces: np.ndarray
    values: np.ndarray
    delta: float
    kind: str = "other"
    info: dict = field(default_factory=dict)


def special_edges(g: SingularGraph, lookup: MeshLookup, v: int) -> np.ndarray:
    """Edges at ``v`` that carry the singular graph: interior singular edges, boundary edges with
    a non-flat fan off sharp features, sharp boundary edges whose fan angle is not the feature's."""
    es = lookup.vertex_edges(v)
    c = g.cls[es]
    q = boundary_edge_quarters(c)
    mism = g.boundary[es] & g.sharp[es] & (q != g.expected[es])
    return es[(c >= 0) | mism]


def _targets(g: SingularGraph, e: int) -> list[int]:
    """Products the seed edge ``e`` may take: the identity (interior), or the fan transports
    whose angle is the one the geometry asks for (boundary; at most 4)."""
    if not g.boundary[e]:
        return [0]
    q = g.fan_q[g.bpos[e]]  # (24,): q for every transport, the fan's angle as the estimate
    want = g.expected[e]
    return [int(P) for P in np.nonzero(q == want)[0] if P != g.prod[e]][:4]


def _kind(g: SingularGraph, v: int, e1: int, e2: int) -> str:
    b1, b2 = g.boundary[e1], g.boundary[e2]
    if (b1 and g.sharp[e1]) or (b2 and g.sharp[e2]):
        return "feature_sector"
    if b1 or b2:
        return "push_inside"
    if g.on_b[v]:
        return "move_off"
    if g.vcls[v] == ZIPPER:
        return "zip"
    if g.vcls[v] == INVALID:
        return "detach"
    return "other"


def _link_paths(g: SingularGraph, lookup: MeshLookup, v: int, a: int, b: int, axis, n_paths: int,
                modes=PATH_MODES) -> list:
    """Link paths ``a -> b`` around ``v`` (:func:`.disk.link_path`): per weighting of ``modes``
    the shortest and, with ``n_paths > 1``, the shortest around its inside."""
    paths = []
    for mode in modes:
        p = link_path(g, lookup, v, a, b, axis, mode=mode)
        if p is not None:
            paths.append(p)
            if n_paths > 1 and p.size > 2:
                q = link_path(g, lookup, v, a, b, axis, blocked=p[1:-1], mode=mode)
                if q is not None:
                    paths.append(q)
    return paths


def _try_disk(g: SingularGraph, faces, seed: int, e1: int, target: int, inside, seen: set):
    """Re-solve the disk ``faces`` so that ``e1`` takes ``target`` (:func:`.disk.solve_disk`), try it
    on ``g`` and undo it: ``(values, cost change)``, or ``None`` when there is no new solution or
    it makes a singular graph already in ``seen`` (which it joins)."""
    vals = solve_disk(g, faces, seed, e1, target, inside)
    if vals is None or (vals == g.match[faces]).all():
        return None
    before = g.local_cost(faces)
    token = g.set_matchings(faces, vals)
    after = g.local_cost(faces)
    es = np.unique(g.face_edges[faces])
    key = (tuple(es.tolist()), tuple(g.prod[es].tolist()))  # the same singular graph
    g.undo(token)
    if key in seen:
        return None
    seen.add(key)
    return vals, after - before


def candidate_moves(g: SingularGraph, lookup: MeshLookup, v: int, kinds=None, n_paths: int = 2):
    """Every cone move at ``v`` and, at a zipper node, every ``retract`` move (module docstring)
    with its cost change, as :class:`Move` s."""
    if g.vcls[v] == ZIPPER and (kinds is None or "retract" in kinds):
        yield from retract_moves(g, lookup, v)
    if g.on_b[v] and (kinds is None or "slide_end" in kinds):
        yield from slide_moves(g, lookup, v, n_paths)
    sp_e = special_edges(g, lookup, v)
    seen = set()  # the pair (e2, e1) over the reversed path often makes the same singular graph
    for e1 in sp_e.tolist():
        for e2 in sp_e.tolist():
            if e1 == e2:
                continue
            kind = _kind(g, v, e1, e2)
            if kinds is not None and kind not in kinds:
                continue
            a, b = lookup.other_end(e1, v), lookup.other_end(e2, v)
            axis = None
            if not g.boundary[e1]:
                k = _AXIS[g.prod[e1]]
                if k >= 0:
                    axis = g.frames[g.walks.start[e1]][:, k]
            paths = _link_paths(g, lookup, v, a, b, axis, n_paths, PATH_MODES if axis is not None else PATH_MODES[:1])
            kept = set()  # paths found twice (two weightings) tried once
            paths = [p for p in paths if not (tuple(p.tolist()) in kept or kept.add(tuple(p.tolist())))]
            for path in paths:
                cone = cone_disk(lookup, v, path)
                if cone is None:
                    continue
                faces, inside, _ = cone
                for target in _targets(g, e1):
                    tried = _try_disk(g, faces, int(faces[0]), e1, target, inside, seen)
                    if tried is not None:
                        yield Move(vertex=int(v), edges=(int(e1), int(e2)), path=path, faces=faces, values=tried[0],
                                   delta=tried[1], kind=kind)


def touching_ends(g: SingularGraph, lookup: MeshLookup, v: int) -> np.ndarray:
    """Interior singular edges at the boundary vertex ``v`` that touch the boundary there about a
    tangent axis (their turn axis more than 45° from the normal of a boundary face at ``v``:
    :func:`~torchconn.hexmesh.meshability.tangent_axes`)."""
    es = lookup.vertex_edges(v)
    es = es[~g.boundary[es] & (g.cls[es] >= 0) & (g.cls[es] != 4)]
    return es[g.tang[es, np.maximum(_AXIS[g.prod[es]], 0)]]


def slide_moves(g: SingularGraph, lookup: MeshLookup, v: int, n_paths: int = 2):
    """The ``slide_end`` moves at a boundary vertex ``v`` where an arc ends touching the boundary
    about a tangent axis, as :class:`Move` s.

    The arc ``.. a - v`` ends at ``v`` and nothing else is to repair there (an arc passing
    through ``v`` is ``move_off``'s; a singular curve on the boundary at ``v``, or a feature
    fan of the wrong angle, is ``push_inside``'s or ``feature_sector``'s first: slides there
    lead the rounds to worse states, measured on s13c). For each boundary edge ``e2 = (v, w)`` and link path ``a -> w``
    (:func:`.disk.link_path`, the arc's axis), the cone over the path is re-solved with
    ``e1 = (v, a)`` regular: the arc now runs ``a - p_1 - .. - w`` and ends at ``w``, one ring
    along the surface; the fan of ``e2`` turns by the arc's rotation, which keeps it flat where
    the arc's axis is the surface normal there. Chains of slides (:func:`.driver.chain_move`)
    carry the end over several rings to where the axis is the normal.
    """
    e1s = touching_ends(g, lookup, v)
    if not e1s.size:
        return
    es = lookup.vertex_edges(v)
    c = g.cls[es]
    q = boundary_edge_quarters(c)
    bnd = g.boundary[es]
    other = (~bnd & (c >= 0)).sum() > 1 or (bnd & ~g.sharp[es] & (q != 2)).any() or \
        (bnd & g.sharp[es] & (q != g.expected[es])).any()
    if other:  # an arc through v, or a curve on the boundary (or a feature's fan) still to repair there
        return
    e1 = int(e1s[0])
    a = lookup.other_end(e1, v)
    k = _AXIS[g.prod[e1]]
    axis = g.frames[g.walks.start[e1]][:, max(int(k), 0)]
    seen = set()
    for e2 in es[g.boundary[es]].tolist():
        w = lookup.other_end(e2, v)
        for path in _link_paths(g, lookup, v, a, w, axis, n_paths):
            cone = cone_disk(lookup, v, path)
            if cone is None:
                continue
            faces, inside, _ = cone
            tried = _try_disk(g, faces, int(faces[0]), e1, 0, inside, seen)
            if tried is not None:
                yield Move(vertex=int(v), edges=(e1, int(e2)), path=path, faces=faces, values=tried[0],
                           delta=tried[1], kind="slide_end")


def _branch(g: SingularGraph, lookup: MeshLookup, v: int, e: int, max_len: int) -> list[int]:
    """The vertices of the singular arc from ``v`` through edge ``e``, followed through vertices
    with exactly two interior singular edges, until another vertex (included) or ``max_len`` edges."""
    out, prev = [int(v)], int(e)
    while len(out) <= max_len:
        x = lookup.other_end(prev, out[-1])
        out.append(x)
        es = lookup.vertex_edges(x)
        es = es[~g.boundary[es] & (g.cls[es] >= 0) & (es != prev)]
        if g.on_b[x] or es.size != 1 or x == v:
            break
        prev = int(es[0])
    return out


def _boundary_path(g: SingularGraph, lookup: MeshLookup, a: int, b: int, near: np.ndarray) -> np.ndarray | None:
    """A shortest path ``a -> b`` over boundary edges between vertices of ``near`` (bool (V,))."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    be = lookup.edges[g.boundary & near[lookup.edges].all(1)]
    nodes = np.unique(np.r_[be.reshape(-1), a, b])
    loc = np.searchsorted(nodes, be)
    w = np.linalg.norm(g.X[be[:, 0]] - g.X[be[:, 1]], axis=1)
    A = sp.coo_matrix((w, (loc[:, 0], loc[:, 1])), shape=(nodes.size, nodes.size)).tocsr()
    ia, ib = int(np.searchsorted(nodes, a)), int(np.searchsorted(nodes, b))
    dist, pred = dijkstra(A, directed=False, indices=ia, return_predecessors=True)
    if not np.isfinite(dist[ib]):
        return None
    out = [ib]
    while out[-1] != ia:
        out.append(int(pred[out[-1]]))
    return nodes[np.array(out[::-1])]


def retract_moves(g: SingularGraph, lookup: MeshLookup, v: int, max_len: int = 4):
    """The ``retract`` moves at a zipper node ``v`` (module docstring), as :class:`Move` s.

    For a branch ``v = s_0, ..., s_k`` that reaches the boundary within ``max_len`` edges and the
    other branch ``v, c_1, c_2, ...``: for each ``c_j`` (``j <= k + 2``) and each boundary
    neighbour ``b`` of ``c_j`` (up to 3, nearest first), the loop ``s_k .. s_1 v c_1 .. c_j b``
    closed by a boundary path ``b -> s_k``; its least-area disk re-solved with ``(v, s_1)`` regular.
    """
    es = lookup.vertex_edges(v)
    es = es[~g.boundary[es] & (g.cls[es] >= 0)]
    if es.size != 2:
        return
    seen = set()
    for short, long_ in ((es[0], es[1]), (es[1], es[0])):
        S = _branch(g, lookup, v, int(short), max_len)
        if not g.on_b[S[-1]]:
            continue
        Lb = _branch(g, lookup, v, int(long_), len(S) + 2)
        for j in range(1, len(Lb)):
            c = Lb[j]
            nb = lookup.edges[lookup.vertex_edges(c)].reshape(-1)
            nb = np.unique(nb[(nb != c) & g.on_b[nb]])
            if g.on_b[c]:
                nb = np.array([c])
            nb = nb[np.argsort(np.linalg.norm(g.X[nb] - g.X[c], axis=1))][:3]
            for b in nb.tolist():
                near = np.zeros(g.V, bool)
                near[np.r_[S, Lb[:j + 1], b]] = True
                for _ in range(3):  # the boundary path stays within 3 rings of the hook
                    near[lookup.edges[near[lookup.edges].any(1)].reshape(-1)] = True
                bp = _boundary_path(g, lookup, b, S[-1], near)
                if bp is None:
                    continue
                head = [*S[::-1], *Lb[1:j + 1]] + ([b] if b != c else [])
                loop = np.array(head + bp[1:].tolist())
                if np.unique(loop[:-1]).size != loop.size - 1:
                    continue
                disk = spanning_disk(g, lookup, loop)
                if disk is None:
                    continue
                faces, inside, _ = disk
                e1 = int(lookup.edge_id(v, S[1])[0])
                seed = [f for f in faces.tolist() if e1 in lookup.face_edges[f]]
                if len(seed) != 1:
                    continue
                tried = _try_disk(g, faces, seed[0], e1, 0, inside, seen)
                if tried is not None:
                    yield Move(vertex=int(v), edges=(e1, int(long_)), path=loop, faces=faces, values=tried[0],
                               delta=tried[1], kind="retract")


def best_move(g: SingularGraph, lookup: MeshLookup, v: int, kinds=None, n_paths: int = 2) -> Move | None:
    """The cone move at ``v`` that lowers the cost most (``None`` if none lowers it)."""
    best = None
    for mv in candidate_moves(g, lookup, v, kinds, n_paths):
        if mv.delta < -1e-9 and (best is None or mv.delta < best.delta):
            best = mv
    return best


def _apply(kinds, mesh, tet_frames, face_match, vertex, weights=None):
    g = SingularGraph(mesh, tet_frames, face_match, weights=weights)
    lookup = MeshLookup(mesh)
    V = mesh.n_vertices
    if not (0 <= int(vertex) < V):
        raise ValueError(f"vertex {vertex} is not a vertex of this mesh (0..{V - 1})")
    mv = best_move(g, lookup, int(vertex), kinds)
    if mv is None:
        return g.match.copy(), None
    vs = np.unique(g.edges[np.unique(g.face_edges[mv.faces])])
    before = {"vertex_class": g.vcls[vs].copy()}
    g.set_matchings(mv.faces, mv.values)
    mv.info = {"vertices": vs, "class_before": before["vertex_class"], "class_after": g.vcls[vs].copy(),
               "counts_after": g.counts()}
    return g.match.copy(), mv


def push_inside(mesh, tet_frames, face_match, vertex: int, *, weights: dict | None = None):
    """Push a singular curve lying on a smooth part of the boundary off the boundary vertex
    ``vertex`` into the interior (module docstring). Returns ``(face_match (F,), Move or None)``."""
    return _apply(("push_inside",), mesh, tet_frames, face_match, vertex, weights)


def move_off_boundary(mesh, tet_frames, face_match, vertex: int, *, weights: dict | None = None):
    """Detach an arc that touches the boundary at ``vertex`` (both its edges interior) from it.
    Returns ``(face_match (F,), Move or None)``."""
    return _apply(("move_off",), mesh, tet_frames, face_match, vertex, weights)


def slide_touching_end(mesh, tet_frames, face_match, vertex: int, *, weights: dict | None = None):
    """Slide the end of an arc that touches the boundary at ``vertex`` about a tangent axis one
    ring along the surface (:func:`slide_moves`). Returns ``(face_match (F,), Move or None)``."""
    return _apply(("slide_end",), mesh, tet_frames, face_match, vertex, weights)


def detach_arc(mesh, tet_frames, face_match, vertex: int, *, weights: dict | None = None):
    """Detach an arc from the invalid interior node ``vertex``. Returns ``(face_match, Move or None)``."""
    return _apply(("detach",), mesh, tet_frames, face_match, vertex, weights)


def zip_zipper(mesh, tet_frames, face_match, vertex: int, *, weights: dict | None = None):
    """Move the tip of the hairpin at the zipper node ``vertex`` across a cone of faces (zips its
    branches). Returns ``(face_match, Move or None)``."""
    return _apply(("zip",), mesh, tet_frames, face_match, vertex, weights)


def retract_hook(mesh, tet_frames, face_match, vertex: int, *, weights: dict | None = None):
    """Retract the hook at the zipper node ``vertex`` through the boundary (module docstring).
    Returns ``(face_match, Move or None)``."""
    return _apply(("retract",), mesh, tet_frames, face_match, vertex, weights)


def repair_feature_sector(mesh, tet_frames, face_match, vertex: int, *, weights: dict | None = None):
    """Give the fans at the feature vertex ``vertex`` the angles their sharp feature asks for.
    Returns ``(face_match, Move or None)``."""
    return _apply(("feature_sector",), mesh, tet_frames, face_match, vertex, weights)
