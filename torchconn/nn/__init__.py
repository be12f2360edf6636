"""``torch.nn`` modules over the functional core: mesh topology held as buffers, parameters
owned by the module, the math delegated to :mod:`torchconn.dec`."""
from . import field, modules
from .field import ConnectionField
from .modules import AveragedCovariantD, BianchiCheck, CovariantD, Curvature, MeshBuffers, Torsion, edge_rotations

__all__ = ["field", "modules", "ConnectionField", "Curvature", "Torsion", "CovariantD", "AveragedCovariantD",
           "BianchiCheck", "MeshBuffers", "edge_rotations"]
