"""studies.frame_studies: the diagnostic studies of the smoothness metric on small meshes."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import io, so3
from torchconn.frames import frame_metrics
from studies import frame_studies as studies


def _about_z(theta):
    return so3.exp(torch.stack([torch.zeros_like(theta), torch.zeros_like(theta), theta], -1))


def test_constant_interior_field_on_box_is_exact_and_aligned(gen):
    m = io.box(3)
    F = studies.constant_interior_field(m, torch.eye(3, dtype=torch.float64))
    met = frame_metrics(F, m)
    assert met["smoothness_mean_deg"] < 1e-9 and met["n_singular_faces"] == 0
    R = so3.random_rotation(1, generator=gen, dtype=torch.float64)[0]
    met = frame_metrics(studies.constant_interior_field(m, R), m)
    assert met["alignment_max_deg"] < 1e-6  # every non-feature boundary vertex is snapped


def test_planar_l1_optimum_recovers_the_box_field(gen):
    m = io.box(3)
    theta = 0.1 * torch.randn(m.vertices.shape[0], generator=gen, dtype=torch.float64)
    F0 = _about_z(theta)
    assert frame_metrics(F0, m)["n_singular_faces"] == 0  # so the frozen structure is the box's
    F, obj = studies.planar_l1_optimum(m, F0, lam=1.0)
    met = frame_metrics(F, m)
    assert obj == pytest.approx(0.0, abs=1e-7)
    assert met["smoothness_mean_deg"] < 1e-6 and met["alignment_max_deg"] < 1e-6
    assert met["smoothness_mean_deg"] < frame_metrics(F0, m)["smoothness_mean_deg"]
    # the objective is the metric's own quantity: mean edge angle + lam * feature mean
    F1, obj1 = studies.planar_l1_optimum(m, F0, lam=0.0)
    assert obj1 == pytest.approx(frame_metrics(F1, m)["smoothness_mean_deg"], abs=1e-6)


def test_fixed_matching_descent_lowers_the_mean_angle(gen):
    m = io.box(3)
    F0 = so3.exp(0.15 * torch.randn(m.vertices.shape[0], 3, generator=gen, dtype=torch.float64))
    from torchconn.frames.sh import _snap_axis

    bv = m.boundary_vertices
    F0[bv] = _snap_axis(F0[bv], m.boundary_vertex_normals)
    F = studies.fixed_matching_descent(m, F0, rounds=2, steps=40, lr=0.02)
    before, after = frame_metrics(F0, m), frame_metrics(F, m)
    assert after["smoothness_mean_deg"] < 0.7 * before["smoothness_mean_deg"]
    assert after["alignment_max_deg"] < 1e-6  # rotation about the normal only
    so3.check_rotation(F)


def test_studies_cli(tmp_path, capsys):
    import meshio

    m = io.box(2)
    path = tmp_path / "box.mesh"
    meshio.write(str(path), meshio.Mesh(m.vertices.numpy(), [("tetra", m.tets.numpy())]))
    studies.main(["constint", "--mesh", str(path), "--restarts", "2", "--out", str(tmp_path / "f.npy")])
    assert "constint: smoothness 0.000" in capsys.readouterr().out
    np.savez(tmp_path / "frames.npz", frames=np.load(tmp_path / "f.npy"))
    studies.main(["planar_lp", str(tmp_path / "frames.npz"), "--mesh", str(path)])
    assert "LP objective 0.0000" in capsys.readouterr().out
