"""Singular-structure search: edge matchings that remove complex-type singular faces.

The singular structure of an octahedral field is a function of its edge matchings alone: the
holonomy of a face ``[a<b<c]`` is ``H = g_ab g_bc g_ac^T`` (:func:`~torchconn.frames.singular.face_holonomy_from_matchings`),
and its type (:data:`~torchconn.frames.singular.FACE_TYPES`: regular, quarter turn, half turn,
complex) is what a hex mesher reads. A *complex-type* face (a holonomy that is not a turn about a
frame axis, e.g. a third of a turn about a cube diagonal) has no valid hex-mesh singularity. The
frames' own matchings (each edge's best element of O, :func:`~torchconn.frames.octahedral.match_edges`)
are a local choice; changing the matching of one edge changes the holonomy of every face around
that edge and nothing else.

:func:`repair_matchings` is a greedy descent over these discrete choices. Every face carries a cost
by type, ``face_costs = (regular, quarter, half, complex)`` (default ``(0, 1, 1, 6)``: a complex face
costs more than the two quarter-turn faces that usually replace it), and every edge the increase of
its matched residual ``||F_i g - F_j||^2 - ||F_i g* - F_j||^2`` over the best match ``g*`` (weighted
by ``residual_weight``: a move the frames cannot follow cheaply is charged). A *move* sets the
matching of one edge of a complex face to another element of O; among the moves that lower the
total face cost, the one with the lowest ``face-cost change + residual_weight x residual change`` is
taken, the types of the faces around its edge are updated, and the search repeats until no move
lowers the face cost (it terminates: the integer-valued face cost falls at every move). The best
move of every edge of a complex face is scored once, in one batched evaluation (the 24 elements
of O at once), and after each move only the edges of the faces around the moved edge are
rescored (the only ones whose moves changed); the loop runs over moves, not mesh elements.

The frames then follow the prescribed matchings by :func:`~torchconn.frames.quality_paths.relax_to_matchings`
(L-BFGS with the matchings held). Until 2026-11-27 the connection method made the result a
candidate and ran the quality paths from it; on the HexMe ``c`` models those candidates never gave a
good hex mesh where the others did not, so the method no longer does (the hex stage repairs the
structure, :mod:`torchconn.hexmesh.repair`): this module is a tool beside it.

Measurements (2026-11-25, of a default since superseded): ``docs/results/hexme.md`` at commit f4941d1
(git history).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from . import octahedral
from .quality_paths import relax_to_matchings
from .singular import classify_holonomy

__all__ = ["FACE_COSTS", "MOVED_EDGE_WEIGHTS", "complex_face_count", "edge_face_incidence", "repair_matchings",
           "repair_structure"]

#: Default costs of the face types ``(regular, quarter, half, complex)`` of :func:`repair_matchings`.
FACE_COSTS = (0.0, 1.0, 1.0, 6.0)
#: Default weights of the re-matched edges in the relaxations of :func:`repair_structure`.
MOVED_EDGE_WEIGHTS = (1.0, 10.0)


def edge_face_incidence(mesh) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The faces around every edge, in CSR form (built once per mesh).

    Returns:
        ``(offsets (E + 1,), faces (3F,), slot (3F,))`` long: the faces containing edge ``e`` are
        ``faces[offsets[e]:offsets[e + 1]]``, and ``slot`` is the column of ``e`` in
        ``mesh.face_edges`` (``0: bc, 1: ac, 2: ab``) for each of them.
    """
    fe = mesh.face_edges
    nF, E = fe.shape[0], mesh.edges.shape[0]
    pe = fe.reshape(-1)
    order = torch.argsort(pe, stable=True)
    pf = torch.arange(nF, device=fe.device).repeat_interleave(3)[order]
    pp = torch.arange(3, device=fe.device).repeat(nF)[order]
    offsets = torch.searchsorted(pe[order], torch.arange(E + 1, device=fe.device))
    return offsets, pf, pp


def _types_of(g: torch.Tensor) -> torch.Tensor:
    """Face types of the matchings ``g (..., 3, 3, 3)`` of the face edges ``bc, ac, ab`` (dim -3):
    the holonomy ``g_ab g_bc g_ac^T`` of :func:`~torchconn.frames.singular.face_holonomy_from_matchings`."""
    return classify_holonomy(g[..., 2, :, :] @ g[..., 0, :, :] @ g[..., 1, :, :].transpose(-1, -2))[0]


def _face_types(idx: torch.Tensor, G: torch.Tensor, mesh, faces: torch.Tensor | None = None) -> torch.Tensor:
    fe = mesh.face_edges if faces is None else mesh.face_edges[faces]
    return _types_of(G[idx[fe]])


def repair_matchings(frames: torch.Tensor, mesh, *, matchings: torch.Tensor | None = None,
                     residual_weight: float = 0.5, face_costs: Sequence[float] = FACE_COSTS,
                     max_moves: int | None = None) -> tuple[torch.Tensor, dict]:
    """Greedy search over edge matchings that lowers the face-type cost (module docstring).

    Args:
        frames: ``(V, 3, 3)`` the field (its matched residuals price the moves).
        mesh: ``TetMesh``.
        matchings: ``(E,)`` long group indices to start from (default: the frames' own,
            :func:`~torchconn.frames.octahedral.match_edges`).
        residual_weight: ``mu >= 0``, the weight of the residual increase of a move.
        face_costs: costs of the face types ``(regular, quarter, half, complex)``; the complex
            cost must be the largest.
        max_moves: bound on the number of moves (default ``4 x`` the initial complex faces
            ``+ 16``).

    Returns:
        ``(matchings (E,) long, info)``; ``info`` has ``"moves"`` (a list of ``(edge, old index,
        new index, face-cost change, residual change)``), ``"complex_before"``,
        ``"complex_after"``, ``"singular_before"``, ``"singular_after"`` (face counts of the
        matchings before and after) and ``"cost_before"``, ``"cost_after"``.
    """
    costs = [float(c) for c in face_costs]
    if len(costs) != 4 or not all(math.isfinite(c) and c >= 0 for c in costs) or costs[3] < max(costs[:3]):
        raise ValueError(f"repair_matchings: face_costs must be 4 finite costs >= 0 with the complex one the largest, "
                         f"got {face_costs}")
    if not (math.isfinite(residual_weight) and residual_weight >= 0):
        raise ValueError(f"repair_matchings: residual_weight must be finite and >= 0, got {residual_weight}")
    V, E = mesh.vertices.shape[0], mesh.edges.shape[0]
    if not torch.is_tensor(frames) or tuple(frames.shape) != (V, 3, 3):
        raise ValueError(f"repair_matchings: frames must be a ({V}, 3, 3) tensor for this mesh, got "
                         f"{tuple(frames.shape) if torch.is_tensor(frames) else type(frames).__name__}")
    dev = frames.device
    G = octahedral.group(frames.dtype, dev)
    if matchings is None:
        idx = octahedral.match_edges(frames, mesh.edges)[0]
    else:
        if not torch.is_tensor(matchings) or matchings.shape != (E,) or matchings.is_floating_point():
            raise ValueError(f"repair_matchings: matchings must be an ({E},) integer tensor of group indices")
        idx = matchings.to(dev)
    idx = idx.clone()
    cost = torch.tensor(costs, dtype=frames.dtype, device=dev)
    typ = _face_types(idx, G, mesh)
    n_complex0 = int((typ == 3).sum())
    info = {"complex_before": n_complex0, "singular_before": int((typ > 0).sum()),
            "cost_before": float(cost[typ].sum()), "moves": []}
    limit = 4 * n_complex0 + 16 if max_moves is None else int(max_moves)
    if n_complex0:
        offsets, pf, pp = edge_face_incidence(mesh)
        fe, edges = mesh.face_edges, mesh.edges
        E = edges.shape[0]
        # the best move of every candidate edge (an edge of a complex face), kept per edge and
        # updated only around each move: a move changes the types of the faces around its edge,
        # so only the edges of those faces change their best move or stop/start being candidates
        best_score = torch.full((E,), math.inf, dtype=frames.dtype, device=dev)
        best_k = torch.zeros(E, dtype=torch.long, device=dev)
        best_dc = torch.zeros(E, dtype=frames.dtype, device=dev)
        best_dres = torch.zeros(E, dtype=frames.dtype, device=dev)

        def rescore(ce: torch.Tensor) -> None:
            """Best move (lowest score among the face-cost-lowering ones) of each edge of ``ce``
            (sorted, unique), or ``inf`` where the edge is on no complex face or has none."""
            cnt = offsets[ce + 1] - offsets[ce]
            owner = torch.repeat_interleave(torch.arange(ce.numel(), device=dev), cnt)
            start = torch.repeat_interleave(offsets[ce] - torch.cumsum(cnt, 0) + cnt, cnt)
            sel = start + torch.arange(owner.numel(), device=dev)
            f, slot = pf[sel], pp[sel]
            on_complex = torch.zeros(ce.numel(), dtype=torch.long, device=dev).index_add_(
                0, owner, (typ[f] == 3).long()) > 0
            g3 = G[idx[fe[f]]]  # (m, 3, 3, 3)
            gg = g3[:, None].expand(-1, 24, -1, -1, -1).clone()  # (m, 24, 3, 3, 3)
            gg[torch.arange(f.numel(), device=dev), :, slot] = G[None].expand(f.numel(), -1, -1, -1)
            dcost = cost[_types_of(gg)] - cost[typ[f]][:, None]  # (m, 24)
            dc = torch.zeros(ce.numel(), 24, dtype=frames.dtype, device=dev).index_add_(0, owner, dcost)
            # residual of every element of O on an edge: ||F_i G_k - F_j||^2 = 6 - 2 tr(F_j^T F_i G_k)
            M = frames[edges[ce, 1]].transpose(-1, -2) @ frames[edges[ce, 0]]
            res = 6.0 - 2.0 * torch.einsum("nab,kba->nk", M, G)
            dres = res - res.gather(1, idx[ce][:, None])
            score = torch.where((dc < -0.5) & on_complex[:, None], dc + residual_weight * dres,
                                torch.full_like(dc, math.inf))
            sc, k = score.min(1)  # the first k on a tie
            best_score[ce], best_k[ce] = sc, k
            best_dc[ce] = dc.gather(1, k[:, None]).squeeze(1)
            best_dres[ce] = dres.gather(1, k[:, None]).squeeze(1)

        rescore(torch.unique(fe[typ == 3].reshape(-1)))
        while len(info["moves"]) < limit:
            e = int(best_score.argmin())  # the first edge on a tie: the same order as a full rescan
            if not math.isfinite(float(best_score[e])):
                break
            k = int(best_k[e])
            info["moves"].append((e, int(idx[e]), k, float(best_dc[e]), float(best_dres[e])))
            idx[e] = k
            around = pf[offsets[e]:offsets[e + 1]]
            typ[around] = _face_types(idx, G, mesh, around)
            rescore(torch.unique(fe[around].reshape(-1)))
    info.update(complex_after=int((typ == 3).sum()), singular_after=int((typ > 0).sum()),
                cost_after=float(cost[typ].sum()))
    return idx, info


def complex_face_count(frames: torch.Tensor, mesh) -> int:
    """Complex-type singular faces of the frames' own matchings."""
    idx = octahedral.match_edges(frames, mesh.edges)[0]
    return int((_face_types(idx, octahedral.group(frames.dtype, frames.device), mesh) == 3).sum())


def repair_structure(frames: torch.Tensor, mesh, *, a_ref: float, d_ref: float, passes: int = 2,
                     residual_weight: float = 0.5, face_costs: Sequence[float] = FACE_COSTS,
                     moved_edge_weights: Sequence[float] = MOVED_EDGE_WEIGHTS, relax_iters: int = 40,
                     dirichlet_weight: float = 8.0, feature_weight: float = 1.0, eps: float = 1e-3,
                     align_eps: float = 1e-3, angle_deg: float = 30.0) -> tuple[torch.Tensor, dict]:
    """A field with fewer complex-type singular faces: matchings searched, frames relaxed onto them.

    Each pass runs :func:`repair_matchings` on the current field, then
    :func:`~torchconn.frames.quality_paths.relax_to_matchings` once per weight of ``moved_edge_weights``
    (the weight of the re-matched edges in the edge terms, the others weigh 1; a heavier weight makes
    the frames follow the new matchings, at the price of the edges around them) and keeps the
    relaxed field whose *own* matchings have the fewest complex faces (the first on a tie). A pass
    that does not lower the count ends the search; so does a field without complex faces.

    Args:
        frames: ``(V, 3, 3)`` start field.
        mesh: ``TetMesh``.
        a_ref, d_ref: normalizations of the relaxation (:func:`~torchconn.frames.quality_paths.relax_to_matchings`).
        passes: the most search-and-relax passes.
        residual_weight, face_costs: of :func:`repair_matchings`.
        moved_edge_weights: weights tried in each pass (each a relaxation: their number is the
            cost of a pass).
        relax_iters, dirichlet_weight, feature_weight, eps, align_eps, angle_deg: of the
            relaxation.

    Returns:
        ``(frames (V, 3, 3), info)``; ``info["complex_before"]``, ``info["complex_after"]`` (the
        frames' own complex faces) and ``info["passes"]``, one dict per pass with ``"moves"``,
        ``"complex_matchings"`` (of the searched matchings) and ``"complex_relaxed"`` (one per
        weight). ``frames`` is the input when no pass lowered the count.
    """
    ws = [float(w) for w in moved_edge_weights]
    if not ws or not all(math.isfinite(w) and w > 0 for w in ws):
        raise ValueError(f"repair_structure: moved_edge_weights must be finite and > 0, got {moved_edge_weights}")
    if not isinstance(passes, int) or passes < 0:
        raise ValueError(f"repair_structure: passes must be an integer >= 0, got {passes!r}")
    F = frames.detach()
    n = complex_face_count(F, mesh)
    info = {"complex_before": n, "passes": []}
    for _ in range(passes):
        if n == 0:
            break
        idx, rinfo = repair_matchings(F, mesh, residual_weight=residual_weight, face_costs=face_costs)
        entry = {"moves": len(rinfo["moves"]), "complex_matchings": rinfo["complex_after"], "complex_relaxed": []}
        info["passes"].append(entry)
        if rinfo["complex_after"] >= rinfo["complex_before"]:
            break
        moved = torch.tensor([mv[0] for mv in rinfo["moves"]], dtype=torch.long, device=F.device)
        best = None
        for w in ws:
            ew = None
            if w != 1.0:
                ew = torch.ones(mesh.edges.shape[0], dtype=F.dtype, device=F.device)
                ew[moved] = w
            Fr = relax_to_matchings(mesh, F, idx, a_ref=a_ref, d_ref=d_ref, dirichlet_weight=dirichlet_weight,
                                    iters=relax_iters, feature_weight=feature_weight, edge_weights=ew, eps=eps,
                                    align_eps=align_eps, angle_deg=angle_deg)
            c = complex_face_count(Fr, mesh)
            entry["complex_relaxed"].append(c)
            if best is None or c < best[0]:
                best = (c, Fr)
        if best[0] >= n:
            break
        n, F = best
    info["complex_after"] = n
    return F, info
