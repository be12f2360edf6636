"""Second-order derivatives through the fused kernels: exact, or a clear error, never silently wrong.

The face-curvature op (``torchconn::face_curvature``) and the averaged d∇d∇θ tet
op (``torchconn::tet_dd``, ``ops.tet.tet_dd``) have backward passes that are themselves
differentiable, so ``create_graph=True``, double backward and Hessian-vector products are
exact: float64 ``gradgradcheck`` of the modules and of the functional entry points through
``so3.exp`` of skew parameters, Hessian-vector products against central differences of the
gradient, and the same values with the compiled kernels off. The compiled frame-loss kernel
computes a first-order gradient only: a recorded backward through it raises ``RuntimeError``
naming the op and the switch, and the torch terms (compiled kernels off) give exact
Hessian-vector products.
"""
from __future__ import annotations

import pytest
import torch
from torch.autograd import gradgradcheck

import torchconn.ops
from torchconn import AveragedCovariantD, ConnectionField, Curvature, Torsion, curvature, dnabla, io, so3
from torchconn.frames.loss import FrameFieldLoss
from torchconn.mesh import TetMesh
from torchconn.ops import curvature as ops_curvature
from torchconn.ops import native
from torchconn.ops import tet as ops_tet

DT = torch.float64


def _skew(mesh, seed, scale=0.6):
    """``(E, 3)`` float64 skew parameters of a connection (rotation angles up to ~``scale * 3``)."""
    g = torch.Generator().manual_seed(seed)
    return scale * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=DT)


def _frames(mesh, seed):
    return so3.random_rotation(mesh.vertices.shape[0], generator=torch.Generator().manual_seed(seed), dtype=DT)


# ---------------------------------------------------------------- gradgradcheck through so3.exp


def _two_tets():
    """Two tets sharing a face (9 edges, 7 faces): the gradgradchecks' complex (tets sharing edges
    and faces, edges used in both directions; on ``io.box(1)``, 19 edges, they took 3-13 s each)."""
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.2]], dtype=DT)
    return TetMesh(v, [[0, 1, 2, 3], [1, 2, 3, 4]], reorient=True)

MODULES = {
    "Curvature(two_prong)": lambda m: Curvature(m),
    "Curvature(two_prong, cut b)": lambda m: Curvature(m, cut=1),
    "Curvature(holonomy)": lambda m: Curvature(m, kind="holonomy"),
    "AveragedCovariantD": lambda m: AveragedCovariantD(m),
    "Torsion": lambda m: Torsion(m),
}


@pytest.mark.parametrize("name", list(MODULES))
def test_module_gradgradcheck_through_exp(name):
    mesh = _two_tets()
    mod = MODULES[name](mesh)
    w = _skew(mesh, seed=1).requires_grad_()
    assert gradgradcheck(lambda p: mod(so3.exp(p)), (w,))


def test_module_with_frames_gradgradcheck_through_exp():
    mesh = _two_tets()
    frames = _frames(mesh, 2)
    w = _skew(mesh, seed=3).requires_grad_()
    assert gradgradcheck(lambda p: AveragedCovariantD(mesh)(so3.exp(p), frames), (w,))


@pytest.mark.parametrize("cut,kind", [(-1, "two_prong"), (1, "two_prong"), (-1, "holonomy")])
def test_functional_face_curvature_gradgradcheck(cut, kind):
    mesh = _two_tets()
    w = _skew(mesh, seed=4).requires_grad_()
    assert gradgradcheck(lambda p: curvature.face_curvature(so3.exp(p), mesh, cut=cut, kind=kind), (w,))


@pytest.mark.parametrize("variant", ["sqrt", "half_exp", "frames"])
def test_functional_averaged_dd_solder_gradgradcheck(variant):
    mesh = _two_tets()
    frames = _frames(mesh, 5) if variant == "frames" else None

    def f(p):
        half = so3.exp(0.5 * p) if variant == "half_exp" else None
        return dnabla.averaged_dd_solder(so3.exp(p), mesh, frames=frames, half_rot=half)

    w = _skew(mesh, seed=6).requires_grad_()
    assert gradgradcheck(f, (w,))


# ---------------------------------------------------------------- Hessian-vector products


def _hvp_and_central_difference(loss_of, params, v, h=1e-5):
    """``H v`` by double backward, and ``(∇L(p + h v) - ∇L(p - h v)) / 2h``."""
    p = params.clone().requires_grad_()
    (g,) = torch.autograd.grad(loss_of(p), p, create_graph=True)
    (hv,) = torch.autograd.grad(g, p, v)

    def grad_at(x):
        x = x.detach().requires_grad_()
        return torch.autograd.grad(loss_of(x), x)[0]

    fd = (grad_at(params + h * v) - grad_at(params - h * v)) / (2 * h)
    return hv, fd


def _field_loss(mesh, module):
    """``L(params) = |module(ConnectionField(params))|²`` with the field's own parametrization."""
    field = ConnectionField(mesh.edges, mesh.vertices.shape[0], dtype=DT)

    def loss_of(p):
        return torch.func.functional_call(module, {}, (torch.func.functional_call(field, {"params": p}, ()),)) \
            .square().sum()

    return loss_of


@pytest.mark.parametrize("kind", ["two_prong", "holonomy"])
def test_curvature_hvp_matches_central_differences(kind):
    mesh = io.box(2)
    loss_of = _field_loss(mesh, Curvature(mesh, kind=kind))
    w = _skew(mesh, seed=7)
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(8), dtype=DT)
    hv, fd = _hvp_and_central_difference(loss_of, w, v)
    rel = float((hv - fd).norm() / fd.norm())
    assert rel < 1e-6, f"Hessian-vector product of Curvature({kind}) off by relative {rel:.3g}"
    # torch.autograd.functional.hvp (double-backward trick: the incoming gradient requires grad)
    _, hv2 = torch.autograd.functional.hvp(loss_of, w, v)
    torch.testing.assert_close(hv2, hv, atol=1e-11, rtol=1e-11)
    with torchconn.ops.compiled(False):  # the torch kernels of so3: the same Hessian
        hv_torch, _ = _hvp_and_central_difference(loss_of, w, v)
    torch.testing.assert_close(hv_torch, hv, atol=1e-11, rtol=1e-11)


def test_averaged_dd_hvp_matches_central_differences():
    mesh = io.box(2)
    loss_of = _field_loss(mesh, AveragedCovariantD(mesh))
    w = _skew(mesh, seed=9)
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(10), dtype=DT)
    hv, fd = _hvp_and_central_difference(loss_of, w, v)
    rel = float((hv - fd).norm() / fd.norm())
    assert rel < 1e-6, f"Hessian-vector product of AveragedCovariantD off by relative {rel:.3g}"
    with torchconn.ops.compiled(False):
        hv_torch, _ = _hvp_and_central_difference(loss_of, w, v)
    torch.testing.assert_close(hv_torch, hv, atol=1e-11, rtol=1e-11)


def test_curvature_hvp_equals_generic_loop_formula():
    """The fused kernel's Hessian equals that of the generic loop formula under plain autograd."""
    mesh = io.box(2)
    w = _skew(mesh, seed=11)
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(12), dtype=DT)
    _, groups = curvature.face_loops(mesh)
    _, le, ls, _ = groups[0]
    from torchconn.dec.transport import orient

    fused = lambda p: curvature.face_curvature(so3.exp(p), mesh).square().sum()  # noqa: E731
    generic = lambda p: curvature.two_prong(orient(so3.exp(p), le, ls)).square().sum()  # noqa: E731
    _, hv_fused = torch.autograd.functional.hvp(fused, w, v)
    _, hv_generic = torch.autograd.functional.hvp(generic, w, v)
    torch.testing.assert_close(hv_fused, hv_generic, atol=1e-11, rtol=1e-11)


# ---------------------------------------------------------------- the two backward paths agree


def test_recorded_backward_equals_first_order_backward():
    """The recorded (create_graph) and the unrecorded backward give the same first-order gradient."""
    mesh = io.box(2)
    R = so3.exp(_skew(mesh, seed=13))
    th = torch.randn(R.shape[0], 2, 3, generator=torch.Generator().manual_seed(14), dtype=DT)
    k = ops_tet.tet_kernel(mesh)
    ops = [lambda A, t: ops_tet.tet_dd(A, t, k)]
    ops += [lambda A, t, c=c: ops_curvature.face_curvature(A, mesh, c) * t.sum() for c in (0, 1, 2)]
    for op in ops:
        grads = []
        for create in (False, True):
            A, t = R.clone().requires_grad_(), th.clone().requires_grad_()
            out = op(A, t)
            G = torch.randn(out.shape, generator=torch.Generator().manual_seed(15), dtype=DT)
            grads.append(torch.autograd.grad((out * G).sum(), (A, t), create_graph=create))
        for a, b in zip(*grads):
            torch.testing.assert_close(a.detach(), b.detach(), atol=1e-13, rtol=0)


# ---------------------------------------------------------------- compiled frame loss

_needs_kernel = pytest.mark.skipif(native.library("frame_loss") is None,
                                   reason="no C compiler (or TORCHCONN_NATIVE=0): the compiled frame-loss "
                                          "kernel cannot be built")
LOSS_WEIGHTS = {"smooth": 1.0, "tie": 1.0, "flat": 1.0, "torsion": 1.0}


def _loss_setup():
    mesh = io.box(2)
    loss = FrameFieldLoss(mesh, LOSS_WEIGHTS)
    g = torch.Generator().manual_seed(16)
    w = 0.15 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=DT)
    phi = 0.15 * torch.randn(mesh.vertices.shape[0], 3, generator=g, dtype=DT)
    return loss, w, phi


@_needs_kernel
def test_compiled_frame_loss_hvp_equals_the_torch_terms_hvp():
    """A recorded backward through the compiled kernel (C first order) is exact: same HVP as the torch terms."""
    loss, w, phi = _loss_setup()
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(17), dtype=DT)
    hv = {}
    for on in (True, False):
        with torchconn.ops.compiled(on):
            hv[on] = torch.autograd.functional.hvp(lambda p: loss(so3.exp(p), so3.exp(phi))["total"], w, v)[1]
    torch.testing.assert_close(hv[True], hv[False], atol=1e-12, rtol=1e-10)


def test_frame_loss_torch_terms_hvp_matches_central_differences():
    """With the compiled kernels off the Hessian-vector product is exact."""
    loss, w, phi = _loss_setup()
    v = torch.randn(w.shape, generator=torch.Generator().manual_seed(17), dtype=DT)
    with torchconn.ops.compiled(False):
        hv, fd = _hvp_and_central_difference(lambda p: loss(so3.exp(p), so3.exp(phi))["total"], w, v)
    rel = float((hv - fd).norm() / fd.norm())
    assert rel < 1e-6, f"Hessian-vector product of the frame-field loss (torch terms) off by relative {rel:.3g}"
