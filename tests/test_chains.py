"""Tests of torchconn.chains: curvature over a disk-like 2-chain (report Sec. 3.6)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import data_path
from torchconn import chains, curvature, so3, son, transport
from torchconn.mesh import CellComplex
from torchconn.tolerances import get_eps


def rand_rot(*shape, n=3, gen=None, dtype=torch.float64):
    if n == 3:
        return so3.random_rotation(*shape, generator=gen, dtype=dtype)
    return son.random_rotation(*shape, n=n, generator=gen, dtype=dtype)


def boundary_two_prong(R, cx, face_ids, e, c):
    """Reference: the region's boundary loop seen as one big face, started at e, cut at c."""
    bl = chains.boundary_loop(cx, face_ids).tolist()
    k = bl.index(e)
    loop = bl[k:] + bl[:k]
    ei, es = cx.edge_index(torch.tensor(loop), torch.tensor(loop[1:] + loop[:1]))
    return curvature.two_prong(transport.orient(R, ei, es), loop.index(c))


def prong_pairs(bl, gen, k=4):
    """Evaluation/cut pairs on a boundary loop: adjacent, far apart, reversed and equal (holonomy)."""
    L = len(bl)
    i = int(torch.randint(L, (1,), generator=gen))
    return [(bl[i], bl[(i + 1) % L]), (bl[i], bl[(i + L // 2) % L]), (bl[(i + L // 3) % L], bl[i]),
            (bl[i], bl[(i - 1) % L]), (bl[i], bl[i])][:k + 1]


def check_patch(cx, ids, gen, n=3, tol=1e-12):
    R = rand_rot(cx.edges.shape[0], n=n, gen=gen)
    bl = chains.boundary_loop(cx, ids).tolist()
    worst = 0.0
    for e, c in prong_pairs(bl, gen):
        X = chains.curvature_over_chain(R, cx, ids, e, c)
        ref = boundary_two_prong(R, cx, ids, e, c)
        assert X.shape == (n, n)
        worst = max(worst, float((X - ref).abs().max()))
        assert float(ref.abs().max()) > 1e-3  # Haar-random: the value is not trivially small
    assert worst < tol, worst
    return worst


# ---------------------------------------------------------------- complexes built here
def quad_grid(nx, ny):
    V = np.array([[i, j, 0.0] for j in range(ny + 1) for i in range(nx + 1)])
    vid = lambda i, j: j * (nx + 1) + i  # noqa: E731
    F = [[vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)] for j in range(ny) for i in range(nx)]
    return V, F, vid


def mixed_grid(nx=12, ny=10):
    """Quads, triangles (split quads) and hexagons (two merged quads) on a grid."""
    V, _, vid = quad_grid(nx, ny)
    F = []
    for j in range(ny):
        i = 0
        while i < nx:
            a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
            r = (i + 2 * j) % 5
            if r == 0 and i + 1 < nx:  # hexagon of two quads
                F.append([a, b, vid(i + 2, j), vid(i + 2, j + 1), c, d])
                i += 2
                continue
            if r in (1, 3):
                F += [[a, b, c], [a, c, d]]
            else:
                F.append([a, b, c, d])
            i += 1
    return CellComplex(V, F)


def test_boundary_loop_small():
    V, F, vid = quad_grid(2, 2)
    cx = CellComplex(V, F)
    bl = chains.boundary_loop(cx, [0, 1, 2, 3]).tolist()
    assert bl == [0, 1, 2, 5, 8, 7, 6, 3]  # counter-clockwise like the faces
    assert chains.boundary_loop(cx, [2]).tolist() == [3, 4, 7, 6]


@pytest.mark.parametrize("n", [2, 3, 4])
def test_chain_equals_boundary_two_prong_polygon_grid(gen, n):
    cx = mixed_grid()
    sizes = {m: int(g.face_ids.numel()) for m, g in cx.face_groups.items()}
    assert set(sizes) == {3, 4, 6}
    ids = chains.patch(cx, seed_face=40, n_faces=70)
    assert len(ids) == 70
    check_patch(cx, ids, gen, n=n)


def test_chain_face_order_does_not_matter(gen):
    """The input order of the faces (here random, not a shelling) is irrelevant."""
    V, F, vid = quad_grid(8, 8)
    cx = CellComplex(V, F)
    ids = torch.randperm(len(F), generator=gen)
    R = rand_rot(cx.edges.shape[0], gen=gen)
    X = chains.curvature_over_chain(R, cx, ids, vid(0, 0), vid(8, 8))
    Y = chains.curvature_over_chain(R, cx, ids.flip(0), vid(0, 0), vid(8, 8))
    ref = boundary_two_prong(R, cx, ids, vid(0, 0), vid(8, 8))
    assert (X - ref).abs().max() < 1e-12 and (Y - ref).abs().max() < 1e-12


def triangulated_disk_grid(k=9):
    V, _, vid = quad_grid(k, k)
    F = []
    for j in range(k):
        for i in range(k):
            a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
            F += [[a, b, c], [a, c, d]] if (i + j) % 2 else [[a, b, d], [b, c, d]]
    return CellComplex(V, F)


def test_chain_triangle_grid(gen):
    cx = triangulated_disk_grid()
    check_patch(cx, chains.patch(cx, 80, 120), gen)
    check_patch(cx, torch.arange(cx.face_sizes.numel()), gen)  # the whole disk


def test_chain_triangle_surface_bunny(gen):
    from torchconn import io

    V, F = io.load_surface(data_path("bunny.obj"))
    cx = CellComplex.from_triangles(V, F)
    w = check_patch(cx, chains.patch(cx, seed_face=1000, n_faces=80), gen)
    assert w < 1e-12


def test_chain_tet_boundary_ball(gen):
    from torchconn import io

    mesh = io.ball(edge_length=0.35)
    cx = mesh.boundary_complex()
    ids = chains.patch(cx, seed_face=0, n_faces=60)
    check_patch(cx, ids, gen)
    # SO(4) on the same patch
    check_patch(cx, ids, gen, n=4)


def test_chain_tet_boundary_shared_sphere(gen):
    from torchconn import io

    cx = io.load_tet_mesh(data_path("sphere_r0.17.mesh")).boundary_complex()
    check_patch(cx, chains.patch(cx, seed_face=5, n_faces=200), gen)


def test_single_face_chain(gen):
    V, F, vid = quad_grid(2, 1)
    cx = CellComplex(V, F)
    R = rand_rot(cx.edges.shape[0], gen=gen)
    loop = F[1]
    ei, es = cx.edge_index(torch.tensor(loop), torch.tensor(loop[1:] + loop[:1]))
    L = transport.orient(R, ei, es)
    for k in range(4):
        for c in range(4):
            X = chains.curvature_over_chain(R, cx, [1], loop[k], loop[c])
            ref = curvature.two_prong(curvature.roll(L, k), (c - k) % 4)
            assert (X - ref).abs().max() < 1e-13


def test_chain_gauge_covariance(gen):
    V, F, vid = quad_grid(6, 5)
    cx = CellComplex(V, F)
    R = rand_rot(cx.edges.shape[0], gen=gen)
    G = rand_rot(V.shape[0], gen=gen)
    i, j = cx.edges[:, 0], cx.edges[:, 1]
    Rg = G[i] @ R @ G[j].transpose(-1, -2)
    ids = chains.patch(cx, 12, 20)
    bl = chains.boundary_loop(cx, ids).tolist()
    e, c = bl[0], bl[len(bl) // 2]
    X = chains.curvature_over_chain(R, cx, ids, e, c)
    Xg = chains.curvature_over_chain(Rg, cx, ids, e, c)
    assert (Xg - G[e] @ X @ G[c].T).abs().max() < 1e-12
    H, Hg = (chains.curvature_over_chain(S, cx, ids, e, e) for S in (R, Rg))
    assert (Hg - G[e] @ H @ G[e].T).abs().max() < 1e-12


def test_chain_summability_of_two_patches(gen):
    """(3.2.2) on 2-chains: two disks sharing a boundary chain add up at the chain's ends."""
    V, F, vid = quad_grid(6, 4)
    cx = CellComplex(V, F)
    R = rand_rot(cx.edges.shape[0], gen=gen)
    left = [j * 6 + i for j in range(4) for i in range(3)]
    right = [j * 6 + i for j in range(4) for i in range(3, 6)]
    top, bot = vid(3, 4), vid(3, 0)  # ends of the shared chain x = 3
    Xl = chains.curvature_over_chain(R, cx, left, top, bot)  # left runs the chain downwards
    Xr = chains.curvature_over_chain(R, cx, right, top, bot)
    X = chains.curvature_over_chain(R, cx, left + right, top, bot)
    assert (Xl + Xr - X).abs().max() < 1e-12


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_chain_dtypes(gen, dtype):
    cx = triangulated_disk_grid(6)
    ids = chains.patch(cx, 10, 50)
    R64 = rand_rot(cx.edges.shape[0], gen=gen)
    bl = chains.boundary_loop(cx, ids).tolist()
    X = chains.curvature_over_chain(R64.to(dtype), cx, ids, bl[0], bl[7])
    assert X.dtype == dtype
    assert (X.double() - boundary_two_prong(R64, cx, ids, bl[0], bl[7])).abs().max() < 200 * get_eps("identity", dtype)


def test_chain_gradcheck(gen):
    V, F, vid = quad_grid(3, 2)
    cx = CellComplex(V, F)
    p = torch.randn(cx.edges.shape[0], 3, generator=gen, dtype=torch.float64).requires_grad_()
    ids = [0, 1, 2, 4, 5]
    assert torch.autograd.gradcheck(lambda q: chains.curvature_over_chain(so3.exp(q), cx, ids, vid(0, 0), vid(2, 2)), (p,))


def test_shelling_order_is_a_permutation(gen):
    cx = mixed_grid(6, 6)
    ids = torch.randperm(cx.face_sizes.numel(), generator=gen).tolist()
    order = chains.shelling_order(cx, ids)
    assert sorted(order) == sorted(ids)


# ---------------------------------------------------------------- bad input
def test_not_a_disk_errors(gen):
    V, F, vid = quad_grid(3, 3)
    cx = CellComplex(V, F)
    R = rand_rot(cx.edges.shape[0], gen=gen)
    ring = [0, 1, 2, 3, 5, 6, 7, 8]  # annulus around the middle quad
    with pytest.raises(ValueError, match="several boundary components"):
        chains.boundary_loop(cx, ring)
    with pytest.raises(ValueError, match="not connected"):
        chains.boundary_loop(cx, [0, 8])
    with pytest.raises(ValueError, match="not on the region boundary"):
        chains.curvature_over_chain(R, cx, list(range(9)), vid(1, 1), vid(0, 0))
    with pytest.raises(ValueError, match="duplicates"):
        chains.boundary_loop(cx, [0, 0])
    with pytest.raises(ValueError, match="out of range"):
        chains.boundary_loop(cx, [0, 99])
    V4, F4, vid4 = quad_grid(4, 4)
    cx4 = CellComplex(V4, F4)
    # faces (1,1) and (2,2) meet only at vertex (2,2); the rest of the patch connects them around
    with pytest.raises(ValueError, match=f"vertex {vid4(2, 2)} is a non-manifold \\(pinched\\)"):
        chains.boundary_loop(cx4, [5, 4, 8, 12, 13, 14, 10])
    flipped = CellComplex(V, [F[0], F[1][::-1]])
    with pytest.raises(ValueError, match="consistently oriented"):
        chains.boundary_loop(flipped, [0, 1])


def test_punctured_torus_is_not_a_disk():
    """One boundary loop and edge-connected, but Euler characteristic -1."""
    k = 4
    V = np.array([[i, j, 0.0] for j in range(k) for i in range(k)])
    vid = lambda i, j: (j % k) * k + (i % k)  # noqa: E731
    F = [[vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)] for j in range(k) for i in range(k)]
    cx = CellComplex(V, F)
    with pytest.raises(ValueError, match="Euler characteristic -1"):
        chains.boundary_loop(cx, list(range(1, k * k)))
    with pytest.raises(ValueError, match="no boundary"):
        chains.boundary_loop(cx, list(range(k * k)))


def test_closed_surface_errors(gen):
    # tetrahedron surface: no boundary
    V = np.eye(4, 3)
    cx = CellComplex(V, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    with pytest.raises(ValueError, match="no boundary"):
        chains.boundary_loop(cx, [0, 1, 2, 3])
    with pytest.raises(ValueError, match="could only grow"):
        chains.patch(cx, 0, 4)
