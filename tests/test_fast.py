"""Fused kernels of torchconn.ops against the generic operators and plain autograd."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation as Rot
from torch.autograd import gradcheck, gradgradcheck

from torchconn import dnabla, io, so3
from torchconn.frames import octahedral
import torchconn.ops
from torchconn.ops import curvature as ops_curvature
from torchconn.ops import so3 as ops_so3
from torchconn.ops import tet as ops_tet
from torchconn.ops import tet_solder as ops_tet_solder
from torchconn.ops import torsion as ops_torsion
from torchconn.dec.connection import Connection
from torchconn.dec.transport import orient
from torchconn.mesh import TetMesh

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 2e-6, torch.float64: 1e-13}


def _rotvecs(n, dtype, seed=0, max_angle=math.pi):
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    ang = torch.rand(n, 1, generator=g, dtype=torch.float64) * max_angle
    w = axis * ang
    w[:3] = 0.0
    w[3:6] *= 1e-6  # inside the Taylor branch
    return w.to(dtype)


def _rodrigues_matrix_route(w):
    """Slow obviously-correct reference: the matrix exponential of the skew matrix."""
    return torch.linalg.matrix_exp(so3.hat(w))


# ---------------------------------------------------------------- exp


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_matches_matrix_exp_and_autograd(dtype):
    w = _rotvecs(2000, dtype).requires_grad_()
    with torchconn.ops.compiled(False):  # the torch kernel (the compiled one: tests/test_native_so3.py)
        R = ops_so3.exp(w)
    torch.testing.assert_close(R, _rodrigues_matrix_route(w.detach().double()).to(dtype), atol=TOL[dtype] * 4, rtol=0)
    G = torch.randn(R.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    (g_fast,) = torch.autograd.grad((R * G).sum(), w)
    w2 = w.detach().clone().requires_grad_()
    R2 = ops_so3.exp_autograd(w2)
    (g_ref,) = torch.autograd.grad((R2 * G).sum(), w2)
    assert torch.equal(R.detach(), R2.detach())
    torch.testing.assert_close(g_fast, g_ref, atol=10 * TOL[dtype], rtol=0)
    assert torch.isfinite(g_fast).all()


@pytest.mark.parametrize("scale", [0.0, 1e-7, 1e-3, 1.0, 3.0])
def test_exp_gradcheck_and_double_backward(scale):
    g = torch.Generator().manual_seed(2)
    w = (torch.randn(6, 3, generator=g, dtype=torch.float64) * scale).requires_grad_()
    assert gradcheck(ops_so3.exp, (w,))
    assert gradgradcheck(ops_so3.exp, (w,))


def test_exp_gradient_at_identity_is_hat_pairing():
    # dR/dw at 0 is hat(e_k): the gradient of <G, R> is (G21 - G12, G02 - G20, G10 - G01)
    w = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    G = torch.arange(9, dtype=torch.float64).reshape(1, 3, 3) ** 1.5
    (g,) = torch.autograd.grad((ops_so3.exp(w) * G).sum(), w)
    Gm = G[0]
    expect = torch.stack((Gm[2, 1] - Gm[1, 2], Gm[0, 2] - Gm[2, 0], Gm[1, 0] - Gm[0, 1]))
    torch.testing.assert_close(g[0], expect)


# ---------------------------------------------------------------- log / sqrt


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_matches_scipy(dtype):
    w = _rotvecs(3000, torch.float64, seed=3, max_angle=math.pi - 1e-6)
    R = torch.from_numpy(Rot.from_rotvec(w.numpy()).as_matrix()).to(dtype)
    ref = torch.from_numpy(Rot.from_matrix(R.double().numpy()).as_rotvec())
    out = ops_so3.log(R).double()
    # float32 near pi: the angle itself is only known to ~sqrt(eps)-ish from rounded entries
    atol = 1e-12 if dtype == torch.float64 else 5e-4
    torch.testing.assert_close(out, ref, atol=atol, rtol=0)


@pytest.mark.parametrize("theta", [0.0, 1e-5, 0.5, 1.4, 1.8, 2.5, math.pi - 1e-3])
def test_log_sqrt_gradcheck_all_branches(theta):
    # (not at a branch switch, t = pi/2 or 2 pi/3: gradcheck perturbs R off SO(3), where the
    # branches extend differently)
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    R = so3.exp(axis / axis.norm() * theta)[None].requires_grad_()
    assert gradcheck(ops_so3.log, (R,))
    assert gradcheck(ops_so3.sqrt, (R,))


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_sqrt_finite_gradient_at_pi(dtype):
    # at exactly pi log jumps (+pi n or -pi n), so only finiteness of value and gradient is asked
    R = so3.rot_x(torch.tensor([math.pi], dtype=dtype)).requires_grad_()
    for fn in (ops_so3.log, ops_so3.sqrt):
        out = fn(R)
        (g,) = torch.autograd.grad(out.sum(), R)
        assert torch.isfinite(out).all() and torch.isfinite(g).all()
    torch.testing.assert_close(ops_so3.log(R).abs().detach(),
                               torch.tensor([[math.pi, 0.0, 0.0]], dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_sqrt_equals_half_log_route(dtype):
    R = so3.random_rotation(5000, generator=torch.Generator().manual_seed(4), dtype=dtype)
    S = ops_so3.sqrt(R)
    ref = ops_so3.exp(0.5 * ops_so3.log(R))
    torch.testing.assert_close(S, ref, atol=5 * TOL[dtype], rtol=0)
    torch.testing.assert_close(S @ S, R, atol=5 * TOL[dtype], rtol=0)
    # batch shape kept, both branches present
    tr = R.diagonal(dim1=-2, dim2=-1).sum(-1)
    assert (tr > 0).any() and (tr <= 0).any()
    assert ops_so3.sqrt(R.reshape(50, 100, 3, 3)).shape == (50, 100, 3, 3)


def test_half_exp_is_principal_root():
    w = _rotvecs(500, torch.float64, seed=5, max_angle=math.pi - 1e-3)
    torch.testing.assert_close(ops_so3.half_exp(w), so3.sqrt(so3.exp(w)), atol=1e-11, rtol=0)


# ---------------------------------------------------------------- tet kernel


def _setup(dtype, n=3, scale=0.6, seed=0):
    mesh = io.box(n).to(dtype=dtype)
    conn = Connection.random_on_mesh(mesh, generator=torch.Generator().manual_seed(seed), scale=scale)
    return mesh, conn.edge_rot


def _two_tets():
    """Two tets sharing a face (9 edges, 7 faces): the smallest complex with shared edges and faces."""
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.2]], dtype=torch.float64)
    return TetMesh(v, [[0, 1, 2, 3], [1, 2, 3, 4]], reorient=True)


def _generic_dd(edge_rot, mesh, frames=None, half_rot=None):
    """The dense generic path (𝔡∇ Alt 𝔡∇ Alt θ̃ through the tuple machinery)."""
    T = dnabla.tet_transports(edge_rot, mesh)
    return dnabla.averaged_dd_tet(T, dnabla.tet_solder_sqrt(edge_rot, mesh, frames, half_rot))


def test_tet_kernel_indices_match_orient():
    mesh, R = _setup(torch.float64)
    k = ops_tet.tet_kernel(mesh)
    both = torch.stack((R, R.transpose(-1, -2)), 1).reshape(-1, 3, 3)
    torch.testing.assert_close(both[k.rot_index], orient(R, mesh.tet_edges, mesh.tet_edge_signs))
    th = dnabla.tet_solder_sqrt(R, mesh)  # dense (T, 4, 4, 3)
    H = so3.sqrt(R)
    e = mesh.edges
    vec = mesh.vertices[e[:, 1]] - mesh.vertices[e[:, 0]]
    edge_th = ops_tet.edge_solder_sqrt(H, vec).reshape(-1, 3)[k.theta_index]
    for col, (x, y) in enumerate(ops_tet.TetKernel._DIRECTED):
        torch.testing.assert_close(edge_th[:, col], th[:, x, y])
    assert ops_tet.tet_kernel(mesh) is k  # cached


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("with_frames", [False, True])
def test_tet_dd_matches_generic(dtype, with_frames):
    mesh, R = _setup(dtype)
    frames = so3.random_rotation(mesh.vertices.shape[0], generator=torch.Generator().manual_seed(7),
                                 dtype=dtype) if with_frames else None
    ref = _generic_dd(R, mesh, frames)
    out = ops_tet_solder.tet_dd_solder(R, mesh, frames=frames)
    torch.testing.assert_close(out, ref, atol=20 * TOL[dtype], rtol=0)
    # the explicit printed formula on the dense tables agrees too
    wedge = dnabla.wedge_curvature_solder_tet(dnabla.tet_transports(R, mesh),
                                             dnabla.tet_solder_sqrt(R, mesh, frames))
    torch.testing.assert_close(out, wedge, atol=20 * TOL[dtype], rtol=0)
    # the public wrappers route here
    torch.testing.assert_close(dnabla.averaged_dd_solder(R, mesh, frames), out, atol=0, rtol=0)


def test_tet_dd_with_half_rot_from_params():
    mesh = io.box(3)
    w = 0.4 * torch.randn(mesh.edges.shape[0], 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    R = so3.exp(w)
    out = ops_tet_solder.tet_dd_solder(R, mesh, half_rot=ops_so3.half_exp(w))
    torch.testing.assert_close(out, _generic_dd(R, mesh), atol=1e-13, rtol=0)


@pytest.mark.parametrize("with_frames", [False, True])
def test_tet_dd_fused_backward_matches_autograd(with_frames):
    dtype = torch.float64
    mesh, R = _setup(dtype, scale=0.8, seed=2)
    frames = so3.random_rotation(mesh.vertices.shape[0], generator=torch.Generator().manual_seed(8),
                                 dtype=dtype) if with_frames else None
    w = so3.log(R).requires_grad_()
    Gout = torch.randn(mesh.tets.shape[0], 3, generator=torch.Generator().manual_seed(9), dtype=dtype)
    (g_fast,) = torch.autograd.grad((ops_tet_solder.tet_dd_solder(so3.exp(w), mesh, frames=frames) * Gout).sum(), w)
    (g_ref,) = torch.autograd.grad((_generic_dd(so3.exp(w), mesh, frames) * Gout).sum(), w)
    torch.testing.assert_close(g_fast, g_ref, atol=1e-12, rtol=0)


def test_tet_dd_fused_gradcheck():
    mesh, R = _setup(torch.float64, n=1, scale=0.8, seed=4)
    k = ops_tet.tet_kernel(mesh)
    Rr = R.clone().requires_grad_()
    th = torch.randn(R.shape[0], 2, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64,
                     requires_grad=True)
    fused = lambda A, t: ops_tet.tet_dd(A, t, k)  # noqa: E731

    def plain(A, t):
        both = torch.stack((A, A.transpose(-1, -2)), 1).reshape(-1, 3, 3)
        return ops_tet.tet_dd_from_rotations(both[k.rot_index], t.reshape(-1, 3)[k.theta_index])

    torch.testing.assert_close(fused(Rr, th), plain(Rr, th), atol=1e-14, rtol=0)
    assert gradcheck(fused, (Rr, th))
    assert gradcheck(plain, (Rr, th))


def test_tet_dd_fused_gradgradcheck():
    """The hand-written backward is itself differentiable (create_graph, double backward). Fast
    mode on the cube (285 inputs: the full Jacobian of the backward took 15-23 s); the full
    ``gradgradcheck`` of ``tet_dd`` is ``test_ops_library_tet.py::test_gradcheck_and_gradgradcheck``
    (two tets)."""
    mesh, R = _setup(torch.float64, n=1, scale=0.8, seed=4)
    k = ops_tet.tet_kernel(mesh)
    th = torch.randn(R.shape[0], 2, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    fused = lambda A, t: ops_tet.tet_dd(A, t, k)  # noqa: E731
    assert gradgradcheck(fused, (R.clone().requires_grad_(), th.clone().requires_grad_()), fast_mode=True)
    # one input differentiated only (needs_input_grad of the recorded backward)
    assert gradgradcheck(lambda A: fused(A, th), (R.clone().requires_grad_(),), fast_mode=True)
    assert gradgradcheck(lambda t: fused(R, t).square(), (th.clone().requires_grad_(),), fast_mode=True)


def test_exp_matches_numpy_rodrigues_per_element():
    """Per-element reference written with numpy, one rotation at a time."""
    w = _rotvecs(50, torch.float64, seed=11)
    out = ops_so3.exp(w).numpy()
    for i, wi in enumerate(w.numpy()):
        t = np.linalg.norm(wi)
        K = np.array([[0, -wi[2], wi[1]], [wi[2], 0, -wi[0]], [-wi[1], wi[0], 0]])
        A = np.sinc(t / np.pi)
        B = 0.5 if t < 1e-8 else (1 - np.cos(t)) / t**2
        np.testing.assert_allclose(out[i], np.eye(3) + A * K + B * K @ K, atol=1e-14)


# ---------------------------------------------------------------- faces


def _generic_face_curvature(R, mesh, cut, kind):
    from torchconn import curvature

    _, groups = curvature.face_loops(mesh)
    _, le, ls, _ = groups[0]
    L = orient(R, le, ls)
    return curvature.holonomy(L) if kind == "holonomy" else curvature.two_prong(L, cut)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("cut,kind", [(-1, "two_prong"), (2, "two_prong"), (1, "two_prong"), (-2, "two_prong"),
                                      (0, "two_prong"), (-1, "holonomy")])
def test_face_curvature_matches_generic_values_and_gradients(dtype, cut, kind):
    from torchconn import curvature

    mesh, R = _setup(dtype, scale=0.8, seed=5)
    w = so3.log(R).requires_grad_()
    out = curvature.face_curvature(so3.exp(w), mesh, cut, kind)  # routes to ops.curvature
    ref = _generic_face_curvature(so3.exp(w), mesh, cut, kind)
    torch.testing.assert_close(out, ref, atol=5 * TOL[dtype], rtol=0)
    G = torch.randn(out.shape, generator=torch.Generator().manual_seed(6), dtype=dtype)
    (g_fast,) = torch.autograd.grad((out * G).sum(), w)
    (g_ref,) = torch.autograd.grad((ref * G).sum(), w)
    torch.testing.assert_close(g_fast, g_ref, atol=50 * TOL[dtype], rtol=0)


@pytest.mark.parametrize("kind", [0, 1, 2])
def test_face_curvature_fused_gradcheck(kind):
    mesh, R = _setup(torch.float64, n=1, scale=0.8, seed=6)
    assert gradcheck(lambda A: ops_curvature.face_curvature(A, mesh, kind), (R.clone().requires_grad_(),))


@pytest.mark.parametrize("kind", [0, 1, 2])
def test_face_curvature_fused_gradgradcheck(kind):
    """The hand-written backward is itself differentiable (create_graph, double backward); on two
    tets sharing a face (on the cube, 19 edges, it took 3-6 s per kind)."""
    mesh = _two_tets()
    R = Connection.random_on_mesh(mesh, generator=torch.Generator().manual_seed(6), scale=0.8).edge_rot
    A = R.clone().requires_grad_()
    assert gradgradcheck(lambda A: ops_curvature.face_curvature(A, mesh, kind), (A,))
    # an incoming gradient in the output's component-major layout
    assert gradgradcheck(lambda A: ops_curvature.face_curvature(A, mesh, kind).square(), (A,), fast_mode=True)


def test_face_curvature_general_rank_uses_matmul_path():
    from torchconn import son

    mesh = io.box(2)
    R = son.random_rotation(mesh.edges.shape[0], n=4, generator=torch.Generator().manual_seed(1),
                            dtype=torch.float64)
    torch.testing.assert_close(ops_curvature.face_curvature(R, mesh), _generic_face_curvature(R, mesh, -1, "two_prong"))


@pytest.mark.parametrize("kind", ["sqrt", "naive"])
@pytest.mark.parametrize("with_frames", [False, True])
def test_face_torsion_matches_generic_loop(kind, with_frames):
    from torchconn import torsion

    dtype = torch.float64
    mesh, R = _setup(dtype, scale=0.8, seed=7)
    frames = so3.random_rotation(mesh.vertices.shape[0], generator=torch.Generator().manual_seed(3),
                                 dtype=dtype) if with_frames else None
    w = so3.log(R).requires_grad_()
    out = ops_torsion.face_torsion(so3.exp(w), mesh, kind, frames)
    # generic loop path: a cut given as a tensor is not routed to the fast kernel
    ref = torsion.face_torsion(so3.exp(w), mesh, kind=kind, cut=torch.tensor(-1), frames=frames)
    torch.testing.assert_close(out, ref, atol=1e-13, rtol=0)
    G = torch.randn(out.shape, generator=torch.Generator().manual_seed(4), dtype=dtype)
    (g1,) = torch.autograd.grad((out * G).sum(), w)
    (g2,) = torch.autograd.grad((ref * G).sum(), w)
    torch.testing.assert_close(g1, g2, atol=1e-12, rtol=0)


def test_face_curvature_grad_in_output_layout_gradcheck():
    """The output is a (F, 3, 3) view of a component-major (9, F) array; elementwise consumers
    keep that layout in the incoming gradient (no transposed copy in backward): same gradient."""
    mesh, R = _setup(torch.float64, n=1, scale=0.8, seed=8)
    assert gradcheck(lambda A: ops_curvature.face_curvature(A, mesh, 0).square(), (R.clone().requires_grad_(),))
    A = R.clone().requires_grad_()
    out = ops_curvature.face_curvature(A, mesh, 0)
    (g_fast,) = torch.autograd.grad(out.square().sum(), A)
    (g_ref,) = torch.autograd.grad(_generic_face_curvature(A, mesh, 0, "holonomy").square().sum(), A)
    torch.testing.assert_close(g_fast, g_ref, atol=1e-12, rtol=0)


def test_face_torsion_with_shared_edge_frames_is_identical():
    dtype = torch.float64
    mesh, R = _setup(dtype, scale=0.8, seed=9)
    frames = so3.random_rotation(mesh.vertices.shape[0], generator=torch.Generator().manual_seed(5), dtype=dtype)
    w = so3.log(R).requires_grad_()
    f = so3.log(frames).requires_grad_()
    a = ops_torsion.face_torsion(so3.exp(w), mesh, "sqrt", so3.exp(f))
    Rw = so3.exp(w)
    b = ops_torsion.face_torsion(Rw, mesh, "sqrt", edge_frame_rot=ops_torsion.edge_frames(Rw, mesh, so3.exp(f)))
    assert torch.equal(a, b)
    G = torch.randn(a.shape, generator=torch.Generator().manual_seed(6), dtype=dtype)
    ga = torch.autograd.grad((a * G).sum(), (w, f))
    gb = torch.autograd.grad((b * G).sum(), (w, f))
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, atol=1e-13, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_frame_field_loss_shared_path_matches_term_by_term_composition(dtype):
    """FrameFieldLoss (edge gathers and F_i R_ij shared by tie and torsion, fused kernels)
    against the terms composed from the public single-term functions and the generic loop
    torsion: same values and gradients."""
    from torchconn import curvature, torsion
    from torchconn.frames import loss as losses

    mesh = io.box(2).to(dtype=dtype)
    g = torch.Generator().manual_seed(10)
    w = (0.3 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=dtype)).requires_grad_()
    p = (0.3 * torch.randn(mesh.vertices.shape[0], 3, generator=g, dtype=dtype)).requires_grad_()
    lf = losses.FrameFieldLoss(mesh, {k: 1.0 for k in losses.TERMS})
    out = lf(so3.exp(w), so3.exp(p))
    R, F = so3.exp(w), so3.exp(p)
    tie, _ = losses.tie_loss(R, F, mesh.edges)
    hol = curvature.face_curvature(R, mesh, kind="holonomy") + torch.eye(3, dtype=dtype)
    # torsion through the matchings, every face: R h^T with F_i R_ij = F_j h_ij (h without gradient)
    e = mesh.edges
    with torch.no_grad():
        _, h = octahedral.match(F[e[:, 1]], F[e[:, 0]] @ R)
    tor = torsion.face_torsion(R @ h.transpose(-1, -2), mesh, kind="sqrt", cut=torch.tensor(-1), frames=F)  # loop
    # the averaged d∇ on the regular tets (no face holonomy nearest a non-identity element)
    from torchconn.nn import AveragedCovariantD

    dd = AveragedCovariantD(mesh)(R, F)
    with torch.no_grad():
        regular = (octahedral.closest_element(hol)[0] == 0)[mesh.tet_faces].all(-1)
    X = mesh.vertices[mesh.tets]
    vol = torch.linalg.det(X[:, 1:] - X[:, :1]).abs() / 6
    ref = {"smooth": losses.smoothness_loss(R), "tie": tie, "flat": losses.symmetric_flatness_loss(hol),
           "torsion": ((tor ** 2).sum(-1) / lf.face_area).mean(),
           "dnabla": ((dd ** 2).sum(-1) / vol ** (2 / 3))[regular].mean(),
           "dirichlet": losses.matched_dirichlet_loss(F, mesh.edges)}
    tol = 5 * TOL[dtype]
    for k, v in ref.items():
        torch.testing.assert_close(out[k], v, atol=tol, rtol=tol)
    total_ref = sum(ref.values()) + out["align"] + out["feature"]
    g1 = torch.autograd.grad(out["total"], (w, p), retain_graph=True)
    g2 = torch.autograd.grad(total_ref, (w, p))
    for x, y in zip(g1, g2):
        torch.testing.assert_close(x, y, atol=100 * TOL[dtype], rtol=100 * TOL[dtype])
