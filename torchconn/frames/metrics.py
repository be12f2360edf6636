"""Fixed quality metrics of an octahedral frame field on a tet mesh (compute for every method).

Definitions (all angles in degrees; ``frames[i][:, k]`` is axis ``k`` at vertex ``i`` in world
coordinates):

* **smoothness** over all mesh edges ``(i, j)``: with the best match
  ``g* = octahedral.match_edges(frames, edges)`` (``F_i g* ~ F_j``) the residual rotation is ``(F_i g*)^T F_j``; report the mean
  and the RMS of its geodesic angle and the mean of ``||F_i g* - F_j||_F^2``.
* **feature edges**: boundary edges whose two boundary faces' normals differ by more than
  ``angle_deg`` (30 by default); **feature vertices** are their endpoints.
* **alignment** at the other boundary vertices: angle between the area-weighted vertex normal and
  the closest frame axis (up to sign); mean and max.
* **feature alignment** at feature vertices: for every (feature vertex, incident boundary face)
  pair, angle between the face normal and the closest frame axis; mean and max (``nan`` if the
  mesh has no feature vertex).
* **dirichlet_energy_mean**: the discrete Dirichlet energy per edge, the mean of
  ``||F_i g* - F_j||_F^2`` over all edges (the same number as the older key
  ``smoothness_mean_sqfrob``, kept).
* **singularities**: number of faces with non-identity matched holonomy and number of tets with
  exactly one such face (:mod:`torchconn.frames.octahedral`).
* **singular graph** (:func:`~torchconn.frames.singular.singular_graph`, its ``counts()``):
  ``n_singular_curves``, ``n_singular_faces_quarter`` / ``_half`` / ``_complex``,
  ``n_singular_faces_valence3`` / ``_valence5`` (quarter turns), ``singular_valid_fraction``
  (quarter-turn faces whose axis is the frame axis most aligned with the curve tangent, over all
  quarter-turn faces; ``nan`` without any), ``n_singular_junctions``,
  ``n_curves_ending_inside`` (0 for a valid field).
* **integrability (curl)** :func:`face_closure`: for each interior face ``[a < b < c]``, traversed
  ``a -> b -> c -> a``, the frames are carried to frame ``a``'s labeling through the matchings
  along the loop, ``M_a = F_a``, ``M_b = F_b g_ab^T``, ``M_c = F_c (g_ab g_bc)^T``; each edge
  vector ``x_j - x_i`` of the loop is expressed in the average of its endpoints' matched frames,
  and the closure is ``c = sum_(i->j) ((M_i + M_j)/2)^T (x_j - x_i)`` (frame-``a`` coordinates).
  ``curl_mean`` and ``curl_p95`` are the mean and 95th percentile of ``|c| / perimeter`` over the
  interior faces (singular faces included). ``c = 0`` for a constant field (to round-off). For a
  smooth field with matchings ``I`` on the face, Stokes gives ``c_k = area (curl a_k) . n_hat +
  O(h^3)`` with ``a_k = F e_k`` and ``n_hat`` the unit normal of the loop, so the measure is
  ``O(h)``, proportional to the field's curl (an orthonormal frame field is integrable only where
  it is locally constant). It is invariant under ``F_i -> F_i h_i``, ``h_i in O``.

The boundary sets (feature vertices, aligned vertices and their normals, feature pairs) come from
the mesh's :class:`~torchconn.frames.constraints.BoundaryConstraint`.

Diagnostics (not part of the fixed metrics): :func:`edge_class_breakdown` splits the mean edge
angle by where the edge lies (feature, boundary surface, boundary layer, near singular faces,
interior).
"""
from __future__ import annotations

import math

import torch

from ..lie import so3
from . import octahedral
from .constraints import BoundaryConstraint, _require, feature_curve_alignment, feature_edges, feature_vertices
from .singular import edge_matchings, face_holonomy_from_matchings, singular_graph

__all__ = ["feature_edges", "feature_vertices", "axis_alignment_angle", "frame_metrics", "METRIC_KEYS",
           "face_closure", "edge_angles_deg", "edge_class_breakdown", "EDGE_CLASSES"]

METRIC_KEYS = (
    "smoothness_mean_deg",
    "smoothness_rms_deg",
    "smoothness_mean_sqfrob",
    "alignment_mean_deg",
    "alignment_max_deg",
    "feature_alignment_mean_deg",
    "feature_alignment_max_deg",
    "n_feature_vertices",
    "n_singular_faces",
    "n_tets_one_singular_face",
    "dirichlet_energy_mean",
    "n_singular_curves",
    "n_singular_faces_quarter",
    "n_singular_faces_half",
    "n_singular_faces_complex",
    "n_singular_faces_valence3",
    "n_singular_faces_valence5",
    "singular_valid_fraction",
    "n_singular_junctions",
    "n_curves_ending_inside",
    "curl_mean",
    "curl_p95",
    "feature_curve_alignment_mean_deg",
    "feature_curve_alignment_max_deg",
)


def face_closure(frames: torch.Tensor, mesh, matchings: torch.Tensor | None = None) -> torch.Tensor:
    """Integrability closure ``c (F, 3)`` of every face (module docstring, "integrability").

    Args:
        frames: ``(V, 3, 3)``; ``frames[i][:, k]`` axis ``k`` at vertex ``i``.
        mesh: a ``TetMesh`` (``faces [a < b < c]``, ``face_edges``).
        matchings: optional ``(E, 3, 3)`` or ``(E,)`` group indices for ``mesh.edges``.

    Returns:
        ``c (F, 3)``: ``sum_(i->j) ((M_i + M_j)/2)^T (x_j - x_i)`` over the loop ``a -> b -> c -> a``,
        in the coordinates of frame ``a``; divide by the perimeter for the relative measure.
    """
    g = edge_matchings(frames, mesh, matchings)
    g_ab, g_abc, _ = face_holonomy_from_matchings(g, mesh)
    f = mesh.faces
    X = mesh.vertices.to(frames.dtype)[f]  # (F, 3, 3): rows x_a, x_b, x_c
    Ma = frames[f[:, 0]]
    Mb = frames[f[:, 1]] @ g_ab.transpose(-1, -2)
    Mc = frames[f[:, 2]] @ g_abc.transpose(-1, -2)
    M = torch.stack([Ma, Mb, Mc], 1)  # (F, 3, 3, 3)
    Mn = M.roll(-1, 1)  # matched frame at the edge's end
    d = X.roll(-1, 1) - X  # (F, 3, 3): x_b - x_a, x_c - x_b, x_a - x_c
    return (0.5 * (M + Mn).transpose(-1, -2) @ d.unsqueeze(-1)).squeeze(-1).sum(1)


def axis_alignment_angle(frames: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Angle (radians) between each unit ``normals (..., 3)`` and the closest axis ``±frames[..., :, k]``.

    ``frames (..., 3, 3)`` broadcast against ``normals``. Uses ``atan2(|a x n|, |a . n|)`` for the
    axis with the largest ``|a . n|`` (no ``acos``, accurate near 0).
    """
    c = (frames * normals[..., :, None]).sum(-2)  # (..., 3): a_k . n
    k = c.abs().argmax(-1, keepdim=True)
    a = torch.gather(frames, -1, k[..., None, :].expand(*frames.shape[:-1], 1)).squeeze(-1)
    s = torch.linalg.cross(a, normals.expand_as(a), dim=-1).norm(dim=-1)
    return torch.atan2(s, torch.gather(c, -1, k).squeeze(-1).abs())


def frame_metrics(frames: torch.Tensor, mesh, angle_deg: float = 30.0, *, curl: bool = True) -> dict:
    """All fixed metrics of a frame field (see the module docstring) as a dict of Python numbers.

    Args:
        frames: ``(V, 3, 3)`` rotations, ``frames[i][:, k]`` axis ``k`` at vertex ``i``.
        mesh: a ``TetMesh``.
        angle_deg: feature-edge threshold (30 degrees in the fixed definition).
        curl: compute the integrability measure (``False``: ``curl_mean``/``curl_p95`` are
            ``nan``; a caller that does not read them, e.g. the scoring of the candidates, saves a
            pass over the faces).

    Returns:
        dict with exactly the keys of :data:`METRIC_KEYS` (floats, counts as ints).

    The singular-graph chaining loops over the singular faces in Python (one-time work per call).
    """
    _require(mesh, "vertices", "edges", "faces", "face_edges", "tet_faces", "boundary_faces",
             "boundary_vertices", "boundary_vertex_normals")
    V = mesh.vertices.shape[0]
    if not torch.is_tensor(frames) or frames.shape != (V, 3, 3):
        shape = tuple(frames.shape) if torch.is_tensor(frames) else type(frames).__name__
        raise ValueError(f"frames must have shape (V, 3, 3) = ({V}, 3, 3) for this mesh, got {shape}")
    frames = frames.to(mesh.vertices.dtype)
    deg = 180.0 / math.pi

    # smoothness
    _, g = octahedral.match_edges(frames, mesh.edges)
    Fm = frames[mesh.edges[:, 0]] @ g
    Fj = frames[mesh.edges[:, 1]]
    ang = so3.geodesic_distance(Fm, Fj) * deg
    sqf = ((Fm - Fj) ** 2).sum((-2, -1))

    bc = BoundaryConstraint.from_mesh(mesh, angle_deg)
    # alignment at non-feature boundary vertices
    al = axis_alignment_angle(frames[bc.align_vertices], bc.align_normals.to(frames.dtype)) * deg
    # alignment at feature vertices against each incident boundary face normal
    fal = axis_alignment_angle(frames[bc.pair_vertices], bc.pair_normals.to(frames.dtype)) * deg

    # the faces' matched holonomy from the edge matchings above (the same exact signed
    # permutations as octahedral.singular_faces, without matching every face edge again)
    H = face_holonomy_from_matchings(g, mesh)[2]
    mask = ((H - torch.eye(3, dtype=H.dtype, device=H.device)).abs() > 0.5).flatten(-2).any(-1)
    one = octahedral.tets_with_one_singular_face(mask, mesh)
    sg = singular_graph(frames, mesh, g).counts()
    if curl:
        interior = (mesh.face_tets >= 0).all(1)
        Xf = mesh.vertices.to(frames.dtype)[mesh.faces[interior]]
        perim = (Xf.roll(-1, 1) - Xf).norm(dim=-1).sum(1)
        closure = face_closure(frames, mesh, g)[interior].norm(dim=-1) / perim
    else:
        closure = frames.new_zeros(0)
    fca = feature_curve_alignment(frames, mesh, angle_deg)  # tangent pairs inside the feature curves

    def _mean(x):
        return float(x.mean()) if x.numel() else float("nan")

    def _max(x):
        return float(x.max()) if x.numel() else float("nan")

    return {
        "smoothness_mean_deg": _mean(ang),
        "smoothness_rms_deg": float(torch.sqrt((ang**2).mean())) if ang.numel() else float("nan"),
        "smoothness_mean_sqfrob": _mean(sqf),
        "alignment_mean_deg": _mean(al),
        "alignment_max_deg": _max(al),
        "feature_alignment_mean_deg": _mean(fal),
        "feature_alignment_max_deg": _max(fal),
        "n_feature_vertices": int(bc.feature_vertices.numel()),
        "n_singular_faces": int(mask.sum()),
        "n_tets_one_singular_face": int(one.sum()),
        "dirichlet_energy_mean": _mean(sqf),
        "n_singular_curves": sg["n_singular_curves"],
        "n_singular_faces_quarter": sg["n_singular_faces_by_type"]["quarter"],
        "n_singular_faces_half": sg["n_singular_faces_by_type"]["half"],
        "n_singular_faces_complex": sg["n_singular_faces_by_type"]["complex"],
        "n_singular_faces_valence3": sg["n_quarter_faces_by_valence"][3],
        "n_singular_faces_valence5": sg["n_quarter_faces_by_valence"][5],
        "singular_valid_fraction": sg["valid_fraction"],
        "n_singular_junctions": sg["n_junctions"],
        "n_curves_ending_inside": sg["n_curves_ending_inside"],
        "curl_mean": _mean(closure),
        "curl_p95": float(torch.quantile(closure, 0.95)) if closure.numel() else float("nan"),
        "feature_curve_alignment_mean_deg": fca["feature_curve_alignment_mean_deg"],
        "feature_curve_alignment_max_deg": fca["feature_curve_alignment_max_deg"],
    }


EDGE_CLASSES = ("feature", "boundary_surface", "boundary_layer", "singular", "near_singular", "interior")


def edge_angles_deg(frames: torch.Tensor, mesh) -> torch.Tensor:
    """``(E,)`` angle in degrees of ``(F_i g*)^T F_j`` per mesh edge (the smoothness metric's terms)."""
    _, g = octahedral.match_edges(frames, mesh.edges)
    return so3.geodesic_distance(frames[mesh.edges[:, 0]] @ g, frames[mesh.edges[:, 1]]) * (180.0 / math.pi)


def edge_class_breakdown(frames: torch.Tensor, mesh, angle_deg: float = 30.0, near_rings: int = 2) -> dict:
    """Where the mean edge angle sits: edges split into disjoint classes, first match wins.

    Classes (:data:`EDGE_CLASSES`), in priority order:

    * ``feature``: an endpoint is a feature vertex;
    * ``boundary_surface``: an edge of a boundary face;
    * ``boundary_layer``: another edge with an endpoint on the boundary;
    * ``singular``: an endpoint is a vertex of a singular face (matched holonomy ``!= I``);
    * ``near_singular``: an endpoint within ``near_rings`` edge rings of such a vertex;
    * ``interior``: the rest.

    Returns:
        ``{class: {"count", "fraction", "mean_deg", "share"}}`` with ``share`` the class's
        fraction of the summed angle (so ``sum_c fraction_c * mean_c`` is the smoothness mean
        and the shares add up to 1); ``mean_deg`` is ``nan`` for an empty class.
    """
    _require(mesh, "vertices", "edges", "faces", "boundary_faces", "boundary_vertices")
    V = mesh.vertices.shape[0]
    if not torch.is_tensor(frames) or frames.shape != (V, 3, 3):
        raise ValueError(f"frames must have shape (V, 3, 3) = ({V}, 3, 3) for this mesh")
    if near_rings < 0:
        raise ValueError(f"near_rings must be >= 0, got {near_rings}")
    frames = frames.to(mesh.vertices.dtype)
    e = mesh.edges
    ang = edge_angles_deg(frames, mesh)
    dev = e.device
    is_feat = BoundaryConstraint.from_mesh(mesh, angle_deg).is_feature
    on_b = torch.zeros(V, dtype=torch.bool, device=dev)
    on_b[mesh.boundary_vertices] = True
    # boundary-face edges by sorted key lookup
    bf = mesh.boundary_faces
    be = torch.cat([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]]).sort(dim=1).values
    bkey = torch.unique(be[:, 0] * V + be[:, 1])
    ekey = e[:, 0] * V + e[:, 1]  # mesh.edges rows are i < j
    pos = torch.searchsorted(bkey, ekey).clamp(max=max(bkey.numel() - 1, 0))
    on_surface = (bkey[pos] == ekey) if bkey.numel() else torch.zeros_like(ekey, dtype=torch.bool)
    mask, _ = octahedral.singular_faces(frames, mesh)
    near = torch.zeros(V, dtype=torch.bool, device=dev)
    near[mesh.faces[mask].reshape(-1)] = True
    sing_v = near.clone()
    for _ in range(near_rings):
        hit = near[e[:, 0]] | near[e[:, 1]]
        near = near.index_fill(0, e[hit].reshape(-1), True)
    tests = [
        is_feat[e[:, 0]] | is_feat[e[:, 1]],
        on_surface,
        on_b[e[:, 0]] | on_b[e[:, 1]],
        sing_v[e[:, 0]] | sing_v[e[:, 1]],
        near[e[:, 0]] | near[e[:, 1]],
        torch.ones_like(on_surface),
    ]
    taken = torch.zeros_like(on_surface)
    total = float(ang.sum())
    E = max(int(e.shape[0]), 1)
    out = {}
    for name, t in zip(EDGE_CLASSES, tests):
        m = t & ~taken
        taken |= m
        a = ang[m]
        out[name] = {
            "count": int(m.sum()),
            "fraction": int(m.sum()) / E,
            "mean_deg": float(a.mean()) if a.numel() else float("nan"),
            "share": float(a.sum()) / total if total > 0 else 0.0,
        }
    return out
