"""Is an integer-grid map valid, and if not, where and why (HEXMESH.md step 7).

Every check is exact: the map's corner parameters are dyadic (:mod:`.igm`), the transitions
are signed permutations with integer shifts, so differences, transitions and integrality are
evaluated exactly in float64 and orientations with the exact predicate of :mod:`.predicates`.

Checks (``MapValidity.counts`` keys; a map is valid when all are zero):

* ``unmeshable_singular_edges``: interior edges whose holonomy is complex (not the identity,
  not a quarter or half turn): no integer-grid map follows the field there (the meshability
  gate);
* ``inverted_tets`` / ``degenerate_tets``: tets with negative / zero parametric volume;
* ``broken_transitions``: interior faces where ``u_t1 - R_f u_t0`` is not one integer vector at
  all three vertices (the map is not seamless there);
* ``singular_edges_off_integer_lines``: singular edges whose two transverse coordinates are not
  the same integers at both ends;
* ``boundary_faces_off_integer_planes``: boundary faces with no coordinate that is one integer
  at all three corners;
* ``contradictory_constraints``: constraint rows that reduced to ``c = 0``, ``c != 0``
  (constraints the field makes incompatible; the map ignores them).

Reported, not part of validity: ``feature_edges_off_integer_lines`` and
``corners_off_integer_points`` (features the map does not mesh).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cut import face_corner_pairs, group_matrices

__all__ = ["MapValidity", "check_map", "VALIDITY_CHECKS", "FEATURE_CHECKS"]

VALIDITY_CHECKS = ("unmeshable_singular_edges", "inverted_tets", "degenerate_tets", "broken_transitions",
                   "singular_edges_off_integer_lines", "boundary_faces_off_integer_planes",
                   "contradictory_constraints")
FEATURE_CHECKS = ("feature_edges_off_integer_lines", "corners_off_integer_points")
_WHERE = 10  # elements listed per failing check

_WHAT = {
    "unmeshable_singular_edges": "complex singular edges (no integer-grid map follows them)",
    "inverted_tets": "tets inverted in parameter space",
    "degenerate_tets": "tets of zero parametric volume",
    "broken_transitions": "interior faces where the map is not seamless",
    "singular_edges_off_integer_lines": "singular edges off an integer line",
    "boundary_faces_off_integer_planes": "boundary faces off an integer plane",
    "contradictory_constraints": "constraints that contradict each other",
}


@dataclass
class MapValidity:
    """The verdict on an :class:`~.igm.IntegerGridMap`.

    Attributes:
        valid: every check of :data:`VALIDITY_CHECKS` is zero.
        counts: ``{check: count}`` for :data:`VALIDITY_CHECKS` and :data:`FEATURE_CHECKS`.
        where: ``{check: [element ids]}`` (the first few; tets, faces or edges of the mesh,
            edges as vertex pairs) and ``where_xyz``: their barycenters.
        reasons: one sentence per failing check, e.g. ``"12 tets inverted in parameter space
            (e.g. tet 41 at (0.1, 0.5, 0.2))"``; empty for a valid map.
    """

    valid: bool
    counts: dict
    where: dict = field(default_factory=dict)
    where_xyz: dict = field(default_factory=dict)
    reasons: list = field(default_factory=list)

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"valid": self.valid, "reasons": list(self.reasons), "counts": dict(self.counts),
                "where": {k: list(v) for k, v in self.where.items()}}


def check_map(mesh, igm) -> MapValidity:
    """Check an integer-grid map of ``mesh`` (module docstring); never raises on a bad map."""
    from .predicates import orient3d

    uvw = igm.uvw
    ch = igm.charts
    tets = mesh.tets.cpu().numpy()
    faces = mesh.faces.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    face_tets = mesh.face_tets.cpu().numpy()
    X = mesh.vertices.detach().cpu().double().numpy()
    G = group_matrices().astype(np.float64)
    counts, where, xyz = {}, {}, {}

    def record(name, ids, points):
        ids = np.asarray(ids)
        counts[name] = int(ids.shape[0])
        if ids.size:
            where[name] = ids[:_WHERE].tolist() if ids.ndim == 1 else [list(map(int, r)) for r in ids[:_WHERE]]
            xyz[name] = np.asarray(points)[:_WHERE].round(6).tolist()

    sing = ch.singular_edge
    bad_e = np.nonzero(sing & ~ch.edge_meshable)[0]
    record("unmeshable_singular_edges", edges[bad_e], X[edges[bad_e]].mean(1))

    o = orient3d(uvw[:, 0], uvw[:, 1], uvw[:, 2], uvw[:, 3])
    inv = np.nonzero(o < 0)[0]
    deg = np.nonzero(o == 0)[0]
    tb = X[tets].mean(1)
    record("inverted_tets", inv, tb[inv])
    record("degenerate_tets", deg, tb[deg])

    fc = face_corner_pairs(tets, faces, mesh.tet_faces.cpu().numpy(), face_tets)
    fi = np.nonzero(ch.interior_face)[0]
    R = G[ch.face_rot[fi]]
    s = np.stack([uvw[face_tets[fi, 1], fc[fi, 1, m]] - np.einsum("fij,fj->fi", R, uvw[face_tets[fi, 0], fc[fi, 0, m]])
                  for m in range(3)], 1)  # (n, 3 vertices, 3)
    ok = (s == s[:, :1]).all((1, 2)) & (s == np.round(s)).all((1, 2))
    bad_f = fi[~ok]
    record("broken_transitions", bad_f, X[faces[bad_f]].mean(1))

    ms = np.nonzero(sing & ch.edge_meshable)[0]
    if ms.size:
        st = ch.edge_start_tet[ms]
        ax = ch.edge_axis[ms]
        la = np.argmax(tets[st] == edges[ms, 0][:, None], axis=1)
        lb = np.argmax(tets[st] == edges[ms, 1][:, None], axis=1)
        pa, pb = uvw[st, la], uvw[st, lb]
        keep = np.ones((ms.size, 3), bool)
        keep[np.arange(ms.size), ax] = False
        ta, tb_ = pa[keep].reshape(-1, 2), pb[keep].reshape(-1, 2)
        ok = (ta == tb_).all(1) & (ta == np.round(ta)).all(1)
        bad = ms[~ok]
    else:
        bad = np.zeros(0, np.int64)
    record("singular_edges_off_integer_lines", edges[bad], X[edges[bad]].mean(1))

    bfi = mesh.boundary_face_index.cpu().numpy()
    bt = np.where(face_tets[bfi, 0] >= 0, face_tets[bfi, 0], face_tets[bfi, 1])
    slot = np.argmax(mesh.tet_faces.cpu().numpy()[bt] == bfi[:, None], axis=1)
    loc = (slot[:, None] + 1 + np.arange(3)) % 4
    P = uvw[bt[:, None], loc]  # (B, 3 corners, 3)
    on_plane = ((P == P[:, :1]).all(1) & (P[:, 0] == np.round(P[:, 0]))).any(1)
    bad_b = bfi[~on_plane]
    record("boundary_faces_off_integer_planes", bad_b, X[faces[bad_b]].mean(1))

    prob = igm.problem
    conf = prob.elim.conflicts if prob is not None else []
    counts["contradictory_constraints"] = len(conf)
    if conf:
        where["contradictory_constraints"] = [f"{lab} (row {r}, residual {res:g})" for r, lab, res in conf[:_WHERE]]

    # features (reported, not validity)
    if prob is not None and prob.feature_edges.shape[0]:
        fe = prob.feature_edges
        eid = np.searchsorted(edges[:, 0] * X.shape[0] + edges[:, 1], fe[:, 0] * X.shape[0] + fe[:, 1])
        ft = ch.edge_start_tet[eid]
        la = np.argmax(tets[ft] == fe[:, 0][:, None], axis=1)
        lb = np.argmax(tets[ft] == fe[:, 1][:, None], axis=1)
        pa, pb = uvw[ft, la], uvw[ft, lb]
        same_int = (pa == pb) & (pa == np.round(pa))
        on_line = same_int.sum(1) >= 2
        bad = np.nonzero(~on_line)[0]
        record("feature_edges_off_integer_lines", fe[bad], X[fe[bad]].mean(1))
    else:
        counts["feature_edges_off_integer_lines"] = 0
    if prob is not None and prob.corner_vertices.size:
        cv = prob.corner_vertices
        first = np.full(X.shape[0], tets.size, np.int64)
        np.minimum.at(first, tets.reshape(-1), np.arange(tets.size))
        pc = uvw[first[cv] // 4, first[cv] % 4]
        bad = cv[~(pc == np.round(pc)).all(1)]
        record("corners_off_integer_points", bad, X[bad])
    else:
        counts["corners_off_integer_points"] = 0

    reasons = []
    for name in VALIDITY_CHECKS:
        n = counts.get(name, 0)
        if n:
            eg = ""
            if name in where:
                first_id = where[name][0]
                eg = f" (e.g. {first_id}" + (f" at {tuple(xyz[name][0])}" if name in xyz else "") + ")"
            reasons.append(f"{n} {_WHAT[name]}{eg}")
    valid = not reasons
    return MapValidity(valid=valid, counts=counts, where=where, where_xyz=xyz, reasons=reasons)
