"""The exact identities of the report on every tet mesh of ../shared/data (float64, Haar-random
rotations on every edge, not near-identity ones): issue 3's "on real meshes" layer.

Each identity is also tested on hand-built small complexes in the per-module test files; here
the same statements are checked on tens of thousands of cells at once.
"""
from __future__ import annotations

import pytest
import torch

from conftest import TET_MESHES, data_path
from torchconn import bianchi, chains, curvature, dnabla, io, so3, torsion, transport
from torchconn.dec.transport import orient

F64 = torch.float64
TOL = 1e-12


@pytest.fixture(scope="module", params=TET_MESHES)
def shared(request):
    mesh = io.load_tet_mesh(data_path(request.param))
    gen = torch.Generator().manual_seed(7)
    R = so3.random_rotation(mesh.n_edges, generator=gen, dtype=F64)
    G = so3.random_rotation(mesh.n_vertices, generator=gen, dtype=F64)
    return request.param, mesh, R, G


def _gauge(R, G, mesh):
    i, j = mesh.edges[:, 0], mesh.edges[:, 1]
    return G[i] @ R @ G[j].transpose(-1, -2)


def test_two_prong_is_holonomy_times_prong(shared):
    """<Ω,[abc]>_a^c = (R_ab R_bc R_ca − I) R_ac on every face; cut 0 is the holonomy form."""
    _, mesh, R, _ = shared
    two = curvature.face_curvature(R, mesh, cut=2)
    hol = curvature.face_curvature(R, mesh, kind="holonomy")
    Rac = R[mesh.face_edges[:, 1]]  # canonical (a, c): prong a -> c of the sorted face
    assert (two - hol @ Rac).abs().max() < TOL
    assert (curvature.face_curvature(R, mesh, cut=0) - hol).abs().max() < TOL
    # and 𝔡∇w on the face template is the same two-prong (Ch. 5: <𝔡∇w,[abc]>_a^c = R_ab R_bc − R_ac)
    T = transport.dense_simplex_transports(R[mesh.face_edges[:, [2, 1, 0]]], 3)  # pairs ab, ac, bc
    tri = torch.tensor([[0, 1, 2]])
    dw = dnabla.unsymmetrized_vector(T, dnabla.connection_form(T), tri, matrix_values=True).squeeze(-3)
    assert (dw - two).abs().max() < TOL
    assert two.abs().max() > 0.1  # random rotations: a real test


def test_summability_over_tet_boundaries(shared):
    """(3.2.2): the faces of ∂[abcd] summed at a common evaluation/cut fiber give 𝔡∇Ω = 0."""
    _, mesh, R, _ = shared
    res = bianchi.differential_residual(R, mesh)
    assert res.shape == (mesh.n_tets,) and res.max() < TOL


def test_gauge_covariance(shared):
    """Curvature X -> G_a X G_c^T, torsion (frames) and averaged d∇d∇θ̃ (frames) -> G_a x."""
    _, mesh, R, G = shared
    Rg = _gauge(R, G, mesh)
    a, c = mesh.faces[:, 0], mesh.faces[:, 2]
    two, two_g = curvature.face_curvature(R, mesh), curvature.face_curvature(Rg, mesh)
    assert (two_g - G[a] @ two @ G[c].transpose(-1, -2)).abs().max() < TOL
    hol, hol_g = (curvature.face_curvature(X, mesh, kind="holonomy") for X in (R, Rg))
    assert (hol_g - G[a] @ hol @ G[a].transpose(-1, -2)).abs().max() < TOL
    # frames F are the columns of the vertex frames; the gauge G changes them to F G^T
    Fr = so3.random_rotation(mesh.n_vertices, generator=torch.Generator().manual_seed(8), dtype=F64)
    Frg = Fr @ G.transpose(-1, -2)
    scale = float(mesh.vertices.abs().max())
    t, t_g = torsion.face_torsion(R, mesh, frames=Fr), torsion.face_torsion(Rg, mesh, frames=Frg)
    assert (t_g - (G[a] @ t[..., None]).squeeze(-1)).abs().max() < TOL * scale
    t0 = mesh.tets[:, 0]
    d, d_g = dnabla.averaged_dd_solder(R, mesh, frames=Fr), dnabla.averaged_dd_solder(Rg, mesh, frames=Frg)
    assert (d_g - (G[t0] @ d[..., None]).squeeze(-1)).abs().max() < TOL * scale
    assert d.abs().max() > 1e-3 * scale


def test_algebraic_bianchi_and_explicit_wedge(shared):
    """𝔡∇ Alt 𝔡∇ Alt θ̃ equals the explicit Ch. 5 tet formula (the discrete Ω∧θ) on every tet."""
    _, mesh, R, _ = shared
    scale = float(mesh.vertices.abs().max())
    assert bianchi.algebraic_residual(R, mesh).max() < TOL * scale
    res = bianchi.check(R, mesh)
    assert res["differential"] < TOL and res["algebraic"] < TOL * scale


def test_behs21_twice_is_curvature_times_theta(shared):
    """Ch. 4: BEHS21 applied twice to the plain θ is (R_ab R_bc − R_ac) θ_cd."""
    _, mesh, R, _ = shared
    a, b, c, d = mesh.tets.unbind(1)
    te, ts = mesh.tet_edges, mesh.tet_edge_signs
    Rab, Rbc, Rac = (orient(R, te[:, k], ts[:, k]) for k in (0, 3, 1))
    theta_cd = mesh.vertices[d] - mesh.vertices[c]
    ref = ((Rab @ Rbc - Rac) @ theta_cd[..., None]).squeeze(-1)
    got = dnabla.behs21_dd_solder(R, mesh)
    assert (got - ref).abs().max() < TOL * float(mesh.vertices.abs().max())


def test_chain_accumulation_on_boundary_patch(shared):
    """Sec. 3.6: face-by-face accumulation over a 60-face disk of the boundary surface equals the
    two-prong of the region's boundary loop."""
    name, mesh, R, _ = shared
    cx = mesh.boundary_complex(compact=False)  # keeps the mesh's vertex ids
    e, sgn = mesh.edge_index(cx.edges[:, 0], cx.edges[:, 1])
    assert (sgn > 0).all()
    Rb = R[e]  # rotations of the surface's canonical edges
    ids = chains.patch(cx, 0, 60)
    loop = chains.boundary_loop(cx, ids)
    ev, cut = int(loop[0]), int(loop[len(loop) // 2])
    acc = chains.curvature_over_chain(Rb, cx, ids, ev, cut)
    le, ls = cx.edge_index(loop, torch.roll(loop, -1))
    lr = orient(Rb, le, ls)  # R_{x_k x_{k+1}} along the boundary loop
    ref = curvature.two_prong(lr, len(loop) // 2)
    assert (acc - ref).abs().max() < 1e-11, name
    assert ref.abs().max() > 0.1
