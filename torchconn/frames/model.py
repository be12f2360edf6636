"""The matched connection of a frame field and the trainable connection + frames model.

Conventions (docs/conventions.md §1, :mod:`torchconn.frames.loss`): ``edge_rot (E, 3, 3)`` holds ``R_ij``
of the canonical edges ``(i, j)``, ``i < j``, mapping coordinates at ``v_j`` to coordinates at
``v_i``; ``frames[i][:, k]`` is axis ``k`` at vertex ``i``; ``F_j`` is parallel to ``F_i`` along
``(i, j)`` when ``F_j = F_i R_ij``, and cross frames ask for ``F_i R_ij = F_j h_ij``, ``h_ij in O``.
"""
from __future__ import annotations

import torch

from ..nn import ConnectionField
from ..lie import so3
from . import octahedral
from .constraints import BoundaryConstraint
from .param import constrained_frames
from .propagate import comb_frames, propagate_frames, spanning_tree

__all__ = ["matched_connection", "FrameFieldModel", "FORMULATIONS"]

#: Variables of :class:`FrameFieldModel` besides the connection.
FORMULATIONS = ("vertex", "propagate")


def matched_connection(frames: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``R_ij = F_i^T F_j h_ij (E, 3, 3)`` with ``h_ij = argmin_{h in O} ||F_j h - F_i||``.

    ``h_ij = g_ij^T`` for the edge match ``F_i g_ij ~ F_j`` (:func:`octahedral.match_edges`).
    Then ``F_i R_ij = F_j h_ij`` exactly and ``R_ij`` is the residual rotation closest to ``I``.
    ``frames (V, 3, 3)``, ``edges (E, 2)`` long rows ``(i, j)``.
    """
    _, g = octahedral.match_edges(frames, edges)
    Fi, Fj = frames[edges[:, 0]], frames[edges[:, 1]]
    return Fi.transpose(-1, -2) @ Fj @ g.transpose(-1, -2)


class FrameFieldModel(torch.nn.Module):
    """Connection (+ frames) parametrization; ``forward() -> (edge_rot (E,3,3), frames (V,3,3))``.

    The initial cross frames are combed along a BFS spanning tree
    (:func:`~torchconn.frames.propagate.comb_frames`), so that the matched connection is in one
    gauge on the tree (``R_ij ~ I`` there) and face holonomies are near ``I`` on regular faces
    and near a non-identity element of O only around singular curves; the connection
    (:class:`~torchconn.nn.ConnectionField`) starts at :func:`matched_connection`.

    Args:
        mesh: ``TetMesh``.
        init_frames: ``(V, 3, 3)`` initial frames ``F^0``.
        formulation: ``"vertex"``: per-vertex rotation vectors ``w (V, 3)``,
            ``F = exp(hat(w')) F^0`` rotating only about the normal at the aligned boundary
            vertices of ``constraint`` (:mod:`torchconn.frames.param`); ``"propagate"``: one
            root rotation per connected component, ``F`` the parallel propagation of the root
            frames by the connection along the tree (:func:`~torchconn.frames.propagate.propagate_frames`).
        constraint: the mesh's :class:`~torchconn.frames.constraints.BoundaryConstraint`
            (``formulation="vertex"`` only).
    """

    def __init__(self, mesh, init_frames: torch.Tensor, formulation: str, constraint: BoundaryConstraint):
        super().__init__()
        if formulation not in FORMULATIONS:
            raise ValueError(f"unknown formulation {formulation!r}; known: {list(FORMULATIONS)}")
        self.formulation = formulation
        self.tree = spanning_tree(mesh)
        init_frames = comb_frames(init_frames, self.tree)
        R0 = matched_connection(init_frames, mesh.edges)
        self.connection = ConnectionField(mesh.edges, mesh.n_vertices, init=R0)
        self.register_buffer("F0", init_frames.detach().clone())
        if formulation == "vertex":
            self.w = torch.nn.Parameter(torch.zeros_like(init_frames[:, :, 0]))
            self.register_buffer("constrained", constraint.constrained.clone())
            self.register_buffer("normals", constraint.normals.to(init_frames.dtype).clone())
        else:
            self.w = torch.nn.Parameter(init_frames.new_zeros(self.tree.roots.numel(), 3))

    def forward(self) -> tuple[torch.Tensor, torch.Tensor]:
        R = self.connection.edge_rotations()
        if self.formulation == "vertex":
            F = constrained_frames(self.w, self.F0, self.constrained, self.normals)
        else:
            roots = self.tree.roots.to(self.F0.device)
            F = propagate_frames(R, self.tree, so3.exp(self.w) @ self.F0[roots])
        return R, F
