"""Local meshability of the edge-based singular graph (Liu & Bommes, "Locally Meshable Frame Fields", 2023).

An integer-grid map follows a frame field only where the field's singular graph looks, locally,
like the singular graph of a hex mesh (HEXMESH.md step 1). With one frame per tet the singular
graph lives on mesh edges (:mod:`.cut`); :func:`meshability_report` checks it vertex by vertex and edge
by edge and lists the offending elements of each condition.

The hex count of an edge
------------------------
Every edge gets the number of hexes the field puts around it, ``edge_hexes (E,)``:

* interior edge: ``4`` regular; a quarter turn about the edge's parameter axis ``3`` or ``5``
  (:mod:`.cut`: ``+90°`` about the edge's parametric direction is valence 3); a half turn
  ``2`` or ``6``, decided by the field's own rotation about the edge: walking
  counter-clockwise about ``a -> b`` (``a < b``), each step ``i -> j`` across a face with
  transition ``S`` (``u_j = S u_i``) leaves the misfit rotation ``Q = F_j S F_i^T`` (world
  frame; identity for a field that agrees with its matching), and the lifted turn of the field
  is ``A = sum_steps <log Q, d>`` (``d`` the unit edge direction): ``A ~ +pi/2`` at valence 3,
  ``-pi/2`` at 5, ``+pi`` at 2, ``-pi`` at 6 (the charts around the edge unfold to
  ``2 pi - A``); ``-1`` for a complex holonomy.
* boundary edge: the parametric angle of its boundary fan in quarter turns, ``q in 0..4``
  (``q`` hexes). The fan runs from the boundary face of its first tet (outward normal ``n0``)
  to that of its last tet (``n1``); in the first tet's chart ``n0`` is the signed axis ``a0``
  and ``n1``, carried back through the fan's transitions ``P`` (``u_last = P u_first``), the
  signed axis ``a1``. ``a1 = a0``: a flat fan, ``q = 2``. ``a1 ⟂ a0``: the edge runs along
  ``e = ±a0 × a1`` (the sign of the edge's parametric direction), the first face leaves the
  edge along ``t0 = e × a0`` and the last along ``t1 = a1 × e``, and the counter-clockwise
  angle from ``t0`` to ``t1`` is ``pi/2`` (``q = 1``, convex) or ``3 pi/2`` (``q = 3``,
  concave). ``a1 = -a0``: the fan folds, ``q = 0`` or ``4``, whichever is nearer to the
  estimate ``phi + A`` (``phi`` the fan's dihedral angle in space, ``A`` as above).

Conditions (each a list of offending elements in :class:`Meshability`)
-----------------------------------------------------------------------
* ``complex_edges``: interior edges whose holonomy is not a quarter or half turn.
* ``surface_valence2_edges`` (LMFF's "valence ±2 edges on feature surfaces"): boundary edges
  off sharp features (a feature edge whose dihedral angle is within 45° of ``pi``, a smooth
  CAD curve, is a surface edge here) whose fan folds, ``q in {0, 4}``: the map would lay the
  two sides of the fan onto one integer plane, back to back.
* ``zipper_nodes``: vertices where a valence +1 arc meets a -1 arc and nothing else: hex
  counts 3 and 5 (or 2 and 6) at the vertex's only two singular edges; at a boundary vertex
  also a convex (``q = 1``) and a concave (``q = 3``) boundary edge, a ``q = 1`` edge and a
  valence-5 arc, a ``q = 3`` edge and a valence-3 arc (:data:`BOUNDARY_CONFIGS`). The count
  is by the edges' classes, so an edge across its axis (whose sign is that of a small
  component) may make one. At an interior vertex with exactly two singular
  edges the holonomy is conserved (the loops about the two edges are homotopic in the vertex
  star), so the two turns have the same axis and opposite senses *seen from the vertex*; they
  have the same hex count exactly when their directions are opposite along that axis (a
  straight arc) and counts 3 and 5 exactly when the curve doubles back on itself along its
  axis: a hairpin, which no map can follow (the two branches would lie on one integer line).
* ``invalid_nodes``: vertices whose incident singular edges are not the singular edges of any
  hex-mesh vertex. The link of a hex-mesh vertex is a triangulated sphere (interior vertex)
  or disk (boundary vertex): one triangle per hex corner, one link vertex per incident hex
  edge, of degree its hex count ``k`` (interior) or ``k + 1`` (boundary edge). Euler's formula
  gives ``sum_interior (6 - k) + sum_boundary (3 - q) = 12`` (sphere) or ``6`` (disk), with the
  regular edges (``k = 4``, ``q = 2``) the map may add contributing ``2`` and ``1``; which
  counts are realized is the enumeration of small triangulations. Interior vertices (valences
  3 and 5 only; any other half turn than an arc is invalid): ``(n3, n5)`` in
  :data:`INTERIOR_NODES` -- the 11 triangulated spheres with vertex degrees 3-5 (Liu et al.
  2018), less the octahedron (a regular vertex) and the two arcs. Boundary vertices: the
  configurations of :data:`BOUNDARY_CONFIGS` (feature curves and corners, arcs ending on a
  surface or on a concave curve: the boundary configurations of AlgoHex's node taxonomy,
  each within the Euler count); a vertex of a flat surface (no non-flat boundary edge)
  carries at most one singular edge, which may not be a valence-2 edge (the Euler count
  leaves no room for a second one, nor for a link vertex of degree 2). The counts say
  nothing of the edges' directions: beyond arcs (where conservation fixes them) a node of a
  valid kind may still be arranged wrongly; the conditions are necessary, not sufficient.
  Vertices at a complex edge are classed ``complex`` (the edge is reported) and not counted.
  A sharp feature edge with a flat fan (``q = 2``) is still a hex edge: not in the table's counts,
  it takes ``3 - 2 = 1`` of the disk's 6, and a boundary vertex whose edges take more is invalid
  (a pyramid apex's four convex curves with fans ``1, 1, 1, 2``: a cube corner to the table; its
  hexes are flat there, HexMe n09c, n14c).
* ``touching_edges``: interior singular edges with an end on the boundary whose turn axis is
  more than 45° from the boundary normal there (:func:`tangent_axes`; the search's ``w_tangent``,
  :func:`~.straighten.touching_edges`).
* ``across_edges``: singular edges whose turn axis is not the parameter axis closest to their
  direction (:attr:`~.cut.TetCharts.edge_across`).

Reported for information (not conditions): ``singular_nodes`` (valid nodes),
``boundary_crease_edges`` (``q in {1, 3}`` off sharp features: the map lays a param corner
into a smooth surface) and ``feature_mismatch_edges`` (sharp feature edges whose ``q`` is not
the nearest quarter multiple of their dihedral angle, clamped to 1..3).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .cut import GROUP_INV, TetCharts, edge_walks, group_matrices, tet_charts

__all__ = ["Meshability", "meshability_report", "VERTEX_CLASSES", "EDGE_CLASSES", "INTERIOR_NODES", "BOUNDARY_CONFIGS",
           "classify_vertices", "edge_class_counts", "interior_edge_class", "boundary_edge_class", "boundary_edge_quarters",
           "interior_class_table", "BoundaryFans", "boundary_fans", "fan_quarters", "folded_fan_quarters", "fan_quarter_table",
           "field_turn", "sharp_edges", "tangent_axes", "walk_products"]

VERTEX_CLASSES = ("regular", "arc", "node", "zipper", "invalid", "complex")
"""Codes of :attr:`Meshability.vertex_class`: no singular edge; on an arc (or a feature curve,
or an arc's end on the boundary); a valid singular node (or CAD corner); a zipper node; an
invalid node; at a complex edge."""
REGULAR, ARC, NODE, ZIPPER, INVALID, COMPLEX = range(6)

EDGE_CLASSES = ("v3", "v5", "v2", "v6", "complex", "q0", "q1", "q3", "q4")
"""The columns of :func:`edge_class_counts`: interior singular edges by hex count (and complex),
then boundary edges by fan angle in quarter turns (``q = 2``, a flat fan, is not counted)."""

INTERIOR_NODES = ((4, 0), (2, 2), (1, 3), (0, 4), (2, 6), (0, 6), (0, 8), (0, 12))
"""``(n3, n5)``: the valid interior singular nodes (links: tetrahedron, ``3^2 4^2 5^2``,
``3 4^3 5^3``, snub disphenoid, ``3^2 5^6``, triaugmented triangular prism, gyroelongated
square bipyramid, icosahedron; ``4`` = a regular edge added by the map)."""

# boundary configurations: ((q0, q1, q3, q4) boundary edges, (v3, v5, v2, v6) interior edges) -> class
_B = {
    # an arc ending on a surface; feature curves (and folds) passing through
    ((0, 0, 0, 0), (1, 0, 0, 0)): ARC, ((0, 0, 0, 0), (0, 1, 0, 0)): ARC, ((0, 0, 0, 0), (0, 0, 0, 1)): ARC,
    ((0, 2, 0, 0), (0, 0, 0, 0)): ARC, ((0, 0, 2, 0), (0, 0, 0, 0)): ARC,
    ((2, 0, 0, 0), (0, 0, 0, 0)): ARC, ((0, 0, 0, 2), (0, 0, 0, 0)): ARC,
    # a +1 and a -1 meeting
    ((0, 0, 0, 0), (1, 1, 0, 0)): ZIPPER, ((0, 0, 0, 0), (0, 0, 1, 1)): ZIPPER,
    ((0, 1, 1, 0), (0, 0, 0, 0)): ZIPPER, ((1, 0, 0, 1), (0, 0, 0, 0)): ZIPPER,
    ((0, 1, 0, 0), (0, 1, 0, 0)): ZIPPER, ((0, 0, 1, 0), (1, 0, 0, 0)): ZIPPER,
    # corners of feature curves
    ((0, 3, 0, 0), (0, 0, 0, 0)): NODE, ((0, 2, 1, 0), (0, 0, 0, 0)): NODE, ((0, 2, 2, 0), (0, 0, 0, 0)): NODE,
    ((0, 1, 2, 0), (0, 0, 0, 0)): NODE, ((0, 0, 3, 0), (0, 0, 0, 0)): NODE,
    # arcs ending on concave curves and corners
    ((0, 0, 2, 0), (1, 0, 0, 0)): NODE, ((0, 0, 2, 0), (0, 1, 0, 0)): NODE, ((0, 0, 2, 0), (1, 1, 0, 0)): NODE,
    ((0, 0, 3, 0), (0, 1, 0, 0)): NODE, ((0, 1, 2, 0), (1, 0, 0, 0)): NODE, ((0, 1, 2, 0), (0, 1, 0, 0)): NODE,
    # a 2 pi fan touching corners
    ((0, 2, 2, 1), (0, 0, 0, 0)): NODE, ((0, 2, 0, 1), (0, 0, 0, 0)): NODE, ((0, 0, 2, 1), (0, 0, 0, 0)): NODE,
}
BOUNDARY_CONFIGS = dict(_B)
"""``((q0, q1, q3, q4), (v3, v5, v2, v6)) -> class`` for boundary vertices (counts of incident
boundary edges by fan angle and of interior singular edges by hex count); anything else with a
singular edge is invalid."""


def _key(cnt: np.ndarray) -> np.ndarray:
    """Pack ``(..., 8)`` counts (columns of :data:`EDGE_CLASSES` without ``complex``) into int64 keys."""
    c = np.minimum(cnt, 15).astype(np.int64)
    return (c << (4 * np.arange(c.shape[-1]))).sum(-1)


def _table():
    """Sorted keys and classes of the boundary and interior configurations."""
    bnd = {int(_key(np.array([*i, *b]))): c for (b, i), c in _B.items()}
    inner = {int(_key(np.array([n3, n5, 0, 0, 0, 0, 0, 0]))): NODE for n3, n5 in INTERIOR_NODES}
    for arc in ((2, 0, 0, 0), (0, 2, 0, 0), (0, 0, 2, 0), (0, 0, 0, 2)):
        inner[int(_key(np.array([*arc, 0, 0, 0, 0])))] = ARC
    for zz in ((1, 1, 0, 0), (0, 0, 1, 1)):
        inner[int(_key(np.array([*zz, 0, 0, 0, 0])))] = ZIPPER
    out = []
    for d in (bnd, inner):
        k = np.array(sorted(d), np.int64)
        out.append((k, np.array([d[x] for x in k.tolist()], np.int8)))
    return out


(_BKEYS, _BVALS), (_IKEYS, _IVALS) = _table()


_LINK_EXCESS = np.array([3, 1, 4, 0, 0, 3, 2, 0, -1])
"""Per :data:`EDGE_CLASSES`, what an incident edge takes of a boundary vertex's link disk:
``6 - k`` for an interior edge of ``k`` hexes, ``3 - q`` for a boundary edge of fan ``q``
(complex edges: 0, their vertex is ``complex`` anyway); the disk's Euler count is 6."""


def classify_vertices(counts: np.ndarray, on_boundary: np.ndarray, flat_sharp: np.ndarray | None = None) -> np.ndarray:
    """Class (:data:`VERTEX_CLASSES`) of vertices from the counts of their incident edges.

    Args:
        counts: ``(..., 9)`` int, per vertex the incident edges of each of :data:`EDGE_CLASSES`.
        on_boundary: ``(...)`` bool, boundary vertices.
        flat_sharp: ``(...)`` int, per vertex the incident sharp feature edges whose fan is flat
            (``q = 2``, not counted in ``counts``). A sharp edge is a hex edge of the mesh,
            flat fan or not, so each takes ``3 - 2 = 1`` of the link's Euler count: a boundary
            vertex whose edges take more than 6 is invalid whatever :data:`BOUNDARY_CONFIGS`
            says of its other edges (module docstring, ``invalid_nodes``). ``None``: not counted.

    Returns:
        ``(...)`` int8 codes (module docstring: the rules).
    """
    counts = np.asarray(counts)
    cx = counts[..., 4] > 0
    rest = np.concatenate([counts[..., :4], counts[..., 5:]], -1)
    key = _key(rest)
    out = np.full(key.shape, INVALID, np.int8)
    out[rest.sum(-1) == 0] = REGULAR
    for keys, vals, sel in ((_IKEYS, _IVALS, ~on_boundary), (_BKEYS, _BVALS, on_boundary)):
        pos = np.clip(np.searchsorted(keys, key), 0, keys.size - 1)
        hit = (keys[pos] == key) & sel & (rest.sum(-1) > 0)
        out[hit] = vals[pos[hit]]
    if flat_sharp is not None:
        excess = counts @ _LINK_EXCESS + np.asarray(flat_sharp)
        out[on_boundary & (excess > 6)] = INVALID
    out[cx] = COMPLEX
    return out


def edge_class_counts(edges: np.ndarray, edge_cls: np.ndarray, V: int) -> np.ndarray:
    """``(V, 9)`` counts of incident edges per class (``edge_cls (E,)`` index into
    :data:`EDGE_CLASSES`, ``-1`` for regular / flat edges)."""
    out = np.zeros((V, len(EDGE_CLASSES)), np.int64)
    sel = edge_cls >= 0
    for end in (0, 1):
        np.add.at(out, (edges[sel, end], edge_cls[sel]), 1)
    return out


def interior_edge_class(hexes: np.ndarray) -> np.ndarray:
    """Class index (:data:`EDGE_CLASSES`) of interior edges from their hex count (``-1`` regular)."""
    lut = {3: 0, 5: 1, 2: 2, 6: 3, -1: 4}
    out = np.full(hexes.shape, -1, np.int64)
    for k, c in lut.items():
        out[hexes == k] = c
    return out


def boundary_edge_class(q: np.ndarray) -> np.ndarray:
    """Class index (:data:`EDGE_CLASSES`) of boundary edges from their fan angle ``q`` (``-1`` flat)."""
    lut = {0: 5, 1: 6, 3: 7, 4: 8}
    out = np.full(q.shape, -1, np.int64)
    for k, c in lut.items():
        out[q == k] = c
    return out


def boundary_edge_quarters(cls: np.ndarray) -> np.ndarray:
    """The inverse of :func:`boundary_edge_class`: a boundary edge's fan angle in quarter turns from
    its class (``q0``..``q4`` -> 0, 1, 3, 4; anything else, a flat fan, -> 2)."""
    return np.select([cls == 5, cls == 6, cls == 7, cls == 8], [0, 1, 3, 4], 2)


# ----------------------------------------------------------------------------- boundary fans
@dataclass
class BoundaryFans:
    """The two boundary faces of every boundary edge's fan.

    Rows are the boundary edges ``edge (Eb,)``; ``first_tet``/``last_tet (Eb,)`` the fan's end
    tets (:class:`~.cut.EdgeWalks` order); ``n_first``/``n_last (Eb, 3)`` the outward unit
    normals of the boundary faces there (the fan enters its first tet through one and leaves
    its last through the other); ``dihedral (Eb,)`` the fan's angle in space (radians).
    """

    edge: np.ndarray
    first_tet: np.ndarray
    last_tet: np.ndarray
    n_first: np.ndarray
    n_last: np.ndarray
    dihedral: np.ndarray


def _csr_rows(ptr: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entries of CSR rows ``rows``: ``(row position (N,), entry index (N,))``."""
    lens = ptr[rows + 1] - ptr[rows]
    pos = np.repeat(np.arange(rows.size), lens)
    offs = np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens)
    return pos, ptr[rows][pos] + offs


def boundary_fans(mesh, walks=None) -> BoundaryFans:
    """:class:`BoundaryFans` of a ``TetMesh`` (``walks``: its :func:`~.cut.edge_walks`)."""
    walks = edge_walks(mesh) if walks is None else walks
    tets = mesh.tets.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    face_tets = mesh.face_tets.cpu().numpy()
    X = mesh.vertices.detach().cpu().double().numpy()
    eb = np.nonzero(walks.boundary)[0]
    first = walks.start[eb]
    row, idx = _csr_rows(walks.ptr, eb)
    f, frm = walks.face[idx], walks.from_tet[idx]
    to = np.where(face_tets[f, 0] == frm, face_tets[f, 1], face_tets[f, 0])
    last = first.copy()
    last[row] = to  # steps are in walk order: the last write per row is the fan's last tet
    a, b = edges[eb, 0], edges[eb, 1]

    def others(t, ea, eb_):
        """The two vertices of tets ``t`` other than ``ea``, ``eb_``, ordered so that orient(a, b, c, d) > 0."""
        tv = tets[t]
        oo = np.sort(np.where((tv != ea[:, None]) & (tv != eb_[:, None]), tv, -1), 1)[:, 2:]
        c, d = oo[:, 0], oo[:, 1]
        vol = np.einsum("ij,ij->i", np.cross(X[eb_] - X[ea], X[c] - X[ea]), X[d] - X[ea])
        return np.where(vol > 0, c, d), np.where(vol > 0, d, c)

    def normal(p, q, r, away):
        n = np.cross(X[q] - X[p], X[r] - X[p])
        n *= np.where(np.einsum("ij,ij->i", n, X[away] - X[p]) > 0, -1.0, 1.0)[:, None]
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    c0, d0 = others(first, a, b)
    c1, d1 = others(last, a, b)
    # the walk goes counter-clockwise about a -> b: it enters a tet through (a, b, c) and leaves
    # through (a, b, d) (cut.edge_walks)
    n_first = normal(a, b, c0, d0)
    n_last = normal(a, b, d1, c1)
    # the fan's angle in space: the sum of its tets' dihedral angles at the edge
    fan_row = np.concatenate([np.arange(eb.size), row])
    fan_t = np.concatenate([first, to])
    ea, eb_ = a[fan_row], b[fan_row]
    c, d = others(fan_t, ea, eb_)
    u = X[eb_] - X[ea]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    p = X[c] - X[ea]
    r = X[d] - X[ea]
    p -= np.einsum("ij,ij->i", p, u)[:, None] * u
    r -= np.einsum("ij,ij->i", r, u)[:, None] * u
    ang = np.arctan2(np.linalg.norm(np.cross(p, r), axis=1), np.einsum("ij,ij->i", p, r))
    dihedral = np.bincount(fan_row, weights=ang, minlength=eb.size)
    return BoundaryFans(edge=eb, first_tet=first, last_tet=last, n_first=n_first, n_last=n_last, dihedral=dihedral)


def _signed_axis(v: np.ndarray) -> np.ndarray:
    """``(..., 3)`` vectors -> ``(..., 3)`` int: the signed coordinate axis nearest each."""
    k = np.abs(v).argmax(-1)
    out = np.zeros(v.shape, np.int64)
    s = np.sign(np.take_along_axis(v, k[..., None], -1)).astype(np.int64)
    np.put_along_axis(out, k[..., None], s, -1)
    return out


def fan_quarters(a0: np.ndarray, a1: np.ndarray, dpar: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """Parametric angle of boundary fans in quarter turns (module docstring).

    Args:
        a0, a1: ``(..., 3)`` int signed axes of the first and last boundary normals, both in the
            first tet's chart.
        dpar: ``(..., 3)`` the edge direction ``a -> b`` in that chart.
        estimate: ``(...)`` radians, the fan's angle ``phi + A`` (decides 0 against 2 pi).

    Returns:
        ``(...)`` int64 ``q in 0..4``.
    """
    same = (a0 == a1).all(-1)
    opp = (a0 == -a1).all(-1)
    cr = np.cross(a0, a1)
    s = np.sign((dpar * cr).sum(-1))
    s = np.where(s == 0, 1, s)
    e = cr * s[..., None]
    t0 = np.cross(e, a0)
    t1 = np.cross(a1, e)
    ang = np.arctan2((e * np.cross(t0, t1)).sum(-1), (t0 * t1).sum(-1)) % (2 * math.pi)
    q = np.rint(ang / (math.pi / 2)).astype(np.int64)
    q = np.where(same, 2, q)
    q = np.where(opp, folded_fan_quarters(estimate), q)
    return q


def folded_fan_quarters(estimate: np.ndarray) -> np.ndarray:
    """``q`` of a folded fan (first and last normals opposite): 0 or 4 quarter turns, by whether the
    fan's angle ``estimate`` (radians, ``phi + A``) is below or above pi (:func:`fan_quarters`)."""
    return np.where(np.asarray(estimate) < math.pi, 0, 4)


def fan_quarter_table(frames: np.ndarray, fans: BoundaryFans, edge_dir: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """``(Eb, 24)``: the fan angle ``q`` of every boundary edge for each possible fan transport
    ``P`` (index into O, ``u_last = P u_first``), in the charts of ``frames (T, 3, 3)``.

    ``edge_dir (Eb, 3)`` the edges' directions ``a -> b``; ``estimate (Eb,)`` the fans' angle
    estimates (:func:`fan_quarters`).
    """
    G = group_matrices().astype(np.float64)
    a0 = _signed_axis(np.einsum("eji,ej->ei", frames[fans.first_tet], fans.n_first))
    n1 = np.einsum("eji,ej->ei", frames[fans.last_tet], fans.n_last)  # in the last tet's chart
    a1 = _signed_axis(np.einsum("pji,ej->epi", G, n1))  # P^T n1 for every P: (Eb, 24, 3)
    dpar = np.einsum("eji,ej->ei", frames[fans.first_tet], edge_dir)
    return fan_quarters(a0[:, None], a1, dpar[:, None], estimate[:, None])


def field_turn(mesh, frames: np.ndarray, face_rot: np.ndarray, walks) -> np.ndarray:
    """``(E,)`` the lifted turn ``A`` of the field about every edge (radians; module docstring),
    over the whole walk (boundary edges: over the fan), for transitions ``face_rot (F,)``
    (``u_t1 = G[face_rot[f]] u_t0``) between the charts of ``frames (T, 3, 3)``."""
    from ..lie import so3

    E = walks.start.size
    face_tets = mesh.face_tets.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    X = mesh.vertices.detach().cpu().double().numpy()
    G = group_matrices().astype(np.float64)
    steps_e = np.repeat(np.arange(E), np.diff(walks.ptr))
    S = np.where(walks.forward, face_rot[walks.face], GROUP_INV[face_rot[walks.face]])
    to = np.where(face_tets[walks.face, 0] == walks.from_tet, face_tets[walks.face, 1], face_tets[walks.face, 0])
    # misfit of each step in space: F_to S F_from^T (identity when F_to^T = S F_from^T)
    Q = frames[to] @ G[S] @ np.transpose(frames[walks.from_tet], (0, 2, 1))
    w = so3.log(torch.as_tensor(Q)).numpy() if Q.shape[0] else np.zeros((0, 3))
    d = X[edges[:, 1]] - X[edges[:, 0]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.bincount(steps_e, weights=np.einsum("si,si->s", w, d[steps_e]), minlength=E)


def sharp_edges(mesh, fans: BoundaryFans, features: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(feature (E,) bool, expected (E,) int)``: the feature edges of the mesh (its CAD curves,
    else dihedral features: :class:`torchconn.frames.constraints.BoundaryConstraint`, as the map
    takes them) and the fan angle ``q`` each boundary edge's geometry asks for: the nearest
    quarter multiple of its dihedral angle, clamped to 1..3, on a feature edge whose dihedral
    angle is more than 45° from ``pi`` (a sharp feature); 2 elsewhere; ``-1`` on interior edges."""
    E = mesh.edges.shape[0]
    feat = np.zeros(E, bool)
    if features and fans.edge.size:
        from ..frames.constraints import BoundaryConstraint

        bc = BoundaryConstraint.from_mesh(mesh)
        if bc.feature_edges is not None and bc.feature_edges.numel():
            fe = bc.feature_edges.cpu()
            fid, _ = mesh.edge_index(fe[:, 0], fe[:, 1])
            feat[fid.cpu().numpy()] = True
    expected = np.full(E, -1, np.int64)
    expected[fans.edge] = 2
    sharp = feat[fans.edge] & (np.abs(fans.dihedral - math.pi) > math.pi / 4)
    expected[fans.edge[sharp]] = np.clip(np.rint(fans.dihedral[sharp] / (math.pi / 2)), 1, 3).astype(np.int64)
    return feat, expected


def interior_class_table(dpar: np.ndarray, half_class: np.ndarray | None = None) -> np.ndarray:
    """``(E, 24)``: the class (:data:`EDGE_CLASSES` index, ``-1`` regular) of an interior edge
    for each holonomy in O, given its direction ``dpar (E, 3)`` in the chart the holonomy acts
    on: a quarter turn ``+90°`` about the direction is valence 3 (:mod:`.cut`), half turns take
    ``half_class (E,)`` (default 6: their 2 or 6 is the field's turn, :func:`field_turn`)."""
    typ, axis, w = _ELEMENTS
    E = dpar.shape[0]
    ax = np.maximum(axis, 0)
    sgn = w[np.arange(24), ax][None, :] * dpar[:, ax]  # (E, 24)
    out = np.full((E, 24), -1, np.int64)
    out[:, typ == 1] = np.where(sgn[:, typ == 1] > 0, 0, 1)
    hc = np.full(E, 3, np.int64) if half_class is None else np.asarray(half_class, np.int64)
    out[:, typ == 2] = hc[:, None]
    out[:, typ == 3] = 4
    return out


def _element_tables():
    from ..frames.singular import classify_holonomy

    typ, axis, w = classify_holonomy(torch.tensor(group_matrices(), dtype=torch.float64))
    return typ.numpy(), axis.numpy(), w.numpy()


_ELEMENTS = _element_tables()


def tangent_axes(mesh, start_frames: np.ndarray, edges: np.ndarray, boundary_edge: np.ndarray) -> np.ndarray:
    """``(E, 3)`` bool: for each interior edge with an end on the boundary, the parameter axes
    (frame axes of its start tet) more than 45° from the normal of some boundary face at that end.

    A singular line about such an axis through a boundary vertex lies in that face's boundary
    plane of the map (the tets between collapse); in particular a singular curve cannot end on a
    feature curve, whose faces have two normals. Edges without a boundary end: all false.
    """
    E = edges.shape[0]
    V = mesh.n_vertices
    bf = mesh.boundary_faces.cpu().numpy()
    X = mesh.vertices.detach().cpu().double().numpy()
    n = np.cross(X[bf[:, 1]] - X[bf[:, 0]], X[bf[:, 2]] - X[bf[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    vv = bf.reshape(-1)
    nn = np.repeat(n, 3, axis=0)
    order = np.argsort(vv, kind="stable")
    ptr = np.searchsorted(vv[order], np.arange(V + 1))
    nn = nn[order]
    out = np.zeros((E, 3), bool)
    c45 = np.sqrt(0.5)
    for end in (0, 1):
        v = edges[:, end]
        cnt = ptr[v + 1] - ptr[v]
        sel = np.nonzero((cnt > 0) & ~boundary_edge)[0]
        if not sel.size:
            continue
        lens = cnt[sel]
        rows = np.repeat(sel, lens)
        offs = np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens)
        normals = nn[np.repeat(ptr[v[sel]], lens) + offs]
        cosk = np.abs(np.einsum("pik,pi->pk", start_frames[rows], normals))  # |F[:, k] . n_f|
        np.logical_or.at(out, rows, cosk < c45)
    return out


# ----------------------------------------------------------------------------- the report
@dataclass
class Meshability:
    """The local meshability of a field's edge-based singular graph (module docstring).

    Per element (numpy): ``edge_hexes (E,)`` (hex count: interior 2..6 or ``-1`` complex;
    boundary ``q`` 0..4), ``edge_turn (E,)`` the lifted field turn ``A`` about each edge
    (radians; boundary edges: over the fan), ``boundary_expected (E,)`` the ``q`` a boundary
    edge's geometry asks for (2 off sharp features, ``-1`` on interior edges), ``feature_edge
    (E,)`` bool, ``vertex_class (V,)`` int8 codes of :data:`VERTEX_CLASSES`.

    Offending elements: ``complex_edges``, ``surface_valence2_edges``, ``touching_edges``,
    ``across_edges`` (edge ids), ``zipper_nodes``, ``invalid_nodes`` (vertex ids); for
    information ``singular_nodes``, ``boundary_crease_edges``, ``feature_mismatch_edges``.
    ``charts``: the :class:`~.cut.TetCharts` it was computed from.
    """

    edge_hexes: np.ndarray
    edge_turn: np.ndarray
    boundary_expected: np.ndarray
    feature_edge: np.ndarray
    vertex_class: np.ndarray
    complex_edges: np.ndarray
    zipper_nodes: np.ndarray
    invalid_nodes: np.ndarray
    surface_valence2_edges: np.ndarray
    touching_edges: np.ndarray
    across_edges: np.ndarray
    singular_nodes: np.ndarray
    boundary_crease_edges: np.ndarray
    feature_mismatch_edges: np.ndarray
    charts: TetCharts = field(repr=False)

    CONDITIONS = ("complex_edges", "zipper_nodes", "invalid_nodes", "surface_valence2_edges")
    """LMFF's local conditions (``meshable`` when all are empty)."""

    @property
    def meshable(self) -> bool:
        """No complex edge, zipper node, invalid node or valence ±2 edge on a surface."""
        return all(getattr(self, k).size == 0 for k in self.CONDITIONS)

    def counts(self) -> dict:
        """Number of elements of every condition and information list, and ``meshable`` (JSON-ready)."""
        out = {k: int(getattr(self, k).size) for k in (
            "complex_edges", "zipper_nodes", "invalid_nodes", "surface_valence2_edges", "touching_edges",
            "across_edges", "singular_nodes", "boundary_crease_edges", "feature_mismatch_edges")}
        out["meshable"] = bool(self.meshable)
        return out


def meshability_report(mesh, tet_frames, face_match: np.ndarray | None = None, *, charts: TetCharts | None = None,
                features: bool = True) -> Meshability:
    """LMFF's local conditions on the edge-based singular graph of per-tet frames.

    Args:
        mesh: a ``TetMesh``.
        tet_frames: ``(T, 3, 3)`` rotations (tensor or array), axes as columns.
        face_match: ``(F,)`` face matchings (default the best ones, :func:`~.cut.face_matchings`).
        charts: the :func:`~.cut.tet_charts` of the same input, if already computed.
        features: take sharp features from the mesh (:func:`sharp_edges`); without, every
            boundary edge is a surface edge.

    Returns:
        :class:`Meshability`.

    Raises:
        ValueError: frames of the wrong shape or not finite, bad ``face_match`` (as
            :func:`~.cut.tet_charts`).

    Cost: linear in the mesh (one pass of rotation logs over the steps of the edge walks).
    """
    ch = tet_charts(mesh, tet_frames, face_match) if charts is None else charts
    walks = edge_walks(mesh)
    edges = mesh.edges.cpu().numpy()
    E, V = edges.shape[0], mesh.n_vertices
    X = mesh.vertices.detach().cpu().double().numpy()
    Fc = ch.frames  # combed frames; ch.face_rot relates their charts
    bnd = walks.boundary
    turn = field_turn(mesh, Fc, ch.face_rot, walks)

    # interior hex counts (quarter turns from cut, half turns from the field's turn)
    hexes = np.full(E, 4, np.int64)
    hexes[ch.edge_valence == 3] = 3
    hexes[ch.edge_valence == 5] = 5
    half = ch.singular_edge & (ch.edge_type == 2)
    hexes[half] = np.where(turn[half] > 0, 2, 6)
    hexes[ch.singular_edge & ~ch.edge_meshable] = -1

    # boundary fans
    fans = boundary_fans(mesh, walks)
    eb = fans.edge
    d = X[edges[:, 1]] - X[edges[:, 0]]
    qtab = fan_quarter_table(Fc, fans, d[eb], fans.dihedral + turn[eb])
    P = walk_products(walks, ch.face_rot)[eb]
    hexes[eb] = qtab[np.arange(eb.size), P]
    feat, expected = sharp_edges(mesh, fans, features)
    sharp = bnd & (expected != 2)

    # vertex classes
    cls = np.where(bnd, boundary_edge_class(np.where(bnd, hexes, 2)), interior_edge_class(np.where(bnd, 4, hexes)))
    on_b = np.zeros(V, bool)
    on_b[mesh.boundary_vertices.cpu().numpy()] = True
    flat_sharp = np.bincount(edges[sharp & (hexes == 2)].reshape(-1), minlength=V)
    vclass = classify_vertices(edge_class_counts(edges, cls, V), on_b, flat_sharp)

    tang = tangent_axes(mesh, Fc[ch.edge_start_tet], edges, bnd)
    touching = ch.singular_edge & ch.edge_meshable & tang[np.arange(E), np.maximum(ch.edge_axis, 0)]
    return Meshability(
        edge_hexes=hexes, edge_turn=turn, boundary_expected=expected, feature_edge=feat, vertex_class=vclass,
        complex_edges=np.nonzero(ch.singular_edge & ~ch.edge_meshable)[0],
        zipper_nodes=np.nonzero(vclass == ZIPPER)[0], invalid_nodes=np.nonzero(vclass == INVALID)[0],
        surface_valence2_edges=np.nonzero(bnd & ~sharp & ((hexes == 0) | (hexes == 4)))[0],
        touching_edges=np.nonzero(touching)[0], across_edges=np.nonzero(ch.edge_across)[0],
        singular_nodes=np.nonzero(vclass == NODE)[0],
        boundary_crease_edges=np.nonzero(bnd & ~sharp & ((hexes == 1) | (hexes == 3)))[0],
        feature_mismatch_edges=np.nonzero(sharp & (hexes != expected))[0], charts=ch)


def walk_products(walks, face_rot: np.ndarray) -> np.ndarray:
    """``(E,)`` index into O of ``R_{n-1} ... R_0`` over every edge's walk for transitions
    ``face_rot (F,)``: the holonomy of interior edges, the fan's transport ``u_last = P u_first``
    of boundary edges (:meth:`~.cut.EdgeWalks.products`)."""
    return walks.products(face_rot)
