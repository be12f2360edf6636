"""Every script in examples/ runs as a user would run it and prints (or writes) what it promises
(one in a fresh process, ``python examples/x.py``; the others in this process as ``__main__``)."""
from __future__ import annotations

import contextlib
import io
import os
import re
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def _run_fresh(script: str, *args, cwd: Path) -> str:
    """``python examples/SCRIPT ARGS`` in ``cwd`` in a fresh process: its standard output."""
    # `python examples/x.py` puts examples/ first on sys.path; the checkout's torchconn comes next
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    proc = subprocess.run([sys.executable, str(EXAMPLES / script), *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def _run(script: str, *args, cwd: Path) -> str:
    """``python examples/SCRIPT ARGS`` in ``cwd``, run in this process (``runpy``, as ``__main__``,
    with ``examples/`` first on ``sys.path`` as ``python examples/x.py`` puts it; the global RNG
    state restored after): its standard output. A fresh process per example cost ~5 s on 2 loaded
    cores, mostly importing torch again."""
    saved_argv, saved_path, saved_cwd = sys.argv, list(sys.path), os.getcwd()
    buf = io.StringIO()
    try:
        sys.argv = [str(EXAMPLES / script), *map(str, args)]
        sys.path.insert(0, str(EXAMPLES))
        os.chdir(cwd)
        with torch.random.fork_rng(), contextlib.redirect_stdout(buf):
            runpy.run_path(str(EXAMPLES / script), run_name="__main__")
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path
        os.chdir(saved_cwd)
    return buf.getvalue()


def test_every_example_is_tested():
    tested = {"curvature_bianchi.py", "train_connection.py", "frames_to_paraview.py"}
    assert {p.name for p in EXAMPLES.glob("*.py")} == tested


def test_curvature_bianchi(tmp_path):
    out = _run_fresh("curvature_bianchi.py", cwd=tmp_path)  # the one example run in a fresh process
    assert "TetMesh(" in out and "mean |Ω|_F" in out
    (diff, alg), = re.findall(r"max differential residual (\S+), max algebraic residual (\S+)", out)
    assert float(diff) < 1e-12 and float(alg) < 1e-12  # float64 identities hold to round-off


def test_train_connection_decreases_the_loss(tmp_path):
    out = _run("train_connection.py", 40, cwd=tmp_path)
    losses = [float(x) for x in re.findall(r"loss (\S+)", out)]
    assert len(losses) == 5
    assert all(b < a for a, b in zip(losses, losses[1:])), losses
    assert losses[-1] < 0.2 * losses[0]
    assert "bianchi.check" in out


def test_frames_to_paraview_writes_a_vtu(tmp_path):
    meshio = pytest.importorskip("meshio")
    pytest.importorskip("igl")
    pytest.importorskip("pymeshlab")
    out = _run("frames_to_paraview.py", tmp_path / "out", cwd=tmp_path)
    assert "singular faces" in out
    mesh = meshio.read(tmp_path / "out" / "frames.vtu")
    n = mesh.points.shape[0]
    assert mesh.cells_dict["tetra"].shape[1] == 4
    axes = [mesh.point_data[f"axis{k}"] for k in range(3)]
    for a in axes:
        assert a.shape == (n, 3)
    # the three axes of every vertex form a rotation (orthonormal, right-handed)
    frames = np.stack(axes, -1)
    assert np.allclose(frames.transpose(0, 2, 1) @ frames, np.eye(3), atol=1e-6)
    assert np.allclose(np.linalg.det(frames), 1.0, atol=1e-6)
