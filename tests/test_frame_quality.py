"""Frame-field quality against the baseline (issue 13): the quality paths (torchconn.frames.quality_paths), the
candidates of the connection method and their proxy choice (torchconn.frames.candidates), the matched
Dirichlet term, and design()'s use of them."""
from __future__ import annotations

import math

import pytest
import torch

from torchconn import io, so3
from torchconn.frames import frame_metrics, octahedral, sh
from torchconn.frames.design import design
from torchconn.frames.loss import FrameFieldLoss, matched_dirichlet_loss
from torchconn.frames.model import matched_connection
from torchconn.frames.candidates import Candidate, choose_by_proxies, connection_candidates, quality_score


@pytest.fixture(scope="module")
def cyl():
    m = io.cylinder(edge_length=0.6).to(dtype=torch.float64)
    return m, sh.sh_frame_field(m, n_smooth_iters=0)


def _ref() -> dict:
    return {"smoothness_mean_deg": 10.0, "smoothness_rms_deg": 12.0, "dirichlet_energy_mean": 0.1,
            "n_singular_faces": 20, "n_singular_faces_complex": 2, "n_curves_ending_inside": 0,
            "n_tets_one_singular_face": 0, "alignment_mean_deg": 0.0, "feature_curve_alignment_mean_deg": 3.0}


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


def test_choose_by_proxies_puts_the_curve_bound_first():
    fc = "feature_curve_alignment_mean_deg"

    def cands(*pairs):
        return [Candidate(torch.eye(3)[None], "optimized", "sh", None, {fc: v}, score) for score, v in pairs]

    ref = (0.0, 3.5)  # outside the bound (SH misses the tangents)
    assert choose_by_proxies(None, cands(ref)) == (0, {"by": "proxies",
                                                       "reason": "lowest proxy score (feature-curve bound first)"})
    assert choose_by_proxies(None, cands(ref, (-0.1, 3.2)))[0] == 1  # better score, both outside: the score decides
    assert choose_by_proxies(None, cands(ref, (-0.1, 3.2), (0.05, 1.0)))[0] == 2  # within the bound first
    assert choose_by_proxies(None, cands(ref, (0.05, 1.0)), feature_curve_bound=0.5)[0] == 0  # none within: the score
    assert choose_by_proxies(None, cands((0.0, float("nan")), (-0.2, float("nan"))))[0] == 1  # no feature curve
    assert choose_by_proxies(None, cands((0.1, 1.0), (0.1, 1.0)))[0] == 0  # a tie: the first
    with pytest.raises(ValueError, match="no candidate"):
        choose_by_proxies(None, [])


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
    from torchconn.frames.quality_paths import snap_axes

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
    from torchconn.frames.quality_paths import quality_path

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


def test_connection_candidates_from_an_optimized_field(cyl):
    m, F0 = cyl
    ref = frame_metrics(F0, m)
    R0 = matched_connection(F0, m.edges)
    kw = {"dirichlet_weights": (4.0, 1.0), "rounds": 1, "iters": 15}
    cands, info = connection_candidates(m, {"sh": (F0, R0)}, ref, paths=("soft", "tangent"), **kw)
    # the optimized field first (with its connection), then one checkpoint per (path, weight) from it
    assert [(c.kind, c.start, c.dirichlet_weight) for c in cands] == [
        ("optimized", "sh", None), ("soft", "sh", 4.0), ("soft", "sh", 1.0), ("tangent", "sh", 4.0),
        ("tangent", "sh", 1.0)]
    assert [c.label for c in cands[:2]] == ["sh/optimized", "sh/soft@4"]
    assert torch.equal(cands[0].frames, F0) and torch.equal(cands[0].edge_rot, R0)
    assert all(c.edge_rot is None for c in cands[1:])
    assert info["stages"] == ["optimized:sh", "paths"] and info["seconds"] > 0
    for c in cands:
        so3.check_rotation(c.frames)
        assert c.metrics["alignment_max_deg"] < 1e-6  # rotation about the normal only
        # the score: quality_score against the reference with the default weights (1, 0.1)
        assert c.score == pytest.approx(quality_score(c.metrics, ref, 1.0, 0.1), abs=1e-12)
        assert c.metrics["dirichlet_energy_mean"] == pytest.approx(
            frame_metrics(c.frames, m)["dirichlet_energy_mean"], rel=1e-12)
        assert set(c.summary()) >= {"label", "score", "smoothness_mean_deg", "n_singular_faces_complex"}
    assert cands[0].score == pytest.approx(0.0, abs=1e-12)  # the reference's own field
    # this SH field is far from the Dirichlet minimum: a path checkpoint wins the proxies and improves both
    idx, why = choose_by_proxies(m, cands)
    best = cands[idx]
    assert why["by"] == "proxies" and best.kind in ("soft", "tangent") and best.score < 0
    assert best.score == min(c.score for c in cands if not c.metrics["feature_curve_alignment_mean_deg"] > 2.0)
    assert best.metrics["dirichlet_energy_mean"] < ref["dirichlet_energy_mean"]
    assert best.metrics["smoothness_mean_deg"] < ref["smoothness_mean_deg"]
    assert best.metrics["feature_curve_alignment_mean_deg"] <= 2.0
    # the score weights reach the candidates
    c2, _ = connection_candidates(m, {"sh": (F0, R0)}, ref, paths=(), score_dirichlet=0.5, score_complex=0.0)
    assert len(c2) == 1 and c2[0].score == pytest.approx(0.0, abs=1e-12)
    # one path kind only; no path: the optimized field alone
    one, _ = connection_candidates(m, {"sh": (F0, R0)}, ref, paths=("tangent",), **kw)
    assert [c.kind for c in one] == ["optimized", "tangent", "tangent"]
    for kw_bad, msg in [({"paths": ("hard",)}, "path kind"), ({"dirichlet_weights": (1.0, float("nan"))},
                                                             "dirichlet_weights"), ({"iters": 0}, "iters")]:
        with pytest.raises(ValueError, match=msg):
            connection_candidates(m, {"sh": (F0, R0)}, ref, **kw_bad)
    with pytest.raises(ValueError, match="no optimized field"):
        connection_candidates(m, {}, ref)


def test_connection_candidates_paths_start_at_each_optimized_field(cyl):
    m, F0 = cyl
    gen = torch.Generator().manual_seed(2)
    noisy = so3.exp(0.3 * torch.randn(F0.shape[0], 3, generator=gen, dtype=torch.float64)) @ F0
    ref = frame_metrics(F0, m)
    kw = {"paths": ("soft",), "dirichlet_weights": (2.0,), "rounds": 1, "iters": 10}
    both, _ = connection_candidates(m, {"sh": (F0, None), "mbo": (noisy, None)}, ref, **kw)
    # the optimized fields first, in the order given, then the paths of each start
    assert [(c.kind, c.start) for c in both] == [("optimized", "sh"), ("optimized", "mbo"), ("soft", "sh"),
                                                 ("soft", "mbo")]
    assert both[1].edge_rot is None and torch.equal(both[1].frames, noisy)
    alone, _ = connection_candidates(m, {"sh": (F0, None)}, ref, **kw)
    assert torch.equal(both[2].frames, alone[1].frames)  # a path depends on its own start only
    assert both[3].score != pytest.approx(both[2].score, abs=1e-6)  # a path from the noisy field


def test_the_returned_field_is_the_connection_methods(cyl):
    """Every candidate descends from a connection optimization (its start: the SH or the MBO field);
    the SH field is the yardstick of the proxies, never a candidate (issue 23)."""
    m, _ = cyl
    kw = {"sh": {"n_smooth_iters": 5}, "steps": 10, "quality": {"dirichlet_weights": [2.0], "iters": 10},
          "starts": ["sh", "mbo"]}
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
