"""A training step with the default threads while another process holds a core (issue 24).

    python -m benchmarks.under_load [--steps 400] [--edge-length 0.25] [--spinner pinned free]
                                    [--wait-policy default passive] [--output-dir DIR]

The step: an MLP maps per-edge features (midpoint, direction) of a built-in mesh
(``torchconn.ball(1.0, edge_length)``) to skew parameters ``ω (E, 3)``; the loss is
``Σ‖Ω_f‖² + Σ‖d∇d∇θ̃_t‖²`` through the modules ``Curvature`` and ``AveragedCovariantD`` of
``R = so3.exp(ω)``; backward and an Adam step (``train_step``). The same MLP with the loss
``Σ‖ω‖²`` and no torchconn op (``torch_only_step``) shows what torch's own operations do.

Side by side in one process: blocks of ``--steps / --rounds`` steps alternate between one thread
and ``--threads`` (default: torch's default, the number of cores), first with nothing else
started (``unloaded``), then while a spinner process (a Python busy loop) holds a core: pinned to
the last CPU (``pinned``) or placed by the OS (``free``). Each row: the median ms/step of each
setting over its blocks, their ratio (``threads`` / one thread; issue 24's target with the
spinner: <= 1.5) and ``/proc/loadavg`` when the row started.

``--wait-policy``: each value runs the rows in a fresh child process with GNU OpenMP's
``OMP_WAIT_POLICY`` unset and torch imported first (``default``: torch's OpenMP threads spin at
every barrier and between parallel regions, up to ~300k iterations), unset and ``import
torchconn`` first (``torchconn-first``: torchconn sets ``PASSIVE`` before it loads torch, see
``torchconn/__init__.py``) or ``PASSIVE`` (they sleep at once). The variable is
read once, when torch loads its OpenMP runtime, so it cannot be changed from inside a process
that imported torch. torchconn's compiled kernels do not use OpenMP (their pool, ``csrc/pool.c``,
sleeps after a 20 us spin either way); torch's own parallel operations do.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
_SPIN = "import os, sys\ncpu = int(sys.argv[1])\nif cpu >= 0:\n    os.sched_setaffinity(0, {cpu})\nwhile True:\n    pass\n"
POLICIES = {"default": None, "torchconn-first": None, "passive": "PASSIVE"}
# the child imports torchconn before torch: torchconn sets OMP_WAIT_POLICY=PASSIVE when unset
_CHILD_TORCHCONN_FIRST = "import sys, torchconn; from benchmarks.under_load import main; main(sys.argv[1:])"


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


class Spinner:
    """A child process in a busy loop, pinned to CPU ``cpu`` (or placed by the OS: ``cpu = -1``)."""

    def __init__(self, cpu: int):
        self.cpu = cpu

    def __enter__(self):
        self.proc = subprocess.Popen([sys.executable, "-c", _SPIN, str(self.cpu)])
        time.sleep(0.5)  # let it start spinning
        return self

    def __exit__(self, *exc):
        self.proc.terminate()
        self.proc.wait()


def make_step(edge_length: float, torch_only: bool = False, hidden: int = 64, seed: int = 0):
    """The training step (a closure) on ``torchconn.ball(1.0, edge_length)``: ``(step, n_tets)``."""
    import torchconn as tc
    from torchconn import so3

    torch.manual_seed(seed)
    mesh = tc.ball(radius=1.0, edge_length=edge_length)
    V, e = mesh.vertices.to(torch.float32), mesh.edges
    feat = torch.cat([0.5 * (V[e[:, 0]] + V[e[:, 1]]), V[e[:, 1]] - V[e[:, 0]]], dim=1)
    mlp = torch.nn.Sequential(torch.nn.Linear(6, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, hidden),
                              torch.nn.Tanh(), torch.nn.Linear(hidden, 3))
    curv, dd = tc.Curvature(mesh), tc.AveragedCovariantD(mesh)
    opt = torch.optim.Adam(mlp.parameters(), lr=1e-3)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        w = mlp(feat)
        if torch_only:
            loss = w.square().sum()
        else:
            R = so3.exp(w)
            loss = curv(R).square().sum() + dd(R).square().sum()
        loss.backward()
        opt.step()

    return step, int(mesh.tets.shape[0])


def side_by_side(step, steps: int, rounds: int, threads: int) -> dict:
    """Median ms/step of one thread and of ``threads``, alternating blocks of ``steps // rounds``."""
    block = max(1, steps // rounds)
    times: dict[int, list[float]] = {1: [], threads: []}
    prev = torch.get_num_threads()
    try:
        for nt in (1, threads):  # warm-up of both settings
            torch.set_num_threads(nt)
            for _ in range(3):
                step()
        for _ in range(rounds):
            for nt in (1, threads):
                torch.set_num_threads(nt)
                t0 = time.perf_counter()
                for _ in range(block):
                    step()
                times[nt].append((time.perf_counter() - t0) / block * 1e3)
    finally:
        torch.set_num_threads(prev)
    one, many = statistics.median(times[1]), statistics.median(times[threads])
    return {"ms_1_thread": one, "ms_threads": many, "ratio": many / one,
            "blocks_1_thread": times[1], "blocks_threads": times[threads]}


def bench(steps: int = 400, rounds: int = 4, edge_length: float = 0.25, threads: int | None = None,
          spinners: tuple[str, ...] = ("pinned",), unloaded: bool = True, torch_only: bool = True,
          label: str | None = None) -> list[dict]:
    """Rows ``{name, tets, threads, ms_1_thread, ms_threads, ratio, loadavg, wait_policy, ...}``
    in this process (see the module doc)."""
    threads = threads or torch.get_num_threads()
    ncpu = os.cpu_count() or 1
    policy = os.environ.get("OMP_WAIT_POLICY", "") or "default (unset)"
    if label == "torchconn-first":
        policy = f"{policy} (import torchconn first)"
    rows = []
    kinds = [("train_step", False)] + ([("torch_only_step", True)] if torch_only else [])
    for kind, only in kinds:
        step, T = make_step(edge_length, torch_only=only)
        for case in (["unloaded"] if unloaded else []) + list(spinners):
            load = _loadavg()
            if case == "unloaded":
                res = side_by_side(step, steps, rounds, threads)
            else:
                with Spinner(ncpu - 1 if case == "pinned" else -1):
                    res = side_by_side(step, steps, rounds, threads)
            name = f"{kind}({case if case == 'unloaded' else 'spinner ' + case})"
            row = {"name": name, "tets": T, "threads": threads, "steps": steps, "rounds": rounds,
                   "wait_policy": policy, "loadavg": load, **res}
            rows.append(row)
            print(f"{name:34s} OMP_WAIT_POLICY {policy:15s} {T} tets: 1 thread {res['ms_1_thread']:7.2f} ms, "
                  f"{threads} threads {res['ms_threads']:7.2f} ms, ratio {res['ratio']:5.2f} (loadavg {load})",
                  flush=True)
    return rows


def bench_policies(policies: tuple[str, ...] = ("default", "torchconn-first", "passive"), **kw) -> list[dict]:
    """:func:`bench` in a fresh child process per OpenMP wait policy (set before torch loads)."""
    rows = []
    for pol in policies:
        env = dict(os.environ)
        env.pop("OMP_WAIT_POLICY", None)
        if POLICIES[pol]:
            env["OMP_WAIT_POLICY"] = POLICIES[pol]
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "rows.json"
            head = ["-c", _CHILD_TORCHCONN_FIRST] if pol == "torchconn-first" else ["-m", "benchmarks.under_load"]
            cmd = [sys.executable, *head, "--child", str(out), "--label", pol,
                   "--steps", str(kw.get("steps", 400)), "--rounds", str(kw.get("rounds", 4)),
                   "--edge-length", str(kw.get("edge_length", 0.25)), "--spinner", *kw.get("spinners", ("pinned",))]
            if kw.get("threads"):
                cmd += ["--threads", str(kw["threads"])]
            if not kw.get("unloaded", True):
                cmd.append("--no-unloaded")
            if not kw.get("torch_only", True):
                cmd.append("--no-torch-only")
            subprocess.run(cmd, env=env, cwd=ROOT, check=True)
            rows += json.loads(out.read_text())
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=400, help="steps per setting and row")
    ap.add_argument("--rounds", type=int, default=4, help="alternating blocks per setting")
    ap.add_argument("--edge-length", type=float, default=0.25, help="torchconn.ball edge length")
    ap.add_argument("--threads", type=int, default=None, help="the default setting (default: torch's)")
    ap.add_argument("--spinner", nargs="+", default=["pinned"], choices=["pinned", "free"])
    ap.add_argument("--wait-policy", nargs="+", default=list(POLICIES), choices=list(POLICIES))
    ap.add_argument("--no-unloaded", action="store_true", help="skip the rows without a spinner")
    ap.add_argument("--no-torch-only", action="store_true", help="skip the torch-only step")
    ap.add_argument("--output-dir", type=Path, default=None, help="write under_load.json there")
    ap.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)  # rows of this process -> file
    ap.add_argument("--label", default=None, help=argparse.SUPPRESS)  # the child's policy name
    args = ap.parse_args(argv)
    kw = dict(steps=args.steps, rounds=args.rounds, edge_length=args.edge_length, threads=args.threads,
              spinners=tuple(args.spinner), unloaded=not args.no_unloaded, torch_only=not args.no_torch_only)
    if args.child is not None:
        rows = bench(**kw, label=args.label)
        args.child.write_text(json.dumps(rows))
        return rows
    rows = bench_policies(tuple(args.wait_policy), **kw)
    if args.output_dir is not None:
        args.output_dir.mkdir(parents=True, exist_ok=True)
        (args.output_dir / "under_load.json").write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
