"""End-to-end tests of the `train_frames` command (training/train_frames.py)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch

from torchconn.frames import loss as losses
from torchconn.frames.metrics import METRIC_KEYS
from torchconn.mesh import MeshError
from training import io_utils
from training.train_frames import NonFiniteLossError, load_config, train

ROOT = Path(__file__).resolve().parents[1]
# a tiny generated mesh with singular curves and sharp rims (about 180 vertices); one start and the
# proxies' choice keep these tests of the job cheap (test_cli_end_to_end runs the defaults: two
# starts, the choice by the hex meshes)
TINY = {"mesh": "cylinder", "edge_length": 0.6, "sh": {"n_smooth_iters": 5}, "progress": False, "num_threads": 1,
        "starts": ["sh"], "select": "proxies", "map_weight": 0.0}
OUTPUTS = ("frames.npz", "metrics.json", "frames.vtu", "frames.fra", "singular_faces.vtu", "singular_curves.vtu",
           "loss.png",
           "singularities.png",
           "checkpoint.pt")


def _cfg(tmp_path, name="run", **kw):
    cfg = {**TINY, "output_dir": str(tmp_path / name)}
    cfg.update(kw)
    return cfg


def _run_cli(args, cwd=ROOT, timeout=300):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "training.train_frames", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_cli_end_to_end(tmp_path):
    out = tmp_path / "cli"
    r = _run_cli(["mesh=cylinder", "edge_length=0.6", "steps=3", "sh.n_smooth_iters=5", "starts=[sh,mbo]",
                  f"output_dir={out}", "num_threads=1",
                  f"hydra.run.dir={tmp_path / 'hydra'}",
                  "checkpoint_every=2"])
    assert r.returncode == 0, r.stderr[-3000:]
    for name in OUTPUTS:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    for part in ("final", "init"):
        assert set(METRIC_KEYS) <= set(m[part]), part
    assert m["method"] == "connection"
    assert set(m["loss_history"]) >= {"total", "smooth", "tie", "flat", "torsion", "align", "feature"}
    assert all(len(v) == 3 for v in m["loss_history"].values())
    inv = m["invariants"]
    assert inv["bianchi_ok"] is True and inv["bianchi_differential_max"] <= inv["bianchi_tolerance"]
    assert inv["n_tets_one_singular_face"] == m["final"]["n_tets_one_singular_face"]
    assert m["timings"]["iterations"] == 6 and m["timings"]["wall_s"] > 0  # 3 steps from each of the 2 starts
    c = m["chosen"]  # the returned field: a candidate of the connection optimization, chosen by its hex mesh
    zm = np.load(out / "map_frames.npz")  # the field its map follows, per tet on the map's mesh
    assert zm["frames"].shape == (zm["tets"].shape[0], 3, 3) and zm["vertices"].shape[1] == 3
    assert c["by"] == "hex" and c["start"] in ("sh", "mbo") and c["meshed"] and len(c["candidates"]) >= 2
    assert "returned field:" in r.stdout and c["label"] in r.stdout
    z = np.load(out / "frames.npz")
    V, T = z["vertices"], z["tets"]
    assert V.dtype == np.float64 and T.dtype == np.int64 and z["frames"].dtype == np.float64
    assert z["frames"].shape == (V.shape[0], 3, 3) and T.shape[1] == 4
    assert z["singular_faces"].shape == (m["final"]["n_singular_faces"], 3)
    F = z["frames"]
    assert np.allclose(F.transpose(0, 2, 1) @ F, np.eye(3), atol=1e-10)
    vtu = meshio.read(out / "frames.vtu")
    assert {"axis0", "axis1", "axis2"} <= set(vtu.point_data)
    assert np.allclose(vtu.point_data["axis1"], F[:, :, 1])
    ck = io_utils.load_checkpoint(out / "checkpoint.pt")
    assert ck["step"] == 3
    assert torch.load(out / "checkpoint.pt", weights_only=True)["step"] == 3  # no pickled objects
    # the lock is released and no staging folder or temporary file is left
    assert not [p.name for p in out.iterdir() if p.name.startswith((".lock", ".staging")) or p.name.endswith(".tmp")]


def test_loss_decreases_and_field_improves(tmp_path):
    # the optimized field itself (the quality stage off: tests/test_frame_quality.py covers it)
    m = train(_cfg(tmp_path, steps=25, quality={"enabled": False}))
    h = m["loss_history"]
    assert h["total"][-1] < h["total"][0]
    assert m["chosen"]["kind"] == "optimized" and len(m["chosen"]["candidates"]) == 1
    assert m["invariants"]["bianchi_ok"]
    assert h["feature"][-1] < h["feature"][0]  # the rims follow their face normals better
    f, i = m["final"], m["init"]
    assert f["smoothness_mean_deg"] < i["smoothness_mean_deg"]
    # exact alignment at non-feature boundary vertices is kept (rotation about the normal only)
    assert i["alignment_max_deg"] < 1e-6 and f["alignment_max_deg"] < 1e-6
    assert m["final_loss_terms"]["total"] < h["total"][0]


def test_sh_baseline_method(tmp_path):
    m = train(_cfg(tmp_path, method="sh_baseline"))
    assert m["final"] == m["init"] and m["timings"]["iterations"] == 0
    assert (tmp_path / "run" / "frames.npz").is_file()
    # the edge-class diagnostic recomposes the smoothness mean
    ec = m["edge_classes"]
    mean = sum(v["fraction"] * v["mean_deg"] for v in ec.values() if v["count"])
    assert mean == pytest.approx(m["final"]["smoothness_mean_deg"], rel=1e-9)
    # the SH options are wired through the config
    mb = train(_cfg(tmp_path, name="lin", method="sh_baseline", sh={"n_smooth_iters": 0}))
    assert mb["config"]["sh"]["n_smooth_iters"] == 0 and mb["final"] != m["final"]
    assert mb["final"]["alignment_max_deg"] < 1e-6


def test_resume_equals_uninterrupted(tmp_path, monkeypatch):
    full = train(_cfg(tmp_path, "full", steps=6, checkpoint_every=2))
    # simulate a crash during step 3 (the checkpoint of step 2 is on disk), then resume
    real = losses.FrameFieldLoss.__call__
    calls = {"n": 0}

    def crash(*a, **k):
        calls["n"] += 1
        if calls["n"] == 4:
            raise RuntimeError("simulated crash")
        return real(*a, **k)

    monkeypatch.setattr(losses.FrameFieldLoss, "__call__", crash)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(_cfg(tmp_path, "part", steps=6, checkpoint_every=2))
    monkeypatch.setattr(losses.FrameFieldLoss, "__call__", real)
    assert io_utils.load_checkpoint(tmp_path / "part" / "checkpoint.pt")["step"] == 2
    resumed = train(_cfg(tmp_path, "part", steps=6, checkpoint_every=2, resume=True))
    a = np.load(tmp_path / "full" / "frames.npz")["frames"]
    b = np.load(tmp_path / "part" / "frames.npz")["frames"]
    assert np.abs(a - b).max() <= 1e-10
    assert np.allclose(full["loss_history"]["total"], resumed["loss_history"]["total"], rtol=0, atol=1e-12)
    assert resumed["timings"]["iterations"] == 4


def test_resume_rejects_other_configuration(tmp_path):
    off = {"enabled": False}  # the quality stage runs after the checkpointed steps: not what is tested
    train(_cfg(tmp_path, steps=1, quality=off))
    with pytest.raises(ValueError, match="refusing to resume"):
        train(_cfg(tmp_path, steps=1, quality=off, resume=True, weights={"tie": 3.0}))
    with pytest.raises(FileNotFoundError, match="checkpoint"):
        train(_cfg(tmp_path, "empty", steps=2, resume=True))


def test_nan_stops_with_term_name_and_keeps_checkpoint(tmp_path, monkeypatch):
    real = losses.FrameFieldLoss.__call__
    calls = {"n": 0}

    def poisoned(*a, **k):
        calls["n"] += 1
        out = real(*a, **k)
        if calls["n"] > 5:  # steps 0..4 fine, NaN in the smooth term at step 5
            out["smooth"] = out["smooth"] * float("nan")
            out["total"] = out["total"] + out["smooth"]
        return out

    monkeypatch.setattr(losses.FrameFieldLoss, "__call__", poisoned)
    with pytest.raises(NonFiniteLossError, match=r"'smooth'.*step 5"):
        train(_cfg(tmp_path, steps=10, checkpoint_every=2))
    ck = io_utils.load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert ck["step"] == 4  # the last good checkpoint survives
    assert all(torch.isfinite(v).all() for v in ck["model"].values() if v.is_floating_point())
    assert not any(p.name.endswith(".tmp") for p in (tmp_path / "run").iterdir())


def test_unknown_config_key_fails_before_anything(tmp_path):
    from hydra.errors import ConfigCompositionException
    from omegaconf.errors import ConfigKeyError

    with pytest.raises(ConfigCompositionException):
        load_config(["weigths.smooth=1"])
    with pytest.raises(ConfigKeyError, match="smoth"):
        train(_cfg(tmp_path, weights={"smoth": 1.0}))
    with pytest.raises(ValueError, match="optim"):
        train(_cfg(tmp_path, optim="sgd"))
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match="align_kind"):
        train(_cfg(tmp_path, align_kind="cubic"))
    assert not (tmp_path / "run").exists()
    cfg = load_config(["steps=7", "optim=lbfgs", "method=sh_baseline", "dtype=float32"])
    assert cfg.steps == 7 and cfg.optim == "lbfgs" and cfg.align_kind == "angle"


def test_cli_unknown_key_exits_nonzero(tmp_path, monkeypatch, capsys):
    """The console entry point (in this process: a fresh one cost ~9 s; the fresh-process run is
    the slow ``test_cli_end_to_end``) exits nonzero naming the key and writes nothing."""
    code = _main_in_process(["no_such_key=1", f"output_dir={tmp_path / 'x'}"], tmp_path, monkeypatch)
    assert code not in (0, None) and "no_such_key" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and list(tmp_path.iterdir()) == []


def test_hex_choice_writes_the_field_its_map_follows(tmp_path):
    """``select=hex``: ``map_frames.npz`` holds the chosen candidate's map's field (per tet on the
    map's mesh, the input's vertices first); ``select=proxies`` writes none."""
    out = tmp_path / "hex"
    m = train(_cfg(tmp_path, "hex", mesh="box", edge_length=0.5, select="hex", select_candidates=1, steps=3,
                   quality={"enabled": False}))
    assert m["chosen"]["by"] == "hex"
    zm, z = np.load(out / "map_frames.npz"), np.load(out / "frames.npz")
    assert zm["frames"].shape == (zm["tets"].shape[0], 3, 3)
    np.testing.assert_array_equal(zm["vertices"][: z["vertices"].shape[0]], z["vertices"])
    R = torch.as_tensor(zm["frames"])
    torch.testing.assert_close(R.transpose(1, 2) @ R, torch.eye(3, dtype=R.dtype).expand_as(R), atol=1e-9, rtol=0)
    train(_cfg(tmp_path, "proxies", mesh="box", edge_length=0.5, steps=3, quality={"enabled": False}))
    assert not (tmp_path / "proxies" / "map_frames.npz").exists()


CLI_TINY = ["mesh=cylinder", "edge_length=0.6", "method=sh_baseline", "sh.n_smooth_iters=5", "progress=false",
            "num_threads=1"]


def _main_in_process(args, cwd, monkeypatch):
    """The frame job's console entry point run in this process (Hydra parses ``sys.argv``) in
    ``cwd``; its exit status (0 when it returns)."""
    from training import train_frames as job

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", ["train_frames", *args])
    try:
        job.main()
    except SystemExit as exc:
        return exc.code
    return 0


@pytest.mark.parametrize("given", [True, False])
def test_console_run_writes_only_its_output_dir(tmp_path, monkeypatch, capsys, given):
    """With ``output_dir`` given nothing is written under the working directory (no
    ``outputs/<date>``, no ``.hydra``, no log); without it the outputs go to
    ``outputs/train_frames/<date>/<time>``."""
    cwd, out = tmp_path / "cwd", tmp_path / "out"
    cwd.mkdir()
    assert _main_in_process([*CLI_TINY] + ([f"output_dir={out}"] if given else []), cwd, monkeypatch) == 0
    printed = capsys.readouterr().out
    if given:
        assert list(cwd.iterdir()) == [] and (out / "metrics.json").is_file() and not (out / ".hydra").exists()
        assert f"output {out}" in printed
    else:
        runs = list((cwd / "outputs" / "train_frames").glob("*/*"))
        assert [p.name for p in cwd.iterdir()] == ["outputs"] and len(runs) == 1
        assert (runs[0] / "metrics.json").is_file() and f"output {runs[0]}" in printed


def test_unwritable_output_dir(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    with pytest.raises(io_utils.OutputDirError, match="file.txt"):
        train(_cfg(tmp_path, output_dir=str(blocker / "sub")))
    with pytest.raises(io_utils.OutputDirError, match="not a directory"):
        train(_cfg(tmp_path, output_dir=str(blocker)))


def test_inverted_tet_mesh_fails_cleanly(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=float)
    tets = np.array([[0, 1, 2, 3], [1, 2, 4, 3]])  # the second one is negatively oriented
    path = tmp_path / "bad.mesh"
    meshio.write(path, meshio.Mesh(pts, [("tetra", tets)]))
    with pytest.raises(MeshError, match="inverted"):
        train(_cfg(tmp_path, mesh=str(path)))
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
    with pytest.raises(FileNotFoundError, match="no_such.mesh"):
        train(_cfg(tmp_path, mesh=str(tmp_path / "no_such.mesh")))


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    p = tmp_path / "a.json"
    io_utils.atomic_write_json(p, {"x": 1})

    def boom(f):
        f.write(b"partial")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        io_utils.atomic_write(p, boom)
    assert json.loads(p.read_text()) == {"x": 1}
    assert [q.name for q in tmp_path.iterdir()] == ["a.json"]


def test_propagate_formulation_and_lbfgs(tmp_path):
    m = train(_cfg(tmp_path, steps=5, formulation="propagate", optim="lbfgs", lr=0.5, quality={"enabled": False}))
    assert m["formulation"] == "propagate" and np.isfinite(m["final"]["smoothness_mean_deg"])


def test_hydra_multirun(tmp_path):
    sweep = tmp_path / "sweep"
    r = _run_cli(["-m", "mesh=cylinder", "edge_length=0.6", "steps=1", "sh.n_smooth_iters=2",
                  "weights.flat=0.1,1.0", f"hydra.sweep.dir={sweep}"], timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    for job in ("0", "1"):
        assert (sweep / job / "metrics.json").is_file()


def test_compare_frames_table():
    """benchmarks.compare_frames renders the relative smoothness change and failed runs."""
    from benchmarks.compare_frames import COLUMNS, table

    base = {k: 1.0 for k in COLUMNS} | {"smoothness_mean_deg": 4.0, "feature_alignment_mean_deg": float("nan")}
    res = {"gear": {"sh_baseline": {"metrics": base, "wall_s": 1.0},
                    "connection": {"metrics": base | {"smoothness_mean_deg": 3.6}, "wall_s": 2.0},
                    "mouette": {"error": "did not finish within 300 s"}}}
    lines = table(res).splitlines()
    assert len(lines) == 5 and "-10.0%" in lines[3] and "did not finish" in lines[4]
    assert "| – |" in lines[2]  # nan shown as a dash
    # with the linear-only baseline: a second relative column
    res["gear"]["sh_linear"] = {"metrics": base | {"smoothness_mean_deg": 4.5}, "wall_s": 0.5,
                                "edge_classes": {"interior": {"count": 3, "mean_deg": 2.0, "share": 1.0}}}
    lines = table(res).splitlines()
    assert "| -10.0% | -20.0% |" in lines[3]
    from benchmarks.compare_frames import breakdown_table

    assert "| gear | sh_linear | interior | 3 | 2.000 | 1.000 |" in breakdown_table(res)


def test_init_frames_from_file(tmp_path):
    """init_frames= starts from a saved field (studies); shape and rotation are checked first."""
    a = train(_cfg(tmp_path, name="a", method="sh_baseline"))
    src = tmp_path / "a" / "frames.npz"
    b = train(_cfg(tmp_path, name="b", method="sh_baseline", init_frames=str(src), sh={"n_smooth_iters": 0}))
    keys = ("smoothness_mean_deg", "feature_alignment_mean_deg", "n_singular_faces")
    # the saved field (to round-off), not the (different) SH field without smoothing
    assert [b["init"][k] for k in keys] == pytest.approx([a["init"][k] for k in keys], rel=1e-9)
    assert b["init"]["alignment_max_deg"] < 1e-6
    c = train(_cfg(tmp_path, name="c", init_frames=str(src), steps=3, quality={"enabled": False}))
    assert [c["init"][k] for k in keys] == pytest.approx([a["init"][k] for k in keys], rel=1e-9)
    assert c["timings"]["iterations"] == 3
    F = np.load(src)["frames"]
    np.save(tmp_path / "short.npy", F[:-1])
    with pytest.raises(ValueError, match="shape"):
        train(_cfg(tmp_path, name="d", init_frames=str(tmp_path / "short.npy")))
    np.save(tmp_path / "scaled.npy", 2.0 * F)
    with pytest.raises(ValueError, match="not rotations"):
        train(_cfg(tmp_path, name="e", init_frames=str(tmp_path / "scaled.npy")))
    with pytest.raises(FileNotFoundError, match="init_frames"):
        train(_cfg(tmp_path, name="f", init_frames=str(tmp_path / "missing.npz")))


def test_resume_is_bitwise_and_frames_equal_design(tmp_path, monkeypatch):
    """A crash + resume=true gives the uninterrupted run's frames bit for bit (quality stage on), and both
    are the frames of torchconn.frames.design with the same options."""
    from torchconn import io as tio
    from torchconn.frames import design

    kw = {"steps": 5, "checkpoint_every": 2}
    full = train(_cfg(tmp_path, "full", **kw))
    real = losses.FrameFieldLoss.__call__
    calls = {"n": 0}

    def crash(*a, **k):
        calls["n"] += 1
        if calls["n"] == 4:
            raise RuntimeError("simulated crash")
        return real(*a, **k)

    monkeypatch.setattr(losses.FrameFieldLoss, "__call__", crash)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(_cfg(tmp_path, "part", **kw))
    monkeypatch.setattr(losses.FrameFieldLoss, "__call__", real)
    resumed = train(_cfg(tmp_path, "part", resume=True, **kw))
    a = np.load(tmp_path / "full" / "frames.npz")["frames"]
    b = np.load(tmp_path / "part" / "frames.npz")["frames"]
    assert np.array_equal(a, b)
    assert full["loss_history"] == resumed["loss_history"] and full["final"] == resumed["final"]
    r = design(tio.cylinder(edge_length=0.6), steps=5, sh={"n_smooth_iters": 5}, starts=["sh"])
    assert np.array_equal(a, r.vertex_frames.numpy())
