"""A representative set of operators on every device present (issue 11, "any device").

Parametrized by the ``device`` fixture of ``conftest.py``: ``cpu`` always, ``cuda`` when
``torch.cuda.is_available()`` (skipped with that reason otherwise). Values and gradients on the
device are compared with the same calls on CPU. Inputs are drawn on CPU (seeded) and moved.
"""
from __future__ import annotations

import pytest
import torch

from torchconn.dec import curvature, dnabla, torsion
from torchconn.dec.connection import Connection
from torchconn.lie import so3
from torchconn.mesh import box
from torchconn.nn import AveragedCovariantD, ConnectionField, Curvature, Torsion

F64 = torch.float64


@pytest.fixture(scope="module")
def mesh():
    return box(2)


def params(mesh, batch=(), seed=0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    return (0.6 * torch.randn(*batch, mesh.n_edges, 3, generator=g, dtype=F64)).to(dtype)


def close(a, b, dtype):
    tol = 1e-10 if dtype == F64 else 2e-4
    assert a.shape == b.shape
    torch.testing.assert_close(a.cpu(), b.cpu(), atol=tol, rtol=tol)


OPS = {
    "curvature": lambda R, m, F: curvature.face_curvature(R, m),
    "holonomy": lambda R, m, F: curvature.face_curvature(R, m, kind="holonomy"),
    "torsion": lambda R, m, F: torsion.face_torsion(R, m),
    "torsion_frames": lambda R, m, F: torsion.face_torsion(R, m, frames=F),
    "averaged_dd": lambda R, m, F: dnabla.averaged_dd_solder(R, m),
    "averaged_dd_frames": lambda R, m, F: dnabla.averaged_dd_solder(R, m, frames=F),
}


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("batch", [(), (2,)], ids=["single", "batched"])
@pytest.mark.parametrize("name", sorted(OPS))
def test_ops_on_device_match_cpu(mesh, device, name, batch, dtype):
    fn = OPS[name]
    R_cpu = so3.exp(params(mesh, batch, dtype=dtype))
    F_cpu = so3.exp(params(mesh, (), seed=1, dtype=dtype)[: mesh.n_vertices])
    ref = fn(R_cpu, mesh, F_cpu)
    R, F = R_cpu.to(device), F_cpu.to(device)
    # the mesh moved to the device, and a CPU mesh used with device tensors
    for m in (mesh.to(device), mesh):
        out = fn(R, m, F)
        assert out.device.type == device.type and out.dtype == dtype
        close(out, ref, dtype)


@pytest.mark.parametrize("batch", [(), (2,)], ids=["single", "batched"])
def test_field_and_modules_forward_backward_on_device(mesh, device, batch):
    p = params(mesh, batch)
    frames = so3.exp(params(mesh, (), seed=1)[: mesh.n_vertices])

    def run(dev):
        field = ConnectionField(mesh.edges, mesh.n_vertices, init=p).to(dev)
        mods = [Curvature(mesh).to(dev), Torsion(mesh).to(dev), AveragedCovariantD(mesh).to(dev)]
        outs = [mods[0](field), mods[1](field, frames.to(dev)), mods[2](field)]
        loss = sum(o.square().sum() for o in outs)
        loss.backward()
        assert field.params.grad.device.type == torch.device(dev).type
        return [o.detach() for o in outs], field.params.grad

    outs, grad = run(device)
    outs_cpu, grad_cpu = run("cpu")
    for o, r in zip(outs, outs_cpu):
        close(o, r, F64)
    close(grad, grad_cpu, F64)


def test_so3_maps_on_device(device):
    g = torch.Generator().manual_seed(3)
    w = (2.0 * torch.randn(64, 3, generator=g, dtype=F64))
    R = so3.exp(w)
    for f, x in ((so3.exp, w), (so3.log, R), (so3.sqrt, R)):
        xd = x.detach().clone().to(device).requires_grad_()
        out = f(xd)
        out.square().sum().backward()
        xc = x.detach().clone().requires_grad_()
        oc = f(xc)
        oc.square().sum().backward()
        assert out.device.type == device.type
        close(out.detach(), oc.detach(), F64)
        close(xd.grad, xc.grad, F64)


def test_connection_on_device(mesh, device):
    c = Connection.random_on_mesh(mesh, generator=torch.Generator().manual_seed(4), batch_shape=(2,))
    cd = c.to(device)
    assert cd.edges.device.type == device.type
    i, j = mesh.edges[:4, 1], mesh.edges[:4, 0]
    close(cd.transport(i.to(device), j.to(device)), c.transport(i, j), F64)
    close(cd.half().edge_rot, c.half().edge_rot, F64)


def test_index_tables_move_once_per_device(mesh):
    """A CPU mesh used with tensors on another device: the index tables of the dec formulas are
    moved once and cached per device (``meta`` stands in for an accelerator here; no values are
    needed). The ops of ``torchconn.ops`` cache their own tables (``ops._cache``)."""
    m = box(1)
    R = torch.empty(2, m.n_edges, 3, 3, device="meta")
    frames = torch.empty(m.n_vertices, 3, 3, device="meta")
    dnabla.tet_solder_sqrt(R, m, frames=frames)
    dnabla.behs21_dd_solder(R, m)
    cached = m.__dict__.get("_derived", {})
    keys = {k for k in cached if k.startswith("dec.")}
    assert {"dec.edges.meta", "dec.tets.meta", "dec.tet_edges.meta", "dec.tet_edge_signs.meta"} <= keys
    before = {k: cached[k] for k in keys}
    dnabla.tet_solder_sqrt(R, m, frames=frames)
    dnabla.behs21_dd_solder(R, m)
    assert all(cached[k] is before[k] for k in keys)  # reused, not moved again
    assert all(cached[k].device.type == "meta" for k in keys)
