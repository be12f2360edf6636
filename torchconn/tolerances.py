"""One registry of per-dtype tolerances and thresholds (STYLE: "one tolerance registry").

Every epsilon, Taylor-branch threshold and identity tolerance used by torchconn comes from
here, keyed by a name and the dtype of the data it applies to, so that float32 and float64
code paths stay consistent and a test can ask for the same number the library uses.

>>> get_eps("identity", torch.float64)
1e-10
"""
from __future__ import annotations

import torch

__all__ = ["get_eps", "TOLERANCES"]

# name -> {dtype: value}
TOLERANCES: dict[str, dict[torch.dtype, float]] = {
    # Angle below which Rodrigues / log use Taylor expansions (|theta| small).
    "small_angle": {torch.float32: 1e-2, torch.float64: 1e-4, torch.float16: 5e-2, torch.bfloat16: 5e-2},
    # Distance to pi within which the general-n log/sqrt (son, n >= 4) is ill-conditioned and
    # returns NaN for that element (so3.log is exact up to pi and does not use it).
    "near_pi": {torch.float32: 1e-2, torch.float64: 1e-5, torch.float16: 5e-2, torch.bfloat16: 5e-2},
    # Tolerance of ||R^T R - I|| and |det R - 1| when validating rotations.
    "rotation": {torch.float32: 1e-4, torch.float64: 1e-9, torch.float16: 1e-2, torch.bfloat16: 2e-2},
    # Exact algebraic identities (differential Bianchi, summability, ...), relative to the
    # scale of the operands (rotations have entries of size 1).
    "identity": {torch.float32: 5e-5, torch.float64: 1e-10, torch.float16: 1e-2, torch.bfloat16: 5e-2},
    # Relative tolerance for geometric degeneracy (zero-volume tets, zero-area faces).
    "degenerate": {torch.float32: 1e-7, torch.float64: 1e-14, torch.float16: 1e-3, torch.bfloat16: 1e-2},
}


def get_eps(name: str, dtype: torch.dtype) -> float:
    """Return the tolerance ``name`` for ``dtype``.

    Args:
        name: one of the keys of :data:`TOLERANCES`.
        dtype: a floating torch dtype.

    Raises:
        KeyError: unknown name (the message lists the known ones).
    """
    try:
        table = TOLERANCES[name]
    except KeyError:
        raise KeyError(f"unknown tolerance {name!r}; known: {sorted(TOLERANCES)}") from None
    if dtype not in table:
        raise KeyError(f"tolerance {name!r} has no value for dtype {dtype}; known: {list(table)}")
    return table[dtype]
