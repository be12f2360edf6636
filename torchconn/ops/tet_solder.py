"""Averaged ``d∇d∇θ`` on tets with ``θ̃`` formed inside the kernel, and the mesh-level entry point.

Three custom ops next to ``torchconn::tet_dd`` of :mod:`torchconn.ops.tet` (same tables, same
contract: CPU kernel in ``csrc/tet.c`` when :func:`torchconn.ops.backend.can_use_compiled` allows,
generic torch kernel on every device, fake implementation, exact autograd whose backward op
differentiates the generic formula, vmap rule, and the ``autograd.Function`` of
:func:`torchconn.ops.tet._func_wrapper` for eager calls and the ``torch.func`` transforms):

* ``torchconn::tet_dd_sqrt`` (:func:`tet_dd_sqrt`): ``θ̃ = edge_solder_sqrt(√R, v_j - v_i)``
  formed per edge inside the kernel (no ``θ̃`` tensor and no ``θ̃`` gradient in memory);
* ``torchconn::tet_dd_rot`` (:func:`tet_dd_rot`): ``√R = so3.sqrt(R)`` formed inside as well (the
  element kernels of ``csrc/so3.c``, included by ``csrc/tet.c``; no ``√R`` tensor, no ``∂L/∂√R``);
* ``torchconn::tet_dd_frames`` (:func:`tet_dd_frames`): the solder form read in a frame field,
  ``θ̃'_ij = F_iᵀ √(F_i R F_jᵀ) v``, formed inside (no ``θ̃'``, root or per-edge frame tensor; the
  frame gradients summed per vertex in the kernel).

:func:`tet_dd_solder` is the function that :func:`torchconn.dec.dnabla.averaged_dd_solder` and
:func:`torchconn.dec.dnabla.wedge_solder` call: ``tet_dd_rot`` when neither frames nor
``half_rot`` are given, ``tet_dd_sqrt`` when ``half_rot`` is, ``tet_dd_frames`` for frames
without ``half_rot``, and ``tet_dd`` on the frames' ``θ̃'`` for frames with ``half_rot``; it returns ``None`` where the kernel does not apply (rank other than 3), and
the caller then evaluates its generic operators.
"""
from __future__ import annotations

import ctypes

import torch

from . import _so3_formulas as _f
from . import native as _native
from ._cache import edge_ends as _edge_ends
from ._cache import edge_index as _edge_index
from ._cache import edge_vectors as _edge_vectors
from ._library import leading_vmap, qualname
from ._mat import _matTvec, _matvec
from .backend import can_use_compiled
from .so3 import sqrt as _sqrt
from .tet import (_I64, _P, TetKernel, _c_sizes, _func_wrapper, _generic_bwd, _tables, _generic_fwd, _setup_bwd,
                  _setup_fwd, edge_solder_sqrt, tet_dd, tet_kernel)
from ..tolerances import get_eps

__all__ = ["tet_dd_sqrt", "tet_dd_rot", "tet_dd_frames", "tet_dd_solder"]

# ---- the same with θ̃ formed inside the kernel from √R and v_j - v_i (no θ̃ tensors at all)

_SFWD = {dt: _native.declare("tet", f"tet_dds_fwd_{sfx}", [_P, _P, _P, _P, _P, _P, _I64, _I64, _I64, ctypes.c_int],
                             ctypes.c_int)
         for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}
_SBWD = {dt: _native.declare("tet", f"tet_dds_bwd_{sfx}",
                             [_P, _P, _P, _P, _P, _P, _P, _P, _P, _I64, _P, _P, _P, _I64, _I64, _I64, ctypes.c_int],
                             ctypes.c_int)
         for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}


def _check_scratch(status: int) -> None:
    """The √R kernels map their scratch themselves (``csrc/tet.c``); -1: the mapping failed."""
    if status != 0:
        raise MemoryError("torchconn::tet_dd_sqrt / tet_dd_rot: the C kernel could not map its scratch buffer")


def _generic_sqrt_fwd(edge_rot, half_rot, edge_vec, rot_index, theta_index):
    return _generic_fwd(edge_rot, edge_solder_sqrt(half_rot, edge_vec), rot_index, theta_index)


def _generic_sqrt_bwd(edge_rot, half_rot, edge_vec, grad, rot_index, theta_index):
    theta = edge_solder_sqrt(half_rot, edge_vec)
    g_rot, g_th = _generic_bwd(edge_rot, theta, grad, rot_index, theta_index)
    g0, g1 = g_th[..., 0, :], g_th[..., 1, :]  # θ̃_ij = H v, θ̃_ji = -Hᵀ v
    g_half = g0.unsqueeze(-1) * edge_vec.unsqueeze(-2) - edge_vec.unsqueeze(-1) * g1.unsqueeze(-2)
    g_vec = (_matTvec(half_rot, g0) - _matvec(half_rot, g1)).reshape(-1, *edge_vec.shape).sum(0)
    return g_rot, g_half.contiguous(), g_vec


@torch.library.custom_op(qualname("tet_dd_sqrt"), mutates_args=())
def _tet_dd_sqrt_op(edge_rot: torch.Tensor, half_rot: torch.Tensor, edge_vec: torch.Tensor,
                    rot_index: torch.Tensor, theta_index: torch.Tensor, order: torch.Tensor,
                    chunk_start: torch.Tensor, color_start: torch.Tensor) -> torch.Tensor:
    """``torchconn::tet_dd_sqrt``: ``tet_dd`` with ``θ̃_ij = √R_ij v``, ``θ̃_ji = -√R_ijᵀ v`` formed
    inside: ``edge_rot``, ``half_rot (*B, E, 3, 3)``, ``edge_vec (E, 3)`` -> ``(*B, T, 3)`` (generic kernel)."""
    return _generic_sqrt_fwd(edge_rot, half_rot, edge_vec, rot_index, theta_index)


@_tet_dd_sqrt_op.register_kernel("cpu")
def _(edge_rot, half_rot, edge_vec, rot_index, theta_index, order, chunk_start, color_start):
    if not can_use_compiled("tet", edge_rot, half_rot, edge_vec):
        return _generic_sqrt_fwd(edge_rot, half_rot, edge_vec, rot_index, theta_index)
    R, H, v = edge_rot.contiguous(), half_rot.contiguous(), edge_vec.contiguous()
    ri, ti = rot_index.contiguous(), theta_index.contiguous()
    out = _native.empty(*edge_rot.shape[:-3], rot_index.shape[0], 3, dtype=edge_rot.dtype)
    nb, E, T = _c_sizes(R, ri)
    if out.numel():
        _check_scratch(_SFWD[R.dtype](_native.ptr(R), _native.ptr(H), _native.ptr(v), _native.ptr(ri),
                                      _native.ptr(ti), _native.ptr(out), nb, E, T, torch.get_num_threads()))
    return out


@_tet_dd_sqrt_op.register_fake
def _(edge_rot, half_rot, edge_vec, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(*edge_rot.shape[:-3], rot_index.shape[0], 3)


@torch.library.custom_op(qualname("tet_dd_sqrt_backward"), mutates_args=())
def _tet_dd_sqrt_backward_op(edge_rot: torch.Tensor, half_rot: torch.Tensor, edge_vec: torch.Tensor,
                             grad: torch.Tensor, rot_index: torch.Tensor, theta_index: torch.Tensor,
                             order: torch.Tensor, chunk_start: torch.Tensor, color_start: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``torchconn::tet_dd_sqrt_backward``: ``(∂L/∂edge_rot, ∂L/∂half_rot, ∂L/∂edge_vec)`` (generic kernel)."""
    return _generic_sqrt_bwd(edge_rot, half_rot, edge_vec, grad, rot_index, theta_index)


@_tet_dd_sqrt_backward_op.register_kernel("cpu")
def _(edge_rot, half_rot, edge_vec, grad, rot_index, theta_index, order, chunk_start, color_start):
    if not can_use_compiled("tet", edge_rot, half_rot, edge_vec, grad):
        return _generic_sqrt_bwd(edge_rot, half_rot, edge_vec, grad, rot_index, theta_index)
    R, H, v, g = edge_rot.contiguous(), half_rot.contiguous(), edge_vec.contiguous(), grad.contiguous()
    tabs = [t.contiguous() for t in (rot_index, theta_index, order, chunk_start)]
    cs = color_start.contiguous()
    nb, E, T = _c_sizes(R, rot_index)
    g_rot, g_half = _native.empty(*R.shape, dtype=R.dtype), _native.empty(*H.shape, dtype=R.dtype)
    g_vec = _native.empty(*((nb.value,) if nb.value > 1 else ()), *v.shape, dtype=R.dtype)
    if g_rot.numel():  # the kernel zeroes its outputs
        _check_scratch(_SBWD[R.dtype](_native.ptr(R), _native.ptr(H), _native.ptr(v), _native.ptr(g),
                                      *(_native.ptr(t) for t in tabs), _native.ptr(cs), _I64(cs.shape[0] - 1),
                                      _native.ptr(g_rot), _native.ptr(g_half), _native.ptr(g_vec), nb, E, T,
                                      torch.get_num_threads()))
    else:
        g_rot.zero_(), g_half.zero_(), g_vec.zero_()
    return g_rot, g_half, (g_vec if nb.value <= 1 else g_vec.sum(0))


@_tet_dd_sqrt_backward_op.register_fake
def _(edge_rot, half_rot, edge_vec, grad, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(edge_rot.shape), half_rot.new_empty(half_rot.shape), edge_vec.new_empty(edge_vec.shape)


def _backward_sqrt_fwd(ctx, grad):
    edge_rot, half_rot, edge_vec, *tables = ctx.saved_tensors
    gs = _tet_dd_sqrt_backward_op(edge_rot, half_rot, edge_vec, grad.contiguous(), *tables)
    return tuple(g if n else None for g, n in zip(gs, ctx.needs_input_grad[:3])) + (None,) * 5


def _backward_sqrt_bwd(ctx, gg_rot, gg_half, gg_vec):
    """As :func:`_backward_bwd`: ``torch.func.vjp`` of the vjp of the generic formula."""
    edge_rot, half_rot, edge_vec, grad, rot_index, theta_index = ctx.saved_tensors[:6]

    def vjp_generic(R, H, v, g):
        return torch.func.vjp(lambda a, b, c: _generic_sqrt_fwd(a, b, c, rot_index, theta_index), R, H, v)[1](g)

    _, pullback = torch.func.vjp(vjp_generic, edge_rot, half_rot, edge_vec, grad)
    gg = tuple(torch.zeros_like(x) if g is None else g
               for g, x in zip((gg_rot, gg_half, gg_vec), (edge_rot, half_rot, edge_vec)))
    res = pullback(gg)
    return tuple(r if n else None for r, n in zip(res, ctx.needs_input_grad[:4])) + (None,) * 5


_tet_dd_sqrt_op.register_autograd(_backward_sqrt_fwd, setup_context=_setup_fwd)
_tet_dd_sqrt_backward_op.register_autograd(_backward_sqrt_bwd, setup_context=_setup_bwd)
_tet_dd_sqrt_op.register_vmap(leading_vmap(_tet_dd_sqrt_op, "tet_dd_sqrt", batched=(0, 1)))
_tet_dd_sqrt_backward_op.register_vmap(
    leading_vmap(_tet_dd_sqrt_backward_op, "tet_dd_sqrt_backward", batched=(0, 1, 3), n_out=3, summed=True))
_tet_dd_sqrt_call = _func_wrapper(_tet_dd_sqrt_op, _tet_dd_sqrt_backward_op, _generic_sqrt_fwd, 3)


# ---- and with √R formed inside too: torchconn::tet_dd_rot (no √R tensor, no ∂L/∂√R tensor)

_RFWD = {dt: _native.declare("tet", f"tet_ddr_fwd_{sfx}", [_P, _P, _P, _P, _P, _I64, _I64, _I64, ctypes.c_int,
                                                          ctypes.c_double], ctypes.c_int)
         for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}
_RBWD = {dt: _native.declare("tet", f"tet_ddr_bwd_{sfx}",
                             [_P, _P, _P, _P, _P, _P, _P, _P, _I64, _P, _P, _I64, _I64, _I64, ctypes.c_int,
                              ctypes.c_double], ctypes.c_int)
         for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}


def _generic_rot_fwd(edge_rot, edge_vec, rot_index, theta_index):
    return _generic_sqrt_fwd(edge_rot, _f.sqrt(edge_rot), edge_vec, rot_index, theta_index)


def _generic_rot_bwd(edge_rot, edge_vec, grad, rot_index, theta_index):
    g_rot, g_half, g_vec = _generic_sqrt_bwd(edge_rot, _f.sqrt(edge_rot), edge_vec, grad, rot_index, theta_index)
    return g_rot + _f.sqrt_bwd(edge_rot, g_half), g_vec


@torch.library.custom_op(qualname("tet_dd_rot"), mutates_args=())
def _tet_dd_rot_op(edge_rot: torch.Tensor, edge_vec: torch.Tensor, rot_index: torch.Tensor,
                   theta_index: torch.Tensor, order: torch.Tensor, chunk_start: torch.Tensor,
                   color_start: torch.Tensor) -> torch.Tensor:
    """``torchconn::tet_dd_rot``: ``tet_dd_sqrt`` with ``√R`` itself formed inside
    (:func:`torchconn.ops.so3.sqrt`): ``edge_rot (*B, E, 3, 3)``, ``edge_vec (E, 3)`` -> ``(*B, T, 3)``
    (generic kernel)."""
    return _generic_rot_fwd(edge_rot, edge_vec, rot_index, theta_index)


@_tet_dd_rot_op.register_kernel("cpu")
def _(edge_rot, edge_vec, rot_index, theta_index, order, chunk_start, color_start):
    if not can_use_compiled("tet", edge_rot, edge_vec):
        return _generic_rot_fwd(edge_rot, edge_vec, rot_index, theta_index)
    R, v = edge_rot.contiguous(), edge_vec.contiguous()
    ri, ti = rot_index.contiguous(), theta_index.contiguous()
    out = _native.empty(*edge_rot.shape[:-3], rot_index.shape[0], 3, dtype=edge_rot.dtype)
    nb, E, T = _c_sizes(R, ri)
    if out.numel():
        _check_scratch(_RFWD[R.dtype](_native.ptr(R), _native.ptr(v), _native.ptr(ri), _native.ptr(ti),
                                      _native.ptr(out), nb, E, T, torch.get_num_threads(),
                                      get_eps("small_angle", R.dtype)))
    return out


@_tet_dd_rot_op.register_fake
def _(edge_rot, edge_vec, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(*edge_rot.shape[:-3], rot_index.shape[0], 3)


@torch.library.custom_op(qualname("tet_dd_rot_backward"), mutates_args=())
def _tet_dd_rot_backward_op(edge_rot: torch.Tensor, edge_vec: torch.Tensor, grad: torch.Tensor,
                            rot_index: torch.Tensor, theta_index: torch.Tensor, order: torch.Tensor,
                            chunk_start: torch.Tensor, color_start: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """``torchconn::tet_dd_rot_backward``: ``(∂L/∂edge_rot, ∂L/∂edge_vec)`` (generic kernel)."""
    return _generic_rot_bwd(edge_rot, edge_vec, grad, rot_index, theta_index)


@_tet_dd_rot_backward_op.register_kernel("cpu")
def _(edge_rot, edge_vec, grad, rot_index, theta_index, order, chunk_start, color_start):
    if not can_use_compiled("tet", edge_rot, edge_vec, grad):
        return _generic_rot_bwd(edge_rot, edge_vec, grad, rot_index, theta_index)
    R, v, g = edge_rot.contiguous(), edge_vec.contiguous(), grad.contiguous()
    tabs = [t.contiguous() for t in (rot_index, theta_index, order, chunk_start)]
    cs = color_start.contiguous()
    nb, E, T = _c_sizes(R, rot_index)
    g_rot = _native.empty(*R.shape, dtype=R.dtype)
    g_vec = _native.empty(*((nb.value,) if nb.value > 1 else ()), *v.shape, dtype=R.dtype)
    if g_rot.numel():  # the kernel zeroes its outputs
        _check_scratch(_RBWD[R.dtype](_native.ptr(R), _native.ptr(v), _native.ptr(g),
                                      *(_native.ptr(t) for t in tabs), _native.ptr(cs), _I64(cs.shape[0] - 1),
                                      _native.ptr(g_rot), _native.ptr(g_vec), nb, E, T, torch.get_num_threads(),
                                      get_eps("small_angle", R.dtype)))
    else:
        g_rot.zero_(), g_vec.zero_()
    return g_rot, (g_vec if nb.value <= 1 else g_vec.sum(0))


@_tet_dd_rot_backward_op.register_fake
def _(edge_rot, edge_vec, grad, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(edge_rot.shape), edge_vec.new_empty(edge_vec.shape)


def _backward_rot_fwd(ctx, grad):
    edge_rot, edge_vec, *tables = ctx.saved_tensors
    gs = _tet_dd_rot_backward_op(edge_rot, edge_vec, grad.contiguous(), *tables)
    return tuple(g if n else None for g, n in zip(gs, ctx.needs_input_grad[:2])) + (None,) * 5


def _backward_rot_bwd(ctx, gg_rot, gg_vec):
    """As :func:`_backward_bwd`: ``torch.func.vjp`` of the vjp of the generic formula."""
    edge_rot, edge_vec, grad, rot_index, theta_index = ctx.saved_tensors[:5]

    def vjp_generic(R, v, g):
        return torch.func.vjp(lambda a, b: _generic_rot_fwd(a, b, rot_index, theta_index), R, v)[1](g)

    _, pullback = torch.func.vjp(vjp_generic, edge_rot, edge_vec, grad)
    gg = tuple(torch.zeros_like(x) if g is None else g for g, x in zip((gg_rot, gg_vec), (edge_rot, edge_vec)))
    res = pullback(gg)
    return tuple(r if n else None for r, n in zip(res, ctx.needs_input_grad[:3])) + (None,) * 5


_tet_dd_rot_op.register_autograd(_backward_rot_fwd, setup_context=_setup_fwd)
_tet_dd_rot_backward_op.register_autograd(_backward_rot_bwd, setup_context=_setup_bwd)
_tet_dd_rot_op.register_vmap(leading_vmap(_tet_dd_rot_op, "tet_dd_rot", batched=(0,)))
_tet_dd_rot_backward_op.register_vmap(
    leading_vmap(_tet_dd_rot_backward_op, "tet_dd_rot_backward", batched=(0, 2), n_out=2, summed=True))
_tet_dd_rot_call = _func_wrapper(_tet_dd_rot_op, _tet_dd_rot_backward_op, _generic_rot_fwd, 2)


def tet_dd_sqrt(edge_rot: torch.Tensor, half_rot: torch.Tensor, edge_vec: torch.Tensor,
                kernel: TetKernel) -> torch.Tensor:
    """``torchconn::tet_dd_sqrt``: :func:`tet_dd` with ``θ̃ = edge_solder_sqrt(half_rot, edge_vec)``
    formed inside the kernel (no ``θ̃`` tensors: less memory and one pass less).

    ``edge_rot``, ``half_rot``: ``(*B, E, 3, 3)`` (``R_ij``, ``√R_ij``; ``half_rot`` broadcast to
    the batch of ``edge_rot``); ``edge_vec``: ``(E, 3)`` ``v_j - v_i`` (shared by the batch)
    -> ``(*B, T, 3)``.
    """
    E = kernel.n_edges
    if edge_rot.dim() < 3 or edge_rot.shape[-3:] != (E, 3, 3):
        raise ValueError(f"tet_dd_sqrt: edge_rot must have shape (*B, {E}, 3, 3), got {tuple(edge_rot.shape)}")
    if half_rot.shape[-3:] != (E, 3, 3):
        raise ValueError(f"tet_dd_sqrt: half_rot must have shape (*B, {E}, 3, 3), got {tuple(half_rot.shape)}")
    if edge_vec.shape != (E, 3):
        raise ValueError(f"tet_dd_sqrt: edge_vec must have shape ({E}, 3), got {tuple(edge_vec.shape)}")
    batch = torch.broadcast_shapes(edge_rot.shape[:-3], half_rot.shape[:-3])
    return _tet_dd_sqrt_call(edge_rot.expand(*batch, E, 3, 3), half_rot.expand(*batch, E, 3, 3),
                             edge_vec.to(edge_rot), *_tables(kernel))


def tet_dd_rot(edge_rot: torch.Tensor, edge_vec: torch.Tensor, kernel: TetKernel) -> torch.Tensor:
    """``torchconn::tet_dd_rot``: :func:`tet_dd_sqrt` with ``half_rot = so3.sqrt(edge_rot)`` formed
    inside the kernel too (no ``√R`` tensor kept for the backward, no ``∂L/∂√R`` tensor: the
    backward recomputes the roots per edge and returns ``∂L/∂edge_rot`` through them).

    ``edge_rot``: ``(*B, E, 3, 3)`` ``R_ij``; ``edge_vec``: ``(E, 3)`` ``v_j - v_i`` -> ``(*B, T, 3)``.
    """
    E = kernel.n_edges
    if edge_rot.dim() < 3 or edge_rot.shape[-3:] != (E, 3, 3):
        raise ValueError(f"tet_dd_rot: edge_rot must have shape (*B, {E}, 3, 3), got {tuple(edge_rot.shape)}")
    if edge_vec.shape != (E, 3):
        raise ValueError(f"tet_dd_rot: edge_vec must have shape ({E}, 3), got {tuple(edge_vec.shape)}")
    return _tet_dd_rot_call(edge_rot, edge_vec.to(edge_rot), *_tables(kernel))


def tet_dd_solder(edge_rot: torch.Tensor, mesh, half_rot: torch.Tensor | None = None,
                  frames: torch.Tensor | None = None) -> torch.Tensor | None:
    """Averaged ``d∇d∇θ = 𝔡∇ Alt 𝔡∇ Alt θ̃`` on every tet of ``mesh``: ``(*B, T, 3)`` at ``tets[t,0]``.

    Same value (to round-off) as the generic operators of
    :func:`torchconn.dec.dnabla.averaged_dd_solder` with the same arguments, without the dense
    ``(T, 4, 4, 3, 3)`` tables. ``None`` when the kernel does not apply (rotations or vertices
    not of rank 3). Arguments are not validated (the caller does that).

    Args:
        edge_rot: ``(*B, E, 3, 3)`` ``R_ij`` of the canonical edges (read in ``frames`` if given).
        mesh: :class:`~torchconn.mesh.TetMesh`.
        half_rot: ``(*B, E, 3, 3)`` ``√R_ij`` (in the vertex frames when ``frames`` is given);
            default :func:`torchconn.ops.so3.sqrt` (of ``F_i R_ij F_jᵀ`` with frames). For a
            connection given by skew parameters ``ω`` pass :func:`torchconn.ops.so3.half_exp`
            of ``ω``: no logarithm is needed.
        frames: ``(V, 3, 3)`` (or ``(*B, V, 3, 3)``) or ``None`` (conventions of
            :func:`torchconn.dec.dnabla.tet_solder_sqrt`: ``θ̃'_ij = F_iᵀ √R^amb_ij (v_j - v_i)``).
    """
    if edge_rot.shape[-1] != 3 or mesh.vertices.shape[-1] != 3:
        return None
    dev, dt = edge_rot.device, edge_rot.dtype
    k = tet_kernel(mesh, dev)
    vec = _edge_vectors(mesh, dev, dt)  # (E, 3) v_j - v_i
    if frames is None:
        return tet_dd_rot(edge_rot, vec, k) if half_rot is None else tet_dd_sqrt(edge_rot, half_rot, vec, k)
    if half_rot is None:
        Fv = frames.to(device=dev, dtype=dt)
        batch = torch.broadcast_shapes(edge_rot.shape[:-3], Fv.shape[:-3])
        return tet_dd_frames(edge_rot.expand(*batch, *edge_rot.shape[-3:]), Fv.expand(*batch, *Fv.shape[-3:]), vec,
                             _edge_index(mesh, dev), k)
    else:
        Fv = frames.to(device=dev, dtype=dt)
        i, j = _edge_ends(mesh, dev)
        Fi, Fj = Fv.index_select(-3, i), Fv.index_select(-3, j)
        H = Fi @ half_rot @ Fj.transpose(-1, -2)
        amb = edge_solder_sqrt(H, vec)  # (*B, E, 2, 3) ambient
        theta = torch.stack((_matTvec(Fi, amb[..., 0, :]), _matTvec(Fj, amb[..., 1, :])), -2)
    batch = torch.broadcast_shapes(edge_rot.shape[:-3], theta.shape[:-3])
    E = edge_rot.shape[-3]
    return tet_dd(edge_rot.expand(*batch, E, 3, 3), theta.expand(*batch, E, 2, 3), k)


# ---- and with the solder form in a frame field: torchconn::tet_dd_frames (θ̃' formed inside from R and F)

_FFWD = {dt: _native.declare("tet", f"tet_ddf_fwd_{sfx}", [_P, _P, _P, _P, _P, _P, _P, _I64, _I64, _I64, _I64,
                                                          ctypes.c_int, ctypes.c_double], ctypes.c_int)
         for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}
_FBWD = {dt: _native.declare("tet", f"tet_ddf_bwd_{sfx}",
                             [_P] * 10 + [_I64, _P, _P, _P, _I64, _I64, _I64, _I64, ctypes.c_int, ctypes.c_double],
                             ctypes.c_int)
         for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}


def _frames_theta(edge_rot, frames, edge_vec, edges):
    """``(θ̃' (*B, E, 2, 3), A, H, F_i, F_j, u = H v, w = Hᵀ v)`` with ``A = F_i R F_jᵀ``, ``H = √A``,
    ``θ̃'_ij = F_iᵀ u``, ``θ̃'_ji = -F_jᵀ w`` (the generic formulas)."""
    Fi, Fj = frames.index_select(-3, edges[:, 0].contiguous()), frames.index_select(-3, edges[:, 1].contiguous())
    A = Fi @ edge_rot @ Fj.transpose(-1, -2)
    H = _f.sqrt(A)
    vec = edge_vec.expand(*H.shape[:-1])
    u, w = _matvec(H, vec), _matTvec(H, vec)
    theta = torch.stack((_matTvec(Fi, u), -_matTvec(Fj, w)), -2)
    return theta, A, H, Fi, Fj, u, w


def _generic_frames_fwd(edge_rot, frames, edge_vec, edges, rot_index, theta_index):
    return _generic_fwd(edge_rot, _frames_theta(edge_rot, frames, edge_vec, edges)[0], rot_index, theta_index)


def _generic_frames_bwd(edge_rot, frames, edge_vec, grad, edges, rot_index, theta_index):
    """``(∂L/∂R, ∂L/∂F, ∂L/∂v)``, the chain of :func:`_frames_theta` written out (no autograd: an op kernel)."""
    theta, A, H, Fi, Fj, u, w = _frames_theta(edge_rot, frames, edge_vec, edges)
    g_rot, g_th = _generic_bwd(edge_rot, theta, grad, rot_index, theta_index)
    gp, gm = g_th[..., 0, :], g_th[..., 1, :]
    vec = edge_vec.expand(*u.shape)
    gu, gw = _matvec(Fi, gp), -_matvec(Fj, gm)
    g_fi = u.unsqueeze(-1) * gp.unsqueeze(-2)
    g_fj = -(w.unsqueeze(-1) * gm.unsqueeze(-2))
    g_h = gu.unsqueeze(-1) * vec.unsqueeze(-2) + vec.unsqueeze(-1) * gw.unsqueeze(-2)
    g_vec = (_matTvec(H, gu) + _matvec(H, gw)).reshape(-1, *edge_vec.shape).sum(0)
    g_a = _f.sqrt_bwd(A, g_h)
    g_rot = g_rot + Fi.transpose(-1, -2) @ g_a @ Fj  # A = F_i R F_jᵀ
    g_fi = g_fi + g_a @ Fj @ edge_rot.transpose(-1, -2)
    g_fj = g_fj + g_a.transpose(-1, -2) @ Fi @ edge_rot
    g_fr = torch.zeros_like(frames, memory_format=torch.contiguous_format)
    g_fr.index_add_(-3, edges[:, 0].contiguous(), g_fi).index_add_(-3, edges[:, 1].contiguous(), g_fj)
    return g_rot.contiguous(), g_fr, g_vec.contiguous()


def _c_frames_sizes(edge_rot, frames, rot_index):
    nb, E, T = _c_sizes(edge_rot, rot_index)
    return nb, E, _I64(frames.shape[-3]), T


@torch.library.custom_op(qualname("tet_dd_frames"), mutates_args=())
def _tet_dd_frames_op(edge_rot: torch.Tensor, frames: torch.Tensor, edge_vec: torch.Tensor, edges: torch.Tensor,
                      rot_index: torch.Tensor, theta_index: torch.Tensor, order: torch.Tensor,
                      chunk_start: torch.Tensor, color_start: torch.Tensor) -> torch.Tensor:
    """``torchconn::tet_dd_frames``: ``tet_dd`` with ``θ̃'_ij = F_iᵀ √(F_i R F_jᵀ) v``, ``θ̃'_ji = -F_jᵀ
    √(F_i R F_jᵀ)ᵀ v`` formed inside: ``edge_rot (*B, E, 3, 3)``, ``frames (*B, V, 3, 3)``,
    ``edge_vec (E, 3)``, ``edges (E, 2)`` int64 -> ``(*B, T, 3)`` (generic kernel)."""
    return _generic_frames_fwd(edge_rot, frames, edge_vec, edges, rot_index, theta_index)


@_tet_dd_frames_op.register_kernel("cpu")
def _(edge_rot, frames, edge_vec, edges, rot_index, theta_index, order, chunk_start, color_start):
    if not (can_use_compiled("tet", edge_rot, frames, edge_vec) and edges.dtype == torch.int64):
        return _generic_frames_fwd(edge_rot, frames, edge_vec, edges, rot_index, theta_index)
    R, Fr, v, e = edge_rot.contiguous(), frames.contiguous(), edge_vec.contiguous(), edges.contiguous()
    ri, ti = rot_index.contiguous(), theta_index.contiguous()
    out = _native.empty(*edge_rot.shape[:-3], rot_index.shape[0], 3, dtype=edge_rot.dtype)
    nb, E, V, T = _c_frames_sizes(R, Fr, ri)
    if out.numel():
        _check_scratch(_FFWD[R.dtype](_native.ptr(R), _native.ptr(Fr), _native.ptr(v), _native.ptr(e),
                                      _native.ptr(ri), _native.ptr(ti), _native.ptr(out), nb, E, V, T,
                                      torch.get_num_threads(), get_eps("small_angle", R.dtype)))
    return out


@_tet_dd_frames_op.register_fake
def _(edge_rot, frames, edge_vec, edges, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(*edge_rot.shape[:-3], rot_index.shape[0], 3)


@torch.library.custom_op(qualname("tet_dd_frames_backward"), mutates_args=())
def _tet_dd_frames_backward_op(edge_rot: torch.Tensor, frames: torch.Tensor, edge_vec: torch.Tensor,
                               grad: torch.Tensor, edges: torch.Tensor, rot_index: torch.Tensor,
                               theta_index: torch.Tensor, order: torch.Tensor, chunk_start: torch.Tensor,
                               color_start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``torchconn::tet_dd_frames_backward``: ``(∂L/∂edge_rot, ∂L/∂frames, ∂L/∂edge_vec)`` (generic kernel)."""
    return _generic_frames_bwd(edge_rot, frames, edge_vec, grad, edges, rot_index, theta_index)


@_tet_dd_frames_backward_op.register_kernel("cpu")
def _(edge_rot, frames, edge_vec, grad, edges, rot_index, theta_index, order, chunk_start, color_start):
    if not (can_use_compiled("tet", edge_rot, frames, edge_vec, grad) and edges.dtype == torch.int64):
        return _generic_frames_bwd(edge_rot, frames, edge_vec, grad, edges, rot_index, theta_index)
    R, Fr, v, g, e = (t.contiguous() for t in (edge_rot, frames, edge_vec, grad, edges))
    tabs = [t.contiguous() for t in (rot_index, theta_index, order, chunk_start)]
    cs = color_start.contiguous()
    nb, E, V, T = _c_frames_sizes(R, Fr, rot_index)
    g_rot, g_fr = _native.empty(*R.shape, dtype=R.dtype), _native.empty(*Fr.shape, dtype=R.dtype)
    g_vec = _native.empty(*((nb.value,) if nb.value > 1 else ()), *v.shape, dtype=R.dtype)
    if g_rot.numel() and g_fr.numel():  # the kernel zeroes its outputs
        _check_scratch(_FBWD[R.dtype](_native.ptr(R), _native.ptr(Fr), _native.ptr(v), _native.ptr(e), _native.ptr(g),
                                      *(_native.ptr(t) for t in tabs), _native.ptr(cs), _I64(cs.shape[0] - 1),
                                      _native.ptr(g_rot), _native.ptr(g_fr), _native.ptr(g_vec), nb, E, V, T,
                                      torch.get_num_threads(), get_eps("small_angle", R.dtype)))
    else:
        g_rot.zero_(), g_fr.zero_(), g_vec.zero_()
    return g_rot, g_fr, (g_vec if nb.value <= 1 else g_vec.sum(0))


@_tet_dd_frames_backward_op.register_fake
def _(edge_rot, frames, edge_vec, grad, edges, rot_index, theta_index, order, chunk_start, color_start):
    return edge_rot.new_empty(edge_rot.shape), frames.new_empty(frames.shape), edge_vec.new_empty(edge_vec.shape)


def _backward_frames_fwd(ctx, grad):
    edge_rot, frames, edge_vec, edges, *tables = ctx.saved_tensors
    gs = _tet_dd_frames_backward_op(edge_rot, frames, edge_vec, grad.contiguous(), edges, *tables)
    return tuple(g if n else None for g, n in zip(gs, ctx.needs_input_grad[:3])) + (None,) * 6


def _backward_frames_bwd(ctx, gg_rot, gg_fr, gg_vec):
    """As :func:`_backward_bwd`: ``torch.func.vjp`` of the vjp of the generic formula."""
    edge_rot, frames, edge_vec, grad, edges, rot_index, theta_index = ctx.saved_tensors[:7]

    def vjp_generic(R, F, v, g):
        return torch.func.vjp(lambda a, b, c: _generic_frames_fwd(a, b, c, edges, rot_index, theta_index),
                              R, F, v)[1](g)

    _, pullback = torch.func.vjp(vjp_generic, edge_rot, frames, edge_vec, grad)
    gg = tuple(torch.zeros_like(x) if g is None else g
               for g, x in zip((gg_rot, gg_fr, gg_vec), (edge_rot, frames, edge_vec)))
    res = pullback(gg)
    return tuple(r if n else None for r, n in zip(res, ctx.needs_input_grad[:4])) + (None,) * 6


_tet_dd_frames_op.register_autograd(_backward_frames_fwd, setup_context=_setup_fwd)
_tet_dd_frames_backward_op.register_autograd(_backward_frames_bwd, setup_context=_setup_bwd)
_tet_dd_frames_op.register_vmap(leading_vmap(_tet_dd_frames_op, "tet_dd_frames", batched=(0, 1)))
_tet_dd_frames_backward_op.register_vmap(
    leading_vmap(_tet_dd_frames_backward_op, "tet_dd_frames_backward", batched=(0, 1, 3), n_out=3, summed=True))
_tet_dd_frames_call = _func_wrapper(_tet_dd_frames_op, _tet_dd_frames_backward_op, _generic_frames_fwd, 3,
                                    n_extra=1)


def tet_dd_frames(edge_rot: torch.Tensor, frames: torch.Tensor, edge_vec: torch.Tensor, edges: torch.Tensor,
                  kernel: TetKernel) -> torch.Tensor:
    """``torchconn::tet_dd_frames``: :func:`tet_dd` with the solder form read in a frame field and formed
    inside the kernel: ``θ̃'_ij = F_iᵀ H v``, ``θ̃'_ji = -F_jᵀ Hᵀ v`` with ``H = so3.sqrt(F_i R_ij F_jᵀ)``
    (the conventions of :func:`torchconn.dec.dnabla.tet_solder_sqrt` with ``frames``; no ``θ̃'``, ``H``
    or per-edge frame tensor in memory, the frame gradients summed per vertex in the kernel).

    ``edge_rot``: ``(*B, E, 3, 3)``; ``frames``: ``(*B, V, 3, 3)`` (the batch of ``edge_rot``);
    ``edge_vec``: ``(E, 3)`` ``v_j - v_i``; ``edges``: ``(E, 2)`` int64 -> ``(*B, T, 3)``.
    """
    E = kernel.n_edges
    if edge_rot.dim() < 3 or edge_rot.shape[-3:] != (E, 3, 3):
        raise ValueError(f"tet_dd_frames: edge_rot must have shape (*B, {E}, 3, 3), got {tuple(edge_rot.shape)}")
    if frames.shape[:-3] != edge_rot.shape[:-3] or frames.shape[-2:] != (3, 3):
        raise ValueError(f"tet_dd_frames: frames must have shape (*B, V, 3, 3) with the batch dims of edge_rot "
                         f"{tuple(edge_rot.shape[:-3])}, got {tuple(frames.shape)}")
    if edge_vec.shape != (E, 3) or edges.shape != (E, 2):
        raise ValueError(f"tet_dd_frames: edge_vec and edges must have shapes ({E}, 3) and ({E}, 2), got "
                         f"{tuple(edge_vec.shape)} and {tuple(edges.shape)}")
    return _tet_dd_frames_call(edge_rot, frames.to(edge_rot), edge_vec.to(edge_rot), edges, *_tables(kernel))
