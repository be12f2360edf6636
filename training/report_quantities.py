"""The discrete quantities of the report's convergence experiments and their smooth references.

Pure, batched functions on cells given by their vertex rows (report Secs. 3.3-3.4, Chs. 4-5);
:mod:`training.experiments` builds the cells and turns these values into errors and slopes.


Quantities (docs/conventions.md §3; evaluation vertex 0 and cut vertex 2 unless named)
------------------------------------------------------------------------------
Triangle ``[v0 v1 v2]`` — the discrete value divided by the triangle area is compared with the
smooth 2-form at the reference point evaluated on the unit normal of ``[v0 v1 v2]``:

=============================  ==================================================  ==========
name                           discrete value                                      reference
=============================  ==================================================  ==========
``torsion_naive``              prong sums with plain ``θ_ij = v_j - v_i``, cut 2    ``Θ(N)``
``torsion_naive_loop``         same, cut 0 (whole loop)                             ``Θ(N)``
``torsion_sqrt``               Def. 3.2 with ``θ̃_ij = √R_ij θ_ij``, cut 2          ``Θ(N)``
``torsion_sqrt_loop``          Def. 3.2, cut 0                                      ``Θ(N)``
``torsion_barycentric``        eq. 3.3.1 ``Σ_e R_{c,c_e} θ_e``                      ``Θ(N)``
``curvature_holonomy``         eq. 3.2.1 ``R01 R12 R20 - I``                        ``Ω(N)``
``curvature_two_prong``        ``R01 R12 - R02`` (cut 2)                            ``Ω(N)``
``curvature_two_prong_cut1``   ``R01 - R02 R21`` (cut 1)                            ``Ω(N)``
=============================  ==================================================  ==========

Tet ``[v0 v1 v2 v3]`` — the discrete ``d∇d∇θ`` divided by the signed volume ``det/6`` is compared
with the ``dx∧dy∧dz`` coefficient of ``Ω∧θ`` at the reference point (``(0, 0, -xy)`` for the
report's connection): ``ddtheta_behs`` (BEHS21 ``𝔡∇𝔡∇θ`` with plain ``θ``, Sec. 4 / Ch. 5),
``ddtheta_averaged`` (``𝔡∇ Alt 𝔡∇ Alt θ̃``, Def. 5.2, Fig. 5.1), ``ddtheta_primal_dual``
(Def. 4.2 applied twice, Fig. 4.3).

Transports (docs/conventions.md §3). ``transport="midpoint"`` (the report's main series): the edge
rotations ``R_ij`` and the barycenter segment transports ``R_{c,c_e}``, ``R_{c_t,c_f}`` are
``exp(ω_m[b - a])`` of their straight segment ``a -> b``; the half transports are
``√R_ij = exp(½ ω_m[v_j - v_i])`` with ``ω_m`` at the *edge* midpoint.
``transport="path_ordered"``: every one of these segment transports is the path-ordered
solution along its segment (``SmoothConnection.path_ordered_transport``), and ``√R_ij`` is the
principal square root ``so3.sqrt(R_ij)`` of the path-ordered edge transport (the rule of a
discrete connection, which keeps ``√R_ji = √R_ij^T``).

Reference point. ``"vertex0"`` (the report's choice): the smooth form at ``v0``;
``"centroid"``: at the cell centroid. In the global coordinate frame of the smooth connection
the fibers of all points are identified with R^3, so only the evaluation point moves.

Errors are Euclidean norms (vectors) and Frobenius norms (matrices); slopes are least-squares
fits of ``log error`` against ``log h`` (levels 7..12 in the report's setting).
"""
from __future__ import annotations

from typing import Iterable, Sequence

import torch

from torchconn import curvature, dnabla, so3, torsion
from torchconn.dec.smooth import SmoothConnection, evaluate_2form, unit_normal
from torchconn.dec.transport import dense_simplex_transports, pair_list

__all__ = [
    "TRIANGLE_QUANTITIES",
    "TET_QUANTITIES",
    "QUANTITIES",
    "TRANSPORTS",
    "REFERENCE_POINTS",
    "segment_transport",
    "half_edge_transport",
    "triangle_quantities",
    "tet_quantities",
    "cell_error",
]

# ----------------------------------------------------------------------------- names (docs/conventions.md §3)
TRIANGLE_QUANTITIES: tuple[str, ...] = (
    "torsion_naive",
    "torsion_naive_loop",
    "torsion_sqrt",
    "torsion_sqrt_loop",
    "torsion_barycentric",
    "curvature_holonomy",
    "curvature_two_prong",
    "curvature_two_prong_cut1",
)
TET_QUANTITIES: tuple[str, ...] = ("ddtheta_behs", "ddtheta_averaged", "ddtheta_primal_dual")
QUANTITIES: tuple[str, ...] = TRIANGLE_QUANTITIES + TET_QUANTITIES

TRANSPORTS: tuple[str, ...] = ("midpoint", "path_ordered")
REFERENCE_POINTS: tuple[str, ...] = ("vertex0", "centroid")


# ----------------------------------------------------------------------------- transports
def segment_transport(smooth: SmoothConnection, a: torch.Tensor, b: torch.Tensor, method: str, steps: int) -> torch.Tensor:
    """``R_ab`` (fiber at ``b`` -> fiber at ``a``) along ``[a, b]``: midpoint or path-ordered."""
    return smooth.transport(a, b, method=method, steps=steps)


def half_edge_transport(smooth: SmoothConnection, a: torch.Tensor, b: torch.Tensor, method: str, steps: int) -> torch.Tensor:
    """``√R_ab`` (edge midpoint -> ``a``): midpoint ``exp(½ ω_m[b - a])`` with ``m`` the *edge*
    midpoint (report Sec. 3.3, docs/conventions.md §3), or for ``path_ordered`` the principal square
    root ``so3.sqrt(R_ab)`` of the path-ordered edge transport -- the same rule a discrete
    connection uses, and the one that keeps ``√R_ba = √R_ab^T`` and ``R_ba θ̃_ab = -θ̃_ba``."""
    if method == "midpoint":
        return smooth.half_transport(a, b)
    if method == "path_ordered":
        return so3.sqrt(smooth.path_ordered_transport(a, b, steps=steps))
    raise ValueError(f"unknown transport method {method!r}; known: {list(TRANSPORTS)}")


def _check_choice(value: str, known: Iterable[str], what: str) -> None:
    known = tuple(known)
    if value not in known:
        raise ValueError(f"unknown {what} {value!r}; known: {list(known)}")


def _reference_point(cells: torch.Tensor, reference_point: str) -> torch.Tensor:
    _check_choice(reference_point, REFERENCE_POINTS, "reference_point")
    return cells[..., 0, :] if reference_point == "vertex0" else cells.mean(-2)


# ----------------------------------------------------------------------------- triangles
def triangle_quantities(
    smooth: SmoothConnection,
    tri: torch.Tensor,
    quantities: Sequence[str] = TRIANGLE_QUANTITIES,
    *,
    transport: str = "midpoint",
    reference_point: str = "vertex0",
    steps: int = 64,
) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Discrete triangle quantities (already divided by the area) and their smooth references.

    Args:
        smooth: the smooth connection (its ``torsion_form`` / ``curvature_form`` give the
            references).
        tri: ``(..., 3, 3)`` triangles ``[v0 v1 v2]`` (vertex rows).
        quantities: names from :data:`TRIANGLE_QUANTITIES`.
        transport: ``"midpoint"`` or ``"path_ordered"`` (see the module docstring).
        reference_point: ``"vertex0"`` or ``"centroid"``.
        steps: Magnus sub-steps of the path-ordered transports.

    Returns:
        ``name -> (value, reference)``: ``(..., 3)`` for torsions, ``(..., 3, 3)`` for
        curvatures. Values live in the fiber of ``v0`` (barycentric torsion: of the centroid),
        all identified with R^3 by the global frame.
    """
    unknown = [q for q in quantities if q not in TRIANGLE_QUANTITIES]
    if unknown:
        raise ValueError(f"unknown triangle quantities {unknown}; known: {list(TRIANGLE_QUANTITIES)}")
    _check_choice(transport, TRANSPORTS, "transport")
    nxt = tri.roll(-1, dims=-2)  # x_{k+1}
    loop_rot = segment_transport(smooth, tri, nxt, transport, steps)  # (...,3,3,3): R_{x_k x_{k+1}}
    p0, p1, p2 = tri.unbind(-2)
    cross = torch.linalg.cross(p1 - p0, p2 - p0, dim=-1)
    area = 0.5 * cross.norm(dim=-1)
    normal = unit_normal(p0, p1, p2)
    x_ref = _reference_point(tri, reference_point)
    out: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    wants_torsion = any(q.startswith("torsion") for q in quantities)
    wants_curv = any(q.startswith("curvature") for q in quantities)
    if wants_torsion:
        theta_ref = evaluate_2form(smooth.torsion_form(x_ref), normal)  # (...,3)
    if wants_curv:
        omega_ref = evaluate_2form(smooth.curvature_form(x_ref), normal)  # (...,3,3)
    a2 = area[..., None]
    if "torsion_naive" in quantities:
        out["torsion_naive"] = (torsion.naive(loop_rot, tri, 2) / a2, theta_ref)
    if "torsion_naive_loop" in quantities:
        out["torsion_naive_loop"] = (torsion.naive(loop_rot, tri, 0) / a2, theta_ref)
    if "torsion_sqrt" in quantities or "torsion_sqrt_loop" in quantities:
        half = half_edge_transport(smooth, tri, nxt, transport, steps)  # √R_{x_k x_{k+1}}
        if "torsion_sqrt" in quantities:
            out["torsion_sqrt"] = (torsion.sqrt(loop_rot, half, tri, 2) / a2, theta_ref)
        if "torsion_sqrt_loop" in quantities:
            out["torsion_sqrt_loop"] = (torsion.sqrt(loop_rot, half, tri, 0) / a2, theta_ref)
    if "torsion_barycentric" in quantities:
        c = tri.mean(-2, keepdim=True).expand_as(tri)
        c_e = 0.5 * (tri + nxt)  # midpoint of edge x_k -> x_{k+1}
        r_c_ce = segment_transport(smooth, c, c_e, transport, steps)  # R_{c, c_e}: c_e -> c
        out["torsion_barycentric"] = (torsion.barycentric(r_c_ce, nxt - tri) / a2, theta_ref)
    a3 = area[..., None, None]
    if "curvature_holonomy" in quantities:
        out["curvature_holonomy"] = (curvature.holonomy(loop_rot) / a3, omega_ref)
    if "curvature_two_prong" in quantities:
        out["curvature_two_prong"] = (curvature.two_prong(loop_rot, 2) / a3, omega_ref)
    if "curvature_two_prong_cut1" in quantities:
        out["curvature_two_prong_cut1"] = (curvature.two_prong(loop_rot, 1) / a3, omega_ref)
    return {q: out[q] for q in quantities}


# ----------------------------------------------------------------------------- tets
def _pair_transports(smooth: SmoothConnection, pts: torch.Tensor, transport: str, steps: int) -> torch.Tensor:
    """Dense table ``T[..., i, j] = R_{x_i x_j}`` of a simplex -> ``(..., s, s, n, n)``.

    Only the pairs ``i < j`` of :func:`torchconn.transport.pair_list` are integrated; the table
    is completed by ``R_ji = R_ij^T`` (docs/conventions.md §1), exactly, also for path-ordered transports.
    """
    pairs = pair_list(pts.shape[-2])
    i = torch.tensor([p[0] for p in pairs], device=pts.device)
    j = torch.tensor([p[1] for p in pairs], device=pts.device)
    pair_rot = segment_transport(smooth, pts[..., i, :], pts[..., j, :], transport, steps)
    return dense_simplex_transports(pair_rot, pts.shape[-2])


def _half_transports(smooth: SmoothConnection, pts: torch.Tensor, transport: str, steps: int) -> torch.Tensor:
    """Dense table ``T_half[..., i, j] = √R_{x_i x_j}`` (edge midpoint -> ``x_i``) -> ``(..., s, s, n, n)``,
    completed by ``√R_ji = √R_ij^T`` (true for both half-transport rules of :func:`half_edge_transport`)."""
    pairs = pair_list(pts.shape[-2])
    i = torch.tensor([p[0] for p in pairs], device=pts.device)
    j = torch.tensor([p[1] for p in pairs], device=pts.device)
    pair_half = half_edge_transport(smooth, pts[..., i, :], pts[..., j, :], transport, steps)
    return dense_simplex_transports(pair_half, pts.shape[-2])


def tet_quantities(
    smooth: SmoothConnection,
    tet: torch.Tensor,
    quantities: Sequence[str] = TET_QUANTITIES,
    *,
    transport: str = "midpoint",
    reference_point: str = "vertex0",
    steps: int = 64,
) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """``d∇d∇θ`` on tets (divided by the signed volume) and the smooth ``Ω∧θ`` (report Chs. 4, 5).

    * ``ddtheta_behs``: :func:`torchconn.dnabla.behs21_dd_tet` on the plain solder form
      ``θ_ij = v_j - v_i``, i.e. ``(R_ab R_bc - R_ac) θ_cd`` (Ch. 4, erratum 1).
    * ``ddtheta_averaged``: :func:`torchconn.dnabla.averaged_dd_tet`, ``𝔡∇ Alt 𝔡∇ Alt θ̃``
      with ``θ̃_ij = √R_ij θ_ij`` (Def. 5.2, Fig. 5.1).
    * ``ddtheta_primal_dual``: :func:`torchconn.dnabla.primal_dual_dd` with the solder form
      ``v_j - v_i`` stored at the edge barycenters and segment transports
      ``R_{c_f c_e}``, ``R_{c_t c_f}`` between barycenters (Defs. 4.1-4.2, Fig. 4.3).

    Args:
        smooth: the smooth connection (``curvature_wedge_solder`` gives the reference).
        tet: ``(..., 4, 3)`` tets ``[v0 v1 v2 v3]`` (vertex rows); values are divided by the
            signed volume ``det(v1-v0, v2-v0, v3-v0)/6``, so either orientation compares
            with ``Ω∧θ``.
        quantities: names from :data:`TET_QUANTITIES`.
        transport, reference_point, steps: as in :func:`triangle_quantities`.

    Returns:
        ``name -> (value (..., 3), reference (..., 3))``. BEHS21 and averaged values live in the
        fiber of ``v0``, the primal-dual value in the fiber of the tet barycenter.
    """
    unknown = [q for q in quantities if q not in TET_QUANTITIES]
    if unknown:
        raise ValueError(f"unknown tet quantities {unknown}; known: {list(TET_QUANTITIES)}")
    _check_choice(transport, TRANSPORTS, "transport")
    p0 = tet[..., 0, :]
    vol = torch.linalg.det(tet[..., 1:, :] - p0[..., None, :]) / 6.0  # signed volume (rows)
    ref = smooth.curvature_wedge_solder(_reference_point(tet, reference_point))
    v3 = vol[..., None]
    out: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    if "ddtheta_behs" in quantities or "ddtheta_averaged" in quantities:
        T = _pair_transports(smooth, tet, transport, steps)  # (...,4,4,3,3)
        theta = dnabla.solder_form(tet)  # (...,4,4,3): v_j - v_i
        if "ddtheta_behs" in quantities:
            out["ddtheta_behs"] = (dnabla.behs21_dd_tet(T, theta) / v3, ref)
        if "ddtheta_averaged" in quantities:
            theta_t = dnabla.solder_form_sqrt(_half_transports(smooth, tet, transport, steps), theta)
            out["ddtheta_averaged"] = (dnabla.averaged_dd_tet(T, theta_t) / v3, ref)
    if "ddtheta_primal_dual" in quantities:
        out["ddtheta_primal_dual"] = (_primal_dual_ddtheta(smooth, tet, transport, steps) / v3, ref)
    return {q: out[q] for q in quantities}


def _primal_dual_ddtheta(smooth: SmoothConnection, tet: torch.Tensor, transport: str, steps: int) -> torch.Tensor:
    """Def. 4.2 twice: ``Σ_f s_f R_{c_t c_f} Σ_{e⊂f} s_fe R_{c_f c_e} θ_e`` -> ``(..., 3)``.

    Local template of :func:`torchconn.dnabla.primal_dual_dd`: face ``k`` =
    ``dnabla.TET_FACES[k]`` ``[p<q<r]``, slot ``m`` its edge opposite the ``m``-th vertex
    (``qr, pr, pq``); ``θ_e = v_j - v_i`` for local edges ``i < j`` (pair_list(4) order).
    """
    dev = tet.device
    faces = torch.tensor(dnabla.TET_FACES, device=dev)  # (4,3)
    slot_edges = torch.tensor([[[q, r], [p, r], [p, q]] for p, q, r in dnabla.TET_FACES], device=dev)  # (4,3,2)
    c_f = tet[..., faces, :].mean(-2)  # (...,4,3)
    c_e = tet[..., slot_edges, :].mean(-2)  # (...,4,3,3) midpoints of the slot edges
    c_t = tet.mean(-2)  # (...,3)
    face_edge_rot = segment_transport(smooth, c_f[..., None, :].expand_as(c_e), c_e, transport, steps)
    tet_face_rot = segment_transport(smooth, c_t[..., None, :].expand_as(c_f), c_f, transport, steps)
    pairs = pair_list(4)
    i = torch.tensor([p[0] for p in pairs], device=dev)
    j = torch.tensor([p[1] for p in pairs], device=dev)
    edge_values = tet[..., j, :] - tet[..., i, :]  # (...,6,3) solder form at c_e
    return dnabla.primal_dual_dd(tet_face_rot, face_edge_rot, edge_values)




def cell_error(quantity: str, value: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Error of one quantity per cell: Frobenius norm of ``value - reference`` for the
    (matrix-valued) curvatures, Euclidean norm for the vector-valued torsions and ``d∇d∇θ``
    (docs/conventions.md §3) -> batch shape."""
    d = value - reference
    if quantity.startswith("curvature"):
        return torch.linalg.matrix_norm(d)
    return torch.linalg.vector_norm(d, dim=-1)

