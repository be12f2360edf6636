"""End-to-end test of ``python -m training.convergence`` on a reduced study (2 cases, 4 levels)."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

from training import experiments as E

REPO = Path(__file__).resolve().parents[1]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run([sys.executable, "-m", "training.convergence", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def _main_in_process(args: list[str], cwd: Path, monkeypatch) -> int:
    """``python -m training.convergence ARGS`` in this process (Hydra parses ``sys.argv``) in ``cwd``;
    its exit status (0 when it returns). A fresh process cost 5-11 s on 2 loaded cores; the
    module fixture below runs the command line in one."""
    from training import convergence

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", ["convergence", *args])
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    try:
        convergence.main()
    except SystemExit as exc:
        return exc.code
    return 0


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


@pytest.fixture(scope="module")
def reduced_run(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("cli")
    out = tmp / "out"
    proc = _run(["experiment=quick", "cases=[A,B]", "levels=4", "mesh.levels=2", f"output_dir={out}"], cwd=tmp)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "claims reproduced" in proc.stdout
    assert [p.name for p in tmp.iterdir()] == ["out"]  # output_dir given: nothing else in the working directory
    return out


def test_convergence_csv(reduced_run):
    header, rows = _read_csv(reduced_run / "convergence.csv")
    assert header == ["case", "quantity", "level", "h", "error"]
    assert len(rows) == 2 * len(E.QUANTITIES) * 4
    assert {(r[0], r[1], int(r[2])) for r in rows} == {
        (c, q, n) for c in "AB" for q in E.QUANTITIES for n in range(4)}
    for r in rows:
        assert float(r[3]) == 2.0 ** -int(r[2])
        err = float(r[4])
        assert err > 0 and repr(err) == r[4]  # full precision, round-trips exactly
    assert (reduced_run / "convergence.csv").read_text().splitlines()[0] == "case,quantity,level,h,error"


def test_slopes_summary_and_plots(reduced_run):
    header, rows = _read_csv(reduced_run / "slopes.csv")
    assert header == ["case", "quantity", "slope"]
    assert {(r[0], r[1]) for r in rows} == {(c, q) for c in "AB" for q in E.QUANTITIES}
    assert all(abs(float(r[2])) < 5 for r in rows)
    summary = (reduced_run / "summary.md").read_text()
    assert "| quantity | report's claim | slope A | slope B | reproduced in every case |" in summary
    for q in E.QUANTITIES:
        assert f"| {q} |" in summary
    for name in ("path_ordered", "centroid"):
        assert f"## Variant `{name}`" in summary
        folder = reduced_run / "variants" / name
        assert _read_csv(folder / "convergence.csv")[0] == ["case", "quantity", "level", "h", "error"]
        assert len(_read_csv(folder / "convergence.csv")[1]) == 2 * len(E.QUANTITIES) * 4
        assert (folder / "slopes.csv").exists()
    for c in "AB":
        for folder in (reduced_run, reduced_run / "variants" / "centroid"):
            png = folder / f"convergence_{c}.png"
            assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(reduced_run.rglob("*.tmp"))  # atomic writes leave no temp files


def test_mesh_outputs(reduced_run):
    header, rows = _read_csv(reduced_run / "mesh_convergence.csv")
    assert header == ["level", "h", "cells", "quantity", "kind", "mean_error", "p95_error", "max_error", "min_quality"]
    assert len(rows) == 2 * len(E.MESH_QUANTITIES)
    header, rows = _read_csv(reduced_run / "mesh_slopes.csv")
    assert header == ["quantity", "kind", "slope_mean", "slope_p95", "slope_max"]
    assert [r[0] for r in rows] == [q for q, _ in E.MESH_QUANTITIES]
    assert "## Whole-mesh convergence" in (reduced_run / "summary.md").read_text()


def test_unknown_key_fails_clearly(tmp_path, monkeypatch, capsys):
    code = _main_in_process(["experiment=report", "levels=3", "no_such_key=1", f"output_dir={tmp_path / 'o'}"],
                            tmp_path, monkeypatch)
    err = capsys.readouterr().err
    assert code not in (0, None)
    assert "no_such_key" in err and "not in struct" in err
    assert not (tmp_path / "o" / "convergence.csv").exists()


def test_unwritable_output_dir_fails_before_computing(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    bad = blocker / "out"
    code = _main_in_process(["experiment=report", "levels=3", f"output_dir={bad}"], tmp_path, monkeypatch)
    out = capsys.readouterr()
    assert code not in (0, None)
    assert str(bad) in out.err and "output_dir" in out.err
    assert "claims reproduced" not in out.out


def test_train_validates_in_process(tmp_path):
    from training.convergence import train
    from training.io_utils import OutputDirError

    base = {"cases": ["A"], "levels": 3, "variants": [], "plots": False, "mesh": {"enabled": False},
            "output_dir": str(tmp_path / "o")}
    with pytest.raises(ValueError, match="unknown config keys"):
        train({**base, "typo": 1})
    with pytest.raises(ValueError, match=r"unknown config keys mesh"):
        train({**base, "mesh": {"enabled": False, "lvls": 2}})
    for key, value, msg in (("transport", "euler", "unknown transport"), ("cases", ["Z"], "cases must be"),
                            ("quantities", ["torsion_magic"], "quantities must be"), ("dtype", "float16", "unknown dtype"),
                            ("connection", "flat", "unknown connection"), ("variants", ["midpoint"], "unknown variants"),
                            ("levels", 1, "levels must be")):
        with pytest.raises(ValueError, match=msg):
            train({**base, key: value})
    blocker = tmp_path / "f"
    blocker.write_text("")
    with pytest.raises(OutputDirError, match=str(blocker)):
        train({**base, "output_dir": str(blocker / "x")})
    res = train(base)
    assert set(res["slopes"]) == set(E.QUANTITIES) and list(res["slopes"]["torsion_sqrt"]) == ["A"]
    assert (tmp_path / "o" / "convergence.csv").exists() and (tmp_path / "o" / "summary.md").exists()


def test_bad_value_is_a_message_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    """A value the study refuses: the message (no traceback), a nonzero exit, and without
    ``output_dir`` no empty ``outputs/convergence/<date>/<time>`` left in the working directory."""
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    code = _main_in_process(["experiment=quick", "cases=[A]", "levels=3", "mesh.levels=1"], tmp_path, monkeypatch)
    err = capsys.readouterr().err
    assert code not in (0, None)
    assert "[convergence] error: mesh.levels must be >= 2" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []
