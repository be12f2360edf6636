"""The discrete exterior calculus of bundle-valued forms (the report).

:mod:`.transport` (orientation, path products, per-simplex tables), :mod:`.connection`
(one rotation per edge), :mod:`.smooth` (smooth connections and their discretizations),
:mod:`.curvature` (holonomy and two-prong curvature, Sec. 3.2), :mod:`.chains` (curvature over
2-chains, Sec. 3.6), :mod:`.torsion` (Def. 3.2, 3.3.1), :mod:`.dnabla` (covariant exterior
derivatives, Chs. 4-5) and :mod:`.bianchi` (the Bianchi identities).
"""
from . import bianchi, chains, connection, curvature, dnabla, smooth, torsion, transport

__all__ = ["transport", "connection", "smooth", "curvature", "chains", "torsion", "dnabla", "bianchi"]
