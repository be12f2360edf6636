"""The weighted squared norm of the face curvature, value and gradient in one sweep (issue 30).

``torchconn::face_curvature_sqnorm``: per batch item the scalar

    ``s = Σ_f w_f |H_f|_F²``,  ``H = face_curvature(R)`` (:mod:`torchconn.ops.curvature`: cut ``c``
    ``R_ab R_bc − R_ac``, cut ``b`` ``R_ab − R_ac R_bcᵀ``, holonomy ``R_ab R_bc R_acᵀ − I``; report
    Sec. 3.2, (3.2.1)),

with per-face weights ``w (*B, F)`` (a face with ``w_f = 0`` is not computed). It is what a loss
on the curvature (``Curvature(mesh)(R).square().sum()``, weighted) computes, without the
``(F, 3, 3)`` curvature, its square and their backward tensors: the C kernel (``curv_sqn`` in
``csrc/curvature.c``) runs over the edges, recomputes ``H_f`` of each incident face and adds the
slot term of ``2 w_f H_f`` to the edge's gradient (race-free, the CSR table of the curvature's
backward), so the value and ``∂s/∂R`` come out of one sweep. The gradient is an output of the op
(non-differentiable); the op's autograd scales it by the incoming gradient of ``s``.

Op contract (as every op of :mod:`torchconn.ops`): generic torch kernel on every device and dtype
(the generic formulas of :mod:`torchconn.ops.curvature`), CPU kernel = the compiled C when
:func:`~torchconn.ops.backend.can_use_compiled` allows, fake kernel, autograd (second and higher
derivatives, and first derivatives in ``weight``, by ``torch.func.vjp`` of the generic formula:
exact), vmap rule (leading batch dims of ``R`` and ``w``).
"""
from __future__ import annotations

from ctypes import c_int, c_long, c_void_p

import torch

from . import native as _native
from ._library import jvp as _library_jvp
from ._library import leading_vmap, qualname
from ._library import eager_function as _eager_function
from ._library import scale_saved as _scale_saved
from .backend import can_use_compiled
from .curvature import _curvature_bwd_generic, _curvature_generic, _sorted_triangles, _tables

__all__ = ["face_curvature_sqnorm"]

_C_SQN = {dt: _native.declare("curvature", f"curv_sqn_{s}", [c_void_p] * 7 + [c_long, c_long, c_long, c_int, c_int],
                              c_int)
          for dt, s in ((torch.float32, "f32"), (torch.float64, "f64"))}


def _generic_value(edge_rot, weight, face_index, kind):
    """``(s (*B,), H (*B, F, 3, 3))`` in torch operations (differentiable)."""
    H = _curvature_generic(edge_rot, face_index, kind)
    return (weight * H.square().sum((-1, -2))).sum(-1), H


def _empty(x: torch.Tensor) -> torch.Tensor:
    return x.new_empty(*x.shape[:-3], 0)


def _generic(edge_rot, weight, face_index, kind, with_grad):
    value, H = _generic_value(edge_rot, weight, face_index, kind)
    if not with_grad:
        return value, _empty(edge_rot)
    G = 2.0 * weight.unsqueeze(-1).unsqueeze(-1) * H
    return value, _curvature_bwd_generic(edge_rot, G, face_index, kind)


@torch.library.custom_op(qualname("face_curvature_sqnorm"), mutates_args=())
def _sqnorm_op(edge_rot: torch.Tensor, weight: torch.Tensor, face_index: torch.Tensor, inc_ptr: torch.Tensor,
               inc: torch.Tensor, kind: int, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """``torchconn::face_curvature_sqnorm``: ``edge_rot (*B, E, 3, 3)``, ``weight (*B, F)``, the tables
    of the curvature op, ``kind`` (2 cut ``c``, 1 cut ``b``, 0 holonomy) -> ``(s (*B,), ∂s/∂R)`` (the
    gradient ``(*B, 0)`` without ``with_grad``; generic kernel)."""
    return _generic(edge_rot, weight, face_index, kind, with_grad)


@_sqnorm_op.register_kernel("cpu")
def _(edge_rot, weight, face_index, inc_ptr, inc, kind, with_grad):
    if not can_use_compiled("curvature", edge_rot, weight):
        return _generic(edge_rot, weight, face_index, kind, with_grad)
    batch, E, F = edge_rot.shape[:-3], edge_rot.shape[-3], face_index.shape[1]
    nb = batch.numel()
    value = torch.zeros(nb, dtype=torch.float64)
    grad = _native.empty(*edge_rot.shape, dtype=edge_rot.dtype) if with_grad else _empty(edge_rot)
    if nb and E and F:
        ts = [t.contiguous() for t in (edge_rot, weight, face_index, inc_ptr, inc)]
        status = _C_SQN[edge_rot.dtype](*(_native.ptr(t) for t in ts), _native.ptr(value),
                                        _native.ptr(grad) if with_grad else None, nb, E, F, kind,
                                        torch.get_num_threads())
        if status != 0:
            raise MemoryError("torchconn::face_curvature_sqnorm: the C kernel could not allocate its task sums")
    elif with_grad:
        grad.zero_()
    return value.to(edge_rot.dtype).reshape(batch), grad


@_sqnorm_op.register_fake
def _(edge_rot, weight, face_index, inc_ptr, inc, kind, with_grad):
    value = edge_rot.new_empty(edge_rot.shape[:-3])
    if not with_grad:
        return value, _empty(edge_rot)
    return value, torch.empty_like(edge_rot, memory_format=torch.contiguous_format)


def _setup(ctx, inputs, output):
    _, grad = output
    ctx.mark_non_differentiable(grad)
    ctx.kind, with_grad = inputs[5], inputs[6]
    ctx.save_for_backward(inputs[0], inputs[1], inputs[2], grad if with_grad else None)


def _backward(ctx, g_value, _g_grad):
    """First order: the forward's gradient scaled by ``g_value``. Under ``create_graph``, or for
    ``weight``: ``torch.func.vjp`` of the generic formula (exact, differentiable)."""
    R, w, fi, saved = ctx.saved_tensors
    need = ctx.needs_input_grad
    if g_value is None:  # no gradient came in (grads are not materialized: _Fn)
        return (None,) * 7
    if saved is not None and saved.numel() and not torch.is_grad_enabled() and not need[1]:
        return (_scale_saved(saved, g_value),) + (None,) * 6
    _, pullback = torch.func.vjp(lambda a, b: _generic_value(a, b, fi, ctx.kind)[0], R, w)
    gR, gw = pullback(g_value)
    return (gR if need[0] else None, gw if need[1] else None) + (None,) * 5


_sqnorm_op.register_autograd(_backward, setup_context=_setup)
_sqnorm_op.register_vmap(leading_vmap(_sqnorm_op, "face_curvature_sqnorm", batched=(0, 1), n_out=2))


def _jvp(ctx, t_rot, t_w, *_):
    """Forward mode: the generic formula's, by :func:`~._library.jvp`."""
    R, w, fi = ctx.saved_tensors[:3]
    tangents = (torch.zeros_like(R) if t_rot is None else t_rot, torch.zeros_like(w) if t_w is None else t_w)
    t = _library_jvp(lambda a, b: _generic_value(a, b, fi, ctx.kind)[0], (R, w), tangents)
    return t, None


_Fn = _eager_function("FaceCurvatureSqnorm", _sqnorm_op, _setup, _backward, _jvp, n_forward=3)


def face_curvature_sqnorm(edge_rot: torch.Tensor, mesh, weight: torch.Tensor | None = None, cut=-1,
                          kind: str = "two_prong") -> torch.Tensor | None:
    """``Σ_f w_f |H_f|_F²`` per batch item: ``(*B,)``, ``H`` the face curvature of
    :func:`torchconn.ops.curvature.face_curvature` (same ``cut`` and ``kind``), without the
    ``(*B, F, 3, 3)`` tensor.

    Args:
        edge_rot: ``(*B, E, 3, 3)`` ``R_ij`` of the canonical edges of ``mesh`` (a tet mesh or its
            ``nn.MeshBuffers``).
        weight: ``(*B, F)`` or ``(F,)`` per-face weights (default 1), faces in the mesh's global order.

    ``None`` where :func:`~torchconn.ops.curvature.face_curvature` does not apply (a mesh without
    sorted triangles, a non-integer ``cut``) or the rank is not 3: the caller reduces the curvature
    itself. Differentiable to any order in ``edge_rot`` and ``weight`` (module doc). Shapes are
    checked (``ValueError`` naming the argument).
    """
    if (not _sorted_triangles(mesh) or not (kind == "holonomy" or (type(cut) is int and -3 <= cut <= 2))
            or edge_rot.shape[-2:] != (3, 3)):
        return None
    E = int(mesh.edges.shape[0])
    if edge_rot.dim() < 3 or edge_rot.shape[-3] != E:
        raise ValueError(f"face_curvature_sqnorm: edge_rot must have shape (*B, {E}, 3, 3), got {tuple(edge_rot.shape)}")
    fi, ptr, inc = _tables(mesh, edge_rot.device)
    batch, F = edge_rot.shape[:-3], fi.shape[1]
    if weight is None:
        weight = edge_rot.new_ones(F)
    elif weight.shape[-1:] != (F,) or weight.dim() > len(batch) + 1:
        raise ValueError(f"face_curvature_sqnorm: weight must have shape (*B, {F}) or ({F},), got {tuple(weight.shape)}")
    w = weight.to(device=edge_rot.device, dtype=edge_rot.dtype).expand(*batch, F)
    c = cut % 3 if kind == "two_prong" else 0
    with_grad = torch.is_grad_enabled() and edge_rot.requires_grad
    args = (edge_rot, w, fi, ptr, inc, c, with_grad)
    return (_sqnorm_op(*args) if torch.compiler.is_compiling() else _Fn.apply(*args))[0]
