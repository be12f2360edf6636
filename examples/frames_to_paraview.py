"""An octahedral frame field on a built-in mesh, written for ParaView.

    python examples/frames_to_paraview.py OUTPUT_DIR

Computes the spherical-harmonic frame field of Ray, Sokolov & Lévy 2016
(``torchconn.frames.sh_frame_field``) on a built-in tet cylinder, reports its metrics, and writes
``OUTPUT_DIR/frames.vtu``: the tet mesh with the three frame axes as per-vertex vector fields
``axis0``, ``axis1``, ``axis2`` (``frames[i][:, k]`` is axis ``k`` at vertex ``i``). In ParaView:
open the file, apply a *Glyph* filter with orientation array ``axis0`` (and again for the
others). The cylinder (libigl, pymeshlab) and the writer (meshio) need the ``io`` extra.
"""
from __future__ import annotations

import sys
from pathlib import Path

import meshio

import torchconn as tc
from torchconn.frames import frame_metrics, sh_frame_field

out = Path(sys.argv[1] if len(sys.argv) > 1 else "frames_out")
out.mkdir(parents=True, exist_ok=True)

mesh = tc.cylinder(radius=1.0, height=2.0, edge_length=0.5)  # libigl tetgen on a pymeshlab cylinder
frames = sh_frame_field(mesh)  # (V, 3, 3) rotations, columns are the frame axes
metrics = frame_metrics(frames, mesh)
print(f"{mesh}\nsmoothness mean {metrics['smoothness_mean_deg']:.3f} deg, "
      f"alignment mean {metrics['alignment_mean_deg']:.3f} deg, singular faces {metrics['n_singular_faces']}")

points = mesh.vertices.detach().cpu().numpy()
cells = [("tetra", mesh.tets.cpu().numpy())]
axes = frames.detach().cpu().numpy()
point_data = {f"axis{k}": axes[:, :, k] for k in range(3)}  # (V, 3) each
path = out / "frames.vtu"
meshio.write(path, meshio.Mesh(points, cells, point_data=point_data))
print(f"wrote {path} ({points.shape[0]} vertices, {mesh.tets.shape[0]} tets)")
