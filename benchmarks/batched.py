"""Batched connections (issue 11): one call on ``(B, E, 3)`` skew parameters against a Python loop
over the ``B`` items, forward+backward, side by side in one run.

    python -m benchmarks.batched [--n 12] [--batch 8] [--threads 2] [--repeats 5]

For each device present (CPU; CUDA when available), float32 and float64, and each module
(``Curvature``, ``Torsion``, ``AveragedCovariantD``) on ``box(n)``: the loss
``Σ module(so3.exp(p))²`` backward to ``p``, with ``p`` of shape ``(B, E, 3)`` in one call
("batched") and item by item ("loop"). Prints a markdown table: best of ``repeats`` seconds and
``batched / loop`` (below 1: the batched call is faster).

Until the ops of :mod:`torchconn.ops` take leading batch dims themselves (issue 11, in progress), a
batched call runs the generic torch formula of :mod:`torchconn.dec` (see
:mod:`torchconn.dec._batch`) while the loop runs the fused op on every item.
"""
from __future__ import annotations

import argparse
import time

import torch

from torchconn.lie import so3
from torchconn.mesh import box
from torchconn.nn import AveragedCovariantD, Curvature, Torsion


def _best(fn, p, sync, repeats: int) -> float:
    fn()
    sync()
    ts = []
    for _ in range(repeats):
        p.grad = None
        sync()
        t = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t)
    return min(ts)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=12, help="box(n): 6 n^3 tets")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    mesh0 = box(args.n)
    B = args.batch
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"box({args.n}): E={mesh0.n_edges} F={mesh0.faces.shape[0]} T={mesh0.tets.shape[0]}, B={B}, "
          f"threads={torch.get_num_threads()}\n")
    print("| device | dtype | module | batched s | loop s | batched / loop |")
    print("| --- | --- | --- | --- | --- | --- |")
    rows = []
    for dev in devices:
        sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
        for dt in (torch.float32, torch.float64):
            mesh = mesh0.to(dev, dtype=dt)
            g = torch.Generator().manual_seed(0)
            p = (0.5 * torch.randn(B, mesh.n_edges, 3, generator=g, dtype=dt)).to(dev).requires_grad_()
            for name, mod in (("Curvature", Curvature(mesh)), ("Torsion", Torsion(mesh)),
                              ("AveragedCovariantD", AveragedCovariantD(mesh))):
                def batched():
                    mod(so3.exp(p)).square().sum().backward()

                def loop():
                    for b in range(B):
                        mod(so3.exp(p[b])).square().sum().backward()

                tb, tl = _best(batched, p, sync, args.repeats), _best(loop, p, sync, args.repeats)
                rows.append(dict(device=dev, dtype=str(dt), module=name, batched=tb, loop=tl))
                print(f"| {dev} | {str(dt)[6:]} | {name} | {tb:.4f} | {tl:.4f} | {tb / tl:.2f} |", flush=True)
    return rows


if __name__ == "__main__":
    main()
