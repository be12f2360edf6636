"""Frames from a connection: parallel propagation along a BFS spanning tree of the vertex graph.

Convention (docs/conventions.md §1): ``R_ij`` maps the coordinates of a vector at ``v_j`` to the
coordinates of its parallel transport at ``v_i``. A frame ``F (3, 3)`` has its axes as columns
in world coordinates (``F[:, k]`` is axis ``k``). Coordinates ``X`` at ``j`` describe the world
vector ``F_j X``; the same vector has coordinates ``R_ij X`` at ``i``, i.e. the world vector
``F_i R_ij X``. A frame at ``j`` that is parallel to ``F_i`` under the connection therefore is

    ``F_j = F_i R_ij``      (``i`` the parent, ``j`` the child of a tree edge),

and conversely ``R_ij = F_i^T F_j`` for frames that are exactly parallel along the edge.

The tree is combinatorics (built once, integer buffers, never differentiated); the propagation
is differentiable in ``edge_rot`` and ``root_frames``. It loops over BFS *levels* (the tree
depth, a few tens for the meshes we use), never over vertices.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components, shortest_path

from ..dec.transport import orient

__all__ = ["TreeLevel", "SpanningTree", "spanning_tree", "propagate_frames", "comb_frames"]


@dataclass
class TreeLevel:
    """One BFS level: vertices at depth ``d >= 1`` and the tree edges to their parents.

    Attributes:
        child: ``(n,)`` long, vertices of this level.
        parent: ``(n,)`` long, their parents (depth ``d - 1``).
        parent_pos: ``(n,)`` long, position of each parent in the previous level's ``child``
            (for level 1: position in ``SpanningTree.roots``).
        edge: ``(n,)`` long, canonical edge id of ``{parent, child}``.
        sign: ``(n,)`` long, ``+1`` if the edge is stored as ``(parent, child)`` (then the
            transport ``R_{parent, child}`` is ``edge_rot[edge]``), ``-1`` otherwise (transpose).
    """

    child: torch.Tensor
    parent: torch.Tensor
    parent_pos: torch.Tensor
    edge: torch.Tensor
    sign: torch.Tensor

    def to(self, device) -> "TreeLevel":
        return TreeLevel(*(getattr(self, k).to(device) for k in ("child", "parent", "parent_pos", "edge", "sign")))


@dataclass
class SpanningTree:
    """BFS spanning forest of a vertex graph, one tree per connected component.

    Attributes:
        roots: ``(C,)`` long, one root per component (level 0).
        levels: ``TreeLevel`` for depths ``1, 2, ...``.
        parent: ``(V,)`` long, parent vertex (``-1`` at roots).
        depth: ``(V,)`` long, hop distance to the root of the component.
        tree_edge: ``(E,)`` bool, edges used by the tree.
        order: ``(V,)`` long, vertices in propagation order (roots, then level 1, 2, ...).
    """

    roots: torch.Tensor
    levels: list
    parent: torch.Tensor
    depth: torch.Tensor
    tree_edge: torch.Tensor
    order: torch.Tensor

    @property
    def n_vertices(self) -> int:
        return int(self.parent.numel())

    def to(self, device) -> "SpanningTree":
        return SpanningTree(self.roots.to(device), [lv.to(device) for lv in self.levels], self.parent.to(device),
                            self.depth.to(device), self.tree_edge.to(device), self.order.to(device))


def spanning_tree(mesh=None, *, edges: torch.Tensor | None = None, n_vertices: int | None = None,
                  roots=None) -> SpanningTree:
    """BFS spanning forest of the vertex graph, grouped by level.

    Args:
        mesh: a ``TetMesh`` (uses ``edges``, ``vertices``); or pass ``edges`` and ``n_vertices``.
        edges: ``(E, 2)`` long canonical edges ``i < j`` (sorted rows, as ``TetMesh.edges``).
        n_vertices: ``V``.
        roots: optional one root vertex per connected component (any order). Default: in each
            component the vertex closest to the component's centroid when a mesh is given (a
            central root keeps the tree shallow), else its lowest index.

    Returns:
        :class:`SpanningTree`. Parents are shortest-path (BFS) predecessors, so every tree path
        is a shortest edge path to the root.

    Raises:
        ValueError: bad shapes, indices out of range, or ``roots`` not one per component.
    """
    if mesh is not None:
        edges, n_vertices = mesh.edges, mesh.n_vertices
        pos = mesh.vertices.detach().cpu().numpy()
    else:
        pos = None
    if edges is None or n_vertices is None:
        raise ValueError("spanning_tree needs a mesh or both edges and n_vertices")
    if edges.dim() != 2 or edges.shape[1] != 2:
        raise ValueError(f"edges must have shape (E, 2), got {tuple(edges.shape)}")
    device = edges.device
    e = edges.detach().cpu().numpy().astype(np.int64)
    V = int(n_vertices)
    if e.size and (e.min() < 0 or e.max() >= V):
        raise ValueError(f"edges refer to vertices outside [0, {V})")
    if e.size and not (e[:, 0] < e[:, 1]).all():
        raise ValueError("edges must be canonical (edges[:, 0] < edges[:, 1])")
    E = e.shape[0]
    A = sp.coo_matrix((np.ones(E), (e[:, 0], e[:, 1])), shape=(V, V)).tocsr()
    A = A + A.T
    n_comp, label = connected_components(A, directed=False)

    if roots is None:
        root_list = []
        for c in range(n_comp):  # loop over connected components (few), not vertices
            members = np.nonzero(label == c)[0]
            if pos is not None:
                d = ((pos[members] - pos[members].mean(0)) ** 2).sum(1)
                root_list.append(int(members[np.argmin(d)]))
            else:
                root_list.append(int(members[0]))
        root_arr = np.asarray(root_list, dtype=np.int64)
    else:
        root_arr = np.asarray(torch.as_tensor(roots).cpu().numpy(), dtype=np.int64).reshape(-1)
        if root_arr.size and (root_arr.min() < 0 or root_arr.max() >= V):
            raise ValueError(f"roots outside [0, {V}): {root_arr.tolist()}")
        if root_arr.size != n_comp or np.unique(label[root_arr]).size != n_comp:
            raise ValueError(f"need exactly one root per connected component ({n_comp} components), got {root_arr.tolist()}")

    dist, pred = shortest_path(A, unweighted=True, directed=False, indices=root_arr, return_predecessors=True)
    dist = np.atleast_2d(dist)
    pred = np.atleast_2d(pred)
    comp_of_root = label[root_arr]
    row = np.searchsorted(np.sort(comp_of_root), label)  # which root serves each vertex
    row = np.argsort(comp_of_root)[row]
    depth = dist[row, np.arange(V)].astype(np.int64)
    parent = pred[row, np.arange(V)].astype(np.int64)
    parent[root_arr] = -1

    # canonical edge ids of the tree edges (parent, child) by key lookup
    keys = e[:, 0] * V + e[:, 1]
    nonroot = np.nonzero(parent >= 0)[0]
    lo = np.minimum(parent[nonroot], nonroot)
    hi = np.maximum(parent[nonroot], nonroot)
    eid_nonroot = np.searchsorted(keys, lo * V + hi)
    if nonroot.size and not (keys[np.clip(eid_nonroot, 0, E - 1)] == lo * V + hi).all():
        raise ValueError("edges are not sorted lexicographically (as TetMesh.edges)")
    eid = np.full(V, -1, dtype=np.int64)
    eid[nonroot] = eid_nonroot
    tree_edge = np.zeros(E, dtype=bool)
    tree_edge[eid_nonroot] = True

    # group by depth; position of each vertex within its level
    order = np.lexsort((np.arange(V), depth))
    d_sorted = depth[order]
    max_d = int(d_sorted[-1]) if V else 0
    starts = np.searchsorted(d_sorted, np.arange(max_d + 2))
    pos_in_level = np.empty(V, dtype=np.int64)
    pos_in_level[order] = np.arange(V) - starts[d_sorted]
    if not np.array_equal(np.sort(order[: starts[1]]), np.sort(root_arr)):
        raise ValueError("internal error: level 0 is not the set of roots")
    # roots in level 0 appear in ascending vertex order; re-express roots in that order
    roots_sorted = order[: starts[1]]
    T = lambda a: torch.as_tensor(a, dtype=torch.long, device=device)  # noqa: E731
    levels = []
    for d in range(1, max_d + 1):  # loop over BFS levels only
        child = order[starts[d]: starts[d + 1]]
        par = parent[child]
        levels.append(TreeLevel(T(child), T(par), T(pos_in_level[par]), T(eid[child]),
                                T(np.where(par < child, 1, -1))))
    return SpanningTree(T(roots_sorted), levels, T(parent), T(depth), torch.as_tensor(tree_edge, device=device),
                        T(order))


def propagate_frames(edge_rot: torch.Tensor, tree: SpanningTree, root_frames: torch.Tensor) -> torch.Tensor:
    """Parallel-propagate root frames through the tree: ``F_child = F_parent R_{parent,child}``.

    Args:
        edge_rot: ``(E, 3, 3)`` rotations ``R_ij`` of the canonical edges (``i < j``).
        tree: from :func:`spanning_tree` on the same edges.
        root_frames: ``(C, 3, 3)`` frames at ``tree.roots`` (same order), or ``(3, 3)`` for a
            single component.

    Returns:
        ``(V, 3, 3)`` frames; ``frames[i][:, k]`` is axis ``k`` at vertex ``i`` in world coords.
        For every tree edge ``frames[child] == frames[parent] @ R_{parent,child}`` (to round-off).
        Differentiable in ``edge_rot`` and ``root_frames``; rotations in, rotations out.
    """
    if edge_rot.dim() != 3 or edge_rot.shape[-2:] != (3, 3):
        raise ValueError(f"edge_rot must have shape (E, 3, 3), got {tuple(edge_rot.shape)}")
    if root_frames.dim() == 2:
        root_frames = root_frames[None]
    C = int(tree.roots.numel())
    if root_frames.shape != (C, 3, 3):
        raise ValueError(f"root_frames must have shape ({C}, 3, 3) (one per tree root), got {tuple(root_frames.shape)}")
    blocks = [root_frames.to(edge_rot.dtype)]
    for lv in tree.levels:
        R = orient(edge_rot, lv.edge, lv.sign)  # R_{parent, child}
        blocks.append(blocks[-1][lv.parent_pos] @ R)
    F_sorted = torch.cat(blocks, 0)
    inv = torch.empty_like(tree.order)
    inv[tree.order] = torch.arange(tree.order.numel(), device=tree.order.device)
    return F_sorted[inv]


def comb_frames(frames: torch.Tensor, tree: SpanningTree) -> torch.Tensor:
    """Relabel cross frames along the tree so that every tree edge matches without relabeling.

    Each frame ``F_v`` is replaced by ``F_v g_v`` with ``g_v in O`` (the same octahedral frame,
    other axis labels), level by level from the roots: ``g_child`` is the best match of the
    child onto its (already combed) parent, ``octahedral.match(F_child, F_parent)``. Afterwards
    ``octahedral.match(F_parent, F_child)`` is the identity on every tree edge (up to exact ties),
    so a connection ``R_ij = F_i^T F_j`` is close to ``I`` there; label jumps remain only on
    non-tree edges (around singular curves and across the cut of their monodromy).

    Args:
        frames: ``(V, 3, 3)``; tree: :func:`spanning_tree` of the same mesh.

    Returns:
        ``(V, 3, 3)`` relabeled frames (no gradient through the discrete choice).
    """
    from .octahedral import match

    if frames.dim() != 3 or frames.shape[1:] != (3, 3) or frames.shape[0] != tree.n_vertices:
        raise ValueError(f"frames must have shape ({tree.n_vertices}, 3, 3), got {tuple(frames.shape)}")
    blocks = [frames[tree.roots]]
    for lv in tree.levels:  # loop over BFS levels only
        child = frames[lv.child]
        _, g = match(child, blocks[-1][lv.parent_pos])
        blocks.append(child @ g)
    F_sorted = torch.cat(blocks, 0)
    inv = torch.empty_like(tree.order)
    inv[tree.order] = torch.arange(tree.order.numel(), device=tree.order.device)
    return F_sorted[inv]
