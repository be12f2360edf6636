"""Frame files for hex meshers (.fra, mouette's .frame), meshio conversion, boundary surface and
tagged gmsh files written by meshio (no gmsh needed)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import io, so3
from torchconn.frames.constraints import BoundaryConstraint, boundary_face_normals, feature_edges
from torchconn.frames.field_files import read_fra, read_mouette_frame, write_fra, write_mouette_frame
from torchconn.mesh.cad import cad_tags_from_elements, load_tagged_msh
from torchconn.mesh.convert import from_meshio, to_meshio


@pytest.fixture(scope="module")
def cube():
    return io.box(2).to(dtype=torch.float64)


def _rotations(n, gen):
    return so3.exp(torch.randn(n, 3, generator=gen, dtype=torch.float64) * 2.0)


# ----------------------------------------------------------------------------- .fra
def test_fra_round_trip_is_exact_and_follows_the_layout(tmp_path, cube, gen):
    frames = _rotations(cube.n_tets, gen)
    p = write_fra(tmp_path / "f.fra", frames, cube)
    lines = p.read_text().splitlines()
    assert lines[0] == "FRA 1"
    assert lines[1] == f"{cube.n_tets} 3 4"
    assert len(lines) == 2 + 3 * cube.n_tets
    # tet 1, axis 2 = column 2 of frames[1] on line 2 + 3*1 + 2
    assert np.array([float(x) for x in lines[2 + 3 + 2].split()]).tolist() == frames[1][:, 2].tolist()
    back = read_fra(p)
    assert back.dtype == torch.float64 and torch.equal(back, frames)


def test_fra_rejects_bad_files(tmp_path, cube, gen):
    frames = _rotations(3, gen)
    with pytest.raises(ValueError, match="T = "):
        write_fra(tmp_path / "x.fra", frames, cube)
    p = write_fra(tmp_path / "x.fra", frames)
    text = p.read_text().splitlines()
    (tmp_path / "h.fra").write_text("\n".join(["FRA 2"] + text[1:]))
    with pytest.raises(ValueError, match="line 1"):
        read_fra(tmp_path / "h.fra")
    (tmp_path / "c.fra").write_text("\n".join(text[:2] + text[2:-1]))
    with pytest.raises(ValueError, match="9 axis lines"):
        read_fra(tmp_path / "c.fra")
    (tmp_path / "r.fra").write_text("\n".join(text[:2] + ["1 2"] + text[3:]))
    with pytest.raises(ValueError, match="line 3"):
        read_fra(tmp_path / "r.fra")


# ----------------------------------------------------------------------------- mouette .frame
def test_mouette_frame_round_trip_and_layout(tmp_path, cube, gen):
    frames = _rotations(cube.n_tets, gen)
    p = write_mouette_frame(tmp_path / "f.frame", frames, cube)
    lines = p.read_text().splitlines()
    assert lines[0] == "FRAME" and lines[1] == str(cube.n_tets) and lines[-1] == "END"
    # mouette writes mat[0][0] mat[1][0] mat[2][0] mat[0][1] ...: column after column
    row = [float(x) for x in lines[2 + 4].split()]
    assert row == frames[4].T.reshape(-1).tolist()
    assert torch.equal(read_mouette_frame(p), frames)
    # mouette's reader does not need END
    (tmp_path / "n.frame").write_text("\n".join(lines[:-1]) + "\n")
    assert torch.equal(read_mouette_frame(tmp_path / "n.frame"), frames)
    (tmp_path / "b.frame").write_text("\n".join(lines[:2] + lines[3:]))
    with pytest.raises(ValueError, match="frame lines"):
        read_mouette_frame(tmp_path / "b.frame")


# ----------------------------------------------------------------------------- meshio, boundary surface
def test_meshio_round_trip(tmp_path, cube, gen):
    pytest.importorskip("meshio", reason="meshio is part of the io extra")
    m = to_meshio(cube, point_data={"w": torch.arange(cube.n_vertices)}, cell_data={"q": torch.ones(cube.n_tets, 3)})
    assert m.cells[0].type == "tetra" and len(m.cells) == 1
    back = from_meshio(m)
    assert torch.equal(back.vertices, cube.vertices) and torch.equal(back.tets, cube.tets)
    assert back.cad is None
    m.write(tmp_path / "c.vtu")
    import meshio

    again = from_meshio(meshio.read(tmp_path / "c.vtu"))
    assert torch.equal(again.tets, cube.tets) and torch.equal(again.vertices, cube.vertices)


def test_boundary_surface_is_the_closed_outward_boundary(cube):
    V, F = cube.boundary_surface()
    assert V.shape == (cube.boundary_vertices.numel(), 3) and F.shape == (cube.n_boundary_faces, 3)
    assert torch.equal(cube.boundary_vertices[F], cube.boundary_faces)
    # divergence theorem: (1/6) sum over outward triangles of (a x b) . c = enclosed volume
    p = V[F]
    vol = (torch.linalg.cross(p[:, 0], p[:, 1], dim=-1) * p[:, 2]).sum() / 6
    torch.testing.assert_close(vol, cube.volume())


def _box_tags(mesh):
    """Tags of the cube [.,.]^3 from geometry: surface = 1 + 2*axis + (max side), the 12 sharp
    edges with a curve id per (direction, position), the 8 corners."""
    bf = mesh.boundary_faces
    n = boundary_face_normals(mesh)
    axis = n.abs().argmax(1)
    surf = 1 + 2 * axis + (n.gather(1, axis[:, None]).squeeze(1) > 0).long()
    fe = feature_edges(mesh, 30.0)
    d = (mesh.vertices[fe[:, 1]] - mesh.vertices[fe[:, 0]]).abs().argmax(1)
    mid = (mesh.vertices[fe[:, 0]] + mesh.vertices[fe[:, 1]]) / 2
    lo, hi = mesh.vertices.min(0).values, mesh.vertices.max(0).values
    side = ((mid - lo).abs() > (mid - hi).abs()).long()  # 1 on the max side per coordinate
    side[torch.arange(fe.shape[0]), d] = 0
    curve = 100 + 10 * d + 4 * side[:, 0] + 2 * side[:, 1] + side[:, 2]
    at_lo = (mesh.vertices - lo).abs() < 1e-9
    at_hi = (mesh.vertices - hi).abs() < 1e-9
    corners = ((at_lo | at_hi).all(1)).nonzero().flatten()
    return bf, surf, fe, curve, corners


def test_tagged_msh_written_by_meshio_reads_back(tmp_path, cube):
    pytest.importorskip("meshio", reason="meshio is part of the io extra")
    bf, surf, fe, curve, corners = _box_tags(cube)
    cube = cube.to()  # a copy: tags on the shared fixture would leak into other tests
    cube.cad = cad_tags_from_elements(cube, bf, surf, fe, curve, corners, 1000 + torch.arange(corners.numel()))
    assert cube.cad.n_surfaces == 6 and cube.cad.n_curves == 12 and corners.numel() == 8
    m = to_meshio(cube)
    assert [c.type for c in m.cells] == ["tetra", "triangle", "line", "vertex"]
    m.write(tmp_path / "t.msh", file_format="gmsh22", binary=False)
    back = load_tagged_msh(tmp_path / "t.msh")
    assert torch.equal(back.tets, cube.tets)
    for name in ("face_surface", "boundary_face_surface", "feature_edges", "feature_edge_curve",
                 "corner_vertices", "corner_point"):
        assert torch.equal(getattr(back.cad, name), getattr(cube.cad, name)), name
    # the boundary constraint takes these CAD curves: on a cube they are the sharp edges
    bc = BoundaryConstraint.from_mesh(back)
    assert bc.feature_source == "cad" and torch.equal(bc.feature_edges, fe)
    assert BoundaryConstraint.from_mesh(back, features="dihedral").feature_source == "dihedral"
    # tags follow the mesh to another dtype
    assert back.to(dtype=torch.float32).cad.feature_edges.device == back.device


def test_tags_that_are_not_mesh_faces_raise(cube):
    from torchconn.mesh import MeshError

    bf = cube.boundary_faces
    bad = bf.clone()
    bad[3] = torch.tensor([0, 1, cube.n_vertices - 1])
    with pytest.raises(MeshError, match="triangle indices \\[3\\]"):
        cad_tags_from_elements(cube, bad, torch.zeros(bf.shape[0], dtype=torch.long))
    with pytest.raises(MeshError, match="not edges"):
        cad_tags_from_elements(cube, lines=[[0, cube.n_vertices - 1]], line_tags=[1])
    other = io.box(3)
    with pytest.raises(MeshError, match="another mesh"):
        other.cad = cad_tags_from_elements(cube, bf, torch.zeros(bf.shape[0], dtype=torch.long))


def test_feature_curve_alignment_on_a_tagged_cube(cube):
    """Exact values: the cube's curves run along x, y, z; a field rotated by 20 degrees about z
    is 20 degrees off on the x and y curves and aligned on the z curves."""
    from torchconn.frames.constraints import feature_curve_alignment

    bf, surf, fe, curve, corners = _box_tags(cube)
    mesh = cube.to()
    mesh.cad = cad_tags_from_elements(mesh, bf, surf, fe, curve, corners, torch.arange(corners.numel()))
    eye = torch.eye(3, dtype=torch.float64).expand(mesh.n_vertices, 3, 3)
    m = feature_curve_alignment(eye, mesh)
    assert m["feature_curve_alignment_max_deg"] < 1e-6 and m["feature_curve_corner_alignment_max_deg"] < 1e-6
    assert m["n_feature_curve_edges"] == fe.shape[0] and m["n_feature_corners"] == 8
    a = torch.deg2rad(torch.tensor(20.0, dtype=torch.float64))
    Rz = torch.tensor([[a.cos(), -a.sin(), 0], [a.sin(), a.cos(), 0], [0, 0, 1]], dtype=torch.float64)
    m = feature_curve_alignment(Rz @ eye, mesh)
    bc = BoundaryConstraint.from_mesh(mesh)
    along_z = bc.tangent_dirs[~bc.tangent_at_corner, 2].abs() > 0.5
    expected = 20.0 * float((~along_z).double().mean())
    assert m["feature_curve_alignment_mean_deg"] == pytest.approx(expected, abs=1e-9)
    assert m["feature_curve_alignment_max_deg"] == pytest.approx(20.0, abs=1e-9)
    # float32 mesh: the constraint follows the dtype, the tags the device
    m32 = mesh.to(dtype=torch.float32)
    bc32 = BoundaryConstraint.from_mesh(m32)
    assert bc32.tangent_dirs.dtype == torch.float32 and torch.equal(bc32.feature_edges, bc.feature_edges)


def test_feature_sources():
    ball = io.ball(edge_length=0.5).to(dtype=torch.float64)
    with pytest.raises(ValueError, match="CAD tags"):
        BoundaryConstraint.from_mesh(ball, features="cad")
    with pytest.raises(ValueError, match="features must be"):
        BoundaryConstraint.from_mesh(ball, features="sharp")
    from torchconn.frames.constraints import feature_curve_alignment

    m = feature_curve_alignment(torch.eye(3, dtype=torch.float64).expand(ball.n_vertices, 3, 3), ball, 60.0)
    assert m["n_feature_curve_edges"] == 0 and np.isnan(m["feature_curve_alignment_mean_deg"])


def test_frames_vtu_with_tet_frames_round_trip(tmp_path):
    from torchconn.frames import FramesVTU, read_frames_vtu, write_frames_vtu  # the public names (README)

    m = io.box(2)
    gen = torch.Generator().manual_seed(3)
    Fv = so3.random_rotation(m.n_vertices, generator=gen, dtype=torch.float64)
    Ft = so3.random_rotation(m.n_tets, generator=gen, dtype=torch.float64)
    write_frames_vtu(tmp_path / "f.vtu", m, Fv, Ft)
    V, T, Fv2, Ft2 = read_frames_vtu(tmp_path / "f.vtu")
    assert np.array_equal(V, m.vertices.numpy()) and np.array_equal(T, m.tets.numpy())
    assert np.array_equal(Fv2, Fv.numpy()) and np.array_equal(Ft2, Ft.numpy())
    back = read_frames_vtu(tmp_path / "f.vtu")  # a named tuple: the same arrays by name
    assert isinstance(back, FramesVTU) and back._fields == ("vertices", "tets", "vertex_frames", "tet_frames")
    assert np.array_equal(back.vertex_frames, Fv.numpy()) and np.array_equal(back.tet_frames, Ft.numpy())
    assert back.vertices.shape == (m.n_vertices, 3) and back.tets.shape == (m.n_tets, 4)
    write_frames_vtu(tmp_path / "g.vtu", m, Fv)  # per-vertex only
    assert read_frames_vtu(tmp_path / "g.vtu")[3] is None and read_frames_vtu(tmp_path / "g.vtu").tet_frames is None
    with pytest.raises(ValueError, match=r"tet_frames must have shape \(T, 3, 3\)"):
        write_frames_vtu(tmp_path / "h.vtu", m, Fv, Ft[:-1])
