"""The cases of the transform matrix (``tests/test_transform_matrix.py``, issue 24) and its
``torch.compile`` runner.

Every public module and functional operator is a :class:`Case`: a function ``fn(x) -> tensor``
of one floating input ``x`` on a tiny mesh (``io.box(1)``: 8 vertices, 19 edges, 6 tets), built
in a given dtype. The transforms act on two functions of ``x`` derived from ``fn`` (both
traceable: no eager call is needed to build them, so a compile case starts cold):

* the scalar loss ``loss(x) = ½ Σ out² + Σ c ⊙ out`` with fixed weights ``c = cos(0, 1, 2, ...)``;
* the projection ``proj(x) = P out.flatten()`` onto 3 fixed directions ``P[k, i] = cos(0.7 (k+1) i + k)``
  (small Jacobians for ``jacrev`` / ``jacfwd`` / ``jvp``).

The eager-autograd references (``torch.autograd.grad``) are computed by :func:`eager_grad` and
:func:`eager_jacobian`. *Diagnostic* cases (``BianchiCheck``) return Python floats instead of
a differentiable value: their ``fn`` records what the diagnostic returned and passes ``x``
through, and the test compares the record with the eager one.

Run as a script it is the compile runner (one fresh process per call; the test points
``TORCHCONN_CACHE`` and the inductor cache at an empty temporary folder)::

    python tests/transform_cases.py --cases Curvature,so3.exp --backends eager,inductor

prints one JSON line per (case, backend, dtype, switch, cold/warm) with ``status`` ``pass`` or
``error`` (the exception type and message) and the largest deviations from eager autograd.
Each combination builds its case anew (a fresh mesh and module: the compiled call is the
first call, no warm-up); ``warm`` recompiles the same objects after the eager reference ran.
"""
from __future__ import annotations

import argparse
import functools
import json
import time
import traceback
from dataclasses import dataclass, field
from typing import Callable

import torch

import torchconn as tc
from torchconn import io, ops, so3
from torchconn.dec import bianchi
from torchconn.ops import _so3_formulas

DTYPES = {"float32": torch.float32, "float64": torch.float64}
SWITCH = {"on": True, "off": False}
#: Relative tolerance of a transform against eager autograd in the same dtype (different kernels
#: may run: C under autograd and vmap, the generic formula under forward mode).
RTOL = {torch.float32: 1e-4, torch.float64: 1e-10}
#: Relative tolerance against central differences computed in float64 (the eager and the
#: double-backward rows: ``h = 1e-6`` for the loss, ``1e-5`` for its gradient).
RTOL_FD = {torch.float32: 1e-3, torch.float64: 1e-6}


@dataclass
class Case:
    """One operator as a function of one input: ``fn(x)`` with ``x`` and a second input ``x2``
    (the other item of the ``vmap`` batch), built in ``x.dtype``."""

    name: str
    x: torch.Tensor
    x2: torch.Tensor
    fn: Callable[[torch.Tensor], torch.Tensor]
    #: diagnostic cases: what each call returned (in call order)
    record: list = field(default_factory=list)
    diagnostic: bool = False


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _rotations(n: int, dtype, seed: int, scale: float = 0.5) -> torch.Tensor:
    """``n`` rotations ``exp(ω)``, ``ω ~ scale·N(0, 1)``, formed in float64 by the plain torch formula."""
    w = scale * torch.randn(n, 3, generator=_gen(seed), dtype=torch.float64)
    return _so3_formulas.exp(w).to(dtype)


def _randn(*shape, dtype, seed: int, scale: float = 1.0) -> torch.Tensor:
    return (scale * torch.randn(*shape, generator=_gen(seed), dtype=torch.float64)).to(dtype)


def _mesh():
    return io.box(1)


# ----------------------------------------------------------------------------- module cases

def _module_case(name: str, make_module, frames: str | None = None):
    """A module of :mod:`torchconn.nn` on edge rotations ``x (E, 3, 3)``, with fixed frames
    (``frames="fixed"``), or as a function of the frames ``x (V, 3, 3)`` with fixed rotations
    (``frames="input"``)."""
    def build(dtype):
        mesh = _mesh()
        mod = make_module(mesh)
        E, V = mesh.edges.shape[0], mesh.vertices.shape[0]
        if frames == "input":
            R0 = _rotations(E, dtype, 1)
            return Case(name, _rotations(V, dtype, 7), _rotations(V, dtype, 8), lambda x: mod(R0, x))
        F0 = _rotations(V, dtype, 7) if frames else None
        fn = (lambda x: mod(x, F0)) if frames else mod
        return Case(name, _rotations(E, dtype, 1), _rotations(E, dtype, 2), fn)
    return build


def _sqnorm_case(name: str, make_module, frames: bool = False):
    """A module's fused ``sqnorm`` (a 0-dim value: the value and gradient of one C sweep) on edge
    rotations ``x (E, 3, 3)``, with fixed frames when ``frames``."""
    def build(dtype):
        mesh = _mesh()
        mod = make_module(mesh)
        E, V = mesh.edges.shape[0], mesh.vertices.shape[0]
        args = (_rotations(V, dtype, 7),) if frames else ()
        return Case(name, _rotations(E, dtype, 1), _rotations(E, dtype, 2), lambda x: mod.sqnorm(x, *args))
    return build


def _bianchi_case(dtype):
    mesh = _mesh()
    check = tc.BianchiCheck(mesh)
    E = mesh.edges.shape[0]
    case = Case("BianchiCheck", _rotations(E, dtype, 1), _rotations(E, dtype, 2), None, diagnostic=True)

    def fn(x):
        case.record.append(check(x))
        return x * 1.0

    case.fn = fn
    return case


def _field_case(dtype):
    mesh = _mesh()
    E, V = mesh.edges.shape[0], mesh.vertices.shape[0]
    field_ = tc.ConnectionField(mesh.edges, V, dtype=dtype)
    return Case("ConnectionField", _randn(E, 3, dtype=dtype, seed=1, scale=0.5),
                _randn(E, 3, dtype=dtype, seed=2, scale=0.5),
                lambda x: torch.func.functional_call(field_, {"params": x}, ()).edge_rot)


def _frame_loss_case(which: str):
    def build(dtype):
        from torchconn.frames.loss import TERMS, FrameFieldLoss

        mesh = _mesh()
        loss = FrameFieldLoss(mesh, {k: 1.0 for k in TERMS})
        E, V = mesh.edges.shape[0], mesh.vertices.shape[0]
        R0, F0 = _rotations(E, dtype, 3, scale=0.2), _rotations(V, dtype, 4)

        def terms(R, F):
            out = loss(R, F)
            return torch.stack([out[k] for k in (*TERMS, "total")])

        if which == "rot":
            return Case("FrameFieldLoss(edge_rot)", R0, _rotations(E, dtype, 5, scale=0.2), lambda x: terms(x, F0))
        return Case("FrameFieldLoss(frames)", F0, _rotations(V, dtype, 6), lambda x: terms(R0, x))
    return build


# ----------------------------------------------------------------------------- so3 cases

N = 4  # elements per so3 case


def _so3_case(name: str, fn, make_x):
    def build(dtype):
        return Case(f"so3.{name}", make_x(dtype, 1), make_x(dtype, 2), fn)
    return build


def _vec(dtype, seed, scale=1.0):
    return _randn(N, 3, dtype=dtype, seed=seed, scale=scale)


def _rot(dtype, seed, scale=0.8):
    return _rotations(N, dtype, seed, scale)


def _mat(dtype, seed):
    return _randn(N, 3, 3, dtype=dtype, seed=seed)


def _so3_fn(name):
    """``so3.<name>`` looked up at call time (the cases table names functions a checkout may add)."""
    return lambda *a, **k: getattr(so3, name)(*a, **k)


SO3_CASES: dict[str, Callable] = {
    "hat": _so3_case("hat", _so3_fn("hat"), _vec),
    "vee": _so3_case("vee", _so3_fn("vee"), _mat),
    "exp": _so3_case("exp", _so3_fn("exp"), lambda d, s: _vec(d, s, 1.2)),
    # angles up to ~2.7 rad: the generic, small-angle and obtuse (axis from the symmetric part) branches
    "log": _so3_case("log", _so3_fn("log"), lambda d, s: _rot(d, s, 1.5)),
    # angles on both sides of 120° (the quaternion identity and exp(log/2))
    "sqrt": _so3_case("sqrt", _so3_fn("sqrt"), lambda d, s: _rot(d, s, 1.5)),
    "angle": _so3_case("angle", _so3_fn("angle"), _rot),
    "geodesic_distance": lambda dtype: Case(
        "so3.geodesic_distance", _rot(dtype, 1), _rot(dtype, 2),
        functools.partial(so3.geodesic_distance, R2=_rotations(N, dtype, 9))),
    "rot_x": _so3_case("rot_x", _so3_fn("rot_x"), lambda d, s: _randn(N, dtype=d, seed=s)),
    "rot_y": _so3_case("rot_y", _so3_fn("rot_y"), lambda d, s: _randn(N, dtype=d, seed=s)),
    "rot_z": _so3_case("rot_z", _so3_fn("rot_z"), lambda d, s: _randn(N, dtype=d, seed=s)),
    "euler_xyz": _so3_case("euler_xyz", lambda x: so3.euler_xyz(x[..., 0], x[..., 1], x[..., 2]), _vec),
    # random matrices: distinct singular values (the SVD backward is defined)
    "project_to_rotation": _so3_case("project_to_rotation", _so3_fn("project_to_rotation"), _mat),
    "quat_to_matrix": _so3_case(
        "quat_to_matrix", lambda x: torch.stack([so3.quat_to_matrix(x, convention=c) for c in ("wxyz", "xyzw")]),
        lambda d, s: _randn(N, 4, dtype=d, seed=s)),
    "matrix_to_quat": _so3_case(
        "matrix_to_quat", lambda x: torch.stack([so3.matrix_to_quat(x, convention=c) for c in ("wxyz", "xyzw")]),
        lambda d, s: _rot(d, s, 1.5)),
    "rot6d_to_matrix": _so3_case("rot6d_to_matrix", _so3_fn("rot6d_to_matrix"),
                                 lambda d, s: _randn(N, 6, dtype=d, seed=s)),
    "matrix_to_rot6d": _so3_case("matrix_to_rot6d", _so3_fn("matrix_to_rot6d"), _rot),
}

#: Names of ``so3.__all__`` that are not differentiable operators of an input, and why.
SO3_NOT_OPERATORS = {
    "random_rotation": "a sampler: its output is a function of the generator, not of a tensor input",
    "check_rotation": "a validation that raises or returns None (tests/test_so3.py); no output to differentiate",
    "QUAT_CONVENTIONS": "a constant (the quaternion storage orders)",
}

def _pipeline_case(dtype):
    """The researcher's loss of issue 24: skew parameters ``ω (E, 3)`` -> ``so3.exp`` ->
    ``Curvature``, ``Torsion``, ``AveragedCovariantD``, their squared values summed per module."""
    mesh = _mesh()
    curv, tors, dd = tc.Curvature(mesh), tc.Torsion(mesh), tc.AveragedCovariantD(mesh)
    E = mesh.edges.shape[0]

    def fn(w):
        R = so3.exp(w)
        return torch.stack((curv(R).square().sum(), tors(R).square().sum(), dd(R).square().sum()))

    return Case("pipeline", _randn(E, 3, dtype=dtype, seed=1, scale=0.5), _randn(E, 3, dtype=dtype, seed=2, scale=0.5), fn)


#: Cases of the compile runner only (a composition of the cases below, the loss of issue 24).
COMPILE_ONLY: dict[str, Callable] = {"pipeline": _pipeline_case}

CASES: dict[str, Callable] = {
    "Curvature": _module_case("Curvature", tc.Curvature),
    "Torsion": _module_case("Torsion", tc.Torsion),
    "Torsion(frames)": _module_case("Torsion(frames)", tc.Torsion, frames="fixed"),
    "Torsion(d/dframes)": _module_case("Torsion(d/dframes)", tc.Torsion, frames="input"),
    "CovariantD(behs21)": _module_case("CovariantD(behs21)", lambda m: tc.CovariantD(m, "behs21")),
    "CovariantD(wedge)": _module_case("CovariantD(wedge)", lambda m: tc.CovariantD(m, "wedge")),
    "AveragedCovariantD": _module_case("AveragedCovariantD", tc.AveragedCovariantD),
    "AveragedCovariantD(frames)": _module_case("AveragedCovariantD(frames)", tc.AveragedCovariantD,
                                               frames="fixed"),
    "AveragedCovariantD(d/dframes)": _module_case("AveragedCovariantD(d/dframes)", tc.AveragedCovariantD,
                                                  frames="input"),
    "Curvature.sqnorm": _sqnorm_case("Curvature.sqnorm", tc.Curvature),
    "Curvature(holonomy).sqnorm": _sqnorm_case("Curvature(holonomy).sqnorm", lambda m: tc.Curvature(m, kind="holonomy")),
    "AveragedCovariantD.sqnorm": _sqnorm_case("AveragedCovariantD.sqnorm", tc.AveragedCovariantD),
    "AveragedCovariantD(frames).sqnorm": _sqnorm_case("AveragedCovariantD(frames).sqnorm", tc.AveragedCovariantD,
                                                      frames=True),
    "BianchiCheck": _bianchi_case,
    "ConnectionField": _field_case,
    "FrameFieldLoss(edge_rot)": _frame_loss_case("rot"),
    "FrameFieldLoss(frames)": _frame_loss_case("frames"),
    **{f"so3.{k}": v for k, v in SO3_CASES.items() if k in so3.__all__},
}

#: The transforms of the matrix (``compile_*`` run in the subprocess runner below).
TRANSFORMS = ("eager", "create_graph", "grad", "vmap_grad", "jacrev", "jacfwd", "jvp")
COMPILE_TRANSFORMS = ("compile_eager", "compile_inductor", "compile_eager_warm")

#: ``(case, transform) -> regex`` of the documented error that the combination raises instead of
#: a result (the docstrings of the named operators state them).
_BIANCHI_COMPILE = r"BianchiCheck.*torch\.compile"
DOCUMENTED_ERRORS: dict[tuple[str, str], str] = {
    ("BianchiCheck", "vmap_grad"): r"BianchiCheck.*vmap",
    ("BianchiCheck", "compile_eager"): _BIANCHI_COMPILE,
    ("BianchiCheck", "compile_inductor"): _BIANCHI_COMPILE,
    ("BianchiCheck", "compile_eager_warm"): _BIANCHI_COMPILE,
}


def build(name: str, dtype: torch.dtype) -> Case:
    return {**CASES, **COMPILE_ONLY}[name](dtype)


# ----------------------------------------------------------------------------- loss, projection

def _weights(out: torch.Tensor) -> torch.Tensor:
    return torch.cos(torch.arange(out.numel(), dtype=out.dtype, device=out.device)).reshape(out.shape)


def loss(case: Case, x: torch.Tensor) -> torch.Tensor:
    """``½ Σ out² + Σ c ⊙ out`` of ``out = case.fn(x)`` (module doc)."""
    out = case.fn(x)
    return 0.5 * out.square().sum() + (_weights(out) * out).sum()


def proj(case: Case, x: torch.Tensor) -> torch.Tensor:
    """``P out.flatten()``: ``(3,)`` (module doc)."""
    out = case.fn(x).reshape(-1)
    i = torch.arange(out.numel(), dtype=out.dtype, device=out.device)
    P = torch.stack([torch.cos(0.7 * (k + 1) * i + k) for k in range(3)])
    return P @ out


def direction(x: torch.Tensor, seed: int = 11) -> torch.Tensor:
    """A fixed tangent / perturbation direction of ``x``'s shape, unit RMS."""
    return _randn(*x.shape, dtype=x.dtype, seed=seed)


# ----------------------------------------------------------------------------- eager references

def eager_grad(case: Case, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(loss(x), ∇loss(x))`` by ``torch.autograd.grad``."""
    x = x.detach().clone().requires_grad_()
    val = loss(case, x)
    return val.detach(), torch.autograd.grad(val, x)[0]


def eager_jacobian(case: Case, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(proj(x), ∂proj/∂x (3, *x.shape))``: three ``torch.autograd.grad`` calls."""
    x = x.detach().clone().requires_grad_()
    p = proj(case, x)
    rows = [torch.autograd.grad(p[k], x, retain_graph=k < 2)[0] for k in range(3)]
    return p.detach(), torch.stack(rows)


def max_rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """``max |a - b| / max |b|`` (norm-wise relative deviation of ``a`` from the reference ``b``)."""
    a, b = a.detach().double(), b.detach().double()
    if a.shape != b.shape:
        raise AssertionError(f"shape {tuple(a.shape)} differs from the reference's {tuple(b.shape)}")
    scale = float(b.abs().max()) if b.numel() else 0.0
    return float((a - b).abs().max()) / max(scale, 1e-300) if b.numel() else 0.0


# ----------------------------------------------------------------------------- compile runner

def run_compile(name: str, backend: str, dtype: torch.dtype, switch: bool) -> list[dict]:
    """Compile ``loss`` of a freshly built case (``fullgraph=True``) before any eager call, run it
    forward and backward, and compare with eager autograd; with ``backend="eager"`` also
    recompile the same objects after an eager call (warm: the tables and caches exist). Rows
    as in the module doc."""
    rows = []
    with ops.compiled(switch):
        case = build(name, dtype)
        rows.append(_compile_row(case, backend, "cold", dtype, switch))
        if backend == "eager":
            eager_grad(case, case.x)  # the eager call that fills the caches (tables, edge vectors)
            rows.append(_compile_row(case, backend, "warm", dtype, switch))
    return rows


def _compile_row(case: Case, backend: str, when: str, dtype, switch) -> dict:
    row = {"case": case.name, "backend": backend, "when": when, "dtype": str(dtype).replace("torch.", ""),
           "switch": "on" if switch else "off"}
    torch._dynamo.reset()
    cl = torch.compile(lambda x: loss(case, x), fullgraph=True, backend=backend)
    x = case.x.detach().clone().requires_grad_()
    t0 = time.perf_counter()
    try:
        val = cl(x)
        val.backward()
    except Exception as e:  # noqa: BLE001 - reported, and judged by the test
        row.update(status="error", error=f"{type(e).__name__}: {e}"[:4000],
                   where=traceback.format_exc()[-3000:])
        return row
    row["compile_s"] = round(time.perf_counter() - t0, 2)
    ref_val, ref_grad = eager_grad(case, case.x)
    row.update(status="pass", value_rel=max_rel(val, ref_val), grad_rel=max_rel(x.grad, ref_grad))
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--backends", default="eager,inductor")
    ap.add_argument("--dtypes", default="float32,float64")
    ap.add_argument("--switch", default="on,off")
    a = ap.parse_args(argv)
    for name in a.cases.split(","):
        for backend in a.backends.split(","):
            for dt in a.dtypes.split(","):
                for sw in a.switch.split(","):
                    for row in run_compile(name, backend, DTYPES[dt], SWITCH[sw]):
                        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
