"""The documentation: it builds from the docstrings with warnings as errors, opens with the install
and quick-start page, documents every module and every public name once, under the name users
import (``torchconn.Curvature``, not ``torchconn.nn.modules.Curvature``), and shows no text a
class inherits from torch or Python.

Cost: one Sphinx build (~15 s alone on 2 cores), shared by the tests that read its output; the
other tests read files and import the package (< 1 s).
"""
from __future__ import annotations

import importlib
import inspect
import re
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
import torch

import torchconn

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PACKAGE = ROOT / "torchconn"


def _resolve(name: str):
    """The object a dotted name reaches as a user would (``torchconn.so3`` is an attribute of
    ``torchconn``); a module shadowed by a same-named attribute (``torchconn.frames.design``) by import."""
    parts = name.split(".")
    obj = importlib.import_module(parts[0])
    for i, part in enumerate(parts[1:], start=1):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            obj = importlib.import_module(".".join(parts[: i + 1]))
    return obj


def _public_namespaces() -> list[str]:
    """``torchconn`` and every module its ``__all__`` names (``torchconn.so3``, ``torchconn.frames``, ...)."""
    return ["torchconn"] + [f"torchconn.{n}" for n in torchconn.__all__ if inspect.ismodule(getattr(torchconn, n))]


def _public_names() -> dict[str, object]:
    """``namespace.name`` -> object for every non-module, non-dunder name of a public ``__all__``."""
    out = {}
    for namespace in _public_namespaces():
        ns = _resolve(namespace)
        for name in getattr(ns, "__all__", []):
            if not name.startswith("__") and not inspect.ismodule(getattr(ns, name)):
                out[f"{namespace}.{name}"] = getattr(ns, name)
    return out


# ----------------------------------------------------------------------------- source checks
def _automodule_names() -> list[str]:
    text = "\n".join(p.read_text() for p in (DOCS / "api").glob("*.md"))
    return re.findall(r"^\s*\.\. automodule:: (\S+)", text, flags=re.M)


def test_every_module_has_an_api_entry():
    """Every module of ``torchconn/`` is on an API page (``.. automodule::``), under its own name or
    the public alias users import (``torchconn.so3`` for ``torchconn/lie/so3.py``): a new module
    needs one line in ``docs/api/<subpackage>.md``."""
    documented = set()
    for name in _automodule_names():
        obj = _resolve(name)
        if not inspect.ismodule(obj):  # a module shadowed by its own main function
            obj = importlib.import_module(name)
        documented.add(obj.__name__)
    missing = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if any(p.startswith("_") for p in parts):
            continue  # private modules (lie/_validate.py) are not API
        if ".".join(parts) not in documented:
            missing.append(".".join(parts))
    assert missing == [], f"modules without an automodule entry in docs/api/: {missing}"


def test_conventions_sections_are_numbered_as_cited():
    """Docstrings cite "docs/conventions.md §N"; the numbers are fixed."""
    headings = re.findall(r"^## (\d+)\. (.+)$", (DOCS / "conventions.md").read_text(), flags=re.M)
    assert [(n, t.split()[0]) for n, t in headings] == [("1", "Conventions"), ("2", "Errata"), ("3", "The")]


def test_index_opens_with_the_quick_start_and_no_notes_about_the_docs_tool():
    index = (DOCS / "index.md").read_text()
    toctrees = re.findall(r"```\{toctree\}\n(.*?)```", index, flags=re.S)
    entries = [line.strip() for t in toctrees for line in t.splitlines() if line.strip() and not line.startswith(":")]
    assert entries[0] == "quickstart", entries
    assert "sphinx" not in index.lower() and "mkdocs" not in index.lower()
    quick = (DOCS / "quickstart.md").read_text()
    for must in ('pip install -e ".[train]" && python -m training.train_frames', "python -m pytest -q",
                 "torchconn-hex", "python -m training.hex_mesh", "```python"):
        assert must in quick, must


def test_each_public_module_forward_has_its_own_docstring():
    """The nn.Modules users import state their forward's inputs and outputs themselves; torch's
    ``Module.forward`` text ("Define the computation performed at every call") is not theirs."""
    torch_doc = torch.nn.Module.forward.__doc__
    modules = [obj for obj in _public_names().values() if inspect.isclass(obj) and issubclass(obj, torch.nn.Module)
               and obj.forward is not torch.nn.Module.forward]  # MeshBuffers holds buffers, it has no forward
    assert {"Curvature", "AveragedCovariantD", "ConnectionField"} <= {m.__name__ for m in modules}
    for cls in modules:
        doc = cls.forward.__doc__
        assert doc and doc != torch_doc, f"{cls.__name__}.forward has no docstring of its own"
        assert "(*batch" in (cls.__doc__ or "") + doc, f"{cls.__name__}: no batched shape (*batch...) stated"
    assert "(*batch, T, 3)" in torchconn.AveragedCovariantD.__doc__


# ----------------------------------------------------------------------------- the built site
@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    pytest.importorskip("sphinx", reason="sphinx is not installed (pip install -e '.[docs]')")
    pytest.importorskip("myst_parser", reason="myst-parser is not installed (pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("docs") / "html"
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS), str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-6000:]
    return out


def _inventory(site: Path) -> list[tuple[str, str, int]]:
    """``(name, domain:role, priority)`` of every entry of the built ``objects.inv`` (priority -1:
    an alias, e.g. the defining path autodoc records as ``:canonical:``)."""
    raw = (site / "objects.inv").read_bytes()
    body = zlib.decompress(raw.split(b"\n", 4)[4]).decode()
    entries = []
    for line in body.splitlines():
        m = re.match(r"(.+?)\s+(\S+:\S+)\s+(-?\d+)\s+\S+\s+.*$", line)
        if m:
            entries.append((m.group(1), m.group(2), int(m.group(3))))
    return entries


def test_sphinx_build_has_no_warnings(site):
    for page in ("index", "quickstart", "conventions", "architecture", "api/index", "api/nn", "api/dec",
                 "api/frames", "api/hexmesh", "results/convergence"):
        assert (site / f"{page}.html").is_file(), page
    # autodoc really ran: a function's signature is on its page
    assert "two_prong" in (site / "api" / "dec.html").read_text()
    # a constant documented under a public alias keeps the doc comment of the module that assigns it
    assert "Storage orders of a quaternion" in (site / "api" / "lie.html").read_text()
    # the quick start comes first in the navigation
    index = (site / "index.html").read_text()
    assert index.find('href="quickstart.html"') < index.find('href="conventions.html"')


def test_every_public_name_is_documented_once_under_its_public_name(site):
    """Each name of a public ``__all__`` (``torchconn``, ``torchconn.so3``, ``torchconn.frames``, ...)
    is documented, under a public name; no class or function is documented under two names."""
    documented: dict[int, list[str]] = {}
    for name, role, priority in _inventory(site):
        if role in ("py:class", "py:function", "py:exception", "py:data") and priority >= 0:
            documented.setdefault(id(_resolve(name)), []).append(name)
    public = _public_names()
    missing = [n for n, obj in public.items() if not set(documented.get(id(obj), [])) & set(public)]
    assert missing == [], f"public names without an entry under a public name in the docs: {missing}"
    twice = {names[0]: names for names in documented.values()
             if len(names) > 1 and (inspect.isclass(_resolve(names[0])) or callable(_resolve(names[0])))}
    assert twice == {}, f"documented under several names: {twice}"
    names = {n for n, _, p in _inventory(site) if p >= 0}
    for must in ("torchconn.Curvature", "torchconn.AveragedCovariantD", "torchconn.so3.exp",
                 "torchconn.so3.quat_to_matrix", "torchconn.frames.design", "torchconn.frames.write_frames_vtu",
                 "torchconn.hexmesh.hex_mesh", "torchconn.join_meshes", "torchconn.TetMeshBatch",
                 "torchconn.mesh.merge_duplicate_vertices", "torchconn.mesh.to_meshio"):
        assert must in names, must
    assert "torchconn.nn.modules.Curvature" not in names  # only the alias autodoc records (priority -1)


def test_no_text_inherited_from_torch_or_python(site):
    """No page shows a docstring a class inherits from torch (every ``nn.Module.forward``,
    ``autograd.Function``) or Python (a named tuple's fields, a dict constant's type)."""
    boilerplate = [inspect.cleandoc(torch.nn.Module.forward.__doc__).splitlines()[0],
                   "Alias for field number", "new empty dictionary", "Built-in immutable sequence"]
    for page in site.rglob("*.html"):
        text = page.read_text()
        for phrase in boilerplate:
            assert phrase not in text, f"{page.relative_to(site)}: {phrase!r}"
