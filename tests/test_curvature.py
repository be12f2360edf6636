"""Tests of torchconn.curvature: two-prong / holonomy (Sec. 3.2, (3.2.1), (3.2.2))."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import curvature, so3, son
from torchconn.tolerances import get_eps

DTYPES = [torch.float32, torch.float64]


def rand_rot(*shape, n=3, gen=None, dtype=torch.float64):
    if n == 3:
        return so3.random_rotation(*shape, generator=gen, dtype=dtype)
    return son.random_rotation(*shape, n=n, generator=gen, dtype=dtype)


# ---------------------------------------------------------------- slow references
def slow_prod(mats, n, dtype):
    out = torch.eye(n, dtype=dtype)
    for M in mats:
        out = out @ M
    return out


def slow_two_prong(L, cut):
    """Plain per-loop definition: gamma1 forward to x_c, gamma2 backward to x_c (cut 0: whole loop)."""
    m, n = L.shape[0], L.shape[-1]
    c = cut % m
    if c == 0:
        return slow_prod([L[k] for k in range(m)], n, L.dtype) - torch.eye(n, dtype=L.dtype)
    g1 = slow_prod([L[k] for k in range(c)], n, L.dtype)
    g2 = slow_prod([L[k].T for k in range(m - 1, c - 1, -1)], n, L.dtype)
    return g1 - g2


def loop_from_vertices(vloop, rot_of):
    """loop_rot of a vertex loop with transports rot_of(i, j) = R_ij."""
    m = len(vloop)
    return torch.stack([rot_of(vloop[k], vloop[(k + 1) % m]) for k in range(m)])


def edge_table(edges, R):
    table = {}
    for e, (i, j) in enumerate(edges):
        table[(i, j)] = R[e]
        table[(j, i)] = R[e].T
    return lambda i, j: table[(i, j)]


# ---------------------------------------------------------------- functional core
@pytest.mark.parametrize("n", [2, 3, 4])
@pytest.mark.parametrize("m", [3, 4, 6])
def test_two_prong_matches_slow_reference(gen, n, m):
    L = rand_rot(5, m, n=n, gen=gen)
    for cut in range(-m, m):
        X = curvature.two_prong(L, cut)
        ref = torch.stack([slow_two_prong(L[b], cut) for b in range(5)])
        assert torch.allclose(X, ref, atol=1e-13, rtol=0)
    # per-loop tensor cuts
    cuts = torch.tensor([0, 1, m - 1, 2 % m, -1])
    X = curvature.two_prong(L, cuts)
    ref = torch.stack([slow_two_prong(L[b], int(cuts[b])) for b in range(5)])
    assert torch.allclose(X, ref, atol=1e-13, rtol=0)


def test_triangle_formula(gen):
    L = rand_rot(4, 3, gen=gen)
    Rab, Rbc, Rca = L[:, 0], L[:, 1], L[:, 2]
    Rac = Rca.transpose(-1, -2)
    assert torch.allclose(curvature.two_prong(L, 2), Rab @ Rbc - Rac, atol=1e-14)
    assert torch.allclose(curvature.two_prong(L, 1), Rab - Rac @ Rbc.transpose(-1, -2), atol=1e-14)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_cut_zero_is_holonomy(gen, n):
    L = rand_rot(7, 5, n=n, gen=gen)
    H = curvature.holonomy(L)
    assert torch.equal(curvature.two_prong(L, 0), H)
    ref = torch.stack([slow_prod(list(L[b]), n, L.dtype) for b in range(7)]) - torch.eye(n, dtype=L.dtype)
    assert torch.allclose(H, ref, atol=1e-14)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_two_prong_is_holonomy_times_second_prong(gen, n):
    """T(g1) - T(g2) = (T(loop) - I) T(g2) since T(g1) = T(loop) T(g2)."""
    m = 6
    L = rand_rot(4, m, n=n, gen=gen)
    H = curvature.holonomy(L)
    for c in range(1, m):
        g2 = torch.stack([slow_prod([L[b, k].T for k in range(m - 1, c - 1, -1)], n, L.dtype) for b in range(4)])
        X = curvature.two_prong(L, c)
        assert (X - H @ g2).abs().max() < 1e-13
        t1, t2 = curvature.prong_transports(L, c)
        assert torch.allclose(t2, g2, atol=1e-14)
        assert torch.allclose(t1 - t2, X, atol=1e-14)


def test_reexpression_equals_direct_evaluation(gen):
    """Moving the evaluation vertex = pre-multiplication, moving the cut = post-multiplication."""
    m = 6
    L = rand_rot(3, m, gen=gen)
    for c in range(m):
        X = curvature.two_prong(L, c)
        for k in range(m):
            if k == c and k != 0:
                with pytest.raises(ValueError, match="cut vertex"):
                    curvature.eval_transport(L, c, k)
                continue
            pre, new_cut = curvature.eval_transport(L, c, k)
            direct = curvature.two_prong(curvature.roll(L, k), new_cut)
            assert (curvature.reexpress(X, pre=pre) - direct).abs().max() < 1e-13
            # the cut vertex is the same mesh vertex: x_c = (rolled loop)[new_cut]
            assert (k + new_cut) % m == c % m
        for c2 in range(m):
            post = curvature.cut_transport(L, c, c2)
            assert (curvature.reexpress(X, post=post) - curvature.two_prong(L, c2)).abs().max() < 1e-13
    # both at once
    pre, nc = curvature.eval_transport(L, 4, 2)
    Y = curvature.two_prong(curvature.roll(L, 2), nc)
    post = curvature.cut_transport(curvature.roll(L, 2), nc, 3)
    assert (curvature.reexpress(curvature.two_prong(L, 4), pre, post) - curvature.two_prong(curvature.roll(L, 2), 3)).abs().max() < 1e-13
    assert (Y @ post - curvature.two_prong(curvature.roll(L, 2), 3)).abs().max() < 1e-13


@pytest.mark.parametrize("n", [3, 4])
def test_summability_3_2_2(gen, n):
    """Polygon P = [v0..v6] split by the chain v0 -> w1 -> w2 -> v4 into f and g (random rotations)."""
    v = list(range(7))
    w1, w2 = 7, 8
    f = [v[0], v[1], v[2], v[3], v[4], w2, w1]
    g = [v[0], w1, w2, v[4], v[5], v[6]]
    P = v
    pairs = sorted({tuple(sorted((a[k], a[(k + 1) % len(a)]))) for a in (f, g, P) for k in range(len(a))})
    rot = edge_table(pairs, rand_rot(len(pairs), n=n, gen=gen))
    Lf, Lg, LP = (loop_from_vertices(a, rot) for a in (f, g, P))
    Xf = curvature.two_prong(Lf, 4)  # eval v0, cut v4
    Xg = curvature.two_prong(Lg, 3)
    XP = curvature.two_prong(LP, 4)
    assert (curvature.merge(Xf, Xg) - XP).abs().max() < 1e-13
    # the shared chain is gamma2 of f and gamma1 of g: the cancelling term is not small
    assert (Xf - XP).abs().max() > 1e-2
    # summability needs common prongs: with g evaluated at its own first vertex but another cut it fails
    assert (Xf + curvature.two_prong(Lg, 4) - XP).abs().max() > 1e-2


@pytest.mark.parametrize("n", [2, 3, 4])
def test_gauge_covariance(gen, n):
    m, V = 5, 5
    vloop = list(range(V))
    L = rand_rot(m, n=n, gen=gen)
    G = rand_rot(V, n=n, gen=gen)
    Lg = torch.stack([G[vloop[k]] @ L[k] @ G[vloop[(k + 1) % m]].T for k in range(m)])
    for c in range(1, m):
        X, Xg = curvature.two_prong(L, c), curvature.two_prong(Lg, c)
        assert (Xg - G[0] @ X @ G[vloop[c]].T).abs().max() < 1e-13
    H, Hg = curvature.holonomy(L), curvature.holonomy(Lg)
    assert (Hg - G[0] @ H @ G[0].T).abs().max() < 1e-13


def test_so2_holonomy_is_rotation_by_total_angle(gen):
    """In SO(2) transports commute: the holonomy is the rotation by the sum of the edge angles."""
    ang = torch.rand(6, 5, generator=gen, dtype=torch.float64) * 6 - 3
    c, s = torch.cos(ang), torch.sin(ang)
    L = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    tot = ang.sum(-1)
    ref = torch.stack([torch.stack([tot.cos() - 1, -tot.sin()], -1), torch.stack([tot.sin(), tot.cos() - 1], -1)], -2)
    assert torch.allclose(curvature.holonomy(L), ref, atol=1e-13)


@pytest.mark.parametrize("dtype", DTYPES)
def test_dtypes_agree(gen, dtype):
    L64 = rand_rot(10, 5, gen=gen)
    L = L64.to(dtype)
    for c in [0, 2, -1]:
        X = curvature.two_prong(L, c)
        assert X.dtype == dtype
        assert (X.double() - curvature.two_prong(L64, c)).abs().max() < 50 * get_eps("identity", dtype)
    pre, nc = curvature.eval_transport(L, 2, 3)
    assert pre.dtype == dtype


def test_gradcheck_two_prong_and_holonomy(gen):
    p = (torch.randn(2, 5, 3, generator=gen, dtype=torch.float64) * 2).requires_grad_()
    cuts = torch.tensor([1, 3])
    assert torch.autograd.gradcheck(lambda q: curvature.two_prong(so3.exp(q), 2), (p,))
    assert torch.autograd.gradcheck(lambda q: curvature.two_prong(so3.exp(q), cuts), (p,))
    assert torch.autograd.gradcheck(lambda q: curvature.holonomy(so3.exp(q)), (p,))
    assert torch.autograd.gradcheck(lambda q: curvature.eval_transport(so3.exp(q), 3, 4)[0], (p,))
    assert torch.autograd.gradcheck(lambda q: curvature.cut_transport(so3.exp(q), 1, 4), (p,))


def test_errors(gen):
    L = rand_rot(4, gen=gen)
    with pytest.raises(ValueError, match="out of range"):
        curvature.two_prong(L, 4)
    with pytest.raises(ValueError, match="out of range"):
        curvature.two_prong(L, -5)
    with pytest.raises(ValueError, match="out of range"):
        curvature.two_prong(L[None].expand(2, 4, 3, 3), torch.tensor([1, 7]))
    with pytest.raises(ValueError, match="shape"):
        curvature.holonomy(torch.eye(3))
    with pytest.raises(ValueError, match="int"):
        curvature.two_prong(L, 1.0)
    with pytest.raises(ValueError, match="shift"):
        curvature.roll(L, 9)


# ---------------------------------------------------------------- mesh level
def test_face_curvature_tet_mesh_matches_slow_loop(gen):
    from torchconn import io

    mesh = io.box(n=2)
    R = rand_rot(mesh.edges.shape[0], gen=gen)
    rot = edge_table(mesh.edges.tolist(), R)
    X = curvature.face_curvature(R, mesh, cut=2)
    Xh = curvature.face_curvature(R, mesh, kind="holonomy")
    assert X.shape == (mesh.faces.shape[0], 3, 3)
    ref = torch.stack([rot(a, b) @ rot(b, c) - rot(a, c) for a, b, c in mesh.faces.tolist()])
    refh = torch.stack([rot(a, b) @ rot(b, c) @ rot(c, a) for a, b, c in mesh.faces.tolist()]) - torch.eye(3, dtype=R.dtype)
    assert (X - ref).abs().max() < 1e-14
    assert (Xh - refh).abs().max() < 1e-14
    assert torch.equal(curvature.face_curvature(R, mesh), X)  # default cut -1 = c


def test_face_curvature_accepts_connection(gen):
    from torchconn import io
    from torchconn.dec.connection import Connection

    mesh = io.box(n=1)
    conn = Connection.random(mesh.edges, mesh.n_vertices, generator=gen, dtype=torch.float64)
    assert torch.equal(curvature.face_curvature(conn, mesh), curvature.face_curvature(conn.edge_rot, mesh))


@pytest.mark.parametrize("n", [2, 3, 4])
def test_face_curvature_cell_complex_mixed_sizes(gen, n):
    from torchconn.mesh import CellComplex

    # a quad, a triangle, a pentagon and a hexagon glued around vertex 0 (faces in arbitrary global order)
    V = np.random.default_rng(0).normal(size=(12, 3))
    faces = [[0, 1, 2, 3], [0, 3, 4], [0, 4, 5, 6, 7], [0, 7, 8, 9, 10, 1], [2, 11, 3]]
    cx = CellComplex(V, faces)
    R = rand_rot(cx.edges.shape[0], n=n, gen=gen)
    rot = edge_table(cx.edges.tolist(), R)
    for kind, cut in [("two_prong", -1), ("two_prong", 1), ("holonomy", 0)]:
        X = curvature.face_curvature(R, cx, cut=cut, kind=kind)
        assert X.shape == (len(faces), n, n)
        for f, loop in enumerate(faces):
            ref = slow_two_prong(loop_from_vertices(loop, rot), 0 if kind == "holonomy" else cut)
            assert (X[f] - ref).abs().max() < 1e-13


def test_face_curvature_gradcheck(gen):
    from torchconn.mesh import CellComplex

    cx = CellComplex(np.zeros((6, 3)), [[0, 1, 2, 3], [0, 3, 4], [3, 2, 5]])
    p = torch.randn(cx.edges.shape[0], 3, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda q: curvature.face_curvature(so3.exp(q), cx, cut=1), (p,))


def test_face_curvature_errors(gen):
    from torchconn import io

    mesh = io.box(n=1)
    R = rand_rot(mesh.edges.shape[0], gen=gen)
    with pytest.raises(ValueError, match="kind"):
        curvature.face_curvature(R, mesh, kind="loop")
    with pytest.raises(ValueError, match="out of range"):
        curvature.face_curvature(R[:3], mesh)
    with pytest.raises(ValueError, match="CellComplex"):
        curvature.face_curvature(R, object())
    with pytest.raises(ValueError, match="out of range"):
        curvature.face_curvature(R, mesh, cut=3)
