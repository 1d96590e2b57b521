"""Shared helpers of the loss tests: random poses and gradient checks in both modes."""

import math

import torch

from dejaview.sim.gradients import forward_value_and_grad, reverse_value_and_grad

F64 = dict(dtype=torch.float64)


def rng(seed=0):
    return torch.Generator().manual_seed(seed)


def random_quat(*shape, seed=0):
    q = torch.randn(*shape, 4, generator=rng(seed), **F64)
    return q / q.norm(dim=-1, keepdim=True)


def axis_angle_quat(axis, angle):
    """(4,) quaternion of a rotation by ``angle`` about ``axis``."""
    axis = torch.as_tensor(axis, **F64)
    axis = axis / axis.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)], **F64), math.sin(angle / 2) * axis])


def assert_forward_equals_reverse(fn, x, rtol=1e-8):
    """Values and gradients of ``fn`` (..., P) -> (...) agree between jvp (vmapped) and autograd."""
    v_rev, g_rev = reverse_value_and_grad(fn, x)
    v_fwd, g_fwd = forward_value_and_grad(fn, x)
    assert torch.isfinite(g_rev).all() and torch.isfinite(g_fwd).all()
    assert torch.allclose(v_fwd, v_rev, rtol=1e-12, atol=1e-15)
    scale = g_rev.abs().max().clamp(min=1e-12)
    assert ((g_fwd - g_rev).abs().max() / scale) < rtol
    return g_rev
