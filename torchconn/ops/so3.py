"""SO(3) maps as custom ops: ``exp``, ``log``, ``sqrt`` (and ``half_exp``, ``log_checked``).

Each map is a ``torch.library`` custom op with native leading batch dimensions:

* ``torchconn::so3_exp (..., 3) -> (..., 3, 3)``, ``torchconn::so3_log (..., 3, 3) -> (..., 3)``,
  ``torchconn::so3_sqrt (..., 3, 3) -> (..., 3, 3)``;
* ``torchconn::so3_log_checked(R, atol) -> (ω, n_bad, first)`` (the log and its validation,
  ``n_bad``/``first`` as 0-d int64 tensors; :func:`log_checked` reads them with ``.item()``
  outside the op);
* the backward of each is another custom op, ``torchconn::so3_<map>_backward(x, grad)``.

Kernels: the default (every device, every dtype) is the torch code of
:mod:`torchconn.ops._so3_formulas` (unbound components, safe-where branches, no ``nonzero``: no
device sync, nothing data dependent); the CPU kernel runs the compiled loops of
``csrc/so3.c`` (one pass over memory per direction, OpenMP; the same expressions and branches,
values to round-off) when :func:`torchconn.ops.backend.can_use_compiled` allows it (switch
on, float32/float64, library built), else the torch code. The compiled backward is the exact
derivative of the same formulas for *every* 3x3 input, not only along rotations (the tests
compare them on random matrices). Fake kernels give shapes (``meta``, ``torch.compile``,
``torch.export``); the vmap rule is :func:`torchconn.ops._library.leading_vmap`.

Higher derivatives: the backward op's own autograd differentiates the torch formula of that
backward with ``torch.func.vjp``, so ``create_graph=True``, double backward and
Hessian-vector products are exact on every path, with the C kernel used for first order.

:mod:`torchconn.lie.so3` validates its arguments and calls these ops; its ``log`` calls
:func:`log_checked` (the validation computed inside the compiled log kernel, in the same pass),
while :func:`log` here stays unvalidated.
"""
from __future__ import annotations

from ctypes import POINTER, byref, c_double, c_int, c_long, c_void_p

import torch

from . import _so3_formulas as _f
from . import native as _native
from ._library import jvp as _library_jvp
from ._library import leading_vmap, qualname
from .backend import can_use_compiled
from ..tolerances import get_eps

__all__ = ["exp", "log", "log_checked", "sqrt", "half_exp", "exp_autograd"]

# ----------------------------------------------------------------------------- C signatures

_MAP = [c_void_p, c_void_p, c_long, c_int, c_double]            # (in, out, n, threads, eps)
_BWD = [c_void_p, c_void_p, c_void_p, c_long, c_int, c_double,  # (in, grad_out, grad_in, ...
        c_long, c_long]                                             #  ..., grad_out's two strides)
_SUF = {torch.float32: "f32", torch.float64: "f64"}
#: ``_C[name, dtype]``: the C functions of ``csrc/so3.c`` (declared once; built on first call).
_C = {(f"{m}_{d}", dt): _native.declare("so3", f"so3_{m}_{d}_{suf}", _BWD if d == "bwd" else _MAP)
      for m in ("exp", "log", "sqrt") for d in ("fwd", "bwd") for dt, suf in _SUF.items()}
_C.update({("log_fwd_checked", dt): _native.declare(
    "so3", f"so3_log_fwd_checked_{suf}",
    [c_void_p, c_void_p, c_long, c_int, c_double, c_double, POINTER(c_long)], c_long)
    for dt, suf in _SUF.items()})

_IN = {"exp": 3, "log": 9, "sqrt": 9}   # components per element of the input
_OUT = {"exp": 9, "log": 3, "sqrt": 9}  # ... and of the output


def _c_run(name: str, n: int, width: int, *inputs: torch.Tensor) -> torch.Tensor:
    """``so3_<name>_<f32|f64>(*inputs, out (n, width), n, threads, eps)`` on contiguous inputs."""
    x = inputs[0]
    out = _native.empty(n, width, dtype=x.dtype)
    if n:
        ts = [t.contiguous() for t in inputs]  # kept alive until the call returns
        _C[name, x.dtype](*(_native.ptr(t) for t in ts), _native.ptr(out), n, torch.get_num_threads(),
                          get_eps("small_angle", x.dtype))
    return out


def _map_c(kind: str, x: torch.Tensor) -> torch.Tensor:
    batch = x.shape[:-1] if kind == "exp" else x.shape[:-2]
    n = batch.numel()
    out = _c_run(f"{kind}_fwd", n, _OUT[kind], x.reshape(n, _IN[kind]))
    return out.reshape(*batch, *((3,) if kind == "log" else (3, 3)))


def _bwd_c(kind: str, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The compiled backward; ``g`` is read through its strides (the gradient of a ``sum`` is a
    broadcast view: no ``(n, 9)`` copy of it)."""
    n = x.numel() // _IN[kind]
    xs = x.reshape(n, _IN[kind]).contiguous()
    gs = g.reshape(n, _OUT[kind])  # a view where one exists; kept alive until the call returns
    gx = _native.empty(n, _IN[kind], dtype=x.dtype)
    if n:
        _C[f"{kind}_bwd", x.dtype](_native.ptr(xs), c_void_p(gs.data_ptr()), _native.ptr(gx), n,
                                   torch.get_num_threads(), get_eps("small_angle", x.dtype), *gs.stride())
    return gx.reshape(x.shape)


_FWD = {"exp": _f.exp, "log": _f.log, "sqrt": _f.sqrt}
_BWD_F = {"exp": _f.exp_bwd, "log": _f.log_bwd, "sqrt": _f.sqrt_bwd}


def _out_shape(kind: str, x: torch.Tensor):
    return (*x.shape, 3) if kind == "exp" else (*x.shape[:-2], 3) if kind == "log" else x.shape


def _register(kind: str):
    """Declare ``torchconn::so3_<kind>`` and ``torchconn::so3_<kind>_backward`` (see module doc)."""
    fwd_f, bwd_f = _FWD[kind], _BWD_F[kind]

    # the generic kernels return contiguous tensors, as the fake kernels say (inductor checks the
    # strides of an op's outputs against its fake kernel; the formulas can return transposed ones)
    @torch.library.custom_op(qualname(f"so3_{kind}_backward"), mutates_args=())
    def bwd_op(x: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
        return bwd_f(x, grad).contiguous()

    @bwd_op.register_kernel("cpu")
    def _(x, grad):
        if can_use_compiled("so3", x, grad):
            return _bwd_c(kind, x, grad)
        return bwd_f(x, grad).contiguous()

    @bwd_op.register_fake
    def _(x, grad):
        return torch.empty_like(x, memory_format=torch.contiguous_format)

    def bwd_setup(ctx, inputs, output):
        ctx.save_for_backward(*inputs)

    def bwd_backward(ctx, gg):
        x, grad = ctx.saved_tensors
        _, vjp = torch.func.vjp(bwd_f, x, grad)
        return vjp(gg)

    bwd_op.register_autograd(bwd_backward, setup_context=bwd_setup)
    bwd_op.register_vmap(leading_vmap(bwd_op, f"so3_{kind}_backward", batched=(0, 1)))

    @torch.library.custom_op(qualname(f"so3_{kind}"), mutates_args=())
    def op(x: torch.Tensor) -> torch.Tensor:
        return fwd_f(x).contiguous()

    @op.register_kernel("cpu")
    def _(x):
        if can_use_compiled("so3", x):
            return _map_c(kind, x)
        return fwd_f(x).contiguous()

    @op.register_fake
    def _(x):
        return x.new_empty(_out_shape(kind, x))

    def setup(ctx, inputs, output):
        ctx.save_for_backward(inputs[0])

    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return bwd_op(x, grad)

    op.register_autograd(backward, setup_context=setup)
    op.register_vmap(leading_vmap(op, f"so3_{kind}", batched=(0,)))
    return op, bwd_op


_so3_exp, _so3_exp_backward = _register("exp")
_so3_log, _so3_log_backward = _register("log")
_so3_sqrt, _so3_sqrt_backward = _register("sqrt")


def _func_wrapper(op, bwd_op, fwd_f, bwd_f, name: str):
    """An ``autograd.Function`` around ``op`` for the ``torch.func`` transforms.

    ``register_autograd`` generates an ``autograd.Function`` without ``setup_context``, which
    ``torch.func.grad`` / ``jacrev`` / ``hessian`` refuse (pytorch/pytorch#168393, #179652).
    Eager calls therefore go through this Function: forward = the op, backward = the backward
    op (C on CPU), its backward and both ``jvp`` = ``torch.func`` of the torch formulas, vmap
    generated (it reaches the ops' vmap rules). Under ``torch.compile`` the public functions
    call the op itself (dynamo does not trace a custom ``jvp``; the op's own autograd applies).
    """

    class Backward(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(x, grad):
            return bwd_op(x, grad)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(*inputs)
            ctx.save_for_forward(*inputs)

        @staticmethod
        def backward(ctx, gg):
            x, grad = ctx.saved_tensors
            return torch.func.vjp(bwd_f, x, grad)[1](gg)

        @staticmethod
        def jvp(ctx, tx, tg):
            x, grad = ctx.saved_tensors
            return _library_jvp(bwd_f, (x, grad), (tx, tg))

    class Map(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(x):
            return op(x)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(inputs[0])
            ctx.save_for_forward(inputs[0])

        @staticmethod
        def backward(ctx, grad):
            (x,) = ctx.saved_tensors
            return Backward.apply(x, grad)

        @staticmethod
        def jvp(ctx, tx):
            (x,) = ctx.saved_tensors
            return _library_jvp(fwd_f, (x,), (tx,))


    def call(x: torch.Tensor) -> torch.Tensor:
        return op(x) if torch.compiler.is_compiling() else Map.apply(x)

    return call


_exp_call = _func_wrapper(_so3_exp, _so3_exp_backward, _f.exp, _f.exp_bwd, "exp")
_log_call = _func_wrapper(_so3_log, _so3_log_backward, _f.log, _f.log_bwd, "log")
_sqrt_call = _func_wrapper(_so3_sqrt, _so3_sqrt_backward, _f.sqrt, _f.sqrt_bwd, "sqrt")


# ----------------------------------------------------------------------------- log_checked

def _log_checked_generic(R: torch.Tensor, atol: float):
    w = _f.log(R)
    bad = _f.rotation_flags(R, atol)[0]
    n_bad = bad.sum()
    first = torch.where(n_bad > 0, bad.to(torch.uint8).argmax() if bad.numel() else n_bad, -1)
    return w, n_bad.to(torch.int64), first.to(torch.int64)


@torch.library.custom_op(qualname("so3_log_checked"), mutates_args=())
def _so3_log_checked(R: torch.Tensor, atol: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return _log_checked_generic(R, atol)


@_so3_log_checked.register_kernel("cpu")
def _(R, atol):
    if not can_use_compiled("so3", R):
        return _log_checked_generic(R, atol)
    batch = R.shape[:-2]
    n = batch.numel()
    w = torch.empty((n, 3), dtype=R.dtype)
    first, n_bad = c_long(-1), 0
    if n:
        src = R.reshape(n, 9).contiguous()  # kept alive until the call returns
        n_bad = int(_C["log_fwd_checked", R.dtype](
            _native.ptr(src), _native.ptr(w), n, torch.get_num_threads(),
            get_eps("small_angle", R.dtype), atol, byref(first)))
    return (w.reshape(*batch, 3), torch.tensor(n_bad, dtype=torch.int64),
            torch.tensor(first.value if n_bad else -1, dtype=torch.int64))


@_so3_log_checked.register_fake
def _(R, atol):
    return R.new_empty((*R.shape[:-2], 3)), R.new_empty((), dtype=torch.int64), R.new_empty((), dtype=torch.int64)


def _log_checked_setup(ctx, inputs, output):
    ctx.save_for_backward(inputs[0])


def _log_checked_backward(ctx, gw, _g_n, _g_first):
    (R,) = ctx.saved_tensors
    return _so3_log_backward(R, gw), None


_so3_log_checked.register_autograd(_log_checked_backward, setup_context=_log_checked_setup)


# ----------------------------------------------------------------------------- public functions

def _check(x: torch.Tensor, fn: str, mat: bool) -> None:
    if mat and (x.dim() < 2 or x.shape[-2:] != (3, 3)):
        raise ValueError(f"{fn} expects a tensor of shape (..., 3, 3), got {tuple(x.shape)}")
    if not mat and (x.dim() < 1 or x.shape[-1] != 3):
        raise ValueError(f"{fn} expects a tensor of shape (..., 3), got {tuple(x.shape)}")


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues ``exp(hat(ω)) = I + A K + B K²``: ``omega (..., 3) -> (..., 3, 3)`` (``torchconn::so3_exp``).

    ``A = sin t/t``, ``B = (1 - cos t)/t²``, Taylor series below the dtype's ``small_angle``
    registry threshold (finite value and gradient at ``ω = 0``). Backward in closed form
    (:func:`torchconn.ops._so3_formulas.exp_bwd`, ``omega`` the only saved tensor).
    """
    _check(omega, "exp", False)
    return _exp_call(omega)


def exp_autograd(omega: torch.Tensor) -> torch.Tensor:
    """The same closed form as :func:`exp` in plain torch ops, differentiated by autograd (reference)."""
    return _f.exp(omega)


def half_exp(omega: torch.Tensor) -> torch.Tensor:
    """``√R = exp(ω/2)`` for ``R = exp(ω)``: ``omega (..., 3) -> (..., 3, 3)`` (no logarithm).

    The half transport of a connection given by skew parameters (``ConnectionField``); it is
    the principal root whenever ``|ω| < π`` (docs/conventions.md §1: ``√R_ij = exp(½ ∫ω)``).
    """
    return exp(0.5 * omega)


def log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector of ``R (..., 3, 3)`` -> ``(..., 3)``, ``|ω| ∈ [0, π]`` (``torchconn::so3_log``).

    The branches of :func:`torchconn.ops._so3_formulas.log_parts` (generic ``atan2(|v|, c)/|v| v``,
    Taylor near 0, the axis from the symmetric part for angles above π/2), evaluated entrywise;
    backward the chain rule of the same expressions. Not validated (see
    :func:`torchconn.lie.so3.check_rotation`, :func:`log_checked`).
    """
    _check(R, "log", True)
    return _log_call(R)


def log_checked(R: torch.Tensor, atol: float) -> tuple[torch.Tensor, int, int]:
    """:func:`log` of ``R (..., 3, 3)`` and its validation: ``(ω (..., 3), n_bad, first)``.

    ``n_bad`` counts the matrices that are not rotations within ``atol``
    (``||Rᵀ R - I||_F > atol``, ``det R < 0`` or a NaN/inf entry; :func:`_rotation_flags`),
    ``first`` is the flat batch index of the first one (``-1`` if none); ``ω`` is exactly
    :func:`log`'s. Compiled: computed inside the log kernel from the nine entries already
    loaded (no second pass over memory). Torch path: one fused elementwise check and a
    reduction. The op ``torchconn::so3_log_checked`` returns the two numbers as tensors; this
    function reads them (``.item()``: **one device synchronization** off the CPU), so call it
    only on eager tensors with data (not under ``torch.compile``, vmap or on ``meta``):
    :func:`torchconn.lie.so3.log` decides that.
    """
    _check(R, "log", True)
    w, n_bad, first = _so3_log_checked(R, float(atol))
    return w, int(n_bad), int(first)


def _rotation_flags(R: torch.Tensor, atol: float):
    """:func:`torchconn.ops._so3_formulas.rotation_flags` (``(bad, e2, det)`` per flat matrix)."""
    return _f.rotation_flags(R, atol)


def sqrt(R: torch.Tensor) -> torch.Tensor:
    """Principal square root of ``R (..., 3, 3)`` -> ``(..., 3, 3)``, equal to ``exp(log(R)/2)`` (``torchconn::so3_sqrt``).

    Quaternion half-angle identity: with ``s = sqrt(1 + tr R) = 2 cos(t/2)``,
    ``√R = ((1 + s) I + R + (R - Rᵀ)/s) / (2 + s)`` (from ``q_½ ∝ (1 + w, u)`` for the unit
    quaternion ``(w, u)`` of ``R``), used where ``tr R > 0`` (angle below 120°, ``s > 1``: no
    cancellation); elsewhere ``exp(log(R)/2)`` (so at angle exactly π the branch follows
    :func:`log`). The torch kernel evaluates both on every entry (safe-where, no ``nonzero``);
    the compiled kernel takes the same two branches per element.
    """
    _check(R, "sqrt", True)
    return _sqrt_call(R)
