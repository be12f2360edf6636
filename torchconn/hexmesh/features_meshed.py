"""The CAD corners and curves a hex mesh meshes (:func:`~.quality.hex_quality`'s feature figures).

A CAD corner is meshed when a hex vertex lies on it (within :data:`FEATURE_TOL_REL` of the
diagonal); a CAD curve when hex edges lying on the feature set (both ends within that
tolerance, the midpoint within the chord's sagitta, :data:`FEATURE_CHORD_REL` of the edge)
cover every sample point of the curve's tet edges (:data:`FEATURE_CURVE_SAMPLES` per edge).
"""
from __future__ import annotations

import numpy as np

__all__ = ["FEATURE_TOL_REL", "FEATURE_CHORD_REL", "FEATURE_CURVE_SAMPLES"]

#: A hex vertex "on" a CAD corner or curve is within this fraction of the input's diagonal of
#: it (a tenth of the ``good`` Hausdorff threshold; hex vertices from a map on the tet mesh lie
#: on its feature edges up to round-off).
FEATURE_TOL_REL = 1e-3
#: The midpoint of a hex edge lying on a curved CAD curve is off it by the chord's sagitta
#: ``L^2 / (8 r)``; up to this fraction of the edge length is accepted (a chord of up to 0.8
#: radii of arc).
FEATURE_CHORD_REL = 0.1
#: Interior sample points per tet feature edge when checking that hex edges cover a curve.
FEATURE_CURVE_SAMPLES = 4


def _feature_metrics(p: np.ndarray, used: np.ndarray, edges: np.ndarray, tet_mesh, diag: float) -> dict:
    """Corners and sharp curves of ``tet_mesh.cad`` meshed by the hex mesh (module docstring)."""
    import igl
    from scipy.spatial import cKDTree

    from ..frames.constraints import BoundaryConstraint

    bc = BoundaryConstraint.from_mesh(tet_mesh, features="cad")
    tv = tet_mesh.vertices.detach().cpu().double().numpy()
    V = tv.shape[0]
    tol = FEATURE_TOL_REL * diag
    corners = bc.corner_vertices.cpu().numpy()
    if corners.size and used.size:
        dc, _ = cKDTree(p[used]).query(tv[corners])
        corner_ok = dc <= tol
    else:
        corner_ok = np.zeros(corners.size, dtype=bool)

    fe = bc.feature_edges.cpu().numpy().astype(np.int64)  # (K, 2), i < j
    tags = tet_mesh.cad
    tag_keys = (tags.feature_edges[:, 0] * V + tags.feature_edges[:, 1]).cpu().numpy()
    tag_curve = tags.feature_edge_curve.cpu().numpy()
    pos = np.searchsorted(tag_keys, fe[:, 0] * V + fe[:, 1])  # fe is a subset of the tagged edges
    curve_of = tag_curve[pos] if fe.shape[0] else np.zeros(0, np.int64)
    curves = np.unique(curve_of)
    coverage = np.zeros(curves.size)
    if curves.size and edges.shape[0]:
        fe_v = np.ascontiguousarray(tv)
        # hex edges lying on the feature set: ends within tol, midpoint within the chord tolerance
        d_end = np.full(p.shape[0], np.inf)
        d_end[used], _, _ = igl.point_mesh_squared_distance(p[used], fe_v, fe)
        d_end = np.sqrt(np.maximum(d_end, 0.0))
        on = (d_end[edges[:, 0]] <= tol) & (d_end[edges[:, 1]] <= tol)
        he = edges[on]
        mid = 0.5 * (p[he[:, 0]] + p[he[:, 1]])
        length = np.linalg.norm(p[he[:, 1]] - p[he[:, 0]], axis=1)
        radius = np.maximum(tol, FEATURE_CHORD_REL * length)
        if he.shape[0]:
            sq, idx, _ = igl.point_mesh_squared_distance(mid, fe_v, fe)
            lies = np.sqrt(np.maximum(sq, 0.0)) <= radius
            he_curve = curve_of[np.asarray(idx, dtype=np.int64).reshape(-1)]
        else:
            lies, he_curve = np.zeros(0, bool), np.zeros(0, np.int64)
        t = np.linspace(0.0, 1.0, FEATURE_CURVE_SAMPLES + 2)
        samples = tv[fe[:, 0]][:, None] + t[None, :, None] * (tv[fe[:, 1]] - tv[fe[:, 0]])[:, None]  # (K, S, 3)
        for k, c in enumerate(curves):
            mine = lies & (he_curve == c)
            if not mine.any():
                continue
            q = samples[curve_of == c].reshape(-1, 3)
            seg = he[mine]
            sq, idx, _ = igl.point_mesh_squared_distance(q, p, np.ascontiguousarray(seg))
            r = radius[mine][np.asarray(idx, dtype=np.int64).reshape(-1)]
            coverage[k] = float(np.mean(np.sqrt(np.maximum(sq, 0.0)) <= r))
    n_c, n_k = int(corners.size), int(curves.size)
    return dict(
        n_corners=n_c, n_corners_meshed=int(corner_ok.sum()),
        corner_fraction=float(corner_ok.mean()) if n_c else float("nan"),
        n_curves=n_k, n_curves_meshed=int((coverage >= 1.0).sum()),
        curve_fraction=float((coverage >= 1.0).mean()) if n_k else float("nan"),
        curve_coverage=coverage,
    )
