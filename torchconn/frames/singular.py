"""The singular graph of an octahedral frame field: classified singular faces chained into curves.

Conventions
-----------
* Frames are per vertex, ``frames[i][:, k]`` is axis ``k`` at vertex ``i`` (world coordinates),
  matched along canonical edges ``(i < j)`` by ``F_i g*_ij ~ F_j``
  (:func:`~torchconn.frames.octahedral.match_edges`).
* A face ``[a < b < c]`` of ``mesh.faces`` is traversed ``a -> b -> c -> a``; its matched holonomy
  ``H = g_ab g_bc g_ca`` is an exact element of O that acts on the coordinates of frame ``a``
  (``F_a H ~ F_a`` once the small residual rotations are removed). ``H = I`` on regular faces.
  With per-vertex frames the singular curves cross the faces; a curve crosses exactly the faces
  whose ``H != I`` (e.g. Nieser et al. 2011, Ray et al. 2016).
* **Type** of a singular face, by the conjugacy class of ``H`` in O (read from ``tr H``, exact):

  - ``quarter`` (``tr H = 1``): ±90° about frame axis ``k`` (the diagonal entry ``H_kk = 1``);
  - ``half`` (``tr H = -1``, ``H`` diagonal): 180° about frame axis ``k``;
  - ``complex``: 120° about a cube diagonal (``tr H = 0``) or 180° about a face diagonal
    (``tr H = -1``, ``H`` not diagonal).

* **Valence** of a quarter-turn face. Let ``n = (v_b - v_a) x (v_c - v_a)`` be the normal of the
  traversed loop and ``w = axial(H - H^T)/2 = sin(theta) e_k`` the signed rotation axis in frame-a
  coordinates. The field itself turns *opposite* to its matched holonomy: along the loop the
  residual rotations compose to ``H^{-1}``. A field turning by +90° about ``n`` while going once
  around the curve in the sense of ``n`` (right-hand rule) is the valence-3 configuration (index
  ``+1/4`` in a cross-section: 3 hexes share the edge); its holonomy is ``-90°`` about ``n``.
  Hence: ``(F_a w) . n < 0`` -> **valence 3**, ``> 0`` -> **valence 5**. The rule does not depend
  on the traversal direction (reversing the loop flips both ``H`` and ``n``). Example
  (``tests/test_singular.py``): ``F = Rz(phi/4)`` with ``phi`` the angle around the z-axis gives
  one valence-3 curve along it, ``Rz(-phi/4)`` a valence-5 curve. A half turn's sign is lost
  (180° = -180°): its valence (2 or 6) is reported as ``0``. (A smooth ±180° field is never
  resolved on a triangle anyway: the three angular gaps around the curve average 120°, frame
  steps of 60° > 45° that the matching takes for the next quarter turn, so half-turn faces come
  from rough fields.)
* **Chaining** (one-time setup on the singular faces only): a tet with exactly two singular faces
  links them; a curve ends at a boundary singular face (``"boundary"``), at a junction tet with
  three or four singular faces (``"junction"``), or inside a tet with exactly one singular face
  (``"inside"``, which a valid field never has); a curve without ends is ``closed``. Its points
  are the face barycenters with the barycenter of each linking tet between consecutive faces,
  the end tet's barycenter added at a junction or inside end, and the first face repeated at the
  end of a closed curve.
* **Validity** of a quarter-turn face: its rotation axis ``F_a e_k`` is the frame axis of ``F_a``
  most aligned with the curve tangent there (``argmax_j |F_a e_j . t| = k``); otherwise the face
  is a "zipper"/turning point. The tangent ``t`` at a face is the chord between the polyline
  points ``2w`` rows (``w`` faces, ``tangent_window``) before and after the face's barycenter;
  near an open curve's end the window slides inward to keep its length (clipped only on curves
  shorter than it), on closed curves it wraps around.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from . import octahedral

__all__ = ["FACE_TYPES", "CURVE_TYPES", "END_KINDS", "classify_holonomy", "edge_matchings",
           "face_holonomy_from_matchings", "SingularCurve", "SingularGraph", "singular_graph"]

FACE_TYPES = ("regular", "quarter", "half", "complex")
"""Codes of :attr:`SingularGraph.face_type` (index into this tuple)."""
CURVE_TYPES = ("valence3", "valence5", "half", "complex", "mixed")
"""Labels of a curve: every face of the curve of one kind, else ``"mixed"``."""
END_KINDS = ("boundary", "junction", "inside")


def classify_holonomy(H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Type, axis and signed axis of elements ``H (..., 3, 3)`` of O (exact signed permutations).

    Returns:
        ``type (...)`` long, codes of :data:`FACE_TYPES`; ``axis (...)`` long, the frame axis
        ``k`` of a quarter or half turn (``-1`` otherwise); ``w (..., 3)`` the axial vector
        ``axial(H - H^T)/2 = sin(theta) e_k`` (``±e_k`` for a quarter turn, ``0`` for half turns).
    """
    tr = H.diagonal(dim1=-2, dim2=-1).sum(-1)
    off = (H - torch.diag_embed(H.diagonal(dim1=-2, dim2=-1))).abs().flatten(-2).amax(-1)
    # entries of H are exactly 0 or ±1, so 0.5 separates every comparison below
    regular = tr > 2.5
    quarter = (tr - 1).abs() < 0.5
    half = ((tr + 1).abs() < 0.5) & (off < 0.5)
    typ = torch.full(tr.shape, 3, dtype=torch.long, device=H.device)
    typ = torch.where(quarter, 1, torch.where(half, 2, torch.where(regular, 0, typ)))
    axis = torch.where(quarter | half, H.diagonal(dim1=-2, dim2=-1).argmax(-1), -1)
    w = 0.5 * torch.stack([H[..., 2, 1] - H[..., 1, 2], H[..., 0, 2] - H[..., 2, 0],
                           H[..., 1, 0] - H[..., 0, 1]], -1)
    return typ, axis, w


def edge_matchings(frames: torch.Tensor, mesh, matchings: torch.Tensor | None = None) -> torch.Tensor:
    """The matchings ``g*_ij (E, 3, 3)`` of ``mesh.edges`` (computed when ``matchings`` is None).

    ``matchings`` may be given as ``(E, 3, 3)`` elements of O or as ``(E,)`` long indices into
    :func:`~torchconn.frames.octahedral.group`, for the canonical edges ``mesh.edges``.
    """
    E = mesh.edges.shape[0]
    if matchings is None:
        return octahedral.match_edges(frames, mesh.edges)[1]
    if not torch.is_tensor(matchings):
        raise TypeError(f"matchings must be a tensor, got {type(matchings).__name__}")
    if matchings.dim() == 1 and not matchings.is_floating_point():
        if matchings.shape[0] != E:
            raise ValueError(f"matchings has {matchings.shape[0]} indices but the mesh has {E} edges")
        return octahedral.group(frames.dtype, frames.device)[matchings.to(frames.device)]
    if matchings.shape != (E, 3, 3):
        raise ValueError(f"matchings must be (E,) group indices or (E, 3, 3) = ({E}, 3, 3), "
                         f"got {tuple(matchings.shape)}")
    return matchings.to(dtype=frames.dtype, device=frames.device)


def face_holonomy_from_matchings(g: torch.Tensor, mesh) -> tuple[torch.Tensor, torch.Tensor]:
    """``(g_ab (F, 3, 3), g_ab g_bc (F, 3, 3), H = g_ab g_bc g_ac^T (F, 3, 3))`` of the faces
    ``[a < b < c]`` from the canonical-edge matchings ``g (E, 3, 3)`` (``mesh.face_edges`` lists
    the edges ``bc, ac, ab``)."""
    fe = mesh.face_edges
    g_bc, g_ac, g_ab = g[fe[:, 0]], g[fe[:, 1]], g[fe[:, 2]]
    g_abc = g_ab @ g_bc
    return g_ab, g_abc, g_abc @ g_ac.transpose(-1, -2)


@dataclass
class SingularCurve:
    """One singular curve: an ordered chain of singular faces.

    Attributes:
        faces: ``(n,)`` long, mesh face indices in chain order.
        points: ``(m, 3)`` polyline points (module docstring).
        label: one of :data:`CURVE_TYPES`.
        closed: no ends.
        ends: two ``(kind, tet)`` pairs, kind in :data:`END_KINDS` (tet ``-1`` on the boundary);
            empty for a closed curve.
        n_valid, n_quarter: quarter-turn faces of the curve whose axis is tangent-dominant, and all.
    """

    faces: torch.Tensor
    points: torch.Tensor
    label: str
    closed: bool
    ends: tuple = ()
    n_valid: int = 0
    n_quarter: int = 0


@dataclass
class SingularGraph:
    """The singular graph (module docstring); per-singular-face tensors have ``S`` rows.

    Attributes:
        face_index: ``(S,)`` long, mesh face index of each singular face (ascending).
        face_holonomy: ``(S, 3, 3)`` matched holonomy in frame-``a`` coordinates.
        face_type: ``(S,)`` long codes of :data:`FACE_TYPES`.
        face_axis: ``(S,)`` long frame axis of a quarter/half turn, ``-1`` for complex.
        face_valence: ``(S,)`` long: 3 or 5 for quarter turns, 0 otherwise.
        face_tangent: ``(S, 3)`` curve tangent (not normalized).
        face_valid: ``(S,)`` bool, quarter turn with tangent-dominant axis.
        face_curve: ``(S,)`` long, the curve each face belongs to.
        curves: list of :class:`SingularCurve`.
        junctions: list of dicts ``{"tet", "point" (3,), "curves", "labels"}`` (a curve with both
            ends at the same junction is listed twice).
        n_tets_one_singular_face: tets where a curve ends inside.
    """

    face_index: torch.Tensor
    face_holonomy: torch.Tensor
    face_type: torch.Tensor
    face_axis: torch.Tensor
    face_valence: torch.Tensor
    face_tangent: torch.Tensor
    face_valid: torch.Tensor
    face_curve: torch.Tensor
    curves: list = field(default_factory=list)
    junctions: list = field(default_factory=list)
    n_tets_one_singular_face: int = 0

    def counts(self) -> dict:
        """The counts of the metrics (Python numbers).

        Keys: ``n_singular_curves``; ``n_singular_faces_by_type`` (``{"quarter", "half",
        "complex"}``); ``n_quarter_faces_by_valence`` (``{3, 5}``); ``valid_fraction`` (valid
        quarter-turn faces / quarter-turn faces, ``nan`` without any); ``n_junctions``;
        ``n_curves_ending_inside`` (curves with at least one end inside a tet; 0 for a valid field).
        """
        t = self.face_type
        nq = int((t == 1).sum())
        return {
            "n_singular_curves": len(self.curves),
            "n_singular_faces_by_type": {name: int((t == c).sum()) for c, name in enumerate(FACE_TYPES) if c},
            "n_quarter_faces_by_valence": {v: int((self.face_valence == v).sum()) for v in (3, 5)},
            "valid_fraction": int(self.face_valid.sum()) / nq if nq else float("nan"),
            "n_junctions": len(self.junctions),
            "n_curves_ending_inside": sum(any(k == "inside" for k, _ in c.ends) for c in self.curves),
        }


def _chain(mask: np.ndarray, tet_faces: np.ndarray, face_tets: np.ndarray):
    """Order the singular faces into chains (numpy; loops over singular faces only).

    Returns ``(count (T,), face_tets of the singular faces (S, 2), chains)`` with each chain
    ``(seq (list of positions), links (tets between consecutive faces), closed, end0, end1)`` and
    an end ``(position, side)`` or ``None``.
    """
    S_idx = np.nonzero(mask)[0]
    S = S_idx.size
    pos = np.full(mask.shape[0], -1, np.int64)
    pos[S_idx] = np.arange(S)
    count = mask[tet_faces].sum(1)
    ft = face_tets[S_idx]  # (S, 2)
    nbr = np.full((S, 2), -1, np.int64)
    link = np.nonzero(count == 2)[0]
    lf = tet_faces[link]
    pair = pos[lf[mask[lf]].reshape(-1, 2)]  # (L, 2) positions of the two singular faces
    for c in range(2):  # the side of face pair[:, c] that holds the link tet
        p, q = pair[:, c], pair[:, 1 - c]
        side = np.where(ft[p, 0] == link, 0, 1)
        nbr[p, side] = q
    visited = np.zeros(S, bool)
    chains = []
    starts = np.concatenate([np.nonzero((nbr < 0).any(1))[0], np.arange(S)])
    for start in starts:  # each singular face is visited once
        if visited[start]:
            continue
        open_side = int(np.argmax(nbr[start] < 0)) if (nbr[start] < 0).any() else 0
        closed = False
        seq, links = [int(start)], []
        visited[start] = True
        cur, out = int(start), 1 - open_side
        while True:
            nxt = int(nbr[cur, out])
            if nxt < 0:
                break
            if nxt == start:
                closed = True
                links.append(int(ft[cur, out]))
                break
            tet = int(ft[cur, out])
            links.append(tet)
            into = 0 if ft[nxt, 0] == tet else 1
            cur, out = nxt, 1 - into
            seq.append(nxt)
            visited[nxt] = True
        ends = (None, None) if closed else ((int(start), open_side), (cur, out))
        chains.append((seq, links, closed, *ends))
    return count, ft, chains


def singular_graph(frames: torch.Tensor, mesh, matchings: torch.Tensor | None = None,
                   tangent_window: int = 3) -> SingularGraph:
    """Extract and classify the singular graph of per-vertex frames (module docstring).

    Args:
        frames: ``(V, 3, 3)`` rotations, ``frames[i][:, k]`` axis ``k`` at vertex ``i``.
        mesh: a ``TetMesh``.
        matchings: optional ``(E, 3, 3)`` or ``(E,)`` group indices for ``mesh.edges`` (default:
            :func:`~torchconn.frames.octahedral.match_edges` of ``frames``).
        tangent_window: ``w``, the tangent at a face is the chord between the polyline points
            ``2w`` rows (``w`` faces) before and after it (a discrete curve zigzags through the
            faces by about one edge length; the chord averages that out).

    Returns:
        :class:`SingularGraph` on the device and in the dtype of ``frames``.
    """
    V = mesh.vertices.shape[0]
    if not torch.is_tensor(frames) or frames.shape != (V, 3, 3) or not frames.is_floating_point():
        shape = tuple(frames.shape) if torch.is_tensor(frames) else type(frames).__name__
        raise ValueError(f"frames must be a floating (V, 3, 3) = ({V}, 3, 3) tensor for this mesh, got {shape}")
    if tangent_window < 1:
        raise ValueError(f"tangent_window must be >= 1, got {tangent_window}")
    frames = frames.detach()
    dev, dt = frames.device, frames.dtype
    g = edge_matchings(frames, mesh, matchings)
    _, _, H = face_holonomy_from_matchings(g, mesh)
    typ_all, axis_all, w_all = classify_holonomy(H)
    mask_t = typ_all != 0
    S_idx = torch.nonzero(mask_t).squeeze(1)
    faces = mesh.faces[S_idx]
    Hs, typ, axis, w = H[S_idx], typ_all[S_idx], axis_all[S_idx], w_all[S_idx]
    X = mesh.vertices.to(dt)
    Fa = frames[faces[:, 0]]
    n = torch.linalg.cross(X[faces[:, 1]] - X[faces[:, 0]], X[faces[:, 2]] - X[faces[:, 0]], dim=-1)
    sgn = ((Fa @ w.unsqueeze(-1)).squeeze(-1) * n).sum(-1)
    valence = torch.where(typ == 1, torch.where(sgn < 0, 3, 5), 0)

    # --- chaining (numpy, one-time, over the singular faces)
    count, ft, chains = _chain(mask_t.cpu().numpy(), mesh.tet_faces.cpu().numpy(), mesh.face_tets.cpu().numpy())
    S = int(S_idx.numel())
    s_np = S_idx.cpu().numpy()
    C = len(chains)
    face_curve = np.full(S, -1, np.int64)
    row_is_face, row_id, n_rows, ends_all, closed_all = [], [], np.zeros(C, np.int64), [], np.zeros(C, bool)
    t_from, t_to = np.zeros(S, np.int64), np.zeros(S, np.int64)
    offset = 0

    def end_of(e):
        tet = int(ft[e[0], e[1]])
        return ("boundary" if tet < 0 else "junction" if count[tet] >= 3 else "inside"), tet

    for cid, (seq, links, closed, e0, e1) in enumerate(chains):
        face_curve[seq] = cid
        ends = (end_of(e0), end_of(e1)) if not closed else ()
        k = len(seq)
        # rows: [end tet], f0, t0, f1, ..., f(k-1), [t(k-1), f0 if closed], [end tet]
        kinds = np.zeros(2 * k - 1 + 2 * closed, bool)
        kinds[0::2] = True
        ids = np.empty(kinds.size, np.int64)
        ids[0:2 * k:2] = s_np[seq]
        ids[1:2 * k - 1:2] = links[:k - 1]
        if closed:
            ids[2 * k - 1], ids[2 * k] = links[k - 1], s_np[seq[0]]
        head = [t for kind, t in ends[:1] if t >= 0]
        tail = [t for kind, t in ends[1:] if t >= 0]
        kinds = np.concatenate([np.zeros(len(head), bool), kinds, np.zeros(len(tail), bool)])
        ids = np.concatenate([np.asarray(head, np.int64), ids, np.asarray(tail, np.int64)])
        m = ids.size
        r = len(head) + 2 * np.arange(k)  # row of each face of the chain
        lo, hi = r - 2 * tangent_window, r + 2 * tangent_window
        if closed:  # the last row repeats the first face: wrap over m - 1 distinct rows
            lo, hi = lo % (m - 1), hi % (m - 1)
        else:  # near an end, slide the window inward so the chord keeps its length
            lo, hi = lo - np.maximum(hi - (m - 1), 0), hi - np.minimum(lo, 0)
            lo, hi = np.maximum(lo, 0), np.minimum(hi, m - 1)
        t_from[seq], t_to[seq] = offset + lo, offset + hi
        row_is_face.append(kinds)
        row_id.append(ids)
        n_rows[cid], closed_all[cid] = m, closed
        ends_all.append(ends)
        offset += m

    fb = mesh.face_barycenters.to(dt)
    tb = mesh.tet_barycenters.to(dt)
    if C:
        kinds_t = torch.as_tensor(np.concatenate(row_is_face), device=dev)
        ids_t = torch.as_tensor(np.concatenate(row_id), device=dev)
        P = torch.where(kinds_t[:, None], fb[ids_t.clamp(max=fb.shape[0] - 1)], tb[ids_t.clamp(max=tb.shape[0] - 1)])
        tangent = P[torch.as_tensor(t_to, device=dev)] - P[torch.as_tensor(t_from, device=dev)]
    else:
        P, tangent = torch.zeros(0, 3, dtype=dt, device=dev), torch.zeros(0, 3, dtype=dt, device=dev)
    dom = (Fa * tangent.unsqueeze(-1)).sum(-2).abs().argmax(-1)  # |F_a e_j . t|
    valid = (typ == 1) & (dom == axis)

    # --- per-curve statistics by bincount over face_curve
    typ_np, val_np, valid_np = typ.cpu().numpy(), valence.cpu().numpy(), valid.cpu().numpy()
    nf = np.bincount(face_curve, minlength=C)
    per = lambda x: np.bincount(face_curve, weights=x, minlength=C).astype(np.int64)  # noqa: E731
    nq, nv = per(typ_np == 1), per(valid_np)
    n3, n5 = per((typ_np == 1) & (val_np == 3)), per((typ_np == 1) & (val_np == 5))
    nh, nc = per(typ_np == 2), per(typ_np == 3)
    label_idx = np.select([n3 == nf, n5 == nf, nh == nf, nc == nf], [0, 1, 2, 3], 4)
    order = torch.as_tensor(np.concatenate([c[0] for c in chains]) if C else np.zeros(0, np.int64), device=dev)
    curve_faces = torch.split(S_idx[order], nf.tolist())
    curve_points = torch.split(P, n_rows.tolist())
    curves = [SingularCurve(faces=curve_faces[i], points=curve_points[i], label=CURVE_TYPES[label_idx[i]],
                            closed=bool(closed_all[i]), ends=ends_all[i], n_valid=int(nv[i]), n_quarter=int(nq[i]))
              for i in range(C)]
    junctions = {}
    for cid, ends in enumerate(ends_all):
        for kind, tet in ends:
            if kind == "junction":
                junctions.setdefault(tet, []).append(cid)
    jlist = [{"tet": t, "point": tb[t], "curves": cs, "labels": [curves[c].label for c in cs]}
             for t, cs in sorted(junctions.items())]
    return SingularGraph(
        face_index=S_idx, face_holonomy=Hs, face_type=typ, face_axis=axis, face_valence=valence,
        face_tangent=tangent, face_valid=valid, face_curve=torch.as_tensor(face_curve, device=dev),
        curves=curves, junctions=jlist, n_tets_one_singular_face=int((count == 1).sum()))
