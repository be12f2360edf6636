"""The eager references of :mod:`benchmarks.run` and the loss rows' cases.

Eager, generic compositions — the code paths before the fused kernels of :mod:`torchconn.ops` —
kept so that the ratios stay measurable after the library routes through the fused kernels:
``matrix_exp`` and the matrix-based log / sqrt of SO(3), loop curvature and torsion, dense
averaged-d∇ tables, and the frame-field loss composed from the library's single-term functions
(:func:`ref_frame_loss_terms`), with the check that a loss row and its reference compute one loss
(:func:`loss_agreement`, :data:`LOSS_AGREEMENT_RTOL`; ``tests/test_losses.py`` asserts it on a
small mesh).
"""
from __future__ import annotations

import math

import torch

from torchconn import curvature, dnabla, so3
from torchconn import torsion as _torsion
from torchconn.dec.transport import orient

__all__ = ["LOSS_AGREEMENT_RTOL", "loss_cases", "ref_frame_loss_terms", "loss_agreement"]


# ----------------------------------------------------------------------------- operators

def _ref_exp_matrix(w: torch.Tensor) -> torch.Tensor:
    """``matrix_exp(hat(ω))`` (the route the issue compares against)."""
    return torch.linalg.matrix_exp(so3.hat(w))


def _ref_exp_rodrigues(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues with dense ``K`` and ``K @ K`` (the previous ``so3.exp``)."""
    K = so3.hat(w)
    t2 = (w * w).sum(-1)
    eps = 1e-2 if w.dtype == torch.float32 else 1e-4
    small = t2 < eps * eps
    ts2 = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(ts2)
    A = torch.where(small, 1.0 - t2 / 6.0, torch.sin(t) / t)
    B = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / ts2)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + A[..., None, None] * K + B[..., None, None] * (K @ K)


def _ref_log(R: torch.Tensor) -> torch.Tensor:
    """The previous matrix-based ``so3.log`` (vee, diagonal, column gather by argmax)."""
    dtype, device = R.dtype, R.device
    eps_small = 1e-2 if dtype == torch.float32 else 1e-4
    v = so3.vee(R)
    c = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    s2 = (v * v).sum(-1)
    small = (s2 < eps_small * eps_small) & (c > 0)
    obtuse = c < 0
    generic = ~(small | obtuse)
    s_g = torch.sqrt(torch.where(generic, s2, torch.ones_like(s2)))
    c_g = torch.where(generic, c, torch.zeros_like(c))
    fac_g = torch.atan2(s_g, c_g) / s_g
    s2_s = torch.where(small, s2, torch.zeros_like(s2))
    fac_s = 1.0 + s2_s * (1.0 / 6.0 + s2_s * (3.0 / 40.0 + s2_s * (5.0 / 112.0)))
    omega_main = torch.where(small, fac_s, fac_g)[..., None] * v
    R_pi = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dtype, device=device))
    Rp = torch.where(obtuse[..., None, None], R, R_pi)
    vp = so3.vee(Rp)
    cp = 0.5 * (Rp.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    eye = torch.eye(3, dtype=dtype, device=device)
    Bp = 0.5 * (Rp + Rp.transpose(-1, -2)) - cp[..., None, None] * eye
    k = Bp.diagonal(dim1=-2, dim2=-1).argmax(-1)
    col = torch.gather(Bp, -1, k[..., None, None].expand(*k.shape, 3, 1)).squeeze(-1)
    n = col / torch.linalg.vector_norm(col, dim=-1, keepdim=True)
    sign = torch.where((n * vp).sum(-1) < 0, -torch.ones_like(cp), torch.ones_like(cp))
    n = n * sign[..., None]
    omega_pi = torch.atan2((n * vp).sum(-1), cp)[..., None] * n
    return torch.where(obtuse[..., None], omega_pi, omega_main)


def _ref_sqrt(R: torch.Tensor) -> torch.Tensor:
    return _ref_exp_rodrigues(0.5 * _ref_log(R))


def _ref_face_curvature(R, mesh, kind="two_prong"):
    """Generic loop curvature (``face_loops`` + ``orient`` + ``two_prong`` / ``holonomy``)."""
    _, groups = curvature.face_loops(mesh)
    _, le, ls, _ = groups[0]
    L = orient(R, le, ls)
    return curvature.holonomy(L) if kind == "holonomy" else curvature.two_prong(L, -1)


def _ref_face_torsion(R, mesh, frames=None):
    """Generic √R torsion (loop gather, ``torsion.two_prong``), frames as in ``face_torsion``."""
    V = mesh.vertices.to(R.dtype)
    if frames is not None:
        e = mesh.edges
        R = frames[e[:, 0]] @ R @ frames[e[:, 1]].transpose(-1, -2)
    H = _ref_sqrt(R)
    _, groups = curvature.face_loops(mesh)
    _, le, ls, loops = groups[0]
    L = orient(R, le, ls)
    pts = V[loops]
    d = torch.roll(pts, shifts=-1, dims=-2) - pts
    Hf = orient(H, le, ls)
    fwd = (Hf @ d[..., None]).squeeze(-1)
    bwd = (Hf.transpose(-1, -2) @ (-d)[..., None]).squeeze(-1)
    val = _torsion.two_prong(L, fwd, bwd, -1)
    if frames is not None:
        val = (frames[loops[:, 0]].transpose(-1, -2) @ val[..., None]).squeeze(-1)
    return val


def _ref_dd(R, mesh):
    """Generic dense ``𝔡∇ Alt 𝔡∇ Alt θ̃`` (``(T, 4, 4, 3, 3)`` tables, tuple machinery)."""
    T = dnabla.tet_transports(R, mesh)
    pts = mesh.vertices.to(R.dtype)[mesh.tets]
    th = dnabla.solder_form_sqrt(dnabla.tet_transports(_ref_sqrt(R), mesh), pts)
    return dnabla.averaged_dd_tet(T, th)



# ----------------------------------------------------------------------------- the loss

#: Largest relative difference between a loss row and its eager reference (per term and total):
#: a row above it is reported as failed (the two do not compute one loss).
LOSS_AGREEMENT_RTOL = 1e-6


def loss_cases(mesh) -> list:
    """``[(row name, FrameFieldLoss)]``: the loss :func:`torchconn.frames.design` builds with its
    defaults (``DEFAULTS``: weights, ``smooth_power``, ``smooth_eps``, ``align_kind``, ``align_eps``,
    ``feature_angle_deg``; ``tests/test_losses.py`` checks it against the loss ``design()`` itself
    constructs) and the same options with every term of ``TERMS`` weighted 1."""
    from torchconn.frames.design import DEFAULTS
    from torchconn.frames.loss import TERMS, FrameFieldLoss

    opts = {k: DEFAULTS[k] for k in ("feature_angle_deg", "smooth_power", "smooth_eps", "align_kind", "align_eps")}
    return [("frame_field_loss(default)", FrameFieldLoss(mesh, dict(DEFAULTS["weights"]), **opts)),
            ("frame_field_loss(all terms)", FrameFieldLoss(mesh, {k: 1.0 for k in TERMS}, **opts))]


def _ref_dd_frames(R, mesh, frames):
    """Generic dense ``𝔡∇ Alt 𝔡∇ Alt θ̃`` with the solder form in ``frames`` (``(T, 4, 4, 3, 3)`` tables)."""
    return dnabla.averaged_dd_tet(dnabla.tet_transports(R, mesh), dnabla.tet_solder_sqrt(R, mesh, frames))


def ref_frame_loss_terms(loss, edge_rot, frames) -> dict:
    """Eager composition of the terms of ``loss`` (a ``FrameFieldLoss``) from the library's single-term
    functions (:mod:`torchconn.frames.terms`, :mod:`torchconn.frames.octahedral`) and the generic
    operators above (loop curvature and torsion, dense ``d∇`` tables): ``{term: value}`` of the
    weighted terms and ``"total"``. The reference the loss rows are timed and checked against."""
    from torchconn.frames import octahedral
    from torchconn.frames import terms as T

    mesh, w = loss.mesh, loss.weights
    e = mesh.edges
    p, eps = loss.smooth_power, loss.smooth_eps
    out = {}
    if w["smooth"]:
        out["smooth"] = T.smoothness_loss(edge_rot, p, eps)
    if w["tie"]:
        out["tie"] = T.tie_loss(edge_rot, frames, e, p, eps)[0]
    if w["flat"] or w["dnabla"]:
        hol = _ref_face_curvature(edge_rot, mesh, kind="holonomy") + torch.eye(3, dtype=edge_rot.dtype)
    if w["flat"]:
        out["flat"] = T.symmetric_flatness_loss(hol)
    if w["torsion"]:
        M = T.matched_rotations_of(edge_rot, frames, e)
        tor = _ref_face_torsion(M, mesh, frames)
        out["torsion"] = ((tor**2).sum(-1) / loss.face_area.to(tor.dtype)).mean()
    if w["dnabla"]:
        with torch.no_grad():
            regular = (octahedral.closest_element(hol.detach())[0] == 0)[mesh.tet_faces].all(-1)
        t = mesh.vertices.to(torch.float64)[mesh.tets]
        scale = (torch.linalg.det(t[:, 1:] - t[:, :1]).abs() / 6.0).pow(2.0 / 3.0).to(edge_rot.dtype)
        per = (_ref_dd_frames(edge_rot, mesh, frames) ** 2).sum(-1) / scale
        out["dnabla"] = per[regular].sum() / max(1, int(regular.sum()))
    for k, verts, normals in (("align", loss.align_vertices, loss.align_normals),
                              ("feature", loss.feature_vertices_rep, loss.feature_normals)):
        if w[k]:
            n = normals.to(frames.dtype)
            out[k] = (T.axis_angle_loss(frames[verts], n, loss.align_eps) if loss.align_kind == "angle"
                      else T.normal_alignment_loss(frames[verts], n))
    if w["dirichlet"]:
        out["dirichlet"] = T.matched_dirichlet_loss(frames, e)
    out["total"] = sum(w[k] * v for k, v in out.items())
    return out


def loss_agreement(loss, edge_rot, frames) -> tuple[float, str]:
    """``(largest relative difference, term)`` between ``loss(edge_rot, frames)`` and
    :func:`ref_frame_loss_terms` over the terms and the total (no gradients)."""
    with torch.no_grad():
        a = loss(edge_rot, frames)
        b = ref_frame_loss_terms(loss, edge_rot, frames)
    if a.keys() != b.keys():
        return math.inf, f"terms differ: {sorted(a)} vs {sorted(b)}"
    rel = {k: abs(float(a[k]) - float(b[k])) / max(abs(float(b[k])), 1e-30) for k in b}
    worst = max(rel, key=rel.get)
    return rel[worst], worst


