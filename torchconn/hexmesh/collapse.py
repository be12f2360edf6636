"""Edge collapses that keep the face matchings: the structure stage's answer to collapsed tets.

A tet is *collapsed* when the seamless problem's constraints send two of its corners to one
parametric point whatever the unknowns (:meth:`~.seamless.SeamlessProblem.flat_tets`): two
singular or feature curves, or a curve and a boundary plane, that the constraints make meet
along a tet edge. No split opens it (the midpoint meets the same constraints); the map wants
the two vertices to be one. :func:`collapse_edge` merges them in the tet mesh:

* the tets around the edge ``(a, b)`` disappear; every other tet with ``b`` gets ``a`` instead;
  the merged vertex sits at ``a``, at ``b`` or at the midpoint — the first of these (in the
  order that keeps boundary, feature curves and CAD corners in place) at which every tet keeps
  a positive volume; the mesh must stay a manifold (the :class:`~torchconn.mesh.TetMesh` checks);
* the face matchings are carried: a face between two surviving tets keeps its matching (with
  ``F_t0 g_f ~ F_t1``, :func:`~.cut.face_matchings`); a vanished tet ``T = (a, b, x, y)`` glues
  its neighbours ``P`` across ``(a, x, y)`` and ``Q`` across ``(b, x, y)``, which meet in the new
  face with the transported matching ``g_PQ = g_PT g_TQ``. The holonomy of a cycle that avoids
  the vanished tets is unchanged, so every singular edge away from ``(a, b)`` keeps its type;
* the CAD tags follow (triangles, feature lines, corners; a collapse that would move a CAD
  corner, or glue two boundary pieces, is refused).

A refused collapse is reported, never forced. The vertex ``b`` is removed (the vertices after it
shift down by one; ``vertex_map`` says where each old vertex went).
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["collapse_edge", "collapse_edges"]


def _oriented(face_match, face_tets, fidx, a):
    """The matching of face ``fidx`` oriented from tet ``a`` to the other one (``fidx`` and ``a``
    scalars or arrays of one shape)."""
    from .cut import GROUP_INV

    g = np.asarray(face_match)[fidx]
    return np.where(face_tets[fidx, 0] == a, g, GROUP_INV[g])


def _signed_volumes(X: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = X[tets]
    return np.einsum("ti,ti->t", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])


def _kernel_point(X: np.ndarray, tets: np.ndarray, a: int, sign: np.ndarray) -> np.ndarray | None:
    """A position of vertex ``a`` at which every tet of ``tets (k, 4)`` (each with ``a``) has the
    volume sign ``sign (k,)``: each volume is affine in ``a``'s position, so this is a linear
    program (the Chebyshev centre of the star's kernel, :func:`scipy.optimize.linprog`); ``None``
    when the kernel is empty."""
    from scipy.optimize import linprog

    Y = X.copy()
    Y[a] = 0.0
    h = _signed_volumes(Y, tets)
    g = np.empty((tets.shape[0], 3))
    for i in range(3):
        Y[a] = np.eye(3)[i]
        g[:, i] = _signed_volumes(Y, tets) - h
    g *= sign[:, None]
    h = h * sign
    norm = np.linalg.norm(g, axis=1)
    # max s  s.t.  g p + h >= s |g|   <=>   -g p + |g| s <= h
    lo, hi = X[np.unique(tets)].min(0), X[np.unique(tets)].max(0)
    res = linprog(c=[0, 0, 0, -1.0], A_ub=np.c_[-g, norm], b_ub=h,
                  bounds=[(lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2]), (None, None)], method="highs")
    if res.status != 0 or res.x[3] <= 1e-9 * float(np.abs(hi - lo).max()):
        return None
    return res.x[:3]


def collapse_edge(mesh, tet_frames, a: int, b: int, face_match: np.ndarray):
    """Collapse the edge ``(a, b)`` of ``mesh`` (module docstring).

    Args:
        mesh: a ``TetMesh``; tet_frames: ``(T, 3, 3)``; ``a, b``: the edge's vertices;
        face_match: ``(F,)`` the face matchings to carry.

    Returns:
        ``(mesh, tet_frames, parent (T',), face_match (F',), vertex_map (V,))`` with ``vertex_map``
        the new index of each old vertex (``b``'s is ``a``'s), or ``None`` when the collapse is
        refused (it would invert a tet, break the manifold, move a CAD corner or a boundary or
        feature vertex off its place).
    """
    from ..mesh.cad import cad_tags_from_elements
    from ..mesh.tet import MeshError, TetMesh
    from .cut import GROUP_INV, GROUP_MUL

    tets = mesh.tets.cpu().numpy()
    X = mesh.vertices.detach().cpu().double().numpy()
    V, T = X.shape[0], tets.shape[0]
    cad = getattr(mesh, "cad", None)
    bv = np.zeros(V, bool)
    bv[mesh.boundary_vertices.cpu().numpy()] = True
    fv = np.zeros(V, bool)
    corner = np.zeros(V, bool)
    if cad is not None:
        fv[cad.feature_edges.cpu().numpy().reshape(-1)] = True
        corner[cad.corner_vertices.cpu().numpy()] = True
    rank = lambda v: 4 * corner[v] + 2 * fv[v] + bv[v]  # noqa: E731 - how pinned a vertex is
    if rank(b) > rank(a):
        a, b = b, a
    if corner[b] or (bv[b] and not bv[a]) or (fv[b] and not fv[a]):
        return None
    has_a, has_b = (tets == a).any(1), (tets == b).any(1)
    gone = has_a & has_b
    keep = ~gone
    new_tets = tets[keep].copy()
    new_tets[new_tets == b] = a
    # where the merged vertex goes: a first; b or the midpoint only when a is no more pinned than b
    spots = [X[a]] if rank(a) > rank(b) else [X[a], X[b]] if bv[a] else [X[a], X[b], 0.5 * (X[a] + X[b])]
    moved = np.nonzero((new_tets == a).any(1))[0]
    old_vol = _signed_volumes(X, tets[keep][moved])
    where = None
    for p in spots:
        Y = X.copy()
        Y[a] = p
        vol = _signed_volumes(Y, new_tets[moved])
        if (np.sign(vol) == np.sign(old_vol)).all() and (np.abs(vol) > 1e-12 * np.abs(old_vol).max()).all():
            where = p
            break
    if where is None and not bv[a] and not bv[b]:
        where = _kernel_point(X, new_tets[moved], a, np.sign(old_vol))
    if where is None:
        return None
    Y = X.copy()
    Y[a] = where
    vmap = np.arange(V) - (np.arange(V) > b)
    vmap[b] = vmap[a]
    Ynew = np.delete(Y, b, axis=0)
    new_tets = vmap[new_tets]
    try:
        new = TetMesh(torch.as_tensor(Ynew, dtype=mesh.vertices.dtype), torch.as_tensor(new_tets),
                      unreferenced="error", dtype=mesh.vertices.dtype)
    except MeshError:
        return None
    bf = mesh.boundary_faces.cpu().numpy()
    if new.boundary_faces.shape[0] != bf.shape[0] - int(((bf == a).any(1) & (bf == b).any(1)).sum()):
        return None  # two boundary pieces glued (or a boundary face lost): not a plain collapse
    parent = np.nonzero(keep)[0]
    Fr = torch.as_tensor(tet_frames)[torch.as_tensor(parent)]
    # ---- matchings
    old_ft = mesh.face_tets.cpu().numpy()
    old_tf = mesh.tet_faces.cpu().numpy()
    fm = np.asarray(face_match)
    # the old interior faces by their (unordered) pair of tets, as sorted keys
    inner = np.nonzero((old_ft >= 0).all(1))[0]
    lo, hi = old_ft[inner].min(1), old_ft[inner].max(1)
    order = np.argsort(lo * T + hi)
    old_keys, old_faces = (lo * T + hi)[order], inner[order]
    # through a vanished tet: its two faces without the edge's other end glue its neighbours
    glue = {}
    faces_old = mesh.faces.cpu().numpy()
    for t in np.nonzero(gone)[0]:
        fa = fb = None
        for f in old_tf[t]:
            vs = faces_old[f]
            if b not in vs and a in vs:
                fa = f
            elif a not in vs and b in vs:
                fb = f
        nb = lambda f: int(old_ft[f, 1] if old_ft[f, 0] == t else old_ft[f, 0])  # noqa: E731
        if fa is None or fb is None or min(old_ft[fa].min(), old_ft[fb].min()) < 0:
            continue
        P, Q = nb(fa), nb(fb)
        g = int(GROUP_MUL[_oriented(fm, old_ft, fa, P), _oriented(fm, old_ft, fb, t)])
        glue[(P, Q)] = g
    nft = new.face_tets.cpu().numpy()
    new_fm = np.zeros(nft.shape[0], np.int64)
    nf = np.nonzero((nft >= 0).all(1))[0]
    P, Q = parent[nft[nf, 0]], parent[nft[nf, 1]]
    k = np.minimum(P, Q) * T + np.maximum(P, Q)
    if old_keys.size:
        pos = np.minimum(np.searchsorted(old_keys, k), old_keys.size - 1)
        hit = old_keys[pos] == k
    else:
        pos, hit = np.zeros(k.size, np.int64), np.zeros(k.size, bool)
    new_fm[nf[hit]] = _oriented(fm, old_ft, old_faces[pos[hit]], P[hit])
    for f, p, q in zip(nf[~hit].tolist(), P[~hit].tolist(), Q[~hit].tolist()):  # loop over the glued faces (a few)
        if (p, q) in glue:
            new_fm[f] = glue[(p, q)]
        elif (q, p) in glue:
            new_fm[f] = GROUP_INV[glue[(q, p)]]
        else:  # two tets that met only through several vanished tets: not handled
            return None
    # ---- CAD tags
    if cad is not None:
        fs = cad.face_surface.cpu().numpy()
        tf = np.nonzero(fs >= 0)[0]
        tris = vmap[faces_old[tf]]
        ok = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
        lines = vmap[cad.feature_edges.cpu().numpy()]
        lok = lines[:, 0] != lines[:, 1]
        try:
            new.cad = cad_tags_from_elements(new, tris[ok], fs[tf][ok], lines[lok],
                                             cad.feature_edge_curve.cpu().numpy()[lok],
                                             vmap[cad.corner_vertices.cpu().numpy()], cad.corner_point,
                                             source="collapse")
        except MeshError:
            return None
    return new, Fr, parent, new_fm, vmap


def collapse_edges(mesh, tet_frames, pairs: np.ndarray, face_match: np.ndarray):
    """Collapse the edges with vertex pairs ``pairs (K, 2)`` one after another (vertex indices
    followed through the earlier collapses; a pair already merged is skipped).

    Returns ``(mesh, tet_frames, parent (T',), face_match, counts)`` with ``counts``
    ``{"collapsed": n, "refused": n}``.
    """
    Fr = torch.as_tensor(tet_frames)
    parent = np.arange(mesh.n_tets)
    vmap = np.arange(mesh.n_vertices)
    counts = {"collapsed": 0, "refused": 0}
    for p, q in np.asarray(pairs, np.int64).reshape(-1, 2):
        a, b = int(vmap[p]), int(vmap[q])
        if a == b:
            continue
        out = collapse_edge(mesh, Fr, a, b, face_match)
        if out is None:
            counts["refused"] += 1
            continue
        mesh, Fr, par, face_match, vm = out
        parent = parent[par]
        vmap = vm[vmap]
        counts["collapsed"] += 1
    return mesh, Fr, parent, face_match, counts
