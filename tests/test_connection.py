"""Tests of torchconn.connection: Connection (lookup, paths, gauge, half, constructors) and ConnectionField."""
from __future__ import annotations

import itertools
from types import SimpleNamespace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchconn import so3, son
from torchconn.dec.connection import Connection
from torchconn.nn import ConnectionField
from torchconn.dec.smooth import ReportConnection
from torchconn.tolerances import get_eps

F64 = torch.float64

# A small tet complex: three tets around a shared edge plus a fourth hanging off a face.
TETS = [(0, 1, 2, 3), (1, 2, 3, 4), (0, 2, 3, 5), (2, 3, 4, 6)]
V = 7


def _edges_and_triangles():
    edges = sorted({tuple(sorted(p)) for t in TETS for p in itertools.combinations(t, 2)})
    tris = sorted({tuple(sorted(f)) for t in TETS for f in itertools.combinations(t, 3)})
    return edges, tris


EDGES, TRIS = _edges_and_triangles()


def _shuffled_edges(gen):
    """Canonical edges in a random row order (the lookup must not assume sorted rows)."""
    e = torch.tensor(EDGES)
    return e[torch.randperm(len(EDGES), generator=gen)]


def _plain_transport(conn: Connection, i: int, j: int) -> torch.Tensor:
    """Slow reference: scan the edge list."""
    for e, (a, b) in enumerate(conn.edges.tolist()):
        if (a, b) == (i, j):
            return conn.edge_rot[e]
        if (a, b) == (j, i):
            return conn.edge_rot[e].T
    raise KeyError((i, j))


def _random_paths(gen, n_paths, length):
    adj = {v: sorted({b for e in EDGES for a, b in (e, e[::-1]) if a == v}) for v in range(V)}
    paths = []
    for _ in range(n_paths):
        p = [int(torch.randint(V, (1,), generator=gen))]
        for _ in range(length):
            nb = adj[p[-1]]
            p.append(nb[int(torch.randint(len(nb), (1,), generator=gen))])
        paths.append(p)
    return torch.tensor(paths)


# ----------------------------------------------------------------------------- lookups and paths
def test_transport_lookup_and_transpose(gen):
    edges = _shuffled_edges(gen)
    c = Connection.random(edges, V, generator=gen, dtype=F64)
    # canonical pairs return the stored matrices exactly, reversed pairs their transposes
    assert torch.equal(c.transport(edges[:, 0], edges[:, 1]), c.edge_rot)
    assert torch.equal(c.transport(edges[:, 1], edges[:, 0]), c.edge_rot.transpose(-1, -2))
    # batched (2-D) queries against the plain scan
    i = torch.tensor([[0, 3, 6], [4, 2, 1]])
    j = torch.tensor([[1, 2, 4], [1, 6, 0]])
    R = c.transport(i, j)
    assert R.shape == (2, 3, 3, 3)
    for a in range(2):
        for b in range(3):
            assert torch.equal(R[a, b], _plain_transport(c, int(i[a, b]), int(j[a, b])))
    idx, sign = c.edge_index(i, j)
    assert torch.equal(sign, torch.where(i < j, 1, -1))
    assert torch.equal(torch.sort(edges[idx], -1).values, torch.stack((torch.minimum(i, j), torch.maximum(i, j)), -1))


@settings(max_examples=25, deadline=None)
@given(
    n_vertices=st.integers(2, 12),
    pairs=st.lists(st.tuples(st.integers(0, 11), st.integers(0, 11)), min_size=1, max_size=30),
    queries=st.lists(st.tuples(st.integers(0, 11), st.integers(0, 11)), min_size=1, max_size=20),
    seed=st.integers(0, 2**16),
)
def test_lookup_property(n_vertices, pairs, queries, seed):
    """Random edge sets and queries: lookup agrees with a dict, non-edges are reported."""
    edge_set = sorted({(min(i, j), max(i, j)) for i, j in pairs if i != j and max(i, j) < n_vertices})
    if not edge_set:
        return
    g = torch.Generator().manual_seed(seed)
    edges = torch.tensor(edge_set)[torch.randperm(len(edge_set), generator=g)]
    c = Connection.random(edges, n_vertices, generator=g, dtype=F64)
    table = {tuple(e): c.edge_rot[k] for k, e in enumerate(edges.tolist())}
    qs = [(i, j) for i, j in queries if max(i, j) < n_vertices]
    good = [(i, j) for i, j in qs if (min(i, j), max(i, j)) in table and i != j]
    bad = [(i, j) for i, j in qs if (i, j) not in good]
    if good:
        R = c.transport(torch.tensor([q[0] for q in good]), torch.tensor([q[1] for q in good]))
        for (i, j), Rij in zip(good, R):
            ref = table[(i, j)] if i < j else table[(j, i)].T
            assert torch.equal(Rij, ref)
    for i, j in bad[:3]:
        with pytest.raises(ValueError, match=r"not edges.*\[\[%d, %d\]\]" % (i, j)):
            c.transport(torch.tensor([i]), torch.tensor([j]))


def test_path_products_against_plain_loop(gen):
    c = Connection.random(_shuffled_edges(gen), V, generator=gen, dtype=F64)
    paths = _random_paths(gen, 12, 5)
    T = c.path(paths)
    for p, Tp in zip(paths.tolist(), T):
        ref = torch.eye(3, dtype=F64)
        for a, b in zip(p[:-1], p[1:]):
            ref = ref @ _plain_transport(c, a, b)
        assert (Tp - ref).abs().max() < 1e-14
    # length-0 path is the identity; a path and its reverse are inverse
    assert torch.equal(c.path(torch.tensor([[3]])), torch.eye(3, dtype=F64)[None])
    assert (c.path(paths) @ c.path(paths.flip(-1)) - torch.eye(3, dtype=F64)).abs().max() < 1e-13


def test_vector_transport_convention(gen):
    """R_ij takes coordinates at v_j to v_i: transporting j -> i -> j is the identity and a path
    product T(p0..pk) applied to a vector at pk equals transporting it edge by edge."""
    c = Connection.random(torch.tensor(EDGES), V, generator=gen, dtype=F64)
    x = torch.randn(3, generator=gen, dtype=F64)  # a vector at vertex 2
    y = c.transport(1, 2) @ x  # now at vertex 1
    z = c.transport(0, 1) @ y  # now at vertex 0
    assert (c.path(torch.tensor([0, 1, 2])) @ x - z).abs().max() < 1e-14
    assert (c.transport(2, 1) @ y - x).abs().max() < 1e-14


def test_one_form_and_solder_flip(gen):
    """R_ij w_ji = -w_ij (eq. 3.1.2) and R_ji θ̃_ij = -θ̃_ji, θ̃_ij = √R_ij (v_j - v_i) (errata 9)."""
    edges = _shuffled_edges(gen)
    verts = torch.randn(V, 3, generator=gen, dtype=F64)
    for c in (
        Connection.random(edges, V, generator=gen, dtype=F64),
        Connection.random(edges, V, generator=gen, scale=0.3, dtype=F64),
        Connection.from_smooth(verts, edges, ReportConnection()),
    ):
        i, j = c.edges[:, 0], c.edges[:, 1]
        eye = torch.eye(3, dtype=F64)
        w = c.one_form()
        assert torch.equal(w, c.edge_rot - eye)
        w_ji = c.transport(j, i) - eye
        assert (c.edge_rot @ w_ji + w).abs().max() < 1e-13
        H = c.half()
        assert (H.edge_rot @ H.edge_rot - c.edge_rot).abs().max() < 1e-13
        th_ij = (H.transport(i, j) @ (verts[j] - verts[i])[..., None])[..., 0]
        th_ji = (H.transport(j, i) @ (verts[i] - verts[j])[..., None])[..., 0]
        assert ((c.transport(j, i) @ th_ij[..., None])[..., 0] + th_ji).abs().max() < 1e-12
        # plain θ (no half transport) does not flip like this for a non-trivial connection
        th_plain = verts[j] - verts[i]
        assert ((c.transport(j, i) @ th_plain[..., None])[..., 0] - th_plain).abs().max() > 1e-3


def test_half_matches_smooth_half_transport(gen):
    edges = torch.tensor(EDGES)
    verts = torch.randn(V, 3, generator=gen, dtype=F64)
    rc = ReportConnection()
    c = Connection.from_smooth(verts, edges, rc)
    a, b = verts[edges[:, 0]], verts[edges[:, 1]]
    assert (c.edge_rot - rc.midpoint_transport(a, b)).abs().max() == 0
    assert (c.half().edge_rot - rc.half_transport(a, b)).abs().max() < 1e-12
    cp = Connection.from_smooth(verts, edges, rc, method="path_ordered", steps=16)
    assert (cp.edge_rot - rc.path_ordered_transport(a, b, steps=16)).abs().max() == 0


# ----------------------------------------------------------------------------- gauge and flatness
def test_gauge_composition_and_identity(gen):
    c = Connection.random(_shuffled_edges(gen), V, generator=gen, dtype=F64)
    G1 = so3.random_rotation(V, generator=gen, dtype=F64)
    G2 = so3.random_rotation(V, generator=gen, dtype=F64)
    # R'' = G2 (G1 R G1^T) G2^T = (G2 G1) R (G2 G1)^T
    assert (c.gauge(G1).gauge(G2).edge_rot - c.gauge(G2 @ G1).edge_rot).abs().max() < 1e-13
    assert (c.gauge(G1).gauge(G2).edge_rot - c.gauge(G1 @ G2).edge_rot).abs().max() > 1e-3
    eye = torch.eye(3, dtype=F64).expand(V, 3, 3)
    assert torch.equal(c.gauge(eye).edge_rot, c.edge_rot)
    # plain per-edge reference and holonomy covariance G_p0 H G_p0^T
    cg = c.gauge(G1)
    for e, (i, j) in enumerate(c.edges.tolist()):
        assert (cg.edge_rot[e] - G1[i] @ c.edge_rot[e] @ G1[j].T).abs().max() < 1e-14
    loops = torch.tensor([list(t) + [t[0]] for t in TRIS])
    assert (cg.path(loops) - G1[loops[:, 0]] @ c.path(loops) @ G1[loops[:, 0]].transpose(-1, -2)).abs().max() < 1e-13
    with pytest.raises(ValueError, match="gauge expects G"):
        c.gauge(G1[:-1])


@pytest.mark.parametrize("n", [2, 3, 4])
def test_from_frames_is_flat(n, gen):
    edges = _shuffled_edges(gen)
    F = son.random_rotation(V, n=n, generator=gen, dtype=F64)
    c = Connection.from_frames(F, edges)
    loops = torch.tensor([list(t) + [t[0]] for t in TRIS])
    eye = torch.eye(n, dtype=F64)
    assert (c.path(loops) - eye).abs().max() < 1e-13
    # holonomy of a random connection is not trivial (the test above can fail)
    r = Connection.random(edges, V, n=n, generator=gen, dtype=F64)
    assert (r.path(loops) - eye).abs().max() > 1e-2
    # from_frames = identity gauged by G_i = F_i^T
    ident = Connection.identity(edges, V, n=n, dtype=F64)
    assert (ident.gauge(F.transpose(-1, -2)).edge_rot - c.edge_rot).abs().max() < 1e-14
    # a vector field parallel in the frames' ambient space, X_i = F_i^T u, is transported exactly
    u = torch.randn(n, generator=gen, dtype=F64)
    X = F.transpose(-1, -2) @ u
    i, j = c.edges[:, 0], c.edges[:, 1]
    assert ((c.edge_rot @ X[j][..., None])[..., 0] - X[i]).abs().max() < 1e-14


# ----------------------------------------------------------------------------- dense tables, meshes
def test_simplex_transports_dense_table(gen):
    c = Connection.random(_shuffled_edges(gen), V, generator=gen, dtype=F64)
    tets = torch.tensor(TETS)
    pairs = [(a, b) for a in range(4) for b in range(a + 1, 4)]
    ti = torch.stack([tets[:, a] for a, _ in pairs], 1)
    tj = torch.stack([tets[:, b] for _, b in pairs], 1)
    idx, sign = c.edge_index(ti, tj)
    D = c.simplex_transports(idx, sign, 4)
    assert D.shape == (len(TETS), 4, 4, 3, 3)
    for t, tet in enumerate(TETS):
        for a in range(4):
            for b in range(4):
                ref = torch.eye(3, dtype=F64) if a == b else _plain_transport(c, tet[a], tet[b])
                assert torch.equal(D[t, a, b], ref)
    assert torch.equal(c.oriented(idx, sign), c.transport(ti, tj))
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        c.simplex_transports(idx[:, :5], sign[:, :5], 4)


def test_mesh_constructors(gen):
    verts = torch.randn(V, 3, generator=gen, dtype=F64)
    mesh = SimpleNamespace(vertices=verts, edges=torch.tensor(EDGES), n_vertices=V)
    c = Connection.from_mesh(mesh)
    assert c.dtype == F64 and torch.equal(c.edge_rot, torch.eye(3, dtype=F64).expand(len(EDGES), 3, 3))
    r = Connection.random_on_mesh(mesh, generator=gen)
    assert r.dtype == F64 and r.n_edges == len(EDGES)
    r.check_rotations()
    assert torch.equal(Connection.from_mesh(mesh, r.edge_rot, validate=True).edge_rot, r.edge_rot)
    s = Connection.smooth_on_mesh(mesh, ReportConnection())
    assert torch.equal(s.edge_rot, Connection.from_smooth(verts, mesh.edges, ReportConnection()).edge_rot)


# ----------------------------------------------------------------------------- errors
def test_errors_name_offenders(gen):
    edges = torch.tensor(EDGES)
    c = Connection.random(edges, V, generator=gen, dtype=F64)
    with pytest.raises(ValueError, match=r"not edges.*\[\[0, 4\], \[6, 6\]\]"):
        c.transport(torch.tensor([0, 6, 1]), torch.tensor([4, 6, 0]))
    with pytest.raises(ValueError, match=r"not edges.*\[\[0, 9\]\]"):
        c.path(torch.tensor([1, 0, 9]))
    bad = c.edge_rot.clone()
    bad[5] = bad[5] * 1.01
    bad[7] = -bad[7]  # a reflection (det -1)
    with pytest.raises(ValueError, match=r"edge indices \[5, 7\] \(vertex pairs \[\[%d, %d\], \[%d, %d\]\]\)" % (*EDGES[5], *EDGES[7])):
        Connection(bad, edges, V, validate=True)
    Connection(bad, edges, V)  # not validated unless asked
    with pytest.raises(ValueError, match=r"canonical.*edge indices \[2\]"):
        Connection(c.edge_rot[:3], torch.tensor([[0, 1], [0, 2], [3, 1]]), V)
    with pytest.raises(ValueError, match=r"duplicated.*\[\[0, 2\]\]"):
        Connection(c.edge_rot[:3], torch.tensor([[0, 1], [1, 2], [0, 1]]), V)
    with pytest.raises(ValueError, match=r"out of range.*edge indices \[1\]"):
        Connection(c.edge_rot[:2], torch.tensor([[0, 1], [1, 7]]), V)
    with pytest.raises(ValueError, match="edge_rot has 3 matrices but edges has 2"):
        Connection(c.edge_rot[:3], torch.tensor([[0, 1], [1, 2]]), V)
    with pytest.raises(ValueError, match=r"\(\.\.\., E, n, n\)"):
        Connection(c.edge_rot[:, :2], edges, V)
    with pytest.raises(TypeError, match="integer"):
        Connection(c.edge_rot, edges.double(), V)
    with pytest.raises(ValueError, match="different edges"):
        ConnectionField(edges.flip(0), V, init=c)  # same edge set, other row order


# ----------------------------------------------------------------------------- ConnectionField
@pytest.mark.parametrize("n", [2, 3, 4])
def test_field_gradcheck(n, gen):
    # n = 4 goes through torch.linalg.matrix_exp, whose backward is slow: fewer edges, fast mode
    E = 2 if n == 4 else 5
    edges = torch.tensor(EDGES[:E])
    field = ConnectionField(edges, V, n=n, dtype=F64)
    p = torch.randn(E, son.dim(n), generator=gen, dtype=F64)
    p[0] = 0.0  # exactly the identity: Taylor branch, gradient must be finite and correct
    p[1] = 1e-9
    p.requires_grad_(True)

    def f(params):
        return torch.func.functional_call(field, {"params": params}, ()).edge_rot

    assert torch.autograd.gradcheck(f, (p,), fast_mode=(n == 4))
    # derivative at params = 0 is the Lie-algebra basis: d exp(hat(t e_k))/dt = hat(e_k)
    z = torch.zeros(1, son.dim(n), dtype=F64, requires_grad=True)
    f1 = ConnectionField(edges[:1], V, n=n, dtype=F64)
    J = torch.autograd.functional.jacobian(lambda q: torch.func.functional_call(f1, {"params": q}, ()).edge_rot, z)
    basis = son.hat(torch.eye(son.dim(n), dtype=F64), n)  # (m, n, n)
    assert torch.isfinite(J).all()
    assert (J[0, :, :, 0, :].permute(2, 0, 1) - basis).abs().max() < 1e-12


@pytest.mark.parametrize("n", [2, 3, 4])
def test_field_round_trips(n, gen):
    edges = _shuffled_edges(gen)
    c = Connection.random(edges, V, n=n, generator=gen, dtype=F64)
    f = ConnectionField.from_connection(c)
    assert f.params.shape == (len(EDGES), son.dim(n))
    assert (f().edge_rot - c.edge_rot).abs().max() < 1e-12
    # principal branch: parameters of norm < pi survive exp -> log (n = 3: rotation vectors)
    p = torch.randn(len(EDGES), son.dim(n), generator=gen, dtype=F64)
    if n == 3:
        p = p * (3.0 / p.norm(dim=-1, keepdim=True)).clamp(max=1.0)
    else:
        p = 0.3 * p
    f2 = ConnectionField(edges, V, n=n, init=_exp(p, n))
    assert (f2.params - p).abs().max() < 1e-10
    f3 = ConnectionField(edges, V, n=n, init=p)
    assert torch.equal(f3.params.detach(), p)
    # forward gives a working Connection sharing the module's edge lookup
    conn = f3()
    assert torch.equal(conn.transport(edges[:, 1], edges[:, 0]), f3.edge_rotations().transpose(-1, -2))
    assert conn.n == n and conn.n_vertices == V
    # identity init
    f0 = ConnectionField(edges, V, n=n)
    assert torch.equal(f0.params.detach(), torch.zeros(len(EDGES), son.dim(n)))
    with pytest.raises(ValueError, match="init tensor must have shape"):
        ConnectionField(edges, V, n=n, init=torch.zeros(2, 2))


def _exp(p, n):
    return so3.exp(p) if n == 3 else son.exp_params(p, n)


def test_field_training_step_and_state_dict(gen):
    """A few optimizer steps reduce a holonomy loss; buffers travel in the state dict."""
    edges = torch.tensor(EDGES)
    field = ConnectionField(edges, V, init=Connection.random(edges, V, generator=gen, scale=0.5, dtype=F64))
    loops = torch.tensor([list(t) + [t[0]] for t in TRIS])
    eye = torch.eye(3, dtype=F64)

    def loss():
        return ((field().path(loops) - eye) ** 2).sum()

    # plain gradient descent (torch.optim's first use imports torch._dynamo: seconds)
    l0 = loss().item()
    for _ in range(20):
        field.params.grad = None
        loss().backward()
        with torch.no_grad():
            field.params -= 0.02 * field.params.grad
    assert loss().item() < 0.5 * l0
    sd = field.state_dict()
    assert set(sd) == {"params", "edges"}
    g2 = ConnectionField(edges, V, dtype=F64)
    g2.load_state_dict(sd)
    assert torch.equal(g2().edge_rot, field().edge_rot)
    # loading other edges (same count) rebuilds the transport lookup
    g3 = ConnectionField(edges.flip(0), V, dtype=F64)
    g3.load_state_dict(sd)
    assert torch.equal(g3().transport(edges[:, 0], edges[:, 1]), field().edge_rot)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtypes(dtype, gen):
    edges = _shuffled_edges(gen)
    F = so3.random_rotation(V, generator=gen, dtype=dtype)
    c = Connection.from_frames(F, edges)
    assert c.dtype == dtype and c.one_form().dtype == dtype and c.half().dtype == dtype
    loops = torch.tensor([list(t) + [t[0]] for t in TRIS])
    tol = 10 * get_eps("identity", dtype)
    assert (c.path(loops) - torch.eye(3, dtype=dtype)).abs().max() < tol
    r = Connection.random(edges, V, generator=gen, dtype=dtype)
    r.check_rotations()
    f = ConnectionField.from_connection(r)
    assert f.params.dtype == dtype and f().edge_rot.dtype == dtype
    assert (f().edge_rot - r.edge_rot).abs().max() < tol
    # casting keeps the lookup working
    r64 = r.to(torch.float64)
    assert r64.dtype == torch.float64
    assert torch.equal(r64.transport(edges[:, 1], edges[:, 0]), r.edge_rot.double().transpose(-1, -2))
    d = r.detach()
    assert not d.edge_rot.requires_grad and torch.equal(d.edge_rot, r.edge_rot)
    s = Connection.random(edges, V, generator=gen, scale=0.1, dtype=dtype)
    assert s.dtype == dtype and (s.edge_rot - torch.eye(3, dtype=dtype)).abs().max() < 1.0
