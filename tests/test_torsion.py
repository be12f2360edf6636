"""Tests of torchconn.torsion: Def. 3.2 prong sums, naive / sqrt / barycentric torsion (Sec. 3.3)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import curvature, so3, son, torsion, transport
from torchconn.tolerances import get_eps


def rand_rot(*shape, n=3, gen=None, dtype=torch.float64):
    if n == 3:
        return so3.random_rotation(*shape, generator=gen, dtype=dtype)
    return son.random_rotation(*shape, n=n, generator=gen, dtype=dtype)


def slow_torsion(L, fwd, bwd, cut):
    """Def. 3.2 written out: gamma1 = x0..x_c forward, gamma2 = x0, x_{m-1}, ..., x_c (cut 0: whole loop)."""
    m, n = L.shape[0], L.shape[-1]
    c = cut % m
    c = m if c == 0 else c
    s1 = torch.zeros(n, dtype=L.dtype)
    T = torch.eye(n, dtype=L.dtype)
    for k in range(c):  # edge x_k -> x_{k+1}
        s1 = s1 + T @ fwd[k]
        T = T @ L[k]
    s2 = torch.zeros(n, dtype=L.dtype)
    T = torch.eye(n, dtype=L.dtype)
    for k in range(m - 1, c - 1, -1):  # edge x_{k+1} -> x_k, starting at x_m = x0
        s2 = s2 + T @ bwd[k]
        T = T @ L[k].T
    return s1 - s2


@pytest.mark.parametrize("n", [2, 3, 4])
def test_two_prong_matches_slow_reference(gen, n):
    m, B = 5, 4
    L = rand_rot(B, m, n=n, gen=gen)
    fwd = torch.randn(B, m, n, generator=gen, dtype=torch.float64)
    bwd = torch.randn(B, m, n, generator=gen, dtype=torch.float64)
    for cut in range(-m, m):
        got = torsion.two_prong(L, fwd, bwd, cut)
        ref = torch.stack([slow_torsion(L[b], fwd[b], bwd[b], cut) for b in range(B)])
        assert (got - ref).abs().max() < 1e-13
    cuts = torch.tensor([0, 2, 4, -2])
    got = torsion.two_prong(L, fwd, bwd, cuts)
    ref = torch.stack([slow_torsion(L[b], fwd[b], bwd[b], int(cuts[b])) for b in range(B)])
    assert (got - ref).abs().max() < 1e-13


def test_triangle_formulas(gen):
    L = rand_rot(3, gen=gen)
    H = so3.sqrt(L)
    P = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    a, b, c = P
    Rab, Rbc = L[0], L[1]
    Hab, Hbc, Hca = H
    Hac = Hca.T  # sqrt(R_ac) = sqrt(R_ca)^T
    # Def. 3.2 on [abc], cut c: (th_ab + R_ab th_bc) - th_ac
    ref = Hab @ (b - a) + Rab @ Hbc @ (c - b) - Hac @ (c - a)
    assert (torsion.sqrt(L, H, P, 2) - ref).abs().max() < 1e-13
    ref_naive = (b - a) + Rab @ (c - b) - (c - a)
    assert (torsion.naive(L, P, 2) - ref_naive).abs().max() < 1e-13


def test_reverse_solder_value(gen):
    """theta~_ji = -R_ji theta~_ij equals sqrt(R_ji) theta_ji for principal roots (erratum 9)."""
    R = rand_rot(50, gen=gen)
    H = so3.sqrt(R)
    d = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    fwd = (H @ d[..., None]).squeeze(-1)
    assert ((-(R.transpose(-1, -2) @ fwd[..., None]).squeeze(-1)) - (H.transpose(-1, -2) @ (-d)[..., None]).squeeze(-1)).abs().max() < 1e-13


def test_trivial_connection_zero_torsion(gen):
    """R = I, theta_ij = v_j - v_i: both prongs sum to x_c - x0, so the torsion is 0 for every cut."""
    m = 6
    I = torch.eye(3, dtype=torch.float64).expand(4, m, 3, 3)
    P = torch.randn(4, m, 3, generator=gen, dtype=torch.float64) * 10
    for cut in range(m):
        assert torsion.naive(I, P, cut).abs().max() < 1e-13
        assert torsion.sqrt(I, I, P, cut).abs().max() < 1e-13


def test_flat_frame_connection_zero_torsion_on_mesh(gen):
    """Frames F_i, R_ij = F_i^T F_j and theta_ij = F_i^T (v_j - v_i): zero (naive) torsion on every face,
    every cut -- the Levi-Civita connection of R^3 seen in a random frame field."""
    from torchconn import io

    mesh = io.box(n=2)
    Fr = rand_rot(mesh.n_vertices, gen=gen)
    i, j = mesh.edges[:, 0], mesh.edges[:, 1]
    R = Fr[i].transpose(-1, -2) @ Fr[j]
    for cut in (0, 1, 2):
        T = torsion.face_torsion(R, mesh, kind="naive", cut=cut, frames=Fr)
        assert T.abs().max() < 1e-13
    # the sqrt kind takes the root of the ambient (frame-independent) rotation: also exactly 0
    assert torsion.face_torsion(R, mesh, kind="sqrt", frames=Fr).abs().max() < 1e-13
    # not an empty statement: a non-flat connection in the same frames has torsion
    assert torsion.face_torsion(rand_rot(R.shape[0], gen=gen), mesh, kind="sqrt", frames=Fr).abs().max() > 1e-2


def test_cut_dependence_is_governed_by_holonomy(gen):
    """With theta_bwd = -R^T theta_fwd: Theta_0 - Theta_c = H^T (H - I) sum_{k>=c} T(x0..x_k) theta_fwd[k],
    H the loop transport at x0; in particular a flat loop (H = I) gives the same torsion for every cut."""
    m = 6
    L = rand_rot(5, m, gen=gen)
    H = so3.sqrt(L)
    P = torch.randn(5, m, 3, generator=gen, dtype=torch.float64)
    d = torch.roll(P, -1, -2) - P
    fwd = (H @ d[..., None]).squeeze(-1)
    Hol = curvature.holonomy(L) + torch.eye(3, dtype=L.dtype)
    T0 = torsion.sqrt(L, H, P, 0)
    for c in range(1, m):
        prefix = torch.stack([transport.path_product(L[:, :k]) for k in range(m)], 1)
        tail = (prefix[:, c:] @ fwd[:, c:, :, None]).squeeze(-1).sum(1)
        lhs = T0 - torsion.sqrt(L, H, P, c)
        rhs = (Hol.transpose(-1, -2) @ (Hol - torch.eye(3, dtype=L.dtype)) @ tail[..., None]).squeeze(-1)
        assert (lhs - rhs).abs().max() < 1e-12
    # flat loop: close the loop with the inverse of the other transports
    Lf = L.clone()
    Lf[:, -1] = transport.path_product(L[:, :-1]).transpose(-1, -2)
    Hf = so3.sqrt(Lf)
    for c in range(1, m):
        assert (torsion.sqrt(Lf, Hf, P, 0) - torsion.sqrt(Lf, Hf, P, c)).abs().max() < 1e-12


def test_summability_two_faces(gen):
    """f and g share the chain v0 -> w1 -> w2 -> v4; at eval v0 / cut v4 their torsions add up to P's."""
    f = [0, 1, 2, 3, 4, 8, 7]
    g = [0, 7, 8, 4, 5, 6]
    P = [0, 1, 2, 3, 4, 5, 6]
    pts = torch.randn(9, 3, generator=gen, dtype=torch.float64)
    pairs = sorted({tuple(sorted((a[k], a[(k + 1) % len(a)]))) for a in (f, g, P) for k in range(len(a))})
    Rs = rand_rot(len(pairs), gen=gen)
    table = {}
    for e, (i, j) in enumerate(pairs):
        table[(i, j)], table[(j, i)] = Rs[e], Rs[e].T

    def data(loop):
        m = len(loop)
        L = torch.stack([table[(loop[k], loop[(k + 1) % m])] for k in range(m)])
        return L, so3.sqrt(L), pts[loop]

    Tf = torsion.sqrt(*data(f), 4)
    Tg = torsion.sqrt(*data(g), 3)
    TP = torsion.sqrt(*data(P), 4)
    assert (Tf + Tg - TP).abs().max() < 1e-13
    assert (Tf - TP).abs().max() > 1e-2
    Nf, Ng, NP = (torsion.naive(data(a)[0], pts[a], c) for a, c in ((f, 4), (g, 3), (P, 4)))
    assert (Nf + Ng - NP).abs().max() < 1e-13


def test_gauge_covariance(gen):
    m = 5
    vloop = list(range(m))
    L = rand_rot(m, gen=gen)
    G = rand_rot(m, gen=gen)
    nxt = [vloop[(k + 1) % m] for k in range(m)]
    Lg = G[vloop] @ L @ G[nxt].transpose(-1, -2)
    fwd = torch.randn(m, 3, generator=gen, dtype=torch.float64)
    bwd = torch.randn(m, 3, generator=gen, dtype=torch.float64)
    fg = (G[vloop] @ fwd[..., None]).squeeze(-1)
    bg = (G[nxt] @ bwd[..., None]).squeeze(-1)
    for c in range(m):
        assert (torsion.two_prong(Lg, fg, bg, c) - G[0] @ torsion.two_prong(L, fwd, bwd, c)).abs().max() < 1e-13
    # sqrt kind: half transports midpoint -> x_k transform as G_{x_k} H_k (midpoint frames kept)
    H = so3.sqrt(L)
    P = torch.randn(m, 3, generator=gen, dtype=torch.float64)
    for c in range(m):
        assert (torsion.sqrt(Lg, G[vloop] @ H, P, c) - G[0] @ torsion.sqrt(L, H, P, c)).abs().max() < 1e-13


@pytest.mark.parametrize("kind", ["naive", "sqrt"])
def test_gauge_covariance_mesh_frames(gen, kind):
    """Frame change F'_i = F_i G_i^T with R'_ij = G_i R_ij G_j^T: face torsion -> G_a Theta (both kinds)."""
    from torchconn import io

    mesh = io.box(n=1)
    R = rand_rot(mesh.edges.shape[0], gen=gen)
    Fr = rand_rot(mesh.n_vertices, gen=gen)
    G = rand_rot(mesh.n_vertices, gen=gen)
    i, j = mesh.edges[:, 0], mesh.edges[:, 1]
    Rg = G[i] @ R @ G[j].transpose(-1, -2)
    T = torsion.face_torsion(R, mesh, kind=kind, frames=Fr)
    Tg = torsion.face_torsion(Rg, mesh, kind=kind, frames=Fr @ G.transpose(-1, -2))
    assert T.abs().max() > 1e-2
    a = mesh.faces[:, 0]
    assert (Tg - (G[a] @ T[..., None]).squeeze(-1)).abs().max() < 1e-13


def test_barycentric(gen):
    m = 4
    Rc = rand_rot(3, m, gen=gen)
    d = torch.randn(3, m, 3, generator=gen, dtype=torch.float64)
    ref = torch.stack([sum(Rc[b, k] @ d[b, k] for k in range(m)) for b in range(3)])
    assert (torsion.barycentric(Rc, d) - ref).abs().max() < 1e-13
    P = torch.randn(m, 3, generator=gen, dtype=torch.float64)
    closed = torch.roll(P, -1, 0) - P
    assert torsion.barycentric(torch.eye(3, dtype=torch.float64).expand(m, 3, 3), closed).abs().max() < 1e-13
    with pytest.raises(ValueError, match="shapes"):
        torsion.barycentric(Rc, d[..., :2])


def test_solder_form(gen):
    V = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    E = torch.tensor([[0, 1], [1, 4], [2, 3]])
    assert torch.equal(torsion.solder_form(V, E), V[E[:, 1]] - V[E[:, 0]])
    Fr = rand_rot(5, gen=gen)
    got = torsion.solder_form(V, E, Fr)
    for e, (i, j) in enumerate(E.tolist()):
        assert (got[e] - Fr[i].T @ (V[j] - V[i])).abs().max() < 1e-14
    with pytest.raises(ValueError, match="out of range"):
        torsion.solder_form(V, torch.tensor([[0, 5]]))
    with pytest.raises(ValueError, match="frames"):
        torsion.solder_form(V, E, Fr[:3])


@pytest.mark.parametrize("kind", ["sqrt", "naive"])
@pytest.mark.parametrize("use_frames", [False, True])
def test_face_torsion_tet_mesh_matches_slow_loop(gen, kind, use_frames):
    from torchconn import io

    mesh = io.box(n=2)
    R = rand_rot(mesh.edges.shape[0], gen=gen)
    Fr = rand_rot(mesh.n_vertices, gen=gen) if use_frames else None
    rot, half = {}, {}
    for e, (i, j) in enumerate(mesh.edges.tolist()):
        # with frames, the rotation read in the vertex frames and carried to the ambient frame
        Ra = Fr[i] @ R[e] @ Fr[j].T if use_frames else R[e]
        Ha = so3.sqrt(Ra)
        rot[(i, j)], rot[(j, i)] = Ra, Ra.T
        half[(i, j)], half[(j, i)] = Ha, Ha.T
    V = mesh.vertices

    def theta(i, j):
        t = V[j] - V[i]
        return half[(i, j)] @ t if kind == "sqrt" else t

    got = torsion.face_torsion(R, mesh, kind=kind, cut=2, frames=Fr)
    ref = torch.stack([
        (Fr[a].T if use_frames else torch.eye(3, dtype=R.dtype)) @ (theta(a, b) + rot[(a, b)] @ theta(b, c) - theta(a, c))
        for a, b, c in mesh.faces.tolist()
    ])
    assert (got - ref).abs().max() < 1e-13
    if not use_frames and kind == "sqrt":  # = the functional core on the loops a -> b -> c
        F = mesh.faces
        L = torch.stack([torch.stack([rot[(a, b)], rot[(b, c)], rot[(c, a)]]) for a, b, c in F.tolist()])
        assert (torsion.sqrt(L, so3.sqrt(L), V[F], 0) - torsion.face_torsion(R, mesh, cut=0)).abs().max() < 1e-13


def test_face_torsion_cell_complex(gen):
    from torchconn.mesh import CellComplex

    V = np.random.default_rng(1).normal(size=(8, 3))
    faces = [[0, 1, 2, 3], [0, 3, 4], [3, 2, 5, 6, 7]]
    cx = CellComplex(V, faces)
    R = rand_rot(cx.edges.shape[0], gen=gen)
    Vt = cx.vertices
    got = torsion.face_torsion(R, cx, kind="sqrt", cut=1)
    for f, loop in enumerate(faces):
        ei, es = cx.edge_index(torch.tensor(loop), torch.tensor(loop[1:] + loop[:1]))
        L = transport.orient(R, ei, es)
        assert (got[f] - torsion.sqrt(L, so3.sqrt(L), Vt[loop], 1)).abs().max() < 1e-13


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtypes(gen, dtype):
    L64 = rand_rot(6, 5, gen=gen)
    P64 = torch.randn(6, 5, 3, generator=gen, dtype=torch.float64)
    for c in (0, 3):
        got = torsion.sqrt(L64.to(dtype), so3.sqrt(L64.to(dtype)), P64.to(dtype), c)
        assert got.dtype == dtype
        ref = torsion.sqrt(L64, so3.sqrt(L64), P64, c)
        assert (got.double() - ref).abs().max() < 100 * get_eps("identity", dtype)


def test_gradcheck(gen):
    from torchconn.mesh import CellComplex

    p = (torch.randn(2, 4, 3, generator=gen, dtype=torch.float64) * 2).requires_grad_()
    P = torch.randn(2, 4, 3, generator=gen, dtype=torch.float64).requires_grad_()
    th = torch.randn(2, 4, 3, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda q, x: torsion.sqrt(so3.exp(q), so3.exp(q / 2), x, 2), (p, P))
    assert torch.autograd.gradcheck(lambda q, x: torsion.naive(so3.exp(q), x, 0), (p, P))
    assert torch.autograd.gradcheck(lambda q, t: torsion.two_prong(so3.exp(q), t, -t, torch.tensor([1, 3])), (p, th))
    assert torch.autograd.gradcheck(lambda q, t: torsion.barycentric(so3.exp(q), t), (p, th))
    cx = CellComplex(np.random.default_rng(2).normal(size=(5, 3)), [[0, 1, 2, 3], [0, 3, 4]])
    e = torch.randn(cx.edges.shape[0], 3, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda q: torsion.face_torsion(so3.exp(q), cx, kind="sqrt", cut=2), (e,))


def test_errors(gen):
    from torchconn import io

    L = rand_rot(4, gen=gen)
    P = torch.randn(4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="theta_fwd"):
        torsion.two_prong(L, P[:3], P, 1)
    with pytest.raises(ValueError, match="out of range"):
        torsion.naive(L, P, 4)
    with pytest.raises(ValueError, match="loop_half_rot"):
        torsion.sqrt(L, L[:3], P, 1)
    mesh = io.box(n=1)
    R4 = son.random_rotation(mesh.edges.shape[0], n=4, generator=gen, dtype=torch.float64)
    with pytest.raises(ValueError, match="n=3"):
        torsion.face_torsion(R4, mesh, kind="sqrt")
    with pytest.raises(ValueError, match="kind"):
        torsion.face_torsion(rand_rot(mesh.edges.shape[0], gen=gen), mesh, kind="barycentric")
