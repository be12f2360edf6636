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


def test_the_map_follows_the_field_re_optimized_with_its_matchings():
    """The map stage's ``fixed_holonomy``: where the matchings it follows are not the frames' best
    ones (here the zipped hairpin's, given), the frames are re-optimized with them fixed and the
    map fits those; the returned field's own matchings are the map's, and it fits them better."""
    from torchconn.hexmesh import hex_mesh

    mesh, F, (p, q, v) = hairpin()
    fm, _ = zip_zipper(mesh, F, None, v)
    on = hex_mesh(mesh, F, face_match=fm, extract=False, quality=False, one_ring=False)
    off = hex_mesh(mesh, F, face_match=fm, extract=False, quality=False, one_ring=False, fixed_holonomy=False)
    st = on.map.stats["fixed_holonomy"]
    assert st["free_tets"] > 0 and st["agree"] == 1.0 and st["misfit_deg_after"] < st["misfit_deg_before"]
    assert off.map.stats.get("fixed_holonomy") is None  # off: the input's frames, a child tet with its parent's
    torch.testing.assert_close(off.map.tet_frames, F[torch.as_tensor(off.map.parent_tet)], atol=0, rtol=0)
    assert not torch.allclose(on.map.tet_frames, off.map.tet_frames)
    # the charts carry the new field, combed as before (same cut and transitions)
    np.testing.assert_array_equal(on.map.charts.comb, off.map.charts.comb)
    np.testing.assert_array_equal(on.map.charts.face_rot, off.map.charts.face_rot)
    assert not np.allclose(on.map.charts.frames, off.map.charts.frames)
    assert on.map.energy_continuous < off.map.energy_continuous
