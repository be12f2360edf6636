"""Band-4 spherical harmonics, the SH frame representation and the Ray et al. 2016 baseline."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import data_path
from torchconn import io, so3
from torchconn.frames import octahedral
from torchconn.frames import frame_metrics
from torchconn.frames import sh


def _sphere_quadrature(n_z: int = 12, n_phi: int = 24):
    """Product rule exact for polynomials of degree <= 2*n_z-1 in z and < n_phi in phi."""
    z, wz = np.polynomial.legendre.leggauss(n_z)
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    Z, P = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - Z**2)
    pts = np.stack([r * np.cos(P), r * np.sin(P), Z], -1).reshape(-1, 3)
    w = (wz[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None, :]).reshape(-1)
    return torch.tensor(pts), torch.tensor(w)


def _project_band4(fun, pts, w):
    """Coefficients <fun, Y_m> by quadrature (independent of the library's rotation code)."""
    return (sh.sh_basis(pts) * (w * fun(pts))[:, None]).sum(0)


def test_basis_is_orthonormal():
    pts, w = _sphere_quadrature()
    Y = sh.sh_basis(pts)
    gram = Y.T @ (w[:, None] * Y)
    assert torch.allclose(gram, torch.eye(9, dtype=torch.float64), atol=1e-12)


def test_reference_vector_is_the_projection_of_x4_y4_z4():
    pts, w = _sphere_quadrature()
    c = _project_band4(lambda x: (x**4).sum(-1), pts, w)
    c = c / c.norm()
    q0 = sh.reference_sh(torch.float64)
    assert torch.allclose(c, q0, atol=1e-12)
    assert abs(q0[4] - math.sqrt(7 / 12)) < 1e-15 and abs(q0[8] - math.sqrt(5 / 12)) < 1e-15


def test_frame_to_sh_of_identity_and_invariance(gen):
    eye = torch.eye(3, dtype=torch.float64)
    q = sh.frame_to_sh(eye)
    assert abs(float(q.norm()) - 1.0) < 1e-14
    assert torch.allclose(q, sh.reference_sh(torch.float64), atol=1e-14)
    F = so3.random_rotation(16, generator=gen, dtype=torch.float64)
    qF = sh.frame_to_sh(F)
    assert torch.allclose(qF.norm(dim=-1), torch.ones(16, dtype=torch.float64), atol=1e-13)
    for g in octahedral.group(torch.float64):
        assert torch.allclose(sh.frame_to_sh(F @ g), qF, atol=1e-13)
    # a generic rotation changes q
    R = so3.exp(torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64))
    assert (sh.frame_to_sh(R) - q).norm() > 0.1


def test_frame_to_sh_equals_quadrature_of_the_rotated_function(gen):
    pts, w = _sphere_quadrature()
    F = so3.random_rotation(3, generator=gen, dtype=torch.float64)
    for Fk in F:
        ref = _project_band4(lambda x: ((x @ Fk) ** 4).sum(-1), pts, w)
        ref = ref / ref.norm()
        assert torch.allclose(sh.frame_to_sh(Fk), ref, atol=1e-12)


def test_sh_rotation_homomorphism_and_orthogonal(gen):
    R1 = so3.random_rotation(10, generator=gen, dtype=torch.float64)
    R2 = so3.random_rotation(10, generator=gen, dtype=torch.float64)
    D1, D2, D12 = sh.sh_rotation(R1), sh.sh_rotation(R2), sh.sh_rotation(R1 @ R2)
    eye9 = torch.eye(9, dtype=torch.float64)
    assert D1.shape == (10, 9, 9)
    assert torch.allclose(D12, D1 @ D2, atol=1e-12)
    assert torch.allclose(D1.transpose(-1, -2) @ D1, eye9.expand(10, 9, 9), atol=1e-12)
    assert torch.allclose(sh.sh_rotation(torch.eye(3, dtype=torch.float64)), eye9, atol=1e-13)
    q0 = sh.reference_sh(torch.float64)
    assert torch.allclose(D1 @ q0, sh.frame_to_sh(R1), atol=1e-12)
    # definition: (D q) . Y(x) = q . Y(R^T x) at random points
    x = torch.nn.functional.normalize(torch.randn(7, 3, generator=gen, dtype=torch.float64), dim=-1)
    q = torch.randn(9, generator=gen, dtype=torch.float64)
    lhs = sh.sh_basis(x) @ (D1[0] @ q)
    rhs = sh.sh_basis(x @ R1[0]) @ q
    assert torch.allclose(lhs, rhs, atol=1e-12)


def test_generators_exponentiate_to_axis_rotations():
    L = sh.sh_generators(torch.float64)
    assert torch.allclose(L, -L.transpose(-1, -2), atol=1e-14)
    eye = torch.eye(3, dtype=torch.float64)
    for k in range(3):
        for t in (0.3, 1.1, -2.5):
            assert torch.allclose(torch.linalg.matrix_exp(t * L[k]), sh.sh_rotation(so3.exp(t * eye[k])), atol=1e-12)
    # Lz couples m with -m with weight |m| (a rotation by m*t in each (m, -m) plane)
    Lz = L[2]
    for i, m in enumerate(range(-4, 5)):
        assert abs(abs(float(Lz[8 - i, i])) - abs(m)) < 1e-12
        assert abs(float(Lz[:, i].abs().sum()) - abs(m)) < 1e-12


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-6), (torch.float32, 1e-2)])
def test_sh_to_frame_recovers_frames_up_to_O(gen, dtype, tol):
    F = so3.random_rotation(2, 300, generator=gen, dtype=dtype)
    Fr = sh.sh_to_frame(sh.frame_to_sh(F) * 3.0)  # scale does not matter
    assert Fr.shape == (2, 300, 3, 3) and Fr.dtype == dtype
    _, g = octahedral.match(Fr, F)
    err = so3.geodesic_distance(Fr @ g, F)
    assert float(err.max()) < tol
    assert torch.allclose(Fr.transpose(-1, -2) @ Fr, torch.eye(3, dtype=dtype).expand_as(Fr), atol=10 * tol)


def test_sh_to_frame_warm_start(gen):
    F = so3.random_rotation(500, generator=gen, dtype=torch.float64)
    q = sh.frame_to_sh(F)
    # a start near the answer (0.2 rad off) converges from it alone; the result is F up to O
    near = so3.exp(0.2 * torch.nn.functional.normalize(torch.randn(500, 3, generator=gen, dtype=torch.float64),
                                                        dim=-1)) @ F
    Fw = sh.sh_to_frame(q, n_restarts=1, init=near)
    _, g = octahedral.match(Fw, F)
    assert float(so3.geodesic_distance(Fw @ g, F).max()) < 1e-6
    # with the exact frames as init the answer is the init itself (no element of O is chosen)
    assert torch.allclose(sh.sh_to_frame(q, n_restarts=1, init=F), F, atol=1e-8)
    # init is one more start: with the fixed restarts the residual is never worse than without
    res = lambda X: (sh.frame_to_sh(X) - q).norm(dim=-1)  # noqa: E731
    far = so3.random_rotation(500, generator=gen, dtype=torch.float64)
    assert bool((res(sh.sh_to_frame(q, n_restarts=8, init=far)) <= res(sh.sh_to_frame(q, n_restarts=1, init=far)) + 1e-12).all())
    with pytest.raises(ValueError, match="init must have shape"):
        sh.sh_to_frame(q, init=F[:3])


def test_sh_to_frame_bad_input():
    with pytest.raises(ValueError, match=r"\(\.\.\., 9\)"):
        sh.sh_to_frame(torch.zeros(4, 8))
    with pytest.raises(TypeError, match="floating"):
        sh.sh_to_frame(torch.zeros(4, 9, dtype=torch.long))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        sh.frame_to_sh(torch.zeros(3, 4))


def test_boundary_constraint_characterizes_aligned_frames(gen):
    n = torch.nn.functional.normalize(torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=-1)
    n[0] = torch.tensor([0.0, 0.0, -1.0])
    n[1] = torch.tensor([0.0, 0.0, 1.0])
    A, t = sh.boundary_constraint(n)
    assert A.shape == (50, 7, 9) and t.shape == (50, 7)
    # frames with one axis along n: rotate a random frame so its axis k lands on n
    F = so3.random_rotation(50, generator=gen, dtype=torch.float64)
    Fa = sh._snap_axis(F, n)
    c = (Fa * n[:, :, None]).sum(-2).abs().amax(-1)
    assert torch.allclose(c, torch.ones(50, dtype=torch.float64), atol=1e-12)
    q = sh.frame_to_sh(Fa)
    assert torch.allclose((A @ q[..., None])[..., 0], t, atol=1e-12)
    # generic frames violate it
    r = (A @ sh.frame_to_sh(F)[..., None])[..., 0] - t
    assert float(r.norm(dim=-1).min()) > 1e-3


def _is_in_O(F, atol):
    _, g = octahedral.closest_element(F)
    return (F - g).abs().amax() < atol


def test_box_gives_axis_aligned_frames_and_no_singularity():
    m = io.box(3)
    F = sh.sh_frame_field(m)
    assert F.shape == (m.vertices.shape[0], 3, 3) and F.dtype == m.vertices.dtype
    assert _is_in_O(F, 1e-6)
    mask, sing = octahedral.singular_faces(F, m)
    assert int(mask.sum()) == 0 and sing.shape == (0, 3)
    assert int(octahedral.tets_with_one_singular_face(mask, m).sum()) == 0
    met = frame_metrics(F, m)
    assert met["smoothness_mean_deg"] < 1e-4 and met["feature_alignment_max_deg"] < 1e-4
    # the linear step alone (no nonlinear iterations) already gives the exact field
    F0 = sh.sh_frame_field(m, n_smooth_iters=0)
    assert _is_in_O(F0, 1e-6)


def test_box_rotated_follows_the_rotation(gen):
    m = io.box(2)
    R = so3.exp(torch.tensor([0.3, -0.5, 0.7], dtype=torch.float64))
    from torchconn.mesh import TetMesh

    mr = TetMesh(m.vertices @ R.T, m.tets)
    F = sh.sh_frame_field(mr)
    assert _is_in_O(R.T @ F, 1e-6)


def test_sphere_alignment_and_singularities():
    m = io.load_tet_mesh(data_path("sphere_r0.17.mesh"))
    F = sh.sh_frame_field(m)
    so3.check_rotation(F)
    met = frame_metrics(F, m)
    assert met["n_feature_vertices"] == 0
    assert met["alignment_mean_deg"] < 1.0 and met["alignment_max_deg"] < 1.0
    assert met["n_singular_faces"] > 0
    # the nonlinear step does not increase the SH energy of the linear projection
    F0 = sh.sh_frame_field(m, n_smooth_iters=0)
    e = m.edges

    def energy(Fx):
        q = sh.frame_to_sh(Fx)
        return float(((q[e[:, 0]] - q[e[:, 1]]) ** 2).sum())

    assert energy(F) < energy(F0)
    assert met["smoothness_mean_deg"] < frame_metrics(F0, m)["smoothness_mean_deg"]


def test_sh_frame_field_bad_input():
    with pytest.raises(TypeError, match="TetMesh"):
        sh.sh_frame_field(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="boundary_weight"):
        sh.sh_frame_field(io.box(2), boundary_weight=0.0)


def test_gear_runs_and_aligns():
    m = io.load_tet_mesh(data_path("78322_gear.2.mesh"))
    F = sh.sh_frame_field(m)
    met = frame_metrics(F, m)
    assert met["n_feature_vertices"] > 0
    assert met["alignment_max_deg"] < 1e-6
    assert met["feature_alignment_mean_deg"] < 10.0
    assert met["smoothness_mean_deg"] < 10.0


def test_sh_rotation_equals_exponential_of_generators(gen):
    """Independent route: D(R) = matrix_exp(sum_k w_k L_k) with w = log(R) (Lie homomorphism)."""
    R = so3.random_rotation(20, generator=gen, dtype=torch.float64)
    w = so3.log(R)
    L = sh.sh_generators(torch.float64)
    D = torch.linalg.matrix_exp(torch.einsum("nk,kab->nab", w, L))
    assert torch.allclose(D, sh.sh_rotation(R), atol=1e-11)


def test_frame_to_sh_gradcheck(gen):
    w = (0.5 * torch.randn(4, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda w: sh.frame_to_sh(so3.exp(w)), (w,))
    assert torch.autograd.gradcheck(lambda w: sh.sh_rotation(so3.exp(w)), (w,))


def test_float32_box():
    m = io.box(2, dtype=torch.float32)
    F = sh.sh_frame_field(m)
    assert F.dtype == torch.float32
    assert _is_in_O(F, 1e-4)


