"""Octahedral frame fields on tet meshes from a differentiable connection.

Usage::

    python -m training.train_frames                                  # built-in cylinder
    python -m training.train_frames mesh=../shared/data/sphere_r0.17.mesh steps=300
    python -m training.train_frames mesh=bunny.obj edge_length=0.05 method=sh_baseline
    python -m training.train_frames optim=lbfgs weights.tie=5 output_dir=out/run1
    python -m training.train_frames optim=lbfgs weights.tie=5 output_dir=out/run1 resume=true  # after a crash
    python -m training.train_frames -m mesh=cylinder,torus weights.flat=0.1,1
    python -m training.train_frames mesh=../shared/data/fandisk.ply edge_length=0.2 polish.steps=0  # no polish

Method (``method=connection``; details in :mod:`torchconn.losses`):

1. Initialization: the spherical-harmonic baseline ``F^0`` (Ray, Sokolov, Lévy 2016;
   :func:`torchconn.frames.sh.sh_frame_field`), its axis labels combed along a BFS tree
   (:func:`torchconn.frames.propagate.comb_frames`), and the matched connection
   ``R_ij = F_i^T F_j h_ij`` with ``h_ij in O`` the relabeling that makes ``R_ij`` closest to
   ``I`` (``F_j h_ij ~ F_i``), so that ``F_i R_ij = F_j h_ij`` exactly.
2. Variables: the connection as per-edge skew parameters (:class:`ConnectionField`) and

   * ``formulation=vertex`` (default): per-vertex rotations ``F_i = exp(hat(w_i)) F_i^0``;
     at non-feature boundary vertices ``w_i = (w_i . n_i) n_i`` (rotation about the normal, so
     the aligned axis stays exactly on ``n_i``);
   * ``formulation=propagate``: one root rotation per connected component; all frames are
     the parallel propagation ``F_child = F_parent R_parent,child`` along a BFS tree
     (:mod:`torchconn.frames.propagate`).

3. Loss: ``smooth + tie + flat + torsion + align + feature`` (weights in the config;
   ``smooth`` and ``tie`` use ``rho = |x|^smooth_power``, default 1). ``align`` and ``feature``
   take the form ``align_kind``: ``angle`` (default; :func:`torchconn.frames.loss.axis_angle_loss`,
   the smoothed angle between a normal and the closest axis, i.e. what the alignment metrics
   average) or ``quartic`` (``1 - sum_k (F_k . n)^4``). At a feature vertex the incident face
   normals generally cannot all be matched by one frame (non-right dihedral angles, curved
   faces); the quartic penalty then settles at a least-squares compromise whose *mean* angle is
   larger: on ``78322_gear.2.mesh`` (150 steps) the feature alignment mean is 5.11 deg with
   ``quartic`` (also with ``weights.feature=50``), 4.88 deg with ``angle``; the per-vertex
   optimum of the metric, ignoring smoothness, is about 4.90 deg (8 random restarts per
   vertex), so ``angle`` sits at that floor. Smoothness is unchanged (3.96 deg; 151 vs 155
   singular faces). ``weights.feature`` (angle form) trades the feature fit against smoothness
   and singular faces; default 1 (gear: 3.92 deg, feature mean 4.93 deg, 151 singular faces;
   with 2: 3.96, 4.89, 151; with 10: 3.96, 4.88, 151). On the tetrahedralized ``bunny.obj``
   (edge length 0.08), whose faceted surface makes 496 spurious feature vertices, weights 1/2/3/10
   give 1634/1658/1667/1701 singular faces (SH 1654) and smoothness 7.47/7.51/7.53/7.57 deg.

Choice of formulation (measured on ``sphere_r0.17.mesh``, 150 Adam steps, cosine lr 0.02):
``vertex`` and ``propagate`` reach the same mean smoothness (11.18 vs 11.16 deg, SH 11.86), but
``propagate`` only gets boundary alignment by penalty (mean 0.44, max 0.95 deg; the first Adam
step moves every edge and the error accumulates along the tree depth), while ``vertex`` keeps
it exact by construction; hence ``vertex`` is the default. ``smooth_power=2`` (the Dirichlet
energy that the SH baseline already minimizes) does not improve on the SH field (11.97 deg);
``smooth_power=1`` does.

What does not move the mean smoothness further (measured on ``sphere_r0.17.mesh``, SH 11.86 deg,
default 11.18 deg; all converge to the same local minimum of the total-variation energy around
the SH field's singular structure): 300 steps (11.11, but 248 singular faces > SH's 245), ``lr``
0.01-0.05 (11.06-11.18, up to 255 singular faces), ``weights.tie`` 1.2-4 (11.08-11.31),
``weights.flat=1`` (11.26), L-BFGS (11.25-11.35), dropping ``flat`` and ``torsion`` (11.17; the
same result ~3x faster on the gear, 12 vs 36 s at 300 steps). Optimizing the frames alone with
the metric's own angle (smoothed, eps annealed 0.1 -> 0.001, up to 3000 Adam steps), a power
0.5 or 0.7, starting before or after the SH nonlinear smoothing, or from an SH field with
boundary weight 10/1000 or 200 smoothing iterations, all end at 10.74-11.10 deg; relaxing exact
boundary alignment only helps once the alignment mean exceeds 1 deg. The largest decrease seen
is thus about -9% (sphere), -10% (gear), far from -15%.

Both baselines and where the error sits (2026-11-21, 1 thread, busy 2-core machine; ``python -m
benchmarks.compare_frames --cases sphere,gear,bunny,fandisk --breakdown``; "connection" without
the polish of step 4, i.e. ``polish.steps=0``, "+ polish" the default). ``sh_linear`` is
``method=sh_baseline sh.n_smooth_iters=0`` (the L4 linear solve with the boundary constraint
and the projection, literally the issue's description of the baseline); ``sh_baseline`` adds
Ray's nonlinear smoothing (the default, and the initialization). Mean smoothness in degrees
(singular faces); alignment mean is 0.000 everywhere; no tet has exactly one singular face:

============  =============  =============  =============  =============  =============
mesh          sh_linear      sh_baseline    connection     + polish       vs SH / lin
============  =============  =============  =============  =============  =============
sphere_r0.17  17.957 (308)   11.859 (245)   11.178 (243)   11.178 (243)   -5.7 / -37.7%
gear          4.435 (207)    4.377 (152)    3.920 (151)    3.898 (150)    -11.0 / -12.1%
bunny 0.08    9.620 (2056)   7.970 (1654)   7.471 (1634)   7.471 (1634)   -6.3 / -22.3%
fandisk 0.2   3.134 (372)    3.043 (346)    2.779 (345)    2.705 (322)    -11.1 / -13.7%
============  =============  =============  =============  =============  =============

(the percentages are for "+ polish"). End to end with the polish, 1 thread on the busy
machine: sphere 2.4 s, gear 18.2 s, bunny 21.6 s, fandisk 23.6 s.

``metrics.json`` now holds ``edge_classes`` (:func:`torchconn.frames.metrics.edge_class_breakdown`:
edges touching a feature vertex, other boundary-surface edges, other edges touching the
boundary ("layer"), edges touching a singular-face vertex, 2 rings further, the rest). Gear
(51626 edges), mean angle per class for sh_baseline -> connection, with the share of the sum:
feature 7585 edges 6.17 -> 5.70 deg (21% of the sum), boundary surface 5848 2.55 -> 2.27 (7%),
layer 9737 5.00 -> 5.53 (27%), singular 1353/1364 11.10 -> 11.15 (8%), near singular
10533/10840 4.12 -> 3.74 (20%), interior 16570/16252 3.45 -> 2.23 (18%). The connection's
gain is in the interior and near the singular curves; the layer gets *worse* (total variation moves rotation into the layer next to
the boundary); the feature and surface classes (26% of the edges, 28% of the sum) are forced by
the geometry. Sphere and bunny alike (sphere: layer 17.3 -> 20.2, near singular 5.6 -> 2.8;
bunny: layer 11.5 -> 12.8, interior 3.2 -> 2.2); on the fandisk the layer improves too (3.36 ->
2.79, interior 2.32 -> 2.16, boundary surface 2.09 -> 1.97).

Bounds and ideas measured for the -15% target (commands reproduce the figures;
:mod:`studies.frame_studies` holds the study code):

* The gear is an extrusion: every field above has an axis on ``z`` (mean deviation 0.01 deg),
  so a frame is an in-plane angle and, with the period jumps (the singular structure) frozen,
  the minimum of "mean edge angle + lam * feature-alignment mean" over fields with an axis on
  ``z`` and exact side-wall alignment (alignment max 0.49 deg from the few near-vertical
  normals) is a linear program
  (``python -m studies.frame_studies planar_lp OUT/gear/connection/frames.npz --mesh
  78322_gear.2.mesh --lam L``). Its exact optimum for the connection's structure: lam=1: 3.892
  deg (feature 4.897); lam=0.5: 3.845 (4.963); lam=0.3: 3.820 (5.024, over the 5 deg target);
  lam=0: 3.717 (6.30). From the structures of sh_linear (207 faces) and sh_baseline (152):
  3.889 and 3.894 at lam=1 (sh_baseline's at lam=0.5: 3.845, as from the connection's). So with feature alignment <= 5 deg no field with these singular
  structures has a mean below ~3.84 (-12.2% vs 4.377); -15% (3.72) needs giving up feature
  alignment entirely (6.3 deg). The connection run sits ~0.05 deg above this frontier
  (``weights.feature`` 1 / 0.5 / 0.3: 3.920 / 3.881 / 3.860 deg with feature 4.93 / 5.01 / 5.09;
  ``steps=800 weights.flat=0 weights.torsion=0``: 3.88, 151 faces, ~44 s).
* (a) MBO diffusion-projection (Palmer, Bommes & Solomon 2020) as a refinement of the
  projected SH field before Ray's smoothing, ``sh.mbo_steps=20`` (tau 4 -> 0.05): sphere SH
  11.56 deg (250 faces), then connection 10.90 (-8.1% vs 11.86, but 249 > 245 faces); gear SH
  4.369 (149), connection 3.918 (148), +18-28 s of initialization. MBO alone without the
  smoothing: sphere 12.0-12.4, gear 4.33-4.34 for tau schedules 0.5-50 -> 0.02-0.5, 10-40
  rounds. Off by default: the connection then no longer starts from Ray's baseline (a
  different, smoother initialization), it adds singular faces on the sphere and nothing on
  the gear.
* (b) Frames only with the edge matchings frozen per round (Adam on the smoothed angle, 3
  rounds of 200 steps, re-matched between rounds; ``python -m studies.frame_studies
  fixmatch FRAMES.npz --mesh M``): sphere from SH or from the connection 10.92 deg but 258
  singular faces (> 245); 6 rounds of 500 steps 10.89 (254); gear from the connection 3.899
  (151 faces, feature 4.90) -- the LP bound above says that is essentially optimal.
* (c) A constant interior: one rotation at every interior vertex, snapped to the normal on the
  boundary (``python -m studies.frame_studies constint --mesh sphere_r0.17.mesh --out
  c.npy``; best of 16 rotations): sphere 10.65 deg, 244 faces; then ``init_frames=c.npy``
  (connection): 10.60 deg (-10.6%), 244 faces -- better than anything starting from the SH
  field, but degenerate (boundary-layer edges 31 deg mean, interior ~0.3; the singular curves
  hug the boundary) and it does not start from the SH baseline. On the gear (``R = I`` wins):
  3.708 deg (-15.3%), 113 singular faces, exact alignment -- but feature alignment 15.9 deg;
  the connection from it ends at 3.879 with feature 6.51 and 230 faces, and the LP for its
  structure at 3.809 with feature 6.40 (lam=1): that structure cannot carry the features.
  (Snapping the feature vertices too: 10.5 deg, 3175 faces.) The mean edge angle rewards
  concentrating the rotation in the boundary layer and giving up feature alignment; the
  total-variation loss already drifts that way.
* (c) ``smooth_eps`` 1e-4 / 1e-2: gear 3.92 / 3.94; ``lr`` 0.05 / 0.01 with 400 steps (no
  flat/torsion): 3.88 / 3.90.
* Frames-only descent of the metric with re-matching at every step from the connection result
  (what the polish of step 4 runs, unguarded, 600 steps): sphere 10.886 (254 faces), gear
  3.898 (148), bunny 6.987 (1698 > 1654; 7.388 with exactly 1654 at step 20 when checked every
  10 steps), fandisk 2.705 (322). With frozen matchings per round (``fixmatch``): fandisk 2.713
  (325), bunny 7.209 (1710). On the sphere the gain and the new singular faces come together:
  lr 0.002 / 0.0005 give 11.05 (251) / 11.13 (247) already at step 50; adding ``beta *
  mean angle^2`` to the polish objective (beta 0.5 / 2 / 5) keeps 247 / 242 / 242 faces but
  ends at 11.16 / 11.42 / 11.63 deg.

Judgment: against the smoothed SH baseline, -15% on the gear is not reachable with exact
boundary alignment and feature alignment <= 5 deg for the singular structures any of these
methods produce (LP bound -12.2%); on the sphere the best field found (-10.6%) is degenerate,
and on the sphere and the bunny every further decrease of the metric found adds singular faces.
Against the linear-only baseline the method (with the polish) is at -37.7% / -22.3% (sphere,
bunny) and -12.1% / -13.7% (gear, fandisk).

4. Polish (``polish.steps``, default 600; :mod:`torchconn.frames.polish`): Adam on the frames
   alone (about the normal at non-feature boundary vertices) with the smoothness metric's own
   smoothed edge angle, matchings re-chosen every step, plus ``weights.feature`` times the
   feature angle; guarded: of the checkpoints every ``polish.check_every`` steps (the input
   included) the best one with no more singular faces than the SH initialization and no tet
   with one singular face is kept. The returned connection is then the matched connection of
   the polished frames (``F_i R_ij = F_j h_ij`` exactly). Measured (``metrics.json`` ``polish``):
   gear 3.920 -> 3.898 deg (150 faces, feature 4.897, +11 s), fandisk 2.779 -> 2.705 (322
   faces, +14 s); on the sphere (257 faces at step 50 > 245) and the bunny (1694 > 1654) the
   guard keeps the unpolished field. The RMS angle grows (gear 6.71 -> 7.49, fandisk 5.53 ->
   5.88): the L1 metric concentrates rotation.
5. Invariants: the differential (and algebraic) Bianchi residuals of the optimized connection
   (:func:`torchconn.bianchi.check`, error above tolerance) and the count of tets with exactly
   one singular face; both in ``metrics.json``.

Outputs in ``output_dir``: ``frames.npz``, ``metrics.json``, ``frames.vtu``,
``singular_faces.vtu``, ``loss.png``, ``singularities.png``, ``checkpoint.pt`` (atomic, every
``checkpoint_every`` steps and at the end). ``resume=true`` continues an interrupted run from
the checkpoint and reaches the same result as an uninterrupted run (model, optimizer, lr
schedule, RNG state and step saved); the configuration must be the same (including ``steps``,
which fixes the cosine schedule), otherwise the resume is refused.

Bad input fails before any optimization: unknown config keys (struct mode), unknown
choices, an unwritable ``output_dir``, a mesh that cannot be read, is not closed/manifold or
has inverted/degenerate tets (:class:`torchconn.mesh.MeshError` with the indices). A NaN/inf
loss term stops the run with :class:`NonFiniteLossError` naming the term and the step; the
last good checkpoint is kept.
"""
from __future__ import annotations

import hashlib
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from torchconn import bianchi, io as tio, so3
from torchconn.frames import octahedral
from torchconn.nn import ConnectionField
from torchconn.frames.metrics import METRIC_KEYS, edge_class_breakdown, frame_metrics
from torchconn.frames.polish import polish_frames
from torchconn.frames.propagate import comb_frames, propagate_frames, spanning_tree
from torchconn.frames.sh import sh_frame_field
from torchconn.frames.loss import TERMS, FrameFieldLoss
from torchconn.mesh import MeshError

from . import io_utils

__all__ = ["train", "load_config", "FrameFieldModel", "NonFiniteLossError", "CONFIG_DIR", "BUILTIN_MESHES"]

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
BUILTIN_MESHES = ("box", "ball", "cylinder", "torus")
_CHOICES = {
    "method": ("connection", "sh_baseline"),
    "formulation": ("vertex", "propagate"),
    "optim": ("adam", "lbfgs"),
    "dtype": ("float32", "float64"),
    "lr_schedule": ("cosine", "constant"),
    "align_kind": ("quartic", "angle"),
}


class NonFiniteLossError(FloatingPointError):
    """A loss term became NaN/inf; the message names the term and the step."""


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
    """Merge ``cfg`` onto the schema in struct mode (unknown keys raise) and check the choices."""
    schema = _schema()
    OmegaConf.set_struct(schema, True)
    user = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)
    user = OmegaConf.masked_copy(user, [k for k in user.keys() if k != "hydra"]) if "hydra" in user else user
    merged = OmegaConf.merge(schema, user)  # raises ConfigKeyError on unknown keys
    for key, allowed in _CHOICES.items():
        if merged[key] not in allowed:
            raise ValueError(f"config {key}={merged[key]!r} is not one of {list(allowed)}")
    if int(merged.steps) < 0:
        raise ValueError(f"config steps must be >= 0, got {merged.steps}")
    if not float(merged.lr) > 0:
        raise ValueError(f"config lr must be > 0, got {merged.lr}")
    if int(merged.checkpoint_every) < 1:
        raise ValueError(f"config checkpoint_every must be >= 1, got {merged.checkpoint_every}")
    for k, w in merged.weights.items():
        if not (math.isfinite(float(w)) and float(w) >= 0):
            raise ValueError(f"config weights.{k} must be finite and >= 0, got {w}")
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


# ----------------------------------------------------------------------------- model
def matched_connection(frames: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``R_ij = F_i^T F_j h_ij (E, 3, 3)`` with ``h_ij = argmin_{h in O} ||F_j h - F_i||``.

    Then ``F_i R_ij = F_j h_ij`` exactly and ``R_ij`` is the residual rotation closest to ``I``.
    """
    Fi, Fj = frames[edges[:, 0]], frames[edges[:, 1]]
    _, h = octahedral.match(Fj, Fi)
    return Fi.transpose(-1, -2) @ Fj @ h


class FrameFieldModel(torch.nn.Module):
    """Connection (+ frames) parametrization; ``forward() -> (edge_rot (E,3,3), frames (V,3,3))``.

    Args:
        mesh: ``TetMesh``.
        init_frames: ``(V, 3, 3)`` initial frames ``F^0``.
        formulation: ``"vertex"`` or ``"propagate"`` (see the module docstring).
        constrained: ``(V,) bool`` vertices whose rotation is restricted to the axis
            ``normals[i]`` (``formulation="vertex"`` only).
        normals: ``(V, 3)`` unit axes for the constrained vertices.
    """

    def __init__(self, mesh, init_frames: torch.Tensor, formulation: str, constrained: torch.Tensor,
                 normals: torch.Tensor):
        super().__init__()
        self.formulation = formulation
        # comb the labels of the initial cross frames along a BFS tree: the matched connection
        # is then in one gauge on the tree (R_ij ~ I there), so that face holonomies are near I
        # on regular faces and near a non-identity element of O only around singular curves
        self.tree = spanning_tree(mesh)
        init_frames = comb_frames(init_frames, self.tree)
        R0 = matched_connection(init_frames, mesh.edges)
        self.connection = ConnectionField(mesh.edges, mesh.n_vertices, init=R0)
        self.register_buffer("F0", init_frames.detach().clone())
        if formulation == "vertex":
            self.w = torch.nn.Parameter(torch.zeros_like(init_frames[:, :, 0]))
            self.register_buffer("constrained", constrained.clone())
            self.register_buffer("normals", normals.clone())
        elif formulation == "propagate":
            self.w = torch.nn.Parameter(init_frames.new_zeros(self.tree.roots.numel(), 3))
        else:
            raise ValueError(f"unknown formulation {formulation!r}")

    def forward(self) -> tuple[torch.Tensor, torch.Tensor]:
        R = self.connection.edge_rotations()
        if self.formulation == "vertex":
            n = self.normals
            w = torch.where(self.constrained[:, None], (self.w * n).sum(-1, keepdim=True) * n, self.w)
            F = so3.exp(w) @ self.F0
        else:
            roots = self.tree.roots.to(self.F0.device)
            F = propagate_frames(R, self.tree, so3.exp(self.w) @ self.F0[roots])
        return R, F


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


def _check_finite_terms(terms: dict, step: int) -> None:
    for k, v in terms.items():
        if not bool(torch.isfinite(v).all()):
            raise NonFiniteLossError(
                f"loss term {k!r} is {float(v.detach())} at step {step}; stopping "
                f"(the last good checkpoint is kept)")


def _make_optimizer(cfg, params):
    if cfg.optim == "adam":
        opt = torch.optim.Adam(params, lr=float(cfg.lr))
    else:
        opt = torch.optim.LBFGS(params, lr=float(cfg.lr), history_size=int(cfg.lbfgs.history_size),
                                max_iter=int(cfg.lbfgs.max_iter), line_search_fn="strong_wolfe")
    steps = max(int(cfg.steps), 1)
    if cfg.lr_schedule == "cosine":  # lr -> 0 at the last step: Adam settles instead of jittering
        fn = lambda s: 0.5 * (1.0 + math.cos(math.pi * min(s, steps) / steps))  # noqa: E731
    else:
        fn = lambda s: 1.0  # noqa: E731
    return opt, torch.optim.lr_scheduler.LambdaLR(opt, fn)


def _save_outputs(out: Path, mesh, frames: torch.Tensor, sing_faces: torch.Tensor, history: dict,
                  metrics: dict) -> None:
    import meshio

    V = mesh.vertices.detach().cpu().double().numpy()
    T = mesh.tets.cpu().numpy().astype(np.int64)
    F = frames.detach().cpu().double().numpy()
    S = sing_faces.cpu().numpy().astype(np.int64).reshape(-1, 3)
    io_utils.atomic_savez(out / "frames.npz", vertices=V, tets=T, frames=F, singular_faces=S)
    io_utils.atomic_write_json(out / "metrics.json", metrics)

    def write_mesh(path, m):
        # meshio writes to a path: write a temp file in the same dir, then replace atomically
        tmp = path.with_name(f".{path.name}.tmp.vtu")
        meshio.write(str(tmp), m)
        os.replace(tmp, path)

    write_mesh(out / "frames.vtu", meshio.Mesh(V, [("tetra", T)], point_data={
        f"axis{k}": F[:, :, k] for k in range(3)}))
    write_mesh(out / "singular_faces.vtu", meshio.Mesh(V, [("triangle", S)]))
    _plot_loss(out / "loss.png", history)
    _plot_singularities(out / "singularities.png", mesh, sing_faces)


def _plot_loss(path: Path, history: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for k, vals in history.items():
        v = np.asarray(vals, dtype=float)
        if v.size and np.any(v > 0):
            ax.semilogy(np.arange(v.size), np.where(v > 0, v, np.nan), label=k, lw=2 if k == "total" else 1)
    ax.set_xlabel("step")
    ax.set_ylabel("loss term (unweighted; total weighted)")
    ax.set_title("train_frames loss")
    if ax.lines:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no optimization steps", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    io_utils.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


def _plot_singularities(path: Path, mesh, sing_mask_faces: torch.Tensor) -> None:
    """Boundary vertices (points) and singular curves: for every singular face the dual segments
    from the barycenters of its tets through the face barycenter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    P = mesh.vertices.detach().cpu().double().numpy()
    bv = mesh.boundary_vertices.cpu().numpy()
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    ax.scatter(P[bv, 0], P[bv, 1], P[bv, 2], s=2, c="0.45", alpha=0.5, linewidths=0)
    S = sing_mask_faces.cpu().numpy().reshape(-1, 3)
    if S.shape[0]:
        faces = mesh.faces.cpu().numpy()
        key = lambda a: (a[:, 0] * P.shape[0] + a[:, 1]) * P.shape[0] + a[:, 2]  # noqa: E731
        idx = np.searchsorted(key(faces), key(np.sort(S, axis=1)))
        fb = mesh.face_barycenters.detach().cpu().double().numpy()[idx]
        tb = mesh.tet_barycenters.detach().cpu().double().numpy()
        ft = mesh.face_tets.cpu().numpy()[idx]
        segs = [np.stack([tb[ft[:, c][ft[:, c] >= 0]], fb[ft[:, c] >= 0]], 1) for c in range(2)]
        segs = np.concatenate(segs, 0)
        ax.add_collection3d(Line3DCollection(segs, colors="r", linewidths=1.5))
    ax.set_title(f"singular curves ({S.shape[0]} singular faces)")
    lo, hi = P.min(0), P.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    fig.tight_layout()
    io_utils.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


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
    cfg = _validate(cfg)
    try:
        out_dir_value = cfg.output_dir
    except Exception as exc:  # unresolved ${hydra:...} outside Hydra
        raise ValueError("output_dir must be set when train() runs outside Hydra") from exc
    out = io_utils.check_output_dir(out_dir_value)
    ckpt_path = out / "checkpoint.pt"
    if cfg.resume and not ckpt_path.is_file():
        raise FileNotFoundError(f"resume=true but there is no checkpoint at {str(ckpt_path)!r}")
    dtype = getattr(torch, cfg.dtype)
    device = torch.device(cfg.device)
    if cfg.num_threads is not None:
        torch.set_num_threads(int(cfg.num_threads))
    torch.manual_seed(int(cfg.seed))
    np.random.seed(int(cfg.seed))

    mesh = _load_mesh(cfg, dtype, device)
    fp = _fingerprint(cfg, mesh)
    ckpt = None
    if cfg.resume:
        ckpt = io_utils.load_checkpoint(ckpt_path, map_location=device)
        if ckpt.get("fingerprint") != fp:
            raise ValueError(f"checkpoint {str(ckpt_path)!r} was written for another mesh/method/optimizer/"
                             f"weights configuration; refusing to resume")

    # --- initialization (SH baseline); stored in the checkpoint so a resume does not redo it
    t0 = time.perf_counter()
    if ckpt is not None:
        F0 = ckpt["init_frames"].to(device=device, dtype=dtype)
        init_metrics = ckpt["init_metrics"]
    elif cfg.init_frames is not None:
        F0 = _load_init_frames(str(cfg.init_frames), mesh)
        init_metrics = frame_metrics(F0, mesh, cfg.feature_angle_deg)
    else:
        F0 = sh_frame_field(mesh, boundary_weight=float(cfg.sh.boundary_weight),
                            n_smooth_iters=int(cfg.sh.n_smooth_iters),
                            feature_angle_deg=float(cfg.feature_angle_deg),
                            mbo_steps=int(cfg.sh.mbo_steps),
                            mbo_tau=(float(cfg.sh.mbo_tau_start), float(cfg.sh.mbo_tau_end)))
        init_metrics = frame_metrics(F0, mesh, cfg.feature_angle_deg)
    t_init = time.perf_counter() - t0

    loss_fn = FrameFieldLoss(mesh, dict(cfg.weights), feature_angle_deg=float(cfg.feature_angle_deg),
                             smooth_power=float(cfg.smooth_power), smooth_eps=float(cfg.smooth_eps),
                             align_kind=str(cfg.align_kind), align_eps=float(cfg.align_eps))
    V = mesh.n_vertices
    normals = torch.zeros(V, 3, dtype=dtype, device=device)
    normals[mesh.boundary_vertices] = mesh.boundary_vertex_normals
    constrained = torch.zeros(V, dtype=torch.bool, device=device)
    constrained[mesh.boundary_vertices] = True
    constrained &= ~loss_fn.is_feature
    model = FrameFieldModel(mesh, F0, cfg.formulation, constrained, normals).to(device)

    history = {k: [] for k in (*TERMS, "total") if k == "total" or cfg.weights[k] > 0}
    if cfg.weights["torsion"] > 0 and "tie" not in history:
        history["tie"] = []
    start = 0
    steps = int(cfg.steps) if cfg.method == "connection" else 0
    optimizer, scheduler = _make_optimizer(cfg, model.parameters())
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

    # --- optimization
    t0 = time.perf_counter()
    bar = None
    if cfg.progress and steps > start:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, initial=start, desc="train_frames", dynamic_ncols=True)
    if ckpt is None and steps > 0:
        checkpoint(0)
    try:
        for step in range(start, steps):
            record = {}

            def closure():
                optimizer.zero_grad(set_to_none=True)
                R, F = model()
                terms = loss_fn(R, F)
                _check_finite_terms(terms, step)
                terms["total"].backward()
                if not record:
                    record.update({k: float(v.detach()) for k, v in terms.items()})
                return terms["total"]

            if cfg.optim == "lbfgs":
                optimizer.step(closure)
            else:
                closure()
                optimizer.step()
            scheduler.step()
            for k in history:
                history[k].append(record.get(k, 0.0))
            if (step + 1) % int(cfg.checkpoint_every) == 0 or step + 1 == steps:
                checkpoint(step + 1)
            if bar is not None:
                bar.update(1)
                bar.set_postfix({k: f"{v:.3g}" for k, v in record.items()}, refresh=False)
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
    mask, sing = octahedral.singular_faces(F, mesh)
    one = octahedral.tets_with_one_singular_face(mask, mesh)
    atol = None if cfg.bianchi_atol is None else float(cfg.bianchi_atol)
    bianchi_error = None
    try:
        bres = bianchi.check(R.detach(), mesh, atol=atol)
    except bianchi.BianchiError as exc:
        bianchi_error = str(exc)
        bres = {"differential": float(bianchi.differential_residual(R.detach(), mesh).max())}
    from torchconn.tolerances import get_eps

    metrics = {
        "mesh": {"source": str(cfg.mesh), "n_vertices": V, "n_edges": mesh.n_edges, "n_faces": mesh.n_faces,
                 "n_tets": mesh.n_tets, "n_boundary_vertices": int(mesh.boundary_vertices.numel())},
        "method": cfg.method,
        "formulation": cfg.formulation if cfg.method == "connection" else None,
        "final": final_metrics,
        "init": init_metrics,
        "edge_classes": edge_class_breakdown(F.detach(), mesh, cfg.feature_angle_deg),
        "polish": polish_info,
        "final_loss_terms": final_terms,
        "loss_history": history,
        "invariants": {
            "bianchi_differential_max": bres.get("differential"),
            "bianchi_algebraic_max": bres.get("algebraic"),
            "bianchi_tolerance": (atol if atol is not None else get_eps("identity", dtype)) * 3,
            "bianchi_ok": bianchi_error is None,
            "bianchi_error": bianchi_error,
            "n_singular_faces": int(mask.sum()),
            "n_tets_one_singular_face": int(one.sum()),
        },
        "timings": {
            "wall_s": time.perf_counter() - t_start,
            "init_s": t_init,
            "optimize_s": t_opt,
            "iterations": steps - start,
            "total_steps": steps,
            "s_per_iteration": t_opt / max(steps - start, 1),
        },
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    assert set(METRIC_KEYS) <= set(final_metrics)
    _save_outputs(out, mesh, F, sing, history, metrics)
    if bianchi_error is not None:
        raise bianchi.BianchiError(bianchi_error)
    return metrics


def _main() -> None:
    import hydra

    @hydra.main(config_path=str(CONFIG_DIR), config_name="train_frames", version_base="1.3")
    def app(cfg: DictConfig) -> None:
        m = train(cfg)
        f, i = m["final"], m["init"]
        print(f"[train_frames] {cfg.method}: smoothness {i['smoothness_mean_deg']:.2f} -> "
              f"{f['smoothness_mean_deg']:.2f} deg, alignment mean {f['alignment_mean_deg']:.3f} deg, "
              f"singular faces {f['n_singular_faces']}, wall {m['timings']['wall_s']:.1f} s, "
              f"output {cfg.output_dir}")

    app()


if __name__ == "__main__":
    _main()
