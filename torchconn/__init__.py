"""torchconn: discrete connections on cell complexes in PyTorch.

Layers, each importing only the ones above it:

* :mod:`torchconn.tolerances` -- the one per-dtype registry of thresholds and tolerances;
* :mod:`torchconn.ops` -- kernels (compiled C and fused torch) and the choice between them;
* :mod:`torchconn.lie` -- ``so3`` and ``son``;
* :mod:`torchconn.mesh` -- ``TetMesh``, ``CellComplex``, I/O and built-in meshes;
* :mod:`torchconn.dec` -- the report: transport, connection, smooth, curvature, chains, torsion,
  dnabla, bianchi;
* :mod:`torchconn.nn` -- ``nn.Module`` wrappers;
* :mod:`torchconn.frames` -- the application: octahedral frame fields on tet meshes.
* :mod:`torchconn.hexmesh` -- hexahedral meshes from frame fields (integer-grid map, extraction).

The report's modules are also reachable from the top level (``torchconn.so3``,
``torchconn.curvature``, ...). The core (``tolerances`` ... ``nn``) never imports the
application: ``torchconn.frames`` is a lazy attribute (PEP 562), imported on first access, so
``import torchconn`` loads the core only. See README.md and docs/architecture.md.

Threads: when ``import torchconn`` is what loads torch (the console scripts, ``python -m
training.*``, a script importing torchconn first) and ``OMP_WAIT_POLICY`` is unset, it is set to
``PASSIVE`` first: torch's OpenMP threads then sleep at a barrier instead of spinning ~300k
iterations, so a core held by another process no longer multiplies the step time
(``benchmarks/under_load.py``: a training step with two threads and a spinner on one core 8-15x the
one-thread time with the variable unset, 1.3-1.4x with ``PASSIVE``). Where torch is imported first the
variable is left alone (libgomp reads it once, when torch loads it); set it yourself, or
``OMP_WAIT_POLICY=ACTIVE`` to keep the spinning.
"""
from __future__ import annotations

import os
import sys

if "torch" not in sys.modules:  # libgomp reads the variable when torch loads it (docstring)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import importlib  # noqa: E402

from . import dec, lie, mesh, nn, ops, tolerances  # noqa: E402
from .dec import bianchi, chains, connection, curvature, dnabla, smooth, torsion, transport
from .dec.bianchi import BianchiError
from .dec.connection import Connection
from .dec.smooth import FunctionConnection, ReportConnection, SmoothConnection, evaluate_2form, unit_normal
from .lie import so3, son
from .mesh import (
    CellComplex, FaceGroup, MeshError, TetMesh, TetMeshBatch, ball, box, cylinder, io, join_meshes, load_mesh,
    load_polygon_surface, load_surface, load_tet_mesh, tet_mesh_as_cell_complex, tetrahedralize, torus,
)
from .nn import AveragedCovariantD, BianchiCheck, ConnectionField, CovariantD, Curvature, Torsion
from .tolerances import get_eps

__version__ = "0.1.0"

#: Subpackages of the application, imported on first attribute access (PEP 562).
_LAZY_SUBPACKAGES = ("frames", "hexmesh")

__all__ = [
    # submodules
    "lie", "mesh", "ops", "dec", "nn", "frames", "hexmesh", "tolerances",
    "so3", "son", "io", "transport", "connection", "smooth", "curvature", "chains", "torsion", "dnabla", "bianchi",
    # meshes
    "TetMesh", "TetMeshBatch", "join_meshes", "CellComplex", "FaceGroup", "MeshError", "tet_mesh_as_cell_complex",
    "load_tet_mesh", "load_surface", "load_polygon_surface", "load_mesh", "tetrahedralize",
    "box", "ball", "cylinder", "torus",
    # connections
    "Connection", "ConnectionField", "SmoothConnection", "FunctionConnection", "ReportConnection",
    "evaluate_2form", "unit_normal",
    # modules and invariants
    "Curvature", "Torsion", "CovariantD", "AveragedCovariantD", "BianchiCheck", "BianchiError",
    "get_eps", "__version__",
]


def __getattr__(name: str):
    """Import the application subpackage ``torchconn.<name>`` on first access (PEP 562)."""
    if name in _LAZY_SUBPACKAGES:
        # The import binds torchconn.<name> as an attribute, so later accesses skip this hook.
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
