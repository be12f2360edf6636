"""Per-mesh cache of kernel tables: ``mesh.require`` where the mesh has it.

A ``TetMesh`` caches derived data itself (``mesh.require(name, builder)``). Mesh-like objects
without ``require`` (e.g. :class:`torchconn.nn.MeshBuffers`, which duck-types as a mesh) get the
same cache here, held weakly: it goes away with the object, and no attribute is set on it.

Tables are built eagerly, on the mesh's real tensors, whoever asks first:

* inside a ``torch.func`` transform (``grad``, ``vmap``, ``jacrev``, ...) every tensor op
  returns a wrapper of that transform (no storage, so no NumPy view; dead once the transform
  exits), so :func:`require` runs its builders with the transforms switched off;
* while ``torch.compile`` traces, the mesh's tensors are fake (no values: a NumPy schedule
  cannot be built from them) and a cache lookup would put Python side effects into the graph,
  so the public table functions are wrapped in :func:`traced_constant`: dynamo calls them on
  the real mesh at trace time and puts their tables into the graph as constants.
"""
from __future__ import annotations

import functools
import weakref

import torch

from .backend import _plain

__all__ = ["require", "traced_constant", "edge_ends", "edge_index", "edge_vectors"]

#: Whether this torch's dynamo passes an object (the mesh) to an ``assume_constant_result``
#: function: torch 2.13 does (guarded on its identity); torch 2.11 does not ("MeshBuffers is not a
#: constant", seen on an H100 machine with torch 2.11, 2026-11-27), so :func:`traced_constant`
#: then stops the trace with a message that names the version instead of dynamo's internal error.
COMPILE_SUPPORTED = tuple(int(x) for x in torch.__version__.split("+")[0].split(".")[:2]) >= (2, 13)

_FALLBACK: "weakref.WeakKeyDictionary[object, dict]" = weakref.WeakKeyDictionary()


def require(mesh, name: str, builder):
    """``builder(mesh)`` built once per mesh object under ``name`` (the builder must not keep ``mesh``).

    The builder runs outside any ``torch.func`` transform (module doc), so the cached tables
    are plain tensors even when first asked for inside ``torch.func.grad`` or ``vmap``."""
    def build(m):
        with torch._C._DisableFuncTorch():
            return builder(m)

    req = getattr(mesh, "require", None)
    if req is not None:
        return req(name, build)
    try:
        cache = _FALLBACK.setdefault(mesh, {})
    except TypeError:  # not weak-referenceable: no cache
        return build(mesh)
    if name not in cache:
        cache[name] = build(mesh)
    return cache[name]


def traced_constant(fn):
    """``fn(mesh, *constants)``, a per-mesh table function, callable while ``torch.compile`` traces.

    Eagerly it is ``fn``. While dynamo traces, ``fn`` is not traced but called on the real
    mesh object (:func:`torch.compiler.assume_constant_result`; the graph is guarded on the
    identity of ``mesh``) and its result — tensors, tuples of tensors, a table object — enters
    the graph as constants: the tables are built (or found in the mesh's cache) once, at trace
    time, never inside the compiled code, whether or not an eager call came first. The other
    arguments must be Python constants (device, dtype, str, int); ``fn``'s result must depend
    only on them and the mesh's topology (built once per mesh, as every :func:`require` table)."""
    def constant(mesh, *args):
        return fn(mesh, *args)

    torch.compiler.assume_constant_result(constant)

    @functools.wraps(fn)
    def call(mesh, *args):
        if torch.compiler.is_compiling():
            if not COMPILE_SUPPORTED:
                raise RuntimeError(
                    f"torchconn under torch.compile needs torch >= 2.13 (this is torch {torch.__version__}, "
                    f"whose dynamo cannot take the mesh's tables as constants); call it eagerly or upgrade torch")
            return constant(mesh, *args)
        return fn(mesh, *args)

    return call


@traced_constant
def edge_ends(mesh, device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(i (E,), j (E,))``: the columns of ``mesh.edges`` as contiguous long tensors on ``device``
    (built once per mesh and device), the indices of per-edge gathers such as ``F_i``, ``F_j``.

    Not the strided views ``edges[:, 0]``, ``edges[:, 1]``: inductor's vectorized CPU code
    (torch 2.13) reads a strided index tensor as contiguous in the backward of a gather:
    ``torch.compile`` of ``(F[e[:, 0]] @ R @ F[e[:, 1]]ᵀ).sin().sum()`` gave gradients off by
    O(1) in float64 and heap corruption in float32 (correct with ``cpp.simdlen=1`` or with
    contiguous indices), which broke the frame-field loss differentiated in the frames."""
    dev = torch.device(device)
    return require(mesh, f"ops.edge_ends.{dev}",
                   lambda m: tuple(m.edges[:, k].to(dev).contiguous() for k in (0, 1)))


@traced_constant
def edge_index(mesh, device) -> torch.Tensor:
    """``mesh.edges`` as a contiguous ``(E, 2)`` int64 tensor on ``device`` (built once per mesh and
    device): the edge table a C kernel reads."""
    dev = torch.device(device)
    return require(mesh, f"ops.edge_index.{dev}", lambda m: m.edges.to(dev, torch.int64).contiguous())


def edge_vectors(mesh, device, dtype):
    """``v_j - v_i`` of every canonical edge ``(i, j)`` of ``mesh.edges``: ``(E, 3)`` on ``device``, ``dtype``.

    Geometry, unlike the tables above, can change: the result is cached per mesh only for the
    vertex tensor it was computed from (the same object at the same version counter, so an
    in-place edit or a ``.to()`` of the mesh recomputes it). Vertices that require grad or are
    a ``torch.func`` wrapper (differentiated by a transform) are never cached: the result is
    then differentiable in them. Under ``torch.compile`` the two gathers and the subtraction
    are traced into the graph (a version counter cannot be guarded on, and the compiled code
    fuses them). Saves two gathers and a subtraction over the edges per eager call (~20 ms at
    1M tets on the 2-core machine)."""
    verts = mesh.vertices
    if (torch.compiler.is_compiling() or verts.requires_grad or verts.device.type == "meta"
            or not _plain(verts)):
        return _edge_vectors(mesh, verts, device, dtype)
    dev = torch.device(device)
    slot = require(mesh, f"ops.edge_vectors.{dev}.{dtype}", lambda m: [None, -1, None])
    if slot[0] is not verts or slot[1] != verts._version:
        # keep the vertex tensor itself: an id could be reused by a new tensor once it is freed
        with torch._C._DisableFuncTorch():  # plain tensors in the cache, even inside a transform
            vec = _edge_vectors(mesh, verts, dev, dtype)
        slot[:] = verts, verts._version, vec
    return slot[2]


def _edge_vectors(mesh, verts, device, dtype):
    i, j = edge_ends(mesh, device)
    v = verts.to(device=device, dtype=dtype)
    return v.index_select(0, j) - v.index_select(0, i)
