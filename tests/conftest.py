"""Shared pytest fixtures: the shared test-mesh folder and seeded generators."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# ../shared/data beside the repository (DEVELOPERS.md); overridable for other layouts.
DATA_DIR = Path(os.environ.get("TORCHCONN_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))



def assert_hvp_matches_fd(f, w: torch.Tensor, v: torch.Tensor, h: float = 1e-5, tol: float = 1e-6) -> None:
    """The Hessian-vector product of the scalar ``f`` at ``w`` along ``v`` (double backward) equals the
    central difference of its gradient, ``(grad f(w + h v) - grad f(w - h v)) / 2h``."""
    def grad(z):
        z = z.clone().requires_grad_()
        return torch.autograd.grad(f(z), z)[0]

    _, hv = torch.autograd.functional.hvp(f, w, v)
    fd = (grad(w + h * v) - grad(w - h * v)) / (2 * h)
    torch.testing.assert_close(hv, fd, atol=tol, rtol=tol)


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


def _device_params() -> list:
    """CPU always; CUDA when present, else a skipped case that says why (never silently absent)."""
    params = [pytest.param("cpu", id="cpu")]
    if torch.cuda.is_available():
        params.append(pytest.param("cuda", id="cuda"))
    else:
        params.append(pytest.param("cuda", id="cuda", marks=pytest.mark.skip(
            reason="no CUDA device on this machine (torch.cuda.is_available() is False)")))
    return params


DEVICES = _device_params()


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Every device present: ``cpu``, and ``cuda`` when available (skipped with a reason otherwise)."""
    return torch.device(request.param)
