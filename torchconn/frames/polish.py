"""Guarded frames-only polish of a frame field with the smoothness metric's own angle.

After the connection optimization the frames can still be moved to lower the *metric* (the mean
over edges of the angle of ``(F_i g*)^T F_j``, :mod:`torchconn.frames.metrics`), which is not
exactly what the connection loss minimizes. :func:`polish_frames` runs Adam on per-vertex
rotations ``F_i = exp(hat(w_i)) F_i^0`` (about the normal only at non-feature boundary
vertices, so the alignment stays exact; :mod:`torchconn.frames.param`) minimizing

    mean_e 2 asin(sqrt(||F_i g_ij - F_j||^2 + eps^2) / (2 sqrt 2))  +  w_f * feature angle

with ``g_ij`` re-matched at every step (no gradient through the matching) and the feature term of
:func:`torchconn.frames.loss.axis_angle_loss`. The mean angle prefers to split large edge rotations
into new singular faces, so the result is *guarded*: every ``check_every`` steps the field is
scored, and the best-smoothness checkpoint (step 0, the input, included) with at most
``max_singular_faces`` singular faces and no tet with exactly one singular face is returned.
"""
from __future__ import annotations

import math

import torch

from ..lie import so3
from . import octahedral
from .constraints import BoundaryConstraint
from .loss import axis_angle_loss
from .metrics import frame_metrics
from .param import constrained_frames
from .solver import cosine_factor

__all__ = ["polish_frames"]


def polish_frames(mesh, frames: torch.Tensor, steps: int, lr: float = 0.01, check_every: int = 50,
                  feature_weight: float = 1.0, max_singular_faces: int | None = None, eps: float = 1e-3,
                  angle_deg: float = 30.0, align_eps: float = 1e-3) -> tuple[torch.Tensor, dict]:
    """Guarded polish (see the module docstring).

    Args:
        mesh: ``TetMesh``.
        frames: ``(V, 3, 3)`` input field (non-feature boundary frames should be aligned).
        steps: Adam steps (cosine lr from ``lr`` to 0); 0 returns the input.
        check_every: scoring interval of the guard.
        feature_weight: weight of the feature-alignment angle term.
        max_singular_faces: the guard's bound (``None``: the input's count).

    Returns:
        ``(frames, info)``: ``info["accepted_step"]`` and ``info["checks"]``, a list of
        ``(step, smoothness_mean_deg, n_singular_faces, n_tets_one_singular_face)``.
    """
    if steps < 0 or check_every < 1 or not lr > 0:
        raise ValueError(f"need steps >= 0, check_every >= 1, lr > 0; got {steps}, {check_every}, {lr}")
    dtype = mesh.vertices.dtype
    F0 = frames.detach().to(dtype)
    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    fv, fn = bc.feature_targets()
    e0, e1 = mesh.edges[:, 0], mesh.edges[:, 1]

    def score(F):
        m = frame_metrics(F, mesh, angle_deg)
        return m["smoothness_mean_deg"], m["n_singular_faces"], m["n_tets_one_singular_face"]

    s0 = score(F0)
    bound = s0[1] if max_singular_faces is None else int(max_singular_faces)
    checks = [(0, *s0)]
    best, best_F, best_step = (s0[0] if s0[1] <= bound and s0[2] == 0 else math.inf), F0, 0
    if steps == 0:
        return F0, {"accepted_step": 0, "checks": checks}
    w = torch.zeros_like(F0[:, :, 0], requires_grad=True)
    opt = torch.optim.Adam([w], lr=lr)

    def current():
        return constrained_frames(w, F0, bc.constrained, bc.normals)

    with torch.enable_grad():
        for s in range(steps):
            for pg in opt.param_groups:
                pg["lr"] = lr * cosine_factor(s, steps)
            F = current()
            A, B = F[e0], F[e1]
            with torch.no_grad():
                _, g = octahedral.match_edges(F, mesh.edges)
            d2 = ((A @ g - B) ** 2).sum((-2, -1))
            ang = 2.0 * torch.asin((torch.sqrt(d2 + eps * eps) / (2.0 * math.sqrt(2.0))).clamp(max=1.0))
            total = ang.mean()
            if feature_weight and fv.numel():
                total = total + feature_weight * axis_angle_loss(F[fv], fn, align_eps)
            opt.zero_grad(set_to_none=True)
            total.backward()
            opt.step()
            if (s + 1) % check_every == 0 or s + 1 == steps:
                with torch.no_grad():
                    Fs = so3.project_to_rotation(current())
                sc = score(Fs)
                checks.append((s + 1, *sc))
                if sc[1] <= bound and sc[2] == 0 and sc[0] < best:
                    best, best_F, best_step = sc[0], Fs, s + 1
    return best_F, {"accepted_step": best_step, "checks": checks}
