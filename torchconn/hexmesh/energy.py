"""The seamless map's fitting energy as a differentiable function of the frames.

For per-tet frames ``F_t`` the continuous seamless map of :mod:`.seamless` minimizes
``E(u) = sum_t vol_t || grad u_t (h F'_t) - I ||_F^2`` (``F'_t = F_t G[comb_t]`` the combed frame)
over the unknowns left free by the constraints, ``u = Z y + z0`` (:mod:`.elimination`), with
**every integer unknown relaxed** (continuous). Written in ``y``,
``E(y) = y^T A y - 2 b^T y + c`` (:meth:`.seamless.SeamlessProblem.energy_matrices`), so

    ``E_map(F) = min_y E(y) = c(F) - b(F)^T A^{-1} b(F)``.

Because every ``F'_t`` is orthogonal, ``|| grad u (h F') ||^2 = h^2 || grad u ||^2``: **``A`` does not
depend on the frames**, and ``b``, ``c`` are affine in them. With ``r = Z_c y + z0_c`` the corner
parameters, ``K = G^T W G`` (frame-free) and ``q(F) = G^T W g`` (per tet and corner ``k``,
``q_tk = vol_t h (B_t F'_t)[k]``, ``B_t (4, 3)`` the gradients of the barycentric coordinates):
``b(F) = Z_c^T (q(F) - K z0_c)``, ``c(F) = z0_c^T K z0_c - 2 z0_c . q(F) + 3 sum_t vol_t``.

:class:`MapEnergy` freezes everything combinatorial at construction, from a starting field: the
charts (cut, face matchings, combing), the constraints (boundary axes, singular and feature
lines, corners, the pinned vertex) and so ``Z``, ``z0`` and ``A``, which it factors **once**, and
the sparse matrix ``L = Z_c^T Q`` with ``q(F) = Q vec(F)`` (the combing folded in). Each call is
one sparse product ``b = b_const + L vec(F)`` and **one** solve (:meth:`.sparse.SPDSolve.inv_quad`:
the solve's output is also the gradient ``dE/db = -2 A^{-1} b``, so the backward runs no solve,
only ``L^T``; second derivatives are exact). Per-vertex frames go through
:func:`smooth_tet_frames` (:meth:`MapEnergy.from_vertex_frames`, :meth:`MapEnergy.of_vertex_frames`).

Conventions
-----------
* The value is ``E_map / sum_t vol_t`` (dimensionless; the same normalization as
  :attr:`.igm.IntegerGridMap.energy_continuous`): 0 when a map's gradient is exactly ``F^T / h``
  everywhere.
* Off the rotations (``F^T F != I``, e.g. the perturbations of a finite-difference check) the
  function is the extension with ``A`` kept frozen, ``c(F) - b(F)^T A^{-1} b(F)``: smooth, with exact
  derivatives of every order, equal to the fitting energy on rotations. Its gradient agrees
  with that of the fitting energy along every rotation (tangent directions ``F Omega``, ``Omega``
  skew), which is what an optimizer over rotations sees.
* The structure is frozen: frames that drift far from the start (a face matching, a boundary
  axis or the combing would change) still get the energy of the *frozen* structure. Build a new
  :class:`MapEnergy` when the structure changes.
* Computed in float64 whatever the input dtype (the value is a difference of two terms of size
  ``3 sum vol``, so its absolute round-off is about ``1e-15``); returned in the input dtype,
  gradients too. CPU (the solve, :mod:`.sparse`). ``torch.func.grad`` / ``vjp`` work;
  ``torch.compile`` runs the evaluation outside the graph (sparse matrices and a factorization:
  a graph break).
"""
from __future__ import annotations

import math
import time

import numpy as np
import scipy.sparse as sp
import torch

from ..frames.kernels.tet_frames import smooth_tet_frames_op, vertex_incidence
from .cut import group_matrices, tet_charts
from .seamless import FEATURE_MAX_DEG, build_problem, default_edge_length
from .solver import NotPositiveDefinite
from .sparse import SPDSolve

__all__ = ["MapEnergy", "smooth_tet_frames"]

_COMPILE_REASON = ("MapEnergy applies scipy sparse matrices and a CHOLMOD factorization built once, so torch.compile "
                   "runs it outside the graph")


def _check_frames(frames, n: int, what: str, who: str) -> torch.Tensor:
    if not torch.is_tensor(frames):
        frames = torch.as_tensor(np.asarray(frames))
    if frames.dim() != 3 or frames.shape != (n, 3, 3):
        raise ValueError(f"{who}: {what} must have shape ({n}, 3, 3), got {tuple(frames.shape)}")
    if frames.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{who}: {what} must be float32 or float64, got {frames.dtype}")
    if frames.device.type != "cpu":
        raise ValueError(f"{who}: {what} is on {frames.device}; the map energy runs on CPU (its sparse solve): "
                         f"move the frames with .cpu()")
    return frames


def _check_rotations(frames: torch.Tensor, what: str, who: str) -> None:
    """Raise unless every frame is a rotation (the start field defines the structure)."""
    from ..tolerances import get_eps

    F = frames.detach().to(torch.float64)
    if not torch.isfinite(F).all():
        bad = torch.nonzero(~torch.isfinite(F).flatten(1).all(1)).flatten()[:5].tolist()
        raise ValueError(f"{who}: {what} has non-finite entries (rows {bad})")
    tol = max(get_eps("rotation", frames.dtype), 1e-9) * 100
    err = (F.transpose(1, 2) @ F - torch.eye(3, dtype=F.dtype)).abs().amax(dim=(1, 2))
    bad = torch.nonzero((err > tol) | (torch.linalg.det(F) <= 0)).flatten()
    if bad.numel():
        raise ValueError(f"{who}: {what} must be rotations: {bad.numel()} are not (first rows {bad[:5].tolist()}, "
                         f"||F^T F - I|| up to {float(err.max()):.2e}); project them with so3.project_to_rotation")


def smooth_tet_frames(vertex_frames: torch.Tensor, mesh, matchings: torch.Tensor) -> torch.Tensor:
    """Per-tet frames ``(T, 3, 3)`` from per-vertex ``vertex_frames (V, 3, 3)``, differentiable everywhere.

    The rule of :func:`torchconn.frames.octahedral.tet_frames` (tet ``t`` with lowest vertex ``a``:
    ``F_a polar(F_a^T M)``, ``M`` the mean of its four vertex frames relabeled into ``F_a``'s labels
    through the edge ``matchings (E,)``), with the polar factor by a Newton iteration
    (scaled, stopped at convergence) instead of an SVD: the op ``torchconn::smooth_tet_frames``
    (:mod:`torchconn.frames.kernels.tet_frames`; a C kernel on CPU, its first-order backward in closed
    form over the tets and then the vertices). Same values to round-off; but ``octahedral.tet_frames`` is
    not differentiable where a tet's four relabeled frames agree exactly (it returns ``F_a`` there,
    whose gradient ignores the other three vertices; e.g. a constant field), and its SVD's
    derivative loses accuracy as singular values meet, while this one is smooth there.

    Raises:
        ValueError: a tet whose averaged frame has ``det <= 0`` (its vertex frames more than about
            90 degrees apart under the matchings: no nearest rotation varies smoothly there).
    """
    return smooth_tet_frames_op(vertex_frames, *_relabel_tables(mesh, matchings, vertex_frames.dtype))


def _relabel_tables(mesh, matchings: torch.Tensor, dtype: torch.dtype):
    """The tables of :func:`~torchconn.frames.kernels.tet_frames.smooth_tet_frames_op` for ``mesh`` and the
    edge ``matchings (E,)``: the relabeling of :func:`torchconn.frames.octahedral.tet_relabeling` (``g`` in
    ``dtype``) and the per-vertex incidence."""
    from ..frames import octahedral

    a, others, g = octahedral.tet_relabeling(mesh, matchings, dtype)
    return a, others, g, *vertex_incidence(a, others, mesh.n_vertices)


class _SparseLinear(torch.autograd.Function):
    """``M @ x`` for a fixed scipy CSR ``M (p, q)`` and ``x (q,)`` float64 (``MT`` its transpose, CSR):
    linear, so the backward ``MT @ g`` is this op again and every derivative is exact."""

    @staticmethod
    def forward(x, M, MT):
        return torch.from_numpy(M @ x.detach().numpy())

    @staticmethod
    def setup_context(ctx, inputs, output):
        _, ctx.M, ctx.MT = inputs

    @staticmethod
    def backward(ctx, g):
        return _SparseLinear.apply(g.contiguous(), ctx.MT, ctx.M), None, None


class MapEnergy:
    """The seamless map's minimal fitting energy of per-tet frames, differentiable (module docstring).

    Args:
        mesh: a ``TetMesh``.
        tet_frames0: ``(T, 3, 3)`` rotations (tensor or array), axes as columns: the start field
            that fixes the structure (charts, cut, matchings, combing, constraints).
        edge_length: the hex edge length ``h`` (default :func:`~.seamless.default_edge_length`).
        features: constrain feature curves and CAD corners (:func:`~.seamless.build_problem`).
        feature_max_deg: see :func:`~.seamless.build_problem`.
        face_match: ``(F,)`` face matchings to use (default the best ones of ``tet_frames0``;
            a repaired structure, e.g. :func:`~.straighten.straighten_singular_edges`, passes its own).
        backend: of the factorization (:class:`~.solver.SPDFactor`).

    Calling it: ``energy(tet_frames (T, 3, 3))`` -> 0-dim tensor, ``E_map / sum vol`` in the dtype of
    ``tet_frames`` (float32 / float64, CPU), differentiable (double backward exact); one solve.

    Attributes:
        mesh, edge_length, problem (:class:`~.seamless.SeamlessProblem`), charts
        (:class:`~.cut.TetCharts`), solver (:class:`~.sparse.SPDSolve` of ``A``), volume (the
        total), edge_matchings (``(E,)`` when built by :meth:`from_vertex_frames`, else ``None``),
        timings (the construction's steps, in s).

    Raises:
        ValueError: frames of the wrong shape, dtype, device or not rotations; a non-positive
            edge length. :class:`~.solver.NotPositiveDefinite`: ``A`` is singular (an unknown the
            objective does not see, a degenerate tet).
    """

    def __init__(self, mesh, tet_frames0, edge_length: float | None = None, *, features: bool = True,
                 feature_max_deg: float = FEATURE_MAX_DEG, face_match=None, backend: str = "auto"):
        who = "MapEnergy"
        t_start = time.perf_counter()
        F0 = _check_frames(tet_frames0, mesh.n_tets, "tet_frames0", who)
        _check_rotations(F0, "tet_frames0", who)
        h = default_edge_length(mesh) if edge_length is None else edge_length
        if not (isinstance(h, (int, float)) and math.isfinite(h) and h > 0):
            raise ValueError(f"{who}: edge_length must be a positive finite number, got {edge_length!r}")
        self.mesh = mesh
        self.edge_length = float(h)
        self.edge_matchings = None
        timings = {}
        t0 = time.perf_counter()
        self.charts = tet_charts(mesh, F0.detach().to(torch.float64), face_match)
        timings["charts_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.problem = prob = build_problem(mesh, self.charts, self.edge_length, features=features,
                                            feature_max_deg=feature_max_deg)
        timings["problem_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        A, _, _ = prob.energy_matrices()
        T = mesh.n_tets
        rows = prob.corner_var.reshape(-1)  # (12 T,): corner unknown 12 t + 3 k + i
        Zc = prob.elim.Z[rows].tocoo()
        z0c = prob.elim.z0[rows]
        vol = prob.vol
        # K z0_c with K = G^T W G (frame-free: the G of any rotations gives the same K)
        Kz0 = prob.G.T @ (np.repeat(vol, 9) * (prob.G @ z0c))
        b_const = -(Zc.T @ Kz0)
        c_const = float(z0c @ Kz0) + 3.0 * float(vol.sum())
        # h B_t (4, 3) from G's documented layout: G[9t + 3i + k, 12t + 3k' + i] = h (B_t F'_t)[k', k]
        t_i = np.arange(T)[:, None, None]
        k_i = np.arange(3)[None, None, :]
        kp_i = np.arange(4)[None, :, None]
        coef = np.asarray(prob.G[np.broadcast_to(9 * t_i + k_i, (T, 4, 3)).reshape(-1),
                                 np.broadcast_to(12 * t_i + 3 * kp_i, (T, 4, 3)).reshape(-1)]).reshape(T, 4, 3)
        hB = coef @ np.transpose(self.charts.frames, (0, 2, 1))  # h B_t = (h B_t F'_t) F'_t^T
        # q = Q vec(F): q[t, k, i] = sum_j vol_t h B_t[k, j] (F_t G[comb_t])[j, i]; G[comb_t] is a signed
        # permutation, (F G)[j, i] = s_ti F[j, p_ti]: row 12t + 3k + i, column 9t + 3j + p_ti
        Gc = group_matrices()[self.charts.comb].astype(np.float64)  # (T, 3, 3)
        p = np.abs(Gc).argmax(1)  # (T, 3): the row l of the non-zero in column i
        sgn = np.take_along_axis(Gc, p[:, None, :], 1)[:, 0]  # (T, 3)
        vhB = vol[:, None, None] * hB  # (T, 4, 3): [t, k, j]
        shape = (T, 4, 3, 3)  # (t, k, i, j)
        t_, k_, i_, j_ = (np.broadcast_to(a, shape) for a in np.ix_(np.arange(T), np.arange(4), np.arange(3),
                                                                    np.arange(3)))
        Q = sp.csr_matrix(((vhB[:, :, None, :] * sgn[:, None, :, None]).reshape(-1),
                           ((12 * t_ + 3 * k_ + i_).reshape(-1), (9 * t_ + 3 * j_ + p[:, None, :, None]).reshape(-1))),
                          shape=(12 * T, 9 * T))
        L = (Zc.T.tocsr() @ Q).tocsr()  # b(F) = b_const + L vec(F)
        self._L = L
        self._LT = L.T.tocsr()
        self._lc = torch.as_tensor(-2.0 * (Q.T @ z0c))  # c(F) = c_const + lc . vec(F)
        self._Zc = Zc.tocsr()
        self._ZcT = Zc.T.tocsr()
        self._z0c = torch.as_tensor(z0c)
        self._b_const = torch.as_tensor(b_const, dtype=torch.float64)
        self._c_const = c_const
        self.volume = float(vol.sum())
        self.n_unknowns = int(A.shape[0])
        timings["assemble_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        As = ((A + A.T) * 0.5).tocoo()
        idx = torch.as_tensor(np.stack([As.row, As.col]), dtype=torch.int64)
        try:
            self.solver = SPDSolve(idx, torch.as_tensor(As.data, dtype=torch.float64), self.n_unknowns, backend=backend)
        except NotPositiveDefinite as exc:
            raise NotPositiveDefinite(f"{who}: the seamless map's normal matrix ({self.n_unknowns} unknowns, "
                                      f"{T} tets) cannot be factored: {exc}") from exc
        timings["factor_s"] = time.perf_counter() - t0
        timings["total_s"] = time.perf_counter() - t_start
        self.timings = timings

    # ------------------------------------------------------------------ construction from vertex frames
    @classmethod
    def from_vertex_frames(cls, mesh, vertex_frames0, edge_length: float | None = None, **kwargs) -> "MapEnergy":
        """A :class:`MapEnergy` of per-vertex frames ``(V, 3, 3)``: the edge matchings of
        ``vertex_frames0`` (:func:`torchconn.frames.octahedral.match_edges`) are fixed, the per-tet
        start field is :func:`smooth_tet_frames` of them; evaluate with :meth:`of_vertex_frames`.
        ``kwargs`` as the constructor's."""
        from ..frames import octahedral

        vf0 = _check_frames(vertex_frames0, mesh.n_vertices, "vertex_frames0", "MapEnergy.from_vertex_frames")
        _check_rotations(vf0, "vertex_frames0", "MapEnergy.from_vertex_frames")
        vf0 = vf0.detach().to(torch.float64)
        matchings = octahedral.match_edges(vf0, mesh.edges)[0]
        tables = _relabel_tables(mesh, matchings, torch.float64)
        energy = cls(mesh, smooth_tet_frames_op(vf0, *tables), edge_length, **kwargs)
        energy.edge_matchings = matchings
        energy._relabel = tables
        return energy

    def of_vertex_frames(self, vertex_frames: torch.Tensor) -> torch.Tensor:
        """The energy of per-vertex frames ``(V, 3, 3)`` through :func:`smooth_tet_frames` with the
        edge matchings fixed at construction (:meth:`from_vertex_frames`); differentiable."""
        if self.edge_matchings is None:
            raise ValueError("MapEnergy.of_vertex_frames needs the edge matchings of a start field: build the energy "
                             "with MapEnergy.from_vertex_frames")
        vf = _check_frames(vertex_frames, self.mesh.n_vertices, "vertex_frames", "MapEnergy.of_vertex_frames")
        if vf.dtype != self._relabel[2].dtype:  # the matchings in the frames' dtype, converted once
            a, others, g, inc_ptr, inc = self._relabel
            self._relabel = (a, others, g.to(vf.dtype), inc_ptr, inc)
        return self(smooth_tet_frames_op(vf, *self._relabel))

    # ------------------------------------------------------------------ evaluation
    @torch.compiler.disable(reason=_COMPILE_REASON)
    def rhs(self, tet_frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(b (m,), c ())`` of ``E(y) = y^T A y - 2 b^T y + c`` for ``tet_frames (T, 3, 3)``, float64,
        differentiable: ``b = b_const + L vec(F)``, ``c = c_const + l_c . vec(F)`` (module docstring; ``L``
        a sparse matrix built once)."""
        F = _check_frames(tet_frames, self.mesh.n_tets, "tet_frames", "MapEnergy").to(torch.float64)
        f = F.reshape(-1)
        b = self._b_const + _SparseLinear.apply(f, self._L, self._LT)
        c = self._c_const + self._lc @ f
        return b, c

    @torch.compiler.disable(reason=_COMPILE_REASON)
    def __call__(self, tet_frames: torch.Tensor) -> torch.Tensor:
        """``E_map(F) / sum vol``: 0-dim tensor in ``tet_frames``' dtype (module docstring)."""
        b, c = self.rhs(tet_frames)
        return ((c - self.solver.inv_quad(b)) / self.volume).to(tet_frames.dtype)

    @torch.compiler.disable(reason=_COMPILE_REASON)
    def corner_params(self, tet_frames: torch.Tensor) -> torch.Tensor:
        """``(T, 4, 3)`` parameters of the tet corners of the continuous optimal map (chart of each
        tet; integers relaxed), differentiable: ``Z_c A^{-1} b(F) + z0_c`` (one solve)."""
        b, _ = self.rhs(tet_frames)
        r = _SparseLinear.apply(self.solver(b), self._Zc, self._ZcT) + self._z0c
        return r.reshape(self.mesh.n_tets, 4, 3).to(tet_frames.dtype)

    def __repr__(self) -> str:
        return (f"MapEnergy({self.mesh.n_tets} tets, h={self.edge_length:.4g}, {self.n_unknowns} unknowns, "
                f"backend={self.solver.backend!r})")
