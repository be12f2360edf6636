"""TetMesh / CellComplex: buffers against slow per-element references, ∂∂ = 0, boundary
orientation, validation errors, subdivision."""
from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchconn.mesh.io import ball, box, load_tet_mesh, torus
from torchconn.mesh import CellComplex, MeshError, TetMesh, tet_mesh_as_cell_complex
from torchconn.mesh.simplex import pair_list

from conftest import data_path

# one regular-ish positively oriented tet and a two-tet mesh sharing face (1,2,3)
TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TWO_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
TWO_T = np.array([[0, 1, 2, 3], [1, 4, 2, 3]])


@pytest.fixture(scope="module")
def small_ball():
    return ball(edge_length=0.4)


@pytest.fixture(scope="module")
def sphere_mesh():
    return load_tet_mesh(data_path("sphere_r0.17.mesh"))


def _perm_sign(seq):
    """Sign of the permutation sorting ``seq`` (slow reference)."""
    s = 1
    seq = list(seq)
    for i in range(len(seq)):
        for j in range(i + 1, len(seq)):
            if seq[i] > seq[j]:
                s = -s
    return s


# ----------------------------------------------------------------------------- buffers
def test_two_tets_basic():
    m = TetMesh(TWO_V, TWO_T)
    assert (m.n_vertices, m.n_edges, m.n_faces, m.n_tets) == (5, 9, 7, 2)
    assert m.euler_characteristic() == 1
    assert m.boundary_euler_characteristic() == 2
    assert (m.signed_volumes() > 0).all()
    assert "V=5" in repr(m) and "T=2" in repr(m)
    shared = m.faces.tolist().index([1, 2, 3])
    assert sorted(m.face_tets[shared].tolist()) == [0, 1]
    assert m.face_adjacency().shape == (1, 2)


@pytest.mark.parametrize("which", ["box", "ball", "sphere_file"])
def test_buffers_against_reference(which, small_ball, sphere_mesh):
    m = {"box": lambda: box(3), "ball": lambda: small_ball, "sphere_file": lambda: sphere_mesh}[which]()
    tets, edges, faces = m.tets.numpy(), m.edges.numpy(), m.faces.numpy()
    # canonical, unique, lexicographically sorted
    assert (edges[:, 0] < edges[:, 1]).all()
    assert len({tuple(e) for e in edges}) == len(edges)
    assert (np.lexsort(edges.T[::-1]) == np.arange(len(edges))).all()
    assert (np.diff(faces, axis=1) > 0).all()
    assert len({tuple(f) for f in faces}) == len(faces)
    assert (np.lexsort(faces.T[::-1]) == np.arange(len(faces))).all()
    te, ts = m.tet_edges.numpy(), m.tet_edge_signs.numpy()
    tf, tfs = m.tet_faces.numpy(), m.tet_face_signs.numpy()
    fe, fes = m.face_edges.numpy(), m.face_edge_signs.numpy()
    # slow per-tet reference
    for t in range(len(tets)):
        for p, (i, j) in enumerate(pair_list(4)):
            a, b = tets[t, i], tets[t, j]
            e = edges[te[t, p]]
            if ts[t, p] == 1:
                assert (e[0], e[1]) == (a, b)
            else:
                assert ts[t, p] == -1 and (e[0], e[1]) == (b, a)
        for k in range(4):
            loc = [tets[t, x] for x in range(4) if x != k]
            assert tuple(faces[tf[t, k]]) == tuple(sorted(loc))
            assert tfs[t, k] == (-1) ** k * _perm_sign(loc)
    for f in range(len(faces)):
        a, b, c = faces[f]
        assert [tuple(edges[e]) for e in fe[f]] == [(b, c), (a, c), (a, b)]
        assert fes[f].tolist() == [1, -1, 1]


def test_boundary_boundary_is_zero(sphere_mesh):
    m = sphere_mesh
    T, F, E = m.n_tets, m.n_faces, m.n_edges
    d3 = sp.coo_matrix((m.tet_face_signs.numpy().ravel(), (m.tet_faces.numpy().ravel(), np.repeat(np.arange(T), 4))),
                       shape=(F, T)).tocsr()
    d2 = sp.coo_matrix((m.face_edge_signs.numpy().ravel(), (m.face_edges.numpy().ravel(), np.repeat(np.arange(F), 3))),
                       shape=(E, F)).tocsr()
    ev = m.edges.numpy()
    d1 = sp.coo_matrix((np.r_[-np.ones(E), np.ones(E)], (np.r_[ev[:, 0], ev[:, 1]], np.r_[np.arange(E), np.arange(E)])),
                       shape=(m.n_vertices, E)).tocsr()
    assert abs(d2 @ d3).sum() == 0
    assert abs(d1 @ d2).sum() == 0
    assert d3.nnz == 4 * T and d2.nnz == 3 * F
    # every interior face in exactly two tets with opposite signs, boundary faces in one
    colsum = np.asarray(d3.sum(axis=1)).ravel()
    count = np.asarray(abs(d3).sum(axis=1)).ravel()
    interior = count == 2
    assert set(np.unique(count)) == {1, 2}
    assert (colsum[interior] == 0).all()
    assert (count == 1).sum() == m.n_boundary_faces
    # the chain sum of all tets is the (outward) boundary
    bidx = m.boundary_face_index.numpy()
    assert set(np.nonzero(colsum)[0]) == set(bidx)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_boundary_outward_on_ball(dtype, small_ball):
    m = small_ball.to(dtype=dtype)
    assert m.vertices.dtype == dtype and m.boundary_vertex_normals.dtype == dtype
    assert m.euler_characteristic() == 1 and m.boundary_euler_characteristic() == 2
    p = m.vertices[m.boundary_faces]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    c = p.mean(1)
    assert ((n * c).sum(-1) > 0).all()  # centred ball: outward means away from the origin
    # divergence theorem: Σ_faces (c · n_area)/3 = volume
    vol_b = (n * c).sum() / 6
    torch.testing.assert_close(vol_b, m.volume(), rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
    nv = m.boundary_vertex_normals
    torch.testing.assert_close(nv.norm(dim=1), torch.ones_like(nv[:, 0]))
    radial = m.vertices[m.boundary_vertices]
    cosang = (nv * radial / radial.norm(dim=1, keepdim=True)).sum(1)
    assert (cosang > 0.9).all()
    # barycenters follow the dtype and are the vertex means
    torch.testing.assert_close(m.tet_barycenters, m.vertices[m.tets].mean(1))
    assert m.face_barycenters.dtype == dtype and m.edge_barycenters.shape == (m.n_edges, 3)


def test_boundary_complex_and_cell_complex(small_ball):
    m = small_ball
    bc = m.boundary_complex()
    assert bc.is_closed() and bc.is_edge_manifold() and bc.is_consistently_oriented()
    assert bc.euler_characteristic() == 2
    torch.testing.assert_close(bc.enclosed_volume(), m.volume())
    cc = tet_mesh_as_cell_complex(m)
    assert torch.equal(cc.edges, m.edges)
    g = cc.face_groups[3]
    assert torch.equal(g.loops, m.faces) and torch.equal(g.face_ids, torch.arange(m.n_faces))
    torch.testing.assert_close(g.loop_edges, m.face_edges[:, [2, 0, 1]])  # ab, bc, ca
    assert (g.loop_signs == torch.tensor([1, 1, -1])).all()
    assert cc.euler_characteristic() == m.euler_characteristic() == 1
    assert torch.equal(cc.cell_faces.reshape(-1, 4), m.tet_faces)


def test_edge_index(small_ball):
    m = small_ball
    e = m.edges
    idx, sign = m.edge_index(e[:, 1], e[:, 0])
    assert torch.equal(idx, torch.arange(m.n_edges)) and (sign == -1).all()
    t = m.tets
    idx, sign = m.edge_index(t[:, 0], t[:, 3])
    assert torch.equal(idx, m.tet_edges[:, 2]) and torch.equal(sign, m.tet_edge_signs[:, 2])
    far = int(torch.argmax(m.vertices[:, 0])), int(torch.argmin(m.vertices[:, 0]))
    with pytest.raises(MeshError, match=rf"not edges of the TetMesh: \[\[{far[0]}, {far[1]}\]\]"):
        m.edge_index(torch.tensor([0, far[0]]), torch.tensor([int(e[0, 1]), far[1]]))
    with pytest.raises(MeshError, match="not edges"):
        m.edge_index(torch.tensor([3]), torch.tensor([3]))


def test_to_keeps_topology(small_ball):
    m32 = small_ball.to(dtype=torch.float32)
    assert m32.tets.dtype == torch.long and torch.equal(m32.tets, small_ball.tets)
    assert small_ball.vertices.dtype == torch.float64  # the original is untouched
    with pytest.raises(TypeError):
        small_ball.to(dtype=torch.int64)


def test_box_counts_and_torus_genus():
    m = box((2, 3, 4), size=(1.0, 2.0, 3.0))
    assert m.n_vertices == 3 * 4 * 5 and m.n_tets == 6 * 24
    assert m.n_boundary_faces == 4 * (6 + 12 + 8)
    assert m.euler_characteristic() == 1 and m.boundary_euler_characteristic() == 2
    torch.testing.assert_close(m.volume(), torch.tensor(6.0, dtype=torch.float64))
    tor = torus()
    assert tor.euler_characteristic() == 0 and tor.boundary_euler_characteristic() == 0


@pytest.mark.parametrize("mesh_fn", [lambda: box(2), lambda: ball(edge_length=0.5)])
def test_subdivide(mesh_fn):
    m = mesh_fn()
    s = m.subdivide()
    assert s.n_tets == 8 * m.n_tets
    assert s.n_vertices == m.n_vertices + m.n_edges
    assert (s.signed_volumes() > 0).all()
    torch.testing.assert_close(s.volume(), m.volume())
    assert s.euler_characteristic() == m.euler_characteristic()
    assert s.n_boundary_faces == 4 * m.n_boundary_faces
    torch.testing.assert_close(s.vertices[m.n_vertices:], m.edge_barycenters)


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "V, T, exc, pattern",
    [
        (TET_V, np.array([[0.0, 1, 2, 3]]), TypeError, "integer dtype"),
        (TET_V, np.array([[0, 1, 2]]), MeshError, r"shape \(T, 4\)"),
        (TET_V[:, :2], np.array([[0, 1, 2, 3]]), MeshError, r"shape \(V, 3\)"),
        (TWO_V, np.array([[0, 1, 2, 3], [1, 4, 2, 5]]), MeshError, r"out of range.*tet indices \[1\]"),
        (TWO_V, np.array([[0, 1, 2, 3], [1, -1, 2, 3]]), MeshError, r"out of range.*\[1\]"),
        (np.where(np.arange(15).reshape(5, 3) == 13, np.nan, TWO_V), TWO_T, MeshError, r"NaN/inf.*\[4\]"),
        (np.where(np.arange(15).reshape(5, 3) == 3, np.inf, TWO_V), TWO_T, MeshError, r"NaN/inf.*\[1\]"),
        (TET_V, np.zeros((0, 4), np.int64), MeshError, "no tets"),
        (np.zeros((0, 3)), np.zeros((0, 4), np.int64), MeshError, "no vertices"),
        (TWO_V, np.array([[0, 1, 2, 3], [1, 4, 2, 2]]), MeshError, r"repeated vertex.*\[1\]"),
        (TWO_V, np.array([[0, 1, 2, 3], [1, 4, 2, 3], [0, 1, 3, 2]]), MeshError, r"duplicate tets.*\[0, 2\]"),
        (TWO_V, np.array([[0, 1, 2, 3], [1, 4, 3, 2]]), MeshError, r"inverted.*\[1\]"),
    ],
)
def test_bad_input(V, T, exc, pattern):
    with pytest.raises(exc, match=pattern):
        TetMesh(V, T)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_volume_tet(dtype):
    V = np.vstack([TET_V, [[0.3, 0.3, 0.0]]])  # vertex 4 in the plane of face (0, 1, 2)
    with pytest.raises(MeshError, match=r"zero-volume.*\[1\]"):
        TetMesh(V, np.array([[0, 1, 2, 3], [0, 1, 2, 4]]), dtype=dtype)
    # a thin but honest tet is accepted
    V[4, 2] = -1e-3
    m = TetMesh(V, np.array([[0, 1, 2, 3], [0, 2, 1, 4]]), dtype=dtype)
    assert (m.signed_volumes() > 0).all()


def test_non_manifold_and_overlap():
    V = np.vstack([TWO_V, [[1.0, 1.0, 1.2]]])
    with pytest.raises(MeshError, match=r"more than two tets.*\(1, 2, 3\)"):
        TetMesh(V, np.array([[0, 1, 2, 3], [1, 4, 2, 3], [1, 5, 2, 3]]))
    V2 = np.vstack([TET_V, [[-0.1, -0.1, -0.1]]])  # tet 1 lies on the same side of (1,2,3) as tet 0
    with pytest.raises(MeshError, match=r"overlapping.*\(1, 2, 3\).*tets \[0, 1\]"):
        TetMesh(V2, np.array([[0, 1, 2, 3], [4, 1, 2, 3]]))


def test_reorient_fixes_inverted():
    bad = np.array([[0, 1, 2, 3], [1, 4, 3, 2]])
    m = TetMesh(TWO_V, bad, reorient=True)
    assert (m.signed_volumes() > 0).all()
    assert torch.equal(m.tets[0], torch.tensor([0, 1, 2, 3]))
    assert sorted(m.tets[1].tolist()) == [1, 2, 3, 4]
    ref = TetMesh(TWO_V, TWO_T)
    assert torch.equal(m.faces, ref.faces) and torch.equal(m.boundary_faces.sort(1).values.sort(0).values,
                                                            ref.boundary_faces.sort(1).values.sort(0).values)


def test_unreferenced_vertices():
    V = np.vstack([[[9.0, 9, 9]], TWO_V])  # vertex 0 unused
    T = TWO_T + 1
    with pytest.warns(UserWarning, match=r"1 unreferenced vertices.*\[0\]"):
        m = TetMesh(V, T)
    assert m.n_vertices == 6 and m.boundary_vertices.numel() == 5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = TetMesh(V, T, unreferenced="drop")
    assert d.n_vertices == 5 and torch.equal(d.tets, torch.as_tensor(TWO_T))
    assert torch.equal(d.kept_vertices, torch.arange(1, 6))
    with pytest.raises(MeshError, match=r"unreferenced.*\[0\]"):
        TetMesh(V, T, unreferenced="error")


# ----------------------------------------------------------------------------- CellComplex
def test_cell_complex_polygons():
    # a cube as 6 outward quads
    V = np.array(list(itertools.product([0.0, 1.0], repeat=3)))  # index = 4x + 2y + z
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    cc = CellComplex(V, quads, cells=[[(f, 1) for f in range(6)]])
    assert cc.n_faces == 6 and cc.n_edges == 12 and list(cc.face_groups) == [4]
    assert cc.euler_characteristic() == 8 - 12 + 6 - 1
    assert cc.is_closed() and cc.is_edge_manifold() and cc.is_consistently_oriented()
    torch.testing.assert_close(cc.enclosed_volume(), torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(cc.face_areas(), torch.ones(6, dtype=torch.float64))
    n = cc.face_normals()
    c = cc.face_barycenters() - 0.5
    assert ((n * c).sum(1) > 0).all()
    g = cc.face_groups[4]
    ed = cc.edges.numpy()
    for f in range(6):
        for k in range(4):
            a, b = g.loops[f, k].item(), g.loops[f, (k + 1) % 4].item()
            e = ed[g.loop_edges[f, k]]
            assert (tuple(e) == (a, b)) if g.loop_signs[f, k] == 1 else (tuple(e) == (b, a))
    pairs, shared = cc.face_adjacency()
    assert pairs.shape == (12, 2) and sorted(shared.tolist()) == list(range(12))
    # mixed sizes: split one quad into two triangles
    mixed = CellComplex(V, quads[1:] + [[0, 1, 3], [0, 3, 2]])
    assert sorted(mixed.face_groups) == [3, 4] and mixed.n_faces == 7
    assert mixed.face_groups[3].face_ids.tolist() == [5, 6]
    assert mixed.is_closed() and mixed.euler_characteristic() == 2
    # open surface and flipped face
    open_cc = CellComplex(V, quads[1:])
    assert not open_cc.is_closed() and open_cc.boundary_edges().numel() == 4
    with pytest.raises(MeshError, match="not closed: 4 boundary edges"):
        open_cc.enclosed_volume()
    flipped = CellComplex(V, quads[:5] + [quads[5][::-1]])
    assert not flipped.is_consistently_oriented()
    with pytest.raises(MeshError, match="not consistently oriented: 4 edges"):
        flipped.check_closed_manifold()


def test_cell_complex_validation():
    V = TET_V
    with pytest.raises(MeshError, match=r"repeated vertex.*\[1\]"):
        CellComplex(V, [[0, 1, 2], [0, 1, 1]])
    with pytest.raises(MeshError, match=r"out of range.*\[1\]"):
        CellComplex(V, [[0, 1, 2], [0, 1, 7]])
    with pytest.raises(MeshError, match=r"NaN/inf.*\[3\]"):
        CellComplex(np.where(np.arange(12).reshape(4, 3) == 10, np.nan, V), [[0, 1, 2]])
    with pytest.raises(MeshError, match="fewer than 3"):
        CellComplex(V, [[0, 1]])
    with pytest.raises(TypeError):
        CellComplex(V, np.array([[0.0, 1, 2]]))
    with pytest.raises(MeshError, match=r"face ids out of range.*\[0\]"):
        CellComplex(V, [[0, 1, 2]], cells=[[(3, 1)]])
    # an edge in three faces is reported, not rejected
    fan = CellComplex(np.vstack([V, [[1.0, 1, 0]]]), [[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    assert not fan.is_edge_manifold() and fan.nonmanifold_edges().tolist() == [0]
    with pytest.raises(MeshError, match=r"not closed|not edge-manifold"):
        fan.check_closed_manifold()
    idx, sign = fan.edge_index([1], [0])
    assert idx.tolist() == [0] and sign.tolist() == [-1]


def test_tensor_inputs_and_dtype():
    v32 = torch.as_tensor(TWO_V, dtype=torch.float32)
    t32 = torch.as_tensor(TWO_T, dtype=torch.int32)
    m = TetMesh(v32, t32)
    assert m.vertices.dtype == torch.float32 and m.tets.dtype == torch.long
    m64 = TetMesh(v32, t32, dtype=torch.float64, device="cpu")
    assert m64.vertices.dtype == torch.float64 and m64.device == torch.device("cpu")
    assert torch.equal(m64.tet_faces, m.tet_faces)
    with pytest.raises(TypeError, match="integer dtype"):
        TetMesh(v32, t32.float())
    with pytest.raises(TypeError, match="floating"):
        TetMesh(v32, t32, dtype=torch.int64)
    with pytest.raises(ValueError, match="unreferenced"):
        TetMesh(v32, t32, unreferenced="ignore")


def test_subdivide_keeps_shape_quality_bounded():
    """Shortest-diagonal red refinement: the worst tet quality does not decay with the level."""
    from torchconn import io

    def min_quality(m):
        p = m.vertices[m.tets]
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        lrms = torch.stack([(p[:, i] - p[:, j]).norm(dim=-1) for i, j in pairs], 1).square().mean(1).sqrt()
        return float((6 * 2**0.5 * m.signed_volumes() / lrms**3).min())  # 1 for a regular tet

    m0 = io.ball(edge_length=0.7)
    m2 = m0.subdivide().subdivide()
    assert m2.n_tets == 64 * m0.n_tets
    assert min_quality(m2) >= 0.9 * min_quality(m0)
    torch.testing.assert_close(m2.volume(), m0.volume())
