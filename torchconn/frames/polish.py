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
The mean angle is an L1 measure: lowered alone it concentrates the turning of the frames and
raises the RMS angle and the Dirichlet energy (issue 13), so this polish is off by default.

:func:`quality_polish` (the connection method's last stage) lowers the mean angle *and* the
matched Dirichlet energy ``mean_e ||F_i g_ij - F_j||^2`` (Ray et al. 2016, Palmer et al. 2020)
along a path whose Dirichlet weight is annealed from high to low, and its guard
(:func:`guard_violations`) admits only fields no worse than a reference field (the SH baseline)
on every guarded metric: mean and RMS angle, Dirichlet energy, singular and complex singular
faces, singular curves ending inside, tets with one singular face, boundary and feature-curve
alignment. The reference itself is always a candidate, so the result is never worse than it.
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
from .singular import classify_holonomy, face_holonomy_from_matchings
from .solver import cosine_factor

__all__ = ["polish_frames", "quality_polish", "guard_violations", "quality_score", "GUARD_CONTINUOUS",
           "GUARD_COUNTS", "GUARD_BOUNDS"]


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


# ----------------------------------------------------------------------------- quality polish
#: Metrics the quality guard holds at or below the reference's (times ``1 + slack``).
GUARD_CONTINUOUS = ("smoothness_mean_deg", "smoothness_rms_deg", "dirichlet_energy_mean")
#: Counts the quality guard holds at or below the reference's.
GUARD_COUNTS = ("n_singular_faces", "n_singular_faces_complex", "n_curves_ending_inside", "n_tets_one_singular_face")
#: ``metric: floor``: held at or below ``max(reference, floor)`` (degrees). Boundary alignment may
#: reach the issue's 0.5 degree bound; the feature-curve alignment is held at the reference's (a
#: floor of 2 degrees, the issue's bound, let the polish trade the tangents for smoothness up to
#: it: measured in studies/frame_quality.py).
GUARD_BOUNDS = {"alignment_mean_deg": 0.5, "feature_curve_alignment_mean_deg": 0.0}


def guard_violations(metrics: dict, reference: dict, slack: float = 0.0, bounds: dict | None = None) -> list[str]:
    """The metrics of ``metrics`` that are worse than ``reference`` (both :func:`frame_metrics` dicts).

    A field passes the guard (empty list) when: ``smoothness_mean_deg``, ``smoothness_rms_deg``
    and ``dirichlet_energy_mean`` are at most ``(1 + slack)`` times the reference's; the counts of
    :data:`GUARD_COUNTS` (singular faces, complex-type singular faces, singular curves ending
    inside, tets with one singular face) at most the reference's; and each metric of
    :data:`GUARD_BOUNDS` at most ``max(reference, floor)`` (a ``nan`` value, e.g. no feature
    curve, passes). NaN in a continuous metric fails.
    """
    bad = []
    for k in GUARD_CONTINUOUS:
        if not metrics[k] <= reference[k] * (1.0 + slack):
            bad.append(k)
    for k in GUARD_COUNTS:
        if metrics[k] > reference[k]:
            bad.append(k)
    for k, floor in (GUARD_BOUNDS if bounds is None else bounds).items():
        v, r = metrics[k], reference[k]
        if v == v and v > (max(r, floor) if r == r else floor):
            bad.append(k)
    return bad


def quality_score(metrics: dict, reference: dict, dirichlet_weight: float = 1.0) -> float:
    """``log(mean angle / reference's) + b log(Dirichlet energy / reference's)`` with ``b = dirichlet_weight``
    (lower is better; 0 at the reference)."""
    tiny = 1e-300
    return (math.log(max(metrics["smoothness_mean_deg"], tiny) / max(reference["smoothness_mean_deg"], tiny))
            + dirichlet_weight
            * math.log(max(metrics["dirichlet_energy_mean"], tiny) / max(reference["dirichlet_energy_mean"], tiny)))


def quality_polish(mesh, frames: torch.Tensor, reference_frames: torch.Tensor, *, steps: int = 300,
                   lr: float = 0.01, dirichlet_weight: tuple[float, float] = (4.0, 0.25),
                   feature_weight: float = 1.0, singular_weight: float = 0.0, check_every: int = 20,
                   slack: float = 0.0, score_dirichlet: float = 1.0, lock_tangents: bool = False,
                   path_from: str = "start", feature_curve_floor: float = 0.0, eps: float = 1e-3,
                   angle_deg: float = 30.0, align_eps: float = 1e-3,
                   reference_metrics: dict | None = None) -> tuple[torch.Tensor, dict]:
    """Guarded polish that lowers the mean edge angle and the Dirichlet energy together.

    Adam on per-vertex rotations ``F_i = exp(hat(w_i)) F_i^start`` (about the normal only at
    non-feature boundary vertices, :mod:`torchconn.frames.param`; constant ``lr``) minimizing

        mean_e a_e / a_ref  +  lambda(s) mean_e ||F_i g_ij - F_j||_F^2 / D_ref  +  w_f feature angle / a_ref

    with ``a_e = 2 asin(sqrt(d_e^2 + eps^2) / (2 sqrt 2))`` the smoothed edge angle (radians),
    ``d_e^2 = ||F_i g_ij - F_j||^2`` the matched Dirichlet energy of the edge (Ray et al. 2016,
    Palmer et al. 2020; ``g_ij`` re-matched every step without gradient), ``a_ref`` and
    ``D_ref`` the reference field's mean angle and mean energy (so the two terms are
    commensurate on any mesh), the feature term :func:`~torchconn.frames.loss.axis_angle_loss`
    over :meth:`~torchconn.frames.constraints.BoundaryConstraint.feature_targets`, and the
    Dirichlet weight annealed geometrically from ``dirichlet_weight[0]`` to
    ``dirichlet_weight[1]`` over the steps: the path starts near the Dirichlet minimum (which
    lowers every metric of a field that is not already at it) and moves towards the L1 one
    (lower mean angle, higher energy), tracing the trade-off between the two.

    ``singular_weight = c > 0`` charges half-turn and complex singular faces more than quarter
    turns: at the start and at every check, the faces whose matched holonomy
    (:func:`~torchconn.frames.singular.classify_holonomy`) is a half turn or complex are found,
    and the edge terms (angle and energy) of their edges weigh ``1 + c`` instead of 1 until the
    next check; the frames around such a face are pulled together, which moves the defect off
    the face or splits it into quarter turns.

    The guard: every ``check_every`` steps the field is scored by :func:`frame_metrics`;
    a checkpoint is admissible when :func:`guard_violations` against the reference field is
    empty, and the admissible one with the lowest :func:`quality_score` (``score_dirichlet``) is returned. The
    reference field itself and the start field are candidates too, so the result is never worse
    than the reference on any guarded metric (at worst it *is* the reference field).

    Args:
        mesh: ``TetMesh``.
        frames: ``(V, 3, 3)`` start field (non-feature boundary frames aligned).
        reference_frames: ``(V, 3, 3)`` the field to beat (e.g. the SH baseline).
        steps: Adam steps (0: only the candidates ``frames`` and ``reference_frames`` are scored).
        lr: Adam learning rate (constant; the annealed weight does the scheduling).
        dirichlet_weight: ``(first, last)`` weight ``lambda`` of the normalized Dirichlet term.
        feature_weight: weight ``w_f`` of the feature-alignment angle term.
        singular_weight: extra weight ``c`` of the edges of half-turn and complex singular faces.
        check_every: scoring interval of the guard.
        slack: relative tolerance of the guard on the continuous metrics (0: never worse).
        score_dirichlet: weight ``b`` of the Dirichlet ratio in :func:`quality_score`, the
            choice among admissible checkpoints (< 1 favours the mean angle).
        lock_tangents: at the vertices inside the feature curves
            (:class:`~torchconn.frames.constraints.BoundaryConstraint` tangent pairs), rotate only
            about the start frame's axis closest to the curve tangent, so the feature-curve
            alignment of the path's first field is kept exactly (it can then neither improve nor worsen).
        feature_curve_floor: the guard holds the feature-curve alignment mean at or below
            ``max(reference's, feature_curve_floor)`` degrees (0: never worse than the reference;
            2: the issue's per-model bound, which lets the polish trade tangent alignment for
            smoothness up to it).
        path_from: ``"start"`` (the path starts at ``frames``) or ``"reference"`` (at
            ``reference_frames``; ``frames`` is then only a candidate, scored as step 0).
        reference_metrics: :func:`frame_metrics` of ``reference_frames`` if already computed.

    Returns:
        ``(frames, info)``; ``info`` has ``"accepted"`` (``"reference"``, ``"start"`` or
        ``"step"``), ``"accepted_step"`` (-1 for the reference field, 0 for the start field),
        ``"score"``, ``"checks"`` (a list of ``(step, score, admissible, violations)``),
        ``"reference"`` (the reference's metrics) and ``"final"`` (the returned field's metrics).
    """
    if path_from not in ("start", "reference"):
        raise ValueError(f"quality_polish: path_from must be 'start' or 'reference', got {path_from!r}")
    if steps < 0 or check_every < 1 or not lr > 0 or slack < 0 or not singular_weight >= 0:
        raise ValueError(f"quality_polish: need steps >= 0, check_every >= 1, lr > 0, slack >= 0, "
                         f"singular_weight >= 0; got {steps}, {check_every}, {lr}, {slack}, {singular_weight}")
    lam0, lam1 = (float(x) for x in dirichlet_weight)
    if not (lam0 >= 0 and lam1 >= 0 and math.isfinite(lam0) and math.isfinite(lam1)):
        raise ValueError(f"quality_polish: dirichlet_weight must be two finite numbers >= 0, got {dirichlet_weight}")
    dtype = mesh.vertices.dtype
    V = mesh.vertices.shape[0]
    for name, x in (("frames", frames), ("reference_frames", reference_frames)):
        if not torch.is_tensor(x) or tuple(x.shape) != (V, 3, 3):
            raise ValueError(f"quality_polish: {name} must be a ({V}, 3, 3) tensor for this mesh, got "
                             f"{tuple(x.shape) if torch.is_tensor(x) else type(x).__name__}")
    F0 = frames.detach().to(dtype)
    Fr = reference_frames.detach().to(dtype)
    ref = reference_metrics if reference_metrics is not None else frame_metrics(Fr, mesh, angle_deg)
    if not feature_curve_floor >= 0:
        raise ValueError(f"quality_polish: feature_curve_floor must be >= 0, got {feature_curve_floor}")
    bounds = {**GUARD_BOUNDS, "feature_curve_alignment_mean_deg": float(feature_curve_floor)}
    checks = []
    best = (0.0, Fr, "reference", -1, ref)  # the reference always passes its own guard

    def consider(F, step, kind):
        nonlocal best
        m = frame_metrics(F, mesh, angle_deg)
        bad = guard_violations(m, ref, slack, bounds)
        sc = quality_score(m, ref, score_dirichlet)
        checks.append((step, sc, not bad, bad))
        if not bad and sc < best[0]:
            best = (sc, F, kind, step, m)

    consider(F0, 0, "start")
    if path_from == "reference":
        F0 = Fr
    if steps > 0:
        bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
        fv, fn = bc.feature_targets()
        e0, e1 = mesh.edges[:, 0], mesh.edges[:, 1]
        a_ref = max(math.radians(ref["smoothness_mean_deg"]), 1e-12)
        d_ref = max(ref["dirichlet_energy_mean"], 1e-12)
        w = torch.zeros_like(F0[:, :, 0], requires_grad=True)
        opt = torch.optim.Adam([w], lr=lr)

        cons, axis = bc.constrained, bc.normals.to(dtype)
        if lock_tangents and bc.tangent_vertices is not None and bc.tangent_vertices.numel():
            inner = ~bc.tangent_at_corner
            tv, td = bc.tangent_vertices[inner], bc.tangent_dirs[inner].to(dtype)
            Ft = F0[tv]
            k = (Ft * td[:, :, None]).sum(-2).abs().argmax(-1)  # the axis closest to the tangent
            cons, axis = cons.clone(), axis.clone()
            cons[tv] = True
            axis[tv] = torch.gather(Ft, -1, k[:, None, None].expand(-1, 3, 1)).squeeze(-1)

        def current():
            return constrained_frames(w, F0, cons, axis)

        def edge_weights(F):  # 1 + c on the edges of half-turn / complex singular faces (None: all 1)
            if not singular_weight:
                return None
            _, g = octahedral.match_edges(F, mesh.edges)
            typ = classify_holonomy(face_holonomy_from_matchings(g, mesh)[2])[0]
            bad = mesh.face_edges[typ >= 2].reshape(-1)
            ew = torch.ones(mesh.edges.shape[0], dtype=F.dtype, device=F.device)
            ew[bad] = 1.0 + float(singular_weight)
            return ew / ew.mean()

        ew = edge_weights(F0)

        with torch.enable_grad():
            for s in range(steps):
                lam = lam0 * (lam1 / lam0) ** (s / max(steps - 1, 1)) if lam0 > 0 and lam1 > 0 else (
                    lam0 + (lam1 - lam0) * s / max(steps - 1, 1))
                F = current()
                with torch.no_grad():
                    _, g = octahedral.match_edges(F, mesh.edges)
                d2 = ((F[e0] @ g - F[e1]) ** 2).sum((-2, -1))
                ang = 2.0 * torch.asin((torch.sqrt(d2 + eps * eps) / (2.0 * math.sqrt(2.0))).clamp(max=1.0))
                if ew is not None:
                    ang, d2 = ang * ew, d2 * ew
                total = ang.mean() / a_ref + lam * d2.mean() / d_ref
                if feature_weight and fv.numel():
                    total = total + feature_weight * axis_angle_loss(F[fv], fn.to(F.dtype), align_eps) / a_ref
                opt.zero_grad(set_to_none=True)
                total.backward()
                opt.step()
                if (s + 1) % check_every == 0 or s + 1 == steps:
                    with torch.no_grad():
                        Fs = so3.project_to_rotation(current())
                        consider(Fs, s + 1, "step")
                        ew = edge_weights(Fs)
    score, F, kind, step, m = best
    return F, {"accepted": kind, "accepted_step": step, "score": score, "checks": checks, "reference": ref,
               "final": m}
