"""Bad tensor input to the library API ends in a clear error (issue 14, tensor part).

One test per case: the error class and the words that name the problem, the argument (and
index) and what to do. Where the decision is to propagate (NaN through a math op) or to adapt
(mesh geometry follows the connection's dtype), the test pins that behaviour instead.
"""
from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from torchconn import ops
from torchconn.dec.bianchi import BianchiError
from torchconn.dec.connection import Connection
from torchconn.dec import curvature as dcurv
from torchconn.dec import torsion as dtors
from torchconn.frames.loss import FrameFieldLoss
from torchconn.lie import so3, son
from torchconn.mesh.builtin import box
from torchconn.nn import AveragedCovariantD, BianchiCheck, ConnectionField, Curvature, Torsion

F64 = torch.float64


@pytest.fixture(scope="module")
def mesh():
    return box(2)  # V = 27, E = 98, F = 120, T = 48, float64


@pytest.fixture
def rots(mesh, gen):
    return so3.random_rotation(mesh.edges.shape[0], generator=gen, dtype=F64)


@pytest.fixture
def frames(mesh, gen):
    return so3.random_rotation(mesh.n_vertices, generator=gen, dtype=F64)


@pytest.fixture(scope="module")
def loss(mesh):
    return FrameFieldLoss(mesh, {"smooth": 1.0, "tie": 1.0, "flat": 1.0, "torsion": 1.0, "align": 1.0})


# ----------------------------------------------------------------- 8a: ConnectionField init
def test_field_init_reflection_names_edge(mesh, rots):
    bad = rots.clone()
    bad[7] = -bad[7]  # det -1: its log used to give silent NaN/garbage parameters
    with pytest.raises(ValueError, match=r"ConnectionField init.*edge indices \[7\].*det -1 \(a reflection\)"
                       r".*project_to_rotation"):
        ConnectionField(mesh.edges, mesh.n_vertices, init=bad)


def test_field_init_nan_and_non_orthogonal_name_edges(mesh, rots):
    bad = rots.clone()
    bad[2, 0, 1] = float("nan")
    bad[11] = 2.0 * bad[11]
    with pytest.raises(ValueError, match=r"2 of 98 .*non-finite entries \(NaN/inf\) at edge indices \[2\]"
                       r".*not orthogonal at edge indices \[11\]"):
        ConnectionField(mesh.edges, mesh.n_vertices, init=bad)
    conn = Connection._trusted(bad, mesh.edges, mesh.n_vertices)  # a Connection init is checked too
    with pytest.raises(ValueError, match=r"ConnectionField init \(Connection\).*edge indices \[2, 11\]"):
        ConnectionField(mesh.edges, mesh.n_vertices, init=conn)


def test_field_init_nan_parameters_name_edge(mesh):
    p = torch.zeros(mesh.edges.shape[0], 3, dtype=F64)
    p[5, 1] = float("inf")
    with pytest.raises(ValueError, match=r"parameters .*non-finite .*edge indices \[5\]"):
        ConnectionField(mesh.edges, mesh.n_vertices, init=p)


def test_field_init_accepts_single_precision_rotations(mesh, rots):
    # rotations saved in float32 and cast back to float64 are accepted (float32 tolerance)
    R = rots.float().double()
    field = ConnectionField(mesh.edges, mesh.n_vertices, init=R)
    assert torch.allclose(field.edge_rotations(), R, atol=1e-6)


# ----------------------------------------------------------------- 8b: FrameFieldLoss shapes
@pytest.mark.parametrize("dv", [3, -3])
def test_frame_loss_frames_rows(mesh, loss, rots, frames, dv):
    F = torch.cat([frames, frames[:3]]) if dv > 0 else frames[:dv]
    with pytest.raises(ValueError, match=r"frames must have shape \(27, 3, 3\).*got \(%d, 3, 3\)" % (27 + dv)):
        loss(rots, F)


@pytest.mark.parametrize("shape", [(99, 3, 3), (98, 3), (98, 4, 4)])
def test_frame_loss_edge_rot_shape(loss, frames, shape):
    R = torch.zeros(shape, dtype=F64)
    with pytest.raises(ValueError, match=r"edge_rot must have shape \(98, 3, 3\).*got " + re.escape(str(shape))):
        loss(R, frames)


@pytest.mark.parametrize("compiled", [True, False])
def test_frame_loss_mixed_dtypes(loss, rots, frames, compiled):
    with ops.compiled(compiled):
        with pytest.raises(TypeError, match=r"edge_rot has dtype torch.float32 but frames has dtype torch.float64"):
            loss(rots.float(), frames)
        with pytest.raises(TypeError, match=r"edge_rot has dtype torch.float64 but frames has dtype torch.float32"):
            loss(rots, frames.float())
        # one dtype on a float64 mesh is fine: the mesh geometry follows the inputs
        out = loss(rots.float(), frames.float())
    assert out["total"].dtype == torch.float32 and torch.isfinite(out["total"])


def test_frame_loss_device_and_type(loss, rots, frames):
    with pytest.raises(ValueError, match=r"edge_rot is on cpu but frames is on meta"):
        loss(rots, frames.to("meta"))
    with pytest.raises(TypeError, match=r"frames must be a floating-point tensor, got ndarray"):
        loss(rots, frames.numpy())


# ----------------------------------------------------------------- lie: types and dtypes
@pytest.mark.parametrize("fn, arg", [(so3.exp, "omega"), (so3.hat, "omega")])
def test_so3_vector_maps_reject_int(fn, arg):
    with pytest.raises(TypeError, match=rf"so3\.{fn.__name__}: {arg} must be a floating-point tensor, got dtype "
                       r"torch.int64; pass a float tensor"):
        fn(torch.zeros(4, 3, dtype=torch.long))


@pytest.mark.parametrize("fn", [so3.log, so3.sqrt, so3.vee, so3.angle])
@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.complex64])
def test_so3_matrix_maps_reject_non_float(fn, dtype):
    with pytest.raises(TypeError, match=rf"so3\.{fn.__name__}: .* must be a floating-point tensor, got dtype {dtype}"):
        fn(torch.eye(3).to(dtype))


@pytest.mark.parametrize("fn, x", [(so3.exp, np.zeros(3)), (so3.hat, np.zeros(3)), (so3.log, np.eye(3)),
                                   (so3.sqrt, np.eye(3)), (so3.vee, np.eye(3)), (so3.log, [[1.0, 0, 0]] * 3)])
def test_so3_rejects_numpy_and_lists(fn, x):
    with pytest.raises(TypeError, match=rf"so3\.{fn.__name__}: .* must be a torch.Tensor, got "
                       r"(numpy.ndarray|list); convert it first, e.g. torch.as_tensor"):
        fn(x)


def test_son_rejects_numpy_and_int():
    with pytest.raises(TypeError, match=r"son\.exp: K must be a torch.Tensor, got numpy.ndarray"):
        son.exp(np.zeros((4, 4)))
    with pytest.raises(TypeError, match=r"son\.log: R must be a floating-point tensor, got dtype torch.int64"):
        son.log(torch.eye(4, dtype=torch.long))
    with pytest.raises(TypeError, match=r"son\.hat: params must be a torch.Tensor"):
        son.hat(np.zeros(6), 4)
    with pytest.raises(TypeError, match=r"son\.sqrt: R must be a floating-point tensor"):
        son.sqrt(torch.eye(2, dtype=torch.int32))


def test_check_rotation_rejects_int_with_name():
    with pytest.raises(TypeError, match=r"check_rotation: frames must be a floating-point tensor, got dtype torch.int64"):
        so3.check_rotation(torch.eye(3, dtype=torch.long), name="frames")


def test_so3_log_of_non_rotations_raises_and_the_op_stays_unvalidated():
    # so3.log names the first bad index (tests/test_so3_log_validation.py has every case);
    # the op below it (torchconn.ops.so3.log) keeps the garbage-in behaviour: finite,
    # |omega| <= pi, exp(log(M)) != M; NaN stays local
    M = torch.stack([2.0 * torch.eye(3, dtype=F64), torch.zeros(3, 3, dtype=F64), -torch.eye(3, dtype=F64)])
    with pytest.raises(ValueError, match=r"so3\.log: .* at batch index \(0,\) is not a rotation: not orthogonal"
                       r".*3 of 3 matrices .*project_to_rotation"):
        so3.log(M)
    w = ops.so3.log(M)
    assert torch.isfinite(w).all() and (w.norm(dim=-1) <= torch.pi + 1e-12).all()
    assert not torch.allclose(so3.exp(w), M)
    M[1, 0, 0] = float("nan")
    w = ops.so3.log(M)
    assert torch.isnan(w[1]).all() and torch.isfinite(w[[0, 2]]).all()
    with pytest.raises(ValueError, match=r"3 of 3 matrices are not rotations; non-finite .* at index \(1,\)"):
        so3.check_rotation(M)


# ----------------------------------------------------------------- modules and functional ops
@pytest.mark.parametrize("shape, cls, words", [
    ((99, 3, 3), ValueError, r"Curvature: got 99 edge rotations .* mesh with 98 edges; pass one rotation R_ij per mesh edge"),
    ((97, 3, 3), ValueError, r"Curvature: got 97 edge rotations"),
    ((98, 3), ValueError, r"Curvature: edge rotations must have shape \(\.\.\., E, n, n\).*got \(98, 3\)"),
])
def test_curvature_module_shapes(mesh, shape, cls, words):
    with pytest.raises(cls, match=words):
        Curvature(mesh)(torch.zeros(shape, dtype=F64))


def test_curvature_module_rank4_is_valid(mesh, gen):
    # Curvature takes any rank: (E, 4, 4) is not an error
    R4 = son.random_rotation(mesh.edges.shape[0], n=4, generator=gen, dtype=F64)
    assert Curvature(mesh)(R4).shape == (120, 4, 4)


@pytest.mark.parametrize("module", [Torsion, AveragedCovariantD, BianchiCheck])
def test_solder_modules_need_rank3(mesh, gen, module):
    R4 = son.random_rotation(mesh.edges.shape[0], n=4, generator=gen, dtype=F64)
    with pytest.raises(ValueError, match=rf"{module.__name__}: the solder form lives in R\^3.*\(98, 3, 3\); got \(98, 4, 4\)"):
        module(mesh)(R4)


def test_modules_reject_int_and_numpy(mesh, rots, frames):
    with pytest.raises(TypeError, match=r"Curvature: edge rotations must be a floating-point tensor, got dtype torch.int64"):
        Curvature(mesh)(torch.eye(3, dtype=torch.long).expand(98, 3, 3))
    with pytest.raises(TypeError, match=r"Torsion: expected a Connection.*got ndarray; convert"):
        Torsion(mesh)(rots.numpy())
    with pytest.raises(TypeError, match=r"AveragedCovariantD: frames must be None or a floating-point tensor, got ndarray"):
        AveragedCovariantD(mesh)(rots, frames.numpy())
    with pytest.raises(ValueError, match=r"Torsion: frames must have shape \(27, 3, 3\).*got \(26, 3, 3\)"):
        Torsion(mesh)(rots, frames[:-1])


def test_functional_ops_reject_extra_edge_rows(mesh, rots):
    extra = torch.cat([rots, rots[:1]])  # used to be accepted silently (extra row ignored)
    with pytest.raises(ValueError, match=r"face_curvature: edge_rot must have shape \(98, 3, 3\).*got \(99, 3, 3\)"):
        dcurv.face_curvature(extra, mesh)
    with pytest.raises(ValueError, match=r"face_torsion: edge_rot must have shape \(98, 3, 3\).*got \(99, 3, 3\)"):
        dtors.face_torsion(extra, mesh)


def test_modules_follow_the_connection_dtype(mesh, rots, frames):
    # documented policy: mesh geometry and frames are cast to the dtype of the edge rotations
    field32 = ConnectionField(mesh.edges, mesh.n_vertices, init=rots, dtype=torch.float32)
    assert Curvature(mesh)(field32).dtype == torch.float32
    assert Torsion(mesh)(field32, frames).dtype == torch.float32
    assert AveragedCovariantD(mesh)(rots, frames.float()).dtype == F64
    assert AveragedCovariantD(box(2, dtype=torch.float32))(rots).dtype == F64


def test_nan_propagates_locally_in_math_modules(mesh, rots):
    bad = rots.clone()
    e = 4
    bad[e, 1, 2] = float("nan")
    on_face = (mesh.face_edges == e).any(-1)
    K = Curvature(mesh)(bad)
    assert torch.isnan(K[on_face]).flatten(1).any(-1).all() and torch.isfinite(K[~on_face]).all()
    T = Torsion(mesh)(bad)
    assert torch.isnan(T[on_face]).any(-1).all() and torch.isfinite(T[~on_face]).all()
    D = AveragedCovariantD(mesh)(bad)
    on_tet = (mesh.tet_edges == e).any(-1)
    assert torch.isnan(D[on_tet]).any() and torch.isfinite(D[~on_tet]).all()


def test_bianchi_check_names_nan_term(mesh, rots, frames):
    bad = rots.clone()
    bad[4, 1, 2] = float("nan")
    with pytest.raises(BianchiError, match=r"differential Bianchi residual is NaN/inf on \d+ tets"):
        BianchiCheck(mesh)(bad)
    F = frames.clone()
    F[0, 0, 0] = float("nan")
    with pytest.raises(BianchiError, match=r"algebraic Bianchi residual is NaN/inf"):
        BianchiCheck(mesh)(rots, F)


def test_connection_rejects_non_float_edge_rot(mesh):
    with pytest.raises(TypeError, match=r"Connection: edge_rot must be a floating-point tensor .* got dtype torch.int64"):
        Connection(torch.eye(3, dtype=torch.long).expand(98, 3, 3), mesh.edges, mesh.n_vertices)
    with pytest.raises(TypeError, match=r"got ndarray; convert it first"):
        Connection(np.eye(3)[None].repeat(98, 0), mesh.edges, mesh.n_vertices)


def test_frame_loss_edge_rot_none_only_for_alignment_terms(mesh, loss, frames):
    with pytest.raises(TypeError, match=r"edge_rot is None but the terms \['smooth', 'tie', 'flat', 'torsion'\]"):
        loss(None, frames)
    align_only = FrameFieldLoss(mesh, {"align": 1.0})
    assert torch.isfinite(align_only(None, frames)["align"])
