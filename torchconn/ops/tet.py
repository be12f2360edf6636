"""Averaged ``d∇d∇θ`` on tets as a custom op: the per-tet closed form of ``𝔡∇ Alt 𝔡∇ Alt θ̃``.

The end-of-Ch. 5 tetrahedron formula (:func:`torchconn.dec.dnabla.wedge_curvature_solder_tet`)
regrouped as three rounds of matrix-vector products on the 6 edge rotations of each tet, with
``θ̃`` formed once per *edge* (both directions), never per tet, and gathered per tet from index
tables built once per mesh (:class:`TetKernel`, cached with ``mesh.require``).

The op ``torchconn::tet_dd`` (:func:`tet_dd`) maps ``edge_rot (*B, E, 3, 3)`` and
``edge_theta (*B, E, 2, 3)`` to ``(*B, T, 3)``:

* CPU kernel: ``csrc/tet.c`` (OpenMP over tets, float32/float64, the leading batch looped in C)
  when :func:`torchconn.ops.backend.can_use_compiled` allows it, else the generic kernel;
* generic kernel (every device and float dtype): the component-major torch code of
  :mod:`torchconn.ops._tet_soa`;
* fake implementation (``meta``, ``torch.compile``, ``torch.export``);
* autograd: the backward is the custom op ``torchconn::tet_dd_backward`` (C on CPU: values and
  gradients in one sweep per tet, scattered into the edges race-free by chunks of tets colored
  so that no two chunks of a color share an edge), whose own autograd differentiates the
  generic torch formula: double backward, ``create_graph`` and Hessian-vector products are exact
  on every path;
* vmap: :func:`torchconn.ops._library.leading_vmap` (native leading batch dims);
* ``torch.func``: the ``autograd.Function`` that ``register_autograd`` generates has no
  ``setup_context``, which ``torch.func.grad`` / ``vmap(grad)`` / ``jacrev`` refuse
  (pytorch/pytorch#168393), so eager calls go through an ``autograd.Function`` of the same two
  ops (:func:`_func_wrapper`: ``setup_context``, a backward whose own derivative and ``jvp``
  are ``torch.func`` of the generic formula, vmap rule generated); while ``torch.compile``
  traces, the op itself is called (dynamo does not trace a custom ``jvp``; the op's own
  autograd applies), as in :mod:`torchconn.ops.so3`.

The tables are built once per mesh on the real mesh tensors, also when first asked for inside a
``torch.func`` transform or while ``torch.compile`` traces (:mod:`torchconn.ops._cache`).

The variants with ``θ̃`` (and ``√R``) formed inside the kernel, ``torchconn::tet_dd_sqrt`` and
``torchconn::tet_dd_rot``, and the mesh-level entry point ``tet_dd_solder`` that
:func:`torchconn.dec.dnabla.averaged_dd_solder` calls, live in :mod:`torchconn.ops.tet_solder`;
they share this module's tables, generic formulas and C library.
"""
from __future__ import annotations

import ctypes

import numpy as np
import torch

from . import _tet_soa
from . import native as _native
from ._cache import require as _require
from ._cache import traced_constant
from ._library import jvp as _library_jvp
from ._library import leading_vmap, qualname
from ._mat import _matTvec, _matvec
from .backend import can_use_compiled

__all__ = ["TetKernel", "tet_kernel", "edge_solder_sqrt", "tet_dd", "tet_dd_from_rotations"]

#: Tets per chunk of the race-free C backward (see :class:`TetKernel`). Measured at 1M tets
#: (float32, C kernel alone): 512 (6 colors) 165 ms on one thread, since every color pass
#: sweeps the whole mesh and reloads its edges; 4096 (4 colors) 112 ms, as fast as one
#: sequential chunk, and 2 threads 60 ms. Few colors also mean few barriers: with 512-tet chunks
#: in super-blocks (178 groups, the same speed on a quiet machine) the 2-thread backward took
#: 1.4 s instead of 0.14 s while another process held one of the two cores.
CHUNK = 4096

_I64 = ctypes.c_int64
_P = ctypes.c_void_p
_FWD = {dt: _native.declare("tet", f"tet_dd_fwd_{sfx}", [_P, _P, _P, _P, _P, _I64, _I64, _I64, ctypes.c_int])
        for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}
_BWD = {dt: _native.declare("tet", f"tet_dd_bwd_{sfx}",
                            [_P, _P, _P, _P, _P, _P, _P, _P, _I64, _P, _P, _I64, _I64, _I64, ctypes.c_int])
        for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}


def _schedule(tet_edges: torch.Tensor, n_edges: int, chunk: int):
    """Race-free order of the C backward: ``(order (T,), chunk_start (K+1,), color_start (C+1,))``.

    Tets sorted by their smallest edge index (a band order when the vertex numbering is
    coherent), cut into chunks of ``chunk`` consecutive tets; a greedy coloring gives chunks that
    share an edge different colors (a 63-bit mask per edge; a chunk that finds all 63 taken gets
    a color of its own, i.e. runs alone). The chunks are listed color by color. One-time cost per
    mesh: a loop over the ``T / chunk`` chunks (numpy), not over tets."""
    te = tet_edges.detach().cpu().numpy().astype(np.int64, copy=False)
    T = te.shape[0]
    order = np.argsort(te.min(1), kind="stable") if T else np.zeros(0, np.int64)
    K = (T + chunk - 1) // chunk
    mask = np.zeros(max(n_edges, 1), np.int64)
    color = np.empty(K, np.int64)
    own = 63
    for k in range(K):
        edges = te[order[k * chunk:(k + 1) * chunk]].reshape(-1)
        used = int(np.bitwise_or.reduce(mask[edges]))
        free = ~used & ((1 << 63) - 1)
        if free:
            c = (free & -free).bit_length() - 1
            mask[edges] |= np.int64(1 << c)
        else:
            c, own = own, own + 1
        color[k] = c
    chunks = np.argsort(color, kind="stable")  # chunk ids, color by color
    starts = np.minimum(np.arange(K + 1) * chunk, T)
    lens = starts[1:] - starts[:-1]
    new_order = np.concatenate([order[starts[c]:starts[c + 1]] for c in chunks]) if K else order
    chunk_start = np.concatenate(([0], np.cumsum(lens[chunks])))
    counts = np.bincount(color, minlength=int(color.max()) + 1 if K else 0)
    color_start = np.concatenate(([0], np.cumsum(counts)))
    return tuple(torch.from_numpy(np.ascontiguousarray(a, dtype=np.int64)) for a in (new_order, chunk_start, color_start))


class TetKernel:
    """Gather tables of a :class:`~torchconn.mesh.TetMesh` for the tet kernel (built once per mesh).

    Attributes (long, on the mesh device):
        rot_index ``(T, 6)``: ``2 e + (sign < 0)``: the oriented ``R_{x_i x_j}`` of local pair
            ``p`` (``pair_list(4)`` order) is ``R_e`` or, for odd entries, ``R_eᵀ`` (equivalently
            an index into ``torch.stack((R, Rᵀ), 1).reshape(2E, 3, 3)``).
        theta_index ``(T, 7)``: index into ``stack((θ̃_ij, θ̃_ji), 1).reshape(2E, 3)`` of the
            seven directed edges the formula reads, ``ba, ca, da, cb, db, dc, cd`` (local labels
            ``a, b, c, d = 0..3``).
        order ``(T,)``, chunk_start ``(K+1,)``, color_start ``(C+1,)``: the race-free schedule of
            the C backward (:func:`_schedule`; read only by the CPU kernel; on other devices a
            trivial one-chunk schedule).
    """

    # local pairs 01 02 03 12 13 23 and the directed edges (x, y) read as θ̃_xy
    _DIRECTED = ((1, 0), (2, 0), (3, 0), (2, 1), (3, 1), (3, 2), (2, 3))

    def __init__(self, mesh, chunk: int = CHUNK):
        te = mesh.tet_edges
        neg = (mesh.tet_edge_signs < 0).long()
        self.rot_index = (2 * te + neg).contiguous()
        pair = {(0, 1): 0, (0, 2): 1, (0, 3): 2, (1, 2): 3, (1, 3): 4, (2, 3): 5}
        cols = []
        for x, y in self._DIRECTED:
            p = pair[(min(x, y), max(x, y))]
            # the tet traverses local pair p as stored when sign > 0; directed (x, y) with x > y
            # runs against the local order, so against the stored edge iff sign > 0
            against = neg[:, p] if x < y else 1 - neg[:, p]
            cols.append(2 * te[:, p] + against)
        self.theta_index = torch.stack(cols, 1).contiguous()
        self.n_edges = int(mesh.edges.shape[0])
        self.chunk = chunk
        self._set_schedule(te)

    def _set_schedule(self, te):
        dev = self.rot_index.device
        if dev.type == "cpu":
            self.order, self.chunk_start, self.color_start = _schedule(te, self.n_edges, self.chunk)
        else:  # read only by the CPU kernel; no values needed (meta) and no device sync
            T = self.rot_index.shape[0]
            self.order = torch.arange(T, device=dev)
            self.chunk_start = torch.tensor([0, T], device=dev)
            self.color_start = torch.tensor([0, 1], device=dev)

    @property
    def n_colors(self) -> int:
        """Number of colors of the backward schedule."""
        return self.color_start.shape[0] - 1

    def tables(self) -> tuple[torch.Tensor, ...]:
        """``(rot_index, theta_index, order, chunk_start, color_start)``: the table arguments of :func:`tet_dd`."""
        return _tables(self)

    def to(self, device) -> "TetKernel":
        """A copy with the tables on ``device`` (``self`` is left as it is)."""
        new = object.__new__(TetKernel)
        new.n_edges, new.chunk = self.n_edges, self.chunk
        new.rot_index, new.theta_index = self.rot_index.to(device), self.theta_index.to(device)
        dev = torch.device(device)
        if dev.type == "cpu" and self.rot_index.device.type != "cpu":
            new._set_schedule((self.rot_index // 2).cpu())  # a real schedule for the C kernel
        elif dev.type == "cpu":
            new.order, new.chunk_start, new.color_start = self.order, self.chunk_start, self.color_start
        else:
            new._set_schedule(None)
        return new


def _tables(kernel: TetKernel) -> tuple[torch.Tensor, ...]:
    """:meth:`TetKernel.tables` as attribute reads: while ``torch.compile`` traces, a kernel is a
    constant of the graph (:func:`tet_kernel`) whose attributes dynamo reads but whose methods it
    cannot call (no guardable source)."""
    return kernel.rot_index, kernel.theta_index, kernel.order, kernel.chunk_start, kernel.color_start


@traced_constant
def tet_kernel(mesh, device: torch.device | str | None = None) -> TetKernel:
    """The :class:`TetKernel` of ``mesh`` on ``device`` (default: the mesh's), cached with ``mesh.require``.

    Built eagerly on the real mesh tensors, also when first asked for inside a ``torch.func``
    transform or while ``torch.compile`` traces (then at trace time; the tables enter the graph
    as constants): :mod:`torchconn.ops._cache`."""
    k = _require(mesh, "ops.tet_kernel", TetKernel)
    if device is None or k.rot_index.device == torch.device(device):
        return k
    dev = torch.device(device)
    return _require(mesh, f"ops.tet_kernel.{dev}", lambda m: k.to(dev))


def edge_solder_sqrt(half_rot: torch.Tensor, edge_vec: torch.Tensor) -> torch.Tensor:
    """Half-transported solder form of both directions of every edge: ``(*B, E, 2, 3)``.

    ``[e, 0] = θ̃_ij = √R_ij (v_j - v_i)`` and ``[e, 1] = θ̃_ji = √R_ji (v_i - v_j) =
    -√R_ijᵀ (v_j - v_i)`` for ``edges[e] = (i, j)`` (report Sec. 3.3, docs/conventions.md §1).

    Args:
        half_rot: ``(*B, E, 3, 3)`` ``√R_ij``; edge_vec: ``(E, 3)`` (or broadcastable) ``v_j - v_i``.
    """
    vec = edge_vec.expand(*half_rot.shape[:-1])
    return torch.stack((_matvec(half_rot, vec), -_matTvec(half_rot, vec)), -2)


# ----------------------------------------------------------------------------- the custom ops

def _flat(edge_rot, edge_theta):
    E = edge_rot.shape[-3]
    return edge_rot.reshape(-1, E, 3, 3), edge_theta.reshape(-1, E, 2, 3)


def _generic_fwd(edge_rot, edge_theta, rot_index, theta_index):
    R, th = _flat(edge_rot, edge_theta)
    out = _tet_soa.forward(R, th, rot_index, theta_index)
    return out.reshape(*edge_rot.shape[:-3], rot_index.shape[0], 3)


def _generic_bwd(edge_rot, edge_theta, grad, rot_index, theta_index):
    R, th = _flat(edge_rot, edge_theta)
    gR, gth = _tet_soa.backward(R, th, grad.reshape(R.shape[0], -1, 3), rot_index, theta_index)
    return gR.reshape(edge_rot.shape).contiguous(), gth.reshape(edge_theta.shape).contiguous()


def _c_sizes(edge_rot, rot_index):
    E, T = edge_rot.shape[-3], rot_index.shape[0]
    return _I64(edge_rot.numel() // (9 * E) if E else 0), _I64(E), _I64(T)


@torch.library.custom_op(qualname("tet_dd"), mutates_args=())
def _tet_dd_op(edge_rot: torch.Tensor, edge_theta: torch.Tensor, rot_index: torch.Tensor,
               theta_index: torch.Tensor, order: torch.Tensor, chunk_start: torch.Tensor,
               color_start: torch.Tensor) -> torch.Tensor:
    """``torchconn::tet_dd``: ``(*B, E, 3, 3)``, ``(*B, E, 2, 3)`` -> ``(*B, T, 3)`` (generic kernel)."""
    return _generic_fwd(edge_rot, edge_theta, rot_index, theta_index)


@_tet_dd_op.register_kernel("cpu")
def _(edge_rot, edge_theta, rot_index, theta_index, order, chunk_start, color_start):
    if not can_use_compiled("tet", edge_rot, edge_theta):
        return _generic_fwd(edge_rot, edge_theta, rot_index, theta_index)
    R, th = edge_rot.contiguous(), edge_theta.contiguous()
    ri, ti = rot_index.contiguous(), theta_index.contiguous()
    out = _native.empty(*edge_rot.shape[:-3], rot_index.shape[0], 3, dtype=edge_rot.dtype)
    nb, E, T = _c_sizes(R, ri)
    if out.numel():
        _FWD[R.dtype](_native.ptr(R), _native.ptr(th), _native.ptr(ri), _native.ptr(ti), _native.ptr(out),
                      nb, E, T, torch.get_num_threads())
    return out


@_tet_dd_op.register_fake
def _(edge_rot, edge_theta, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(*edge_rot.shape[:-3], rot_index.shape[0], 3)


@torch.library.custom_op(qualname("tet_dd_backward"), mutates_args=())
def _tet_dd_backward_op(edge_rot: torch.Tensor, edge_theta: torch.Tensor, grad: torch.Tensor,
                        rot_index: torch.Tensor, theta_index: torch.Tensor, order: torch.Tensor,
                        chunk_start: torch.Tensor, color_start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``torchconn::tet_dd_backward``: the vector-Jacobian product of ``tet_dd`` for ``grad (*B, T, 3)``:
    ``(∂L/∂edge_rot (*B, E, 3, 3), ∂L/∂edge_theta (*B, E, 2, 3))`` (generic kernel)."""
    return _generic_bwd(edge_rot, edge_theta, grad, rot_index, theta_index)


@_tet_dd_backward_op.register_kernel("cpu")
def _(edge_rot, edge_theta, grad, rot_index, theta_index, order, chunk_start, color_start):
    if not can_use_compiled("tet", edge_rot, edge_theta, grad):
        return _generic_bwd(edge_rot, edge_theta, grad, rot_index, theta_index)
    R, th, g = edge_rot.contiguous(), edge_theta.contiguous(), grad.contiguous()
    tabs = [t.contiguous() for t in (rot_index, theta_index, order, chunk_start)]
    cs = color_start.contiguous()
    g_rot, g_th = _native.empty(*R.shape, dtype=R.dtype), _native.empty(*th.shape, dtype=R.dtype)
    nb, E, T = _c_sizes(R, rot_index)
    if g_rot.numel():  # the kernel zeroes its outputs
        _BWD[R.dtype](_native.ptr(R), _native.ptr(th), _native.ptr(g), *(_native.ptr(t) for t in tabs),
                      _native.ptr(cs), _I64(cs.shape[0] - 1), _native.ptr(g_rot), _native.ptr(g_th),
                      nb, E, T, torch.get_num_threads())
    else:
        g_rot.zero_(), g_th.zero_()
    return g_rot, g_th


@_tet_dd_backward_op.register_fake
def _(edge_rot, edge_theta, grad, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(edge_rot.shape), edge_theta.new_empty(edge_theta.shape)


def _setup_fwd(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _backward_fwd(ctx, grad):
    edge_rot, edge_theta, *tables = ctx.saved_tensors
    g_rot, g_th = _tet_dd_backward_op(edge_rot, edge_theta, grad.contiguous(), *tables)
    need = ctx.needs_input_grad
    return (g_rot if need[0] else None, g_th if need[1] else None) + (None,) * 5


def _setup_bwd(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _backward_bwd(ctx, gg_rot, gg_th):
    """Differentiates the generic torch formula (exact second and higher derivatives).

    ``torch.func.vjp`` of the map ``(R, θ̃, g) -> vjp of the generic forward``: a function
    transform, so its derivatives do not leak into the outer graph (``g`` usually depends on
    ``R`` there: differentiating with ``autograd.grad`` on the saved tensors would count that
    path twice), while the result stays differentiable for the outer autograd (third order)."""
    edge_rot, edge_theta, grad, rot_index, theta_index = ctx.saved_tensors[:5]

    def vjp_generic(R, th, g):
        return torch.func.vjp(lambda a, b: _generic_fwd(a, b, rot_index, theta_index), R, th)[1](g)

    _, pullback = torch.func.vjp(vjp_generic, edge_rot, edge_theta, grad)
    gg = (torch.zeros_like(edge_rot) if gg_rot is None else gg_rot,
          torch.zeros_like(edge_theta) if gg_th is None else gg_th)
    res = pullback(gg)
    return tuple(r if n else None for r, n in zip(res, ctx.needs_input_grad[:3])) + (None,) * 5


_tet_dd_op.register_autograd(_backward_fwd, setup_context=_setup_fwd)
_tet_dd_backward_op.register_autograd(_backward_bwd, setup_context=_setup_bwd)
_tet_dd_op.register_vmap(leading_vmap(_tet_dd_op, "tet_dd", batched=(0, 1)))
_tet_dd_backward_op.register_vmap(leading_vmap(_tet_dd_backward_op, "tet_dd_backward", batched=(0, 1, 2), n_out=2))


def _func_wrapper(op, bwd_op, generic_fwd, n_diff: int, n_extra: int = 0):
    """``op`` (a tet op: ``n_diff`` differentiable inputs, ``n_extra`` non-differentiable ones, then
    the five tables of :meth:`TetKernel.tables`) through ``autograd.Function`` s with
    ``setup_context``, for eager calls and the ``torch.func`` transforms (module doc).

    Forward is ``op``, backward ``bwd_op`` (``(*inputs, grad, *extra, *tables)`` -> the ``n_diff``
    gradients; C on the CPU); the backward's own backward and both ``jvp`` are ``torch.func``
    of ``generic_fwd(*inputs, *extra, rot_index, theta_index)``, the generic torch formula, so higher
    derivatives are exact on every path. ``generate_vmap_rule``: under ``vmap`` the ops' own
    vmap rules run. Returns ``call(*inputs, *extra, *tables)``: the op itself while ``torch.compile``
    traces."""
    n_rest = n_extra + 5

    def vjp_generic(*args):  # (*inputs, grad, *extra, rot_index, theta_index) -> n_diff gradients
        xs, g, extra, (ri, ti) = args[:n_diff], args[n_diff], args[n_diff + 1:n_diff + 1 + n_extra], args[-2:]
        return torch.func.vjp(lambda *d: generic_fwd(*d, *extra, ri, ti), *xs)[1](g)

    class Backward(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(*args):
            return bwd_op(*args)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(*inputs[:n_diff + 1])
            ctx.save_for_forward(*inputs[:n_diff + 1])
            ctx.tables = inputs[n_diff + 1:n_diff + 3 + n_extra]  # the extra inputs, rot_index, theta_index

        @staticmethod
        def backward(ctx, *gg):
            xs = ctx.saved_tensors
            gg = tuple(torch.zeros_like(x) if g is None else g for g, x in zip(gg, xs))
            res = torch.func.vjp(lambda *a: vjp_generic(*a, *ctx.tables), *xs)[1](gg)
            return (*res, *([None] * n_rest))

        @staticmethod
        def jvp(ctx, *tangents):
            xs = ctx.saved_tensors
            return _library_jvp(lambda *a: vjp_generic(*a, *ctx.tables), xs, tangents[:n_diff + 1])

    class Fn(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(*args):
            return op(*args)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(*inputs[:n_diff])
            ctx.save_for_forward(*inputs[:n_diff])
            ctx.tables = inputs[n_diff:]

        @staticmethod
        def backward(ctx, grad):
            gs = Backward.apply(*ctx.saved_tensors, grad.contiguous(), *ctx.tables)
            return (*(g if n else None for g, n in zip(gs, ctx.needs_input_grad)), *([None] * n_rest))

        @staticmethod
        def jvp(ctx, *tangents):
            extra, (ri, ti) = ctx.tables[:n_extra], ctx.tables[n_extra:n_extra + 2]
            return _library_jvp(lambda *d: generic_fwd(*d, *extra, ri, ti), ctx.saved_tensors, tangents[:n_diff])

    def call(*args):
        return op(*args) if torch.compiler.is_compiling() else Fn.apply(*args)

    return call


_tet_dd_call = _func_wrapper(_tet_dd_op, _tet_dd_backward_op, _generic_fwd, 2)


def tet_dd(edge_rot: torch.Tensor, edge_theta: torch.Tensor, kernel: TetKernel) -> torch.Tensor:
    """``torchconn::tet_dd`` on the tables of ``kernel``: ``(*B, E, 3, 3)``, ``(*B, E, 2, 3)`` -> ``(*B, T, 3)``.

    Value at ``tets[t, 0]`` of the closed form :func:`tet_dd_from_rotations` on the gathered
    oriented rotations ``edge_rot`` (``R_ij`` of the canonical edges) and half-transported solder
    forms ``edge_theta`` (``[e, 0] = θ̃_ij``, ``[e, 1] = θ̃_ji``, :func:`edge_solder_sqrt`).
    ``edge_theta`` has the batch dims of ``edge_rot``.
    """
    E = kernel.n_edges
    if edge_rot.dim() < 3 or edge_rot.shape[-3:] != (E, 3, 3):
        raise ValueError(f"tet_dd: edge_rot must have shape (*B, {E}, 3, 3), got {tuple(edge_rot.shape)}")
    if edge_theta.shape != (*edge_rot.shape[:-3], E, 2, 3):
        raise ValueError(f"tet_dd: edge_theta must have shape {(*edge_rot.shape[:-3], E, 2, 3)} (the batch "
                         f"dims of edge_rot), got {tuple(edge_theta.shape)}")
    if edge_theta.dtype != edge_rot.dtype or edge_theta.device != edge_rot.device:
        raise ValueError(f"tet_dd: edge_theta ({edge_theta.dtype}, {edge_theta.device}) must match edge_rot "
                         f"({edge_rot.dtype}, {edge_rot.device})")
    return _tet_dd_call(edge_rot, edge_theta, *_tables(kernel))


def tet_dd_from_rotations(rot: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Closed-form ``𝔡∇ Alt 𝔡∇ Alt θ̃`` at ``[abcd]`` from per-tet gathered data: ``(T, 3)``.

    Args:
        rot: ``(T, 6, 3, 3)`` oriented ``R_ab, R_ac, R_ad, R_bc, R_bd, R_cd`` (pair_list(4)).
        theta: ``(T, 7, 3)`` ``θ̃_ba, θ̃_ca, θ̃_da, θ̃_cb, θ̃_db, θ̃_dc, θ̃_cd``.

    The end-of-Ch. 5 formula (:func:`torchconn.dec.dnabla.wedge_curvature_solder_tet`) regrouped by
    its leading transport, ``R_ab X_b + R_ac X_c + R_ad X_d`` with (fibers of ``b, c, d``)::

        X_b = R_bc (-θ̃_ca/6 + R_cd θ̃_db/6 - θ̃_cb/3 + θ̃_cd/2)
            + R_bd (-R_dc θ̃_cb/6 + θ̃_da/6 + θ̃_db/3 - θ̃_dc/2)
        X_c = (R_cb θ̃_ba - R_cd θ̃_da)/6 + θ̃_cb/2 - θ̃_cd/2
        X_d = (R_dc θ̃_ca - R_db θ̃_ba)/6 - (θ̃_db - θ̃_dc)/2

    Three rounds of matrix-vector products (6, then 2, then 3 per tet) instead of the 8
    matrix-matrix products and 16 matrix-vector products of the printed formula. Batched
    ``bmm``, differentiated by plain autograd: the per-tet reference of the op :func:`tet_dd`.
    """
    return _tet_soa.tet_dd_dense(rot, theta)[0]
