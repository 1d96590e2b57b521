r"""The roll stick of a line contact: normal forces that hold the roll of a body on an edge.

A body on an edge (its touching contacts along a line) should not roll about
the axis that lifts one end of the line and presses the other: a rigid edge's
end forces hold that roll within the impact, whatever friction's torque starts
it. The penalty normal forces, springs on depth, resisted it only as the ends
sank and lifted (over about 1/omega_0); a box landing on its edge while sliding
along it (box-thrown, docs/physics-fidelity.md) left rolling at 0.66 rad/s
where MuJoCo's box did not roll. So per body and substep, over its touching
static contacts (weights w_i, arms r_i, normals n_i): the centroid
c = sum w_i r_i, the mean normal z, the in-plane second moment
S = sum w_i p_i p_i^T of p_i = P (r_i - c) (P = I - z z^T), its eigenvalues
l1 >= l2 and major axis e (the line), and the roll axis a = z x e. Its
projector has a closed form, a a^T = (P - (2 S - T P) / D) / 2 with
T = l1 + l2 = tr S and D = l1 - l2 = sqrt(2 tr(S^2) - T^2), so values and
gradients need no eigen-solver. Each contact's normal velocity from the spin
about a, u_i = ((a a^T omega) x r_i) . n_i, is stopped within a time tau by a
normal force added to it,

    g_i = -f w_i m_n,i (u_i - sum_j w_j u_j) / tau,    f_n,i <- max(f_n,i + g_i, 0)

(m_n,i the contact's effective mass along its normal, as the friction's stick
limit; tau = max(h, ROLL_STOP_OMEGA_T / omega_0), ``roll_stop_time``: one
substep h at the default step, the contact's time scale at finer ones),
gated to elongated sets, f = relu(1 - LINE_ASPECT l2 / l1)
(LINE_ASPECT = 4; 0 for a set within a micron of a point, ``LINE_MIN_SPREAD``):
a face, a ring or a single contact is left alone (f = 0),
and so is any spin about the line itself (rolling over an edge, tipping). It
pushes and unloads, never pulls. The friction's Coulomb limit and predicted
slip read the spring forces f_n,i (the stick changes only the wrench).
The gate is why a box's pitch stays free after it lands on an edge (ungated,
the stick holds it), and the stick acts on the roll alone
because one on every difference of the contacts' normal velocities would hold
any turn over an edge (docs/physics-fidelity.md, "Sliding along an edge", has
the fidelity rows with and without it;
``tests/sim/test_physics.py::test_a_box_landing_on_an_edge_while_sliding_along_it_does_not_roll_over_the_edge_line``).

Why tau and not h: a force that stops the roll in every substep (tau = h)
grows as 1 / h, each substep's push an impulse of a fixed size; where the
roll is not gone by the next substep (an end that cannot pull, the max;
friction starting it again), the pushes add up with the number of
substeps and the answer moves with the step (making only the gate's share
a rate, 1 - (1 - f)^(h / tau), does not cure it). With tau fixed by omega_0
the stick is a damper of one rate at every step, and the answer holds
across steps (docs/physics-fidelity.md, "The roll stick and the step", has
the numbers; ``tests/sim/test_physics.py``). At the default step tau = h.

Static contacts only (``dejaview.sim.contacts.static_contact_wrench`` calls it after the
friction), and not for box bodies: they meet planes and static boxes with their exact corners
(``dejaview.sim.box_edges``), where the stick is not needed; the native engine has the same
formula (``native/static_contacts.h``, ``line_roll_stick``) and its reverse mode
(``native/adjoint_roll_stick.h``, ``RollStick``).
"""

from __future__ import annotations

import torch

from dejaview.sim.epsilons import TINY
from dejaview.sim.rotation import small_matmul

LINE_ASPECT = 4.0
"""A static contact set counts as a line (an edge) while its in-plane second moments' ratio
l1 / l2 exceeds this; the roll stick's gate is ``relu(1 - LINE_ASPECT l2 / l1)``."""

ROLL_STOP_OMEGA_T = 0.25
"""omega_0 tau: the roll stick stops a line's roll in tau = ROLL_STOP_OMEGA_T / omega_0 (the default
substep, ``dejaview.sim.world.DEFAULT_OMEGA_H``), or in one substep where that is longer."""

LINE_MIN_SPREAD = 1e-12
"""m^2: a contact set whose in-plane second moment l1 + l2 is at most this (its points within
about a micron of their centroid: one touching contact) is a point, not a line; its gate is 0."""


def roll_stop_time(h: float, omega: float) -> float:
    """tau (s): the time in which the roll stick stops a line's roll, ``max(h, ROLL_STOP_OMEGA_T / omega)``
    for substep ``h`` (s) and contact frequency ``omega`` (rad/s)."""
    return max(float(h), ROLL_STOP_OMEGA_T / float(omega))


def line_roll_stick(fn: torch.Tensor, weight: torch.Tensor, arm: torch.Tensor, normal: torch.Tensor,
                    angular_velocity: torch.Tensor, mass: torch.Tensor, inv_inertia_w: torch.Tensor,
                    tau: float, lines: torch.Tensor | None = None) -> torch.Tensor:
    """Normal forces (B, N, M) of each body's static contact set with the roll of a line contact
    held (the module docstring).

    Args:
        fn: (B, N, M) normal forces of the set's M contacts; weight: (B, N, M) their depth weights.
        arm, normal: (B, N, M, 3) lever arms and normals; angular_velocity: (B, N, 3).
        mass: (N,); inv_inertia_w: (B, N, 3, 3); tau: ``roll_stop_time`` (s).
        lines: (N,) bool, the bodies whose sets the stick holds (None: all); box bodies meet
            statics with their exact corners and go without it (``dejaview.sim.box_edges``).
    Returns:
        (B, N, M) ``max(fn + g, 0)``: fn where the set is not elongated (or has fewer than two
        touching contacts).
    """
    w = weight.unsqueeze(-1)
    centre = (w * arm).sum(-2, keepdim=True)  # (B, N, 1, 3)
    mean_n = (w * normal).sum(-2, keepdim=True)
    z = mean_n / torch.sqrt((mean_n * mean_n).sum(-1, keepdim=True) + TINY)  # (B, N, 1, 3)
    d = arm - centre
    p = d - (d * z).sum(-1, keepdim=True) * z  # in the set's mean plane
    second = (w.unsqueeze(-1) * p.unsqueeze(-1) * p.unsqueeze(-2)).sum(-3)  # (B, N, 3, 3)
    trace = second.diagonal(dim1=-2, dim2=-1).sum(-1)  # l1 + l2, (B, N)
    spread = torch.sqrt(torch.relu(2.0 * (second * second).sum((-2, -1)) - trace * trace) + TINY)  # l1 - l2
    # relu(1 - a l2 / l1) with l2 / l1 = (T - D) / (T + D)
    gate = torch.relu((trace + spread - LINE_ASPECT * (trace - spread)) / (trace + spread + TINY))
    gate = torch.where(trace > LINE_MIN_SPREAD, gate, torch.zeros_like(gate))
    if lines is not None:
        gate = torch.where(lines, gate, torch.zeros_like(gate))
    on = gate > 0
    safe = torch.where(on, spread, torch.ones_like(spread)).unsqueeze(-1).unsqueeze(-1)
    zz = z.squeeze(-2)
    plane = torch.eye(3, dtype=fn.dtype, device=fn.device) - zz.unsqueeze(-1) * zz.unsqueeze(-2)
    # a a^T of the roll axis a = z x e (e the major axis): (P - (2 S - T P) / D) / 2
    roll = 0.5 * (1.0 + trace.unsqueeze(-1).unsqueeze(-1) / safe) * plane - second / safe
    spin = small_matmul(roll, angular_velocity.unsqueeze(-1)).squeeze(-1)  # (B, N, 3)
    q = torch.linalg.cross(arm, normal, dim=-1)
    u = (spin.unsqueeze(-2) * q).sum(-1)  # (B, N, M): (spin x r_i) . n_i
    rel = u - (weight * u).sum(-1, keepdim=True)
    inv_mn = (1.0 / mass)[None, :, None] + (q * small_matmul(q, inv_inertia_w.transpose(-1, -2))).sum(-1)
    g = -(gate.unsqueeze(-1) * weight * rel) / (inv_mn * tau)
    return torch.relu(fn + g)
