"""Repair of the edge-based singular graph so that it is locally meshable (LMFF, Liu & Bommes 2023).

With one frame per tet the singular graph lives on mesh edges, set by the face matchings
(:mod:`torchconn.hexmesh.cut`). The repair changes matchings on disks of faces, which moves
singular arcs across the disks without changing the frames:

* :mod:`.graph`: :class:`SingularGraph`, the matchings with LMFF's edge and vertex classes
  (exactly those of :func:`~torchconn.hexmesh.meshability.meshability_report`), updated face by
  face, and the repair cost;
* :mod:`.disk`: the disk re-solve (:func:`solve_disk`), the one-ring cone, the link paths and
  the least-area disk spanning a loop (:func:`spanning_disk`);
* :mod:`.ops`: the operations (push a curve off the boundary, move an arc off a boundary vertex,
  slide an arc's end that touches the boundary about a tangent axis along the surface, detach an arc from an invalid node, zip a zipper node, retract a hook through the boundary,
  repair a feature sector);
* :mod:`.driver`: :func:`repair_singular_graph`, the rounds and the :class:`RepairReport`.
"""
from .disk import MeshLookup, cone_disk, link_path, solve_disk, spanning_disk
from .driver import RepairReport, repair_singular_graph
from .graph import REPAIR_WEIGHTS, SingularGraph
from .ops import (MOVE_KINDS, Move, best_move, detach_arc, move_off_boundary, push_inside, repair_feature_sector,
                  retract_hook, slide_touching_end, zip_zipper)

__all__ = ["repair_singular_graph", "RepairReport", "SingularGraph", "REPAIR_WEIGHTS", "MeshLookup", "solve_disk",
           "cone_disk", "spanning_disk", "link_path", "Move", "MOVE_KINDS", "best_move", "push_inside",
           "move_off_boundary", "slide_touching_end", "detach_arc", "zip_zipper", "retract_hook", "repair_feature_sector"]
