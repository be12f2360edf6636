"""The repair of the edge-based singular graph (torchconn.hexmesh.repair).

Layers: the state's classes equal the meshability report's on random matchings (a slow
reference: the report recomputed from scratch); the disk re-solve on a constructed arc (a
valence-3 chain on the axis of a prism, detached from a vertex: exact expectations); each
operation on a case whose condition is known (the hairpin zipper of the meshability tests,
HexMe models whose straightened SH fields have the condition), before and after: the condition
gone at the vertex, the cost lower, the walk products of the new matchings recomputed from
scratch equal to the state's, and the conservation of holonomy the Bianchi identity of the
transitions implies (no singular arc ends at an interior vertex; an interior vertex with two
singular edges has two turns of one type).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import io
from torchconn.hexmesh.cut import edge_walks, face_matchings, group_matrices
from torchconn.hexmesh.meshability import INVALID, ZIPPER, meshability_report
from torchconn.hexmesh.repair import (MeshLookup, SingularGraph, cone_disk, detach_arc, link_path, move_off_boundary,
                                      push_inside, repair_feature_sector, repair_singular_graph, retract_hook,
                                      slide_touching_end, solve_disk, spanning_disk, zip_zipper)
from torchconn.hexmesh.repair.graph import _TYP

from conftest import hexme_mesh
from test_hexmesh_map import axis_prism
from test_hexmesh_meshability import hairpin


def _identity(mesh):
    return torch.eye(3, dtype=torch.float64).expand(mesh.n_tets, 3, 3).clone()


def _check_consistent(mesh, frames, match, g=None):
    """The walk products of ``match`` recomputed from scratch, the state's (if given) equal to them,
    the report's classes equal to the state's, and the conservation of holonomy at interior vertices."""
    walks = edge_walks(mesh)
    from torchconn.hexmesh.cut import GROUP_INV

    prod = walks.products(GROUP_INV[match])
    if g is not None:
        assert (g.prod == prod).all()
        m = meshability_report(mesh, frames, match)
        assert (m.vertex_class == g.vcls).all()
        c = g.counts()
        assert all(c[k] == m.counts()[k] for k in ("complex_edges", "zipper_nodes", "invalid_nodes",
                                                   "surface_valence2_edges", "touching_edges"))
    E = mesh.edges.numpy()
    sing = ~walks.boundary & (prod != 0)
    on_b = np.zeros(mesh.n_vertices, bool)
    on_b[mesh.boundary_vertices.numpy()] = True
    deg = np.bincount(E[sing].reshape(-1), minlength=mesh.n_vertices)
    assert not ((deg == 1) & ~on_b).any(), "a singular arc ends at an interior vertex"
    two = np.nonzero((deg == 2) & ~on_b)[0]
    for v in two.tolist():
        es = np.nonzero(sing & (E == v).any(1))[0]
        assert _TYP[prod[es[0]]] == _TYP[prod[es[1]]]
    return prod


# ----------------------------------------------------------------------------- the state
@pytest.mark.parametrize("seed", [0, 1])
def test_state_classes_equal_the_report_on_random_matchings(seed):
    mesh = io.box(2)
    F = _identity(mesh)
    rng = np.random.default_rng(seed)
    g = SingularGraph(mesh, F)
    fi = np.nonzero(g.interior_face)[0]
    for _ in range(3):  # random changes, each checked against the report recomputed from scratch
        f = rng.choice(fi, 6, replace=False)
        tok = g.set_matchings(f, rng.integers(0, 24, f.size))
        _check_consistent(mesh, F, g.match, g)
    prev = g.match.copy()
    g.undo(tok)
    assert (g.match[f] == tok[1]).all() and (prev[f] != tok[1]).any()
    _check_consistent(mesh, F, g.match, g)


def test_state_on_the_hairpin_and_bad_input():
    mesh, F, (p, q, v) = hairpin()
    g = SingularGraph(mesh, F)
    assert g.counts()["zipper_nodes"] == 1 and g.bad_vertices().tolist() == [v]
    _check_consistent(mesh, F, g.match, g)
    with pytest.raises(ValueError, match="tet_frames"):
        SingularGraph(mesh, F[:-1])
    with pytest.raises(ValueError, match="face_match"):
        SingularGraph(mesh, F, np.zeros(3, np.int64))
    with pytest.raises(ValueError, match="unknown weights"):
        SingularGraph(mesh, F, weights={"nope": 1.0})
    bf = np.nonzero(~g.interior_face)[0][:1]
    with pytest.raises(ValueError, match="boundary faces"):
        g.set_matchings(bf, [1])


# ----------------------------------------------------------------------------- the disk re-solve
def _prism_axis():
    """The valence-3 prism (a chain on the z-axis, z = 0, 1/3, 2/3, 1), its state and lookup, and
    the axis vertices ordered by height."""
    mesh, F = axis_prism(turns=4.0)
    X = mesh.vertices.numpy()
    axis_v = np.nonzero(np.abs(X[:, :2]).max(1) < 1e-12)[0]
    return mesh, F, SingularGraph(mesh, F), MeshLookup(mesh), axis_v[np.argsort(X[axis_v, 2])]


def test_cone_move_detaches_the_prism_arc_from_a_vertex():
    mesh, F, g, L, axis_v = _prism_axis()
    v = int(axis_v[1])  # z = 1/3
    a, b = int(axis_v[0]), int(axis_v[2])
    e1, e2 = int(L.edge_id(v, a)[0]), int(L.edge_id(v, b)[0])
    assert g.cls[e1] == g.cls[e2] == 0  # valence 3
    path = link_path(g, L, v, a, b, np.array([0.0, 0.0, 1.0]))
    assert path[0] == a and path[-1] == b and path.size >= 3
    faces, inside, rim = cone_disk(L, v, path)
    prod0 = g.prod.copy()
    vals = solve_disk(g, faces, int(faces[0]), e1, 0, inside)
    assert vals is not None
    g.set_matchings(faces, vals)
    prod = _check_consistent(mesh, F, g.match, g)
    # the arc left v: its two edges are regular, the rim path carries a quarter turn about z
    assert prod[e1] == 0 and prod[e2] == 0
    assert (_TYP[prod[rim]] == 1).all()
    assert (prod[inside] == prod0[inside]).all()
    changed = np.nonzero(prod != prod0)[0]
    assert set(changed.tolist()) == {e1, e2, *rim.tolist()}
    assert not (g.cls[L.vertex_edges(v)] >= 0).any()
    # a seed edge with two disk faces on its walk, or a seed outside the disk, has no solution
    assert solve_disk(g, faces, int(faces[0]), int(inside[0]), 0, inside[1:]) is None if inside.size else True
    assert solve_disk(g, faces[1:], int(faces[0]), e1, 0, inside) is None


def test_candidate_moves_never_repeat_a_singular_graph():
    """A move over the reversed pair of arc edges (or another path) that makes a singular graph an
    earlier move made is not yielded again: the candidates are distinct graphs (a chain's few
    branches are then distinct too)."""
    from torchconn.hexmesh.repair.ops import candidate_moves

    _, _, g, L, axis_v = _prism_axis()
    v = int(axis_v[1])
    keys = []
    for mv in candidate_moves(g, L, v):
        tok = g.set_matchings(mv.faces, mv.values)
        es = np.unique(g.face_edges[mv.faces])
        keys.append((tuple(es.tolist()), tuple(g.prod[es].tolist())))
        g.undo(tok)
    assert len(keys) >= 2 and len(set(keys)) == len(keys)


# ----------------------------------------------------------------------------- the operations
def test_zip_zipper_removes_the_hairpin():
    mesh, F, (p, q, v) = hairpin()
    m0 = meshability_report(mesh, F)
    assert m0.zipper_nodes.tolist() == [v]
    fm, mv = zip_zipper(mesh, F, None, v)
    assert mv is not None and mv.kind == "zip" and mv.delta < 0
    g = SingularGraph(mesh, F, fm)
    _check_consistent(mesh, F, fm, g)
    m1 = meshability_report(mesh, F, fm)
    assert m1.zipper_nodes.size == 0 and m1.meshable
    # the other operations do not apply at a zipper node
    for op in (push_inside, move_off_boundary, detach_arc, repair_feature_sector):
        fm2, mv2 = op(mesh, F, None, v)
        assert mv2 is None and (fm2 == face_matchings(mesh, F)).all()
    with pytest.raises(ValueError, match="not a vertex"):
        zip_zipper(mesh, F, None, mesh.n_vertices)


def test_retract_hook_through_the_floor_and_the_least_area_disk():
    # the hairpin's branches both end on the floor: the hook retracts through it
    mesh, F, (p, q, v) = hairpin()
    fm, mv = retract_hook(mesh, F, None, v)
    assert mv is not None and mv.kind == "retract" and mv.delta < 0
    g = SingularGraph(mesh, F, fm)
    _check_consistent(mesh, F, fm, g)
    assert g.counts()["zipper_nodes"] == 0 and g.counts()["singular_edges"] == 0
    # the least-area disk of the prism's detach loop is the cone over the link path
    pm, pF = axis_prism(turns=4.0)
    X = pm.vertices.numpy()
    gp, L = SingularGraph(pm, pF), MeshLookup(pm)
    axis_v = np.nonzero(np.abs(X[:, :2]).max(1) < 1e-12)[0]
    a, w, b = (int(x) for x in axis_v[np.argsort(X[axis_v, 2])][:3])
    path = link_path(gp, L, w, a, b, np.array([0.0, 0.0, 1.0]))
    faces, inside, rim = spanning_disk(gp, L, np.r_[a, w, b, path[::-1][1:]])
    cf, ci, _ = cone_disk(L, w, path)
    assert set(faces.tolist()) == set(cf.tolist()) and set(inside.tolist()) == set(ci.tolist())
    assert spanning_disk(gp, L, np.array([a, w, a])) is None  # not a loop of three or more edges


def _hexme_case(name):
    from torchconn.frames.design import design
    from torchconn.hexmesh.inputs import tet_frames_of
    from torchconn.hexmesh.straighten import straighten_singular_edges

    mesh = hexme_mesh(name)
    Fr = tet_frames_of(mesh, design(mesh, "sh_baseline").vertex_frames)
    fm, _ = straighten_singular_edges(mesh, Fr, boundary_moves=True)
    return mesh, Fr, fm


def _check_operation(mesh, Fr, fm, op, kind):
    """Find a vertex where ``kind`` is the best move (its condition is there), apply ``op`` there
    and check the result (module docstring)."""
    from torchconn.hexmesh.repair.ops import best_move

    g = SingularGraph(mesh, Fr, fm)
    L = MeshLookup(mesh)
    v = next((int(x) for x in g.bad_vertices() if best_move(g, L, int(x), (kind,)) is not None), None)
    assert v is not None, f"no vertex takes a {kind} move"
    assert g.bad_vertices_mask()[v]
    cost0 = g.cost()
    fm1, mv = op(mesh, Fr, fm, v)
    assert mv is not None and mv.kind == kind and mv.delta < 0
    g1 = SingularGraph(mesh, Fr, fm1)
    _check_consistent(mesh, Fr, fm1, g1)
    assert g1.cost() == pytest.approx(cost0 + mv.delta, abs=1e-9)
    assert (fm1 != fm).sum() <= mv.faces.size
    return v, g, g1


@pytest.mark.slow  # gmsh meshing, the SH field and the straightening: 3-5 s
def test_push_inside_and_move_off_on_a_hexme_model():
    # s10c: the straightened SH field has a singular curve on the cylinder's smooth surface and
    # an arc through a boundary vertex (2 invalid nodes, 3 touching edges, 2 crease edges)
    mesh, Fr, fm = _hexme_case("s10c_cyl_cutsphere")
    v, g, g1 = _check_operation(mesh, Fr, fm, push_inside, "push_inside")
    assert g1.counts()["boundary_crease_edges"] < g.counts()["boundary_crease_edges"]
    v, g, g1 = _check_operation(mesh, Fr, fm, move_off_boundary, "move_off")
    assert g1.counts()["touching_edges"] < g.counts()["touching_edges"]
    assert g1.vcls[v] not in (ZIPPER, INVALID) and g.vcls[v] == INVALID


@pytest.mark.slow  # gmsh meshing, the SH field, the straightening and the repair's rounds: 20-30 s
def test_slide_touching_end_on_a_hexme_model():
    # s13c: without slides the repair leaves one arc ending on the rounded edge about a tangent
    # axis; the slide moves its end along the fillet to where its axis is the normal
    mesh, Fr, fm = _hexme_case("s13c_cube_rounded_2")
    fm1, rep = repair_singular_graph(mesh, Fr, fm, slide=False)
    assert rep.after["meshable"] and rep.after["touching_edges"] >= 1
    m, F = rep.mesh, rep.tet_frames
    v, g, g1 = _check_operation(m, F, fm1, slide_touching_end, "slide_end")
    assert g1.counts()["touching_edges"] < g.counts()["touching_edges"] and g1.counts()["meshable"]


@pytest.mark.slow  # gmsh meshing, the SH field and the straightening: 2-4 s
def test_feature_sector_on_a_hexme_model():
    # n08c: fans on the pentagonal pyramid's sharp edges whose angle is not the feature's
    mesh, Fr, fm = _hexme_case("n08c_pentapyr")
    v, g, g1 = _check_operation(mesh, Fr, fm, repair_feature_sector, "feature_sector")
    assert g1.counts()["feature_mismatch_edges"] < g.counts()["feature_mismatch_edges"] or \
        g1.counts()["invalid_nodes"] < g.counts()["invalid_nodes"]


def test_detach_arc_at_an_invalid_interior_node():
    # the valence-3 chain on the prism axis and a small singular loop through its vertex v (one
    # face's transition turned by a quarter turn, group algebra only): v has four singular
    # edges whose hex counts are not those of a hex-mesh vertex, an invalid node
    from torchconn.hexmesh.cut import GROUP_INV, GROUP_MUL

    mesh, F = axis_prism(turns=4.0)
    X = mesh.vertices.numpy()
    L = MeshLookup(mesh)
    axis_v = np.nonzero(np.abs(X[:, :2]).max(1) < 1e-12)[0]
    v = int(axis_v[np.argsort(X[axis_v, 2])][1])
    g = SingularGraph(mesh, F)
    fm_bad = None
    for f in L.vertex_faces(v).tolist():
        if not g.interior_face[f] or np.isin(L.faces[f], axis_v).sum() > 1:
            continue
        for k in range(1, 24):
            new = GROUP_INV[GROUP_MUL[k, GROUP_INV[g.match[f]]]]  # R_f <- G[k] R_f
            tok = g.set_matchings([f], [new])
            if g.vcls[v] == INVALID and g.counts()["complex_edges"] == 0:
                fm_bad = g.match.copy()
                break
            g.undo(tok)
        if fm_bad is not None:
            break
    assert fm_bad is not None, "no face move at v makes it an invalid node"
    assert (g.cls[L.vertex_edges(v)] >= 0).sum() == 4
    fm, mv = detach_arc(mesh, F, fm_bad, v)
    assert mv is not None and mv.kind == "detach" and mv.delta < 0
    g1 = SingularGraph(mesh, F, fm)
    _check_consistent(mesh, F, fm, g1)
    assert g1.vcls[v] not in (INVALID, ZIPPER)
    fm2, rep = repair_singular_graph(mesh, F, fm_bad, max_rounds=3, split_passes=0)
    _check_consistent(mesh, F, fm2, SingularGraph(mesh, F, fm2))
    assert rep.before["invalid_nodes"] >= 1 and rep.after["invalid_nodes"] == 0 and rep.after["meshable"]


def _touching_box():
    """The unit box ``io.box(4)`` (grid step 1/4, identity frames) with two quarter-turn arcs
    about z in the plane ``y = 1/2``, made by group algebra: the least-area disk spanning the loop
    bottom ``(1/4, 0) -> (3/4, 0)``, up the column ``x = 3/4`` to ``z = 3/4``, the face diagonal
    to ``c = (1, 1/2, 1)`` on the box's top-right edge, along the top back to ``x = 1/4`` and down
    the column ``x = 1/4``, re-solved (:func:`solve_disk`) with the loop's first edge a quarter
    turn about z. Arc B (``x = 1/4``) meets the top and the floor along their normal; arc A ends
    at ``c``, on a feature curve, whose wall faces (normal x) are tangent to its axis: one
    touching end, and ``c`` an invalid node (an arc ends on a sharp edge), nothing else to
    repair (the top and floor fans turn about their normal and stay flat).

    Returns ``(mesh, frames, face matchings, c, the column's top vertex (3/4, 1/2, 1))``."""
    from test_hexmesh_meshability import _element

    mesh = io.box(4)
    F = _identity(mesh)
    g, L = SingularGraph(mesh, F), MeshLookup(mesh)

    def vid(i, k):  # the grid vertex (i/4, 1/2, k/4)
        return (i * 5 + 2) * 5 + k

    loop = np.array([vid(1, 0), vid(2, 0), vid(3, 0), vid(3, 1), vid(3, 2), vid(3, 3), vid(4, 4), vid(3, 4),
                     vid(2, 4), vid(1, 4), vid(1, 3), vid(1, 2), vid(1, 1), vid(1, 0)])
    faces, inside, _ = spanning_disk(g, L, loop)
    e1 = int(L.edge_id(loop[1], loop[2])[0])
    seed = [f for f in faces.tolist() if e1 in L.face_edges[f]]
    quarter = _element([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    vals = solve_disk(g, faces, seed[0], e1, quarter, inside)
    g.set_matchings(faces, vals)
    return mesh, F, g.match.copy(), vid(4, 4), vid(3, 4)


def test_slide_touching_end_moves_the_arc_end_off_the_wall():
    mesh, F, fm0, c, w = _touching_box()
    g = SingularGraph(mesh, F, fm0)
    L = MeshLookup(mesh)
    _check_consistent(mesh, F, fm0, g)
    c0 = g.counts()
    assert c0["touching_edges"] == 1 and c0["invalid_nodes"] == 1 and c0["singular_edges"] == 8
    assert c0["boundary_crease_edges"] == c0["feature_mismatch_edges"] == 0
    assert g.bad_vertices().tolist() == [c] and g.vcls[c] == INVALID
    # the other moves have nothing to do at an arc's touching end
    for op in (push_inside, move_off_boundary, detach_arc, zip_zipper, repair_feature_sector):
        assert op(mesh, F, fm0, c)[1] is None
    fm, mv = slide_touching_end(mesh, F, fm0, c)
    assert mv is not None and mv.kind == "slide_end" and mv.delta < 0
    g1 = SingularGraph(mesh, F, fm)
    _check_consistent(mesh, F, fm, g1)
    c1 = g1.counts()
    assert c1["touching_edges"] == 0 and c1["meshable"] and c1["boundary_crease_edges"] == 0
    assert c1["feature_mismatch_edges"] == 0 and g1.bad_vertices().size == 0
    # the arc now goes straight up the column to w, along the top's normal; nothing is left at c
    ec = L.vertex_edges(c)
    assert not (g1.cls[ec[~g1.boundary[ec]]] >= 0).any() and g1.vcls[c] != INVALID
    e = int(L.edge_id(w - 1, w)[0])
    assert g1.cls[e] >= 0 and _TYP[g1.prod[e]] == 1 and c1["singular_edges"] == 8
    assert g1.cost() == pytest.approx(g.cost() + mv.delta, abs=1e-9)
    # the driver slides it; without slides no single move lowers the cost and the end stays
    # (chains off: those of feature-sector and retract moves remove the arc at a higher cost)
    fm2, rep = repair_singular_graph(mesh, F, fm0, max_rounds=4, chain_depth=0, split_passes=0, slide=True)
    assert rep.moves == {"slide_end": 1} and rep.after["touching_edges"] == 0 and rep.after["meshable"]
    assert (fm2 == fm).all()
    fm3, rep3 = repair_singular_graph(mesh, F, fm0, max_rounds=4, chain_depth=0, split_passes=0)  # the default
    assert rep3.after["touching_edges"] == 1 and rep3.faces_changed == 0 and rep3.stopped == "no_move"


# ----------------------------------------------------------------------------- the driver
def test_driver_on_the_hairpin_and_on_a_clean_field():
    mesh, F, (p, q, v) = hairpin()
    fm, rep = repair_singular_graph(mesh, F)
    assert rep.before["zipper_nodes"] == 1 and rep.after["zipper_nodes"] == 0 and rep.after["meshable"]
    assert rep.stopped == "meshable" and rep.moves.get("zip", 0) + rep.moves.get("retract", 0) >= 1
    assert rep.faces_changed >= 1
    assert rep.mesh is mesh and rep.splits == 0
    _check_consistent(mesh, F, fm, SingularGraph(mesh, F, fm))
    import json

    json.dumps(rep.as_dict())
    box = io.box(2)
    fm0, rep0 = repair_singular_graph(box, _identity(box))
    assert rep0.rounds == 0 and rep0.stopped == "meshable" and rep0.faces_changed == 0
    with pytest.raises(ValueError, match="max_rounds"):
        repair_singular_graph(box, _identity(box), max_rounds=-1)


def test_driver_splits_again_only_after_a_split_led_to_a_move(monkeypatch):
    """A split pass makes room around the stuck vertices; another pass follows only when the rounds
    after the last one made a move, and a vertex that found no move is tried again after a split
    only when a split edge is within two rings of it (moves stubbed: none is ever found)."""
    import torchconn.hexmesh.repair.driver as drv

    mesh, F, (p, q, v) = hairpin()
    tried, splits = [], []
    monkeypatch.setattr(drv, "best_move", lambda g, lookup, x, kinds=None: tried.append(x))
    monkeypatch.setattr(drv, "chain_move", lambda g, lookup, x, *a, **k: [])

    def room(g, lookup, stuck):
        out = drv_room(g, lookup, stuck)
        splits.append((len(out), list(stuck)))
        return out

    drv_room = drv.room_edges
    monkeypatch.setattr(drv, "room_edges", room)
    fm, rep = repair_singular_graph(mesh, F, split_passes=3)
    assert len(splits) == 1 and splits[0][0] > 0  # one pass: it led to no move, so no second one
    assert rep.stopped == "no_move" and rep.splits == splits[0][0] and rep.after["zipper_nodes"] == 1
    first, again = tried[:len(splits[0][1])], tried[len(splits[0][1]):]
    assert sorted(first) == sorted(splits[0][1]) and again
    # every vertex tried again is within two rings of a split edge (its ends or its midpoint)
    E = rep.mesh.edges.numpy()
    near = np.arange(mesh.n_vertices, rep.mesh.n_vertices)  # the midpoints
    for _ in range(2):
        near = np.unique(E[np.isin(E, near).any(1)])
    assert set(again) <= set(near.tolist())


def test_group_helpers_are_consistent():
    G = group_matrices()
    assert _TYP[0] == 0 and (_TYP[1:] > 0).all() and G.shape == (24, 3, 3)


def test_map_stage_follows_given_matchings_and_repairs_its_own():
    from benchmarks.structures import summarize
    from torchconn.hexmesh import hex_mesh

    mesh, F, (p, q, v) = hairpin()
    fm, _ = zip_zipper(mesh, F, None, v)
    r = hex_mesh(mesh, F, face_match=fm, extract=False, quality=False)
    assert r.map.stats["straighten"]["given"] and r.meshability.meshable  # the zipper is gone in the map's graph
    assert "repair" not in r.map.stats  # given matchings are followed as they are
    # the map stage's own repair removes the same zipper (the search alone leaves it)
    off = hex_mesh(mesh, F, straighten=False, repair=False, extract=False, quality=False)
    on = hex_mesh(mesh, F, straighten=False, repair=True, extract=False, quality=False)
    assert off.meshability.counts()["zipper_nodes"] == 1 and not off.gates["structure"].passed
    rep = on.map.stats["repair"]
    assert rep["before"]["zipper_nodes"] == 1 and rep["after"]["zipper_nodes"] == 0 and on.meshability.meshable
    assert on.gates["structure"].counts["repair_moves"] == sum(rep["moves"].values()) >= 1
    assert on.metrics()["map"]["repair"]["after"]["zipper_nodes"] == 0  # hex_metrics.json says what was repaired
    with pytest.raises(ValueError, match="face_match must have shape"):
        hex_mesh(mesh, F, face_match=fm[:-1], extract=False)
    with pytest.raises(ValueError, match="24 elements"):
        hex_mesh(mesh, F, face_match=np.full_like(fm, 30), extract=False)
    rec = {"kind": "s", "before": {"meshable": False, "touching_edges": 0, "complex_edges": 0, "zipper_nodes": 1,
                                   "invalid_nodes": 0, "surface_valence2_edges": 0},
           "after": {"meshable": True, "touching_edges": 0, "complex_edges": 0, "zipper_nodes": 0,
                     "invalid_nodes": 0, "surface_valence2_edges": 0}}
    s = summarize([rec])["s"]
    assert s["meshable_before"] == 0 and s["meshable_after"] == 1 and s["zipper_nodes_before"] == 1
