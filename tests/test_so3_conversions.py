"""so3 quaternion (wxyz and xyzw) and 6D conversions: scipy, round trips, the singular points.

Invariants mirrored here (torchconn.lie.so3 docstrings):

* ``quat_to_matrix(q, convention=c)`` equals scipy's ``Rotation.from_quat(q, scalar_first=(c ==
  "wxyz")).as_matrix()`` for any nonzero scale of ``q``;
* ``matrix_to_quat(R, convention=c)`` equals scipy's ``as_quat(canonical=True, scalar_first=...)``
  (``w >= 0``), up to sign where ``w = 0`` (angle pi), and matches ``exp``'s axis-angle;
* ``rot6d_to_matrix`` is Gram-Schmidt on the two columns (a QR reference per element) and
  inverts ``matrix_to_rot6d`` on rotations;
* values and gradients are finite at the identity and at angle pi (backpropagating through
  the function under test), and ``gradcheck`` passes there and at generic points.

Cost: well under a second (a few hundred 3x3 matrices).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchconn import so3

CONVENTIONS = ["wxyz", "xyzw"]


def _scalar_first(convention):
    return convention == "wxyz"


def _special_rotvecs(dtype=torch.float64):
    """Rotation vectors at the singular points: identity, tiny angles, pi about coordinate and
    diagonal axes, and just below pi."""
    axes = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1], [-1, 2, 0.5]], dtype=dtype)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    return torch.cat([
        torch.zeros(1, 3, dtype=dtype),
        1e-9 * axes,
        math.pi * axes,
        (math.pi - 1e-7) * axes,
    ])


def _rotations(gen, n=200):
    return torch.cat([so3.random_rotation(n, generator=gen, dtype=torch.float64), so3.exp(_special_rotvecs())])


# ----------------------------------------------------------------------------- scipy
@pytest.mark.parametrize("convention", CONVENTIONS)
def test_matrix_to_quat_matches_scipy(gen, convention):
    R = _rotations(gen)
    q = so3.matrix_to_quat(R, convention=convention)
    ref = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_quat(canonical=True,
                                                                   scalar_first=_scalar_first(convention)))
    w = q[..., 0] if convention == "wxyz" else q[..., 3]
    assert bool((w >= 0).all())
    # at w = 0 (angle pi) the canonical signs of the two libraries may differ (docstring): compare up to sign there
    sign = torch.where((q * ref).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q.dtype)
    assert bool((sign > 0)[w.abs() > 1e-6].all())
    torch.testing.assert_close(q * sign, ref, rtol=0, atol=1e-14)


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_quat_to_matrix_matches_scipy_for_any_scale(gen, convention):
    q = torch.randn(4, 50, 4, generator=gen, dtype=torch.float64)
    q = q * torch.rand(4, 50, 1, generator=gen, dtype=torch.float64).mul(10).add(0.1)  # not unit
    R = so3.quat_to_matrix(q, convention=convention)
    ref = Rotation.from_quat(q.reshape(-1, 4).numpy(), scalar_first=_scalar_first(convention)).as_matrix()
    torch.testing.assert_close(R, torch.from_numpy(ref).reshape(4, 50, 3, 3), rtol=0, atol=1e-14)
    torch.testing.assert_close(R, so3.quat_to_matrix(-2.5 * q, convention=convention), rtol=0, atol=1e-14)


def test_quaternion_of_exp_is_the_half_angle_axis():
    omega = torch.cat([_special_rotvecs()[1:13], torch.tensor([[0.3, -1.2, 2.0]], dtype=torch.float64)])
    t = omega.norm(dim=-1, keepdim=True)
    expect = torch.cat([torch.cos(t / 2), torch.sin(t / 2) * omega / t], dim=-1)  # wxyz, w >= 0 for t <= pi
    q = so3.matrix_to_quat(so3.exp(omega), convention="wxyz")
    sign = torch.where((q * expect).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q.dtype)  # only at t = pi
    torch.testing.assert_close(q * sign, expect, rtol=0, atol=1e-14)
    xyzw = so3.matrix_to_quat(so3.exp(omega), convention="xyzw")
    assert torch.equal(xyzw, q[..., [1, 2, 3, 0]])


def _gram_schmidt_reference(x: np.ndarray) -> np.ndarray:
    """Per element: QR of the 3x2 matrix [a1 a2] with a positive diagonal, third column by cross."""
    out = []
    for v in x.reshape(-1, 6):
        Q, Rr = np.linalg.qr(np.stack([v[:3], v[3:]], axis=1))
        Q = Q * np.sign(np.diag(Rr))[None, :]
        out.append(np.column_stack([Q, np.cross(Q[:, 0], Q[:, 1])]))
    return np.asarray(out).reshape(*x.shape[:-1], 3, 3)


def test_rot6d_is_gram_schmidt_of_two_columns(gen):
    x = torch.randn(3, 40, 6, generator=gen, dtype=torch.float64)
    R = so3.rot6d_to_matrix(x)
    torch.testing.assert_close(R, torch.from_numpy(_gram_schmidt_reference(x.numpy())), rtol=0, atol=1e-13)
    so3.check_rotation(R)
    # the first column is along a1, the second in the plane of a1, a2 (Zhou et al.)
    torch.testing.assert_close(so3.matrix_to_rot6d(R)[..., :3], x[..., :3] / x[..., :3].norm(dim=-1, keepdim=True))
    assert so3.matrix_to_rot6d(R).shape == (3, 40, 6)


def test_rot6d_layout_is_the_first_two_columns():
    R = so3.exp(torch.tensor([0.2, -0.7, 1.1], dtype=torch.float64))
    assert so3.matrix_to_rot6d(R).tolist() == [R[0, 0], R[1, 0], R[2, 0], R[0, 1], R[1, 1], R[2, 1]]


# ----------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("convention", CONVENTIONS)
def test_round_trips(gen, convention):
    R = _rotations(gen)
    q = so3.matrix_to_quat(R, convention=convention)
    torch.testing.assert_close(so3.quat_to_matrix(q, convention=convention), R, rtol=0, atol=1e-14)
    # canonical quaternions (w > 0) come back exactly, to round-off
    q2 = torch.randn(100, 4, generator=gen, dtype=torch.float64)
    wi = 0 if convention == "wxyz" else 3
    q2 = q2 / q2.norm(dim=-1, keepdim=True)
    q2 = torch.where(q2[..., wi:wi + 1] < 0, -q2, q2)
    back = so3.matrix_to_quat(so3.quat_to_matrix(q2, convention=convention), convention=convention)
    torch.testing.assert_close(back, q2, rtol=0, atol=1e-14)
    torch.testing.assert_close(so3.rot6d_to_matrix(so3.matrix_to_rot6d(R)), R, rtol=0, atol=1e-14)


# ----------------------------------------------------------------------------- singular points
@pytest.mark.parametrize("convention", CONVENTIONS)
def test_gradients_finite_at_identity_and_pi(convention):
    """Backpropagate through each conversion at the identity and at angle pi (about coordinate
    and oblique axes), from rotation vectors through so3.exp as a pipeline would."""
    omega = _special_rotvecs()[[0, 7, 8, 9, 10, 11, 12]]  # the identity and six axes at pi
    torch.testing.assert_close(omega[1:].norm(dim=-1), torch.full((6,), math.pi, dtype=torch.float64))
    for fn in ("matrix_to_quat", "matrix_to_rot6d", "quat_to_matrix", "rot6d_to_matrix"):
        w = omega.clone().requires_grad_()
        R = so3.exp(w)
        if fn == "matrix_to_quat":
            out = so3.matrix_to_quat(R, convention=convention)
        elif fn == "matrix_to_rot6d":
            out = so3.rot6d_to_matrix(so3.matrix_to_rot6d(R))
        elif fn == "quat_to_matrix":
            out = so3.quat_to_matrix(so3.matrix_to_quat(R, convention=convention), convention=convention)
        else:
            out = so3.rot6d_to_matrix(so3.matrix_to_rot6d(R) + 0.0)
        weight = torch.linspace(-1, 1, out.numel(), dtype=out.dtype).reshape(out.shape)
        (g,) = torch.autograd.grad((out * weight).sum(), w)
        assert torch.isfinite(out).all() and torch.isfinite(g).all(), fn
        assert bool((g.abs().sum(-1) > 0).all()), fn  # a real gradient, not a zeroed one


def test_gradcheck_at_identity_pi_and_generic_points(gen):
    """``gradcheck`` at the identity, at pi (6D and quat_to_matrix) and at generic rotations.

    matrix_to_quat is checked just below pi instead of at pi: there ``w = 0`` and the sign
    convention ``w >= 0`` flips ``q`` to ``-q`` across it (the double cover: a jump of the
    function, not of its gradient), so the central differences of gradcheck would straddle
    the jump; its gradient at pi is finite (test above). Where two of Shepperd's rows tie (a
    rotation about (1, -1, 1) has equal diagonal entries) the rows agree on SO(3) only, so the
    derivative is checked along rotations, through ``exp``: the derivative in directions that
    leave SO(3) depends on the row (docstring)."""
    rv = _special_rotvecs()
    R = torch.cat([so3.exp(rv[[0, 7, 11]]), so3.random_rotation(3, generator=gen, dtype=torch.float64)])
    near_pi = torch.cat([so3.exp(rv[[0]] + 0.0), so3.exp(rv[[7, 12]] * (1 - 1e-2)),
                         so3.random_rotation(3, generator=gen, dtype=torch.float64)])
    tie = torch.cat([rv[[11]] * (1 - 1e-2), 0.5 * rv[[11]], torch.randn(2, 3, generator=gen, dtype=torch.float64)])
    for convention in CONVENTIONS:
        assert torch.autograd.gradcheck(lambda M: so3.matrix_to_quat(M, convention=convention),
                                        (near_pi.clone().requires_grad_(),))
        assert torch.autograd.gradcheck(lambda w: so3.matrix_to_quat(so3.exp(w), convention=convention),
                                        (tie.clone().requires_grad_(),))
    q = torch.cat([torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0.6, 0, 0.8]], dtype=torch.float64),
                   torch.randn(3, 4, generator=gen, dtype=torch.float64)])
    for convention in CONVENTIONS:
        assert torch.autograd.gradcheck(lambda v: so3.quat_to_matrix(v, convention=convention),
                                        (q.clone().requires_grad_(),))
    x = so3.matrix_to_rot6d(R) + 0.1 * torch.randn(6, 6, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(so3.rot6d_to_matrix, (torch.cat([so3.matrix_to_rot6d(R), x]).requires_grad_(),))


# ----------------------------------------------------------------------------- dtypes, devices, errors
@pytest.mark.parametrize("dtype,atol", [(torch.float32, 2e-6), (torch.bfloat16, 4e-2), (torch.float16, 4e-3)])
def test_low_precision_dtypes_follow_float64(gen, dtype, atol):
    R = _rotations(gen, n=50)
    for convention in CONVENTIONS:
        q = so3.matrix_to_quat(R.to(dtype), convention=convention)
        assert q.dtype == dtype
        ref = so3.matrix_to_quat(R, convention=convention)
        wi = 0 if convention == "wxyz" else 3
        sign = torch.where((q.double() * ref).sum(-1, keepdim=True) < 0, -1.0, 1.0).double()
        assert bool((sign > 0)[ref[..., wi].abs() > 10 * atol].all())  # sign flips only where w ~ 0
        torch.testing.assert_close(q.double() * sign, ref, rtol=0, atol=atol)
        Rq = so3.quat_to_matrix(ref.to(dtype), convention=convention)
        assert Rq.dtype == dtype
        torch.testing.assert_close(Rq.double(), R, rtol=0, atol=atol)
    R6 = so3.rot6d_to_matrix(so3.matrix_to_rot6d(R).to(dtype))
    assert R6.dtype == dtype
    torch.testing.assert_close(R6.double(), R, rtol=0, atol=atol)


def test_conversions_on_device(device, gen):
    R = _rotations(gen, n=20)
    for convention in CONVENTIONS:
        q = so3.matrix_to_quat(R.to(device), convention=convention)
        assert q.device.type == device.type
        torch.testing.assert_close(q.cpu(), so3.matrix_to_quat(R, convention=convention), rtol=0, atol=1e-13)
        torch.testing.assert_close(so3.quat_to_matrix(q, convention=convention).cpu(), R, rtol=0, atol=1e-13)
    x = so3.matrix_to_rot6d(R.to(device))
    torch.testing.assert_close(so3.rot6d_to_matrix(x).cpu(), R, rtol=0, atol=1e-13)


def test_bad_input_names_the_problem():
    R = torch.eye(3, dtype=torch.float64)
    q = torch.tensor([1.0, 0, 0, 0])
    with pytest.raises(TypeError, match="convention"):
        so3.matrix_to_quat(R)  # no default convention: the libraries disagree
    with pytest.raises(ValueError, match="'wxyz' .* 'xyzw'"):
        so3.quat_to_matrix(q, convention="xyz")
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 4\)"):
        so3.quat_to_matrix(torch.zeros(3), convention="wxyz")
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 6\)"):
        so3.rot6d_to_matrix(torch.zeros(2, 9))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3, 3\)"):
        so3.matrix_to_rot6d(torch.zeros(2, 3))
    with pytest.raises(TypeError, match="torch.Tensor"):
        so3.quat_to_matrix(np.array([1.0, 0, 0, 0]), convention="wxyz")
    with pytest.raises(TypeError, match="floating-point"):
        so3.rot6d_to_matrix(torch.ones(6, dtype=torch.long))
