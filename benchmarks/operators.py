"""Forward+backward time of curvature + averaged d∇ (issue: operators' performance note).

    python -m benchmarks.operators [--mesh PATH] [--repeats 5] [--dtype float32 float64]

Default mesh: the largest tet mesh of ../shared/data (dinosaur.msh, 49,973 tets) when present,
else a built-in box of 6·n³ tets. Each figure is the median over ``--repeats`` runs after one
warm-up; the loss is ``Σ‖Ω_f‖² + Σ‖d∇d∇θ_t‖²`` through a ``ConnectionField`` (skew params →
so3.exp), and backward reaches the skew parameters.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from torchconn import io
from torchconn.dec.connection import Connection
from torchconn.nn import ConnectionField
from torchconn.nn import AveragedCovariantD, Curvature

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def bench(mesh, dtype: torch.dtype, repeats: int) -> dict[str, float]:
    mesh = mesh.to(dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    field = ConnectionField.from_connection(Connection.random_on_mesh(mesh, generator=gen, scale=0.3))
    curv, dd = Curvature(mesh), AveragedCovariantD(mesh)

    def curvature_only():
        field.zero_grad()
        curv(field).square().sum().backward()

    def averaged_only():
        field.zero_grad()
        dd(field).square().sum().backward()

    def both():
        field.zero_grad()
        conn = field()
        (curv(conn).square().sum() + dd(conn).square().sum()).backward()

    return {
        "curvature": _time(curvature_only, repeats),
        "averaged_dnabla": _time(averaged_only, repeats),
        "curvature+averaged_dnabla": _time(both, repeats),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=None)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dtype", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    ap.add_argument("--box", type=int, default=20, help="box resolution when no mesh file is used")
    args = ap.parse_args(argv)
    path = args.mesh or (DATA / "dinosaur.msh" if (DATA / "dinosaur.msh").exists() else None)
    mesh = io.load_tet_mesh(path) if path else io.box(n=args.box)
    print(f"mesh: {path or f'box(n={args.box})'}: {mesh}; torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads")
    print("| dtype | curvature fwd+bwd (s) | averaged d∇ fwd+bwd (s) | both (s) |")
    print("|---|---|---|---|")
    for name in args.dtype:
        r = bench(mesh, getattr(torch, name), args.repeats)
        print(f"| {name} | {r['curvature']:.3f} | {r['averaged_dnabla']:.3f} | {r['curvature+averaged_dnabla']:.3f} |")


if __name__ == "__main__":
    main()
