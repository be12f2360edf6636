"""Shared pytest fixtures: the shared test-mesh folder and seeded generators."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# ../shared/data beside the repository (DEVELOPERS.md); overridable for other layouts.
DATA_DIR = Path(os.environ.get("TORCHCONN_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))

TET_MESHES = ["sphere_r0.17.mesh", "78322_gear.2.mesh", "dinosaur.msh"]
SURFACES = ["bunny.obj", "fandisk.ply", "rocker_arm.ply"]


def data_path(name: str) -> Path:
    """Path of a shared test mesh, or skip the test with a clear reason when it is absent."""
    p = DATA_DIR / name
    if not p.exists():
        pytest.skip(f"shared test mesh {name} not found in {DATA_DIR} (set TORCHCONN_DATA to its folder)")
    return p


@pytest.fixture
def gen() -> torch.Generator:
    """A CPU generator seeded identically for every test."""
    return torch.Generator().manual_seed(1234)
