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

:func:`quality_polish` (the connection method's last stage) runs the quality paths of
:mod:`torchconn.frames.refine` (L-BFGS on the frames, the mean angle and the matched Dirichlet
energy ``mean_e ||F_i g_ij - F_j||^2`` of Ray et al. 2016 / Palmer et al. 2020 traded along an
annealed weight, with the feature curves soft or held) and its guard (:func:`guard_violations`)
admits only fields no worse than a reference field (the SH baseline), within ``slack``, on every
guarded metric: mean and RMS angle, Dirichlet energy, singular and complex singular faces,
singular curves ending inside, tets with one singular face, boundary and feature-curve
alignment. The reference itself is always a candidate, so the result is never worse than it.
Where the best candidate keeps complex-type singular faces, the singular-structure repair of
:mod:`torchconn.frames.structure` makes a field with fewer of them and the paths run again from
it, under the same guard.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..lie import so3
from . import octahedral
from .constraints import BoundaryConstraint
from .loss import axis_angle_loss
from .mbo import mbo_frames
from .metrics import frame_metrics
from .param import constrained_frames
from .refine import DIRICHLET_WEIGHTS, PATH_KINDS, quality_path
from .solver import cosine_factor
from .structure import repair_structure

__all__ = ["polish_frames", "quality_polish", "Candidate", "connection_candidates", "choose_by_proxies", "PATH_STARTS", "choose_candidate", "guard_violations", "quality_score", "GUARD_CONTINUOUS",
           "GUARD_COUNTS", "GUARD_STRICT", "GUARD_BOUNDS"]


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
#: Counts the quality guard holds at or below the reference's times ``1 + slack``.
GUARD_COUNTS = ("n_singular_faces", "n_singular_faces_complex")
#: Counts the quality guard holds at or below the reference's exactly (defects of the singular graph).
GUARD_STRICT = ("n_curves_ending_inside", "n_tets_one_singular_face")
#: ``metric: floor``: held at or below ``max(reference, floor)`` (degrees): the boundary alignment
#: may reach the issue's 0.5 degree bound, the feature-curve alignment its 2 degree bound.
GUARD_BOUNDS = {"alignment_mean_deg": 0.5, "feature_curve_alignment_mean_deg": 2.0}


def guard_violations(metrics: dict, reference: dict, slack: float = 0.0, bounds: dict | None = None) -> list[str]:
    """The metrics of ``metrics`` that are worse than ``reference`` (both :func:`frame_metrics` dicts).

    A field passes the guard (empty list) when: ``smoothness_mean_deg``, ``smoothness_rms_deg``,
    ``dirichlet_energy_mean`` and the counts of :data:`GUARD_COUNTS` (singular and complex-type
    singular faces) are at most ``(1 + slack)`` times the reference's; the counts of
    :data:`GUARD_STRICT` (singular curves ending inside, tets with one singular face) at most the
    reference's; and each metric of :data:`GUARD_BOUNDS` (or ``bounds``) at most
    ``max(reference, floor)`` (a ``nan`` value, e.g. no feature curve, passes). NaN in a
    continuous metric fails.
    """
    bad = []
    for k in GUARD_CONTINUOUS:
        if not metrics[k] <= reference[k] * (1.0 + slack):
            bad.append(k)
    for k in GUARD_COUNTS:
        if metrics[k] > reference[k] * (1.0 + slack):
            bad.append(k)
    for k in GUARD_STRICT:
        if metrics[k] > reference[k]:
            bad.append(k)
    for k, floor in (GUARD_BOUNDS if bounds is None else bounds).items():
        v, r = metrics[k], reference[k]
        if v == v and v > (max(r, floor) if r == r else floor):
            bad.append(k)
    return bad


def quality_score(metrics: dict, reference: dict, dirichlet_weight: float = 1.0, complex_weight: float = 0.0) -> float:
    """``log(mean angle / reference's) + b log(Dirichlet energy / reference's) + c log((n_c + 1) / (n_c_ref + 1))``
    with ``b = dirichlet_weight``, ``c = complex_weight`` and ``n_c`` the complex-type singular faces
    (lower is better; 0 at the reference)."""
    tiny = 1e-300
    score = (math.log(max(metrics["smoothness_mean_deg"], tiny) / max(reference["smoothness_mean_deg"], tiny))
             + dirichlet_weight
             * math.log(max(metrics["dirichlet_energy_mean"], tiny) / max(reference["dirichlet_energy_mean"], tiny)))
    if complex_weight:
        score += complex_weight * math.log((metrics["n_singular_faces_complex"] + 1.0)
                                           / (reference["n_singular_faces_complex"] + 1.0))
    return score


def choose_candidate(scored: Sequence[tuple[float, dict]], feature_curve_bound: float = 2.0) -> int:
    """Index of the candidate :func:`quality_polish` returns among admissible ``(score, metrics)`` pairs.

    Candidates whose ``feature_curve_alignment_mean_deg`` is within ``feature_curve_bound`` (or
    ``nan``: no feature curve) come first; among them (all of them when none is) the lowest score
    wins, the first one on a tie.
    """
    if not scored:
        raise ValueError("choose_candidate: no candidate")
    within = [i for i, (_, m) in enumerate(scored) if not m["feature_curve_alignment_mean_deg"] > feature_curve_bound]
    pool = within or list(range(len(scored)))
    return min(pool, key=lambda i: scored[i][0])


#: Start fields of the quality paths (:func:`quality_polish`'s ``path_starts``).
PATH_STARTS = ("reference", "frames", "mbo")


def quality_polish(mesh, frames: torch.Tensor, reference_frames: torch.Tensor, *,
                   paths: Sequence[str] = PATH_KINDS, dirichlet_weights: Sequence[float] = DIRICHLET_WEIGHTS,
                   rounds: int = 2, iters: int = 20, feature_weight: float = 1.0, tangent_weight: float = 0.25,
                   complex_weight: float = 0.0, path_starts: Sequence[str] = ("reference", "mbo"),
                   mbo_options: dict | None = None, conditional_starts: bool = True,
                   slack: float = 0.01, score_dirichlet: float = 1.0,
                   score_complex: float = 0.1, feature_curve_bound: float = 2.0, repair_rounds: int = 1,
                   repair_residual_weight: float = 0.5, repair_relax_iters: int = 40,
                   repair_dirichlet_weights: Sequence[float] | None = (8.0, 2.0, 0.5), eps: float = 1e-3,
                   angle_deg: float = 30.0, align_eps: float = 1e-3,
                   reference_metrics: dict | None = None) -> tuple[torch.Tensor, dict]:
    """Guarded quality stage: the checkpoints of quality paths, the best one no worse than a reference.

    The candidates are ``frames``, ``reference_frames``, the MBO field when ``"mbo"`` is among
    ``path_starts``, every path checkpoint, and the fields of the singular-structure repair.

    Runs :func:`~torchconn.frames.refine.quality_path` for every kind in ``paths`` (``"soft"``,
    ``"tangent"``; L-BFGS on the frames along ``mean angle / a_ref + lambda Dirichlet / D_ref`` with
    ``lambda`` over ``dirichlet_weights``, ``a_ref`` and ``D_ref`` the reference's) from every
    start of ``path_starts``: ``"reference"`` (``reference_frames``), ``"frames"`` (``frames``) and
    ``"mbo"`` (:func:`~torchconn.frames.mbo.mbo_frames` of ``mesh``, the diffusion-projection field
    of Palmer, Bommes & Solomon 2020, computed here with ``mbo_options``). It scores every
    checkpoint and every start field with :func:`frame_metrics`. A candidate is *admissible* when
    :func:`guard_violations` against the reference is empty: mean and RMS angle, Dirichlet energy,
    singular and complex-type singular faces at most ``1 + slack`` times the reference's (the
    issue's "no more than 1% worse" with ``slack = 0.01``), no more singular curves ending inside
    or tets with one singular face, the boundary alignment within ``max(reference, 0.5 deg)`` and
    the feature-curve alignment within ``max(reference, feature_curve_bound)``. Among the
    admissible candidates those whose feature-curve alignment is within ``feature_curve_bound``
    come first (the bound is a target of its own), and the one with the lowest
    :func:`quality_score` (``score_dirichlet``, ``score_complex``) is returned. The reference is
    always admissible, so the result is never worse than it beyond ``slack`` on any guarded
    metric (at worst it *is* the reference field).

    Then the singular-structure repair (``repair_rounds`` times, :mod:`torchconn.frames.structure`):
    where the best candidate so far has complex-type singular faces,
    :func:`~torchconn.frames.structure.repair_structure` searches its edge matchings for fewer of
    them and relaxes the frames onto the result; when the relaxed field has fewer complex faces
    than the candidate, it is a candidate (kind ``"repaired"``) and the paths run from it too (start
    ``"repair"``, or ``"repair1"``... for later rounds) with ``repair_dirichlet_weights``. The paths
    keep the singular structure they start from, and neither the SH nor the MBO field offers one
    without these faces on the models where they are left; the repair makes that structure. On the
    35 HexMe ``c`` meshes (quality stage alone from the SH field, one thread, docs/results/hexme.md)
    it takes the complex-type faces 73 -> 29 (of the SH field's 126) with the geometric-mean ratios of
    mean angle, RMS angle and Dirichlet energy 0.938 / 0.969 / 0.940 instead of 0.937 / 0.968 /
    0.939, and the models above the 2 degree feature-curve bound 6 -> 4; with the full
    ``dirichlet_weights`` for the repair paths 26 faces, at about 10 s more on HexMe i02u_m2 (159k
    tets), which then takes over the issue's 60 s on 2 cores.

    Measured on the 35 HexMe ``c`` meshes (docs/results/hexme.md, the quality stage alone from the
    SH field, one thread): the paths from the MBO field reach other singular structures than
    those from the SH field (fewer complex-type singular faces on the coarse polyhedra, e.g. n14c
    18 -> 4). With ``path_starts=("reference", "mbo")`` and ``score_complex=0.1`` the set's
    complex faces go 126 -> 73 with ``conditional_starts`` (the default: MBO paths only where
    the MBO field has fewer complex faces than the SH field) and 126 -> 67 without it, against
    103 with the SH start alone (``path_starts=("reference",)``), at the same mean angle, RMS
    angle and Dirichlet energy (geometric-mean ratios 0.937 / 0.969 / 0.941). Without
    ``conditional_starts`` the whole method takes HexMe i02u_m2 (159k tets) 65.6 s on 2 cores,
    over the issue's 60 s; 10 iterations per round instead of 20 give the same ``c``-set figures
    but a worse 1M-tet field (mean-angle ratio 0.991 instead of 0.984). The
    ``score_complex`` weight changes no choice there (0.1, 0.3 and 1.0 pick the same
    candidates): the guard decides. The paths from the connection-optimized field
    (``"frames"``) inherit its extra singular faces and fail the guard there (HexMe i02u).

    Args:
        mesh: ``TetMesh``.
        frames: ``(V, 3, 3)`` a candidate field (the connection method's optimized field;
            non-feature boundary frames aligned).
        reference_frames: ``(V, 3, 3)`` the field to beat (the SH baseline).
        paths: path kinds to run (``()``: only the start fields are scored).
        path_starts: start fields of the paths, each of :data:`PATH_STARTS` at most once.
        mbo_options: keyword arguments of :func:`~torchconn.frames.mbo.mbo_frames`
            (``feature_angle_deg`` defaults to ``angle_deg``, ``warm_start`` to ``True``).
        conditional_starts: the paths from a start other than ``"reference"`` run only when that
            start field has fewer complex-type singular faces than the reference (the reason to
            start elsewhere: the paths keep the singular structure they start from); the start
            field is a candidate either way.
        dirichlet_weights, rounds, iters, feature_weight, tangent_weight, complex_weight, eps: of
            :func:`~torchconn.frames.refine.quality_path`.
        slack: relative tolerance of the guard on the continuous metrics and the face counts.
        score_dirichlet, score_complex: weights ``b`` and ``c`` of :func:`quality_score`.
        feature_curve_bound: the feature-curve alignment bound in degrees (above).
        reference_metrics: :func:`frame_metrics` of ``reference_frames`` if already computed.
        repair_rounds: rounds of the singular-structure repair (0: off); a round starts from the
            best candidate at that point and is skipped when it has no complex face or is the
            field the last round started from.
        repair_residual_weight: ``residual_weight`` of :func:`~torchconn.frames.structure.repair_matchings`.
        repair_relax_iters: L-BFGS iterations of each relaxation onto the repaired matchings.
        repair_dirichlet_weights: the Dirichlet weights of the paths from the repaired field
            (``None``: ``dirichlet_weights``).

    Returns:
        ``(frames, info)``; ``info`` has ``"accepted"`` (``"reference"``, ``"start"``, ``"mbo"``,
        ``"repaired"`` or the path kind), ``"accepted_start"`` (the start of the accepted path,
        ``None`` for a start field), ``"dirichlet_weight"`` of the accepted checkpoint (``None`` for a start
        field), ``"score"``, ``"checks"`` (a list of ``(kind, dirichlet_weight, score,
        admissible, violations, start, complex-type singular faces)``), ``"starts_run"`` (the
        starts whose paths ran), ``"mbo_seconds"``, ``"repairs"`` (one dict per repair round:
        ``"round"``, ``"from"`` and ``"from_start"``, the kind and start of the field it repaired,
        ``"complex_before"``, ``"complex_after"``, the ``"passes"`` of
        :func:`~torchconn.frames.structure.repair_structure`, ``"paths_run"``, ``"seconds"``),
        ``"reference"`` (the reference's metrics) and ``"final"`` (the returned field's metrics).
    """
    starts = list(path_starts)
    bad_starts = [s for s in starts if s not in PATH_STARTS]
    if bad_starts or len(set(starts)) != len(starts):
        raise ValueError(f"quality_polish: path_starts must name each of {list(PATH_STARTS)} at most once, "
                         f"got {starts}")
    bad_paths = [k for k in paths if k not in PATH_KINDS]
    if bad_paths:
        raise ValueError(f"quality_polish: unknown path kind(s) {bad_paths}; known: {list(PATH_KINDS)}")
    if not (slack >= 0 and math.isfinite(slack)) or not feature_curve_bound >= 0:
        raise ValueError(f"quality_polish: need slack >= 0 and feature_curve_bound >= 0, got {slack}, "
                         f"{feature_curve_bound}")
    if not (isinstance(repair_rounds, int) and repair_rounds >= 0 and repair_relax_iters >= 1
            and math.isfinite(repair_residual_weight) and repair_residual_weight >= 0):
        raise ValueError(f"quality_polish: need an integer repair_rounds >= 0, repair_relax_iters >= 1 and "
                         f"repair_residual_weight >= 0, got {repair_rounds!r}, {repair_relax_iters!r}, "
                         f"{repair_residual_weight!r}")
    if repair_dirichlet_weights is not None:
        rw = [float(x) for x in repair_dirichlet_weights]
        if not rw or not all(math.isfinite(x) and x >= 0 for x in rw):
            raise ValueError(f"quality_polish: repair_dirichlet_weights must be finite numbers >= 0 (or None), got "
                             f"{repair_dirichlet_weights}")
    if not (score_complex >= 0 and math.isfinite(score_complex)):
        raise ValueError(f"quality_polish: need score_complex >= 0, got {score_complex}")
    dtype = mesh.vertices.dtype
    V = mesh.vertices.shape[0]
    for name, x in (("frames", frames), ("reference_frames", reference_frames)):
        if not torch.is_tensor(x) or tuple(x.shape) != (V, 3, 3):
            raise ValueError(f"quality_polish: {name} must be a ({V}, 3, 3) tensor for this mesh, got "
                             f"{tuple(x.shape) if torch.is_tensor(x) else type(x).__name__}")
    F0 = frames.detach().to(dtype)
    Fr = reference_frames.detach().to(dtype)
    ref = reference_metrics if reference_metrics is not None else frame_metrics(Fr, mesh, angle_deg)
    bounds = {**GUARD_BOUNDS, "feature_curve_alignment_mean_deg": float(feature_curve_bound)}
    checks = []
    cands = [(0.0, ref, Fr, "reference", None, None)]  # admissible: (score, metrics, F, kind, lambda, start)

    def consider(F, kind, lam, start):
        m = frame_metrics(F, mesh, angle_deg, curl=False)
        bad = guard_violations(m, ref, slack, bounds)
        sc = quality_score(m, ref, score_dirichlet, score_complex)
        checks.append((kind, lam, sc, not bad, bad, start, m["n_singular_faces_complex"]))
        if not bad:
            cands.append((sc, m, F, kind, lam, start))
        return m["n_singular_faces_complex"]

    start_fields = {"reference": Fr, "frames": F0}
    complex_of = {"reference": ref["n_singular_faces_complex"], "frames": consider(F0, "start", None, None)}
    mbo_seconds = 0.0
    if "mbo" in starts:
        t0 = time.perf_counter()
        mbo_kw = {"feature_angle_deg": angle_deg, "warm_start": True, **(mbo_options or {})}
        start_fields["mbo"] = mbo_frames(mesh, **mbo_kw).to(dtype)
        mbo_seconds = time.perf_counter() - t0
        complex_of["mbo"] = consider(start_fields["mbo"], "mbo", None, None)
    if conditional_starts:
        starts = [s for s in starts if s == "reference" or complex_of[s] < complex_of["reference"]]
    a_ref = math.radians(ref["smoothness_mean_deg"])

    def run_paths(start_field, label, weights):
        for kind in dict.fromkeys(paths):  # each kind once, in the given order
            for cp in quality_path(mesh, start_field, kind=kind, a_ref=a_ref, d_ref=ref["dirichlet_energy_mean"],
                                   dirichlet_weights=weights, rounds=rounds, iters=iters,
                                   feature_weight=feature_weight, tangent_weight=tangent_weight,
                                   complex_weight=complex_weight, eps=eps, align_eps=align_eps,
                                   angle_deg=angle_deg):
                consider(cp.frames, kind, cp.dirichlet_weight, label)

    for start in starts:
        run_paths(start_fields[start], start, dirichlet_weights)

    def best():
        return cands[choose_candidate([(c[0], c[1]) for c in cands], feature_curve_bound)]

    # singular-structure repair (torchconn.frames.structure): the best candidate's matchings searched
    # for fewer complex faces, the frames relaxed onto them, and the quality paths from there
    repairs = []
    last = None
    rep_weights = dirichlet_weights if repair_dirichlet_weights is None else repair_dirichlet_weights
    for r in range(repair_rounds):
        cur = best()
        if cur[1]["n_singular_faces_complex"] == 0 or cur[2] is last:
            break
        last = cur[2]
        t0 = time.perf_counter()
        Fs, sinfo = repair_structure(cur[2], mesh, a_ref=a_ref, d_ref=ref["dirichlet_energy_mean"],
                                     residual_weight=repair_residual_weight, relax_iters=repair_relax_iters,
                                     dirichlet_weight=max(dirichlet_weights, default=8.0),
                                     feature_weight=feature_weight, eps=eps, align_eps=align_eps, angle_deg=angle_deg)
        entry = {"round": r, "from": cur[3], "from_start": cur[5], "complex_before": sinfo["complex_before"],
                 "complex_after": sinfo["complex_after"], "passes": sinfo["passes"], "paths_run": False}
        repairs.append(entry)
        if sinfo["complex_after"] < sinfo["complex_before"]:  # the paths keep the structure they start from
            label = f"repair{r}" if r else "repair"
            consider(Fs, "repaired", None, label)
            entry["paths_run"] = bool(paths)
            run_paths(Fs, label, rep_weights)
        entry["seconds"] = time.perf_counter() - t0
    score, m, F, kind, lam, start = best()
    return F, {"accepted": kind, "accepted_start": start, "dirichlet_weight": lam, "score": score,
               "checks": checks, "starts_run": starts if paths else [], "mbo_seconds": mbo_seconds,
               "repairs": repairs, "reference": ref, "final": m}


# ----------------------------------------------------------------------------- candidates of the connection method
@dataclass
class Candidate:
    """A field the connection method may return (:func:`connection_candidates`).

    Attributes:
        frames: ``(V, 3, 3)``.
        kind: ``"optimized"`` (the connection optimization's own field), a path kind of
            :data:`~torchconn.frames.refine.PATH_KINDS` (a checkpoint of a quality path from an
            optimized field) or ``"repaired"`` (the singular-structure repair of a candidate).
        start: the start field the connection optimization began from (``"sh"``, ``"mbo"``,
            ``"init"``): every candidate descends from that optimization.
        dirichlet_weight: the path checkpoint's ``lambda`` (``None`` otherwise).
        metrics: :func:`frame_metrics` of ``frames`` (without the curl).
        score: :func:`quality_score` against the reference (the SH field): lower is better.
        edge_rot: ``(E, 3, 3)`` the optimized connection for ``kind == "optimized"``, else ``None``.
    """

    frames: torch.Tensor
    kind: str
    start: str
    dirichlet_weight: float | None
    metrics: dict
    score: float
    edge_rot: torch.Tensor | None = None

    @property
    def label(self) -> str:
        lam = "" if self.dirichlet_weight is None else f"@{self.dirichlet_weight:g}"
        return f"{self.start}/{self.kind}{lam}"

    def summary(self) -> dict:
        """JSON-ready: label, kind, start, lambda, score and the proxies."""
        m = self.metrics
        return {"label": self.label, "kind": self.kind, "start": self.start, "dirichlet_weight": self.dirichlet_weight,
                "score": self.score, "smoothness_mean_deg": m["smoothness_mean_deg"],
                "smoothness_rms_deg": m["smoothness_rms_deg"], "dirichlet_energy_mean": m["dirichlet_energy_mean"],
                "n_singular_faces": m["n_singular_faces"], "n_singular_faces_complex": m["n_singular_faces_complex"],
                "feature_curve_alignment_mean_deg": m["feature_curve_alignment_mean_deg"]}


def connection_candidates(mesh, optimized: dict, reference: dict, *, paths: Sequence[str] = PATH_KINDS,
                          dirichlet_weights: Sequence[float] = DIRICHLET_WEIGHTS, rounds: int = 2, iters: int = 20,
                          feature_weight: float = 1.0, tangent_weight: float = 0.25, complex_weight: float = 0.0,
                          score_dirichlet: float = 1.0, score_complex: float = 0.1, feature_curve_bound: float = 2.0,
                          repair_rounds: int = 1, repair_residual_weight: float = 0.5, repair_relax_iters: int = 40,
                          repair_dirichlet_weights: Sequence[float] | None = (8.0, 2.0, 0.5), eps: float = 1e-3,
                          angle_deg: float = 30.0, align_eps: float = 1e-3) -> tuple[list[Candidate], dict]:
    """The candidates of the connection method: its optimized fields and their polish.

    Every candidate descends from a connection optimization (``optimized``: ``{start label:
    (frames (V, 3, 3), edge_rot (E, 3, 3))}``): the optimized field itself, the checkpoints of the
    quality paths (:func:`~torchconn.frames.refine.quality_path`, ``paths`` x ``dirichlet_weights``)
    started at it, and, where the best candidate by the proxies (:func:`choose_candidate` on
    :func:`quality_score` against ``reference``, the SH field's :func:`frame_metrics`) has
    complex-type singular faces, the singular-structure repair of that candidate
    (:func:`~torchconn.frames.structure.repair_structure`) and the paths from it (``repair_rounds``
    rounds). There is no fallback to the reference: it is the yardstick of the scores only.

    Returns:
        ``(candidates, info)``: :class:`Candidate` list (optimized fields first, in the order of
        ``optimized``) and ``{"repairs": [...], "seconds": ...}``.
    """
    t_start = time.perf_counter()
    bad_paths = [k for k in paths if k not in PATH_KINDS]
    if bad_paths:
        raise ValueError(f"connection_candidates: unknown path kind(s) {bad_paths}; known: {list(PATH_KINDS)}")
    if not optimized:
        raise ValueError("connection_candidates: no optimized field")
    a_ref = math.radians(reference["smoothness_mean_deg"])
    d_ref = reference["dirichlet_energy_mean"]
    cands: list[Candidate] = []

    def consider(F, kind, start, lam, R=None):
        m = frame_metrics(F, mesh, angle_deg, curl=False)
        c = Candidate(F.detach(), kind, start, lam, m, quality_score(m, reference, score_dirichlet, score_complex), R)
        cands.append(c)
        return c

    def run_paths(F, start, weights):
        for kind in dict.fromkeys(paths):
            for cp in quality_path(mesh, F, kind=kind, a_ref=a_ref, d_ref=d_ref, dirichlet_weights=weights,
                                   rounds=rounds, iters=iters, feature_weight=feature_weight,
                                   tangent_weight=tangent_weight, complex_weight=complex_weight, eps=eps,
                                   align_eps=align_eps, angle_deg=angle_deg):
                consider(cp.frames, kind, start, cp.dirichlet_weight)

    for start, (F, R) in optimized.items():
        consider(F.detach(), "optimized", start, None, R.detach() if R is not None else None)
    for start, (F, _) in optimized.items():
        run_paths(F.detach(), start, dirichlet_weights)

    def best():
        return cands[choose_candidate([(c.score, c.metrics) for c in cands], feature_curve_bound)]

    repairs = []
    last = None
    rep_weights = dirichlet_weights if repair_dirichlet_weights is None else repair_dirichlet_weights
    for r in range(repair_rounds):
        cur = best()
        if cur.metrics["n_singular_faces_complex"] == 0 or cur.frames is last:
            break
        last = cur.frames
        t0 = time.perf_counter()
        Fs, sinfo = repair_structure(cur.frames, mesh, a_ref=a_ref, d_ref=d_ref, residual_weight=repair_residual_weight,
                                     relax_iters=repair_relax_iters, dirichlet_weight=max(dirichlet_weights, default=8.0),
                                     feature_weight=feature_weight, eps=eps, align_eps=align_eps, angle_deg=angle_deg)
        entry = {"round": r, "from": cur.label, "complex_before": sinfo["complex_before"],
                 "complex_after": sinfo["complex_after"], "passes": sinfo["passes"], "paths_run": False}
        repairs.append(entry)
        if sinfo["complex_after"] < sinfo["complex_before"]:
            consider(Fs, "repaired", cur.start, None)
            entry["paths_run"] = bool(paths)
            run_paths(Fs, cur.start, rep_weights)
        entry["seconds"] = time.perf_counter() - t0
    return cands, {"repairs": repairs, "seconds": time.perf_counter() - t_start}


def choose_by_proxies(mesh, candidates: Sequence[Candidate], feature_curve_bound: float = 2.0) -> tuple[int, dict]:
    """The default choice among :class:`Candidate` s: :func:`choose_candidate` on their scores."""
    i = choose_candidate([(c.score, c.metrics) for c in candidates], feature_curve_bound)
    return i, {"by": "proxies", "reason": "lowest proxy score (feature-curve bound first)"}
