"""Matched edge terms of a frame field as a custom op: the objective of the quality paths.

For frames ``F (*B, V, 3, 3)`` (axes as columns), edges ``(E, 2)`` and fixed matchings ``g_e``
given by their index ``match (E,)`` into the octahedral group ``group (24, 3, 3)``
(:func:`torchconn.frames.octahedral.group`, any table of signed permutation matrices)::

    L = sum_e w_e (s_a a_e + s_d d2_e)                                           (*B,)
    d2_e = max(||F_i g_e - F_j||_F^2, 0) = max(6 - 2 <F_i g_e, F_j>, 0)   (rotations)
    a_e = 2 asin(min(sqrt(d2_e + eps^2) / (2 sqrt 2), h_max)),   h_max = 1 - max(1e-12, finfo(dtype).eps)

``d2`` is the matched Dirichlet energy of the edge (Ray et al. 2016, Palmer et al. 2020) and
``a`` the smoothed geodesic angle of the residual rotation ``(F_i g_e)^T F_j`` (for rotations
``||R - I||_F = 2 sqrt 2 sin(angle / 2)``); ``w (E,)`` optional edge weights (``None``: 1).
:func:`torchconn.frames.quality_paths.quality_path` minimizes ``L`` (with ``s_a = 1 / (E a_ref)``,
``s_d = lambda / (E D_ref)``) by L-BFGS.

Ops (``torch.ops.torchconn.*``):

* ``matched_edge_terms(frames, edges, match, group, weight, s_a, s_d, eps) -> (*B,)``;
* ``matched_edge_terms_backward(grad (*B,), frames, edges, match, group, weight, s_a, s_d, eps)
  -> (*B, V, 3, 3)``: ``grad · dL/dF`` with ``dL/dF_i = k_e (-2 F_j g_eᵀ)``,
  ``dL/dF_j = k_e (-2 F_i g_e)``, ``k_e = w_e (s_a / (2 sqrt 2 r_e sqrt(1 - h_e^2)) + s_d)``
  (``r = sqrt(d2 + eps^2)``, ``h = r / (2 sqrt 2)``; the clamps are not differentiated: this is
  the derivative of ``L`` wherever neither clamp is active, i.e. at every field a path meets).
  Its own autograd differentiates the generic backward formula (``torch.func.vjp``), so double
  backward and Hessian-vector products are exact.

Kernels: generic = the formulas in torch operations (gathers for the signed permutations,
``index_add`` for the scatter; every device and dtype); CPU = ``csrc/edge_terms.c`` when
:func:`~torchconn.ops.backend.can_use_compiled` allows (one sweep per pass, no ``(E, 3, 3)``
intermediates, per-thread scatter buffers), else the generic code. Fake kernels for
``torch.compile``/``export`` and vmap rules (batch = leading dims of ``frames``/``grad``).

Measured (``python -m benchmarks.ops_kernels --rows edge_terms --dtype float64``, and on the
1M-tet HexMe mesh ``i02c_m2@lmax=0.14``: 183,517 vertices, 1.22M edges, float64, 2 threads):
forward + backward 0.052 s compiled against 0.70 s generic; the quality paths of that mesh from
its SH field (:func:`torchconn.frames.quality_paths.quality_path`, 24 L-BFGS rounds) 310 s -> 106 s.
"""
from __future__ import annotations

import ctypes
from pathlib import Path
import math
from typing import Optional

import torch

from ...ops import native as _native
from ...ops._library import jvp as _library_jvp
from ...ops._library import leading_vmap, qualname
from ...ops.backend import can_use_compiled

__all__ = ["matched_edge_terms"]

_C0 = 1.0 / (2.0 * math.sqrt(2.0))

_vp, _long, _int, _dbl = ctypes.c_void_p, ctypes.c_long, ctypes.c_int, ctypes.c_double
# edge_terms_fwd_<T>(B, E, V, nt, F, edges, match, group, w, s_a, s_d, eps, h_max, out)
_FWD_ARGS = [_long] * 3 + [_int] + [_vp] * 5 + [_dbl] * 4 + [_vp]
# edge_terms_bwd_<T>(B, E, V, nt, F, edges, match, group, w, s_a, s_d, eps, h_max, grad, gF, work)
_BWD_ARGS = [_long] * 3 + [_int] + [_vp] * 5 + [_dbl] * 4 + [_vp] * 3
_native.register_source("edge_terms", Path(__file__).resolve().parent / "csrc" / "edge_terms.c")
_C_FWD = {torch.float32: _native.declare("edge_terms", "edge_terms_fwd_f32", _FWD_ARGS, _int),
          torch.float64: _native.declare("edge_terms", "edge_terms_fwd_f64", _FWD_ARGS, _int)}
_C_BWD = {torch.float32: _native.declare("edge_terms", "edge_terms_bwd_f32", _BWD_ARGS, _int),
          torch.float64: _native.declare("edge_terms", "edge_terms_bwd_f64", _BWD_ARGS, _int)}
_C_ERRORS = {-1: "group is not a table of signed permutation matrices",
             -3: "an edge index is outside [0, V) or a match index outside [0, 24)"}


# ----------------------------------------------------------------------------- generic formulas

def _h_max(dtype: torch.dtype) -> float:
    """The clamp of ``h`` below 1 (``asin'`` is finite there): ``1 - max(1e-12, eps of dtype)``."""
    return 1.0 - max(1e-12, torch.finfo(dtype).eps)


def _perm_tables(group: torch.Tensor, match: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(index (E, 3, 3), sign (E, 1, 3))`` with ``X @ g_e == X.gather(-1, index) * sign``."""
    k = group.abs().argmax(-2)  # (24, 3): the row of the nonzero entry of each column
    sign = torch.gather(group, -2, k[:, None, :])  # (24, 1, 3)
    return k[:, None, :].expand(-1, 3, -1)[match], sign[match]


def _parts(frames, edges, match, group, eps):
    gi, gs = _perm_tables(group, match)
    A = frames.index_select(-3, edges[:, 0])
    B = frames.index_select(-3, edges[:, 1])
    Ag = A.gather(-1, gi.expand(A.shape)) * gs
    d2 = (6.0 - 2.0 * (Ag * B).sum((-2, -1))).clamp_min(0.0)
    r = torch.sqrt(d2 + eps * eps)
    h = (r * _C0).clamp(max=_h_max(frames.dtype))
    return A, B, Ag, d2, r, h


def _value_generic(frames, edges, match, group, weight, s_a, s_d, eps):
    _, _, _, d2, _, h = _parts(frames, edges, match, group, eps)
    terms = s_a * (2.0 * torch.asin(h)) + s_d * d2
    if weight is not None:
        terms = terms * weight
    return terms.sum(-1)


def _grad_generic(grad, frames, edges, match, group, weight, s_a, s_d, eps):
    _, B, Ag, _, r, h = _parts(frames, edges, match, group, eps)
    k = (-2.0 * grad[..., None]) * (s_a * _C0 / (r * torch.sqrt(1.0 - h * h)) + s_d)
    if weight is not None:
        k = k * weight
    k = k[..., None, None]
    gti, gts = _perm_tables(group.transpose(-1, -2), match)
    Bgt = B.gather(-1, gti.expand(B.shape)) * gts  # F_j g^T
    gF = torch.zeros_like(frames)
    return gF.index_add(-3, edges[:, 0], k * Bgt).index_add(-3, edges[:, 1], k * Ag)


# ----------------------------------------------------------------------------- C kernels

def _c_args(frames, edges, match, group, weight):
    F = frames.contiguous()
    e = edges.contiguous()
    m = match.contiguous()
    g = group.detach().to(torch.float64).contiguous()
    w = weight.contiguous() if weight is not None else None
    V, E = F.shape[-3], e.shape[0]
    Bn = math.prod(F.shape[:-3])
    return F, e, m, g, w, int(Bn), int(E), int(V)


def _check_rc(rc: int, name: str) -> None:
    if rc != 0:
        raise ValueError(f"torchconn::{name}: {_C_ERRORS.get(rc, f'kernel error {rc}')}")


def _value_c(frames, edges, match, group, weight, s_a, s_d, eps):
    F, e, m, g, w, Bn, E, V = _c_args(frames, edges, match, group, weight)
    out = torch.empty(Bn, dtype=torch.float64)
    rc = _C_FWD[F.dtype](Bn, E, V, torch.get_num_threads(), _native.ptr(F), _native.ptr(e), _native.ptr(m),
                         _native.ptr(g), _native.ptr(w) if w is not None else None, float(s_a), float(s_d),
                         float(eps), _h_max(F.dtype), _native.ptr(out))
    _check_rc(rc, "matched_edge_terms")
    return out.to(F.dtype).reshape(F.shape[:-3])


def _grad_c(grad, frames, edges, match, group, weight, s_a, s_d, eps):
    F, e, m, g, w, Bn, E, V = _c_args(frames, edges, match, group, weight)
    gd = grad.detach().to(torch.float64).reshape(-1).contiguous()
    nt = torch.get_num_threads()
    gF = _native.empty(*F.shape, dtype=F.dtype)
    work = torch.empty(max(nt - 1, 0) * 9 * V, dtype=F.dtype)
    rc = _C_BWD[F.dtype](Bn, E, V, nt, _native.ptr(F), _native.ptr(e), _native.ptr(m), _native.ptr(g),
                         _native.ptr(w) if w is not None else None, float(s_a), float(s_d), float(eps),
                         _h_max(F.dtype), _native.ptr(gd), _native.ptr(gF), _native.ptr(work) if work.numel() else None)
    _check_rc(rc, "matched_edge_terms_backward")
    return gF


def _use_c(frames, edges, match, group, weight, *extra):
    ts = [frames, group, *extra] + ([weight] if weight is not None else [])
    return (edges.device.type == "cpu" and match.device.type == "cpu" and edges.dtype == torch.int64
            and match.dtype == torch.int64 and can_use_compiled("edge_terms", *ts))


# ----------------------------------------------------------------------------- backward op

@torch.library.custom_op(qualname("matched_edge_terms_backward"), mutates_args=())
def _edge_terms_backward(grad: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, match: torch.Tensor,
                         group: torch.Tensor, weight: Optional[torch.Tensor], s_a: float, s_d: float,
                         eps: float) -> torch.Tensor:
    return _grad_generic(grad, frames, edges, match, group, weight, s_a, s_d, eps)


@_edge_terms_backward.register_kernel("cpu")
def _(grad, frames, edges, match, group, weight, s_a, s_d, eps):
    if _use_c(frames, edges, match, group, weight, grad):
        return _grad_c(grad, frames, edges, match, group, weight, s_a, s_d, eps)
    return _grad_generic(grad, frames, edges, match, group, weight, s_a, s_d, eps)


@_edge_terms_backward.register_fake
def _(grad, frames, edges, match, group, weight, s_a, s_d, eps):
    return torch.empty_like(frames, memory_format=torch.contiguous_format)


def _bwd_setup(ctx, inputs, output):
    grad, frames, edges, match, group, weight, s_a, s_d, eps = inputs
    ctx.save_for_backward(grad, frames, edges, match, group, weight)
    ctx.consts = (s_a, s_d, eps)


def _bwd_backward(ctx, g_out):
    grad, frames, edges, match, group, weight = ctx.saved_tensors
    s_a, s_d, eps = ctx.consts
    f = lambda gr, F: _grad_generic(gr, F, edges, match, group, weight, s_a, s_d, eps)  # noqa: E731
    _, vjp = torch.func.vjp(f, grad, frames)
    g_grad, g_frames = vjp(g_out)
    return g_grad, g_frames, None, None, None, None, None, None, None


_edge_terms_backward.register_autograd(_bwd_backward, setup_context=_bwd_setup)
_edge_terms_backward.register_vmap(leading_vmap(_edge_terms_backward, "matched_edge_terms_backward",
                                                batched=(0, 1)))


# ----------------------------------------------------------------------------- forward op

@torch.library.custom_op(qualname("matched_edge_terms"), mutates_args=())
def _edge_terms(frames: torch.Tensor, edges: torch.Tensor, match: torch.Tensor, group: torch.Tensor,
                weight: Optional[torch.Tensor], s_a: float, s_d: float, eps: float) -> torch.Tensor:
    return _value_generic(frames, edges, match, group, weight, s_a, s_d, eps)


@_edge_terms.register_kernel("cpu")
def _(frames, edges, match, group, weight, s_a, s_d, eps):
    if _use_c(frames, edges, match, group, weight):
        return _value_c(frames, edges, match, group, weight, s_a, s_d, eps)
    return _value_generic(frames, edges, match, group, weight, s_a, s_d, eps)


@_edge_terms.register_fake
def _(frames, edges, match, group, weight, s_a, s_d, eps):
    return frames.new_empty(frames.shape[:-3])


def _fwd_setup(ctx, inputs, output):
    frames, edges, match, group, weight, s_a, s_d, eps = inputs
    ctx.save_for_backward(frames, edges, match, group, weight)
    ctx.consts = (s_a, s_d, eps)


def _fwd_backward(ctx, grad):
    frames, edges, match, group, weight = ctx.saved_tensors
    return (_edge_terms_backward(grad, frames, edges, match, group, weight, *ctx.consts),
            None, None, None, None, None, None, None)


_edge_terms.register_autograd(_fwd_backward, setup_context=_fwd_setup)
_edge_terms.register_vmap(leading_vmap(_edge_terms, "matched_edge_terms", batched=(0,)))


class _EdgeTermsFn(torch.autograd.Function):
    """The op for the ``torch.func`` transforms (``setup_context`` and ``jvp``; see
    :class:`torchconn.ops.curvature._CurvatureFn`)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(frames, edges, match, group, weight, s_a, s_d, eps):
        return _edge_terms(frames, edges, match, group, weight, s_a, s_d, eps)

    @staticmethod
    def setup_context(ctx, inputs, output):
        frames, edges, match, group, weight, s_a, s_d, eps = inputs
        ctx.save_for_backward(frames, edges, match, group, weight)
        ctx.save_for_forward(frames, edges, match, group, weight)
        ctx.consts = (s_a, s_d, eps)

    @staticmethod
    def backward(ctx, grad):
        frames, edges, match, group, weight = ctx.saved_tensors
        gF = _EdgeTermsBwdFn.apply(grad, frames, edges, match, group, weight, *ctx.consts)
        return gF, None, None, None, None, None, None, None

    @staticmethod
    def jvp(ctx, t_frames, *_):
        frames, edges, match, group, weight = ctx.saved_tensors
        f = lambda F: _value_generic(F, edges, match, group, weight, *ctx.consts)  # noqa: E731
        return _library_jvp(f, (frames,), (t_frames,))


class _EdgeTermsBwdFn(torch.autograd.Function):
    generate_vmap_rule = True

    @staticmethod
    def forward(grad, frames, edges, match, group, weight, s_a, s_d, eps):
        return _edge_terms_backward(grad, frames, edges, match, group, weight, s_a, s_d, eps)

    @staticmethod
    def setup_context(ctx, inputs, output):
        grad, frames, edges, match, group, weight, s_a, s_d, eps = inputs
        ctx.save_for_backward(grad, frames, edges, match, group, weight)
        ctx.save_for_forward(grad, frames, edges, match, group, weight)
        ctx.consts = (s_a, s_d, eps)

    @staticmethod
    def backward(ctx, g_out):
        return _bwd_backward(ctx, g_out)

    @staticmethod
    def jvp(ctx, t_grad, t_frames, *_):
        grad, frames, edges, match, group, weight = ctx.saved_tensors
        f = lambda gr, F: _grad_generic(gr, F, edges, match, group, weight, *ctx.consts)  # noqa: E731
        z = torch.zeros_like
        return _library_jvp(f, (grad, frames), (z(grad) if t_grad is None else t_grad,
                                                z(frames) if t_frames is None else t_frames))


def matched_edge_terms(frames: torch.Tensor, edges: torch.Tensor, match: torch.Tensor, group: torch.Tensor,
                       weight: torch.Tensor | None = None, *, s_a: float = 1.0, s_d: float = 0.0,
                       eps: float = 1e-3) -> torch.Tensor:
    """``L = sum_e w_e (s_a a_e + s_d d2_e)`` of ``frames (*B, V, 3, 3)`` (module doc): ``(*B,)``.

    Args:
        frames: ``(*B, V, 3, 3)`` rotations (axes as columns), any leading batch dims.
        edges: ``(E, 2)`` int64 vertex pairs ``(i, j)``.
        match: ``(E,)`` int64 index into ``group`` of each edge's matching ``g_e`` (``F_i g_e ~ F_j``,
            :func:`torchconn.frames.octahedral.match_edges`).
        group: ``(24, 3, 3)`` signed permutation matrices (:func:`torchconn.frames.octahedral.group`),
            dtype of ``frames``.
        weight: ``(E,)`` edge weights or ``None`` (all 1).
        s_a, s_d: weights of the angle and Dirichlet terms; eps: smoothing of the angle (radians).

    Raises:
        ValueError: shapes or dtypes that do not fit (named), an index out of range.
    """
    if not (torch.is_tensor(frames) and frames.dim() >= 3 and frames.shape[-2:] == (3, 3)):
        raise ValueError(f"matched_edge_terms: frames must be (*B, V, 3, 3), got "
                         f"{tuple(frames.shape) if torch.is_tensor(frames) else type(frames).__name__}")
    E = edges.shape[0] if torch.is_tensor(edges) else -1
    if not (torch.is_tensor(edges) and edges.dim() == 2 and edges.shape[1] == 2 and edges.dtype == torch.int64):
        raise ValueError(f"matched_edge_terms: edges must be an (E, 2) int64 tensor, got "
                         f"{tuple(edges.shape) if torch.is_tensor(edges) else type(edges).__name__}")
    if not (torch.is_tensor(match) and tuple(match.shape) == (E,) and match.dtype == torch.int64):
        raise ValueError(f"matched_edge_terms: match must be an ({E},) int64 tensor, got "
                         f"{tuple(match.shape) if torch.is_tensor(match) else type(match).__name__}")
    if not (torch.is_tensor(group) and tuple(group.shape) == (24, 3, 3) and group.dtype == frames.dtype):
        raise ValueError(f"matched_edge_terms: group must be a (24, 3, 3) tensor of dtype {frames.dtype}")
    if weight is not None and not (torch.is_tensor(weight) and tuple(weight.shape) == (E,)
                                   and weight.dtype == frames.dtype):
        raise ValueError(f"matched_edge_terms: weight must be None or an ({E},) tensor of dtype {frames.dtype}")
    args = (frames, edges, match, group, weight, float(s_a), float(s_d), float(eps))
    if torch.compiler.is_compiling():
        return _edge_terms(*args)
    return _EdgeTermsFn.apply(*args)
