"""From a tet mesh and a frame field to a hex mesh, in one call: the gated stages and the judgement.

The stages (:data:`~.validity.STAGES`), each with its verdict (:class:`~.validity.Gate`):
**structure**, **seamless** map and **quantization** (:func:`~.igm.integer_grid_map`), then
**extraction** (:func:`~.extract.extract_hexes`: passes when every cube of a valid map is extracted
into a valid hex mesh). :attr:`HexMeshResult.first_failed` names the first stage that fails.

>>> from torchconn import io
>>> from torchconn.hexmesh import hex_mesh
>>> import torch
>>> mesh = io.box(2)                                   # the unit cube, 48 tets
>>> frames = torch.eye(3, dtype=torch.float64).expand(mesh.n_tets, 3, 3)
>>> result = hex_mesh(mesh, frames, edge_length=0.25)
>>> result.validity.valid, result.hexes.shape, round(result.quality.sj_min, 12)
(True, (64, 8), 1.0)
"""
from __future__ import annotations

import inspect
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .extract import extract_hexes
from .igm import IntegerGridMap, integer_grid_map
from .seamless import FEATURE_MAX_DEG
from .validity import STAGES, Gate, MapValidity

__all__ = ["HexMeshResult", "hex_mesh", "add_one_ring", "extraction_gate", "MAP_OPTIONS", "CLOSER_STEPS"]

MAP_OPTIONS = ("edge_length", "face_match", "straighten", "straighten_boundary", "touch_rounds", "repair",
               "repair_rounds", "repair_slide", "split", "collapse", "features", "feature_max_deg", "flat_rounds",
               "relocate", "one_ring", "fixed_holonomy", "injective",
               "fit_weight", "sd_weight", "refine_limit", "integrable", "batch_error", "stiffening_iters", "stiffening_factor",
               "grid_bits", "backend")
"""The keyword options of :func:`~.igm.integer_grid_map` that :func:`hex_mesh` passes on."""
#: At most this many runs at ``h / √2`` after the default edge length's, where the hex mesh of a
#: valid map is too far from the input alone (:func:`hex_mesh`).
CLOSER_STEPS = 2
#: The extraction's lattice-point limit per tet (``extract_hexes``' default, which
#: :func:`hex_mesh` uses): a map whose tets exceed it has an edge length too small for the mesh.
_EXTRACT_MAX_TET_POINTS = inspect.signature(extract_hexes).parameters["max_tet_points"].default


@dataclass
class HexMeshResult:
    """What :func:`hex_mesh` returns (numpy arrays; nothing is written).

    Attributes:
        map: the :class:`~.igm.IntegerGridMap` (``map.mesh`` is the tet mesh it lives on: the
            input, or its refinement by the map's edge splits).
        validity: the :class:`~.validity.MapValidity` of the map (valid, counts, reasons, where).
        extraction: the :class:`~.extract.HexExtraction` (``None`` with ``extract=False``): the
            hex mesh, extracted also from an invalid map where the map allows it, with the cubes
            it dropped and why.
        quality: the :class:`~.quality.HexQuality` of the hex mesh against the input mesh
            (``None`` without hexes or with ``quality=False``).
        meshability: the :class:`~.meshability.Meshability` report of the singular graph the
            map saw (after the straightening search and the splits): LMFF's local conditions.
        gates: ``{stage: Gate}`` for every stage of :data:`~.validity.STAGES` that ran
            (``map.gates`` and ``extraction``).
        timings: seconds per step (``map``, ``extract``, ``untangle``, ``quality``, ``total``).
        input_mesh: the ``TetMesh`` that was given (float64, CPU); ``map.parent_tet`` maps the
            map's tets to its tets.
    """

    map: IntegerGridMap
    validity: MapValidity
    extraction: object | None = None
    quality: object | None = None
    timings: dict = field(default_factory=dict)
    meshability: object | None = None
    input_mesh: object | None = None
    gates: dict = field(default_factory=dict)

    @property
    def first_failed(self) -> str | None:
        """The first stage whose gate failed and stopped the pipeline (``None``: none did;
        :func:`~.validity.first_failed`)."""
        from .validity import first_failed

        return first_failed(self.gates)

    @property
    def points(self) -> np.ndarray:
        """``(N, 3)`` hex-mesh vertices (empty without an extraction)."""
        return self.extraction.points if self.extraction is not None else np.zeros((0, 3))

    @property
    def hexes(self) -> np.ndarray:
        """``(H, 8)`` hexahedra in VTK order, positively oriented."""
        return self.extraction.hexes if self.extraction is not None else np.zeros((0, 8), np.int64)

    @property
    def good(self) -> bool:
        """The verdict's ``good`` (:func:`~.report.verdict`): a valid map and a good hex mesh
        (:attr:`HexQuality.good`: valid, irregular edges, Hausdorff distance, volume ratio)."""
        return self.verdict()["good"]

    def verdict(self) -> dict:
        """:func:`~.report.verdict` of :meth:`metrics`: ``good``, ``status`` (``"good"``,
        ``"not good"``, ``"no hex mesh"``, ``"not judged"``), ``reasons`` and ``text``."""
        return self.metrics()["verdict"]

    def metrics(self) -> dict:
        """JSON-ready summary: map figures and validity, extraction counts, hex quality, timings,
        and the one ``verdict`` (:func:`~.report.verdict`; ``good`` is its ``good``). Figures that
        do not exist are ``None`` (``quality`` without hexes)."""
        from .report import map_figures, verdict

        m = self.map
        stats = {k: v for k, v in m.stats.items() if k != "timings"}
        ext = None
        if self.extraction is not None:
            ext = {**self.extraction.counts(), "max_tet_points": _EXTRACT_MAX_TET_POINTS}
        out = {
            "good": False,
            "verdict": None,
            "map": {"valid": self.validity.valid, "reasons": list(self.validity.reasons),
                    "checks": dict(self.validity.counts), "where": self.validity.where,
                    "edge_length": m.edge_length, "energy": m.energy, "energy_continuous": m.energy_continuous,
                    "tets": int(m.mesh.n_tets), "vertices": int(m.mesh.n_vertices),
                    "singular_graph": m.charts.counts(), **map_figures(m, self.input_mesh), **stats},
            "gates": {k: g.as_dict() for k, g in self.gates.items()},
            "first_failed": self.first_failed,
            "meshability": self.meshability.counts() if self.meshability is not None else None,
            "extraction": ext,
            "quality": self.quality.as_dict() if self.quality is not None else None,
            "timings": {**{f"map_{k}": v for k, v in m.stats.get("timings", {}).items()}, **self.timings},
        }
        out["verdict"] = verdict(out)
        out["good"] = out["verdict"]["good"]
        return out


def hex_mesh(mesh, frames, *, extract: bool = True, untangle: bool = True, quality: bool = True,
             progress: bool = False, **map_options) -> HexMeshResult:
    """The hex mesh of a frame field (HEXMESH.md steps 1-8 and the judgement).

    Args:
        mesh: a ``TetMesh`` or a path that :func:`torchconn.io.load_mesh` reads (a tet mesh, a
            CAD file or a HexMe parameter file; CAD tags are kept).
        frames: a :class:`~torchconn.frames.design.FrameFieldResult` on ``mesh``, or frames
            ``(V, 3, 3)`` per vertex or ``(T, 3, 3)`` per tet (rotations: axes as columns).
        extract: extract the hexes (also from an invalid map, where it allows).
        untangle: move the interior hex vertices to raise the worst scaled Jacobian
            (:func:`~.hex_untangle.untangle`; boundary vertices fixed, kept only if it helps).
        quality: judge the hex mesh (:func:`~.quality.hex_quality`) against ``mesh``.
        progress: progress bars on the rounding and the extraction.
        **map_options: :data:`MAP_OPTIONS`, passed to :func:`~.igm.integer_grid_map`
            (``edge_length``, the hex edge length ``h``, defaults to
            :func:`~.seamless.default_edge_length`: half the mean edge length of ``mesh``).

    The default resolution: without ``edge_length``, where the map is valid and its hex mesh fails
    only the distance to the input (valid, irregular edges and volume ratio within the good
    bounds, Hausdorff distance over :data:`~.quality.GOOD_HAUSDORFF_MAX_REL`: the hexes are too
    coarse for a thin or curved part), the stage runs again at ``h / √2``, at most
    :data:`CLOSER_STEPS` times, and returns the last run (``timings["closer_s"]``: the seconds of
    the runs before it; ``map.stats["closer"]``: each run's edge length and distance). A given
    ``edge_length`` is kept as it is.

    Returns:
        :class:`HexMeshResult`. An invalid map is a result (``validity.valid`` false, with its
        reasons), not an error; so is a map without hexes (``result.verdict()`` says why: the
        map, an edge length too small or too large for the mesh, every cube dropped).

    Raises:
        ValueError: unknown options, frames that do not fit the mesh (the expected and given
            shape; non-finite entries; not rotations, how many and of which kind, e.g.
            reflections), a non-positive edge length, or one so small that the parameters
            reach ``2**30`` edge lengths.
    """
    unknown = set(map_options) - set(MAP_OPTIONS)
    if unknown:
        raise ValueError(f"unknown hex_mesh options {sorted(unknown)}; known: {list(MAP_OPTIONS)}")
    if isinstance(mesh, (str, Path)):
        from ..mesh import load_mesh

        mesh = load_mesh(mesh)
    import torch

    if mesh.vertices.dtype != torch.float64 or mesh.vertices.device.type != "cpu":
        mesh = mesh.to(device="cpu", dtype=torch.float64)
    res = _stage(mesh, frames, extract, untangle, quality, progress, map_options)
    if map_options.get("edge_length") is not None:
        return res
    runs, spent = [], 0.0
    while _only_too_far(res) and len(runs) < CLOSER_STEPS:
        runs.append({"edge_length": res.map.edge_length, "hausdorff_rel": res.quality.hausdorff_rel})
        spent += res.timings["total_s"]
        res = _stage(mesh, frames, extract, untangle, quality, progress,
                     {**map_options, "edge_length": res.map.edge_length / math.sqrt(2.0)})
    if runs:
        res.map.stats["closer"] = runs + [{"edge_length": res.map.edge_length,
                                           "hausdorff_rel": res.quality.hausdorff_rel if res.quality else None}]
        res.timings["closer_s"] = spent
        res.timings["total_s"] += spent
    return res


def _only_too_far(res: HexMeshResult) -> bool:
    """A valid map whose hex mesh fails the good bounds by its distance to the input alone."""
    from .quality import GOOD_HAUSDORFF_MAX_REL, GOOD_IRREGULAR_MAX, GOOD_VOLUME_RATIO_TOL

    q = res.quality
    return bool(res.validity.valid and q is not None and q.valid and q.hausdorff_rel > GOOD_HAUSDORFF_MAX_REL
                and q.irregular_fraction <= GOOD_IRREGULAR_MAX and abs(q.volume_ratio - 1.0) <= GOOD_VOLUME_RATIO_TOL)


def _stage(mesh, frames, extract, untangle, quality, progress, map_options) -> HexMeshResult:
    """One run of the stage at the options given (:func:`hex_mesh`)."""
    timings = {}
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    igm = integer_grid_map(mesh, frames, progress=progress, **map_options)
    timings["map_s"] = time.perf_counter() - t0
    gates = dict(igm.gates)
    ext = hq = None
    if extract:
        t0 = time.perf_counter()
        ext = extract_hexes(igm.mesh, igm.uvw, igm.face_rot, igm.face_shift, grid_bits=igm.grid_bits,
                            progress=progress)
        timings["extract_s"] = time.perf_counter() - t0
        # the hex vertices of a valid map are untangled; a partial mesh of an invalid one is shown as it is
        if untangle and ext.hexes.shape[0] and igm.validity.valid:
            from .quality import boundary_quads_of
            from .hex_untangle import untangle as _untangle

            t0 = time.perf_counter()
            bv = np.unique(boundary_quads_of(ext.hexes).reshape(-1))
            surf = (mesh.vertices.detach().cpu().double().numpy(), mesh.boundary_faces.cpu().numpy())
            ext.points, uinfo = _untangle(ext.points, ext.hexes, bv, surface=surf)
            ext.timings["untangle"] = uinfo
            timings["untangle_s"] = time.perf_counter() - t0
        if quality and ext.hexes.shape[0]:
            from .quality import hex_quality

            t0 = time.perf_counter()
            hq = hex_quality(ext.points, ext.hexes, tet_mesh=mesh)
            timings["quality_s"] = time.perf_counter() - t0
        gates["extraction"] = extraction_gate(ext, hq)
    timings["total_s"] = time.perf_counter() - t_all
    return HexMeshResult(map=igm, validity=igm.validity, extraction=ext, quality=hq, timings=timings,
                         meshability=igm.meshability, input_mesh=mesh, gates=gates)


def add_one_ring(result: HexMeshResult, *, features: bool = True, feature_max_deg: float = FEATURE_MAX_DEG,
                 backend: str = "auto") -> HexMeshResult:
    """LMFF's one-ring test (:func:`~.one_ring.one_ring_test`) on the structure of a result made
    with ``one_ring=False``, written into its structure gate (:func:`~.validity.record_one_ring`) and
    timed in the map's ``stats["timings"]["one_ring_s"]``: the result is then what
    ``hex_mesh(..., one_ring=True)`` returns (the test reports, it does not decide a gate). Used
    where many fields are meshed and one is kept (:func:`~.choose.hex_chooser`). ``features``,
    ``feature_max_deg`` and ``backend``: the map's own options. Returns ``result`` (changed in place)."""
    from .one_ring import one_ring_test
    from .validity import record_one_ring

    m = result.map
    t0 = time.perf_counter()
    ring = one_ring_test(m.mesh, None, charts=m.charts, meshability=m.meshability, edge_length=m.edge_length,
                         features=features, feature_max_deg=feature_max_deg, backend=backend)
    record_one_ring(m.gates["structure"], ring)  # the Gate that result.gates holds too
    m.stats.setdefault("timings", {})["one_ring_s"] = time.perf_counter() - t0
    return result


def extraction_gate(ext, quality=None) -> Gate:
    """The extraction's verdict: hexes were extracted, no cube was dropped, and the hex mesh is
    valid (all hexahedra, none inverted, conforming, a closed manifold boundary:
    :attr:`~.quality.HexQuality.valid`, when judged)."""
    c = ext.counts()
    counts = {"hexes": c["hexes"], "cubes_dropped": c["cubes_dropped"]}
    reasons = []
    if not counts["hexes"]:
        reasons.append("no hexes extracted")
    if counts["cubes_dropped"]:
        why = ", ".join(f"{k}: {v}" for k, v in (c.get("dropped") or {}).items() if v)
        reasons.append(f"{counts['cubes_dropped']} cubes dropped" + (f" ({why})" if why else ""))
    if quality is not None:
        counts["hex_mesh_valid"] = bool(quality.valid)
        if not quality.valid:
            reasons.append("the hex mesh is not valid: " + "; ".join(quality.invalid_reasons))
    return Gate(stage="extraction", passed=not reasons, counts=counts, reasons=reasons)
