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

The **seamless map** (before quantization, :func:`check_seamless`) is judged by the same checks
without integrality (:data:`SEAMLESS_CHECKS`): its translations are real, so across every
interior face ``u_t1 - R_f u_t0`` must be one vector at all three vertices (dyadic, exact), a
singular edge must lie on a parametric line (its transverse coordinates equal at both ends:
``singular_edges_off_lines``), a boundary face on a parametric plane (one coordinate equal at
its three corners: ``boundary_faces_off_planes``); reported, ``feature_edges_off_lines``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cut import face_corner_pairs, group_matrices

__all__ = ["MapValidity", "Gate", "check_map", "check_seamless", "check_params", "structure_gate", "record_one_ring",
           "first_failed",
           "VALIDITY_CHECKS", "FEATURE_CHECKS", "SEAMLESS_CHECKS", "STRUCTURE_CHECKS", "STAGES"]

VALIDITY_CHECKS = ("unmeshable_singular_edges", "inverted_tets", "degenerate_tets", "broken_transitions",
                   "singular_edges_off_integer_lines", "boundary_faces_off_integer_planes",
                   "contradictory_constraints")
FEATURE_CHECKS = ("feature_edges_off_integer_lines", "corners_off_integer_points")
SEAMLESS_CHECKS = ("unmeshable_singular_edges", "inverted_tets", "degenerate_tets", "broken_transitions",
                   "singular_edges_off_lines", "boundary_faces_off_planes", "contradictory_constraints")
STRUCTURE_CHECKS = ("complex_edges", "zipper_nodes", "invalid_nodes", "surface_valence2_edges", "collapsed_tets",
                    "flat_tets")
"""The structure gate: LMFF's local conditions (:mod:`.meshability`) and the tets the constraints
flatten (:meth:`.seamless.SeamlessProblem.flat_tets`: ``collapsed_tets`` have two corners sent to
one point, ``flat_tets`` the others, left after the splits)."""
STAGES = ("structure", "frames", "seamless", "quantization", "extraction")
"""The gated stages of the hex pipeline, in order."""
_WHERE = 10  # elements listed per failing check

_WHAT = {
    "unmeshable_singular_edges": "complex singular edges (no integer-grid map follows them)",
    "inverted_tets": "tets inverted in parameter space",
    "degenerate_tets": "tets of zero parametric volume",
    "broken_transitions": "interior faces where the map is not seamless",
    "singular_edges_off_integer_lines": "singular edges off an integer line",
    "boundary_faces_off_integer_planes": "boundary faces off an integer plane",
    "contradictory_constraints": "constraints that contradict each other",
    "singular_edges_off_lines": "singular edges off a parametric line",
    "complex_edges": "complex singular edges",
    "zipper_nodes": "zipper nodes (a valence +1 arc meeting a -1 arc)",
    "invalid_nodes": "invalid singular nodes",
    "surface_valence2_edges": "valence +-2 edges on a boundary surface",
    "collapsed_tets": "tets with two corners the constraints send to one point (singular or feature curves that meet)",
    "flat_tets": "tets the constraints flatten",
    "boundary_faces_off_planes": "boundary faces off a parametric plane",
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


@dataclass
class Gate:
    """The verdict of one stage of the hex pipeline (:data:`STAGES`).

    Attributes:
        stage: its name; passed: the stage's output is valid.
        counts: ``{check: count}``; where: ``{check: [element ids]}`` (the first few);
        where_xyz: ``{check: [points]}``; reasons: one sentence per failing check.
        before: for ``quantization``, whether its input (the seamless map) was valid (``None``
            elsewhere): a quantization that loses a valid map says so.
        info: reported beside the checks, not deciding ``passed`` (the structure gate: the
            one-ring test's counts and failing vertices with their reasons).
    """

    stage: str
    passed: bool
    counts: dict = field(default_factory=dict)
    where: dict = field(default_factory=dict)
    where_xyz: dict = field(default_factory=dict)
    reasons: list = field(default_factory=list)
    before: bool | None = None
    info: dict = field(default_factory=dict)

    @classmethod
    def of_validity(cls, stage: str, v: MapValidity, before: bool | None = None) -> "Gate":
        return cls(stage=stage, passed=bool(v.valid), counts=dict(v.counts), where=dict(v.where),
                   where_xyz=dict(v.where_xyz), reasons=list(v.reasons), before=before)

    def as_dict(self) -> dict:
        """JSON-ready."""
        out = {"passed": self.passed, "reasons": list(self.reasons), "counts": dict(self.counts),
               "where": {k: list(v) for k, v in self.where.items()}}
        if self.before is not None:
            out["valid_before"] = self.before
        if self.info:
            out["info"] = dict(self.info)
        return out


def first_failed(gates: dict) -> str | None:
    """The first stage of :data:`STAGES` whose gate failed and stopped the pipeline: a failed
    gate followed by a passed one (LMFF's conditions flag a structure, yet the seamless map is
    valid) did not stop it. ``None`` when no stage did."""
    order = [s for s in STAGES if s in gates]
    for i, name in enumerate(order):
        if not gates[name].passed and not any(gates[later].passed for later in order[i + 1:] if later != "extraction"):
            return name
    return None


def structure_gate(mesh, meshability, flat: np.ndarray, collapsed: np.ndarray, one_ring=None) -> Gate:
    """The structure gate: LMFF's conditions of ``meshability`` (a
    :class:`~.meshability.Meshability`) and the flat tets ``flat (k,)`` of the seamless problem,
    ``collapsed (k,)`` bool those with a collapsed edge (:data:`STRUCTURE_CHECKS`).

    ``one_ring``: a :class:`~.one_ring.OneRingReport`, reported beside the conditions (counts
    ``one_ring_tested`` / ``one_ring_failed``, the failing vertices in ``where`` and
    ``where_xyz``, its :meth:`~.one_ring.OneRingReport.as_dict` in ``info["one_ring"]``); it
    does not decide ``passed``."""
    X = mesh.vertices.detach().cpu().double().numpy()
    edges = mesh.edges.cpu().numpy()
    tets = mesh.tets.cpu().numpy()
    counts, where, xyz = {}, {}, {}
    for name in ("complex_edges", "surface_valence2_edges"):
        ids = np.asarray(getattr(meshability, name))
        counts[name] = int(ids.size)
        if ids.size:
            where[name] = [list(map(int, r)) for r in edges[ids[:_WHERE]]]
            xyz[name] = X[edges[ids[:_WHERE]]].mean(1).round(6).tolist()
    for name in ("zipper_nodes", "invalid_nodes"):
        ids = np.asarray(getattr(meshability, name))
        counts[name] = int(ids.size)
        if ids.size:
            where[name] = ids[:_WHERE].tolist()
            xyz[name] = X[ids[:_WHERE]].round(6).tolist()
    flat = np.asarray(flat, np.int64)
    collapsed = np.asarray(collapsed, bool)
    for name, ids in (("collapsed_tets", flat[collapsed]), ("flat_tets", flat[~collapsed])):
        counts[name] = int(ids.size)
        if ids.size:
            where[name] = ids[:_WHERE].tolist()
            xyz[name] = X[tets[ids[:_WHERE]]].mean(1).round(6).tolist()
    reasons = []
    for name in STRUCTURE_CHECKS:
        n = counts.get(name, 0)
        if n:
            eg = f" (e.g. {where[name][0]} at {tuple(xyz[name][0])})" if name in where else ""
            reasons.append(f"{n} {_WHAT[name]}{eg}")
    gate = Gate(stage="structure", passed=not reasons, counts=counts, where=where, where_xyz=xyz, reasons=reasons,
                info={})
    if one_ring is not None:
        record_one_ring(gate, one_ring)
    return gate


def record_one_ring(gate: Gate, one_ring) -> Gate:
    """Write a :class:`~.one_ring.OneRingReport` into the structure ``gate`` (in place; returned):
    counts ``one_ring_tested`` / ``one_ring_failed``, the failing vertices in ``where`` and
    ``where_xyz``, the report's :meth:`~.one_ring.OneRingReport.as_dict` in ``info["one_ring"]``.
    It does not change ``passed``."""
    ok = one_ring.passed
    gate.counts["one_ring_tested"] = int(ok.size)
    gate.counts["one_ring_failed"] = int((~ok).sum())
    if (~ok).any():
        gate.where["one_ring_failed"] = one_ring.vertices[~ok][:_WHERE].tolist()
        gate.where_xyz["one_ring_failed"] = one_ring.position[~ok][:_WHERE].round(6).tolist()
    gate.info["one_ring"] = one_ring.as_dict(limit=_WHERE)
    return gate


def check_map(mesh, igm) -> MapValidity:
    """Check an integer-grid map of ``mesh`` (module docstring); never raises on a bad map."""
    return check_params(mesh, igm.charts, igm.uvw, igm.problem, integer=True)


def check_seamless(mesh, charts, uvw: np.ndarray, problem=None) -> MapValidity:
    """Check a seamless map ``uvw (T, 4, 3)`` (dyadic: snapped to a grid) of ``mesh`` by
    :data:`SEAMLESS_CHECKS` (module docstring); never raises on a bad map."""
    return check_params(mesh, charts, uvw, problem, integer=False)


def check_params(mesh, charts, uvw: np.ndarray, problem=None, *, integer: bool = True) -> MapValidity:
    """The checks of :func:`check_map` (``integer``) or :func:`check_seamless` on corner
    parameters ``uvw (T, 4, 3)`` with the transitions of ``charts`` (:class:`~.cut.TetCharts`) and
    the constraints of ``problem`` (a :class:`~.seamless.SeamlessProblem`, or ``None``)."""
    from .predicates import orient3d

    ch = charts
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
    ok = (s == s[:, :1]).all((1, 2)) & ((s == np.round(s)).all((1, 2)) | (not integer))
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
        ok = (ta == tb_).all(1) & ((ta == np.round(ta)).all(1) | (not integer))
        bad = ms[~ok]
    else:
        bad = np.zeros(0, np.int64)
    record("singular_edges_off_integer_lines" if integer else "singular_edges_off_lines", edges[bad],
           X[edges[bad]].mean(1))

    bfi = mesh.boundary_face_index.cpu().numpy()
    bt = np.where(face_tets[bfi, 0] >= 0, face_tets[bfi, 0], face_tets[bfi, 1])
    slot = np.argmax(mesh.tet_faces.cpu().numpy()[bt] == bfi[:, None], axis=1)
    loc = (slot[:, None] + 1 + np.arange(3)) % 4
    P = uvw[bt[:, None], loc]  # (B, 3 corners, 3)
    on_plane = ((P == P[:, :1]).all(1) & ((P[:, 0] == np.round(P[:, 0])) | (not integer))).any(1)
    bad_b = bfi[~on_plane]
    record("boundary_faces_off_integer_planes" if integer else "boundary_faces_off_planes", bad_b,
           X[faces[bad_b]].mean(1))

    prob = problem
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
        same_int = (pa == pb) & ((pa == np.round(pa)) | (not integer))
        on_line = same_int.sum(1) >= 2
        bad = np.nonzero(~on_line)[0]
        record("feature_edges_off_integer_lines" if integer else "feature_edges_off_lines", fe[bad], X[fe[bad]].mean(1))
    else:
        counts["feature_edges_off_integer_lines" if integer else "feature_edges_off_lines"] = 0
    # (a corner of the seamless map is any point: corners are checked on the integer map only)
    if integer and prob is not None and prob.corner_vertices.size:
        cv = prob.corner_vertices
        first = np.full(X.shape[0], tets.size, np.int64)
        np.minimum.at(first, tets.reshape(-1), np.arange(tets.size))
        pc = uvw[first[cv] // 4, first[cv] % 4]
        bad = cv[~(pc == np.round(pc)).all(1)]
        record("corners_off_integer_points", bad, X[bad])
    elif integer:
        counts["corners_off_integer_points"] = 0

    reasons = []
    for name in (VALIDITY_CHECKS if integer else SEAMLESS_CHECKS):
        n = counts.get(name, 0)
        if n:
            eg = ""
            if name in where:
                first_id = where[name][0]
                eg = f" (e.g. {first_id}" + (f" at {tuple(xyz[name][0])}" if name in xyz else "") + ")"
            reasons.append(f"{n} {_WHAT[name]}{eg}")
    valid = not reasons
    return MapValidity(valid=valid, counts=counts, where=where, where_xyz=xyz, reasons=reasons)
