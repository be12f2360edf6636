"""The frame field chosen by its hex meshes (:mod:`torchconn.hexmesh.choose`)."""
from __future__ import annotations

import torch

from torchconn import so3
from torchconn.frames.candidates import Candidate
from torchconn.hexmesh import hex_mesh
from torchconn.hexmesh.choose import NO_STRUCTURE, hex_chooser
from torchconn.mesh.builtin import box


# The hex-mesh options of every chooser here: the singular-graph repair off (the noisy field's hex
# mesh then fails its structure gate in ~0.8 s instead of ~4 s of repair; the chooser's logic does
# not depend on why a hex mesh is not good; the repair is tests/test_hexmesh_repair.py's).
HEX = {"edge_length": 0.25, "repair": False}


def _cands(mesh):
    V = mesh.n_vertices
    eye = torch.eye(3, dtype=torch.float64).expand(V, 3, 3).clone()
    g = torch.Generator().manual_seed(0)
    noisy = so3.exp(0.7 * torch.randn(V, 3, generator=g, dtype=torch.float64))
    mk = lambda F, kind, s: Candidate(frames=F, kind=kind, start="sh", dirichlet_weight=None, metrics={}, score=s)  # noqa: E731
    # the noisy field has the better proxy score: only its hex mesh loses
    return [mk(noisy, "optimized", 0.0), mk(eye, "optimized", 1.0)]


def test_the_chooser_picks_the_good_hex_mesh_and_keeps_it(monkeypatch):
    from torchconn.hexmesh import one_ring

    tested = []
    real = one_ring.one_ring_test
    monkeypatch.setattr(one_ring, "one_ring_test", lambda *a, **k: tested.append(1) or real(*a, **k))
    mesh = box(1)
    cands = _cands(mesh)
    choose = hex_chooser(**HEX)
    idx, info = choose(mesh, cands)
    assert len(tested) == 1  # two candidates meshed, the one-ring test run on the chosen one only
    assert idx == 1 and info["by"] == "hex" and info["reason"] == "a valid map and a good hex mesh"
    assert [r["good"] for r in info["meshed"]] == [False, True]
    # each row names the first gate that failed (none for the good one) and its hex stage's seconds
    assert info["meshed"][0]["first_failed"] in ("structure", "seamless", "quantization", "extraction")
    assert info["meshed"][1]["first_failed"] is None and all(r["seconds"] > 0 for r in info["meshed"])
    frames, kept = choose.chosen
    assert frames is cands[1].frames and kept.good
    # what it keeps is the hex mesh of that field with those options: no need to mesh it again
    again = hex_mesh(mesh, cands[1].frames, **HEX)
    assert torch.equal(torch.as_tensor(kept.hexes), torch.as_tensor(again.hexes))
    assert torch.equal(torch.as_tensor(kept.points), torch.as_tensor(again.points))
    g, h = kept.gates["structure"], again.gates["structure"]
    assert g.counts == h.counts and g.counts["one_ring_tested"] > 0 and g.passed == h.passed
    for d in (g.info, h.info):
        d["one_ring"]["counts"].pop("seconds")
    assert g.info == h.info
    assert kept.map.stats["timings"]["one_ring_s"] > 0


def _stack(mesh, order, calls, **kw):
    from torchconn.frames.candidates import CandidateStack
    from torchconn.frames.metrics import frame_metrics

    fields = {name: c.frames for name, c in zip(("noisy", "good"), _cands(mesh))}

    def start(label):
        def run():
            calls.append(label)  # the optimization of this start, run when its stage is made
            return fields[label], None
        return run

    ref = frame_metrics(fields["good"], mesh, 30.0, curl=False)
    return CandidateStack(mesh, {label: start(label) for label in order}, ref, **kw)


def test_the_chooser_makes_the_stages_only_until_a_good_hex_mesh():
    mesh = box(1)
    calls = []
    stack = _stack(mesh, ("good", "noisy"), calls)
    idx, info = hex_chooser(**HEX)(mesh, stack)
    assert calls == ["good"] and stack.info["stages"] == ["optimized:good"]  # the second start never optimized
    assert idx == 0 and info["stopped"] == "the first good hex mesh" and [r["good"] for r in info["meshed"]] == [True]
    calls = []
    stack = _stack(mesh, ("noisy", "good"), calls)
    idx, info = hex_chooser(**HEX)(mesh, stack)
    # the first start's field does not mesh well: the next stage is made, its field meshed, and the
    # quality paths (stage 3) are never made
    assert calls == ["noisy", "good"] and stack.info["stages"] == ["optimized:noisy", "optimized:good"]
    assert stack[idx].start == "good" and [r["good"] for r in info["meshed"]] == [False, True]
    assert not stack.done and stack.next_stage() is not None  # what is left can still be made


def test_the_chooser_without_first_good_makes_and_meshes_everything():
    mesh = box(1)
    calls = []
    stack = _stack(mesh, ("good", "noisy"), calls, paths=())
    idx, info = hex_chooser(first_good=False, **HEX)(mesh, stack)
    assert calls == ["good", "noisy"] and stack.done and stack.next_stage() is None
    assert stack[idx].start == "good" and info["stopped"] == "every candidate meshed" and len(info["meshed"]) == 2
    capped = hex_chooser(1, first_good=False, **HEX)(mesh, _stack(mesh, ("noisy", "good"), [], paths=()))[1]
    assert capped["stopped"] == "max_candidates=1 meshed" and len(capped["meshed"]) == 1



def _fake_hex(monkeypatch, stack, gates: dict):
    """``hex_mesh`` replaced by a stand-in whose result fails the gate ``gates[start]`` (``None``:
    good) for the optimized field of ``start`` and ``"seamless"`` for every other field: the
    chooser's logic on given outcomes, without meshing. Returns the list of the gates it gave."""
    from types import SimpleNamespace

    from torchconn.hexmesh import pipeline

    made = []

    def fake(mesh, frames, **options):
        c = next(c for c in stack if c.frames.data_ptr() == frames.data_ptr())
        ff = gates[c.start] if c.kind == "optimized" else "seamless"
        made.append(ff)
        return SimpleNamespace(first_failed=ff, good=ff is None, quality=None, extraction=None,
                               hexes=torch.zeros(0, 8, dtype=torch.long),
                               validity=SimpleNamespace(valid=ff in (None, "extraction"), reasons=[], counts={}))

    monkeypatch.setattr(pipeline, "hex_mesh", fake)
    return made


def test_the_quality_paths_continue_only_fields_whose_structure_passed(monkeypatch):
    mesh = box(1)
    kw = dict(dirichlet_weights=(1.0, 0.5), rounds=1, iters=2)
    # both optimized fields fail the structure gate: no quality path is made
    stack = _stack(mesh, ("noisy", "good"), [], **kw)
    made = _fake_hex(monkeypatch, stack, {"noisy": "structure", "good": "structure"})
    idx, info = hex_chooser(one_ring=False)(mesh, stack)
    assert made == ["structure", "structure"] and info["stopped"] == NO_STRUCTURE
    assert stack.info["stages"] == ["optimized:noisy", "optimized:good"] and len(stack) == 2
    # the second start's field passes the structure gate (and fails later): only its paths are made
    stack = _stack(mesh, ("noisy", "good"), [], **kw)
    made = _fake_hex(monkeypatch, stack, {"noisy": "structure", "good": "extraction"})
    idx, info = hex_chooser(one_ring=False)(mesh, stack)
    assert stack.done and stack.path_starts == {"good"} and len(stack) == 4
    assert [c.start for c in stack] == ["noisy", "good", "good", "good"]
    assert made == ["structure", "extraction", "seamless"]  # the best checkpoint of the one path kind
    assert info["stopped"] == "every candidate meshed" and stack[idx].start == "good"
    # and both pass: the paths of both
    stack = _stack(mesh, ("noisy", "good"), [], **kw)
    _fake_hex(monkeypatch, stack, {"noisy": "seamless", "good": "seamless"})
    hex_chooser(one_ring=False)(mesh, stack)
    assert stack.path_starts == {"noisy", "good"} and [c.start for c in stack[2:]].count("noisy") == 2
