"""Frame-field quality against the baseline (issue 13): the quality paths (torchconn.frames.refine), the
guarded quality stage, its guard, the matched Dirichlet term, and design()'s use of them."""
from __future__ import annotations

import math

import pytest
import torch

from torchconn import io, so3
from torchconn.frames import frame_metrics, octahedral, sh
from torchconn.frames.design import design
from torchconn.frames.loss import FrameFieldLoss, matched_dirichlet_loss
from torchconn.frames.model import matched_connection
from torchconn.frames.polish import (GUARD_CONTINUOUS, GUARD_COUNTS, GUARD_STRICT, guard_violations, quality_polish,
                                     quality_score)


@pytest.fixture(scope="module")
def cyl():
    m = io.cylinder(edge_length=0.6).to(dtype=torch.float64)
    return m, sh.sh_frame_field(m, n_smooth_iters=0)


def _ref() -> dict:
    return {"smoothness_mean_deg": 10.0, "smoothness_rms_deg": 12.0, "dirichlet_energy_mean": 0.1,
            "n_singular_faces": 20, "n_singular_faces_complex": 2, "n_curves_ending_inside": 0,
            "n_tets_one_singular_face": 0, "alignment_mean_deg": 0.0, "feature_curve_alignment_mean_deg": 3.0}


def test_guard_names_every_worse_metric():
    ref = _ref()
    assert guard_violations(ref, ref) == []
    for k in GUARD_CONTINUOUS:
        m = {**ref, k: ref[k] * 1.005}
        assert guard_violations(m, ref) == [k]
        assert guard_violations(m, ref, slack=0.01) == []  # within the slack
        assert guard_violations({**ref, k: float("nan")}, ref) == [k]
    for k in GUARD_COUNTS:  # face counts: "no more than 1% worse" with slack = 0.01
        assert guard_violations({**ref, k: ref[k] + 1}, ref) == [k]
        assert guard_violations({**ref, k: ref[k] + 1}, ref, slack=0.5) == []
        assert guard_violations({**ref, k: ref[k] * 2}, ref, slack=0.5) == [k]
    for k in GUARD_STRICT:  # defects of the singular graph take no slack
        assert guard_violations({**ref, k: ref[k] + 1}, ref, slack=0.5) == [k]
    # bounds: max(reference, floor)
    assert guard_violations({**ref, "alignment_mean_deg": 0.4}, ref) == []
    assert guard_violations({**ref, "alignment_mean_deg": 0.6}, ref) == ["alignment_mean_deg"]
    fc = "feature_curve_alignment_mean_deg"
    assert guard_violations({**ref, fc: 2.9}, ref) == []
    assert guard_violations({**ref, fc: 3.1}, ref) == [fc]
    low = {**ref, fc: 0.5}
    assert guard_violations({**low, fc: 1.9}, low) == []  # the 2-degree bound
    assert guard_violations({**low, fc: 2.1}, low) == [fc]
    assert guard_violations({**low, fc: 0.6}, low, bounds={fc: 0.0}) == [fc]  # held at the reference's
    nofc = {**ref, fc: float("nan")}
    assert guard_violations(nofc, nofc) == []
    assert guard_violations({**nofc, fc: 2.5}, nofc) == [fc]


def test_quality_score():
    ref = _ref()
    assert quality_score(ref, ref) == 0.0
    m = {**ref, "smoothness_mean_deg": 9.0, "dirichlet_energy_mean": 0.11}
    assert quality_score(m, ref) == pytest.approx(math.log(0.9) + math.log(1.1))
    assert quality_score(m, ref, 0.5) == pytest.approx(math.log(0.9) + 0.5 * math.log(1.1))
    # the complex-face term: c log((n + 1) / (n_ref + 1)), 0 when c = 0
    mc = {**m, "n_singular_faces_complex": ref["n_singular_faces_complex"] + 3}
    assert quality_score(mc, ref, 1.0, 0.0) == pytest.approx(quality_score(m, ref))
    n0 = ref["n_singular_faces_complex"]
    assert quality_score(mc, ref, 1.0, 0.1) == pytest.approx(quality_score(m, ref) + 0.1 * math.log((n0 + 4) / (n0 + 1)))


def test_choose_candidate_puts_the_curve_bound_first():
    from torchconn.frames.polish import choose_candidate

    fc = "feature_curve_alignment_mean_deg"
    ref = (0.0, {fc: 3.5})  # the reference outside the bound (SH misses the tangents)
    assert choose_candidate([ref]) == 0
    assert choose_candidate([ref, (-0.1, {fc: 3.2})]) == 1  # better score, both outside: the score decides
    assert choose_candidate([ref, (-0.1, {fc: 3.2}), (0.05, {fc: 1.0})]) == 2  # within the bound first
    assert choose_candidate([ref, (0.05, {fc: 1.0})], feature_curve_bound=0.5) == 0  # none within: the score
    nofc = (0.0, {fc: float("nan")})
    assert choose_candidate([nofc, (-0.2, {fc: float("nan")})]) == 1
    with pytest.raises(ValueError, match="no candidate"):
        choose_candidate([])


def test_matched_dirichlet_loss_is_the_metric_and_differentiable(cyl):
    m, F0 = cyl
    assert float(matched_dirichlet_loss(F0, m.edges)) == pytest.approx(
        frame_metrics(F0, m)["dirichlet_energy_mean"], rel=1e-12)
    # slow per-edge reference: min over the 24 elements
    G = octahedral.group(torch.float64)
    e = m.edges[:50]
    ref = torch.stack([min(float(((F0[i] @ g - F0[j]) ** 2).sum()) for g in G) * torch.ones((), dtype=torch.float64)
                       for i, j in e.tolist()]).mean()
    assert float(matched_dirichlet_loss(F0, e)) == pytest.approx(float(ref), rel=1e-10)
    assert float(matched_dirichlet_loss(F0, e[:0])) == 0.0
    # gradcheck / gradgradcheck through the frames (the matching is piecewise constant)
    gen = torch.Generator().manual_seed(0)
    F = so3.exp(0.1 * torch.randn(12, 3, generator=gen, dtype=torch.float64)) @ F0[:12]
    edges = torch.tensor([[0, 1], [1, 2], [2, 5], [3, 7], [4, 11]])

    def fn(w):
        return matched_dirichlet_loss(so3.exp(w) @ F, edges)

    w = (1e-3 * torch.randn(12, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(fn, (w,))
    assert torch.autograd.gradgradcheck(fn, (w,))


def test_loss_dirichlet_term(cyl):
    m, F0 = cyl
    R = matched_connection(F0, m.edges)
    loss = FrameFieldLoss(m, {"dirichlet": 2.0, "align": 1.0})
    out = loss(R, F0)
    assert float(out["dirichlet"]) == pytest.approx(frame_metrics(F0, m)["dirichlet_energy_mean"], rel=1e-12)
    assert float(out["total"]) == pytest.approx(2.0 * float(out["dirichlet"]) + float(out["align"]), rel=1e-12)
    assert "dirichlet" not in FrameFieldLoss(m, {"align": 1.0})(R, F0)


def test_snap_axes_puts_the_closest_axis_on_the_direction():
    from torchconn.frames.metrics import axis_alignment_angle
    from torchconn.frames.refine import snap_axes

    gen = torch.Generator().manual_seed(3)
    F = so3.random_rotation(50, generator=gen, dtype=torch.float64)
    t = torch.nn.functional.normalize(torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=-1)
    S = snap_axes(F, t)
    so3.check_rotation(S)
    assert float(axis_alignment_angle(S, t).max()) < 1e-12
    # the minimal rotation: its angle is the misalignment it removes
    turn = so3.geodesic_distance(S, F)
    assert torch.allclose(turn, axis_alignment_angle(F, t), atol=1e-12)


def test_quality_path_constraints(cyl):
    from torchconn.frames.constraints import BoundaryConstraint
    from torchconn.frames.metrics import axis_alignment_angle
    from torchconn.frames.refine import quality_path

    m, F0 = cyl
    ref = frame_metrics(F0, m)
    kw = {"a_ref": math.radians(ref["smoothness_mean_deg"]), "d_ref": ref["dirichlet_energy_mean"],
          "dirichlet_weights": (4.0, 1.0), "rounds": 1, "iters": 15}
    bc = BoundaryConstraint.from_mesh(m)
    inner = ~bc.tangent_at_corner
    tv, td = bc.tangent_vertices[inner], bc.tangent_dirs[inner]
    assert tv.numel() > 0  # the rims are feature curves
    for kind in ("soft", "tangent"):
        cps = quality_path(m, F0, kind=kind, **kw)
        assert [c.dirichlet_weight for c in cps] == [4.0, 1.0] and all(c.kind == kind for c in cps)
        for c in cps:
            so3.check_rotation(c.frames)
            after = frame_metrics(c.frames, m)
            assert after["alignment_max_deg"] < 1e-6  # rotation about the normal only
        # this SH field (no nonlinear smoothing) is far from the Dirichlet minimum
        assert frame_metrics(cps[0].frames, m)["dirichlet_energy_mean"] < ref["dirichlet_energy_mean"]
    # the tangent path holds the curve tangents exactly away from singular faces
    F = quality_path(m, F0, kind="tangent", **kw)[-1].frames
    mask, _ = octahedral.singular_faces(F, m)
    on_sing = torch.zeros(F.shape[0], dtype=torch.bool)
    on_sing[m.faces[mask].reshape(-1)] = True
    held = ~on_sing[tv]
    assert held.any()
    assert float(axis_alignment_angle(F[tv[held]], td[held]).max()) < 1e-9
    for bad, msg in [({"kind": "hard"}, "kind"), ({"rounds": 0}, "rounds"),
                     ({"dirichlet_weights": (1.0, float("nan"))}, "dirichlet_weights")]:
        with pytest.raises(ValueError, match=msg):
            quality_path(m, F0, **{**kw, **bad})


def test_quality_polish_never_worse_than_the_reference(cyl):
    m, F0 = cyl
    ref = frame_metrics(F0, m)
    kw = {"dirichlet_weights": (4.0, 1.0), "rounds": 1, "iters": 15, "path_starts": ("reference",)}
    F, info = quality_polish(m, F0, F0, **kw)
    so3.check_rotation(F)
    after = frame_metrics(F, m)
    assert guard_violations(after, ref, slack=0.01) == []
    assert info["accepted"] in ("reference", "start", "soft", "tangent")
    assert len(info["checks"]) == 1 + 2 * 2  # the start + one checkpoint per (path, weight)
    assert {c[5] for c in info["checks"][1:]} == {"reference"} and info["mbo_seconds"] == 0.0
    # the returned field is the best-scored admissible candidate within the curve bound
    ok = [c for c in info["checks"] if c[3]]
    assert info["score"] == pytest.approx(min([0.0] + [c[2] for c in ok]), abs=1e-12)
    assert quality_score(after, ref) == pytest.approx(info["score"], abs=1e-9)
    # this SH field is far from the Dirichlet minimum: a path checkpoint wins and improves both
    assert info["accepted"] in ("soft", "tangent") and info["dirichlet_weight"] in (4.0, 1.0)
    assert after["dirichlet_energy_mean"] < ref["dirichlet_energy_mean"]
    assert after["smoothness_mean_deg"] < ref["smoothness_mean_deg"]
    assert after["alignment_max_deg"] < 1e-6
    assert after["feature_curve_alignment_mean_deg"] <= 2.0
    # one path only
    _, one = quality_polish(m, F0, F0, paths=("tangent",), **kw)
    assert {c[0] for c in one["checks"]} == {"start", "tangent"}


def test_quality_polish_paths_start_at_the_reference(cyl):
    m, F0 = cyl
    gen = torch.Generator().manual_seed(2)
    noisy = so3.exp(0.3 * torch.randn(F0.shape[0], 3, generator=gen, dtype=torch.float64)) @ F0
    kw = {"paths": ("soft",), "dirichlet_weights": (2.0,), "rounds": 1, "iters": 10, "path_starts": ("reference",)}
    # the paths start at the reference whatever the candidate; the candidate is scored as "start"
    a, ia = quality_polish(m, noisy, F0, **kw)
    b, ib = quality_polish(m, F0, F0, **kw)
    assert [c[2] for c in ia["checks"][1:]] == pytest.approx([c[2] for c in ib["checks"][1:]], abs=1e-12)
    assert ia["checks"][0][0] == "start" and ia["checks"][0][3] is False  # the noisy candidate fails the guard
    assert torch.allclose(a, b)
    _, ic = quality_polish(m, noisy, F0, **{**kw, "path_starts": ("frames",), "conditional_starts": False})
    assert ic["checks"][1][2] != pytest.approx(ib["checks"][1][2], abs=1e-6)  # a path from the noisy field


def test_quality_polish_paths_from_the_mbo_field(cyl):
    m, F0 = cyl
    from torchconn.frames.mbo import mbo_frames
    kw = {"paths": ("soft",), "dirichlet_weights": (2.0,), "rounds": 1, "iters": 10}
    F, info = quality_polish(m, F0, F0, path_starts=("reference", "mbo"), score_complex=0.1,
                             conditional_starts=False, **kw)
    ref = frame_metrics(F0, m)
    # the start, the MBO field (a candidate of its own), then one path per start
    assert [(c[0], c[5]) for c in info["checks"]] == [("start", None), ("mbo", None), ("soft", "reference"),
                                                      ("soft", "mbo")]
    assert info["mbo_seconds"] > 0
    assert guard_violations(frame_metrics(F, m), ref, slack=0.01) == []
    # the MBO candidate is the MBO method's field (warm-started projections), scored against the reference
    mm = frame_metrics(mbo_frames(m, warm_start=True), m)
    assert info["checks"][1][2] == pytest.approx(quality_score(mm, ref, 1.0, 0.1), abs=1e-9)
    # the path from the MBO field is a different field from the path from the reference
    assert info["checks"][3][2] != pytest.approx(info["checks"][2][2], abs=1e-6)
    # conditional starts: the MBO paths run only where the MBO field has fewer complex faces
    _, ic = quality_polish(m, F0, F0, path_starts=("reference", "mbo"), score_complex=0.1,
                           conditional_starts=True, **kw)
    fewer = mm["n_singular_faces_complex"] < ref["n_singular_faces_complex"]
    assert ic["starts_run"] == (["reference", "mbo"] if fewer else ["reference"])
    assert [c[5] for c in ic["checks"][2:]] == ic["starts_run"]
    assert info["starts_run"] == ["reference", "mbo"]
    # both branches: against a noisy reference (many complex faces) the MBO field has fewer
    gen = torch.Generator().manual_seed(5)
    noisy = so3.exp(0.8 * torch.randn(F0.shape[0], 3, generator=gen, dtype=torch.float64)) @ F0
    assert frame_metrics(noisy, m)["n_singular_faces_complex"] > mm["n_singular_faces_complex"]
    _, inoisy = quality_polish(m, F0, noisy, path_starts=("reference", "mbo"), score_complex=0.1,
                               conditional_starts=True, paths=())
    assert inoisy["starts_run"] == [] and inoisy["accepted"] in ("start", "mbo")
    _, inoisy = quality_polish(m, F0, noisy, path_starts=("reference", "mbo"), score_complex=0.1,
                               conditional_starts=True, **{**kw, "dirichlet_weights": (8.0,), "iters": 2})
    assert inoisy["starts_run"] == ["reference", "mbo"]
    # mbo_options reach mbo_frames
    _, i2 = quality_polish(m, F0, F0, path_starts=("mbo",), paths=(), mbo_options={"n_taus": 0}, score_complex=0.1)
    mm0 = frame_metrics(mbo_frames(m, n_taus=0), m)
    assert i2["checks"][1][2] == pytest.approx(quality_score(mm0, ref, 1.0, 0.1), abs=1e-9)


def test_quality_polish_falls_back_to_the_reference(cyl):
    m, F0 = cyl
    gen = torch.Generator().manual_seed(1)
    noisy = so3.exp(torch.randn(F0.shape[0], 3, generator=gen, dtype=torch.float64)) @ F0  # a bad start
    F, info = quality_polish(m, noisy, F0, paths=(), path_starts=("reference",))
    assert info["accepted"] == "reference" and info["dirichlet_weight"] is None and torch.equal(F, F0)
    assert info["checks"][0][3] is False and info["checks"][0][4]  # the start fails, naming metrics
    F, info = quality_polish(m, F0, F0, paths=(), path_starts=("reference",))
    assert torch.equal(F, F0)  # the start equals the reference: score 0, the reference is kept
    for kw, msg in [({"paths": ("hard",)}, "path kind"), ({"slack": -0.1}, "slack"),
                    ({"feature_curve_bound": -1.0}, "feature_curve_bound"),
                    ({"dirichlet_weights": (1.0, float("nan"))}, "dirichlet_weights"),
                    ({"iters": 0}, "iters"), ({"path_starts": ("middle",)}, "path_starts"),
                    ({"path_starts": ("mbo", "mbo")}, "path_starts"), ({"score_complex": -1.0}, "score_complex")]:
        with pytest.raises(ValueError, match=msg):
            quality_polish(m, F0, F0, **kw)
    with pytest.raises(ValueError, match="reference_frames"):
        quality_polish(m, F0, F0[:-1])


def test_the_returned_field_is_the_connection_methods(cyl):
    """Every candidate descends from a connection optimization (its start: the SH or the MBO field);
    the SH field is the yardstick of the proxies, never a candidate (issue 23)."""
    m, _ = cyl
    kw = {"sh": {"n_smooth_iters": 5}, "steps": 10, "quality": {"dirichlet_weights": [2.0], "iters": 10}}
    r = design(m, **kw)
    c = r.metrics["chosen"]
    assert c["by"] == "proxies" and c["start"] in ("sh", "mbo") and r.timings["quality_s"] > 0
    kinds = {x["kind"] for x in c["candidates"]}
    assert kinds <= {"optimized", "soft", "tangent", "repaired"} and "optimized" in kinds
    assert {x["start"] for x in c["candidates"]} == {"sh", "mbo"}
    sh = design(m, "sh", sh=kw["sh"]).vertex_frames
    assert not torch.equal(r.vertex_frames, sh)
    off = design(m, **{**kw, "quality": {"enabled": False}})
    assert [x["kind"] for x in off.metrics["chosen"]["candidates"]] == ["optimized", "optimized"]
    with pytest.raises(TypeError, match="quality.bogus"):
        design(m, quality={"bogus": 1})
    with pytest.raises(ValueError, match="starts"):
        design(m, starts=["sh", "sh"])


def _same_field(F1, F2, tol=1e-9) -> bool:
    """Equal as cross fields: every vertex frame equal up to an element of O."""
    idx, g = octahedral.match(F1, F2)
    return bool(((F1 @ g - F2).abs().amax() <= tol))


def test_a_sweep_over_a_loss_weight_changes_the_field(cyl):
    """Hydra sweeps such as -m weights.flat=0.0,0.1 must give different fields: the returned field
    comes out of the optimization those weights drive."""
    m, _ = cyl
    kw = {"sh": {"n_smooth_iters": 5}, "steps": 15, "starts": ["sh"], "quality": {"enabled": False}}
    a = design(m, **kw, weights={"flat": 0.0})
    b = design(m, **kw, weights={"flat": 0.1})
    assert not _same_field(a.vertex_frames, b.vertex_frames)
    assert a.metrics["final"] != b.metrics["final"]
