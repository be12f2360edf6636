"""``train_frames``: an octahedral frame field on a tet mesh from a differentiable connection.

Method (``method=connection``; the pieces live in :mod:`torchconn.frames`):

1. Initialization ``F^0``: the spherical-harmonic baseline of Ray, Sokolov & Lévy 2016
   (:func:`~torchconn.frames.sh.sh_frame_field`), or ``init_frames`` from a file.
2. Variables (:class:`~torchconn.frames.model.FrameFieldModel`): the connection, started at the
   matched connection of the combed ``F^0`` (``F_i R_ij = F_j h_ij``, ``h_ij in O``), and the
   frames, per vertex about the normal at aligned boundary vertices (``formulation=vertex``,
   :mod:`~torchconn.frames.param`) or propagated from one root per component (``propagate``).
3. Loss :class:`~torchconn.frames.loss.FrameFieldLoss`, ``smooth + tie + flat + torsion + align
   + feature`` with the config's weights, on the mesh's
   :class:`~torchconn.frames.constraints.BoundaryConstraint`; Adam or L-BFGS with a cosine
   schedule (:func:`~torchconn.frames.solver.optimize`).
4. Guarded frames-only polish with the smoothness metric's own angle
   (:func:`~torchconn.frames.polish.polish_frames`, ``polish.steps``; 0 = off).
5. Metrics (:mod:`~torchconn.frames.metrics`) and invariants: Bianchi residuals of the connection
   (:func:`torchconn.dec.bianchi.check`), tets with exactly one singular face.

``method=sh_baseline`` writes the initialization's field. Measurements of the method and its
studies: ``docs/results/frame-fields.md``.

Outputs in ``output_dir``: ``frames.npz`` (vertices, tets, frames, singular_faces),
``metrics.json``, ``frames.vtu``, ``singular_faces.vtu``, ``loss.png``, ``singularities.png``,
``checkpoint.pt`` (atomic, every ``checkpoint_every`` steps and at the end). ``resume=true``
continues from the checkpoint to the same result as an uninterrupted run; a checkpoint of another
configuration (mesh, method, optimizer, weights, ``steps``) is refused.

Bad input fails before any optimization: unknown config keys (``ConfigKeyError``), a value of the
wrong type or out of range (:class:`ConfigError`, from the one typed schema
:data:`training.config_check.TRAIN_FRAMES`; ``resume=no`` is refused, not truthy), an unwritable
``output_dir`` or one in use by another run (:class:`~training.io_utils.OutputDirLockedError`), a
corrupted or foreign checkpoint (:class:`~training.io_utils.CheckpointError`; checkpoints load with
``weights_only=True``, so no code in the file runs), an unreadable or invalid mesh
(:class:`torchconn.mesh.MeshError`). A NaN/inf loss term stops the run with
:class:`NonFiniteLossError` naming the term and the step. The final outputs appear together or not
at all (staged, ``metrics.json`` last); a failed run leaves only its last good checkpoint.

Usage::

    torchconn-frames                                   # or: python -m training.train_frames
    python -m training.train_frames mesh=bunny.obj edge_length=0.05 method=sh_baseline
    python -m training.train_frames optim=lbfgs weights.tie=5 output_dir=out/run1 [resume=true]
    python -m training.train_frames -m mesh=cylinder,torus weights.flat=0.1,1
"""
from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from torchconn import io as tio
from torchconn.dec import bianchi
from torchconn.frames import export, octahedral
from torchconn.frames.constraints import BoundaryConstraint
from torchconn.frames.loss import FrameFieldLoss
from torchconn.frames.metrics import METRIC_KEYS, edge_class_breakdown, frame_metrics
from torchconn.frames.model import FrameFieldModel, matched_connection
from torchconn.frames.polish import polish_frames
from torchconn.frames.sh import sh_frame_field
from torchconn.frames.solver import NonFiniteLossError, make_optimizer, new_history, optimize
from torchconn.lie import so3
from torchconn.mesh import MeshError
from torchconn.tolerances import get_eps

from . import config_check, frame_plots, io_utils

__all__ = ["train", "main", "load_config", "NonFiniteLossError", "ConfigError", "CONFIG_DIR", "BUILTIN_MESHES"]

ConfigError = config_check.ConfigError

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
BUILTIN_MESHES = ("box", "ball", "cylinder", "torus")
CHECKPOINT_KEYS = ("step", "model", "optimizer", "scheduler", "rng", "history", "fingerprint", "init_frames",
                   "init_metrics")


# ----------------------------------------------------------------------------- config
def _schema() -> DictConfig:
    base = OmegaConf.load(CONFIG_DIR / "train_frames.yaml")
    base.pop("hydra", None)
    base.pop("defaults", None)
    return base


def load_config(overrides: list[str] | None = None) -> DictConfig:
    """Compose ``configs/train_frames.yaml`` with Hydra overrides (struct mode), without running.

    Unknown keys raise (Hydra's ``ConfigCompositionException``).
    """
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name="train_frames", overrides=list(overrides or []))


def _validate(cfg) -> DictConfig:
    """Merge ``cfg`` onto the defaults in struct mode (unknown keys raise ``ConfigKeyError``), then
    check every value's type and range (:data:`training.config_check.TRAIN_FRAMES`, :class:`ConfigError`)."""
    schema = _schema()
    OmegaConf.set_struct(schema, True)
    user = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)
    user = OmegaConf.masked_copy(user, [k for k in user.keys() if k != "hydra"]) if "hydra" in user else user
    merged = OmegaConf.merge(schema, user)  # raises ConfigKeyError on unknown keys
    config_check.check_config(merged, config_check.TRAIN_FRAMES, "configs/train_frames.yaml")
    return merged


def _load_mesh(cfg, dtype, device):
    name = str(cfg.mesh)
    kw = {} if cfg.edge_length is None else {"edge_length": float(cfg.edge_length)}
    if name in BUILTIN_MESHES:
        if name == "box":
            n = 4 if cfg.edge_length is None else max(1, round(1.0 / float(cfg.edge_length)))
            mesh = tio.box(n=n)
        else:
            mesh = getattr(tio, name)(**kw)
    else:
        path = Path(name).expanduser()
        if not path.is_file():
            raise FileNotFoundError(f"mesh {name!r}: no such file (built-ins: {list(BUILTIN_MESHES)})")
        mesh = tio.load_mesh(path, **kw)
    if mesh.boundary_faces.shape[0] == 0:
        raise MeshError(f"mesh {name!r} has no boundary faces; a frame field needs a boundary to align to")
    return mesh.to(device=device, dtype=dtype)


def _load_init_frames(path: str, mesh) -> torch.Tensor:
    """Frames ``(V, 3, 3)`` from a ``.npz`` (key ``frames``) or ``.npy``; checked against the mesh."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"init_frames {path!r}: no such file")
    data = np.load(p)
    F = data["frames"] if isinstance(data, np.lib.npyio.NpzFile) else data
    V = mesh.n_vertices
    if F.shape != (V, 3, 3):
        raise ValueError(f"init_frames {path!r} has shape {F.shape}, expected ({V}, 3, 3) for this mesh")
    F = torch.as_tensor(np.asarray(F, dtype=np.float64)).to(device=mesh.vertices.device, dtype=mesh.vertices.dtype)
    err = float((F.transpose(-1, -2) @ F - torch.eye(3, dtype=F.dtype, device=F.device)).abs().max())
    if not err < 1e-4 or not bool((torch.linalg.det(F) > 0).all()):
        raise ValueError(f"init_frames {path!r} are not rotations (max |F^T F - I| = {err:.2e} or det <= 0)")
    return so3.project_to_rotation(F)


# ----------------------------------------------------------------------------- helpers
def _fingerprint(cfg, mesh) -> str:
    """Hash of what a resumed run must share with the checkpoint (mesh, method, optimizer)."""
    h = hashlib.sha256()
    h.update(mesh.vertices.detach().cpu().double().numpy().tobytes())
    h.update(mesh.tets.cpu().numpy().tobytes())
    keys = ["method", "formulation", "optim", "dtype", "feature_angle_deg", "smooth_power", "smooth_eps",
            "align_kind", "align_eps", "lr", "lr_schedule", "steps"]
    h.update(repr([(k, cfg[k]) for k in keys]).encode())
    h.update(repr(OmegaConf.to_container(cfg.weights)).encode())
    h.update(repr(OmegaConf.to_container(cfg.lbfgs)).encode())
    return h.hexdigest()


def _initial_frames(cfg, mesh, ckpt) -> tuple[torch.Tensor, dict]:
    """``(F0 (V, 3, 3), its metrics)``: from the checkpoint, ``init_frames`` or the SH baseline."""
    if ckpt is not None:  # stored in the checkpoint so that a resume does not redo it
        return ckpt["init_frames"].to(device=mesh.vertices.device, dtype=mesh.vertices.dtype), ckpt["init_metrics"]
    if cfg.init_frames is not None:
        F0 = _load_init_frames(str(cfg.init_frames), mesh)
    else:
        F0 = sh_frame_field(mesh, boundary_weight=float(cfg.sh.boundary_weight),
                            n_smooth_iters=int(cfg.sh.n_smooth_iters),
                            feature_angle_deg=float(cfg.feature_angle_deg),
                            mbo_steps=int(cfg.sh.mbo_steps),
                            mbo_tau=(float(cfg.sh.mbo_tau_start), float(cfg.sh.mbo_tau_end)))
    return F0, frame_metrics(F0, mesh, cfg.feature_angle_deg)


def _invariants(R: torch.Tensor, F: torch.Tensor, mesh, atol, dtype) -> tuple[dict, torch.Tensor, str | None]:
    """``(invariants dict, singular faces (S, 3), Bianchi error message or None)``."""
    mask, sing = octahedral.singular_faces(F, mesh)
    one = octahedral.tets_with_one_singular_face(mask, mesh)
    bianchi_error = None
    try:
        bres = bianchi.check(R.detach(), mesh, atol=atol)
    except bianchi.BianchiError as exc:
        bianchi_error = str(exc)
        bres = {"differential": float(bianchi.differential_residual(R.detach(), mesh).max())}
    return {
        "bianchi_differential_max": bres.get("differential"),
        "bianchi_algebraic_max": bres.get("algebraic"),
        "bianchi_tolerance": (atol if atol is not None else get_eps("identity", dtype)) * 3,
        "bianchi_ok": bianchi_error is None,
        "bianchi_error": bianchi_error,
        "n_singular_faces": int(mask.sum()),
        "n_tets_one_singular_face": int(one.sum()),
    }, sing, bianchi_error


def _save_outputs(out: Path, mesh, frames: torch.Tensor, sing_faces: torch.Tensor, history: dict,
                  metrics: dict) -> None:
    with io_utils.staged_outputs(out) as stage:  # a failing writer leaves no partial output
        _write_outputs(stage, mesh, frames, sing_faces, history, metrics)


def _write_outputs(out: Path, mesh, frames, sing_faces, history, metrics) -> None:
    io_utils.atomic_savez(out / "frames.npz", vertices=mesh.vertices.detach().cpu().double().numpy(),
                          tets=mesh.tets.cpu().numpy().astype(np.int64),
                          frames=frames.detach().cpu().double().numpy(),
                          singular_faces=sing_faces.cpu().numpy().astype(np.int64).reshape(-1, 3))
    io_utils.atomic_write_json(out / "metrics.json", metrics)
    export.write_frames_vtu(out / "frames.vtu", mesh, frames)
    export.write_singular_faces_vtu(out / "singular_faces.vtu", mesh, sing_faces)
    frame_plots.plot_loss(out / "loss.png", history)
    frame_plots.plot_singularities(out / "singularities.png", mesh, sing_faces)


# ----------------------------------------------------------------------------- train
def train(cfg) -> dict:
    """Run the frame-field optimization described by ``cfg``; return the metrics dict.

    Args:
        cfg: a ``DictConfig`` or dict with the keys of ``configs/train_frames.yaml`` (missing
            keys take the defaults; unknown keys raise). ``output_dir`` must be set.

    Returns:
        The dict written to ``metrics.json`` (``final`` and ``init`` frame metrics, loss
        history, invariants, timings).
    """
    t_start = time.perf_counter()
    cfg = _validate(cfg)  # types and ranges of every key (ConfigError), before anything is created
    out = io_utils.check_output_dir(cfg.output_dir)
    with io_utils.lock_output_dir(out):  # one run per output_dir (OutputDirLockedError)
        return _train(cfg, out, t_start)


def _train(cfg: DictConfig, out: Path, t_start: float) -> dict:
    """The body of :func:`train` on a checked ``cfg``, with ``out`` locked."""
    ckpt_path = out / "checkpoint.pt"
    if cfg.resume and not ckpt_path.is_file():
        raise FileNotFoundError(f"resume=true but there is no checkpoint at {str(ckpt_path)!r}")
    dtype = getattr(torch, cfg.dtype)
    device = torch.device(cfg.device)
    threads = config_check.resolve_num_threads(cfg.num_threads)
    if threads is not None:
        torch.set_num_threads(threads)
    torch.manual_seed(int(cfg.seed))
    np.random.seed(int(cfg.seed))

    mesh = _load_mesh(cfg, dtype, device)
    fp = _fingerprint(cfg, mesh)
    ckpt = None
    if cfg.resume:
        ckpt = io_utils.load_checkpoint(ckpt_path, map_location=device, fingerprint=fp, required=CHECKPOINT_KEYS)

    t0 = time.perf_counter()
    F0, init_metrics = _initial_frames(cfg, mesh, ckpt)
    t_init = time.perf_counter() - t0

    # --- library objects: constraint, loss, model, optimizer
    constraint = BoundaryConstraint.from_mesh(mesh, float(cfg.feature_angle_deg))
    loss_fn = FrameFieldLoss(mesh, dict(cfg.weights), feature_angle_deg=float(cfg.feature_angle_deg),
                             smooth_power=float(cfg.smooth_power), smooth_eps=float(cfg.smooth_eps),
                             align_kind=str(cfg.align_kind), align_eps=float(cfg.align_eps))
    model = FrameFieldModel(mesh, F0, cfg.formulation, constraint).to(device)
    steps = int(cfg.steps) if cfg.method == "connection" else 0
    optimizer, scheduler = make_optimizer(model.parameters(), cfg.optim, float(cfg.lr), int(cfg.steps),
                                          cfg.lr_schedule, int(cfg.lbfgs.history_size), int(cfg.lbfgs.max_iter))
    history = new_history(loss_fn.weights)
    start = 0
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        io_utils.set_rng_state(ckpt["rng"])
        start = int(ckpt["step"])
        history = {k: list(v) for k, v in ckpt["history"].items()}
        if start > steps:
            raise ValueError(f"checkpoint is at step {start}, beyond steps={steps}")

    def checkpoint(step: int) -> None:
        io_utils.save_checkpoint(ckpt_path, {
            "step": step, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "rng": io_utils.get_rng_state(), "history": history, "fingerprint": fp,
            "init_frames": F0.detach().cpu(), "init_metrics": init_metrics,
            "config": OmegaConf.to_container(cfg, resolve=True),
        })

    bar = None
    if cfg.progress and steps > start:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, initial=start, desc="train_frames", dynamic_ncols=True)

    def on_step(step: int, record: dict) -> None:
        if step % int(cfg.checkpoint_every) == 0 or step == steps:
            checkpoint(step)
        if bar is not None:
            bar.update(1)
            bar.set_postfix({k: f"{v:.3g}" for k, v in record.items()}, refresh=False)

    # --- optimization
    t0 = time.perf_counter()
    if ckpt is None and steps > 0:
        checkpoint(0)
    try:
        optimize(model, loss_fn, optimizer, scheduler, steps, start=start, history=history, on_step=on_step)
    finally:
        if bar is not None:
            bar.close()
    t_opt = time.perf_counter() - t0

    # --- final field (optionally polished), invariants, metrics
    with torch.no_grad():
        R, F = model()
    polish_info = None
    if cfg.method == "connection" and int(cfg.polish.steps) > 0:
        t1 = time.perf_counter()
        F, polish_info = polish_frames(
            mesh, F, int(cfg.polish.steps), lr=float(cfg.polish.lr), check_every=int(cfg.polish.check_every),
            feature_weight=float(cfg.weights.feature), max_singular_faces=int(init_metrics["n_singular_faces"]),
            angle_deg=float(cfg.feature_angle_deg), align_eps=float(cfg.align_eps))
        if polish_info["accepted_step"] > 0:  # the connection that transports the polished frames
            R = matched_connection(F, mesh.edges)
        polish_info["seconds"] = time.perf_counter() - t1
    with torch.no_grad():
        final_terms = {k: float(v) for k, v in loss_fn(R, F).items()}
    if cfg.method == "sh_baseline":
        F = F0
    final_metrics = frame_metrics(F, mesh, cfg.feature_angle_deg)
    atol = None if cfg.bianchi_atol is None else float(cfg.bianchi_atol)
    invariants, sing, bianchi_error = _invariants(R, F, mesh, atol, dtype)
    metrics = {
        "mesh": {"source": str(cfg.mesh), "n_vertices": mesh.n_vertices, "n_edges": mesh.n_edges,
                 "n_faces": mesh.n_faces, "n_tets": mesh.n_tets,
                 "n_boundary_vertices": int(mesh.boundary_vertices.numel())},
        "method": cfg.method,
        "formulation": cfg.formulation if cfg.method == "connection" else None,
        "final": final_metrics,
        "init": init_metrics,
        "edge_classes": edge_class_breakdown(F.detach(), mesh, cfg.feature_angle_deg),
        "polish": polish_info,
        "final_loss_terms": final_terms,
        "loss_history": history,
        "invariants": invariants,
        "timings": {
            "wall_s": time.perf_counter() - t_start,
            "init_s": t_init,
            "optimize_s": t_opt,
            "iterations": steps - start,
            "total_steps": steps,
            "s_per_iteration": t_opt / max(steps - start, 1),
            "num_threads": torch.get_num_threads(),  # after num_threads=auto was resolved
        },
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    assert set(METRIC_KEYS) <= set(final_metrics)
    _save_outputs(out, mesh, F, sing, history, metrics)
    if bianchi_error is not None:
        raise bianchi.BianchiError(bianchi_error)
    return metrics


def main() -> None:
    """Console entry point ``torchconn-frames``: Hydra composes ``configs/train_frames.yaml`` + overrides."""
    import hydra

    @hydra.main(config_path="../configs", config_name="train_frames", version_base="1.3")
    def app(cfg: DictConfig) -> None:
        m = train(cfg)
        f, i = m["final"], m["init"]
        print(f"[train_frames] {cfg.method}: smoothness {i['smoothness_mean_deg']:.2f} -> "
              f"{f['smoothness_mean_deg']:.2f} deg, alignment mean {f['alignment_mean_deg']:.3f} deg, "
              f"singular faces {f['n_singular_faces']}, wall {m['timings']['wall_s']:.1f} s, "
              f"output {cfg.output_dir}")

    app()


if __name__ == "__main__":
    main()
