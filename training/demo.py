"""A two-second tour: a random discrete connection on a built-in tet mesh, its curvature,
torsion, averaged d∇d∇θ and the Bianchi identities as invariants.

    python -m training.demo                      # built-in ball
    python -m training.demo mesh=torus seed=3 scale=0.1
    python -m training.demo mesh=../shared/data/sphere_r0.17.mesh
"""
from __future__ import annotations

import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from torchconn import io
from torchconn.dec.connection import Connection
from torchconn.nn import AveragedCovariantD, BianchiCheck, ConnectionField, Curvature, Torsion

from .config_check import DEMO, check_config

BUILTINS = {"ball": io.ball, "box": None, "cylinder": io.cylinder, "torus": io.torus}
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def load(cfg: DictConfig):
    """Built-in mesh by name, or any file ``torchconn.io.load_mesh`` reads."""
    if cfg.dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {sorted(DTYPES)}, got {cfg.dtype!r}")
    if cfg.mesh == "box":
        mesh = io.box(n=max(2, round(1.0 / cfg.edge_length)))
    elif cfg.mesh in BUILTINS:
        mesh = BUILTINS[cfg.mesh](edge_length=cfg.edge_length)
    else:
        mesh = io.load_mesh(Path(cfg.mesh), edge_length=cfg.edge_length)
    return mesh.to(device=cfg.device, dtype=DTYPES[cfg.dtype])


def run(cfg: DictConfig) -> dict:
    """Build everything, print a report, return the figures (a plain function for tests)."""
    t0 = time.perf_counter()
    check_config(cfg, DEMO, "configs/demo.yaml")  # typed, range-checked keys (ConfigError)
    mesh = load(cfg)
    gen = torch.Generator().manual_seed(int(cfg.seed))
    conn = Connection.random_on_mesh(mesh, generator=gen, scale=cfg.scale)
    field = ConnectionField.from_connection(conn)  # the design card's skew parametrization
    curv, tors, dd, check = Curvature(mesh), Torsion(mesh), AveragedCovariantD(mesh), BianchiCheck(mesh)
    omega = curv(field)
    theta = tors(field)
    ddtheta = dd(field)
    loss = omega.square().sum() + ddtheta.square().sum()
    loss.backward()  # differentiable end to end w.r.t. the skew parameters
    residuals = check(field)
    out = {
        "mesh": repr(mesh),
        "curvature_frobenius_mean": float(torch.linalg.matrix_norm(omega.detach()).mean()),
        "torsion_norm_mean": float(theta.detach().norm(dim=-1).mean()),
        "ddtheta_norm_mean": float(ddtheta.detach().norm(dim=-1).mean()),
        "grad_norm": float(field.params.grad.norm()),
        "bianchi_differential_max": residuals["differential"],
        "bianchi_algebraic_max": residuals["algebraic"],
        "seconds": time.perf_counter() - t0,
    }
    print(mesh)
    print(f"random connection: {conn}")
    for k, v in out.items():
        if k != "mesh":
            print(f"  {k:28s} {v:.3e}")
    return out


@hydra.main(config_path="../configs", config_name="demo", version_base="1.3")
def main(cfg: DictConfig) -> None:
    OmegaConf.set_struct(cfg, True)
    run(cfg)


if __name__ == "__main__":
    main()
