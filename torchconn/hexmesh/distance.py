"""Distances between triangle surfaces: exact point-to-triangle distances and the certified
two-sided Hausdorff distance that :func:`~.quality.hex_quality` reports.

The distance is computed by adaptive sampling with exact
point-to-triangle distances (libigl's ``point_mesh_squared_distance``, an AABB tree): for each
direction the source triangles are evaluated at their vertices and centroids and split 1-to-4
where a certified upper bound on the distance over the triangle exceeds the largest sampled
distance by more than :data:`HAUSDORFF_REL_ACCURACY` of it or :data:`HAUSDORFF_ABS_ACCURACY_REL`
of the diagonal. The bound uses that the distance to a convex target piece is convex, so its
maximum over a source triangle is attained at a vertex: a target triangle closest to a vertex
or the centroid; two such triangles that share a side, lie in one plane and form a convex
quadrilateral; or, where the source triangle projects into the disk a flat vertex fan of the
target covers, that fan's plane (where the surfaces coincide, as on planar CAD faces, the
refinement then stops at once instead of following every target edge). ``hausdorff_rel`` is the
largest sampled distance (a lower bound), ``hausdorff_upper_rel`` the certified upper bound:
the true value lies between them; ``hausdorff_evaluations`` counts the point queries (at most
:data:`HAUSDORFF_MAX_EVALUATIONS` per direction).
"""
from __future__ import annotations

import numpy as np

__all__ = ["HAUSDORFF_REL_ACCURACY", "HAUSDORFF_ABS_ACCURACY_REL", "HAUSDORFF_MAX_EVALUATIONS"]

#: The sampled Hausdorff distance is refined until the certified upper bound is within this
#: fraction of it ...
HAUSDORFF_REL_ACCURACY = 0.02
#: ... or within this fraction of the input's diagonal (1% of the ``good`` threshold), which
#: ends the refinement where the distance is (near) zero.
HAUSDORFF_ABS_ACCURACY_REL = 1e-4
#: At most this many distance evaluations per direction; past it the refinement stops and the
#: (then looser) certified upper bound says how far off the sampled value may be.
HAUSDORFF_MAX_EVALUATIONS = 4_000_000
#: Unit normals closer than this count as parallel when the Hausdorff bounds treat adjacent
#: target triangles as one plane (the residual tilt is added to the bound as slack).
FLAT_NORMAL_TOL = 1e-9
#: Rows per block in the vectorized per-hex and per-triangle computations (bounds the memory:
#: about 0.3 GB per block for the Hausdorff bounds).
_CHUNK = 100_000


def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", x, y)


def _point_segment_distance(q: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Distance ``(K,)`` from points ``q (K, 3)`` to segments ``[u, v]`` (a point when ``u = v``)."""
    uv = v - u
    L2 = _dot(uv, uv)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(L2 > 0, np.clip(_dot(q - u, uv) / L2, 0.0, 1.0), 0.0)
    return np.linalg.norm(q - u - t[:, None] * uv, axis=-1)


def _point_triangle_distance(q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance ``(...)`` from points ``q (..., 3)`` to triangles ``(a, b, c)``
    (broadcast against each other).

    The closest point by Voronoi regions of the vertices, sides and face (Ericson, *Real-Time
    Collision Detection*, 5.1.5); a (near) zero-area triangle is measured to its sides.
    """
    q, a, b, c = np.broadcast_arrays(q, a, b, c)
    shape = q.shape[:-1]
    q, a, b, c = (x.reshape(-1, 3) for x in (q, a, b, c))
    ab, ac = b - a, c - a
    ap, bp, cp = q - a, q - b, q - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(invalid="ignore", divide="ignore"):
        den = va + vb + vc
        v, w = vb / den, vc / den  # face region
        # the regions in reverse order of precedence, each overriding the ones before
        e1, e2 = d4 - d3, d5 - d6
        m = (va <= 0) & (e1 >= 0) & (e2 >= 0)  # side bc
        wbc = e1 / (e1 + e2)
        v, w = np.where(m, 1.0 - wbc, v), np.where(m, wbc, w)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)  # side ac
        v, w = np.where(m, 0.0, v), np.where(m, d2 / (d2 - d6), w)
        m = (d6 >= 0) & (d5 <= d6)  # vertex c
        v, w = np.where(m, 0.0, v), np.where(m, 1.0, w)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)  # side ab
        v, w = np.where(m, d1 / (d1 - d3), v), np.where(m, 0.0, w)
        m = (d3 >= 0) & (d4 <= d3)  # vertex b
        v, w = np.where(m, 1.0, v), np.where(m, 0.0, w)
        m = (d1 <= 0) & (d2 <= 0)  # vertex a
        v, w = np.where(m, 0.0, v), np.where(m, 0.0, w)
    d = np.linalg.norm(ap - v[:, None] * ab - w[:, None] * ac, axis=-1)
    # (near) zero-area triangles: the face region's round-off can pick a wrong side; a triangle
    # thinner than 1e-12 of its sides is measured to its sides (off by at most that width)
    n2 = np.einsum("ij,ij->i", *(np.cross(ab, ac),) * 2)
    bad = ~np.isfinite(d) | (n2 <= 1e-24 * _dot(ab, ab) * _dot(ac, ac))
    if bad.any():
        qa, aa, ba, ca = q[bad], a[bad], b[bad], c[bad]
        d[bad] = np.minimum(np.minimum(_point_segment_distance(qa, aa, ba), _point_segment_distance(qa, ba, ca)),
                            _point_segment_distance(qa, ca, aa))
    return d.reshape(shape)


class _Target:
    """A target surface ``(vertices, triangles)`` for distance queries, with what the certified
    bounds of :func:`_one_sided_hausdorff` need: unit normals, and per vertex whether its fan is
    flat (every incident normal within :data:`FLAT_NORMAL_TOL` of the mean, angles summing to
    ``2 pi``) with the radius ``rho`` of the disk around it that the fan covers."""

    def __init__(self, v: np.ndarray, f: np.ndarray):
        from scipy.spatial import cKDTree

        self.v = np.ascontiguousarray(v, dtype=np.float64)
        self.f = np.ascontiguousarray(f, dtype=np.int64)
        self.tri = self.v[self.f]  # (F, 3, 3)
        n = np.cross(self.tri[:, 1] - self.tri[:, 0], self.tri[:, 2] - self.tri[:, 0])
        area2 = np.linalg.norm(n, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.normal = np.where(area2[:, None] > 0, n / area2[:, None], 0.0)
        V = self.v.shape[0]
        corner_v = self.f.reshape(-1)
        corner_t = np.repeat(np.arange(self.f.shape[0]), 3)
        a = self.v[np.roll(self.f, -1, axis=1).reshape(-1)]
        b = self.v[np.roll(self.f, -2, axis=1).reshape(-1)]
        w = self.v[corner_v]
        nsum = np.zeros((V, 3))
        np.add.at(nsum, corner_v, n[corner_t])
        nlen = np.linalg.norm(nsum, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            nw = nsum / nlen[:, None]
        dev = np.zeros(V)
        np.maximum.at(dev, corner_v, np.linalg.norm(self.normal[corner_t] - nw[corner_v], axis=1))
        u, t = a - w, b - w
        ang = np.arctan2(np.linalg.norm(np.cross(u, t), axis=1), np.einsum("ij,ij->i", u, t))
        angle_sum = np.bincount(corner_v, weights=ang, minlength=V)
        rho = np.full(V, np.inf)
        np.minimum.at(rho, corner_v, _point_segment_distance(w, a, b))  # distance to the opposite side
        flat = (nlen > 0) & (dev <= FLAT_NORMAL_TOL) & (np.abs(angle_sum - 2 * np.pi) <= 1e-9) & np.isfinite(rho)
        self.flat_vertex = np.nonzero(flat)[0]
        self.flat_normal, self.flat_rho = nw[self.flat_vertex], rho[self.flat_vertex]
        self.flat_slack = 2.0 * dev[self.flat_vertex] * rho[self.flat_vertex]
        self.flat_tree = cKDTree(self.v[self.flat_vertex]) if self.flat_vertex.size else None

    def dist(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact distances ``(Q,)`` of points ``q (Q, 3)`` to the surface and the closest triangles."""
        import igl

        sq, idx, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(q, dtype=np.float64), self.v, self.f)
        return np.sqrt(np.maximum(sq, 0.0)), np.asarray(idx, dtype=np.int64).reshape(-1)

    def upper_bound(self, tri: np.ndarray, cand: np.ndarray, enough: float = -np.inf) -> np.ndarray:
        """Certified upper bounds ``(M,)`` on the distance to the surface over each source
        triangle ``tri (M, 3, 3)``, given candidate target triangles ``cand (M, J)``.

        The smallest of: for one candidate ``t_j``, the largest vertex distance to it (the
        distance to one triangle is convex); for two candidates sharing a side, coplanar, whose
        union is convex, the largest vertex distance to the union; where the triangle's vertices
        project into the disk a flat vertex fan covers, the largest distance to the fan's plane
        (both convex too). The coplanarity tolerance is added as slack. The pair and fan bounds
        are only tried on triangles whose bound is still above ``enough``.
        """
        M, J = cand.shape
        cand = np.sort(cand, axis=1)
        new = np.ones((M, J), dtype=bool)
        new[:, 1:] = cand[:, 1:] != cand[:, :-1]  # a repeated candidate copies the previous column
        t = self.tri[cand]  # (M, J, 3, 3)
        r, j = np.nonzero(new)
        d = np.empty((M, J, 3))
        d[r, j] = _point_triangle_distance(tri[r], t[r, j, None, 0], t[r, j, None, 1], t[r, j, None, 2])
        for k in range(1, J):
            d[:, k] = np.where(new[:, k, None], d[:, k], d[:, k - 1])
        ub = d.max(axis=2).min(axis=1)  # (M,) single candidates
        rows = np.nonzero(ub > enough)[0]
        if rows.size:
            ub[rows] = np.minimum(ub[rows], self._pair_bound(cand[rows], t[rows], d[rows]))
            rows = rows[ub[rows] > enough]
        if rows.size and self.flat_tree is not None:
            ub[rows] = np.minimum(ub[rows], self._fan_bound(tri[rows]))
        return ub

    def _pair_bound(self, cand: np.ndarray, t: np.ndarray, d: np.ndarray) -> np.ndarray:
        """The bound over the union of two candidates ``(M,)`` (``inf`` where no pair qualifies);
        ``t (M, J, 3, 3)`` the candidates' corners, ``d (M, J, 3)`` the source vertices' distances."""
        M, J = cand.shape
        out = np.full(M, np.inf)
        fv = self.f[cand]  # (M, J, 3)
        r = np.arange(M)
        for j in range(J):
            for k in range(j + 1, J):
                eq = fv[:, j, :, None] == fv[:, k, None, :]  # (M, 3, 3): vertex of t_j == vertex of t_k
                in_k, in_j = eq.any(axis=2), eq.any(axis=1)  # vertices of t_j in t_k, of t_k in t_j
                nj = self.normal[cand[:, j]]
                parallel = np.linalg.norm(nj - self.normal[cand[:, k]], axis=1) <= FLAT_NORMAL_TOL
                ok = (in_k.sum(axis=1) == 2) & parallel
                if not ok.any():
                    continue
                oj, ok_ = t[r, j, np.argmin(in_k, axis=1)], t[r, k, np.argmin(in_j, axis=1)]  # opposite vertices
                s_idx = np.argsort(~in_k, axis=1, kind="stable")[:, :2]
                s0, s1 = t[r, j, s_idx[:, 0]], t[r, j, s_idx[:, 1]]  # the shared side

                def side(u, v, x):  # which side of the line u-v (in the plane of t_j) x lies on
                    return np.einsum("ij,ij->i", np.cross(v - u, x - u), nj)

                # a convex quadrilateral: the opposite vertices on either side of the shared side,
                # the shared side's ends on either side of the line between the opposite vertices
                ok &= (side(s0, s1, oj) * side(s0, s1, ok_) < 0) & (side(oj, ok_, s0) * side(oj, ok_, s1) <= 0)
                slack = 2.0 * np.abs(np.einsum("ij,ij->i", ok_ - s0, nj))  # t_k's tilt out of t_j's plane
                pair = np.minimum(d[:, j], d[:, k]).max(axis=1) + slack
                out = np.where(ok, np.minimum(out, pair), out)
        return out

    def _fan_bound(self, tri: np.ndarray) -> np.ndarray:
        """The bound by the flat fan nearest to each triangle's centroid ``(M,)`` (``inf`` where
        the triangle's vertices do not all project into the fan's disk)."""
        _, w = self.flat_tree.query(tri.mean(axis=1))
        c = self.v[self.flat_vertex[w]]
        n = self.flat_normal[w]
        rel = tri - c[:, None, :]
        off = np.einsum("mki,mi->mk", rel, n)  # (M, 3)
        inplane = np.linalg.norm(rel - off[..., None] * n[:, None, :], axis=2)
        inside = (inplane <= self.flat_rho[w][:, None]).all(axis=1)
        return np.where(inside, np.abs(off).max(axis=1) + self.flat_slack[w], np.inf)


def _one_sided_hausdorff(src_v: np.ndarray, src_f: np.ndarray, dst: _Target,
                         tol_abs: float) -> tuple[float, float, int]:
    """``max over the source surface of the distance to the target surface``, by adaptive
    sampling (module docstring): ``(lower bound, certified upper bound, distance evaluations)``."""
    used = np.unique(src_f)
    dv_all, iv_all = np.zeros(src_v.shape[0]), np.zeros(src_v.shape[0], np.int64)
    dv_all[used], iv_all[used] = dst.dist(src_v[used])
    tri = src_v[src_f]  # (M, 3, 3)
    dv, iv = dv_all[src_f], iv_all[src_f]  # (M, 3)
    evals = used.size
    lower = float(dv.max()) if dv.size else 0.0
    upper_done = lower
    kids = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])
    while tri.shape[0]:
        dg, ig = dst.dist(tri.mean(axis=1))
        evals += dg.size
        lower = max(lower, float(dg.max()))
        cand = np.concatenate([iv, ig[:, None]], axis=1)
        enough = lower + max(HAUSDORFF_REL_ACCURACY * lower, tol_abs)
        ub = np.concatenate([dst.upper_bound(tri[i:i + _CHUNK], cand[i:i + _CHUNK], enough)
                             for i in range(0, tri.shape[0], _CHUNK)])
        refine = ub > enough
        if (~refine).any():
            upper_done = max(upper_done, float(ub[~refine].max()))
        if not refine.any():
            break
        if evals + 7 * int(refine.sum()) > HAUSDORFF_MAX_EVALUATIONS:
            upper_done = max(upper_done, float(ub[refine].max()))
            break
        tri, dv, iv = tri[refine], dv[refine], iv[refine]
        m = np.stack([0.5 * (tri[:, 0] + tri[:, 1]), 0.5 * (tri[:, 1] + tri[:, 2]),
                      0.5 * (tri[:, 2] + tri[:, 0])], axis=1)  # (M', 3, 3): m01, m12, m20
        dm, im = dst.dist(m.reshape(-1, 3))
        evals += dm.size
        dm, im = dm.reshape(-1, 3), im.reshape(-1, 3)
        lower = max(lower, float(dm.max()))
        # children (a, m01, m20), (m01, b, m12), (m20, m12, c), (m01, m12, m20)
        P = np.concatenate([tri, m], axis=1)  # (M', 6, 3): a b c m01 m12 m20
        tri = P[:, kids].reshape(-1, 3, 3)
        dv = np.concatenate([dv, dm], axis=1)[:, kids].reshape(-1, 3)
        iv = np.concatenate([iv, im], axis=1)[:, kids].reshape(-1, 3)
    return lower, max(lower, upper_done), evals


def _hausdorff(hex_v, hex_tris, tet_v, tet_tris, diag: float) -> tuple[float, float, int]:
    tol = HAUSDORFF_ABS_ACCURACY_REL * diag
    lo1, up1, n1 = _one_sided_hausdorff(hex_v, hex_tris, _Target(tet_v, tet_tris), tol)
    lo2, up2, n2 = _one_sided_hausdorff(tet_v, tet_tris, _Target(hex_v, hex_tris), tol)
    return max(lo1, lo2), max(up1, up2), n1 + n2
