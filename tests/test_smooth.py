"""Tests of torchconn.smooth: transports of smooth connections and the report's Sec. 3.4 example."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchconn import so3, son
from torchconn.dec.smooth import (
    FunctionConnection,
    ReportConnection,
    SmoothConnection,
    evaluate_2form,
    expm_skew,
    unit_normal,
)
from torchconn.tolerances import get_eps

F64 = torch.float64


# ----------------------------------------------------------------------------- test connections
def _nonlinear_omega(x: torch.Tensor) -> torch.Tensor:
    """A non-affine so(3)-valued 1-form whose components do not commute."""
    X, Y, Z = x.unbind(-1)
    w_x = torch.stack((torch.sin(Y), X * Z, 0.3 + 0 * X), -1)
    w_y = torch.stack((X * torch.cos(Z), 0.5 + 0 * X, Y * Y), -1)
    w_z = torch.stack((Z, torch.sin(X + Y), X * Y), -1)
    return so3.hat(torch.stack((w_x, w_y, w_z), -2))


def _rank4_omega(x: torch.Tensor) -> torch.Tensor:
    """A rank-4 connection (so(4), 6 parameters per direction)."""
    X, Y, Z = x.unbind(-1)
    o = torch.ones_like(X)
    p_x = torch.stack((Y, 0.5 * o, -Z, X * Y, 0.2 * o, torch.cos(Z)), -1)
    p_y = torch.stack((o, Z, X, -0.3 * o, Y * Z, 0.1 * o), -1)
    p_z = torch.stack((torch.sin(X), -Y, 0.4 * o, Z, o, X), -1)
    return son.hat(torch.stack((p_x, p_y, p_z), -2), 4)


CONNECTIONS = {
    "report": ReportConnection(),
    "nonlinear": FunctionConnection(_nonlinear_omega, n=3),
    "rank4": FunctionConnection(_rank4_omega, n=4),
}


def _random_segments(gen, N, length=1.0, dtype=F64):
    a = torch.randn(N, 3, generator=gen, dtype=dtype)
    d = torch.randn(N, 3, generator=gen, dtype=dtype)
    b = a + length * d / d.norm(dim=-1, keepdim=True)
    return a, b


# ----------------------------------------------------------------------------- plain references
def rk4_transport(conn: SmoothConnection, a: torch.Tensor, b: torch.Tensor, N: int = 20000) -> torch.Tensor:
    """Classical RK4 on dR/dt = R(t) A(t), A(t) = sum_c (b-a)_c omega_c(a + t(b-a)), R(0) = I.

    Plain fixed-step loop (numpy for speed of the 20000 small steps).
    """
    n = conn.n
    ts = torch.arange(2 * N + 1, dtype=a.dtype) / (2 * N)
    x = a[None] + ts[:, None, None] * (b - a)[None]  # (2N+1, S, 3)
    om = conn.omega(x)  # (2N+1, S, 3, n, n)
    A = ((b - a)[None, :, :, None, None] * om).sum(2).numpy()
    R = np.broadcast_to(np.eye(n), (a.shape[0], n, n)).copy()
    h = 1.0 / N
    for k in range(N):
        A0, Am, A1 = A[2 * k], A[2 * k + 1], A[2 * k + 2]
        k1 = R @ A0
        k2 = (R + 0.5 * h * k1) @ Am
        k3 = (R + 0.5 * h * k2) @ Am
        k4 = (R + h * k3) @ A1
        R = R + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return torch.from_numpy(R)


def fd_curvature(conn: SmoothConnection, x: torch.Tensor, h: float = 1e-4) -> torch.Tensor:
    """Curvature values Omega(e_b, e_c) for (b,c) = (y,z),(z,x),(x,y) by central differences."""
    om = conn.omega(x)

    def d(c):
        e = torch.zeros(3, dtype=x.dtype)
        e[c] = h
        return (conn.omega(x + e) - conn.omega(x - e)) / (2 * h)  # d_c omega_b at [..., b]

    D = [d(c) for c in range(3)]
    out = []
    for b, c in ((1, 2), (2, 0), (0, 1)):
        wb, wc = om[..., b, :, :], om[..., c, :, :]
        out.append(D[b][..., c, :, :] - D[c][..., b, :, :] + wb @ wc - wc @ wb)
    return torch.stack(out, -1)


def _slope(Ls, errs):
    lx = torch.log(torch.tensor(Ls, dtype=F64))
    ly = torch.log(torch.tensor(errs, dtype=F64))
    lx = lx - lx.mean()
    return float((lx * (ly - ly.mean())).sum() / (lx * lx).sum())


# ----------------------------------------------------------------------------- transports
@pytest.mark.parametrize("name", ["report", "nonlinear", "rank4"])
def test_path_ordered_matches_rk4(name, gen):
    conn = CONNECTIONS[name]
    a, b = _random_segments(gen, 4)
    ref = rk4_transport(conn, a, b)
    P = conn.path_ordered_transport(a, b)
    assert P.shape == (4, conn.n, conn.n) and P.dtype == F64
    assert (P - ref).abs().max() < 1e-12
    # the one-point quadrature is a genuinely different (second-order) approximation
    assert (conn.midpoint_transport(a, b) - ref).abs().max() > 1e-4


def test_magnus_is_fourth_order(gen):
    """Error ratio 16 per doubling of steps; a flipped commutator sign would give order 2."""
    conn = CONNECTIONS["nonlinear"]
    a, b = _random_segments(gen, 3)
    ref = conn.path_ordered_transport(a, b, steps=512)
    e = [(conn.path_ordered_transport(a, b, steps=s) - ref).abs().max().item() for s in (8, 16, 32)]
    assert 12 < e[0] / e[1] < 20 and 12 < e[1] / e[2] < 20


@pytest.mark.parametrize("name", ["report", "nonlinear"])
def test_path_ordered_composition(name, gen):
    conn = CONNECTIONS[name]
    a, b = _random_segments(gen, 6)
    s = torch.rand(6, 1, generator=gen, dtype=F64) * 0.8 + 0.1
    m = a + s * (b - a)
    Rab = conn.path_ordered_transport(a, b)
    Ram = conn.path_ordered_transport(a, m)
    Rmb = conn.path_ordered_transport(m, b)
    assert (Rab - Ram @ Rmb).abs().max() < 1e-12
    # reversal: R_ba = R_ab^T
    assert (conn.path_ordered_transport(b, a) - Rab.transpose(-1, -2)).abs().max() < 1e-12
    # the midpoint rule does not compose when the omega_i do not commute (report Sec. 3.4)
    Mab, Mam, Mmb = conn.midpoint_transport(a, b), conn.midpoint_transport(a, m), conn.midpoint_transport(m, b)
    assert (Mab - Mam @ Mmb).abs().max() > 1e-6


@pytest.mark.parametrize("name", ["report", "nonlinear"])
def test_second_order_expansion_residual_is_cubic(name, gen):
    """Report Sec. 3.4: R = I + w L + L^2/2 (w^2 + [w_i, w_j]/6) + O(L^3), w at the midpoint."""
    conn = CONNECTIONS[name]
    x0 = torch.randn(3, generator=gen, dtype=F64)
    d = torch.randn(3, generator=gen, dtype=F64)
    d = d / d.norm()
    eye = torch.eye(3, dtype=F64)
    Ls = [2.0 ** (-k) for k in range(1, 7)]
    res_mid, res_po, po_mid = [], [], []
    for L in Ls:
        a, b = x0 - 0.5 * L * d, x0 + 0.5 * L * d
        M = conn.along(a, b, 0.5 * (a + b))
        Wi, Wj = conn.along(a, b, a), conn.along(a, b, b)
        expansion = eye + M + 0.5 * (M @ M + (Wi @ Wj - Wj @ Wi) / 6.0)
        mid = conn.midpoint_transport(a, b)
        po = conn.path_ordered_transport(a, b)
        res_mid.append((mid - expansion).norm().item())
        res_po.append((po - expansion).norm().item())
        po_mid.append((po - mid).norm().item())
    for errs in (res_mid, res_po, po_mid):
        assert 2.8 < _slope(Ls, errs) < 3.2, errs


def test_midpoint_matches_matrix_exp_and_half_squares(gen):
    for name in ("report", "nonlinear", "rank4"):
        conn = CONNECTIONS[name]
        a, b = _random_segments(gen, 8, length=1.5)
        M = conn.midpoint_integral(a, b)
        R = conn.midpoint_transport(a, b)
        assert (R - torch.linalg.matrix_exp(M)).abs().max() < 1e-12
        H = conn.half_transport(a, b)
        assert (H @ H - R).abs().max() < 1e-12
        assert (conn.transport(a, b) - R).abs().max() == 0
        assert (conn.transport(a, b, method="path_ordered", steps=8)
                - conn.path_ordered_transport(a, b, steps=8)).abs().max() == 0


def test_report_segment_integral(gen):
    rc = ReportConnection()
    a, b = _random_segments(gen, 10, length=2.0)
    S = rc.segment_integral(a, b)
    assert (S - rc.midpoint_integral(a, b)).abs().max() < 1e-13
    # independent check: 3-point Gauss-Legendre is exact for the affine-in-t integrand
    nodes = [(0.5 - math.sqrt(15) / 10, 5 / 18), (0.5, 8 / 18), (0.5 + math.sqrt(15) / 10, 5 / 18)]
    quad = sum(w * rc.along(a, b, a + t * (b - a)) for t, w in nodes)
    assert (S - quad).abs().max() < 1e-13
    # printed closed form of Sec. 3.4 with (a1,b1,c1) = a, (a2,b2,c2) = b
    B = so3.hat(torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    A = so3.hat(torch.tensor([0.0, 1.0, 0.0], dtype=F64))
    cB = -(a[:, 1] + b[:, 1]) * (b[:, 0] - a[:, 0]) / 2 - (b[:, 2] - a[:, 2])
    cA = (a[:, 0] + b[:, 0]) * (b[:, 2] - a[:, 2]) / 2
    assert (S - cB[:, None, None] * B - cA[:, None, None] * A).abs().max() < 1e-13


# ----------------------------------------------------------------------------- smooth invariants
def test_report_closed_forms_match_numeric(gen):
    rc = ReportConnection()
    x = torch.randn(20, 3, generator=gen, dtype=F64) * 2
    assert (rc.torsion_form(x) - SmoothConnection.torsion_form(rc, x)).abs().max() < 1e-10
    assert (rc.curvature_form(x) - SmoothConnection.curvature_form(rc, x)).abs().max() < 1e-10
    assert (rc.curvature_wedge_solder(x) - SmoothConnection.curvature_wedge_solder(rc, x)).abs().max() < 1e-10
    # values printed in the report at one point
    p = torch.tensor([0.5, -2.0, 3.0], dtype=F64)
    assert torch.allclose(rc.curvature_wedge_solder(p), torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    T = rc.torsion_form(p)
    assert torch.allclose(T, torch.tensor([[-1.0, 0.0, -2.0], [0.0, -1.0, 0.0], [0.0, -0.5, 0.0]], dtype=F64))
    C = rc.curvature_form(p)
    assert torch.allclose(C[..., 1], torch.tensor([[0, 0, -1], [0, 0, -1.0], [1, 1.0, 0]], dtype=F64))


def test_numeric_forms_against_plain_formulas(gen):
    """Evaluate the stored forms on arbitrary (u, v) via u x v and compare with the definitions."""
    conn = CONNECTIONS["nonlinear"]
    x = torch.randn(7, 3, generator=gen, dtype=F64)
    u = torch.randn(7, 3, generator=gen, dtype=F64)
    v = torch.randn(7, 3, generator=gen, dtype=F64)
    N = torch.linalg.cross(u, v, dim=-1)
    # torsion (w ^ theta)(u, v) = w(u) v - w(v) u
    wu = torch.einsum("sa,saij->sij", u, conn.omega(x))
    wv = torch.einsum("sa,saij->sij", v, conn.omega(x))
    T_plain = (wu @ v[..., None] - wv @ u[..., None])[..., 0]
    assert (evaluate_2form(conn.torsion_form(x), N) - T_plain).abs().max() < 1e-12
    # curvature against central finite differences
    C = conn.curvature_form(x)
    assert (C - fd_curvature(conn, x)).abs().max() < 1e-7
    assert (C + C.transpose(-2, -3)).abs().max() < 1e-12  # skew values
    # Omega ^ theta from the three components
    W = conn.curvature_wedge_solder(x)
    ex = torch.eye(3, dtype=F64)
    plain = sum(C[..., f] @ ex[k] for f, k in ((0, 0), (1, 1), (2, 2)))
    assert (W - plain).abs().max() < 1e-12
    # rank 4: curvature works, torsion needs the rank-3 solder form
    c4 = CONNECTIONS["rank4"]
    assert (c4.curvature_form(x) - fd_curvature(c4, x)).abs().max() < 1e-7
    with pytest.raises(ValueError, match="rank n = 4"):
        c4.torsion_form(x)


def test_evaluate_2form_and_unit_normal(gen):
    p0, p1, p2 = (torch.randn(5, 3, generator=gen, dtype=F64) for _ in range(3))
    N = unit_normal(p0, p1, p2)
    assert torch.allclose(N.norm(dim=-1), torch.ones(5, dtype=F64))
    assert (N * (p1 - p0)).sum(-1).abs().max() < 1e-12 and (N * (p2 - p0)).sum(-1).abs().max() < 1e-12
    assert (torch.linalg.det(torch.stack((p1 - p0, p2 - p0, N), -2)) > 0).all()
    rc = ReportConnection()
    curv = rc.curvature_form(p0)
    val = evaluate_2form(curv, N)
    assert val.shape == (5, 3, 3)
    ref = curv[..., 0] * N[:, 0, None, None] + curv[..., 1] * N[:, 1, None, None] + curv[..., 2] * N[:, 2, None, None]
    assert (val - ref).abs().max() < 1e-14
    with pytest.raises(ValueError, match=r"degenerate.*\[1\]"):
        unit_normal(p0[:2], torch.stack((p1[0], p0[1] + 1.0)), torch.stack((p2[0], p0[1] + 2.0)))


# ----------------------------------------------------------------------------- dtypes, gradients, errors
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtypes(dtype, gen):
    rc = ReportConnection()
    a64, b64 = _random_segments(gen, 5)
    a, b = a64.to(dtype), b64.to(dtype)
    tol = 50 * get_eps("identity", dtype)
    for method in ("midpoint", "path_ordered"):
        R = rc.transport(a, b, method=method, steps=32)
        assert R.dtype == dtype
        assert (R - rc.transport(a64, b64, method=method, steps=32).to(dtype)).abs().max() < tol
        eye = torch.eye(3, dtype=dtype)
        assert (R.transpose(-1, -2) @ R - eye).abs().max() < tol
    for f in (rc.torsion_form, rc.curvature_form, rc.curvature_wedge_solder, rc.omega):
        assert f(a).dtype == dtype
    assert SmoothConnection.curvature_form(rc, a).dtype == dtype


def test_gradcheck_transports(gen):
    conn = CONNECTIONS["nonlinear"]
    a, b = _random_segments(gen, 2)
    a.requires_grad_(True)
    b.requires_grad_(True)
    assert torch.autograd.gradcheck(conn.midpoint_transport, (a, b))
    assert torch.autograd.gradcheck(conn.half_transport, (a, b))
    assert torch.autograd.gradcheck(lambda p, q: conn.path_ordered_transport(p, q, steps=3), (a, b))
    # zero-length segment: identity with finite gradient
    z = a.detach().clone().requires_grad_(True)
    R = conn.midpoint_transport(z, z.detach())
    assert torch.allclose(R, torch.eye(3, dtype=F64).expand(2, 3, 3))
    R.sum().backward()
    assert torch.isfinite(z.grad).all()


def test_gradcheck_numeric_invariants(gen):
    """The autograd-derived forms stay differentiable in x (create_graph when grad mode is on)."""
    conn = CONNECTIONS["nonlinear"]
    x = torch.randn(1, 3, generator=gen, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(conn.curvature_form, (x,), fast_mode=True)
    assert torch.autograd.gradcheck(conn.curvature_wedge_solder, (x,))
    assert torch.autograd.gradcheck(conn.torsion_form, (x,))
    with torch.no_grad():
        C = conn.curvature_form(x)
    assert not C.requires_grad and (C - conn.curvature_form(x)).abs().max() == 0


def test_errors(gen):
    rc = ReportConnection()
    a, b = _random_segments(gen, 2)
    with pytest.raises(ValueError, match="steps"):
        rc.path_ordered_transport(a, b, steps=0)
    with pytest.raises(ValueError, match="unknown transport method"):
        rc.transport(a, b, method="trapezoid")
    bad = FunctionConnection(lambda x: torch.zeros(*x.shape[:-1], 3, 2, 2, dtype=x.dtype), n=3)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3, 3\)"):
        bad.omega(a)
    with pytest.raises(TypeError, match="must implement omega"):
        SmoothConnection().omega(a)
    with pytest.raises(ValueError, match="square"):
        expm_skew(torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"midpoint_integral expects points of shape \(\.\.\., 3\), got \(2, 2\)"):
        rc.midpoint_transport(a, b[:, :2])
    with pytest.raises(ValueError, match="path_ordered_transport expects points"):
        rc.path_ordered_transport(a[:, :2], b[:, :2])


def test_path_ordered_chunking_matches(gen, monkeypatch):
    """Chunked evaluation of the sub-steps (large batches) gives the same product."""
    import torchconn.dec.smooth as sm

    conn = CONNECTIONS["nonlinear"]
    a, b = _random_segments(gen, 3)
    full = conn.path_ordered_transport(a, b, steps=40)
    monkeypatch.setattr(sm, "_MAGNUS_CHUNK", 3 * 7)  # chunks of 7 sub-steps (uneven split)
    assert (conn.path_ordered_transport(a, b, steps=40) - full).abs().max() < 1e-14
