"""``dejaview.sim.rotation`` keeps pytorch-kinematics' conventions (w x y z quaternions, axis-angle
vectors, rotation matrices): each conversion is pinned to that library's on random inputs, and the
three places where the module departs from it on purpose (see its docstring) are checked too."""

import math

import pytest
import pytorch_kinematics.transforms as pk
import torch

from dejaview.sim.rotation import (geodesic_angle, quat_multiply, quat_rotate, quat_to_matrix,
                                   quat_to_rotvec, rotvec_to_quat)


@pytest.fixture
def quats():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(256, 4, generator=g, dtype=torch.float64)
    return q / q.norm(dim=-1, keepdim=True)


def test_products_rotations_and_matrices_match_pytorch_kinematics(quats):
    a, b = quats[:128], quats[128:]
    assert torch.allclose(quat_multiply(a, b), pk.quaternion_raw_multiply(a, b), atol=1e-14)
    assert torch.allclose(quat_to_matrix(a), pk.quaternion_to_matrix(a), atol=1e-14)
    v = torch.randn(128, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert torch.allclose(quat_rotate(a, v), pk.quaternion_apply(a, v), atol=1e-13)


def test_rotation_vectors_match_pytorch_kinematics_axis_angles(quats):
    r = quat_to_rotvec(quats)
    ref = pk.quaternion_to_axis_angle(pk.standardize_quaternion(quats))
    assert torch.allclose(r, ref, atol=1e-12)
    assert torch.allclose(rotvec_to_quat(r), pk.axis_angle_to_quaternion(r), atol=1e-12)


def test_where_the_module_departs_from_pytorch_kinematics_on_purpose():
    # a running integration keeps the sign of w: quat_multiply does not standardise
    a = torch.tensor([[0.0, 1.0, 0.0, 0.0]], dtype=torch.float64)
    b = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    assert quat_multiply(a, a)[0, 0] == -1.0 and pk.quaternion_multiply(a, a)[0, 0] == 1.0
    assert torch.equal(quat_multiply(a, b), pk.quaternion_raw_multiply(a, b))
    # a finite gradient at zero rotation, where axis_angle_to_quaternion's is NaN
    r = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    g, = torch.autograd.grad(rotvec_to_quat(r).sum(), r)
    assert torch.isfinite(g).all()
    r2 = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    g2, = torch.autograd.grad(pk.axis_angle_to_quaternion(r2).sum(), r2)
    assert not torch.isfinite(g2).all()
    # the geodesic angle resolves half a degree (0.0087 rad), sign-invariant
    q = rotvec_to_quat(torch.tensor([[0.0, 0.0, math.radians(0.5)]], dtype=torch.float64))
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    assert geodesic_angle(q, identity).item() == pytest.approx(math.radians(0.5), rel=1e-9)
    assert geodesic_angle(-q, identity).item() == pytest.approx(math.radians(0.5), rel=1e-9)
