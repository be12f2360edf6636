"""The matched-edge-terms custom op (the quality paths' objective) against the op contract.

``torchconn::matched_edge_terms`` (+ ``matched_edge_terms_backward``, ``csrc/edge_terms.c`` on
CPU): opcheck (float32/float64, compiled kernels on and off), the value against a per-edge
autograd loop, gradcheck / gradgradcheck, a Hessian-vector product against central differences,
C against generic, batched and vmapped calls against loops, ``torch.func`` transforms,
``torch.compile``, meta tensors, thread-count independence, errors.
"""
from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_hvp_matches_fd
from torch.autograd import gradcheck, gradgradcheck

import torchconn.ops
from torchconn import io, so3
from torchconn.frames import octahedral
from torchconn.frames.kernels import edge_terms as ops_et

DTYPES = [torch.float32, torch.float64]
SWITCH = [True, False]
FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")


def _field(mesh, batch=(), dtype=torch.float64, seed=0, scale=0.3):
    """A smooth-ish field (small rotations of one frame) and its matchings (index into the group)."""
    V = mesh.vertices.shape[0]
    gen = torch.Generator().manual_seed(seed)
    F0 = so3.exp(torch.randn(3, generator=gen, dtype=torch.float64))
    F = so3.exp(scale * torch.randn(*batch, V, 3, generator=gen, dtype=torch.float64)) @ F0
    idx, _ = octahedral.match_edges(F.reshape(-1, V, 3, 3)[0], mesh.edges)
    return F.to(dtype), idx


@pytest.fixture(scope="module")
def mesh():
    return io.box(1)


def _reference(F, edges, idx, G, weight, s_a, s_d, eps):
    """The plain autograd graph of the same sum, edge by edge (the slow reference), with the op's
    ``d2 = 6 - 2 <F_i g, F_j>`` (``= ||F_i g - F_j||^2`` on rotations; the two differ off SO(3),
    so their gradients in the ambient ``(3, 3)`` entries differ by a normal component)."""
    terms = []
    for k, (i, j) in enumerate(edges.tolist()):
        d2 = 6 - 2 * (F[i] @ G[idx[k]] * F[j]).sum()
        t = s_a * 2 * torch.asin(torch.sqrt(d2 + eps * eps) / (2 * math.sqrt(2))) + s_d * d2
        terms.append(t if weight is None else weight[k] * t)
    return torch.stack(terms).sum()


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("dtype", DTYPES)
def test_opcheck(mesh, dtype, compiled):
    F, idx = _field(mesh, (2,), dtype)
    G = octahedral.group(dtype)
    w = 1.0 + torch.rand(mesh.edges.shape[0], generator=torch.Generator().manual_seed(1), dtype=dtype)
    g = torch.randn(2, generator=torch.Generator().manual_seed(2), dtype=dtype)
    utils = {} if (dtype == torch.float64 and compiled) else {"test_utils": FAST_UTILS}
    with torchconn.ops.compiled(compiled):
        for weight in (None, w):
            torch.library.opcheck(ops_et._edge_terms, (F.clone().requires_grad_(), mesh.edges, idx, G, weight,
                                                       0.7, 1.3, 1e-3), **utils)
            torch.library.opcheck(ops_et._edge_terms_backward,
                                  (g.clone().requires_grad_(), F.clone().requires_grad_(), mesh.edges, idx, G,
                                   weight, 0.7, 1.3, 1e-3), **utils)


@pytest.mark.parametrize("compiled", SWITCH)
def test_value_and_gradient_against_the_edge_loop(compiled):
    m = io.box(1)
    F, idx = _field(m, seed=3)
    G = octahedral.group(torch.float64)
    w = 1.0 + torch.rand(m.edges.shape[0], generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    for weight in (None, w):
        x, y = F.clone().requires_grad_(), F.clone().requires_grad_()
        with torchconn.ops.compiled(compiled):
            a = ops_et.matched_edge_terms(x, m.edges, idx, G, weight, s_a=0.7, s_d=1.3)
        b = _reference(y, m.edges, idx, G, weight, 0.7, 1.3, 1e-3)
        assert float(a.detach()) == pytest.approx(float(b.detach()), rel=1e-12)
        (ga,), (gb,) = torch.autograd.grad(a, x), torch.autograd.grad(b, y)
        torch.testing.assert_close(ga, gb, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
def test_compiled_matches_generic(dtype):
    m = io.box(3)
    F, idx = _field(m, (2,), dtype, seed=5)
    G = octahedral.group(dtype)
    w = 1.0 + torch.rand(m.edges.shape[0], generator=torch.Generator().manual_seed(6), dtype=dtype)
    outs = []
    for compiled in SWITCH:
        x = F.clone().requires_grad_()
        with torchconn.ops.compiled(compiled):
            v = ops_et.matched_edge_terms(x, m.edges, idx, G, w, s_a=0.01, s_d=0.02)
            (g,) = torch.autograd.grad((v * torch.tensor([1.0, -2.0], dtype=dtype)).sum(), x)
        outs.append((v.detach(), g))
    rtol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(outs[0][0], outs[1][0], rtol=rtol, atol=0)
    scale = float(outs[1][1].abs().max())
    torch.testing.assert_close(outs[0][1], outs[1][1], rtol=0, atol=10 * rtol * scale)


@pytest.mark.parametrize("compiled", SWITCH)
def test_gradcheck_gradgradcheck(mesh, compiled):
    F0, idx = _field(mesh, seed=7)
    G = octahedral.group(torch.float64)
    w = (0.2 * torch.randn(F0.shape[0], 3, generator=torch.Generator().manual_seed(8),
                           dtype=torch.float64)).requires_grad_()
    weight = 1.0 + torch.rand(mesh.edges.shape[0], generator=torch.Generator().manual_seed(9), dtype=torch.float64)

    def f(w):
        return ops_et.matched_edge_terms(so3.exp(w) @ F0, mesh.edges, idx, G, weight, s_a=0.7, s_d=1.3)

    with torchconn.ops.compiled(compiled):
        assert gradcheck(f, (w,))
        assert gradgradcheck(f, (w,))


def test_hvp_matches_central_differences(mesh):
    F0, idx = _field(mesh, seed=10)
    G = octahedral.group(torch.float64)
    w = 0.2 * torch.randn(F0.shape[0], 3, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(12), dtype=torch.float64)

    def f(z):
        return ops_et.matched_edge_terms(so3.exp(z) @ F0, mesh.edges, idx, G, s_a=0.7, s_d=1.3)

    assert_hvp_matches_fd(f, w, v)


def test_batched_vmap_and_func_transforms(mesh):
    F, idx = _field(mesh, (3, 2), seed=13)
    G = octahedral.group(torch.float64)

    def f(A):
        return ops_et.matched_edge_terms(A, mesh.edges, idx, G, s_a=0.7, s_d=1.3)

    loop = torch.stack([torch.stack([f(F[i, j]) for j in range(2)]) for i in range(3)])
    torch.testing.assert_close(f(F), loop, atol=1e-13, rtol=0)
    torch.testing.assert_close(torch.func.vmap(f)(F), loop, atol=1e-13, rtol=0)
    torch.testing.assert_close(torch.func.vmap(f, in_dims=1)(F), loop.T, atol=1e-13, rtol=0)
    per = torch.func.vmap(torch.func.grad(f))(F[0])
    ref = torch.stack([torch.func.grad(f)(F[0, j]) for j in range(2)])
    torch.testing.assert_close(per, ref, atol=1e-12, rtol=0)
    t = torch.randn(F[0, 0].shape, generator=torch.Generator().manual_seed(14), dtype=torch.float64)
    _, jv = torch.func.jvp(f, (F[0, 0],), (t,))
    jv_ref = torch.autograd.functional.jvp(lambda A: _reference(A, mesh.edges, idx, G, None, 0.7, 1.3, 1e-3),
                                           F[0, 0], t)[1]
    torch.testing.assert_close(jv, jv_ref, atol=1e-10, rtol=1e-10)


def test_torch_compile_and_meta(mesh):
    F, idx = _field(mesh, (2,), seed=15)
    G = octahedral.group(torch.float64)

    def loss(A):
        return ops_et.matched_edge_terms(A, mesh.edges, idx, G, s_a=0.7, s_d=1.3).sum()

    x = F.clone().requires_grad_()
    val = torch.compile(loss, fullgraph=True, backend="aot_eager")(x)
    (g,) = torch.autograd.grad(val, x)
    (g_ref,) = torch.autograd.grad(loss(x), x)
    torch.testing.assert_close(val, loss(x), atol=1e-12, rtol=0)
    torch.testing.assert_close(g, g_ref, atol=1e-12, rtol=0)
    out = ops_et._edge_terms(F.to("meta"), mesh.edges.to("meta"), idx.to("meta"), G.to("meta"), None, 1.0, 1.0, 1e-3)
    assert out.device.type == "meta" and out.shape == (2,)


def test_backward_thread_count_changes_only_round_off():
    m = io.box(12)
    F, idx = _field(m, seed=16)
    G = octahedral.group(torch.float64)
    g = torch.tensor(1.0, dtype=torch.float64)
    before = torch.get_num_threads()
    try:
        outs = []
        for t in (1, 2, 3):
            torch.set_num_threads(t)
            outs.append(ops_et._edge_terms_backward(g, F, m.edges, idx, G, None, 0.7, 1.3, 1e-3))
    finally:
        torch.set_num_threads(before)
    for o in outs[1:]:
        torch.testing.assert_close(o, outs[0], atol=1e-12, rtol=0)


def test_errors_name_the_problem(mesh):
    F, idx = _field(mesh)
    G = octahedral.group(torch.float64)
    E = mesh.edges
    with pytest.raises(ValueError, match="frames must be"):
        ops_et.matched_edge_terms(F[..., :2], E, idx, G)
    with pytest.raises(ValueError, match="edges must be"):
        ops_et.matched_edge_terms(F, E.int(), idx, G)
    with pytest.raises(ValueError, match="match must be"):
        ops_et.matched_edge_terms(F, E, idx[:-1], G)
    with pytest.raises(ValueError, match="group must be"):
        ops_et.matched_edge_terms(F, E, idx, G.float())
    with pytest.raises(ValueError, match="weight must be"):
        ops_et.matched_edge_terms(F, E, idx, G, torch.ones(3, dtype=torch.float64))
    with torchconn.ops.compiled(True):
        with pytest.raises(ValueError, match="match index outside"):
            ops_et.matched_edge_terms(F, E, torch.full_like(idx, 24), G)
        with pytest.raises(ValueError, match="signed permutation"):
            ops_et.matched_edge_terms(F, E, idx, G * 0.1)


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                reason="no CUDA device: the generic kernel on CUDA is not tested"))]


@pytest.mark.parametrize("device", DEVICES)
def test_generic_kernel_on_every_device(mesh, device):
    F, idx = _field(mesh, (2,), seed=17)
    G = octahedral.group(torch.float64)
    outs = []
    for dev in ("cpu", device):
        x = F.to(dev).requires_grad_()
        with torchconn.ops.compiled(dev != "cpu"):
            v = ops_et.matched_edge_terms(x, mesh.edges.to(dev), idx.to(dev), G.to(dev), s_a=0.7, s_d=1.3)
            (g,) = torch.autograd.grad(v.sum(), x)
        assert v.device.type == dev
        outs.append((v.detach().cpu(), g.cpu()))
    torch.testing.assert_close(outs[0][0], outs[1][0], atol=1e-12, rtol=0)
    torch.testing.assert_close(outs[0][1], outs[1][1], atol=1e-10, rtol=0)
