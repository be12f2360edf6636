"""SO(3): rotations as 3x3 matrices, batched over any leading dimensions.

Conventions
-----------
* Rotation matrices act on column vectors: ``y = R @ x``.
* ``hat(omega)`` is the skew matrix with ``hat(omega) @ x == cross(omega, x)``.
* ``exp(omega) = expm(hat(omega))`` (Rodrigues); ``omega`` is the rotation vector
  (axis times angle, right-hand rule).

All functions accept any float dtype and device; constants follow the input.
(Skeleton: exp/hat/vee/random; log/sqrt/angle/euler are completed in the so3 work item.)
"""
from __future__ import annotations

import torch

from .tolerances import get_eps

__all__ = ["hat", "vee", "exp", "random_rotation"]


def hat(omega: torch.Tensor) -> torch.Tensor:
    """Skew matrix of a vector: ``omega (..., 3) -> (..., 3, 3)`` with ``hat(w) x = w x x``."""
    if omega.shape[-1:] != (3,):
        raise ValueError(f"hat expects a tensor of shape (..., 3), got {tuple(omega.shape)}")
    x, y, z = omega.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), -2
    )


def vee(K: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat` on the skew part: ``(..., 3, 3) -> (..., 3)``.

    Uses the antisymmetric part ``(K - K^T)/2``, so it is the projection for non-skew input.
    """
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"vee expects a tensor of shape (..., 3, 3), got {tuple(K.shape)}")
    return 0.5 * torch.stack(
        (K[..., 2, 1] - K[..., 1, 2], K[..., 0, 2] - K[..., 2, 0], K[..., 1, 0] - K[..., 0, 1]), -1
    )


def _exp_coeffs(theta2: torch.Tensor):
    """Return ``A = sin(t)/t`` and ``B = (1-cos t)/t^2`` as functions of ``t^2``, stable at 0."""
    eps = get_eps("small_angle", theta2.dtype)
    small = theta2 < eps * eps
    # safe-where: the unused branch gets a harmless input so its gradient stays finite
    t2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2_safe)
    A_big = torch.sin(t) / t
    B_big = (1.0 - torch.cos(t)) / t2_safe
    A_small = 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0
    B_small = 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0
    return torch.where(small, A_small, A_big), torch.where(small, B_small, B_big)


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula ``exp(hat(omega))``: ``omega (..., 3) -> (..., 3, 3)`` rotation.

    Taylor branches below the dtype's ``small_angle`` threshold keep value and gradient
    finite (and exact to round-off) at ``omega = 0``.
    """
    K = hat(omega)
    theta2 = (omega * omega).sum(-1)
    A, B = _exp_coeffs(theta2)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye + A[..., None, None] * K + B[..., None, None] * (K @ K)


def random_rotation(
    *shape: int,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Uniformly (Haar) distributed rotations of shape ``(*shape, 3, 3)``.

    Drawn from normalized Gaussian quaternions; pass a seeded ``generator`` for
    reproducibility (all randomness goes through it).
    """
    dtype = dtype or torch.get_default_dtype()
    q = torch.randn(*shape, 4, generator=generator, dtype=dtype, device=device)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        (
            torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)), -1),
            torch.stack((2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)), -1),
            torch.stack((2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)), -1),
        ),
        -2,
    )
    return R
