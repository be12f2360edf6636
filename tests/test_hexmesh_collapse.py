"""Edge collapses that carry the face matchings (:mod:`torchconn.hexmesh.collapse`)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import so3
from torchconn.hexmesh.collapse import collapse_edge, collapse_edges
from torchconn.hexmesh.cut import face_matchings, tet_charts
from torchconn.mesh.builtin import box


def _frames(mesh, seed, scale=0.9):
    g = torch.Generator().manual_seed(seed)
    return so3.exp(scale * torch.randn(mesh.n_tets, 3, generator=g, dtype=torch.float64))


def _interior_edge(mesh):
    bv = np.zeros(mesh.n_vertices, bool)
    bv[mesh.boundary_vertices.cpu().numpy()] = True
    E = mesh.edges.cpu().numpy()
    return E[np.nonzero(~bv[E[:, 0]] & ~bv[E[:, 1]])[0][0]]


def _edge_types(mesh, charts, vmap=None):
    E = mesh.edges.cpu().numpy()
    if vmap is not None:
        E = vmap[E]
    return {tuple(sorted(map(int, e))): int(t) for e, t in zip(E, charts.edge_type)}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_collapse_keeps_every_other_edge_type_and_face_matching(seed):
    mesh = box(3)
    F = _frames(mesh, seed)
    fm = face_matchings(mesh, F)
    before = tet_charts(mesh, F, fm)
    a, b = map(int, _interior_edge(mesh))
    out = collapse_edge(mesh, F, a, b, fm)
    assert out is not None
    new, F2, parent, fm2, vmap = out
    X = new.vertices.numpy()
    p = X[new.tets.numpy()]
    vol = np.einsum("ti,ti->t", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    assert (vol > 0).all() and new.n_vertices == mesh.n_vertices - 1
    assert new.n_tets == mesh.n_tets - int(((mesh.tets == a).any(1) & (mesh.tets == b).any(1)).sum())
    assert torch.equal(F2, F[torch.as_tensor(parent)])
    after = tet_charts(new, F2, fm2)
    # every edge away from the merged vertex keeps its holonomy class
    old_t, new_t = _edge_types(mesh, before, vmap), _edge_types(new, after)
    m = int(vmap[a])
    far = [e for e in new_t if m not in e]
    assert far and all(old_t[e] == new_t[e] for e in far)
    # the matching of a face between two surviving tets that were neighbours is carried as it was
    oft, nft = mesh.face_tets.numpy(), new.face_tets.numpy()
    old = {(int(t0), int(t1)): int(g) for (t0, t1), g in zip(oft, fm) if t0 >= 0 and t1 >= 0}
    n_same = 0
    for (t0, t1), g in zip(nft, fm2):
        if t0 >= 0 and t1 >= 0 and (int(parent[t0]), int(parent[t1])) in old:
            assert g == old[(int(parent[t0]), int(parent[t1]))]
            n_same += 1
    assert n_same > 0


def test_a_collapse_that_would_move_the_boundary_or_invert_a_tet_is_refused():
    mesh = box(2)
    F = _frames(mesh, 0)
    fm = face_matchings(mesh, F)
    bv = np.zeros(mesh.n_vertices, bool)
    bv[mesh.boundary_vertices.numpy()] = True
    E = mesh.edges.numpy()
    # an interior vertex pulled onto the boundary is fine (it moves to the boundary vertex's place);
    # two boundary vertices of different box faces glued across the interior are not
    cross = [e for e in E if bv[e[0]] and bv[e[1]]
             and not any(np.allclose(mesh.vertices[e[0], k], mesh.vertices[e[1], k]) for k in range(3))]
    refused = [collapse_edge(mesh, F, int(a), int(b), fm) is None for a, b in cross]
    assert cross and all(refused)


def test_collapse_edges_follows_vertex_indices_through_earlier_collapses():
    mesh = box(3)
    F = _frames(mesh, 3)
    fm = face_matchings(mesh, F)
    a, b = map(int, _interior_edge(mesh))
    pairs = np.array([[a, b], [a, b]])  # the second is already merged: skipped
    new, F2, parent, fm2, counts = collapse_edges(mesh, F, pairs, fm)
    assert counts == {"collapsed": 1, "refused": 0} and new.n_vertices == mesh.n_vertices - 1
