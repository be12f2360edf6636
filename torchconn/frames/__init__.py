"""Octahedral frame fields on tet meshes: the application of the connection library.

Modules: :mod:`.octahedral` (the group O, matching), :mod:`.sh` (the spherical-harmonic baseline of
Ray et al. 2016), :mod:`.constraints` (boundary and feature constraints, built once per mesh),
:mod:`.param` (normal-constrained frame rotations), :mod:`.propagate` (spanning tree, combing,
parallel propagation), :mod:`.model` (matched connection, trainable model), :mod:`.loss`,
:mod:`.solver` (schedule, optimizer, loop), :mod:`.polish`, :mod:`.metrics`, :mod:`.export` (VTU).

>>> from torchconn import io
>>> from torchconn.frames import sh_frame_field, frame_metrics
>>> mesh = io.box(3)
>>> frames = sh_frame_field(mesh)          # (V, 3, 3); frames[i][:, k] = axis k at vertex i
>>> frame_metrics(frames, mesh)["n_singular_faces"]
0
"""
from . import propagate
from .constraints import BoundaryConstraint, feature_edges, feature_vertices
from .metrics import METRIC_KEYS, axis_alignment_angle, frame_metrics
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

__all__ = [
    "propagate",
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
]
