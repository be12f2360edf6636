"""Hex extraction from integer-grid maps (torchconn.hexmesh.extract) and its exact predicates.

Constructed maps whose hex mesh is known by hand (STYLE "Combinatorial geometry"): the box with
the identity map (the structured grid), the rotated box, the same maps re-charted by random
transitions (the same hexes), a generic (jittered) map of the box, a tetgen ball against a
brute-force count, valence-3 and valence-5 singular edges (quadrants glued by quarter turns),
maps broken on purpose (flipped tets, a boundary off its integer plane, a broken seam, a
singular edge off its integer line), and the predicates against a slow exact reference in
:class:`fractions.Fraction`. Default cases cost about 3 s in all (2 cores under load); the
larger ones are ``slow``.
"""
from __future__ import annotations

import itertools
from fractions import Fraction

import numpy as np
import pytest
import torch

import torchconn as tc
from torchconn.hexmesh import predicates as pr
from torchconn.hexmesh.extract import HEX_CORNERS, HEX_FACES, REASONS, extract_hexes

GROUP = tc.frames.octahedral.group(dtype=torch.float64).numpy().round().astype(np.int64)


# ----------------------------------------------------------------------------- helpers
def fit_transitions(mesh, uvw):
    """``face_rot (F,)``, ``face_shift (F, 3)`` with ``uvw_t1 = G uvw_t0 + s`` on every interior face
    (the unique element of O and shift that maps the face's three corners; error if none)."""
    tets = mesh.tets.numpy()
    faces = mesh.faces.numpy()
    ft = mesh.face_tets.numpy()
    F = faces.shape[0]
    rot = np.zeros(F, np.int64)
    shift = np.zeros((F, 3), np.int64)
    fi = np.nonzero((ft >= 0).all(1))[0]
    t0, t1 = ft[fi, 0], ft[fi, 1]
    loc0 = (tets[t0][:, None, :] == faces[fi][:, :, None]).argmax(2)
    loc1 = (tets[t1][:, None, :] == faces[fi][:, :, None]).argmax(2)
    A = np.take_along_axis(uvw[t0], loc0[:, :, None], 1)    # (n, 3, 3) corners in t0
    B = np.take_along_axis(uvw[t1], loc1[:, :, None], 1)
    found = np.zeros(fi.size, bool)
    for g in range(24):
        GA = np.einsum("ij,nkj->nki", GROUP[g], A)
        s = B[:, 0] - GA[:, 0]
        ok = ~found & np.all(GA + s[:, None, :] == B, axis=(1, 2)) & np.all(s == np.round(s), axis=1)
        rot[fi[ok]] = g
        shift[fi[ok]] = s[ok].astype(np.int64)
        found |= ok
    assert found.all(), f"faces without an exact transition: {fi[~found][:5]}"
    return rot, shift


def identity_transitions(mesh):
    F = mesh.faces.shape[0]
    return np.zeros(F, np.int64), np.zeros((F, 3), np.int64)


def box_map(n, size, h):
    mesh = tc.io.box(n, size=size)
    uvw = mesh.vertices.numpy()[mesh.tets.numpy()] / h
    return mesh, uvw


def scaled_jacobian_corners(P):
    """``(H, 8)``: determinant of the unit edge vectors at each corner (the cube's scaled Jacobian)."""
    nbrs = [(1, 3, 4), (2, 0, 5), (3, 1, 6), (0, 2, 7), (7, 5, 0), (4, 6, 1), (5, 7, 2), (6, 4, 3)]
    out = []
    for c, (a, b, d) in enumerate(nbrs):
        e = [P[:, x] - P[:, c] for x in (a, b, d)]
        e = [x / np.linalg.norm(x, axis=1, keepdims=True) for x in e]
        out.append(np.einsum("ni,ni->n", e[0], np.cross(e[1], e[2])))
    return np.stack(out, 1)


def hex_keys(res, decimals=9):
    """Hexes as sets of rounded world corner tuples (chart-independent)."""
    P = np.round(res.points, decimals)
    return {frozenset(map(tuple, P[h])) for h in res.hexes}


def check_conforming(res):
    """Every quad face in at most two hexes, with opposite orientations; no repeated vertex."""
    assert len(np.unique(np.round(res.points, 9), axis=0)) == res.points.shape[0]
    quads = res.hexes[:, HEX_FACES].reshape(-1, 4)
    key = np.sort(quads, 1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    assert cnt.max(initial=0) <= 2
    # orientation of each quad: its smallest vertex first, is the next one smaller than the last?
    m = np.argmin(quads, 1)
    rows = np.arange(len(quads))
    turn = quads[rows, (m + 1) % 4] < quads[rows, (m + 3) % 4]
    shared = cnt[inv] == 2
    n_turn = np.bincount(inv[shared], weights=turn[shared], minlength=cnt.size)
    assert (n_turn[cnt == 2] == 1).all()            # a shared face is seen from both sides
    return quads, inv, cnt


def edge_valences(res):
    """(interior edge -> number of hexes) and the set of boundary edges, from the hex connectivity."""
    quads, inv, cnt = check_conforming(res)
    boundary_quads = quads[cnt[inv] == 1]
    bedges = {tuple(sorted((q[i], q[(i + 1) % 4]))) for q in boundary_quads for i in range(4)}
    hex_edges = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
    val = {}
    for h in res.hexes:
        for a, b in hex_edges:
            e = tuple(sorted((h[a], h[b])))
            val[e] = val.get(e, 0) + 1
    return {e: v for e, v in val.items() if e not in bedges}, bedges


def assert_structured_grid(res, L, h, R=np.eye(3)):
    """The hex mesh of the box [0, L]^3 with spacing h (rotated by R): counts, lattice points,
    axis-aligned (rotated) cubes, scaled Jacobian 1, conforming."""
    m = int(round(L / h))
    assert res.hexes.shape == (m ** 3, 8)
    assert res.points.shape == ((m + 1) ** 3, 3)
    grid = res.points @ R / h                           # back to the lattice
    np.testing.assert_allclose(grid, np.round(grid), atol=1e-9)
    assert set(map(tuple, np.round(grid).astype(int))) == set(itertools.product(range(m + 1), repeat=3))
    P = res.points[res.hexes] @ R / h
    rel = np.round(P - P[:, :1]).astype(int)
    # each hex is a unit lattice cube, its VTK corners a rotation of the template (positive)
    for r in rel:
        M = np.stack([r[1], r[3], r[4]], 1)            # edge vectors 0->1, 0->3, 0->4
        assert round(np.linalg.det(M)) == 1
        np.testing.assert_array_equal(r, HEX_CORNERS @ M.T)
    np.testing.assert_allclose(scaled_jacobian_corners(res.points[res.hexes]), 1.0, atol=1e-9)
    check_conforming(res)
    assert sum(res.dropped.values()) == 0


# ----------------------------------------------------------------------------- predicates
def frac_orient(a, b, c, d):
    A, B, C, D = ([Fraction(float(x)) for x in p] for p in (a, b, c, d))
    u = [B[i] - A[i] for i in range(3)]
    v = [C[i] - A[i] for i in range(3)]
    w = [D[i] - A[i] for i in range(3)]
    det = u[0] * (v[1] * w[2] - v[2] * w[1]) - u[1] * (v[0] * w[2] - v[2] * w[0]) + u[2] * (v[0] * w[1] - v[1] * w[0])
    return (det > 0) - (det < 0)


def _random_dyadic(rng, shape, bits=20, mag=2.0 ** 10):
    return np.round(rng.uniform(-mag, mag, shape) * 2 ** bits) / 2 ** bits


def _degenerate_quads(rng, n):
    """Coplanar / collinear / coincident point quadruples on a 2**-20 grid, large and small."""
    out = []
    for _ in range(n):
        a, b, c = _random_dyadic(rng, (3, 3), mag=2.0 ** rng.integers(-3, 25))
        kind = rng.integers(4)
        if kind == 0:    # d in the plane abc (dyadic combination)
            s, t = rng.integers(-8, 9, 2) / 8
            d = a + s * (b - a) + t * (c - a)
        elif kind == 1:  # d on line ab
            d = a + rng.integers(-8, 9) / 8 * (b - a)
        elif kind == 2:  # d = a vertex
            d = b.copy()
        else:            # axis-aligned plane: all four share one coordinate
            d = _random_dyadic(rng, 3)
            ax = rng.integers(3)
            a[ax] = b[ax] = c[ax] = d[ax]
        out.append((a, b, c, d))
    return [np.array(x) for x in zip(*out)]


def test_orient3d_matches_fraction_reference():
    rng = np.random.default_rng(0)
    rand = [_random_dyadic(rng, (300, 3)) for _ in range(4)]
    deg = _degenerate_quads(rng, 300)
    floats = [rng.normal(size=(200, 3)) * 10.0 ** rng.integers(-5, 5, (200, 1)) for _ in range(4)]
    floats[3][:50] = floats[0][:50] + 0.1 * (floats[1][:50] - floats[0][:50])   # near-coplanar, non-dyadic
    for pts in (rand, deg, floats):
        got = pr.orient3d(*pts)
        ref = np.array([frac_orient(*(p[i] for p in pts)) for i in range(pts[0].shape[0])])
        np.testing.assert_array_equal(got, ref)
    assert (pr.orient3d(*deg) == 0).sum() >= 250          # the degenerate set is mostly exactly 0
    # integer input, permutation parity, batch shape and torch round trip
    a, b, c, d = (np.array(x) for x in ([0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]))
    assert pr.orient3d(a, b, c, d) == 1 and pr.orient3d(a, c, b, d) == -1 and pr.orient3d(a, b, c, a + b) == 0
    big = [np.array(x, np.int64) * (2 ** 40) + 3 for x in ([0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0])]
    assert pr.orient3d(*big) == 0
    T = torch.from_numpy(np.stack(rand, 1)[:12].reshape(3, 4, 4, 3))
    out = pr.orient3d(T[..., 0, :], T[..., 1, :], T[..., 2, :], T[..., 3, :])
    assert isinstance(out, torch.Tensor) and out.dtype == torch.int8 and out.shape == (3, 4)
    np.testing.assert_array_equal(out.numpy().ravel(), pr.orient3d(*rand)[:12])


def test_classify_point_on_face_edge_vertex():
    rng = np.random.default_rng(1)
    tet = _random_dyadic(rng, (4, 3), mag=4.0)
    if pr.orient3d(*tet) < 0:
        tet = tet[[0, 1, 3, 2]]
    cases = []
    for k in range(4):                                 # a point on face k: a dyadic combination
        w = np.array([1, 2, 5], float) / 8
        others = [i for i in range(4) if i != k]
        cases.append((w @ tet[others], pr.ON_FACE, {k}))
    for i, j in itertools.combinations(range(4), 2):   # on edge ij
        cases.append((0.25 * tet[i] + 0.75 * tet[j], pr.ON_EDGE, set(range(4)) - {i, j}))
    for v in range(4):
        cases.append((tet[v], pr.ON_VERTEX, set(range(4)) - {v}))
    cases.append((tet.mean(0), pr.INSIDE, set()))
    cases.append((2 * tet[0] - tet.mean(0), pr.OUTSIDE, None))
    for q, kind, zeros in cases:
        loc = pr.classify_point(tet, q)
        assert loc.kind == kind
        if zeros is not None:
            assert set(np.nonzero(loc.zero)[0]) == zeros
        # against the Fraction reference, both orientations
        ref = [frac_orient(*[q if m == k else tet[m] for m in range(4)]) for k in range(4)]
        np.testing.assert_array_equal(pr.barycentric_signs(tet, q), ref)
        flipped = pr.classify_point(tet[[1, 0, 2, 3]], q)
        assert flipped.kind == kind and flipped.orientation == -1
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    assert pr.classify_point(flat, np.zeros(3)).kind == pr.DEGENERATE


def test_sos_orientation_is_the_perturbed_limit():
    """``_orient3d_sos_int`` equals the sign of orient3d at a tiny explicit perturbation (Fractions)."""
    rng = np.random.default_rng(2)
    S = 2 ** 4
    for _ in range(300):
        pts = rng.integers(-3, 4, (5, 3)) * S            # small lattice: degeneracies are frequent
        p, g, a, b, c = pts
        got = pr._orient3d_sos_int(*(x[None] for x in (p, g, a, b, c)))[0]
        eps = Fraction(1, 10 ** 6)
        pe = [Fraction(int(p[i])) + eps * (int(g[i]) - int(p[i])) + eps ** (2 + i) for i in range(3)]
        ref = frac_orient(pe, a, b, c)
        if np.linalg.matrix_rank(np.stack([b - a, c - a])) < 2:
            assert got == 0                               # collinear a, b, c: no perturbation helps
        else:
            assert got == ref != 0


def test_to_grid_and_input_errors():
    assert pr.to_grid(np.array([[0.5, -1.25]]), 2).tolist() == [[2, -5]]
    with pytest.raises(ValueError, match=r"not on the dyadic grid.*rows \[1\]"):
        pr.to_grid(np.array([[0.5], [0.1]]), 20)
    with pytest.raises(ValueError, match="non-finite"):
        pr.to_grid(np.array([[np.nan]]), 20)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        pr.orient3d(np.zeros(2), np.zeros(3), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 3\)"):
        pr.barycentric_signs(np.zeros((3, 3)), np.zeros(3))

    mesh, uvw = box_map(2, 2.0, 1.0)
    rot, shift = identity_transitions(mesh)
    with pytest.raises(ValueError, match=r"uvw must have shape \(T, 4, 3\) = \(48, 4, 3\)"):
        extract_hexes(mesh, uvw[:-1], rot, shift)
    bad = uvw.copy()
    bad[[5, 7], 0, 0] += 0.1
    with pytest.raises(ValueError, match=r"not on the dyadic grid 2\*\*-20.*tets \[5, 7\]"):
        extract_hexes(mesh, bad, rot, shift)
    with pytest.raises(ValueError, match=r"face_rot must have shape"):
        extract_hexes(mesh, uvw, rot[:-1], shift)
    interior = np.nonzero((mesh.face_tets.numpy() >= 0).all(1))[0]
    r2 = rot.copy()
    r2[interior[3]] = 24
    with pytest.raises(ValueError, match=rf"0\.\.23.*faces \[{interior[3]}\]"):
        extract_hexes(mesh, uvw, r2, shift)
    s2 = shift.astype(float)
    s2[interior[1], 2] = 0.5
    with pytest.raises(ValueError, match=rf"face_shift must be integer-valued.*faces \[{interior[1]}\]"):
        extract_hexes(mesh, uvw, rot, s2)
    with pytest.raises(ValueError, match="grid_bits"):
        extract_hexes(mesh, uvw, rot, shift, grid_bits=0)
    with pytest.raises(TypeError, match="TetMesh"):
        extract_hexes(uvw, uvw, rot, shift)
    # boundary faces are ignored: any value there is accepted
    bnd = np.nonzero((mesh.face_tets.numpy() < 0).any(1))[0]
    r3 = rot.copy()
    r3[bnd] = 99
    assert extract_hexes(mesh, uvw, r3, shift).hexes.shape == (8, 8)


# ----------------------------------------------------------------------------- constructed maps
@pytest.mark.parametrize("n,size,h", [(4, 4.0, 1.0), (4, 4.0, 2.0), (2, 4.0, 1.0), (3, 3.0, 0.5)])
def test_box_gives_the_structured_grid(n, size, h):
    """Hexes larger than, equal to and smaller than the cubes of the tet mesh."""
    mesh, uvw = box_map(n, size, h)
    res = extract_hexes(mesh, torch.from_numpy(uvw), *identity_transitions(mesh))
    assert_structured_grid(res, size, h)
    # canonical representatives: the lowest tet holding each point, its parameter there
    np.testing.assert_array_equal(res.point_param, np.round(res.points / h).astype(np.int64))
    for p, t in zip(res.point_param[::7], res.point_tet[::7]):
        holders = np.nonzero((pr.barycentric_signs(uvw, p[None]) >= 0).all(1))[0]
        assert t == holders.min()
    np.testing.assert_array_equal(res.points[res.hexes[:, 0]] / h, res.hex_param)   # identity chart
    assert res.counts()["hexes"] == res.hexes.shape[0] and res.counts()["flipped_tets"] == 0


def test_rotated_box_gives_the_rotated_grid():
    rng = np.random.default_rng(3)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    base = tc.io.box(4, size=4.0)
    mesh = tc.TetMesh(base.vertices.numpy() @ R.T, base.tets.numpy())
    x = mesh.vertices.numpy()[mesh.tets.numpy()]
    uvw = np.round(x @ R / 2.0 * 2 ** 20) / 2 ** 20       # R^T x / h, snapped to the grid
    res = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    assert_structured_grid(res, 4.0, 2.0, R=R)


def jittered_box_map(n, size, h, amp=0.2, seed=0):
    """``box(n, size)`` with parameters ``x / h`` plus a random offset of up to ``amp`` tet
    spacings (snapped to 2**-20; boundary vertices keep their coordinate on their plane): generic
    vertex positions, so the predicates take their filtered path, not the lattice shortcut."""
    mesh = tc.io.box(n, size=size)
    V = mesh.vertices.numpy()
    P = V / h + np.random.default_rng(seed).uniform(-amp, amp, V.shape) * (size / n / h)
    for ax in range(3):
        on = (np.abs(V[:, ax]) < 1e-12) | (np.abs(V[:, ax] - size) < 1e-12)
        P[on, ax] = V[on, ax] / h
    uvw = (np.round(P * 2 ** 20) / 2 ** 20)[mesh.tets.numpy()]
    assert (pr.orient3d(uvw[:, 0], uvw[:, 1], uvw[:, 2], uvw[:, 3]) > 0).all()
    return mesh, uvw


def test_generic_map_gives_the_grid_topology():
    mesh, uvw = jittered_box_map(4, 4.0, 1.0)
    res = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    assert res.hexes.shape == (64, 8) and sum(res.dropped.values()) == 0
    assert set(map(tuple, res.point_param)) == set(itertools.product(range(5), repeat=3))
    interior, _ = edge_valences(res)
    assert len(interior) == 3 * 4 * 3 * 3 and set(interior.values()) == {4}
    # each hex vertex maps back to its parameter through its tet (the map is linear per tet)
    X = mesh.vertices.numpy()[mesh.tets.numpy()[res.point_tet]]
    lam = np.linalg.solve(np.concatenate([X, np.ones((len(X), 4, 1))], 2).transpose(0, 2, 1),
                          np.concatenate([res.points, np.ones((len(X), 1))], 1)[:, :, None])[:, :, 0]
    assert (lam > -1e-9).all()
    np.testing.assert_allclose(np.einsum("nk,nki->ni", lam, uvw[res.point_tet]), res.point_param, atol=1e-9)
    # hex corners in VTK order: the parameter offsets from the min corner are the template
    rel = res.point_param[res.hexes] - res.point_param[res.hexes[:, :1]]
    np.testing.assert_array_equal(rel, np.broadcast_to(HEX_CORNERS, rel.shape))


def _rechart(uvw, tets_sel, rng):
    """Apply a random element of O and a random integer shift to the charts of ``tets_sel``."""
    sel = np.asarray(list(tets_sel))
    out = uvw.copy()
    g = GROUP[rng.integers(24, size=sel.size)]
    out[sel] = np.einsum("nij,nkj->nki", g, uvw[sel]) + rng.integers(-5, 6, (sel.size, 1, 3))
    return out


@pytest.mark.parametrize("mode", ["half_space", "every_tet"])
def test_transitions_give_the_same_hex_mesh(mode):
    rng = np.random.default_rng(4)
    mesh, uvw = box_map(3, 3.0, 0.5)
    ref = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    T = uvw.shape[0]
    if mode == "half_space":
        c = mesh.vertices.numpy()[mesh.tets.numpy()].mean(1)
        sel = np.nonzero(c @ np.array([1.0, 0.7, 0.3]) > 2.0)[0]
        g, s = GROUP[rng.integers(1, 24)], rng.integers(-5, 6, 3)
        new = uvw.copy()
        new[sel] = uvw[sel] @ g.T + s
    else:
        new = _rechart(uvw, range(T), rng)
    rot, shift = fit_transitions(mesh, new)
    assert (rot != 0).sum() > 0
    res = extract_hexes(mesh, new, rot, shift)
    assert hex_keys(res) == hex_keys(ref) and res.hexes.shape == ref.hexes.shape
    np.testing.assert_allclose(scaled_jacobian_corners(res.points[res.hexes]), 1.0, atol=1e-9)
    check_conforming(res)
    # each representative is the lowest tet holding the point (found in world space), with the
    # point's parameter in that tet's (new) chart
    X = mesh.vertices.numpy()[mesh.tets.numpy()]
    M = np.linalg.inv(np.concatenate([X, np.ones((len(X), 4, 1))], 2).transpose(0, 2, 1))
    for x, p, t in zip(res.points[::5], res.point_param[::5], res.point_tet[::5]):
        lam = M @ np.append(x, 1.0)
        assert t == np.nonzero((lam > -1e-9).all(1))[0].min()
        np.testing.assert_allclose(lam[t] @ new[t], p, atol=1e-9)


def valence_map(k=3, n=2, m=2):
    """A valence-``k`` singular edge: ``k`` quadrants ``[0, n]^2 x [0, m]`` of unit-cube tets around
    the z axis, quadrant ``j`` charted as quadrant 1 turned by ``j`` quarter turns (so the
    triangulations of every shared face match: Kuhn's is not invariant under sign flips), quadrant
    ``j``'s side ``y = 0`` glued to quadrant ``j - 1``'s side ``x = 0`` (and the first to the last),
    embedded in 3D by scaling the polar angle by ``4 / k`` so it closes. For ``k = 3`` the parameter
    domain is ``([-n, n]^2`` minus the quadrant ``x > 0, y < 0) x [0, m]`` in one chart but for the
    seam, which carries a quarter turn; for ``k = 5`` the fifth quadrant overlaps the first in
    parameter space (charts, not one flat domain)."""
    pts, index = [], {}

    def vid(j, x, y, z):
        """Vertex of quadrant ``j`` at local (quadrant-1 frame) coordinates ``(x, y, z)``."""
        if x == 0 and y == 0:
            key = (0, 0, 0, z)                  # the axis, shared by every quadrant
        elif y == 0:                            # side y = 0 of quadrant j = side x = 0 of j - 1
            key = ((j - 1) % k, 0, x, z)
        else:
            key = (j, x, y, z)
        if key not in index:
            index[key] = len(pts)
            pts.append(key)
        return index[key]

    q1 = []                                     # Kuhn tets of quadrant 1, positively oriented
    for i, j, l in itertools.product(range(n), range(n), range(m)):
        c = np.array([i, j, l])
        for perm in itertools.permutations(range(3)):
            corners, off = [c.copy()], np.zeros(3, int)
            for ax in perm:
                off[ax] += 1
                corners.append(c + off)
            if sum(perm[a] > perm[b] for a in range(3) for b in range(a + 1, 3)) % 2:
                corners[2], corners[3] = corners[3], corners[2]
            q1.append(corners)
    q1 = np.array(q1)
    quarter = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    tets, uvw = [], []
    for j in range(k):
        R = np.linalg.matrix_power(quarter, j)
        for corners in q1:
            tets.append([vid(j, *p) for p in corners])
            uvw.append((corners @ R.T).astype(float))
    P = np.array(pts, float)                   # (quadrant, x, y, z) in the quadrant-1 frame
    r = np.hypot(P[:, 1], P[:, 2])
    theta = (P[:, 0] * np.pi / 2 + np.arctan2(P[:, 2], P[:, 1])) * 4 / k
    X = np.stack([r * np.cos(theta), r * np.sin(theta), P[:, 3]], 1)
    return tc.TetMesh(X, np.array(tets)), np.array(uvw)


def valence3_map(n=2, m=2):
    return valence_map(3, n, m)


@pytest.mark.parametrize("k", [3, 5])
def test_singular_edge_valence(k):
    """The hex mesh of the valence-k map: k n^2 m hexes, the m axis edges in exactly k hexes and
    every other interior edge in 4."""
    n, m = 2, 2
    mesh, uvw = valence_map(k, n, m)
    rot, shift = fit_transitions(mesh, uvw)
    quarter_turns_z = [g for g in range(24) if GROUP[g][2, 2] == 1 and GROUP[g][0, 0] == 0]
    assert set(np.unique(rot)) - {0} <= set(quarter_turns_z) and (rot != 0).any()
    res = extract_hexes(mesh, uvw, rot, shift)
    assert res.hexes.shape == (k * n * n * m, 8) and sum(res.dropped.values()) == 0
    assert res.counts()["invalid_singular_edges"] == 0
    interior, _ = edge_valences(res)
    axis = {e for e in interior if np.allclose(res.points[list(e)][:, :2], 0, atol=1e-9)}
    assert len(axis) == m
    assert all(interior[e] == k for e in axis)
    assert all(v == 4 for e, v in interior.items() if e not in axis)
    # every hex positively oriented in the world too (the embedding preserves orientation)
    assert (scaled_jacobian_corners(res.points[res.hexes]) > 0).all()


# ----------------------------------------------------------------------------- broken maps
def _linf_to_cubes(res, x):
    """L-infinity distance from the point ``x`` to each hex's (axis-aligned) world box."""
    P = res.points[res.hexes]
    lo, hi = P.min(1), P.max(1)
    return np.maximum(0, np.maximum(lo - x, x - hi)).max(1)


def _kept(ref, res):
    keys = hex_keys(res)
    return np.array([frozenset(map(tuple, np.round(ref.points[h], 9))) in keys for h in ref.hexes])


def test_flipped_tets_are_dropped_never_emitted():
    """Box [0,4]^3 of tets of size 1/2, hexes of size 1; one interior vertex's parameter pushed
    out of its star, so tets around it flip. The cubes touching it are dropped; those two hexes
    away are all kept; what is kept is exactly the grid."""
    mesh, uvw = box_map(8, 4.0, 1.0)
    ref = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    V = mesh.vertices.numpy()
    v = int(np.argmin(np.linalg.norm(V - 1.0, axis=1)))   # the vertex (1, 1, 1)
    vmap = V.copy()
    vmap[v] = [1.75, 1.375, 1.5]
    res = extract_hexes(mesh, vmap[mesh.tets.numpy()], *identity_transitions(mesh))
    c = res.counts()
    assert c["flipped_tets"] > 0
    assert res.dropped["flipped_tet"] > 0
    assert set(np.unique(res.dropped_reason)) <= {REASONS.index("flipped_tet"), REASONS.index("near_invalid")}
    assert c["hexes"] + c["cubes_dropped"] == 64               # every cube found once
    kept, d = _kept(ref, res), _linf_to_cubes(ref, V[v])
    assert kept.sum() == c["hexes"]                            # what is kept is the grid's
    assert not kept[d == 0].any() and kept[d >= 2].all() and (d >= 2).sum() == 37
    assert (scaled_jacobian_corners(res.points[res.hexes]) > 0).all()
    check_conforming(res)


def test_boundary_off_its_integer_plane():
    mesh, uvw = box_map(4, 4.0, 1.0)
    V = mesh.vertices.numpy()
    v = int(np.argmin(np.linalg.norm(V - [2.0, 2.0, 0.0], axis=1)))   # a boundary vertex on w = 0
    vmap = V.copy()
    vmap[v, 2] = 0.25                                                 # pushed inwards
    res = extract_hexes(mesh, vmap[mesh.tets.numpy()], *identity_transitions(mesh))
    # the 4 cubes with that corner lose it (outside the domain); the other 60 are the grid's
    assert res.dropped["leaves_domain"] == 4 and sum(res.dropped.values()) == 4
    np.testing.assert_array_equal(np.sort(res.dropped_centre[:, :2] - 2.0, 0).round(1),
                                  [[-0.5, -0.5], [-0.5, -0.5], [0.5, 0.5], [0.5, 0.5]])
    assert (res.dropped_centre[:, 2] == 0.5).all()
    ref = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    assert res.hexes.shape[0] == 60 and hex_keys(res) <= hex_keys(ref)
    check_conforming(res)


def test_broken_seam():
    """Half the box re-charted by an element of O and a shift while the faces claim the identity:
    the seam at x = 2.5 (through the middle of a layer of cubes) is mismatched."""
    mesh, uvw = box_map(8, 4.0, 1.0)
    V, tets = mesh.vertices.numpy(), mesh.tets.numpy()
    sel = np.nonzero(V[tets].mean(1)[:, 0] > 2.5)[0]
    new = uvw.copy()
    new[sel] = uvw[sel] @ GROUP[5].T + np.array([3, -2, 1])
    res = extract_hexes(mesh, new, *identity_transitions(mesh))
    ref = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    assert res.counts()["mismatched_faces"] == 2 * 8 * 8       # the seam's triangles
    kept = _kept(ref, res)
    cx = ref.points[ref.hexes].mean(1)[:, 0]
    # cubes cut by the seam: found once from each side, dropped as seam_mismatch; the layers
    # next to the seam's tets: near_invalid; the rest is the grid
    assert res.dropped["seam_mismatch"] == 2 * 16
    assert res.dropped["near_invalid"] == 2 * 16
    np.testing.assert_array_equal(kept, cx == 0.5)
    check_conforming(res)


def test_singular_edge_off_its_integer_line():
    """The valence-3 map translated by (1/2, 1/2, 0): every transition is still exact (the seam
    gets the shift (0, 1, 0)) but the quarter turn's axis is the line x = y = 1/2, through the
    middle of a column of cubes. Those cubes are dropped, never emitted as hexes around it."""
    n, m = 3, 2
    mesh, uvw = valence3_map(n, m)
    moved = uvw + np.array([0.5, 0.5, 0.0])
    rot, shift = fit_transitions(mesh, moved)
    res = extract_hexes(mesh, moved, rot, shift)
    pts = mesh.vertices.numpy()
    on_axis = np.nonzero(np.abs(pts[:, :2]).max(1) < 1e-12)[0]
    assert {tuple(sorted(e)) for e in res.invalid_singular_edges.tolist()} == \
        {tuple(sorted(p)) for p in itertools.combinations(on_axis, 2) if abs(pts[p[0], 2] - pts[p[1], 2]) == 1}
    assert res.hexes.shape[0] > 0
    # the column of cubes around the axis (centre (1/2, 1/2) in the charts) is dropped ...
    axis_cubes = np.abs(res.dropped_centre[:, :2] - 0.5).max(1) == 0
    assert axis_cubes.sum() == m and (res.dropped_reason[axis_cubes] == REASONS.index("near_invalid")).all()
    assert not (res.hex_param[:, :2] == 0).all(1).any()
    # ... the boundary planes are now at half-integers: the cubes cut by them leave the domain
    assert set(np.unique(res.dropped_reason)) <= {REASONS.index("near_invalid"), REASONS.index("leaves_domain")}
    assert (scaled_jacobian_corners(res.points[res.hexes]) > 0).all()
    check_conforming(res)


def test_unstructured_ball_matches_brute_force():
    """A tetgen ball (unstructured tets, boundary off the lattice) with the linear map x / h:
    the hexes are exactly the lattice cubes whose 8 corners lie in the closed domain (the domain
    is convex, so the centre-to-corner segments are inside too), found by brute force over all
    tets; re-charting every tet by a random element of O and shift gives the same hexes."""
    mesh = tc.ball(radius=1.5, edge_length=0.5)
    h = 0.5
    uvw = np.round(mesh.vertices.numpy() / h * 2 ** 20)[mesh.tets.numpy()] / 2 ** 20
    res = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    lo, hi = np.floor(uvw.min((0, 1))).astype(int), np.ceil(uvw.max((0, 1))).astype(int)
    grid = np.array(list(itertools.product(*[range(a, b + 1) for a, b in zip(lo, hi)])))
    near = ((grid[:, None] >= uvw.min(1)[None]) & (grid[:, None] <= uvw.max(1)[None])).all(2)   # bbox holds it
    g, t = np.nonzero(near)
    inside = np.zeros(len(grid), bool)
    inside[g[(pr.barycentric_signs(uvw[t], grid[g]) >= 0).all(1)]] = True
    ins = set(map(tuple, grid[inside]))
    cubes = {tuple(c) for c in grid if all(tuple(c + o) in ins for o in HEX_CORNERS)}
    assert len(cubes) > 20 and {tuple(c) for c in res.hex_param} == cubes
    assert set(np.unique(res.dropped_reason)) <= {REASONS.index("leaves_domain")}
    np.testing.assert_allclose(res.points, h * res.point_param, atol=h * 2.0 ** -19)
    np.testing.assert_allclose(scaled_jacobian_corners(res.points[res.hexes]), 1.0, atol=1e-5)
    check_conforming(res)
    new = _rechart(uvw, range(uvw.shape[0]), np.random.default_rng(6))
    res2 = extract_hexes(mesh, new, *fit_transitions(mesh, new))
    assert hex_keys(res2, 6) == hex_keys(res, 6)


def test_limits_empty_maps_and_progress():
    # hexes larger than the domain: no cube at all, an empty but well-formed result
    mesh, uvw = box_map(2, 1.0, 4.0)
    res = extract_hexes(mesh, uvw, *identity_transitions(mesh), progress=True)
    assert res.hexes.shape == (0, 8) and res.points.shape == (0, 3) and res.counts()["cubes_dropped"] == 0
    # walks that need a step are cut by max_walk_steps=0 (tets smaller than the cubes)
    mesh, uvw = box_map(8, 4.0, 1.0)
    res = extract_hexes(mesh, uvw, *identity_transitions(mesh), max_walk_steps=0)
    assert res.hexes.shape[0] == 0 and res.dropped["walk_limit"] == 64
    # tets holding more lattice points than max_tet_points are skipped and reported
    mesh, uvw = box_map(2, 4.0, 0.5)                   # 4 x 4 x 4 half-cubes per tet bbox
    res = extract_hexes(mesh, uvw, *identity_transitions(mesh), max_tet_points=8)
    assert res.counts()["oversized_tets"] == uvw.shape[0] and res.hexes.shape[0] == 0


def test_overlap_guard():
    """``_drop_overlaps``: a quad shared by two hexes with the same orientation (a fold), or by
    three hexes, marks them; a properly shared face does not."""
    from torchconn.hexmesh.extract import _OK, _R, _drop_overlaps
    a = np.arange(8)
    b = np.array([4, 5, 6, 7, 8, 9, 10, 11])            # on top of a: shares a's top face, reversed
    c = np.array([8, 9, 10, 11, 4, 5, 6, 7])            # below a's top face: same orientation as a
    ok = np.full(2, _OK, np.int8)
    assert (_drop_overlaps(np.stack([a, b]), ok) == _OK).all()
    assert (_drop_overlaps(np.stack([a, c]), ok) == _R["overlap"]).all()
    d = np.array([4, 5, 6, 7, 12, 13, 14, 15])
    out = _drop_overlaps(np.stack([a, b, d]), np.full(3, _OK, np.int8))
    assert (out == _R["overlap"]).all()


def test_chunking_does_not_change_the_result(monkeypatch):
    """Lattice points and walks are processed in chunks (memory bounds): tiny chunks give the
    same extraction as one chunk, on a map with transitions."""
    import torchconn.hexmesh.extract as ex
    import torchconn.hexmesh.lattice as lat
    mesh, uvw = jittered_box_map(3, 3.0, 0.5)
    new = _rechart(uvw, range(0, uvw.shape[0], 3), np.random.default_rng(7))
    F = fit_transitions(mesh, new)
    ref = extract_hexes(mesh, new, *F)
    monkeypatch.setattr(ex, "_CUBE_CHUNK", 5)
    monkeypatch.setattr(lat, "_POINT_CHUNK", 7)
    res = extract_hexes(mesh, new, *F)
    for name in ("points", "hexes", "point_tet", "point_param", "hex_tet", "hex_param"):
        np.testing.assert_array_equal(getattr(res, name), getattr(ref, name))
    assert res.hexes.shape[0] == 216


# ----------------------------------------------------------------------------- larger cases
@pytest.mark.slow
def test_large_generic_map_with_random_charts():
    """16^3 hexes over 196,608 generic tets (48 per hex), every tet in its own random chart: the
    structured topology, and the same hexes as with one chart."""
    mesh, uvw = jittered_box_map(32, 16.0, 1.0)
    ref = extract_hexes(mesh, uvw, *identity_transitions(mesh))
    assert ref.hexes.shape[0] == 16 ** 3 and sum(ref.dropped.values()) == 0
    interior, _ = edge_valences(ref)
    assert len(interior) == 3 * 16 * 15 * 15 and set(interior.values()) == {4}
    new = _rechart(uvw, range(uvw.shape[0]), np.random.default_rng(8))
    res = extract_hexes(mesh, new, *fit_transitions(mesh, new))
    assert hex_keys(res) == hex_keys(ref)


@pytest.mark.slow
@pytest.mark.parametrize("k,n,m", [(3, 6, 4), (5, 4, 3)])
def test_large_singular_edge(k, n, m):
    mesh, uvw = valence_map(k, n, m)
    res = extract_hexes(mesh, uvw, *fit_transitions(mesh, uvw))
    assert res.hexes.shape == (k * n * n * m, 8) and sum(res.dropped.values()) == 0
    interior, _ = edge_valences(res)
    axis = {e for e in interior if np.allclose(res.points[list(e)][:, :2], 0, atol=1e-9)}
    assert len(axis) == m and all(interior[e] == k for e in axis)
    assert all(v == 4 for e, v in interior.items() if e not in axis)
