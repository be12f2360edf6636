"""``torchconn.frames.design``: the frame-field method as a library call (torchconn/frames/design.py)."""
from __future__ import annotations

import doctest
import io as _io
import math
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import torchconn.frames
from torchconn import io as tio
from torchconn.frames import FrameFieldResult, design, octahedral
from torchconn.frames.design import DEFAULTS, OPTIONS
from torchconn.frames.octahedral import tet_frames
from torchconn.frames.sh import sh_frame_field
from torchconn.lie import so3

ROOT = Path(__file__).resolve().parents[1]
FAST = {"sh": {"n_smooth_iters": 5}}
ONE = {**FAST, "starts": ["sh"]}  # one start: the tests of the optimization loop itself
TWO = {**FAST, "starts": ["sh", "mbo"]}  # both starts (the default is the SH start alone)


@pytest.fixture(scope="module")
def mesh():
    return tio.cylinder(edge_length=0.6)  # 182 vertices, 675 tets, sharp rims, singular curves


def _rotations_ok(R, atol=1e-12):
    eye = torch.eye(3, dtype=R.dtype)
    return bool(((R.transpose(-1, -2) @ R - eye).abs().max() < atol) and (torch.linalg.det(R) > 0).all())


# ----------------------------------------------------------------------------- CLI equality
def test_design_equals_cli_frames_bitwise(tmp_path, mesh):
    from training.train_frames import design_options, train

    cfg = {"mesh": "cylinder", "edge_length": 0.6, "steps": 4, "sh": {"n_smooth_iters": 5}, "progress": False,
           "output_dir": str(tmp_path / "cli"), "seed": 3,
           "select": "proxies", "map_weight": 0.0}  # design() alone: no hex-stage term, its own choice
    m = train(cfg)
    z = np.load(tmp_path / "cli" / "frames.npz")
    r = design(mesh, "connection", seed=3, dtype=torch.float64, steps=4, sh={"n_smooth_iters": 5})
    assert np.array_equal(z["frames"], r.vertex_frames.numpy())
    assert np.array_equal(z["vertices"], r.mesh.vertices.numpy())
    assert np.array_equal(z["singular_faces"], r.mesh.faces[r.singular_faces].numpy())
    assert m["loss_history"] == r.history
    assert m["final"] == r.metrics["final"] and m["init"] == r.metrics["init"]
    # the CLI passes exactly the method's options
    from training.train_frames import _validate

    assert set(design_options(_validate(cfg))) == set(OPTIONS["connection"])
    assert design_options(_validate({**cfg, "map_weight": 1.5}))["weights"]["map"] == 1.5  # the job's hex-stage term
    assert set(design_options(_validate({**cfg, "method": "sh_baseline"}))) == set(OPTIONS["sh"])


def test_defaults_are_the_schema_and_the_job_composes_them():
    """DEFAULTS is the schema's (torchconn.frames.options.FrameOptions, the one place a default is
    written); the frame job's composed config holds exactly those values for the method's keys, and
    its other keys are the job's own."""
    import dataclasses

    from torchconn.frames.options import FrameOptions
    from training.train_frames import load_config

    assert DEFAULTS == dataclasses.asdict(FrameOptions())
    assert tuple(DEFAULTS) == OPTIONS["connection"]
    cfg = OmegaConf.to_container(load_config(["output_dir=x"]))
    for k, v in DEFAULTS.items():
        assert cfg[k] == v, f"the job's {k!r} = {cfg[k]!r}, design()'s default {v!r}"
    cli_only = {"mesh", "edge_length", "method", "device", "num_threads", "dtype", "seed", "output_dir", "resume",
                "checkpoint_every", "progress", "select", "select_candidates", "map_weight"}
    assert set(cfg) - set(DEFAULTS) == cli_only


# ----------------------------------------------------------------------------- library behaviour
def test_in_memory_mesh_writes_no_files(tmp_path, monkeypatch, mesh):
    monkeypatch.chdir(tmp_path)
    r = design(mesh, steps=3, **FAST)
    assert list(tmp_path.iterdir()) == []
    assert list(r.histories) == ["sh"] and r.history is r.histories["sh"]  # the default: the SH start alone
    r = design(mesh, steps=3, **TWO)
    assert list(r.histories) == ["sh", "mbo"] and r.history is r.histories[r.metrics["chosen"]["start"]]
    assert isinstance(r, FrameFieldResult)
    V, E, T = mesh.n_vertices, mesh.n_edges, mesh.n_tets
    assert r.vertex_frames.shape == (V, 3, 3) and r.tet_frames.shape == (T, 3, 3)
    assert r.edge_rot.shape == (E, 3, 3) and r.matchings.shape == (E,) and r.matchings.dtype == torch.long
    assert r.singular_faces.shape == (mesh.n_faces,) and r.singular_faces.dtype == torch.bool
    assert _rotations_ok(r.vertex_frames) and _rotations_ok(r.tet_frames) and _rotations_ok(r.edge_rot, 1e-10)
    # the result's pieces are the ones the metrics use
    assert torch.equal(r.matchings, octahedral.match_edges(r.vertex_frames, mesh.edges)[0])
    assert torch.equal(r.singular_faces, octahedral.singular_faces(r.vertex_frames, mesh)[0])
    assert r.metrics["final"]["n_singular_faces"] == int(r.singular_faces.sum())
    assert r.metrics["invariants"]["bianchi_ok"] and r.metrics["method"] == "connection"
    assert set(r.history) >= {"total", "smooth", "tie"} and all(len(v) == 3 for v in r.history.values())
    assert r.timings["iterations"] == 6 and not r.timings["stopped_early"]  # 3 steps from each start
    assert repr(r).startswith("FrameFieldResult(method='connection', V=182, T=675") and len(repr(r)) < 300


def test_path_input_equals_in_memory(tmp_path, mesh):
    path = tmp_path / "cyl.mesh"
    meshio.write(path, meshio.Mesh(mesh.vertices.numpy(), [("tetra", mesh.tets.numpy())]))
    a = design(path, "sh", sh=FAST["sh"])
    b = design(mesh, "sh", sh=FAST["sh"])
    assert torch.equal(a.vertex_frames, b.vertex_frames)
    with pytest.raises(FileNotFoundError, match="nope.mesh"):
        design(tmp_path / "nope.mesh")


def test_callback_sees_every_step_and_stops_early(mesh):
    seen = []

    def cb(step, record):
        seen.append((step, record["total"]))

    r = design(mesh, steps=4, callback=cb, **TWO)
    assert [s for s, _ in seen] == [1, 2, 3, 4, 5, 6, 7, 8]  # counted across the two starts
    assert [t for _, t in seen] == r.histories["sh"]["total"] + r.histories["mbo"]["total"]

    r = design(mesh, steps=10, callback=lambda step, record: step == 3, **ONE)
    assert len(r.history["total"]) == 3 and r.timings["stopped_early"] and r.timings["iterations"] == 3
    assert r.timings["total_steps"] == 10
    # a truthy value other than True does not stop (the documented rule is "returns True")
    r = design(mesh, steps=2, callback=lambda step, record: 1, **ONE)
    assert len(r.history["total"]) == 2 and not r.timings["stopped_early"]


def test_progress_bar(capsys, mesh):
    pytest.importorskip("tqdm")
    r = design(mesh, steps=2, progress=True, **ONE)
    assert len(r.history["total"]) == 2
    assert "design" in capsys.readouterr().err


def test_unknown_options_name_themselves(mesh):
    with pytest.raises(TypeError, match=r"'stpes'.*known options.*'steps'"):
        design(mesh, stpes=3)
    with pytest.raises(TypeError, match=r"weights\.smoth.*'smooth'"):
        design(mesh, weights={"smoth": 1.0})
    with pytest.raises(TypeError, match=r"'steps'.*another method"):
        design(mesh, "sh", steps=3)
    with pytest.raises(ValueError, match="unknown method 'ffd'"):
        design(mesh, "ffd")
    with pytest.raises(ValueError, match="optim='sgd'"):
        design(mesh, optim="sgd")
    with pytest.raises(ValueError, match="weights.tie"):
        design(mesh, weights={"tie": -1.0})


def test_sh_method(mesh):
    r = design(mesh, "sh", sh={"n_smooth_iters": 5})
    F = sh_frame_field(mesh, n_smooth_iters=5)
    assert torch.equal(r.vertex_frames, F)
    assert r.history == {} and r.timings["iterations"] == 0 and r.metrics["final"] == r.metrics["init"]
    assert r.metrics["final_loss_terms"] is None and r.metrics["formulation"] is None
    # edge_rot is the matched connection: F_i R_ij = F_j g*_ij^T exactly up to round-off
    g = octahedral.group(F.dtype)[r.matchings]
    i, j = mesh.edges.unbind(1)
    assert (F[i] @ r.edge_rot - F[j] @ g.transpose(-1, -2)).abs().max() < 1e-12
    assert design(mesh, "sh_baseline", sh={"n_smooth_iters": 5}).vertex_frames.equal(F)
    # init_frames as an in-memory tensor (checked against the mesh)
    assert (design(mesh, "sh", init_frames=F).vertex_frames - F).abs().max() < 1e-14
    with pytest.raises(ValueError, match=r"init_frames has shape \(181, 3, 3\)"):
        design(mesh, "sh", init_frames=F[1:])


def test_dtype_argument(mesh):
    r = design(mesh, "sh", dtype=torch.float32, sh={"n_smooth_iters": 2})
    assert r.vertex_frames.dtype == r.tet_frames.dtype == r.edge_rot.dtype == torch.float32
    assert r.mesh.vertices.dtype == torch.float32 and mesh.vertices.dtype == torch.float64


def test_resume_from_state_equals_uninterrupted(mesh):
    states = {}

    def keep(state):  # serialize now: the state_dicts are live
        buf = _io.BytesIO()
        torch.save(state, buf)
        states[(state["start"], state["step"])] = buf.getvalue()

    full = design(mesh, steps=6, checkpoint_every=2, on_checkpoint=keep, **TWO)
    assert sorted(states) == sorted((s, k) for s in ("sh", "mbo") for k in (0, 2, 4, 6))
    for key, iters in ((("sh", 2), 4 + 6), (("mbo", 4), 2)):  # inside the first start, inside the second
        state = torch.load(_io.BytesIO(states[key]), weights_only=False)
        resumed = design(mesh, steps=6, state=state, **TWO)
        assert torch.equal(full.vertex_frames, resumed.vertex_frames)
        assert full.histories == resumed.histories and resumed.timings["iterations"] == iters


# ----------------------------------------------------------------------------- per-tet frames
def test_tet_frames_of_a_constant_field_are_exact(mesh):
    Q = so3.random_rotation(1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)[0]
    F = Q.expand(mesh.n_vertices, 3, 3).clone()
    assert torch.equal(tet_frames(F, mesh), Q.expand(mesh.n_tets, 3, 3))
    # relabeled per vertex: the tet takes its lowest vertex's frame, exactly
    G = octahedral.group(torch.float64)
    h = G[torch.randint(0, 24, (mesh.n_vertices,), generator=torch.Generator().manual_seed(1))]
    Fh = Q @ h
    a = mesh.tets.min(1).values
    assert torch.equal(tet_frames(Fh, mesh), Fh[a])


def _tet_frames_naive(F: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Per-tet loop: chordal mean of the frames relabeled onto the lowest vertex's, projected by SVD."""
    G = octahedral.group(torch.float64).numpy()
    out = np.empty((len(tets), 3, 3))
    for t, tet in enumerate(tets):
        a = tet.min()
        acc = np.zeros((3, 3))
        for v in tet:
            g = G[np.argmax([np.trace(gg.T @ F[a].T @ F[v]) for gg in G])]
            acc += F[v] @ g.T
        U, _, Vt = np.linalg.svd(acc / 4)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        out[t] = U @ D @ Vt
    return out


def test_tet_frames_match_a_naive_reference_and_follow_relabeling(mesh):
    F = sh_frame_field(mesh, n_smooth_iters=5)
    T = tet_frames(F, mesh)
    assert _rotations_ok(T)
    assert np.abs(T.numpy() - _tet_frames_naive(F.numpy(), mesh.tets.numpy())).max() < 1e-12
    # relabeling the vertex frames relabels each tet frame by its lowest vertex's element
    h = octahedral.group(torch.float64)[torch.randint(0, 24, (mesh.n_vertices,),
                                                     generator=torch.Generator().manual_seed(2))]
    a = mesh.tets.min(1).values
    assert (tet_frames(F @ h, mesh) - T @ h[a]).abs().max() < 1e-12
    # a tet frame lies close to its vertex frames (smooth field: within the largest tet-edge angle)
    ang = so3.geodesic_distance(T, F[a]) * 180 / math.pi
    assert float(ang.max()) < 90.0 and float(ang.median()) < 10.0


def test_module_docstring_example():
    res = doctest.testmod(torchconn.frames, verbose=False)
    assert res.attempted >= 6 and res.failed == 0
