"""The weighted squared norm of the averaged ``d∇d∇θ`` in a frame field, value and gradient in one sweep.

``torchconn::tet_dd_frames_sqnorm``: per batch item the scalar

    ``s = Σ_t w_t |dd_t|²``,  ``dd = tet_dd_frames(R, F)`` (:func:`torchconn.ops.tet_solder.tet_dd_frames`,
    the averaged ``𝔡∇ Alt 𝔡∇ Alt θ̃'`` with ``θ̃'_ij = F_iᵀ √(F_i R_ij F_jᵀ) (v_j - v_i)``; frames
    ``(*B, 0, 3, 3)`` — no rows — stand for the global frame ``F_i = I``, ``θ̃ = √R v``:
    :func:`torchconn.ops.tet_solder.tet_dd_rot`, without the frame products),

with per-tet weights ``w (*B, T)`` (not differentiated by the C kernel; a tet with ``w_t = 0`` is
not computed at all). It is the loss term of a squared ``d∇d∇θ``
(:class:`torchconn.frames.terms.RegularCovariantD`: ``w_t = [t regular] / vol_t^{2/3}``, the sum then
divided by ``#regular``) without its ``(T, 3)`` output and the torch passes
over it: the C kernel (``tet_ddf_sqn`` in ``csrc/tet.c``) forms ``θ̃'`` once per edge, and with
``with_grad`` computes the gradient ``(∂s/∂R, ∂s/∂F)`` in the same sweep (the tet pass
back-propagates ``2 w_t dd_t`` as soon as it has ``dd_t``), so no forward tet pass precedes the
backward and ``θ̃'`` is not formed twice. Those gradients are outputs of the op (non-differentiable);
the op's autograd scales them by the incoming gradient of ``s`` (first order: no second sweep).

Op contract (as every op of :mod:`torchconn.ops`): generic torch kernel on every device and dtype
(the generic formulas of :mod:`torchconn.ops.tet_solder`), CPU kernel = the compiled C when
:func:`~torchconn.ops.backend.can_use_compiled` allows, fake kernel, autograd (second and higher
derivatives, and first derivatives in ``edge_vec`` or ``w``, by ``torch.func.vjp`` of the
generic formula: exact), vmap rule (leading batch dims of ``R``, ``F``, ``w``).
"""
from __future__ import annotations

import ctypes

import torch

from . import native as _native
from ._cache import edge_index as _edge_index
from ._cache import edge_vectors as _edge_vectors
from ._library import jvp as _library_jvp
from ._library import leading_vmap, qualname
from ._library import eager_function as _eager_function
from ._library import scale_saved as _scale_saved
from .backend import can_use_compiled
from .tet import _I64, _P, _tables, tet_kernel
from .tet_solder import _generic_frames_bwd, _generic_frames_fwd, _generic_rot_bwd, _generic_rot_fwd
from ..tolerances import get_eps

__all__ = ["tet_dd_frames_sqnorm"]

_SQN = {dt: _native.declare("tet", f"tet_ddf_sqn_{sfx}",
                            [_P] * 10 + [_I64] + [_P] * 3 + [_I64] * 4 + [ctypes.c_int, ctypes.c_double,
                                                                            ctypes.c_int], ctypes.c_int)
        for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}


def _framed(frames: torch.Tensor) -> bool:
    """Frames with rows (``(*B, V, 3, 3)``); ``(*B, 0, 3, 3)`` is the global frame, ``F_i = I``."""
    return frames.shape[-3] > 0


def _generic_value(edge_rot, frames, edge_vec, edges, weight, rot_index, theta_index):
    """``(s (*B,), dd (*B, T, 3))`` in torch operations (differentiable)."""
    if _framed(frames):
        dd = _generic_frames_fwd(edge_rot, frames, edge_vec, edges, rot_index, theta_index)
    else:
        dd = _generic_rot_fwd(edge_rot, edge_vec, rot_index, theta_index)
    return (weight * (dd * dd).sum(-1)).sum(-1), dd


def _generic(edge_rot, frames, edge_vec, edges, weight, rot_index, theta_index, with_grad):
    value, dd = _generic_value(edge_rot, frames, edge_vec, edges, weight, rot_index, theta_index)
    if not with_grad:
        return value, _empty(edge_rot), _empty(edge_rot)
    g = 2.0 * weight.unsqueeze(-1) * dd
    if not _framed(frames):
        g_rot, _ = _generic_rot_bwd(edge_rot, edge_vec, g, rot_index, theta_index)
        return value, g_rot, torch.zeros_like(frames, memory_format=torch.contiguous_format)
    g_rot, g_fr, _ = _generic_frames_bwd(edge_rot, frames, edge_vec, g, edges, rot_index, theta_index)
    return value, g_rot, g_fr


def _empty(x: torch.Tensor) -> torch.Tensor:
    return x.new_empty(*x.shape[:-3], 0)


@torch.library.custom_op(qualname("tet_dd_frames_sqnorm"), mutates_args=())
def _sqnorm_op(edge_rot: torch.Tensor, frames: torch.Tensor, edge_vec: torch.Tensor, edges: torch.Tensor,
               weight: torch.Tensor, rot_index: torch.Tensor, theta_index: torch.Tensor, order: torch.Tensor,
               chunk_start: torch.Tensor, color_start: torch.Tensor, with_grad: bool
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``torchconn::tet_dd_frames_sqnorm``: ``edge_rot (*B, E, 3, 3)``, ``frames (*B, V, 3, 3)``,
    ``edge_vec (E, 3)``, ``edges (E, 2)`` int64, ``weight (*B, T)``, the tables of
    :meth:`~torchconn.ops.tet.TetKernel.tables` -> ``(s (*B,), ∂s/∂R, ∂s/∂F)`` (the gradients
    ``(*B, 0)`` without ``with_grad``; generic kernel)."""
    return _generic(edge_rot, frames, edge_vec, edges, weight, rot_index, theta_index, with_grad)


@_sqnorm_op.register_kernel("cpu")
def _(edge_rot, frames, edge_vec, edges, weight, rot_index, theta_index, order, chunk_start, color_start, with_grad):
    if not (can_use_compiled("tet", edge_rot, frames, edge_vec, weight) and edges.dtype == torch.int64):
        return _generic(edge_rot, frames, edge_vec, edges, weight, rot_index, theta_index, with_grad)
    R, Fr, v, e, w = (t.contiguous() for t in (edge_rot, frames, edge_vec, edges, weight))
    tabs = [t.contiguous() for t in (rot_index, theta_index, order, chunk_start, color_start)]
    batch, E, V, T = edge_rot.shape[:-3], R.shape[-3], Fr.shape[-3], rot_index.shape[0]
    framed = _framed(frames)
    nb = batch.numel()
    value = torch.zeros(nb, dtype=torch.float64)
    g_rot = _native.empty(*R.shape, dtype=R.dtype) if with_grad else _empty(R)
    g_fr = _native.empty(*Fr.shape, dtype=R.dtype) if with_grad else _empty(R)
    if nb and E and T:
        status = _SQN[R.dtype](_native.ptr(R), _native.ptr(Fr) if framed else None, _native.ptr(v), _native.ptr(e), _native.ptr(w),
                               *(_native.ptr(t) for t in tabs), _I64(tabs[-1].shape[0] - 1), _native.ptr(value),
                               _native.ptr(g_rot) if with_grad else None,
                               _native.ptr(g_fr) if with_grad and framed else None,
                               _I64(nb), _I64(E), _I64(V), _I64(T), torch.get_num_threads(),
                               get_eps("small_angle", R.dtype), int(with_grad))
        if status != 0:
            raise MemoryError("torchconn::tet_dd_frames_sqnorm: the C kernel could not map its scratch buffer")
    elif with_grad:
        g_rot.zero_(), g_fr.zero_()
    return value.to(R.dtype).reshape(batch), g_rot, g_fr


@_sqnorm_op.register_fake
def _(edge_rot, frames, edge_vec, edges, weight, rot_index, theta_index, order, chunk_start, color_start, with_grad):
    value = edge_rot.new_empty(edge_rot.shape[:-3])
    if not with_grad:
        return value, _empty(edge_rot), _empty(edge_rot)
    return (value, torch.empty_like(edge_rot, memory_format=torch.contiguous_format),
            torch.empty_like(frames, memory_format=torch.contiguous_format))


def _setup(ctx, inputs, output):
    _, g_rot, g_fr = output
    ctx.mark_non_differentiable(g_rot, g_fr)
    with_grad = inputs[-1]
    ctx.save_for_backward(*inputs[:7], g_rot if with_grad else None, g_fr if with_grad else None)


def _backward(ctx, g_value, _g_rot, _g_fr):
    """First order: the forward's gradients scaled by ``g_value``. Under ``create_graph``, or for
    ``edge_vec`` / ``weight``: ``torch.func.vjp`` of the generic formula (exact, differentiable)."""
    R, Fr, vec, edges, w, ri, ti, saved_rot, saved_fr = ctx.saved_tensors
    need = ctx.needs_input_grad
    if g_value is None:  # no gradient came in (grads are not materialized: _Fn)
        return (None,) * 11
    if (saved_rot is not None and saved_rot.numel() and not torch.is_grad_enabled()
            and not (need[2] or need[4])):
        return (_scale_saved(saved_rot, g_value) if need[0] else None,
                _scale_saved(saved_fr, g_value) if need[1] else None) + (None,) * 9
    _, pullback = torch.func.vjp(lambda a, b, c, d: _generic_value(a, b, c, edges, d, ri, ti)[0], R, Fr, vec, w)
    gR, gF, gv, gw = pullback(g_value)
    return (gR if need[0] else None, gF if need[1] else None, gv if need[2] else None, None,
            gw if need[4] else None) + (None,) * 6


_sqnorm_op.register_autograd(_backward, setup_context=_setup)
_sqnorm_op.register_vmap(leading_vmap(_sqnorm_op, "tet_dd_frames_sqnorm", batched=(0, 1, 4), n_out=3))


def _jvp(ctx, t_rot, t_fr, t_vec, _t_edges, t_w, *_):
    """Forward mode: the generic formula's, by :func:`~._library.jvp`."""
    R, Fr, vec, edges, w, ri, ti = ctx.saved_tensors[:7]
    tangents = tuple(torch.zeros_like(x) if t is None else t for x, t in ((R, t_rot), (Fr, t_fr), (vec, t_vec),
                                                                          (w, t_w)))
    t = _library_jvp(lambda a, b, c, d: _generic_value(a, b, c, edges, d, ri, ti)[0], (R, Fr, vec, w), tangents)
    return t, None, None


_Fn = _eager_function("TetDDFramesSqnorm", _sqnorm_op, _setup, _backward, _jvp, n_forward=7)


def tet_dd_frames_sqnorm(edge_rot: torch.Tensor, frames: torch.Tensor | None, weight: torch.Tensor, mesh
                         ) -> torch.Tensor:
    """``Σ_t w_t |dd_t|²`` per batch item: ``(*B,)``, with ``dd (*B, T, 3)`` the averaged ``d∇d∇θ`` of
    ``edge_rot`` with the solder form in ``frames`` (:func:`torchconn.dec.dnabla.averaged_dd_solder`
    with ``frames``; :func:`torchconn.ops.tet_solder.tet_dd_frames`), without the ``(T, 3)`` tensor.

    Args:
        edge_rot: ``(*B, E, 3, 3)`` ``R_ij`` of the canonical edges of ``mesh`` (a ``TetMesh``).
        frames: ``(*B, V, 3, 3)``, axes as columns (the batch dims of ``edge_rot``), or ``None``: the
            global frame (``F_i = I``, ``θ̃ = √R v``; the kernel then forms no frame products and
            no frame gradient).
        weight: ``(*B, T)`` per-tet weights (or ``(T,)``, broadcast), dtype of ``edge_rot``.

    Differentiable to any order in ``edge_rot``, ``frames`` and ``weight`` (module doc). Shapes are
    checked (``ValueError`` naming the argument).
    """
    k = tet_kernel(mesh, edge_rot.device)
    E, T = k.n_edges, k.rot_index.shape[0]
    if edge_rot.dim() < 3 or edge_rot.shape[-3:] != (E, 3, 3):
        raise ValueError(f"tet_dd_frames_sqnorm: edge_rot must have shape (*B, {E}, 3, 3), got {tuple(edge_rot.shape)}")
    batch = edge_rot.shape[:-3]
    V = mesh.vertices.shape[0]
    if frames is None:
        frames = edge_rot.new_empty(*batch, 0, 3, 3)
    elif frames.shape != (*batch, V, 3, 3):
        raise ValueError(f"tet_dd_frames_sqnorm: frames must have shape {(*batch, V, 3, 3)}, got {tuple(frames.shape)}")
    if weight.shape[-1:] != (T,):
        raise ValueError(f"tet_dd_frames_sqnorm: weight must have shape (*B, {T}), got {tuple(weight.shape)}")
    dev, dt = edge_rot.device, edge_rot.dtype
    w = weight.to(device=dev, dtype=dt).expand(*batch, T)
    with_grad = torch.is_grad_enabled() and (edge_rot.requires_grad or frames.requires_grad)
    args = (edge_rot, frames.to(dtype=dt), _edge_vectors(mesh, dev, dt), _edge_index(mesh, dev), w, *_tables(k),
            with_grad)
    return (_sqnorm_op(*args) if torch.compiler.is_compiling() else _Fn.apply(*args))[0]
