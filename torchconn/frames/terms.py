"""The terms of the frame-field loss: functions on tensors and the ``nn.Module`` of each term.

Conventions (docs/conventions.md §1, :mod:`torchconn.frames.octahedral`): ``edge_rot (E, 3, 3)``
holds ``R_ij`` for the canonical edges ``(i, j)``, ``i < j`` (coordinates at ``v_j`` to ``v_i``);
``frames (V, 3, 3)``: ``frames[i][:, k]`` is axis ``k`` at vertex ``i``. Cross frames ask for
``F_i R_ij = F_j h_ij`` with ``h_ij`` in the octahedral group O; the residual (matched)
connection of a smooth field is ``R_ij ~ I``.

The modules (what :class:`~torchconn.frames.loss.FrameFieldLoss` composes) are built once from a
mesh and take the connection as a tensor ``(E, 3, 3)``, a
:class:`~torchconn.dec.connection.Connection` or the model's
:class:`~torchconn.nn.ConnectionField` (:func:`torchconn.nn.edge_rotations`); the terms of the
connection's geometry are the library's own modules (:mod:`torchconn.nn`):

* :class:`ConnectionSmoothness` (``smooth``): :func:`smoothness_loss`;
* :class:`FrameTie` (``tie``): :func:`tie_loss`;
* :class:`SymmetricFlatness` (``flat``): :class:`~torchconn.nn.Curvature` (holonomy) and
  :func:`symmetric_flatness_loss`;
* :class:`MatchedTorsion` (``torsion``): :class:`~torchconn.nn.Torsion` (√R, in the frames) of
  the matched connection, per face ``|Θ_f|² / area_f``, averaged over every face;
* :class:`RegularCovariantD` (``dnabla``): :class:`~torchconn.nn.AveragedCovariantD` in the frames,
  ``|·|² / vol_t^{2/3}``, averaged over the regular tets (their four faces' holonomy nearest the
  identity: :class:`~torchconn.nn.Curvature`);
* :class:`AxisAlignment` (``align``, ``feature``): :func:`normal_alignment_loss` or
  :func:`axis_angle_loss`;
* :class:`MatchedDirichlet` (``dirichlet``): :func:`matched_dirichlet_loss`.

Every matching (``h``, ``g``) is chosen without gradient (the min over the 24 smooth branches has
the gradient of the active branch). The fused kernel :mod:`torchconn.frames.kernels.frame_loss`
computes ``smooth``, ``tie``, ``flat``, ``torsion`` and ``dirichlet`` (and the regular faces) in one
sweep: the same values and gradients to round-off (``tests/test_losses.py``).
"""
from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from ..nn import AveragedCovariantD, Curvature, MeshBuffers, Torsion, edge_rotations
from ..ops import can_use_compiled
from . import octahedral

__all__ = [
    "smoothness_loss",
    "tie_loss",
    "symmetric_flatness_loss",
    "normal_alignment_loss",
    "axis_angle_loss",
    "matched_dirichlet_loss",
    "matched_rotations_of",
    "ALIGN_KINDS",
    "ConnectionSmoothness",
    "FrameTie",
    "SymmetricFlatness",
    "MatchedTorsion",
    "RegularCovariantD",
    "AxisAlignment",
    "MatchedDirichlet",
]

#: Forms of the ``align``/``feature`` terms (:func:`normal_alignment_loss`, :func:`axis_angle_loss`).
ALIGN_KINDS = ("quartic", "angle")


# ----------------------------------------------------------------------------- functions

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
    with torch.no_grad():
        idx, g = octahedral.match(Fj, Fi)  # F_j h ~ F_i R_ij
    d = _rho(((Fi - Fj @ g) ** 2).sum((-2, -1)), power, eps)
    return d.mean(), idx == 0


def matched_rotations_of(edge_rot: torch.Tensor, frames: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """The matched connection ``M_ij = R_ij h_ijᵀ (E, 3, 3)`` with ``h_ij = argmin_{h in O}
    ||F_i R_ij - F_j h||`` (chosen without gradient; differentiable in ``edge_rot``).

    ``M_ij`` carries ``F_i`` onto ``F_j`` as labeled (``F_i M_ij ~ F_j``), so the three frames of
    every face are in one gauge: the connection the torsion term reads.
    """
    with torch.no_grad():
        FiR = frames.index_select(0, edges[:, 0]) @ edge_rot
        _, h = octahedral.match(frames.index_select(0, edges[:, 1]), FiR)  # F_j h ~ F_i R_ij
    return edge_rot @ h.transpose(-1, -2).to(edge_rot.dtype)


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


# ----------------------------------------------------------------------------- modules

def _face_areas(mesh: MeshBuffers) -> torch.Tensor:
    """``(F,)`` triangle areas, formed in float64."""
    p = mesh.vertices.to(torch.float64)[mesh.faces]
    return 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)


def _tet_scales(mesh: MeshBuffers) -> torch.Tensor:
    """``(T,)`` ``vol_t^{2/3}``, formed in float64."""
    t = mesh.vertices.to(torch.float64)[mesh.tets]
    return (torch.linalg.det(t[:, 1:] - t[:, :1]).abs() / 6.0).pow(2.0 / 3.0)


class ConnectionSmoothness(nn.Module):
    """``smooth``: ``mean_e rho(||R_e - I||_F)`` of the connection (:func:`smoothness_loss`).

    Args:
        power, eps: ``rho`` (``power = 2``: the chordal Dirichlet energy ``8 sin²(t/2)``; ``1``:
            smoothed total variation).
    """

    def __init__(self, power: float = 2.0, eps: float = 1e-3):
        super().__init__()
        self.power, self.eps = float(power), float(eps)

    def forward(self, connection: Any) -> torch.Tensor:
        """The term (0-dim) of a connection ``(E, 3, 3)`` (tensor, ``Connection`` or ``ConnectionField``)."""
        return smoothness_loss(edge_rotations(connection, "ConnectionSmoothness"), self.power, self.eps)


class FrameTie(nn.Module):
    """``tie``: ``mean_e rho(min_{h in O} ||F_i R_ij - F_j h||_F)`` (:func:`tie_loss`): the connection
    transports each frame onto its neighbour's cross frame.

    Args:
        mesh: ``TetMesh`` (or the loss's shared :class:`~torchconn.nn.MeshBuffers`).
        power, eps: ``rho`` as in :class:`ConnectionSmoothness`.
    """

    def __init__(self, mesh: Any, power: float = 2.0, eps: float = 1e-3):
        super().__init__()
        self.mesh = MeshBuffers.of(mesh)
        self.power, self.eps = float(power), float(eps)

    def forward(self, connection: Any, frames: torch.Tensor) -> torch.Tensor:
        """The term (0-dim) of a connection ``(E, 3, 3)`` and ``frames (V, 3, 3)``."""
        R = edge_rotations(connection, "FrameTie")
        return tie_loss(R, frames, self.mesh.edges, self.power, self.eps)[0]


class SymmetricFlatness(nn.Module):
    """``flat``: ``mean_f min_{g in O} ||H_f - g||_F²`` of the face holonomies ``H_f``
    (:class:`~torchconn.nn.Curvature` ``kind="holonomy"`` plus ``I``; report eq. 3.2.1):
    singular faces (``H_f`` near a non-identity element of O) are allowed, anything else is penalized.

    Args:
        mesh: ``TetMesh`` (or a shared :class:`~torchconn.nn.MeshBuffers`).
    """

    def __init__(self, mesh: Any):
        super().__init__()
        self.curvature = Curvature(MeshBuffers.of(mesh), kind="holonomy")

    def forward(self, connection: Any) -> torch.Tensor:
        """The term (0-dim) of a connection ``(E, 3, 3)`` (tensor, ``Connection`` or ``ConnectionField``)."""
        hol = self.curvature(connection)
        return symmetric_flatness_loss(hol + torch.eye(3, dtype=hol.dtype, device=hol.device))


class MatchedTorsion(nn.Module):
    """``torsion``: mean over **every** face of ``|Θ_f|² / area_f`` (dimensionless), the √R torsion
    (report Def. 3.2; :class:`~torchconn.nn.Torsion`) of the solder form in the frames, through the
    matchings.

    On an edge whose frames are relabeled (``F_i R_ij = F_j h_ij``, ``h_ij != I``) the torsion reads
    the matched connection ``M_ij = R_ij h_ijᵀ`` (:func:`matched_rotations_of`), which carries
    ``F_i`` onto ``F_j`` as labeled, so the three frames of every face are in one gauge and the
    value does not change when the frames are relabeled vertex by vertex. Its vanishing is the
    integrability of the frames (the field is locally the gradient of a map; Corman & Crane 2019).

    Args:
        mesh: ``TetMesh`` (or a shared :class:`~torchconn.nn.MeshBuffers`).
    """

    def __init__(self, mesh: Any):
        super().__init__()
        self.torsion = Torsion(MeshBuffers.of(mesh), kind="sqrt")
        self.register_buffer("face_area", _face_areas(self.torsion.mesh).to(self.torsion.mesh.vertices.dtype))

    def forward(self, connection: Any, frames: torch.Tensor) -> torch.Tensor:
        """The term (0-dim) of a connection ``(E, 3, 3)`` and ``frames (V, 3, 3)``."""
        R = edge_rotations(connection, "MatchedTorsion")
        M = matched_rotations_of(R, frames, self.torsion.mesh.edges)
        tor = self.torsion(M, frames)  # (F, 3) in the frame of each face's first vertex
        return ((tor**2).sum(-1) / self.face_area.to(device=tor.device, dtype=tor.dtype)).mean()


class RegularCovariantD(nn.Module):
    """``dnabla``: mean over the *regular* tets of ``|𝔡∇ Alt 𝔡∇ Alt θ̃|² / vol_t^{2/3}``, the averaged
    covariant exterior derivative of the solder form in the frames (report Def. 5.2;
    :class:`~torchconn.nn.AveragedCovariantD`; by the algebraic Bianchi identity the discrete ``Ω∧θ``).

    Regular tets: their four faces have holonomy nearest the identity of O (chosen without
    gradient, :meth:`regular_faces`). Around a singular curve the holonomy is a turn in O by
    design and ``Ω∧θ`` is large there; elsewhere it is the curvature of the connection weighted by
    the geometry, which ``flat`` (per face, without geometry) does not see. 0 when no tet is regular.

    Where the compiled kernel serves (unbatched plain CPU tensors, float32/float64, the switch
    :func:`torchconn.ops.compiled` on, no ``torch.compile`` trace) the term is the module's
    :meth:`~torchconn.nn.CovariantD.sqnorm` (the op :func:`torchconn.ops.tet_sqnorm.tet_dd_frames_sqnorm`)
    with ``w_t = [t regular] / (vol_t^{2/3} #regular)``:
    the same value to round-off, its gradient computed in the forward sweep, irregular tets skipped;
    elsewhere :class:`~torchconn.nn.AveragedCovariantD`'s ``(T, 3)`` output is reduced in torch.

    Args:
        mesh: ``TetMesh`` (or a shared :class:`~torchconn.nn.MeshBuffers`).
    """

    def __init__(self, mesh: Any):
        super().__init__()
        mb = MeshBuffers.of(mesh)
        self.dd = AveragedCovariantD(mb)
        self.curvature = Curvature(mb, kind="holonomy")
        self.register_buffer("tet_scale", _tet_scales(mb).to(mb.vertices.dtype))
        self.register_buffer("tet_inv_scale", _tet_scales(mb).reciprocal().to(mb.vertices.dtype), persistent=False)

    def regular_faces(self, connection: Any) -> torch.Tensor:
        """``(F,)`` bool: faces whose holonomy's nearest element of O is the identity (no gradient)."""
        with torch.no_grad():
            hol = self.curvature(edge_rotations(connection, "RegularCovariantD").detach())
            idx, _ = octahedral.closest_element(hol + torch.eye(3, dtype=hol.dtype, device=hol.device))
        return idx == 0

    def forward(self, connection: Any, frames: torch.Tensor, face_regular: torch.Tensor | None = None
                ) -> torch.Tensor:
        """The term (0-dim) of a connection ``(E, 3, 3)`` and ``frames (V, 3, 3)``.

        ``face_regular (F,)`` bool: the regular faces when the caller has them (the fused kernel
        returns them); default :meth:`regular_faces`.
        """
        R = edge_rotations(connection, "RegularCovariantD")
        if face_regular is None:
            face_regular = self.regular_faces(R)
        tf = self.dd.mesh.tet_faces.to(face_regular.device)
        four = face_regular.index_select(-1, tf.reshape(-1))  # (4T,) the flags of each tet's faces
        if (R.dim() == 3 and isinstance(frames, torch.Tensor) and frames.dim() == 3 and four.dim() == 1
                and not torch.compiler.is_compiling() and can_use_compiled("tet", R, frames)):
            # the compiled kernel: the same sum without the (T, 3) tensor, its gradient in the same
            # sweep, irregular tets (weight 0) skipped. A tet is regular when its four flag bytes
            # (bool: 0 or 1) read as one int32 are 0x01010101: one pass instead of all(-1) over a
            # dim of 4 (at 1M tets 10 ms -> 2 ms); a bool times a float is one pass, where() three.
            regular = four.view(torch.int32) == 0x01010101
            w = self.tet_inv_scale.to(device=R.device, dtype=R.dtype) * regular
            return self.dd.sqnorm(R, frames, weight=w) / regular.sum().clamp_min(1)
        regular = four.reshape(*face_regular.shape[:-1], *tf.shape).all(-1)  # (T,)
        dd = self.dd(R, frames)  # (T, 3)
        per = (dd**2).sum(-1) / self.tet_scale.to(device=dd.device, dtype=dd.dtype)
        # no int(): a data-dependent branch breaks vmap and torch.compile(fullgraph=True); 0 when
        # no tet is regular (the sum is then 0, divided by 1)
        return torch.where(regular, per, 0.0).sum() / regular.sum().clamp_min(1)


class AxisAlignment(nn.Module):
    """``align`` / ``feature``: frames at given vertices aligned with given unit directions.

    ``kind="quartic"``: :func:`normal_alignment_loss`, ``mean (1 - Σ_k (F[:, k]·n)⁴)``;
    ``kind="angle"``: :func:`axis_angle_loss` (the smoothed angle to the closest axis, an L1-type
    penalty). Both vanish iff an axis is ``±n`` at every pair.

    Args:
        vertices: ``(N,)`` long, a vertex per pair (repeated for several directions).
        normals: ``(N, 3)`` unit directions (boundary normals, feature-curve tangents).
        kind, eps: the form (:data:`ALIGN_KINDS`) and the smoothing of ``"angle"``.
    """

    def __init__(self, vertices: torch.Tensor, normals: torch.Tensor, kind: str = "quartic", eps: float = 1e-3):
        super().__init__()
        if kind not in ALIGN_KINDS or not float(eps) > 0:
            raise ValueError(f"align_kind must be one of {list(ALIGN_KINDS)} and align_eps > 0, got {kind!r}, {eps}")
        self.kind, self.eps = kind, float(eps)
        self.register_buffer("vertices", vertices.clone())
        self.register_buffer("normals", normals.clone())

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """The term (0-dim) of ``frames (V, 3, 3)`` (computed in the frames' dtype)."""
        F = frames.index_select(0, self.vertices.to(frames.device))
        n = self.normals.to(device=frames.device, dtype=frames.dtype)
        if self.kind == "angle":
            return axis_angle_loss(F, n, self.eps)
        return normal_alignment_loss(F, n)


class MatchedDirichlet(nn.Module):
    """``dirichlet``: the matched Dirichlet energy of the frames, ``mean_e ||F_i g_ij - F_j||_F²``
    (:func:`matched_dirichlet_loss`; Ray et al. 2016, Palmer et al. 2020). Reads the frames only.

    Args:
        mesh: ``TetMesh`` (or a shared :class:`~torchconn.nn.MeshBuffers`).
    """

    def __init__(self, mesh: Any):
        super().__init__()
        self.mesh = MeshBuffers.of(mesh)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """The term (0-dim) of ``frames (V, 3, 3)``."""
        return matched_dirichlet_loss(frames, self.mesh.edges.to(frames.device))
