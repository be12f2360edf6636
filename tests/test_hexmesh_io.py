"""Files of the hex-meshing stage (torchconn.hexmesh.io): ``.hexex`` bit for bit, ``.vtu`` and
``.mesh`` hex meshes through meshio, atomic writes, errors on malformed files, the picture."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from test_hexmesh_quality import CUBE, grid, three_around_an_axis
from torchconn import io
from torchconn.hexmesh.io import plot_hex_mesh, read_hex_mesh, read_hexex, write_hex_mesh, write_hexex
from torchconn.hexmesh.quality import hex_quality, scaled_jacobian

meshio = pytest.importorskip("meshio", reason="hex mesh files need meshio (pip install 'torchconn[io]')")


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def _map(seed=0):
    mesh = io.box(2)
    T = mesh.tets.numpy()
    rng = np.random.default_rng(seed)
    # random bit patterns over the whole finite range, and the hard cases of decimal round trips
    U = rng.integers(0, 2 ** 63 - 1, size=(T.shape[0], 4, 3), dtype=np.int64).view(np.float64)
    U = np.where(np.isfinite(U), U, 1.5) * rng.choice([-1.0, 1.0], size=U.shape)
    U[0] = [[0.1, 1 / 3, -0.0], [1e-300, 2.2250738585072014e-308, 5e-324], [1e300, -1.7976931348623157e308, 0.0],
            [2.0 / 3, 1e-7, 123456789.123456789]]
    return mesh.vertices.numpy() * (1 / 3), T, U


# ----------------------------------------------------------------------------- .hexex
def test_hexex_round_trip_is_bit_for_bit(tmp_path):
    V, T, U = _map()
    path = write_hexex(tmp_path / "igm.hexex", V, T, U)
    V2, T2, U2 = read_hexex(path)
    assert np.array_equal(_bits(V), _bits(V2)) and np.array_equal(T, T2) and np.array_equal(_bits(U), _bits(U2))
    assert T2.dtype == np.int64 and U2.shape == U.shape
    lines = path.read_text().splitlines()
    assert lines[0] == str(V.shape[0]) and lines[1 + V.shape[0]] == str(T.shape[0])
    assert lines[2 + V.shape[0]].split()[4:10] == ["0.1", "0.3333333333333333", "-0.0", "1e-300",
                                                   "2.2250738585072014e-308", "5e-324"]
    assert len(lines) == 2 + V.shape[0] + T.shape[0] and all(len(ln.split()) == 16 for ln in lines[2 + V.shape[0]:])
    # torch input, the same file
    write_hexex(tmp_path / "t.hexex", torch.from_numpy(V), torch.from_numpy(T), torch.from_numpy(U))
    assert (tmp_path / "t.hexex").read_bytes() == path.read_bytes()


def test_hexex_writer_refuses_bad_input_and_writes_nothing(tmp_path):
    V, T, U = _map()
    target = tmp_path / "igm.hexex"
    bad = [
        ((V, T, U[:-1]), r"uvw must have shape \(%d, 4, 3\)" % T.shape[0]),
        ((V, T[:, [0, 1, 3, 2]], U), r"tets \[0, 1, .*not positively oriented"),
        ((V, np.where(T == 5, 99, T), U), r"tets rows .* outside \[0, %d\)" % V.shape[0]),
        ((V, T, np.where(np.arange(U.size).reshape(U.shape) == 13, np.nan, U)),
         r"uvw has NaN/inf entries at rows \[1\]"),
        ((V, T.astype(float), U), r"tets must hold integer vertex indices"),
    ]
    for args, msg in bad:
        with pytest.raises(ValueError, match=msg):
            write_hexex(target, *args)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("text, message", [
    ("", r"empty file"),
    ("x\n", r"line 1: expected the number of vertices"),
    ("2\n0 0 0\n1 0\n0\n", r"line 3: a vertex line must hold 3 numbers, got 2"),
    ("2\n0 0 0\n1 0 zz\n0\n", r"line 3: entry 3 of the vertex line must be a finite number, got 'zz'"),
    ("1\n0 0 0\n", r"the number of tets is missing"),
    ("1\n0 0 0\n\n2\n" + "0 0 0 0" + " 0" * 12 + "\n", r"2 tet lines announced, the file ends after 1"),
    ("1\n0 0 0\n1\n0 0 0 0.5" + " 0" * 12 + "\n", r"line 4: entry 4 of the tet line must be an integer vertex index"),
    ("1\n0 0 0\n1\n0 0 0 0" + " 0" * 11 + " inf\n", r"line 4: entry 16 of the tet line must be a finite number"),
    ("1\n0 0 0\n1\n0 0 0 3" + " 0" * 12 + "\n", r"line 4: tet 0 has vertex indices outside \[0, 1\)"),
    ("1\n0 0 0\n0\n7\n", r"line 4: unexpected content after the 0 announced tets"),
])
def test_malformed_hexex_names_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.hexex"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        read_hexex(path)
    assert str(path) in str(err.value)


def test_hexex_reader_missing_and_binary_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such .hexex file"):
        read_hexex(tmp_path / "none.hexex")
    (tmp_path / "bin.hexex").write_bytes(b"3\n0 0 0\n\xff\xfe\n")
    with pytest.raises(ValueError, match=r"line 3: not a text .hexex file"):
        read_hexex(tmp_path / "bin.hexex")


# ----------------------------------------------------------------------------- .vtu / .mesh
@pytest.mark.parametrize("suffix, cell", [(".vtu", "hexahedron"), (".mesh", "hexahedron")])
def test_hex_mesh_files_read_back_by_meshio(tmp_path, suffix, cell):
    P, H, _ = three_around_an_axis(layers=2)
    path = write_hex_mesh(tmp_path / f"hex{suffix}", torch.from_numpy(P), H)
    m = meshio.read(path)  # meshio itself, not our reader
    blocks = [c.data for c in m.cells if c.type == cell]
    assert len(blocks) == 1 and np.array_equal(blocks[0], H)
    assert np.array_equal(np.asarray(m.points), P)
    assert (scaled_jacobian(m.points, blocks[0]) > 0).all()  # still positively oriented
    P2, H2 = read_hex_mesh(path)
    assert np.array_equal(P2, P) and np.array_equal(H2, H) and H2.dtype == np.int64
    assert hex_quality(P2, H2).irregular_valence_counts == {3: 2}


def test_vtu_opens_in_vtk(tmp_path):
    """ParaView's reader: VTK's own XML reader sees hexahedra (cell type 12), positively oriented."""
    vtk_io = pytest.importorskip("vtkmodules.vtkIOXML", reason="vtk is not installed (pip install vtk)")
    from vtkmodules.vtkFiltersVerdict import vtkMeshQuality

    P, H, _ = three_around_an_axis(layers=2)
    path = write_hex_mesh(tmp_path / "hex.vtu", P, H)
    reader = vtk_io.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid_ = reader.GetOutput()
    assert grid_.GetNumberOfCells() == H.shape[0] and grid_.GetNumberOfPoints() == P.shape[0]
    assert {grid_.GetCellType(i) for i in range(H.shape[0])} == {12}  # VTK_HEXAHEDRON
    sj = [vtkMeshQuality.HexScaledJacobian(grid_.GetCell(i)) for i in range(H.shape[0])]
    np.testing.assert_allclose(sj, scaled_jacobian(P, H), atol=1e-12)
    assert min(sj) > 0


def test_medit_file_with_boundary_quads_reads_its_hexahedra(tmp_path):
    P, H = grid(2)
    q = hex_quality(P, H)
    path = tmp_path / "with_quads.mesh"
    meshio.write(path, meshio.Mesh(P, [("quad", q.boundary_quads), ("hexahedron", H)]))
    P2, H2 = read_hex_mesh(path)
    assert np.array_equal(H2, H) and np.allclose(P2, P)


def test_hex_mesh_writes_are_atomic(tmp_path, monkeypatch):
    P, H = grid(2)
    target = tmp_path / "hex.vtu"
    target.write_bytes(b"the previous file")
    with pytest.raises(ValueError, match=r"hexes rows \[0\].* outside \[0, 27\)"):
        write_hex_mesh(target, P, np.where(np.arange(H.size).reshape(H.shape) == 3, 27, H))
    with pytest.raises(ValueError, match=r"unsupported hex mesh suffix '.obj'"):
        write_hex_mesh(tmp_path / "hex.obj", P, H)

    def half_then_fail(path, mesh, file_format=None, **kw):  # a writer that dies mid-file
        with open(path, "w") as f:
            f.write("<VTKFile half written")
        raise OSError("disk full")

    monkeypatch.setattr(meshio, "write", half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        write_hex_mesh(target, P, H)
    with pytest.raises(OSError, match="disk full"):
        write_hex_mesh(tmp_path / "new.mesh", P, H)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hex.vtu"]  # no temporary file, no new file
    assert target.read_bytes() == b"the previous file"  # the old file untouched
    monkeypatch.undo()
    write_hex_mesh(target, P, H)
    assert np.array_equal(read_hex_mesh(target)[1], H)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_hex_mesh(tmp_path / "no_dir" / "hex.vtu", P, H)


def test_malformed_hex_mesh_files(tmp_path):
    (tmp_path / "bad.vtu").write_text("<VTKFile garbage")
    with pytest.raises(ValueError, match=r"bad.vtu: cannot be read as a vtu hex mesh"):
        read_hex_mesh(tmp_path / "bad.vtu")  # meshio calls sys.exit on it: still a ValueError
    (tmp_path / "bad.mesh").write_text("MeshVersionFormatted 2\nDimension 3\nVertices\n2\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad.mesh: cannot be read as a medit hex mesh"):
        read_hex_mesh(tmp_path / "bad.mesh")
    mesh = io.box(1)
    meshio.write(tmp_path / "tets.vtu", meshio.Mesh(mesh.vertices.numpy(), [("tetra", mesh.tets.numpy())]))
    with pytest.raises(ValueError, match=r"volume cells other than hexahedra \(tetra\)"):
        read_hex_mesh(tmp_path / "tets.vtu")
    meshio.write(tmp_path / "quads.vtu", meshio.Mesh(CUBE, [("quad", np.array([[0, 1, 2, 3]]))]))
    with pytest.raises(ValueError, match=r"no hexahedra \(cells: quad\)"):
        read_hex_mesh(tmp_path / "quads.vtu")
    with pytest.raises(FileNotFoundError):
        read_hex_mesh(tmp_path / "none.vtu")


# ----------------------------------------------------------------------------- picture
def test_picture_is_written(tmp_path):
    P, H, _ = three_around_an_axis(layers=3)
    path = plot_hex_mesh(tmp_path / "hex.png", P, H, title="three hexes around an axis")
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    q = hex_quality(P, H)
    plot_hex_mesh(tmp_path / "again.png", P, H, quality=q)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.png", "hex.png"]
    with pytest.raises(ValueError, match=r"hexes must have shape"):
        plot_hex_mesh(tmp_path / "bad.png", P, H[:, :4])
    assert not (tmp_path / "bad.png").exists()
    assert os.path.getsize(tmp_path / "again.png") > 20_000
