"""Diagnostic studies of the mean-smoothness metric (issue 5), reproducible from the command line.

These are *not* part of the frame-field method; they answer "how low can the mean edge angle go
on this mesh, and where" (figures and commands in ``docs/results/frame-fields.md``)::

    python -m studies.frame_studies fixmatch FRAMES.npz --mesh M [--edge-length H]
    python -m studies.frame_studies constint --mesh M
    python -m studies.frame_studies planar_lp FRAMES.npz --mesh M [--lam 1.0]

``FRAMES.npz`` is a ``frames.npz`` written by ``python -m training.train_frames``.

* :func:`fixed_matching_descent`: frames only (rotation about the normal at non-feature
  boundary vertices, so alignment stays exact), minimizing the smoothed mean edge angle with
  the edge matchings ``g_ij`` *frozen* at the start of each round (Adam, cosine lr), then
  re-matched.
* :func:`constant_interior_field`: one rotation ``R`` at every interior (and feature) vertex,
  the minimal snap of ``R`` to the normal at the other boundary vertices: all rotation sits on the boundary surface and
  the boundary-to-interior edges (a degenerate field that still scores well on a ball).
* :func:`planar_l1_optimum`: for an *extruded* mesh whose frames all share the axis ``z``, the
  frame is its in-plane angle ``theta_i`` (mod 90 deg) and the edge angle is
  ``|theta_i - theta_j - 90 k_ij|``; with the period jumps ``k_ij`` frozen (the singular
  structure fixed) the minimum of the mean edge angle plus ``lam`` times the feature-alignment
  mean is a linear program (HiGHS): the exact optimum for that singular structure. Side-wall
  boundary vertices are fixed to their normal (exact alignment).
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from torchconn.frames import octahedral
from torchconn.frames.constraints import BoundaryConstraint
from torchconn.frames.metrics import frame_metrics
from torchconn.frames.param import constrained_frames
from torchconn.frames.solver import cosine_factor
from torchconn.lie import so3

__all__ = ["fixed_matching_descent", "constant_interior_field", "planar_l1_optimum", "main"]


def fixed_matching_descent(mesh, frames: torch.Tensor, rounds: int = 3, steps: int = 200, lr: float = 0.01,
                           eps: float = 1e-3, feature_weight: float = 1.0, angle_deg: float = 30.0) -> torch.Tensor:
    """Minimize ``mean_e angle(F_i g_ij, F_j)`` (smoothed by ``eps``) over the frames, ``g_ij`` frozen per round.

    Plus ``feature_weight`` times the smoothed feature-alignment angle
    (:func:`torchconn.frames.loss.axis_angle_loss`). Returns the frames ``(V, 3, 3)``.
    """
    from torchconn.frames.loss import FrameFieldLoss

    loss = FrameFieldLoss(mesh, {"feature": 1.0}, feature_angle_deg=angle_deg, align_kind="angle")
    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    e0, e1 = mesh.edges[:, 0], mesh.edges[:, 1]
    F = frames.detach().to(mesh.vertices.dtype)
    for _ in range(rounds):
        with torch.no_grad():
            _, g = octahedral.match_edges(F, mesh.edges)
        w = torch.zeros_like(F[:, :, 0], requires_grad=True)
        opt = torch.optim.Adam([w], lr=lr)
        for s in range(steps):
            for pg in opt.param_groups:
                pg["lr"] = lr * cosine_factor(s, steps)
            Fc = constrained_frames(w, F, bc.constrained, bc.normals)
            d2 = ((Fc[e0] @ g - Fc[e1]) ** 2).sum((-2, -1))
            th = 2.0 * torch.asin((torch.sqrt(d2 + eps * eps) / (2.0 * math.sqrt(2.0))).clamp(max=1.0))
            total = th.mean()
            if feature_weight:
                total = total + feature_weight * loss(None, Fc)["feature"]
            opt.zero_grad()
            total.backward()
            opt.step()
        with torch.no_grad():
            F = so3.project_to_rotation(constrained_frames(w, F, bc.constrained, bc.normals))
    return F


def constant_interior_field(mesh, R: torch.Tensor, angle_deg: float = 30.0) -> torch.Tensor:
    """``R`` at every vertex, snapped minimally to the normal at every non-feature boundary vertex."""
    from torchconn.frames.sh import _snap_axis

    V = mesh.vertices.shape[0]
    F = R.to(mesh.vertices.dtype).expand(V, 3, 3).clone()
    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    F[bc.constrained] = _snap_axis(F[bc.constrained], bc.normals[bc.constrained].to(F.dtype))
    return F


def _planar_angle(F: torch.Tensor) -> np.ndarray:
    """In-plane angle (deg, mod 90) of the cross of the axes orthogonal to the axis closest to z."""
    k = F[:, 2, :].abs().argmax(-1)
    a = F[torch.arange(F.shape[0]), :, (k + 1) % 3]
    return np.degrees(np.arctan2(a[:, 1].double().numpy(), a[:, 0].double().numpy())) % 90.0


def _planar_frames(theta: np.ndarray) -> torch.Tensor:
    t = np.radians(theta)
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((t.size, 3, 3))
    R[:, 0, 0], R[:, 1, 0], R[:, 0, 1], R[:, 1, 1], R[:, 2, 2] = c, s, -s, c, 1.0
    return torch.as_tensor(R)


def planar_l1_optimum(mesh, frames: torch.Tensor, lam: float = 1.0, rounds: int = 1,
                      angle_deg: float = 30.0) -> tuple[torch.Tensor, float]:
    """Exact L1 optimum of an extruded (axis-``z``) field for the singular structure of ``frames``.

    Minimizes ``mean_e |theta_i - theta_j - 90 k_ij| + lam * sum_p |theta_v - phi_p - 90 m_p| / P``
    over real ``theta`` (degrees) with ``k_ij``, ``m_p`` the nearest periods of the current field,
    ``p`` the (feature vertex, incident vertical boundary face) pairs and ``P`` all (feature vertex,
    incident boundary face) pairs (horizontal faces are aligned by the ``z`` axis), and
    ``theta`` fixed to the normal's angle at non-feature side-wall boundary vertices. ``rounds``
    re-matches and solves again. Returns ``(frames (V, 3, 3) float64, LP objective)``.
    """
    import scipy.sparse as sp
    from scipy.optimize import linprog

    V = mesh.vertices.shape[0]
    e = mesh.edges.cpu().numpy()
    E = e.shape[0]
    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    isf = bc.is_feature.cpu().numpy()
    bv = mesh.boundary_vertices.cpu().numpy()
    bn = mesh.boundary_vertex_normals.detach().double().cpu().numpy()
    side = (~isf[bv]) & (np.abs(bn[:, 2]) < 0.9)
    fix_v, fix_phi = bv[side], np.degrees(np.arctan2(bn[side, 1], bn[side, 0])) % 90.0
    vert = bc.pair_vertices.cpu().numpy()
    pn = bc.pair_normals.detach().double().cpu().numpy()  # (P, 3) normal of each pair's face
    P_all = max(vert.size, 1)
    vs = np.abs(pn[:, 2]) < 0.9
    pv, pphi = vert[vs], np.degrees(np.arctan2(pn[vs, 1], pn[vs, 0])) % 90.0
    nP = pv.size
    th = _planar_angle(frames.detach().cpu())
    obj = float("nan")
    for _ in range(max(rounds, 1)):
        c = 90.0 * np.round((th[e[:, 0]] - th[e[:, 1]]) / 90.0)
        fixv = fix_phi + 90.0 * np.round((th[fix_v] - fix_phi) / 90.0)
        cp = pphi + 90.0 * np.round((th[pv] - pphi) / 90.0)
        nvar = V + E + nP
        cost = np.r_[np.zeros(V), np.full(E, 1.0 / E), np.full(nP, lam / P_all)]
        i_e, i_p = np.arange(E), np.arange(nP)
        one_e, one_p = np.ones(E), np.ones(nP)
        rows = np.r_[i_e, i_e, i_e, E + i_e, E + i_e, E + i_e,
                     2 * E + i_p, 2 * E + i_p, 2 * E + nP + i_p, 2 * E + nP + i_p]
        cols = np.r_[e[:, 0], e[:, 1], V + i_e, e[:, 0], e[:, 1], V + i_e, pv, V + E + i_p, pv, V + E + i_p]
        vals = np.r_[one_e, -one_e, -one_e, -one_e, one_e, -one_e, one_p, -one_p, -one_p, -one_p]
        A = sp.csr_matrix((vals, (rows, cols)), shape=(2 * E + 2 * nP, nvar))
        lb = np.r_[np.full(V, -np.inf), np.zeros(E + nP)]
        ub = np.full(nvar, np.inf)
        lb[fix_v] = ub[fix_v] = fixv
        res = linprog(cost, A_ub=A, b_ub=np.r_[c, -c, cp, -cp], bounds=np.c_[lb, ub], method="highs")
        if res.status != 0:
            raise RuntimeError(f"planar L1 linear program failed: {res.message}")
        th, obj = res.x[:V] % 90.0, float(res.fun)
    return _planar_frames(th), obj


def _summary(tag: str, F: torch.Tensor, mesh) -> None:
    m = frame_metrics(F, mesh)
    print(f"{tag}: smoothness {m['smoothness_mean_deg']:.3f} deg, singular faces {m['n_singular_faces']} "
          f"(tets with one: {m['n_tets_one_singular_face']}), alignment {m['alignment_mean_deg']:.3f}/"
          f"{m['alignment_max_deg']:.3f}, feature {m['feature_alignment_mean_deg']:.3f}", flush=True)


def main(argv: list[str] | None = None) -> None:
    from torchconn import io as tio

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("study", choices=("fixmatch", "constint", "planar_lp"))
    ap.add_argument("frames", nargs="?", help="frames.npz of a train_frames run (fixmatch, planar_lp)")
    ap.add_argument("--mesh", required=True)
    ap.add_argument("--edge-length", type=float, default=None)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--lr", type=float, default=0.01)
    ap.add_argument("--lam", type=float, default=1.0)
    ap.add_argument("--restarts", type=int, default=16)
    ap.add_argument("--out", default=None, help="save the frames (V, 3, 3) as .npy")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    kw = {} if a.edge_length is None else {"edge_length": a.edge_length}
    mesh = tio.load_mesh(a.mesh, **kw).to(dtype=torch.float64)
    if a.study != "constint":
        if not a.frames:
            ap.error(f"{a.study} needs a frames.npz")
        F0 = torch.as_tensor(np.load(a.frames)["frames"])
        _summary("input", F0, mesh)
    if a.study == "fixmatch":
        F = fixed_matching_descent(mesh, F0, rounds=a.rounds, steps=a.steps, lr=a.lr)
    elif a.study == "planar_lp":
        F, obj = planar_l1_optimum(mesh, F0, lam=a.lam, rounds=1)
        print(f"LP objective {obj:.4f}")
    else:
        g = torch.Generator().manual_seed(0)
        Rs = torch.cat([torch.eye(3, dtype=torch.float64)[None],
                        so3.random_rotation(a.restarts - 1, generator=g, dtype=torch.float64)])
        cands = [constant_interior_field(mesh, R) for R in Rs]
        F = min(cands, key=lambda X: frame_metrics(X, mesh)["smoothness_mean_deg"])
    _summary(a.study, F, mesh)
    if a.out:
        np.save(a.out, F.numpy())


if __name__ == "__main__":
    main()
