"""Sphinx extension of the torchconn docs: the API reference under the names users import.

Every object is documented once, under its *public name*: the first ``namespace.name`` of
:func:`public_namespaces` whose ``__all__`` lists it (``torchconn.Curvature``, not
``torchconn.nn.modules.Curvature``; ``torchconn.so3.exp``, not ``torchconn.lie.so3.exp``).

* ``.. public-api:: NAMESPACE`` (option ``:names: a b c``, default: the namespace's whole
  ``__all__``) writes one autodoc directive per name under that public name, and one line
  linking the names of the namespace that are documented under another public name
  (``torchconn.mesh.TetMesh`` is ``torchconn.TetMesh``).
* ``.. automodule::`` of a module with ``:members:`` skips the objects that have a public name
  (they are documented there), so a module's page lists what only that module holds.

``tests/test_docs.py`` reads the built inventory (``objects.inv``) and checks both rules: every
name of every namespace here is documented, under its public name, and no class or function
twice.
"""
from __future__ import annotations

import importlib
import inspect
import re
import sys
from functools import lru_cache
from typing import Any

from docutils import nodes
from docutils.parsers.rst import directives
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective

def public_namespaces() -> list[str]:
    """The namespaces users import, in priority order: ``torchconn`` (``import torchconn as tc``),
    then every module its ``__all__`` names, in that order (``torchconn.mesh``, ``torchconn.so3``,
    ``torchconn.frames``, ...). An object listed by several is documented under the first."""
    import torchconn

    return ["torchconn"] + [f"torchconn.{n}" for n in torchconn.__all__ if inspect.ismodule(getattr(torchconn, n))]


def resolve(name: str) -> Any:
    """The object a dotted name refers to, through attributes as a user reaches it
    (``torchconn.so3`` is the attribute ``so3`` of ``torchconn``, the module ``torchconn.lie.so3``)."""
    parts = name.split(".")
    obj = importlib.import_module(parts[0])
    for i, part in enumerate(parts[1:], start=1):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            obj = importlib.import_module(".".join(parts[: i + 1]))  # a submodule not imported yet
    return obj


def public_names(namespace: str) -> list[str]:
    """The documented names of a namespace: its ``__all__`` without submodules and dunders."""
    ns = resolve(namespace)
    return [n for n in ns.__all__ if not n.startswith("__") and not inspect.ismodule(getattr(ns, n))]


@lru_cache(maxsize=None)
def owners() -> dict[int, str]:
    """``id(object)`` -> its public name (the first namespace listing it wins)."""
    out: dict[int, str] = {}
    for namespace in public_namespaces():
        ns = resolve(namespace)
        for name in public_names(namespace):
            out.setdefault(id(getattr(ns, name)), f"{namespace}.{name}")
    return out


def data_doc(namespace: str, name: str) -> list[str]:
    """The ``#:`` doc comment of the constant ``namespace.name``, found in the module that assigns
    it (autodoc reads the comment from the module it is told, which for ``torchconn.so3.X`` or
    ``torchconn.frames.METRIC_KEYS`` is not where the assignment is)."""
    from sphinx.errors import PycodeError
    from sphinx.pycode import ModuleAnalyzer

    ns = resolve(namespace)
    obj = getattr(ns, name)
    candidates = [ns.__name__] + sorted(m for m, mod in list(sys.modules.items())
                                        if m.startswith(ns.__name__ + ".") and getattr(mod, name, None) is obj)
    for modname in candidates:
        try:
            docs = ModuleAnalyzer.for_module(modname).find_attr_docs()
        except PycodeError:
            continue
        if ("", name) in docs:
            return list(docs[("", name)])
    return []


def _directive(obj: Any) -> str:
    if inspect.isclass(obj):
        return "autoexception" if issubclass(obj, BaseException) else "autoclass"
    if inspect.isfunction(obj) or inspect.isbuiltin(obj) or inspect.ismethod(obj):
        return "autofunction"
    return "autodata"


class PublicApi(SphinxDirective):
    """``.. public-api:: NAMESPACE`` with an optional ``:names:`` subset (see the module docstring)."""

    required_arguments = 1
    option_spec = {"names": directives.unchanged}

    def run(self) -> list[nodes.Node]:
        namespace = self.arguments[0]
        ns = resolve(namespace)
        available = public_names(namespace)
        names = self.options["names"].split() if "names" in self.options else available
        unknown = [n for n in names if n not in available]
        if unknown:
            raise self.error(f"public-api: {namespace}.__all__ does not list {unknown}")
        lines, elsewhere = [], []
        for name in names:
            obj, full = getattr(ns, name), f"{namespace}.{name}"
            owner = owners()[id(obj)]
            if owner != full:
                elsewhere.append(f":py:obj:`{name} <{owner}>`")
                continue
            lines += [f".. {_directive(obj)}:: {full}", ""]
            if _directive(obj) == "autodata":
                lines += [f"   {line}" if line else "" for line in data_doc(namespace, name)] + [""]
        if elsewhere:
            lines += [f"Also importable from ``{namespace}`` and documented under their public names: "
                      + ", ".join(elsewhere) + ".", ""]
        content = StringList(lines, source=f"<public-api {namespace}>")
        node = nodes.Element()
        self.state.nested_parse(content, self.content_offset, node)
        return node.children


def _skip_public_members(app, what: str, name: str, obj: Any, skip: bool, options) -> bool | None:
    """In a module's member list, skip an object that is documented under its public name."""
    if what == "module" and id(obj) in owners():
        return True
    return None


def _drop_type_docstrings(app, what: str, name: str, obj: Any, options, lines: list[str]) -> None:
    """A constant without a doc comment of its own shows no text, not its type's docstring
    (``dict() -> new empty dictionary ...`` for a dict), nor a named tuple's field Python's
    ``Alias for field number 0``."""
    if what in ("attribute", "property") and re.fullmatch(r"Alias for field number \d+", "\n".join(lines).strip()):
        lines.clear()
        return
    if what in ("data", "attribute") and lines and not inspect.isclass(obj) and not callable(obj):
        type_doc = type(obj).__doc__
        own = inspect.cleandoc(type_doc) if isinstance(type_doc, str) else ""
        if own and "\n".join(lines).strip() == own.strip():
            lines.clear()


def _alias_real_module_names(app, env) -> None:
    """Make a module's real name a cross-reference target of the page of its public name:
    ``:mod:`.curvature``` in ``torchconn.dec``'s docstring means ``torchconn.dec.curvature``,
    documented as ``torchconn.curvature`` (classes and functions get the same through autodoc's
    ``:canonical:``). The inventory lists the real name as a module too (a valid import path)."""
    py = env.get_domain("py")
    for name, entry in list(py.objects.items()):
        if entry.objtype != "module":
            continue
        try:
            real = resolve(name)
        except (ImportError, AttributeError):
            continue
        real_name = getattr(real, "__name__", name) if inspect.ismodule(real) else name
        if real_name != name and real_name not in py.objects:
            py.objects[real_name] = entry._replace(aliased=True)
            py.modules[real_name] = py.modules[name]


def _relative_module_refs(app, doctree) -> None:
    """``:mod:`.solver``` in a docstring names a module as a relative import would: a child of
    the documented package, or a sibling of the documented module (``torchconn.hexmesh.solver``
    from ``torchconn.hexmesh.seamless``), not any module whose name ends in ``.solver``."""
    from sphinx.addnodes import pending_xref

    for node in doctree.findall(pending_xref):
        # the role strips the leading dot of ".solver" and marks the reference refspecific
        target, current = node.get("reftarget", ""), node.get("py:module")
        if node.get("refdomain") != "py" or node.get("reftype") != "mod" or not node.get("refspecific") or not current:
            continue
        try:
            mod = resolve(current)
        except (ImportError, AttributeError):
            continue
        base = getattr(mod, "__name__", current)
        if inspect.ismodule(mod) and not hasattr(mod, "__path__"):
            base = base.rpartition(".")[0]
        try:
            importlib.import_module(f"{base}.{target}")
        except ImportError:
            continue
        node["reftarget"], node["refspecific"] = f"{base}.{target}", False


def setup(app) -> dict[str, Any]:
    app.connect("doctree-read", _relative_module_refs)
    app.add_directive("public-api", PublicApi)
    app.connect("autodoc-skip-member", _skip_public_members)
    app.connect("autodoc-process-docstring", _drop_type_docstrings)
    app.connect("env-updated", _alias_real_module_names)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
