"""``so3.log`` of a non-rotation raises, naming the batch index and the defect (issue 14).

Both paths: the compiled kernel (``so3_log_fwd_checked`` in csrc/so3.c, the check computed in
the log's own pass) and the torch code (``torchconn.ops.compiled(False)``). The check does not
change the values (bitwise), the gradients, nor what ``torch.compile`` and ``vmap`` see.
"""
from __future__ import annotations

import math

import pytest
import torch

import torchconn.ops
from torchconn import so3
from torchconn.ops import native
from torchconn.ops import so3 as ops_so3
from torchconn.ops.backend import can_use_compiled

DTYPES = [torch.float32, torch.float64]
PATHS = [pytest.param(True, id="compiled"), pytest.param(False, id="torch")]


@pytest.fixture(params=PATHS)
def compiled(request):
    if request.param and native._compiler() is None:
        pytest.skip("no C compiler found ($CC, cc, gcc, clang): csrc/so3.c cannot be built")
    with torchconn.ops.compiled(request.param):
        yield request.param


def _rots(n, dtype, seed=0):
    return so3.random_rotation(n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)


def _shear():
    S = torch.eye(3, dtype=torch.float64)
    S[0, 1] = 0.3
    return S


# name, what replaces matrix k (a function of the rotation there), words of the defect
CASES = [
    ("reflection", lambda R: -R, r"det -1 \(a reflection\): det R = -1\.0"),
    ("reflection_one_axis", lambda R: R * torch.tensor([1.0, 1.0, -1.0], dtype=R.dtype),
     r"det -1 \(a reflection\)"),
    ("scaled", lambda R: 1.01 * R, r"not orthogonal: residual \|\|R\^T R - I\|\|_F = 3\.4\d*e-02 > tolerance 1\.0e-04"),
    ("sheared", lambda R: R @ _shear().to(R.dtype), r"not orthogonal: residual .* > tolerance"),
    ("zero", lambda R: torch.zeros_like(R), r"not orthogonal: residual \|\|R\^T R - I\|\|_F = 1\.732e\+00"),
    ("nan", lambda R: R.index_put((torch.tensor(1), torch.tensor(2)), torch.tensor(float("nan"), dtype=R.dtype)),
     r"non-finite entries \(NaN/inf\)"),
    ("inf", lambda R: R.index_put((torch.tensor(0), torch.tensor(0)), torch.tensor(float("inf"), dtype=R.dtype)),
     r"non-finite entries \(NaN/inf\)"),
    ("neg_inf_and_nan", lambda R: torch.full_like(R, -float("inf")), r"non-finite entries"),
]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name, bad, words", CASES, ids=[c[0] for c in CASES])
def test_non_rotation_raises_with_index(compiled, dtype, name, bad, words):
    R = _rots(12, dtype).reshape(3, 4, 3, 3)
    R[2, 1] = bad(R[2, 1].clone())
    assert can_use_compiled("so3", R) == compiled
    with pytest.raises(ValueError, match=r"so3\.log: R \(shape \(3, 4, 3, 3\)\) at batch index \(2, 1\) is not a "
                       r"rotation: " + words + r".*1 of 12 matrices are not rotations.*so3\.project_to_rotation\(R\)"
                       r".*so3\.check_rotation\(R\)"):
        so3.log(R)


def test_unbatched_and_first_of_many(compiled):
    with pytest.raises(ValueError, match=r"shape \(3, 3\)\) at batch index \(\) .*det -1 .*1 of 1 matrices"):
        so3.log(-torch.eye(3, dtype=torch.float64))
    # more than one parallel block (SO3_B = 128 elements) and thread chunk (SO3_PAR_MIN = 4096):
    # the count is the total and the index the smallest, whichever thread finds it first
    R = _rots(20_000, torch.float64, seed=1)
    bad = [19_999, 7_777, 5_000, 130, 4_100]
    R[bad] = 2.0 * R[bad]
    with pytest.raises(ValueError, match=r"at batch index \(130,\) .*not orthogonal.* 5 of 20000 matrices"):
        so3.log(R)


def test_paths_flag_the_same_matrices():
    if native._compiler() is None:
        pytest.skip("no C compiler found")
    # near the tolerance (1e-4 on ||R^T R - I||_F, about 2 sqrt(3) |s| for R (1 + s)) on both sides
    R = _rots(3000, torch.float64, seed=2)
    s = torch.logspace(-7, -2, 3000, dtype=torch.float64) * torch.where(torch.arange(3000) % 2 == 0, 1.0, -1.0)
    M = R * (1.0 + s)[:, None, None]
    M[::7] = -M[::7]
    for dtype in DTYPES:
        x = M.to(dtype)
        with torchconn.ops.compiled(True):
            w_c, n_c, first_c = ops_so3.log_checked(x, 1e-4)
        with torchconn.ops.compiled(False):
            _, n_t, first_t = ops_so3.log_checked(x, 1e-4)
        flags = ops_so3._rotation_flags(x, 1e-4)[0]
        assert n_c == n_t == int(flags.sum()) and 0 < n_c < 3000
        assert first_c == first_t == int(torch.nonzero(flags)[0, 0]) == 0
        with torchconn.ops.compiled(True):
            assert torch.equal(w_c, ops_so3.log(x))  # the checked kernel's values, bitwise


@pytest.mark.parametrize("dtype", DTYPES)
def test_checked_kernel_values_bitwise_unchanged(compiled, dtype):
    # random rotations, angles 0 and exactly pi, and garbage (which only the count reports)
    R = _rots(5000, dtype, seed=3)
    pi_x = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dtype))
    extra = torch.stack([torch.eye(3, dtype=dtype), pi_x, torch.zeros(3, 3, dtype=dtype), -pi_x])
    x = torch.cat([R, extra])
    w, n_bad, first = ops_so3.log_checked(x, 1e-4)
    assert torch.equal(w.nan_to_num(), ops_so3.log(x).nan_to_num())
    assert (n_bad, first) == (2, 5002)


@pytest.mark.parametrize("dtype", DTYPES)
def test_valid_rotations_at_0_and_pi_pass(compiled, dtype):
    axes = torch.nn.functional.normalize(torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [1.0, 1.0, 1.0], [0.3, -0.5, 0.8]],
                                                      dtype=torch.float64), dim=-1)
    R_pi = 2.0 * axes[:, :, None] * axes[:, None, :] - torch.eye(3, dtype=torch.float64)  # angle exactly pi
    R = torch.cat([torch.eye(3, dtype=torch.float64)[None], R_pi, so3.exp(1e-9 * axes)]).to(dtype)
    w = so3.log(R)
    assert torch.equal(w, ops_so3.log(R))
    assert torch.allclose(w[0], torch.zeros(3, dtype=dtype))
    assert torch.allclose(w[1:5].norm(dim=-1), torch.full((4,), math.pi, dtype=dtype))
    assert so3.log(R[:0]).shape == (0, 3)


def test_float32_stored_rotations_and_half_precision(compiled):
    # rotations rounded to float32 and cast back are accepted in float64 (residual ~1e-7 <= 1e-4)
    R = _rots(100, torch.float32, seed=4).double()
    assert torch.equal(so3.log(R), ops_so3.log(R))
    for dtype in (torch.float16, torch.bfloat16):  # torch path, check computed in float32
        Rh = _rots(6, dtype, seed=5)
        assert so3.log(Rh).dtype == dtype
        Rh[4] = -Rh[4]
        with pytest.raises(ValueError, match=r"at batch index \(4,\) .*det -1"):
            so3.log(Rh)


def test_gradients_unchanged(compiled):
    R = _rots(50, torch.float64, seed=6).requires_grad_()
    G = torch.randn(50, 3, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    (g,) = torch.autograd.grad((so3.log(R) * G).sum(), R)
    (g_ref,) = torch.autograd.grad((ops_so3.log(R) * G).sum(), R)
    assert torch.equal(g, g_ref)
    assert torch.autograd.gradcheck(so3.log, (R[:3].detach().clone().requires_grad_(),))


def test_no_check_under_compile_vmap_meta(compiled):
    import torch._dynamo as dynamo

    R = _rots(5, torch.float64, seed=8)
    dynamo.reset()
    assert dynamo.explain(so3.log)(R).graph_break_count == 0  # as for the unvalidated op
    dynamo.reset()
    torch.testing.assert_close(torch.compile(so3.log, backend="eager")(R), ops_so3.log(R), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.func.vmap(so3.log)(R), ops_so3.log(R), atol=1e-12, rtol=0)
    # documented: not validated where no data may be read (no sync, no graph break)
    Rb = R.clone()
    Rb[3] = -Rb[3]
    dynamo.reset()
    assert torch.compile(so3.log, backend="eager")(Rb).shape == (5, 3)
    assert torch.func.vmap(so3.log)(Rb).shape == (5, 3)
    assert so3.log(Rb.to("meta")).shape == (5, 3)
    with pytest.raises(ValueError, match=r"batch index \(3,\)"):
        so3.log(Rb)
