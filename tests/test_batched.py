"""Leading batch dims on the connection (issue 11): every dec operator and nn module against a
per-item Python loop; gradcheck/gradgradcheck of batched calls; vmap vs loop; torch.func.jvp."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn.dec import bianchi, chains, curvature, dnabla, torsion, transport
from torchconn.dec.connection import Connection
from torchconn.lie import so3
from torchconn.mesh import CellComplex, TetMesh, box
from torchconn.nn import (AveragedCovariantD, BianchiCheck, ConnectionField, CovariantD, Curvature, Torsion)

F64 = torch.float64
BATCH = (2, 3)


@pytest.fixture(scope="module")
def mesh():
    return box(1)  # 19 edges, 18 faces, 6 tets


@pytest.fixture(scope="module")
def mesh2():
    return box(2)


@pytest.fixture(scope="module")
def two_tets():
    """Two tets sharing a face (9 edges, 7 faces): the batched gradgradchecks' complex (tets that
    share edges and faces, edges used in both directions; on ``box(1)`` they took 4-16 s each)."""
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.2]], dtype=F64)
    return TetMesh(v, [[0, 1, 2, 3], [1, 2, 3, 4]], reorient=True)


def quad_complex():
    """Quads, triangles and a hexagon on a 3 x 2 grid (face sizes 3, 4, 6)."""
    nx, ny = 4, 2
    V = np.array([[i, j, 0.0] for j in range(ny + 1) for i in range(nx + 1)])
    vid = lambda i, j: j * (nx + 1) + i  # noqa: E731
    F = [[vid(0, 0), vid(1, 0), vid(1, 1)], [vid(0, 0), vid(1, 1), vid(0, 1)],
         [vid(1, 0), vid(2, 0), vid(2, 1), vid(1, 1)],
         [vid(2, 0), vid(3, 0), vid(4, 0), vid(4, 1), vid(3, 1), vid(2, 1)]]
    F += [[vid(i, 1), vid(i + 1, 1), vid(i + 1, 2), vid(i, 2)] for i in range(nx)]
    return CellComplex(V, F)


def rots(m, batch=BATCH, seed=0, scale=0.6):
    g = torch.Generator().manual_seed(seed)
    return Connection.random_on_mesh(m, generator=g, scale=scale, batch_shape=batch).edge_rot


def frames_of(m, batch=(), seed=1):
    g = torch.Generator().manual_seed(seed)
    N = int(np.prod(batch, dtype=np.int64)) * m.n_vertices
    return so3.random_rotation(N, generator=g, dtype=F64).reshape(*batch, m.n_vertices, 3, 3)


def loop_ref(fn, R, *per_item):
    """``fn`` applied item by item over the leading dims of ``R`` (and of ``per_item``), restacked."""
    batch = R.shape[:-3]
    flat = R.reshape(-1, *R.shape[-3:])
    items = [p.reshape(-1, *p.shape[len(batch):]) if p is not None and p.ndim > 3 else None for p in per_item]
    outs = []
    for b in range(flat.shape[0]):
        args = [it[b] if it is not None else p for it, p in zip(items, per_item)]
        outs.append(fn(flat[b], *args))
    out = torch.stack(outs)
    return out.reshape(*batch, *out.shape[1:])


def assert_close(a, b, tol=1e-12):
    assert a.shape == b.shape, (a.shape, b.shape)
    torch.testing.assert_close(a, b, atol=tol, rtol=tol)


# ----------------------------------------------------------------------------- functional, tet mesh
TET_OPS = {
    "curvature_cut_c": lambda R, m: curvature.face_curvature(R, m),
    "curvature_cut_b": lambda R, m: curvature.face_curvature(R, m, cut=1),
    "curvature_tensor_cut": lambda R, m: curvature.face_curvature(R, m, cut=torch.tensor(0)),
    "holonomy": lambda R, m: curvature.face_curvature(R, m, kind="holonomy"),
    "torsion_sqrt": lambda R, m: torsion.face_torsion(R, m),
    "torsion_sqrt_cut_b": lambda R, m: torsion.face_torsion(R, m, cut=1),
    "torsion_naive": lambda R, m: torsion.face_torsion(R, m, kind="naive"),
    "tet_transports": lambda R, m: dnabla.tet_transports(R, m),
    "tet_solder_sqrt": lambda R, m: dnabla.tet_solder_sqrt(R, m),
    "averaged_dd": lambda R, m: dnabla.averaged_dd_solder(R, m),
    "wedge": lambda R, m: dnabla.wedge_solder(R, m),
    "behs21": lambda R, m: dnabla.behs21_dd_solder(R, m),
    "bianchi_differential": lambda R, m: bianchi.differential_residual(R, m, reduce=False),
    "bianchi_differential_alt": lambda R, m: bianchi.differential_residual(R, m, alternate=True),
    "bianchi_algebraic": lambda R, m: bianchi.algebraic_residual(R, m, reduce=False),
}


@pytest.mark.parametrize("name", sorted(TET_OPS))
@pytest.mark.parametrize("batch", [(4,), BATCH, (1, 2, 1)])
def test_tet_ops_batched_equal_loop(mesh, name, batch):
    fn = TET_OPS[name]
    R = rots(mesh, batch)
    out = fn(R, mesh)
    assert out.shape[:len(batch)] == batch
    assert_close(out, loop_ref(lambda r: fn(r, mesh), R))


FRAME_OPS = {
    "torsion_sqrt": lambda R, m, F: torsion.face_torsion(R, m, frames=F),
    "torsion_naive": lambda R, m, F: torsion.face_torsion(R, m, kind="naive", frames=F),
    "averaged_dd": lambda R, m, F: dnabla.averaged_dd_solder(R, m, frames=F),
    "wedge": lambda R, m, F: dnabla.wedge_solder(R, m, frames=F),
    "behs21": lambda R, m, F: dnabla.behs21_dd_solder(R, m, frames=F),
    "tet_solder_sqrt": lambda R, m, F: dnabla.tet_solder_sqrt(R, m, frames=F),
    "bianchi_algebraic": lambda R, m, F: bianchi.algebraic_residual(R, m, frames=F),
}


@pytest.mark.parametrize("name", sorted(FRAME_OPS))
@pytest.mark.parametrize("per_item", [False, True], ids=["shared_frames", "batched_frames"])
def test_frame_ops_batched_equal_loop(mesh, name, per_item):
    fn = FRAME_OPS[name]
    R = rots(mesh)
    F = frames_of(mesh, BATCH if per_item else ())
    out = fn(R, mesh, F)
    assert_close(out, loop_ref(lambda r, f: fn(r, mesh, f), R, F))


def test_primal_dual_batched_equal_loop(mesh):
    g = torch.Generator().manual_seed(3)
    T, F, E = mesh.tets.shape[0], mesh.faces.shape[0], mesh.n_edges
    tfr = so3.random_rotation(2 * T * 4, generator=g, dtype=F64).reshape(2, T, 4, 3, 3)
    fer = so3.random_rotation(2 * F * 3, generator=g, dtype=F64).reshape(2, F, 3, 3, 3)
    ev = torch.randn(2, E, 3, generator=g, dtype=F64)
    for fn in (dnabla.primal_dual_dd_mesh, dnabla.primal_dual_wedge_mesh, bianchi.primal_dual_residual):
        out = fn(tfr, fer, ev, mesh)
        ref = torch.stack([fn(tfr[b], fer[b], ev[b], mesh) for b in range(2)])
        assert_close(out, ref)
        # batch dims broadcast: one set of dual transports, two value fields
        assert_close(fn(tfr[0], fer[0], ev, mesh), torch.stack([fn(tfr[0], fer[0], ev[b], mesh) for b in range(2)]))


def test_bianchi_check_batched(mesh):
    R = rots(mesh)
    res = bianchi.check(R, mesh)
    assert set(res) == {"differential", "algebraic"} and max(res.values()) < 1e-12
    # a NaN in one batch item is found and named by its tet
    bad = R.clone()
    bad[1, 2, 0, 0] = float("nan")
    with pytest.raises(bianchi.BianchiError, match="NaN/inf"):
        bianchi.check(bad, mesh)
    with pytest.raises(bianchi.BianchiError, match="NaN/inf"):
        BianchiCheck(mesh)(bad)


# ----------------------------------------------------------------------------- functional, cell complex
def test_cell_complex_curvature_and_chain_batched():
    cx = quad_complex()
    R = rots(cx, (3,))
    for kind, cut in (("two_prong", -1), ("two_prong", 2), ("holonomy", -1)):
        fn = lambda r: curvature.face_curvature(r, cx, cut=cut, kind=kind)  # noqa: E731
        assert_close(fn(R), loop_ref(fn, R))
    fn = lambda r: torsion.face_torsion(r, cx)  # noqa: E731
    assert_close(fn(R), loop_ref(fn, R))
    ids = [0, 1, 2, 4, 5]
    bl = chains.boundary_loop(cx, ids).tolist()
    fn = lambda r: chains.curvature_over_chain(r, cx, ids, bl[0], bl[3])  # noqa: E731
    out = fn(R)
    assert out.shape == (3, 3, 3)
    assert_close(out, loop_ref(fn, R))


def test_transport_and_connection_batched(mesh):
    R = rots(mesh, (2,))
    c = Connection(R, mesh.edges, mesh.n_vertices, validate=True)
    assert c.batch_shape == (2,) and c.n_edges == mesh.n_edges and "batch_shape=(2,)" in repr(c)
    items = [Connection(R[b], mesh.edges, mesh.n_vertices) for b in range(2)]
    i, j = mesh.edges[:5, 1], mesh.edges[:5, 0]
    assert_close(c.transport(i, j), torch.stack([x.transport(i, j) for x in items]))
    a, b = int(mesh.edges[0, 0]), int(mesh.edges[0, 1])
    path = torch.tensor([[a, b, a], [b, a, b]])  # there and back along edge 0
    assert_close(c.path(path), torch.stack([x.path(path) for x in items]))
    assert c.path(torch.tensor([3])).shape == (2, 3, 3)
    assert_close(c.simplex_transports(mesh.tet_edges, mesh.tet_edge_signs, 4),
                 torch.stack([x.simplex_transports(mesh.tet_edges, mesh.tet_edge_signs, 4) for x in items]))
    assert_close(c.half().edge_rot, torch.stack([x.half().edge_rot for x in items]))
    assert_close(c.one_form(), torch.stack([x.one_form() for x in items]))
    G = frames_of(mesh, (2,))
    assert_close(c.gauge(G).edge_rot, torch.stack([x.gauge(G[b]).edge_rot for b, x in enumerate(items)]))
    assert_close(c.gauge(G[0]).edge_rot, torch.stack([x.gauge(G[0]).edge_rot for x in items]))
    idx = torch.tensor([[0, 3], [5, 1]])
    sgn = torch.tensor([[1, -1], [-1, 1]])
    assert_close(transport.orient(R, idx, sgn), torch.stack([transport.orient(R[b], idx, sgn) for b in range(2)]))
    # the flat connection of a batch of frame fields
    cf = Connection.from_frames(G, mesh.edges)
    assert cf.batch_shape == (2,)
    assert_close(cf.edge_rot, torch.stack([Connection.from_frames(G[b], mesh.edges).edge_rot for b in range(2)]))
    assert float(curvature.face_curvature(cf, mesh, kind="holonomy").abs().max()) < 1e-12
    # identity/random with batch_shape
    ci = Connection.identity(mesh.edges, mesh.n_vertices, dtype=F64, batch_shape=(3,))
    assert ci.edge_rot.shape == (3, mesh.n_edges, 3, 3)
    assert float(curvature.face_curvature(ci, mesh).abs().max()) == 0.0


def test_connection_batched_validation_names_edges(mesh):
    R = rots(mesh, (2,))
    bad = R.clone()
    bad[1, 4] = -bad[1, 4]  # a reflection in item 1 only
    with pytest.raises(ValueError, match=r"1 of 19 edge matrices.*edge indices \[4\].*det -1"):
        Connection(bad, mesh.edges, mesh.n_vertices, validate=True)
    with pytest.raises(ValueError, match=r"edge_rot has 18 matrices but edges has 19 rows: expected shape \(2, 19, 3, 3\)"):
        Connection(R[:, :18], mesh.edges, mesh.n_vertices)


# ----------------------------------------------------------------------------- shape errors name the batch
def test_shape_errors_name_the_batch(mesh):
    R = rots(mesh)[:, :, :18]
    with pytest.raises(ValueError, match=r"face_curvature: edge_rot must have shape \(2, 3, 19, 3, 3\).*got \(2, 3, 18, 3, 3\)"):
        curvature.face_curvature(R, mesh)
    with pytest.raises(ValueError, match=r"face_torsion: edge_rot must have shape \(2, 3, 19, 3, 3\)"):
        torsion.face_torsion(R, mesh)
    with pytest.raises(ValueError, match=r"averaged_dd_solder: edge_rot must have shape \(2, 3, 19, 3, 3\)"):
        dnabla.averaged_dd_solder(R, mesh)
    with pytest.raises(ValueError, match=r"Curvature: .*shape \(2, 3, 19, n, n\)|Curvature: .*shape \(2, 3, 19, 3, 3\)"):
        Curvature(mesh)(R)
    with pytest.raises(ValueError, match=r"Torsion: frames must have shape \(8, 3, 3\).* or \(2, 3, 8, 3, 3\).*got \(3, 8, 3, 3\)"):
        Torsion(mesh)(rots(mesh), frames_of(mesh, (3,)))
    with pytest.raises(ValueError, match=r"face_torsion: frames must have shape \(8, 3, 3\) or \(2, 3, 8, 3, 3\).*got \(2, 8, 3, 3\)"):
        torsion.face_torsion(rots(mesh), mesh, frames=frames_of(mesh, (2,)))
    with pytest.raises(ValueError, match=r"ConnectionField init: init tensor must have shape \(4, 19, 3\)"):
        ConnectionField(mesh.edges, mesh.n_vertices, init=torch.zeros(2, 19, 3), batch_shape=(4,))


# ----------------------------------------------------------------------------- modules
MODULES = {
    "curvature": lambda m: Curvature(m),
    "holonomy": lambda m: Curvature(m, kind="holonomy"),
    "torsion": lambda m: Torsion(m),
    "torsion_naive": lambda m: Torsion(m, kind="naive"),
    "averaged": lambda m: AveragedCovariantD(m),
    "behs21": lambda m: CovariantD(m, "behs21"),
    "wedge": lambda m: CovariantD(m, "wedge"),
}


@pytest.mark.parametrize("name", sorted(MODULES))
def test_modules_batched_field_forward_backward_equal_loop(mesh2, name):
    mod = MODULES[name](mesh2)
    g = torch.Generator().manual_seed(5)
    params = 0.7 * torch.randn(*BATCH, mesh2.n_edges, 3, generator=g, dtype=F64)
    field = ConnectionField(mesh2.edges, mesh2.n_vertices, init=params)
    assert field.batch_shape == BATCH and field().edge_rot.shape == (*BATCH, mesh2.n_edges, 3, 3)
    w = torch.randn(mod(field).shape, generator=g, dtype=F64)
    loss = (mod(field) * w).sum()
    loss.backward()
    grad = field.params.grad.clone()
    outs, grads = [], []
    for idx in np.ndindex(*BATCH):
        f1 = ConnectionField(mesh2.edges, mesh2.n_vertices, init=params[idx])
        out = mod(f1)
        (out * w[idx]).sum().backward()
        outs.append(out.detach())
        grads.append(f1.params.grad)
    assert_close(mod(field).detach(), torch.stack(outs).reshape(*BATCH, *outs[0].shape))
    assert_close(grad, torch.stack(grads).reshape(grad.shape), tol=1e-10)


def test_module_frames_batched(mesh2):
    R = rots(mesh2)
    for mod in (Torsion(mesh2), AveragedCovariantD(mesh2)):
        for F in (frames_of(mesh2), frames_of(mesh2, BATCH)):
            assert_close(mod(R, F), loop_ref(lambda r, f: mod(r, f), R, F))


def test_connection_field_batch_api(mesh):
    f = ConnectionField(mesh.edges, mesh.n_vertices, batch_shape=(4,), dtype=F64)
    assert f.params.shape == (4, mesh.n_edges, 3) and "batch_shape=(4,)" in repr(f)
    assert float((f().edge_rot - torch.eye(3, dtype=F64)).abs().max()) == 0.0
    c = Connection.random_on_mesh(mesh, generator=torch.Generator().manual_seed(2), batch_shape=(2, 2))
    f2 = ConnectionField.from_connection(c)
    assert f2.batch_shape == (2, 2)
    assert_close(f2().edge_rot, c.edge_rot, tol=1e-10)
    f3 = ConnectionField(mesh.edges, mesh.n_vertices, init=c.edge_rot)
    assert f3.batch_shape == (2, 2)
    sd = f3.state_dict()
    f4 = ConnectionField(mesh.edges, mesh.n_vertices, batch_shape=(2, 2), dtype=F64)
    f4.load_state_dict(sd)
    assert_close(f4().edge_rot, f3().edge_rot, tol=0)


# ----------------------------------------------------------------------------- gradcheck / gradgradcheck
GRAD_OPS = {
    "curvature": lambda R, m: curvature.face_curvature(R, m),
    "holonomy": lambda R, m: curvature.face_curvature(R, m, kind="holonomy"),
    "torsion_sqrt": lambda R, m: torsion.face_torsion(R, m),
    "averaged_dd": lambda R, m: dnabla.averaged_dd_solder(R, m),
    "wedge": lambda R, m: dnabla.wedge_solder(R, m),
}


@pytest.mark.parametrize("name", sorted(GRAD_OPS))
def test_gradcheck_gradgradcheck_batched(two_tets, name):
    mesh = two_tets
    fn = GRAD_OPS[name]
    g = torch.Generator().manual_seed(7)
    p = (0.5 * torch.randn(2, mesh.n_edges, 3, generator=g, dtype=F64)).requires_grad_()
    f = lambda p: fn(so3.exp(p), mesh)  # noqa: E731  (through exp: rotations stay rotations)
    assert torch.autograd.gradcheck(f, (p,))
    assert torch.autograd.gradgradcheck(f, (p,))


def test_gradcheck_gradgradcheck_batched_module(two_tets):
    mesh = two_tets
    mod = AveragedCovariantD(mesh)
    curv = Curvature(mesh)
    g = torch.Generator().manual_seed(8)
    p = (0.5 * torch.randn(2, mesh.n_edges, 3, generator=g, dtype=F64)).requires_grad_()
    f = lambda p: (mod(so3.exp(p)).square().sum(-1), curv(so3.exp(p)))  # noqa: E731
    assert torch.autograd.gradcheck(f, (p,))
    # fast mode (10 s in full on 2 loaded cores): the full batched gradgradchecks of both ops are
    # test_gradcheck_gradgradcheck_batched[averaged_dd], [curvature]; of the modules, test_second_order's
    assert torch.autograd.gradgradcheck(f, (p,), fast_mode=True)


# ----------------------------------------------------------------------------- vmap
VMAP_OPS = {
    "curvature": lambda R, m: curvature.face_curvature(R, m),
    "holonomy": lambda R, m: curvature.face_curvature(R, m, kind="holonomy"),
    "torsion_naive": lambda R, m: torsion.face_torsion(R, m, kind="naive"),
    "behs21": lambda R, m: dnabla.behs21_dd_solder(R, m),
    "tet_transports": lambda R, m: dnabla.tet_transports(R, m),
    "bianchi_differential": lambda R, m: bianchi.differential_residual(R, m),
    "module_curvature": lambda R, m: Curvature(m)(R),
    "module_behs21": lambda R, m: CovariantD(m, "behs21")(R),
}
VMAP_SQRT_OPS = {
    "torsion_sqrt": lambda R, m: torsion.face_torsion(R, m),
    "averaged_dd": lambda R, m: dnabla.averaged_dd_solder(R, m),
    "wedge": lambda R, m: dnabla.wedge_solder(R, m),
    "module_averaged": lambda R, m: AveragedCovariantD(m)(R),
}


@pytest.mark.parametrize("name", sorted(VMAP_OPS) + sorted(VMAP_SQRT_OPS))
def test_vmap_equals_loop(mesh, name):
    fn = {**VMAP_OPS, **VMAP_SQRT_OPS}[name]
    R = rots(mesh, (3,))
    f = lambda r: fn(r, mesh)  # noqa: E731
    assert_close(torch.vmap(f)(R), loop_ref(f, R))
    # vmap over a non-leading dim and nested vmap
    assert_close(torch.vmap(f, in_dims=1)(R.movedim(0, 1)), loop_ref(f, R))
    R2 = rots(mesh, (2, 2))
    assert_close(torch.vmap(torch.vmap(f))(R2), loop_ref(f, R2))


def test_vmap_over_frames(mesh):
    R = rots(mesh, (3,))
    F = frames_of(mesh, (3,))
    f = lambda r, fr: torsion.face_torsion(r, mesh, kind="naive", frames=fr)  # noqa: E731
    assert_close(torch.vmap(f)(R, F), loop_ref(f, R, F))


# ----------------------------------------------------------------------------- forward mode (jvp)
JVP_OPS = {
    "curvature": lambda R, m: curvature.face_curvature(R, m),
    "holonomy": lambda R, m: curvature.face_curvature(R, m, kind="holonomy"),
    "torsion_sqrt": lambda R, m: torsion.face_torsion(R, m),
    "torsion_naive": lambda R, m: torsion.face_torsion(R, m, kind="naive"),
    "averaged_dd": lambda R, m: dnabla.averaged_dd_solder(R, m),
    "wedge": lambda R, m: dnabla.wedge_solder(R, m),
    "behs21": lambda R, m: dnabla.behs21_dd_solder(R, m),
    "bianchi_algebraic": lambda R, m: bianchi.algebraic_residual(R, m, reduce=False),
    "module_averaged": lambda R, m: AveragedCovariantD(m)(R),
    "module_torsion": lambda R, m: Torsion(m)(R),
}


def _jvp_check(fn, mesh, R, seed=9, forward_ad=True):
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(*R.shape[:-2], 3, generator=g, dtype=F64)
    V = R @ so3.hat(w)
    f = lambda r: fn(r, mesh)  # noqa: E731
    out, tangent = torch.func.jvp(f, (R,), (V,))
    assert_close(out, f(R))
    h = 1e-5
    fd = (f(R @ so3.exp(h * w)) - f(R @ so3.exp(-h * w))) / (2 * h)
    torch.testing.assert_close(tangent, fd, atol=1e-7, rtol=1e-7)
    if not forward_ad:
        return
    # the forward_ad API agrees with torch.func.jvp
    with torch.autograd.forward_ad.dual_level():
        dual = torch.autograd.forward_ad.make_dual(R, V)
        t2 = torch.autograd.forward_ad.unpack_dual(f(dual)).tangent
    assert_close(t2, tangent, tol=1e-12)


@pytest.mark.parametrize("name", sorted(JVP_OPS))
@pytest.mark.parametrize("batch", [(), (2,)], ids=["single", "batched"])
def test_jvp_matches_central_differences(mesh, name, batch):
    """torch.func.jvp along tangent directions of SO(3) (``R hat(w)``) against central
    differences of the curve ``R exp(t hat(w))``; the value equals the plain call. Rotation
    angles below pi/2 (see the next test for obtuse ones through so3.sqrt)."""
    R = rots(mesh, batch, scale=0.25)
    assert float(so3.log(R).norm(dim=-1).max()) < 1.5
    _jvp_check(JVP_OPS[name], mesh, R, forward_ad=name not in SQRT_USERS)


# these go through so3.sqrt (the torchconn::so3_sqrt op, whose eager wrapper has a jvp rule):
# the forward_ad API is checked separately below
SQRT_USERS = {"torsion_sqrt", "averaged_dd", "wedge", "bianchi_algebraic", "module_averaged", "module_torsion"}


@pytest.mark.parametrize("name", ["torsion_sqrt", "averaged_dd"])
def test_forward_ad_api_through_sqrt(mesh, name):
    _jvp_check(JVP_OPS[name], mesh, rots(mesh, (2,), scale=0.25))


@pytest.mark.parametrize("name", ["torsion_sqrt", "averaged_dd"])
def test_jvp_obtuse_angles_through_sqrt(mesh, name):
    R = rots(mesh, (2,), scale=1.5)
    assert float(so3.log(R).norm(dim=-1).max()) > 1.6
    _jvp_check(JVP_OPS[name], mesh, R)


def test_jvp_reaches_the_ops(mesh):
    """Forward mode goes to the ops (their eager autograd.Functions have exact jvp rules), not to
    the generic formulas, which agree with the fused tet closed form on SO(3) only: the tangent
    of ``averaged_dd_solder`` off SO(3) is the derivative of the value it returns there."""
    from torchconn.dec import _batch

    R = rots(mesh, (), scale=0.25)
    called = []
    with torch.autograd.forward_ad.dual_level():
        dual = torch.autograd.forward_ad.make_dual(R, torch.ones_like(R))
        assert _batch.ask_op(lambda: called.append(1), dual) is None
    assert called == [1]
    g = torch.Generator().manual_seed(3)
    M = R + 0.01 * torch.randn(R.shape, generator=g, dtype=F64)  # not rotations
    V = torch.randn(R.shape, generator=g, dtype=F64)            # an ambient direction
    f = lambda r: dnabla.averaged_dd_solder(r, mesh)  # noqa: E731
    _, tangent = torch.func.jvp(f, (M,), (V,))
    h = 1e-6
    torch.testing.assert_close(tangent, (f(M + h * V) - f(M - h * V)) / (2 * h), atol=1e-7, rtol=1e-7)
