"""Convergence study of the report's discrete curvature, torsion and d∇d∇θ (report Secs. 3.4, 4, 5).

Usage (Hydra; config ``configs/convergence.yaml``)::

    python -m training.convergence                                   # the whole study
    python -m training.convergence experiment=report                 # main series only
    python -m training.convergence cases=[A,B] quantities=[torsion_sqrt] levels=8 \\
        transport=path_ordered reference_point=centroid dtype=float32 connection=wave \\
        output_dir=/tmp/conv

Outputs in ``output_dir`` (default: Hydra's run directory ``outputs/convergence/<date>/<time>``; with
``output_dir`` given nothing is written under the working directory), all written atomically:

* ``convergence.csv`` -- ``case,quantity,level,h,error``, one row per case × quantity × level
  of the main series (floats with full precision, ``repr``);
* ``slopes.csv`` -- ``case,quantity,slope``: least-squares slope of ``log error`` against
  ``log h`` over ``fit_levels`` (docs/conventions.md §3: 7..12);
* ``convergence_<case>.png`` -- log-log error plots in the style of Figs. 3.3-3.6, 4.3, 5.1,
  fitted slopes in the legend;
* ``variants/<name>/`` -- the same three kinds of files for each entry of ``variants``
  (``path_ordered``: path-ordered transports; ``centroid``: smooth reference at the centroid);
* ``mesh_convergence.csv`` (``level,h,cells,quantity,kind,mean_error,p95_error,max_error,min_quality``) and
  ``mesh_slopes.csv`` (``quantity,kind,slope_mean,slope_p95,slope_max``) -- per-cell errors on a refined
  tetrahedral ball, when ``mesh.enabled``;
* ``summary.md`` -- for every quantity whether the report's claim (converges: slope >= 0.9 /
  does not: slope <= 0.2) is reproduced in every case, for the main series and every variant
  (and whether the variant changes any conclusion), plus the mesh table;
* ``config.yaml`` -- the resolved configuration.

``train(cfg) -> dict`` is the plain function; :func:`main` is the thin Hydra wrapper.
"""
from __future__ import annotations

import io
import time
from pathlib import Path

import torch

from . import experiments as E
from .io_utils import atomic_write, atomic_write_text, check_output_dir

__all__ = ["train", "main", "KNOWN_KEYS", "VARIANTS"]

#: Top-level configuration keys ``train`` understands (``hydra`` is ignored).
KNOWN_KEYS = frozenset({
    "connection", "cases", "quantities", "transport", "reference_point", "dtype", "levels",
    "fit_levels", "path_ordered_steps", "variants", "thresholds", "plots", "mesh", "output_dir",
})
MESH_KEYS = frozenset({"enabled", "levels", "radius", "edge_length", "center", "fit_levels", "chunk"})
#: Variant name -> the setting it changes relative to the main series.
VARIANTS = {"path_ordered": {"transport": "path_ordered"}, "centroid": {"reference_point": "centroid"}}
DTYPES = {"float64": torch.float64, "float32": torch.float32}

_PLOT_GROUPS = (("torsion", "torsion (Figs. 3.3-3.5)"), ("curvature", "curvature (Fig. 3.6)"),
                ("ddtheta", "d∇d∇θ - Ω∧θ (Figs. 4.3, 5.1)"))


# ----------------------------------------------------------------------------- config
def _get(cfg, key, default=None):
    return cfg.get(key, default) if hasattr(cfg, "get") else getattr(cfg, key, default)


def _plain(cfg) -> dict:
    """A plain ``dict`` of the configuration (OmegaConf containers resolved), without ``hydra``."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            cfg = OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # plain dicts work without OmegaConf
        pass
    out = dict(cfg)
    out.pop("hydra", None)
    return out


def _validate(cfg: dict) -> dict:
    """Check every key and value before anything is computed; return normalized settings."""
    unknown = sorted(set(cfg) - KNOWN_KEYS)
    if unknown:
        raise ValueError(f"unknown config keys {unknown}; known: {sorted(KNOWN_KEYS)}")
    mesh = dict(cfg.get("mesh") or {})
    bad = sorted(set(mesh) - MESH_KEYS)
    if bad:
        raise ValueError(f"unknown config keys mesh.{bad}; known: {sorted(MESH_KEYS)}")
    s = {
        "connection": str(cfg.get("connection", "report")),
        "cases": [str(c) for c in cfg.get("cases", list(E.CASES))],
        "quantities": [str(q) for q in cfg.get("quantities", list(E.QUANTITIES))],
        "transport": str(cfg.get("transport", "midpoint")),
        "reference_point": str(cfg.get("reference_point", "vertex0")),
        "dtype": str(cfg.get("dtype", "float64")),
        "levels": cfg.get("levels", 13),
        "fit_levels": cfg.get("fit_levels", list(range(7, 13))),
        "steps": int(cfg.get("path_ordered_steps", 64)),
        "variants": [str(v) for v in (cfg.get("variants") or [])],
        "thresholds": dict(cfg.get("thresholds") or {"converge": 0.9, "diverge": 0.2}),
        "plots": bool(cfg.get("plots", True)),
        "mesh": mesh,
        "output_dir": cfg.get("output_dir"),
    }
    if s["connection"] not in E.CONNECTIONS:
        raise ValueError(f"unknown connection {s['connection']!r}; known: {sorted(E.CONNECTIONS)}")
    for key, known in (("cases", E.CASES), ("quantities", E.QUANTITIES)):
        wrong = [x for x in s[key] if x not in known]
        if wrong or not s[key]:
            raise ValueError(f"{key} must be a non-empty subset of {list(known)}, got unknown {wrong or s[key]}")
    if s["transport"] not in E.TRANSPORTS:
        raise ValueError(f"unknown transport {s['transport']!r}; known: {list(E.TRANSPORTS)}")
    if s["reference_point"] not in E.REFERENCE_POINTS:
        raise ValueError(f"unknown reference_point {s['reference_point']!r}; known: {list(E.REFERENCE_POINTS)}")
    if s["dtype"] not in DTYPES:
        raise ValueError(f"unknown dtype {s['dtype']!r}; known: {list(DTYPES)}")
    if not isinstance(s["levels"], int) or isinstance(s["levels"], bool) or s["levels"] < 2:
        raise ValueError(f"levels must be an int >= 2 (levels 0..levels-1), got {s['levels']!r}")
    wrong = [v for v in s["variants"] if v not in VARIANTS]
    if wrong:
        raise ValueError(f"unknown variants {wrong}; known: {list(VARIANTS)}")
    if set(s["thresholds"]) != {"converge", "diverge"}:
        raise ValueError(f"thresholds must have exactly the keys converge, diverge; got {sorted(s['thresholds'])}")
    if s["steps"] < 1:
        raise ValueError(f"path_ordered_steps must be >= 1, got {s['steps']}")
    if s["output_dir"] in (None, ""):
        raise ValueError("output_dir is not set (the Hydra entry point defaults it to the run directory)")
    if mesh.get("enabled", False) and int(mesh.get("levels", 0)) < 2:
        raise ValueError(f"mesh.levels must be >= 2 to fit a slope, got {mesh.get('levels')!r}")
    return s


# ----------------------------------------------------------------------------- writers
def _csv(path: Path, header: str, rows) -> None:
    lines = [header] + [",".join(x if isinstance(x, str) else repr(x) for x in r) for r in rows]
    atomic_write_text(path, "\n".join(lines) + "\n")


def _write_study(folder: Path, res: E.StudyResult, plots: bool, title: str) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    _csv(folder / "convergence.csv", "case,quantity,level,h,error",
         [(c, q, int(n), float(h), float(e)) for c, q, n, h, e in res.rows()])
    _csv(folder / "slopes.csv", "case,quantity,slope", res.slope_rows())
    files = [folder / "convergence.csv", folder / "slopes.csv"]
    if plots:
        files += _plot_cases(folder, res, title)
    return [str(f) for f in files]


def _plot_cases(folder: Path, res: E.StudyResult, title: str) -> list[Path]:
    """One log-log figure per case, one panel per family, slopes in the legend (Figs. 3.3-5.1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    h = res.h.numpy()
    groups = [(p, t) for p, t in _PLOT_GROUPS if any(q.startswith(p) for q in res.quantities)]
    for ci, case in enumerate(res.cases):
        (ang, v) = E.CASES[case]
        fig, axes = plt.subplots(1, len(groups), figsize=(5.2 * len(groups), 4.4), squeeze=False)
        for ax, (prefix, label) in zip(axes[0], groups):
            for q in res.quantities:
                if not q.startswith(prefix):
                    continue
                ax.loglog(h, res.errors[q][ci].numpy(), "o-", ms=3, label=f"{q} (slope {float(res.slopes[q][ci]):.2f})")
            ax.loglog(h, h, "k:", lw=1, label="h (slope 1)")
            ax.set_xlabel("h = 2^-n")
            ax.set_ylabel("error")
            ax.set_title(label, fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
        fig.suptitle(f"case {case}: R{ang}, v = {v}; {title}", fontsize=10)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110)
        plt.close(fig)
        path = folder / f"convergence_{case}.png"
        atomic_write(path, lambda f, b=buf.getvalue(): f.write(b))
        files.append(path)
    return files


def _verdict_table(res: E.StudyResult, th: dict) -> tuple[list[str], dict[str, bool]]:
    ver = res.verdicts(th["converge"], th["diverge"])
    head = "| quantity | report's claim | " + " | ".join(f"slope {c}" for c in res.cases) + " | reproduced in every case |"
    sep = "|" + "---|" * (3 + len(res.cases))
    lines = [head, sep]
    summary = {}
    for q in res.quantities:
        claim = f"converges (slope ≥ {th['converge']})" if E.CLAIMS[q] else f"does not converge (slope ≤ {th['diverge']})"
        ok = all(ver[q].values())
        summary[q] = ok
        failed = [c for c, v in ver[q].items() if not v]
        cell = "yes" if ok else f"**NO** (fails in {', '.join(failed)})"
        lines.append(f"| {q} | {claim} | " + " | ".join(f"{float(s):.3f}" for s in res.slopes[q]) + f" | {cell} |")
    return lines, summary


def _mesh_slopes(rows: list[dict], fit_levels) -> list[tuple[str, str, float, float, float]]:
    out = []
    for q, kind in dict.fromkeys((r["quantity"], r["kind"]) for r in rows):
        rs = [r for r in rows if r["quantity"] == q and (fit_levels is None or r["level"] in fit_levels)]
        if len(rs) < 2:
            raise ValueError(f"mesh slope of {q}: need at least two fitted levels, got {len(rs)}")
        h = torch.tensor([r["h"] for r in rs], dtype=torch.float64)
        mean = torch.tensor([r["mean_error"] for r in rs], dtype=torch.float64)
        p95 = torch.tensor([r["p95_error"] for r in rs], dtype=torch.float64)
        mx = torch.tensor([r["max_error"] for r in rs], dtype=torch.float64)
        out.append((q, kind, float(E.fit_slope(h, mean)), float(E.fit_slope(h, p95)), float(E.fit_slope(h, mx))))
    return out


def _secondary_claims(res: E.StudyResult) -> list[str]:
    """Error-constant remarks of the report, compared at the finest level of every case.

    * Sec. 3.4: the barycentric torsion (3.3.1) "converges fastest in all our tested cases";
    * Ch. 5: the primal-dual d∇d∇θ converges faster than the averaged one (Fig. 5.1).
    """
    lines = ["### Error constants at the finest level (secondary remarks of the report)", ""]
    last = -1
    tors = [q for q in ("torsion_sqrt", "torsion_sqrt_loop", "torsion_barycentric") if q in res.quantities]
    if "torsion_barycentric" in tors and len(tors) > 1:
        wins = [c for ci, c in enumerate(res.cases)
                if all(res.errors["torsion_barycentric"][ci, last] <= res.errors[q][ci, last] for q in tors)]
        lines.append(f"- Sec. 3.4, barycentric torsion has the smallest error among the converging torsions: "
                     f"cases {', '.join(wins) or 'none'} of {', '.join(res.cases)}"
                     + (" (reproduced)." if len(wins) == len(res.cases) else " (**not in every case**)."))
    if "ddtheta_averaged" in res.quantities and "ddtheta_primal_dual" in res.quantities:
        ratio = res.errors["ddtheta_averaged"][:, last] / res.errors["ddtheta_primal_dual"][:, last]
        wins = [c for ci, c in enumerate(res.cases) if ratio[ci] > 1]
        lines.append("- Ch. 5, primal-dual d∇d∇θ more accurate than the averaged one (error ratio averaged/primal-dual: "
                     + ", ".join(f"{c} {float(r):.2f}" for c, r in zip(res.cases, ratio)) + "): "
                     + ("reproduced in every case." if len(wins) == len(res.cases)
                        else f"holds in cases {', '.join(wins)} only, **not in every case**." if wins
                        else "holds in no case."))
    return lines if len(lines) > 2 else []


# ----------------------------------------------------------------------------- train
def train(cfg) -> dict:
    """Run the configured convergence study and write every output file (see module doc).

    Args:
        cfg: a mapping (``DictConfig`` or ``dict``) with the keys of ``configs/convergence.yaml``.

    Returns:
        ``{"output_dir", "files", "slopes", "reproduced", "variants", "mesh", "seconds"}``:
        ``slopes[quantity][case]`` of the main series, ``reproduced[quantity]`` whether the
        report's claim holds in every case, ``variants[name]`` the same for each variant.

    Raises:
        ValueError: unknown config keys or values (before anything is computed).
        training.io_utils.OutputDirError: ``output_dir`` cannot be created or written, naming the
            path (before anything is computed).
    """
    t0 = time.perf_counter()
    raw = _plain(cfg)
    s = _validate(raw)
    out = check_output_dir(s["output_dir"])
    dtype = DTYPES[s["dtype"]]
    smooth = E.make_connection(s["connection"])
    th = s["thresholds"]
    common = dict(cases=s["cases"], quantities=s["quantities"], levels=s["levels"], fit_levels=s["fit_levels"],
                  dtype=dtype, steps=s["steps"])

    timings = {}
    t = time.perf_counter()
    main_res = E.study(smooth, transport=s["transport"], reference_point=s["reference_point"], **common)
    timings["main"] = time.perf_counter() - t
    title = f"{s['connection']} connection, {s['transport']} transports, reference {s['reference_point']}, {s['dtype']}"
    t = time.perf_counter()
    files = _write_study(out, main_res, s["plots"], title)
    timings["writing csv/plots"] = time.perf_counter() - t

    variant_results = {}
    skipped = []
    for name in s["variants"]:
        change = VARIANTS[name]
        setting = {"transport": s["transport"], "reference_point": s["reference_point"], **change}
        if setting["transport"] == s["transport"] and setting["reference_point"] == s["reference_point"]:
            skipped.append(name)  # identical to the main series
            continue
        t = time.perf_counter()
        res = E.study(smooth, **setting, **common)
        timings[f"variant {name}"] = time.perf_counter() - t
        vtitle = f"{s['connection']} connection, {setting['transport']} transports, reference {setting['reference_point']}, {s['dtype']}"
        t = time.perf_counter()
        files += _write_study(out / "variants" / name, res, s["plots"], vtitle)
        timings["writing csv/plots"] += time.perf_counter() - t
        variant_results[name] = res

    mesh_rows, mesh_slopes, mesh_info = [], [], ""
    mcfg = s["mesh"]
    if mcfg.get("enabled", False):
        from torchconn import io as tio

        t = time.perf_counter()
        mesh = tio.ball(radius=float(mcfg.get("radius", 0.5)), edge_length=float(mcfg.get("edge_length", 0.4)),
                        center=tuple(float(c) for c in mcfg.get("center", (0.6, 0.4, 0.3))), dtype=dtype)
        mesh_info = repr(mesh)
        mesh_rows = E.mesh_convergence(smooth, mesh, int(mcfg["levels"]), transport=s["transport"],
                                       reference_point=s["reference_point"], steps=s["steps"],
                                       chunk=int(mcfg.get("chunk", 1 << 15)))
        timings["mesh"] = time.perf_counter() - t
        fit = mcfg.get("fit_levels")
        mesh_slopes = _mesh_slopes(mesh_rows, None if fit is None else list(fit))
        keys = ("level", "h", "cells", "quantity", "kind", "mean_error", "p95_error", "max_error", "min_quality")
        _csv(out / "mesh_convergence.csv", ",".join(keys), [tuple(r[k] for k in keys) for r in mesh_rows])
        _csv(out / "mesh_slopes.csv", "quantity,kind,slope_mean,slope_p95,slope_max", mesh_slopes)
        files += [str(out / "mesh_convergence.csv"), str(out / "mesh_slopes.csv")]

    # ------------------------------------------------------------------ summary.md
    md = ["# Convergence study (report Secs. 3.4, 4, 5; docs/conventions.md §3)", ""]
    md += [f"- connection: `{s['connection']}` ({type(smooth).__name__}); dtype: `{s['dtype']}`",
           f"- main series: transports `{s['transport']}`, reference point `{s['reference_point']}`, "
           f"levels 0..{s['levels'] - 1}, slope fit over levels {main_res.settings['fit_levels']}",
           f"- claim thresholds: converges ⇔ slope ≥ {th['converge']}; does not converge ⇔ slope ≤ {th['diverge']}",
           ""]
    if list(main_res.settings["fit_levels"]) != [n for n in s["fit_levels"]]:
        md += [f"Note: the configured fit levels {list(s['fit_levels'])} were not all computed (levels 0..{s['levels'] - 1}); "
               f"slopes are fitted over levels {main_res.settings['fit_levels']} and may be pre-asymptotic "
               "(a reduced study, not a test of the report's claims).", ""]
    md += ["## Main series (`convergence.csv`, `slopes.csv`, `convergence_<case>.png`)", ""]
    table, main_ok = _verdict_table(main_res, th)
    md += table + [""]
    n_ok = sum(main_ok.values())
    md.append(f"**{n_ok} of {len(main_ok)} claims reproduced in every case.**" if n_ok < len(main_ok)
              else f"**All {len(main_ok)} claims reproduced in every case.**")
    if s["dtype"] == "float32":
        md += ["", "Note: in float32 the level-n cells (edge length 2^-n next to coordinates of size ~3) "
               "lose most significant digits at fine levels; round-off then dominates the discretization "
               "error and slopes over levels 7..12 are not meaningful for the converging quantities."]
    md += [""] + _secondary_claims(main_res) + [""]
    variant_ok = {}
    for name, res in variant_results.items():
        md += [f"## Variant `{name}` (`variants/{name}/`)", "",
               f"transports `{res.settings['transport']}`, reference point `{res.settings['reference_point']}`.", ""]
        table, ok = _verdict_table(res, th)
        variant_ok[name] = ok
        changed = [q for q in ok if ok[q] != main_ok[q]]
        md += table + [""]
        md.append("Conclusions change relative to the main series for: " + ", ".join(changed) + "." if changed
                  else "Conclusions do not change relative to the main series.")
        md.append("")
    for name in skipped:
        md += [f"## Variant `{name}`", "", "Identical to the main series settings; not run separately.", ""]
    if mesh_rows:
        md += ["## Whole-mesh convergence (`mesh_convergence.csv`, `mesh_slopes.csv`)", "",
               f"Ball {mesh_info}, refined by `TetMesh.subdivide()` (1→8); h = mean edge length. "
               "Faces: stored orientation `[a<b<c]`, evaluation vertex `a`, cut `c`; tets positively oriented.", "",
               "| quantity | cells | " + " | ".join(f"L{lv} mean / p95 / max" for lv in sorted({r['level'] for r in mesh_rows}))
               + " | slope mean | slope p95 | slope max |",
               "|" + "---|" * (5 + len({r['level'] for r in mesh_rows}))]
        for q, kind, sm, sp, sx in mesh_slopes:
            rs = [r for r in mesh_rows if r["quantity"] == q]
            md.append(f"| {q} | {kind} | "
                      + " | ".join(f"{r['mean_error']:.2e} / {r['p95_error']:.2e} / {r['max_error']:.2e}" for r in rs)
                      + f" | {sm:.3f} | {sp:.3f} | {sx:.3f} |")
        for kind in ("face", "tet"):
            qual = {r["level"]: r["min_quality"] for r in mesh_rows if r["kind"] == kind}
            if qual:
                md.append(f"| min {kind} shape quality (1 = regular) | {kind} | "
                          + " | ".join(f"{qual[lv]:.2e}" for lv in sorted(qual)) + " | | | |")
        sm = [x[2] for x in mesh_slopes]
        sx = [x[4] for x in mesh_slopes]
        qual_all = {k: [r["min_quality"] for r in mesh_rows if r["kind"] == k and r["quantity"] == q0]
                    for k, q0 in (("face", mesh_slopes[0][0]), ("tet", mesh_slopes[-1][0]))}
        md += ["", f"Slopes of the mean per-cell error lie in [{min(sm):.2f}, {max(sm):.2f}], of the max per-cell "
               f"error in [{min(sx):.2f}, {max(sx):.2f}] (fitted over "
               f"{'all levels' if mcfg.get('fit_levels') is None else 'levels ' + str(list(mcfg['fit_levels']))}). "
               "Values are divided by the cell area/volume, so the max error is governed by the worst-shaped cells; "
               f"the smallest face quality goes {qual_all['face'][0]:.2e} → {qual_all['face'][-1]:.2e} and the smallest "
               f"tet quality {qual_all['tet'][0]:.2e} → {qual_all['tet'][-1]:.2e} under `subdivide()`.", ""]
    md += ["## Run time", ""] + [f"- {k}: {v:.1f} s" for k, v in timings.items()]
    md.append(f"- total: {time.perf_counter() - t0:.1f} s")
    atomic_write_text(out / "summary.md", "\n".join(md) + "\n")
    files.append(str(out / "summary.md"))
    try:
        from omegaconf import OmegaConf

        atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(raw)))
        files.append(str(out / "config.yaml"))
    except ImportError:
        pass

    return {
        "output_dir": str(out),
        "files": files,
        "slopes": {q: {c: float(main_res.slopes[q][ci]) for ci, c in enumerate(main_res.cases)} for q in main_res.quantities},
        "reproduced": main_ok,
        "variants": variant_ok,
        "mesh": {"rows": mesh_rows, "slopes": mesh_slopes},
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    """Hydra entry point (thin wrapper around :func:`train`)."""
    import hydra

    from . import io_utils, schema  # noqa: F401 - schema registers the run-directory resolver

    @hydra.main(version_base="1.3", config_path="../configs", config_name="convergence")
    def _run(cfg) -> None:
        with io_utils.report_errors("convergence"):  # the message, not a traceback (unless HYDRA_FULL_ERROR=1)
            with io_utils.hydra_output_dir(cfg):
                result = train(cfg)
        ok = sum(result["reproduced"].values())
        print(f"convergence study written to {result['output_dir']} "
              f"({ok}/{len(result['reproduced'])} claims reproduced, {result['seconds']:.1f} s)")

    _run()


if __name__ == "__main__":
    main()
