"""One call from a tet mesh to an octahedral frame field: :func:`design` -> :class:`FrameFieldResult`.

The library form of the ``train_frames`` job (``training/train_frames.py`` is ``config ->
design() -> writers``); nothing is written to disk. Methods:

* ``"connection"``: the connection does the work. From each start field of ``starts`` (the
  spherical-harmonic field of Ray, Sokolov & Lévy 2016, :func:`~torchconn.frames.sh.sh_frame_field`,
  or ``init_frames``; the MBO field of Palmer, Bommes & Solomon 2020,
  :func:`~torchconn.frames.mbo.mbo_frames`) a :class:`~torchconn.frames.model.FrameFieldModel`
  (connection + frames) is optimized against :class:`~torchconn.frames.loss.FrameFieldLoss`
  (smoothness, tie, symmetric flatness, √R torsion through the matchings, the averaged covariant
  exterior derivative, alignment; plus any ``extra_terms``, e.g. the seamless map's fitting
  energy of :mod:`torchconn.hexmesh.energy`) by :func:`~torchconn.frames.solver.optimize`;
  then the candidates (:class:`~torchconn.frames.candidates.CandidateStack`, made stage by stage
  as the choice asks for them): the optimized fields and the checkpoints of the L-BFGS quality
  paths from them (:mod:`~torchconn.frames.quality_paths`).
  Every candidate descends from a connection optimization; the SH field is the yardstick of the
  proxies and is reported beside the result (``metrics["init"]``), never returned. The returned
  field is the candidate ``choose`` picks (default: the proxies' score; the jobs choose by the
  hex meshes the candidates make, :func:`torchconn.hexmesh.choose.hex_chooser`);
  ``metrics["chosen"]`` says which and why, and lists every candidate made (the hex chooser stops
  at its first good hex mesh, and the stages after it are never made);
* ``"sh"``: the spherical-harmonic field only (``"sh_baseline"`` is accepted as the config's name).

Options are the fields of :class:`~torchconn.frames.options.FrameOptions` that belong to the method
(:data:`OPTIONS`, defaults :data:`DEFAULTS`; types, ranges and meanings: :mod:`~torchconn.frames.options`);
nested groups (``weights``, ``lbfgs``, ``quality``, ``sh``) are merged onto their defaults, so
``weights={"tie": 5.0}`` changes one weight. Unknown names raise ``TypeError`` listing the known ones.

Conventions (docs/conventions.md §1, :mod:`torchconn.frames.octahedral`): ``frames[i][:, k]`` is
axis ``k`` at vertex ``i``; ``edge_rot[e] = R_ij`` for the canonical edge ``(i, j)``, ``i < j``, maps
coordinates at ``v_j`` to coordinates at ``v_i`` with ``F_i R_ij = F_j h_ij``, ``h_ij in O``;
``matchings[e]`` indexes :func:`~torchconn.frames.octahedral.group`, ``F_i g*_ij ~ F_j``.

Per-tet frames: :func:`~torchconn.frames.octahedral.tet_frames` (the result's ``tet_frames``).
"""
from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..dec import bianchi
from ..lie import so3
from ..mesh import MeshError, load_mesh
from ..tolerances import get_eps
from . import octahedral
from .octahedral import tet_frames
from .constraints import BoundaryConstraint
from .loss import FrameFieldLoss
from .mbo import mbo_frames
from .metrics import edge_class_breakdown, frame_metrics
from .model import FrameFieldModel, matched_connection
from .options import STARTS, FrameOptions
from .candidates import CandidateStack, choose_by_proxies
from .sh import sh_frame_field
from .singular import singular_graph
from .solver import make_optimizer, new_history, optimize

__all__ = ["DEFAULTS", "METHODS", "OPTIONS", "FrameFieldResult", "design", "method_options"]

#: Methods of :func:`design` (``"sh_baseline"`` is an alias of ``"sh"``).
METHODS = ("connection", "sh")
_ALIASES = {"sh_baseline": "sh"}

#: Default value of every option: ``dataclasses.asdict(FrameOptions())``, the schema of
#: :mod:`torchconn.frames.options` (where each option's type, range and meaning are written).
DEFAULTS: dict[str, Any] = dataclasses.asdict(FrameOptions())
_COMMON = ("sh", "feature_angle_deg", "init_frames", "bianchi_atol")
#: Option names of each method.
OPTIONS: dict[str, tuple[str, ...]] = {
    "connection": tuple(DEFAULTS),
    "sh": _COMMON,
}
# the string options with a fixed set of values (lists of choices are checked where they are used)
_CHOICES = {f.name: f.metadata["choices"] for f in dataclasses.fields(FrameOptions)
            if "choices" in f.metadata and f.type == "str"}


def method_options(method: str) -> tuple[str, ...]:
    """The option names of ``method`` (a name of :data:`METHODS` or an alias)."""
    return OPTIONS[_method_name(method)]


@dataclass
class FrameFieldResult:
    """What :func:`design` returns (tensors on the mesh's device and dtype, detached).

    Attributes:
        mesh: the ``TetMesh`` the field lives on (after the ``device``/``dtype`` move).
        vertex_frames: ``(V, 3, 3)`` rotations; ``vertex_frames[i][:, k]`` is axis ``k`` at vertex ``i``.
        tet_frames: ``(T, 3, 3)`` rotations by the rule of :func:`~torchconn.frames.octahedral.tet_frames`.
        edge_rot: ``(E, 3, 3)`` the connection ``R_ij`` on ``mesh.edges``, ``F_i R_ij = F_j h_ij``,
            ``h_ij in O`` (the optimized one for an ``"optimized"`` candidate; the matched
            connection of ``vertex_frames`` for the other candidates and for ``method="sh"``).
        matchings: ``(E,)`` long, ``g*_ij = octahedral.group()[matchings[e]]`` with ``F_i g*_ij ~ F_j``
            (:func:`~torchconn.frames.octahedral.match_edges`, the matchings of the metrics).
        singular_faces: ``(F,)`` bool, faces of ``mesh.faces`` with non-identity matched holonomy.
        singular_graph: the :class:`~torchconn.frames.singular.SingularGraph` of ``vertex_frames``
            (curves through the singular faces, their holonomy types, junctions; ``counts()``).
        metrics: ``{"mesh", "method", "formulation", "final", "init", "edge_classes",
            "quality", "chosen", "final_loss_terms", "invariants"}``: ``final``/``init`` are
            :func:`~torchconn.frames.metrics.frame_metrics` of the result and of the SH field (or
            ``init_frames``), ``chosen`` the returned candidate (``label``, ``start``, ``kind``,
            ``dirichlet_weight``, ``by``, ``reason``, ``candidates``: every candidate's proxies),
            ``invariants`` the Bianchi residuals of ``edge_rot`` (``bianchi_ok``) and the singular
            counts; ``final_loss_terms``, ``quality`` and ``chosen`` are ``None`` for ``method="sh"``.
        history: ``{loss term: [value per step]}`` of the optimization that made the returned field
            (unweighted terms, ``"total"`` weighted; empty for ``"sh"``); ``histories``:
            ``{start: history}`` of every start.
        timings: ``{"wall_s", "init_s", "optimize_s", "quality_s", "choose_s",
            "iterations", "total_steps", "s_per_iteration", "stopped_early"}`` (``iterations``:
            over every start).
        hex: the hex mesh a hex chooser made of this very field while choosing it
            (:func:`torchconn.hexmesh.choose.design_for_hex`, a
            :class:`~torchconn.hexmesh.pipeline.HexMeshResult`), so that it is not meshed twice;
            ``None`` otherwise.
    """

    mesh: Any
    vertex_frames: torch.Tensor
    tet_frames: torch.Tensor
    edge_rot: torch.Tensor
    matchings: torch.Tensor
    singular_faces: torch.Tensor
    singular_graph: Any
    metrics: dict
    history: dict[str, list[float]] = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    histories: dict[str, dict] = field(default_factory=dict)
    hex: Any = None

    def __repr__(self) -> str:  # shapes and headline numbers, not every tensor entry
        f = self.metrics.get("final", {})
        return (f"FrameFieldResult(method={self.metrics.get('method')!r}, V={self.vertex_frames.shape[0]}, "
                f"T={self.tet_frames.shape[0]}, E={self.edge_rot.shape[0]}, "
                f"smoothness_mean_deg={f.get('smoothness_mean_deg', float('nan')):.3f}, "
                f"n_singular_faces={int(self.singular_faces.sum())}, "
                f"steps={self.timings.get('iterations', 0)}, wall_s={self.timings.get('wall_s', 0.0):.2f})")


# ----------------------------------------------------------------------------- options
def _method_name(method: str) -> str:
    name = _ALIASES.get(method, method)
    if name not in METHODS:
        raise ValueError(f"unknown method {method!r}; known: {list(METHODS)} (alias: {_ALIASES})")
    return name


def _resolve_options(method: str, options: dict, extra: tuple = ()) -> dict:
    """Defaults of ``method`` overlaid with ``options`` (groups merged), names and values checked;
    ``extra``: names of extra loss terms, allowed as ``weights`` keys (default 0)."""
    known = OPTIONS[method]
    unknown = [k for k in options if k not in known]
    if unknown:
        other = [k for k in unknown if k in DEFAULTS]
        hint = f" ({other} belong to another method)" if other else ""
        raise TypeError(f"design(method={method!r}): unknown option(s) {unknown}{hint}; known options: {list(known)}")
    opts = {}
    for k in known:
        default = DEFAULTS[k]
        if isinstance(default, dict):
            given = dict(options.get(k) or {})
            if k == "weights":
                default = {**default, **{name: 0.0 for name in extra}}
            bad = [s for s in given if s not in default]
            if bad:
                raise TypeError(f"design(): unknown option(s) {[f'{k}.{s}' for s in bad]}; "
                                f"known {k} keys: {list(default)}")
            opts[k] = {**default, **given}
        else:
            opts[k] = options.get(k, default)
    for k, allowed in _CHOICES.items():
        if k in opts and opts[k] not in allowed:
            raise ValueError(f"design(): option {k}={opts[k]!r} is not one of {list(allowed)}")
    if method == "connection":
        bad = [x for x in opts["starts"] if x not in STARTS]
        if bad or not opts["starts"] or len(set(opts["starts"])) != len(opts["starts"]):
            raise ValueError(f"design(): option starts must name each of {list(STARTS)} at most once, got {opts['starts']}")
        if int(opts["steps"]) < 0:
            raise ValueError(f"design(): option steps must be >= 0, got {opts['steps']}")
        if not float(opts["lr"]) > 0:
            raise ValueError(f"design(): option lr must be > 0, got {opts['lr']}")
        for k, w in opts["weights"].items():
            if not (math.isfinite(float(w)) and float(w) >= 0):
                raise ValueError(f"design(): option weights.{k} must be finite and >= 0, got {w}")
    return opts


def _as_mesh(mesh, device, dtype):
    if isinstance(mesh, (str, Path)):
        path = Path(mesh).expanduser()
        if not path.is_file():
            raise FileNotFoundError(f"mesh {str(mesh)!r}: no such file")
        mesh = load_mesh(path)
    if not hasattr(mesh, "tets"):
        raise TypeError(f"mesh must be a TetMesh or a path to a mesh file, got {type(mesh).__name__}")
    if isinstance(dtype, str):
        dtype = getattr(torch, dtype)
    if device is not None or dtype is not None:
        mesh = mesh.to(device=device, dtype=dtype)
    if mesh.boundary_faces.shape[0] == 0:
        raise MeshError("mesh has no boundary faces; a frame field needs a boundary to align to")
    return mesh


def _init_frames(value, mesh) -> torch.Tensor:
    """Frames ``(V, 3, 3)`` from a tensor/array or a ``.npz`` (key ``frames``) / ``.npy`` path, checked."""
    name = "init_frames"
    if isinstance(value, (str, Path)):
        p = Path(value).expanduser()
        name = f"init_frames {str(value)!r}"
        if not p.is_file():
            raise FileNotFoundError(f"{name}: no such file")
        data = np.load(p)
        value = data["frames"] if isinstance(data, np.lib.npyio.NpzFile) else data
    F = torch.as_tensor(np.asarray(value, dtype=np.float64) if not torch.is_tensor(value) else value)
    V = mesh.n_vertices
    if tuple(F.shape) != (V, 3, 3):
        raise ValueError(f"{name} has shape {tuple(F.shape)}, expected ({V}, 3, 3) for this mesh")
    F = F.to(device=mesh.vertices.device, dtype=mesh.vertices.dtype)
    err = float((F.transpose(-1, -2) @ F - torch.eye(3, dtype=F.dtype, device=F.device)).abs().max())
    if not err < 1e-4 or not bool((torch.linalg.det(F) > 0).all()):
        raise ValueError(f"{name} are not rotations (max |F^T F - I| = {err:.2e} or det <= 0)")
    return so3.project_to_rotation(F)


def _invariants(R: torch.Tensor, mask: torch.Tensor, mesh, atol) -> dict:
    one = octahedral.tets_with_one_singular_face(mask, mesh)
    error = None
    try:
        res = bianchi.check(R.detach(), mesh, atol=atol)
    except bianchi.BianchiError as exc:
        error = str(exc)
        res = {"differential": float(bianchi.differential_residual(R.detach(), mesh).max())}
    return {
        "bianchi_differential_max": res.get("differential"),
        "bianchi_algebraic_max": res.get("algebraic"),
        "bianchi_tolerance": (atol if atol is not None else get_eps("identity", R.dtype)) * 3,
        "bianchi_ok": error is None,
        "bianchi_error": error,
        "n_singular_faces": int(mask.sum()),
        "n_tets_one_singular_face": int(one.sum()),
    }


def _rng_state(device) -> dict:
    state = {"torch": torch.get_rng_state()}
    if torch.device(device).type == "cuda" and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _progress_bar(enabled: bool, total: int, initial: int):
    if not enabled or total <= initial:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        warnings.warn("design(progress=True): tqdm is not installed (pip install tqdm); no progress bar",
                      stacklevel=3)
        return None
    return tqdm(total=total, initial=initial, desc="design", dynamic_ncols=True)


# ----------------------------------------------------------------------------- design
def design(mesh, method: str = "connection", *, progress: bool = False,
           callback: Callable[[int, dict], bool | None] | None = None, seed: int | None = 0,
           device=None, dtype=None, state: dict | None = None,
           on_checkpoint: Callable[[dict], None] | None = None, checkpoint_every: int = 25,
           choose: Callable | None = None, extra_terms: dict | None = None,
           **options) -> FrameFieldResult:
    """Octahedral frame field on a tet mesh (methods and rules: the module docstring). Writes no file.

    Args:
        mesh: a ``TetMesh`` or a path to a mesh file (:func:`torchconn.mesh.load_mesh` with its
            defaults). It needs boundary faces (:class:`~torchconn.mesh.MeshError` otherwise).
        method: ``"connection"`` or ``"sh"`` (:data:`METHODS`).
        progress: a tqdm bar over the optimizer steps (a warning and no bar without tqdm).
        callback: ``callback(step, record)`` after every optimizer step ``step = 1, ..., steps``
            (of each start, counted across starts) with ``record`` the step's loss terms
            (floats). **Returning ``True`` stops** the optimization of the current start after
            that step (``timings["stopped_early"]``); exceptions propagate.
        seed: ``torch.manual_seed(seed)`` first (``None``: the global RNG is left alone).
        device, dtype: move the mesh (and so everything) there; ``None`` keeps the mesh's.
        state: resume from a dict given to ``on_checkpoint`` by an earlier call with the same
            mesh and options (``method="connection"``): the start fields, the finished starts'
            optimized fields, the current start's model, optimizer, scheduler, torch RNG, step and
            history are restored, and the result equals the uninterrupted run's.
        on_checkpoint: ``on_checkpoint(state)`` at step 0 of every start, every
            ``checkpoint_every`` steps and at its last step, with ``state = {"start", "done",
            "step", "model", "optimizer", "scheduler", "rng", "history", "init_frames", "starts",
            "init_metrics"}`` (live ``state_dict`` objects: serialize them before the next step;
            ``init_frames`` holds the start fields made so far, ``starts`` every start's label).
        choose: ``choose(mesh, stack) -> (index, info)`` picks the returned field among the
            :class:`~torchconn.frames.candidates.Candidate` s of a
            :class:`~torchconn.frames.candidates.CandidateStack` (the candidates made so far; it
            asks for more with ``stack.next_stage()`` or ``stack.complete()``; ``index`` into
            ``stack.candidates``). Default: :func:`~torchconn.frames.candidates.choose_by_proxies`
            of every candidate; :func:`torchconn.hexmesh.choose.hex_chooser` chooses by the hex
            meshes they make.
        extra_terms: ``{name: factory}`` extra loss terms: ``factory(mesh, start_frames)`` returns
            ``term(edge_rot, frames) -> 0-dim tensor``, weighted by ``weights[name]`` (e.g.
            :class:`torchconn.hexmesh.energy.MapEnergy`, the seamless map's fitting energy).
        **options: :data:`OPTIONS` of the method (defaults :data:`DEFAULTS`); ``init_frames`` is a
            ``(V, 3, 3)`` tensor/array or a ``.npz`` (key ``frames``) / ``.npy`` path: it
            replaces the ``"sh"`` start (label ``"init"``).

    Returns:
        :class:`FrameFieldResult`. A failed Bianchi check is reported in
        ``metrics["invariants"]`` (``bianchi_ok``, ``bianchi_error``), not raised.

    Raises:
        TypeError: an unknown option (the message lists the known ones).
        torchconn.frames.solver.NonFiniteLossError: a NaN/inf loss term (naming it and the step).
    """
    t_start = time.perf_counter()
    method = _method_name(method)
    extra_terms = dict(extra_terms or {})
    opts = _resolve_options(method, options, extra=tuple(extra_terms))
    if checkpoint_every < 1:
        raise ValueError(f"design(): checkpoint_every must be >= 1, got {checkpoint_every}")
    if state is not None and method != "connection":
        raise ValueError(f"design(): state= resumes method 'connection' only, not {method!r}")
    mesh = _as_mesh(mesh, device, dtype)
    if seed is not None:
        torch.manual_seed(int(seed))
    angle = float(opts["feature_angle_deg"])

    # 1. the start fields: SH (the reference whose proxies are reported beside the result); MBO
    # (``None`` here) is computed when its start is first optimized
    t0 = time.perf_counter()
    if state is not None:
        made = {k: v.to(device=mesh.vertices.device, dtype=mesh.vertices.dtype) for k, v in state["init_frames"].items()}
        starts_F = {k: made.get(k) for k in state.get("starts", list(made))}
        init_metrics = state["init_metrics"]
        F_ref = made.get("sh", next(iter(made.values())))
    else:
        if opts["init_frames"] is not None:  # replaces the SH field: the "sh" method's field and start
            F_ref = _init_frames(opts["init_frames"], mesh)
        else:
            s = opts["sh"]
            F_ref = sh_frame_field(mesh, boundary_weight=float(s["boundary_weight"]),
                                   n_smooth_iters=int(s["n_smooth_iters"]), feature_angle_deg=angle)
        init_metrics = frame_metrics(F_ref, mesh, angle)
        starts_F = {}
        if method == "connection":
            for label in opts["starts"]:
                if label == "sh":
                    starts_F["init" if opts["init_frames"] is not None else "sh"] = F_ref
                elif label == "mbo":
                    starts_F["mbo"] = None
    t_init = time.perf_counter() - t0

    history: dict[str, list[float]] = {}
    histories: dict[str, dict] = {}
    t_opt = t_quality = t_choose = 0.0
    steps = iterations = 0
    stopped = False
    final_terms = quality_info = choice = None
    if method == "sh":
        F = F_ref
        R = matched_connection(F, mesh.edges)
    else:
        constraint = BoundaryConstraint.from_mesh(mesh, angle)
        steps = int(opts["steps"])
        lb = opts["lbfgs"]
        done: dict = {} if state is None else {k: dict(v) for k, v in state["done"].items()}
        labels = list(starts_F)
        bar = _progress_bar(progress, steps * len(labels), 0)
        loss_fns = {}
        tally = {"stopped": False, "iterations": 0, "seconds": 0.0, "init_s": 0.0}

        def run_start(n_start: int, label: str):
            """2.-3. The connection optimization from the start field ``label``: its ``(frames, edge_rot)``."""
            t0 = time.perf_counter()
            # 2. model, loss, optimizer of this start
            if starts_F[label] is None:  # the MBO start field, made when first needed
                t1 = time.perf_counter()
                starts_F[label] = mbo_frames(mesh, feature_angle_deg=angle, warm_start=True).to(mesh.vertices.dtype)
                tally["init_s"] += time.perf_counter() - t1
            model = FrameFieldModel(mesh, starts_F[label], opts["formulation"], constraint).to(mesh.vertices.device)
            # the extra terms are built on the model's own (combed) start frames: their labels
            with torch.no_grad():
                F_model0 = model()[1].detach()
            terms = {name: factory(mesh, F_model0) for name, factory in extra_terms.items()
                     if float(opts["weights"].get(name, 0.0)) > 0}
            loss_fn = FrameFieldLoss(mesh, dict(opts["weights"]), feature_angle_deg=angle,
                                     smooth_power=float(opts["smooth_power"]), smooth_eps=float(opts["smooth_eps"]),
                                     align_kind=str(opts["align_kind"]), align_eps=float(opts["align_eps"]),
                                     extra_terms=terms)
            loss_fns[label] = loss_fn
            if label in done:
                if bar is not None:
                    bar.update(steps)
                return done[label]["frames"], done[label]["edge_rot"]
            optimizer, scheduler = make_optimizer(model.parameters(), opts["optim"], float(opts["lr"]), steps,
                                                  opts["lr_schedule"], int(lb["history_size"]), int(lb["max_iter"]))
            hist = new_history(loss_fn.weights)
            first = 0
            if state is not None and state.get("start") == label and label not in done:
                model.load_state_dict(state["model"])
                optimizer.load_state_dict(state["optimizer"])
                scheduler.load_state_dict(state["scheduler"])
                if "rng" in state:
                    _set_rng_state(state["rng"])
                first = int(state["step"])
                hist = {k: list(v) for k, v in state["history"].items()}
                if first > steps:
                    raise ValueError(f"design(): the state is at step {first}, beyond steps={steps}")
                if bar is not None:
                    bar.update(first)

            def checkpoint(step: int, label=label, model=model, optimizer=optimizer, scheduler=scheduler,
                           hist=hist) -> None:
                on_checkpoint({
                    "start": label, "done": done, "step": step, "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                    "rng": _rng_state(mesh.vertices.device), "history": hist,
                    "init_frames": {k: v.detach().cpu() for k, v in starts_F.items() if v is not None},
                    "starts": list(starts_F),
                    "init_metrics": init_metrics,
                })

            offset = n_start * steps

            def on_step(step: int, record: dict, checkpoint=checkpoint, offset=offset) -> bool:
                if on_checkpoint is not None and (step % checkpoint_every == 0 or step == steps):
                    checkpoint(step)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix({k: f"{v:.3g}" for k, v in record.items()}, refresh=False)
                return callback is not None and callback(offset + step, record) is True

            # 3. the connection optimization from this start
            if first == 0 and steps > 0 and on_checkpoint is not None:
                checkpoint(0)
            optimize(model, loss_fn, optimizer, scheduler, steps, start=first, history=hist, on_step=on_step)
            tally["stopped"] = tally["stopped"] or len(hist["total"]) < steps
            tally["iterations"] += len(hist["total"]) - first
            with torch.no_grad():
                R_s, F_s = model()
            done[label] = {"frames": F_s.detach(), "edge_rot": R_s.detach(), "history": hist}
            if on_checkpoint is not None:
                checkpoint(len(hist["total"]))
            tally["seconds"] += time.perf_counter() - t0
            return done[label]["frames"], done[label]["edge_rot"]

        # each start is optimized when the choice first asks for its field (the proxies: all of them;
        # the hex chooser: the next one only when the fields so far did not mesh well)
        optimized = {label: (lambda n=n, label=label: run_start(n, label)) for n, label in enumerate(labels)}

        # 4. the candidates: the optimized fields and the quality paths from them
        q = opts["quality"]
        stack = CandidateStack(
            mesh, optimized, init_metrics, paths=tuple(q["paths"]) if q["enabled"] else (),
            dirichlet_weights=tuple(float(x) for x in q["dirichlet_weights"]), rounds=int(q["rounds"]),
            iters=int(q["iters"]), feature_weight=float(q["feature_weight"]), tangent_weight=float(q["tangent_weight"]),
            complex_weight=float(q["complex_weight"]), score_dirichlet=float(q["score_dirichlet"]),
            score_complex=float(q["score_complex"]),
            angle_deg=angle, align_eps=float(opts["align_eps"]))
        # 5. the choice (default: the proxies, of every candidate; a hex chooser: the hex meshes
        # they make, taking the stages one at a time and stopping at its first good hex mesh)
        t0 = time.perf_counter()
        try:
            if choose is None:
                idx, cinfo = choose_by_proxies(mesh, stack.complete(), float(q["feature_curve_bound"]))
            else:
                idx, cinfo = choose(mesh, stack)
        finally:
            if bar is not None:
                bar.close()
        t_init += tally["init_s"]  # the MBO start field, made inside its start's optimization
        t_opt = tally["seconds"] - tally["init_s"]
        t_quality = stack.info["seconds"] - tally["seconds"]  # the candidates' making, besides the optimizations
        t_choose = time.perf_counter() - t0 - stack.info["seconds"]
        stopped, iterations = tally["stopped"], tally["iterations"]
        histories = {k: done[k]["history"] for k in labels if k in done}
        quality_info = {**stack.info, "seconds": t_quality}
        cands = stack.candidates
        win = cands[idx]
        F = win.frames
        R = win.edge_rot if win.edge_rot is not None else matched_connection(F, mesh.edges)
        history = histories[win.start]
        choice = {"index": int(idx), "label": win.label, "kind": win.kind, "start": win.start,
                  "dirichlet_weight": win.dirichlet_weight, "score": win.score, **cinfo,
                  "candidates": [c.summary() for c in cands]}
        with torch.no_grad():
            final_terms = {k: float(v) for k, v in loss_fns[win.start](R, F).items()}

    # 6. matchings, per-tet frames, metrics, invariants
    F, R = F.detach(), R.detach()
    matchings = octahedral.match_edges(F, mesh.edges)[0]
    mask, _ = octahedral.singular_faces(F, mesh)
    atol = None if opts["bianchi_atol"] is None else float(opts["bianchi_atol"])
    metrics = {
        "mesh": {"n_vertices": mesh.n_vertices, "n_edges": mesh.n_edges, "n_faces": mesh.n_faces,
                 "n_tets": mesh.n_tets, "n_boundary_vertices": int(mesh.boundary_vertices.numel())},
        "method": method,
        "formulation": opts["formulation"] if method == "connection" else None,
        "final": frame_metrics(F, mesh, angle),
        "init": init_metrics,
        "edge_classes": edge_class_breakdown(F, mesh, angle),
        "quality": quality_info,
        "chosen": choice,
        "final_loss_terms": final_terms,
        "invariants": _invariants(R, mask, mesh, atol),
    }
    timings = {
        "wall_s": time.perf_counter() - t_start,
        "init_s": t_init,
        "optimize_s": t_opt,
        "quality_s": t_quality,
        "choose_s": t_choose,
        "iterations": iterations,
        "total_steps": steps,
        "s_per_iteration": t_opt / max(iterations, 1),
        "stopped_early": stopped,
    }
    return FrameFieldResult(mesh=mesh, vertex_frames=F, tet_frames=tet_frames(F, mesh, matchings), edge_rot=R,
                            matchings=matchings, singular_faces=mask,
                            singular_graph=singular_graph(F, mesh, matchings), metrics=metrics, history=history,
                            timings=timings, histories=histories)
