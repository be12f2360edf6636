"""Optimize a learnable connection to flatten it: gradient descent on the face curvature.

    python examples/train_connection.py [steps]

``ConnectionField`` holds one skew vector per edge and returns ``R_ij = exp(hat(w_ij))``
(``torchconn.so3.exp``, closed-form Rodrigues with its own backward). The loss is the mean
squared two-prong curvature ``|R_ab R_bc - R_ac|_F^2`` over the faces (report Sec. 3.2) plus a
small term that keeps the averaged ``d∇d∇θ`` (Def. 5.2) small as well; both go to zero for a
flat connection, so the printed loss decreases.
"""
from __future__ import annotations

import sys

import torch

import torchconn as tc

steps = int(sys.argv[1]) if len(sys.argv) > 1 else 60
torch.manual_seed(0)

mesh = tc.box(n=3)  # 27 vertices, 98 edges, 48 tets
gen = torch.Generator().manual_seed(0)
start = tc.Connection.random_on_mesh(mesh, generator=gen, scale=0.5)
field = tc.ConnectionField.from_connection(start)  # parameters: (E, 3) skew vectors

curvature = tc.Curvature(mesh)  # (F, 3, 3) per face
dd = tc.AveragedCovariantD(mesh)  # (T, 3) per tet
optimizer = torch.optim.Adam(field.parameters(), lr=0.05)

for step in range(steps + 1):
    optimizer.zero_grad()
    conn = field()  # Connection with edge_rot = exp(hat(params))
    loss = curvature(conn).square().sum((-2, -1)).mean() + 0.1 * dd(conn).square().sum(-1).mean()
    if step % 10 == 0:
        print(f"step {step:3d}  loss {loss.item():.6f}")
    if step < steps:
        loss.backward()
        optimizer.step()

# The optimized connection still satisfies the Bianchi identities (they hold for any connection).
print("bianchi.check:", tc.BianchiCheck(mesh)(field))
