"""LMFF's numeric one-ring test (torchconn.hexmesh.one_ring) on constructed cases with known answers.

* a box with the identity field: every vertex passes, the angles are 2 pi (interior), pi (flat
  boundary) and pi/2 (the cube's edges), exactly;
* the axis prism with a quarter / half turn about its axis: the axis vertices pass with the
  angle of their hex count on the singular edges (3 pi/2, 5 pi/2, 3 pi);
* a regular vertex of a box whose frames turn once and a half about a vertical line, matchings
  the identity: the least-squares map folds, the foldover-free solve untangles it: passes;
* the same with one full turn: the combinatorial conditions see a regular vertex, the solve
  leaves no inverted tet but a map that winds twice about six edges (4 pi): fails, by angle;
* the hairpin's zipper node (a valence-3 and a valence-5 edge doubling back): its constraints
  flatten tets; the cube whose surface fans fold (valence +-2 on a surface): angle pi, not 2 pi;
  a complex turn: complex edges -- each fails with that reason, where LMFF's conditions fail;
* the batched rings against a slow per-ring reference (each ring its own mesh, its own problem,
  a dense least-squares solve, the angles tet by tet);
* the report in the structure gate (JSON) and bad input.

Cost: about 3 s in all (the meshes have at most a few hundred tets).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from torchconn import io, so3
from torchconn.hexmesh.cut import face_matchings, tet_charts
from torchconn.hexmesh.meshability import VERTEX_CLASSES, meshability_report
from torchconn.hexmesh.one_ring import ANGLE_TOL, one_ring_test
from torchconn.mesh import TetMesh

from test_hexmesh_map import axis_prism
from test_hexmesh_meshability import _element, cube5, hairpin


def _identity(mesh):
    return torch.eye(3, dtype=torch.float64).expand(mesh.n_tets, 3, 3).clone()


def _axis_vertices(mesh, interior=True):
    X = mesh.vertices.numpy()
    on = np.nonzero(np.abs(X[:, :2]).max(1) < 1e-12)[0]
    inner = (X[on, 2] > 0) & (X[on, 2] < 1)
    return on[inner] if interior else on[~inner]


def _twist(k):
    """A box(4) with frames turning ``k`` times about the vertical line through its centre, and
    identity matchings (so every holonomy is the identity); the centre vertex."""
    mesh = io.box(4)
    bc = mesh.tet_barycenters
    phi = k * torch.atan2(bc[:, 1] - 0.5, bc[:, 0] - 0.5)
    F = so3.exp(phi[:, None] * torch.tensor([0, 0, 1.0], dtype=torch.float64))
    v = int(np.nonzero((np.abs(mesh.vertices.numpy() - 0.5) < 1e-12).all(1))[0][0])
    return mesh, F, np.zeros(mesh.n_faces, np.int64), v


# ----------------------------------------------------------------------------- passing cases
def test_box_with_the_identity_field_passes_everywhere_with_exact_angles():
    mesh = io.box(3)
    X = mesh.vertices.numpy()
    inner = np.nonzero(((X > 0) & (X < 1)).all(1))[0]
    r = one_ring_test(mesh, _identity(mesh), vertices=inner)
    assert r.vertices.tolist() == inner.tolist() and r.passed.all() and not r.solved.any()
    np.testing.assert_allclose(r.measured, 2 * math.pi, atol=1e-9)
    assert r.edge_judged.all() and (r.edge_hexes == 4).all()
    # the default vertices: the feature curves and corners of the cube (the identity field is
    # regular inside); boundary edges: pi on the faces, pi/2 on the cube's edges
    r = one_ring_test(mesh, _identity(mesh))
    m = meshability_report(mesh, _identity(mesh))
    assert r.vertices.tolist() == np.nonzero(m.vertex_class != 0)[0].tolist() and r.vertices.size == 32
    assert r.passed.all() and r.counts()["failed"] == 0 and r.failing() == []
    assert set(r.edge_hexes[r.edge_boundary].tolist()) == {1, 2}
    np.testing.assert_allclose(r.measured, r.edge_hexes * math.pi / 2, atol=1e-9)


@pytest.mark.parametrize("turns,hexes", [(4.0, 3), (-4.0, 5), (-2.0, 6)])
def test_prism_axis_vertices_pass_with_the_angle_of_their_hex_count(turns, hexes):
    mesh, F = axis_prism(n_layers=3, turns=turns)
    axis = _axis_vertices(mesh)
    r = one_ring_test(mesh, F, vertices=axis)
    assert r.passed.all(), [r.reasons(i) for i in range(axis.size)]
    sing = r.edge_hexes != 4
    assert sing.sum() == 2 * axis.size  # the axis edges below and above each vertex
    np.testing.assert_allclose(r.measured[sing], hexes * math.pi / 2, atol=1e-6)
    np.testing.assert_allclose(r.measured[~sing], 2 * math.pi, atol=1e-6)
    # the axis' ends on the flat top and bottom: an arc ending on a surface
    ends = one_ring_test(mesh, F, vertices=_axis_vertices(mesh, interior=False))
    assert ends.passed.all() and (ends.vertex_class == VERTEX_CLASSES.index("arc")).all()


def test_a_folded_least_squares_map_is_untangled_by_the_solver():
    mesh, F, fm, v = _twist(1.5)
    ls = one_ring_test(mesh, F, fm, vertices=[v], solve=False)
    assert not ls.passed[0] and ls.inverted[0] > 0 and not ls.solved[0]
    assert "inverted in the least-squares map" in " ".join(ls.reasons(0))
    r = one_ring_test(mesh, F, fm, vertices=[v])
    assert r.solved[0] and r.inverted[0] == 0 and r.passed[0]
    np.testing.assert_allclose(r.measured, 2 * math.pi, atol=1e-6)


# ----------------------------------------------------------------------------- failing cases
def test_a_twisted_regular_vertex_fails_by_its_angles_not_by_inversion():
    mesh, F, fm, v = _twist(1.0)
    m = meshability_report(mesh, F, fm)
    assert m.vertex_class[v] == VERTEX_CLASSES.index("regular") and m.charts.counts()["singular_edges"] == 0
    r = one_ring_test(mesh, F, fm, vertices=[v])
    # the solver's map keeps every tet positive but winds twice about six of the 14 edges
    assert r.solved[0] and r.inverted[0] == 0 and not r.passed[0]
    assert r.counts()["failed_angle"] == 1 and r.counts()["failed_inverted"] == 0
    off = ~r.edge_ok
    assert off.sum() == 6
    np.testing.assert_allclose(r.measured[off], 4 * math.pi, atol=1e-6)
    reasons = r.failing()[0]["reasons"]
    assert len(reasons) == 6 and all("parametric angle 12.566 rad, expected 6.283" in s for s in reasons)


def test_the_hairpin_zipper_fails_where_lmff_says_so():
    mesh, F, (p, q, v) = hairpin()
    m = meshability_report(mesh, F)
    r = one_ring_test(mesh, F, meshability=m)
    failed = r.vertices[~r.passed].tolist()
    assert failed == [v] == m.zipper_nodes.tolist()
    row = int(np.nonzero(r.vertices == v)[0][0])
    # both branches on one parametric line through v: the tets between them are flattened
    assert r.flat[row] > 0 and r.failed_by()["flat"][row]
    assert any("flatten" in s for s in r.reasons(row))
    assert sorted(r.edge_hexes[(r.edge_ring == row) & (r.edge_hexes != 4)].tolist()) == [3, 5]


def test_folded_surface_fans_fail_by_their_angle():
    mesh = cube5()
    F = _identity(mesh)
    fm = face_matchings(mesh, F)
    f = int(np.nonzero((np.sort(mesh.faces.numpy(), 1) == [0, 3, 5]).all(1))[0][0])
    fm[f] = _element(np.diag([1, -1, -1]))
    m = meshability_report(mesh, F, fm)
    r = one_ring_test(mesh, F, fm, meshability=m)
    assert r.vertices[~r.passed].tolist() == [0, 3, 5] == m.invalid_nodes.tolist()
    bad = r.edge_judged & ~r.edge_ok
    assert {tuple(sorted(e)) for e in r.edge_verts[bad].tolist()} == {(0, 3), (0, 5)}
    np.testing.assert_allclose(r.expected[bad], 2 * math.pi)  # four quarter turns: a fold
    np.testing.assert_allclose(r.measured[bad], math.pi, atol=1e-6)  # the map keeps the fan flat
    assert r.counts()["failed_angle"] == 3 and r.counts()["failed_inverted"] == 0


def test_a_complex_turn_fails_as_complex():
    mesh = axis_prism()
    bc = mesh.tet_barycenters
    axis = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64) / math.sqrt(3)
    F = so3.exp((torch.atan2(bc[:, 1], bc[:, 0]) / 3)[:, None] * axis)
    chain = np.unique(mesh.edges.numpy()[meshability_report(mesh, F).complex_edges])
    r = one_ring_test(mesh, F, vertices=chain)
    assert not r.passed.any() and (r.complex > 0).all() and not r.solved.any()
    assert np.isnan(r.expected[r.edge_hexes == -1]).all()
    assert all("complex singular edges" in f["reasons"][0] for f in r.failing())


# ----------------------------------------------------------------------------- against a slow reference
def _reference(mesh, F, v, h, identity_matchings):
    """The ring of ``v`` as a mesh of its own, its own charts (the best matchings, or the identity)
    and problem (link faces free, no features), a dense least-squares solve, the angles about
    the edges at ``v`` tet by tet: ``({w: angle}, inverted tets)``."""
    from torchconn.hexmesh.injective import TetJacobians
    from torchconn.hexmesh.seamless import build_problem

    tets = mesh.tets.numpy()
    ring = np.nonzero((tets == v).any(1))[0]
    verts, loc = np.unique(tets[ring], return_inverse=True)
    sub = TetMesh(mesh.vertices[torch.as_tensor(verts)], torch.as_tensor(loc.reshape(-1, 4)))
    fm = np.zeros(sub.n_faces, np.int64) if identity_matchings else None
    ch = tet_charts(sub, torch.as_tensor(F)[torch.as_tensor(ring)], fm)
    bnd = {tuple(sorted(f)) for f in mesh.boundary_faces.numpy().tolist()}
    plane = np.array([tuple(sorted(verts[f])) in bnd for f in sub.boundary_faces.numpy()])
    prob = build_problem(sub, ch, h, features=False, plane_faces=plane)
    jac = TetJacobians.of_problem(prob)
    G = jac.GZ.toarray() * np.sqrt(np.repeat(jac.vol, 9))[:, None]
    rhs = (np.tile(np.eye(3).reshape(9), sub.n_tets) - jac.j0) * np.sqrt(np.repeat(jac.vol, 9))
    y = np.linalg.lstsq(G, rhs, rcond=None)[0]
    uvw = prob.corner_params(y)
    out, inverted = {}, 0
    for t in range(sub.n_tets):  # tet by tet
        P = uvw[t]
        det = np.dot(np.cross(P[1] - P[0], P[2] - P[0]), P[3] - P[0])
        inverted += det <= 0
        c = int(np.nonzero(verts[sub.tets.numpy()[t]] == v)[0][0])
        for j in range(4):
            if j == c:
                continue
            l, m = [k for k in range(4) if k not in (c, j)]
            e = (P[j] - P[c]) / np.linalg.norm(P[j] - P[c])
            a = P[l] - P[c] - np.dot(P[l] - P[c], e) * e
            b = P[m] - P[c] - np.dot(P[m] - P[c], e) * e
            ang = math.atan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)) * (1 if det > 0 else -1)
            w = int(verts[sub.tets.numpy()[t, j]])
            out[w] = out.get(w, 0.0) + ang
    return out, int(inverted)


@pytest.mark.parametrize("case", ["twist", "prism"])
def test_batched_rings_match_the_per_ring_reference(case):
    if case == "twist":  # least-squares rings that fold, identity transitions
        mesh, F, fm, v = _twist(1.0)
        verts = np.unique(mesh.edges.numpy()[(mesh.edges.numpy() == v).any(1)])
    else:  # transitions about the valence-3 axis, boundary planes
        mesh, F = axis_prism(n_layers=2, turns=4.0)
        fm, verts = None, np.arange(0, mesh.n_vertices, 5)
    r = one_ring_test(mesh, F, fm, vertices=verts, features=False, solve=False, edge_length=0.3)
    assert r.flat.sum() == 0 and (r.inverted.sum() > 0) == (case == "twist")  # not vacuous
    for row, v in enumerate(verts.tolist()):
        ref, inv = _reference(mesh, F, v, 0.3, identity_matchings=fm is not None)
        sel = r.edge_ring == row
        got = dict(zip(r.edge_verts[sel, 1].tolist(), r.measured[sel].tolist()))
        assert got.keys() == ref.keys()
        np.testing.assert_allclose([got[w] for w in ref], list(ref.values()), atol=1e-7)
        assert r.inverted[row] == inv


# ----------------------------------------------------------------------------- the structure gate, bad input
def test_the_structure_gate_reports_the_one_ring_test_beside_the_conditions():
    from torchconn.hexmesh.structure import map_structure

    mesh, F, _ = hairpin()
    # the given matchings: no search and no repair, so the zipper stays for the gate to report
    st = map_structure(mesh, F, 0.3, face_match=face_matchings(mesh, F), split=False)
    g = st.gate
    assert g.counts["zipper_nodes"] == 1 and g.counts["one_ring_failed"] >= 1
    assert g.counts["one_ring_tested"] == st.one_ring.vertices.size
    d = json.loads(json.dumps(g.as_dict()))
    fail = d["info"]["one_ring"]["failing"]
    assert any(f["vertex"] == st.meshability.zipper_nodes[0] for f in fail) and all(f["reasons"] for f in fail)
    assert d["where"]["one_ring_failed"] == [f["vertex"] for f in fail][:10]
    off = map_structure(mesh, F, 0.3, face_match=face_matchings(mesh, F), split=False, one_ring=False)
    assert off.one_ring is None and "one_ring_tested" not in off.gate.counts and not off.gate.info
    assert off.gate.passed == g.passed  # reported beside the conditions, not deciding the gate


def test_bad_input_is_a_clear_error():
    mesh = io.box(2)
    F = _identity(mesh)
    with pytest.raises(ValueError, match="vertex ids"):
        one_ring_test(mesh, F, vertices=[0, mesh.n_vertices])
    with pytest.raises(ValueError, match="tet_frames must have shape"):
        one_ring_test(mesh, F[:-1])
    with pytest.raises(ValueError, match="face_match must be"):
        one_ring_test(mesh, F, np.zeros(3, np.int64))
    r = one_ring_test(mesh, F, vertices=[])
    assert r.counts()["tested"] == 0 and r.failing() == [] and ANGLE_TOL == 0.035
    json.dumps(r.as_dict())


@pytest.mark.slow  # a HexMe model with its SH field: ~5 s
def test_a_hexme_model_agrees_with_the_conditions_at_its_zipper_nodes():
    """s04c (the tetrahedron) with the SH field and its best matchings: LMFF's conditions find two
    zipper nodes; the one-ring test fails there too (and at one more arc vertex, whose ring the
    constraints flatten: two constrained curves on one line, which the map's splits would open)."""
    from conftest import hexme_mesh
    from torchconn.frames import design

    mesh = hexme_mesh("s04c_tetrahedron")
    F = design(mesh, "sh").tet_frames
    m = meshability_report(mesh, F)
    r = one_ring_test(mesh, F, meshability=m)
    failed = set(r.vertices[~r.passed].tolist())
    assert m.zipper_nodes.size == 2 and set(m.zipper_nodes.tolist()) <= failed
    assert r.counts()["tested"] == int((m.vertex_class != 0).sum()) and r.passed.sum() > 0.9 * r.vertices.size
