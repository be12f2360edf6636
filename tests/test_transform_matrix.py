"""Every public module and functional operator under every transform a PyTorch user applies (issue 24).

One matrix, case x transform x dtype x switch (``tests/transform_cases.py`` builds the cases: the
modules of :mod:`torchconn.nn`, ``ConnectionField``, the frame-field loss and ``so3.*`` as
functions of one input on ``io.box(1)``), each compared with eager autograd in the same dtype
with the compiled kernels on and off (``torchconn.ops.compiled``):

* ``eager``: ``torch.autograd.grad`` of the loss against central differences (float64);
* ``create_graph``: the Hessian-vector product by double backward against central differences
  of the gradient (float64);
* ``grad``, ``vmap_grad``: ``torch.func.grad`` (and ``vmap`` of it over two inputs) against
  ``torch.autograd.grad``;
* ``jacrev``, ``jacfwd``, ``jvp``: of a 3-vector projection of the output, against the
  Jacobian from ``torch.autograd.grad`` row by row;
* ``compile_eager``, ``compile_inductor`` (``torch.compile(fullgraph=True)``, value and
  gradient): in a fresh process with empty ``TORCHCONN_CACHE`` and inductor caches, the first
  call of a freshly built case (no warm-up); ``compile_eager_warm``: compiled again after the
  eager call. The full compile matrix is ``slow`` (one fresh process per case, ~1 min each on
  2 cores); the default suite runs issue 24's loss (so3.exp, Curvature, Torsion,
  AveragedCovariantD) with ``backend="eager"`` cold and warm, then inductor cold, in one
  subprocess (~20 s CPU; its kernel cache holds the C kernels built by the test process), and BianchiCheck's documented compile error in process (~1 s).

A combination either matches eager autograd or raises the documented error listed in
``transform_cases.DOCUMENTED_ERRORS`` (``BianchiCheck`` under ``vmap`` and ``torch.compile``: a
diagnostic that returns Python floats and raises). Cost of the non-compile matrix: ~16 s CPU.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import transform_cases as tcases
from torchconn import ops, so3
from torchconn.ops import native
from torchconn.tolerances import get_eps

HERE = Path(__file__).resolve().parent
_HAS_CC = native._compiler() is not None


def _switch(on: bool):
    if on and not _HAS_CC:
        pytest.skip("no C compiler: the compiled kernels cannot be built (the switch-off cases run)")
    return ops.compiled(on)


SWITCHES = [pytest.param(True, id="compiled"), pytest.param(False, id="generic")]
DTYPES = [pytest.param(torch.float32, id="float32"), pytest.param(torch.float64, id="float64")]


def test_every_so3_name_is_a_case_or_excluded_with_a_reason():
    missing = [n for n in so3.__all__ if f"so3.{n}" not in tcases.CASES and n not in tcases.SO3_NOT_OPERATORS]
    assert not missing, f"so3 names without a transform-matrix case or a stated reason: {missing}"


# ----------------------------------------------------------------------------- the checks

# Cases and eager references are built once per (case, dtype[, switch]) and shared by the
# transforms (the cases are deterministic; a diagnostic's record is cleared before each use).
_CASES: dict = {}
_REFS: dict = {}


def _case(name, dtype):
    if (name, dtype) not in _CASES:
        _CASES[name, dtype] = tcases.build(name, dtype)
    case = _CASES[name, dtype]
    case.record.clear()
    return case


def _ref(case, what: str, on: bool):
    """Eager reference ``what`` of ``case`` with the switch ``on``, computed once."""
    key = (case.name, case.x.dtype, on, what)
    if key not in _REFS:
        x, v = case.x, tcases.direction(case.x)
        if what == "grad":
            val = tcases.eager_grad(case, x)[1]
        elif what == "grad2":
            val = tcases.eager_grad(case, case.x2)[1]
        elif what == "jac":
            val = tcases.eager_jacobian(case, x)
        elif what == "fd":  # (loss(x + h v) - loss(x - h v)) / 2h in float64, h = 1e-6
            c64, x64, v64, h = _case(case.name, torch.float64), x.double(), v.double(), 1e-6
            with torch.no_grad():
                val = (tcases.loss(c64, x64 + h * v64) - tcases.loss(c64, x64 - h * v64)) / (2 * h)
        elif what == "fd_hvp":  # central difference of the float64 eager gradient along v, h = 1e-5
            c64, x64, v64, h = _case(case.name, torch.float64), x.double(), v.double(), 1e-5
            val = (tcases.eager_grad(c64, x64 + h * v64)[1] - tcases.eager_grad(c64, x64 - h * v64)[1]) / (2 * h)
        else:
            raise AssertionError(what)
        _REFS[key] = val
    return _REFS[key]


def _run(case, transform: str, dtype, on: bool):
    """``(result, reference, rtol)`` of one combination."""
    x, v = case.x, tcases.direction(case.x)
    loss = lambda z: tcases.loss(case, z)  # noqa: E731
    proj = lambda z: tcases.proj(case, z)  # noqa: E731
    if case.diagnostic and transform in ("eager", "create_graph"):
        # a diagnostic passes x through (fn(x) = x), and its values are off SO(3) under central
        # differences: the analytic gradient of the loss, x + c, and its Hessian along v, v
        z = x.detach().clone().requires_grad_()
        (g,) = torch.autograd.grad(loss(z), z, create_graph=transform == "create_graph")
        if transform == "eager":
            return g, x + tcases._weights(x), tcases.RTOL[dtype]
        return torch.autograd.grad((g * v).sum(), z)[0], v, tcases.RTOL[dtype]
    if transform == "eager":
        _, g = tcases.eager_grad(case, x)
        return (g.double() * v.double()).sum(), _ref(case, "fd", on), tcases.RTOL_FD[dtype]
    if transform == "create_graph":
        z = x.detach().clone().requires_grad_()
        (g,) = torch.autograd.grad(loss(z), z, create_graph=True)
        (hv,) = torch.autograd.grad((g * v).sum(), z)
        return hv, _ref(case, "fd_hvp", on), tcases.RTOL_FD[dtype]
    rtol = tcases.RTOL[dtype]
    if transform == "grad":
        return torch.func.grad(loss)(x), _ref(case, "grad", on), rtol
    if transform == "vmap_grad":
        ref = torch.stack([_ref(case, "grad", on), _ref(case, "grad2", on)])
        return torch.func.vmap(torch.func.grad(loss))(torch.stack((x, case.x2))), ref, rtol
    p0, J = _ref(case, "jac", on)
    if transform == "jacrev":
        return torch.func.jacrev(proj)(x), J, rtol
    if transform == "jacfwd":
        return torch.func.jacfwd(proj)(x), J, rtol
    if transform == "jvp":
        p, t = torch.func.jvp(proj, (x,), (v,))
        return torch.cat((p, t)), torch.cat((p0, (J * v).reshape(3, -1).sum(-1))), rtol
    raise AssertionError(transform)


@pytest.mark.parametrize("on", SWITCHES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("transform", tcases.TRANSFORMS)
@pytest.mark.parametrize("name", list(tcases.CASES))
def test_transform_matrix(name, transform, dtype, on):
    with _switch(on):
        case = _case(name, dtype)
        documented = tcases.DOCUMENTED_ERRORS.get((name, transform))
        if documented:
            with pytest.raises(Exception, match=documented):
                _run(case, transform, dtype, on)
            return
        got, ref, rtol = _run(case, transform, dtype, on)
        assert torch.isfinite(got).all(), f"{name} under {transform}: non-finite result"
        err = tcases.max_rel(got, ref)
        assert err <= rtol, f"{name} under {transform} ({dtype}): relative deviation {err:.2e} > {rtol:.0e}"
        if case.diagnostic:  # what the diagnostic returned inside the transform, against its eager value
            records = list(case.record)
            assert records, f"{name} was not called under {transform}"
            case.record.clear()
            case.fn(case.x)
            tol = get_eps("identity", dtype)
            for rec in records:
                assert rec == pytest.approx(case.record[0], rel=1e-6, abs=tol), (transform, rec, case.record)


# ----------------------------------------------------------------------------- compile (subprocess)

def _prebuilt_kernel_cache(folder: Path) -> None:
    """Fill ``folder`` with this process's built kernel libraries (``ops/csrc``: built here, or
    loaded from this process's cache) so the fresh process loads them instead of compiling them
    again with ``cc`` (~20 s on 2 cores); it still loads each one for the first time under
    ``torch.compile``. Building into an empty cache is tested by ``test_native.py``."""
    folder.mkdir(parents=True, exist_ok=True)
    for src in sorted(native.CSRC.glob("*.c")):
        lib = native.library(src.stem)
        if lib is not None:
            shutil.copy2(lib._name, folder / Path(lib._name).name)


def _compile_runner(tmp_path: Path, args: list[str], timeout: float, prebuilt: bool = False) -> list[dict]:
    """Run ``transform_cases.py`` in a fresh process with empty inductor caches and an empty
    torchconn kernel cache (``prebuilt``: one holding the kernels built here)."""
    env = dict(os.environ)
    env.update(TORCHCONN_CACHE=str(tmp_path / "torchconn"), TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "inductor"),
               TRITON_CACHE_DIR=str(tmp_path / "triton"))
    if prebuilt:
        _prebuilt_kernel_cache(tmp_path / "torchconn")
    proc = subprocess.run([sys.executable, str(HERE / "transform_cases.py"), *args], capture_output=True,
                          text=True, env=env, timeout=timeout, cwd=tmp_path)
    rows = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert proc.returncode == 0, f"compile runner failed (rc {proc.returncode}):\n{proc.stderr[-4000:]}"
    return rows


def _judge(row: dict) -> None:
    name, transform = row["case"], f"compile_{row['backend']}" + ("_warm" if row["when"] == "warm" else "")
    documented = tcases.DOCUMENTED_ERRORS.get((name, transform))
    tag = f"{name} under {transform} ({row['dtype']}, switch {row['switch']})"
    if documented:
        assert row["status"] == "error" and re.search(documented, row["error"], re.S), \
            f"{tag}: expected the documented error /{documented}/, got {row}"
        return
    assert row["status"] == "pass", f"{tag}: {row.get('error')}\n{row.get('where', '')}"
    rtol = tcases.RTOL[getattr(torch, row["dtype"])]
    assert row["value_rel"] <= rtol and row["grad_rel"] <= rtol, f"{tag}: deviates from eager autograd: {row}"


def test_compile_module_loss_fresh_process(tmp_path):
    """Issue 24's loss (``so3.exp`` -> ``Curvature``, ``Torsion``, ``AveragedCovariantD``, float64,
    compiled kernels on) under ``torch.compile(fullgraph=True)`` in a fresh process with empty
    caches: ``backend="eager"`` as the first call of fresh modules (the tet schedule and the
    curvature tables built while dynamo traces: NumPy on a fake tensor before the fix), again
    after an eager call (the guard on the vertex tensor's ``_version``), and inductor as the
    first call of other fresh modules; value and gradient against eager autograd. The kernel
    cache holds the libraries built by this process (loaded, not rebuilt, by the fresh one: the
    build is ``test_native.py``'s, and cost ~20 s here). ~25 s on 2 cores."""
    rows = _compile_runner(tmp_path, ["--cases", "pipeline", "--backends", "eager,inductor", "--dtypes", "float64",
                                      "--switch", "on"], timeout=600, prebuilt=True)
    assert [(r["backend"], r["when"]) for r in rows] == [("eager", "cold"), ("eager", "warm"), ("inductor", "cold")]
    for row in rows:
        _judge(row)


def test_bianchi_check_under_compile_names_itself_and_the_transform():
    """The documented error of the diagnostic under ``torch.compile(fullgraph=True)`` (in process,
    ``backend="eager"``: the trace stops at the excluded function, no compilation)."""
    case = tcases.build("BianchiCheck", torch.float64)
    with pytest.raises(torch._dynamo.exc.Unsupported, match=tcases._BIANCHI_COMPILE):
        torch.compile(lambda x: tcases.loss(case, x), fullgraph=True, backend="eager")(case.x)
    # without fullgraph it runs eagerly at the graph break
    val = torch.compile(lambda x: tcases.loss(case, x), backend="eager")(case.x)
    assert torch.isfinite(val) and case.record and case.record[-1]["algebraic"] < 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("name", [*tcases.COMPILE_ONLY, *tcases.CASES])
def test_compile_matrix(name, tmp_path):
    """Every case under ``torch.compile(fullgraph=True)``, backends eager and inductor, float32 and
    float64, compiled kernels on and off, each the first call of a freshly built case, in one
    fresh process per case with empty caches (``backend="eager"`` also warm). Rows are appended
    to the JSON-lines file ``$TRANSFORM_MATRIX_JSON`` when it is set (the report's table)."""
    rows = _compile_runner(tmp_path, ["--cases", name], timeout=3600)
    out = os.environ.get("TRANSFORM_MATRIX_JSON")
    if out:
        with open(out, "a") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in rows)
    assert len(rows) == 12, rows  # 2 dtypes x 2 switches x (eager cold, eager warm, inductor cold)
    for row in rows:
        _judge(row)
