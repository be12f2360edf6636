"""The installable product: the wheel holds ``torchconn`` only, with the jobs, their configs and the C sources.

The fast test builds the wheel offline (``pip wheel --no-build-isolation``, from a copy of the
sources so the checkout gets no ``build/``) and inspects it; the slow one installs it into a fresh
virtual environment and runs the console scripts from an unrelated directory.
"""
from __future__ import annotations

import configparser
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "torchconn", "training", "configs")
SCRIPTS = {
    "torchconn-frames": "torchconn.training.train_frames:main",
    "torchconn-hex": "torchconn.training.hex_mesh:main",
    "torchconn-convergence": "torchconn.training.convergence:main",
    "torchconn-demo": "torchconn.training.demo:main",
}

pytest.importorskip("setuptools", reason="building the wheel needs setuptools (part of the test extra)")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build")
    for name in SOURCES:
        p = ROOT / name
        (shutil.copytree(p, src / name, ignore=ignore) if p.is_dir() else shutil.copy2(p, src / name))
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "--no-index",
         "-q", "-w", str(tmp / "dist")],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (whl,) = (tmp / "dist").glob("torchconn-*.whl")
    return whl


@pytest.fixture(scope="module")
def names(wheel) -> set[str]:
    with zipfile.ZipFile(wheel) as z:
        return set(z.namelist())


def _dist_info(names: set[str], file: str) -> str:
    (path,) = [n for n in names if n.endswith(f".dist-info/{file}")]
    return path


def test_only_torchconn_is_a_top_level_package(wheel, names):
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"torchconn"}
    for other in ("training", "configs", "benchmarks", "studies", "tests", "docs", "examples"):
        assert not any(n.startswith(f"{other}/") for n in names), other
    with zipfile.ZipFile(wheel) as z:
        assert z.read(_dist_info(names, "top_level.txt")).decode().split() == ["torchconn"]


def test_configs_jobs_and_c_sources_are_inside(names):
    configs = sorted(p.relative_to(ROOT / "configs").as_posix() for p in (ROOT / "configs").rglob("*.yaml"))
    for required in ("train_frames.yaml", "convergence.yaml", "demo.yaml", "experiment/quick.yaml"):
        assert required in configs
    for cfg in configs:
        assert f"torchconn/configs/{cfg}" in names, cfg
    assert "torchconn/configs/__init__.py" in names  # Hydra's pkg:// search path imports it
    for job in sorted((ROOT / "training").glob("*.py")):
        assert f"torchconn/training/{job.name}" in names, job.name
    for c in sorted((ROOT / "torchconn" / "ops" / "csrc").glob("*.c")):
        assert f"torchconn/ops/csrc/{c.name}" in names, c.name


def test_every_package_of_the_tree_is_in_the_wheel(names):
    """pyproject.toml lists the packages by hand (package-dir remaps training/ and configs/)."""
    for module in sorted((ROOT / "torchconn").rglob("*.py")):
        rel = module.relative_to(ROOT).as_posix()
        assert rel in names, f"{rel} is missing from the wheel: list its package in pyproject.toml"


def test_console_scripts(wheel, names):
    with zipfile.ZipFile(wheel) as z:
        text = z.read(_dist_info(names, "entry_points.txt")).decode()
    entry_points = configparser.ConfigParser()
    entry_points.read_string(text)
    assert dict(entry_points["console_scripts"]) == SCRIPTS


def test_mesh_io_dependencies_are_an_extra(wheel, names):
    with zipfile.ZipFile(wheel) as z:
        meta = z.read(_dist_info(names, "METADATA")).decode()
    requires = [l.split(":", 1)[1].strip() for l in meta.splitlines() if l.startswith("Requires-Dist:")]
    core = [r for r in requires if "extra ==" not in r]
    for dep in ("libigl", "pymeshlab", "meshio", "hydra-core", "matplotlib", "pytest"):
        assert not any(r.startswith(dep) for r in core), (dep, core)
        assert any(r.startswith(dep) or "torchconn[" in r for r in requires), dep
    assert any(r.startswith("torch") for r in core)


@pytest.mark.slow
def test_installed_wheel_runs_its_commands_outside_the_checkout(wheel, tmp_path):
    """Install into a fresh venv (system site-packages for torch & co.) and run the jobs from /tmp."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True, timeout=300)
    bindir = venv / ("Scripts" if os.name == "nt" else "bin")
    py = bindir / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
                   check=True, timeout=600)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}

    def run(*cmd):
        proc = subprocess.run([str(c) for c in cmd], cwd=work, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        return proc.stdout

    where = run(py, "-c", "import torchconn, torchconn.training.convergence as c; print(torchconn.__file__); "
                          "print(c.__file__)")
    assert all(line.startswith(str(venv)) for line in where.split()), where
    demo = run(bindir / "torchconn-demo", "mesh=box", "edge_length=0.5")
    assert "bianchi_differential_max" in demo
    run(bindir / "torchconn-convergence", "experiment=quick", "plots=false", f"output_dir={work / 'conv'}")
    assert (work / "conv" / "slopes.csv").is_file() and (work / "conv" / "summary.md").is_file()
    frames = run(bindir / "torchconn-frames", "mesh=box", "steps=2", f"output_dir={work / 'frames'}")
    assert "[train_frames]" in frames and (work / "frames" / "metrics.json").is_file()
    hexes = run(bindir / "torchconn-hex", "mesh=box", "edge_length=0.5", "method=sh_baseline", "hex.edge_length=0.25",
                "progress=false", f"output_dir={work / 'hex'}")
    assert "[hex_mesh] map valid" in hexes and (work / "hex" / "hex_metrics.json").is_file()
