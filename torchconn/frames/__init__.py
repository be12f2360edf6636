"""Octahedral frame fields: the spherical-harmonic baseline (Ray et al. 2016) and fixed metrics.

>>> from torchconn import io
>>> from torchconn.frames import sh_frame_field, frame_metrics
>>> mesh = io.box(3)
>>> frames = sh_frame_field(mesh)          # (V, 3, 3); frames[i][:, k] = axis k at vertex i
>>> frame_metrics(frames, mesh)["n_singular_faces"]
0
"""
from . import propagate
from .metrics import METRIC_KEYS, axis_alignment_angle, feature_edges, feature_vertices, frame_metrics
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
