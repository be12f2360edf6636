"""The default frame-field loss (the one ``design()`` runs) in float32 and float64, side by side.

``python -m benchmarks.loss_dtypes [--tets N] [--threads T] [--repeats R] [--device D]`` times forward +
backward of :func:`benchmarks.run.loss_cases`' default loss on ``io.box`` with about ``N`` tets
(default 1M) in both dtypes in one process, without the eager reference (which
``benchmarks.run`` times too, and which needs more memory than a 24 GB machine has in float64 at
1M tets). Prints the median seconds and the process's peak RSS after each dtype; on CUDA the timer
synchronizes the device and the row adds the dtype's peak device memory.
"""
from __future__ import annotations

import argparse
import resource
import time

import torch


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tets", type=int, default=1_000_000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ...")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from torchconn import so3

    from .references import loss_cases
    from .run import _box

    device = torch.device(args.device)
    cuda = device.type == "cuda"

    def sync():
        if cuda:
            torch.cuda.synchronize(device)

    rows = []
    for dtype in (torch.float32, torch.float64):
        mesh = _box(args.tets, dtype).to(device)
        g = torch.Generator().manual_seed(2)
        w = (0.2 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=dtype)).to(device).requires_grad_()
        phi = (0.2 * torch.randn(mesh.vertices.shape[0], 3, generator=g, dtype=dtype)).to(device).requires_grad_()
        name, loss = loss_cases(mesh)[0]

        def step():
            w.grad = phi.grad = None
            loss(so3.exp(w), so3.exp(phi))["total"].backward()

        step()  # warm-up (kernel build, caches)
        sync()
        if cuda:
            torch.cuda.reset_peak_memory_stats(device)
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            step()
            sync()
            times.append(time.perf_counter() - t)
        row = {"row": name, "dtype": str(dtype).replace("torch.", ""), "device": str(device),
               "tets": int(mesh.tets.shape[0]), "median_s": sorted(times)[len(times) // 2],
               "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}
        if cuda:
            row["peak_device_gb"] = torch.cuda.max_memory_allocated(device) / 1e9
        rows.append(row)
        print(row, flush=True)
    print(f"float64 / float32: {rows[1]['median_s'] / rows[0]['median_s']:.2f}x")
    return rows


if __name__ == "__main__":
    main()
