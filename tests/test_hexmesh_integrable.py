"""Integrable coframes as a torsion problem (torchconn.hexmesh.integrable; issue 31, step 2).

* the loop torsion of the corner complex's quads (the library's ``two_prong``) is the tangential
  jump ``B_t0 e - R_f^T B_t1 e`` on every face, against a per-face reference loop; its solder form is
  ``torsion.solder_form`` of the corner complex with the coframes as frames;
* it is zero on the gradient of every seamless map (the box's identity map, a rotated box, random
  seamless maps of the box and of the valence-3 prism) and not zero on the prism's rotation field;
* the sparse quadratic terms equal the operator's energies; gradcheck / gradgradcheck in float64;
* the alignment constraints hold on every coframe of the space; the axes carried around the
  singular edges are those of a valid map; a tet whose constraints admit no positive coframe is
  reported;
* the continuation drives the torsion of the prism's field to round-off, no coframe inverted, and
  the seamless map that fits the coframes is valid; the box's field is integrable already;
* ``SeamlessProblem.with_targets``: the field's coframes give the default objective, a valid map's
  gradients give that map back; bad targets are clear errors.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from torchconn import io, so3
from torchconn import torsion as tc_torsion
from torchconn.hexmesh import hex_mesh, integer_grid_map, tet_charts
from torchconn.hexmesh import integrable as I
from torchconn.hexmesh.cut import group_matrices
from torchconn.hexmesh.injective import TetJacobians
from torchconn.hexmesh.quantize import solve_fixed
from torchconn.hexmesh.seamless import build_problem
from torchconn.mesh import TetMesh

from test_hexmesh_map import axis_prism


def _identity(mesh):
    return torch.eye(3, dtype=torch.float64).expand(mesh.n_tets, 3, 3).clone()


def _setup(mesh, F, h):
    charts = tet_charts(mesh, F)
    prob = build_problem(mesh, charts, h)
    return charts, prob, I.corner_complex(mesh, charts, h)


def _grads(mesh, uvw: np.ndarray) -> np.ndarray:
    """``(T, 3, 3)`` gradients ``B_t`` of a map given by its corner parameters ``uvw (T, 4, 3)``."""
    X = mesh.vertices.double().numpy()[mesh.tets.numpy()]
    Em = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))
    Um = np.transpose(uvw[:, 1:] - uvw[:, :1], (0, 2, 1))
    return Um @ np.linalg.inv(Em)


@pytest.fixture(scope="module")
def prism_map():
    """The valid map of the valence-3 prism (on the refined mesh it lives on), h = 0.3."""
    mesh, F = axis_prism(turns=4.0)
    m = integer_grid_map(mesh, F, edge_length=0.3)
    assert m.validity.valid, m.validity.reasons
    return m


@pytest.fixture(scope="module")
def prism():
    mesh, F = axis_prism(turns=4.0)
    h = 0.3
    charts, prob, cc = _setup(mesh, F, h)
    return mesh, F, h, charts, prob, cc


# ----------------------------------------------------------------------------- the torsion
def test_quad_torsion_is_the_tangential_jump_on_every_face(prism):
    mesh, _, _, charts, _, cc = prism
    assert (cc.face_rot != np.eye(3)).any()  # cut faces: transports other than I are exercised
    g = torch.Generator().manual_seed(0)
    B = torch.randn(mesh.n_tets, 3, 3, generator=g, dtype=torch.float64)
    th = I.quad_torsion(cc, B).numpy()
    # slow reference: every interior face, each of its three edges
    X = mesh.vertices.double().numpy()
    faces, face_tets = mesh.faces.numpy(), mesh.face_tets.numpy()
    G = group_matrices().astype(np.float64)
    Bn = B.numpy()
    ref = []
    for f in np.nonzero(charts.interior_face)[0]:
        t0, t1 = face_tets[f]
        R = G[charts.face_rot[f]]
        for p, q in ((0, 1), (1, 2), (2, 0)):
            e = X[faces[f, q]] - X[faces[f, p]]
            ref.append(Bn[t0] @ e - R.T @ (Bn[t1] @ e))
    np.testing.assert_allclose(th, np.array(ref), rtol=0, atol=1e-12)


def test_solder_form_is_the_library_solder_form_of_the_corner_complex(prism):
    mesh, _, _, _, _, cc = prism
    B = torch.randn(mesh.n_tets, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    frames = B.transpose(-1, -2).repeat_interleave(4, dim=0)  # corner (t, k) carries B_t^T
    pts = torch.as_tensor(cc.corner_points)
    for k in (0, 2):
        edges = torch.as_tensor(cc.quad_corners[:, [k, k + 1]])
        ref = tc_torsion.solder_form(pts, edges, frames)
        assert torch.allclose(I._solder(cc, B, k), ref, rtol=0, atol=1e-13)


def test_torsion_is_zero_on_gradients_of_seamless_maps(prism, prism_map):
    mesh, F, h, charts, prob, cc = prism
    rng = np.random.default_rng(0)
    # random seamless maps of the prism: any free unknowns satisfy every transition
    for _ in range(3):
        y = rng.normal(scale=3.0, size=prob.elim.free.size)
        B = torch.from_numpy(_grads(mesh, prob.corner_params(y)))
        scale = float(B.abs().max())
        assert I.quad_torsion(cc, B).abs().max() < 1e-12 * scale * 3
    # the valid map of the valence-3 prism (on the refined mesh the map lives on)
    m = prism_map
    ccm = I.corner_complex(m.mesh, m.charts, h)
    for uvw in (m.seamless_uvw, m.uvw):
        assert I.quad_torsion(ccm, torch.from_numpy(_grads(m.mesh, uvw))).abs().max() < 1e-11
    # the rotation field's coframes are not integrable around the axis
    Bf = torch.from_numpy(np.transpose(charts.frames, (0, 2, 1)) / h)
    assert I.quad_torsion(cc, Bf).abs().max() > 0.1


@pytest.mark.parametrize("rotate", [False, True])
def test_torsion_is_zero_on_the_box_maps(rotate):
    mesh = io.box(2)
    F = _identity(mesh)
    if rotate:
        R = so3.exp(torch.tensor([0.3, -0.5, 0.7], dtype=torch.float64))
        mesh = TetMesh(mesh.vertices @ R.T, mesh.tets)
        F = R.expand(mesh.n_tets, 3, 3).clone()
    charts, prob, cc = _setup(mesh, F, 0.25)
    # the identity map (x -> R^T x / h): the field's own coframes
    Bf = torch.from_numpy(np.transpose(charts.frames, (0, 2, 1)) / 0.25)
    assert I.quad_torsion(cc, Bf).abs().max() < 1e-12
    y = np.random.default_rng(1).normal(size=prob.elim.free.size)
    assert I.quad_torsion(cc, torch.from_numpy(_grads(mesh, prob.corner_params(y)))).abs().max() < 1e-11


def test_quadratic_terms_equal_the_operator_energies(prism):
    mesh, _, h, _, _, cc = prism
    J = torch.randn(mesh.n_tets, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    B = cc.coframes(J)
    assert torch.allclose(cc.normalized_coframes(B), J, atol=1e-13)
    j = J.reshape(-1).numpy()
    K = I.torsion_matrix(cc)
    rel = h * I.quad_torsion(cc, B).numpy() / np.linalg.norm(cc.quad_edge, axis=1)[:, None]
    np.testing.assert_allclose((K @ j).reshape(-1, 3), rel, atol=1e-12)
    assert float(K @ j @ (K @ j)) / (3 * mesh.n_tets) == pytest.approx(float(I.torsion_energy(cc, B)), rel=1e-12)
    S = I.smoothness_matrix(cc)
    D = (S @ j).reshape(-1, 9)
    Dref = (J[cc.tet1] @ torch.as_tensor(cc.frames[cc.tet1]).transpose(1, 2)
            - torch.as_tensor(cc.face_rot) @ J[cc.tet0] @ torch.as_tensor(cc.frames[cc.tet0]).transpose(1, 2))
    np.testing.assert_allclose(D, Dref.reshape(-1, 9).numpy(), atol=1e-12)
    assert float((cc.face_weight * (D * D).sum(1)).sum()) == pytest.approx(float(I.smoothness_energy(cc, B)), rel=1e-12)
    # the loop transports read off the operator: I and R_f^T (the report's convention)
    C0, C2 = I._loop_transports(cc)
    assert np.allclose(C0, np.eye(3)) and np.allclose(C2, np.transpose(cc.face_rot[cc.quad_face], (0, 2, 1)))


def test_gradcheck_of_the_new_terms():
    mesh = io.box(1)  # 6 tets
    charts, _, cc = _setup(mesh, _identity(mesh), 0.5)
    G = group_matrices().astype(np.float64)
    rng = np.random.default_rng(3)
    cc = dataclasses.replace(cc, face_rot=G[rng.integers(0, 24, size=cc.face.size)])  # any transitions
    B0 = torch.randn(mesh.n_tets, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    sub = torch.tensor([0, 3])  # two tets' coframes are the inputs (fewer evaluations), the rest fixed
    b = B0[sub].clone().requires_grad_(True)

    def full(x):
        return B0.index_put((sub,), x)

    for fn in (lambda x: I.quad_torsion(cc, full(x)), lambda x: I.torsion_energy(cc, full(x)),
               lambda x: I.smoothness_energy(cc, full(x))):
        assert torch.autograd.gradcheck(fn, (b,))
        assert torch.autograd.gradgradcheck(fn, (b,))
    # batched coframes: one value per batch element
    Bb = torch.randn(2, mesh.n_tets, 3, 3, dtype=torch.float64)
    assert I.quad_torsion(cc, Bb).shape == (2, cc.quad_face.size, 3)
    assert torch.allclose(I.torsion_energy(cc, Bb)[1], I.torsion_energy(cc, Bb[1]))


# ----------------------------------------------------------------------------- alignment
def test_alignment_constraints_hold_on_every_coframe_of_the_space(prism):
    mesh, _, h, charts, prob, cc = prism
    space = I.coframe_space(prob)
    assert space.conflicts.size == 0 and space.counts["constrained_tets"] > 0
    assert np.abs(space.j0).max() == 0  # build_problem's constraints are homogeneous
    y = np.random.default_rng(5).normal(size=space.GZ.shape[1])
    B = cc.coframes(torch.from_numpy((space.GZ @ y).reshape(-1, 3, 3))).numpy()
    X = mesh.vertices.double().numpy()
    P = X[mesh.boundary_faces.numpy()]
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    row = B[prob.boundary_tet, prob.boundary_axis]  # (Bf, 3) must be parallel to the normal
    cos = np.abs((row * n).sum(1)) / (np.linalg.norm(row, axis=1) * np.linalg.norm(n, axis=1))
    assert np.allclose(cos, 1.0, atol=1e-12)
    # singular edges: in every tet at the edge, the edge is mapped onto one parameter axis
    E = mesh.edges.numpy()
    tets = mesh.tets.numpy()
    sing = np.nonzero(charts.singular_edge)[0]
    n_checked = 0
    for e in sing:
        at = np.nonzero(np.isin(tets, E[e]).sum(1) == 2)[0]
        d = B[at] @ (X[E[e, 1]] - X[E[e, 0]])  # (k, 3): the edge in each tet's chart
        assert (np.sort(np.abs(d), axis=1)[:, :2] < 1e-12 * np.abs(d).max()).all()
        if e == sing[0]:  # the start tet: along the holonomy's axis
            t0 = charts.edge_start_tet[e]
            assert np.abs(B[t0] @ (X[E[e, 1]] - X[E[e, 0]])).argmax() == charts.edge_axis[e]
        n_checked += at.size
    assert n_checked >= 3 * sing.size


def test_the_space_holds_every_seamless_map_and_frees_the_unconstrained_tets(prism):
    mesh, _, h, charts, prob, cc = prism
    space = I.coframe_space(prob)
    rng = np.random.default_rng(7)
    for _ in range(2):  # the gradient of every seamless map lies in the space (projection is exact)
        uvw = prob.corner_params(rng.normal(scale=2.0, size=prob.elim.free.size))
        J = cc.normalized_coframes(torch.from_numpy(_grads(mesh, uvw))).numpy()
        back = (space.GZ @ space.project(J)).reshape(-1, 3, 3)
        assert np.abs(back - J).max() < 1e-10 * np.abs(J).max()
    # an unconstrained interior tet (no corner on the boundary or on the axis) is free
    bverts = np.unique(mesh.boundary_faces.numpy())
    sverts = np.unique(mesh.edges.numpy()[charts.singular_edge])
    inner = ~np.isin(mesh.tets.numpy(), np.concatenate([bverts, sverts])).any(1)
    assert inner.any() and (space.dims[inner] == 9).all()
    assert (space.dims[~inner] < 9).any()


def test_a_tet_whose_constraints_admit_no_coframe_is_reported():
    # one tet, four boundary faces: the slanted face and one coordinate face share an axis, so that
    # row must be parallel to two normals (the seamless map flattens this tet too)
    mesh = TetMesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64),
                   torch.tensor([[0, 1, 2, 3]]), reorient=True)
    charts, prob, _ = _setup(mesh, _identity(mesh), 0.25)
    assert prob.flat_tets()[0].tolist() == [0]
    space = I.coframe_space(prob)
    assert space.conflicts.tolist() == [0] and space.counts["conflicts"] == 1
    assert space.dims[0] == 9  # dropped, not kept half-way
    r = I.integrable_frames(mesh, charts, prob, schedule=((1.0, 1.0),))
    gate = r.gate()
    assert not gate.passed and gate.counts["alignment_conflicts"] == 1 and gate.where["alignment_conflicts"] == [0]
    assert any("no positive coframe" in s for s in gate.reasons)


# ----------------------------------------------------------------------------- the solve
def test_continuation_makes_the_prism_field_integrable_and_the_map_valid():
    mesh, F = axis_prism(n_layers=1, height=0.4, turns=4.0)
    h = 0.3
    charts, prob, cc = _setup(mesh, F, h)
    seen = []
    r = I.integrable_frames(mesh, charts, prob, schedule=((1e2, 1e4), (0.0, 1e8)),
                            callback=lambda k, B: seen.append(k))
    assert seen == [0, 1]
    assert r.start["torsion_max"] > 0.1
    tors = [x["torsion_max"] for x in r.rounds]
    assert tors[0] < r.start["projected"]["torsion_max"] and tors[1] < 1e-5 and tors[1] < tors[0]
    assert r.inverted.size == 0 and r.gate().passed
    # the least-squares seamless map that fits the integrable coframes: no fold, coframes reproduced
    p2 = prob.with_targets(r.targets())
    A, b, c = p2.energy_matrices()
    y = solve_fixed(A, b, np.zeros_like(p2.free_is_int), np.zeros(0))
    det = np.linalg.det(TetJacobians.of_problem(p2)(y))
    assert (det > 0).all()
    assert float(y @ (A @ y) - 2 * b @ y + c) / p2.vol.sum() < 1e-8
    s = r.summary()
    assert s["inverted"] == 0 and len(s["rounds"]) == 2 and s["conflicts"] == 0


def test_the_box_field_is_integrable_already():
    mesh = io.box(2)
    r = hex_mesh(mesh, _identity(mesh), edge_length=0.25, integrable=True)
    assert r.validity.valid and r.hexes.shape == (64, 8) and r.good
    st = r.map.stats["integrable"]
    assert st["start"]["torsion_max"] < 1e-12 and st["rounds"][-1]["torsion_max"] < 1e-12
    assert r.map.gates["frames"].passed
    assert r.quality.sj_min == pytest.approx(1.0, abs=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("turns", [4.0, -4.0])
def test_prism_hex_mesh_with_integrable_frames(turns):
    mesh, F = axis_prism(turns=turns)
    r = hex_mesh(mesh, F, edge_length=0.3, integrable=True)
    assert r.validity.valid and r.good, r.validity.reasons
    st = r.map.stats["integrable"]
    assert st["rounds"][-1]["torsion_max"] < 1e-6 and st["inverted"] == 0
    assert r.map.stats["seamless"]["inverted_least_squares"] == 0


def test_bad_schedule_is_a_clear_error(prism):
    mesh, _, _, charts, prob, _ = prism
    with pytest.raises(ValueError, match="schedule"):
        I.integrable_frames(mesh, charts, prob, schedule=((1.0, -1.0),))


# ----------------------------------------------------------------------------- seamless targets
def test_with_targets_of_the_field_gives_the_default_objective(prism):
    mesh, F, h, charts, prob, _ = prism
    Bf = np.transpose(charts.frames, (0, 2, 1)) / h
    assert abs(prob.with_targets(Bf).G - prob.G).max() < 1e-12
    assert abs(build_problem(mesh, charts, h, targets=Bf).G - prob.G).max() < 1e-12



def test_with_targets_reproduces_a_valid_map_from_its_gradients(prism_map):
    m = prism_map
    p2 = m.problem.with_targets(_grads(m.mesh, m.seamless_uvw))
    A, b, c = p2.energy_matrices()
    y = solve_fixed(A, b, np.zeros_like(p2.free_is_int), np.zeros(0))
    assert float(y @ (A @ y) - 2 * b @ y + c) < 1e-12 * p2.vol.sum()
    # the same map: both pin one vertex at the origin, so the corner parameters agree
    np.testing.assert_allclose(p2.corner_params(y), m.seamless_uvw, atol=1e-8)


def test_bad_targets_are_clear_errors(prism):
    _, _, _, charts, prob, _ = prism
    T = charts.frames.shape[0]
    with pytest.raises(ValueError, match=r"shape \(T, 3, 3\)"):
        prob.with_targets(np.zeros((T, 3)))
    bad = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    bad[7, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"non-finite.*\[7\]"):
        prob.with_targets(bad)
    bad[7] = np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match=r"positive determinants; 1 do not \(tets \[7\]\)"):
        prob.with_targets(bad)
