"""Covariant exterior derivatives of discrete bundle-valued forms (report Chs. 4 and 5).

* :mod:`.simplex` -- the operators on a simplex template: corrected Def. 5.1 (vector and
  Lie-algebra versions), Alt and the averaged ``d∇`` of Def. 5.2, BEHS21, the connection and
  solder forms.
* :mod:`.tet` -- the explicit Ch. 5 tetrahedron formula (discrete ``Ω∧θ``) and the mesh-level
  ``𝔡∇ Alt 𝔡∇ Alt θ̃``.
* :mod:`.primal_dual` -- Defs. 4.1-4.2 on the generalized dual complex.
"""
from . import primal_dual, simplex, tet
from .simplex import (
    all_tuples,
    distinct_tuples,
    faces_of,
    permutations_of,
    ListForm,
    unsymmetrized_vector,
    unsymmetrized_lie,
    alt_vector,
    alt_lie,
    averaged,
    behs21,
    connection_form,
    solder_form,
    solder_form_sqrt,
    TET_FACES,
    TET_FACE_SIGNS,
    FACE_EDGE_SIGNS,
)
from .tet import (
    wedge_curvature_solder_tet,
    averaged_dd_tet,
    behs21_dd_tet,
    tet_transports,
    tet_solder_sqrt,
    averaged_dd_solder,
    behs21_dd_solder,
    wedge_solder,
)
from .primal_dual import (
    primal_dual_face,
    primal_dual_tet,
    primal_dual_dd,
    primal_dual_wedge,
    primal_dual_dd_mesh,
    primal_dual_wedge_mesh,
)

__all__ = [
    "simplex",
    "tet",
    "primal_dual",
    "all_tuples",
    "distinct_tuples",
    "faces_of",
    "permutations_of",
    "ListForm",
    "unsymmetrized_vector",
    "unsymmetrized_lie",
    "alt_vector",
    "alt_lie",
    "averaged",
    "behs21",
    "connection_form",
    "solder_form",
    "solder_form_sqrt",
    "TET_FACES",
    "TET_FACE_SIGNS",
    "FACE_EDGE_SIGNS",
    "wedge_curvature_solder_tet",
    "averaged_dd_tet",
    "behs21_dd_tet",
    "tet_transports",
    "tet_solder_sqrt",
    "averaged_dd_solder",
    "behs21_dd_solder",
    "wedge_solder",
    "primal_dual_face",
    "primal_dual_tet",
    "primal_dual_dd",
    "primal_dual_wedge",
    "primal_dual_dd_mesh",
    "primal_dual_wedge_mesh",
]
