"""Tests of torchconn.so3: SciPy agreement, singular points, gradients, conventions."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation as Rot
from torch.autograd import gradcheck

from torchconn import so3
from torchconn.tolerances import get_eps

DTYPES = [torch.float32, torch.float64]
# agreement with an independent float64 reference, per dtype of the computation
REF_TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_rotvecs(n: int, seed: int, max_angle: float = math.pi) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axes = _unit(rng.standard_normal((n, 3)))
    return axes * rng.uniform(0.0, max_angle, size=(n, 1))


EDGE_AXES = _unit(
    np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0], [0.3, -0.5, 0.8], [-2.0, 0.1, 0.4]])
)


# ---------------------------------------------------------------- scipy agreement


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_matches_scipy(dtype):
    w = _random_rotvecs(10_000, seed=0)
    R = so3.exp(torch.tensor(w, dtype=dtype))
    assert R.dtype == dtype
    ref = Rot.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(R.double().numpy(), ref, rtol=0, atol=REF_TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_matches_scipy(dtype):
    rots = Rot.random(10_000, random_state=1)
    w = so3.log(torch.tensor(rots.as_matrix(), dtype=dtype))
    assert w.dtype == dtype and w.shape == (10_000, 3)
    np.testing.assert_allclose(w.double().numpy(), rots.as_rotvec(), rtol=0, atol=REF_TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("theta", [0.0, 1e-8, math.pi - 1e-6])
def test_edge_angles_exp_log(dtype, theta):
    w = EDGE_AXES * theta
    ref = Rot.from_rotvec(w).as_matrix()
    R = so3.exp(torch.tensor(w, dtype=dtype))
    np.testing.assert_allclose(R.double().numpy(), ref, rtol=0, atol=REF_TOL[dtype])
    w_back = so3.log(torch.tensor(ref, dtype=dtype))
    np.testing.assert_allclose(w_back.double().numpy(), w, rtol=0, atol=REF_TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_at_pi_axis_up_to_sign(dtype):
    w = EDGE_AXES * math.pi
    R = torch.tensor(Rot.from_rotvec(w).as_matrix(), dtype=dtype)
    out = so3.log(R).double().numpy()
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), math.pi, atol=REF_TOL[dtype])
    sign = np.sign((out * w).sum(-1, keepdims=True))
    assert np.all(sign != 0)
    np.testing.assert_allclose(out * sign, w, rtol=0, atol=REF_TOL[dtype])
    # either sign is a logarithm: exp maps it back to R
    torch.testing.assert_close(so3.exp(torch.tensor(out, dtype=dtype)), R, rtol=0, atol=REF_TOL[dtype])


def test_log_sign_follows_skew_part_near_pi():
    # just below pi the skew part sin(t) n is tiny but fixes the sign of the axis
    w = EDGE_AXES * (math.pi - 1e-9)
    for s in (1.0, -1.0):
        out = so3.log(so3.exp(torch.tensor(s * w)))
        np.testing.assert_allclose(out.numpy(), s * w, atol=1e-8)


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_exp_round_trip(dtype):
    w = torch.tensor(_random_rotvecs(4000, seed=2, max_angle=math.pi - 1e-3), dtype=dtype)
    tol = REF_TOL[dtype]
    torch.testing.assert_close(so3.log(so3.exp(w)), w, rtol=0, atol=tol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_log_round_trip(dtype, gen):
    R = so3.random_rotation(4000, generator=gen, dtype=dtype)
    tol = REF_TOL[dtype]
    torch.testing.assert_close(so3.exp(so3.log(R)), R, rtol=0, atol=tol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sqrt(dtype, gen):
    R = so3.random_rotation(1000, generator=gen, dtype=dtype)
    S = so3.sqrt(R)
    tol = REF_TOL[dtype]
    torch.testing.assert_close(S @ S, R, rtol=0, atol=tol)
    torch.testing.assert_close(so3.angle(S), so3.angle(R) / 2, rtol=0, atol=tol)
    # principal root: same axis, half the rotation vector
    torch.testing.assert_close(so3.log(S), so3.log(R) / 2, rtol=0, atol=tol)


# ---------------------------------------------------------------- gradients


def _rotvec(theta: float, seed: int = 0, n: int = 3) -> torch.Tensor:
    return torch.tensor(_unit(np.random.default_rng(seed).standard_normal((n, 3))) * theta)


@pytest.mark.parametrize("theta", [1e-6, 0.7, 2.5])
def test_gradcheck_exp(theta):
    w = _rotvec(theta).requires_grad_()
    assert gradcheck(so3.exp, (w,))


@pytest.mark.parametrize("fn", [so3.log, so3.sqrt], ids=["log", "sqrt"])
@pytest.mark.parametrize("theta", [1e-6, 0.7, 2.5, math.pi - 1e-3])
def test_gradcheck_log_sqrt(fn, theta):
    R = so3.exp(_rotvec(theta, seed=1)).requires_grad_()
    assert gradcheck(fn, (R,))


def test_gradcheck_random_points(gen):
    R = so3.random_rotation(8, generator=gen, dtype=torch.float64).requires_grad_()
    assert gradcheck(so3.log, (R,))
    assert gradcheck(so3.sqrt, (R,))
    assert gradcheck(so3.angle, (R,))
    R2 = so3.random_rotation(8, generator=gen, dtype=torch.float64).requires_grad_()
    assert gradcheck(so3.geodesic_distance, (R, R2))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("theta", [0.0, math.pi])
def test_finite_gradients_at_singular_points(dtype, theta):
    weights = torch.tensor([1.0, -2.0, 3.0], dtype=dtype)
    w = _rotvec(theta, seed=3, n=4).to(dtype).requires_grad_()
    R = so3.exp(w)
    assert torch.isfinite(R).all()
    (R * torch.arange(9, dtype=dtype).reshape(3, 3)).sum().backward(retain_graph=True)
    assert torch.isfinite(w.grad).all()
    # log on a leaf rotation, and through exp(log)
    Rl = R.detach().requires_grad_()
    out = so3.log(Rl)
    assert torch.isfinite(out).all()
    (out * weights).sum().backward()
    assert torch.isfinite(Rl.grad).all()
    assert Rl.grad.abs().sum() > 0
    w.grad = None
    (so3.log(R) * weights).sum().backward()
    assert torch.isfinite(w.grad).all()
    for f in (so3.sqrt, so3.angle):
        Rf = R.detach().requires_grad_()
        f(Rf).sum().backward()
        assert torch.isfinite(Rf.grad).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_derivatives_at_identity(dtype):
    # d exp at 0 is hat, d log at I is vee: the Taylor branches carry the right first order
    a = torch.tensor([0.3, -1.2, 0.5], dtype=dtype)
    zero = torch.zeros(3, dtype=dtype, requires_grad=True)
    (so3.exp(zero) * so3.hat(a)).sum().backward()
    torch.testing.assert_close(zero.grad, 2 * a)  # <hat(e_i), hat(a)>_F = 2 a_i
    eye = torch.eye(3, dtype=dtype)
    _, jvp = torch.autograd.functional.jvp(so3.log, eye, so3.hat(a))
    torch.testing.assert_close(jvp, a)


# ---------------------------------------------------------------- angle / distance


@pytest.mark.parametrize("dtype", DTYPES)
def test_geodesic_distance_matches_scipy(dtype):
    r1, r2 = Rot.random(2000, random_state=4), Rot.random(2000, random_state=5)
    ref = (r1.inv() * r2).magnitude()
    d = so3.geodesic_distance(torch.tensor(r1.as_matrix(), dtype=dtype), torch.tensor(r2.as_matrix(), dtype=dtype))
    np.testing.assert_allclose(d.double().numpy(), ref, rtol=0, atol=REF_TOL[dtype])
    a = so3.angle(torch.tensor(r1.as_matrix(), dtype=dtype))
    np.testing.assert_allclose(a.double().numpy(), r1.magnitude(), rtol=0, atol=REF_TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_angle_edge_values(dtype):
    for theta in (0.0, 1e-8, math.pi - 1e-6, math.pi):
        R = torch.tensor(Rot.from_rotvec(EDGE_AXES * theta).as_matrix(), dtype=dtype)
        np.testing.assert_allclose(so3.angle(R).double().numpy(), theta, rtol=0, atol=REF_TOL[dtype])


# ---------------------------------------------------------------- Euler angles


def _rx(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# the four parameter sets of docs/conventions.md §3
EULER_CASES = [(1.3, 1.1, -1.6), (1.7, 2.1, -2.6), (2.3, -1.1, 2.0), (-2.2, 2.1, 1.7)]


@pytest.mark.parametrize("abc", EULER_CASES)
def test_euler_xyz_explicit_and_scipy_intrinsic(abc):
    a, b, c = abc
    R = so3.euler_xyz(a, b, c)
    assert R.dtype == torch.get_default_dtype()
    expected = _rx(a) @ _ry(b) @ _rz(c)
    np.testing.assert_allclose(R.double().numpy(), expected, atol=1e-6)
    R64 = so3.euler_xyz(torch.tensor(a, dtype=torch.float64), b, c)
    np.testing.assert_allclose(R64.numpy(), expected, atol=1e-14)
    # Rx Ry Rz is SciPy's *intrinsic* "XYZ", not the extrinsic "xyz"
    np.testing.assert_allclose(R64.numpy(), Rot.from_euler("XYZ", abc).as_matrix(), atol=1e-14)
    assert np.abs(R64.numpy() - Rot.from_euler("xyz", abc).as_matrix()).max() > 1e-2
    np.testing.assert_allclose(so3.rot_x(torch.tensor(a, dtype=torch.float64)).numpy(), _rx(a), atol=1e-15)
    np.testing.assert_allclose(so3.rot_y(torch.tensor(b, dtype=torch.float64)).numpy(), _ry(b), atol=1e-15)
    np.testing.assert_allclose(so3.rot_z(torch.tensor(c, dtype=torch.float64)).numpy(), _rz(c), atol=1e-15)


def test_axis_rotations_match_exp():
    t = torch.linspace(-3.0, 3.0, 7, dtype=torch.float64)
    e = torch.eye(3, dtype=torch.float64)
    for f, axis in ((so3.rot_x, e[0]), (so3.rot_y, e[1]), (so3.rot_z, e[2])):
        torch.testing.assert_close(f(t), so3.exp(t[:, None] * axis))


def test_euler_xyz_broadcasts():
    a = torch.linspace(0, 1, 5, dtype=torch.float64)
    g = torch.tensor([[0.1], [0.2]], dtype=torch.float64)
    R = so3.euler_xyz(a, 0.4, g)
    assert R.shape == (2, 5, 3, 3) and R.dtype == torch.float64
    np.testing.assert_allclose(R[1, 3].numpy(), _rx(a[3].item()) @ _ry(0.4) @ _rz(0.2), atol=1e-14)
    # dtypes promote; integer angles become the default float dtype
    R = so3.euler_xyz(torch.tensor(0.1, dtype=torch.float32), torch.tensor([0.2], dtype=torch.float64), 0)
    assert R.dtype == torch.float64 and R.shape == (1, 3, 3)
    assert so3.rot_z(torch.tensor(1)).dtype == torch.get_default_dtype()


def test_gradcheck_euler_xyz():
    angles = [torch.tensor([0.3, -2.0], dtype=torch.float64, requires_grad=True) for _ in range(3)]
    assert gradcheck(so3.euler_xyz, tuple(angles))


# ---------------------------------------------------------------- validation / projection


def test_check_rotation_accepts_rotations(gen):
    so3.check_rotation(so3.random_rotation(10, 4, generator=gen, dtype=torch.float64))
    so3.check_rotation(so3.random_rotation(10, generator=gen, dtype=torch.float32))
    so3.check_rotation(torch.eye(3))


def test_check_rotation_reports_defect_and_index(gen):
    R = so3.random_rotation(4, 5, generator=gen, dtype=torch.float64)
    bad = R.clone()
    bad[2, 3] = bad[2, 3] * 1.01
    with pytest.raises(ValueError, match=r"edge_rot.*not orthogonal at index \(2, 3\)"):
        so3.check_rotation(bad, name="edge_rot")
    bad = R.clone()
    bad[1, 4, :, 0] *= -1
    with pytest.raises(ValueError, match=r"det = -1\.0+ .*at index \(1, 4\)"):
        so3.check_rotation(bad)
    bad = R.clone()
    bad[0, 2, 1, 1] = float("nan")
    bad[3, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"NaN/inf\) at index \(0, 2\)"):
        so3.check_rotation(bad)
    with pytest.raises(ValueError, match="shape"):
        so3.check_rotation(torch.eye(4))


@pytest.mark.parametrize("dtype", DTYPES)
def test_check_rotation_default_tolerance(dtype, gen):
    R = so3.random_rotation(3, generator=gen, dtype=dtype)
    atol = get_eps("rotation", dtype)
    # ||s R^T s R - I||_F = sqrt(3) |s^2 - 1| ~ 2 sqrt(3) (s - 1)
    so3.check_rotation(R * (1 + 0.1 * atol))
    with pytest.raises(ValueError, match=r"not orthogonal at index \(0,\)"):
        so3.check_rotation(R * (1 + 2 * atol))
    so3.check_rotation(R * (1 + 2 * atol), atol=10 * atol)


def test_project_to_rotation(gen):
    U = so3.random_rotation(20, generator=gen, dtype=torch.float64)
    V = so3.random_rotation(20, generator=gen, dtype=torch.float64)
    # M = U diag(3, 2, -1) V^T has det < 0; the nearest rotation is U V^T (max tr(Q^T diag))
    M = U @ torch.diag(torch.tensor([3.0, 2.0, -1.0], dtype=torch.float64)) @ V.transpose(-1, -2)
    P = so3.project_to_rotation(M)
    so3.check_rotation(P)
    torch.testing.assert_close(P, U @ V.transpose(-1, -2))
    # a rotation times an SPD factor projects to the rotation (polar factor)
    S = torch.diag(torch.tensor([1.5, 0.7, 0.2], dtype=torch.float64))
    torch.testing.assert_close(so3.project_to_rotation(U @ V @ S @ V.transpose(-1, -2)), U)
    Mg = M[:3].clone().requires_grad_()
    assert gradcheck(so3.project_to_rotation, (Mg,))


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        so3.hat(torch.zeros(4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        so3.log(torch.zeros(2, 2))


def test_no_hard_coded_device():
    # on the meta device any constant created on the CPU would raise a device mismatch
    m = torch.zeros(5, 3, 3, device="meta")
    for out in (so3.exp(torch.zeros(5, 3, device="meta")), so3.log(m), so3.sqrt(m), so3.angle(m),
                so3.geodesic_distance(m, m), so3.project_to_rotation(m),
                so3.euler_xyz(torch.zeros(5, device="meta"), 0.1, 0.2), so3.random_rotation(5, device="meta")):
        assert out.device.type == "meta"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu(gen):
    R = so3.random_rotation(100, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(so3.log(R.cuda()).cpu(), so3.log(R))
    torch.testing.assert_close(so3.sqrt(R.cuda()).cpu(), so3.sqrt(R))
    so3.check_rotation(R.cuda())
