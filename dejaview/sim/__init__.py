"""Differentiable rigid-body simulation with sphere-packing contacts.

``World`` (static, built once), ``State`` (batched, immutable), ``step`` and
``rollout``. See ``dejaview.sim.contacts`` for the contact model,
``dejaview.sim.integrate`` for the integrator and ``dejaview.sim.native`` for
the same model in C++ (``rollout(..., engine="native")``).
"""

from dejaview.sim.integrate import Trajectory, rollout, step
from dejaview.sim.state import State
from dejaview.sim.world import BodySpec, StaticShape, World

__all__ = ["BodySpec", "State", "StaticShape", "Trajectory", "World", "rollout", "step"]
