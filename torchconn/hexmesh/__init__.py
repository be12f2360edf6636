"""Hexahedral meshes from octahedral frame fields: the integer-grid map and hex extraction.

The pipeline of CubeCover (Nieser et al. 2011) and HexEx (Lyon et al. 2016), restated in
``../shared/HEXMESH.md`` (the API page: docs/api/hexmesh.md; measurements:
docs/results/hexmesh.md): per-tet frames and their face matchings
(:mod:`torchconn.frames.octahedral`), a cut surface and combing, the seamless parametrization
with boundary / singular-edge / feature constraints, quantization of its integer unknowns, a
validity check that says where and why a map fails, extraction of a conforming all-hex mesh,
and the hex mesh's quality.

This subpackage sits above :mod:`torchconn.frames` (it reuses the octahedral group, the
matchings and the boundary/feature constraints) and is imported on first use.
"""
from .cut import TetCharts, tet_charts
from .energy import MapEnergy, smooth_tet_frames
from .extract import HexExtraction, extract_hexes
from .choose import design_for_hex, hex_chooser
from .igm import IntegerGridMap, integer_grid_map
from .io import plot_hex_mesh, read_hex_mesh, read_hexex, write_hex_mesh, write_hexex
from .meshability import Meshability, meshability_report
from .pipeline import MAP_OPTIONS, HexMeshResult, hex_mesh
from .quality import HexQuality, hex_quality, scaled_jacobian
from .seamless import default_edge_length
from .hex_untangle import untangle
from .sparse import SPDSolve, sparse_spd_solve
from .validity import MapValidity, check_map

__all__ = [
    "hex_mesh", "HexMeshResult", "MAP_OPTIONS",
    "integer_grid_map", "IntegerGridMap", "default_edge_length",
    "tet_charts", "TetCharts",
    "check_map", "MapValidity",
    "extract_hexes", "HexExtraction",
    "hex_quality", "HexQuality", "scaled_jacobian", "untangle",
    "meshability_report", "Meshability",
    "design_for_hex", "hex_chooser", "MapEnergy", "smooth_tet_frames",
    "sparse_spd_solve", "SPDSolve",
    "write_hexex", "read_hexex", "write_hex_mesh", "read_hex_mesh", "plot_hex_mesh",
]
