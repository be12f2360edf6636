"""Meta device (issue 11): meshes, connections, fields and modules built and called on ``meta``
(shapes only); checks that need values are skipped there, diagnostics that return values raise."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn.dec import bianchi, curvature, dnabla, torsion
from torchconn.dec.connection import Connection
from torchconn.lie import so3, son
from torchconn.mesh import CellComplex, MeshError, TetMesh, box
from torchconn.nn import (AveragedCovariantD, BianchiCheck, ConnectionField, CovariantD, Curvature, Torsion)

META = torch.device("meta")


@pytest.fixture(scope="module")
def cpu_mesh():
    return box(2)


@pytest.fixture(scope="module")
def meta_mesh():
    return box(2, device="meta")


def test_box_on_meta_has_the_cpu_topology_shapes(cpu_mesh, meta_mesh):
    assert meta_mesh.device == META
    for name, t in cpu_mesh.buffers().items():
        m = getattr(meta_mesh, name)
        assert m.device == META and m.shape == t.shape and m.dtype == t.dtype, name
    moved = cpu_mesh.to("meta")
    assert moved.device == META and moved.n_edges == cpu_mesh.n_edges


def test_tet_mesh_and_complex_constructors_on_meta():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    T = [[0, 1, 2, 3], [1, 2, 3, 4]]
    m = TetMesh(V, T, device="meta")
    assert m.device == META and m.n_edges == 9 and m.faces.shape == (7, 3)
    cx = CellComplex(V, [[0, 1, 2], [0, 1, 3, 4]], device="meta")
    assert cx.device == META and all(g.loops.device == META for g in cx.face_groups.values())
    # validation still runs (on CPU) before the move
    with pytest.raises(MeshError, match="repeated vertex"):
        TetMesh(V, [[0, 1, 2, 2]], device="meta")
    # meta vertices carry no values: a clear error, not an .item() failure
    with pytest.raises(MeshError, match="meta device carry no values"):
        TetMesh(torch.empty(5, 3, device="meta"), T)


def test_connection_and_field_on_meta(cpu_mesh, meta_mesh):
    E = cpu_mesh.n_edges
    f = ConnectionField(cpu_mesh.edges, cpu_mesh.n_vertices, device="meta")
    assert f.params.device == META and f().edge_rot.shape == (E, 3, 3) and f().edge_rot.device == META
    fb = ConnectionField(meta_mesh.edges, meta_mesh.n_vertices, batch_shape=(4,))
    assert fb.params.shape == (4, E, 3) and fb().edge_rot.device == META
    # rotation / parameter inits on meta: the value checks are skipped, the shapes checked
    R = torch.empty(2, E, 3, 3, device="meta")
    assert ConnectionField(meta_mesh.edges, meta_mesh.n_vertices, init=R).params.shape == (2, E, 3)
    assert ConnectionField(meta_mesh.edges, meta_mesh.n_vertices, init=torch.empty(E, 3, device="meta")).batch_shape == ()
    with pytest.raises(ValueError, match=r"must have shape \(\*batch_shape, %d, 3\)" % E):
        ConnectionField(meta_mesh.edges, meta_mesh.n_vertices, init=torch.empty(E + 1, 3, device="meta"))
    c = Connection(R, meta_mesh.edges, meta_mesh.n_vertices, validate=True)
    assert c.batch_shape == (2,) and c.half().edge_rot.device == META
    c.check_rotations()  # no values: skipped (documented), no .item() failure
    son.check_rotation(R)
    assert Connection.from_mesh(meta_mesh).edge_rot.device == META


MODULES = {
    "curvature": (lambda m: Curvature(m), "F33"),
    "holonomy": (lambda m: Curvature(m, kind="holonomy"), "F33"),
    "torsion": (lambda m: Torsion(m), "F3"),
    "torsion_naive": (lambda m: Torsion(m, kind="naive"), "F3"),
    "averaged": (lambda m: AveragedCovariantD(m), "T3"),
    "behs21": (lambda m: CovariantD(m, "behs21"), "T3"),
    "wedge": (lambda m: CovariantD(m, "wedge"), "T3"),
}


@pytest.mark.parametrize("name", sorted(MODULES))
@pytest.mark.parametrize("batch", [(), (3,)])
def test_modules_on_meta_match_cpu_shapes(cpu_mesh, meta_mesh, name, batch):
    make, _ = MODULES[name]
    field = ConnectionField(meta_mesh.edges, meta_mesh.n_vertices, batch_shape=batch, dtype=torch.float32)
    out = make(meta_mesh)(field)
    ref = make(cpu_mesh)(ConnectionField(cpu_mesh.edges, cpu_mesh.n_vertices, batch_shape=batch,
                                         dtype=torch.float32))
    assert out.device == META and out.shape == ref.shape and out.dtype == torch.float32
    # a module built on CPU and moved to meta with .to()
    moved = make(cpu_mesh).to("meta")
    assert moved(field).shape == ref.shape
    # frames on meta
    if name.startswith(("torsion", "averaged")):
        F = torch.empty(*batch, meta_mesh.n_vertices, 3, 3, device="meta")
        assert make(meta_mesh)(field, F).shape == ref.shape


def test_functional_ops_on_meta(cpu_mesh, meta_mesh):
    E, T, F = cpu_mesh.n_edges, cpu_mesh.tets.shape[0], cpu_mesh.faces.shape[0]
    R = torch.empty(2, E, 3, 3, device="meta")
    assert curvature.face_curvature(R, meta_mesh, cut=1).shape == (2, F, 3, 3)
    assert torsion.face_torsion(R, meta_mesh, frames=torch.empty(meta_mesh.n_vertices, 3, 3, device="meta")).shape == (2, F, 3)
    assert dnabla.averaged_dd_solder(R, meta_mesh).shape == (2, T, 3)
    assert dnabla.tet_solder_sqrt(R, meta_mesh).shape == (2, T, 4, 4, 3)
    assert bianchi.differential_residual(R, meta_mesh).shape == (2, T)
    assert bianchi.algebraic_residual(R, meta_mesh).shape == (2, T)
    tfr = torch.empty(T, 4, 3, 3, device="meta")
    fer = torch.empty(F, 3, 3, 3, device="meta")
    ev = torch.empty(2, E, 3, device="meta")
    assert dnabla.primal_dual_wedge_mesh(tfr, fer, ev, meta_mesh).shape == (2, T, 3)
    # the so3 maps through lie.so3
    x = torch.empty(4, E, 3, device="meta")
    assert so3.exp(x).shape == (4, E, 3, 3) and so3.log(so3.exp(x)).shape == (4, E, 3)
    assert so3.sqrt(R).shape == R.shape


def test_cell_complex_curvature_on_meta():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]])
    cx = CellComplex(V, [[0, 1, 2, 3], [1, 4, 2]], device="meta")
    R = torch.empty(3, cx.n_edges, 3, 3, device="meta")
    assert curvature.face_curvature(R, cx).shape == (3, 2, 3, 3)
    assert Curvature(cx)(R).shape == (3, 2, 3, 3)


def test_value_diagnostics_raise_on_meta(meta_mesh):
    R = torch.empty(meta_mesh.n_edges, 3, 3, device="meta")
    with pytest.raises(ValueError, match="meta tensors carry no values"):
        BianchiCheck(meta_mesh)(R)
    with pytest.raises(ValueError, match="meta tensors carry no values"):
        bianchi.check(R, meta_mesh)
