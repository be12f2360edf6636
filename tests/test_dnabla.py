"""Tests of torchconn.dnabla: Defs. 5.1-5.2 (corrected), Lie Alt, the Ch. 5 tet formula, BEHS21,
primal-dual Defs. 4.1-4.2, against slow per-element references written plainly here."""
from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchconn import dnabla as D
from torchconn import curvature, so3, son, transport
from torchconn.mesh import TetMesh
from torchconn.tolerances import get_eps

F64 = torch.float64
ABCD = (0, 1, 2, 3)


# ----------------------------------------------------------------------------- helpers

def rand_T(B, gen, dtype=F64, n=3, s=4):
    """Haar-random transports for every pair of a batch of s-simplices, dense, plus the half table."""
    P = s * (s - 1) // 2
    if n == 3:
        K = so3.hat(torch.randn(B, P, 3, generator=gen, dtype=dtype) * 1.5)
        pair = so3.random_rotation(B, P, generator=gen, dtype=dtype)
        # half transports of the Haar rotations through the principal log (angle < pi a.s.)
        half = so3.sqrt(pair)
    else:
        K = torch.randn(B, P, n, n, generator=gen, dtype=dtype)
        K = K - K.transpose(-1, -2)
        pair = son.exp(K)
        half = son.exp(0.5 * K)
    del K
    return transport.dense_simplex_transports(pair, s), transport.dense_simplex_transports(half, s)


def perm_sign(p):
    inv = sum(1 for a in range(len(p)) for b in range(a + 1, len(p)) if p[a] > p[b])
    return -1 if inv % 2 else 1


def slow_unsym_vector(T, alpha, t):
    """R_{x0x1} α[x1..] + Σ_{j>=1} (-1)^j α[t without j], one tuple, plain Python."""
    out = T[..., t[0], t[1], :, :] @ alpha[(Ellipsis,) + tuple(t[1:]) + (slice(None),)].unsqueeze(-1)
    out = out.squeeze(-1)
    for j in range(1, len(t)):
        face = tuple(t[:j]) + tuple(t[j + 1:])
        out = out + (-1) ** j * alpha[(Ellipsis,) + face + (slice(None),)]
    return out


def slow_alt_vector(T, alpha, t):
    m = len(t)
    out = 0
    for p in itertools.permutations(range(m)):
        tp = tuple(t[i] for i in p)
        out = out + perm_sign(p) * (T[..., t[0], tp[0], :, :] @ alpha[(Ellipsis,) + tp + (slice(None),)].unsqueeze(-1)).squeeze(-1)
    return out / math.factorial(m)


def slow_wedge(T, th):
    """End of Ch. 5, written with named R_ab etc. (one batch of tets)."""
    R = {}
    for i, x in enumerate("abcd"):
        for j, y in enumerate("abcd"):
            R[x + y] = T[..., i, j, :, :]
    t = {x + y: th[..., i, j, :, None] for i, x in enumerate("abcd") for j, y in enumerate("abcd")}
    Rab, Rac, Rad, Rbc, Rbd, Rcd = R["ab"], R["ac"], R["ad"], R["bc"], R["bd"], R["cd"]
    Rcb, Rdb, Rdc = R["cb"], R["db"], R["dc"]
    v = ((Rac @ Rcb - Rad @ Rdb) @ t["ba"] - (Rab @ Rbc - Rad @ Rdc) @ t["ca"]
         + (Rac - Rab @ Rbd @ Rdc) @ t["cb"] + (Rab @ Rbd - Rac @ Rcd) @ t["da"]
         - (Rad - Rab @ Rbc @ Rcd) @ t["db"] + (Rad - Rab @ Rbd) @ t["dc"]) / 6
    v = v + ((Rac - Rab @ Rbc) @ t["cb"] - (Rad - Rab @ Rbd) @ t["db"] + (Rad - Rab @ Rbd) @ t["dc"]) / 3
    v = v + (Rab @ Rbc - Rac) @ t["cd"] / 2
    return v.squeeze(-1)


def theta_tilde(Th, pts):
    return D.solder_form_sqrt(Th, pts)


def tol(dtype, scale=1.0):
    return 50 * get_eps("identity", dtype) * scale if dtype == torch.float32 else 1e-12 * scale


# ----------------------------------------------------------------------------- Def. 5.1 / curvature

@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_curvature_of_connection_form_on_every_ordered_triangle(gen, dtype):
    T, _ = rand_T(6, gen, dtype)
    omega = D.unsymmetrized_vector(T, D.connection_form(T), matrix_values=True)
    assert omega.shape == (6, 4, 4, 4, 3, 3)
    for a, b, c in itertools.permutations(range(4), 3):
        R_ab, R_bc, R_ac = T[:, a, b], T[:, b, c], T[:, a, c]
        torch.testing.assert_close(omega[:, a, b, c], R_ab @ R_bc - R_ac, atol=tol(dtype), rtol=0)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_differential_bianchi_every_ordering_any_rank(gen, n):
    T, _ = rand_T(5, gen, F64, n=n)
    omega = D.unsymmetrized_vector(T, D.connection_form(T), matrix_values=True)
    dom = D.unsymmetrized_lie(T, omega)
    for p in itertools.permutations(range(4)):
        assert dom[(slice(None),) + p].abs().max() < 1e-12
    # the closed form of Ch. 5 term by term on [abcd]: each of its four terms is O(1)
    R = lambda i, j: T[:, i, j]  # noqa: E731
    terms = [R(0, 1) @ (R(1, 2) @ R(2, 3) - R(1, 3)), -(R(0, 2) @ R(2, 3) - R(0, 3)),
             R(0, 1) @ R(1, 3) - R(0, 3), -(R(0, 1) @ R(1, 2) - R(0, 2)) @ R(2, 3)]
    assert min(float(x.abs().max()) for x in terms) > 1e-3
    torch.testing.assert_close(dom[:, 0, 1, 2, 3], sum(terms), atol=1e-12, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_lie_alt_fixes_curvature(gen, dtype):
    T, _ = rand_T(6, gen, dtype)
    omega = D.unsymmetrized_vector(T, D.connection_form(T), matrix_values=True)
    alt = D.alt_lie(T, omega)
    for t in itertools.permutations(range(4), 3):
        torch.testing.assert_close(alt[(slice(None),) + t], omega[(slice(None),) + t], atol=tol(dtype), rtol=0)
    # a generic Lie 2-form is changed by Alt (the test can fail)
    beta = torch.randn(6, 4, 4, 4, 3, 3, generator=gen, dtype=dtype)
    assert (D.alt_lie(T, beta) - beta)[:, 0, 1, 2].abs().max() > 1e-2


def test_lie_alt_slow_reference_triangle(gen):
    T, _ = rand_T(4, gen, F64, s=3)
    beta = torch.randn(4, 3, 3, 3, 3, 3, generator=gen, dtype=F64)
    out = D.alt_lie(T, beta)
    for x0, x1, x2 in itertools.permutations(range(3)):
        acc = 0
        for y, y1, y2 in ((x0, x1, x2), (x1, x2, x0), (x2, x0, x1)):
            A = 0.5 * (beta[:, y, y1, y2] - beta[:, y, y2, y1] @ T[:, y1, y2])
            acc = acc + T[:, x0, y] @ A @ T[:, y2, x2]
        torch.testing.assert_close(out[:, x0, x1, x2], acc / 3, atol=1e-13, rtol=0)


def test_lie_alt_1form_fixes_covariant_derivative_of_0form(gen):
    T, _ = rand_T(3, gen, F64)
    phi = torch.randn(3, 4, 3, 3, generator=gen, dtype=F64)
    dphi = D.unsymmetrized_lie(T, phi)  # R_01 φ_1 - φ_0 R_01
    for a, b in itertools.permutations(range(4), 2):
        torch.testing.assert_close(dphi[:, a, b], T[:, a, b] @ phi[:, b] - phi[:, a] @ T[:, a, b], atol=1e-13, rtol=0)
    alt = D.alt_lie(T, dphi)
    for a, b in itertools.permutations(range(4), 2):
        torch.testing.assert_close(alt[:, a, b], dphi[:, a, b], atol=1e-13, rtol=0)
    # the differential Bianchi analogue for a 0-form: 𝔡∇𝔡∇φ = [Ω, φ]-type curvature term, not 0
    ddphi = D.unsymmetrized_lie(T, dphi, [[0, 1, 2]]).squeeze(-3)
    R_ab, R_bc, R_ac = T[:, 0, 1], T[:, 1, 2], T[:, 0, 2]
    Om = R_ab @ R_bc - R_ac
    torch.testing.assert_close(ddphi, Om @ phi[:, 2] - phi[:, 0] @ Om, atol=1e-12, rtol=0)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_unsymmetrized_and_alt_vector_vs_slow(gen, k):
    T, _ = rand_T(3, gen, F64)
    alpha = torch.randn(3, *([4] * (k + 1)), 3, generator=gen, dtype=F64)
    d = D.unsymmetrized_vector(T, alpha)
    a = D.alt_vector(T, alpha)
    for t in itertools.product(range(4), repeat=k + 2):
        torch.testing.assert_close(d[(slice(None),) + t], slow_unsym_vector(T, alpha, t), atol=1e-13, rtol=0)
    for t in itertools.product(range(4), repeat=k + 1):
        torch.testing.assert_close(a[(slice(None),) + t], slow_alt_vector(T, alpha, t), atol=1e-13, rtol=0)
    # explicit tuples give the same entries as the dense evaluation
    tup = torch.tensor([[3, 1, 0, 2][: k + 2], [0, 1, 2, 3][: k + 2]])
    torch.testing.assert_close(D.unsymmetrized_vector(T, alpha, tup), torch.stack([d[(slice(None),) + tuple(r.tolist())] for r in tup], 1))


def test_unsymmetrized_lie_vs_slow(gen):
    T, _ = rand_T(3, gen, F64)
    beta = torch.randn(3, 4, 4, 4, 3, 3, generator=gen, dtype=F64)
    out = D.unsymmetrized_lie(T, beta)
    for x0, x1, x2, x3 in itertools.product(range(4), repeat=4):
        ref = (T[:, x0, x1] @ beta[:, x1, x2, x3] - beta[:, x0, x2, x3] + beta[:, x0, x1, x3]
               - beta[:, x0, x1, x2] @ T[:, x2, x3])
        torch.testing.assert_close(out[:, x0, x1, x2, x3], ref, atol=1e-13, rtol=0)


def test_alt_vector_properties(gen):
    T, Th = rand_T(5, gen, F64)
    pts = torch.randn(5, 4, 3, generator=gen, dtype=F64)
    th = theta_tilde(Th, pts)
    # θ̃_ji = -R_ji θ̃_ij, hence Alt θ̃ = θ̃ (Alt on the 1-form changes nothing) ...
    for i, j in itertools.permutations(range(4), 2):
        torch.testing.assert_close(th[:, j, i], -(T[:, j, i] @ th[:, i, j, :, None]).squeeze(-1), atol=1e-13, rtol=0)
    torch.testing.assert_close(D.alt_vector(T, th), th, atol=1e-13, rtol=0)
    # ... while the plain θ is changed by it
    theta = D.solder_form(pts)
    torch.testing.assert_close(D.solder_form_sqrt(Th, theta), th, atol=0, rtol=0)  # θ or points accepted
    assert (D.alt_vector(T, theta) - theta).abs().max() > 1e-2
    # Alt of a 1-form is alternating under transport; Alt of a 2-form is antisymmetric when x0 is fixed
    a1 = D.alt_vector(T, theta)
    torch.testing.assert_close(a1[:, 1, 0], -(T[:, 1, 0] @ a1[:, 0, 1, :, None]).squeeze(-1), atol=1e-13, rtol=0)
    a2 = D.alt_vector(T, torch.randn(5, 4, 4, 4, 3, generator=gen, dtype=F64))
    torch.testing.assert_close(a2[:, 0, 2, 1], -a2[:, 0, 1, 2], atol=1e-13, rtol=0)


# ----------------------------------------------------------------------------- Ch. 5 tet formula

@pytest.mark.parametrize("n", [3, 4])
def test_averaged_dd_equals_explicit_tet_formula(gen, n):
    T, Th = rand_T(8, gen, F64, n=n)
    pts = torch.randn(8, 4, n, generator=gen, dtype=F64)
    th = theta_tilde(Th, pts)
    dd = D.averaged_dd_tet(T, th)
    ref = slow_wedge(T, th)
    assert ref.abs().max() > 0.1
    torch.testing.assert_close(dd, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(D.wedge_curvature_solder_tet(T, th), ref, atol=1e-13, rtol=0)
    # the fully dense route (Def. 5.2 twice on every tuple) agrees with the sparse one
    dense = D.averaged(T, D.averaged(T, th))[:, 0, 1, 2, 3]
    torch.testing.assert_close(dense, dd, atol=1e-13, rtol=0)
    # Alt on the 1-form is a no-op here: 𝔡∇ Alt 𝔡∇ θ̃ gives the same value
    torch.testing.assert_close(D.averaged(T, D.unsymmetrized_vector(T, th), [ABCD]).squeeze(-2), dd, atol=1e-12, rtol=0)


def test_averaged_dd_float32(gen):
    T, Th = rand_T(16, gen, torch.float32)
    pts = torch.randn(16, 4, 3, generator=gen, dtype=torch.float32)
    th = theta_tilde(Th, pts)
    dd = D.averaged_dd_tet(T, th)
    assert dd.dtype == torch.float32
    torch.testing.assert_close(dd, slow_wedge(T, th), atol=tol(torch.float32, 10), rtol=0)


def test_behs21_twice_is_curvature_times_theta(gen):
    T, _ = rand_T(6, gen, F64)
    pts = torch.randn(6, 4, 3, generator=gen, dtype=F64)
    theta = D.solder_form(pts)
    R_ab, R_bc, R_ac = T[:, 0, 1], T[:, 1, 2], T[:, 0, 2]
    ref = ((R_ab @ R_bc - R_ac) @ theta[:, 2, 3, :, None]).squeeze(-1)
    torch.testing.assert_close(D.behs21_dd_tet(T, theta), ref, atol=1e-12, rtol=0)
    # Ch. 4 display: R_ab[bcd] - [acd] + [abd] - [abc] with [xyz] = R_xy θ_yz - θ_xz + θ_xy
    th = lambda i, j: theta[:, i, j, :, None]  # noqa: E731
    tri = lambda x, y, z: T[:, x, y] @ th(y, z) - th(x, z) + th(x, y)  # noqa: E731
    ch4 = T[:, 0, 1] @ tri(1, 2, 3) - tri(0, 2, 3) + tri(0, 1, 3) - tri(0, 1, 2)
    torch.testing.assert_close(D.behs21_dd_tet(T, theta), ch4.squeeze(-1), atol=1e-12, rtol=0)


def test_alternation_flips_sign_swapping_last_two_vertices(gen):
    """𝔡∇ Alt α at [x0 x1 x3 x2] = -[x0 x1 x2 x3] exactly: Alt is antisymmetric when the first
    label is fixed, and the transported term R_{x0x1} keeps its edge. Other odd relabelings
    change the transport paths, so there the flip holds only up to curvature terms."""
    T, Th = rand_T(5, gen, F64)
    pts = torch.randn(5, 4, 3, generator=gen, dtype=F64)
    th = theta_tilde(Th, pts)
    dd = D.averaged_dd_tet(T, th)
    idx = torch.tensor((0, 1, 3, 2))
    Tp, thp = T[:, idx][:, :, idx], th[:, idx][:, :, idx]
    torch.testing.assert_close(D.averaged_dd_tet(Tp, thp), -dd, atol=1e-12, rtol=0)
    torch.testing.assert_close(D.wedge_curvature_solder_tet(Tp, thp), -dd, atol=1e-12, rtol=0)
    # the same holds for the averaged d∇ of any alternated vector 2-form
    alpha = torch.randn(5, 4, 4, 4, 3, generator=gen, dtype=F64)
    d0 = D.averaged(T, alpha, [ABCD])
    d1 = D.averaged(Tp, alpha[:, idx][:, :, idx][:, :, :, idx], [ABCD])
    torch.testing.assert_close(d1, -d0, atol=1e-12, rtol=0)
    # the unaveraged BEHS21 value lacks this symmetry (so the check above can fail)
    theta = D.solder_form(pts)
    b0 = D.behs21_dd_tet(T, theta)
    b1 = D.behs21_dd_tet(Tp, theta[:, idx][:, :, idx])
    assert (b0 + b1).abs().max() > 1e-2


def test_gauge_covariance(gen):
    T, Th = rand_T(5, gen, F64)
    pts = torch.randn(5, 4, 3, generator=gen, dtype=F64)
    th = theta_tilde(Th, pts)
    G = so3.random_rotation(5, 4, generator=gen, dtype=F64)
    gauge = lambda X: G[:, :, None] @ X @ G[:, None, :].transpose(-1, -2)  # noqa: E731
    T2, Th2 = gauge(T), gauge(Th)
    th2 = (G[:, :, None] @ th.unsqueeze(-1)).squeeze(-1)
    dd2 = D.averaged_dd_tet(T2, th2)
    torch.testing.assert_close(dd2, (G[:, 0] @ D.averaged_dd_tet(T, th)[..., None]).squeeze(-1), atol=1e-12, rtol=0)
    # Lie values transform as G_eval X G_cut^T
    om = D.unsymmetrized_vector(T, D.connection_form(T), matrix_values=True)
    om2 = D.unsymmetrized_vector(T2, D.connection_form(T2), matrix_values=True)
    for a, b, c in itertools.permutations(range(4), 3):
        torch.testing.assert_close(om2[:, a, b, c], G[:, a] @ om[:, a, b, c] @ G[:, c].transpose(-1, -2), atol=1e-12, rtol=0)
    assert D.unsymmetrized_lie(T2, om2)[:, 0, 1, 2, 3].abs().max() < 1e-12


def test_gradcheck_averaged_dd(gen):
    params = (torch.randn(2, 6, 3, generator=gen, dtype=F64) * 0.8).requires_grad_()
    pts = torch.randn(2, 4, 3, generator=gen, dtype=F64)

    def f(p):
        T = transport.dense_simplex_transports(so3.exp(p), 4)
        Th = transport.dense_simplex_transports(so3.exp(0.5 * p), 4)
        return D.averaged_dd_tet(T, theta_tilde(Th, pts))

    assert torch.autograd.gradcheck(f, (params,))
    # at the flat connection (params = 0: Taylor branch of exp) the gradient is finite and exact too
    assert torch.autograd.gradcheck(f, (torch.zeros_like(params).requires_grad_(),))

    def g(p):
        T = transport.dense_simplex_transports(so3.exp(p), 4)
        om = D.unsymmetrized_vector(T, D.connection_form(T), matrix_values=True)
        return D.averaged(T, om, [ABCD], lie=True)

    assert torch.autograd.gradcheck(g, (params,))


# ----------------------------------------------------------------------------- primal-dual

def rand_dual(B, gen, dtype=F64):
    return (so3.random_rotation(B, 4, generator=gen, dtype=dtype), so3.random_rotation(B, 4, 3, generator=gen, dtype=dtype),
            torch.randn(B, 6, 3, generator=gen, dtype=dtype))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_primal_dual_dd_equals_curvature_pair_form(gen, dtype):
    tf, fe, ev = rand_dual(7, gen, dtype)
    dd = D.primal_dual_dd(tf, fe, ev)
    assert dd.abs().max() > 0.1
    torch.testing.assert_close(D.primal_dual_wedge(tf, fe, ev), dd, atol=tol(dtype, 10), rtol=0)
    # slow reference of Def. 4.2 twice with explicit faces/edges
    pair_index = {p: a for a, p in enumerate(transport.pair_list(4))}
    ref = 0
    for k, (p, q, r) in enumerate(((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))):
        face = 0
        for m, (e, sgn) in enumerate((((q, r), 1), ((p, r), -1), ((p, q), 1))):
            face = face + sgn * (fe[:, k, m] @ ev[:, pair_index[e], :, None])
        ref = ref + (-1) ** k * (tf[:, k] @ face)
    torch.testing.assert_close(dd, ref.squeeze(-1), atol=tol(dtype, 10), rtol=0)


def _physical_dual(gen):
    """Dual transports and edge values attached to the physical segments of a tet [0123]."""
    faces = [frozenset(f) for f in itertools.combinations(range(4), 3)]
    Rtf = {f: so3.random_rotation(generator=gen, dtype=F64) for f in faces}
    Rfe = {(f, frozenset(e)): so3.random_rotation(generator=gen, dtype=F64)
           for f in faces for e in itertools.combinations(sorted(f), 2)}
    alpha = {e: torch.randn(3, generator=gen, dtype=F64) for e in itertools.combinations(range(4), 2)}
    return Rtf, Rfe, alpha


def _template(x, Rtf, Rfe, alpha):
    """Local template arguments for the vertex order x (local label i = physical x[i])."""
    tf, fe = [], []
    for (p, q, r) in D.TET_FACES:
        f = frozenset((x[p], x[q], x[r]))
        tf.append(Rtf[f])
        fe.append(torch.stack([Rfe[(f, frozenset((x[u], x[v])))] for u, v in ((q, r), (p, r), (p, q))]))
    ev = []
    for i, j in transport.pair_list(4):
        a, b = x[i], x[j]
        ev.append(alpha[(a, b)] if a < b else -alpha[(b, a)])
    return torch.stack(tf), torch.stack(fe), torch.stack(ev)


def test_primal_dual_orientation_flip(gen):
    Rtf, Rfe, alpha = _physical_dual(gen)
    base = D.primal_dual_wedge(*_template((0, 1, 2, 3), Rtf, Rfe, alpha))
    assert base.abs().max() > 0.1
    for x in itertools.permutations(range(4)):
        args = _template(x, Rtf, Rfe, alpha)
        torch.testing.assert_close(D.primal_dual_wedge(*args), perm_sign(x) * base, atol=1e-12, rtol=0)
        torch.testing.assert_close(D.primal_dual_dd(*args), perm_sign(x) * base, atol=1e-12, rtol=0)


def test_primal_dual_gradcheck(gen):
    p1 = (torch.randn(2, 4, 3, generator=gen, dtype=F64)).requires_grad_()
    p2 = (torch.randn(2, 4, 3, 3, generator=gen, dtype=F64)).requires_grad_()
    ev = torch.randn(2, 6, 3, generator=gen, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: D.primal_dual_wedge(so3.exp(a), so3.exp(b), c), (p1, p2, ev))


# ----------------------------------------------------------------------------- mesh wrappers

def two_tets():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.2]], dtype=F64)
    return TetMesh(v, [[0, 1, 2, 3], [1, 2, 3, 4]], reorient=True)


def edge_R(mesh, edge_rot, i, j):
    """R_ij looked up plainly from the canonical edge list."""
    for e, (a, b) in enumerate(mesh.edges.tolist()):
        if (a, b) == (i, j):
            return edge_rot[e]
        if (a, b) == (j, i):
            return edge_rot[e].T
    raise KeyError((i, j))


def test_mesh_wrappers_vs_per_tet_reference(gen):
    mesh = two_tets()
    er = so3.random_rotation(mesh.edges.shape[0], generator=gen, dtype=F64)
    half = so3.sqrt(er)
    dd = D.averaged_dd_solder(er, mesh)
    wd = D.wedge_solder(er, mesh)
    bh = D.behs21_dd_solder(er, mesh)
    for t, tet in enumerate(mesh.tets.tolist()):
        T = torch.stack([torch.stack([edge_R(mesh, er, i, j) if i != j else torch.eye(3, dtype=F64) for j in tet]) for i in tet])
        Th = torch.stack([torch.stack([edge_R(mesh, half, i, j) if i != j else torch.eye(3, dtype=F64) for j in tet]) for i in tet])
        th = theta_tilde(Th, mesh.vertices[tet])
        torch.testing.assert_close(dd[t], slow_wedge(T, th), atol=1e-12, rtol=0)
        torch.testing.assert_close(wd[t], slow_wedge(T, th), atol=1e-12, rtol=0)
        a, b, c, d_ = tet
        R_ab, R_bc, R_ac = edge_R(mesh, er, a, b), edge_R(mesh, er, b, c), edge_R(mesh, er, a, c)
        torch.testing.assert_close(bh[t], (R_ab @ R_bc - R_ac) @ (mesh.vertices[d_] - mesh.vertices[c]), atol=1e-12, rtol=0)
    om = _curvature_2form_ref(er, mesh)
    for f, (a, b, c) in enumerate(mesh.faces.tolist()):
        ref = edge_R(mesh, er, a, b) @ edge_R(mesh, er, b, c) - edge_R(mesh, er, a, c)
        torch.testing.assert_close(om[f], ref, atol=1e-13, rtol=0)
    # the public face curvature (fused kernel on a tet mesh) is the same two-prong form
    torch.testing.assert_close(curvature.face_curvature(er, mesh), om, atol=1e-13, rtol=0)


def _curvature_2form_ref(edge_rot, mesh):
    """Slow reference: ``⟨Ω,[abc]⟩_a^c = R_ab R_bc - R_ac`` as ``𝔡∇w`` on the face template (Ch. 5).

    The vector version of 𝔡∇ applied column-wise to the matrix-valued connection form ``w``;
    evaluation ``a = faces[f,0]``, cut ``c = faces[f,2]``: ``(F, n, n)``.
    """
    fe = mesh.face_edges.to(edge_rot.device)
    # pair_list(3) = (01, 02, 12) = (ab, ac, bc) = face_edges slots (2, 1, 0); all canonical (a<b<c)
    T = transport.dense_simplex_transports(edge_rot[fe[:, [2, 1, 0]]], 3)
    tri = torch.tensor([[0, 1, 2]], dtype=torch.long, device=edge_rot.device)
    return D.unsymmetrized_vector(T, D.connection_form(T), tri, matrix_values=True).squeeze(-3)


@pytest.mark.parametrize("n", [3, 4])
def test_curvature_2form_reference_equals_face_curvature(gen, n):
    """𝔡∇w on every face of a tet mesh equals :func:`torchconn.curvature.face_curvature` (any rank)."""
    from torchconn import io

    mesh = io.box(2)
    er = son.random_rotation(mesh.edges.shape[0], n=n, generator=gen, dtype=F64)
    ref = _curvature_2form_ref(er, mesh)
    assert ref.shape == (mesh.faces.shape[0], n, n) and ref.abs().max() > 0.1
    torch.testing.assert_close(curvature.face_curvature(er, mesh), ref, atol=1e-13, rtol=0)


def test_mesh_frames_and_half_rot_gauge(gen):
    mesh = two_tets()
    er = so3.random_rotation(mesh.edges.shape[0], generator=gen, dtype=F64)
    half = so3.sqrt(er)
    Fr = so3.random_rotation(mesh.vertices.shape[0], generator=gen, dtype=F64)  # frame columns
    i, j = mesh.edges[:, 0], mesh.edges[:, 1]
    G = Fr.transpose(-1, -2)  # coordinates in the frame: x' = F^T x
    er2 = G[i] @ er @ G[j].transpose(-1, -2)
    half2 = G[i] @ half @ G[j].transpose(-1, -2)
    dd = D.averaged_dd_solder(er, mesh)
    dd2 = D.averaged_dd_solder(er2, mesh, frames=Fr, half_rot=half2)
    a = mesh.tets[:, 0]
    torch.testing.assert_close(dd2, (G[a] @ dd[..., None]).squeeze(-1), atol=1e-12, rtol=0)
    # default half transports (sqrt taken in the ambient frame) and the explicit wedge agree
    torch.testing.assert_close(D.averaged_dd_solder(er2, mesh, frames=Fr), dd2, atol=1e-12, rtol=0)
    torch.testing.assert_close(D.wedge_solder(er2, mesh, frames=Fr), dd2, atol=1e-12, rtol=0)
    # BEHS21 on the plain θ_ij = F_i^T (v_j - v_i) is covariant as well
    torch.testing.assert_close(D.behs21_dd_solder(er2, mesh, frames=Fr),
                               (G[a] @ D.behs21_dd_solder(er, mesh)[..., None]).squeeze(-1), atol=1e-12, rtol=0)


def test_mesh_primal_dual_matches_template(gen):
    mesh = two_tets()
    Tn, F, E = mesh.tets.shape[0], mesh.faces.shape[0], mesh.edges.shape[0]
    tfr = so3.random_rotation(Tn, 4, generator=gen, dtype=F64)
    fer = so3.random_rotation(F, 3, generator=gen, dtype=F64)
    ev = torch.randn(E, 3, generator=gen, dtype=F64)
    dd = D.primal_dual_dd_mesh(tfr, fer, ev, mesh)
    torch.testing.assert_close(D.primal_dual_wedge_mesh(tfr, fer, ev, mesh), dd, atol=1e-12, rtol=0)
    # per tet: physical segments -> local template in the tet's own vertex order
    faces = {tuple(f): k for k, f in enumerate(mesh.faces.tolist())}
    edges = {tuple(e): k for k, e in enumerate(mesh.edges.tolist())}
    for t, tet in enumerate(mesh.tets.tolist()):
        Rtf = {frozenset(mesh.faces[mesh.tet_faces[t, k]].tolist()): tfr[t, k] for k in range(4)}
        Rfe = {}
        for f in Rtf:
            fid = faces[tuple(sorted(f))]
            for m in range(3):
                Rfe[(f, frozenset(mesh.edges[mesh.face_edges[fid, m]].tolist()))] = fer[fid, m]
        alpha = {e: ev[k] for e, k in edges.items()}
        ref = D.primal_dual_dd(*_template(tuple(tet), Rtf, Rfe, alpha))
        torch.testing.assert_close(dd[t], ref, atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- bad input

def test_bad_input_raises(gen):
    T, Th = rand_T(2, gen, F64)
    with pytest.raises(ValueError, match="shape"):
        D.unsymmetrized_vector(T[..., 0], torch.zeros(2, 4, 3, dtype=F64))
    with pytest.raises(ValueError, match="label dims"):
        D.unsymmetrized_vector(T, torch.zeros(2, 4, 5, 3, dtype=F64))
    with pytest.raises(TypeError, match="dtype"):
        D.alt_vector(T, torch.zeros(2, 4, 4, 3, dtype=torch.float32))
    with pytest.raises(ValueError, match="labels must lie"):
        D.unsymmetrized_vector(T, torch.zeros(2, 4, 4, 3, dtype=F64), [[0, 1, 7]])
    with pytest.raises(ValueError, match="lacks the entries"):
        D.unsymmetrized_vector(T, D.ListForm(torch.zeros(2, 1, 3, dtype=F64), [[0, 1]]), [[0, 1, 2]])
    with pytest.raises(ValueError, match="k <= 2"):
        D.alt_lie(T, torch.zeros(2, 4, 4, 4, 4, 3, 3, dtype=F64))
    with pytest.raises(ValueError, match="tet"):
        D.wedge_curvature_solder_tet(T[:, :3, :3], torch.zeros(2, 3, 3, 3, dtype=F64))
    with pytest.raises(ValueError, match="edge_values"):
        D.primal_dual_dd(torch.zeros(2, 4, 3, 3), torch.zeros(2, 4, 3, 3, 3), torch.zeros(2, 5, 3))
    mesh = two_tets()
    with pytest.raises(ValueError, match="edges"):
        D.tet_transports(so3.random_rotation(3, generator=gen, dtype=F64), mesh)
    with pytest.raises(ValueError, match="half_rot"):
        D.averaged_dd_solder(son.random_rotation(mesh.edges.shape[0], n=4, generator=gen, dtype=F64), mesh)


# ----------------------------------------------------------------------------- convergence (Ch. 5)

def test_averaged_dd_converges_linearly_behs21_does_not():
    """Case D of docs/conventions.md §3 (report Fig. 5.1): d∇d∇θ / vol -> Ω∧θ = (0, 0, -xy) at vertex 0."""
    import numpy as np

    from torchconn import smooth

    sc = smooth.ReportConnection()
    Rot = so3.euler_xyz(torch.tensor(-2.2, dtype=F64), torch.tensor(2.1, dtype=F64), torch.tensor(1.7, dtype=F64))
    v = torch.tensor([1.1, -1.2, -1.2], dtype=F64)
    base = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]], dtype=F64)
    ref = sc.curvature_wedge_solder(v)
    hs, err_avg, err_behs = [], [], []
    for level in range(5, 10):
        h = 2.0 ** -level
        P = v + h * base @ Rot.T
        a, b = P[:, None, :].expand(4, 4, 3), P[None, :, :].expand(4, 4, 3)
        T, Th = sc.midpoint_transport(a, b), sc.half_transport(a, b)
        vol = torch.det(torch.stack([P[1] - P[0], P[2] - P[0], P[3] - P[0]])) / 6
        err_avg.append(float((D.averaged_dd_tet(T, D.solder_form_sqrt(Th, P)) / vol - ref).norm()))
        err_behs.append(float((D.behs21_dd_tet(T, D.solder_form(P)) / vol - ref).norm()))
        hs.append(h)
    slope_avg = np.polyfit(np.log(hs), np.log(err_avg), 1)[0]
    slope_behs = np.polyfit(np.log(hs), np.log(err_behs), 1)[0]
    assert 0.9 < slope_avg < 1.1 and err_avg[-1] < 5e-3
    assert abs(slope_behs) < 0.1 and err_behs[-1] > 1.0
