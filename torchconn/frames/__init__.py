"""Octahedral frame fields on tet meshes: the application of the connection library.

Modules, in the order of the method: :mod:`.octahedral` (the group O, matching, per-tet frames),
:mod:`.constraints` (boundary and feature constraints, built once per mesh), :mod:`.param`
(normal-constrained frame rotations); the start fields :mod:`.sh` (the spherical-harmonic baseline
of Ray et al. 2016) and :mod:`.mbo` (Palmer, Bommes & Solomon 2020); :mod:`.propagate` (spanning
tree, combing, parallel propagation), :mod:`.model` (matched connection, trainable model),
:mod:`.loss` and :mod:`.terms`, :mod:`.solver` (schedule, optimizer, loop); then
:mod:`.quality_paths` (the L-BFGS quality paths), :mod:`.candidates` (the candidates of the
connection method, made stage by stage, and their proxy choice); :mod:`.matching_search` (a
singular-structure search over edge matchings: a tool beside the method, which no longer runs it); :mod:`.metrics`, :mod:`.singular` (the singular graph), :mod:`.field_files`
(VTU files: :func:`write_frames_vtu`, :func:`read_frames_vtu` -> :class:`FramesVTU`, singular faces
and curves; ``.fra``, mouette's ``.frame``); :mod:`.design` (the whole method in one call:
:func:`design` -> :class:`FrameFieldResult`). Beside the method: :mod:`.kernels` (the frame-field
custom ops behind the loss and the quality paths), :mod:`.fixed_holonomy` (a tet field
re-optimized with its face matchings fixed).

>>> from torchconn import io
>>> from torchconn.frames import sh_frame_field, frame_metrics
>>> mesh = io.box(3)
>>> frames = sh_frame_field(mesh)          # (V, 3, 3); frames[i][:, k] = axis k at vertex i
>>> frame_metrics(frames, mesh)["n_singular_faces"]
0

The connection method in one call (no files written; ``method="sh"`` for the baseline):

>>> from torchconn.frames import design
>>> result = design(mesh, steps=5, sh={"n_smooth_iters": 2})
>>> result.vertex_frames.shape, result.tet_frames.shape == (mesh.n_tets, 3, 3)
(torch.Size([64, 3, 3]), True)
>>> len(result.history["total"]), result.metrics["invariants"]["bianchi_ok"]
(5, True)
"""
from . import propagate
from .constraints import BoundaryConstraint, feature_edges, feature_vertices
from .design import FrameFieldResult, design
from .metrics import METRIC_KEYS, axis_alignment_angle, face_closure, frame_metrics
from .field_files import (
    FramesVTU,
    read_fra,
    read_frames_vtu,
    read_mouette_frame,
    read_singular_curves_vtk,
    write_fra,
    write_frames_vtu,
    write_mouette_frame,
    write_singular_curves_vtk,
    write_singular_faces_vtu,
)
from .sh import (
    boundary_constraint,
    frame_to_sh,
    reference_sh,
    sh_basis,
    sh_frame_field,
    sh_generators,
    sh_rotation,
    sh_to_frame,
)
from .singular import SingularCurve, SingularGraph, singular_graph

__all__ = [
    "propagate",
    "design",
    "FrameFieldResult",
    "BoundaryConstraint",
    "METRIC_KEYS",
    "axis_alignment_angle",
    "feature_edges",
    "feature_vertices",
    "frame_metrics",
    "boundary_constraint",
    "frame_to_sh",
    "reference_sh",
    "sh_basis",
    "sh_frame_field",
    "sh_generators",
    "sh_rotation",
    "sh_to_frame",
    "singular_graph",
    "SingularGraph",
    "SingularCurve",
    "face_closure",
    "write_frames_vtu",
    "read_frames_vtu",
    "FramesVTU",
    "write_singular_faces_vtu",
    "write_singular_curves_vtk",
    "read_singular_curves_vtk",
    "write_fra",
    "read_fra",
    "write_mouette_frame",
    "read_mouette_frame",
]
