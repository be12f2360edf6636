"""``torch.nn`` modules over the functional core: mesh topology held as buffers, parameters
owned by the module, the math delegated to :mod:`torchconn.dec`."""
from . import modules
from .modules import AveragedCovariantD, BianchiCheck, CovariantD, Curvature, MeshBuffers, Torsion, edge_rotations

__all__ = ["modules", "Curvature", "Torsion", "CovariantD", "AveragedCovariantD", "BianchiCheck", "MeshBuffers",
           "edge_rotations"]
