"""SO(3): rotations as 3x3 matrices, batched over any leading dimensions.

Conventions
-----------
* Rotation matrices act on column vectors: ``y = R @ x``.
* ``hat(omega)`` is the skew matrix with ``hat(omega) @ x == cross(omega, x)``.
* ``exp(omega) = expm(hat(omega))`` (Rodrigues); ``omega`` is the rotation vector
  (axis times angle, right-hand rule). ``log`` is its inverse with angle in ``[0, pi]``.
* ``sqrt(R) = exp(log(R) / 2)`` is the half transport ``sqrt(R_ij)`` of report Sec. 3.3
  (docs/conventions.md §1: it maps the edge-midpoint fiber to the fiber at ``v_i``).
* ``euler_xyz(a, b, c) = Rx(a) @ Ry(b) @ Rz(c)`` (report Sec. 3.4); this equals SciPy's
  *intrinsic* ``Rotation.from_euler("XYZ", [a, b, c])`` (upper-case axes).
* Quaternions (:func:`quat_to_matrix`, :func:`matrix_to_quat`) are Hamilton unit quaternions
  ``q = w + x i + y j + z k`` rotating ``x -> q x q*``; the rotation by ``t`` about the unit axis
  ``n`` is ``(cos(t/2), sin(t/2) n)``. The storage order is an argument with no default,
  ``convention="wxyz"`` (scalar first: pytorch3d, Eigen's constructor, ``scipy`` with
  ``scalar_first=True``) or ``convention="xyzw"`` (scalar last: scipy's default, roma, ROS),
  because the libraries disagree and a silent mix-up gives a valid but wrong rotation.
  ``q`` and ``-q`` are the same rotation; :func:`matrix_to_quat` returns ``w >= 0``.
* The 6D representation (Zhou, Barnes, Lu, Yang, Li 2019, "On the continuity of rotation
  representations in neural networks") is the first two *columns* of ``R``, column 0 then
  column 1: ``(R00, R10, R20, R01, R11, R21)`` (:func:`matrix_to_rot6d`); back by Gram-Schmidt
  (:func:`rot6d_to_matrix`). pytorch3d's ``matrix_to_rotation_6d`` takes the first two *rows*
  (its matrices act on row vectors), i.e. the 6D vector of ``R^T``.

Input types
-----------
All functions take ``torch.Tensor`` s of a floating dtype (float16, bfloat16, float32, float64)
on any device; constants follow the input. Anything else raises ``TypeError`` naming the
function, the argument and the type or dtype: a NumPy array or a list is *not* converted
(``torch`` functions do not convert either, and a hidden ``torch.as_tensor`` would choose the
device, and for lists the dtype, for the caller: call ``torch.as_tensor(x, dtype=...)``
first), and integer, bool or complex tensors are refused (the Taylor thresholds of
:func:`torchconn.tolerances.get_eps` exist only for the float dtypes). Shapes are checked
(``ValueError`` naming the expected and the given shape). These checks read no data: no device
sync, fine under ``torch.compile`` and ``vmap``.

Values: :func:`log` raises ``ValueError`` for a matrix that is not a rotation (NaN/inf,
``||R^T R - I||_F`` above 1e-4, ``det < 0``), naming the first such batch
index; the check is computed inside the compiled log kernel (in the same pass, about +5% to
+25% of the op on 10^6 matrices) or, on the torch path, by one fused elementwise check and
one ``any()`` (see :func:`log` for when it runs and when it synchronizes). :func:`sqrt` and
:func:`angle` are not checked (``sqrt`` is on the hot path of the torsion and the Bianchi
terms) and are garbage-in, garbage-out for non-rotations. Rotations are also validated where
they enter the library (:class:`torchconn.nn.ConnectionField` ``init``,
``Connection(..., validate=True)``), or explicitly with :func:`check_rotation`, which
reports every defect. There is no ``check=`` flag: a flag that changes whether a function can
raise would make every call site choose (the unvalidated op is
:func:`torchconn.ops.so3.log`, for callers that validated already).

Thresholds of
the Taylor and near-pi branches come from :func:`torchconn.tolerances.get_eps`; the unused
branch of every ``torch.where`` gets a harmless input ("safe-where") so that values *and*
gradients are finite at angle 0 and at angle pi. No ``acos(trace)`` is used anywhere.
"""
from __future__ import annotations

import torch
from torch._subclasses.fake_tensor import FakeTensor

from ..ops import so3 as _ops_so3
from ..ops.backend import _plain
from ..tolerances import get_eps
from ._validate import check_float_tensor as _check_float
from ._validate import check_rotation as _check_rotation_n

__all__ = [
    "hat",
    "vee",
    "exp",
    "log",
    "sqrt",
    "angle",
    "geodesic_distance",
    "rot_x",
    "rot_y",
    "rot_z",
    "euler_xyz",
    "random_rotation",
    "check_rotation",
    "project_to_rotation",
    "QUAT_CONVENTIONS",
    "quat_to_matrix",
    "matrix_to_quat",
    "rot6d_to_matrix",
    "matrix_to_rot6d",
]

#: Storage orders of a quaternion's components (see the module docstring).
QUAT_CONVENTIONS = ("wxyz", "xyzw")


def _check_mat3(R: torch.Tensor, fn: str, arg: str = "R") -> None:
    _check_float(R, f"so3.{fn}", arg)
    if R.dim() < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"so3.{fn} expects a tensor of shape (..., 3, 3), got {tuple(R.shape)}")


def _check_vec3(omega: torch.Tensor, fn: str) -> None:
    _check_float(omega, f"so3.{fn}", "omega")
    if omega.dim() < 1 or omega.shape[-1:] != (3,):
        raise ValueError(f"so3.{fn} expects a tensor of shape (..., 3), got {tuple(omega.shape)}")


def hat(omega: torch.Tensor) -> torch.Tensor:
    """Skew matrix of a vector: ``omega (..., 3) -> (..., 3, 3)`` with ``hat(w) x = w x x``.

    ``hat((x, y, z)) = [[0, -z, y], [z, 0, -x], [-y, x, 0]]``.
    """
    _check_vec3(omega, "hat")
    x, y, z = omega.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), -2
    )


def vee(K: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat` on the skew part: ``(..., 3, 3) -> (..., 3)``.

    Uses the antisymmetric part ``(K - K^T)/2``, so it is the projection for non-skew input.
    For a rotation by angle ``t`` about the unit axis ``n``, ``vee(R) = sin(t) n``.
    """
    _check_mat3(K, "vee", "K")
    return 0.5 * torch.stack(
        (K[..., 2, 1] - K[..., 1, 2], K[..., 0, 2] - K[..., 2, 0], K[..., 1, 0] - K[..., 0, 1]), -1
    )


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula ``exp(hat(omega))``: ``omega (..., 3) -> (..., 3, 3)`` rotation.

    ``exp(w) = I + sin(t)/t K + (1 - cos t)/t^2 K^2`` with ``K = hat(w)``, ``t = |w|``
    (report Remark 3.4: the exponential of a skew matrix is a rotation). Taylor branches
    below the dtype's ``small_angle`` threshold keep value and gradient finite (and exact to
    round-off) at ``omega = 0``. Differentiable.
    """
    _check_vec3(omega, "exp")
    # entries written out, closed-form backward, or compiled (torchconn.ops.so3.exp; same value as I + A K + B K²)
    return _ops_so3.exp(omega)


def log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector of a rotation: ``R (..., 3, 3) -> omega (..., 3)``, ``|omega|`` in ``[0, pi]``.

    Inverse of :func:`exp`: ``exp(log(R)) == R`` and ``log(exp(w)) == w`` for ``|w| < pi``.
    With ``v = vee(R) = sin(t) n`` and ``c = (tr R - 1)/2 = cos(t)``, three branches:

    * generic: ``t = atan2(|v|, c)``, ``omega = t / |v| * v``;
    * small angle (``|v|`` below ``small_angle`` and ``c > 0``):
      ``omega = asin(s)/s * v`` by its Taylor series in ``s^2 = |v|^2``;
    * obtuse angles (``c < 0``, i.e. ``t > pi/2``, which contains the near-pi region): the
      axis is the largest column of the symmetric part ``(R + R^T)/2 - c I = (1 - c) n n^T``,
      normalized, with its sign chosen so that ``n . v >= 0`` (consistent with the skew part);
      ``t = atan2(n . v, c)``. This is accurate to round-off up to and including pi, whereas
      ``t / |v| * v`` loses ``eps / (pi - t)``; so the near-pi switch is taken at ``t = pi/2``
      rather than at the registry's ``near_pi`` distance.

    At exactly ``t = pi`` the skew part vanishes and the sign of the axis is arbitrary (both
    ``+pi n`` and ``-pi n`` are logarithms). Differentiable, with finite gradients at 0 and pi.

    Non-rotations raise ``ValueError`` naming the first bad batch index, the defect
    (non-finite entries; not orthogonal, with the residual ``||R^T R - I||_F`` and the
    tolerance, 1e-4 (see below); ``det -1``, a reflection) and the number of bad
    matrices: their logarithm means nothing (``log(-R)`` would be an arbitrary-looking vector,
    ``log(2 I) = 0``, ``log(0) = (pi, 0, 0)``). Project first with
    :func:`project_to_rotation`, or call :func:`check_rotation` for a report of every defect.

    When the check runs: on eager tensors with data, on every device. Where the compiled
    kernel runs (CPU, float32/float64) it is computed in the log kernel itself (no extra pass
    over memory; +15-25% of the op). Elsewhere it is one elementwise pass (+40-50% of the
    torch log on the CPU) and one ``any()``, which on an accelerator is **one device
    synchronization**, accepted here because
    a log that names the bad index is worth more than the overlap lost; a training step that
    must not sync can run under ``torch.compile`` or call the unvalidated
    :func:`torchconn.ops.so3.log`. It is skipped, without reading any data (no sync, no graph
    break), under ``torch.compile`` / ``torch.export`` tracing, inside ``vmap`` and other
    ``torch.func`` transforms, on ``meta`` and fake tensors and during CUDA-graph capture;
    there the values are not validated (NaN/inf give NaN in that batch element only).

    Tolerance: ``get_eps("rotation")`` of float32 (1e-4), or of the dtype where looser
    (float16, bfloat16), as for :class:`torchconn.nn.ConnectionField` ``init``: the log of a
    matrix within ``δ`` of SO(3) is that of the nearest rotation to ``O(δ)``, so rotations
    stored in float32 and cast to float64, and the finite-difference perturbations of
    ``gradcheck``, are accepted.
    """
    _check_mat3(R, "log")
    if not _can_validate(R):
        # the three branches evaluated entrywise with safe-where, or compiled (torchconn.ops.so3.log)
        return _ops_so3.log(R)
    atol = _log_tolerance(R.dtype)
    omega, n_bad, first = _ops_so3.log_checked(R, atol)
    if n_bad:
        raise _not_rotation_error(R, n_bad, first, atol)
    return omega


def _log_tolerance(dtype: torch.dtype) -> float:
    """Largest ``||R^T R - I||_F`` that :func:`log` accepts: ``get_eps("rotation")`` of ``dtype``
    or of float32, whichever is looser (1e-4 for float32 and float64).

    The rule of :class:`torchconn.nn.ConnectionField` ``init``: the log of a matrix within
    ``δ`` of SO(3) is that of the nearest rotation to ``O(δ)``, so rotations stored in float32
    and cast to float64 are accepted, and so are the ``1e-6`` finite-difference perturbations
    of ``gradcheck`` (the float64 ``1e-9`` would reject both); reflections, scaled, sheared,
    zero and non-finite matrices are far outside it.
    """
    return max(get_eps("rotation", dtype), get_eps("rotation", torch.float32))


def _can_validate(R: torch.Tensor) -> bool:
    """Whether :func:`log` may read ``R``'s values (see its docstring): eager, plain, with data."""
    if torch.compiler.is_compiling():  # first: nothing else is traced
        return False
    if R.device.type == "meta" or isinstance(R, FakeTensor) or not _plain(R):
        return False
    return not (R.device.type == "cuda" and torch.cuda.is_current_stream_capturing())


def _not_rotation_error(R: torch.Tensor, n_bad: int, first: int, atol: float) -> ValueError:
    """The ``ValueError`` of :func:`log`: the first bad matrix (flat index ``first``) classified."""
    batch = R.shape[:-2]
    idx = tuple(int(i) for i in torch.unravel_index(torch.tensor(first), batch)) if batch else ()
    M = R.detach().reshape(-1, 3, 3)[first]
    _, e2, det = _ops_so3._rotation_flags(M, atol)
    if not bool(torch.isfinite(M).all()):
        defect = "non-finite entries (NaN/inf)"
    elif not float(e2) <= atol * atol:
        defect = f"not orthogonal: residual ||R^T R - I||_F = {float(e2) ** 0.5:.3e} > tolerance {atol:.1e}"
    else:
        defect = f"det -1 (a reflection): det R = {float(det):.6f}"
    return ValueError(
        f"so3.log: R (shape {tuple(R.shape)}) at batch index {idx} is not a rotation: {defect}; "
        f"{n_bad} of {batch.numel()} matrices are not rotations. The logarithm of a non-rotation "
        f"means nothing: project first with so3.project_to_rotation(R), or call "
        f"so3.check_rotation(R) for a report of every defect"
    )


def sqrt(R: torch.Tensor) -> torch.Tensor:
    """Principal square root ``exp(log(R)/2)``: ``(..., 3, 3) -> (..., 3, 3)``.

    The half transport ``sqrt(R_ij)`` of report Sec. 3.3 (midpoint of edge ``ij`` -> ``v_i``).
    ``sqrt(R) @ sqrt(R) == R``; at angle exactly pi the branch follows :func:`log`.
    Differentiable. Computed by the quaternion half-angle identity
    ``((1 + s) I + R + (R - R^T)/s) / (2 + s)``, ``s = sqrt(1 + tr R)``, below 120 degrees and as
    ``exp(log(R)/2)`` above (:func:`torchconn.ops.so3.sqrt`): same value to round-off.
    Values are not validated: for non-rotations the result is as meaningless as :func:`log`'s.
    """
    _check_mat3(R, "sqrt")
    return _ops_so3.sqrt(R)


def _safe_norm(x: torch.Tensor, dims) -> torch.Tensor:
    # clamp before sqrt: the gradient is 0 (not NaN) where the norm vanishes
    return torch.sqrt(torch.clamp_min((x * x).sum(dims), torch.finfo(x.dtype).tiny))


def angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle ``|log(R)|`` of a rotation: ``(..., 3, 3) -> (...)`` in ``[0, pi]``.

    ``t = atan2(|vee(R)|, (tr R - 1)/2)`` (``vee(R) = sin(t) n``): accurate to round-off at
    both ends, no ``acos``. Finite gradients everywhere; at exactly 0 and pi, where ``t`` has
    a cone singularity, the gradient is the zero subgradient.
    """
    _check_mat3(R, "angle")
    c = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    return torch.atan2(_safe_norm(vee(R), (-1,)), c)


def geodesic_distance(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Angle of the relative rotation: ``(..., 3, 3), (..., 3, 3) -> (...)`` in ``[0, pi]``.

    ``angle(R1^T R2)`` (atan2 form, accurate at 0 and pi; ``2 asin(|R1 - R2|_F / (2 sqrt 2))``
    would lose half the digits near pi). Broadcasts over batch dims.
    """
    _check_mat3(R1, "geodesic_distance", "R1")
    _check_mat3(R2, "geodesic_distance", "R2")
    return angle(R1.transpose(-1, -2) @ R2)


def _as_angle(t) -> torch.Tensor:
    if isinstance(t, torch.Tensor):
        return t if t.is_floating_point() else t.to(torch.get_default_dtype())
    return torch.as_tensor(t, dtype=torch.get_default_dtype())


def _axis_rot(t, i: int, j: int) -> torch.Tensor:
    """Rotation by ``t`` in the plane of axes ``(i, j)``: ``e_i -> cos e_i + sin e_j``."""
    t = _as_angle(t)
    c, s = torch.cos(t), torch.sin(t)
    o, one = torch.zeros_like(t), torch.ones_like(t)
    rows = [[one, o, o], [o, one, o], [o, o, one]]
    rows[i][i], rows[j][j], rows[j][i], rows[i][j] = c, c, s, -s
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def rot_x(t) -> torch.Tensor:
    """Rotation by angle ``t`` about the x axis: ``t (...) -> (..., 3, 3)`` (right-hand rule)."""
    return _axis_rot(t, 1, 2)


def rot_y(t) -> torch.Tensor:
    """Rotation by angle ``t`` about the y axis: ``t (...) -> (..., 3, 3)`` (right-hand rule)."""
    return _axis_rot(t, 2, 0)


def rot_z(t) -> torch.Tensor:
    """Rotation by angle ``t`` about the z axis: ``t (...) -> (..., 3, 3)`` (right-hand rule)."""
    return _axis_rot(t, 0, 1)


def euler_xyz(alpha, beta, gamma) -> torch.Tensor:
    """``R(alpha, beta, gamma) = Rx(alpha) @ Ry(beta) @ Rz(gamma)`` (report Sec. 3.4).

    Angles are tensors of broadcastable shapes ``(...)`` or Python floats; the result has the
    promoted float dtype of the tensor arguments and the device of the first one (the default
    dtype when all are floats). Returns ``(..., 3, 3)``. Equals SciPy's *intrinsic*
    ``Rotation.from_euler("XYZ", [alpha, beta, gamma])``, not the extrinsic ``"xyz"``.
    Differentiable in the angles.
    """
    tensors = [_as_angle(t) for t in (alpha, beta, gamma) if isinstance(t, torch.Tensor)]
    if tensors:
        dtype, device = tensors[0].dtype, tensors[0].device
        for t in tensors[1:]:
            dtype = torch.promote_types(dtype, t.dtype)
    else:
        dtype, device = torch.get_default_dtype(), None
    angles = [torch.as_tensor(t, dtype=dtype, device=device) for t in (alpha, beta, gamma)]
    a, b, g = torch.broadcast_tensors(*angles)
    return rot_x(a) @ rot_y(b) @ rot_z(g)


def random_rotation(
    *shape: int,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Uniformly (Haar) distributed rotations of shape ``(*shape, 3, 3)``.

    Drawn from normalized Gaussian quaternions (Haar on the unit 3-sphere, mapped 2:1 onto
    SO(3)); pass a seeded ``generator`` for reproducibility (all randomness goes through it).
    """
    dtype = dtype or torch.get_default_dtype()
    q = torch.randn(*shape, 4, generator=generator, dtype=dtype, device=device)
    return quat_to_matrix(q, convention="wxyz")


def check_rotation(R: torch.Tensor, name: str = "R", atol: float | None = None) -> None:
    """Raise ``ValueError`` unless every ``R (..., 3, 3)`` is a rotation.

    Delegates to :func:`torchconn.lie.son.check_rotation` (NaN/inf, ``||R^T R - I||_F > atol``,
    ``det R < 0``; the message names the first offending batch index). ``atol`` defaults to
    ``get_eps("rotation", R.dtype)``. Synchronizes with the device (explicit validation).
    """
    _check_mat3(R, "check_rotation", name)
    _check_rotation_n(R, name=name, atol=atol)


def project_to_rotation(M: torch.Tensor) -> torch.Tensor:
    """Nearest rotation in Frobenius norm: ``M (..., 3, 3) -> (..., 3, 3)``.

    ``U diag(1, 1, det(U V^T)) V^T`` from the SVD ``M = U S V^T`` (orthogonal Procrustes with
    the determinant fixed to +1). Differentiable where the singular values of ``M`` are
    distinct (SVD backward is undefined for repeated singular values, e.g. ``M = I``).
    """
    _check_mat3(M, "project_to_rotation", "M")
    U, _, Vh = torch.linalg.svd(M)
    d = torch.linalg.det(U @ Vh)
    ones = torch.ones_like(d)
    D = torch.stack((ones, ones, torch.where(d < 0, -ones, ones)), -1)
    return (U * D[..., None, :]) @ Vh



# ----------------------------------------------------------------------------- quaternions, 6D
def _quat_convention(convention, fn: str) -> str:
    if convention not in QUAT_CONVENTIONS:
        raise ValueError(f"so3.{fn}: convention must be 'wxyz' (scalar first) or 'xyzw' (scalar last, scipy's "
                         f"default), got {convention!r}")
    return convention


def quat_to_matrix(q: torch.Tensor, *, convention: str) -> torch.Tensor:
    """Rotation of a quaternion: ``q (..., 4) -> (..., 3, 3)``.

    Args:
        q: quaternions, stored ``(w, x, y, z)`` or ``(x, y, z, w)`` as ``convention`` says; any
            nonzero scale (``q`` is divided by ``|q|`` first, so ``q`` and ``c q`` give the same
            rotation for every ``c != 0``).
        convention: ``"wxyz"`` (scalar first) or ``"xyzw"`` (scalar last, scipy's default),
            keyword only, no default (module docstring).

    ``R = I + 2 w K + 2 K^2`` with ``K = hat((x, y, z))`` for the unit ``q``, i.e. the rotation by
    ``2 atan2(|(x, y, z)|, w)`` about ``(x, y, z)``; equals scipy's
    ``Rotation.from_quat(q, scalar_first=(convention == "wxyz")).as_matrix()``. Differentiable
    (finite gradients for every nonzero ``q``, at the identity and at angle pi included).
    Values are not validated (no sync): a zero quaternion gives NaN in that batch element.
    """
    _check_float(q, "so3.quat_to_matrix", "q")
    if q.dim() < 1 or q.shape[-1] != 4:
        raise ValueError(f"so3.quat_to_matrix expects a tensor of shape (..., 4), got {tuple(q.shape)}")
    if _quat_convention(convention, "quat_to_matrix") == "xyzw":
        q = q[..., [3, 0, 1, 2]]
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)), -1),
            torch.stack((2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)), -1),
            torch.stack((2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)), -1),
        ),
        -2,
    )


def matrix_to_quat(R: torch.Tensor, *, convention: str) -> torch.Tensor:
    """Unit quaternion of a rotation: ``R (..., 3, 3) -> q (..., 4)`` with ``w >= 0``.

    Args:
        R: rotations.
        convention: ``"wxyz"`` (scalar first) or ``"xyzw"`` (scalar last, scipy's default),
            keyword only, no default (module docstring).

    Shepperd's method, without ``acos`` and without square roots of small numbers: the four
    rows ``4 q_i q`` (``i = w, x, y, z``) are linear in ``R``, with diagonal entries
    ``t_i = 4 q_i^2`` (``t_w = 1 + tr R``, ``t_x = 1 + R00 - R11 - R22``, ...); the row of the
    largest ``t_i`` (chosen without gradient) is normalized. The ``t_i`` sum to 4 for any
    matrix, so the chosen one is at least 1: value and gradient are finite everywhere, at the
    identity and at angle pi included, and the rows agree where the choice switches (the
    result is continuous except where ``w`` changes sign, see below). For a matrix that is a
    rotation only to round-off (float32 products) the result is a unit quaternion of a nearby
    rotation; off SO(3) the rows differ to first order in the distance from SO(3), so where two
    ``t_i`` tie the derivative is exact along rotations (``matrix_to_quat(exp(w))``) but, in
    directions leaving SO(3), that of the chosen row.

    Sign: ``q`` and ``-q`` are one rotation; the result has ``w >= 0`` (scipy's
    ``as_quat(canonical=True)``). At angle exactly pi (``w = 0``) both signs qualify and the
    one with the largest-magnitude component positive is returned (scipy's canonical form makes
    the *first* nonzero component positive instead), so only there may the two differ, by sign.
    Values are not validated (garbage in, garbage out: see :func:`check_rotation`).
    """
    _check_mat3(R, "matrix_to_quat")
    convention = _quat_convention(convention, "matrix_to_quat")
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    rows = torch.stack(
        (
            torch.stack((1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01), -1),  # 4 w q
            torch.stack((m21 - m12, 1 + m00 - m11 - m22, m10 + m01, m02 + m20), -1),  # 4 x q
            torch.stack((m02 - m20, m10 + m01, 1 - m00 + m11 - m22, m12 + m21), -1),  # 4 y q
            torch.stack((m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22), -1),  # 4 z q
        ),
        -2,
    )  # (..., 4, 4), wxyz columns
    with torch.no_grad():
        k = rows.diagonal(dim1=-2, dim2=-1).argmax(-1)  # the largest 4 q_i^2, >= 1
    row = torch.gather(rows, -2, k[..., None, None].expand(*k.shape, 1, 4)).squeeze(-2)
    q = row / row.norm(dim=-1, keepdim=True)  # row_k = 4 q_k q with q_k > 0: the norm is >= 1
    q = torch.where(q[..., :1] < 0, -q, q)
    return q[..., [1, 2, 3, 0]] if convention == "xyzw" else q


def rot6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """Rotation of a 6D vector by Gram-Schmidt: ``x (..., 6) -> (..., 3, 3)`` (Zhou et al. 2019).

    With ``a1 = x[..., :3]`` and ``a2 = x[..., 3:]``, the columns of ``R`` are
    ``b1 = a1 / |a1|``, ``b2 = (a2 - (b1 . a2) b1) / |...|`` and ``b3 = b1 x b2``: the inverse
    of :func:`matrix_to_rot6d` on rotations (``rot6d_to_matrix(matrix_to_rot6d(R)) == R``) and
    a continuous, differentiable map from every ``x`` with ``a1 != 0`` and ``a2`` not parallel
    to ``a1`` (the representation learning code regresses; finite gradients at the identity and
    at angle pi). Values are not validated (no sync): a degenerate ``x`` gives NaN in that batch
    element.
    """
    _check_float(x, "so3.rot6d_to_matrix", "x")
    if x.dim() < 1 or x.shape[-1] != 6:
        raise ValueError(f"so3.rot6d_to_matrix expects a tensor of shape (..., 6), got {tuple(x.shape)}")
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True)
    b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = b2 / b2.norm(dim=-1, keepdim=True)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """The 6D representation of a rotation: ``R (..., 3, 3) -> (..., 6)``, its first two columns,
    column 0 then column 1: ``(R00, R10, R20, R01, R11, R21)`` (Zhou et al. 2019; the transpose
    of pytorch3d's ``matrix_to_rotation_6d``, see the module docstring)."""
    _check_mat3(R, "matrix_to_rot6d")
    return R[..., :, :2].transpose(-1, -2).reshape(*R.shape[:-2], 6)
