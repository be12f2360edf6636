"""The face-curvature and √R-torsion custom ops against the op contract of issue 11.

``torchconn::face_curvature`` (+ ``face_curvature_backward``, ``csrc/curvature.c`` on CPU) and
``torchconn::face_torsion_sqrt`` (+ backward; C kernel csrc/torsion.c): opcheck (float32/float64, compiled kernels on
and off), gradcheck / gradgradcheck through the public functions, a Hessian-vector product
against central differences, vmap and batched calls against loops, ``torch.compile``, meta
tensors, the generic loop formula of ``dec`` as reference, the CSR backward independent of the
thread count.
"""
from __future__ import annotations

import pytest
import torch
from conftest import assert_hvp_matches_fd
from torch.autograd import gradcheck, gradgradcheck

import torchconn.ops
from torchconn import io, so3
from torchconn.dec import curvature as dec_curvature
from torchconn.ops import curvature as ops_curvature
from torchconn.ops import native
from torchconn.ops import torsion as ops_torsion

DTYPES = [torch.float32, torch.float64]
SWITCH = [True, False]
CUTS = [(-1, "two_prong"), (1, "two_prong"), (0, "holonomy")]
FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")
OPCHECK_CASES = [pytest.param(dt, on, marks=() if (dt == torch.float64 and on) else pytest.mark.slow)
                 for dt in DTYPES for on in SWITCH]


@pytest.fixture(scope="module")
def mesh():
    return io.box(1)


def _rot(mesh, batch=(), dtype=torch.float64, seed=0, scale=0.8):
    E = mesh.edges.shape[0]
    w = scale * torch.randn(*batch, E, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return so3.exp(w).to(dtype)


def _on(compiled, fn):
    def call(*a):
        with torchconn.ops.compiled(compiled):
            return fn(*a)
    return call


def _generic_loop(R, mesh, cut, kind):
    """dec's loop formula (orient + two_prong / holonomy), the reference of the op."""
    F, groups = dec_curvature.face_loops(mesh)
    (_, le, ls, _), = groups
    L = dec_curvature.orient(R, le, ls)
    return dec_curvature.holonomy(L) if kind == "holonomy" else dec_curvature.two_prong(L, cut)


# ------------------------------------------------------------------------- curvature: opcheck


def _curv_args(mesh, dtype, kind):
    fi, ptr, inc = ops_curvature._tables(mesh, "cpu")
    R = _rot(mesh, (2,), dtype, seed=1)
    return R, fi, ptr, inc


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", [0, 1, 2])
def test_curvature_opcheck_schema_autograd_fake(mesh, kind, dtype, compiled):
    R, fi, ptr, inc = _curv_args(mesh, dtype, kind)
    G = torch.randn(2, fi.shape[1], 3, 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(ops_curvature._face_curvature, (R.requires_grad_(), fi, ptr, inc, kind),
                              test_utils=FAST_UTILS)
        torch.library.opcheck(ops_curvature._face_curvature_backward,
                              (R.detach().requires_grad_(), G.requires_grad_(), fi, ptr, inc, kind),
                              test_utils=FAST_UTILS)


@pytest.mark.parametrize("dtype,compiled", OPCHECK_CASES)
def test_curvature_opcheck_full(mesh, dtype, compiled):
    R, fi, ptr, inc = _curv_args(mesh, dtype, 0)
    G = torch.randn(2, fi.shape[1], 3, 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(ops_curvature._face_curvature, (R.requires_grad_(), fi, ptr, inc, 0))
        torch.library.opcheck(ops_curvature._face_curvature_backward,
                              (R.detach().requires_grad_(), G.requires_grad_(), fi, ptr, inc, 2))


# ------------------------------------------------------------------------- curvature: values, grads


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("cut,kind", CUTS)
def test_curvature_switch_on_off_and_generic_loop(mesh, cut, kind, dtype):
    R = _rot(io.box(2), (2,), dtype, seed=3)
    m = io.box(2)
    outs = []
    for compiled in SWITCH:
        x = R.clone().requires_grad_()
        H = _on(compiled, ops_curvature.face_curvature)(x, m, cut, kind)
        G = torch.randn(H.shape, generator=torch.Generator().manual_seed(4), dtype=dtype)
        (g,) = torch.autograd.grad((H * G).sum(), x)
        outs.append((H.detach(), g))
    tol = 1e-5 if dtype == torch.float32 else 1e-13
    torch.testing.assert_close(outs[0][0], outs[1][0], atol=tol, rtol=0)
    torch.testing.assert_close(outs[0][1], outs[1][1], atol=10 * tol, rtol=0)
    ref = torch.stack([_generic_loop(R[i], m, cut, kind) for i in range(2)])
    torch.testing.assert_close(outs[0][0], ref, atol=tol, rtol=0)


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("cut,kind", CUTS)
def test_curvature_gradcheck_gradgradcheck(mesh, cut, kind, compiled):
    R = _rot(mesh, (2,), seed=5).requires_grad_()
    f = lambda A: ops_curvature.face_curvature(A, mesh, cut, kind)  # noqa: E731
    with torchconn.ops.compiled(compiled):
        assert gradcheck(f, (R,))
        assert gradgradcheck(lambda A: f(A).square(), (R,), fast_mode=True)


@pytest.mark.parametrize("compiled", SWITCH)
def test_curvature_hvp_matches_central_differences(mesh, compiled):
    w = 0.5 * torch.randn(2, mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)

    def f(w):
        return ops_curvature.face_curvature(so3.exp(w), mesh, 0, "holonomy").square().sum()

    with torchconn.ops.compiled(compiled):
        assert_hvp_matches_fd(f, w, v)


def test_curvature_vmap_batched_and_loop(mesh):
    R = _rot(mesh, (3, 2), seed=8)
    loop = torch.stack([torch.stack([ops_curvature.face_curvature(R[i, j], mesh) for j in range(2)]) for i in range(3)])
    torch.testing.assert_close(ops_curvature.face_curvature(R, mesh), loop, atol=1e-14, rtol=0)
    vm = torch.func.vmap(lambda A: ops_curvature.face_curvature(A, mesh))(R)
    torch.testing.assert_close(vm, loop, atol=1e-14, rtol=0)
    vm1 = torch.func.vmap(lambda A: ops_curvature.face_curvature(A, mesh), in_dims=1)(R)
    torch.testing.assert_close(vm1, loop.movedim(1, 0), atol=1e-14, rtol=0)
    # per-sample gradients and the torch.func transforms
    f = lambda A: ops_curvature.face_curvature(A, mesh, 0, "holonomy").square().sum()  # noqa: E731
    per = torch.func.vmap(torch.func.grad(f))(R[0])
    ref = torch.stack([torch.func.grad(f)(R[0, j]) for j in range(2)])
    torch.testing.assert_close(per, ref, atol=1e-13, rtol=0)
    t = torch.randn(R[0, 0].shape, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    _, jv = torch.func.jvp(lambda A: ops_curvature.face_curvature(A, mesh), (R[0, 0],), (t,))
    jv_ref = torch.autograd.functional.jvp(lambda A: _generic_loop(A, mesh, -1, "two_prong"), R[0, 0], t)[1]
    torch.testing.assert_close(jv, jv_ref, atol=1e-13, rtol=0)


def test_curvature_other_rank_batched(mesh):
    R = torch.randn(2, mesh.edges.shape[0], 2, 2, generator=torch.Generator().manual_seed(10), dtype=torch.float64)
    out = ops_curvature.face_curvature(R, mesh)
    torch.testing.assert_close(out, torch.stack([ops_curvature.face_curvature(R[i], mesh) for i in range(2)]))


def test_curvature_backward_thread_independent():
    m = io.box(20)  # 48k tets, 101k faces, 59k edges: above the C code's parallel threshold (32768)
    R = _rot(m, (), torch.float32, seed=11)
    fi, ptr, inc = ops_curvature._tables(m, "cpu")
    G = torch.randn(fi.shape[1], 3, 3, generator=torch.Generator().manual_seed(12))
    before = torch.get_num_threads()
    try:
        outs = []
        for t in (1, 2):
            torch.set_num_threads(t)
            outs.append(ops_curvature._face_curvature_backward(R, G, fi, ptr, inc, 0))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(outs[0], outs[1])


def test_curvature_meta_and_bad_shape(mesh):
    R = _rot(mesh, (2,)).to("meta")
    # tables on meta come from the mesh's (CPU) tables: shapes only
    out = ops_curvature._face_curvature(R, *(t.to("meta") for t in ops_curvature._tables(mesh, "cpu")), 2)
    assert out.device.type == "meta" and out.shape == (2, mesh.face_edges.shape[0], 3, 3)
    assert ops_curvature.face_curvature(R, mesh).shape == out.shape
    with pytest.raises(ValueError, match="edge_rot must have shape"):
        ops_curvature.face_curvature(torch.zeros(3, 3, 3), mesh)


def test_curvature_torch_compile_fullgraph(mesh):
    w = (0.4 * torch.randn(2, mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(13),
                           dtype=torch.float64)).requires_grad_()

    def loss(w):
        R = so3.exp(w)
        return (ops_curvature.face_curvature(R, mesh).square().sum()
                + ops_torsion.face_torsion(R, mesh).square().sum())

    compiled = torch.compile(loss, fullgraph=True, backend="aot_eager")
    val = compiled(w)
    (g,) = torch.autograd.grad(val, w)
    (g_ref,) = torch.autograd.grad(loss(w), w)
    torch.testing.assert_close(val, loss(w), atol=1e-12, rtol=0)
    torch.testing.assert_close(g, g_ref, atol=1e-12, rtol=0)


def test_torch_compile_on_an_old_torch_names_the_version(mesh, monkeypatch):
    """Where this torch's dynamo cannot take the mesh's tables as constants (torch 2.11), tracing
    stops with a message naming the version needed, not dynamo's internal error."""
    from torchconn.ops import _cache

    monkeypatch.setattr(_cache, "COMPILE_SUPPORTED", False)
    w = torch.randn(mesh.edges.shape[0], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    compiled = torch.compile(lambda w: ops_curvature.face_curvature(so3.exp(w), mesh).sum(), fullgraph=True,
                             backend="eager")
    with pytest.raises(Exception, match=r"torch.compile needs torch >= 2\.13"):
        compiled(w)
    assert _cache.COMPILE_SUPPORTED is False and ops_curvature.face_curvature(so3.exp(w), mesh).isfinite().all()


# ------------------------------------------------------------------------- √R torsion


def _tor_args(mesh, dtype):
    fi, inc_ptr, inc = ops_curvature._tables(mesh, "cpu")
    vec = ops_torsion._edge_vectors(mesh, "cpu", dtype)
    return _rot(mesh, (2,), dtype, seed=14, scale=1.2), vec, (fi, inc_ptr, inc)


@pytest.mark.parametrize("full", [False, pytest.param(True, marks=pytest.mark.slow)])  # full: ~30 s
@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("dtype", DTYPES)
def test_torsion_opcheck(mesh, dtype, compiled, full):
    R, vec, tabs = _tor_args(mesh, dtype)
    G = torch.randn(2, tabs[0].shape[1], 3, generator=torch.Generator().manual_seed(15), dtype=dtype)
    utils = {} if full else {"test_utils": FAST_UTILS}
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(ops_torsion._face_torsion_sqrt, (R.requires_grad_(), vec.requires_grad_(), *tabs), **utils)
        torch.library.opcheck(ops_torsion._face_torsion_sqrt_backward,
                              (R.detach().requires_grad_(), vec.detach(), *tabs, G.requires_grad_()), **utils)


@pytest.mark.parametrize("compiled", SWITCH)
def test_torsion_values_grads_and_higher_order(mesh, compiled):
    R, vec, tabs = _tor_args(mesh, torch.float64)
    with torchconn.ops.compiled(compiled):
        out = ops_torsion.face_torsion(R, mesh)
        # the previous composition (per-edge root, then gathers), per batch element
        ref = torch.stack([ops_torsion._combine(R[i], (so3.sqrt(R[i]) @ vec.unsqueeze(-1)).squeeze(-1), tabs[0])
                           for i in range(2)])
        torch.testing.assert_close(out, ref, atol=1e-13, rtol=0)
        x, v = R.clone().requires_grad_(), vec.clone().requires_grad_()
        f = lambda A, e: ops_torsion.face_torsion_sqrt(A, e, *tabs)  # noqa: E731
        assert gradcheck(f, (x, v))
        assert gradgradcheck(lambda A, e: f(A, e).square(), (x, v), fast_mode=True)
    on_off = []
    for c in SWITCH:
        x = R.clone().requires_grad_()
        with torchconn.ops.compiled(c):
            (g,) = torch.autograd.grad(ops_torsion.face_torsion(x, mesh).square().sum(), x)
        on_off.append(g)
    torch.testing.assert_close(on_off[0], on_off[1], atol=1e-12, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("scale", [0.3, 2.8])
def test_torsion_compiled_kernel_equals_generic(dtype, scale):
    """csrc/torsion.c (roots per edge, faces, the edge-wise backward over the incidence table) against
    the generic kernels, both ops, a batch of 2; scale 2.8: most angles above 120° (the roots'
    log/exp branch)."""
    if native.library("torsion") is None:
        pytest.skip("no C compiler: csrc/torsion.c cannot be built")
    m = io.box(3)
    R = _rot(m, (2,), dtype, seed=21, scale=scale)
    vec = torch.randn(m.edges.shape[0], 3, generator=torch.Generator().manual_seed(22), dtype=torch.float64).to(dtype)
    tabs = ops_curvature._tables(m, "cpu")
    G = torch.randn(2, tabs[0].shape[1], 3, generator=torch.Generator().manual_seed(23), dtype=torch.float64).to(dtype)
    res = {}
    for on in (True, False):
        with torchconn.ops.compiled(on):
            res[on] = (ops_torsion._face_torsion_sqrt(R, vec, *tabs),
                       *ops_torsion._face_torsion_sqrt_backward(R, vec, *tabs, G))
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    for a, b in zip(res[True], res[False]):
        torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0)


def test_torsion_vmap_batched_and_hvp(mesh):
    R, vec, _ = _tor_args(mesh, torch.float64)
    loop = torch.stack([ops_torsion.face_torsion(R[i], mesh) for i in range(2)])
    torch.testing.assert_close(ops_torsion.face_torsion(R, mesh), loop, atol=1e-14, rtol=0)
    torch.testing.assert_close(torch.func.vmap(lambda A: ops_torsion.face_torsion(A, mesh))(R), loop,
                               atol=1e-14, rtol=0)
    w = 0.5 * torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(16), dtype=torch.float64)
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(17), dtype=torch.float64)
    f = lambda z: ops_torsion.face_torsion(so3.exp(z), mesh).square().sum()  # noqa: E731
    assert_hvp_matches_fd(f, w, v)
    per = torch.func.vmap(torch.func.grad(lambda A: ops_torsion.face_torsion(A, mesh).square().sum()))(R)
    ref = torch.stack([torch.func.grad(lambda A: ops_torsion.face_torsion(A, mesh).square().sum())(R[i])
                       for i in range(2)])
    torch.testing.assert_close(per, ref, atol=1e-12, rtol=0)


def test_torsion_meta(mesh):
    R = _rot(mesh, (2,)).to("meta")
    out = ops_torsion._face_torsion_sqrt(R, torch.empty(mesh.edges.shape[0], 3, device="meta"),
                                         *(t.to("meta") for t in ops_curvature._tables(mesh, "cpu")))
    assert out.shape == (2, mesh.face_edges.shape[0], 3) and out.device.type == "meta"


# ------------------------------------------------------------------------- devices

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                reason="no CUDA device: the generic kernels on CUDA are not tested"))]


@pytest.mark.parametrize("device", DEVICES)
def test_generic_kernels_on_every_device(mesh, device):
    R = _rot(mesh, (2,), seed=20)
    outs = []
    for dev in ("cpu", device):
        x = R.to(dev).requires_grad_()
        with torchconn.ops.compiled(dev != "cpu"):
            H = ops_curvature.face_curvature(x, mesh, 0, "holonomy")
            T = ops_torsion.face_torsion(x, mesh)
            (g,) = torch.autograd.grad(H.square().sum() + T.square().sum(), x)
        assert H.device.type == dev and T.device.type == dev
        outs.append((H.detach().cpu(), T.detach().cpu(), g.cpu()))
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    x = R[0].to(device).requires_grad_()
    # off the CPU the generic backward scatters with index_add_ (atomic adds: summation order
    # varies between runs), so repeated backwards agree to round-off, not bit for bit
    nondet = 0.0 if device == "cpu" else 1e-12
    assert gradgradcheck(lambda A: ops_curvature.face_curvature(A, mesh).square(), (x,), fast_mode=True,
                         nondet_tol=nondet)
