"""The connection field's time against the SH field's on the same mesh, side by side in one run.

``python -m benchmarks.field_time [--set shared] [--models 78322_gear.2,fandisk] [--threads 1]``

Per mesh (``benchmarks.frames_hexme.load_case``), in one process:

* ``sh``: the SH baseline, ``design(mesh, "sh")`` (Ray, Sokolov & Lévy 2016), its defaults;
* ``connection_first``: the field the jobs mesh first, ``design_for_hex(mesh, select="proxies",
  weights={"map": 1}, starts=("sh",), quality.enabled=false)``: the SH start, the connection
  optimized with the jobs' loss (the map's fitting energy included) — what the jobs compute before
  their first hex mesh, and all they compute for the field when that mesh is good
  (:func:`torchconn.hexmesh.choose.hex_chooser` stops there);
* ``connection_all``: every candidate the chooser may ask for, ``design_for_hex(mesh,
  select="proxies", weights={"map": 1})`` (both starts, the quality paths, the repair): the
  field's cost when no candidate meshes well (the chooser then also meshes up to 8 of them).

Prints one row per (mesh, field) with the wall seconds (``wall_s``, around the call), the ratio to
``sh``'s and ``design()``'s own timings (``design_*``); writes them to ``--out`` (JSON) when given.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

FIELDS = ("sh", "connection_first", "connection_all")


def run_field(field: str, mesh):
    from torchconn.frames.design import design
    from torchconn.hexmesh.choose import design_for_hex

    if field == "sh":
        return design(mesh, "sh")
    if field == "connection_first":
        return design_for_hex(mesh, "connection", select="proxies", weights={"map": 1.0}, starts=["sh"],
                              quality={"enabled": False})
    if field == "connection_all":
        return design_for_hex(mesh, "connection", select="proxies", weights={"map": 1.0})
    raise ValueError(f"unknown field {field!r}; known: {list(FIELDS)}")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="shared", choices=("shared", "hexme"))
    ap.add_argument("--models", default="78322_gear.2")
    ap.add_argument("--fields", default=",".join(FIELDS))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from .frames_hexme import load_case

    fields = [f for f in args.fields.split(",") if f]
    bad = [f for f in fields if f not in FIELDS]
    if bad:
        raise SystemExit(f"unknown field(s) {bad}; known: {list(FIELDS)}")
    rows = []
    for name in [m for m in args.models.split(",") if m]:
        mesh = load_case(args.set, name)
        base = None
        for field in fields:
            t0 = time.perf_counter()
            res = run_field(field, mesh)
            wall = time.perf_counter() - t0
            base = wall if field == "sh" else base
            row = {"model": name, "tets": int(mesh.n_tets), "field": field, "wall_s": round(wall, 2),
                   "ratio_to_sh": None if base is None else round(wall / base, 2),
                   "threads": args.threads,
                   **{f"design_{k}": (round(v, 2) if isinstance(v, float) else v) for k, v in res.timings.items()}}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
