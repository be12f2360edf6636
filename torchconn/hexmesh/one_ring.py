"""The numeric one-ring test of local meshability (Liu & Bommes, "Locally Meshable Frame Fields", 2023).

LMFF's combinatorial conditions (:mod:`.meshability`) are necessary, not sufficient; its local
test is numeric: a singular vertex ``v`` is locally meshable when the seamless map of its
one-ring (the tets incident to ``v``) has

* no inverted tet, after the foldover-free solver (:func:`~.injective.minimize_barrier`), and
* at every edge ``v-w`` the parametric angle expected there: the sum of the parametric dihedral
  angles of the tets around the edge (the transitions are rotations, so the angles need no
  unfolding) equals ``k pi/2`` within :data:`ANGLE_TOL`, with ``k`` the edge's hex count
  (:attr:`~.meshability.Meshability.edge_hexes`): ``2 pi + valence pi/2`` at an interior edge
  (valence ``-1`` for 3 hexes, ``+1`` for 5, ``0`` regular, ``±2`` half turns), the fan's quarter
  turns ``q`` at a boundary edge. Holonomy fixes the angle only up to ``2 pi`` (a map whose tets
  all keep their orientation may still wind twice about an edge, or not close at all).

The one-ring's map (:func:`~.seamless.build_problem` on the ring, every integer relaxed) keeps
what the global map would impose there: the face matchings of the input (the ring's
transitions, hence its holonomy and the singular-edge lines of the edges at ``v``), the
parametric planes of the ring's faces that lie on the input's boundary, and the lines of its
feature edges; the ring's link faces are free. Its objective is the frame fit
``|grad u (h F) - I|^2``; where the least-squares map folds, the foldover-free solve untangles
it (``solve=True``). A map found with no inverted tet and the right angles passes; a fold the
solver cannot remove is reported as such (the solver may miss a map that exists: the verdict is
that of LMFF's test, not a proof).

Rings that the constraints flatten (:meth:`~.seamless.SeamlessProblem.flat_tets`: e.g. two
singular edges on one line) and rings at a complex singular edge (no expected angle) fail too,
with that reason.

Vectorized: all the rings are copies in one disjoint tet mesh (vertices duplicated per ring),
whose charts, constraints, exact flat-tet test, least-squares map and angles are computed once;
only the foldover-free solve loops, over the rings whose least-squares map folds (each a small
system of its own).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from .cut import GROUP_INV, tet_charts
from .meshability import REGULAR, VERTEX_CLASSES, meshability_report
from .seamless import FEATURE_MAX_DEG

__all__ = ["OneRingReport", "one_ring_test", "ANGLE_TOL", "REASONS", "SOLVER_BUDGET"]

ANGLE_TOL = 0.035
"""LMFF's acceptance of an edge's parametric angle (radians; AlgoHex's one-ring check)."""

REASONS = ("inverted", "angle", "flat", "complex")
"""Why a vertex fails: tets inverted after the solve, edges whose parametric angle is off, tets
the ring's constraints flatten, a complex singular edge at the vertex."""

SOLVER_BUDGET = {"untangle_rounds": 3, "rounds": 1, "max_iter": 20}
"""The foldover-free solve's budget per ring (:func:`~.injective.minimize_barrier`'s options;
its defaults are 3 / 4 / 50). A ring that the solve untangles is untangled early (within the
first untangling solve on the HexMe models tried); a ring it cannot untangle spends the whole
budget, which is what the test costs."""

_PAIRS = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]  # TetMesh.tet_edges' local pairs


@dataclass
class OneRingReport:
    """What :func:`one_ring_test` returns (numpy; ``N`` tested vertices, ``K`` edges checked).

    Per vertex: ``vertices (N,)`` ids, ``position (N, 3)``, ``vertex_class (N,)`` codes of
    :data:`~.meshability.VERTEX_CLASSES`, ``inverted (N,)`` tets with ``det J <= 0`` in the final
    map of the ring (flat tets not counted), ``flat (N,)`` tets the ring's constraints flatten,
    ``complex (N,)`` complex singular edges at the vertex, ``solved (N,)`` bool, whether the
    foldover-free solve ran (the least-squares map folded), ``n_tets (N,)`` the ring's tets.

    Per edge at a tested vertex: ``edge_ring (K,)`` the row of its vertex, ``edge (K,)`` its id
    in the mesh, ``edge_verts (K, 2)`` its vertices (the tested one first), ``edge_hexes (K,)``
    its hex count (boundary: quarter turns; ``-1`` complex), ``edge_boundary (K,)`` bool, on the
    boundary, ``edge_flat (K,)`` the flat tets about it, ``expected (K,)`` radians
    (``edge_hexes * pi/2``, NaN at a complex edge), ``measured (K,)`` the sum of the signed
    parametric dihedral angles about it (flat tets add nothing). An edge's angle is judged
    where it is defined: not at a complex edge, not about a flat tet (the ``flat`` reason).

    ``timings``: seconds per step; ``options``: what the test ran with.
    """

    vertices: np.ndarray
    position: np.ndarray
    vertex_class: np.ndarray
    inverted: np.ndarray
    flat: np.ndarray
    complex: np.ndarray
    solved: np.ndarray
    n_tets: np.ndarray
    edge_ring: np.ndarray
    edge: np.ndarray
    edge_verts: np.ndarray
    edge_hexes: np.ndarray
    edge_boundary: np.ndarray
    edge_flat: np.ndarray
    expected: np.ndarray
    measured: np.ndarray
    timings: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)

    @property
    def edge_judged(self) -> np.ndarray:
        """``(K,)`` bool: edges whose angle is judged (not complex, no flat tet about them)."""
        return np.isfinite(self.expected) & (self.edge_flat == 0)

    @property
    def edge_ok(self) -> np.ndarray:
        """``(K,)`` bool: the parametric angle is within :data:`ANGLE_TOL` of the expected one."""
        return np.abs(self.measured - self.expected) <= ANGLE_TOL  # NaN (complex) compares false

    @property
    def angle_off(self) -> np.ndarray:
        """``(N,)`` judged edges of each vertex whose angle is off."""
        bad = ~self.edge_ok & self.edge_judged
        return np.bincount(self.edge_ring[bad], minlength=self.vertices.size)

    def failed_by(self) -> dict:
        """``{reason: (N,) bool}`` for each of :data:`REASONS`."""
        return {"inverted": self.inverted > 0, "angle": self.angle_off > 0, "flat": self.flat > 0,
                "complex": self.complex > 0}

    @property
    def passed(self) -> np.ndarray:
        """``(N,)`` bool: no reason to fail."""
        return ~np.any(np.stack(list(self.failed_by().values())), axis=0) if self.vertices.size else \
            np.zeros(0, bool)

    def counts(self) -> dict:
        """Vertices tested / passed / failed, failed by each reason (a vertex may have several),
        failed per vertex class, and the solves run (JSON-ready)."""
        ok = self.passed
        out = {"tested": int(ok.size), "passed": int(ok.sum()), "failed": int((~ok).sum())}
        for k, v in self.failed_by().items():
            out[f"failed_{k}"] = int(v.sum())
        out["failed_by_class"] = {VERTEX_CLASSES[c]: int((~ok & (self.vertex_class == c)).sum())
                                  for c in np.unique(self.vertex_class[~ok]).tolist()}
        out["solved"] = int(self.solved.sum())
        out["seconds"] = round(float(self.timings.get("total_s", 0.0)), 3)
        return out

    def reasons(self, row: int) -> list[str]:
        """One sentence per reason vertex ``vertices[row]`` fails (empty when it passes)."""
        out = []
        if self.complex[row]:
            e = self.edge_verts[(self.edge_ring == row) & ~np.isfinite(self.expected)]
            out.append(f"{int(self.complex[row])} complex singular edges (e.g. {e[0, 0]}-{e[0, 1]}): no angle "
                       "a map can have there")
        if self.flat[row]:
            out.append(f"{int(self.flat[row])} tets the ring's constraints flatten")
        if self.inverted[row]:
            how = "after the foldover-free solve" if self.solved[row] else "in the least-squares map"
            out.append(f"{int(self.inverted[row])} of {int(self.n_tets[row])} tets inverted {how}")
        sel = np.nonzero((self.edge_ring == row) & ~self.edge_ok & self.edge_judged)[0]
        for k in sel:
            a, b = self.edge_verts[k]
            out.append(f"edge {a}-{b} ({_edge_kind(self, k)}): parametric angle {self.measured[k]:.3f} rad, "
                       f"expected {self.expected[k]:.3f}")
        return out

    def failing(self, limit: int | None = None) -> list[dict]:
        """The failing vertices: ``{"vertex", "position", "class", "reasons"}`` each (JSON-ready;
        the first ``limit``)."""
        rows = np.nonzero(~self.passed)[0][:limit]
        return [{"vertex": int(self.vertices[r]), "position": [round(float(x), 6) for x in self.position[r]],
                 "class": VERTEX_CLASSES[int(self.vertex_class[r])], "reasons": self.reasons(int(r))} for r in rows]

    def as_dict(self, limit: int | None = 50) -> dict:
        """``counts()`` and ``failing(limit)`` (JSON-ready)."""
        return {"counts": self.counts(), "failing": self.failing(limit)}


def _edge_kind(rep: OneRingReport, k: int) -> str:
    hexes = int(rep.edge_hexes[k])
    if rep.edge_boundary[k]:
        return f"boundary, {hexes} quarter turns"
    return "regular" if hexes == 4 else f"{hexes} hexes"


# ----------------------------------------------------------------------------- the rings as one mesh
@dataclass
class _Rings:
    """The disjoint union of the one-rings: ``mesh`` (a ``TetMesh``), ``ring_tet (Tu,)`` the ring
    of each of its tets (rings contiguous, in order), ``orig_tet (Tu,)``, ``center (Tu,)`` the
    local corner of the ring's vertex, ``orig_vertex (Vu,)``, ``orig_face (Fu,)``, ``orig_edge (Eu,)``."""

    mesh: object
    ring_tet: np.ndarray
    orig_tet: np.ndarray
    center: np.ndarray
    orig_vertex: np.ndarray
    orig_face: np.ndarray
    orig_edge: np.ndarray


def _rings(mesh, vertices: np.ndarray) -> _Rings:
    from ..mesh import TetMesh

    tets = mesh.tets.cpu().numpy()
    V = mesh.n_vertices
    row = np.full(V, -1, np.int64)
    row[vertices] = np.arange(vertices.size)
    t, k = np.nonzero(row[tets] >= 0)  # incidences (tet, local corner) of a tested vertex
    r = row[tets[t, k]]
    order = np.argsort(r, kind="stable")
    t, k, r = t[order], k[order], r[order]
    keys = r[:, None] * V + tets[t]  # a vertex of ring r: (r, original vertex)
    ukeys, inv = np.unique(keys.reshape(-1), return_inverse=True)
    X = mesh.vertices.detach().cpu().to(torch.float64)
    tu = torch.as_tensor(inv.reshape(-1, 4))
    union = TetMesh(X[torch.as_tensor(ukeys % V)], tu)
    if not torch.equal(union.tets, tu):  # pragma: no cover - TetMesh keeps positive tets as given
        raise RuntimeError("the one-ring mesh reordered its tets")
    orig_face = np.empty(union.n_faces, np.int64)
    orig_face[union.tet_faces.numpy()] = mesh.tet_faces.cpu().numpy()[t]
    orig_edge = np.empty(union.n_edges, np.int64)
    orig_edge[union.tet_edges.numpy()] = mesh.tet_edges.cpu().numpy()[t]
    return _Rings(mesh=union, ring_tet=r, orig_tet=t, center=k, orig_vertex=ukeys % V, orig_face=orig_face,
                  orig_edge=orig_edge)


def _ring_matchings(mesh, rings: _Rings, face_match: np.ndarray) -> np.ndarray:
    """``(Fu,)`` the input's face matchings on the rings' faces (inverted where the ring's mesh
    orders a face's two tets the other way round)."""
    ft_u = rings.mesh.face_tets.numpy()
    ft = mesh.face_tets.cpu().numpy()
    out = np.zeros(ft_u.shape[0], np.int64)
    fi = np.nonzero((ft_u >= 0).all(1))[0]
    f = rings.orig_face[fi]
    same = ft[f, 0] == rings.orig_tet[ft_u[fi, 0]]
    out[fi] = np.where(same, face_match[f], GROUP_INV[face_match[f]])
    return out


def _features(mesh, rings: _Rings, features: bool) -> tuple[np.ndarray, np.ndarray]:
    """The input's feature edges and CAD corners on the rings (ring vertex ids)."""
    if not features:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    from ..frames.constraints import BoundaryConstraint

    bc = BoundaryConstraint.from_mesh(mesh)
    feat = np.zeros(mesh.edges.shape[0], bool)
    if bc.feature_edges is not None and bc.feature_edges.numel():
        fe = bc.feature_edges.cpu()
        fid, _ = mesh.edge_index(fe[:, 0], fe[:, 1])
        feat[fid.cpu().numpy()] = True
    corner = np.zeros(mesh.n_vertices, bool)
    if bc.corner_vertices is not None and bc.corner_vertices.numel():
        corner[bc.corner_vertices.cpu().numpy()] = True
    edges_u = rings.mesh.edges.numpy()
    return edges_u[feat[rings.orig_edge]], np.nonzero(corner[rings.orig_vertex])[0]


# ----------------------------------------------------------------------------- angles
def _dihedral_sums(rings: _Rings, uvw: np.ndarray, skip: np.ndarray) -> np.ndarray:
    """``(Eu,)`` the sum of the signed parametric dihedral angles at every edge of the rings
    through a ring's vertex (0 elsewhere), for corner parameters ``uvw (Tu, 4, 3)``: each tet's
    angle at the edge, negative where the tet is inverted; the tets ``skip (Tu,)`` bool (flat
    whatever the map: their angles are 0 or pi by round-off) add nothing."""
    Tu = uvw.shape[0]
    c = rings.center
    pair = {p: i for i, p in enumerate(_PAIRS)}
    lut = np.full((4, 4), -1, np.int64)
    for (i, j), p in pair.items():
        lut[i, j] = lut[j, i] = p
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])  # (4, 3)
    J = others[c]  # (Tu, 3): the edge's other end, one column per edge through the centre
    rest = np.stack([np.stack([others[c, (m + 1) % 3], others[c, (m + 2) % 3]], 1) for m in range(3)], 1)
    t = np.arange(Tu)[:, None]
    p0 = uvw[t, c[:, None]]  # (Tu, 1, 3)
    d = uvw[t, J] - p0  # (Tu, 3, 3)
    a = uvw[t, rest[:, :, 0]] - p0
    b = uvw[t, rest[:, :, 1]] - p0
    dn = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
    a = a - np.einsum("tmi,tmi->tm", a, dn)[..., None] * dn
    b = b - np.einsum("tmi,tmi->tm", b, dn)[..., None] * dn
    ang = np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("tmi,tmi->tm", a, b))
    P = uvw
    det = np.einsum("ti,ti->t", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), P[:, 3] - P[:, 0])
    ang = ang * np.where(skip, 0.0, np.where(det > 0, 1.0, -1.0))[:, None]
    eid = rings.mesh.tet_edges.numpy()[t, lut[c[:, None], J]]
    return np.bincount(eid.reshape(-1), weights=ang.reshape(-1), minlength=rings.mesh.n_edges)


# ----------------------------------------------------------------------------- the test
def one_ring_test(mesh, tet_frames, face_match=None, *, vertices=None, charts=None, meshability=None,
                  edge_length: float | None = None, features: bool = True, feature_max_deg: float = FEATURE_MAX_DEG,
                  solve: bool = True, solver_options: dict | None = None, backend: str = "auto") -> OneRingReport:
    """LMFF's numeric one-ring test at the singular vertices of a field (module docstring).

    Args:
        mesh: a ``TetMesh``.
        tet_frames: ``(T, 3, 3)`` rotations (axes as columns).
        face_match: ``(F,)`` face matchings (indices into O; default the best ones,
            :func:`~.cut.face_matchings`).
        vertices: the vertices to test (default every vertex that
            :func:`~.meshability.meshability_report` does not class ``regular``: on a singular or
            feature curve, a node, a zipper, an invalid node or at a complex edge).
        charts: the :func:`~.cut.tet_charts` of the input, if already computed (then its combed
            frames and transitions are used, ``tet_frames`` and ``face_match`` are not).
        meshability: its :class:`~.meshability.Meshability` report, if already computed (the
            expected angles are its hex counts).
        edge_length: ``h`` of the fit (default :func:`~.seamless.default_edge_length`; the
            verdict does not depend on it: no integer is rounded).
        features, feature_max_deg: the feature constraints (:func:`~.seamless.build_problem`).
        solve: untangle the rings whose least-squares map folds with
            :func:`~.injective.minimize_barrier` (``False``: judge the least-squares map); rings
            that fail anyway (a flat tet, a complex edge) are not solved.
        solver_options: :func:`~.injective.minimize_barrier`'s options (default
            :data:`SOLVER_BUDGET`; also ``w_fit``, ``w_sd``, ``tol``).
        backend: sparse solver (:mod:`.solver`).

    Returns:
        :class:`OneRingReport`.

    Raises:
        ValueError: frames or matchings that do not fit the mesh (as :func:`~.cut.tet_charts`),
            vertex ids out of range.

    Cost: the charts, constraints and least-squares map of a mesh of ``sum_v |ring(v)|`` tets
    (about 4x the input's tets where every vertex is tested), and one small foldover-free solve
    per ring whose least-squares map folds (the ``solve`` timing).
    """
    from .injective import DET_SAFE, TetJacobians, minimize_barrier
    from .seamless import build_problem, default_edge_length
    from .solver import factorize

    t_all = time.perf_counter()
    timings = {}
    if charts is not None:
        frames = np.asarray(charts.frames, np.float64)
        fm = GROUP_INV[charts.face_rot]  # the combed frames' matchings g' = R'^T (0 on boundary faces)
    else:
        # validates the frames and the matchings; default: the best matchings
        charts = tet_charts(mesh, tet_frames, None if face_match is None else np.asarray(face_match))
        frames = charts.frames
        fm = GROUP_INV[charts.face_rot]
    rep = meshability_report(mesh, frames, charts=charts, features=features) if meshability is None else meshability
    V = mesh.n_vertices
    if vertices is None:
        vertices = np.nonzero(rep.vertex_class != REGULAR)[0]
    else:
        vertices = np.unique(np.asarray(vertices, np.int64).reshape(-1))
        bad = vertices[(vertices < 0) | (vertices >= V)]
        if bad.size:
            raise ValueError(f"vertices must be vertex ids in [0, {V}); got {bad[:5].tolist()}")
    N = vertices.size
    X = mesh.vertices.detach().cpu().double().numpy()
    opts = dict(SOLVER_BUDGET if solver_options is None else solver_options)
    empty = np.zeros(0, np.int64)
    if N == 0:
        return OneRingReport(vertices=empty, position=np.zeros((0, 3)), vertex_class=np.zeros(0, np.int8),
                             inverted=empty, flat=empty, complex=empty, solved=np.zeros(0, bool), n_tets=empty,
                             edge_ring=empty, edge=empty, edge_verts=np.zeros((0, 2), np.int64), edge_hexes=empty,
                             edge_boundary=np.zeros(0, bool), edge_flat=empty, expected=np.zeros(0),
                             measured=np.zeros(0), timings={"total_s": 0.0}, options={"solve": solve, "solver": opts})

    # ---- the rings as one mesh: charts, constraints, flat tets (once)
    t0 = time.perf_counter()
    rings = _rings(mesh, vertices)
    um = rings.mesh
    fm_u = _ring_matchings(mesh, rings, fm)
    ch_u = tet_charts(um, frames[rings.orig_tet], fm_u)
    ft = mesh.face_tets.cpu().numpy()
    plane = (ft[rings.orig_face[um.boundary_face_index.numpy()]] < 0).any(1)  # on the input's boundary
    h = default_edge_length(mesh) if edge_length is None else float(edge_length)
    prob = build_problem(um, ch_u, h, features=_features(mesh, rings, features), feature_max_deg=feature_max_deg,
                         plane_faces=plane)
    flat, _, _ = prob.flat_tets()
    timings["setup_s"] = time.perf_counter() - t0

    # ---- the least-squares map of every ring (one solve; a tiny Tikhonov term fixes each ring's
    # translation, which the one pinned vertex of the problem fixes for one ring only)
    t0 = time.perf_counter()
    jac = TetJacobians.of_problem(prob)
    used = np.unique(jac.GZ.indices)  # unknowns of the free link faces' planes appear nowhere
    GZ = jac.GZ[:, used].tocsr()
    w = np.repeat(jac.vol, 9)
    target = np.broadcast_to(np.eye(3).reshape(1, 9), (jac.n_tets, 9)).reshape(-1)
    A = (GZ.T @ sp.diags(w) @ GZ).tocsr()
    b = GZ.T @ (w * (target - jac.j0))
    scale = max(float(np.abs(A.diagonal()).max(initial=0.0)), 1e-300)
    y = factorize(A + sp.identity(A.shape[0], format="csr") * (1e-10 * scale), backend).solve(b)
    sub = TetJacobians(GZ=GZ, j0=jac.j0, vol=jac.vol)
    det = np.linalg.det(sub(y))
    is_flat = np.zeros(jac.n_tets, bool)
    is_flat[flat] = True
    timings["least_squares_s"] = time.perf_counter() - t0

    # ---- the foldover-free solve, ring by ring where the least-squares map folds and the ring
    # has no other reason to fail (a flat tet or a complex edge: the solve could not change the verdict)
    t0 = time.perf_counter()
    ptr = np.searchsorted(rings.ring_tet, np.arange(N + 1))
    folds = np.bincount(rings.ring_tet, weights=(det <= DET_SAFE) & ~is_flat, minlength=N) > 0
    Eu = um.edges.numpy()
    cen = np.zeros(um.n_vertices, bool)
    cen[um.tets.numpy()[np.arange(um.n_tets), rings.center]] = True
    ek = np.nonzero(cen[Eu[:, 0]] | cen[Eu[:, 1]])[0]  # the edges through a ring's vertex
    ring_v = np.zeros(um.n_vertices, np.int64)
    ring_v[um.tets.numpy().reshape(-1)] = np.repeat(rings.ring_tet, 4)
    e_ring = ring_v[Eu[ek, 0]]
    oe = rings.orig_edge[ek]
    hexes = rep.edge_hexes[oe].astype(np.int64)
    nflat = np.bincount(rings.ring_tet, weights=is_flat, minlength=N).astype(np.int64)
    ncx = np.bincount(e_ring, weights=hexes < 0, minlength=N).astype(np.int64)
    solved = np.zeros(N, bool)
    if solve:
        # one small system per folded ring (its unknowns are its own)
        for r in np.nonzero(folds & (nflat == 0) & (ncx == 0))[0]:
            rows = slice(9 * ptr[r], 9 * ptr[r + 1])
            Gr = GZ[rows]
            cols = np.unique(Gr.indices)
            jr = TetJacobians(GZ=Gr[:, cols].tocsr(), j0=jac.j0[rows], vol=jac.vol[ptr[r]:ptr[r + 1]])
            ign = np.nonzero(is_flat[ptr[r]:ptr[r + 1]])[0]
            res = minimize_barrier(jr, y[cols], ignore=ign if ign.size else None, backend=backend, **opts)
            y[cols] = res.y
            solved[r] = True
        det = np.linalg.det(sub(y))
    timings["solve_s"] = time.perf_counter() - t0

    # ---- the verdict: inverted tets, angles
    y_full = np.zeros(prob.elim.free.size)
    y_full[used] = y
    uvw = prob.corner_params(y_full)
    ang = _dihedral_sums(rings, uvw, is_flat)
    first = cen[Eu[ek, 0]]
    ev = np.stack([np.where(first, Eu[ek, 0], Eu[ek, 1]), np.where(first, Eu[ek, 1], Eu[ek, 0])], 1)
    expected = np.where(hexes >= 0, hexes * (math.pi / 2), np.nan)
    order = np.lexsort((ev[:, 1], e_ring))
    inverted = np.bincount(rings.ring_tet, weights=(det <= 0) & ~is_flat, minlength=N).astype(np.int64)
    eflat = np.bincount(um.tet_edges.numpy()[flat].reshape(-1), minlength=um.n_edges)
    timings["total_s"] = time.perf_counter() - t_all
    bnd_edge = (rep.boundary_expected >= 0)[oe][order]
    return OneRingReport(
        vertices=vertices, position=X[vertices], vertex_class=rep.vertex_class[vertices].astype(np.int8),
        inverted=inverted, flat=nflat, complex=ncx, solved=solved, n_tets=np.diff(ptr),
        edge_ring=e_ring[order], edge=oe[order], edge_verts=rings.orig_vertex[ev[order]], edge_hexes=hexes[order],
        edge_boundary=bnd_edge, edge_flat=eflat[ek][order], expected=expected[order], measured=ang[ek][order],
        timings=timings, options={"solve": solve, "edge_length": h, "features": features, "solver": opts})
