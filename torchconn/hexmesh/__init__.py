"""Hexahedral meshes from octahedral frame fields: the integer-grid map and hex extraction.

The pipeline of CubeCover (Nieser et al. 2011) and HexEx (Lyon et al. 2016), restated in
``../shared/HEXMESH.md`` and in docs/hexmesh.md: per-tet frames and their face matchings
(:mod:`torchconn.frames.octahedral`), a cut surface and combing, the seamless parametrization
with boundary / singular-edge / feature constraints, quantization of its integer unknowns, a
validity check that says where and why a map fails, extraction of a conforming all-hex mesh,
and the hex mesh's quality.

This subpackage sits above :mod:`torchconn.frames` (it reuses the octahedral group, the
matchings and the boundary/feature constraints) and is imported on first use.
"""
