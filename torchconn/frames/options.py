"""The options of :func:`torchconn.frames.design`: one typed, nested schema, the one place a default is written.

:class:`FrameOptions` (with its groups :class:`Weights`, :class:`LBFGS`, :class:`Quality`,
:class:`SH`) is a tree of dataclasses. Each field carries its type, its default and, in its
``metadata``, what the value may be (:func:`option`):

- ``lo``, ``hi``: inclusive bounds of a number (``lo_open``: ``lo`` itself excluded, ``lr > 0``);
- ``choices``: the allowed values of a string (of each element, for a list);
- ``kind``: a value with its own rule (``"device"``, ``"threads"``: the jobs' keys).

``Optional[...]`` (``X | None``) means ``null`` is allowed; a ``list[...]`` is non-empty. Floats
are finite. :data:`torchconn.frames.design.DEFAULTS` is ``dataclasses.asdict(FrameOptions())``;
the jobs' configs (``training/schema.py``) extend :class:`FrameOptions` with their own keys and
generate their validation from these fields (``training/config_check.py``). The library itself
takes plain Python values and checks them in :func:`~torchconn.frames.design.design`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from .loss import ALIGN_KINDS
from .model import FORMULATIONS
from .quality_paths import DIRICHLET_WEIGHTS, PATH_KINDS
from .solver import LR_SCHEDULES, OPTIMIZERS

__all__ = ["FrameOptions", "LBFGS", "Quality", "SH", "STARTS", "Weights", "option"]

#: Start fields of the connection optimization (option ``starts``).
STARTS = ("sh", "mbo")


def option(default: Any, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           choices: tuple | None = None, kind: str | None = None) -> Any:
    """A dataclass field with its default and what it accepts (``metadata``: ``lo``, ``hi``,
    ``lo_open``, ``choices``, ``kind``; only the given ones are stored). A list or dict default
    becomes a ``default_factory`` (a fresh copy per instance)."""
    meta = {k: v for k, v in (("lo", lo), ("hi", hi), ("choices", choices), ("kind", kind)) if v is not None}
    if lo_open:
        meta["lo_open"] = True
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def group(cls) -> Any:
    """A nested group field: its default is ``cls()``."""
    return dataclasses.field(default_factory=cls)


@dataclass
class Weights:
    """Loss weights (:class:`torchconn.frames.loss.FrameFieldLoss`; a weight of 0 skips the term)."""

    #: ``mean rho(||R_ij - I||)`` (connection smoothness)
    smooth: float = option(1.0, lo=0)
    #: ``mean rho(min_h ||F_i R_ij - F_j h||)``, ``h in O`` (the connection transports the frames; with
    #: smooth_power=1 and tie > smooth an exact penalty)
    tie: float = option(2.0, lo=0)
    #: ``mean min_g ||hol_f - g||^2``, ``g in O`` (symmetric flatness)
    flat: float = option(0.1, lo=0)
    #: solder-form torsion in the frames, ``|Theta_f|^2 / area_f``, over every face (relabeled faces
    #: through the matchings): the non-integrability of the field
    torsion: float = option(0.01, lo=0)
    #: averaged covariant exterior derivative (Def. 5.2, torchconn.AveragedCovariantD): mean over
    #: regular tets of ``|d^nabla Alt d^nabla Alt theta|^2 / vol^(2/3)`` (the discrete ``Omega ^ theta``)
    dnabla: float = option(0.01, lo=0)
    #: boundary normal alignment (non-feature vertices), form: align_kind
    align: float = option(10.0, lo=0)
    #: the same against every face normal incident to a feature vertex
    feature: float = option(1.0, lo=0)
    #: ``mean ||F_i g_ij - F_j||^2`` of the frames (matched Dirichlet energy, the SH baseline's
    #: measure); off by default: the quality stage carries it (studies/frame_quality.py)
    dirichlet: float = option(0.0, lo=0)


@dataclass
class LBFGS:
    """The L-BFGS optimizer of ``optim="lbfgs"`` (:func:`torchconn.frames.solver.make_optimizer`)."""

    history_size: int = option(20, lo=1)
    #: iterations per outer step
    max_iter: int = option(5, lo=1)


@dataclass
class Quality:
    """Quality stage (:func:`torchconn.frames.candidates.connection_candidates`), after the connection
    optimization.

    Quality paths (:mod:`torchconn.frames.quality_paths`) from every optimized field: L-BFGS on the
    frames minimizing mean angle / SH's + lambda x Dirichlet energy / SH's (+ feature terms), lambda
    over ``dirichlet_weights`` (one checkpoint each), ``rounds`` re-matchings of ``iters`` iterations
    per lambda; ``paths``: ``soft`` (feature curves soft; the default) and ``tangent`` (curve tangents
    held exactly except at vertices of singular faces, where ``tangent_weight`` pulls them; not run by
    default since 2026-11-27: on the 35 HexMe ``c`` models no tangent checkpoint gave the first good
    hex mesh of the jobs' chooser, every good mesh came from an optimized field or a soft
    checkpoint, and on the models with no good mesh the two tangent candidates were two more hex
    stages of a failing field; docs/results/hexmesh.md). The optimized fields
    and every checkpoint are the candidates; the returned one is chosen by the proxies (log mean-angle
    ratio + ``score_dirichlet`` x log Dirichlet ratio + ``score_complex`` x log complex-face ratio,
    those within ``feature_curve_bound`` first) or, in the jobs with ``select=hex``, by the hex meshes
    they make (:mod:`torchconn.hexmesh.choose`). ``enabled=False``: only the optimized fields are
    candidates. (The singular-structure search of :mod:`torchconn.frames.matching_search` was a
    third stage until 2026-11-27: its candidates never gave a good hex mesh where the others did
    not, on any HexMe ``c`` model measured, so the method no longer runs it.)
    """

    enabled: bool = option(True)
    paths: list[str] = option(["soft"], choices=PATH_KINDS)
    dirichlet_weights: list[float] = option(list(DIRICHLET_WEIGHTS), lo=0)
    rounds: int = option(2, lo=1)
    #: L-BFGS iterations per round
    iters: int = option(20, lo=1)
    feature_weight: float = option(1.0, lo=0)
    tangent_weight: float = option(0.25, lo=0)
    #: extra weight of the edges of complex-type singular faces (0: off; measured: no gain)
    complex_weight: float = option(0.0, lo=0)
    #: b of the choice among admissible candidates: log(mean ratio) + b log(Dirichlet ratio)
    #: + c log((complex + 1) / (ref's + 1))
    score_dirichlet: float = option(1.0, lo=0)
    #: c of that score
    score_complex: float = option(0.1, lo=0)
    #: degrees (the HexMe issue's per-model bound)
    feature_curve_bound: float = option(2.0, lo=0)


@dataclass
class SH:
    """The SH baseline / initialization (:func:`torchconn.frames.sh.sh_frame_field`)."""

    boundary_weight: float = option(100.0, lo=0, lo_open=True)
    #: L-BFGS iterations of Ray's nonlinear smoothing (0: the linear solve + projection only)
    n_smooth_iters: int = option(30, lo=0)


@dataclass
class FrameOptions:
    """Every option of :func:`torchconn.frames.design` (``method="sh"`` takes ``sh``,
    ``feature_angle_deg``, ``init_frames`` and ``bianchi_atol`` only)."""

    #: vertex: per-vertex frame rotations are variables too, tied to the connection by the loss;
    #: non-feature boundary frames only rotate about their normal (exact alignment).
    #: propagate: frames come from the connection by parallel propagation along a BFS spanning tree
    #: from one root frame per component (the connection + root frames are the only variables;
    #: alignment is a penalty).
    formulation: str = option("vertex", choices=FORMULATIONS)
    weights: Weights = group(Weights)
    #: Start fields of the connection optimization: the connection (+ frames) is optimized from each,
    #: and every candidate the method may return descends from one of these optimizations (no
    #: fallback to a start field): sh (the SH field of Ray et al. 2016, also the reference whose
    #: metrics are reported beside the result) and mbo (the MBO field of torchconn.frames.mbo,
    #: Palmer, Bommes & Solomon 2020; the two reach different singular structures). Default sh
    #: alone: on the 35 HexMe c models no candidate of the MBO start gave a good hex mesh that the
    #: SH start's candidates did not; on the simple u meshes it gives s06's (docs/results/hexmesh.md,
    #: 2026-11-28: the time targets of the c models against one more good u mesh).
    starts: list[str] = option(["sh"], choices=STARTS)
    #: sharp-edge threshold of the boundary constraint (torchconn.frames.constraints)
    feature_angle_deg: float = option(30.0, lo=0, hi=180)
    #: rho of the smooth and tie terms: 2 = squared (Dirichlet), 1 = total variation (smoothed by
    #: smooth_eps); FrameFieldLoss's range
    smooth_power: float = option(1.0, lo=0.5, hi=2)
    smooth_eps: float = option(1e-3, lo=0, lo_open=True)
    #: form of the align/feature terms: angle = smoothed angle to the closest axis (what the
    #: alignment metrics average; L1-like, best mean at feature vertices); quartic = ``1 - sum_k (F_k . n)^4``
    align_kind: str = option("angle", choices=ALIGN_KINDS)
    #: smoothing of the angle form (radians)
    align_eps: float = option(1e-3, lo=0, lo_open=True)
    optim: str = option("adam", choices=OPTIMIZERS)
    #: optimizer steps (L-BFGS: outer steps of lbfgs.max_iter iterations each)
    steps: int = option(150, lo=0)
    lr: float = option(0.02, lo=0, lo_open=True)
    #: cosine (to 0 at ``steps``) or constant
    lr_schedule: str = option("cosine", choices=LR_SCHEDULES)
    lbfgs: LBFGS = group(LBFGS)
    quality: Quality = group(Quality)
    sh: SH = group(SH)
    #: initialization from a file instead of the SH field (a frames.npz of an earlier run, key
    #: ``frames``, or a .npy of shape (V, 3, 3) for this mesh); None: the SH baseline (the method's
    #: definition). For studies only (e.g. ``python -m studies.frame_studies constint --mesh M --out f.npy``).
    init_frames: str | None = option(None)
    #: relative tolerance of the Bianchi check (None: tolerances.get_eps("identity"))
    bianchi_atol: float | None = option(None, lo=0, lo_open=True)
