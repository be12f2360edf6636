"""LMFF's local conditions before and after the repair of the singular graph, per HexMe model.

For every model: the field (``sh``: the SH baseline of ``design``; ``connection``: the jobs'
default, :func:`benchmarks.frames_hexme.run_method`), one frame per tet, the matching search of
the map stage (:func:`torchconn.hexmesh.straighten.straighten_singular_edges`, boundary moves on),
then :func:`torchconn.hexmesh.repair.repair_singular_graph`; the conditions are those of
:func:`torchconn.hexmesh.meshability.meshability_report` on the mesh the map would see (after
:func:`torchconn.hexmesh.split.split_for_map`), before and after. With ``--map`` the map stage
runs too (:func:`torchconn.hexmesh.hex_mesh`): on the field as the jobs mesh it, and on the
repaired matchings (given to the map as its straightened ones, :func:`given_matchings`) with the
frames re-optimized by the connection with those matchings fixed
(:func:`torchconn.frames.fixed_holonomy.fixed_holonomy_frames`) and with the input frames.

    python -m benchmarks.structures --method sh --out OUT [--models s n i] [--map] [--rounds 30] [--slide]
    python -m benchmarks.structures --set shared --models 78322_gear.2 fandisk --out OUT

Writes ``OUT/<model>__<method>.json`` per model (kept: a rerun skips them) and prints one line
per model; ``OUT/summary.json`` has the counts per category. Fields are read from ``--fields DIR``
(``DIR/<model>__<method>.npy``, per-vertex frames ``(V, 3, 3)``) where there, else computed and
cached in ``OUT/fields/`` (pickles of this process's own making).
"""
from __future__ import annotations

import argparse
import json
import pickle
import time
from pathlib import Path

CONDS = ("complex_edges", "zipper_nodes", "invalid_nodes", "surface_valence2_edges")


def _field(model: str, method: str, cache: Path, set_name: str = "hexme", fields: Path | None = None):
    import numpy as np
    import torch

    from benchmarks.frames_hexme import load_case, run_method
    from torchconn.hexmesh.inputs import tet_frames_of

    if fields is not None and (fields / f"{model}__{method}.npy").is_file():
        mesh = load_case(set_name, model)
        return mesh, tet_frames_of(mesh, torch.as_tensor(np.load(fields / f"{model}__{method}.npy"))), None
    path = cache / f"{model}__{method}.pkl"
    if path.is_file():
        d = pickle.loads(path.read_bytes())
        return d["mesh"], torch.as_tensor(d["tet_frames"]), d["field_s"]
    mesh = load_case(set_name, model)
    t0 = time.perf_counter()
    if method == "sh":
        from torchconn.frames.design import design

        F = design(mesh, "sh_baseline").vertex_frames
    else:
        F = run_method(method, mesh)
    Fr = tet_frames_of(mesh, F)
    field_s = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps({"mesh": mesh, "tet_frames": Fr.numpy(), "field_s": field_s}))
    return mesh, Fr, field_s


def _conditions(mesh, Fr, fm) -> dict:
    from torchconn.hexmesh.meshability import meshability_report
    from torchconn.hexmesh.split import split_for_map

    sr = split_for_map(mesh, Fr, fm)
    return meshability_report(sr.mesh, sr.tet_frames, sr.face_match).counts()


def _map(mesh, F, face_match=None, **kw) -> dict:
    """One run of the hex stage: its verdict, gates, quality and time."""
    from torchconn.hexmesh import hex_mesh

    t0 = time.perf_counter()
    r = hex_mesh(mesh, F, face_match=face_match, **kw)
    q = r.quality
    st = r.map.stats
    out = {"valid": bool(r.validity.valid), "good": bool(r.good), "meshable": bool(r.meshability.meshable),
           "first_failed": r.first_failed, "gates": {k: g.passed for k, g in r.gates.items()},
           "structure": r.gates["structure"].counts, "conditions": r.meshability.counts(),
           "inverted_tets": int(r.validity.counts.get("inverted_tets", 0)),
           "seamless_inverted": st["seamless"].get("injective", {}) and st["seamless"]["injective"]["inverted_after"],
           "hexes": int(r.hexes.shape[0]), "sj_min": None if q is None else float(q.sj_min),
           "irregular": None if q is None else q.irregular_fraction,
           "hausdorff": None if q is None else q.hausdorff_rel,
           "corners": None if q is None else [q.n_corners_meshed, q.n_corners],
           "curves": None if q is None else [q.n_curves_meshed, q.n_curves],
           "verdict": r.verdict()["text"], "timings": st.get("timings", {}),
           "seconds": time.perf_counter() - t0}
    if "repair" in st:
        out["repair"] = st["repair"]
    return out


def run_hex(model: str, method: str, out: Path, rounds: int, set_name: str = "hexme",
            fields: Path | None = None) -> dict:
    """The hex stage on the field with ``repair=False`` and ``repair=True`` (module docstring)."""
    import torch

    torch.set_num_threads(1)
    mesh, Fr, field_s = _field(model, method, out / "fields", set_name, fields)
    kind = model[0] if set_name == "hexme" else "shared"
    rec = {"model": model, "method": method, "kind": kind, "tets": int(mesh.n_tets), "field_s": field_s}
    rec["repair_on"] = _map(mesh, Fr, repair=True, repair_rounds=rounds)
    rep = rec["repair_on"]["repair"]
    if rep["faces_changed"] == 0 and rep["splits"] == 0:
        rec["repair_off"] = {**rec["repair_on"], "same_as_repair_on": True}
    else:
        rec["repair_off"] = _map(mesh, Fr, repair=False)
    return rec


def run_model(model: str, method: str, out: Path, rounds: int, with_map: bool, set_name: str = "hexme",
              fields: Path | None = None, slide: bool = False) -> dict:
    import torch

    from torchconn.hexmesh.repair import repair_singular_graph
    from torchconn.hexmesh.straighten import straighten_singular_edges

    torch.set_num_threads(1)
    mesh, Fr, field_s = _field(model, method, out / "fields", set_name, fields)
    t0 = time.perf_counter()
    fm, _ = straighten_singular_edges(mesh, Fr, boundary_moves=True)
    straighten_s = time.perf_counter() - t0
    before = _conditions(mesh, Fr, fm)
    fm2, rep = repair_singular_graph(mesh, Fr, fm, max_rounds=rounds, slide=slide)
    after = _conditions(rep.mesh, rep.tet_frames, fm2)
    kind = model[0] if set_name == "hexme" else "shared"
    rec = {"model": model, "method": method, "kind": kind, "tets": int(mesh.n_tets), "field_s": field_s,
           "straighten_s": straighten_s, "before": before, "after": after, "repair": rep.as_dict()}
    if with_map:
        from torchconn.frames.fixed_holonomy import fixed_holonomy_frames

        rec["map_field"] = _map(mesh, Fr)
        t0 = time.perf_counter()
        fh = fixed_holonomy_frames(rep.mesh, rep.tet_frames, fm2)
        rec["fixed_holonomy"] = {"agree": fh.agree, "misfit_deg_before": fh.misfit_deg_before,
                                 "misfit_deg_after": fh.misfit_deg_after, "seconds": time.perf_counter() - t0}
        rec["fixed_holonomy"]["passes"] = fh.passes
        rec["map_repaired"] = _map(rep.mesh, fh.tet_frames, fm2)  # the re-optimized frames, the repaired matchings
        rec["map_repaired_input_frames"] = _map(rep.mesh, rep.tet_frames, fm2)  # the input frames, the repaired matchings
        rec["repaired_field_conditions"] = _conditions(rep.mesh, fh.tet_frames, None)  # the frames' own matchings
        del np
    return rec


def _strict(c: dict) -> bool:
    return all(c[k] == 0 for k in CONDS) and c["touching_edges"] == 0


def summarize(recs: list[dict]) -> dict:
    out = {}
    for kind in ("s", "n", "i", "shared"):
        rs = [r for r in recs if r["kind"] == kind]
        if not rs:
            continue
        if "repair_on" in rs[0]:
            row = {"models": len(rs)}
            for v in ("repair_off", "repair_on"):
                row[f"{v}_meshable"] = sum(r[v]["meshable"] for r in rs)
                row[f"{v}_structure"] = sum(r[v]["gates"]["structure"] for r in rs)
                row[f"{v}_valid"] = sum(r[v]["valid"] for r in rs)
                row[f"{v}_good"] = sum(r[v]["good"] for r in rs)
                row[f"{v}_seconds"] = sum(r[v]["seconds"] for r in rs)
                for k in ("corners", "curves"):
                    pairs = [r[v][k] for r in rs if r[v][k]]
                    row[f"{v}_{k}"] = [sum(p[0] for p in pairs), sum(p[1] for p in pairs)]
            out[kind] = row
            continue
        row = {"models": len(rs),
               "meshable_before": sum(r["before"]["meshable"] for r in rs),
               "meshable_after": sum(r["after"]["meshable"] for r in rs),
               "strict_before": sum(_strict(r["before"]) for r in rs),
               "strict_after": sum(_strict(r["after"]) for r in rs)}
        for k in (*CONDS, "touching_edges"):
            row[f"{k}_before"] = sum(r["before"][k] for r in rs)
            row[f"{k}_after"] = sum(r["after"][k] for r in rs)
        if all("map_repaired" in r for r in rs):
            for v in ("map_field", "map_repaired", "map_repaired_input_frames"):
                row[f"{v}_valid"] = sum(r[v]["valid"] for r in rs)
                row[f"{v}_good"] = sum(r[v]["good"] for r in rs)
        out[kind] = row
    return out


def main(argv=None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", default="sh", choices=("sh", "connection"))
    ap.add_argument("--set", default="hexme", choices=("hexme", "shared"), help="HexMe c models or the shared meshes")
    ap.add_argument("--models", nargs="*", default=None, help="name prefixes (default: every c model)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--slide", action="store_true", help="the repair also slides touching arc ends (slide=True)")
    ap.add_argument("--map", action="store_true", help="also run the map stage (minutes per model)")
    ap.add_argument("--hex", action="store_true", help="the hex stage with repair=False and repair=True instead")
    ap.add_argument("--fields", type=Path, default=None, help="a folder of <model>__<method>.npy per-vertex frames")
    a = ap.parse_args(argv)
    from benchmarks.frames_hexme import list_cases

    a.out.mkdir(parents=True, exist_ok=True)
    recs = []
    for model in list_cases(a.set, ("c",), a.models):
        path = a.out / f"{model}__{a.method}{'__hex' if a.hex else ''}.json"
        if path.is_file():
            rec = json.loads(path.read_text())
        else:
            t0 = time.perf_counter()
            if a.hex:
                rec = run_hex(model, a.method, a.out, a.rounds, a.set, a.fields)
            else:
                rec = run_model(model, a.method, a.out, a.rounds, a.map, a.set, a.fields, a.slide)
            rec["wall_s"] = time.perf_counter() - t0
            path.write_text(json.dumps(rec, indent=1, default=float))
        recs.append(rec)
        if a.hex:
            on, off = rec["repair_on"], rec["repair_off"]
            print(f"{model:30s} off: valid {off['valid']} good {off['good']} ({off['first_failed']}, {off['seconds']:.0f} s)"
                  f" | on: valid {on['valid']} good {on['good']} ({on['first_failed']}, {on['seconds']:.0f} s,"
                  f" moves {on['repair']['moves']})", flush=True)
            continue
        b, f = rec["before"], rec["after"]
        cond = lambda c: " ".join(f"{k.split('_')[0]}={c[k]}" for k in (*CONDS, "touching_edges"))  # noqa: E731
        extra = ""
        if "map_repaired" in rec:
            extra = f" | map valid: field {rec['map_field']['valid']} repaired {rec['map_repaired']['valid']}"
        print(f"{model:30s} {cond(b)} -> {cond(f)} ({rec['repair']['seconds']:.0f} s){extra}", flush=True)
    summary = summarize(recs)
    (a.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    return a.out


if __name__ == "__main__":
    main()
