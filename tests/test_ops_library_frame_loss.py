"""The custom ops ``torchconn::frame_loss`` / ``torchconn::frame_loss_backward`` (issues 11, 30).

Layers: opcheck of both ops (float32/float64, switch on/off, with and without the forward's
gradient); both kernels against a slow reference made of the frame-field loss's own term
functions (:mod:`torchconn.frames.terms`, :mod:`torchconn.dec.torsion`, the torsion mean over the
faces in a Python loop); the generic gradient (``torch.func.vjp`` inside the kernel) and the C
sweep against autograd of the torch terms on matrices that are not rotations, every subset of
the terms; gradcheck + gradgradcheck (float64, switch on/off); a Hessian-vector product against
central differences with the C kernel on; vmap and batched calls against loops; jvp;
``torch.compile(fullgraph=True)`` (no graph break, the C kernel runs at runtime); meta tensors;
the reuse of the forward's gradient (one C sweep for ``total.backward()``); two threads at once.
"""
import itertools
import threading

import pytest
import torch

import torchconn.ops
from torchconn import io, so3
from torchconn.dec import curvature as dec_curvature
from torchconn.dec import torsion as dec_torsion
from torchconn.frames import octahedral
from torchconn.mesh.tet import TetMesh
from torchconn.frames.loss import FrameFieldLoss, TERMS
from torchconn.frames.terms import matched_dirichlet_loss, smoothness_loss, symmetric_flatness_loss, tie_loss
from torchconn.frames.kernels import _frame_loss_torch as T
from torchconn.frames.kernels import frame_loss as FL
from torchconn.ops import native

HAS_C = native.library("frame_loss") is not None
NEEDS_C = pytest.mark.skipif(not HAS_C, reason="no C compiler (or TORCHCONN_NATIVE=0): csrc/frame_loss.c cannot be built")
SWITCH = [pytest.param(True, marks=NEEDS_C, id="compiled"), pytest.param(False, id="torch")]
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                 reason="no CUDA device"))]
W4 = {"smooth": 0.7, "tie": 1.3, "flat": 0.4, "torsion": 0.9, "dirichlet": 0.6}  # every term of the op
ON = (True, True, True, True, True)
OPTS_BWD = (*ON, 0.7, 1.3, 0.4, 0.9, 0.6, 1.0, 1e-3)  # on flags, weights, power, eps
OPTS = (*ON, True, *OPTS_BWD[5:])  # the forward op's: the regular-face flags too


def _inputs(mesh, dtype, batch=(), seed=0, scale=0.25, noise=0.0, device="cpu"):
    """Rotations near I (``so3.exp``), plus ``noise`` off the rotations."""
    g = torch.Generator().manual_seed(seed)
    E, V = mesh.edges.shape[0], mesh.n_vertices
    R = so3.exp(scale * torch.randn(*batch, E, 3, generator=g, dtype=torch.float64))
    F = so3.exp(scale * torch.randn(*batch, V, 3, generator=g, dtype=torch.float64))
    if noise:
        R = R + noise * torch.randn(R.shape, generator=g, dtype=torch.float64)
        F = F + noise * torch.randn(F.shape, generator=g, dtype=torch.float64)
    return R.to(device, dtype), F.to(device, dtype)


def _tables(mesh, dtype, device="cpu"):
    return (*FL.mesh_tables(mesh, dtype, device), octahedral.group(dtype, device))


def _terms(R, F, mesh, weights=W4, power=1.0):
    """The op, whichever kernel the switch picks (:func:`FL.call`)."""
    return FL.call(R, F, mesh, octahedral.group(torch.float64), weights, power, 1e-3)


def _weighted(R, F, mesh, coef=(0.3, -1.1, 2.0, 0.6, -0.7), weights=W4, power=1.0):
    """A combination of the returned terms other than the loss weights (the backward re-sweeps)."""
    out = _terms(R, F, mesh, weights, power)
    return sum(c * out[k] for c, k in zip(coef, FL.COMPILED_TERMS) if k in out)


def _count_sweeps(monkeypatch):
    calls = []
    for dt, fn in list(FL._C_SWEEP.items()):
        def counted(*args, _fn=fn):
            calls.append(args[18])  # the grad flag
            return _fn(*args)
        monkeypatch.setitem(FL._C_SWEEP, dt, counted)
    return calls


# ----------------------------------------------------------------------------- opcheck

#: opcheck's AOT-dispatch test traces the backward op's own autograd (a torch.func double vjp of
#: the terms, ~5-15 s): run for every case of the forward op, once for the backward op (float64,
#: compiled kernel on) and marked slow for the other combinations; the other three utilities
#: run for every dtype, switch state and case.
FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")


def _backward_args(dtype, case):
    mesh = io.box(1)
    R, F = _inputs(mesh, dtype, batch=(2,))
    tabs = _tables(mesh, dtype)
    _, gR, gF, _ = torch.ops.torchconn.frame_loss(R, F, *tabs, *OPTS, True)
    g = torch.tensor(OPTS_BWD[5:10], dtype=dtype).expand(2, 5) * torch.tensor([[2.0], [-0.5]], dtype=dtype)
    if case != "reuse":
        g = torch.randn(2, 5, generator=torch.Generator().manual_seed(3)).to(dtype)
    saved = (None, None) if case == "no_saved" else (gR, gF)
    return (R.requires_grad_(), F.requires_grad_(), *tabs, g.requires_grad_(), *saved, *OPTS_BWD)


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("with_grad", [True, False])
def test_opcheck_forward(compiled, dtype, with_grad):
    mesh = io.box(1)
    R, F = _inputs(mesh, dtype, batch=(2,))
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(torch.ops.torchconn.frame_loss.default,
                              (R.requires_grad_(), F.requires_grad_(), *_tables(mesh, dtype), *OPTS, with_grad))


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["reuse", "resweep", "no_saved"])
def test_opcheck_backward(compiled, dtype, case):
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(torch.ops.torchconn.frame_loss_backward.default, _backward_args(dtype, case),
                              test_utils=FAST_UTILS)


@pytest.mark.parametrize("compiled,dtype", [
    pytest.param(True, torch.float64, marks=NEEDS_C, id="compiled-float64"),
    pytest.param(True, torch.float32, marks=(NEEDS_C, pytest.mark.slow), id="compiled-float32"),
    pytest.param(False, torch.float64, marks=pytest.mark.slow, id="torch-float64"),
    pytest.param(False, torch.float32, marks=pytest.mark.slow, id="torch-float32")])
def test_opcheck_backward_aot_dispatch(compiled, dtype):
    with torchconn.ops.compiled(compiled):
        torch.library.opcheck(torch.ops.torchconn.frame_loss_backward.default, _backward_args(dtype, "resweep"),
                              test_utils="test_aot_dispatch_dynamic")


# ----------------------------------------------------------------------------- against references

def _reference_terms(R, F, mesh, power):
    """Slow reference: the frame-field loss's own term functions; the matched connection and the
    torsion mean per face in Python loops."""
    out = {"smooth": smoothness_loss(R, power, 1e-3)}
    out["tie"], _ = tie_loss(R, F, mesh.edges, power, 1e-3)
    hol = dec_curvature.face_curvature(R, mesh, kind="holonomy")
    out["flat"] = symmetric_flatness_loss(hol + torch.eye(3, dtype=R.dtype))
    G = octahedral.group(R.dtype)
    M = []
    for e, (i, j) in enumerate(mesh.edges.tolist()):  # h_e = argmax_h tr(h^T F_j^T F_i R_e), per edge
        scores = [float((g * (F[j].T @ F[i] @ R[e])).detach().sum()) for g in G]
        M.append(R[e] @ G[scores.index(max(scores))].T)
    tor = dec_torsion.face_torsion(torch.stack(M), mesh, kind="sqrt", frames=F)
    p = mesh.vertices.to(R.dtype)[mesh.faces]
    area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)
    out["torsion"] = torch.stack([(tor[f] ** 2).sum() / area[f] for f in range(tor.shape[0])]).mean()
    out["dirichlet"] = matched_dirichlet_loss(F, mesh.edges)
    return out


@pytest.mark.parametrize("compiled", SWITCH)
@pytest.mark.parametrize("power", [2.0, 1.0])
def test_values_and_gradients_match_the_frame_loss_term_functions(compiled, power):
    mesh = io.box(2)
    R, F = _inputs(mesh, torch.float64, seed=4, scale=0.4)
    with torchconn.ops.compiled(False):  # the reference's own so3/curvature kernels: torch
        Rr, Fr = R.clone().requires_grad_(), F.clone().requires_grad_()
        ref = _reference_terms(Rr, Fr, mesh, power)
        ref_grads = torch.autograd.grad(sum(W4[k] * v for k, v in ref.items()), (Rr, Fr))
    with torchconn.ops.compiled(compiled):
        Ro, Fo = R.clone().requires_grad_(), F.clone().requires_grad_()
        out = _terms(Ro, Fo, mesh, power=power)
        grads = torch.autograd.grad(sum(W4[k] * v for k, v in out.items()), (Ro, Fo))
    assert 0 < float(ref["torsion"]) and out.keys() == ref.keys()
    for k in ref:
        torch.testing.assert_close(out[k], ref[k], atol=1e-12, rtol=1e-12)
    for a, b in zip(grads, ref_grads):
        torch.testing.assert_close(a, b, atol=1e-11, rtol=1e-10)


@pytest.mark.parametrize("on", [c for c in itertools.product([False, True], repeat=5) if any(c)])
def test_generic_and_compiled_gradients_equal_autograd_off_rotations(on):
    """Every subset of terms, batched, matrices that are not rotations, per-item weights: the
    backward op's generic kernel (``torch.func.vjp`` inside the kernel) and its C sweep."""
    mesh = io.box(2)
    R, F = _inputs(mesh, torch.float64, batch=(2,), seed=1, scale=0.3, noise=0.05)
    tabs = _tables(mesh, torch.float64)
    wts = torch.randn(2, 5, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for power in (2.0, 1.0):
        Rr, Fr = R.clone().requires_grad_(), F.clone().requires_grad_()
        vals = T.terms(Rr, Fr, *tabs, on, power, 1e-3)
        ref = torch.autograd.grad((vals * wts).sum(), (Rr, Fr), allow_unused=True)
        ref = [torch.zeros_like(x) if g is None else g for x, g in zip((R, F), ref)]
        got = []
        for c in ([False, True] if HAS_C else [False]):
            with torchconn.ops.compiled(c):
                got.append(torch.ops.torchconn.frame_loss_backward(R, F, *tabs, wts, None, None, *on,
                                                                   1.0, 1.0, 1.0, 1.0, 1.0, power, 1e-3))
                v2 = torch.ops.torchconn.frame_loss(R, F, *tabs, *on, False, 1.0, 1.0, 1.0, 1.0, 1.0, power, 1e-3,
                                                    False)[0]
            torch.testing.assert_close(v2, vals.detach(), atol=1e-13, rtol=1e-13)
        for g in got:
            for a, b in zip(g, ref):
                torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [(), (3,)])
@NEEDS_C
def test_switch_off_and_on_give_the_same_values_and_gradients(dtype, batch):
    mesh = io.box(2)
    R, F = _inputs(mesh, dtype, batch=batch, seed=6, scale=0.5)
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    res = {}
    for on in (True, False):
        with torchconn.ops.compiled(on):
            Ro, Fo = R.clone().requires_grad_(), F.clone().requires_grad_()
            out = _terms(Ro, Fo, mesh)
            total = sum(W4[k] * v for k, v in out.items()).sum()
            res[on] = (torch.stack(list(out.values())), *torch.autograd.grad(total, (Ro, Fo)))
    for a, b in zip(res[True], res[False]):
        torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0)


# ----------------------------------------------------------------------------- derivatives

def _one_tet():
    return TetMesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64),
                   torch.tensor([[0, 1, 2, 3]]))


@pytest.fixture
def one_thread():
    """One thread: OpenMP barriers of 2 threads on a loaded 2-core box make ~10^3 tiny calls slow."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.mark.parametrize("compiled", SWITCH)
def test_gradcheck_and_gradgradcheck(compiled, one_thread):
    mesh = _one_tet()
    R, F = _inputs(mesh, torch.float64, seed=5, scale=0.3, noise=0.02)  # not rotations
    with torchconn.ops.compiled(compiled):
        assert set(_terms(R, F, mesh)) == set(W4) and float(_terms(R, F, mesh)["torsion"]) > 0
        for fn in (lambda r, f: _weighted(r, f, mesh),  # other weights: the backward re-sweeps
                   lambda r, f: sum(W4[k] * v for k, v in _terms(r, f, mesh).items())):  # the forward's gradient
            args = (R.clone().requires_grad_(), F.clone().requires_grad_())
            assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-7)
            assert torch.autograd.gradgradcheck(fn, args, eps=1e-6, atol=1e-6)


@NEEDS_C
def test_hessian_vector_product_with_the_compiled_kernel_matches_central_differences(monkeypatch):
    mesh = io.box(2)
    loss = FrameFieldLoss(mesh, {"smooth": 1.0, "tie": 1.0, "flat": 1.0, "torsion": 1.0}, smooth_power=1.0)
    g = torch.Generator().manual_seed(16)
    w = 0.15 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=torch.float64)
    phi = so3.exp(0.15 * torch.randn(mesh.n_vertices, 3, generator=g, dtype=torch.float64))
    v = torch.randn(w.shape, generator=g, dtype=torch.float64)

    def grad_at(x, create=False):
        x = x if create else x.detach().requires_grad_()
        return torch.autograd.grad(loss(so3.exp(x), phi)["total"], x, create_graph=create)[0]

    with torchconn.ops.compiled(True):
        calls = _count_sweeps(monkeypatch)
        x = w.clone().requires_grad_()
        (hv,) = torch.autograd.grad((grad_at(x, create=True) * v).sum(), x)
        assert calls, "the compiled kernel did not run"
        h = 1e-5
        fd = (grad_at(w + h * v) - grad_at(w - h * v)) / (2 * h)
        (hv2,) = torch.autograd.functional.hvp(lambda p: loss(so3.exp(p), phi)["total"], w, v)[1:]
    rel = float((hv - fd).norm() / fd.norm())
    assert rel < 1e-6, f"HVP of the frame-field loss off by relative {rel:.3g}"
    torch.testing.assert_close(hv2, hv, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("compiled", SWITCH)
def test_jvp_matches_the_gradient(compiled):
    mesh = io.box(1)
    R, F = _inputs(mesh, torch.float64, seed=7)
    tR, tF = _inputs(mesh, torch.float64, seed=8, scale=1.0)
    with torchconn.ops.compiled(compiled):
        _, t = torch.func.jvp(lambda r, f: _weighted(r, f, mesh), (R, F), (tR, tF))
        Rr, Fr = R.clone().requires_grad_(), F.clone().requires_grad_()
        gR, gF = torch.autograd.grad(_weighted(Rr, Fr, mesh), (Rr, Fr))
    torch.testing.assert_close(t, (gR * tR).sum() + (gF * tF).sum(), atol=1e-12, rtol=1e-10)


# ----------------------------------------------------------------------------- batching

@pytest.mark.parametrize("compiled", SWITCH)
def test_vmap_matches_a_loop(compiled):
    mesh = io.box(1)
    R, F = _inputs(mesh, torch.float64, batch=(3,), seed=9, scale=0.4)

    def f(r, f_):
        out = _terms(r, f_, mesh)
        return torch.stack([out[k] for k in FL.COMPILED_TERMS])

    with torchconn.ops.compiled(compiled):
        vals = torch.func.vmap(f)(R, F)
        grads = torch.func.vmap(torch.func.grad(lambda r, f_: _weighted(r, f_, mesh), argnums=(0, 1)))(R, F)
        vals_shared = torch.func.vmap(f, in_dims=(0, None))(R, F[0])  # frames not vmapped
        for b in range(3):
            torch.testing.assert_close(vals[b], f(R[b], F[b]), atol=1e-14, rtol=0)
            torch.testing.assert_close(vals_shared[b], f(R[b], F[0]), atol=1e-14, rtol=0)
            Rb, Fb = R[b].clone().requires_grad_(), F[b].clone().requires_grad_()
            for got, ref in zip(grads, torch.autograd.grad(_weighted(Rb, Fb, mesh), (Rb, Fb))):
                torch.testing.assert_close(got[b], ref, atol=1e-14, rtol=0)


@pytest.mark.parametrize("compiled", SWITCH)
def test_batched_call_matches_a_loop(compiled):
    mesh = io.box(2)
    R, F = _inputs(mesh, torch.float64, batch=(2, 2), seed=10, scale=0.4)
    with torchconn.ops.compiled(compiled):
        Ro, Fo = R.clone().requires_grad_(), F[0, 0].clone().requires_grad_()  # frames broadcast
        out = _terms(Ro, Fo, mesh)
        assert all(v.shape == (2, 2) for v in out.values())
        gR, gF = torch.autograd.grad(sum(W4[k] * v for k, v in out.items()).sum(), (Ro, Fo))
        gF_loop = torch.zeros_like(gF)
        for i, j in itertools.product(range(2), range(2)):
            Rb, Fb = R[i, j].clone().requires_grad_(), F[0, 0].clone().requires_grad_()
            ref = _terms(Rb, Fb, mesh)
            for k in ref:
                torch.testing.assert_close(out[k][i, j], ref[k], atol=1e-14, rtol=0)
            a, b = torch.autograd.grad(sum(W4[k] * v for k, v in ref.items()), (Rb, Fb))
            torch.testing.assert_close(gR[i, j], a, atol=1e-14, rtol=0)
            gF_loop += b
    torch.testing.assert_close(gF, gF_loop, atol=1e-13, rtol=0)


# ----------------------------------------------------------------------------- compile, meta, devices

@pytest.mark.slow
@NEEDS_C
def test_compile_fullgraph_runs_the_compiled_kernel(monkeypatch):
    mesh = io.box(2)
    loss = FrameFieldLoss(mesh, {k: 1.0 for k in TERMS}, smooth_power=1.0)
    _, phi = _inputs(mesh, torch.float64, seed=11)
    w = 0.2 * torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def step(w, frames):
        return loss(so3.exp(w), frames)["total"]

    torch._dynamo.reset()
    compiled_step = torch.compile(step, fullgraph=True, backend="aot_eager")
    with torchconn.ops.compiled(True):
        x = w.clone().requires_grad_()
        val = compiled_step(x, phi)
        calls = _count_sweeps(monkeypatch)
        x2 = w.clone().requires_grad_()
        val = compiled_step(x2, phi)  # the compiled graph, at runtime
        (g,) = torch.autograd.grad(val, x2)
        assert calls == [1], f"expected one C sweep with the gradient (reused by the backward), got {calls}"
        x3 = w.clone().requires_grad_()
        ref = step(x3, phi)
        (g_ref,) = torch.autograd.grad(ref, x3)
    torch.testing.assert_close(val, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(g, g_ref, atol=1e-12, rtol=0)


def test_meta_tensors_give_shapes():
    mesh = io.box(1)
    R, F = _inputs(mesh, torch.float32, batch=(2,))
    out = _terms(R.to("meta").requires_grad_(), F.to("meta"), mesh)
    assert all(v.device.type == "meta" and v.shape == (2,) for v in out.values())
    loss = FrameFieldLoss(mesh, W4)
    res = loss(R[0].to("meta"), F[0].to("meta"))
    assert res["total"].device.type == "meta" and res["total"].shape == ()


@pytest.mark.parametrize("device", DEVICES)
def test_generic_kernel_on_each_device_matches_the_cpu(device):
    mesh = io.box(2)
    R, F = _inputs(mesh, torch.float64, seed=12, scale=0.4)
    res = []
    for dev in ("cpu", device):
        Ro, Fo = R.to(dev).requires_grad_(), F.to(dev).requires_grad_()
        out = _terms(Ro, Fo, mesh)
        grads = torch.autograd.grad(sum(W4[k] * v for k, v in out.items()), (Ro, Fo), create_graph=True)
        hv = torch.autograd.grad(grads[0].sum(), Ro)[0]
        res.append([torch.stack(list(out.values())), *grads, hv])
    for a, b in zip(*res):
        assert b.device.type == torch.device(device).type
        torch.testing.assert_close(b.detach().cpu(), a.detach(), atol=1e-11, rtol=1e-10)


# ----------------------------------------------------------------------------- reuse, threads, errors

@NEEDS_C
def test_total_backward_reuses_the_forward_gradient(monkeypatch):
    mesh = io.box(2)
    loss = FrameFieldLoss(mesh, W4, smooth_power=1.0)
    R, F = _inputs(mesh, torch.float64, seed=13)
    with torchconn.ops.compiled(True):
        calls = _count_sweeps(monkeypatch)
        Ro = R.clone().requires_grad_()
        loss(Ro, F)["total"].backward()
        assert calls == [1]  # the forward sweep (with gradient) only
        calls.clear()
        Ro.grad = None
        loss(Ro, F)["tie"].backward()  # another combination: one more sweep
        assert calls == [1, 1]
        g_tie = Ro.grad.clone()
    with torchconn.ops.compiled(False):
        Rr = R.clone().requires_grad_()
        loss(Rr, F)["tie"].backward()
    torch.testing.assert_close(g_tie, Rr.grad, atol=1e-12, rtol=0)


@NEEDS_C
def test_two_threads_at_once_give_the_serial_results():
    """No scratch state shared between calls: concurrent calls on two meshes/sizes are exact."""
    cases = [(io.box(3), 14), (io.box(2), 15)]
    losses = [FrameFieldLoss(m, W4, smooth_power=1.0) for m, _ in cases]
    inputs = [_inputs(m, torch.float64, seed=s) for m, s in cases]

    def run(i):
        R = inputs[i][0].clone().requires_grad_()
        out = losses[i](R, inputs[i][1])
        out["total"].backward()
        return float(out["total"]), R.grad

    with torchconn.ops.compiled(True):
        serial = [run(0), run(1)]
        results, errors = {}, []

        def worker(i):
            try:
                for _ in range(5):
                    v, g = run(i)
                    assert v == serial[i][0] and torch.equal(g, serial[i][1])
                results[i] = True
            except BaseException as exc:  # reported below
                errors.append(exc)

        threads = [threading.Thread(target=worker, args=(i,)) for i in (0, 1)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert not errors and results == {0: True, 1: True}, errors


def test_does_not_apply_and_release():
    mesh = io.box(1)
    R, F = _inputs(mesh, torch.float64)
    group = octahedral.group(torch.float64)

    def fast(R, F, weights=W4):
        return FL.frame_loss_terms(R, F, mesh, group, weights, 1.0, 1e-3)

    with torchconn.ops.compiled(True):
        assert (fast(R, F) is not None) == HAS_C
        assert fast(R, F, {"align": 1.0}) is None  # no term of the op
        assert fast(R[:-1], F) is None  # wrong number of edges
        assert fast(R, F.float()) is None  # mixed dtypes
        if HAS_C:
            assert set(fast(R, F, {"torsion": 1.0})) == {"torsion"}  # the matching runs without the tie term
            regular = FL.frame_loss_terms(R, F, mesh, group, {"smooth": 1.0}, 1.0, 1e-3, regular=True)
            assert regular["face_regular"].dtype == torch.bool and regular["face_regular"].shape == (mesh.n_faces,)
    with torchconn.ops.compiled(False):
        assert fast(R, F) is None  # the switch off: the loss's modules run
    FL.release_scratch()
    assert set(_terms(R, F, mesh)) == set(W4)
