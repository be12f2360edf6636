"""The seamless parametrization: unknowns, constraints, frame-fitting objective, one sparse solve.

Unknowns (HEXMESH.md steps 3-5; CubeCover, Nieser et al. 2011)
-----------------------------------------------------------------
* one parameter ``u in R^3`` per *corner copy*: the corners ``(t, k)`` of the tets (``k`` the local
  corner, vertex ``mesh.tets[t, k]``) merged across every un-cut face (their charts agree there,
  :mod:`.cut`); variable ``3 c + i`` is coordinate ``i`` of copy ``c``;
* a translation ``s_f in Z^3`` per cut face (integer);
* an integer per boundary face (the integer plane it lies on), two per meshable singular edge and
  per constrained feature edge (the integer line), three per CAD corner.

Constraints (rows of :class:`~.elimination.ConstraintRows`, eliminated exactly)
-----------------------------------------------------------------------------------
* cut face ``f = (t0, t1)``, each vertex ``v``: ``u_{t1}(v) = R_f u_{t0}(v) + s_f``;
* boundary face of tet ``t`` with outward normal ``n``: coordinate ``k = argmax_k |(F_t^T n)_k|``
  of its three corners equals the face's integer;
* meshable singular edge (a quarter or half turn about its parameter axis ``k``), in its start
  tet's chart: the two other coordinates of both endpoints equal the edge's two integers (the
  transitions around the edge already put it on the turn's fixed line; this makes the line an
  integer line);
* feature edge (a sharp CAD curve, or a dihedral feature of an untagged mesh) whose direction
  in a tet's chart is within ``feature_max_deg`` of a parameter axis ``k``: the other two
  coordinates of both endpoints equal the edge's two integers;
* CAD corner: its three coordinates are integers;
* one vertex pinned at the origin (a corner, else a singular-edge vertex, else a boundary
  vertex): the map is defined up to an integer translation.

Objective: ``E(u) = sum_t vol_t || grad u_t (h F_t) - I ||_F^2`` with ``F_t`` the combed tet frame
and ``h`` the hex edge length (``grad u_t`` is exact for the linear map on tet ``t``); after the
elimination ``u = Z y + z0`` it is a quadratic in the free unknowns ``y`` whose normal equations
``A y = b`` are solved by one sparse Cholesky factorization (:mod:`.solver`). With per-tet target
coframes ``B_t`` (the integrable frames of :mod:`.integrable`; ``targets=`` or
:meth:`SeamlessProblem.with_targets`) the rows are ``grad u_t B_t^-1 - I`` instead: ``B_t = F_t^T / h``
is the default. The constraints (and their axes) stay those of the frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
import torch

from .cut import TetCharts, face_corner_pairs, group_matrices
from .elimination import ConstraintRows, Elimination, eliminate

__all__ = ["SeamlessProblem", "build_problem", "default_edge_length", "INTEGER_KINDS", "FEATURE_MAX_DEG"]

INTEGER_KINDS = ("translation", "boundary", "singular", "feature", "corner")
"""What each integer unknown stands for (codes of :attr:`SeamlessProblem.var_kind` minus 1; 0 = continuous)."""


DEFAULT_EDGE_LENGTH_FACTOR = 0.5
"""The default hex edge length is this times the mean edge length of the tet mesh."""

FEATURE_MAX_DEG = 15.0
"""Degrees: a feature edge whose parametric direction is farther than this from every parameter
axis is left free (``feature_max_deg``; the default of every function and job option that takes it).
15 since 2026-11-27 (30 before), chosen together with the repair's slides (``repair_slide``) on
the 35 HexMe ``c`` models: more valid maps and CAD corners meshed, the same good hex meshes, 1.3x
the job time; 15 alone, or the slides alone, gained no valid map (docs/results/hexmesh.md)."""


def default_edge_length(mesh) -> float:
    """The default hex edge length ``h``: half the mean edge length of the tet mesh.

    HEXMESH.md's rule ``h = (volume / target hex count)^(1/3)`` (AlgoHex) with a target of
    ``8 volume / mean_edge^3`` hexes. Measured on the 17 simple HexMe ``c`` meshes with the
    default field (docs/results/hexmesh.md): with the mean edge length itself, 4 good hex meshes
    (the prism's 16 hexes have 10.5% irregular edges and the notch's boundary is 1.3% off); with
    half of it, 5, the maps' validity unchanged (it is decided by the singular structure, not by
    ``h``).
    """
    X = mesh.vertices.detach().cpu().double()
    e = mesh.edges.cpu()
    return DEFAULT_EDGE_LENGTH_FACTOR * float((X[e[:, 1]] - X[e[:, 0]]).norm(dim=1).mean())


@dataclass
class SeamlessProblem:
    """The constrained least-squares problem of a seamless parametrization (module docstring).

    Attributes:
        charts: the :class:`~.cut.TetCharts` it was built from.
        edge_length: ``h``.
        corner_copy: ``(T, 4)`` int64, the copy of each tet corner.
        n_copies: number of copies.
        n_vars: number of unknowns; ``var_kind (n_vars,)`` int8 (0 continuous, else
            ``1 + INTEGER_KINDS.index(kind)``).
        elim: the :class:`~.elimination.Elimination` of the constraints.
        G: ``(9T, 12T)`` CSR, ``g (9T,)``: ``grad u_t (h F_t) - I`` per tet, row ``9t + 3i + k``
            (component ``i``, frame axis ``k``) over the corner unknowns ``12 t + 3 k' + i``
            (``k'`` the local corner); ``vol (T,)`` the tet volumes (weights).
        corner_var: ``(T, 4, 3)`` int64, the unknown of each corner coordinate.
        boundary_axis: ``(B,)`` the parameter axis of each boundary face (rows of
            ``mesh.boundary_faces``) and ``boundary_tet (B,)`` its tet.
        feature_edges: ``(K, 2)`` the feature edges; ``feature_constrained (K,)`` bool, those
            close enough to a parameter axis to be constrained; ``corner_vertices (C,)``.
        pinned_vertex: the pinned vertex.
        counts: sizes, for reports.
        tet_grad: ``(T, 3, 3)`` the gradients of the barycentric differences (``grad u_t = U_t^T D_t``
            with ``U_t`` the corner differences ``u_m - u_0``): what :meth:`with_targets` rebuilds ``G`` from.
        targets: ``(T, 3, 3)`` the target coframes ``B_t`` of the objective, ``None`` for the frames'
            ``F_t^T / h``.
    """

    charts: TetCharts
    edge_length: float
    corner_copy: np.ndarray
    n_copies: int
    n_vars: int
    var_kind: np.ndarray
    elim: Elimination
    G: sp.csr_matrix
    g: np.ndarray
    vol: np.ndarray
    corner_var: np.ndarray
    boundary_axis: np.ndarray
    boundary_tet: np.ndarray
    feature_edges: np.ndarray
    feature_constrained: np.ndarray
    corner_vertices: np.ndarray
    pinned_vertex: int
    counts: dict = field(default_factory=dict)
    tet_grad: np.ndarray | None = field(default=None, repr=False)
    targets: np.ndarray | None = field(default=None, repr=False)

    @property
    def free_is_int(self) -> np.ndarray:
        return self.elim.free_is_int

    def corner_params(self, y: np.ndarray) -> np.ndarray:
        """``(T, 4, 3)`` parameters of the tet corners from the free unknowns ``y``."""
        x = self.elim.expand(y)
        return x[self.corner_var]

    def energy_matrices(self, weights: np.ndarray | None = None) -> tuple[sp.csr_matrix, np.ndarray, float]:
        """``(A, b, c)`` with ``E(y) = y^T A y - 2 b^T y + c`` for tet weights ``vol * weights``."""
        w = self.vol if weights is None else self.vol * weights
        W = sp.diags(np.repeat(w, 9))
        GZ = (self.G @ self.elim.Z[self._corner_rows()]).tocsr()
        r0 = self.G @ self.elim.z0[self._corner_rows()] - self.g
        A = (GZ.T @ W @ GZ).tocsr()
        b = -(GZ.T @ (W @ r0))
        c = float(r0 @ (W @ r0))
        return A, b, c

    def with_targets(self, targets) -> "SeamlessProblem":
        """The same problem (unknowns, constraints, elimination) fitting target coframes ``targets
        (T, 3, 3)`` (rows: parameter gradients in world space, in each tet's chart; e.g.
        :attr:`.integrable.IntegrableFrames.coframes`): objective rows ``grad u_t B_t^-1 - I``.

        Raises:
            ValueError: a shape other than ``(T, 3, 3)``, non-finite entries, or a coframe whose
            determinant is not positive (naming the first tets).
        """
        if self.tet_grad is None:
            raise ValueError("this SeamlessProblem was built without tet_grad; rebuild it with build_problem")
        B = _check_targets(targets, self.tet_grad.shape[0])
        G = _objective_rows(self.tet_grad @ np.linalg.inv(B))
        return replace(self, G=G, targets=B)

    def _corner_rows(self) -> np.ndarray:
        return self.corner_var.reshape(-1)

    def flat_tets(self, samples: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The tets that the constraints flatten: zero parametric volume for **every** value of the
        free unknowns. No map is valid while one is left.

        Decided with exact arithmetic at random points: the corner parameters are affine in the
        free unknowns with dyadic coefficients, so at integer unknowns they are dyadic and the
        exact :func:`~.predicates.orient3d` decides each tet's volume; a tet whose volume (a cubic
        polynomial in the unknowns) is zero at ``samples`` independent random points in
        ``[-2^10, 2^10]^m`` is identically zero but with a probability below ``(3/2049)^samples``
        per tet (Schwartz-Zippel). ``seed`` makes it deterministic.

        Returns:
            ``(flat (k,), collapsed (k,) bool, line_face (k,) int)``: the flat tets; those with
            two corners that the constraints send to **one point** (a collapsed edge: singular or
            feature curves, or a zig-zag of one, that the constraints make meet; no refinement
            opens it, the singular structure must change); and for each, a local face (the one
            opposite that corner) whose three corners the constraints put on **one line** (``-1``
            if none: the tet is only coplanar, and a free vertex anywhere in it opens it).
        """
        from .predicates import orient3d

        rng = np.random.default_rng(seed)
        m = self.elim.free.size
        T = self.corner_var.shape[0]
        flat = np.ones(T, bool)
        same = np.ones((T, 6), bool)  # corner pairs (0,1) (0,2) (0,3) (1,2) (1,3) (2,3) equal so far
        line = np.ones((T, 4), bool)  # the face opposite corner k has collinear corners so far
        pa, pb = np.array([0, 0, 0, 1, 1, 2]), np.array([1, 2, 3, 2, 3, 3])
        opp = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
        for _ in range(samples):
            y = rng.integers(-1024, 1025, size=m).astype(np.float64)
            uvw = self.corner_params(y)
            flat &= orient3d(uvw[:, 0], uvw[:, 1], uvw[:, 2], uvw[:, 3]) == 0
            same &= (uvw[:, pa] == uvw[:, pb]).all(-1)
            for k in range(4):
                a, b, c = uvw[:, opp[k, 0]], uvw[:, opp[k, 1]], uvw[:, opp[k, 2]]
                # dyadic input: the cross product's components are exact enough to test for zero
                # (every product and sum of a few dyadics with small exponents is exact in float64)
                line[:, k] &= (np.cross(b - a, c - a) == 0).all(-1)
            if not flat.any():
                break
        idx = np.nonzero(flat)[0]
        collapsed = same[idx].any(1)
        lf = np.where(line[idx].any(1), line[idx].argmax(1), -1)
        return idx, collapsed, lf

# ----------------------------------------------------------------------------- building
def _check_targets(targets, T: int) -> np.ndarray:
    B = np.asarray(targets.detach().cpu() if isinstance(targets, torch.Tensor) else targets, np.float64)
    if B.shape != (T, 3, 3):
        raise ValueError(f"targets must have shape (T, 3, 3) = ({T}, 3, 3), got {B.shape}")
    bad = np.nonzero(~np.isfinite(B).all((1, 2)))[0]
    if bad.size:
        raise ValueError(f"targets have non-finite entries (tets {bad[:5].tolist()})")
    bad = np.nonzero(~(np.linalg.det(B) > 0))[0]
    if bad.size:
        raise ValueError(f"targets must have positive determinants; {bad.size} do not (tets {bad[:5].tolist()})")
    return B


def _objective_rows(M: np.ndarray) -> sp.csr_matrix:
    """``G (9T, 12T)``: row ``9t + 3i + k`` of ``grad u_t M_t`` (``M (T, 3, 3)``, rows ``m`` for corner
    ``m + 1``) over the corner unknowns ``12 t + 3 k' + i``."""
    T = M.shape[0]
    coef = np.concatenate([-M.sum(1, keepdims=True), M], 1)  # (T, 4, 3): corner k', axis k
    t_idx = np.arange(T)[:, None, None, None]
    i_idx = np.arange(3)[None, :, None, None]
    k_idx = np.arange(3)[None, None, :, None]
    kp = np.arange(4)[None, None, None, :]
    rr = np.broadcast_to(9 * t_idx + 3 * i_idx + k_idx, (T, 3, 3, 4))
    cc = np.broadcast_to(12 * t_idx + 3 * kp + i_idx, (T, 3, 3, 4))
    vv = np.broadcast_to(np.transpose(coef, (0, 2, 1))[:, None, :, :], (T, 3, 3, 4))
    return sp.csr_matrix((vv.reshape(-1), (rr.reshape(-1), cc.reshape(-1))), shape=(9 * T, 12 * T))


def build_problem(mesh, charts: TetCharts, edge_length: float, *, features=True,
                  feature_max_deg: float = FEATURE_MAX_DEG, targets=None, plane_faces=None) -> SeamlessProblem:
    """Unknowns, constraints (eliminated) and objective of the seamless map (module docstring).

    Args:
        mesh: the ``TetMesh``; ``charts``: its :func:`~.cut.tet_charts`.
        edge_length: ``h > 0``, in the mesh's length unit.
        features: constrain feature edges and CAD corners (a mesh's CAD tags or its dihedral
            features, as :class:`torchconn.frames.constraints.BoundaryConstraint` finds them);
            or a pair ``(feature_edges (K, 2), corner_vertices (C,))`` of vertex ids to constrain
            instead (a piece of a larger mesh keeps the features of the whole: :mod:`.one_ring`).
        feature_max_deg: feature edges whose parametric direction is farther than this from
            every axis are left free (the field does not follow them; forcing them would fold
            the map); their number is in ``counts``.
        targets: ``(T, 3, 3)`` target coframes ``B_t`` (:meth:`SeamlessProblem.with_targets`);
            ``None``: the frames' ``F_t^T / h``.
        plane_faces: ``(B,)`` bool over the rows of ``mesh.boundary_faces``: the boundary faces
            held on a parametric plane (default all; a one-ring's link faces are left free).
    """
    if not (isinstance(edge_length, (int, float)) and math.isfinite(edge_length) and edge_length > 0):
        raise ValueError(f"edge_length must be a positive finite number, got {edge_length!r}")
    h = float(edge_length)
    tets = mesh.tets.cpu().numpy()
    faces = mesh.faces.cpu().numpy()
    face_tets = mesh.face_tets.cpu().numpy()
    tet_faces = mesh.tet_faces.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    X = mesh.vertices.detach().cpu().double().numpy()
    T, F = tets.shape[0], faces.shape[0]
    Gm = group_matrices()
    frames = charts.frames

    # ---- corner copies: union of corners across un-cut interior faces
    fc = face_corner_pairs(tets, faces, tet_faces, face_tets)  # (F, 2, 3)
    glue = charts.interior_face & ~charts.cut
    gf = np.nonzero(glue)[0]
    a = (face_tets[gf, 0][:, None] * 4 + fc[gf, 0]).reshape(-1)
    b = (face_tets[gf, 1][:, None] * 4 + fc[gf, 1]).reshape(-1)
    adj = sp.coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(4 * T, 4 * T))
    n_copies, label = connected_components(adj, directed=False)
    corner_copy = label.reshape(T, 4).astype(np.int64)

    # ---- unknowns
    cutf = np.nonzero(charts.cut)[0]
    bf_index = mesh.boundary_face_index.cpu().numpy()
    B = bf_index.size
    sing = np.nonzero(charts.singular_edge & charts.edge_meshable)[0]
    from ..frames.constraints import BoundaryConstraint  # the one home of feature edges

    if isinstance(features, tuple):
        fedges = np.asarray(features[0], np.int64).reshape(-1, 2)
        corners = np.asarray(features[1], np.int64).reshape(-1)
    elif features:
        bc = BoundaryConstraint.from_mesh(mesh)
        fedges = (bc.feature_edges.cpu().numpy() if bc.feature_edges is not None else np.zeros((0, 2), np.int64))
        corners = (bc.corner_vertices.cpu().numpy() if bc.corner_vertices is not None else np.zeros(0, np.int64))
    else:
        fedges, corners = np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    K, C = fedges.shape[0], corners.size
    # feature edges close enough to a parameter axis (in the chart of a tet at the edge)
    fcon = np.zeros(K, bool)
    if K:
        eid, _ = mesh.edge_index(torch.as_tensor(fedges[:, 0]), torch.as_tensor(fedges[:, 1]))
        eid = eid.cpu().numpy()
        ft = charts.edge_start_tet[eid]
        d = X[fedges[:, 1]] - X[fedges[:, 0]]
        dpar = np.einsum("kji,kj->ki", frames[ft], d)
        dn = dpar / np.linalg.norm(dpar, axis=1, keepdims=True)
        fax = np.abs(dn).argmax(1)
        fcon = np.abs(dn[np.arange(K), fax]) >= math.cos(math.radians(feature_max_deg))
    fidx = np.nonzero(fcon)[0]
    off = {}
    n = 3 * n_copies
    for name, size in (("translation", 3 * cutf.size), ("boundary", B), ("singular", 2 * sing.size),
                       ("feature", 2 * fidx.size), ("corner", 3 * C)):
        off[name] = n
        n += size
    var_kind = np.zeros(n, np.int8)
    ends = [off[k] for k in INTEGER_KINDS[1:]] + [n]
    for code, (name, end) in enumerate(zip(INTEGER_KINDS, ends), start=1):
        var_kind[off[name]:end] = code
    corner_var = 3 * corner_copy[:, :, None] + np.arange(3)  # (T, 4, 3)

    rows = ConstraintRows()
    # ---- cut faces: u_B[i] - R[i, j] u_A[j] - s_f[i] = 0
    if cutf.size:
        R = Gm[charts.face_rot[cutf]]  # (n, 3, 3)
        j_of = np.abs(R).argmax(2)  # (n, 3): column of the nonzero in row i
        sgn = np.take_along_axis(R, j_of[:, :, None], 2)[:, :, 0]  # (n, 3)
        t0, t1 = face_tets[cutf, 0], face_tets[cutf, 1]
        s_var = off["translation"] + 3 * np.arange(cutf.size)[:, None] + np.arange(3)  # (n, 3)
        for m in range(3):  # the three vertices of each cut face
            ca = corner_copy[t0, fc[cutf, 0, m]]
            cb = corner_copy[t1, fc[cutf, 1, m]]
            for i in range(3):
                vars_ = np.stack([3 * cb + i, 3 * ca + j_of[:, i], s_var[:, i]], 1)
                coefs = np.stack([np.ones(cutf.size), -sgn[:, i], -np.ones(cutf.size)], 1)
                rows.add_many(vars_, coefs, label="cut face")

    # ---- boundary faces: coordinate k of the three corners equals the face's integer
    bt = np.where(face_tets[bf_index, 0] >= 0, face_tets[bf_index, 0], face_tets[bf_index, 1])
    bfaces = mesh.boundary_faces.cpu().numpy()
    P = X[bfaces]
    nrm = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    npar = np.einsum("bji,bj->bi", frames[bt], nrm)
    baxis = np.abs(npar).argmax(1)
    slot = np.argmax(tet_faces[bt] == bf_index[:, None], axis=1)  # local slot of the face in its tet
    bvar = off["boundary"] + np.arange(B)
    held = np.ones(B, bool) if plane_faces is None else np.asarray(plane_faces, bool)
    if held.shape != (B,):
        raise ValueError(f"plane_faces must be a ({B},) bool mask over the boundary faces, got shape {held.shape}")
    for m in range(3):
        loc = (slot + 1 + m) % 4  # the three other local corners
        cv = corner_var[bt, loc, baxis]
        rows.add_many(np.stack([cv, bvar], 1)[held], np.array([1.0, -1.0]), label="boundary plane")

    # ---- singular edges: transverse coordinates of both endpoints equal two integers
    if sing.size:
        st = charts.edge_start_tet[sing]
        ax = charts.edge_axis[sing]
        la = np.argmax(tets[st] == edges[sing, 0][:, None], axis=1)
        lb = np.argmax(tets[st] == edges[sing, 1][:, None], axis=1)
        others = np.stack([(ax + 1) % 3, (ax + 2) % 3], 1)
        for q in range(2):
            mvar = off["singular"] + 2 * np.arange(sing.size) + q
            for loc in (la, lb):
                cv = corner_var[st, loc, others[:, q]]
                rows.add_many(np.stack([cv, mvar], 1), np.array([1.0, -1.0]), label="singular line")

    # ---- feature edges and corners
    if fidx.size:
        la = np.argmax(tets[ft] == fedges[:, 0][:, None], axis=1)
        lb = np.argmax(tets[ft] == fedges[:, 1][:, None], axis=1)
        others = np.stack([(fax + 1) % 3, (fax + 2) % 3], 1)
        for q in range(2):
            mvar = off["feature"] + 2 * np.arange(fidx.size) + q
            for loc in (la, lb):
                cv = corner_var[ft[fidx], loc[fidx], others[fidx, q]]
                rows.add_many(np.stack([cv, mvar], 1), np.array([1.0, -1.0]), label="feature line")
    if C:
        # a tet at each corner vertex: the first tet listing it
        first = np.full(X.shape[0], tets.size, np.int64)
        np.minimum.at(first, tets.reshape(-1), np.arange(tets.size))
        ct, cl = first[corners] // 4, first[corners] % 4
        for i in range(3):
            mvar = off["corner"] + 3 * np.arange(C) + i
            rows.add_many(np.stack([corner_var[ct, cl, i], mvar], 1), np.array([1.0, -1.0]), label="corner point")

    # ---- pin one vertex at the origin
    if C:
        pin_t, pin_l = int(ct[0]), int(cl[0])
    elif sing.size:
        pin_t = int(charts.edge_start_tet[sing[0]])
        pin_l = int(np.argmax(tets[pin_t] == edges[sing[0], 0]))
    else:
        pin_t = int(bt[0]) if B else 0
        pin_l = int((slot[0] + 1) % 4) if B else 0
    for i in range(3):
        rows.add([corner_var[pin_t, pin_l, i]], [1.0], 0.0, label="pinned point")
    pinned_vertex = int(tets[pin_t, pin_l])

    is_int = var_kind > 0
    elim = eliminate(rows, n, is_int)

    # ---- objective rows: grad u_t (h F_t) - I
    Xt = X[tets]  # (T, 4, 3)
    Em = np.transpose(Xt[:, 1:] - Xt[:, :1], (0, 2, 1))  # (T, 3, 3) columns x_m - x_0
    D = np.linalg.inv(Em)  # (T, 3, 3): grad of the barycentric-difference coordinates
    if targets is None:
        M = D @ frames * h  # (T, 3, 3), rows m (corner m+1), columns k (frame axis)
    else:
        targets = _check_targets(targets, T)
        M = D @ np.linalg.inv(targets)
    vol = np.abs(np.linalg.det(Em)) / 6.0
    # row 9t + 3i + k, column 12t + 3k' + i (corner-major unknowns of corner_var's order)
    G = _objective_rows(M)
    g = np.broadcast_to(np.eye(3).reshape(1, 9), (T, 9)).reshape(-1).copy()

    counts = {
        "tets": int(T), "corner_copies": int(n_copies), "unknowns": int(n), "rows": len(rows),
        "free_unknowns": int(elim.free.size), "free_integers": int(elim.free_is_int.sum()),
        "redundant_rows": int(elim.redundant), "conflicting_rows": len(elim.conflicts),
        "relaxed_integers": len(elim.relaxed_integers), "cut_faces": int(cutf.size),
        "boundary_faces": int(B), "singular_edges_constrained": int(sing.size),
        "feature_edges": int(K), "feature_edges_constrained": int(fcon.sum()),
        "feature_edges_free": int(K - fidx.size), "corners": int(C),
    }
    return SeamlessProblem(charts=charts, edge_length=h, corner_copy=corner_copy, n_copies=int(n_copies), n_vars=n,
                           var_kind=var_kind, elim=elim, G=G, g=g, vol=vol, corner_var=corner_var,
                           boundary_axis=baxis, boundary_tet=bt, feature_edges=fedges, feature_constrained=fcon,
                           corner_vertices=corners, pinned_vertex=pinned_vertex, counts=counts, tet_grad=D,
                           targets=targets)
