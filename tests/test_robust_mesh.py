"""Bad mesh input (issue 14): every case ends in a MeshError (or a warning that counts what was
repaired) whose message names the problem, where it is and what to do; never a crash, a
``sys.exit`` or silent corruption. The bad files are written here, in ``tmp_path``.

No test runs tetgen on a self-intersecting surface: ``_no_tetgen`` replaces it with a failure.
"""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

from torchconn.mesh import MeshError, TetMesh, builtin, merge_duplicate_vertices
from torchconn.mesh.io import ball, cylinder, load_mesh, load_polygon_surface, load_surface, load_tet_mesh, tetrahedralize

from conftest import data_path

TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
# two positive tets sharing the face (1, 2, 3)
TWO_V = np.vstack([TET_V, [[1.0, 1, 1]]])
TWO_T = np.array([[0, 1, 2, 3], [4, 3, 2, 1]])


def _sphere(subdiv: int = 1, scale: float = 1.0, shift=(0.0, 0.0, 0.0)):
    V, F = builtin._primitive("create_sphere", radius=1.0, subdiv=subdiv)
    return V * scale + np.asarray(shift), builtin._orient_outward(V, F)


def _write_obj(path, V, F):
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in V]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")
    return path


def _write_medit(path, V, T, version: int = 1, extra: str = ""):
    rows = "\n".join(f"{float(x)!r} {float(y)!r} {float(z)!r} 0" for x, y, z in V)
    tets = "\n".join(" ".join(str(int(i) + 1) for i in t) + " 0" for t in T)
    path.write_text(f"MeshVersionFormatted {version}\nDimension 3\nVertices\n{len(V)}\n{rows}\n{extra}"
                    f"Tetrahedra\n{len(T)}\n{tets}\nEnd\n")
    return path


@pytest.fixture
def _no_tetgen(monkeypatch):
    import igl.copyleft.tetgen as tg

    def refuse(*args, **kwargs):
        raise AssertionError("tetgen must not run on this surface")

    monkeypatch.setattr(tg, "tetrahedralize", refuse)


# ----------------------------------------------------------------------------- 1 self-intersections
def test_overlapping_spheres_named_before_tetgen(tmp_path, _no_tetgen):
    V1, F1 = _sphere()
    V = np.vstack([V1, V1 + [1.0, 0.0, 0.0]])
    F = np.vstack([F1, F1 + len(V1)])
    path = _write_obj(tmp_path / "two_spheres.obj", V, F)
    crossing = builtin.self_intersecting_faces(V, F)
    assert crossing.size > 0 and (crossing < len(F)).all()
    with pytest.raises(MeshError, match=r"two_spheres\.obj: surface self-intersects: triangles \[.*\(count "
                                        rf"{crossing.size}\).*Repair the surface"):
        load_mesh(path, edge_length=0.3)


def test_single_self_intersection_named(_no_tetgen):
    V, F = _sphere(subdiv=2)
    V[0] = -1.3 * V[0]  # push one vertex through the opposite side: its fan crosses the surface
    fan = np.nonzero((F == 0).any(axis=1))[0]
    crossing = builtin.self_intersecting_faces(V, F)
    assert set(fan.tolist()) <= set(crossing.tolist())
    with pytest.raises(MeshError, match=rf"self-intersects: triangles \[{int(crossing[0])}, .*cross other triangles"):
        tetrahedralize(V, F, edge_length=0.3)


def test_clean_surface_has_no_self_intersections():
    V, F = _sphere(subdiv=2)
    assert builtin.self_intersecting_faces(V, F).size == 0


# ----------------------------------------------------------------------------- 2 unreadable files
def test_empty_medit_file(tmp_path):
    (tmp_path / "empty.mesh").write_text("")
    with pytest.raises(MeshError, match=r"empty\.mesh is empty: a MEDIT \.mesh file needs 'Vertices'"):
        load_tet_mesh(tmp_path / "empty.mesh")


def test_medit_renamed_vtk(tmp_path):
    path = _write_medit(tmp_path / "tets.vtk", TWO_V, TWO_T)
    with pytest.raises(MeshError, match=r"could not read .*tets\.vtk as a VTK \.vtk file: SystemExit.*"
                                        r"suffix matches its content"):
        load_tet_mesh(path)


def test_obj_renamed_msh(tmp_path):
    V, F = _sphere(subdiv=0)
    path = _write_obj(tmp_path / "surface.msh", V, F)
    with pytest.raises(MeshError, match=r"could not read .*surface\.msh as a gmsh \.msh file: meshio: .*libigl: "):
        load_mesh(path)


def test_obj_renamed_medit(tmp_path):
    V, F = _sphere(subdiv=0)
    path = _write_obj(tmp_path / "surface.mesh", V, F)
    with pytest.raises(MeshError, match=r"surface\.mesh is not a MEDIT \.mesh file: no 'Vertices' section"):
        load_tet_mesh(path)


def test_empty_vtu(tmp_path):
    (tmp_path / "empty.vtu").write_text("")
    with pytest.raises(MeshError, match=r"could not read .*empty\.vtu as a VTU \.vtu file \(the file is empty\)"):
        load_tet_mesh(tmp_path / "empty.vtu")


def test_garbage_polygon_surface(tmp_path):
    (tmp_path / "junk.off").write_text("this is not an OFF file\n1 2 3\n")
    with pytest.raises(MeshError, match=r"could not read surface .*junk\.off as \.off"):
        load_polygon_surface(tmp_path / "junk.off")


# ----------------------------------------------------------------------------- 3 .mesh precision
def test_shared_sphere_read_at_full_precision():
    path = data_path("sphere_r0.17.mesh")
    lines = path.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip() == "Vertices")
    n = int(lines[start + 1])
    ref = np.array([[float(x) for x in line.split()[:3]] for line in lines[start + 2:start + 2 + n]])
    assert lines[0].split() == ["MeshVersionFormatted", "1"]
    m = load_tet_mesh(path)
    assert np.array_equal(m.vertices.numpy(), ref)  # bitwise: float64 from the 17-digit text


def test_small_tet_far_from_origin_is_not_zero_volume(tmp_path):
    # 5e-8 offsets at coordinate 1 vanish in float32 (the tet collapsed to "zero-volume" before)
    V = np.array([[1.0, 1, 1], [1 + 5e-8, 1, 1], [1, 1 + 5e-8, 1], [1, 1, 1 + 5e-8]])
    m = load_tet_mesh(_write_medit(tmp_path / "needle.mesh", V, [[0, 1, 2, 3]], version=1))
    assert np.array_equal(m.vertices.numpy(), V) and float(m.volume()) > 0


def test_medit_sections_comments_and_inline_counts(tmp_path):
    rows = "\n".join(f"{x} {y} {z} 1" for x, y, z in TWO_V)
    text = (f"MeshVersionFormatted 2 # double\nDimension\n3\nVertices 5\n{rows}\n"
            "Edges\n1\n1 2 0\nTriangles\n1\n1 2 3 7\n"
            "Corners\n2\n1\n2\n# tets follow\nTetrahedra 2\n1 2 3 4 0\n5 4 3 2 0\nEnd\n")
    (tmp_path / "m.mesh").write_text(text)
    m = load_tet_mesh(tmp_path / "m.mesh")
    assert torch.equal(m.tets, torch.as_tensor(TWO_T)) and np.array_equal(m.vertices.numpy(), TWO_V)


def test_medit_malformed_section_named(tmp_path):
    path = _write_medit(tmp_path / "short.mesh", TWO_V, TWO_T)
    path.write_text(path.read_text().replace("Vertices\n5\n", "Vertices\n6\n"))
    with pytest.raises(MeshError, match=r"short\.mesh: section 'Vertices' is malformed: .*got 20 numbers \(count 6\)"):
        load_tet_mesh(path)


def test_medit_2d_rejected(tmp_path):
    path = _write_medit(tmp_path / "flat.mesh", TWO_V, TWO_T)
    path.write_text(path.read_text().replace("Dimension 3", "Dimension 2"))
    with pytest.raises(MeshError, match=r"flat\.mesh: 'Dimension 2' is not a 3-D mesh"):
        load_tet_mesh(path)


# ----------------------------------------------------------------------------- 4 sizes
def test_millimetre_surface_stopped_by_estimate(tmp_path, _no_tetgen):
    V, F = _sphere(scale=1e6)  # a unit sphere in micrometres with an absolute edge length 0.4
    with pytest.raises(MeshError, match=r"mesh too large: about [\d,]+ tets estimated .* above the limit "
                                        r"max_tets=5,000,000; .*raise the limit with max_tets"):
        load_mesh(_write_obj(tmp_path / "um.obj", V, F), edge_length=0.4)


def test_builtin_ball_stopped_before_building():
    with pytest.raises(MeshError, match=r"about [\d,]+ tets estimated \(ball of volume 4\.189 with edge_length "
                                        r"0\.001\), above the limit max_tets=5,000,000"):
        ball(edge_length=0.001)


def test_max_tets_is_configurable(_no_tetgen):
    V, F = _sphere()
    with pytest.raises(MeshError, match=r"above the limit max_tets=100;"):
        tetrahedralize(V, F, edge_length=0.2, max_tets=100)
    with pytest.raises(MeshError, match=r"max_tets must be a positive integer or None"):
        tetrahedralize(V, F, max_tets=0)


def test_tiny_model_warns():
    V, F = _sphere(scale=1e-6)
    with pytest.warns(UserWarning, match=r"coarser than the model \(bounding-box diagonal 3\.\d+e-06\).*"
                                         r"Sizes are absolute"):
        m = tetrahedralize(V, F, edge_length=0.4)
    assert m.n_tets > 0


@pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), "abc"])
def test_bad_edge_length_named(bad, _no_tetgen):
    V, F = _sphere()
    with pytest.raises(MeshError, match=rf"edge_length must be a positive finite number .*got {bad!r}"):
        tetrahedralize(V, F, edge_length=bad)


def test_bad_sizes_of_builtins_and_max_volume(_no_tetgen):
    V, F = _sphere()
    with pytest.raises(MeshError, match=r"max_volume must be a positive finite number .*got -2"):
        tetrahedralize(V, F, max_volume=-2)
    with pytest.raises(MeshError, match=r"edge_length must be a positive finite number .*got 0"):
        ball(edge_length=0)
    with pytest.raises(MeshError, match=r"edge_length must be a positive finite number .*got nan"):
        cylinder(edge_length=float("nan"))
    with pytest.raises(MeshError, match=r"quality must be a finite number >= 1.*got 0\.5"):
        tetrahedralize(V, F, quality=0.5)


def test_default_size_is_relative_to_the_model():
    V, F = _sphere()
    a = tetrahedralize(V, F)
    b = tetrahedralize(V * 1024.0, F)  # a power of two scales every float exactly
    assert a.n_tets == b.n_tets and a.n_tets > 200
    torch.testing.assert_close(b.vertices, a.vertices * 1024.0, rtol=0, atol=0)
    L = builtin.DEFAULT_EDGE_FRACTION * float(np.linalg.norm(np.ptp(V, axis=0)))
    est = builtin.estimate_tets(abs(float(builtin.CellComplex(V, F).enclosed_volume())),
                                builtin._regular_tet_volume(L), len(F))
    assert est / 2 <= a.n_tets <= 2 * est  # the estimate is right within a factor 2


# ----------------------------------------------------------------------------- 9 non-manifold vertices
OCTA_V = np.array([[0.0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])


def test_tets_sharing_one_vertex():
    T = np.array([[0, 1, 3, 5], [0, 2, 4, 6]])
    with pytest.raises(MeshError, match=r"non-manifold vertices .*vertex indices \[0\] \(count 1\); e\.g\. vertex 0: "
                                        r"its 2 tets \[0, 1\] .*form 2 groups.*own copy of the vertex"):
        TetMesh(OCTA_V, T, reorient=True, unreferenced="drop")


def test_tets_sharing_one_edge():
    T = np.array([[0, 1, 3, 5], [0, 1, 4, 6]])
    with pytest.raises(MeshError, match=r"non-manifold vertices .*vertex indices \[0, 1\] \(count 2\)"):
        TetMesh(OCTA_V, T, reorient=True, unreferenced="drop")


def test_vertex_link_annulus():
    # the 8 octants around vertex 0 without two opposite ones: a connected star whose link is an
    # annulus (Euler characteristic 0), not a disc
    octants = [[0, x, y, z] for x in (1, 2) for y in (3, 4) for z in (5, 6)]
    T = np.array([t for t in octants if t[1:] not in ([1, 3, 5], [2, 4, 6])])
    with pytest.raises(MeshError, match=r"non-manifold vertices .*\[0\] .*link has Euler characteristic 0, not 1"):
        TetMesh(OCTA_V, T, reorient=True)
    assert TetMesh(OCTA_V, np.array(octants), reorient=True).n_tets == 8  # the full star is a ball


def test_non_manifold_file_names_vertex(tmp_path):
    path = _write_medit(tmp_path / "pinch.mesh", OCTA_V, [[0, 1, 3, 5], [0, 2, 6, 4]])
    with pytest.raises(MeshError, match=r"non-manifold vertices .*\[0\]"):
        load_tet_mesh(path)


def _cracked_box(keep=(), mixed=()):
    """box(2) cut along its middle plane z = 0.5: the tets above use copies of the plane's 9
    vertices (vertex 27 + k copies the k-th copied plane vertex, in index order), except the
    vertices in ``keep`` (not copied: shared by both sides) and, for the top tets with x < 0.5,
    those in ``mixed`` (so both copies of them are used above). Vertex 13 is the plane's centre
    (0.5, 0.5, 0.5)."""
    m = builtin.box(2)
    V, T = m.vertices.numpy(), m.tets.numpy()
    plane = np.array([i for i in np.nonzero(V[:, 2] == 0.5)[0] if i not in keep])
    copy = np.arange(V.shape[0])
    copy[plane] = V.shape[0] + np.arange(plane.size)
    top = (V[T][:, :, 2] >= 0.5).all(axis=1)
    left = V[T].mean(axis=1)[:, 0] < 0.5
    Tc = T.copy()
    for i in plane:
        swap = (T == i) & top[:, None] & ~(left[:, None] & (i in mixed))
        Tc[swap] = copy[i]
    return m, np.vstack([V, V[plane]]), Tc


def test_crack_of_duplicated_vertices_names_the_duplicate():
    """Above the centre both of its copies are used: the centre is non-manifold and is named as a
    duplicated vertex, with its coordinates, its copy and the merge as the remedy."""
    box, V, T = _cracked_box(mixed=(13,))
    with pytest.raises(MeshError, match=r"non-manifold vertices .* e\.g\. vertex 13: .*form 2 groups.*\. Vertex 13 is a "
                                        r"duplicated vertex: vertex 31 has the same coordinates \(0\.5, 0\.5, 0\.5\) "
                                        r"\(2 of the 4 non-manifold vertices have coincident copies, 18 vertices of the "
                                        r"mesh in all\): the mesh is cut along a crack of duplicated vertices; merge the "
                                        r"coincident vertices: .*merge_duplicates=True.*merge_duplicate_vertices"):
        TetMesh(V, T)
    # the remedy named in the message: the merged mesh is the box again
    merged, pairs = merge_duplicate_vertices(V, T)
    assert pairs.tolist() == [[27 + k, int(i)] for k, i in enumerate(np.nonzero(V[:27, 2] == 0.5)[0])]
    m = TetMesh(V, merged, unreferenced="drop")
    assert torch.equal(m.tets, box.tets) and torch.equal(m.vertices, box.vertices)


def test_crack_pinched_at_a_shared_vertex_names_the_duplicates(tmp_path):
    """The crack covers the whole plane except its centre: the two halves meet only there; the
    centre is not itself duplicated, so the message names a duplicated vertex of its tets; the
    loader with merge_duplicates=False says the same, by default it merges and the box is valid."""
    box, V, T = _cracked_box(keep=(13,))
    match = (r"non-manifold vertices .*vertex indices \[13\] \(count 1\).*form 2 groups.*\. Its tets have duplicated "
             r"vertices: vertex 1 at \(0, 0, 0\.5\) has the same coordinates as vertex 27 .*16 of the mesh in all.*"
             r"crack of duplicated vertices that leaves vertex 13 shared; merge the coincident vertices")
    with pytest.raises(MeshError, match=match):
        TetMesh(V, T, unreferenced="drop")
    path = _write_medit(tmp_path / "crack.mesh", V, T)
    with pytest.raises(MeshError, match=match):
        load_tet_mesh(path, merge_duplicates=False)
    with pytest.warns(UserWarning, match=r"crack\.mesh: merged 8 duplicate vertices"):
        m = load_tet_mesh(path)
    assert torch.equal(m.tets, box.tets) and m.n_boundary_faces == box.n_boundary_faces


# ----------------------------------------------------------------------------- weak cases
def test_duplicate_vertex_merged_with_count(tmp_path):
    V = np.vstack([TWO_V, TWO_V[[3]]])  # vertex 5 repeats vertex 3; the second tet uses the copy
    T = np.array([[0, 1, 2, 3], [4, 5, 2, 1]])
    path = _write_medit(tmp_path / "dup.mesh", V, T)
    with pytest.warns(UserWarning, match=r"dup\.mesh: merged 1 duplicate vertices .*vertex 5 into vertex 3"):
        m = load_tet_mesh(path)
    assert m.n_vertices == 5 and m.n_boundary_faces == 6  # no internal boundary left
    assert m.kept_vertices.tolist() == [0, 1, 2, 3, 4]
    # kept, the copy cuts the two tets apart along the edge (1, 2): named as non-manifold
    with pytest.raises(MeshError, match=r"non-manifold vertices .*\[1, 2\] \(count 2\)"):
        load_tet_mesh(path, merge_duplicates=False)


def test_unused_vertex_dropped_with_count(tmp_path):
    V = np.vstack([[[9.0, 9, 9]], TWO_V, [[7.0, 7, 7]]])
    path = _write_medit(tmp_path / "unused.mesh", V, TWO_T + 1)
    with pytest.warns(UserWarning, match=r"unused\.mesh: dropped 2 vertices used by no tet: indices \[0, 6\]"):
        m = load_tet_mesh(path)
    assert m.n_vertices == 5 and m.kept_vertices.tolist() == [1, 2, 3, 4, 5]
    with pytest.warns(UserWarning, match=r"2 unreferenced vertices"):
        assert load_tet_mesh(path, unreferenced="warn").n_vertices == 7


@pytest.mark.parametrize("scale, word", [(1e20, "overflow"), (1e-20, "underflow")])
def test_float32_out_of_range_named(tmp_path, scale, word):
    with pytest.raises(MeshError, match=rf"tet volumes {word} in torch\.float32 .*tet indices \[0, 1\].*"
                                        r"pass dtype=torch\.float64"):
        load_tet_mesh(_write_medit(tmp_path / "big.mesh", TWO_V * scale, TWO_T), dtype=torch.float32)
    m = load_tet_mesh(tmp_path / "big.mesh")  # float64 holds it
    assert (m.signed_volumes() > 0).all()


def test_empty_obj(tmp_path):
    (tmp_path / "empty.obj").write_text("\n")
    with pytest.raises(MeshError, match=r"empty surface: no faces in .*empty\.obj \(the file is empty\)"):
        load_surface(tmp_path / "empty.obj")


def test_obj_without_faces(tmp_path):
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match=r"empty surface: no faces in .*points\.obj \(3 vertices\)"):
        load_mesh(tmp_path / "points.obj", edge_length=0.1)


# ----------------------------------------------------------------------------- tetgen crashes
def _unit_cube_surface():
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return V, F


@pytest.mark.skipif(sys.platform == "win32", reason="tetgen runs in a forked child only where fork exists")
def test_tetgen_segfault_becomes_a_mesh_error(monkeypatch):
    """tetgen segfaults on some valid surfaces (e.g. cylinder(edge_length=0.2)); it runs in a forked
    child, so the caller gets a MeshError instead of losing its interpreter."""
    import os
    import signal

    import igl.copyleft.tetgen as tg

    monkeypatch.setattr(tg, "tetrahedralize", lambda *a, **k: os.kill(os.getpid(), signal.SIGSEGV))
    V, F = _unit_cube_surface()
    with pytest.raises(MeshError, match=r"tetgen crashed \(signal 11\).*8 vertices / 12 triangles"):
        builtin.tetrahedralize(V, F, edge_length=0.5)


def test_tetgen_in_a_child_gives_the_same_mesh_as_in_process():
    import igl.copyleft.tetgen as tg

    V, F = _unit_cube_surface()
    m = builtin.tetrahedralize(V, F, edge_length=0.5)
    a = 0.5**3 / (6 * math.sqrt(2))
    TV, TT = tg.tetrahedralize(V, F.astype(np.int64), flags=f"pq1.414a{a:.9g}Q")[:2]
    assert m.n_vertices == TV.shape[0] and m.n_tets == TT.shape[0]
    assert torch.equal(m.vertices, torch.as_tensor(TV, dtype=m.vertices.dtype))
