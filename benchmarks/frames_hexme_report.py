"""Aggregation of :mod:`benchmarks.frames_hexme`: job files -> CSV, markdown table, ratio plot.

    python -m benchmarks.frames_hexme --aggregate-only --out DIR      (or aggregate(DIR))

Reads every ``DIR/jobs/*.json`` (whatever has finished: a partial sweep aggregates too) and writes

* ``DIR/results.csv``: one row per (model, method), the columns :data:`CSV_COLUMNS` (every key of
  :data:`torchconn.frames.metrics.METRIC_KEYS`, the mesh size, the times, the peak memory and
  ``error``, empty for a run that finished);
* ``DIR/results.md``: the per-model rows; the set-level figures of every method against the SH
  baseline (geometric means over the models where both finished of the ratios of the mean
  angle, RMS angle and Dirichlet energy, and of ``(n + 1) / (n_sh + 1)`` for the singular-face
  counts, which can be 0; totals of complex-type singular faces; the total valid fraction
  ``sum(valid quarter faces) / sum(quarter faces)``; times); the worst model per metric; the
  issue's targets, each marked held / not held per method (:func:`targets`);
* ``DIR/ratios.png``: per-model ratio to the baseline, one panel per metric of :data:`RATIO_METRICS`.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from torchconn.frames.metrics import METRIC_KEYS

BASELINE = "sh"
ID_COLUMNS = ("set", "model", "kind", "method", "n_vertices", "n_tets")
TIME_COLUMNS = ("mesh_s", "method_s", "metrics_s", "wall_s", "peak_rss_mb")
#: The hex stage's columns (benchmarks.frames_hexme.hex_stage).
GATES = ("structure", "seamless", "quantization", "extraction")
HEX_COLUMNS = ("hex_valid", "hex_good", "hex_first_failed", *(f"hex_gate_{g}" for g in GATES), "hex_meshable",
               "hex_first_check", "hex_inverted_tets", "hex_degenerate_tets",
               "hex_complex_edges", "hex_n", "hex_dropped", "hex_sj_min", "hex_sj_mean", "hex_irregular", "hex_hausdorff",
               "hex_volume_ratio", "hex_corners_meshed", "hex_corners", "hex_curves_meshed", "hex_curves",
               "hex_edge_length", "hex_map_tets", "hex_s", "end_to_end_s", "hex_reason", "hex_not_good", "hex_error")
CSV_COLUMNS = ID_COLUMNS + tuple(METRIC_KEYS) + TIME_COLUMNS + HEX_COLUMNS + ("error",)
#: HexMe categories by the model name's first letter.
CATEGORIES = {"s": "simple", "n": "nasty", "i": "industrial"}
#: The anchors of HEXMESH.md: valid integer-grid maps of Locally Meshable Frame Fields (Liu & Bommes
#: 2023) per category, counted from the published meshes; features meshed by the HexMe paper's
#: pipeline (SH field, greedy rounding, HexEx) over all 189 inputs.
ANCHOR_LMFF_VALID = {"simple": 0.94, "nasty": 0.60, "industrial": 0.37}
ANCHOR_HEXME_FEATURES = {"corners": 0.709, "curves": 0.485}
#: Metrics compared as ratios to the baseline (lower is better): key -> label.
RATIO_METRICS = {
    "smoothness_mean_deg": "mean angle",
    "smoothness_rms_deg": "RMS angle",
    "dirichlet_energy_mean": "Dirichlet",
    "n_singular_faces": "singular faces",
    "n_singular_faces_complex": "complex faces",
}
_COUNTS = ("n_singular_faces", "n_singular_faces_complex")
#: Round-off floors of the ratios: a value below its floor counts as the floor, so two fields that
#: are both exact to round-off (a cube's constant field: 1e-8 degrees against 1e-9) have ratio 1.
FLOORS = {"smoothness_mean_deg": 1e-3, "smoothness_rms_deg": 1e-3, "dirichlet_energy_mean": 1e-9}
#: Per-model table columns: key -> header.
TABLE = {
    "n_tets": "tets",
    "smoothness_mean_deg": "mean °",
    "smoothness_rms_deg": "RMS °",
    "dirichlet_energy_mean": "Dirichlet",
    "n_singular_faces": "sing. faces",
    "n_singular_faces_complex": "complex",
    "n_curves_ending_inside": "ending inside",
    "singular_valid_fraction": "valid frac.",
    "alignment_mean_deg": "bnd align °",
    "feature_curve_alignment_mean_deg": "feat. curve °",
    "wall_s": "wall s",
    "peak_rss_mb": "peak MB",
}


def load_rows(out: Path) -> list[dict]:
    rows = []
    for p in sorted((Path(out) / "jobs").glob("*.json")):
        try:
            rec = json.loads(p.read_text())
        except (OSError, ValueError) as exc:
            rec = {"model": p.stem, "method": "?", "error": f"unreadable result file: {exc}"}
        rows.append(_chooser_hex_s(rec))
    return rows


def _chooser_hex_s(rec: dict) -> dict:
    """A row whose hex mesh the connection method's chooser made (``hex_from_chooser``): its
    ``hex_s`` is that mesh's own hex stage time (``hex_times["total_s"]``, as measured when it was
    made), also in result files written before :func:`benchmarks.frames_hexme.hex_stage` said so
    (they hold the seconds of reading the columns)."""
    total = (rec.get("hex_times") or {}).get("total_s")
    if rec.get("hex_from_chooser") and total is not None:
        rec["hex_s"] = float(total)
    return rec


def ok(r: dict | None) -> bool:
    return r is not None and not r.get("error")


def _f(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _fmt(v, digits: int = 3) -> str:
    if v is None or v == "":
        return "–"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):
        return str(v)
    x = _f(v)
    if math.isnan(x):
        return "–"
    return f"{x:.{digits}g}" if abs(x) < 1000 else f"{x:.0f}"


def _gmean(xs: list[float]) -> float:
    xs = [x for x in xs if x > 0 and math.isfinite(x)]
    return math.exp(sum(map(math.log, xs)) / len(xs)) if xs else float("nan")


def ratio(key: str, r: dict, b: dict) -> float:
    x, y = _f(r.get(key)), _f(b.get(key))
    if key in _COUNTS:
        return (x + 1.0) / (y + 1.0)
    lo = FLOORS.get(key, 0.0)
    x, y = max(x, lo), max(y, lo)
    return x / y if y > 0 else float("nan")


def by_model(rows: list[dict]) -> tuple[list[str], list[str], dict]:
    models = sorted({r["model"] for r in rows})
    order = ["sh", "mbo", "connection", "mouette"]
    methods = sorted({r["method"] for r in rows}, key=lambda m: (order.index(m) if m in order else 9, m))
    table = {(r["model"], r["method"]): r for r in rows}
    return models, methods, table


def set_figures(rows: list[dict]) -> dict:
    """``{method: {...}}``: geometric-mean ratios, totals and times against the baseline."""
    models, methods, t = by_model(rows)
    res = {}
    for m in methods:
        done = [x for x in models if ok(t.get((x, m)))]
        pairs = [(t[(x, m)], t[(x, BASELINE)]) for x in done if ok(t.get((x, BASELINE)))]
        fig = {"models": len(models), "finished": len(done), "compared": len(pairs),
               "failed": [x for x in models if (x, m) in t and not ok(t[(x, m)])]}
        for key in RATIO_METRICS:
            fig[f"gmean_ratio_{key}"] = _gmean([ratio(key, r, b) for r, b in pairs])
        fig["total_complex"] = sum(int(_f(r.get("n_singular_faces_complex"))) for r, _ in pairs)
        fig["total_complex_baseline"] = sum(int(_f(b.get("n_singular_faces_complex"))) for _, b in pairs)
        fig["total_singular"] = sum(int(_f(r.get("n_singular_faces"))) for r, _ in pairs)

        def valid(rs):
            q = sum(_f(r.get("n_singular_faces_quarter")) for r in rs)
            v = sum(_f(r.get("n_singular_faces_quarter")) * _f(r.get("singular_valid_fraction"))
                    for r in rs if _f(r.get("n_singular_faces_quarter")) > 0)
            return v / q if q > 0 else float("nan")

        fig["valid_fraction"] = valid([r for r, _ in pairs])
        fig["valid_fraction_baseline"] = valid([b for _, b in pairs])
        walls = [_f(t[(x, m)].get("wall_s")) for x in done]
        fig["wall_total_s"] = sum(walls)
        fig["wall_max_s"] = max(walls) if walls else float("nan")
        mems = [_f(t[(x, m)].get("peak_rss_mb")) for x in done]
        mems = [x for x in mems if math.isfinite(x)]
        fig["peak_rss_max_mb"] = max(mems) if mems else float("nan")
        res[m] = fig
    return res


def _model_checks(r: dict, b: dict) -> dict[str, bool]:
    """The issue's per-model targets of one run against the baseline run (True = held)."""
    c = {
        "boundary alignment mean ≤ 0.5°": _f(r.get("alignment_mean_deg")) <= 0.5
        or math.isnan(_f(r.get("alignment_mean_deg"))),
        "feature-curve alignment mean ≤ 2°": not (_f(r.get("feature_curve_alignment_mean_deg")) > 2.0),
        "no singular curve ending inside": int(_f(r.get("n_curves_ending_inside"))) == 0,
    }
    for key, label in RATIO_METRICS.items():
        c[f"{label} ≤ 1% worse than SH"] = ratio(key, r, b) <= 1.01 if key not in _COUNTS else \
            _f(r.get(key)) <= 1.01 * _f(b.get(key))
    return c


def targets(rows: list[dict], figs: dict, method: str) -> list[tuple[str, bool | None, str]]:
    """``[(target, held, measured)]`` of the issue for ``method`` against the SH baseline."""
    models, _, t = by_model(rows)
    out = []
    failed = [x for x in models if (x, method) in t and not ok(t[(x, method)])]
    missing = [x for x in models if (x, method) not in t]
    gaps = (f"; failed: {', '.join(failed[:6])}" if failed else "") + (f"; not run: {len(missing)}" if missing else "")
    out.append(("every model finishes (no crash, no NaN)", not failed and not missing and bool(models),
                f"{len(models) - len(failed) - len(missing)}/{len(models)}" + gaps))
    pairs = {x: (t[(x, method)], t[(x, BASELINE)]) for x in models
             if ok(t.get((x, method))) and ok(t.get((x, BASELINE)))}
    if pairs:
        checks = {x: _model_checks(r, b) for x, (r, b) in pairs.items()}
        incomplete = len(models) - len(pairs)
        for name in next(iter(checks.values())):
            bad = [x for x, c in checks.items() if not c[name]]
            text = f"{len(pairs) - len(bad)}/{len(pairs)} compared"
            if bad:
                text += f"; not: {', '.join(bad[:5])}" + (" …" if len(bad) > 5 else "")
            if incomplete:
                text += f"; {incomplete} without a comparison"
            out.append((f"every model: {name}", not bad and not incomplete, text))
    f = figs.get(method, {})
    g1, g2 = f.get("gmean_ratio_smoothness_mean_deg", float("nan")), f.get("gmean_ratio_dirichlet_energy_mean", float("nan"))
    out.append(("set: geometric mean of the mean-angle ratio ≤ 0.90", g1 <= 0.90, _fmt(g1, 4)))
    out.append(("set: geometric mean of the Dirichlet ratio ≤ 0.97", g2 <= 0.97, _fmt(g2, 4)))
    tc, tb = f.get("total_complex", 0), f.get("total_complex_baseline", 0)
    out.append(("set: complex-type singular faces ≤ 50% of the baseline's", tc <= 0.5 * tb, f"{tc} vs {tb}"))
    v, vb = f.get("valid_fraction", float("nan")), f.get("valid_fraction_baseline", float("nan"))
    out.append(("set: higher valid fraction than the baseline (total)", v > vb, f"{_fmt(v, 4)} vs {_fmt(vb, 4)}"))
    small = [x for x in models if ok(t.get((x, method))) and _f(t[(x, method)].get("n_tets")) <= 200_000]
    slow = [x for x in small if _f(t[(x, method)].get("wall_s")) > 60.0]
    out.append(("time: ≤ 60 s end to end per model up to 200k tets", not slow and bool(small),
                f"max {_fmt(max([_f(t[(x, method)].get('wall_s')) for x in small] or [float('nan')]), 3)} s"
                + (f"; over: {', '.join(slow[:5])}" if slow else "")))
    cset = [x for x in models if len(x) > 3 and x[3] == "c" and x[0] in "sni"]
    if cset:
        tot = sum(_f(t[(x, method)].get("wall_s")) for x in cset if ok(t.get((x, method))))
        complete = all(ok(t.get((x, method))) for x in cset)
        out.append(("time: the s-, n-, i- `c` meshes together ≤ 10 min", complete and tot <= 600.0,
                    f"{tot:.0f} s over {len(cset)} models" + ("" if complete else " (not all finished)")))
    return out


def category(model: str) -> str:
    return CATEGORIES.get(model[:1], "other")


def hex_figures(rows: list[dict]) -> dict:
    """Per method and category: models, valid maps, good hex meshes, features meshed, times."""
    models, methods, t = by_model(rows)
    out = {}
    for m in methods:
        per = {}
        for x in models:
            r = t.get((x, m))
            if r is None or "hex_s" not in r and not r.get("error"):
                continue
            c = per.setdefault(category(x), {"models": 0, "valid": 0, "good": 0, "corners": 0, "corners_meshed": 0,
                                             "curves": 0, "curves_meshed": 0, "hex_s_max": 0.0, "end_to_end_s_max": 0.0,
                                             "errors": 0, **{f"gate_{g}": 0 for g in GATES}, "gated": 0})
            c["models"] += 1
            if not ok(r) or r.get("hex_error"):
                c["errors"] += 1
                continue
            c["valid"] += bool(r.get("hex_valid"))
            c["good"] += bool(r.get("hex_good"))
            if f"hex_gate_{GATES[0]}" in r:
                c["gated"] += 1
                for g in GATES:
                    c[f"gate_{g}"] += bool(r.get(f"hex_gate_{g}"))
            for k in ("corners", "corners_meshed", "curves", "curves_meshed"):
                v = r.get(f"hex_{k}")
                c[k] += int(v) if v is not None else 0
            c["hex_s_max"] = max(c["hex_s_max"], _f(r.get("hex_s")))
            c["end_to_end_s_max"] = max(c["end_to_end_s_max"], _f(r.get("end_to_end_s")))
        out[m] = per
    return out


def hex_markdown(rows: list[dict]) -> list[str]:
    models, methods, t = by_model(rows)
    hf = hex_figures(rows)
    if not any(hf[m] for m in methods):
        return []
    cats = [c for c in ("simple", "nasty", "industrial", "other") if any(c in hf[m] for m in methods)]

    def frac(a, b):
        return f"{a}/{b} ({100 * a / b:.0f}%)" if b else "–"

    L = ["", "### Hex meshes (the hex stage of every field: torchconn.hexmesh.hex_mesh, default options)", "",
         "A *good* hex mesh: a valid map, and the hex mesh valid (all hexes, none inverted, conforming, closed "
         "boundary), irregular interior edges ≤ 5%, Hausdorff distance ≤ 1% of the bounding-box diagonal.", "",
         "| method | " + " | ".join(f"valid maps: {c}" for c in cats) + " | "
         + " | ".join(f"good hex meshes: {c}" for c in cats) + " | CAD corners meshed | CAD curves meshed | "
         "hex stage max s | end to end max s |", "|---|" + "---|" * (2 * len(cats) + 4)]
    for m in methods:
        per = hf[m]
        cells = [frac(per[c]["valid"], per[c]["models"]) if c in per else "–" for c in cats]
        cells += [frac(per[c]["good"], per[c]["models"]) if c in per else "–" for c in cats]
        cm = sum(v["corners_meshed"] for v in per.values())
        cn = sum(v["corners"] for v in per.values())
        km = sum(v["curves_meshed"] for v in per.values())
        kn = sum(v["curves"] for v in per.values())
        cells += [frac(cm, cn), frac(km, kn), _fmt(max((v["hex_s_max"] for v in per.values()), default=float("nan"))),
                  _fmt(max((v["end_to_end_s_max"] for v in per.values()), default=float("nan")))]
        L.append(f"| {m} | " + " | ".join(cells) + " |")
    anchor = [f"{100 * ANCHOR_LMFF_VALID[c]:.0f}%" if c in ANCHOR_LMFF_VALID else "–" for c in cats]
    L.append("| anchor: LMFF (2023) valid maps | " + " | ".join(anchor) + " | " + " | ".join("–" for _ in cats)
             + f" | – | – | – | – |")
    L.append("| anchor: HexMe paper pipeline, features meshed (all 189 inputs) | " + " | ".join("–" for _ in cats)
             + " | " + " | ".join("–" for _ in cats)
             + f" | {100 * ANCHOR_HEXME_FEATURES['corners']:.1f}% | {100 * ANCHOR_HEXME_FEATURES['curves']:.1f}% | – | – |")
    if any(v.get("gated") for m in methods for v in hf[m].values()):
        L += ["", "### Gates: models whose stage passes (structure: LMFF's conditions and no flat tet; seamless: the "
              "map before quantization valid, checked exactly; quantization: the integer-grid map valid; extraction: "
              "every cube extracted into a valid hex mesh)", "",
              "| method | category | models | " + " | ".join(GATES) + " | good hex meshes |", "|---|---|---|" + "---|" * (len(GATES) + 1)]
        for m in methods:
            for c in cats:
                v = hf[m].get(c)
                if not v or not v.get("gated"):
                    continue
                L.append(f"| {m} | {c} | {v['gated']} | " + " | ".join(str(v[f'gate_{g}']) for g in GATES)
                         + f" | {v['good']} |")
    L += ["", "### Hex meshes per model", "",
          "| model | method | map | first failing stage | first failing check | LMFF conditions left | inverted / flat tets | "
          "hexes | SJ min | SJ mean | irregular % | Hausdorff % | corners | curves | good | hex s | why not good |",
          "|---|---|" + "---|" * 15]
    for x in models:
        for m in methods:
            r = t.get((x, m))
            if r is None or ("hex_s" not in r):
                continue
            if r.get("hex_error"):
                L.append(f"| {x} | {m} | error | {r['hex_error'][:120]} |" + " |" * 12)
                continue
            pct = lambda v: _fmt(100 * _f(v), 3) if v is not None else "–"  # noqa: E731
            mc = r.get("hex_meshability") or {}
            lmff = ", ".join(f"{k.replace('_', ' ')} {mc[k]}" for k in ("complex_edges", "zipper_nodes", "invalid_nodes",
                                                                      "surface_valence2_edges", "touching_edges")
                             if mc.get(k)) or ("none" if mc else "–")
            L.append(f"| {x} | {m} | {'valid' if r.get('hex_valid') else 'invalid'} | {r.get('hex_first_failed') or ''} | "
                     f"{r.get('hex_first_check') or ''} | "
                     f"{lmff} | "
                     f"{r.get('hex_inverted_tets', 0)} / {r.get('hex_degenerate_tets', 0)} | {r.get('hex_n', 0)} | "
                     f"{_fmt(r.get('hex_sj_min'))} | {_fmt(r.get('hex_sj_mean'))} | {pct(r.get('hex_irregular'))} | "
                     f"{pct(r.get('hex_hausdorff'))} | {r.get('hex_corners_meshed', '–')}/{r.get('hex_corners', '–')} | "
                     f"{r.get('hex_curves_meshed', '–')}/{r.get('hex_curves', '–')} | {'yes' if r.get('hex_good') else 'no'} | "
                     f"{_fmt(r.get('hex_s'))} | {(r.get('hex_not_good') or '')[:100]} |")
    return L


def markdown(rows: list[dict], options: dict | None = None) -> str:
    options = options or {}
    models, methods, t = by_model(rows)
    figs = set_figures(rows)
    L = []
    if options.get("command"):
        L += [f"Command: `{options['command']}` (started {options.get('started', '?')}; "
              f"{options.get('threads', '?')} torch threads per job).", ""]
    # set-level figures
    others = [m for m in methods if m != BASELINE]
    L += ["### Set-level figures (against the SH baseline, over the models where both finished)", "",
          "| figure | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    lines = [("models finished", lambda f: f"{f['finished']}/{f['models']}")]
    for key, label in RATIO_METRICS.items():
        extra = " ((n+1)/(n_sh+1))" if key in _COUNTS else ""
        lines.append((f"geo. mean ratio: {label}{extra}", lambda f, k=key: _fmt(f[f"gmean_ratio_{k}"], 4)))
    lines += [("total singular faces", lambda f: str(f["total_singular"])),
              ("total complex-type singular faces", lambda f: str(f["total_complex"])),
              ("total valid fraction", lambda f: _fmt(f["valid_fraction"], 4)),
              ("wall time, total s", lambda f: f"{f['wall_total_s']:.1f}"),
              ("wall time, max per model s", lambda f: _fmt(f["wall_max_s"])),
              ("peak memory, max MB", lambda f: _fmt(f["peak_rss_max_mb"]))]
    for label, fn in lines:
        L.append(f"| {label} | " + " | ".join(fn(figs[m]) for m in methods) + " |")
    # targets
    if others:
        L += ["", "### Targets of the issue (each method against the SH baseline)", "",
              "| target | " + " | ".join(others) + " |", "|---|" + "---|" * len(others)]
        tg = {m: targets(rows, figs, m) for m in others}
        for i, (name, _, _) in enumerate(tg[others[0]]):
            cells = []
            for m in others:
                row = next((x for x in tg[m] if x[0] == name), None)
                cells.append("–" if row is None else f"{'held' if row[1] else 'not held'} ({row[2]})")
            L.append(f"| {name} | " + " | ".join(cells) + " |")
        # worst model per metric
        L += ["", "### Worst model per metric (largest ratio to the SH baseline)", "",
              "| metric | " + " | ".join(others) + " |", "|---|" + "---|" * len(others)]
        for key, label in RATIO_METRICS.items():
            cells = []
            for m in others:
                rs = [(ratio(key, t[(x, m)], t[(x, BASELINE)]), x) for x in models
                      if ok(t.get((x, m))) and ok(t.get((x, BASELINE)))]
                rs = [r for r in rs if math.isfinite(r[0])]
                cells.append(f"{max(rs)[1]} ({max(rs)[0]:.3g}×)" if rs else "–")
            L.append(f"| {label} | " + " | ".join(cells) + " |")
        for key, label in (("alignment_mean_deg", "boundary alignment mean ° (max over models)"),
                           ("feature_curve_alignment_mean_deg", "feature-curve alignment mean ° (max)")):
            cells = []
            for m in others:
                rs = [(_f(t[(x, m)].get(key)), x) for x in models if ok(t.get((x, m)))]
                rs = [r for r in rs if math.isfinite(r[0])]
                cells.append(f"{max(rs)[1]} ({max(rs)[0]:.3g})" if rs else "–")
            L.append(f"| {label} | " + " | ".join(cells) + " |")
    L += hex_markdown(rows)
    # per-model rows
    L += ["", "### Per model (frame-field proxies)", "", "| model | method | " + " | ".join(TABLE.values()) + " | error |",
          "|---|---|" + "---|" * (len(TABLE) + 1)]
    for x in models:
        for m in methods:
            r = t.get((x, m))
            if r is None:
                continue
            cells = [_fmt(r.get(k)) for k in TABLE]
            L.append(f"| {x} | {m} | " + " | ".join(cells) + f" | {r.get('error') or ''} |")
    return "\n".join(L) + "\n"


def plot(rows: list[dict], path: Path) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        return None
    models, methods, t = by_model(rows)
    others = [m for m in methods if m != BASELINE]
    if not others or not models:
        return None
    fig, axes = plt.subplots(len(RATIO_METRICS), 1, figsize=(max(8, 0.28 * len(models) + 2), 2.4 * len(RATIO_METRICS)),
                             sharex=True)
    xs = range(len(models))
    for ax, (key, label) in zip(axes, RATIO_METRICS.items()):
        for k, m in enumerate(others):
            ys = [ratio(key, t[(x, m)], t[(x, BASELINE)]) if ok(t.get((x, m))) and ok(t.get((x, BASELINE)))
                  else float("nan") for x in models]
            ax.plot([i + 0.15 * (k - (len(others) - 1) / 2) for i in xs], ys, "o", ms=4, label=m)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.2g"))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%.2g"))
        ax.tick_params(axis="y", which="minor", labelsize=6)
        ax.set_ylabel(label + (" (n+1)" if key in _COUNTS else "") + "\n/ SH")
        ax.grid(True, which="both", axis="y", alpha=0.3)
    axes[0].legend(loc="upper left", ncol=len(others), fontsize=8)
    axes[-1].set_xticks(list(xs))
    axes[-1].set_xticklabels(models, rotation=90, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def aggregate(out: Path) -> dict:
    """Write ``results.csv``, ``results.md`` and ``ratios.png`` of ``out``; returns their paths."""
    out = Path(out)
    rows = load_rows(out)
    opts_path = out / "options.json"
    options = json.loads(opts_path.read_text()) if opts_path.is_file() else {}
    csv_path = out / "results.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in sorted(rows, key=lambda r: (r.get("model", ""), r.get("method", ""))):
            w.writerow({k: r.get(k, "") for k in CSV_COLUMNS})
    md = out / "results.md"
    md.write_text(markdown(rows, options))
    png = plot(rows, out / "ratios.png")
    return {"csv": csv_path, "md": md, "png": png}
