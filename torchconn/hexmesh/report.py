"""What a person reads after a hex-meshing run: the one verdict, the console summary, and what
shows an invalid map (per-tet flags, a VTU, a picture).

* :func:`verdict` is the single judgement of a run (the console line, ``hex_metrics.json`` and
  the pictures' subtitles all print its ``text``): a **good hex mesh** is a valid map and a hex
  mesh that :func:`~.quality.hex_quality` calls good (valid: all hexahedra, none inverted,
  conforming, closed manifold boundary; irregular interior edges ``<= 5%``; Hausdorff distance
  ``<= 1%`` of the diagonal; volume ratio within ``10%`` of 1, docs/results/hexmesh.md). Without
  hexes the verdict is ``"no hex mesh"`` with the reasons (:func:`no_hex_reasons`): the invalid
  map, an edge length too small for the mesh (tets over the extraction's lattice-point limit) or
  too large (no unit cube fits the map's image), every cube dropped (by reason).
* :func:`summary` is the console text; figures that do not exist (no hexes) are not printed.
* :func:`tet_flags` marks the tets where a map fails (inverted, degenerate, on a singular edge
  no integer-grid map follows, oversized for the extraction, cubes dropped there), on the map's
  own (refined) mesh and on the input tets through ``map.parent_tet``;
  :func:`~.io.write_failure_vtu` writes them with the singular graph (:func:`singular_lines`) as
  line cells and :func:`~.io.plot_failure` draws the input's boundary with the failing regions marked.
"""
from __future__ import annotations

import numpy as np

__all__ = ["verdict", "no_hex_reasons", "summary", "map_figures", "tet_flags", "singular_lines", "FLAGS",
           "DROP_WORDS"]

#: What each drop reason of :data:`~.extract.REASONS` means, in a person's words.
DROP_WORDS = {
    "flipped_tet": "crossed a tet inverted or flat in the map",
    "oversized_tet": "crossed a tet too large for the extraction",
    "seam_mismatch": "crossed a face where the map is not seamless",
    "near_invalid": "lay next to an inverted tet, a broken seam or an invalid singular edge",
    "leaves_domain": "left the domain (a boundary off its integer plane)",
    "walk_limit": "needed too long a walk",
    "not_closed": "did not close (wrapped around a singularity)",
    "overlap": "overlapped other hexes",
}

#: Per-tet flags of :func:`tet_flags`, their bit in ``flags`` and their words.
FLAGS = {
    "inverted": (1, "inverted in the map"),
    "degenerate": (2, "of zero parametric volume"),
    "unmeshable_singular_edge": (4, "on a singular edge no integer-grid map follows (complex)"),
    "oversized": (8, "too large for the extraction"),
    "cubes_dropped": (16, "where cubes were dropped"),
}
_MAP_REASONS_SHOWN = 2  # the map's first failing checks quoted in a verdict


# ----------------------------------------------------------------------------- figures and verdict
def map_figures(igm, input_mesh=None) -> dict:
    """Figures of a map that explain a run without hexes (JSON-ready):

    * ``image_cubes``: the volume of the map's image in unit cubes (the sum of the positive
      parametric tet volumes): about the number of hexes a valid map gives;
    * ``parameter_max``: the largest ``|u|`` of a corner, in edge lengths;
    * ``bbox_edge_lengths``: the mesh's bounding box in edge lengths ``(3,)``;
    * ``default_edge_length``: :func:`~.seamless.default_edge_length` of ``input_mesh`` (when given).
    """
    from .seamless import default_edge_length

    U = np.asarray(igm.uvw, dtype=np.float64)
    d = U[:, 1:] - U[:, :1]
    vol = np.einsum("ti,ti->t", np.cross(d[:, 0], d[:, 1]), d[:, 2]) / 6.0
    X = igm.mesh.vertices.detach().cpu().double().numpy()
    ext = X.max(0) - X.min(0) if X.size else np.zeros(3)
    out = {"image_cubes": float(vol[vol > 0].sum()), "parameter_max": float(np.abs(U).max(initial=0.0)),
           "bbox_edge_lengths": (ext / igm.edge_length).tolist()}
    if input_mesh is not None:
        out["default_edge_length"] = default_edge_length(input_mesh)
    return out


def _first_map_reasons(mp: dict, metrics: dict | None = None) -> str:
    """The first failing stage of the map (its gate's reasons), else the final map's checks."""
    stage = (metrics or {}).get("first_failed")
    gate = ((metrics or {}).get("gates") or {}).get(stage) if stage not in (None, "extraction") else None
    r = list(gate["reasons"] if gate else (mp.get("reasons") or []))
    more = f"; {len(r) - _MAP_REASONS_SHOWN} more failing checks" if len(r) > _MAP_REASONS_SHOWN else ""
    head = f"the {stage} stage fails first: " if gate else ""
    return head + "; ".join(r[:_MAP_REASONS_SHOWN]) + more


def no_hex_reasons(metrics: dict) -> list[str]:
    """Why a run has no hexes, from its :meth:`~.pipeline.HexMeshResult.metrics` (most telling
    first): not extracted; an invalid map (its first failing checks); an edge length too small
    (tets over the extraction's lattice-point limit, how many, and the parameters' magnitude)
    or too large (the bounding box and the map's image in edge lengths / unit cubes); every cube
    dropped (how many, by reason)."""
    mp, ex = metrics.get("map") or {}, metrics.get("extraction")
    if ex is None:
        return ["the hexes were not extracted (extract=False)"]
    reasons = []
    if mp and not mp.get("valid", True):
        reasons.append(f"invalid map ({_first_map_reasons(mp, metrics)})")
    h = mp.get("edge_length")
    default = mp.get("default_edge_length")
    dflt = f"; the default, {default:.3g}, is half the mean tet edge" if default is not None else ""
    if ex.get("oversized_tets"):
        limit = ex.get("max_tet_points")
        reasons.append(f"edge length {h:.3g} too small for the mesh: {ex['oversized_tets']} of {mp.get('tets')} tets "
                       f"hold more than {limit:,} lattice points each (the extraction's limit), the map's "
                       f"parameters reach {mp.get('parameter_max', float('nan')):.3g} edge lengths; raise "
                       f"hex.edge_length{dflt}")
    cubes, box = mp.get("image_cubes"), mp.get("bbox_edge_lengths")
    too_large = cubes is not None and box is not None and (cubes < 1.0 or min(box) < 1.0)
    if too_large and not ex.get("oversized_tets"):
        reasons.append(f"edge length {h:.3g} too large for the mesh: its bounding box spans "
                       f"{' x '.join(f'{b:.3g}' for b in box)} edge lengths and the map's image holds "
                       f"{cubes:.3g} unit cubes; lower hex.edge_length{dflt}")
    n_drop = int(ex.get("cubes_dropped") or 0)
    if n_drop:
        by = ", ".join(f"{c} {DROP_WORDS.get(k, k)}" for k, c in (ex.get("dropped") or {}).items() if c)
        reasons.append(f"the 1 cube found was dropped: {by}" if n_drop == 1 else
                       f"all {n_drop} cubes found were dropped: {by}")
    elif not ex.get("oversized_tets") and not too_large and cubes is not None:
        reasons.append(f"no unit cube of the integer grid lies in the map's image (its volume: {cubes:.3g} unit cubes)")
    return reasons or ["no cube of the integer grid was found in the map"]


def verdict(metrics: dict) -> dict:
    """The one judgement of a run, from its :meth:`~.pipeline.HexMeshResult.metrics` (or any
    dict with ``quality`` and optionally ``map`` / ``extraction``: a hex mesh judged alone).

    Returns ``{"good", "status", "reasons", "text"}``: ``status`` is ``"good"``, ``"not good"``,
    ``"no hex mesh"`` or ``"not judged"`` (hexes without a quality report); ``reasons`` say what
    fails (the map's first failing checks, the hex mesh's invalidity, each threshold missed with
    its figure); ``text`` is the sentence every report prints.
    """
    mp, ex, q = metrics.get("map"), metrics.get("extraction"), metrics.get("quality")
    n = ex["hexes"] if ex is not None else (q or {}).get("n_hexes", 0)
    if not n:
        reasons = no_hex_reasons(metrics)
        return {"good": False, "status": "no hex mesh", "reasons": reasons, "text": "no hex mesh: " + "; ".join(reasons)}
    reasons = []
    if mp is not None and not mp.get("valid", False):
        reasons.append(f"invalid map ({_first_map_reasons(mp, metrics)})")
    if q is None:
        status = "not judged"
        reasons.append(f"{n} hexes not judged (quality=False)")
    else:
        if not q.get("valid"):
            reasons.append("invalid hex mesh: " + "; ".join(q.get("invalid_reasons") or []))
        if q.get("good") is None:
            reasons.append("not compared with the input (no tet mesh given)")
        else:
            reasons += [r for r in q.get("not_good_reasons") or [] if r != "not valid"]
        status = "not good" if reasons else "good"
    text = "good hex mesh" if not reasons else (
        "hexes not judged: " if status == "not judged" else "not a good hex mesh: ") + "; ".join(reasons)
    return {"good": not reasons, "status": status, "reasons": reasons, "text": text}


def summary(metrics: dict) -> list[str]:
    """The console text of a run: the verdict's sentence, then the figures that exist (the map,
    hexes and cubes dropped, and with hexes the scaled Jacobian, irregular interior edges,
    Hausdorff distance and volume ratio)."""
    v = metrics.get("verdict") or verdict(metrics)
    mp, ex, q = metrics.get("map") or {}, metrics.get("extraction"), metrics.get("quality")
    parts = [f"map {'valid' if mp.get('valid') else 'INVALID'} (edge length {mp.get('edge_length', float('nan')):.3g})"]
    if metrics.get("first_failed"):
        parts.append(f"first failing stage: {metrics['first_failed']}")
    if ex is not None:
        parts.append(f"{ex['hexes']} hex{'' if ex['hexes'] == 1 else 'es'} ({ex.get('cubes_dropped', 0)} cubes dropped)")
    if q is not None:
        parts.append(f"scaled Jacobian min {q['sj_min']:.3f} mean {q['sj_mean']:.3f}")
        if q["n_interior_edges"]:  # a mesh without interior edges has no such fraction
            parts.append(f"irregular interior edges {q['n_irregular_interior_edges']} of {q['n_interior_edges']} "
                         f"({100 * q['irregular_fraction']:.1f}%)")
        if q.get("hausdorff_rel") is not None:
            parts.append(f"Hausdorff {100 * q['hausdorff_rel']:.2f}% of the diagonal")
        if q.get("volume_ratio") is not None:
            parts.append(f"volume ratio {q['volume_ratio']:.3f}")
    return [v["text"], "; ".join(parts)]


# ----------------------------------------------------------------------------- where a map fails
def tet_flags(igm, extraction=None, n_input: int | None = None) -> dict:
    """Per-tet flags of a map (numpy).

    Returns ``{"map": {name: (T_map,) bool}, "input": {name: (T_in,) int32}, "flags_map",
    "flags_input"}``: for each flag of :data:`FLAGS` the map's tets that carry it (``inverted``
    and ``degenerate`` by the exact orientation of their parameters; ``unmeshable_singular_edge``
    holding an interior edge whose holonomy is complex; with ``extraction`` the tets skipped as
    ``oversized`` and the owners of ``cubes_dropped``) and, per input tet, how many of its
    sub-tets do (``map.parent_tet``; ``n_input`` input tets, default ``parent_tet.max() + 1``);
    ``flags_*`` the bits of :data:`FLAGS` or-ed together.
    """
    from .predicates import orient3d

    U = np.asarray(igm.uvw)
    T = U.shape[0]
    o = np.asarray(orient3d(U[:, 0], U[:, 1], U[:, 2], U[:, 3]))
    ch = igm.charts
    bad_edge = ch.singular_edge & ~ch.edge_meshable
    tet_edges = igm.mesh.tet_edges.cpu().numpy()
    per_map = {"inverted": o < 0, "degenerate": o == 0, "unmeshable_singular_edge": bad_edge[tet_edges].any(1),
               "oversized": np.zeros(T, bool), "cubes_dropped": np.zeros(T, bool)}
    if extraction is not None:
        per_map["oversized"][np.asarray(extraction.oversized_tets, dtype=np.int64)] = True
        per_map["cubes_dropped"][np.asarray(extraction.dropped_tet, dtype=np.int64)] = True
    parent = np.asarray(igm.parent_tet, dtype=np.int64)
    n_in = n_input if n_input is not None else (int(parent.max()) + 1 if parent.size else 0)
    per_input = {k: np.bincount(parent[v], minlength=n_in).astype(np.int32) for k, v in per_map.items()}
    bits_map = np.zeros(T, np.int32)
    bits_in = np.zeros(n_in, np.int32)
    for k, (bit, _) in FLAGS.items():
        bits_map |= np.where(per_map[k], bit, 0).astype(np.int32)
        bits_in |= np.where(per_input[k] > 0, bit, 0).astype(np.int32)
    return {"map": per_map, "input": per_input, "flags_map": bits_map, "flags_input": bits_in}


def singular_lines(igm) -> tuple[np.ndarray, dict]:
    """The map's singular edges ``(S, 2)`` (vertex ids of ``igm.mesh``) and per edge ``edge_type``
    (1 quarter turn, 2 half turn, 3 complex), ``valence`` (3, 5; 0 half turn, -1 complex) and
    ``meshable`` (int32 arrays)."""
    ch = igm.charts
    sing = np.nonzero(ch.singular_edge)[0]
    edges = igm.mesh.edges.cpu().numpy()[sing].astype(np.int64)
    return edges, {"edge_type": ch.edge_type[sing].astype(np.int32),  # 1 quarter, 2 half, 3 complex
                   "valence": ch.edge_valence[sing].astype(np.int32),
                   "meshable": ch.edge_meshable[sing].astype(np.int32)}
