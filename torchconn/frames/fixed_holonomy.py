"""A tet frame field re-optimized by its connection with the face matchings fixed (frozen holonomy).

The singular graph of one frame per tet is set by the face matchings (``F_t0 G[g_f] ~ F_t1`` for
an interior face ``f`` with ``mesh.face_tets[f] = (t0, t1)``; :mod:`torchconn.hexmesh.cut`). A
repair of the singular graph (:mod:`torchconn.hexmesh.repair`) changes matchings without
changing the frames, so the frames no longer match as the matchings say. Freezing the matchings
freezes the holonomy class of every edge (the singularity types, LMFF's "field optimized with the
matchings fixed"); the frames are then re-optimized under that constraint, by a connection:

* the dual graph: tets as vertices, interior faces as canonical edges ``(a, b)``, ``a < b``, each
  with its fixed relabeling ``h_ab`` (``F_a G[h_ab] ~ F_b``);
* the free region: the tets within ``rings`` dual steps of the faces whose fixed matching is not
  the input frames' best one (LMFF re-optimizes locally in its loop); the other frames stay;
* the connection ``R_ab = exp(hat(omega_ab))`` (:class:`torchconn.nn.ConnectionField`, skew
  parameters through the exponential) on the faces at a free tet, started at the matched
  connection ``R_ab = F_a^T F_b G[h_ab]^T`` (the residual rotation of the input frames under the
  fixed matchings), so that ``F_a R_ab = F_b G[h_ab]^T`` (the convention of
  :mod:`torchconn.frames.model`: ``F_i R_ij = F_j h_ij``);
* the free frames ``exp(hat(w_t)) F_t`` tied to the connection (the design card's ``vertex``
  formulation: the tie is an exact penalty, at the optimum the connection transports the
  frames; propagating the frames along a spanning tree instead, the card's ``propagate``
  formulation, drifted on HexMe meshes: Adam moves every rotation of a deep tree by its step);
* the loss, the design card's terms (:mod:`torchconn.frames.terms`) on these faces: ``smooth``
  (:func:`~torchconn.frames.terms.smoothness_loss` of ``R``), ``tie``
  ``mean rho(||F_a R_ab - F_b G[h_ab]^T||)`` with ``h`` *fixed* (around every edge the ties
  close the loop on the frozen holonomy: the flatness of the connection relative to it),
  ``align`` (:func:`~torchconn.frames.terms.axis_angle_loss`) of every free boundary tet's frame
  to each of its boundary faces' normals (at sharp features a tet has two and follows both), and
  ``keep``, ``mean relu(||R - I||^2 - c)^2`` with ``c`` the value at :data:`KEEP_DEG`: the frozen
  holonomy is an inequality on every face (its fixed matching must stay the best one,
  ``|R_ab| < 45°``, since ``F_b ~ F_a R_ab G[h_ab]``), which the smoothness alone does not hold.

The returned frames' best matchings are, where the optimization reached a fit within 45°, the
fixed ones (:attr:`FixedHolonomyResult.agree` says on how many faces).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from ..lie import so3
from ..nn import ConnectionField
from . import octahedral
from .terms import axis_angle_loss, smoothness_loss

__all__ = ["FixedHolonomyResult", "fixed_holonomy_frames", "FixedHolonomyField", "free_region", "DEFAULT_WEIGHTS",
           "KEEP_DEG"]

DEFAULT_WEIGHTS = {"smooth": 1.0, "tie": 2.0, "align": 10.0, "keep": 100.0}
"""Weights of the terms (the design card's ``smooth``, ``tie`` and ``align``; ``keep`` the
penalty that keeps every face's fixed matching its best one, module docstring)."""

KEEP_DEG = 35.0
"""The ``keep`` term penalizes connection rotations beyond this angle (degrees): a face whose
frames are related by ``F_b = F_a R G[h]`` keeps ``h`` as its best matching while ``|R| < 45°``."""


def _dual(mesh, face_match):
    """Interior faces as canonical dual edges ``(a, b)`` with their relabelings ``h_ab``."""
    _, _, INV = octahedral.group_tables()
    T = mesh.n_tets
    ft = mesh.face_tets.cpu().numpy()
    match = np.asarray(face_match, np.int64)
    if match.shape != (ft.shape[0],) or (match.size and (match.min() < 0 or match.max() > 23)):
        raise ValueError(f"face_match must be ({ft.shape[0]},) indices into the 24 elements of O")
    fi = np.nonzero((ft >= 0).all(1))[0]
    a, b = ft[fi, 0], ft[fi, 1]
    h = np.where(a < b, match[fi], INV[match[fi]])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.argsort(lo * T + hi)
    return np.stack([lo[order], hi[order]], 1), fi[order], h[order]


def free_region(mesh, tet_frames, face_match, rings: int | None = 4) -> np.ndarray:
    """``(T,)`` bool: the tets within ``rings`` dual steps (across interior faces) of a face whose
    matching in ``face_match`` is not the best one of ``tet_frames`` (all tets for ``None``)."""
    T = mesh.n_tets
    if rings is None:
        return np.ones(T, bool)
    dual, dface, h = _dual(mesh, face_match)
    F = torch.as_tensor(tet_frames).detach()
    ft = mesh.face_tets.cpu().numpy()[dface]
    best, _ = octahedral.match(F[ft[:, 0]], F[ft[:, 1]])
    off = best.numpy() != np.asarray(face_match, np.int64)[dface]
    free = np.zeros(T, bool)
    free[dual[off].reshape(-1)] = True
    A = sp.coo_matrix((np.ones(2 * dual.shape[0]), (np.r_[dual[:, 0], dual[:, 1]], np.r_[dual[:, 1], dual[:, 0]])),
                      shape=(T, T)).tocsr()
    for _ in range(int(rings)):  # loop over the rings
        free |= (A @ free.astype(np.float64)) > 0
    return free


class FixedHolonomyField(torch.nn.Module):
    """The connection on the dual faces at free tets and the free frames (module docstring).

    Args:
        mesh: a ``TetMesh``; tet_frames: ``(T, 3, 3)`` rotations; face_match: ``(F,)`` indices
            into :func:`~torchconn.frames.octahedral.group` (``F_t0 G[g] ~ F_t1``);
        free: ``(T,)`` bool, the tets whose frames move (default all).

    ``forward() -> (edge_rot (D, 3, 3), frames (T, 3, 3))`` over the ``D`` interior faces with a
    free tet (buffers ``dual_edges (D, 2)``, ``dual_face (D,)``, ``h (D,)``, ``Gh (D, 3, 3)``).
    """

    def __init__(self, mesh, tet_frames: torch.Tensor, face_match, free: np.ndarray | None = None):
        super().__init__()
        G = octahedral.group_tables()[0]
        F0 = torch.as_tensor(tet_frames).detach()
        T = mesh.n_tets
        dual, dface, h = _dual(mesh, face_match)
        free = np.ones(T, bool) if free is None else np.asarray(free, bool)
        act = free[dual[:, 0]] | free[dual[:, 1]]
        dual, dface, h = dual[act], dface[act], h[act]
        self.register_buffer("dual_edges", torch.as_tensor(dual))
        self.register_buffer("dual_face", torch.as_tensor(dface))
        self.register_buffer("h", torch.as_tensor(h))
        self.register_buffer("Gh", torch.as_tensor(np.array(G), dtype=F0.dtype)[torch.as_tensor(h)])
        self.register_buffer("F0", F0.clone())
        self.register_buffer("free_tets", torch.as_tensor(np.nonzero(free)[0]))
        Fa, Fb = F0[self.dual_edges[:, 0]], F0[self.dual_edges[:, 1]]
        R0 = Fa.transpose(-1, -2) @ Fb @ self.Gh.transpose(-1, -2)
        self.connection = ConnectionField(self.dual_edges, T, init=R0)
        self.w = torch.nn.Parameter(F0.new_zeros(self.free_tets.numel(), 3))

    def forward(self) -> tuple[torch.Tensor, torch.Tensor]:
        R = self.connection().edge_rot
        F = self.F0.index_copy(0, self.free_tets, so3.exp(self.w) @ self.F0[self.free_tets])
        return R, F


@dataclass
class FixedHolonomyResult:
    """What :func:`fixed_holonomy_frames` returns.

    Attributes:
        tet_frames: ``(T, 3, 3)`` the connection's frames (detached).
        agree: fraction of interior faces whose best matching of the returned frames is the fixed one.
        misfit_deg_before, misfit_deg_after: mean angle (degrees) between ``F_t0 G[g_f]`` and
            ``F_t1`` over the interior faces, for the input and the returned frames.
        free_tets: tets whose frames moved (:func:`free_region`); passes: optimization passes run.
        history: the loss terms per step (floats); ``seconds``: wall time.
    """

    tet_frames: torch.Tensor
    agree: float
    misfit_deg_before: float
    misfit_deg_after: float
    free_tets: int = 0
    passes: int = 0
    history: list = field(default_factory=list)
    seconds: float = 0.0


def _misfit_deg(F: torch.Tensor, ft: torch.Tensor, g: torch.Tensor) -> float:
    G = octahedral.group(F.dtype)
    M = F[ft[:, 0]] @ G[g] - F[ft[:, 1]]
    c = 1 - (M ** 2).sum((-2, -1)) / 4  # ||A - B||^2 = 4 (1 - cos t) for rotations
    return float(torch.rad2deg(torch.arccos(c.clamp(-1, 1))).mean())


def fixed_holonomy_frames(mesh, tet_frames, face_match, *, rings: int | None = 4, weights: dict | None = None,
                          steps: int = 150, lr: float = 0.02, smooth_power: float = 2.0, smooth_eps: float = 1e-3,
                          max_passes: int = 3, progress: bool = False) -> FixedHolonomyResult:
    """Re-optimize per-tet frames by the dual connection with the face matchings fixed.

    Args:
        mesh: a ``TetMesh``; tet_frames: ``(T, 3, 3)`` rotations (axes as columns).
        face_match: ``(F,)`` the matchings to freeze (e.g. :func:`torchconn.hexmesh.repair.repair_singular_graph`'s).
        rings: the free region (:func:`free_region`; ``None``: every tet).
        weights: overrides of :data:`DEFAULT_WEIGHTS`.
        steps, lr: Adam steps and learning rate (cosine schedule) of a pass, as the design card's.
        max_passes: passes of ``steps``; a pass after the first runs only while some face's best
            matching is not its fixed one, with the ``keep`` weight 10 times the last (measured on
            s10c after the repair: 2 of 1,208 faces left after 150 steps, none after a second pass).
        smooth_power, smooth_eps: ``rho`` of the ``smooth`` and ``tie`` terms. Default 2 (the
            Dirichlet energy of the connection; the card uses 1, total variation, which gathers the
            turning on few faces: on the detached prism arc of the tests 0.3% of the faces then
            leave their fixed matching and the singular graph moves, with 2 none does).
        progress: a tqdm bar.

    Returns:
        :class:`FixedHolonomyResult`.

    Raises:
        ValueError: frames or matchings that do not fit the mesh, unknown weights, ``steps < 0``.
    """
    if not (isinstance(max_passes, int) and max_passes >= 1):
        raise ValueError(f"max_passes must be an integer >= 1, got {max_passes!r}")
    w = dict(DEFAULT_WEIGHTS)
    if weights:
        unknown = set(weights) - set(w)
        if unknown:
            raise ValueError(f"unknown weights {sorted(unknown)}; known: {sorted(w)}")
        w.update({k: float(v) for k, v in weights.items()})
    if not (isinstance(steps, int) and steps >= 0):
        raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
    t0 = time.perf_counter()
    F0 = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    if F0.shape != (mesh.n_tets, 3, 3) or not torch.isfinite(F0).all():
        raise ValueError(f"tet_frames must be finite with shape ({mesh.n_tets}, 3, 3), got {tuple(F0.shape)}")
    free = free_region(mesh, F0, face_match, rings)
    model = FixedHolonomyField(mesh, F0, face_match, free)
    # every interior face, for the agreement and the misfit
    _, dface_all, _ = _dual(mesh, face_match)
    ft_all = mesh.face_tets.cpu()
    ft = ft_all[torch.as_tensor(dface_all)]
    g_fixed = torch.as_tensor(np.asarray(face_match, np.int64))[torch.as_tensor(dface_all)]
    # free boundary tets and the normals of their boundary faces
    bfi = torch.nonzero((ft_all < 0).any(1)).flatten()
    bt = ft_all[bfi].amax(1)
    sel = torch.as_tensor(free)[bt]
    bfi, bt = bfi[sel], bt[sel]
    X = mesh.vertices.detach().cpu().double()
    tri = mesh.faces.cpu()[bfi]
    n = torch.linalg.cross(X[tri[:, 1]] - X[tri[:, 0]], X[tri[:, 2]] - X[tri[:, 0]])
    n = n / n.norm(dim=1, keepdim=True)
    keep_c = 8.0 * math.sin(math.radians(KEEP_DEG) / 2) ** 2  # ||R - I||^2 = 8 sin^2(angle / 2)
    ea, eb = model.dual_edges[:, 0], model.dual_edges[:, 1]
    eye = torch.eye(3, dtype=F0.dtype)

    def loss_terms():
        R, F = model()
        # ||F_a R - F_b G[h]^T|| = ||G[h] F_b^T F_a R - I||: the tie is the smoothness of that rotation
        out = {"smooth": smoothness_loss(R, smooth_power, smooth_eps),
               "tie": smoothness_loss(model.Gh @ F[eb].transpose(-1, -2) @ F[ea] @ R, smooth_power, smooth_eps),
               "align": axis_angle_loss(F[bt], n) if bt.numel() else R.new_zeros(()),
               "keep": torch.relu(((R - eye) ** 2).sum((-2, -1)) - keep_c).square().mean()}
        return out, F

    before = _misfit_deg(F0, ft, g_fixed)
    history = []

    def agreement():
        with torch.no_grad():
            _, F = model()
        idx, _ = octahedral.match(F[ft[:, 0]], F[ft[:, 1]])
        return F.detach(), float((idx == g_fixed).double().mean()) if idx.numel() else 1.0

    F, agree = agreement()
    passes = 0
    while model.free_tets.numel() and model.dual_edges.shape[0] and passes < max_passes and (agree < 1.0 or not passes):
        # a pass of Adam steps; while faces leave their fixed matching, again with keep x 10
        wp = dict(w, keep=w["keep"] * 10.0 ** passes)
        opt = torch.optim.Adam(model.parameters(), lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1))
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=steps, desc=f"fixed holonomy {passes + 1}", unit="step", leave=False)
        try:
            for _ in range(steps):
                opt.zero_grad()
                terms, _ = loss_terms()
                total = sum(wp[k] * v for k, v in terms.items())
                total.backward()
                opt.step()
                sched.step()
                history.append({k: float(v.detach()) for k, v in terms.items()} | {"total": float(total.detach())})
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        F, agree = agreement()
        passes += 1
    return FixedHolonomyResult(tet_frames=F, agree=agree, misfit_deg_before=before,
                               misfit_deg_after=_misfit_deg(F, ft, g_fixed), free_tets=int(free.sum()), passes=passes,
                               history=history, seconds=time.perf_counter() - t0)
