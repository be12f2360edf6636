"""Frame-field losses (torchconn.frames.loss) and parallel frame propagation (torchconn.frames.propagate)."""
from __future__ import annotations

import math

import pytest
import torch

from torchconn import io as tio
from torchconn import so3
from torchconn.frames import octahedral
from torchconn.frames.propagate import comb_frames, propagate_frames, spanning_tree
from torchconn.frames.loss import (
    TERMS,
    FrameFieldLoss,
    axis_angle_loss,
    normal_alignment_loss,
    smoothness_loss,
    symmetric_flatness_loss,
    tie_loss,
)
from torchconn.mesh import TetMesh

D = torch.float64


@pytest.fixture(scope="module")
def box():
    return tio.box(n=2)


def _random_frames(V, gen):
    return so3.random_rotation(V, generator=gen, dtype=D)


# ----------------------------------------------------------------------------- single terms
def test_smoothness_is_chordal_angle(gen):
    w = torch.randn(50, 3, generator=gen, dtype=D)
    t = w.norm(dim=-1)
    val = smoothness_loss(so3.exp(w))
    assert torch.allclose(val, (8 * torch.sin(t / 2) ** 2).mean(), atol=1e-12)
    assert float(smoothness_loss(torch.eye(3, dtype=D).expand(4, 3, 3))) == 0.0


def test_tie_zero_for_matched_connection_and_label_invariant(box, gen):
    from torchconn.frames.model import matched_connection

    F = _random_frames(box.n_vertices, gen)
    R = matched_connection(F, box.edges)
    loss, unrel = tie_loss(R, F, box.edges)
    assert float(loss) < 1e-24
    # relabeling the frames by g_v in O is a gauge change R_ij -> g_i^T R_ij g_j: loss unchanged
    G = octahedral.group(D)
    g = G[torch.randint(0, 24, (box.n_vertices,), generator=gen)]
    i, j = box.edges.unbind(1)
    loss2, _ = tie_loss(g[i].transpose(-1, -2) @ R @ g[j], F @ g, box.edges)
    assert float(loss2) < 1e-24
    # a perturbed connection is penalized
    R2 = so3.exp(0.1 * torch.randn(box.n_edges, 3, generator=gen, dtype=D)) @ R
    assert float(tie_loss(R2, F, box.edges)[0]) > 1e-4
    assert unrel.dtype == torch.bool and unrel.shape == (box.n_edges,)


def test_symmetric_flatness_zero_on_group_positive_off(gen):
    G = octahedral.group(D)
    assert float(symmetric_flatness_loss(G)) == 0.0
    H = so3.exp(0.2 * torch.randn(24, 3, generator=gen, dtype=D)) @ G
    H.requires_grad_(True)
    val = symmetric_flatness_loss(H)
    val.backward()
    assert float(val.detach()) > 0 and torch.isfinite(H.grad).all()


def test_normal_alignment_values(gen):
    F = _random_frames(20, gen)
    assert float(normal_alignment_loss(F, F[:, :, 1])) < 1e-14  # axis 1 is the normal
    assert float(normal_alignment_loss(F, -F[:, :, 2])) < 1e-14  # sign does not matter
    n = F @ torch.full((20, 3, 1), 1 / math.sqrt(3), dtype=D)  # the worst direction
    assert abs(float(normal_alignment_loss(F, n[..., 0])) - 2.0 / 3.0) < 1e-12
    assert float(normal_alignment_loss(F[:0], n[:0, :, 0])) == 0.0


def test_axis_angle_loss_is_the_alignment_metric_angle(gen):
    """The angle form tracks frames.metrics.axis_alignment_angle (the fixed metric) within eps."""
    from torchconn.frames.metrics import axis_alignment_angle

    F = _random_frames(64, gen)
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=D), dim=-1)
    ref = axis_alignment_angle(F, n).mean()
    assert abs(float(axis_angle_loss(F, n, eps=1e-9)) - float(ref)) < 1e-7
    assert abs(float(axis_angle_loss(F, n, eps=1e-3)) - float(ref)) < 1e-3
    assert abs(float(axis_angle_loss(F, F[:, :, 1]))) < 1e-12  # aligned (either sign): 0
    assert abs(float(axis_angle_loss(F, -F[:, :, 2]))) < 1e-12
    assert float(axis_angle_loss(F[:0], n[:0])) == 0.0
    with pytest.raises(ValueError, match="eps"):
        axis_angle_loss(F, n, eps=0.0)


def test_axis_angle_loss_gradient_finite_at_alignment(gen):
    """Smoothed by eps: finite gradients at exact alignment, bounded by the angle's own (1 rad/rad)."""
    F0 = _random_frames(16, gen)
    n = F0[:, :, 0].clone()
    w = torch.zeros(16, 3, dtype=D, requires_grad=True)
    axis_angle_loss(so3.exp(w) @ F0, n).backward()
    assert torch.isfinite(w.grad).all() and float(w.grad.abs().max()) < 1e-9  # a minimum: zero gradient
    w2 = (1e-2 * torch.randn(16, 3, generator=gen, dtype=D)).requires_grad_(True)
    (axis_angle_loss(so3.exp(w2) @ F0, n) * 16).backward()
    assert torch.isfinite(w2.grad).all() and float(w2.grad.norm(dim=-1).max()) <= 1.0 + 1e-9


# ----------------------------------------------------------------------------- FrameFieldLoss
def test_frame_field_loss_terms_and_total(box, gen):
    from torchconn.frames.model import matched_connection

    w = {"smooth": 1.0, "tie": 2.0, "flat": 0.5, "torsion": 0.1, "dnabla": 0.2, "align": 3.0, "feature": 4.0,
         "dirichlet": 0.5}
    lf = FrameFieldLoss(box, w)
    F = _random_frames(box.n_vertices, gen)
    R = matched_connection(F, box.edges)
    out = lf(R, F)
    assert set(out) == set(TERMS) | {"total"}
    total = sum(w[k] * out[k] for k in TERMS)
    assert torch.allclose(out["total"], total)
    assert all(torch.isfinite(v) for v in out.values())


def test_torsion_runs_through_the_matchings_on_every_face(box, gen):
    """Relabeling the frames vertex by vertex (F_v g_v, g_v in O) changes the matchings, not the
    field: the torsion through the matchings is the same (the unrelabeled-faces mean was not)."""
    from torchconn.frames.model import matched_connection

    lf = FrameFieldLoss(box, {"torsion": 1.0})
    Q = so3.exp(0.2 * torch.randn(box.n_vertices, 3, generator=gen, dtype=D))
    F = Q @ so3.exp(torch.tensor([[0.3, -0.2, 0.1]], dtype=D))  # a smooth-ish field
    R = so3.exp(0.05 * torch.randn(box.n_edges, 3, generator=gen, dtype=D)) @ matched_connection(F, box.edges)
    g = octahedral.group(D)[torch.randint(0, 24, (box.n_vertices,), generator=gen)]
    Fg = F @ g
    e = box.edges
    # the same connection, expressed against the relabeled frames: R'_ij = g_i^T R_ij g_j
    Rg = g[e[:, 0]].transpose(-1, -2) @ R @ g[e[:, 1]]
    a, b = lf(R, F)["torsion"], lf(Rg, Fg)["torsion"]
    assert float(a) > 1e-6 and torch.allclose(a, b, rtol=1e-10, atol=0)


def test_dnabla_term_zero_when_flat_positive_when_curved_and_masks_singular_tets(box, gen):
    from torchconn.frames.model import matched_connection

    lf = FrameFieldLoss(box, {"dnabla": 1.0})
    F = torch.eye(3, dtype=D).expand(box.n_vertices, 3, 3).clone()
    R = matched_connection(F, box.edges)
    assert float(lf(R, F)["dnabla"]) < 1e-28
    Rc = so3.exp(0.1 * torch.randn(box.n_edges, 3, generator=gen, dtype=D))
    val = lf(Rc, F)["dnabla"]
    assert float(val) > 1e-6
    # a quarter turn on one edge makes the tets around it singular: they leave the mean
    Rs = Rc.clone()
    Rs[0] = so3.exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=D)) @ Rs[0]
    assert torch.isfinite(lf(Rs, F)["dnabla"])


@pytest.mark.parametrize("term", ["torsion", "dnabla"])
def test_new_terms_gradgradcheck(gen, term):
    cube = tio.box(n=1)
    lf = FrameFieldLoss(cube, {term: 1.0})
    p = (0.2 * torch.randn(cube.n_edges, 3, generator=gen, dtype=D)).requires_grad_(True)
    w = (0.2 * torch.randn(cube.n_vertices, 3, generator=gen, dtype=D)).requires_grad_(True)
    F0 = _random_frames(cube.n_vertices, gen)
    fn = lambda p, w: lf(so3.exp(p), so3.exp(w) @ F0)[term]  # noqa: E731
    assert torch.autograd.gradcheck(fn, (p, w), eps=1e-7, atol=1e-5, fast_mode=True)
    assert torch.autograd.gradgradcheck(fn, (p, w), eps=1e-6, atol=1e-4, fast_mode=True)


def test_frame_field_loss_rejects_bad_weights(box):
    with pytest.raises(KeyError, match="smoth"):
        FrameFieldLoss(box, {"smoth": 1.0})
    with pytest.raises(ValueError, match="tie"):
        FrameFieldLoss(box, {"tie": -1.0})
    with pytest.raises(ValueError, match="align_kind"):
        FrameFieldLoss(box, {"align": 1.0}, align_kind="cubic")
    with pytest.raises(ValueError, match="align_eps"):
        FrameFieldLoss(box, {"align": 1.0}, align_kind="angle", align_eps=0.0)


@pytest.mark.parametrize("power,align_kind", [(2.0, "quartic"), (1.0, "quartic"), (1.0, "angle")])
def test_frame_field_loss_gradcheck(gen, power, align_kind):
    cube = tio.box(n=1)
    lf = FrameFieldLoss(cube, {k: 1.0 for k in TERMS}, smooth_power=power, align_kind=align_kind)
    p = (0.3 * torch.randn(cube.n_edges, 3, generator=gen, dtype=D)).requires_grad_(True)
    w = (0.3 * torch.randn(cube.n_vertices, 3, generator=gen, dtype=D)).requires_grad_(True)
    F0 = _random_frames(cube.n_vertices, gen)
    # the O-matching choices are piecewise constant; gradcheck with a small step stays on one piece
    assert torch.autograd.gradcheck(lambda p, w: lf(so3.exp(p), so3.exp(w) @ F0)["total"], (p, w),
                                    eps=1e-7, atol=1e-5, fast_mode=True)


@pytest.mark.parametrize("align_kind", ["quartic", "angle"])
def test_boundary_terms_vanish_for_aligned_box_frames(box, align_kind):
    """Identity frames on a box are aligned with every face: align and feature terms are 0."""
    lf = FrameFieldLoss(box, {"align": 1.0, "feature": 1.0, "smooth": 1.0, "flat": 1.0}, align_kind=align_kind)
    F = torch.eye(3, dtype=D).expand(box.n_vertices, 3, 3)
    R = torch.eye(3, dtype=D).expand(box.n_edges, 3, 3)
    out = lf(R, F)
    for k in ("align", "feature", "smooth", "flat"):
        assert float(out[k]) < 1e-24, k


# ----------------------------------------------------------------------------- propagation
def _reference_propagation(edge_rot, mesh, tree, root_frames):
    """Slow per-vertex reference: walk up to the root for every vertex."""
    V = mesh.n_vertices
    parent = tree.parent.tolist()
    roots = tree.roots.tolist()
    out = []
    for v in range(V):
        path = [v]
        while parent[path[-1]] >= 0:
            path.append(parent[path[-1]])
        F = root_frames[roots.index(path[-1])]
        for a, b in zip(reversed(path[1:]), reversed(path[:-1])):  # parent a -> child b
            e, s = mesh.edge_index(torch.tensor(a), torch.tensor(b))
            R = edge_rot[e] if int(s) > 0 else edge_rot[e].T
            F = F @ R
        out.append(F)
    return torch.stack(out)


def test_spanning_tree_structure(box):
    tree = spanning_tree(box)
    V = box.n_vertices
    assert tree.roots.numel() == 1
    assert int(tree.tree_edge.sum()) == V - 1
    covered = torch.cat([tree.roots] + [lv.child for lv in tree.levels])
    assert torch.equal(covered.sort().values, torch.arange(V))
    for d, lv in enumerate(tree.levels, start=1):
        assert (tree.depth[lv.child] == d).all() and (tree.depth[lv.parent] == d - 1).all()
        e = box.edges[lv.edge]
        assert torch.equal(e.min(1).values, torch.minimum(lv.child, lv.parent))
        assert torch.equal(e.max(1).values, torch.maximum(lv.child, lv.parent))
    # BFS: every vertex is at its graph distance from the root (corner-to-corner on a 2x2x2 box)
    assert int(tree.depth.max()) >= 1


def test_propagation_matches_reference_and_convention(box, gen):
    tree = spanning_tree(box)
    R = so3.exp(torch.randn(box.n_edges, 3, generator=gen, dtype=D))
    root = _random_frames(1, gen)
    F = propagate_frames(R, tree, root)
    ref = _reference_propagation(R, box, tree, root)
    assert torch.allclose(F, ref, atol=1e-12)
    # recovering frames from their own connection R_ij = F_i^T F_j (F_j = F_i R_ij)
    Ft = _random_frames(box.n_vertices, gen)
    Rt = Ft[box.edges[:, 0]].transpose(-1, -2) @ Ft[box.edges[:, 1]]
    assert torch.allclose(propagate_frames(Rt, tree, Ft[tree.roots]), Ft, atol=1e-12)


def test_propagation_two_components_and_gradcheck(gen):
    a = tio.box(n=1)
    V = a.vertices
    verts = torch.cat([V, V + torch.tensor([3.0, 0, 0], dtype=D)])
    tets = torch.cat([a.tets, a.tets + V.shape[0]])
    mesh = TetMesh(verts, tets)
    tree = spanning_tree(mesh)
    assert tree.roots.numel() == 2
    p = (0.5 * torch.randn(mesh.n_edges, 3, generator=gen, dtype=D)).requires_grad_(True)
    r = (0.5 * torch.randn(2, 3, generator=gen, dtype=D)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p, r: propagate_frames(so3.exp(p), tree, so3.exp(r)), (p, r))
    with pytest.raises(ValueError, match="root_frames"):
        propagate_frames(so3.exp(p), tree, torch.eye(3, dtype=D))
    with pytest.raises(ValueError, match="one root per"):
        spanning_tree(mesh, roots=[0, 1])


def test_comb_frames_relabels_only_and_combs_tree_edges(box, gen):
    tree = spanning_tree(box)
    # a smooth field (small rotations of one frame) with random axis labels per vertex
    base = so3.exp(0.1 * torch.randn(box.n_vertices, 3, generator=gen, dtype=D))
    G = octahedral.group(D)
    F = base @ G[torch.randint(0, 24, (box.n_vertices,), generator=gen)]
    C = comb_frames(F, tree)
    # same cross frames: C_v = F_v g_v with g_v in O
    g = F.transpose(-1, -2) @ C
    assert torch.allclose(g.round(), g, atol=1e-12)
    # every tree edge now matches without relabeling
    for lv in tree.levels:
        idx, _ = octahedral.match(C[lv.parent], C[lv.child])
        assert (idx == 0).all()
