"""``hex_mesh``: a hexahedral mesh from a frame field (``torchconn-hex``).

A thin command over :func:`torchconn.hexmesh.hex_mesh`: config -> the frame field (the frame
job's method and options, or ``frames=PATH``) -> the integer-grid map, its validity report, the
hex extraction and the hex mesh's quality -> files.

Outputs in ``output_dir``:

* ``seamless.hexex``: the seamless map before quantization, in the same format and on the same tet
  mesh as ``igm.hexex`` (its translations real, its parameters on the ``2**-grid_bits`` grid);
* ``igm.hexex``: the final map in libHexEx's format (the tet mesh the map lives on: the input's
  own vertices first, in their order, then the midpoints of the edges the map split; per tet
  its 4 corners' parameters, in units of the hex edge length);
* ``hex.vtu`` and ``hex.mesh``: the hexahedra (VTK order, positively oriented), when any;
* ``hex_metrics.json``: the ``verdict`` (:func:`torchconn.hexmesh.report.verdict`: ``good``,
  ``status``, ``reasons``, ``text``; ``good`` repeats its ``good``), the ``gates`` (structure,
  seamless map, quantization, extraction: ``passed``, ``reasons``, ``counts``, ``where``) and
  ``first_failed`` (the first stage that fails), the map's validity
  (``map.valid``, ``map.reasons``: which check fails and where), its figures (energy, integers,
  singular edges, splits, the image's volume in unit cubes, timings), the extraction's counts
  (hexes, cubes dropped and why, oversized tets), the hex quality (scaled Jacobian min/mean,
  irregular interior edges, Hausdorff distance, volume ratio, CAD corners and curves meshed,
  ``valid``, ``good``; ``null`` without hexes), the field's metrics and the times;
* ``hex.png``: the hex mesh's boundary and its singular (irregular) edges, the verdict as subtitle;
* after an invalid map, what shows the failure: ``map_failure.vtu`` (the input tets with their
  flags: inverted, degenerate, on a complex singular edge, oversized, cubes dropped, counted over
  their sub-tets in the map's refined mesh; the singular graph as line cells) and
  ``map_failure.png`` (the input's boundary with the flagged tets and the singular graph);
* ``frames.npz`` (vertices, tets, frames): the field, reusable with ``frames=`` (and by
  ``resume=true``, which skips the field's computation when the file is there);
* ``map_frames.npz`` (vertices, tets, frames per tet): the field the map follows, on the map's tet
  mesh (``igm.hexex``'s): the field's frames with the structure stage's matchings, re-optimized
  with those fixed where the stage changed them and its gate passed (``hex.fixed_holonomy``): its
  own singular graph is then the repaired one.

The console prints the verdict (``good hex mesh``, ``not a good hex mesh: <reasons>``, or ``no hex
mesh: <reasons>``: the invalid map, an edge length too small or too large for the mesh, every cube
dropped) and the figures that exist. An invalid map is a result, not an error: the job exits 0
and writes the map, the report and the hex mesh extracted where the map allows it. Bad input
stops with a message that names the problem (and exit status 1; the traceback only with
``debug=true`` or ``HYDRA_FULL_ERROR=1``): an unknown or mistyped key (``ConfigError``), a frames
file that is not an ``.npz``, has no ``frames`` array, has another shape than the mesh's (both
named) or belongs to another mesh, holds NaN/inf or frames that are not rotations (how many per
vertex or tet, reflections named as such), a non-positive or absurdly small ``hex.edge_length``,
an unreadable or invalid mesh. An input error leaves no output directory behind; with
``output_dir`` given nothing is written under the working directory (``configs/hex_mesh.yaml``'s
``hydra`` section). The outputs appear together (staged, ``hex_metrics.json`` last).

Usage::

    torchconn-hex mesh=part.step                       # or: python -m training.hex_mesh
    python -m training.hex_mesh mesh=../shared/data/hexme/meta/s02c_prism.yaml method=sh_baseline
    python -m training.hex_mesh mesh=m.mesh frames=outputs/train_frames/.../frames.npz hex.edge_length=0.1
"""
from __future__ import annotations

import time
import zipfile
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from . import config_check, io_utils, schema
from .train_frames import _load_mesh, design_options

__all__ = ["run", "main", "load_config", "read_frames_file", "summary_line", "FramesFileError", "CONFIG_DIR", "SCHEMA"]

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
#: The checks of this job's keys, generated from :class:`training.schema.HexMeshConfig`.
SCHEMA = config_check.HEX_MESH


class FramesFileError(ValueError):
    """A ``frames=`` file that cannot be read or does not fit the mesh."""


def _schema() -> DictConfig:
    """The job's defaults (:class:`training.schema.HexMeshConfig`) as a plain ``DictConfig``."""
    return OmegaConf.create(schema.defaults(schema.HexMeshConfig))


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
    if "output_dir" not in user or OmegaConf.is_missing(user, "output_dir") or user.output_dir is None:
        raise config_check.ConfigError("output_dir must be set")
    merged = OmegaConf.merge(schema, user)  # raises ConfigKeyError on unknown keys
    config_check.check_config(merged, SCHEMA, "configs/hex_mesh.yaml")
    return merged


_NPZ_HOW = "an .npz file (a zip of numpy arrays, as np.savez writes) with a 'frames' array"


def _not_npz(path: Path) -> str | None:
    """Why ``path`` is not an ``.npz`` file, or ``None`` (read from its first bytes)."""
    with open(path, "rb") as f:
        head = f.read(6)
    if head.startswith(b"\x93NUMPY"):
        return f"a .npy file (one array), not {_NPZ_HOW}: np.savez(path, frames=frames)"
    if not zipfile.is_zipfile(path):
        kind = "an empty file" if not head else "not a zip archive"
        return f"not an .npz file ({kind}); expected {_NPZ_HOW}"
    return None


def read_frames_file(path, mesh) -> np.ndarray:
    """The ``(V, 3, 3)`` or ``(T, 3, 3)`` frames of a ``frames.npz`` written for ``mesh``, checked:
    an ``.npz`` (never unpickled) with a ``frames`` array of the mesh's shape, of the same mesh
    (when it stores ``vertices`` and ``tets``), finite and rotations
    (:func:`torchconn.hexmesh.inputs.frames_defects`). Raises :class:`FramesFileError` naming the
    file and the problem."""
    from torchconn.hexmesh.inputs import frames_defects

    path = Path(path).expanduser()
    where = f"frames={str(path)!r}"
    if not path.is_file():
        raise FramesFileError(f"{where}: no such file")
    why = _not_npz(path)
    if why is not None:
        raise FramesFileError(f"{where}: {why}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - any unreadable array is the same error for the user
        detail = "an array of Python objects (not loaded: that would unpickle)" if "pickle" in str(exc) else (
            f"{type(exc).__name__}: {exc}")
        raise FramesFileError(f"{where}: an unreadable .npz file: {detail}") from None
    if "frames" not in data:
        raise FramesFileError(f"{where}: no 'frames' array (keys: {sorted(data)})")
    F = np.asarray(data["frames"])
    V, T = mesh.n_vertices, mesh.n_tets
    if F.ndim != 3 or F.shape[1:] != (3, 3) or F.shape[0] not in (V, T):
        _, problem = frames_defects(F, mesh)
        raise FramesFileError(f"{where}: {problem}")
    if "vertices" in data and "tets" in data:
        vx, tt = np.asarray(data["vertices"]), np.asarray(data["tets"])
        same = (vx.shape == (V, 3) and tt.shape == (T, 4)
                and np.array_equal(tt, mesh.tets.cpu().numpy())
                and np.allclose(vx, mesh.vertices.detach().cpu().double().numpy(), rtol=0, atol=1e-9))
        if not same:
            raise FramesFileError(f"{where}: the file's mesh ({vx.shape[0]} vertices, {tt.shape[0]} tets) "
                                  f"is not this mesh ({V} vertices, {T} tets): the field is for another mesh")
    if not np.issubdtype(F.dtype, np.number) or np.issubdtype(F.dtype, np.complexfloating):
        raise FramesFileError(f"{where}: 'frames' must hold real numbers, got dtype {F.dtype}")
    _, problem = frames_defects(F.astype(np.float64), mesh)
    if problem is not None:
        raise FramesFileError(f"{where}: {problem}")
    return F.astype(np.float64)


def _field(cfg, mesh, out: Path):
    """``(frames, field summary, frames (V,3,3) to save or None, the chooser's HexMeshResult of
    these frames or None)``."""
    if cfg.frames is not None:
        F = read_frames_file(cfg.frames, mesh)
        return torch.as_tensor(F), {"source": str(cfg.frames)}, None, None
    cached = out / "frames.npz"
    if cfg.resume and cached.is_file():
        F = read_frames_file(cached, mesh)
        return torch.as_tensor(F), {"source": str(cached), "resumed": True}, None, None
    t0 = time.perf_counter()
    made = None
    if cfg.method == "mbo":
        from torchconn.frames.mbo import mbo_frames

        F = mbo_frames(mesh)
        summary = {"method": "mbo"}
    else:
        from torchconn.hexmesh.choose import design_for_hex

        res = design_for_hex(mesh, cfg.method, select=str(cfg.select), select_candidates=int(cfg.select_candidates),
                             hex_options=OmegaConf.to_container(cfg.hex, resolve=True), progress=bool(cfg.progress),
                             seed=int(cfg.seed), **design_options(cfg))
        F = res.vertex_frames
        made = res.hex
        summary = {"method": cfg.method, "final": res.metrics.get("final"), "chosen": res.metrics.get("chosen")}
    summary["seconds"] = time.perf_counter() - t0
    F = F.detach().cpu().double()
    return F, summary, F.numpy(), made


def run(cfg) -> dict:
    """Run the hex job described by ``cfg``; return the dict written to ``hex_metrics.json``."""
    t_start = time.perf_counter()
    cfg = _validate(cfg)
    with io_utils.output_dir_for_run(cfg.output_dir) as out:  # an input error leaves no directory
        threads = config_check.resolve_num_threads(cfg.num_threads)
        if threads is not None:
            torch.set_num_threads(threads)
        np.random.seed(int(cfg.seed))
        mesh = _load_mesh(cfg, torch.float64, torch.device("cpu"))
        frames, field_summary, to_save, made = _field(cfg, mesh, out)
        from torchconn.hexmesh import hex_mesh

        opts = OmegaConf.to_container(cfg.hex, resolve=True)
        # the chooser meshed the chosen field with these options already: not again
        result = made if made is not None else hex_mesh(mesh, frames, progress=bool(cfg.progress), **opts)
        field_summary["hex_mesh_from_chooser"] = made is not None
        metrics = result.metrics()
        metrics["field"] = field_summary
        metrics["mesh"] = {"source": str(cfg.mesh), "vertices": mesh.n_vertices, "tets": mesh.n_tets}
        metrics["timings"]["wall_s"] = time.perf_counter() - t_start
        metrics["config"] = OmegaConf.to_container(cfg, resolve=True)
        _save(out, mesh, result, metrics, to_save)
    return metrics


def _save(out: Path, mesh, result, metrics: dict, frames) -> None:
    from torchconn.hexmesh.io import plot_failure, plot_hex_mesh, write_failure_vtu, write_hex_mesh, write_hexex

    text = metrics["verdict"]["text"]
    with io_utils.staged_outputs(out, last=("hex_metrics.json",)) as stage:
        m = result.map
        if frames is not None:
            io_utils.atomic_savez(stage / "frames.npz", vertices=mesh.vertices.detach().cpu().double().numpy(),
                                  tets=mesh.tets.cpu().numpy().astype(np.int64), frames=frames)
        X, tets = m.mesh.vertices.detach().cpu().double().numpy(), m.mesh.tets.cpu().numpy()
        io_utils.atomic_savez(stage / "map_frames.npz", vertices=X, tets=tets.astype(np.int64),
                              frames=m.tet_frames.detach().cpu().double().numpy())
        write_hexex(stage / "seamless.hexex", X, tets, m.seamless_uvw)
        write_hexex(stage / "igm.hexex", X, tets, m.uvw)
        if result.hexes.shape[0]:
            write_hex_mesh(stage / "hex.vtu", result.points, result.hexes)
            write_hex_mesh(stage / "hex.mesh", result.points, result.hexes)
            plot_hex_mesh(stage / "hex.png", result.points, result.hexes, result.quality,
                          title=_title(metrics), verdict=text)
        if not result.validity.valid:
            write_failure_vtu(stage / "map_failure.vtu", mesh, m, result.extraction)
            plot_failure(stage / "map_failure.png", mesh, m, result.extraction, verdict_text=text,
                         title=_title(metrics), where_xyz=result.validity.where_xyz)
        io_utils.atomic_write_json(stage / "hex_metrics.json", metrics)


def _title(metrics: dict) -> str:
    """The pictures' first line: the mesh, the field and the edge length."""
    field = metrics.get("field") or {}
    src = field.get("method") or Path(str(field.get("source", "?"))).name
    return (f"{Path(str(metrics['mesh']['source'])).name} ({metrics['mesh']['tets']} tets), field {src}, "
            f"hex edge length {metrics['map']['edge_length']:.3g}")


def summary_line(metrics: dict, output_dir) -> str:
    """The console summary of a run: the verdict (:func:`torchconn.hexmesh.report.summary`), the
    figures that exist, the wall time and the output directory."""
    from torchconn.hexmesh.report import summary

    verdict, figures = summary(metrics)
    return (f"[hex_mesh] {verdict}\n[hex_mesh] {figures}; wall {metrics['timings']['wall_s']:.1f} s, "
            f"output {output_dir}")


def main() -> None:
    """Console entry point ``torchconn-hex``: Hydra composes ``configs/hex_mesh.yaml`` + overrides.

    Errors are printed as a message (exit status 1), the traceback only with ``debug=true`` or
    ``HYDRA_FULL_ERROR=1`` (:func:`training.io_utils.report_errors`)."""
    import hydra

    @hydra.main(config_path="../configs", config_name="hex_mesh", version_base="1.3")
    def app(cfg: DictConfig) -> None:
        debug = OmegaConf.select(cfg, "debug", default=False) is True
        with io_utils.report_errors("hex_mesh", debug=debug, how="debug=true or HYDRA_FULL_ERROR=1"):
            with io_utils.hydra_output_dir(cfg):
                m = run(cfg)
        print(summary_line(m, cfg.output_dir))

    app()


if __name__ == "__main__":
    main()
