"""Quaternion and rotation helpers that are safe to differentiate.

Quaternions are ``(..., 4)`` tensors ``w x y z``, in the conventions of
``pytorch_kinematics.transforms`` (the user's robotics stack): products,
matrices, rotations and axis-angle vectors equal that library's results
(``tests/sim/test_rotation_conventions.py`` pins each on random inputs). They
are written here rather than imported (importing pytorch-kinematics pulls
matplotlib, ~2 s) and differ from it in three places on purpose:

- ``axis_angle_to_quaternion`` there has a NaN reverse-mode gradient at zero
  rotation, so ``rotvec_to_quat`` uses a series expansion near zero;
- ``quaternion_multiply`` there forces ``w >= 0``, which breaks a running
  integration, so we use ``quaternion_raw_multiply``;
- ``quaternion_angular_distance`` there returns zero (and a zero gradient)
  within ~1 degree and fails under vmap, so ``geodesic_angle`` is written here
  as ``2 * atan2(|v|, |w|)`` with a gradient that stays finite at zero.

Everything here works under ``torch.func.jvp``, ``vmap`` and ``torch.compile``:
no data-dependent Python branches.

The two functions of the integrator's inner loop, ``quat_multiply`` and
``quat_to_matrix``, are written as one contraction of the outer product of
their inputs with a constant matrix (3 tensor ops instead of ~25): a rollout
is bound by per-op overhead.
"""

from __future__ import annotations

import torch

from dejaview.sim.epsilons import small_angle


def _product_table() -> torch.Tensor:
    """(16, 4): Hamilton product coefficients, (a outer b).flatten() @ table = a * b."""
    t = torch.zeros(4, 4, 4, dtype=torch.float64)
    # w = aw bw - ax bx - ay by - az bz, and so on
    terms = {
        0: [(0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)],
        1: [(0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)],
        2: [(0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)],
        3: [(0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)],
    }
    for k, entries in terms.items():
        for i, j, sign in entries:
            t[i, j, k] = sign
    return t.reshape(16, 4)


def _matrix_table() -> tuple[torch.Tensor, torch.Tensor]:
    """(16, 9) and (9,): (q outer q).flatten() @ table + offset = rotation matrix of unit q."""
    t = torch.zeros(4, 4, 9, dtype=torch.float64)
    w, x, y, z = range(4)
    entries = {
        0: [((y, y), -2), ((z, z), -2)], 1: [((x, y), 2), ((z, w), -2)], 2: [((x, z), 2), ((y, w), 2)],
        3: [((x, y), 2), ((z, w), 2)], 4: [((x, x), -2), ((z, z), -2)], 5: [((y, z), 2), ((x, w), -2)],
        6: [((x, z), 2), ((y, w), -2)], 7: [((y, z), 2), ((x, w), 2)], 8: [((x, x), -2), ((y, y), -2)],
    }
    for k, terms in entries.items():
        for (i, j), c in terms:
            t[i, j, k] = c
    offset = torch.eye(3, dtype=torch.float64).reshape(9)
    return t.reshape(16, 9), offset


_PRODUCT = _product_table()
_MATRIX, _MATRIX_OFFSET = _matrix_table()


def small_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for small matrices, e.g. (..., n, 3) @ (..., 3, m) -> (..., n, m).

    Eagerly one ``matmul``. Under ``torch.compile`` a broadcast product and a
    sum, which inductor fuses into the surrounding kernels: as a matmul each
    of these tiny products was an extern ``bmm``/``mm`` call, dozens per
    substep (``dejaview bench profile --compile`` shows them). (A trace-time branch on the
    compile flag, not on tensor values.)
    """
    if torch.compiler.is_compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


def _outer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product without sign standardisation.

    Same result as ``pytorch_kinematics.transforms.quaternion_raw_multiply``.

    Args:
        a, b: (..., 4) quaternions, w x y z.
    Returns:
        (..., 4) the product ``a * b``.
    """
    return small_matmul(_outer(a, b), _PRODUCT.to(a))


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse for unit quaternions). q: (..., 4) -> (..., 4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of unit quaternions (as ``pytorch_kinematics``' quaternion_to_matrix).

    Args:
        q: (..., 4) unit quaternions.
    Returns:
        (..., 3, 3) rotation matrices.
    """
    flat = small_matmul(_outer(q, q), _MATRIX.to(q)) + _MATRIX_OFFSET.to(q)
    return flat.unflatten(-1, (3, 3))


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors by unit quaternions.

    Args:
        q: (..., 4) quaternions, w x y z.
        v: (..., 3) vectors.
    Returns:
        (..., 3) rotated vectors.
    """
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + w * t + torch.linalg.cross(u, t, dim=-1)


def normalize_quat(q: torch.Tensor) -> torch.Tensor:
    """Scale (..., 4) quaternions to unit length."""
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def _safe_norm(v: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Norm of (..., 3) vectors and a mask of small ones, with a finite gradient at 0."""
    sq = (v * v).sum(-1, keepdim=True)
    small = sq < eps * eps
    norm = torch.sqrt(torch.where(small, torch.ones_like(sq), sq))
    return norm, small


def rotvec_to_quat(r: torch.Tensor) -> torch.Tensor:
    """Quaternion of a rotation vector (axis times angle), finite gradients at zero.

    Args:
        r: (..., 3) rotation vectors in radians.
    Returns:
        (..., 4) unit quaternions w x y z with w >= 0 for angles below pi.
    """
    eps = small_angle(r.dtype)
    sq = (r * r).sum(-1, keepdim=True)
    small = sq < eps * eps
    norm = torch.sqrt(torch.where(small, 1.0, sq))  # (_safe_norm, its square reused below)
    half = 0.5 * norm
    # series of sin(t/2)/t and cos(t/2) below eps keeps the gradient exact at 0
    sinc_small = 0.5 - sq / 48.0
    cos_small = 1.0 - sq / 8.0
    sinc = torch.where(small, sinc_small, torch.sin(half) / norm)
    cos = torch.where(small, cos_small, torch.cos(half))
    return torch.cat([cos, sinc * r], dim=-1)


def quat_to_rotvec(q: torch.Tensor) -> torch.Tensor:
    """Rotation vector of unit quaternions (shortest rotation), finite gradients at identity.

    Args:
        q: (..., 4) unit quaternions.
    Returns:
        (..., 3) rotation vectors, angle in [0, pi].
    """
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    v = q[..., 1:]
    eps = 1e-6 if q.dtype == torch.float64 else 1e-3
    vn, small = _safe_norm(v, eps)
    angle = 2.0 * torch.atan2(vn, q[..., :1])
    # angle / |v| -> 2 / w near identity
    scale = torch.where(small, 2.0 / q[..., :1], angle / vn)
    return v * scale


def integrate_quat(q: torch.Tensor, omega: torch.Tensor, dt: float) -> torch.Tensor:
    """Advance orientations by a world-frame angular velocity over ``dt`` (exponential map).

    Args:
        q: (..., 4) unit quaternions.
        omega: (..., 3) angular velocities in the world frame (rad/s).
        dt: step length in seconds.
    Returns:
        (..., 4) renormalised quaternions ``exp(omega dt / 2) * q``.
    """
    return normalize_quat(quat_multiply(rotvec_to_quat(omega * dt), q))


def geodesic_angle(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Angle (radians, in [0, pi]) of the rotation between two orientations.

    ``2 * atan2(|v|, |w|)`` of the relative quaternion, invariant to the sign of
    either input. The gradient is finite everywhere; at exactly zero angle it is
    a subgradient of zero.

    Args:
        q1, q2: (..., 4) unit quaternions.
    Returns:
        (...) angles.
    """
    rel = quat_multiply(quat_conjugate(q1), q2)
    v = rel[..., 1:]
    sq = (v * v).sum(-1)
    tiny = torch.finfo(q1.dtype).tiny
    vn = torch.sqrt(sq + tiny)
    return 2.0 * torch.atan2(vn, rel[..., 0].abs())
