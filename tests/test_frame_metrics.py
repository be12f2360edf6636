"""frame_metrics against a slow per-element Python reference written from the definitions."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from torchconn import io, so3
from torchconn.frames import METRIC_KEYS, feature_edges, feature_vertices, frame_metrics
from torchconn.mesh import TetMesh


def _cube_group():
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            M = np.zeros((3, 3))
            for c, r in enumerate(perm):
                M[r, c] = signs[c]
            if np.linalg.det(M) > 0:
                mats.append(M)
    return mats


def _angle_between(u, v):
    c = np.clip(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)), -1.0, 1.0)
    return math.degrees(math.acos(c))


def _closest_axis_angle(F, n):
    return min(min(_angle_between(F[:, k], n), _angle_between(-F[:, k], n)) for k in range(3))


def _reference_metrics(frames, vertices, tets, angle_deg=30.0):
    """Plain loops over edges, faces, tets; its own topology (not the TetMesh buffers)."""
    G = _cube_group()
    # topology
    edges, faces = set(), {}
    for t in tets:
        for a, b in itertools.combinations(sorted(t), 2):
            edges.add((a, b))
        for f in itertools.combinations(sorted(t), 3):
            faces[f] = faces.get(f, 0) + 1
    # smoothness
    angles, sq = [], []
    match = {}
    for i, j in sorted(edges):
        dists = [np.linalg.norm(frames[i] @ g - frames[j]) for g in G]
        g = G[int(np.argmin(dists))]
        match[(i, j)] = g
        res = (frames[i] @ g).T @ frames[j]
        angles.append(math.degrees(math.acos(np.clip((np.trace(res) - 1) / 2, -1, 1))))
        sq.append(np.sum((frames[i] @ g - frames[j]) ** 2))
    # outward boundary faces: the face of a single tet, oriented away from the 4th vertex
    bfaces = []
    for t in tets:
        for f in itertools.combinations(t, 3):
            if faces[tuple(sorted(f))] == 1:
                (o,) = set(t) - set(f)
                a, b, c = f
                n = np.cross(vertices[b] - vertices[a], vertices[c] - vertices[a])
                if np.dot(n, vertices[o] - vertices[a]) > 0:
                    b, c = c, b
                bfaces.append((a, b, c))
    fnormal = []
    for a, b, c in bfaces:
        n = np.cross(vertices[b] - vertices[a], vertices[c] - vertices[a])
        fnormal.append(n)
    edge_faces = {}
    for fi, f in enumerate(bfaces):
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            edge_faces.setdefault((min(a, b), max(a, b)), []).append(fi)
    feat_edges = sorted(e for e, fs in edge_faces.items() if len(fs) == 2 and _angle_between(fnormal[fs[0]], fnormal[fs[1]]) > angle_deg)
    feat = {v for e in feat_edges for v in e}
    bverts = sorted({v for f in bfaces for v in f})
    al, fal = [], []
    for v in bverts:
        if v in feat:
            for fi, f in enumerate(bfaces):
                if v in f:
                    fal.append(_closest_axis_angle(frames[v], fnormal[fi]))
        else:
            n = sum(fnormal[fi] for fi, f in enumerate(bfaces) if v in f)  # |cross| = 2*area
            al.append(_closest_axis_angle(frames[v], n))

    def g(i, j):
        return match[(i, j)] if i < j else match[(j, i)].T

    sing, kind, valence = {}, {}, {}
    for a, b, c in faces:
        H = g(a, b) @ g(b, c) @ g(c, a)
        sing[(a, b, c)] = not np.allclose(H, np.eye(3))
        if sing[(a, b, c)]:
            # rotation angle and axis of H from their definitions (H = exp(theta [u]x))
            theta = math.degrees(math.acos(np.clip((np.trace(H) - 1) / 2, -1, 1)))
            wv, vecs = np.linalg.eig(H)
            u = np.real(vecs[:, np.argmin(np.abs(wv - 1))])
            on_axis = np.isclose(np.max(np.abs(u)), 1.0)
            kind[(a, b, c)] = ("quarter" if abs(theta - 90) < 1e-6 and on_axis else
                               "half" if abs(theta - 180) < 1e-6 and on_axis else "complex")
            if kind[(a, b, c)] == "quarter":
                s = np.array([H[2, 1] - H[1, 2], H[0, 2] - H[2, 0], H[1, 0] - H[0, 1]]) / 2
                n = np.cross(vertices[b] - vertices[a], vertices[c] - vertices[a])
                valence[(a, b, c)] = 3 if np.dot(frames[a] @ s, n) < 0 else 5
    tet_sing = [[f for f in itertools.combinations(sorted(t), 3) if sing[f]] for t in tets]
    one = sum(1 for fs in tet_sing if len(fs) == 1)
    # curves: singular faces linked through tets with exactly two of them (union-find)
    parent = {f: f for f in faces if sing[f]}

    def root(f):
        while parent[f] != f:
            f = parent[f]
        return f

    for fs in tet_sing:
        if len(fs) == 2:
            parent[root(fs[0])] = root(fs[1])
    curves = {root(f) for f in parent}
    inside = {root(fs[0]) for fs in tet_sing if len(fs) == 1}
    # integrability closure: matched frames carried to frame a along a -> b -> c, trapezoid rule
    curl = []
    for (a, b, c), cnt in faces.items():
        if cnt != 2:
            continue
        M = [frames[a], frames[b] @ g(a, b).T, frames[c] @ (g(a, b) @ g(b, c)).T]
        X = [vertices[a], vertices[b], vertices[c]]
        clos = sum(0.5 * (M[k] + M[(k + 1) % 3]).T @ (X[(k + 1) % 3] - X[k]) for k in range(3))
        perim = sum(np.linalg.norm(X[(k + 1) % 3] - X[k]) for k in range(3))
        curl.append(np.linalg.norm(clos) / perim)
    # feature-curve alignment: inside a curve (two feature edges turning by at most angle_deg) the
    # tangent is the sum of the two edge directions oriented alike; angle to the closest axis
    away = {}
    for i, j in feat_edges:
        d = (vertices[j] - vertices[i]) / np.linalg.norm(vertices[j] - vertices[i])
        away.setdefault(i, []).append(d)
        away.setdefault(j, []).append(-d)
    fca = []
    for vtx, us in away.items():
        if len(us) != 2:
            continue
        u1, u2 = us
        if np.degrees(np.arctan2(np.linalg.norm(np.cross(u1, -u2)), np.dot(u1, -u2))) > angle_deg:
            continue
        t = u1 + (1.0 if np.dot(u1, u2) >= 0 else -1.0) * u2
        t /= np.linalg.norm(t)
        a = frames[vtx][:, np.argmax(np.abs(frames[vtx].T @ t))]
        fca.append(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, t)), abs(np.dot(a, t)))))
    return {
        "feature_curve_alignment_mean_deg": float(np.mean(fca)) if fca else float("nan"),
        "feature_curve_alignment_max_deg": float(np.max(fca)) if fca else float("nan"),
        "smoothness_mean_deg": float(np.mean(angles)),
        "smoothness_rms_deg": float(np.sqrt(np.mean(np.square(angles)))),
        "smoothness_mean_sqfrob": float(np.mean(sq)),
        "alignment_mean_deg": float(np.mean(al)) if al else float("nan"),
        "alignment_max_deg": float(np.max(al)) if al else float("nan"),
        "feature_alignment_mean_deg": float(np.mean(fal)) if fal else float("nan"),
        "feature_alignment_max_deg": float(np.max(fal)) if fal else float("nan"),
        "n_feature_vertices": len(feat),
        "n_singular_faces": int(sum(sing.values())),
        "n_tets_one_singular_face": one,
        "dirichlet_energy_mean": float(np.mean(sq)),
        "n_singular_curves": len(curves),
        "n_singular_faces_quarter": sum(k == "quarter" for k in kind.values()),
        "n_singular_faces_half": sum(k == "half" for k in kind.values()),
        "n_singular_faces_complex": sum(k == "complex" for k in kind.values()),
        "n_singular_faces_valence3": sum(v == 3 for v in valence.values()),
        "n_singular_faces_valence5": sum(v == 5 for v in valence.values()),
        "n_singular_junctions": sum(1 for fs in tet_sing if len(fs) >= 3),
        "n_curves_ending_inside": len(inside),
        "curl_mean": float(np.mean(curl)),
        "curl_p95": float(np.quantile(curl, 0.95)),
    }, feat_edges


def _jittered_box(gen, n=3):
    """A box whose vertices are jittered (so normals are generic) but stay a valid mesh."""
    m = io.box(n)
    v = m.vertices + 0.03 / n * torch.randn(m.vertices.shape, generator=gen, dtype=m.vertices.dtype)
    return TetMesh(v, m.tets)


NOT_IN_REFERENCE = ("singular_valid_fraction",)  # needs the chained curve tangents: tests/test_singular.py


def _compare(met, ref):
    assert set(met) == set(METRIC_KEYS)
    v = met["singular_valid_fraction"]
    assert math.isnan(v) if met["n_singular_faces_quarter"] == 0 else 0.0 <= v <= 1.0
    for k in METRIC_KEYS:
        if k in NOT_IN_REFERENCE:
            continue
        if isinstance(ref[k], int):
            assert met[k] == ref[k], k
        elif math.isnan(ref[k]):
            assert math.isnan(met[k]), k
        else:
            # the reference uses acos (loses ~1e-8 rad near 0); the library uses atan2
            assert met[k] == pytest.approx(ref[k], rel=1e-6, abs=1e-5), k


@pytest.mark.parametrize("scale", [0.2, 3.0])
def test_metrics_equal_slow_reference_on_random_frames(gen, scale):
    m = _jittered_box(gen)
    # frames near a smooth field (scale 0.2, few singular faces) and fully random (scale 3)
    frames = so3.exp(scale * torch.randn(m.vertices.shape[0], 3, generator=gen, dtype=torch.float64))
    met = frame_metrics(frames, m)
    ref, ref_feat = _reference_metrics(frames.numpy(), m.vertices.numpy(), m.tets.tolist())
    _compare(met, ref)
    assert feature_edges(m).tolist() == [list(e) for e in ref_feat]
    assert met["n_feature_vertices"] > 0 and not math.isnan(met["alignment_mean_deg"])
    if scale > 1:
        assert met["n_singular_faces"] > 0


def test_metrics_on_a_smooth_ball_have_no_features(gen):
    m = io.ball(edge_length=0.5)
    frames = so3.random_rotation(m.vertices.shape[0], generator=gen, dtype=m.vertices.dtype)
    met = frame_metrics(frames, m)
    ref, _ = _reference_metrics(frames.numpy(), m.vertices.numpy(), m.tets.tolist())
    _compare(met, ref)
    assert met["n_feature_vertices"] == 0 and math.isnan(met["feature_alignment_mean_deg"])


def test_identity_frames_on_box_are_perfect():
    m = io.box(2)
    F = torch.eye(3, dtype=m.vertices.dtype).expand(m.vertices.shape[0], 3, 3)
    met = frame_metrics(F, m)
    assert met["smoothness_mean_deg"] < 1e-12 and met["n_singular_faces"] == 0
    assert met["feature_alignment_max_deg"] < 1e-12 and met["alignment_max_deg"] < 1e-12
    # box(2): all 8 corners and 12 edge midpoints (3x3x3 grid minus face and cell centres)
    assert met["n_feature_vertices"] == 20
    assert feature_vertices(m).numel() == 20


def test_metrics_bad_input():
    m = io.box(2)
    with pytest.raises(ValueError, match="shape"):
        frame_metrics(torch.eye(3).expand(5, 3, 3), m)
    with pytest.raises(TypeError, match="TetMesh"):
        frame_metrics(torch.eye(3).expand(5, 3, 3), object())
    with pytest.raises(ValueError, match="angle_deg"):
        feature_edges(m, angle_deg=-1.0)


def _slow_edge_classes(frames, m, near_rings=2):
    """Per-edge loop reference of edge_class_breakdown (same priority order)."""
    from torchconn.frames import octahedral

    F = frames.numpy()
    group = _cube_group()
    E = m.edges.tolist()
    ang = []
    for i, j in E:
        best = max(group, key=lambda g: np.trace(g.T @ F[i].T @ F[j]))
        R = (F[i] @ best).T @ F[j]
        ang.append(math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    feat = set(feature_vertices(m).tolist())
    bnd = set(m.boundary_vertices.tolist())
    surf = set()
    for a, b, c in m.boundary_faces.tolist():
        surf |= {tuple(sorted(p)) for p in ((a, b), (b, c), (a, c))}
    mask, _ = octahedral.singular_faces(frames, m)
    sing = {v for f in m.faces[mask].tolist() for v in f}
    near = set(sing)
    for _ in range(near_rings):
        near |= {v for i, j in E if i in near or j in near for v in (i, j)}
    out = {}
    for (i, j), a in zip(E, ang):
        if i in feat or j in feat:
            c = "feature"
        elif (i, j) in surf:
            c = "boundary_surface"
        elif i in bnd or j in bnd:
            c = "boundary_layer"
        elif i in sing or j in sing:
            c = "singular"
        elif i in near or j in near:
            c = "near_singular"
        else:
            c = "interior"
        out.setdefault(c, []).append(a)
    return out, float(np.sum(ang))


@pytest.mark.parametrize("scale", [0.15, 0.5])
def test_edge_class_breakdown_equals_slow_reference(gen, scale):
    from torchconn.frames.metrics import EDGE_CLASSES, edge_class_breakdown

    m = io.box(6)  # scale 0.15: every class non-empty; 0.5: singular faces everywhere inside
    frames = so3.exp(scale * torch.randn(m.vertices.shape[0], 3, generator=gen, dtype=torch.float64))
    b = edge_class_breakdown(frames, m)
    ref, total = _slow_edge_classes(frames, m)
    assert tuple(b) == EDGE_CLASSES
    assert sum(v["count"] for v in b.values()) == m.edges.shape[0]
    if scale < 0.3:
        assert all(b[k]["count"] > 0 for k in EDGE_CLASSES)
    for k in EDGE_CLASSES:
        assert b[k]["count"] == len(ref.get(k, [])), k
        if b[k]["count"]:
            assert b[k]["mean_deg"] == pytest.approx(np.mean(ref[k]), abs=1e-5), k
            assert b[k]["share"] == pytest.approx(np.sum(ref[k]) / total, abs=1e-7), k
    # the class means recompose the smoothness metric
    mean = sum(v["fraction"] * v["mean_deg"] for v in b.values() if v["count"])
    assert mean == pytest.approx(frame_metrics(frames, m)["smoothness_mean_deg"], rel=1e-12)
    assert sum(v["share"] for v in b.values()) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="near_rings"):
        edge_class_breakdown(frames, m, near_rings=-1)
