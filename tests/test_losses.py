"""Frame-field losses (torchconn.frames.loss, the term modules of torchconn.frames.terms) and parallel
frame propagation (torchconn.frames.propagate)."""
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
from torchconn import nn as tnn
from torchconn import ops
from torchconn.mesh import TetMesh
from torchconn.ops import native

D = torch.float64
HAS_C = native._compiler() is not None


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


# ----------------------------------------------------------------------------- the loss's modules
def test_loss_is_a_module_made_of_the_library_modules(box):
    """FrameFieldLoss is an nn.Module; its terms are modules, those of the connection's geometry the
    library's own (Curvature, Torsion, AveragedCovariantD), all on one shared copy of the topology."""
    loss = FrameFieldLoss(box, {k: 1.0 for k in TERMS})
    assert isinstance(loss, torch.nn.Module) and set(loss.terms) == set(TERMS)
    assert isinstance(loss.terms["flat"].curvature, tnn.Curvature) and loss.terms["flat"].curvature.kind == "holonomy"
    assert isinstance(loss.terms["torsion"].torsion, tnn.Torsion) and loss.terms["torsion"].torsion.kind == "sqrt"
    assert isinstance(loss.terms["dnabla"].dd, tnn.AveragedCovariantD)
    shared = [loss.terms["tie"].mesh, loss.terms["flat"].curvature.mesh, loss.terms["torsion"].torsion.mesh,
              loss.terms["dnabla"].dd.mesh, loss.terms["dnabla"].curvature.mesh, loss.terms["dirichlet"].mesh]
    assert all(m is loss.mesh for m in shared)
    assert set(FrameFieldLoss(box, {"tie": 1.0, "align": 2.0}).terms) == {"tie", "align"}  # unweighted: not built
    f32 = FrameFieldLoss(box, {"torsion": 1.0, "dnabla": 1.0}).float()  # the buffers follow the module
    assert f32.mesh.vertices.dtype == torch.float32 and f32.terms["torsion"].face_area.dtype == torch.float32


@pytest.mark.parametrize("compiled", [pytest.param(True, marks=pytest.mark.skipif(not HAS_C, reason="no C compiler")),
                                      False], ids=["fused", "modules"])
def test_loss_takes_the_models_connection_field(box, gen, compiled):
    """The connection may be the model's ConnectionField (or a Connection): the same terms as its tensor,
    and the gradient reaches the field's parameters."""
    field = tnn.ConnectionField(box.edges, box.n_vertices, init=so3.exp(0.2 * torch.randn(box.n_edges, 3, generator=gen,
                                                                                          dtype=D)))
    F = _random_frames(box.n_vertices, gen)
    loss = FrameFieldLoss(box, {k: 1.0 for k in TERMS})
    with ops.compiled(compiled):
        a = loss(field, F)
        b = loss(field.edge_rotations().detach(), F)
        a["total"].backward()
    for k in b:
        torch.testing.assert_close(a[k].detach(), b[k], atol=1e-14, rtol=0)
    assert field.params.grad is not None and bool(field.params.grad.abs().sum() > 0)


@pytest.mark.skipif(not HAS_C, reason="no C compiler: the fused kernel cannot be built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("power,align_kind", [(1.0, "angle"), (2.0, "quartic")])
def test_fused_kernel_equals_the_modules(gen, dtype, power, align_kind):
    """The fast path behind the modules: the fused kernel's terms and gradients equal the term modules'
    (the switch off) to round-off, every term weighted."""
    mesh = tio.box(3).to(dtype=dtype)
    loss = FrameFieldLoss(mesh, {k: 0.5 + 0.25 * i for i, k in enumerate(TERMS)}, smooth_power=power,
                          align_kind=align_kind)
    w = 0.3 * torch.randn(mesh.n_edges, 3, generator=gen, dtype=D)
    phi = 0.3 * torch.randn(mesh.n_vertices, 3, generator=gen, dtype=D)
    res = {}
    for on in (True, False):
        ww, pp = w.to(dtype).requires_grad_(), phi.to(dtype).requires_grad_()
        with ops.compiled(on):
            out = loss(so3.exp(ww), so3.exp(pp))
            grads = torch.autograd.grad(out["total"], (ww, pp))
        res[on] = ({k: v.detach() for k, v in out.items()}, grads)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert res[True][0].keys() == res[False][0].keys() == {*TERMS, "total"}
    for k, v in res[False][0].items():
        torch.testing.assert_close(res[True][0][k], v, atol=tol * max(1.0, float(v.abs())), rtol=0, msg=k)
    for a, b in zip(res[True][1], res[False][1]):
        torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_benchmark_reference_agrees_with_the_loss(dtype):
    """Issue 30: the eager reference of ``benchmarks.references`` (the library's single-term functions and the
    generic operators) computes the loss rows' losses -- every term and the total to
    ``LOSS_AGREEMENT_RTOL`` relative, and the gradients -- so the benchmark cannot drift from the loss."""
    from benchmarks.references import LOSS_AGREEMENT_RTOL, _ref_exp_matrix, loss_agreement, loss_cases, ref_frame_loss_terms

    mesh = tio.box(3).to(dtype=dtype)
    g = torch.Generator().manual_seed(2)
    w = 0.2 * torch.randn(mesh.n_edges, 3, generator=g, dtype=dtype)
    phi = 0.2 * torch.randn(mesh.n_vertices, 3, generator=g, dtype=dtype)
    cases = loss_cases(mesh)
    assert [name for name, _ in cases] == ["frame_field_loss(default)", "frame_field_loss(all terms)"]
    for name, loss in cases:
        rel, worst = loss_agreement(loss, so3.exp(w), so3.exp(phi))
        assert rel <= (1e-13 if dtype == torch.float64 else LOSS_AGREEMENT_RTOL), (name, worst, rel)
        ww, pp = w.clone().requires_grad_(), phi.clone().requires_grad_()
        ga = torch.autograd.grad(loss(so3.exp(ww), so3.exp(pp))["total"], (ww, pp))
        gb = torch.autograd.grad(ref_frame_loss_terms(loss, _ref_exp_matrix(ww), _ref_exp_matrix(pp))["total"],
                                 (ww, pp))
        for a, b in zip(ga, gb):
            # float32: the angle alignment term's sqrt(d2 + eps^2), eps = 1e-3, amplifies the ~1e-7
            # difference of the two exps (so3.exp against matrix_exp) in its gradient
            tol = (1e-12 if dtype == torch.float64 else 1e-3) * float(b.abs().max())
            torch.testing.assert_close(a, b, atol=tol, rtol=0)
    # the check sees a loss that is not the reference's: the modules' torsion doubled
    loss = cases[1][1]
    torsion = loss.terms["torsion"]
    with ops.compiled(False):
        torsion.forward = lambda *args, _f=torsion.forward: 2.0 * _f(*args)
        rel, worst = loss_agreement(loss, so3.exp(w), so3.exp(phi))
    assert worst in ("torsion", "total") and rel > 0.01


def test_benchmark_default_loss_is_the_loss_design_builds(monkeypatch):
    """``benchmarks.references.loss_cases``' default row has the weights and options of the FrameFieldLoss
    ``design()`` constructs with its defaults (captured at construction, the run stopped there)."""
    import importlib

    from benchmarks.references import loss_cases

    design_mod = importlib.import_module("torchconn.frames.design")  # the module (frames.design is the function)

    seen = {}

    class Stop(Exception):
        pass

    class Recording(FrameFieldLoss):
        def __init__(self, mesh, weights, **kw):
            super().__init__(mesh, weights, **kw)
            seen.update(weights=self.weights, kw=kw)
            raise Stop

    monkeypatch.setattr(design_mod, "FrameFieldLoss", Recording)
    mesh = tio.box(1)
    with pytest.raises(Stop):
        design_mod.design(mesh, steps=1, sh={"n_smooth_iters": 1})
    bench = loss_cases(mesh)[0][1]
    assert bench.weights == seen["weights"]
    assert {k: seen["kw"][k] for k in ("feature_angle_deg", "smooth_power", "smooth_eps", "align_kind", "align_eps")} \
        == {"feature_angle_deg": bench.constraint.feature_angle_deg, "smooth_power": bench.smooth_power,
            "smooth_eps": bench.smooth_eps, "align_kind": bench.align_kind, "align_eps": bench.align_eps}
    assert not seen["kw"].get("extra_terms")  # design()'s default: no extra term


def test_loss_dtypes_benchmark_runs_on_every_device(device):
    """``benchmarks.loss_dtypes`` times the default loss on the device asked for, both dtypes."""
    from benchmarks.loss_dtypes import main

    rows = main(["--tets", "200", "--repeats", "1", "--threads", "1", "--device", str(device)])
    assert [r["dtype"] for r in rows] == ["float32", "float64"]
    assert all(r["device"].startswith(device.type) and r["median_s"] > 0 for r in rows)
    assert all(("peak_device_gb" in r) == (device.type == "cuda") for r in rows)


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
