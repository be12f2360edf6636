"""Per-mesh cache of kernel tables: ``mesh.require`` where the mesh has it.

A ``TetMesh`` caches derived data itself (``mesh.require(name, builder)``). Mesh-like objects
without ``require`` (e.g. :class:`torchconn.nn.MeshBuffers`, which duck-types as a mesh) get the
same cache here, held weakly: it goes away with the object, and no attribute is set on it.
"""
from __future__ import annotations

import weakref

_FALLBACK: "weakref.WeakKeyDictionary[object, dict]" = weakref.WeakKeyDictionary()


def require(mesh, name: str, builder):
    """``builder(mesh)`` built once per mesh object under ``name`` (the builder must not keep ``mesh``)."""
    req = getattr(mesh, "require", None)
    if req is not None:
        return req(name, builder)
    try:
        cache = _FALLBACK.setdefault(mesh, {})
    except TypeError:  # not weak-referenceable: no cache
        return builder(mesh)
    if name not in cache:
        cache[name] = builder(mesh)
    return cache[name]
