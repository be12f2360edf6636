"""The report's convergence experiments as pure, batched functions (report Secs. 3.4, 4, 5).

Everything the Hydra entry point ``training/convergence.py`` writes to disk is computed here,
so that a notebook can call the same functions:

* :func:`case_cells` builds the level-``n`` triangles and tets of docs/conventions.md §3
  (``P_n = v + 2^{-n} Rot · base``, vertex 0 at ``v``, ``h = 2^{-n}``) for all cases and levels
  at once, as one ``(C, L, 3|4, 3)`` batch.
* :func:`triangle_quantities` / :func:`tet_quantities` evaluate every discrete quantity of
  docs/conventions.md §3 on a batch of cells together with its smooth reference value.
* :func:`convergence_errors`, :func:`fit_slope` and :func:`study` turn them into the error
  tables and least-squares slopes behind the report's Figs. 3.3-3.6, 4.3 and 5.1.
* :func:`mesh_convergence` repeats the per-cell measurement on a refined tetrahedral ball
  (``TetMesh.subdivide``), beyond the report.
* :class:`WaveConnection` is a second smooth connection with non-constant, non-polynomial
  curvature and closed-form ``Θ``, ``Ω``, ``Ω∧θ`` (derived by hand below), beyond the report.

The discrete quantities themselves (the table of names, the transports and reference points)
are computed in :mod:`training.report_quantities`; their names are re-exported here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch

from torchconn import so3
from torchconn.dec.smooth import ReportConnection, SmoothConnection
from torchconn.dec.transport import pair_list

from .report_quantities import (
    QUANTITIES,
    REFERENCE_POINTS,
    TET_QUANTITIES,
    TRANSPORTS,
    TRIANGLE_QUANTITIES,
    cell_error,
    half_edge_transport,
    segment_transport,
    tet_quantities,
    triangle_quantities,
)

__all__ = [
    "CASES",
    "TRIANGLE_QUANTITIES",
    "TET_QUANTITIES",
    "QUANTITIES",
    "CLAIMS",
    "TRANSPORTS",
    "REFERENCE_POINTS",
    "WaveConnection",
    "CONNECTIONS",
    "make_connection",
    "BASE_TRIANGLE",
    "BASE_TET",
    "case_cells",
    "segment_transport",
    "half_edge_transport",
    "triangle_quantities",
    "tet_quantities",
    "cell_error",
    "convergence_errors",
    "fit_slope",
    "StudyResult",
    "study",
    "mesh_convergence",
    "shape_quality",
    "MESH_QUANTITIES",
]

# ----------------------------------------------------------------------------- set-up (§3)
#: Parameter sets of docs/conventions.md §3: ``case -> ((alpha, beta, gamma), v)``, rotation
#: ``R = Rx(alpha) Ry(beta) Rz(gamma)`` (report Sec. 3.4), shift ``v`` of vertex 0.
CASES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "A": ((1.3, 1.1, -1.6), (3.3, 1.6, -0.3)),  # Fig. 3.3
    "B": ((1.7, 2.1, -2.6), (1.3, 1.8, -1.3)),  # Fig. 3.4
    "C": ((2.3, -1.1, 2.0), (2.3, -0.6, 1.1)),  # Figs. 3.5, 3.6
    "D": ((-2.2, 2.1, 1.7), (1.1, -1.2, -1.2)),  # Fig. 5.1
}


#: The report's claim per quantity (docs/conventions.md §3 "expected outcome"): ``True`` = converges
#: linearly (tested as slope >= 0.9), ``False`` = does not converge (slope <= 0.2).
CLAIMS: dict[str, bool] = {q: q not in ("torsion_naive", "torsion_naive_loop", "ddtheta_behs") for q in QUANTITIES}


BASE_TRIANGLE = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
BASE_TET = BASE_TRIANGLE + ((0.0, 0.0, 1.0),)


# ----------------------------------------------------------------------------- 2nd connection
def _generators(dtype: torch.dtype, device) -> torch.Tensor:
    """``J = hat(e1), hat(e2), hat(e3)`` -> ``(3, 3, 3)``; ``[J_i, J_j] = ε_ijk J_k``."""
    return so3.hat(torch.eye(3, dtype=dtype, device=device))


class WaveConnection(SmoothConnection):
    """A smooth so(3) connection with non-constant, non-polynomial curvature (beyond the report).

    With ``J_k = hat(e_k)`` (so ``[J1, J2] = J3`` cyclically and ``J_i e_j = e_i × e_j``)::

        ω = sin(y) J3 dx + exp(z/2) J1 dy + cos(x) J2 dz.

    Closed forms, derived by hand from ``Ω(e_b, e_c) = ∂_b ω_c - ∂_c ω_b + [ω_b, ω_c]`` and
    ``Θ(e_b, e_c) = ω_b e_c - ω_c e_b`` (conventions of :mod:`torchconn.smooth`), and checked
    against the autograd (reverse-mode) numerical forms of the base class in ``tests/test_convergence.py``:

    * ``Ω = (-cos y J3 + sin y e^{z/2} J2) dx∧dy + (-½ e^{z/2} J1 + cos x e^{z/2} J3) dy∧dz
      + (sin x J2 + cos x sin y J1) dz∧dx``
      (e.g. ``Ω_xy = ∂_x ω_y - ∂_y ω_x + [ω_x, ω_y] = -cos y J3 + sin y e^{z/2} [J3, J1]``);
    * ``Θ = -e^{z/2} e2 dy∧dz - cos x e3 dz∧dx - sin y e1 dx∧dy``
      (e.g. ``Θ_xy = sin y J3 e2 - e^{z/2} J1 e1 = -sin y e1``);
    * ``Ω∧θ = Ω_yz e1 + Ω_zx e2 + Ω_xy e3 = (sin y e^{z/2}, cos x e^{z/2}, cos x sin y) dx∧dy∧dz``.

    The curvature mixes all three generators and all three coordinates, so neither Ω nor
    Ω∧θ is constant or polynomial, and ``ω`` is not affine: the midpoint rule is a genuine
    one-point quadrature here (unlike the report's affine ``ω``).
    """

    n = 3

    def omega(self, x: torch.Tensor) -> torch.Tensor:
        """``x (..., 3) -> (..., 3, 3, 3)``: ``[..., a]`` is ``ω_a(x)``."""
        J = _generators(x.dtype, x.device)
        X, Y, Z = (x[..., k, None, None] for k in range(3))
        return torch.stack((torch.sin(Y) * J[2], torch.exp(0.5 * Z) * J[0], torch.cos(X) * J[1]), -3)

    def curvature_form(self, x: torch.Tensor) -> torch.Tensor:
        """Closed-form ``Ω`` -> ``(..., 3, 3, 3)`` on ``(dy∧dz, dz∧dx, dx∧dy)`` (see class doc)."""
        J = _generators(x.dtype, x.device)
        X, Y, Z = (x[..., k, None, None] for k in range(3))
        ez = torch.exp(0.5 * Z)
        f_yz = -0.5 * ez * J[0] + torch.cos(X) * ez * J[2]
        f_zx = torch.sin(X) * J[1] + torch.cos(X) * torch.sin(Y) * J[0]
        f_xy = -torch.cos(Y) * J[2] + torch.sin(Y) * ez * J[1]
        return torch.stack((f_yz, f_zx, f_xy), -1)

    def torsion_form(self, x: torch.Tensor) -> torch.Tensor:
        """Closed-form ``Θ`` -> ``(..., 3, 3)``: ``[..., i, f]`` component ``i`` on form ``f``."""
        X, Y, Z = x.unbind(-1)
        o = torch.zeros_like(X)
        f_yz = torch.stack((o, -torch.exp(0.5 * Z), o), -1)
        f_zx = torch.stack((o, o, -torch.cos(X)), -1)
        f_xy = torch.stack((-torch.sin(Y), o, o), -1)
        return torch.stack((f_yz, f_zx, f_xy), -1)

    def curvature_wedge_solder(self, x: torch.Tensor) -> torch.Tensor:
        """Closed-form ``Ω∧θ = (sin y e^{z/2}, cos x e^{z/2}, cos x sin y)`` -> ``(..., 3)``."""
        X, Y, Z = x.unbind(-1)
        ez = torch.exp(0.5 * Z)
        return torch.stack((torch.sin(Y) * ez, torch.cos(X) * ez, torch.cos(X) * torch.sin(Y)), -1)


#: Smooth connections selectable by name (``connection=`` in the CLI).
CONNECTIONS: dict[str, type[SmoothConnection]] = {"report": ReportConnection, "wave": WaveConnection}


def make_connection(name: str) -> SmoothConnection:
    """Instantiate a connection of :data:`CONNECTIONS` by name (clear error otherwise)."""
    try:
        return CONNECTIONS[name]()
    except KeyError:
        raise ValueError(f"unknown connection {name!r}; known: {sorted(CONNECTIONS)}") from None


# ----------------------------------------------------------------------------- cells
def case_cells(
    cases: Sequence[str],
    levels: Sequence[int] | int,
    *,
    dtype: torch.dtype = torch.float64,
    device=None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Level-``n`` cells of docs/conventions.md §3 for all ``cases`` × ``levels`` in one batch.

    ``P_n = v + 2^{-n} Rot · base`` with ``Rot = euler_xyz(α, β, γ)`` (report Sec. 3.4: the
    triangle is rotated, then shifted so that vertex 0 sits at ``v``; each level halves it).

    Args:
        cases: names in :data:`CASES`.
        levels: level list, or an int ``L`` meaning ``0..L-1``.

    Returns:
        ``tri (C, L, 3, 3)``, ``tet (C, L, 4, 3)`` (vertex rows), ``h (L,)`` with ``h = 2^{-n}``.
    """
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise ValueError(f"unknown cases {unknown}; known: {sorted(CASES)}")
    lv = list(range(levels)) if isinstance(levels, int) else list(levels)
    if not lv or min(lv) < 0:
        raise ValueError(f"levels must be a non-empty list of non-negative ints, got {lv}")
    ang = torch.tensor([CASES[c][0] for c in cases], dtype=dtype, device=device)  # (C,3)
    shift = torch.tensor([CASES[c][1] for c in cases], dtype=dtype, device=device)  # (C,3)
    rot = so3.euler_xyz(ang[:, 0], ang[:, 1], ang[:, 2])  # (C,3,3)
    h = torch.tensor([2.0 ** (-n) for n in lv], dtype=dtype, device=device)  # exact powers of 2
    base = torch.tensor(BASE_TET, dtype=dtype, device=device)  # (4,3)
    rotated = torch.einsum("cij,vj->cvi", rot, base)  # (C,4,3)
    tet = shift[:, None, None, :] + h[None, :, None, None] * rotated[:, None]  # (C,L,4,3)
    return tet[..., :3, :], tet, h


# ----------------------------------------------------------------------------- errors, slopes
def convergence_errors(
    smooth: SmoothConnection,
    cases: Sequence[str],
    levels: Sequence[int] | int,
    quantities: Sequence[str] = QUANTITIES,
    *,
    transport: str = "midpoint",
    reference_point: str = "vertex0",
    dtype: torch.dtype = torch.float64,
    steps: int = 64,
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Errors of every quantity for all cases × levels, computed as one batch.

    Returns:
        ``(errors, h)``: ``errors[name]`` is ``(C, L)`` (float64 regardless of ``dtype``),
        ``h (L,)`` float64.
    """
    unknown = [q for q in quantities if q not in QUANTITIES]
    if unknown:
        raise ValueError(f"unknown quantities {unknown}; known: {list(QUANTITIES)}")
    tri, tet, h = case_cells(cases, levels, dtype=dtype)
    errs: dict[str, torch.Tensor] = {}
    tq = [q for q in quantities if q in TRIANGLE_QUANTITIES]
    kq = [q for q in quantities if q in TET_QUANTITIES]
    if tq:
        for q, (val, ref) in triangle_quantities(
            smooth, tri, tq, transport=transport, reference_point=reference_point, steps=steps
        ).items():
            errs[q] = cell_error(q, val, ref).double()
    if kq:
        for q, (val, ref) in tet_quantities(
            smooth, tet, kq, transport=transport, reference_point=reference_point, steps=steps
        ).items():
            errs[q] = cell_error(q, val, ref).double()
    return {q: errs[q] for q in quantities}, h.double()



def fit_slope(h: torch.Tensor, err: torch.Tensor, levels: Sequence[int] | None = None, all_levels: Sequence[int] | None = None) -> torch.Tensor:
    """Least-squares slope of ``log err`` against ``log h`` (docs/conventions.md §3).

    Args:
        h: ``(L,)`` mesh sizes.
        err: ``(..., L)`` errors.
        levels: the levels to fit (default: all); interpreted against ``all_levels`` (the level
            number of each column, default ``0..L-1``). Levels not present are ignored; at
            least two must remain.

    Returns:
        ``(...)`` slopes (float64). A zero error gives ``-inf`` in the log and a NaN slope.
    """
    cols = list(range(h.shape[-1])) if all_levels is None else list(all_levels)
    if levels is None:
        idx = list(range(len(cols)))
    else:
        wanted = set(levels)
        idx = [i for i, n in enumerate(cols) if n in wanted]
    if len(idx) < 2:
        raise ValueError(f"need at least two levels to fit a slope, got levels {[cols[i] for i in idx]} of {cols}")
    x = torch.log(h[idx].double())
    y = torch.log(err[..., idx].double())
    xc = x - x.mean()
    return ((y - y.mean(-1, keepdim=True)) * xc).sum(-1) / (xc * xc).sum()


@dataclass
class StudyResult:
    """Errors and slopes of one study (one transport / reference-point / connection setting).

    Attributes:
        cases, quantities, levels: the axes.
        h: ``(L,)`` mesh sizes ``2^{-n}``.
        errors: ``name -> (C, L)`` float64 errors.
        slopes: ``name -> (C,)`` float64 slopes over ``fit_levels``.
        settings: transport, reference point, dtype, connection, fit levels.
    """

    cases: list[str]
    quantities: list[str]
    levels: list[int]
    h: torch.Tensor
    errors: dict[str, torch.Tensor]
    slopes: dict[str, torch.Tensor]
    settings: dict = field(default_factory=dict)

    def rows(self) -> list[tuple[str, str, int, float, float]]:
        """``(case, quantity, level, h, error)`` rows, case-major then quantity then level."""
        out = []
        for ci, c in enumerate(self.cases):
            for q in self.quantities:
                for li, n in enumerate(self.levels):
                    out.append((c, q, n, float(self.h[li]), float(self.errors[q][ci, li])))
        return out

    def slope_rows(self) -> list[tuple[str, str, float]]:
        """``(case, quantity, slope)`` rows."""
        return [(c, q, float(self.slopes[q][ci])) for ci, c in enumerate(self.cases) for q in self.quantities]

    def verdicts(self, converge_min: float = 0.9, diverge_max: float = 0.2) -> dict[str, dict[str, bool]]:
        """Per quantity and case, whether the report's claim (:data:`CLAIMS`) holds."""
        res: dict[str, dict[str, bool]] = {}
        for q in self.quantities:
            s = self.slopes[q]
            ok = s >= converge_min if CLAIMS[q] else s <= diverge_max
            res[q] = {c: bool(ok[ci]) for ci, c in enumerate(self.cases)}
        return res


def study(
    smooth: SmoothConnection,
    cases: Sequence[str] = tuple(CASES),
    quantities: Sequence[str] = QUANTITIES,
    levels: int | Sequence[int] = 13,
    *,
    fit_levels: Sequence[int] | None = tuple(range(7, 13)),
    transport: str = "midpoint",
    reference_point: str = "vertex0",
    dtype: torch.dtype = torch.float64,
    steps: int = 64,
) -> StudyResult:
    """One complete convergence study (report Figs. 3.3-3.6, 4.3, 5.1), all in one batch.

    ``fit_levels`` are the levels entering the slope fit (docs/conventions.md §3: 7..12); levels
    outside the computed range are ignored, and when fewer than two remain the fit uses the
    last ``min(6, L)`` computed levels (reduced studies, e.g. 4 levels in the CLI test).
    """
    lv = list(range(levels)) if isinstance(levels, int) else list(levels)
    errors, h = convergence_errors(
        smooth, cases, lv, quantities, transport=transport, reference_point=reference_point, dtype=dtype, steps=steps
    )
    fit = [n for n in (fit_levels if fit_levels is not None else lv) if n in lv]
    if len(fit) < 2:
        fit = lv[-min(6, len(lv)):]
    slopes = {q: fit_slope(h, e, fit, lv) for q, e in errors.items()}
    return StudyResult(
        cases=list(cases), quantities=list(quantities), levels=lv, h=h, errors=errors, slopes=slopes,
        settings={"transport": transport, "reference_point": reference_point, "dtype": str(dtype).replace("torch.", ""),
                  "fit_levels": fit, "connection": type(smooth).__name__},
    )


# ----------------------------------------------------------------------------- whole meshes
MESH_QUANTITIES: tuple[tuple[str, str], ...] = (
    ("curvature_holonomy", "face"),
    ("curvature_two_prong", "face"),
    ("torsion_sqrt", "face"),
    ("torsion_barycentric", "face"),
    ("ddtheta_averaged", "tet"),
    ("ddtheta_primal_dual", "tet"),
)


def mesh_convergence(
    smooth: SmoothConnection,
    mesh,
    levels: int,
    *,
    transport: str = "midpoint",
    reference_point: str = "vertex0",
    steps: int = 64,
    quantities: Sequence[tuple[str, str]] = MESH_QUANTITIES,
    chunk: int = 1 << 15,
) -> list[dict]:
    """Per-cell errors on a mesh refined ``levels - 1`` times by ``TetMesh.subdivide`` (1 -> 8).

    Each interior and boundary face ``[a<b<c]`` (sorted, as stored) is a triangle of
    :func:`triangle_quantities` (evaluation vertex ``a``, cut ``c``, normal of ``[a b c]``); each
    positively oriented tet is a tet of :func:`tet_quantities`. All cells of a level are
    evaluated in batches of ``chunk``.

    Returns:
        one dict per (level, quantity) with keys ``level, h`` (mean edge length), ``cells``,
        ``quantity, kind, mean_error, p95_error`` (95th percentile), ``max_error, min_quality`` (the smallest
        :func:`shape_quality` of the cells of that kind at that level).
    """
    rows: list[dict] = []
    m = mesh
    for lvl in range(levels):
        if lvl > 0:
            m = m.subdivide()
        v = m.vertices
        ev = v[m.edges]
        h = float((ev[:, 1] - ev[:, 0]).norm(dim=-1).mean())
        face_pts = v[m.faces]
        tet_pts = v[m.tets]
        face_quality = float(shape_quality(face_pts).min())
        tet_quality = float(shape_quality(tet_pts).min())
        for q, kind in quantities:
            pts = face_pts if kind == "face" else tet_pts
            fn = triangle_quantities if kind == "face" else tet_quantities
            errs = []
            for s in range(0, pts.shape[0], chunk):
                (val, ref), = fn(smooth, pts[s:s + chunk], [q], transport=transport,
                                 reference_point=reference_point, steps=steps).values()
                errs.append(cell_error(q, val, ref))
            err = torch.cat(errs).double()
            quality = face_quality if kind == "face" else tet_quality
            rows.append({"level": lvl, "h": h, "cells": int(err.numel()), "quantity": q, "kind": kind,
                         "mean_error": float(err.mean()), "p95_error": float(torch.quantile(err, 0.95)),
                         "max_error": float(err.max()),
                         "min_quality": quality})
    return rows


def shape_quality(cells: torch.Tensor) -> torch.Tensor:
    """Scale-free shape quality of triangles ``(..., 3, 3)`` or tets ``(..., 4, 3)``, 1 when regular.

    Triangles: ``(4/√3) area / L_max²``; tets: ``6√2 |vol| / L_max³`` (``L_max`` the longest
    edge). Small values flag slivers, for which the per-cell errors (value / area or / volume)
    carry a large constant.
    """
    s = cells.shape[-2]
    pairs = pair_list(s)
    L = torch.stack([(cells[..., j, :] - cells[..., i, :]).norm(dim=-1) for i, j in pairs], -1).amax(-1)
    e = cells[..., 1:, :] - cells[..., :1, :]
    if s == 3:
        return (4.0 / math.sqrt(3.0)) * 0.5 * torch.linalg.cross(e[..., 0, :], e[..., 1, :], dim=-1).norm(dim=-1) / L**2
    if s == 4:
        return 6.0 * math.sqrt(2.0) * torch.linalg.det(e).abs() / 6.0 / L**3
    raise ValueError(f"shape_quality expects triangles (..., 3, 3) or tets (..., 4, 3), got {tuple(cells.shape)}")

