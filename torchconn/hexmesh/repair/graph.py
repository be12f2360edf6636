"""The edge-based singular graph of face matchings as a mutable state, with LMFF's classes and a cost.

:class:`SingularGraph` holds the face matchings ``match (F,)`` of a ``TetMesh`` with one frame per
tet (the conventions of :mod:`torchconn.hexmesh.cut`: ``F_t0 G[match[f]] ~ F_t1``, transition
``R_f = G[match[f]]^T``, ``u_t1 = R_f u_t0``) and, for every edge, the product of the transitions
over its counter-clockwise walk (:class:`~torchconn.hexmesh.cut.EdgeWalks`: the holonomy ``H_e``
of an interior edge, the fan transport ``P_e`` of a boundary edge), the edge's class and every
vertex's class, computed exactly as :func:`~torchconn.hexmesh.meshability.meshability_report`
computes them (a test compares the two on random matchings):

* interior edge: the class of its holonomy (:data:`~torchconn.hexmesh.meshability.EDGE_CLASSES`:
  ``v3``/``v5`` for a quarter turn by the sign of the turn against the edge's parametric
  direction, ``v2``/``v6`` for a half turn by the sign of the field's lifted turn about the
  edge, ``complex``; ``-1`` regular);
* boundary edge: its fan angle ``q`` in quarter turns (``q0, q1, q3, q4``; ``q = 2`` flat is
  ``-1``), and the ``q`` its geometry asks for (:func:`~torchconn.hexmesh.meshability.sharp_edges`);
* vertex: :data:`~torchconn.hexmesh.meshability.VERTEX_CLASSES` from the counts of its incident
  edge classes (:func:`~torchconn.hexmesh.meshability.classify_vertices`).

:meth:`SingularGraph.set_matchings` changes the matchings of a few faces and updates the walk
products of exactly the edges of those faces (a face is on the walks of its three edges only),
their classes and the classes of their end vertices; it returns what is needed to undo it. The
cost (:data:`REPAIR_WEIGHTS`) prices LMFF's conditions (complex edges, zipper and invalid nodes,
folded fans on surfaces), the information lists that keep the map from following the graph
(singular edges touching the boundary about a tangent axis, fan angles that do not match a sharp
feature, singular curves lying on a smooth part of the boundary: ``crease`` edges), the singular
edges themselves (short arcs along their axis first) and the rotation by which the matchings
depart from the frames' best matches (``misfit``, radians).
"""
from __future__ import annotations

import numpy as np
import torch

from ...frames.singular import classify_holonomy
from ..cut import GROUP_INV, GROUP_MUL, edge_walks, face_matchings, group_matrices
from ..meshability import (INVALID, VERTEX_CLASSES, ZIPPER, boundary_edge_class, boundary_edge_quarters, boundary_fans,
                           classify_vertices, edge_class_counts, fan_quarters, folded_fan_quarters, sharp_edges,
                           tangent_axes)

__all__ = ["SingularGraph", "REPAIR_WEIGHTS"]

REPAIR_WEIGHTS = {"complex": 16.0, "zipper": 8.0, "node": 8.0, "fold": 8.0, "mismatch": 4.0, "touching": 3.0,
                  "crease": 1.0, "singular": 0.1, "across": 0.5, "misfit": 0.25}
"""Weights of :meth:`SingularGraph.cost`: per complex edge, zipper node, invalid node (and vertex
at a complex edge), folded surface fan (LMFF's valence ±2 edge on a surface), boundary edge
whose fan angle differs from its sharp feature's, interior singular edge touching the boundary
about a tangent axis, singular boundary edge off sharp features (``q`` 1 or 3: a singular curve
lying on a smooth part of the boundary), interior singular edge, singular edge across its axis;
``misfit`` per radian by which a face's matching departs from its best one."""

_G = group_matrices()
_TYP, _AXIS, _W = (x.numpy() for x in classify_holonomy(torch.as_tensor(_G, dtype=torch.float64)))


def _signed_axis(v: np.ndarray) -> np.ndarray:
    k = np.abs(v).argmax(-1)
    out = np.zeros(v.shape, np.int64)
    s = np.sign(np.take_along_axis(v, k[..., None], -1)).astype(np.int64)
    np.put_along_axis(out, k[..., None], s, -1)
    return out


class SingularGraph:
    """Face matchings and their edge-based singular graph, updated face by face (module docstring).

    Args:
        mesh: a ``TetMesh`` (float64 CPU vertices are read).
        tet_frames: ``(T, 3, 3)`` rotations, axes as columns.
        face_match: ``(F,)`` matchings (default the best ones, :func:`~torchconn.hexmesh.cut.face_matchings`).
        weights: overrides of :data:`REPAIR_WEIGHTS`.
        features: take sharp features from the mesh (as :func:`~torchconn.hexmesh.meshability.meshability_report`).

    Attributes (numpy, current): ``match (F,)``, ``prod (E,)`` walk products, ``cls (E,)`` edge
    classes, ``vcnt (V, 9)`` incident class counts, ``fsc (V,)`` incident sharp edges with a flat
    fan, ``vcls (V,)`` vertex classes; static:
    ``best (F,)`` the best matchings, ``edges (E, 2)``, ``boundary (E,)`` bool, ``on_b (V,)``,
    ``expected (E,)`` fan angle asked for (``-1`` interior), ``sharp (E,)`` bool, ``walks``.

    Cost of construction: linear in the mesh (vectorized); of :meth:`set_matchings`: the walks
    of the edges of the changed faces.
    """

    def __init__(self, mesh, tet_frames, face_match: np.ndarray | None = None, *, weights: dict | None = None,
                 features: bool = True):
        w = dict(REPAIR_WEIGHTS)
        if weights:
            unknown = set(weights) - set(w)
            if unknown:
                raise ValueError(f"unknown weights {sorted(unknown)}; known: {sorted(w)}")
            w.update({k: float(v) for k, v in weights.items()})
        self.weights = w
        Fr = torch.as_tensor(tet_frames).detach().to("cpu", torch.float64)
        T = mesh.n_tets
        if Fr.shape != (T, 3, 3):
            raise ValueError(f"tet_frames must have shape (T, 3, 3) = ({T}, 3, 3) for this mesh, got {tuple(Fr.shape)}")
        if not torch.isfinite(Fr).all():
            raise ValueError("tet_frames has non-finite entries")
        self.mesh = mesh
        self.frames = Fr.numpy()
        self.best = face_matchings(mesh, Fr)
        F = self.best.shape[0]
        if face_match is None:
            match = self.best.copy()
        else:
            match = np.asarray(face_match, np.int64).copy()
            if match.shape != (F,) or (match.size and (match.min() < 0 or match.max() > 23)):
                raise ValueError(f"face_match must be ({F},) indices into the 24 elements of O")
        self.face_tets = mesh.face_tets.cpu().numpy()
        self.interior_face = (self.face_tets >= 0).all(1)
        match[~self.interior_face] = 0
        self.match = match
        self.faces = mesh.faces.cpu().numpy()
        self.face_edges = mesh.face_edges.cpu().numpy()
        self.edges = mesh.edges.cpu().numpy()
        E, V = self.edges.shape[0], mesh.n_vertices
        self.V = V
        self.walks = walks = edge_walks(mesh)
        self.boundary = walks.boundary
        self.steps_e = np.repeat(np.arange(E), np.diff(walks.ptr))
        self.to_tet = np.where(self.face_tets[walks.face, 0] == walks.from_tet, self.face_tets[walks.face, 1],
                               self.face_tets[walks.face, 0])
        self.on_b = np.zeros(V, bool)
        self.on_b[mesh.boundary_vertices.cpu().numpy()] = True
        X = mesh.vertices.detach().cpu().double().numpy()
        self.X = X
        d = X[self.edges[:, 1]] - X[self.edges[:, 0]]
        self.dir = d / np.linalg.norm(d, axis=1, keepdims=True)
        self.dpar = np.einsum("eji,ej->ei", self.frames[walks.start], d)  # direction in the start tet's chart
        # boundary fans: signed axes of the first normal and of the last normal for every P
        fans = boundary_fans(mesh, walks)
        self.fans = fans
        eb = fans.edge
        self.bpos = np.full(E, -1, np.int64)
        self.bpos[eb] = np.arange(eb.size)
        self.a0 = _signed_axis(np.einsum("eji,ej->ei", self.frames[fans.first_tet], fans.n_first))
        n1 = np.einsum("eji,ej->ei", self.frames[fans.last_tet], fans.n_last)
        self.a1 = _signed_axis(np.einsum("pji,ej->epi", _G.astype(np.float64), n1))  # (Eb, 24, 3)
        self.feature, self.expected = sharp_edges(mesh, fans, features)
        self.sharp = self.boundary & (self.expected != 2)
        self.tang = tangent_axes(mesh, self.frames[walks.start], self.edges, self.boundary)  # (E, 3)
        # the fan angle q of every boundary edge for every fan transport P, with the fan's own angle
        # as the estimate: exact for every P but a folded one (a0 = -a1: 0 or 4 by the field's turn)
        bdpar = np.einsum("eji,ej->ei", self.frames[fans.first_tet], d[eb])
        self.fan_opp = (self.a0[:, None, :] == -self.a1).all(-1)  # (Eb, 24)
        self.fan_q = fan_quarters(np.broadcast_to(self.a0[:, None, :], self.a1.shape), self.a1,
                                  np.broadcast_to(bdpar[:, None, :], self.a1.shape),
                                  np.broadcast_to(fans.dihedral[:, None], self.a1.shape[:2]))
        # misfit of every face for every matching: the angle between F_t0 g and F_t1 (radians)
        fi = np.nonzero(self.interior_face)[0]
        self.misfit_tab = np.zeros((F, 24))
        if fi.size:
            M = np.einsum("fji,fjk->fik", self.frames[self.face_tets[fi, 0]], self.frames[self.face_tets[fi, 1]])
            tr = np.einsum("gab,fab->fg", _G.astype(np.float64), M)
            self.misfit_tab[fi] = np.arccos(np.clip((tr - 1) / 2, -1, 1))
        vl = np.zeros(len(VERTEX_CLASSES))
        vl[ZIPPER] = w["zipper"]
        vl[INVALID] = w["node"]
        vl[VERTEX_CLASSES.index("complex")] = w["node"]
        self.vlut = vl
        # current state
        self.prod = walks.products(self.transitions())
        self.cls = self.edge_classes(np.arange(E))
        self.vcnt = edge_class_counts(self.edges, self.cls, V)
        self.fsc = np.bincount(self.edges[self.sharp & (self.cls < 0)].reshape(-1), minlength=V)
        self.vcls = classify_vertices(self.vcnt, self.on_b, self.fsc)

    # ------------------------------------------------------------------ per-edge quantities
    def transitions(self) -> np.ndarray:
        """``(F,)`` index of ``R_f = G[match[f]]^T`` (identity on boundary faces)."""
        return GROUP_INV[self.match]

    def edge_products(self, e_ids: np.ndarray, match: np.ndarray | None = None) -> np.ndarray:
        """Walk products of the edges ``e_ids`` for ``match`` (default the current matchings)."""
        e_ids = np.asarray(e_ids, np.int64)
        R = GROUP_INV[self.match if match is None else match]
        w = self.walks
        lens = w.ptr[e_ids + 1] - w.ptr[e_ids]
        out = np.zeros(e_ids.size, np.int64)
        for k in range(int(lens.max(initial=0))):  # loop over the steps (the largest valence)
            sel = np.nonzero(lens > k)[0]
            s = w.ptr[e_ids[sel]] + k
            r = R[w.face[s]]
            out[sel] = GROUP_MUL[np.where(w.forward[s], r, GROUP_INV[r]), out[sel]]
        return out

    def field_turn(self, e_ids: np.ndarray) -> np.ndarray:
        """The lifted turn ``A`` (radians) of the field about the edges ``e_ids`` for the current
        matchings (:func:`~torchconn.hexmesh.meshability.field_turn`, over these edges only)."""
        from ...lie import so3

        e_ids = np.asarray(e_ids, np.int64)
        w = self.walks
        lens = w.ptr[e_ids + 1] - w.ptr[e_ids]
        rows = np.repeat(np.arange(e_ids.size), lens)
        s = np.repeat(w.ptr[e_ids], lens) + (np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens))
        if not s.size:
            return np.zeros(e_ids.size)
        R = GROUP_INV[self.match[w.face[s]]]
        S = np.where(w.forward[s], R, GROUP_INV[R])
        Q = self.frames[self.to_tet[s]] @ _G[S] @ np.transpose(self.frames[w.from_tet[s]], (0, 2, 1))
        lg = so3.log(torch.as_tensor(Q)).numpy()
        return np.bincount(rows, weights=np.einsum("si,si->s", lg, self.dir[e_ids[rows]]), minlength=e_ids.size)

    def edge_classes(self, e_ids: np.ndarray, prod: np.ndarray | None = None) -> np.ndarray:
        """Classes (:data:`~torchconn.hexmesh.meshability.EDGE_CLASSES` index, ``-1`` regular or
        flat) of the edges ``e_ids`` with walk products ``prod`` (default the current ones)."""
        e_ids = np.asarray(e_ids, np.int64)
        P = self.prod[e_ids] if prod is None else np.asarray(prod, np.int64)
        out = np.full(e_ids.size, -1, np.int64)
        bnd = self.boundary[e_ids]
        ii = np.nonzero(~bnd)[0]
        if ii.size:
            e, H = e_ids[ii], P[ii]
            typ, ax = _TYP[H], np.maximum(_AXIS[H], 0)
            sgn = _W[H, ax] * self.dpar[e, ax]
            c = np.full(ii.size, -1, np.int64)
            c[typ == 1] = np.where(sgn[typ == 1] > 0, 0, 1)
            c[typ == 3] = 4
            half = np.nonzero(typ == 2)[0]
            if half.size:
                c[half] = np.where(self.field_turn(e[half]) > 0, 2, 3)
            out[ii] = c
        bi = np.nonzero(bnd)[0]
        if bi.size:
            e, Pb = e_ids[bi], P[bi]
            r = self.bpos[e]
            q = self.fan_q[r, Pb]
            opp = self.fan_opp[r, Pb]
            if opp.any():  # a folded fan: 0 or 4 by the fan's angle plus the field's turn
                q = q.copy()
                q[opp] = folded_fan_quarters(self.fans.dihedral[r[opp]] + self.field_turn(e[opp]))
            out[bi] = boundary_edge_class(q)
        return out

    # ------------------------------------------------------------------ cost
    def edge_cost(self, e_ids: np.ndarray) -> np.ndarray:
        """Per-edge part of :meth:`cost` for the edges ``e_ids`` (current state)."""
        e_ids = np.asarray(e_ids, np.int64)
        w = self.weights
        c = self.cls[e_ids]
        P = self.prod[e_ids]
        bnd = self.boundary[e_ids]
        out = np.zeros(e_ids.size)
        sing = ~bnd & (c >= 0)
        out += sing * w["singular"]
        out += (~bnd & (c == 4)) * w["complex"]
        turn = sing & (c != 4)
        ax = np.maximum(_AXIS[P], 0)
        along = np.abs(self.dpar[e_ids]).argmax(1)
        out += (turn & (ax != along)) * w["across"]
        out += (turn & self.tang[e_ids, ax]) * w["touching"]
        q = boundary_edge_quarters(c)
        sharp = self.sharp[e_ids]
        out += (bnd & ~sharp & ((q == 0) | (q == 4))) * w["fold"]
        out += (bnd & ~sharp & ((q == 1) | (q == 3))) * w["crease"]
        out += (bnd & sharp & (q != self.expected[e_ids])) * w["mismatch"]
        return out

    def vertex_cost(self, v_ids: np.ndarray) -> np.ndarray:
        """Per-vertex part of :meth:`cost` (zipper, invalid and complex vertices)."""
        return self.vlut[self.vcls[np.asarray(v_ids, np.int64)]]

    def misfit(self, f_ids: np.ndarray | None = None) -> np.ndarray:
        """Radians by which the matchings of faces ``f_ids`` depart from their best ones."""
        f = np.arange(self.match.size) if f_ids is None else np.asarray(f_ids, np.int64)
        return self.misfit_tab[f, self.match[f]] - self.misfit_tab[f, self.best[f]]

    def cost(self) -> float:
        """The repair cost of the current state (module docstring, :data:`REPAIR_WEIGHTS`)."""
        E = self.edges.shape[0]
        return float(self.edge_cost(np.arange(E)).sum() + self.vertex_cost(np.arange(self.V)).sum()
                     + self.weights["misfit"] * self.misfit().sum())

    def local_cost(self, faces: np.ndarray) -> float:
        """The part of :meth:`cost` that a change of the matchings of ``faces`` can change."""
        faces = np.asarray(faces, np.int64)
        es = np.unique(self.face_edges[faces])
        vs = np.unique(self.edges[es])
        return float(self.edge_cost(es).sum() + self.vertex_cost(vs).sum()
                     + self.weights["misfit"] * self.misfit(faces).sum())

    # ------------------------------------------------------------------ changes
    def set_matchings(self, faces: np.ndarray, values: np.ndarray) -> tuple:
        """Set ``match[faces] = values`` and update the edges of those faces and their vertices.

        Returns an undo token for :meth:`undo`.
        """
        faces = np.asarray(faces, np.int64)
        values = np.asarray(values, np.int64)
        if (~self.interior_face[faces]).any():
            raise ValueError(f"faces {faces[~self.interior_face[faces]][:5].tolist()} are boundary faces: "
                             "they have no matching")
        es = np.unique(self.face_edges[faces])
        vs = np.unique(self.edges[es])
        token = (faces, self.match[faces].copy(), es, self.prod[es].copy(), self.cls[es].copy(), vs,
                 self.vcnt[vs].copy(), self.fsc[vs].copy(), self.vcls[vs].copy())
        self.match[faces] = values
        self.prod[es] = self.edge_products(es)
        new = self.edge_classes(es)
        self._recount(es, new)
        return token

    def _recount(self, es, new):
        old = self.cls[es]
        for end in (0, 1):
            o = old >= 0
            np.subtract.at(self.vcnt, (self.edges[es[o], end], old[o]), 1)
            n = new >= 0
            np.add.at(self.vcnt, (self.edges[es[n], end], new[n]), 1)
            sh = self.sharp[es]  # sharp edges with a flat fan (class -1)
            np.subtract.at(self.fsc, self.edges[es[sh & ~o], end], 1)
            np.add.at(self.fsc, self.edges[es[sh & ~n], end], 1)
        self.cls[es] = new
        vs = np.unique(self.edges[es])
        self.vcls[vs] = classify_vertices(self.vcnt[vs], self.on_b[vs], self.fsc[vs])

    def undo(self, token: tuple) -> None:
        """Restore the state before the :meth:`set_matchings` call that returned ``token``."""
        faces, match, es, prod, cls, vs, vcnt, fsc, vcls = token
        self.match[faces] = match
        self.prod[es] = prod
        self.cls[es] = cls
        self.vcnt[vs] = vcnt
        self.fsc[vs] = fsc
        self.vcls[vs] = vcls

    # ------------------------------------------------------------------ summaries
    def counts(self) -> dict:
        """Counts of LMFF's conditions and the information lists (the keys of
        :meth:`~torchconn.hexmesh.meshability.Meshability.counts` that this state tracks)."""
        b, c = self.boundary, self.cls
        q = boundary_edge_quarters(c)
        turn = ~b & (c >= 0) & (c != 4)
        ax = np.maximum(_AXIS[self.prod], 0)
        out = {
            "complex_edges": int((~b & (c == 4)).sum()),
            "zipper_nodes": int((self.vcls == ZIPPER).sum()),
            "invalid_nodes": int((self.vcls == INVALID).sum()),
            "surface_valence2_edges": int((b & ~self.sharp & ((q == 0) | (q == 4))).sum()),
            "touching_edges": int((turn & self.tang[np.arange(c.size), ax]).sum()),
            "boundary_crease_edges": int((b & ~self.sharp & ((q == 1) | (q == 3))).sum()),
            "feature_mismatch_edges": int((b & self.sharp & (q != self.expected)).sum()),
            "singular_edges": int((~b & (c >= 0)).sum()),
        }
        out["meshable"] = all(out[k] == 0 for k in ("complex_edges", "zipper_nodes", "invalid_nodes",
                                                    "surface_valence2_edges"))
        return out

    def bad_vertices_mask(self) -> np.ndarray:
        """``(V,)`` bool: the vertices the repair works on (:meth:`bad_vertices`)."""
        b, c = self.boundary, self.cls
        q = boundary_edge_quarters(c)
        turn = ~b & (c >= 0) & (c != 4)
        ax = np.maximum(_AXIS[self.prod], 0)
        E = c.size
        touch = self.edges[turn & self.tang[np.arange(E), ax]].reshape(-1)
        bad_b = self.edges[(b & ~self.sharp & (q != 2)) | (b & self.sharp & (q != self.expected))].reshape(-1)
        badv = self.vlut[self.vcls] > 0
        badv[touch[self.on_b[touch]]] = True
        badv[bad_b] = True
        return badv

    def bad_vertices(self) -> np.ndarray:
        """Vertices the repair works on: zipper, invalid and complex vertices, the boundary ends
        of touching edges, the ends of folded, mismatched and crease boundary edges."""
        return np.nonzero(self.bad_vertices_mask())[0]
