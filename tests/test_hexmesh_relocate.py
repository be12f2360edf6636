"""Relocation of the singular arcs onto their turn axes (torchconn.hexmesh.relocate; issue 29).

* the valence-3 prism with its axis pushed sideways: the arc runs along z again (its across part
  down 40×), no tet inverts, no edge's hex count changes, the top and bottom vertices stay in their planes, the faceted side
  does not move, the numbering and the frames' tets are the input's;
* an arc already on its axis, and a field with no arc, move nothing (the input mesh returned);
* a HexMe model with CAD tags: every moved boundary vertex stays on the planes of its boundary
  faces, CAD corners and tags are kept, every edge keeps its hex count; the structure stage
  reports what it did.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from torchconn import io
from torchconn.hexmesh import tet_charts
from torchconn.hexmesh.relocate import relocate_singular_vertices
from torchconn.hexmesh.structure import map_structure
from torchconn.mesh import TetMesh

from test_hexmesh_map import axis_prism

HEXME = Path(__file__).resolve().parents[2] / "shared" / "data" / "hexme" / "meta"


def _tilted_prism(dx: float = 0.12):
    mesh, F = axis_prism(turns=4.0)
    X = mesh.vertices.clone()
    axis_v = torch.nonzero(X[:, :2].norm(dim=1) < 1e-12).reshape(-1)
    X[axis_v[1:-1], 0] += dx  # the inner vertices of the z-axis chain pushed sideways
    return TetMesh(X, mesh.tets), F, axis_v


def test_a_tilted_arc_is_moved_back_onto_its_axis():
    mesh, F, axis_v = _tilted_prism()
    charts = tet_charts(mesh, F)
    assert int((charts.singular_edge & (charts.edge_valence == 3)).sum()) == 3  # the chain, valence 3
    new, rl = relocate_singular_vertices(mesh, charts)
    assert new is not mesh and rl.arcs == 3 and rl.moved > 0
    assert rl.misalignment_after < rl.misalignment_before / 40 and rl.energy_after < rl.energy_before
    # the same numbering, every tet positive
    for a in ("tets", "faces", "edges", "boundary_faces"):
        assert torch.equal(getattr(new, a), getattr(mesh, a))
    assert (new.signed_volumes() > 0).all()
    assert np.array_equal(tet_charts(new, F).edge_valence, charts.edge_valence)  # no hex count flipped
    Y, X = new.vertices, mesh.vertices
    # the chain is straight again: its vertices share x and y
    chain = Y[axis_v]
    assert float((chain[:, :2] - chain[:1, :2]).norm(dim=1).max()) < 0.02
    # top and bottom vertices move within their planes; the faceted side (two normals) stays
    bnd = mesh.boundary_vertices
    top_bottom = bnd[(X[bnd, 2] == 0) | (X[bnd, 2] == 1)]
    assert float((Y[top_bottom, 2] - X[top_bottom, 2]).abs().max()) < 1e-14
    rim = bnd[(X[bnd, :2].norm(dim=1) > 0.85)]  # the 18-gon's ring and its edges on the caps
    assert torch.equal(Y[rim], X[rim])


def test_an_arc_on_its_axis_and_a_field_without_arcs_move_nothing():
    mesh, F = axis_prism(turns=4.0)
    new, rl = relocate_singular_vertices(mesh, tet_charts(mesh, F))
    assert rl.arcs == 3 and rl.misalignment_before < 1e-12
    assert float((new.vertices - mesh.vertices).norm(dim=1).max()) < 1e-9
    box = io.box(2)
    F = torch.eye(3, dtype=torch.float64).expand(box.n_tets, 3, 3).clone()
    same, rl = relocate_singular_vertices(box, tet_charts(box, F))
    assert same is box and rl.arcs == 0 and rl.moved == 0


@pytest.mark.skipif(not (HEXME / "s03c_pentagon.yaml").is_file(), reason="../shared/data/hexme is absent")
def test_a_cad_model_keeps_its_surfaces_curves_corners_and_tags():
    from torchconn.frames.design import design
    from torchconn.hexmesh.inputs import tet_frames_of
    from torchconn.hexmesh.seamless import default_edge_length
    from torchconn.mesh.cad import load_hexme

    mesh = load_hexme(HEXME / "s03c_pentagon.yaml", dtype=torch.float64)
    Fr = tet_frames_of(mesh, design(mesh, "sh"))
    h = default_edge_length(mesh)
    off = map_structure(mesh, Fr, h, relocate=False, one_ring=False)
    on = map_structure(mesh, Fr, h, relocate=True, one_ring=False)
    rl = on.stats["relocation"]
    assert rl["moved"] > 0 and rl["misalignment_after"] < rl["misalignment_before"] / 4
    assert "relocation" not in off.stats and "relocate_s" in on.timings
    m0, m1 = off.mesh, on.mesh
    assert torch.equal(m0.tets, m1.tets)
    assert all(torch.equal(getattr(m0.cad, f.name), getattr(m1.cad, f.name)) for f in dataclasses.fields(m0.cad))
    X0, X1 = m0.vertices.numpy(), m1.vertices.numpy()
    corners = m0.cad.corner_vertices.numpy()
    assert np.array_equal(X0[corners], X1[corners])
    # every boundary vertex stays in the planes of its boundary faces (the pentagon prism is planar)
    bf = m0.boundary_faces.numpy()
    n = np.cross(X0[bf[:, 1]] - X0[bf[:, 0]], X0[bf[:, 2]] - X0[bf[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    for k in range(3):
        v = bf[:, k]
        assert np.abs(np.einsum("fi,fi->f", X1[v] - X0[v], n)).max() < 1e-12
    assert (m1.signed_volumes() > 0).all()
    # the singular graph is the same: every edge keeps its hex count (an edge stays on its axis' side)
    assert np.array_equal(on.meshability.edge_hexes, off.meshability.edge_hexes)
