"""The one switch of the compiled kernels (torchconn.ops.backend) and the layering of kernel choice."""
import ast
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import torch

import torchconn.ops
from torchconn import io, so3
from torchconn.frames.loss import FrameFieldLoss, TERMS
from torchconn.ops import backend, native

PACKAGE = Path(torchconn.ops.__file__).resolve().parent.parent


def test_context_manager_restores_previous_state():
    before = torchconn.ops.compiled_enabled()
    try:
        for outer in (True, False):
            torchconn.ops.set_compiled(outer)
            with torchconn.ops.compiled(not outer):
                assert torchconn.ops.compiled_enabled() is (not outer)
                with torchconn.ops.compiled(outer):
                    assert torchconn.ops.compiled_enabled() is outer
                assert torchconn.ops.compiled_enabled() is (not outer)
            assert torchconn.ops.compiled_enabled() is outer
            with pytest.raises(RuntimeError, match="inside"):  # restored on an exception too
                with torchconn.ops.compiled(not outer):
                    raise RuntimeError("inside")
            assert torchconn.ops.compiled_enabled() is outer
    finally:
        torchconn.ops.set_compiled(before)


def test_switch_is_global_across_threads():
    seen = []
    with torchconn.ops.compiled(False):
        t = threading.Thread(target=lambda: seen.append(torchconn.ops.compiled_enabled()))
        t.start()
        t.join()
    assert seen == [False]


def test_switch_off_never_uses_compiled():
    x = torch.zeros(2, 3, dtype=torch.float64)
    with torchconn.ops.compiled(False):
        assert not torchconn.ops.can_use_compiled("so3", x)
        assert not torchconn.ops.can_use_compiled("frame_loss", x)


@pytest.mark.skipif(native.library("so3") is None or native.library("frame_loss") is None,
                    reason="no C compiler: nothing to switch")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_switch_off_equals_compiled_path(dtype):
    tol = {torch.float32: 2e-5, torch.float64: 1e-12}[dtype]
    mesh = io.box(2).to(dtype=dtype)
    g = torch.Generator().manual_seed(0)
    w = 0.3 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=torch.float64)
    phi = 0.3 * torch.randn(mesh.n_vertices, 3, generator=g, dtype=torch.float64)
    loss = FrameFieldLoss(mesh, {k: 1.0 for k in TERMS})

    def run():
        ww, pp = w.to(dtype).requires_grad_(), phi.to(dtype).requires_grad_()
        R = so3.exp(ww)
        out = {"exp": R, "log": so3.log(R), "sqrt": so3.sqrt(R), **loss(R, so3.exp(pp))}
        out["total"].backward()
        return {k: v.detach() for k, v in out.items()}, ww.grad, pp.grad

    with torchconn.ops.compiled(True):
        assert torchconn.ops.can_use_compiled("so3", w.to(dtype))
        on, gw_on, gp_on = run()
    with torchconn.ops.compiled(False):
        off, gw_off, gp_off = run()
    assert on.keys() == off.keys()
    for k in on:
        torch.testing.assert_close(on[k], off[k], atol=tol, rtol=0)
    scale = max(1.0, float(gw_off.abs().max()), float(gp_off.abs().max()))
    torch.testing.assert_close(gw_on, gw_off, atol=tol * scale, rtol=0)
    torch.testing.assert_close(gp_on, gp_off, atol=tol * scale, rtol=0)


def test_environment_variable_initializes_the_switch():
    """A fresh process started with ``TORCHCONN_NATIVE=0`` has the switch off from its import on
    (one process: ~10 s on 2 loaded cores; the values are read by ``_from_env``, tested below)."""
    env = {**os.environ, "TORCHCONN_NATIVE": "0"}
    code = "import torchconn.ops as o; print(o.compiled_enabled())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    # and this process, started without the variable set to an off value, started with it on
    assert torchconn.ops.compiled_enabled() == backend._from_env()


@pytest.mark.parametrize("value,expected", [("0", False), ("off", False), ("FALSE", False), ("no", False),
                                            (" No ", False), ("1", True), ("", True), ("yes", True), (None, True)])
def test_environment_variable_values(value, expected, monkeypatch):
    """The value the switch starts from, for each spelling (``None``: the variable unset)."""
    if value is None:
        monkeypatch.delenv("TORCHCONN_NATIVE", raising=False)
    else:
        monkeypatch.setenv("TORCHCONN_NATIVE", value)
    assert backend._from_env() is expected


#: The kernel packages: the core ops and the frame-field ops (torchconn/frames/kernels, whose C
#: sources ops.native builds). Only they may load compiled code; each op asks ops.backend.
KERNEL_PACKAGES = (("ops",), ("frames", "kernels"))


def _modules_outside_ops():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if not any(rel.parts[:len(k)] == k for k in KERNEL_PACKAGES):
            yield rel, path.read_text(encoding="utf-8")


def test_no_kernel_choice_outside_ops():
    """Only the kernel packages mention the compiled kernels; nobody else imports ops.native."""
    offenders = []
    for rel, text in _modules_outside_ops():
        if "native" in text:
            offenders.append(f"{rel}: mentions 'native'")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom):
                names = {a.name for a in node.names}
                if (node.module or "").endswith("ops.native") or ("native" in names and "ops" in (node.module or "")):
                    offenders.append(f"{rel}: imports ops.native")
            elif isinstance(node, ast.Import) and any(a.name.endswith("ops.native") for a in node.names):
                offenders.append(f"{rel}: imports ops.native")
    assert not offenders, offenders


def test_frame_kernels_choose_through_the_one_switch():
    """The frame-field kernels load their C code through ops.native and ask ops.backend (no switch
    of their own); their libraries build from frames/kernels/csrc."""
    import torchconn.frames.kernels as fk

    for path in sorted((PACKAGE / "frames" / "kernels").glob("*.py")):
        text = path.read_text(encoding="utf-8")
        if "_native.declare" in text:
            assert "can_use_compiled" in text, path.name
        assert "set_compiled" not in text and "TORCHCONN_NATIVE" not in text, path.name
    for name in ("frame_loss", "edge_terms"):
        assert native._source(name) == fk.CSRC / f"{name}.c"


def test_ops_imports_no_upper_layer():
    """ops/ sits below lie, mesh, dec, nn and frames: it imports none of them."""
    upper = ("lie", "mesh", "dec", "nn", "frames")
    offenders = []
    for path in sorted((PACKAGE / "ops").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                mod = node.module or ""
                parts = mod.split(".")
                if (node.level >= 2 and parts[0] in upper) or (mod.startswith("torchconn.")
                                                                and parts[1] in upper):
                    offenders.append(f"{path.name}: {'.' * node.level}{mod}")
            elif isinstance(node, ast.Import):
                offenders += [f"{path.name}: {a.name}" for a in node.names
                              if a.name.startswith("torchconn.") and a.name.split(".")[1] in upper]
    assert not offenders, offenders
