"""The hex verdict of the jobs' method on AVX2 and AVX-512 code paths, side by side (issue 31).

    python -m benchmarks.march_verdicts --models s01,s02,... [--workers 12] [--out DIR]
                                        [--meshes DIR] [--pack DIR] [--timeout 240]

Each HexMe ``c`` model runs the connection method of the jobs (``benchmarks.frames_hexme``'s
``connection``: ``design_for_hex`` and its hex chooser) and the hex stage of the field it returns,
once per code path, in a fresh process of one thread with

* AVX2: ``TORCHCONN_MARCH=x86-64-v3`` (the C kernels) and ``ATEN_CPU_CAPABILITY=avx2`` (torch's);
* AVX-512: ``TORCHCONN_MARCH=x86-64-v4`` and ``ATEN_CPU_CAPABILITY=avx512`` — only where the CPU
  has ``avx512f`` (said so otherwise).

Each path builds its kernels into a cache of its own (``TORCHCONN_CACHE``) before the models run.
Printed per model: good / valid / Hausdorff / hexes / the chosen candidate / a digest of the frames
(rounded to 1e-6) for each path, and ``SAME`` or ``DIFFER`` (good, valid and the hex count);
``DIR/march_verdicts.json`` holds the records. ``--pack DIR`` writes the models' tet meshes (made
by gmsh) as pickles, and ``--meshes DIR`` reads them, for a machine without gmsh.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import hashlib
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

PATHS = {"avx2": ("x86-64-v3", "avx2"), "avx512": ("x86-64-v4", "avx512")}
HEX_KEYS = ("hex_good", "hex_valid", "hex_hausdorff", "hex_n", "hex_first_failed", "hex_not_good", "hex_error")


def has_avx512() -> bool:
    try:
        return " avx512f" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def _env(path: str, cache_root: Path) -> dict:
    march, aten = PATHS[path]
    return {**os.environ, "TORCHCONN_MARCH": march, "ATEN_CPU_CAPABILITY": aten,
            "TORCHCONN_CACHE": str(cache_root / march), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def load(case: str, meshes: Path | None):
    if meshes is not None:
        with open(meshes / f"{case}.pkl", "rb") as f:
            return pickle.load(f)
    from .frames_hexme import load_case

    return load_case("hexme", case)


def run_one(case: str, meshes: Path | None) -> dict:
    """This process's code path: the jobs' connection method and the hex stage of ``case``."""
    import torch

    from .frames_hexme import LAST_HEX, hex_stage, run_method

    torch.set_num_threads(1)
    rec = {"case": case, "march": os.environ.get("TORCHCONN_MARCH"), "aten": torch.backends.cpu.get_cpu_capability()}
    t0 = time.perf_counter()
    try:
        mesh = load(case, meshes)
        F = run_method("connection", mesh, None, {})
        rec["frames_digest"] = hashlib.sha1(F.detach().double().numpy().round(6).tobytes()).hexdigest()[:12]
        rec["chosen"] = (LAST_HEX.get("chosen") or {}).get("label")
        h = hex_stage(mesh, F, {}, LAST_HEX.pop("result", None))
        rec.update({k: h.get(k) for k in HEX_KEYS})
    except Exception as exc:  # noqa: BLE001 - a failing model is a record with its error
        rec["error"] = f"{type(exc).__name__}: {exc}"[:400]
    rec["wall_s"] = time.perf_counter() - t0
    return rec


def same(recs: dict) -> bool:
    """The verdicts agree: good, valid and the hex count equal on every path run."""
    return len({(r.get("hex_good"), r.get("hex_valid"), r.get("hex_n")) for r in recs.values()}) == 1


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", required=True, help="comma-separated HexMe ids or names (s01,s02,n09,...)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("march_verdicts"))
    ap.add_argument("--meshes", type=Path, default=None, help="read <case>.pkl meshes from DIR (no gmsh needed)")
    ap.add_argument("--pack", type=Path, default=None, help="write the models' meshes as DIR/<case>.pkl and stop")
    ap.add_argument("--timeout", type=float, default=240.0, help="seconds per model and path")
    ap.add_argument("--one", nargs=2, metavar=("CASE", "JSON"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        rec = run_one(args.one[0], args.meshes)
        Path(args.one[1]).write_text(json.dumps(rec))
        return rec
    from .frames_hexme import list_cases

    ids = [m.strip() for m in args.models.split(",") if m.strip()]
    if args.meshes is not None:
        names = sorted(p.stem for p in args.meshes.glob("*.pkl"))
        cases = [c for c in names if any(c.startswith(i) for i in ids)]
    else:
        cases = list_cases("hexme", ("c",), ids)
    if args.pack is not None:
        args.pack.mkdir(parents=True, exist_ok=True)
        for c in cases:
            with open(args.pack / f"{c}.pkl", "wb") as f:
                pickle.dump(load(c, None), f)
        print(f"wrote {len(cases)} meshes to {args.pack}")
        return {}
    paths = ["avx2"] + (["avx512"] if has_avx512() else [])
    if len(paths) == 1:
        print("this CPU has no avx512f: the AVX2 path only", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    cache_root = args.out / "kernels"
    root = str(Path(__file__).resolve().parents[1])
    for p in paths:  # build each path's kernels once, before the parallel runs
        subprocess.run([sys.executable, "-c", "import torchconn.frames.design"], env=_env(p, cache_root), cwd=root,
                       check=False)

    def job(cp):
        case, p = cp
        dest = args.out / f"{case}__{p}.json"
        cmd = [sys.executable, "-m", "benchmarks.march_verdicts", "--models", case, "--one", case, str(dest)]
        if args.meshes is not None:
            cmd += ["--meshes", str(args.meshes.resolve())]
        try:
            subprocess.run(cmd, env=_env(p, cache_root), cwd=root, timeout=args.timeout,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
        except subprocess.TimeoutExpired:
            dest.write_text(json.dumps({"case": case, "error": f"timeout {args.timeout:.0f} s"}))
        try:
            return case, p, json.loads(dest.read_text())
        except (OSError, ValueError) as exc:
            return case, p, {"case": case, "error": f"no record: {exc}"}

    rows: dict = {c: {} for c in cases}
    with cf.ThreadPoolExecutor(max(1, args.workers)) as ex:
        for case, p, rec in ex.map(job, [(c, p) for c in cases for p in paths]):
            rows[case][p] = rec
    for case, recs in rows.items():
        cells = [f"{p}: good={r.get('hex_good')} valid={r.get('hex_valid')} haus={r.get('hex_hausdorff')} "
                 f"hexes={r.get('hex_n')} chosen={r.get('chosen')} frames={r.get('frames_digest')} "
                 f"{r.get('wall_s', 0):.0f}s {r.get('error', '')}".rstrip() for p, r in recs.items()]
        print(case, "|", " | ".join(cells), "|", "SAME" if same(recs) else "DIFFER", flush=True)
    (args.out / "march_verdicts.json").write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
