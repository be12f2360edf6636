"""Curvature, torsion and the Bianchi identities of a random discrete connection.

    python examples/curvature_bianchi.py                 # built-in 3x3x3 box (no mesh-I/O deps)
    python examples/curvature_bianchi.py path/to/mesh.msh  # any tet mesh or closed surface (io extra)

A discrete connection is one rotation per edge, ``R_ij`` (fiber at ``v_j`` -> fiber at ``v_i``,
``R_ji = R_ij^T``; docs/conventions.md §1). Its two-prong curvature on a face ``[abc]`` is
``R_ab R_bc - R_ac`` (report Sec. 3.2), and the differential (``𝔡∇Ω = 0``) and algebraic
(``d∇d∇θ = Ω∧θ``) Bianchi identities hold on every tet to round-off (report Ch. 5).
"""
from __future__ import annotations

import sys

import torch

import torchconn as tc

# A mesh: a file if one is given (read with torchconn.io), else the structured box built in torch.
mesh = tc.load_mesh(sys.argv[1], edge_length=0.3) if len(sys.argv) > 1 else tc.box(n=3)
print(mesh)

# A random connection: exp of Gaussian skew parameters (std 0.3) on every canonical edge.
gen = torch.Generator().manual_seed(0)
conn = tc.Connection.random_on_mesh(mesh, generator=gen, scale=0.3)
edge_rot = conn.edge_rot  # (E, 3, 3)

# Curvature on every face (F, 3, 3) through the functional nn.Module (topology as buffers).
omega = tc.Curvature(mesh)(conn)
print(f"faces {omega.shape[0]}: mean |Ω|_F = {torch.linalg.matrix_norm(omega).mean():.4f}")

# √R torsion (F, 3) of the solder form θ_ij = v_j - v_i (Def. 3.2).
theta = tc.Torsion(mesh)(conn)
print(f"mean |Θ| = {theta.norm(dim=-1).mean():.4f}")

# The Bianchi residuals per tet: both are exact identities of the discrete calculus.
differential = tc.bianchi.differential_residual(edge_rot, mesh)  # (T,)
algebraic = tc.bianchi.algebraic_residual(edge_rot, mesh)  # (T,)
print(f"tets {differential.shape[0]}: max differential residual {differential.max():.2e}, "
      f"max algebraic residual {algebraic.max():.2e}")

# The one-call check raises BianchiError if either exceeds the dtype's identity tolerance.
print("bianchi.check:", tc.bianchi.check(edge_rot, mesh))
