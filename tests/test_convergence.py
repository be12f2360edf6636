"""The report's convergence claims (Secs. 3.4, 4, 5; docs/conventions.md §3), measured in process.

The full float64 study (4 cases x 13 levels x 11 quantities) is a few hundred tiny cells and
runs in well under a second; every claim is asserted per case:
converging quantities have slope >= 0.9, the naive torsions and BEHS21 slope <= 0.2.
"""
from __future__ import annotations

import math

import pytest
import torch

from training import experiments as E
from training import report_quantities as RQ
from torchconn import so3
from torchconn.dec.smooth import ReportConnection, SmoothConnection, evaluate_2form

CONVERGING = [q for q in E.QUANTITIES if E.CLAIMS[q]]
NOT_CONVERGING = [q for q in E.QUANTITIES if not E.CLAIMS[q]]


@pytest.fixture(scope="module")
def report_study() -> E.StudyResult:
    return E.study(ReportConnection())


def test_claim_table_matches_conventions():
    assert set(NOT_CONVERGING) == {"torsion_naive", "torsion_naive_loop", "ddtheta_behs"}
    assert len(E.TRIANGLE_QUANTITIES) == 8 and len(E.TET_QUANTITIES) == 3


@pytest.mark.parametrize("quantity", CONVERGING)
def test_report_converging_quantities(report_study, quantity):
    slopes = report_study.slopes[quantity]
    assert slopes.shape == (4,)
    for case, s in zip(report_study.cases, slopes.tolist()):
        assert s >= 0.9, f"{quantity} case {case}: slope {s:.3f} < 0.9 (report claims linear convergence)"
    # and the errors really get small (not a spurious slope of a constant-ish curve)
    assert float(report_study.errors[quantity][:, -1].max()) < 5e-3


@pytest.mark.parametrize("quantity", NOT_CONVERGING)
def test_report_non_converging_quantities(report_study, quantity):
    for case, s in zip(report_study.cases, report_study.slopes[quantity].tolist()):
        assert s <= 0.2, f"{quantity} case {case}: slope {s:.3f} > 0.2 (report claims no convergence)"
    assert float(report_study.errors[quantity][:, -1].min()) > 0.5  # an O(1) error that stays


def test_report_study_shapes_and_h(report_study):
    assert report_study.cases == ["A", "B", "C", "D"]
    assert report_study.levels == list(range(13))
    assert torch.equal(report_study.h, torch.tensor([2.0 ** -n for n in range(13)], dtype=torch.float64))
    assert report_study.settings["fit_levels"] == list(range(7, 13))
    assert len(report_study.rows()) == 4 * 11 * 13
    assert all(report_study.verdicts()[q][c] for q in E.QUANTITIES for c in "ABCD")


@pytest.mark.parametrize("variant", [dict(reference_point="centroid"), dict(transport="path_ordered", steps=8)])
def test_variants_keep_conclusions(variant):
    res = E.study(ReportConnection(), **variant)
    for q in E.QUANTITIES:
        for c, s in zip(res.cases, res.slopes[q].tolist()):
            assert (s >= 0.9) if E.CLAIMS[q] else (s <= 0.2), f"{variant}: {q} case {c} slope {s:.3f}"


def test_wave_connection_study_claims():
    """Beyond the report: the same conclusions for a connection with non-polynomial curvature."""
    res = E.study(E.WaveConnection())
    for q in E.QUANTITIES:
        for c, s in zip(res.cases, res.slopes[q].tolist()):
            assert (s >= 0.9) if E.CLAIMS[q] else (s <= 0.2), f"wave: {q} case {c} slope {s:.3f}"


# ----------------------------------------------------------------------------- building blocks
def test_case_cells_follow_conventions():
    tri, tet, h = E.case_cells(["A", "C"], [0, 3, 12])
    assert tri.shape == (2, 3, 3, 3) and tet.shape == (2, 3, 4, 3) and tri.dtype == torch.float64
    assert torch.equal(tri, tet[..., :3, :])
    for ci, case in enumerate(["A", "C"]):
        (a, b, g), v = E.CASES[case]
        R = so3.euler_xyz(torch.tensor(a, dtype=torch.float64), b, g)
        for li, n in enumerate([0, 3, 12]):
            assert torch.allclose(tet[ci, li, 0], torch.tensor(v, dtype=torch.float64), atol=0, rtol=0)
            expect = torch.tensor(v, dtype=torch.float64) + 2.0 ** -n * R.T  # rows R e_k
            assert torch.allclose(tet[ci, li, 1:], expect, rtol=0, atol=1e-15)
    assert torch.equal(h, torch.tensor([1.0, 0.125, 2.0 ** -12], dtype=torch.float64))
    with pytest.raises(ValueError, match="unknown cases"):
        E.case_cells(["E"], 3)


def _explicit_triangle(smooth: SmoothConnection, p: torch.Tensor) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Slow per-triangle reference written out term by term (docs/conventions.md §1, §3)."""
    R = lambda i, j: smooth.midpoint_transport(p[i], p[j])  # noqa: E731
    H = lambda i, j: smooth.half_transport(p[i], p[j])  # noqa: E731
    th = lambda i, j: p[j] - p[i]  # noqa: E731
    tt = lambda i, j: H(i, j) @ th(i, j)  # noqa: E731
    n = torch.linalg.cross(p[1] - p[0], p[2] - p[0])
    area = 0.5 * n.norm()
    N = n / n.norm()
    Th = evaluate_2form(smooth.torsion_form(p[0]), N)
    Om = evaluate_2form(smooth.curvature_form(p[0]), N)
    c = p.mean(0)
    m = lambda i, j: 0.5 * (p[i] + p[j])  # noqa: E731
    I = torch.eye(3, dtype=p.dtype)
    return {
        "torsion_naive": ((th(0, 1) + R(0, 1) @ th(1, 2) - th(0, 2)) / area, Th),
        "torsion_naive_loop": ((th(0, 1) + R(0, 1) @ th(1, 2) + R(0, 1) @ R(1, 2) @ th(2, 0)) / area, Th),
        "torsion_sqrt": ((tt(0, 1) + R(0, 1) @ tt(1, 2) - tt(0, 2)) / area, Th),
        "torsion_sqrt_loop": ((tt(0, 1) + R(0, 1) @ tt(1, 2) + R(0, 1) @ R(1, 2) @ tt(2, 0)) / area, Th),
        "torsion_barycentric": (sum(smooth.midpoint_transport(c, m(i, j)) @ th(i, j)
                                    for i, j in ((0, 1), (1, 2), (2, 0))) / area, Th),
        "curvature_holonomy": ((R(0, 1) @ R(1, 2) @ R(2, 0) - I) / area, Om),
        "curvature_two_prong": ((R(0, 1) @ R(1, 2) - R(0, 2)) / area, Om),
        "curvature_two_prong_cut1": ((R(0, 1) - R(0, 2) @ R(2, 1)) / area, Om),
    }


@pytest.mark.parametrize("smooth", [ReportConnection(), E.WaveConnection()], ids=["report", "wave"])
def test_batched_triangle_quantities_match_explicit_formulas(smooth):
    tri, _, _ = E.case_cells(list(E.CASES), [1, 4])
    got = E.triangle_quantities(smooth, tri)
    for ci in range(4):
        for li in range(2):
            ref = _explicit_triangle(smooth, tri[ci, li])
            for q, (val, smooth_val) in ref.items():
                assert torch.allclose(got[q][0][ci, li], val, rtol=1e-9, atol=1e-9), q
                assert torch.allclose(got[q][1][ci, li], smooth_val, rtol=1e-12, atol=1e-12), q


def test_batched_tet_quantities_match_explicit_formulas():
    smooth = E.WaveConnection()
    _, tet, _ = E.case_cells(list(E.CASES), [2])
    got = E.tet_quantities(smooth, tet)
    for ci in range(4):
        p = tet[ci, 0]
        R = lambda i, j: smooth.midpoint_transport(p[i], p[j])  # noqa: E731
        vol = torch.linalg.det(p[1:] - p[0]) / 6
        ref = smooth.curvature_wedge_solder(p[0])
        # BEHS21 twice (report Ch. 4, erratum 1): (R_ab R_bc - R_ac) θ_cd
        behs = (R(0, 1) @ R(1, 2) - R(0, 2)) @ (p[3] - p[2]) / vol
        assert torch.allclose(got["ddtheta_behs"][0][ci, 0], behs, rtol=1e-9, atol=1e-9)
        # primal-dual (Def. 4.2 twice) written over the oriented boundary faces
        ct = p.mean(0)
        pd = torch.zeros(3, dtype=p.dtype)
        for sign, f in ((1, (1, 2, 3)), (-1, (0, 2, 3)), (1, (0, 1, 3)), (-1, (0, 1, 2))):
            cf = p[list(f)].mean(0)
            face = sum(smooth.midpoint_transport(cf, 0.5 * (p[a] + p[b])) @ (p[b] - p[a])
                       for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])))
            pd = pd + sign * smooth.midpoint_transport(ct, cf) @ face
        assert torch.allclose(got["ddtheta_primal_dual"][0][ci, 0], pd / vol, rtol=1e-9, atol=1e-9)
        for q in E.TET_QUANTITIES:
            assert torch.equal(got[q][1][ci, 0], ref)


def test_averaged_equals_explicit_chapter5_formula():
    """``𝔡∇ Alt 𝔡∇ Alt θ̃`` used by the study equals the end-of-Ch. 5 tetrahedron formula."""
    from torchconn import dnabla

    smooth = E.WaveConnection()
    _, tet, _ = E.case_cells(list(E.CASES), [0, 2])
    got = E.tet_quantities(smooth, tet, ["ddtheta_averaged"])["ddtheta_averaged"][0]
    T = RQ._pair_transports(smooth, tet, "midpoint", 1)
    theta_t = dnabla.solder_form_sqrt(RQ._half_transports(smooth, tet, "midpoint", 1), dnabla.solder_form(tet))
    vol = torch.linalg.det(tet[..., 1:, :] - tet[..., :1, :]) / 6
    explicit = dnabla.wedge_curvature_solder_tet(T, theta_t) / vol[..., None]
    assert torch.allclose(got, explicit, rtol=1e-9, atol=1e-10)


def test_fit_slope_exact_on_power_law():
    h = torch.tensor([2.0 ** -n for n in range(13)], dtype=torch.float64)
    err = torch.stack([3.0 * h ** 1.5, 0.7 * h ** 0.0])
    s = E.fit_slope(h, err, range(7, 13))
    assert torch.allclose(s, torch.tensor([1.5, 0.0], dtype=torch.float64), atol=1e-12)
    with pytest.raises(ValueError, match="at least two levels"):
        E.fit_slope(h, err, [12])


def test_study_falls_back_to_last_levels_when_fit_levels_missing():
    res = E.study(ReportConnection(), cases=["A"], quantities=["curvature_holonomy"], levels=4)
    assert res.settings["fit_levels"] == [0, 1, 2, 3]
    assert res.errors["curvature_holonomy"].shape == (1, 4)


def test_unknown_names_raise():
    with pytest.raises(ValueError, match="unknown quantities"):
        E.convergence_errors(ReportConnection(), ["A"], 2, ["torsion_magic"])
    with pytest.raises(ValueError, match="unknown transport"):
        E.triangle_quantities(ReportConnection(), torch.eye(3, dtype=torch.float64), transport="euler")
    with pytest.raises(ValueError, match="unknown reference_point"):
        E.tet_quantities(ReportConnection(), torch.eye(4, 3, dtype=torch.float64), reference_point="middle")
    with pytest.raises(ValueError, match="unknown connection"):
        E.make_connection("flat")


def test_float32_selectable():
    res = E.study(ReportConnection(), levels=5, dtype=torch.float32)
    ref = E.study(ReportConnection(), levels=5)
    assert res.settings["dtype"] == "float32"
    tri, _, _ = E.case_cells(["A"], 2, dtype=torch.float32)
    assert tri.dtype == torch.float32
    for q in E.QUANTITIES:
        # at coarse levels round-off (~1e-7 / h^2) is far below the discretization error
        assert torch.allclose(res.errors[q], ref.errors[q], rtol=2e-3, atol=1e-4), q


# ----------------------------------------------------------------------------- second connection
def test_wave_connection_closed_forms_match_numeric(gen):
    """Hand-derived Θ, Ω, Ω∧θ of WaveConnection vs the base class's AD-based forms."""
    conn = E.WaveConnection()
    x = 2.0 * torch.randn(64, 3, generator=gen, dtype=torch.float64)
    num_T = SmoothConnection.torsion_form(conn, x)
    num_O = SmoothConnection.curvature_form(conn, x)
    num_W = SmoothConnection.curvature_wedge_solder(conn, x)
    assert torch.allclose(conn.torsion_form(x), num_T, rtol=1e-12, atol=1e-12)
    assert torch.allclose(conn.curvature_form(x), num_O, rtol=1e-10, atol=1e-10)
    assert torch.allclose(conn.curvature_wedge_solder(x), num_W, rtol=1e-10, atol=1e-10)
    # non-constant and non-polynomial: Ω changes between points and is not affine along a line
    O = conn.curvature_form(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]], dtype=torch.float64))
    assert not torch.allclose(O[1] - O[0], O[2] - O[1], atol=1e-3)


def test_wave_connection_curvature_by_finite_differences():
    """Ω(e_b, e_c) = ∂_b ω_c - ∂_c ω_b + [ω_b, ω_c] with central differences, independent of AD."""
    conn = E.WaveConnection()
    x = torch.tensor([[0.3, -1.2, 0.8], [2.3, -0.6, 1.1]], dtype=torch.float64)
    eps = 1e-6
    d = []
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = eps
        d.append((conn.omega(x + e) - conn.omega(x - e)) / (2 * eps))  # (..., 3(b), 3, 3) = ∂_k ω_b
    om = conn.omega(x)
    pairs = ((1, 2), (2, 0), (0, 1))
    fd = torch.stack([d[b][..., c, :, :] - d[c][..., b, :, :] + om[..., b, :, :] @ om[..., c, :, :]
                      - om[..., c, :, :] @ om[..., b, :, :] for b, c in pairs], -1)
    assert torch.allclose(conn.curvature_form(x), fd, atol=1e-8)
    tors = torch.stack([om[..., b, :, c] - om[..., c, :, b] for b, c in pairs], -1)
    assert torch.allclose(conn.torsion_form(x), tors, atol=1e-15)
    assert torch.allclose(conn.omega(x), -conn.omega(x).transpose(-1, -2))


# ----------------------------------------------------------------------------- meshes
def test_mesh_convergence_on_refined_box():
    from torchconn import io

    mesh = io.box(1, size=0.4, origin=(0.6, 0.4, 0.3))
    rows = E.mesh_convergence(ReportConnection(), mesh, 3)
    assert len(rows) == 3 * len(E.MESH_QUANTITIES)
    for q, kind in E.MESH_QUANTITIES:
        rs = [r for r in rows if r["quantity"] == q]
        assert [r["level"] for r in rs] == [0, 1, 2] and all(r["kind"] == kind for r in rs)
        assert rs[1]["cells"] > rs[0]["cells"]
        assert all(math.isfinite(r["mean_error"]) and r["max_error"] >= r["p95_error"] >= 0 for r in rs)
        assert all(r["max_error"] >= r["mean_error"] for r in rs)
        h = torch.tensor([r["h"] for r in rs])
        mean = torch.tensor([r["mean_error"] for r in rs])
        assert float(E.fit_slope(h, mean)) > 0.6, q  # mean per-cell error decreases ~linearly
    assert all(0 < r["min_quality"] <= 1 for r in rows)


def test_shape_quality_is_one_for_regular_cells():
    tri = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0.5, math.sqrt(3) / 2, 0]], dtype=torch.float64)
    tet = torch.tensor([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=torch.float64)
    assert abs(float(E.shape_quality(tri)) - 1) < 1e-12
    assert abs(float(E.shape_quality(tet)) - 1) < 1e-12
