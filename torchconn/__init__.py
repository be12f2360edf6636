"""torchconn: discrete connections on cell complexes in PyTorch.

Functional core (``so3``, ``son``, ``transport``, ``curvature``, ``chains``, ``torsion``,
``dnabla``, ``bianchi``), cell complexes built once (``mesh``, ``io``), connections
(``connection``, ``smooth``), thin ``nn.Module`` wrappers (``modules``) and the frame-field
application (``octahedral``, ``frames``, ``losses``). See README.md and docs/architecture.md.
"""
from . import (
    bianchi,
    chains,
    connection,
    curvature,
    dnabla,
    frames,
    io,
    losses,
    mesh,
    modules,
    octahedral,
    smooth,
    so3,
    son,
    tolerances,
    torsion,
    transport,
)
from .bianchi import BianchiError
from .connection import Connection, ConnectionField
from .io import ball, box, cylinder, load_mesh, load_polygon_surface, load_surface, load_tet_mesh, tetrahedralize, torus
from .mesh import CellComplex, FaceGroup, MeshError, TetMesh, tet_mesh_as_cell_complex
from .modules import AveragedCovariantD, BianchiCheck, CovariantD, Curvature, Torsion
from .smooth import FunctionConnection, ReportConnection, SmoothConnection, evaluate_2form, unit_normal
from .tolerances import get_eps

__version__ = "0.1.0"

__all__ = [
    # submodules
    "bianchi", "chains", "connection", "curvature", "dnabla", "frames", "io", "losses", "mesh", "modules",
    "octahedral", "smooth", "so3", "son", "tolerances", "torsion", "transport",
    # meshes
    "TetMesh", "CellComplex", "FaceGroup", "MeshError", "tet_mesh_as_cell_complex",
    "load_tet_mesh", "load_surface", "load_polygon_surface", "load_mesh", "tetrahedralize",
    "box", "ball", "cylinder", "torus",
    # connections
    "Connection", "ConnectionField", "SmoothConnection", "FunctionConnection", "ReportConnection",
    "evaluate_2form", "unit_normal",
    # modules and invariants
    "Curvature", "Torsion", "CovariantD", "AveragedCovariantD", "BianchiCheck", "BianchiError",
    "get_eps", "__version__",
]
