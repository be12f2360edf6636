"""Per-tet frames from per-vertex frames, smoothed and differentiable, as a custom op.

``torchconn::smooth_tet_frames(frames (V, 3, 3), a (T,), others (T, 3), g (T, 3, 3, 3), inc_ptr (V + 1),
inc (4T)) -> (Y, M, R)``, each ``(T, 3, 3)``: tet ``t`` with lowest vertex ``a_t``, its other three
vertices ``others_t`` and the matchings ``g_tk`` of the edges ``(a_t, others_tk)`` (``F_a g ~ F_o``)

    ``M_t = (F_a + Σ_k F_{o_k} g_kᵀ) / 4``,  ``R_t = polar(F_aᵀ M_t)``,  ``Y_t = F_a R_t``

(the rule of :func:`torchconn.frames.octahedral.tet_frames`, with the polar factor by a scaled
Newton iteration instead of an SVD: smooth where the four relabeled frames agree, e.g. a constant
field; :func:`torchconn.hexmesh.energy.smooth_tet_frames`). ``M`` and ``R`` are outputs for the
backward (non-differentiable). ``a``, ``others``, ``g`` are the relabeling of
:func:`torchconn.frames.octahedral.tet_relabeling`; ``inc_ptr``/``inc`` the per-vertex CSR table of the
incident ``(tet, slot)`` pairs (``4 t + slot``, slot 0 the lowest vertex, ``k + 1`` the others;
:func:`vertex_incidence`). Both are built once per mesh and matchings.

Kernels: generic = the formulas below in torch operations (every device and dtype); CPU =
``csrc/tet_frames.c`` when :func:`~torchconn.ops.backend.can_use_compiled` allows: one pass over the
tets forward (the Newton iteration per matrix), and for the first-order backward a tet pass (the
closed-form derivative of the polar factor) and a race-free pass over the vertices through the CSR
table. A tet whose ``F_aᵀ M`` has ``det <= 0`` raises ``ValueError`` (its four frames disagree by more
than a rotation can smooth). Fake kernel; autograd: first order by the C backward, higher orders and
forward mode through ``torch.func`` of the generic formula (exact: :class:`_Polar` has a closed-form
derivative written in torch operations). No vmap rule (no batch dimensions).
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import torch

from ...lie import so3
from ...ops import native as _native
from ...ops._library import jvp as _library_jvp
from ...ops._library import eager_function, qualname
from ...ops.backend import can_use_compiled

__all__ = ["smooth_tet_frames_op", "vertex_incidence", "polar"]

_POLAR_ITERS = 12
_vp, _long, _int = ctypes.c_void_p, ctypes.c_long, ctypes.c_int
_native.register_source("tet_frames", Path(__file__).resolve().parent / "csrc" / "tet_frames.c")
_C_FWD = {dt: _native.declare("tet_frames", f"stf_fwd_{s}", [_long, _long, _int] + [_vp] * 4 + [ct, _int] + [_vp] * 4,
                              _long)
          for dt, s, ct in ((torch.float32, "f32", ctypes.c_float), (torch.float64, "f64", ctypes.c_double))}
_C_BWD = {dt: _native.declare("tet_frames", f"stf_bwd_{s}", [_long, _long, _int] + [_vp] * 10, _int)
          for dt, s in ((torch.float32, "f32"), (torch.float64, "f64"))}


def polar(X: torch.Tensor) -> torch.Tensor:
    """Orthogonal polar factor ``R`` of ``X (..., 3, 3)``, ``det X > 0``, differentiable to every order.

    The value by :func:`_polar_newton` (no autograd graph through its iterations); the derivative in
    closed form (:class:`_Polar`): with ``S = R^T X`` (symmetric positive definite),
    ``dR = R [w]_x``, ``w = (tr(S) I - S)^{-1} v(R^T dX)``, ``v(A) = (A_32 - A_23, A_13 - A_31, A_21 - A_12)``
    (the skew part of ``R^T dX = [w]_x S + dS`` is ``[(tr(S) I - S) w]_x / 2``); so the VJP of ``G`` is
    ``R [(tr(S) I - S)^{-1} v(R^T G)]_x``, written in torch operations of ``X`` and the output ``R``,
    so that its own derivative is exact.
    """
    return _Polar.apply(X)


class _Polar(torch.autograd.Function):
    """The polar factor with its closed-form derivative (:func:`_polar`)."""

    @staticmethod
    def forward(X):
        return _polar_newton(X)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(inputs[0], output)
        ctx.save_for_forward(inputs[0], output)

    @staticmethod
    def backward(ctx, G):
        X, R = ctx.saved_tensors
        return _polar_derivative(X, R, G)

    @staticmethod
    def jvp(ctx, dX):
        """``dR = R [w]_x``, ``w = (tr(S) I - S)^{-1} v(R^T dX)``: the same map as the VJP (it is self-adjoint)."""
        X, R = ctx.saved_tensors
        return _polar_derivative(X, R, dX)


def _polar_derivative(X: torch.Tensor, R: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """``R [(tr(S) I - S)^{-1} v(R^T G)]_x`` with ``S = sym(R^T X)`` (:func:`polar`), in torch operations."""
    Rt = R.transpose(-1, -2)
    S = Rt @ X
    S = 0.5 * (S + S.transpose(-1, -2))
    P = torch.diagonal(S, dim1=-2, dim2=-1).sum(-1)[..., None, None] * torch.eye(3, dtype=S.dtype,
                                                                                   device=S.device) - S
    w = torch.linalg.solve(P, 2.0 * so3.vee(Rt @ G).unsqueeze(-1)).squeeze(-1)  # 2 vee(A) = v(A)
    return R @ so3.hat(w)


def _polar_newton(X: torch.Tensor, max_iters: int = _POLAR_ITERS) -> torch.Tensor:
    """Orthogonal polar factor of ``X (..., 3, 3)`` with ``det X > 0`` by the scaled Newton iteration
    ``X <- (z X + (z X)^{-T}) / 2``, ``z = sqrt(|X^{-1}|_F / |X|_F)`` (Higham).

    ``X^{-T}`` is the cofactor matrix over the determinant, written out entry by entry (the nine
    entries as rows of a ``(9, N)`` array: elementwise and vectorized). Smooth where ``X`` is
    invertible, ``X = I`` included (the SVD route of ``so3.project_to_rotation`` has no derivative
    at repeated singular values). The iteration converges quadratically: it stops one step after
    the largest change falls below ``sqrt(eps)`` (so the last step leaves an error at round-off),
    after at most ``max_iters`` steps (one host sync per step).
    """
    shape = X.shape
    x = X.reshape(-1, 9).T.contiguous()  # (9, N): entries a b c / d e f / g h i, each row contiguous
    tol = torch.finfo(X.dtype).eps ** 0.5
    last = False
    for _ in range(max_iters):
        a, b, c, d, e, f, g, h, i = x.unbind(0)
        cof = torch.stack([e * i - f * h, f * g - d * i, d * h - e * g,
                           c * h - b * i, a * i - c * g, b * g - a * h,
                           b * f - c * e, c * d - a * f, a * e - b * d])
        inv_t = cof / (a * cof[0] + b * cof[1] + c * cof[2])  # X^{-T}
        z = (inv_t.square().sum(0) / x.square().sum(0)) ** 0.25
        x_new = 0.5 * (z * x + inv_t / z)
        if last:
            x = x_new
            break
        last = bool((x_new - x).abs().max() < tol) if x.numel() else True
        x = x_new
    return x.T.reshape(shape)


def vertex_incidence(a: torch.Tensor, others: torch.Tensor, n_vertices: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(inc_ptr (V + 1), inc (4T))``: the per-vertex CSR table of the incident ``(tet, slot)`` pairs,
    ``4 t + slot`` in increasing order, of the lowest vertices ``a (T,)`` (slot 0) and the others
    ``others (T, 3)`` (slots 1-3) of :func:`torchconn.frames.octahedral.tet_relabeling`. Built once per
    mesh (a sort)."""
    owner = torch.cat((a[:, None], others), 1).reshape(-1)  # position 4 t + slot -> vertex
    inc = torch.sort(owner, stable=True).indices
    inc_ptr = torch.zeros(n_vertices + 1, dtype=torch.int64, device=a.device)
    inc_ptr[1:] = torch.cumsum(torch.bincount(owner, minlength=n_vertices), 0)
    return inc_ptr, inc


def _generic(frames: torch.Tensor, a: torch.Tensor, others: torch.Tensor, g: torch.Tensor, check: bool = True):
    """``(Y, M, R)`` in torch operations (differentiable in ``frames``)."""
    Fa = frames[a]
    # sum_v F_v g_av^T (einsum: a batched matmul of 3T tiny matrices is several times slower)
    M = (Fa + torch.einsum("tvij,tvkj->tik", frames[others], g.to(frames.dtype))) / 4.0
    X = Fa.transpose(-1, -2) @ M
    if check:
        Xd = X.detach()
        det = (Xd[..., 0, :] * torch.linalg.cross(Xd[..., 1, :], Xd[..., 2, :])).sum(-1)
        if (det <= 0).any():
            bad = torch.nonzero(det <= 0).flatten()
            _bad(bad.numel(), bad[:5].tolist())
    R = polar(X)
    return Fa @ R, M, R


def _generic_outputs(frames, a, others, g):
    """The generic kernel's outputs: detached, contiguous (the fake kernel's layout)."""
    return tuple(t.detach().clone(memory_format=torch.contiguous_format) for t in _generic(frames, a, others, g))


def _bad(count: int, first: list) -> None:
    raise ValueError(f"smooth_tet_frames: {count} tets (first {first}) average their vertex frames to a matrix "
                     f"with det <= 0: the frames disagree by more than a rotation can smooth")


def _use_c(frames, *index) -> bool:
    return all(t.device.type == "cpu" and t.dtype == torch.int64 for t in index) and can_use_compiled(
        "tet_frames", frames)


@torch.library.custom_op(qualname("smooth_tet_frames"), mutates_args=())
def _op(frames: torch.Tensor, a: torch.Tensor, others: torch.Tensor, g: torch.Tensor, inc_ptr: torch.Tensor,
        inc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``torchconn::smooth_tet_frames`` (module doc; generic kernel)."""
    return _generic_outputs(frames, a, others, g)


@_op.register_kernel("cpu")
def _(frames, a, others, g, inc_ptr, inc):
    if not _use_c(frames, a, others, inc_ptr, inc):
        return _generic_outputs(frames, a, others, g)
    F, aa, oo, gg = frames.contiguous(), a.contiguous(), others.contiguous(), g.to(frames.dtype).contiguous()
    NT, V = int(aa.shape[0]), int(F.shape[0])
    Y, M, R = (torch.empty(NT, 3, 3, dtype=F.dtype) for _ in range(3))
    first = torch.full((1,), -1, dtype=torch.int64)
    tol = torch.finfo(F.dtype).eps ** 0.5
    nbad = _C_FWD[F.dtype](NT, V, torch.get_num_threads(), _native.ptr(F), _native.ptr(aa), _native.ptr(oo),
                           _native.ptr(gg), tol, _POLAR_ITERS, _native.ptr(Y), _native.ptr(M), _native.ptr(R),
                           _native.ptr(first))
    if nbad < 0:
        raise MemoryError("torchconn::smooth_tet_frames: the C kernel could not map its scratch")
    if nbad:
        _bad(nbad, [int(first)])
    return Y, M, R


@_op.register_fake
def _(frames, a, others, g, inc_ptr, inc):
    T = a.shape[0]
    return tuple(frames.new_empty(T, 3, 3) for _ in range(3))


def _backward_c(frames, a, others, g, inc_ptr, inc, M, R, G):
    F = frames.contiguous()
    gF = torch.empty_like(F)
    ts = [a.contiguous(), others.contiguous(), g.to(F.dtype).contiguous(), M.contiguous(), R.contiguous(),
          G.to(F.dtype).contiguous(), inc_ptr.contiguous(), inc.contiguous()]
    rc = _C_BWD[F.dtype](int(a.shape[0]), int(F.shape[0]), torch.get_num_threads(), _native.ptr(F),
                         *(_native.ptr(t) for t in ts), _native.ptr(gF))
    if rc != 0:
        raise MemoryError("torchconn::smooth_tet_frames: the C backward could not map its scratch")
    return gF


def _setup(ctx, inputs, output):
    frames, a, others, g, inc_ptr, inc = inputs
    _, M, R = output
    ctx.mark_non_differentiable(M, R)
    ctx.save_for_backward(frames, a, others, g, inc_ptr, inc, M, R)


def _backward(ctx, gY, _gM, _gR):
    """First order: the C backward (module doc). Under ``create_graph``, or off the C kernel:
    ``torch.func.vjp`` of the generic formula (exact, differentiable)."""
    if gY is None or not ctx.needs_input_grad[0]:
        return (None,) * 6
    frames, a, others, g, inc_ptr, inc, M, R = ctx.saved_tensors
    if not torch.is_grad_enabled() and _use_c(frames, a, others, inc_ptr, inc) and gY.device.type == "cpu":
        return (_backward_c(frames, a, others, g, inc_ptr, inc, M, R, gY),) + (None,) * 5
    _, pullback = torch.func.vjp(lambda f: _generic(f, a, others, g, check=False)[0], frames)
    return pullback(gY) + (None,) * 5


_op.register_autograd(_backward, setup_context=_setup)


def _jvp(ctx, t_frames, *_):
    """Forward mode: the generic formula's, by :func:`~torchconn.ops._library.jvp`."""
    frames, a, others, g = ctx.saved_tensors[:4]
    t = _library_jvp(lambda f: _generic(f, a, others, g, check=False)[0], (frames,), (t_frames,))
    return t, None, None


_Fn = eager_function("SmoothTetFrames", _op, _setup, _backward, _jvp, n_forward=4, vmap=False)


def smooth_tet_frames_op(frames: torch.Tensor, a: torch.Tensor, others: torch.Tensor, g: torch.Tensor,
                         inc_ptr: torch.Tensor, inc: torch.Tensor) -> torch.Tensor:
    """``Y (T, 3, 3)``: the smoothed per-tet frames of ``frames (V, 3, 3)`` with the tables of
    :func:`~torchconn.frames.octahedral.tet_relabeling` and :func:`vertex_incidence` (module doc). Differentiable to any order in ``frames``.

    Raises:
        ValueError: a tet whose averaged frame has ``det <= 0``.
    """
    args = (frames, a, others, g, inc_ptr, inc)
    return (_op(*args) if torch.compiler.is_compiling() else _Fn.apply(*args))[0]
