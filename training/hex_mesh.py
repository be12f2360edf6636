"""``hex_mesh``: a hexahedral mesh from a frame field (``torchconn-hex``).

A thin command over :func:`torchconn.hexmesh.hex_mesh`: config -> the frame field (the frame
job's method and options, or ``frames=PATH``) -> the integer-grid map, its validity report, the
hex extraction and the hex mesh's quality -> files.

Outputs in ``output_dir``:

* ``igm.hexex``: the final map in libHexEx's format (the tet mesh the map lives on: the input's
  own vertices first, in their order, then the midpoints of the edges the map split; per tet
  its 4 corners' parameters, in units of the hex edge length);
* ``hex.vtu`` and ``hex.mesh``: the hexahedra (VTK order, positively oriented), when any;
* ``hex_metrics.json``: the map's validity (``map.valid``, ``map.reasons``: which check fails and
  where), its figures (energy, integers, singular edges, splits, timings), the extraction's
  counts (hexes, cubes dropped and why), the hex quality (scaled Jacobian min/mean, irregular
  interior edges, Hausdorff distance, volume ratio, CAD corners and curves meshed, ``valid``,
  ``good``), the field's metrics and the times;
* ``hex.png``: the hex mesh's boundary and its singular (irregular) edges;
* ``frames.npz`` (vertices, tets, frames): the field, reusable with ``frames=`` (and by
  ``resume=true``, which skips the field's computation when the file is there).

An invalid map is a result, not an error: the job exits 0 and writes the map, the report and the
hex mesh extracted where the map allows it. Bad input stops before anything is written, with an
error that names the problem: an unknown or mistyped key (``ConfigError``), a frames file that is
unreadable, has no ``frames`` array or belongs to another mesh, a non-positive ``hex.edge_length``,
an unreadable or invalid mesh. The outputs appear together (staged, ``hex_metrics.json`` last).

Usage::

    torchconn-hex mesh=part.step                       # or: python -m training.hex_mesh
    python -m training.hex_mesh mesh=../shared/data/hexme/meta/s02c_prism.yaml method=sh_baseline
    python -m training.hex_mesh mesh=m.mesh frames=outputs/train_frames/.../frames.npz hex.edge_length=0.1
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from . import config_check, io_utils
from .train_frames import _load_mesh, design_options

__all__ = ["run", "main", "load_config", "FramesFileError", "CONFIG_DIR"]

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


class FramesFileError(ValueError):
    """A ``frames=`` file that cannot be read or does not fit the mesh."""


def _schema() -> DictConfig:
    """The frame job's keys overlaid with this job's (the files themselves, without Hydra)."""
    parts = []
    for name in ("train_frames.yaml", "hex_mesh.yaml"):
        c = OmegaConf.load(CONFIG_DIR / name)
        c.pop("hydra", None)
        c.pop("defaults", None)
        parts.append(c)
    return OmegaConf.merge(*parts)


def load_config(overrides: list[str] | None = None) -> DictConfig:
    """Compose ``configs/hex_mesh.yaml`` with Hydra overrides (struct mode), without running."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name="hex_mesh", overrides=list(overrides or []))


def _validate(cfg) -> DictConfig:
    schema = _schema()
    OmegaConf.set_struct(schema, True)
    user = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)
    user = OmegaConf.masked_copy(user, [k for k in user.keys() if k != "hydra"]) if "hydra" in user else user
    if "output_dir" not in user or OmegaConf.is_missing(user, "output_dir"):
        raise config_check.ConfigError("output_dir must be set")
    merged = OmegaConf.merge(schema, user)  # raises ConfigKeyError on unknown keys
    config_check.check_config(merged, config_check.HEX_MESH, "configs/hex_mesh.yaml")
    return merged


def read_frames_file(path, mesh) -> np.ndarray:
    """The ``(V, 3, 3)`` frames of a ``frames.npz`` written for ``mesh`` (checked: same vertices
    and tets, finite rotations). Raises :class:`FramesFileError` naming the file and the problem."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise FramesFileError(f"frames={str(path)!r}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same error for the user
        raise FramesFileError(f"frames={str(path)!r}: not a readable .npz file ({type(exc).__name__}: {exc})") from exc
    if "frames" not in data:
        raise FramesFileError(f"frames={str(path)!r}: no 'frames' array (keys: {sorted(data)})")
    F = np.asarray(data["frames"])
    V, T = mesh.n_vertices, mesh.n_tets
    if F.ndim != 3 or F.shape[1:] != (3, 3) or F.shape[0] not in (V, T):
        raise FramesFileError(f"frames={str(path)!r}: 'frames' has shape {F.shape}, but this mesh needs ({V}, 3, 3) "
                              f"per vertex or ({T}, 3, 3) per tet: the field is for another mesh")
    if "vertices" in data and "tets" in data:
        vx, tt = np.asarray(data["vertices"]), np.asarray(data["tets"])
        same = (vx.shape == (V, 3) and tt.shape == (T, 4)
                and np.array_equal(tt, mesh.tets.cpu().numpy())
                and np.allclose(vx, mesh.vertices.detach().cpu().double().numpy(), rtol=0, atol=1e-9))
        if not same:
            raise FramesFileError(f"frames={str(path)!r}: the file's mesh ({vx.shape[0]} vertices, {tt.shape[0]} tets) "
                                  f"is not this mesh ({V} vertices, {T} tets): the field is for another mesh")
    if not np.isfinite(F).all():
        raise FramesFileError(f"frames={str(path)!r}: 'frames' has non-finite entries")
    return F.astype(np.float64)


def _field(cfg, mesh, out: Path):
    """``(frames or FrameFieldResult, field summary, frames (V,3,3) to save or None)``."""
    if cfg.frames is not None:
        F = read_frames_file(cfg.frames, mesh)
        return torch.as_tensor(F), {"source": str(cfg.frames)}, None
    cached = out / "frames.npz"
    if cfg.resume and cached.is_file():
        F = read_frames_file(cached, mesh)
        return torch.as_tensor(F), {"source": str(cached), "resumed": True}, None
    t0 = time.perf_counter()
    if cfg.method == "mbo":
        from torchconn.frames.mbo import mbo_frames

        F = mbo_frames(mesh)
        summary = {"method": "mbo"}
    else:
        from torchconn.hexmesh.field import design_for_hex

        res = design_for_hex(mesh, cfg.method, select=str(cfg.select), select_candidates=int(cfg.select_candidates),
                             hex_options=OmegaConf.to_container(cfg.hex, resolve=True), progress=bool(cfg.progress),
                             seed=int(cfg.seed), **design_options(cfg))
        F = res.vertex_frames
        summary = {"method": cfg.method, "final": res.metrics.get("final"), "chosen": res.metrics.get("chosen")}
    summary["seconds"] = time.perf_counter() - t0
    F = F.detach().cpu().double()
    return F, summary, F.numpy()


def run(cfg) -> dict:
    """Run the hex job described by ``cfg``; return the dict written to ``hex_metrics.json``."""
    t_start = time.perf_counter()
    cfg = _validate(cfg)
    out = io_utils.check_output_dir(cfg.output_dir)
    with io_utils.lock_output_dir(out):
        threads = config_check.resolve_num_threads(cfg.num_threads)
        if threads is not None:
            torch.set_num_threads(threads)
        np.random.seed(int(cfg.seed))
        mesh = _load_mesh(cfg, torch.float64, torch.device("cpu"))
        frames, field_summary, to_save = _field(cfg, mesh, out)
        from torchconn.hexmesh import hex_mesh

        opts = OmegaConf.to_container(cfg.hex, resolve=True)
        result = hex_mesh(mesh, frames, progress=bool(cfg.progress), **opts)
        metrics = result.metrics()
        metrics["field"] = field_summary
        metrics["mesh"] = {"source": str(cfg.mesh), "vertices": mesh.n_vertices, "tets": mesh.n_tets}
        metrics["timings"]["wall_s"] = time.perf_counter() - t_start
        metrics["config"] = OmegaConf.to_container(cfg, resolve=True)
        _save(out, mesh, result, metrics, to_save)
    return metrics


def _save(out: Path, mesh, result, metrics: dict, frames) -> None:
    from torchconn.hexmesh.io import plot_hex_mesh, write_hex_mesh, write_hexex

    with io_utils.staged_outputs(out, last=("hex_metrics.json",)) as stage:
        m = result.map
        if frames is not None:
            io_utils.atomic_savez(stage / "frames.npz", vertices=mesh.vertices.detach().cpu().double().numpy(),
                                  tets=mesh.tets.cpu().numpy().astype(np.int64), frames=frames)
        write_hexex(stage / "igm.hexex", m.mesh.vertices.detach().cpu().double().numpy(),
                    m.mesh.tets.cpu().numpy(), m.uvw)
        if result.hexes.shape[0]:
            write_hex_mesh(stage / "hex.vtu", result.points, result.hexes)
            write_hex_mesh(stage / "hex.mesh", result.points, result.hexes)
            plot_hex_mesh(stage / "hex.png", result.points, result.hexes, result.quality,
                          title=_title(metrics))
        io_utils.atomic_write_json(stage / "hex_metrics.json", metrics)


def _title(metrics: dict) -> str:
    q = metrics.get("quality") or {}
    return (f"{'valid' if metrics['map']['valid'] else 'invalid'} map, {q.get('n_hexes', 0)} hexes, "
            f"scaled Jacobian min {q.get('sj_min', float('nan')):.2f}")


def summary_line(metrics: dict, output_dir) -> str:
    """The console summary of a run."""
    mp, q, ex = metrics["map"], metrics.get("quality") or {}, metrics.get("extraction") or {}
    why = "" if mp["valid"] else " (" + "; ".join(mp["reasons"]) + ")"
    return (f"[hex_mesh] map {'valid' if mp['valid'] else 'INVALID'}{why}; {ex.get('hexes', 0)} hexes "
            f"({ex.get('cubes_dropped', 0)} cubes dropped), scaled Jacobian min {q.get('sj_min', float('nan')):.3f} "
            f"mean {q.get('sj_mean', float('nan')):.3f}, irregular interior edges "
            f"{100 * (q.get('irregular_fraction') or 0):.1f}%, Hausdorff {100 * (q.get('hausdorff_rel') or 0):.2f}% "
            f"of the diagonal, good hex mesh: {metrics['good']}; wall {metrics['timings']['wall_s']:.1f} s, "
            f"output {output_dir}")


def main() -> None:
    """Console entry point ``torchconn-hex``: Hydra composes ``configs/hex_mesh.yaml`` + overrides."""
    import hydra

    @hydra.main(config_path="../configs", config_name="hex_mesh", version_base="1.3")
    def app(cfg: DictConfig) -> None:
        m = run(cfg)
        print(summary_line(m, cfg.output_dir))

    app()


if __name__ == "__main__":
    main()
