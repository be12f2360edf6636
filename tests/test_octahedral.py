"""Octahedral group, matching and matched holonomy against plain per-element references."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from torchconn import so3
from torchconn.frames import octahedral


def test_group_is_the_cube_rotation_group():
    G = octahedral.group(torch.float64)
    assert G.shape == (24, 3, 3)
    assert torch.equal(G[0], torch.eye(3, dtype=torch.float64))
    keys = {tuple(g.flatten().tolist()) for g in G}
    assert len(keys) == 24
    assert torch.allclose(torch.linalg.det(G), torch.ones(24, dtype=torch.float64))
    assert torch.equal(G @ G.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(24, 3, 3))
    # every entry is 0 or +-1 and every row has exactly one non-zero
    assert set(G.unique().tolist()) == {-1.0, 0.0, 1.0}
    assert torch.equal(G.abs().sum(-1), torch.ones(24, 3, dtype=torch.float64))
    # closed under products
    for a in G:
        for b in G:
            assert tuple((a @ b).flatten().tolist()) in keys


def test_group_follows_dtype_device():
    G = octahedral.group(torch.float32, "cpu")
    assert G.dtype == torch.float32 and G.device.type == "cpu"


def _match_naive(Fi, Fj):
    """Plain loop: the element minimizing ||Fi g - Fj||_F (first one on ties)."""
    G = octahedral.group(torch.float64)
    best, best_k = None, None
    for k in range(24):
        d = float(torch.linalg.norm(Fi @ G[k] - Fj))
        if best is None or d < best - 1e-12:
            best, best_k = d, k
    return best_k


def test_match_equals_brute_force(gen):
    Fi = so3.random_rotation(200, generator=gen, dtype=torch.float64)
    Fj = so3.random_rotation(200, generator=gen, dtype=torch.float64)
    idx, g = octahedral.match(Fi, Fj)
    G = octahedral.group(torch.float64)
    assert idx.shape == (200,) and g.shape == (200, 3, 3)
    assert torch.equal(g, G[idx])
    for n in range(200):
        assert int(idx[n]) == _match_naive(Fi[n], Fj[n])


def test_match_is_invariant_under_right_multiplication(gen):
    Fi = so3.random_rotation(50, generator=gen, dtype=torch.float64)
    Fj = so3.random_rotation(50, generator=gen, dtype=torch.float64)
    _, g = octahedral.match(Fi, Fj)
    for h in octahedral.group(torch.float64):
        _, gh = octahedral.match(Fi @ h, Fj)
        # the matched frame F_i g* does not depend on the representative of F_i
        assert torch.allclose((Fi @ h) @ gh, Fi @ g, atol=1e-12)
        assert torch.allclose(gh, h.T @ g, atol=1e-12)


def test_match_recovers_a_perturbed_group_element(gen):
    F = so3.random_rotation(64, generator=gen, dtype=torch.float64)
    G = octahedral.group(torch.float64)
    k = torch.randint(0, 24, (64,), generator=gen)
    axis = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=torch.float64), dim=-1)
    small = so3.exp(0.7 * axis)  # < 45 degrees: g stays the unique best match
    idx, _ = octahedral.match(F, F @ G[k] @ small)
    assert torch.equal(idx, k)


def test_closest_element(gen):
    G = octahedral.group(torch.float64)
    k = torch.randint(0, 24, (32,), generator=gen)
    # rotations by < 45 degrees are closer to I than to any other element (which is >= 90 deg away)
    axis = torch.nn.functional.normalize(torch.randn(32, 3, generator=gen, dtype=torch.float64), dim=-1)
    R = G[k] @ so3.exp(0.7 * axis)
    idx, g = octahedral.closest_element(R)
    assert torch.equal(idx, k) and torch.equal(g, G[k])


def test_bad_input_raises():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        octahedral.match(torch.zeros(3, 2), torch.zeros(3, 3))
    with pytest.raises(IndexError, match="outside"):
        octahedral.matched_rotations(torch.eye(3).expand(2, 3, 3), torch.tensor([[0, 5]]))
    with pytest.raises(ValueError, match=r"\(V, 3, 3\)"):
        octahedral.matched_rotations(torch.eye(3), torch.tensor([[0, 1]]))


def _two_tets():
    """Two tets sharing face (1,2,3): faces and tet_faces built by hand."""
    tets = [[0, 1, 2, 3], [1, 2, 3, 4]]
    faces = sorted({tuple(sorted(c)) for t in tets for c in itertools.combinations(t, 3)})
    tet_faces = [[faces.index(tuple(sorted(c))) for c in (t[1:], [t[0]] + t[2:], t[:2] + [t[3]], t[:3])] for t in tets]
    return torch.tensor(faces), torch.tensor(tet_faces)


def test_face_holonomy_matches_naive_loop(gen):
    V = 30
    frames = so3.random_rotation(V, generator=gen, dtype=torch.float64)
    faces = torch.tensor(list(itertools.combinations(range(8), 3)))
    H = octahedral.face_matched_holonomy(frames, faces)
    G = octahedral.group(torch.float64)

    def g(i, j):
        if i < j:
            return G[_match_naive(frames[i], frames[j])]
        return G[_match_naive(frames[j], frames[i])].T

    for f, (a, b, c) in enumerate(faces.tolist()):
        ref = g(a, b) @ g(b, c) @ g(c, a)
        assert torch.equal(H[f], ref)
    # consistency with per-edge matching
    edges = torch.tensor([[0, 1], [1, 2], [0, 2]])
    ge = octahedral.matched_rotations(frames, edges)
    assert torch.equal(H[0], ge[0] @ ge[1] @ ge[2].T)


def test_singular_faces_and_tets():
    faces, tet_faces = _two_tets()
    eye = torch.eye(3, dtype=torch.float64)
    # a smooth field: no singular faces
    frames = eye.expand(5, 3, 3).clone()
    mask, sing = octahedral.singular_faces(frames, faces)
    assert not mask.any() and sing.shape == (0, 3)
    # frames about z at 0, 30, 60 degrees on vertices 0, 1, 2: edges 0-1 and 1-2 match with I
    # (30 deg residual), edge 0-2 (60 deg) matches with a quarter turn (30 deg residual), so the
    # loop 0-1-2 closes with a non-trivial holonomy: face (0,1,2) is singular.
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    frames = torch.stack([so3.exp(z * a) for a in (0.0, np.pi / 6, np.pi / 3, 0.0, 0.0)])
    mask, sing = octahedral.singular_faces(frames, faces)
    H = octahedral.face_matched_holonomy(frames, faces)
    ref = []
    for a, b, c in faces.tolist():
        Gs = octahedral.group(torch.float64)

        def g(i, j):
            return Gs[_match_naive(frames[i], frames[j])] if i < j else Gs[_match_naive(frames[j], frames[i])].T

        ref.append(not torch.equal(g(a, b) @ g(b, c) @ g(c, a), eye))
    assert mask.tolist() == ref
    assert mask[faces.tolist().index([0, 1, 2])]
    assert not torch.equal(H[faces.tolist().index([0, 1, 2])], eye)
    one = octahedral.tets_with_one_singular_face(mask, tet_faces)
    counts = [int(mask[tf].sum()) for tf in tet_faces]
    assert one.tolist() == [c == 1 for c in counts]


def _match_einsum_reference(Fi, Fj):
    """The previous implementation: 24 scores by einsum against the group, argmax."""
    G = octahedral.group(Fi.dtype)
    scores = torch.einsum("gab,...ab->...g", G, Fi.transpose(-1, -2) @ Fj)
    idx = scores.argmax(-1)
    return idx, G[idx]


def test_match_ties_go_to_the_lowest_index():
    s = math.sqrt(0.5)
    D = torch.float64
    Rz45 = torch.tensor([[s, -s, 0.0], [s, s, 0.0], [0.0, 0.0, 1.0]], dtype=D)  # halfway between two elements
    cases = torch.stack([torch.eye(3, dtype=D), Rz45, Rz45.T, torch.zeros(3, 3, dtype=D),
                         torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=D)])
    eye = torch.eye(3, dtype=D).expand_as(cases)
    idx, g = octahedral.match(eye, cases)
    for n in range(cases.shape[0]):
        assert int(idx[n]) == _match_naive(eye[n], cases[n])
    ref_idx, ref_g = _match_einsum_reference(eye, cases)
    assert torch.equal(idx, ref_idx) and torch.equal(g, ref_g)
    assert int(idx[3]) == 0  # all 24 scores tie at M = 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_match_agrees_with_einsum_reference_broadcast_and_empty(gen, dtype):
    Fi = so3.random_rotation(20, generator=gen, dtype=dtype).reshape(4, 5, 3, 3)[:, :1]  # (4, 1, 3, 3)
    Fj = so3.random_rotation(5, generator=gen, dtype=dtype)  # (5, 3, 3)
    idx, g = octahedral.match(Fi, Fj)
    ref_idx, ref_g = _match_einsum_reference(Fi, Fj)
    assert idx.shape == (4, 5) and g.shape == (4, 5, 3, 3) and g.dtype == dtype
    assert torch.equal(idx, ref_idx) and torch.equal(g, ref_g)
    R = so3.random_rotation(64, generator=gen, dtype=dtype)
    ci, cg = octahedral.closest_element(R)
    mi, mg = octahedral.match(torch.eye(3, dtype=dtype).expand_as(R), R)
    assert torch.equal(ci, mi) and torch.equal(cg, mg)
    e_idx, e_g = octahedral.match(torch.zeros(0, 3, 3, dtype=dtype), torch.zeros(0, 3, 3, dtype=dtype))
    assert e_idx.shape == (0,) and e_g.shape == (0, 3, 3)
