"""Per-tet charts of a frame field: face transitions, edge holonomy, the cut surface and combing.

Conventions
-----------
* A chart per tet: the integer-grid map ``u_t`` of tet ``t`` is sought with
  ``grad u_t ~ F_t^T / h`` (``F_t (3, 3)`` the tet's frame, axes as columns, ``h`` the hex edge
  length), so parameter axis ``k`` of tet ``t`` follows frame axis ``k`` of ``F_t``.
* **Face transition.** For an interior face ``f`` with ``mesh.face_tets[f] = (t0, t1)`` and the
  face matching ``g_f = match(F_t0, F_t1)`` (``F_t0 g_f ~ F_t1``,
  :func:`torchconn.frames.octahedral.match`), the charts of the two tets are related on the face
  by ``u_t1 = R_f u_t0 + s_f`` with ``R_f = g_f^T`` (because ``F_t1^T ~ g_f^T F_t0^T``) and a
  translation ``s_f`` the map decides. ``face_rot[f]`` is the index of ``R_f`` in
  :func:`~torchconn.frames.octahedral.group` (``0`` = identity; ``0`` on boundary faces).
* **Edge holonomy.** Around an interior edge ``(a < b)`` the tets are visited counter-clockwise
  about the direction ``a -> b`` (right-hand rule), starting at the lowest tet id; composing the
  transitions crossed gives ``H_e = R_{n-1} ... R_0``, an element of O acting on the start tet's
  chart. ``H_e = I`` on regular edges. On a singular edge that a valid map can follow, ``H_e``
  is a quarter or half turn about the parameter axis ``k`` along the edge: ``+90°`` about the
  edge's parametric direction is **valence 3** (three hexes around it: the charts around the
  edge unfold to an angle of ``3π/2``), ``-90°`` **valence 5**, ``180°`` valence 2 or 6. A complex
  ``H_e`` (120° about a diagonal, 180° about a face diagonal) admits no integer-grid map there.
* **Cut surface and combing** (HEXMESH.md step 2): a BFS spanning tree of the dual graph (tets
  across interior faces, :func:`torchconn.frames.propagate.spanning_tree`) leaves every other
  interior face cut; the cut shrinks by repeatedly un-cutting the single cut face at any
  interior *regular* edge that has exactly one; the frames are combed along the tree,
  ``F'_t = F_t G[comb[t]]``, so that the transition across every un-cut face is the identity
  (tree faces by construction, the others because a regular edge's holonomy is the identity).
  What remains cut has its boundary on singular edges (and on the mesh boundary).

All of this is combinatorics, built once: integer numpy arrays, vectorized over faces and
edges (loops run over BFS levels, the valence around an edge, or the rounds of the shrinking).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch

from ..frames import octahedral
from ..frames.propagate import spanning_tree
from ..frames.singular import classify_holonomy

__all__ = ["GROUP_MUL", "GROUP_INV", "group_matrices", "TetCharts", "tet_charts", "face_matchings", "face_corner_pairs",
           "edge_walks"]


def group_matrices() -> np.ndarray:
    """The 24 elements of O as an ``(24, 3, 3)`` int64 array (identity first; a fresh copy)."""
    return octahedral.group_tables()[0].copy()


_, GROUP_MUL, GROUP_INV = octahedral.group_tables()
"""``GROUP_MUL[i, j]``: index of ``G[i] @ G[j]``; ``GROUP_INV[i]``: index of ``G[i]^T``."""


@dataclass
class TetCharts:
    """Charts of a frame field on a tet mesh: combed frames, transitions, holonomy, cut surface.

    Attributes (numpy; ``T`` tets, ``F`` faces, ``E`` edges of the mesh):

    * ``frames (T, 3, 3)`` float64: the combed tet frames ``F_t G[comb[t]]``.
    * ``comb (T,)``: the relabeling applied to each input tet frame.
    * ``face_rot (F,)``: ``R_f`` of the module docstring after combing (0 on boundary faces).
    * ``interior_face (F,)`` bool, ``tree_face (F,)`` bool, ``cut (F,)`` bool: the cut surface
      (interior faces only; ``face_rot[f] == 0`` wherever ``cut[f]`` is false).
    * ``edge_holonomy (E,)``: ``H_e`` (index into O) of each interior edge, ``-1`` on boundary
      edges; ``edge_start_tet (E,)`` the tet whose chart ``H_e`` acts on.
    * ``edge_type (E,)``: codes of :data:`torchconn.frames.singular.FACE_TYPES`
      (``regular/quarter/half/complex``) of ``H_e``, ``-1`` on boundary edges;
      ``edge_axis (E,)`` the parameter axis of a quarter or half turn (``-1`` otherwise);
      ``edge_valence (E,)``: 3 or 5 for a quarter turn about the edge, 0 for a half turn
      (2 or 6), 4 on regular edges, ``-1`` on boundary edges and on complex singular edges;
      ``edge_meshable (E,)`` bool: regular, or a quarter or half turn (about any axis);
      ``edge_across (E,)`` bool: a turn whose axis is not the parameter axis closest to the
      edge's direction in the field (the map must turn such an edge onto its axis: a zipper
      where it is long, a zig-zag step of a singular curve where it is short).
    * ``tet_face_corners`` etc.: see :func:`face_corner_pairs`.
    """

    frames: np.ndarray
    comb: np.ndarray
    face_rot: np.ndarray
    interior_face: np.ndarray
    tree_face: np.ndarray
    cut: np.ndarray
    edge_holonomy: np.ndarray
    edge_start_tet: np.ndarray
    edge_type: np.ndarray
    edge_axis: np.ndarray
    edge_valence: np.ndarray
    edge_meshable: np.ndarray
    edge_across: np.ndarray

    @property
    def singular_edge(self) -> np.ndarray:
        """``(E,)`` bool: interior edges with ``H_e != I``."""
        return self.edge_holonomy > 0

    def counts(self) -> dict:
        """Counts of the cut and of the edge-based singular graph (JSON-ready)."""
        sing = self.singular_edge
        return {
            "cut_faces": int(self.cut.sum()),
            "interior_faces": int(self.interior_face.sum()),
            "singular_edges": int(sing.sum()),
            "valence3_edges": int((self.edge_valence == 3).sum()),
            "valence5_edges": int((self.edge_valence == 5).sum()),
            "half_turn_edges": int((sing & (self.edge_type == 2)).sum()),
            "unmeshable_singular_edges": int((sing & ~self.edge_meshable).sum()),
            "singular_edges_across_axis": int(self.edge_across.sum()),
            "complex_edges": int((self.edge_type == 3).sum()),
        }


# ----------------------------------------------------------------------------- corners of faces
def face_corner_pairs(tets: np.ndarray, faces: np.ndarray, tet_faces: np.ndarray,
                      face_tets: np.ndarray) -> np.ndarray:
    """Local corners of each face's vertices in its two tets.

    Returns ``(F, 2, 3)`` int64: ``out[f, s, m]`` is the local corner (0..3) in tet
    ``face_tets[f, s]`` of vertex ``faces[f, m]`` (``-1`` where that tet does not exist).
    """
    F = faces.shape[0]
    out = np.full((F, 2, 3), -1, np.int64)
    T = tets.shape[0]
    for slot in range(4):  # loop over the 4 face slots of a tet
        f = tet_faces[:, slot]
        others = np.array([k for k in range(4) if k != slot])
        loc = np.broadcast_to(others, (T, 3))
        verts = tets[:, others]
        order = np.argsort(verts, axis=1, kind="stable")  # align with the sorted face rows
        loc = np.take_along_axis(loc, order, axis=1)
        t_idx = np.arange(T)
        side = np.where(face_tets[f, 0] == t_idx, 0, 1)
        out[f, side] = loc
    return out


# ----------------------------------------------------------------------------- edge cycles
def _edge_walk(tets: np.ndarray, tet_edges: np.ndarray, tet_faces: np.ndarray, face_tets: np.ndarray,
               edges: np.ndarray, E: int):
    """Counter-clockwise walk of the tets around every edge (module docstring).

    Returns ``(start_tet (E,), steps)``: ``steps`` is a list of ``(edge ids, face crossed,
    from_tet, to_tet)`` arrays, one entry per step of the walk (edges whose walk has ended or hit
    the boundary drop out); boundary edges start at the tet that begins their fan, so the walk
    visits the whole fan and stops at the boundary.
    """
    T = tets.shape[0]
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    # for the incidence (t, local pair p = (i, j)): the other two local corners (k, l) with
    # parity of the permutation (i, j, k, l); the exit face is the one opposite "c" (module doc)
    inc_edge = tet_edges.reshape(-1)
    inc_tet = np.repeat(np.arange(T), 6)
    i_loc = np.tile(pairs[:, 0], T)
    j_loc = np.tile(pairs[:, 1], T)
    rest = np.array([[k for k in range(4) if k not in p] for p in pairs.tolist()])  # (6, 2), k < l
    parity = np.array([_perm_parity([*p, *r]) for p, r in zip(pairs.tolist(), rest.tolist())])
    k_loc = np.tile(rest[:, 0], T)
    l_loc = np.tile(rest[:, 1], T)
    par = np.tile(parity, T)
    # the edge is a -> b with a < b; if tets[t, i] > tets[t, j] the pair is reversed: flip parity
    rev = tets[inc_tet, i_loc] > tets[inc_tet, j_loc]
    par = par ^ rev.astype(np.int64)
    c_loc = np.where(par == 0, k_loc, l_loc)  # orient(a, b, c, d) > 0
    d_loc = np.where(par == 0, l_loc, k_loc)
    exit_face = tet_faces[inc_tet, c_loc]  # the face (a, b, d): counter-clockwise neighbour
    entry_face = tet_faces[inc_tet, d_loc]  # the face (a, b, c): clockwise neighbour
    # incidence lookup by (edge, tet)
    key = inc_edge * T + inc_tet
    order = np.argsort(key)
    skey = key[order]

    def lookup(e, t):
        pos = np.searchsorted(skey, e * T + t)
        return order[pos]

    # start: boundary edges at the tet whose entry face is a boundary face; interior at lowest tet
    is_bface = (face_tets < 0).any(1)
    inc_start_b = is_bface[entry_face]
    start = np.full(E, -1, np.int64)
    # lowest tet per edge among incidences (interior start)
    o2 = np.lexsort((inc_tet, inc_edge))
    first = np.ones(o2.size, bool)
    first[1:] = inc_edge[o2][1:] != inc_edge[o2][:-1]
    start[inc_edge[o2][first]] = inc_tet[o2][first]
    bs = np.nonzero(inc_start_b)[0]
    start[inc_edge[bs]] = inc_tet[bs]
    boundary_edge = np.zeros(E, bool)
    boundary_edge[inc_edge[bs]] = True

    steps = []
    cur_e = np.arange(E)
    cur_t = start.copy()
    while cur_e.size:
        inc = lookup(cur_e, cur_t)
        f = exit_face[inc]
        t0, t1 = face_tets[f, 0], face_tets[f, 1]
        nxt = np.where(t0 == cur_t, t1, t0)
        alive = nxt >= 0  # boundary face: the fan has ended
        steps.append((cur_e[alive], f[alive], cur_t[alive], nxt[alive]))
        done = ~alive | (nxt == start[cur_e])
        keep = ~done
        cur_e, cur_t = cur_e[keep], nxt[keep]
        if len(steps) > T + 1:  # pragma: no cover - a walk longer than the mesh is a bug
            raise RuntimeError("edge walk did not close")
    return start, boundary_edge, steps


def _perm_parity(p) -> int:
    p = list(p)
    n = 0
    for i in range(len(p)):
        for j in range(i + 1, len(p)):
            n += p[i] > p[j]
    return n % 2


@dataclass
class EdgeWalks:
    """The counter-clockwise walk of the tets around every edge, as CSR arrays.

    ``ptr (E+1,)``; for edge ``e`` the steps ``ptr[e]:ptr[e+1]`` in walk order cross the faces
    ``face[k]`` from tet ``from_tet[k]``, ``forward[k]`` when that is ``mesh.face_tets[face, 0]``
    (the step applies ``R_f``, else ``R_f^T``); ``start (E,)`` the first tet; ``boundary (E,)``
    bool, edges on the boundary (their walk is the open fan, from boundary face to boundary face).
    """

    ptr: np.ndarray
    face: np.ndarray
    from_tet: np.ndarray
    forward: np.ndarray
    start: np.ndarray
    boundary: np.ndarray

    def holonomy(self, face_rot: np.ndarray) -> np.ndarray:
        """``(E,)`` index of ``H_e = R_{n-1} ... R_0`` for transitions ``face_rot (F,)``; ``-1`` on
        boundary edges."""
        hol = self.products(face_rot)
        hol[self.boundary] = -1
        return hol

    def products(self, face_rot: np.ndarray) -> np.ndarray:
        """``(E,)`` index into O of ``R_{n-1} ... R_0`` over every edge's walk for transitions
        ``face_rot (F,)``: the holonomy of interior edges, the fan's transport ``u_last = P u_first``
        of boundary edges (:meth:`holonomy` without the ``-1`` on boundary edges)."""
        R = np.where(self.forward, face_rot[self.face], GROUP_INV[face_rot[self.face]])
        out = np.zeros(self.start.size, np.int64)
        lens = np.diff(self.ptr)
        for k in range(int(lens.max(initial=0))):  # loop over the steps (max valence)
            e = np.nonzero(lens > k)[0]
            out[e] = GROUP_MUL[R[self.ptr[e] + k], out[e]]
        return out


def edge_walks(mesh) -> EdgeWalks:
    """:class:`EdgeWalks` of a ``TetMesh`` (module docstring: the counter-clockwise order)."""
    tets = mesh.tets.cpu().numpy()
    face_tets = mesh.face_tets.cpu().numpy()
    E = mesh.edges.shape[0]
    start, boundary_edge, steps = _edge_walk(tets, mesh.tet_edges.cpu().numpy(), mesh.tet_faces.cpu().numpy(),
                                             face_tets, mesh.edges.cpu().numpy(), E)
    e_all = np.concatenate([st[0] for st in steps]) if steps else np.zeros(0, np.int64)
    k_all = np.concatenate([np.full(st[0].size, k) for k, st in enumerate(steps)]) if steps else np.zeros(0, np.int64)
    f_all = np.concatenate([st[1] for st in steps]) if steps else np.zeros(0, np.int64)
    t_all = np.concatenate([st[2] for st in steps]) if steps else np.zeros(0, np.int64)
    order = np.lexsort((k_all, e_all))
    ptr = np.zeros(E + 1, np.int64)
    np.add.at(ptr, e_all + 1, 1)
    ptr = np.cumsum(ptr)
    f = f_all[order]
    t = t_all[order]
    return EdgeWalks(ptr=ptr, face=f, from_tet=t, forward=face_tets[f, 0] == t, start=start, boundary=boundary_edge)


# ----------------------------------------------------------------------------- main entry
def face_matchings(mesh, tet_frames) -> np.ndarray:
    """``(F,)`` index into O of the best matching ``g_f = match(F_t0, F_t1)`` of every interior
    face (``F_t0 g_f ~ F_t1``, ``(t0, t1) = mesh.face_tets[f]``); 0 on boundary faces."""
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    face_tets = mesh.face_tets.cpu().numpy()
    fi = np.nonzero((face_tets >= 0).all(1))[0]
    g = np.zeros(face_tets.shape[0], np.int64)
    if fi.size:
        idx, _ = octahedral.match(Fr[torch.as_tensor(face_tets[fi, 0])], Fr[torch.as_tensor(face_tets[fi, 1])])
        g[fi] = idx.numpy()
    return g


def tet_charts(mesh, tet_frames, face_match: np.ndarray | None = None) -> TetCharts:
    """Charts, transitions, edge holonomy, cut surface and combing of per-tet frames.

    Args:
        mesh: a ``TetMesh``.
        tet_frames: ``(T, 3, 3)`` rotations (tensor or array), axes as columns.
        face_match: ``(F,)`` the face matchings ``g_f`` to use (default :func:`face_matchings`,
            the best ones; a repaired singular structure passes its own).

    Returns:
        :class:`TetCharts` (module docstring for every convention).

    Cost: linear in the mesh; the loops run over BFS levels of the dual tree, the steps of the
    walk around the edges (the largest valence) and the rounds of the cut shrinking.
    """
    Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
    T = mesh.n_tets
    if Fr.shape != (T, 3, 3):
        raise ValueError(f"tet_frames must have shape (T, 3, 3) = ({T}, 3, 3) for this mesh, got {tuple(Fr.shape)}")
    if not torch.isfinite(Fr).all():
        bad = torch.nonzero(~torch.isfinite(Fr).flatten(1).all(1)).flatten()[:5].tolist()
        raise ValueError(f"tet_frames has non-finite entries (tets {bad})")
    tets = mesh.tets.cpu().numpy()
    faces = mesh.faces.cpu().numpy()
    face_tets = mesh.face_tets.cpu().numpy()
    tet_faces = mesh.tet_faces.cpu().numpy()
    tet_edges = mesh.tet_edges.cpu().numpy()
    edges = mesh.edges.cpu().numpy()
    F, E = faces.shape[0], edges.shape[0]
    interior = (face_tets >= 0).all(1)
    fi = np.nonzero(interior)[0]

    # face matchings g_f (F_t0 g ~ F_t1) and transitions R_f = g^T
    if face_match is None:
        g_idx = face_matchings(mesh, Fr)
    else:
        g_idx = np.asarray(face_match, np.int64)
        if g_idx.shape != (F,) or (g_idx.size and (g_idx.min() < 0 or g_idx.max() > 23)):
            raise ValueError(f"face_match must be ({F},) indices into the 24 elements of O")

    # dual spanning tree (tets across interior faces), rooted at the lowest tet of each component
    d0, d1 = face_tets[fi, 0], face_tets[fi, 1]
    lo, hi = np.minimum(d0, d1), np.maximum(d0, d1)
    dkey = lo * T + hi
    dorder = np.argsort(dkey)
    dual_edges = np.stack([lo[dorder], hi[dorder]], 1)
    dual_face = fi[dorder]
    tree = spanning_tree(edges=torch.as_tensor(dual_edges), n_vertices=T)
    tree_face = np.zeros(F, bool)
    comb = np.zeros(T, np.int64)
    for lv in tree.levels:  # loop over BFS levels of the dual tree
        child = lv.child.numpy()
        par = lv.parent.numpy()
        f = dual_face[lv.edge.numpy()]
        tree_face[f] = True
        # matching from parent to child: g_f if the parent is face_tets[f, 0], else g_f^T
        g_pc = np.where(face_tets[f, 0] == par, g_idx[f], GROUP_INV[g_idx[f]])
        comb[child] = GROUP_MUL[GROUP_INV[g_pc], comb[par]]  # h_c = g_pc^T h_p
    # combed matchings g'_f = h_t0^T g_f h_t1 and transitions R'_f = g'^T
    g_comb = np.zeros(F, np.int64)
    if fi.size:
        g_comb[fi] = GROUP_MUL[GROUP_MUL[GROUP_INV[comb[face_tets[fi, 0]]], g_idx[fi]], comb[face_tets[fi, 1]]]
    face_rot = GROUP_INV[g_comb]
    face_rot[~interior] = 0
    if (face_rot[tree_face] != 0).any():  # pragma: no cover - guaranteed by the combing
        raise RuntimeError("combing left a non-identity transition on a tree face")
    G = group_matrices()
    frames = Fr.numpy() @ G[comb].astype(np.float64)

    # holonomy around every edge (counter-clockwise walk)
    walks = edge_walks(mesh)
    start, boundary_edge = walks.start, walks.boundary
    hol = walks.holonomy(face_rot)

    # classification of the holonomy (exact, from frames.singular)
    Hm = torch.as_tensor(G[np.maximum(hol, 0)], dtype=torch.float64)
    typ, axis, w = classify_holonomy(Hm)
    typ, axis, w = typ.numpy().copy(), axis.numpy().copy(), w.numpy()
    typ[boundary_edge] = -1
    axis[boundary_edge] = -1
    # parametric direction of the edge a -> b in the start tet's chart
    X = mesh.vertices.detach().cpu().numpy().astype(np.float64)
    dvec = X[edges[:, 1]] - X[edges[:, 0]]
    dpar = np.einsum("eji,ej->ei", frames[start], dvec)  # F'^T d
    along = np.abs(dpar).argmax(1)
    sing = hol > 0
    turn = sing & ((typ == 1) | (typ == 2))
    meshable = (hol == 0) | turn
    valence = np.full(E, 4, np.int64)
    valence[boundary_edge] = -1
    ax0 = np.maximum(axis, 0)
    sgn = np.sign(dpar[np.arange(E), ax0])
    quarter = sing & (typ == 1)
    # w = sin(theta) e_k: +90 deg about the edge's direction (w_k * sign(d_k) > 0) is valence 3
    wk = w[np.arange(E), ax0]
    valence[quarter] = np.where(wk[quarter] * sgn[quarter] > 0, 3, 5)
    valence[sing & (typ == 2)] = 0
    valence[sing & ~meshable] = -1
    across = turn & (axis != along)

    # cut surface: non-tree interior faces, shrunk at regular interior edges with one cut face
    cut = interior & ~tree_face
    cut = _shrink_cut(cut, mesh.face_edges.cpu().numpy(), regular_edge=(hol == 0), E=E)
    if (face_rot[interior & ~cut] != 0).any():  # pragma: no cover - the holonomy argument
        raise RuntimeError("an un-cut face has a non-identity transition")
    return TetCharts(frames=frames, comb=comb, face_rot=face_rot, interior_face=interior, tree_face=tree_face,
                     cut=cut, edge_holonomy=hol, edge_start_tet=start, edge_type=typ, edge_axis=axis,
                     edge_valence=valence, edge_meshable=meshable | boundary_edge, edge_across=across)


def _shrink_cut(cut: np.ndarray, face_edges: np.ndarray, regular_edge: np.ndarray, E: int) -> np.ndarray:
    """Un-cut, round by round, the single cut face at every interior regular edge with exactly one.

    ``regular_edge`` is false on boundary edges (their faces do not close a cycle). Each round
    only revisits the edges of the faces un-cut in the previous round.
    """
    cut = cut.copy()
    F = face_edges.shape[0]
    # edge -> faces CSR
    fe = face_edges.reshape(-1)
    ff = np.repeat(np.arange(F), 3)
    inc = sp.csr_matrix((np.ones(fe.size, np.int8), (fe, ff)), shape=(E, F))
    indptr, indices = inc.indptr, inc.indices
    count = np.bincount(fe[cut[ff]], minlength=E)
    frontier = np.nonzero(regular_edge & (count == 1))[0]
    while frontier.size:  # loop over rounds (the depth of the peeling)
        frontier = frontier[regular_edge[frontier] & (count[frontier] == 1)]
        if not frontier.size:
            break
        # the one cut face of each frontier edge
        lens = indptr[frontier + 1] - indptr[frontier]
        starts = indptr[frontier]
        offs = np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens)
        cols = indices[np.repeat(starts, lens) + offs]
        sel = cut[cols]
        uncut = np.unique(cols[sel])
        cut[uncut] = False
        touched = face_edges[uncut].reshape(-1)
        np.subtract.at(count, touched, 1)
        frontier = np.unique(touched)
    return cut
