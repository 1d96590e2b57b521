"""How a contact turns from loading to unloading: the restitution of the hysteretic contact.

The contact is stiffer while loading (k) than while unloading (phi k), so it returns the
fraction phi of the energy it stored (``dejaview.sim.contacts``). Between the two it blends by how
much it is loading,

    s = sigmoid(-(v_n + beta L) / (v_s + L)),   L = w omega_0 delta                  (``loading``)

(v_n the normal velocity, negative approaching; delta the depth; w = ``UNLOAD_WIDTH``, beta =
``UNLOAD_LEAD``): at rest over a few mm/s (v_s), in an impact over a fixed part of its phase (in a
harmonic impact v_n / (omega_0 delta) is the cotangent of the phase, zero at the deepest point),
centred beta w radians before the deepest point.

Why the phase: with v_s alone (until 2026-12-07) an impact's normal velocity, changing by hundreds
of mm/s per substep near the deepest point, crossed the blend within one substep, and the energy
the contact kept depended on where in its substep the deepest point fell. Restitution was a
sawtooth in the start: one ball thrown at the floor at 2.6 m/s with e = 0.4, its start moved over
2 mm, rebounded with 0.364-0.421, and tracked bounces' fits and their inferred restitution were
rough (issue 58's identify calibration). Over a part of the phase the same ball rebounds with
0.368-0.372 (docs/physics.md, "Restitution", has the table). The lead lowers what a contact without
restitution (phi = 0) returns, but does not stop it: at v_n = 0 the blend is still sigmoid(-beta),
so phi = 0 rebounds with 0.111 in the calibration below (v_s = 0; 0.121 in the engines at 3 m/s
without gravity, 0.09 with it at 1-5 m/s). Below that, phi goes
negative, down to ``UNLOAD_MIN``: the factor phi + (1 - phi) s then crosses zero while the contact
unloads, and the force is cut off there (``dejaview.sim.contacts.normal_force``: it never pulls),
before the blend gives the energy back. ``World.restitution_to_unloading`` calibrates phi against
this blend and cut-off: every restitution from 0.045 up is reached (docs/physics.md, "Restitution").
"""

from __future__ import annotations

import math

import torch

UNLOAD_WIDTH = 0.05
"""w: an impact's loading-to-unloading blend spans about 4 w radians of its phase (``loading``)."""

UNLOAD_LEAD = 2.0
"""beta: the blend is centred beta w radians before an impact's deepest point (``loading``)."""

UNLOAD_MIN = -0.05
"""The least unloading factor phi (the restitution's floor: 0.045 without gravity at omega_0 h =
0.25). Below it the contact's rest suffers: at rest (v_n = 0, depth delta) the blend is
sigmoid(-beta L / (v_s + L)), below 0.5, and the factor phi + (1 - phi) s tends to
phi + (1 - phi) sigmoid(-beta) as the depth grows: zero at phi = -0.135, where a resting body
sinks through the floor (measured: at phi = -0.14 a box sinks, at -0.2 a ball falls through).
At -0.05 a ball rests 0.60 mm deep at omega_0 = 250 rad/s (0.49 mm at phi = 0)."""


def loading(depth: torch.Tensor, normal_velocity: torch.Tensor, unload_velocity: float,
            omega: float) -> torch.Tensor:
    """How much each contact is loading, s in (0, 1) (module docstring).

    Args:
        depth: (B, C) penetration depths (>= 0); normal_velocity: (B, C) (negative approaching).
        unload_velocity: v_s (m/s); omega: the contact frequency omega_0 (rad/s).
    Returns:
        (B, C) loading fractions.
    """
    lead = (UNLOAD_WIDTH * omega) * depth
    return torch.sigmoid(-(normal_velocity + UNLOAD_LEAD * lead) / (unload_velocity + lead))


def loading_of(depth: float, normal_velocity: float, unload_velocity: float, omega: float) -> float:
    """``loading`` for one contact in Python floats (the restitution's calibration integrates one
    contact step by step, ``dejaview.sim.world.restitution_to_unloading``): the same formula, 0 where
    the sigmoid's argument is beyond 700 (exp would overflow) and at zero depth with v_s = 0."""
    lead = (UNLOAD_WIDTH * omega) * depth
    spread = unload_velocity + lead
    if spread <= 0.0:
        return 0.0
    arg = (normal_velocity + UNLOAD_LEAD * lead) / spread
    return 1.0 / (1.0 + math.exp(arg)) if arg < 700.0 else 0.0
