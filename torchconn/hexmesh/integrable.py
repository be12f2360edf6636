"""Integrable coframes: the frames a seamless map can follow, as a torsion problem (issue 31, step 2).

A seamless map ``u`` is piecewise linear, one chart per tet; on tet ``t`` its gradient is a
*coframe* ``B_t = grad u_t (3, 3)`` (rows: the world-space gradients of the three parameter
coordinates, in tet ``t``'s combed chart, :mod:`.cut`). The rotation field gives the coframes
``B_t = (h F_t)^-1 = F_t^T / h`` that the least-squares map of :mod:`.seamless` fits; they are
not gradients (not *integrable*) wherever the field turns, and a map that fits them folds where
the mismatch is large. This stage finds coframes close to the field's that are integrable up to
a small residual, and the map then fits those (:meth:`.seamless.SeamlessProblem.with_targets`).

The corner complex and its torsion (report Sec. 3.3, Def. 3.2; CONVENTIONS.md §1)
-------------------------------------------------------------------------------------
* **Vertices** are the tet corners ``(t, v)``; the fiber of ``(t, v)`` is tet ``t``'s chart.
* **Edges**: inside a tet, ``(t, a) - (t, b)`` with connection ``I`` and solder form
  ``theta = B_t (x_b - x_a)`` (the coframe's solder form, :func:`torchconn.torsion.solder_form`
  of the corner complex with ``frames = B_t^T``: for the rotation field it is the usual
  ``F_t^T (x_b - x_a) / h``); across an interior face ``f = (t0, t1)`` (``mesh.face_tets``) with
  transition ``u_t1 = R_f u_t0 + s_f``, the link ``(t0, v) - (t1, v)`` with connection
  ``R_{(t0,v),(t1,v)} = R_f^T`` (fiber of ``t1`` -> fiber of ``t0``) and solder form ``0``.
* **2-cells**: for every interior face and each of its three edges ``(a, b)``, the quad
  ``[x0, x1, x2, x3] = [(t0,a), (t0,b), (t1,b), (t1,a)]`` with
  ``loop_rot = [I, R_f^T, I, R_f]`` (``loop_rot[k] = R_{x_k x_{k+1}}``).

Its loop torsion (:func:`torchconn.torsion.two_prong`, cut ``0``: the whole loop as ``gamma1``)
with ``theta_fwd = [B_t0 e, 0, -B_t1 e, 0]``, ``e = x_b - x_a``, is

.. code-block:: text

    Theta_q = B_t0 e - R_f^T B_t1 e          (in the fiber of (t0, a): tet t0's chart)

the tangential jump of the coframes across the face: ``B`` is the gradient of a seamless map
exactly when ``Theta_q = 0`` on every quad (then ``grad u_t1 = R_f grad u_t0`` along the face, the
map's two linear pieces agree on it up to the translation ``s_f``). :func:`quad_torsion` computes
it with the library's operator; the tests hold it equal to the jump formula on every face and
zero on the gradients of seamless maps (identity, rotated, the valence-3 prism).

The energy (AlgoHex's ``optimize_integrable_regularized``, Liu & Bommes; written here)
----------------------------------------------------------------------------------------
Unknowns: the normalized coframes ``J_t = B_t (h F_t) = h B_t F_t`` (``I`` for the rotation
field; ``det J_t > 0`` keeps the orientation), 9 per tet minus the alignment constraints. With
``V = sum_t vol_t``, ``T`` tets and the interior faces ``f = (t0, t1)``:

.. code-block:: text

    E(J) = sum_t (vol_t / V) SD(J_t)                                   symmetric Dirichlet, barrier at det J = 0
         + w_s sum_f ((vol_t0 + vol_t1) / 4V) |h (B_t1 - R_f B_t0)|_F^2  smoothness under the transitions
         + w_i sum_q (1 / 3T) |h Theta_q|^2 / |e_q|^2                   torsion (non-integrability)

``SD(J) = |J|^2 + |J^-1|^2 - 6`` (:func:`~.tet_energies.barrier_terms`: zero at a rotation, infinite
at ``det J = 0``); ``h (B_t1 - R_f B_t0) = J_t1 F_t1^T - R_f J_t0 F_t0^T``; ``h Theta_q / |e_q|`` is the
relative length mismatch of edge ``e_q`` seen from the two tets. The per-face weight ``1/3T`` of
the torsion makes the sum over a face's three quads ``(1/2T) |D_f P_f|^2`` on an equilateral face
(``P_f`` the projector on the face plane): AlgoHex's uniform integrability weight; the smoothness
weight is its volume weight. The two penalty terms are quadratic in ``J`` (constant sparse matrices,
:func:`torsion_matrix`, :func:`smoothness_matrix`), so the whole energy has the shape that
:func:`~.injective._newton` minimizes: per-tet barrier terms plus a constant quadratic; PSD-projected
Newton, one sparse Cholesky per step, a line search that never crosses ``det J = 0``.

Alignment (hard, linear): the coframes the seamless problem's own constraints allow
(:func:`coframe_space`, read off :func:`~.seamless.build_problem` tet by tet, so that the two
stages cannot disagree):

* a boundary face of tet ``t`` with parameter axis ``k`` (``prob.boundary_axis``): row ``k`` of
  ``B_t`` is parallel to the face normal (``B_t[k] . a = 0`` for the face's tangents ``a``: the face
  lies on a plane ``u_k = c``);
* a constrained singular or feature edge ``e`` with parameter axis ``k_t`` in tet ``t`` (the start
  tet's axis carried around the edge by the transitions), in every tet at the edge: the other two
  rows are orthogonal to ``e``;
* what these imply together (a tet edge between two corners on one boundary plane or on one
  feature line lies in that plane or on that line).

Each tet's ``vec(J_t)`` is written in an orthonormal basis of its allowed subspace; a tet where every
allowed ``J_t`` has ``det J_t = 0`` (a row forced to ``0``: two boundary faces of one tet on
different planes of one axis; or rows forced into dependent spaces: two singular edges of one tet
along one axis) is a **conflict**: its constraints are dropped and it is reported (the seamless
map cannot be valid there either: these are the tets that
:meth:`~.seamless.SeamlessProblem.flat_tets` finds).

Continuation (:data:`SCHEDULE`): rounds of ``(w_s, w_i)``, each a Newton solve from the previous
round's coframes; AlgoHex's ``(1e4, 1e4) -> (1e3, 1e5) -> (1e2, 1e6) -> (1e1, 1e7) -> (0, 1e8) -> (0, 1e9)``.
Tets that start inverted or flat (``det J <= DET_SAFE``, a strongly misaligned frame projected on
its constraints) get :mod:`.injective`'s per-tet shift, removed once positive.

Cost: the setup (quads, walks around the constrained edges, the bases) is vectorized numpy
(loops over the steps of an edge walk, i.e. the largest valence); each Newton step assembles the
per-tet ``9 x 9`` blocks and factors one sparse matrix of size ``<= 9T``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from ..dec import torsion as _torsion
from ..tolerances import get_eps
from .cut import TetCharts, face_corner_pairs, group_matrices
from .injective import DET_SAFE, PENALTY_ROUND, PENALTY_START, TetJacobians, _Barrier, _newton, _shifts

__all__ = ["CornerComplex", "corner_complex", "quad_torsion", "torsion_energy", "smoothness_energy",
           "torsion_matrix", "smoothness_matrix", "CoframeSpace", "coframe_space", "IntegrableFrames",
           "integrable_frames", "SCHEDULE"]

SCHEDULE = ((1e4, 1e4), (1e3, 1e5), (1e2, 1e6), (1e1, 1e7), (0.0, 1e8), (0.0, 1e9))
"""The continuation of ``(w_smooth, w_torsion)`` (AlgoHex's six rounds; module docstring)."""


# ----------------------------------------------------------------------------- the corner complex
@dataclass
class CornerComplex:
    """The corner complex of a tet mesh with per-tet charts (module docstring), as flat arrays
    (``Fi`` interior faces, ``Q = 3 Fi`` quads, ``T`` tets).

    Attributes:
        face: ``(Fi,)`` the interior faces (ids of ``mesh.faces``); tet0, tet1: ``(Fi,)``
            ``mesh.face_tets`` of each; face_rot: ``(Fi, 3, 3)`` float64 ``R_f``
            (``u_t1 = R_f u_t0 + s_f``); face_weight: ``(Fi,)`` ``(vol_t0 + vol_t1) / 4V``.
        quad_face: ``(Q,)`` index into the ``Fi`` faces; quad_edge: ``(Q, 3)`` float64
            ``e = x_b - x_a`` (world); quad_corners: ``(Q, 4)`` int64 the loop's corners as
            ``4 t + k`` (``k`` the local corner): ``[(t0,a), (t0,b), (t1,b), (t1,a)]``;
            quad_weight: ``(Q,)`` ``1 / (3 T |e|^2)``.
        corner_points: ``(4T, 3)`` float64 position of corner ``4 t + k``.
        frames: ``(T, 3, 3)`` the combed frames ``F_t``; tet_weight: ``(T,)`` ``vol_t / V``;
            edge_length: ``h``.
    """

    face: np.ndarray
    tet0: np.ndarray
    tet1: np.ndarray
    face_rot: np.ndarray
    face_weight: np.ndarray
    quad_face: np.ndarray
    quad_edge: np.ndarray
    quad_corners: np.ndarray
    quad_weight: np.ndarray
    corner_points: np.ndarray
    frames: np.ndarray
    tet_weight: np.ndarray
    edge_length: float

    @property
    def n_tets(self) -> int:
        return self.frames.shape[0]

    def loop_rot(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """``(Q, 4, 3, 3)`` ``[I, R_f^T, I, R_f]`` of every quad (``loop_rot[k] = R_{x_k x_{k+1}}``)."""
        R = torch.as_tensor(self.face_rot[self.quad_face], dtype=dtype, device=device)
        eye = torch.eye(3, dtype=dtype, device=device).expand_as(R)
        return torch.stack([eye, R.transpose(-1, -2), eye, R], dim=-3)

    def normalized_coframes(self, coframes: torch.Tensor) -> torch.Tensor:
        """``J_t = h B_t F_t`` of coframes ``B (..., T, 3, 3)``."""
        F = torch.as_tensor(self.frames, dtype=coframes.dtype, device=coframes.device)
        return self.edge_length * coframes @ F

    def coframes(self, J: torch.Tensor) -> torch.Tensor:
        """``B_t = J_t F_t^T / h`` of normalized coframes ``J (..., T, 3, 3)``."""
        F = torch.as_tensor(self.frames, dtype=J.dtype, device=J.device)
        return J @ F.transpose(-1, -2) / self.edge_length


def corner_complex(mesh, charts: TetCharts, edge_length: float) -> CornerComplex:
    """The :class:`CornerComplex` of ``mesh`` with the charts ``charts`` and hex edge length ``h``."""
    tets = mesh.tets.cpu().numpy()
    faces = mesh.faces.cpu().numpy()
    face_tets = mesh.face_tets.cpu().numpy()
    X = mesh.vertices.detach().cpu().double().numpy()
    T = tets.shape[0]
    fc = face_corner_pairs(tets, faces, mesh.tet_faces.cpu().numpy(), face_tets)  # (F, 2, 3)
    fi = np.nonzero(charts.interior_face)[0]
    t0, t1 = face_tets[fi, 0], face_tets[fi, 1]
    G = group_matrices().astype(np.float64)
    Xt = X[tets]
    vol = np.abs(np.linalg.det(Xt[:, 1:] - Xt[:, :1])) / 6.0
    V = float(vol.sum())
    # the three edges (a, b) of each face: face vertex pairs (0, 1), (1, 2), (2, 0)
    p = np.array([0, 1, 2])
    q = np.array([1, 2, 0])
    ca0, cb0 = fc[fi][:, 0, p], fc[fi][:, 0, q]  # (Fi, 3) local corners in t0
    ca1, cb1 = fc[fi][:, 1, p], fc[fi][:, 1, q]
    corners = np.stack([4 * t0[:, None] + ca0, 4 * t0[:, None] + cb0, 4 * t1[:, None] + cb1,
                        4 * t1[:, None] + ca1], -1).reshape(-1, 4)
    e = (X[faces[fi][:, q]] - X[faces[fi][:, p]]).reshape(-1, 3)
    quad_face = np.repeat(np.arange(fi.size), 3)
    return CornerComplex(face=fi, tet0=t0, tet1=t1, face_rot=G[charts.face_rot[fi]],
                         face_weight=(vol[t0] + vol[t1]) / (4.0 * V), quad_face=quad_face, quad_edge=e,
                         quad_corners=corners, quad_weight=1.0 / (3.0 * T * (e * e).sum(1)),
                         corner_points=Xt.reshape(-1, 3), frames=np.asarray(charts.frames, np.float64),
                         tet_weight=vol / V, edge_length=float(edge_length))


def _solder(cc: CornerComplex, B: torch.Tensor, k: int) -> torch.Tensor:
    """``(..., Q, 3)``: the coframes' solder form on the loop edge ``x_k -> x_{k+1}`` (``k = 0, 2``),
    ``theta = B_t (x_{k+1} - x_k)`` in the fiber of ``x_k`` (``t`` the tet of both corners)."""
    c = torch.as_tensor(cc.quad_corners, device=B.device)
    P = torch.as_tensor(cc.corner_points, dtype=B.dtype, device=B.device)
    d = P[c[:, k + 1]] - P[c[:, k]]
    Bt = B.index_select(-3, c[:, k] // 4)
    return (Bt @ d[..., None]).squeeze(-1)


def quad_torsion(cc: CornerComplex, coframes: torch.Tensor) -> torch.Tensor:
    """Loop torsion of every quad of the corner complex (module docstring):
    :func:`torchconn.torsion.two_prong` with ``cut = 0``, ``loop_rot = [I, R_f^T, I, R_f]``,
    ``theta_fwd = [B_t0 e, 0, -B_t1 e, 0]`` and ``theta_bwd`` its reverse values.

    Args:
        cc: the :class:`CornerComplex`.
        coframes: ``(..., T, 3, 3)`` ``B_t`` (rows: parameter gradients in world space).

    Returns:
        ``(..., Q, 3)`` ``Theta_q = B_t0 e - R_f^T B_t1 e`` in tet ``t0``'s chart (parameter units).
        Differentiable in ``coframes``.
    """
    th0 = _solder(cc, coframes, 0)  # B_t0 (x_b - x_a)
    th2 = _solder(cc, coframes, 2)  # B_t1 (x_a - x_b)
    z = torch.zeros_like(th0)
    fwd = torch.stack([th0, z, th2, z], dim=-2)
    bwd = torch.stack([-th0, z, -th2, z], dim=-2)  # same edges reversed, in the fiber of x_{k+1}
    return _torsion.two_prong(cc.loop_rot(coframes.dtype, coframes.device), fwd, bwd, 0)


def torsion_energy(cc: CornerComplex, coframes: torch.Tensor) -> torch.Tensor:
    """``sum_q (1 / 3T) |h Theta_q|^2 / |e_q|^2`` (``(...,)`` for coframes ``(..., T, 3, 3)``)."""
    Th = quad_torsion(cc, coframes) * cc.edge_length
    w = torch.as_tensor(cc.quad_weight, dtype=coframes.dtype, device=coframes.device)
    return (w * Th.square().sum(-1)).sum(-1)


def smoothness_energy(cc: CornerComplex, coframes: torch.Tensor) -> torch.Tensor:
    """``sum_f ((vol_t0 + vol_t1) / 4V) |h (B_t1 - R_f B_t0)|_F^2`` (``(...,)``)."""
    t0 = torch.as_tensor(cc.tet0, device=coframes.device)
    t1 = torch.as_tensor(cc.tet1, device=coframes.device)
    R = torch.as_tensor(cc.face_rot, dtype=coframes.dtype, device=coframes.device)
    D = cc.edge_length * (coframes.index_select(-3, t1) - R @ coframes.index_select(-3, t0))
    w = torch.as_tensor(cc.face_weight, dtype=coframes.dtype, device=coframes.device)
    return (w * D.square().sum((-2, -1))).sum(-1)


# ----------------------------------------------------------------------------- the quadratic terms
def _loop_transports(cc: CornerComplex) -> tuple[np.ndarray, np.ndarray]:
    """``(C0, C2)``, ``(Q, 3, 3)`` each: ``Theta_q = C0 theta_fwd[0] + C2 theta_fwd[2]``, read off the
    torsion operator itself (it is linear in ``theta_fwd``; the forward prefix transports of the
    loop, ``I`` and ``R_f^T``)."""
    L = cc.loop_rot()
    Q = L.shape[0]
    # one batched call: basis values e_j on loop edge k, for (k, j) in {0, 2} x {0, 1, 2}
    th = torch.zeros(2, 3, Q, 4, 3, dtype=torch.float64)
    for a, k in enumerate((0, 2)):
        for j in range(3):
            th[a, j, :, k, j] = 1.0
    out = _torsion.two_prong(L, th, torch.zeros_like(th), 0)  # (2, 3, Q, 3): column j of C_k
    C = out.permute(0, 2, 3, 1).numpy()  # (2, Q, i, j)
    return C[0], C[1]


def torsion_matrix(cc: CornerComplex) -> sp.csr_matrix:
    """``K (3Q, 9T)``: ``K vec(J) = h Theta_q / |e_q|`` stacked per quad, for the normalized coframes
    ``J`` (row-major, entry ``(i, l)`` of tet ``t`` at ``9 t + 3 i + l``).

    ``h Theta = C0 J_t0 a0 - C2 J_t1 a1`` with ``a = F_t^T e / |e|`` and the loop transports ``C0, C2``
    of :func:`quad_torsion`'s operator; the block of tet ``t0`` is ``C0[i, j] a0[l]``."""
    C0, C2 = _loop_transports(cc)
    c = cc.quad_corners
    tq0, tq1 = c[:, 0] // 4, c[:, 2] // 4
    en = cc.quad_edge / np.linalg.norm(cc.quad_edge, axis=1, keepdims=True)
    a0 = np.einsum("qml,qm->ql", cc.frames[tq0], en)  # F_t0^T e / |e|
    a1 = np.einsum("qml,qm->ql", cc.frames[tq1], en)
    Q, T = c.shape[0], cc.n_tets
    rows = np.broadcast_to(3 * np.arange(Q)[:, None, None, None] + np.arange(3)[None, :, None, None], (Q, 3, 3, 3))
    jl = 3 * np.arange(3)[:, None] + np.arange(3)[None, :]  # (j, l) -> 3 j + l
    blocks = []
    for tq, Ck, a, sgn in ((tq0, C0, a0, 1.0), (tq1, C2, a1, -1.0)):
        vals = sgn * Ck[:, :, :, None] * a[:, None, None, :]  # (Q, i, j, l)
        cols = 9 * tq[:, None, None, None] + jl[None, None]
        blocks.append((vals.reshape(-1), rows.reshape(-1), np.broadcast_to(cols, (Q, 3, 3, 3)).reshape(-1)))
    v, r, cl = (np.concatenate(x) for x in zip(*blocks))
    nz = v != 0  # the transports are signed permutations: two thirds of each block are zeros
    return sp.csr_matrix((v[nz], (r[nz], cl[nz])), shape=(3 * Q, 9 * T))


def smoothness_matrix(cc: CornerComplex) -> sp.csr_matrix:
    """``S (9Fi, 9T)``: ``S vec(J) = vec(J_t1 F_t1^T - R_f J_t0 F_t0^T)`` per interior face (row
    ``9 f + 3 i + m``): the blocks ``kron(I, F_t1)`` and ``-kron(R_f, F_t0)``."""
    Fi, T = cc.face.size, cc.n_tets
    eye = np.broadcast_to(np.eye(3), (Fi, 3, 3))
    rows = np.broadcast_to(9 * np.arange(Fi)[:, None, None] + np.arange(9)[None, :, None], (Fi, 9, 9))
    parts = []
    for t, A, F in ((cc.tet1, eye, cc.frames[cc.tet1]), (cc.tet0, -cc.face_rot, cc.frames[cc.tet0])):
        vals = np.einsum("fij,fml->fimjl", A, F).reshape(Fi, 9, 9)  # row (i, m), column (j, l)
        cols = np.broadcast_to(9 * t[:, None, None] + np.arange(9)[None, None, :], (Fi, 9, 9))
        parts.append((vals.reshape(-1), rows.reshape(-1), cols.reshape(-1)))
    v, r, c = (np.concatenate(x) for x in zip(*parts))
    nz = v != 0
    return sp.csr_matrix((v[nz], (r[nz], c[nz])), shape=(9 * Fi, 9 * T))


# ----------------------------------------------------------------------------- alignment
@dataclass
class CoframeSpace:
    """The normalized coframes that the seamless problem's constraints allow: ``vec(J) = GZ y + j0``.

    Attributes:
        basis: ``(T, 9, 9)`` float64, ``basis[t, :, :dims[t]]`` orthonormal columns spanning the
            allowed ``vec(J_t)`` (row-major, entry ``(i, l)`` at ``3 i + l``; the rest zero);
            dims: ``(T,)``.
        j0: ``(T, 3, 3)`` the constant part (zero when every constraint is homogeneous, as
            :func:`~.seamless.build_problem`'s are).
        GZ: ``(9T, m)`` CSR, ``m = dims.sum()``: the unknowns ``y`` of tet ``t`` are consecutive.
        conflicts: ``(k,)`` int64 the tets where every allowed coframe has ``det J = 0`` (a row
            forced to ``0``, or rows forced into dependent spaces: the tets that
            :meth:`~.seamless.SeamlessProblem.flat_tets` finds); their constraints are dropped
            (``J_t`` free) and they are reported (:meth:`IntegrableFrames.gate`).
        counts: ``constrained_tets`` (``dims < 9``), ``constraints`` (``sum 9 - dims``), ``conflicts``.
    """

    basis: np.ndarray
    dims: np.ndarray
    j0: np.ndarray
    GZ: sp.csr_matrix
    conflicts: np.ndarray
    counts: dict = field(default_factory=dict)

    def project(self, J: np.ndarray) -> np.ndarray:
        """``y (m,)``: the orthogonal projection of normalized coframes ``J (T, 3, 3)`` on the space."""
        y = np.einsum("tkd,tk->td", self.basis, (J - self.j0).reshape(-1, 9))
        return y[np.arange(9)[None, :] < self.dims[:, None]]


_SAMPLES = 12  # random seamless maps per coframe space (the allowed space of a tet has dimension <= 9)


def coframe_space(prob) -> CoframeSpace:
    """The alignment constraints of the module docstring, read off the seamless problem ``prob``
    (:func:`~.seamless.build_problem`) tet by tet: ``J_t = h (grad u_t) F_t`` of every seamless map
    ``u`` (every value of the free unknowns) spans the allowed space of tet ``t``.

    ``grad u_t = U_t D_t`` (``U_t`` the corner differences, ``D_t = prob.tet_grad``) is linear in the
    free unknowns, so the span of ``_SAMPLES`` random seamless maps' ``J_t`` is the whole allowed
    space with probability 1; its orthonormal basis comes from their SVD (singular values at most
    ``get_eps("identity", float64)`` times the largest are dropped). This is the boundary rows
    parallel to the face normals, the rows across a singular or feature edge orthogonal to it (in
    every tet at the edge, the axis carried by the transitions), and what these constraints imply
    together (a tet edge between two corners on one boundary plane or one feature line); a tet
    where every allowed ``J_t`` has ``det = 0`` (three random points of the space, each
    ``|det| <= eps * prod |rows|``) is a conflict (:class:`CoframeSpace`)."""
    if prob.tet_grad is None:
        raise ValueError("coframe_space needs a SeamlessProblem from build_problem (tet_grad)")
    T = prob.corner_var.shape[0]
    M = prob.edge_length * prob.tet_grad @ np.asarray(prob.charts.frames, np.float64)  # J_t = U_t M_t
    rng = np.random.default_rng(0)
    Y = rng.standard_normal((prob.elim.free.size, _SAMPLES))
    x = prob.elim.Z @ Y  # (n, k): the homogeneous part
    u = x[prob.corner_var]  # (T, 4, 3, k)
    U = np.transpose(u[:, 1:] - u[:, :1], (0, 2, 1, 3))  # (T, i, m, k): corner differences
    Js = np.einsum("timk,tml->tilk", U, M).reshape(T, 9, _SAMPLES)
    z = prob.elim.z0[prob.corner_var]  # (T, 4, 3)
    j0 = np.transpose(z[:, 1:] - z[:, :1], (0, 2, 1)) @ M
    W, sig, _ = np.linalg.svd(Js, full_matrices=True)  # (T, 9, 9), (T, 9) descending
    tol = get_eps("identity", torch.float64)
    keep = sig > tol * np.maximum(sig[:, :1], np.finfo(float).tiny)
    keep &= sig[:, :1] > 0
    dims = keep.sum(1)
    basis = np.where(keep[:, None, :], W, 0.0)  # the kept columns lead (singular values descend)
    # flat: det J = 0 on the whole space (a cubic in the coefficients: zero at three random points)
    flat = np.ones(T, bool)
    for _ in range(3):
        J = np.einsum("tkd,td->tk", basis, rng.standard_normal((T, 9))).reshape(T, 3, 3) + j0
        scale = np.prod(np.linalg.norm(J, axis=2), axis=1)
        flat &= np.abs(np.linalg.det(J)) <= tol * np.maximum(scale, np.finfo(float).tiny)
    bad = np.nonzero(flat)[0]
    basis[bad] = np.eye(9)  # their constraints are dropped (reported)
    dims[bad] = 9
    j0[bad] = 0.0
    r = np.repeat(np.arange(T), 9)
    c = np.tile(np.arange(9), T)
    sel = c < dims[r]
    off = np.concatenate([[0], np.cumsum(dims)])
    col = off[r[sel]] + c[sel]
    vals = basis[r[sel], :, c[sel]]  # (n, 9): column c of tet r's basis
    rows_ = 9 * r[sel][:, None] + np.arange(9)[None, :]
    GZ = sp.csr_matrix((vals.reshape(-1), (rows_.reshape(-1), np.repeat(col, 9))), shape=(9 * T, int(off[-1])))
    GZ.eliminate_zeros()
    counts = {"constrained_tets": int((dims < 9).sum()), "constraints": int((9 - dims).sum()),
              "conflicts": int(bad.size)}
    return CoframeSpace(basis=basis, dims=dims, j0=j0, GZ=GZ, conflicts=bad.astype(np.int64), counts=counts)


# ----------------------------------------------------------------------------- the solve
class _CoframeBarrier(_Barrier):
    """:mod:`.injective`'s shifted barrier on the coframes (no fitting term), its energy offset by
    the symmetric Dirichlet's value at a rotation (``|J|^2 + |J^-1|^2 = 6`` per unit volume; the
    tet weights sum to 1): the minimizer is unchanged, and :func:`~.injective._newton`'s relative
    stopping test has a scale that does not vanish when the field is integrable already."""

    def __init__(self, eps: np.ndarray):
        super().__init__(eps, 0.0, 1.0)

    def energy(self, J: np.ndarray, vol: np.ndarray) -> float:
        return super().energy(J, vol) + 6.0


@dataclass
class IntegrableFrames:
    """What :func:`integrable_frames` returns.

    Attributes:
        coframes: ``(T, 3, 3)`` float64 ``B_t`` (rows: parameter gradients in world space, in tet
            ``t``'s combed chart), the seamless map's targets
            (:meth:`~.seamless.SeamlessProblem.with_targets`).
        J: ``(T, 3, 3)`` the normalized coframes ``h B_t F_t``.
        frames: ``(T, 3, 3)`` the combed frames ``F_t``; edge_length: ``h``.
        space: the :class:`CoframeSpace` (alignment bases, conflicts).
        rounds: one dict per round of the schedule (``w_smooth``, ``w_torsion``, ``iterations``,
            ``converged``, ``inverted``, ``min_det``, the terms ``sd``, ``smooth``, ``torsion``
            (unweighted) and the relative torsion ``torsion_rms`` / ``torsion_max``
            (``h |Theta_q| / |e_q|``)); ``start``: the same figures for the rotation field.
        seconds: wall time; setup_seconds: the part before the first round.
    """

    coframes: np.ndarray
    J: np.ndarray
    space: CoframeSpace
    frames: np.ndarray
    edge_length: float
    rounds: list = field(default_factory=list)
    start: dict = field(default_factory=dict)
    seconds: float = 0.0
    setup_seconds: float = 0.0

    @property
    def inverted(self) -> np.ndarray:
        """``(k,)`` tets with ``det J_t <= 0``."""
        return np.nonzero(np.linalg.det(self.J) <= 0)[0]

    def targets(self) -> np.ndarray:
        """``(T, 3, 3)`` the seamless map's target coframes: :attr:`coframes`, except on the tets
        whose coframe is not safely positive (``det J_t <= DET_SAFE``, reported by :meth:`gate`),
        which keep the field's ``F_t^T / h``."""
        ok = np.linalg.det(self.J) > DET_SAFE
        field_cof = np.transpose(self.frames, (0, 2, 1)) / self.edge_length
        return np.where(ok[:, None, None], self.coframes, field_cof)

    def gate(self):
        """The stage's :class:`~.validity.Gate` (``"frames"``): passes when every coframe keeps its
        orientation (``det J_t > 0``) and no alignment constraint conflicts (``inverted_coframes``,
        ``alignment_conflicts``; where: tets). The torsion left is in :meth:`summary`."""
        from .validity import Gate

        inv = self.inverted
        conf = self.space.conflicts
        counts = {"inverted_coframes": int(inv.size), "alignment_conflicts": int(conf.size)}
        where = {k: ids[:10].tolist() for k, ids in (("inverted_coframes", inv), ("alignment_conflicts", conf))
                 if ids.size}
        reasons = []
        if inv.size:
            reasons.append(f"{inv.size} integrable coframes inverted (e.g. tet {int(inv[0])})")
        if conf.size:
            reasons.append(f"{conf.size} tets whose alignment constraints admit no positive coframe "
                           f"(e.g. tet {int(conf[0])}; their constraints dropped)")
        return Gate(stage="frames", passed=not reasons, counts=counts, where=where, reasons=reasons)

    def summary(self) -> dict:
        """JSON-ready figures: the start, every round, conflicts, timings."""
        return {"start": dict(self.start), "rounds": [dict(r) for r in self.rounds],
                "conflicts": int(self.space.conflicts.size), "conflict_where": self.space.conflicts[:10].tolist(),
                "inverted": int(self.inverted.size), "unknowns": int(self.space.GZ.shape[1]),
                "constraints": dict(self.space.counts), "seconds": self.seconds, "setup_seconds": self.setup_seconds}


def _figures(cc: CornerComplex, K: sp.csr_matrix, S: sp.csr_matrix, J: np.ndarray) -> dict:
    j = J.reshape(-1)
    th = (K @ j).reshape(-1, 3)
    rel = np.linalg.norm(th, axis=1)
    det = np.linalg.det(J)
    pos = det > 0
    sd = np.full(det.shape, np.inf)
    if pos.any():
        Jp = J[pos]
        sd[pos] = (Jp * Jp).sum((1, 2)) + (np.linalg.inv(Jp) ** 2).sum((1, 2)) - 6.0
    D = (S @ j).reshape(-1, 9)
    # torsion in the module's weighting: (1/3T) |h Theta|^2 / |e|^2 = |K j|^2 / 3T per quad
    return {"sd": float((cc.tet_weight * sd).sum()), "smooth": float((cc.face_weight * (D * D).sum(1)).sum()),
            "torsion": float((rel * rel).sum() / (3.0 * cc.n_tets)),
            "torsion_rms": float(np.sqrt((rel * rel).mean())) if rel.size else 0.0,
            "torsion_max": float(rel.max(initial=0.0)), "inverted": int((det <= 0).sum()),
            "min_det": float(det.min(initial=np.inf))}


def integrable_frames(mesh, charts: TetCharts, prob, *, schedule=SCHEDULE, max_iter: int = 20,
                      tol: float = 1e-6, backend: str = "auto", callback=None) -> IntegrableFrames:
    """Integrable coframes near the combed frames of ``charts`` (module docstring).

    Args:
        mesh: the ``TetMesh`` of the seamless problem; charts: its :class:`~.cut.TetCharts`.
        prob: the :class:`~.seamless.SeamlessProblem` (its boundary and feature axes, ``h``).
        schedule: the rounds ``(w_smooth, w_torsion)`` (default :data:`SCHEDULE`); empty: the
            frames' coframes projected on the alignment constraints.
        max_iter, tol: Newton steps per round and the stopping test of
            :func:`~.injective._newton` (decrement below ``tol`` times the energy).
        backend: sparse solver (:mod:`.solver`).
        callback: ``callback(k, coframes)`` after round ``k`` (``coframes (T, 3, 3)``), e.g. to
            measure what each round does to the seamless map.

    Returns:
        :class:`IntegrableFrames`. Tets left inverted (``det J <= 0``: the barrier could not open
        a tet that the constraints invert) are reported in ``rounds`` and ``inverted``, not raised.
    """
    for pair in schedule:
        if len(pair) != 2 or min(pair) < 0 or not all(np.isfinite(pair)):
            raise ValueError(f"schedule must be pairs (w_smooth, w_torsion) of finite numbers >= 0, got {pair!r}")
    t_start = time.perf_counter()
    h = float(prob.edge_length)
    cc = corner_complex(mesh, charts, h)
    space = coframe_space(prob)
    K = torsion_matrix(cc)
    S = smoothness_matrix(cc)
    T = cc.n_tets
    jac = TetJacobians(GZ=space.GZ, j0=space.j0.reshape(-1), vol=cc.tet_weight)
    # the penalties in the unknowns y: |K (GZ y + j0)|^2 / 3T and |S (GZ y + j0)|^2_W, as
    # y^T P y - 2 q^T y (+ constants)
    KZ = (K @ space.GZ).tocsr()
    SZ = (S @ space.GZ).tocsr()
    Wf = sp.diags(np.repeat(cc.face_weight, 9))
    j0 = space.j0.reshape(-1)
    Pt = (KZ.T @ KZ).tocsr() / (3.0 * T)
    qt = -(KZ.T @ (K @ j0)) / (3.0 * T)
    Ps = (SZ.T @ Wf @ SZ).tocsr()
    qs = -(SZ.T @ (Wf @ (S @ j0)))
    eye = np.broadcast_to(np.eye(3), (T, 3, 3))
    y = space.project(eye)
    start = _figures(cc, K, S, np.broadcast_to(np.eye(3), (T, 3, 3)).copy())
    start["projected"] = _figures(cc, K, S, jac(y))
    setup = time.perf_counter() - t_start
    det = np.linalg.det(jac(y))
    eps = _shifts(det, PENALTY_START)
    free = np.ones(y.size, bool)
    rounds = []
    for k, (ws, wi) in enumerate(schedule):
        history = []
        P = (ws * Ps + wi * Pt).tocsr()
        y, it, conv = _newton(jac, y, _CoframeBarrier(eps), free, max_iter=max_iter, tol=tol, backend=backend,
                              history=history, rnd=("integrable", k), quad=(P, ws * qs + wi * qt))
        det = np.linalg.det(jac(y))
        eps = _shifts(det, PENALTY_ROUND)  # a tet that became positive loses its shift for good
        fig = _figures(cc, K, S, jac(y))
        fig.update(w_smooth=float(ws), w_torsion=float(wi), iterations=int(it), converged=bool(conv))
        rounds.append(fig)
        if callback is not None:
            callback(k, cc.coframes(torch.from_numpy(jac(y))).numpy())
    J = jac(y)
    B = cc.coframes(torch.from_numpy(J)).numpy()
    return IntegrableFrames(coframes=B, J=J, space=space, frames=cc.frames, edge_length=h, rounds=rounds, start=start,
                            seconds=time.perf_counter() - t_start, setup_seconds=setup)
