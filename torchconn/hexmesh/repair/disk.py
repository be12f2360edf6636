"""Moving singular arcs by re-solving the matchings of a disk of faces.

The holonomy of an edge is the product of the transitions over its walk, and a face is on the
walks of its three edges only. Take a disk ``D`` of interior faces: an edge inside ``D`` (two
faces of ``D`` at it) is crossed by ``D`` twice, an edge of its rim ``∂D`` once. Changing the
matchings of ``D``'s faces so that every edge inside ``D`` keeps its walk product changes only
the products of the rim's edges: sweeping ``D`` moves a singular arc from one part of the rim
to the other (as a relabeling of the frames on one side of ``D`` would, but without touching
the frames). This is the operation of Locally Meshable Frame Fields' repair (Liu & Bommes
2023; AlgoHex's "zipping" of a cut surface), restated:

* :func:`solve_disk` fixes the new matching of one seed face from the product one rim edge
  must take (e.g. the identity: the arc leaves that edge), then peels: an edge inside ``D``
  with exactly one face left unsolved determines that face (``st_k = S^-1 H P^-1``, the step's
  transition from the prefix ``P`` and suffix ``S`` of the walk and the product ``H`` it keeps).
  It fails (``None``) when faces stay unsolved or an edge inside ``D`` closes inconsistently
  (``D`` is not a disk whose inside is free of the conservation it would break), so every
  result keeps the products of the inside edges exactly.
* :func:`cone_disk` is the disk of LMFF's one-ring moves: the faces ``(v, p_{i-1}, p_i)`` over a
  path ``p_0 .. p_m`` in the link of a vertex ``v``. With the spoke ``(v, p_0)`` made regular,
  an arc ``a - v - b`` (``a = p_0``, ``b = p_m``) becomes ``a - p_1 - ... - b``: detached from
  ``v``, pushed off a boundary vertex, a zipper tip moved (:mod:`.ops`).
* :func:`link_path` finds the path: Dijkstra over the link's edges (``scipy.sparse.csgraph``),
  weighted against boundary vertices, other singular spokes, and turns of the arc along its axis.

Group conventions: :mod:`torchconn.hexmesh.cut` (``R_f = G[match[f]]^T``; a walk step from
``face_tets[f, 0]`` applies ``R_f``, the other way ``R_f^T``).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from ..cut import GROUP_INV, GROUP_MUL

__all__ = ["MeshLookup", "solve_disk", "cone_disk", "link_path"]


class MeshLookup:
    """Incidences the moves need, built once per mesh (vectorized): vertex -> edges, vertex ->
    faces, and the lookup of an edge or a face by its vertices."""

    def __init__(self, mesh):
        self.edges = mesh.edges.cpu().numpy()
        self.faces = mesh.faces.cpu().numpy()
        self.face_edges = mesh.face_edges.cpu().numpy()
        V = mesh.n_vertices
        self.V = V
        E, F = self.edges.shape[0], self.faces.shape[0]
        ve = self.edges.reshape(-1)
        order = np.argsort(ve, kind="stable")
        self.ve_ptr = np.searchsorted(ve[order], np.arange(V + 1))
        self.ve_idx = np.repeat(np.arange(E), 2)[order]
        vf = self.faces.reshape(-1)
        order = np.argsort(vf, kind="stable")
        self.vf_ptr = np.searchsorted(vf[order], np.arange(V + 1))
        self.vf_idx = np.repeat(np.arange(F), 3)[order]
        s = np.sort(self.edges, 1)
        self._ekey = s[:, 0] * V + s[:, 1]
        self._eord = np.argsort(self._ekey)
        sf = np.sort(self.faces, 1)
        self._fkey = (sf[:, 0] * V + sf[:, 1]) * V + sf[:, 2]
        self._ford = np.argsort(self._fkey)

    def vertex_edges(self, v: int) -> np.ndarray:
        """Edge ids at vertex ``v``."""
        return self.ve_idx[self.ve_ptr[v]:self.ve_ptr[v + 1]]

    def vertex_faces(self, v: int) -> np.ndarray:
        """Face ids at vertex ``v``."""
        return self.vf_idx[self.vf_ptr[v]:self.vf_ptr[v + 1]]

    def edge_id(self, a, b) -> np.ndarray:
        """Edge ids of the vertex pairs ``(a, b)`` (arrays; ``-1`` where there is no edge)."""
        a, b = np.atleast_1d(a), np.atleast_1d(b)
        key = np.minimum(a, b) * self.V + np.maximum(a, b)
        sk = self._ekey[self._eord]
        pos = np.clip(np.searchsorted(sk, key), 0, sk.size - 1)
        return np.where(sk[pos] == key, self._eord[pos], -1)

    def face_id(self, a, b, c) -> np.ndarray:
        """Face ids of the vertex triples (arrays; ``-1`` where there is no face)."""
        t = np.sort(np.stack([np.atleast_1d(a), np.atleast_1d(b), np.atleast_1d(c)], 1), 1)
        key = (t[:, 0] * self.V + t[:, 1]) * self.V + t[:, 2]
        sk = self._fkey[self._ford]
        pos = np.clip(np.searchsorted(sk, key), 0, sk.size - 1)
        return np.where(sk[pos] == key, self._ford[pos], -1)

    def other_end(self, e: int, v: int) -> int:
        a, b = self.edges[e]
        return int(b if a == v else a)


def _walk_steps(g, e: int, match: np.ndarray):
    """Faces, step transitions and directions of the walk of edge ``e`` for ``match``."""
    w = g.walks
    s = np.arange(w.ptr[e], w.ptr[e + 1])
    f = w.face[s]
    R = GROUP_INV[match[f]]
    return f, np.where(w.forward[s], R, GROUP_INV[R]), w.forward[s]


def _solve_step(g, e: int, f: int, target: int, match: np.ndarray) -> int:
    """The matching of face ``f`` (on the walk of ``e``) that gives ``e`` the product ``target``."""
    faces, st, fwd = _walk_steps(g, e, match)
    k = int(np.nonzero(faces == f)[0][0])
    P = 0
    for x in st[:k].tolist():
        P = GROUP_MUL[x, P]
    S = 0
    for x in st[k + 1:].tolist():
        S = GROUP_MUL[x, S]
    step = GROUP_MUL[GROUP_MUL[GROUP_INV[S], target], GROUP_INV[P]]
    return int(GROUP_INV[step] if fwd[k] else step)  # match = R_f^T; R_f = step forward, step^T backward


def solve_disk(g, faces: np.ndarray, seed_face: int, seed_edge: int, seed_target: int,
               inside: np.ndarray) -> np.ndarray | None:
    """New matchings of the disk ``faces`` (module docstring), or ``None`` if there are none.

    Args:
        g: the :class:`~.graph.SingularGraph` (read, not changed).
        faces: ``(m,)`` interior face ids of the disk.
        seed_face, seed_edge: a face of the disk and an edge of it on the disk's rim (no other
            disk face on its walk).
        seed_target: the walk product (index into O) ``seed_edge`` must take.
        inside: the edges inside the disk: their walk products are kept.

    Returns:
        ``(m,)`` matchings for ``faces`` (in their order), or ``None``.
    """
    faces = np.asarray(faces, np.int64)
    inside = np.asarray(inside, np.int64)
    if not g.interior_face[faces].all():
        return None
    unknown = set(faces.tolist())
    work = g.match.copy()
    seed_faces, _, _ = _walk_steps(g, seed_edge, work)
    if seed_face not in unknown or sum(int(x) in unknown for x in seed_faces) != 1:
        return None
    work[seed_face] = _solve_step(g, seed_edge, seed_face, seed_target, work)
    unknown.discard(seed_face)
    walk_faces = {int(e): _walk_steps(g, e, work)[0] for e in inside.tolist()}
    progress = True
    while unknown and progress:  # loop over the peeling (at most m rounds)
        progress = False
        for e, wf in walk_faces.items():
            open_ = [int(x) for x in wf if int(x) in unknown]
            if len(open_) == 1:
                f = open_[0]
                work[f] = _solve_step(g, e, f, int(g.prod[e]), work)
                unknown.discard(f)
                progress = True
    if unknown:
        return None
    if inside.size and (g.edge_products(inside, work) != g.prod[inside]).any():
        return None
    return work[faces]


def cone_disk(lookup: MeshLookup, v: int, path: np.ndarray):
    """The cone over a link path of ``v``: ``(faces (m,), inside spokes (m-1,), rim path edges (m,))``,
    or ``None`` if a triangle ``(v, p_{i-1}, p_i)`` is not a face of the mesh."""
    path = np.asarray(path, np.int64)
    f = lookup.face_id(np.full(path.size - 1, v), path[:-1], path[1:])
    if (f < 0).any() or np.unique(f).size != f.size:
        return None
    spokes = lookup.edge_id(np.full(path.size - 2, v), path[1:-1]) if path.size > 2 else np.zeros(0, np.int64)
    rim = lookup.edge_id(path[:-1], path[1:])
    return f, spokes, rim


def link_path(g, lookup: MeshLookup, v: int, a: int, b: int, axis_world: np.ndarray | None = None,
              blocked: np.ndarray | None = None, mode: str = "aligned") -> np.ndarray | None:
    """A path ``a -> b`` in the link of ``v`` over interior faces (Dijkstra), or ``None``.

    Edge weights: 1, plus 4 for a boundary edge and 2 per boundary end (other than ``a``, ``b``:
    the new arc should leave the boundary), 5 per end whose spoke is singular (other arcs at
    ``v``); with the arc's world axis ``axis_world``, ``mode="aligned"`` adds 2 (1 - c) per edge
    (``c`` the absolute cosine of its angle to the axis), ``mode="monotone"`` 2 per spoke length
    by which an end lies outside the heights of ``a`` and ``b`` along the axis (the arc
    ``.. a P b ..`` should not turn back on ``P``: a zipper); ``blocked`` vertices are left out
    (another way around).
    """
    fs = lookup.vertex_faces(v)
    fs = fs[g.interior_face[fs]]
    if not fs.size:
        return None
    tri = lookup.faces[fs]
    others = tri[tri != v].reshape(-1, 2)
    nodes = np.unique(others)
    if a not in nodes or b not in nodes:
        return None
    loc = np.searchsorted(nodes, others)
    x, y = others[:, 0], others[:, 1]
    wgt = np.ones(x.size)
    le = lookup.edge_id(x, y)
    wgt += 4.0 * g.boundary[le]
    if axis_world is not None and mode == "aligned":
        d = g.X[y] - g.X[x]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        wgt += 2.0 * (1.0 - np.abs(d @ axis_world))
    monotone = axis_world is not None and mode == "monotone"
    if monotone:
        h = g.X[nodes] @ axis_world
        lo, hi = sorted((float(g.X[a] @ axis_world), float(g.X[b] @ axis_world)))
        scale = float(np.linalg.norm(g.X[nodes] - g.X[v], axis=1).mean())
        out = np.maximum(lo - h, 0.0) + np.maximum(h - hi, 0.0)
        off = dict(zip(nodes.tolist(), (4.0 * out / scale).tolist()))
    for p in (x, y):
        wgt += 2.0 * (g.on_b[p] & (p != a) & (p != b))
        spoke = lookup.edge_id(np.full(p.size, v), p)
        wgt += 5.0 * ((g.cls[spoke] >= 0) & (p != a) & (p != b))
        if monotone:
            wgt += 0.5 * np.array([off[int(q)] for q in p.tolist()])
    if blocked is not None and len(blocked):
        bad = np.isin(x, blocked) | np.isin(y, blocked)
        wgt = np.where(bad, np.inf, wgt)
    keep = np.isfinite(wgt)
    n = nodes.size
    A = sp.coo_matrix((wgt[keep], (loc[keep, 0], loc[keep, 1])), shape=(n, n)).tocsr()
    ia, ib = int(np.searchsorted(nodes, a)), int(np.searchsorted(nodes, b))
    dist, pred = dijkstra(A, directed=False, indices=ia, return_predecessors=True)
    if not np.isfinite(dist[ib]):
        return None
    out = [ib]
    while out[-1] != ia:
        out.append(int(pred[out[-1]]))
    return nodes[np.array(out[::-1])]


def spanning_disk(g, lookup: MeshLookup, loop: np.ndarray, rings: int = 2):
    """The least-area chain of interior faces whose boundary is the closed vertex ``loop``
    (``loop[0] == loop[-1]``, consecutive vertices joined by mesh edges), or ``None``.

    The faces within ``rings`` vertex rings of the loop are the candidates; the 2-chain ``x``
    (one coefficient per face) with ``d x = loop`` and least ``sum area |x|`` is a linear
    program (HiGHS through ``scipy.optimize.linprog``) whose optimum is integral in a
    tetrahedral mesh of a region of space (the boundary matrix is totally unimodular there:
    Dey, Hirani, Krishnamoorthy 2011, optimal homologous chains). This is the disk of LMFF's
    dual-path search found by area instead of by a walk.

    Returns ``(faces (m,), inside edges (k,), rim edges (r,))`` or ``None`` (no such chain in the
    region, or a fractional optimum). The answer depends on the mesh alone (not on the
    matchings), so it is kept per graph and loop: the repair's chains can ask for a loop again
    (n01c's repair from the SH field: 102.9 -> 97.5 s with it, the same matchings).
    """
    loop = np.asarray(loop, np.int64)
    if loop.size < 4 or loop[0] != loop[-1]:
        return None
    cache = g.__dict__.setdefault("_spanning_disks", {})
    key = (tuple(loop.tolist()), int(rings))
    if key not in cache:
        cache[key] = _spanning_disk(g, lookup, loop, rings)
    return cache[key]


def _spanning_disk(g, lookup: MeshLookup, loop: np.ndarray, rings: int):
    """:func:`spanning_disk` computed (its LP)."""
    from scipy.optimize import linprog

    rim = lookup.edge_id(loop[:-1], loop[1:])
    if (rim < 0).any():
        return None
    near = np.zeros(g.V, bool)
    near[loop] = True
    for _ in range(rings):  # loop over the rings
        near[lookup.edges[near[lookup.edges].any(1)].reshape(-1)] = True
    cand = np.nonzero(g.interior_face & near[lookup.faces].all(1))[0]
    if not cand.size:
        return None
    fv = lookup.faces[cand]  # sorted rows (a < b < c): d(abc) = ab + bc - ac
    fe = np.stack([lookup.edge_id(fv[:, 0], fv[:, 1]), lookup.edge_id(fv[:, 1], fv[:, 2]),
                   lookup.edge_id(fv[:, 0], fv[:, 2])], 1)
    sgn = np.array([1.0, 1.0, -1.0])
    es, col = np.unique(fe.reshape(-1), return_inverse=True)
    B = sp.coo_matrix((np.tile(sgn, cand.size), (col, np.repeat(np.arange(cand.size), 3))),
                      shape=(es.size, cand.size)).tocsr()
    rhs = np.zeros(es.size)
    pos = np.searchsorted(es, rim)
    if (pos >= es.size).any() or (es[np.minimum(pos, es.size - 1)] != rim).any():
        return None
    # the loop's edges, oriented: +1 along the canonical direction (lower vertex first)
    np.add.at(rhs, pos, np.where(loop[:-1] < loop[1:], 1.0, -1.0))
    X = g.X
    area = 0.5 * np.linalg.norm(np.cross(X[fv[:, 1]] - X[fv[:, 0]], X[fv[:, 2]] - X[fv[:, 0]]), axis=1)
    n = cand.size
    res = linprog(np.r_[area, area], A_eq=sp.hstack([B, -B]).tocsr(), b_eq=rhs, bounds=(0, 1), method="highs")
    if res.status != 0:
        return None
    x = res.x[:n] - res.x[n:]
    if np.abs(x - np.round(x)).max() > 1e-6:
        return None
    faces = cand[np.abs(np.round(x)) > 0]
    inside = np.setdiff1d(np.unique(lookup.face_edges[faces]), rim)
    return faces, inside, rim
