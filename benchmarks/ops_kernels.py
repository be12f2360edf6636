"""Custom-op kernels of issue 11, compiled (C) against generic (torch), side by side.

    python -m benchmarks.ops_kernels [--n 55] [--threads 2] [--repeats 5] [--dtype float32]

Prints a markdown table. Rows (forward + backward of ``Σ out²``, float32 by default):

* ``face_curvature`` cut ``c`` and holonomy on ``io.box(n)`` (``6 n³`` tets; ``n = 55``: 998k
  tets, 2.0M faces, 1.19M edges), compiled ``csrc/curvature.c`` against the generic torch
  kernel (``torchconn.ops.compiled(False)``);
* ``face_torsion`` √R (``torchconn::face_torsion_sqrt``) on the same mesh;
* ``edge_terms``: ``torchconn::matched_edge_terms`` (the quality paths' angle + Dirichlet
  objective, ``csrc/edge_terms.c``) of a smooth vertex field on the same mesh's edges;
* ``so3.exp`` / ``log`` / ``sqrt`` on 10⁶ elements, compiled and generic, and
  ``torch.linalg.matrix_exp(hat(ω))`` (the ratio the issue asks to keep ≥ 5×);
* batched (B = 8) against a loop over the 8 (face curvature on ``io.box(n // 3)``);
* a Hessian-vector product against the first-order gradient (face curvature holonomy of
  ``so3.exp(ω)``, ``io.box(n // 3)``).

The mesh is built once (it takes ~25 s at ``n = 55``) and its tables saved to a temporary file.
Every cell runs in its **own subprocesses** (``--row``), which load the tables and build the
inputs. Time: one warm-up, then ``--repeats`` timed runs, median. Peak memory: another
subprocess with ``MALLOC_MMAP_THRESHOLD_=65536`` (glibc returns every freed block of 64 KB or
more to the OS, so the RSS follows the live tensors) runs the case once: its peak RSS is reset
just before (``/proc/self/clear_refs`` ← ``5``, Linux ≥ 4.0: ``VmHWM`` := ``VmRSS``) and read
after (``VmHWM`` in ``/proc/self/status``); ``peak MB`` is that peak minus the RSS before the
run, i.e. the extra memory of the op (autograd graph, outputs, gradients, temporaries), inputs
and tables excluded. ``resource.getrusage(...).ru_maxrss`` cannot be used for this: it is a
process-lifetime mark and, measured here, a child started by ``subprocess`` reported the
parent's high-water mark (the parent holds the 1M-tet mesh: 1464 MB in every row); it is
only the fallback where ``clear_refs`` cannot be written.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import torch

ROWS = ["curv_cut_c", "curv_holonomy", "torsion_sqrt", "edge_terms", "so3_exp", "so3_log", "so3_sqrt", "matrix_exp",
        "curv_batched8", "curv_loop8", "curv_first_order", "curv_hvp"]


class _Mesh:
    """Duck-typed tet mesh (what the ops read): ``kind``, ``edges``, ``face_edges``, ``vertices``."""

    kind = "tet"

    def __init__(self, d):
        self.edges, self.face_edges, self.vertices = d["edges"], d["face_edges"], d["vertices"]


def _save_mesh(n: int, path: str) -> dict:
    from torchconn import io

    m = io.box(n)
    torch.save({"edges": m.edges, "face_edges": m.face_edges, "vertices": m.vertices}, path)
    return {"tets": int(m.tets.shape[0]), "faces": int(m.face_edges.shape[0]), "edges": int(m.edges.shape[0])}


def _status_mb(key: str) -> float:
    """``VmRSS`` / ``VmHWM`` of this process from ``/proc/self/status``, in MB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"{key} not in /proc/self/status")


def _reset_peak() -> bool:
    """Reset this process's peak RSS (``VmHWM``) to its current RSS (Linux >= 4.0: ``clear_refs`` 5)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _row(name: str, mesh_path: str, small_path: str, compiled: bool, dtype: torch.dtype, repeats: int,
         memory: bool) -> dict:
    import torchconn.frames.kernels  # noqa: F401  (registers the frame kernels' C sources with ops.native)
    import torchconn.ops
    from torchconn import so3
    from torchconn.ops import curvature, native, torsion

    g = torch.Generator().manual_seed(0)
    if name.startswith("so3_") or name == "matrix_exp":
        N = 1_000_000
        w = (1.2 * torch.randn(N, 3, generator=g)).to(dtype)
        x = w if name in ("so3_exp", "matrix_exp") else so3.exp(w)
        fn = {"so3_exp": so3.exp, "so3_log": so3.log, "so3_sqrt": so3.sqrt,
              "matrix_exp": lambda v: torch.linalg.matrix_exp(so3.hat(v))}[name]
        x = x.requires_grad_()

        def run():
            fn(x).square().sum().backward()
            x.grad = None
    elif name == "edge_terms":
        from torchconn.frames import octahedral
        from torchconn.frames.kernels import edge_terms

        mesh = _Mesh(torch.load(mesh_path))
        V = mesh.vertices.shape[0]
        F0 = so3.exp(torch.randn(3, generator=g, dtype=torch.float64))
        F = (so3.exp(0.3 * torch.randn(V, 3, generator=g, dtype=torch.float64)) @ F0).to(dtype)
        idx, _ = octahedral.match_edges(F, mesh.edges)
        G = octahedral.group(dtype)
        F = F.requires_grad_()

        def run():
            edge_terms.matched_edge_terms(F, mesh.edges, idx, G, s_a=1e-6, s_d=1e-6).backward()
            F.grad = None
    elif name in ("curv_cut_c", "curv_holonomy", "torsion_sqrt"):
        mesh = _Mesh(torch.load(mesh_path))
        E = mesh.edges.shape[0]
        curvature._tables(mesh, "cpu")  # per-mesh tables (cached), outside the timed runs
        R = so3.exp(0.3 * torch.randn(E, 3, generator=g, dtype=dtype)).requires_grad_()
        if name == "torsion_sqrt":
            torsion._edge_vectors(mesh, "cpu", dtype)
            fn = lambda A: torsion.face_torsion(A, mesh)  # noqa: E731
        else:
            cut, kind = (-1, "two_prong") if name == "curv_cut_c" else (0, "holonomy")
            fn = lambda A: curvature.face_curvature(A, mesh, cut, kind)  # noqa: E731

        def run():
            fn(R).square().sum().backward()
            R.grad = None
    else:
        mesh = _Mesh(torch.load(small_path))
        E = mesh.edges.shape[0]
        curvature._tables(mesh, "cpu")
        w = (0.3 * torch.randn(8, E, 3, generator=g, dtype=dtype)).requires_grad_()
        if name == "curv_batched8":
            def run():
                curvature.face_curvature(so3.exp(w), mesh).square().sum().backward()
                w.grad = None
        elif name == "curv_loop8":
            def run():
                sum(curvature.face_curvature(so3.exp(w[i]), mesh).square().sum() for i in range(8)).backward()
                w.grad = None
        else:
            w1 = w[0].detach().requires_grad_()
            v = torch.randn(w1.shape, generator=g, dtype=dtype)
            f = lambda z: curvature.face_curvature(so3.exp(z), mesh, 0, "holonomy").square().sum()  # noqa: E731
            if name == "curv_first_order":
                def run():
                    torch.autograd.grad(f(w1), w1)
            else:
                def run():
                    torch.autograd.functional.hvp(f, w1, v)
    with torchconn.ops.compiled(compiled):
        if memory:  # one run, peak RSS around it (every block >= 64 KB mmapped: see _run_row)
            if compiled:
                native.library("curvature"), native.library("so3"), native.library("edge_terms"), native.library("torsion")  # outside the run
            rss0 = _status_mb("VmRSS")
            reset = _reset_peak()
            run()
            peak = _status_mb("VmHWM") if reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            return {"peak_mb": max(0.0, peak - rss0), "peak_reset": reset}
        run()  # warm-up (builds the C library on a cold cache)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            run()
            times.append(time.perf_counter() - t)
    return {"seconds": statistics.median(times)}


def _run_row(name, compiled, args, mesh_path, small_path) -> dict:
    """Time (one subprocess) and peak memory (another, with ``MALLOC_MMAP_THRESHOLD_=65536`` so
    that glibc returns every freed block of 64 KB or more to the OS and the RSS follows the live
    tensors; it slows allocation, hence not in the timed process)."""
    out = {}
    for memory in (False, True):
        cmd = [sys.executable, "-m", "benchmarks.ops_kernels", "--row", name, "--mesh-path", mesh_path,
               "--small-path", small_path, "--threads", str(args.threads), "--repeats", str(args.repeats),
               "--dtype", args.dtype] + (["--compiled"] if compiled else []) + (["--memory"] if memory else [])
        env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536") if memory else None
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if proc.returncode != 0:
            return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"}
        out.update(json.loads(proc.stdout.strip().splitlines()[-1]))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=55, help="io.box(n): 6 n^3 tets (55: ~1M)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--rows", default=",".join(ROWS), help="comma-separated subset of " + ",".join(ROWS))
    ap.add_argument("--row", help=argparse.SUPPRESS)
    ap.add_argument("--compiled", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--memory", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--mesh-path", help=argparse.SUPPRESS)
    ap.add_argument("--small-path", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    if args.row:
        print(json.dumps(_row(args.row, args.mesh_path, args.small_path, args.compiled, dtype, args.repeats,
                              args.memory)))
        return
    rows = [r for r in args.rows.split(",") if r]
    with tempfile.TemporaryDirectory() as tmp:
        mesh_path, small_path = os.path.join(tmp, "mesh.pt"), os.path.join(tmp, "small.pt")
        big = small = None
        if any(r.startswith(("curv_cut", "curv_hol", "torsion", "edge_terms")) for r in rows):
            t = time.perf_counter()
            big = _save_mesh(args.n, mesh_path)
            print(f"io.box({args.n}): {big['tets']} tets, {big['faces']} faces, {big['edges']} edges "
                  f"(built in {time.perf_counter() - t:.1f} s)", flush=True)
        if any(r.startswith(("curv_batched", "curv_loop", "curv_first", "curv_hvp")) for r in rows):
            small = _save_mesh(max(2, args.n // 3), small_path)
            print(f"io.box({max(2, args.n // 3)}): {small['tets']} tets (batched / HVP rows)", flush=True)
        print(f"\n{args.dtype}, torch.set_num_threads({args.threads}), median of {args.repeats} after 1 warm-up; "
              f"peak MB = VmHWM (reset) - VmRSS around one run; subprocesses per cell\n")
        print("| row | compiled s | generic s | generic / compiled | compiled peak MB | generic peak MB |")
        print("|---|---|---|---|---|---|")
        results = {}
        for r in rows:
            on = _run_row(r, True, args, mesh_path, small_path)
            # matrix_exp has no compiled kernel of ours: one measurement, both columns
            off = on if r == "matrix_exp" else _run_row(r, False, args, mesh_path, small_path)
            results[r] = (on, off)
            if "error" in on or "error" in off:
                print(f"| {r} | {on.get('error', '')} | {off.get('error', '')} | | | |", flush=True)
                continue
            print(f"| {r} | {on['seconds']:.4f} | {off['seconds']:.4f} | {off['seconds'] / on['seconds']:.2f} | "
                  f"{on['peak_mb']:.0f} | {off['peak_mb']:.0f} |", flush=True)
        ok = lambda k: k in results and "error" not in results[k][0]  # noqa: E731
        if ok("matrix_exp") and ok("so3_exp"):
            print(f"\nso3.exp (compiled) vs matrix_exp(hat(w)): "
                  f"{results['matrix_exp'][0]['seconds'] / results['so3_exp'][0]['seconds']:.1f}x")
        if ok("curv_batched8") and ok("curv_loop8"):
            print(f"batched B=8 vs loop of 8 (compiled): "
                  f"{results['curv_loop8'][0]['seconds'] / results['curv_batched8'][0]['seconds']:.2f}x")
        if ok("curv_hvp") and ok("curv_first_order"):
            print(f"HVP / first order (compiled): "
                  f"{results['curv_hvp'][0]['seconds'] / results['curv_first_order'][0]['seconds']:.2f}x")


if __name__ == "__main__":
    main()
