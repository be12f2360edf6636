"""Normal-constrained frame parametrization ``F_i = exp(hat(w_i')) F_i^0``.

A frame field is moved by per-vertex rotation vectors ``w (V, 3)`` (world coordinates, left
multiplication: ``F_i = exp(hat(w_i')) F_i^0`` rotates the axes of ``F_i^0`` about ``w_i'``). At a
constrained vertex (an aligned boundary vertex of :class:`~torchconn.frames.constraints.BoundaryConstraint`)
only the component along the unit normal ``n_i`` acts, ``w_i' = (w_i . n_i) n_i``: the rotation
is about ``n_i``, so an axis of ``F_i^0`` equal to ``±n_i`` stays exactly on ``±n_i`` (for any
``w``; the gradient with respect to ``w_i`` is its projection on ``n_i``). Elsewhere ``w_i' = w_i``.
"""
from __future__ import annotations

import torch

from ..lie import so3

__all__ = ["constrained_rotation_vector", "constrained_frames"]


def constrained_rotation_vector(w: torch.Tensor, constrained: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """``w' (V, 3)``: ``(w_i . n_i) n_i`` where ``constrained (V,) bool``, else ``w_i`` (``w, normals (V, 3)``)."""
    return torch.where(constrained[:, None], (w * normals).sum(-1, keepdim=True) * normals, w)


def constrained_frames(w: torch.Tensor, init_frames: torch.Tensor, constrained: torch.Tensor,
                       normals: torch.Tensor) -> torch.Tensor:
    """``so3.exp(w') @ init_frames`` ``(V, 3, 3)`` with ``w'`` of :func:`constrained_rotation_vector`."""
    return so3.exp(constrained_rotation_vector(w, constrained, normals)) @ init_frames
