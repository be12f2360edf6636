"""The loss of the frame-field method: :class:`FrameFieldLoss`, an ``nn.Module`` made of the term modules.

Conventions (docs/conventions.md §1, :mod:`torchconn.frames.octahedral`):

* ``edge_rot (E, 3, 3)`` holds ``R_ij`` for the canonical edges ``(i, j)``, ``i < j``: it maps
  coordinates at ``v_j`` to coordinates at ``v_i``.
* ``frames (V, 3, 3)``: ``frames[i][:, k]`` is axis ``k`` at vertex ``i`` in world coordinates.
  A frame ``F_j`` is parallel to ``F_i`` along ``(i, j)`` when ``F_j = F_i R_ij``
  (:mod:`torchconn.frames.propagate`). Cross frames are classes ``{F g, g in O}``, so the
  relation the connection has to satisfy is ``F_i R_ij = F_j h_ij`` for *some* ``h_ij in O``.
* The connection is the *residual* (matched) connection: smooth frames mean ``R_ij ~ I``; a
  face around a singular curve has holonomy ``R_ab R_bc R_ca`` near a non-identity element of O
  (a 90 or 180 degree turn), a regular face near ``I``.

Terms (each a mean over its elements, so that weights do not depend on the mesh size; all are
dimensionless; each is a module of :mod:`torchconn.frames.terms`, built on the library's own
:class:`~torchconn.nn.Curvature`, :class:`~torchconn.nn.Torsion` and
:class:`~torchconn.nn.AveragedCovariantD` where the term reads the connection's geometry):

* ``smooth``  — ``mean_e rho(||R_e - I||_F)``: ``rho(x) = x^2`` (``= 8 sin^2(angle/2)``, the chordal
  Dirichlet energy of the connection) or a smoothed ``x^p`` (``smooth_power``; ``p = 1`` is
  total variation, see :func:`smoothness_loss`).
* ``tie``     — ``mean_e rho(||F_i R_ij - F_j h_ij||_F)`` (same ``rho`` as ``smooth``; for ``p = 1`` and
  ``w_tie > w_smooth`` it is an exact penalty: the optimum transports the frames exactly) with ``h_ij = argmin_{h in O}`` (chosen
  without gradient, re-chosen at every evaluation): the connection transports the frame at
  ``i`` onto the cross frame at ``j``. This is the edge-wise torsion-free condition: with
  ``θ_ij = F_i^T (v_j - v_i)`` the solder form in frame coordinates, the naive triangle torsion
  ``θ_ab + R_ab θ_bc - θ_ac`` equals ``(R_ab F_b^T - F_a^T)(v_c - v_b)``, which vanishes for every
  triangle exactly when ``F_a R_ab = F_b`` on its edges.
* ``flat``    — symmetric flatness ``mean_f min_{g in O} ||H_f - g||_F^2`` with ``H_f`` the face
  holonomy (report eq. 3.2.1 plus the identity; :func:`torchconn.dec.curvature.face_curvature`).
  Singular faces (``H_f`` near a non-identity element) are allowed, anything else is penalized.
* ``torsion`` — solder-form torsion (report Def. 3.2, √R transports, :mod:`torchconn.dec.torsion`)
  of ``θ`` expressed in the frames, per face ``|Θ_f|^2 / area_f`` (dimensionless), averaged over
  **every** face. On an edge whose frames are relabeled (``F_i R_ij = F_j h_ij`` with
  ``h_ij != I``) the torsion is taken through the matching: with ``R_ij h_ij^T``, the connection
  that carries ``F_i`` onto ``F_j`` as labeled, so the three frames of every face are in one gauge
  (``h`` chosen without gradient, as in ``tie``). Its vanishing is the integrability of the frames
  (the field is locally the gradient of a map; Corman & Crane 2019): the part of the
  non-integrability a seamless map cannot absorb.
* ``dnabla`` — the averaged covariant exterior derivative ``𝔡∇ Alt 𝔡∇ Alt θ̃`` per tet (report
  Def. 5.2, :class:`torchconn.nn.AveragedCovariantD`; by the algebraic Bianchi identity the
  discrete ``Ω∧θ``) of the connection with ``θ`` in the frames, ``|·|^2 / vol_t^{2/3}``
  (dimensionless), averaged over the *regular* tets: those whose four faces have holonomy
  nearest the identity (chosen without gradient). Around a singular curve the holonomy is a
  turn in O by design and ``Ω∧θ`` is large there; elsewhere it is the curvature of the
  connection weighted by the geometry, which ``flat`` (per face, without geometry) does not see.
* ``align``   — at non-feature boundary vertices with unit normal ``n``:
  ``mean (1 - sum_k (F[:, k] . n)^4)``, zero iff one axis is ``±n``.
* ``feature`` — the same for every (feature vertex, incident boundary face normal) pair, so
  that at sharp edges the frame follows every incident face, and, on CAD feature curves, for
  the curve tangent at each curve-interior vertex
  (:meth:`~torchconn.frames.constraints.BoundaryConstraint.feature_targets`). With ``align_kind="angle"``
  (:func:`axis_angle_loss`) both alignment terms are instead the smoothed *angle* between the
  normal and the closest axis, i.e. the quantity the fixed alignment metrics average: an
  L1-type penalty. At a feature vertex whose incident face normals cannot all be matched by
  one frame (dihedral angles that are not multiples of 90 degrees, curved faces), the quartic
  penalty settles at a least-squares compromise, which has a larger *mean* angle than the
  L1 optimum (measurements: ``docs/results/frame-fields.md``).
* ``dirichlet`` — the matched Dirichlet energy of the *frames*, ``mean_e ||F_i g_ij - F_j||_F^2``
  with ``g_ij`` the best octahedral match (chosen without gradient, re-chosen at every
  evaluation; :func:`matched_dirichlet_loss`): the measure hex-meshing papers score a field by
  (Ray et al. 2016, Palmer et al. 2020) and the metric ``dirichlet_energy_mean`` of
  :func:`torchconn.frames.metrics.frame_metrics`. It reads the frames only (not the connection).
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import torch
from torch import nn

from ..nn import MeshBuffers, edge_rotations
from . import octahedral
from .constraints import BoundaryConstraint
from .kernels import frame_loss as _fused
from .terms import (  # noqa: F401  (the term functions, importable from here as before)
    ALIGN_KINDS,
    AxisAlignment,
    ConnectionSmoothness,
    FrameTie,
    MatchedDirichlet,
    MatchedTorsion,
    RegularCovariantD,
    SymmetricFlatness,
    axis_angle_loss,
    matched_dirichlet_loss,
    normal_alignment_loss,
    smoothness_loss,
    symmetric_flatness_loss,
    tie_loss,
)

__all__ = ["TERMS", "FrameFieldLoss"]

#: Names of the loss terms, in display order.
TERMS = ("smooth", "tie", "flat", "torsion", "dnabla", "align", "feature", "dirichlet")
#: The terms the fused kernel computes (:mod:`torchconn.frames.kernels.frame_loss`).
_FUSED = _fused.COMPILED_TERMS


class FrameFieldLoss(nn.Module):
    """All terms of the frame-field objective on one mesh: a module per term (:attr:`terms`), topology
    held once.

    Args:
        mesh: a ``TetMesh``.
        weights: mapping from term name (:data:`TERMS`) to its weight; missing names weigh 0
            and are not built nor evaluated.
        feature_angle_deg: threshold of :func:`torchconn.frames.metrics.feature_edges`; the
            ``align`` and ``feature`` terms use the mesh's
            :class:`~torchconn.frames.constraints.BoundaryConstraint` for it.
        smooth_power, smooth_eps: ``rho`` of the ``smooth`` and ``tie`` terms.
        align_kind: ``"quartic"`` (:func:`normal_alignment_loss`) or ``"angle"``
            (:func:`axis_angle_loss` with ``align_eps``) for the ``align`` and ``feature`` terms.
        extra_terms: ``{name: fn}`` further terms ``fn(edge_rot, frames) -> 0-dim tensor``,
            weighted by ``weights[name]`` (default 0: not evaluated).

    Structure: :attr:`mesh` is the mesh's :class:`~torchconn.nn.MeshBuffers`, shared by the term
    modules of :attr:`terms` (an ``nn.ModuleDict`` of the weighted terms: ``smooth``
    :class:`~torchconn.frames.terms.ConnectionSmoothness`, ``tie``
    :class:`~torchconn.frames.terms.FrameTie`, ``flat``
    :class:`~torchconn.frames.terms.SymmetricFlatness` (a :class:`~torchconn.nn.Curvature`),
    ``torsion`` :class:`~torchconn.frames.terms.MatchedTorsion` (a :class:`~torchconn.nn.Torsion`),
    ``dnabla`` :class:`~torchconn.frames.terms.RegularCovariantD` (an
    :class:`~torchconn.nn.AveragedCovariantD`), ``align`` / ``feature``
    :class:`~torchconn.frames.terms.AxisAlignment`, ``dirichlet``
    :class:`~torchconn.frames.terms.MatchedDirichlet`). ``loss.to(device)`` / ``loss.double()`` move
    them all.

    Call with ``(connection, frames (V,3,3))``, the connection an ``(E,3,3)`` tensor, a
    :class:`~torchconn.dec.connection.Connection` or the model's
    :class:`~torchconn.nn.ConnectionField`; returns a dict of the unweighted terms (0-dim tensors)
    of non-zero weight plus ``"total" = sum_k w_k term_k``.

    Fast path: where the fused kernel serves (the CPU, float32/float64, the switch
    :func:`torchconn.ops.compiled` on, plain tensors; :func:`~torchconn.frames.kernels.frame_loss.frame_loss_terms`)
    the ``smooth``, ``tie``, ``flat``, ``torsion`` and ``dirichlet`` terms and the regular faces of
    ``dnabla`` come from one sweep of ``torchconn::frame_loss`` (``csrc/frame_loss.c``) instead of
    the modules, and ``dnabla`` itself from the module's fused
    :meth:`AveragedCovariantD.sqnorm <torchconn.nn.CovariantD.sqnorm>` (``torchconn::tet_dd_frames_sqnorm``,
    its gradient in the same sweep; :class:`~torchconn.frames.terms.RegularCovariantD`): the same values and
    gradients to round-off (``tests/test_losses.py``), gradients of every order exact. Everywhere else (other devices, the ``torch.func`` transforms, the switch
    off) the modules run, each through its own operators' kernels.

    Input checks (every call, no data read, no device sync): ``edge_rot`` (``None`` is allowed
    when only ``align``/``feature``/``dirichlet`` are weighted) and ``frames`` must be floating tensors of shapes ``(E, 3, 3)`` and ``(V, 3, 3)`` for the mesh's ``E`` edges
    and ``V`` vertices, of one dtype and on one device (``ValueError``/``TypeError`` naming
    the argument, the expected and the given shape, or both dtypes/devices). A mixed pair is
    refused rather than promoted: both are optimization variables, and a silent cast per step
    would hide a copy and bypass the compiled kernel. The mesh's geometry follows the dtype of
    the inputs. *Values* are not validated here (a rotation check would synchronize on every
    step): NaN entries make the affected terms NaN, which the solver reports by term name, and
    :func:`torchconn.lie.so3.check_rotation` checks frames explicitly.
    """

    def __init__(self, mesh, weights: Mapping[str, float], feature_angle_deg: float = 30.0,
                 smooth_power: float = 2.0, smooth_eps: float = 1e-3, align_kind: str = "quartic",
                 align_eps: float = 1e-3, extra_terms: Mapping[str, object] | None = None):
        super().__init__()
        self.extra_terms = dict(extra_terms or {})
        clash = set(self.extra_terms) & set(TERMS)
        if clash:
            raise KeyError(f"extra_terms {sorted(clash)} clash with the built-in terms {list(TERMS)}")
        unknown = {k for k in set(weights) - set(TERMS) - set(self.extra_terms) if float(weights[k]) != 0.0}
        if unknown:
            raise KeyError(f"unknown loss terms {sorted(unknown)}; known: {list(TERMS) + list(self.extra_terms)}")
        if not (0.5 <= float(smooth_power) <= 2.0 and float(smooth_eps) > 0):
            raise ValueError(f"smooth_power must lie in [0.5, 2] and smooth_eps be > 0, got {smooth_power}, {smooth_eps}")
        self.smooth_power, self.smooth_eps = float(smooth_power), float(smooth_eps)
        if align_kind not in ALIGN_KINDS or not float(align_eps) > 0:
            raise ValueError(f"align_kind must be one of {list(ALIGN_KINDS)} and align_eps > 0, got "
                             f"{align_kind!r}, {align_eps}")
        self.align_kind, self.align_eps = align_kind, float(align_eps)
        self.weights = {k: float(weights.get(k, 0.0)) for k in (*TERMS, *self.extra_terms)}  # zero-weight extras: off
        bad = [k for k, w in self.weights.items() if not math.isfinite(w) or w < 0]
        if bad:
            raise ValueError(f"loss weights must be finite and >= 0: {[(k, self.weights[k]) for k in bad]}")
        self.mesh = MeshBuffers(mesh)  # one copy of the topology, shared by the term modules
        con = self.constraint = BoundaryConstraint.from_mesh(mesh, feature_angle_deg)
        self.is_feature = con.is_feature
        self.align_vertices, self.align_normals = con.align_vertices, con.align_normals
        self.feature_vertices_rep, self.feature_normals = con.feature_targets()
        self.register_buffer("group", octahedral.group(torch.float64, mesh.vertices.device), persistent=False)
        w, mb = self.weights, self.mesh
        build = {
            "smooth": lambda: ConnectionSmoothness(self.smooth_power, self.smooth_eps),
            "tie": lambda: FrameTie(mb, self.smooth_power, self.smooth_eps),
            "flat": lambda: SymmetricFlatness(mb),
            "torsion": lambda: MatchedTorsion(mb),
            "dnabla": lambda: RegularCovariantD(mb),
            "align": lambda: AxisAlignment(self.align_vertices, self.align_normals, align_kind, align_eps),
            "feature": lambda: AxisAlignment(self.feature_vertices_rep, self.feature_normals, align_kind, align_eps),
            "dirichlet": lambda: MatchedDirichlet(mb),
        }
        #: The weighted terms' modules, by name.
        self.terms = nn.ModuleDict({k: build[k]() for k in TERMS if w[k]})

    def forward(self, connection: Any, frames: torch.Tensor) -> dict[str, torch.Tensor]:
        """The weighted terms and their total.

        Args:
            connection: ``(E, 3, 3)`` edge rotations ``R_ij`` in ``mesh.edges`` order, a
                ``Connection`` or a ``ConnectionField`` (``None`` when only ``align``,
                ``feature`` or ``dirichlet`` are weighted).
            frames: ``(V, 3, 3)`` frames, axes as columns.

        Returns:
            ``{term: 0-dim tensor}`` for every term of non-zero weight (unweighted values) and
            ``"total"``, in the dtype and on the device of the inputs.
        """
        edge_rot = connection
        if connection is not None and not isinstance(connection, torch.Tensor):
            edge_rot = edge_rotations(connection, "FrameFieldLoss")
        self._check_inputs(edge_rot, frames)
        w, terms = self.weights, self.terms
        out: dict[str, torch.Tensor] = {}
        face_regular = None
        fused = None
        if edge_rot is not None:
            fused = _fused.frame_loss_terms(edge_rot, frames, self.mesh, self.group, {k: w[k] for k in _FUSED},
                                            self.smooth_power, self.smooth_eps, regular=bool(w["dnabla"]))
        if fused is not None:
            face_regular = fused.pop("face_regular", None)
            out.update(fused)
        else:
            for k in ("smooth", "flat"):
                if w[k]:
                    out[k] = terms[k](edge_rot)
            for k in ("tie", "torsion"):
                if w[k]:
                    out[k] = terms[k](edge_rot, frames)
            if w["dirichlet"]:
                out["dirichlet"] = terms["dirichlet"](frames)
        if w["dnabla"]:
            out["dnabla"] = terms["dnabla"](edge_rot, frames, face_regular)
        for k in ("align", "feature"):
            if w[k]:
                out[k] = terms[k](frames)
        for name, fn in self.extra_terms.items():
            if w[name]:
                out[name] = fn(edge_rot, frames)
        out = {k: out[k] for k in (*TERMS, *self.extra_terms) if k in out}
        total = frames.new_zeros(())
        for k, v in out.items():
            # alpha, not `w[k] * v`: forward mode of a 0-dim tensor times a Python float gives a
            # float64 tangent for float32 values (pytorch/pytorch#90065; torch.func.jvp, jacfwd)
            total = torch.add(total, v, alpha=w[k])
        out["total"] = total
        return out

    @property
    def face_area(self) -> torch.Tensor:
        """``(F,)`` face areas (the torsion's normalization), in the mesh's dtype."""
        p = self.mesh.vertices[self.mesh.faces]
        return 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)

    def _check_inputs(self, edge_rot, frames) -> None:
        """Types, shapes, dtypes and devices of the call's inputs (class docstring); no sync."""
        E, V = int(self.mesh.edges.shape[0]), int(self.mesh.vertices.shape[0])
        checks = [("edge_rot", edge_rot, (E, 3, 3), "one rotation R_ij per mesh edge, in mesh.edges order"),
                  ("frames", frames, (V, 3, 3), "one frame per mesh vertex")]
        if edge_rot is None:  # allowed when only the frame terms are on (they read the frames only)
            need = [k for k in ("smooth", "tie", "flat", "torsion", "dnabla") if self.weights[k]]
            if need:
                raise TypeError(f"FrameFieldLoss: edge_rot is None but the terms {need} have non-zero weight "
                                f"and need it; pass the ({E}, 3, 3) edge rotations")
            checks = checks[1:]
        for name, x, shape, what in checks:
            if not isinstance(x, torch.Tensor) or not x.is_floating_point():
                got = f"dtype {x.dtype}" if isinstance(x, torch.Tensor) else type(x).__name__
                raise TypeError(f"FrameFieldLoss: {name} must be a floating-point tensor, got {got}; "
                                f"convert it, e.g. torch.as_tensor({name}, dtype=torch.float64)")
            if tuple(x.shape) != shape:
                raise ValueError(f"FrameFieldLoss: {name} must have shape {shape} ({what}; the mesh has "
                                 f"E={E} edges, V={V} vertices), got {tuple(x.shape)}")
        if edge_rot is None:
            return
        if edge_rot.dtype != frames.dtype:
            raise TypeError(f"FrameFieldLoss: edge_rot has dtype {edge_rot.dtype} but frames has dtype "
                            f"{frames.dtype}; pass both in one dtype, e.g. frames.to(edge_rot.dtype)")
        if edge_rot.device != frames.device:
            raise ValueError(f"FrameFieldLoss: edge_rot is on {edge_rot.device} but frames is on "
                             f"{frames.device}; move both to one device")
