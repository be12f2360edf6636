"""The foldover-free seamless map and the injective quantization (torchconn.hexmesh.injective,
quantize.round_injective, SeamlessProblem.flat_tets, validity.check_seamless).

* the line-search bound: the first root of the determinant cubic against numpy's roots;
* the per-tet barrier: gradient and Hessian against autograd, the Hessian positive semidefinite
  (projected) and exact where the energy is convex;
* a box map folded on purpose becomes foldover-free and the identity again; a fixed unknown stays;
* moving a boundary plane by one unit keeps the map injective; moving it onto the opposite plane
  fails and leaves the map as it was;
* a tet no value of the unknowns opens: left out, the rest untangled; not left out, the shifted
  rounds end once a round opens nothing, and it is reported inverted;
* rounding a valid non-integral map keeps every tet positive and makes every integer exact;
* the flat tets of a hand-built constraint system: coplanar and collapsed ones told apart;
* the seamless check passes the identity map and catches a broken one.
* (slow, HexMe data) n10c's seamless map: foldover-free with the untangling phases' relieved fit,
  inverted tets left with the full fit.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchconn import io
from torchconn.hexmesh.cut import tet_charts
from torchconn.hexmesh.elimination import Elimination
from torchconn.hexmesh.injective import DET_SAFE, TetJacobians, minimize_barrier, move_fixed
from torchconn.hexmesh.quantize import round_injective, solve_fixed
from torchconn.hexmesh.tet_energies import barrier_terms, first_root
from torchconn.hexmesh.seamless import SeamlessProblem, build_problem
from torchconn.hexmesh.validity import check_seamless


def _box_problem(n=3, h=None):
    mesh = io.box(n)
    frames = torch.eye(3, dtype=torch.float64).expand(mesh.n_tets, 3, 3).clone()
    charts = tet_charts(mesh, frames)
    prob = build_problem(mesh, charts, 1.0 / n if h is None else h)
    A, b, _ = prob.energy_matrices()
    y = solve_fixed(A, b, np.zeros(A.shape[0], bool), np.zeros(0))
    return mesh, charts, prob, y


# ----------------------------------------------------------------------------- line search bound
def test_first_root_matches_numpy_roots():
    rng = np.random.default_rng(0)
    n = 400
    a = np.abs(rng.normal(size=n)) + 1e-3
    b, c, d = rng.normal(size=(3, n))
    # degenerate cubics: quadratic, linear, a double root at s = 0.5
    c[:20], d[:20] = rng.normal(size=20), 0.0
    c[20:40], d[20:40] = 0.0, 0.0
    a[40:50], b[40:50], c[40:50], d[40:50] = 0.25, -1.0, 1.0, 0.0
    got = first_root(a, b, c, d, 2.0)
    for i in range(n):
        r = np.roots([d[i], c[i], b[i], a[i]] if d[i] else ([c[i], b[i], a[i]] if c[i] else [b[i], a[i]]))
        real = sorted(z.real for z in r if abs(z.imag) <= 1e-7 * max(1.0, abs(z)) and 0 < z.real <= 2.0)
        if real:
            assert got[i] == pytest.approx(real[0], rel=1e-6, abs=1e-6), i
        else:
            # no root (a double root is touched, not crossed: p stays >= 0)
            s = np.linspace(0, 2, 2001)
            assert np.isinf(got[i]) or (a[i] + s * (b[i] + s * (c[i] + s * d[i]))).min() <= 1e-9, i


def test_first_root_never_overshoots_a_sign_change():
    rng = np.random.default_rng(1)
    a = np.abs(rng.normal(size=1000)) + 1e-6
    b, c, d = rng.normal(size=(3, 1000)) * 3
    r = first_root(a, b, c, d, 1.0)
    s = np.linspace(0, 1, 4001)[None, :]
    p = a[:, None] + s * (b[:, None] + s * (c[:, None] + s * d[:, None]))
    before = np.where(s <= np.minimum(r, 1.0)[:, None] * (1 - 1e-9), p, np.inf)
    assert (before > 0).all()


# ----------------------------------------------------------------------------- per-tet terms
def test_barrier_terms_gradient_and_hessian_against_autograd():
    gen = torch.Generator().manual_seed(0)
    J = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(16, 3, 3, generator=gen, dtype=torch.float64)
    eps = torch.zeros(16, dtype=torch.float64)
    eps[:4] = 0.5
    f, g, H = barrier_terms(J, eps, 0.7, 1.3)

    def total(j, eps=eps):
        Jm = j.reshape(-1, 3, 3)
        adj = torch.stack([torch.cross(Jm[:, 1], Jm[:, 2], dim=-1), torch.cross(Jm[:, 2], Jm[:, 0], dim=-1),
                           torch.cross(Jm[:, 0], Jm[:, 1], dim=-1)], -1)
        det = torch.linalg.det(Jm)
        fit = (Jm - torch.eye(3, dtype=j.dtype)).square().sum((1, 2))
        sd = Jm.square().sum((1, 2)) + adj.square().sum((1, 2)) / (det + eps).square() - 6
        return 0.7 * fit + 1.3 * sd

    j = J.reshape(16, 9)
    torch.testing.assert_close(f, total(j))
    gref = torch.autograd.functional.jacobian(lambda x: total(x).sum(), j)
    torch.testing.assert_close(g, gref)
    # the Hessian: the fitting term's 2 w_fit I plus the PSD projection of the barrier's exact Hessian
    eye = torch.eye(9, dtype=torch.float64)
    for i in range(16):
        Hsd = torch.autograd.functional.hessian(lambda x: (total(x.reshape(1, 9), eps[i:i + 1]).sum()
                                                           - 0.7 * (x - eye.diagonal().reshape(3, 3).flatten()
                                                                    * 0 - torch.eye(3, dtype=x.dtype).flatten()
                                                                    ).square().sum()), j[i])
        w, V = torch.linalg.eigh(Hsd)
        ref = 2 * 0.7 * eye + (V * w.clamp_min(0)) @ V.T
        torch.testing.assert_close(H[i], ref, rtol=1e-7, atol=1e-7 * float(ref.abs().max()))


def test_barrier_hessian_is_psd_far_from_the_identity():
    gen = torch.Generator().manual_seed(2)
    J = torch.randn(200, 3, 3, generator=gen, dtype=torch.float64)
    det = torch.linalg.det(J)
    eps = torch.where(det > 0, torch.zeros_like(det), 1e-2 - det)
    _, _, H = barrier_terms(J, eps, 0.0, 1.0)
    w = torch.linalg.eigvalsh(H)
    assert (w >= -1e-9 * w.abs().amax(1, keepdim=True)).all()


# ----------------------------------------------------------------------------- minimize_barrier
def test_a_folded_box_map_becomes_foldover_free_and_the_identity_again():
    mesh, charts, prob, y = _box_problem(3)
    jac = TetJacobians.of_problem(prob)
    assert np.allclose(jac(y), np.eye(3), atol=1e-9)
    rng = np.random.default_rng(0)
    y0 = y + rng.normal(scale=0.5, size=y.size)
    assert (np.linalg.det(jac(y0)) <= 0).sum() > 10
    r = minimize_barrier(jac, y0)
    assert r.n_inverted == 0 and r.min_det > DET_SAFE
    assert np.allclose(r.y, y, atol=1e-5)
    assert r.fit_energy < 1e-9
    # the untangling and shifted solves stop at the step that leaves no tet inverted; the barrier
    # solve minimizes from there
    phases = [(h[0][0], h[2]) for h in r.history]
    untangling = [n for p, n in phases if p != "barrier"]
    assert untangling and untangling[-1] == 0 and all(n > 0 for n in untangling[:-1])
    assert any(p == "barrier" for p, _ in phases)


def test_fixed_unknowns_stay_where_they_are():
    mesh, charts, prob, y = _box_problem(3)
    jac = TetJacobians.of_problem(prob)
    rng = np.random.default_rng(1)
    y0 = y + rng.normal(scale=0.2, size=y.size)
    fixed = np.zeros(y.size, bool)
    fixed[rng.choice(y.size, 5, replace=False)] = True
    r = minimize_barrier(jac, y0, fixed=fixed)
    assert np.array_equal(r.y[fixed], y0[fixed])
    assert r.n_inverted == 0


# ----------------------------------------------------------------------------- move_fixed / rounding
def _plane_integers(prob):
    return np.nonzero(prob.free_is_int)[0]


def test_moving_a_boundary_plane_keeps_the_map_injective_and_a_collapse_fails():
    mesh, charts, prob, y = _box_problem(3, h=1.0 / 3)
    jac = TetJacobians.of_problem(prob)
    I = _plane_integers(prob)
    # the box's planes: one integer per axis for the far faces (the near ones meet the pinned corner)
    assert I.size == 3 and np.allclose(y[I], 3.0)
    y1, ok, _ = move_fixed(jac, y, I[:1], np.array([4.0]))
    assert ok and y1[I[0]] == 4.0 and (np.linalg.det(jac(y1)) > 0).all()
    y2, ok, _ = move_fixed(jac, y, I[:1], np.array([0.0]))  # onto the opposite face: the box would collapse
    assert not ok and np.array_equal(y2, y)


def test_injective_rounding_makes_every_integer_exact_and_folds_nothing():
    mesh, charts, prob, y = _box_problem(3, h=0.3)  # the box is 3.33 units: its planes are not integers
    jac = TetJacobians.of_problem(prob)
    im = prob.free_is_int
    assert not np.allclose(y[im], np.round(y[im]))
    yq, info = round_injective(jac, y, im)
    assert info["failed"] == [] and info["rounded"] == im.sum()
    assert np.array_equal(yq[im], np.round(yq[im]))
    assert (np.linalg.det(jac(yq)) > 0).all()


# ----------------------------------------------------------------------------- flat tets
def _hand_built_problem(corner_rows, n_free):
    """A SeamlessProblem whose corner parameters are given rows of Z (no objective)."""
    T = len(corner_rows)
    rows, cols, vals = [], [], []
    z0 = np.zeros(12 * T)
    for t, corners in enumerate(corner_rows):
        for k, coords in enumerate(corners):
            for i, terms in enumerate(coords):
                r = 12 * t + 3 * k + i
                for col, v in terms.items():
                    if col == "c":
                        z0[r] = v
                    else:
                        rows.append(r)
                        cols.append(col)
                        vals.append(v)
    Z = sp.csr_matrix((vals, (rows, cols)), shape=(12 * T, n_free))
    el = Elimination(n_vars=12 * T, free=np.arange(n_free), Z=Z, z0=z0, is_int=np.zeros(12 * T, bool),
                     free_is_int=np.zeros(n_free, bool), redundant=0)
    corner_var = np.arange(12 * T).reshape(T, 4, 3)
    return SeamlessProblem(charts=None, edge_length=1.0, corner_copy=np.arange(4 * T).reshape(T, 4), n_copies=4 * T,
                           n_vars=12 * T, var_kind=np.zeros(12 * T, np.int8), elim=el, G=None, g=None,
                           vol=np.ones(T), corner_var=corner_var, boundary_axis=np.zeros(0, np.int64),
                           boundary_tet=np.zeros(0, np.int64), feature_edges=np.zeros((0, 2), np.int64),
                           feature_constrained=np.zeros(0, bool), corner_vertices=np.zeros(0, np.int64),
                           pinned_vertex=0)


def test_flat_tets_tells_coplanar_from_collapsed_and_free_tets():
    O = {"c": 0.0}
    free = [({0: 1.0}, {1: 1.0}, {2: 1.0}), ({3: 1.0}, {4: 1.0}, {5: 1.0}), ({6: 1.0}, {7: 1.0}, {8: 1.0})]
    # tet 0: four free corners; tet 1: all corners on the plane w = u_9; tet 2: corners 1 and 2 on one point
    plane = [({0: 1.0}, {1: 1.0}, {9: 1.0}), ({3: 1.0}, {4: 1.0}, {9: 1.0}), ({6: 1.0}, {7: 1.0}, {9: 1.0}),
             ({10: 1.0}, {11: 1.0}, {9: 1.0})]
    point = ({12: 1.0}, {13: 1.0}, {14: 1.0})
    tets = [[(O, O, O)] + free, plane, [free[0], point, point, free[1]]]
    prob = _hand_built_problem(tets, 15)
    flat, collapsed, line_face = prob.flat_tets()
    assert flat.tolist() == [1, 2] and collapsed.tolist() == [False, True]
    # tet 2's corners 1 and 2 coincide: the faces opposite 0 and 3 hold both, hence a line
    assert line_face.tolist() == [-1, 0]


# ----------------------------------------------------------------------------- seamless check
def test_check_seamless_passes_the_box_map_and_catches_a_broken_one():
    mesh, charts, prob, y = _box_problem(3, h=0.3)
    uvw = prob.corner_params(np.round(y * 2.0 ** 20) / 2.0 ** 20)
    v = check_seamless(mesh, charts, uvw, prob)
    assert v.valid, v.reasons
    bad = uvw.copy()
    t = int(np.argmax(mesh.tets.numpy().min(1) >= 0))
    bad[t, 0] += 0.25  # a corner moved in one tet only: its faces are no longer seamless
    v = check_seamless(mesh, charts, bad, prob)
    assert not v.valid and v.counts["broken_transitions"] > 0


def test_tets_no_map_can_open_are_left_out_and_the_rest_untangled():
    mesh, charts, prob, y = _box_problem(3)
    jac = TetJacobians.of_problem(prob)
    k = 7  # a tet made flat for every value of the unknowns: its Jacobian is constant and singular
    GZ = jac.GZ.tolil()
    GZ[9 * k:9 * k + 9, :] = 0
    j0 = jac.j0.copy()
    j0[9 * k:9 * k + 9] = np.diag([1.0, 1.0, 0.0]).reshape(9)
    jac = TetJacobians(GZ=GZ.tocsr(), j0=j0, vol=jac.vol)
    rng = np.random.default_rng(3)
    y0 = y + rng.normal(scale=0.4, size=y.size)
    r = minimize_barrier(jac, y0, ignore=np.array([k]))
    assert r.n_inverted == 0 and np.linalg.det(jac(r.y))[k] == 0.0
    det = np.linalg.det(jac(r.y))
    assert (np.delete(det, k) > DET_SAFE).all()


def test_a_tet_no_map_opens_ends_the_shifted_rounds_once_a_round_opens_nothing():
    # the same pinned tet, inverted and not left out: no round can open it, so the shifted rounds end
    # at the second (the first that leaves as many inverted as the round before) instead of spending
    # all four; the other tets are untangled and the pinned one is reported, not hidden
    mesh, charts, prob, y = _box_problem(3)
    jac = TetJacobians.of_problem(prob)
    k = 7
    GZ = jac.GZ.tolil()
    GZ[9 * k:9 * k + 9, :] = 0
    j0 = jac.j0.copy()
    j0[9 * k:9 * k + 9] = np.diag([1.0, 1.0, -1.0]).reshape(9)
    jac = TetJacobians(GZ=GZ.tocsr(), j0=j0, vol=jac.vol)
    rng = np.random.default_rng(3)
    y0 = y + rng.normal(scale=0.4, size=y.size)
    r = minimize_barrier(jac, y0, rounds=4)
    assert r.rounds == 2
    assert r.inverted.tolist() == [k]
    det = np.linalg.det(jac(r.y))
    assert (np.delete(det, k) > DET_SAFE).all()


def _dipole(n=4, x1=0.25, x2=0.75):
    """A box with two singular lines along z, valence 3 and 5 (a +90 and a -90 degree turn), at
    ``x1`` and ``x2`` on the box's grid: ``Rz((phi_1 - phi_2) / 4)`` per tet."""
    from torchconn import so3

    mesh = io.box(n)
    bc = mesh.tet_barycenters
    p1 = torch.atan2(bc[:, 1] - 0.5, bc[:, 0] - x1)
    p2 = torch.atan2(bc[:, 1] - 0.5, bc[:, 0] - x2)
    return mesh, so3.exp(((p1 - p2) / 4)[:, None] * torch.tensor([0, 0, 1.0], dtype=torch.float64))


@pytest.mark.slow  # ~20-30 s: the injective rounding's failed moves at the first size
def test_two_close_singular_lines_greedy_rounding_folds_the_injective_one_keeps_them_apart():
    from torchconn.hexmesh import integer_grid_map

    mesh, frames = _dipole()
    # at h = 0.7 the lines are 0.71 apart and the box 1.43 wide in integer units: the boundary planes
    # and the two lines cannot all sit on distinct integers
    greedy = integer_grid_map(mesh, frames, edge_length=0.7, injective=False)
    assert greedy.gates["seamless"].passed and not greedy.validity.valid
    assert greedy.validity.counts["inverted_tets"] > 0
    inj = integer_grid_map(mesh, frames, edge_length=0.7)
    assert inj.gates["seamless"].passed and inj.validity.valid, inj.validity.reasons
    # no injective rounding at h: the same map at h/2, where the lines fit on distinct integers
    assert inj.stats["quantization"]["refined"] == 2 and inj.edge_length == pytest.approx(0.35)
    assert inj.gates["quantization"].counts["refined"] == 2
    sing = inj.charts.singular_edge
    assert sing.sum() == greedy.charts.singular_edge.sum() > 0


@pytest.mark.slow  # a HexMe model through the map stage: ~15-40 s
def test_a_hexme_model_gets_a_valid_seamless_map_and_an_injectively_rounded_igm():
    """s03c (the pentagon) with the SH field: a valid seamless map (untangled by the foldover-free
    solve where the least squares fold: with the matching search's boundary moves they no longer
    do on this model) and the injective rounding keeps it valid."""
    from conftest import hexme_mesh
    from torchconn.frames import design
    from torchconn.hexmesh import integer_grid_map

    mesh = hexme_mesh("s03c_pentagon")
    frames = design(mesh, "sh_baseline").vertex_frames
    m = integer_grid_map(mesh, frames)
    inj = m.stats["seamless"]["injective"]
    assert (inj is None) == (m.stats["seamless"]["inverted_least_squares"] == 0)
    assert inj is None or inj["inverted_after"] == 0
    assert m.gates["seamless"].passed and m.validity.valid, m.validity.reasons
    assert m.stats["quantization"]["method"] == "injective"


# ----------------------------------------------------------------------------- refinement of flat tets
def test_centroid_and_edge_splits_keep_the_vertices_the_orientation_and_the_singular_graph():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_hexmesh_map import axis_prism

    from torchconn.hexmesh.cut import face_matchings
    from torchconn.hexmesh.split import open_flat_tets, split_tets_centroid

    mesh, frames = axis_prism(turns=4)  # a valence-3 axis
    fm = face_matchings(mesh, frames)
    ch = tet_charts(mesh, frames, fm)
    tets = np.arange(0, mesh.n_tets, 7)
    new, F2, parent, fm2 = split_tets_centroid(mesh, frames, tets, fm)
    assert new.n_tets == mesh.n_tets + 3 * tets.size and new.n_vertices == mesh.n_vertices + tets.size
    assert torch.equal(new.vertices[: mesh.n_vertices], mesh.vertices)
    X, T = new.vertices.numpy(), new.tets.numpy()
    P = X[T]
    assert (np.einsum("ti,ti->t", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), P[:, 3] - P[:, 0]) > 0).all()
    assert np.bincount(parent, minlength=mesh.n_tets)[tets].tolist() == [4] * tets.size
    ch2 = tet_charts(new, F2, fm2)
    assert ch2.counts()["singular_edges"] == ch.counts()["singular_edges"]
    assert ch2.counts()["valence3_edges"] == ch.counts()["valence3_edges"]
    # one round of the flat-tet refinement: edge splits where an edge is free, centroids elsewhere
    keep = ch.singular_edge.copy()
    keep[mesh.face_edges.numpy()[mesh.boundary_face_index.numpy()].reshape(-1)] = True
    line_face = -np.ones(tets.size, np.int64)
    new, F2, parent, fm2, n = open_flat_tets(mesh, frames, tets, line_face, fm, keep, ch.singular_edge)
    assert n["edge"] + n["centroid"] > 0 and tet_charts(new, F2, fm2).counts()["singular_edges"] == ch.counts()["singular_edges"]


@pytest.mark.slow
def test_the_relieved_fit_untangles_n10c_where_the_full_fit_stalls(monkeypatch):
    """HexMe n10c (a quarter torus on a cylinder), the jobs' first connection field: its structure
    passes every gate and the one-ring test, but with the fitting term at full weight in the
    untangling phases the seamless map keeps inverted tets (8 after 179 Newton steps,
    2026-11-27); with :data:`FIT_RELIEF` the map is foldover-free and the hex mesh good."""
    from conftest import DATA_DIR

    from torchconn.hexmesh import hex_mesh, injective
    from torchconn.hexmesh.choose import design_for_hex

    if not (DATA_DIR / "hexme" / "meta" / "n10c_qtorus_cyl.yaml").is_file():
        pytest.skip(f"HexMe parameter files not found in {DATA_DIR / 'hexme'} (the shared data is missing)")
    from benchmarks.frames_hexme import load_case

    mesh = load_case("hexme", "n10c_qtorus_cyl")
    field = design_for_hex(mesh, "connection", select="proxies", weights={"map": 1.0}, starts=["sh"],
                           quality={"enabled": False}).vertex_frames
    r = hex_mesh(mesh, field)
    assert r.gates["structure"].passed and r.gates["seamless"].passed
    assert r.map.stats["seamless"]["injective"]["inverted_after"] == 0
    assert r.verdict()["good"], r.verdict()["text"]
    monkeypatch.setattr(injective, "FIT_RELIEF", 1.0)
    full = hex_mesh(mesh, field, extract=False)
    assert full.gates["structure"].passed and not full.gates["seamless"].passed
    assert full.map.stats["seamless"]["injective"]["inverted_after"] > 0
