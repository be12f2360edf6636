"""LMFF's numeric one-ring test beside its combinatorial conditions, per HexMe model (SH fields).

For every model: the SH field of ``design(mesh, "sh")`` (one frame per tet), then either

* ``--stage input``: :func:`torchconn.hexmesh.one_ring.one_ring_test` on the input mesh with the
  field's best face matchings, beside :func:`torchconn.hexmesh.meshability.meshability_report`; or
* ``--stage structure``: :func:`torchconn.hexmesh.structure.map_structure` (the matching search,
  the repair, the splits), whose report carries both.

One JSON line per model: singular vertices tested / passed / failed (by reason: flat, inverted,
angle, complex), the rings the foldover-free solve ran on, LMFF's zipper / invalid nodes and
complex edges, the vertices both flag (``both``), the conditions only (``conditions_only``: a
zipper, invalid or complex vertex whose ring passes) and the one-ring test only (``ring_only``),
and the seconds of the test (and of the structure stage).

    python -m benchmarks.one_ring_hexme --stage input s01c_cube s04c_tetrahedron
    python -m benchmarks.one_ring_hexme --stage structure s13c_cube_rounded_2
"""
from __future__ import annotations

import argparse
import json
import time

SIMPLE_C = ("s01c_cube", "s02c_prism", "s03c_pentagon", "s04c_tetrahedron", "s05c_cube_sphere", "s06c_dodecahedron",
            "s07c_notch", "s08c_cross_cyls_dr", "s09c_bridge", "s10c_cyl_cutsphere", "s11c_cube_cyl",
            "s12c_cube_rounded_1", "s13c_cube_rounded_2", "s14c_cube_corner_sub_sphere", "s15c_cylinder",
            "s16c_torus", "s17c_sphere")


def row(name: str, stage: str) -> dict:
    import numpy as np

    from benchmarks.frames_hexme import load_case
    from torchconn.frames import design
    from torchconn.hexmesh.meshability import COMPLEX, INVALID, ZIPPER, meshability_report
    from torchconn.hexmesh.one_ring import one_ring_test

    mesh = load_case("hexme", name)
    fr = design(mesh, "sh").tet_frames
    out = {"model": name, "stage": stage}
    if stage == "input":
        m = meshability_report(mesh, fr)
        r = one_ring_test(mesh, fr, meshability=m)
        out["tets"] = mesh.n_tets
    else:
        from torchconn.hexmesh.seamless import default_edge_length
        from torchconn.hexmesh.structure import map_structure

        t0 = time.perf_counter()
        st = map_structure(mesh, fr, default_edge_length(mesh))
        out["structure_s"] = round(time.perf_counter() - t0, 2)
        m, r = st.meshability, st.one_ring
        out["tets"] = st.mesh.n_tets
    c, mc = r.counts(), m.counts()
    flagged = np.isin(r.vertex_class, [ZIPPER, INVALID, COMPLEX])
    out.update(tested=c["tested"], passed=c["passed"], failed=c["failed"],
               **{k: c[k] for k in ("failed_flat", "failed_inverted", "failed_angle", "failed_complex", "solved")},
               zipper_nodes=mc["zipper_nodes"], invalid_nodes=mc["invalid_nodes"], complex_edges=mc["complex_edges"],
               both=int((flagged & ~r.passed).sum()), conditions_only=int((flagged & r.passed).sum()),
               ring_only=int((~flagged & ~r.passed).sum()), one_ring_s=round(r.timings["total_s"], 2),
               solve_s=round(r.timings["solve_s"], 2))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="*", default=list(SIMPLE_C))
    ap.add_argument("--stage", choices=("input", "structure"), default="input")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    for name in args.models:
        print(json.dumps(row(name, args.stage)), flush=True)


if __name__ == "__main__":
    main()
