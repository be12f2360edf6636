"""The map stage's setup made to scale, against the slow references it replaces.

* :func:`~torchconn.hexmesh.split.split_for_map` carries the singular edges through its rounds
  instead of rebuilding the charts every round: the same refined mesh, frames and counts as the
  per-round rebuild (kept here as the reference), on fields with many singular edges;
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import so3
from torchconn.hexmesh.cut import tet_charts
from torchconn.hexmesh.split import SPLIT_RULES, SplitResult, _independent, split_edges, split_for_map
from torchconn.mesh.builtin import box


def _random_frames(mesh, seed, scale=0.6):
    """Per-tet rotations: a smooth turn plus noise (many singular, some complex edges)."""
    g = torch.Generator().manual_seed(seed)
    w = scale * torch.randn(mesh.n_tets, 3, generator=g, dtype=torch.float64)
    return so3.exp(w)


def split_for_map_reference(mesh, tet_frames, face_match=None, *, rules=SPLIT_RULES, max_rounds=50):
    """The per-round rebuild: the charts (hence the singular edges) recomputed every round."""
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    parent = np.arange(mesh.n_tets)
    counts = {r: 0 for r in SPLIT_RULES}
    rounds = 0
    for _ in range(max_rounds):
        edges = mesh.edges.cpu().numpy()
        V, E = mesh.n_vertices, edges.shape[0]
        cand_by_rule = {}
        if "singular" in rules:
            ch = tet_charts(mesh, Fr, face_match)
            sv = np.zeros(V, bool)
            sv[edges[ch.singular_edge].reshape(-1)] = True
            cand_by_rule["singular"] = np.nonzero(~ch.singular_edge & sv[edges[:, 0]] & sv[edges[:, 1]])[0]
        if "boundary" in rules:
            bv = np.zeros(V, bool)
            bv[mesh.boundary_vertices.cpu().numpy()] = True
            bfe = mesh.face_edges.cpu().numpy()[mesh.boundary_face_index.cpu().numpy()].reshape(-1)
            on_b = np.zeros(E, bool)
            on_b[bfe] = True
            cand_by_rule["boundary"] = np.nonzero(~on_b & bv[edges[:, 0]] & bv[edges[:, 1]])[0]
        cand = np.unique(np.concatenate([c for c in cand_by_rule.values()] or [np.zeros(0, np.int64)]))
        if cand.size == 0:
            break
        chosen = _independent(mesh.tet_edges.cpu().numpy(), cand, E)
        for r, c in cand_by_rule.items():
            counts[r] += int(np.isin(chosen, c).sum())
        mesh, Fr, par, face_match = split_edges(mesh, Fr, chosen, face_match)
        parent = parent[par]
        rounds += 1
    return SplitResult(mesh=mesh, tet_frames=Fr, parent_tet=parent, splits=counts, rounds=rounds,
                       face_match=face_match)


def _same_split(a, b):
    assert a.rounds == b.rounds and a.splits == b.splits
    assert torch.equal(a.mesh.tets, b.mesh.tets) and torch.equal(a.mesh.vertices, b.mesh.vertices)
    assert torch.equal(a.tet_frames, b.tet_frames) and np.array_equal(a.parent_tet, b.parent_tet)
    assert (a.face_match is None) == (b.face_match is None)
    if a.face_match is not None:
        assert np.array_equal(a.face_match, b.face_match)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_split_carries_the_singular_edges_as_the_per_round_rebuild(seed):
    mesh = box(4)
    Fr = _random_frames(mesh, seed)
    new = split_for_map(mesh, Fr, max_rounds=6)
    ref = split_for_map_reference(mesh, Fr, max_rounds=6)
    assert ref.splits["singular"] > 0 and ref.rounds >= 2  # the case exercises the carried edges
    _same_split(new, ref)
    # the carried singular edges are the refined mesh's: its charts agree
    ch0 = tet_charts(mesh, Fr)
    ch1 = tet_charts(new.mesh, new.tet_frames)
    assert int(ch1.singular_edge.sum()) >= int(ch0.singular_edge.sum())


def test_split_with_given_matchings_and_one_rule():
    from torchconn.hexmesh.cut import face_matchings

    mesh = box(3)
    Fr = _random_frames(mesh, 7)
    fm = face_matchings(mesh, Fr)
    fm = np.where(np.arange(fm.size) % 5 == 0, 0, fm)  # a matching that is not the best one
    for rules in (("singular",), SPLIT_RULES):
        _same_split(split_for_map(mesh, Fr, fm, rules=rules, max_rounds=5),
                    split_for_map_reference(mesh, Fr, fm, rules=rules, max_rounds=5))
