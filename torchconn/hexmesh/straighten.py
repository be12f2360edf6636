"""Singular edges along their turn axis: a greedy search over the face matchings of tet charts.

With one frame per tet the singular curves of a field run along mesh edges (:mod:`.cut`), and
a curve that crosses the mesh obliquely becomes a staircase of edges. A map sends every
singular edge onto the fixed line of its holonomy (a turn about parameter axis ``k``), so a
step of the staircase whose direction in the field is *across* that axis must be turned onto
it: the tets around it fold (measured on HexMe: most inverted tets of the maps sit at such
edges). The holonomy of an edge is the product of the face transitions around it, and changing
the matching of one face ``f`` (its transition ``R_f <- g R_f``, ``g in O``) changes the holonomy
of exactly the three edges of ``f``: it moves a singular edge onto the other two edges of the
face (a singular curve through ``a -> b`` then runs ``a -> c -> b``), or back.

The search (as :mod:`torchconn.frames.matching_search` does for the vertex-based picture) descends a
cost over interior edges: regular 0, a quarter or half turn about the parameter axis closest
to the edge's direction in the field ``w_along``, a turn about another axis ``w_across``, a
complex holonomy ``w_complex``, and ``w_tangent`` more for a turn at a boundary vertex about an
axis more than 45° from the boundary normal there (a singular curve touching the boundary
instead of ending on it: the map lays its line into the boundary plane); plus ``w_misfit`` times the rotation angle (radians) by which a
face's matching departs from its best match. LMFF's local conditions (:mod:`.meshability`) add
``w_zipper`` per zipper node and ``w_node`` per invalid singular node (vertex costs: a move
changes the classes of its face's three vertices) and ``w_fold`` per boundary edge off sharp
features whose fan folds (valence ±2 on a surface: a move on a face of the fan changes the fan's
transport). The search does not tell a half turn's valence 2 from 6 (it counts 6). Each step
takes the move with the largest decrease among the faces at a singular edge or at a folded
boundary fan (faces with a boundary edge only with ``boundary_moves``: their matchings set how
the boundary planes meet), the chosen move's decrease recomputed before it is made (the vertex
costs of a face also change with moves at its vertices); it stops when no move decreases the
cost. It terminates: the cost falls at every move and takes finitely many values.
"""
from __future__ import annotations

import numpy as np
import torch

from ..frames.singular import classify_holonomy
from .cut import GROUP_INV, GROUP_MUL, edge_walks, face_matchings, group_matrices
from .meshability import (VERTEX_CLASSES, boundary_edge_class, boundary_fans, classify_vertices, edge_class_counts,
                          fan_quarter_table, field_turn, interior_class_table, sharp_edges, tangent_axes,
                          walk_products)

__all__ = ["straighten_singular_edges", "DEFAULT_WEIGHTS", "touching_edges"]  # tangent_axes: from .meshability

DEFAULT_WEIGHTS = {"along": 1.0, "across": 8.0, "complex": 16.0, "tangent": 8.0, "misfit": 2.0,
                   "zipper": 8.0, "node": 8.0, "fold": 4.0}
"""Weights of the search's cost (module docstring). ``zipper`` and ``node``: measured on the 17
simple HexMe ``c`` meshes with the connection field (valid maps 7 with 0, 4, 8 or 16; zipper /
invalid nodes left 75 / 113 without, 7 / 68 with 8); ``fold``: no fan folds there (set on the
constructed case of the tests)."""


def _element_tables():
    G = torch.as_tensor(group_matrices(), dtype=torch.float64)
    typ, axis, _ = classify_holonomy(G)
    return typ.numpy(), axis.numpy()


_ETYPE, _EAXIS = _element_tables()


def straighten_singular_edges(mesh, tet_frames, face_match: np.ndarray | None = None, *, weights: dict | None = None,
                              max_moves: int = 10_000, boundary_moves: bool = False) -> tuple[np.ndarray, dict]:
    """Greedy repair of the face matchings so that singular edges run along their axis.

    Args:
        mesh: a ``TetMesh``; tet_frames: ``(T, 3, 3)`` rotations.
        face_match: ``(F,)`` starting matchings (default the best ones,
            :func:`~.cut.face_matchings`).
        weights: overrides of :data:`DEFAULT_WEIGHTS`.
        max_moves: a cap on the moves (the descent ends earlier on every mesh measured).

    Returns:
        ``(face_match (F,), info)`` with ``info``: ``moves``, ``edge_cost_before/after`` (the
        edge part of the cost, folds included), ``misfit_added_rad`` (summed over the moved
        faces), the edge counts ``across_before/after``, ``complex_before/after``,
        ``singular_before/after``, ``folds_before/after``, and the vertex counts
        ``zipper_before/after``, ``invalid_nodes_before/after`` (the search's classes).
    """
    w = dict(DEFAULT_WEIGHTS)
    if weights:
        unknown = set(weights) - set(w)
        if unknown:
            raise ValueError(f"unknown weights {sorted(unknown)}; known: {sorted(w)}")
        w.update({k: float(v) for k, v in weights.items()})
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    g_best = face_matchings(mesh, Fr)
    match = (g_best if face_match is None else np.asarray(face_match, np.int64)).copy()
    face_tets = mesh.face_tets.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    E, F = edges.shape[0], face_tets.shape[0]
    walks = edge_walks(mesh)
    interior_e = ~walks.boundary

    # misfit of a face for every matching: the angle between F_t0 g and F_t1 (computed on demand)
    Fnp = Fr.numpy()
    Gf = group_matrices().astype(np.float64)

    def misfit_row(f: int) -> np.ndarray:
        Mf = Fnp[face_tets[f, 0]].T @ Fnp[face_tets[f, 1]]
        tr = np.einsum("jab,ab->j", Gf, Mf)
        return np.arccos(np.clip((tr - 1) / 2, -1, 1))

    fi = np.nonzero((face_tets >= 0).all(1))[0]

    # cost table per edge: along axis from the field direction in the start tet's frame
    X = mesh.vertices.detach().cpu().double().numpy()
    d = X[edges[:, 1]] - X[edges[:, 0]]
    dpar = np.einsum("eji,ej->ei", Fr.numpy()[walks.start], d)
    along = np.abs(dpar).argmax(1)
    turn = (_ETYPE == 1) | (_ETYPE == 2)
    cost_tab = np.where(_ETYPE[None] == 3, w["complex"],
                        np.where(turn[None], np.where(_EAXIS[None] == along[:, None], w["along"], w["across"]), 0.0))
    # an interior singular edge at a boundary vertex whose turn axis is not along the boundary
    # normal there: the map puts its line into the boundary plane (the tets between collapse)
    tang = tangent_axes(mesh, Fr.numpy()[walks.start], edges, walks.boundary)  # (E, 3) bool per axis
    cost_tab = cost_tab + w["tangent"] * (turn[None] & tang[:, np.maximum(_EAXIS, 0)])
    cost_tab[walks.boundary] = 0.0

    def transitions():
        return GROUP_INV[match]

    # LMFF's conditions (meshability): the class of every edge for each product of its walk
    # (interior: holonomy; boundary: the fan's transport), folded fans off sharp features priced
    # per edge, zipper and invalid nodes per vertex
    fans = boundary_fans(mesh, walks)
    eb = fans.edge
    rot0 = transitions()
    rot0[~(face_tets >= 0).all(1)] = 0
    turn0 = field_turn(mesh, Fnp, rot0, walks)
    qtab = fan_quarter_table(Fnp, fans, d[eb], fans.dihedral + turn0[eb])  # (Eb, 24)
    _, expected = sharp_edges(mesh, fans)
    cls_tab = interior_class_table(dpar)
    cls_tab[eb] = boundary_edge_class(qtab)
    fold_tab = (qtab == 0) | (qtab == 4)
    cost_tab[eb] = w["fold"] * (fold_tab & (expected[eb] == 2)[:, None])
    use_v = w["zipper"] > 0 or w["node"] > 0
    vlut = np.zeros(len(VERTEX_CLASSES))
    vlut[VERTEX_CLASSES.index("zipper")] = w["zipper"]
    vlut[VERTEX_CLASSES.index("invalid")] = w["node"]
    vlut[VERTEX_CLASSES.index("complex")] = w["node"]  # a complex edge does not make its ends valid nodes
    on_b = np.zeros(mesh.n_vertices, bool)
    on_b[mesh.boundary_vertices.cpu().numpy()] = True
    faces_v = mesh.faces.cpu().numpy()

    def edge_cost(prod):
        return cost_tab[np.arange(E), prod]

    prod = walk_products(walks, transitions())  # holonomy, or the fan's transport on boundary edges
    hol = np.where(walks.boundary, -1, prod)
    cost_e = edge_cost(prod)
    cls_e = cls_tab[np.arange(E), prod]
    vcnt = edge_class_counts(edges, cls_e, mesh.n_vertices)
    vcls = classify_vertices(vcnt, on_b)
    info = {"edge_cost_before": float(cost_e.sum())}
    misfit_added = 0.0
    sing0 = (hol > 0)
    info.update(singular_before=int(sing0.sum()), across_before=int((sing0 & turn[np.maximum(hol, 0)]
                                                                     & (_EAXIS[np.maximum(hol, 0)] != along)).sum()),
                complex_before=int((sing0 & (_ETYPE[np.maximum(hol, 0)] == 3)).sum()),
                folds_before=int((cost_e[eb] > 0).sum()),
                zipper_before=int((vcls == VERTEX_CLASSES.index("zipper")).sum()),
                invalid_nodes_before=int((vcls == VERTEX_CLASSES.index("invalid")).sum()))

    # face -> its (edge, step) incidences in the walks of interior edges
    steps_e = np.repeat(np.arange(E), np.diff(walks.ptr))
    steps_k = np.arange(walks.face.size) - walks.ptr[steps_e]
    order = np.argsort(walks.face, kind="stable")
    f_ptr = np.searchsorted(walks.face[order], np.arange(F + 1))
    inc_step = order  # step ids grouped by face
    # faces with a boundary edge are not moved
    fe = mesh.face_edges.cpu().numpy()
    movable = np.zeros(F, bool)
    movable[fi] = True if boundary_moves else ~walks.boundary[fe[fi]].any(1)

    def prefix_suffix(e_ids):
        """For every step of the walks of edges ``e_ids``: (P, S) products before / after it."""
        R = transitions()
        out = {}
        for e in e_ids.tolist():
            a, b = walks.ptr[e], walks.ptr[e + 1]
            st = np.where(walks.forward[a:b], R[walks.face[a:b]], GROUP_INV[R[walks.face[a:b]]])
            n = b - a
            P = np.zeros(n, np.int64)
            S = np.zeros(n, np.int64)
            acc = 0
            for k in range(n):
                P[k] = acc
                acc = GROUP_MUL[st[k], acc]
            acc = 0
            for k in range(n - 1, -1, -1):
                S[k] = acc
                acc = GROUP_MUL[acc, st[k]]
            out[e] = (P, S)
        return out

    ps: dict = {}

    def score(faces):
        """Best (delta, g) of each face in ``faces`` over the 23 non-identity left factors."""
        R = transitions()
        best_d = np.full(len(faces), np.inf)
        best_g = np.zeros(len(faces), np.int64)
        for n_f, f in enumerate(faces):
            if not movable[f]:
                continue
            steps = inc_step[f_ptr[f]:f_ptr[f + 1]]
            es = steps_e[steps]
            if steps.size == 0:
                continue
            ks = steps_k[steps]
            for e in es.tolist():
                if e not in ps:
                    ps.update(prefix_suffix(np.array([e])))
            P = np.array([ps[e][0][k] for e, k in zip(es.tolist(), ks.tolist())])
            S = np.array([ps[e][1][k] for e, k in zip(es.tolist(), ks.tolist())])
            fwd = walks.forward[steps]
            Rn = GROUP_MUL[np.arange(24), R[f]]  # (24,) new transitions g R_f
            step_new = np.where(fwd[:, None], Rn[None, :], GROUP_INV[Rn][None, :])  # (m, 24)
            Hn = GROUP_MUL[S[:, None], GROUP_MUL[step_new, P[:, None]]]  # (m, 24)
            dc = (cost_tab[es[:, None], Hn] - cost_e[es][:, None]).sum(0)
            new_match = GROUP_INV[Rn]
            mr = misfit_row(f)
            dm = w["misfit"] * (mr[new_match] - mr[match[f]])
            delta = dc + dm
            if use_v:
                delta = delta + vertex_delta(f, es, Hn)
            delta[0] = np.inf  # g = I: no move
            j = int(np.argmin(delta))
            best_d[n_f], best_g[n_f] = delta[j], j
        return best_d, best_g

    def vertex_delta(f, es, Hn):
        """(24,) change of the vertex costs at the corners of face f when its edges es take the
        walk products Hn (m, 24)."""
        fv = faces_v[f]
        cnt = np.repeat(vcnt[fv][None], 24, axis=0)  # (24, 3, C)
        new_c = cls_tab[es[:, None], Hn]  # (m, 24)
        at = edges[es][:, None, :] == fv[None, :, None]  # (m, 3, 2)
        g_all = np.arange(24)
        for i in range(es.size):  # the face's (up to 3) edges
            for j in np.nonzero(at[i].any(1))[0]:  # its two corners
                if cls_e[es[i]] >= 0:
                    cnt[:, j, cls_e[es[i]]] -= 1
                ok = new_c[i] >= 0
                cnt[g_all[ok], j, new_c[i][ok]] += 1
        new_v = classify_vertices(cnt, np.broadcast_to(on_b[fv], (24, 3)))
        return vlut[new_v].sum(1) - vlut[vcls[fv]].sum()

    # candidate faces: those in the walks of singular interior edges and of folded fans
    def faces_of(e_ids):
        if len(e_ids) == 0:
            return np.zeros(0, np.int64)
        idx = np.concatenate([np.arange(walks.ptr[e], walks.ptr[e + 1]) for e in e_ids])
        return np.unique(walks.face[idx])

    sing_e = np.nonzero(((hol > 0) & interior_e) | (cost_e > 0))[0]
    if use_v:  # the boundary edges of bad vertices (a zipper of feature curves)
        bad_v = vlut[vcls] > 0
        sing_e = np.union1d(sing_e, np.nonzero(walks.boundary & (cls_e >= 0) & bad_v[edges].any(1))[0])
    cand = faces_of(sing_e.tolist())
    fbest_d = np.full(F, np.inf)
    fbest_g = np.zeros(F, np.int64)
    if cand.size:
        fbest_d[cand], fbest_g[cand] = score(cand.tolist())
    moves = 0
    tol = 1e-9
    while moves < max_moves:
        f = int(np.argmin(fbest_d))
        if not fbest_d[f] < -tol:
            break
        if use_v:  # vertex costs change with moves at the face's corners: recompute before moving
            d_f, g_f = score([f])
            if not d_f[0] <= fbest_d[f] + tol:
                fbest_d[f], fbest_g[f] = d_f[0], g_f[0]
                continue
        g = int(fbest_g[f])
        R = transitions()
        mr = misfit_row(f)
        new = GROUP_INV[GROUP_MUL[g, R[f]]]
        misfit_added += float(mr[new] - mr[match[f]])
        match[f] = new
        moves += 1
        # the three edges of f change; rescore every face on their walks
        steps = inc_step[f_ptr[f]:f_ptr[f + 1]]
        es = np.unique(steps_e[steps])
        prod[es] = _holonomy_of(walks, es, transitions())
        cost_e[es] = cost_tab[es, prod[es]]
        new_c = cls_tab[es, prod[es]]
        for end in (0, 1):
            old = cls_e[es] >= 0
            np.subtract.at(vcnt, (edges[es[old], end], cls_e[es[old]]), 1)
            new = new_c >= 0
            np.add.at(vcnt, (edges[es[new], end], new_c[new]), 1)
        cls_e[es] = new_c
        fv = faces_v[f]
        vcls[fv] = classify_vertices(vcnt[fv], on_b[fv])
        for e in es.tolist():
            ps.pop(e, None)
        ps.update(prefix_suffix(es))
        aff = faces_of(es.tolist())
        if use_v:  # faces moving a singular edge at the corners see new vertex costs
            at_v = np.nonzero((cls_e >= 0) & np.isin(edges, fv).any(1))[0]
            aff = np.union1d(aff, faces_of(at_v.tolist()))
        # faces on the walks of the affected edges' faces also see changed P/S of those edges
        fbest_d[aff], fbest_g[aff] = score(aff.tolist())
    prod = walk_products(walks, transitions())
    hol = np.where(walks.boundary, -1, prod)
    sing1 = hol > 0
    vcls = classify_vertices(edge_class_counts(edges, cls_tab[np.arange(E), prod], mesh.n_vertices), on_b)
    info.update(moves=moves, edge_cost_after=float(edge_cost(prod).sum()), misfit_added_rad=misfit_added,
                singular_after=int(sing1.sum()),
                across_after=int((sing1 & turn[np.maximum(hol, 0)] & (_EAXIS[np.maximum(hol, 0)] != along)).sum()),
                complex_after=int((sing1 & (_ETYPE[np.maximum(hol, 0)] == 3)).sum()),
                folds_after=int((edge_cost(prod)[eb] > 0).sum()),
                zipper_after=int((vcls == VERTEX_CLASSES.index("zipper")).sum()),
                invalid_nodes_after=int((vcls == VERTEX_CLASSES.index("invalid")).sum()))
    return match, info


def touching_edges(mesh, tet_frames, face_match: np.ndarray | None = None) -> np.ndarray:
    """Interior singular edges with an end on the boundary whose turn axis is more than 45° from
    the boundary normal there (:func:`tangent_axes`): ``(K,)`` edge ids."""
    from .cut import tet_charts

    ch = tet_charts(mesh, tet_frames, face_match)
    edges = mesh.edges.cpu().numpy()
    tang = tangent_axes(mesh, ch.frames[ch.edge_start_tet], edges, ch.edge_holonomy < 0)
    turn = ch.singular_edge & ch.edge_meshable
    return np.nonzero(turn & tang[np.arange(edges.shape[0]), np.maximum(ch.edge_axis, 0)])[0]


def _holonomy_of(walks, e_ids, face_rot):
    """Products of the walks of edges ``e_ids`` (the fan's transport on boundary edges)."""
    out = np.empty(len(e_ids), np.int64)
    for n, e in enumerate(np.asarray(e_ids).tolist()):
        a, b = walks.ptr[e], walks.ptr[e + 1]
        fr = face_rot[walks.face[a:b]]
        R = np.where(walks.forward[a:b], fr, GROUP_INV[fr])
        acc = 0
        for r in R.tolist():
            acc = GROUP_MUL[r, acc]
        out[n] = acc
    return out
