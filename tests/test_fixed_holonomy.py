"""The tet frame field re-optimized by its dual connection with the face matchings fixed
(torchconn.frames.fixed_holonomy): gradients in float64, the start at the input frames, the
returned field's own singular graph equal to the repaired one, bad input."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import io, so3
from torchconn.frames.fixed_holonomy import FixedHolonomyField, fixed_holonomy_frames, free_region
from torchconn.hexmesh.cut import face_matchings, tet_charts
from torchconn.hexmesh.meshability import meshability_report
from torchconn.hexmesh.repair import zip_zipper

from test_hexmesh_meshability import hairpin


def _random_case(seed=0):
    mesh = io.box(1)
    gen = torch.Generator().manual_seed(seed)
    F = so3.exp(0.3 * torch.randn(mesh.n_tets, 3, generator=gen, dtype=torch.float64))
    rng = np.random.default_rng(seed)
    fm = face_matchings(mesh, F)
    inner = np.nonzero((mesh.face_tets.numpy() >= 0).all(1))[0]
    fm[inner[:2]] = rng.integers(1, 24, 2)  # two faces relabeled: a connection far from the frames
    return mesh, F, fm


def test_field_starts_at_the_input_frames_and_is_differentiable():
    mesh, F, fm = _random_case()
    model = FixedHolonomyField(mesh, F, fm)  # every tet free
    R, Fo = model()
    torch.testing.assert_close(Fo, F, atol=1e-12, rtol=0)  # the matched connection propagates the input
    # the matched connection holds F_a R = F_b G[h]^T exactly; R is a rotation
    G = model.Gh
    a, b = model.dual_edges[:, 0], model.dual_edges[:, 1]
    res = (Fo[a] @ R - Fo[b] @ G.transpose(-1, -2)).abs().amax((-2, -1))
    assert res.max() < 1e-12
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=R.dtype).expand_as(R), atol=1e-12, rtol=0)

    # gradcheck of the propagated frames and the connection in their parameters (float64)
    omega0 = (model.connection.params.detach() + 0.05).requires_grad_()
    w0 = torch.full_like(model.w, 0.1).requires_grad_()

    def fwd(omega, w):
        R_, F_ = torch.func.functional_call(model, {"connection.params": omega, "w": w}, ())
        return (F_ ** 3).sum() + (R_ ** 3).sum()

    assert torch.autograd.gradcheck(fwd, (omega0, w0))


def test_repaired_hairpin_field_has_the_repaired_singular_graph():
    mesh, F, (p, q, v) = hairpin()
    assert meshability_report(mesh, F).zipper_nodes.tolist() == [v]
    fm, mv = zip_zipper(mesh, F, None, v)
    changed = np.nonzero(fm != face_matchings(mesh, F))[0]
    assert changed.size >= 1  # the frames alone no longer give these matchings
    res = fixed_holonomy_frames(mesh, F, fm, steps=30, lr=0.05, weights={"align": 0.0})
    assert res.agree == 1.0 and 0 < res.free_tets < mesh.n_tets
    free = free_region(mesh, F, fm, 4)
    torch.testing.assert_close(res.tet_frames[~torch.as_tensor(free)], F[~torch.as_tensor(free)], atol=0, rtol=0)
    assert (face_matchings(mesh, res.tet_frames) == fm)[(mesh.face_tets.numpy() >= 0).all(1)].all()
    m = meshability_report(mesh, res.tet_frames)  # the field's own singular graph: the repaired one
    assert m.zipper_nodes.size == 0 and m.meshable
    assert (tet_charts(mesh, res.tet_frames).edge_holonomy > 0).sum() == (tet_charts(mesh, F, fm).edge_holonomy > 0).sum()
    assert res.misfit_deg_after < res.misfit_deg_before
    assert res.history[-1]["total"] < res.history[0]["total"]


def test_bad_input_is_a_clear_error():
    mesh, F, fm = _random_case()
    with pytest.raises(ValueError, match="face_match"):
        fixed_holonomy_frames(mesh, F, fm[:-1])
    with pytest.raises(ValueError, match="tet_frames"):
        fixed_holonomy_frames(mesh, F[:-1], fm)
    with pytest.raises(ValueError, match="unknown weights"):
        fixed_holonomy_frames(mesh, F, fm, weights={"flat": 1.0})
    with pytest.raises(ValueError, match="steps"):
        fixed_holonomy_frames(mesh, F, fm, steps=-1)
