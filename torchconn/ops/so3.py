"""SO(3) maps as ops: ``exp``, ``log``, ``sqrt`` (and ``half_exp``), each choosing its kernel.

Every map exists twice:

* as torch code on unbound components (any device and dtype, differentiable to any order):
  ``exp``, ``log`` and ``sqrt`` of 3x3 rotations never form ``(..., 3, 3)`` products
  (``K @ K``) or gather columns; ``exp`` has a hand-written backward that keeps only ``omega``;
* as compiled C loops (``csrc/so3.c``: one pass over memory per direction, OpenMP threads;
  same branches and thresholds, values to round-off).

Each op takes the compiled kernel when :func:`torchconn.ops.backend.can_use_compiled` allows
it (switch on, CPU float32/float64, library built, no ``torch.compile`` trace, no vmap), else
the torch code. The C backward is first order: when the backward itself is recorded
(``create_graph``, e.g. ``gradgradcheck`` or ``autograd.functional.jvp``, detected by grad mode
being on inside backward) it is computed by the torch code instead.
:mod:`torchconn.lie.so3` validates its arguments and calls these ops; its ``log`` calls
:func:`log_checked`, which also reports the matrices that are not rotations (computed inside
the compiled log kernel, in the same pass), while :func:`log` here stays unvalidated.
"""
from __future__ import annotations

import ctypes

import torch

from . import native as _native
from .backend import _plain, can_use_compiled
from ..tolerances import get_eps

__all__ = ["exp", "log", "log_checked", "sqrt", "half_exp", "exp_autograd"]


def _c_call(name: str, out_shape, *inputs: torch.Tensor) -> torch.Tensor:
    """Run ``so3_<name>_<f32|f64>(*inputs, out, n, threads, small_angle eps)`` on contiguous copies."""
    x = inputs[0]
    out = torch.empty(out_shape, dtype=x.dtype)
    n = out_shape[0]
    if n:
        fn = _native.function("so3", f"so3_{name}_{'f32' if x.dtype == torch.float32 else 'f64'}",
                              [ctypes.c_void_p] * (len(inputs) + 1) + [ctypes.c_long, ctypes.c_int, ctypes.c_double])
        ts = [t.contiguous() for t in inputs]  # kept alive until the call returns
        fn(*(_native.ptr(t) for t in ts), _native.ptr(out), ctypes.c_long(n),
           ctypes.c_int(torch.get_num_threads()), ctypes.c_double(get_eps("small_angle", x.dtype)))
    return out


class _CompiledMapFn(torch.autograd.Function):
    """One of the C maps ``kind`` in ``exp`` / ``log`` / ``sqrt`` with its C backward (input saved).

    ``x`` is ``(..., 3)`` (exp) or ``(..., 3, 3)``; the batch dims are flattened for C and
    restored. Under ``create_graph`` the backward is the torch one (differentiable).
    """

    @staticmethod
    def forward(x, kind, check=None):
        batch = x.shape[:-1] if kind == "exp" else x.shape[:-2]
        n = batch.numel()
        out_tail = (3,) if kind == "log" else (3, 3)
        flat = x.reshape(n, 3 if kind == "exp" else 9)
        if check is not None:  # log validated in the same pass (_LogCheck receives the result)
            out = _log_fwd_checked_c(flat, check)
        else:
            out = _c_call(f"{kind}_fwd", (n, 3 if kind == "log" else 9), flat)
        return out.reshape(*batch, *out_tail)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.kind = inputs[1]
        ctx.save_for_backward(inputs[0])

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        kind = ctx.kind
        # create_graph (a recorded, differentiable backward) or a batched grad_output
        # (autograd.functional.jacobian(vectorize=True)): the torch formulas
        if torch.is_grad_enabled() or not _plain(g):
            if kind == "exp":
                return _exp_backward(x, g), None, None
            torch_fn = _log_torch if kind == "log" else _sqrt_torch
            with torch.enable_grad():
                out = torch_fn(x)
                (gx,) = torch.autograd.grad(out, x, g, create_graph=True)
            return gx, None, None
        m = 3 if kind == "exp" else 9  # components of x per element
        n = x.numel() // m
        gx = _c_call(f"{kind}_bwd", (n, m), x.reshape(n, m), g.reshape(n, 3 if kind == "log" else 9))
        return gx.reshape(x.shape), None, None


def _compiled_map(x: torch.Tensor, kind: str, check: "_LogCheck | None" = None) -> torch.Tensor:
    if x.requires_grad and torch.is_grad_enabled():
        return _CompiledMapFn.apply(x, kind, check)
    return _CompiledMapFn.forward(x, kind, check)


class _LogCheck:
    """Tolerance in, ``(n_bad, first)`` out: the validation result of one compiled log call."""

    __slots__ = ("atol", "n_bad", "first")

    def __init__(self, atol: float):
        self.atol, self.n_bad, self.first = atol, 0, -1


def _log_fwd_checked_c(flat: torch.Tensor, check: _LogCheck) -> torch.Tensor:
    """``so3_log_fwd_checked_<f32|f64>`` on ``flat (n, 9)``: ω ``(n, 3)``; fills ``check``."""
    n = flat.shape[0]
    out = torch.empty((n, 3), dtype=flat.dtype)
    check.n_bad, check.first = 0, -1
    if n:
        fn = _native.function(
            "so3", f"so3_log_fwd_checked_{'f32' if flat.dtype == torch.float32 else 'f64'}",
            [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_long, ctypes.c_int, ctypes.c_double,
             ctypes.c_double, ctypes.POINTER(ctypes.c_long)], ctypes.c_long)
        src = flat.contiguous()  # kept alive until the call returns
        first = ctypes.c_long(n)
        n_bad = fn(_native.ptr(src), _native.ptr(out), ctypes.c_long(n), ctypes.c_int(torch.get_num_threads()),
                   ctypes.c_double(get_eps("small_angle", flat.dtype)), ctypes.c_double(check.atol),
                   ctypes.byref(first))
        check.n_bad, check.first = int(n_bad), (int(first.value) if n_bad else -1)
    return out


# ----------------------------------------------------------------------------- exp

def _exp_coeffs(t2: torch.Tensor, with_derivatives: bool):
    """``A = sin t / t``, ``B = (1 - cos t)/t²`` and (optionally) ``dA/d(t²)``, ``dB/d(t²)``.

    Taylor series below the dtype's ``small_angle`` threshold (``t² < eps²``); the trigonometric
    branch gets ``t² = 1`` there (safe-where: finite values and gradients in the unused branch).
    ``dA/d(t²) = (t cos t - sin t) / (2 t³)``, ``dB/d(t²) = (t sin t - 2 (1 - cos t)) / (2 t⁴)``.
    """
    eps = get_eps("small_angle", t2.dtype)
    small = t2 < eps * eps
    ts2 = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(ts2)
    s, c = torch.sin(t), torch.cos(t)
    A = torch.where(small, 1.0 - t2 * (1.0 / 6.0 - t2 / 120.0), s / t)
    omc = 1.0 - c
    B = torch.where(small, 0.5 - t2 * (1.0 / 24.0 - t2 / 720.0), omc / ts2)
    if not with_derivatives:
        return A, B
    dA = torch.where(small, -1.0 / 6.0 + t2 * (1.0 / 60.0 - t2 / 1680.0), (t * c - s) / (2.0 * ts2 * t))
    dB = torch.where(small, -1.0 / 24.0 + t2 * (1.0 / 360.0 - t2 / 13440.0),
                     (t * s - 2.0 * omc) / (2.0 * ts2 * ts2))
    return A, B, dA, dB


def _rodrigues(x, y, z, A, B) -> torch.Tensor:
    """``I + A K + B K²`` with ``K = hat(x, y, z)``, entries written out: ``(...) -> (..., 3, 3)``.

    ``K² = w wᵀ - |w|² I``, so the diagonal is ``1 - B (|w|² - w_i²)`` and the off-diagonal
    entries are ``B w_i w_j ∓ A w_k``.
    """
    Bx, By = B * x, B * y
    Ax, Ay, Az = A * x, A * y, A * z
    bxy, bxz, byz = Bx * y, Bx * z, By * z
    xx, yy, zz = x * x, y * y, z * z
    r = torch.stack((
        1.0 - B * (yy + zz), bxy - Az, bxz + Ay,
        bxy + Az, 1.0 - B * (xx + zz), byz - Ax,
        bxz - Ay, byz + Ax, 1.0 - B * (xx + yy),
    ), -1)
    return r.unflatten(-1, (3, 3))


class _ExpFn(torch.autograd.Function):
    """Rodrigues' formula with a closed-form backward (``omega`` is the only saved tensor).

    With ``G = ∂L/∂R`` (3x3), ``g = vee-like (G21 - G12, G02 - G20, G10 - G01)``, ``S = G + Gᵀ``:
    ``∂L/∂ω = A g + B (S ω - 2 tr(G) ω) + 2 A'(ω·g) ω + 2 B'(ωᵀ G ω - |ω|² tr G) ω``
    (``A' = dA/d(t²)``, ``B' = dB/d(t²)``), from ``∂R/∂ω_k = A E_k + B (E_k K + K E_k) + ...``
    with ``E_k K + K E_k = ω e_kᵀ + e_k ωᵀ - 2 ω_k I``. The backward is made of differentiable
    torch ops, so double backward works.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(omega):
        x, y, z = omega.unbind(-1)
        A, B = _exp_coeffs(x * x + y * y + z * z, False)
        return _rodrigues(x, y, z, A, B)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(inputs[0])

    @staticmethod
    def backward(ctx, G):
        (omega,) = ctx.saved_tensors
        return _exp_backward(omega, G)


def _exp_backward(omega: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """``∂L/∂ω`` from ``G = ∂L/∂R`` (formula of :class:`_ExpFn`), in differentiable torch ops."""
    x, y, z = omega.unbind(-1)
    t2 = x * x + y * y + z * z
    A, B, dA, dB = _exp_coeffs(t2, True)
    (g00, g01, g02), (g10, g11, g12), (g20, g21, g22) = (r.unbind(-1) for r in G.unbind(-2))
    gx, gy, gz = g21 - g12, g02 - g20, g10 - g01
    tr = g00 + g11 + g22
    s01, s02, s12 = g01 + g10, g02 + g20, g12 + g21
    Sx = 2.0 * g00 * x + s01 * y + s02 * z
    Sy = s01 * x + 2.0 * g11 * y + s12 * z
    Sz = s02 * x + s12 * y + 2.0 * g22 * z
    wGw = 0.5 * (x * Sx + y * Sy + z * Sz)
    wg = x * gx + y * gy + z * gz
    radial = 2.0 * dA * wg + 2.0 * dB * (wGw - t2 * tr) - 2.0 * B * tr
    return torch.stack((A * gx + B * Sx + radial * x,
                        A * gy + B * Sy + radial * y,
                        A * gz + B * Sz + radial * z), -1)


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues ``exp(hat(ω))``: ``omega (..., 3) -> (..., 3, 3)``, closed-form backward.

    Same value as :func:`exp_autograd` to round-off; finite value and gradient at ``ω = 0``
    (Taylor branch, ``small_angle`` registry threshold). Compiled C or :class:`_ExpFn` (see the
    module doc).
    """
    if omega.dim() < 1 or omega.shape[-1] != 3:
        raise ValueError(f"exp expects a tensor of shape (..., 3), got {tuple(omega.shape)}")
    if can_use_compiled("so3", omega):
        return _compiled_map(omega, "exp")
    return _ExpFn.apply(omega)


def exp_autograd(omega: torch.Tensor) -> torch.Tensor:
    """The same closed form as :func:`exp` differentiated by plain autograd (reference)."""
    x, y, z = omega.unbind(-1)
    A, B = _exp_coeffs(x * x + y * y + z * z, False)
    return _rodrigues(x, y, z, A, B)


def half_exp(omega: torch.Tensor) -> torch.Tensor:
    """``√R = exp(ω/2)`` for ``R = exp(ω)``: ``omega (..., 3) -> (..., 3, 3)`` (no logarithm).

    The half transport of a connection given by skew parameters (``ConnectionField``); it is
    the principal root whenever ``|ω| < π`` (docs/conventions.md §1: ``√R_ij = exp(½ ∫ω)``).
    """
    return exp(0.5 * omega)


# ----------------------------------------------------------------------------- log

def _log_parts(r, eps_small):
    """All branches of the log on unbound components ``r`` (9 tensors): ``(ω, intermediates)``.

    With ``v = vee(R) = sin(t) n`` and ``c = (tr R - 1)/2``: ``ω = f v``, ``f = atan2(|v|, c)/|v|``
    (Taylor ``asin(s)/s`` for tiny ``|v|`` and ``c > 0``); for ``c < 0`` the axis is the column
    ``u`` of ``sym(R) - c I = (1 - c) n nᵀ`` with the largest diagonal entry, ``n = σ u/|u|``
    signed so that ``n·v ≥ 0``, and ``ω = atan2(n·v, c) n``. Every branch is evaluated on all
    entries with a harmless input where it is unused (safe-where): finite values and gradients
    at 0 and at π.
    """
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    vx, vy, vz = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    c = 0.5 * (r00 + r11 + r22 - 1.0)
    s2 = vx * vx + vy * vy + vz * vz
    small = (s2 < eps_small * eps_small) & (c > 0)
    obtuse = c < 0
    generic = ~(small | obtuse)
    one = torch.ones_like(c)
    s_g = torch.sqrt(torch.where(generic, s2, one))
    c_g = torch.where(generic, c, torch.zeros_like(c))
    s2_s = torch.where(small, s2, torch.zeros_like(s2))
    fac = torch.where(small, 1.0 + s2_s * (1.0 / 6.0 + s2_s * (3.0 / 40.0 + s2_s * (5.0 / 112.0))),
                      torch.atan2(s_g, c_g) / s_g)
    # obtuse branch on a rotation by pi about x where unused (diag (1, -1, -1), v = 0, c = -1)
    cp = torch.where(obtuse, c, -one)
    d0 = torch.where(obtuse, r00, one) - cp
    d1 = torch.where(obtuse, r11, -one) - cp
    d2 = torch.where(obtuse, r22, -one) - cp
    o01 = torch.where(obtuse, 0.5 * (r01 + r10), torch.zeros_like(c))
    o02 = torch.where(obtuse, 0.5 * (r02 + r20), torch.zeros_like(c))
    o12 = torch.where(obtuse, 0.5 * (r12 + r21), torch.zeros_like(c))
    pick0 = (d0 >= d1) & (d0 >= d2)
    pick1 = ~pick0 & (d1 >= d2)
    # column k of sym(R) - c I; largest diagonal => |column| >= (1 - c)/sqrt(3) > 0
    ux = torch.where(pick0, d0, torch.where(pick1, o01, o02))
    uy = torch.where(pick0, o01, torch.where(pick1, d1, o12))
    uz = torch.where(pick0, o02, torch.where(pick1, o12, d2))
    inv = torch.rsqrt(ux * ux + uy * uy + uz * uz)
    vpx, vpy, vpz = (torch.where(obtuse, x, torch.zeros_like(x)) for x in (vx, vy, vz))
    uv = (ux * vpx + uy * vpy + uz * vpz) * inv  # û·v
    sgn = torch.where(uv < 0, -one, one)
    nv = uv * sgn  # n·v >= 0
    tp = torch.atan2(nv, cp)
    k = tp * inv * sgn  # ω = k u on the obtuse branch
    w = (torch.where(obtuse, k * ux, fac * vx), torch.where(obtuse, k * uy, fac * vy),
         torch.where(obtuse, k * uz, fac * vz))
    return w, dict(v=(vx, vy, vz), c=c, obtuse=obtuse)


def log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector of ``R (..., 3, 3)`` -> ``(..., 3)``, ``|ω| ∈ [0, π]`` (:func:`torchconn.lie.so3.log`).

    The branches of :func:`_log_parts` evaluated entrywise on unbound components, differentiated
    by plain autograd (a hand-written torch backward would have to recompute every branch,
    whereas autograd keeps the intermediates). The compiled kernel computes the same branches
    and, in its backward, the chain rule autograd forms on them, per element in one pass. Not
    validated (see :func:`torchconn.lie.so3.check_rotation`).
    """
    if R.dim() < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"log expects a tensor of shape (..., 3, 3), got {tuple(R.shape)}")
    if can_use_compiled("so3", R):
        return _compiled_map(R, "log")
    return _log_torch(R)


def _log_torch(R: torch.Tensor) -> torch.Tensor:
    w, _ = _log_parts(R.flatten(-2).unbind(-1), get_eps("small_angle", R.dtype))
    return torch.stack(w, -1)


def _rotation_flags(R: torch.Tensor, atol: float):
    """Per matrix of ``R (..., 3, 3)``, flattened: ``(bad (N,) bool, e2 (N,), det (N,))``.

    ``e2 = ||Rᵀ R - I||_F²`` from the dot products of the columns, ``bad = ¬(e2 ≤ atol²) ∨
    det < 0`` (true for NaN/inf entries too, whose ``e2`` is NaN or inf): the expressions of
    ``not_rotation`` in ``csrc/so3.c``, in the same order, so both paths flag the same
    matrices. Computed in at least float32 (float16/bfloat16 would round the residual away),
    on the components made contiguous first (one copy; the ~40 elementwise ops that follow
    then stream instead of striding by 9). No gradient, no sync.
    """
    with torch.no_grad():
        work = torch.promote_types(R.dtype, torch.float32)
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = R.detach().to(work).reshape(-1, 9).T.contiguous()
        aa = r0 * r0 + r3 * r3 + r6 * r6 - 1.0
        bb = r1 * r1 + r4 * r4 + r7 * r7 - 1.0
        cc = r2 * r2 + r5 * r5 + r8 * r8 - 1.0
        ab = r0 * r1 + r3 * r4 + r6 * r7
        ac = r0 * r2 + r3 * r5 + r6 * r8
        bc = r1 * r2 + r4 * r5 + r7 * r8
        e2 = aa * aa + bb * bb + cc * cc + 2.0 * (ab * ab + ac * ac + bc * bc)
        det = r0 * (r4 * r8 - r5 * r7) - r1 * (r3 * r8 - r5 * r6) + r2 * (r3 * r7 - r4 * r6)
        tol2 = torch.tensor(atol * atol, dtype=work).item()  # rounded as C's (T)(tol * tol)
        return ~(e2 <= tol2) | (det < 0.0), e2, det


def log_checked(R: torch.Tensor, atol: float) -> tuple[torch.Tensor, int, int]:
    """:func:`log` of ``R (..., 3, 3)`` and its validation: ``(ω (..., 3), n_bad, first)``.

    ``n_bad`` counts the matrices that are not rotations within ``atol``
    (``||Rᵀ R - I||_F > atol``, ``det R < 0`` or a NaN/inf entry; :func:`_rotation_flags`),
    ``first`` is the flat batch index of the first one (``-1`` if none); ``ω`` is exactly
    :func:`log`'s. Compiled: computed inside the log kernel from the nine entries already
    loaded (no second pass over memory, no torch op). Torch path: one fused elementwise check
    and one ``any()``, which **synchronizes** with the device off the CPU. Call it only on
    eager tensors with data (not under ``torch.compile``, vmap or on ``meta``):
    :func:`torchconn.lie.so3.log` decides that.
    """
    if R.dim() < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"log expects a tensor of shape (..., 3, 3), got {tuple(R.shape)}")
    if can_use_compiled("so3", R):
        check = _LogCheck(atol)
        w = _compiled_map(R, "log", check)
        return w, check.n_bad, check.first
    w = _log_torch(R)
    bad = _rotation_flags(R, atol)[0]
    if not bool(bad.any()):
        return w, 0, -1
    return w, int(bad.sum()), int(torch.nonzero(bad)[0, 0])


# ----------------------------------------------------------------------------- sqrt

def sqrt(R: torch.Tensor) -> torch.Tensor:
    """Principal square root of ``R (..., 3, 3)`` -> ``(..., 3, 3)``, equal to ``exp(log(R)/2)``.

    Quaternion half-angle identity: with ``s = sqrt(1 + tr R) = 2 cos(t/2)``,
    ``√R = ((1 + s) I + R + (R - Rᵀ)/s) / (2 + s)`` (from ``q_½ ∝ (1 + w, u)`` for the unit
    quaternion ``(w, u)`` of ``R``). It is used where ``c = (tr R - 1)/2 > -1/2`` (angle below
    120°, ``s > 1``: no cancellation); the remaining entries go through ``exp(log(R)/2)`` (on
    CPU on that subset only, gathered with ``nonzero``; on other devices on every entry with
    safe-where, so there is no device sync), so at angle exactly π the branch follows
    :func:`log`. The compiled kernel takes the same two branches per element.
    """
    if R.dim() < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"sqrt expects a tensor of shape (..., 3, 3), got {tuple(R.shape)}")
    if can_use_compiled("so3", R):
        return _compiled_map(R, "sqrt")
    return _sqrt_torch(R)


def _sqrt_torch(R: torch.Tensor) -> torch.Tensor:
    shape = R.shape
    Rf = R.reshape(-1, 3, 3)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = Rf.flatten(-2).unbind(-1)
    tr = r00 + r11 + r22
    ok = tr > 0.0  # c > -1/2
    s = torch.sqrt(torch.where(ok, 1.0 + tr, torch.full_like(tr, 4.0)))
    inv_s = 1.0 / s
    den = 1.0 / (2.0 + s)
    diag = 1.0 + s
    out = torch.stack((
        diag + r00, r01 + (r01 - r10) * inv_s, r02 + (r02 - r20) * inv_s,
        r10 + (r10 - r01) * inv_s, diag + r11, r12 + (r12 - r21) * inv_s,
        r20 + (r20 - r02) * inv_s, r21 + (r21 - r12) * inv_s, diag + r22,
    ), -1) * den[:, None]
    out = out.unflatten(-1, (3, 3))
    if Rf.device.type == "cpu":
        # CPU: the fallback only on the (usually few) obtuse entries; nonzero does not sync here
        bad = torch.nonzero(~ok).squeeze(-1)
        if bad.numel():
            out = out.index_copy(0, bad, _ExpFn.apply(0.5 * _log_torch(Rf.index_select(0, bad))))
    else:
        # other devices: fallback on every entry (harmless input where unused), no device sync
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        alt = _ExpFn.apply(0.5 * _log_torch(torch.where(ok[:, None, None], eye, Rf)))
        out = torch.where(ok[:, None, None], out, alt)
    return out.reshape(shape)
