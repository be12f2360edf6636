"""Singular-structure search (torchconn.frames.matching_search) and the fixed-matching relaxation
(torchconn.frames.quality_paths.relax_to_matchings): against a slow per-edge reference, and its invariants."""
from __future__ import annotations

import math

import pytest
import torch

from torchconn import io, so3
from torchconn.frames import frame_metrics, octahedral, sh
from torchconn.frames.quality_paths import relax_to_matchings
from torchconn.frames.singular import classify_holonomy, face_holonomy_from_matchings
from torchconn.frames.matching_search import (FACE_COSTS, complex_face_count, edge_face_incidence, repair_matchings,
                                        repair_structure)


@pytest.fixture(scope="module")
def cyl():
    m = io.cylinder(edge_length=0.6).to(dtype=torch.float64)
    F0 = sh.sh_frame_field(m, n_smooth_iters=0)
    gen = torch.Generator().manual_seed(5)
    noisy = so3.exp(0.8 * torch.randn(F0.shape[0], 3, generator=gen, dtype=torch.float64)) @ F0
    return m, F0, noisy


@pytest.fixture(scope="module")
def small():
    m = io.box(3).to(dtype=torch.float64)
    F0 = sh.sh_frame_field(m, n_smooth_iters=0)
    gen = torch.Generator().manual_seed(5)
    return m, so3.exp(0.8 * torch.randn(F0.shape[0], 3, generator=gen, dtype=torch.float64)) @ F0, F0


def _types(idx, mesh, around=None):
    """Face types of the matchings ``idx`` (of the faces ``around`` only when given)."""
    g = octahedral.group(torch.float64)[idx]
    if around is None:
        return classify_holonomy(face_holonomy_from_matchings(g, mesh)[2])[0]
    bc, ac, ab = (g[mesh.face_edges[around, c]] for c in range(3))
    return classify_holonomy(ab @ bc @ ac.transpose(-1, -2))[0]


def _slow_repair(F, mesh, mu, costs, limit):
    """Per-edge, per-element loop: the same greedy rule, every face type recomputed from scratch."""
    G = octahedral.group(F.dtype)
    idx = octahedral.match_edges(F, mesh.edges)[0].clone()
    cost = torch.tensor(costs, dtype=F.dtype)
    moves = []
    while len(moves) < limit:
        typ = _types(idx, mesh)
        edges = sorted({int(e) for f in torch.nonzero(typ == 3).reshape(-1).tolist() for e in mesh.face_edges[f]})
        best = None
        for e in edges:
            i, j = mesh.edges[e].tolist()
            r_old = float(((F[i] @ G[idx[e]] - F[j]) ** 2).sum())
            around = (mesh.face_edges == e).any(1)
            for k in range(24):
                trial = idx.clone()
                trial[e] = k
                dc = float(cost[_types(trial, mesh, around)].sum() - cost[typ[around]].sum())
                dr = float(((F[i] @ G[k] - F[j]) ** 2).sum()) - r_old
                if dc < -0.5 and (best is None or dc + mu * dr < best[0] - 1e-9):
                    best = (dc + mu * dr, e, k)
        if best is None:
            break
        moves.append(best[1:])
        idx[best[1]] = best[2]
    return idx, moves


def test_edge_face_incidence_lists_the_faces_of_every_edge(cyl):
    m = cyl[0]
    offsets, faces, slot = edge_face_incidence(m)
    assert offsets[0] == 0 and offsets[-1] == 3 * m.faces.shape[0]
    for e in torch.randperm(m.edges.shape[0], generator=torch.Generator().manual_seed(0))[:60].tolist():
        fs = faces[offsets[e]:offsets[e + 1]]
        want = torch.nonzero((m.face_edges == e).any(1)).reshape(-1)
        assert sorted(fs.tolist()) == want.tolist()
        assert (m.face_edges[fs, slot[offsets[e]:offsets[e + 1]]] == e).all()


def test_repair_matches_the_slow_reference(small):
    m, noisy, _ = small
    # 3 greedy moves (two state updates after a move; 6 took 8 s on 2 loaded cores, the loop's cost)
    idx, info = repair_matchings(noisy, m, max_moves=3)
    ref_idx, ref_moves = _slow_repair(noisy, m, 0.5, FACE_COSTS, 3)
    assert len(ref_moves) == 3
    assert [(mv[0], mv[2]) for mv in info["moves"]] == ref_moves
    assert torch.equal(idx, ref_idx)


def test_repair_invariants(small):
    m, noisy, F0 = small
    idx0 = octahedral.match_edges(noisy, m.edges)[0]
    typ0 = _types(idx0, m)
    idx, info = repair_matchings(noisy, m)
    typ = _types(idx, m)
    cost = torch.tensor(FACE_COSTS, dtype=torch.float64)
    assert info["complex_before"] == int((typ0 == 3).sum()) > 0
    assert info["complex_after"] == int((typ == 3).sum()) < info["complex_before"]
    assert info["singular_after"] == int((typ > 0).sum())
    assert info["cost_after"] == pytest.approx(float(cost[typ].sum()))
    assert info["cost_after"] < info["cost_before"] == pytest.approx(float(cost[typ0].sum()))
    assert all(mv[3] < 0 for mv in info["moves"])  # every move lowers the face cost
    assert info["cost_before"] + sum(mv[3] for mv in info["moves"]) == pytest.approx(info["cost_after"])
    changed = torch.nonzero(idx != idx0).reshape(-1)
    assert set(changed.tolist()) <= {mv[0] for mv in info["moves"]}
    # no complex face is left that one move could remove (the search stops at a local minimum)
    assert len(info["moves"]) < 4 * info["complex_before"] + 16
    # a field without complex faces is left alone; explicit matchings are the start
    idx_s, info_s = repair_matchings(F0, m)
    assert info_s["complex_before"] == 0 and info_s["moves"] == []
    assert torch.equal(idx_s, octahedral.match_edges(F0, m.edges)[0])
    idx_m, _ = repair_matchings(noisy, m, matchings=idx0)
    assert torch.equal(idx_m, idx)
    # max_moves bounds the search; float32 frames give a search of their own dtype
    _, info1 = repair_matchings(noisy, m, max_moves=1)
    assert len(info1["moves"]) == 1 and info1["moves"][0] == info["moves"][0]
    idx32, _ = repair_matchings(noisy.float(), m.to(dtype=torch.float32), max_moves=3)
    assert idx32.dtype == torch.long


def test_repair_errors(cyl):
    m, F0, _ = cyl
    for kw, msg in [({"face_costs": (0, 1, 1)}, "face_costs"), ({"face_costs": (0, 1, 9, 6)}, "face_costs"),
                    ({"face_costs": (0, 1, 1, float("nan"))}, "face_costs"),
                    ({"residual_weight": -1.0}, "residual_weight"),
                    ({"matchings": torch.zeros(3, dtype=torch.long)}, "matchings")]:
        with pytest.raises(ValueError, match=msg):
            repair_matchings(F0, m, **kw)
    with pytest.raises(ValueError, match="frames"):
        repair_matchings(F0[:-1], m)


def test_relax_to_matchings(cyl):
    m, F0, noisy = cyl
    idx, info = repair_matchings(noisy, m)
    G = octahedral.group(torch.float64)
    a_ref, d_ref = math.radians(10.0), 0.1

    def fixed_energy(F):
        e0, e1 = m.edges[:, 0], m.edges[:, 1]
        return float(((F[e0] @ G[idx] - F[e1]) ** 2).sum((-1, -2)).mean())

    F = relax_to_matchings(m, noisy, idx, a_ref=a_ref, d_ref=d_ref, iters=60)
    so3.check_rotation(F)
    assert fixed_energy(F) < 0.8 * fixed_energy(noisy)
    # the frames follow the prescribed matchings: fewer complex faces than the noisy field's own
    assert frame_metrics(F, m)["n_singular_faces_complex"] < info["complex_before"]
    # aligned boundary vertices rotate about their normal only: the alignment stays exact
    Fa = relax_to_matchings(m, F0, octahedral.match_edges(F0, m.edges)[0], a_ref=a_ref, d_ref=d_ref, iters=20)
    assert frame_metrics(F0, m)["alignment_max_deg"] < 1e-9 and frame_metrics(Fa, m)["alignment_max_deg"] < 1e-9
    assert not torch.allclose(Fa, F0)  # the frames did move
    for kw, msg in [({"matchings": idx[:-1]}, "matchings"), ({"matchings": idx.double()}, "matchings"),
                    ({"matchings": idx + 30}, "24 elements"), ({"iters": 0}, "iters"),
                    ({"dirichlet_weight": float("nan")}, "dirichlet_weight")]:
        with pytest.raises(ValueError, match=msg):
            relax_to_matchings(m, noisy, **{"matchings": idx, "a_ref": a_ref, "d_ref": d_ref, **kw})


def test_repair_structure(small):
    m, noisy, F0 = small
    a_ref, d_ref = math.radians(10.0), 0.1
    F, info = repair_structure(noisy, m, a_ref=a_ref, d_ref=d_ref, relax_iters=30)
    so3.check_rotation(F)
    assert info["complex_before"] == complex_face_count(noisy, m) == frame_metrics(noisy, m)["n_singular_faces_complex"]
    assert info["complex_after"] == complex_face_count(F, m) < info["complex_before"]
    p0 = info["passes"][0]
    assert len(p0["complex_relaxed"]) == 2 and p0["moves"] > 0
    assert info["complex_after"] <= min(p0["complex_relaxed"])
    # each pass lowers the count; one weight, one relaxation per pass
    _, one = repair_structure(noisy, m, a_ref=a_ref, d_ref=d_ref, relax_iters=30, passes=1, moved_edge_weights=(1.0,))
    assert len(one["passes"]) == 1 and len(one["passes"][0]["complex_relaxed"]) == 1
    assert one["complex_after"] == min(one["complex_before"], one["passes"][0]["complex_relaxed"][0])
    # no pass, or no complex face: the input comes back
    F_none, none = repair_structure(noisy, m, a_ref=a_ref, d_ref=d_ref, passes=0)
    assert F_none is not None and torch.equal(F_none, noisy) and none["passes"] == []
    F_clean, clean = repair_structure(F0, m, a_ref=a_ref, d_ref=d_ref)
    assert torch.equal(F_clean, F0) and clean["complex_before"] == clean["complex_after"] == 0
    for kw, msg in [({"moved_edge_weights": ()}, "moved_edge_weights"), ({"moved_edge_weights": (0.0,)}, "moved_edge_weights"),
                    ({"passes": -1}, "passes")]:
        with pytest.raises(ValueError, match=msg):
            repair_structure(noisy, m, a_ref=a_ref, d_ref=d_ref, **kw)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_repair_on_cuda_matches_cpu(small):
    m, noisy, _ = small
    idx, info = repair_matchings(noisy, m)
    mc = m.to(device="cuda")
    idx_c, info_c = repair_matchings(noisy.cuda(), mc)
    assert idx_c.device.type == "cuda" and torch.equal(idx_c.cpu(), idx)
    assert [mv[:3] for mv in info_c["moves"]] == [mv[:3] for mv in info["moves"]]
    F, s = repair_structure(noisy.cuda(), mc, a_ref=0.2, d_ref=0.1, relax_iters=10)
    assert F.device.type == "cuda" and s["complex_after"] <= s["complex_before"]
