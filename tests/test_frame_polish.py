"""torchconn.frames.polish: the guarded frames-only polish."""
from __future__ import annotations

import pytest
import torch

from torchconn import io, so3
from torchconn.frames import frame_metrics, sh
from torchconn.frames.polish import polish_frames


@pytest.fixture(scope="module")
def cyl():
    m = io.cylinder(edge_length=0.6).to(dtype=torch.float64)
    return m, sh.sh_frame_field(m, n_smooth_iters=0)


def test_polish_lowers_the_metric_within_the_guard(cyl):
    m, F0 = cyl
    before = frame_metrics(F0, m)
    F, info = polish_frames(m, F0, steps=60, lr=0.01, check_every=20)
    after = frame_metrics(F, m)
    so3.check_rotation(F)
    assert info["accepted_step"] > 0 and len(info["checks"]) == 4
    assert after["smoothness_mean_deg"] < before["smoothness_mean_deg"]
    assert after["n_singular_faces"] <= before["n_singular_faces"] and after["n_tets_one_singular_face"] == 0
    assert after["alignment_max_deg"] < 1e-6  # rotation about the normal only
    # the accepted checkpoint is the best admissible one
    ok = [c for c in info["checks"] if c[2] <= before["n_singular_faces"] and c[3] == 0]
    assert after["smoothness_mean_deg"] == pytest.approx(min(c[1] for c in ok), rel=1e-9)


def test_polish_guard_and_no_op(cyl):
    m, F0 = cyl
    F, info = polish_frames(m, F0, steps=20, check_every=10, max_singular_faces=-1)  # nothing admissible
    assert info["accepted_step"] == 0 and torch.equal(F, F0)
    F, info = polish_frames(m, F0, steps=0)
    assert torch.equal(F, F0) and info["checks"][0][0] == 0
    with pytest.raises(ValueError, match="check_every"):
        polish_frames(m, F0, steps=10, check_every=0)
