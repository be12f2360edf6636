"""Frame-field comparison: SH baseline vs the connection method (vs mouette), one markdown table.

    python -m benchmarks.compare_frames [--cases sphere,gear,bunny,fandisk] [--mouette]
        [--mouette-timeout 300] [--threads 1] [--output-dir DIR] [key=value ...]

Each case runs :func:`training.train_frames.train` three times on the same mesh: ``sh_linear``
(``method=sh_baseline sh.n_smooth_iters=0``: the linear L4 solve with the boundary constraint and
the projection only, literally the issue's description of the baseline), ``sh_baseline`` (the
default, with Ray et al.'s nonlinear smoothing) and ``connection`` (the default config plus the
trailing ``key=value`` overrides, e.g. ``steps=300``), and reports the fixed metrics of
:func:`torchconn.frames.metrics.frame_metrics` with the wall time of each run. The columns
"vs SH" and "vs SH lin" are the relative change of the mean smoothness against ``sh_baseline``
and ``sh_linear``. ``--breakdown`` also prints, per run, the edge-class split of the mean angle
(:func:`torchconn.frames.metrics.edge_class_breakdown`, stored in ``metrics.json``).

Cases (``--cases``; the surfaces are tetrahedralized with the edge length given here):

* ``sphere``:  ``../shared/data/sphere_r0.17.mesh`` (tet mesh)
* ``gear``:    ``../shared/data/78322_gear.2.mesh`` (tet mesh)
* ``bunny``:   ``../shared/data/bunny.obj``, ``edge_length=0.08`` (~9.8k vertices, 49k tets)
* ``fandisk``: ``../shared/data/fandisk.ply``, ``edge_length=0.2`` (~12.6k vertices, 54k tets)

``--mouette`` also runs mouette's Ray et al. 2016 ``VolumeFrameField(mesh, "vertices")`` (when
the package is installed) in a subprocess limited to ``--mouette-timeout`` seconds, on the
*same* tet mesh (written to a temporary MEDIT file with vertices and tets only), and evaluates
its frames with the same metrics. mouette 1.2.7 indexes its boundary-normal attribute (sized
by the number of boundary vertices) with volume-vertex ids in ``normalize()``, which fails
unless the boundary vertices are numbered first; the runner therefore renumbers the vertices
(boundary first, in increasing order, which makes mouette's boundary map the identity), checks
that map, and maps the frames back to the original order. mouette's ``frames`` are
``scipy.spatial.transform.Rotation`` objects; their matrices have the frame axes as columns
(the convention of this library: the boundary alignment of the columns is ~1 degree, of the
rows ~30 degrees).

Writes ``DIR/compare_frames.json`` (rewritten after every run) and prints the table.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

CASES = {
    "sphere": (DATA / "sphere_r0.17.mesh", None),
    "gear": (DATA / "78322_gear.2.mesh", None),
    "bunny": (DATA / "bunny.obj", 0.08),
    "fandisk": (DATA / "fandisk.ply", 0.2),
}
COLUMNS = ("smoothness_mean_deg", "smoothness_rms_deg", "alignment_mean_deg", "alignment_max_deg",
           "feature_alignment_mean_deg", "n_singular_faces")

_MOUETTE_CHILD = r'''
import json, sys, time
import numpy as np, meshio, torch
torch.set_num_threads(int(sys.argv[4]))
import mouette
from torchconn import io as tio
from torchconn.frames.metrics import frame_metrics
path, edge_length, tmp = sys.argv[1], (None if sys.argv[2] == "none" else float(sys.argv[2])), sys.argv[3]
mesh = tio.load_mesh(path, **({} if edge_length is None else {"edge_length": edge_length})).to(dtype=torch.float64)
P, T = mesh.vertices.numpy(), mesh.tets.numpy()
on_b = np.zeros(P.shape[0], bool)
on_b[mesh.boundary_vertices.numpy()] = True
new_to_old = np.concatenate([np.flatnonzero(on_b), np.flatnonzero(~on_b)])
old_to_new = np.empty_like(new_to_old)
old_to_new[new_to_old] = np.arange(new_to_old.size)
meshio.write(tmp, meshio.Mesh(P[new_to_old], [("tetra", old_to_new[T])]))
m = mouette.mesh.load(tmp)
t0 = time.perf_counter()
ff = mouette.framefield.VolumeFrameField(m, "vertices")
ff.run()
wall = time.perf_counter() - t0
b2m = ff.mesh.boundary_connectivity.b2m_vertex
assert all(b2m[k] == k for k in range(int(on_b.sum()))), "mouette boundary numbering is not the identity"
R = np.stack([f.as_matrix() for f in ff.frames])[old_to_new]  # back to the original vertex order
met = frame_metrics(torch.as_tensor(R), mesh)
print("RESULT " + json.dumps({"metrics": met, "wall_s": wall}))
'''


RUNS = {  # label: (method, fixed overrides)
    "sh_linear": ("sh_baseline", ["sh.n_smooth_iters=0"]),
    "sh_baseline": ("sh_baseline", []),
    "connection": ("connection", []),
}


def _run_train(name: str, path: Path, edge_length, label: str, out: Path, threads: int, overrides: list[str]) -> dict:
    from training.train_frames import load_config, train

    method, fixed = RUNS[label]
    ov = [f"mesh={path}", f"method={method}", f"output_dir={out / name / label}", "progress=false",
          f"num_threads={threads}", *fixed, *overrides]
    if edge_length is not None:
        ov.append(f"edge_length={edge_length}")
    cfg = load_config(ov)
    t0 = time.perf_counter()
    m = train(cfg)
    return {"metrics": m["final"], "wall_s": time.perf_counter() - t0, "edge_classes": m["edge_classes"]}


def _run_mouette(path: Path, edge_length, timeout: float, threads: int) -> dict:
    with tempfile.TemporaryDirectory() as td:
        cmd = [sys.executable, "-c", _MOUETTE_CHILD, str(path), "none" if edge_length is None else str(edge_length),
               str(Path(td) / "in.mesh"), str(threads)]
        t0 = time.perf_counter()
        try:
            r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"error": f"did not finish within {timeout:.0f} s"}
        wall = time.perf_counter() - t0
    for line in r.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["no output"]
    return {"error": f"exit {r.returncode} after {wall:.0f} s: {tail[0][:200]}"}


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return "–" if math.isnan(v) else f"{v:.3f}"
    return str(v)


def table(results: dict) -> str:
    """Markdown table of ``results[case][method] = {"metrics": ..., "wall_s": ...} | {"error": ...}``."""
    head = ["mesh", "method", *COLUMNS, "vs SH", "vs SH lin", "wall s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for case, runs in results.items():
        bases = [runs.get(b, {}).get("metrics", {}).get("smoothness_mean_deg") for b in ("sh_baseline", "sh_linear")]
        for method, r in runs.items():
            if "error" in r:
                lines.append(f"| {case} | {method} | " + " | ".join(["–"] * len(COLUMNS)) + f" | – | – | {r['error']} |")
                continue
            m = r["metrics"]
            rel = ["–" if not b else f"{100.0 * (m['smoothness_mean_deg'] / b - 1.0):+.1f}%" for b in bases]
            lines.append(f"| {case} | {method} | " + " | ".join(_fmt(m.get(k)) for k in COLUMNS)
                         + f" | {rel[0]} | {rel[1]} | {r['wall_s']:.1f} |")
    return "\n".join(lines)


def breakdown_table(results: dict) -> str:
    """Markdown table of the edge-class split (count, mean angle, share of the sum) per run."""
    lines = ["| mesh | method | class | edges | mean deg | share |", "|---|---|---|---|---|---|"]
    for case, runs in results.items():
        for method, r in runs.items():
            for cls, v in (r.get("edge_classes") or {}).items():
                lines.append(f"| {case} | {method} | {cls} | {v['count']} | {_fmt(v['mean_deg'])} | {v['share']:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="sphere,gear,bunny,fandisk")
    ap.add_argument("--mouette", action="store_true", help="also run mouette's VolumeFrameField (subprocess)")
    ap.add_argument("--mouette-timeout", type=float, default=300.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--output-dir", default=None)
    ap.add_argument("--breakdown", action="store_true", help="also print the edge-class split of the mean angle")
    ap.add_argument("overrides", nargs="*", help="train_frames overrides for the connection runs (key=value)")
    args = ap.parse_args(argv)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        ap.error(f"unknown cases {unknown}; known: {list(CASES)}")
    out = Path(args.output_dir or tempfile.mkdtemp(prefix="compare_frames_"))
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    for case in cases:
        path, el = CASES[case]
        results[case] = {}
        for method in RUNS:
            ov = args.overrides if method == "connection" else []
            results[case][method] = _run_train(case, path, el, method, out, args.threads, ov)
            (out / "compare_frames.json").write_text(json.dumps(results, indent=1))
        if args.mouette:
            results[case]["mouette"] = _run_mouette(path, el, args.mouette_timeout, args.threads)
            (out / "compare_frames.json").write_text(json.dumps(results, indent=1))
    print(table(results))
    if args.breakdown:
        print()
        print(breakdown_table(results))
    print(f"\n(json: {out / 'compare_frames.json'})")
    return results


if __name__ == "__main__":
    main()
