"""The frame field chosen by its hex meshes (:mod:`torchconn.hexmesh.choose`)."""
from __future__ import annotations

import torch

from torchconn import so3
from torchconn.frames.candidates import Candidate
from torchconn.hexmesh import hex_mesh
from torchconn.hexmesh.choose import hex_chooser
from torchconn.mesh.builtin import box


def _cands(mesh):
    V = mesh.n_vertices
    eye = torch.eye(3, dtype=torch.float64).expand(V, 3, 3).clone()
    g = torch.Generator().manual_seed(0)
    noisy = so3.exp(0.7 * torch.randn(V, 3, generator=g, dtype=torch.float64))
    mk = lambda F, kind, s: Candidate(frames=F, kind=kind, start="sh", dirichlet_weight=None, metrics={}, score=s)  # noqa: E731
    # the noisy field has the better proxy score: only its hex mesh loses
    return [mk(noisy, "optimized", 0.0), mk(eye, "optimized", 1.0)]


def test_the_chooser_picks_the_good_hex_mesh_and_keeps_it():
    mesh = box(2)
    cands = _cands(mesh)
    choose = hex_chooser(edge_length=0.25)
    idx, info = choose(mesh, cands)
    assert idx == 1 and info["by"] == "hex" and info["reason"] == "a valid map and a good hex mesh"
    assert [r["good"] for r in info["meshed"]] == [False, True]
    frames, kept = choose.chosen
    assert frames is cands[1].frames and kept.good
    # what it keeps is the hex mesh of that field with those options: no need to mesh it again
    again = hex_mesh(mesh, cands[1].frames, edge_length=0.25)
    assert torch.equal(torch.as_tensor(kept.hexes), torch.as_tensor(again.hexes))
    assert torch.equal(torch.as_tensor(kept.points), torch.as_tensor(again.points))
