"""The compiled frame-field loss kernel (frames/kernels/csrc/frame_loss.c, torchconn.frames.kernels.frame_loss)
against the modules of FrameFieldLoss (switch off: the fused kernel does not serve and the loss runs
its term modules, torchconn.frames.terms, through the library's operators).

Layers: values and gradients (through so3.exp parameters) equal the torch path to round-off on
a small box and on a shared mesh, float32 and float64, every term alone and together, both
``rho``; float64 gradcheck of the compiled path; any combination of the returned terms
differentiates exactly (the backward re-runs the kernel with the incoming weights); results
do not depend on the thread count beyond round-off and are deterministic for a fixed count;
fallback and errors.
"""
import pytest
import torch

import torchconn.ops
from torchconn import io, so3
from torchconn.ops import native
from torchconn.frames.kernels.frame_loss import COMPILED_TERMS, frame_loss_terms
from torchconn.frames import octahedral
from torchconn.frames.loss import FrameFieldLoss, TERMS
from torchconn.tolerances import get_eps

from conftest import data_path

pytestmark = pytest.mark.skipif(native.library("frame_loss") is None,
                                reason="no C compiler (or TORCHCONN_NATIVE=0): the compiled kernel cannot be built")

ALL = {k: 1.0 for k in TERMS}


@pytest.fixture(autouse=True)
def _compiled_on():
    with torchconn.ops.compiled(True):
        yield


def _torch_path(loss):
    """``loss`` evaluated with the compiled kernels switched off (its term modules)."""
    def call(R, F):
        with torchconn.ops.compiled(False):
            return loss(R, F)
    return call


def _applies(mesh, R, F, weights=ALL):
    return frame_loss_terms(R, F, mesh, octahedral.group(torch.float64), weights, 2.0, 1e-3) is not None


def _params(mesh, dtype, seed=0, scale=0.15):
    g = torch.Generator().manual_seed(seed)
    w = scale * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=torch.float64)
    phi = scale * torch.randn(mesh.n_vertices, 3, generator=g, dtype=torch.float64)
    return w.to(dtype), phi.to(dtype)


def _run(loss, w, phi, key="total"):
    w = w.clone().requires_grad_()
    phi = phi.clone().requires_grad_()
    out = loss(so3.exp(w), so3.exp(phi))
    out[key].backward()
    grads = [torch.zeros_like(x) if x.grad is None else x.grad for x in (w, phi)]
    return {k: float(v.detach()) for k, v in out.items()}, *grads


def _compare(mesh, weights, dtype, power, key="total", seed=0):
    kw = dict(smooth_power=power, align_kind="angle")
    w, phi = _params(mesh, dtype, seed)
    assert _applies(mesh, so3.exp(w), so3.exp(phi), weights)
    a = _run(FrameFieldLoss(mesh, weights, **kw), w, phi, key=key)
    b = _run(_torch_path(FrameFieldLoss(mesh, weights, **kw)), w, phi, key=key)
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    assert a[0].keys() == b[0].keys()
    for k in a[0]:
        assert abs(a[0][k] - b[0][k]) <= tol * max(1.0, abs(b[0][k])), (k, a[0][k], b[0][k])
    scale = max(1.0, float(b[1].abs().max()), float(b[2].abs().max()))
    assert float((a[1] - b[1]).abs().max()) <= tol * scale
    assert float((a[2] - b[2]).abs().max()) <= tol * scale


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("power", [2.0, 1.0, 1.5])
def test_all_terms_match_torch_path(dtype, power):
    """Powers 1 and 2 run the kernel's vectorized blocks, another power its scalar edge passes."""
    _compare(io.box(3), ALL, dtype, power)


@pytest.mark.parametrize("weights", [{"smooth": 1.0}, {"tie": 2.0}, {"flat": 0.5}, {"torsion": 1.0},
                                     {"dirichlet": 1.0}, {"dnabla": 1.0, "smooth": 1.0},
                                     {"tie": 1.0, "torsion": 3.0}, {"smooth": 1.0, "align": 1.0}])
def test_single_terms_match_torch_path(weights):
    _compare(io.box(3), weights, torch.float64, 1.0)


@pytest.mark.parametrize("key", ["tie", "flat", "torsion", "smooth", "dirichlet", "dnabla"])
def test_backward_of_one_term_is_exact(key):
    """A backward of one returned term (weights not proportional to the loss weights) re-runs the kernel."""
    _compare(io.box(3), {"smooth": 1.0, "tie": 2.0, "flat": 0.1, "torsion": 0.01, "dnabla": 0.01, "dirichlet": 0.5},
             torch.float64, 1.0, key=key)


def test_matches_torch_path_on_shared_mesh():
    path = data_path("sphere_r0.17.mesh")
    mesh = io.load_tet_mesh(path).to(dtype=torch.float64)
    _compare(mesh, ALL, torch.float64, 1.0, seed=3)
    _compare(mesh, ALL, torch.float64, 2.0, seed=4)


def test_gradcheck_through_exp_params():
    mesh = io.box(1)
    loss = FrameFieldLoss(mesh, {"smooth": 1.0, "tie": 1.0, "flat": 1.0, "torsion": 1.0, "dirichlet": 1.0},
                          smooth_power=1.0)
    w, phi = _params(mesh, torch.float64, seed=5, scale=0.3)
    assert _applies(mesh, so3.exp(w), so3.exp(phi))

    def f(w, phi):
        return loss(so3.exp(w), so3.exp(phi))["total"]

    assert torch.autograd.gradcheck(f, (w.requires_grad_(), phi.requires_grad_()), eps=1e-6, atol=1e-7)


def test_no_grad_values_and_torsion_mask():
    mesh = io.box(2)
    w, phi = _params(mesh, torch.float64, seed=1, scale=1.5)  # large: many relabeled edges
    a = FrameFieldLoss(mesh, ALL)
    b = _torch_path(FrameFieldLoss(mesh, ALL))
    with torch.no_grad():
        va, vb = a(so3.exp(w), so3.exp(phi)), b(so3.exp(w), so3.exp(phi))
    for k in va:
        assert abs(float(va[k]) - float(vb[k])) <= 1e-12 * max(1.0, abs(float(vb[k])))


def test_relabeled_faces_are_in_the_torsion_through_the_matchings():
    """Every edge turns the frames by 90 degrees (matched h != I everywhere): through the matchings
    ``R h^T`` is the identity on every edge, so the identity frames' torsion is 0 to round-off on
    every face -- no face is left out, and the relabeling does not read as torsion."""
    mesh = io.box(1).to(dtype=torch.float64)
    E, V = mesh.edges.shape[0], mesh.n_vertices
    z90 = so3.rot_z(torch.tensor(torch.pi / 2, dtype=torch.float64))
    R = z90.expand(E, 3, 3).clone().requires_grad_()
    Fr = torch.eye(3, dtype=torch.float64).expand(V, 3, 3).clone().requires_grad_()
    assert _applies(mesh, R, Fr, {"tie": 1.0, "torsion": 1.0})
    out = FrameFieldLoss(mesh, {"tie": 1.0, "torsion": 1.0})(R, Fr)
    ref = _torch_path(FrameFieldLoss(mesh, {"tie": 1.0, "torsion": 1.0}))(R.detach(), Fr.detach())
    assert abs(float(out["torsion"].detach())) <= 1e-28 and abs(float(ref["torsion"])) <= 1e-28
    out["total"].backward()
    assert torch.isfinite(R.grad).all() and torch.isfinite(Fr.grad).all()


def test_thread_count_only_changes_round_off_and_is_deterministic():
    mesh = io.box(4)
    loss = FrameFieldLoss(mesh, ALL, smooth_power=1.0)
    w, phi = _params(mesh, torch.float64, seed=2)
    assert _applies(mesh, so3.exp(w), so3.exp(phi))
    old = torch.get_num_threads()
    try:
        res = {}
        for nt in (1, 2, 3, 2):
            torch.set_num_threads(nt)
            v, gw, gp = _run(loss, w, phi)
            if nt in res:  # same thread count: bitwise identical
                assert v == res[nt][0] and torch.equal(gw, res[nt][1]) and torch.equal(gp, res[nt][2])
            res[nt] = (v, gw, gp)
        for nt in (2, 3):
            assert abs(res[nt][0]["total"] - res[1][0]["total"]) <= 1e-13
            assert float((res[nt][1] - res[1][1]).abs().max()) <= 1e-15
    finally:
        torch.set_num_threads(old)


def test_fallback_and_errors():
    mesh = io.box(1)
    w, phi = _params(mesh, torch.float64)
    R, Fr = so3.exp(w), so3.exp(phi)
    # wrong shapes / no term of the op / float16 (no C kernel for it): the fast path does not serve
    # (the loss's modules run)
    assert _applies(mesh, R, Fr)
    assert not _applies(mesh, R[:-1], Fr)
    assert not torchconn.ops.can_use_compiled("frame_loss", R.half(), Fr.half())
    assert not _applies(mesh, R.half(), Fr.half())
    assert not _applies(mesh, R, Fr, {"align": 1.0})
    with pytest.raises(TypeError):
        FrameFieldLoss(mesh, ALL, native=True)  # the kernel is chosen by the switch, not by a flag
    # switched off: the modules run, same values
    auto = FrameFieldLoss(mesh, ALL)
    v_native = float(auto(R, Fr)["total"])
    with torchconn.ops.compiled(False):
        assert not torchconn.ops.can_use_compiled("frame_loss", R, Fr)
        assert not _applies(mesh, R, Fr)
        assert abs(float(auto(R, Fr)["total"]) - v_native) <= 1e-12


def test_group_table_order_is_checked():
    mesh = io.box(1)
    w, phi = _params(mesh, torch.float64)
    R, Fr = so3.exp(w), so3.exp(phi)
    group = octahedral.group(torch.float64)
    assert frame_loss_terms(R, Fr, mesh, group, ALL, 2.0, 1e-3) is not None
    with pytest.raises(RuntimeError, match="score table"):
        frame_loss_terms(R, Fr, mesh, group.flip(0), ALL, 2.0, 1e-3)  # another order of the same group


def test_terms_constant_lists_the_kernel_terms():
    assert set(COMPILED_TERMS) <= set(TERMS) and get_eps("identity", torch.float64) > 0
