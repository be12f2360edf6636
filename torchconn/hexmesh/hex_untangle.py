"""Untangling the interior of an extracted hex mesh: move interior vertices, raise the worst scaled Jacobian.

The hexes of a valid map are the images of unit cubes under a piecewise-linear map; the hex with
straight edges through the images of the cube's corners can still fold where the map bends
strongly inside one cube (a valid map gave hexes of scaled Jacobian -0.6 on HexMe s04). The
remedy of the hex-meshing pipelines is a local optimization of the vertex positions. Here only
**interior** vertices move (boundary vertices, hence the boundary, the Hausdorff distance and
the features meshed, are kept exactly), and only those of the hexes below the target and one ring
of hexes around them (every other term is zero and stays so): L-BFGS on::

    E(x) = sum_{hexes, 9 samples} relu(target - J)^2 + reg * sum_interior |x - x0|^2 / h^2

with ``J`` the determinant of the unit edge vectors at each corner and at the centre (the nine
values whose minimum is Verdict's scaled Jacobian, :func:`~.quality.scaled_jacobian`) and ``h``
the mean hex edge length. The result is kept only if the minimum scaled Jacobian rose; otherwise
the input is returned unchanged.
"""
from __future__ import annotations

import numpy as np
import torch

from .quality import scaled_jacobian

__all__ = ["untangle", "corner_jacobians", "UNTANGLE_PASSES"]

#: Solves of :func:`untangle` at most. On s17c's first connection field (one thread, 2026-11-28)
#: one solve left a hex at scaled Jacobian -0.042 where a second reached 0.297 and a third 0.300
#: (docs/results/hexmesh.md).
UNTANGLE_PASSES = 4

# the three edges at each corner of a VTK hexahedron, positively oriented
_CORNER_EDGES = ((1, 3, 4), (2, 0, 5), (3, 1, 6), (0, 2, 7), (7, 5, 0), (4, 6, 1), (5, 7, 2), (6, 4, 3))


def corner_jacobians(P: torch.Tensor, hexes: torch.Tensor) -> torch.Tensor:
    """``(H, 9)``: the determinant of the unit edge vectors at the 8 corners and of the unit
    principal axes at the centre of each hex (Verdict's scaled-Jacobian samples)."""
    X = P[hexes]  # (H, 8, 3)
    out = []
    for c, (a, b, d) in enumerate(_CORNER_EDGES):
        e = torch.stack([X[:, a] - X[:, c], X[:, b] - X[:, c], X[:, d] - X[:, c]], 1)
        e = e / e.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        out.append(torch.linalg.det(e))
    x1 = (X[:, 1] + X[:, 2] + X[:, 5] + X[:, 6]) - (X[:, 0] + X[:, 3] + X[:, 4] + X[:, 7])
    x2 = (X[:, 2] + X[:, 3] + X[:, 6] + X[:, 7]) - (X[:, 0] + X[:, 1] + X[:, 4] + X[:, 5])
    x3 = (X[:, 4] + X[:, 5] + X[:, 6] + X[:, 7]) - (X[:, 0] + X[:, 1] + X[:, 2] + X[:, 3])
    e = torch.stack([x1, x2, x3], 1)
    e = e / e.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    out.append(torch.linalg.det(e))
    return torch.stack(out, 1)


def untangle(points: np.ndarray, hexes: np.ndarray, boundary_vertices: np.ndarray, *, target: float = 0.3,
             reg: float = 1e-3, iters: int = 200, surface=None, sharp_deg: float = 30.0,
             slide: float = 100.0, passes: int = UNTANGLE_PASSES) -> tuple[np.ndarray, dict]:
    """Move the vertices to raise the worst scaled Jacobian (module docstring), in ``passes``
    solves at most: each frees the vertices of the hexes then below the target (a solve can push
    hexes outside its free set below it) and the next runs while the minimum rose and is still
    below the target.

    Args:
        points: ``(N, 3)``; hexes: ``(H, 8)`` VTK order; boundary_vertices: the hex mesh's
            boundary vertices (fixed without ``surface``).
        target: scaled Jacobian below which a sample is penalized.
        reg: weight of staying near the extracted positions.
        iters: L-BFGS iterations per solve.
        surface: ``(vertices (Vs, 3), triangles (Fs, 3))`` the input boundary: boundary vertices
            whose incident boundary quads turn by less than ``sharp_deg`` slide and are projected
            back onto it.
        slide: weight of the normal motion of sliding vertices.
        passes: solves at most (:data:`UNTANGLE_PASSES`).

    Returns:
        ``(points, info)``: ``info`` has ``sj_min_before`` (the input's), ``sj_min_after``,
        ``moved`` (the most vertices one solve moved), ``accepted`` (some solve raised the
        minimum: otherwise the input is returned unchanged) and ``passes`` (the solves kept).
    """
    P = np.asarray(points)
    info = None
    kept = 0
    for _ in range(max(int(passes), 1)):
        P, step = _untangle_once(P, hexes, boundary_vertices, target=target, reg=reg, iters=iters, surface=surface,
                                 sharp_deg=sharp_deg, slide=slide)
        if info is None:
            info = dict(step)
        if not step["accepted"]:
            break
        kept += 1
        info.update(sj_min_after=step["sj_min_after"], accepted=True, moved=max(info["moved"], step["moved"]),
                    boundary_moved=max(info.get("boundary_moved", 0), step.get("boundary_moved", 0)))
        if step["sj_min_after"] >= target:
            break
    info["passes"] = kept
    return P, info


def _untangle_once(points: np.ndarray, hexes: np.ndarray, boundary_vertices: np.ndarray, *, target: float,
                   reg: float, iters: int, surface, sharp_deg: float, slide: float) -> tuple[np.ndarray, dict]:
    """One solve of :func:`untangle` (its arguments): ``(points, info)``, the input unchanged and
    ``accepted`` false unless the minimum scaled Jacobian rose."""
    P0 = torch.as_tensor(np.asarray(points, dtype=np.float64))
    H = torch.as_tensor(np.asarray(hexes, dtype=np.int64))
    before = float(scaled_jacobian(points, hexes).min()) if len(hexes) else float("nan")
    info = {"sj_min_before": before, "sj_min_after": before, "moved": 0, "accepted": False}
    if not len(hexes):
        return np.asarray(points), info
    fixed = np.zeros(P0.shape[0], bool)
    bvs = np.asarray(boundary_vertices, np.int64)
    fixed[bvs] = True
    normals = None
    if surface is not None and bvs.size:
        from .quality import boundary_quads_of

        q = boundary_quads_of(hexes)
        Pq = np.asarray(points, dtype=np.float64)[q]
        qn = np.cross(Pq[:, 2] - Pq[:, 0], Pq[:, 3] - Pq[:, 1])
        qn /= np.linalg.norm(qn, axis=1, keepdims=True).clip(1e-300)
        nv = np.zeros((P0.shape[0], 3))
        np.add.at(nv, q.reshape(-1), np.repeat(qn, 4, axis=0))
        nv /= np.linalg.norm(nv, axis=1, keepdims=True).clip(1e-300)
        # sharp: some incident quad normal farther than sharp_deg from the vertex normal
        cos = np.einsum("qi,qi->q", np.repeat(qn, 4, axis=0), nv[q.reshape(-1)])
        worst = np.ones(P0.shape[0])
        np.minimum.at(worst, q.reshape(-1), cos)
        slides = bvs[worst[bvs] >= np.cos(np.radians(sharp_deg))]
        fixed[slides] = False
        normals = torch.as_tensor(nv)
    if before >= target:
        return np.asarray(points), info
    # only the hexes below the target and a ring of vertices around them move: every other hex's
    # term is zero and stays so while none of its vertices moves (the energy restricted to these
    # unknowns is the full energy up to a constant)
    hx = np.asarray(hexes, np.int64)
    with torch.no_grad():
        low = (corner_jacobians(P0, H) < target).any(1).numpy()
    near = np.zeros(P0.shape[0], bool)
    near[hx[low].reshape(-1)] = True
    near[hx[near[hx].any(1)].reshape(-1)] = True  # one ring of hexes further
    free = np.nonzero(~fixed & near)[0]
    if not free.size:
        return np.asarray(points), info
    edges = torch.stack([H[:, [0, 1, 2, 3, 4, 5, 6, 7, 0, 1, 2, 3]], H[:, [1, 2, 3, 0, 5, 6, 7, 4, 4, 5, 6, 7]]], -1)
    h = float((P0[edges[..., 0]] - P0[edges[..., 1]]).norm(dim=-1).mean())
    active = np.nonzero(np.isin(hx, free).any(1))[0]
    H = H[torch.as_tensor(active)]
    free_t = torch.as_tensor(free)
    on_b = np.zeros(P0.shape[0], bool)
    on_b[bvs] = True
    bfree = torch.as_tensor(on_b[free])
    x = P0[free_t].clone().requires_grad_(True)
    opt = torch.optim.LBFGS([x], lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        P = P0.index_put((free_t,), x)
        J = corner_jacobians(P, H)
        d = x - P0[free_t]
        e = torch.relu(target - J).pow(2).sum() + reg * (d**2).sum() / (h * h)
        if normals is not None and bool(bfree.any()):
            dn = (d[bfree] * normals[free_t][bfree]).sum(-1)
            e = e + slide * (dn**2).sum() / (h * h)
        e.backward()
        return e

    opt.step(closure)
    P = P0.index_put((free_t,), x.detach()).numpy()
    if normals is not None and bool(bfree.any()):  # back onto the input surface
        import igl

        Vs, Fs = (np.asarray(a) for a in surface)
        ids = free[bfree.numpy()]
        _, _, C = igl.point_mesh_squared_distance(P[ids], np.ascontiguousarray(Vs, dtype=np.float64),
                                                  np.ascontiguousarray(Fs, dtype=np.int64))
        P[ids] = C
    after = float(scaled_jacobian(P, hexes).min())
    if after > before:
        info.update(sj_min_after=after, moved=int(free.size), accepted=True,
                    boundary_moved=int(bfree.sum()))
        return P, info
    return np.asarray(points), info
