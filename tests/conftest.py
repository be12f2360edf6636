"""Shared pytest fixtures: the shared test-mesh folder and seeded generators."""
from __future__ import annotations

import os
import sys
from pathlib import Path

# Before torch loads, as ``import torchconn`` does for its users (torchconn/__init__.py): torch's
# OpenMP threads sleep at a barrier instead of spinning. Without it (pytest imports torch here,
# first), a hex-mesh test on 2 cores with one held by another process ran 3-5x longer
# (test_complex_singularity_...: 35.7 s spinning, 11.6 s passive). A value already set is kept.
if "torch" not in sys.modules:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest  # noqa: E402
import torch  # noqa: E402

# ../shared/data beside the repository (DEVELOPERS.md); overridable for other layouts.
DATA_DIR = Path(os.environ.get("TORCHCONN_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def hexme_mesh(name: str):
    """The float64 ``TetMesh`` of the HexMe parameter file ``DATA_DIR/hexme/meta/<name>.yaml``
    (meshed by gmsh); the test is skipped, with the reason, without gmsh or the shared data."""
    pytest.importorskip("gmsh", reason="CAD input needs gmsh (pip install 'torchconn[cad]')")
    path = DATA_DIR / "hexme" / "meta" / f"{name}.yaml"
    if not path.is_file():
        pytest.skip(f"HexMe parameter file {path} not found (the shared data folder is absent)")
    from torchconn.mesh.cad import load_hexme

    return load_hexme(path, dtype=torch.float64)



def assert_hvp_matches_fd(f, w: torch.Tensor, v: torch.Tensor, h: float = 1e-5, tol: float = 1e-6) -> None:
    """The Hessian-vector product of the scalar ``f`` at ``w`` along ``v`` (double backward) equals the
    central difference of its gradient, ``(grad f(w + h v) - grad f(w - h v)) / 2h``."""
    def grad(z):
        z = z.clone().requires_grad_()
        return torch.autograd.grad(f(z), z)[0]

    _, hv = torch.autograd.functional.hvp(f, w, v)
    fd = (grad(w + h * v) - grad(w - h * v)) / (2 * h)
    torch.testing.assert_close(hv, fd, atol=tol, rtol=tol)


TET_MESHES = ["sphere_r0.17.mesh", "78322_gear.2.mesh", "dinosaur.msh"]
SURFACES = ["bunny.obj", "fandisk.ply", "rocker_arm.ply"]


def data_path(name: str) -> Path:
    """Path of a shared test mesh, or skip the test with a clear reason when it is absent."""
    p = DATA_DIR / name
    if not p.exists():
        pytest.skip(f"shared test mesh {name} not found in {DATA_DIR} (set TORCHCONN_DATA to its folder)")
    return p


@pytest.fixture
def gen() -> torch.Generator:
    """A CPU generator seeded identically for every test."""
    return torch.Generator().manual_seed(1234)


def _device_params() -> list:
    """CPU always; CUDA when present, else a skipped case that says why (never silently absent)."""
    params = [pytest.param("cpu", id="cpu")]
    if torch.cuda.is_available():
        params.append(pytest.param("cuda", id="cuda"))
    else:
        params.append(pytest.param("cuda", id="cuda", marks=pytest.mark.skip(
            reason="no CUDA device on this machine (torch.cuda.is_available() is False)")))
    return params


DEVICES = _device_params()


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Every device present: ``cpu``, and ``cuda`` when available (skipped with a reason otherwise)."""
    return torch.device(request.param)


# The default suite's budget is ~5 min on 2 cores (DEVELOPERS.md). These tests took 8-90 s each in
# a full run on 2 loaded cores (2026-11-26, `pytest --durations=80`); each has a faster sibling that
# stays in the default suite (another parametrization, or a test of the same path on a smaller case).
# They run with `python -m pytest -m slow`.
SLOW_IDS = frozenset({
    "tests/test_train_frames.py::test_hydra_multirun",  # sibling: the single-run job tests of this file
    "tests/test_train_frames.py::test_cli_end_to_end",  # sibling: test_cli_unknown_key_exits_nonzero, test_resume_equals_uninterrupted
    "tests/test_train_frames.py::test_resume_is_bitwise_and_frames_equal_design",  # sibling: test_resume_equals_uninterrupted
    "tests/test_ops_library_tet.py::test_gradcheck_and_gradgradcheck[generic]",  # sibling: [compiled]
    "tests/test_ops_library_tet.py::test_gradgradcheck_through_skew_parameters[False-generic]",
    "tests/test_ops_library_tet.py::test_gradgradcheck_through_skew_parameters[False-compiled]",
    "tests/test_ops_library_tet.py::test_gradgradcheck_through_skew_parameters[True-generic]",  # sibling: [True-compiled]
    "tests/test_ops_library_frame_loss.py::test_opcheck_backward_aot_dispatch[compiled-float64]",
    "tests/test_ops_library_frame_loss.py::test_gradcheck_and_gradgradcheck[torch]",  # sibling: [compiled]
    "tests/test_robust_job.py::test_resume_from_weights_only_checkpoint",
    "tests/test_robust_job.py::test_finished_run_leaves_no_temporary_files",  # sibling: test_failing_writer_...
    "tests/test_ops_library_so3.py::test_opcheck_full[log-dtype2-True]",
    "tests/test_ops_library_so3.py::test_opcheck_full[exp-dtype2-True]",  # siblings: the other dtypes
    "tests/test_second_order.py::test_functional_averaged_dd_solder_gradgradcheck[frames]",
    "tests/test_second_order.py::test_functional_averaged_dd_solder_gradgradcheck[sqrt]",  # sibling: [half_exp]
    "tests/test_design.py::test_resume_from_state_equals_uninterrupted",  # sibling: test_train_frames resume
    "tests/test_design.py::test_design_equals_cli_frames_bitwise",
    "tests/test_design.py::test_callback_sees_every_step_and_stops_early",
    "tests/test_cad.py::test_connection_method_follows_the_cad_curves[notch]",  # sibling: [prism]
    "tests/test_ops_library_curvature.py::test_curvature_opcheck_full[dtype2-True]",
    "tests/test_sh_baseline.py::test_gear_runs_and_aligns",
})


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`SLOW_IDS` ``slow`` (before ``-m 'not slow'`` deselects)."""
    known = set()
    for item in items:
        if item.nodeid in SLOW_IDS:
            item.add_marker(pytest.mark.slow)
            known.add(item.nodeid)
    stale = SLOW_IDS - known
    if stale and len(items) > 2000:  # a full collection: every listed id must still exist
        raise pytest.UsageError(f"tests/conftest.py SLOW_IDS names tests that no longer exist: {sorted(stale)}")
