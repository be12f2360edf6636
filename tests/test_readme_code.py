"""The code a reader copies first runs as written: every Python block of README.md and of
docs/quickstart.md, every ``torchconn.`` name the README mentions, and every command it lists.

A Python block right after a line ``<!-- test: skip: REASON -->`` (a file the reader brings, the
shared data, a run of minutes) is not executed: its imports are, and the test is reported as
skipped with that reason. The commands are checked without running the jobs: each module, console
script and example exists, each ``--flag`` is one the benchmark's parser declares, and each
``key=value`` of a job composes with its Hydra config (the commands themselves were run by hand:
they take seconds to hours).

Cost: ~6 s alone on 2 cores, most of it the README's API tour (its tetgen ball) and the quick
start's 50 optimizer steps.
"""
from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SKIP_MARK = re.compile(r"<!-- test: skip: (.+?) -->\s*$")


def _python_blocks(path: Path) -> list:
    """One ``pytest.param(code, skip_reason)`` per fenced Python block, id ``file:line``."""
    lines = path.read_text().splitlines()
    out, i = [], 0
    while i < len(lines):
        if lines[i].strip() == "```python":
            start = i
            i += 1
            body = []
            while lines[i].strip() != "```":
                body.append(lines[i])
                i += 1
            mark = SKIP_MARK.match(lines[start - 1].strip()) if start else None
            out.append(pytest.param("\n".join(body) + "\n", mark.group(1) if mark else None,
                                    id=f"{path.relative_to(ROOT)}:{start + 1}"))
        i += 1
    return out


BLOCKS = _python_blocks(README) + _python_blocks(ROOT / "docs" / "quickstart.md")


def test_the_blocks_are_found():
    assert len(BLOCKS) >= 4, [b.id for b in BLOCKS]  # README: API tour, frame fields; quick start: two


@pytest.mark.parametrize("code, skip_reason", BLOCKS)
def test_python_block_runs(code, skip_reason, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a block that writes files writes them here
    tree = ast.parse(code)
    if skip_reason is not None:
        imports = ast.Module([n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))], type_ignores=[])
        exec(compile(imports, "<block imports>", "exec"), {})  # noqa: S102 - documentation under test
        pytest.skip(f"imports checked; not run: {skip_reason}")
    exec(compile(tree, "<block>", "exec"), {})  # noqa: S102 - documentation under test


def _inline_spans(text: str) -> list[str]:
    """The inline code spans of Markdown text (fenced blocks removed; a span wrapped over two lines
    is one span, its line break a space)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return [" ".join(s.split()) for s in re.findall(r"`([^`]+)`", text)]


# ----------------------------------------------------------------------------- names
def _resolve(name: str):
    parts = name.split(".")
    obj = importlib.import_module(parts[0])
    for i, part in enumerate(parts[1:], start=1):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            obj = importlib.import_module(".".join(parts[: i + 1]))
    return obj


def test_every_torchconn_name_in_the_readme_imports():
    """``torchconn.frames.candidates.connection_candidates``, ``torchconn.ops.compiled(False)``, ... resolve as
    written (``torch.ops.torchconn.<op>`` names ops, not modules; ``torchconn.training`` and
    ``torchconn.configs`` exist once installed and are ``training/`` and ``configs/`` in a checkout)."""
    names = set()
    for span in _inline_spans(README.read_text()):
        for m in re.finditer(r"(?<![\w.:/])torchconn(?:\.[A-Za-z_]\w*)+", span):
            names.add(m.group(0))
    assert len(names) > 10, sorted(names)
    installed_only = {"torchconn.training": "training", "torchconn.configs": "configs"}
    unresolved = []
    for name in sorted(names):
        if name in installed_only:
            assert (ROOT / installed_only[name]).is_dir(), name
            continue
        try:
            _resolve(name)
        except (ImportError, AttributeError) as exc:
            unresolved.append(f"{name}: {exc}")
    assert unresolved == [], unresolved


# ----------------------------------------------------------------------------- commands
def _command_spans() -> list[str]:
    """Inline code and bash lines of the README that are commands."""
    text = README.read_text()
    spans = _inline_spans(text)
    for block in re.findall(r"```(?:bash|sh)\n(.*?)```", text, flags=re.S):
        spans += [line for line in block.splitlines() if line.strip()]
    starts = ("python -m ", "python examples/", "torchconn-", "sphinx-build", "pip install")
    return [s for s in spans if any(p in s for p in starts)]


def test_every_command_module_script_and_example_exists():
    spans = _command_spans()
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    modules = {m for s in spans for m in re.findall(r"python -m ([\w.]*\w)\b(?!\.<)", s)}  # not training.<job>
    assert {"training.train_frames", "training.hex_mesh", "benchmarks.run", "pytest"} <= modules, modules
    missing = [m for m in sorted(modules) if importlib.util.find_spec(m) is None]
    assert missing == [], f"README runs modules that do not exist: {missing}"
    used = {m for s in spans for m in re.findall(r"\b(torchconn-[a-z]+)", s)}
    assert {"torchconn-frames", "torchconn-hex"} <= used, used
    assert used <= set(scripts), f"README names console scripts pyproject.toml does not declare: {used - set(scripts)}"
    for script in used:  # the entry point's module is the checkout's training/<job>.py
        module, _, func = scripts[script].partition(":")
        path = ROOT / "training" / (module.rsplit(".", 1)[1] + ".py")
        assert path.is_file() and f"def {func}(" in path.read_text(), (script, scripts[script])
    examples = {e for s in spans for e in re.findall(r"python (examples/\w+\.py)", s)}
    assert examples and all((ROOT / e).is_file() for e in examples), examples


def _parser_flags(module: str) -> set[str]:
    """The ``--flags`` a benchmark's argparse parser declares (``add_argument("--x", ...)`` calls,
    read from the source: importing the benchmarks costs seconds)."""
    tree = ast.parse((ROOT / (module.replace(".", "/") + ".py")).read_text())
    return {arg.value for node in ast.walk(tree)
            if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument"
            for arg in node.args if isinstance(arg, ast.Constant) and str(arg.value).startswith("--")}


def test_every_benchmark_flag_in_the_readme_is_accepted():
    """Each ``--flag`` the README (and docs/results/performance.md, where its performance tables
    moved) passes to ``python -m benchmarks.<name>`` is one its parser declares."""
    flags: dict[str, set[str]] = {}
    text = README.read_text() + "\n" + (README.parent / "docs" / "results" / "performance.md").read_text()
    for span in _inline_spans(text):
        for m in re.finditer(r"python -m (benchmarks\.\w+)((?:\s+(?:\[?--[\w-]+(?:\s+[^\s`\[\]-][^\s`\[\]]*)*\]?))*)", span):
            flags.setdefault(m.group(1), set()).update(re.findall(r"--[\w-]+", m.group(2)))
    assert "benchmarks.run" in flags and "--quick" in flags["benchmarks.run"], flags
    assert "--box" in flags.get("benchmarks.operators", set()), flags
    unknown = {m: sorted(fs - _parser_flags(m)) for m, fs in flags.items()}
    assert all(not u for u in unknown.values()), f"flags the parsers do not declare: {unknown}"
    assert "--quick" in _parser_flags("benchmarks.run") and "--no-such-flag" not in _parser_flags("benchmarks.run")


def test_every_job_override_in_the_readme_composes():
    """``torchconn-frames [mesh=PATH] [method=connection|sh_baseline] ...``, the Commands' and the
    frame-field section's ``key=value`` overrides compose with the job's Hydra config (struct mode:
    an unknown key fails)."""
    pytest.importorskip("hydra", reason="hydra-core is not installed (pip install -e '.[train]')")
    from hydra import compose, initialize_config_dir

    import training.schema  # noqa: F401 - stores the jobs' schemas in Hydra's ConfigStore, as the jobs do

    text = README.read_text()
    commands = text.split("## Commands", 1)[1].split("\n## ", 1)[0]
    jobs = {"torchconn-frames": "train_frames", "torchconn-hex": "hex_mesh",
            "torchconn-convergence": "convergence", "torchconn-demo": "demo"}
    overrides: dict[str, list[str]] = {job: [] for job in jobs.values()}
    for span in [s for s in _inline_spans(commands) if re.match(r"torchconn-[a-z]+ ", s)]:
        script, _, rest = span.partition(" ")
        for tok in re.findall(r"\[?([\w.]+=[^\s\]]+)\]?", rest):
            key, _, value = tok.partition("=")
            overrides[jobs[script]].append(f"{key}={value.split('|')[0]}")
    frames_section = text.split("## Frame fields", 1)[1].split("\n## ", 1)[0]
    for span in _inline_spans(frames_section):
        for part in span.split():
            if re.fullmatch(r"[a-z_]+(?:\.[a-z_]+)*=\S+", part) and not part.startswith(("method=\"", "steps=")):
                overrides["train_frames"].append(part)
    assert overrides["hex_mesh"] and overrides["train_frames"] and overrides["demo"], overrides
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        for job, ovs in overrides.items():  # one composition per job: raises on an unknown key or option
            compose(config_name=job, overrides=ovs)
