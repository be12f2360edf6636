"""The map stage's setup made to scale, against the slow references it replaces.

* :func:`~torchconn.hexmesh.split.split_for_map` carries the singular edges through its rounds
  instead of rebuilding the charts every round: the same refined mesh, frames and counts as the
  per-round rebuild (kept here as the reference), on fields with many singular edges;
* :func:`~torchconn.hexmesh.elimination.eliminate` (continuous variables in bulk, the per-row rule
  over the integer rows only) gives the same ``free``, ``Z``, ``z0``, redundant rows, conflicts
  and relaxed integers as :func:`~torchconn.hexmesh.elimination.eliminate_reference` (the per-row
  rule over every row), bit for bit: on random systems of the seamless problem's row kinds (cut
  links with translations, anchors, half-turn rows, integer rows; random orders), on the
  constraints of real problems (random and turning fields), on a contradictory system;
* the injective rounding takes a least-squares re-solve only when it keeps every tet positive
  (the box: everything at once; a fold: refused, the injective moves round it), with the same
  guarantee; the greedy rounding in blocks (no ``|I| x |I|`` matrix) ends with every integer
  exact and the continuous unknowns optimal for them;
* the per-tet gradients and Hessians of the foldover-free solve's energies in closed form equal
  batched autograd (float64), inverted and nearly flat Jacobians included.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import so3
from torchconn.hexmesh import seamless
from torchconn.hexmesh.cut import tet_charts
from torchconn.hexmesh.elimination import ConstraintRows, eliminate, eliminate_reference
from torchconn.hexmesh.split import SPLIT_RULES, SplitResult, _independent, split_edges, split_for_map
from torchconn.mesh.builtin import box


def _random_frames(mesh, seed, scale=0.6):
    """Per-tet rotations: a smooth turn plus noise (many singular, some complex edges)."""
    g = torch.Generator().manual_seed(seed)
    w = scale * torch.randn(mesh.n_tets, 3, generator=g, dtype=torch.float64)
    return so3.exp(w)


def split_for_map_reference(mesh, tet_frames, face_match=None, *, rules=SPLIT_RULES, max_rounds=50):
    """The per-round rebuild: the charts (hence the singular edges) recomputed every round."""
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    parent = np.arange(mesh.n_tets)
    counts = {r: 0 for r in SPLIT_RULES}
    rounds = 0
    for _ in range(max_rounds):
        edges = mesh.edges.cpu().numpy()
        V, E = mesh.n_vertices, edges.shape[0]
        cand_by_rule = {}
        if "singular" in rules:
            ch = tet_charts(mesh, Fr, face_match)
            sv = np.zeros(V, bool)
            sv[edges[ch.singular_edge].reshape(-1)] = True
            cand_by_rule["singular"] = np.nonzero(~ch.singular_edge & sv[edges[:, 0]] & sv[edges[:, 1]])[0]
        if "boundary" in rules:
            bv = np.zeros(V, bool)
            bv[mesh.boundary_vertices.cpu().numpy()] = True
            bfe = mesh.face_edges.cpu().numpy()[mesh.boundary_face_index.cpu().numpy()].reshape(-1)
            on_b = np.zeros(E, bool)
            on_b[bfe] = True
            cand_by_rule["boundary"] = np.nonzero(~on_b & bv[edges[:, 0]] & bv[edges[:, 1]])[0]
        cand = np.unique(np.concatenate([c for c in cand_by_rule.values()] or [np.zeros(0, np.int64)]))
        if cand.size == 0:
            break
        chosen = _independent(mesh.tet_edges.cpu().numpy(), cand, E)
        for r, c in cand_by_rule.items():
            counts[r] += int(np.isin(chosen, c).sum())
        mesh, Fr, par, face_match = split_edges(mesh, Fr, chosen, face_match)
        parent = parent[par]
        rounds += 1
    return SplitResult(mesh=mesh, tet_frames=Fr, parent_tet=parent, splits=counts, rounds=rounds,
                       face_match=face_match)


def _same_split(a, b):
    assert a.rounds == b.rounds and a.splits == b.splits
    assert torch.equal(a.mesh.tets, b.mesh.tets) and torch.equal(a.mesh.vertices, b.mesh.vertices)
    assert torch.equal(a.tet_frames, b.tet_frames) and np.array_equal(a.parent_tet, b.parent_tet)
    assert (a.face_match is None) == (b.face_match is None)
    if a.face_match is not None:
        assert np.array_equal(a.face_match, b.face_match)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_split_carries_the_singular_edges_as_the_per_round_rebuild(seed):
    mesh = box(4)
    Fr = _random_frames(mesh, seed)
    new = split_for_map(mesh, Fr, max_rounds=6)
    ref = split_for_map_reference(mesh, Fr, max_rounds=6)
    assert ref.splits["singular"] > 0 and ref.rounds >= 2  # the case exercises the carried edges
    _same_split(new, ref)
    # the carried singular edges are the refined mesh's: its charts agree
    ch0 = tet_charts(mesh, Fr)
    ch1 = tet_charts(new.mesh, new.tet_frames)
    assert int(ch1.singular_edge.sum()) >= int(ch0.singular_edge.sum())


def test_split_with_given_matchings_and_one_rule():
    from torchconn.hexmesh.cut import face_matchings

    mesh = box(3)
    Fr = _random_frames(mesh, 7)
    fm = face_matchings(mesh, Fr)
    fm = np.where(np.arange(fm.size) % 5 == 0, 0, fm)  # a matching that is not the best one
    for rules in (("singular",), SPLIT_RULES):
        _same_split(split_for_map(mesh, Fr, fm, rules=rules, max_rounds=5),
                    split_for_map_reference(mesh, Fr, fm, rules=rules, max_rounds=5))


# ----------------------------------------------------------------------------- elimination
def _random_rows(rng, nc, ni, nrows):
    """A random system of the seamless problem's row kinds over interleaved continuous and integer
    variables: links ``a x_u - s a x_v (± t) = 0``, anchors ``± x_c - k = 0`` (or a pin),
    integer rows with unit coefficients, half-turn rows ``2 m - a - b = 0``."""
    n = nc + ni
    perm = rng.permutation(n)
    cont, ints = perm[:nc], perm[nc:]
    is_int = np.zeros(n, bool)
    is_int[ints] = True
    rows = ConstraintRows()
    for _ in range(nrows):
        kind = rng.choice(["link", "anchor", "int", "half"], p=[0.6, 0.25, 0.1, 0.05])
        if kind == "link":
            u, v = rng.choice(cont, 2, replace=False)
            s, a = rng.choice([-1.0, 1.0]), rng.choice([-1.0, 1.0])
            vs, cs = [u, v], [a, -s * a]
            if rng.random() < 0.8:
                vs.append(rng.choice(ints))
                cs.append(rng.choice([-1.0, 1.0]))
            rows.add(vs, cs, 0.0, "link")
        elif kind == "anchor":
            vs, cs = [rng.choice(cont)], [rng.choice([-1.0, 1.0])]
            if rng.random() < 0.9:
                vs.append(rng.choice(ints))
                cs.append(-1.0)
            rows.add(vs, cs, 0.0, "anchor")
        elif kind == "int":
            k = int(rng.integers(1, 4))
            rows.add(rng.choice(ints, k, replace=False), rng.choice([-1.0, 1.0], k), 0.0, "int")
        else:
            rows.add(rng.choice(ints, 3, replace=False), [2.0, -1.0, -1.0], 0.0, "half")
    return rows, n, is_int


def _assert_same_elimination(a, b):
    assert np.array_equal(a.free, b.free)
    assert a.Z.shape == b.Z.shape and (a.Z != b.Z).nnz == 0  # bit for bit
    assert np.array_equal(a.z0, b.z0)
    assert a.redundant == b.redundant and a.relaxed_integers == b.relaxed_integers
    assert [(int(r), lab, c) for r, lab, c in a.conflicts] == [(int(r), lab, c) for r, lab, c in b.conflicts]


def _dyadic(el):
    d = np.r_[el.Z.data, el.z0] * 2.0**20
    return bool(np.array_equal(d, np.round(d)))


def test_eliminate_equals_the_per_row_reference_on_random_systems():
    checked = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        rows, n, is_int = _random_rows(rng, int(rng.integers(3, 30)), int(rng.integers(3, 20)),
                                       int(rng.integers(1, 45)))
        order = rng.permutation(len(rows)) if seed % 3 == 0 else None
        ref = eliminate_reference(rows, n, is_int, order=order)
        if not _dyadic(ref):  # the reference's own arithmetic rounded (non-dyadic pivots): not comparable
            continue
        _assert_same_elimination(eliminate(rows, n, is_int, order=order), ref)
        checked += 1
    assert checked >= 36


def test_eliminate_reports_the_same_contradictions():
    rows = ConstraintRows()
    rows.add([0, 1, 2], [1, -1, -1])  # x0 = x1 + t2 (t2, t5 integer)
    rows.add([3, 0], [1, -1])
    rows.add([2, 5], [1, -1])
    rows.add([0, 1, 2], [1, -1, -1])  # redundant
    rows.add([5], [1], -3.0, "pin")
    rows.add([4], [2], -1.0)
    rows.add([4], [1], -1.0, "contradiction")
    rows.add([1, 3, 5], [1, -1, 1], 0.5, "contradiction 2")
    is_int = np.array([0, 0, 1, 0, 0, 1], bool)
    a, b = eliminate(rows, 6, is_int), eliminate_reference(rows, 6, is_int)
    _assert_same_elimination(a, b)
    assert [c[1] for c in a.conflicts] == ["contradiction", "contradiction 2"]


def _captured_rows(mesh, Fr, monkeypatch):
    cap = {}

    def capture(rows, n, is_int, **kw):
        cap["args"] = (rows, n, is_int)
        return eliminate(rows, n, is_int, **kw)

    monkeypatch.setattr(seamless, "eliminate", capture)
    ch = tet_charts(mesh, Fr)
    seamless.build_problem(mesh, ch, seamless.default_edge_length(mesh))
    return cap["args"], ch


@pytest.mark.parametrize("seed", [3, 4])
def test_eliminate_equals_the_reference_on_real_constraints(seed, monkeypatch):
    """The constraints of seamless problems: a random field (many singular edges, half turns among
    them) and the turning prism field (a valence-3 axis), on meshes with boundary features."""
    from tests.test_hexmesh_map import axis_prism

    cases = [(box(3), _random_frames(box(3), seed, scale=0.8))]
    mesh, Fr = axis_prism(n_layers=2, turns=4)
    cases.append((mesh, Fr))
    half = 0
    for mesh, Fr in cases:
        (rows, n, is_int), ch = _captured_rows(mesh, Fr, monkeypatch)
        half += int((ch.singular_edge & (ch.edge_type == 2)).sum())
        ref = eliminate_reference(rows, n, is_int)
        assert _dyadic(ref)
        _assert_same_elimination(eliminate(rows, n, is_int), ref)
    assert half > 0 or seed != 3  # this random field has half-turn edges


# ----------------------------------------------------------------------------- rounding
def _box_problem(n=3, h=0.3):
    from torchconn import io
    from torchconn.hexmesh.injective import TetJacobians
    from torchconn.hexmesh.quantize import solve_fixed

    mesh = io.box(n)
    frames = torch.eye(3, dtype=torch.float64).expand(mesh.n_tets, 3, 3).clone()
    prob = seamless.build_problem(mesh, tet_charts(mesh, frames), h)
    A, b, _ = prob.energy_matrices()
    y = solve_fixed(A, b, np.zeros(A.shape[0], bool), np.zeros(0))
    return prob, A, b, y, TetJacobians.of_problem(prob)


def test_injective_rounding_takes_the_least_squares_re_solve_when_it_folds_nothing():
    from torchconn.hexmesh.quantize import round_injective

    prob, A, b, y, jac = _box_problem(3, h=0.3)  # the box is 3.33 units: its planes are not integers
    im = prob.free_is_int
    yq, info = round_injective(jac, y, im, lsq=(A, b))
    assert info["failed"] == [] and info["rounded"] == im.sum()
    assert info["lsq_accepted"] == 1 and info["moves"] == 0  # everything at once
    assert np.array_equal(yq[im], np.round(y[im])) and (np.linalg.det(jac(yq)) > 0).all()
    # and it is the least-squares optimum with those integers (gradient zero on the others)
    g = A @ yq - b
    assert np.abs(g[~im]).max() < 1e-9


def test_injective_rounding_refuses_a_least_squares_map_that_folds():
    from torchconn.hexmesh.quantize import round_injective

    prob, A, b, y, jac = _box_problem(3, h=0.3)
    im = prob.free_is_int
    # an objective whose optimum with the box's planes rounded flips the box (a mirrored fit):
    # the injective rounding must refuse it and move the planes instead
    flipped = y.copy()
    flipped[~im] = -y[~im]
    b_bad = A @ flipped
    yq, info = round_injective(jac, y, im, lsq=(A, b_bad))
    assert info["lsq_tries"] >= 1 and info["lsq_accepted"] == 0 and info["moves"] >= 1
    assert info["failed"] == [] and np.array_equal(yq[im], np.round(yq[im]))
    assert (np.linalg.det(jac(yq)) > 0).all()


def test_greedy_rounding_in_blocks_makes_no_dense_matrix_and_ends_exact():
    from torchconn.hexmesh.quantize import round_greedy

    prob, A, b, y, _ = _box_problem(4, h=0.27)
    im = prob.free_is_int
    yb, info = round_greedy(A, b, im, dense_budget=0)
    assert info.get("blocks") and 1 <= info["steps"] <= 5
    assert np.array_equal(yb[im], np.round(yb[im]))
    assert np.abs((A @ yb - b)[~im]).max() < 1e-9  # the continuous unknowns optimal for the integers
    yd, _ = round_greedy(A, b, im)  # the one-factorization rounding: same integers on this box
    assert np.array_equal(yd[im], yb[im])


# ----------------------------------------------------------------------------- closed-form derivatives
@pytest.mark.parametrize("energy", ["sd", "untangling"])
def test_closed_form_derivatives_equal_autograd(energy):
    from torchconn.hexmesh import tet_energies as inj

    g = torch.Generator().manual_seed(5)
    T = 300
    j = (torch.eye(3, dtype=torch.float64).reshape(9) + 0.7 * torch.randn(T, 9, generator=g, dtype=torch.float64))
    j[:5] = torch.tensor([1.0, 0, 0, 0, 1, 0, 0, 0, 1e-6], dtype=torch.float64)  # nearly flat
    det = torch.linalg.det(j.reshape(-1, 3, 3))
    assert (det < 0).any() and (det > 0).any()
    if energy == "sd":
        eps = torch.where(det > 0, torch.zeros_like(det), 1e-2 - det)  # the shifted barrier's shifts
        ref, got = inj._rowwise_derivatives(inj._sd, j, eps, True), inj._sd_derivatives(j, eps, True)
    else:
        eps = torch.tensor(0.05, dtype=torch.float64)
        ref, got = (inj._rowwise_derivatives(inj._untangling, j, eps, True),
                    inj._untangling_derivatives(j, eps, True))
    for a, b in zip(ref, got):
        scale = a.abs().reshape(T, -1).amax(1).clamp_min(1.0)
        err = (a - b).abs().reshape(T, -1).amax(1) / scale
        assert err.max() < 1e-10


def _jacobians_with_hard_cases(T: int, seed: int) -> torch.Tensor:
    """Random Jacobians around ``I``, inverted ones among them, and the cases where the analytic
    eigensystem has repeated singular values: rotations, ``diag(2, 2, 1)``, a reflection, and a
    nearly flat tet."""
    g = torch.Generator().manual_seed(seed)
    J = torch.eye(3, dtype=torch.float64) + 0.7 * torch.randn(T, 3, 3, generator=g, dtype=torch.float64)
    J[0] = torch.eye(3, dtype=torch.float64)
    J[1] = so3.exp(torch.tensor([0.3, -1.2, 0.5], dtype=torch.float64))
    J[2] = torch.diag(torch.tensor([2.0, 2.0, 1.0], dtype=torch.float64))
    J[3] = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    J[4] = torch.diag(torch.tensor([1.0, 1.0, 1e-6], dtype=torch.float64))
    J[5] = 3.0 * J[1]
    return J


@pytest.mark.parametrize("energy", ["sd", "untangling"])
@pytest.mark.parametrize("eps_small", [False, True])
def test_analytic_psd_hessian_equals_projected_eigendecomposition(energy, eps_small):
    """The projected Hessian from the isotropic energies' analytic eigensystem equals the closed-form
    Hessian projected by a 9 x 9 eigen-decomposition, block by block; it is PSD and equals the
    Hessian itself where that is already PSD."""
    from torchconn.hexmesh import tet_energies as te

    J = _jacobians_with_hard_cases(400, 11)
    j = J.reshape(-1, 9)
    det = torch.linalg.det(J)
    assert (det < 0).any() and (det > 0).any()
    if energy == "sd":
        floor = 1e-4 if eps_small else 1e-1
        eps = torch.where(det > 0, torch.zeros_like(det), floor - det)
        H = te._sd_derivatives(j, eps, True)[2]
        got = te._sd_hessian_psd(J, eps)
    else:
        eps = torch.tensor(1e-3 if eps_small else 0.3, dtype=torch.float64)
        H = te._untangling_derivatives(j, eps, True)[2]
        got = te._untangling_hessian_psd(J, eps)
    ref = te._project_psd(H.clone())
    scale = ref.abs().amax((1, 2))
    assert ((got - ref).abs().amax((1, 2)) / scale).max() < 1e-6
    assert (got - got.transpose(1, 2)).abs().max() <= 1e-12 * scale.max()
    assert (torch.linalg.eigvalsh(got) >= -1e-10 * scale[:, None]).all()
    pd = torch.linalg.cholesky_ex(0.5 * (H + H.transpose(1, 2)))[1] == 0
    assert pd.any() and (~pd).any()  # both kinds of block are exercised
    assert ((got[pd] - H[pd]).abs().amax((1, 2)) / scale[pd]).max() < 1e-10


def test_public_terms_use_the_projected_hessian_and_raise_on_overflow():
    from torchconn.hexmesh import tet_energies as te

    J = _jacobians_with_hard_cases(50, 12)
    det = torch.linalg.det(J)
    eps = torch.where(det > 0, torch.zeros_like(det), 1e-2 - det)
    f, g, H = te.barrier_terms(J, eps, 0.5, 2.0)
    ref = 2.0 * te._project_psd(te._sd_derivatives(J.reshape(-1, 9), eps, True)[2]) + torch.eye(9, dtype=J.dtype)
    assert torch.allclose(H, ref, rtol=1e-8, atol=1e-8 * float(ref.abs().max()))
    assert te.barrier_terms(J, eps, 0.5, 2.0, hessian=False)[2] is None
    flat = torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64))[None]
    with pytest.raises(FloatingPointError, match="nearly flat"):
        te.barrier_terms(flat, torch.zeros(1, dtype=torch.float64), 1.0, 1.0)
