"""``torchconn::face_curvature_sqnorm`` (:mod:`torchconn.ops.curvature_sqnorm`) per the custom-op
contract, and the modules' ``sqnorm`` (``Curvature.sqnorm``, ``CovariantD.sqnorm``) that use it.

opcheck (with and without the forward's gradient, unbatched and batched, every kind) with the
compiled kernel on and off; the C kernel (a batch of 2, zero weights, every kind) against the
generic kernel, and both against the per-face composition ``Σ_f w_f |H_f|²`` of the curvature op
with autograd; gradcheck and gradgradcheck in float64 (rotations and weights); batched calls,
vmap and forward mode against loops; meta tensors and shape errors; the saved gradient intact
after a backward that keeps the graph (the backward returns it unscaled for an incoming 1).
The modules: ``sqnorm`` equals the reduction of ``forward`` (every kind and variant, frames,
weights, a batch, a cell complex), with gradients; weight errors name the shape.
"""
from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

from torchconn import io, so3
from torchconn.mesh import CellComplex
from torchconn.nn import AveragedCovariantD, CovariantD, Curvature
from torchconn.ops import native
from torchconn.ops import curvature as ops_curv
from torchconn.ops import curvature_sqnorm as ops_csq

from kernel_cases import SWITCH, assert_kernels_agree, switch, two_tets

DT = torch.float64
KINDS = [pytest.param(2, id="cut_c"), pytest.param(1, id="cut_b"), pytest.param(0, id="holonomy")]
_has_c = native.library("curvature") is not None
_FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")
_CUT_KIND = {2: (-1, "two_prong"), 1: (1, "two_prong"), 0: (-1, "holonomy")}


def _switch(on: bool):
    return switch(on, "curvature", "csrc/curvature.c")


_two_tets = two_tets


def _data(mesh, dtype=DT, seed=0, batch=()):
    """Rotations (large angles too) and per-face weights with zeros (skipped faces)."""
    g = torch.Generator().manual_seed(seed)
    E, F = mesh.edges.shape[0], mesh.faces.shape[0]
    R = so3.exp(1.2 * torch.randn(*batch, E, 3, generator=g, dtype=torch.float64))
    w = torch.rand(*batch, F, generator=g, dtype=torch.float64) * (torch.rand(*batch, F, generator=g) > 0.3)
    return R.to(dtype), w.to(dtype)


def _composed(R, w, mesh, kind):
    """The reference: the curvature op's ``(F, 3, 3)`` output squared and weighted in torch."""
    cut, name = _CUT_KIND[kind]
    H = ops_curv.face_curvature(R, mesh, cut=cut, kind=name)
    return (w * H.square().sum((-1, -2))).sum(-1)


def _public(mesh, kind):
    cut, name = _CUT_KIND[kind]
    return lambda A, w: ops_csq.face_curvature_sqnorm(A, mesh, w, cut=cut, kind=name)  # noqa: E731


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck(on, kind, dtype):
    mesh = _two_tets()
    fi, ptr, inc = ops_curv._tables(mesh, "cpu")
    R, w = _data(mesh, dtype)
    w = w + 0.5
    with _switch(on):
        for Rb, wb in ((R, w), (torch.stack((R, R.flip(0))), torch.stack((w, 2 * w)))):
            for with_grad in (True, False):
                torch.library.opcheck(ops_csq._sqnorm_op, (Rb.clone().requires_grad_(), wb.clone().requires_grad_(),
                                                           fi, ptr, inc, kind, with_grad), test_utils=_FAST_UTILS)


@pytest.mark.skipif(not _has_c, reason="no C compiler: csrc/curvature.c cannot be built")
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_equals_generic_and_the_composition(kind, dtype):
    """box(7) (over 2048 faces and edges: several tasks of the C loops), a batch of 2, zero weights."""
    mesh = io.box(7)
    fi, ptr, inc = ops_curv._tables(mesh, "cpu")
    assert fi.shape[1] > 2048 and mesh.edges.shape[0] > 2048
    R, w = _data(mesh, dtype, seed=11, batch=(2,))
    assert bool((w == 0).any()) and bool((w != 0).any())
    value, g = assert_kernels_agree(lambda with_grad: ops_csq._sqnorm_op(R, w, fi, ptr, inc, kind, with_grad), dtype)
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    Rr = R.clone().requires_grad_()
    ref = _composed(Rr, w, mesh, kind)
    (g_ref,) = torch.autograd.grad(ref.sum(), Rr)
    torch.testing.assert_close(value, ref.detach(), atol=tol * float(ref.abs().max()), rtol=0)
    torch.testing.assert_close(g, g_ref, atol=tol * max(1.0, float(g_ref.abs().max())), rtol=0)


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("kind", KINDS)
def test_public_function_matches_the_composition_with_gradients(on, kind):
    mesh = io.box(2)
    R, w = _data(mesh, seed=3)
    with _switch(on):
        out = []
        for fn in (_public(mesh, kind), lambda A, c: _composed(A, c, mesh, kind)):
            Rr, wr = R.clone().requires_grad_(), w.clone().requires_grad_()
            v = fn(Rr, wr)
            out.append((v.detach(), *torch.autograd.grad(3.0 * v, (Rr, wr))))
    for a, b in zip(*out):
        torch.testing.assert_close(a, b, atol=1e-12 * max(1.0, float(b.abs().max())), rtol=0)


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("kind", KINDS)
def test_gradcheck_and_gradgradcheck(on, kind):
    mesh = _two_tets()
    R, w = _data(mesh, seed=5)
    w = w + 0.5
    f = _public(mesh, kind)
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        assert gradcheck(f, rg(R, w))
        assert gradgradcheck(f, rg(R, w), fast_mode=True)
        # the incoming gradient depends on the input: no path counted twice
        assert gradgradcheck(lambda A: f(A, w).square(), rg(R), fast_mode=True)


@pytest.mark.parametrize("on", SWITCH)
def test_batch_vmap_and_forward_mode_match_loops(on):
    mesh = _two_tets()
    R, w = _data(mesh, seed=7, batch=(3,))
    f = _public(mesh, 2)
    with _switch(on):
        loop = torch.stack([f(R[b], w[b]) for b in range(3)])
        torch.testing.assert_close(f(R, w), loop, atol=1e-13, rtol=0)
        torch.testing.assert_close(torch.func.vmap(f)(R, w), loop, atol=1e-13, rtol=0)
        g = torch.func.vmap(torch.func.grad(f, argnums=(0, 1)))(R, w)
        for b in range(3):
            Rb, wb = R[b].clone().requires_grad_(), w[b].clone().requires_grad_()
            ref = torch.autograd.grad(f(Rb, wb), (Rb, wb))
            for a, r in zip(g, ref):
                torch.testing.assert_close(a[b], r, atol=1e-12, rtol=0)
        ts = [torch.randn(x.shape, generator=torch.Generator().manual_seed(9), dtype=DT) for x in (R[0], w[0])]
        _, jv = torch.func.jvp(f, (R[0], w[0]), tuple(ts))
        xs = [x[0].clone().requires_grad_() for x in (R, w)]
        gs = torch.autograd.grad(f(*xs), xs)
        torch.testing.assert_close(jv, sum((g_ * t_).sum() for g_, t_ in zip(gs, ts)), atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("on", SWITCH)
def test_saved_gradient_survives_a_second_backward(on):
    """The first-order backward hands out the forward's gradient itself when the incoming gradient
    is 1 (``ops._library.scale_saved``): a graph kept for a second backward gives the same gradient,
    also when autograd accumulates it with another path's."""
    mesh = io.box(2)
    R, w = _data(mesh, seed=13)
    f = _public(mesh, 2)
    with _switch(on):
        Rr = R.clone().requires_grad_()
        loss = f(Rr, w) + (Rr * Rr).sum()  # a second path into Rr: autograd sums the two
        first = torch.autograd.grad(loss, Rr, retain_graph=True)[0].clone()
        second = torch.autograd.grad(loss, Rr)[0]
        torch.testing.assert_close(first, second, atol=0, rtol=0)
        x = Rr.detach().clone().requires_grad_()
        (2.0 * f(x, w)).backward()  # an incoming 2: scaled
        torch.testing.assert_close(x.grad, 2.0 * first - 4.0 * Rr.detach(), atol=1e-12, rtol=0)


def test_meta_and_shape_errors():
    mesh = _two_tets()
    R, w = _data(mesh)
    meta = mesh.to(device="meta")
    out = ops_csq.face_curvature_sqnorm(R.to("meta").requires_grad_(), meta, w.to("meta"))
    assert out.device.type == "meta" and out.shape == ()
    with pytest.raises(ValueError, match="weight must have shape"):
        ops_csq.face_curvature_sqnorm(R, mesh, w[:-1])
    with pytest.raises(ValueError, match="edge_rot must have shape"):
        ops_csq.face_curvature_sqnorm(R[:-1], mesh, w)
    assert ops_csq.face_curvature_sqnorm(R, mesh, w, cut=0.5) is None  # not an integer cut


# ----------------------------------------------------------------------------- the modules' sqnorm

def _reduce(module, R, *args, weight=None):
    out = module(R, *args)
    per = out.square().sum((-1, -2)) if isinstance(module, Curvature) else out.square().sum(-1)
    return (per if weight is None else weight * per).sum(-1)


@pytest.mark.parametrize("on", SWITCH)
def test_module_sqnorm_equals_the_reduction_of_forward(on):
    mesh = io.box(2)
    E, V, F, T = mesh.edges.shape[0], mesh.n_vertices, mesh.faces.shape[0], mesh.tets.shape[0]
    g = torch.Generator().manual_seed(21)
    R0 = so3.exp(0.8 * torch.randn(2, E, 3, generator=g, dtype=DT))
    frames = so3.exp(0.6 * torch.randn(V, 3, generator=g, dtype=DT))
    wf, wt = torch.rand(F, generator=g, dtype=DT), torch.rand(2, T, generator=g, dtype=DT)
    cases = [(Curvature(mesh), (), None), (Curvature(mesh, cut=1), (), wf), (Curvature(mesh, kind="holonomy"), (), wf),
             (AveragedCovariantD(mesh), (), None), (AveragedCovariantD(mesh), (frames,), wt),
             (CovariantD(mesh, "wedge"), (frames,), wt), (CovariantD(mesh, "behs21"), (), None)]
    with _switch(on):
        for module, args, weight in cases:
            got = []
            for fn in (lambda A: module.sqnorm(A, *args, weight=weight), lambda A: _reduce(module, A, *args, weight=weight)):
                Rr = R0.clone().requires_grad_()
                v = fn(Rr)
                got.append((v.detach(), torch.autograd.grad(v.sum(), Rr)[0]))
            assert got[0][0].shape == (2,)
            for a, b in zip(*got):
                torch.testing.assert_close(a, b, atol=1e-12 * max(1.0, float(b.abs().max())), rtol=0,
                                           msg=lambda m: f"{module}: {m}")


def test_module_sqnorm_on_a_cell_complex_and_weight_errors():
    cc = CellComplex(torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.]], dtype=DT), [[0, 1, 2, 3]])
    curv = Curvature(cc)
    R = so3.exp(0.4 * torch.randn(cc.edges.shape[0], 3, generator=torch.Generator().manual_seed(2), dtype=DT))
    torch.testing.assert_close(curv.sqnorm(R), _reduce(curv, R), atol=1e-14, rtol=0)
    torch.testing.assert_close(curv.sqnorm(R, weight=torch.tensor([2.0], dtype=DT)), 2 * _reduce(curv, R),
                               atol=1e-14, rtol=0)
    mesh = _two_tets()
    R, _ = _data(mesh)
    with pytest.raises(ValueError, match=r"Curvature.sqnorm: weight must have shape \(7,\)"):
        Curvature(mesh).sqnorm(R, weight=torch.ones(3, dtype=DT))
    with pytest.raises(ValueError, match=r"AveragedCovariantD.sqnorm: weight must have shape \(2,\)"):
        AveragedCovariantD(mesh).sqnorm(R, weight=torch.ones(3, dtype=DT))
    with pytest.raises(TypeError, match="weight must be None or a floating-point tensor"):
        AveragedCovariantD(mesh).sqnorm(R, weight=torch.ones(2, dtype=torch.int64))
