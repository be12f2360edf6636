"""The integrable-frames stage (issue 31, step 2) on HexMe ``c`` models: the hex stage with and without it.

    python -m benchmarks.integrable --out OUT [--models s,n] [--field sh|connection] [--fields DIR]
        [--rounds] [--timeout 1800] [--threads 1]

For every model, one frame field (per-vertex frames): ``sh`` is the SH baseline
(``design(mesh, "sh_baseline").vertex_frames``), ``connection`` the jobs' default field
(:func:`benchmarks.frames_hexme.run_method`); a file ``FIELDS/<model>__<field>.npy`` (``--fields``)
is used when it exists, else the field is computed and saved under ``OUT/fields/``. Then
:func:`torchconn.hexmesh.hex_mesh` twice, ``integrable=False`` (``base``) and ``integrable=True``,
each in a child process (``--timeout`` seconds, ``--threads`` torch threads), each writing
``OUT/<model>__<field>__<variant>.json``: the gates (structure, frames, seamless, quantization), the
least-squares map's inverted tets, the inverted tets left by the foldover-free solve, the map's
validity, the verdict (good), the hex quality (scaled Jacobian min/mean, irregular edges,
Hausdorff distance / diagonal), the hexes, the times (map stage, the integrable stage) and the
stage's per-round figures (torsion, coframes). With ``--rounds`` the integrable run also solves the
least-squares seamless map on each round's coframes and counts its inverted tets (``map_inverted``
per round: what the round does to the seamless map; one more sparse solve per round).

A run whose file exists is skipped (``--force`` reruns). The summary table (markdown, both variants
side by side) is printed and written to ``OUT/summary.md``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

SIMPLE = ("s01c_cube", "s02c_prism", "s03c_pentagon", "s04c_tetrahedron", "s05c_cube_sphere", "s06c_dodecahedron",
          "s07c_notch", "s08c_cross_cyls_dr", "s09c_bridge", "s10c_cyl_cutsphere", "s11c_cube_cyl",
          "s12c_cube_rounded_1", "s13c_cube_rounded_2", "s14c_cube_corner_sub_sphere", "s15c_cylinder",
          "s16c_torus", "s17c_sphere")
NASTY = ("n01c_cross_cyls_sr", "n02c_skijump_anti_box_cyl", "n03c_skijump_box_cyl", "n04c_transition_prism",
         "n05c_box_min_pcyls", "n06c_anti_pentapyr", "n07c_anti_pyramid", "n08c_pentapyr", "n09c_pyramid",
         "n10c_qtorus_cyl", "n11c_limit_cycle", "n12c_limit_cycle_genus0", "n13c_acute_line", "n14c_octahedron",
         "n15c_icosahedron")
VARIANTS = ("base", "integrable")


def _frames(model: str, field: str, fields: Path | None, out: Path):
    import numpy as np
    import torch

    from benchmarks.frames_hexme import load_case

    mesh = load_case("hexme", model)
    for d in ([fields] if fields else []) + [out / "fields"]:
        p = d / f"{model}__{field}.npy"
        if p.is_file():
            return mesh, torch.as_tensor(np.load(p)), None
    t0 = time.perf_counter()
    if field == "sh":
        from torchconn.frames.design import design

        F = design(mesh, "sh_baseline").vertex_frames
    else:
        from benchmarks.frames_hexme import run_method

        F = run_method(field, mesh)
    s = time.perf_counter() - t0
    (out / "fields").mkdir(parents=True, exist_ok=True)
    np.save(out / "fields" / f"{model}__{field}.npy", F.detach().cpu().numpy())
    return mesh, F, s


def _with_round_maps(records: list):
    """Wrap :func:`torchconn.hexmesh.integrable.integrable_frames` so that each round's coframes are
    also fitted by the least-squares seamless map (its inverted tets appended to ``records``)."""
    import numpy as np

    import torchconn.hexmesh.integrable as integ
    from torchconn.hexmesh.injective import DET_SAFE, TetJacobians
    from torchconn.hexmesh.quantize import solve_fixed

    orig = integ.integrable_frames

    def wrapped(mesh, charts, prob, **kw):
        h = prob.edge_length
        Fr = charts.frames
        field_cof = np.transpose(Fr, (0, 2, 1)) / h

        def cb(k, B):
            t0 = time.perf_counter()
            ok = np.linalg.det(h * B @ Fr) > DET_SAFE  # the stage's fallback (IntegrableFrames.targets)
            p = prob.with_targets(np.where(ok[:, None, None], B, field_cof))
            A, b, _ = p.energy_matrices()
            y = solve_fixed(A, b, np.zeros_like(p.free_is_int), np.zeros(0))
            det = np.linalg.det(TetJacobians.of_problem(p)(y))
            records.append({"round": k, "map_inverted": int((det <= 0).sum()), "seconds": time.perf_counter() - t0})

        return orig(mesh, charts, prob, callback=cb, **kw)

    integ.integrable_frames = wrapped


def run_one(model: str, field: str, variant: str, out: Path, fields: Path | None, rounds: bool) -> dict:
    import torch

    from torchconn.hexmesh import hex_mesh

    mesh, F, field_s = _frames(model, field, fields, out)
    round_maps = []
    if variant == "integrable" and rounds:
        _with_round_maps(round_maps)
    t0 = time.perf_counter()
    r = hex_mesh(mesh, F, integrable=(variant == "integrable"))
    wall = time.perf_counter() - t0
    m = r.map
    q = r.quality
    st = m.stats
    inj = st["seamless"].get("injective")
    rec = {
        "model": model, "field": field, "variant": variant, "tets": int(mesh.n_tets), "map_tets": int(m.mesh.n_tets),
        "gates": {k: bool(g.passed) for k, g in m.gates.items()},
        "gate_reasons": {k: list(g.reasons)[:3] for k, g in m.gates.items() if not g.passed},
        "ls_inverted": int(st["seamless"]["inverted_least_squares"]),
        "injective_inverted": None if inj is None else int(inj["inverted_after"]),
        "valid": bool(r.validity.valid), "good": bool(r.good), "inverted_final": int(r.validity.counts.get("inverted_tets", 0)),
        "hexes": int(r.hexes.shape[0]),
        "sj_min": None if q is None else float(q.sj_min), "sj_mean": None if q is None else float(q.sj_mean),
        "irregular": None if q is None else q.as_dict().get("irregular_fraction"),
        "hausdorff": None if q is None else q.as_dict().get("hausdorff_rel"),
        "verdict": r.verdict()["text"], "seconds": wall, "field_s": field_s,
        "timings": {k: float(v) for k, v in st.get("timings", {}).items()},
        "integrable": st.get("integrable"), "round_maps": round_maps, "threads": torch.get_num_threads(),
    }
    return rec


def _fmt(x, nd=3):
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:.{nd}g}"
    return str(x)


def summary(out: Path, models, field: str) -> str:
    rows = ["| model | variant | map tets | structure | frames | LS inverted | after untangling | seamless | valid | good "
            "| SJ min | SJ mean | irregular | Hausdorff | hexes | map s | frames s | torsion max (start -> end) |",
            "|" + "---|" * 18]
    tally = {v: {"valid": 0, "good": 0, "seamless": 0, "n": 0} for v in VARIANTS}
    for model in models:
        for v in VARIANTS:
            p = out / f"{model}__{field}__{v}.json"
            if not p.is_file():
                continue
            d = json.loads(p.read_text())
            if "error" in d:
                rows.append(f"| {model} | {v} | error: {d['error'][:80]} |" + " |" * 16)
                continue
            g = d["gates"]
            integ = d.get("integrable") or {}
            tors = "–"
            if integ:
                tors = f"{integ['start']['torsion_max']:.3g} -> {integ['rounds'][-1]['torsion_max']:.3g}" if integ["rounds"] else "–"
            t = tally[v]
            t["n"] += 1
            t["valid"] += d["valid"]
            t["good"] += d["good"]
            t["seamless"] += g.get("seamless", False)
            rows.append("| " + " | ".join([model, v, _fmt(d["map_tets"]), _fmt(g.get("structure")), _fmt(g.get("frames")),
                                           _fmt(d["ls_inverted"]), _fmt(d["injective_inverted"]), _fmt(g.get("seamless")),
                                           _fmt(d["valid"]), _fmt(d["good"]), _fmt(d["sj_min"]), _fmt(d["sj_mean"]),
                                           _fmt(d["irregular"]), _fmt(d["hausdorff"]), _fmt(d["hexes"]),
                                           _fmt(d["timings"].get("seamless_s", 0) + d["timings"].get("quantization_s", 0)
                                                + d["timings"].get("integrable_s", 0), 3),
                                           _fmt(d["timings"].get("integrable_s")), tors]) + " |")
    rows.append("")
    for v, t in tally.items():
        rows.append(f"* {v}: {t['n']} models, valid seamless maps {t['seamless']}, valid maps {t['valid']}, "
                    f"good hex meshes {t['good']}")
    return "\n".join(rows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--models", default="s,n", help="prefixes (s, n, s05c, ...) or full names, comma-separated")
    ap.add_argument("--field", default="sh", choices=("sh", "connection"))
    ap.add_argument("--fields", type=Path, default=None, help="a folder of <model>__<field>.npy per-vertex frames")
    ap.add_argument("--rounds", action="store_true", help="the least-squares map of every round's coframes")
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--one", nargs=2, metavar=("MODEL", "VARIANT"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    if a.one:
        import torch

        torch.set_num_threads(a.threads)
        model, variant = a.one
        rec = run_one(model, a.field, variant, a.out, a.fields, a.rounds)
        (a.out / f"{model}__{a.field}__{variant}.json").write_text(json.dumps(rec, indent=1))
        return
    prefixes = [p.strip() for p in a.models.split(",") if p.strip()]
    models = list(dict.fromkeys(m for p in prefixes for m in SIMPLE + NASTY if m.startswith(p)))  # in the given order
    for model in models:
        for v in VARIANTS:
            path = a.out / f"{model}__{a.field}__{v}.json"
            if path.is_file() and not a.force:
                continue
            cmd = [sys.executable, "-m", "benchmarks.integrable", "--out", str(a.out), "--field", a.field,
                   "--threads", str(a.threads), "--one", model, v] + (["--rounds"] if a.rounds else []) \
                + (["--fields", str(a.fields)] if a.fields else [])
            t0 = time.perf_counter()
            try:
                p = subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout)
                err = None if p.returncode == 0 else (p.stderr.strip().splitlines() or ["exit %d" % p.returncode])[-1]
            except subprocess.TimeoutExpired:
                err = f"timeout after {a.timeout:g} s"
            if err is not None:
                path.write_text(json.dumps({"model": model, "variant": v, "error": err,
                                            "seconds": time.perf_counter() - t0}))
            print(f"{model} {v}: {'ok' if err is None else err} ({time.perf_counter() - t0:.0f} s)", flush=True)
    text = summary(a.out, models, a.field)
    (a.out / "summary.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
