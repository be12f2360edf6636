"""The HexMe frame-field benchmark (benchmarks/frames_hexme.py): cases, jobs, error rows, aggregation."""
from __future__ import annotations

import csv
import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from conftest import DATA_DIR

pytest.importorskip("gmsh", reason="the HexMe meshes are made by gmsh (torchconn[cad])")
pytest.importorskip("yaml", reason="HexMe parameter files are YAML")

from benchmarks import frames_hexme as fh  # noqa: E402
from benchmarks import frames_hexme_report as rep  # noqa: E402
from torchconn.frames.metrics import METRIC_KEYS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HEXME = DATA_DIR / "hexme"


def _need_hexme():
    if not (HEXME / "meta" / "s02c_prism.yaml").is_file():
        pytest.skip(f"HexMe parameter files not found in {HEXME} (the shared data is missing)")


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_cases_and_options():
    _need_hexme()
    c = fh.list_cases("hexme", ("c",), None, DATA_DIR)
    assert len(c) == 35 and "s02c_prism" in c and all(n[3] == "c" for n in c)
    assert fh.list_cases("hexme", ("c",), ["s02", "n13"], DATA_DIR) == ["n13c_acute_line", "s02c_prism"]
    assert len(fh.list_cases("hexme", ("c", "u"), ["i"], DATA_DIR)) == 6
    assert fh.list_cases("shared") == list(fh.SHARED)
    with pytest.raises(ValueError, match="kinds"):
        fh.list_cases("hexme", ("x",), None, DATA_DIR)
    with pytest.raises(ValueError, match="set"):
        fh.list_cases("nope")
    assert fh.parse_opts(["mbo.n_taus=4", "connection.weights.tie=5", "mbo.tau=[2, 0.5]"]) == {
        "mbo": {"n_taus": 4, "tau": [2, 0.5]}, "connection": {"weights": {"tie": 5}}}
    with pytest.raises(ValueError, match="METHOD.KEY"):
        fh.parse_opts(["steps=4"])
    with pytest.raises(ValueError, match="unknown method"):
        fh.parse_opts(["foo.steps=4"])


def test_jobs_in_process_with_an_error_row(tmp_path):
    """Fast path of the pipeline: one job that finishes and one failing method, as job files."""
    _need_hexme()
    opts = {"set": "hexme", "data_dir": str(DATA_DIR), "threads": 1,
            "method_options": {"sh": {"sh": {"n_smooth_iters": 0}}, "mbo": {"tau": [1.0, -1.0]}}}
    ok_rec = json.loads(fh.run_job("hexme", "s02c_prism", "sh", tmp_path, opts, in_process=True).read_text())
    bad = json.loads(fh.run_job("hexme", "s02c_prism", "mbo", tmp_path, opts, in_process=True).read_text())
    assert ok_rec["error"] == "" and set(METRIC_KEYS) <= set(ok_rec) and ok_rec["alignment_mean_deg"] < 1e-6
    assert {"mesh_s", "method_s", "metrics_s", "wall_s"} <= set(ok_rec)
    assert bad["error"].startswith("ValueError") and "tau" in bad["error"] and "smoothness_mean_deg" not in bad
    rows = rep.load_rows(tmp_path)
    assert len(rows) == 2
    md = rep.markdown(rows)
    assert "| s02c_prism | mbo |" in md and "not held (0/1; failed: s02c_prism)" in md


@pytest.mark.slow
def test_end_to_end_in_process_on_s02c(tmp_path):
    """sh, mbo (given a bad option: an error row) and a short connection run, then the report."""
    _need_hexme()
    out = tmp_path / "run"
    argv = ["--models", "s02c", "--methods", "sh,mbo,connection", "--out", str(out), "--no-hydra", "--in-process",
            "--data-dir", str(DATA_DIR), "--opt", "mbo.laplacian=nope", "--opt", "connection.steps=5",
            "--opt", "connection.sh.n_smooth_iters=0",
            "--opt", "sh.sh.n_smooth_iters=0"]  # short runs: the test is of the pipeline
    fh.main(argv)
    with open(out / "results.csv") as fh_:
        rows = list(csv.DictReader(fh_))
    assert list(rows[0]) == list(rep.CSV_COLUMNS)
    assert set(METRIC_KEYS) <= set(rows[0]) and {"wall_s", "peak_rss_mb", "error"} <= set(rows[0])
    by = {r["method"]: r for r in rows}
    assert sorted(by) == ["connection", "mbo", "sh"]
    assert "laplacian" in by["mbo"]["error"] and by["mbo"]["smoothness_mean_deg"] == ""
    for m in ("sh", "connection"):
        r = by[m]
        assert r["error"] == "" and r["model"] == "s02c_prism" and r["kind"] == "c"
        assert int(r["n_tets"]) > 100 and float(r["wall_s"]) > 0
        assert math.isfinite(float(r["smoothness_mean_deg"])) and float(r["alignment_mean_deg"]) < 1e-6
        # the hex stage ran on the field: a map with its verdict, hexes, their quality, times
        assert r["hex_error"] == "" and r["hex_valid"] in ("True", "False") and int(r["hex_n"]) > 0
        assert float(r["hex_s"]) > 0 and float(r["end_to_end_s"]) >= float(r["wall_s"])
        assert -1 <= float(r["hex_sj_min"]) <= 1 and int(r["hex_corners"]) == 6  # the prism's CAD points
    assert by["mbo"]["hex_n"] == ""  # no field, no hex stage
    md = (out / "results.md").read_text()
    assert "### Hex meshes" in md and "| anchor: LMFF (2023) valid maps | 94% |" in md
    assert "Set-level figures" in md and "Targets of the issue" in md and "Per model" in md
    assert "| s02c_prism | mbo |" in md and "laplacian" in md
    assert "every model finishes (no crash, no NaN) | not held (0/1; failed: s02c_prism)" in md
    assert (out / "ratios.png").is_file() or importlib.util.find_spec("matplotlib") is None
    # resumption: an existing result file is not rerun
    job = out / "jobs" / "hexme__s02c_prism__sh.json"
    before = job.stat().st_mtime_ns
    fh.main(argv[:5] + ["sh", "--out", str(out), "--no-hydra", "--in-process", "--data-dir", str(DATA_DIR)])
    assert job.stat().st_mtime_ns == before


@pytest.mark.slow
def test_child_process_job_and_error_rows(tmp_path):
    """A job in its child process records the peak memory; a missing model is an error row, not a stop."""
    _need_hexme()
    opts = {"set": "hexme", "threads": 1, "timeout_s": 600, "data_dir": str(DATA_DIR)}
    (tmp_path / "options.json").write_text(json.dumps(opts))
    p = fh.run_job("hexme", "s02c_prism", "sh", tmp_path, opts)
    rec = json.loads(p.read_text())
    assert rec["error"] == "" and rec["peak_rss_mb"] > 10 and rec["n_tets"] > 100
    p = fh.run_job("hexme", "s99c_missing", "sh", tmp_path, opts)
    rec = json.loads(p.read_text())
    assert "FileNotFoundError" in rec["error"]
    opts_t = dict(opts, timeout_s=0.01)
    p = fh.run_job("hexme", "s02c_prism", "mbo", tmp_path, opts_t)
    assert json.loads(p.read_text())["error"].startswith("timeout")


def _rec(model, method, **kw):
    base = {k: 0 for k in METRIC_KEYS}
    base.update(set="hexme", model=model, method=method, kind="c", n_tets=1000, error="", wall_s=1.0,
                peak_rss_mb=100.0, alignment_mean_deg=0.0, feature_curve_alignment_mean_deg=0.5)
    base.update(kw)
    return base


def test_chooser_rows_report_their_own_hex_stage_time(tmp_path):
    """A row whose hex mesh the chooser made reports that mesh's hex stage seconds (also in files
    written when ``hex_s`` held the seconds of reading the columns); other rows are unchanged."""
    (tmp_path / "jobs").mkdir()
    recs = {"a": {"model": "s01c_a", "method": "connection", "hex_from_chooser": True, "hex_s": 0.001,
                  "hex_times": {"total_s": 12.5}},
            "b": {"model": "s01c_a", "method": "sh", "hex_from_chooser": False, "hex_s": 3.0,
                  "hex_times": {"total_s": 2.9}}}
    for k, r in recs.items():
        (tmp_path / "jobs" / f"{k}.json").write_text(json.dumps(r))
    assert [r["hex_s"] for r in rep.load_rows(tmp_path)] == [12.5, 3.0]


def test_set_figures_and_targets_on_known_numbers(tmp_path):
    rows = [
        _rec("s01c_a", "sh", smoothness_mean_deg=10.0, smoothness_rms_deg=12.0, dirichlet_energy_mean=0.2,
             n_singular_faces=10, n_singular_faces_complex=4, n_singular_faces_quarter=6, singular_valid_fraction=0.5),
        _rec("s01c_a", "connection", smoothness_mean_deg=8.0, smoothness_rms_deg=12.0, dirichlet_energy_mean=0.18,
             n_singular_faces=10, n_singular_faces_complex=1, n_singular_faces_quarter=9,
             singular_valid_fraction=1.0),
        _rec("s02c_b", "sh", smoothness_mean_deg=5.0, smoothness_rms_deg=6.0, dirichlet_energy_mean=0.1,
             n_singular_faces=0, n_singular_faces_complex=0, n_singular_faces_quarter=0,
             singular_valid_fraction=float("nan")),
        _rec("s02c_b", "connection", smoothness_mean_deg=4.5, smoothness_rms_deg=6.3, dirichlet_energy_mean=0.09,
             n_singular_faces=1, n_singular_faces_complex=0, n_singular_faces_quarter=1, singular_valid_fraction=0.0,
             wall_s=70.0),
        _rec("s03c_c", "connection", error="RuntimeError: boom"),
    ]
    # round-off floors: two fields exact to round-off compare as equal, counts as (n + 1) / (n_sh + 1)
    assert rep.ratio("smoothness_mean_deg", {"smoothness_mean_deg": 1e-8}, {"smoothness_mean_deg": 1e-10}) == 1.0
    assert rep.ratio("dirichlet_energy_mean", {"dirichlet_energy_mean": 0.2}, {"dirichlet_energy_mean": 0.1}) == 2.0
    assert rep.ratio("n_singular_faces", {"n_singular_faces": 3}, {"n_singular_faces": 0}) == 4.0
    figs = rep.set_figures(rows)["connection"]
    assert figs["gmean_ratio_smoothness_mean_deg"] == pytest.approx(math.sqrt(0.8 * 0.9))
    assert figs["gmean_ratio_dirichlet_energy_mean"] == pytest.approx(0.9)
    assert figs["gmean_ratio_n_singular_faces"] == pytest.approx(math.sqrt(1.0 * 2.0))
    assert figs["total_complex"] == 1 and figs["total_complex_baseline"] == 4
    assert figs["valid_fraction"] == pytest.approx(9 / 10) and figs["valid_fraction_baseline"] == pytest.approx(0.5)
    assert figs["finished"] == 2 and figs["failed"] == ["s03c_c"]
    t = {name: held for name, held, _ in rep.targets(rows, rep.set_figures(rows), "connection")}
    assert t["every model finishes (no crash, no NaN)"] is False
    assert t["every model: RMS angle ≤ 1% worse than SH"] is False  # s02c_b: 6.3 > 6.06
    assert t["every model: singular faces ≤ 1% worse than SH"] is False  # 1 > 0
    assert t["set: geometric mean of the mean-angle ratio ≤ 0.90"] is True  # 0.849
    assert t["set: geometric mean of the Dirichlet ratio ≤ 0.97"] is True
    assert t["set: complex-type singular faces ≤ 50% of the baseline's"] is True
    assert t["set: higher valid fraction than the baseline (total)"] is True
    assert t["time: ≤ 60 s end to end per model up to 200k tets"] is False  # 70 s
    # aggregation from job files
    (tmp_path / "jobs").mkdir()
    for r in rows:
        (tmp_path / "jobs" / f"hexme__{r['model']}__{r['method']}.json").write_text(json.dumps(r))
    paths = rep.aggregate(tmp_path)
    md = paths["md"].read_text()
    assert "| s03c_c | connection |" in md and "boom" in md
    assert "| mean angle | s02c_b (0.9×) |" in md  # the worst mean-angle ratio
    with open(paths["csv"]) as f:
        assert len(list(csv.DictReader(f))) == 5


@pytest.mark.slow
def test_hydra_joblib_sweep(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="hydra-joblib-launcher (torchconn[bench])")
    _need_hexme()
    out = tmp_path / "run"
    fh.main(["--models", "s02c", "--methods", "sh", "--out", str(out), "--launcher", "joblib", "--jobs", "1",
             "--data-dir", str(DATA_DIR)])
    rec = json.loads((out / "jobs" / "hexme__s02c_prism__sh.json").read_text())
    assert rec["error"] == "" and (out / "hydra" / "sweep" / "multirun.yaml").is_file()


def test_slurm_launcher_config_composes():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="hydra-submitit-launcher (torchconn[bench])")
    r = subprocess.run([sys.executable, "-m", "benchmarks.frames_hexme", "hydra-job", "case=s02c_prism", "method=sh",
                        "out_dir=/tmp/unused", "hydra/launcher=hexme_slurm", "--cfg", "hydra", "--package",
                        "hydra.launcher"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "SlurmLauncher" in r.stdout and "cpus_per_task: 2" in r.stdout
