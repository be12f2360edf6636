"""Hostile inputs to the ``train_frames`` command (issue 14): typed config, safe checkpoints,
one run per output directory, no partial output. Each test asserts the error class and the words
that name the problem; runs are tiny (the built-in box, one step)."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import pickle
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError

from torchconn.frames.options import option
from training import config_check, frame_plots, io_utils, schema
from training.config_check import ConfigError, check_config
from training.train_frames import CONFIG_DIR, _validate, load_config, train

ROOT = Path(__file__).resolve().parents[1]
TINY = {"mesh": "box", "edge_length": 0.5, "sh": {"n_smooth_iters": 0}, "progress": False, "num_threads": 1,
        "steps": 1}


def _cfg(tmp_path, name="run", **kw):
    return {**TINY, "output_dir": str(tmp_path / name), **kw}


def _leftovers(out: Path) -> list[str]:
    """Temporary, staging and lock files that a finished or failed run must not leave."""
    return [p.name for p in out.iterdir() if p.name.startswith(".") or p.name.endswith(".tmp")]


# ----------------------------------------------------------------------------- typed config (case 7, weak)
@pytest.mark.parametrize("value", ["no", "maybe", "false", 1, 0])
def test_resume_must_be_a_boolean(tmp_path, value):
    """``resume=no`` used to resume (a non-empty string is truthy)."""
    with pytest.raises(ConfigError, match=rf"'resume' = {value!r} .*train_frames.yaml.*not a boolean.*true or false"):
        train(_cfg(tmp_path, resume=value))
    assert not (tmp_path / "run").exists()  # refused before the output directory is created


def test_resume_no_from_the_command_line_is_refused():
    """Hydra's override grammar reads ``resume=no`` as the string 'no'."""
    cfg = load_config(["resume=no", "output_dir=unused"])
    assert cfg.resume == "no"
    with pytest.raises(ConfigError, match="'resume' = 'no'"):
        _validate(cfg)


def test_progress_must_be_a_boolean():
    with pytest.raises(ConfigError, match=r"'progress' = 1 \(int\).*boolean"):
        _validate({"progress": 1, "output_dir": "x"})


def test_steps_not_a_number_names_the_key():
    with pytest.raises(ConfigError, match=r"'steps' = 'abc' \(str\).*not an integer.*an integer >= 0.*steps=\.\.\."):
        _validate({"steps": "abc", "output_dir": "x"})


def test_steps_fraction_is_not_rounded():
    """``steps=1.5`` used to run one step."""
    with pytest.raises(ConfigError, match=r"'steps' = 1.5 \(float\).*never rounded"):
        _validate({"steps": 1.5, "output_dir": "x"})


@pytest.mark.parametrize(("key", "value", "allowed"), [
    ("sh.n_smooth_iters", -1, ">= 0"),
    ("lbfgs.max_iter", 0, ">= 1"),
    ("checkpoint_every", 0, ">= 1"),
    ("lr", 0, "> 0"),
    ("weights.tie", -1.0, ">= 0"),
    ("feature_angle_deg", 200.0, "<= 180"),
    ("smooth_power", 3.0, "<= 2"),
    ("seed", -1, ">= 0"),
    ("quality.rounds", 0, ">= 1"),
    ("quality.score_complex", -1.0, ">= 0"),
])
def test_out_of_range_values_name_the_key(key, value, allowed):
    section, _, leaf = key.rpartition(".")
    user = {section: {leaf: value}} if section else {key: value}
    with pytest.raises(ConfigError, match=rf"'{key}' = {value!r}.*out of range.*{allowed}"):
        _validate({**user, "output_dir": "x"})


@pytest.mark.parametrize("value", [0, -1, float("nan"), float("inf")])
def test_edge_length_must_be_positive_and_finite(value):
    reason = "not finite" if not math.isfinite(value) else "out of range"
    with pytest.raises(ConfigError, match=rf"'edge_length' = .*{reason}.*> 0 or null"):
        _validate({"edge_length": value, "output_dir": "x"})
    _validate({"edge_length": None, "output_dir": "x"})  # null: the generator's default


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_device_cuda_without_cuda_names_the_key():
    with pytest.raises(ConfigError, match=r"'device'.*'cuda' is not available.*device=cpu"):
        _validate({"device": "cuda", "output_dir": "x"})


def test_device_that_is_not_a_device():
    with pytest.raises(ConfigError, match=r"'device'.*'gpu0' is not a torch device"):
        _validate({"device": "gpu0", "output_dir": "x"})


@pytest.mark.parametrize("value", [0, -2, 1.5, "many"])
def test_num_threads_must_be_auto_or_positive(value):
    with pytest.raises(ConfigError, match=rf"'num_threads' = {value!r}.*'auto' or an integer >= 1"):
        _validate({"num_threads": value, "output_dir": "x"})


def test_num_threads_auto_uses_the_idle_cores(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.2, 1.0, 1.0))  # one core busy
    assert config_check.resolve_num_threads("auto") == 1
    monkeypatch.setattr(os, "getloadavg", lambda: (0.1, 0.0, 0.0))
    assert config_check.resolve_num_threads("auto") == 2
    monkeypatch.setattr(os, "getloadavg", lambda: (7.0, 7.0, 7.0))  # overloaded: still one thread
    assert config_check.resolve_num_threads("auto") == 1
    assert config_check.resolve_num_threads(None) is None and config_check.resolve_num_threads(3) == 3


def test_ints_are_accepted_for_floats():
    cfg = _validate({"lr": 1, "weights": {"tie": 3}, "edge_length": 1, "output_dir": "x"})
    assert cfg.lr == 1 and cfg.weights.tie == 3


def test_unknown_keys_keep_raising():
    with pytest.raises(ConfigKeyError, match="stesp"):
        _validate({"stesp": 3, "output_dir": "x"})
    with pytest.raises(ConfigError, match=r"'lbfgs.max_itr' is not a key of cfg.yaml; did you mean 'lbfgs.max_iter'"):
        check_config({"lbfgs": {"max_itr": 1}}, config_check.TRAIN_FRAMES, "cfg.yaml")


def test_train_without_output_dir_is_named(tmp_path, monkeypatch):
    """``train()`` outside the command line needs ``output_dir`` (null is the CLI's "Hydra's run
    directory"): the error names it, and nothing is written in the working directory."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"output_dir is null"):
        train({})
    assert list(tmp_path.iterdir()) == []


def test_the_config_files_hold_no_option_and_compose_the_schema():
    """configs/train_frames.yaml and demo.yaml add Hydra's settings to their ConfigStore schema (the
    one place a default is written) and no key; the composed keys are the checked keys, and the
    shipped defaults pass their own checks."""
    for name in ("train_frames", "demo"):
        raw = yaml.safe_load((CONFIG_DIR / f"{name}.yaml").read_text())
        assert set(raw) == {"defaults", "hydra"} and raw["defaults"][0] == f"{name}_schema", name
    cfg = load_config(["output_dir=x"])
    assert set(config_check._flatten(OmegaConf.to_container(cfg))) == set(config_check.TRAIN_FRAMES)
    _validate(cfg)
    demo = OmegaConf.create(schema.defaults(schema.DemoConfig))
    assert set(config_check._flatten(demo)) == set(config_check.DEMO)
    check_config(demo, config_check.DEMO, "configs/demo.yaml")
    _validate({"output_dir": "x"})


@dataclasses.dataclass
class _Group:
    n: int = option(3, lo=1)


@dataclasses.dataclass
class _Toy:
    """One field of every kind the generator knows."""
    flag: bool = option(True)
    count: int = option(2, lo=0, hi=9)
    rate: float = option(0.5, lo=0, lo_open=True)
    tol: float | None = option(None, lo=0)
    name: str = option("a")
    kind: str = option("x", choices=("x", "y"))
    kinds: list[str] = option(["x"], choices=("x", "y"))
    ws: list[float] | None = option([1.0], lo=0)
    device: str = option("cpu", kind="device")
    threads: int | str | None = option("auto", kind="threads")
    group: _Group = dataclasses.field(default_factory=_Group)


def test_checks_are_generated_from_the_schema_fields():
    """Type -> kind, ``X | None`` -> nullable, metadata -> range/choices/kind, groups -> dotted keys."""
    S = config_check.Spec
    assert config_check.specs_of(_Toy) == {
        "flag": S("bool"),
        "count": S("int", lo=0, hi=9),
        "rate": S("float", lo=0, lo_open=True),
        "tol": S("float", lo=0, nullable=True),
        "name": S("str"),
        "kind": S("choice", choices=("x", "y")),
        "kinds": S("list", item=S("choice", choices=("x", "y"))),
        "ws": S("list", item=S("float", lo=0), nullable=True),
        "device": S("device"),
        "threads": S("threads", nullable=True),
        "group.n": S("int", lo=1),
    }
    specs = config_check.specs_of(_Toy)
    check_config(schema.defaults(_Toy), specs, "toy.yaml")  # the defaults pass
    with pytest.raises(ConfigError, match=r"'group.n' = 0 \(int\) in toy.yaml is out of range; allowed: an integer >= 1"):
        check_config({"group": {"n": 0}}, specs, "toy.yaml")
    with pytest.raises(ConfigError, match=r"'kinds' = \['z'\].*element 0 \('z'\).*one of \['x', 'y'\]"):
        check_config({"kinds": ["z"]}, specs, "toy.yaml")

    @dataclasses.dataclass
    class Bad:
        x: dict = option({})

    with pytest.raises(TypeError, match="Bad.x"):
        config_check.specs_of(Bad)


def test_the_jobs_checks_keep_their_ranges():
    """A few checks of the frame and hex jobs as the hand-written tables had them."""
    tf, hx = config_check.TRAIN_FRAMES, config_check.HEX_MESH
    assert tf["smooth_power"].describe() == "a finite number >= 0.5 and <= 2"
    assert tf["seed"].describe() == "an integer >= 0 and <= 4.29497e+09"
    assert tf["starts"].describe() == "a non-empty list, each element one of ['sh', 'mbo']"
    assert tf["quality.dirichlet_weights"].describe() == "a non-empty list, each element a finite number >= 0"
    assert tf["method"].choices == ("connection", "sh_baseline") and "mbo" in hx["method"].choices
    assert hx["hex.feature_max_deg"].describe() == "a finite number >= 0 and <= 90"
    assert hx["hex.backend"].describe() == "one of ['auto', 'cholmod', 'superlu', 'pardiso']"
    assert set(hx) - set(tf) == {"frames", "debug"} | {k for k in hx if k.startswith("hex.")}


def test_demo_config_is_checked():
    from training.demo import run

    cfg = OmegaConf.create({"mesh": "box", "edge_length": 0.5, "seed": 0, "dtype": "float64", "scale": None,
                            "device": "cpu"})
    with pytest.raises(ConfigError, match=r"'seed' = 1.5.*configs/demo.yaml"):
        run(OmegaConf.merge(cfg, {"seed": 1.5}))
    with pytest.raises(ConfigError, match=r"'edge_length' = -1"):
        run(OmegaConf.merge(cfg, {"edge_length": -1}))


# ----------------------------------------------------------------------------- checkpoints (case 5)
class _Marker:
    """Unpickling this runs ``open(path, "w")``: the file appears if the checkpoint's code ran."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_malicious_checkpoint_is_not_run_on_resume(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    marker = tmp_path / "pwned"
    torch.save({"step": 0, "fingerprint": "x", "payload": _Marker(marker)}, out / "checkpoint.pt")
    with pytest.raises(io_utils.CheckpointError, match=r"checkpoint\.pt.*holds objects other than tensors.*"
                                                       r"not loaded.*resume=true"):
        train(_cfg(tmp_path, resume=True))
    assert not marker.exists()
    # a raw pickle (no zip container) is refused as well
    (out / "checkpoint.pt").write_bytes(pickle.dumps(_Marker(marker), protocol=2))
    with pytest.raises(io_utils.CheckpointError, match="checkpoint.pt"):
        io_utils.load_checkpoint(out / "checkpoint.pt")
    assert not marker.exists()
    assert _leftovers(out) == []  # the lock is released after the error


def test_random_bytes_checkpoint_names_its_path(tmp_path):
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(io_utils.CheckpointError, match=rf"{path}.*corrupted, truncated or not a checkpoint.*delete it"):
        io_utils.load_checkpoint(path)


def test_truncated_checkpoint_names_its_path(tmp_path):
    path = tmp_path / "checkpoint.pt"
    io_utils.save_checkpoint(path, {"step": 3, "model": {"w": torch.arange(4000.0)}})
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(io_utils.CheckpointError, match=rf"{path}.*corrupted, truncated"):
        io_utils.load_checkpoint(path)
    path.write_bytes(b"")
    with pytest.raises(io_utils.CheckpointError, match=rf"{path}.*corrupted, truncated"):
        io_utils.load_checkpoint(path)


def test_checkpoint_missing_keys_or_other_configuration(tmp_path):
    path = tmp_path / "checkpoint.pt"
    io_utils.save_checkpoint(path, {"step": 3, "fingerprint": "abc"})
    with pytest.raises(io_utils.CheckpointError, match=r"lacks \['model'\]"):
        io_utils.load_checkpoint(path, required=("step", "model"))
    with pytest.raises(io_utils.CheckpointError, match="another mesh.*refusing to resume"):
        io_utils.load_checkpoint(path, fingerprint="def")
    io_utils.save_checkpoint(path, [1, 2])  # type: ignore[arg-type]
    with pytest.raises(io_utils.CheckpointError, match="holds a list"):
        io_utils.load_checkpoint(path)


def test_checkpoint_holds_only_plain_data(tmp_path):
    """What a checkpoint holds is checked when it is written, so every one loads with weights_only."""
    import numpy as np

    with pytest.raises(TypeError, match=r"state\['rng'\]\[0\] is a numpy.ndarray"):
        io_utils.save_checkpoint(tmp_path / "c.pt", {"rng": [np.zeros(3)]})
    assert not (tmp_path / "c.pt").exists()
    np.random.seed(5)
    torch.manual_seed(5)
    io_utils.save_checkpoint(tmp_path / "c.pt", {"rng": io_utils.get_rng_state(), "x": np.float64(2.5)})
    a = (np.random.rand(3), torch.rand(3))
    ck = io_utils.load_checkpoint(tmp_path / "c.pt")
    assert ck["x"] == 2.5 and type(ck["x"]) is float
    io_utils.set_rng_state(ck["rng"])
    b = (np.random.rand(3), torch.rand(3))
    assert np.array_equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_resume_from_weights_only_checkpoint(tmp_path):
    """A real run's checkpoint (model, Adam, scheduler, RNG, history) loads with weights_only=True."""
    train(_cfg(tmp_path, steps=2, checkpoint_every=1))
    ck = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert ck["step"] == 2
    m = train(_cfg(tmp_path, steps=2, checkpoint_every=1, resume=True))
    assert m["timings"]["iterations"] == 0 and len(m["loss_history"]["total"]) == 2
    with pytest.raises(io_utils.CheckpointError, match="refusing to resume"):
        train(_cfg(tmp_path, steps=3, resume=True))  # steps is part of the fingerprint


# ----------------------------------------------------------------------------- output-dir lock (case 6)
def test_second_lock_on_one_dir_is_refused_and_released(tmp_path):
    with io_utils.lock_output_dir(tmp_path) as lock:
        holder = json.loads(lock.read_text())
        assert holder["pid"] == os.getpid() and holder["host"] == socket.gethostname()
        with pytest.raises(io_utils.OutputDirLockedError, match=rf"{tmp_path}.*in use by another run.*"
                                                                rf"pid {os.getpid()}.*another output_dir"):
            with io_utils.lock_output_dir(tmp_path):
                pass
    assert not lock.exists()
    with pytest.raises(RuntimeError, match="boom"), io_utils.lock_output_dir(tmp_path):
        raise RuntimeError("boom")
    assert not lock.exists()  # released on exceptions too
    with io_utils.lock_output_dir(tmp_path):
        pass


def test_train_refuses_a_locked_output_dir(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    with io_utils.lock_output_dir(out):
        with pytest.raises(io_utils.OutputDirLockedError, match=rf"{out}.*in use by another run"):
            train(_cfg(tmp_path))
        assert sorted(p.name for p in out.iterdir()) == [".lock"]  # nothing written by the refused run


_HOLDER = textwrap.dedent("""
    import fcntl, json, os, socket, sys
    fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.write(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "time": "t", "argv": "x"}).encode())
    print("locked", flush=True)
    sys.stdin.read()
""")


@pytest.mark.skipif(sys.platform == "win32", reason="fcntl locks")
def test_lock_of_another_process_then_stale_after_it_dies(tmp_path):
    lock = tmp_path / io_utils.LOCK_NAME
    proc = subprocess.Popen([sys.executable, "-c", _HOLDER, str(lock)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        with pytest.raises(io_utils.OutputDirLockedError, match=rf"pid {proc.pid} on host"):
            with io_utils.lock_output_dir(tmp_path):
                pass
    finally:
        proc.kill()  # like SIGKILL: the lock file stays, the kernel drops the flock
        proc.wait()
    assert lock.exists()
    with pytest.warns(io_utils.StaleLockWarning, match=rf"stale lock of pid {proc.pid}.*not running"):
        with io_utils.lock_output_dir(tmp_path):
            assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert not lock.exists()


@pytest.mark.skipif(sys.platform == "win32", reason="fcntl locks")
def test_file_system_without_locks_is_named(tmp_path, monkeypatch):
    import errno
    import fcntl

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with pytest.raises(io_utils.OutputDirError, match=rf"{tmp_path}.*cannot be locked.*local file system"):
        with io_utils.lock_output_dir(tmp_path):
            pass


# ----------------------------------------------------------------------------- no partial output
def test_failing_writer_leaves_no_partial_output(tmp_path, monkeypatch):
    """A run stopped while writing its outputs adds none of them (metrics.json comes last)."""
    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(frame_plots, "plot_singularities", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        train(_cfg(tmp_path))
    out = tmp_path / "run"
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]  # the last good checkpoint only


def test_staged_outputs_keep_old_files_on_failure(tmp_path):
    (tmp_path / "metrics.json").write_text("old")
    with pytest.raises(ValueError, match="half"), io_utils.staged_outputs(tmp_path) as stage:
        (stage / "metrics.json").write_text("new")
        (stage / "frames.vtu").write_text("partial")
        raise ValueError("half written")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]
    assert (tmp_path / "metrics.json").read_text() == "old"
    with io_utils.staged_outputs(tmp_path) as stage:
        (stage / "metrics.json").write_text("new")
        (stage / "frames.vtu").write_text("full")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames.vtu", "metrics.json"]
    assert (tmp_path / "metrics.json").read_text() == "new"


def test_finished_run_leaves_no_temporary_files(tmp_path):
    train(_cfg(tmp_path))
    out = tmp_path / "run"
    assert _leftovers(out) == []
    assert {"frames.npz", "metrics.json", "checkpoint.pt"} <= {p.name for p in out.iterdir()}


@pytest.mark.slow  # a subprocess (about 4 s of imports); in-process: test_resume_no_from_the_command_line_is_refused
def test_cli_bad_value_exits_nonzero_naming_the_key(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run([sys.executable, "-m", "training.train_frames", "steps=1.5", f"output_dir={tmp_path / 'x'}",
                        f"hydra.run.dir={tmp_path / 'h'}"], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=120, check=False)
    assert r.returncode != 0 and "ConfigError" in r.stderr and "'steps' = 1.5" in r.stderr
    assert not (tmp_path / "x").exists()
