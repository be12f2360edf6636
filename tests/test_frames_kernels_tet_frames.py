"""``torchconn::smooth_tet_frames`` (:mod:`torchconn.frames.kernels.tet_frames`) per the custom-op contract.

opcheck with the compiled kernel on and off; the C kernel against the generic torch formula
(values and first-order gradients, float32 and float64, several tasks of the C loops) and both
against the SVD rule of :func:`torchconn.frames.octahedral.tet_frames`; gradcheck and gradgradcheck
in float64; ``torch.func.grad`` and ``jvp``; the per-vertex incidence table against a loop; the
clear error of a tet whose frames disagree; meta tensors. The map energy that uses it:
``tests/test_hexmesh_energy.py``.
"""
from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

from torchconn import io, so3
from torchconn.frames import octahedral
from torchconn.frames.kernels import tet_frames as tf
from torchconn.ops import compiled, native

from kernel_cases import SWITCH, switch

DT = torch.float64
_has_c = native.library("tet_frames") is not None
_FAST_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor")


def _switch(on: bool):
    return switch(on, "tet_frames", "csrc/tet_frames.c")


def _field(mesh, seed=0, scale=0.2, dtype=DT):
    """Vertex frames near a smooth field, each relabeled by a random element of O, and the tables."""
    g = torch.Generator().manual_seed(seed)
    V = mesh.n_vertices
    base = so3.exp(scale * torch.randn(V, 3, generator=g, dtype=DT))
    F = base @ octahedral.group(DT)[torch.randint(0, 24, (V,), generator=g)]
    match = octahedral.match_edges(F, mesh.edges)[0]
    a, others, g = octahedral.tet_relabeling(mesh, match, DT)
    return F.to(dtype), match, (a, others, g, *tf.vertex_incidence(a, others, V))


@pytest.mark.parametrize("on", SWITCH)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck(on, dtype):
    mesh = io.box(1)
    F, _, tables = _field(mesh, dtype=dtype)
    with _switch(on):
        torch.library.opcheck(tf._op, (F.clone().requires_grad_(), *tables), test_utils=_FAST_UTILS)


@pytest.mark.skipif(not _has_c, reason="no C compiler: csrc/tet_frames.c cannot be built")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_equals_generic_and_the_svd_rule(dtype):
    """box(7): 2,058 tets and 512 vertices (several tasks of 2,048 tets); values and gradients."""
    mesh = io.box(7)
    F, match, tables = _field(mesh, seed=3, dtype=dtype)
    G = torch.randn(mesh.tets.shape[0], 3, 3, generator=torch.Generator().manual_seed(4), dtype=DT).to(dtype)
    out = []
    for on in (True, False):
        with compiled(on):
            x = F.clone().requires_grad_()
            Y = tf.smooth_tet_frames_op(x, *tables)
            out.append((Y.detach(), torch.autograd.grad((Y * G).sum(), x)[0]))
    tol = 5e-6 if dtype == torch.float32 else 1e-12
    for a, b in zip(*out):
        torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0)
    ref = octahedral.tet_frames(F.double(), mesh, match)
    torch.testing.assert_close(out[0][0].double(), ref, atol=100 * tol, rtol=0)


def test_incidence_table_matches_a_loop():
    mesh = io.box(2)
    _, _, (a, others, _, inc_ptr, inc) = _field(mesh)
    slots = torch.cat((a[:, None], others), 1)
    for v in range(mesh.n_vertices):
        got = inc[inc_ptr[v]:inc_ptr[v + 1]].tolist()
        want = [4 * t + s for t in range(slots.shape[0]) for s in range(4) if int(slots[t, s]) == v]
        assert got == want


@pytest.mark.parametrize("on", SWITCH)
def test_gradcheck_gradgradcheck_and_func_transforms(on):
    mesh = io.box(1)
    F, _, tables = _field(mesh, seed=5)
    f = lambda x: tf.smooth_tet_frames_op(x, *tables)  # noqa: E731
    with _switch(on):
        x = F.clone().requires_grad_()
        assert gradcheck(f, (x,))
        assert gradgradcheck(f, (x,), fast_mode=True)
        w = torch.randn(mesh.tets.shape[0], 3, 3, generator=torch.Generator().manual_seed(6), dtype=DT)
        loss = lambda x: (f(x) * w).sum()  # noqa: E731
        (ref,) = torch.autograd.grad(loss(x), x)
        torch.testing.assert_close(torch.func.grad(loss)(F), ref, atol=1e-12, rtol=0)
        t = torch.randn(F.shape, generator=torch.Generator().manual_seed(7), dtype=DT)
        _, jv = torch.func.jvp(loss, (F,), (t,))
        torch.testing.assert_close(jv, (ref * t).sum(), atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("on", SWITCH)
def test_disagreeing_frames_raise_a_clear_error(on):
    mesh = io.box(1)
    F, _, tables = _field(mesh, seed=8)
    bad = F.clone()
    bad[int(tables[0][0])] = -bad[int(tables[0][0])]  # det -1 at a tet's lowest vertex: det(F_a^T M) <= 0
    with _switch(on), pytest.raises(ValueError, match=r"smooth_tet_frames: \d+ tets \(first \[\d+"):
        tf.smooth_tet_frames_op(bad, *tables)


def test_meta():
    mesh = io.box(1)
    F, _, tables = _field(mesh)
    Y = tf.smooth_tet_frames_op(F.to("meta"), *(t.to("meta") for t in tables))
    assert Y.device.type == "meta" and Y.shape == (mesh.tets.shape[0], 3, 3)
