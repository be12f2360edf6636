"""The lattice points of a map's tets and their stars (:func:`~.extract.extract_hexes`' first steps).

The integer points in the closed image of every usable tet, found in chunks of whole tets with
exact integer barycentric signs (:mod:`.predicates`); the star of each point (the tets whose
image holds it, followed across faces by the transitions, ``G Q + s``); the singular edges whose
points' stars do not close (the lattice is broken there). The elements of O act on integer
points by :func:`_apply` (a signed permutation: a gather and a product).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .predicates import _barycentric_signs_int

__all__: list[str] = []

_POINT_CHUNK = 1 << 21  # lattice candidates classified together (whole tets per chunk)


# ----------------------------------------------------------------------------- lattice points
@dataclass
class _Lattice:
    """Lattice points in the closed images of the usable tets.

    A point is ``k (+ 1/2 if half)`` in lattice units, ``Q = k S + off`` scaled. Occurrence ``i``:
    tet ``tet[i]``, lattice coordinates ``k[i] (3,)``, ``zero[i, j]`` iff it lies on face ``j``.
    ``lo, dims, base, slot``: per-tet bounding boxes and a perfect hash ``(t, k) -> occurrence``.
    """

    off: int
    lo: np.ndarray
    dims: np.ndarray
    base: np.ndarray
    slot: np.ndarray
    tet: np.ndarray
    k: np.ndarray
    zero: np.ndarray

    def lookup(self, t: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Occurrence index of lattice point ``k (N, 3)`` in tet ``t (N,)``, -1 where absent."""
        out = np.full(t.shape[0], -1, np.int64)
        ok = t >= 0
        tt = np.where(ok, t, 0)
        rel = k - self.lo[tt]
        d = self.dims[tt]
        ok &= ((rel >= 0) & (rel < d)).all(1)
        idx = np.nonzero(ok)[0]
        if idx.size:
            r, dd = rel[idx], d[idx]
            local = (r[:, 0] * dd[:, 1] + r[:, 1]) * dd[:, 2] + r[:, 2]
            out[idx] = self.slot[self.base[tt[idx]] + local]
        return out


def _bbox(U: np.ndarray):
    """Per-tet min and max corner ``(T, 3)`` (elementwise over the 4 corners: numpy's reduction
    over a length-4 axis is several times slower)."""
    mn = np.minimum(np.minimum(U[:, 0], U[:, 1]), np.minimum(U[:, 2], U[:, 3]))
    mx = np.maximum(np.maximum(U[:, 0], U[:, 1]), np.maximum(U[:, 2], U[:, 3]))
    return mn, mx


def _bbox_counts(bbox, g: int, off: int):
    """Lattice points ``k 2**g + off`` in each tet's bounding box: ``lo (T, 3)``, ``dims (T, 3)``,
    their product as float64 (no overflow). Shifts are floor divisions by ``S = 2**g``."""
    mn, mx = bbox
    lo = -((off - mn) >> g)          # ceil((mn - off) / S)
    hi = (mx - off) >> g             # floor((mx - off) / S)
    dims = np.maximum(hi - lo + 1, 0)
    return lo, dims, dims.astype(np.float64).prod(axis=1)


def _lattice(U: np.ndarray, bbox, usable: np.ndarray, g: int, half: bool) -> _Lattice:
    S = 1 << g
    off = S // 2 if half else 0
    lo, dims, _ = _bbox_counts(bbox, g, off)
    dims = np.where(usable[:, None], dims, 0)
    count = dims.prod(axis=1)
    base = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
    total = int(base[-1])
    slot = np.full(total, -1, np.int64)
    tets_out, k_out, zero_out, slots_out = [], [], [], []
    tids = np.nonzero(count)[0]
    if tids.size:  # chunks of whole tets with about _POINT_CHUNK candidate points each
        cid = (np.cumsum(count[tids]) - 1) // _POINT_CHUNK
        bounds = np.concatenate([[0], np.nonzero(np.diff(cid))[0] + 1, [tids.size]])
    else:
        bounds = np.zeros(1, np.int64)
    for a, b in zip(bounds[:-1], bounds[1:]):
        ids = tids[a:b]
        c = count[ids]
        tt = np.repeat(ids, c)
        local = np.arange(tt.size, dtype=np.int64) - np.repeat(base[ids] - base[ids[0]], c)
        d = dims[tt]
        rel = np.stack([local // (d[:, 1] * d[:, 2]), (local // d[:, 2]) % d[:, 1], local % d[:, 2]], axis=1)
        k = lo[tt] + rel
        s = _barycentric_signs_int(U[tt], k * S + off)
        keep = (s >= 0).all(axis=1)
        tets_out.append(tt[keep])
        k_out.append(k[keep])
        zero_out.append(s[keep] == 0)
        slots_out.append(base[tt[keep]] + local[keep])
    if tets_out:
        tet, k, zero, slots = (np.concatenate(x) for x in (tets_out, k_out, zero_out, slots_out))
    else:
        tet, k, zero, slots = (np.zeros(0, np.int64), np.zeros((0, 3), np.int64),
                               np.zeros((0, 4), bool), np.zeros(0, np.int64))
    slot[slots] = np.arange(tet.size, dtype=np.int64)
    return _Lattice(off=off, lo=lo, dims=dims, base=base, slot=slot, tet=tet, k=k, zero=zero)


def _apply(G: np.ndarray, rot: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``G[rot] @ x`` for ``rot (N,)``, ``x (N, 3)`` or ``(N, k, 3)`` (int64).

    Each element of O is a signed permutation, ``(G x)_i = sign_i x[perm_i]``: a gather and a
    product on the rows whose element is not the identity (most rows of a combed map).
    """
    nz = np.nonzero(rot != 0)[0]
    if not nz.size:
        return x.copy()
    perm = np.argmax(G != 0, axis=2)                         # (24, 3)
    sign = np.take_along_axis(G, perm[:, :, None], axis=2)[:, :, 0]
    P, Sg = perm[rot[nz]], sign[rot[nz]]
    out = x.copy()
    if x.ndim == 2:
        out[nz] = np.take_along_axis(x[nz], P, axis=1) * Sg
    else:
        out[nz] = np.take_along_axis(x[nz], P[:, None, :], axis=2) * Sg[:, None, :]
    return out


def _cross_face(G, mult, inv, A, b, gf, shift_f, from_t0):
    """A walk's chart map ``x -> G[A] x + b`` (rows ``(N,)``, ``(N, 3)``) carried across faces with
    transitions ``gf (N,)``, ``shift_f (N, 3)`` (``t0 -> t1``: ``G x + s``), entered from ``t0``
    (``from_t0``) or from ``t1``: the new ``(A, b)``."""
    A_new = np.where(from_t0, mult[A, inv[gf]], mult[A, gf])
    b_new = np.where(from_t0[:, None], b - _apply(G, A_new, shift_f), b + _apply(G, A, shift_f))
    return A_new, b_new


# ----------------------------------------------------------------------------- stars
def _transport(G, inv, rot_f, shift_f, from_t0, Q):
    """Scaled point ``Q`` across faces: ``G Q + s`` from ``t0`` to ``t1``, ``G^T (Q - s)`` back."""
    fwd = _apply(G, rot_f, Q) + shift_f
    back = _apply(G, inv[rot_f], Q - shift_f)
    return np.where(from_t0[:, None], fwd, back)


def _stars(lat: _Lattice, g, G, inv, tet_faces, ft, face_good, face_rot, shiftS, tainted):
    """Connected components of the occurrences of ``lat`` across good faces.

    Returns ``label (M,)``, per component: ``rep (C,)`` occurrence in the lowest tet,
    ``broken (C,)`` (on a face towards an unusable tet or a mismatched seam, or in a tainted tet),
    ``multi (C,)`` (two occurrences in one tet).
    """
    M = lat.tet.size
    rows, ks = np.nonzero(lat.zero)
    t = lat.tet[rows]
    f = tet_faces[t, ks]
    pair = ft[f]
    from_t0 = pair[:, 0] == t
    nbr = np.where(from_t0, pair[:, 1], pair[:, 0])
    good = face_good[f]
    Q = (lat.k[rows] << g) + lat.off
    Qn = _transport(G, inv, face_rot[f], shiftS[f], from_t0, Q)
    kn = (Qn - lat.off) >> g
    j = np.where(good, lat.lookup(np.where(good, nbr, -1), kn), -1)
    linked = j >= 0
    broken_occ = tainted[lat.tet].copy()
    bad = (nbr >= 0) & ~linked          # towards an unusable tet, a broken seam, or a missing point
    np.logical_or.at(broken_occ, rows[bad], True)
    graph = coo_matrix((np.ones(int(linked.sum()), np.int8), (rows[linked], j[linked])), shape=(M, M))
    C, label = connected_components(graph, directed=False)
    order = np.lexsort((lat.tet, label))                  # by component, then tet
    first = np.ones(M, bool)
    first[1:] = label[order][1:] != label[order][:-1]
    rep = order[first]
    same = np.zeros(M, bool)
    same[1:] = ~first[1:] & (lat.tet[order][1:] == lat.tet[order][:-1])
    multi = np.zeros(C, bool)
    np.logical_or.at(multi, label[order][same], True)
    broken = np.zeros(C, bool)
    np.logical_or.at(broken, label, broken_occ)
    return label, rep, broken, multi


# ----------------------------------------------------------------------------- singular edges
def _bad_singular_edges(tets, tet_edges, tet_faces, ft, face_edges, U, G, mult, inv, face_rot, shiftS, usable,
                        seam_ok, S):
    """Interior edges whose holonomy is not a valid singularity: ``(K, 2)`` vertex pairs.

    Around an interior edge whose ring of tets is usable and seamless, the composed transition
    ``H`` (start tet's chart to itself) fixes the edge's endpoints, so it is a rotation about the
    edge's line. The edge is regular when ``H`` is the identity, a valid singular edge when ``H``
    is a quarter or half turn about a coordinate axis and the edge lies on an integer line along
    that axis (HEXMESH.md step 7), and invalid otherwise (a complex singularity, or a singular
    edge off its integer line): an invalid map that folds around it. Only edges of faces with a
    non-identity rotation can be singular; their rings are traversed all at once, one tet per
    iteration.
    """
    from ..mesh.simplex import pair_list

    interior = (ft >= 0).all(axis=1)
    cand = np.unique(face_edges[interior & (face_rot != 0)].ravel())
    if not cand.size:
        return np.zeros((0, 2), np.int64)
    pairs = np.array(pair_list(4))                               # (6, 2) local vertex pairs
    others = np.array([sorted(set(range(4)) - set(p)) for p in pairs.tolist()])
    edge_ids, first = np.unique(tet_edges.ravel(), return_index=True)
    first = first[np.searchsorted(edge_ids, cand)]
    t_start, p_start = first // 6, first % 6
    ends = tets[t_start[:, None], pairs[p_start]]                # (K, 2) global endpoint ids
    t = t_start.copy()
    f = tet_faces[t, others[p_start, 0]]
    rot = np.zeros(t.size, np.int64)
    b = np.zeros((t.size, 3), np.int64)
    act = np.nonzero(usable[t])[0]
    bad = np.zeros(t.size, bool)
    # every candidate edge's walk advances together, one tet per step (batched over the edges):
    # a walk closes or leaves through the boundary within its edge's valence
    for _ in range(int(np.bincount(tet_edges.ravel()).max()) + 1):
        if not act.size:
            break
        ta, fa = t[act], f[act]
        pair = ft[fa]
        from_t0 = pair[:, 0] == ta
        nbr = np.where(from_t0, pair[:, 1], pair[:, 0])
        go = (nbr >= 0) & seam_ok[fa]                           # boundary edges are skipped
        go[go] &= usable[nbr[go]]
        act, ta, fa, from_t0, nbr = act[go], ta[go], fa[go], from_t0[go], nbr[go]
        rot[act], b[act] = _cross_face(G, mult, inv, rot[act], b[act], face_rot[fa], shiftS[fa], from_t0)
        t[act] = nbr
        closed = nbr == t_start[act]
        done = act[closed]
        if done.size:
            H = G[rot[done]]
            diag = np.einsum("nii->ni", H)
            axis_ok = (diag == 1).sum(axis=1) == 1                # a quarter or half turn about an axis
            ax = np.argmax(diag == 1, axis=1)
            loc = (tets[t_start[done]] == ends[done, :1]).argmax(axis=1)
            a = U[t_start[done], loc]                            # an endpoint in the start chart
            on_line = ((a & (S - 1) == 0) | (np.arange(3)[None, :] == ax[:, None])).all(axis=1)
            bad[done] = (rot[done] != 0) & ~(axis_ok & on_line)
        act = act[~closed]
        # the next face of the ring: the new tet's other face through the edge
        ta = t[act]
        p_loc = np.argmax(tet_edges[ta] == cand[act][:, None], axis=1)
        fk = tet_faces[ta[:, None], others[p_loc]]
        f[act] = np.where(fk[:, 0] == f[act], fk[:, 1], fk[:, 0])
    return ends[bad]
