"""The SO(3) custom ops (``torchconn::so3_*``) against the op contract of issue 11.

opcheck (float32 and float64, compiled kernels on and off) for every op and backward op;
gradcheck / gradgradcheck through the public functions on both paths; a Hessian-vector product
against central differences of the gradient; vmap and batched calls against per-item loops;
``torch.func`` transforms; ``torch.compile(fullgraph=True)``; meta tensors; the compiled
backward against the torch formula on arbitrary 3x3 matrices; the fallback without a compiler.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

import torchconn.ops
from torchconn import so3
from torchconn.ops import _so3_formulas as formulas
from torchconn.ops import native
from torchconn.ops import so3 as ops_so3

DTYPES = [torch.float32, torch.float64]
SWITCH = [True, False]
HAVE_C = native._compiler() is not None and native.library("so3") is not None


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _omega(n, dtype=torch.float64, seed=0, scale=1.5):
    return (scale * torch.randn(n, 3, generator=_gen(seed), dtype=torch.float64)).to(dtype)


def _rot(n, dtype=torch.float64, seed=0):
    """Rotations with angles spread over [0, π) (both sqrt branches, all three log branches)."""
    w = _omega(n, torch.float64, seed)
    w = w / w.norm(dim=-1, keepdim=True) * torch.rand(n, 1, generator=_gen(seed + 1), dtype=torch.float64) * 3.1
    return ops_so3.exp(w).to(dtype)


def _input(kind, n, dtype=torch.float64, seed=0):
    return _omega(n, dtype, seed) if kind == "exp" else _rot(n, dtype, seed)


OPS = {"exp": ops_so3._so3_exp, "log": ops_so3._so3_log, "sqrt": ops_so3._so3_sqrt}
BWD_OPS = {"exp": ops_so3._so3_exp_backward, "log": ops_so3._so3_log_backward, "sqrt": ops_so3._so3_sqrt_backward}
PUBLIC = {"exp": ops_so3.exp, "log": ops_so3.log, "sqrt": ops_so3.sqrt}


def _on(compiled, fn):
    def call(*a):
        with torchconn.ops.compiled(compiled):
            return fn(*a)
    return call


# ------------------------------------------------------------------------- opcheck


#: opcheck's AOT-dispatch test compiles (3-10 s per op): run in full for float64 with the
#: compiled kernels on, the other three utilities for every dtype and switch state; the full
#: check of the other combinations is marked slow.
FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")
OPCHECK_CASES = [pytest.param(dt, on, marks=() if (dt == torch.float64 and on) else pytest.mark.slow)
                 for dt in DTYPES for on in SWITCH]
FULL_KINDS = ["exp", "log", pytest.param("sqrt", marks=pytest.mark.slow)]  # sqrt: ~20 s


def _opcheck_so3(kind, dtype, compiled, utils):
    x = _input(kind, 6, dtype, seed=1).reshape(2, 3, *(_input(kind, 1).shape[1:]))
    kw = {} if utils is None else {"test_utils": utils}
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(OPS[kind], (x.clone().requires_grad_(),), **kw)
        g = torch.randn(OPS[kind](x).shape, generator=_gen(2), dtype=dtype)
        torch.library.opcheck(BWD_OPS[kind], (x.clone().requires_grad_(), g.requires_grad_()), **kw)


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_opcheck_schema_autograd_fake(kind, dtype, compiled):
    _opcheck_so3(kind, dtype, compiled, FAST_UTILS)


@pytest.mark.parametrize("dtype,compiled", OPCHECK_CASES)
@pytest.mark.parametrize("kind", FULL_KINDS)
def test_opcheck_full(kind, dtype, compiled):
    _opcheck_so3(kind, dtype, compiled, None)


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("dtype", DTYPES)
def test_opcheck_log_checked(dtype, compiled):
    R = _rot(5, dtype, seed=3)
    R[2] = -R[2]  # a reflection
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(ops_so3._so3_log_checked, (R.clone().requires_grad_(), 1e-4))
        w, n_bad, first = ops_so3._so3_log_checked(R, 1e-4)
    assert n_bad.dtype == first.dtype == torch.int64 and (int(n_bad), int(first)) == (1, 2)
    assert ops_so3.log_checked(R, 1e-4)[1:] == (1, 2)


# ------------------------------------------------------------------------- values, gradients


@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_switch_on_off_same_values_and_gradients(kind):
    x = _input(kind, 200, torch.float64, seed=4)
    outs = []
    for compiled in SWITCH:
        xx = x.clone().requires_grad_()
        y = _on(compiled, PUBLIC[kind])(xx)
        G = torch.randn(y.shape, generator=_gen(5), dtype=y.dtype)
        (g,) = torch.autograd.grad((y * G).sum(), xx)
        outs.append((y.detach(), g))
    torch.testing.assert_close(outs[0][0], outs[1][0], atol=1e-12, rtol=0)
    torch.testing.assert_close(outs[0][1], outs[1][1], atol=1e-11, rtol=0)


@pytest.mark.skipif(not HAVE_C, reason="no C compiler: csrc/so3.c cannot be built")
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", ["log", "sqrt"])
def test_compiled_backward_is_the_formula_on_any_matrix(kind, dtype):
    # not only along rotations: random 3x3 matrices (both signs of tr R, all log branches),
    # scaled rotations and matrices with tr R close to 0 (the sqrt branch switch)
    M = torch.randn(4000, 3, 3, generator=_gen(6), dtype=torch.float64)
    near0 = _rot(500, seed=7)
    near0 = near0 - (near0.diagonal(dim1=-2, dim2=-1).sum(-1) / 3 - 1e-3)[:, None, None] * torch.eye(3, dtype=torch.float64)
    M = torch.cat([M, 1.3 * _rot(500, seed=8), near0]).to(dtype)
    G = torch.randn(OPS[kind](M).shape, generator=_gen(9), dtype=dtype)
    with torchconn.ops.compiled(True):
        g_c = BWD_OPS[kind](M, G)
    g_t = getattr(formulas, f"{kind}_bwd")(M, G)
    finite = torch.isfinite(g_t).flatten(1).all(1)
    assert finite.float().mean() > 0.99
    assert torch.equal(torch.isfinite(g_c).flatten(1).all(1), finite)
    tol = 2e-3 if dtype == torch.float32 else 1e-9
    scale = g_t[finite].abs().flatten(1).amax(1, keepdim=True).clamp_min(1.0)
    assert ((g_c[finite] - g_t[finite]).abs().flatten(1) / scale).max() < tol


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_gradcheck_gradgradcheck(kind, compiled):
    x = _input(kind, 4, torch.float64, seed=10).reshape(2, 2, *_input(kind, 1).shape[1:]).requires_grad_()
    with torchconn.ops.compiled(compiled):
        assert gradcheck(PUBLIC[kind], (x,))
        assert gradgradcheck(PUBLIC[kind], (x,))
        # the op itself (its register_autograd path, as torch.compile sees it)
        assert gradgradcheck(OPS[kind], (x,))


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_hvp_matches_central_differences(kind, compiled):
    x = _input(kind, 5, torch.float64, seed=11)
    v = torch.randn(x.shape, generator=_gen(12), dtype=torch.float64)
    f = lambda z: PUBLIC[kind](z).square().sum() + PUBLIC[kind](z).sum()  # noqa: E731

    def grad(z):
        z = z.clone().requires_grad_()
        return torch.autograd.grad(f(z), z)[0]

    with torchconn.ops.compiled(compiled):
        _, hv = torch.autograd.functional.hvp(f, x, v)
        h = 1e-5
        fd = (grad(x + h * v) - grad(x - h * v)) / (2 * h)
    torch.testing.assert_close(hv, fd, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_vmap_and_batched_match_a_loop(kind):
    x = _input(kind, 12, torch.float64, seed=13).reshape(3, 4, *_input(kind, 1).shape[1:])
    loop = torch.stack([PUBLIC[kind](x[i]) for i in range(3)])
    torch.testing.assert_close(torch.func.vmap(PUBLIC[kind])(x), loop, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.func.vmap(PUBLIC[kind], in_dims=1)(x.movedim(0, 1)), loop, atol=1e-12, rtol=0)
    torch.testing.assert_close(PUBLIC[kind](x), loop, atol=1e-12, rtol=0)  # C: vector vs tail lanes
    # vmap of the gradient (per-sample gradients) against a loop
    f = lambda z: PUBLIC[kind](z).square().sum()  # noqa: E731
    per = torch.func.vmap(torch.func.grad(f))(x)
    ref = torch.stack([torch.func.grad(f)(x[i]) for i in range(3)])
    torch.testing.assert_close(per, ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_torch_func_transforms(kind):
    x = _input(kind, 3, torch.float64, seed=14)
    ref_f = {"exp": formulas.exp, "log": formulas.log, "sqrt": formulas.sqrt}[kind]
    J = torch.autograd.functional.jacobian(ref_f, x)
    torch.testing.assert_close(torch.func.jacrev(PUBLIC[kind])(x), J, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.func.jacfwd(PUBLIC[kind])(x), J, atol=1e-12, rtol=0)
    t = torch.randn(x.shape, generator=_gen(15), dtype=torch.float64)
    _, jv = torch.func.jvp(PUBLIC[kind], (x,), (t,))
    torch.testing.assert_close(jv, (J.reshape(-1, x.numel()) @ t.reshape(-1)).reshape(jv.shape), atol=1e-12, rtol=0)
    H = torch.func.hessian(lambda z: PUBLIC[kind](z).square().sum())(x)
    Hr = torch.func.hessian(lambda z: ref_f(z).square().sum())(x)
    torch.testing.assert_close(H, Hr, atol=1e-10, rtol=0)


def test_torch_compile_fullgraph():
    w = _omega(7, torch.float64, seed=16).requires_grad_()

    def loss(w):
        R = ops_so3.exp(w)
        return ops_so3.log(R).square().sum() + ops_so3.sqrt(R).sum()

    compiled = torch.compile(loss, fullgraph=True, backend="aot_eager")
    val = compiled(w)
    (g,) = torch.autograd.grad(val, w)
    (g_ref,) = torch.autograd.grad(loss(w), w)
    torch.testing.assert_close(val, loss(w), atol=1e-12, rtol=0)
    torch.testing.assert_close(g, g_ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_meta_tensors(kind):
    x = _input(kind, 4).reshape(2, 2, *_input(kind, 1).shape[1:]).to("meta")
    out = PUBLIC[kind](x)
    assert out.device.type == "meta" and out.shape == OPS[kind](_input(kind, 4).reshape(x.shape)).shape
    assert so3.log(so3.exp(torch.zeros(3, 3, device="meta"))).shape == (3, 3)  # validation skipped on meta


def test_generic_sqrt_has_no_nonzero_and_compiles_on_the_generic_path():
    # the torch formula is safe-where: traceable by make_fx with no data-dependent op
    R = _rot(6, seed=17)
    gm = torch.fx.experimental.proxy_tensor.make_fx(formulas.sqrt)(R)
    assert not any("nonzero" in str(n.target) for n in gm.graph.nodes)
    torch.testing.assert_close(gm(R), formulas.sqrt(R), atol=0, rtol=0)


# ------------------------------------------------------------------------- no compiler


def test_fallback_without_a_compiler(tmp_path):
    """CC naming a missing compiler and an empty cache: one warning per library, torch kernels, same values."""
    code = textwrap.dedent("""
        import warnings, torch
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            import torchconn.ops
            from torchconn import io, so3
            from torchconn.ops import curvature, native
            w = torch.randn(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
            R = so3.exp(w.requires_grad_())
            out = so3.log(R).sum() + so3.sqrt(R).sum()
            mesh = io.box(1)
            Re = so3.exp(0.3 * torch.randn(mesh.edges.shape[0], 3, dtype=torch.float64))
            H = curvature.face_curvature(Re, mesh)
            out.backward()
            assert native.library("so3") is None and native.library("curvature") is None
            with torchconn.ops.compiled(False):
                w2 = w.detach().clone().requires_grad_()
                R2 = so3.exp(w2)
                (so3.log(R2).sum() + so3.sqrt(R2).sum()).backward()
                assert torch.equal(curvature.face_curvature(Re, mesh), H)
            assert torch.equal(w.grad, w2.grad)
        msgs = [str(r.message) for r in rec if issubclass(r.category, RuntimeWarning)]
        for lib in ("so3", "curvature"):  # one warning per library, naming it and the compiler
            assert len([m for m in msgs if f"csrc/{lib}.c" in m and "/nonexistent/cc" in m]) == 1, msgs
        print("OK", len(msgs))
    """)
    env = dict(os.environ, CC="/nonexistent/cc", TORCHCONN_CACHE=str(tmp_path / "cache"))
    env.pop("TORCHCONN_NATIVE", None)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith("OK")
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def test_near_pi_and_zero_gradients_finite_on_both_paths():
    w = torch.tensor([[0.0, 0.0, 0.0], [math.pi, 0.0, 0.0], [0.0, 1e-9, 0.0]], dtype=torch.float64)
    for compiled in SWITCH:
        with torchconn.ops.compiled(compiled):
            R = ops_so3.exp(w).requires_grad_()
            (g,) = torch.autograd.grad((ops_so3.log(R).sum() + ops_so3.sqrt(R).sum()), R)
            assert torch.isfinite(g).all()


# ------------------------------------------------------------------------- devices

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                reason="no CUDA device: the generic kernels on CUDA are not tested"))]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kind", ["exp", "log", "sqrt"])
def test_generic_kernels_on_every_device(kind, device):
    x = _input(kind, 64, torch.float64, seed=18)
    G = torch.randn(OPS[kind](x).shape, generator=_gen(19), dtype=torch.float64)
    xd = x.to(device).requires_grad_()
    y = PUBLIC[kind](xd)
    (g,) = torch.autograd.grad((y * G.to(device)).sum(), xd)
    assert y.device.type == device
    with torchconn.ops.compiled(False):
        xr = x.clone().requires_grad_()
        yr = PUBLIC[kind](xr)
        (gr,) = torch.autograd.grad((yr * G).sum(), xr)
    torch.testing.assert_close(y.cpu(), yr.detach(), atol=1e-12, rtol=0)
    torch.testing.assert_close(g.cpu(), gr, atol=1e-11, rtol=0)
    assert gradgradcheck(PUBLIC[kind], (xd[:3].detach().requires_grad_(),))
