"""The hex job (training/hex_mesh.py, torchconn-hex): outputs, an invalid map as a result, bad input."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch

from torchconn import so3
from torchconn.hexmesh import read_hex_mesh, read_hexex
from training import config_check
from training.hex_mesh import FramesFileError, run

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_hexmesh_map import axis_prism  # noqa: E402

BOX = {"mesh": "box", "edge_length": 0.5, "method": "sh_baseline", "progress": False, "hex": {"edge_length": 0.25}}


def _cfg(out, **kw):
    cfg = {**BOX, "output_dir": str(out)}
    for k, v in kw.items():
        if k == "hex":
            cfg["hex"] = {**cfg["hex"], **v}
        else:
            cfg[k] = v
    return cfg


def test_box_writes_every_output_and_a_good_grid(tmp_path):
    m = run(_cfg(tmp_path))
    assert m["map"]["valid"] and m["good"] and m["quality"]["n_hexes"] == 64
    for name in ("igm.hexex", "hex.vtu", "hex.mesh", "hex_metrics.json", "hex.png", "frames.npz"):
        assert (tmp_path / name).is_file() and (tmp_path / name).stat().st_size > 0, name
    saved = json.loads((tmp_path / "hex_metrics.json").read_text())
    assert saved["map"]["valid"] and saved["quality"]["sj_min"] == pytest.approx(1.0)
    # the .hexex holds the map of the tet mesh with the input's own vertices first
    V, T, U = read_hexex(tmp_path / "igm.hexex")
    z = np.load(tmp_path / "frames.npz")
    assert np.array_equal(V[: z["vertices"].shape[0]], z["vertices"]) and U.shape == (T.shape[0], 4, 3)
    P, H = read_hex_mesh(tmp_path / "hex.vtu")
    assert H.shape == (64, 8)
    vtu = meshio.read(tmp_path / "hex.vtu")
    assert vtu.cells[0].type == "hexahedron"
    # frames=PATH reuses the field: the same map
    out2 = tmp_path / "again"
    m2 = run(_cfg(out2, frames=str(tmp_path / "frames.npz")))
    assert m2["field"]["source"].endswith("frames.npz") and not (out2 / "frames.npz").exists()
    assert np.array_equal(read_hexex(out2 / "igm.hexex")[2], U)


def test_invalid_map_is_a_result_not_an_error(tmp_path):
    mesh = axis_prism()
    bc = mesh.tet_barycenters
    phi = torch.atan2(bc[:, 1], bc[:, 0])
    axis = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64) / math.sqrt(3)
    F = so3.exp((phi / 3)[:, None] * axis)  # a complex singularity along the axis
    meshio.write(tmp_path / "prism.mesh", meshio.Mesh(mesh.vertices.numpy(), [("tetra", mesh.tets.numpy())]))
    np.savez(tmp_path / "f.npz", vertices=mesh.vertices.numpy(), tets=mesh.tets.numpy(), frames=F.numpy())
    out = tmp_path / "out"
    m = run(_cfg(out, mesh=str(tmp_path / "prism.mesh"), frames=str(tmp_path / "f.npz"), hex={"edge_length": 0.2}))
    assert not m["map"]["valid"] and not m["good"]
    assert any("complex" in r for r in m["map"]["reasons"])
    assert (out / "igm.hexex").is_file() and (out / "hex_metrics.json").is_file()


@pytest.mark.parametrize("case", ["other_mesh", "not_npz", "no_frames_key"])
def test_bad_frames_file_fails_clearly_and_writes_nothing(tmp_path, case):
    path = tmp_path / "f.npz"
    if case == "other_mesh":
        np.savez(path, vertices=np.zeros((5, 3)), tets=np.zeros((1, 4), np.int64), frames=np.tile(np.eye(3), (5, 1, 1)))
        match = "another mesh"
    elif case == "not_npz":
        path.write_text("not a zip")
        match = "not a readable"
    else:
        np.savez(path, something=np.zeros(3))
        match = "no 'frames'"
    out = tmp_path / "out"
    with pytest.raises(FramesFileError, match=match):
        run(_cfg(out, frames=str(path)))
    written = sorted(p.name for p in out.glob("*")) if out.exists() else []
    assert not [n for n in written if n.endswith((".hexex", ".vtu", ".mesh", ".json", ".png", ".npz"))], written


@pytest.mark.parametrize("override,match", [({"hex": {"edge_length": -1.0}}, "hex.edge_length"),
                                            ({"hex": {"stiffening_factor": 0.5}}, "hex.stiffening_factor"),
                                            ({"method": "nope"}, "method")])
def test_bad_config_values_fail_before_anything_runs(tmp_path, override, match):
    with pytest.raises(config_check.ConfigError, match=match):
        run(_cfg(tmp_path / "out", **override))
    assert not (tmp_path / "out" / "hex_metrics.json").exists()


def test_unknown_key_fails(tmp_path):
    from omegaconf.errors import ConfigKeyError

    with pytest.raises(ConfigKeyError):
        run(_cfg(tmp_path / "out", hex={"edge_lenght": 0.3}))


def test_console_command(tmp_path):
    r = subprocess.run([sys.executable, "-m", "training.hex_mesh", "mesh=box", "edge_length=0.5", "method=sh_baseline",
                        "hex.edge_length=0.25", "progress=false", f"output_dir={tmp_path}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "[hex_mesh] map valid; 64 hexes" in r.stdout and "good hex mesh: True" in r.stdout


def test_schema_lists_exactly_the_keys_of_the_config_files():
    import yaml

    def keys(name):
        raw = yaml.safe_load((ROOT / "configs" / name).read_text())
        raw.pop("hydra", None)
        raw.pop("defaults", None)
        return set(config_check._flatten(raw))

    assert keys("train_frames.yaml") | keys("hex_mesh.yaml") == set(config_check.HEX_MESH)
