"""Mesh I/O: shared meshes with their documented counts, tetrahedralization of the shared
surfaces, file round trips, built-in meshes, and the error paths."""
from __future__ import annotations

import math

import meshio
import numpy as np
import pytest
import torch

import torchconn.mesh.io as tio
from torchconn.mesh import builtin
from torchconn.mesh.io import (ball, box, cylinder, load_mesh, load_polygon_surface, load_surface, load_tet_mesh,
                          tetrahedralize, torus)
from torchconn.mesh import MeshError, TetMesh

from conftest import data_path

# name: (V, T, boundary faces, boundary vertices, boundary Euler characteristic), README.md
TET_COUNTS = {
    "sphere_r0.17.mesh": (790, 3654, 700, 352, 2),
    "78322_gear.2.mesh": (8522, 39536, 7136, 3568, 0),
    "dinosaur.msh": (13270, 49973, 17212, 8608, 2),
}
# name: (V, F, boundary Euler characteristic)
SURFACE_COUNTS = {"bunny.obj": (3490, 6976, 2), "fandisk.ply": (7229, 14454, 2), "rocker_arm.ply": (10044, 20088, 0)}


def _check_valid(m: TetMesh, chi_boundary: int):
    assert (m.signed_volumes() > 0).all()
    bc = m.boundary_complex()
    assert bc.is_closed() and bc.is_edge_manifold() and bc.is_consistently_oriented()
    assert m.boundary_euler_characteristic() == chi_boundary == bc.euler_characteristic()
    torch.testing.assert_close(bc.enclosed_volume(), m.volume())


@pytest.mark.parametrize("name", list(TET_COUNTS))
def test_shared_tet_meshes(name):
    m = load_tet_mesh(data_path(name))
    V, T, B, Vb, chi = TET_COUNTS[name]
    assert (m.n_vertices, m.n_tets, m.n_boundary_faces, m.boundary_vertices.numel()) == (V, T, B, Vb)
    assert m.vertices.dtype == torch.float64
    _check_valid(m, chi)
    # one component: V - E + F - T equals 1 - (genus of the solid) here
    assert m.euler_characteristic() == chi // 2


@pytest.mark.parametrize("name", ["sphere_r0.17.mesh", "dinosaur.msh"])
def test_libigl_fallback(name, monkeypatch):
    path = data_path(name)
    ref = load_tet_mesh(path)

    def broken(p):
        raise RuntimeError("meshio disabled in this test")

    monkeypatch.setattr(tio, "_read_tets_meshio", broken)
    m = load_tet_mesh(path)
    assert torch.equal(m.tets, ref.tets)
    torch.testing.assert_close(m.vertices, ref.vertices, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", list(SURFACE_COUNTS))
def test_shared_surfaces_tetrahedralize(name):
    V, F = load_surface(data_path(name))
    nV, nF, chi = SURFACE_COUNTS[name]
    assert V.shape == (nV, 3) and F.shape == (nF, 3) and V.dtype == np.float64 and F.dtype == np.int64
    # coarse volume target and the input surface kept: the mesh size is set by the surface
    m = tetrahedralize(V, F, edge_length=float(np.ptp(V, axis=0).max()) / 4, keep_surface=True)
    _check_valid(m, chi)
    assert m.n_boundary_faces == nF  # 'Y' keeps every input triangle


def test_load_mesh_dispatch():
    m = load_mesh(data_path("bunny.obj"), edge_length=0.5)
    assert m.boundary_euler_characteristic() == 2 and (m.signed_volumes() > 0).all()
    t = load_mesh(data_path("sphere_r0.17.mesh"))
    assert t.n_tets == 3654


def _mesh_io_equal(a: TetMesh, b: TetMesh):
    assert torch.equal(a.tets, b.tets)
    torch.testing.assert_close(a.vertices, b.vertices, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "fname, fmt, kw",
    [
        ("m.msh", "gmsh", {"binary": False}),  # gmsh 4.1 ascii
        ("m.msh", "gmsh", {"binary": True}),  # gmsh 4.1 binary
        ("m.msh", "gmsh22", {"binary": False}),
        ("m.vtu", "vtu", {}),
        ("m.vtk", "vtk", {}),
        ("m.mesh", "medit", {}),
        ("m.node", "tetgen", {}),
    ],
)
def test_round_trip(tmp_path, fname, fmt, kw):
    m = box(2)
    path = tmp_path / fname
    meshio.write(path, meshio.Mesh(m.vertices.numpy(), [("tetra", m.tets.numpy())]), file_format=fmt, **kw)
    back = load_tet_mesh(path)
    _mesh_io_equal(back, m)
    if fname.endswith(".node"):
        _mesh_io_equal(load_tet_mesh(tmp_path / "m.ele"), m)


def test_hand_written_node_ele(tmp_path):
    # tetgen files, 1-based, with an attribute column and a comment
    (tmp_path / "t.node").write_text("# two tets\n5 3 1 0\n1 0 0 0 7\n2 1 0 0 7\n3 0 1 0 7\n4 0 0 1 7\n5 1 1 1 7\n")
    (tmp_path / "t.ele").write_text("2 4 0\n1 1 2 3 4\n2 2 5 3 4\n")
    m = load_tet_mesh(tmp_path / "t.ele")
    assert m.n_tets == 2 and m.n_vertices == 5
    assert torch.equal(m.tets, torch.tensor([[0, 1, 2, 3], [1, 4, 2, 3]]))


def test_load_errors(tmp_path):
    with pytest.raises(MeshError, match=r"unsupported tet-mesh suffix '\.xyz'"):
        load_tet_mesh(tmp_path / "a.xyz")
    with pytest.raises(MeshError, match="unsupported mesh suffix"):
        load_mesh(tmp_path / "a.foo")
    with pytest.raises(FileNotFoundError):
        load_tet_mesh(tmp_path / "missing.vtu")
    tri = tmp_path / "tri_only.vtu"
    meshio.write(tri, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshError, match=r"tri_only\.vtu contains no tetrahedra"):
        load_tet_mesh(tri)
    with pytest.raises(MeshError, match="unsupported surface suffix"):
        load_surface(tmp_path / "s.mesh")
    # tet-mesh kwargs pass through
    inv = tmp_path / "inv.vtu"
    meshio.write(inv, meshio.Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
                                  [("tetra", np.array([[0, 2, 1, 3]]))]))
    with pytest.raises(MeshError, match=r"inverted.*\[0\]"):
        load_tet_mesh(inv)
    assert (load_tet_mesh(inv, reorient=True, dtype=torch.float32).signed_volumes() > 0).all()


def test_polygon_surface_obj(tmp_path):
    obj = tmp_path / "cube.obj"
    lines = ["# unit cube, quads"] + [f"v {x} {y} {z}" for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4]]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}/1" for i in q) for q in quads]
    lines += ["f -7 -3 -1", "f -7 -1 -5"]  # last quad [1,5,7,3] as two triangles, relative indices
    obj.write_text("\n".join(lines) + "\n")
    cc = load_polygon_surface(obj)
    assert sorted(cc.face_groups) == [3, 4] and cc.n_faces == 7
    assert cc.face_groups[4].loops.tolist() == quads
    assert cc.face_groups[3].loops.tolist() == [[1, 5, 7], [1, 7, 3]]
    assert cc.is_closed() and cc.euler_characteristic() == 2
    torch.testing.assert_close(cc.enclosed_volume(), torch.tensor(1.0, dtype=torch.float64))
    V, F = load_surface(obj)  # pymeshlab triangulates the quads
    assert F.shape == (12, 3)


def _sphere_surface():
    V, F = builtin._primitive("create_sphere", radius=1.0, subdiv=1)
    return V, F


def test_tetrahedralize_rejects_bad_surfaces():
    V, F = _sphere_surface()
    with pytest.raises(MeshError, match=r"surface is not closed: 3 boundary edges, e\.g\. \("):
        tetrahedralize(V, F[1:])
    Fi = F.copy()
    Fi[0] = Fi[0, [0, 2, 1]]
    with pytest.raises(MeshError, match="not consistently oriented: 3 edges"):
        tetrahedralize(V, Fi)
    Fd = np.vstack([F, F[:1]])  # one triangle twice: its edges are in three faces
    with pytest.raises(MeshError, match="not edge-manifold: 3 edges"):
        tetrahedralize(V, Fd)
    Vz = V.copy()
    a, b, c = F[0]
    Vz[c] = 0.5 * (Vz[a] + Vz[b])  # flatten triangle 0 (and bend its neighbours)
    with pytest.raises(MeshError, match=r"degenerate.*\[0"):
        tetrahedralize(Vz, F)
    with pytest.raises(MeshError, match=r"V \(N, 3\) and F \(M, 3\)"):
        tetrahedralize(V[:, :2], F)


@pytest.mark.parametrize(
    "make, volume, chi, rel",
    [
        (lambda: box(3, size=2.0), 8.0, 2, 1e-12),
        (lambda: ball(), 4 / 3 * math.pi, 2, 0.05),
        (lambda: cylinder(), math.pi * 2.0, 2, 0.05),
        # the coarse polygonal tube (11 sides) loses about 5 % of the smooth volume
        (lambda: torus(), 2 * math.pi**2 * 1.0 * 0.4**2, 0, 0.1),
    ],
)
def test_builtins(make, volume, chi, rel):
    m = make()
    _check_valid(m, chi)
    assert m.euler_characteristic() == chi // 2
    assert abs(float(m.volume()) - volume) <= rel * volume


def test_subdivide_torus():
    m = torus(edge_length=0.4)
    s = m.subdivide()
    assert s.n_tets == 8 * m.n_tets and (s.signed_volumes() > 0).all()
    torch.testing.assert_close(s.volume(), m.volume())
    assert s.euler_characteristic() == 0 and s.boundary_euler_characteristic() == 0


def test_builtin_geometry():
    c = cylinder(radius=0.5, height=3.0)
    lo, hi = c.vertices.min(0).values, c.vertices.max(0).values
    torch.testing.assert_close(hi[2] - lo[2], torch.tensor(3.0, dtype=torch.float64))  # axis z
    assert float(c.vertices[:, :2].norm(dim=1).max()) <= 0.5 + 1e-9
    b = ball(radius=2.0, center=(1.0, 0.0, 0.0))
    r = (b.vertices[b.boundary_vertices] - torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)).norm(dim=1)
    assert float(r.max()) <= 2.0 + 1e-9 and float(r.min()) > 1.8
    k = box((1, 2, 3), dtype=torch.float32)
    assert k.vertices.dtype == torch.float32 and k.n_tets == 36
    with pytest.raises(MeshError, match="minor_radius"):
        torus(major_radius=0.3, minor_radius=0.5)


@pytest.mark.parametrize("suffix", [".stl", ".off", ".ply"])
def test_surface_formats_round_trip(tmp_path, suffix):
    V, F = _sphere_surface()
    path = tmp_path / f"s{suffix}"
    meshio.write(path, meshio.Mesh(V, [("triangle", F)]))
    V2, F2 = load_surface(path)  # STL stores corners per triangle; the reader merges them
    assert V2.shape == V.shape and F2.shape == F.shape
    m = load_mesh(path, edge_length=0.5)
    _check_valid(m, 2)
