"""Losses for octahedral frame fields from a differentiable connection (the ``train_frames`` method).

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
dimensionless):

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
from typing import Mapping

import torch

from .kernels import frame_loss as _ops_frame_loss
from ..ops import torsion as _ops_torsion
from . import octahedral
from .constraints import BoundaryConstraint

__all__ = [
    "TERMS",
    "smoothness_loss",
    "tie_loss",
    "symmetric_flatness_loss",
    "normal_alignment_loss",
    "axis_angle_loss",
    "ALIGN_KINDS",
    "FrameFieldLoss",
    "matched_dirichlet_loss",
]

#: Names of the loss terms, in display order.
TERMS = ("smooth", "tie", "flat", "torsion", "dnabla", "align", "feature", "dirichlet")
#: Forms of the ``align``/``feature`` terms (:func:`normal_alignment_loss`, :func:`axis_angle_loss`).
ALIGN_KINDS = ("quartic", "angle")


def smoothness_loss(edge_rot: torch.Tensor, power: float = 2.0, eps: float = 1e-3,
                    weight: torch.Tensor | None = None) -> torch.Tensor:
    """``mean_e w_e rho(||R_e - I||_F)`` for ``edge_rot (E, 3, 3)`` (``weight (E,)``, default 1).

    ``rho(x) = x^2`` for ``power=2`` (Dirichlet energy of the connection, ``x^2 = 8 sin^2(t/2)``
    for angle ``t``); otherwise the smoothed ``rho(x) = (x^2 + eps^2)^(power/2) - eps^power``
    (``power=1``: total variation, ~ ``2 sqrt(2) sin(t/2)``, which concentrates the turning of
    the frames near singular curves instead of spreading it; ``eps`` keeps the gradient finite
    at ``R = I``).
    """
    eye = torch.eye(3, dtype=edge_rot.dtype, device=edge_rot.device)
    d = _rho(((edge_rot - eye) ** 2).sum((-2, -1)), power, eps)
    return (d * weight).sum() / weight.sum() if weight is not None else d.mean()


def _rho(d2: torch.Tensor, power: float, eps: float) -> torch.Tensor:
    """``d2`` for ``power=2``, else ``(d2 + eps^2)^(power/2) - eps^power`` (smoothed ``|x|^power``)."""
    if power == 2.0:
        return d2
    return (d2 + eps * eps) ** (0.5 * power) - eps**power


def tie_loss(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor, power: float = 2.0,
             eps: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """``mean_e rho(min_{h in O} ||F_i R_ij - F_j h||_F)`` (``rho`` as in :func:`smoothness_loss`).

    Args:
        edge_rot: ``(E, 3, 3)`` ``R_ij`` of the canonical edges ``edges (E, 2)``.
        frames: ``(V, 3, 3)``.

    Returns:
        ``(loss, unrelabeled (E,) bool)``: the loss and where the best ``h`` is the identity.
        ``h`` is chosen by :func:`octahedral.match` without gradient (a piecewise-constant choice).
    """
    Fi = frames.index_select(0, edges[:, 0]) @ edge_rot  # frame at i transported to j
    Fj = frames.index_select(0, edges[:, 1])
    return _tie_from(Fi, Fj, power, eps)


def _tie_from(FiR: torch.Tensor, Fj: torch.Tensor, power: float, eps: float
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`tie_loss` from the per-edge ``F_i R_ij (E, 3, 3)`` and ``F_j (E, 3, 3)``."""
    with torch.no_grad():
        idx, g = octahedral.match(Fj, FiR)  # F_j h ~ F_i R_ij
    d = _rho(((FiR - Fj @ g) ** 2).sum((-2, -1)), power, eps)
    return d.mean(), idx == 0


def matched_dirichlet_loss(frames: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``mean_e ||F_i g_ij - F_j||_F^2`` for ``frames (V, 3, 3)`` and ``edges (E, 2)`` rows ``(i, j)``.

    ``g_ij = argmin_{g in O} ||F_i g - F_j||`` (:func:`octahedral.match_edges`, without gradient:
    the min over the 24 smooth branches has the gradient of the active one). For a residual
    rotation of angle ``t`` the edge's value is ``4 (1 - cos t) = 8 sin^2(t / 2)``. Empty ``edges``
    give 0. The value equals ``dirichlet_energy_mean`` of :func:`~torchconn.frames.metrics.frame_metrics`.
    """
    if edges.shape[0] == 0:
        return frames.new_zeros(())
    with torch.no_grad():
        _, g = octahedral.match_edges(frames.detach(), edges)
    d = frames.index_select(0, edges[:, 0]) @ g.to(frames.dtype) - frames.index_select(0, edges[:, 1])
    return (d**2).sum((-2, -1)).mean()


def symmetric_flatness_loss(face_hol: torch.Tensor) -> torch.Tensor:
    """``mean_f min_{g in O} ||H_f - g||_F^2`` for holonomies ``face_hol (F, 3, 3)``.

    The nearest element is chosen without gradient (the min of smooth functions: its gradient
    is that of the active branch).
    """
    with torch.no_grad():
        _, g = octahedral.closest_element(face_hol)
    return ((face_hol - g) ** 2).sum((-2, -1)).mean()


def normal_alignment_loss(frames: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """``mean (1 - sum_k (F[:, k] . n)^4)`` for ``frames (N, 3, 3)`` and unit ``normals (N, 3)``.

    In ``[0, 2/3]``; zero iff an axis is ``±n``. Empty input gives 0.
    """
    if normals.shape[0] == 0:
        return frames.new_zeros(())
    c = (frames * normals[:, :, None]).sum(-2)  # (N, 3): F[:, k] . n
    return (1.0 - (c**4).sum(-1)).mean()


def axis_angle_loss(frames: torch.Tensor, normals: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Mean smoothed angle (radians) between each unit normal and the closest frame axis.

    For ``frames (N, 3, 3)`` and unit ``normals (N, 3)``: with ``c = max_k |F[:, k] . n|`` the
    chord between the closest (sign-matched) axis and ``n`` is ``d = sqrt(2 - 2c)`` and the
    angle ``2 asin(d / 2)``; the loss is ``mean(2 asin(sqrt(d^2 + eps^2) / 2)) - 2 asin(eps / 2)``,
    which is ``>= 0``, zero iff an axis is ``±n``, within ``eps`` of the angle of
    :func:`torchconn.frames.metrics.axis_alignment_angle`, and differentiable everywhere
    (``eps > 0``; the closest axis is selected without gradient). Empty input gives 0.
    """
    if normals.shape[0] == 0:
        return frames.new_zeros(())
    if not eps > 0:
        raise ValueError(f"eps must be > 0, got {eps}")
    c = (frames * normals[:, :, None]).sum(-2).abs()  # (N, 3)
    with torch.no_grad():
        k = c.argmax(-1, keepdim=True)
    cmax = torch.gather(c, -1, k).squeeze(-1)
    d2 = (2.0 - 2.0 * cmax).clamp_min(0.0)
    half = (torch.sqrt(d2 + eps * eps) * 0.5).clamp(max=1.0)
    return (2.0 * torch.asin(half)).mean() - 2.0 * math.asin(0.5 * eps)


class FrameFieldLoss:
    """All terms of the frame-field objective on one mesh; topology gathered once.

    Args:
        mesh: a ``TetMesh``.
        weights: mapping from term name (:data:`TERMS`) to its weight; missing names weigh 0
            and are not evaluated.
        feature_angle_deg: threshold of :func:`torchconn.frames.metrics.feature_edges`; the
            ``align`` and ``feature`` terms use the mesh's
            :class:`~torchconn.frames.constraints.BoundaryConstraint` for it.
        smooth_power, smooth_eps: ``rho`` of the ``smooth`` and ``tie`` terms.
        align_kind: ``"quartic"`` (:func:`normal_alignment_loss`) or ``"angle"``
            (:func:`axis_angle_loss` with ``align_eps``) for the ``align`` and ``feature`` terms.

    Call with ``(edge_rot (E,3,3), frames (V,3,3))``; returns a dict of the unweighted terms
    (0-dim tensors) plus ``"total" = sum_k w_k term_k``. Terms with zero weight are skipped
    (not computed) except that ``tie`` always runs when ``torsion`` is on (it supplies the mask).
    The ``smooth``, ``tie``, ``flat`` and ``torsion`` terms run in the op
    :func:`torchconn.ops.frame_loss.frame_loss_terms` on a ``TetMesh`` (``torchconn::frame_loss``:
    the compiled kernel for CPU float32/float64 with the switch :func:`torchconn.ops.compiled`
    on, its torch kernel otherwise); gradients of every order are exact on both paths.

    Input checks (every call, no data read, no device sync): ``edge_rot`` (``None`` is allowed
    when only ``align``/``feature`` are weighted) and ``frames`` must be floating tensors of shapes ``(E, 3, 3)`` and ``(V, 3, 3)`` for the mesh's ``E`` edges
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
        self.mesh = mesh
        self.weights = {k: float(weights.get(k, 0.0)) for k in (*TERMS, *self.extra_terms)}  # zero-weight extras: off
        bad = [k for k, w in self.weights.items() if not math.isfinite(w) or w < 0]
        if bad:
            raise ValueError(f"loss weights must be finite and >= 0: {[(k, self.weights[k]) for k in bad]}")
        con = self.constraint = BoundaryConstraint.from_mesh(mesh, feature_angle_deg)
        self.is_feature = con.is_feature
        self.align_vertices, self.align_normals = con.align_vertices, con.align_normals
        self.feature_vertices_rep, self.feature_normals = con.feature_targets()
        # face areas for the torsion normalization, tet volumes for the dnabla one
        p = mesh.vertices[mesh.faces]
        self.face_area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)
        self._dd = None
        if self.weights["dnabla"]:
            from ..nn import AveragedCovariantD

            self._dd = AveragedCovariantD(mesh)
            t = mesh.vertices[mesh.tets]
            vol = torch.linalg.det(t[:, 1:] - t[:, :1]).abs() / 6.0
            self.tet_scale = vol.pow(2.0 / 3.0)

    def __call__(self, edge_rot: torch.Tensor, frames: torch.Tensor) -> dict[str, torch.Tensor]:
        from ..dec import curvature, torsion

        self._check_inputs(edge_rot, frames)
        mesh, w = self.mesh, self.weights
        out: dict[str, torch.Tensor] = {}
        # the op's own torsion term is the unrelabeled-faces one: torsion runs outside it (every face)
        w_op = {**w, "torsion": 0.0}
        compiled = _ops_frame_loss.frame_loss_terms(edge_rot, frames, mesh, octahedral.group(torch.float64), w_op,
                                                    self.smooth_power, self.smooth_eps)
        if compiled is not None:
            out.update(compiled)
            if w["torsion"]:
                out["torsion"] = self._torsion(edge_rot, frames, None)
            return self._finish(out, frames, edge_rot)
        if w["smooth"]:
            out["smooth"] = smoothness_loss(edge_rot, self.smooth_power, self.smooth_eps)
        if w["tie"]:
            shared = _ops_torsion.edge_frames(edge_rot, mesh, frames)
            if shared is not None:
                out["tie"], _ = _tie_from(shared[1], shared[2], self.smooth_power, self.smooth_eps)
            else:
                out["tie"], _ = tie_loss(edge_rot, frames, mesh.edges, self.smooth_power, self.smooth_eps)
        if w["flat"]:
            hol = curvature.face_curvature(edge_rot, mesh, kind="holonomy")
            eye = torch.eye(3, dtype=hol.dtype, device=hol.device)
            out["flat"] = symmetric_flatness_loss(hol + eye)
        if w["torsion"]:
            out["torsion"] = self._torsion(edge_rot, frames, torsion)
        return self._finish(out, frames, edge_rot)

    def _matched(self, edge_rot: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """``R_ij h_ij^T`` with ``F_i R_ij = F_j h_ij``, ``h`` the best match (no gradient through it)."""
        e = self.mesh.edges
        with torch.no_grad():
            FiR = frames.index_select(0, e[:, 0]) @ edge_rot
            _, h = octahedral.match(frames.index_select(0, e[:, 1]), FiR)  # F_j h ~ F_i R_ij
        return edge_rot @ h.transpose(-1, -2).to(edge_rot.dtype)

    def _torsion(self, edge_rot: torch.Tensor, frames: torch.Tensor, generic) -> torch.Tensor:
        """Mean over every face of ``|Θ_f|^2 / area_f`` through the matchings (class docstring)."""
        Rm = self._matched(edge_rot, frames)
        tor = _ops_torsion.face_torsion(Rm, self.mesh, "sqrt", frames=frames)
        if tor is None:
            from ..dec import torsion as _torsion

            tor = _torsion.face_torsion(Rm, self.mesh, kind="sqrt", frames=frames)
        return ((tor**2).sum(-1) / self.face_area.to(device=tor.device, dtype=tor.dtype)).mean()

    def _dnabla(self, edge_rot: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """Mean over regular tets of ``|𝔡∇ Alt 𝔡∇ Alt θ̃|^2 / vol^{2/3}`` (class docstring)."""
        from ..dec import curvature

        mesh = self.mesh
        with torch.no_grad():
            hol = curvature.face_curvature(edge_rot.detach(), mesh, kind="holonomy")
            eye = torch.eye(3, dtype=hol.dtype, device=hol.device)
            idx, _ = octahedral.closest_element(hol + eye)
            regular = (idx == 0)[mesh.tet_faces].all(-1)
        dd = self._dd(edge_rot, frames)  # (T, 3)
        per = (dd**2).sum(-1) / self.tet_scale.to(device=dd.device, dtype=dd.dtype)
        # no int(): a data-dependent branch breaks vmap and torch.compile(fullgraph=True); 0 when
        # no tet is regular (the sum is then 0, divided by 1)
        return torch.where(regular, per, 0.0).sum() / regular.sum().clamp_min(1)

    def _check_inputs(self, edge_rot, frames) -> None:
        """Types, shapes, dtypes and devices of the call's inputs (class docstring); no sync."""
        E, V = int(self.mesh.edges.shape[0]), int(self.mesh.vertices.shape[0])
        checks = [("edge_rot", edge_rot, (E, 3, 3), "one rotation R_ij per mesh edge, in mesh.edges order"),
                  ("frames", frames, (V, 3, 3), "one frame per mesh vertex")]
        if edge_rot is None:  # allowed when only the alignment terms are on (they read the frames only)
            need = [k for k in ("smooth", "tie", "flat", "torsion") if self.weights[k]]
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

    def _finish(self, out: dict[str, torch.Tensor], frames: torch.Tensor,
                edge_rot: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Add the dnabla, alignment, Dirichlet and extra terms and ``total`` to ``out``."""
        w = self.weights
        if w["dnabla"]:
            out["dnabla"] = self._dnabla(edge_rot, frames)
        for name, fn in self.extra_terms.items():
            if w[name]:
                out[name] = fn(edge_rot, frames)
        if w["align"]:
            out["align"] = self._align(frames[self.align_vertices], self.align_normals.to(frames.dtype))
        if w["feature"]:
            out["feature"] = self._align(frames[self.feature_vertices_rep], self.feature_normals.to(frames.dtype))
        if w["dirichlet"]:
            out["dirichlet"] = matched_dirichlet_loss(frames, self.mesh.edges)
        total = frames.new_zeros(())
        for k, v in out.items():
            if w[k]:
                # alpha, not `w[k] * v`: forward mode of a 0-dim tensor times a Python float gives a
                # float64 tangent for float32 values (pytorch/pytorch#90065; torch.func.jvp, jacfwd)
                total = torch.add(total, v, alpha=w[k])
        out["total"] = total
        return out

    def _align(self, frames: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        if self.align_kind == "angle":
            return axis_angle_loss(frames, normals, self.align_eps)
        return normal_alignment_loss(frames, normals)
