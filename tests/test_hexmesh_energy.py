"""The seamless map's fitting energy as a differentiable function of the frames (torchconn.hexmesh.energy).

* the value equals the continuous optimum of ``SeamlessProblem.energy_matrices`` by a direct solve,
  and the ``energy_continuous`` of ``integer_grid_map`` on the same structure; at other rotations
  it equals the problem rebuilt from them with the structure held;
* ``gradcheck`` / ``gradgradcheck`` in float64 on ``box(2)`` and on the one-layer valence-3 prism,
  per-tet and per-vertex frames (a constant field included: the smooth per-tet projection);
* known answers: 0 for the identity field on a box (``h`` dividing it or not: the integers are
  relaxed); lower after smoothing a noisy field; the gradient of a globally rotated box field
  turns it back;
* one solve per evaluation *and* its backward; float32 in, float32 out;
* errors.

Cost: about 3 s (48 to 180 tets). The cost on HexMe meshes is measured by the slow test.
"""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch

from torchconn import io, so3
from torchconn.frames import octahedral
from torchconn.frames.design import design
from torchconn.frames.octahedral import tet_frames
from torchconn.hexmesh import integer_grid_map, tet_charts
from torchconn.hexmesh.cut import face_matchings
from torchconn.hexmesh.energy import MapEnergy, smooth_tet_frames
from torchconn.hexmesh.seamless import build_problem
from test_hexmesh_map import axis_prism

F64 = torch.float64


def _noisy(n: int, scale: float, seed: int) -> torch.Tensor:
    return so3.exp(scale * torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=F64))


def _identity(n: int) -> torch.Tensor:
    return torch.eye(3, dtype=F64).expand(n, 3, 3).clone()


def _reference(problem) -> tuple[float, np.ndarray]:
    """The continuous optimum by a direct sparse solve of the problem's normal equations."""
    A, b, c = problem.energy_matrices()
    y = spla.spsolve(A.tocsc(), b)
    return float(c - b @ y) / float(problem.vol.sum()), y


@pytest.fixture(scope="module")
def box2():
    mesh = io.box(2)
    return mesh, _noisy(mesh.n_tets, 0.2, 0)


@pytest.fixture(scope="module")
def prism():
    mesh, frames = axis_prism(n_layers=1, turns=4)  # valence-3 axis
    return mesh, frames


# ----------------------------------------------------------------------------- values
@pytest.mark.parametrize("case", ["box2", "prism"])
def test_value_equals_direct_solve_and_the_maps_continuous_energy(case, request):
    mesh, frames = request.getfixturevalue(case)
    energy = MapEnergy(mesh, frames, edge_length=0.5)
    ref, y = _reference(energy.problem)
    assert ref > 1e-3  # not a trivial case
    assert float(energy(frames)) == pytest.approx(ref, rel=1e-12, abs=1e-14)
    # the lead's pipeline on the same structure (no straightening, no splits): same continuous optimum
    igm = integer_grid_map(mesh, frames, edge_length=0.5, straighten=False, repair=False, split=False,
                           relocate=False, stiffening_iters=0)
    assert float(energy(frames)) == pytest.approx(igm.energy_continuous, rel=1e-10, abs=1e-13)
    # the optimal map itself
    np.testing.assert_allclose(energy.corner_params(frames).numpy(), energy.problem.corner_params(y),
                               rtol=1e-10, atol=1e-12)
    if case == "prism":
        assert energy.charts.counts()["valence3_edges"] == 1  # the constrained singular edge is there


def test_value_at_other_rotations_equals_the_rebuilt_problem(prism):
    mesh, frames0 = prism
    energy = MapEnergy(mesh, frames0, edge_length=0.4)
    frames1 = frames0 @ _noisy(mesh.n_tets, 0.02, 1)  # about a degree off the start field
    charts1 = tet_charts(mesh, frames1, face_matchings(mesh, frames0))
    prob1 = build_problem(mesh, charts1, 0.4)
    # the same structure (otherwise the comparison would be of two different problems)
    np.testing.assert_array_equal(charts1.comb, energy.charts.comb)
    np.testing.assert_array_equal(charts1.cut, energy.charts.cut)
    np.testing.assert_array_equal(prob1.boundary_axis, energy.problem.boundary_axis)
    np.testing.assert_array_equal(prob1.feature_constrained, energy.problem.feature_constrained)
    ref, _ = _reference(prob1)
    assert float(energy(frames1)) == pytest.approx(ref, rel=1e-11)
    assert abs(ref - float(energy(frames0))) > 1e-3


def test_identity_box_has_zero_energy_and_a_rotated_one_does_not():
    mesh = io.box(2)
    eye = _identity(mesh.n_tets)
    for h in (0.5, 0.25, 0.3):  # 0.3 does not divide the box: no matter, the integers are relaxed
        energy = MapEnergy(mesh, eye, edge_length=h)
        assert abs(float(energy(eye))) < 1e-13
    R = so3.exp(torch.tensor([0.1, 0.0, 0.0], dtype=F64)).expand(mesh.n_tets, 3, 3)
    assert float(energy(R)) > 1e-3


def test_smoothing_a_noisy_field_lowers_the_energy():
    mesh = io.box(3)
    w = 0.1 * torch.randn(mesh.n_tets, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    energy = MapEnergy(mesh, so3.exp(w), edge_length=1 / 3)
    # noise small enough to leave the structure regular (at 0.2 rad this seed has 10 singular edges,
    # which stay frozen into the problem whatever the frames do)
    assert energy.charts.counts()["singular_edges"] == 0
    # Jacobi smoothing of the rotation vectors over the dual graph (tets across interior faces)
    ft = mesh.face_tets
    inner = (ft >= 0).all(1)
    a, b = ft[inner, 0], ft[inner, 1]
    values = [float(energy(so3.exp(w)))]
    for _ in range(3):
        acc = w.clone().index_add(0, a, w[b]).index_add(0, b, w[a])
        deg = torch.ones(mesh.n_tets, dtype=F64).index_add(0, a, torch.ones_like(a, dtype=F64)).index_add(
            0, b, torch.ones_like(b, dtype=F64))
        w = acc / deg[:, None]
        values.append(float(energy(so3.exp(w))))
    assert all(v1 < v0 for v0, v1 in zip(values, values[1:])), values
    assert values[-1] < 0.5 * values[0]


def test_gradient_of_a_globally_rotated_box_field_turns_it_back():
    mesh = io.box(2)
    energy = MapEnergy(mesh, _identity(mesh.n_tets), edge_length=0.5)
    axis = torch.tensor([1.0, 2.0, 3.0], dtype=F64) / math.sqrt(14.0)
    F = so3.exp(0.2 * axis).expand(mesh.n_tets, 3, 3).clone().requires_grad_()
    (g,) = torch.autograd.grad(energy(F), F)
    # the gradient in the Lie algebra of a global rotation F -> exp(hat(v)) F: v = sum_t vee(G_t F_t^T - F_t G_t^T)/...
    M = (g @ F.detach().transpose(1, 2)).sum(0)
    v = torch.stack([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    assert float(v @ axis) > 0.9 * float(v.norm())  # uphill is further along the rotation
    step = so3.exp(-0.05 * v / v.norm())
    F1 = step @ F.detach()
    assert float(energy(F1)) < float(energy(F.detach()))
    angle = lambda X: float(so3.log(X[0]).norm())  # noqa: E731  (all tets share the rotation)
    assert angle(F1) < angle(F.detach())


# ----------------------------------------------------------------------------- derivatives
def test_gradcheck_and_gradgradcheck_box(box2):
    mesh, frames = box2
    energy = MapEnergy(mesh, frames, edge_length=0.5)
    F = frames.clone().requires_grad_()
    assert torch.autograd.gradcheck(energy, (F,))
    assert torch.autograd.gradgradcheck(energy, (F,), fast_mode=True)
    assert torch.autograd.gradcheck(energy.corner_params, (F,), fast_mode=True)


def test_gradcheck_and_gradgradcheck_prism(prism):
    mesh, frames = prism
    energy = MapEnergy(mesh, frames, edge_length=0.4)
    F = frames.clone().requires_grad_()
    assert torch.autograd.gradcheck(energy, (F,), fast_mode=True)
    assert torch.autograd.gradgradcheck(energy, (F,), fast_mode=True)


@pytest.mark.parametrize("scale", [0.0, 0.2])  # 0: a constant field, every tet's vertex frames agree
def test_vertex_frames_path_is_differentiable(scale):
    mesh = io.box(1)
    base = so3.exp(torch.tensor([0.3, -0.2, 0.5], dtype=F64))
    vf = base @ _noisy(mesh.n_vertices, scale, 3) if scale else base.expand(mesh.n_vertices, 3, 3).clone()
    energy = MapEnergy.from_vertex_frames(mesh, vf, edge_length=0.5)
    matchings = octahedral.match_edges(vf, mesh.edges)[0]
    assert torch.equal(energy.edge_matchings, matchings)
    # the smooth per-tet rule has the values of tet_frames
    torch.testing.assert_close(smooth_tet_frames(vf, mesh, matchings), tet_frames(vf, mesh, matchings),
                               rtol=0, atol=1e-12)
    assert float(energy.of_vertex_frames(vf)) == pytest.approx(float(energy(tet_frames(vf, mesh))), abs=1e-13)
    V = vf.clone().requires_grad_()
    assert torch.autograd.gradcheck(energy.of_vertex_frames, (V,))
    assert torch.autograd.gradgradcheck(energy.of_vertex_frames, (V,), fast_mode=True)


def test_one_solve_per_evaluation_with_its_backward(box2):
    mesh, frames = box2
    energy = MapEnergy(mesh, frames, edge_length=0.5)
    fac = energy.solver._factors[0]
    calls = []
    real = fac.solve
    fac.solve = lambda b: (calls.append(1), real(b))[1]
    F = frames.clone().requires_grad_()
    for k in range(1, 4):
        energy(F).backward()
        assert len(calls) == k


def test_float32_frames():
    mesh = io.box(2)
    frames = _noisy(mesh.n_tets, 0.2, 4)
    energy = MapEnergy(mesh, frames, edge_length=0.5)
    F32 = frames.float().requires_grad_()
    e32 = energy(F32)
    assert e32.dtype == torch.float32
    # float64 inside: only the float32 rounding of the frames and of the result remain
    assert e32.item() == pytest.approx(energy(F32.detach().double()).item(), rel=2e-7)
    e32.backward()
    assert F32.grad.dtype == torch.float32 and torch.isfinite(F32.grad).all()


# ----------------------------------------------------------------------------- errors
def test_errors():
    mesh = io.box(1)
    eye = _identity(mesh.n_tets)
    with pytest.raises(ValueError, match=r"must have shape \(6, 3, 3\)"):
        MapEnergy(mesh, eye[:5])
    with pytest.raises(ValueError, match="must be rotations"):
        MapEnergy(mesh, 1.1 * eye)
    with pytest.raises(ValueError, match="edge_length"):
        MapEnergy(mesh, eye, edge_length=-1.0)
    energy = MapEnergy(mesh, eye, edge_length=0.5)
    with pytest.raises(ValueError, match="CPU"):
        energy(eye.to("meta"))
    with pytest.raises(ValueError, match=r"must have shape \(6, 3, 3\)"):
        energy(eye[:, :2])
    with pytest.raises(ValueError, match="from_vertex_frames"):
        energy.of_vertex_frames(_identity(mesh.n_vertices))


# ----------------------------------------------------------------------------- cost (slow)
@pytest.mark.slow
@pytest.mark.parametrize("name", ["s05c_cube_sphere", "i02c_m2"])
def test_cost_on_hexme(name):
    """Builds the energy of the SH field of a HexMe ``c`` mesh, prints the construction and per-call
    costs, and checks the gradient along a random rotation of every frame against a central
    difference of the value."""
    pytest.importorskip("gmsh", reason="the HexMe meshes are made by gmsh (torchconn[cad])")
    from benchmarks.frames_hexme import load_case

    try:
        mesh = load_case("hexme", name)
    except FileNotFoundError as exc:
        pytest.skip(f"HexMe data missing: {exc}")
    frames = design(mesh, method="sh").tet_frames.to(F64)
    energy = MapEnergy(mesh, frames)
    F = frames.clone().requires_grad_()

    def best(fn, n=5):
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
        return 1e3 * min(out)

    fwd = best(lambda: energy(frames))
    fwd_bwd = best(lambda: energy(F).backward())
    print(f"\n{name}: {mesh.n_tets} tets, {energy.n_unknowns} unknowns, build {energy.timings['total_s']:.2f} s "
          f"({ {k: round(v, 3) for k, v in energy.timings.items()} }), forward {fwd:.1f} ms, forward+backward "
          f"{fwd_bwd:.1f} ms, load {open('/proc/loadavg').read().split()[0]}")
    omega = torch.randn(mesh.n_tets, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    (g,) = torch.autograd.grad(energy(F), F)
    eps = 1e-5
    fd = (float(energy(frames @ so3.exp(eps * omega))) - float(energy(frames @ so3.exp(-eps * omega)))) / (2 * eps)
    assert float((g * (frames @ so3.hat(omega))).sum()) == pytest.approx(fd, rel=1e-6)
