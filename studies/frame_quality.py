"""Frame-field quality against the SH baseline on HexMe ``c`` meshes and the shared meshes (issue 13).

    python -m studies.frame_quality run --models s02,s07,n04 [--variants default,no_quality] --out DIR
    python -m studies.frame_quality run --models all --variants default --out DIR
    python -m studies.frame_quality report DIR

``run`` meshes each model (``../shared/data/hexme/meta/XNNc_*.yaml`` with
:func:`torchconn.mesh.cad.load_hexme`, or a shared mesh file name such as ``sphere_r0.17.mesh``),
runs :func:`torchconn.frames.design.design` with ``method="sh"`` (the baseline) and with
``method="connection"`` for each variant of :data:`VARIANTS` (the options that differ from the
defaults), and appends one JSON line per (model, method) to ``DIR/rows.jsonl`` (every
:func:`~torchconn.frames.metrics.frame_metrics` key, wall time, the quality stage's choice). A
failure is a row with its error. ``report`` prints the per-model table (SH -> variant, all
metrics side by side) and the set-level figures against the issue's targets, per variant.

This is a study (ablations, one process, one thread by default), not the benchmark harness
(``benchmarks/frames_hexme.py``).
"""
from __future__ import annotations

import argparse
import json
import math
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
HEXME = DATA / "hexme" / "meta"

#: Variants of the connection method: the options that differ from ``design``'s defaults.
VARIANTS: dict[str, dict] = {
    # the default: connection optimization from the SH and the MBO field + quality paths from both
    "default": {},
    # no connection optimization: the quality paths start at the SH field
    "no_connection": {"steps": 0},
    # no quality paths: the optimized fields only
    "optimized_only": {"quality": {"paths": []}},
    # one path kind only
    "soft_only": {"quality": {"paths": ["soft"]}},
    "tangent_only": {"quality": {"paths": ["tangent"]}},
    # no anneal: one Dirichlet weight
    "dirichlet_fixed_1": {"quality": {"dirichlet_weights": [1.0]}},
    "dirichlet_fixed_8": {"quality": {"dirichlet_weights": [8.0]}},
    # no Dirichlet term: the mean angle (+ feature terms) only
    "angle_only": {"quality": {"dirichlet_weights": [0.0]}},
    # cheaper paths (fewer weights or iterations)
    "lambda_4": {"quality": {"dirichlet_weights": [8.0, 2.0, 1.0, 0.5]}},
    "iters_40": {"quality": {"iters": 40}},
    # the starts of the connection optimization (default: from the SH and from the MBO field)
    "sh_start_only": {"starts": ["sh"]},
    "mbo_start_only": {"starts": ["mbo"]},
    "iters_10": {"quality": {"iters": 10}},
    # each term of the connection loss off (issue 23's ablation; the hex-stage figures of these are
    # benchmarks.frames_hexme --opt connection.weights.X=0)
    "no_flat": {"weights": {"flat": 0.0}},
    "no_torsion": {"weights": {"torsion": 0.0}},
    "no_dnabla": {"weights": {"dnabla": 0.0}},
    # complex-type singular faces charged more (their edges weigh 1 + c in the paths)
    "complex_4": {"quality": {"complex_weight": 4.0}},
    # no feature-normal term in the paths
    "no_feature_term": {"quality": {"feature_weight": 0.0}},
    # the matched Dirichlet term in the connection loss too
    "loss_dirichlet": {"weights": {"dirichlet": 1.0}},
    # a choice that favours the Dirichlet energy / the mean angle
    "score_dirichlet_2": {"quality": {"score_dirichlet": 2.0}},
    "score_dirichlet_05": {"quality": {"score_dirichlet": 0.5}},
    # the feature-curve alignment never worse than SH's (no 2-degree bound)
    "curve_bound_0": {"quality": {"feature_curve_bound": 0.0}},
}

KEYS = ("smoothness_mean_deg", "smoothness_rms_deg", "dirichlet_energy_mean", "n_singular_faces",
        "n_singular_faces_complex", "singular_valid_fraction", "n_singular_faces_quarter", "alignment_mean_deg",
        "feature_curve_alignment_mean_deg", "n_curves_ending_inside", "n_tets_one_singular_face")
SHORT = ("mean°", "rms°", "Dir", "sing", "cx", "valid", "quarter", "align°", "fcurve°", "end_in", "one_sf")


def all_models() -> list[str]:
    """The HexMe ``c`` models (``s01``, ..., ``i10``) plus the two shared tet meshes."""
    names = sorted(p.name.split("c_")[0] for p in HEXME.glob("*c_*.yaml"))
    return names + ["sphere_r0.17.mesh", "78322_gear.2.mesh"]


def load(name: str, cache: Path | None = None):
    """The mesh of ``name``; from ``cache/name.pkl`` (a pickled ``TetMesh``) when that file exists."""
    if cache is not None and (cache / f"{name}.pkl").is_file():
        import pickle

        with open(cache / f"{name}.pkl", "rb") as fh:
            return pickle.load(fh)
    from torchconn.mesh import load_mesh
    from torchconn.mesh.cad import load_hexme

    if "." in name:
        return load_mesh(DATA / name)
    (meta,) = sorted(HEXME.glob(f"{name}c_*.yaml"))
    return load_hexme(meta)


def _merge(a: dict, b: dict) -> dict:
    return {k: ({**a.get(k, {}), **v} if isinstance(v, dict) else v) for k, v in {**a, **b}.items()}


def run(models: list[str], variants: list[str], out: Path, options: dict | None = None,
        cache: Path | None = None) -> None:
    import torch

    from torchconn.frames.design import design

    out.mkdir(parents=True, exist_ok=True)
    rows = out / "rows.jsonl"
    for name in models:
        try:
            t = time.perf_counter()
            mesh = load(name, cache)
            t_mesh = time.perf_counter() - t
        except Exception as exc:  # a row with the error, never a stop
            _write(rows, {"model": name, "method": "mesh", "error": f"{type(exc).__name__}: {exc}"})
            continue
        for method, opts in [("sh", {}), *[(v, _merge(VARIANTS[v], options or {})) for v in variants]]:
            row = {"model": name, "method": method, "n_tets": mesh.n_tets, "mesh_s": t_mesh}
            try:
                t = time.perf_counter()
                r = design(mesh, "sh" if method == "sh" else "connection", **opts)
                row["wall_s"] = time.perf_counter() - t
                row.update({k: r.metrics["final"][k] for k in r.metrics["final"]})
                c = r.metrics.get("chosen")
                if c:
                    row["quality_n_candidates"] = len(c["candidates"])
                    row["quality_accepted"] = c["label"]
                    row["quality_weight"] = c["dirichlet_weight"]
                    row["quality_s"] = r.timings["quality_s"]
                row["optimize_s"] = r.timings["optimize_s"]
                row["finite"] = bool(torch.isfinite(r.vertex_frames).all())
            except Exception as exc:
                row["error"] = f"{type(exc).__name__}: {exc}"
                row["trace"] = traceback.format_exc(limit=3)
            _write(rows, row)
            print(json.dumps({k: row.get(k) for k in ("model", "method", "n_tets", "wall_s", "smoothness_mean_deg",
                                                      "dirichlet_energy_mean", "quality_accepted", "error")}),
                  flush=True)


def _write(path: Path, row: dict) -> None:
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(row) + "\n")


def _fmt(v) -> str:
    if isinstance(v, float):
        return "nan" if v != v else (f"{v:.4f}" if abs(v) < 1 else f"{v:.2f}")
    return str(v)


def report(out: Path) -> str:
    """Markdown: per variant, the per-model table and the set-level figures (see the module docstring)."""
    rows = [json.loads(s) for s in open(out / "rows.jsonl", encoding="utf-8")]
    by = {}
    for r in rows:
        by[(r["model"], r["method"])] = r  # the last row of a (model, method) wins
    models = list(dict.fromkeys(r["model"] for r in rows))
    methods = [m for m in dict.fromkeys(r["method"] for r in rows) if m not in ("sh", "mesh")]
    lines = []
    for meth in methods:
        lines += [f"## {meth} vs sh", "",
                  "| model | tets | " + " | ".join(SHORT) + " | s (sh→new) | worse >1% on |",
                  "|---|---|" + "---|" * (len(SHORT) + 2)]
        logm, logd, cx = [], [], [0, 0]
        valid = [0.0, 0.0, 0.0, 0.0]  # valid quarter faces, quarter faces (sh, new)
        fails, worst, n = [], {}, 0
        for name in models:
            a, b = by.get((name, "sh")), by.get((name, meth))
            if a is None or b is None:
                continue
            if "error" in a or "error" in b:
                lines.append(f"| {name} | | error: {(a.get('error') or b.get('error'))[:80]} |")
                fails.append((name, "error"))
                continue
            n += 1
            cells = [f"{_fmt(a[k])}→{_fmt(b[k])}" for k in KEYS]
            worse = [s for k, s in zip(KEYS[:5], SHORT[:5]) if b[k] > a[k] * 1.01 + 1e-12]
            if b["alignment_mean_deg"] > 0.5:
                worse.append("align>0.5")
            fc = b["feature_curve_alignment_mean_deg"]
            if fc == fc and fc > 2.0:
                worse.append("fcurve>2")
            if b["n_curves_ending_inside"] > 0:
                worse.append("end_in>0")
            fails += [(name, w) for w in worse]
            lines.append(f"| {name} | {a['n_tets']} | " + " | ".join(cells)
                         + f" | {a['wall_s']:.1f}→{b['wall_s']:.1f} | {', '.join(worse) or '—'} |")
            logm.append(math.log(b["smoothness_mean_deg"] / a["smoothness_mean_deg"]))
            logd.append(math.log(b["dirichlet_energy_mean"] / a["dirichlet_energy_mean"]))
            for k, s in (("smoothness_mean_deg", "mean"), ("dirichlet_energy_mean", "Dir")):
                ratio = b[k] / a[k]
                if ratio > worst.get(s, (0, ""))[0]:
                    worst[s] = (ratio, name)
            cx[0] += a["n_singular_faces_complex"]
            cx[1] += b["n_singular_faces_complex"]
            for i, r in enumerate((a, b)):
                q = r["n_singular_faces_quarter"]
                vf = r["singular_valid_fraction"]
                valid[2 * i] += (vf * q) if vf == vf else 0.0
                valid[2 * i + 1] += q
        if not n:
            continue
        gm, gd = math.exp(sum(logm) / n), math.exp(sum(logd) / n)
        va, vb = valid[0] / max(valid[1], 1), valid[2] / max(valid[3], 1)
        lines += ["", f"Set ({n} models): geomean mean-angle ratio {gm:.3f} (target ≤ 0.90), "
                      f"geomean Dirichlet ratio {gd:.3f} (≤ 0.97), complex singular faces {cx[1]} vs {cx[0]} "
                      f"(≤ 50%: {cx[1] <= 0.5 * cx[0]}), valid fraction {vb:.4f} vs {va:.4f} (higher: {vb > va}); "
                      f"worst ratio: " + ", ".join(f"{s} {r:.3f} ({m})" for s, (r, m) in worst.items())
                  + f"; per-model misses: {len(fails)} {fails[:20]}", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m studies.frame_quality", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--models", default="s02,s07,s09,n04,n10,n13,i01,i10,sphere_r0.17.mesh,78322_gear.2.mesh")
    r.add_argument("--variants", default="default")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--threads", type=int, default=1)
    r.add_argument("--mesh-cache", type=Path, default=None, help="folder of pickled meshes NAME.pkl (optional)")
    p = sub.add_parser("report")
    p.add_argument("out", type=Path)
    a = ap.parse_args(argv)
    if a.cmd == "run":
        import torch

        torch.set_num_threads(a.threads)
        models = all_models() if a.models == "all" else a.models.split(",")
        variants = a.variants.split(",")
        unknown = [v for v in variants if v not in VARIANTS]
        if unknown:
            raise SystemExit(f"unknown variants {unknown}; known: {list(VARIANTS)}")
        run(models, variants, a.out, cache=a.mesh_cache)
    else:
        print(report(a.out))


if __name__ == "__main__":
    main()
