"""Tests of torchconn.son: SO(n) parametrization, exp/log, Haar sampling, validation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from torch.autograd import gradcheck

from torchconn import so3, son
from torchconn.tolerances import get_eps

DTYPES = [torch.float32, torch.float64]
RANKS = [2, 3, 4, 5]
REF_TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def _skew(n: int, batch: int, gen: torch.Generator, max_angle: float, dtype=torch.float64) -> torch.Tensor:
    """Random skew matrices whose largest rotation angle (spectral norm) is in (0, max_angle)."""
    K = son.hat(torch.randn(batch, son.dim(n), generator=gen, dtype=torch.float64), n)
    scale = torch.rand(batch, generator=gen, dtype=torch.float64) * max_angle
    K = K / torch.linalg.matrix_norm(K, ord=2)[:, None, None] * scale[:, None, None]
    return K.to(dtype)


def test_dim():
    assert [son.dim(n) for n in (1, 2, 3, 4, 5)] == [0, 1, 3, 6, 10]
    with pytest.raises(ValueError, match="n must be >= 1"):
        son.dim(0)


# ---------------------------------------------------------------- hat / vee


@pytest.mark.parametrize("n", RANKS)
def test_hat_vee_round_trip(n, gen):
    p = torch.randn(7, son.dim(n), generator=gen, dtype=torch.float64)
    K = son.hat(p, n)
    assert K.shape == (7, n, n)
    torch.testing.assert_close(K, -K.transpose(-1, -2), rtol=0, atol=0)
    torch.testing.assert_close(son.vee(K), p, rtol=0, atol=1e-15)
    # vee is the projection on the skew part
    S = torch.randn(7, n, n, generator=gen, dtype=torch.float64)
    S = S + S.transpose(-1, -2)
    torch.testing.assert_close(son.vee(K + S), p, rtol=0, atol=1e-14)
    torch.testing.assert_close(son.hat(son.vee(K), n), K, rtol=0, atol=1e-15)


def test_hat_n3_equals_so3(gen):
    w = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(son.hat(w, 3), so3.hat(w), rtol=0, atol=0)
    torch.testing.assert_close(son.vee(so3.hat(w)), so3.vee(so3.hat(w)), rtol=0, atol=0)


def test_hat_lexicographic_order():
    n = 4
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    for a, (i, j) in enumerate(pairs):
        K = son.hat(torch.eye(6, dtype=torch.float64)[a], n)
        expected = torch.zeros(n, n, dtype=torch.float64)
        expected[j, i], expected[i, j] = 1.0, -1.0
        torch.testing.assert_close(K, expected, rtol=0, atol=0)


def test_n2_positive_angle_is_counter_clockwise():
    t = torch.tensor([0.3, -1.2, 2.9], dtype=torch.float64)
    R = son.exp_params(t[:, None], 2)
    e0 = torch.tensor([1.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(R @ e0, torch.stack((torch.cos(t), torch.sin(t)), -1))


def test_hat_bad_shape():
    with pytest.raises(ValueError, match=r"n=4 expects params of shape \(\.\.\., 6\)"):
        son.hat(torch.zeros(5), 4)
    with pytest.raises(ValueError, match=r"\(\.\.\., n, n\)"):
        son.vee(torch.zeros(3, 4))


# ---------------------------------------------------------------- exp / log


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", RANKS)
def test_exp_is_rotation_and_matches_matrix_exp(n, dtype, gen):
    K = son.hat(2.0 * torch.randn(64, son.dim(n), generator=gen, dtype=torch.float64), n)
    R = son.exp(K.to(dtype))
    assert R.dtype == dtype and R.shape == (64, n, n)
    son.check_rotation(R)
    eye = torch.eye(n, dtype=dtype)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye.expand(64, n, n), rtol=0, atol=REF_TOL[dtype])
    assert torch.all(torch.linalg.det(R) > 0)
    ref = torch.from_numpy(np.stack([scipy.linalg.expm(k) for k in K[:12].numpy()]))
    torch.testing.assert_close(R[:12].double(), ref, rtol=0, atol=100 * REF_TOL[dtype])
    torch.testing.assert_close(R, torch.linalg.matrix_exp(K.to(dtype)), rtol=0, atol=100 * REF_TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", RANKS)
def test_log_exp_round_trip(n, dtype, gen):
    K = _skew(n, 64, gen, max_angle=3.0, dtype=dtype)
    # a 1e-4 margin per unit of conditioning 1/(pi - t): tolerance scales with the dtype
    torch.testing.assert_close(son.log(son.exp(K)), K, rtol=0, atol=100 * REF_TOL[dtype])


@pytest.mark.parametrize("n", [4, 5])
def test_log_matches_scipy_logm(n, gen):
    R = son.random_rotation(8, n=n, generator=gen, dtype=torch.float64)
    ref = np.stack([scipy.linalg.logm(r).real for r in R.numpy()])
    L = son.log(R)
    torch.testing.assert_close(L, torch.from_numpy(ref), rtol=0, atol=1e-9)
    torch.testing.assert_close(son.exp(L), R, rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", [2, 3])
def test_general_log_agrees_with_closed_forms(n, gen):
    # the n >= 4 algorithm (inverse scaling and squaring) against the closed forms
    R = son.random_rotation(200, n=n, generator=gen, dtype=torch.float64)
    angle = son.vee(son.log(R)).norm(dim=-1)
    R = R[angle < math.pi - 1e-2]
    torch.testing.assert_close(son._log_iss(R), son.log(R), rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", RANKS)
def test_exp_log_of_random_rotations(n, gen):
    R = son.random_rotation(200, n=n, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(son.exp(son.log(R)), R, rtol=0, atol=1e-11)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_gradcheck_exp(n, gen):
    # one parameter vector: batched torch.linalg.matrix_exp has a ~0.08 s per-call backward
    # overhead on CPU (torch 2.13), which gradcheck would pay ~40 times
    p = torch.randn(son.dim(n), generator=gen, dtype=torch.float64).requires_grad_()
    assert gradcheck(lambda q: son.exp_params(q, n), (p,))
    # exp on a general (non-skew) matrix input: the derivative of the skew projection too
    K = torch.randn(n, n, generator=gen, dtype=torch.float64).requires_grad_()
    assert gradcheck(son.exp, (K,))


@pytest.mark.parametrize("n", [2, 3, 4])
def test_gradcheck_log(n, gen):
    R = son.exp(_skew(n, 2, gen, max_angle=2.5)).requires_grad_()
    assert gradcheck(son.log, (R,))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", RANKS)
def test_finite_gradient_at_identity(n, dtype):
    p = torch.zeros(son.dim(n), dtype=dtype, requires_grad=True)
    R = son.exp_params(p, n)
    w = torch.arange(n * n, dtype=dtype).reshape(n, n)
    (R * w).sum().backward()
    # d/dp <exp(hat p), W> at 0 = <E_a, W>: the exact first-order term
    expected = (son.hat(torch.eye(son.dim(n), dtype=dtype), n) * w).sum((-2, -1))
    torch.testing.assert_close(p.grad, expected)
    Rl = R.detach().requires_grad_()
    son.log(Rl).sum().backward()
    assert torch.isfinite(Rl.grad).all()


# ---------------------------------------------------------------- random rotations


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", RANKS)
def test_random_rotation_is_rotation_and_seeded(n, dtype):
    R1 = son.random_rotation(4, 3, n=n, generator=torch.Generator().manual_seed(7), dtype=dtype)
    R2 = son.random_rotation(4, 3, n=n, generator=torch.Generator().manual_seed(7), dtype=dtype)
    R3 = son.random_rotation(4, 3, n=n, generator=torch.Generator().manual_seed(8), dtype=dtype)
    assert R1.shape == (4, 3, n, n) and R1.dtype == dtype
    torch.testing.assert_close(R1, R2, rtol=0, atol=0)
    assert (R1 - R3).abs().max() > 0.1
    eye = torch.eye(n, dtype=dtype).expand_as(R1)
    torch.testing.assert_close(R1.transpose(-1, -2) @ R1, eye, rtol=0, atol=REF_TOL[dtype])
    torch.testing.assert_close(torch.linalg.det(R1), torch.ones(4, 3, dtype=dtype), rtol=0, atol=REF_TOL[dtype])


@pytest.mark.parametrize("n", RANKS)
def test_random_rotation_haar_moments(n, gen):
    # Haar on SO(n): E[R] = 0, E[tr R] = 0, E[tr(R)^2] = 1 (n >= 3), = 2 for SO(2)
    N = 20_000
    R = son.random_rotation(N, n=n, generator=gen, dtype=torch.float64)
    tr = R.diagonal(dim1=-2, dim2=-1).sum(-1)
    se = 1.0 / math.sqrt(N)
    assert R.mean(0).abs().max() < 5 * se
    assert abs(tr.mean().item()) < 5 * se * math.sqrt(2)
    m2 = 2.0 if n == 2 else 1.0
    assert abs((tr**2).mean().item() - m2) < 6 * se * math.sqrt(3)


# ---------------------------------------------------------------- validation


@pytest.mark.parametrize("n", [2, 4])
def test_check_rotation_messages(n, gen):
    R = son.random_rotation(3, 2, n=n, generator=gen, dtype=torch.float64)
    son.check_rotation(R)
    bad = R.clone()
    bad[1, 0, :, 1] *= -1
    with pytest.raises(ValueError, match=r"Q .*1 of 6 .*det = -1\.0+ .*index \(1, 0\)"):
        son.check_rotation(bad, name="Q")
    bad = R.clone()
    bad[2, 1] += 1e-3
    with pytest.raises(ValueError, match=r"not orthogonal at index \(2, 1\): \|\|R\^T R - I\|\|_F = "):
        son.check_rotation(bad)
    bad = R.clone()
    bad[0, 1, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"NaN/inf\) at index \(0, 1\)"):
        son.check_rotation(bad)
    with pytest.raises(ValueError, match=r"index \(\)"):
        son.check_rotation(2 * torch.eye(n))
    with pytest.raises(TypeError, match="floating-point"):
        son.check_rotation(torch.eye(n, dtype=torch.long))
    atol = get_eps("rotation", torch.float64)
    son.check_rotation(R * (1 + 0.1 * atol))


@pytest.mark.parametrize("dtype", DTYPES)
def test_general_log_near_pi_gives_nan_only_there(dtype):
    n = 4
    K = torch.zeros(3, n, n, dtype=torch.float64)
    K[0, 1, 0] = 1.0
    K[1, 1, 0] = math.pi  # exactly pi: the logarithm is not unique
    K[2, 1, 0] = math.pi - 0.5
    K[2, 3, 2] = 0.7
    K = (K - K.transpose(-1, -2)).to(dtype)
    R = son.exp(K).requires_grad_()
    L = son.log(R)
    assert torch.isnan(L[1]).all()
    torch.testing.assert_close(L[[0, 2]], K[[0, 2]], rtol=0, atol=100 * REF_TOL[dtype])
    L[[0, 2]].sum().backward()
    assert torch.isfinite(R.grad).all()


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", RANKS)
def test_sqrt(n, dtype, gen):
    K = _skew(n, 32, gen, max_angle=3.0, dtype=dtype)
    S = son.sqrt(son.exp(K))
    torch.testing.assert_close(S, son.exp(K / 2), rtol=0, atol=100 * REF_TOL[dtype])
    torch.testing.assert_close(S @ S, son.exp(K), rtol=0, atol=10 * REF_TOL[dtype])


def test_gradcheck_sqrt(gen):
    R = son.exp(_skew(4, 2, gen, max_angle=2.5)).requires_grad_()
    assert gradcheck(son.sqrt, (R,))
    K = torch.zeros(4, 4, dtype=torch.float64)
    K[1, 0], K[0, 1] = math.pi, -math.pi
    assert torch.isnan(son.sqrt(son.exp(K))).all()


def test_no_hard_coded_device():
    # on the meta device any constant created on the CPU would raise a device mismatch
    for n in (2, 3, 4):
        m = torch.zeros(5, n, n, device="meta")
        for out in (son.exp(m), son.log(m), son.sqrt(m), son.hat(torch.zeros(5, son.dim(n), device="meta"), n),
                    son.random_rotation(5, n=n, device="meta")):
            assert out.device.type == "meta"
        assert son.vee(m).device.type == "meta"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu(gen):
    R = son.random_rotation(50, n=5, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(son.log(R.cuda()).cpu(), son.log(R))
    torch.testing.assert_close(son.exp(son.log(R).cuda()).cpu(), R)
    son.check_rotation(R.cuda())
