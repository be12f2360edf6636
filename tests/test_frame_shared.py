"""The shared frame-field pieces: boundary constraint, constrained parametrization, schedule,
edge matching, matched connection and the solver loop, against plain references."""
from __future__ import annotations

import math

import pytest
import torch

from torchconn import io, so3
from torchconn.frames import octahedral, sh
from torchconn.frames.constraints import BoundaryConstraint
from torchconn.frames.loss import FrameFieldLoss
from torchconn.frames.constraints import boundary_face_normals, feature_vertices
from torchconn.frames.model import FrameFieldModel, matched_connection
from torchconn.frames.param import constrained_frames, constrained_rotation_vector
from torchconn.frames.solver import (NonFiniteLossError, cosine_factor, make_optimizer, new_history,
                                     optimize)


@pytest.fixture(scope="module")
def cyl():
    """A small cylinder: curved side wall, flat caps, two sharp rims (feature vertices)."""
    return io.cylinder(edge_length=0.6).to(dtype=torch.float64)


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(7)


# ----------------------------------------------------------------------------- constraint
def _reference_constraint(mesh, angle):
    """The per-module computation the constraint replaced (one vertex/face at a time)."""
    V = mesh.vertices.shape[0]
    fv = set(feature_vertices(mesh, angle).tolist())
    normals = torch.zeros(V, 3, dtype=mesh.vertices.dtype)
    constrained = torch.zeros(V, dtype=torch.bool)
    align_v, align_n = [], []
    for b, v in enumerate(mesh.boundary_vertices.tolist()):
        normals[v] = mesh.boundary_vertex_normals[b]
        if v not in fv:
            constrained[v] = True
            align_v.append(v)
            align_n.append(mesh.boundary_vertex_normals[b])
    nf = boundary_face_normals(mesh)
    pair_v, pair_f, pair_n = [], [], []
    for f, face in enumerate(mesh.boundary_faces.tolist()):
        for v in face:
            if v in fv:
                pair_v.append(v)
                pair_f.append(f)
                pair_n.append(nf[f])
    return fv, normals, constrained, align_v, torch.stack(align_n), pair_v, pair_f, torch.stack(pair_n)


@pytest.mark.parametrize("angle", [30.0, 60.0])
def test_constraint_equals_per_element_reference(cyl, angle):
    bc = BoundaryConstraint.from_mesh(cyl, angle)
    fv, normals, constrained, align_v, align_n, pair_v, pair_f, pair_n = _reference_constraint(cyl, angle)
    assert len(fv) > 0 and len(pair_v) > 0  # the rims are sharp: the test exercises both kinds
    assert bc.feature_angle_deg == angle
    assert bc.feature_vertices.tolist() == sorted(fv)
    assert bc.is_feature.nonzero().flatten().tolist() == sorted(fv)
    assert torch.equal(bc.normals, normals)
    assert torch.equal(bc.constrained, constrained)
    assert bc.align_vertices.tolist() == align_v
    assert torch.equal(bc.align_normals, align_n)
    assert bc.pair_vertices.tolist() == pair_v and bc.pair_faces.tolist() == pair_f
    assert torch.equal(bc.pair_normals, pair_n)


def test_constraint_is_built_once_and_follows_dtype(cyl):
    a = BoundaryConstraint.from_mesh(cyl, 30.0)
    assert BoundaryConstraint.from_mesh(cyl, 30.0) is a
    assert BoundaryConstraint.from_mesh(cyl, 45.0) is not a
    m32 = cyl.to(dtype=torch.float32)
    b = BoundaryConstraint.from_mesh(m32, 30.0)
    assert b is not a and b.normals.dtype == torch.float32 and b.pair_normals.dtype == torch.float32
    assert torch.equal(b.constrained, a.constrained)
    # the loss reads the same object
    loss = FrameFieldLoss(cyl, {"align": 1.0, "feature": 1.0}, feature_angle_deg=30.0)
    assert loss.constraint is a


# ----------------------------------------------------------------------------- parametrization
def test_constrained_frames_keep_the_axis_on_the_normal(cyl, gen):
    bc = BoundaryConstraint.from_mesh(cyl)
    F0 = sh.sh_frame_field(cyl, n_smooth_iters=0)  # aligned: an axis is +-n at constrained vertices
    con = bc.constrained
    w = (0.8 * torch.randn(F0.shape[0], 3, generator=gen, dtype=torch.float64)).requires_grad_()
    F = constrained_frames(w, F0, con, bc.normals)
    so3.check_rotation(F.detach())
    c = (F[con] * bc.normals[con][:, :, None]).sum(-2).abs().max(-1).values  # max_k |F_k . n|
    assert torch.allclose(c, torch.ones_like(c), atol=1e-12, rtol=0)
    # unconstrained vertices take the full rotation vector
    assert torch.allclose(F[~con], so3.exp(w[~con]) @ F0[~con], atol=1e-14, rtol=0)
    # the gradient at a constrained vertex is along its normal
    F.sum().backward()
    g = w.grad[con]
    along = (g * bc.normals[con]).sum(-1, keepdim=True) * bc.normals[con]
    assert torch.allclose(g, along, atol=1e-12, rtol=0)
    wp = constrained_rotation_vector(w.detach(), con, bc.normals)
    assert torch.equal(wp[~con], w.detach()[~con])


# ----------------------------------------------------------------------------- schedule
def test_cosine_factor_values():
    assert cosine_factor(0, 10) == 1.0
    assert cosine_factor(5, 10) == pytest.approx(0.5, abs=1e-15)
    assert cosine_factor(10, 10) == 0.0 and cosine_factor(15, 10) == 0.0
    assert cosine_factor(2, 8) == pytest.approx(0.5 * (1 + math.cos(math.pi / 4)), abs=1e-15)
    assert cosine_factor(0, 0) == 1.0 and cosine_factor(1, 0) == 0.0  # steps < 1 counts as 1


@pytest.mark.parametrize("schedule", ["cosine", "constant"])
def test_make_optimizer_follows_the_schedule(schedule):
    p = torch.nn.Parameter(torch.zeros(3))
    opt, sched = make_optimizer([p], "adam", lr=0.2, steps=4, schedule=schedule)
    lrs = []
    for _ in range(5):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    want = [0.2 * (cosine_factor(s, 4) if schedule == "cosine" else 1.0) for s in range(5)]
    assert lrs == pytest.approx(want, abs=1e-15)
    with pytest.raises(ValueError, match="optim"):
        make_optimizer([p], "sgd")


# ----------------------------------------------------------------------------- matching
def _match_edges_naive(frames, edges):
    """Per edge, the first element minimizing ||F_i g - F_j||_F."""
    G = octahedral.group(frames.dtype)
    out = []
    for i, j in edges.tolist():
        d = [float(torch.linalg.norm(frames[i] @ G[k] - frames[j])) for k in range(24)]
        best = min(d)
        out.append(next(k for k in range(24) if d[k] <= best + 1e-12))
    return torch.tensor(out)


def test_match_edges_equals_per_edge_reference(cyl, gen):
    F = so3.random_rotation(cyl.n_vertices, generator=gen, dtype=torch.float64)
    idx, g = octahedral.match_edges(F, cyl.edges)
    assert idx.shape == (cyl.n_edges,) and g.shape == (cyl.n_edges, 3, 3)
    assert torch.equal(idx, _match_edges_naive(F, cyl.edges))
    assert torch.equal(g, octahedral.group(torch.float64)[idx])
    assert torch.equal(g, octahedral.matched_rotations(F, cyl.edges))
    # the reverse direction is the transpose
    _, g_rev = octahedral.match_edges(F, cyl.edges.flip(1))
    assert torch.equal(g_rev, g.transpose(-1, -2))


def test_matched_connection_transports_onto_the_cross_frame(cyl, gen):
    F = so3.random_rotation(cyl.n_vertices, generator=gen, dtype=torch.float64)
    R = matched_connection(F, cyl.edges)
    Fi, Fj = F[cyl.edges[:, 0]], F[cyl.edges[:, 1]]
    G = octahedral.group(torch.float64)
    # F_i R_ij = F_j h_ij with h_ij in O, and R_ij is the residual closest to I
    h = Fj.transpose(-1, -2) @ Fi @ R
    _, hg = octahedral.closest_element(h)
    assert torch.allclose(h, hg, atol=1e-12, rtol=0)
    eye = torch.eye(3, dtype=torch.float64)
    d = ((Fi.transpose(-1, -2) @ Fj @ G[:, None] - eye) ** 2).sum((-2, -1)).min(0).values  # over h in O
    assert torch.allclose(((R - eye) ** 2).sum((-2, -1)), d, atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- solver
def test_optimize_lowers_the_loss_and_records_the_history(cyl):
    bc = BoundaryConstraint.from_mesh(cyl)
    F0 = sh.sh_frame_field(cyl, n_smooth_iters=0)
    weights = {"smooth": 1.0, "tie": 2.0, "align": 10.0, "feature": 1.0}
    loss = FrameFieldLoss(cyl, weights, smooth_power=1.0, align_kind="angle")
    model = FrameFieldModel(cyl, F0, "vertex", bc)
    opt, sched = make_optimizer(model.parameters(), "adam", lr=0.02, steps=20)
    seen = []
    with torch.no_grad():
        before = float(loss(*model())["total"])
    hist = optimize(model, loss, opt, sched, 20, on_step=lambda s, rec: seen.append(s))
    with torch.no_grad():
        after = float(loss(*model())["total"])
    assert seen == list(range(1, 21))
    assert set(hist) == set(new_history(loss.weights)) == {"smooth", "tie", "align", "feature", "total"}
    assert all(len(v) == 20 for v in hist.values())
    assert after < before


def test_optimize_stops_on_a_non_finite_term(cyl):
    bc = BoundaryConstraint.from_mesh(cyl)
    model = FrameFieldModel(cyl, sh.sh_frame_field(cyl, n_smooth_iters=0), "vertex", bc)
    opt, sched = make_optimizer(model.parameters(), "adam", lr=0.02, steps=3)

    def bad(R, F):
        v = R.sum() * float("nan")
        return {"smooth": v, "total": v}

    bad.weights = {"smooth": 1.0}
    with pytest.raises(NonFiniteLossError, match="'smooth'.*step 0"):
        optimize(model, bad, opt, sched, 3)
