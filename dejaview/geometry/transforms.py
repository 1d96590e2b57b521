"""Rigid transforms in numpy, for building and exporting geometry (no gradients).

Quaternions are w x y z, as everywhere in DejaView; the differentiable torch twins live in
``dejaview.sim.rotation``. Every numpy caller (robot files, the fcl checks, ``World`` building, MJCF
export, the Warp backend) uses these, so that the convention is written once.
"""

from __future__ import annotations

import math

import numpy as np

from dejaview.errors import GeometryError

__all__ = ["matrix_to_quat", "quat_multiply", "quat_to_matrix", "rigid_transform", "rpy_to_matrix"]


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrices of quaternions (normalised here).

    Args:
        q: (..., 4) quaternions, w x y z.
    Returns:
        (..., 3, 3) rotation matrices.
    Raises:
        GeometryError: a zero or non-finite quaternion.
    """
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(norm < 1e-12):
        raise GeometryError("orientation: quaternions must be finite and non-zero (w x y z)")
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quat(r) -> tuple[float, float, float, float]:
    """Unit quaternion of a rotation matrix (Shepperd's method; any sign of w).

    Args:
        r: (3, 3) rotation matrix.
    Returns:
        (4,) w x y z, as floats.
    """
    m = np.asarray(r, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 0.0))
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = ((m[k, j] - m[j, k]) / s, *v)
    n = math.sqrt(sum(c * c for c in q))
    return tuple(float(c / n) for c in q)


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product ``a * b`` of two (4,) w x y z quaternions: (4,)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def rpy_to_matrix(rpy) -> np.ndarray:
    """(3, 3) rotation of URDF roll-pitch-yaw (fixed axes x, y, z: R = Rz(yaw) Ry(pitch) Rx(roll))."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def rigid_transform(rotation=None, translation=None) -> np.ndarray:
    """(4, 4) homogeneous transform of a (3, 3) rotation and a (3,) translation (None: none)."""
    t = np.eye(4)
    if rotation is not None:
        t[:3, :3] = rotation
    if translation is not None:
        t[:3, 3] = translation
    return t
