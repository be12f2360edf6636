"""How the map stage scales: per-step time and peak memory on growing meshes, and the hex stage per model.

    python -m benchmarks.hex_stage_scale scale [--model i02c_m2] [--lmax 0.5,0.3,0.2,0.14]
        [--field sh|connection] [--variant NAME=PATH ...] [--threads 1] [--timeout 1800] [--out DIR]
    python -m benchmarks.hex_stage_scale models [--models s,n,i|s02c,...] [--field sh|connection]
        [--variant NAME=PATH ...] [--threads 1] [--timeout 1800] [--out DIR]

``scale``: one HexMe model (``--model``) meshed at several ``Mesh.CharacteristicLengthMax`` values
(``--lmax``; ``i02c_m2`` at 0.14 is about a million tets), the map stage
(:func:`torchconn.hexmesh.integer_grid_map`) of each, with every step's wall time and the peak
resident memory of the process during that step. ``models``: the whole hex stage
(:func:`torchconn.hexmesh.hex_mesh`: map, extraction, untangling, quality) of each HexMe ``c``
model (``--models`` prefixes, default all 35): its time per step, its peak memory, its verdict.

Fields (``--field``): ``sh`` (default), :func:`torchconn.frames.design` ``"sh_baseline"``, computed
once per mesh and cached in ``DIR/fields/`` so every variant sees the same frames; ``connection``:
the cached per-vertex frames ``/work/dev/cache/<model>__connection.npy`` (``--cache``) where one
exists for the model's default mesh (a model without one is a row with that error).

Variants (``--variant NAME=PATH``, repeatable; default ``after=<this checkout>``): the package
imported from ``PATH`` (a checkout or an exported revision: ``git worktree add /tmp/before REV``),
so a before/after comparison runs in one invocation on the same machine, the variants of one case
one after the other. Every run is a child process (``--threads`` for torch, OpenMP, BLAS; the
results in docs/results/ use 1): its peak memory is sampled from ``/proc/self/statm`` every 10 ms
by a thread (numpy, scipy and CHOLMOD allocate outside Python, so ``tracemalloc`` does not see
them) and attributed to the step running at that moment (the steps' own ``stats["timings"]``,
which follow one another), as is its CPU time (``<step>_cpu``: on a shared machine the wall
time grows with the load, the CPU time much less); ``peak_mb`` is the process's ``getrusage``
maximum resident size. A run
past ``--timeout`` is a row with that error. The time to mesh the model and to compute its field
is not counted. The HexMe files are read from ``../shared/data`` beside this checkout (or
``$TORCHCONN_DATA``).

Output: ``DIR/scale.csv`` / ``DIR/models.csv`` (one row per case and variant, every step's seconds
``<step>_s`` and peak ``<step>_mb``) and the markdown tables ``DIR/scale.md`` / ``DIR/models.md``.
Targets (issue 31): the seamless map at ~1M tets within 120 s and 8 GB; the hex stage of every
``c`` model within 60 s.
"""
from __future__ import annotations

import argparse
import csv
import datetime as _dt
import json
import os
import platform
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TORCHCONN_DATA", ROOT.parent / "shared" / "data"))
CACHE = Path("/work/dev/cache")
SEAMLESS_TARGET_S, SEAMLESS_TARGET_MB = 120.0, 8192.0
HEX_TARGET_S = 60.0
#: The map stage's steps, as ``integer_grid_map`` names them in ``stats["timings"]`` (in order).
MAP_STEPS = ("straighten", "split", "charts_and_constraints", "meshability", "seamless", "quantization", "validity")
#: The hex stage's steps after the map (``HexMeshResult.timings``).
HEX_STEPS = ("extract", "untangle", "quality")


# ----------------------------------------------------------------------------- memory sampling
class RSSSampler:
    """Resident set size and CPU time of this process every ``period`` seconds, as
    ``(time, MB, cpu seconds)`` triples."""

    def __init__(self, period: float = 0.01):
        self.period = period
        self.samples: list[tuple[float, float, float]] = []
        self._stop = threading.Event()
        self._page = os.sysconf("SC_PAGE_SIZE") / 2**20
        self._thread = threading.Thread(target=self._run, daemon=True)

    def rss_mb(self) -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self._page

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.perf_counter(), self.rss_mb(), time.process_time()))
            self._stop.wait(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.samples.append((time.perf_counter(), self.rss_mb(), time.process_time()))

    def cpu(self, t: float) -> float:
        """Process CPU seconds at the last sample at or before ``t``."""
        before = [c for tt, _, c in self.samples if tt <= t]
        return before[-1] if before else self.samples[0][2]

    def peak(self, t0: float, t1: float) -> float:
        """Peak RSS (MB) over the samples in ``[t0, t1]`` (and the last one before ``t0``)."""
        before = [mb for t, mb, _ in self.samples if t <= t0]
        inside = [mb for t, mb, _ in self.samples if t0 < t <= t1]
        return max(inside + before[-1:], default=float("nan"))


def _step_peaks(sampler: RSSSampler, start: float, timings: dict, steps) -> dict:
    """``{step_s, step_mb, step_cpu}`` from a stage's consecutive step durations starting at
    ``start`` (``cpu``: process CPU seconds, which a loaded machine inflates less than wall time)."""
    out = {}
    t = start
    for name in steps:
        dt = timings.get(f"{name}_s")
        if dt is None:
            continue
        out[f"{name}_s"] = float(dt)
        out[f"{name}_mb"] = sampler.peak(t, t + dt)
        out[f"{name}_cpu"] = sampler.cpu(t + dt) - sampler.cpu(t)
        t += dt
    return out


# ----------------------------------------------------------------------------- the child
def _load(model: str, lmax: float | None, data: str | None = None):
    import torch

    from torchconn.mesh.cad import load_hexme

    path = Path(data or DATA) / "hexme" / "meta" / f"{model}.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such HexMe parameter file")
    options = {} if lmax is None else {"Mesh.CharacteristicLengthMax": float(lmax)}
    return load_hexme(path, dtype=torch.float64, options=options)


def _frames(job: dict, mesh):
    """Per-vertex frames of the job's field (computed once and cached in the output folder)."""
    import numpy as np
    import torch

    if job["field"] == "connection":
        path = Path(job["cache"]) / f"{job['model']}__connection.npy"
        if job.get("lmax") is not None or not path.is_file():
            raise FileNotFoundError(f"{path}: no cached connection field for this mesh")
        F = np.load(path)
    else:
        path = Path(job["out"]) / "fields" / f"{case_name(job['model'], job.get('lmax'))}__sh.npy"
        if path.is_file():
            F = np.load(path)
        else:
            from torchconn.frames import design

            F = design(mesh, "sh_baseline").vertex_frames.detach().cpu().numpy()
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npy")
            np.save(tmp, F)
            os.replace(tmp, path)
    if F.shape != (mesh.n_vertices, 3, 3):
        raise ValueError(f"field of shape {F.shape} for a mesh of {mesh.n_vertices} vertices")
    return torch.as_tensor(F, dtype=torch.float64)


def run_child(job: dict) -> dict:
    """One case in this process: mesh, field, then the map stage or the whole hex stage."""
    import torch

    torch.set_num_threads(int(job["threads"]))
    rec = {"case": case_name(job["model"], job.get("lmax")), "variant": job["variant"], "field": job["field"],
           "error": ""}
    mesh = _load(job["model"], job.get("lmax"), job.get("data"))
    rec.update(tets=mesh.n_tets, vertices=mesh.n_vertices)
    F = _frames(job, mesh)
    if job["mode"] == "field":
        return rec
    with RSSSampler() as sampler:
        rec["rss_start_mb"] = sampler.rss_mb()
        t0 = time.perf_counter()
        if job["mode"] == "scale":
            from torchconn.hexmesh import integer_grid_map

            igm = integer_grid_map(mesh, F)
            total = time.perf_counter() - t0
            timings = igm.stats["timings"]
            rec.update(_step_peaks(sampler, t0, timings, MAP_STEPS))
            gates, first, map_tets = igm.gates, igm.first_failed, igm.mesh.n_tets
            stats = igm.stats
        else:
            from torchconn.hexmesh import hex_mesh

            r = hex_mesh(mesh, F)
            total = time.perf_counter() - t0
            timings = r.map.stats["timings"]
            rec.update(_step_peaks(sampler, t0, timings, MAP_STEPS))
            t_map = t0 + r.timings.get("map_s", 0.0)
            rec.update(_step_peaks(sampler, t_map, r.timings, HEX_STEPS))
            gates, first, map_tets = r.gates, r.first_failed, r.map.mesh.n_tets
            stats = r.map.stats
            rec.update(hexes=int(r.hexes.shape[0]), good=bool(r.good))
        rec["total_s"] = total
        rec["total_cpu"] = sampler.cpu(time.perf_counter()) - sampler.cpu(t0)
        rec["total_mb"] = sampler.peak(t0, time.perf_counter())
    rec["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    rec.update(map_tets=int(map_tets), first_failed=first or "", gates=" ".join(
        f"{k}:{'ok' if g.passed else 'FAIL'}" for k, g in gates.items()))
    rec["detail_s"] = {k: float(v) for k, v in timings.items() if k.removesuffix("_s") not in MAP_STEPS}
    q = stats.get("quantization", {})
    rec.update(unknowns=stats.get("unknowns"), free_unknowns=stats.get("free_unknowns"),
               integers=q.get("integers"), rounding=q.get("method", ""))
    return rec


def case_name(model: str, lmax) -> str:
    return model if lmax is None else f"{model}@lmax={lmax:g}"


# ----------------------------------------------------------------------------- the parent
def _run(job: dict, timeout: float, path: str) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([path, *filter(None, [env.get("PYTHONPATH")])])
    th = str(int(job["threads"]))
    env.update(OMP_NUM_THREADS=th, MKL_NUM_THREADS=th, OPENBLAS_NUM_THREADS=th)
    cmd = [sys.executable, str(Path(__file__).resolve()), "child", json.dumps(job)]
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, cwd=path, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"case": case_name(job["model"], job.get("lmax")), "variant": job["variant"], "field": job["field"],
                "error": f"timeout: no result within {timeout:.0f} s"}
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    if r.returncode or not lines:
        tail = ((r.stderr or r.stdout).strip().splitlines() or ["no output"])[-1][:300]
        return {"case": case_name(job["model"], job.get("lmax")), "variant": job["variant"], "field": job["field"],
                "error": f"exit {r.returncode}: {tail}", "wall_s": time.perf_counter() - t0}
    return json.loads(lines[-1][len("RESULT "):])


def _table(rows: list[dict], steps, title: str) -> list[str]:
    cols = ["case", "variant", "tets", "map_tets"] + [f"{s}_s" for s in steps] + ["total_s", "total_cpu", "total_mb",
                                                                                   "peak_mb", "first_failed", "error"]
    if any("hexes" in r for r in rows):
        cols[-2:-2] = ["hexes", "good"]
    out = [f"### {title}", "", "| " + " | ".join(c.removesuffix("_s") if c.endswith("_s") and c != "total_s" else c
                                                 for c in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            if isinstance(v, float):
                v = f"{v:.0f}" if c.endswith("_mb") else f"{v:.2f}"
            cells.append(str(v))
        out.append("| " + " | ".join(cells) + " |")
    for suffix, what, fmt in (("_cpu", "CPU seconds per step", "{:.2f}"), ("_mb", "Peak resident memory per step (MB)",
                                                                          "{:.0f}")):
        out += ["", f"{what}:", "", "| case | variant | " + " | ".join(s for s in steps) + " |",
                "|---|---|" + "---|" * len(steps)]
        for r in rows:
            out.append(f"| {r.get('case')} | {r.get('variant')} | " + " | ".join(
                fmt.format(r[s + suffix]) if isinstance(r.get(s + suffix), float) else "" for s in steps) + " |")
    return out


def _write(out: Path, mode: str, rows: list[dict], steps, argv) -> None:
    keys = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(out / f"{mode}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: json.dumps(v) if isinstance(v, dict) else v for k, v in r.items()})
    lines = [f"# hex_stage_scale {mode}", "",
             f"{_dt.date.today().isoformat()}, `python -m benchmarks.hex_stage_scale {' '.join(argv)}`, "
             f"{platform.machine()} {os.cpu_count()} cores, 1-min load at the end {os.getloadavg()[0]:.1f}", ""]
    lines += _table(rows, steps, "steps (s)")
    if mode == "scale":
        lines += ["", f"Target: the seamless map (every step above) at ~1M tets <= {SEAMLESS_TARGET_S:.0f} s and "
                      f"<= {SEAMLESS_TARGET_MB / 1024:.0f} GB."]
    else:
        ok = [r for r in rows if not r.get("error")]
        over = [f"{r['case']} ({r['variant']}: {r['total_s']:.0f} s)" for r in ok if r["total_s"] > HEX_TARGET_S]
        lines += ["", f"Target: hex stage <= {HEX_TARGET_S:.0f} s per model: {len(ok) - len(over)} of {len(ok)} runs "
                      f"within; over: {', '.join(over) or 'none'}."]
    (out / f"{mode}.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> Path:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["child"]:
        job = json.loads(argv[1])
        try:
            rec = run_child(job)
        except Exception as exc:  # noqa: BLE001 - a failing run is a row with its error
            rec = {"case": case_name(job["model"], job.get("lmax")), "variant": job["variant"], "field": job["field"],
                   "error": f"{type(exc).__name__}: {exc}".replace("\n", " ")[:300]}
        print("RESULT " + json.dumps(rec, default=float), flush=True)
        return Path(".")
    p = argparse.ArgumentParser(prog="python -m benchmarks.hex_stage_scale", description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=("scale", "models"))
    p.add_argument("--model", default="i02c_m2")
    p.add_argument("--lmax", default="0.5,0.3,0.2,0.14")
    p.add_argument("--models", default="s,n,i")
    p.add_argument("--field", choices=("sh", "connection"), default="sh")
    p.add_argument("--cache", default=str(CACHE))
    p.add_argument("--variant", action="append", default=[])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--timeout", type=float, default=1800.0)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    variants = [v.split("=", 1) for v in a.variant] or [["after", str(ROOT)]]
    out = Path(a.out or ROOT / "results" / f"hex_stage_scale_{a.mode}")
    out.mkdir(parents=True, exist_ok=True)
    if a.mode == "scale":
        cases = [(a.model, float(x)) for x in a.lmax.split(",") if x]
        steps = MAP_STEPS
    else:
        meta = DATA / "hexme" / "meta"
        if not meta.is_dir():
            raise SystemExit(f"{meta}: no HexMe parameter files (the shared data is missing)")
        pref = [m for m in a.models.split(",") if m]
        names = sorted(q.stem for q in meta.glob("*.yaml") if q.stem[3:4] == "c" and len(q.stem) > 4)
        cases = [(n, None) for n in names if any(n.startswith(m) for m in pref)]
        steps = MAP_STEPS + HEX_STEPS
    rows = []
    for model, lmax in cases:
        base = {"model": model, "lmax": lmax, "field": a.field, "cache": a.cache, "threads": a.threads,
                "out": str(out.resolve()), "data": str(DATA.resolve())}
        if a.field == "sh":  # the field once, for every variant
            rec = _run({**base, "mode": "field", "variant": "field"}, a.timeout, str(ROOT))
            if rec.get("error"):
                rows += [{**rec, "variant": name} for name, _ in variants]
                continue
        for name, path in variants:
            rec = _run({**base, "mode": a.mode, "variant": name}, a.timeout, path)
            rows.append(rec)
            print(json.dumps({k: v for k, v in rec.items() if k != "detail_s"}, default=float), flush=True)
            _write(out, a.mode, rows, steps, argv)
    _write(out, a.mode, rows, steps, argv)
    return out


if __name__ == "__main__":
    if __package__ in (None, ""):  # run as a file by the parent: the variant's package comes first
        sys.path[:1] = []
    main()
