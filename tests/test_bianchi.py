"""Tests of torchconn.bianchi: differential and algebraic Bianchi identities on small complexes,
the shared tet meshes and a built-in box; check() and its error messages."""
from __future__ import annotations

import math
import re

import pytest
import torch

from conftest import TET_MESHES, data_path
from torchconn import bianchi, curvature, io, so3
from torchconn import dnabla as D
from torchconn.mesh import TetMesh

F64 = torch.float64


# ----------------------------------------------------------------------------- complexes

def one_tet():
    return TetMesh(torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.]], dtype=F64), [[0, 1, 2, 3]])


def two_tets():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.2]], dtype=F64)
    return TetMesh(v, [[0, 1, 2, 3], [1, 2, 3, 4]], reorient=True)


def five_tet_star():
    """Five tets around the edge (0,0,-1)-(0,0,1)."""
    ring = [[math.cos(2 * math.pi * k / 5), math.sin(2 * math.pi * k / 5), 0.0] for k in range(5)]
    v = torch.tensor([[0, 0, -1.0], [0, 0, 1.0]] + ring, dtype=F64)
    tets = [[0, 1, 2 + k, 2 + (k + 1) % 5] for k in range(5)]
    return TetMesh(v, tets, reorient=True)


SMALL = {"one_tet": one_tet, "two_tets": two_tets, "five_tet_star": five_tet_star, "box": lambda: io.box(2)}


def haar(mesh, gen, dtype=F64):
    return so3.random_rotation(mesh.edges.shape[0], generator=gen, dtype=dtype)


def slow_differential(mesh, edge_rot):
    """⟨𝔡∇Ω,[abcd]⟩_a^d with named R's per tet (closed form of Ch. 5)."""
    out = []
    E = {tuple(e): k for k, e in enumerate(mesh.edges.tolist())}

    def R(i, j):
        return edge_rot[E[(i, j)]] if (i, j) in E else edge_rot[E[(j, i)]].T

    for a, b, c, d in mesh.tets.tolist():
        out.append(R(a, b) @ (R(b, c) @ R(c, d) - R(b, d)) - (R(a, c) @ R(c, d) - R(a, d))
                   + (R(a, b) @ R(b, d) - R(a, d)) - (R(a, b) @ R(b, c) - R(a, c)) @ R(c, d))
    return torch.stack(out)


# ----------------------------------------------------------------------------- identities

@pytest.mark.parametrize("name", list(SMALL))
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_bianchi_identities_small_complexes(name, dtype, gen):
    mesh = SMALL[name]().to(dtype=dtype)
    er = haar(mesh, gen, dtype)
    eps = 1e-12 if dtype == F64 else 1e-5
    raw = bianchi.differential_residual(er, mesh, reduce=False)
    assert raw.shape == (mesh.tets.shape[0], 3, 3)
    assert raw.abs().max() < eps
    assert bianchi.differential_residual(er, mesh, alternate=True).max() < 5 * eps
    alg = bianchi.algebraic_residual(er, mesh)
    assert alg.shape == (mesh.tets.shape[0],)
    assert alg.max() < 5 * eps
    # both sides of the algebraic identity are O(1) here, so the residual is meaningful
    assert D.averaged_dd_solder(er, mesh).abs().max() > 1e-2
    res = bianchi.check(er, mesh)
    assert set(res) == {"differential", "algebraic"}


def test_differential_residual_terms_are_not_trivially_zero(gen):
    """The closed form is a sum of four O(1) terms; the generic route reproduces its cancellation."""
    mesh = five_tet_star()
    er = haar(mesh, gen)
    ref = slow_differential(mesh, er)
    assert ref.abs().max() < 1e-12
    raw = bianchi.differential_residual(er, mesh, reduce=False)
    torch.testing.assert_close(raw, ref, atol=1e-12, rtol=0)
    # a non-exact "curvature" (one term with the wrong cut) leaves a large residual
    T = D.tet_transports(er, mesh)
    omega = D.unsymmetrized_vector(T, D.connection_form(T), matrix_values=True)
    wrong = D.unsymmetrized_lie(T, omega.transpose(-1, -2), [[0, 1, 2, 3]])
    assert wrong.abs().max() > 1e-2


def test_bianchi_on_small_shared_mesh(gen):
    name = TET_MESHES[0]  # sphere_r0.17.mesh, 3654 tets
    mesh = io.load_tet_mesh(data_path(name))
    er = haar(mesh, gen, mesh.vertices.dtype)
    res = bianchi.check(er, mesh)
    assert res["differential"] < 1e-12 and res["algebraic"] < 1e-12 * float(mesh.vertices.abs().max() + 1)


@pytest.mark.parametrize("name", TET_MESHES[1:])
def test_bianchi_on_large_shared_meshes(name, gen):
    mesh = io.load_tet_mesh(data_path(name))
    er = haar(mesh, gen, mesh.vertices.dtype)
    res = bianchi.check(er, mesh)
    assert res["differential"] < 1e-12 and res["algebraic"] < 1e-12 * float(mesh.vertices.abs().max() + 1)


def test_primal_dual_residual_and_check(gen):
    mesh = five_tet_star()
    Tn, F, E = mesh.tets.shape[0], mesh.faces.shape[0], mesh.edges.shape[0]
    dual = (so3.random_rotation(Tn, 4, generator=gen, dtype=F64), so3.random_rotation(F, 3, generator=gen, dtype=F64),
            torch.randn(E, 3, generator=gen, dtype=F64))
    assert bianchi.primal_dual_residual(*dual, mesh).max() < 1e-12
    assert D.primal_dual_dd_mesh(*dual, mesh).abs().max() > 1e-2
    res = bianchi.check(haar(mesh, gen), mesh, dual=dual)
    assert res["primal_dual"] < 1e-12


def test_gauge_invariance_of_residuals(gen):
    mesh = two_tets()
    er = haar(mesh, gen)
    G = so3.random_rotation(mesh.vertices.shape[0], generator=gen, dtype=F64)
    i, j = mesh.edges[:, 0], mesh.edges[:, 1]
    er2 = G[i] @ er @ G[j].transpose(-1, -2)
    assert bianchi.differential_residual(er2, mesh).max() < 1e-12
    assert bianchi.algebraic_residual(er2, mesh, frames=G.transpose(-1, -2)).max() < 1e-12
    # curvature as a Lie value transforms with G_eval (.) G_cut^T
    om, om2 = curvature.face_curvature(er, mesh), curvature.face_curvature(er2, mesh)
    a, c = mesh.faces[:, 0], mesh.faces[:, 2]
    torch.testing.assert_close(om2, G[a] @ om @ G[c].transpose(-1, -2), atol=1e-12, rtol=0)


def test_gradcheck_raw_residuals(gen):
    mesh = two_tets()
    params = (torch.randn(mesh.edges.shape[0], 3, generator=gen, dtype=F64) * 0.9).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: bianchi.differential_residual(so3.exp(p), mesh, reduce=False), (params,))
    assert torch.autograd.gradcheck(
        lambda p: bianchi.algebraic_residual(so3.exp(p), mesh, half_rot=so3.exp(0.5 * p), reduce=False), (params,))
    # and of the averaged d∇d∇θ itself at the mesh level
    assert torch.autograd.gradcheck(lambda p: D.averaged_dd_solder(so3.exp(p), mesh, half_rot=so3.exp(0.5 * p)), (params,))


# ----------------------------------------------------------------------------- failures

def test_check_raises_on_nan_rotation_and_names_tet(gen):
    mesh = five_tet_star()
    er = haar(mesh, gen).clone()
    # the edge (2,3) belongs to exactly one tet of the star
    e = int(((mesh.edges[:, 0] == 2) & (mesh.edges[:, 1] == 3)).nonzero())
    tets_with = ((mesh.tet_edges == e).any(1)).nonzero().flatten().tolist()
    er[e, 0, 0] = float("nan")
    with pytest.raises(bianchi.BianchiError, match=re.escape(f"NaN/inf on {len(tets_with)} tets, e.g. tets {tets_with}")):
        bianchi.check(er, mesh)


def test_assert_residual_names_worst_tets():
    res = torch.tensor([1e-16, 3e-3, 2e-16, 5e-2, 0.0], dtype=F64)
    with pytest.raises(bianchi.BianchiError, match=r"violated on 2 of 5 tets; worst tet 3: 5\.000e-02.*tet 1: 3\.000e-03"):
        bianchi.assert_residual(res, "algebraic", 1e-10)
    assert bianchi.assert_residual(res[[0, 2, 4]], "algebraic", 1e-10) == pytest.approx(2e-16)


def test_check_raises_on_broken_operator(gen, monkeypatch):
    """A deliberately broken wedge (wrong weight on the 1/2 term) must be caught and named."""
    mesh = two_tets()
    er = haar(mesh, gen)
    good = D.wedge_curvature_solder_tet

    def broken(T, th):
        out = good(T, th)
        R_ab, R_bc, R_ac = T[..., 0, 1, :, :], T[..., 1, 2, :, :], T[..., 0, 2, :, :]
        return out + 1e-3 * ((R_ab @ R_bc - R_ac) @ th[..., 2, 3, :, None]).squeeze(-1)

    monkeypatch.setattr(D, "wedge_curvature_solder_tet", broken)
    with pytest.raises(bianchi.BianchiError, match=r"algebraic Bianchi identity violated on 2 of 2 tets; worst tet \d"):
        bianchi.check(er, mesh)


def test_check_bad_input(gen):
    mesh = two_tets()
    with pytest.raises(ValueError, match="edges"):
        bianchi.check(so3.random_rotation(2, generator=gen, dtype=F64), mesh)


# ----------------------------------------------------------------------------- input, not identity

def test_non_orthogonal_connection_is_named_not_the_identity(gen):
    """float32 rotations cast to float64 (orthogonal to ~1e-6): issue 24 reported 'algebraic
    Bianchi identity violated on 1294 of 1296 tets'. The input is named: its worst edge (index
    and vertices) and residual, the float64 tolerance, and the remedy; projected, it passes."""
    from torchconn.nn import BianchiCheck

    mesh = io.box(2)
    R = haar(mesh, gen, torch.float32).double()
    err = torch.linalg.matrix_norm(R.transpose(-1, -2) @ R - torch.eye(3, dtype=F64))
    e = int(err.argmax())
    i, j = mesh.edges[e].tolist()
    pattern = (rf"the connection is not a rotation to the float64 tolerance 1e-09 on \d+ of {mesh.edges.shape[0]} "
               rf"edges; worst edge {e} = \({i}, {j}\): \|\|R_eᵀ R_e − I\|\|_F = {float(err[e]):.2e}.*"
               r"so3\.project_to_rotation")
    with pytest.raises(ValueError, match="bianchi.check: " + pattern):
        bianchi.check(R, mesh)
    with pytest.raises(ValueError, match="BianchiCheck: " + pattern):
        BianchiCheck(mesh)(R)
    res = bianchi.check(so3.project_to_rotation(R), mesh)
    assert res["algebraic"] < 1e-13 and res["differential"] < 1e-13
    # the float32 tolerance (1e-4) accepts the same rotations in float32
    assert bianchi.check(R.float(), mesh)["algebraic"] < 1e-4


def test_reflection_and_batch_item_are_named(gen):
    mesh = two_tets()
    R = haar(mesh, gen)
    bad = R.clone()
    bad[3] = -R[3]  # det -1, orthogonal
    i, j = mesh.edges[3].tolist()
    with pytest.raises(ValueError, match=rf"1 of 18 edges; worst edge 3 = \({i}, {j}\) of batch item \(1,\): "
                                         r"det R_e = −1 \(a reflection\)"):
        bianchi.check(torch.stack((R, bad)), mesh)


def test_identity_failure_within_the_rotation_tolerance_mentions_orthogonality(gen):
    """Orthogonal to ~6e-10 (inside float64's rotation tolerance 1e-9), checked against a tighter
    identity tolerance: the BianchiError says how orthogonal the connection is, and the remedy."""
    mesh = io.box(2)
    R = haar(mesh, gen)
    S = torch.randn(R.shape, generator=gen, dtype=F64)
    S = S + S.transpose(-1, -2)
    R = R @ (torch.eye(3, dtype=F64) + 3e-10 * S / torch.linalg.matrix_norm(S)[..., None, None])
    bianchi.check(R, mesh)  # default tolerance: passes
    with pytest.raises(bianchi.BianchiError, match=r"algebraic Bianchi identity violated.*orthogonal only to "
                                                   r"\d\.\de-10.*so3\.project_to_rotation"):
        bianchi.check(R, mesh, atol=1e-13)
