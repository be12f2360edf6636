"""SO(n): rotations of any rank n as ``(..., n, n)`` matrices, batched over leading dims.

Conventions
-----------
* Rotations act on column vectors (``y = R @ x``); transports follow docs/conventions.md §1.
* The Lie algebra so(n) (skew ``n x n`` matrices, report Remark 3.4) is parametrized by
  ``m = dim(n) = n(n-1)/2`` numbers. For ``n == 3`` the order is that of :func:`so3.hat`
  (``omega = (x, y, z)``, ``hat(omega) x = omega x x``). For every other ``n`` the parameters
  follow the lexicographic pairs ``(i, j)``, ``i < j`` (the order of ``transport.pair_list``),
  with ``K[j, i] = +p`` and ``K[i, j] = -p``; for ``n = 2``, ``p = theta`` gives the rotation by
  ``+theta`` (counter-clockwise).
* ``exp`` has closed forms for ``n = 2`` (cos/sin) and ``n = 3`` (Rodrigues, :func:`so3.exp`)
  and uses ``torch.linalg.matrix_exp`` for ``n >= 4``. ``log`` has closed forms for
  ``n = 2`` (atan2) and ``n = 3`` (:func:`so3.log`); for ``n >= 4`` it uses inverse scaling and
  squaring (see :func:`log`).

All functions accept any float dtype and device; constants follow the input. Inputs are
checked as in :mod:`torchconn.lie.so3` (no data read, no sync): a non-tensor (NumPy array, list) or a
non-floating dtype raises ``TypeError`` naming the function, the argument and the type or
dtype (convert with ``torch.as_tensor(x, dtype=...)`` first); a wrong shape raises
``ValueError``. Values are not validated: :func:`log` and :func:`sqrt` of a non-rotation
return a meaningless (finite, or NaN near angle pi for ``n >= 4``) result; check explicitly
with :func:`check_rotation` (synchronizes).
"""
from __future__ import annotations

from functools import lru_cache
import itertools

import torch

from . import so3
from ..tolerances import get_eps
from ._validate import check_float_tensor as _check_float
from ._validate import check_rotation

__all__ = [
    "dim", "hat", "vee", "exp", "exp_params", "log", "sqrt", "random_rotation", "check_rotation"
]


def dim(n: int) -> int:
    """Dimension ``n(n-1)/2`` of so(n) (number of skew parameters)."""
    if n < 1:
        raise ValueError(f"rank n must be >= 1, got {n}")
    return n * (n - 1) // 2


@lru_cache(maxsize=None)
def _basis_cpu(n: int) -> torch.Tensor:
    """``(m, n, n)`` float64 basis of so(n) in the parameter order of the module docstring."""
    m = dim(n)
    if n == 3:
        return so3.hat(torch.eye(3, dtype=torch.float64))
    E = torch.zeros(m, n, n, dtype=torch.float64)
    for a, (i, j) in enumerate(itertools.combinations(range(n), 2)):
        E[a, j, i] = 1.0
        E[a, i, j] = -1.0
    return E


def _basis(n: int, like: torch.Tensor) -> torch.Tensor:
    return _basis_cpu(n).to(dtype=like.dtype, device=like.device)


def _check_square(K: torch.Tensor, fn: str, arg: str = "R") -> int:
    _check_float(K, f"son.{fn}", arg)
    if K.dim() < 2 or K.shape[-1] != K.shape[-2]:
        raise ValueError(f"son.{fn} expects a tensor of shape (..., n, n), got {tuple(K.shape)}")
    return K.shape[-1]


def hat(params: torch.Tensor, n: int) -> torch.Tensor:
    """Skew matrix from parameters: ``params (..., m) -> K (..., n, n)``, ``m = dim(n)``.

    Parameter order: :func:`so3.hat` for ``n = 3``; lexicographic pairs ``i < j`` with
    ``K[j, i] = p``, ``K[i, j] = -p`` otherwise (module docstring). Linear, differentiable.
    """
    m = dim(n)
    _check_float(params, "son.hat", "params")
    if params.dim() < 1 or params.shape[-1] != m:
        raise ValueError(
            f"hat for n={n} expects params of shape (..., {m}), got {tuple(params.shape)}"
        )
    E = _basis(n, params)
    return (params @ E.reshape(m, n * n)).reshape(*params.shape[:-1], n, n)


def vee(K: torch.Tensor) -> torch.Tensor:
    """Parameters of the skew part of ``K (..., n, n) -> (..., m)``; inverse of :func:`hat`.

    Uses ``(K - K^T)/2``, so it is the orthogonal projection for non-skew input.
    """
    n = _check_square(K, "vee", "K")
    m = dim(n)
    E = _basis(n, K)
    # <E_a, E_a>_F = 2 and <E_a, K> = <E_a, skew(K)>
    return 0.5 * (K.reshape(*K.shape[:-2], n * n) @ E.reshape(m, n * n).transpose(0, 1))


def exp(K: torch.Tensor) -> torch.Tensor:
    """Matrix exponential of the skew part of ``K (..., n, n)``: a rotation ``(..., n, n)``.

    ``n = 2``: ``[[cos t, -sin t], [sin t, cos t]]`` with ``t = (K[1,0] - K[0,1])/2``;
    ``n = 3``: Rodrigues ``so3.exp(so3.vee(K))``; ``n >= 4``: ``torch.linalg.matrix_exp`` of
    ``(K - K^T)/2`` (report Remark 3.4: the exponential of a skew matrix lies in SO(n)).
    Differentiable, finite gradients at ``K = 0``.
    """
    n = _check_square(K, "exp", "K")
    if n == 1:
        return torch.ones_like(K)
    if n == 2:
        t = 0.5 * (K[..., 1, 0] - K[..., 0, 1])
        c, s = torch.cos(t), torch.sin(t)
        return torch.stack((torch.stack((c, -s), -1), torch.stack((s, c), -1)), -2)
    if n == 3:
        return so3.exp(so3.vee(K))
    return torch.linalg.matrix_exp(0.5 * (K - K.transpose(-1, -2)))


def exp_params(params: torch.Tensor, n: int) -> torch.Tensor:
    """``exp(hat(params, n))``: ``params (..., dim(n)) -> (..., n, n)`` rotation."""
    return exp(hat(params, n))


def _polar_sqrt(R: torch.Tensor, iters: int) -> torch.Tensor:
    """Principal square root of a rotation with all angles ``< pi``.

    For a rotation, ``I + R`` has the polar decomposition ``sqrt(R) * (sqrt(R)^T + sqrt(R))``
    whose symmetric factor is positive definite (eigenvalues ``2 cos(t/2) > 0``), so the
    orthogonal polar factor of ``I + R`` *is* ``sqrt(R)``. It is computed by the scaled Newton
    iteration ``X <- (z X + (z X)^{-T}) / 2``, ``z = sqrt(|X^{-1}|_F / |X|_F)`` (Higham),
    a fixed number of times (matmul/inverse only, hence differentiable).
    """
    n = R.shape[-1]
    X = R + torch.eye(n, dtype=R.dtype, device=R.device)
    for _ in range(iters):
        Xi = torch.linalg.inv(X)
        z = torch.sqrt(
            torch.linalg.matrix_norm(Xi) / torch.linalg.matrix_norm(X)
        )[..., None, None]
        X = 0.5 * (z * X + Xi.transpose(-1, -2) / z)
    return X


def _log_iss(R: torch.Tensor, n_sqrt: int = 4, n_series: int = 8) -> torch.Tensor:
    """General-n logarithm by inverse scaling and squaring (see :func:`log`)."""
    n = R.shape[-1]
    eye = torch.eye(n, dtype=R.dtype, device=R.device)
    # first root: angles in [0, pi) -> [0, pi/2), singular values of I+R may be tiny
    # (scaled Newton for these normal matrices converges in <= 8 steps even for pi - 1e-10)
    X = _polar_sqrt(R, iters=10)
    for _ in range(n_sqrt - 1):
        X = _polar_sqrt(X, iters=6)
    # Cayley transform C = (X - I)(X + I)^{-1}, skew with eigenvalues i tan(t/2);
    # log X = 2 atanh(C) = 2 (C + C^3/3 + C^5/5 + ...), |tan(t/2)| <= tan(pi/2^(n_sqrt+1));
    # with 4 roots and 8 terms the truncation is tan(pi/32)^17/17 < 1e-18
    C = torch.linalg.solve(X + eye, X - eye, left=False)
    C2 = C @ C
    term, acc = C, C
    for j in range(1, n_series):
        term = term @ C2
        acc = acc + term / (2 * j + 1)
    L = (2.0 ** (n_sqrt + 1)) * acc
    return 0.5 * (L - L.transpose(-1, -2))


def log(R: torch.Tensor) -> torch.Tensor:
    """Principal logarithm of a rotation: ``R (..., n, n) -> K (..., n, n)`` skew.

    * ``n = 2``: ``t = atan2((R10 - R01)/2, (R00 + R11)/2)``, ``t`` in ``[-pi, pi]``.
    * ``n = 3``: ``so3.hat(so3.log(R))`` (angle in ``[0, pi]``, stable at 0 and pi).
    * ``n >= 4``: inverse scaling and squaring. Four principal square roots, each the
      orthogonal polar factor of ``I + R`` (scaled Newton iteration, see ``_polar_sqrt``),
      bring every rotation angle below ``pi/16``; then ``log = 2^5 atanh(C)`` by its series in
      the Cayley transform ``C = (X - I)(X + I)^{-1}``. Correct for rotations whose angles are
      all ``< pi``; the error grows like ``eps / (pi - t)`` as an angle ``t`` approaches pi.
      Matrices with an angle within ``get_eps("near_pi", dtype)`` of pi (where the logarithm
      is ill-conditioned, and not unique at pi) give NaN, without raising and without
      affecting the other batch elements. Differentiable (only matmul, inverse and solve).

    ``exp(log(R)) == R``; ``log(exp(K)) == K`` for skew ``K`` with all angles ``< pi``.
    For ``n = 3`` the input is validated by :func:`so3.log` (``ValueError`` naming the batch
    index); other ``n`` are not (see :func:`check_rotation`).
    """
    n = _check_square(R, "log")
    if n == 1:
        return torch.zeros_like(R)
    if n == 2:
        t = torch.atan2(0.5 * (R[..., 1, 0] - R[..., 0, 1]), 0.5 * (R[..., 0, 0] + R[..., 1, 1]))
        z = torch.zeros_like(t)
        return torch.stack((torch.stack((z, -t), -1), torch.stack((t, z), -1)), -2)
    if n == 3:
        return so3.hat(so3.log(R))
    return _guard_near_pi(R, _log_iss)


def _guard_near_pi(R: torch.Tensor, fn) -> torch.Tensor:
    """``fn(R)``, with NaN for the matrices having an angle within ``near_pi`` of pi."""
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    with torch.no_grad():
        # the smallest singular value of I + R is 2 cos(t_max / 2) ~ pi - t_max
        margin = torch.linalg.svdvals(R.detach() + eye).amin(-1)
        bad = ~(margin >= get_eps("near_pi", R.dtype))  # also catches NaN input
    # safe-where: iterate on the identity where the input is (too close to) angle pi
    out = fn(torch.where(bad[..., None, None], eye, R))
    return torch.where(bad[..., None, None], torch.full_like(out, float("nan")), out)


def sqrt(R: torch.Tensor) -> torch.Tensor:
    """Principal square root ``exp(log(R)/2)`` of a rotation: ``(..., n, n) -> (..., n, n)``.

    The half transport of report Sec. 3.3 for any rank. ``n = 3``: :func:`so3.sqrt`;
    ``n <= 2``: ``exp(log(R)/2)``; ``n >= 4``: the orthogonal polar factor of ``I + R``
    (``I + R = sqrt(R) (sqrt(R) + sqrt(R)^T)`` with a positive definite second factor when all
    angles are ``< pi``), by a scaled Newton iteration -- cheaper and more accurate than
    ``exp(log(R)/2)``. For ``n >= 4``, matrices with an angle within ``get_eps("near_pi")``
    of pi give NaN (as :func:`log`). ``sqrt(R) @ sqrt(R) == R``. Differentiable.
    """
    n = _check_square(R, "sqrt")
    if n <= 2:
        return exp(0.5 * log(R))
    if n == 3:
        return so3.sqrt(R)
    return _guard_near_pi(R, lambda X: _polar_sqrt(X, iters=10))


def random_rotation(
    *shape: int,
    n: int,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Haar-uniform rotations of shape ``(*shape, n, n)``.

    QR of a Gaussian matrix with the signs of ``diag(R_qr)`` moved into ``Q`` (Haar on O(n)),
    then the first column negated where ``det Q = -1`` (Haar on SO(n) by invariance). All
    randomness goes through ``generator`` (its device must match ``device``).
    """
    if n < 1:
        raise ValueError(f"rank n must be >= 1, got {n}")
    dtype = dtype or torch.get_default_dtype()
    A = torch.randn(*shape, n, n, generator=generator, dtype=dtype, device=device)
    Q, Rq = torch.linalg.qr(A)
    d = Rq.diagonal(dim1=-2, dim2=-1)
    d = torch.where(d < 0, -torch.ones_like(d), torch.ones_like(d))
    Q = Q * d[..., None, :]
    det = torch.linalg.det(Q)
    flip = torch.where(det < 0, -torch.ones_like(det), torch.ones_like(det))
    return torch.cat((Q[..., :1] * flip[..., None, None], Q[..., 1:]), -1)
