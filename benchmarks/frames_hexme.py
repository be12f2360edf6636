"""Frame-field benchmark on HexMe (and the shared meshes): every model x every method, one row each.

    python -m benchmarks.frames_hexme [--set hexme|shared] [--kinds c,u] [--models s,n,i|s02c,...]
        [--methods sh,mbo,connection,mouette] [--out DIR] [--jobs 1] [--threads 2]
        [--launcher joblib|hexme_slurm|none] [--timeout 1800] [--max-tets 200000]
        [--opt METHOD.KEY=VALUE ...] [--force] [--aggregate-only]

Methods (``--methods``; default ``sh,mbo,connection`` plus ``mouette`` when it imports):

* ``sh``: the SH baseline of Ray, Sokolov & Lévy 2016 (``design(mesh, "sh")``, its defaults);
* ``mbo``: :func:`torchconn.frames.mbo.mbo_frames` (Palmer, Bommes & Solomon 2020), its defaults;
* ``connection``: the connection method as the jobs run it,
  :func:`torchconn.hexmesh.choose.design_for_hex` (``select=hex`` over 8 candidates, the map-energy
  term with weight :data:`CONNECTION_MAP_WEIGHT`; ``--opt connection.select=proxies``,
  ``--opt connection.weights.map=0`` etc. change them);
* ``mouette``: mouette's ``VolumeFrameField(mesh, "vertices")`` on the same tet mesh (optional;
  an error row when the package is missing). mouette indexes its boundary-normal attribute with
  volume-vertex ids, so the mesh is renumbered boundary-first for it and the frames mapped back
  (the workaround of ``benchmarks.compare_frames``).

``--opt mbo.n_taus=4`` (repeatable) passes an option to one method (``design()`` options for
``sh``/``connection``, ``mbo_frames`` keywords for ``mbo``; values are parsed as YAML).

Sets (``--set``): ``hexme``: the parameter files ``../shared/data/hexme/meta/XNN{k}_name.yaml``
for the kinds ``--kinds`` (``c``, ``u``), meshed by gmsh with the dataset's parameters and one
thread (:func:`torchconn.mesh.cad.load_hexme`; deterministic, so every method sees the same
mesh); ``--models`` keeps the names that start with one of the given prefixes (``s,n,i``: all;
``s02c,n05``: those; ``i02c_m2@lmax=0.15``: that parameter file with
``Mesh.CharacteristicLengthMax = 0.15``, a finer mesh, about a million tets here). A mesh over
``--max-tets`` tets is an error row ("over max-tets").
``shared``: ``sphere_r0.17``, ``78322_gear.2``, ``dinosaur``, ``bunny`` (tetrahedralized with
edge length 0.08) and ``fandisk`` (0.2).

Jobs: one per (model, method). Each runs in a child process (``--threads`` torch threads), which
writes ``DIR/jobs/<set>__<model>__<method>.json``: every metric of
:func:`torchconn.frames.metrics.frame_metrics`, the mesh size, the times (``mesh_s`` meshing,
``method_s`` the method, ``metrics_s`` the metrics, ``wall_s`` their sum) and the
child's peak resident memory (``peak_rss_mb``, ``getrusage`` max RSS); then the **hex stage**
(:func:`torchconn.hexmesh.hex_mesh` of the field, ``--hex-opt KEY=VALUE`` options; ``--no-hex``
skips it): ``hex_valid`` (the map) and ``hex_reason`` (which checks fail, and where),
``hex_inverted_tets``, ``hex_degenerate_tets``, ``hex_n`` hexes, ``hex_sj_min``/``hex_sj_mean``
(scaled Jacobian), ``hex_irregular`` (fraction of interior edges not in four hexes),
``hex_hausdorff`` (relative to the bounding-box diagonal), CAD corners and curves meshed,
``hex_good`` (a valid map and a good hex mesh: HEXMESH.md / issue 22), ``hex_s`` and
``end_to_end_s`` (field + hex stage; the connection method's chooser already meshed the field it
returned, ``hex_from_chooser``: that mesh is used, not made again). A failing hex stage is the row's ``hex_error``. A job that raises, dies or
runs past ``--timeout`` is a row with its ``error``, never a stop. A job whose result file exists
is skipped (resumption; ``--force`` reruns). The options of the run are in ``DIR/options.json``.

Launchers: ``--launcher joblib`` (default when ``hydra-joblib-launcher`` is installed) runs the jobs
as a Hydra multirun, ``hydra/launcher=joblib`` with ``hydra.launcher.n_jobs=--jobs``; the Hydra app
is ``python -m benchmarks.frames_hexme hydra-job`` with ``benchmarks/conf/frames_hexme.yaml``.
``--launcher hexme_slurm`` submits the same sweep to SLURM with ``hydra-submitit-launcher``
(``benchmarks/conf/hydra/launcher/hexme_slurm.yaml``: edit partition, time and memory there or
override them, e.g. ``--hydra-arg hydra.launcher.partition=cpu``); run ``--aggregate-only`` on the
same ``--out`` once the array has finished. ``--launcher none`` (``--no-hydra``) runs the jobs one
after the other in this process's loop (each still in its child process; ``--in-process`` runs
them in this process itself, without the memory column). The plugins are the ``bench`` extra.

Aggregation (:mod:`benchmarks.frames_hexme_report`, also ``--aggregate-only``) reads the job files
and writes ``DIR/results.csv``, ``DIR/results.md`` (per-model rows, set-level figures against
the SH baseline, the issue's targets held / not held) and ``DIR/ratios.png``.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import resource
import subprocess
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
METHODS = ("sh", "mbo", "connection", "mouette")
SETS = ("hexme", "shared")
#: The shared meshes: name -> (file, edge length of the tetrahedralization or None for tet files).
SHARED = {
    "sphere_r0.17": ("sphere_r0.17.mesh", None),
    "78322_gear.2": ("78322_gear.2.mesh", None),
    "dinosaur": ("dinosaur.msh", None),
    "bunny": ("bunny.obj", 0.08),
    "fandisk": ("fandisk.ply", 0.2),
}
FEATURE_ANGLE = 30.0
#: ``map_weight`` of configs/train_frames.yaml (the connection method as the jobs run it).
CONNECTION_MAP_WEIGHT = 1.0


# ----------------------------------------------------------------------------- cases
def list_cases(set_name: str = "hexme", kinds=("c",), models=None, data_dir: Path | None = None) -> list[str]:
    """Model names of a set: HexMe parameter-file stems (``s02c_prism``) or :data:`SHARED` keys.

    ``models``: prefixes (``["s", "n02"]``; an entry ``NAME@lmax=X`` is the case of :func:`load_case`);
    ``None`` keeps all. ``kinds``: HexMe mesh kinds.
    """
    data = Path(data_dir) if data_dir else DATA
    if set_name == "shared":
        names = list(SHARED)
    elif set_name == "hexme":
        meta = data / "hexme" / "meta"
        if not meta.is_dir():
            raise FileNotFoundError(f"{meta}: no HexMe parameter files (the shared data is missing)")
        kinds = tuple(kinds)
        bad = [k for k in kinds if k not in ("c", "u", "b")]
        if bad:
            raise ValueError(f"unknown HexMe kinds {bad}; known: c, u (b: embedded in a box)")
        names = sorted(p.stem for p in meta.glob("*.yaml") if p.stem[3:4] in kinds and len(p.stem) > 4)
    else:
        raise ValueError(f"unknown set {set_name!r}; known: {list(SETS)}")
    if models:
        # a model with '@' is a case of its own (NAME@lmax=X, see load_case), listed as given
        exact = [m for m in models if "@" in m and m.partition("@")[0] in names]
        names = [n for n in names if any(n.startswith(m) for m in models if "@" not in m)] + exact
    return names


def load_case(set_name: str, name: str, data_dir: Path | None = None):
    """The float64 ``TetMesh`` of one model.

    A HexMe name may end in ``@lmax=X``: the model's parameter file with
    ``Mesh.CharacteristicLengthMax = X`` (a finer mesh of the same kind, e.g. ``i02c_m2@lmax=0.15``).
    """
    import torch

    from torchconn.mesh import load_mesh

    data = Path(data_dir) if data_dir else DATA
    if set_name == "hexme":
        from torchconn.mesh.cad import load_hexme

        stem, _, spec = name.partition("@")
        options = {}
        if spec:
            key, _, value = spec.partition("=")
            if key != "lmax" or not value:
                raise ValueError(f"{name!r}: a HexMe case is NAME or NAME@lmax=X, got {spec!r} after '@'")
            options["Mesh.CharacteristicLengthMax"] = float(value)
        path = data / "hexme" / "meta" / f"{stem}.yaml"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such HexMe parameter file")
        return load_hexme(path, dtype=torch.float64, options=options)
    if name not in SHARED:
        raise ValueError(f"unknown shared mesh {name!r}; known: {list(SHARED)}")
    file, el = SHARED[name]
    kw = {} if el is None else {"edge_length": el}
    return load_mesh(data / file, **kw).to(dtype=torch.float64)


# ----------------------------------------------------------------------------- methods
def _mouette_frames(mesh):
    import tempfile

    import meshio
    import mouette
    import numpy as np
    import torch

    P, T = mesh.vertices.cpu().numpy(), mesh.tets.cpu().numpy()
    on_b = np.zeros(P.shape[0], bool)
    on_b[mesh.boundary_vertices.cpu().numpy()] = True
    new_to_old = np.concatenate([np.flatnonzero(on_b), np.flatnonzero(~on_b)])
    old_to_new = np.empty_like(new_to_old)
    old_to_new[new_to_old] = np.arange(new_to_old.size)
    with tempfile.TemporaryDirectory(prefix="hexme_mouette_") as td:
        path = str(Path(td) / "in.mesh")
        meshio.write(path, meshio.Mesh(P[new_to_old], [("tetra", old_to_new[T])]))
        m = mouette.mesh.load(path)
    ff = mouette.framefield.VolumeFrameField(m, "vertices")
    ff.run()
    b2m = ff.mesh.boundary_connectivity.b2m_vertex
    if not all(b2m[k] == k for k in range(int(on_b.sum()))):
        raise RuntimeError("mouette's boundary vertex numbering is not the identity after the renumbering")
    R = np.stack([f.as_matrix() for f in ff.frames])[old_to_new]
    return torch.as_tensor(R, dtype=mesh.vertices.dtype)


def run_method(method: str, mesh, options: dict | None = None, hex_options: dict | None = None):
    """Frames ``(V, 3, 3)`` of ``method`` on ``mesh`` with the method's ``options``.

    For ``connection`` (the hex chooser), the chosen field's hex mesh, made while choosing with
    ``hex_options``, is kept in :data:`LAST_HEX` for :func:`hex_stage`, and the choice (the
    winner's label, why meshing stopped, the stages made, each meshed candidate's label / good /
    valid / first failing gate / hex-stage seconds, ``design()``'s timings) for the row's
    ``chosen`` column.
    """
    options = dict(options or {})
    LAST_HEX.clear()
    if method == "sh":
        from torchconn.frames.design import design

        return design(mesh, method, **options).vertex_frames
    if method == "connection":  # the jobs' default: the hex chooser and the map-energy term
        from torchconn.hexmesh.choose import design_for_hex

        weights = {"map": CONNECTION_MAP_WEIGHT, **(options.pop("weights", None) or {})}
        select = options.pop("select", "hex")
        k = int(options.pop("select_candidates", 8))
        res = design_for_hex(mesh, "connection", select=select, select_candidates=k, weights=weights,
                             hex_options=hex_options, **options)
        if res.hex is not None:
            LAST_HEX["result"] = res.hex
        c = res.metrics.get("chosen") or {}
        LAST_HEX["chosen"] = {"label": c.get("label"), "by": c.get("by"), "stopped": c.get("stopped"),
                              "stages": (res.metrics.get("quality") or {}).get("stages"),
                              "meshed": [(r["label"], r["good"], r["valid"], r.get("first_failed"),
                                          round(float(r["seconds"]), 1)) for r in c.get("meshed", [])],
                              "timings": {k: v for k, v in res.timings.items() if k.endswith("_s")}}
        return res.vertex_frames
    if method == "mbo":
        from torchconn.frames.mbo import mbo_frames

        return mbo_frames(mesh, **options)
    if method == "mouette":
        if options:
            raise TypeError(f"method mouette takes no options, got {sorted(options)}")
        return _mouette_frames(mesh)
    raise ValueError(f"unknown method {method!r}; known: {list(METHODS)}")


#: the hex mesh the connection method's chooser made of the field it returned (:func:`run_method`)
LAST_HEX: dict = {}


def job_name(set_name: str, case: str, method: str) -> str:
    return f"{set_name}__{case}__{method}"


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def evaluate(set_name: str, case: str, method: str, opts: dict) -> dict:
    """One job in this process: mesh, method, metrics -> the result record (errors caught)."""
    rec = {"set": set_name, "model": case, "method": method,
           "kind": case[3] if set_name == "hexme" and len(case) > 3 else "", "error": ""}
    try:
        import torch

        from torchconn.frames.metrics import frame_metrics

        torch.set_num_threads(int(opts.get("threads", 1)))
        t0 = time.perf_counter()
        mesh = load_case(set_name, case, opts.get("data_dir"))
        rec["mesh_s"] = time.perf_counter() - t0
        rec.update(n_vertices=mesh.n_vertices, n_tets=mesh.n_tets)
        max_tets = opts.get("max_tets")
        if max_tets and mesh.n_tets > int(max_tets):
            raise RuntimeError(f"over max-tets: {mesh.n_tets} tets > {int(max_tets)}")
        t0 = time.perf_counter()
        F = run_method(method, mesh, (opts.get("method_options") or {}).get(method), opts.get("hex_options") or {})
        rec["method_s"] = time.perf_counter() - t0
        if not bool(torch.isfinite(F).all()):
            raise FloatingPointError(f"{method} returned non-finite frames")
        t0 = time.perf_counter()
        rec.update(frame_metrics(F, mesh, FEATURE_ANGLE))
        rec["metrics_s"] = time.perf_counter() - t0
        rec["wall_s"] = rec["mesh_s"] + rec["method_s"] + rec["metrics_s"]
    except Exception as exc:  # noqa: BLE001 - a failing run is a row with its error
        rec["error"] = f"{type(exc).__name__}: {exc}".replace("\n", " ")[:500]
        rec["traceback"] = traceback.format_exc()[-4000:]
        return rec
    if opts.get("hex", True):
        if "chosen" in LAST_HEX:
            rec["chosen"] = LAST_HEX.pop("chosen")
        rec.update(hex_stage(mesh, F, opts.get("hex_options") or {}, LAST_HEX.pop("result", None)))
        # the chooser's hex meshes (the returned one among them) are inside the method's seconds
        rec["end_to_end_s"] = rec["wall_s"] + (0.0 if rec.get("hex_from_chooser") else rec.get("hex_s", 0.0))
    return rec


def hex_stage(mesh, frames, options: dict, made=None) -> dict:
    """The hex stage (:func:`torchconn.hexmesh.hex_mesh`) of one field: the ``hex_*`` columns.

    ``made``: that field's :class:`~torchconn.hexmesh.HexMeshResult` with these ``options``, when the
    method already made it (the connection method's chooser): it is used, not made again
    (``hex_from_chooser``; its meshing, and that of every candidate meshed before it, is then
    inside the method's seconds, and ``hex_s`` is that mesh's own hex stage time, as measured
    when it was made: ``timings["total_s"]``).
    A failure of the stage is a row's ``hex_error``, never a lost field row.
    """
    out = {"hex_error": "", "hex_from_chooser": made is not None}
    t0 = time.perf_counter()
    try:
        from torchconn.hexmesh import hex_mesh

        r = made if made is not None else hex_mesh(mesh, frames, **options)
        v, q, ex = r.validity, r.quality, r.extraction
        out.update(hex_valid=bool(v.valid), hex_reason="; ".join(v.reasons)[:300],
                   hex_first_check=next((k for k in v.counts if v.counts[k] and k in _VALIDITY_ORDER), ""),
                   hex_inverted_tets=v.counts.get("inverted_tets", 0), hex_degenerate_tets=v.counts.get("degenerate_tets", 0),
                   hex_complex_edges=v.counts.get("unmeshable_singular_edges", 0),
                   hex_checks=dict(v.counts), hex_n=int(r.hexes.shape[0]),
                   hex_dropped=int(ex.counts()["cubes_dropped"]) if ex is not None else 0,
                   hex_good=bool(r.good), hex_edge_length=float(r.map.edge_length),
                   hex_map_tets=int(r.map.mesh.n_tets), hex_singular_edges=int(r.map.charts.counts()["singular_edges"]),
                   hex_stats={k: val for k, val in r.map.stats.items() if k != "timings"},
                   hex_meshability=r.meshability.counts() if r.meshability is not None else None,
                   hex_meshable=bool(r.meshability.meshable) if r.meshability is not None else None,
                   hex_times={**{f"map_{k}": val for k, val in r.map.stats["timings"].items()}, **r.timings},
                   hex_first_failed=r.first_failed or "",
                   hex_seamless_inverted_ls=r.map.stats["seamless"]["inverted_least_squares"],
                   hex_quantization=r.map.stats["quantization"].get("method", ""),
                   hex_quantization_failed=int(r.map.stats["quantization"].get("failed") or 0),
                   **{f"hex_gate_{k}": bool(g.passed) for k, g in r.gates.items()},
                   hex_gates={k: g.as_dict() for k, g in r.gates.items()})
        if q is not None:
            out.update(hex_sj_min=q.sj_min, hex_sj_mean=q.sj_mean, hex_valid_mesh=bool(q.valid),
                       hex_irregular=q.irregular_fraction, hex_hausdorff=q.hausdorff_rel,
                       hex_volume_ratio=q.volume_ratio, hex_corners=q.n_corners, hex_corners_meshed=q.n_corners_meshed,
                       hex_curves=q.n_curves, hex_curves_meshed=q.n_curves_meshed,
                       hex_not_good="; ".join(q.not_good_reasons)[:300])
    except Exception as exc:  # noqa: BLE001 - a failing stage is a row with its error
        out["hex_error"] = f"{type(exc).__name__}: {exc}".replace("\n", " ")[:500]
        out["hex_traceback"] = traceback.format_exc()[-4000:]
    out["hex_s"] = time.perf_counter() - t0
    if made is not None and "total_s" in (made.timings or {}):
        out["hex_s"] = float(made.timings["total_s"])
    return out


_VALIDITY_ORDER = ("unmeshable_singular_edges", "contradictory_constraints", "inverted_tets", "degenerate_tets",
                   "broken_transitions", "singular_edges_off_integer_lines", "boundary_faces_off_integer_planes")


def _write(path: Path, rec: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(rec, indent=1, default=float))
    os.replace(tmp, path)  # atomic: a result file is complete or absent


def run_job(set_name: str, case: str, method: str, out: Path, opts: dict | None = None, *, force: bool = False,
            in_process: bool = False) -> Path:
    """Run one job unless its result file exists; returns the file. Never raises for a failed run."""
    out = Path(out)
    if opts is None:
        opts = read_options(out)
    jobs = out / "jobs"
    jobs.mkdir(parents=True, exist_ok=True)
    path = jobs / f"{job_name(set_name, case, method)}.json"
    if path.exists() and not force:
        return path
    if in_process:
        rec = evaluate(set_name, case, method, opts)
        rec["peak_rss_mb"] = float("nan")  # not per run in a shared process
        _write(path, rec)
        return path
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    threads = str(int(opts.get("threads", 1)))
    env.update(OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads, OPENBLAS_NUM_THREADS=threads)
    cmd = [sys.executable, "-m", "benchmarks.frames_hexme", "child", set_name, case, method, str(out)]
    timeout = float(opts.get("timeout_s", 1800))
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        err = None if path.exists() else (
            f"child exited {r.returncode} without a result: "
            + ((r.stderr or r.stdout).strip().splitlines() or ["no output"])[-1][:300])
    except subprocess.TimeoutExpired:
        err = f"timeout: no result within {timeout:.0f} s"
        path.unlink(missing_ok=True)
    if err is not None:
        _write(path, {"set": set_name, "model": case, "method": method, "error": err,
                      "wall_s": time.perf_counter() - t0})
    return path


def _child(argv: list[str]) -> None:
    set_name, case, method, out = argv
    out = Path(out)
    rec = evaluate(set_name, case, method, read_options(out))
    rec["peak_rss_mb"] = _peak_rss_mb()
    _write(out / "jobs" / f"{job_name(set_name, case, method)}.json", rec)


# ----------------------------------------------------------------------------- options and sweep
def read_options(out: Path) -> dict:
    p = Path(out) / "options.json"
    return json.loads(p.read_text()) if p.is_file() else {}


def parse_opts(items: list[str]) -> dict:
    """``["mbo.n_taus=4", "connection.steps=50"]`` -> ``{"mbo": {"n_taus": 4}, ...}`` (YAML values)."""
    import yaml

    res: dict = {}
    for it in items or []:
        key, sep, val = it.partition("=")
        method, dot, name = key.partition(".")
        if not sep or not dot or not name:
            raise ValueError(f"--opt {it!r}: expected METHOD.KEY=VALUE")
        if method not in METHODS:
            raise ValueError(f"--opt {it!r}: unknown method {method!r}; known: {list(METHODS)}")
        d = res.setdefault(method, {})
        *groups, last = name.split(".")
        for g in groups:  # design(weights={"tie": 5}) from connection.weights.tie=5
            d = d.setdefault(g, {})
        d[last] = yaml.safe_load(val)
    return res


def parse_hex_opts(items: list[str]) -> dict:
    """``["edge_length=0.1", "straighten=false"]`` -> options of :func:`torchconn.hexmesh.hex_mesh`."""
    import yaml

    from torchconn.hexmesh import MAP_OPTIONS

    res = {}
    for it in items or []:
        key, sep, val = it.partition("=")
        if not sep or key not in MAP_OPTIONS:
            raise ValueError(f"--hex-opt {it!r}: expected KEY=VALUE with KEY in {list(MAP_OPTIONS)}")
        res[key] = yaml.safe_load(val)
    return res


def plugins_available() -> dict:
    found = {}
    for name, mod in (("joblib", "hydra_plugins.hydra_joblib_launcher"),
                      ("submitit", "hydra_plugins.hydra_submitit_launcher")):
        try:
            __import__(mod)
            found[name] = True
        except ImportError:
            found[name] = False
    return found


def mouette_available() -> bool:
    try:
        import mouette  # noqa: F401
    except Exception:  # noqa: BLE001 - any import failure means "not available"
        return False
    return True


def _hydra_sweep(cases, methods, out: Path, launcher: str, jobs: int, extra: list[str]) -> int:
    launch = {"joblib": ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"],
              "hexme_slurm": ["hydra/launcher=hexme_slurm"]}[launcher]
    cmd = [sys.executable, "-m", "benchmarks.frames_hexme", "hydra-job", "--multirun",
           "case=" + ",".join(f"'{c}'" for c in cases), f"method={','.join(methods)}", f"out_dir={out}", *launch, *extra]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return subprocess.run(cmd, cwd=ROOT, env=env).returncode


def _hydra_entry() -> None:
    import hydra

    @hydra.main(config_path="conf", config_name="frames_hexme", version_base=None)
    def job(cfg) -> None:
        out = Path(cfg.out_dir)
        opts = read_options(out)
        run_job(opts.get("set", "hexme"), str(cfg.case), str(cfg.method), out, opts)

    job()


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", default="hexme", choices=SETS)
    ap.add_argument("--kinds", default="c", help="HexMe mesh kinds, comma-separated (c, u)")
    ap.add_argument("--models", default=None, help="name prefixes, comma-separated (default: all)")
    ap.add_argument("--methods", default=None, help=f"comma-separated of {METHODS} (default: sh,mbo,connection"
                                                    f" and mouette when it imports)")
    ap.add_argument("--out", default=None, help="output directory (default: benchmarks/out/frames_hexme_<set>)")
    ap.add_argument("--data-dir", default=None, help="the shared data folder (default ../shared/data)")
    ap.add_argument("--jobs", type=int, default=1, help="parallel jobs (joblib launcher)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads per job (1: on a shared machine more threads than free cores is far slower)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per job")
    ap.add_argument("--max-tets", type=int, default=200_000)
    ap.add_argument("--launcher", default=None, choices=("joblib", "hexme_slurm", "none"))
    ap.add_argument("--no-hydra", action="store_true", help="same as --launcher none")
    ap.add_argument("--in-process", action="store_true", help="with --launcher none: no child process per job")
    ap.add_argument("--hydra-arg", action="append", default=[], help="extra Hydra override (repeatable)")
    ap.add_argument("--opt", action="append", default=[], help="METHOD.KEY=VALUE method option (repeatable)")
    ap.add_argument("--no-hex", action="store_true", help="skip the hex stage (map, extraction, hex quality)")
    ap.add_argument("--hex-opt", action="append", default=[],
                    help="KEY=VALUE option of torchconn.hexmesh.hex_mesh (repeatable; YAML values)")
    ap.add_argument("--force", action="store_true", help="rerun jobs whose result file exists")
    ap.add_argument("--aggregate-only", action="store_true", help="only read the job files and write the report")
    args = ap.parse_args(argv)

    out = Path(args.out or ROOT / "benchmarks" / "out" / f"frames_hexme_{args.set}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    from . import frames_hexme_report as report

    if not args.aggregate_only:
        kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
        models = [m.strip() for m in args.models.split(",") if m.strip()] if args.models else None
        cases = list_cases(args.set, kinds, models, args.data_dir)
        if not cases:
            ap.error(f"no model of set {args.set!r} matches kinds={kinds} models={models}")
        if args.methods:
            methods = [m.strip() for m in args.methods.split(",") if m.strip()]
            bad = [m for m in methods if m not in METHODS]
            if bad:
                ap.error(f"unknown methods {bad}; known: {list(METHODS)}")
        else:
            methods = ["sh", "mbo", "connection"] + (["mouette"] if mouette_available() else [])
        opts = {"set": args.set, "cases": cases, "methods": methods, "threads": args.threads,
                "timeout_s": args.timeout, "max_tets": args.max_tets, "method_options": parse_opts(args.opt),
                "hex": not args.no_hex, "hex_options": parse_hex_opts(args.hex_opt),
                "data_dir": str(Path(args.data_dir).resolve()) if args.data_dir else None,
                "command": "python -m benchmarks.frames_hexme " + " ".join(argv if argv is not None else sys.argv[1:]),
                "started": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
        (out / "options.json").write_text(json.dumps(opts, indent=1))
        if args.force:
            for c in cases:
                for m in methods:
                    (out / "jobs" / f"{job_name(args.set, c, m)}.json").unlink(missing_ok=True)
        launcher = "none" if args.no_hydra else args.launcher
        if launcher is None:
            launcher = "joblib" if plugins_available()["joblib"] else "none"
            if launcher == "none":
                print("hydra-joblib-launcher is not installed (pip install 'torchconn[bench]'): running the jobs "
                      "in a plain loop", file=sys.stderr)
        t0 = time.perf_counter()
        if launcher == "none":
            for c in cases:
                for m in methods:
                    run_job(args.set, c, m, out, opts, in_process=args.in_process)
        else:
            rc = _hydra_sweep(cases, methods, out, launcher, args.jobs, args.hydra_arg)
            if rc != 0:
                print(f"the Hydra sweep exited with {rc}; aggregating what is there", file=sys.stderr)
        print(f"sweep: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    paths = report.aggregate(out)
    print(paths["md"].read_text())
    return out


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "hydra-job":
        del sys.argv[1]
        _hydra_entry()
    elif len(sys.argv) > 1 and sys.argv[1] == "child":
        _child(sys.argv[2:])
    else:
        main()
