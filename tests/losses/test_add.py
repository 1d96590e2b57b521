"""ADD: closed forms, model-point sampling, conventions and gradients."""

import math

import numpy as np
import pytest
import torch

from dejaview.losses import add_error, body_model_points, model_points
from tests.losses.helpers import F64, assert_forward_equals_reverse, axis_angle_quat, random_quat, rng
from tests.sim.conftest import box_body, make_world

IDENT = torch.tensor([1.0, 0, 0, 0], **F64)


def circle(n=64, r=0.07, z=0.0):
    a = torch.arange(n, **F64) * (2 * math.pi / n)
    return torch.stack([r * torch.cos(a), r * torch.sin(a), torch.full_like(a, z)], -1)


def test_zero_at_target():
    pts = torch.randn(50, 3, generator=rng(), **F64) * 0.1
    p, q = torch.randn(4, 3, generator=rng(1), **F64), random_quat(4)
    assert add_error(p, q, p, q, pts).abs().max() < 1e-12


def test_pure_translation_is_its_length():
    pts = torch.randn(50, 3, generator=rng(), **F64) * 0.1
    q = random_quat(seed=2)
    shift = torch.tensor([0.01, -0.02, 0.02], **F64)
    err = add_error(shift, q, torch.zeros(3, **F64), q, pts, eps=0.0)
    assert abs(err - 0.03) < 1e-12


@pytest.mark.parametrize("angle", [0.1, math.pi / 6, 2.0, math.pi])
def test_rotation_of_a_circle_about_its_axis_is_the_chord(angle):
    """Every point of a circle of radius r turned by theta moves by the chord 2 r sin(theta / 2)."""
    r = 0.07
    q = axis_angle_quat([0, 0, 1], angle)
    zero = torch.zeros(3, **F64)
    err = add_error(zero, q, zero, IDENT, circle(r=r, z=0.03), eps=0.0)
    assert abs(err - 2 * r * math.sin(angle / 2)) < 1e-12


def test_quaternion_double_cover_gives_the_same_loss():
    pts = torch.randn(30, 3, generator=rng(), **F64) * 0.1
    q, t = random_quat(5, seed=3), random_quat(5, seed=4)
    p = torch.randn(5, 3, generator=rng(5), **F64) * 0.1
    z = torch.zeros(3, **F64)
    base = add_error(p, q, z, t, pts)
    for a, b in ((-q, t), (q, -t), (-q, -t)):
        assert torch.allclose(add_error(p, a, z, b, pts), base, atol=1e-15)


def _fn(pts, target):
    return lambda x: add_error(x[..., :3], x[..., 3:], target[:3], target[3:], pts)


def test_gradients_are_finite_and_zero_at_zero_error():
    pts = torch.randn(20, 3, generator=rng(), **F64) * 0.1
    target = torch.cat([torch.tensor([0.3, 0.1, -0.2], **F64), random_quat(seed=6)])
    g = assert_forward_equals_reverse(_fn(pts, target), target.expand(2, 7).clone())
    assert g.abs().max() < 1e-6


def test_forward_equals_reverse_and_gradcheck():
    pts = torch.randn(20, 3, generator=rng(), **F64) * 0.1
    target = torch.cat([torch.randn(3, generator=rng(7), **F64), random_quat(seed=8)])
    x = torch.cat([torch.randn(3, 3, generator=rng(9), **F64), random_quat(3, seed=10)], -1)
    assert_forward_equals_reverse(_fn(pts, target), x)
    assert torch.autograd.gradcheck(_fn(pts, target), (x.requires_grad_(True),))


def test_model_points_are_deterministic_spread_and_within_budget():
    v = np.random.default_rng(0).normal(size=(5000, 3))
    a = model_points(v, budget=64, seed=0)
    assert a.shape == (64, 3) and a.dtype == torch.float64
    assert torch.equal(a, model_points(v, budget=64, seed=0))
    assert not torch.equal(a, model_points(v, budget=64, seed=1))
    # farthest-point sampling covers the cloud: its spread beats a random subset's
    def spread(p):  # mean nearest-neighbour distance
        return torch.cdist(p, p).add(torch.eye(len(p), **F64) * 1e9).min(1).values.mean()

    rand = torch.as_tensor(v[np.random.default_rng(1).choice(5000, 64, replace=False)])
    assert spread(a) > spread(rand)
    # rows of the input only, duplicates merged, small inputs kept whole
    assert all((np.abs(v - p.numpy()).sum(1) < 1e-15).any() for p in a)
    dup = np.concatenate([v[:10], v[:10]])
    assert model_points(dup, budget=64).shape == (10, 3)


def test_model_points_are_in_the_com_frame():
    v = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    com = torch.tensor([0.5, 0.5, 0.0], **F64)
    pts = model_points(v, com=com)
    assert torch.allclose(pts.mean(0), torch.tensor([1 / 3, 1 / 3, 0], **F64) - com)


def test_body_model_points_default_to_sphere_centres_and_subtract_the_com():
    body = box_body()
    world = make_world([body], [])
    pts = body_model_points(world, "box")
    assert pts.shape == (len(body.radii), 3)
    shifted = body.__class__(**{**body.__dict__, "com": np.array([0.01, 0.0, 0.0]),
                                "centers": body.centers + np.array([0.01, 0.0, 0.0])})
    world2 = make_world([shifted], [])
    assert torch.allclose(body_model_points(world2, 0).mean(0), torch.zeros(3, **F64), atol=1e-15)
    verts = body.centers + np.array([0.01, 0.0, 0.0])  # object-frame vertices
    assert torch.allclose(body_model_points(world2, 0, vertices=verts).mean(0), torch.zeros(3, **F64),
                          atol=1e-15)
