"""LMFF's local meshability conditions on the edge-based singular graph (torchconn.hexmesh.meshability)
and their repair by the straightening search (torchconn.hexmesh.straighten), on constructed cases.

* the box with the identity field: meshable; its 8 corners are nodes, its 12 feature curves arcs;
* the axis prism with a +-90 / +-180 degree turn about its axis: hex counts 3, 5, 2, 6 on the
  chain, meshable but for the valence-2 chain ending on flat faces (invalid nodes);
* a 120-degree turn about a diagonal: complex edges;
* the prism's field turned 50 degrees off its axis: singular edges across their axis, touching
  the boundary about a tangent axis;
* a hairpin: a singular curve rising from the floor of a slab and going back down (a valence-3
  and a valence-5 edge meeting at its apex: a zipper node), reported and removed by the search's
  zipper cost (and not without it);
* a cube cut into 5 tets whose matchings fold two boundary fans on the cube's faces (valence
  +-2 on a surface), reported and unfolded by the search's fold cost (and not without it);
* the vectorized report against slow per-element references (the fans' parametric angle by
  accumulating wedge angles, the field's turn by scipy rotations, the vertex rules as tuples).

Cost: about 3 s in all (the meshes have at most a few hundred tets).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

from torchconn import io, so3
from torchconn.hexmesh.cut import GROUP_MUL, edge_walks, face_matchings, group_matrices
from torchconn.hexmesh.meshability import (EDGE_CLASSES, INTERIOR_NODES, VERTEX_CLASSES, classify_vertices,
                                           meshability_report)
from torchconn.hexmesh.straighten import straighten_singular_edges
from torchconn.mesh import TetMesh

from test_hexmesh_map import axis_prism


def _identity(mesh):
    return torch.eye(3, dtype=torch.float64).expand(mesh.n_tets, 3, 3).clone()


def _solid_angle(x, tri):
    """Signed solid angle of the triangle ``tri (3, 3)`` seen from the points ``x (N, 3)``
    (Van Oosterom & Strackee); it jumps by 4 pi across the triangle."""
    r = tri[None] - x[:, None]
    n = np.linalg.norm(r, axis=2)
    num = np.einsum("ni,ni->n", r[:, 0], np.cross(r[:, 1], r[:, 2]))
    den = (n[:, 0] * n[:, 1] * n[:, 2] + np.einsum("ni,ni->n", r[:, 0], r[:, 1]) * n[:, 2]
           + np.einsum("ni,ni->n", r[:, 0], r[:, 2]) * n[:, 1] + np.einsum("ni,ni->n", r[:, 1], r[:, 2]) * n[:, 0])
    return 2 * np.arctan2(num, den)


def hairpin():
    """A slab ``[-1, 1]^2 x [0, 1]`` (a triangulated xz-rectangle extruded in 4 layers along y)
    whose mid layer y = 0 has the triangle p = (-0.3, 0, 0), v = (0, 0, 0.6), q = (0.3, 0, 0)
    as a face, p and q on the floor. The field turns about z by a quarter of the solid angle of
    the loop p -> v -> q -> p (saturated: ``pi/4 tanh(3 W / 2 pi) / tanh 3``), so the holonomy
    is a quarter turn about z around p-v and v-q (q-p lies on the floor): one singular curve
    up from p to v and back down to q, valence 3 then 5, a zipper at v.

    Returns ``(mesh, tet_frames, (p, q, v))``."""
    P2 = np.array([(-0.3, 0.0), (0.3, 0.0), (0.0, 0.6), (-1, 0), (1, 0), (-1, 1), (1, 1), (-0.7, 0), (0.7, 0),
                   (0, 1), (-0.5, 1), (0.5, 1), (-0.6, 0.45), (0.6, 0.45), (-1, 0.5), (1, 0.5), (-0.35, 0.8),
                   (0.35, 0.8)])
    tri = np.sort(Delaunay(P2).simplices, axis=1)
    assert any(set(t) == {0, 1, 2} for t in tri.tolist())  # p, q, v span a triangle
    n, layers = len(P2), 4
    P = np.concatenate([np.c_[P2[:, 0], np.full(n, y), P2[:, 1]] for y in np.linspace(-1, 1, layers + 1)])
    tets = []
    for layer in range(layers):
        a, b, c = tri.T + layer * n
        tets += [np.c_[a, b, c, c + n], np.c_[a, b, b + n, c + n], np.c_[a, a + n, b + n, c + n]]
    mesh = TetMesh(torch.tensor(P), torch.tensor(np.concatenate(tets)), reorient=True)
    p, q, v = 2 * n, 2 * n + 1, 2 * n + 2
    w = _solid_angle(mesh.tet_barycenters.numpy(), P[[p, v, q]])
    phi = math.pi / 4 * np.tanh(3 * w / (2 * math.pi)) / math.tanh(3)
    F = so3.exp(torch.as_tensor(phi)[:, None] * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    return mesh, F, (p, q, v)


def cube5():
    """The unit cube cut into 5 tets (a central tet on the corners 0, 3, 5, 6 and four corner tets):
    every edge of the central tet is a diagonal of a cube face, so its four faces are the only
    interior faces and each of their edges is a boundary edge."""
    X = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float)
    tets = np.array([[0, 3, 5, 6], [1, 0, 3, 5], [2, 0, 3, 6], [4, 0, 5, 6], [7, 3, 5, 6]])
    return TetMesh(torch.tensor(X), torch.tensor(tets), reorient=True)


def _element(R):
    G = group_matrices()
    return int(np.nonzero((G == np.asarray(R)).reshape(24, -1).all(1))[0][0])


# ----------------------------------------------------------------------------- slow references
def _ref_turn(mesh, frames, face_rot):
    """Per edge, step by step: the misfit F_to S F_from^T as a scipy rotation vector, projected on
    the unit edge direction, summed over the walk."""
    walks = edge_walks(mesh)
    G = group_matrices().astype(float)
    ft = mesh.face_tets.numpy()
    X, E = mesh.vertices.numpy(), mesh.edges.numpy()
    out = np.zeros(E.shape[0])
    for e in range(E.shape[0]):
        d = X[E[e, 1]] - X[E[e, 0]]
        d /= np.linalg.norm(d)
        for k in range(walks.ptr[e], walks.ptr[e + 1]):
            f, t = walks.face[k], walks.from_tet[k]
            to = ft[f, 1] if ft[f, 0] == t else ft[f, 0]
            S = G[face_rot[f]] if walks.forward[k] else G[face_rot[f]].T
            out[e] += Rotation.from_matrix(frames[to] @ S @ frames[t].T).as_rotvec() @ d
    return out


def _ref_fan_quarters(mesh, frames, face_rot):
    """Per boundary edge: the fan's parametric angle by accumulation, in quarter turns. In the
    first tet's chart (transports multiplied out step by step), each tet's two faces at the edge,
    projected on the plane normal to the edge's nearest axis; the signed angles between them
    summed over the fan. (Equal to the exact count where the fan's boundary faces are close to
    coordinate planes; near 45 degrees the two round differently.)"""
    walks = edge_walks(mesh)
    G = group_matrices().astype(float)
    ft, T = mesh.face_tets.numpy(), mesh.tets.numpy()
    X, E = mesh.vertices.numpy(), mesh.edges.numpy()
    faces = mesh.faces.numpy()
    out = {}
    for e in np.nonzero(walks.boundary)[0]:
        a, b = E[e]
        t = walks.start[e]
        P = np.eye(3)
        axis = frames[t].T @ (X[b] - X[a])
        axis /= np.linalg.norm(axis)
        seq = [t]
        trans = [P.copy()]
        for s in range(walks.ptr[e], walks.ptr[e + 1]):
            f = walks.face[s]
            S = G[face_rot[f]] if walks.forward[s] else G[face_rot[f]].T
            P = S @ P
            t = ft[f, 1] if ft[f, 0] == seq[-1] else ft[f, 0]
            seq.append(t)
            trans.append(P.copy())
        total = 0.0
        for i, (t, P) in enumerate(zip(seq, trans)):
            o = [v for v in T[t] if v not in (a, b)]
            if i + 1 < len(seq):  # the exit face is the one crossed next
                f = walks.face[walks.ptr[e] + i]
                d_ = [v for v in faces[f] if v not in (a, b)][0]
                c_ = o[0] if o[1] == d_ else o[1]
            else:
                c_, d_ = o
                if i > 0:  # the entry face is the one crossed last
                    f = walks.face[walks.ptr[e] + i - 1]
                    c_ = [v for v in faces[f] if v not in (a, b)][0]
                    d_ = o[0] if o[1] == c_ else o[1]
                elif np.dot(np.cross(X[b] - X[a], X[c_] - X[a]), X[d_] - X[a]) < 0:
                    c_, d_ = d_, c_

            def par(v):
                u = P.T @ frames[t].T @ (X[v] - X[a])
                return u - (u @ axis) * axis

            uc, ud = par(c_), par(d_)
            total += math.atan2(axis @ np.cross(uc, ud), uc @ ud)
        out[int(e)] = total / (math.pi / 2)
    return out


def _ref_fan_rotations(mesh, frames, face_rot, turn):
    """Per boundary edge, from the fan's two boundary normals: the first one's nearest signed axis
    ``a0`` and the last one's, carried to the first chart by the product of the transitions
    (3x3 matrices multiplied along the walk), ``a1``; then the number of quarter turns about
    the edge's axis ``e`` (``a0 x a1``, or the axis nearest the edge) that take the first
    face's direction ``e x a0`` to the last's ``a1 x e`` (4 instead of 0 where the dihedral
    angle plus the field's turn exceeds pi)."""
    walks = edge_walks(mesh)
    G = group_matrices().astype(float)
    ft, T = mesh.face_tets.numpy(), mesh.tets.numpy()
    X, E = mesh.vertices.numpy(), mesh.edges.numpy()
    bf = mesh.boundary_faces.numpy()
    out = {}

    def snap(v):
        k = np.abs(v).argmax()
        a = np.zeros(3)
        a[k] = np.sign(v[k])
        return a

    by_edge = {}
    for tri in bf.tolist():
        for i in range(3):
            by_edge.setdefault(tuple(sorted((tri[i], tri[(i + 1) % 3]))), []).append(tri)

    def outward(t, a, b):
        # the boundary faces of tet t through a, b (outward normal from mesh.boundary_faces)
        for tri in by_edge[(a, b)]:
            if set(tri) <= set(T[t].tolist()):
                n = np.cross(X[tri[1]] - X[tri[0]], X[tri[2]] - X[tri[0]])
                yield n / np.linalg.norm(n), [v for v in tri if v not in (a, b)][0]

    for e in np.nonzero(walks.boundary)[0]:
        a, b = E[e]
        first = t = walks.start[e]
        P = np.eye(3)
        phi = 0.0
        seq = [t]
        for s in range(walks.ptr[e], walks.ptr[e + 1]):
            f = walks.face[s]
            P = (G[face_rot[f]] if walks.forward[s] else G[face_rot[f]].T) @ P
            t = ft[f, 1] if ft[f, 0] == t else ft[f, 0]
            seq.append(t)
        for t in seq:  # dihedral angle of each tet at the edge, from its two face normals
            c, d = [v for v in T[t] if v not in (a, b)]
            n1 = np.cross(X[b] - X[a], X[c] - X[a])
            n2 = np.cross(X[b] - X[a], X[d] - X[a])
            phi += math.pi - math.acos(np.clip(-(n1 @ n2) / np.linalg.norm(n1) / np.linalg.norm(n2), -1, 1))
        cand0 = list(outward(first, a, b))
        cand1 = list(outward(seq[-1], a, b))
        if len(seq) > 1:
            n0 = [n for n, c in cand0 if c not in T[seq[1]]][0]
            n1 = [n for n, c in cand1 if c not in T[seq[-2]]][0]
        else:  # one tet: the walk enters through (a, b, c) with orient(a, b, c, d) > 0
            (na, ca), (nb, cb) = cand0
            enter_a = np.dot(np.cross(X[b] - X[a], X[ca] - X[a]), X[cb] - X[a]) > 0
            n0, n1 = (na, nb) if enter_a else (nb, na)
        a0 = snap(frames[first].T @ n0)
        a1 = snap(P.T @ frames[seq[-1]].T @ n1)
        dpar = frames[first].T @ (X[b] - X[a])
        if (a1 == a0).all():
            out[int(e)] = 2
            continue
        if (a1 == -a0).all():
            out[int(e)] = 0 if phi + turn[e] < math.pi else 4
            continue
        ax = np.cross(a0, a1)
        ax = ax if ax @ dpar >= 0 else -ax
        t0, t1 = np.cross(ax, a0), np.cross(a1, ax)
        R = Rotation.from_rotvec(ax * math.pi / 2).as_matrix()
        v, k = t0, 0
        while not np.allclose(v, t1):
            v, k = R @ v, k + 1
        out[int(e)] = k
    return out


_REF_INTERIOR = {(3, 3): "arc", (5, 5): "arc", (2, 2): "arc", (6, 6): "arc", (3, 5): "zipper", (2, 6): "zipper",
                 (3, 3, 3, 3): "node", (3, 3, 5, 5): "node", (3, 5, 5, 5): "node", (5, 5, 5, 5): "node",
                 (3, 3, 5, 5, 5, 5, 5, 5): "node", (5,) * 6: "node", (5,) * 8: "node", (5,) * 12: "node"}
_REF_BOUNDARY = {
    ((), (3,)): "arc", ((), (5,)): "arc", ((), (6,)): "arc", ((1, 1), ()): "arc", ((3, 3), ()): "arc",
    ((0, 0), ()): "arc", ((4, 4), ()): "arc",
    ((), (3, 5)): "zipper", ((), (2, 6)): "zipper", ((1, 3), ()): "zipper", ((0, 4), ()): "zipper",
    ((1,), (5,)): "zipper", ((3,), (3,)): "zipper",
    ((1, 1, 1), ()): "node", ((1, 1, 3), ()): "node", ((1, 1, 3, 3), ()): "node", ((1, 3, 3), ()): "node",
    ((3, 3, 3), ()): "node", ((3, 3), (3,)): "node", ((3, 3), (5,)): "node", ((3, 3), (3, 5)): "node",
    ((3, 3, 3), (5,)): "node", ((1, 3, 3), (3,)): "node", ((1, 3, 3), (5,)): "node",
    ((1, 1, 3, 3, 4), ()): "node", ((1, 1, 4), ()): "node", ((3, 3, 4), ()): "node"}


def _ref_vertex_classes(mesh, hexes, expected):
    """Per vertex: the sorted hex counts of its singular interior edges and the sorted fan angles of
    its non-flat boundary edges, looked up in the tables above (written independently); a boundary
    vertex whose edges, with its sharp ones of flat fan, take more than the link disk's Euler count
    (6 - k per interior edge, 3 - q per boundary edge) is invalid."""
    E = mesh.edges.numpy()
    bnd_v = set(mesh.boundary_vertices.tolist())
    bnd_e = edge_walks(mesh).boundary
    out = []
    for v in range(mesh.n_vertices):
        inc = np.nonzero((E == v).any(1))[0]
        ins = tuple(sorted(int(hexes[e]) for e in inc if not bnd_e[e] and hexes[e] != 4))
        bs = tuple(sorted(int(hexes[e]) for e in inc if bnd_e[e] and hexes[e] != 2))
        flat_sharp = sum(1 for e in inc if bnd_e[e] and hexes[e] == 2 and expected[e] != 2)
        euler = sum(6 - k for k in ins) + sum(3 - q for q in bs) + flat_sharp
        if -1 in ins:
            out.append("complex")
        elif v in bnd_v and euler > 6:
            out.append("invalid")
        elif not ins and not bs:
            out.append("regular")
        elif v in bnd_v:
            out.append(_REF_BOUNDARY.get((bs, ins), "invalid"))
        else:
            out.append(_REF_INTERIOR.get(ins, "invalid"))
    return out


def _check_against_references(mesh, F, face_match=None, accumulate=False):
    m = meshability_report(mesh, F, face_match)
    ch = m.charts
    np.testing.assert_allclose(m.edge_turn, _ref_turn(mesh, ch.frames, ch.face_rot), atol=1e-9)
    ref_r = _ref_fan_rotations(mesh, ch.frames, ch.face_rot, m.edge_turn)
    assert {e: int(m.edge_hexes[e]) for e in ref_r} == ref_r
    assert [VERTEX_CLASSES[c] for c in m.vertex_class] == _ref_vertex_classes(mesh, m.edge_hexes, m.boundary_expected)
    if not accumulate:
        return m
    ref_q = _ref_fan_quarters(mesh, ch.frames, ch.face_rot)
    # compared where both boundary faces of the fan are within 30 degrees of a coordinate plane
    from torchconn.hexmesh.meshability import boundary_fans

    fans = boundary_fans(mesh)
    c0 = np.abs(np.einsum("eji,ej->ei", ch.frames[fans.first_tet], fans.n_first)).max(1)
    c1 = np.abs(np.einsum("eji,ej->ei", ch.frames[fans.last_tet], fans.n_last)).max(1)
    clear = fans.edge[(np.minimum(c0, c1) > math.cos(math.radians(30)))]
    assert clear.size >= 0.25 * fans.edge.size  # not vacuous
    got = {int(e): int(m.edge_hexes[e]) for e in clear}
    assert got == {int(e): int(round(ref_q[int(e)])) for e in clear}
    return m


# ----------------------------------------------------------------------------- clean cases
def test_box_with_the_identity_field_is_meshable_with_its_corners_as_nodes():
    mesh = io.box(2)
    m = meshability_report(mesh, _identity(mesh))
    c = m.counts()
    assert c["meshable"] and c["singular_nodes"] == 8
    assert all(c[k] == 0 for k in ("complex_edges", "zipper_nodes", "invalid_nodes", "surface_valence2_edges",
                                   "touching_edges", "across_edges", "boundary_crease_edges",
                                   "feature_mismatch_edges"))
    X = mesh.vertices.numpy()
    corner = (np.isin(X, [0.0, 1.0]).all(1))
    assert (m.vertex_class[corner] == VERTEX_CLASSES.index("node")).all()
    # the 12 cube edges (2 mesh edges each) are convex features with one hex, the faces flat
    E = mesh.edges.numpy()
    bnd = m.boundary_expected >= 0
    on_two_faces = ((X[E[:, 0]] == X[E[:, 1]]) & np.isin(X[E[:, 0]], [0.0, 1.0])).sum(1) >= 2
    assert (m.edge_hexes[bnd & on_two_faces] == 1).all() and (m.edge_hexes[bnd & ~on_two_faces] == 2).all()
    assert (m.boundary_expected == m.edge_hexes)[bnd].all() and m.feature_edge.sum() == 24
    json.dumps(c)


@pytest.mark.parametrize("turns,hexes", [(4.0, 3), (-4.0, 5), (2.0, 2), (-2.0, 6)])
def test_prism_chain_has_the_hex_count_of_its_turn(turns, hexes):
    mesh, F = axis_prism(turns=turns)
    m = _check_against_references(mesh, F, accumulate=True)
    sing = np.nonzero(m.charts.singular_edge)[0]
    assert sing.size == 3 and (m.edge_hexes[sing] == hexes).all()
    # the field turns by 2 pi / |turns| about the chain: +pi/2 at valence 3 ... -pi at valence 6
    np.testing.assert_allclose(m.edge_turn[sing], (4 - hexes) * math.pi / 2, atol=1e-6)
    E, X = mesh.edges.numpy(), mesh.vertices.numpy()
    chain_v = np.unique(E[sing])
    ends = chain_v[np.isin(X[chain_v, 2], [0.0, 1.0])]
    inner = chain_v[~np.isin(chain_v, ends)]
    assert (m.vertex_class[inner] == VERTEX_CLASSES.index("arc")).all()
    assert m.complex_edges.size == 0 and m.zipper_nodes.size == 0 and m.across_edges.size == 0
    if hexes == 2:  # a valence-2 edge cannot end on a flat face (the link disk has no room)
        assert set(ends.tolist()) <= set(m.invalid_nodes.tolist()) and not m.meshable
    else:
        assert (m.vertex_class[ends] == VERTEX_CLASSES.index("arc")).all()
        assert m.invalid_nodes.size == 0 and m.meshable


def test_complex_turn_gives_complex_edges_and_complex_vertices():
    mesh = axis_prism()
    bc = mesh.tet_barycenters
    axis = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64) / math.sqrt(3)
    F = so3.exp((torch.atan2(bc[:, 1], bc[:, 0]) / 3)[:, None] * axis)
    m = _check_against_references(mesh, F)
    E, X = mesh.edges.numpy(), mesh.vertices.numpy()
    chain = np.nonzero(np.abs(X[E][:, :, :2]).max((1, 2)) < 1e-12)[0]
    assert set(m.complex_edges.tolist()) == set(chain.tolist()) and not m.meshable
    assert (m.edge_hexes[chain] == -1).all()
    assert (m.vertex_class[np.unique(E[chain])] == VERTEX_CLASSES.index("complex")).all()
    assert not set(np.unique(E[chain]).tolist()) & set(m.invalid_nodes.tolist())  # counted once, as complex edges


def test_field_off_its_axis_gives_across_and_touching_edges():
    mesh, F = axis_prism(turns=4.0)
    tilt = so3.exp(torch.tensor([math.radians(50.0), 0.0, 0.0], dtype=torch.float64))
    m = meshability_report(mesh, tilt @ F)
    E, X = mesh.edges.numpy(), mesh.vertices.numpy()
    chain = set(np.nonzero(np.abs(X[E][:, :, :2]).max((1, 2)) < 1e-12)[0].tolist())
    assert set(m.across_edges.tolist()) == chain  # the turn axis is 50 degrees off the chain
    touching = set(m.touching_edges.tolist())  # the end edges: axis 50 degrees off the face normal
    assert touching and touching <= chain
    assert all(np.isin(X[E[e], 2], [0.0, 1.0]).any() for e in touching)
    assert meshability_report(mesh, F).touching_edges.size == 0


# ----------------------------------------------------------------------------- the constructed conditions
def test_hairpin_zipper_is_reported_and_removed_by_the_zipper_cost():
    mesh, F, (p, q, v) = hairpin()
    m = _check_against_references(mesh, F)
    E = mesh.edges.numpy()
    sing = np.nonzero(m.charts.singular_edge)[0]
    assert {tuple(e) for e in E[sing].tolist()} == {tuple(sorted((p, v))), tuple(sorted((q, v)))}
    assert sorted(m.edge_hexes[sing].tolist()) == [3, 5]
    assert m.zipper_nodes.tolist() == [v] and not m.meshable
    assert m.vertex_class[p] == m.vertex_class[q] == VERTEX_CLASSES.index("arc")  # ends on the floor
    # without the zipper cost the hairpin stays: unmaking it costs more misfit than its two edges
    fm0, info0 = straighten_singular_edges(mesh, F, weights={"zipper": 0.0}, boundary_moves=True)
    assert info0["moves"] == 0
    fm, info = straighten_singular_edges(mesh, F, boundary_moves=True)
    assert info["zipper_before"] == 1 and info["zipper_after"] == 0 and info["moves"] >= 1
    m1 = _check_against_references(mesh, F, fm)
    assert m1.meshable and m1.counts()["zipper_nodes"] == 0 and m1.charts.counts()["singular_edges"] == 0


def test_folded_fans_on_the_cube_faces_are_reported_and_unfolded_by_the_fold_cost():
    mesh = cube5()
    F = _identity(mesh)
    best = face_matchings(mesh, F)
    assert (best == 0).all()
    # a half turn about x on the central tet's face (0, 3, 5): the fans of its edges on the faces
    # z = 0 (0-3) and y = 0 (0-5) carry the outward normal to its opposite (x = 1: 3-5 stays flat)
    faces = mesh.faces.numpy()
    f = int(np.nonzero((np.sort(faces, 1) == [0, 3, 5]).all(1))[0][0])
    fm = best.copy()
    fm[f] = _element(np.diag([1, -1, -1]))
    m = _check_against_references(mesh, F, fm)
    E = mesh.edges.numpy()
    folded = {tuple(e) for e in E[m.surface_valence2_edges].tolist()}
    assert folded == {(0, 3), (0, 5)} and not m.meshable
    assert set(m.edge_hexes[m.surface_valence2_edges].tolist()) <= {0, 4}
    assert m.charts.counts()["singular_edges"] == 0  # every edge is a boundary edge: no holonomy
    # the edge-only search has no candidate (no singular edge); the fold cost alone unfolds the
    # fans, and so does the default search (the folds also make the corners 0, 3, 5 invalid nodes)
    off = {"fold": 0.0, "zipper": 0.0, "node": 0.0}
    fm0, info0 = straighten_singular_edges(mesh, F, fm, weights=off, boundary_moves=True)
    assert info0["moves"] == 0 and (fm0 == fm).all()
    for weights in ({**off, "fold": 4.0}, None):
        fm1, info1 = straighten_singular_edges(mesh, F, fm, weights=weights, boundary_moves=True)
        assert info1["folds_before"] == 2 and info1["folds_after"] == 0
        m1 = _check_against_references(mesh, F, fm1)
        assert m1.meshable and m1.surface_valence2_edges.size == 0
    # faces with a boundary edge move only with boundary_moves
    _, info2 = straighten_singular_edges(mesh, F, fm, boundary_moves=False)
    assert info2["moves"] == 0


def test_random_matchings_against_the_references():
    # arbitrary matchings on the box: every kind of holonomy, fan and vertex configuration
    mesh = io.box(2)
    gen = np.random.default_rng(3)
    fm = face_matchings(mesh, _identity(mesh))
    interior = (mesh.face_tets.numpy() >= 0).all(1)
    pick = np.nonzero(interior)[0]
    pick = gen.choice(pick, pick.size // 6, replace=False)
    fm[pick] = gen.integers(1, 24, pick.size)
    m = _check_against_references(mesh, _identity(mesh), fm)
    c = m.counts()
    assert c["complex_edges"] > 0 and c["invalid_nodes"] > 0 and not c["meshable"]


# ----------------------------------------------------------------------------- rules and errors
def test_vertex_rules():
    def cls(on_b, flat=None, **k):
        c = np.zeros(len(EDGE_CLASSES), np.int64)
        for name, n in k.items():
            c[EDGE_CLASSES.index(name)] = n
        fs = None if flat is None else np.array([flat])
        return VERTEX_CLASSES[int(classify_vertices(c[None], np.array([on_b]), fs)[0])]

    for n3, n5 in INTERIOR_NODES:
        assert cls(False, v3=n3, v5=n5) == "node"
    assert cls(False) == "regular" and cls(False, v3=2) == "arc" and cls(False, v6=2) == "arc"
    assert cls(False, v3=1, v5=1) == "zipper" and cls(False, v2=1, v6=1) == "zipper"
    # three valence-3 edges alone are no node (a link of degrees 3, 3, 3 plus 4s and 5s does not exist)
    assert cls(False, v3=3) == "invalid" and cls(False, v3=3, v5=1) == "invalid" and cls(False, v3=1) == "invalid"
    assert cls(False, v3=2, complex=1) == "complex"
    assert cls(True, v3=1) == "arc" and cls(True, v2=1) == "invalid" and cls(True, v3=2) == "invalid"
    assert cls(True, q1=3) == "node" and cls(True, q1=4) == "invalid" and cls(True, q1=2, v3=1) == "invalid"
    assert cls(True, q3=2, v3=1) == "node" and cls(True, q1=1, q3=1) == "zipper"
    # a sharp edge with a flat fan is still a hex edge: a pyramid apex's fans 1, 1, 1, 2 take 7 of
    # the link disk's Euler count 6 (the table alone sees a cube corner); 2, 1, 2, 1 take 6
    assert cls(True, q1=3) == "node" and cls(True, q1=3, flat=0) == "node" and cls(True, q1=3, flat=1) == "invalid"
    assert cls(True, q1=2, flat=2) == "arc" and cls(True, q3=3, flat=1) == "node"
    assert cls(True, flat=7) == "invalid" and cls(True, flat=6) == "regular"
    assert cls(False, v3=2, flat=9) == "arc"  # interior vertices have no sharp edges to count


def test_every_boundary_configuration_is_within_the_link_disks_euler_count():
    # sum_interior (6 - k) + sum_boundary (3 - q) <= 6 for every configuration the table accepts, so
    # counting the flat sharp edges only ever rejects a vertex for those (module docstring)
    from torchconn.hexmesh.meshability import _LINK_EXCESS, BOUNDARY_CONFIGS

    for (b, i), _ in BOUNDARY_CONFIGS.items():
        c = np.zeros(len(EDGE_CLASSES), np.int64)
        c[[EDGE_CLASSES.index(n) for n in ("q0", "q1", "q3", "q4")]] = b
        c[[EDGE_CLASSES.index(n) for n in ("v3", "v5", "v2", "v6")]] = i
        assert int(c @ _LINK_EXCESS) <= 6, (b, i)


def test_bad_input_is_a_clear_error():
    mesh = io.box(1)
    with pytest.raises(ValueError, match="shape"):
        meshability_report(mesh, torch.eye(3).expand(2, 3, 3))
    with pytest.raises(ValueError, match="face_match"):
        meshability_report(mesh, _identity(mesh), np.full(mesh.faces.shape[0], 30))


def test_group_element_helper():
    G = group_matrices()
    for i in (0, 5, 17):
        assert _element(G[i]) == i
    assert GROUP_MUL[_element(np.diag([1, -1, -1])), _element(np.diag([1, -1, -1]))] == 0


def test_boundary_edge_quarters_inverts_boundary_edge_class():
    from torchconn.hexmesh.meshability import boundary_edge_class, boundary_edge_quarters

    q = np.array([0, 1, 2, 3, 4])
    assert boundary_edge_quarters(boundary_edge_class(q)).tolist() == q.tolist()
    assert boundary_edge_quarters(np.array([-1, 0, 4])).tolist() == [2, 2, 2]  # regular / interior classes: flat
