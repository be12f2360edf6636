"""The connection method chosen by the hex meshes its candidates make.

:func:`hex_chooser` returns a ``choose(mesh, candidates)`` for
:func:`torchconn.frames.design` (its ``choose=`` hook): the candidates (every one a descendant of a
connection optimization, :class:`torchconn.frames.candidates.Candidate`) are meshed by
:func:`~.pipeline.hex_mesh` and ranked by the end metric: a valid map with a good hex mesh first,
then a valid map, then fewer inverted and flat tets in the map, fewer cubes dropped, a larger
minimum scaled Jacobian, fewer irregular interior edges; the proxies' score
(:func:`~torchconn.frames.candidates.quality_score`) breaks ties. Only the most promising candidates are
meshed (the cost is one hex stage each): each start's optimized field, then the best checkpoint
by the proxies of each (start, path kind), up to ``max_candidates`` — the quality paths only of
the starts whose optimized field passed the structure gate.

:func:`design_for_hex` is :func:`torchconn.frames.design` with this chooser and the seamless map's
fitting energy (:class:`~.energy.MapEnergy`) as the loss term ``map``: the connection method as the
hex job and the benchmark run it.
"""
from __future__ import annotations

import math
import time

import torch

__all__ = ["hex_chooser", "hex_key", "design_for_hex", "preselect", "map_energy_term", "NO_STRUCTURE"]


def map_energy_term(edge_length: float | None = None):
    """A loss-term factory for :func:`torchconn.frames.design`'s ``extra_terms``: per start field,
    :class:`~.energy.MapEnergy` with the structure frozen there, as ``term(edge_rot, frames)`` of the
    per-vertex frames (the seamless map's fitting energy per volume; differentiable)."""
    from .energy import MapEnergy

    def factory(mesh, start_frames):
        state = {"energy": MapEnergy.from_vertex_frames(mesh, start_frames.detach(), edge_length), "rebuilt": 0}

        def term(edge_rot, frames):
            try:
                return state["energy"].of_vertex_frames(frames)
            except ValueError:
                # the frames left the frozen structure (a tet's relabeled vertex frames no longer
                # average to a rotation): freeze the structure of the current field instead
                state["energy"] = MapEnergy.from_vertex_frames(mesh, frames.detach(), edge_length)
                state["rebuilt"] += 1
                return state["energy"].of_vertex_frames(frames)

        return term

    return factory


def hex_key(result, score: float) -> tuple:
    """Sort key of a :class:`~.pipeline.HexMeshResult` (smaller is better; module docstring)."""
    v, q, ex = result.validity, result.quality, result.extraction
    bad_tets = v.counts.get("inverted_tets", 0) + v.counts.get("degenerate_tets", 0)
    dropped = ex.counts()["cubes_dropped"] if ex is not None else math.inf
    sj = q.sj_min if q is not None and q.sj_min == q.sj_min else -math.inf
    irr = q.irregular_fraction if q is not None else math.inf
    return (not result.good, not v.valid, bad_tets, dropped, -sj, irr, score)


def preselect(candidates, max_candidates: int) -> list[int]:
    """Indices of the candidates to mesh: optimized fields, then the best checkpoint per (start, kind)
    by the proxies; at most ``max_candidates``, in that order."""
    order = []
    for i, c in enumerate(candidates):
        if c.kind == "optimized":
            order.append(i)
    best = {}
    for i, c in enumerate(candidates):
        if c.kind != "optimized":
            key = (c.start, c.kind)
            if key not in best or c.score < candidates[best[key]].score:
                best[key] = i
    order += sorted(best.values(), key=lambda i: candidates[i].score)
    seen, out = set(), []
    for i in order:
        if i not in seen:
            seen.add(i)
            out.append(i)
    return out[:max_candidates]


NO_STRUCTURE = "no optimized field passed the structure gate: no quality path made"
"""``info["stopped"]`` of :func:`hex_chooser` when the quality paths were not made (see there)."""


def hex_chooser(max_candidates: int = 8, first_good: bool = True, **hex_options):
    """A ``choose(mesh, candidates) -> (index, info)`` for :func:`torchconn.frames.design`.

    Args:
        max_candidates: how many candidates are meshed at most (:func:`preselect`).
        first_good: stop at the first candidate, in :func:`preselect`'s order, whose hex mesh is
            good: the set of inputs that get a good hex mesh is the same as meshing all the
            candidates it makes (only which good mesh is returned may differ), and with a
            :class:`~torchconn.frames.candidates.CandidateStack` (what :func:`~torchconn.frames.design`
            passes) the later stages of candidates are then never made. With a stack, the quality
            paths continue only the optimized fields whose hex mesh passed the structure gate
            (:attr:`~torchconn.frames.candidates.CandidateStack.path_starts`), and are not made
            when none did (``"stopped"``: :data:`NO_STRUCTURE`): they smooth a field whose
            singular structure meshes, they do not repair one. Measured on the 35 HexMe ``c``
            models (three runs of 2026-11-27, docs/results/hexmesh.md): every quality-path field
            that gave a good hex mesh (s06, s07, n09) continued an optimized field that had passed
            the structure gate. ``False``: make every candidate, mesh the ``max_candidates`` first
            and return the best by :func:`hex_key`.
        **hex_options: options of :func:`~.pipeline.hex_mesh` (``edge_length``, ...). Its
            ``one_ring`` test (a report, deciding nothing) runs on the chosen candidate's hex
            mesh only (:func:`~.pipeline.add_one_ring`), not on every meshed candidate.

    ``candidates`` is a sequence of :class:`~torchconn.frames.candidates.Candidate` s or a
    :class:`~torchconn.frames.candidates.CandidateStack`, whose stages are made one at a time: after
    each, the candidates :func:`preselect` puts first among those made and not yet meshed are meshed.
    The ``info`` lists, per meshed candidate, its label, the map's validity, the first gate that
    failed (``first_failed``, ``None`` when none did) and the first reasons, the hexes, the scaled
    Jacobian, the irregular fraction, the Hausdorff distance, ``good`` and the seconds of its hex
    stage; ``"by": "hex"``; ``"stopped"``: why meshing stopped. After a call,
    ``choose.chosen`` is ``(frames, HexMeshResult)`` of the chosen candidate
    (:func:`design_for_hex` hands it on as ``FrameFieldResult.hex``).
    """
    if not (isinstance(max_candidates, int) and max_candidates >= 1):
        raise ValueError(f"max_candidates must be an integer >= 1, got {max_candidates!r}")

    def choose(mesh, candidates):
        from ..frames.candidates import CandidateStack
        from .pipeline import add_one_ring, hex_mesh

        lazy = isinstance(candidates, CandidateStack) and first_good
        if isinstance(candidates, CandidateStack) and not first_good:
            candidates.complete()
        meshed, rows, keys, results = [], [], [], []
        stopped = None

        def mesh_next() -> str | None:
            for i in preselect(candidates, len(candidates)):
                if i in meshed:
                    continue
                if len(meshed) == max_candidates:
                    return f"max_candidates={max_candidates} meshed"
                c = candidates[i]
                t0 = time.perf_counter()
                r = hex_mesh(mesh, c.frames, **{**hex_options, "one_ring": False})
                q = r.quality
                rows.append({"label": c.label, "valid": bool(r.validity.valid), "good": bool(r.good),
                             "first_failed": r.first_failed,
                             "reasons": list(r.validity.reasons)[:3], "hexes": int(r.hexes.shape[0]),
                             "sj_min": None if q is None else q.sj_min,
                             "irregular": None if q is None else q.irregular_fraction,
                             "hausdorff": None if q is None else q.hausdorff_rel,
                             "seconds": time.perf_counter() - t0})
                meshed.append(i)
                keys.append(hex_key(r, c.score))
                results.append(r)
                if first_good and r.good:
                    return "the first good hex mesh"
            return f"max_candidates={max_candidates} meshed" if len(meshed) == max_candidates else None

        if lazy:
            while stopped is None and candidates.pending is not None:
                if candidates.pending == "paths":
                    candidates.path_starts = {candidates[i].start for i, r in zip(meshed, results)
                                              if candidates[i].kind == "optimized" and r.first_failed != "structure"}
                    if not candidates.path_starts:
                        stopped = NO_STRUCTURE
                        break
                candidates.next_stage()
                stopped = mesh_next()
        else:
            stopped = mesh_next()
        if not meshed:
            raise ValueError("hex_chooser: no candidate")
        best = min(range(len(keys)), key=keys.__getitem__)
        win = meshed[best]
        row = rows[best]
        if hex_options.get("one_ring", True):
            add_one_ring(results[best], **{k: hex_options[k] for k in ("features", "feature_max_deg", "backend")
                                           if k in hex_options})
        choose.chosen = (candidates[win].frames, results[best])  # the winner's hex mesh, not made again
        reason = ("a valid map and a good hex mesh" if row["good"] else "a valid map" if row["valid"]
                  else "no candidate has a valid map: the fewest broken tets")
        return win, {"by": "hex", "reason": reason, "stopped": stopped or "every candidate meshed",
                     "meshed": rows}

    return choose


def design_for_hex(mesh, method: str = "connection", *, select: str = "hex", select_candidates: int = 8,
                   hex_options: dict | None = None, **options):
    """:func:`torchconn.frames.design` with the hex chooser (``select="hex"``; ``"proxies"``: the
    default choice) and, when ``weights["map"] > 0``, the seamless map's fitting energy as a loss
    term (:class:`~.energy.MapEnergy`, built per start field, structure frozen there). With the
    hex chooser, ``result.hex`` is the :class:`~.pipeline.HexMeshResult` of the returned field
    (``hex_mesh(mesh, result.vertex_frames, **hex_options)``, made while choosing)."""
    from ..frames.design import design

    if select not in ("hex", "proxies"):
        raise ValueError(f"select must be 'hex' or 'proxies', got {select!r}")
    hex_options = dict(hex_options or {})
    extra = {"map": map_energy_term(edge_length=hex_options.get("edge_length"))} if method == "connection" else {}
    choose = hex_chooser(select_candidates, **hex_options) if select == "hex" and method == "connection" else None
    res = design(mesh, method, choose=choose, extra_terms=extra or None, **options)
    chosen = getattr(choose, "chosen", None)
    if chosen is not None and torch.equal(chosen[0].detach().to(res.vertex_frames), res.vertex_frames):
        res.hex = chosen[1]  # the hex mesh of exactly the returned field, with hex_options
    return res
