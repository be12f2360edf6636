"""The generic (torch) formulas of the SO(3) maps and of their backward passes.

Plain torch operations on unbound components, elementwise over any leading dimensions, any
device and dtype; every branch is evaluated on every element with a harmless input where it is
unused (safe-where: no ``nonzero``, no data-dependent control flow, finite values and gradients
at angle 0 and π). They are the default kernels of the custom ops of :mod:`torchconn.ops.so3`
(which run below autograd, so a backward cannot be left to autograd there: each ``*_bwd`` is
the chain rule written out), and, differentiated by ``torch.func.vjp``, the second derivatives
of those ops. ``csrc/so3.c`` computes the same expressions in the same order.
"""
from __future__ import annotations

import torch

from ..tolerances import get_eps


# ----------------------------------------------------------------------------- exp

def exp_coeffs(t2: torch.Tensor, with_derivatives: bool):
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


def rodrigues(x, y, z, A, B) -> torch.Tensor:
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


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues ``exp(hat(ω))``: ``(..., 3) -> (..., 3, 3)``."""
    x, y, z = omega.unbind(-1)
    A, B = exp_coeffs(x * x + y * y + z * z, False)
    return rodrigues(x, y, z, A, B)


def exp_bwd(omega: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """``∂L/∂ω (..., 3)`` from ``G = ∂L/∂R (..., 3, 3)``.

    With ``g = (G21 - G12, G02 - G20, G10 - G01)``, ``S = G + Gᵀ``:
    ``∂L/∂ω = A g + B (S ω - 2 tr(G) ω) + 2 A'(ω·g) ω + 2 B'(ωᵀ G ω - |ω|² tr G) ω``
    (``A' = dA/d(t²)``, ``B' = dB/d(t²)``), from ``∂R/∂ω_k = A E_k + B (E_k K + K E_k) + ...``
    with ``E_k K + K E_k = ω e_kᵀ + e_k ωᵀ - 2 ω_k I``.
    """
    x, y, z = omega.unbind(-1)
    t2 = x * x + y * y + z * z
    A, B, dA, dB = exp_coeffs(t2, True)
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


# ----------------------------------------------------------------------------- log

def _log_poly(s2):
    return 1.0 + s2 * (1.0 / 6.0 + s2 * (3.0 / 40.0 + s2 * (5.0 / 112.0)))


def log_parts(r, eps_small):
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
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    s_g = torch.sqrt(torch.where(generic, s2, one))
    c_g = torch.where(generic, c, zero)
    s2_s = torch.where(small, s2, zero)
    a_g = torch.atan2(s_g, c_g)
    fac = torch.where(small, _log_poly(s2_s), a_g / s_g)
    # obtuse branch on a rotation by pi about x where unused (diag (1, -1, -1), v = 0, c = -1)
    cp = torch.where(obtuse, c, -one)
    d0 = torch.where(obtuse, r00, one) - cp
    d1 = torch.where(obtuse, r11, -one) - cp
    d2 = torch.where(obtuse, r22, -one) - cp
    o01 = torch.where(obtuse, 0.5 * (r01 + r10), zero)
    o02 = torch.where(obtuse, 0.5 * (r02 + r20), zero)
    o12 = torch.where(obtuse, 0.5 * (r12 + r21), zero)
    pick0 = (d0 >= d1) & (d0 >= d2)
    pick1 = ~pick0 & (d1 >= d2)
    # column k of sym(R) - c I; largest diagonal => |column| >= (1 - c)/sqrt(3) > 0
    ux = torch.where(pick0, d0, torch.where(pick1, o01, o02))
    uy = torch.where(pick0, o01, torch.where(pick1, d1, o12))
    uz = torch.where(pick0, o02, torch.where(pick1, o12, d2))
    inv = torch.rsqrt(ux * ux + uy * uy + uz * uz)
    vp = tuple(torch.where(obtuse, x, zero) for x in (vx, vy, vz))
    uvr = ux * vp[0] + uy * vp[1] + uz * vp[2]
    uv = uvr * inv  # û·v
    sgn = torch.where(uv < 0, -one, one)
    nv = uv * sgn  # n·v >= 0
    tp = torch.atan2(nv, cp)
    k = tp * inv * sgn  # ω = k u on the obtuse branch
    w = (torch.where(obtuse, k * ux, fac * vx), torch.where(obtuse, k * uy, fac * vy),
         torch.where(obtuse, k * uz, fac * vz))
    return w, dict(v=(vx, vy, vz), c=c, small=small, obtuse=obtuse, s_g=s_g, c_g=c_g, a_g=a_g,
                   s2_s=s2_s, fac=fac, cp=cp, pick0=pick0, pick1=pick1, u=(ux, uy, uz), inv=inv,
                   vp=vp, uvr=uvr, sgn=sgn, nv=nv, tp=tp, k=k)


def log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector ``(..., 3)`` of ``R (..., 3, 3)`` (the branches of :func:`log_parts`)."""
    w, _ = log_parts(R.flatten(-2).unbind(-1), get_eps("small_angle", R.dtype))
    return torch.stack(w, -1)


def log_bwd(R: torch.Tensor, gw: torch.Tensor) -> torch.Tensor:
    """``∂L/∂R (..., 3, 3)`` from ``gw = ∂L/∂ω (..., 3)``: the chain rule through :func:`log_parts`.

    Exactly what autograd forms on those expressions (the picks and ``sgn`` are constants; the
    gradient of ``atan2(y, x)`` is ``(x, -y)/(x² + y²)``, finite at ``(0, -1)``, i.e. at angle
    π), on the safe-where intermediates, so that it is finite and differentiable again.
    """
    q = log_parts(R.flatten(-2).unbind(-1), get_eps("small_angle", R.dtype))[1]
    g0, g1, g2 = gw.unbind(-1)
    vx, vy, vz = q["v"]
    zero = torch.zeros_like(g0)
    ob, small = q["obtuse"], q["small"]
    gwv = g0 * vx + g1 * vy + g2 * vz
    # obtuse: w = k u, k = tp inv sgn, tp = atan2(nv, cp), nv = uv sgn, uv = (u.vp) inv
    ux, uy, uz = q["u"]
    inv, sgn, nv, tp, k, cp = q["inv"], q["sgn"], q["nv"], q["tp"], q["k"], q["cp"]
    gk = g0 * ux + g1 * uy + g2 * uz
    gtp = gk * inv * sgn
    den_o = nv * nv + cp * cp
    gnv = gtp * cp / den_o
    gc_o = -gtp * nv / den_o
    al = gnv * sgn * inv  # d/d(u.vp)
    ginv = gk * tp * sgn + gnv * sgn * q["uvr"]
    be = -ginv * inv * inv * inv  # inv = rsqrt(u.u)
    vpx, vpy, vpz = q["vp"]
    gu0, gu1, gu2 = k * g0 + al * vpx + be * ux, k * g1 + al * vpy + be * uy, k * g2 + al * vpz + be * uz
    p0, p1 = q["pick0"], q["pick1"]
    p2 = ~(p0 | p1)
    gd0 = torch.where(ob & p0, gu0, zero)
    gd1 = torch.where(ob & p1, gu1, zero)
    gd2 = torch.where(ob & p2, gu2, zero)
    go01 = torch.where(ob, torch.where(p0, gu1, torch.where(p1, gu0, zero)), zero)
    go02 = torch.where(ob, torch.where(p0, gu2, torch.where(p2, gu0, zero)), zero)
    go12 = torch.where(ob, torch.where(p1, gu2, torch.where(p2, gu1, zero)), zero)
    gc_o = gc_o - (gd0 + gd1 + gd2)
    # small: w = poly(s2) v;  generic: w = (a/s) v, a = atan2(s, c)
    s2_s = q["s2_s"]
    dpoly = 1.0 / 6.0 + s2_s * (2.0 * 3.0 / 40.0 + s2_s * (3.0 * 5.0 / 112.0))
    s, c_g, a = q["s_g"], q["c_g"], q["a_g"]
    den_g = s * s + c_g * c_g
    ga = gwv / s
    gs = -gwv * a / (s * s) + ga * c_g / den_g
    gc_g = -ga * s / den_g
    gr = torch.where(small, 2.0 * gwv * dpoly, gs / s)  # dL/dv = fac gw + gr v
    fac = q["fac"]
    gvx = torch.where(ob, al * ux, fac * g0 + gr * vx)
    gvy = torch.where(ob, al * uy, fac * g1 + gr * vy)
    gvz = torch.where(ob, al * uz, fac * g2 + gr * vz)
    gc = torch.where(ob, gc_o, torch.where(small, zero, gc_g))
    hc = 0.5 * gc
    return torch.stack((
        gd0 + hc, 0.5 * (go01 - gvz), 0.5 * (go02 + gvy),
        0.5 * (go01 + gvz), gd1 + hc, 0.5 * (go12 - gvx),
        0.5 * (go02 - gvy), 0.5 * (go12 + gvx), gd2 + hc,
    ), -1).unflatten(-1, (3, 3))


# ----------------------------------------------------------------------------- sqrt

def _half_angle_ok(R: torch.Tensor):
    """``(ok, s)``: ``ok = tr R > 0`` (angle below 120°) and ``s = sqrt(1 + tr R)`` (``2`` where not ok)."""
    tr = R.diagonal(dim1=-2, dim2=-1).sum(-1)
    ok = tr > 0.0
    return ok, torch.sqrt(torch.where(ok, 1.0 + tr, torch.full_like(tr, 4.0)))


def sqrt(R: torch.Tensor) -> torch.Tensor:
    """Principal root of ``R (..., 3, 3)``: ``((1 + s) I + R + (R - Rᵀ)/s) / (2 + s)`` where
    ``tr R > 0``, ``exp(log(R)/2)`` elsewhere (evaluated on ``I`` where unused)."""
    ok, s = _half_angle_ok(R)
    inv_s = (1.0 / s)[..., None, None]
    den = (1.0 / (2.0 + s))[..., None, None]
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    half = ((1.0 + s)[..., None, None] * eye + R + (R - R.transpose(-1, -2)) * inv_s) * den
    okm = ok[..., None, None]
    alt = exp(0.5 * log(torch.where(okm, eye, R)))
    return torch.where(okm, half, alt)


def sqrt_bwd(R: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """``∂L/∂R`` from ``G = ∂L/∂√R`` (both ``(..., 3, 3)``): the chain rule through :func:`sqrt`.

    Half-angle branch, with ``P = (1 + s) I + R + (R - Rᵀ)/s`` and ``d = 1/(2 + s)``:
    ``g = d G``, ``∂L/∂s = -d² ⟨G, P⟩ + tr g - ⟨g - gᵀ, R - Rᵀ⟩/(2 s²)``,
    ``∂L/∂R = g + (g - gᵀ)/s + ∂L/∂s / (2 s) I``; elsewhere through ``exp`` and ``log``.
    """
    ok, s = _half_angle_ok(R)
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    okm = ok[..., None, None]
    inv_s, den = 1.0 / s, 1.0 / (2.0 + s)
    A = R - R.transpose(-1, -2)
    P = (1.0 + s)[..., None, None] * eye + R + A * inv_s[..., None, None]
    g = G * den[..., None, None]
    gA = g - g.transpose(-1, -2)
    gs = (-(G * P).sum((-1, -2)) * den * den + g.diagonal(dim1=-2, dim2=-1).sum(-1)
          - 0.5 * (gA * A).sum((-1, -2)) * inv_s * inv_s)
    half = g + gA * inv_s[..., None, None] + (gs / (2.0 * s))[..., None, None] * eye
    Rs = torch.where(okm, eye, R)
    gh = 0.5 * exp_bwd(0.5 * log(Rs), G)
    return torch.where(okm, half, log_bwd(Rs, gh))


# ----------------------------------------------------------------------------- validation

def rotation_flags(R: torch.Tensor, atol: float):
    """Per matrix of ``R (..., 3, 3)``, flattened: ``(bad (N,) bool, e2 (N,), det (N,))``.

    ``e2 = ||Rᵀ R - I||_F²`` from the dot products of the columns, ``bad = ¬(e2 ≤ atol²) ∨
    det < 0`` (true for NaN/inf entries too, whose ``e2`` is NaN or inf): the expressions of
    ``not_rotation`` in ``csrc/so3.c``, in the same order, so both paths flag the same
    matrices. Computed in at least float32 (float16/bfloat16 would round the residual away),
    on the components made contiguous first. No gradient; the tolerance is rounded to the
    working dtype as C's ``(T)(tol * tol)``.
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
        tol2 = torch.tensor(atol * atol, dtype=work)  # rounded as C's (T)(tol * tol)
        return ~(e2 <= tol2) | (det < 0.0), e2, det
