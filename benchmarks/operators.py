"""Forward+backward time and peak memory of curvature + averaged d∇ (issue 11: operators' performance).

    python -m benchmarks.operators [--mesh PATH | --box N] [--repeats 3] [--dtype float32 float64]
                                   [--threads 2] [--rows pair tet_op ...] [--switch on off]

Default mesh: the largest tet mesh of ../shared/data (dinosaur.msh, 49,973 tets) when present,
else a built-in box of 6·n³ tets (``--box 55``: 998,250 tets, the issue's 1M-tet figure).
Every (row, dtype, switch) runs in its own subprocess, so that its peak resident memory can be
read: after one warm-up call, freed memory is returned to the OS (``malloc_trim``), the
resident size is taken as the baseline, the peak counter is reset (``/proc/self/clear_refs``)
and the timed calls run; "peak +GB" is the peak resident size during the timed calls minus the
baseline (mesh, tables and parameters excluded), "RSS GB" the absolute peak. Each time is the
median (and the best) over ``--repeats`` calls (on a shared machine the best is
the steadier figure; "CPU (s)" is the least process CPU time of a call, all threads
together, which a loaded machine inflates less than wall time). ``on`` = compiled C kernels where an op has one, ``off`` = the
generic torch kernels (``torchconn.ops.compiled(False)``), side by side.

Rows (loss = sum of squares, backward to the skew parameters of a ``ConnectionField``):

* ``curvature``: ``Curvature(mesh)``; ``averaged_dnabla``: ``AveragedCovariantD(mesh)``: the
  modules' tensor outputs, squared and summed in torch;
* ``pair``: both on one connection (the design card's modules) as a loss computes them, through
  the modules' ``sqnorm`` (``Curvature.sqnorm`` + ``AveragedCovariantD.sqnorm``: the value and
  the gradient of each in one fused sweep, no ``(F, 3, 3)`` / ``(T, 3)`` tensors; issue 30);
  ``pair_tensors``: the same loss from the modules' tensor outputs (``C.square().sum() +
  D.square().sum()``), beside it;
* ``tet_op``: the op ``torchconn::tet_dd`` alone on given ``R (E,3,3)`` and ``θ̃ (E,2,3)``
  (both requiring grad): the tet kernel's own figure;
* ``tet_b8`` / ``tet_loop8``: ``ops.tet_solder.tet_dd_solder`` on a batch of 8 connections ``(8, E, 3, 3)``
  against a Python loop over the 8 (use a smaller ``--box``);
* ``tet_hvp`` / ``tet_grad``: a Hessian-vector product of the averaged-d∇ loss
  (``torch.autograd.functional.hvp``) against its first-order gradient.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
ROWS = ("curvature", "averaged_dnabla", "pair", "pair_tensors", "tet_op", "tet_b8", "tet_loop8", "tet_hvp", "tet_grad")


def _status(key: str) -> float:
    """``VmRSS`` / ``VmHWM`` of this process in GB (Linux)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 2**20
    return float("nan")


def _trim() -> None:
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _load(args):
    from torchconn import io
    path = args.mesh or (DATA / "dinosaur.msh" if (args.box is None and (DATA / "dinosaur.msh").exists()) else None)
    mesh = io.load_tet_mesh(path) if path else io.box(n=args.box or 20)
    return mesh, (str(path) if path else f"box(n={args.box or 20})")


def _make(row: str, mesh, dtype: torch.dtype):
    """The timed callable of ``row`` (setup done here, outside the measurement)."""
    from torchconn.dec.connection import Connection
    from torchconn.lie import so3
    from torchconn.nn import AveragedCovariantD, ConnectionField, Curvature
    from torchconn.ops import tet, tet_solder

    gen = torch.Generator().manual_seed(0)
    field = ConnectionField.from_connection(Connection.random_on_mesh(mesh, generator=gen, scale=0.3))
    curv, dd = Curvature(mesh), AveragedCovariantD(mesh)
    E = mesh.edges.shape[0]
    if row == "curvature":
        def fn():
            field.zero_grad()
            curv(field).square().sum().backward()
    elif row == "averaged_dnabla":
        def fn():
            field.zero_grad()
            dd(field).square().sum().backward()
    elif row == "pair":
        def fn():
            field.zero_grad()
            conn = field()
            (curv.sqnorm(conn) + dd.sqnorm(conn)).backward()
    elif row == "pair_tensors":
        def fn():
            field.zero_grad()
            conn = field()
            (curv(conn).square().sum() + dd(conn).square().sum()).backward()
    elif row == "tet_op":
        k = tet.tet_kernel(mesh)
        R = so3.exp(0.3 * torch.randn(E, 3, generator=gen, dtype=dtype)).requires_grad_()
        th = torch.randn(E, 2, 3, generator=gen, dtype=dtype).requires_grad_()

        def fn():
            R.grad = th.grad = None
            tet.tet_dd(R, th, k).square().sum().backward()
    elif row in ("tet_b8", "tet_loop8"):
        w = (0.3 * torch.randn(8, E, 3, generator=gen, dtype=dtype)).requires_grad_()
        if row == "tet_b8":
            def fn():
                w.grad = None
                tet_solder.tet_dd_solder(so3.exp(w), mesh).square().sum().backward()
        else:
            def fn():
                w.grad = None
                for i in range(8):
                    tet_solder.tet_dd_solder(so3.exp(w[i]), mesh).square().sum().backward()
    elif row in ("tet_hvp", "tet_grad"):
        w0 = 0.3 * torch.randn(E, 3, generator=gen, dtype=dtype)
        v = torch.randn(E, 3, generator=gen, dtype=dtype)
        loss = lambda p: tet_solder.tet_dd_solder(so3.exp(p), mesh).square().sum()  # noqa: E731
        if row == "tet_hvp":
            def fn():
                torch.autograd.functional.hvp(loss, w0, v)
        else:
            def fn():
                torch.autograd.grad(loss(w0.requires_grad_()), w0)
    else:
        raise ValueError(row)
    return fn


def _child(args) -> None:
    torch.set_num_threads(args.threads)
    from torchconn.ops import compiled
    mesh, _ = _load(args)
    dtype = getattr(torch, args.dtype[0])
    mesh = mesh.to(dtype=dtype)
    with compiled(args.switch[0] == "on"):
        fn = _make(args.rows[0], mesh, dtype)
        fn()  # warm-up (builds the per-mesh tables and the C libraries)
        _trim()
        base = _status("VmRSS")
        _reset_peak()
        ts, cpu = [], []
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            ts.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        peak = _status("VmHWM")
    print(json.dumps({"time": statistics.median(ts), "best": min(ts), "cpu": min(cpu), "peak_extra": peak - base, "rss": peak}))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=None)
    ap.add_argument("--box", type=int, default=None, help="box resolution n (6·n³ tets) instead of a mesh file")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--dtype", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    ap.add_argument("--rows", nargs="+", default=["curvature", "averaged_dnabla", "pair", "pair_tensors", "tet_op"], choices=ROWS)
    ap.add_argument("--switch", nargs="+", default=["on", "off"], choices=["on", "off"])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child(args)
    mesh, name = _load(args)
    print(f"mesh: {name}: {mesh.tets.shape[0]} tets, {mesh.edges.shape[0]} edges; torch {torch.__version__}, "
          f"{args.threads} threads; median of {args.repeats}")
    print("| row | dtype | kernels | median (s) | best (s) | CPU (s) | peak +GB | RSS GB |")
    print("|---|---|---|---|---|---|---|---|")
    base = [sys.executable, "-m", "benchmarks.operators", "--child", "--repeats", str(args.repeats),
            "--threads", str(args.threads)]
    base += ["--mesh", str(args.mesh)] if args.mesh else (["--box", str(args.box)] if args.box else [])
    for dt in args.dtype:
        for row in args.rows:
            for sw in args.switch:
                proc = subprocess.run(base + ["--dtype", dt, "--rows", row, "--switch", sw],
                                      capture_output=True, text=True)
                if proc.returncode != 0:
                    print(f"| {row} | {dt} | {sw} | failed: {proc.stderr.strip().splitlines()[-1:]} | | | | |")
                    continue
                r = json.loads(proc.stdout.strip().splitlines()[-1])
                kern = "C" if sw == "on" else "generic"
                print(f"| {row} | {dt} | {kern} | {r['time']:.3f} | {r['best']:.3f} | {r['cpu']:.3f} | {r['peak_extra']:.3f} | "
                      f"{r['rss']:.3f} |",
                      flush=True)


if __name__ == "__main__":
    main()
