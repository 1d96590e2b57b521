"""Pose errors: known values, conventions, and gradients at and away from zero in both modes."""

import math

import pytest
import torch

from dejaview.losses import (DEFAULT_ORIENTATION_WEIGHT, SMOOTH_EPS, orientation_error, pose_error,
                             position_error, velocity_error)
from tests.losses.helpers import F64, assert_forward_equals_reverse, axis_angle_quat, random_quat, rng


def test_zero_at_target():
    p = torch.randn(5, 3, generator=rng(), **F64)
    q = random_quat(5)
    assert position_error(p, p).abs().max() < 1e-15
    assert orientation_error(q, q).abs().max() < 1e-12
    assert pose_error(p, q, p, q).abs().max() < 1e-12


def test_translation_of_3cm_is_3cm():
    p = torch.zeros(2, 3, **F64)
    t = p + torch.tensor([0.0, 0.03, 0.0], **F64)
    assert torch.allclose(position_error(p, t, eps=0.0), torch.full((2,), 0.03, **F64), atol=1e-15)
    # default smoothing stays within eps of the true distance
    assert (position_error(p, t) - 0.03).abs().max() <= SMOOTH_EPS


def test_rotation_of_30_degrees_about_z_is_pi_over_6():
    q = axis_angle_quat([0, 0, 1], math.pi / 6)
    ident = torch.tensor([1.0, 0, 0, 0], **F64)
    assert abs(orientation_error(q, ident, eps=0.0) - math.pi / 6) < 1e-12
    assert abs(orientation_error(q, ident) - math.pi / 6) <= SMOOTH_EPS
    # relative rotation, not absolute: both rotated by the same extra rotation
    r = random_quat(seed=3)
    from dejaview.sim.rotation import quat_multiply
    assert abs(orientation_error(quat_multiply(r, q), r, eps=0.0) - math.pi / 6) < 1e-12


def test_pose_error_weights_orientation_in_metres_per_radian():
    p = torch.zeros(3, **F64)
    t = torch.tensor([0.03, 0.0, 0.0], **F64)
    q = axis_angle_quat([1, 0, 0], 1.0)
    ident = torch.tensor([1.0, 0, 0, 0], **F64)
    assert abs(pose_error(p, q, t, ident, eps=0.0) - math.hypot(0.03, DEFAULT_ORIENTATION_WEIGHT * 1.0)) < 1e-12
    assert abs(pose_error(p, q, t, ident, orientation_weight=0.2, eps=0.0) - math.hypot(0.03, 0.2)) < 1e-12


def test_quaternion_double_cover_gives_the_same_loss():
    q, t = random_quat(6, seed=1), random_quat(6, seed=2)
    p = torch.zeros(6, 3, **F64)
    base = orientation_error(q, t)
    for a, b in ((-q, t), (q, -t), (-q, -t)):
        assert torch.allclose(orientation_error(a, b), base, atol=1e-14)
        assert torch.allclose(pose_error(p, a, p, b), pose_error(p, q, p, t), atol=1e-14)


def test_velocity_error_is_euclidean():
    v = torch.tensor([[1.0, 2.0, 2.0]], **F64)
    assert torch.allclose(velocity_error(v, torch.zeros(3, **F64), eps=0.0), torch.tensor([3.0], **F64))


def _pose_fn(x, target):
    """(B, 7) -> (B,): pose error of (position, quaternion) against target (7,)."""
    return pose_error(x[..., :3], x[..., 3:], target[:3], target[3:])


@pytest.mark.parametrize("eps", [SMOOTH_EPS, 0.0], ids=["smooth", "exact"])
def test_gradients_are_finite_at_exactly_zero_error(eps):
    """Finite in both modes; with smoothing also ~0 (with eps = 0 the angle's roundoff,
    ~1e-17 rad, sits on the cone and its gradient has norm ~1: why the default smooths)."""
    target = torch.cat([torch.tensor([0.1, -0.2, 0.3], **F64), random_quat(seed=4)])
    x = target.expand(2, 7).clone()
    fns = [
        lambda x: position_error(x[..., :3], target[:3], eps),
        lambda x: orientation_error(x[..., 3:], target[3:], eps),
        lambda x: velocity_error(x[..., :3], target[:3], eps),
        lambda x: pose_error(x[..., :3], x[..., 3:], target[:3], target[3:], eps=eps),
    ]
    for fn in fns:
        g = assert_forward_equals_reverse(fn, x)
        if eps > 0:
            assert g.abs().max() < 1e-6  # zero error is a smooth minimum


def test_forward_equals_reverse_on_random_inputs():
    target = torch.cat([torch.randn(3, generator=rng(5), **F64), random_quat(seed=6)])
    x = torch.cat([torch.randn(4, 3, generator=rng(7), **F64), random_quat(4, seed=8)], -1)
    assert_forward_equals_reverse(lambda x: _pose_fn(x, target), x)


def test_gradcheck_float64():
    target = torch.cat([torch.randn(3, generator=rng(9), **F64), random_quat(seed=10)])
    x = torch.cat([torch.randn(3, 3, generator=rng(11), **F64), random_quat(3, seed=12)], -1)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: _pose_fn(x, target), (x,))
    assert torch.autograd.gradcheck(lambda x: velocity_error(x[..., :3], target[:3]), (x,))


def test_smoothing_is_pseudo_huber():
    """Quadratic well inside eps, |d| - eps well outside: the documented shape."""
    z = torch.zeros(3, **F64)
    small = torch.tensor([1e-3, 0, 0], **F64)
    assert abs(position_error(small, z, eps=1.0) - (math.sqrt(1 + 1e-6) - 1)) < 1e-15
    assert abs(position_error(small, z, eps=1e-9) - (1e-3 - 1e-9)) < 1e-15


def test_squared_pose_loss_is_smooth_where_the_position_matches_and_the_orientation_does_not():
    """The optimisers minimise 0.5 * loss^2. Across a matching position (orientation 0.5 rad
    off) its gradient in the position must be continuous, ~0 on both sides; with the sum
    a + w b it jumped by 2 w b (a V-shaped valley where L-BFGS stalled)."""
    t = torch.tensor([0.1, 0.2, 0.3], **F64)
    q = axis_angle_quat([0, 0, 1], 0.5)
    ident = torch.tensor([1.0, 0, 0, 0], **F64)
    grads = []
    for side in (-1.0, 1.0):
        p = (t + torch.tensor([side * 1e-7, 0.0, 0.0], **F64)).requires_grad_(True)
        (g,) = torch.autograd.grad(0.5 * pose_error(p, q, t, ident) ** 2, p)
        grads.append(g)
    assert torch.allclose(grads[0], -grads[1], atol=1e-12)
    assert grads[1].abs().max() < 1e-6  # the sum gave w b = 0.025
