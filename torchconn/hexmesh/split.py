"""Edge splits that separate the singular edges before the map (HEXMESH.md step 1).

A map sends every vertex of a singular edge onto an integer line. A tet whose vertices all lie
on singular edges (two singular edges of one chain sharing a vertex, or two opposite ones)
then has a face or edge that the constraints collapse onto that line, and an interior edge
whose two ends lie on the boundary can be pressed flat between boundary planes. The remedy of
the hex-meshing pipelines is to split such edges first: the midpoint ``m`` of an edge ``(a, b)``
replaces every tet ``(a, b, c, d)`` around it by ``(m, b, c, d)`` and ``(a, m, c, d)`` (same
orientation), both children keep the parent's frame, so the transitions inside a parent are the
identity and every holonomy, hence the singular structure, is unchanged; the original vertices
keep their index and coordinates (the map is of the refined mesh, vertices ``V..`` appended).
CAD tags follow the split (a tagged boundary triangle and a tagged curve edge become two).

Rules, applied in rounds until none applies (each round splits a set of edges no two of which
share a tet, so every parent tet is split at most once per round):

* ``"singular"``: a non-singular edge whose two ends lie on singular edges;
* ``"boundary"``: an interior edge whose two ends lie on the boundary.

The singular edges are found once (:func:`~.cut.tet_charts` of the input) and carried through the
rounds by vertex pairs (a split singular edge becomes its two halves; the edges a split creates
inside a parent are regular), not recomputed per round: a split keeps every holonomy. Cost on the
1M-tet ``i02c_m2@lmax=0.14``: docs/results/hexmesh.md (``python -m benchmarks.hex_stage_scale``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["SplitResult", "split_for_map", "split_edges", "split_tets_edges", "split_tets_centroid", "open_flat_tets", "SPLIT_RULES"]

SPLIT_RULES = ("singular", "boundary")


@dataclass
class SplitResult:
    """The refined mesh and its frames.

    Attributes:
        mesh: the refined ``TetMesh`` (original vertices first, same coordinates).
        tet_frames: ``(T', 3, 3)`` float64 frames, each child tet with its parent's frame.
        parent_tet: ``(T',)`` int64, the original tet each tet comes from.
        splits: ``{rule: number of edges split}``; ``rounds``: the rounds run.
        face_match: ``(F',)`` the carried face matchings (``None`` if none were given).
    """

    mesh: object
    tet_frames: torch.Tensor
    parent_tet: np.ndarray
    splits: dict
    rounds: int
    face_match: np.ndarray | None = None


def _independent(tet_edges: np.ndarray, cand: np.ndarray, E: int) -> np.ndarray:
    """A maximal subset of the candidate edges no two of which share a tet (greedy in edge order;
    a loop over the candidates, one-time setup)."""
    if cand.size == 0:
        return cand
    T = tet_edges.shape[0]
    inc_e = tet_edges.reshape(-1)
    inc_t = np.repeat(np.arange(T), 6)
    order = np.argsort(inc_e, kind="stable")
    ptr = np.searchsorted(inc_e[order], np.arange(E + 1))
    tets_of = inc_t[order]
    taken = np.zeros(T, bool)
    chosen = []
    for e in np.sort(cand).tolist():
        ts = tets_of[ptr[e]:ptr[e + 1]]
        if not taken[ts].any():
            taken[ts] = True
            chosen.append(e)
    return np.asarray(chosen, np.int64)


def split_edges(mesh, tet_frames: torch.Tensor, edge_ids: np.ndarray, face_match: np.ndarray | None = None):
    """Split the edges ``edge_ids`` (no two in one tet) at their midpoints (module docstring).

    ``face_match (F,)``: face matchings of ``mesh`` (:func:`~.cut.tet_charts`) to carry over: a
    face inside a parent tet gets the identity, a piece of an old face the old face's matching.

    Returns ``(new_mesh, new_tet_frames, parent (T',), new_face_match (F',) or None)``.
    """
    from ..mesh.cad import cad_tags_from_elements
    from ..mesh.tet import TetMesh

    tets = mesh.tets.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    X = mesh.vertices.detach().cpu()
    V, T = X.shape[0], tets.shape[0]
    edge_ids = np.asarray(edge_ids, np.int64)
    mid_of = np.full(edges.shape[0], -1, np.int64)
    mid_of[edge_ids] = V + np.arange(edge_ids.size)
    newX = torch.cat([X, 0.5 * (X[edges[edge_ids, 0]] + X[edges[edge_ids, 1]])])
    tet_edges = mesh.tet_edges.cpu().numpy()
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    hit = mid_of[tet_edges] >= 0  # (T, 6)
    if (hit.sum(1) > 1).any():
        raise ValueError("split_edges: two edges of one tet in one round")
    t_hit = np.nonzero(hit.any(1))[0]
    p = hit[t_hit].argmax(1)
    m = mid_of[tet_edges[t_hit, p]]
    i_loc, j_loc = pairs[p, 0], pairs[p, 1]
    c1 = tets[t_hit].copy()
    c2 = tets[t_hit].copy()
    c1[np.arange(t_hit.size), i_loc] = m  # (m, b, c, d)
    c2[np.arange(t_hit.size), j_loc] = m  # (a, m, c, d)
    keep = np.ones(T, bool)
    keep[t_hit] = False
    new_tets = np.concatenate([tets[keep], c1, c2])
    parent = np.concatenate([np.nonzero(keep)[0], t_hit, t_hit])
    Fr = torch.as_tensor(tet_frames)[torch.as_tensor(parent)]
    new = TetMesh(newX, torch.as_tensor(new_tets), dtype=mesh.vertices.dtype)
    new_match = None
    if face_match is not None:
        from .cut import GROUP_INV

        old_ft = mesh.face_tets.cpu().numpy()
        ofi = np.nonzero((old_ft >= 0).all(1))[0]
        key_old = old_ft[ofi, 0] * T + old_ft[ofi, 1]
        order = np.argsort(key_old)
        nft = new.face_tets.cpu().numpy()
        new_match = np.zeros(nft.shape[0], np.int64)
        nfi = np.nonzero((nft >= 0).all(1))[0]
        p0, p1 = parent[nft[nfi, 0]], parent[nft[nfi, 1]]
        cross = p0 != p1
        for a, b, flip in ((p0, p1, False), (p1, p0, True)):
            k = a * T + b
            pos = np.searchsorted(key_old[order], k).clip(max=max(ofi.size - 1, 0))
            hit = cross & (key_old[order][pos] == k) if ofi.size else np.zeros_like(cross)
            g = np.asarray(face_match)[ofi[order][pos]]
            new_match[nfi[hit]] = GROUP_INV[g[hit]] if flip else g[hit]
    cad = getattr(mesh, "cad", None)
    if cad is not None:
        faces = mesh.faces.cpu().numpy()
        fs = cad.face_surface.cpu().numpy()
        tf = np.nonzero(fs >= 0)[0]
        tris, ttag = [], []
        fe = mesh.face_edges.cpu().numpy()[tf]  # edges bc, ac, ab of the sorted face
        split_e = mid_of[fe]  # (n, 3)
        for k, (ka, kb, kc) in enumerate(((1, 2, 0), (0, 2, 1), (0, 1, 2))):  # edge k joins corners ka, kb
            sel = split_e[:, k] >= 0
            f = faces[tf[sel]]
            mm = split_e[sel, k]
            t1 = f.copy()
            t1[:, ka] = mm
            t2 = f.copy()
            t2[:, kb] = mm
            tris += [t1, t2]
            ttag += [fs[tf[sel]], fs[tf[sel]]]
        unsplit = (split_e < 0).all(1)
        tris.append(faces[tf[unsplit]])
        ttag.append(fs[tf[unsplit]])
        fe_edges = cad.feature_edges.cpu().numpy()
        fe_idx = cad.feature_edge_index.cpu().numpy()
        curve = cad.feature_edge_curve.cpu().numpy()
        mm = mid_of[fe_idx]
        s = mm >= 0
        lines = np.concatenate([fe_edges[~s], np.stack([fe_edges[s, 0], mm[s]], 1), np.stack([mm[s], fe_edges[s, 1]], 1)])
        ltag = np.concatenate([curve[~s], curve[s], curve[s]])
        new.cad = cad_tags_from_elements(new, np.concatenate(tris), np.concatenate(ttag), lines, ltag,
                                         cad.corner_vertices, cad.corner_point, source="split")
    return new, Fr, parent, new_match


def split_pairs(mesh, tet_frames, pairs: np.ndarray, face_match: np.ndarray | None = None):
    """Split the edges with vertex pairs ``pairs (K, 2)`` at their midpoints, in rounds of edges
    that share no tet. Returns ``(mesh, tet_frames, parent (T',), face_match)``."""
    Fr = torch.as_tensor(tet_frames)
    parent = np.arange(mesh.n_tets)
    todo = np.sort(np.asarray(pairs, np.int64).reshape(-1, 2), axis=1)
    while todo.shape[0]:
        V = mesh.n_vertices
        keys = mesh.edges[:, 0].cpu().numpy() * V + mesh.edges[:, 1].cpu().numpy()
        k = todo[:, 0] * V + todo[:, 1]
        eid = np.searchsorted(keys, k)
        ok = (eid < keys.size) & (keys[np.minimum(eid, keys.size - 1)] == k)
        todo, eid = todo[ok], eid[ok]
        if not todo.shape[0]:
            break
        chosen = _independent(mesh.tet_edges.cpu().numpy(), eid, keys.size)
        mesh, Fr, par, face_match = split_edges(mesh, Fr, chosen, face_match)
        parent = parent[par]
        todo = todo[~np.isin(eid, chosen)]
    return mesh, Fr, parent, face_match


def split_for_map(mesh, tet_frames, face_match: np.ndarray | None = None, *, rules=SPLIT_RULES,
                  max_rounds: int = 50) -> SplitResult:
    """Split edges by ``rules`` (module docstring) until none applies or ``max_rounds``.

    Args:
        mesh: a ``TetMesh``; tet_frames: ``(T, 3, 3)`` rotations.
        face_match: ``(F,)`` face matchings to use and carry (default: the best ones).
        rules: a subset of :data:`SPLIT_RULES`.
    """
    from .cut import face_matchings, tet_charts

    unknown = [r for r in rules if r not in SPLIT_RULES]
    if unknown:
        raise ValueError(f"unknown split rules {unknown}; known: {list(SPLIT_RULES)}")
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    parent = np.arange(mesh.n_tets)
    counts = {r: 0 for r in SPLIT_RULES}
    rounds = 0
    given = face_match is not None
    sing = None
    if "singular" in rules:
        # the singular edges once: a split keeps every holonomy (module docstring), so afterwards
        # they are the halves of the singular edges split and the others, carried by vertex pairs
        if not given:
            face_match = face_matchings(mesh, Fr)
        sing = tet_charts(mesh, Fr, face_match).singular_edge
    for _ in range(max_rounds):
        edges = mesh.edges.cpu().numpy()
        V, E = mesh.n_vertices, edges.shape[0]
        cand_by_rule = {}
        if "singular" in rules:
            sv = np.zeros(V, bool)
            sv[edges[sing].reshape(-1)] = True
            cand_by_rule["singular"] = np.nonzero(~sing & sv[edges[:, 0]] & sv[edges[:, 1]])[0]
        if "boundary" in rules:
            bv = np.zeros(V, bool)
            bv[mesh.boundary_vertices.cpu().numpy()] = True
            bfe = mesh.face_edges.cpu().numpy()[mesh.boundary_face_index.cpu().numpy()].reshape(-1)
            on_b = np.zeros(E, bool)
            on_b[bfe] = True
            cand_by_rule["boundary"] = np.nonzero(~on_b & bv[edges[:, 0]] & bv[edges[:, 1]])[0]
        cand = np.unique(np.concatenate([c for c in cand_by_rule.values()] or [np.zeros(0, np.int64)]))
        if cand.size == 0:
            break
        chosen = _independent(mesh.tet_edges.cpu().numpy(), cand, E)
        for r, c in cand_by_rule.items():
            counts[r] += int(np.isin(chosen, c).sum())
        mesh, Fr, par, face_match = split_edges(mesh, Fr, chosen, face_match)
        parent = parent[par]
        rounds += 1
        if sing is not None:
            sing = _carry_edges(sing, edges, V, chosen, mesh)
    if not given:
        face_match = None
    return SplitResult(mesh=mesh, tet_frames=Fr, parent_tet=parent, splits=counts, rounds=rounds,
                       face_match=face_match)


def _carry_edges(flag: np.ndarray, edges: np.ndarray, V: int, chosen: np.ndarray, new_mesh) -> np.ndarray:
    """``(E',)`` bool on ``new_mesh``'s edges: the edges flagged in ``flag (E,)`` (of the mesh with
    ``edges (E, 2)`` and ``V`` vertices) after :func:`split_edges` of ``chosen`` (midpoint of
    ``chosen[k]`` is vertex ``V + k``): a flagged edge split becomes its two halves."""
    mid = np.full(edges.shape[0], -1, np.int64)
    mid[chosen] = V + np.arange(chosen.size)
    keep = flag & (mid < 0)
    halves = flag & (mid >= 0)
    pairs = np.concatenate([edges[keep], np.stack([edges[halves, 0], mid[halves]], 1),
                            np.stack([mid[halves], edges[halves, 1]], 1)])
    pairs = np.sort(pairs, axis=1)
    new_edges = new_mesh.edges.cpu().numpy()
    V2 = new_mesh.n_vertices
    keys = new_edges[:, 0] * V2 + new_edges[:, 1]
    out = np.zeros(new_edges.shape[0], bool)
    if pairs.shape[0]:
        k = pairs[:, 0] * V2 + pairs[:, 1]
        order = np.argsort(keys)
        pos = np.searchsorted(keys[order], k)
        if not np.array_equal(keys[order][np.minimum(pos, keys.size - 1)], k):  # pragma: no cover - a bug
            raise RuntimeError("a carried edge is missing from the refined mesh")
        out[order[pos]] = True
    return out


def split_tets_edges(mesh, tet_frames, tets: np.ndarray, face_match: np.ndarray | None = None,
                     keep_edges: np.ndarray | None = None):
    """Split one edge of each of the tets ``tets`` (one round: edges that share no tet).

    The edge split in a tet is its longest edge not in ``keep_edges (E,)`` bool (edges whose
    midpoint would be as constrained as their ends: boundary, singular and feature edges), else
    its longest edge. Returns ``(mesh, tet_frames, parent (T',), face_match, n_split)``.
    """
    tets = np.asarray(tets, np.int64)
    if tets.size == 0:
        return mesh, tet_frames, np.arange(mesh.n_tets), face_match, 0
    X = mesh.vertices.detach().cpu().double().numpy()
    edges = mesh.edges.cpu().numpy()
    te = mesh.tet_edges.cpu().numpy()[tets]  # (k, 6)
    length = np.linalg.norm(X[edges[te, 1]] - X[edges[te, 0]], axis=2)
    if keep_edges is not None:
        length = np.where(np.asarray(keep_edges, bool)[te], -1.0 / (1.0 + length), length)
    pick = np.unique(te[np.arange(tets.size), length.argmax(1)])
    chosen = _independent(mesh.tet_edges.cpu().numpy(), pick, edges.shape[0])
    new, Fr, parent, fm = split_edges(mesh, tet_frames, chosen, face_match)
    return new, Fr, parent, fm, int(chosen.size)


def split_tets_centroid(mesh, tet_frames, tets: np.ndarray, face_match: np.ndarray | None = None):
    """Split each tet of ``tets`` into four at its centroid (a new, free interior vertex).

    Child ``k`` is the parent with corner ``k`` replaced by the centroid (same orientation); it
    holds the parent's face opposite corner ``k``, whose matching and CAD tags it keeps; the faces
    between children get the identity matching; every child keeps the parent's frame (so every
    holonomy, hence the singular structure, is unchanged). Original vertices keep their index.

    Returns ``(mesh, tet_frames, parent (T',), face_match (F',) or None)``.
    """
    from ..mesh.cad import cad_tags_from_elements
    from ..mesh.tet import TetMesh
    from .cut import GROUP_INV

    tets = np.unique(np.asarray(tets, np.int64))
    old_t = mesh.tets.cpu().numpy()
    X = mesh.vertices.detach().cpu()
    V, T = X.shape[0], old_t.shape[0]
    if tets.size == 0:
        return mesh, torch.as_tensor(tet_frames), np.arange(T), face_match
    m = V + np.arange(tets.size)
    newX = torch.cat([X, X[torch.as_tensor(old_t[tets])].mean(1)])
    keep = np.ones(T, bool)
    keep[tets] = False
    children = []
    for k in range(4):
        c = old_t[tets].copy()
        c[:, k] = m
        children.append(c)
    new_tets = np.concatenate([old_t[keep]] + children)
    parent = np.concatenate([np.nonzero(keep)[0]] + [tets] * 4)
    Fr = torch.as_tensor(tet_frames)[torch.as_tensor(parent)]
    new = TetMesh(newX, torch.as_tensor(new_tets), dtype=mesh.vertices.dtype)
    new_match = None
    if face_match is not None:
        nv = V + tets.size
        okey = np.sort(mesh.faces.cpu().numpy(), axis=1) @ np.array([nv * nv, nv, 1])
        order = np.argsort(okey)
        old_ft = mesh.face_tets.cpu().numpy()
        nft = new.face_tets.cpu().numpy()
        nkey = np.sort(new.faces.cpu().numpy(), axis=1) @ np.array([nv * nv, nv, 1])
        new_match = np.zeros(nft.shape[0], np.int64)
        inter = np.nonzero((nft >= 0).all(1))[0]
        pos = np.searchsorted(okey[order], nkey[inter]).clip(max=okey.size - 1)
        found = okey[order][pos] == nkey[inter]
        of = order[pos]
        g = np.asarray(face_match)[of]
        same = parent[nft[inter, 0]] == old_ft[of, 0]
        new_match[inter] = np.where(found, np.where(same, g, GROUP_INV[g]), 0)
    cad = getattr(mesh, "cad", None)
    if cad is not None:
        faces = mesh.faces.cpu().numpy()
        fs = cad.face_surface.cpu().numpy()
        tf = np.nonzero(fs >= 0)[0]
        new.cad = cad_tags_from_elements(new, faces[tf], fs[tf], cad.feature_edges.cpu().numpy(),
                                         cad.feature_edge_curve.cpu().numpy(), cad.corner_vertices, cad.corner_point,
                                         source="split")
    return new, Fr, parent, new_match


def open_flat_tets(mesh, tet_frames, tets: np.ndarray, line_face: np.ndarray, face_match: np.ndarray | None,
                   keep_edges: np.ndarray, line_keep_edges: np.ndarray):
    """One round of refinement of tets the constraints flatten (not collapsed ones).

    * a tet with a face the constraints put on one line (``line_face (k,)``, its local index, or
      -1; :meth:`~.seamless.SeamlessProblem.flat_tets`) gets that face's longest edge not in
      ``line_keep_edges (E,)`` (singular and feature edges: a midpoint there stays on the line)
      split: the midpoint leaves the line;
    * another tet with an edge whose midpoint would be free (not in ``keep_edges (E,)``:
      boundary, singular, feature edges) gets its longest such edge split;
    * a tet with neither is split at its centroid (:func:`split_tets_centroid`).

    Edge splits go first (one round: edges that share no tet); a centroid split is made on a tet
    no edge split touched. Returns ``(mesh, tet_frames, parent (T',), face_match, {"edge": n,
    "centroid": n})``.
    """
    tets = np.asarray(tets, np.int64)
    line_face = np.asarray(line_face, np.int64)
    X = mesh.vertices.detach().cpu().double().numpy()
    edges = mesh.edges.cpu().numpy()
    te_all = mesh.tet_edges.cpu().numpy()
    te = te_all[tets]  # (k, 6) local edges (0,1) (0,2) (0,3) (1,2) (1,3) (2,3)
    length = np.linalg.norm(X[edges[te, 1]] - X[edges[te, 0]], axis=2)
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    on_face = np.zeros((tets.size, 6), bool)
    has_line = line_face >= 0
    on_face[has_line] = (pairs[None, :, :] != line_face[has_line, None, None]).all(-1)
    ok_line = on_face & ~np.asarray(line_keep_edges, bool)[te]
    ok_free = ~np.asarray(keep_edges, bool)[te]
    use = np.where(has_line[:, None], ok_line, ok_free)
    pick_ok = use.any(1)
    pick = te[np.arange(tets.size), np.where(use, length, -1.0).argmax(1)]
    counts = {"edge": 0, "centroid": 0}
    parent = np.arange(mesh.n_tets)
    chosen = _independent(te_all, np.unique(pick[pick_ok]), edges.shape[0])
    cen = tets[~pick_ok & ~has_line]  # a line face with no splittable edge: left as it is
    if chosen.size:
        mesh, tet_frames, par, face_match = split_edges(mesh, tet_frames, chosen, face_match)
        counts["edge"] = int(chosen.size)
        parent = par
        if cen.size:  # a tet no edge split touched keeps one child: find its new index
            first = np.full(par.max() + 1, -1, np.int64)
            once = np.bincount(par, minlength=par.max() + 1) == 1
            first[par[::-1]] = np.arange(par.size)[::-1]
            cen = first[cen[once[cen]]]
    if cen.size:
        mesh, tet_frames, par, face_match = split_tets_centroid(mesh, tet_frames, cen, face_match)
        counts["centroid"] = int(cen.size)
        parent = parent[par]
    return mesh, tet_frames, parent, face_match, counts
