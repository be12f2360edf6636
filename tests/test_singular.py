"""The singular graph (torchconn.frames.singular) and the integrability measure on hand-built fields.

The fields turn about the z-axis as one goes around it: ``F(x) = R_u(phi(x) / d)`` with ``phi``
the angle of ``x`` around the z-axis (the branch cut of ``atan2`` is a jump by an element of O,
which the matching absorbs). The mesh is a layered prism mesh of a disk whose central triangle
contains the axis, so the axis pierces one face per horizontal level and the inner faces of the
three tets of each central prism, and every edge subtends less than 180° around the axis.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import data_path

from torchconn import io, so3
from torchconn.frames import octahedral
from torchconn.frames.field_files import read_singular_curves_vtk, write_singular_curves_vtk
from torchconn.frames.metrics import METRIC_KEYS, face_closure, frame_metrics
from torchconn.frames.singular import (
    CURVE_TYPES,
    FACE_TYPES,
    classify_holonomy,
    singular_graph,
)
from torchconn.mesh import TetMesh


def _prism_mesh(n_layers=6, height=1.0, dtype=torch.float64):
    """Disk of 3 rings (3, 6, 18 points, rotated generically) extruded in ``n_layers`` layers;
    each prism split into 3 tets by global vertex order (conforming)."""
    from scipy.spatial import Delaunay

    pts = []
    for r, k in ((1, 3), (2, 6), (3, 18)):
        th = 2 * np.pi * np.arange(k) / k + 0.37 * r
        pts += [[0.3 * r * np.cos(t), 0.3 * r * np.sin(t)] for t in th]
    P2 = np.array(pts)
    tri = np.sort(Delaunay(P2).simplices, axis=1)
    n = len(P2)
    P = np.concatenate([np.c_[P2, np.full(n, z)] for z in np.linspace(0, height, n_layers + 1)])
    tets = []
    for layer in range(n_layers):
        a, b, c = tri.T + layer * n
        tets += [np.c_[a, b, c, c + n], np.c_[a, b, b + n, c + n], np.c_[a, a + n, b + n, c + n]]
    return TetMesh(torch.tensor(P, dtype=dtype), torch.tensor(np.concatenate(tets)), reorient=True)


def _turning_field(mesh, axis, turns):
    """``R_axis(phi / turns)`` at every vertex, ``phi`` the angle around the z-axis."""
    v = mesh.vertices
    phi = torch.atan2(v[:, 1], v[:, 0])
    u = torch.tensor(axis, dtype=v.dtype)
    return so3.exp((phi / turns)[:, None] * (u / u.norm()))


def _pierced_faces(mesh):
    """Faces whose xy-projection contains the origin (the z-axis passes through them)."""
    p = mesh.vertices[mesh.faces][..., :2]  # (F, 3, 2)
    cr = lambda a, b: a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]  # noqa: E731
    s = torch.stack([cr(p[:, k], p[:, (k + 1) % 3]) for k in range(3)], 1)  # origin vs edge k
    return torch.nonzero((s > 0).all(1) | (s < 0).all(1)).squeeze(1)


def test_classify_holonomy_over_the_group():
    G = octahedral.group(torch.float64)
    typ, axis, w = classify_holonomy(G)
    counts = [int((typ == c).sum()) for c in range(len(FACE_TYPES))]
    assert counts == [1, 6, 3, 14]  # identity, ±90° about 3 axes, 180° about 3 axes, 8 + 6
    assert typ[0] == 0
    for g, t, k, wk in zip(G, typ, axis, w):
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(g.trace()) - 1) / 2))))
        if t in (1, 2):
            e = torch.zeros(3, dtype=g.dtype)
            e[k] = 1.0
            assert torch.equal(g @ e, e)  # the axis is fixed
            assert angle == pytest.approx(90.0 if t == 1 else 180.0)
            assert torch.equal(wk.abs(), e if t == 1 else torch.zeros(3, dtype=g.dtype))
        elif t == 3:
            assert int(k) == -1 and (angle == pytest.approx(120.0) or angle == pytest.approx(180.0))


def test_constant_field_has_no_singular_face_and_zero_curl(gen):
    m = io.box(3)
    R = so3.random_rotation(1, generator=gen, dtype=m.vertices.dtype)
    F = R.expand(m.vertices.shape[0], 3, 3).contiguous()
    g = singular_graph(F, m)
    assert g.face_index.numel() == 0 and g.curves == [] and g.junctions == []
    c = g.counts()
    assert c["n_singular_curves"] == 0 and c["n_junctions"] == 0 and math.isnan(c["valid_fraction"])
    assert face_closure(F, m).abs().max() < 1e-14
    met = frame_metrics(F, m)
    assert met["curl_mean"] < 1e-14 and met["curl_p95"] < 1e-14
    assert met["n_singular_curves"] == 0 and met["n_singular_faces_quarter"] == 0


@pytest.mark.parametrize("turns,valence", [(4.0, 3), (-4.0, 5)])
def test_quarter_turn_around_a_line_is_one_valid_curve(turns, valence):
    m = _prism_mesh()
    F = _turning_field(m, (0.0, 0.0, 1.0), turns)
    g = singular_graph(F, m)
    assert torch.equal(g.face_index, _pierced_faces(m))
    assert (g.face_type == FACE_TYPES.index("quarter")).all() and (g.face_axis == 2).all()
    assert (g.face_valence == valence).all()
    assert len(g.curves) == 1
    (c,) = g.curves
    assert c.label == f"valence{valence}" and not c.closed
    assert c.ends == (("boundary", -1), ("boundary", -1))
    assert c.faces.numel() == g.face_index.numel() and bool(g.face_valid.all())
    # the polyline runs inside the central prism column, from one cap to the other
    assert c.points[:, :2].norm(dim=1).max() < 0.3
    assert sorted([float(c.points[0, 2]), float(c.points[-1, 2])]) == [0.0, 1.0]
    counts = g.counts()
    assert counts["n_singular_curves"] == 1 and counts["valid_fraction"] == 1.0
    assert counts["n_curves_ending_inside"] == 0 and counts["n_junctions"] == 0
    assert counts["n_quarter_faces_by_valence"][valence] == g.face_index.numel()


def test_graph_is_invariant_under_relabeling_the_frames(gen):
    m = _prism_mesh()
    F = _turning_field(m, (0.0, 0.0, 1.0), 4.0)
    h = octahedral.group(F.dtype)[torch.randint(0, 24, (F.shape[0],), generator=gen)]
    a, b = singular_graph(F, m), singular_graph(F @ h, m)
    for name in ("face_index", "face_type", "face_valence", "face_valid", "face_curve"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.allclose(face_closure(F, m).norm(dim=1), face_closure(F @ h, m).norm(dim=1), atol=1e-14)


def test_quarter_turn_about_a_transverse_axis_is_a_zipper():
    m = _prism_mesh()
    g = singular_graph(_turning_field(m, (1.0, 0.0, 0.0), 4.0), m)
    assert len(g.curves) == 1 and (g.face_type == 1).all() and (g.face_axis == 0).all()
    assert not bool(g.face_valid.any()) and g.counts()["valid_fraction"] == 0.0


def test_120_degree_turn_about_the_diagonal_is_complex():
    m = _prism_mesh()
    g = singular_graph(_turning_field(m, (1.0, 1.0, 1.0), 3.0), m)
    assert torch.equal(g.face_index, _pierced_faces(m))
    assert (g.face_type == FACE_TYPES.index("complex")).all() and (g.face_axis == -1).all()
    assert [c.label for c in g.curves] == ["complex"]
    assert g.counts()["n_singular_faces_by_type"] == {"quarter": 0, "half": 0, "complex": g.face_index.numel()}
    assert math.isnan(g.counts()["valid_fraction"])


def test_matchings_may_be_given_as_elements_or_indices():
    m = _prism_mesh(n_layers=2)
    F = _turning_field(m, (0.0, 0.0, 1.0), 4.0)
    idx, gm = octahedral.match_edges(F, m.edges)
    for arg in (idx, gm):
        assert torch.equal(singular_graph(F, m, arg).face_valence, singular_graph(F, m).face_valence)
    with pytest.raises(ValueError, match="edges"):
        singular_graph(F, m, idx[:-1])
    with pytest.raises(ValueError, match="frames"):
        singular_graph(F[:-1], m)
    with pytest.raises(ValueError, match="tangent_window"):
        singular_graph(F, m, tangent_window=0)


def _smooth_rotation(x):
    """A smooth, slowly varying, non-integrable field at points ``x (..., 3)``."""
    return so3.exp(torch.stack([0.4 * x[..., 1], 0.3 * x[..., 2], 0.5 * x[..., 0]], -1))


def _smooth_field(mesh):
    return _smooth_rotation(mesh.vertices)


def test_curl_is_first_order_for_a_smooth_field():
    coarse, fine = io.box(4), io.box(8)
    cm = [frame_metrics(_smooth_field(m), m) for m in (coarse, fine)]
    assert cm[0]["n_singular_faces"] == 0 and cm[1]["n_singular_faces"] == 0
    ratio = cm[0]["curl_mean"] / cm[1]["curl_mean"]
    assert 1.8 < ratio < 2.2, ratio
    assert 1.7 < cm[0]["curl_p95"] / cm[1]["curl_p95"] < 2.3
    assert cm[0]["curl_mean"] > 1e-3  # the field is not integrable: the measure sees it


def test_closure_is_the_curl_flux_by_stokes():
    """``c_k = oint a_k . dx = area (curl a_k) . n`` for a slowly varying field (all matchings I)."""
    errs = []
    for n in (4, 8):
        m = io.box(n)
        c = face_closure(_smooth_field(m), m)
        X = m.vertices[m.faces]
        area_n = torch.linalg.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], dim=-1) / 2  # loop a -> b -> c
        J = torch.func.vmap(torch.func.jacrev(_smooth_rotation))(X.mean(1))
        # J[f, i, k, j] = d a_k,i / d x_j with a_k = F[:, k]; (curl a_k)_i = eps_ijl d_j a_k,l
        curl = torch.stack([J[:, 2, :, 1] - J[:, 1, :, 2], J[:, 0, :, 2] - J[:, 2, :, 0],
                            J[:, 1, :, 0] - J[:, 0, :, 1]], 1)
        expect = (curl * area_n[:, :, None]).sum(1)  # (F, k)
        errs.append(float((c - expect).norm(dim=1).max() / expect.norm(dim=1).max()))
    assert errs[0] < 0.03 and 1.7 < errs[0] / errs[1] < 2.3, errs  # trapezoid + centroid: O(h) relative


def test_metrics_dtype_and_keys():
    m = _prism_mesh(n_layers=2, dtype=torch.float32)
    F = _turning_field(m, (0.0, 0.0, 1.0), 4.0)
    met = frame_metrics(F, m)
    assert set(met) == set(METRIC_KEYS)
    assert met["n_singular_curves"] == 1 and met["n_singular_faces_valence3"] == met["n_singular_faces"]
    assert met["singular_valid_fraction"] == 1.0 and met["dirichlet_energy_mean"] == met["smoothness_mean_sqfrob"]


def _check_graph_structure(g, m):
    """Every singular face in exactly one curve; consecutive faces share a tet with exactly two
    singular faces; ends are boundary faces or junction tets (3+ singular faces)."""
    S = g.face_index.numel()
    mask = torch.zeros(m.n_faces, dtype=torch.bool)
    mask[g.face_index] = True
    count = mask[m.tet_faces].sum(1)
    all_faces = torch.cat([c.faces for c in g.curves]) if g.curves else torch.zeros(0, dtype=torch.long)
    assert all_faces.numel() == S and torch.equal(all_faces.sort().values, g.face_index)
    for cid, c in enumerate(g.curves):
        ft = m.face_tets[c.faces]
        for p, q in zip(ft[:-1].tolist(), ft[1:].tolist()):
            shared = set(p) & set(q) - {-1}
            assert len(shared) == 1 and count[shared.pop()] == 2
        assert c.closed == (len(c.ends) == 0)
        for kind, tet in c.ends:
            assert kind in ("boundary", "junction"), (cid, kind, tet)
            assert (tet == -1) if kind == "boundary" else int(count[tet]) >= 3
        assert torch.isfinite(c.points).all()
    for j in g.junctions:
        assert int(count[j["tet"]]) == len(j["curves"]) >= 3
        assert j["labels"] == [g.curves[c].label for c in j["curves"]]


def test_curves_of_a_rough_field_form_a_graph(gen):
    """Many curves and junctions: chains, ends and junction lists are consistent; the polyline
    alternates face and tet barycenters."""
    m = io.box(3)
    F = so3.exp(2.0 * torch.randn(m.vertices.shape[0], 3, generator=gen, dtype=torch.float64))
    g = singular_graph(F, m)
    assert len(g.curves) > 10 and len(g.junctions) > 3
    _check_graph_structure(g, m)
    assert g.counts()["n_curves_ending_inside"] == 0 == g.n_tets_one_singular_face
    for cid, c in enumerate(g.curves):
        assert (g.face_curve[torch.searchsorted(g.face_index, c.faces)] == cid).all()
        inner = c.points[(1 if c.ends and c.ends[0][1] >= 0 else 0)::2][: c.faces.numel()]
        assert torch.equal(inner, m.face_barycenters[c.faces])


def test_curves_on_the_shared_sphere_are_closed_or_end_on_boundary_or_junctions():
    from torchconn.frames import sh_frame_field
    from torchconn.mesh.io import load_tet_mesh

    m = load_tet_mesh(data_path("sphere_r0.17.mesh"))
    F = sh_frame_field(m, n_restarts=1, n_smooth_iters=0)  # the linear SH step: fast, many curves
    g = singular_graph(F, m)
    assert len(g.curves) > 10 and len(g.junctions) > 0
    _check_graph_structure(g, m)
    c = g.counts()
    assert c["n_curves_ending_inside"] == 0 and 0.5 < c["valid_fraction"] <= 1.0


@pytest.mark.slow
def test_curves_of_the_full_sh_field_on_the_shared_sphere():
    from torchconn.frames import sh_frame_field
    from torchconn.mesh.io import load_tet_mesh

    m = load_tet_mesh(data_path("sphere_r0.17.mesh"))
    g = singular_graph(sh_frame_field(m), m)
    _check_graph_structure(g, m)
    assert g.counts()["valid_fraction"] > 0.9


@pytest.mark.parametrize("suffix", [".vtu", ".vtk"])
def test_singular_curves_vtk_round_trip(tmp_path, suffix, gen):
    m = io.box(3)
    F = so3.exp(1.5 * torch.randn(m.vertices.shape[0], 3, generator=gen, dtype=torch.float64))
    g = singular_graph(F, m)
    assert len(g.curves) > 3
    path = tmp_path / f"singular_curves{suffix}"
    write_singular_curves_vtk(path, g)
    back = read_singular_curves_vtk(path)
    assert len(back) == len(g.curves)
    for c, r in zip(g.curves, back):
        np.testing.assert_allclose(r["points"], c.points.numpy(), rtol=0, atol=1e-12)
        assert r["label"] == c.label and r["label"] in CURVE_TYPES and r["closed"] == c.closed
        if c.n_quarter:
            assert r["valid"] == pytest.approx(c.n_valid / c.n_quarter)
        else:
            assert math.isnan(r["valid"])
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary file was moved over the target
    empty = tmp_path / f"empty{suffix}"
    write_singular_curves_vtk(empty, singular_graph(torch.eye(3, dtype=torch.float64).expand(m.vertices.shape[0], 3, 3), m))
    assert read_singular_curves_vtk(empty) == []


def test_singularities_png_from_a_graph_and_from_faces(tmp_path):
    pytest.importorskip("matplotlib")
    from training import frame_plots

    m = _prism_mesh(n_layers=3)
    g = singular_graph(_turning_field(m, (1.0, 0.0, 0.0), 4.0), m)  # a zipper curve: orange dots
    for name, arg in (("graph.png", g), ("faces.png", m.faces[g.face_index])):
        frame_plots.plot_singularities(tmp_path / name, m, arg)
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
