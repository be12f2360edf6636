"""Octahedral frame fields: the spherical-harmonic baseline (Ray et al. 2016) and fixed metrics."""
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
