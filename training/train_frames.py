"""``train_frames``: an octahedral frame field on a tet mesh from a differentiable connection.

A thin command over :func:`torchconn.frames.design` (the same field from Python, no files):
config -> ``design(mesh, method, **options)`` -> writers + checkpoint/resume.

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
4. Candidates (:class:`~torchconn.frames.candidates.CandidateStack`): the optimized fields and the
   L-BFGS quality paths from them; the returned one is chosen by the proxies (``select=proxies``)
   or by the hex meshes they make (``select=hex``, stage by stage until the first good hex mesh).
5. Metrics (:mod:`~torchconn.frames.metrics`) and invariants: Bianchi residuals of the connection
   (:func:`torchconn.dec.bianchi.check`), tets with exactly one singular face.

``method=sh_baseline`` writes the initialization's field. Measurements of the method and its
studies: ``docs/results/frame-fields.md``.

Outputs in ``output_dir``: ``frames.npz`` (vertices, tets, frames, singular_faces),
``metrics.json``, ``frames.vtu`` (per-vertex and per-tet frames), ``frames.fra`` (per-tet frames for
CubeCover / HexFrameFlow), ``singular_faces.vtu``, ``singular_curves.vtu`` (the singular graph's
polylines with their type), ``loss.png``, ``singularities.png``,
``checkpoint.pt`` (atomic, every ``checkpoint_every`` steps and at the end); with ``select=hex``,
``map_frames.npz``: the field the chosen candidate's map follows (per tet, on the map's tet mesh:
with the hex stage's repaired matchings, re-optimized with them fixed where they changed; the hex
job's file of the same name). ``resume=true
continues from the checkpoint to the same result as an uninterrupted run; a checkpoint of another
configuration (mesh, method, optimizer, weights, ``steps``) is refused.

Bad input fails before any optimization: unknown config keys (``ConfigKeyError``), a value of the
wrong type or out of range (:class:`ConfigError`, checked against the one typed schema
:class:`training.schema.TrainFramesConfig`; ``resume=no`` is refused, not truthy), an unwritable
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
from torchconn.frames import field_files
from torchconn.frames.design import FrameFieldResult, design, method_options
from torchconn.frames.metrics import METRIC_KEYS
from torchconn.frames.solver import NonFiniteLossError
from torchconn.mesh import MeshError

from . import config_check, frame_plots, io_utils, schema

__all__ = ["train", "main", "load_config", "NonFiniteLossError", "ConfigError", "CONFIG_DIR", "BUILTIN_MESHES"]

ConfigError = config_check.ConfigError

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
BUILTIN_MESHES = ("box", "ball", "cylinder", "torus")
CHECKPOINT_KEYS = ("start", "done", "step", "model", "optimizer", "scheduler", "rng", "history", "fingerprint",
                   "init_frames", "init_metrics")


# ----------------------------------------------------------------------------- config
def _schema() -> DictConfig:
    """The job's defaults (:class:`training.schema.TrainFramesConfig`) as a plain ``DictConfig``."""
    return OmegaConf.create(schema.defaults(schema.TrainFramesConfig))


def load_config(overrides: list[str] | None = None) -> DictConfig:
    """Compose ``configs/train_frames.yaml`` (the schema :class:`training.schema.TrainFramesConfig`
    from Hydra's ConfigStore and Hydra's settings) with Hydra overrides (struct mode), without running.

    Unknown keys raise (Hydra's ``ConfigCompositionException``).
    """
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name="train_frames", overrides=list(overrides or []))


def _validate(cfg) -> DictConfig:
    """Merge ``cfg`` onto the defaults in struct mode (unknown keys raise ``ConfigKeyError``), then
    check every value's type and range (:class:`training.schema.TrainFramesConfig`, :class:`ConfigError`)."""
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


# ----------------------------------------------------------------------------- helpers
def _fingerprint(cfg, mesh) -> str:
    """Hash of what a resumed run must share with the checkpoint (mesh, method, optimizer)."""
    h = hashlib.sha256()
    h.update(mesh.vertices.detach().cpu().double().numpy().tobytes())
    h.update(mesh.tets.cpu().numpy().tobytes())
    keys = ["method", "formulation", "optim", "dtype", "feature_angle_deg", "smooth_power", "smooth_eps",
            "align_kind", "align_eps", "lr", "lr_schedule", "steps", "starts", "map_weight"]
    h.update(repr([(k, cfg[k]) for k in keys]).encode())
    h.update(repr(OmegaConf.to_container(cfg.weights)).encode())
    h.update(repr(OmegaConf.to_container(cfg.lbfgs)).encode())
    return h.hexdigest()


def _save_outputs(out: Path, result: FrameFieldResult, metrics: dict) -> None:
    with io_utils.staged_outputs(out) as stage:  # a failing writer leaves no partial output
        _write_outputs(stage, result, metrics)


def _write_outputs(out: Path, result: FrameFieldResult, metrics: dict) -> None:
    mesh, frames = result.mesh, result.vertex_frames
    sing_faces = mesh.faces[result.singular_faces]
    io_utils.atomic_savez(out / "frames.npz", vertices=mesh.vertices.detach().cpu().double().numpy(),
                          tets=mesh.tets.cpu().numpy().astype(np.int64),
                          frames=frames.detach().cpu().double().numpy(),
                          singular_faces=sing_faces.cpu().numpy().astype(np.int64).reshape(-1, 3))
    io_utils.atomic_write_json(out / "metrics.json", metrics)
    field_files.write_frames_vtu(out / "frames.vtu", mesh, frames, result.tet_frames)
    field_files.write_fra(out / "frames.fra", result.tet_frames, mesh)
    field_files.write_singular_faces_vtu(out / "singular_faces.vtu", mesh, sing_faces)
    field_files.write_singular_curves_vtk(out / "singular_curves.vtu", result.singular_graph)
    frame_plots.plot_loss(out / "loss.png", result.history, result.histories, result.metrics.get("chosen"))
    frame_plots.plot_singularities(out / "singularities.png", mesh, result.singular_graph)
    hx = getattr(result, "hex", None)  # select=hex: the chosen field's hex stage, made while choosing
    if hx is not None:
        m = hx.map
        io_utils.atomic_savez(out / "map_frames.npz", vertices=m.mesh.vertices.detach().cpu().double().numpy(),
                              tets=m.mesh.tets.cpu().numpy().astype(np.int64),
                              frames=m.tet_frames.detach().cpu().double().numpy())


# ----------------------------------------------------------------------------- train
def design_options(cfg) -> dict:
    """The :func:`torchconn.frames.design` options of ``cfg``'s method (plain Python values); the
    connection method's ``weights`` gain ``map`` = ``cfg.map_weight`` (the hex stage's term that
    :func:`torchconn.hexmesh.choose.design_for_hex` injects)."""
    out = {k: OmegaConf.to_container(cfg[k], resolve=True) if OmegaConf.is_config(cfg[k]) else cfg[k]
           for k in method_options(cfg.method)}
    if "weights" in out and "map_weight" in cfg:
        out["weights"] = {**out["weights"], "map": float(cfg.map_weight)}
    return out


def train(cfg) -> dict:
    """Run the frame-field optimization described by ``cfg``; return the metrics dict.

    ``config -> torchconn.frames.design(mesh, **design_options(cfg)) -> writers`` plus the
    checkpoint (``design``'s ``on_checkpoint`` state with the configuration's fingerprint) and
    ``resume`` (``design(state=checkpoint)``).

    Args:
        cfg: a ``DictConfig`` or dict with the keys of :class:`training.schema.TrainFramesConfig` (missing
            keys take the defaults; unknown keys raise). ``output_dir`` must be set.

    Returns:
        The dict written to ``metrics.json`` (``final`` and ``init`` frame metrics, loss
        history, invariants, timings).
    """
    t_start = time.perf_counter()
    cfg = _validate(cfg)  # types and ranges of every key (ConfigError), before anything is created
    if cfg.output_dir is None:
        raise ConfigError("output_dir is null: train() needs the directory its outputs go to "
                          "(the command line job defaults it to outputs/train_frames/<date>/<time>)")
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
    np.random.seed(int(cfg.seed))  # design() seeds torch

    mesh = _load_mesh(cfg, dtype, device)
    fp = _fingerprint(cfg, mesh)
    ckpt = None
    if cfg.resume:
        ckpt = io_utils.load_checkpoint(ckpt_path, map_location=device, fingerprint=fp, required=CHECKPOINT_KEYS)
    config = OmegaConf.to_container(cfg, resolve=True)

    def on_checkpoint(state: dict) -> None:
        io_utils.save_checkpoint(ckpt_path, {**state, "fingerprint": fp, "config": config})

    connection = cfg.method == "connection"
    from torchconn.hexmesh.choose import design_for_hex

    result = design_for_hex(mesh, cfg.method, select=str(cfg.select), select_candidates=int(cfg.select_candidates),
                            progress=bool(cfg.progress), seed=int(cfg.seed), state=ckpt if connection else None,
                            on_checkpoint=on_checkpoint if connection else None,
                            checkpoint_every=int(cfg.checkpoint_every), **design_options(cfg))
    m = result.metrics
    from torchconn.hexmesh.meshability import meshability_report
    from torchconn.hexmesh.straighten import straighten_singular_edges

    # LMFF's local conditions on the edge-based singular graph the map will see: with the best
    # face matchings, and after the hex stage's repair search over them
    tf = result.tet_frames.detach().cpu().double()
    fm, _ = straighten_singular_edges(mesh.to(device="cpu", dtype=torch.float64), tf, boundary_moves=True)
    meshability = {"field": meshability_report(mesh.to(device="cpu", dtype=torch.float64), tf).counts(),
                   "after_search": meshability_report(mesh.to(device="cpu", dtype=torch.float64), tf, fm).counts()}
    metrics = {
        **m,
        "meshability": meshability,
        "mesh": {"source": str(cfg.mesh), **m["mesh"]},
        "method": cfg.method,
        "loss_history": result.history,
        "timings": {**result.timings, "wall_s": time.perf_counter() - t_start,
                    "num_threads": torch.get_num_threads()},  # after num_threads=auto was resolved
        "config": config,
    }
    assert set(METRIC_KEYS) <= set(m["final"])
    _save_outputs(out, result, metrics)
    if not m["invariants"]["bianchi_ok"]:
        raise bianchi.BianchiError(m["invariants"]["bianchi_error"])
    return metrics


def main() -> None:
    """Console entry point ``torchconn-frames``: Hydra composes ``configs/train_frames.yaml`` + overrides."""
    import hydra

    @hydra.main(config_path="../configs", config_name="train_frames", version_base="1.3")
    def app(cfg: DictConfig) -> None:
        with io_utils.report_errors("train_frames"):  # the message, not a traceback (unless HYDRA_FULL_ERROR=1)
            with io_utils.hydra_output_dir(cfg):
                m = train(cfg)
        f, i = m["final"], m["init"]
        print(f"[train_frames] {cfg.method}: smoothness {i['smoothness_mean_deg']:.2f} -> "
              f"{f['smoothness_mean_deg']:.2f} deg, alignment mean {f['alignment_mean_deg']:.3f} deg, "
              f"singular faces {f['n_singular_faces']} ({f['n_singular_faces_quarter']} quarter turns: "
              f"{f['n_singular_faces_valence3']} valence 3, {f['n_singular_faces_valence5']} valence 5; "
              f"{f['n_singular_faces_half']} half, {f['n_singular_faces_complex']} complex), "
              f"{f['n_singular_curves']} curves (valid fraction {f['singular_valid_fraction']:.3f}, "
              f"{f['n_singular_junctions']} junctions, {f['n_curves_ending_inside']} ending inside), "
              f"wall {m['timings']['wall_s']:.1f} s, output {cfg.output_dir}")
        c = m.get("chosen")
        if c:
            print(f"[train_frames] returned field: {c['label']} (the connection optimization from the {c['start']} "
                  f"field" + (f", then its {c['kind']} quality path at lambda {c['dirichlet_weight']:g}"
                              if c['dirichlet_weight'] is not None else f", {c['kind']}") + f"), chosen by {c['by']}: "
                  f"{c['reason']}, of {len(c['candidates'])} candidates")

    app()


if __name__ == "__main__":
    main()
