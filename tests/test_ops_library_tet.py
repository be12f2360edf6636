"""The averaged d∇d∇θ tet op ``torchconn::tet_dd`` (and ``tet_dd_backward``) per the custom-op contract.

opcheck in float32 and float64 with the compiled kernels on and off; gradcheck and gradgradcheck
in float64 through the public functions, switch on and off; a Hessian-vector product against
central differences of the gradient; batched calls and vmap against per-item loops; the C
backward's colored-chunk schedule (many colors) against the generic kernel; meta tensors;
``torch.compile(fullgraph=True)``; ``torch.func`` (grad, vmap of grad, jacrev, jacfwd, jvp) over
the three public functions against autograd, and the tables built first inside a transform or
a compile trace. (The modules under every transform: ``tests/test_transform_matrix.py``.)
"""
from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

from torchconn import dnabla, io, so3
from torchconn.ops import compiled, native
from torchconn.ops import tet as ops_tet
from torchconn.ops import tet_solder as ops_tet_solder

from kernel_cases import SWITCH, switch, two_tets

DT = torch.float64
_has_c = native.library("tet") is not None


def _switch(on: bool):
    return switch(on, "tet", "csrc/tet.c")


_two_tets = two_tets


def _data(mesh, dtype=DT, seed=0, batch=()):
    g = torch.Generator().manual_seed(seed)
    E = mesh.edges.shape[0]
    R = so3.exp(0.7 * torch.randn(*batch, E, 3, generator=g, dtype=torch.float64)).to(dtype)
    th = torch.randn(*batch, E, 2, 3, generator=g, dtype=torch.float64).to(dtype)
    return R, th


def _per_tet_reference(R, th, k):
    """Slow reference: per-tet gathers with plain indexing and the bmm formula (autograd)."""
    both = torch.stack((R, R.transpose(-1, -2)), -3).reshape(*R.shape[:-3], -1, 3, 3)
    return ops_tet.tet_dd_from_rotations(both[..., k.rot_index, :, :].reshape(-1, 6, 3, 3),
                                         th.reshape(*th.shape[:-3], -1, 3)[..., k.theta_index, :].reshape(-1, 7, 3)
                                         ).reshape(*R.shape[:-3], -1, 3)


# ---------------------------------------------------------------- opcheck


_FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")
_ALL_UTILS = _FAST_UTILS + ("test_aot_dispatch_dynamic",)


@pytest.mark.parametrize("utils", [pytest.param(_FAST_UTILS, id="fast"),
                                   pytest.param(_ALL_UTILS, id="aot", marks=pytest.mark.slow)])
@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck(on, dtype, utils):
    """Schema, autograd registration and fake tensors in the default run; with
    ``test_aot_dispatch_dynamic`` (minutes on a loaded 2-core machine) under ``-m slow``."""
    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, th = _data(mesh, dtype)
    H = so3.sqrt(R)
    vec = torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    g = torch.randn(2, mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        for args in ((R, th), (torch.stack((R, R.flip(0))), torch.stack((th, -th)))):  # unbatched, batched
            torch.library.opcheck(ops_tet._tet_dd_op, (*rg(*args), *k.tables()), test_utils=utils)
        torch.library.opcheck(ops_tet._tet_dd_backward_op,
                              (*rg(torch.stack((R, R)), torch.stack((th, th)), g), *k.tables()), test_utils=utils)
        torch.library.opcheck(ops_tet_solder._tet_dd_sqrt_op, (*rg(torch.stack((R, R.flip(0))), torch.stack((H, H)), vec),
                                                        *k.tables()), test_utils=utils)
        torch.library.opcheck(ops_tet_solder._tet_dd_sqrt_backward_op,
                              (*rg(torch.stack((R, R)), torch.stack((H, H)), vec, g), *k.tables()), test_utils=utils)


# ---------------------------------------------------------------- values


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_match_per_tet_reference_and_generic_operators(on, dtype):
    mesh = io.box(2)
    k = ops_tet.tet_kernel(mesh)
    R, th = _data(mesh, dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-13
    with _switch(on):
        out = ops_tet.tet_dd(R, th, k)
        torch.testing.assert_close(out, _per_tet_reference(R, th, k), atol=tol, rtol=0)
        # the mesh-level function against the dense generic operators (𝔡∇ Alt 𝔡∇ Alt θ̃)
        dd = ops_tet_solder.tet_dd_solder(R, mesh)
    ref = dnabla.averaged_dd_tet(dnabla.tet_transports(R, mesh), dnabla.tet_solder_sqrt(R, mesh))
    torch.testing.assert_close(dd, ref, atol=10 * tol, rtol=0)


@pytest.mark.skipif(not _has_c, reason="no C compiler: csrc/tet.c cannot be built")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_equals_generic_with_a_many_color_schedule(dtype):
    """Chunks of 3 tets: many colors and chunks, so the race-free scatter is really exercised."""
    mesh = io.box(3)
    k = ops_tet.TetKernel(mesh, chunk=3)
    assert k.n_colors > 4 and k.chunk_start.shape[0] > 50
    # the schedule: a permutation of the tets, and no two chunks of one color share an edge
    assert torch.equal(k.order.sort().values, torch.arange(mesh.tets.shape[0]))
    te = mesh.tet_edges
    for c in range(k.n_colors):
        seen = set()
        for ch in range(int(k.color_start[c]), int(k.color_start[c + 1])):
            edges = set(te[k.order[k.chunk_start[ch]:k.chunk_start[ch + 1]]].reshape(-1).tolist())
            assert not (edges & seen)
            seen |= edges
    R, th = _data(mesh, dtype, seed=3, batch=(2,))
    g = torch.randn(2, mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(4), dtype=dtype)
    res = {}
    for on in (True, False):
        with compiled(on):
            res[on] = (ops_tet.tet_dd(R, th, k), *ops_tet._tet_dd_backward_op(R, th, g, *k.tables()))
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    for a, b in zip(res[True], res[False]):
        torch.testing.assert_close(a, b, atol=tol, rtol=0)


# ---------------------------------------------------------------- derivatives


@pytest.mark.parametrize("on", SWITCH)
def test_gradcheck_and_gradgradcheck(on):
    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, th = _data(mesh, seed=5)
    vec = torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(6), dtype=DT)
    H = so3.sqrt(R)
    f = lambda A, t: ops_tet.tet_dd(A, t, k)  # noqa: E731
    fs = lambda A, B, v: ops_tet_solder.tet_dd_sqrt(A, B, v, k)  # noqa: E731
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        assert gradcheck(f, rg(R, th))
        assert gradgradcheck(f, rg(R, th))
        assert gradcheck(fs, rg(R, H, vec))
        assert gradgradcheck(fs, rg(R, H, vec), fast_mode=True)  # 189 inputs: slow mode takes long
        # one input only, and an incoming gradient that depends on the input (square): the
        # double backward must not count the path through the incoming gradient twice
        assert gradgradcheck(lambda A: f(A, th).square(), rg(R), fast_mode=True)
        assert gradgradcheck(lambda t: f(R, t).square(), rg(th), fast_mode=True)
        assert gradgradcheck(lambda A: fs(A, H, vec).square(), rg(R), fast_mode=True)
        assert gradgradcheck(lambda B: fs(R, B, vec).square(), rg(H), fast_mode=True)


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("with_frames", [False, True])
def test_gradgradcheck_through_skew_parameters(on, with_frames):
    """The mesh-level function of ω (so3.exp, so3.sqrt, θ̃ formation, the op), batched."""
    mesh = _two_tets()
    g = torch.Generator().manual_seed(6)
    w = 0.6 * torch.randn(2, mesh.edges.shape[0], 3, generator=g, dtype=DT)
    frames = so3.random_rotation(mesh.vertices.shape[0], generator=g, dtype=DT) if with_frames else None
    f = lambda p: ops_tet_solder.tet_dd_solder(so3.exp(p), mesh, frames=frames)  # noqa: E731
    with _switch(on):
        assert gradcheck(f, (w.clone().requires_grad_(),))
        assert gradgradcheck(f, (w.clone().requires_grad_(),))


@pytest.mark.parametrize("on", SWITCH)
def test_hvp_matches_central_differences(on):
    mesh = io.box(2)
    g = torch.Generator().manual_seed(7)
    w = 0.6 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=DT)
    v = torch.randn(w.shape, generator=g, dtype=DT)
    loss = lambda p: ops_tet_solder.tet_dd_solder(so3.exp(p), mesh).square().sum()  # noqa: E731

    def grad(p):
        p = p.clone().requires_grad_()
        return torch.autograd.grad(loss(p), p)[0]

    with _switch(on):
        _, hv = torch.autograd.functional.hvp(loss, w, v)
        h = 1e-5
        fd = (grad(w + h * v) - grad(w - h * v)) / (2 * h)
    assert hv.abs().max() > 1e-3  # not trivially zero
    torch.testing.assert_close(hv, fd, atol=1e-6 * (1 + fd.abs().max()), rtol=1e-6)


def test_switch_on_off_same_values_and_gradients():
    if not _has_c:
        pytest.skip("no C compiler: csrc/tet.c cannot be built")
    mesh = io.box(3)
    w = 0.6 * torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(8), dtype=DT)
    res = []
    for on in (True, False):
        with compiled(on):
            p = w.clone().requires_grad_()
            out = ops_tet_solder.tet_dd_solder(so3.exp(p), mesh)
            (gp,) = torch.autograd.grad(out.square().sum(), p)
            res.append((out.detach(), gp))
    for a, b in zip(*res):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


# ---------------------------------------------------------------- batching


@pytest.mark.parametrize("on", SWITCH)
def test_batched_matches_loop(on):
    mesh = io.box(2)
    k = ops_tet.tet_kernel(mesh)
    R, th = _data(mesh, seed=9, batch=(2, 3))
    G = torch.randn(2, 3, mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(10), dtype=DT)
    with _switch(on):
        Rb, thb = R.clone().requires_grad_(), th.clone().requires_grad_()
        out = ops_tet.tet_dd(Rb, thb, k)
        gR, gth = torch.autograd.grad((out * G).sum(), (Rb, thb))
        for i in range(2):
            for j in range(3):
                Ri, ti = R[i, j].clone().requires_grad_(), th[i, j].clone().requires_grad_()
                oi = ops_tet.tet_dd(Ri, ti, k)
                gi = torch.autograd.grad((oi * G[i, j]).sum(), (Ri, ti))
                torch.testing.assert_close(out[i, j], oi, atol=1e-13, rtol=0)
                torch.testing.assert_close(gR[i, j], gi[0], atol=1e-13, rtol=0)
                torch.testing.assert_close(gth[i, j], gi[1], atol=1e-13, rtol=0)
        # the mesh-level function broadcasts (B, E, 3, 3) against shared frames
        frames = so3.random_rotation(mesh.vertices.shape[0], generator=torch.Generator().manual_seed(11), dtype=DT)
        batched = ops_tet_solder.tet_dd_solder(R[0], mesh, frames=frames)
        for j in range(3):
            torch.testing.assert_close(batched[j], ops_tet_solder.tet_dd_solder(R[0, j], mesh, frames=frames),
                                       atol=1e-13, rtol=0)


@pytest.mark.parametrize("on", SWITCH)
def test_vmap_matches_loop(on):
    mesh = io.box(2)
    k = ops_tet.tet_kernel(mesh)
    R, th = _data(mesh, seed=12, batch=(3,))
    with _switch(on):
        f = lambda A, t: ops_tet.tet_dd(A, t, k)  # noqa: E731
        out = torch.vmap(f)(R, th)
        # vmap over dim 1 of θ̃ only (R shared); gradients through the vmapped op (autograd
        # outside vmap: the vmap rule calls the op once on the batch)
        out_t = torch.vmap(f, in_dims=(None, 1))(R[0], th.movedim(0, 1))
        Rg = R.clone().requires_grad_()
        (gR,) = torch.autograd.grad(torch.vmap(f)(Rg, th).square().sum(), Rg)
        for i in range(3):
            torch.testing.assert_close(out[i], f(R[i], th[i]), atol=1e-13, rtol=0)
            torch.testing.assert_close(out_t[i], f(R[0], th[i]), atol=1e-13, rtol=0)
            Ri = R[i].clone().requires_grad_()
            (gi,) = torch.autograd.grad(f(Ri, th[i]).square().sum(), Ri)
            torch.testing.assert_close(gR[i], gi, atol=1e-12, rtol=0)
        # the sqrt op, vmapped over R and √R (v shared)
        vec = torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(14), dtype=DT)
        H = so3.sqrt(R)
        outs = torch.vmap(lambda A, B: ops_tet_solder.tet_dd_sqrt(A, B, vec, k))(R, H)
        for i in range(3):
            torch.testing.assert_close(outs[i], ops_tet_solder.tet_dd_sqrt(R[i], H[i], vec, k), atol=1e-13, rtol=0)
    with pytest.raises(ValueError, match="tet_dd"):
        torch.vmap(lambda ri: ops_tet._tet_dd_op(R[0], th[0], ri, *k.tables()[1:]))(k.rot_index[None])


@pytest.mark.parametrize("on", SWITCH)
def test_vmap_of_the_backward_ops_matches_loop(on):
    """The backward ops sum ∂L/∂edge_vec over their leading batch: vmapped, every item keeps its own."""
    mesh = io.box(2)
    k = ops_tet.tet_kernel(mesh)
    R, _ = _data(mesh, seed=21, batch=(3,))
    gen = torch.Generator().manual_seed(22)
    vec = torch.randn(mesh.edges.shape[0], 3, generator=gen, dtype=DT)
    grad = torch.randn(3, mesh.n_tets, 3, generator=gen, dtype=DT)
    tabs = k.tables()
    H = so3.sqrt(R)
    with _switch(on):
        sq = lambda A, B, g: ops_tet_solder._tet_dd_sqrt_backward_op(A, B, vec, g, *tabs)  # noqa: E731
        ro = lambda A, g: ops_tet_solder._tet_dd_rot_backward_op(A, vec, g, *tabs)  # noqa: E731
        out_sq, out_ro = torch.vmap(sq)(R, H, grad), torch.vmap(ro)(R, grad)
        for i in range(3):
            for a, b in zip(out_sq, sq(R[i], H[i], grad[i])):
                torch.testing.assert_close(a[i], b, atol=1e-12, rtol=0)
            for a, b in zip(out_ro, ro(R[i], grad[i])):
                torch.testing.assert_close(a[i], b, atol=1e-12, rtol=0)
        assert out_sq[2].shape == (3, *vec.shape) and out_ro[1].shape == (3, *vec.shape)


# ---------------------------------------------------------------- meta, compile, errors


def test_meta_tensors():
    mesh = io.box(2)
    k = ops_tet.tet_kernel(mesh, "meta")
    E, T = mesh.edges.shape[0], mesh.tets.shape[0]
    R = torch.empty(4, E, 3, 3, device="meta", requires_grad=True)
    th = torch.empty(4, E, 2, 3, device="meta")
    out = ops_tet.tet_dd(R, th, k)
    assert out.device.type == "meta" and out.shape == (4, T, 3)
    (g,) = torch.autograd.grad(out.sum(), R)
    assert g.shape == R.shape and g.device.type == "meta"


@pytest.mark.parametrize("on", SWITCH)
def test_compile_fullgraph(on):
    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, th = _data(mesh, seed=13)

    def loss(A, t):
        return ops_tet.tet_dd(A, t, k).square().sum()

    with _switch(on):
        cf = torch.compile(loss, fullgraph=True, backend="aot_eager")
        A, t = R.clone().requires_grad_(), th.clone().requires_grad_()
        val = cf(A, t)
        val.backward()
        A2, t2 = R.clone().requires_grad_(), th.clone().requires_grad_()
        ref = loss(A2, t2)
        ref.backward()
    torch.testing.assert_close(val, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(A.grad, A2.grad, atol=1e-12, rtol=0)


def test_shape_errors_name_the_argument():
    mesh = io.box(1)
    k = ops_tet.tet_kernel(mesh)
    R, th = _data(mesh)
    with pytest.raises(ValueError, match="tet_dd: edge_rot"):
        ops_tet.tet_dd(R[:-1], th, k)
    with pytest.raises(ValueError, match="tet_dd: edge_theta"):
        ops_tet.tet_dd(torch.stack((R, R)), th, k)
    with pytest.raises(ValueError, match="tet_dd: edge_theta"):
        ops_tet.tet_dd(R, th.float(), k)


def test_edge_vectors_cache_follows_the_vertices():
    """The per-mesh edge vectors ``v_j - v_i`` (cached for the vertex tensor they come from):
    recomputed after an in-place edit of the vertices, per dtype, and differentiable (never
    cached) when the vertices require grad."""
    from torchconn.nn import MeshBuffers
    from torchconn.ops._cache import edge_vectors

    mesh = io.box(2)
    e = mesh.edges
    direct = lambda v: v[e[:, 1]] - v[e[:, 0]]  # noqa: E731
    a = edge_vectors(mesh, "cpu", DT)
    assert torch.equal(a, direct(mesh.vertices)) and edge_vectors(mesh, "cpu", DT) is a
    assert edge_vectors(mesh, "cpu", torch.float32).dtype == torch.float32
    mesh.vertices.mul_(2.0)
    b = edge_vectors(mesh, "cpu", DT)
    assert torch.equal(b, direct(mesh.vertices)) and torch.equal(b, 2 * a)
    mb = MeshBuffers(mesh)
    mb.vertices.requires_grad_(True)
    c = edge_vectors(mb, "cpu", DT)
    assert c.requires_grad
    c.sum().backward()
    assert mb.vertices.grad is not None and torch.equal(mb.vertices.grad.sum(0), torch.zeros(3, dtype=DT))


@pytest.mark.skipif(not _has_c, reason="no C compiler: csrc/tet.c cannot be built")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_sqrt_backward_equals_generic_with_a_many_color_schedule(dtype):
    """The √R variant (θ̃ formed per edge in the kernel) on chunks of 5 tets: many colors, and a
    partial lane block at the end of every chunk; forward and backward against the generic
    kernels."""
    mesh = io.box(3)
    k = ops_tet.TetKernel(mesh, chunk=5)
    assert k.n_colors > 4
    T = mesh.tets.shape[0]
    R, _ = _data(mesh, dtype, seed=7, batch=(2,))
    H = so3.sqrt(R)
    vec = torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(8), dtype=dtype)
    g = torch.randn(2, T, 3, generator=torch.Generator().manual_seed(9), dtype=dtype)
    res = {}
    for on in (True, False):
        with compiled(on):
            res[on] = (*ops_tet_solder._tet_dd_sqrt_backward_op(R, H, vec, g, *k.tables()),
                       ops_tet_solder._tet_dd_sqrt_op(R, H, vec, *k.tables()))
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    for a, b in zip(res[True], res[False]):
        torch.testing.assert_close(a, b, atol=tol, rtol=0)


# ---------------------------------------------------------------- tet_dd_rot (√R formed in the kernel)


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tet_dd_rot_opcheck(on, dtype):
    """Schema, autograd registration and fake tensors of ``torchconn::tet_dd_rot`` and its backward."""
    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, _ = _data(mesh, dtype)
    vec = torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    g = torch.randn(2, mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        for Rb in (R, torch.stack((R, R.flip(0)))):
            torch.library.opcheck(ops_tet_solder._tet_dd_rot_op, (*rg(Rb, vec), *k.tables()), test_utils=_FAST_UTILS)
        torch.library.opcheck(ops_tet_solder._tet_dd_rot_backward_op, (*rg(torch.stack((R, R)), vec, g), *k.tables()),
                              test_utils=_FAST_UTILS)


@pytest.mark.skipif(not _has_c, reason="no C compiler: csrc/tet.c cannot be built")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("scale", [0.3, 2.8])
def test_tet_dd_rot_compiled_equals_generic_and_the_two_op_path(dtype, scale):
    """The C kernels (roots per edge, colored chunks of 5 tets, a batch of 2) against the generic
    kernels, and against ``tet_dd_sqrt`` on ``so3.sqrt(R)`` followed by the root's backward; scale
    2.8: angles above 120° (the roots' log/exp branch) in most blocks."""
    mesh = io.box(3)
    k = ops_tet.TetKernel(mesh, chunk=5)
    g = torch.Generator().manual_seed(11)
    E, T = mesh.edges.shape[0], mesh.tets.shape[0]
    R = so3.exp(scale * torch.randn(2, E, 3, generator=g, dtype=torch.float64)).to(dtype)
    vec = torch.randn(E, 3, generator=g, dtype=torch.float64).to(dtype)
    G = torch.randn(2, T, 3, generator=g, dtype=torch.float64).to(dtype)
    res = {}
    for on in (True, False):
        with compiled(on):
            res[on] = (ops_tet_solder._tet_dd_rot_op(R, vec, *k.tables()), *ops_tet_solder._tet_dd_rot_backward_op(R, vec, G, *k.tables()))
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    for a, b in zip(res[True], res[False]):
        torch.testing.assert_close(a, b, atol=tol, rtol=0)
    Rg = R.clone().requires_grad_()
    vg = vec.clone().requires_grad_()
    out = ops_tet_solder.tet_dd_sqrt(Rg, so3.sqrt(Rg), vg, k)
    g_rot, g_vec = torch.autograd.grad((out * G).sum(), (Rg, vg))
    for a, b in zip(res[True], (out, g_rot, g_vec)):
        torch.testing.assert_close(a, b, atol=tol, rtol=0)


@pytest.mark.parametrize("on", SWITCH)
def test_tet_dd_rot_gradcheck_and_gradgradcheck(on):
    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, _ = _data(mesh, seed=5)
    vec = torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(6), dtype=DT)
    fr = lambda A, v: ops_tet_solder.tet_dd_rot(A, v, k)  # noqa: E731
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        assert gradcheck(fr, rg(R, vec))
        assert gradgradcheck(fr, rg(R, vec), fast_mode=True)
        # an incoming gradient that depends on the input (square): no path counted twice
        assert gradgradcheck(lambda A: fr(A, vec).square(), rg(R), fast_mode=True)


# ---------------------------------------------------------------- tet_dd_frames (the solder form in a frame field)

def _frames_data(mesh, dtype=DT, seed=0, batch=(), relabel=True):
    """Rotations near the octahedral group (relabeled edges: quarter and half turns, the roots'
    large-angle branches) and frames."""
    from torchconn.frames import octahedral

    g = torch.Generator().manual_seed(seed)
    E, V = mesh.edges.shape[0], mesh.n_vertices
    R = so3.exp(0.3 * torch.randn(*batch, E, 3, generator=g, dtype=torch.float64))
    if relabel:
        R = R @ octahedral.group(torch.float64)[torch.randint(0, 24, (*batch, E), generator=g)]
    F = so3.exp(0.6 * torch.randn(*batch, V, 3, generator=g, dtype=torch.float64))
    vec = torch.randn(E, 3, generator=g, dtype=torch.float64)
    return R.to(dtype), F.to(dtype), vec.to(dtype)


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tet_dd_frames_opcheck(on, dtype):
    """Schema, autograd registration and fake tensors of ``torchconn::tet_dd_frames`` and its backward."""
    from torchconn.ops._cache import edge_index

    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, F, vec = _frames_data(mesh, dtype, relabel=False)
    e = edge_index(mesh, "cpu")
    g = torch.randn(2, mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        for Rb, Fb in ((R, F), (torch.stack((R, R.flip(0))), torch.stack((F, F)))):
            torch.library.opcheck(ops_tet_solder._tet_dd_frames_op, (*rg(Rb, Fb, vec), e, *k.tables()),
                                  test_utils=_FAST_UTILS)
        torch.library.opcheck(ops_tet_solder._tet_dd_frames_backward_op,
                              (*rg(torch.stack((R, R)), torch.stack((F, F)), vec), g.clone().requires_grad_(), e,
                               *k.tables()), test_utils=_FAST_UTILS)


@pytest.mark.skipif(not _has_c, reason="no C compiler: csrc/tet.c cannot be built")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tet_dd_frames_compiled_equals_generic_and_the_dense_operators(dtype):
    """The C kernels (edge stripes with their own frame buffers, colored chunks of 5 tets, a batch of
    2, relabeled edges) against the generic kernels; and the mesh-level entry against the dense
    operators of the report with frames (tet_transports, tet_solder_sqrt) through skew parameters."""
    from torchconn.ops._cache import edge_index

    mesh = io.box(3)
    k = ops_tet.TetKernel(mesh, chunk=5)
    R, F, vec = _frames_data(mesh, dtype, seed=11, batch=(2,))
    e = edge_index(mesh, "cpu")
    G = torch.randn(2, mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64).to(dtype)
    res = {}
    for on in (True, False):
        with compiled(on):
            res[on] = (ops_tet_solder._tet_dd_frames_op(R, F, vec, e, *k.tables()),
                       *ops_tet_solder._tet_dd_frames_backward_op(R, F, vec, G, e, *k.tables()))
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    for a, b in zip(res[True], res[False]):
        torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0)
    # the dense operators: along SO(3) (skew parameters), where the two agree
    from torchconn.frames import octahedral

    gen = torch.Generator().manual_seed(12)
    w = 0.3 * torch.randn(mesh.n_edges, 3, generator=gen, dtype=torch.float64)
    P = octahedral.group(torch.float64)[torch.randint(0, 24, (mesh.n_edges,), generator=gen)]
    p = 0.6 * torch.randn(mesh.n_vertices, 3, generator=gen, dtype=torch.float64)
    C = torch.randn(mesh.tets.shape[0], 3, generator=gen, dtype=torch.float64)
    m = mesh.to(dtype=dtype)
    out = []
    for dense in (False, True):
        ww, pp = w.to(dtype).requires_grad_(), p.to(dtype).requires_grad_()
        Rr, Fr = so3.exp(ww) @ P.to(dtype), so3.exp(pp)
        d = (dnabla.averaged_dd_tet(dnabla.tet_transports(Rr, m), dnabla.tet_solder_sqrt(Rr, m, Fr)) if dense
             else dnabla.averaged_dd_solder(Rr, m, frames=Fr))
        out.append((d.detach(), *torch.autograd.grad((d * C.to(dtype)).sum(), (ww, pp))))
    for a, b in zip(*out):
        torch.testing.assert_close(a, b, atol=(1e-5 if dtype == torch.float32 else 1e-12) * float(b.abs().max()), rtol=0)


@pytest.mark.parametrize("on", SWITCH)
def test_tet_dd_frames_gradcheck_and_gradgradcheck(on):
    from torchconn.ops._cache import edge_index

    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, F, vec = _frames_data(mesh, seed=5)
    e = edge_index(mesh, "cpu")
    ff = lambda A, B, v: ops_tet_solder.tet_dd_frames(A, B, v, e, k)  # noqa: E731
    rg = lambda *ts: tuple(t.clone().requires_grad_() for t in ts)  # noqa: E731
    with _switch(on):
        assert gradcheck(ff, rg(R, F, vec))
        assert gradgradcheck(ff, rg(R, F, vec), fast_mode=True)
        assert gradgradcheck(lambda A, B: ff(A, B, vec).square(), rg(R, F), fast_mode=True)


@pytest.mark.parametrize("on", SWITCH)
def test_tet_dd_frames_vmap_and_batch_match_loops(on):
    from torchconn.ops._cache import edge_index

    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, F, vec = _frames_data(mesh, seed=7, batch=(3,))
    e = edge_index(mesh, "cpu")
    f = lambda A, B: ops_tet_solder.tet_dd_frames(A, B, vec, e, k)  # noqa: E731
    with _switch(on):
        loop = torch.stack([f(R[b], F[b]) for b in range(3)])
        torch.testing.assert_close(f(R, F), loop, atol=1e-13, rtol=0)
        torch.testing.assert_close(torch.func.vmap(f)(R, F), loop, atol=1e-13, rtol=0)
        gl = torch.func.vmap(torch.func.grad(lambda A, B: f(A, B).square().sum(), argnums=(0, 1)))(R, F)
        for b in range(3):
            Rb, Fb = R[b].clone().requires_grad_(), F[b].clone().requires_grad_()
            ref = torch.autograd.grad(f(Rb, Fb).square().sum(), (Rb, Fb))
            for a, r in zip(gl, ref):
                torch.testing.assert_close(a[b], r, atol=1e-12, rtol=0)


def test_tet_dd_frames_meta_and_shape_errors():
    from torchconn.ops._cache import edge_index

    mesh = _two_tets()
    k = ops_tet.tet_kernel(mesh)
    R, F, vec = _frames_data(mesh)
    e = edge_index(mesh, "cpu")
    out = ops_tet_solder.tet_dd_frames(R.to("meta"), F.to("meta"), vec.to("meta"), e.to("meta"), k.to("meta"))
    assert out.device.type == "meta" and out.shape == (mesh.tets.shape[0], 3)
    with pytest.raises(ValueError, match="frames must have shape"):
        ops_tet_solder.tet_dd_frames(R, torch.stack((F, F)), vec, e, k)
    with pytest.raises(ValueError, match="edge_vec and edges"):
        ops_tet_solder.tet_dd_frames(R, F, vec[:-1], e, k)


# ---------------------------------------------------------------- torch.func, tables built inside transforms

def _tet_functions(mesh):
    """The three public functions as functions of ``R`` only (θ̃ / √R and edge vectors fixed)."""
    from torchconn.ops._cache import edge_vectors

    k = ops_tet.tet_kernel(mesh)
    _, th = _data(mesh, seed=4)
    vec = edge_vectors(mesh, "cpu", DT)
    H = so3.sqrt(_data(mesh, seed=5)[0])
    return {"tet_dd": lambda R: ops_tet.tet_dd(R, th, k),
            "tet_dd_sqrt": lambda R: ops_tet_solder.tet_dd_sqrt(R, H, vec, k),
            "tet_dd_rot": lambda R: ops_tet_solder.tet_dd_rot(R, vec, k)}


@pytest.mark.parametrize("fn", ["tet_dd", "tet_dd_sqrt", "tet_dd_rot"])
@pytest.mark.parametrize("on", SWITCH)
def test_torch_func_transforms_match_autograd(on, fn):
    """torch.func.grad, vmap(grad), jacrev, jacfwd and jvp through the eager autograd.Function of
    each op (the register_autograd Function has no setup_context: grad/jacrev raised) against
    torch.autograd.grad, in ambient directions (not only along SO(3))."""
    mesh = _two_tets()
    f = _tet_functions(mesh)[fn]
    R, _ = _data(mesh, seed=6)
    R2, _ = _data(mesh, seed=7)
    W = torch.randn(mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(8), dtype=DT)
    V = torch.randn(R.shape, generator=torch.Generator().manual_seed(9), dtype=DT)
    loss = lambda r: (W * f(r)).sum() + f(r).square().sum()  # noqa: E731

    def ref_grad(r):
        r = r.clone().requires_grad_()
        return torch.autograd.grad(loss(r), r)[0]

    def ref_jac(r):
        r = r.clone().requires_grad_()
        out = f(r).reshape(-1)
        return torch.stack([torch.autograd.grad(out[i], r, retain_graph=True)[0] for i in range(out.numel())]
                           ).reshape(*out.shape, *r.shape).reshape(mesh.tets.shape[0], 3, *r.shape)

    close = lambda a, b: torch.testing.assert_close(a, b, atol=1e-11, rtol=1e-11)  # noqa: E731
    with _switch(on):
        close(torch.func.grad(loss)(R), ref_grad(R))
        close(torch.func.vmap(torch.func.grad(loss))(torch.stack((R, R2))), torch.stack((ref_grad(R), ref_grad(R2))))
        J = ref_jac(R)
        close(torch.func.jacrev(f)(R), J)
        close(torch.func.jacfwd(f)(R), J)
        close(torch.func.jvp(f, (R,), (V,))[1], (J * V).flatten(-3).sum(-1))


@pytest.mark.parametrize("transform", ["grad", "vmap"])
def test_tables_first_built_inside_a_transform_are_plain_and_reused(transform):
    """The tet tables and edge vectors asked for first inside torch.func.grad / vmap (whose tensor
    ops return storage-less wrappers: the NumPy schedule failed) are built on the real mesh:
    plain tensors, reused by the next eager call. (First asked while torch.compile traces:
    ``test_transform_matrix.py::test_compile_module_loss_fresh_process``.)"""
    from torchconn.nn import AveragedCovariantD
    from torchconn.ops._cache import edge_vectors

    mesh = _two_tets()
    mod = AveragedCovariantD(mesh)
    R, _ = _data(mesh, seed=3)
    f = lambda r: mod(r).square().sum()  # noqa: E731
    if transform == "grad":
        torch.func.grad(f)(R)
    else:
        torch.func.vmap(f)(torch.stack((R, R)))
    k = ops_tet.tet_kernel(mod.mesh)
    plain = lambda t: not torch._C._functorch.is_functorch_wrapped_tensor(t)  # noqa: E731
    assert all(plain(t) for t in k.tables()) and k.order.numpy().shape == (mesh.tets.shape[0],)
    assert plain(edge_vectors(mod.mesh, "cpu", DT))
    torch.testing.assert_close(f(R), (dnabla.averaged_dd_tet(dnabla.tet_transports(R, mesh),
                                                             dnabla.tet_solder_sqrt(R, mesh))).square().sum())
