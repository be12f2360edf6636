"""The candidates of the connection method and the proxy choice among them.

:class:`CandidateStack` makes the fields the connection method may return, stage by stage on
demand (:func:`connection_candidates`: all of them), every one descended from a connection
optimization: each optimized field itself; the checkpoints of the
quality paths of :mod:`torchconn.frames.quality_paths` started at it (L-BFGS on the frames, the mean
angle and the matched Dirichlet energy ``mean_e ||F_i g_ij - F_j||^2`` of Ray et al. 2016 /
Palmer et al. 2020 traded along an annealed weight, with the feature curves soft or held).

Each :class:`Candidate` carries its :func:`~torchconn.frames.metrics.frame_metrics` and its
proxy score (:func:`quality_score` against a reference field's metrics, the SH field: log ratios
of mean angle, Dirichlet energy and complex-type singular faces). :func:`choose_by_proxies` is
the default choice among them (those within the feature-curve bound first, then the lowest
score); the jobs choose by the hex meshes the candidates make
(:func:`torchconn.hexmesh.choose.hex_chooser`).
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from .metrics import frame_metrics
from .quality_paths import DIRICHLET_WEIGHTS, PATH_KINDS, quality_path

__all__ = ["Candidate", "CandidateStack", "connection_candidates", "choose_by_proxies", "quality_score"]


def quality_score(metrics: dict, reference: dict, dirichlet_weight: float = 1.0, complex_weight: float = 0.0) -> float:
    """``log(mean angle / reference's) + b log(Dirichlet energy / reference's) + c log((n_c + 1) / (n_c_ref + 1))``
    with ``b = dirichlet_weight``, ``c = complex_weight`` and ``n_c`` the complex-type singular faces
    (lower is better; 0 at the reference)."""
    tiny = 1e-300
    score = (math.log(max(metrics["smoothness_mean_deg"], tiny) / max(reference["smoothness_mean_deg"], tiny))
             + dirichlet_weight
             * math.log(max(metrics["dirichlet_energy_mean"], tiny) / max(reference["dirichlet_energy_mean"], tiny)))
    if complex_weight:
        score += complex_weight * math.log((metrics["n_singular_faces_complex"] + 1.0)
                                           / (reference["n_singular_faces_complex"] + 1.0))
    return score


# ----------------------------------------------------------------------------- candidates of the connection method
@dataclass
class Candidate:
    """A field the connection method may return (:func:`connection_candidates`).

    Attributes:
        frames: ``(V, 3, 3)``.
        kind: ``"optimized"`` (the connection optimization's own field), a path kind of
            :data:`~torchconn.frames.quality_paths.PATH_KINDS` (a checkpoint of a quality path from an
            optimized field).
        start: the start field the connection optimization began from (``"sh"``, ``"mbo"``,
            ``"init"``): every candidate descends from that optimization.
        dirichlet_weight: the path checkpoint's ``lambda`` (``None`` otherwise).
        metrics: :func:`frame_metrics` of ``frames`` (without the curl).
        score: :func:`quality_score` against the reference (the SH field): lower is better.
        edge_rot: ``(E, 3, 3)`` the optimized connection for ``kind == "optimized"``, else ``None``.
    """

    frames: torch.Tensor
    kind: str
    start: str
    dirichlet_weight: float | None
    metrics: dict
    score: float
    edge_rot: torch.Tensor | None = None

    @property
    def label(self) -> str:
        lam = "" if self.dirichlet_weight is None else f"@{self.dirichlet_weight:g}"
        return f"{self.start}/{self.kind}{lam}"

    def summary(self) -> dict:
        """JSON-ready: label, kind, start, lambda, score and the proxies."""
        m = self.metrics
        return {"label": self.label, "kind": self.kind, "start": self.start, "dirichlet_weight": self.dirichlet_weight,
                "score": self.score, "smoothness_mean_deg": m["smoothness_mean_deg"],
                "smoothness_rms_deg": m["smoothness_rms_deg"], "dirichlet_energy_mean": m["dirichlet_energy_mean"],
                "n_singular_faces": m["n_singular_faces"], "n_singular_faces_complex": m["n_singular_faces_complex"],
                "feature_curve_alignment_mean_deg": m["feature_curve_alignment_mean_deg"]}


class CandidateStack:
    """The candidates of the connection method, made stage by stage on demand.

    Every candidate descends from a connection optimization (``optimized``: ``{start label:
    (frames (V, 3, 3), edge_rot (E, 3, 3))}``, or ``{start label: callable}`` returning that pair:
    the optimization is then run when its stage is made). The stages, in order (:attr:`stages`):

    1. ``"optimized:<start label>"``, one per start: the optimized field itself;
    2. ``"paths"``: the checkpoints of the quality paths
       (:func:`~torchconn.frames.quality_paths.quality_path`, ``paths`` x ``dirichlet_weights``)
       started at each optimized field (all the optimized stages come first), or at those of the
       starts in :attr:`path_starts` when it is set.

    Each candidate is scored by :func:`quality_score` against ``reference`` (the SH field's
    :func:`frame_metrics`).

    A chooser that judges candidates by an expensive end metric (the hex chooser) takes the
    stages one at a time (:meth:`next_stage`) and stops when it has what it needs: the later
    stages are then never made. :meth:`complete` makes them all (the proxy choice needs all).
    There is no fallback to the reference: it is the yardstick of the scores only.

    Attributes:
        candidates: the :class:`Candidate` s made so far, in the order they were made.
        info: ``{"stages": [names made], "seconds": ...}``.
        path_starts: ``None`` (every start) or the start labels whose optimized fields the
            ``"paths"`` stage continues; a chooser sets it before that stage is made (the hex
            chooser: the starts whose optimized field passed the structure gate).
    """

    def __init__(self, mesh, optimized: dict, reference: dict, *, paths: Sequence[str] = ("soft",),
                 dirichlet_weights: Sequence[float] = DIRICHLET_WEIGHTS, rounds: int = 2, iters: int = 20,
                 feature_weight: float = 1.0, tangent_weight: float = 0.25, complex_weight: float = 0.0,
                 score_dirichlet: float = 1.0, score_complex: float = 0.1, eps: float = 1e-3,
                 angle_deg: float = 30.0, align_eps: float = 1e-3):
        bad_paths = [k for k in paths if k not in PATH_KINDS]
        if bad_paths:
            raise ValueError(f"connection_candidates: unknown path kind(s) {bad_paths}; known: {list(PATH_KINDS)}")
        if not optimized:
            raise ValueError("connection_candidates: no optimized field")
        self.mesh, self.reference = mesh, reference
        self._optimized = dict(optimized)  # label -> (F, R) or a callable returning it
        self.stages = tuple(f"optimized:{label}" for label in self._optimized) + ("paths",)
        self.paths, self.dirichlet_weights = tuple(paths), tuple(dirichlet_weights)
        self.path_options = dict(rounds=rounds, iters=iters, feature_weight=feature_weight,
                                 tangent_weight=tangent_weight, complex_weight=complex_weight, eps=eps,
                                 align_eps=align_eps, angle_deg=angle_deg,
                                 a_ref=math.radians(reference["smoothness_mean_deg"]),
                                 d_ref=reference["dirichlet_energy_mean"])
        self.score_weights = (score_dirichlet, score_complex)
        self.candidates: list[Candidate] = []
        self.info: dict = {"stages": [], "seconds": 0.0}
        self.path_starts: set | None = None

    # a read-only sequence of the candidates made so far
    def __len__(self) -> int:
        return len(self.candidates)

    def __getitem__(self, i):
        return self.candidates[i]

    def __iter__(self):
        return iter(self.candidates)

    @property
    def done(self) -> bool:
        """Whether every stage has been made."""
        return len(self.info["stages"]) == len(self.stages)

    @property
    def pending(self) -> str | None:
        """The name of the stage :meth:`next_stage` makes next (``None`` when all are made)."""
        return None if self.done else self.stages[len(self.info["stages"])]

    def next_stage(self) -> list[int] | None:
        """Make the next stage; the indices of its new candidates (maybe none), ``None`` when all are made."""
        name = self.pending
        if name is None:
            return None
        t0 = time.perf_counter()
        n0 = len(self.candidates)
        if name.startswith("optimized:"):
            self._stage_optimized(name.split(":", 1)[1])
        else:
            getattr(self, f"_stage_{name}")()
        self.info["stages"].append(name)
        self.info["seconds"] += time.perf_counter() - t0
        return list(range(n0, len(self.candidates)))

    def complete(self) -> list[Candidate]:
        """Make every stage left; the list of all candidates."""
        while self.next_stage() is not None:
            pass
        return self.candidates

    def _consider(self, F, kind, start, lam, R=None) -> Candidate:
        m = frame_metrics(F, self.mesh, self.path_options["angle_deg"], curl=False)
        c = Candidate(F.detach(), kind, start, lam, m, quality_score(m, self.reference, *self.score_weights), R)
        self.candidates.append(c)
        return c

    def _run_paths(self, F, start, weights) -> None:
        for kind in dict.fromkeys(self.paths):
            for cp in quality_path(self.mesh, F, kind=kind, dirichlet_weights=weights, **self.path_options):
                self._consider(cp.frames, kind, start, cp.dirichlet_weight)

    def _stage_optimized(self, start: str) -> None:
        field = self._optimized[start]
        F, R = field() if callable(field) else field
        self._optimized[start] = (F, R)
        self._consider(F.detach(), "optimized", start, None, R.detach() if R is not None else None)

    def _stage_paths(self) -> None:
        for start, (F, _) in self._optimized.items():
            if self.path_starts is None or start in self.path_starts:
                self._run_paths(F.detach(), start, self.dirichlet_weights)


def connection_candidates(mesh, optimized: dict, reference: dict, **options) -> tuple[list[Candidate], dict]:
    """Every candidate of the connection method: :class:`CandidateStack` ``(mesh, optimized,
    reference, **options)`` with all its stages made.

    Returns:
        ``(candidates, info)``: :class:`Candidate` list (optimized fields first, in the order of
        ``optimized``) and ``{"stages": [...], "seconds": ...}``.
    """
    stack = CandidateStack(mesh, optimized, reference, **options)
    return stack.complete(), stack.info


def choose_by_proxies(mesh, candidates: Sequence[Candidate], feature_curve_bound: float = 2.0) -> tuple[int, dict]:
    """The default choice among :class:`Candidate` s (``mesh`` unused: the signature of ``design``'s ``choose``).

    Candidates whose ``feature_curve_alignment_mean_deg`` is within ``feature_curve_bound`` (or
    ``nan``: no feature curve) come first; among them (all of them when none is) the lowest
    :attr:`Candidate.score` wins, the first one on a tie.

    Returns:
        ``(index, {"by": "proxies", "reason": ...})``.
    """
    if not candidates:
        raise ValueError("choose_by_proxies: no candidate")
    within = [i for i, c in enumerate(candidates)
              if not c.metrics["feature_curve_alignment_mean_deg"] > feature_curve_bound]
    pool = within or list(range(len(candidates)))
    i = min(pool, key=lambda k: candidates[k].score)
    return i, {"by": "proxies", "reason": "lowest proxy score (feature-curve bound first)"}
