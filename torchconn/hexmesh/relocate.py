"""Relocation: the singular arcs moved onto their axes by a solve over the vertex positions.

The singular graph lives on mesh edges, and an edge of a singular arc seldom runs along the frame
axis it turns about: a tet mesh made without the field offers no better edge. The map must then
lay the edge on its integer line along that axis anyway, and the tets and the hexes around it
pay with distortion. Locally Meshable Frame Fields (Liu & Bommes 2023) relocates the singular
vertices before the map; this is that step, as one smooth solve with the matchings, the tets and
their frames unchanged (on the 35 HexMe ``c`` models: the same verdicts, the good hex meshes'
smallest scaled Jacobian up on 10 of 13; docs/results/hexmesh.md)::

    min over x   sum_t vol_t (SD(J_t) - 6) / sum_t vol_t  +  w / n_arc * sum_e |P_e (x_b - x_a)|^2 / l_e^2

* ``J_t`` the Jacobian of the tet's deformation from its input shape, ``SD(J) = |J|^2 + |J^-1|^2``
  its symmetric Dirichlet energy (6 at a rotation, +inf as the tet flattens: no tet
  inverts, the line search never crosses ``det J = 0``);
* ``e = (a, b)`` the interior singular edges of meshable turns, ``P_e = I - d d^T`` for the world
  direction ``d`` of the edge's turn axis (the axis column of its start tet's frame), ``l_e`` the
  edge's input length: the part of the edge across its axis, squared. An edge stays on its side
  of the axis (``(x_b - x_a) . d`` keeps its sign, a constraint of the line search): the hex
  count of a quarter turn, 3 or 5, is read from that sign (:mod:`.cut`), and an edge nearly
  across its axis that turned over would flip it (HexMe n10c: three such edges made five zipper
  nodes before this constraint);
* the unknowns are the vertices within ``rings`` vertex rings of the arcs; an interior vertex moves
  freely, a boundary vertex within its face where the face is planar, a vertex of a straight
  feature curve along the curve; CAD corners, vertices of curved faces or curves, and the
  vertices outside the rings stay. So the domain, its CAD surfaces, curves and corners, and every
  tag are kept exactly.

Solved by L-BFGS with a backtracking line search that keeps every tet positive. The relocated
mesh has the input's topology, CAD tags and (per tet) frames, so matchings and the singular
graph carry over unchanged.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from .distance import FLAT_NORMAL_TOL as _FLAT  # unit normals (curve edges) this close: one plane (line)

__all__ = ["relocate_singular_vertices", "Relocation", "RELOCATE_WEIGHT"]

RELOCATE_WEIGHT = 10.0
"""Weight ``w`` of the arcs' alignment against the tets' distortion (module docstring): of 3, 10,
30 and 100 on the SH fields of ten good HexMe models, the one that kept every hex mesh good with
the highest minimum scaled Jacobians (docs/results/hexmesh.md)."""


@dataclass
class Relocation:
    """What :func:`relocate_singular_vertices` did: ``arcs`` (the singular edges aligned),
    ``moved`` vertices (count), ``free_dofs``, the across part of the arcs before and after (``misalignment_before`` / ``_after``: the mean
    of ``|P_e (x_b - x_a)| / l_e``, the sine of the edge's angle to its axis), the energy
    ``before``/``after``, ``iterations``, ``max_move_rel`` (largest displacement over the mean
    edge length), ``seconds``."""

    moved: int = 0
    free_dofs: int = 0
    arcs: int = 0
    misalignment_before: float = 0.0
    misalignment_after: float = 0.0
    energy_before: float = 0.0
    energy_after: float = 0.0
    iterations: int = 0
    max_move_rel: float = 0.0
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("moved", "free_dofs", "arcs", "misalignment_before",
                                               "misalignment_after", "energy_before", "energy_after",
                                               "iterations", "max_move_rel", "seconds")}


def _vertex_bases(mesh, X: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(dofs (V,), basis (V, 3, 3))``: per vertex the number of free directions (3 interior,
    2 on a planar face, 1 on a straight feature curve, 0 else) and those directions as the first
    columns of ``basis``; only vertices of ``free`` get any."""
    from ..frames.constraints import BoundaryConstraint

    V = X.shape[0]
    dofs = np.zeros(V, np.int64)
    basis = np.zeros((V, 3, 3))
    basis[:] = np.eye(3)
    on_b = np.zeros(V, bool)
    on_b[mesh.boundary_vertices.cpu().numpy()] = True
    dofs[free & ~on_b] = 3
    bf = mesh.boundary_faces.cpu().numpy()
    n = np.cross(X[bf[:, 1]] - X[bf[:, 0]], X[bf[:, 2]] - X[bf[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    bc = BoundaryConstraint.from_mesh(mesh)
    fe = bc.feature_edges.cpu().numpy() if bc.feature_edges is not None else np.zeros((0, 2), np.int64)
    corner = np.zeros(V, bool)
    if bc.corner_vertices is not None:
        corner[bc.corner_vertices.cpu().numpy()] = True
    fdeg = np.bincount(fe.reshape(-1), minlength=V)
    cad = mesh.cad
    if cad is not None:
        corner[cad.corner_vertices.cpu().numpy()] = True
    for v in np.flatnonzero(free & on_b).tolist():  # loop over the boundary vertices near the arcs
        if corner[v] or fdeg[v] not in (0, 2):
            continue
        if fdeg[v] == 2:
            ends = fe[(fe == v).any(1)]
            o = np.where(ends[:, 0] == v, ends[:, 1], ends[:, 0])
            d0, d1 = X[o[0]] - X[v], X[o[1]] - X[v]
            d0, d1 = d0 / np.linalg.norm(d0), d1 / np.linalg.norm(d1)
            if np.linalg.norm(np.cross(d0, d1)) < _FLAT and d0 @ d1 < 0:
                dofs[v] = 1
                basis[v, :, 0] = d0
            continue
        nv = n[(bf == v).any(1)]
        if np.linalg.norm(np.cross(nv, nv[0]), axis=1).max() < _FLAT:
            dofs[v] = 2
            t = np.linalg.svd(np.eye(3) - np.outer(nv[0], nv[0]))[0]
            basis[v, :, :2] = t[:, :2]
    return dofs, basis


def _sd_energy(Y, tets, Dinv, vol):
    """``sum_t vol_t (SD(J_t) - 6) / sum vol`` (torch), or ``None`` where a tet is flat or inverted."""
    P = Y[tets]
    D = torch.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], -1)
    J = D @ Dinv
    if not bool((torch.linalg.det(J) > 0).all()):
        return None
    inv = torch.linalg.inv(J)
    sd = J.square().sum((-1, -2)) + inv.square().sum((-1, -2)) - 6.0
    return (vol * sd).sum() / vol.sum()


def relocate_singular_vertices(mesh, charts, *, rings: int = 2, weight: float = RELOCATE_WEIGHT,
                               iterations: int = 200, tol: float = 1e-9):
    """The mesh with its singular vertices relocated onto their arcs' axes (module docstring).

    Args:
        mesh: a ``TetMesh`` (float64 CPU).
        charts: :func:`~.cut.tet_charts` of the field on ``mesh`` (its combed frames, the edges'
            turn axes and start tets).
        rings: the vertex rings around the arcs' vertices that move with them.
        weight: ``w`` (:data:`RELOCATE_WEIGHT`).
        iterations: L-BFGS iterations at most; ``tol``: stop when the energy drops by less than
            this (relative) over an iteration.

    Returns:
        ``(mesh, Relocation)``: a new ``TetMesh`` (same tets, faces, edges, CAD tags; moved
        vertices) or the input itself when there is no arc or nothing may move.
    """
    from ..mesh import TetMesh

    t0 = time.perf_counter()
    X = mesh.vertices.detach().cpu().double().numpy()
    tets = mesh.tets.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    arc = np.asarray(charts.singular_edge & charts.edge_meshable & (charts.edge_axis >= 0))
    out = Relocation()
    if not arc.any():
        out.seconds = time.perf_counter() - t0
        return mesh, out
    ea = np.flatnonzero(arc)
    axis = charts.frames[charts.edge_start_tet[ea], :, charts.edge_axis[ea]]  # (n, 3) world directions
    near = np.zeros(X.shape[0], bool)
    near[edges[ea].reshape(-1)] = True
    for _ in range(rings):  # loop over the rings
        near[edges[near[edges].any(1)].reshape(-1)] = True
    dofs, basis = _vertex_bases(mesh, X, near)
    mv = np.flatnonzero(dofs > 0)
    out.arcs = int(ea.size)
    if not mv.size:
        out.seconds = time.perf_counter() - t0
        return mesh, out
    # the unknowns: per moving vertex its free directions
    cols = [(v, k) for v in mv.tolist() for k in range(dofs[v])]
    vi = torch.as_tensor([c[0] for c in cols])
    Bdir = torch.as_tensor(np.stack([basis[v, :, k] for v, k in cols]))  # (n_dof, 3)
    ttouch = np.flatnonzero(near[tets].any(1) & (dofs[tets] > 0).any(1))
    T_ = torch.as_tensor(tets[ttouch])
    X0 = torch.as_tensor(X)
    P0 = X0[T_]
    D0 = torch.stack([P0[:, 1] - P0[:, 0], P0[:, 2] - P0[:, 0], P0[:, 3] - P0[:, 0]], -1)
    Dinv = torch.linalg.inv(D0)
    vol = torch.linalg.det(D0).abs() / 6.0
    Ea = torch.as_tensor(edges[ea])
    dax = torch.as_tensor(axis / np.linalg.norm(axis, axis=1, keepdims=True))
    w = float(weight) / ea.size

    def positions(z):
        return X0.index_add(0, vi, Bdir * z[:, None])

    def arcs(Y):  # the arc edges' vectors and their parts along their axes
        d = Y[Ea[:, 1]] - Y[Ea[:, 0]]
        return d, (d * dax).sum(1, keepdim=True)

    def across_sq(d, along):  # |P_e d_e|^2 / l_e^2 (squared: a smooth term, finite gradient on the axis)
        return (d - along * dax).square().sum(1) / l0.square()

    d0, along0 = arcs(X0)
    l0 = d0.norm(dim=1)
    # the side of its axis each edge runs to: its hex count (3 or 5) is read from that sign
    # (an edge exactly across its axis has no side and is not held to one)
    side = torch.sign(along0[:, 0])
    sided = side != 0

    def energy(z):
        Y = positions(z)
        d, along = arcs(Y)
        if not bool((along[:, 0] * side > 0)[sided].all()):
            return None  # an edge would turn to the other side of its axis: its class would flip
        sd = _sd_energy(Y, T_, Dinv, vol)
        if sd is None:
            return None
        return sd + w * across_sq(d, along).sum()

    z = torch.zeros(len(cols), dtype=torch.float64, requires_grad=True)
    f = energy(z)
    # (finite: J = I at the start, every tet of a TetMesh positive, every sided edge on its side)
    out.energy_before = float(f.detach())
    out.misalignment_before = float(across_sq(d0, along0).sqrt().mean())
    g, = torch.autograd.grad(f, z)
    S, Yh = [], []
    it = 0
    for it in range(1, iterations + 1):  # L-BFGS iterations
        q = -g.clone()
        alphas = []
        for s, y in reversed(list(zip(S, Yh))):
            a = (s @ q) / (y @ s)
            alphas.append(a)
            q -= a * y
        if S:
            q *= (S[-1] @ Yh[-1]) / (Yh[-1] @ Yh[-1])
        for (s, y), a in zip(zip(S, Yh), reversed(alphas)):
            b = (y @ q) / (y @ s)
            q += (a - b) * s
        if (q @ g) >= 0:  # not a descent direction: restart from the gradient
            q, S, Yh = -g, [], []
        step, fn = 1.0, None
        for _ in range(40):  # backtracking: finite (no tet at or past det 0) and Armijo
            # each trial keeps its graph: the accepted one's gives the gradient (no second evaluation)
            zn = (z + step * q).detach().requires_grad_(True)
            fn = energy(zn)
            if fn is not None and fn <= f + 1e-4 * step * (q @ g):
                break
            step *= 0.5
        else:
            fn = None
        if fn is None:
            break
        gn, = torch.autograd.grad(fn, zn)
        s_, y_ = (zn - z).detach(), (gn - g).detach()
        if (s_ @ y_) > 1e-300:
            S.append(s_)
            Yh.append(y_)
            if len(S) > 10:
                S.pop(0)
                Yh.pop(0)
        drop = float((f - fn).detach())
        z, f, g = zn, fn.detach(), gn
        if drop <= tol * max(abs(float(f)), 1e-12):
            break
    with torch.no_grad():
        Y = positions(z.detach())
    out.iterations = it
    out.energy_after = float(f.detach())
    out.misalignment_after = float(across_sq(*arcs(Y)).sqrt().mean())
    disp = (Y - X0).norm(dim=1)
    out.moved = int((disp > 0).sum())
    out.free_dofs = len(cols)
    mean_len = float(np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1).mean())
    out.max_move_rel = float(disp.max()) / mean_len
    new = TetMesh(Y.to(mesh.vertices.dtype), mesh.tets.cpu(), dtype=mesh.vertices.dtype)
    if not (torch.equal(new.tets.cpu(), mesh.tets.cpu()) and torch.equal(new.faces.cpu(), mesh.faces.cpu())
            and torch.equal(new.edges.cpu(), mesh.edges.cpu())):
        raise RuntimeError("relocation changed the mesh's numbering")  # same tets: cannot happen
    if mesh.cad is not None:
        new.cad = mesh.cad
    out.seconds = time.perf_counter() - t0
    return new, out
