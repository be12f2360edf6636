"""nn.Module wrappers: same values as the functional core, buffers follow .to(), gradients flow."""
from __future__ import annotations

import pytest
import torch

from torchconn import curvature, dnabla, io, so3, torsion
from torchconn.dec.bianchi import BianchiError
from torchconn.dec.connection import Connection
from torchconn.nn import AveragedCovariantD, BianchiCheck, ConnectionField, CovariantD, Curvature, MeshBuffers, Torsion


@pytest.fixture(scope="module")
def mesh():
    return io.box(n=2)  # 48 tets


def _random_conn(mesh, seed=0):
    return Connection.random_on_mesh(mesh, generator=torch.Generator().manual_seed(seed))


def test_modules_match_functional_core(mesh):
    conn = _random_conn(mesh)
    R = conn.edge_rot
    torch.testing.assert_close(Curvature(mesh)(conn), curvature.face_curvature(R, mesh), rtol=0, atol=0)
    torch.testing.assert_close(Torsion(mesh)(conn), torsion.face_torsion(R, mesh), rtol=0, atol=0)
    torch.testing.assert_close(AveragedCovariantD(mesh)(conn), dnabla.averaged_dd_solder(R, mesh), rtol=0, atol=0)
    torch.testing.assert_close(CovariantD(mesh, "behs21")(R), dnabla.behs21_dd_solder(R, mesh), rtol=0, atol=0)


def test_curvature_module_against_slow_reference(mesh):
    conn = _random_conn(mesh, 1)
    out = Curvature(mesh)(conn)
    for f in range(0, mesh.n_faces, 17):
        a, b, c = (int(x) for x in mesh.faces[f])
        Rab, Rbc, Rac = (conn.transport(torch.tensor([i]), torch.tensor([j]))[0] for i, j in ((a, b), (b, c), (a, c)))
        torch.testing.assert_close(out[f], Rab @ Rbc - Rac, rtol=0, atol=1e-14)


def test_accepts_field_and_tensor_and_rejects_wrong_edge_count(mesh):
    conn = _random_conn(mesh, 2)
    field = ConnectionField.from_connection(conn)
    mod = Curvature(mesh)
    torch.testing.assert_close(mod(field), mod(conn), rtol=0, atol=1e-12)
    torch.testing.assert_close(mod(conn.edge_rot), mod(conn), rtol=0, atol=0)
    with pytest.raises(ValueError, match="edge rotations"):
        mod(conn.edge_rot[:-1])
    with pytest.raises(TypeError, match="Connection"):
        mod("not a connection")


def test_buffers_follow_dtype(mesh):
    mod = AveragedCovariantD(mesh).to(torch.float32)
    assert mod.mesh.vertices.dtype == torch.float32
    assert mod.mesh.tets.dtype == torch.long  # integer topology is untouched
    R = _random_conn(mesh, 3).edge_rot.float()
    assert mod(R).dtype == torch.float32
    names = dict(mod.named_buffers())
    assert "mesh.tet_edges" in names and "mesh.vertices" in names


def test_cell_complex_module():
    m = io.box(n=2)
    cx = m.boundary_complex()
    R = so3.random_rotation(cx.n_edges, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    out = Curvature(cx, kind="holonomy")(R)
    torch.testing.assert_close(out, curvature.face_curvature(R, cx, kind="holonomy"), rtol=0, atol=0)
    assert isinstance(MeshBuffers(cx).face_groups, dict)


@pytest.mark.parametrize("module_cls", [Curvature, Torsion, AveragedCovariantD])
def test_gradcheck_through_modules(module_cls):
    m = io.box(n=1)  # 6 tets
    gen = torch.Generator().manual_seed(5)
    params = (0.8 * torch.randn(m.n_edges, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    mod = module_cls(m)
    assert torch.autograd.gradcheck(lambda p: mod(so3.exp(p)), (params,), eps=1e-6, atol=1e-7)


def test_bianchi_check_passes_and_raises(mesh):
    conn = _random_conn(mesh, 6)
    res = BianchiCheck(mesh)(conn)
    assert res["differential"] < 1e-12 and res["algebraic"] < 1e-12
    R = conn.edge_rot.clone()
    R[int(mesh.tet_edges[7, 0])] = float("nan")
    with pytest.raises(BianchiError, match="tet"):
        BianchiCheck(mesh)(R)
