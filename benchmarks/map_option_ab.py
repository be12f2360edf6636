"""One option of the hex stage on and off, side by side, per HexMe ``c`` model: does it change the verdict?

    python -m benchmarks.map_option_ab OPTION [--models s|s05c,...] [--field sh|connection]
        [--cache DIR] [--threads 1] [--out DIR]

For each model (``--models`` prefixes; the default mesh of its ``c`` parameter file) and its field
(:func:`benchmarks.hex_stage_scale._frames`: the SH field computed once and cached in ``DIR``, or
the cached connection field), :func:`torchconn.hexmesh.hex_mesh` runs twice in this process, with
``OPTION=True`` and ``OPTION=False`` (every other option at its default, the one-ring report off:
it decides nothing), one after the other. Each row: the verdict (good hex mesh / valid map /
invalid), the first failing stage, the inverted tets of the final map, the Hausdorff distance,
the seconds of the run and of the option's own step where the map times it
(``stats["timings"][OPTION + "_s"]``), and the map's ``stats[OPTION]`` when it records one.

Output: ``DIR/map_option_ab.jsonl`` (a line per run, appended as each finishes) and
``DIR/map_option_ab.md`` (the side-by-side table and the counts of good hex meshes).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import platform
import time
from pathlib import Path

from benchmarks.hex_stage_scale import CACHE, DATA, _frames, _load


def _models(prefixes: str, data: Path) -> list[str]:
    names = sorted(p.stem for p in (data / "hexme" / "meta").glob("*c_*.yaml"))
    return [n for n in names if any(n.startswith(q) for q in prefixes.split(","))]


def run_one(model: str, option: str, value: bool, field: str, cache: str, out: str) -> dict:
    """One hex stage of ``model`` with ``option=value``: the row (errors caught)."""
    from torchconn.hexmesh import hex_mesh

    rec = {"model": model, "option": option, "value": value, "field": field}
    try:
        mesh = _load(model, None)
        F = _frames({"field": field, "cache": cache, "model": model, "out": out}, mesh)
        t0 = time.perf_counter()
        r = hex_mesh(mesh, F, one_ring=False, **{option: value})
        q = r.quality
        rec.update(good=bool(r.good), valid=bool(r.validity.valid), first_failed=r.first_failed,
                   inverted=int(r.validity.counts.get("inverted_tets", 0)),
                   hausdorff_rel=None if q is None else q.hausdorff_rel, seconds=time.perf_counter() - t0,
                   option_s=r.map.stats["timings"].get(f"{option}_s"), stats=r.map.stats.get(option))
    except Exception as exc:  # noqa: BLE001 - a failing run is a row with its error
        rec["error"] = f"{type(exc).__name__}: {exc}"[:300]
    return rec


def _verdict(r: dict | None) -> str:
    if r is None:
        return "–"
    if r.get("error"):
        return f"error: {r['error'][:60]}"
    v = "good" if r["good"] else "valid map" if r["valid"] else f"invalid ({r['first_failed']})"
    opt = f", step {r['option_s']:.1f} s" if r.get("option_s") is not None else ""
    return f"{v}, {r['inverted']} inverted, {r['seconds']:.0f} s{opt}"


def table(rows: list[dict], option: str) -> str:
    by: dict = {}
    for r in rows:
        by.setdefault(r["model"], {})[r["value"]] = r
    lines = [f"| model | {option}=True | {option}=False |", "|---|---|---|"]
    lines += [f"| {m} | {_verdict(d.get(True))} | {_verdict(d.get(False))} |" for m, d in by.items()]
    good = {v: sum(bool(d.get(v, {}).get("good")) for d in by.values()) for v in (True, False)}
    lines += ["", f"Good hex meshes: {good[True]}/{len(by)} with {option}=True, {good[False]}/{len(by)} with False."]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m benchmarks.map_option_ab", description=__doc__.split("\n\n")[0])
    p.add_argument("option", help="a boolean option of torchconn.hexmesh.hex_mesh, e.g. fixed_holonomy")
    p.add_argument("--models", default="s")
    p.add_argument("--field", choices=("sh", "connection"), default="sh")
    p.add_argument("--cache", default=str(CACHE))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="map_option_ab_out")
    a = p.parse_args(argv)
    from torchconn.hexmesh.pipeline import MAP_OPTIONS

    if a.option not in MAP_OPTIONS:
        p.error(f"unknown option {a.option!r}; known: {', '.join(MAP_OPTIONS)}")
    import torch

    torch.set_num_threads(a.threads)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for model in _models(a.models, DATA):
        for value in (True, False):
            rec = run_one(model, a.option, value, a.field, a.cache, str(out))
            rows.append(rec)
            with open(out / "map_option_ab.jsonl", "a") as f:
                f.write(json.dumps(rec, default=str) + "\n")
            print(f"{model} {a.option}={value}: {_verdict(rec)}", flush=True)
    head = (f"# {a.option} on and off, {a.field} fields\n\n{_dt.date.today().isoformat()}, "
            f"`python -m benchmarks.map_option_ab {a.option} --models {a.models} --field {a.field} --threads {a.threads}`, "
            f"{platform.processor() or platform.machine()}, {a.threads} thread(s).\n\n")
    (out / "map_option_ab.md").write_text(head + table(rows, a.option) + "\n")


if __name__ == "__main__":
    main()
