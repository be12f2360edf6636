"""``torchconn::tet_dd_frames_sqnorm`` (:mod:`torchconn.ops.tet_sqnorm`) per the custom-op contract.

opcheck (with and without the forward's gradient, unbatched and batched) with the compiled
kernel on and off; the C kernel (colored chunks of 5 tets, a batch of 2, relabeled edges, zero
weights) against the generic kernel, and both against the per-tet composition
``Σ_t w_t |tet_dd_frames_t|²`` with autograd; gradcheck and gradgradcheck in float64 (in the
rotations, the frames and the weights); batched calls and vmap against loops; meta tensors and
shape errors. The loss term that uses it against its modules: ``tests/test_losses.py``.
"""
from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

from torchconn import io, so3
from torchconn.ops import native
from torchconn.ops import tet as ops_tet
from torchconn.ops import tet_solder as ops_tet_solder
from torchconn.ops import tet_sqnorm as ops_sqn
from torchconn.ops._cache import edge_index, edge_vectors

from kernel_cases import SWITCH, assert_kernels_agree, switch, two_tets

DT = torch.float64
_has_c = native.library("tet") is not None
_FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")


def _switch(on: bool):
    return switch(on, "tet", "csrc/tet.c")


_two_tets = two_tets


def _data(mesh, dtype=DT, seed=0, batch=(), relabel=True):
    """Rotations near the octahedral group (quarter and half turns: the roots' large-angle branches),
    frames, and weights with zeros (skipped tets)."""
    from torchconn.frames import octahedral

    g = torch.Generator().manual_seed(seed)
    E, V, T = mesh.edges.shape[0], mesh.n_vertices, mesh.tets.shape[0]
    R = so3.exp(0.3 * torch.randn(*batch, E, 3, generator=g, dtype=torch.float64))
    if relabel:
        R = R @ octahedral.group(torch.float64)[torch.randint(0, 24, (*batch, E), generator=g)]
    F = so3.exp(0.6 * torch.randn(*batch, V, 3, generator=g, dtype=torch.float64))
    w = torch.rand(*batch, T, generator=g, dtype=torch.float64) * (torch.rand(*batch, T, generator=g) > 0.3)
    return R.to(dtype), F.to(dtype), w.to(dtype)


def _composed(R, F, w, mesh):
    """The reference: the (T, 3) output of ``tet_dd_frames`` squared and weighted in torch."""
    k = ops_tet.tet_kernel(mesh)
    dd = ops_tet_solder.tet_dd_frames(R, F, edge_vectors(mesh, "cpu", R.dtype), edge_index(mesh, "cpu"), k)
    return (w * (dd * dd).sum(-1)).sum(-1)


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck(on, dtype):
    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, F, w = _data(mesh, dtype)
    w = w + 0.5  # both tets weighted
    vec, e = edge_vectors(mesh, "cpu", dtype), edge_index(mesh, "cpu")
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        for Rb, Fb, wb in ((R, F, w), (torch.stack((R, R.flip(0))), torch.stack((F, F)), torch.stack((w, 2 * w)))):
            for with_grad in (True, False):
                torch.library.opcheck(ops_sqn._sqnorm_op, (*rg(Rb, Fb), vec, e, wb, *k.tables(), with_grad),
                                      test_utils=_FAST_UTILS)


@pytest.mark.skipif(not _has_c, reason="no C compiler: csrc/tet.c cannot be built")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_equals_generic_and_the_composition(dtype):
    """Chunks of 5 tets (many colors), a batch of 2, zero weights: value and the forward's gradients."""
    mesh = io.box(3)
    k = ops_tet.TetKernel(mesh, chunk=5)
    assert k.n_colors > 4
    R, F, w = _data(mesh, dtype, seed=11, batch=(2,))
    assert bool((w == 0).any()) and bool((w != 0).any())
    vec, e = edge_vectors(mesh, "cpu", dtype), edge_index(mesh, "cpu")
    value, g_rot, g_fr = assert_kernels_agree(
        lambda with_grad: ops_sqn._sqnorm_op(R, F, vec, e, w, *k.tables(), with_grad), dtype)
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    Rr, Fr = R.clone().requires_grad_(), F.clone().requires_grad_()
    ref = _composed(Rr, Fr, w, mesh)
    g_ref = torch.autograd.grad(ref.sum(), (Rr, Fr))
    ref = ref.detach()
    torch.testing.assert_close(value, ref, atol=tol * float(ref.abs().max()), rtol=0)
    for a, b in zip((g_rot, g_fr), g_ref):
        torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0)


@pytest.mark.parametrize("on", SWITCH)
def test_public_function_matches_the_composition_with_gradients(on):
    mesh = io.box(2)
    R, F, w = _data(mesh, seed=3)
    with _switch(on):
        out = []
        for fn in (lambda A, B, c: ops_sqn.tet_dd_frames_sqnorm(A, B, c, mesh),
                   lambda A, B, c: _composed(A, B, c, mesh)):
            Rr, Fr, wr = R.clone().requires_grad_(), F.clone().requires_grad_(), w.clone().requires_grad_()
            v = fn(Rr, Fr, wr)
            out.append((v.detach(), *torch.autograd.grad(3.0 * v, (Rr, Fr, wr))))
    for a, b in zip(*out):
        torch.testing.assert_close(a, b, atol=1e-12 * max(1.0, float(b.abs().max())), rtol=0)


@pytest.mark.parametrize("on", SWITCH)
def test_gradcheck_and_gradgradcheck(on):
    mesh = _two_tets()
    R, F, w = _data(mesh, seed=5)
    w = w + 0.5
    f = lambda A, B, c: ops_sqn.tet_dd_frames_sqnorm(A, B, c, mesh)  # noqa: E731
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        assert gradcheck(f, rg(R, F, w))
        assert gradgradcheck(f, rg(R, F, w), fast_mode=True)
        # the incoming gradient depends on the input: no path counted twice
        assert gradgradcheck(lambda A, B: f(A, B, w).square(), rg(R, F), fast_mode=True)


@pytest.mark.parametrize("on", SWITCH)
def test_batch_and_vmap_match_loops(on):
    mesh = _two_tets()
    R, F, w = _data(mesh, seed=7, batch=(3,))
    f = lambda A, B, c: ops_sqn.tet_dd_frames_sqnorm(A, B, c, mesh)  # noqa: E731
    with _switch(on):
        loop = torch.stack([f(R[b], F[b], w[b]) for b in range(3)])
        torch.testing.assert_close(f(R, F, w), loop, atol=1e-13, rtol=0)
        torch.testing.assert_close(torch.func.vmap(f)(R, F, w), loop, atol=1e-13, rtol=0)
        g = torch.func.vmap(torch.func.grad(f, argnums=(0, 1)))(R, F, w)
        for b in range(3):
            Rb, Fb = R[b].clone().requires_grad_(), F[b].clone().requires_grad_()
            ref = torch.autograd.grad(f(Rb, Fb, w[b]), (Rb, Fb))
            for a, r in zip(g, ref):
                torch.testing.assert_close(a[b], r, atol=1e-12, rtol=0)
        # forward mode: the directional derivative equals the gradient's inner product
        ts = [torch.randn(x.shape, generator=torch.Generator().manual_seed(9), dtype=DT) for x in (R[0], F[0], w[0])]
        _, jv = torch.func.jvp(f, (R[0], F[0], w[0]), tuple(ts))
        xs = [x[0].clone().requires_grad_() for x in (R, F, w)]
        gs = torch.autograd.grad(f(*xs), xs)
        torch.testing.assert_close(jv, sum((g_ * t_).sum() for g_, t_ in zip(gs, ts)), atol=1e-12, rtol=1e-12)


def test_meta_and_shape_errors():
    mesh = _two_tets()
    R, F, w = _data(mesh)
    meta = mesh.to(device="meta")
    out = ops_sqn.tet_dd_frames_sqnorm(R.to("meta").requires_grad_(), F.to("meta"), w.to("meta"), meta)
    assert out.device.type == "meta" and out.shape == ()
    with pytest.raises(ValueError, match="frames must have shape"):
        ops_sqn.tet_dd_frames_sqnorm(R, torch.stack((F, F)), w, mesh)
    with pytest.raises(ValueError, match="weight must have shape"):
        ops_sqn.tet_dd_frames_sqnorm(R, F, w[:-1], mesh)
    with pytest.raises(ValueError, match="edge_rot must have shape"):
        ops_sqn.tet_dd_frames_sqnorm(R[:-1], F, w, mesh)


@pytest.mark.parametrize("on", SWITCH)
def test_without_frames_is_the_global_frame(on):
    """``frames=None`` (rows-free frames ``(*B, 0, 3, 3)`` at the op): the composition with
    ``tet_dd_rot`` (``θ̃ = √R v``) and the identity frames, values and gradients; chunks of 5 tets,
    a batch of 2, zero weights; opcheck; gradcheck and gradgradcheck."""
    mesh = io.box(3)
    k = ops_tet.TetKernel(mesh, chunk=5)
    R, _, w = _data(mesh, seed=17, batch=(2,))
    vec, e = edge_vectors(mesh, "cpu", DT), edge_index(mesh, "cpu")
    eye = torch.eye(3, dtype=DT).expand(2, mesh.n_vertices, 3, 3)
    with _switch(on):
        got = []
        for fn in (lambda A: ops_sqn.tet_dd_frames_sqnorm(A, None, w, mesh),
                   lambda A: ops_sqn.tet_dd_frames_sqnorm(A, eye, w, mesh),
                   lambda A: (w * ops_tet_solder.tet_dd_rot(A, vec, k).square().sum(-1)).sum(-1)):
            Rr = R.clone().requires_grad_()
            v = fn(Rr)
            got.append((v.detach(), torch.autograd.grad(v.sum(), Rr)[0]))
        for other in got[1:]:
            for a, b in zip(got[0], other):
                torch.testing.assert_close(a, b, atol=1e-12 * max(1.0, float(b.abs().max())), rtol=0)
        none = R.new_empty(2, 0, 3, 3)
        for with_grad in (True, False):
            torch.library.opcheck(ops_sqn._sqnorm_op, (R.clone().requires_grad_(), none, vec, e, w, *k.tables(),
                                                       with_grad), test_utils=_FAST_UTILS)
        small = _two_tets()
        Rs, _, ws = _data(small, seed=19)
        f = lambda A, c: ops_sqn.tet_dd_frames_sqnorm(A, None, c, small)  # noqa: E731
        args = (Rs.clone().requires_grad_(), (ws + 0.5).requires_grad_())
        assert gradcheck(f, args)
        assert gradgradcheck(f, args, fast_mode=True)
