"""Several meshes in one batch (torchconn.mesh.batch): the disjoint union against separate calls.

Invariants mirrored here (TetMeshBatch docstring):

* the union's buffers equal those of a TetMesh built from scratch on the concatenated vertices
  and offset tets (the canonical edge/face orders hold in the union);
* split undoes the concatenation: piece k of every buffer, minus the offsets, is mesh k's;
* every module on the union gives, split per mesh, the values and gradients of separate calls
  (with leading batch dims of connections, frames, compiled kernels on and off);
* the frame-field loss on the union is the element-count-weighted mean of the per-mesh terms;
* CAD tags are carried, offset; a mix of tagged and untagged meshes is refused.

Cost: three meshes of 27, 24 and 67 vertices; the whole file runs in a few seconds.
"""
from __future__ import annotations

import pytest
import torch

import torchconn as tc
from torchconn import so3
from torchconn.dec import curvature
from torchconn.frames import octahedral
from torchconn.frames.loss import TERMS, FrameFieldLoss
from torchconn.mesh.batch import ELEMENT_KINDS
from torchconn.mesh.cad import cad_tags_from_elements
from torchconn.ops import compiled


@pytest.fixture(scope="module")
def meshes():
    """Three different meshes: a grid box, a shifted 2x1x1 box and a coarse tetgen ball."""
    return [tc.io.box(2), tc.io.box((2, 1, 1), size=(2.0, 1.0, 1.0), origin=(3.0, 0.0, 0.0)),
            tc.io.ball(edge_length=0.6)]


@pytest.fixture(scope="module")
def union(meshes):
    return tc.join_meshes(meshes)


def _params(meshes, gen, batch=()):
    """Per-mesh skew parameters ``(*batch, E_k, 3)`` and their union (cat on the edge dim)."""
    parts = [0.4 * torch.randn(*batch, m.n_edges, 3, generator=gen, dtype=torch.float64) for m in meshes]
    return parts, torch.cat(parts, dim=-2)


def _frames(meshes, gen, batch=()):
    parts = [so3.exp(torch.randn(*batch, m.n_vertices, 3, generator=gen, dtype=torch.float64)) for m in meshes]
    return parts, torch.cat(parts, dim=-3)


# ----------------------------------------------------------------------------- structure
def test_union_equals_the_mesh_built_from_scratch(meshes, union):
    off = [0]
    for m in meshes:
        off.append(off[-1] + m.n_vertices)
    ref = tc.TetMesh(torch.cat([m.vertices for m in meshes]), torch.cat([m.tets + o for m, o in zip(meshes, off)]))
    assert isinstance(union, tc.TetMesh) and union.n_meshes == 3
    for name, t in ref.buffers().items():
        got = getattr(union, name)
        assert got.dtype == t.dtype and got.shape == t.shape, name
        if t.is_floating_point():
            torch.testing.assert_close(got, t, rtol=0, atol=1e-15, msg=name)
        else:
            assert torch.equal(got, t), name
    assert union.offsets("vertex") == tuple(off)
    assert union.euler_characteristic() == sum(m.euler_characteristic() for m in meshes)


def test_split_undoes_the_join(meshes, union):
    """Piece k of each buffer, minus the offsets of the kind it indexes, is mesh k's buffer."""
    index_kind = {"tets": "vertex", "edges": "vertex", "faces": "vertex", "boundary_faces": "vertex",
                  "boundary_vertices": "vertex", "tet_edges": "edge", "face_edges": "edge", "tet_faces": "face",
                  "boundary_face_index": "face", "face_tets": "tet"}
    rows = {"tets": "tet", "edges": "edge", "faces": "face", "tet_edges": "tet", "tet_edge_signs": "tet",
            "tet_faces": "tet", "tet_face_signs": "tet", "face_edges": "face", "face_edge_signs": "face",
            "face_tets": "face", "boundary_faces": "boundary_face", "boundary_face_index": "boundary_face",
            "boundary_vertices": "boundary_vertex", "vertices": "vertex", "boundary_vertex_normals": "boundary_vertex",
            "edge_barycenters": "edge", "face_barycenters": "face", "tet_barycenters": "tet"}
    for name, kind in rows.items():
        pieces = union.split(getattr(union, name), kind, dim=0)
        for k, (m, p) in enumerate(zip(meshes, pieces)):
            if name in index_kind:
                o = union.offsets(index_kind[name])[k]
                p = torch.where(p >= 0, p - o, p)
            assert torch.equal(p, getattr(m, name)), (name, k)
    for kind, buf in ELEMENT_KINDS.items():
        assert union.counts(kind) == tuple(getattr(m, buf).shape[0] for m in meshes)
        idx = union.mesh_index(kind)
        assert idx.shape == (union.offsets(kind)[-1],)
        assert torch.equal(torch.bincount(idx, minlength=3), torch.tensor(union.counts(kind)))


def test_split_finds_the_element_dim_with_batch_dims(union):
    F = union.n_faces
    x = torch.randn(2, 5, F, 3, 3, dtype=torch.float64)
    pieces = union.split(x, "face")
    assert [p.shape for p in pieces] == [(2, 5, c, 3, 3) for c in union.counts("face")]
    assert torch.equal(torch.cat(pieces, dim=2), x)
    assert union.split(x, "face", dim=-3)[1].shape == (2, 5, union.counts("face")[1], 3, 3)
    with pytest.raises(ValueError, match="pass dim="):
        union.split(torch.zeros(F, F), "face")
    with pytest.raises(ValueError, match="size"):
        union.split(torch.zeros(3, 3), "tet")
    with pytest.raises(ValueError, match="dim 0"):
        union.split(x, "face", dim=0)
    with pytest.raises(KeyError, match="unknown element kind"):
        union.split(x, "cell")


def test_join_refuses_bad_input(meshes):
    with pytest.raises(ValueError, match="at least one"):
        tc.join_meshes([])
    with pytest.raises(TypeError, match="single TetMesh"):
        tc.join_meshes(meshes[0])
    with pytest.raises(TypeError, match=r"meshes\[1\] is a CellComplex"):
        tc.join_meshes([meshes[0], meshes[0].boundary_complex()])
    with pytest.raises(tc.MeshError, match=r"meshes\[1\] has dtype torch.float32"):
        tc.join_meshes([meshes[0], meshes[1].to(dtype=torch.float32)])
    with pytest.raises(tc.MeshError, match=r"meshes\[2\] is on meta"):
        tc.join_meshes([meshes[0], meshes[1], meshes[2].to("meta")])


def test_union_moves_with_its_offsets(meshes, union):
    u32 = union.to(dtype=torch.float32)
    assert isinstance(u32, tc.TetMeshBatch) and u32.dtype == torch.float32
    assert u32.offsets("edge") == union.offsets("edge")
    meta = tc.join_meshes([m.to("meta") for m in meshes])
    assert meta.device.type == "meta" and meta.tets.shape == union.tets.shape
    assert not isinstance(union.subdivide(), tc.TetMeshBatch)


# ----------------------------------------------------------------------------- modules
MODULES = [
    ("curvature_two_prong", lambda m: tc.Curvature(m), "face", False),
    ("curvature_holonomy", lambda m: tc.Curvature(m, kind="holonomy"), "face", False),
    ("torsion_sqrt", lambda m: tc.Torsion(m), "face", True),
    ("torsion_naive", lambda m: tc.Torsion(m, kind="naive"), "face", True),
    ("averaged_covariant_d", lambda m: tc.AveragedCovariantD(m), "tet", True),
    ("covariant_d_behs21", lambda m: tc.CovariantD(m, "behs21"), "tet", True),
    ("covariant_d_wedge", lambda m: tc.CovariantD(m, "wedge"), "tet", True),
]


@pytest.mark.parametrize("native", [True, False], ids=["compiled", "torch"])
@pytest.mark.parametrize("name,make,kind,takes_frames", MODULES, ids=[m[0] for m in MODULES])
def test_module_on_union_equals_separate_calls(meshes, union, gen, name, make, kind, takes_frames, native):
    """Values and gradients (w.r.t. the skew parameters and the frames), with batch dims (2,)."""
    parts, joined = _params(meshes, gen, batch=(2,))
    fparts, fjoined = _frames(meshes, gen, batch=(2,)) if takes_frames else ([None] * 3, None)

    def run(mesh, params, frames):
        field = tc.ConnectionField(mesh.edges, mesh.n_vertices, init=params)  # a module feeding a module
        frames = frames.clone().requires_grad_() if frames is not None else None
        out = make(mesh)(field, *((frames,) if takes_frames else ()))
        weight = torch.linspace(-1.0, 2.0, out.numel(), dtype=out.dtype).reshape(out.shape)
        return out, field.params, frames, weight

    with compiled(native):
        out_u, p_u, f_u, _ = run(union, joined, fjoined)
        seps = [run(m, p, f) for m, p, f in zip(meshes, parts, fparts)]
        # the same per-element weights on both sides: the union's are the separate ones, joined
        # along the element dim (dim 1, after the batch dim)
        w_u = torch.cat([w for *_, w in seps], dim=1)
        (out_u * w_u).sum().backward()
        for out, p, f, w in seps:
            (out * w).sum().backward()
    for k, piece in enumerate(union.split(out_u, kind, dim=1)):
        torch.testing.assert_close(piece, seps[k][0], rtol=1e-12, atol=1e-13, msg=f"{name} values, mesh {k}")
    for k, g in enumerate(union.split(p_u.grad, "edge", dim=1)):
        torch.testing.assert_close(g, seps[k][1].grad, rtol=1e-12, atol=1e-13, msg=f"{name} grad params, mesh {k}")
    if takes_frames:
        for k, g in enumerate(union.split(f_u.grad, "vertex", dim=1)):
            torch.testing.assert_close(g, seps[k][2].grad, rtol=1e-12, atol=1e-13, msg=f"{name} grad frames, mesh {k}")


def test_bianchi_check_on_union_is_the_max_over_meshes(meshes, union, gen):
    parts, joined = _params(meshes, gen)
    fparts, fjoined = _frames(meshes, gen)
    res_u = tc.BianchiCheck(union)(so3.exp(joined), fjoined)
    res = [tc.BianchiCheck(m)(so3.exp(p), f) for m, p, f in zip(meshes, parts, fparts)]
    for key in ("differential", "algebraic"):
        assert res_u[key] == pytest.approx(max(r[key] for r in res), rel=0, abs=1e-15)


def test_connection_field_on_union(meshes, union, gen):
    parts, joined = _params(meshes, gen)
    field = tc.ConnectionField(union.edges, union.n_vertices, init=joined)
    for k, R in enumerate(union.split(field().edge_rot, "edge")):
        sep = tc.ConnectionField(meshes[k].edges, meshes[k].n_vertices, init=parts[k])
        torch.testing.assert_close(R, sep().edge_rot, rtol=0, atol=1e-15)
    # transports along an edge of mesh 1, in the union's vertex numbering
    i, j = (int(x) for x in meshes[1].edges[3])
    o = union.offsets("vertex")[1]
    sep = tc.ConnectionField(meshes[1].edges, meshes[1].n_vertices, init=parts[1])()
    torch.testing.assert_close(field().transport(i + o, j + o), sep.transport(i, j), rtol=0, atol=1e-15)


# ----------------------------------------------------------------------------- frame-field loss
@pytest.mark.parametrize("native", [True, False], ids=["compiled", "torch"])
def test_frame_field_loss_on_union_is_the_count_weighted_mean(meshes, union, gen, native):
    """Each term on the union is sum_k n_k term_k / sum_k n_k with n_k the elements that term
    averages over on mesh k (edges, faces -- the torsion too, through the matchings --, regular
    tets, aligned vertices, feature pairs); so are the gradients, term by term."""
    weights = {t: 1.0 for t in TERMS}
    parts, joined = _params(meshes, gen)
    fparts, fjoined = _frames(meshes, gen)

    def terms(mesh, params, frames):
        params, frames = params.clone().requires_grad_(), frames.clone().requires_grad_()
        loss = FrameFieldLoss(mesh, weights)
        out = loss(so3.exp(params), frames)
        hol = curvature.face_curvature(so3.exp(params).detach(), mesh, kind="holonomy")
        idx, _ = octahedral.closest_element(hol + torch.eye(3, dtype=hol.dtype))
        regular = int((idx == 0)[mesh.tet_faces].all(-1).sum())  # tets whose four faces are unsingular
        n = {"smooth": mesh.n_edges, "tie": mesh.n_edges, "dirichlet": mesh.n_edges, "flat": mesh.n_faces,
             "torsion": mesh.n_faces, "dnabla": regular, "align": loss.align_vertices.numel(),
             "feature": loss.feature_vertices_rep.numel()}
        return out, n, params, frames

    with compiled(native):
        out_u, n_u, p_u, f_u = terms(union, joined, fjoined)
        seps = [terms(m, p, f) for m, p, f in zip(meshes, parts, fparts)]
    assert all(n > 0 for n in n_u.values()), n_u  # every term is exercised (the boxes have feature edges)
    for t in TERMS:
        assert n_u[t] == sum(s[1][t] for s in seps), t
        expect = sum(s[1][t] * s[0][t] for s in seps) / n_u[t]
        torch.testing.assert_close(out_u[t], expect, rtol=1e-12, atol=1e-14, msg=t)
    # gradients of the pooled total: mesh k's part is sum_t w_t n_k,t / N_t * grad term_t,k
    with compiled(native):
        g_p, g_f = torch.autograd.grad(out_u["total"], (p_u, f_u))
        expected = [torch.autograd.grad(sum(out[t] * n[t] / n_u[t] for t in TERMS), (p, f)) for out, n, p, f in seps]
    for k, (e_p, e_f) in enumerate(expected):
        torch.testing.assert_close(union.split(g_p, "edge")[k], e_p, rtol=1e-10, atol=1e-13)
        torch.testing.assert_close(union.split(g_f, "vertex")[k], e_f, rtol=1e-10, atol=1e-13)


# ----------------------------------------------------------------------------- CAD tags
def _face_tags(mesh, base):
    """Surface tag ``base + axis`` per boundary face, by its normal's dominant axis (any fixed
    tagging will do: the test checks that the union carries it)."""
    p = mesh.vertices[mesh.boundary_faces]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1)
    return mesh.boundary_faces, base + n.abs().argmax(1)


def test_cad_tags_are_carried_and_offset(meshes):
    tagged = []
    for k, m in enumerate(meshes[:2]):
        m = m.to()  # a copy: tags on the module fixture would leak into other tests
        tri, tags = _face_tags(m, 10 * k)
        lines = m.edges[:3]
        m.cad = cad_tags_from_elements(m, tri, tags, lines, torch.tensor([7, 7, 8]) + k, m.boundary_vertices[:2],
                                       torch.tensor([1, 2]))
        tagged.append(m)
    u = tc.join_meshes(tagged)
    # the reference: the same tagged elements given to the union in its numbering
    vo, eo = u.offsets("vertex"), u.offsets("edge")
    ref = cad_tags_from_elements(
        u, torch.cat([_face_tags(m, 10 * k)[0] + vo[k] for k, m in enumerate(tagged)]),
        torch.cat([_face_tags(m, 10 * k)[1] for k, m in enumerate(tagged)]),
        torch.cat([m.edges[:3] + vo[k] for k, m in enumerate(tagged)]),
        torch.tensor([7, 7, 8, 8, 8, 9]),
        torch.cat([m.boundary_vertices[:2] + vo[k] for k, m in enumerate(tagged)]), torch.tensor([1, 2, 1, 2]))
    for name in ("face_surface", "boundary_face_surface", "feature_edges", "feature_edge_index",
                 "feature_edge_curve", "corner_vertices", "corner_point"):
        assert torch.equal(getattr(u.cad, name), getattr(ref, name)), name
    assert torch.equal(u.cad.feature_edge_index[3:] - eo[1], tagged[1].cad.feature_edge_index)
    with pytest.raises(tc.MeshError, match=r"meshes \[0\] have CAD tags .* meshes \[1\] do not"):
        tc.join_meshes([tagged[0], meshes[1]])
    assert tc.join_meshes(meshes).cad is None
