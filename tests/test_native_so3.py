"""Compiled SO(3) kernels (torchconn/ops/csrc/so3.c) against the torch path of torchconn.ops.so3.

The torch code (switch off: ``torchconn.ops.compiled(False)``) is the reference: same branches, same thresholds, so the
two agree to round-off in values (float32 1e-6, float64 1e-12) and in gradients, including at
the singular points θ = 0 and θ = π. Skipped only when no C compiler is found.
"""
from __future__ import annotations

import math
import warnings

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

import torchconn.ops
from torchconn import so3
from torchconn.ops import native
from torchconn.ops import so3 as ops_so3
from torchconn.tolerances import get_eps

DTYPES = [torch.float32, torch.float64]
VAL_TOL = {torch.float32: 1e-6, torch.float64: 1e-12}
MAPS = ["exp", "log", "sqrt"]
FN = {"exp": ops_so3.exp, "log": ops_so3.log, "sqrt": ops_so3.sqrt}


_C_CALLS: list = []  # names of the C functions of ops_so3._C called since the last _is_native


@pytest.fixture(autouse=True)
def _native_built(monkeypatch):
    if native._compiler() is None:
        pytest.skip("no C compiler found ($CC, cc, gcc, clang): torchconn/csrc/so3.c cannot be built")
    assert native.library("so3") is not None, "torchconn/csrc/so3.c did not build or load"
    for key, fn in list(ops_so3._C.items()):
        def counted(*args, _fn=fn, _key=key):
            _C_CALLS.append(_key)
            return _fn(*args)
        monkeypatch.setitem(ops_so3._C, key, counted)
    _C_CALLS.clear()
    with torchconn.ops.compiled(True):
        yield


def _is_native(out: torch.Tensor) -> bool:
    """Whether a compiled kernel ran since the last call (and ``out`` went through the custom op)."""
    ran = bool(_C_CALLS)
    _C_CALLS.clear()
    return ran and out.grad_fn is not None


def _with(fn, compiled: bool):
    """``fn`` called with the compiled kernels switched on (the default here) or off (torch)."""
    def call(x):
        with torchconn.ops.compiled(compiled):
            return fn(x)
    return call


def _unit(v):
    return v / v.norm(dim=-1, keepdim=True)


def _rotvecs(n, dtype, seed=0, max_angle=math.pi):
    """Axis uniform on the sphere, angle uniform in [0, max_angle) (float64, then cast)."""
    g = torch.Generator().manual_seed(seed)
    axis = _unit(torch.randn(n, 3, generator=g, dtype=torch.float64))
    return (axis * torch.rand(n, 1, generator=g, dtype=torch.float64) * max_angle).to(dtype)


AXES = _unit(torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0],
                           [0.3, -0.5, 0.8], [-2.0, 0.1, 0.4]], dtype=torch.float64))


def _edge_angles(dtype):
    eps = get_eps("small_angle", dtype)
    return [0.0, 1e-8, 0.5 * eps, eps * (1 - 1e-3), eps, eps * (1 + 1e-3), 2 * eps, 0.5,
            math.pi / 2, 2 * math.pi / 3, 2.5, math.pi - 1e-3, math.pi - 1e-6, math.pi]


def _edge_rotvecs(dtype):
    ang = torch.tensor(_edge_angles(dtype), dtype=torch.float64)
    return (AXES[:, None, :] * ang[None, :, None]).reshape(-1, 3)


def _rotation_pi(n):
    """Rotation by exactly π about unit n: 2 n nᵀ − I (exact diag(1, −1, −1) for n = e_x)."""
    return 2.0 * n[..., :, None] * n[..., None, :] - torch.eye(3, dtype=n.dtype)


def _inputs(kind, dtype, n=10_000, seed=0):
    """10⁴ random inputs (angles in [0, π)) plus the edge cases, built in float64 and cast."""
    w = torch.cat([_rotvecs(n, torch.float64, seed), _edge_rotvecs(dtype)])
    if kind == "exp":
        extra = torch.tensor([[0.0, 0.0, 0.0], [7.0, -3.0, 1.0], [2 * math.pi, 0.0, 0.0]], dtype=torch.float64)
        return torch.cat([w, extra]).to(dtype)
    R = so3.exp(w)
    R = torch.cat([R, _rotation_pi(AXES), torch.eye(3, dtype=torch.float64)[None]])
    return R.to(dtype)


def _grad(fn, x, G):
    x = x.detach().clone().requires_grad_()
    out = fn(x)
    (g,) = torch.autograd.grad((out * G).sum(), x)
    return out.detach(), g, out


# ---------------------------------------------------------------- values


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", MAPS)
def test_values_match_torch_path(kind, dtype):
    x = _inputs(kind, dtype)
    fn = FN[kind]
    a, b = fn(x), _with(fn, False)(x)
    assert torch.isfinite(a).all()
    torch.testing.assert_close(a, b, atol=VAL_TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_at_pi_same_branch_and_sign(dtype):
    # at exactly π both signs are logarithms; the C path makes the torch path's choice
    R = _rotation_pi(AXES).to(dtype)
    a, b = ops_so3.log(R), _with(ops_so3.log, False)(R)
    torch.testing.assert_close(a, b, atol=VAL_TOL[dtype], rtol=0)
    torch.testing.assert_close(a.norm(dim=-1), torch.full((len(AXES),), math.pi, dtype=dtype),
                               atol=10 * VAL_TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_log_roundtrip_native(dtype):
    w = _rotvecs(5000, dtype, seed=3, max_angle=math.pi - 1e-3)
    torch.testing.assert_close(ops_so3.log(ops_so3.exp(w)), w, atol=50 * VAL_TOL[dtype], rtol=0)
    R = ops_so3.exp(w)
    S = ops_so3.sqrt(R)
    torch.testing.assert_close(S @ S, R, atol=5 * VAL_TOL[dtype], rtol=0)


@pytest.mark.parametrize("kind", MAPS)
def test_batch_shapes_empty_and_noncontiguous(kind):
    dtype = torch.float64
    fn = FN[kind]
    x = _inputs(kind, dtype, n=40)[:40]
    batched = x.reshape(2, 4, 5, *x.shape[1:])
    out = fn(batched)
    tail = (3,) if kind == "log" else (3, 3)
    assert out.shape == (2, 4, 5, *tail)
    torch.testing.assert_close(out.reshape(40, *tail), fn(x), atol=0, rtol=0)
    # non-contiguous input (a transposed batch)
    nc = batched.transpose(0, 2)
    assert not nc.is_contiguous()
    torch.testing.assert_close(fn(nc), _with(fn, False)(nc), atol=VAL_TOL[dtype], rtol=0)
    # empty batches, forward and backward
    for shape in [(0,), (2, 0)]:
        e = torch.zeros(*shape, *x.shape[1:], dtype=dtype, requires_grad=True)
        oe = fn(e)
        assert oe.shape == (*shape, *tail)
        (ge,) = torch.autograd.grad(oe.sum(), e)
        assert ge.shape == e.shape


def test_bad_shapes_still_raise():
    with pytest.raises(ValueError):
        ops_so3.exp(torch.zeros(4, 2))
    with pytest.raises(ValueError):
        ops_so3.log(torch.zeros(4, 3))


def test_threads_do_not_change_results():
    x = _inputs("log", torch.float32, n=50_000)  # above the C code's parallel threshold
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        a = [FN[k](x if k != "exp" else x[:, 0]) for k in MAPS]
        torch.set_num_threads(2)
        b = [FN[k](x if k != "exp" else x[:, 0]) for k in MAPS]
    finally:
        torch.set_num_threads(before)
    for u, v in zip(a, b):
        assert torch.equal(u, v)


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_checked_kernel_same_values_any_threads(dtype):
    # so3_log_fwd_checked: the same ω as so3_log_fwd bitwise on every edge case, and the same
    # count and first index with 1 or 2 threads (OpenMP reductions over blocks)
    x = _inputs("log", dtype, n=20_000)
    bad = x.clone()
    bad[[17_000, 9_000, 4_500]] = -bad[[17_000, 9_000, 4_500]]
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            w, n_bad, first = ops_so3.log_checked(x, 1e-4)
            assert torch.equal(w, ops_so3.log(x)) and (n_bad, first) == (0, -1)
            w, n_bad, first = ops_so3.log_checked(bad, 1e-4)
            assert torch.equal(w, ops_so3.log(bad)) and (n_bad, first) == (3, 4_500)
    finally:
        torch.set_num_threads(before)


# ---------------------------------------------------------------- gradients


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", MAPS)
def test_gradients_match_torch_path(kind, dtype):
    x = _inputs(kind, dtype)
    fn = FN[kind]
    G = torch.randn(fn(x).shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    _, g_n, out = _grad(fn, x, G.to(dtype))
    _, g_t, _ = _grad(_with(fn, False), x, G.to(dtype))
    assert _is_native(out)
    assert torch.isfinite(g_n).all()
    # both paths against the float64 torch path: the C backward is as accurate as the torch one
    _, g_64, _ = _grad(_with(fn, False), x.double(), G)
    err_n = (g_n.double() - g_64).abs().max()
    err_t = (g_t.double() - g_64).abs().max()
    scale = g_64.abs().max()
    if dtype == torch.float64:
        torch.testing.assert_close(g_n, g_t, atol=1e-12 * scale, rtol=0)
    else:
        # float32: exp's dB/d(t²) = (t sin t − 2(1 − cos t))/(2 t⁴) cancels just above the Taylor
        # threshold (|ω| ~ 1e-2..5e-2), where each path is ~1e-5 off float64; elsewhere 1e-6
        assert err_n <= 2 * err_t + 1e-6 * scale, (float(err_n), float(err_t))
        if kind == "exp":
            t = x.double().norm(dim=-1)
            away = (t < 0.9 * get_eps("small_angle", dtype)) | (t > 0.1)  # margin: float32 rounding of |ω|
            torch.testing.assert_close(g_n[away], g_t[away], atol=1e-6 * scale, rtol=0)
        else:
            torch.testing.assert_close(g_n, g_t, atol=1e-6 * scale, rtol=0)


@pytest.mark.parametrize("scale", [0.0, 1e-7, 1e-3, 1.0, 3.0])
def test_exp_gradcheck_native(scale):
    g = torch.Generator().manual_seed(2)
    w = (torch.randn(6, 3, generator=g, dtype=torch.float64) * scale).requires_grad_()
    assert _is_native(ops_so3.exp(w))
    assert gradcheck(ops_so3.exp, (w,))


@pytest.mark.parametrize("theta", [0.0, 1e-5, 0.5, 1.4, 1.8, 2.5, math.pi - 1e-3])
def test_log_sqrt_gradcheck_native(theta):
    # away from the branch switches (t = π/2, 2π/3), where gradcheck's off-SO(3) perturbations
    # see the branches extend differently
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    R = so3.exp(axis / axis.norm() * theta)[None].requires_grad_()
    for kind in ("log", "sqrt"):
        assert _is_native(FN[kind](R))
        assert gradcheck(FN[kind], (R,))


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradients_finite_and_equal_at_0_and_pi(dtype):
    tol = {torch.float32: 1e-5, torch.float64: 1e-12}[dtype]
    G = torch.randn(4, 3, 3, generator=torch.Generator().manual_seed(5), dtype=dtype)
    # exp at ω = 0 and |ω| = π
    w = torch.stack([torch.zeros(3, dtype=torch.float64), AXES[0] * math.pi, AXES[3] * math.pi,
                     AXES[4] * 1e-8]).to(dtype)
    for kind, x, Gk in [("exp", w, G),
                        ("log", torch.cat([torch.eye(3, dtype=dtype)[None], _rotation_pi(AXES[[0, 3, 4]]).to(dtype)]),
                         G[..., 0]),
                        ("sqrt", torch.cat([torch.eye(3, dtype=dtype)[None], _rotation_pi(AXES[[0, 3, 4]]).to(dtype)]),
                         G)]:
        v_n, g_n, out = _grad(FN[kind], x, Gk)
        v_t, g_t, _ = _grad(_with(FN[kind], False), x, Gk)
        assert _is_native(out)
        assert torch.isfinite(v_n).all() and torch.isfinite(g_n).all(), kind
        torch.testing.assert_close(v_n, v_t, atol=tol, rtol=0)
        torch.testing.assert_close(g_n, g_t, atol=tol, rtol=0)


def test_double_backward_uses_torch_path():
    # create_graph: the backward is recorded through the torch code, so higher orders work
    g = torch.Generator().manual_seed(6)
    w = (torch.randn(5, 3, generator=g, dtype=torch.float64) * 1.2).requires_grad_()
    R = so3.exp(w.detach())[:3].clone().requires_grad_()
    assert gradgradcheck(ops_so3.exp, (w,))
    assert gradgradcheck(ops_so3.log, (R,))
    assert gradgradcheck(ops_so3.sqrt, (R,))
    # and equals the torch path's second derivative
    for kind, x in (("exp", w), ("log", R), ("sqrt", R)):
        outs = []
        for nat in (True, False):
            (g1,) = torch.autograd.grad(_with(FN[kind], nat)(x).square().sum(), x, create_graph=True)
            (g2,) = torch.autograd.grad(g1.square().sum(), x)
            outs.append(g2)
        torch.testing.assert_close(outs[0], outs[1], atol=1e-10, rtol=0)


# ---------------------------------------------------------------- routing and fallbacks


def test_default_routes_to_native_on_cpu_float():
    w = torch.randn(10, 3, dtype=torch.float32, requires_grad=True)
    assert _is_native(so3.exp(w))
    assert _is_native(so3.log(so3.exp(w)))
    assert _is_native(so3.sqrt(so3.exp(w)))


def test_switch_off_uses_torch():
    w = _rotvecs(100, torch.float64, seed=7).requires_grad_()
    for kind, x in (("exp", w), ("log", so3.exp(w)), ("sqrt", so3.exp(w))):
        _C_CALLS.clear()  # so3.exp(w) above ran the compiled kernel
        with torchconn.ops.compiled(False):
            out = FN[kind](x)
        assert not _is_native(out)
        on = FN[kind](x)
        assert _is_native(on)
        torch.testing.assert_close(out, on, atol=VAL_TOL[torch.float64], rtol=0)
        out.sum().backward()


def test_no_compiler_warns_and_falls_back(monkeypatch):
    monkeypatch.setattr(native, "_compiler", lambda: None)
    monkeypatch.setattr(native, "_LIBS", {})
    monkeypatch.setattr(native, "_WARNED", set())
    w = _rotvecs(20, torch.float32, seed=8)
    with pytest.warns(RuntimeWarning, match="no C compiler"):
        out = so3.exp(w)
    torch.testing.assert_close(out, _with(ops_so3.exp, False)(w), atol=0, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_other_dtypes_use_torch(dtype):
    w = _rotvecs(20, torch.float32, seed=9).to(dtype).requires_grad_()
    out = ops_so3.exp(w)
    assert out.dtype == dtype and not _is_native(out)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "native unavailable" warning for a dtype it never handles
        ops_so3.exp(w.detach())


def test_vmap_runs_the_op_on_the_whole_batch():
    # the vmap rule of the custom ops hands the batch to the op as a leading dim: compiled kernel
    w = _rotvecs(8, torch.float64, seed=10)
    _C_CALLS.clear()
    out = torch.func.vmap(ops_so3.exp)(w)
    assert _C_CALLS
    torch.testing.assert_close(out, _with(ops_so3.exp, False)(w), atol=VAL_TOL[torch.float64], rtol=0)
    R = so3.exp(w)
    torch.testing.assert_close(torch.func.vmap(ops_so3.log)(R), _with(ops_so3.log, False)(R),
                               atol=VAL_TOL[torch.float64], rtol=0)


@pytest.mark.parametrize("kind", MAPS)
def test_jacobian_vectorized_and_jacrev(kind):
    # batched grad_outputs (autograd.functional.jacobian(vectorize=True)) and torch.func
    # transforms reach the backward with tensors C cannot read: the torch formulas run there
    w = _rotvecs(4, torch.float64, seed=11, max_angle=3.0)
    x = w if kind == "exp" else so3.exp(w)
    fn = FN[kind]
    ref = torch.autograd.functional.jacobian(_with(fn, False), x)
    for vec in (False, True):
        J = torch.autograd.functional.jacobian(fn, x, vectorize=vec)
        torch.testing.assert_close(J, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.func.jacrev(fn)(x), ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sqrt_fast_path_of_blocks_below_120_degrees(dtype):
    """Blocks of the compiled sqrt whose every trace is positive (angles below 120°) run only the
    half-angle branch: values and gradients against the torch path, and bitwise the values the
    full kernel gives the same matrices inside a mixed block (so the path taken never shows)."""
    small = so3.exp(_rotvecs(3000, torch.float64, seed=5, max_angle=2 * math.pi / 3 * 0.999)).to(dtype)
    mixed = _inputs("sqrt", dtype, n=3000, seed=6)
    for x in (small, torch.cat([small, mixed])):
        fn = FN["sqrt"]
        torch.testing.assert_close(fn(x), _with(fn, False)(x), atol=VAL_TOL[dtype], rtol=0)
        G = torch.randn(x.shape, generator=torch.Generator().manual_seed(7), dtype=dtype)
        _, g_n, out = _grad(fn, x, G)
        _, g_t, _ = _grad(_with(fn, False), x, G)
        assert _is_native(out)
        torch.testing.assert_close(g_n, g_t, atol=VAL_TOL[dtype] * 10 * float(g_t.abs().max()), rtol=0)
    # small matrices interleaved with a π rotation in every block of 128: all blocks take the full kernel
    pi = _rotation_pi(AXES[:1]).to(dtype)
    inter = torch.cat([torch.cat([pi, small[i:i + 127]]) for i in range(0, small.shape[0], 127)])
    keep = torch.ones(inter.shape[0], dtype=torch.bool)
    keep[::128] = False
    G = torch.randn(inter.shape, generator=torch.Generator().manual_seed(8), dtype=dtype)
    _, g_full, _ = _grad(FN["sqrt"], inter, G)
    _, g_fast, _ = _grad(FN["sqrt"], inter[keep], G[keep])
    assert torch.equal(FN["sqrt"](inter)[keep], FN["sqrt"](inter[keep]))
    assert torch.equal(g_full[keep], g_fast)


# ---------------------------------------------------------------- written-out sin, cos, atan2

_TRIG_MAX = {torch.float32: 8192.0, torch.float64: 65536.0}  # SO3_TRIG_MAX of csrc/so3.c
_ULP_BOUND = 3.0  # measured: sin/cos 2.4 ulp, atan2 2.6 ulp (csrc/so3.c)


def _trig(name, dtype, *args):
    """``so3_<name>_<f32|f64>`` of csrc/so3.c on contiguous 1-D tensors: its outputs."""
    from ctypes import c_long, c_void_p

    suf = {torch.float32: "f32", torch.float64: "f64"}[dtype]
    nout = 2 if name == "sincos" else 1
    ins = [a.to(dtype).contiguous() for a in args]
    outs = [torch.empty_like(ins[0]) for _ in range(nout)]
    fn = native.function("so3", f"so3_{name}_{suf}", [c_void_p] * (len(ins) + nout) + [c_long])
    fn(*(native.ptr(t) for t in ins + outs), ins[0].numel())
    return outs


def _ulps(got, ref, dtype):
    """|got - ref| in units of the spacing of ``dtype`` at ``ref`` (``ref`` exact, as float64 or
    mpmath-derived)."""
    import numpy as np

    npd = {torch.float32: np.float32, torch.float64: np.float64}[dtype]
    r = np.abs(np.asarray(ref, dtype=npd))
    spacing = np.spacing(np.maximum(r, np.finfo(npd).tiny)).astype(np.float64)
    return np.abs(got.numpy().astype(np.float64) - np.asarray(ref, dtype=np.float64)) / spacing


def _exact(f, *cols):
    """``f`` of every row evaluated with mpmath (40 digits), rounded to float64 (its error is
    then <= 0.5 ulp of float64: below 1e-8 ulp of float32, 0.5 ulp of float64)."""
    import mpmath

    with mpmath.workdps(40):
        return [float(f(*(mpmath.mpf(float(c)) for c in row))) for row in zip(*cols)]


@pytest.mark.parametrize("dtype", DTYPES)
def test_trig_sincos_accuracy(dtype):
    """sincos within 3 ulp of the exact values on [0, SO3_TRIG_MAX), near multiples of π/2
    (where the reduction cancels) and at tiny arguments; NaN for NaN and ±inf (cost ~0.2 s)."""
    g = torch.Generator().manual_seed(11)
    t = torch.cat([torch.rand(3000, generator=g, dtype=torch.float64) * 4,
                   torch.rand(3000, generator=g, dtype=torch.float64) * _TRIG_MAX[dtype] * 0.999,
                   torch.arange(1, 2000, dtype=torch.float64) * (math.pi / 2),
                   10 ** (-30 * torch.rand(300, generator=g, dtype=torch.float64)),
                   -torch.rand(300, generator=g, dtype=torch.float64) * 100]).to(dtype)
    s, c = _trig("sincos", dtype, t)
    import mpmath

    assert _ulps(s, _exact(mpmath.sin, t), dtype).max() <= _ULP_BOUND
    assert _ulps(c, _exact(mpmath.cos, t), dtype).max() <= _ULP_BOUND
    s, c = _trig("sincos", dtype, torch.tensor([math.nan, math.inf, -math.inf]))
    assert s.isnan().all() and c.isnan().all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_trig_atan2_accuracy_and_ieee_cases(dtype):
    """atan2 within 3 ulp of the exact values over every octant and many magnitudes, and equal
    to C99's atan2 (here torch.atan2) at signed zeros, infinities and NaN (cost ~0.1 s)."""
    g = torch.Generator().manual_seed(12)
    y = torch.cat([torch.randn(4000, generator=g, dtype=torch.float64),
                   torch.randn(2000, generator=g, dtype=torch.float64) * 10 ** (20 * torch.rand(2000, generator=g) - 10)])
    x = torch.cat([torch.randn(4000, generator=g, dtype=torch.float64),
                   torch.randn(2000, generator=g, dtype=torch.float64) * 10 ** (20 * torch.rand(2000, generator=g) - 10)])
    y, x = y.to(dtype), x.to(dtype)
    (a,) = _trig("atan2", dtype, y, x)
    import mpmath

    assert _ulps(a, _exact(mpmath.atan2, y, x), dtype).max() <= _ULP_BOUND
    sp = torch.tensor([0.0, -0.0, 1.0, -1.0, 3.0, math.inf, -math.inf, math.nan], dtype=dtype)
    Y, X = torch.meshgrid(sp, sp, indexing="ij")
    Y, X = Y.reshape(-1), X.reshape(-1)
    (a,) = _trig("atan2", dtype, Y, X)
    ref = torch.atan2(Y, X)
    same = (a == ref) & (torch.signbit(a) == torch.signbit(ref)) | (a.isnan() & ref.isnan())
    close = (a - ref).abs() <= 2 * torch.finfo(dtype).eps * ref.abs()  # e.g. atan2(1, 3): rounding
    finite_args = torch.isfinite(Y) & torch.isfinite(X) & ((Y != 0) | (X != 0))
    assert (same | (close & finite_args)).all(), list(zip(Y[~same].tolist(), X[~same].tolist(), a[~same].tolist()))


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_beyond_the_reduction_range_matches_torch(dtype):
    """Blocks holding an angle |ω| >= SO3_TRIG_MAX take libm's sin/cos (the written-out
    reduction is exact only below): values and gradients still match the torch path."""
    big = _TRIG_MAX[dtype]
    w = torch.cat([_rotvecs(300, torch.float64, seed=13),
                   torch.tensor([[big * 1.5, 0.0, 0.0], [0.0, -3.1 * big, 0.5], [1e8, 2.0, 3.0]],
                                dtype=torch.float64)]).to(dtype)
    fn = FN["exp"]
    torch.testing.assert_close(fn(w), _with(fn, False)(w), atol=VAL_TOL[dtype] * 10, rtol=0)
    G = torch.randn(w.shape[0], 3, 3, generator=torch.Generator().manual_seed(14), dtype=dtype)
    _, g_n, out = _grad(fn, w, G)
    _, g_t, _ = _grad(_with(fn, False), w, G)
    assert _is_native(out)
    torch.testing.assert_close(g_n, g_t, atol=VAL_TOL[dtype] * 10, rtol=0)


@pytest.mark.parametrize("kind", MAPS)
def test_backward_reads_strided_gradients_in_place(kind):
    """The compiled backward reads the incoming gradient through its strides: a broadcast one
    (the gradient of a sum, strides 0), one broadcast along the batch and a transposed one give
    bitwise what the same gradient made contiguous gives (cost ~20 ms)."""
    dtype = torch.float32
    x = _inputs(kind, dtype, n=3000, seed=15)
    bwd = {"exp": ops_so3._so3_exp_backward, "log": ops_so3._so3_log_backward,
           "sqrt": ops_so3._so3_sqrt_backward}[kind]
    shape = (x.shape[0], 3) if kind == "log" else (x.shape[0], 3, 3)
    gen = torch.Generator().manual_seed(16)
    K = 3 if kind == "log" else 9
    grads = [torch.ones((), dtype=dtype).expand(shape),                                  # strides (0, 0)
             torch.randn(shape[1:], generator=gen, dtype=dtype).expand(shape),            # (0, 1)
             torch.randn(K, x.shape[0], generator=gen, dtype=dtype).t().reshape(shape)]   # (1, n)
    for G in grads:
        assert not G.is_contiguous() and G.reshape(x.shape[0], K)._base is not None  # read as a view
        out = bwd(x, G)
        assert _C_CALLS, "the compiled backward did not run"
        _C_CALLS.clear()
        assert torch.equal(out, bwd(x, G.contiguous()))
        torch.testing.assert_close(out, _with(lambda t: bwd(t, G), False)(x), atol=VAL_TOL[dtype] * 100, rtol=1e-5)
