"""The fast path of the frame-field loss terms ``smooth``, ``tie``, ``flat``, ``torsion``, ``dirichlet``: one custom op.

The terms are defined by the loss's modules (:mod:`torchconn.frames.terms`, composed by
:class:`~torchconn.frames.loss.FrameFieldLoss`); this op computes the same values and gradients
in one fused sweep, with ``rho(d2) = d2`` for ``power = 2``, else ``(d2 + eps²)^(power/2) - eps^power``:

* ``smooth    = mean_e rho(|R_e - I|²)``;
* ``tie       = mean_e rho(|F_i R_e - F_j h_e|²)``, ``h_e = argmax_{h in O} tr(hᵀ F_jᵀ F_i R_e)``;
* ``flat      = mean_f |H_f - g_f|²``, ``H_f = R_ab R_bc R_acᵀ`` (report eq. 3.2.1 plus ``I``),
  ``g_f = argmax_{g in O} tr(gᵀ H_f)``;
* ``torsion   = mean_f |Θ_f|² / area_f`` over **every** face, through the matchings:
  ``Θ_f = θ_ab + M_ab θ_bc - θ_ac`` (Def. 3.2) for the matched connection ``M_ij = R_ij h_ijᵀ``,
  ``θ_ij = F_iᵀ √(F_i M_ij F_jᵀ) (v_j - v_i)``;
* ``dirichlet = mean_e |F_i g_e - F_j|²``, ``g_e = argmax_{g in O} tr(gᵀ F_iᵀ F_j)``;

and, on request, the flags of the *regular* faces (``g_f = I``), the mask of the loss's ``dnabla``
term. The matchings ``h``, ``g`` are piecewise-constant choices (first maximal score, the order of
the group table), not differentiated. ``√A = ((1 + s) I + A + (A - Aᵀ)/s) / (2 + s)``,
``s = sqrt(1 + tr A)``: the closed form of :func:`torchconn.ops.so3.sqrt` on rotations of angle
< 120° (the matched ``A`` of a rotation field is within ~63° of ``I``, the covering radius of O),
written in the entries of ``A``, so C and torch agree for any matrices, not only along rotations.

Ops (``torch.ops.torchconn.*``; inputs ``edge_rot (*B, E, 3, 3)``, ``frames (*B, V, 3, 3)`` with
one batch shape, the tables of :func:`mesh_tables`, the group ``(24, 3, 3)``, explicit options):

* ``frame_loss`` -> ``(values (*B, 5), grad_rot, grad_frames, face_regular)``: the values of the
  five terms (0 for a term that is off), with ``with_grad`` the gradient of ``Σ_k w_k term_k``
  (``(*B, E, 3, 3)``, ``(*B, V, 3, 3)``, non-differentiable outputs; ``(*B, 0)`` without) and
  with ``regular`` the flags ``(*B, F)`` bool (``(*B, 0)`` without). CPU kernel:
  ``csrc/frame_loss.c`` when :func:`~torchconn.ops.backend.can_use_compiled` allows (values and
  gradient in one sweep, batch items looped in C), else the generic kernel (``_frame_loss_torch``:
  the terms with their gradient written out in torch, no autograd inside the kernel), which is also
  the kernel of every other device.
* ``frame_loss_backward`` -> ``(d edge_rot, d frames)``, the gradient of ``Σ_k g_k term_k``
  for incoming weights ``g (*B, 5)``: when the forward's gradient is passed in and ``g`` is
  proportional to ``w`` item by item (the usual ``out["total"].backward()``) it is scaled
  (no second sweep); otherwise one more C sweep (CPU) or the generic gradient. Its own
  autograd differentiates the torch terms (``torch.func``: a Hessian-vector product in
  ``R, F``, a JVP in ``g``), so double backward, ``create_graph`` and Hessian-vector products
  are exact on every path, with C for the first order.

Both ops have fake implementations (meta tensors, ``torch.compile``, ``export``) and vmap
rules (native leading batch dims). :func:`frame_loss_terms`, the loss's entry, calls the op
where its compiled kernel serves and returns ``None`` elsewhere (the loss then runs its modules);
eagerly through an ``autograd.Function`` with ``setup_context`` and ``jvp``, so ``torch.func.grad``,
``vmap`` and ``jvp`` work (the ``register_autograd`` Function has no ``setup_context`` and no
forward mode), directly while ``torch.compile`` traces (one op in the graph, the C kernel at
runtime). First-order eager ``total.backward()`` returns the forward's gradient itself (no copy,
no second sweep).

Scratch memory of the C sweep (per-thread scatter buffers, solder forms, the matchings;
``(nt - 1)(12E + 9V) + 6E`` values + ``E`` bytes, ~94 MB at 1M tets, float32, 2 threads) is not
state of the loss or the mesh: it lives in a per-thread cache (``threading.local``) keyed by
dtype, grown to the largest size needed (:func:`release_scratch` frees the calling thread's),
so two threads never share it (allocated per call instead, glibc maps blocks over 32 MB afresh
and every step page-faults them again). Index and geometry tables are immutable, built once per
mesh, dtype and device (``mesh.require``).
"""
from __future__ import annotations

import ctypes
import threading
from pathlib import Path
from typing import Mapping, Optional

import torch

from ...ops import native as _native
from ...ops._cache import require as _require
from ...ops._cache import traced_constant
from ...ops._library import jvp as _library_jvp
from ...ops._library import leading_vmap, qualname
from ...ops.backend import can_use_compiled, compiled_enabled
from ...ops.curvature import _sorted_triangles
from . import _frame_loss_torch as _T

__all__ = ["COMPILED_TERMS", "frame_loss_terms", "call", "mesh_tables", "terms_generic", "release_scratch"]

#: The terms of the op, in the order of its ``values`` output.
COMPILED_TERMS = ("smooth", "tie", "flat", "torsion", "dirichlet")
_K = len(COMPILED_TERMS)

_vp, _long, _int, _dbl = ctypes.c_void_p, ctypes.c_long, ctypes.c_int, ctypes.c_double
# frame_loss_<T>(B, E, V, F, nt, R, Fr, edges, fidx, vec, area, group, do_smooth, do_tie, do_flat,
#                do_torsion, do_dirichlet, do_regular, grad, power, eps, wts, sums, gR, gF, regular,
#                work, theta, gtheta, hidx)
_ARGTYPES = [_long] * 4 + [_int] + [_vp] * 7 + [_int] * 7 + [_dbl] * 2 + [_vp] * 9
_native.register_source("frame_loss", Path(__file__).resolve().parent / "csrc" / "frame_loss.c")
_C_SWEEP = {torch.float32: _native.declare("frame_loss", "frame_loss_f32", _ARGTYPES, _int),
            torch.float64: _native.declare("frame_loss", "frame_loss_f64", _ARGTYPES, _int)}


def terms_generic(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, face_edges: torch.Tensor,
                  edge_vec: torch.Tensor, face_area: torch.Tensor, group: torch.Tensor, smooth: bool, tie: bool,
                  flat: bool, torsion: bool, dirichlet: bool, power: float, eps: float) -> torch.Tensor:
    """The five terms (module doc) in torch operations: ``(*B, 5)``, 0 for a term that is off.

    Any device and floating dtype, differentiable to any order (the matchings are index choices).
    ``edge_rot (*B, E, 3, 3)``, ``frames (*B, V, 3, 3)``; tables as :func:`mesh_tables`,
    ``group (24, 3, 3)``. The generic kernel of the ops and the function their backward
    differentiates (``_frame_loss_torch``).
    """
    return _T.terms(edge_rot, frames, edges, face_edges, edge_vec, face_area, group,
                    (smooth, tie, flat, torsion, dirichlet), power, eps)


# ----------------------------------------------------------------------------- scratch memory

_TLS = threading.local()


def _scratch(dtype: torch.dtype, n: int, n_bytes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(n,)`` of ``dtype`` and ``(n_bytes,)`` uint8 from the calling thread's cache (see module doc)."""
    bufs = _TLS.__dict__.setdefault("bufs", {})
    size = torch.empty((), dtype=dtype).element_size()
    need = max(1, n + (n_bytes + size - 1) // size)
    buf = bufs.get(dtype)
    if buf is None or buf.numel() < need:
        bufs[dtype] = None  # free the old one first
        buf = bufs[dtype] = torch.empty(need, dtype=dtype)
    return buf[:n], buf[n:need].view(torch.uint8)[:n_bytes]


def release_scratch() -> None:
    """Free the calling thread's scratch buffers of the compiled kernel (they are rebuilt on use)."""
    _TLS.__dict__.pop("bufs", None)


# ----------------------------------------------------------------------------- C sweep

def _sweep_c(edge_rot, frames, edges, face_edges, edge_vec, face_area, group, on, regular, wts, power, eps, grad):
    """Run ``csrc/frame_loss.c``: ``(sums (B, 5) float64, gR (B, E, 3, 3) | None, gF | None,
    face_regular (B, F) bool | None)``. ``wts (B, 5)`` float64: the gradient weights of each item."""
    dt = edge_rot.dtype
    E, V, F = edge_rot.shape[-3], frames.shape[-3], face_edges.shape[0]
    R = edge_rot.reshape(-1, E, 3, 3).contiguous()
    Fr = frames.reshape(-1, V, 3, 3).contiguous()
    B = R.shape[0]
    nt = max(1, min(64, torch.get_num_threads()))
    smooth, tie, flat, torsion, dirichlet = on
    n_work = (nt - 1) * (12 * E + 9 * V) if grad else 0
    n_theta = 3 * E if torsion else 0
    work, hidx = _scratch(dt, n_work + 2 * n_theta, E if (tie or torsion) else 0)
    sums = torch.empty(B, _K, dtype=torch.float64)
    gR = _native.empty(B, E, 3, 3, dtype=dt) if grad else None
    gF = torch.empty(B, V, 3, 3, dtype=dt) if grad else None
    reg = torch.empty(B, F, dtype=torch.bool) if regular else None
    w64 = wts.to(torch.float64).reshape(B, _K).contiguous() if grad else torch.zeros(B, _K, dtype=torch.float64)
    g64 = group.to(torch.float64).reshape(24, 9).contiguous()
    base = work.data_ptr()
    isz = work.element_size()
    status = _C_SWEEP[dt](
        B, E, V, F, nt, R.data_ptr(), Fr.data_ptr(), edges.data_ptr(), face_edges.data_ptr(),
        edge_vec.data_ptr(), face_area.data_ptr(), g64.data_ptr(), int(smooth), int(tie), int(flat),
        int(torsion), int(dirichlet), int(regular), int(grad), float(power), float(eps), w64.data_ptr(),
        sums.data_ptr(), gR.data_ptr() if grad else None, gF.data_ptr() if grad else None,
        reg.data_ptr() if regular else None, base, base + isz * n_work, base + isz * (n_work + n_theta),
        hidx.data_ptr())
    if status != 0:
        raise RuntimeError(f"torchconn::frame_loss: csrc/frame_loss.c returned {status}: its octahedral score "
                           "table does not match the group table passed in (torchconn.frames.octahedral.group())")
    return sums, gR, gF, reg


def _c_applies(edge_rot, frames, edges, face_edges, edge_vec, face_area) -> bool:
    return (can_use_compiled("frame_loss", edge_rot, frames, edge_vec, face_area)
            and edges.dtype == face_edges.dtype == torch.int64
            and edges.is_contiguous() and face_edges.is_contiguous()
            and edge_vec.is_contiguous() and face_area.is_contiguous())


# ----------------------------------------------------------------------------- forward op

def _empty(edge_rot: torch.Tensor, dtype=None) -> torch.Tensor:
    return edge_rot.new_empty(*edge_rot.shape[:-3], 0, dtype=dtype)


def _grad_generic(R, Fr, gv, tables, on, power, eps):
    """``∇_{R, F} Σ_k g_k term_k`` by ``torch.func.vjp`` of :func:`terms_generic` (autograd level
    only: composable with autograd and the transforms, not for use inside an op kernel)."""
    vals, vjp = torch.func.vjp(lambda a, b: _T.terms(a, b, *tables, on, power, eps), R, Fr)
    return vjp(gv.to(vals.dtype).expand(vals.shape))


def _forward_generic(edge_rot, frames, tables, on, regular, w, power, eps, with_grad):
    wts = torch.tensor(w, dtype=edge_rot.dtype, device=edge_rot.device) if with_grad else None
    vals, gR, gF = _T.sweep(edge_rot, frames, *tables, on, power, eps, wts)
    if not with_grad:
        gR, gF = _empty(edge_rot), _empty(edge_rot)
    reg = _T.face_regular(edge_rot, tables[1], tables[4]) if regular else _empty(edge_rot, torch.bool)
    return vals, gR, gF, reg


@torch.library.custom_op(qualname("frame_loss"), mutates_args=())
def _frame_loss(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, face_edges: torch.Tensor,
                edge_vec: torch.Tensor, face_area: torch.Tensor, group: torch.Tensor, smooth: bool, tie: bool,
                flat: bool, torsion: bool, dirichlet: bool, regular: bool, w_smooth: float, w_tie: float,
                w_flat: float, w_torsion: float, w_dirichlet: float, power: float, eps: float, with_grad: bool
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    return _forward_generic(edge_rot, frames, (edges, face_edges, edge_vec, face_area, group),
                            (smooth, tie, flat, torsion, dirichlet), regular,
                            [w_smooth, w_tie, w_flat, w_torsion, w_dirichlet], power, eps, with_grad)


@_frame_loss.register_kernel("cpu")
def _(edge_rot, frames, edges, face_edges, edge_vec, face_area, group, smooth, tie, flat, torsion, dirichlet,
      regular, w_smooth, w_tie, w_flat, w_torsion, w_dirichlet, power, eps, with_grad):
    on, w = (smooth, tie, flat, torsion, dirichlet), [w_smooth, w_tie, w_flat, w_torsion, w_dirichlet]
    tables = (edges, face_edges, edge_vec, face_area, group)
    if not _c_applies(edge_rot, frames, edges, face_edges, edge_vec, face_area):
        return _forward_generic(edge_rot, frames, tables, on, regular, w, power, eps, with_grad)
    batch = edge_rot.shape[:-3]
    wts = torch.tensor(w, dtype=torch.float64).expand(max(1, batch.numel()), _K)
    sums, gR, gF, reg = _sweep_c(edge_rot, frames, *tables, on, regular, wts, power, eps, with_grad)
    vals = sums.to(edge_rot.dtype).reshape(*batch, _K)
    reg = reg.reshape(*batch, -1) if regular else _empty(edge_rot, torch.bool)
    if not with_grad:
        return vals, _empty(edge_rot), _empty(edge_rot), reg
    return vals, gR.reshape(edge_rot.shape), gF.reshape(frames.shape), reg


@_frame_loss.register_fake
def _(edge_rot, frames, edges, face_edges, edge_vec, face_area, group, smooth, tie, flat, torsion, dirichlet,
      regular, w_smooth, w_tie, w_flat, w_torsion, w_dirichlet, power, eps, with_grad):
    b = edge_rot.shape[:-3]
    vals = edge_rot.new_empty(*b, _K)
    reg = edge_rot.new_empty(*b, face_edges.shape[0] if regular else 0, dtype=torch.bool)
    if not with_grad:
        return vals, _empty(edge_rot), _empty(edge_rot), reg
    return vals, torch.empty_like(edge_rot, memory_format=torch.contiguous_format), \
        torch.empty_like(frames, memory_format=torch.contiguous_format), reg


# ----------------------------------------------------------------------------- backward op

def _reuse_scale(grad_values, options, saved_rot) -> torch.Tensor | None:
    """Per item ``s`` with ``grad_values = s w`` on the terms that are on (then the forward's
    gradient scaled by ``s`` is the answer), or ``None``. Reads the ``(*B, 5)`` weights (a device
    sync off the CPU). ``options``: the backward op's (five flags, five weights, power, eps)."""
    if saved_rot is None or saved_rot.numel() == 0:
        return None
    on, w = options[:_K], options[_K:2 * _K]
    idx = [k for k in range(_K) if on[k]]
    ref = next((k for k in idx if w[k] != 0.0), None)
    if ref is None:
        return None
    g = grad_values.detach().to("cpu", torch.float64).reshape(-1, _K)[:, idx]
    wt = torch.tensor([w[k] for k in idx], dtype=torch.float64)
    s = g[:, idx.index(ref)] / w[ref]
    sw = s[:, None] * wt
    tol = 1e-12 if saved_rot.dtype == torch.float64 else 1e-6
    if bool(((g - sw).abs() <= tol * torch.maximum(g.abs(), sw.abs())).all()):
        return s
    return None


def _hvp_generic(R, Fr, gv, v_rot, v_frames, tables, options):
    """Derivative of ``(R, F, g) -> ∇_{R,F} Σ_k g_k term_k`` along ``(v_rot, v_frames)`` (a
    Hessian-vector product in ``R, F``, a JVP of the terms in ``g``), by ``torch.func`` of
    :func:`terms_generic`; recorded by autograd when the caller's backward is (``create_graph``),
    so every order is exact."""
    on, power, eps = options[:_K], options[-2], options[-1]
    _, vjp = torch.func.vjp(lambda a, b, g: _grad_generic(a, b, g, tables, on, power, eps), R, Fr, gv)
    return vjp((torch.zeros_like(R) if v_rot is None else v_rot, torch.zeros_like(Fr) if v_frames is None else v_frames))


def _scaled(saved_rot, saved_frames, s, edge_rot, frames):
    s = s.to(device=saved_rot.device, dtype=saved_rot.dtype)
    return (saved_rot.reshape(-1, *edge_rot.shape[-3:]) * s[:, None, None, None]).reshape(edge_rot.shape), \
        (saved_frames.reshape(-1, *frames.shape[-3:]) * s[:, None, None, None]).reshape(frames.shape)


def _backward_generic(edge_rot, frames, tables, grad_values, options):
    return _T.sweep(edge_rot, frames, *tables, options[:_K], options[-2], options[-1], grad_values)[1:]


@torch.library.custom_op(qualname("frame_loss_backward"), mutates_args=())
def _frame_loss_backward(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor,
                         face_edges: torch.Tensor, edge_vec: torch.Tensor, face_area: torch.Tensor,
                         group: torch.Tensor, grad_values: torch.Tensor, saved_grad_rot: Optional[torch.Tensor],
                         saved_grad_frames: Optional[torch.Tensor], smooth: bool, tie: bool, flat: bool,
                         torsion: bool, dirichlet: bool, w_smooth: float, w_tie: float, w_flat: float,
                         w_torsion: float, w_dirichlet: float, power: float, eps: float
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    options = (smooth, tie, flat, torsion, dirichlet, w_smooth, w_tie, w_flat, w_torsion, w_dirichlet, power, eps)
    s = _reuse_scale(grad_values, options, saved_grad_rot)
    if s is not None:
        return _scaled(saved_grad_rot, saved_grad_frames, s, edge_rot, frames)
    return _backward_generic(edge_rot, frames, (edges, face_edges, edge_vec, face_area, group), grad_values, options)


@_frame_loss_backward.register_kernel("cpu")
def _(edge_rot, frames, edges, face_edges, edge_vec, face_area, group, grad_values, saved_grad_rot,
      saved_grad_frames, smooth, tie, flat, torsion, dirichlet, w_smooth, w_tie, w_flat, w_torsion, w_dirichlet,
      power, eps):
    options = (smooth, tie, flat, torsion, dirichlet, w_smooth, w_tie, w_flat, w_torsion, w_dirichlet, power, eps)
    s = _reuse_scale(grad_values, options, saved_grad_rot)
    if s is not None:
        return _scaled(saved_grad_rot, saved_grad_frames, s, edge_rot, frames)
    tables = (edges, face_edges, edge_vec, face_area, group)
    if not _c_applies(edge_rot, frames, edges, face_edges, edge_vec, face_area):
        return _backward_generic(edge_rot, frames, tables, grad_values, options)
    B = max(1, edge_rot.shape[:-3].numel())
    gv = grad_values.to(torch.float64).expand(*edge_rot.shape[:-3], _K).reshape(B, _K)
    _, gR, gF, _ = _sweep_c(edge_rot, frames, *tables, options[:_K], False, gv, power, eps, True)
    return gR.reshape(edge_rot.shape), gF.reshape(frames.shape)


@_frame_loss_backward.register_fake
def _(edge_rot, frames, edges, face_edges, edge_vec, face_area, group, grad_values, saved_grad_rot,
      saved_grad_frames, smooth, tie, flat, torsion, dirichlet, w_smooth, w_tie, w_flat, w_torsion, w_dirichlet,
      power, eps):
    return (torch.empty_like(edge_rot, memory_format=torch.contiguous_format),
            torch.empty_like(frames, memory_format=torch.contiguous_format))


# ----------------------------------------------------------------------------- autograd

_N_TABLES = 7  # edge_rot, frames, edges, face_edges, edge_vec, face_area, group
_N_OPTIONS_BWD = 2 * _K + 2  # five flags, five weights, power, eps


def _bwd_options(fwd_options):
    """The backward op's options from the forward op's (five flags, regular, five weights, power, eps)."""
    return (*fwd_options[:_K], *fwd_options[_K + 1:])


def _fwd_setup(ctx, inputs, output):
    _, gR, gF, reg = output
    ctx.mark_non_differentiable(gR, gF, reg)
    with_grad = inputs[-1]
    ctx.save_for_backward(*inputs[:_N_TABLES], gR if with_grad else None, gF if with_grad else None)
    ctx.options = _bwd_options(inputs[_N_TABLES:-1])


def _fwd_backward(ctx, grad_values, _grad_rot, _grad_frames, _grad_reg):
    *tables, saved_rot, saved_frames = ctx.saved_tensors
    dR, dF = _frame_loss_backward(*tables, grad_values, saved_rot, saved_frames, *ctx.options)
    return (dR if ctx.needs_input_grad[0] else None, dF if ctx.needs_input_grad[1] else None,
            *([None] * (len(ctx.needs_input_grad) - 2)))


def _bwd_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs[:_N_TABLES], inputs[_N_TABLES])  # + grad_values
    ctx.options = inputs[_N_TABLES + 3:]


def _bwd_backward(ctx, v_rot, v_frames):
    R, Fr, *tables, gv = ctx.saved_tensors
    gR, gF, gg = _hvp_generic(R, Fr, gv, v_rot, v_frames, tables, ctx.options)
    need = ctx.needs_input_grad
    out = [gR if need[0] else None, gF if need[1] else None] + [None] * (_N_TABLES - 2)
    out.append(gg if need[_N_TABLES] else None)
    return (*out, *([None] * (len(need) - _N_TABLES - 1)))


_frame_loss.register_autograd(_fwd_backward, setup_context=_fwd_setup)
_frame_loss_backward.register_autograd(_bwd_backward, setup_context=_bwd_setup)


# ----------------------------------------------------------------------------- vmap

_frame_loss.register_vmap(leading_vmap(_frame_loss, "frame_loss", batched=(0, 1), n_out=4))


def _bwd_vmap(info, in_dims, *args):
    """Leading batch dims on ``edge_rot, frames, grad_values`` and the saved gradients (possibly None)."""
    batched = (0, 1, _N_TABLES, _N_TABLES + 1, _N_TABLES + 2)
    args = list(args)
    for i, d in enumerate(in_dims):
        if i in batched:
            if args[i] is None:
                continue
            if d is None:
                args[i] = args[i].unsqueeze(0).expand(info.batch_size, *args[i].shape)
            elif d != 0:
                args[i] = args[i].movedim(d, 0)
        elif d is not None:
            raise ValueError(f"torchconn::frame_loss_backward: vmap over argument {i} is not supported "
                             f"(only arguments {list(batched)} take leading batch dimensions)")
    return _frame_loss_backward(*args), (0, 0)


_frame_loss_backward.register_vmap(_bwd_vmap)


# ----------------------------------------------------------------------------- torch.func

class _BackwardFn(torch.autograd.Function):
    """``torchconn::frame_loss_backward`` for eager calls (see :class:`_LossFn`)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(*args):
        return _frame_loss_backward(*args)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(*inputs[:_N_TABLES + 1])
        ctx.save_for_forward(*inputs[:_N_TABLES + 1])
        ctx.options = inputs[_N_TABLES + 3:]

    @staticmethod
    def backward(ctx, v_rot, v_frames):
        R, Fr, *tables, gv = ctx.saved_tensors
        gR, gF, gg = _hvp_generic(R, Fr, gv, v_rot, v_frames, tables, ctx.options)
        return gR, gF, *([None] * (_N_TABLES - 2)), gg, *([None] * (2 + _N_OPTIONS_BWD))

    @staticmethod
    def jvp(ctx, t_rot, t_frames, *tangents):
        R, Fr, *tables, gv = ctx.saved_tensors
        t_gv = tangents[_N_TABLES - 2]
        on, power, eps = ctx.options[:_K], ctx.options[-2], ctx.options[-1]
        return _library_jvp(lambda a, b, g: _grad_generic(a, b, g, tables, on, power, eps), (R, Fr, gv),
                            tuple(torch.zeros_like(x) if t is None else t
                                  for x, t in ((R, t_rot), (Fr, t_frames), (gv, t_gv))))


class _LossFn(torch.autograd.Function):
    """``torchconn::frame_loss`` for eager calls, for the ``torch.func`` transforms.

    The autograd that ``register_autograd`` generates has no ``setup_context``, which
    ``torch.func.grad`` / ``jacrev`` / ``hessian`` refuse, and no forward mode (``jvp`` would
    silently see a constant). This Function calls the same ops (forward: the op, C on the CPU;
    backward: the backward op, reusing the forward's gradient; its backward and both ``jvp`` =
    ``torch.func`` of :func:`terms_generic`; vmap generated, reaching the ops' vmap rules).
    Under ``torch.compile`` the op is called directly (its registered autograd applies).
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(*args):
        return _frame_loss(*args)

    @staticmethod
    def setup_context(ctx, inputs, output):
        _, gR, gF, reg = output
        ctx.mark_non_differentiable(gR, gF, reg)
        with_grad = inputs[-1]
        ctx.save_for_backward(*inputs[:_N_TABLES], gR if with_grad else None, gF if with_grad else None)
        ctx.save_for_forward(*inputs[:_N_TABLES])
        ctx.options = _bwd_options(inputs[_N_TABLES:-1])

    @staticmethod
    def backward(ctx, grad_values, _grad_rot, _grad_frames, _grad_reg):
        *tables, saved_rot, saved_frames = ctx.saved_tensors
        n_none = _N_TABLES - 2 + _N_OPTIONS_BWD + 2  # tables, options (with regular), with_grad
        if not torch.is_grad_enabled():
            # first order and the incoming weights are the loss weights (out["total"].backward()):
            # the forward's gradient itself, without the copy an op output would need
            s = _reuse_scale(grad_values, ctx.options, saved_rot)
            if s is not None and bool((s == 1.0).all()):
                return saved_rot, saved_frames, *([None] * n_none)
        dR, dF = _BackwardFn.apply(*tables, grad_values, saved_rot, saved_frames, *ctx.options)
        return dR, dF, *([None] * n_none)

    @staticmethod
    def jvp(ctx, t_rot, t_frames, *_):
        R, Fr, *tables = ctx.saved_tensors
        on, power, eps = ctx.options[:_K], ctx.options[-2], ctx.options[-1]
        t = _library_jvp(lambda a, b: _T.terms(a, b, *tables, on, power, eps),
                         (R, Fr), (torch.zeros_like(R) if t_rot is None else t_rot,
                                   torch.zeros_like(Fr) if t_frames is None else t_frames))
        return t, None, None, None


# ----------------------------------------------------------------------------- public functions

@traced_constant
def mesh_tables(mesh, dtype: torch.dtype, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(edges (E, 2) int64, face_edges (F, 3) int64, edge_vec (E, 3), face_area (F,))`` of ``mesh``.

    ``face_edges`` = canonical edges ``ab, bc, ac`` of each sorted face ``[a<b<c]``,
    ``edge_vec = v_j - v_i`` and the face areas in ``dtype`` (formed in float64), on ``device``.
    Built once per mesh, dtype and device (``mesh.require``); immutable. While ``torch.compile``
    traces, built (or found) on the real mesh at trace time and passed to the graph as
    constants (:func:`torchconn.ops._cache.traced_constant`).
    """
    dev = torch.device(device)

    def build(m):
        e = m.edges.to(torch.int64)
        verts = m.vertices.to(torch.float64)
        p = verts[m.faces]
        area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)
        vec = verts.index_select(0, e[:, 1]) - verts.index_select(0, e[:, 0])
        fidx = m.face_edges.to(torch.int64)[:, [2, 0, 1]]
        return (e.to(dev).contiguous(), fidx.to(dev).contiguous(), vec.to(dev, dtype).contiguous(),
                area.to(dev, dtype).contiguous())

    return _require(mesh, f"frames.kernels.frame_loss.tables.{dtype}.{dev}", build)


def call(edge_rot: torch.Tensor, frames: torch.Tensor, mesh, group: torch.Tensor, weights: Mapping[str, float],
         smooth_power: float, smooth_eps: float, regular: bool = False) -> dict[str, torch.Tensor]:
    """The op ``torchconn::frame_loss`` on ``(edge_rot (*B, E, 3, 3), frames (*B, V, 3, 3))``
    (batch shapes broadcast), whichever kernel serves: ``{term: (*B)}`` for the terms of
    :data:`COMPILED_TERMS` with non-zero weight, plus ``"face_regular" (*B, F)`` bool with
    ``regular``. Differentiable to any order. ``group`` as in :func:`frame_loss_terms`; shapes are
    not checked (:func:`frame_loss_terms` does)."""
    batch = torch.broadcast_shapes(edge_rot.shape[:-3], frames.shape[:-3])
    edge_rot = edge_rot.expand(*batch, *edge_rot.shape[-3:])
    frames = frames.expand(*batch, *frames.shape[-3:])
    on = [bool(weights.get(k, 0.0)) for k in COMPILED_TERMS]
    w = [float(weights.get(k, 0.0)) for k in COMPILED_TERMS]
    with_grad = torch.is_grad_enabled() and (edge_rot.requires_grad or frames.requires_grad)
    tables = mesh_tables(mesh, edge_rot.dtype, edge_rot.device)
    args = (edge_rot, frames, *tables, group.to(edge_rot.dtype).to(edge_rot.device), *on, bool(regular), *w,
            float(smooth_power), float(smooth_eps), with_grad)
    vals, _, _, reg = _frame_loss(*args) if torch.compiler.is_compiling() else _LossFn.apply(*args)
    out = {k: vals[..., b] for b, k in enumerate(COMPILED_TERMS) if on[b]}
    if regular:
        out["face_regular"] = reg
    return out


def frame_loss_terms(edge_rot: torch.Tensor, frames: torch.Tensor, mesh, group: torch.Tensor,
                     weights: Mapping[str, float], smooth_power: float, smooth_eps: float, regular: bool = False
                     ) -> dict[str, torch.Tensor] | None:
    """The fast path of :class:`~torchconn.frames.loss.FrameFieldLoss`: the terms of
    :data:`COMPILED_TERMS` with non-zero weight by the compiled kernel of ``torchconn::frame_loss``.

    Args:
        edge_rot: ``(*B, E, 3, 3)`` ``R_ij`` of the canonical edges of ``mesh``.
        frames: ``(*B, V, 3, 3)`` (columns = axes); batch shapes broadcast.
        mesh: a mesh with sorted triangles (``TetMesh`` or its ``nn.MeshBuffers``).
        group: ``(24, 3, 3)`` the octahedral group in the order of
            :func:`torchconn.frames.octahedral.group` (the C kernel checks its written-out scores
            against it and raises ``RuntimeError`` on a mismatch).
        weights: term name -> weight; terms of weight 0 are not computed.
        smooth_power, smooth_eps: ``rho`` of the ``smooth`` and ``tie`` terms.
        regular: also return ``"face_regular" (*B, F)`` bool, the faces whose holonomy is nearest
            the identity of O (no gradient).

    Returns:
        ``{term: (*B) tensor}``, differentiable to any order (first order by the C sweep), or
        ``None`` where the compiled kernel does not serve (the caller then evaluates its modules,
        which compute the same terms): no such term; a mesh without sorted triangles; other
        shapes; not the CPU, not float32/float64 of one dtype, a ``torch.func`` transform's
        tensors, the switch :func:`torchconn.ops.compiled` off or no C compiler (while
        ``torch.compile`` traces: the op is put into the graph for CPU inputs with the switch on,
        and its CPU kernel chooses at runtime). No data-dependent Python control flow.
    """
    if not any(weights.get(k, 0.0) for k in COMPILED_TERMS):
        return None
    if not (_sorted_triangles(mesh) and edge_rot.dim() >= 3 and frames.dim() >= 3
            and tuple(edge_rot.shape[-2:]) == (3, 3) and tuple(frames.shape[-2:]) == (3, 3)
            and edge_rot.shape[-3] == mesh.edges.shape[0] and frames.shape[-3] == mesh.vertices.shape[0]
            and edge_rot.is_floating_point() and frames.dtype == edge_rot.dtype
            and frames.device == edge_rot.device):
        return None
    if torch.compiler.is_compiling():
        serves = edge_rot.device.type == "cpu" and compiled_enabled()
    else:
        serves = can_use_compiled("frame_loss", edge_rot, frames)
    if not serves:
        return None
    return call(edge_rot, frames, mesh, group, weights, smooth_power, smooth_eps, regular)
