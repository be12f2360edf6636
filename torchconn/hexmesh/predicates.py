"""Exact geometric predicates for hex extraction (HEXMESH.md step 8; STYLE "Combinatorial geometry").

Every predicate returns the *exact* sign of a polynomial in the input coordinates, never a
tolerance decision. Two input kinds:

- **integers** (``int64``, e.g. parameters scaled by ``2**grid_bits``, see :func:`to_grid`):
  differences are formed in ``int64`` (exact for ``|x| < 2**62``), then
- **floats** (any finite ``float64``): when every value is a multiple of a common power of two
  with ``|x| * 2**k < 2**62`` (all dyadic grids of :func:`to_grid` qualify) they are converted
  exactly to integers and take the integer path; otherwise differences are formed in floating
  point and only Shewchuk's first filter applies, with an exact :class:`fractions.Fraction`
  fallback per uncertain row.

**How the integer path is exact** (per row, vectorized): the determinant is evaluated in
float64 from the exact differences (exact as floats while ``|difference| < 2**53``). Its sign is
certain when

1. ``|det| > (7 + 56 eps) eps * permanent`` (Shewchuk 1997, ``o3derrboundA``, ``eps = 2**-53``;
   ``permanent`` is the same sum with every product in absolute value), or
2. ``permanent == 0``: every product has a zero factor, so ``det`` is exactly 0 (the common
   degenerate case of a point on a boundary face lying on an integer plane, or on a singular
   edge lying on an integer line), or
3. after dividing out the common power of two of the row, every entry is below ``2**16``: then
   every product and partial sum is an integer below ``2**53`` and the float evaluation has no
   rounding at all (lattice-aligned input: boxes, constructed test cases).

Rows left uncertain are recomputed with Python integers (object arrays), so no overflow and no
rounding anywhere. On maps with generic (quantized) vertices the fallback is taken only for rows
that are degenerate without being axis-aligned, a small fraction.

Sign conventions:

- ``orient3d(a, b, c, d) = sign det[b - a, c - a, d - a]`` (rows), positive when the tet
  ``[a b c d]`` is positively oriented, as in :class:`torchconn.TetMesh`
  (``((b-a) x (c-a)) . (d-a) > 0``).
- ``barycentric_signs(tet, q)[..., k]`` is the sign of the barycentric coordinate ``k`` of
  ``q`` times the tet's orientation: ``orient3d`` of the tet with vertex ``k`` replaced by ``q``.
"""
from __future__ import annotations

from fractions import Fraction
from typing import NamedTuple

import numpy as np
import torch

__all__ = [
    "orient3d", "barycentric_signs", "classify_point", "PointLocation", "to_grid",
    "OUTSIDE", "INSIDE", "ON_FACE", "ON_EDGE", "ON_VERTEX", "DEGENERATE",
]

# Point classes of classify_point (the number of zero barycentric coordinates for the closed tet).
DEGENERATE, OUTSIDE, INSIDE, ON_FACE, ON_EDGE, ON_VERTEX = -2, -1, 0, 1, 2, 3

_EPS = 2.0 ** -53
_O3D_ERR = (7.0 + 56.0 * _EPS) * _EPS  # Shewchuk's o3derrboundA
_O2D_ERR = (3.0 + 16.0 * _EPS) * _EPS  # Shewchuk's ccwerrboundA (bounds a 2x2 determinant too)
_EXACT_FLOAT = 2 ** 53                 # int64 values below this convert to float64 exactly
_INT_LIMIT = 2 ** 62                   # integer coordinates must stay below (differences fit int64)
_SMALL_BITS = 2 ** 16                  # reduced entries below this: float evaluation is exact


# ----------------------------------------------------------------------------- input handling
def _to_numpy(x) -> np.ndarray:
    if torch.is_tensor(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _float_scale_exponent(x: np.ndarray) -> int | None:
    """Smallest ``k`` with ``x * 2**k`` integral for every (finite) value, or ``None`` if the
    scaled values would not stay below ``2**62`` (non-dyadic-grid input).

    Read from the IEEE bits: ``x = m * 2**(e - 1075)`` with the 53-bit integer mantissa ``m``
    (implicit bit included; subnormals have ``e = 1``); its trailing zeros ``tz`` give the
    lowest set bit ``2**(e - 1075 + tz)``.
    """
    x = np.ascontiguousarray(x, dtype=np.float64).ravel()
    x = x[x != 0]
    if x.size == 0:
        return 0
    bits = x.view(np.int64)
    e = (bits >> 52) & 0x7FF
    mant = bits & ((1 << 52) - 1)
    full = np.where(e == 0, mant, mant | (1 << 52))
    e = np.maximum(e, 1)
    low = (full & -full).astype(np.float64).view(np.int64)      # 2**tz as a float: read its exponent
    tz = (low >> 52) - 1023
    k = int(-(e - 1075 + tz).min())
    top = int((e - 1022).max()) + k                             # |x| < 2**(e - 1022)
    return k if top <= 62 else None


def _as_exact_ints(arrays: list[np.ndarray]) -> list[np.ndarray] | None:
    """The arrays as ``int64`` with one common power-of-two scale (signs unchanged), or ``None``."""
    if all(np.issubdtype(a.dtype, np.integer) for a in arrays):
        out = [a.astype(np.int64, copy=False) for a in arrays]
        for a in out:
            if a.size and int(np.abs(a).max()) >= _INT_LIMIT:
                raise ValueError(f"integer coordinates must satisfy |x| < 2**62, got {int(np.abs(a).max())}")
        return out
    flo = [a.astype(np.float64, copy=False) for a in arrays]
    for a in flo:
        if not np.all(np.isfinite(a)):
            raise ValueError("coordinates must be finite (NaN or inf found)")
    k = _float_scale_exponent(np.concatenate([a.ravel() for a in flo]))
    if k is None:
        return None
    return [np.ldexp(a, k).astype(np.int64) for a in flo]


def _broadcast_points(*pts) -> list[np.ndarray]:
    arrs = [_to_numpy(p) for p in pts]
    for i, a in enumerate(arrs):
        if a.ndim == 0 or a.shape[-1] != 3:
            raise ValueError(f"point argument {i} must have shape (..., 3), got {tuple(a.shape)}")
        if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
            raise TypeError(f"point argument {i} must be integer or floating, got {a.dtype}")
    return list(np.broadcast_arrays(*arrs))


def _wrap(out: np.ndarray, like: tuple):
    """Return a torch tensor when any input was one (same device as the first), else numpy."""
    for x in like:
        if torch.is_tensor(x):
            return torch.from_numpy(np.ascontiguousarray(out)).to(x.device)
    return out


# ----------------------------------------------------------------------------- integer kernels
def _reduced_small(rows: np.ndarray) -> np.ndarray:
    """``(N, k)`` int64 -> ``(N,)`` bool: after dividing out the row's common power of two, all
    entries are below ``2**16`` in magnitude (so float products of three and their sums are exact)."""
    a = np.abs(rows)
    common = np.bitwise_or.reduce(a, axis=1)
    low = np.where(common == 0, 1, common & -common)
    return (a.max(axis=1) // low) < _SMALL_BITS


def _sign_of(d: np.ndarray) -> np.ndarray:
    return (d > 0).astype(np.int8) - (d < 0).astype(np.int8)


def _det3_exact(u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``sign det[u; v; w]`` in Python integers (object arrays) for int64 rows ``(N, 3)``."""
    U, V, W = (x.astype(object) for x in (u, v, w))
    d = (U[:, 0] * (V[:, 1] * W[:, 2] - V[:, 2] * W[:, 1]) + U[:, 1] * (V[:, 2] * W[:, 0] - V[:, 0] * W[:, 2])
         + U[:, 2] * (V[:, 0] * W[:, 1] - V[:, 1] * W[:, 0]))
    return _sign_of(d)


def _cross_parts(y: np.ndarray, z: np.ndarray):
    """``y x z`` and ``|y_j z_k| + |y_k z_j|`` per component, float64 ``(N, 3)``."""
    p0, q0 = y[:, 1] * z[:, 2], y[:, 2] * z[:, 1]
    p1, q1 = y[:, 2] * z[:, 0], y[:, 0] * z[:, 2]
    p2, q2 = y[:, 0] * z[:, 1], y[:, 1] * z[:, 0]
    cross = np.stack([p0 - q0, p1 - q1, p2 - q2], axis=1)
    absum = np.stack([np.abs(p0) + np.abs(q0), np.abs(p1) + np.abs(q1), np.abs(p2) + np.abs(q2)], axis=1)
    return cross, absum


def _filtered(det: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """Rows whose float determinant's sign is certain (Shewchuk's bound, or all products zero)."""
    return (np.abs(det) > _O3D_ERR * perm) | (perm == 0)


def _det3_sign_int(u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Exact ``sign det[u; v; w]`` of int64 rows ``(N, 3)`` each -> ``(N,)`` int8.

    Float evaluation with the certificates of the module docstring; Python integers for the rest.
    """
    n = u.shape[0]
    out = np.zeros(n, np.int8)
    if n == 0:
        return out
    big = max(int(np.abs(x).max()) for x in (u, v, w)) >= _EXACT_FLOAT
    if big:  # rare: entries that do not convert to float exactly are decided exactly
        fits = np.maximum(np.maximum(np.abs(u).max(1), np.abs(v).max(1)), np.abs(w).max(1)) < _EXACT_FLOAT
    uf, vf, wf = (x.astype(np.float64) for x in (u, v, w))
    cross, absum = _cross_parts(vf, wf)
    det = np.einsum("ni,ni->n", uf, cross)
    perm = np.einsum("ni,ni->n", np.abs(uf), absum)
    sure = _filtered(det, perm)
    if big:
        sure &= fits
    unsure = np.nonzero(~sure)[0]
    if unsure.size:
        rows = np.concatenate([u[unsure], v[unsure], w[unsure]], axis=1)
        small = _reduced_small(rows)
        if big:
            small &= fits[unsure]
        sure[unsure[small]] = True
    out[sure] = np.sign(det[sure])
    rest = np.nonzero(~sure)[0]
    if rest.size:
        out[rest] = _det3_exact(u[rest], v[rest], w[rest])
    return out


def _det2_sign_int(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Exact ``sign(a d - b c)`` of int64 ``(N,)`` arrays -> ``(N,)`` int8."""
    n = a.shape[0]
    out = np.zeros(n, np.int8)
    if n == 0:
        return out
    rows = np.stack([a, b, c, d], axis=1)
    fits = np.abs(rows).max(axis=1) < _EXACT_FLOAT
    af, bf, cf, df = (x.astype(np.float64) for x in (a, b, c, d))
    p, q = af * df, bf * cf
    det = p - q
    sure = fits & ((np.abs(det) > _O2D_ERR * (np.abs(p) + np.abs(q))) | ((p == 0) & (q == 0)))
    if not sure.all():
        sure |= fits & _reduced_small(rows)
    out[sure] = np.sign(det[sure])
    rest = np.nonzero(~sure)[0]
    if rest.size:
        A, B, C, D = (x[rest].astype(object) for x in (a, b, c, d))
        out[rest] = _sign_of(A * D - B * C)
    return out


def _orient3d_int(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``sign det[b-a, c-a, d-a]`` for int64 ``(N, 3)`` points (``|x| < 2**62``) -> ``(N,)`` int8."""
    return _det3_sign_int(b - a, c - a, d - a)


def _barycentric_signs_int(tet: np.ndarray, q: np.ndarray) -> np.ndarray:
    """int64 ``tet (N, 4, 3)``, ``q (N, 3)`` -> ``(N, 4)`` int8: ``orient3d`` with vertex ``k``
    replaced by ``q``.

    With ``a_k = v_k - q`` (the point at the origin) the four determinants are
    ``det[a1,a2,a3]``, ``-det[a0,a2,a3]``, ``det[a0,a1,a3]``, ``-det[a0,a1,a2]``: two cross products
    (``a2 x a3``, ``a0 x a1``) and four dot products, filtered and certified as in
    :func:`_det3_sign_int`, exact integers for the uncertain entries.
    """
    n = tet.shape[0]
    out = np.zeros((n, 4), np.int8)
    if n == 0:
        return out
    A = tet - q[:, None, :]
    big = int(np.abs(A).max()) >= _EXACT_FLOAT
    Af = A.astype(np.float64)
    a0, a1, a2, a3 = Af[:, 0], Af[:, 1], Af[:, 2], Af[:, 3]
    c23, p23 = _cross_parts(a2, a3)
    c01, p01 = _cross_parts(a0, a1)
    dot = lambda x, y: np.einsum("ni,ni->n", x, y)  # noqa: E731
    det = np.stack([dot(a1, c23), -dot(a0, c23), dot(a3, c01), -dot(a2, c01)], axis=1)
    perm = np.stack([dot(np.abs(a1), p23), dot(np.abs(a0), p23), dot(np.abs(a3), p01), dot(np.abs(a2), p01)], axis=1)
    sure = _filtered(det, perm)
    if big:
        sure &= (np.abs(A).max(axis=(1, 2)) < _EXACT_FLOAT)[:, None]
    rows_unsure = np.nonzero(~sure.all(axis=1))[0]
    if rows_unsure.size:
        small = _reduced_small(A[rows_unsure].reshape(-1, 12))
        if big:
            small &= np.abs(A[rows_unsure]).max(axis=(1, 2)) < _EXACT_FLOAT
        sure[rows_unsure[small]] = True
    out[sure] = np.sign(det[sure])
    r, k = np.nonzero(~sure)
    if r.size:
        trip = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[k]
        sgn = np.array([1, -1, 1, -1], np.int8)[k]
        out[r, k] = sgn * _det3_exact(A[r, trip[:, 0]], A[r, trip[:, 1]], A[r, trip[:, 2]])
    return out


def _orient3d_sos_int(p: np.ndarray, g: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Sign of ``orient3d(p_eps, a, b, c)`` for the symbolically perturbed point
    ``p_eps = p + eps (g - p) + eps^2 e_x + eps^3 e_y + eps^4 e_z`` as ``eps -> 0+``.

    ``orient3d(x, a, b, c)`` is affine in ``x`` with gradient ``-n``, ``n = (b-a) x (c-a)``, so the
    sign is the first nonzero of ``orient3d(p,a,b,c)``, ``orient3d(g,a,b,c)`` (the eps term when the
    first vanishes), ``-n_x``, ``-n_y``, ``-n_z``. It is 0 only when ``a, b, c`` are collinear.
    The walk of :mod:`torchconn.hexmesh.extract` moves ``p`` (a cube centre) towards ``g`` (the
    centroid of its tet) so the perturbed start is inside that tet. int64 ``(N, 3)`` -> ``(N,)`` int8.
    """
    s = _orient3d_int(p, a, b, c)
    z = np.nonzero(s == 0)[0]
    if z.size:
        s[z] = _orient3d_int(g[z], a[z], b[z], c[z])
        z = z[s[z] == 0]
    if z.size:
        u, v = b[z] - a[z], c[z] - a[z]
        for i, j in ((1, 2), (2, 0), (0, 1)):  # n_x, n_y, n_z = u_i v_j - u_j v_i
            nz = _det2_sign_int(u[:, i], u[:, j], v[:, i], v[:, j])
            s[z] = -nz
            keep = nz == 0
            z, u, v = z[keep], u[keep], v[keep]
            if not z.size:
                break
    return s


# ----------------------------------------------------------------------------- float fallback
def _orient3d_float(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Exact orientation of arbitrary finite float64 points ``(N, 3)``: Shewchuk's filter on the
    rounded differences (its bound covers their rounding), :class:`Fraction` for the rest."""
    u, v, w = b - a, c - a, d - a
    m0a, m0b = v[:, 1] * w[:, 2], v[:, 2] * w[:, 1]
    m1a, m1b = v[:, 2] * w[:, 0], v[:, 0] * w[:, 2]
    m2a, m2b = v[:, 0] * w[:, 1], v[:, 1] * w[:, 0]
    det = u[:, 0] * (m0a - m0b) + u[:, 1] * (m1a - m1b) + u[:, 2] * (m2a - m2b)
    perm = (np.abs(u[:, 0]) * (np.abs(m0a) + np.abs(m0b)) + np.abs(u[:, 1]) * (np.abs(m1a) + np.abs(m1b))
            + np.abs(u[:, 2]) * (np.abs(m2a) + np.abs(m2b)))
    # The bound assumes no overflow or underflow: rows with extreme magnitudes go exact.
    mag = np.abs(np.concatenate([a, b, c, d], axis=1))
    tame = (mag.max(axis=1) < 2.0 ** 250) & np.all((mag == 0) | (mag > 2.0 ** -250), axis=1)
    sure = tame & (np.abs(det) > _O3D_ERR * perm) & (perm > 0)
    out = np.zeros(a.shape[0], np.int8)
    out[sure] = np.sign(det[sure])
    for i in np.nonzero(~sure)[0]:  # rare: near-degenerate rows of non-dyadic input
        A, B, C, D = ([Fraction(float(t)) for t in x[i]] for x in (a, b, c, d))
        U = [B[k] - A[k] for k in range(3)]
        V = [C[k] - A[k] for k in range(3)]
        W = [D[k] - A[k] for k in range(3)]
        e = (U[0] * (V[1] * W[2] - V[2] * W[1]) + U[1] * (V[2] * W[0] - V[0] * W[2])
             + U[2] * (V[0] * W[1] - V[1] * W[0]))
        out[i] = (e > 0) - (e < 0)
    return out


# ----------------------------------------------------------------------------- public predicates
def orient3d(a, b, c, d):
    """Exact orientation sign of four points, batched.

    Args:
        a, b, c, d: ``(..., 3)`` numpy arrays or torch tensors (broadcastable), integer or float64.
            Integers must satisfy ``|x| < 2**62``; floats must be finite (any finite value is
            decided exactly; dyadic input such as a map on a ``2**-grid_bits`` grid takes the fast
            integer path).

    Returns:
        ``(...)`` int8 (numpy, or a torch tensor when an input was one): ``sign det[b-a, c-a, d-a]``,
        ``+1`` for a positively oriented tet ``[a b c d]`` (``((b-a) x (c-a)) . (d-a) > 0``, the
        :class:`torchconn.TetMesh` convention), ``-1`` inverted, ``0`` coplanar.

    Example (flipped tets of a map ``uvw (T, 4, 3)``)::

        flipped = orient3d(uvw[:, 0], uvw[:, 1], uvw[:, 2], uvw[:, 3]) <= 0
    """
    pts = _broadcast_points(a, b, c, d)
    shape = pts[0].shape[:-1]
    flat = [p.reshape(-1, 3) for p in pts]
    ints = _as_exact_ints(flat)
    if ints is not None:
        out = _orient3d_int(*ints)
    else:
        out = _orient3d_float(*(p.astype(np.float64) for p in flat))
    return _wrap(out.reshape(shape), (a, b, c, d))


def barycentric_signs(tet, q):
    """Exact signs of the barycentric coordinates of points with respect to tets, batched.

    Args:
        tet: ``(..., 4, 3)`` vertices; q: ``(..., 3)`` points (broadcastable batch dims; integer or
            float64, as in :func:`orient3d`).

    Returns:
        ``(..., 4)`` int8: entry ``k`` is ``orient3d`` of the tet with vertex ``k`` replaced by ``q``,
        i.e. ``sign(lambda_k(q)) * orient3d(tet)``. For a positively oriented tet, ``q`` is in the
        closed tet iff all four are ``>= 0`` and lies on face ``k`` (opposite vertex ``k``) where
        entry ``k`` is 0.
    """
    T = _to_numpy(tet)
    Q = _to_numpy(q)
    if T.ndim < 2 or T.shape[-2:] != (4, 3):
        raise ValueError(f"tet must have shape (..., 4, 3), got {tuple(T.shape)}")
    if Q.ndim == 0 or Q.shape[-1] != 3:
        raise ValueError(f"q must have shape (..., 3), got {tuple(Q.shape)}")
    batch = np.broadcast_shapes(T.shape[:-2], Q.shape[:-1])
    T = np.broadcast_to(T, batch + (4, 3)).reshape(-1, 4, 3)
    Q = np.broadcast_to(Q, batch + (3,)).reshape(-1, 3)
    verts = [T[:, k] for k in range(4)]
    ints = _as_exact_ints(verts + [Q])
    if ints is not None:
        out = _barycentric_signs_int(np.stack(ints[:4], axis=1), ints[4])
    else:
        v = [x.astype(np.float64) for x in verts]
        qf = Q.astype(np.float64)
        out = np.stack([_orient3d_float(qf, v[1], v[2], v[3]), _orient3d_float(v[0], qf, v[2], v[3]),
                        _orient3d_float(v[0], v[1], qf, v[3]), _orient3d_float(v[0], v[1], v[2], qf)], axis=1)
    return _wrap(out.reshape(batch + (4,)), (tet, q))


class PointLocation(NamedTuple):
    """Result of :func:`classify_point`.

    ``kind (...)`` int8: :data:`INSIDE` (0), :data:`ON_FACE` (1), :data:`ON_EDGE` (2),
    :data:`ON_VERTEX` (3) (the number of vanishing barycentric coordinates), :data:`OUTSIDE` (-1),
    or :data:`DEGENERATE` (-2) for a flat tet. ``zero (..., 4)`` bool: which barycentric
    coordinates vanish (on face ``k`` where only ``zero[k]``; on the edge opposite ``i, j`` where
    ``zero[i]`` and ``zero[j]``; on vertex ``v`` where all but ``zero[v]``). ``orientation (...)``
    int8: the tet's :func:`orient3d` sign.
    """

    kind: np.ndarray
    zero: np.ndarray
    orientation: np.ndarray


def classify_point(tet, q) -> PointLocation:
    """Classify points against closed tets exactly: inside / on face k / on edge / on vertex / outside.

    Args:
        tet: ``(..., 4, 3)``; q: ``(..., 3)`` (broadcastable; integer, or float64 such as the
            integer and half-integer query points of a ``2**-grid_bits`` map). Tets of either
            orientation are classified against their closed point set; flat tets give
            :data:`DEGENERATE`.

    Returns:
        :class:`PointLocation` of numpy arrays.
    """
    s = _to_numpy(barycentric_signs(tet, q))
    T = _to_numpy(tet)
    o = _to_numpy(orient3d(T[..., 0, :], T[..., 1, :], T[..., 2, :], T[..., 3, :]))
    o = np.broadcast_to(o, s.shape[:-1])
    rel = s * o[..., None]                     # sign of lambda_k for either orientation
    zero = rel == 0
    kind = zero.sum(axis=-1).astype(np.int8)
    kind = np.where((rel < 0).any(axis=-1), np.int8(OUTSIDE), kind)
    kind = np.where(o == 0, np.int8(DEGENERATE), kind).astype(np.int8)
    return PointLocation(kind=kind, zero=zero & (o != 0)[..., None], orientation=o.astype(np.int8))


def to_grid(x, grid_bits: int, *, name: str = "x", limit_bits: int = 52) -> np.ndarray:
    """Exact integer coordinates ``x * 2**grid_bits`` of dyadic input, as int64.

    Args:
        x: array or tensor of any shape, integer or float.
        grid_bits: the grid is ``2**-grid_bits``.
        name: used in error messages.
        limit_bits: the scaled values must satisfy ``|x| * 2**grid_bits < 2**limit_bits``.

    Raises:
        ValueError: non-finite values, values not on the grid, or too large; the message names the
            first offending flat indices along the first axis and their count.
    """
    a = _to_numpy(x)
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise TypeError(f"{name} must be integer or floating, got {a.dtype}")
    a = a.astype(np.float64)
    lead = a.reshape(a.shape[0], -1) if a.ndim else a.reshape(1, 1)

    def bad_rows(mask):
        rows = np.nonzero(mask.reshape(lead.shape).any(axis=1))[0]
        return f"{rows[:8].tolist()}{' ...' if rows.size > 8 else ''} ({rows.size} in all)"

    fin = np.isfinite(lead)
    if not fin.all():
        raise ValueError(f"{name} has non-finite values at rows {bad_rows(~fin)}")
    scaled = np.ldexp(lead, grid_bits)
    big = np.abs(scaled) >= 2.0 ** limit_bits
    if big.any():
        raise ValueError(f"{name} is too large for a 2**-{grid_bits} grid (|value| * 2**{grid_bits} must be "
                         f"< 2**{limit_bits}) at rows {bad_rows(big)}")
    off = scaled != np.round(scaled)
    if off.any():
        raise ValueError(f"{name} is not on the dyadic grid 2**-{grid_bits} (values must be multiples of "
                         f"2**-{grid_bits}; snap them first) at rows {bad_rows(off)}")
    return scaled.astype(np.int64).reshape(a.shape)
